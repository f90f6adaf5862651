//! Turn-by-turn for a route: structured maneuvers in the convention route
//! engines use (OSRM / Valhalla steps: a type, a modifier, the distance, the
//! place at the maneuver), so any client can render or speak them in its own
//! language, and plain English sentences a screen reader can speak built from
//! them: "Walk 12 m, then turn left at help desk."
//!
//! An 8-connected grid route zig-zags (east, south-east, east, ...) where a
//! person simply walks on, so the route is first simplified to its corners
//! (Douglas–Peucker, tolerance [`CORNER_TOLERANCE_CELLS`]); each corner whose
//! bend is at least 30° becomes a turn: under 60° "slight", under 135° a plain
//! turn, under 175° "sharp", beyond that a U-turn. A maneuver within
//! [`PLACE_RADIUS_CELLS`] of a named place is named after it. Guidance
//! (`crate::guide`) announces these same maneuvers while the route is walked.

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

/// What a maneuver is, as OSRM / Valhalla name step types.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum ManeuverType {
    /// Where the route starts.
    Depart,
    /// A change of direction: a decision point.
    Turn,
    /// The destination.
    Arrive,
}

/// Which way a turn goes, as OSRM names step modifiers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Modifier {
    SlightRight,
    SlightLeft,
    Right,
    Left,
    SharpRight,
    SharpLeft,
    Uturn,
}

impl Modifier {
    /// The English words for the turn.
    pub fn words(self) -> &'static str {
        match self {
            Modifier::SlightRight => "bear right",
            Modifier::SlightLeft => "bear left",
            Modifier::Right => "turn right",
            Modifier::Left => "turn left",
            Modifier::SharpRight => "turn sharply right",
            Modifier::SharpLeft => "turn sharply left",
            Modifier::Uturn => "turn around",
        }
    }
}

/// One maneuver of a route.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Maneuver {
    #[serde(rename = "type")]
    pub kind: ManeuverType,
    /// Which way to turn; `None` for depart and arrive.
    pub modifier: Option<Modifier>,
    /// Walking distance from the previous maneuver to this one, metres.
    pub distance_m: f64,
    /// Walking distance from the start of the route to this one, metres.
    pub along_m: f64,
    pub at: Cell,
    /// The named place at the maneuver, if one is within
    /// [`PLACE_RADIUS_CELLS`].
    pub place: Option<String>,
}

impl Maneuver {
    /// Whether the walker must decide something here (turn or stop).
    pub fn is_decision(&self) -> bool {
        self.kind != ManeuverType::Depart
    }

    /// The English sentence for the walk up to this maneuver and the
    /// maneuver itself, as a screen reader speaks it.
    pub fn sentence(&self, distance_m: f64) -> String {
        let named = self
            .place
            .as_ref()
            .map(|p| format!(" at {p}"))
            .unwrap_or_default();
        match (self.kind, self.modifier) {
            (ManeuverType::Arrive, _) => {
                format!("Walk {}; you have arrived{named}.", metres(distance_m))
            }
            (_, Some(m)) => format!("Walk {}, then {}{named}.", metres(distance_m), m.words()),
            (_, None) => format!("Walk {}{named}.", metres(distance_m)),
        }
    }
}

/// How far (in cells) a route may stray from the straight line between two
/// kept corners before the cell between them becomes a corner too.
pub const CORNER_TOLERANCE_CELLS: f64 = 1.0;

/// The maneuvers of `route` on `site`: depart, a turn per corner, arrive;
/// empty for a route of one cell.
pub fn maneuvers(site: &Site, route: &Route) -> Vec<Maneuver> {
    let cells = &route.cells;
    if cells.len() < 2 {
        return Vec::new();
    }
    let mut keep = vec![false; cells.len()];
    keep[0] = true;
    keep[cells.len() - 1] = true;
    simplify(cells, 0, cells.len() - 1, &mut keep);
    let corners: Vec<usize> = (0..cells.len()).filter(|&i| keep[i]).collect();
    let place = |c: Cell| site.nearest_place(c, PLACE_RADIUS_CELLS).map(str::to_owned);
    let mut out = vec![Maneuver {
        kind: ManeuverType::Depart,
        modifier: None,
        distance_m: 0.0,
        along_m: 0.0,
        at: cells[0],
        place: place(cells[0]),
    }];
    let (mut walked, mut along) = (0.0, 0.0);
    for k in 1..corners.len() {
        let (a, b) = (corners[k - 1], corners[k]);
        let leg = cells[a..=b]
            .windows(2)
            .map(|w| w[0].distance(w[1]))
            .sum::<f64>()
            * site.cell_m;
        walked += leg;
        along += leg;
        let at = cells[b];
        let (kind, modifier) = match corners.get(k + 1) {
            None => (ManeuverType::Arrive, None),
            Some(&c) => match turn(bearing(cells[a], at), bearing(at, cells[c])) {
                None => continue,
                some => (ManeuverType::Turn, some),
            },
        };
        out.push(Maneuver {
            kind,
            modifier,
            distance_m: walked,
            along_m: along,
            at,
            place: place(at),
        });
        walked = 0.0;
    }
    out
}

/// The instructions for `route` on `site`: a sentence per turn and one for
/// arriving; empty for a route of one cell.
pub fn instructions(site: &Site, route: &Route) -> Vec<Instruction> {
    maneuvers(site, route)
        .iter()
        .filter(|m| m.is_decision())
        .map(|m| Instruction {
            text: m.sentence(m.distance_m),
            distance_m: m.distance_m,
            at: m.at,
        })
        .collect()
}

/// Douglas–Peucker: marks in `keep` the cells between `a` and `b` that stray
/// more than [`CORNER_TOLERANCE_CELLS`] from the line `a`–`b`.
fn simplify(cells: &[Cell], a: usize, b: usize, keep: &mut [bool]) {
    if b <= a + 1 {
        return;
    }
    let (ax, ay) = (f64::from(cells[a].x), f64::from(cells[a].y));
    let (bx, by) = (f64::from(cells[b].x), f64::from(cells[b].y));
    let len = (bx - ax).hypot(by - ay).max(f64::EPSILON);
    let (far, dist) = (a + 1..b)
        .map(|i| {
            let (x, y) = (f64::from(cells[i].x), f64::from(cells[i].y));
            (i, ((bx - ax) * (ay - y) - (ax - x) * (by - ay)).abs() / len)
        })
        .max_by(|p, q| p.1.total_cmp(&q.1))
        .expect("b > a + 1");
    if dist > CORNER_TOLERANCE_CELLS {
        keep[far] = true;
        simplify(cells, a, far, keep);
        simplify(cells, far, b, keep);
    }
}

/// Direction from `a` to `b` in degrees, clockwise on the map from east
/// (rows grow downwards).
fn bearing(a: Cell, b: Cell) -> f64 {
    let dx = f64::from(b.x) - f64::from(a.x);
    let dy = f64::from(b.y) - f64::from(a.y);
    dy.atan2(dx).to_degrees()
}

/// The turn from bearing `a` to `b`, or `None` when about straight on.
/// Clockwise is to the right.
fn turn(a: f64, b: f64) -> Option<Modifier> {
    let d = (b - a + 540.0).rem_euclid(360.0) - 180.0;
    let right = d > 0.0;
    let side = |r: Modifier, l: Modifier| if right { r } else { l };
    Some(match d.abs() {
        x if x < 30.0 => return None,
        x if x < 60.0 => side(Modifier::SlightRight, Modifier::SlightLeft),
        x if x < 135.0 => side(Modifier::Right, Modifier::Left),
        x if x < 175.0 => side(Modifier::SharpRight, Modifier::SharpLeft),
        _ => Modifier::Uturn,
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
        let kinds: Vec<_> = maneuvers(&site, &route)
            .into_iter()
            .map(|m| (m.kind, m.modifier, m.along_m, m.place))
            .collect();
        assert_eq!(
            kinds,
            [
                (ManeuverType::Depart, None, 0.0, None),
                (
                    ManeuverType::Turn,
                    Some(Modifier::Right),
                    8.0,
                    Some("help desk".into())
                ),
                (ManeuverType::Arrive, None, 12.0, Some("exit".into())),
            ]
        );
    }

    #[test]
    fn left_is_left_on_the_map() {
        assert_eq!(turn(0.0, -90.0), Some(Modifier::Left), "east, then north");
        assert_eq!(turn(90.0, 0.0), Some(Modifier::Left), "south, then east");
        assert_eq!(turn(0.0, 45.0), Some(Modifier::SlightRight));
        assert_eq!(turn(170.0, -170.0), None, "west stays west");
        assert_eq!(turn(0.0, 20.0), None);
    }

    #[test]
    fn a_zig_zag_is_one_straight_walk() {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n######\n######\n'''\n";
        let site = Site::parse(text, Path::new("t.toml")).unwrap();
        let route = Route {
            cells: [(0, 0), (1, 1), (2, 1), (3, 1), (4, 0), (5, 0)]
                .map(|(x, y)| Cell::new(x, y))
                .to_vec(),
        };
        let steps = instructions(&site, &route);
        assert_eq!(steps.len(), 1, "{steps:?}");
        assert_eq!(steps[0].text, "Walk 6 metres; you have arrived.");
    }
}
