//! Weighted k-nearest-neighbour fingerprinting over a site survey.
//!
//! Each survey row is a fingerprint with a known cell. For a new fingerprint the
//! `k` rows nearest in signal space (L1 distance in dB, anchors not heard filled
//! with `[window] missing_dbm`) vote for their cells with a kernel weight
//! `exp(−d / bandwidth_db)`. A cell's vote is divided by how many rows the
//! survey has there, which turns votes into a class-conditional likelihood
//! (otherwise densely surveyed cells would win twice, once here and once in the
//! tracker's prior). Cells without a vote get `floor` (relative to the best
//! cell), so the tracker can still pass through them.
//!
//! The floor is far below the tracker's recovery mass by default: when the
//! vote names cells the motion prior holds almost nothing on, the track moves
//! to them instead of staying where the vote says it is not. A floor of 1e-3
//! (above the recovery mass) kept stale tracks: on the UCI survey, session
//! split, k-NN + hmm went from 1.14 to 1.09 cells with 1e-6.
//!
//! L1 rather than L2: with one to three anchors heard per scan, most of the
//! distance is "heard here, not there" steps of ~40 dB, and L1 ranks those
//! mismatches more evenly than L2 (measured on the UCI survey: within-2 0.70 vs
//! 0.69, mean error 1.47 vs 1.51 cells, random split, before tracking).
//!
//! Its published confidence is the tracker's raw belief: fitting it on
//! held-out sessions as the radio map does made it worse here (the largest
//! reliability gap on the UCI survey went from 0.24 to 0.28), because a vote
//! over two thirds of the survey is much less sure than one over all of it.
//! `k` and the kernel width stay settings: choosing them by cross-validation
//! was noisier than these defaults on the same survey (mean error 1.18
//! against 1.14 cells); the `radiomap` localizer is the surveyed method whose
//! settings and confidence come from the survey.

use std::path::PathBuf;
use std::sync::Arc;

use serde::Deserialize;

use super::crossval::{self, Folds};
use super::reliability::Mapped;
use super::survey::{Sample, Survey};
use super::tracker::TrackerConfig;
use super::{Localizer, LocalizerError};
use crate::site::Site;

/// `[localizer.knn]` in the gateway config.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct KnnConfig {
    /// The survey CSV (see `locate::survey` for the layouts read).
    pub survey: Option<PathBuf>,
    /// Neighbours that vote.
    pub k: usize,
    /// Kernel width in dB of L1 distance.
    pub bandwidth_db: f32,
    /// The survey's "not heard" value.
    pub not_heard: i16,
    /// Relative likelihood of a walkable cell with no vote.
    pub floor: f32,
}

impl Default for KnnConfig {
    fn default() -> Self {
        KnnConfig {
            survey: None,
            k: 30,
            bandwidth_db: 1.5,
            not_heard: -200,
            floor: 1e-6,
        }
    }
}

impl KnnConfig {
    /// Checks the values a user can get wrong, naming the key.
    pub fn validate(&self) -> Result<(), String> {
        if self.k == 0 {
            return Err("`k` must be at least 1".into());
        }
        if !(self.bandwidth_db.is_finite() && self.bandwidth_db > 0.0) {
            return Err(format!(
                "`bandwidth_db` = {} must be a positive number of dB",
                self.bandwidth_db
            ));
        }
        if !(self.floor.is_finite() && self.floor > 0.0 && self.floor < 1.0) {
            return Err(format!(
                "`floor` = {} must be between 0 and 1 (exclusive)",
                self.floor
            ));
        }
        Ok(())
    }
}

pub struct Knn {
    n_anchors: usize,
    /// The survey's distinct fingerprints, anchor by anchor:
    /// `[anchor][stride]`. Real surveys repeat fingerprints (the UCI
    /// survey's 1,420 rows hold 644), and each is compared once. Stored by
    /// anchor so the distance loop runs over [`BLOCK`] fingerprints at once
    /// in SIMD lanes, with no sum across lanes per fingerprint.
    columns: Vec<f32>,
    /// Floats per anchor in `columns`: the fingerprints padded with zeros
    /// to whole blocks.
    stride: usize,
    /// Per anchor, the fingerprints that heard it and how loud: a window
    /// of a building hears ~10 of a floor's ~200 beacons, and a distance
    /// differs from the one to the window that heard nothing only on the
    /// anchors heard ([`Knn::measure_heard`]).
    postings: Vec<Vec<(u32, f32)>>,
    /// The survey's "not heard" value, and whether every value of the
    /// survey is a whole number of dB (then sums in any order are exact).
    not_heard: f32,
    whole_db: bool,
    /// Per fingerprint, its distance to a window hearing nothing (every
    /// anchor at `silence.0`, as bits); rebuilt when that value changes.
    silence: (u32, Vec<f32>),
    /// Survey rows per fingerprint.
    rows_of: Vec<f32>,
    /// Survey rows in all (the sum of `rows_of`).
    rows: f32,
    /// Where each fingerprint's (open cell, rows there) pairs start in
    /// `members`; one more entry than fingerprints.
    member_start: Vec<u32>,
    members: Vec<(u32, f32)>,
    /// 1 / (rows surveyed in the cell), per open cell; 0 where none.
    inv_count: Vec<f32>,
    k: usize,
    inv_bandwidth: f32,
    floor: f32,
    /// L1 distance (dB) from the last fingerprint to the nearest survey row.
    nearest_db: f32,
    /// L1 distance from the query to each fingerprint (and the padding),
    /// reused between calls.
    distance: Vec<f32>,
    /// Every fingerprint as its distance's bits above its index, then the
    /// `k` nearest, nearest first: distances are never negative, so these
    /// integers rank as the distances do, with no float comparisons.
    ranked: Vec<u64>,
    /// The fingerprints that vote, in the survey's order.
    voters: Vec<u32>,
    votes: Vec<f32>,
    /// `ln(floor)`: every cell with no vote gets it.
    ln_floor: f32,
}

/// A survey row within this many kernel widths (L1, dB) of a fingerprint
/// recorded it: the row still carries e^-2 ≈ 14% of an exact match's
/// weight in the vote, so the vote is a lookup of something recorded rather
/// than the least bad of strangers.
pub(crate) const FAMILIAR_BANDWIDTHS: f32 = 2.0;

/// Anchors `a`, `a + LANES`, `a + 2 LANES`, … are summed apart before the
/// lanes are added in order: the order distances have always been summed in
/// (a fingerprint-major SIMD loop of this width), kept so that which rows
/// tie is the same as before.
const LANES: usize = 8;

/// Fingerprints measured at once, their sums held in registers.
const BLOCK: usize = 16;

/// Whole numbers of dB below this are exact in f32, and so is any sum of a
/// floor's distances over them (2²⁴ ÷ 1,000 anchors ÷ 2).
const WHOLE_DB_EXACT: f32 = 8192.0;

impl Knn {
    /// Builds from survey rows (any subset, e.g. a training split).
    pub fn new(
        config: &KnnConfig,
        site: &Site,
        samples: &[&Sample],
        missing_dbm: f32,
    ) -> Result<Self, LocalizerError> {
        if samples.is_empty() {
            return Err(LocalizerError::EmptySurvey);
        }
        let n_anchors = samples[0].rssi.len();
        let n_cells = site.open_cells().len();
        let mut count = vec![0u32; n_cells];
        // Fingerprint (as exact bits) → rows per cell.
        let mut distinct: std::collections::BTreeMap<
            Vec<u32>,
            std::collections::BTreeMap<u32, u32>,
        > = std::collections::BTreeMap::new();
        for s in samples {
            let Some(cell) = site.open_index(s.cell) else {
                return Err(LocalizerError::SurveyOnBlockedCell(s.cell));
            };
            let key = s
                .rssi
                .iter()
                .map(|r| r.map_or(missing_dbm, f32::from).to_bits())
                .collect();
            *distinct
                .entry(key)
                .or_default()
                .entry(cell as u32)
                .or_default() += 1;
            count[cell] += 1;
        }
        let n_fingerprints = distinct.len();
        let stride = n_fingerprints.next_multiple_of(BLOCK);
        let mut columns = vec![0.0; n_anchors * stride];
        let mut postings = vec![Vec::new(); n_anchors];
        let mut rows_of = Vec::with_capacity(n_fingerprints);
        let mut member_start = vec![0u32];
        let mut members = Vec::new();
        for (f, (key, cells)) in distinct.into_iter().enumerate() {
            for (a, bits) in key.into_iter().enumerate() {
                let value = f32::from_bits(bits);
                columns[a * stride + f] = value;
                if value != missing_dbm {
                    postings[a].push((f as u32, value));
                }
            }
            rows_of.push(cells.values().sum::<u32>() as f32);
            members.extend(cells.into_iter().map(|(c, n)| (c, n as f32)));
            member_start.push(members.len() as u32);
        }
        let whole = |v: f32| v.fract() == 0.0 && v.abs() < WHOLE_DB_EXACT;
        let whole_db = whole(missing_dbm) && postings.iter().flatten().all(|&(_, v)| whole(v));
        Ok(Knn {
            n_anchors,
            columns,
            stride,
            postings,
            not_heard: missing_dbm,
            whole_db,
            silence: (f32::NAN.to_bits(), Vec::new()),
            rows: rows_of.iter().sum(),
            distance: vec![0.0; stride],
            ranked: Vec::with_capacity(n_fingerprints),
            voters: Vec::with_capacity(n_fingerprints),
            rows_of,
            member_start,
            members,
            inv_count: count
                .iter()
                .map(|&c| if c == 0 { 0.0 } else { 1.0 / c as f32 })
                .collect(),
            k: config.k.max(1),
            inv_bandwidth: 1.0 / config.bandwidth_db.max(1e-3),
            floor: config.floor,
            ln_floor: config.floor.ln(),
            nearest_db: f32::INFINITY,
            votes: vec![0.0; n_cells],
        })
    }

    /// Loads the configured survey and builds from all of it.
    pub(crate) fn load(
        config: &KnnConfig,
        site: &Arc<Site>,
        anchors: &[String],
        tracker: &TrackerConfig,
        missing_dbm: f32,
    ) -> Result<Box<dyn Localizer>, LocalizerError> {
        let path = config.survey.as_ref().ok_or(LocalizerError::NoSurvey)?;
        let survey = Survey::load(path, site, anchors, config.not_heard)?;
        let samples: Vec<_> = survey.samples.iter().collect();
        surveyed(config, site, tracker, &samples, missing_dbm)
    }
}

/// The vote over `samples`, its published confidence fitted on their
/// walking sessions held out in turn ([`crossval`]).
pub fn surveyed(
    config: &KnnConfig,
    site: &Arc<Site>,
    tracker: &TrackerConfig,
    samples: &[&Sample],
    missing_dbm: f32,
) -> Result<Box<dyn Localizer>, LocalizerError> {
    let held_out = crossval::choose(
        &[()],
        Folds::EachSession,
        site,
        tracker,
        samples,
        missing_dbm,
        |(), rows| Knn::new(config, site, rows, missing_dbm),
    )?;
    Ok(Box::new(Mapped::new(
        Knn::new(config, site, samples, missing_dbm)?,
        held_out.confidence,
    )))
}

impl Knn {
    /// Whether the fingerprint of the last [`Localizer::log_likelihood`]
    /// call is one the survey recorded: a row within
    /// [`FAMILIAR_BANDWIDTHS`] kernel widths of it.
    pub(crate) fn familiar(&self) -> bool {
        self.nearest_db * self.inv_bandwidth <= FAMILIAR_BANDWIDTHS
    }

    /// The L1 distance from `rssi` (the anchors flagged in `heard` heard)
    /// to every fingerprint, into `distance`: over the heard anchors'
    /// postings where that is exact and cheaper, else over every anchor.
    fn measure_any(&mut self, rssi: &[f32], heard: &[bool]) {
        if !self.measure_heard(rssi, heard) {
            self.measure(rssi);
        }
    }

    /// The distances as the distance to silence plus, for each heard
    /// anchor, what hearing it changes for the fingerprints that heard it
    /// too; the rest change by the same amount. Only where that gives the
    /// very numbers [`Knn::measure`] does (every value a whole number of dB:
    /// integer sums are exact in any order, so the same rows tie), and
    /// where the heard anchors' postings are fewer than the full pass's
    /// work; false otherwise, nothing measured.
    fn measure_heard(&mut self, rssi: &[f32], heard: &[bool]) -> bool {
        let n = self.rows_of.len();
        let whole = |v: f32| v.fract() == 0.0 && v.abs() < WHOLE_DB_EXACT;
        // Work counted in the full pass's lanes (one per fingerprint and
        // anchor, vectorised): the postings' pass copies and adds once over
        // the fingerprints, alike, and updates each posting on its own, a
        // scattered update costing about a vector step of [`BLOCK`] lanes.
        let mut silent = None;
        let mut work = 2 * n;
        for (a, (&r, &h)) in rssi.iter().zip(heard).enumerate() {
            if h {
                work += self.postings[a].len() * BLOCK;
            } else if *silent.get_or_insert(r) != r {
                return false;
            }
        }
        let full = n * self.n_anchors;
        let silent = silent.unwrap_or(self.not_heard);
        let heard_whole = rssi.iter().zip(heard).all(|(&r, &h)| !h || whole(r));
        if !(self.whole_db && whole(silent) && heard_whole) || work >= full {
            return false;
        }
        if self.silence.0 != silent.to_bits() {
            // Every anchor at `silent`: the unheard ones of a fingerprint
            // are all `not_heard`, the heard ones in its postings.
            let unheard = (silent - self.not_heard).abs();
            let mut base = vec![self.n_anchors as f32 * unheard; n];
            for &(f, v) in self.postings.iter().flatten() {
                base[f as usize] += (silent - v).abs() - unheard;
            }
            self.silence = (silent.to_bits(), base);
        }
        let distance = &mut self.distance[..n];
        // What hearing the anchors adds to every fingerprint that did not
        // hear them, summed, and what differs for those that did.
        let mut everyone = 0.0;
        distance.copy_from_slice(&self.silence.1);
        for (a, (&x, _)) in rssi.iter().zip(heard).enumerate().filter(|(_, (_, h))| **h) {
            let unheard = (x - self.not_heard).abs() - (silent - self.not_heard).abs();
            everyone += unheard;
            for &(f, v) in &self.postings[a] {
                distance[f as usize] += (x - v).abs() - (silent - v).abs() - unheard;
            }
        }
        distance.iter_mut().for_each(|d| *d += everyone);
        true
    }

    /// The L1 distance from `rssi` to every fingerprint, into `distance`.
    fn measure(&mut self, rssi: &[f32]) {
        let stride = self.stride;
        for (b, distance) in self.distance.chunks_exact_mut(BLOCK).enumerate() {
            let at = b * BLOCK;
            let mut sum = [0.0f32; BLOCK];
            for first in 0..LANES.min(self.n_anchors) {
                let mut lane = [0.0f32; BLOCK];
                for a in (first..self.n_anchors).step_by(LANES) {
                    let q = rssi[a];
                    let column = &self.columns[a * stride + at..][..BLOCK];
                    for (l, &r) in lane.iter_mut().zip(column) {
                        *l += (r - q).abs();
                    }
                }
                for (s, l) in sum.iter_mut().zip(&lane) {
                    *s += l;
                }
            }
            distance.copy_from_slice(&sum);
        }
    }
}

impl Localizer for Knn {
    fn method(&self) -> &'static str {
        "knn"
    }

    fn log_likelihood(&mut self, rssi: &[f32], heard: &[bool], out: &mut [f32]) {
        debug_assert_eq!(rssi.len(), self.n_anchors);
        self.measure_any(rssi, heard);
        let n = self.rows_of.len();
        // The k nearest rows lie among the k nearest fingerprints (each
        // holds at least one row): those are ranked, the rest only checked
        // for ties with the k-th row.
        self.ranked.clear();
        self.ranked.extend(
            (0u32..)
                .zip(&self.distance[..n])
                .map(|(f, d)| (u64::from(d.to_bits()) << 32) | u64::from(f)),
        );
        let first = self.k.min(n);
        if first < n {
            self.ranked.select_nth_unstable(first - 1);
            self.ranked.truncate(first);
        }
        self.ranked.sort_unstable();
        let distance_of = |key: u64| f32::from_bits((key >> 32) as u32);
        let nearest = distance_of(self.ranked[0]);
        self.nearest_db = nearest;
        let k = (self.k as f32).min(self.rows);
        let mut taken = 0.0;
        let last = distance_of(self.ranked[self.ranked.len() - 1]);
        let mut kth = last;
        for &key in &self.ranked {
            taken += self.rows_of[key as u32 as usize];
            if taken >= k {
                kth = distance_of(key);
                break;
            }
        }
        // Every fingerprint within the k-th row's distance votes. Those
        // closer than the farthest ranked one are all ranked; rows tied
        // with it may lie beyond.
        self.voters.clear();
        if kth < last || self.ranked.len() == n {
            let ranked = self.ranked.iter();
            let within = ranked.filter(|&&key| distance_of(key) <= kth);
            self.voters.extend(within.map(|&key| key as u32));
            self.voters.sort_unstable();
        } else {
            let within = (0u32..)
                .zip(&self.distance[..n])
                .filter(|&(_, &d)| d <= kth);
            self.voters.extend(within.map(|(f, _)| f));
        }
        // Rows tied with the k-th share its remaining places equally, so the
        // vote does not depend on the order of the survey's rows (real surveys
        // repeat fingerprints: dozens of rows hear one beacon at one level).
        let (mut closer, mut tied) = (0.0, 0.0);
        for &f in &self.voters {
            let rows = self.rows_of[f as usize];
            if self.distance[f as usize] < kth {
                closer += rows;
            } else {
                tied += rows;
            }
        }
        let tie_share = (k - closer) / tied;
        self.votes.fill(0.0);
        // In the survey's order, so the sums do not depend on the ranking.
        for &f in &self.voters {
            let f = f as usize;
            let d = self.distance[f];
            let share = if d < kth { 1.0 } else { tie_share };
            // Relative to the nearest row, so the kernel never underflows to 0.
            let weight = share * (-(d - nearest) * self.inv_bandwidth).exp();
            let cells = self.member_start[f] as usize..self.member_start[f + 1] as usize;
            for &(cell, rows) in &self.members[cells] {
                self.votes[cell as usize] += weight * rows;
            }
        }
        let mut best = 0.0f32;
        for (v, inv) in self.votes.iter_mut().zip(&self.inv_count) {
            *v *= inv;
            best = best.max(*v);
        }
        for (o, &v) in out.iter_mut().zip(&self.votes) {
            // Most cells have no vote: their logarithm is known.
            *o = if v == 0.0 {
                self.ln_floor
            } else {
                (v / best).max(self.floor).ln()
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A floor of 40 anchors and 300 fingerprints, each hearing a few.
    fn many_anchors() -> (Arc<Site>, Knn) {
        let site = Arc::new(Site::of_map(&"##########\n".repeat(10)));
        let cells = site.open_cells();
        let samples: Vec<Sample> = (0..300usize)
            .map(|i| Sample {
                cell: cells[i % cells.len()],
                at: [0.0, 0.0],
                t: None,
                rssi: (0..40usize)
                    .map(|a| ((i * 7 + a * 13) % 9 == 0).then(|| -50 - ((i + a) % 40) as i16))
                    .collect(),
            })
            .collect();
        let rows: Vec<&Sample> = samples.iter().collect();
        let knn = Knn::new(&KnnConfig::default(), &site, &rows, -105.0).unwrap();
        (site, knn)
    }

    /// Over the heard anchors' postings, the distances are the full pass's
    /// to the bit, for windows hearing one anchor, a few and many, and
    /// with "not heard" other than the survey's; a window the postings
    /// cannot measure exactly (half a dB) is left to the full pass.
    #[test]
    fn distances_over_the_heard_anchors_are_the_full_pass_s() {
        let (_, mut knn) = many_anchors();
        let n = knn.rows_of.len();
        // (not heard, every how many anchors heard, measured over postings:
        // hearing every anchor costs more than the full pass).
        for (silent, heard_every, cheaper) in [
            (-105.0, 40, true),
            (-105.0, 7, true),
            (-105.0, 4, true),
            (-110.0, 5, true),
            (-105.0, 1, false),
        ] {
            let heard: Vec<bool> = (0..40).map(|a| a % heard_every == 0).collect();
            let rssi: Vec<f32> = (0..40)
                .map(|a| if heard[a] { -60.0 - a as f32 } else { silent })
                .collect();
            knn.measure(&rssi);
            let full = knn.distance[..n].to_vec();
            let listed = knn.measure_heard(&rssi, &heard);
            assert_eq!(listed, cheaper, "every {heard_every}");
            if listed {
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&knn.distance[..n]), bits(&full), "every {heard_every}");
            }
        }
        let heard: Vec<bool> = (0..40).map(|a| a == 5).collect();
        let mut rssi = vec![-105.0; 40];
        rssi[5] = -60.5;
        assert!(!knn.measure_heard(&rssi, &heard));
    }
}
