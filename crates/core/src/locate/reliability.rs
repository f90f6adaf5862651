//! Published confidence that means what it says: of fixes published at
//! confidence ≈ p, about p are within one cell of the truth.
//!
//! A tracker's belief is over-confident on real radio (anchors are not
//! independent, the radio model is not the building), so the raw belief
//! within one cell is mapped through a monotone function fitted on held-out
//! fixes whose truth is known: isotonic regression (pool adjacent violators),
//! the standard non-parametric calibrator. Where nothing held out is known,
//! the map is the identity. Two things keep the fit honest where its fixes
//! are few or lopsided: each fix carries a weight, so held-out fixes can
//! count as often as the ground they stood on is met in service
//! ([`super::crossval`]), and no block of the fit publishes more than
//! Laplace's rule of succession grants its fixes, so a handful of right
//! fixes at the top never publishes certainty.
//!
//! Windows that heard one anchor are not as good as windows of the same raw
//! belief that heard five, so the map may be fitted per class of window
//! (one, two, three or more anchors). Whether it is depends on the fixes:
//! both ways are fitted on half the groups of fixes (walking sessions,
//! rehearsed walks) and scored on the other half, and back, by Brier score.
//! A few hundred held-out survey fixes split three ways fit their noise (a
//! map per class made the radio map's published confidence on the UCI
//! survey worse, 0.069 → 0.112), four thousand rehearsed ones do not.

use super::Localizer;
use super::pathloss::PathLoss;

/// A fix whose truth is known: its raw confidence, its error in cells, how
/// many anchors its window heard and the group it came in (a walking
/// session, a rehearsed walk): fixes of one group are not independent.
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct KnownFix {
    pub raw: f32,
    pub error_cells: f64,
    pub heard: usize,
    pub group: usize,
    /// How much the fix counts in a fit: held-out fixes are weighed so
    /// that the ground they cover is the ground the served model meets.
    pub weight: f64,
}

impl KnownFix {
    fn within_one_cell(&self) -> f64 {
        f64::from(u8::from(self.error_cells <= 1.0 + 1e-9))
    }
}

/// Classes of window: one anchor heard, two, three or more.
const CLASSES: usize = 3;

fn class(heard: usize) -> usize {
    heard.clamp(1, CLASSES) - 1
}

/// Monotone maps from raw to published confidence: one for all windows, or
/// one per class of window (a class with too few fixes uses the first).
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct ConfidenceMap {
    all: Knots,
    by_class: Option<[Knots; CLASSES]>,
}

/// Fewer known fixes than this fit nothing: the identity is kept (for a
/// class, the map of all windows).
const MIN_FIXES: usize = 50;

impl ConfidenceMap {
    pub(crate) fn fit(fixes: &[KnownFix]) -> ConfidenceMap {
        let by_class = Self::per_class(fixes);
        let half = |parity: usize| -> Vec<KnownFix> {
            fixes
                .iter()
                .filter(|f| f.group % 2 == parity)
                .copied()
                .collect()
        };
        let (even, odd) = (half(0), half(1));
        let score = |fit: &dyn Fn(&[KnownFix]) -> ConfidenceMap| -> f64 {
            brier(&fit(&even), &odd) + brier(&fit(&odd), &even)
        };
        let per_class_wins = score(&|f| Self::per_class(f)) < score(&|f| Self::pooled(f));
        if per_class_wins {
            by_class
        } else {
            Self::pooled(fixes)
        }
    }

    fn pooled(fixes: &[KnownFix]) -> ConfidenceMap {
        ConfidenceMap {
            all: Knots::fit(fixes.iter()),
            by_class: None,
        }
    }

    fn per_class(fixes: &[KnownFix]) -> ConfidenceMap {
        let all = Knots::fit(fixes.iter());
        let by_class = std::array::from_fn(|c| {
            let mine: Vec<&KnownFix> = fixes.iter().filter(|f| class(f.heard) == c).collect();
            if mine.len() >= MIN_FIXES {
                Knots::fit(mine.into_iter())
            } else {
                all.clone()
            }
        });
        ConfidenceMap {
            all,
            by_class: Some(by_class),
        }
    }

    /// The published confidence of a raw one, for a window that heard
    /// `heard` anchors.
    pub(crate) fn apply(&self, raw: f32, heard: usize) -> f32 {
        match &self.by_class {
            Some(by_class) => by_class[class(heard)].apply(raw),
            None => self.all.apply(raw),
        }
    }
}

/// A localizer whose published confidence goes through a map fitted on
/// its known fixes (held out or rehearsed).
pub(crate) struct Mapped<L> {
    inner: L,
    confidence: ConfidenceMap,
}

impl<L: Localizer> Mapped<L> {
    pub(crate) fn new(inner: L, confidence: ConfidenceMap) -> Self {
        Mapped { inner, confidence }
    }
}

impl<L: Localizer> Localizer for Mapped<L> {
    fn method(&self) -> &'static str {
        self.inner.method()
    }

    fn log_likelihood(&mut self, rssi: &[f32], heard: &[bool], out: &mut [f32]) {
        self.inner.log_likelihood(rssi, heard, out);
    }

    fn confidence(&self, raw: f32, heard: usize) -> f32 {
        self.confidence.apply(raw, heard)
    }

    fn radio_model(&mut self) -> Option<&mut PathLoss> {
        self.inner.radio_model()
    }
}

/// Mean squared difference between published confidence and "within one
/// cell" over `fixes` (0 for none).
fn brier(map: &ConfidenceMap, fixes: &[KnownFix]) -> f64 {
    let sum: f64 = fixes
        .iter()
        .map(|f| f.weight * (f64::from(map.apply(f.raw, f.heard)) - f.within_one_cell()).powi(2))
        .sum();
    let total: f64 = fixes.iter().map(|f| f.weight).sum();
    if total > 0.0 { sum / total } else { 0.0 }
}

/// The chance that the next fix of a block is within one cell when `hits`
/// of its `n` were, by Laplace's rule of succession: (hits + 1) / (n + 2).
///
/// A block's plain share is what publishes, but never above this: the top
/// block of a map can hold a handful of fixes that were all right, and its
/// share, 1, is never honest. On the mall a one-beacon window went out at
/// 1.000 and 12 m off from a block of one fix (now 0.67), and the published
/// confidence there grew more honest (mean gap 0.020 → 0.018). Only the
/// side that misleads is bounded: a share below one half is already below
/// its succession, and under-confidence costs a user a fix, not a wrong one.
fn succession(hits: f64, n: f64) -> f64 {
    (hits + 1.0) / (n + 2.0)
}

/// `(raw, published)` knots, linear between them; none is the identity.
#[derive(Clone, Debug, Default, PartialEq)]
struct Knots(Vec<(f32, f32)>);

impl Knots {
    /// Isotonic regression (pool adjacent violators) of "within one cell"
    /// on raw confidence.
    fn fit<'a>(fixes: impl Iterator<Item = &'a KnownFix>) -> Knots {
        let mut sorted: Vec<(f32, f64, f64)> = fixes
            .filter(|f| f.weight > 0.0)
            .map(|f| (f.raw, f.within_one_cell(), f.weight))
            .collect();
        if sorted.len() < MIN_FIXES {
            return Knots::default();
        }
        sorted.sort_by(|a, b| a.0.total_cmp(&b.0));
        // Blocks of (weighted sums of raw and of hits, total weight), merged
        // while decreasing.
        // Fixes of one raw value are one block from the start: they must get
        // one published value, whatever order the sort left them in.
        let mut blocks: Vec<(f64, f64, f64)> = Vec::new();
        let mut last_raw = f32::NAN;
        for (raw, hit, weight) in sorted {
            if raw == last_raw {
                let last = blocks.last_mut().expect("a block of this raw value");
                *last = (
                    last.0 + weight * f64::from(raw),
                    last.1 + weight * hit,
                    last.2 + weight,
                );
            } else {
                blocks.push((weight * f64::from(raw), weight * hit, weight));
                last_raw = raw;
            }
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
        // From the top down: no block publishes more than its share, than
        // the rule of succession grants it, or than the block above.
        let mut ceiling = 1.0f64;
        let mut knots: Vec<(f32, f32)> = blocks
            .iter()
            .rev()
            .map(|&(raw, hits, n)| {
                ceiling = ceiling.min(hits / n).min(succession(hits, n));
                ((raw / n) as f32, ceiling as f32)
            })
            .collect();
        knots.reverse();
        Knots(knots)
    }

    pub(crate) fn apply(&self, raw: f32) -> f32 {
        let k = &self.0;
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
            fixes.push(known(0.9, if i < 60 { 0.0 } else { 3.0 }, 3, i));
            fixes.push(known(0.5, if i < 30 { 1.0 } else { 2.5 }, 3, i));
        }
        let map = ConfidenceMap::fit(&fixes);
        // 60 of 100 right: 61 / 102 by succession.
        assert!((map.apply(0.9, 3) - 61.0 / 102.0).abs() < 1e-6);
        assert!((map.apply(0.5, 3) - 0.3).abs() < 1e-6);
        assert!((map.apply(0.7, 3) - (0.3 + 61.0 / 102.0) / 2.0).abs() < 1e-6);
        assert!(map.apply(0.95, 3) >= map.apply(0.9, 3));
    }

    #[test]
    fn too_few_fixes_keep_the_raw_confidence() {
        let map = ConfidenceMap::fit(&[known(0.9, 5.0, 2, 0); 10]);
        assert_eq!(map.apply(0.42, 2), 0.42);
    }

    #[test]
    fn a_window_of_one_anchor_publishes_what_such_windows_earned() {
        // At the same raw 0.95, windows of one anchor are right 20% of the
        // time and windows of four 90%; each walk (group) had both.
        let mut fixes = Vec::new();
        for i in 0..100 {
            fixes.push(known(0.95, if i % 5 == 0 { 0.0 } else { 4.0 }, 1, i));
            fixes.push(known(0.95, if i % 10 == 0 { 4.0 } else { 1.0 }, 4, i));
        }
        let map = ConfidenceMap::fit(&fixes);
        assert!((map.apply(0.95, 1) - 0.2).abs() < 1e-6);
        assert!((map.apply(0.95, 5) - 91.0 / 102.0).abs() < 1e-6);
        // Two anchors: no such window was known, so all of them speak.
        assert!((map.apply(0.95, 2) - 111.0 / 202.0).abs() < 1e-6);
    }

    #[test]
    fn a_few_right_fixes_at_the_top_never_publish_certainty() {
        // Most fixes are right a third of the time; the three of highest
        // raw belief were all right.
        let mut fixes: Vec<KnownFix> = (0..90)
            .map(|i| {
                known(
                    0.4 + 0.005 * i as f32,
                    if i % 3 == 0 { 0.5 } else { 3.0 },
                    3,
                    i,
                )
            })
            .collect();
        fixes.extend((0..3).map(|i| known(0.999, 0.0, 3, 90 + i)));
        let map = ConfidenceMap::fit(&fixes);
        assert!((map.apply(0.999, 3) - 4.0 / 5.0).abs() < 1e-6);
        assert!(map.apply(0.999, 3) >= map.apply(0.6, 3));
    }

    #[test]
    fn a_fix_weighing_two_counts_as_two_fixes() {
        let mut weighed = Vec::new();
        let mut repeated = Vec::new();
        for i in 0..60 {
            let (raw, error) = (0.2 + 0.01 * i as f32, if i % 3 == 0 { 0.0 } else { 2.0 });
            let weight = if i % 2 == 0 { 2.0 } else { 1.0 };
            weighed.push(KnownFix {
                weight,
                ..known(raw, error, 3, i)
            });
            repeated.push(known(raw, error, 3, i));
            if weight == 2.0 {
                repeated.push(known(raw, error, 3, i));
            }
        }
        let (a, b) = (ConfidenceMap::fit(&weighed), ConfidenceMap::fit(&repeated));
        for raw in [0.1, 0.3, 0.5, 0.7, 0.9] {
            assert!((a.apply(raw, 3) - b.apply(raw, 3)).abs() < 1e-5, "{raw}");
        }
    }

    fn known(raw: f32, error_cells: f64, heard: usize, group: usize) -> KnownFix {
        KnownFix {
            raw,
            error_cells,
            heard,
            group,
            weight: 1.0,
        }
    }
}
