//! Localization in a building of several floors, from walks with timed
//! waypoints (the Indoor Location Competition layout, one folder of walks per
//! floor): is the floor right, and how far off is the fix on the right floor.
//!
//! - **Split by time.** Each floor's walks in the order of their first
//!   timestamp; the later [`TEST_SHARE`] are held out. Nothing below sees a
//!   held-out walk before it is measured.
//! - **What the daemon would have.** From the training walks only, as
//!   `gangway survey import` would make them: the beacons' identities (an id
//!   heard from several MACs is one beacon per MAC), each floor's beacons
//!   (every beacon heard on that floor often enough, at the position the
//!   import estimates from that floor's readings), each floor's survey (the
//!   import's windows, positions interpolated between waypoints, its
//!   refusals), and the localizer `[localizer] method` builds from them.
//! - **Floor, as the gateway decides it.** The floors' beacons and how
//!   loudly each is heard over each floor (the `heard_dbm` the import
//!   writes) are the evidence ([`FloorEvidence::of_floors`], as the gateway
//!   builds it from the floors' site files); each held-out walk's windows go through the
//!   gateway's own floor tracks in order ([`FloorTracks`]: the filter, a
//!   first guess corrected until it settles, then changes only through the
//!   building's connectors), and each window is located on that floor by
//!   its localizer and tracker, entering it at the connectors' stops as the
//!   gateway does. A window whose floor the gateway would publish as
//!   unknown counts as a wrong floor.
//! - **Recalibrated** (`--recalibrate`, the survey-free model): before
//!   measuring, each floor's radio model is fitted to what its training
//!   walks heard, positions unused, as the gateway's own recalibration
//!   fits what it hears ([`recalibrate::fit_heard`], with the config's
//!   `[localizer.recalibration]` settings and its held-out check). A floor
//!   whose walks heard too little keeps the defaults, and the report says so.
//! - **Baseline**, same windows: a k-NN regressor (k = 5, uniform weights,
//!   Euclidean over RSSI vectors of every beacon of the building with "not
//!   heard" = −100 dBm, as scikit-learn's `KNeighborsRegressor` defaults):
//!   x, y the neighbours' mean, the floor their majority.
//!
//! Errors are metres between the fix (its cell's centre) and the
//! interpolated truth, counted only where the floor is right.
//!
//! **Published confidence** is judged as on a survey
//! ([`crate::score::Reliability`]): the localizer's confidence times
//! the floor's probability, as the daemon publishes it, against whether the
//! fix is on the right floor within one of its cells of the truth.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;
use serde::Serialize;

use super::localization::{Surveyed, surveyed_localizer};
use super::planning::percentile;
use crate::locate::calibration::Calibration;
use crate::locate::floor_track::{self, FloorChange, FloorTracks};
use crate::locate::floors::FloorEvidence;
use crate::locate::gain::Gains;
use crate::locate::recalibrate::{self, Heard as HeardWindow};
use crate::locate::survey::Sample;
use crate::locate::tracker::{Tracker, TrackerConfig};
use crate::locate::window::WindowConfig;
use crate::locate::{Localizer, LocalizerConfig, Method};
use crate::score::{ErrorSummary, Reliability};
use crate::site::{Beacon, Building, Mount, Site};
use crate::survey::{self, Key, Keys, Options, Report, Walk};

/// Share of each floor's walks held out, the latest.
pub const TEST_SHARE: f64 = 0.3;
/// The baseline's neighbours.
const BASELINE_K: usize = 5;
/// The baseline's "not heard", dBm.
const BASELINE_NOT_HEARD: f32 = -100.0;

/// What to evaluate.
#[derive(Clone, Debug)]
pub struct FloorsSetup {
    pub method: Method,
    pub localizer: LocalizerConfig,
    pub window: WindowConfig,
    pub tracker: TrackerConfig,
    /// The floor filter's probability of changing floor between windows.
    pub floor_switch: f64,
    /// Fit each floor's survey-free model to its training walks' windows
    /// first, as the gateway's recalibration would.
    pub recalibrate: bool,
    /// Added to every held-out reading: a phone hearing that much louder.
    pub receiver_offset_db: f32,
}

/// Floor accuracy and errors on the right floor.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FloorMetrics {
    pub floor_accuracy: f64,
    /// Share of the fixes whose floor the gateway would publish as unknown
    /// (counted as wrong in `floor_accuracy`).
    pub floor_unknown: f64,
    pub mean_error_m: f64,
    pub median_error_m: f64,
    pub p90_error_m: f64,
    pub fixes: usize,
}

/// One method's figures, overall and per floor (by the true floor).
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FloorsMetrics {
    #[serde(flatten)]
    pub overall: FloorMetrics,
    pub floors: BTreeMap<String, FloorMetrics>,
}

/// Ours and the baseline's, on the same held-out windows.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct FloorsReport {
    pub method: String,
    #[serde(flatten)]
    pub ours: FloorsMetrics,
    pub baseline: FloorsMetrics,
    pub train_walks: usize,
    pub test_walks: usize,
    /// Held-out windows with no position (the import's refusals).
    pub refused_windows: usize,
    /// Our time per fix, µs, single-threaded: the floor evidence and filter,
    /// then that floor's localizer and tracker (as the daemon runs them per
    /// window); the median and the mean.
    pub us_per_fix_p50: f64,
    pub us_per_fix_mean: f64,
    /// Our published confidence against the share of fixes on the right
    /// floor within one cell.
    #[serde(flatten)]
    pub confidence: Reliability,
    /// With `--recalibrate`, per floor: what its recalibration kept, or why
    /// it kept the defaults.
    #[serde(skip_serializing_if = "BTreeMap::is_empty")]
    pub recalibrated: BTreeMap<String, String>,
}

/// One held-out window with a known position, and the gateway's fix for
/// it (published, or withheld: floor unknown or confidence under
/// `min_confidence`), for `--rows`.
#[derive(Clone, Debug)]
pub struct WindowFix {
    /// The floor the walk was on, and the walk (its file's name).
    pub floor: String,
    pub walk: String,
    /// The mean time of the window's readings, seconds (the walk file's
    /// clock).
    pub t: f64,
    /// Where the walker was, metres in `floor`'s frame.
    pub truth: [f64; 2],
    /// The floor the gateway located the window on, and whether it would
    /// publish that floor (else the floor is unknown).
    pub located_floor: String,
    pub floor_known: bool,
    /// The fix, metres in `located_floor`'s frame.
    pub fix: [f64; 2],
    /// The published confidence: the localizer's times the floor's.
    pub confidence: f32,
    /// Metres from the truth, when located on the walk's floor.
    pub error_m: Option<f64>,
}

/// One floor's walks, split.
struct FloorWalks {
    train: Vec<Walk>,
    test: Vec<Walk>,
}

/// One fix or guess: its floor (none: unknown), and its error in metres
/// when the floor is right.
#[derive(Clone, Copy)]
struct Outcome {
    truth_floor: usize,
    floor: Option<usize>,
    error_m: f64,
}

/// Evaluates `building` with the walks in `walks_dir/<floor name>/path_data_files`.
pub fn evaluate(
    building: &Building,
    walks_dir: &Path,
    setup: &FloorsSetup,
) -> anyhow::Result<(FloorsReport, Vec<WindowFix>)> {
    let options = Options {
        window_s: setup.window.length_s,
        stride_s: setup.window.stride_s,
        ..Options::default()
    };
    let floors = building.floors();
    let mut split = Vec::with_capacity(floors.len());
    for floor in floors {
        let dir = walks_dir.join(&floor.name).join("path_data_files");
        let mut walks = survey::read_walks(&dir, &mut Report::default())
            .with_context(|| format!("floor `{}`", floor.name))?;
        walks.sort_by(|a, b| first_time(a).total_cmp(&first_time(b)));
        let test = (walks.len() as f64 * TEST_SHARE).round() as usize;
        anyhow::ensure!(
            test > 0 && test < walks.len(),
            "{}: {} walks cannot be split {:.0}/{:.0} by time",
            dir.display(),
            walks.len(),
            100.0 * (1.0 - TEST_SHARE),
            100.0 * TEST_SHARE
        );
        let test = walks.split_off(walks.len() - test);
        split.push(FloorWalks { train: walks, test });
    }
    let keys = Keys::of(split.iter().flat_map(|f| &f.train));

    // Each floor's beacons and the building's: every key some floor kept.
    let mut per_floor = Vec::with_capacity(floors.len());
    for (floor, walks) in floors.iter().zip(&split) {
        let estimates = survey::estimate_beacons(
            &floor.site,
            &walks.train,
            &keys,
            &options,
            &mut Report::default(),
        );
        per_floor.push(estimates);
    }
    let all: Vec<Key> = per_floor
        .iter()
        .flat_map(|e| e.keys().copied())
        .collect::<BTreeSet<_>>()
        .into_iter()
        .collect();

    let listed: Vec<Vec<(usize, Option<f64>)>> = per_floor
        .iter()
        .map(|estimates| {
            estimates
                .iter()
                .map(|(key, estimate)| {
                    let anchor = all
                        .binary_search(key)
                        .expect("every floor's keys are in `all`");
                    (anchor, Some(estimate.heard_dbm))
                })
                .collect()
        })
        .collect();
    let mut floor_tracks = FloorTracks::new(
        building,
        FloorEvidence::of_floors(&listed),
        setup.floor_switch,
        setup.tracker.reset_after_s,
    );
    let sites: Vec<(Arc<Site>, Vec<Key>)> = floors
        .iter()
        .zip(&per_floor)
        .map(|(floor, estimates)| {
            let (site, ids) = floor_site(&floor.site, estimates);
            (Arc::new(site), ids)
        })
        .collect();
    // Each floor's fit is its own (seconds to minutes on a large floor):
    // one thread per floor.
    let (mut calibrations, said): (Vec<Option<Calibration>>, Vec<String>) = if setup.recalibrate {
        std::thread::scope(|scope| {
            let fits: Vec<_> = sites
                .iter()
                .zip(&split)
                .map(|((site, ids), walks)| {
                    let (keys, all, options) = (&keys, &all, &options);
                    scope.spawn(move || {
                        recalibration(setup, site, ids, &walks.train, keys, all, options)
                    })
                })
                .collect();
            fits.into_iter()
                .map(|fit| fit.join().expect("a floor's recalibration panicked"))
                .unzip()
        })
    } else {
        (Vec::new(), Vec::new())
    };
    let recalibrated: BTreeMap<String, String> =
        floors.iter().map(|f| f.name.clone()).zip(said).collect();
    let mut localizers = Vec::with_capacity(floors.len());
    let mut baseline_train = Vec::new();
    for (f, ((site, ids), walks)) in sites.into_iter().zip(&split).enumerate() {
        let floor = &floors[f];
        let windows = labelled_windows(&site, &walks.train, &keys, &all, &options);
        let samples: Vec<Sample> = windows
            .iter()
            .map(|(t, at, heard)| {
                let mut rssi = vec![None; ids.len()];
                for &(a, r) in heard {
                    if let Ok(i) = ids.binary_search(&all[a]) {
                        rssi[i] = Some(r);
                    }
                }
                let cell = site
                    .cell_of_world(*at)
                    .expect("labelled on a walkable cell");
                Sample {
                    cell,
                    at: *at,
                    t: Some(*t),
                    rssi,
                }
            })
            .collect();
        baseline_train.extend(windows.into_iter().map(|(_, at, heard)| (f, at, heard)));
        let refs: Vec<&Sample> = samples.iter().collect();
        let calibration = calibrations.get_mut(f).and_then(Option::take);
        let localizer = localizer(setup, &site, &refs, calibration.as_ref())
            .with_context(|| format!("floor `{}`: its localizer", floor.name))?;
        let tracker = Tracker::new(setup.tracker.clone(), site.clone());
        let gains = setup.localizer.device_gains.then(Gains::default);
        localizers.push((site, ids, localizer, tracker, gains));
    }
    let baseline = Baseline::new(&baseline_train, all.len());

    let mut ours = Vec::new();
    let mut theirs = Vec::new();
    let mut refused_windows = 0;
    let mut fix_us = Vec::new();
    // (published confidence, error in cells: infinite on a wrong floor).
    let mut confidences = Vec::new();
    let mut window_fixes = Vec::new();
    for (truth_floor, walks) in split.iter().enumerate() {
        let truth_site = &floors[truth_floor].site;
        for (w, walk) in walks.test.iter().enumerate() {
            let entity: Arc<str> = Arc::from(format!("{truth_floor}-{w}"));
            let mut on_floor: Option<usize> = None;
            for (t, mut heard) in survey::windows(walk, &keys, &all, &options) {
                // Every consumer hears the same phone: floors, fixes, baseline.
                for (_, r) in &mut heard {
                    *r = (f32::from(*r) + setup.receiver_offset_db).round() as i16;
                }
                let truth = survey::labelled(truth_site, walk, t, &options);
                let started = Instant::now();
                let heard_f: Vec<(usize, f32)> =
                    heard.iter().map(|&(a, r)| (a, f32::from(r))).collect();
                let step = floor_tracks.update(&entity, t, &heard_f);
                let floor = step.floor;
                if let Some(left) = on_floor.filter(|&f| f != floor) {
                    localizers[left].3.forget(&entity);
                }
                on_floor = Some(floor);
                let Ok(truth) = truth else {
                    refused_windows += 1;
                    continue;
                };
                let localize = Instant::now();
                let (site, ids, localizer, tracker, gains) = &mut localizers[floor];
                let mut rssi = vec![setup.window.missing_dbm; ids.len()];
                let mut heard_on_floor = vec![false; ids.len()];
                for &(a, r) in &heard {
                    if let Ok(i) = ids.binary_search(&all[a]) {
                        rssi[i] = f32::from(r);
                        heard_on_floor[i] = true;
                    }
                }
                let mut ll = vec![0.0f32; site.open_cells().len()];
                match gains {
                    Some(gains) => gains.log_likelihood(
                        localizer.as_mut(),
                        &entity,
                        &rssi,
                        &heard_on_floor,
                        &mut ll,
                    ),
                    None => localizer.log_likelihood(&rssi, &heard_on_floor, &mut ll),
                }
                let fix = match step.change {
                    FloorChange::From(from) => {
                        tracker.enter(&entity, t, floor_tracks.entries(from, floor), &ll)
                    }
                    FloorChange::Starts | FloorChange::Stays => tracker.update(&entity, t, &ll),
                };
                if let (Some(gains), Some(cell)) = (gains, site.open_index(fix.cell)) {
                    gains.learn(localizer.as_mut(), &entity, t, &rssi, &heard_on_floor, cell);
                }
                fix_us.push((localize - started + localize.elapsed()).as_secs_f64() * 1e6);
                let at = site.world_of_cell(fix.cell);
                let outcome = Outcome {
                    truth_floor,
                    floor: (step.probability >= floor_track::KNOWN).then_some(floor),
                    error_m: (at[0] - truth[0]).hypot(at[1] - truth[1]),
                };
                let heard_count = heard_on_floor.iter().filter(|&&h| h).count();
                let confidence =
                    localizer.confidence(fix.confidence, heard_count) * step.probability as f32;
                window_fixes.push(WindowFix {
                    floor: floors[truth_floor].name.clone(),
                    walk: walk.name.clone(),
                    t,
                    truth,
                    located_floor: floors[floor].name.clone(),
                    floor_known: outcome.floor.is_some(),
                    fix: at,
                    confidence,
                    error_m: (floor == truth_floor).then_some(outcome.error_m),
                });
                confidences.push((
                    confidence,
                    if floor == truth_floor {
                        outcome.error_m / site.cell_m
                    } else {
                        f64::INFINITY
                    },
                ));
                ours.push(outcome);
                let (floor, at) = baseline.predict(&heard);
                theirs.push(Outcome {
                    truth_floor,
                    floor: Some(floor),
                    error_m: (at[0] - truth[0]).hypot(at[1] - truth[1]),
                });
            }
        }
    }
    let names: Vec<&str> = floors.iter().map(|f| f.name.as_str()).collect();
    let report = FloorsReport {
        method: setup.method.name().into(),
        ours: summarise(&ours, &names),
        baseline: summarise(&theirs, &names),
        train_walks: split.iter().map(|f| f.train.len()).sum(),
        test_walks: split.iter().map(|f| f.test.len()).sum(),
        refused_windows,
        us_per_fix_mean: fix_us.iter().sum::<f64>() / fix_us.len().max(1) as f64,
        us_per_fix_p50: percentile(&mut fix_us, 0.5).unwrap_or(0.0),
        confidence: Reliability::of(&confidences),
        recalibrated,
    };
    Ok((report, window_fixes))
}

/// One floor's survey-free model recalibrated from what its training walks
/// heard (each walk a device; `ids`: the floor's beacons, sorted, as keys
/// of `all`), and what was kept, or why nothing was.
fn recalibration(
    setup: &FloorsSetup,
    site: &Arc<Site>,
    ids: &[Key],
    walks: &[Walk],
    keys: &Keys,
    all: &[Key],
    options: &Options,
) -> (Option<Calibration>, String) {
    let names: Vec<&str> = site.beacons.iter().map(|b| b.id.as_str()).collect();
    let mut rows = Vec::new();
    for (w, walk) in walks.iter().enumerate() {
        for (t, heard) in survey::windows(walk, keys, all, options) {
            let readings: Vec<(String, f32)> = heard
                .iter()
                .filter_map(|&(a, r)| {
                    let i = ids.binary_search(&all[a]).ok()?;
                    Some((names[i].to_owned(), f32::from(r)))
                })
                .collect();
            if !readings.is_empty() {
                rows.push(HeardWindow {
                    device: format!("walk-{w:05}"),
                    t,
                    readings,
                    floor: None,
                });
            }
        }
    }
    match recalibrate::fit_heard(
        site,
        setup.window.orientation,
        &setup.localizer.pathloss,
        &setup.tracker,
        &setup.localizer.recalibration,
        &rows,
    ) {
        Ok(done) => {
            let kept = done.fitted.changes.iter().filter(|c| c.kept).count();
            let cells = done.fitted.cells.as_ref().map_or(0, |c| c.cells);
            let said = format!(
                "{} windows of {} walks: {kept} of {} beacons' models and {cells} cells' kept",
                done.windows,
                done.trajectories,
                done.fitted.changes.len()
            );
            (Some(done.fitted.calibration), said)
        }
        Err(e) => (None, format!("the defaults kept: {e}")),
    }
}

fn first_time(walk: &Walk) -> f64 {
    let waypoint = walk.waypoints.first().map_or(f64::INFINITY, |w| w.0);
    let reading = walk.readings.first().map_or(f64::INFINITY, |r| r.t);
    waypoint.min(reading)
}

/// The floor's site with the beacons estimated for it (sorted by key, which
/// is also the order of the returned keys).
fn floor_site(site: &Site, estimates: &BTreeMap<Key, survey::Estimate>) -> (Site, Vec<Key>) {
    let docs = survey::beacon_docs(estimates);
    let mut site = site.clone();
    site.beacons = docs
        .into_iter()
        .zip(estimates)
        .map(|(doc, (key, estimate))| Beacon {
            id: doc.id,
            beacon: key.0,
            cell: site.cell_of_world(estimate.at),
            mount: Some(Mount {
                at: estimate.at,
                height_m: None,
            }),
            tx_power: estimate.tx_power,
            mac: key.1,
            heard_dbm: Some(estimate.heard_dbm),
        })
        .collect();
    (site, estimates.keys().copied().collect())
}

/// Each beacon heard in a window: its index in the building's beacons, dBm.
type Heard = Vec<(usize, i16)>;

/// The labelled windows of `walks` (on `site`'s walkable cells): time,
/// position, and each beacon of `all` heard.
fn labelled_windows(
    site: &Site,
    walks: &[Walk],
    keys: &Keys,
    all: &[Key],
    options: &Options,
) -> Vec<(f64, [f64; 2], Heard)> {
    let mut out = Vec::new();
    for walk in walks {
        for (t, heard) in survey::windows(walk, keys, all, options) {
            if let Ok(at) = survey::labelled(site, walk, t, options) {
                out.push((t, at, heard));
            }
        }
    }
    out
}

/// The localizer `setup.method` builds for one floor's survey.
fn localizer(
    setup: &FloorsSetup,
    site: &Arc<Site>,
    samples: &[&Sample],
    calibration: Option<&Calibration>,
) -> anyhow::Result<Box<dyn Localizer>> {
    let ids: Vec<String> = site.beacons.iter().map(|b| b.id.clone()).collect();
    let from = Surveyed {
        localizer: &setup.localizer,
        window: &setup.window,
        tracker: &setup.tracker,
        site,
        ids: &ids,
        samples,
        calibration,
    };
    surveyed_localizer(setup.method, from, || {
        anyhow::bail!(
            "--method onnx is not evaluated on walks; train a model with `gangway train` and \
             evaluate it on a survey"
        )
    })
}

/// The k-NN baseline over the training windows of every floor.
struct Baseline {
    /// Per training window: floor, position, heard (beacon, dBm − not heard).
    rows: Vec<(usize, [f64; 2], f64)>,
    /// Per beacon: (training window, its dBm above "not heard").
    by_beacon: Vec<Vec<(usize, f32)>>,
}

impl Baseline {
    fn new(train: &[(usize, [f64; 2], Heard)], beacons: usize) -> Baseline {
        let mut by_beacon = vec![Vec::new(); beacons];
        let rows = train
            .iter()
            .enumerate()
            .map(|(i, (floor, at, heard))| {
                let mut norm = 0.0;
                for &(a, r) in heard {
                    let v = f32::from(r) - BASELINE_NOT_HEARD;
                    by_beacon[a].push((i, v));
                    norm += f64::from(v * v);
                }
                (*floor, *at, norm)
            })
            .collect();
        Baseline { rows, by_beacon }
    }

    /// The floor and position of one window: the k nearest training windows'
    /// majority floor (ties to the lower floor index, as scikit-learn's mode)
    /// and mean position. With the vectors shifted so that "not heard" is 0,
    /// |a − b|² = |a|² + |b|² − 2 a·b, and a·b runs over the beacons both heard.
    fn predict(&self, heard: &[(usize, i16)]) -> (usize, [f64; 2]) {
        let mut dot = vec![0.0f64; self.rows.len()];
        let mut norm = 0.0;
        for &(a, r) in heard {
            let v = f32::from(r) - BASELINE_NOT_HEARD;
            norm += f64::from(v * v);
            for &(i, w) in &self.by_beacon[a] {
                dot[i] += f64::from(v * w);
            }
        }
        let mut nearest: Vec<(f64, usize)> = self
            .rows
            .iter()
            .zip(&dot)
            .enumerate()
            .map(|(i, (row, d))| (norm + row.2 - 2.0 * d, i))
            .collect();
        let k = BASELINE_K.min(nearest.len());
        if k == 0 {
            return (0, [0.0, 0.0]);
        }
        nearest.select_nth_unstable_by(k - 1, |a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let nearest = &nearest[..k];
        let mut votes: BTreeMap<usize, usize> = BTreeMap::new();
        let mut at = [0.0; 2];
        for &(_, i) in nearest {
            let (floor, pos, _) = self.rows[i];
            *votes.entry(floor).or_default() += 1;
            at[0] += pos[0] / k as f64;
            at[1] += pos[1] / k as f64;
        }
        let most = votes.values().copied().max().unwrap_or(0);
        let floor = votes
            .into_iter()
            .find(|&(_, n)| n == most)
            .map_or(0, |(f, _)| f);
        (floor, at)
    }
}

fn metrics(outcomes: &[&Outcome]) -> FloorMetrics {
    let right: Vec<f64> = outcomes
        .iter()
        .filter(|o| o.floor == Some(o.truth_floor))
        .map(|o| o.error_m)
        .collect();
    let errors = ErrorSummary::of(&right, 1.0).unwrap_or_default();
    let share = |n: usize| {
        if outcomes.is_empty() {
            0.0
        } else {
            n as f64 / outcomes.len() as f64
        }
    };
    FloorMetrics {
        floor_accuracy: share(right.len()),
        floor_unknown: share(outcomes.iter().filter(|o| o.floor.is_none()).count()),
        mean_error_m: errors.mean_error_m,
        median_error_m: errors.median_error_m,
        p90_error_m: errors.p90_error_m,
        fixes: outcomes.len(),
    }
}

fn summarise(outcomes: &[Outcome], names: &[&str]) -> FloorsMetrics {
    let all: Vec<&Outcome> = outcomes.iter().collect();
    FloorsMetrics {
        overall: metrics(&all),
        floors: names
            .iter()
            .enumerate()
            .map(|(f, name)| {
                let on: Vec<&Outcome> = outcomes.iter().filter(|o| o.truth_floor == f).collect();
                ((*name).to_owned(), metrics(&on))
            })
            .collect(),
    }
}
