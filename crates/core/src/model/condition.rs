//! The condition of a conditional path model: where the walk starts and ends.
//!
//! Encoded as two `W·H` planes (source, then destination), each a Gaussian
//! bump of σ = 1 cell around its cell, cut to zero beyond 3 cells. A bump
//! rather than a one-hot cell means neighbouring cells get similar inputs, so
//! a pair never seen in training still lands near pairs that were.

use crate::site::Cell;

/// Spread of a bump, in cells.
pub(crate) const SIGMA_CELLS: f32 = 1.0;
/// Cells farther than this from the centre get exactly 0.
pub(crate) const CUTOFF_CELLS: i32 = 3;

/// Length of the condition vector on a `width × height` grid.
pub fn len(width: u16, height: u16) -> usize {
    2 * usize::from(width) * usize::from(height)
}

/// Squared distances from a bump's centre to the cells it reaches.
const MAX_D2: usize = 2 * (CUTOFF_CELLS * CUTOFF_CELLS) as usize;

/// A bump's value at each squared distance `d2` ≤ [`MAX_D2`] from its
/// centre, worked out once: the same few numbers every request, which the
/// conditional planner encodes per route (twice per sample before).
fn bump(d2: usize) -> f32 {
    static BUMP: std::sync::LazyLock<[f32; MAX_D2 + 1]> = std::sync::LazyLock::new(|| {
        std::array::from_fn(|d2| (-(d2 as f32) / (2.0 * SIGMA_CELLS * SIGMA_CELLS)).exp())
    });
    BUMP[d2]
}

/// Writes the condition for a walk `source → destination` into `out`
/// (length [`len`]).
pub fn encode(width: u16, height: u16, source: Cell, destination: Cell, out: &mut [f32]) {
    let plane = usize::from(width) * usize::from(height);
    assert_eq!(out.len(), 2 * plane, "condition buffer size");
    out.fill(0.0);
    for (k, centre) in [source, destination].into_iter().enumerate() {
        for dy in -CUTOFF_CELLS..=CUTOFF_CELLS {
            for dx in -CUTOFF_CELLS..=CUTOFF_CELLS {
                let (x, y) = (i32::from(centre.x) + dx, i32::from(centre.y) + dy);
                if x < 0 || y < 0 || x >= i32::from(width) || y >= i32::from(height) {
                    continue;
                }
                out[k * plane + y as usize * usize::from(width) + x as usize] =
                    bump((dx * dx + dy * dy) as usize);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_kept_bump_is_the_expression_it_replaces() {
        for d2 in 0..=MAX_D2 {
            let direct = (-(d2 as f32) / (2.0 * SIGMA_CELLS * SIGMA_CELLS)).exp();
            assert_eq!(bump(d2).to_bits(), direct.to_bits(), "d2 {d2}");
        }
    }

    #[test]
    fn bumps_peak_at_the_endpoints_and_stay_on_the_grid() {
        let mut out = vec![0.0; len(5, 4)];
        encode(5, 4, Cell::new(0, 0), Cell::new(4, 3), &mut out);
        assert_eq!(out[0], 1.0);
        assert_eq!(out[20 + 3 * 5 + 4], 1.0);
        assert!((out[1] - (-0.5f32).exp()).abs() < 1e-6);
        assert_eq!(out[4], 0.0, "4 cells away from the source");
        assert!(out.iter().all(|v| (0.0..=1.0).contains(v)));
    }
}
