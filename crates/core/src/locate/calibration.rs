//! A calibration file: per-anchor radio models (and, optionally, a refined
//! radio map per cell) by anchor id, as `gangway calibrate` and the daemon's
//! recalibration write it and the path-loss localizer reads it. Apart from
//! the fitter ([`super::calibrate`]), so that the localizer that applies a
//! calibration and the fitter that makes one each import it, not each other.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::pathloss::Radio;
use crate::site::{Cell, Site};

/// A calibration file: per-anchor radio models by anchor id.
#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Calibration {
    /// The site it was fitted on (informational: positions matter, not names).
    pub site: String,
    /// Windows it was fitted from.
    pub windows: usize,
    pub iterations: usize,
    #[serde(rename = "anchor")]
    pub anchors: Vec<AnchorCalibration>,
    /// Cells whose radio map EM refined (`gangway calibrate --cells`); the
    /// others follow the anchors' models.
    #[serde(rename = "cell", default, skip_serializing_if = "Vec::is_empty")]
    pub cells: Vec<CellCalibration>,
}

/// One cell's refined radio map: per anchor of [`Calibration::anchors`], in
/// that order, the chance it is heard in a window there and its mean RSSI.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CellCalibration {
    /// The cell, `[x, y]` on the site's grid.
    pub at: [u16; 2],
    pub detection: Vec<f64>,
    pub rssi_dbm: Vec<f64>,
}

#[derive(Clone, Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AnchorCalibration {
    pub id: String,
    /// Windows in which the anchor was heard.
    pub heard: usize,
    #[serde(flatten)]
    pub radio: Radio,
}

#[derive(Debug, thiserror::Error)]
pub enum CalibrationError {
    #[error("{path}: cannot read the calibration file: {reason}")]
    Read { path: PathBuf, reason: String },
    #[error("{path}: {reason}")]
    Invalid { path: PathBuf, reason: String },
}

impl Calibration {
    /// Reads and checks a calibration file against the site's anchor ids.
    pub fn load(path: &Path, site: &Site) -> Result<Calibration, CalibrationError> {
        let read = |reason: String| CalibrationError::Read {
            path: path.to_owned(),
            reason,
        };
        let invalid = |reason: String| CalibrationError::Invalid {
            path: path.to_owned(),
            reason,
        };
        let text = std::fs::read_to_string(path).map_err(|e| read(e.to_string()))?;
        let calibration: Calibration = toml::from_str(&text).map_err(|e| invalid(e.to_string()))?;
        for a in &calibration.anchors {
            let known = site.beacons.iter().any(|b| b.id == a.id)
                || site.gateways.iter().any(|g| g.id == a.id);
            if !known {
                return Err(invalid(format!(
                    "anchor `{}` is not a beacon or gateway of site `{}`; recalibrate for this site",
                    a.id, site.name
                )));
            }
            a.radio
                .validate()
                .map_err(|e| invalid(format!("anchor `{}`: {e}", a.id)))?;
        }
        let n = calibration.anchors.len();
        for c in &calibration.cells {
            let cell = Cell::new(c.at[0], c.at[1]);
            let fail = |what: &str| {
                invalid(format!(
                    "cell {cell}: {what}; recalibrate for this site (`gangway calibrate --cells`)"
                ))
            };
            if !site.walkable(cell) {
                return Err(fail("not a walkable cell of the site"));
            }
            if c.detection.len() != n || c.rssi_dbm.len() != n {
                return Err(fail(&format!(
                    "`detection` and `rssi_dbm` need one value per [[anchor]] ({n})"
                )));
            }
            if !c.detection.iter().all(|p| (0.0..=1.0).contains(p))
                || !c.rssi_dbm.iter().all(|r| r.is_finite())
            {
                return Err(fail(
                    "a detection outside 0–1 or an RSSI that is not a number",
                ));
            }
        }
        Ok(calibration)
    }

    /// The radio model of one anchor, if calibrated.
    pub(crate) fn radio(&self, id: &str) -> Option<Radio> {
        self.anchors.iter().find(|a| a.id == id).map(|a| a.radio)
    }

    pub fn to_toml(&self) -> String {
        toml::to_string(self).expect("a calibration serializes")
    }
}
