//! Tracking: one belief per entity over the site's walkable cells, fused from
//! the localizer's per-cell likelihoods and a motion model.
//!
//! The `hmm` tracker is a forward filter. Between two fixes `dt` seconds apart a
//! person walks at most `max_speed_mps · dt` metres, through walkable cells only;
//! the prediction step spreads the belief that many steps over the access graph
//! (a lazy random walk that never crosses a blocked cell or cuts its corner), so
//! a fix on the far side of a wall or across the building in two seconds gets no
//! prior mass. The `none` tracker is the plain per-window argmax.
//!
//! An entity expected to walk somewhere (a walker guided along a route,
//! [`ExpectedWalk`]) also gets a second, small belief moved that way before
//! the same evidence weighs it ([`Tracker::update_walking`]); its fix stays
//! the first belief's.

use foldhash::HashMap;
use std::collections::VecDeque;
use std::sync::Arc;

use serde::Deserialize;

use super::bounds::Bounds;
use crate::plan::Connectivity;
use crate::site::{Cell, Site};

/// Forgotten entities kept for [`Tracker::take_evicted`] at most; a caller
/// that never takes them loses the oldest.
const MAX_EVICTED_KEPT: usize = 65_536;

/// `[tracker]` in the gateway config.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerConfig {
    pub kind: TrackerKind,
    /// Fastest plausible walking speed, metres per second.
    pub max_speed_mps: f64,
    /// Probability of staying in the cell in each step of the motion model;
    /// the rest is shared equally by the allowed moves. People pause often.
    pub stay_probability: f32,
    /// Weight of the localizer's log-likelihood against the motion prior; below
    /// 1 when the localizer is over-confident (anchors are not independent).
    pub likelihood_weight: f32,
    /// Probability mass spread uniformly over the site each step, so that a
    /// track that went wrong can recover.
    pub recovery: f32,
    /// Gaps longer than this (seconds) restart the track from the likelihood.
    pub reset_after_s: f64,
    /// Which cell of the belief is reported.
    pub estimate: Estimate,
}

/// How a belief becomes one reported cell.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Estimate {
    /// The most probable cell.
    Mode,
    /// The cell with the least expected distance to the true one: fewer exact
    /// hits than `mode` when the belief is split, but smaller errors.
    Median,
}

impl TrackerConfig {
    /// Checks what serde cannot: a message naming the key and what to do.
    pub fn validate(&self) -> Result<(), String> {
        if self.max_speed_mps.is_nan() || self.max_speed_mps <= 0.0 {
            return Err("[tracker] `max_speed_mps` must be positive".into());
        }
        if !(0.0..=1.0).contains(&self.stay_probability) {
            return Err("[tracker] `stay_probability` must be between 0 and 1".into());
        }
        Ok(())
    }
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            kind: TrackerKind::Hmm,
            max_speed_mps: 1.5,
            stay_probability: 0.9,
            likelihood_weight: 1.0,
            recovery: 1e-3,
            reset_after_s: 30.0,
            estimate: Estimate::Median,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum TrackerKind {
    None,
    Hmm,
}

/// A position estimate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Fix {
    pub cell: Cell,
    /// Posterior probability of being within one cell of `cell`.
    pub confidence: f32,
    /// The belief's mean, in grid coordinates (cell centres at + 0.5).
    pub mean: [f32; 2],
}

/// Where an entity is expected to have walked since its last window: of
/// the belief in each `from` cell, `share` moves to its `to` cell before
/// the rest spreads as anyone's does. A walker being guided along a route
/// walks it (`crate::guide`): without this the lazy random walk, which
/// would rather they stood still, holds them back for fixes after they set
/// off and then lets them jump (docs/guidance.md, "Measured").
pub struct ExpectedWalk {
    pub(crate) moves: Vec<(Cell, Cell)>,
    pub(crate) share: f32,
}

struct Track {
    t: f64,
    /// The belief over the open cells, its heaviest cells only between
    /// fixes ([`Sparse::pack_heaviest`]); empty before the first.
    belief: Sparse<f32>,
    /// The belief given an [`ExpectedWalk`], while there is one.
    walking: Sparse,
    fix: Fix,
}

impl Track {
    /// A track with no belief yet (its first window starts it).
    fn new() -> Self {
        Track {
            t: f64::NEG_INFINITY,
            belief: Sparse::default(),
            walking: Sparse::default(),
            fix: Fix {
                cell: Cell::new(0, 0),
                confidence: 0.0,
                mean: [0.5, 0.5],
            },
        }
    }
}

/// The tracks of all entities on one site.
pub struct Tracker {
    config: TrackerConfig,
    site: Arc<Site>,
    /// For each open cell: itself first, then the open cells one allowed step away.
    neighbours: Vec<Vec<u32>>,
    /// The same steps, as what flows into each cell.
    inflows: Inflows,
    tracks: HashMap<Arc<str>, Track>,
    scratch: FilterScratch,
    /// Room for the step of a walking belief.
    walked: WalkStep,
    bounds: Bounds,
    /// Entities forgotten since the last [`Tracker::take_evicted`].
    evicted: VecDeque<Arc<str>>,
}

impl Tracker {
    pub fn new(config: TrackerConfig, site: Arc<Site>) -> Self {
        let neighbours = open_neighbours(&site);
        let inflows = Inflows::new(&neighbours, config.stay_probability);
        Tracker {
            config,
            site,
            neighbours,
            inflows,
            tracks: HashMap::default(),
            scratch: FilterScratch::default(),
            walked: WalkStep::default(),
            bounds: Bounds::default(),
            evicted: VecDeque::new(),
        }
    }

    /// Keeps at most `max` tracks, and none without a window for `idle_s`
    /// seconds (see [`Bounds`]).
    pub(crate) fn bound(mut self, max: usize, idle_s: f64) -> Self {
        self.bounds = Bounds::new(max, idle_s);
        self
    }

    /// Tracks forgotten since start.
    pub(crate) fn evicted_count(&self) -> u64 {
        self.bounds.evicted()
    }

    /// The entities forgotten since the last call (whoever announced them
    /// can withdraw them).
    pub(crate) fn take_evicted(&mut self) -> Vec<Arc<str>> {
        std::mem::take(&mut self.evicted).into()
    }

    /// The latest fix of an entity.
    pub(crate) fn last_fix(&self, entity: &str) -> Option<Fix> {
        self.tracks.get(entity).map(|t| t.fix)
    }

    pub(crate) fn len(&self) -> usize {
        self.tracks.len()
    }

    /// After a reload: takes over the tracks of `old`, the tracker being
    /// replaced, so devices keep their place (and a route request its
    /// `from`) instead of starting afresh. On the same grid the tracks move
    /// as they are. On another, each restarts from its last fix's place in
    /// metres: all its belief on the new site's open cell there, its time
    /// and confidence kept; a track whose place the new site does not have
    /// (off its grid, or not walkable) is forgotten, and reported so with
    /// those `old` forgot and nobody took yet ([`Tracker::take_evicted`]).
    /// Returns how many were kept.
    pub(crate) fn take_over(&mut self, old: &mut Tracker) -> usize {
        let tracks = std::mem::take(&mut old.tracks);
        self.evicted.extend(old.evicted.drain(..));
        if self.site.same_grid(&old.site) {
            self.tracks = tracks;
            return self.tracks.len();
        }
        for (id, track) in tracks {
            let place = old.site.world_of_cell(track.fix.cell);
            let index = self
                .site
                .cell_of_world(place)
                .and_then(|cell| Some((cell, self.site.open_index(cell)?)));
            let Some((cell, index)) = index else {
                if self.evicted.len() >= MAX_EVICTED_KEPT {
                    self.evicted.pop_front();
                }
                self.evicted.push_back(id);
                continue;
            };
            let belief = Sparse::one(index as u32);
            let fix = Fix {
                cell,
                confidence: track.fix.confidence,
                mean: [f32::from(cell.x) + 0.5, f32::from(cell.y) + 0.5],
            };
            let moved = Track {
                t: track.t,
                belief,
                walking: Sparse::default(),
                fix,
            };
            self.tracks.insert(id, moved);
        }
        self.tracks.len()
    }

    /// Heap bytes of an entity's belief given its expected walk (none
    /// while it has none).
    pub(crate) fn walking_bytes(&self, entity: &str) -> usize {
        self.tracks
            .get(entity)
            .map_or(0, |t| t.walking.heap_bytes())
    }

    /// Folds one window's log-likelihoods (one per open cell) into the entity's
    /// track and returns the new fix.
    pub fn update(&mut self, entity: &Arc<str>, t: f64, log_likelihood: &[f32]) -> Fix {
        self.update_walking(entity, t, log_likelihood, None).0
    }

    /// [`Tracker::update`] for an entity expected to have walked `walk`
    /// since its last window (when it has a track to move), which also
    /// returns where, given that walk, it is on average (grid coordinates,
    /// as [`Fix::mean`]): the mean of a second belief, started from the
    /// track's own and moved by the walk before the same evidence weighs
    /// it. The fix itself stays the track's, the walk aside: whether the
    /// entity still walks it is for the fixes to show.
    pub fn update_walking(
        &mut self,
        entity: &Arc<str>,
        t: f64,
        log_likelihood: &[f32],
        walk: Option<&ExpectedWalk>,
    ) -> (Fix, Option<[f32; 2]>) {
        self.make_room(entity, t);
        let model = MotionModel {
            config: &self.config,
            neighbours: &self.neighbours,
            inflows: &self.inflows,
            cell_m: self.site.cell_m,
        };
        let track = self.tracks.entry(entity.clone()).or_insert_with(Track::new);
        let mut likelihood = std::mem::take(&mut self.scratch.likelihood);
        model.likelihood(log_likelihood, &mut likelihood);
        let steps = model.steps(t - track.t);
        let walked_mean = match (walk, steps) {
            (Some(walk), Some(steps)) => {
                if track.walking.is_empty() {
                    // Starts where the track's belief is.
                    track.walking.pack(track.belief.iter());
                }
                let mean = self.walked.step(
                    &self.site,
                    &self.neighbours,
                    (self.config.stay_probability, self.config.recovery),
                    &mut track.walking,
                    walk,
                    steps,
                    &likelihood,
                );
                if mean.is_none() {
                    // The evidence denies the walk everywhere: start again
                    // from the track's belief at the next fix.
                    track.walking = Sparse::default();
                }
                mean
            }
            _ => {
                // Nobody walks this one: its memory goes.
                track.walking = Sparse::default();
                None
            }
        };
        track.t = t;
        track.fix = model.fold(
            &self.site,
            &mut track.belief,
            steps,
            &likelihood,
            &mut self.scratch,
        );
        self.scratch.likelihood = likelihood;
        (track.fix, walked_mean)
    }

    /// Starts (or restarts) the entity's track as it enters this tracker's
    /// floor (at a connector, from another floor's tracker): a prior spread
    /// evenly over the `prior` cells that are open here (none: uniform, as
    /// a new track), weighed by one window's log-likelihoods as
    /// [`Tracker::update`] weighs its prior. Counts towards the bounds as a
    /// new track does.
    pub fn enter(
        &mut self,
        entity: &Arc<str>,
        t: f64,
        prior: &[Cell],
        log_likelihood: &[f32],
    ) -> Fix {
        self.make_room(entity, t);
        let model = MotionModel {
            config: &self.config,
            neighbours: &self.neighbours,
            inflows: &self.inflows,
            cell_m: self.site.cell_m,
        };
        let mut cells: Vec<u32> = prior
            .iter()
            .filter_map(|&c| self.site.open_index(c))
            .map(|i| i as u32)
            .collect();
        cells.sort_unstable();
        cells.dedup();
        let share = 1.0 / cells.len().max(1) as f32;
        let mut track = Track::new();
        track.belief.mass = vec![share; cells.len()];
        track.belief.cells = cells;
        track.t = t;
        let mut likelihood = std::mem::take(&mut self.scratch.likelihood);
        model.likelihood(log_likelihood, &mut likelihood);
        // No motion: the prior is where the entity is now. Without tracking
        // the evidence alone decides, as ever.
        let steps = (self.config.kind == TrackerKind::Hmm).then_some(0);
        track.fix = model.fold(
            &self.site,
            &mut track.belief,
            steps,
            &likelihood,
            &mut self.scratch,
        );
        self.scratch.likelihood = likelihood;
        let fix = track.fix;
        self.tracks.insert(entity.clone(), track);
        fix
    }

    /// Drops the entity's track without reporting it evicted (it moved to
    /// another floor's tracker); whether it had one.
    pub fn forget(&mut self, entity: &str) -> bool {
        self.tracks.remove(entity).is_some()
    }

    /// Heap bytes of all tracks' beliefs as kept between fixes (and of
    /// their walking beliefs).
    #[cfg(test)]
    pub(crate) fn belief_bytes(&self) -> usize {
        self.tracks
            .values()
            .map(|t| t.belief.heap_bytes() + t.walking.heap_bytes())
            .sum()
    }

    /// Room for the entity's track at `t`: idle tracks go, and the least
    /// recently updated when the tracker is full and it has none.
    fn make_room(&mut self, entity: &Arc<str>, t: f64) {
        let full = self.tracks.len() >= self.bounds.max() && !self.tracks.contains_key(entity);
        let evicted = &mut self.evicted;
        self.bounds.make_room(
            &mut self.tracks,
            t,
            full,
            |track| track.t,
            |id| {
                if evicted.len() >= MAX_EVICTED_KEPT {
                    evicted.pop_front();
                }
                evicted.push_back(id.clone());
            },
        );
    }

    /// Fixed-lag smoothing of one recorded trajectory, given as (time,
    /// log-likelihoods) per window in time order: each fix also uses the
    /// evidence of up to `lag` later windows (the forward filter of
    /// [`Tracker::update`], then a backward pass over the lag). A live gateway
    /// would publish each such fix `lag` windows late; recorded walks can
    /// afford it. With `lag` 0 this is the online filter.
    pub fn smooth(&self, windows: &[(f64, Vec<f32>)], lag: usize) -> Vec<Fix> {
        let model = self.model();
        let forward = model.forward(windows);
        let n = windows.len();
        let mut scratch = Vec::new();
        let mut median = MedianScratch::default();
        (0..n)
            .map(|k| {
                let mut backward = vec![1.0f32; forward.filtered[k].len()];
                for j in (k + 1..=(k + lag).min(n.saturating_sub(1))).rev() {
                    forward.pull_back_through(&model, j, &mut backward, &mut scratch);
                }
                let smoothed = forward.combine(k, &backward);
                estimate(self.config.estimate, &self.site, &smoothed, &mut median)
            })
            .collect()
    }

    /// The belief over open cells at every window of one recorded trajectory,
    /// given all of it (forward-backward): what calibration weighs each
    /// window's evidence by when no position is known.
    pub(crate) fn posteriors(&self, windows: &[(f64, Vec<f32>)]) -> Vec<Vec<f32>> {
        let model = self.model();
        let forward = model.forward(windows);
        let n = windows.len();
        let mut out = vec![Vec::new(); n];
        let mut backward = vec![1.0f32; self.neighbours.len()];
        let mut scratch = Vec::new();
        for k in (0..n).rev() {
            out[k] = forward.combine(k, &backward);
            if k > 0 {
                forward.pull_back_through(&model, k, &mut backward, &mut scratch);
            }
        }
        out
    }

    /// The log-likelihood of one recorded trajectory's readings under the
    /// motion model, log p(y₁ … yₙ), up to a constant that does not depend on
    /// the localizer: what calibration compares radio models by on windows
    /// it held out. The evidence is weighed at full strength whatever
    /// `likelihood_weight` says, since a tempered likelihood is not a
    /// probability of the readings and would favour wider models.
    pub(crate) fn log_evidence(&self, windows: &[(f64, Vec<f32>)]) -> f64 {
        let config = TrackerConfig {
            likelihood_weight: 1.0,
            ..self.config.clone()
        };
        let model = MotionModel {
            config: &config,
            ..self.model()
        };
        let (mut belief, mut likelihood) = (Vec::new(), Vec::new());
        let mut scratch = FilterScratch::default();
        let mut last_t = f64::NEG_INFINITY;
        let mut total = 0.0;
        for (t, log_likelihood) in windows {
            // The likelihood is relative to its peak: the peak comes back here.
            let peak = log_likelihood
                .iter()
                .copied()
                .fold(f32::NEG_INFINITY, f32::max);
            model.likelihood(log_likelihood, &mut likelihood);
            let steps = model.steps(t - last_t);
            total += f64::from(peak) + model.filter(&mut belief, steps, &likelihood, &mut scratch);
            last_t = *t;
        }
        total
    }

    fn model(&self) -> MotionModel<'_> {
        MotionModel {
            config: &self.config,
            neighbours: &self.neighbours,
            inflows: &self.inflows,
            cell_m: self.site.cell_m,
        }
    }
}

/// The forward pass over one trajectory, kept for a backward pass.
struct Forward {
    filtered: Vec<Vec<f32>>,
    likelihoods: Vec<Vec<f32>>,
    /// Motion steps into each window; `None` where the track restarted.
    steps: Vec<Option<usize>>,
}

impl Forward {
    /// Moves a backward message from window `j` to window `j − 1`.
    fn pull_back_through(
        &self,
        model: &MotionModel,
        j: usize,
        backward: &mut Vec<f32>,
        scratch: &mut Vec<f32>,
    ) {
        let Some(s) = self.steps[j] else {
            // The track restarted at j: nothing after it informs j − 1.
            backward.fill(1.0);
            return;
        };
        for (b, l) in backward.iter_mut().zip(&self.likelihoods[j]) {
            *b *= l;
        }
        model.pull_back(backward, s, scratch);
    }

    /// The smoothed belief at window `k` given its backward message.
    fn combine(&self, k: usize, backward: &[f32]) -> Vec<f32> {
        let mut smoothed: Vec<f32> = self.filtered[k]
            .iter()
            .zip(backward)
            .map(|(a, b)| a * b)
            .collect();
        if normalize(&mut smoothed).is_none() {
            smoothed.clone_from(&self.filtered[k]);
        }
        smoothed
    }
}

/// The tracker's hidden Markov model: how far belief spreads between windows,
/// and how evidence is weighed.
struct MotionModel<'a> {
    config: &'a TrackerConfig,
    neighbours: &'a [Vec<u32>],
    inflows: &'a Inflows,
    cell_m: f64,
}

/// [`MotionModel::filter`]'s buffers, kept by the tracker between fixes so
/// that a fix allocates nothing.
#[derive(Default)]
struct FilterScratch {
    /// The belief one motion step on.
    next: Vec<f32>,
    /// What each cell passes on and keeps in a step ([`Inflows::step`]).
    outflow: Vec<f32>,
    /// The relative likelihood of the fix being filtered.
    likelihood: Vec<f32>,
    /// The belief of the track being filtered, over every open cell.
    belief: Vec<f32>,
    /// The cells that may hold mass, before and after a motion step
    /// ([`Inflows::step_from`]), and which are listed in the latter.
    support: Vec<u32>,
    next_support: Vec<u32>,
    listed: Vec<bool>,
    pack: PackScratch,
    median: MedianScratch,
}

impl MotionModel<'_> {
    /// Relative likelihood per cell (max 1), weighted, into `out`.
    fn likelihood(&self, log_likelihood: &[f32], out: &mut Vec<f32>) {
        let max_ll = lane_max(log_likelihood, f32::NEG_INFINITY);
        let weight = self.config.likelihood_weight;
        out.clear();
        out.resize(log_likelihood.len(), 0.0);
        // Localizers such as k-NN give most cells one value (their floor):
        // a block of cells that all hold it takes one exponential.
        for (to, from) in out.chunks_mut(LANES).zip(log_likelihood.chunks(LANES)) {
            let first = from[0].to_bits();
            if from.iter().all(|ll| ll.to_bits() == first) {
                to.fill(exp_nonpositive((from[0] - max_ll) * weight));
            } else {
                for (l, &ll) in to.iter_mut().zip(from) {
                    *l = exp_nonpositive((ll - max_ll) * weight);
                }
            }
        }
    }

    /// The forward filter over a whole trajectory.
    fn forward(&self, windows: &[(f64, Vec<f32>)]) -> Forward {
        let mut scratch = FilterScratch::default();
        let mut forward = Forward {
            filtered: Vec::with_capacity(windows.len()),
            likelihoods: Vec::with_capacity(windows.len()),
            steps: Vec::with_capacity(windows.len()),
        };
        let mut belief = Vec::new();
        let mut last_t = f64::NEG_INFINITY;
        for (t, log_likelihood) in windows {
            let mut likelihood = Vec::new();
            self.likelihood(log_likelihood, &mut likelihood);
            let s = self.steps(t - last_t);
            self.filter(&mut belief, s, &likelihood, &mut scratch);
            forward.filtered.push(belief.clone());
            forward.likelihoods.push(likelihood);
            forward.steps.push(s);
            last_t = *t;
        }
        forward
    }

    /// Motion steps for a gap of `dt` seconds since the last window, or `None`
    /// when the track restarts (no tracking, first window, a long gap, or time
    /// running backwards).
    fn steps(&self, dt: f64) -> Option<usize> {
        let continues =
            self.config.kind == TrackerKind::Hmm && (0.0..=self.config.reset_after_s).contains(&dt);
        // As far as one can walk in the gap, at least one step.
        continues.then(|| ((self.config.max_speed_mps * dt / self.cell_m).ceil() as usize).max(1))
    }

    /// One forward step: predict `steps` moves, then weigh by the evidence. A
    /// restart, or evidence that contradicts the prior everywhere, starts from
    /// the evidence alone (a uniform prior). Returns the log of how well the
    /// prior foresaw the evidence, Σ prior·likelihood, in the likelihood's
    /// relative units: [`Tracker::log_evidence`] sums it.
    fn filter(
        &self,
        belief: &mut Vec<f32>,
        steps: Option<usize>,
        likelihood: &[f32],
        scratch: &mut FilterScratch,
    ) -> f64 {
        self.filter_from(belief, None, steps, likelihood, scratch)
    }

    /// [`MotionModel::filter`] of a belief whose mass lies on the cells of
    /// `support` alone, when given: its motion steps visit those cells and
    /// the ones they reach, not the whole floor (the same sums, in the same
    /// order, so the same belief to the bit).
    fn filter_from(
        &self,
        belief: &mut Vec<f32>,
        support: Option<&[u32]>,
        steps: Option<usize>,
        likelihood: &[f32],
        scratch: &mut FilterScratch,
    ) -> f64 {
        let n = self.neighbours.len();
        if let Some(steps) = steps
            && belief.len() == n
        {
            // Reaching a cell costs its neighbours' visits: worth listing
            // while the cells reached stay a small part of the floor.
            match support.filter(|cells| cells.len() * SPARSE_STEP_SHARE < n) {
                Some(cells) => {
                    scratch.support.clear();
                    scratch.support.extend_from_slice(cells);
                    scratch.next.clear();
                    scratch.next.resize(n, 0.0);
                    scratch.outflow.clear();
                    scratch.outflow.resize(2 * n + 1, 0.0);
                    scratch.listed.clear();
                    scratch.listed.resize(n, false);
                    for _ in 0..steps {
                        self.inflows.step_from(
                            self.neighbours,
                            belief,
                            &scratch.support,
                            &mut scratch.next_support,
                            &mut scratch.listed,
                            &mut scratch.outflow,
                            &mut scratch.next,
                        );
                        std::mem::swap(belief, &mut scratch.next);
                        std::mem::swap(&mut scratch.support, &mut scratch.next_support);
                    }
                }
                None => {
                    for _ in 0..steps {
                        self.inflows
                            .step(belief, &mut scratch.outflow, &mut scratch.next);
                        std::mem::swap(belief, &mut scratch.next);
                    }
                }
            }
            let recovery = self.config.recovery;
            let floor = recovery / belief.len() as f32;
            for (b, l) in belief.iter_mut().zip(likelihood) {
                *b = (*b * (1.0 - recovery) + floor) * l;
            }
            if let Some(foreseen) = normalize(belief) {
                return f64::from(foreseen).ln();
            }
        }
        belief.clear();
        belief.extend_from_slice(likelihood);
        normalize(belief).map_or(f64::NEG_INFINITY, |sum| {
            (f64::from(sum) / likelihood.len() as f64).ln()
        })
    }

    /// [`MotionModel::filter`] of a track's belief as kept between fixes:
    /// unpacked into the scratch, filtered, estimated (the fix returned)
    /// and packed again.
    fn fold(
        &self,
        site: &Site,
        belief: &mut Sparse<f32>,
        steps: Option<usize>,
        likelihood: &[f32],
        scratch: &mut FilterScratch,
    ) -> Fix {
        let mut dense = std::mem::take(&mut scratch.belief);
        belief.unpack(self.neighbours.len(), &mut dense);
        let support = (!belief.cells.is_empty()).then_some(&belief.cells[..]);
        self.filter_from(&mut dense, support, steps, likelihood, scratch);
        let fix = estimate(self.config.estimate, site, &dense, &mut scratch.median);
        belief.pack_heaviest(&dense, &mut scratch.pack);
        scratch.belief = dense;
        fix
    }

    /// The backward step of [`MotionModel::filter`]'s prediction: for each cell,
    /// the expected `message` one window later, over `steps` moves and the
    /// recovery mass.
    fn pull_back(&self, message: &mut Vec<f32>, steps: usize, scratch: &mut Vec<f32>) {
        let stay = self.config.stay_probability;
        for _ in 0..steps {
            scratch.clear();
            scratch.extend(self.neighbours.iter().enumerate().map(|(i, n)| {
                let moves = &n[1..];
                if moves.is_empty() {
                    message[i]
                } else {
                    let away: f32 = moves.iter().map(|&j| message[j as usize]).sum();
                    stay * message[i] + (1.0 - stay) * away / moves.len() as f32
                }
            }));
            std::mem::swap(message, scratch);
        }
        let recovery = self.config.recovery;
        let mean = message.iter().sum::<f32>() / message.len() as f32;
        let peak = message
            .iter()
            .copied()
            .fold(0.0, f32::max)
            .max(f32::MIN_POSITIVE);
        for m in message.iter_mut() {
            // Rescaled by the peak: only ratios matter, and this keeps long
            // lags from underflowing.
            *m = ((1.0 - recovery) * *m + recovery * mean) / peak;
        }
    }
}

/// For each open cell (by open index): itself first, then the open cells
/// one allowed step away.
pub(crate) fn open_neighbours(site: &Site) -> Vec<Vec<u32>> {
    site.open_cells()
        .iter()
        .map(|&c| {
            let mut n = vec![site.open_index(c).expect("open") as u32];
            for dy in -1i16..=1 {
                for dx in -1i16..=1 {
                    let (Some(x), Some(y)) =
                        (c.x.checked_add_signed(dx), c.y.checked_add_signed(dy))
                    else {
                        continue;
                    };
                    let next = Cell::new(x, y);
                    if Connectivity::Eight.step_ok(site, c, next) {
                        n.push(site.open_index(next).expect("walkable") as u32);
                    }
                }
            }
            n
        })
        .collect()
}

/// The reported fix of a belief over the site's open cells.
fn estimate(how: Estimate, site: &Site, belief: &[f32], scratch: &mut MedianScratch) -> Fix {
    let cells = site.open_cells();
    let best = match how {
        Estimate::Mode => argmax(belief),
        Estimate::Median => spatial_median(cells, belief, scratch),
    };
    let cell = cells[best];
    Fix {
        cell,
        confidence: within_one_cell(site, cell, belief),
        mean: mean(site, (0..).zip(belief.iter().copied()))
            .unwrap_or([f32::from(cell.x) + 0.5, f32::from(cell.y) + 0.5]),
    }
}

/// A belief's mean in grid coordinates (cell centres at + 0.5), given as
/// (open cell, mass); `None` for an empty one.
fn mean(site: &Site, belief: impl Iterator<Item = (u32, f32)>) -> Option<[f32; 2]> {
    let cells = site.open_cells();
    // Summed in MEAN_LANES interleaved partial sums: over a floor of cells,
    // three chains of dependent adds would wait on each add's latency.
    let (mut sum, mut mx, mut my) = (
        [0.0f64; MEAN_LANES],
        [0.0f64; MEAN_LANES],
        [0.0f64; MEAN_LANES],
    );
    for (k, (i, b)) in belief.enumerate() {
        let lane = k % MEAN_LANES;
        let c = cells[i as usize];
        let b = f64::from(b);
        sum[lane] += b;
        mx[lane] += b * (f64::from(c.x) + 0.5);
        my[lane] += b * (f64::from(c.y) + 0.5);
    }
    let [sum, mx, my] = [sum, mx, my].map(|lanes| lanes.iter().sum::<f64>());
    (sum > 0.0).then(|| [(mx / sum) as f32, (my / sum) as f32])
}

/// Partial sums of [`mean`].
const MEAN_LANES: usize = 4;

/// Least share of its largest mass a cell of a walking belief holds to be
/// kept ([`Sparse::pack`]): less changes no mean a guide reads off it.
const KEPT_SHARE: f32 = 1e-4;

/// Most cells a walking belief keeps (those of the largest mass): 6 bytes
/// each, held for all of them while a device is guided (240 bytes), so a
/// guided session stays under 1 KB. A guided walker's belief is a few
/// metres of the route: tens of cells, unless the evidence is poor, when a
/// coarser mean still serves.
const MAX_KEPT: usize = 40;

/// Mass a track's belief leaves out between fixes ([`Sparse::pack_heaviest`]):
/// its lightest cells, up to this much in all. A tenth of what recovery
/// spreads over the site at every step, so the next prior hardly differs.
const DROPPED_MASS: f64 = 1e-4;

/// Cells [`Sparse::pack_heaviest`] weighs at once.
const PACK_BLOCK: usize = 16;

/// Most cells a track's belief keeps between fixes (its heaviest): 8 bytes
/// each, 32 KiB a track at most where a dense belief over a 240 × 180 m
/// floor at 1 m cells is 170 KB. Tens to hundreds of cells hold all but
/// [`DROPPED_MASS`] of a settled belief; only a diffuse one (weak
/// evidence, recovery spread everywhere) reaches this.
const MAX_TRACKED: usize = 4096;

/// How a [`Sparse`] belief stores each kept mass.
trait Mass: Copy {
    fn store(mass: f32) -> Self;
    fn load(self) -> f32;
}

/// bfloat16: the upper half of an f32 (three significant digits).
#[derive(Clone, Copy)]
struct Bf16(u16);

impl Mass for Bf16 {
    fn store(mass: f32) -> Self {
        // Rounded to nearest: beliefs are finite and non-negative.
        Bf16(((mass.to_bits() + 0x8000) >> 16) as u16)
    }

    fn load(self) -> f32 {
        f32::from_bits(u32::from(self.0) << 16)
    }
}

impl Mass for f32 {
    fn store(mass: f32) -> Self {
        mass
    }

    fn load(self) -> f32 {
        self
    }
}

/// A belief kept small, however large the site: some of its open cells and
/// their masses (the rest taken as none), or, with no cells, a mass for
/// every open cell in order. A walking belief keeps few, in bfloat16
/// ([`Sparse::pack`]); a track's belief between fixes keeps those holding
/// nearly all its mass, in full ([`Sparse::pack_heaviest`]).
struct Sparse<M = Bf16> {
    cells: Vec<u32>,
    mass: Vec<M>,
}

impl<M> Default for Sparse<M> {
    fn default() -> Self {
        Sparse {
            cells: Vec::new(),
            mass: Vec::new(),
        }
    }
}

impl<M: Mass> Sparse<M> {
    fn is_empty(&self) -> bool {
        self.mass.is_empty()
    }

    /// The kept cells and their masses.
    fn iter(&self) -> impl Iterator<Item = (u32, f32)> + Clone + '_ {
        // No cells but masses: one mass per open cell, in order.
        let every = self.cells.is_empty();
        (0..)
            .zip(&self.mass)
            .map(move |(k, &m)| (if every { k } else { self.cells[k as usize] }, m.load()))
    }

    fn heap_bytes(&self) -> usize {
        self.cells.capacity() * std::mem::size_of::<u32>()
            + self.mass.capacity() * std::mem::size_of::<M>()
    }

    /// The belief over all `n` open cells into `dense`; left empty when
    /// this is.
    fn unpack(&self, n: usize, dense: &mut Vec<f32>) {
        dense.clear();
        if self.is_empty() {
            return;
        }
        if self.cells.is_empty() {
            dense.extend(self.mass.iter().map(|&m| m.load()));
            return;
        }
        dense.resize(n, 0.0);
        for (i, b) in self.iter() {
            dense[i as usize] = b;
        }
    }
}

impl Sparse<Bf16> {
    /// Keeps `belief`, given as (open cell, mass): the cells holding at
    /// least [`KEPT_SHARE`] of its largest mass, at most [`MAX_KEPT`] of
    /// them.
    fn pack(&mut self, belief: impl Iterator<Item = (u32, f32)> + Clone) {
        let peak = belief.clone().fold(0.0, |peak, (_, b)| b.max(peak));
        let mut least = (peak * KEPT_SHARE).max(f32::MIN_POSITIVE);
        let heavy = belief.clone().map(|(_, b)| b).filter(|&b| b >= least);
        if heavy.clone().count() > MAX_KEPT {
            let mut kept: Vec<f32> = heavy.collect();
            least = *kept
                .select_nth_unstable_by(MAX_KEPT - 1, |a, b| b.total_cmp(a))
                .1;
        }
        if self.cells.capacity() == 0 {
            // Room for the most it keeps, once: the same bytes a fix later.
            self.cells.reserve_exact(MAX_KEPT);
            self.mass.reserve_exact(MAX_KEPT);
        }
        self.cells.clear();
        self.mass.clear();
        for (i, b) in belief {
            if b >= least && self.cells.len() < MAX_KEPT {
                self.cells.push(i);
                self.mass.push(Bf16::store(b));
            }
        }
    }
}

/// [`Sparse::pack_heaviest`]'s buffers, kept between fixes.
#[derive(Default)]
struct PackScratch {
    /// Per binary exponent of a mass: the mass of the cells with it, and
    /// how many they are.
    exponents: Vec<(f64, u32)>,
    /// The cells kept when more than [`MAX_TRACKED`] qualify: (open cell,
    /// mass).
    heaviest: Vec<(u32, f32)>,
}

impl Sparse<f32> {
    /// Keeps `belief`, dense over the open cells: its heaviest cells that
    /// hold all but [`DROPPED_MASS`] of it (to within a factor of two:
    /// cells are weighed by their mass's binary exponent, in one pass), at
    /// most [`MAX_TRACKED`], rescaled to sum to 1. Where that would be more
    /// than half the open cells, and on any site of at most
    /// [`MAX_TRACKED`], the whole belief as it is, a mass per open cell: no
    /// more bytes than the listed cells would take, and the dense belief
    /// bit for bit. Empty when it has no mass. Room beyond twice what it
    /// keeps is given back.
    fn pack_heaviest(&mut self, belief: &[f32], scratch: &mut PackScratch) {
        let every = |sparse: &mut Self| {
            sparse.cells.clear();
            sparse.cells.shrink_to_fit();
            sparse.mass.clear();
            sparse.mass.extend_from_slice(belief);
            sparse.mass.shrink_to_fit();
        };
        if belief.len() <= MAX_TRACKED {
            every(self);
            return;
        }
        let exponents = &mut scratch.exponents;
        exponents.clear();
        exponents.resize(256, (0.0, 0));
        let mut total = 0.0f64;
        // By blocks of cells. Most cells hold the same tiny mass (those the
        // evidence says nothing about), so most blocks' masses share one
        // exponent: such a block is summed in lanes and added to its bucket
        // at once, where a sum cell by cell would be a chain of dependent
        // adds as long as the floor. Any other block goes cell by cell.
        // (The sums' order is not one pass's, so a bucket may differ from
        // that in its last bits: the exponent chosen below moves only if a
        // sum lies that close to the threshold.)
        for block in belief.chunks(PACK_BLOCK) {
            // Positive finite masses only: the exponent is bits 23..31.
            let exponent =
                |b: f32| (b > 0.0 && b.is_finite()).then_some((b.to_bits() >> 23) as usize);
            let shared = exponent(block[0])
                .filter(|&e| e > 0 && block.iter().all(|b| (b.to_bits() >> 23) as usize == e));
            if let Some(e) = shared {
                let mut lanes = [0.0f64; 4];
                for (k, &b) in block.iter().enumerate() {
                    lanes[k % 4] += f64::from(b);
                }
                let mass: f64 = lanes.iter().sum();
                exponents[e].0 += mass;
                exponents[e].1 += block.len() as u32;
                total += mass;
                continue;
            }
            for &b in block {
                if let Some(e) = exponent(b) {
                    exponents[e].0 += f64::from(b);
                    exponents[e].1 += 1;
                    total += f64::from(b);
                }
            }
        }
        self.cells.clear();
        self.mass.clear();
        if total <= 0.0 {
            self.cells.shrink_to_fit();
            self.mass.shrink_to_fit();
            return;
        }
        // The lightest exponents whose cells hold at most DROPPED_MASS go.
        let mut dropped = 0.0;
        let mut least = 0;
        for (e, &(mass, _)) in exponents.iter().enumerate() {
            if dropped + mass > DROPPED_MASS * total {
                least = e;
                break;
            }
            dropped += mass;
        }
        let least_bits = (least as u32) << 23;
        let kept = |b: f32| b > 0.0 && b.is_finite() && b.to_bits() >= least_bits;
        let count = exponents[least..]
            .iter()
            .map(|&(_, n)| n as usize)
            .sum::<usize>();
        if 2 * count.min(MAX_TRACKED) > belief.len() {
            every(self);
            return;
        }
        if count > MAX_TRACKED {
            let heaviest = &mut scratch.heaviest;
            heaviest.clear();
            heaviest.extend((0..).zip(belief.iter().copied()).filter(|&(_, b)| kept(b)));
            heaviest.select_nth_unstable_by(MAX_TRACKED - 1, |a, b| b.1.total_cmp(&a.1));
            heaviest.truncate(MAX_TRACKED);
            heaviest.sort_unstable_by_key(|&(i, _)| i);
            self.cells.extend(heaviest.iter().map(|&(i, _)| i));
            self.mass.extend(heaviest.iter().map(|&(_, b)| b));
        } else {
            for (start, block) in (0..).step_by(PACK_BLOCK).zip(belief.chunks(PACK_BLOCK)) {
                // No bits as large as the least kept: nothing kept here.
                if block.iter().fold(0, |most, b| most.max(b.to_bits())) < least_bits {
                    continue;
                }
                for (i, &b) in (start..).zip(block) {
                    if kept(b) {
                        self.cells.push(i);
                        self.mass.push(b);
                    }
                }
            }
        }
        let sum: f32 = self.mass.iter().sum();
        self.mass.iter_mut().for_each(|m| *m /= sum);
        if self.cells.capacity() > 2 * self.cells.len() {
            self.cells.shrink_to(self.cells.len());
            self.mass.shrink_to(self.mass.len());
        }
    }

    /// All the belief in one open cell.
    fn one(cell: u32) -> Self {
        Sparse {
            cells: vec![cell],
            mass: vec![1.0],
        }
    }
}

/// One step of a walking belief, over its own cells and those it spreads
/// to only (tens, whatever the site's size), in buffers kept between
/// steps: a dense belief over the open cells that is zero but where it is
/// in use, and a mark per open cell.
#[derive(Default)]
struct WalkStep {
    now: Vec<f32>,
    next: Vec<f32>,
    marked: Vec<bool>,
    cells: Vec<u32>,
    next_cells: Vec<u32>,
    /// Mass the walk moves, as (open cell it moves to, mass).
    carried: Vec<(u32, f32)>,
}

impl WalkStep {
    /// Moves `walking` by `walk` and `steps` moves of the lazy random walk
    /// (the share of the walk first, the rest spreading), weighs it by the
    /// evidence and returns its mean; `None` when the evidence leaves it
    /// nothing.
    #[allow(clippy::too_many_arguments)]
    fn step(
        &mut self,
        site: &Site,
        neighbours: &[Vec<u32>],
        (stay, recovery): (f32, f32),
        walking: &mut Sparse,
        walk: &ExpectedWalk,
        steps: usize,
        likelihood: &[f32],
    ) -> Option<[f32; 2]> {
        let n = neighbours.len();
        for v in [&mut self.now, &mut self.next] {
            v.resize(n, 0.0);
        }
        self.marked.resize(n, false);
        self.cells.clear();
        for (i, b) in walking.iter() {
            self.now[i as usize] = b;
            self.cells.push(i);
        }
        let share = walk.share.clamp(0.0, 1.0);
        self.carried.clear();
        for &(from, to) in &walk.moves {
            let (Some(from), Some(to)) = (site.open_index(from), site.open_index(to)) else {
                continue;
            };
            let mass = self.now[from] * share;
            if mass > 0.0 {
                self.now[from] -= mass;
                self.carried.push((to as u32, mass));
            }
        }
        for _ in 0..steps {
            self.next_cells.clear();
            for &i in &self.cells {
                for &j in &neighbours[i as usize] {
                    if !std::mem::replace(&mut self.marked[j as usize], true) {
                        self.next_cells.push(j);
                    }
                }
                spread_cell(
                    &neighbours[i as usize],
                    stay,
                    std::mem::take(&mut self.now[i as usize]),
                    &mut self.next,
                );
            }
            for &j in &self.next_cells {
                self.marked[j as usize] = false;
            }
            std::mem::swap(&mut self.now, &mut self.next);
            std::mem::swap(&mut self.cells, &mut self.next_cells);
        }
        for &i in &self.cells {
            self.marked[i as usize] = true;
        }
        for &(to, mass) in &self.carried {
            if !std::mem::replace(&mut self.marked[to as usize], true) {
                self.cells.push(to);
            }
            self.now[to as usize] += mass;
        }
        for &i in &self.cells {
            self.marked[i as usize] = false;
        }
        // The recovery mass, as the tracker's own belief has (what lets
        // evidence ahead of the walk take hold): over every open cell.
        let floor = recovery / n as f32;
        let mut sum = 0.0;
        for (b, &l) in self.now.iter_mut().zip(likelihood) {
            *b = (*b * (1.0 - recovery) + floor) * l;
            sum += *b;
        }
        let now = &self.now;
        // `move`: a closure borrowing `sum` would keep it in memory, and
        // the loop above would store and reload it at every cell.
        let belief = (0..).zip(now.iter().map(move |&b| b / sum));
        let mean = (sum.is_finite() && sum > 0.0).then(|| {
            walking.pack(belief.clone());
            mean(site, belief)
        });
        self.now.fill(0.0);
        mean.flatten()
    }
}

/// The belief that the entity is within one cell of `cell` (the cell or one
/// of its four edge neighbours): what a published `confidence` promises.
fn within_one_cell(site: &Site, cell: Cell, belief: &[f32]) -> f32 {
    let near = [(0, 0), (-1, 0), (1, 0), (0, -1), (0, 1)];
    near.iter()
        .filter_map(|&(dx, dy)| {
            let x = cell.x.checked_add_signed(dx)?;
            let y = cell.y.checked_add_signed(dy)?;
            site.open_index(Cell::new(x, y))
        })
        .map(|i| belief[i])
        .sum::<f32>()
        .min(1.0)
}

fn argmax(v: &[f32]) -> usize {
    v.iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map_or(0, |(i, _)| i)
}

/// [`spatial_median`]'s buffers, kept between fixes.
#[derive(Default)]
struct MedianScratch {
    /// The cells summed over: (x, y) of the centre and the belief there.
    support: Vec<[f64; 3]>,
    support_cells: Vec<usize>,
    candidates: Vec<usize>,
    costs: Vec<f64>,
}

/// Candidates whose costs are summed in one pass over the support.
const CANDIDATE_LANES: usize = 4;

/// The cell with the least expected distance to where the entity is under the
/// belief. Cells holding under 0.1% of the peak are left out of the sum, and
/// only the most probable cells are candidates: the answer lies among them in
/// practice, and this keeps a diffuse belief from costing O(cells²).
///
/// Each candidate's cost is a sum in support order, but [`CANDIDATE_LANES`]
/// candidates are summed side by side: one candidate's sum is a chain of
/// dependent adds, several are independent lanes (SIMD, and no wait on the
/// add before).
fn spatial_median(cells: &[Cell], belief: &[f32], scratch: &mut MedianScratch) -> usize {
    const CANDIDATES: usize = 24;
    let peak = lane_max(belief, 0.0);
    let MedianScratch {
        support,
        support_cells,
        candidates,
        costs,
    } = scratch;
    support_cells.clear();
    support_cells.extend((0..belief.len()).filter(|&i| belief[i] >= peak * 1e-3));
    support.clear();
    support.extend(support_cells.iter().map(|&j| {
        let c = cells[j];
        [f64::from(c.x), f64::from(c.y), f64::from(belief[j])]
    }));
    candidates.clone_from(support_cells);
    if candidates.len() > CANDIDATES {
        candidates.select_nth_unstable_by(CANDIDATES - 1, |&a, &b| belief[b].total_cmp(&belief[a]));
        candidates.truncate(CANDIDATES);
    }
    costs.clear();
    for group in candidates.chunks(CANDIDATE_LANES) {
        let (mut x, mut y) = ([0.0f64; CANDIDATE_LANES], [0.0f64; CANDIDATE_LANES]);
        for (k, &c) in group.iter().enumerate() {
            x[k] = f64::from(cells[c].x);
            y[k] = f64::from(cells[c].y);
        }
        let mut cost = [0.0f64; CANDIDATE_LANES];
        for &[sx, sy, b] in support.iter() {
            for k in 0..CANDIDATE_LANES {
                // `b · Cell::distance`, operation for operation.
                let (dx, dy) = (x[k] - sx, y[k] - sy);
                cost[k] += b * (dx * dx + dy * dy).sqrt();
            }
        }
        costs.extend_from_slice(&cost[..group.len()]);
    }
    candidates
        .iter()
        .zip(costs.iter())
        .min_by(|a, b| a.1.total_cmp(b.1).then(a.0.cmp(b.0)))
        .map_or(0, |(&c, _)| c)
}

/// Most inflows of a cell: what it keeps and what its eight neighbours pass.
const MAX_INFLOWS: usize = 9;

/// One step of the lazy random walk over every open cell, [`spread_cell`]
/// of each, written as a gather: each cell sums what flows into it.
///
/// Scattering each cell's mass into its nine neighbours makes every add a
/// read-modify-write of the target, and one cell's adds wait on the stores
/// of the cell before; gathering from a flat list of sources after one
/// vectorised pass that works out what each cell keeps and passes on has
/// no such chain. Every cell sums [`MAX_INFLOWS`] inflows, the missing
/// ones a zero: a count the compiler unrolls, where a count per cell
/// mispredicted the end of almost every cell's loop (half the step's time
/// on the sample site). The inflows of a cell are added in the order the
/// scatter added them (ascending source cell) and adding zero changes no
/// sum, so the result is the scatter's, bit for bit.
struct Inflows {
    /// Per open cell, indices into a step's outflows: `j` for the share
    /// open cell `j` passes to each of its moves, cells + `j` for what it
    /// keeps, 2 × cells (always zero) for none.
    sources: Vec<[u32; MAX_INFLOWS]>,
    /// Per open cell, the share of its mass it keeps: `stay`, or all of it
    /// when it has no allowed move.
    keep: Vec<f32>,
    /// Per open cell, its allowed moves (1 when none: that share has no
    /// taker).
    moves: Vec<f32>,
    /// The share of a cell's mass that moves.
    pass: f32,
}

impl Inflows {
    fn new(neighbours: &[Vec<u32>], stay: f32) -> Self {
        let n = neighbours.len();
        let mut into: Vec<Vec<u32>> = vec![Vec::new(); n];
        for (j, targets) in neighbours.iter().enumerate() {
            into[j].push((n + j) as u32);
            for &k in &targets[1..] {
                into[k as usize].push(j as u32);
            }
        }
        let sources = into
            .into_iter()
            .map(|mut from| {
                // Ascending source cell, the scatter's order (a cell's own
                // kept mass counts as from itself).
                from.sort_unstable_by_key(|&s| s as usize % n);
                let mut padded = [(2 * n) as u32; MAX_INFLOWS];
                padded[..from.len()].copy_from_slice(&from);
                padded
            })
            .collect();
        let moves_of = |targets: &Vec<u32>| targets.len() - 1;
        Inflows {
            sources,
            keep: neighbours
                .iter()
                .map(|t| if moves_of(t) == 0 { 1.0 } else { stay })
                .collect(),
            moves: neighbours
                .iter()
                .map(|t| moves_of(t).max(1) as f32)
                .collect(),
            pass: 1.0 - stay,
        }
    }

    /// One step from `from` into `to`, with `outflow` as room.
    fn step(&self, from: &[f32], outflow: &mut Vec<f32>, to: &mut Vec<f32>) {
        let n = from.len();
        outflow.resize(2 * n + 1, 0.0);
        let (passed, kept) = outflow.split_at_mut(n);
        let (kept, none) = kept.split_at_mut(n);
        none[0] = 0.0;
        for (((p, k), &mass), (&keep, &moves)) in passed
            .iter_mut()
            .zip(kept.iter_mut())
            .zip(from)
            .zip(self.keep.iter().zip(&self.moves))
        {
            // As `spread_cell` works them out, operation for operation.
            *p = mass * self.pass / moves;
            *k = mass * keep;
        }
        to.clear();
        to.extend(self.sources.iter().map(|sources| {
            sources
                .iter()
                .fold(0.0f32, |sum, &s| sum + outflow[s as usize])
        }));
    }
}

impl Inflows {
    /// [`Inflows::step`] of a belief whose mass lies on the cells of
    /// `support` alone: computes the cells they reach (into
    /// `next_support`) and nothing else. `outflow`, `to` and `listed` are
    /// all zero (false) on entry and are left so; `from` is zeroed on the
    /// support, so that it can be the next step's `to`.
    #[allow(clippy::too_many_arguments)]
    fn step_from(
        &self,
        neighbours: &[Vec<u32>],
        from: &mut [f32],
        support: &[u32],
        next_support: &mut Vec<u32>,
        listed: &mut [bool],
        outflow: &mut [f32],
        to: &mut [f32],
    ) {
        let n = from.len();
        next_support.clear();
        for &j in support.iter() {
            let j = j as usize;
            let mass = from[j];
            // As `step` works them out, operation for operation.
            outflow[j] = mass * self.pass / self.moves[j];
            outflow[n + j] = mass * self.keep[j];
            for &k in &neighbours[j] {
                if !std::mem::replace(&mut listed[k as usize], true) {
                    next_support.push(k);
                }
            }
        }
        for &c in next_support.iter() {
            to[c as usize] = self.sources[c as usize]
                .iter()
                .fold(0.0f32, |sum, &s| sum + outflow[s as usize]);
        }
        for &j in support.iter() {
            let j = j as usize;
            outflow[j] = 0.0;
            outflow[n + j] = 0.0;
            from[j] = 0.0;
        }
        for &c in next_support.iter() {
            listed[c as usize] = false;
        }
    }
}

/// A listed motion step ([`Inflows::step_from`]) visits each cell reached
/// and its up to 8 neighbours, against one pass over every cell for the
/// whole floor's: worth it while the belief's cells are fewer than this
/// part of the floor.
const SPARSE_STEP_SHARE: usize = 4;

/// One step of the lazy random walk for one cell: of `mass` in the cell
/// whose neighbours are `n` (the cell itself first), `stay` stays, the rest
/// goes to the allowed moves equally.
fn spread_cell(n: &[u32], stay: f32, mass: f32, to: &mut [f32]) {
    let moves = &n[1..];
    if moves.is_empty() {
        to[n[0] as usize] += mass;
        return;
    }
    to[n[0] as usize] += mass * stay;
    let share = mass * (1.0 - stay) / moves.len() as f32;
    for &j in moves {
        to[j as usize] += share;
    }
}

/// Partial results of [`lane_sum`] and [`lane_max`].
const LANES: usize = 16;

/// Σ `v`, in [`LANES`] interleaved partial sums added at the end: one chain
/// of dependent adds over a floor of cells waits on every add's latency;
/// independent lanes do not, and vectorise.
fn lane_sum(v: &[f32]) -> f32 {
    let chunks = v.chunks_exact(LANES);
    let rest: f32 = chunks.remainder().iter().sum();
    let mut lanes = [0.0f32; LANES];
    for chunk in chunks {
        for (lane, &x) in lanes.iter_mut().zip(chunk) {
            *lane += x;
        }
    }
    lanes.iter().sum::<f32>() + rest
}

/// The largest of `v` and `floor` ([`f32::max`]: a NaN is passed over), in
/// [`LANES`] partial maxima: the same value as one pass in order, since a
/// maximum does not depend on the order it is taken in.
fn lane_max(v: &[f32], floor: f32) -> f32 {
    let chunks = v.chunks_exact(LANES);
    let rest = chunks.remainder().iter().copied().fold(floor, f32::max);
    let mut lanes = [floor; LANES];
    for chunk in chunks {
        for (lane, &x) in lanes.iter_mut().zip(chunk) {
            *lane = lane.max(x);
        }
    }
    lanes.into_iter().fold(rest, f32::max)
}

/// e^x for x ≤ 0 (a relative likelihood's exponent), within 2 ulp of
/// [`f32::exp`] and 0 below −87 (where `exp` leaves slow subnormals), NaN
/// for NaN. Written out because it is plain arithmetic a loop over a floor
/// vectorises, where `exp` is a libm call per cell: a fifth of a fix on a
/// floor of 10,800 cells. The reduction `x = k·ln2 + r` and the polynomial
/// for e^r on |r| ≤ ln2/2 are Cephes' `expf`.
fn exp_nonpositive(x: f32) -> f32 {
    // Adding 1.5·2^23 rounds to the nearest integer k, which then sits in
    // the low bits (taking it off again gives k as a float).
    const ROUND: f32 = 12_582_912.0;
    // ln 2 in two parts, the first exact in few bits, so k·ln2 loses nothing.
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    let rounded = x * std::f32::consts::LOG2_E + ROUND;
    let k = rounded - ROUND;
    let r = x - k * LN2_HI - k * LN2_LO;
    let p = ((((1.987_569_1e-4 * r + 1.398_2e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
        + 0.166_666_65)
        * r
        + 0.5;
    let e_r = p * r * r + r + 1.0;
    // 2^k by its exponent bits, k taken from `rounded`'s bits rather than
    // cast from a float (a cast checks each lane for overflow, one by one);
    // k ∈ [−126, 0] wherever the result is used.
    let k_bits = rounded.to_bits().wrapping_sub(ROUND.to_bits());
    let two_k = f32::from_bits(k_bits.wrapping_add(127) << 23);
    if x < -87.0 { 0.0 } else { e_r * two_k }
}

/// Scales `v` to sum to 1 and returns what it summed to; `None` (and `v`
/// untouched) when that is not a positive number.
fn normalize(v: &mut [f32]) -> Option<f32> {
    let sum = lane_sum(v);
    if !(sum.is_finite() && sum > 0.0) {
        return None;
    }
    v.iter_mut().for_each(|x| *x /= sum);
    Some(sum)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn site() -> Arc<Site> {
        // Two rooms joined by a door at the bottom: x=0..2 and x=4..6.
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n###.###\n###.###\n#######\n'''\n";
        Arc::new(Site::parse(text, Path::new("t.toml")).unwrap())
    }

    /// Log-likelihoods falling off with distance from `cell`.
    fn peak_at(site: &Site, cell: Cell, sharpness: f32) -> Vec<f32> {
        site.open_cells()
            .iter()
            .map(|&c| -sharpness * c.distance(cell) as f32)
            .collect()
    }

    #[test]
    fn a_step_gathered_is_the_scatter_bit_for_bit() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        for site in [
            site(),
            Arc::new(Site::load(&root.join("config/sites/waldo.toml")).unwrap()),
        ] {
            let neighbours = open_neighbours(&site);
            let stay = TrackerConfig::default().stay_probability;
            let inflows = Inflows::new(&neighbours, stay);
            let n = neighbours.len();
            let belief: Vec<f32> = (0..n).map(|i| ((i * 37 % 11) as f32 + 0.1) / 7.0).collect();
            let mut scattered = vec![0.0; n];
            for (cell, &mass) in neighbours.iter().zip(&belief) {
                spread_cell(cell, stay, mass, &mut scattered);
            }
            let (mut outflow, mut gathered) = (Vec::new(), Vec::new());
            inflows.step(&belief, &mut outflow, &mut gathered);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&gathered), bits(&scattered));
        }
    }

    /// Steps over a belief's listed cells only give what steps over the
    /// whole floor give, to the bit, and leave their buffers zeroed.
    #[test]
    fn steps_over_the_listed_cells_are_the_whole_floor_s_bit_for_bit() {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let site = Site::load(&root.join("config/sites/waldo.toml")).unwrap();
        let neighbours = open_neighbours(&site);
        let inflows = Inflows::new(&neighbours, TrackerConfig::default().stay_probability);
        let n = neighbours.len();
        // Mass on a few cells apart, the rest zero.
        let mut dense = vec![0.0f32; n];
        let mut support: Vec<u32> = vec![3, 40, 41, 90];
        for (k, &c) in support.iter().enumerate() {
            dense[c as usize] = 0.1 + k as f32 * 0.2;
        }
        let mut listed_belief = dense.clone();
        let (mut outflow, mut next) = (Vec::new(), Vec::new());
        let (mut listed_outflow, mut listed_next) = (vec![0.0; 2 * n + 1], vec![0.0; n]);
        let (mut next_support, mut listed) = (Vec::new(), vec![false; n]);
        for _ in 0..4 {
            inflows.step(&dense, &mut outflow, &mut next);
            std::mem::swap(&mut dense, &mut next);
            inflows.step_from(
                &neighbours,
                &mut listed_belief,
                &support,
                &mut next_support,
                &mut listed,
                &mut listed_outflow,
                &mut listed_next,
            );
            std::mem::swap(&mut listed_belief, &mut listed_next);
            std::mem::swap(&mut support, &mut next_support);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&listed_belief), bits(&dense));
            assert!(listed_next.iter().chain(&listed_outflow).all(|&x| x == 0.0));
            assert!(!listed.contains(&true));
            // Every cell holding mass is listed.
            assert!((0..n).all(|c| dense[c] == 0.0 || support.contains(&(c as u32))));
        }
    }

    #[test]
    fn a_jump_through_a_wall_is_not_believed_at_once() {
        let site = site();
        let mut tracker = Tracker::new(TrackerConfig::default(), site.clone());
        let me: Arc<str> = "me".into();
        let start = tracker.update(&me, 0.0, &peak_at(&site, Cell::new(2, 0), 10.0));
        assert_eq!(start.cell, Cell::new(2, 0));
        // One second later the evidence says "other room, just through the wall":
        // the wall means that is 6 steps away, beyond 1.5 m/s.
        let next = tracker.update(&me, 1.0, &peak_at(&site, Cell::new(4, 0), 2.0));
        assert_ne!(next.cell, Cell::new(4, 0));
        assert!(next.cell.x <= 2, "stays in the first room: {:?}", next.cell);
    }

    #[test]
    fn a_reload_keeps_the_tracks_the_new_site_can_place() {
        let old_site = site();
        let mut old = Tracker::new(TrackerConfig::default(), old_site.clone());
        let (a, b): (Arc<str>, Arc<str>) = ("a".into(), "b".into());
        let fix_a = old.update(&a, 0.0, &peak_at(&old_site, Cell::new(1, 0), 10.0));
        old.update(&b, 0.0, &peak_at(&old_site, Cell::new(6, 0), 10.0));
        // The same grid: the tracks move as they are.
        let mut same = Tracker::new(TrackerConfig::default(), site());
        assert_eq!(same.take_over(&mut old), 2);
        assert_eq!(same.last_fix("a"), Some(fix_a));
        // A grid one column narrower, the second room walled off: a keeps
        // its place, b's is gone.
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n###.#.\n###.#.\n######\n'''\n";
        let narrower = Arc::new(Site::parse(text, Path::new("t.toml")).unwrap());
        let mut moved = Tracker::new(TrackerConfig::default(), narrower.clone());
        assert_eq!(moved.take_over(&mut same), 1);
        let fix = moved.last_fix("a").unwrap();
        assert_eq!(
            (fix.cell, fix.confidence),
            (Cell::new(1, 0), fix_a.confidence)
        );
        assert!(moved.last_fix("b").is_none());
        assert_eq!(moved.take_evicted(), vec![b.clone()]);
        // And it tracks on from there.
        let next = moved.update(&a, 1.0, &peak_at(&narrower, Cell::new(1, 0), 10.0));
        assert_eq!(next.cell, Cell::new(1, 0));
    }

    #[test]
    fn without_tracking_the_argmax_wins() {
        let site = site();
        let config = TrackerConfig {
            kind: TrackerKind::None,
            estimate: Estimate::Mode,
            ..TrackerConfig::default()
        };
        let mut tracker = Tracker::new(config, site.clone());
        let me: Arc<str> = "me".into();
        tracker.update(&me, 0.0, &peak_at(&site, Cell::new(2, 0), 10.0));
        let next = tracker.update(&me, 1.0, &peak_at(&site, Cell::new(4, 0), 2.0));
        assert_eq!(next.cell, Cell::new(4, 0));
        assert!(next.confidence > 0.5);
    }

    #[test]
    fn an_expected_walk_carries_the_belief_on_without_evidence_for_it() {
        let text = "name = \"c\"\ncell_m = 1.0\nmap = '''\n##########\n'''\n";
        let site = Arc::new(Site::parse(text, Path::new("c.toml")).unwrap());
        let mut tracker = Tracker::new(TrackerConfig::default(), site.clone());
        let flat = vec![0.0; site.open_cells().len()];
        let me: Arc<str> = "me".into();
        let start = peak_at(&site, Cell::new(1, 0), 10.0);
        assert_eq!(tracker.update_walking(&me, 0.0, &start, None).1, None);
        // Two metres along the corridor a second, told nothing new.
        let walk = ExpectedWalk {
            moves: (0..8)
                .map(|x| (Cell::new(x, 0), Cell::new(x + 2, 0)))
                .collect(),
            share: 0.8,
        };
        let mut walked = None;
        for t in [1.0, 2.0] {
            let (fix, mean) = tracker.update_walking(&me, t, &flat, Some(&walk));
            // The fix is the track's own, as if nobody walked.
            assert_eq!(fix.cell, Cell::new(1, 0), "{fix:?}");
            walked = mean;
        }
        let [x, _] = walked.expect("walking");
        assert!((4.0..6.0).contains(&x), "two seconds on from 1.5: {x}");
        // Evidence against the walk still wins: the walker turned back.
        for t in [3.0, 4.0] {
            let (_, mean) = tracker.update_walking(&me, t, &start, Some(&walk));
            walked = mean;
        }
        let [x, _] = walked.expect("walking");
        assert!(x < 2.5, "back at 1.5: {x}");
        // Once nobody walks it, none is kept.
        assert_eq!(tracker.update_walking(&me, 5.0, &start, None).1, None);
        assert!(tracker.tracks[&me].walking.is_empty());
    }

    #[test]
    fn entering_at_a_far_cell_holds_the_first_fix_near_it() {
        let text = "name = \"c\"\ncell_m = 1.0\nmap = '''\n####################\n'''\n";
        let site = Arc::new(Site::parse(text, Path::new("c.toml")).unwrap());
        let mut tracker = Tracker::new(TrackerConfig::default(), site.clone()).bound(1, 60.0);
        let (me, other): (Arc<str>, Arc<str>) = ("me".into(), "other".into());
        // Weak evidence for the far end of the corridor...
        let weak = peak_at(&site, Cell::new(17, 0), 0.2);
        // ...which alone wins.
        let alone = tracker.update(&other, 0.0, &weak);
        assert!(alone.cell.x >= 15, "{alone:?}");
        // Entered at a connector at the near end (and a cell that is not
        // open, ignored), the fix stays near it.
        let entered = tracker.enter(&me, 1.0, &[Cell::new(2, 0), Cell::new(2, 5)], &weak);
        assert!(entered.cell.x <= 3, "{entered:?}");
        // It counts towards the bounds as a new track: the other one went.
        assert_eq!(tracker.len(), 1);
        assert_eq!(tracker.take_evicted(), vec![other.clone()]);
        // And it tracks on from there.
        let next = tracker.update(&me, 2.0, &weak);
        assert!(next.cell.x <= 5, "{next:?}");
        // An empty prior is a fresh track's: the evidence alone.
        let fresh = tracker.enter(&me, 3.0, &[], &weak);
        assert_eq!(fresh, alone);
    }

    #[test]
    fn forgetting_a_track_is_no_eviction() {
        let site = site();
        let mut tracker = Tracker::new(TrackerConfig::default(), site.clone());
        let me: Arc<str> = "me".into();
        tracker.update(&me, 0.0, &peak_at(&site, Cell::new(2, 0), 10.0));
        // A small site's belief is kept whole: a mass per open cell.
        assert_eq!(tracker.belief_bytes(), 4 * site.open_cells().len());
        assert!(tracker.forget("me"));
        assert_eq!(tracker.last_fix("me"), None);
        assert!(!tracker.forget("me"));
        assert_eq!(tracker.evicted_count(), 0);
        assert!(tracker.take_evicted().is_empty());
        assert_eq!(tracker.belief_bytes(), 0);
    }

    #[test]
    fn a_track_keeps_a_settled_belief_in_few_cells_and_fixes_as_dense() {
        // A 240 × 180 m floor at 1 m cells; a walk along its middle.
        let text = "name = \"big\"\ncell_m = 1.0\nwidth_m = 240.0\nheight_m = 180.0\n";
        let site = Arc::new(Site::parse(text, Path::new("big.toml")).unwrap());
        let n = site.open_cells().len();
        let mut tracker = Tracker::new(TrackerConfig::default(), site.clone());
        let reference = Tracker::new(TrackerConfig::default(), site.clone());
        let model = reference.model();
        let (mut dense, mut scratch) = (Vec::new(), FilterScratch::default());
        let mut likelihood = Vec::new();
        let me: Arc<str> = "me".into();
        for k in 0..10u16 {
            let ll = peak_at(&site, Cell::new(100 + k, 90), 1.0);
            let fix = tracker.update(&me, f64::from(k), &ll);
            // The same window filtered dense, as before beliefs were kept sparse.
            model.likelihood(&ll, &mut likelihood);
            let steps = model.steps(if k == 0 { -1.0 } else { 1.0 });
            model.filter(&mut dense, steps, &likelihood, &mut scratch);
            let mut median = MedianScratch::default();
            let want = estimate(Estimate::Median, &site, &dense, &mut median);
            assert_eq!(fix.cell, want.cell, "window {k}: {fix:?} {want:?}");
            // What the dense belief's lightest cells would have added
            // shows in the third decimal at most.
            assert!(
                (fix.confidence - want.confidence).abs() < 5e-3,
                "window {k}: {fix:?} {want:?}"
            );
            assert!(
                (fix.mean[0] - want.mean[0]).abs() < 0.05,
                "window {k}: {fix:?} {want:?}"
            );
        }
        let kept = tracker.tracks[&me].belief.cells.len();
        assert!(kept < n / 20, "{kept} of {n} cells");
        assert!(tracker.belief_bytes() <= MAX_TRACKED * 8);
    }

    /// The likelihood's exponential agrees with libm's over its whole range
    /// (every 1,000th f32 of [−87, 0]), and is 0 below it and NaN for NaN.
    #[test]
    fn exp_nonpositive_is_exp_within_two_ulp() {
        let (from, to) = ((-0.0f32).to_bits(), (-87.0f32).to_bits());
        let mut worst = 0;
        for bits in (from..=to).step_by(1_000).chain([to, 0x8000_0001]) {
            let x = f32::from_bits(bits);
            let (got, want) = (exp_nonpositive(x), x.exp());
            let ulp = got.to_bits().abs_diff(want.to_bits());
            assert!(ulp <= 2, "e^{x}: {got} against {want} ({ulp} ulp)");
            worst = worst.max(ulp);
        }
        assert!(worst > 0, "a tolerance nothing reaches tests nothing");
        for x in [-87.5, -100.0, -1e9, f32::NEG_INFINITY] {
            assert_eq!(exp_nonpositive(x), 0.0, "e^{x}");
        }
        assert!(exp_nonpositive(f32::NAN).is_nan());
        assert_eq!(exp_nonpositive(0.0), 1.0);
    }

    proptest::proptest! {
        /// The lanes' maximum is one pass's, NaN passed over alike; their
        /// sum agrees with an exact one to f32's precision.
        #[test]
        fn lane_reductions_agree_with_one_pass(
            v in proptest::collection::vec(
                proptest::prop_oneof![0.0f32..1.0, proptest::strategy::Just(f32::NAN)],
                0..100,
            ),
            floor in -1.0f32..0.5,
        ) {
            let one_pass = v.iter().copied().fold(floor, f32::max);
            proptest::prop_assert_eq!(lane_max(&v, floor).to_bits(), one_pass.to_bits());
            let finite: Vec<f32> = v.iter().copied().filter(|x| !x.is_nan()).collect();
            let exact: f64 = finite.iter().map(|&x| f64::from(x)).sum();
            proptest::prop_assert!((f64::from(lane_sum(&finite)) - exact).abs() <= 1e-6 * exact.max(1.0));
        }
    }

    /// Packing weighs whole blocks of cells that share an exponent at once:
    /// it keeps the cells a weighing cell by cell keeps.
    #[test]
    fn packing_by_blocks_keeps_what_packing_cell_by_cell_keeps() {
        // Runs of equal tiny masses (a block shares an exponent), cells of
        // mixed exponents, a settled peak and some nothing, at a length
        // that is no whole number of blocks.
        let mut belief: Vec<f32> = (0..20_003)
            .map(|i| match i % 7_001 {
                0..=5_999 => 1e-9,
                6_000..=6_499 => 1e-9 * (1.0 + (i % 13) as f32),
                6_500..=6_509 => 0.05,
                6_510..=6_519 => 0.0,
                _ => 3e-6 * (1.0 + (i % 5) as f32),
            })
            .collect();
        belief[12_345] = 0.4;
        let mut packed = Sparse::<f32>::default();
        packed.pack_heaviest(&belief, &mut PackScratch::default());
        // Cell by cell, as one pass: each positive mass into its
        // exponent's bucket, the lightest buckets holding at most
        // DROPPED_MASS of it all dropped.
        let mut buckets = vec![0.0f64; 256];
        for &b in &belief {
            if b > 0.0 {
                buckets[(b.to_bits() >> 23) as usize] += f64::from(b);
            }
        }
        let total: f64 = buckets.iter().sum();
        let (mut dropped, mut least) = (0.0, 0);
        while dropped + buckets[least] <= DROPPED_MASS * total {
            dropped += buckets[least];
            least += 1;
        }
        let want: Vec<u32> = (0..)
            .zip(&belief)
            .filter(|&(_, &b)| b > 0.0 && (b.to_bits() >> 23) as usize >= least)
            .map(|(i, _)| i)
            .collect();
        assert!(
            want.len() < 4 * MAX_TRACKED / 10,
            "{} kept: a sparse case",
            want.len()
        );
        assert_eq!(packed.cells, want);
        let sum: f32 = packed.mass.iter().sum();
        assert!((sum - 1.0).abs() < 1e-5, "rescaled: {sum}");
    }

    #[test]
    fn smoothing_lets_later_evidence_revise_an_ambiguous_window() {
        let text = "name = \"c\"\ncell_m = 1.0\nmap = '''\n##########\n'''\n";
        let site = Arc::new(Site::parse(text, Path::new("c.toml")).unwrap());
        let tracker = Tracker::new(TrackerConfig::default(), site.clone());
        let flat = vec![0.0; site.open_cells().len()];
        let windows = vec![
            (0.0, peak_at(&site, Cell::new(2, 0), 10.0)),
            (1.0, flat),
            (2.0, peak_at(&site, Cell::new(4, 0), 10.0)),
        ];
        let online = tracker.smooth(&windows, 0);
        let smoothed = tracker.smooth(&windows, 1);
        // Online, the silent window stays where the walk was; knowing where it
        // went next, the smoother puts it on the way.
        assert_eq!(online[1].cell, Cell::new(2, 0));
        assert_eq!(smoothed[1].cell, Cell::new(3, 0));
        assert_eq!(smoothed[0].cell, Cell::new(2, 0));
        assert_eq!(smoothed[2].cell, Cell::new(4, 0));
    }
}
