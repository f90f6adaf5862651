//! Recalibration from what the gateway itself hears: the survey-free radio
//! model refitted on a schedule or on request, with no position known.
//!
//! Three parts, so that the daemon's event loop only ever does the cheap one:
//! - [`Heard::of`] turns each fingerprint window that heard an anchor into an
//!   [`crate::publish::Output::Heard`], which the learning store's sink keeps
//!   ([`crate::store::Record::Heard`]; memory: the sink's bounded buffer; disk:
//!   the store's quotas and [`RecalibrationConfig::max_windows`], see
//!   [`Store::keep_newest_heard`]);
//! - [`Schedule`] says when a run is due: every `every_h` hours once
//!   `min_windows` new windows were heard, or at once on request;
//! - [`run`] is the job: it reads the newest windows from the store, fits
//!   the radio model by EM ([`super::calibrate::fit`], per cell too when
//!   `cells` is set, since these are the phones and the floor the gateway
//!   localizes), writes the calibration file atomically (a temporary file
//!   renamed over the old one) and returns it. It blocks for seconds and
//!   touches nothing the event loop holds, so it runs on a blocking thread;
//!   the daemon then builds its pipeline anew with the file and swaps it in
//!   only if that succeeds, as a reload does. Restarts and reloads serve the
//!   newest recalibrated file ([`serving`]).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::calibrate::{
    Calibration, CellChange, Change, DEFAULT_CELL_PRIOR_READINGS, FitOptions, Window, fit,
};
use super::pathloss::{PathLossConfig, anchors};
use super::tracker::TrackerConfig;
use super::window::{Fingerprint, Orientation, anchor_ids};
use super::{LocalizerConfig, LocalizerError, Method};
use crate::site::Site;
use crate::store::{Store, StoreConfig, StoreError};

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
    pub(crate) fn validate(&self) -> Result<(), String> {
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

    /// Where the calibration goes: `out`, else beside the store.
    pub(crate) fn out_path(&self, store: &Path) -> PathBuf {
        self.out
            .clone()
            .unwrap_or_else(|| store.with_file_name("calibration.toml"))
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
}

impl Heard {
    /// The window, if it heard any anchor; `ids` are the anchors in the
    /// window's order ([`anchor_ids`]).
    pub(crate) fn of(window: &Fingerprint, ids: &[String]) -> Option<Heard> {
        let readings: Vec<(String, f32)> = window
            .heard
            .iter()
            .zip(&window.rssi)
            .zip(ids)
            .filter(|((heard, _), _)| **heard)
            .map(|((_, &rssi), id)| (id.clone(), rssi))
            .collect();
        (!readings.is_empty()).then(|| Heard {
            device: window.entity.to_string(),
            t: window.t,
            readings,
        })
    }
}

/// Whether recalibration changes what `config` serves: the survey-free
/// model, configured or chosen by `auto` for want of a survey.
pub(crate) fn applies(config: &LocalizerConfig) -> bool {
    match config.method {
        Method::Pathloss => true,
        Method::Auto => config.knn.survey.is_none() && config.radiomap.survey.is_none(),
        Method::Knn | Method::Radiomap | Method::Onnx | Method::Strongest => false,
    }
}

/// The localizer config a gateway serves with: with recalibration on and a
/// recalibrated file that loads, that file; else `config` as it is.
pub(crate) fn serving(
    config: &LocalizerConfig,
    store: &StoreConfig,
    site: &Site,
) -> LocalizerConfig {
    if !(config.recalibration.enabled && applies(config)) {
        return config.clone();
    }
    let path = config.recalibration.out_path(&store.resolved_path());
    if !path.exists() {
        return config.clone();
    }
    match Calibration::load(&path, site) {
        Ok(_) => with_calibration(config, &path),
        Err(e) => {
            tracing::error!("{e}; serving the configured calibration instead");
            config.clone()
        }
    }
}

/// When the next recalibration is due.
#[derive(Clone, Debug)]
pub(crate) struct Schedule {
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
    pub(crate) fn new(config: &RecalibrationConfig, now: f64) -> Schedule {
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
    pub(crate) fn request(&mut self) {
        self.requested = true;
    }

    /// Whether a run should start now, `gathered` windows having been kept
    /// since start.
    pub(crate) fn due(&self, now: f64, gathered: u64) -> bool {
        if self.running {
            return false;
        }
        let scheduled = self.every_s > 0.0
            && now - self.last >= self.every_s
            && gathered.saturating_sub(self.gathered_at_last) >= self.min_windows;
        self.requested || scheduled
    }

    /// A run started.
    pub(crate) fn started(&mut self, now: f64, gathered: u64) {
        self.running = true;
        self.requested = false;
        self.last = now;
        self.gathered_at_last = gathered;
    }

    /// The run ended (applied or not).
    pub(crate) fn finished(&mut self) {
        self.running = false;
    }
}

/// Everything a recalibration reads, owned, so the job can run on another
/// thread while the daemon serves.
#[derive(Clone, Debug)]
pub(crate) struct Job {
    pub site: Arc<Site>,
    pub orientation: Orientation,
    /// The configured model EM starts from (its calibration file unused).
    pub pathloss: PathLossConfig,
    pub tracker: TrackerConfig,
    pub config: RecalibrationConfig,
    /// The learning store the windows are in.
    pub store: PathBuf,
}

impl Job {
    /// The job of a gateway config's parts.
    pub(crate) fn new(
        site: &Arc<Site>,
        orientation: Orientation,
        localizer: &LocalizerConfig,
        tracker: &TrackerConfig,
        store: &Path,
    ) -> Job {
        Job {
            site: site.clone(),
            orientation,
            pathloss: localizer.pathloss.clone(),
            tracker: tracker.clone(),
            config: localizer.recalibration.clone(),
            store: store.to_owned(),
        }
    }
}

/// A finished recalibration.
#[derive(Debug)]
pub(crate) struct Recalibrated {
    /// What was written to `path` (the daemon reloads it from there).
    #[cfg(test)]
    pub calibration: Calibration,
    /// The file written.
    pub path: PathBuf,
    pub windows: usize,
    pub trajectories: usize,
    pub changes: Vec<Change>,
    pub cells: Option<CellChange>,
    pub seconds: f64,
}

#[derive(Debug, thiserror::Error)]
pub(crate) enum RecalibrationError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error(
        "only {found} fingerprint windows gathered, {needed} needed \
         ([localizer.recalibration] min_windows)"
    )]
    TooFew { found: usize, needed: usize },
    #[error(transparent)]
    Fit(#[from] LocalizerError),
    #[error("{}: cannot write the calibration: {source}", path.display())]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// Runs one recalibration (blocking; see the module doc).
pub(crate) fn run(job: &Job) -> Result<Recalibrated, RecalibrationError> {
    let started = std::time::Instant::now();
    let store = Store::open_read_only(&job.store)?;
    let rows = store.heard(job.config.max_windows)?;
    drop(store);
    let ids = anchor_ids(&job.site, job.orientation);
    let trajectories = trajectories(&rows, &ids, job.tracker.reset_after_s);
    let windows: usize = trajectories.iter().map(Vec::len).sum();
    if windows < job.config.min_windows.max(1) {
        return Err(RecalibrationError::TooFew {
            found: windows,
            needed: job.config.min_windows.max(1),
        });
    }
    let start = anchors(&job.site, job.orientation, &job.pathloss, None);
    let options = FitOptions {
        iterations: crate::eval::localization::CALIBRATION_ITERATIONS,
        cell_iterations: if job.config.cells { CELL_ITERATIONS } else { 0 },
        cell_prior_readings: DEFAULT_CELL_PRIOR_READINGS,
    };
    let fitted = fit(
        &job.site,
        &ids,
        &start,
        &job.tracker,
        &trajectories,
        &options,
    )?;
    let path = job.config.out_path(&job.store);
    let text = format!(
        "# Written by the gateway's recalibration from {windows} fingerprint windows it heard \
         ({} trajectories) in {}.\n{}",
        trajectories.len(),
        job.store.display(),
        fitted.calibration.to_toml()
    );
    write_atomically(&path, &text).map_err(|source| RecalibrationError::Write {
        path: path.clone(),
        source,
    })?;
    Ok(Recalibrated {
        #[cfg(test)]
        calibration: fitted.calibration,
        path,
        windows,
        trajectories: trajectories.len(),
        changes: fitted.changes,
        cells: fitted.cells,
        seconds: started.elapsed().as_secs_f64(),
    })
}

/// The localizer config that loads a recalibrated file: what the daemon
/// builds anew and swaps in.
pub(crate) fn with_calibration(config: &LocalizerConfig, path: &Path) -> LocalizerConfig {
    let mut config = config.clone();
    config.pathloss.calibration = Some(path.to_owned());
    config
}

/// Stored windows (by device, then time) as trajectories: a device's windows
/// split where the tracker would restart, and into pieces of at most
/// [`MAX_TRAJECTORY`]; readings of anchors the site does not have are left out.
fn trajectories(
    rows: &[crate::store::HeardRow],
    ids: &[String],
    reset_after_s: f64,
) -> Vec<Vec<Window>> {
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

/// Writes `text` to a temporary file beside `path`, then renames it over
/// `path`: a reader sees the old file or the new one, never half of one.
fn write_atomically(path: &Path, text: &str) -> std::io::Result<()> {
    use std::io::Write;
    let mut temporary = path.as_os_str().to_owned();
    temporary.push(format!(".tmp-{}", std::process::id()));
    let temporary = PathBuf::from(temporary);
    let mut file = std::fs::File::create(&temporary)?;
    file.write_all(text.as_bytes())?;
    file.sync_all()?;
    drop(file);
    std::fs::rename(&temporary, path)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::locate::pathloss::Radio;
    use crate::store::Record;
    use rand::{RngExt, SeedableRng};

    fn site() -> Arc<Site> {
        // A corridor of 12 cells with a beacon at each end and one halfway.
        let text = r#"
name = "corridor"
cell_m = 1.0
map = '''
############
'''
[[beacon]]
id = "west"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 1
cell = [0, 0]
[[beacon]]
id = "middle"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 2
cell = [6, 0]
[[beacon]]
id = "east"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 3
cell = [11, 0]
"#;
        Arc::new(Site::parse(text, Path::new("corridor.toml")).unwrap())
    }

    /// Walkers pacing the corridor heard through `radio`, one window per 2 s,
    /// each with the cell column it was heard in.
    fn walks(site: &Site, radio: &Radio, seed: u64) -> Vec<(Fingerprint, u16)> {
        let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(seed);
        let mut out = Vec::new();
        for walker in 0..6 {
            let entity: Arc<str> = format!("phone-{walker}").into();
            let mut x = rng.random_range(0.0..11.0f64);
            let mut dir = 1.0;
            for step in 0..200 {
                x += dir * rng.random_range(0.0..1.5);
                if !(0.0..=11.0).contains(&x) {
                    dir = -dir;
                    x = x.clamp(0.0, 11.0);
                }
                let here = [x + 0.5, -0.5];
                let (mut rssi, mut heard) = (Vec::new(), Vec::new());
                for b in &site.beacons {
                    let d = b.mount.unwrap().distance_m(here);
                    let h = rng.random_bool(radio.detection(d));
                    let noise: f64 = rng.random_range(-4.0..4.0);
                    heard.push(h);
                    rssi.push(if h {
                        (radio.expected_rssi(d) + noise) as f32
                    } else {
                        -105.0
                    });
                }
                let window = Fingerprint {
                    entity: entity.clone(),
                    t: f64::from(step) * 2.0,
                    rssi,
                    heard,
                };
                out.push((window, x.floor() as u16));
            }
        }
        out
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
        assert_eq!(Heard::of(&silent, &ids), None);
        let heard = Fingerprint {
            heard: vec![false, true, false],
            rssi: vec![-105.0, -71.0, -105.0],
            ..silent
        };
        assert_eq!(
            Heard::of(&heard, &ids),
            Some(Heard {
                device: "p".into(),
                t: 4.0,
                readings: vec![("middle".into(), -71.0)]
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

    /// The whole loop on a made-up floor: windows heard through a radio the
    /// configured defaults know nothing of go through the store, and the
    /// recalibration finds that radio, writes a file the localizer loads,
    /// and locates the walkers better with it than with the defaults.
    #[test]
    fn a_recalibration_from_the_store_learns_the_floor_and_writes_a_loadable_file() {
        let site = site();
        let truth = Radio {
            tx_dbm: -74.0,
            exponent: 2.5,
            shadowing_db: 3.0,
            range_m: 3.0,
            range_slope: 3.0,
            max_detection: 0.9,
        };
        let dir = tempfile::tempdir().unwrap();
        let store_path = dir.path().join("learning.sqlite");
        let mut store = Store::open(&store_path).unwrap();
        let ids = anchor_ids(&site, Orientation::Observer);
        let records: Vec<Record> = walks(&site, &truth, 1)
            .iter()
            .filter_map(|(window, _)| Heard::of(window, &ids))
            .map(|h| Record::Heard {
                device: h.device,
                t: h.t,
                readings: h.readings,
            })
            .collect();
        store.write(&records).unwrap();
        drop(store);
        let gathered = records.len();

        let localizer = LocalizerConfig {
            recalibration: RecalibrationConfig {
                enabled: true,
                min_windows: 500,
                ..RecalibrationConfig::default()
            },
            ..LocalizerConfig::default()
        };
        let tracker = TrackerConfig::default();
        let job = Job::new(
            &site,
            Orientation::Observer,
            &localizer,
            &tracker,
            &store_path,
        );
        let done = run(&job).unwrap();
        assert_eq!(done.path, dir.path().join("calibration.toml"));
        assert_eq!(done.windows, gathered, "every stored window is read back");
        for change in &done.changes {
            assert!(
                (change.after.tx_dbm - truth.tx_dbm).abs() < 6.0,
                "{}: tx {:.1} dBm, truly {}",
                change.id,
                change.after.tx_dbm,
                truth.tx_dbm
            );
        }
        assert!(done.cells.as_ref().is_some_and(|c| c.cells > 0));

        // The file loads, and locates fresh walks (no tracker) better than
        // the defaults it started from.
        let loaded = Calibration::load(&done.path, &site).unwrap();
        assert_eq!(loaded.cells.len(), done.calibration.cells.len());
        let windows = crate::locate::window::WindowConfig::default();
        let error = |config: &LocalizerConfig| {
            let mut model = crate::locate::build(config, &site, &windows, &tracker).unwrap();
            let test = walks(&site, &truth, 2);
            let mut ll = vec![0.0; site.open_cells().len()];
            let mut total = 0.0;
            for (w, x) in &test {
                model.log_likelihood(&w.rssi, &w.heard, &mut ll);
                let best = (0..ll.len())
                    .max_by(|&a, &b| ll[a].total_cmp(&ll[b]))
                    .unwrap();
                total += f64::from(site.open_cells()[best].x.abs_diff(*x));
            }
            total / test.len() as f64
        };
        let (before, after) = (
            error(&localizer),
            error(&with_calibration(&localizer, &done.path)),
        );
        assert!(
            after < 0.8 * before,
            "mean error {after:.2} cells recalibrated against {before:.2} with the defaults"
        );
    }

    #[test]
    fn too_few_windows_refuse_to_recalibrate() {
        let site = site();
        let dir = tempfile::tempdir().unwrap();
        let store_path = dir.path().join("learning.sqlite");
        Store::open(&store_path).unwrap();
        let job = Job::new(
            &site,
            Orientation::Observer,
            &LocalizerConfig::default(),
            &TrackerConfig::default(),
            &store_path,
        );
        let e = run(&job).unwrap_err();
        assert!(e.to_string().contains("min_windows"), "{e}");
        assert!(!dir.path().join("calibration.toml").exists());
    }

    #[test]
    fn a_gateway_serves_the_recalibrated_file_only_when_on_and_loadable() {
        let site = site();
        let dir = tempfile::tempdir().unwrap();
        let store = StoreConfig {
            enabled: true,
            path: Some(dir.path().join("learning.sqlite")),
            ..StoreConfig::default()
        };
        let on = LocalizerConfig {
            recalibration: RecalibrationConfig {
                enabled: true,
                ..RecalibrationConfig::default()
            },
            ..LocalizerConfig::default()
        };
        let file = dir.path().join("calibration.toml");
        // No file yet: the configured calibration.
        assert_eq!(serving(&on, &store, &site).pathloss.calibration, None);
        let calibration = Calibration {
            site: "corridor".into(),
            windows: 1,
            iterations: 1,
            anchors: Vec::new(),
            cells: Vec::new(),
        };
        std::fs::write(&file, calibration.to_toml()).unwrap();
        assert_eq!(
            serving(&on, &store, &site).pathloss.calibration.as_deref(),
            Some(file.as_path())
        );
        // Off, or surveyed: the file is not what serves.
        let off = LocalizerConfig::default();
        assert_eq!(serving(&off, &store, &site).pathloss.calibration, None);
        let mut surveyed = on.clone();
        surveyed.method = Method::Knn;
        assert_eq!(serving(&surveyed, &store, &site).pathloss.calibration, None);
        // A broken file: the configured calibration, not a failure.
        std::fs::write(&file, "anchor = 3").unwrap();
        assert_eq!(serving(&on, &store, &site).pathloss.calibration, None);
    }
}
