//! Shortest walkable paths on the site grid: the baseline planner, and the
//! search that later planners build on (with a per-cell cost factor).

use std::cmp::Ordering;
use std::collections::BinaryHeap;
use std::sync::Arc;

use super::{Connectivity, PlanError, Planned, Planner, Profile, Route};
use crate::site::{Cell, Site};

/// Plain A*: the shortest route by length.
pub struct AStar {
    site: Arc<Site>,
    connectivity: Connectivity,
}

impl AStar {
    pub fn new(site: Arc<Site>, connectivity: Connectivity) -> Self {
        AStar { site, connectivity }
    }
}

impl Planner for AStar {
    fn mode(&self) -> &'static str {
        "astar"
    }

    fn model_version(&self) -> Option<&str> {
        None
    }

    fn plan(&self, from: Cell, to: Cell, profile: Profile) -> Result<Planned, PlanError> {
        let route = profile_search(&self.site, self.connectivity, from, to, profile, |_| 1.0)?;
        Ok(Planned::searched(route))
    }
}

/// The profile's cheapest route, each cell's cost also scaled by `extra`
/// (≥ 1), equally cheap routes broken towards the straight line
/// ([`Costs::hug_line`]). Shared by every planner: the baseline, and the
/// repair of learned frames.
pub(crate) fn profile_search(
    site: &Site,
    connectivity: Connectivity,
    from: Cell,
    to: Cell,
    profile: Profile,
    extra: impl Fn(Cell) -> f64,
) -> Result<Route, PlanError> {
    search_for(site, connectivity, [from, to], profile, extra, true, None)
}

/// [`profile_search`] towards `to` with a better heuristic than the
/// octile distance: `to_target_m`, per open cell (by [`Site::open_index`]),
/// a lower bound on the metres of any route from that cell to `to` for
/// `profile` (infinite where none; `plan::floors` floods one per connector
/// stop). A* with a tighter admissible heuristic finds a route as cheap
/// and expands far fewer cells: on a mall floor, the cells along the route
/// instead of most of the floor.
pub(crate) fn guided_search(
    site: &Site,
    connectivity: Connectivity,
    [from, to]: [Cell; 2],
    profile: Profile,
    to_target_m: &[f32],
) -> Result<Route, PlanError> {
    search_for(
        site,
        connectivity,
        [from, to],
        profile,
        |_| 1.0,
        true,
        Some(to_target_m),
    )
}

/// [`search_with`] the costs of `profile`, scaled by `extra`.
fn search_for(
    site: &Site,
    connectivity: Connectivity,
    [from, to]: [Cell; 2],
    profile: Profile,
    extra: impl Fn(Cell) -> f64,
    hug_line: bool,
    guide: Option<&[f32]>,
) -> Result<Route, PlanError> {
    let costs = Costs {
        passable: |c| profile.passable(site, c),
        cell_cost: |c| profile.cell_cost(site, c) * extra(c),
        turn_cost: profile.turn_cost(),
        hug_line,
    };
    search_with(site, connectivity, from, to, &costs, guide)
}

#[derive(PartialEq, Eq)]
struct Entry {
    /// f as ordered by the search: with [`Costs::hug_line`] in millionths of
    /// a cell (equal-cost routes summed in different orders differ in the
    /// last bits of a float, and must tie), else the float's bits (which
    /// order like the values, f being ≥ 0).
    f: i64,
    /// With `hug_line`, twice the area between the cell and the straight line
    /// from source to destination (else 0): among equal f the cell nearest
    /// the line is expanded first.
    off_line: u64,
    open: u32,
}

impl Entry {
    fn new(f: f64, off_line: Option<u64>, open: u32) -> Entry {
        Entry {
            f: match off_line {
                Some(_) => (f * 1e6).round() as i64,
                None => f.to_bits() as i64,
            },
            off_line: off_line.unwrap_or(0),
            open,
        }
    }
}

impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        // Min-heap on f, then nearest the line, then by index for determinism.
        other
            .f
            .cmp(&self.f)
            .then_with(|| other.off_line.cmp(&self.off_line))
            .then_with(|| other.open.cmp(&self.open))
    }
}

impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// |(c − from) × (to − from)|: how far `c` is off the line from `from` to
/// `to`, scaled by the line's length (the same for every cell of a search).
fn off_line(from: Cell, to: Cell, c: Cell) -> u64 {
    let (fx, fy) = (i64::from(from.x), i64::from(from.y));
    let cross = (i64::from(c.x) - fx) * (i64::from(to.y) - fy)
        - (i64::from(c.y) - fy) * (i64::from(to.x) - fx);
    cross.unsigned_abs()
}

/// A* from `from` to `to` over walkable cells. Entering a cell costs the step
/// length (1 or √2) times `cell_cost(cell)`; pass factors ≥ 1 so the octile
/// heuristic stays admissible. The default profile's search: every walkable
/// cell passable, no cost of its own, no turn cost; equally cheap routes are
/// broken by cell index, not towards the line (the simulator's walkers and
/// the fixtures they recorded keep their routes).
pub fn search(
    site: &Site,
    connectivity: Connectivity,
    from: Cell,
    to: Cell,
    cell_cost: impl Fn(Cell) -> f64,
) -> Result<Route, PlanError> {
    search_for(
        site,
        connectivity,
        [from, to],
        Profile::Default,
        cell_cost,
        false,
        None,
    )
}

/// What a search may use and what it pays.
pub(crate) struct Costs<P, C> {
    /// Cells the walker may stand on (a subset of the site's walkable cells).
    pub passable: P,
    /// Factor ≥ 1 on the cost of entering a cell.
    pub cell_cost: C,
    /// Added for every change of direction, in cell lengths (≥ 0).
    pub turn_cost: f64,
    /// Break ties between equally cheap routes towards the straight line
    /// from source to destination, so the route interleaves straight and
    /// diagonal steps as a person would instead of taking all straight steps
    /// then all diagonals (served routes); else by cell index.
    pub hug_line: bool,
}

/// Metres of slack taken off a guide's lower bounds: they are stored in
/// f32, whose rounding could otherwise lift one just above the true cost.
const GUIDE_SLACK_M: f64 = 1e-3;

/// A* as [`search`], over the cells `costs.passable` allows (corners too:
/// a diagonal never cuts the corner of a cell the walker may not use), with a
/// cost per turn. With a turn cost the search state is (cell, heading), so
/// the cheapest route with fewest turns wins, not the first one found.
/// The heuristic is the octile distance, or the larger of it and `guide`'s
/// lower bound in metres to `to` (see [`guided_search`]).
pub(crate) fn search_with(
    site: &Site,
    connectivity: Connectivity,
    from: Cell,
    to: Cell,
    costs: &Costs<impl Fn(Cell) -> bool, impl Fn(Cell) -> f64>,
    guide: Option<&[f32]>,
) -> Result<Route, PlanError> {
    for c in [from, to] {
        if !site.walkable(c) || !(costs.passable)(c) {
            return Err(PlanError::Blocked(c));
        }
    }
    let cells = site.open_cells();
    // Headings 0..8 index NEIGHBOURS; 8 is "not moved yet". Without a turn
    // cost one heading per cell is enough.
    let headings = if costs.turn_cost > 0.0 { 9 } else { 1 };
    let n = cells.len() * headings;
    let state = |open: usize, heading: usize| open * headings + heading.min(headings - 1);
    let start_open = site.open_index(from).expect("walkable");
    let goal_open = site.open_index(to).expect("walkable");
    let start = state(start_open, 8) as u32;
    let mut g = vec![f64::INFINITY; n];
    let mut came_from = vec![u32::MAX; n];
    let mut closed = vec![false; n];
    let mut heap = BinaryHeap::new();
    g[start as usize] = 0.0;
    let line = |c: Cell| costs.hug_line.then(|| off_line(from, to, c));
    // With hug_line, a route only float rounding makes cheaper is a tie: the
    // first found, nearer the line, keeps the cell.
    let slack = if costs.hug_line { 1e-9 } else { 0.0 };
    let estimate = |c: Cell, open: usize| {
        let octile = heuristic(c, to, connectivity);
        guide.map_or(octile, |m| {
            octile.max(f64::from(m[open]) / site.cell_m - GUIDE_SLACK_M / site.cell_m)
        })
    };
    heap.push(Entry::new(estimate(from, start_open), line(from), start));
    while let Some(Entry { open: s, .. }) = heap.pop() {
        let (open, heading) = (s as usize / headings, s as usize % headings);
        if open == goal_open {
            let mut path = vec![to];
            let mut at = s;
            while at != start {
                at = came_from[at as usize];
                path.push(cells[at as usize / headings]);
            }
            path.reverse();
            return Ok(Route { cells: path });
        }
        if std::mem::replace(&mut closed[s as usize], true) {
            continue;
        }
        let here = cells[open];
        for (k, (dx, dy)) in NEIGHBOURS.into_iter().enumerate() {
            let (Some(x), Some(y)) = (here.x.checked_add_signed(dx), here.y.checked_add_signed(dy))
            else {
                continue;
            };
            let next = Cell::new(x, y);
            if !connectivity.step_ok_by(here, next, |c| site.walkable(c) && (costs.passable)(c)) {
                continue;
            }
            let j = site.open_index(next).expect("step_ok checks walkable");
            let step = if dx != 0 && dy != 0 {
                std::f64::consts::SQRT_2
            } else {
                1.0
            };
            let turn = if headings > 1 && heading != 8 && heading != k {
                costs.turn_cost
            } else {
                0.0
            };
            let t = state(j, k);
            let cand = g[s as usize] + step * (costs.cell_cost)(next) + turn;
            // A cell the guide says cannot reach the target is not queued.
            if cand < g[t] - slack && guide.is_none_or(|m| m[j].is_finite()) {
                g[t] = cand;
                came_from[t] = s;
                heap.push(Entry::new(cand + estimate(next, j), line(next), t as u32));
            }
        }
    }
    Err(PlanError::Unreachable { from, to })
}

pub(crate) const NEIGHBOURS: [(i16, i16); 8] = [
    (1, 0),
    (-1, 0),
    (0, 1),
    (0, -1),
    (1, 1),
    (1, -1),
    (-1, 1),
    (-1, -1),
];

/// Octile distance (8-connected) or Manhattan distance (4-connected).
fn heuristic(a: Cell, b: Cell, connectivity: Connectivity) -> f64 {
    let dx = f64::from(a.x.abs_diff(b.x));
    let dy = f64::from(a.y.abs_diff(b.y));
    match connectivity {
        Connectivity::Four => dx + dy,
        Connectivity::Eight => dx.max(dy) + (std::f64::consts::SQRT_2 - 1.0) * dx.min(dy),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::RouteErrorCode;

    fn site(map: &str) -> Arc<Site> {
        Arc::new(Site::of_map(map))
    }

    #[test]
    fn goes_around_walls_without_cutting_corners() {
        let s = site("###\n#.#\n###");
        let planner = AStar::new(s.clone(), Connectivity::Eight);
        let route = planner
            .plan(Cell::new(0, 0), Cell::new(2, 2), Profile::Default)
            .map(|p| p.route)
            .unwrap();
        route
            .validate(&s, Cell::new(0, 0), Cell::new(2, 2), Connectivity::Eight)
            .unwrap();
        // Around the pillar: two straight steps, then a diagonal is impossible
        // next to the pillar, so 4 steps of length 1.
        assert_eq!(route.cells.len(), 5);
        assert_eq!(route.length_m(&s), 4.0);
    }

    #[test]
    fn uses_diagonals_in_the_open() {
        let s = site("###\n###\n###");
        let route = AStar::new(s.clone(), Connectivity::Eight)
            .plan(Cell::new(0, 0), Cell::new(2, 2), Profile::Default)
            .map(|p| p.route)
            .unwrap();
        assert_eq!(route.cells.len(), 3);
        let four = AStar::new(s.clone(), Connectivity::Four)
            .plan(Cell::new(0, 0), Cell::new(2, 2), Profile::Default)
            .map(|p| p.route)
            .unwrap();
        assert_eq!(four.cells.len(), 5);
        four.validate(&s, Cell::new(0, 0), Cell::new(2, 2), Connectivity::Four)
            .unwrap();
    }

    #[test]
    fn equal_routes_hug_the_straight_line() {
        // 8 columns by 4 rows: 3 diagonal and 4 straight steps in any order
        // are equally short; the route interleaves them along the line.
        let s = site("########\n########\n########\n########");
        let (a, b) = (Cell::new(0, 0), Cell::new(7, 3));
        let route = AStar::new(s.clone(), Connectivity::Eight)
            .plan(a, b, Profile::Default)
            .unwrap()
            .route;
        route.validate(&s, a, b, Connectivity::Eight).unwrap();
        assert!((route.length_m(&s) - (4.0 + 3.0 * std::f64::consts::SQRT_2)).abs() < 1e-9);
        // No cell is more than a cell from the line (straight-then-diagonal
        // would be 3 · 7 / √58 ≈ 2.8 cells off at the bend).
        let worst = route
            .cells
            .iter()
            .map(|&c| off_line(a, b, c) as f64 / 58f64.sqrt())
            .fold(0.0, f64::max);
        assert!(
            worst <= 1.0,
            "{worst} cells off the line: {:?}",
            route.cells
        );
    }

    #[test]
    fn reports_unreachable_and_blocked() {
        let s = site("#.#");
        let p = AStar::new(s, Connectivity::Eight);
        assert_eq!(
            p.plan(Cell::new(0, 0), Cell::new(2, 0), Profile::Default)
                .map(|p| p.route)
                .unwrap_err()
                .code(),
            RouteErrorCode::Unreachable
        );
        assert_eq!(
            p.plan(Cell::new(0, 0), Cell::new(1, 0), Profile::Default)
                .map(|p| p.route)
                .unwrap_err()
                .code(),
            RouteErrorCode::BlockedCell
        );
    }
}
