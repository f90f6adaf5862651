//! A route as a polyline of cell centres in metres, and the projection of a
//! point onto it: how far along the route a fix stands, how far from it,
//! and which way the route goes there.

use crate::plan::Route;
use crate::site::{Cell, Site};

#[derive(Clone, Debug)]
pub(crate) struct RouteLine {
    cells: Vec<Cell>,
    /// Metres from the start to the end (f32: millimetres on any
    /// building's routes, and every guided session holds one). Distances
    /// to each cell are summed as the route is walked through rather than
    /// kept: a session's state stays small.
    length_m: f32,
}

impl RouteLine {
    pub(crate) fn new(site: &Site, route: &Route) -> RouteLine {
        RouteLine {
            cells: route.cells.clone(),
            length_m: route.length_m(site) as f32,
        }
    }

    pub(crate) fn cells(&self) -> &[Cell] {
        &self.cells
    }

    pub(crate) fn length_m(&self) -> f64 {
        f64::from(self.length_m)
    }

    /// The cell the route ends at.
    pub(crate) fn destination(&self) -> Cell {
        *self.cells.last().expect("a route has cells")
    }

    /// Bytes held on the heap.
    pub(crate) fn heap_bytes(&self) -> usize {
        self.cells.capacity() * std::mem::size_of::<Cell>()
    }

    /// Each segment: its ends in metres and metres from the start to them.
    fn segments<'a>(
        &'a self,
        site: &'a Site,
    ) -> impl Iterator<Item = ((f64, f64), (f64, f64), f64, f64)> + 'a {
        let mut along = 0.0;
        self.cells.windows(2).map(move |w| {
            let start = along;
            along += w[0].distance(w[1]) * site.cell_m;
            (site.metres(w[0]), site.metres(w[1]), start, along)
        })
    }

    /// Distance from the point `(x, y)` (metres) to the route, and the
    /// progress it stands for: its projection on the nearest segment that
    /// does not end more than `back_m` behind `progress_m` (so a route
    /// passing near itself does not pull the walker back to its start).
    pub(crate) fn project(
        &self,
        site: &Site,
        (x, y): (f64, f64),
        progress_m: f64,
        back_m: f64,
    ) -> (f64, f64) {
        if self.cells.len() == 1 {
            let (cx, cy) = site.metres(self.cells[0]);
            return ((cx - x).hypot(cy - y), 0.0);
        }
        let mut nearest = f64::INFINITY;
        let mut progress = (f64::INFINITY, progress_m);
        for ((ax, ay), (bx, by), a0, a1) in self.segments(site) {
            let (dx, dy) = (bx - ax, by - ay);
            let len2 = dx * dx + dy * dy;
            let f = if len2 > 0.0 {
                (((x - ax) * dx + (y - ay) * dy) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let d = (ax + f * dx - x).hypot(ay + f * dy - y);
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
}
