//! Scoring a replay: the locations the pipeline published against the
//! `truth` events of the log it replayed. The [`Scorer`] is a sink of the
//! runtime (`replay --score`); the score comes back on a channel at shutdown.
//!
//! Each fix (a location message) is matched to the truth event of the same
//! device nearest to it in time; if that truth is further than the tolerance
//! away, the fix is unmatched and not scored (the log says nothing about where
//! the device was then). A fix's time is the end of its fingerprint window, so
//! the natural tolerance is the window length: the truth then describes the
//! span the fix was computed from. Ties in time go to the earlier truth.
//!
//! Error is the Euclidean distance between the centres of the fixed and the
//! true cell ([`Cell::distance`]), in cells and in metres (times the site's
//! `cell_m`); `within_k` is the share of matched fixes with error ≤ k cells, so
//! a diagonal neighbour (1.41 cells) is within 2 but not within 1.
//!
//! The scorer keeps every truth and fix until [`Scorer::score`], since a truth
//! may arrive after the fix it scores: a few dozen bytes per event.

use std::collections::HashMap;
use std::sync::Arc;

use futures::future::BoxFuture;
use serde::Serialize;
use tokio::sync::oneshot;

use crate::event::Truth;
use crate::publish::{Location, Output};
use crate::sink::Sink;
use crate::site::{Building, Cell};

/// Collects truths and fixes during a replay.
#[derive(Debug)]
pub struct Scorer {
    tolerance_s: f64,
    /// Per device: (t, floor, cell) in arrival order.
    truths: HashMap<String, Vec<(f64, Option<String>, Cell)>>,
    truth_count: u64,
    /// (device, t, floor, cell, published confidence).
    fixes: Vec<(String, f64, Option<String>, Cell, f32)>,
}

/// How well the fixes of a replay match its truth.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Score {
    /// On a building of several floors, the share of matched fixes on the
    /// true floor; the figures below count only those.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub floor_accuracy: Option<f64>,
    /// Share of matched fixes in exactly the true cell.
    pub exact: Option<f64>,
    /// Share of matched fixes within 1 cell (Euclidean) of the truth.
    pub within_1: Option<f64>,
    /// Share of matched fixes within 2 cells of the truth.
    pub within_2: Option<f64>,
    pub mean_error_cells: Option<f64>,
    pub mean_error_m: Option<f64>,
    /// Location messages seen.
    pub fixes: u64,
    /// Fixes with a truth of the same device within the tolerance: the ones scored.
    pub matched: u64,
    /// Truth events seen.
    pub truths: u64,
    pub tolerance_s: f64,
    /// The matched fixes' published confidence against the share of them
    /// within one cell on the true floor. Fixes published as unknown (under
    /// `[localizer] min_confidence`, or on a building with the floor
    /// unknown) name no cell and are not in it; `min_confidence = 0` puts
    /// every fix of a known floor in.
    #[serde(flatten)]
    pub confidence: Reliability,
}

impl Scorer {
    /// `tolerance_s`: how far in time a truth may be from the fix it scores.
    pub fn new(tolerance_s: f64) -> Scorer {
        Scorer {
            tolerance_s,
            truths: HashMap::new(),
            truth_count: 0,
            fixes: Vec::new(),
        }
    }

    pub(crate) fn truth(&mut self, truth: &Truth) {
        self.truth_count += 1;
        self.truths.entry(truth.device.clone()).or_default().push((
            truth.t,
            truth.floor.clone(),
            truth.cell,
        ));
    }

    /// Takes a fix; an unknown location names no cell to score.
    pub(crate) fn location(&mut self, location: &Location) {
        if let Some(cell) = location.cell {
            let floor = location.floor.as_ref().map(|f| f.name.clone());
            self.fixes.push((
                location.device.clone(),
                location.t,
                floor,
                cell,
                location.confidence,
            ));
        }
    }

    /// The scorer as a sink of the runtime: it takes the locations and the
    /// truths that pass through, and sends the score on the channel when
    /// the runtime shuts it down.
    pub fn sink(self, building: Arc<Building>) -> (ScoreSink, oneshot::Receiver<Score>) {
        let (done, score) = oneshot::channel();
        (
            ScoreSink {
                scorer: self,
                building,
                done,
            },
            score,
        )
    }

    /// The score on `building`: a truth or fix without a floor is on its
    /// lowest (the only floor of a one-floor site), and a fix on another
    /// floor than its truth's counts against `floor_accuracy` and has no
    /// error in cells.
    pub(crate) fn score(mut self, building: &Building) -> Score {
        for truths in self.truths.values_mut() {
            truths.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
        let floors = building.floors();
        let (mut matched, mut on_floor, mut confidences) = (0u64, Vec::new(), Vec::new());
        for (device, t, floor, cell, confidence) in &self.fixes {
            let Some((_, truth_floor, truth)) = self
                .truths
                .get(device)
                .and_then(|truths| nearest(truths, *t))
                .filter(|(truth_t, ..)| (truth_t - t).abs() <= self.tolerance_s)
            else {
                continue;
            };
            matched += 1;
            let floor_of = |name: &Option<String>| match name {
                Some(name) => building.floor_named(name),
                None => Some(0),
            };
            let error = match floor_of(truth_floor) {
                Some(f) if floor_of(floor) == Some(f) => {
                    let error = cell.distance(*truth);
                    on_floor.push((f, error));
                    error
                }
                _ => f64::INFINITY,
            };
            confidences.push((*confidence, error));
        }
        let cells: Vec<f64> = on_floor.iter().map(|&(_, e)| e).collect();
        // Metres per cell of the floors the errors are on, when they agree
        // (always on one floor); else each error in its floor's metres.
        let cell_m = floors[on_floor.first().map_or(0, |e| e.0)].site.cell_m;
        let summary = if on_floor
            .iter()
            .all(|&(f, _)| floors[f].site.cell_m == cell_m)
        {
            ErrorSummary::of(&cells, cell_m)
        } else {
            ErrorSummary::of(&cells, 1.0).map(|s| ErrorSummary {
                mean_error_m: on_floor
                    .iter()
                    .map(|&(f, e)| e * floors[f].site.cell_m)
                    .sum::<f64>()
                    / cells.len() as f64,
                ..s
            })
        };
        Score {
            floor_accuracy: (building.is_multi_floor() && matched > 0)
                .then(|| on_floor.len() as f64 / matched as f64),
            exact: summary.as_ref().map(|s| s.exact),
            within_1: summary.as_ref().map(|s| s.within_1),
            within_2: summary.as_ref().map(|s| s.within_2),
            mean_error_cells: summary.as_ref().map(|s| s.mean_error_cells),
            mean_error_m: summary.as_ref().map(|s| s.mean_error_m),
            fixes: self.fixes.len() as u64,
            matched,
            truths: self.truth_count,
            tolerance_s: self.tolerance_s,
            confidence: Reliability::of(&confidences),
        }
    }
}

/// A [`Scorer`] fed by the runtime.
pub struct ScoreSink {
    scorer: Scorer,
    building: Arc<Building>,
    done: oneshot::Sender<Score>,
}

impl Sink for ScoreSink {
    fn name(&self) -> &'static str {
        "score"
    }

    fn send(&mut self, outputs: &[Output]) -> anyhow::Result<()> {
        for output in outputs {
            match output {
                Output::Location(l) => self.scorer.location(l),
                Output::Truth(t) => self.scorer.truth(t),
                _ => {}
            }
        }
        Ok(())
    }

    fn shutdown(self: Box<Self>) -> BoxFuture<'static, anyhow::Result<()>> {
        let ScoreSink {
            scorer,
            building,
            done,
        } = *self;
        // Nobody waiting for the score is no failure of the sink's.
        let _ = done.send(scorer.score(&building));
        Box::pin(std::future::ready(Ok(())))
    }
}

/// Accuracy figures of a set of position errors (in cells), shared by replay
/// scoring and offline evaluation so both count the same way.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ErrorSummary {
    /// Share of errors of exactly 0 (the true cell).
    pub exact: f64,
    /// Share of errors ≤ 1 cell.
    pub within_1: f64,
    /// Share of errors ≤ 2 cells.
    pub within_2: f64,
    pub mean_error_cells: f64,
    pub mean_error_m: f64,
    /// Percentiles of the error (nearest rank), in cells and metres.
    pub median_error_cells: f64,
    pub p75_error_cells: f64,
    pub p90_error_cells: f64,
    pub median_error_m: f64,
    pub p75_error_m: f64,
    pub p90_error_m: f64,
}

impl ErrorSummary {
    /// `None` for no errors at all.
    pub fn of(errors: &[f64], cell_m: f64) -> Option<ErrorSummary> {
        if errors.is_empty() {
            return None;
        }
        let n = errors.len() as f64;
        // Distances between cell centres are exact for 0, 1 and 2; the
        // epsilon only guards against rounding in sums.
        let share = |max: f64| errors.iter().filter(|&&e| e <= max + 1e-9).count() as f64 / n;
        let mean = errors.iter().sum::<f64>() / n;
        let mut sorted = errors.to_vec();
        sorted.sort_by(f64::total_cmp);
        let percentile = |q: f64| sorted[((n * q).ceil() as usize).clamp(1, sorted.len()) - 1];
        Some(ErrorSummary {
            exact: share(0.0),
            within_1: share(1.0),
            within_2: share(2.0),
            mean_error_cells: mean,
            mean_error_m: mean * cell_m,
            median_error_cells: percentile(0.5),
            p75_error_cells: percentile(0.75),
            p90_error_cells: percentile(0.9),
            median_error_m: percentile(0.5) * cell_m,
            p75_error_m: percentile(0.75) * cell_m,
            p90_error_m: percentile(0.9) * cell_m,
        })
    }
}

/// Published confidence against what it promises: fixes by confidence in
/// tenths, each tenth's share within one cell of the truth, and the gaps.
/// Shared by replay scoring and offline evaluation, as [`ErrorSummary`] is.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Reliability {
    pub reliability: Vec<ReliabilityBin>,
    /// The largest |mean confidence − share within one cell| over the bins
    /// holding at least [`RELIABLE_BIN`] fixes: 0 is perfectly calibrated,
    /// or no bin held that many (the bins say which).
    pub confidence_gap_max: f64,
    /// The same gap averaged over every fix (the expected calibration
    /// error): less noisy than the largest, which one sparse bin can set.
    pub confidence_gap_mean: f64,
}

/// Fixes whose confidence fell in `[from, to)`.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ReliabilityBin {
    pub from: f64,
    pub to: f64,
    pub fixes: usize,
    pub mean_confidence: f64,
    /// Share of them within one cell of the truth (what confidence promises).
    pub within_1: f64,
}

/// Bins with fewer fixes are listed but too noisy to judge calibration by.
pub const RELIABLE_BIN: usize = 30;

impl Reliability {
    /// The table of (published confidence, error in cells) pairs; an
    /// infinite error (a fix on the wrong floor) is never within one cell.
    pub fn of(fixes: &[(f32, f64)]) -> Reliability {
        let mut bins: Vec<ReliabilityBin> = (0..10)
            .map(|i| ReliabilityBin {
                from: f64::from(i) / 10.0,
                to: f64::from(i + 1) / 10.0,
                ..ReliabilityBin::default()
            })
            .collect();
        for &(confidence, error) in fixes {
            let bin = &mut bins[((confidence * 10.0) as usize).min(9)];
            bin.fixes += 1;
            bin.mean_confidence += f64::from(confidence);
            bin.within_1 += f64::from(u8::from(error <= 1.0 + 1e-9));
        }
        let (mut gap_max, mut gap_sum) = (0.0f64, 0.0f64);
        for bin in &mut bins {
            if bin.fixes > 0 {
                bin.mean_confidence /= bin.fixes as f64;
                bin.within_1 /= bin.fixes as f64;
            }
            let gap = (bin.mean_confidence - bin.within_1).abs();
            gap_sum += gap * bin.fixes as f64;
            if bin.fixes >= RELIABLE_BIN {
                gap_max = gap_max.max(gap);
            }
        }
        Reliability {
            reliability: bins,
            confidence_gap_max: gap_max,
            confidence_gap_mean: gap_sum / fixes.len().max(1) as f64,
        }
    }
}

impl std::fmt::Display for Reliability {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        writeln!(f, "published confidence   fixes  mean   within 1 cell")?;
        for bin in self.reliability.iter().filter(|b| b.fixes > 0) {
            writeln!(
                f,
                "{:.1}–{:.1}  {:>17}  {:.3}  {:.3}",
                bin.from, bin.to, bin.fixes, bin.mean_confidence, bin.within_1
            )?;
        }
        let largest = if self.reliability.iter().any(|b| b.fixes >= RELIABLE_BIN) {
            format!("{:.3}", self.confidence_gap_max)
        } else {
            "-".to_owned()
        };
        write!(
            f,
            "calibration gap: largest {largest} (bins of {RELIABLE_BIN}+ fixes), mean {:.3} (over fixes)",
            self.confidence_gap_mean
        )
    }
}

/// The truth nearest to `t` in a time-sorted list (the earlier one on a tie).
fn nearest<T>(truths: &[(f64, T, Cell)], t: f64) -> Option<&(f64, T, Cell)> {
    let after = truths.partition_point(|(truth_t, ..)| *truth_t < t);
    let before = after.checked_sub(1).map(|i| &truths[i]);
    let after = truths.get(after);
    match (before, after) {
        (Some(b), Some(a)) => Some(if t - b.0 <= a.0 - t { b } else { a }),
        (b, a) => b.or(a),
    }
}

impl std::fmt::Display for Score {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let show = |v: Option<f64>| v.map_or("-".to_owned(), |v| format!("{v:.3}"));
        writeln!(f, "fixes            {}", self.fixes)?;
        writeln!(
            f,
            "matched          {} (truth of the same device within {} s)",
            self.matched, self.tolerance_s
        )?;
        writeln!(f, "truths           {}", self.truths)?;
        if let Some(share) = self.floor_accuracy {
            writeln!(
                f,
                "floor_accuracy   {share:.3} (the figures below: on the true floor)"
            )?;
        }
        writeln!(f, "exact            {}", show(self.exact))?;
        writeln!(f, "within_1         {}", show(self.within_1))?;
        writeln!(f, "within_2         {}", show(self.within_2))?;
        writeln!(f, "mean_error_cells {}", show(self.mean_error_cells))?;
        writeln!(f, "mean_error_m     {}", show(self.mean_error_m))?;
        write!(f, "{}", self.confidence)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::publish::FloorName;
    use crate::site::Site;
    use std::path::Path;

    fn site() -> Building {
        let text = "name = \"t\"\ncell_m = 0.5\nmap = '''\n#####\n#####\n#####\n'''\n";
        Building::of_site(Arc::new(Site::parse(text, Path::new("t.toml")).unwrap()))
    }

    fn fix(device: &str, t: f64, cell: Cell) -> Location {
        crate::test_support::location(device, t, Some(cell), None)
    }

    fn truth(device: &str, t: f64, cell: Cell) -> Truth {
        Truth {
            t,
            device: device.into(),
            cell,
            floor: None,
        }
    }

    #[test]
    fn matches_each_fix_to_the_nearest_truth_of_its_device() {
        let mut s = Scorer::new(2.0);
        s.truth(&truth("a", 0.0, Cell::new(0, 0)));
        s.truth(&truth("a", 10.0, Cell::new(4, 0)));
        s.truth(&truth("b", 4.0, Cell::new(0, 2)));
        s.location(&fix("a", 1.0, Cell::new(0, 0))); // exact (truth at 0)
        s.location(&fix("a", 9.0, Cell::new(3, 1))); // truth at 10: √2 off
        s.location(&fix("a", 5.0, Cell::new(0, 0))); // nearest truth 5 s away: unmatched
        s.location(&fix("b", 4.5, Cell::new(3, 2))); // 3 cells off
        s.location(&fix("c", 4.5, Cell::new(3, 2))); // no truth for c
        let score = s.score(&site());
        assert_eq!(score.fixes, 5);
        assert_eq!(score.matched, 3);
        assert_eq!(score.truths, 3);
        assert_eq!(score.exact, Some(1.0 / 3.0));
        assert_eq!(score.within_1, Some(1.0 / 3.0));
        assert_eq!(score.within_2, Some(2.0 / 3.0));
        let mean = (0.0 + 2f64.sqrt() + 3.0) / 3.0;
        assert!((score.mean_error_cells.unwrap() - mean).abs() < 1e-12);
        assert!((score.mean_error_m.unwrap() - mean * 0.5).abs() < 1e-12);
    }

    #[test]
    fn ignores_unknown_locations_and_reports_nothing_without_matches() {
        let mut s = Scorer::new(4.0);
        let mut unknown = fix("a", 1.0, Cell::new(0, 0));
        unknown.cell = None;
        s.location(&unknown);
        let score = s.score(&site());
        assert_eq!((score.fixes, score.matched), (0, 0));
        assert_eq!(score.exact, None);
        assert_eq!(score.mean_error_m, None);
    }

    #[test]
    fn ties_go_to_the_earlier_truth() {
        let truths = [(0.0, (), Cell::new(0, 0)), (2.0, (), Cell::new(1, 0))];
        assert_eq!(nearest(&truths, 1.0), Some(&truths[0]));
        assert_eq!(nearest(&truths, 1.5), Some(&truths[1]));
        assert_eq!(nearest(&truths, -3.0), Some(&truths[0]));
        assert_eq!(nearest(&truths, 9.0), Some(&truths[1]));
        assert_eq!(nearest::<()>(&[], 9.0), None);
    }

    /// On a building, a fix on its truth's floor is scored in that floor's
    /// cells and metres, one on another floor only counts against the
    /// floor accuracy, and a truth without a floor is on the lowest.
    #[test]
    fn a_building_s_fixes_are_scored_on_their_truth_s_floor() {
        let building = Building::parse(
            "name = \"b\"\n[[floors]]\nname = \"G\"\nlevel = 0\nsite = \"g.toml\"\n\
             [[floors]]\nname = \"L1\"\nlevel = 1\nsite = \"l1.toml\"\n",
            Path::new("b.toml"),
            |path| {
                let cell_m = if path.ends_with("g.toml") {
                    "0.5"
                } else {
                    "2.0"
                };
                let text =
                    format!("name = \"x\"\ncell_m = {cell_m}\nmap = '''\n#####\n#####\n'''\n");
                Site::parse(&text, path)
            },
        )
        .unwrap();
        let on = |device: &str, cell: Cell, floor: &str, level: i32| Location {
            floor: Some(FloorName {
                level,
                name: floor.into(),
            }),
            confidence: 0.95,
            ..fix(device, 0.0, cell)
        };
        let on_l1 = |device: &str, cell: Cell| Truth {
            floor: Some("L1".into()),
            ..truth(device, 0.0, cell)
        };
        let mut s = Scorer::new(1.0);
        s.truth(&truth("a", 0.0, Cell::new(0, 0))); // no floor: the lowest, G
        s.truth(&on_l1("b", Cell::new(4, 1)));
        s.truth(&on_l1("c", Cell::new(0, 0)));
        s.location(&on("a", Cell::new(1, 0), "G", 0)); // 1 cell, 0.5 m
        s.location(&on("b", Cell::new(4, 0), "L1", 1)); // 1 cell, 2 m
        s.location(&on("c", Cell::new(0, 0), "G", 0)); // the wrong floor
        let score = s.score(&building);
        assert_eq!(score.matched, 3);
        assert_eq!(score.floor_accuracy, Some(2.0 / 3.0));
        assert_eq!(score.mean_error_cells, Some(1.0));
        assert_eq!(score.exact, Some(0.0));
        assert!((score.mean_error_m.unwrap() - 1.25).abs() < 1e-12);
        // The fix on the wrong floor is judged too, and was not within a cell.
        let top = &score.confidence.reliability[9];
        assert_eq!((top.fixes, top.within_1), (3, 2.0 / 3.0));
        // Three fixes are too few to judge a tenth by.
        assert!(score.to_string().contains("largest - "), "{score}");
        // A one-floor site has no floor accuracy to report.
        assert_eq!(Scorer::new(1.0).score(&site()).floor_accuracy, None);
    }
}
