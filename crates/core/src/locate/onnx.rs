//! The `onnx` localizer: the MLP cell classifier that `gangway train --survey`
//! writes, run with tract. It gives a log-posterior per walkable cell; the
//! tracker takes it as a log-likelihood, which is right up to a constant when
//! the survey visits cells about equally often, as site surveys do.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::{Localizer, LocalizerError};
use crate::model::runtime::CellClassifier;
use crate::site::Site;

/// `[localizer.onnx]` in the gateway config.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct OnnxConfig {
    /// The cell classifier model.
    pub model: PathBuf,
}

impl Default for OnnxConfig {
    fn default() -> Self {
        OnnxConfig {
            model: PathBuf::from("../models/cell_classifier.onnx"),
        }
    }
}

pub struct Onnx {
    model: CellClassifier,
}

impl Onnx {
    /// Loads a cell classifier, refusing one made for another site or anchors.
    pub fn load(path: &Path, site: &Site) -> Result<Onnx, LocalizerError> {
        Ok(Onnx {
            model: CellClassifier::load(path, site)?,
        })
    }
}

impl Localizer for Onnx {
    fn method(&self) -> &'static str {
        "onnx"
    }

    fn log_likelihood(&mut self, rssi: &[f32], _heard: &[bool], out: &mut [f32]) {
        if let Err(e) = self.model.log_probs(rssi, out) {
            // Shapes are checked at load, so this is not expected; a fix with no
            // information is better than a dead gateway.
            tracing::error!("cell classifier: {e}");
            out.fill(0.0);
        }
    }
}
