//! Route profiles: who is walking, and so which cells they may use and what
//! each costs them. A profile reads the cell attributes of the site map
//! ([`Tile`]: stairs, elevator, door, narrow).

use crate::site::{Cell, ConnectorKind, Site, Tile};

/// A walker's needs. `Default` walks anywhere walkable, by length.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Profile {
    #[default]
    Default,
    /// Never on stairs.
    Wheelchair,
    /// Avoids narrow passages and doors, and prefers straight walks
    /// (see [`Profile::turn_cost`]).
    LowVision,
}

/// The profile names a request may use, in the order they are listed in errors.
pub(crate) const PROFILE_NAMES: [&str; 3] = ["default", "wheelchair", "low-vision"];

impl Profile {
    /// Every profile, in the order of [`PROFILE_NAMES`] (and of the enum, so
    /// `profile as usize` indexes it).
    pub(crate) const ALL: [Profile; 3] =
        [Profile::Default, Profile::Wheelchair, Profile::LowVision];

    /// The profile called `name`, or `None` for a name not in [`PROFILE_NAMES`].
    pub fn parse(name: &str) -> Option<Profile> {
        match name {
            "default" => Some(Profile::Default),
            "wheelchair" => Some(Profile::Wheelchair),
            "low-vision" => Some(Profile::LowVision),
            _ => None,
        }
    }

    pub(crate) fn name(self) -> &'static str {
        match self {
            Profile::Default => "default",
            Profile::Wheelchair => "wheelchair",
            Profile::LowVision => "low-vision",
        }
    }

    /// Whether this walker may stand on `cell` at all.
    pub(crate) fn passable(self, site: &Site, cell: Cell) -> bool {
        match site.tile(cell) {
            None | Some(Tile::Blocked) => false,
            Some(Tile::Stairs) => self != Profile::Wheelchair,
            Some(_) => true,
        }
    }

    /// Factor (≥ 1, so the search heuristic stays admissible) on the cost of
    /// entering `cell`.
    pub(crate) fn cell_cost(self, site: &Site, cell: Cell) -> f64 {
        match (self, site.tile(cell)) {
            (Profile::LowVision, Some(Tile::Narrow)) => 4.0,
            (Profile::LowVision, Some(Tile::Door)) => 1.5,
            _ => 1.0,
        }
    }

    /// Whether some cell or turn costs this walker more than its length
    /// ([`Profile::cell_cost`], [`Profile::turn_cost`]).
    pub fn has_costs(self) -> bool {
        match self {
            Profile::LowVision => true,
            Profile::Default | Profile::Wheelchair => false,
        }
    }

    /// Typical walking speed, m/s, for the arrival times guidance gives:
    /// 1.2 m/s is a common indoor pedestrian design speed; wheelchair users
    /// and people walking with a cane or a guide dog indoors are often slower.
    pub(crate) fn walking_speed_mps(self) -> f64 {
        match self {
            Profile::Default => 1.2,
            Profile::Wheelchair => 1.0,
            Profile::LowVision => 0.9,
        }
    }

    /// The factor on a connector's time for this walker, or `None` when they
    /// may not use it. A wheelchair takes only step-free connectors (lifts,
    /// ramps): never stairs, nor an escalator, whose steps a wheelchair
    /// cannot board. A low-vision walker may take any, but would rather ride
    /// a lift or walk a ramp than step onto a moving escalator (1.5×) or
    /// climb stairs feeling for each step's edge (2×), so the planner sends
    /// them to those only when the lift costs more than that.
    pub fn connector_factor(self, kind: ConnectorKind) -> Option<f64> {
        match (self, kind) {
            (Profile::Wheelchair, kind) => kind.step_free().then_some(1.0),
            (Profile::LowVision, ConnectorKind::Stairs) => Some(2.0),
            (Profile::LowVision, ConnectorKind::Escalator) => Some(1.5),
            _ => Some(1.0),
        }
    }

    /// Extra cost of changing direction (in cell lengths): a low-vision walker
    /// would rather walk a little further than turn often, since every turn is
    /// one more instruction to follow without seeing the next landmark.
    pub(crate) fn turn_cost(self) -> f64 {
        match self {
            Profile::LowVision => 2.0,
            _ => 0.0,
        }
    }
}

/// Error text naming the known profiles, for `unknown_profile` replies.
pub fn unknown_profile_message(name: &str) -> String {
    format!(
        "profile `{name}` is not supported; known profiles: {}",
        PROFILE_NAMES
            .iter()
            .map(|p| format!("`{p}`"))
            .collect::<Vec<_>>()
            .join(", ")
    )
}
