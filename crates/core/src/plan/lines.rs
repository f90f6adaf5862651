//! How alike two lines in metres are: dynamic time warping and the discrete
//! Fréchet distance, on both lines resampled at the same spacing so that
//! neither measure depends on how densely a line was drawn (a route's three
//! vertices and a walk's sixty cells cover the same ground). Used to judge
//! routes against people's walks (`gangway eval planning`, re-exported by
//! `eval::similarity`) and by training, which cross-validates the desire
//! lines by the same measure (`train::desire`): it sits here, below both.

use crate::site::{Cell, Site};

/// A line through points in metres, in walking order.
#[derive(Clone, Debug, PartialEq)]
pub struct Polyline(pub Vec<[f64; 2]>);

impl Polyline {
    /// The line through the centres of `cells` on `site`.
    pub fn of_cells(site: &Site, cells: &[Cell]) -> Polyline {
        Polyline(
            cells
                .iter()
                .map(|&c| {
                    let (x, y) = site.metres(c);
                    [x, y]
                })
                .collect(),
        )
    }

    /// Length in metres.
    pub fn length_m(&self) -> f64 {
        self.0.windows(2).map(|w| dist(w[0], w[1])).sum()
    }

    /// Points every `step_m` metres along the line, from its first point to
    /// its last (both kept), so two lines are compared at the same density.
    pub(crate) fn resampled(&self, step_m: f64) -> Vec<[f64; 2]> {
        let Some(&first) = self.0.first() else {
            return Vec::new();
        };
        let mut out = vec![first];
        // Distance still to walk before the next sample.
        let mut until_next = step_m;
        for w in self.0.windows(2) {
            let (a, b) = (w[0], w[1]);
            let len = dist(a, b);
            let mut along = 0.0;
            while len - along >= until_next {
                along += until_next;
                let t = along / len;
                out.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
                until_next = step_m;
            }
            until_next -= len - along;
        }
        let last = *self.0.last().expect("not empty");
        if out.last().is_none_or(|&p| dist(p, last) > 1e-9) {
            out.push(last);
        }
        out
    }
}

/// The point of the segment `a`–`b` nearest to `p`: its distance from `p`
/// and how far along the segment it is (0 at `a`, 1 at `b`). Guidance
/// projects fixes on a route's line with it, and instructions the route's
/// cells.
pub(crate) fn nearest_on_segment(p: [f64; 2], a: [f64; 2], b: [f64; 2]) -> (f64, f64) {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len2 = dx * dx + dy * dy;
    let f = if len2 > 0.0 {
        (((p[0] - a[0]) * dx + (p[1] - a[1]) * dy) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    ((a[0] + f * dx - p[0]).hypot(a[1] + f * dy - p[1]), f)
}

fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

/// How far apart two lines are, in metres, both resampled every `step_m`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Shape {
    /// Dynamic time warping: the mean distance between matched points along
    /// the cheapest monotone matching (its total over its number of pairs).
    pub dtw_m: f64,
    /// Discrete Fréchet distance: the longest leash two walkers need to walk
    /// the two lines forwards, each at its own pace.
    pub frechet_m: f64,
}

/// [`Shape`] of `a` against `b`; `None` when either line is empty.
pub fn shape(a: &Polyline, b: &Polyline, step_m: f64) -> Option<Shape> {
    let (p, q) = (a.resampled(step_m), b.resampled(step_m));
    if p.is_empty() || q.is_empty() {
        return None;
    }
    let m = q.len();
    // Row by row: DTW's total and pair count along its cheapest path, and the
    // Fréchet leash, each from the cells above, to the left and diagonally
    // before (of equal totals, the first in that order).
    let mut prev = vec![Coupling::default(); m];
    let mut row = vec![Coupling::default(); m];
    let mut distance = vec![0.0; m];
    for (i, &[x, y]) in p.iter().enumerate() {
        // A row's distances first, in a loop of their own that the compiler
        // vectorises; a plain root, not `hypot`: training scores thousands
        // of walks against each line, and `hypot`'s care for overflow (no
        // line spans 1e150 m) was half of it.
        for (d, &[qx, qy]) in distance.iter_mut().zip(&q) {
            let (dx, dy) = (x - qx, y - qy);
            *d = (dx * dx + dy * dy).sqrt();
        }
        let mut left: Option<Coupling> = None;
        for (j, &d) in distance.iter().enumerate() {
            let before = match (i, left) {
                (0, None) => Coupling::default(),
                (0, Some(left)) => left,
                (_, None) => prev[j],
                (_, Some(left)) => {
                    let (up, diagonal) = (prev[j], prev[j - 1]);
                    let mut cheapest = up;
                    if left.total < cheapest.total {
                        cheapest = left;
                    }
                    if diagonal.total < cheapest.total {
                        cheapest = diagonal;
                    }
                    Coupling {
                        leash: least(least(up.leash, left.leash), diagonal.leash),
                        ..cheapest
                    }
                }
            };
            let here = Coupling {
                total: before.total + d,
                pairs: before.pairs + 1,
                leash: if d > before.leash { d } else { before.leash },
            };
            row[j] = here;
            left = Some(here);
        }
        std::mem::swap(&mut prev, &mut row);
    }
    let last = prev[m - 1];
    Some(Shape {
        dtw_m: last.total / f64::from(last.pairs),
        frechet_m: last.leash,
    })
}

/// The lesser of two distances. `f64::min` also orders NaNs, a few
/// instructions more in the table's innermost loop, where none can occur
/// (distances of finite points).
fn least(a: f64, b: f64) -> f64 {
    if b < a { b } else { a }
}

/// One cell of [`shape`]'s table: the cheapest DTW total reaching it and its
/// pair count, and the shortest Fréchet leash.
#[derive(Clone, Copy, Debug, Default)]
struct Coupling {
    total: f64,
    pairs: u32,
    leash: f64,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resampling_keeps_the_ends_and_the_spacing() {
        let line = Polyline(vec![[0.0, 0.0], [1.0, 0.0], [1.0, 1.5]]);
        let points = line.resampled(0.5);
        assert_eq!(points.len(), 6);
        assert_eq!(points[0], [0.0, 0.0]);
        assert_eq!(points[2], [1.0, 0.0]);
        assert_eq!(points[5], [1.0, 1.5]);
        for w in points.windows(2) {
            assert!((dist(w[0], w[1]) - 0.5).abs() < 1e-9, "{w:?}");
        }
        assert_eq!(line.length_m(), 2.5);
    }

    #[test]
    fn dtw_and_frechet_in_metres() {
        let a = Polyline(vec![[0.0, 0.0], [4.0, 0.0]]);
        // The same line drawn with more points is at distance 0.
        let dense = Polyline((0..=8).map(|i| [f64::from(i) * 0.5, 0.0]).collect());
        let same = shape(&a, &dense, 0.25).unwrap();
        assert!(same.dtw_m < 1e-9 && same.frechet_m < 1e-9, "{same:?}");
        // A parallel line 1 m away: every matched pair is 1 m apart.
        let parallel = Polyline(vec![[0.0, 1.0], [4.0, 1.0]]);
        let s = shape(&a, &parallel, 0.25).unwrap();
        assert!((s.dtw_m - 1.0).abs() < 1e-9 && (s.frechet_m - 1.0).abs() < 1e-9);
        // A detour 2 m out in the middle: the leash is 2 m, the mean less.
        let detour = Polyline(vec![[0.0, 0.0], [2.0, 2.0], [4.0, 0.0]]);
        let s = shape(&a, &detour, 0.25).unwrap();
        assert!((s.frechet_m - 2.0).abs() < 0.2, "{s:?}");
        assert!(s.dtw_m > 0.3 && s.dtw_m < 1.5, "{s:?}");
        // Walked the other way, the Fréchet distance is the whole length.
        let back = Polyline(vec![[4.0, 0.0], [0.0, 0.0]]);
        assert!((shape(&a, &back, 0.25).unwrap().frechet_m - 4.0).abs() < 1e-9);
        assert!(shape(&a, &Polyline(Vec::new()), 0.25).is_none());
    }
}
