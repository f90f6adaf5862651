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
                let d2 = (dx * dx + dy * dy) as f32;
                out[k * plane + y as usize * usize::from(width) + x as usize] =
                    (-d2 / (2.0 * SIGMA_CELLS * SIGMA_CELLS)).exp();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
