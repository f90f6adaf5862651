//! The survey-free localizer: a radio model per anchor, used both to localize
//! without a survey and to simulate what a walker hears.
//!
//! Real BLE is mostly silence: a phone scanning for a few seconds hears one to
//! three beacons of a dozen, and which ones it hears says more about where it
//! is than how loud they were. So each anchor has two parts:
//! - **detection**: the chance it is heard at all in a window at distance `d`,
//!   `p_max / (1 + (d / range_m)^slope)`, a logistic in log-distance: near 1
//!   close by, one half at `range_m`, falling off past it. An anchor that is not
//!   heard contributes `ln(1 − P(heard | d))`: weak evidence of distance, never a
//!   verdict, because adverts collide and scans miss even close beacons;
//! - **strength**: when heard, RSSI is `tx − 10·n·log10(d)` with Gaussian
//!   shadowing of `σ` dB, a deliberately wide spread (walls, bodies and shelves
//!   are not in the model).
//!
//! Every parameter has a default that suits no site in particular; a
//! calibration file written by `gangway calibrate` (fitted from what the
//! gateway hears, no positions needed: [`super::calibrate`]) replaces them per
//! anchor, and a site's `tx_power` sets an anchor's `tx`.

use std::path::PathBuf;
use std::sync::Arc;

use serde::{Deserialize, Serialize};

use super::window::Orientation;
use super::{Localizer, LocalizerError};
use crate::site::{Mount, Site};

/// `[localizer.pathloss]`: the radio model. The simulator reads the same keys
/// so that simulated logs and the localizer agree on what "typical" means.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct PathLossConfig {
    /// Measured power at 1 m for anchors whose site entry has no `tx_power`.
    pub tx_power_dbm: f64,
    /// Path-loss exponent `n`: 2 in free space, 2.5–4 indoors.
    pub exponent: f64,
    /// Shadowing standard deviation in dB.
    pub shadowing_db: f64,
    /// Weakest RSSI a receiver reports (the simulator drops weaker readings).
    pub sensitivity_dbm: f64,
    /// Distance in metres at which an anchor is heard in half the windows.
    pub range_m: f64,
    /// How fast detection falls off past `range_m` (the exponent of `d/range_m`).
    pub range_slope: f64,
    /// Chance of hearing an anchor right next to it in one window.
    pub max_detection: f64,
    /// Per-anchor parameters written by `gangway calibrate`; anchors it does
    /// not list keep the values above.
    pub calibration: Option<PathBuf>,
}

impl Default for PathLossConfig {
    fn default() -> Self {
        PathLossConfig {
            tx_power_dbm: -59.0,
            exponent: 2.2,
            shadowing_db: 5.0,
            sensitivity_dbm: -100.0,
            range_m: 5.0,
            range_slope: 3.0,
            max_detection: 0.9,
            calibration: None,
        }
    }
}

impl PathLossConfig {
    /// The calibration file's contents, when the config names one.
    pub(crate) fn load_calibration(
        &self,
        site: &Site,
    ) -> Result<Option<super::calibration::Calibration>, LocalizerError> {
        Ok(match &self.calibration {
            Some(path) => Some(super::calibration::Calibration::load(path, site)?),
            None => None,
        })
    }

    /// The radio model of an anchor with measured power `tx_dbm`.
    pub(crate) fn radio(&self, tx_dbm: f64) -> Radio {
        Radio {
            tx_dbm,
            exponent: self.exponent,
            shadowing_db: self.shadowing_db,
            range_m: self.range_m,
            range_slope: self.range_slope,
            max_detection: self.max_detection,
        }
    }

    /// Checks the values a user can get wrong, naming the key.
    pub fn validate(&self) -> Result<(), String> {
        self.radio(self.tx_power_dbm).validate()
    }
}

/// Closer than this the model is meaningless (antennas are not points).
const NEAREST_M: f64 = 0.5;

/// One anchor's radio model.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Radio {
    /// RSSI at 1 m, dBm.
    pub tx_dbm: f64,
    /// Path-loss exponent.
    pub exponent: f64,
    /// Spread of RSSI around the expected value, dB.
    pub shadowing_db: f64,
    /// Distance of 50%-of-`max_detection` detection, metres.
    pub range_m: f64,
    /// Fall-off of detection past `range_m`.
    pub range_slope: f64,
    /// Detection right next to the anchor.
    pub max_detection: f64,
}

impl Radio {
    pub fn expected_rssi(&self, distance_m: f64) -> f64 {
        self.tx_dbm - 10.0 * self.exponent * distance_m.max(NEAREST_M).log10()
    }

    /// Chance the anchor is heard in one window at `distance_m`, kept inside
    /// [`DETECTION_BOUNDS`] so neither hearing nor silence is ever impossible.
    pub fn detection(&self, distance_m: f64) -> f64 {
        let d = distance_m.max(NEAREST_M) / self.range_m;
        let p = self.max_detection / (1.0 + d.powf(self.range_slope));
        p.clamp(DETECTION_BOUNDS.0, DETECTION_BOUNDS.1)
    }

    pub(crate) fn validate(&self) -> Result<(), String> {
        let checks: [(&str, f64, bool); 5] = [
            ("exponent", self.exponent, self.exponent > 0.0),
            ("shadowing_db", self.shadowing_db, self.shadowing_db > 0.0),
            ("range_m", self.range_m, self.range_m > 0.0),
            ("range_slope", self.range_slope, self.range_slope > 0.0),
            (
                "max_detection",
                self.max_detection,
                self.max_detection > 0.0 && self.max_detection <= 1.0,
            ),
        ];
        for (key, value, ok) in checks {
            if !(ok && value.is_finite()) {
                return Err(format!(
                    "`{key}` = {value} is out of range (positive; max_detection at most 1)"
                ));
            }
        }
        if !self.tx_dbm.is_finite() {
            return Err(format!("`tx_dbm` = {} is not a number", self.tx_dbm));
        }
        Ok(())
    }
}

/// Detection probabilities are kept in this range: a beacon next to you is
/// still missed now and then (collisions, scan gaps), and one across the
/// floor is still heard through a reflection.
pub(crate) const DETECTION_BOUNDS: (f64, f64) = (1e-3, 0.98);

/// An anchor's mounting position (world metres, maybe a height) and radio
/// model, in the orientation's anchor order; `None` for an anchor without a
/// known position.
pub(crate) type Anchor = Option<(Mount, Radio)>;

/// The anchors of the site in the orientation's order, with the radio model
/// each one gets: the calibration's entry, else the config's values with the
/// site's `tx_power`.
pub fn anchors(
    site: &Site,
    orientation: Orientation,
    config: &PathLossConfig,
    calibration: Option<&super::calibration::Calibration>,
) -> Vec<Anchor> {
    let entries: Vec<(&str, Option<Mount>, Option<f64>)> = match orientation {
        Orientation::Observer => site
            .beacons
            .iter()
            .map(|b| (b.id.as_str(), b.mount, b.tx_power.map(f64::from)))
            .collect(),
        Orientation::Advertiser => site
            .gateways
            .iter()
            .map(|g| (g.id.as_str(), g.mount, None))
            .collect(),
    };
    entries
        .into_iter()
        .map(|(id, mount, tx)| {
            let mount = mount?;
            let radio = calibration
                .and_then(|c| c.radio(id))
                .unwrap_or_else(|| config.radio(tx.unwrap_or(config.tx_power_dbm)));
            Some((mount, radio))
        })
        .collect()
}

/// Localizes from the anchors' radio models.
#[derive(Clone)]
pub struct PathLoss {
    n_cells: usize,
    n_anchors: usize,
    /// Expected RSSI, `[anchor][cell]`: one anchor's cells side by side, so
    /// that scoring a window streams the heard anchors' columns through the
    /// cache and vector lanes. Cell-major rows made every cell fetch a
    /// row of every anchor for the few heard (megabytes per fix on a
    /// 5,500-cell mall floor of ~200 beacons: memory-bound). NaN for
    /// anchors without a position.
    expected: Vec<f32>,
    /// ln P(heard), same layout.
    log_hit: Vec<f32>,
    /// What hearing the anchor at a cell adds to hearing nothing, the
    /// Gaussian's exponent aside: `ln P(heard) − ln P(not heard) + ln(1/σ)`;
    /// `−ln P(not heard)` where the expected RSSI is NaN. Same layout.
    gain: Vec<f32>,
    /// Per cell, the sum of ln P(not heard) over every anchor: the
    /// log-likelihood of hearing nothing. A window hears a few of a
    /// building's hundreds of beacons, so a fix starts from this and visits
    /// the heard anchors only (`cells × heard`, not `cells × anchors`).
    miss_total: Vec<f32>,
    /// The anchors heard in the window being scored.
    heard_scratch: Vec<usize>,
    /// 1/σ per anchor.
    inv_sigma: Vec<f32>,
}

/// A model's tables as they are built, `[anchor][cell]` like the model's,
/// before [`Tables::model`] folds them into what a fix reads.
struct Tables {
    n_cells: usize,
    /// Expected RSSI; NaN for anchors without a position.
    expected: Vec<f32>,
    /// ln P(heard).
    log_hit: Vec<f32>,
    /// ln P(not heard).
    log_miss: Vec<f32>,
    /// 1/σ per anchor.
    inv_sigma: Vec<f32>,
}

impl PathLoss {
    /// The model from the config (and its calibration file, if any).
    pub fn new(
        config: &PathLossConfig,
        site: &Arc<Site>,
        orientation: Orientation,
    ) -> Result<Self, LocalizerError> {
        Self::calibrated(
            site,
            orientation,
            config,
            config.load_calibration(site)?.as_ref(),
        )
    }

    /// The model of the config's anchors with a calibration applied: its
    /// per-anchor models, then its refined cells.
    pub fn calibrated(
        site: &Site,
        orientation: Orientation,
        config: &PathLossConfig,
        calibration: Option<&super::calibration::Calibration>,
    ) -> Result<Self, LocalizerError> {
        let mut tables =
            Tables::of_anchors(site, &anchors(site, orientation, config, calibration))?;
        let Some(calibration) = calibration else {
            return Ok(tables.model());
        };
        // The calibration's anchors in the orientation's order.
        let ids = super::window::anchor_ids(site, orientation);
        let slots: Vec<Option<usize>> = calibration
            .anchors
            .iter()
            .map(|a| ids.iter().position(|id| *id == a.id))
            .collect();
        for cell in &calibration.cells {
            let Some(c) = site.open_index(crate::site::Cell::new(cell.at[0], cell.at[1])) else {
                continue;
            };
            for (j, slot) in slots.iter().enumerate() {
                let Some(a) = *slot else { continue };
                let i = a * tables.n_cells + c;
                if tables.expected[i].is_nan() {
                    continue;
                }
                let p = cell.detection[j].clamp(DETECTION_BOUNDS.0, DETECTION_BOUNDS.1);
                tables.expected[i] = cell.rssi_dbm[j] as f32;
                tables.log_hit[i] = p.ln() as f32;
                tables.log_miss[i] = (1.0 - p).ln() as f32;
            }
        }
        Ok(tables.model())
    }

    /// The model for given anchors (calibration and evaluation build these).
    pub(crate) fn with_anchors(site: &Site, anchors: &[Anchor]) -> Result<Self, LocalizerError> {
        Ok(Tables::of_anchors(site, anchors)?.model())
    }
}

impl Tables {
    /// The tables of given anchors.
    fn of_anchors(site: &Site, anchors: &[Anchor]) -> Result<Self, LocalizerError> {
        if anchors.iter().all(Option::is_none) {
            return Err(LocalizerError::NoAnchorPositions);
        }
        let places: Vec<_> = site
            .open_cells()
            .iter()
            .map(|&cell| site.world_of_cell(cell))
            .collect();
        let n = places.len() * anchors.len();
        let (mut expected, mut log_hit, mut log_miss) = (
            Vec::with_capacity(n),
            Vec::with_capacity(n),
            Vec::with_capacity(n),
        );
        for anchor in anchors {
            for &here in &places {
                match anchor {
                    Some((mount, radio)) => {
                        let d = mount.distance_m(here);
                        let p = radio.detection(d);
                        expected.push(radio.expected_rssi(d) as f32);
                        log_hit.push(p.ln() as f32);
                        log_miss.push((1.0 - p).ln() as f32);
                    }
                    None => {
                        expected.push(f32::NAN);
                        log_hit.push(0.0);
                        log_miss.push(0.0);
                    }
                }
            }
        }
        let inv_sigma = anchors
            .iter()
            .map(|a| a.map_or(0.0, |(_, r)| (1.0 / r.shadowing_db) as f32))
            .collect();
        Ok(Tables {
            n_cells: places.len(),
            expected,
            log_hit,
            log_miss,
            inv_sigma,
        })
    }

    /// The model: what a fix starts from (hearing nothing) and what each
    /// heard anchor adds, the latter in place of ln P(not heard) (a
    /// building's tables are tens of MB: never one more than these three).
    fn model(self) -> PathLoss {
        let Tables {
            n_cells,
            expected,
            log_hit,
            log_miss: mut gain,
            inv_sigma,
        } = self;
        // Each cell's sum over the anchors in their order.
        let mut miss_total = vec![0.0f32; n_cells];
        if n_cells > 0 {
            for column in gain.chunks_exact(n_cells) {
                for (total, &miss) in miss_total.iter_mut().zip(column) {
                    *total += miss;
                }
            }
            for (((gain, expected), log_hit), &inv_sigma) in gain
                .chunks_exact_mut(n_cells)
                .zip(expected.chunks_exact(n_cells))
                .zip(log_hit.chunks_exact(n_cells))
                .zip(&inv_sigma)
            {
                let ln_inv_sigma = inv_sigma.ln();
                for ((gain, &mu), &hit) in gain.iter_mut().zip(expected).zip(log_hit) {
                    let miss = *gain;
                    *gain = if mu.is_nan() {
                        -miss
                    } else {
                        hit - miss + ln_inv_sigma
                    };
                }
            }
        }
        PathLoss {
            n_cells,
            n_anchors: inv_sigma.len(),
            expected,
            log_hit,
            gain,
            miss_total,
            heard_scratch: Vec::new(),
            inv_sigma,
        }
    }
}

impl PathLoss {
    /// Expected RSSI and detection probability per cell and anchor,
    /// `[cell][anchor]`; NaN expected RSSI for anchors without a position.
    pub(crate) fn tables(&self) -> (Vec<f64>, Vec<f64>) {
        let by_cell = |table: &[f32], f: fn(f32) -> f64| -> Vec<f64> {
            (0..self.n_cells)
                .flat_map(|c| (0..self.n_anchors).map(move |a| f(table[a * self.n_cells + c])))
                .collect()
        };
        (
            by_cell(&self.expected, f64::from),
            by_cell(&self.log_hit, |v| f64::from(v).exp()),
        )
    }

    /// 1/σ per anchor.
    pub(crate) fn inv_sigma(&self) -> &[f32] {
        &self.inv_sigma
    }

    /// The model of given expected RSSI and detection tables, `[cell][anchor]`
    /// (as [`PathLoss::tables`] returns them).
    pub(crate) fn from_probabilities(
        n_cells: usize,
        expected: &[f64],
        detection: &[f64],
        inv_sigma: Vec<f32>,
    ) -> Self {
        // An anchor without a position (NaN) weighs nothing, heard or not.
        let log = |f: fn(f64) -> f64| -> Vec<f32> {
            expected
                .iter()
                .zip(detection)
                .map(|(e, &p)| if e.is_nan() { 0.0 } else { f(p).ln() as f32 })
                .collect()
        };
        Self::from_tables(
            n_cells,
            expected.iter().map(|&v| v as f32).collect(),
            log(|p| p),
            log(|p| 1.0 - p),
            inv_sigma,
        )
    }

    /// Likelihood tables made elsewhere (the radio map), `[cell][anchor]`
    /// row-major: each laid out per anchor and dropped in turn (one table
    /// more than the three at most).
    pub(crate) fn from_tables(
        n_cells: usize,
        expected: Vec<f32>,
        log_hit: Vec<f32>,
        log_miss: Vec<f32>,
        inv_sigma: Vec<f32>,
    ) -> Self {
        let n = inv_sigma.len();
        let by_anchor = |table: Vec<f32>| -> Vec<f32> {
            let mut out = Vec::with_capacity(table.len());
            for a in 0..n {
                out.extend((0..n_cells).map(|c| table[c * n + a]));
            }
            out
        };
        Tables {
            n_cells,
            expected: by_anchor(expected),
            log_hit: by_anchor(log_hit),
            log_miss: by_anchor(log_miss),
            inv_sigma,
        }
        .model()
    }
}

impl Localizer for PathLoss {
    fn method(&self) -> &'static str {
        "pathloss"
    }

    fn log_likelihood(&mut self, rssi: &[f32], heard: &[bool], out: &mut [f32]) {
        let mut scratch = std::mem::take(&mut self.heard_scratch);
        self.score(&mut scratch, rssi, heard, out);
        self.heard_scratch = scratch;
    }

    fn radio_model(&mut self) -> Option<&mut PathLoss> {
        Some(self)
    }
}

/// The model scored through a shared borrow, with its own scratch: what a
/// rehearsal localizes with while it reads the same model as its world, so
/// that a building's tables (94 MB on a 240 × 180 m floor of 204 beacons)
/// are never held twice.
pub(crate) struct Borrowed<'m> {
    model: &'m PathLoss,
    heard: Vec<usize>,
}

impl Localizer for Borrowed<'_> {
    fn method(&self) -> &'static str {
        self.model.method()
    }

    fn log_likelihood(&mut self, rssi: &[f32], heard: &[bool], out: &mut [f32]) {
        self.model.score(&mut self.heard, rssi, heard, out);
    }
}

impl PathLoss {
    /// The model as a localizer that borrows it.
    pub(crate) fn borrowed(&self) -> Borrowed<'_> {
        Borrowed {
            model: self,
            heard: Vec::new(),
        }
    }

    /// Expected RSSI and detection probability of `anchor` at the open cell
    /// `cell`; none for an anchor without a position.
    pub(crate) fn heard_at(&self, cell: usize, anchor: usize) -> Option<(f32, f64)> {
        let i = anchor * self.n_cells + cell;
        let mu = self.expected[i];
        (!mu.is_nan()).then(|| (mu, f64::from(self.log_hit[i]).exp()))
    }

    /// [`Localizer::log_likelihood`], the heard anchors listed in `scratch`.
    fn score(&self, scratch: &mut Vec<usize>, rssi: &[f32], heard: &[bool], out: &mut [f32]) {
        debug_assert_eq!(rssi.len(), self.n_anchors);
        debug_assert_eq!(out.len(), self.n_cells);
        let n = self.n_cells;
        scratch.clear();
        scratch.extend((0..self.n_anchors).filter(|&a| heard[a]));
        // Hearing nothing, then each heard anchor's miss swapped for its
        // hit, one anchor's column at a time (an anchor without a position
        // weighs nothing: its gain is 0 and its expected RSSI NaN).
        out.copy_from_slice(&self.miss_total);
        for &a in scratch.iter() {
            let (r, inv_sigma) = (rssi[a], self.inv_sigma[a]);
            let column = a * n..(a + 1) * n;
            for ((slot, &mu), &gain) in out
                .iter_mut()
                .zip(&self.expected[column.clone()])
                .zip(&self.gain[column])
            {
                let z = (r - mu) * inv_sigma;
                *slot += if mu.is_nan() {
                    gain
                } else {
                    gain - 0.5 * z * z
                };
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    impl PathLossConfig {
        /// Expected RSSI at `distance_m` from an anchor with measured power `tx`.
        fn expected_rssi(&self, tx_dbm: f64, distance_m: f64) -> f64 {
            self.radio(tx_dbm).expected_rssi(distance_m)
        }
    }

    fn corridor() -> Arc<Site> {
        let text = r#"
name = "corridor"
cell_m = 1.0
map = '''
##########
'''
[[beacon]]
id = "west"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 1
cell = [0, 0]
[[beacon]]
id = "east"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 2
cell = [9, 0]
"#;
        Arc::new(Site::parse(text, Path::new("t.toml")).unwrap())
    }

    fn best(ll: &[f32]) -> usize {
        (0..ll.len())
            .max_by(|&a, &b| ll[a].total_cmp(&ll[b]))
            .unwrap()
    }

    #[test]
    fn the_cell_next_to_the_loudest_beacon_scores_best() {
        let site = corridor();
        let config = PathLossConfig::default();
        let mut model = PathLoss::new(&config, &site, Orientation::Observer).unwrap();
        // Standing at x = 2: west at 2 m, east at 7 m.
        let rssi = [
            config.expected_rssi(-59.0, 2.0) as f32,
            config.expected_rssi(-59.0, 7.0) as f32,
        ];
        let mut ll = vec![0.0; 10];
        model.log_likelihood(&rssi, &[true, true], &mut ll);
        assert_eq!(best(&ll), 2);
    }

    #[test]
    fn silence_is_weak_evidence_of_distance() {
        // West heard faintly, east silent: the cells next to east lose, but
        // only by what one missed advert costs, never outright.
        let site = corridor();
        let mut model =
            PathLoss::new(&PathLossConfig::default(), &site, Orientation::Observer).unwrap();
        let mut silent = vec![0.0; 10];
        model.log_likelihood(&[-80.0, -105.0], &[true, false], &mut silent);
        let mut unheard_anchor_ignored = vec![0.0; 10];
        let mut one = PathLoss::with_anchors(
            &site,
            &[
                Some((
                    site.beacons[0].mount.unwrap(),
                    PathLossConfig::default().radio(-59.0),
                )),
                None,
            ],
        )
        .unwrap();
        one.log_likelihood(
            &[-80.0, -105.0],
            &[true, false],
            &mut unheard_anchor_ignored,
        );
        let penalty = |ll: &[f32]| ll[9] - ll[5];
        assert!(penalty(&silent) < penalty(&unheard_anchor_ignored));
        assert!(
            penalty(&silent) > -10.0,
            "silence is not a verdict: {silent:?}"
        );
    }

    #[test]
    fn detection_falls_with_distance_and_is_never_certain() {
        let radio = PathLossConfig::default().radio(-59.0);
        let near = radio.detection(0.0);
        let half = radio.detection(radio.range_m);
        let far = radio.detection(100.0);
        assert!(near > half && half > far);
        assert!((half - radio.max_detection / 2.0).abs() < 1e-9);
        assert!(near <= DETECTION_BOUNDS.1 && far >= DETECTION_BOUNDS.0);
    }

    #[test]
    fn a_bad_value_is_named() {
        let config = PathLossConfig {
            max_detection: 1.5,
            ..PathLossConfig::default()
        };
        assert!(config.validate().unwrap_err().contains("max_detection"));
    }
}
