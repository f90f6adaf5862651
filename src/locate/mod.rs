//! Localization: fingerprint windows → per-cell likelihoods → tracked position.
//!
//! - [`window`] turns sightings into one fingerprint per entity and stride;
//! - a [`Localizer`] scores every walkable cell of the site for a fingerprint
//!   (a log-likelihood per cell, not just an argmax, so the tracker can fuse it
//!   with motion);
//! - [`tracker`] keeps a belief per entity that respects walls and walking speed.

pub(crate) mod auto;
pub(crate) mod bounds;
pub mod calibrate;
pub(crate) mod crossval;
pub mod knn;
pub(crate) mod onnx;
pub mod pathloss;
pub mod radiomap;
pub(crate) mod recalibrate;
pub(crate) mod reliability;
pub(crate) mod strongest;
pub mod survey;
pub mod tracker;
pub mod window;

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
    /// belief within one cell) is `raw`: localizers that have held-out truth
    /// to learn from map it so that it means what it says
    /// ([`reliability::ConfidenceMap`]).
    fn confidence(&self, raw: f32) -> f32 {
        raw
    }
}

impl Default for LocalizerConfig {
    fn default() -> Self {
        LocalizerConfig {
            method: Method::default(),
            min_confidence: default_min_confidence(),
            pathloss: Default::default(),
            knn: Default::default(),
            radiomap: Default::default(),
            onnx: Default::default(),
            recalibration: Default::default(),
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
}

fn default_min_confidence() -> f32 {
    0.15
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
    pub(crate) fn name(self) -> &'static str {
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
        "the survey has readings at {0}, which the site map blocks; open that cell or fix the survey"
    )]
    SurveyOnBlockedCell(crate::site::Cell),
    #[error(transparent)]
    Survey(#[from] survey::SurveyError),
    #[error(transparent)]
    Calibration(#[from] calibrate::CalibrationError),
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
        Method::Pathloss => Box::new(pathloss::PathLoss::new(
            &config.pathloss,
            site,
            windows.orientation,
        )?),
        Method::Knn => Box::new(knn::Knn::load(
            &config.knn,
            site,
            &window::anchor_ids(site, windows.orientation),
            windows.missing_dbm,
        )?),
        Method::Radiomap => Box::new(radiomap::RadioMap::load(
            &config.radiomap,
            site,
            &window::anchor_ids(site, windows.orientation),
            windows.orientation,
            tracker,
        )?),
        Method::Onnx => Box::new(onnx::Onnx::load(&config.onnx.model, site)?),
        Method::Strongest => Box::new(strongest::Strongest::new(
            &config.pathloss,
            site,
            windows.orientation,
        )?),
    })
}
