//! Turn-by-turn for a route: structured maneuvers in the convention route
//! engines use (OSRM / Valhalla steps: a type, a modifier, the distance, the
//! place at the maneuver), so any client can render or speak them in its own
//! language, and plain English sentences a screen reader can speak built from
//! them: "Walk 12 m, then turn left at help desk."
//!
//! The maneuvers follow the line the walker is given ([`ServedLine`]), and
//! their distances are metres along it. That line may still zig-zag (a grid
//! route's cells' centres go east, south-east, east, ... where a person
//! simply walks on), so it is first simplified to its corners
//! (Douglas–Peucker, tolerance [`CORNER_TOLERANCE_CELLS`]); each corner whose
//! bend is at least 30° becomes a turn: under 60° "slight", under 135° a plain
//! turn, under 175° "sharp", beyond that a U-turn. A maneuver within
//! [`PLACE_RADIUS_CELLS`] of a named place is named after it; places,
//! junctions and features are looked up on the route's cells. Guidance
//! (`crate::guide`) announces these same maneuvers while the route is walked.
//!
//! The English follows Wayfindr's guidance (ITU-T F.921) for people using a
//! screen reader: landmarks rather than compass bearings, nothing that needs
//! sight ("look", "see"), a way to set off without a compass ("With the help
//! desk behind you, walk …" when a place is next to the start), and a warning
//! before stairs, doors and lifts on the way. Profiles shape them: a
//! wheelchair user is told of lifts (their routes never take stairs); a
//! low-vision walker is told fewer turns (a bend under 60° is walked on, not
//! announced) and a landmark at every decision point (the nearest place
//! within [`LOW_VISION_PLACE_RADIUS_CELLS`], or a door or lift there).

use serde::Serialize;

use super::anyangle::{GridPoint, centre};
use super::lines::nearest_on_segment;
use super::route::kept_vertices;
use super::{Profile, Route, ServedLine};
use crate::site::{Cell, ConnectorKind, Site, Tile};

/// How near (in cells) a named place must be to name a turn after it.
pub(crate) const PLACE_RADIUS_CELLS: f64 = 1.5;

/// How near (in cells) a named place may be to serve a low-vision walker as
/// the landmark of a decision point.
pub(crate) const LOW_VISION_PLACE_RADIUS_CELLS: f64 = 4.0;

/// How near (in cells) a named place must be to the start to set off by it.
pub(crate) const START_PLACE_RADIUS_CELLS: f64 = 3.0;

/// Something on the walk to a maneuver worth a warning before it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Feature {
    Stairs,
    Door,
    Lift,
}

impl Feature {
    fn of(tile: Option<Tile>) -> Option<Feature> {
        match tile? {
            Tile::Stairs => Some(Feature::Stairs),
            Tile::Door => Some(Feature::Door),
            Tile::Elevator => Some(Feature::Lift),
            _ => None,
        }
    }

    /// The warning, as a clause: "…, with a door after 4 metres, …".
    fn warning(self, after_m: f64) -> String {
        let what = match self {
            Feature::Stairs => "stairs",
            Feature::Door => "a door",
            Feature::Lift => "the lift",
        };
        if after_m < 1.0 {
            format!("{what} straight ahead")
        } else {
            format!("{what} after {}", metres(after_m))
        }
    }
}

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
    /// A junction passed straight on (other ways open there): a decision
    /// point too, where a walker who is not told may take the wrong way.
    Continue,
    /// The destination.
    Arrive,
}

/// Which way a turn goes, as OSRM names step modifiers.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Modifier {
    /// Straight on, through a junction.
    Straight,
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
    pub(crate) fn words(self) -> &'static str {
        match self {
            Modifier::Straight => "go straight on",
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
    /// [`PLACE_RADIUS_CELLS`] (for a low-vision walker, the landmark: see
    /// the module).
    pub place: Option<String>,
    /// The first stairs, door or lift on the walk to this maneuver, and
    /// metres from the route's start to it (spoken, not published; f32:
    /// guidance keeps the maneuvers of every session).
    #[serde(skip)]
    pub on_the_way: Option<(Feature, f32)>,
}

impl Maneuver {
    /// Whether the walker must decide something here (turn or stop).
    pub fn is_decision(&self) -> bool {
        self.kind != ManeuverType::Depart
    }

    /// The English sentence for the walk up to this maneuver and the
    /// maneuver itself, as a screen reader speaks it, from `distance_m`
    /// before it: "Walk 12 metres, with a door after 4 metres, then turn
    /// left at help desk." An arrival is walked `towards` what the walk
    /// goes on by ("the lift") when there is one: the end of one floor's
    /// leg of a route across floors.
    pub(crate) fn sentence(&self, distance_m: f64, towards: Option<&str>) -> String {
        capitalised(&self.clause(distance_m, towards)) + "."
    }

    /// [`Maneuver::sentence`] without its capital and full stop, to be
    /// joined to another.
    pub(crate) fn clause(&self, distance_m: f64, towards: Option<&str>) -> String {
        let named = self
            .place
            .as_ref()
            .map(|p| format!(" at {p}"))
            .unwrap_or_default();
        let mut walk = format!("walk {}", metres(distance_m));
        let from_m = self.along_m - distance_m;
        if let Some((feature, at_m)) = self.on_the_way
            && f64::from(at_m) >= from_m - 0.5
        {
            walk.push_str(", with ");
            walk.push_str(&feature.warning(f64::from(at_m) - from_m));
        }
        match (self.kind, self.modifier) {
            (ManeuverType::Arrive, _) => match towards {
                Some(what) => format!("{walk} to {what}"),
                None => format!("{walk}; you have arrived{named}"),
            },
            (ManeuverType::Continue, Some(m)) if self.place.is_none() => {
                format!("{walk}, then {} across the junction", m.words())
            }
            (_, Some(m)) => format!("{walk}, then {}{named}", m.words()),
            (_, None) => format!("{walk}{named}"),
        }
    }
}

/// The sentence a walker sets off along `route` with: how to orient without
/// a compass, then the walk to the first decision point of its `maneuvers`
/// (an arrival walked `towards` what the walk goes on by, as in
/// [`Maneuver::sentence`]).
pub(crate) fn first_sentence(
    site: &Site,
    route: &[Cell],
    maneuvers: &[Maneuver],
    towards: Option<&str>,
) -> Option<String> {
    let first = maneuvers.get(1)?;
    let walk = first.clause(first.distance_m, towards);
    Some(match setting_off(site, route) {
        Some(setting_off) => format!("{setting_off}, {walk}."),
        None => capitalised(&walk) + ".",
    })
}

fn capitalised(clause: &str) -> String {
    let mut chars = clause.chars();
    chars.next().map_or_else(String::new, |c| {
        c.to_uppercase().chain(chars).collect::<String>()
    })
}

/// How far (in cells) a route may stray from the straight line between two
/// kept corners before the cell between them becomes a corner too.
pub(crate) const CORNER_TOLERANCE_CELLS: f64 = 1.0;

/// How far around a cell its ways out are counted, metres: beyond the
/// width of a corridor, so a corridor shows two ways (on and back) and a
/// junction three or more.
pub(crate) const JUNCTION_RADIUS_M: f64 = 3.0;

/// The maneuvers of `route` on `site` for a walker with `profile`, along
/// its cells' centres: [`maneuvers_along`] for a route served without a
/// line of its own.
pub(crate) fn maneuvers(site: &Site, route: &Route, profile: Profile) -> Vec<Maneuver> {
    maneuvers_along(site, route, &ServedLine::of_cells(route).points, profile)
}

/// The maneuvers of `route` on `site` for a walker with `profile` who
/// follows `line` (cell units, through the route's cells): depart, a turn
/// per corner of the line, a continue per junction passed straight on,
/// arrive; empty for a route of one cell.
pub(crate) fn maneuvers_along(
    site: &Site,
    route: &Route,
    line: &[GridPoint],
    profile: Profile,
) -> Vec<Maneuver> {
    let cells = &route.cells;
    if cells.len() < 2 || line.len() < 2 {
        return Vec::new();
    }
    let arc = arc_lengths(line);
    let cell_arc = cells_along(line, &arc, cells);
    // Each corner: where it is on the line (cells along it) and the route's
    // cell nearest to it, the cells walked in order.
    let mut after = 0;
    let corners: Vec<(GridPoint, f64, usize)> = kept_vertices(line, CORNER_TOLERANCE_CELLS)
        .into_iter()
        .map(|v| {
            let at = if v + 1 == line.len() {
                cells.len() - 1
            } else {
                // The cells' places along the line only grow: the nearest
                // is at most one past the corner's place.
                let mut nearest = after;
                for i in after..cells.len() {
                    if (cell_arc[i] - arc[v]).abs() < (cell_arc[nearest] - arc[v]).abs() {
                        nearest = i;
                    }
                    if cell_arc[i] > arc[v] {
                        break;
                    }
                }
                nearest
            };
            after = at;
            (line[v], arc[v], at)
        })
        .collect();
    let low_vision = profile == Profile::LowVision;
    let place = |c: Cell| {
        site.nearest_place(c, PLACE_RADIUS_CELLS)
            .map(str::to_owned)
            .or_else(|| low_vision.then(|| landmark(site, c)).flatten())
    };
    // A bend under this is walked on rather than announced.
    let least_turn_deg = if low_vision { 60.0 } else { 30.0 };
    // The decision points: cell index, cells along the line, what: the
    // corners that turn enough, and the destination…
    let mut points: Vec<(usize, f64, ManeuverType, Option<Modifier>)> = Vec::new();
    for k in 1..corners.len() {
        let ((a, _, _), (b, b_arc, b_at)) = (corners[k - 1], corners[k]);
        match corners.get(k + 1) {
            None => points.push((b_at, b_arc, ManeuverType::Arrive, None)),
            Some(&(c, _, _)) => {
                if let Some(m) = turn(bearing(a, b), bearing(b, c), least_turn_deg) {
                    points.push((b_at, b_arc, ManeuverType::Turn, Some(m)));
                }
            }
        }
    }
    // …and the junctions walked straight through, away from those.
    let decisions: Vec<usize> = points.iter().map(|p| p.0).collect();
    points.extend(junctions(site, cells, &decisions).into_iter().map(|i| {
        (
            i,
            cell_arc[i],
            ManeuverType::Continue,
            Some(Modifier::Straight),
        )
    }));
    points.sort_by(|p, q| p.1.total_cmp(&q.1));
    let mut out = vec![Maneuver {
        kind: ManeuverType::Depart,
        modifier: None,
        distance_m: 0.0,
        along_m: 0.0,
        at: cells[0],
        place: place(cells[0]),
        on_the_way: None,
    }];
    // The first feature since the last maneuver, with metres to it.
    let mut on_the_way = None;
    let (mut from, mut from_arc) = (0, 0.0);
    for (b, b_arc, kind, modifier) in points {
        for i in from + 1..=b {
            if on_the_way.is_none() {
                on_the_way = Feature::of(site.tile(cells[i]))
                    .map(|f| (f, (cell_arc[i] * site.cell_m) as f32));
            }
        }
        from = from.max(b);
        out.push(Maneuver {
            kind,
            modifier,
            distance_m: (b_arc - from_arc) * site.cell_m,
            along_m: b_arc * site.cell_m,
            at: cells[b],
            place: place(cells[b]),
            on_the_way: on_the_way.take(),
        });
        from_arc = b_arc;
    }
    out
}

/// Cells along `line` from its start to each of its vertices.
fn arc_lengths(line: &[GridPoint]) -> Vec<f64> {
    let mut along = 0.0;
    let mut last = line[0];
    line.iter()
        .map(|&p| {
            along += (p[0] - last[0]).hypot(p[1] - last[1]);
            last = p;
            along
        })
        .collect()
}

/// How far along `line` (cells; `arc` from [`arc_lengths`]) each of
/// `cells` lies: its centre projected on the line, searched forward from
/// the previous cell's place and no further than a step beyond it, so a
/// line passing near itself does not pull a cell to its other pass.
fn cells_along(line: &[GridPoint], arc: &[f64], cells: &[Cell]) -> Vec<f64> {
    let mut out = Vec::with_capacity(cells.len());
    let (mut segment, mut last) = (0, 0.0_f64);
    for (i, &cell) in cells.iter().enumerate() {
        let step = if i == 0 {
            0.0
        } else {
            cells[i - 1].distance(cell)
        };
        let reach = last + step + 1.0;
        let mut best = (f64::INFINITY, last, segment);
        for s in segment..line.len() - 1 {
            if arc[s] > reach {
                break;
            }
            let (d, f) = nearest_on_segment(centre(cell), line[s], line[s + 1]);
            if d < best.0 {
                best = (d, arc[s] + f * (arc[s + 1] - arc[s]), s);
            }
        }
        last = best.1.max(last);
        segment = best.2;
        out.push(last);
    }
    out
}

/// Indices in `cells` of the junctions the route passes straight through:
/// cells with three ways out or more ([`ways_out`]) at least
/// [`JUNCTION_RADIUS_M`] along the route from its ends and from every
/// decision point (by index in `cells`), one (the middle) per run of such
/// cells.
fn junctions(site: &Site, cells: &[Cell], decisions: &[usize]) -> Vec<usize> {
    let radius = (JUNCTION_RADIUS_M / site.cell_m).round().max(2.0) as usize;
    let clear = |i: usize| {
        i >= radius
            && i + radius < cells.len()
            && decisions.iter().all(|&j| i.abs_diff(j) >= radius)
    };
    let mut found = Vec::new();
    let mut run: Option<(usize, usize)> = None;
    for (i, &cell) in cells.iter().enumerate() {
        // The radius is the site's (its cell size), so the count is the
        // cell's alone: kept on the site after the first route through it.
        let junction = clear(i) && site.cached_ways_out(cell, || ways_out(site, cell, radius)) >= 3;
        match (&mut run, junction) {
            (Some((_, end)), true) if *end + 1 == i => *end = i,
            (_, true) => {
                if let Some((a, b)) = run.replace((i, i)) {
                    found.push((a + b) / 2);
                }
            }
            (_, false) => {}
        }
    }
    found.extend(run.map(|(a, b)| (a + b) / 2));
    found
}

/// How many separate ways lead out of `centre`: the walkable cells
/// `radius` cells away (the square ring around it) that can be reached from
/// it without leaving the square, counted in runs around the ring. A
/// corridor has two, a junction three or more; an open floor, where the
/// whole ring is reached, one.
fn ways_out(site: &Site, centre: Cell, radius: usize) -> usize {
    let r = radius as i32;
    let side = 2 * r + 1;
    let at = |dx: i32, dy: i32| {
        let (x, y) = (i32::from(centre.x) + dx, i32::from(centre.y) + dy);
        (x >= 0 && y >= 0 && x <= i32::from(u16::MAX) && y <= i32::from(u16::MAX))
            .then(|| Cell::new(x as u16, y as u16))
            .filter(|&c| site.walkable(c))
    };
    let index = |dx: i32, dy: i32| ((dy + r) * side + dx + r) as usize;
    let mut reached = vec![false; (side * side) as usize];
    let mut queue = std::collections::VecDeque::from([(0, 0)]);
    reached[index(0, 0)] = true;
    while let Some((dx, dy)) = queue.pop_front() {
        let here = Cell::new(
            (i32::from(centre.x) + dx) as u16,
            (i32::from(centre.y) + dy) as u16,
        );
        for (sx, sy) in [
            (-1, -1),
            (0, -1),
            (1, -1),
            (-1, 0),
            (1, 0),
            (-1, 1),
            (0, 1),
            (1, 1),
        ] {
            let (nx, ny) = (dx + sx, dy + sy);
            if nx.abs() > r || ny.abs() > r || reached[index(nx, ny)] {
                continue;
            }
            if let Some(next) = at(nx, ny)
                && super::Connectivity::Eight.step_ok(site, here, next)
            {
                reached[index(nx, ny)] = true;
                queue.push_back((nx, ny));
            }
        }
    }
    // The ring clockwise from the top left corner.
    let mut ring: Vec<bool> = (-r..r)
        .map(|d| (d, -r))
        .chain((-r..r).map(|d| (r, d)))
        .chain((-r..r).map(|d| (-d, r)))
        .chain((-r..r).map(|d| (-r, -d)))
        .map(|(dx, dy)| reached[index(dx, dy)])
        .collect();
    // A pillar is not a wall between two ways: one blocked cell between
    // reached ones joins them.
    let n = ring.len();
    let pillars: Vec<usize> = (0..n)
        .filter(|&i| !ring[i] && ring[(i + n - 1) % n] && ring[(i + 1) % n])
        .collect();
    for i in pillars {
        ring[i] = true;
    }
    let starts = (0..ring.len())
        .filter(|&i| ring[i] && !ring[(i + ring.len() - 1) % ring.len()])
        .count();
    if starts == 0 && ring.iter().any(|&r| r) {
        1
    } else {
        starts
    }
}

/// A low-vision walker's landmark at `cell` when no place is at it: the
/// nearest place a little further off, or a door or lift there.
fn landmark(site: &Site, cell: Cell) -> Option<String> {
    site.nearest_place(cell, LOW_VISION_PLACE_RADIUS_CELLS)
        .map(str::to_owned)
        .or_else(|| match Feature::of(site.tile(cell)) {
            Some(Feature::Door) => Some("the door".to_owned()),
            Some(Feature::Lift) => Some("the lift".to_owned()),
            _ => None,
        })
}

/// How to set off along `cells` by the nearest place next to the start (not
/// at it): "With help desk behind you", "With help desk on your left",
/// "Facing help desk"; `None` when no place is near.
fn setting_off(site: &Site, cells: &[Cell]) -> Option<String> {
    let start = *cells.first()?;
    let (name, place) = site
        .places()
        .iter()
        .map(|(n, &c)| (n, c, c.distance(start)))
        .filter(|&(_, _, d)| (0.5..=START_PLACE_RADIUS_CELLS).contains(&d))
        .min_by(|a, b| a.2.total_cmp(&b.2))
        .map(|(n, c, _)| (n, c))?;
    // The first few cells give the direction of walking off.
    let ahead = cells[cells.len().min(4) - 1];
    let side = (bearing(centre(start), centre(place)) - bearing(centre(start), centre(ahead))
        + 540.0)
        .rem_euclid(360.0)
        - 180.0;
    Some(match side.abs() {
        x if x >= 120.0 => format!("With {name} behind you"),
        x if x <= 45.0 => format!("Facing {name}"),
        _ if side > 0.0 => format!("With {name} on your right"),
        _ => format!("With {name} on your left"),
    })
}

/// The instructions for `route` on `site` from its `maneuvers`: a sentence
/// per turn (the first saying how to set off) and one for arriving; empty
/// for a route of one cell.
pub fn instructions(site: &Site, route: &Route, maneuvers: &[Maneuver]) -> Vec<Instruction> {
    instructions_towards(site, route, maneuvers, None)
}

/// [`instructions`] for a walk that goes on at its end `towards` something
/// ("the lift"), which it walks to rather than arrives at.
pub(crate) fn instructions_towards(
    site: &Site,
    route: &Route,
    maneuvers: &[Maneuver],
    towards: Option<&str>,
) -> Vec<Instruction> {
    maneuvers
        .iter()
        .enumerate()
        .filter(|(_, m)| m.is_decision())
        .map(|(i, m)| Instruction {
            text: if i == 1 {
                first_sentence(site, &route.cells, maneuvers, towards).expect("a first decision")
            } else {
                m.sentence(m.distance_m, towards)
            },
            distance_m: m.distance_m,
            at: m.at,
        })
        .collect()
}

/// What a connector is called in a sentence: "the lift".
pub(crate) fn connector_noun(kind: ConnectorKind) -> String {
    format!("the {}", kind.name())
}

/// The sentence for riding a connector of `kind` `levels` levels (negative:
/// down) to `floor`: "Take the lift to F3.", "Take the stairs down to B1.",
/// "Take the escalator up 2 floors to F3." A lift is told only the floor, the
/// button its rider presses; stairs and escalators also which way and, past
/// one, how many floors, which a walker who cannot see the landings counts.
pub(crate) fn ride_sentence(kind: ConnectorKind, levels: i32, floor: &str) -> String {
    let noun = connector_noun(kind);
    if kind == ConnectorKind::Lift {
        return format!("Take {noun} to {floor}.");
    }
    let way = if levels < 0 { "down" } else { "up" };
    match levels.unsigned_abs() {
        1 => format!("Take {noun} {way} to {floor}."),
        n => format!("Take {noun} {way} {n} floors to {floor}."),
    }
}

/// The sentence for leaving a connector of `kind` on `floor`: "Leave the
/// lift on F3." It opens the next floor's walk, so a walker who lost count
/// of the landings hears where they should be.
pub(crate) fn leave_sentence(kind: ConnectorKind, floor: &str) -> String {
    format!("Leave {} on {floor}.", connector_noun(kind))
}

/// The sentence for arriving where a walk of one cell ends (a destination
/// at a connector's stop): "You have arrived at help desk."
pub(crate) fn arrived_sentence(site: &Site, at: Cell) -> String {
    match site.nearest_place(at, PLACE_RADIUS_CELLS) {
        Some(place) => format!("You have arrived at {place}."),
        None => "You have arrived.".to_owned(),
    }
}

/// Direction from `a` to `b` in degrees, clockwise on the map from east
/// (rows grow downwards).
fn bearing(a: GridPoint, b: GridPoint) -> f64 {
    (b[1] - a[1]).atan2(b[0] - a[0]).to_degrees()
}

/// The turn from bearing `a` to `b`, or `None` when about straight on (a
/// bend under `least_deg`). Clockwise is to the right.
fn turn(a: f64, b: f64, least_deg: f64) -> Option<Modifier> {
    let d = (b - a + 540.0).rem_euclid(360.0) - 180.0;
    let right = d > 0.0;
    let side = |r: Modifier, l: Modifier| if right { r } else { l };
    Some(match d.abs() {
        x if x < least_deg => return None,
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
    use crate::plan::Planner;
    use std::path::Path;
    use std::sync::Arc;

    #[test]
    fn kept_ways_out_are_the_search_s() {
        let site = Site::load(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("../../config/sites/waldo.toml"),
        )
        .unwrap();
        let radius = (JUNCTION_RADIUS_M / site.cell_m).round().max(2.0) as usize;
        for &cell in site.open_cells() {
            let direct = ways_out(&site, cell, radius);
            // Worked out on first use, then read back.
            for _ in 0..2 {
                assert_eq!(
                    site.cached_ways_out(cell, || ways_out(&site, cell, radius)),
                    direct
                );
            }
            assert_eq!(site.cached_ways_out(cell, || unreachable!()), direct);
        }
    }

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
        let steps = instructions(&site, &route, &maneuvers(&site, &route, Profile::Default));
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
        let kinds: Vec<_> = maneuvers(&site, &route, Profile::Default)
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
        assert_eq!(
            turn(0.0, -90.0, 30.0),
            Some(Modifier::Left),
            "east, then north"
        );
        assert_eq!(
            turn(90.0, 0.0, 30.0),
            Some(Modifier::Left),
            "south, then east"
        );
        assert_eq!(turn(0.0, 45.0, 30.0), Some(Modifier::SlightRight));
        assert_eq!(turn(170.0, -170.0, 30.0), None, "west stays west");
        assert_eq!(turn(0.0, 20.0, 30.0), None);
        assert_eq!(
            turn(0.0, 45.0, 60.0),
            None,
            "walked on by a low-vision walker"
        );
    }

    #[test]
    fn a_junction_walked_straight_through_is_a_continue() {
        // A corridor crossing another at (5, 4), and an open floor.
        let mut rows = vec![".....#.....".to_owned(); 9];
        rows[4] = "#".repeat(11);
        let site_of = |rows: &[String]| {
            let text = format!(
                "name = \"t\"\ncell_m = 1.0\nmap = '''\n{}\n'''\n",
                rows.join("\n")
            );
            Site::parse(&text, Path::new("t.toml")).unwrap()
        };
        let east = Route {
            cells: (0..=10).map(|x| Cell::new(x, 4)).collect(),
        };
        let site = site_of(&rows);
        let kinds: Vec<_> = maneuvers(&site, &east, Profile::Default)
            .into_iter()
            .map(|m| (m.kind, m.modifier, m.at))
            .collect();
        assert_eq!(
            kinds,
            [
                (ManeuverType::Depart, None, Cell::new(0, 4)),
                (
                    ManeuverType::Continue,
                    Some(Modifier::Straight),
                    Cell::new(5, 4)
                ),
                (ManeuverType::Arrive, None, Cell::new(10, 4)),
            ]
        );
        assert_eq!(
            texts(&site, &east, Profile::Default),
            [
                "Walk 5 metres, then go straight on across the junction.",
                "Walk 5 metres; you have arrived.",
            ]
        );
        // Turning there is the turn, not a continue as well.
        let north = Route {
            cells: (0..=5)
                .map(|x| Cell::new(x, 4))
                .chain((0..4).rev().map(|y| Cell::new(5, y)))
                .collect(),
        };
        let turning: Vec<_> = maneuvers(&site, &north, Profile::Default)
            .into_iter()
            .map(|m| m.kind)
            .collect();
        assert_eq!(
            turning,
            [
                ManeuverType::Depart,
                ManeuverType::Turn,
                ManeuverType::Arrive
            ]
        );
        // On an open floor (a pillar in it too) the ways out join all
        // round: nothing to decide on a straight walk.
        let mut open = vec!["#".repeat(11); 9];
        open[1] = "#######.###".to_owned();
        assert_eq!(maneuvers(&site_of(&open), &east, Profile::Default).len(), 2);
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
        let steps = instructions(&site, &route, &maneuvers(&site, &route, Profile::Default));
        assert_eq!(steps.len(), 1, "{steps:?}");
        assert_eq!(steps[0].text, "Walk 6 metres; you have arrived.");
    }

    #[test]
    fn distances_are_along_the_line_served() {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n#######\n#######\n#######\n'''\n";
        let site = Site::parse(text, Path::new("t.toml")).unwrap();
        // Cells east then up a diagonal, drawn as one slanted line from
        // (0, 0) to (6, 2) through them: 6.32 m, not the cells' 6.83 m.
        let route = Route {
            cells: [(0, 0), (1, 0), (2, 1), (3, 1), (4, 1), (5, 2), (6, 2)]
                .map(|(x, y)| Cell::new(x, y))
                .to_vec(),
        };
        let line = [[0.5, 0.5], [6.5, 2.5]];
        let along = maneuvers_along(&site, &route, &line, Profile::Default);
        assert_eq!(along.len(), 2, "{along:?}");
        assert!(
            (along[1].distance_m - 40f64.sqrt()).abs() < 1e-9,
            "{along:?}"
        );
        assert_eq!(along[1].at, Cell::new(6, 2));
        let by_cells = maneuvers(&site, &route, Profile::Default);
        assert!(by_cells.last().unwrap().along_m > along[1].along_m + 0.4);
    }

    /// Words a screen-reader instruction must not use: sight, and compass
    /// bearings a blind walker cannot take.
    fn assert_followable(texts: &[String]) {
        for text in texts {
            let lower = text.to_lowercase();
            for word in ["look", "see ", "north", "south", "east", "west"] {
                assert!(!lower.contains(word), "{word:?} in {text:?}");
            }
        }
    }

    fn texts(site: &Site, route: &Route, profile: Profile) -> Vec<String> {
        instructions(site, route, &maneuvers(site, route, profile))
            .into_iter()
            .map(|s| s.text)
            .collect()
    }

    #[test]
    fn sets_off_by_a_place_and_warns_of_a_door() {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n#####d####\n#........#\n#........#\n'''\n\
                    [places]\nentrance = [0, 1]\ndesk = [9, 0]\nexit = [9, 2]\n";
        let site = Site::parse(text, Path::new("t.toml")).unwrap();
        let route = Route {
            cells: (1..=9)
                .map(|x| Cell::new(x, 0))
                .chain([Cell::new(9, 1), Cell::new(9, 2)])
                .collect(),
        };
        let said = texts(&site, &route, Profile::Default);
        assert_eq!(
            said,
            [
                "With entrance behind you, walk 8 metres, with a door after 4 metres, then turn right at desk.",
                "Walk 2 metres; you have arrived at exit.",
            ]
        );
        assert_followable(&said);
        // Announced 6 m before the turn, the door is 2 m ahead.
        let turn = &maneuvers(&site, &route, Profile::Default)[1];
        assert_eq!(
            turn.sentence(6.0, None),
            "Walk 6 metres, with a door after 2 metres, then turn right at desk."
        );
        // Past the door, it is not mentioned again.
        assert_eq!(
            turn.sentence(3.0, None),
            "Walk 3 metres, then turn right at desk."
        );
    }

    #[test]
    fn wheelchair_users_are_told_of_lifts_and_never_of_stairs() {
        // Stairs straight across, a lift round the side.
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n###s###\n#.....#\n###e###\n'''\n\
                    [places]\nlibrary = [0, 0]\ncafe = [6, 0]\n";
        let site = Arc::new(Site::parse(text, Path::new("t.toml")).unwrap());
        let planner =
            crate::plan::astar::AStar::new(site.clone(), crate::plan::Connectivity::Eight);
        let (from, to) = (Cell::new(0, 0), Cell::new(6, 0));
        let walk = |profile| {
            let route = planner.plan(from, to, profile).unwrap().route;
            texts(&site, &route, profile)
        };
        let walking = walk(Profile::Default);
        assert!(walking.iter().any(|t| t.contains("stairs")), "{walking:?}");
        let rolling = walk(Profile::Wheelchair);
        assert!(
            rolling.iter().any(|t| t.contains("the lift")),
            "{rolling:?}"
        );
        assert!(rolling.iter().all(|t| !t.contains("stairs")), "{rolling:?}");
        assert_followable(&walking);
        assert_followable(&rolling);
    }

    #[test]
    fn low_vision_walkers_get_fewer_turns_and_a_landmark_at_each() {
        // Bearing right at (4, 0) and left at (7, 3), then a right turn at
        // (9, 3), with the only place a few cells from that turn.
        let row = "#".repeat(10);
        let map = vec![row; 8].join("\n");
        let text = format!(
            "name = \"t\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n[places]\n\"help desk\" = [6, 5]\n"
        );
        let site = Site::parse(&text, Path::new("t.toml")).unwrap();
        let route = Route {
            cells: (0..=4)
                .map(|x| Cell::new(x, 0))
                .chain((1..=3).map(|d| Cell::new(4 + d, d)))
                .chain([Cell::new(8, 3), Cell::new(9, 3)])
                .chain((4..=7).map(|y| Cell::new(9, y)))
                .collect(),
        };
        let turns = |profile| {
            maneuvers(&site, &route, profile)
                .into_iter()
                .filter(|m| m.kind == ManeuverType::Turn)
                .collect::<Vec<_>>()
        };
        let seeing = turns(Profile::Default);
        let low_vision = turns(Profile::LowVision);
        assert!(
            low_vision.len() < seeing.len(),
            "{seeing:?} / {low_vision:?}"
        );
        assert!(!low_vision.is_empty());
        for m in &low_vision {
            assert_eq!(m.place.as_deref(), Some("help desk"), "{m:?}");
        }
        assert!(seeing.iter().any(|m| m.place.is_none()));
        assert_followable(&texts(&site, &route, Profile::LowVision));
    }
}
