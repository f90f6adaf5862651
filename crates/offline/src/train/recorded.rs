//! Training walks from the daemon's learning store (`[store]`): the paper's
//! crowd-sourced loop, where what a gateway saw and what its users said about
//! the routes they were given feed the next models.
//!
//! Two kinds of walk come out of a store:
//! - each device's recorded track, split at long gaps; fixes are seconds apart
//!   and may skip cells, so consecutive fixes are joined by the shortest
//!   walkable path (every training walk is 8-connected, as real walks are);
//!   tracks carry no feedback;
//!   a track walked while its device was being guided carries that
//!   guidance's adherence (the mean [`Adherence::score`] of the sessions it
//!   overlaps), so a walk that did not follow its route counts less;
//! - each route the gateway gave that someone rated or followed: its cells,
//!   with the mean score (1–5) mapped to feedback in [0, 1] or, unrated, the
//!   mean adherence of the sessions that followed it. Explicit scores win:
//!   someone who says a route was good means it even if the localization
//!   thought they strayed.
//!
//! [`weighted`] then turns feedback into sampling weight, so well-rated and
//! well-followed routes are learned more and the others less.

use std::path::Path;

use super::trajectory::Trajectory;
use crate::guide::Adherence;
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
    let followed = store.adherence()?;
    let mut walks = Vec::new();
    for track in store.trajectories(MAX_GAP_S)? {
        let feedback = track_adherence(&followed, &track.device, &track.points);
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
                feedback,
                positions_m: None,
            });
        }
    }
    for route in store.routes()? {
        let feedback = match (route.score, route.adherence) {
            (Some(score), _) => ((score - 1.0) / 4.0).clamp(0.0, 1.0),
            (None, Some(adherence)) => adherence,
            (None, None) => continue,
        };
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
            feedback: Some(feedback),
            positions_m: None,
        });
    }
    Ok(walks)
}

/// The mean adherence score of `device`'s guided sessions that overlap the
/// time of a track's `points`; `None` when it was not guided then.
fn track_adherence(
    followed: &[Adherence],
    device: &str,
    points: &[(f64, crate::site::Cell)],
) -> Option<f64> {
    let (first, last) = (points.first()?.0, points.last()?.0);
    let scores: Vec<f64> = followed
        .iter()
        .filter(|a| a.device == device && a.started_t <= last && a.t >= first)
        .map(Adherence::score)
        .collect();
    (!scores.is_empty()).then(|| scores.iter().sum::<f64>() / scores.len() as f64)
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
    use crate::guide::Ending;
    use crate::site::Cell;
    use crate::store::Record;

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

    /// A guided session of `device` from `t0` to `t1` that ended `arrived`
    /// or was abandoned after leaving the route.
    fn session(device: &str, id: &str, t0: f64, t1: f64, followed: bool) -> Record {
        Record::Adherence(Adherence {
            device: device.into(),
            request_id: Some(id.into()),
            started_t: t0,
            t: t1,
            ending: if followed {
                Ending::Arrived
            } else {
                Ending::Cancelled
            },
            in_corridor_share: if followed { 1.0 } else { 0.4 },
            detours: if followed { 0 } else { 2 },
            arrived: followed,
            expected_s: t1 - t0,
            taken_s: t1 - t0,
        })
    }

    #[test]
    fn a_walk_that_did_not_follow_its_route_is_weighed_down() {
        let site = Site::parse(
            "name = \"s\"\ncell_m = 1.0\nmap = '''\n######\n######\n'''\n",
            Path::new("s.toml"),
        )
        .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sqlite");
        let mut store = Store::open(&path).unwrap();
        let route = |device: &str, id: &str, t: f64| Record::Route {
            device: device.into(),
            request_id: Some(id.into()),
            t,
            planner: "astar".into(),
            cells: (0..6).map(|x| Cell::new(x, 0)).collect(),
        };
        let mut records = vec![
            route("kept", "r1", 0.0),
            route("strayed", "r2", 0.0),
            // Rated and strayed: the explicit score wins.
            route("rated", "r3", 0.0),
            Record::Feedback {
                device: "rated".into(),
                request_id: "r3".into(),
                t: 9.0,
                score: 5,
            },
            session("kept", "r1", 0.0, 6.0, true),
            session("strayed", "r2", 0.0, 6.0, false),
            session("rated", "r3", 0.0, 6.0, false),
        ];
        for device in ["kept", "strayed", "unguided"] {
            for x in 0..6u16 {
                records.push(Record::Fix {
                    device: device.into(),
                    t: f64::from(x),
                    cell: Cell::new(x, 1),
                    confidence: 0.9,
                });
            }
        }
        store.write(&records).unwrap();
        let walks = walks_from_store(&path, &site).unwrap();
        let feedback = |device: &str, route: bool| {
            walks
                .iter()
                .find(|w| w.device == device && (w.cells[0].y == 0) == route)
                .map(|w| w.feedback)
        };
        assert_eq!(feedback("kept", true), Some(Some(1.0)));
        assert_eq!(feedback("kept", false), Some(Some(1.0)));
        let strayed = feedback("strayed", true).unwrap().unwrap();
        assert!(strayed < 0.1, "{strayed}");
        assert_eq!(feedback("strayed", false), Some(Some(strayed)));
        assert_eq!(feedback("rated", true), Some(Some(1.0)));
        assert_eq!(feedback("unguided", false), Some(None));
        // Learned twice, never, and once (no feedback either way).
        let copies = |device: &str| {
            weighted(walks.clone())
                .iter()
                .filter(|w| w.device == device)
                .count()
        };
        assert_eq!(
            (copies("kept"), copies("strayed"), copies("unguided")),
            (4, 0, 1)
        );
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
