//! Planning: a walkable route from a device's cell to a destination.
//!
//! Owns what a route is ([`Route`]), how a destination is named ([`Destination`]),
//! the ways a request can fail ([`PlanError`], each with a stable code for MQTT
//! error replies) and the planners behind [`Planner`]. Every planner answers with
//! a route that [`Route::validate`] accepts, or an error: never an invalid route.

pub mod astar;
mod route;

use serde::{Deserialize, Serialize};

pub use route::{Route, Waypoint};

use crate::site::{Cell, Site};

/// Where a request wants to go: a named place or a cell.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Destination {
    Place(String),
    Cell([i64; 2]),
}

/// Why no route was returned.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PlanError {
    #[error("unknown place `{name}`; the site's places are: {known}")]
    UnknownPlace { name: String, known: String },
    #[error("cell [{x}, {y}] is off the {width}×{height} map")]
    OffMap {
        x: i64,
        y: i64,
        width: u16,
        height: u16,
    },
    #[error("cell {0} is blocked (not public access)")]
    Blocked(Cell),
    #[error("no walkable route from {from} to {to}")]
    Unreachable { from: Cell, to: Cell },
}

impl PlanError {
    /// Stable machine-readable code, as sent in MQTT error replies.
    pub fn code(&self) -> &'static str {
        match self {
            PlanError::UnknownPlace { .. } => "unknown_place",
            PlanError::OffMap { .. } => "off_map",
            PlanError::Blocked(_) => "blocked_cell",
            PlanError::Unreachable { .. } => "unreachable",
        }
    }
}

impl Destination {
    /// The walkable cell this destination names on `site`.
    pub fn resolve(&self, site: &Site) -> Result<Cell, PlanError> {
        let cell = match self {
            Destination::Place(name) => {
                site.place(name).ok_or_else(|| PlanError::UnknownPlace {
                    name: name.clone(),
                    known: site
                        .places()
                        .keys()
                        .map(|k| format!("`{k}`"))
                        .collect::<Vec<_>>()
                        .join(", "),
                })?
            }
            &Destination::Cell([x, y]) => {
                let off_map = PlanError::OffMap {
                    x,
                    y,
                    width: site.width(),
                    height: site.height(),
                };
                let cell = match (u16::try_from(x), u16::try_from(y)) {
                    (Ok(x), Ok(y)) => Cell::new(x, y),
                    _ => return Err(off_map),
                };
                if !site.contains(cell) {
                    return Err(off_map);
                }
                cell
            }
        };
        if site.walkable(cell) {
            Ok(cell)
        } else {
            Err(PlanError::Blocked(cell))
        }
    }
}

/// Which moves a route may make between neighbouring cells.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Connectivity {
    /// Up, down, left, right.
    Four,
    /// Also diagonals, but never across the corner of a blocked cell.
    #[default]
    Eight,
}

impl Connectivity {
    /// Whether a single step from `a` to `b` is allowed on `site`.
    pub fn step_ok(self, site: &Site, a: Cell, b: Cell) -> bool {
        let (dx, dy) = (a.x.abs_diff(b.x), a.y.abs_diff(b.y));
        if !site.walkable(b) || dx > 1 || dy > 1 || (dx == 0 && dy == 0) {
            return false;
        }
        match (dx, dy) {
            (1, 1) => {
                self == Connectivity::Eight
                    && site.walkable(Cell::new(a.x, b.y))
                    && site.walkable(Cell::new(b.x, a.y))
            }
            _ => true,
        }
    }
}

/// `[planner]` in the gateway config.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlannerConfig {
    /// Which planner serves requests. Only `astar` exists so far.
    #[serde(default)]
    pub mode: PlannerMode,
    #[serde(default)]
    pub connectivity: Connectivity,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PlannerMode {
    /// Shortest walkable path.
    #[default]
    Astar,
}

/// Something that answers route requests on a site.
pub trait Planner: Send + Sync {
    /// The mode name reported with every route.
    fn mode(&self) -> &'static str;
    fn plan(&self, from: Cell, to: Cell) -> Result<Route, PlanError>;
}

/// Builds the configured planner for `site`.
pub fn build(config: &PlannerConfig, site: std::sync::Arc<Site>) -> Box<dyn Planner> {
    match config.mode {
        PlannerMode::Astar => Box::new(astar::AStar::new(site, config.connectivity)),
    }
}
