//! The runtime's half of recalibration (the computing half is the core's
//! `locate::recalibrate`): a [`Job`] reads the newest windows the gateway
//! heard back from the learning store, fits them with
//! [`recalibrate::fit_heard`], writes the calibration file atomically (a
//! temporary file renamed over the old one) and returns it. It blocks for
//! seconds and touches nothing the event loop holds, so it runs on a blocking
//! thread; the daemon then builds its pipeline anew with the file and swaps
//! it in only if that succeeds, as a reload does. Restarts and reloads serve
//! the newest recalibrated file ([`serving`]).
//!
//! On a building of several floors each floor is a job of its own: its
//! windows (those whose floor the tracks knew) are fitted to its site and
//! written to its own file ([`RecalibrationConfig::out_path`]), which serves
//! that floor only. A floor that has not heard enough yet keeps what it
//! served, and the others are recalibrated without it ([`run_floors`]).

use std::path::{Path, PathBuf};
use std::sync::Arc;

use gangway_core::locate::LocalizerConfig;
use gangway_core::locate::calibrate::{CellChange, Change, HeldOut};
use gangway_core::locate::calibration::Calibration;
use gangway_core::locate::pathloss::PathLossConfig;
use gangway_core::locate::recalibrate::{self, FitError, RecalibrationConfig};
use gangway_core::locate::tracker::TrackerConfig;
use gangway_core::locate::window::Orientation;
use gangway_core::publish::stats::{FloorRecalibrated, FloorSkipped, RecalibrationStatus};
use gangway_core::site::{Building, Site};
use gangway_io::store::{Store, StoreConfig, StoreError};

/// What a gateway serves with: with recalibration on, each floor's
/// recalibrated file where one loads; else the config as it is.
pub(crate) struct Serving {
    pub config: LocalizerConfig,
    /// Each recalibrated file present, loaded or not: what `gangway check`
    /// reports, and the daemon logs when one does not load.
    pub files: Vec<RecalibratedFile>,
}

/// A file an earlier recalibration wrote for one floor.
pub(crate) struct RecalibratedFile {
    /// The floor of a building it serves (`None`: the one floor of a site).
    pub floor: Option<String>,
    pub path: PathBuf,
    /// What it holds, or why it does not load (then the configured
    /// calibration serves that floor until the next recalibration).
    pub loaded: Result<Calibration, String>,
}

pub(crate) fn serving(
    config: &LocalizerConfig,
    store: &StoreConfig,
    building: &Building,
) -> Serving {
    let mut serving = Serving {
        config: config.clone(),
        files: Vec::new(),
    };
    if !(config.recalibration.enabled && recalibrate::applies(config)) {
        return serving;
    }
    let store = store.resolved_path();
    for (floor, site) in floors(building) {
        let path = config.recalibration.out_path(&store, floor);
        if !path.exists() {
            continue;
        }
        let loaded = Calibration::load(&path, site).map_err(|e| e.to_string());
        if loaded.is_ok() {
            serving.config = recalibrate::with_calibration(&serving.config, floor, &path);
        }
        serving.files.push(RecalibratedFile {
            floor: floor.map(str::to_owned),
            path,
            loaded,
        });
    }
    serving
}

/// Each floor of `building` with its name, which names its recalibration
/// (`None`: the one floor of a site).
fn floors(building: &Building) -> impl Iterator<Item = (Option<&str>, &Arc<Site>)> {
    let several = building.is_multi_floor();
    building
        .floors()
        .iter()
        .map(move |floor| (several.then_some(floor.name.as_str()), &floor.site))
}

/// Everything a recalibration reads, owned, so the job can run on another
/// thread while the daemon serves.
#[derive(Clone, Debug)]
pub(crate) struct Job {
    pub site: Arc<Site>,
    /// The floor of a building of several that `site` is; its windows only
    /// are read, its file written.
    pub floor: Option<String>,
    pub orientation: Orientation,
    /// The configured model EM starts from (its calibration file unused).
    pub pathloss: PathLossConfig,
    pub tracker: TrackerConfig,
    pub config: RecalibrationConfig,
    /// The learning store the windows are in.
    pub store: PathBuf,
}

impl Job {
    /// The jobs of a gateway config's parts: one per floor of `building`.
    pub(crate) fn of_floors(
        building: &Building,
        orientation: Orientation,
        localizer: &LocalizerConfig,
        tracker: &TrackerConfig,
        store: &Path,
    ) -> Vec<Job> {
        floors(building)
            .map(|(floor, site)| Job::new(site, floor, orientation, localizer, tracker, store))
            .collect()
    }

    /// The job of one floor (`None`: of a one-floor site).
    fn new(
        site: &Arc<Site>,
        floor: Option<&str>,
        orientation: Orientation,
        localizer: &LocalizerConfig,
        tracker: &TrackerConfig,
        store: &Path,
    ) -> Job {
        Job {
            site: site.clone(),
            floor: floor.map(str::to_owned),
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
    /// The floor recalibrated, on a building of several.
    pub floor: Option<String>,
    /// The file written.
    pub path: PathBuf,
    pub windows: usize,
    pub trajectories: usize,
    pub changes: Vec<Change>,
    pub cells: Option<CellChange>,
    /// What the changes were checked on and what they won there.
    pub held_out: Option<HeldOut>,
    pub seconds: f64,
}

#[derive(Debug, thiserror::Error)]
pub(crate) enum RecalibrationError {
    #[error(transparent)]
    Store(#[from] StoreError),
    #[error("{}{source}", on_floor(floor.as_deref()))]
    Fit {
        floor: Option<String>,
        source: FitError,
    },
    #[error("{}: cannot write the calibration: {source}", path.display())]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
}

/// `floor `B1`: ` before what is said of one floor of a building.
fn on_floor(floor: Option<&str>) -> String {
    floor.map_or_else(String::new, |floor| format!("floor `{floor}`: "))
}

/// A run over every floor: those recalibrated, and those that kept what
/// they served, with why.
#[derive(Debug)]
pub(crate) struct Ran {
    pub done: Vec<Recalibrated>,
    pub skipped: Vec<FloorSkipped>,
}

/// Runs each floor's job (blocking; see the module doc). A floor whose
/// windows are too few to fit keeps what it served: said in the log and in
/// [`Ran::skipped`], and the other floors are recalibrated; an error only
/// when no floor was, or a file could not be read or written.
pub(crate) fn run_floors(jobs: &[Job]) -> Result<Ran, RecalibrationError> {
    let mut ran = Ran {
        done: Vec::with_capacity(jobs.len()),
        skipped: Vec::new(),
    };
    let mut unfitted = None;
    for job in jobs {
        match run(job) {
            Ok(floor) => ran.done.push(floor),
            Err(RecalibrationError::Fit {
                floor: Some(floor),
                source,
            }) => {
                tracing::warn!(
                    "floor `{floor}`: {source}; this floor serves what it served, the others \
                     are recalibrated"
                );
                ran.skipped.push(FloorSkipped {
                    why: source.to_string(),
                    floor: floor.clone(),
                });
                unfitted.get_or_insert(RecalibrationError::Fit {
                    floor: Some(floor),
                    source,
                });
            }
            Err(e) => return Err(e),
        }
    }
    match unfitted {
        Some(e) if ran.done.is_empty() => Err(e),
        _ => Ok(ran),
    }
}

/// Counts a finished run in `status` (`ran`, or why it failed; `now`: when
/// it ended), keeping what the last run that served did on each floor.
pub(crate) fn record(status: &mut RecalibrationStatus, ran: Result<&Ran, String>, now: f64) {
    status.last_t = Some(now);
    match ran {
        Ok(ran) => {
            status.runs += 1;
            status.last_error = None;
            status.floors = ran.done.iter().map(Recalibrated::status).collect();
            status.skipped = ran.skipped.clone();
        }
        Err(why) => {
            status.failures += 1;
            status.last_error = Some(why);
        }
    }
}

impl Recalibrated {
    /// What the stats say of it.
    pub(crate) fn status(&self) -> FloorRecalibrated {
        FloorRecalibrated {
            floor: self.floor.clone(),
            windows: self.windows,
            anchors: self.changes.len(),
            anchors_kept: self.changes.iter().filter(|c| c.kept).count(),
            cells_kept: self.cells.as_ref().map_or(0, |c| c.cells),
            held_out_gain_per_window: self.held_out.as_ref().map(|h| h.gain_per_window),
        }
    }
}

/// Runs one floor's recalibration (blocking; see the module doc).
pub(crate) fn run(job: &Job) -> Result<Recalibrated, RecalibrationError> {
    let started = std::time::Instant::now();
    let store = Store::open_read_only(&job.store)?;
    let rows = store.heard(job.config.max_windows, job.floor.as_deref())?;
    drop(store);
    let done = recalibrate::fit_heard(
        &job.site,
        job.orientation,
        &job.pathloss,
        &job.tracker,
        &job.config,
        &rows,
    )
    .map_err(|source| RecalibrationError::Fit {
        floor: job.floor.clone(),
        source,
    })?;
    let path = job.config.out_path(&job.store, job.floor.as_deref());
    let text = format!(
        "# Written by the gateway's recalibration from {} fingerprint windows it heard \
         ({} trajectories){} in {}.\n{}",
        done.windows,
        done.trajectories,
        job.floor
            .as_ref()
            .map_or_else(String::new, |floor| format!(" on floor {floor}")),
        job.store.display(),
        done.fitted.calibration.to_toml()
    );
    write_atomically(&path, &text).map_err(|source| RecalibrationError::Write {
        path: path.clone(),
        source,
    })?;
    Ok(Recalibrated {
        #[cfg(test)]
        calibration: done.fitted.calibration,
        floor: job.floor.clone(),
        path,
        windows: done.windows,
        trajectories: done.trajectories,
        changes: done.fitted.changes,
        cells: done.fitted.cells,
        held_out: done.fitted.held_out,
        seconds: started.elapsed().as_secs_f64(),
    })
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
    use gangway_core::locate::Method;
    use gangway_core::locate::pathloss::Radio;
    use gangway_core::locate::recalibrate::{Heard, with_calibration};
    use gangway_core::locate::window::{Fingerprint, anchor_ids};
    use gangway_io::store::Record;
    use rand::{RngExt, SeedableRng};

    /// A corridor of 12 cells with a beacon at each end and one halfway.
    fn site() -> Arc<Site> {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/fixtures/sites/corridor.toml");
        Arc::new(Site::load(Path::new(path)).unwrap())
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

    /// [`walks`] as the learning store keeps them, heard on `floor`.
    fn heard(site: &Site, radio: &Radio, seed: u64, floor: Option<&str>) -> Vec<Record> {
        let ids = anchor_ids(site, Orientation::Observer);
        walks(site, radio, seed)
            .iter()
            .filter_map(|(w, _)| Heard::of(&w.entity, w.t, &w.rssi, &w.heard, &ids))
            .map(|h| Record::Heard {
                device: h.device,
                t: h.t,
                floor: floor.map(str::to_owned),
                readings: h.readings,
            })
            .collect()
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
        let records = heard(&site, &truth, 1, None);
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
            None,
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
        // Every anchor's change is kept: the held-out windows say so.
        assert!(done.changes.iter().all(|c| c.kept), "{:?}", done.changes);
        assert!(
            done.held_out
                .as_ref()
                .is_some_and(|h| h.gain_per_window > 0.0)
        );
        // Cells are refined by default; the radio here is the same in every
        // cell, so the held-out windows may keep few or none of them.
        assert!(
            done.cells
                .as_ref()
                .is_some_and(|c| c.refined > 0 && c.cells <= c.refined)
        );

        // The file loads, and locates fresh walks (no tracker) better than
        // the defaults it started from.
        let loaded = Calibration::load(&done.path, &site).unwrap();
        assert_eq!(loaded.cells.len(), done.calibration.cells.len());
        let windows = gangway_core::locate::window::WindowConfig::default();
        let error = |config: &LocalizerConfig| {
            let mut model = gangway_core::locate::build(config, &site, &windows, &tracker).unwrap();
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
            error(&with_calibration(&localizer, None, &done.path)),
        );
        assert!(
            after < 0.8 * before,
            "mean error {after:.2} cells recalibrated against {before:.2} with the defaults"
        );
    }

    /// Two floors of a building (the corridor twice), walked on `A` only:
    /// `A` is recalibrated, `B` kept as it was and said so, and the stats
    /// count the run; with nothing heard anywhere the run fails, and the
    /// stats keep what the last run that served did.
    #[test]
    fn a_floor_that_heard_too_little_is_skipped_and_the_stats_say_so() {
        let site = site();
        let dir = tempfile::tempdir().unwrap();
        let store_path = dir.path().join("learning.sqlite");
        Store::open(&store_path).unwrap();
        let localizer = LocalizerConfig {
            recalibration: RecalibrationConfig {
                enabled: true,
                min_windows: 500,
                cells: false,
                ..RecalibrationConfig::default()
            },
            ..LocalizerConfig::default()
        };
        let jobs: Vec<Job> = ["A", "B"]
            .iter()
            .map(|floor| {
                Job::new(
                    &site,
                    Some(floor),
                    Orientation::Observer,
                    &localizer,
                    &TrackerConfig::default(),
                    &store_path,
                )
            })
            .collect();
        let mut status = RecalibrationStatus::default();
        let e = run_floors(&jobs).unwrap_err();
        assert!(e.to_string().starts_with("floor `A`: only 0"), "{e}");
        record(&mut status, Err(e.to_string()), 1.0);
        assert_eq!((status.runs, status.failures), (0, 1));

        let truth = Radio {
            tx_dbm: -70.0,
            exponent: 2.2,
            shadowing_db: 3.0,
            range_m: 4.0,
            range_slope: 3.0,
            max_detection: 0.9,
        };
        let records = heard(&site, &truth, 3, Some("A"));
        Store::open(&store_path).unwrap().write(&records).unwrap();
        let ran = run_floors(&jobs).unwrap();
        let done: Vec<Option<&str>> = ran.done.iter().map(|d| d.floor.as_deref()).collect();
        assert_eq!(done, [Some("A")]);
        assert_eq!(ran.done[0].path, dir.path().join("calibration-A.toml"));
        assert!(!dir.path().join("calibration-B.toml").exists());
        assert_eq!(ran.skipped.len(), 1);
        assert_eq!(ran.skipped[0].floor, "B");
        assert!(
            ran.skipped[0].why.contains("min_windows"),
            "{:?}",
            ran.skipped
        );
        record(&mut status, Ok(&ran), 2.0);
        assert_eq!((status.runs, status.failures), (1, 1));
        assert_eq!(status.last_error, None);
        assert_eq!(status.floors[0].floor.as_deref(), Some("A"));
        assert_eq!(status.floors[0].anchors, 3);
        record(&mut status, Err("the store is gone".into()), 3.0);
        assert_eq!((status.runs, status.failures), (1, 2));
        assert_eq!(status.last_error.as_deref(), Some("the store is gone"));
        assert_eq!(status.floors.len(), 1, "what serves is still A's file");
        assert_eq!(status.last_t, Some(3.0));
    }

    #[test]
    fn too_few_windows_refuse_to_recalibrate() {
        let site = site();
        let dir = tempfile::tempdir().unwrap();
        let store_path = dir.path().join("learning.sqlite");
        Store::open(&store_path).unwrap();
        let job = Job::new(
            &site,
            None,
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
        let site = Building::of_site(site());
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
        assert_eq!(
            serving(&on, &store, &site).config.pathloss.calibration,
            None
        );
        let calibration = Calibration {
            site: "corridor".into(),
            windows: 1,
            iterations: 1,
            anchors: Vec::new(),
            cells: Vec::new(),
        };
        std::fs::write(&file, calibration.to_toml()).unwrap();
        assert_eq!(
            serving(&on, &store, &site)
                .config
                .pathloss
                .calibration
                .as_deref(),
            Some(file.as_path())
        );
        // Off, or surveyed: the file is not what serves.
        let off = LocalizerConfig::default();
        assert_eq!(
            serving(&off, &store, &site).config.pathloss.calibration,
            None
        );
        let mut surveyed = on.clone();
        surveyed.method = Method::Knn;
        assert_eq!(
            serving(&surveyed, &store, &site)
                .config
                .pathloss
                .calibration,
            None
        );
        // A broken file: the configured calibration, not a failure, and
        // the file reported with why.
        std::fs::write(&file, "anchor = 3").unwrap();
        let broken = serving(&on, &store, &site);
        assert_eq!(broken.config.pathloss.calibration, None);
        let [reported] = &broken.files[..] else {
            panic!("one file, reported")
        };
        assert_eq!(reported.path, file);
        let why = reported.loaded.as_ref().unwrap_err();
        assert!(why.contains("calibration.toml"), "{why}");
    }
}
