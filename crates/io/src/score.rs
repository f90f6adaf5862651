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
use crate::site::{Cell, Site};

/// Collects truths and fixes during a replay.
#[derive(Debug)]
pub struct Scorer {
    tolerance_s: f64,
    /// Per device: (t, cell) in arrival order.
    truths: HashMap<String, Vec<(f64, Cell)>>,
    truth_count: u64,
    fixes: Vec<(String, f64, Cell)>,
}

/// How well the fixes of a replay match its truth.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Score {
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
        self.truths
            .entry(truth.device.clone())
            .or_default()
            .push((truth.t, truth.cell));
    }

    /// Takes a fix; an unknown location names no cell to score.
    pub(crate) fn location(&mut self, location: &Location) {
        if let Some(cell) = location.cell {
            self.fixes.push((location.device.clone(), location.t, cell));
        }
    }

    /// The scorer as a sink of the runtime: it takes the locations and the
    /// truths that pass through, and sends the score on the channel when
    /// the runtime shuts it down.
    pub fn sink(self, site: Arc<Site>) -> (ScoreSink, oneshot::Receiver<Score>) {
        let (done, score) = oneshot::channel();
        (
            ScoreSink {
                scorer: self,
                site,
                done,
            },
            score,
        )
    }

    pub(crate) fn score(mut self, site: &Site) -> Score {
        for truths in self.truths.values_mut() {
            truths.sort_by(|a, b| a.0.total_cmp(&b.0));
        }
        let errors: Vec<f64> = self
            .fixes
            .iter()
            .filter_map(|(device, t, cell)| {
                self.truths
                    .get(device)
                    .and_then(|truths| nearest(truths, *t))
                    .filter(|(truth_t, _)| (truth_t - t).abs() <= self.tolerance_s)
                    .map(|(_, truth)| cell.distance(truth))
            })
            .collect();
        let summary = ErrorSummary::of(&errors, site.cell_m);
        let matched = errors.len() as u64;
        Score {
            exact: summary.as_ref().map(|s| s.exact),
            within_1: summary.as_ref().map(|s| s.within_1),
            within_2: summary.as_ref().map(|s| s.within_2),
            mean_error_cells: summary.as_ref().map(|s| s.mean_error_cells),
            mean_error_m: summary.as_ref().map(|s| s.mean_error_m),
            fixes: self.fixes.len() as u64,
            matched,
            truths: self.truth_count,
            tolerance_s: self.tolerance_s,
        }
    }
}

/// A [`Scorer`] fed by the runtime.
pub struct ScoreSink {
    scorer: Scorer,
    site: Arc<Site>,
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
        let ScoreSink { scorer, site, done } = *self;
        // Nobody waiting for the score is no failure of the sink's.
        let _ = done.send(scorer.score(&site));
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

/// The truth nearest to `t` in a time-sorted list (the earlier one on a tie).
fn nearest(truths: &[(f64, Cell)], t: f64) -> Option<(f64, Cell)> {
    let after = truths.partition_point(|(truth_t, _)| *truth_t < t);
    let before = after.checked_sub(1).map(|i| truths[i]);
    let after = truths.get(after).copied();
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
        writeln!(f, "exact            {}", show(self.exact))?;
        writeln!(f, "within_1         {}", show(self.within_1))?;
        writeln!(f, "within_2         {}", show(self.within_2))?;
        writeln!(f, "mean_error_cells {}", show(self.mean_error_cells))?;
        write!(f, "mean_error_m     {}", show(self.mean_error_m))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn site() -> Site {
        let text = "name = \"t\"\ncell_m = 0.5\nmap = '''\n#####\n#####\n#####\n'''\n";
        Site::parse(text, Path::new("t.toml")).unwrap()
    }

    fn fix(device: &str, t: f64, cell: Cell) -> Location {
        crate::test_support::location(device, t, Some(cell), None)
    }

    fn truth(device: &str, t: f64, cell: Cell) -> Truth {
        Truth {
            t,
            device: device.into(),
            cell,
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
        let truths = [(0.0, Cell::new(0, 0)), (2.0, Cell::new(1, 0))];
        assert_eq!(nearest(&truths, 1.0), Some(truths[0]));
        assert_eq!(nearest(&truths, 1.5), Some(truths[1]));
        assert_eq!(nearest(&truths, -3.0), Some(truths[0]));
        assert_eq!(nearest(&truths, 9.0), Some(truths[1]));
        assert_eq!(nearest(&[], 9.0), None);
    }
}
