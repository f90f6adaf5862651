//! The log-distance path-loss model, used both to localize without a survey and
//! to simulate what a walker hears.
//!
//! Expected RSSI at distance `d` metres from an anchor with measured power `P`
//! (RSSI at 1 m): `P − 10·n·log10(d)`, with Gaussian shadowing of `σ` dB. An anchor
//! that is not heard is evidence too: it is likely far away, with probability
//! `Φ((sensitivity − expected) / σ)`.

use std::sync::Arc;

use serde::Deserialize;

use super::window::Orientation;
use super::{Localizer, LocalizerError};
use crate::site::{Cell, Site};

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
    /// Weakest RSSI a receiver reports.
    pub sensitivity_dbm: f64,
}

impl Default for PathLossConfig {
    fn default() -> Self {
        PathLossConfig {
            tx_power_dbm: -59.0,
            exponent: 2.2,
            shadowing_db: 5.0,
            sensitivity_dbm: -100.0,
        }
    }
}

impl PathLossConfig {
    /// Expected RSSI at `distance_m` from an anchor with measured power `tx`.
    pub fn expected_rssi(&self, tx_dbm: f64, distance_m: f64) -> f64 {
        // Closer than half a metre the model is meaningless; clamp.
        tx_dbm - 10.0 * self.exponent * distance_m.max(0.5).log10()
    }
}

/// Anchor positions and measured powers in the orientation's anchor order.
/// `None` for an anchor without a known cell.
pub fn anchor_positions(
    site: &Site,
    orientation: Orientation,
    config: &PathLossConfig,
) -> Vec<Option<(Cell, f64)>> {
    match orientation {
        Orientation::Observer => site
            .beacons
            .iter()
            .map(|b| {
                b.cell
                    .map(|c| (c, b.tx_power.map_or(config.tx_power_dbm, f64::from)))
            })
            .collect(),
        Orientation::Advertiser => site
            .gateways
            .iter()
            .map(|g| g.cell.map(|c| (c, config.tx_power_dbm)))
            .collect(),
    }
}

/// Localizes from the path-loss model: a Gaussian likelihood per heard anchor
/// and a miss probability per silent one.
pub struct PathLoss {
    n_cells: usize,
    n_anchors: usize,
    /// Expected RSSI, `[cell][anchor]` row-major; NaN for anchors without a cell.
    expected: Vec<f32>,
    /// ln P(not heard), same layout.
    log_miss: Vec<f32>,
    inv_sigma: f32,
}

impl PathLoss {
    pub fn new(
        config: &PathLossConfig,
        site: &Arc<Site>,
        orientation: Orientation,
    ) -> Result<Self, LocalizerError> {
        let anchors = anchor_positions(site, orientation, config);
        if anchors.iter().all(Option::is_none) {
            return Err(LocalizerError::NoAnchorPositions);
        }
        let cells = site.open_cells();
        let mut expected = Vec::with_capacity(cells.len() * anchors.len());
        let mut log_miss = Vec::with_capacity(cells.len() * anchors.len());
        for &cell in cells {
            for anchor in &anchors {
                match anchor {
                    Some((at, tx)) => {
                        let mu = config.expected_rssi(*tx, cell.distance(*at) * site.cell_m);
                        let miss = normal_cdf((config.sensitivity_dbm - mu) / config.shadowing_db);
                        expected.push(mu as f32);
                        // Floor: even a beacon next to you is missed now and then
                        // (collisions, scan gaps), so silence is never impossible.
                        log_miss.push(miss.max(0.02).ln() as f32);
                    }
                    None => {
                        expected.push(f32::NAN);
                        log_miss.push(0.0);
                    }
                }
            }
        }
        Ok(PathLoss {
            n_cells: cells.len(),
            n_anchors: anchors.len(),
            expected,
            log_miss,
            inv_sigma: (1.0 / config.shadowing_db) as f32,
        })
    }
}

impl Localizer for PathLoss {
    fn method(&self) -> &'static str {
        "pathloss"
    }

    fn log_likelihood(&mut self, rssi: &[f32], heard: &[bool], out: &mut [f32]) {
        debug_assert_eq!(rssi.len(), self.n_anchors);
        debug_assert_eq!(out.len(), self.n_cells);
        let rows = self.expected.chunks_exact(self.n_anchors);
        let misses = self.log_miss.chunks_exact(self.n_anchors);
        for ((slot, expected), log_miss) in out.iter_mut().zip(rows).zip(misses) {
            let mut ll = 0.0f32;
            for a in 0..self.n_anchors {
                let mu = expected[a];
                if mu.is_nan() {
                    continue;
                }
                if heard[a] {
                    let z = (rssi[a] - mu) * self.inv_sigma;
                    ll -= 0.5 * z * z;
                } else {
                    ll += log_miss[a];
                }
            }
            *slot = ll;
        }
    }
}

/// Standard normal CDF. Hand-written (Abramowitz & Stegun 26.2.17, error below
/// 7.5e-8) because it is the only special function the crate needs.
pub fn normal_cdf(z: f64) -> f64 {
    let t = 1.0 / (1.0 + 0.231_641_9 * z.abs());
    let poly = t
        * (0.319_381_530
            + t * (-0.356_563_782
                + t * (1.781_477_937 + t * (-1.821_255_978 + t * 1.330_274_429))));
    let tail = (-0.5 * z * z).exp() / (2.0 * std::f64::consts::PI).sqrt() * poly;
    if z >= 0.0 { 1.0 - tail } else { tail }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    #[test]
    fn normal_cdf_matches_known_values() {
        for (z, p) in [
            (0.0, 0.5),
            (1.0, 0.841_344_7),
            (-1.96, 0.024_997_9),
            (3.0, 0.998_650_1),
        ] {
            assert!((normal_cdf(z) - p).abs() < 1e-6, "Φ({z})");
        }
    }

    #[test]
    fn the_cell_next_to_the_loudest_beacon_scores_best() {
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
        let site = Arc::new(Site::parse(text, Path::new("t.toml")).unwrap());
        let mut model =
            PathLoss::new(&PathLossConfig::default(), &site, Orientation::Observer).unwrap();
        let config = PathLossConfig::default();
        // Standing at x = 2: west at 2 m, east at 7 m.
        let rssi = [
            config.expected_rssi(-59.0, 2.0) as f32,
            config.expected_rssi(-59.0, 7.0) as f32,
        ];
        let mut ll = vec![0.0; 10];
        model.log_likelihood(&rssi, &[true, true], &mut ll);
        let best = (0..10).max_by(|&a, &b| ll[a].total_cmp(&ll[b])).unwrap();
        assert_eq!(best, 2);
    }
}
