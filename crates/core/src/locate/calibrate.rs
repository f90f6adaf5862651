//! Self-calibration of the survey-free radio model from what the gateway
//! hears, with no position known.
//!
//! Expectation-maximisation over the tracker's own belief: with the current
//! per-anchor [`Radio`] models, every recorded trajectory is localized with
//! the forward-backward smoother ([`Tracker::posteriors`]), which gives each
//! window a belief over cells. Each anchor's parameters are then refitted as if
//! every window had been taken at every cell in proportion to that belief:
//! detection (`range_m`, `range_slope`, `max_detection`) by maximum weighted
//! likelihood of heard/not heard against distance, and strength (`tx_dbm`,
//! `exponent`, `shadowing_db`) by weighted least squares of RSSI on
//! log-distance. Walls and the walking-speed limit keep the belief honest, so
//! the loop does not drift into "everything is everywhere". Windows of known
//! position (a few labelled points) enter with their belief fixed at that cell.
//!
//! Detection is fitted on a histogram over distance (0.25 m bins), so the cost
//! of a refit does not grow with the site; the E-step is one smoothing pass.
//!
//! Distance is not the building: shelves, walls and bodies make a beacon
//! louder on one side than the other, which no per-anchor curve can say.
//! With [`FitOptions::cell_iterations`], EM goes on to refine a radio map per
//! cell (each anchor's chance of being heard there and its mean RSSI), each
//! cell's estimate shrunk towards the per-anchor model by
//! [`FitOptions::cell_prior_readings`] readings' weight, so cells the walks
//! rarely reach keep the physics. It pays when the scans come from the phones
//! and the part of the floor that will be localized (what a gateway gathers
//! itself); scans of other phones or of other rooms teach the map their
//! quirks instead (measured on the UCI floor, `BENCHMARKS.md`).
//!
//! EM on unlabelled windows finds the radios that explain them best, which
//! is not always better than where it started; [`calibrate`], what users
//! and the daemon run, holds a quarter of the windows out and keeps only
//! what they confirm. [`fit`] keeps everything: for windows of known
//! position.

use std::collections::HashMap;
use std::sync::Arc;

use serde::Serialize;

use super::calibration::{AnchorCalibration, Calibration, CellCalibration};
use super::pathloss::{Anchor, DETECTION_BOUNDS, PathLoss, Radio};
use super::tracker::{Tracker, TrackerConfig};
use super::{Localizer, LocalizerError};
use crate::sign_test::sign_test;
use crate::site::{Cell, Site};

/// One window of a trajectory: when, what was heard (one slot per anchor,
/// `None` when silent) and, when known, where.
#[derive(Clone, Debug)]
pub struct Window {
    pub t: f64,
    pub rssi: Vec<Option<f32>>,
    pub cell: Option<Cell>,
}

/// Anchors heard in fewer windows than this keep their starting model: too
/// few readings to fit six parameters.
const MIN_HEARD: f64 = 20.0;
/// Width of the distance bins detection is fitted on, metres.
const BIN_M: f64 = 0.25;

/// EM iterations of a calibration: `gangway calibrate`'s default, `eval
/// localization --calibrate`'s and the daemon's recalibration.
pub const CALIBRATION_ITERATIONS: usize = 8;

/// What [`fit`] fits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FitOptions {
    /// EM iterations of the per-anchor models.
    pub iterations: usize,
    /// EM iterations refining a radio map per cell afterwards (0: none).
    pub cell_iterations: usize,
    /// Weight of the per-anchor model in a refined cell, in readings.
    pub cell_prior_readings: f64,
}

impl FitOptions {
    /// Per-anchor models only.
    pub(crate) fn anchors(iterations: usize) -> FitOptions {
        FitOptions {
            iterations,
            cell_iterations: 0,
            cell_prior_readings: DEFAULT_CELL_PRIOR_READINGS,
        }
    }
}

/// Default of [`FitOptions::cell_prior_readings`]: one reading's weight, so
/// a cell the walks stood on a few times is mostly what was heard there.
pub const DEFAULT_CELL_PRIOR_READINGS: f64 = 1.0;

/// Cells whose refinement rests on less belief than this (in windows) are
/// not written: they are the anchors' models anyway.
const MIN_CELL_WEIGHT: f64 = 0.5;

/// How far one anchor's model moved, and whether the move was kept.
#[derive(Clone, Debug, Serialize)]
pub struct Change {
    pub id: String,
    pub heard: usize,
    pub before: Radio,
    pub after: Radio,
    /// Mean change of the expected RSSI over 1–10 m, dB.
    pub rssi_shift_db: f64,
    /// Mean change of the detection probability over 1–10 m.
    pub detection_shift: f64,
    /// Whether `after` was written to the calibration (else the anchor keeps
    /// `before`).
    pub kept: bool,
    pub why: Why,
    /// How much likelier the held-out windows are with this change than
    /// with the anchor alone put back (all other changes made), nats per
    /// window; `None` when nothing was held out.
    pub held_out_gain: Option<f64>,
}

/// Why a change was kept or not.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Why {
    /// The held-out windows are likelier with it, beside the others kept.
    Improved,
    /// The held-out windows are likelier with the anchor put back.
    Worse,
    /// What EM reached, all of it, did not explain the held-out windows
    /// clearly better than the model it started from: nothing is kept.
    NoClearGainTogether,
    /// EM left it where it started.
    Unchanged,
    /// Fitted to windows of known position with nothing held out.
    NotChecked,
}

impl Why {
    /// A few words for a person reading the report.
    pub fn describe(self) -> &'static str {
        match self {
            Why::Improved => "kept: held-out windows likelier with it",
            Why::Worse => "dropped: held-out windows likelier without it",
            Why::NoClearGainTogether => "dropped: the whole fit gains nothing clear held out",
            Why::Unchanged => "unchanged",
            Why::NotChecked => "kept: not checked",
        }
    }
}

/// The fitted calibration and what changed.
pub struct Fitted {
    pub calibration: Calibration,
    pub changes: Vec<Change>,
    /// Mean log-likelihood per window under the model EM reached, on the
    /// windows it was fitted to.
    pub log_likelihood_per_window: f64,
    /// How far the refined cells moved from the anchors' models, when cells
    /// were refined.
    pub cells: Option<CellChange>,
    /// What was held out to check the changes, when anything was.
    pub held_out: Option<HeldOut>,
}

/// The windows a calibration was checked on and what it won there.
#[derive(Clone, Debug, Serialize)]
pub struct HeldOut {
    pub windows: usize,
    /// Log-likelihood of the held-out windows under what was kept, less that
    /// under the starting model, nats per window: 0 when nothing was kept.
    pub gain_per_window: f64,
}

/// How far the per-cell refinement moved the radio map.
#[derive(Clone, Debug, Serialize)]
pub struct CellChange {
    /// Cells refined and written.
    pub cells: usize,
    /// Cells EM refined; those not written made the held-out windows less
    /// likely (each alone, or all together).
    pub refined: usize,
    /// Mean |change| of the detection probability over the written cells
    /// and anchors.
    pub detection_shift: f64,
    /// Mean |change| of the mean RSSI where the anchor is heard, dB,
    /// weighted by how often it is heard there.
    pub rssi_shift_db: f64,
}

/// Fits every positioned anchor's radio model to `trajectories` (each in time
/// order), starting from `start` (in the orientation's anchor order, with the
/// anchors' ids in `ids`), and then, if asked, a radio map per cell; every
/// change is kept. For windows of known position (a labelled survey), where
/// EM cannot wander; what a gateway hears goes through [`calibrate`].
pub fn fit(
    site: &Arc<Site>,
    ids: &[String],
    start: &[Anchor],
    tracker: &TrackerConfig,
    trajectories: &[Vec<Window>],
    options: &FitOptions,
) -> Result<Fitted, LocalizerError> {
    let reached = Em::new(site, start, tracker, trajectories).run(start, options)?;
    let kept = Kept::everything(site, start, &reached);
    Ok(written(site, ids, start, trajectories, &reached, &kept))
}

/// Calibration that does no harm: EM fits three quarters of `trajectories`
/// (as [`fit`] does), and a change is kept only where the windows held out
/// are likelier with it under the tracker (walls and walking speed
/// included): the fit as a whole must win on clearly more held-out walks
/// than chance allows, then each anchor and each refined cell that makes
/// them less likely is put back ([`Check::keep`]). What is kept is then
/// refitted on every window; the report says what was kept and why.
///
/// Windows are held out by walk when there are enough walks, else by blocks
/// of consecutive windows. The check is what stops EM on unlabelled windows
/// from replacing defaults that were right with a model a hair likelier
/// that locates worse, and per-cell maps from learning the noise of a few
/// passes (`tests/it/localization.rs`, BENCHMARKS.md).
pub fn calibrate(
    site: &Arc<Site>,
    ids: &[String],
    start: &[Anchor],
    tracker: &TrackerConfig,
    trajectories: &[Vec<Window>],
    options: &FitOptions,
) -> Result<Fitted, LocalizerError> {
    let (fit_on, held_out) = hold_out(trajectories, site.open_cells().len());
    if held_out.len() < MIN_HELD_OUT {
        return Err(LocalizerError::TooFewToHoldOut {
            windows: trajectories.iter().map(Vec::len).sum(),
            needed: MIN_HELD_OUT * HOLD_OUT_EVERY * BLOCK_WINDOWS,
        });
    }
    let reached = Em::new(site, start, tracker, &fit_on).run(start, options)?;
    let kept = Check::new(site, tracker, &held_out).keep(start, &reached)?;
    // What to keep is settled; what is kept is refitted on every window.
    let reached = Em::new(site, start, tracker, trajectories).run(start, options)?;
    Ok(written(site, ids, start, trajectories, &reached, &kept))
}

/// One in this many walks (or blocks) is held out.
const HOLD_OUT_EVERY: usize = 4;
/// Held-out walks (or blocks) needed at least: fewer could not pass the
/// sign test at [`CLEAR_GAIN_P`] even if all of them gained.
const MIN_HELD_OUT: usize = 5;
/// Walks needed to hold out whole walks rather than blocks of windows.
const MIN_WALKS: usize = MIN_HELD_OUT * HOLD_OUT_EVERY;
/// Windows per block when blocks are held out: a minute of a walk at the
/// gateway's default stride of 2 s, long enough for the tracker to settle.
const BLOCK_WINDOWS: usize = 30;
/// Held-out windows × open cells checked at most: the check keeps one
/// log-likelihood per held-out window and cell (4 bytes each, 64 MB).
const HELD_OUT_TERMS: usize = 16_000_000;

/// `trajectories` split into what EM fits and what it is checked on: every
/// [`HOLD_OUT_EVERY`]th walk, or block of [`BLOCK_WINDOWS`] windows when
/// there are fewer than [`MIN_WALKS`] walks, held out while within
/// [`HELD_OUT_TERMS`]; the rest is fitted.
fn hold_out(
    trajectories: &[Vec<Window>],
    open_cells: usize,
) -> (Vec<Vec<Window>>, Vec<Vec<Window>>) {
    let units: Vec<&[Window]> = if trajectories.len() >= MIN_WALKS {
        trajectories.iter().map(Vec::as_slice).collect()
    } else {
        trajectories
            .iter()
            .flat_map(|t| t.chunks(BLOCK_WINDOWS))
            .collect()
    };
    let mut room = HELD_OUT_TERMS / open_cells.max(1);
    let (mut fit_on, mut held_out) = (Vec::new(), Vec::new());
    for (i, unit) in units.into_iter().enumerate() {
        if i % HOLD_OUT_EVERY == HOLD_OUT_EVERY - 1 && unit.len() <= room {
            room -= unit.len();
            held_out.push(unit.to_vec());
        } else {
            fit_on.push(unit.to_vec());
        }
    }
    (fit_on, held_out)
}

/// What EM reached on the windows it was given.
struct Reached {
    anchors: Vec<Anchor>,
    /// The radio map per cell, when refined.
    cells: Option<CellTables>,
    log_likelihood_per_window: f64,
    iterations: usize,
}

/// A radio map per open cell, `[cell][anchor]`: mean RSSI where heard and
/// detection probability; and the belief, in windows, each cell rests on.
struct CellTables {
    mu: Vec<f64>,
    p: Vec<f64>,
    weight: Vec<f64>,
}

/// What is done with one anchor's change.
#[derive(Clone, Copy)]
struct Verdict {
    kept: bool,
    why: Why,
    /// [`Change::held_out_gain`].
    gain: Option<f64>,
}

/// Which of what EM reached goes into the calibration file.
struct Kept {
    /// Per anchor, in `start`'s order.
    anchors: Vec<Verdict>,
    /// Per open cell: whether its refinement is written.
    cells: Vec<bool>,
    held_out: Option<HeldOut>,
}

impl Kept {
    /// Every change, unchecked.
    fn everything(site: &Site, start: &[Anchor], reached: &Reached) -> Kept {
        Kept {
            anchors: start
                .iter()
                .zip(&reached.anchors)
                .map(|(before, after)| {
                    let why = if before == after {
                        Why::Unchanged
                    } else {
                        Why::NotChecked
                    };
                    Verdict {
                        kept: true,
                        why,
                        gain: None,
                    }
                })
                .collect(),
            cells: reached.cells.as_ref().map_or_else(Vec::new, |t| {
                t.weight.iter().map(|&w| w >= MIN_CELL_WEIGHT).collect()
            }),
            held_out: None,
        }
        .sized(site)
    }

    /// `cells` one per open cell, even when none was refined.
    fn sized(mut self, site: &Site) -> Kept {
        self.cells.resize(site.open_cells().len(), false);
        self
    }

    /// The anchors as written: what EM reached where kept, else the start.
    fn anchors(&self, start: &[Anchor], reached: &Reached) -> Vec<Anchor> {
        start
            .iter()
            .zip(&reached.anchors)
            .zip(&self.anchors)
            .map(|((before, after), verdict)| if verdict.kept { *after } else { *before })
            .collect()
    }
}

/// The calibration file's content and the report, from what EM reached and
/// what is kept of it.
fn written(
    site: &Site,
    ids: &[String],
    start: &[Anchor],
    fitted_on: &[Vec<Window>],
    reached: &Reached,
    kept: &Kept,
) -> Fitted {
    let heard = |a: usize| {
        fitted_on
            .iter()
            .flatten()
            .filter(|w| w.rssi[a].is_some())
            .count()
    };
    let mut entries = Vec::new();
    let mut changes = Vec::new();
    for (a, (after, before)) in reached.anchors.iter().zip(start).enumerate() {
        let (Some((_, after)), Some((_, before))) = (after, before) else {
            continue;
        };
        let verdict = kept.anchors[a];
        let is_kept = verdict.kept && verdict.why != Why::Unchanged;
        if is_kept {
            entries.push(AnchorCalibration {
                id: ids[a].clone(),
                heard: heard(a),
                radio: *after,
            });
        }
        changes.push(Change::between(
            &ids[a],
            heard(a),
            (before, after),
            Verdict {
                kept: is_kept,
                ..verdict
            },
        ));
    }
    let (cells, cell_change) = match &reached.cells {
        Some(tables) => {
            let (cells, change) =
                write_cells(site, &kept.anchors(start, reached), tables, &kept.cells);
            (cells, Some(change))
        }
        None => (Vec::new(), None),
    };
    Fitted {
        calibration: Calibration {
            site: site.name.clone(),
            windows: fitted_on.iter().map(Vec::len).sum(),
            iterations: reached.iterations,
            anchors: entries,
            cells,
        },
        changes,
        log_likelihood_per_window: reached.log_likelihood_per_window,
        cells: cell_change,
        held_out: kept.held_out.clone(),
    }
}

/// The kept cells of a refined radio map as the calibration writes them (per
/// positioned anchor), and how far they moved from `anchors`' models.
fn write_cells(
    site: &Site,
    anchors: &[Anchor],
    tables: &CellTables,
    keep: &[bool],
) -> (Vec<CellCalibration>, CellChange) {
    let n = anchors.len();
    let (prior_mu, prior_p) = PathLoss::with_anchors(site, anchors)
        .expect("the anchors EM started from have positions")
        .tables();
    let positioned: Vec<usize> = (0..n).filter(|&a| anchors[a].is_some()).collect();
    let mut refined = Vec::new();
    let (mut dp, mut dmu, mut dmu_weight) = (0.0, 0.0, 0.0);
    for (c, cell) in site.open_cells().iter().enumerate() {
        if !keep[c] {
            continue;
        }
        for &a in &positioned {
            let i = c * n + a;
            dp += (tables.p[i] - prior_p[i]).abs();
            dmu += tables.p[i] * (tables.mu[i] - prior_mu[i]).abs();
            dmu_weight += tables.p[i];
        }
        refined.push(CellCalibration {
            at: [cell.x, cell.y],
            detection: positioned
                .iter()
                .map(|&a| round_to(tables.p[c * n + a], 1e-4))
                .collect(),
            rssi_dbm: positioned
                .iter()
                .map(|&a| round_to(tables.mu[c * n + a], 1e-2))
                .collect(),
        });
    }
    let change = CellChange {
        cells: refined.len(),
        refined: tables
            .weight
            .iter()
            .filter(|&&w| w >= MIN_CELL_WEIGHT)
            .count(),
        detection_shift: dp / (refined.len() * positioned.len()).max(1) as f64,
        rssi_shift_db: dmu / dmu_weight.max(f64::MIN_POSITIVE),
    };
    (refined, change)
}

/// The held-out half of [`calibrate`]: the windows and the tracker that
/// scores models on them.
struct Check<'a> {
    site: &'a Arc<Site>,
    tracker: Tracker,
    held_out: &'a [Vec<Window>],
}

impl<'a> Check<'a> {
    fn new(site: &'a Arc<Site>, tracker: &TrackerConfig, held_out: &'a [Vec<Window>]) -> Self {
        Check {
            site,
            tracker: Tracker::new(tracker.clone(), site.clone()),
            held_out,
        }
    }

    fn windows(&self) -> usize {
        self.held_out.iter().map(Vec::len).sum()
    }

    /// Each held-out window's log-likelihood per open cell under `model`,
    /// with its time, per trajectory.
    fn log_likelihoods(&self, model: &mut PathLoss) -> Vec<Vec<(f64, Vec<f32>)>> {
        let n_cells = self.site.open_cells().len();
        self.held_out
            .iter()
            .map(|trajectory| {
                trajectory
                    .iter()
                    .map(|w| {
                        let (rssi, heard) = readings(&w.rssi);
                        let mut ll = vec![0.0f32; n_cells];
                        model.log_likelihood(&rssi, &heard, &mut ll);
                        (w.t, ll)
                    })
                    .collect()
            })
            .collect()
    }

    /// Log-likelihood of each held-out walk (or block) given per-window,
    /// per-cell log-likelihoods.
    fn evidence(&self, lls: &[Vec<(f64, Vec<f32>)>]) -> Evidence {
        Evidence(lls.iter().map(|t| self.tracker.log_evidence(t)).collect())
    }

    /// `lls` with anchor `a`'s term under `from` replaced by its term under
    /// `to`. The change depends on the anchor's reading alone, so it is
    /// scored once per distinct reading (every window that did not hear the
    /// anchor shares one): on a floor of hundreds of beacons this is what
    /// the check of each anchor costs.
    fn swap_anchor(&self, lls: &mut [Vec<(f64, Vec<f32>)>], a: usize, from: &Anchor, to: &Anchor) {
        let n_cells = self.site.open_cells().len();
        let one = |anchor: &Anchor| {
            PathLoss::with_anchors(self.site, std::slice::from_ref(anchor))
                .expect("a positioned anchor")
        };
        let (mut from, mut to) = (one(from), one(to));
        let (mut old, mut new) = (vec![0.0f32; n_cells], vec![0.0f32; n_cells]);
        let mut changes: HashMap<Option<u32>, Vec<f32>> = HashMap::new();
        for (trajectory, windows) in self.held_out.iter().zip(lls) {
            for (w, (_, ll)) in trajectory.iter().zip(windows) {
                let reading = &w.rssi[a..=a];
                let change = changes
                    .entry(reading[0].map(f32::to_bits))
                    .or_insert_with(|| {
                        let (rssi, heard) = readings(reading);
                        from.log_likelihood(&rssi, &heard, &mut old);
                        to.log_likelihood(&rssi, &heard, &mut new);
                        new.iter().zip(&old).map(|(n, o)| n - o).collect()
                    });
                for (l, d) in ll.iter_mut().zip(change.iter()) {
                    *l += d;
                }
            }
        }
    }

    /// What to keep of `reached`. First the whole: unless EM's model
    /// explains the held-out walks (or blocks) clearly better than the start
    /// ([`Evidence::clearly_better_than`]), nothing is kept. Then each anchor beside the others, since EM fits them together
    /// (one receiver's gain moves every anchor's power alike, so putting one
    /// anchor back where it started is the alternative, not the start): those
    /// without which the held-out windows are likelier are put back one at a
    /// time, the most harmful first, while that helps. Then cells, by
    /// [`Check::keep_cells`].
    fn keep(&self, start: &[Anchor], reached: &Reached) -> Result<Kept, LocalizerError> {
        let windows = self.windows() as f64;
        let start_lls = self.log_likelihoods(&mut PathLoss::with_anchors(self.site, start)?);
        let start_evidence = self.evidence(&start_lls);
        let mut current =
            self.log_likelihoods(&mut PathLoss::with_anchors(self.site, &reached.anchors)?);
        let mut evidence = self.evidence(&current);
        let clear = evidence.clearly_better_than(&start_evidence);
        let mut verdicts = vec![
            Verdict {
                kept: false,
                why: Why::Unchanged,
                gain: None,
            };
            start.len()
        ];
        let mut harmful = Vec::new();
        for (a, (before, after)) in start.iter().zip(&reached.anchors).enumerate() {
            if before == after || before.is_none() {
                continue;
            }
            let mut without = current.clone();
            self.swap_anchor(&mut without, a, after, before);
            let gain = evidence.total_gain_over(&self.evidence(&without));
            verdicts[a] = Verdict {
                kept: clear,
                why: if clear {
                    Why::Improved
                } else {
                    Why::NoClearGainTogether
                },
                gain: Some(gain / windows),
            };
            if gain <= 0.0 {
                harmful.push((a, gain));
            }
        }
        if !clear {
            (current, evidence) = (start_lls, start_evidence.clone());
        } else {
            harmful.sort_by(|x, y| x.1.total_cmp(&y.1));
            for (a, _) in harmful {
                let mut without = current.clone();
                self.swap_anchor(&mut without, a, &reached.anchors[a], &start[a]);
                let without_evidence = self.evidence(&without);
                if without_evidence.total_gain_over(&evidence) > 0.0 {
                    (current, evidence) = (without, without_evidence);
                    verdicts[a].kept = false;
                    verdicts[a].why = Why::Worse;
                }
            }
        }
        let mut kept = Kept {
            anchors: verdicts,
            cells: Vec::new(),
            held_out: None,
        };
        if let Some(tables) = &reached.cells {
            let anchors = kept.anchors(start, reached);
            // The map, too, is kept only if clearly better as a whole.
            let (cells, with_cells) = self.keep_cells(&anchors, tables, &current);
            if with_cells.clearly_better_than(&evidence) {
                kept.cells = cells;
                evidence = with_cells;
            }
        }
        kept.held_out = Some(HeldOut {
            windows: self.windows(),
            gain_per_window: evidence.total_gain_over(&start_evidence) / windows,
        });
        Ok(kept.sized(self.site))
    }

    /// Which refined cells to keep: all but those where the held-out windows
    /// the tracker places there (under `anchors`, whose log-likelihoods are
    /// `lls`) are less likely with the refinement than with `anchors`'
    /// models; and the held-out evidence with the kept cells. A cell the
    /// held-out walks never reach has nothing against it: whether the map is
    /// kept at all is decided on the whole ([`Check::keep`]).
    fn keep_cells(
        &self,
        anchors: &[Anchor],
        tables: &CellTables,
        lls: &[Vec<(f64, Vec<f32>)>],
    ) -> (Vec<bool>, Evidence) {
        let n_cells = self.site.open_cells().len();
        let n = anchors.len();
        let Ok(base) = PathLoss::with_anchors(self.site, anchors) else {
            return (vec![false; n_cells], self.evidence(lls));
        };
        let (mut mu, mut p) = base.tables();
        let refined = |c: usize| tables.weight[c] >= MIN_CELL_WEIGHT;
        for c in (0..n_cells).filter(|&c| refined(c)) {
            mu[c * n..(c + 1) * n].copy_from_slice(&tables.mu[c * n..(c + 1) * n]);
            p[c * n..(c + 1) * n].copy_from_slice(&tables.p[c * n..(c + 1) * n]);
        }
        let inv_sigma = base.inv_sigma().to_vec();
        let mut map = PathLoss::from_probabilities(n_cells, &mu, &p, inv_sigma);
        let with_map = self.log_likelihoods(&mut map);
        // Each cell's gain: the belief-weighted change of its log-likelihood.
        let mut gain = vec![0.0f64; n_cells];
        for (windows, mapped) in lls.iter().zip(&with_map) {
            let beliefs = self.tracker.posteriors(windows);
            for ((belief, (_, ll)), (_, ll_map)) in beliefs.iter().zip(windows).zip(mapped) {
                for c in 0..n_cells {
                    if belief[c] > 0.0 {
                        gain[c] += f64::from(belief[c]) * f64::from(ll_map[c] - ll[c]);
                    }
                }
            }
        }
        let keep: Vec<bool> = (0..n_cells).map(|c| refined(c) && gain[c] >= 0.0).collect();
        let mut kept_lls = lls.to_vec();
        for (windows, mapped) in kept_lls.iter_mut().zip(&with_map) {
            for ((_, ll), (_, ll_map)) in windows.iter_mut().zip(mapped) {
                for c in (0..n_cells).filter(|&c| keep[c]) {
                    ll[c] = ll_map[c];
                }
            }
        }
        (keep, self.evidence(&kept_lls))
    }
}

/// Log-likelihood of each held-out walk (or block) under one model.
#[derive(Clone)]
struct Evidence(Vec<f64>);

/// The one-sided sign-test level below which a model explains the
/// held-out walks (or blocks) clearly better than another.
const CLEAR_GAIN_P: f64 = 0.05;

impl Evidence {
    /// Log-likelihood of all the held-out windows, less that under `other`.
    fn total_gain_over(&self, other: &Evidence) -> f64 {
        self.0.iter().sum::<f64>() - other.0.iter().sum::<f64>()
    }

    /// Whether this model explains the held-out walks (or blocks) clearly
    /// better than `other`: likelier on more of them than chance allows
    /// (one-sided sign test at [`CLEAR_GAIN_P`]). Counting walks rather than
    /// summing nats keeps a few walks far off from deciding, and a gain
    /// within the walks' noise from counting: on walks the defaults
    /// describe exactly, EM still finds a model a hair likelier in total,
    /// and it locates worse.
    fn clearly_better_than(&self, other: &Evidence) -> bool {
        let wins = self.0.iter().zip(&other.0).filter(|(a, b)| a > b).count();
        let losses = self.0.iter().zip(&other.0).filter(|(a, b)| a < b).count();
        wins > losses && sign_test(wins, losses) / 2.0 < CLEAR_GAIN_P
    }
}

/// A window's readings as the localizer takes them: RSSI (0 where silent)
/// and whether heard, per anchor.
fn readings(rssi: &[Option<f32>]) -> (Vec<f32>, Vec<bool>) {
    (
        rssi.iter().map(|r| r.unwrap_or(0.0)).collect(),
        rssi.iter().map(Option::is_some).collect(),
    )
}

/// What every EM pass shares: the trajectories, the tracker that smooths
/// them and the cell–anchor distances.
struct Em<'a> {
    site: &'a Arc<Site>,
    tracker: Tracker,
    trajectories: &'a [Vec<Window>],
    /// Metres, `[cell][anchor]`; NaN for anchors without a position.
    distance: Vec<f64>,
    n_anchors: usize,
}

impl<'a> Em<'a> {
    fn new(
        site: &'a Arc<Site>,
        start: &[Anchor],
        tracker: &TrackerConfig,
        trajectories: &'a [Vec<Window>],
    ) -> Self {
        Em {
            site,
            tracker: Tracker::new(tracker.clone(), site.clone()),
            trajectories,
            distance: site
                .open_cells()
                .iter()
                .flat_map(|&c| {
                    let here = site.world_of_cell(c);
                    start
                        .iter()
                        .map(move |a| a.map_or(f64::NAN, |(mount, _)| mount.distance_m(here)))
                })
                .collect(),
            n_anchors: start.len(),
        }
    }

    /// EM from `start` (started afresh from the data, see [`initialise`]):
    /// the anchors' models, then the cells' if asked.
    fn run(&self, start: &[Anchor], options: &FitOptions) -> Result<Reached, LocalizerError> {
        let mut anchors = start.to_vec();
        initialise(self.site, &mut anchors, self.trajectories);
        let n_anchors = self.n_anchors;
        let bins = self
            .distance
            .iter()
            .filter(|d| d.is_finite())
            .fold(0.0f64, |m, &d| m.max(d))
            .div_euclid(BIN_M) as usize
            + 1;
        let windows = self.trajectories.iter().map(Vec::len).sum::<usize>().max(1) as f64;
        let mut log_likelihood_per_window = f64::NAN;
        for _ in 0..options.iterations.max(1) {
            let mut stats = vec![Stats::new(bins); n_anchors];
            let mut localizer = PathLoss::with_anchors(self.site, &anchors)?;
            log_likelihood_per_window = self.e_step(&mut localizer, |w, c, b| {
                let row = &self.distance[c * n_anchors..(c + 1) * n_anchors];
                for (a, stat) in stats.iter_mut().enumerate() {
                    if row[a].is_finite() {
                        stat.add(row[a], w.rssi[a], b);
                    }
                }
            }) / windows;
            for (anchor, stat) in anchors.iter_mut().zip(&stats) {
                if let Some((_, radio)) = anchor
                    && stat.heard >= MIN_HEARD
                {
                    *radio = stat.refit(radio);
                }
            }
        }
        let mut cells = None;
        if options.cell_iterations > 0 {
            let (tables, ll) = self.refine_cells(&anchors, options)?;
            cells = Some(tables);
            log_likelihood_per_window = ll / windows;
        }
        Ok(Reached {
            anchors,
            cells,
            log_likelihood_per_window,
            iterations: options.iterations,
        })
    }

    /// Localizes every trajectory with `localizer` through the smoother and
    /// calls `visit(window, cell, belief)` for every cell holding some of a
    /// window's belief; returns the belief-weighted log-likelihood summed
    /// over windows. Windows of known position keep all belief there.
    fn e_step(&self, localizer: &mut PathLoss, mut visit: impl FnMut(&Window, usize, f64)) -> f64 {
        let n_cells = self.site.open_cells().len();
        let mut total_ll = 0.0;
        for trajectory in self.trajectories {
            let lls: Vec<(f64, Vec<f32>)> = trajectory
                .iter()
                .map(|w| {
                    let (rssi, heard) = readings(&w.rssi);
                    let mut ll = vec![0.0f32; n_cells];
                    localizer.log_likelihood(&rssi, &heard, &mut ll);
                    if let Some(i) = w.cell.and_then(|c| self.site.open_index(c)) {
                        ll.iter_mut().enumerate().for_each(|(j, v)| {
                            if j != i {
                                *v = f32::NEG_INFINITY;
                            }
                        });
                    }
                    (w.t, ll)
                })
                .collect();
            let posteriors = self.tracker.posteriors(&lls);
            for ((w, (_, ll)), belief) in trajectory.iter().zip(&lls).zip(&posteriors) {
                for (c, (&b, &l)) in belief.iter().zip(ll).enumerate() {
                    // Cells holding almost none of the belief add nothing.
                    if b < 1e-5 {
                        continue;
                    }
                    total_ll += f64::from(b) * f64::from(l);
                    visit(w, c, f64::from(b));
                }
            }
        }
        total_ll
    }

    /// EM over a radio map per cell, from the anchors' models: each
    /// iteration localizes with the current map and re-estimates every
    /// cell's detection and mean RSSI per anchor from the belief-weighted
    /// windows, shrunk towards the anchors' models. Returns the map and the
    /// log-likelihood of the windows under it.
    fn refine_cells(
        &self,
        anchors: &[Anchor],
        options: &FitOptions,
    ) -> Result<(CellTables, f64), LocalizerError> {
        let cells = self.site.open_cells();
        let n = self.n_anchors;
        let base = PathLoss::with_anchors(self.site, anchors)?;
        let (prior_mu, prior_p) = base.tables();
        let inv_sigma = base.inv_sigma().to_vec();
        let (mut mu, mut p) = (prior_mu.clone(), prior_p.clone());
        let kappa = options.cell_prior_readings.max(0.0);
        let mut weight = vec![0.0f64; cells.len()];
        let mut ll = 0.0;
        for _ in 0..options.cell_iterations {
            let mut localizer =
                PathLoss::from_probabilities(cells.len(), &mu, &p, inv_sigma.clone());
            weight.fill(0.0);
            let mut hits = vec![0.0f64; cells.len() * n];
            let mut sums = vec![0.0f64; cells.len() * n];
            ll = self.e_step(&mut localizer, |w, c, b| {
                weight[c] += b;
                for (a, r) in w.rssi.iter().enumerate() {
                    if let Some(r) = r {
                        hits[c * n + a] += b;
                        sums[c * n + a] += b * f64::from(*r);
                    }
                }
            });
            for (c, &w) in weight.iter().enumerate() {
                for a in 0..n {
                    let i = c * n + a;
                    if prior_mu[i].is_nan() {
                        continue;
                    }
                    let (p0, mu0) = (prior_p[i], prior_mu[i]);
                    p[i] = ((hits[i] + kappa * p0) / (w + kappa))
                        .clamp(DETECTION_BOUNDS.0, DETECTION_BOUNDS.1);
                    mu[i] = (sums[i] + kappa * p0 * mu0) / (hits[i] + kappa * p0);
                }
            }
        }
        Ok((CellTables { mu, p, weight }, ll))
    }
}

/// `v` rounded to a multiple of `step`: the file need not carry f64 noise.
fn round_to(v: f64, step: f64) -> f64 {
    (v / step).round() * step
}

/// A start for EM read off the data alone, so that it does not depend on how
/// far the configured defaults are from this site's radios (EM only finds the
/// nearest optimum):
/// - each anchor's `tx_dbm` is the 90th percentile of its readings: the
///   loudest readings are taken near it, about a metre away;
/// - one `range_m` for all anchors makes the expected number of anchors heard
///   per window, over the site's open cells, equal to the number heard.
fn initialise(site: &Site, anchors: &mut [Anchor], trajectories: &[Vec<Window>]) {
    let windows: Vec<&Window> = trajectories.iter().flatten().collect();
    if windows.is_empty() {
        return;
    }
    for (a, anchor) in anchors.iter_mut().enumerate() {
        let Some((_, radio)) = anchor else { continue };
        let mut readings: Vec<f32> = windows.iter().filter_map(|w| w.rssi[a]).collect();
        if (readings.len() as f64) < MIN_HEARD {
            continue;
        }
        let rank = ((readings.len() as f64 * 0.9) as usize).min(readings.len() - 1);
        let (_, loud, _) = readings.select_nth_unstable_by(rank, f32::total_cmp);
        radio.tx_dbm = f64::from(*loud);
    }
    let heard = windows
        .iter()
        .map(|w| w.rssi.iter().filter(|r| r.is_some()).count())
        .sum::<usize>() as f64
        / windows.len() as f64;
    let cells = site.open_cells();
    let expected_heard = |range_m: f64, anchors: &[Anchor]| -> f64 {
        cells
            .iter()
            .map(|&c| {
                let here = site.world_of_cell(c);
                anchors
                    .iter()
                    .flatten()
                    .map(|(mount, r)| Radio { range_m, ..*r }.detection(mount.distance_m(here)))
                    .sum::<f64>()
            })
            .sum::<f64>()
            / cells.len() as f64
    };
    // Bisection in log-range: more range, more anchors heard.
    let (mut lo, mut hi) = (0.25f64.ln(), 200f64.ln());
    for _ in 0..40 {
        let mid = 0.5 * (lo + hi);
        if expected_heard(mid.exp(), anchors) < heard {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    let range_m = (0.5 * (lo + hi)).exp();
    for (_, radio) in anchors.iter_mut().flatten() {
        radio.range_m = range_m;
    }
}

impl Change {
    /// `before` → `after`, and the verdict on it.
    fn between(
        id: &str,
        heard: usize,
        (before, after): (&Radio, &Radio),
        verdict: Verdict,
    ) -> Change {
        let metres: Vec<f64> = (1..=10).map(f64::from).collect();
        let mean = |f: &dyn Fn(f64) -> f64| metres.iter().map(|&d| f(d)).sum::<f64>() / 10.0;
        Change {
            id: id.to_owned(),
            heard,
            before: *before,
            after: *after,
            rssi_shift_db: mean(&|d| after.expected_rssi(d) - before.expected_rssi(d)),
            detection_shift: mean(&|d| after.detection(d) - before.detection(d)),
            kept: verdict.kept,
            why: verdict.why,
            held_out_gain: verdict.gain,
        }
    }
}

/// Belief-weighted sufficient statistics of one anchor.
#[derive(Clone)]
struct Stats {
    /// Weight of windows in which it was heard / silent, per distance bin.
    hit: Vec<f64>,
    miss: Vec<f64>,
    /// Weighted sums for the regression of RSSI on x = log10(distance).
    w: f64,
    wx: f64,
    wxx: f64,
    wy: f64,
    wxy: f64,
    wyy: f64,
    heard: f64,
}

impl Stats {
    fn new(bins: usize) -> Stats {
        Stats {
            hit: vec![0.0; bins],
            miss: vec![0.0; bins],
            w: 0.0,
            wx: 0.0,
            wxx: 0.0,
            wy: 0.0,
            wxy: 0.0,
            wyy: 0.0,
            heard: 0.0,
        }
    }

    fn add(&mut self, distance_m: f64, rssi: Option<f32>, weight: f64) {
        let bin = ((distance_m / BIN_M) as usize).min(self.hit.len() - 1);
        match rssi {
            Some(r) => {
                self.hit[bin] += weight;
                self.heard += weight;
                let x = distance_m.max(0.5).log10();
                let y = f64::from(r);
                self.w += weight;
                self.wx += weight * x;
                self.wxx += weight * x * x;
                self.wy += weight * y;
                self.wxy += weight * x * y;
                self.wyy += weight * y * y;
            }
            None => self.miss[bin] += weight,
        }
    }

    /// The anchor's model refitted to these statistics, from `current`.
    fn refit(&self, current: &Radio) -> Radio {
        let mut radio = *current;
        // Strength: weighted least squares of RSSI on log10(d).
        let det = self.w * self.wxx - self.wx * self.wx;
        if det > 1e-9 * self.w * self.w {
            let slope = (self.w * self.wxy - self.wx * self.wy) / det;
            // Exponents outside 0.5–6 are a degenerate fit, not a building.
            radio.exponent = (-slope / 10.0).clamp(0.5, 6.0);
        }
        let slope = -10.0 * radio.exponent;
        radio.tx_dbm = (self.wy - slope * self.wx) / self.w;
        let residual = (self.wyy - 2.0 * radio.tx_dbm * self.wy - 2.0 * slope * self.wxy
            + radio.tx_dbm * radio.tx_dbm * self.w
            + 2.0 * radio.tx_dbm * slope * self.wx
            + slope * slope * self.wxx)
            / self.w;
        // Readings are whole dBm and a window's spread is never below a few dB.
        radio.shadowing_db = residual.max(0.0).sqrt().max(2.0);
        // Detection: coordinate search over its three parameters.
        let ll = |r: &Radio| -> f64 {
            (0..self.hit.len())
                .filter(|&i| self.hit[i] + self.miss[i] > 0.0)
                .map(|i| {
                    let p = r.detection((i as f64 + 0.5) * BIN_M);
                    self.hit[i] * p.ln() + self.miss[i] * (1.0 - p).ln()
                })
                .sum()
        };
        let ranges: Vec<f64> = (0..48).map(|i| 0.5 * 1.1f64.powi(i)).collect();
        let slopes = [1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0];
        let maxima: Vec<f64> = (0..14).map(|i| 0.35 + 0.05 * f64::from(i)).collect();
        for _ in 0..3 {
            let round_from = (radio.range_m, radio.range_slope, radio.max_detection);
            radio.range_m = best(&ranges, |v| {
                ll(&Radio {
                    range_m: v,
                    ..radio
                })
            });
            radio.range_slope = best(&slopes, |v| {
                ll(&Radio {
                    range_slope: v,
                    ..radio
                })
            });
            radio.max_detection = best(&maxima, |v| {
                ll(&Radio {
                    max_detection: v,
                    ..radio
                })
            });
            // A round that moved nothing is where the search rests: another
            // would score the same candidates from the same point.
            if (radio.range_m, radio.range_slope, radio.max_detection) == round_from {
                break;
            }
        }
        radio
    }
}

/// The candidate with the highest score.
fn best(candidates: &[f64], score: impl Fn(f64) -> f64) -> f64 {
    candidates
        .iter()
        .copied()
        .map(|v| (v, score(v)))
        .max_by(|a, b| a.1.total_cmp(&b.1))
        .map_or(candidates[0], |(v, _)| v)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn walk(windows: usize) -> Vec<Window> {
        (0..windows)
            .map(|i| Window {
                t: i as f64,
                rssi: vec![Some(-70.0), None],
                cell: None,
            })
            .collect()
    }

    #[test]
    fn enough_walks_are_held_out_whole_and_one_long_walk_in_blocks() {
        let walks: Vec<Vec<Window>> = (0..40).map(|_| walk(10)).collect();
        let (fit_on, held_out) = hold_out(&walks, 100);
        assert_eq!((fit_on.len(), held_out.len()), (30, 10));
        assert!(held_out.iter().all(|w| w.len() == 10));

        let (fit_on, held_out) = hold_out(&[walk(600)], 100);
        assert_eq!((fit_on.len(), held_out.len()), (15, 5));
        assert!(held_out.iter().all(|w| w.len() == BLOCK_WINDOWS));
        // Each block is consecutive windows.
        assert_eq!(held_out[0][0].t, 90.0);

        // A site too large for every held-out window: only what fits the
        // budget is held out, the rest is fitted.
        let (fit_on, held_out) = hold_out(&[walk(600)], HELD_OUT_TERMS / 60);
        assert_eq!((fit_on.len(), held_out.len()), (18, 2));
    }

    #[test]
    fn a_clear_gain_is_one_most_held_out_walks_agree_on() {
        let start = Evidence(vec![0.0; 10]);
        // Nine of ten walks likelier: one chance in a hundred by luck.
        let mut nine = Evidence(vec![1.0; 10]);
        nine.0[3] = -50.0;
        assert!(nine.clearly_better_than(&start));
        // A large total from a few walks is not clear.
        let mut few = Evidence(vec![-0.1; 10]);
        few.0[..3].fill(100.0);
        assert!(few.total_gain_over(&start) > 0.0);
        assert!(!few.clearly_better_than(&start));
        // Too few walks can never be clear.
        assert!(!Evidence(vec![5.0; 4]).clearly_better_than(&Evidence(vec![0.0; 4])));
    }
}
