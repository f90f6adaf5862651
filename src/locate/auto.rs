//! The default method (`method = "auto"`): the best localizer the config's
//! files allow, so a new site gets the surveyed method the day it has a
//! survey and the survey-free one (calibrated when a calibration file is set)
//! until then.
//!
//! With a survey, which surveyed method is best depends on the building (the
//! k-NN vote wins on a floor surveyed cell by cell, the interpolated radio map
//! where test points fall between survey points), so both are
//! cross-validated over the survey's own walking sessions and the one with
//! the lower held-out error serves; the k-NN vote then also gets a confidence
//! map fitted on its held-out fixes, as the radio map has.

use std::sync::Arc;

use super::crossval::choose;
use super::knn::Knn;
use super::radiomap::RadioMap;
use super::reliability::ConfidenceMap;
use super::survey::{Sample, Survey};
use super::tracker::TrackerConfig;
use super::window::{self, WindowConfig};
use super::{Localizer, LocalizerConfig, LocalizerError, pathloss};
use crate::site::Site;

/// Builds the best available localizer for the config.
pub(super) fn build(
    config: &LocalizerConfig,
    site: &Arc<Site>,
    windows: &WindowConfig,
    tracker: &TrackerConfig,
) -> Result<Box<dyn Localizer>, LocalizerError> {
    let ids = window::anchor_ids(site, windows.orientation);
    let (survey, not_heard) = match (&config.radiomap.survey, &config.knn.survey) {
        (Some(map), Some(knn)) if map != knn => {
            return Err(LocalizerError::TwoSurveys {
                radiomap: map.clone(),
                knn: knn.clone(),
            });
        }
        (Some(path), _) => (path, config.radiomap.not_heard),
        (None, Some(path)) => (path, config.knn.not_heard),
        (None, None) => {
            return Ok(Box::new(pathloss::PathLoss::new(
                &config.pathloss,
                site,
                windows.orientation,
            )?));
        }
    };
    let survey = Survey::load(survey, site, &ids, not_heard)?;
    let samples: Vec<&Sample> = survey.samples.iter().collect();
    surveyed(config, site, &ids, windows, tracker, &samples)
}

/// The surveyed localizer for `samples`: the k-NN vote and the radio map
/// blended, the share of each chosen by cross-validation.
pub(crate) fn surveyed(
    config: &LocalizerConfig,
    site: &Arc<Site>,
    ids: &[String],
    windows: &WindowConfig,
    tracker: &TrackerConfig,
    samples: &[&Sample],
) -> Result<Box<dyn Localizer>, LocalizerError> {
    let map = RadioMap::new(
        &config.radiomap,
        site,
        ids,
        windows.orientation,
        tracker,
        samples,
    )?;
    // The map's settings are fixed from here on, so the folds below do not
    // cross-validate them again.
    let settings = map.settings();
    let blend = |knn_share: f64, rows: &[&Sample]| -> Result<Blend, LocalizerError> {
        Ok(Blend::new(
            Knn::new(&config.knn, site, rows, windows.missing_dbm)?,
            RadioMap::with_settings(site, ids, windows.orientation, tracker, rows, settings)?,
            knn_share,
        ))
    };
    let chosen = choose(
        &KNN_SHARES,
        site,
        tracker,
        samples,
        windows.missing_dbm,
        |&share, rows| blend(share, rows),
    )?;
    tracing::info!(
        knn_share = chosen.candidate,
        cv_error_cells = chosen.error_cells,
        "surveyed localizer: k-NN vote and radio map blended as cross-validation chose"
    );
    // `map` is already the map of every row with those settings.
    let mut best = Blend::new(
        Knn::new(&config.knn, site, samples, windows.missing_dbm)?,
        map,
        chosen.candidate,
    );
    best.confidence = chosen.confidence;
    Ok(Box::new(best))
}

/// Shares of the k-NN vote tried in the blend.
const KNN_SHARES: [f64; 5] = [0.0, 0.25, 0.5, 0.75, 1.0];

/// A mixture of the k-NN vote's and the radio map's per-window posteriors.
struct Blend {
    knn: Knn,
    map: RadioMap,
    knn_share: f32,
    confidence: ConfidenceMap,
    knn_ll: Vec<f32>,
}

impl Blend {
    fn new(knn: Knn, map: RadioMap, knn_share: f64) -> Blend {
        Blend {
            knn,
            map,
            knn_share: knn_share as f32,
            confidence: ConfidenceMap::default(),
            knn_ll: Vec::new(),
        }
    }
}

/// Turns log-likelihoods into a posterior under a flat prior, in place.
fn normalise(ll: &mut [f32]) {
    let max = ll.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let mut sum = 0.0;
    for v in ll.iter_mut() {
        *v = (*v - max).exp();
        sum += *v;
    }
    ll.iter_mut().for_each(|v| *v /= sum);
}

impl Localizer for Blend {
    fn method(&self) -> &'static str {
        "surveyed"
    }

    fn log_likelihood(&mut self, rssi: &[f32], heard: &[bool], out: &mut [f32]) {
        let w = self.knn_share;
        if w >= 1.0 {
            return self.knn.log_likelihood(rssi, heard, out);
        }
        if w <= 0.0 {
            return self.map.log_likelihood(rssi, heard, out);
        }
        self.knn_ll.resize(out.len(), 0.0);
        self.knn.log_likelihood(rssi, heard, &mut self.knn_ll);
        self.map.log_likelihood(rssi, heard, out);
        normalise(&mut self.knn_ll);
        normalise(out);
        for (o, k) in out.iter_mut().zip(&self.knn_ll) {
            *o = (w * k + (1.0 - w) * *o).ln();
        }
    }

    fn confidence(&self, raw: f32) -> f32 {
        self.confidence.apply(raw)
    }
}
