//! The line GAN's conventions: a conditional GAN whose samples are lines,
//! not frames, so its size does not grow with the site.
//!
//! The paper's generator writes a whole `W·H` frame and its conditional one
//! also reads two `W·H` planes: at 10,000 cells its last layer alone holds
//! 10 M weights, and neither trains nor serves in reasonable time (issue
//! 33). This generator writes the [`POINTS`]-point line of a walk in the
//! request's own frame, the representation the desire lines learn from
//! ([`super::desire`]): a walk from `a` to `b` resampled evenly by length is
//! `z(s) = a + u(s)·(b − a)` in complex numbers, `u(0) = 0`, `u(1) = 1`. A
//! line's *offsets* are its inner points' `u(s_k) − s_k`, `2·(P − 2)`
//! numbers: the `P − 2` along the chord, then the `P − 2` across it, in
//! units of the chord `|b − a|`. The ends are the requested cells' centres,
//! so a line always starts and ends where it was asked to.
//!
//! The condition is the request's two ends ([`endpoints`]: four numbers in
//! [−1, 1], the cell coordinates over the site's longer side) and its
//! *prior*, the any-angle route between them as the planner would serve it
//! without walks (the [`offsets`] of it resampled to [`POINTS`]), the desire
//! lines' prior too. The prior carries the walls: the generator learns how
//! people depart from the route round them, not where every wall is. Its
//! output, in (−1, 1) (tanh), is the line's offsets *less the prior's*
//! ([`line`]); 0 serves the prior. The planner still checks every line
//! against the site and repairs what crosses a wall (`plan::line_gan`).
//!
//! Inputs of the exported generator: `noise` `[N, noise_dim]` standard
//! normal, `endpoints` `[N, 4]` and `prior` `[N, 2·(P − 2)]`; output
//! `shape` `[N, 2·(P − 2)]`. The discriminator takes `shape`, `endpoints`
//! and `prior` and gives `real` `[N, 1]`.

use super::desire::POINTS;

/// Inner points of a line: the ends are the request's own.
pub const INNER: usize = POINTS - 2;
/// Width of a generated sample, and of the prior: along-chord then
/// across-chord offsets.
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

/// The offsets of `points` ([`POINTS`] points from `a` to `b`, cell units,
/// evenly spaced by length): all 0 when `a` and `b` are the same point.
pub fn offsets(points: &[[f64; 2]], a: [f64; 2], b: [f64; 2]) -> [f32; SHAPE_LEN] {
    assert_eq!(points.len(), POINTS, "a line of POINTS points");
    let chord = [b[0] - a[0], b[1] - a[1]];
    let len2 = chord[0] * chord[0] + chord[1] * chord[1];
    let mut out = [0.0; SHAPE_LEN];
    if len2 <= 1e-12 {
        return out;
    }
    for k in 1..=INNER {
        // u = (z − a) / (b − a) in complex numbers.
        let d = [points[k][0] - a[0], points[k][1] - a[1]];
        out[k - 1] = ((d[0] * chord[0] + d[1] * chord[1]) / len2 - fraction(k)) as f32;
        out[INNER + k - 1] = ((d[1] * chord[0] - d[0] * chord[1]) / len2) as f32;
    }
    out
}

/// A walk's normalised shape ([`super::desire::DesireLines::shapes`]) as the
/// GAN's sample for a request whose prior has `prior` offsets: the walk's
/// offsets less the prior's, clipped to (−1, 1) (a walk that strays more
/// than a chord off its prior is rare and keeps its direction, not its
/// extent).
pub fn shape_sample(shape: &[[f32; 2]; POINTS], prior: &[f32; SHAPE_LEN]) -> [f32; SHAPE_LEN] {
    const EDGE: f32 = 0.999;
    let mut out = [0.0; SHAPE_LEN];
    for k in 1..=INNER {
        out[k - 1] = (shape[k][0] - fraction(k) as f32 - prior[k - 1]).clamp(-EDGE, EDGE);
        out[INNER + k - 1] = (shape[k][1] - prior[INNER + k - 1]).clamp(-EDGE, EDGE);
    }
    out
}

/// The line from `a` to `b` (cell units) that a generated `sample`
/// ([`SHAPE_LEN`] values) describes for a request with `prior` offsets:
/// [`POINTS`] points, `a` and `b` the ends.
pub fn line(a: [f64; 2], b: [f64; 2], prior: &[f32], sample: &[f32]) -> Vec<[f64; 2]> {
    assert_eq!(sample.len(), SHAPE_LEN, "a line GAN sample");
    assert_eq!(prior.len(), SHAPE_LEN, "a line GAN prior");
    let chord = [b[0] - a[0], b[1] - a[1]];
    let offset = |j: usize| f64::from(prior[j]) + f64::from(sample[j]);
    (0..POINTS)
        .map(|k| {
            let (re, im) = if k == 0 || k == POINTS - 1 {
                (fraction(k), 0.0)
            } else {
                (fraction(k) + offset(k - 1), offset(INNER + k - 1))
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
        let (a, b) = ([2.0, 3.0], [10.0, 3.0]);
        // A prior bowing the other way, a tenth of the chord.
        let prior_points: Vec<[f64; 2]> = (0..POINTS)
            .map(|k| {
                let s = fraction(k);
                [2.0 + 8.0 * s, 3.0 - 0.8 * (std::f64::consts::PI * s).sin()]
            })
            .collect();
        let prior = offsets(&prior_points, a, b);
        assert!((prior[INNER + POINTS / 2 - 1] + 0.1).abs() < 1e-6);
        let sample = shape_sample(&shape, &prior);
        let points = line(a, b, &prior, &sample);
        assert_eq!(points.len(), POINTS);
        assert_eq!(points[0], a);
        assert_eq!(points[POINTS - 1], b);
        // Halfway along, a quarter of the 8-cell chord to its left (+y).
        let mid = points[POINTS / 2];
        assert!(
            (mid[0] - 6.0).abs() < 1e-5 && (mid[1] - 5.0).abs() < 1e-5,
            "{mid:?}"
        );
        // A sample of zeros is the prior.
        let on_prior = line(a, b, &prior, &[0.0; SHAPE_LEN]);
        for (p, q) in on_prior.iter().zip(&prior_points) {
            assert!((p[0] - q[0]).abs() < 1e-5 && (p[1] - q[1]).abs() < 1e-5);
        }
        // Of a single point, no offsets.
        assert_eq!(offsets(&[a; POINTS], a, a), [0.0; SHAPE_LEN]);
    }

    #[test]
    fn offsets_beyond_a_chord_are_clipped_into_the_tanh_range() {
        let mut shape: [[f32; 2]; POINTS] = std::array::from_fn(|k| [fraction(k) as f32, 0.0]);
        shape[3] = [5.0, -4.0];
        let sample = shape_sample(&shape, &[0.0; SHAPE_LEN]);
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
