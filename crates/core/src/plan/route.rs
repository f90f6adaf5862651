//! What a planner returns, and the check every returned route must pass.

use serde::Serialize;

use super::{Connectivity, Profile};
use crate::site::{Cell, Site};

/// An ordered walk from the first cell to the last.
#[derive(Clone, Debug, PartialEq)]
pub struct Route {
    pub cells: Vec<Cell>,
}

/// One step of a route as published: the cell and its centre in metres.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Waypoint {
    pub cell: Cell,
    pub x_m: f64,
    pub y_m: f64,
}

impl Route {
    /// Length in metres along cell centres.
    pub fn length_m(&self, site: &Site) -> f64 {
        self.cells
            .windows(2)
            .map(|w| w[0].distance(w[1]))
            .sum::<f64>()
            * site.cell_m
    }

    pub(crate) fn waypoints(&self, site: &Site) -> Vec<Waypoint> {
        self.cells
            .iter()
            .map(|&cell| {
                let (x_m, y_m) = site.metres(cell);
                Waypoint { cell, x_m, y_m }
            })
            .collect()
    }

    /// Checks that the route is walkable from `from` to `to`: exact endpoints,
    /// every cell walkable, every step allowed by `connectivity`, no cell twice.
    pub fn validate(
        &self,
        site: &Site,
        from: Cell,
        to: Cell,
        connectivity: Connectivity,
    ) -> Result<(), String> {
        self.validate_for(site, from, to, connectivity, Profile::Default)
    }

    /// [`Route::validate`] for a walker with `profile`: also no cell the
    /// profile may not use (stairs in a wheelchair), nor a diagonal past one.
    pub fn validate_for(
        &self,
        site: &Site,
        from: Cell,
        to: Cell,
        connectivity: Connectivity,
        profile: Profile,
    ) -> Result<(), String> {
        let (Some(&first), Some(&last)) = (self.cells.first(), self.cells.last()) else {
            return Err("the route is empty".into());
        };
        if first != from || last != to {
            return Err(format!(
                "the route runs {first} → {last}, not {from} → {to}"
            ));
        }
        if let Some(c) = self.cells.iter().find(|&&c| !site.walkable(c)) {
            return Err(format!("the route crosses {c}, which is not walkable"));
        }
        if let Some(c) = self.cells.iter().find(|&&c| !profile.passable(site, c)) {
            return Err(format!(
                "the route crosses {c}, which the {} profile may not use",
                profile.name()
            ));
        }
        if let Some(w) = self
            .cells
            .windows(2)
            .find(|w| !connectivity.step_ok_by(w[0], w[1], |c| profile.passable(site, c)))
        {
            return Err(format!("the step {} → {} is not allowed", w[0], w[1]));
        }
        let mut seen = std::collections::HashSet::with_capacity(self.cells.len());
        if let Some(c) = self.cells.iter().find(|&&c| !seen.insert(c)) {
            return Err(format!("the route visits {c} twice"));
        }
        Ok(())
    }
}
