//! Localization on a labelled survey: split the rows, build the localizer from
//! the training part, locate every held-out row (through the tracker, in time
//! order, when one is used) and compare with the label.
//!
//! Two splits, 70/30, averaged over seeds:
//! - `random`: by row. Neighbouring rows of the same walk are nearly identical,
//!   so this leaks: a held-out row usually has a twin in training.
//! - `session`: by whole walking sessions (a gap over 20 s starts a new one), the
//!   honest protocol: it is what a new visitor meets.
//!
//! In both, the held-out rows of one session form one sequence for the tracker,
//! in time order. Errors are Euclidean distances between cell centres, in cells.

use std::sync::Arc;
use std::time::Instant;

use rand::SeedableRng;
use rand::rngs::Xoshiro256PlusPlus;
use rand::seq::SliceRandom;
use serde::Serialize;

use crate::locate::calibrate::{DEFAULT_CELL_PRIOR_READINGS, FitOptions, Window, calibrate};
use crate::locate::calibration::Calibration;
use crate::locate::gain::Gains;
use crate::locate::knn;
use crate::locate::onnx::Onnx;
use crate::locate::pathloss::anchors;
use crate::locate::radiomap::RadioMap;
use crate::locate::rehearsal;
use crate::locate::survey::{Sample, Survey, sessions};
use crate::locate::tracker::TrackerConfig;
use crate::locate::tracker::{Tracker, TrackerKind};
use crate::locate::window::WindowConfig;
use crate::locate::{Localizer, LocalizerConfig, LocalizerError, Method};
use crate::score::{ErrorSummary, Reliability};
use crate::site::Site;
use crate::train::job::{Options, Progress, train_cells};

pub use crate::locate::survey::SESSION_GAP_S;

/// Share of rows (random) or sessions (session) held out for testing.
const TEST_SHARE: f64 = 0.3;

#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Split {
    Random,
    Session,
}

/// Which rows are held out: drawn per seed, or fixed (`--train`/`--test`).
#[derive(Clone, Debug)]
pub enum Holdout {
    Drawn(Split),
    /// `true` for the test rows; evaluated once.
    Fixed(Vec<bool>),
}

/// What to evaluate.
#[derive(Clone, Debug)]
pub struct Setup {
    pub holdout: Holdout,
    /// A gap longer than this (seconds) between rows starts a new walking session.
    pub session_gap_s: f64,
    pub seeds: u64,
    pub method: Method,
    pub localizer: LocalizerConfig,
    pub window: WindowConfig,
    pub tracker: TrackerConfig,
    /// Fixed-lag smoothing over this many later windows (0: the online filter).
    pub smooth_lag: usize,
    /// Unlabelled scans the survey-free model is calibrated on first.
    pub calibrate_from: Option<UnlabelledRows>,
    /// EM iterations refining a radio map per cell in that calibration (0: none).
    pub calibrate_cells: usize,
    /// Added to every held-out reading: a phone hearing that much louder.
    pub receiver_offset_db: f32,
}

/// The figures, averaged over seeds, and the reliability of the published
/// confidence over all seeds' fixes.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Metrics {
    #[serde(flatten)]
    pub errors: ErrorSummary,
    /// Localizer plus tracker time per fix, single-threaded.
    pub us_per_fix: f64,
    /// Published confidence against the share of fixes within one cell.
    #[serde(flatten)]
    pub confidence: Reliability,
}

/// Metrics plus every error (all seeds), for plotting.
pub struct Outcome {
    pub metrics: Metrics,
    pub errors: Vec<f64>,
    /// Every held-out row's fix, for `--rows`.
    pub rows: Vec<RowFix>,
}

/// One held-out row's fix.
#[derive(Clone, Debug)]
pub struct RowFix {
    pub seed: u64,
    pub session: usize,
    /// The row's index in the survey file (0 = first data row).
    pub row: usize,
    pub t: f64,
    pub truth: crate::site::Cell,
    pub cell: crate::site::Cell,
    pub confidence: f32,
    pub error_cells: f64,
}

#[derive(Debug, thiserror::Error)]
pub enum EvalError {
    #[error("the survey has no time column; sessions and tracking need `date` or `t`")]
    NoTime,
    #[error(
        "too few rows or sessions to split 70/30: {rows} rows in {sessions} walking sessions \
         (a gap over {gap_s} s starts one); try --split random, a smaller --session-gap, or \
         --train and --test"
    )]
    TooSmall {
        rows: usize,
        sessions: usize,
        gap_s: f64,
    },
    #[error(transparent)]
    Localizer(#[from] LocalizerError),
    #[error("training the cell classifier: {0:#}")]
    Training(anyhow::Error),
}

/// What a localizer is built from in an evaluation: its settings, the site
/// and the surveyed rows it may learn from (never those it is scored on).
pub(super) struct Surveyed<'a> {
    pub(super) localizer: &'a LocalizerConfig,
    pub(super) window: &'a WindowConfig,
    pub(super) tracker: &'a TrackerConfig,
    pub(super) site: &'a Arc<Site>,
    /// The anchors' ids, in the fingerprints' order.
    pub(super) ids: &'a [String],
    pub(super) samples: &'a [&'a Sample],
    /// The survey-free model's calibration, when it is evaluated with one.
    pub(super) calibration: Option<&'a Calibration>,
}

/// The localizer of `method` from `from`; `onnx` trains the cell classifier
/// where the caller can (it needs the survey's rows, not just samples).
pub(super) fn surveyed_localizer<E: From<LocalizerError>>(
    method: Method,
    from: Surveyed<'_>,
    onnx: impl FnOnce() -> Result<Box<dyn Localizer>, E>,
) -> Result<Box<dyn Localizer>, E> {
    let Surveyed {
        localizer,
        window,
        tracker,
        site,
        ids,
        samples,
        calibration,
    } = from;
    Ok(match method {
        Method::Knn => knn::surveyed(&localizer.knn, site, tracker, samples, window.missing_dbm)?,
        Method::Radiomap => Box::new(RadioMap::new(
            &localizer.radiomap,
            site,
            ids,
            window.orientation,
            tracker,
            samples,
        )?),
        Method::Onnx => onnx()?,
        Method::Auto => {
            crate::locate::auto::surveyed(localizer, site, ids, window, tracker, samples)?
        }
        Method::Strongest => rehearsal::strongest(&localizer.pathloss, site, window, tracker)?,
        Method::Pathloss => {
            rehearsal::path_loss(&localizer.pathloss, calibration, site, window, tracker)?
        }
    })
}

/// Iterations of the cell classifier trained for each split (as `gangway train`).
const CELL_CLASSIFIER_ITERATIONS: usize = 3_000;

/// Trains the `onnx` localizer's cell classifier on a training split, writes it
/// as ONNX and loads it back through tract, exactly as a deployed model runs.
fn train_cell_classifier(site: &Site, train: &Survey, seed: u64) -> Result<Onnx, EvalError> {
    struct Silent;
    impl Progress for Silent {
        fn stage(&mut self, _: &str, _: usize) {}
        fn step(&mut self, _: usize, _: &[(&str, f32)]) {}
        fn done(&mut self) {}
    }
    let dir = tempfile::tempdir().map_err(|e| EvalError::Training(e.into()))?;
    let options = Options {
        iterations: 0,
        batch: 64,
        seed,
        conditional: false,
        classifier_iterations: CELL_CLASSIFIER_ITERATIONS,
        heldout_share: 0.0,
        checkpoint_every: None,
        accept_failed: false,
        threads: 1,
    };
    let trained =
        train_cells(site, train, &options, dir.path(), &mut Silent).map_err(EvalError::Training)?;
    Ok(Onnx::load(&trained.file, site)?)
}

pub fn evaluate(site: &Arc<Site>, survey: &Survey, setup: &Setup) -> Result<Outcome, EvalError> {
    let needs_time = matches!(setup.holdout, Holdout::Drawn(Split::Session))
        || setup.tracker.kind == TrackerKind::Hmm;
    let times: Vec<f64> = if needs_time {
        survey
            .samples
            .iter()
            .map(|s| s.t.ok_or(EvalError::NoTime))
            .collect::<Result<_, _>>()?
    } else {
        (0..survey.samples.len()).map(|i| i as f64).collect()
    };
    let walks = Sessions::of(&times, setup.session_gap_s);
    let (session, sessions) = (&walks.session, walks.count);
    let walk_rows = walks.sequences();
    // Survey-free with calibration: fitted once, on unlabelled rows only, so
    // it is the same for every split.
    let calibrated = match (&setup.calibrate_from, setup.method) {
        (Some(rows), Method::Pathloss) => Some(calibration(site, survey, setup, rows)?),
        _ => None,
    };

    let mut per_seed = Vec::new();
    let mut errors = Vec::new();
    let mut confidences = Vec::new();
    let mut row_fixes = Vec::new();
    let seeds = match setup.holdout {
        Holdout::Fixed(_) => 1,
        Holdout::Drawn(_) => setup.seeds,
    };
    for seed in 0..seeds {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let test: Vec<bool> = match &setup.holdout {
            Holdout::Fixed(test) => test.clone(),
            Holdout::Drawn(Split::Random) => {
                let mut rows: Vec<usize> = (0..survey.samples.len()).collect();
                rows.shuffle(&mut rng);
                let n_test = (rows.len() as f64 * TEST_SHARE).round() as usize;
                let mut test = vec![false; rows.len()];
                rows[..n_test].iter().for_each(|&r| test[r] = true);
                test
            }
            Holdout::Drawn(Split::Session) => {
                let mut ids: Vec<usize> = (0..sessions).collect();
                ids.shuffle(&mut rng);
                let n_test = (sessions as f64 * TEST_SHARE).round() as usize;
                let held: Vec<bool> = (0..sessions).map(|s| ids[..n_test].contains(&s)).collect();
                session.iter().map(|&s| held[s]).collect()
            }
        };
        let train_rows: Vec<usize> = (0..survey.samples.len()).filter(|&i| !test[i]).collect();
        let train: Vec<&Sample> = train_rows.iter().map(|&i| &survey.samples[i]).collect();
        if train.is_empty() || test.iter().all(|t| !t) {
            return Err(EvalError::TooSmall {
                rows: survey.samples.len(),
                sessions,
                gap_s: setup.session_gap_s,
            });
        }
        let mut localizer = surveyed_localizer(
            setup.method,
            Surveyed {
                localizer: &setup.localizer,
                window: &setup.window,
                tracker: &setup.tracker,
                site,
                ids: &survey.anchors,
                samples: &train,
                calibration: calibrated.as_ref(),
            },
            || -> Result<Box<dyn Localizer>, EvalError> {
                let onnx = train_cell_classifier(site, &survey.subset(&train_rows), seed)?;
                Ok(Box::new(onnx))
            },
        )?;
        let mut tracker = Tracker::new(setup.tracker.clone(), site.clone());
        let entities: Vec<Arc<str>> = (0..sessions)
            .map(|s| Arc::from(format!("session-{s}")))
            .collect();
        let mut rssi = vec![0.0f32; survey.anchors.len()];
        let mut heard = vec![false; survey.anchors.len()];
        let mut seed_errors = Vec::new();
        let started = Instant::now();
        // Held-out rows, one time-ordered sequence per session.
        let sequences: Vec<Vec<usize>> = walk_rows
            .iter()
            .map(|rows| rows.iter().copied().filter(|&r| test[r]).collect())
            .collect();
        // Each session is one device, its gain learned as the daemon learns
        // it: online, from the fixes before (so not under smoothing, whose
        // fixes come after the windows they correct).
        let mut gains =
            (setup.localizer.device_gains && setup.smooth_lag == 0).then(Gains::default);
        for (s, rows) in sequences.iter().enumerate().filter(|(_, r)| !r.is_empty()) {
            let mut windows = Vec::with_capacity(rows.len());
            let mut fixes = Vec::with_capacity(rows.len());
            for &row in rows {
                for (a, r) in survey.samples[row].rssi.iter().enumerate() {
                    heard[a] = r.is_some();
                    rssi[a] = r.map_or(setup.window.missing_dbm, |r| {
                        f32::from(r) + setup.receiver_offset_db
                    });
                }
                let mut ll = vec![0.0f32; site.open_cells().len()];
                match &mut gains {
                    Some(gains) => gains.log_likelihood(
                        localizer.as_mut(),
                        &entities[s],
                        &rssi,
                        &heard,
                        &mut ll,
                    ),
                    None => localizer.log_likelihood(&rssi, &heard, &mut ll),
                }
                if setup.smooth_lag > 0 {
                    windows.push((times[row], ll));
                    continue;
                }
                let fix = tracker.update(&entities[s], times[row], &ll);
                if let (Some(gains), Some(cell)) = (&mut gains, site.open_index(fix.cell)) {
                    gains.learn(
                        localizer.as_mut(),
                        &entities[s],
                        times[row],
                        &rssi,
                        &heard,
                        cell,
                    );
                }
                fixes.push(fix);
            }
            if setup.smooth_lag > 0 {
                fixes = tracker.smooth(&windows, setup.smooth_lag);
            }
            for (fix, &row) in fixes.iter().zip(rows) {
                let truth = survey.samples[row].cell;
                let error = fix.cell.distance(truth);
                let heard_count = survey.samples[row].rssi.iter().flatten().count();
                let confidence = localizer.confidence(fix.confidence, heard_count);
                seed_errors.push(error);
                confidences.push((confidence, error));
                row_fixes.push(RowFix {
                    seed,
                    session: session[row],
                    row,
                    t: times[row],
                    truth,
                    cell: fix.cell,
                    confidence,
                    error_cells: error,
                });
            }
        }
        let us_per_fix = started.elapsed().as_secs_f64() * 1e6 / seed_errors.len() as f64;
        per_seed.push(metrics(&seed_errors, site.cell_m, us_per_fix));
        errors.extend(seed_errors);
    }
    Ok(Outcome {
        metrics: Metrics {
            confidence: Reliability::of(&confidences),
            ..average(&per_seed)
        },
        errors,
        rows: row_fixes,
    })
}

/// Rows in time order (the UCI file is newest first) and the walking session
/// of each: a gap over `gap_s` starts a new one.
struct Sessions {
    order: Vec<usize>,
    session: Vec<usize>,
    count: usize,
}

impl Sessions {
    fn of(times: &[f64], gap_s: f64) -> Sessions {
        let (order, session) = sessions(times, gap_s);
        let count = order.last().map_or(0, |&i| session[i] + 1);
        Sessions {
            order,
            session,
            count,
        }
    }

    /// The rows of each session, in time order.
    fn sequences(&self) -> Vec<Vec<usize>> {
        let mut out = vec![Vec::new(); self.count];
        for &row in &self.order {
            out[self.session[row]].push(row);
        }
        out
    }
}

/// Unlabelled scans for calibration: one row per window, as the evaluation
/// localizes them.
#[derive(Clone, Debug)]
pub struct UnlabelledRows {
    pub rows: Vec<(f64, Vec<Option<i16>>)>,
}

/// The survey-free model fitted by EM to unlabelled rows (whole sessions,
/// positions unknown), starting from the configured model.
fn calibration(
    site: &Arc<Site>,
    survey: &Survey,
    setup: &Setup,
    unlabelled: &UnlabelledRows,
) -> Result<Calibration, EvalError> {
    let times: Vec<f64> = unlabelled.rows.iter().map(|r| r.0).collect();
    let trajectories: Vec<Vec<Window>> = Sessions::of(&times, setup.session_gap_s)
        .sequences()
        .into_iter()
        .map(|rows| {
            rows.into_iter()
                .map(|i| Window {
                    t: unlabelled.rows[i].0,
                    rssi: unlabelled.rows[i]
                        .1
                        .iter()
                        .map(|r| r.map(f32::from))
                        .collect(),
                    cell: None,
                })
                .collect()
        })
        .collect();
    let start = anchors(
        site,
        setup.window.orientation,
        &setup.localizer.pathloss,
        None,
    );
    let options = FitOptions {
        iterations: crate::locate::calibrate::CALIBRATION_ITERATIONS,
        cell_iterations: setup.calibrate_cells,
        cell_prior_readings: DEFAULT_CELL_PRIOR_READINGS,
    };
    let fitted = calibrate(
        site,
        &survey.anchors,
        &start,
        &setup.tracker,
        &trajectories,
        &options,
    )?;
    Ok(fitted.calibration)
}

fn metrics(errors: &[f64], cell_m: f64, us_per_fix: f64) -> Metrics {
    Metrics {
        errors: ErrorSummary::of(errors, cell_m).expect("a split holds out at least one row"),
        us_per_fix,
        ..Metrics::default()
    }
}

fn average(all: &[Metrics]) -> Metrics {
    let n = all.len() as f64;
    let mean = |f: fn(&Metrics) -> f64| all.iter().map(f).sum::<f64>() / n;
    Metrics {
        errors: ErrorSummary {
            exact: mean(|m| m.errors.exact),
            within_1: mean(|m| m.errors.within_1),
            within_2: mean(|m| m.errors.within_2),
            mean_error_cells: mean(|m| m.errors.mean_error_cells),
            mean_error_m: mean(|m| m.errors.mean_error_m),
            median_error_cells: mean(|m| m.errors.median_error_cells),
            p75_error_cells: mean(|m| m.errors.p75_error_cells),
            p90_error_cells: mean(|m| m.errors.p90_error_cells),
            median_error_m: mean(|m| m.errors.median_error_m),
            p75_error_m: mean(|m| m.errors.p75_error_m),
            p90_error_m: mean(|m| m.errors.p90_error_m),
        },
        us_per_fix: mean(|m| m.us_per_fix),
        ..Metrics::default()
    }
}
