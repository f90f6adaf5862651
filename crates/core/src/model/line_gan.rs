//! The line GAN's conventions: a conditional GAN whose samples are lines,
//! not frames, so its size does not grow with the site.
//!
//! The paper's generator writes a whole `W·H` frame and its conditional one
//! also reads two `W·H` planes: at 10,000 cells its last layer alone holds
//! 10 M weights, and neither trains nor serves in reasonable time (issue
//! 33). This generator writes the [`POINTS`]-point line of a walk in the
//! request's own frame, the representation the desire lines learn from
//! ([`super::desire`]): a walk from `a` to `b` resampled evenly by length is
//! `z(s) = a + u(s)·(b − a)` in complex numbers, `u(0) = 0`, `u(1) = 1`, and
//! the model gives the inner points' offsets from the straight line,
//! `u(s_k) − s_k`, as `2·(P − 2)` numbers in (−1, 1) (tanh): the `P − 2`
//! along-the-chord offsets, then the `P − 2` across it, in units of the
//! chord `|b − a|`. The ends are the requested cells' centres, so a line
//! always starts and ends where it was asked to.
//!
//! The condition is the request's two ends ([`endpoints`]): four numbers in
//! [−1, 1], the cell coordinates over the site's longer side, so one model
//! answers any pair of points of its site. What it knows of walls is what the
//! walks taught it; the planner checks every line against the site and
//! repairs what crosses a wall (`plan::line_gan`).
//!
//! Inputs of the exported generator: `noise` `[N, noise_dim]` standard
//! normal and `endpoints` `[N, 4]` ([`endpoints`]); output `shape` `[N,
//! 2·(P − 2)]`. The discriminator takes `shape` and `endpoints` and gives
//! `real` `[N, 1]`.

use super::desire::POINTS;

/// Inner points of a line: the ends are the request's own.
pub const INNER: usize = POINTS - 2;
/// Width of a generated sample: along-chord then across-chord offsets.
pub const SHAPE_LEN: usize = 2 * INNER;
/// Width of the condition.
pub const ENDPOINTS_LEN: usize = 4;

/// The condition for a line from `a` to `b` (cell units) on a `width ×
/// height` grid: `ax, ay, bx, by` as `2·c / L − 1`, `L` the longer side, so
/// the site's square spans [−1, 1] whatever its size.
pub fn endpoints(width: u16, height: u16, a: [f64; 2], b: [f64; 2]) -> [f32; ENDPOINTS_LEN] {
    let side = f64::from(width.max(height).max(1));
    [a[0], a[1], b[0], b[1]].map(|c| (2.0 * c / side - 1.0) as f32)
}

/// The fraction of the way along a line of point `k`.
fn fraction(k: usize) -> f64 {
    k as f64 / (POINTS - 1) as f64
}

/// A walk's normalised shape ([`super::desire::DesireLines::shapes`]) as the
/// GAN's sample: its inner points' offsets from the straight line, clipped
/// to (−1, 1) (a walk that strays more than a chord off its line is rare and
/// keeps its direction, not its extent).
pub fn shape_sample(shape: &[[f32; 2]; POINTS]) -> [f32; SHAPE_LEN] {
    const EDGE: f32 = 0.999;
    let mut out = [0.0; SHAPE_LEN];
    for k in 1..=INNER {
        out[k - 1] = (shape[k][0] - fraction(k) as f32).clamp(-EDGE, EDGE);
        out[INNER + k - 1] = shape[k][1].clamp(-EDGE, EDGE);
    }
    out
}

/// The line from `a` to `b` (cell units) that a generated `sample`
/// ([`SHAPE_LEN`] values) describes: [`POINTS`] points, `a` and `b` the
/// ends.
pub fn line(a: [f64; 2], b: [f64; 2], sample: &[f32]) -> Vec<[f64; 2]> {
    assert_eq!(sample.len(), SHAPE_LEN, "a line GAN sample");
    let chord = [b[0] - a[0], b[1] - a[1]];
    (0..POINTS)
        .map(|k| {
            let (re, im) = if k == 0 || k == POINTS - 1 {
                (fraction(k), 0.0)
            } else {
                (
                    fraction(k) + f64::from(sample[k - 1]),
                    f64::from(sample[INNER + k - 1]),
                )
            };
            // a + (re + i·im)·(b − a)
            [
                a[0] + re * chord[0] - im * chord[1],
                a[1] + re * chord[1] + im * chord[0],
            ]
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_walks_sample_gives_back_its_line_between_the_requested_ends() {
        // A walk bowing left of its chord by a quarter of it, midway.
        let shape: [[f32; 2]; POINTS] = std::array::from_fn(|k| {
            let s = fraction(k) as f32;
            [s, 0.25 * (std::f32::consts::PI * s).sin()]
        });
        let sample = shape_sample(&shape);
        let (a, b) = ([2.0, 3.0], [10.0, 3.0]);
        let points = line(a, b, &sample);
        assert_eq!(points.len(), POINTS);
        assert_eq!(points[0], a);
        assert_eq!(points[POINTS - 1], b);
        // Halfway along, a quarter of the 8-cell chord to its left (+y).
        let mid = points[POINTS / 2];
        assert!(
            (mid[0] - 6.0).abs() < 1e-6 && (mid[1] - 5.0).abs() < 1e-6,
            "{mid:?}"
        );
        // The straight line's sample is all zeros.
        let straight: [[f32; 2]; POINTS] = std::array::from_fn(|k| [fraction(k) as f32, 0.0]);
        assert!(shape_sample(&straight).iter().all(|&v| v.abs() < 1e-6));
    }

    #[test]
    fn offsets_beyond_a_chord_are_clipped_into_the_tanh_range() {
        let mut shape: [[f32; 2]; POINTS] = std::array::from_fn(|k| [fraction(k) as f32, 0.0]);
        shape[3] = [5.0, -4.0];
        let sample = shape_sample(&shape);
        assert!(sample.iter().all(|v| v.abs() < 1.0));
        assert!(sample[2] > 0.99 && sample[INNER + 2] < -0.99);
    }

    #[test]
    fn endpoints_span_the_longer_side() {
        assert_eq!(
            endpoints(20, 10, [0.0, 0.0], [20.0, 10.0]),
            [-1.0, -1.0, 1.0, 0.0]
        );
    }
}
