//! Simulated walks: walkers on a site, with what their phones hear and where
//! they really are. Used for fixtures, demos and tests of the whole pipeline.
//!
//! Each walker starts at a random place, walks shortest walkable routes at its
//! own pace to random destinations (named places mostly, any walkable cell
//! sometimes), pauses, and walks on. Its phone scans `scan_hz` times a second
//! and hears each beacon as the survey-free localizer's radio model of that
//! beacon says (`locate::pathloss::Radio`: the config's values, or the
//! calibration file's fit of the real building): heard with the model's
//! detection probability (spread over the scans of one fingerprint window, so
//! a window hears it as often as the model says), at an RSSI from the
//! log-distance model plus Gaussian shadowing; on top of that it drops a share
//! of adverts and misses those below the receiver's sensitivity. So a
//! simulation of a calibrated site sounds like the building the calibration
//! was fitted to. With a survey, each scan instead replays a real reading
//! taken in (or nearest to) the walker's cell.
//!
//! Output is a time-ordered event list; the same site, config and seed give the
//! same events, bit for bit.
//!
//! Three parts: this module plans the walkers and their timelines
//! ([`simulate`]); [`phone`] is what a phone hears where it stands (also used
//! by `eval guidance`); [`walks`] makes the other kind of output, whole walks
//! between places as trajectories, the training data of the path models
//! (it belongs with the trainers, which it feeds, more than with the sources).

use std::sync::Arc;

use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};

pub(crate) mod phone;
pub(crate) mod walks;

pub(crate) use phone::Phone;
pub use walks::{WalkConfig, simulate_walks};

use crate::event::{Event, RouteRequest, Truth};
use crate::locate::calibration::Calibration;
use crate::locate::pathloss::PathLossConfig;
use crate::locate::survey::Survey;
use crate::plan::{Connectivity, Destination, astar};
use crate::site::{Cell, Site};

/// What to simulate.
#[derive(Clone, Debug)]
pub struct SimConfig {
    pub walkers: usize,
    pub duration_s: f64,
    pub seed: u64,
    /// Scans per second of each walker's phone.
    pub scan_hz: f64,
    /// Share of adverts lost (collisions, scan gaps).
    pub dropout: f64,
    /// Mean walking speed; each walker draws its own around it.
    pub speed_mps: f64,
    /// Route requests per walker, at random times.
    pub requests_per_walker: usize,
    /// Time of the first event (Unix seconds).
    pub start_t: f64,
    /// The beacons' radio: the config's `[localizer.pathloss]` values…
    pub pathloss: PathLossConfig,
    /// …and the per-beacon fit of a calibration file, when there is one.
    pub calibration: Option<Calibration>,
    /// Seconds of one fingerprint window (`[window] length_s`): the span the
    /// radio model's detection probability is about.
    pub window_s: f64,
}

impl Default for SimConfig {
    fn default() -> Self {
        SimConfig {
            walkers: 3,
            duration_s: 120.0,
            seed: 1,
            scan_hz: 1.0,
            dropout: 0.1,
            speed_mps: 1.2,
            requests_per_walker: 2,
            start_t: 1_767_225_600.0, // 2026-01-01T00:00:00Z
            pathloss: PathLossConfig::default(),
            calibration: None,
            window_s: crate::locate::window::WindowConfig::default().length_s,
        }
    }
}

impl SimConfig {
    /// The defaults, with phones hearing the beacons as the gateway config's
    /// survey-free radio model (and its calibration file) describes them.
    pub fn hearing(config: &crate::config::Config, site: &Site) -> anyhow::Result<SimConfig> {
        let pathloss = config.localizer.pathloss.clone();
        let calibration = match &pathloss.calibration {
            Some(path) => Some(Calibration::load(path, site)?),
            None => None,
        };
        Ok(SimConfig {
            pathloss,
            calibration,
            window_s: config.window.length_s,
            ..SimConfig::default()
        })
    }
}

/// Where a walker is over time: cell centres with the times it reaches them.
struct Timeline {
    points: Vec<(f64, Cell)>,
}

impl Timeline {
    /// The cell the walker is in at `t` (the nearer end of the current step) and
    /// its position in cells.
    fn at(&self, t: f64) -> (Cell, (f64, f64)) {
        let i = self.points.partition_point(|&(ti, _)| ti <= t);
        if i == 0 {
            let c = self.points[0].1;
            return (c, centre(c));
        }
        if i == self.points.len() {
            let c = self.points[i - 1].1;
            return (c, centre(c));
        }
        let (t0, a) = self.points[i - 1];
        let (t1, b) = self.points[i];
        let f = if t1 > t0 { (t - t0) / (t1 - t0) } else { 1.0 };
        let (ax, ay) = centre(a);
        let (bx, by) = centre(b);
        let cell = if f < 0.5 { a } else { b };
        (cell, (ax + (bx - ax) * f, ay + (by - ay) * f))
    }
}

fn centre(c: Cell) -> (f64, f64) {
    (f64::from(c.x) + 0.5, f64::from(c.y) + 0.5)
}

/// Simulates `config.walkers` walkers on `site`; the observer ids are
/// `walker-01`, `walker-02`, ….
pub fn simulate(site: &Arc<Site>, config: &SimConfig, survey: Option<&Survey>) -> Vec<Event> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(config.seed);
    let places: Vec<(&String, Cell)> = site.places().iter().map(|(n, &c)| (n, c)).collect();
    let phone = Phone::new(site, config, survey);
    let mut events = Vec::new();
    for w in 0..config.walkers {
        let name: Arc<str> = format!("walker-{:02}", w + 1).into();
        let timeline = walk(site, config, &places, &mut rng);
        let phase = rng.random::<f64>() / config.scan_hz;
        let mut t = phase;
        while t < config.duration_s {
            let (cell, pos) = timeline.at(t);
            let at = config.start_t + round_ms(t);
            phone.scan(cell, pos, at, &name, &mut rng, &mut events);
            t += 1.0 / config.scan_hz;
        }
        for s in 0..config.duration_s.floor() as u64 {
            let (cell, _) = timeline.at(s as f64);
            events.push(Event::Truth(Truth {
                t: config.start_t + s as f64,
                device: name.to_string(),
                cell,
                floor: None,
            }));
        }
        for r in 0..config.requests_per_walker {
            if places.is_empty() || config.duration_s <= 10.0 {
                break;
            }
            let when = rng.random_range(10.0..config.duration_s);
            let (to, _) = places[rng.random_range(0..places.len())];
            events.push(Event::Request(RouteRequest {
                t: config.start_t + round_ms(when),
                device: name.to_string(),
                to: Destination::Place(to.clone()),
                floor: None,
                profile: None,
                request_id: Some(format!("{name}-r{}", r + 1)),
            }));
        }
    }
    // Stable sort: events at the same time keep walker order, so output is
    // reproducible.
    events.sort_by(|a, b| a.t().total_cmp(&b.t()));
    events
}

fn round_ms(t: f64) -> f64 {
    (t * 1000.0).round() / 1000.0
}
/// Plans one walker's whole walk.
fn walk(
    site: &Site,
    config: &SimConfig,
    places: &[(&String, Cell)],
    rng: &mut Xoshiro256PlusPlus,
) -> Timeline {
    let open = site.open_cells();
    let pick = |rng: &mut Xoshiro256PlusPlus| -> Cell {
        if !places.is_empty() && rng.random_bool(0.7) {
            places[rng.random_range(0..places.len())].1
        } else {
            open[rng.random_range(0..open.len())]
        }
    };
    let speed = (config.speed_mps * rng.random_range(0.8..1.2)).max(0.3);
    let mut at = pick(rng);
    let mut t = 0.0;
    let mut points = vec![(t, at)];
    while t < config.duration_s {
        let to = pick(rng);
        if let Ok(route) = astar::search(site, Connectivity::Eight, at, to, |_| 1.0) {
            for step in route.cells.windows(2) {
                t += step[0].distance(step[1]) * site.cell_m / speed;
                points.push((t, step[1]));
            }
            at = to;
        }
        // Pause where the walk ends: reading a sign, waiting at a desk.
        t += rng.random_range(2.0..10.0);
        points.push((t, at));
    }
    Timeline { points }
}
