//! The surveyed localizer: a radio map interpolated from a survey, read with
//! the same likelihood as the survey-free model.
//!
//! For every open cell and anchor the map holds the chance the anchor is heard
//! there and its mean RSSI when heard: the survey's readings near the cell,
//! weighted by a Gaussian kernel of `bandwidth_m`, shrunk towards the
//! survey-free model fitted to the same survey (half a reading's weight), so
//! that a cell between survey points gets the readings around it and a cell far
//! from any gets physics. Silence is evidence here too (a beacon heard in 95% of
//! a cell's readings and not now says "probably not this cell"), which is what
//! a nearest-neighbour vote over dB distances cannot say.
//!
//! The kernel width and the RSSI spread are not constants for one floor: unless
//! the config fixes them, they are chosen at load by cross-validation over the
//! survey's walking sessions (each session localized with the tracker by a map
//! built from the others), and the same held-out fixes fit the map from raw to
//! published confidence ([`super::reliability::ConfidenceMap`]).

use std::path::PathBuf;
use std::sync::Arc;

use serde::Deserialize;

use super::calibrate::{FitOptions, Window, fit};
use super::crossval::{Folds, choose};
use super::pathloss::{Anchor, DETECTION_BOUNDS, PathLoss, PathLossConfig, anchors};
use super::reliability::ConfidenceMap;
use super::survey::{Sample, Survey};
use super::tracker::TrackerConfig;
use super::window::Orientation;
use super::{Localizer, LocalizerError};
use crate::site::Site;

/// `[localizer.radiomap]` in the gateway config.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RadioMapConfig {
    /// The survey CSV (see `locate::survey` for the layouts read).
    pub survey: Option<PathBuf>,
    /// The survey's "not heard" value.
    pub not_heard: i16,
    /// Kernel width in metres; chosen by cross-validation when absent.
    pub bandwidth_m: Option<f64>,
    /// RSSI spread in dB; chosen by cross-validation when absent.
    pub shadowing_db: Option<f64>,
}

impl Default for RadioMapConfig {
    fn default() -> Self {
        RadioMapConfig {
            survey: None,
            not_heard: -200,
            bandwidth_m: None,
            shadowing_db: None,
        }
    }
}

/// Weight of the survey-free model in a cell's estimate, in readings.
const PRIOR_READINGS: f64 = 0.5;
/// Kernel widths tried, in cells.
const BANDWIDTHS_CELLS: [f64; 4] = [0.3, 0.5, 1.0, 2.0];
/// RSSI spreads tried, dB.
const SPREADS_DB: [f64; 4] = [3.0, 4.0, 6.0, 8.0];

/// The interpolated radio map as a localizer.
pub struct RadioMap {
    tables: PathLoss,
    confidence: ConfidenceMap,
    /// The kernel width (m) and RSSI spread (dB) it was built with.
    settings: (f64, f64),
}

/// Per survey cell: where its readings were taken, readings, hits and RSSI
/// sums per anchor.
struct CellReadings {
    /// The mean true position of the readings (world metres): the cell's
    /// centre for surveys by cell, where the walker stood for metric ones.
    at: [f64; 2],
    /// Sum of the readings' offsets from the cell's centre, metres.
    offset_sum: [f64; 2],
    readings: f64,
    hits: Vec<f64>,
    rssi_sum: Vec<f64>,
}

impl RadioMap {
    /// Loads the configured survey and builds from all of it.
    pub(crate) fn load(
        config: &RadioMapConfig,
        site: &Arc<Site>,
        ids: &[String],
        orientation: Orientation,
        tracker: &TrackerConfig,
    ) -> Result<Self, LocalizerError> {
        let path = config.survey.as_ref().ok_or(LocalizerError::NoSurvey)?;
        let survey = Survey::load(path, site, ids, config.not_heard)?;
        let samples: Vec<&Sample> = survey.samples.iter().collect();
        Self::new(config, site, ids, orientation, tracker, &samples)
    }

    /// Builds from survey rows (any subset, e.g. a training split),
    /// cross-validating what the config leaves open.
    pub fn new(
        config: &RadioMapConfig,
        site: &Arc<Site>,
        ids: &[String],
        orientation: Orientation,
        tracker: &TrackerConfig,
        samples: &[&Sample],
    ) -> Result<Self, LocalizerError> {
        let prior = prior(site, ids, orientation, tracker, samples)?;
        let bandwidths: Vec<f64> = match config.bandwidth_m {
            Some(b) => vec![b],
            None => BANDWIDTHS_CELLS.iter().map(|b| b * site.cell_m).collect(),
        };
        let spreads: Vec<f64> = match config.shadowing_db {
            Some(s) => vec![s],
            None => SPREADS_DB.to_vec(),
        };
        let candidates: Vec<(f64, f64)> = bandwidths
            .iter()
            .flat_map(|&b| spreads.iter().map(move |&s| (b, s)))
            .collect();
        // The map reads only what was heard: the "not heard" value is moot.
        let chosen = choose(
            &candidates,
            Folds::Sessions(3),
            site,
            tracker,
            samples,
            f32::NAN,
            |&(b, s), rows| build(site, &prior, rows, b, s),
        )?;
        let (bandwidth_m, shadowing_db) = chosen.candidate;
        tracing::info!(
            bandwidth_m,
            shadowing_db,
            cv_error_cells = chosen.error_cells,
            "radio map: kernel width and RSSI spread chosen by cross-validation over the survey"
        );
        Ok(RadioMap {
            tables: build(site, &prior, samples, bandwidth_m, shadowing_db)?,
            confidence: chosen.confidence,
            settings: chosen.candidate,
        })
    }

    /// The map of `samples` with its settings given, neither cross-validated
    /// nor with a fitted confidence: for callers that cross-validate it
    /// themselves (the blend of [`super::auto`]).
    pub(crate) fn with_settings(
        site: &Arc<Site>,
        ids: &[String],
        orientation: Orientation,
        tracker: &TrackerConfig,
        samples: &[&Sample],
        (bandwidth_m, shadowing_db): (f64, f64),
    ) -> Result<Self, LocalizerError> {
        let prior = prior(site, ids, orientation, tracker, samples)?;
        Ok(RadioMap {
            tables: build(site, &prior, samples, bandwidth_m, shadowing_db)?,
            confidence: ConfidenceMap::default(),
            settings: (bandwidth_m, shadowing_db),
        })
    }

    /// The kernel width (m) and RSSI spread (dB) it was built with.
    pub(crate) fn settings(&self) -> (f64, f64) {
        self.settings
    }
}

/// Checks the rows and fits the map's survey-free prior to them.
fn prior(
    site: &Arc<Site>,
    ids: &[String],
    orientation: Orientation,
    tracker: &TrackerConfig,
    samples: &[&Sample],
) -> Result<Vec<Anchor>, LocalizerError> {
    if samples.is_empty() {
        return Err(LocalizerError::EmptySurvey);
    }
    if let Some(s) = samples.iter().find(|s| site.open_index(s.cell).is_none()) {
        return Err(LocalizerError::SurveyOnBlockedCell(s.cell));
    }
    survey_free(site, ids, orientation, tracker, samples)
}

impl Localizer for RadioMap {
    fn method(&self) -> &'static str {
        "radiomap"
    }

    fn log_likelihood(&mut self, rssi: &[f32], heard: &[bool], out: &mut [f32]) {
        self.tables.log_likelihood(rssi, heard, out);
    }

    fn confidence(&self, raw: f32, heard: usize) -> f32 {
        self.confidence.apply(raw, heard)
    }

    fn radio_model(&mut self) -> Option<&mut PathLoss> {
        Some(&mut self.tables)
    }
}

/// The survey-free model fitted to the survey with its positions known: the
/// map's prior far from survey points.
fn survey_free(
    site: &Arc<Site>,
    ids: &[String],
    orientation: Orientation,
    tracker: &TrackerConfig,
    samples: &[&Sample],
) -> Result<Vec<Anchor>, LocalizerError> {
    let start = anchors(site, orientation, &PathLossConfig::default(), None);
    let known: Vec<Vec<Window>> = vec![
        samples
            .iter()
            .enumerate()
            .map(|(i, s)| Window {
                // Far apart, so the tracker treats each as its own track.
                t: i as f64 * 1e6,
                rssi: s.rssi.iter().map(|r| r.map(f32::from)).collect(),
                cell: Some(s.cell),
            })
            .collect(),
    ];
    let fitted = fit(site, ids, &start, tracker, &known, &FitOptions::anchors(2))?;
    Ok(anchors(
        site,
        orientation,
        &PathLossConfig::default(),
        Some(&fitted.calibration),
    ))
}

/// The radio map of `samples` as likelihood tables.
fn build(
    site: &Site,
    prior: &[Anchor],
    samples: &[&Sample],
    bandwidth_m: f64,
    spread_db: f64,
) -> Result<PathLoss, LocalizerError> {
    let n_anchors = prior.len();
    let mut by_cell: Vec<Option<CellReadings>> = Vec::new();
    by_cell.resize_with(site.open_cells().len(), || None);
    for s in samples {
        let i = site
            .open_index(s.cell)
            .ok_or(LocalizerError::SurveyOnBlockedCell(s.cell))?;
        let centre = site.world_of_cell(s.cell);
        let cell = by_cell[i].get_or_insert_with(|| CellReadings {
            at: centre,
            offset_sum: [0.0; 2],
            readings: 0.0,
            hits: vec![0.0; n_anchors],
            rssi_sum: vec![0.0; n_anchors],
        });
        cell.readings += 1.0;
        cell.offset_sum[0] += s.at[0] - centre[0];
        cell.offset_sum[1] += s.at[1] - centre[1];
        for (a, r) in s.rssi.iter().enumerate() {
            if let Some(r) = r {
                cell.hits[a] += 1.0;
                cell.rssi_sum[a] += f64::from(*r);
            }
        }
    }
    // Offsets from the centre, not positions, are summed, so that readings
    // taken at the centre (surveys by cell) sit exactly there.
    for cell in by_cell.iter_mut().flatten() {
        for k in 0..2 {
            cell.at[k] += cell.offset_sum[k] / cell.readings;
        }
    }
    let surveyed: Vec<&CellReadings> = by_cell.iter().flatten().collect();
    // Past three kernel widths a reading weighs under 1.2% of a near one.
    let reach = 3.0 * bandwidth_m;
    let n = site.open_cells().len() * n_anchors;
    let (mut expected, mut log_hit, mut log_miss) = (
        Vec::with_capacity(n),
        Vec::with_capacity(n),
        Vec::with_capacity(n),
    );
    let mut hits = vec![0.0f64; n_anchors];
    let mut sums = vec![0.0f64; n_anchors];
    for &cell in site.open_cells() {
        let here = site.world_of_cell(cell);
        hits.fill(0.0);
        sums.fill(0.0);
        let mut readings = 0.0;
        for s in &surveyed {
            let d = (here[0] - s.at[0]).hypot(here[1] - s.at[1]);
            if d > reach {
                continue;
            }
            let w = (-0.5 * (d / bandwidth_m).powi(2)).exp();
            readings += w * s.readings;
            for a in 0..n_anchors {
                hits[a] += w * s.hits[a];
                sums[a] += w * s.rssi_sum[a];
            }
        }
        for (a, anchor) in prior.iter().enumerate() {
            let Some((mount, radio)) = anchor else {
                expected.push(f32::NAN);
                log_hit.push(0.0);
                log_miss.push(0.0);
                continue;
            };
            let d = mount.distance_m(here);
            let p = (hits[a] + PRIOR_READINGS * radio.detection(d)) / (readings + PRIOR_READINGS);
            let p = p.clamp(DETECTION_BOUNDS.0, DETECTION_BOUNDS.1);
            let mu =
                (sums[a] + PRIOR_READINGS * radio.expected_rssi(d)) / (hits[a] + PRIOR_READINGS);
            expected.push(mu as f32);
            log_hit.push(p.ln() as f32);
            log_miss.push((1.0 - p).ln() as f32);
        }
    }
    let inv_sigma = prior
        .iter()
        .map(|a| {
            if a.is_some() {
                (1.0 / spread_db) as f32
            } else {
                0.0
            }
        })
        .collect();
    Ok(PathLoss::from_tables(
        site.open_cells().len(),
        expected,
        log_hit,
        log_miss,
        inv_sigma,
    ))
}
