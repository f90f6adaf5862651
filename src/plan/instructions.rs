//! Turn-by-turn instructions for a route, in plain sentences a screen reader
//! can speak: "Walk 12 m, then turn left at help desk."
//!
//! A route is cut where its heading changes by 45° or more. Changes of 45°
//! are "bear left/right", 90° "turn", 135° "turn sharply". A turn within
//! [`PLACE_RADIUS_CELLS`] of a named place is named after it.

use serde::Serialize;

use super::Route;
use crate::site::{Cell, Site};

/// How near (in cells) a named place must be to name a turn after it.
pub const PLACE_RADIUS_CELLS: f64 = 1.5;

/// One spoken step.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Instruction {
    /// The sentence to speak.
    pub text: String,
    /// Walking distance of this step, metres.
    pub distance_m: f64,
    /// Where the step ends (the turn, or the destination).
    pub at: Cell,
}

/// The instructions for `route` on `site`; empty for a route of one cell.
pub fn instructions(site: &Site, route: &Route) -> Vec<Instruction> {
    let cells = &route.cells;
    let mut out = Vec::new();
    let mut walked = 0.0;
    for i in 1..cells.len() {
        walked += cells[i - 1].distance(cells[i]) * site.cell_m;
        let Some(&next) = cells.get(i + 1) else {
            let place = site
                .nearest_place(cells[i], PLACE_RADIUS_CELLS)
                .map(|p| format!(" at {p}"))
                .unwrap_or_default();
            out.push(Instruction {
                text: format!("Walk {}; you have arrived{place}.", metres(walked)),
                distance_m: walked,
                at: cells[i],
            });
            break;
        };
        let Some(turn) = turn(heading(cells[i - 1], cells[i]), heading(cells[i], next)) else {
            continue;
        };
        let place = site
            .nearest_place(cells[i], PLACE_RADIUS_CELLS)
            .map(|p| format!(" at {p}"))
            .unwrap_or_default();
        out.push(Instruction {
            text: format!("Walk {}, then {turn}{place}.", metres(walked)),
            distance_m: walked,
            at: cells[i],
        });
        walked = 0.0;
    }
    out
}

/// Heading of a step in eighths of a turn, 0 = east, clockwise on the map
/// (rows grow downwards).
fn heading(a: Cell, b: Cell) -> i32 {
    let dx = i32::from(b.x) - i32::from(a.x);
    let dy = i32::from(b.y) - i32::from(a.y);
    match (dx.signum(), dy.signum()) {
        (1, 0) => 0,
        (1, 1) => 1,
        (0, 1) => 2,
        (-1, 1) => 3,
        (-1, 0) => 4,
        (-1, -1) => 5,
        (0, -1) => 6,
        _ => 7,
    }
}

/// The words for going from heading `a` to `b`, or `None` when straight on.
fn turn(a: i32, b: i32) -> Option<&'static str> {
    // Clockwise change in eighths, −3..=4; clockwise is to the right.
    let d = (b - a).rem_euclid(8);
    let d = if d > 4 { d - 8 } else { d };
    Some(match d {
        0 => return None,
        1 => "bear right",
        -1 => "bear left",
        2 => "turn right",
        -2 => "turn left",
        3 => "turn sharply right",
        -3 => "turn sharply left",
        _ => "turn around",
    })
}

/// A distance as spoken: whole metres, at least 1.
fn metres(m: f64) -> String {
    let m = m.round().max(1.0);
    if m == 1.0 {
        "1 metre".into()
    } else {
        format!("{m} metres")
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn names_turns_distances_and_places() {
        let text = "name = \"t\"\ncell_m = 2.0\nmap = '''\n#####\n....#\n....#\n'''\n\
                    [places]\n\"help desk\" = [4, 0]\nexit = [4, 2]\n";
        let site = Site::parse(text, Path::new("t.toml")).unwrap();
        let route = Route {
            cells: [(0, 0), (1, 0), (2, 0), (3, 0), (4, 0), (4, 1), (4, 2)]
                .map(|(x, y)| Cell::new(x, y))
                .to_vec(),
        };
        let steps = instructions(&site, &route);
        let texts: Vec<&str> = steps.iter().map(|s| s.text.as_str()).collect();
        assert_eq!(
            texts,
            [
                "Walk 8 metres, then turn right at help desk.",
                "Walk 4 metres; you have arrived at exit.",
            ]
        );
        assert_eq!(steps[0].at, Cell::new(4, 0));
        assert_eq!(steps[1].distance_m, 4.0);
    }

    #[test]
    fn left_is_left_on_the_map() {
        assert_eq!(turn(0, 6), Some("turn left"), "east, then north");
        assert_eq!(turn(2, 0), Some("turn left"), "south, then east");
        assert_eq!(turn(0, 1), Some("bear right"));
        assert_eq!(turn(3, 3), None);
    }
}
