//! Localization: fingerprint windows → per-cell likelihoods → tracked position.
//!
//! - [`window`] turns sightings into one fingerprint per entity and stride;
//! - a [`Localizer`] scores every walkable cell of the site for a fingerprint
//!   (a log-likelihood per cell, not just an argmax, so the tracker can fuse it
//!   with motion);
//! - [`tracker`] keeps a belief per entity that respects walls and walking speed.

pub mod pathloss;
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
    fn log_likelihood(&self, rssi: &[f32], heard: &[bool], out: &mut [f32]);
}

/// `[localizer]` in the gateway config.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LocalizerConfig {
    #[serde(default)]
    pub method: Method,
    /// `[localizer.pathloss]`: the radio model.
    #[serde(default)]
    pub pathloss: pathloss::PathLossConfig,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Method {
    /// Log-distance path loss from the anchors' positions; needs no survey.
    #[default]
    Pathloss,
}

/// Why a localizer could not be built.
#[derive(Debug, thiserror::Error)]
pub enum LocalizerError {
    #[error(
        "the pathloss localizer needs anchor positions, and no anchor of the site has a \
         `cell`; add `cell = [x, y]` to the site's beacons or gateways"
    )]
    NoAnchorPositions,
}

/// Builds the configured localizer for a site and window orientation.
pub fn build(
    config: &LocalizerConfig,
    site: &Arc<Site>,
    orientation: window::Orientation,
) -> Result<Box<dyn Localizer>, LocalizerError> {
    match config.method {
        Method::Pathloss => Ok(Box::new(pathloss::PathLoss::new(
            &config.pathloss,
            site,
            orientation,
        )?)),
    }
}
