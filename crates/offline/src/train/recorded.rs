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
//!
//! A building's store holds every floor's tracks and routes, each cell on
//! its floor's grid (a route across floors as its legs): a site is trained
//! on its own floor's only ([`FloorChoice`]). Routes of a one-floor site
//! name no floor, and are the site's.

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

/// Whose tracks of a store a site learns from.
#[derive(Clone, Copy, Debug)]
pub enum FloorChoice<'a> {
    /// The tracks of the one floor the store has (a one-floor site's); a
    /// store holding several floors' tracks is refused.
    Only,
    /// The tracks of this floor (its name in the building file).
    Named(&'a str),
}

/// Walks recorded in the store at `path`, as training trajectories for `site`,
/// the tracks of the floor `floor` picks.
pub fn walks_from_store(
    path: &Path,
    site: &Site,
    floor: FloorChoice,
) -> anyhow::Result<Vec<Trajectory>> {
    let store = Store::open_read_only(path)?;
    let followed = store.adherence()?;
    let mut walks = Vec::new();
    let tracks = store.trajectories(MAX_GAP_S)?;
    let mut floors: Vec<String> = tracks.iter().filter_map(|t| t.floor.clone()).collect();
    floors.sort_unstable();
    floors.dedup();
    let wanted = match floor {
        FloorChoice::Only if floors.len() > 1 => anyhow::bail!(
            "{}: the store holds walks on {} floors ({}): give --floor NAME, the floor of the \
             building that the site `{}` maps",
            path.display(),
            floors.len(),
            floors.join(", "),
            site.name
        ),
        FloorChoice::Only => None,
        FloorChoice::Named(name) if !floors.iter().any(|f| f == name) => anyhow::bail!(
            "{}: no walks on floor `{name}`; the store holds walks on: {}",
            path.display(),
            if floors.is_empty() {
                "no named floor (recorded before the store kept floors)".to_owned()
            } else {
                floors.join(", ")
            }
        ),
        FloorChoice::Named(name) => Some(name),
    };
    let (tracks, others): (Vec<_>, Vec<_>) = tracks
        .into_iter()
        .partition(|t| wanted.is_none_or(|name| t.floor.as_deref() == Some(name)));
    let floorless = others.iter().filter(|t| t.floor.is_none()).count();
    if floorless > 0 {
        tracing::warn!(
            store = %path.display(),
            "{floorless} walks recorded before the store kept floors left out: their floor is unknown"
        );
    }
    for track in tracks {
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
    // A route naming no floor is a one-floor site's; a leg of a route
    // across floors is its floor's.
    let routes = store
        .routes()?
        .into_iter()
        .filter(|r| match (wanted, r.floor.as_deref()) {
            (_, None) => wanted.is_none(),
            (Some(name), Some(floor)) => floor == name,
            (None, Some(floor)) => floors.len() == 1 && floors[0] == floor,
        });
    for route in routes {
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
            floor: None,
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
                    floor: Some("s".into()),
                    cell: Cell::new(x, 1),
                    confidence: 0.9,
                });
            }
        }
        store.write(&records).unwrap();
        let walks = walks_from_store(&path, &site, FloorChoice::Only).unwrap();
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
    fn a_site_learns_from_its_own_floor_s_tracks() {
        let site = Site::parse(
            "name = \"g\"\ncell_m = 1.0\nmap = '''\n######\n######\n'''\n",
            Path::new("g.toml"),
        )
        .unwrap();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("s.sqlite");
        let mut store = Store::open(&path).unwrap();
        // One device walks row 0 of B1, then row 1 of G.
        let records: Vec<Record> = (0..12u16)
            .map(|i| Record::Fix {
                device: "d".into(),
                t: f64::from(i),
                floor: Some(if i < 6 { "B1" } else { "G" }.into()),
                cell: Cell::new(i % 6, i / 6),
                confidence: 0.9,
            })
            .collect();
        store.write(&records).unwrap();
        let asked = walks_from_store(&path, &site, FloorChoice::Only)
            .unwrap_err()
            .to_string();
        assert!(
            asked.contains("2 floors (B1, G)") && asked.contains("--floor"),
            "{asked}"
        );
        let walks = walks_from_store(&path, &site, FloorChoice::Named("G")).unwrap();
        assert_eq!(walks.len(), 1);
        assert!(
            walks[0].cells.iter().all(|c| c.y == 1),
            "{:?}",
            walks[0].cells
        );
        assert_eq!(walks[0].cells.len(), 6);
        let unknown = walks_from_store(&path, &site, FloorChoice::Named("L9"))
            .unwrap_err()
            .to_string();
        assert!(
            unknown.contains("no walks on floor `L9`") && unknown.contains("B1, G"),
            "{unknown}"
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
