//! Which floor of a building a device is on, from the beacons it hears.
//!
//! Two parts, both pure computation:
//!
//! - [`FloorEvidence`]: what one window says about the floor. Each anchor
//!   (beacon) has a share per floor, how strongly it is heard from there
//!   (from a survey: its readings' received power summed per floor, so the
//!   floor it is heard loudest from dominates and a beacon heard faintly
//!   through an atrium still says a little about the floor below). A
//!   window's log-evidence for a floor is the sum, over the anchors heard,
//!   of the log of that anchor's share, each weighted by its received power
//!   relative to the strongest anchor of the window: the nearest beacon
//!   speaks loudest, a faint one from another floor barely counts.
//! - [`FloorFilter`]: a walk's floor over time, a hidden Markov model over
//!   the floors whose only transition is "change floor" with a small
//!   probability per window. One odd window (a beacon heard through the
//!   floor) does not move it; consistent evidence does, a few windows late.
//!
//! Neither knows where connectors are: the tracker's walls and connectors
//! judge that a change of floor is possible; this judges what is heard.

/// The share of an anchor's evidence spread over every floor, so that no
/// floor is ever ruled out by one window (a beacon moved, a survey that
/// missed a floor).
const SPREAD: f64 = 0.05;

/// Per anchor, how each floor is heard: the evidence of one window.
#[derive(Clone, Debug, PartialEq)]
pub struct FloorEvidence {
    floors: usize,
    /// Per anchor, per floor: ln of the anchor's (spread) share of that floor.
    ln_share: Vec<Vec<f64>>,
}

impl FloorEvidence {
    /// `heard_on[anchor][floor]`: how strongly the anchor is heard from each
    /// floor (for example its readings' power summed per floor, in mW); an
    /// anchor never heard says nothing about the floor.
    pub fn new(floors: usize, heard_on: &[Vec<f64>]) -> FloorEvidence {
        let ln_share = heard_on
            .iter()
            .map(|per_floor| {
                let total: f64 = per_floor.iter().sum();
                (0..floors)
                    .map(|f| {
                        let share = if total > 0.0 {
                            per_floor.get(f).copied().unwrap_or(0.0) / total
                        } else {
                            1.0 / floors as f64
                        };
                        ((share + SPREAD) / (1.0 + SPREAD * floors as f64)).ln()
                    })
                    .collect()
            })
            .collect();
        FloorEvidence { floors, ln_share }
    }

    /// The evidence of a building's site files: `listed[f]` holds each
    /// anchor floor `f`'s site file lists (the building's index of it) and
    /// how loudly it is heard over that floor ([`Beacon::heard_dbm`], from
    /// the survey). An anchor every listing floor gives a loudness for is
    /// heard from each in proportion to it; any other is heard equally
    /// from every floor listing it (listed on one floor, it says that
    /// floor; on two, either).
    ///
    /// [`Beacon::heard_dbm`]: crate::site::Beacon::heard_dbm
    pub fn of_floors(listed: &[Vec<(usize, Option<f64>)>]) -> FloorEvidence {
        let anchors = listed
            .iter()
            .flatten()
            .map(|&(a, _)| a + 1)
            .max()
            .unwrap_or(0);
        let mut loudness = vec![vec![None; listed.len()]; anchors];
        let mut measured = vec![true; anchors];
        for (floor, on_floor) in listed.iter().enumerate() {
            for &(anchor, dbm) in on_floor {
                loudness[anchor][floor] = Some(dbm);
                measured[anchor] &= dbm.is_some();
            }
        }
        let heard_on: Vec<Vec<f64>> = loudness
            .iter()
            .zip(&measured)
            .map(|(per_floor, &measured)| {
                per_floor
                    .iter()
                    .map(|listing| match listing {
                        None => 0.0,
                        Some(Some(dbm)) if measured => 10f64.powf(dbm / 10.0),
                        Some(_) => 1.0,
                    })
                    .collect()
            })
            .collect();
        FloorEvidence::new(listed.len(), &heard_on)
    }

    pub fn floors(&self) -> usize {
        self.floors
    }

    /// The log-evidence of each floor (into `out`, one per floor) for one
    /// window: `heard` holds (anchor, RSSI dBm) of the anchors heard. An
    /// empty window leaves every floor at 0 (no evidence).
    pub fn window(&self, heard: &[(usize, f32)], out: &mut [f64]) {
        out.fill(0.0);
        let Some(strongest) = heard.iter().map(|h| h.1).reduce(f32::max) else {
            return;
        };
        for &(anchor, rssi) in heard {
            let Some(ln_share) = self.ln_share.get(anchor) else {
                continue;
            };
            let weight = 10f64.powf(f64::from(rssi - strongest) / 10.0);
            for (o, s) in out.iter_mut().zip(ln_share) {
                *o += weight * s;
            }
        }
    }
}

/// One walker's floor over time.
#[derive(Clone, Debug, PartialEq)]
pub struct FloorFilter {
    /// ln P(floor | the windows so far), normalised.
    ln_belief: Vec<f64>,
    ln_stay: f64,
    ln_move: f64,
}

impl FloorFilter {
    /// A walker first equally likely on each of `floors` floors, changing
    /// floor between two windows with probability `switch` (spread evenly
    /// over the other floors).
    pub fn new(floors: usize, switch: f64) -> FloorFilter {
        let floors = floors.max(1);
        let switch = if floors == 1 {
            0.0
        } else {
            switch.clamp(1e-12, 0.5)
        };
        FloorFilter {
            ln_belief: vec![-(floors as f64).ln(); floors],
            ln_stay: (1.0 - switch).ln(),
            ln_move: (switch / (floors - 1).max(1) as f64).ln(),
        }
    }

    /// Takes one window's log-evidence per floor; returns the most likely
    /// floor and its probability.
    pub fn update(&mut self, evidence: &[f64]) -> (usize, f64) {
        let ln_all = log_sum_exp(self.ln_belief.iter().copied());
        let prior: Vec<f64> = self
            .ln_belief
            .iter()
            .map(|&b| {
                // Stay on this floor, or come from any other.
                let others = log_sub_exp(ln_all, b);
                log_add_exp(b + self.ln_stay, others + self.ln_move)
            })
            .collect();
        for ((b, p), e) in self.ln_belief.iter_mut().zip(prior).zip(evidence) {
            *b = p + e;
        }
        let norm = log_sum_exp(self.ln_belief.iter().copied());
        for b in &mut self.ln_belief {
            *b -= norm;
        }
        self.floor()
    }

    /// The probability of `floor` (0 for a floor it does not have).
    pub fn probability(&self, floor: usize) -> f64 {
        self.ln_belief.get(floor).map_or(0.0, |b| b.exp())
    }

    /// The most likely floor and its probability.
    pub fn floor(&self) -> (usize, f64) {
        let (floor, ln_p) = self
            .ln_belief
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .map(|(f, &p)| (f, p))
            .unwrap_or((0, 0.0));
        (floor, ln_p.exp())
    }
}

/// ln Σ e^v, without overflow.
pub(crate) fn log_sum_exp(values: impl Iterator<Item = f64> + Clone) -> f64 {
    let max = values.clone().fold(f64::NEG_INFINITY, f64::max);
    if max == f64::NEG_INFINITY {
        return max;
    }
    max + values.map(|v| (v - max).exp()).sum::<f64>().ln()
}

fn log_add_exp(a: f64, b: f64) -> f64 {
    log_sum_exp([a, b].into_iter())
}

/// ln(e^a − e^b) for a ≥ b; −∞ when they are equal.
fn log_sub_exp(a: f64, b: f64) -> f64 {
    if b >= a {
        return f64::NEG_INFINITY;
    }
    a + (-(b - a).exp()).ln_1p()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Two floors: anchor 0 on floor 0, anchor 1 on floor 1, anchor 2 on
    /// floor 1 but heard through the atrium from floor 0 too (a quarter of
    /// its power there).
    fn evidence() -> FloorEvidence {
        FloorEvidence::new(2, &[vec![1.0, 0.0], vec![0.0, 1.0], vec![0.25, 0.75]])
    }

    fn floor_of(evidence: &FloorEvidence, heard: &[(usize, f32)]) -> usize {
        let mut out = [0.0; 2];
        evidence.window(heard, &mut out);
        usize::from(out[1] > out[0])
    }

    #[test]
    fn site_files_weigh_a_beacon_by_how_loudly_each_floor_hears_it() {
        // Anchor 0 on floor 0 only; anchor 1 listed on both floors, heard
        // 6 dB louder over floor 1 (a quarter of its power on floor 0);
        // anchor 2 on both, floor 0 giving no loudness.
        let e = FloorEvidence::of_floors(&[
            vec![(0, Some(-70.0)), (1, Some(-86.0)), (2, None)],
            vec![(1, Some(-80.0)), (2, Some(-75.0))],
        ]);
        let share = |anchor: usize| {
            let mut out = [0.0; 2];
            e.window(&[(anchor, -60.0)], &mut out);
            out.map(f64::exp)
        };
        let [a0, b0] = share(0);
        assert!(a0 > 0.9 && b0 < 0.05, "{a0} {b0}");
        let [a1, b1] = share(1);
        assert!((b1 / a1 - 3.0).abs() < 0.6, "{a1} {b1}");
        let [a2, b2] = share(2);
        assert!(
            (a2 - b2).abs() < 1e-12,
            "unmeasured somewhere: equal, {a2} {b2}"
        );
        assert_eq!(
            FloorEvidence::of_floors(&[vec![(0, None)], vec![]]),
            FloorEvidence::new(2, &[vec![1.0, 0.0]])
        );
    }

    #[test]
    fn a_window_points_at_the_floor_of_the_beacon_heard_loudest() {
        let e = evidence();
        assert_eq!(floor_of(&e, &[(0, -60.0)]), 0);
        assert_eq!(floor_of(&e, &[(1, -60.0)]), 1);
        // The beacon heard from both floors, louder than the one of floor 0
        // (standing under the atrium): it leans to its own floor.
        assert_eq!(floor_of(&e, &[(2, -62.0), (0, -80.0)]), 1);
        // Near floor 0's beacon, the atrium beacon faint: floor 0.
        assert_eq!(floor_of(&e, &[(0, -60.0), (2, -75.0)]), 0);
        let mut out = [1.0; 2];
        e.window(&[], &mut out);
        assert_eq!(out, [0.0, 0.0], "nothing heard, no evidence");
        e.window(&[(7, -50.0)], &mut out);
        assert_eq!(out, [0.0, 0.0], "an anchor it does not know says nothing");
    }

    #[test]
    fn the_filter_changes_floor_only_on_consistent_evidence() {
        let e = evidence();
        let mut filter = FloorFilter::new(2, 0.001);
        let mut out = [0.0; 2];
        let mut step = |filter: &mut FloorFilter, heard: &[(usize, f32)]| {
            e.window(heard, &mut out);
            filter.update(&out).0
        };
        for _ in 0..5 {
            assert_eq!(step(&mut filter, &[(0, -60.0)]), 0);
        }
        // One window of floor 1's beacon (heard through a stairwell): stays.
        assert_eq!(step(&mut filter, &[(1, -70.0)]), 0);
        assert_eq!(step(&mut filter, &[(0, -60.0)]), 0);
        // The walker went up: a few windows later the floor follows.
        let changed = (1..=6).find(|_| step(&mut filter, &[(1, -60.0)]) == 1);
        assert!(matches!(changed, Some(2..=4)), "{changed:?}");
        let (floor, p) = filter.floor();
        assert_eq!(floor, 1);
        assert!(p > 0.5 && p <= 1.0, "{p}");
    }

    #[test]
    fn one_floor_is_always_that_floor() {
        let mut filter = FloorFilter::new(1, 0.01);
        assert_eq!(filter.update(&[-3.0]), (0, 1.0));
    }
}
