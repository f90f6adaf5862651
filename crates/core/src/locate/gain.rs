//! Each device's receiver gain, learned from what it hears.
//!
//! Phones and tags do not hear alike: at the same spot two phone models read
//! the same beacon 5–10 dB apart (antenna, case, the chipset's RSSI scale).
//! A radio model describes one receiver: the defaults, the phones a
//! calibration heard, or the surveyor's phone. A phone 8 dB deafer than
//! that is placed two to three times too far from every beacon it hears,
//! and no file can list the phones that will visit.
//!
//! So each device's offset from the model is learned from its own fixes:
//! after each fix, what it heard minus what the localizer's model expects at
//! the fixed cell by the localizer's radio model
//! ([`Localizer::radio_model`]), averaged over its
//! recent readings and shrunk towards no offset by [`PRIOR_READINGS`]
//! readings' weight. Its next windows are corrected by it before they are
//! localized. The fix absorbs part of an offset (a deaf phone is first put
//! farther away, where the model expects less), so one estimate falls
//! short; corrected windows give fixes that absorb less, and the estimate
//! settles where the residual left is the device's own.
//!
//! Only where the data shows it. A residual at the fixed cell is also the
//! fix's error (a fix pulled away from the beacons it hears reads them
//! louder than the model expects there) and the model's misfit at that
//! spot, neither of them the device's: corrected by them, a device's fixes
//! drift farther, its residuals grow, and the correction feeds itself. So
//! the estimate is applied only while it explains the device's readings
//! better than none does with the position left open: the likelihood of
//! each window summed over every cell, corrected against as heard, scored
//! prequentially (each window against the estimate learned before it) and
//! summed over the device's recent windows; and only past [`NEGLIGIBLE_DB`]
//! and odds of [`STRONG_EVIDENCE`]. The likelihood is a model's, and on
//! real floors small edges in it (1–2 dB, a nat or two) came with worse
//! fixes, not better.
//!
//! Why it is off by default (`[localizer] device_gains`): both tests lean
//! the same way. A fix error reads as a louder phone (above), and the
//! likelihood summed over every cell with no prior favours readings
//! corrected quieter, as quieter readings fit more of a floor. Where every
//! phone is the model's (the paper's floor, its surveyor's rows against the
//! crowd-calibrated model) long-heard devices passed both at +3 to +7.5 dB
//! and guidance and replay got worse; a phone 8 dB deafer than the model
//! was found 9–18% closer. The fair test is each window's likelihood given
//! the tracker's belief before it, which the tracker does not yet hand out.
//!
//! Devices come from the air, so the table is bounded like every
//! per-device table ([`Bounds`]), and one reading moves an estimate by at
//! most [`MAX_RESIDUAL_DB`]'s share.

use std::collections::HashMap;
use std::sync::Arc;

use super::Localizer;
use super::bounds::Bounds;
use super::floors::log_sum_exp;
use super::pathloss::PathLoss;

/// Weight of "no offset" in a device's estimate, in readings: a device's
/// first few windows move it little.
const PRIOR_READINGS: f64 = 20.0;
/// Readings (and windows, for the evidence) a device's estimate remembers
/// (exponential forgetting): long enough to average over walls and bodies,
/// short enough to follow a phone taken out of a pocket.
const MEMORY_READINGS: f64 = 200.0;
/// A residual beyond this (dB) counts as this much: a reading far off the
/// model at the fixed cell says more about the fix than about the receiver.
const MAX_RESIDUAL_DB: f64 = 20.0;
/// An estimate smaller than this (dB) is not weighed or applied: well inside
/// the spread of one reading (4–8 dB of shadowing), so it moves fixes less
/// than the model's own misfit does, and weighing it costs two more scorings
/// per window.
const NEGLIGIBLE_DB: f64 = 3.0;
/// Evidence (nats, summed over the device's recent windows) the estimate
/// needs before it is applied: odds of 20 to 1 over no offset, the usual
/// bar for "strong" evidence, as the likelihood is only a model's and small
/// edges in it do not make fixes better.
const STRONG_EVIDENCE: f64 = 3.0;
/// Once the evidence is this many times [`STRONG_EVIDENCE`] either way, the
/// question is settled for now and only every [`SETTLED_STRIDE`]th window
/// is weighed: a settled device costs a tenth more scoring, not twice.
const SETTLED: f64 = 4.0;
const SETTLED_STRIDE: u64 = 8;

/// What one device's readings said about its gain.
#[derive(Clone, Copy, Debug, Default)]
struct Gain {
    /// Forgetting sums of residuals and of readings.
    residual_sum: f64,
    readings: f64,
    /// Forgetting sum over windows of ln P(window | corrected by the
    /// estimate) − ln P(window | as heard), each summed over every cell.
    evidence: f64,
    /// Windows localized with an estimate worth weighing.
    windows: u64,
    /// Whether its offset was applied when last said (in the log).
    announced: bool,
    last_t: f64,
}

impl Gain {
    fn estimate(&self) -> f64 {
        self.residual_sum / (self.readings + PRIOR_READINGS)
    }

    /// The offset its windows are corrected by: the estimate while it
    /// explains them better than none.
    fn applied(&self) -> f64 {
        if self.evidence > STRONG_EVIDENCE && self.estimate().abs() >= NEGLIGIBLE_DB {
            self.estimate()
        } else {
            0.0
        }
    }
}

/// Learned gains of the devices a localizer hears, in dB above its radio
/// model ([`Localizer::radio_model`]).
#[derive(Debug, Default)]
pub struct Gains {
    devices: HashMap<Arc<str>, Gain>,
    bounds: Bounds,
    /// One window corrected, and the radio model's scores as heard and
    /// corrected: reused, as windows come at the rate of the air.
    corrected: Vec<f32>,
    as_heard: Vec<f32>,
    if_corrected: Vec<f32>,
}

impl Gains {
    /// At most `max_devices`, each forgotten after `idle_s` unheard.
    pub fn bounded(max_devices: usize, idle_s: f64) -> Gains {
        Gains {
            bounds: Bounds::new(max_devices, idle_s),
            ..Gains::default()
        }
    }

    /// [`Localizer::log_likelihood`] of `device`'s window, corrected by its
    /// offset where that has earned its place; first weighs the window's
    /// evidence for its current estimate.
    pub fn log_likelihood<L: Localizer + ?Sized>(
        &mut self,
        localizer: &mut L,
        device: &str,
        rssi: &[f32],
        heard: &[bool],
        out: &mut [f32],
    ) {
        let Some(gain) = self.devices.get_mut(device) else {
            return localizer.log_likelihood(rssi, heard, out);
        };
        let estimate = gain.estimate();
        if estimate.abs() >= NEGLIGIBLE_DB {
            self.corrected.clear();
            self.corrected.extend(
                rssi.iter()
                    .zip(heard)
                    .map(|(&r, &h)| if h { r - estimate as f32 } else { r }),
            );
            gain.windows += 1;
            let settled = gain.evidence.abs() >= SETTLED * STRONG_EVIDENCE;
            let weigh = !settled || gain.windows % SETTLED_STRIDE == 0;
            if let Some(model) = localizer.radio_model().filter(|_| weigh) {
                let cells = out.len();
                let marginal = |scores: &mut Vec<f32>, rssi: &[f32], model: &mut PathLoss| {
                    scores.resize(cells, 0.0);
                    model.log_likelihood(rssi, heard, scores);
                    log_sum_exp(scores.iter().map(|&v| f64::from(v)))
                };
                let without = marginal(&mut self.as_heard, rssi, model);
                let with = marginal(&mut self.if_corrected, &self.corrected, model);
                let keep = 1.0 - 1.0 / MEMORY_READINGS;
                if (with - without).is_finite() {
                    gain.evidence = gain.evidence * keep + (with - without);
                }
            }
        }
        let applied = gain.applied();
        // What a user turning this on needs to see: which devices it
        // corrects, by how much, and when it stops.
        if (applied != 0.0) != gain.announced {
            gain.announced = applied != 0.0;
            tracing::debug!(
                device,
                offset_db = applied,
                estimate_db = estimate,
                evidence = gain.evidence,
                "device gain {}",
                if gain.announced { "applied" } else { "dropped" }
            );
        }
        // Applied only past NEGLIGIBLE_DB, where `corrected` was just filled.
        let rssi = if applied != 0.0 {
            &self.corrected[..]
        } else {
            rssi
        };
        localizer.log_likelihood(rssi, heard, out);
    }

    /// Learns from a fix of `device` at time `t` in the open cell `cell`
    /// from its window as heard: each heard anchor's RSSI against what the
    /// localizer's radio model expects there.
    pub fn learn<L: Localizer + ?Sized>(
        &mut self,
        localizer: &mut L,
        device: &Arc<str>,
        t: f64,
        rssi: &[f32],
        heard: &[bool],
        cell: usize,
    ) {
        let Some(model) = localizer.radio_model() else {
            return;
        };
        let full = !self.devices.contains_key(device) && self.devices.len() >= self.bounds.max();
        self.bounds
            .make_room(&mut self.devices, t, full, |g| g.last_t, |_| {});
        let gain = self.devices.entry(device.clone()).or_default();
        let keep = 1.0 - 1.0 / MEMORY_READINGS;
        for (a, (&r, _)) in rssi.iter().zip(heard).enumerate().filter(|(_, (_, h))| **h) {
            let Some((mu, _)) = model.heard_at(cell, a) else {
                continue;
            };
            let residual = f64::from(r - mu).clamp(-MAX_RESIDUAL_DB, MAX_RESIDUAL_DB);
            if !residual.is_finite() {
                continue;
            }
            gain.residual_sum = gain.residual_sum * keep + residual;
            gain.readings = gain.readings * keep + 1.0;
        }
        gain.last_t = t;
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use rand::rngs::Xoshiro256PlusPlus;
    use rand::{RngExt, SeedableRng};
    use rand_distr::{Distribution, Normal};

    use super::*;
    use crate::locate::tracker::{Tracker, TrackerConfig};
    use crate::locate::window::WindowConfig;
    use crate::locate::{LocalizerConfig, Method, build};
    use crate::site::Site;

    const WINDOWS: usize = 600;

    fn office() -> Arc<Site> {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../../fixtures/sites/office.toml"
        );
        Arc::new(Site::load(Path::new(path)).unwrap())
    }

    fn survey_free(site: &Arc<Site>) -> Box<dyn Localizer> {
        let config = LocalizerConfig {
            method: Method::Pathloss,
            ..LocalizerConfig::default()
        };
        build(
            &config,
            site,
            &WindowConfig::default(),
            &TrackerConfig::default(),
        )
        .unwrap()
    }

    /// A phone `receiver_db` louder than the model walking the office for
    /// [`WINDOWS`] windows, tracked with and without learned gains: its
    /// mean error in cells over the second half each way, and the offset
    /// learned.
    fn walk(site: &Arc<Site>, receiver_db: f64, seed: u64) -> (f64, f64, f64) {
        let mut world = survey_free(site);
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
        let cells = site.open_cells();
        let model = world.radio_model().unwrap();
        let anchors = model.inv_sigma().len();
        let noise: Vec<Normal<f64>> = model
            .inv_sigma()
            .iter()
            .map(|&s| Normal::new(0.0, 1.0 / f64::from(s)).unwrap())
            .collect();
        let (mut with, mut without) = (survey_free(site), survey_free(site));
        let mut gains = Gains::bounded(16, 600.0);
        let device: Arc<str> = Arc::from("phone");
        let (mut track_with, mut track_without) = (
            Tracker::new(TrackerConfig::default(), site.clone()),
            Tracker::new(TrackerConfig::default(), site.clone()),
        );
        let (mut rssi, mut heard) = (vec![0.0f32; anchors], vec![false; anchors]);
        let mut ll = vec![0.0f32; cells.len()];
        let (mut error_with, mut error_without) = (0.0, 0.0);
        let mut here = rng.random_range(0..cells.len());
        for k in 0..WINDOWS {
            // About a cell a window, to a random open neighbour.
            let next: Vec<usize> = (0..cells.len())
                .filter(|&c| cells[c].distance(cells[here]) == 1.0)
                .collect();
            if !next.is_empty() {
                here = next[rng.random_range(0..next.len())];
            }
            let model = world.radio_model().unwrap();
            for a in 0..anchors {
                let Some((mu, detection)) = model.heard_at(here, a) else {
                    heard[a] = false;
                    continue;
                };
                heard[a] = rng.random::<f64>() < detection;
                rssi[a] = (f64::from(mu) + receiver_db + noise[a].sample(&mut rng)) as f32;
            }
            if !heard.contains(&true) {
                continue;
            }
            let t = k as f64 * 2.0;
            gains.log_likelihood(with.as_mut(), &device, &rssi, &heard, &mut ll);
            let fix = track_with.update(&device, t, &ll);
            let cell = site.open_index(fix.cell).unwrap();
            gains.learn(with.as_mut(), &device, t, &rssi, &heard, cell);
            let plain = {
                without.log_likelihood(&rssi, &heard, &mut ll);
                track_without.update(&device, t, &ll)
            };
            if k >= WINDOWS / 2 {
                error_with += fix.cell.distance(cells[here]);
                error_without += plain.cell.distance(cells[here]);
            }
        }
        let half = (WINDOWS - WINDOWS / 2) as f64;
        (
            error_with / half,
            error_without / half,
            gains.devices.get(&device).map_or(0.0, Gain::applied),
        )
    }

    #[test]
    fn a_phone_that_hears_differently_is_corrected_and_found_closer() {
        let site = office();
        for (receiver_db, seed) in [(-8.0, 1), (6.0, 2)] {
            let (with, without, learned) = walk(&site, receiver_db, seed);
            assert!(
                (learned - receiver_db).abs() < 2.5,
                "{receiver_db} dB phone learned as {learned:.2} dB"
            );
            assert!(
                with < without,
                "{receiver_db} dB phone: mean error {with:.2} cells with gains, {without:.2} without"
            );
        }
    }

    #[test]
    fn a_phone_the_model_describes_reads_as_before() {
        let site = office();
        for seed in 3..6 {
            let (with, without, learned) = walk(&site, 0.0, seed);
            assert_eq!(learned, 0.0, "seed {seed}: errors {with:.2} / {without:.2}");
            assert_eq!(with, without, "seed {seed}");
        }
    }

    #[test]
    fn the_table_keeps_at_most_its_bound_of_devices() {
        let site = office();
        let mut localizer = survey_free(&site);
        let anchors = localizer.radio_model().unwrap().inv_sigma().len();
        let (rssi, heard) = (vec![-70.0f32; anchors], vec![true; anchors]);
        let mut gains = Gains::bounded(8, 600.0);
        for d in 0..1000 {
            let device: Arc<str> = Arc::from(format!("flood-{d}"));
            gains.learn(localizer.as_mut(), &device, d as f64, &rssi, &heard, 0);
            assert!(
                gains.devices.len() <= 8,
                "{} devices kept",
                gains.devices.len()
            );
        }
        // The newest is kept: an old table is what a flood pushes out.
        assert!(gains.devices.contains_key("flood-999"));
    }
}
