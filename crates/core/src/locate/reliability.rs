//! Published confidence that means what it says: of fixes published at
//! confidence ≈ p, about p are within one cell of the truth.
//!
//! A tracker's belief is over-confident on real radio (anchors are not
//! independent, the radio model is not the building), so the raw belief
//! within one cell is mapped through a monotone function fitted on held-out
//! fixes whose truth is known: isotonic regression (pool adjacent violators),
//! the standard non-parametric calibrator. Where nothing held out is known,
//! the map is the identity.

/// A monotone map from raw to published confidence: `(raw, published)`
/// knots, linear between them.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct ConfidenceMap {
    knots: Vec<(f32, f32)>,
}

/// Fewer held-out fixes than this fit nothing: the identity is kept.
const MIN_FIXES: usize = 50;

impl ConfidenceMap {
    /// Fits to held-out `(raw confidence, error in cells)` pairs.
    pub(crate) fn fit(fixes: &[(f32, f64)]) -> ConfidenceMap {
        if fixes.len() < MIN_FIXES {
            return ConfidenceMap::default();
        }
        let mut sorted: Vec<(f32, f64)> = fixes
            .iter()
            .map(|&(raw, error)| (raw, f64::from(u8::from(error <= 1.0 + 1e-9))))
            .collect();
        sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
        // Blocks of (sum of raw, sum of hits, count), merged while decreasing.
        let mut blocks: Vec<(f64, f64, f64)> = Vec::new();
        for (raw, hit) in sorted {
            blocks.push((f64::from(raw), hit, 1.0));
            while blocks.len() > 1 {
                let (a, b) = (blocks[blocks.len() - 2], blocks[blocks.len() - 1]);
                if a.1 / a.2 < b.1 / b.2 {
                    break;
                }
                blocks.pop();
                let last = blocks.last_mut().expect("two blocks");
                *last = (a.0 + b.0, a.1 + b.1, a.2 + b.2);
            }
        }
        ConfidenceMap {
            knots: blocks
                .iter()
                .map(|&(raw, hits, n)| ((raw / n) as f32, (hits / n) as f32))
                .collect(),
        }
    }

    /// The published confidence of a raw one.
    pub(crate) fn apply(&self, raw: f32) -> f32 {
        let k = &self.knots;
        let (Some(first), Some(last)) = (k.first(), k.last()) else {
            return raw;
        };
        if raw <= first.0 {
            return first.1;
        }
        if raw >= last.0 {
            return last.1;
        }
        let i = k.partition_point(|knot| knot.0 <= raw);
        let (a, b) = (k[i - 1], k[i]);
        let f = (raw - a.0) / (b.0 - a.0).max(f32::EPSILON);
        a.1 + f * (b.1 - a.1)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_over_confident_belief_is_mapped_down_and_stays_monotone() {
        // Raw 0.9 is right 60% of the time, raw 0.5 30%.
        let mut fixes = Vec::new();
        for i in 0..100 {
            fixes.push((0.9, if i < 60 { 0.0 } else { 3.0 }));
            fixes.push((0.5, if i < 30 { 1.0 } else { 2.5 }));
        }
        let map = ConfidenceMap::fit(&fixes);
        assert!((map.apply(0.9) - 0.6).abs() < 1e-6);
        assert!((map.apply(0.5) - 0.3).abs() < 1e-6);
        assert!((map.apply(0.7) - 0.45).abs() < 1e-6);
        assert!(map.apply(0.95) >= map.apply(0.9));
    }

    #[test]
    fn too_few_fixes_keep_the_raw_confidence() {
        let map = ConfidenceMap::fit(&[(0.9, 5.0); 10]);
        assert_eq!(map.apply(0.42), 0.42);
    }
}
