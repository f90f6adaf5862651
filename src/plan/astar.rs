//! Shortest walkable paths on the site grid: the baseline planner, and the
//! search that later planners build on (with a per-cell cost factor).

use std::cmp::Ordering;
use std::collections::BinaryHeap;
use std::sync::Arc;

use super::{Connectivity, PlanError, Planner, Route};
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

    fn plan(&self, from: Cell, to: Cell) -> Result<Route, PlanError> {
        search(&self.site, self.connectivity, from, to, |_| 1.0)
    }
}

#[derive(PartialEq)]
struct Entry {
    f: f64,
    open: u32,
}

impl Eq for Entry {}

impl Ord for Entry {
    fn cmp(&self, other: &Self) -> Ordering {
        // Min-heap on f; ties broken by index for determinism.
        other
            .f
            .total_cmp(&self.f)
            .then_with(|| other.open.cmp(&self.open))
    }
}

impl PartialOrd for Entry {
    fn partial_cmp(&self, other: &Self) -> Option<Ordering> {
        Some(self.cmp(other))
    }
}

/// A* from `from` to `to` over walkable cells. Entering a cell costs the step
/// length (1 or √2) times `cell_cost(cell)`, which must be at least `min_cost`
/// of 1.0 scaled: pass factors ≥ 1 so the octile heuristic stays admissible.
pub fn search(
    site: &Site,
    connectivity: Connectivity,
    from: Cell,
    to: Cell,
    cell_cost: impl Fn(Cell) -> f64,
) -> Result<Route, PlanError> {
    for c in [from, to] {
        if !site.walkable(c) {
            return Err(PlanError::Blocked(c));
        }
    }
    let cells = site.open_cells();
    let n = cells.len();
    let start = site.open_index(from).expect("walkable") as u32;
    let goal = site.open_index(to).expect("walkable") as u32;
    let mut g = vec![f64::INFINITY; n];
    let mut came_from = vec![u32::MAX; n];
    let mut closed = vec![false; n];
    let mut heap = BinaryHeap::new();
    g[start as usize] = 0.0;
    heap.push(Entry {
        f: heuristic(from, to, connectivity),
        open: start,
    });
    while let Some(Entry { open, .. }) = heap.pop() {
        if open == goal {
            let mut path = vec![to];
            let mut at = goal;
            while at != start {
                at = came_from[at as usize];
                path.push(cells[at as usize]);
            }
            path.reverse();
            return Ok(Route { cells: path });
        }
        if std::mem::replace(&mut closed[open as usize], true) {
            continue;
        }
        let here = cells[open as usize];
        for (dx, dy) in NEIGHBOURS {
            let (Some(x), Some(y)) = (here.x.checked_add_signed(dx), here.y.checked_add_signed(dy))
            else {
                continue;
            };
            let next = Cell::new(x, y);
            if !connectivity.step_ok(site, here, next) {
                continue;
            }
            let j = site.open_index(next).expect("step_ok checks walkable");
            let step = if dx != 0 && dy != 0 {
                std::f64::consts::SQRT_2
            } else {
                1.0
            };
            let cand = g[open as usize] + step * cell_cost(next);
            if cand < g[j] {
                g[j] = cand;
                came_from[j] = open;
                heap.push(Entry {
                    f: cand + heuristic(next, to, connectivity),
                    open: j as u32,
                });
            }
        }
    }
    Err(PlanError::Unreachable { from, to })
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
    use std::path::Path;

    fn site(map: &str) -> Arc<Site> {
        let text = format!("name = \"t\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n");
        Arc::new(Site::parse(&text, Path::new("t.toml")).unwrap())
    }

    #[test]
    fn goes_around_walls_without_cutting_corners() {
        let s = site("###\n#.#\n###");
        let planner = AStar::new(s.clone(), Connectivity::Eight);
        let route = planner.plan(Cell::new(0, 0), Cell::new(2, 2)).unwrap();
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
            .plan(Cell::new(0, 0), Cell::new(2, 2))
            .unwrap();
        assert_eq!(route.cells.len(), 3);
        let four = AStar::new(s.clone(), Connectivity::Four)
            .plan(Cell::new(0, 0), Cell::new(2, 2))
            .unwrap();
        assert_eq!(four.cells.len(), 5);
        four.validate(&s, Cell::new(0, 0), Cell::new(2, 2), Connectivity::Four)
            .unwrap();
    }

    #[test]
    fn reports_unreachable_and_blocked() {
        let s = site("#.#");
        let p = AStar::new(s, Connectivity::Eight);
        assert_eq!(
            p.plan(Cell::new(0, 0), Cell::new(2, 0)).unwrap_err().code(),
            "unreachable"
        );
        assert_eq!(
            p.plan(Cell::new(0, 0), Cell::new(1, 0)).unwrap_err().code(),
            "blocked_cell"
        );
    }
}
