//! Tracking: one belief per entity over the site's walkable cells, fused from
//! the localizer's per-cell likelihoods and a motion model.
//!
//! The `hmm` tracker is a forward filter. Between two fixes `dt` seconds apart a
//! person walks at most `max_speed_mps · dt` metres, through walkable cells only;
//! the prediction step spreads the belief that many steps over the access graph
//! (a lazy random walk that never crosses a blocked cell or cuts its corner), so
//! a fix on the far side of a wall or across the building in two seconds gets no
//! prior mass. The `none` tracker is the plain per-window argmax.

use std::collections::HashMap;
use std::sync::Arc;

use serde::Deserialize;

use crate::plan::Connectivity;
use crate::site::{Cell, Site};

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
    /// Posterior probability of `cell`.
    pub confidence: f32,
}

struct Track {
    t: f64,
    belief: Vec<f32>,
    fix: Fix,
}

/// The tracks of all entities on one site.
pub struct Tracker {
    config: TrackerConfig,
    site: Arc<Site>,
    /// For each open cell: itself first, then the open cells one allowed step away.
    neighbours: Vec<Vec<u32>>,
    tracks: HashMap<Arc<str>, Track>,
    scratch: Vec<f32>,
}

impl Tracker {
    pub fn new(config: TrackerConfig, site: Arc<Site>) -> Self {
        let neighbours = site
            .open_cells()
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
                        if Connectivity::Eight.step_ok(&site, c, next) {
                            n.push(site.open_index(next).expect("walkable") as u32);
                        }
                    }
                }
                n
            })
            .collect();
        Tracker {
            config,
            site,
            neighbours,
            tracks: HashMap::new(),
            scratch: Vec::new(),
        }
    }

    /// The latest fix of an entity.
    pub fn last_fix(&self, entity: &str) -> Option<Fix> {
        self.tracks.get(entity).map(|t| t.fix)
    }

    pub fn len(&self) -> usize {
        self.tracks.len()
    }

    pub fn is_empty(&self) -> bool {
        self.tracks.is_empty()
    }

    /// Folds one window's log-likelihoods (one per open cell) into the entity's
    /// track and returns the new fix.
    pub fn update(&mut self, entity: &Arc<str>, t: f64, log_likelihood: &[f32]) -> Fix {
        let weight = self.config.likelihood_weight;
        let max_ll = log_likelihood
            .iter()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max);
        let likelihood = |i: usize| ((log_likelihood[i] - max_ll) * weight).exp();

        let continues = self.config.kind == TrackerKind::Hmm
            && self
                .tracks
                .get(entity)
                .is_some_and(|track| (0.0..=self.config.reset_after_s).contains(&(t - track.t)));
        let track = self.tracks.entry(entity.clone()).or_insert_with(|| Track {
            t,
            belief: Vec::new(),
            fix: Fix {
                cell: Cell::new(0, 0),
                confidence: 0.0,
            },
        });
        let mut fused = false;
        if continues {
            // Predict: spread the belief as far as one can walk in the gap.
            let reach = self.config.max_speed_mps * (t - track.t) / self.site.cell_m;
            for _ in 0..(reach.ceil() as usize).max(1) {
                spread(
                    &self.neighbours,
                    self.config.stay_probability,
                    &track.belief,
                    &mut self.scratch,
                );
                std::mem::swap(&mut track.belief, &mut self.scratch);
            }
            // Update with the evidence.
            let floor = self.config.recovery / track.belief.len() as f32;
            for (i, b) in track.belief.iter_mut().enumerate() {
                *b = (*b * (1.0 - self.config.recovery) + floor) * likelihood(i);
            }
            fused = normalize(&mut track.belief);
        }
        if !fused {
            // A new track, a long gap, or evidence that contradicts the prior
            // everywhere: start from the evidence alone.
            track.belief.clear();
            track
                .belief
                .extend((0..log_likelihood.len()).map(likelihood));
            normalize(&mut track.belief);
        }
        track.t = t;
        let best = match self.config.estimate {
            Estimate::Mode => argmax(&track.belief),
            Estimate::Median => spatial_median(self.site.open_cells(), &track.belief),
        };
        track.fix = Fix {
            cell: self.site.open_cells()[best],
            confidence: track.belief[best],
        };
        track.fix
    }
}

fn argmax(v: &[f32]) -> usize {
    v.iter()
        .enumerate()
        .max_by(|a, b| a.1.total_cmp(b.1))
        .map_or(0, |(i, _)| i)
}

/// The cell with the least expected distance to where the entity is under the
/// belief. Cells holding under 0.1% of the peak are left out of the sum, and
/// only the most probable cells are candidates: the answer lies among them in
/// practice, and this keeps a diffuse belief from costing O(cells²).
fn spatial_median(cells: &[Cell], belief: &[f32]) -> usize {
    const CANDIDATES: usize = 24;
    let peak = belief.iter().copied().fold(0.0, f32::max);
    let support: Vec<usize> = (0..belief.len())
        .filter(|&i| belief[i] >= peak * 1e-3)
        .collect();
    let mut candidates = support.clone();
    if candidates.len() > CANDIDATES {
        candidates.select_nth_unstable_by(CANDIDATES - 1, |&a, &b| belief[b].total_cmp(&belief[a]));
        candidates.truncate(CANDIDATES);
    }
    candidates
        .iter()
        .map(|&c| {
            let cost: f64 = support
                .iter()
                .map(|&j| f64::from(belief[j]) * cells[c].distance(cells[j]))
                .sum();
            (c, cost)
        })
        .min_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)))
        .map_or(0, |(c, _)| c)
}

/// One step of the lazy random walk: each cell keeps `stay` of its mass and
/// passes equal shares of the rest to each allowed neighbour.
fn spread(neighbours: &[Vec<u32>], stay: f32, from: &[f32], to: &mut Vec<f32>) {
    to.clear();
    to.resize(from.len(), 0.0);
    for (i, n) in neighbours.iter().enumerate() {
        // n[0] is the cell itself.
        let moves = &n[1..];
        if moves.is_empty() {
            to[i] += from[i];
            continue;
        }
        to[i] += from[i] * stay;
        let share = from[i] * (1.0 - stay) / moves.len() as f32;
        for &j in moves {
            to[j as usize] += share;
        }
    }
}

/// Scales to sum 1; false when the sum is zero or not finite.
fn normalize(v: &mut [f32]) -> bool {
    let sum: f32 = v.iter().sum();
    if !(sum.is_finite() && sum > 0.0) {
        return false;
    }
    v.iter_mut().for_each(|x| *x /= sum);
    true
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
}
