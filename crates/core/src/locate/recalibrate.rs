//! Recalibration from what the gateway itself hears: the survey-free radio
//! model refitted on a schedule or on request, with no position known. This
//! is the computing half; the runtime's half (`daemon::recalibrate` in the
//! binary) reads the store, runs [`fit_heard`] on a blocking thread, writes the
//! file and swaps the pipeline, so nothing here touches a file or a clock:
//! - [`Heard::of`] turns each fingerprint window that heard an anchor into an
//!   [`crate::publish::Output::Heard`], which the learning store's sink keeps
//!   (memory: the sink's bounded buffer; disk: the store's quotas and
//!   [`RecalibrationConfig::max_windows`]);
//! - [`Schedule`] says when a run is due: every `every_h` hours once
//!   `min_windows` new windows were heard, or at once on request (the runtime
//!   passes the time in);
//! - [`fit_heard`] fits the radio model by EM to the newest windows the
//!   runtime read back (per cell too when `cells` is set, since these are the
//!   phones and the floor the gateway localizes) and keeps only what windows
//!   held out from the fit confirm ([`super::calibrate::calibrate`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::calibrate::{
    CALIBRATION_ITERATIONS, DEFAULT_CELL_PRIOR_READINGS, FitOptions, Fitted, Window, calibrate,
};
use super::pathloss::{PathLossConfig, anchors};
use super::tracker::TrackerConfig;
use super::window::{Orientation, anchor_ids};
use super::{LocalizerConfig, LocalizerError, Method};
use crate::site::Site;

/// `[localizer.recalibration]` in the gateway config.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RecalibrationConfig {
    /// Gather what is heard into the learning store (`[store] enabled`) and
    /// recalibrate the survey-free model from it.
    pub enabled: bool,
    /// Hours between scheduled recalibrations; 0: only on request.
    pub every_h: f64,
    /// Windows gathered since the last run before a scheduled one starts.
    pub min_windows: usize,
    /// Newest windows kept in the store and read by a run.
    pub max_windows: usize,
    /// Also refine a radio map per cell (see [`super::calibrate`]).
    pub cells: bool,
    /// The calibration file written; default `calibration.toml` beside the
    /// learning store.
    pub out: Option<PathBuf>,
}

impl Default for RecalibrationConfig {
    fn default() -> Self {
        RecalibrationConfig {
            enabled: false,
            every_h: 24.0,
            min_windows: 2_000,
            max_windows: 50_000,
            cells: true,
            out: None,
        }
    }
}

impl RecalibrationConfig {
    /// Checks the values a user can get wrong, naming the key.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.every_h.is_finite() && self.every_h >= 0.0) {
            return Err(format!(
                "`every_h` = {} must be a number of hours, 0 or more",
                self.every_h
            ));
        }
        if self.max_windows == 0 || self.min_windows > self.max_windows {
            return Err(format!(
                "`max_windows` ({}) must be positive and at least `min_windows` ({})",
                self.max_windows, self.min_windows
            ));
        }
        Ok(())
    }

    /// Where the calibration goes: `out`, else beside the store; on a
    /// building of several floors, `floor`'s own file of it
    /// ([`crate::site::floor_file`]: `calibration-B1.toml`), since each
    /// floor's radio model is fitted to that floor's windows.
    pub fn out_path(&self, store: &Path, floor: Option<&str>) -> PathBuf {
        let path = self
            .out
            .clone()
            .unwrap_or_else(|| store.with_file_name("calibration.toml"));
        match floor {
            Some(floor) => crate::site::floor_file(&path, floor, true),
            None => path,
        }
    }
}

/// EM iterations of the per-cell refinement of a scheduled run.
const CELL_ITERATIONS: usize = 8;

/// Trajectories longer than this many windows are fitted in pieces, so a
/// run's memory is bounded by the site, not by how long a device stayed.
const MAX_TRAJECTORY: usize = 512;

/// One fingerprint window kept for recalibration: the anchors a device heard
/// (by id, so a site whose anchors are reordered still reads it) and how loud.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Heard {
    pub device: String,
    pub t: f64,
    pub readings: Vec<(String, f32)>,
    /// On a building of several floors, the floor the device was on (only
    /// windows whose floor was known are kept): each floor's radio model is
    /// fitted to its own windows. `None` on a one-floor site.
    pub floor: Option<String>,
}

impl Heard {
    /// A window of one floor, if it heard any of the floor's anchors:
    /// `rssi` and `heard` hold one value per anchor in the order of `ids`
    /// ([`anchor_ids`]).
    pub fn of(device: &str, t: f64, rssi: &[f32], heard: &[bool], ids: &[String]) -> Option<Heard> {
        let readings: Vec<(String, f32)> = heard
            .iter()
            .zip(rssi)
            .zip(ids)
            .filter(|((heard, _), _)| **heard)
            .map(|((_, &rssi), id)| (id.clone(), rssi))
            .collect();
        (!readings.is_empty()).then(|| Heard {
            device: device.to_owned(),
            t,
            readings,
            floor: None,
        })
    }

    /// This window as heard on floor `floor` of a building of several.
    pub fn on_floor(self, floor: &str) -> Heard {
        Heard {
            floor: Some(floor.to_owned()),
            ..self
        }
    }
}

/// Whether recalibration changes what `config` serves: the survey-free
/// model, configured or chosen by `auto` for want of a survey.
pub fn applies(config: &LocalizerConfig) -> bool {
    match config.method {
        Method::Pathloss => true,
        Method::Auto => config.knn.survey.is_none() && config.radiomap.survey.is_none(),
        Method::Knn | Method::Radiomap | Method::Onnx | Method::Strongest => false,
    }
}

/// When the next recalibration is due.
#[derive(Clone, Debug)]
pub struct Schedule {
    every_s: f64,
    min_windows: u64,
    /// Time of the last run's start (or of the schedule's creation).
    last: f64,
    /// Windows heard (since start) at the last run's start.
    gathered_at_last: u64,
    requested: bool,
    running: bool,
}

impl Schedule {
    pub fn new(config: &RecalibrationConfig, now: f64) -> Schedule {
        Schedule {
            every_s: config.every_h * 3600.0,
            min_windows: config.min_windows as u64,
            last: now,
            gathered_at_last: 0,
            requested: false,
            running: false,
        }
    }

    /// Asks for a run as soon as none is running.
    pub fn request(&mut self) {
        self.requested = true;
    }

    /// Whether a run should start now, `gathered` windows having been kept
    /// since start.
    pub fn due(&self, now: f64, gathered: u64) -> bool {
        if self.running {
            return false;
        }
        let scheduled = self.every_s > 0.0
            && now - self.last >= self.every_s
            && gathered.saturating_sub(self.gathered_at_last) >= self.min_windows;
        self.requested || scheduled
    }

    /// A run started.
    pub fn started(&mut self, now: f64, gathered: u64) {
        self.running = true;
        self.requested = false;
        self.last = now;
        self.gathered_at_last = gathered;
    }

    /// The run ended (applied or not).
    pub fn finished(&mut self) {
        self.running = false;
    }
}

/// Why a recalibration was not fitted.
#[derive(Debug, thiserror::Error)]
pub enum FitError {
    #[error(
        "only {found} fingerprint windows gathered, {needed} needed \
         ([localizer.recalibration] min_windows)"
    )]
    TooFew { found: usize, needed: usize },
    #[error(transparent)]
    Fit(#[from] LocalizerError),
}

/// A fitted recalibration and what it was fitted on.
pub struct FittedHeard {
    pub fitted: Fitted,
    pub windows: usize,
    pub trajectories: usize,
}

/// Fits the survey-free model, starting from the configured `pathloss`, to
/// the stored windows `rows` (by device, then time), as `config` asks
/// (blocking: seconds for tens of thousands of windows).
pub fn fit_heard(
    site: &Arc<Site>,
    orientation: Orientation,
    pathloss: &PathLossConfig,
    tracker: &TrackerConfig,
    config: &RecalibrationConfig,
    rows: &[Heard],
) -> Result<FittedHeard, FitError> {
    let ids = anchor_ids(site, orientation);
    let trajectories = trajectories(rows, &ids, tracker.reset_after_s);
    let windows: usize = trajectories.iter().map(Vec::len).sum();
    if windows < config.min_windows.max(1) {
        return Err(FitError::TooFew {
            found: windows,
            needed: config.min_windows.max(1),
        });
    }
    let start = anchors(site, orientation, pathloss, None);
    let options = FitOptions {
        iterations: CALIBRATION_ITERATIONS,
        cell_iterations: if config.cells { CELL_ITERATIONS } else { 0 },
        cell_prior_readings: DEFAULT_CELL_PRIOR_READINGS,
    };
    let fitted = calibrate(site, &ids, &start, tracker, &trajectories, &options)?;
    Ok(FittedHeard {
        fitted,
        windows,
        trajectories: trajectories.len(),
    })
}

/// The localizer config that loads a recalibrated file: what the daemon
/// builds anew and swaps in. On a building of several floors the file is
/// `floor`'s, and serves that floor only ([`LocalizerConfig::recalibrated`]).
pub fn with_calibration(
    config: &LocalizerConfig,
    floor: Option<&str>,
    path: &Path,
) -> LocalizerConfig {
    let mut config = config.clone();
    match floor {
        Some(floor) => {
            config
                .recalibrated
                .insert(floor.to_owned(), path.to_owned());
        }
        None => config.pathloss.calibration = Some(path.to_owned()),
    }
    config
}

/// Stored windows (by device, then time) as trajectories: a device's windows
/// split where the tracker would restart, and into pieces of at most
/// [`MAX_TRAJECTORY`]; readings of anchors the site does not have are left out.
fn trajectories(rows: &[Heard], ids: &[String], reset_after_s: f64) -> Vec<Vec<Window>> {
    let slot: BTreeMap<&str, usize> = ids
        .iter()
        .enumerate()
        .map(|(i, id)| (id.as_str(), i))
        .collect();
    let mut out: Vec<Vec<Window>> = Vec::new();
    let mut last: Option<(&str, f64)> = None;
    for row in rows {
        let mut rssi = vec![None; ids.len()];
        for (id, r) in &row.readings {
            if let Some(&a) = slot.get(id.as_str())
                && r.is_finite()
            {
                rssi[a] = Some(*r);
            }
        }
        if rssi.iter().all(Option::is_none) {
            continue;
        }
        let continues = last.is_some_and(|(device, t)| {
            device == row.device && (0.0..=reset_after_s).contains(&(row.t - t))
        });
        match out.last_mut() {
            Some(trajectory) if continues && trajectory.len() < MAX_TRAJECTORY => {}
            _ => out.push(Vec::new()),
        }
        out.last_mut().expect("pushed").push(Window {
            t: row.t,
            rssi,
            cell: None,
        });
        last = Some((&row.device, row.t));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::locate::window::Fingerprint;

    /// A corridor of 12 cells with a beacon at each end and one halfway.
    fn site() -> Arc<Site> {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../fixtures/sites/corridor.toml"
        );
        Arc::new(Site::load(Path::new(path)).unwrap())
    }

    #[test]
    fn a_window_is_kept_by_anchor_id_and_only_if_it_heard_one() {
        let site = site();
        let ids = anchor_ids(&site, Orientation::Observer);
        let silent = Fingerprint {
            entity: "p".into(),
            t: 4.0,
            rssi: vec![-105.0; 3],
            heard: vec![false; 3],
        };
        let of = |w: &Fingerprint| Heard::of(&w.entity, w.t, &w.rssi, &w.heard, &ids);
        assert_eq!(of(&silent), None);
        let heard = Fingerprint {
            heard: vec![false, true, false],
            rssi: vec![-105.0, -71.0, -105.0],
            ..silent
        };
        assert_eq!(
            of(&heard),
            Some(Heard {
                device: "p".into(),
                t: 4.0,
                readings: vec![("middle".into(), -71.0)],
                floor: None,
            })
        );
    }

    #[test]
    fn the_schedule_waits_for_time_and_windows_and_a_request_runs_at_once() {
        let config = RecalibrationConfig {
            every_h: 1.0,
            min_windows: 100,
            ..RecalibrationConfig::default()
        };
        let mut schedule = Schedule::new(&config, 0.0);
        assert!(!schedule.due(3599.0, 1000), "too early");
        assert!(!schedule.due(3600.0, 99), "too few windows");
        assert!(schedule.due(3600.0, 100));
        schedule.started(3600.0, 100);
        assert!(!schedule.due(9000.0, 10_000), "one run at a time");
        schedule.finished();
        assert!(!schedule.due(3700.0, 10_000), "an hour after the last run");
        schedule.request();
        assert!(schedule.due(3700.0, 100), "on request, at once");
        schedule.started(3700.0, 100);
        schedule.finished();
        assert!(!schedule.due(3701.0, 100));
    }
}
