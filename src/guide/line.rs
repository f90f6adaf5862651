//! A route as a polyline of cell centres in metres, with the distance from
//! its start to each cell, and the projection of a point onto it: how far
//! along the route a fix stands and how far from it.

use crate::plan::Route;
use crate::site::{Cell, Site};

#[derive(Clone, Debug)]
pub struct RouteLine {
    cells: Vec<Cell>,
    /// Metres from the start to each cell (f32: half the state of f64, and
    /// millimetres on any building's routes).
    along: Vec<f32>,
}

impl RouteLine {
    pub fn new(site: &Site, route: &Route) -> RouteLine {
        let mut along = Vec::with_capacity(route.cells.len());
        let mut metres = 0.0;
        for (i, &c) in route.cells.iter().enumerate() {
            if i > 0 {
                metres += route.cells[i - 1].distance(c) * site.cell_m;
            }
            along.push(metres as f32);
        }
        RouteLine {
            cells: route.cells.clone(),
            along,
        }
    }

    pub fn cells(&self) -> &[Cell] {
        &self.cells
    }

    pub fn length_m(&self) -> f64 {
        self.along.last().map_or(0.0, |&m| f64::from(m))
    }

    /// The cell the route ends at.
    pub fn destination(&self) -> Cell {
        *self.cells.last().expect("a route has cells")
    }

    /// Bytes held on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.cells.capacity() * std::mem::size_of::<Cell>()
            + self.along.capacity() * std::mem::size_of::<f32>()
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
        let centre = |i: usize| site.metres(self.cells[i]);
        if self.cells.len() == 1 {
            let (cx, cy) = centre(0);
            return ((cx - x).hypot(cy - y), 0.0);
        }
        let mut nearest = f64::INFINITY;
        let mut progress = (f64::INFINITY, progress_m);
        for i in 0..self.cells.len() - 1 {
            let ((ax, ay), (bx, by)) = (centre(i), centre(i + 1));
            let (dx, dy) = (bx - ax, by - ay);
            let len2 = dx * dx + dy * dy;
            let f = if len2 > 0.0 {
                (((x - ax) * dx + (y - ay) * dy) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let d = (ax + f * dx - x).hypot(ay + f * dy - y);
            nearest = nearest.min(d);
            let (a0, a1) = (f64::from(self.along[i]), f64::from(self.along[i + 1]));
            if a1 >= progress_m - back_m && d < progress.0 {
                progress = (d, a0 + f * (a1 - a0));
            }
        }
        (nearest, progress.1)
    }
}
