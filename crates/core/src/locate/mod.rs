//! Localization: fingerprint windows → per-cell likelihoods → tracked position.
//!
//! - [`window`] turns sightings into one fingerprint per entity and stride;
//! - a [`Localizer`] scores every walkable cell of the site for a fingerprint
//!   (a log-likelihood per cell, not just an argmax, so the tracker can fuse it
//!   with motion);
//! - [`tracker`] keeps a belief per entity that respects walls and walking speed.

pub mod auto;
pub mod bounds;
pub mod calibrate;
pub mod calibration;
pub(crate) mod crossval;
pub mod floor_track;
pub mod floors;
pub mod gain;
pub mod knn;
pub mod onnx;
pub mod pathloss;
pub mod radiomap;
pub mod recalibrate;
pub mod rehearsal;
pub(crate) mod reliability;
pub mod strongest;
pub mod survey;
pub mod tracker;
pub mod window;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::Deserialize;

use crate::site::Site;

/// Scores the site's walkable cells for one fingerprint.
pub trait Localizer: Send + Sync {
    /// The method name, as in the config.
    fn method(&self) -> &'static str;

    /// Writes into `out` (one slot per cell of `Site::open_cells`) the
    /// log-likelihood, up to an additive constant, of hearing `rssi` (with the
    /// anchors flagged in `heard`) at each cell.
    fn log_likelihood(&mut self, rssi: &[f32], heard: &[bool], out: &mut [f32]);

    /// The published confidence of a fix whose raw confidence (the tracker's
    /// belief within one cell) is `raw`, its window having heard `heard`
    /// anchors: localizers that have held-out truth to learn from, or that
    /// rehearsed ([`rehearsal`]), map it so that it means what it says
    /// ([`reliability::ConfidenceMap`]).
    fn confidence(&self, raw: f32, heard: usize) -> f32 {
        let _ = heard;
        raw
    }

    /// The radio model behind the scores, where there is one: what a
    /// device's gain is measured against ([`gain`]). A localizer without
    /// one (a vote over fingerprints, a classifier) has none, and its
    /// devices keep their gains.
    fn radio_model(&mut self) -> Option<&mut pathloss::PathLoss> {
        None
    }
}

impl Default for LocalizerConfig {
    fn default() -> Self {
        LocalizerConfig {
            method: Method::default(),
            min_confidence: default_min_confidence(),
            device_gains: default_device_gains(),
            pathloss: Default::default(),
            knn: Default::default(),
            radiomap: Default::default(),
            onnx: Default::default(),
            recalibration: Default::default(),
            recalibrated: Default::default(),
        }
    }
}

/// `[localizer]` in the gateway config.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocalizerConfig {
    #[serde(default)]
    pub method: Method,
    /// A fix whose published confidence (the chance it is within one cell)
    /// is under this is published as an unknown location, not a guessed cell.
    #[serde(default = "default_min_confidence")]
    pub min_confidence: f32,
    /// Learn each device's receiver gain from its own fixes and correct its
    /// windows by it where that explains its readings better ([`gain`]):
    /// for sites whose visitors' phones hear differently from the model.
    #[serde(default = "default_device_gains")]
    pub device_gains: bool,
    /// `[localizer.pathloss]`: the radio model.
    #[serde(default)]
    pub pathloss: pathloss::PathLossConfig,
    /// `[localizer.knn]`: the survey and the vote.
    #[serde(default)]
    pub knn: knn::KnnConfig,
    /// `[localizer.radiomap]`: the survey and, optionally, fixed map settings.
    #[serde(default)]
    pub radiomap: radiomap::RadioMapConfig,
    /// `[localizer.onnx]`: the trained cell classifier.
    #[serde(default)]
    pub onnx: onnx::OnnxConfig,
    /// `[localizer.recalibration]`: refitting the survey-free model from what
    /// the gateway hears.
    #[serde(default)]
    pub recalibration: recalibrate::RecalibrationConfig,
    /// Per floor of a building of several, the file the gateway's own
    /// recalibration wrote for it, which serves that floor instead of
    /// `[localizer.pathloss] calibration` ([`recalibrate::with_calibration`]).
    /// Set by the daemon, never read from the config file: a floor gets one
    /// only once enough of its own windows were heard.
    #[serde(skip)]
    pub recalibrated: std::collections::BTreeMap<String, PathBuf>,
}

fn default_min_confidence() -> f32 {
    0.15
}

/// Off: on the paper's floor, where every phone is the surveyor's, the
/// gate let louder-than-modelled estimates through and guidance got worse
/// (BENCHMARKS.md "Each phone's gain").
fn default_device_gains() -> bool {
    false
}

impl LocalizerConfig {
    /// Checks `[localizer]` and its sections: a message naming the key and
    /// what to do.
    pub fn validate(&self) -> Result<(), String> {
        if !(0.0..=1.0).contains(&self.min_confidence) {
            return Err("[localizer] `min_confidence` must be between 0 and 1".into());
        }
        self.pathloss
            .validate()
            .map_err(|e| format!("[localizer.pathloss] {e}"))?;
        self.knn
            .validate()
            .map_err(|e| format!("[localizer.knn] {e}"))?;
        self.recalibration
            .validate()
            .map_err(|e| format!("[localizer.recalibration] {e}"))
    }

    /// This config for the floor called `floor` of a building of several:
    /// `{floor}` in its survey, model and calibration paths becomes the
    /// floor's name. A file the method reads without `{floor}` in its
    /// path would be one floor's read on every floor: refused.
    pub fn for_floor(&self, floor: &str) -> Result<LocalizerConfig, LocalizerError> {
        let mut config = self.clone();
        let recalibrated = self.recalibrated.get(floor);
        if recalibrated.is_some() {
            config.pathloss.calibration = None;
        }
        let uses_model = config.method == Method::Onnx;
        let files = [
            ("[localizer.knn] survey", config.knn.survey.as_mut(), true),
            (
                "[localizer.radiomap] survey",
                config.radiomap.survey.as_mut(),
                true,
            ),
            (
                "[localizer.pathloss] calibration",
                config.pathloss.calibration.as_mut(),
                true,
            ),
            (
                "[localizer.onnx] model",
                Some(&mut config.onnx.model),
                uses_model,
            ),
        ];
        for (key, path, used) in files {
            let Some(path) = path else { continue };
            if let Some(named_path) = crate::site::floor_path(path, floor) {
                *path = named_path;
            } else if used {
                return Err(LocalizerError::OneFileForAllFloors {
                    key,
                    path: path.clone(),
                });
            }
        }
        if let Some(path) = recalibrated {
            config.pathloss.calibration = Some(path.clone());
        }
        Ok(config)
    }

    /// Makes the survey, model and calibration paths relative to `base` (the
    /// config file's directory).
    pub fn resolve_paths(&mut self, base: &Path) {
        for survey in [&mut self.knn.survey, &mut self.radiomap.survey]
            .into_iter()
            .flatten()
        {
            *survey = base.join(&*survey);
        }
        self.onnx.model = base.join(&self.onnx.model);
        if let Some(calibration) = &mut self.pathloss.calibration {
            *calibration = base.join(&*calibration);
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// The surveyed method that cross-validates best when a survey is
    /// configured, else `pathloss` (with its calibration file, if set).
    #[default]
    Auto,
    /// Log-distance path loss from the anchors' positions; needs no survey.
    Pathloss,
    /// Weighted k-nearest neighbours over a survey.
    Knn,
    /// A radio map interpolated from a survey, its settings cross-validated.
    Radiomap,
    /// The MLP cell classifier trained by `gangway train --survey`.
    Onnx,
    /// The cell nearest the anchor heard loudest: the baseline rule.
    Strongest,
}

impl Method {
    pub fn name(self) -> &'static str {
        match self {
            Method::Auto => "auto",
            Method::Pathloss => "pathloss",
            Method::Knn => "knn",
            Method::Radiomap => "radiomap",
            Method::Onnx => "onnx",
            Method::Strongest => "strongest",
        }
    }
}

/// Why a localizer could not be built.
#[derive(Debug, thiserror::Error)]
pub enum LocalizerError {
    #[error(
        "the pathloss localizer needs anchor positions, and no anchor of the site has a \
         `cell` or `pos`; add `cell = [x, y]` or `pos = [x_m, y_m]` to the site's beacons or \
         gateways"
    )]
    NoAnchorPositions,
    #[error(
        "the knn and radiomap localizers need a survey: set `survey` in [localizer.knn] or \
         [localizer.radiomap]"
    )]
    NoSurvey,
    /// A building of several floors with a file that names one floor's.
    #[error(
        "{key} = \"{}\" names one file for every floor of a building of several; put \
         `{{floor}}` in it where each floor's name goes (`surveys/{{floor}}.csv`)",
        path.display()
    )]
    OneFileForAllFloors {
        key: &'static str,
        path: std::path::PathBuf,
    },
    #[error(
        "[localizer.radiomap] and [localizer.knn] name different surveys ({} and {}); \
         method = \"auto\" chooses between them on one survey: name the same file or one of them",
        radiomap.display(),
        knn.display()
    )]
    TwoSurveys {
        radiomap: std::path::PathBuf,
        knn: std::path::PathBuf,
    },
    #[error("the survey has no rows to learn from")]
    EmptySurvey,
    #[error(
        "only {windows} fingerprint windows to calibrate from: a calibration is checked on \
         windows it was not fitted to, so at least {needed} are needed; record for longer"
    )]
    TooFewToHoldOut { windows: usize, needed: usize },
    #[error(
        "the survey has readings at {0}, which the site map blocks; open that cell or fix the survey"
    )]
    SurveyOnBlockedCell(crate::site::Cell),
    #[error(transparent)]
    Survey(#[from] survey::SurveyError),
    #[error(transparent)]
    Calibration(#[from] calibration::CalibrationError),
    #[error(transparent)]
    Model(#[from] crate::model::ModelError),
}

impl LocalizerError {
    /// Whether a file the localizer reads (its survey or model) failed, as
    /// opposed to the config or the site: only then can another method serve
    /// in its place ([`crate::pipeline::Pipeline::with_fallbacks`]).
    pub(crate) fn is_file_failure(&self) -> bool {
        matches!(
            self,
            LocalizerError::EmptySurvey
                | LocalizerError::SurveyOnBlockedCell(_)
                | LocalizerError::Survey(_)
                | LocalizerError::Calibration(_)
                | LocalizerError::Model(_)
        )
    }
}

/// Builds the configured localizer for a site and the windows that feed it
/// (the radio map cross-validates its settings with `tracker`).
pub fn build(
    config: &LocalizerConfig,
    site: &Arc<Site>,
    windows: &window::WindowConfig,
    tracker: &tracker::TrackerConfig,
) -> Result<Box<dyn Localizer>, LocalizerError> {
    Ok(match config.method {
        Method::Auto => auto::build(config, site, windows, tracker)?,
        Method::Pathloss => rehearsal::path_loss(&config.pathloss, None, site, windows, tracker)?,
        Method::Knn => knn::Knn::load(
            &config.knn,
            site,
            &window::anchor_ids(site, windows.orientation),
            tracker,
            windows.missing_dbm,
        )?,
        Method::Radiomap => Box::new(radiomap::RadioMap::load(
            &config.radiomap,
            site,
            &window::anchor_ids(site, windows.orientation),
            windows.orientation,
            tracker,
        )?),
        Method::Onnx => Box::new(onnx::Onnx::load(&config.onnx.model, site)?),
        Method::Strongest => rehearsal::strongest(&config.pathloss, site, windows, tracker)?,
    })
}
