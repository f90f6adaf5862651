//! One floor's stages of the pipeline: its localizer, its tracker and its
//! guidance sessions, and which of the building's anchors are its own. A
//! one-floor site is a building of one floor, so every fix runs through
//! here; [`super::Pipeline`] picks each device's floor and hands the floor
//! its part of the device's fingerprint.

use std::sync::Arc;

use crate::guide::{Guide, Located};
use crate::locate::gain::Gains;
use crate::locate::recalibrate::Heard;
use crate::locate::tracker::{Fix, Tracker};
use crate::locate::window::Fingerprint;
use crate::locate::{self, Localizer};
use crate::site::{Cell, Site};

use super::{PipelineConfig, PipelineError};

pub(super) struct FloorStages {
    pub(super) site: Arc<Site>,
    localizer: Box<dyn Localizer>,
    pub(super) tracker: Tracker,
    pub(super) guide: Guide,
    /// For each anchor of this floor, in its site's order: the index of the
    /// same anchor in the building's fingerprints.
    anchors: Vec<usize>,
    /// Each device's gain over this floor's radio model (devices' windows
    /// are corrected by it), when `[localizer] device_gains` is on.
    gains: Option<Gains>,
    /// The floor's part of one fingerprint, rebuilt per fix.
    rssi: Vec<f32>,
    heard: Vec<bool>,
    log_likelihood: Vec<f32>,
}

/// One floor's answer for one fingerprint.
pub(super) struct FloorFix {
    pub(super) fix: Fix,
    /// The belief of a walker walking the guided route, when there is one.
    pub(super) walked_mean: Option<[f32; 2]>,
    /// The localizer's published confidence of `fix` (before the floor's),
    /// from this floor's anchors heard in the window.
    pub(super) confidence: f32,
}

impl FloorStages {
    /// The stages of `site`, whose anchors are `anchors` of the building's;
    /// with `fall_back`, a localizer whose files fail is replaced by the
    /// survey-free one, and the replacement said in `fallbacks`.
    pub(super) fn build(
        config: &PipelineConfig,
        localizer_config: &locate::LocalizerConfig,
        site: Arc<Site>,
        anchors: Vec<usize>,
        fall_back: bool,
        fallbacks: &mut Vec<String>,
    ) -> Result<FloorStages, PipelineError> {
        let build = |localizer: &locate::LocalizerConfig| {
            locate::build(localizer, &site, &config.window, &config.tracker)
        };
        let localizer = match build(localizer_config) {
            Err(e) if fall_back && e.is_file_failure() => {
                let failed = format!(
                    "[localizer] method = \"{}\": {e}",
                    localizer_config.method.name()
                );
                // The survey-free model stands in; without its calibration
                // file when that is what failed.
                let mut pathloss = locate::LocalizerConfig {
                    method: locate::Method::Pathloss,
                    ..localizer_config.clone()
                };
                if matches!(e, locate::LocalizerError::Calibration(_)) {
                    pathloss.pathloss.calibration = None;
                }
                let localizer = build(&pathloss).map_err(|error| PipelineError::NoStandIn {
                    failed: failed.clone(),
                    error,
                })?;
                fallbacks.push(format!("{failed} (locating with pathloss instead)"));
                localizer
            }
            built => built?,
        };
        let limits = &config.limits;
        Ok(FloorStages {
            localizer,
            tracker: Tracker::new(config.tracker.clone(), site.clone())
                .bound(limits.max_devices, limits.device_idle_s),
            guide: Guide::new(
                config.guidance.clone(),
                config.guidance.fix_lag_s(&config.window),
            ),
            gains: localizer_config
                .device_gains
                .then(|| Gains::bounded(limits.max_devices, limits.device_idle_s)),
            rssi: vec![0.0; anchors.len()],
            heard: vec![false; anchors.len()],
            anchors,
            log_likelihood: vec![0.0; site.open_cells().len()],
            site,
        })
    }

    /// Locates the device of `fp` (a fingerprint over the building's
    /// anchors) on this floor; `entered` holds the cells it came onto the
    /// floor at (a connector's stops) when it just did.
    pub(super) fn locate(&mut self, fp: &Fingerprint, entered: Option<&[Cell]>) -> FloorFix {
        for (i, &anchor) in self.anchors.iter().enumerate() {
            self.rssi[i] = fp.rssi[anchor];
            self.heard[i] = fp.heard[anchor];
        }
        let heard = self.heard.iter().filter(|&&h| h).count();
        match &mut self.gains {
            Some(gains) => gains.log_likelihood(
                self.localizer.as_mut(),
                &fp.entity,
                &self.rssi,
                &self.heard,
                &mut self.log_likelihood,
            ),
            None => {
                self.localizer
                    .log_likelihood(&self.rssi, &self.heard, &mut self.log_likelihood)
            }
        }
        let (fix, walked_mean) = match entered {
            Some(cells) => (
                self.tracker
                    .enter(&fp.entity, fp.t, cells, &self.log_likelihood),
                None,
            ),
            None => {
                let walk = self.guide.expected_walk(&self.site, &fp.entity, fp.t);
                self.tracker
                    .update_walking(&fp.entity, fp.t, &self.log_likelihood, walk.as_ref())
            }
        };
        if let (Some(gains), Some(cell)) = (&mut self.gains, self.site.open_index(fix.cell)) {
            gains.learn(
                self.localizer.as_mut(),
                &fp.entity,
                fp.t,
                &self.rssi,
                &self.heard,
                cell,
            );
        }
        FloorFix {
            confidence: self.localizer.confidence(fix.confidence, heard),
            fix,
            walked_mean,
        }
    }

    /// The fingerprint [`FloorStages::locate`] last read, as this floor's
    /// anchors heard it (`ids`: theirs, in the site's order), kept for
    /// recalibrating this floor's radio model.
    pub(super) fn heard(&self, device: &str, t: f64, ids: &[String]) -> Option<Heard> {
        Heard::of(device, t, &self.rssi, &self.heard, ids)
    }

    /// Where the guide sees a device at a fix: `cell` when it is known,
    /// moved to the walking belief's mean when there is one.
    pub(super) fn located(
        &self,
        cell: Option<Cell>,
        fix: &Fix,
        walked: Option<[f32; 2]>,
    ) -> Option<Located> {
        let mean = walked.unwrap_or(fix.mean);
        cell.map(|cell| Located::with_mean(&self.site, cell, mean.map(f64::from)))
    }
}
