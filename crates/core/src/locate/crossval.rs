//! Settings of a surveyed localizer chosen from its own survey: each
//! candidate localizes every walking session of the survey from a model built
//! on the other sessions, through the tracker, and the candidate with the
//! least mean error wins. The winner's held-out fixes also fit the map from
//! raw to published confidence ([`ConfidenceMap`]).
//!
//! This replaces constants that suit one floor: a survey of 24 beacons on
//! shelves wants another kernel than one of 13 on walls, and only its own
//! sessions can say which.

use std::sync::Arc;

use super::reliability::{ConfidenceMap, KnownFix};
use super::survey::{SESSION_GAP_S, Sample, sessions};
use super::tracker::{Tracker, TrackerConfig};
use super::{Localizer, LocalizerError};
use crate::site::Site;

/// How the survey's rows are split for cross-validation.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Folds {
    /// Whole walking sessions in this many folds (rows in turn when the
    /// survey has no times): cheap, for choosing between settings.
    Sessions(usize),
    /// Each walking session held out in turn, the model built from all the
    /// others, in at most [`MAX_FOLDS`] folds (sessions dealt round-robin
    /// beyond that, and rows without times): held-out fixes from models
    /// nearly as large as the final one, for fitting its confidence.
    EachSession,
}

/// Folds of [`Folds::EachSession`] at most: each trains on ≥ 95% of the
/// survey, and a survey of a thousand one-row sessions is not rebuilt a
/// thousand times.
const MAX_FOLDS: usize = 20;

/// The chosen candidate, its mean held-out error (cells) and the confidence
/// map of its held-out fixes.
pub(crate) struct Chosen<C> {
    pub candidate: C,
    pub error_cells: f64,
    pub confidence: ConfidenceMap,
}

/// Tries every candidate; `build` makes a localizer of one candidate from
/// some survey rows; anchors not heard read `missing_dbm`, as in a window.
pub(crate) fn choose<C: Clone, L: Localizer>(
    candidates: &[C],
    how: Folds,
    site: &Arc<Site>,
    tracker: &TrackerConfig,
    samples: &[&Sample],
    missing_dbm: f32,
    build: impl Fn(&C, &[&Sample]) -> Result<L, LocalizerError>,
) -> Result<Chosen<C>, LocalizerError> {
    let (folds, n_folds) = folds(samples, how);
    let mut best: Option<(Chosen<C>, Vec<KnownFix>)> = None;
    for candidate in candidates {
        let fixes = held_out_fixes(
            site,
            tracker,
            samples,
            (&folds, n_folds),
            missing_dbm,
            |rows| build(candidate, rows),
        )?;
        let error = fixes.iter().map(|f| f.error_cells).sum::<f64>() / fixes.len().max(1) as f64;
        if best.as_ref().is_none_or(|b| error < b.0.error_cells) {
            best = Some((
                Chosen {
                    candidate: candidate.clone(),
                    error_cells: error,
                    confidence: ConfidenceMap::default(),
                },
                fixes,
            ));
        }
    }
    let (mut chosen, fixes) = best.expect("at least one candidate");
    chosen.confidence = ConfidenceMap::fit(&fixes);
    Ok(chosen)
}

/// The fold of each row and the number of folds: whole walking sessions
/// when the survey has times (the honest split: a held-out session is a new
/// visitor), else rows in turn.
fn folds(samples: &[&Sample], how: Folds) -> (Vec<usize>, usize) {
    let times: Option<Vec<f64>> = samples.iter().map(|s| s.t).collect();
    let Some(times) = times else {
        let n = match how {
            Folds::Sessions(n) => n,
            Folds::EachSession => MAX_FOLDS,
        };
        return ((0..samples.len()).map(|i| i % n).collect(), n);
    };
    let (order, session) = sessions(&times, SESSION_GAP_S);
    let count = order.last().map_or(0, |&i| session[i] + 1);
    let n = match how {
        Folds::Sessions(n) => n,
        Folds::EachSession => count.clamp(1, MAX_FOLDS),
    };
    (session.into_iter().map(|s| s % n).collect(), n)
}

/// Every row localized by a model of the other folds, in time order through
/// the tracker: one known fix per row heard at all.
fn held_out_fixes<L: Localizer>(
    site: &Arc<Site>,
    tracker: &TrackerConfig,
    samples: &[&Sample],
    (folds, n_folds): (&[usize], usize),
    missing_dbm: f32,
    build: impl Fn(&[&Sample]) -> Result<L, LocalizerError>,
) -> Result<Vec<KnownFix>, LocalizerError> {
    let n_anchors = samples.first().map_or(0, |s| s.rssi.len());
    let mut fixes = Vec::new();
    let mut rssi = vec![0.0f32; n_anchors];
    let mut heard = vec![false; n_anchors];
    let mut ll = vec![0.0f32; site.open_cells().len()];
    for fold in 0..n_folds {
        let in_fold = |want: bool| -> Vec<&Sample> {
            samples
                .iter()
                .zip(folds)
                .filter(|(_, f)| (**f == fold) == want)
                .map(|(s, _)| *s)
                .collect()
        };
        let (mut held, train) = (in_fold(true), in_fold(false));
        if train.is_empty() || held.is_empty() {
            continue;
        }
        held.sort_by(|a, b| a.t.unwrap_or(0.0).total_cmp(&b.t.unwrap_or(0.0)));
        let mut localizer = build(&train)?;
        let mut tracker = Tracker::new(tracker.clone(), site.clone());
        let entity: Arc<str> = Arc::from("held-out");
        for s in held {
            for (a, r) in s.rssi.iter().enumerate() {
                heard[a] = r.is_some();
                rssi[a] = r.map_or(missing_dbm, f32::from);
            }
            if !heard.contains(&true) {
                continue;
            }
            localizer.log_likelihood(&rssi, &heard, &mut ll);
            let fix = tracker.update(&entity, s.t.unwrap_or(0.0), &ll);
            fixes.push(KnownFix {
                raw: fix.confidence,
                error_cells: fix.cell.distance(s.cell),
                heard: heard.iter().filter(|&&h| h).count(),
                group: fold,
            });
        }
    }
    Ok(fixes)
}
