//! Training walks from the daemon's learning store (`[store]`): the paper's
//! crowd-sourced loop, where what a gateway saw and what its users said about
//! the routes they were given feed the next models.
//!
//! Two kinds of walk come out of a store:
//! - each device's recorded track, split at long gaps; fixes are seconds apart
//!   and may skip cells, so consecutive fixes are joined by the shortest
//!   walkable path (every training walk is 8-connected, as real walks are);
//!   tracks carry no feedback;
//! - each route the gateway gave that someone rated: its cells, with the mean
//!   score (1–5) mapped to feedback in [0, 1].
//!
//! [`weighted`] then turns feedback into sampling weight, so well-rated routes
//! are learned more and badly rated ones less.

use std::path::Path;

use super::trajectory::Trajectory;
use crate::plan::{Connectivity, astar};
use crate::site::Site;
use crate::store::Store;

/// Fixes further apart than this (seconds) start a new walk.
const MAX_GAP_S: f64 = 30.0;

/// Copies of a walk without feedback; a rated walk gets `round(2 × this ×
/// feedback)`: none for the worst score, one for a middling one, two for the
/// best. Copies rather than per-sample weights because the trainers draw
/// minibatches uniformly: equal in expectation, and simpler. One, so that
/// unrated walks (all shipped ones) are never duplicated across the classifier's
/// held-out split.
const NEUTRAL_COPIES: usize = 1;

/// Walks recorded in the store at `path`, as training trajectories for `site`.
pub fn walks_from_store(path: &Path, site: &Site) -> anyhow::Result<Vec<Trajectory>> {
    let store = Store::open_read_only(path)?;
    let mut walks = Vec::new();
    for track in store.trajectories(MAX_GAP_S)? {
        let mut cells = Vec::new();
        let mut times = Vec::new();
        for &(t, cell) in &track.points {
            match cells.last().copied() {
                None => {
                    cells.push(cell);
                    times.push(t);
                }
                Some(last) if last == cell => {}
                Some(last) => {
                    let Ok(leg) = astar::search(site, Connectivity::Eight, last, cell, |_| 1.0)
                    else {
                        continue; // a fix on a cell the current map blocks
                    };
                    let steps = leg.cells.len() - 1;
                    let t0 = *times.last().expect("a cell has a time");
                    for (i, &c) in leg.cells.iter().enumerate().skip(1) {
                        cells.push(c);
                        times.push(t0 + (t - t0) * i as f64 / steps as f64);
                    }
                }
            }
        }
        if cells.len() >= 2 {
            walks.push(Trajectory {
                site: site.name.clone(),
                device: track.device,
                cells,
                times,
                profile: None,
                feedback: None,
                positions_m: None,
            });
        }
    }
    for route in store.routes()? {
        let Some(score) = route.score else { continue };
        if route.cells.len() < 2 {
            continue;
        }
        let times = (0..route.cells.len()).map(|i| route.t + i as f64).collect();
        walks.push(Trajectory {
            site: site.name.clone(),
            device: route.device,
            cells: route.cells,
            times,
            profile: None,
            feedback: Some(((score - 1.0) / 4.0).clamp(0.0, 1.0)),
            positions_m: None,
        });
    }
    Ok(walks)
}

/// Each walk repeated by its feedback weight (see [`NEUTRAL_COPIES`]).
pub fn weighted(walks: Vec<Trajectory>) -> Vec<Trajectory> {
    walks
        .into_iter()
        .flat_map(|w| {
            let copies = w.feedback.map_or(NEUTRAL_COPIES, |f| {
                (2.0 * NEUTRAL_COPIES as f64 * f).round() as usize
            });
            std::iter::repeat_n(w, copies)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::site::Cell;

    fn walk(feedback: Option<f64>) -> Trajectory {
        Trajectory {
            site: "s".into(),
            device: "d".into(),
            cells: vec![Cell::new(0, 0), Cell::new(1, 0)],
            times: vec![0.0, 1.0],
            profile: None,
            feedback,
            positions_m: None,
        }
    }

    #[test]
    fn feedback_sets_how_often_a_walk_is_learned() {
        let copies = |f| weighted(vec![walk(f)]).len();
        assert_eq!(copies(None), 1);
        assert_eq!(copies(Some(0.0)), 0);
        assert_eq!(copies(Some(0.5)), 1);
        assert_eq!(copies(Some(1.0)), 2);
    }
}
