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

use std::sync::Arc;

use serde::Serialize;

use super::calibration::{AnchorCalibration, Calibration, CellCalibration};
use super::pathloss::{Anchor, DETECTION_BOUNDS, PathLoss, Radio};
use super::tracker::{Tracker, TrackerConfig};
use super::{Localizer, LocalizerError};
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

/// How far one anchor's model moved.
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
}

/// The fitted calibration and what changed.
pub struct Fitted {
    pub calibration: Calibration,
    pub changes: Vec<Change>,
    /// Mean log-likelihood per window under the final model.
    pub log_likelihood_per_window: f64,
    /// How far the refined cells moved from the anchors' models, when cells
    /// were refined.
    pub cells: Option<CellChange>,
}

/// How far the per-cell refinement moved the radio map.
#[derive(Clone, Debug, Serialize)]
pub struct CellChange {
    /// Cells refined (and written).
    pub cells: usize,
    /// Mean |change| of the detection probability over those cells and anchors.
    pub detection_shift: f64,
    /// Mean |change| of the mean RSSI where the anchor is heard, dB,
    /// weighted by how often it is heard there.
    pub rssi_shift_db: f64,
}

/// Fits every positioned anchor's radio model to `trajectories` (each in time
/// order), starting from `start` (in the orientation's anchor order, with the
/// anchors' ids in `ids`), and then, if asked, a radio map per cell.
pub fn fit(
    site: &Arc<Site>,
    ids: &[String],
    start: &[Anchor],
    tracker: &TrackerConfig,
    trajectories: &[Vec<Window>],
    options: &FitOptions,
) -> Result<Fitted, LocalizerError> {
    let mut anchors = start.to_vec();
    initialise(site, &mut anchors, trajectories);
    let em = Em {
        site,
        tracker: Tracker::new(tracker.clone(), site.clone()),
        trajectories,
        // Distance from every open cell to every anchor, metres, [cell][anchor].
        distance: site
            .open_cells()
            .iter()
            .flat_map(|&c| {
                let here = site.world_of_cell(c);
                anchors
                    .iter()
                    .map(move |a| a.map_or(f64::NAN, |(mount, _)| mount.distance_m(here)))
            })
            .collect(),
        n_anchors: anchors.len(),
    };
    let n_anchors = em.n_anchors;
    let bins = em
        .distance
        .iter()
        .filter(|d| d.is_finite())
        .fold(0.0f64, |m, &d| m.max(d))
        .div_euclid(BIN_M) as usize
        + 1;
    let windows: usize = trajectories.iter().map(Vec::len).sum();
    let mut log_likelihood_per_window = f64::NAN;
    for _ in 0..options.iterations.max(1) {
        let mut stats = vec![Stats::new(bins); n_anchors];
        let mut localizer = PathLoss::with_anchors(site, &anchors)?;
        log_likelihood_per_window = em.e_step(&mut localizer, |w, c, b| {
            let row = &em.distance[c * n_anchors..(c + 1) * n_anchors];
            for (a, stat) in stats.iter_mut().enumerate() {
                if row[a].is_finite() {
                    stat.add(row[a], w.rssi[a], b);
                }
            }
        }) / windows.max(1) as f64;
        for (anchor, stat) in anchors.iter_mut().zip(&stats) {
            if let Some((_, radio)) = anchor
                && stat.heard >= MIN_HEARD
            {
                *radio = stat.refit(radio);
            }
        }
    }
    let mut cells = Vec::new();
    let mut cell_change = None;
    if options.cell_iterations > 0 {
        let (refined, change, ll) = em.refine_cells(&anchors, options)?;
        cells = refined;
        cell_change = Some(change);
        log_likelihood_per_window = ll / windows.max(1) as f64;
    }
    let heard: Vec<usize> = (0..n_anchors)
        .map(|a| {
            trajectories
                .iter()
                .flatten()
                .filter(|w| w.rssi[a].is_some())
                .count()
        })
        .collect();
    let mut entries = Vec::new();
    let mut changes = Vec::new();
    for (a, (anchor, before)) in anchors.iter().zip(start).enumerate() {
        let (Some((_, after)), Some((_, before))) = (anchor, before) else {
            continue;
        };
        entries.push(AnchorCalibration {
            id: ids[a].clone(),
            heard: heard[a],
            radio: *after,
        });
        changes.push(Change::between(&ids[a], heard[a], before, after));
    }
    Ok(Fitted {
        calibration: Calibration {
            site: site.name.clone(),
            windows,
            iterations: options.iterations,
            anchors: entries,
            cells,
        },
        changes,
        log_likelihood_per_window,
        cells: cell_change,
    })
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

impl Em<'_> {
    /// Localizes every trajectory with `localizer` through the smoother and
    /// calls `visit(window, cell, belief)` for every cell holding some of a
    /// window's belief; returns the belief-weighted log-likelihood summed
    /// over windows. Windows of known position keep all belief there.
    fn e_step(&self, localizer: &mut PathLoss, mut visit: impl FnMut(&Window, usize, f64)) -> f64 {
        let n_cells = self.site.open_cells().len();
        let mut rssi = vec![0.0f32; self.n_anchors];
        let mut heard = vec![false; self.n_anchors];
        let mut total_ll = 0.0;
        for trajectory in self.trajectories {
            let lls: Vec<(f64, Vec<f32>)> = trajectory
                .iter()
                .map(|w| {
                    for (a, r) in w.rssi.iter().enumerate() {
                        heard[a] = r.is_some();
                        rssi[a] = r.unwrap_or(0.0);
                    }
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
    /// windows, shrunk towards the anchors' models.
    fn refine_cells(
        &self,
        anchors: &[Anchor],
        options: &FitOptions,
    ) -> Result<(Vec<CellCalibration>, CellChange, f64), LocalizerError> {
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
        // Written per positioned anchor, in the calibration's anchor order.
        let positioned: Vec<usize> = (0..n).filter(|&a| anchors[a].is_some()).collect();
        let mut refined = Vec::new();
        let (mut dp, mut dmu, mut dmu_weight) = (0.0, 0.0, 0.0);
        for (c, cell) in cells.iter().enumerate() {
            if weight[c] < MIN_CELL_WEIGHT {
                continue;
            }
            for &a in &positioned {
                let i = c * n + a;
                dp += (p[i] - prior_p[i]).abs();
                dmu += p[i] * (mu[i] - prior_mu[i]).abs();
                dmu_weight += p[i];
            }
            refined.push(CellCalibration {
                at: [cell.x, cell.y],
                detection: positioned
                    .iter()
                    .map(|&a| round_to(p[c * n + a], 1e-4))
                    .collect(),
                rssi_dbm: positioned
                    .iter()
                    .map(|&a| round_to(mu[c * n + a], 1e-2))
                    .collect(),
            });
        }
        let change = CellChange {
            cells: refined.len(),
            detection_shift: dp / (refined.len() * positioned.len()).max(1) as f64,
            rssi_shift_db: dmu / dmu_weight.max(f64::MIN_POSITIVE),
        };
        Ok((refined, change, ll))
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
    fn between(id: &str, heard: usize, before: &Radio, after: &Radio) -> Change {
        let metres: Vec<f64> = (1..=10).map(f64::from).collect();
        let mean = |f: &dyn Fn(f64) -> f64| metres.iter().map(|&d| f(d)).sum::<f64>() / 10.0;
        Change {
            id: id.to_owned(),
            heard,
            before: *before,
            after: *after,
            rssi_shift_db: mean(&|d| after.expected_rssi(d) - before.expected_rssi(d)),
            detection_shift: mean(&|d| after.detection(d) - before.detection(d)),
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
