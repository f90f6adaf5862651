//! Routes across the floors of a building: a leg per floor, planned by that
//! floor's own planner, joined by the connectors (stairs, lifts, escalators,
//! ramps) the walker's profile may use.
//!
//! **Which connectors.** [`Profile::connector_factor`]: a wheelchair only
//! step-free ones (lifts, ramps), never stairs nor an escalator; a
//! low-vision walker any, an escalator costing 1.5× its time and stairs 2×,
//! so they are sent to a lift unless it is much further; everyone else any,
//! at its time.
//!
//! **What a route costs** is time: walking on the floors at the profile's
//! walking speed (`Profile::walking_speed_mps`, the speed guidance gives
//! arrival times with: 1.2 m/s, 1.0 in a wheelchair, 0.9 with low vision)
//! plus each connector's [`Connector::seconds`] (its wait and its time per
//! level) times the profile's factor.
//!
//! **How it is searched.** The connectors' stops are the nodes of a small
//! graph. When the planner is built, one Dijkstra flood per stop and profile
//! gives the walk from every cell of the stop's floor to it (metres, the
//! profile's cell costs, each step costing its length times the lower
//! factor of its two cells, so the walk to a stop and from it cost the same
//! and one flood serves both, and A* never finds a walk cheaper: the flood
//! is also the heuristic that guides the search of a leg to or from the
//! stop). A request then costs no flood: the walks from its
//! start to the stops of its floor and from the stops of the destination's
//! floor to it are read off the floods, Dijkstra runs over the stops
//! (tens of nodes, microseconds), and only the legs of the chosen way are
//! planned, each by its floor's planner, which a one-floor request would
//! get. Flooding from the request's two ends instead would cost two floods
//! of a whole floor per request (40,000 cells on a mall floor at 1 m), more
//! than the legs themselves; the floods per stop cost memory instead (4
//! bytes per cell per stop and profile: 20 stops on 40,000-cell floors, 9.6
//! MB for the three profiles) and a start-up of one flood each.
//!
//! A request on one floor is planned on that floor alone; only when the
//! floor does not join its two cells (a floor in two parts joined through
//! another) does it go through the connectors.
//!
//! **No route for the profile.** When the walker needs step-free routes and
//! none exists, the error is `no_step_free_route`, saying which stairs or
//! escalators the only routes take (or that stairs within a floor are in the
//! way); it is never a route over steps. Otherwise, `unreachable`.
//!
//! **Later, the pipeline.** A request names a floor and a cell (or a place,
//! found on its floor by [`BuildingPlanner::resolve`]) at both ends; the
//! pipeline, holding the building's planner instead of one floor's, calls
//! [`BuildingPlanner::plan`] with the device's floor and cell, and publishes
//! the legs as it publishes one route today.

use std::cmp::Reverse;
use std::collections::BinaryHeap;
use std::sync::Arc;

use super::astar::{self, NEIGHBOURS};
use super::instructions::{
    Instruction, Maneuver, arrived_sentence, connector_noun, instructions_towards, leave_sentence,
    ride_sentence,
};
use super::{Connectivity, Destination, PlanError, Planned, Planner, Profile, ServedLine};
use crate::site::{Building, Cell, ConnectorKind, Site, Stop};

/// A cell on one floor of a building.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FloorCell {
    /// Index into [`Building::floors`].
    pub floor: usize,
    pub cell: Cell,
}

/// One floor's part of a route across floors.
#[derive(Clone, Debug)]
pub struct Leg {
    /// Index into [`Building::floors`].
    pub floor: usize,
    /// The floor planner's answer, validated for the profile.
    pub planned: Planned,
    /// Metres along the line the walker is given ([`ServedLine`]).
    pub length_m: f64,
}

/// A connector taken between two legs.
#[derive(Clone, Debug, PartialEq)]
pub struct Ride {
    /// Index into [`Building::connectors`].
    pub connector: usize,
    pub from: Stop,
    pub to: Stop,
    /// The connector's time ([`crate::site::Connector::seconds`]).
    pub seconds: f64,
}

/// A route across floors: `legs[i]` ends where `rides[i]` is boarded, and
/// `legs[i + 1]` starts where it is left.
#[derive(Clone, Debug)]
pub struct FloorsRoute {
    pub legs: Vec<Leg>,
    pub rides: Vec<Ride>,
    /// The legs' walking time at the profile's speed plus the rides'.
    pub total_s: f64,
}

impl FloorsRoute {
    /// Metres walked, over every leg.
    pub fn length_m(&self) -> f64 {
        self.legs.iter().map(|l| l.length_m).sum()
    }

    /// The instructions of leg `i` from its `maneuvers` (as its reply
    /// builds them): after a ride, "Leave the lift on F3." first; then the
    /// floor's turns; before a ride, the walk "to the lift" instead of an
    /// arrival, and "Take the lift to F3.".
    pub fn leg_instructions(
        &self,
        building: &Building,
        i: usize,
        maneuvers: &[Maneuver],
    ) -> Vec<Instruction> {
        let leg = &self.legs[i];
        let site = &building.floors()[leg.floor].site;
        let cells = &leg.planned.route.cells;
        let (first, last) = (cells[0], cells[cells.len() - 1]);
        let said = |text: String, at: Cell| Instruction {
            text,
            distance_m: 0.0,
            at,
        };
        let kind = |ride: &Ride| building.connectors()[ride.connector].kind;
        let mut out = Vec::new();
        if let Some(ride) = i.checked_sub(1).map(|j| &self.rides[j]) {
            out.push(said(
                leave_sentence(kind(ride), &building.floors()[leg.floor].name),
                first,
            ));
        }
        let onward = self.rides.get(i);
        let towards = onward.map(|ride| connector_noun(kind(ride)));
        out.extend(instructions_towards(
            site,
            &leg.planned.route,
            maneuvers,
            towards.as_deref(),
        ));
        match onward {
            Some(ride) => {
                let floors = building.floors();
                let levels = floors[ride.to.floor].level - floors[ride.from.floor].level;
                out.push(said(
                    ride_sentence(kind(ride), levels, &floors[ride.to.floor].name),
                    last,
                ));
            }
            None if cells.len() == 1 => out.push(said(arrived_sentence(site, last), last)),
            None => {}
        }
        out
    }
}

/// The stops of the building's connectors, and for each profile the walk
/// from every cell of a stop's floor to it (see the module doc).
pub struct BuildingPlanner {
    building: Arc<Building>,
    connectivity: Connectivity,
    /// One per floor, in [`Building::floors`]' order.
    floors: Vec<Box<dyn Planner>>,
    stops: Vec<StopNode>,
    /// `walks[profile as usize][stop]`: metres from each open cell of the
    /// stop's floor (by [`Site::open_index`]) to the stop; `None` where the
    /// profile may not stand on the stop.
    walks: [Vec<Option<Vec<f32>>>; 3],
}

/// A connector's stop as a node of the search.
struct StopNode {
    connector: usize,
    stop: Stop,
}

/// The stop at one end of a leg, whose flood can guide its search.
#[derive(Clone, Copy)]
enum Guide {
    None,
    /// The leg ends at this stop.
    To(usize),
    /// The leg starts at this stop.
    From(usize),
}

/// How the search reached a stop.
#[derive(Clone, Copy)]
enum Via {
    /// Walked from the request's start.
    Start,
    /// Walked on the same floor from another stop.
    Walk(usize),
    /// Ridden from another stop of the same connector.
    Ride(usize),
}

impl BuildingPlanner {
    /// The planner of `building` whose legs `floors` plan (one per floor, in
    /// order), its routes moving as `connectivity` allows. Floods every stop
    /// for every profile.
    pub fn new(
        building: Arc<Building>,
        connectivity: Connectivity,
        floors: Vec<Box<dyn Planner>>,
    ) -> BuildingPlanner {
        assert_eq!(
            floors.len(),
            building.floors().len(),
            "one planner per floor"
        );
        let stops: Vec<StopNode> = building
            .connectors()
            .iter()
            .enumerate()
            .flat_map(|(connector, c)| {
                c.stops
                    .iter()
                    .map(move |&stop| StopNode { connector, stop })
            })
            .collect();
        let walks = Profile::ALL.map(|profile| {
            stops
                .iter()
                .map(|node| {
                    let site = &building.floors()[node.stop.floor].site;
                    profile
                        .passable(site, node.stop.cell)
                        .then(|| flood(site, connectivity, profile, node.stop.cell))
                })
                .collect()
        });
        BuildingPlanner {
            building,
            connectivity,
            floors,
            stops,
            walks,
        }
    }

    pub fn building(&self) -> &Building {
        &self.building
    }

    /// The planner of floor `floor`'s legs.
    pub fn floor_planner(&self, floor: usize) -> &dyn Planner {
        &*self.floors[floor]
    }

    /// The cell `destination` names on the floor called `floor`; without a
    /// floor, a place is looked for on every floor (and must be on one
    /// only), and a cell is on the only floor of a one-floor building.
    pub fn resolve(
        &self,
        floor: Option<&str>,
        destination: &Destination,
    ) -> Result<FloorCell, PlanError> {
        let floors = self.building.floors();
        let floor_list = || {
            floors
                .iter()
                .map(|f| format!("`{}`", f.name))
                .collect::<Vec<_>>()
                .join(", ")
        };
        let on = |floor: usize| {
            destination
                .resolve(&floors[floor].site)
                .map(|cell| FloorCell { floor, cell })
        };
        if let Some(name) = floor {
            let floor = self
                .building
                .floor_named(name)
                .ok_or_else(|| PlanError::UnknownFloor {
                    name: name.to_owned(),
                    known: floor_list(),
                })?;
            return on(floor);
        }
        if floors.len() == 1 {
            return on(0);
        }
        let Destination::Place(place) = destination else {
            return Err(PlanError::FloorUnclear(format!(
                "a cell needs its floor on a building of several floors (`F1:x,y`); the floors \
                 are: {}",
                floor_list()
            )));
        };
        let holding: Vec<usize> = (0..floors.len())
            .filter(|&f| floors[f].site.place(place).is_some())
            .collect();
        match holding[..] {
            [floor] => on(floor),
            [] => Err(PlanError::FloorUnclear(format!(
                "no floor has a place `{place}`; name the floor (`F1:{place}`) to hear its places"
            ))),
            _ => Err(PlanError::FloorUnclear(format!(
                "place `{place}` is on several floors ({}); name the floor (`{}:{place}`)",
                holding
                    .iter()
                    .map(|&f| format!("`{}`", floors[f].name))
                    .collect::<Vec<_>>()
                    .join(", "),
                floors[holding[0]].name
            ))),
        }
    }

    /// The quickest route from `from` to `to` for `profile` over the
    /// connectors it may use, every leg validated (see the module doc).
    pub fn plan(
        &self,
        from: FloorCell,
        to: FloorCell,
        profile: Profile,
    ) -> Result<FloorsRoute, PlanError> {
        for end in [from, to] {
            let site = &self.building.floors()[end.floor].site;
            if !(site.walkable(end.cell) && profile.passable(site, end.cell)) {
                return Err(PlanError::Blocked(end.cell));
            }
        }
        if from.floor == to.floor {
            match self.leg(from.floor, from.cell, to.cell, profile) {
                Err(PlanError::Unreachable { .. }) => {}
                found => return found.map(|leg| self.route(vec![leg], Vec::new(), profile)),
            }
        }
        let way = self
            .search(from, to, profile, |kind| profile.connector_factor(kind))
            .ok_or_else(|| self.no_route(from, to, profile))?;
        // The legs: from the start to the first stop boarded, between the
        // stop left and the next boarded, and from the last left to the end.
        let mut legs = Vec::new();
        let mut rides = Vec::new();
        let mut here = from;
        let mut left_stop = None;
        for (boarded, left) in way {
            let (a, b) = (self.stops[boarded].stop, self.stops[left].stop);
            let guide = Guide::To(boarded);
            legs.push(self.guided_leg(here.floor, here.cell, a.cell, profile, guide)?);
            let connector = self.stops[boarded].connector;
            rides.push(Ride {
                connector,
                from: a,
                to: b,
                seconds: self.building.connectors()[connector].seconds(&self.building, a, b),
            });
            here = FloorCell {
                floor: b.floor,
                cell: b.cell,
            };
            left_stop = Some(left);
        }
        let guide = left_stop.map_or(Guide::None, Guide::From);
        legs.push(self.guided_leg(here.floor, here.cell, to.cell, profile, guide)?);
        Ok(self.route(legs, rides, profile))
    }

    fn route(&self, legs: Vec<Leg>, rides: Vec<Ride>, profile: Profile) -> FloorsRoute {
        let walked: f64 = legs.iter().map(|l| l.length_m).sum();
        let ridden: f64 = rides.iter().map(|r| r.seconds).sum();
        FloorsRoute {
            total_s: walked / profile.walking_speed_mps() + ridden,
            legs,
            rides,
        }
    }

    /// Floor `floor`'s planner's route from `a` to `b`, validated.
    fn leg(&self, floor: usize, a: Cell, b: Cell, profile: Profile) -> Result<Leg, PlanError> {
        self.guided_leg(floor, a, b, profile, Guide::None)
    }

    /// [`BuildingPlanner::leg`] where one end is a stop: a floor planned by
    /// A* is searched with the stop's flood as its heuristic (exact for a
    /// walker without cell or turn costs), from the other end towards the
    /// stop (a leg leaving a stop is searched back from its end and
    /// reversed, equally cheap for such a walker). Searched plainly, the
    /// leg from a shop to a lift on a mall floor of 40,000 cells expands most
    /// of the floor; guided, little more than the route.
    fn guided_leg(
        &self,
        floor: usize,
        a: Cell,
        b: Cell,
        profile: Profile,
        guide: Guide,
    ) -> Result<Leg, PlanError> {
        let site = &self.building.floors()[floor].site;
        let planner = &self.floors[floor];
        let flood = |stop: usize| self.walks[profile as usize][stop].as_deref();
        let searched = planner.mode() == super::PlannerMode::Astar.name();
        let planned = match guide {
            Guide::To(stop) if searched && let Some(m) = flood(stop) => Planned::searched(
                astar::guided_search(site, self.connectivity, [a, b], profile, m)?,
            ),
            Guide::From(stop) if searched && let Some(m) = flood(stop) => {
                let mut back = astar::guided_search(site, self.connectivity, [b, a], profile, m)?;
                back.cells.reverse();
                Planned::searched(back)
            }
            _ => planner.plan(a, b, profile)?,
        };
        planned
            .route
            .validate_for(site, a, b, self.connectivity, profile)
            .map_err(|reason| PlanError::Invalid { reason })?;
        let length_m = ServedLine::of(site, &planned, profile).length_m(site);
        Ok(Leg {
            floor,
            planned,
            length_m,
        })
    }

    /// Metres of `profile`'s walk between `cell` and stop `stop` on its
    /// floor, or `None` where it has none.
    fn walk(&self, profile: Profile, stop: usize, cell: Cell) -> Option<f64> {
        let site = &self.building.floors()[self.stops[stop].stop.floor].site;
        let metres = self.walks[profile as usize][stop].as_ref()?[site.open_index(cell)?];
        metres.is_finite().then_some(f64::from(metres))
    }

    /// Dijkstra over the stops: the (boarded, left) stops of each connector
    /// on the quickest way from `from` to `to` for `profile`'s walks, riding
    /// connectors at `factor` of their time (`None`: not at all); `None` when
    /// no way joins them.
    fn search(
        &self,
        from: FloorCell,
        to: FloorCell,
        profile: Profile,
        factor: impl Fn(ConnectorKind) -> Option<f64>,
    ) -> Option<Vec<(usize, usize)>> {
        let speed = profile.walking_speed_mps();
        let n = self.stops.len();
        let mut time = vec![f64::INFINITY; n];
        let mut via = vec![Via::Start; n];
        let mut done = vec![false; n];
        for (s, node) in self.stops.iter().enumerate() {
            if node.stop.floor == from.floor
                && let Some(m) = self.walk(profile, s, from.cell)
            {
                time[s] = m / speed;
            }
        }
        let connectors = self.building.connectors();
        let mut best: Option<(f64, usize)> = None;
        while let Some(s) = (0..n)
            .filter(|&s| !done[s] && time[s].is_finite())
            .min_by(|&a, &b| time[a].total_cmp(&time[b]))
        {
            if best.is_some_and(|(t, _)| t <= time[s]) {
                break;
            }
            done[s] = true;
            let here = &self.stops[s];
            if here.stop.floor == to.floor
                && let Some(m) = self.walk(profile, s, to.cell)
                && best.is_none_or(|(t, _)| time[s] + m / speed < t)
            {
                best = Some((time[s] + m / speed, s));
            }
            for (t, there) in self.stops.iter().enumerate() {
                if done[t] {
                    continue;
                }
                let (cost, how) = if there.connector == here.connector {
                    let connector = &connectors[here.connector];
                    let Some(f) = factor(connector.kind) else {
                        continue;
                    };
                    (
                        connector.seconds(&self.building, here.stop, there.stop) * f,
                        Via::Ride(s),
                    )
                } else if there.stop.floor == here.stop.floor {
                    let Some(m) = self.walk(profile, t, here.stop.cell) else {
                        continue;
                    };
                    (m / speed, Via::Walk(s))
                } else {
                    continue;
                };
                if time[s] + cost < time[t] {
                    time[t] = time[s] + cost;
                    via[t] = how;
                }
            }
        }
        let (_, mut at) = best?;
        let mut rides = Vec::new();
        loop {
            match via[at] {
                Via::Start => break,
                Via::Walk(s) => at = s,
                Via::Ride(s) => {
                    rides.push((s, at));
                    at = s;
                }
            }
        }
        rides.reverse();
        Some(rides)
    }

    /// Why no route joins `from` and `to` for `profile`: for a walker who
    /// needs step-free routes, the stairs or escalators the only routes
    /// take (`no_step_free_route`), else `unreachable`.
    fn no_route(&self, from: FloorCell, to: FloorCell, profile: Profile) -> PlanError {
        let name = |at: FloorCell| format!("{} {}", self.building.floors()[at.floor].name, at.cell);
        // Stairs stand for every connector with steps: a walker who may not
        // take them needs step-free routes.
        if profile.connector_factor(ConnectorKind::Stairs).is_none() {
            if let Some(way) = self.search(from, to, profile, |_| Some(1.0)) {
                let connectors = self.building.connectors();
                let taken: Vec<String> = way
                    .iter()
                    .map(|&(boarded, _)| self.stops[boarded].connector)
                    .filter(|&c| profile.connector_factor(connectors[c].kind).is_none())
                    .map(|c| format!("{} `{}`", connectors[c].kind.name(), connectors[c].id))
                    .collect();
                return PlanError::NoStepFreeRoute {
                    from: name(from),
                    to: name(to),
                    why: format!(
                        "the only way between them takes {}, which have steps; a lift or a \
                         ramp joining those floors is missing",
                        taken.join(" and ")
                    ),
                };
            }
            if self
                .search(from, to, Profile::Default, |_| Some(1.0))
                .is_some()
            {
                return PlanError::NoStepFreeRoute {
                    from: name(from),
                    to: name(to),
                    why: "stairs within a floor are in the way (cells marked `s`)".to_owned(),
                };
            }
        }
        PlanError::NotJoined {
            from: name(from),
            to: name(to),
        }
    }
}

/// Metres of `profile`'s cheapest walk between `from` and every open cell
/// of `site` (by [`Site::open_index`]; infinite where none): Dijkstra, each
/// step costing its length times the lower cost factor of its two cells,
/// so the walk is as dear either way, and never dearer than A* finds it
/// (A* pays the factor of the cell entered, and for turns): a lower bound
/// that guides A* to the stop ([`astar::guided_search`]).
fn flood(site: &Site, connectivity: Connectivity, profile: Profile, from: Cell) -> Vec<f32> {
    let cells = site.open_cells();
    let mut metres = vec![f64::INFINITY; cells.len()];
    let passable = |c: Cell| site.walkable(c) && profile.passable(site, c);
    let start = site.open_index(from).expect("a stop is walkable");
    metres[start] = 0.0;
    // Distances are ≥ 0, so their bits order as they do.
    let mut heap = BinaryHeap::from([Reverse((0f64.to_bits(), start))]);
    while let Some(Reverse((bits, i))) = heap.pop() {
        let d = f64::from_bits(bits);
        if d > metres[i] {
            continue;
        }
        let here = cells[i];
        let cost_here = profile.cell_cost(site, here);
        for (dx, dy) in NEIGHBOURS {
            let (Some(x), Some(y)) = (here.x.checked_add_signed(dx), here.y.checked_add_signed(dy))
            else {
                continue;
            };
            let next = Cell::new(x, y);
            if !connectivity.step_ok_by(here, next, passable) {
                continue;
            }
            let step = if dx != 0 && dy != 0 {
                std::f64::consts::SQRT_2
            } else {
                1.0
            };
            let j = site.open_index(next).expect("step_ok checks walkable");
            let cand = d + step * site.cell_m * cost_here.min(profile.cell_cost(site, next));
            if cand < metres[j] {
                metres[j] = cand;
                heap.push(Reverse((cand.to_bits(), j)));
            }
        }
    }
    metres.into_iter().map(|m| m as f32).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// What A* pays for `cells` as `profile`: each step's length times the
    /// factor of the cell entered, and the turns.
    fn cost(site: &Site, profile: Profile, cells: &[Cell]) -> f64 {
        let heading = |a: Cell, b: Cell| {
            (
                i32::from(b.x) - i32::from(a.x),
                i32::from(b.y) - i32::from(a.y),
            )
        };
        let mut total = 0.0;
        for (i, pair) in cells.windows(2).enumerate() {
            let (dx, dy) = heading(pair[0], pair[1]);
            let step = if dx != 0 && dy != 0 {
                std::f64::consts::SQRT_2
            } else {
                1.0
            };
            total += step * profile.cell_cost(site, pair[1]);
            if i > 0 && heading(cells[i - 1], pair[0]) != (dx, dy) {
                total += profile.turn_cost();
            }
        }
        total
    }

    /// Guided by a stop's flood, A* finds routes to and from the stop as
    /// cheap as the plain search does, for every profile (the flood is a
    /// lower bound of what A* pays, doors, narrow passages and turns
    /// included), and none where the profile has none.
    #[test]
    fn a_search_guided_by_a_stop_s_flood_is_as_cheap_as_a_plain_one() {
        let site = Site::of_map(
            "##########\n\
             #..d....n#\n\
             #.###.##n#\n\
             #...#..#s#\n\
             ###.#.##.#\n\
             #nnn#....#\n\
             ##########",
        );
        let stop = Cell::new(0, 0);
        for profile in Profile::ALL {
            let flood = flood(&site, Connectivity::Eight, profile, stop);
            for &a in site.open_cells() {
                if !profile.passable(&site, a) {
                    continue;
                }
                let plain =
                    astar::profile_search(&site, Connectivity::Eight, a, stop, profile, |_| 1.0);
                let guided =
                    astar::guided_search(&site, Connectivity::Eight, [a, stop], profile, &flood);
                match (plain, guided) {
                    (Ok(plain), Ok(guided)) => {
                        guided
                            .validate_for(&site, a, stop, Connectivity::Eight, profile)
                            .unwrap();
                        let (p, g) = (
                            cost(&site, profile, &plain.cells),
                            cost(&site, profile, &guided.cells),
                        );
                        assert!(
                            (p - g).abs() < 1e-6,
                            "{profile:?} from {a}: {p} plain, {g} guided"
                        );
                        let bound = f64::from(flood[site.open_index(a).unwrap()]) / site.cell_m;
                        assert!(
                            bound <= p + 1e-6,
                            "{profile:?} from {a}: bound {bound} over {p}"
                        );
                    }
                    (Err(_), Err(_)) => {}
                    (plain, guided) => {
                        panic!("{profile:?} from {a}: {plain:?} plain, {guided:?} guided")
                    }
                }
            }
        }
    }
}
