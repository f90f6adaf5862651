//! The line GAN's access penalty: how far its lines stray off the floor.
//!
//! The line generator sees only the request's ends (`model::line_gan`), so
//! what it knows of walls is what the adversarial loss teaches it from the
//! walks; on a walled site that left lines through walls for most requests
//! (the sample site: a quarter of the cells its lines crossed were blocked).
//! As the frame generator's penalty does for its frames ([`super::gan::Access`]),
//! this term of the generator's loss pushes back what leaves the
//! public-access area: the distance from each of a line's inner points, and
//! from the midpoint of each of its segments, to the nearest walkable cell,
//! in chords of the request (so a request's size does not change the
//! push), summed over the line and averaged over the batch. On walkable
//! floor it is 0 and pushes nothing; the distance is read bilinearly
//! between cell centres, so its gradient is defined everywhere and grows as
//! a point nears a wall.

use ndarray::{Array2, ArrayView2};

use super::gan::Penalty;
use crate::model::line_gan::{self, INNER, SHAPE_LEN};
use crate::site::{Cell, Site};

pub(crate) struct LineAccess {
    /// Per cell (row-major), the distance in cells from its centre to the
    /// nearest walkable cell's centre, 0 on walkable cells (a chamfer
    /// transform: within 8 % of the Euclidean distance).
    distance: Vec<f32>,
    width: usize,
    height: usize,
    /// Per data row, what its line was generated for.
    rows: Vec<LineRequest>,
    weight: f32,
}

/// What a data row's line is generated for: the request's ends (cell units)
/// and its prior's offsets (`model::line_gan`).
pub(crate) struct LineRequest {
    pub(crate) ends: [[f64; 2]; 2],
    pub(crate) prior: [f32; SHAPE_LEN],
}

impl LineAccess {
    /// The penalty on `site` for data rows generated for `rows`, at
    /// `weight`.
    pub(crate) fn new(site: &Site, rows: Vec<LineRequest>, weight: f32) -> LineAccess {
        let (width, height) = (usize::from(site.width()), usize::from(site.height()));
        let far = (width + height) as f32;
        let mut distance: Vec<f32> = (0..width * height)
            .map(|i| {
                let cell = Cell::new((i % width) as u16, (i / width) as u16);
                if site.walkable(cell) { 0.0 } else { far }
            })
            .collect();
        // Two passes of the 3 × 3 chamfer (1 and √2): forwards from the
        // top-left neighbours, then backwards from the bottom-right ones.
        let diagonal = std::f32::consts::SQRT_2;
        let forwards = [
            (-1, -1, diagonal),
            (0, -1, 1.0),
            (1, -1, diagonal),
            (-1, 0, 1.0),
        ];
        let backwards = forwards.map(|(dx, dy, d)| (-dx, -dy, d));
        let mut pass = |order: &mut dyn Iterator<Item = usize>, steps: &[(i64, i64, f32)]| {
            for i in order {
                let (x, y) = ((i % width) as i64, (i / width) as i64);
                for &(dx, dy, d) in steps {
                    let (nx, ny) = (x + dx, y + dy);
                    if nx >= 0 && ny >= 0 && (nx as usize) < width && (ny as usize) < height {
                        let through = distance[ny as usize * width + nx as usize] + d;
                        if through < distance[i] {
                            distance[i] = through;
                        }
                    }
                }
            }
        };
        pass(&mut (0..width * height), &forwards);
        pass(&mut (0..width * height).rev(), &backwards);
        LineAccess {
            distance,
            width,
            height,
            rows,
            weight,
        }
    }

    /// The distance to walkable floor at `p` (cell units), and its gradient:
    /// bilinear between cell centres; beyond the grid, the distance at its
    /// edge plus how far beyond.
    fn at(&self, p: [f64; 2]) -> (f32, [f32; 2]) {
        let mut beyond = 0.0;
        let mut outward = [0.0f32; 2];
        let mut coord = [0.0f64; 2];
        let mut cell = [0usize; 2];
        let mut frac = [0.0f32; 2];
        for (axis, size) in [self.width, self.height].into_iter().enumerate() {
            // Cell centres sit at i + 0.5.
            let u = p[axis] - 0.5;
            let clamped = u.clamp(0.0, (size - 1) as f64);
            if u != clamped {
                beyond += (u - clamped).abs() as f32;
                outward[axis] = (u - clamped).signum() as f32;
            }
            coord[axis] = clamped;
            cell[axis] = (clamped.floor() as usize).min(size.saturating_sub(2));
            frac[axis] = (clamped - cell[axis] as f64) as f32;
        }
        let d = |dx: usize, dy: usize| {
            let (x, y) = (
                (cell[0] + dx).min(self.width - 1),
                (cell[1] + dy).min(self.height - 1),
            );
            self.distance[y * self.width + x]
        };
        let (d00, d10, d01, d11) = (d(0, 0), d(1, 0), d(0, 1), d(1, 1));
        let [fx, fy] = frac;
        let value = (1.0 - fx) * (1.0 - fy) * d00
            + fx * (1.0 - fy) * d10
            + (1.0 - fx) * fy * d01
            + fx * fy * d11;
        let gx = (1.0 - fy) * (d10 - d00) + fy * (d11 - d01);
        let gy = (1.0 - fx) * (d01 - d00) + fx * (d11 - d10);
        (value + beyond, [gx + outward[0], gy + outward[1]])
    }
}

impl Penalty for LineAccess {
    fn weight(&self) -> f32 {
        self.weight
    }

    fn apply(
        &self,
        out: ArrayView2<f32>,
        picks: &[usize],
        weight: f32,
        grad: &mut Array2<f32>,
    ) -> f32 {
        let scale = weight / out.nrows() as f32;
        let mut loss = 0.0;
        for ((row, &pick), mut g) in out.rows().into_iter().zip(picks).zip(grad.rows_mut()) {
            let LineRequest {
                ends: [a, b],
                prior,
            } = &self.rows[pick];
            let (a, b) = (*a, *b);
            let points = line_gan::line(a, b, prior, &row.to_vec());
            let chord = [(b[0] - a[0]) as f32, (b[1] - a[1]) as f32];
            let length = chord[0].hypot(chord[1]).max(1.0);
            // d(penalty)/d(point k), for the inner points 1..=INNER.
            let mut pulls = [[0.0f32; 2]; INNER + 2];
            for k in 0..points.len() {
                if (1..=INNER).contains(&k) {
                    let (value, gradient) = self.at(points[k]);
                    loss += value / length;
                    for axis in 0..2 {
                        pulls[k][axis] += gradient[axis];
                    }
                }
                if k + 1 < points.len() {
                    let mid = [
                        (points[k][0] + points[k + 1][0]) / 2.0,
                        (points[k][1] + points[k + 1][1]) / 2.0,
                    ];
                    let (value, gradient) = self.at(mid);
                    loss += value / length;
                    for j in [k, k + 1] {
                        for axis in 0..2 {
                            pulls[j][axis] += gradient[axis] / 2.0;
                        }
                    }
                }
            }
            // Point k moves by (b − a) per unit of its along offset and by
            // i·(b − a) per unit of its across one; tanh's slope takes the
            // gradient to the pre-activation.
            for (k, &[px, py]) in pulls.iter().enumerate().take(INNER + 1).skip(1) {
                let along = px * chord[0] + py * chord[1];
                let across = -px * chord[1] + py * chord[0];
                for (column, g_k) in [(k - 1, along), (INNER + k - 1, across)] {
                    let y = row[column];
                    g[column] = scale * g_k / length * (1.0 - y * y);
                }
            }
        }
        scale * loss
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A site of `map` (`#` open floor, `.` blocked).
    fn site(map: &str) -> Site {
        let text = format!("name = \"t\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n");
        Site::parse(&text, std::path::Path::new("t.toml")).unwrap()
    }

    /// A 9 × 7 floor with a wall down its middle, open below it.
    fn walled() -> Site {
        site("#########\n####.####\n####.####\n####.####\n#########\n#########\n#########")
    }

    /// A request from `a` to `b` whose prior is the straight line.
    fn straight(a: [f64; 2], b: [f64; 2]) -> LineRequest {
        LineRequest {
            ends: [a, b],
            prior: [0.0; SHAPE_LEN],
        }
    }

    #[test]
    fn the_distance_is_zero_on_the_floor_and_grows_into_walls() {
        let s = site(".....\n.###.\n.....");
        let access = LineAccess::new(&s, Vec::new(), 1.0);
        assert_eq!(access.at([2.5, 1.5]).0, 0.0);
        assert!((access.at([0.5, 0.5]).0 - std::f32::consts::SQRT_2).abs() < 1e-6);
        // Halfway between a floor cell and the wall beside it.
        assert!((access.at([1.0, 1.5]).0 - 0.5).abs() < 1e-6);
        // Off the grid: the edge's distance plus how far beyond.
        assert!((access.at([-1.5, 1.5]).0 - 3.0).abs() < 1e-6);
    }

    #[test]
    fn the_gradient_matches_finite_differences() {
        let s = walled();
        let access = LineAccess::new(&s, vec![straight([1.5, 2.5], [7.5, 2.5])], 1.5);
        // A line bowing through the wall, off the cells' edges.
        let out = Array2::from_shape_fn((1, SHAPE_LEN), |(_, j)| {
            if j < INNER {
                0.013 * j as f32
            } else {
                0.07 + 0.011 * (j - INNER) as f32
            }
        });
        let mut grad = Array2::zeros((1, SHAPE_LEN));
        let loss = access.apply(out.view(), &[0], 1.5, &mut grad);
        assert!(loss > 0.0);
        for j in [2, 5, INNER + 3, INNER + 7] {
            // Through tanh: perturb the pre-activation.
            let h = 1e-3f32;
            let at = |delta: f32| {
                let mut o = out.clone();
                o[(0, j)] = (o[(0, j)].atanh() + delta).tanh();
                access.apply(o.view(), &[0], 1.5, &mut Array2::zeros((1, SHAPE_LEN)))
            };
            let numeric = (at(h) - at(-h)) / (2.0 * h);
            assert!(
                (numeric - grad[(0, j)]).abs() < 2e-3 * (1.0 + numeric.abs()),
                "column {j}: numeric {numeric}, analytic {}",
                grad[(0, j)]
            );
        }
    }

    #[test]
    fn a_line_on_the_floor_costs_and_pulls_nothing() {
        let s = walled();
        // Along the bottom row, two rows clear of the wall.
        let access = LineAccess::new(&s, vec![straight([0.5, 6.5], [8.5, 6.5])], 1.0);
        let out = Array2::zeros((1, SHAPE_LEN));
        let mut grad = Array2::from_elem((1, SHAPE_LEN), 9.0);
        assert_eq!(access.apply(out.view(), &[0], 1.0, &mut grad), 0.0);
        assert!(grad.iter().all(|&g| g == 0.0));
    }
}
