//! A route across floors as published: one leg per floor, each the route
//! body a one-floor reply carries (`plan::floors` plans them), the
//! connectors taken between them, and the instructions of the whole way.

use serde::Serialize;

use super::RouteBody;
use crate::plan::floors::{BuildingPlanner, FloorCell, FloorsRoute};
use crate::plan::instructions::Instruction;
use crate::plan::{Planner, Profile};
use crate::site::{Building, Cell};

/// A cell and the floor it is on.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FloorPosition {
    pub floor: String,
    pub level: i32,
    pub cell: Cell,
}

impl FloorPosition {
    fn of(building: &Building, at: FloorCell) -> FloorPosition {
        let floor = &building.floors()[at.floor];
        FloorPosition {
            floor: floor.name.clone(),
            level: floor.level,
            cell: at.cell,
        }
    }
}

/// One floor's leg: the floor, and its route as a one-floor reply has it
/// (its `instructions` are the leg's part of the whole way's).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct LegBody {
    pub floor: String,
    pub level: i32,
    #[serde(flatten)]
    pub route: RouteBody,
}

/// A connector taken between two legs.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ConnectorBody {
    pub id: String,
    /// `stairs`, `lift`, `escalator` or `ramp`.
    pub kind: &'static str,
    pub from: FloorPosition,
    pub to: FloorPosition,
    pub seconds: f64,
}

/// One spoken step and the floor it is on.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FloorInstruction {
    pub floor: String,
    pub level: i32,
    #[serde(flatten)]
    pub instruction: Instruction,
}

/// The published form of a route across floors.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FloorsRouteBody {
    pub from: FloorPosition,
    pub to: FloorPosition,
    pub profile: &'static str,
    /// In walking order; `legs[i]` ends where `connectors[i]` is boarded.
    pub legs: Vec<LegBody>,
    pub connectors: Vec<ConnectorBody>,
    /// Every leg's instructions in order, with the connectors'.
    pub instructions: Vec<FloorInstruction>,
    /// Metres walked over every leg.
    pub length_m: f64,
    /// Walking at the profile's speed plus the connectors' time, seconds.
    pub total_s: f64,
    /// Why a route was sent without a request: `next_floor` for the rest
    /// of a route across floors, planned when the walker came onto the
    /// next floor. Absent on replies.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<&'static str>,
    /// Time from request to route, microseconds.
    pub latency_us: u64,
}

impl FloorsRouteBody {
    /// The published form of `route`, planned by `planner` for `profile`.
    pub fn new(
        planner: &BuildingPlanner,
        profile: Profile,
        route: &FloorsRoute,
        latency_us: u64,
    ) -> FloorsRouteBody {
        let building = planner.building();
        let at = |floor: usize, cell: Cell| FloorPosition::of(building, FloorCell { floor, cell });
        let mut legs = Vec::with_capacity(route.legs.len());
        let mut instructions = Vec::new();
        for (i, leg) in route.legs.iter().enumerate() {
            let floor = &building.floors()[leg.floor];
            let cells = &leg.planned.route.cells;
            let leg_planner: &dyn Planner = planner.floor_planner(leg.floor);
            let mut body = RouteBody::new(
                &floor.site,
                leg_planner,
                profile,
                cells[0],
                cells[cells.len() - 1],
                &leg.planned,
                latency_us,
            );
            body.instructions = route.leg_instructions(building, i, &body.maneuvers);
            instructions.extend(body.instructions.iter().map(|s| FloorInstruction {
                floor: floor.name.clone(),
                level: floor.level,
                instruction: s.clone(),
            }));
            legs.push(LegBody {
                floor: floor.name.clone(),
                level: floor.level,
                route: body,
            });
        }
        let connectors = route
            .rides
            .iter()
            .map(|ride| {
                let connector = &building.connectors()[ride.connector];
                ConnectorBody {
                    id: connector.id.clone(),
                    kind: connector.kind.name(),
                    from: at(ride.from.floor, ride.from.cell),
                    to: at(ride.to.floor, ride.to.cell),
                    seconds: ride.seconds,
                }
            })
            .collect();
        let (first, last) = (&route.legs[0], &route.legs[route.legs.len() - 1]);
        FloorsRouteBody {
            from: at(first.floor, first.planned.route.cells[0]),
            to: at(
                last.floor,
                *last.planned.route.cells.last().expect("a leg has cells"),
            ),
            profile: profile.name(),
            legs,
            connectors,
            instructions,
            length_m: route.length_m(),
            total_s: route.total_s,
            reason: None,
            latency_us,
        }
    }

    /// The same route sent for `reason` instead of a request.
    pub fn with_reason(mut self, reason: &'static str) -> FloorsRouteBody {
        self.reason = Some(reason);
        self
    }
}
