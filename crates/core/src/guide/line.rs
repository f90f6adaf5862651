//! A route as the line its walker was given (the reply's `line`,
//! [`crate::plan::ServedLine`]) and its cells, and the projection of a point
//! onto the line: how far along the route a fix stands, how far from it,
//! and which way the route goes there.
//!
//! The cells are held as a chain code: the first cell, then each step to a
//! neighbouring cell as one of eight directions in half a byte. Every
//! guided session holds its route for as long as it lasts, so the route
//! costs half a byte a cell instead of four (a served route only steps to
//! neighbours: [`crate::plan::Route::validate_for`]). A line through the
//! cells' centres (A*, the GAN modes) is read off the chain code; only a
//! line the planner drew is held, as its turning points.

use crate::plan::anyangle::GridPoint;
use crate::plan::instructions::{Maneuver, maneuvers_along};
use crate::plan::lines::nearest_on_segment;
use crate::plan::{Profile, Route, ServedLine};
use crate::site::{Cell, Site};

/// The eight steps to a neighbouring cell, by their code.
const STEPS: [(i32, i32); 8] = [
    (1, 0),
    (1, 1),
    (0, 1),
    (-1, 1),
    (-1, 0),
    (-1, -1),
    (0, -1),
    (1, -1),
];

#[derive(Clone, Debug)]
pub struct RouteLine {
    start: Cell,
    end: Cell,
    /// The steps from `start`, two to a byte (the low half first).
    steps: Vec<u8>,
    step_count: u32,
    /// The turning points of a line the planner drew, cell units (f32: a
    /// millimetre on any building's grid); `None` for the cells' centres,
    /// which the steps hold already (a long staircase of cells turns at
    /// nearly every cell: its corners would cost 8 bytes a cell).
    drawn: Option<Box<[[f32; 2]]>>,
    /// Metres from the start to the end along the line. Distances to each
    /// vertex are summed as the line is walked through rather than kept: a
    /// session's state stays small.
    length_m: f32,
}

impl RouteLine {
    /// `route` walked along its cells' centres.
    #[cfg(test)]
    pub(crate) fn new(site: &Site, route: &Route) -> RouteLine {
        RouteLine::along(site, route, &ServedLine::of_cells(route).points)
    }

    /// `route` walked along `line` (cell units, through its cells). A step
    /// between cells that are not neighbours (never in a served route) is
    /// held as neighbour steps towards the next cell: the diagonal first,
    /// then straight.
    pub fn along(site: &Site, route: &Route, line: &[GridPoint]) -> RouteLine {
        let start = *route.cells.first().expect("a route has cells");
        let drawn = (line != ServedLine::of_cells(route).points)
            .then(|| line.iter().map(|p| [p[0] as f32, p[1] as f32]).collect());
        let mut line = RouteLine {
            start,
            end: start,
            steps: Vec::new(),
            step_count: 0,
            drawn,
            length_m: 0.0,
        };
        for &next in &route.cells[1..] {
            while line.end != next {
                let (dx, dy) = (
                    (i32::from(next.x) - i32::from(line.end.x)).signum(),
                    (i32::from(next.y) - i32::from(line.end.y)).signum(),
                );
                let code = STEPS.iter().position(|&s| s == (dx, dy)).expect("a step") as u8;
                if line.step_count.is_multiple_of(2) {
                    line.steps.push(code);
                } else {
                    *line.steps.last_mut().expect("pushed") |= code << 4;
                }
                line.step_count += 1;
                line.end = step(line.end, code);
            }
        }
        line.steps.shrink_to_fit();
        line.length_m = line.segments(site).last().map_or(0.0, |s| s.3) as f32;
        line
    }

    /// The route's cells, from the start.
    pub(crate) fn cells(&self) -> impl Iterator<Item = Cell> + '_ {
        std::iter::once(self.start).chain(self.codes().scan(self.start, |at, code| {
            *at = step(*at, code);
            Some(*at)
        }))
    }

    /// Each cell of the route with the cell `ahead_m` further along it
    /// (the nearest cell to that point; the destination for cells nearer
    /// it than that): where a walker following the route would be.
    pub(crate) fn ahead(&self, site: &Site, ahead_m: f64) -> Vec<(Cell, Cell)> {
        let mut along = 0.0;
        let mut last = self.start;
        let cells: Vec<(Cell, f64)> = self
            .cells()
            .map(|c| {
                along += last.distance(c) * site.cell_m;
                last = c;
                (c, along)
            })
            .collect();
        let mut moves = Vec::with_capacity(cells.len());
        let mut j = 0;
        for (i, &(cell, at)) in cells.iter().enumerate() {
            let target = at + ahead_m;
            j = j.max(i);
            while j + 1 < cells.len() && cells[j + 1].1 <= target {
                j += 1;
            }
            // The nearer of the cells either side of the point.
            let to = match cells.get(j + 1) {
                Some(&(next, next_at)) if next_at - target < target - cells[j].1 => next,
                _ => cells[j].0,
            };
            if to != cell {
                moves.push((cell, to));
            }
        }
        moves
    }

    pub(crate) fn length_m(&self) -> f64 {
        f64::from(self.length_m)
    }

    /// The cell the route ends at.
    pub fn destination(&self) -> Cell {
        self.end
    }

    /// Bytes held on the heap.
    pub(crate) fn heap_bytes(&self) -> usize {
        self.steps.capacity()
            + self
                .drawn
                .as_ref()
                .map_or(0, |d| std::mem::size_of_val(&**d))
    }

    /// The route's maneuvers for a walker with `profile` following the
    /// line.
    pub(crate) fn maneuvers(&self, site: &Site, profile: Profile) -> Vec<Maneuver> {
        let route = Route {
            cells: self.cells().collect(),
        };
        maneuvers_along(site, &route, &self.points(), profile)
    }

    /// The line's turning points, cell units.
    pub(crate) fn points(&self) -> Vec<GridPoint> {
        match &self.drawn {
            Some(drawn) => drawn
                .iter()
                .map(|p| [f64::from(p[0]), f64::from(p[1])])
                .collect(),
            None => {
                ServedLine::of_cells(&Route {
                    cells: self.cells().collect(),
                })
                .points
            }
        }
    }

    /// The steps' codes, from the start.
    fn codes(&self) -> impl Iterator<Item = u8> + '_ {
        (0..self.step_count as usize).map(|i| (self.steps[i / 2] >> (4 * (i % 2))) & 0xF)
    }

    /// Each segment of the line: its ends in metres and metres from the
    /// start to them. A line through the cells' centres is read off the
    /// steps, a straight run of them as one segment (projecting on it is
    /// projecting on its steps, for a fraction of the work).
    fn segments<'a>(
        &'a self,
        site: &'a Site,
    ) -> impl Iterator<Item = ((f64, f64), (f64, f64), f64, f64)> + 'a {
        let metres = |p: [f32; 2]| {
            let [x, y] =
                crate::plan::anyangle::world_of_point(site, [f64::from(p[0]), f64::from(p[1])]);
            (x, y)
        };
        let drawn = self.drawn.as_deref();
        let mut codes = self.codes().peekable();
        let (mut from, mut vertex, mut along) = (self.start, 0, 0.0);
        std::iter::from_fn(move || {
            let (a, b) = match drawn {
                Some(points) => {
                    let ends = points.get(vertex..vertex + 2)?;
                    vertex += 1;
                    (metres(ends[0]), metres(ends[1]))
                }
                None => {
                    let code = codes.next()?;
                    let mut to = step(from, code);
                    while let Some(c) = codes.next_if_eq(&code) {
                        to = step(to, c);
                    }
                    let a = std::mem::replace(&mut from, to);
                    (site.metres(a), site.metres(to))
                }
            };
            let start = along;
            along += (b.0 - a.0).hypot(b.1 - a.1);
            Some((a, b, start, along))
        })
    }

    /// Distance from the point `(x, y)` (metres) to the route, and the
    /// progress it stands for: its projection on the nearest segment that
    /// does not end more than `back_m` behind `progress_m` (so a route
    /// passing near itself does not pull the walker back to its start).
    pub fn project(
        &self,
        site: &Site,
        (x, y): (f64, f64),
        progress_m: f64,
        back_m: f64,
    ) -> (f64, f64) {
        if self.step_count == 0 {
            let (cx, cy) = site.metres(self.start);
            return ((cx - x).hypot(cy - y), 0.0);
        }
        let mut nearest = f64::INFINITY;
        let mut progress = (f64::INFINITY, progress_m);
        for ((ax, ay), (bx, by), a0, a1) in self.segments(site) {
            let (d, f) = nearest_on_segment([x, y], [ax, ay], [bx, by]);
            nearest = nearest.min(d);
            if a1 >= progress_m - back_m && d < progress.0 {
                progress = (d, a0 + f * (a1 - a0));
            }
        }
        (nearest, progress.1)
    }

    /// Which way the route goes `along_m` from its start: the unit vector
    /// (metres east, metres along the world's y) of the segment there, the
    /// one leaving a corner when `along_m` is at one.
    pub(crate) fn direction(&self, site: &Site, along_m: f64) -> (f64, f64) {
        let unit = |((ax, ay), (bx, by)): ((f64, f64), (f64, f64))| {
            let len = (bx - ax).hypot(by - ay).max(f64::EPSILON);
            ((bx - ax) / len, (by - ay) / len)
        };
        let mut last = None;
        for (a, b, _, a1) in self.segments(site) {
            last = Some((a, b));
            if a1 > along_m {
                return unit((a, b));
            }
        }
        last.map_or((0.0, 0.0), unit)
    }
}

/// The cell one step of `code` from `at`.
fn step(at: Cell, code: u8) -> Cell {
    let (dx, dy) = STEPS[usize::from(code)];
    Cell::new((i32::from(at.x) + dx) as u16, (i32::from(at.y) + dy) as u16)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn projects_points_and_knows_the_way_at_each_corner() {
        let text = "name = \"t\"\ncell_m = 2.0\nmap = '''\n####\n####\n'''\n";
        let site = Site::parse(text, Path::new("t.toml")).unwrap();
        // East 3 cells, then south 1: 6 m then 2 m.
        let line = RouteLine::new(
            &site,
            &Route {
                cells: [(0, 0), (1, 0), (2, 0), (3, 0), (3, 1)]
                    .map(|(x, y)| Cell::new(x, y))
                    .to_vec(),
            },
        );
        assert_eq!(line.length_m(), 8.0);
        let (x0, y0) = site.metres(Cell::new(0, 0));
        let (off, along) = line.project(&site, (x0 + 3.0, y0 + 0.5), 0.0, 3.0);
        assert!((off - 0.5).abs() < 1e-9 && (along - 3.0).abs() < 1e-9);
        let east = line.direction(&site, 1.0);
        let corner = line.direction(&site, 6.0);
        assert!((east.0 - 1.0).abs() < 1e-9 && east.1.abs() < 1e-9);
        // At the corner, the way on (along the world's y, whichever way
        // the site's y axis runs).
        assert!(corner.0.abs() < 1e-9 && (corner.1.abs() - 1.0).abs() < 1e-9);
        assert_eq!(line.direction(&site, 99.0), corner);
    }

    #[test]
    fn a_drawn_line_is_what_points_are_projected_on() {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n####\n####\n####\n####\n'''\n";
        let site = Site::parse(text, Path::new("t.toml")).unwrap();
        let route = Route {
            cells: [(0, 0), (1, 1), (2, 2), (3, 3)]
                .map(|(x, y)| Cell::new(x, y))
                .to_vec(),
        };
        let drawn = [[0.5, 0.5], [1.5, 2.5], [3.5, 3.5]];
        let line = RouteLine::along(&site, &route, &drawn);
        let expected = 5f64.sqrt() * 2.0;
        assert!((line.length_m() - expected).abs() < 1e-5);
        assert_eq!(line.points(), drawn.to_vec());
        assert_eq!(line.heap_bytes(), 2 + 3 * 8);
        // The drawn line's bend, not the diagonal of cells, is on the line.
        let bend = site.metres(Cell::new(1, 2));
        let (off, along) = line.project(&site, bend, 0.0, 3.0);
        assert!(off < 1e-6 && (along - 5f64.sqrt()).abs() < 1e-5);
        // The cells' own line is not held twice.
        let cells = RouteLine::along(&site, &route, &[[0.5, 0.5], [3.5, 3.5]]);
        assert_eq!(cells.heap_bytes(), 2);
    }

    #[test]
    fn pairs_each_cell_with_the_one_a_walk_ahead() {
        let text = "name = \"t\"\ncell_m = 2.0\nmap = '''\n####\n####\n'''\n";
        let site = Site::parse(text, Path::new("t.toml")).unwrap();
        let cells = [(0, 0), (1, 0), (2, 0), (3, 0), (3, 1)].map(|(x, y)| Cell::new(x, y));
        let line = RouteLine::new(
            &site,
            &Route {
                cells: cells.to_vec(),
            },
        );
        // 4.5 m ahead on 2 m cells: two cells on (4 m is nearer than 6 m),
        // and the destination for those less than that from it.
        let moves = line.ahead(&site, 4.5);
        assert_eq!(
            moves,
            vec![
                (cells[0], cells[2]),
                (cells[1], cells[3]),
                (cells[2], cells[4]),
                (cells[3], cells[4]),
            ]
        );
        // Less than half a cell: nobody moves.
        assert!(line.ahead(&site, 0.9).is_empty());
    }

    #[test]
    fn holds_the_cells_in_half_a_byte_each() {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n######\n######\n######\n'''\n";
        let site = Site::parse(text, Path::new("t.toml")).unwrap();
        // Six of the directions, and a step over a cell (held as two).
        let cells = [
            (0, 0),
            (1, 1),
            (2, 2),
            (3, 1),
            (4, 0),
            (5, 0),
            (5, 1),
            (4, 2),
            (3, 2),
            (1, 2),
        ]
        .map(|(x, y)| Cell::new(x, y))
        .to_vec();
        let route = Route {
            cells: cells.clone(),
        };
        let line = RouteLine::new(&site, &route);
        let mut walked = cells.clone();
        walked.insert(9, Cell::new(2, 2));
        assert_eq!(line.cells().collect::<Vec<_>>(), walked);
        assert_eq!(line.destination(), Cell::new(1, 2));
        assert!((line.length_m() - route.length_m(&site)).abs() < 1e-6);
        assert_eq!(line.heap_bytes(), 5, "ten steps");
        // The other two.
        let back = [(1, 2), (0, 1), (0, 0), (1, 0)]
            .map(|(x, y)| Cell::new(x, y))
            .to_vec();
        let line = RouteLine::new(
            &site,
            &Route {
                cells: back.clone(),
            },
        );
        assert_eq!(line.cells().collect::<Vec<_>>(), back);
    }
}
