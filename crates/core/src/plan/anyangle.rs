//! Any-angle routes: the fair geometric baseline for learned planners, and
//! the straight line between two cells where it is walkable.
//!
//! A grid search such as A* walks in eight headings only, so its routes
//! zig-zag where a person walks straight; comparing a learned planner with
//! it alone flatters the learned one. [`AnyAngle`] is Basic Theta* (Nash et
//! al., 2007) on the same walkable grid and profile: A* whose nodes may take
//! their parent's parent as parent when the straight segment between them is
//! clear, so a route is a polyline between cell centres turning only where
//! something is in the way.
//!
//! "Clear" is decided by [`traverse`], the supercover of a segment: every cell
//! the segment passes through, and both cells beside any corner it crosses
//! exactly, must be passable for the profile. So a segment never crosses a
//! blocked cell nor squeezes between two blocked cells touching at a corner,
//! the same rule as a grid step never cutting a blocked corner. The same walk
//! along a segment ([`segment_cells`]) turns a polyline in metres into the
//! 8-connected cells a walker crosses: the route's cells, the cells of a
//! recorded walk between two fixes, and the cells of the straight line.
//!
//! Profile costs: the cost of a segment is its length times the mean cost
//! factor of the cells it enters; cells a profile may not use are never
//! crossed. Turn costs (low vision) are not applied: an any-angle route turns
//! only at obstacles already.

use std::cmp::Ordering;
use std::collections::BinaryHeap;
use std::sync::Arc;

use super::{Connectivity, PlanError, Planned, Planner, Profile, Route};
use crate::site::{Cell, Site};

/// A point in cell units: cell `(x, y)` spans `[x, x+1) × [y, y+1)`.
pub type GridPoint = [f64; 2];

/// The centre of `cell` in cell units.
pub fn centre(cell: Cell) -> GridPoint {
    [f64::from(cell.x) + 0.5, f64::from(cell.y) + 0.5]
}

/// `p` (cell units) in world metres through the site's frame.
pub fn world_of_point(site: &Site, p: GridPoint) -> [f64; 2] {
    let (origin, step) = frame_steps(site);
    [
        origin[0] + (p[0] - 0.5) * step[0],
        origin[1] + (p[1] - 0.5) * step[1],
    ]
}

/// A point in world metres in cell units (the inverse of [`world_of_point`]).
pub fn point_of_world(site: &Site, w: [f64; 2]) -> GridPoint {
    let (origin, step) = frame_steps(site);
    [
        0.5 + (w[0] - origin[0]) / step[0],
        0.5 + (w[1] - origin[1]) / step[1],
    ]
}

/// The world position of cell (0, 0)'s centre and how far one cell moves it
/// along each axis (negative for a y axis pointing up): the site's frame is
/// axis-aligned, so that is all of it.
fn frame_steps(site: &Site) -> ([f64; 2], [f64; 2]) {
    let a = site.world_of_cell(Cell::new(0, 0));
    let b = site.world_of_cell(Cell::new(1, 1));
    (a, [b[0] - a[0], b[1] - a[1]])
}

/// The cells a segment passes through, in order, from the cell holding `a`
/// to the cell holding `b`.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Traversal {
    /// Cells in order, each a 4-neighbour of the one before except where the
    /// segment crosses a corner exactly (a diagonal step).
    pub cells: Vec<[i64; 2]>,
    /// The two cells beside each corner crossed exactly: the segment touches
    /// them too.
    pub corners: Vec<[i64; 2]>,
}

/// Amanatides–Woo traversal of the segment `a → b` (cell units). Cells may be
/// off the grid (negative or past its size); callers check.
pub fn traverse(a: GridPoint, b: GridPoint) -> Traversal {
    let mut out = Traversal::default();
    walk_segment(a, b, |cell, corner| {
        if corner {
            out.corners.push(cell);
        } else {
            out.cells.push(cell);
        }
        true
    });
    out
}

/// Whether `ok` holds for every cell [`traverse`] gives for `a → b`, its
/// cells and corners, asked in the order the segment meets them and no
/// further than the first refused: the checks of a line without the two
/// vectors (a line check runs per cell of a string-pulled route and per
/// segment of every served line).
pub(crate) fn touches_only(
    a: GridPoint,
    b: GridPoint,
    mut ok: impl FnMut([i64; 2]) -> bool,
) -> bool {
    walk_segment(a, b, |cell, _| ok(cell))
}

/// [`traverse`]'s walk, each cell handed to `visit` with whether it is one
/// of the two beside a corner crossed exactly, until `visit` says stop
/// (`false`, returned).
fn walk_segment(a: GridPoint, b: GridPoint, mut visit: impl FnMut([i64; 2], bool) -> bool) -> bool {
    const EPS: f64 = 1e-9;
    let mut cell = [a[0].floor() as i64, a[1].floor() as i64];
    let end = [b[0].floor() as i64, b[1].floor() as i64];
    let d = [b[0] - a[0], b[1] - a[1]];
    let step = [d[0].signum() as i64, d[1].signum() as i64];
    // Parameter t ∈ [0, 1] along the segment at which it next crosses an x
    // (resp. y) boundary, and how much t a whole cell takes.
    let next = |axis: usize| -> (f64, f64) {
        if d[axis].abs() < EPS {
            return (f64::INFINITY, f64::INFINITY);
        }
        let boundary = if d[axis] > 0.0 {
            a[axis].floor() + 1.0
        } else {
            a[axis].floor()
        };
        ((boundary - a[axis]) / d[axis], 1.0 / d[axis].abs())
    };
    let (mut t_x, dt_x) = next(0);
    let (mut t_y, dt_y) = next(1);
    if !visit(cell, false) {
        return false;
    }
    // At most one step per boundary crossed; the bound guards against float
    // trouble ever looping.
    let bound = (end[0] - cell[0]).unsigned_abs() + (end[1] - cell[1]).unsigned_abs() + 2;
    for _ in 0..bound {
        if cell == end {
            break;
        }
        if (t_x - t_y).abs() < EPS {
            if !visit([cell[0] + step[0], cell[1]], true)
                || !visit([cell[0], cell[1] + step[1]], true)
            {
                return false;
            }
            cell[0] += step[0];
            cell[1] += step[1];
            t_x += dt_x;
            t_y += dt_y;
        } else if t_x < t_y {
            cell[0] += step[0];
            t_x += dt_x;
        } else {
            cell[1] += step[1];
            t_y += dt_y;
        }
        if !visit(cell, false) {
            return false;
        }
    }
    true
}

/// `[x, y]` as a cell on `site`'s grid, when it is on it (a [`traverse`]
/// cell may be off it).
pub fn on_grid(site: &Site, [x, y]: [i64; 2]) -> Option<Cell> {
    let cell = Cell::new(u16::try_from(x).ok()?, u16::try_from(y).ok()?);
    site.contains(cell).then_some(cell)
}

/// Whether the segment between the centres of `a` and `b` crosses only cells
/// `passable` allows, corners included.
pub(crate) fn clear(site: &Site, a: Cell, b: Cell, passable: impl Fn(Cell) -> bool) -> bool {
    touches_only(centre(a), centre(b), |c| {
        on_grid(site, c).is_some_and(&passable)
    })
}

/// The 8-connected cells a walker crosses along the segment `a → b` (cell
/// units), first cell included: the supercover's cells made a walk by
/// [`extend_walk`]. `None` when the segment leaves the grid or crosses a cell
/// `passable` refuses.
pub fn segment_cells(
    site: &Site,
    a: GridPoint,
    b: GridPoint,
    passable: impl Fn(Cell) -> bool,
) -> Option<Vec<Cell>> {
    let ok = |c: Cell| site.walkable(c) && passable(c);
    let mut out: Vec<(Cell, f64)> = Vec::new();
    for raw in traverse(a, b).cells {
        let cell = on_grid(site, raw).filter(|&c| ok(c))?;
        if !extend_walk(&mut out, cell, 0.0, ok) {
            return None;
        }
    }
    Some(out.into_iter().map(|(c, _)| c).collect())
}

/// Appends `cell`, reached at time `t`, to an 8-connected walk along a
/// supercover (`cell` is the same cell as the last, a 4-neighbour, or a
/// diagonal neighbour across a corner crossed exactly). A repeat of the last
/// cell is dropped; a corner is taken diagonally where the step may cut it
/// and through the open side cell (`ok`) where it may not; an L of two steps
/// that one allowed diagonal step could replace is replaced by it, so a
/// slanted line is a thin staircase, as routes are. `false` when the corner
/// has no open side: the walk cannot go on.
pub fn extend_walk(
    out: &mut Vec<(Cell, f64)>,
    cell: Cell,
    t: f64,
    ok: impl Fn(Cell) -> bool,
) -> bool {
    if let Some(&(last, t_last)) = out.last() {
        if last == cell {
            return true;
        }
        if last.x != cell.x && last.y != cell.y && !Connectivity::Eight.step_ok_by(last, cell, &ok)
        {
            let Some(side) = [Cell::new(cell.x, last.y), Cell::new(last.x, cell.y)]
                .into_iter()
                .find(|&c| ok(c))
            else {
                return false;
            };
            out.push((side, (t_last + t) / 2.0));
        }
    }
    if out.len() >= 2 {
        let before = out[out.len() - 2].0;
        if before.chebyshev(cell) == 1 && Connectivity::Eight.step_ok_by(before, cell, &ok) {
            out.pop();
        }
    }
    out.push((cell, t));
    true
}

/// The cells of a polyline through cell centres or any points (cell units),
/// with loops cut out so no cell is visited twice; `None` as for
/// [`segment_cells`].
pub(crate) fn polyline_cells(
    site: &Site,
    points: &[GridPoint],
    passable: impl Fn(Cell) -> bool + Copy,
) -> Option<Vec<Cell>> {
    let mut cells: Vec<Cell> = Vec::new();
    for w in points.windows(2) {
        let leg = segment_cells(site, w[0], w[1], passable)?;
        let skip = usize::from(cells.last() == leg.first());
        cells.extend(&leg[skip..]);
    }
    if cells.is_empty() {
        cells.extend(
            points
                .first()
                .and_then(|&p| on_grid(site, [p[0].floor() as i64, p[1].floor() as i64])),
        );
    }
    Some(without_loops(cells, |&c| c))
}

/// Cuts every loop out of a walk of items at cells (`cell_of`): from a
/// cell's first visit straight on from its last.
pub fn without_loops<T>(items: Vec<T>, cell_of: impl Fn(&T) -> Cell) -> Vec<T> {
    let mut out: Vec<T> = Vec::with_capacity(items.len());
    let mut at: foldhash::HashMap<Cell, usize> = Default::default();
    for item in items {
        let c = cell_of(&item);
        if let Some(&i) = at.get(&c) {
            for dropped in out.drain(i + 1..) {
                at.remove(&cell_of(&dropped));
            }
        } else {
            at.insert(c, out.len());
            out.push(item);
        }
    }
    out
}

/// The turning points of a walk pulled taut: from each kept cell, straight on
/// to the farthest later cell the segment to which is [`clear`] for
/// `passable`. String-pulling a grid route is the cheap any-angle route: a
/// grid search plus one line check per cell, against Theta*'s line check per
/// expanded neighbour.
pub(crate) fn string_pulled(
    site: &Site,
    cells: &[Cell],
    passable: impl Fn(Cell) -> bool,
) -> Vec<Cell> {
    let Some(&first) = cells.first() else {
        return Vec::new();
    };
    let mut out = vec![first];
    let mut anchor = first;
    for w in cells.windows(2).skip(1) {
        // w[1] is the next cell; w[0] the last one still in sight.
        if !clear(site, anchor, w[1], &passable) {
            anchor = w[0];
            out.push(anchor);
        }
    }
    if cells.len() > 1 {
        out.push(*cells.last().expect("not empty"));
    }
    out
}

/// An any-angle route: the polyline (turning points, cell centres) and the
/// 8-connected cells along it.
#[derive(Clone, Debug, PartialEq)]
pub struct AnyAngleRoute {
    pub vertices: Vec<Cell>,
    pub route: Route,
}

impl AnyAngleRoute {
    /// Length in metres along the polyline.
    #[cfg(test)]
    pub(crate) fn length_m(&self, site: &Site) -> f64 {
        self.vertices
            .windows(2)
            .map(|w| w[0].distance(w[1]))
            .sum::<f64>()
            * site.cell_m
    }
}

/// Basic Theta* on the site's grid for a profile.
pub struct AnyAngle {
    site: Arc<Site>,
}

impl AnyAngle {
    pub fn new(site: Arc<Site>) -> Self {
        AnyAngle { site }
    }

    /// The straight segment from `from` to `to` when the profile may walk it
    /// (see [`clear`]).
    pub fn straight(&self, from: Cell, to: Cell, profile: Profile) -> Option<AnyAngleRoute> {
        let site = &*self.site;
        let passable = |c| profile.passable(site, c);
        if !(passable(from) && passable(to) && clear(site, from, to, passable)) {
            return None;
        }
        let cells = polyline_cells(site, &[centre(from), centre(to)], passable)?;
        Some(AnyAngleRoute {
            vertices: vec![from, to],
            route: Route { cells },
        })
    }

    /// The cheapest any-angle route for `profile`.
    pub fn route(
        &self,
        from: Cell,
        to: Cell,
        profile: Profile,
    ) -> Result<AnyAngleRoute, PlanError> {
        let site = &*self.site;
        let passable = |c: Cell| profile.passable(site, c);
        for c in [from, to] {
            if !passable(c) {
                return Err(PlanError::Blocked(c));
            }
        }
        let cells = site.open_cells();
        let n = cells.len();
        let index = |c: Cell| site.open_index(c).expect("passable cells are walkable");
        let (start, goal) = (index(from), index(to));
        // Cost of the segment between two cells' centres: its length times
        // the mean cost factor of the cells it enters.
        let segment_cost = |a: Cell, b: Cell| -> f64 {
            let t = traverse(centre(a), centre(b));
            let entered = &t.cells[1..];
            let factor = if entered.is_empty() {
                1.0
            } else {
                entered
                    .iter()
                    .filter_map(|&c| on_grid(site, c))
                    .map(|c| profile.cell_cost(site, c))
                    .sum::<f64>()
                    / entered.len() as f64
            };
            a.distance(b) * factor
        };
        let h = |c: Cell| c.distance(to);
        let mut g = vec![f64::INFINITY; n];
        let mut parent = vec![u32::MAX; n];
        let mut closed = vec![false; n];
        let mut heap = BinaryHeap::new();
        g[start] = 0.0;
        parent[start] = start as u32;
        heap.push(Open {
            f: h(from),
            g: 0.0,
            node: start as u32,
        });
        while let Some(Open { node, .. }) = heap.pop() {
            let s = node as usize;
            if s == goal {
                let mut vertices = vec![to];
                let mut at = s;
                while at != start {
                    at = parent[at] as usize;
                    vertices.push(cells[at]);
                }
                vertices.reverse();
                let points: Vec<GridPoint> = vertices.iter().map(|&c| centre(c)).collect();
                let route_cells =
                    polyline_cells(site, &points, passable).ok_or_else(|| PlanError::Invalid {
                        reason: "an any-angle segment crosses a cell it may not use".into(),
                    })?;
                let route = Route { cells: route_cells };
                route
                    .validate_for(site, from, to, Connectivity::Eight, profile)
                    .map_err(|reason| PlanError::Invalid { reason })?;
                return Ok(AnyAngleRoute { vertices, route });
            }
            if std::mem::replace(&mut closed[s], true) {
                continue;
            }
            let here = cells[s];
            let up = parent[s] as usize;
            for (dx, dy) in NEIGHBOURS {
                let (Some(x), Some(y)) =
                    (here.x.checked_add_signed(dx), here.y.checked_add_signed(dy))
                else {
                    continue;
                };
                let next = Cell::new(x, y);
                if !Connectivity::Eight.step_ok_by(here, next, passable) {
                    continue;
                }
                let j = index(next);
                if closed[j] {
                    continue;
                }
                // Path 2 of Theta*: straight from the parent when it is clear.
                let (from_node, cand) = if up != s && clear(site, cells[up], next, passable) {
                    (up, g[up] + segment_cost(cells[up], next))
                } else {
                    (s, g[s] + segment_cost(here, next))
                };
                if cand < g[j] - 1e-9 {
                    g[j] = cand;
                    parent[j] = from_node as u32;
                    heap.push(Open {
                        f: cand + h(next),
                        g: cand,
                        node: j as u32,
                    });
                }
            }
        }
        Err(PlanError::Unreachable { from, to })
    }
}

impl Planner for AnyAngle {
    fn mode(&self) -> &'static str {
        "anyangle"
    }

    fn model_version(&self) -> Option<&str> {
        None
    }

    fn plan(&self, from: Cell, to: Cell, profile: Profile) -> Result<Planned, PlanError> {
        let found = self.route(from, to, profile)?;
        Ok(Planned {
            line: Some(found.vertices.iter().map(|&c| centre(c)).collect()),
            ..Planned::searched(found.route)
        })
    }
}

const NEIGHBOURS: [(i16, i16); 8] = [
    (1, 0),
    (-1, 0),
    (0, 1),
    (0, -1),
    (1, 1),
    (1, -1),
    (-1, 1),
    (-1, -1),
];

#[derive(PartialEq)]
struct Open {
    f: f64,
    g: f64,
    node: u32,
}

impl Eq for Open {}

impl Ord for Open {
    fn cmp(&self, other: &Self) -> Ordering {
        // Min-heap on f; among equal f the deeper node first, then by index
        // for determinism.
        other
            .f
            .total_cmp(&self.f)
            .then_with(|| self.g.total_cmp(&other.g))
            .then_with(|| other.node.cmp(&self.node))
    }
}

impl PartialOrd for Open {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::RouteErrorCode;

    fn site(map: &str) -> Arc<Site> {
        Arc::new(Site::of_map(map))
    }

    proptest::proptest! {
        /// The line check that stops early answers as the full traversal
        /// does, whatever the segment and whichever cells are refused.
        #[test]
        fn a_line_check_is_the_traversal_checked(
            a in proptest::array::uniform2(-2.0f64..12.0),
            b in proptest::array::uniform2(-2.0f64..12.0),
            centres in proptest::bool::ANY,
            refused in proptest::collection::hash_set((-2i64..12, -2i64..12), 0..40),
        ) {
            // Centre to centre (exact corners) as well as anywhere.
            let (a, b) = if centres {
                (a.map(|v| v.floor() + 0.5), b.map(|v| v.floor() + 0.5))
            } else {
                (a, b)
            };
            let ok = |[x, y]: [i64; 2]| !refused.contains(&(x, y));
            let t = traverse(a, b);
            proptest::prop_assert_eq!(
                touches_only(a, b, ok),
                t.cells.iter().chain(&t.corners).all(|&c| ok(c))
            );
        }
    }

    #[test]
    fn traversal_is_the_supercover() {
        // Three x boundaries and two y boundaries, none at a corner.
        let t = traverse([0.5, 0.5], [3.5, 2.5]);
        assert_eq!(
            t.cells,
            vec![[0, 0], [1, 0], [1, 1], [2, 1], [2, 2], [3, 2]]
        );
        assert!(t.corners.is_empty());
        // Slope 1/3 from centre to centre crosses the corner at (2, 1).
        let t = traverse([0.5, 0.5], [3.5, 1.5]);
        assert_eq!(t.cells, vec![[0, 0], [1, 0], [2, 1], [3, 1]]);
        assert_eq!(t.corners, vec![[2, 0], [1, 1]]);
        // A 45° line goes through corners: both side cells are touched.
        let t = traverse([0.5, 0.5], [2.5, 2.5]);
        assert_eq!(t.cells, vec![[0, 0], [1, 1], [2, 2]]);
        assert_eq!(t.corners, vec![[1, 0], [0, 1], [2, 1], [1, 2]]);
        // Backwards and vertical.
        let t = traverse([2.5, 3.5], [2.5, 0.5]);
        assert_eq!(t.cells, vec![[2, 3], [2, 2], [2, 1], [2, 0]]);
    }

    #[test]
    fn segment_cells_are_a_thin_walkable_staircase() {
        let s = site("#####\n#####\n#####");
        let cells = segment_cells(&s, [0.5, 0.5], [4.5, 2.5], |_| true).unwrap();
        assert_eq!(cells.first(), Some(&Cell::new(0, 0)));
        assert_eq!(cells.last(), Some(&Cell::new(4, 2)));
        // Two diagonal steps replace two L's: 5 cells for 4 columns.
        assert_eq!(cells.len(), 5, "{cells:?}");
        Route { cells }
            .validate(&s, Cell::new(0, 0), Cell::new(4, 2), Connectivity::Eight)
            .unwrap();
        // Through a blocked cell: none.
        let walled = site("#####\n##.##\n#####");
        assert!(segment_cells(&walled, [0.5, 1.5], [4.5, 1.5], |_| true).is_none());
    }

    #[test]
    fn theta_star_goes_straight_in_the_open_and_bends_at_obstacles() {
        let s = site("########\n########\n########\n########");
        let p = AnyAngle::new(s.clone());
        let (a, b) = (Cell::new(0, 0), Cell::new(7, 3));
        let r = p.route(a, b, Profile::Default).unwrap();
        assert_eq!(r.vertices, vec![a, b], "one straight segment");
        assert!((r.length_m(&s) - 58f64.sqrt()).abs() < 1e-9);
        r.route.validate(&s, a, b, Connectivity::Eight).unwrap();
        // A wall with a gap at the bottom: the route turns at the gap.
        let s = site("###.####\n###.####\n###.####\n########");
        let p = AnyAngle::new(s.clone());
        let (a, b) = (Cell::new(0, 0), Cell::new(7, 0));
        let r = p.route(a, b, Profile::Default).unwrap();
        assert!(r.vertices.len() >= 3, "{:?}", r.vertices);
        r.route.validate(&s, a, b, Connectivity::Eight).unwrap();
        for w in r.vertices.windows(2) {
            assert!(clear(&s, w[0], w[1], |c| s.walkable(c)), "{w:?}");
        }
        // Shorter than the 8-connected shortest route, never shorter than
        // the straight line.
        let grid = super::super::astar::AStar::new(s.clone(), Connectivity::Eight)
            .plan(a, b, Profile::Default)
            .unwrap();
        assert!(r.length_m(&s) <= grid.route.length_m(&s) + 1e-9);
        assert!(r.length_m(&s) >= 7.0);
        assert!(p.straight(a, b, Profile::Default).is_none());
        assert!(
            p.straight(Cell::new(0, 3), Cell::new(7, 3), Profile::Default)
                .is_some()
        );
    }

    #[test]
    fn profiles_keep_off_what_they_may_not_use() {
        // Stairs across the middle row except one end: a wheelchair goes round.
        let s = site("#####\nssss#\n#####");
        let p = AnyAngle::new(s.clone());
        let (a, b) = (Cell::new(0, 0), Cell::new(0, 2));
        let walk = p.route(a, b, Profile::Default).unwrap();
        assert_eq!(walk.vertices, vec![a, b]);
        let wheel = p.route(a, b, Profile::Wheelchair).unwrap();
        wheel
            .route
            .validate_for(&s, a, b, Connectivity::Eight, Profile::Wheelchair)
            .unwrap();
        assert!(wheel.route.cells.contains(&Cell::new(4, 1)));
        assert_eq!(
            p.route(Cell::new(0, 1), b, Profile::Wheelchair)
                .unwrap_err()
                .code(),
            RouteErrorCode::BlockedCell
        );
        let closed = site("#.#");
        assert_eq!(
            AnyAngle::new(closed)
                .route(Cell::new(0, 0), Cell::new(2, 0), Profile::Default)
                .unwrap_err()
                .code(),
            RouteErrorCode::Unreachable
        );
    }

    #[test]
    fn loops_are_cut() {
        let c = |x, y| Cell::new(x, y);
        let walk = vec![c(0, 0), c(1, 0), c(1, 1), c(0, 1), c(1, 0), c(2, 0)];
        assert_eq!(without_loops(walk, |&c| c), vec![c(0, 0), c(1, 0), c(2, 0)]);
    }

    #[test]
    fn string_pulling_keeps_only_the_corners_and_points_map_to_metres_and_back() {
        let text = "name = \"t\"\ncell_m = 0.5\norigin_m = [2.0, 9.0]\ny_axis = \"up\"\nmap = '''\n#####\n#....\n#####\n'''\n";
        let s = Site::parse(text, std::path::Path::new("t.toml")).unwrap();
        // Down the left column, then along the bottom row.
        let walk: Vec<Cell> = [
            (4, 0),
            (3, 0),
            (2, 0),
            (1, 0),
            (0, 0),
            (0, 1),
            (0, 2),
            (1, 2),
            (2, 2),
            (3, 2),
            (4, 2),
        ]
        .map(|(x, y)| Cell::new(x, y))
        .to_vec();
        let taut = string_pulled(&s, &walk, |c| s.walkable(c));
        assert_eq!(taut.first(), Some(&Cell::new(4, 0)));
        assert_eq!(taut.last(), Some(&Cell::new(4, 2)));
        assert!(taut.len() <= 4, "{taut:?}");
        for w in taut.windows(2) {
            assert!(clear(&s, w[0], w[1], |c| s.walkable(c)), "{taut:?}");
        }
        let p = [1.25, 2.75];
        let w = world_of_point(&s, p);
        assert!(
            (w[0] - (2.0 + 1.25 * 0.5)).abs() < 1e-9 && (w[1] - (9.0 - 2.75 * 0.5)).abs() < 1e-9,
            "{w:?}"
        );
        let back = point_of_world(&s, w);
        assert!((back[0] - p[0]).abs() < 1e-9 && (back[1] - p[1]).abs() < 1e-9);
    }
}
