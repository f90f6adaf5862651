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
    /// Weight of the localizer's log-likelihood against the motion prior; below
    /// 1 when the localizer is over-confident (anchors are not independent).
    pub likelihood_weight: f32,
    /// Probability mass spread uniformly over the site each step, so that a
    /// track that went wrong can recover.
    pub recovery: f32,
    /// Gaps longer than this (seconds) restart the track from the likelihood.
    pub reset_after_s: f64,
}

impl Default for TrackerConfig {
    fn default() -> Self {
        TrackerConfig {
            kind: TrackerKind::Hmm,
            max_speed_mps: 1.5,
            likelihood_weight: 1.0,
            recovery: 1e-3,
            reset_after_s: 30.0,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
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
    /// For each open cell: itself and the open cells one allowed step away.
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
        let n = log_likelihood.len();
        let weight = self.config.likelihood_weight;
        let max_ll = log_likelihood
            .iter()
            .copied()
            .fold(f32::NEG_INFINITY, f32::max);
        let likelihood = log_likelihood
            .iter()
            .map(|&ll| ((ll - max_ll) * weight).exp());

        let track = self.tracks.get_mut(entity);
        let restart = match &track {
            None => true,
            Some(track) => {
                self.config.kind == TrackerKind::None
                    || !(0.0..=self.config.reset_after_s).contains(&(t - track.t))
            }
        };
        let belief = if restart {
            let mut belief: Vec<f32> = likelihood.collect();
            normalize(&mut belief);
            let track = self.tracks.entry(entity.clone()).or_insert_with(|| Track {
                t,
                belief: Vec::new(),
                fix: Fix {
                    cell: Cell::new(0, 0),
                    confidence: 0.0,
                },
            });
            track.belief = belief;
            track
        } else {
            let track = track.expect("not a restart");
            let reach = self.config.max_speed_mps * (t - track.t) / self.site.cell_m;
            let steps = reach.ceil().max(1.0) as usize;
            for _ in 0..steps {
                spread(&self.neighbours, &track.belief, &mut self.scratch);
                std::mem::swap(&mut track.belief, &mut self.scratch);
            }
            let floor = self.config.recovery / n as f32;
            for (b, l) in track.belief.iter_mut().zip(likelihood) {
                *b = (*b * (1.0 - self.config.recovery) + floor) * l;
            }
            if !normalize(&mut track.belief) {
                // The evidence contradicts the prior everywhere: trust the evidence.
                track.belief.clear();
                track.belief.extend(
                    log_likelihood
                        .iter()
                        .map(|&ll| ((ll - max_ll) * weight).exp()),
                );
                normalize(&mut track.belief);
            }
            track
        };
        belief.t = t;
        let (best, &p) = belief
            .belief
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .expect("a site has at least one walkable cell");
        belief.fix = Fix {
            cell: self.site.open_cells()[best],
            confidence: p,
        };
        belief.fix
    }
}

/// One step of the lazy random walk: each cell keeps a share of its mass and
/// passes equal shares to each allowed neighbour.
fn spread(neighbours: &[Vec<u32>], from: &[f32], to: &mut Vec<f32>) {
    to.clear();
    to.resize(from.len(), 0.0);
    for (i, n) in neighbours.iter().enumerate() {
        let share = from[i] / n.len() as f32;
        for &j in n {
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
