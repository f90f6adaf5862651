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
//! [`simulate_walks`] makes the other kind of output: whole walks between
//! places as trajectories, the training data of the path models.

use std::sync::Arc;

use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal};

use super::{Event, RouteRequest, Truth};
use crate::locate::calibrate::Calibration;
use crate::locate::pathloss::{self, PathLossConfig, Radio};
use crate::locate::survey::Survey;
use crate::locate::window::Orientation;
use crate::plan::{Connectivity, Destination, astar};
use crate::sighting::Sighting;
use crate::site::{Cell, Site};
use crate::train::trajectory::Trajectory;

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

/// What a simulated phone hears in one scan: beacons by the path-loss
/// model, or with a survey a real reading taken in (or nearest to) its cell.
pub struct Phone<'a> {
    site: &'a Site,
    config: &'a SimConfig,
    survey: Option<&'a Survey>,
    /// Per beacon of the site, its radio and the spread of its RSSI; `None`
    /// for a beacon without a known position (never heard).
    beacons: Vec<Option<(Radio, Normal<f64>)>>,
    /// Scans in one fingerprint window.
    scans_per_window: f64,
}

impl<'a> Phone<'a> {
    pub fn new(site: &'a Site, config: &'a SimConfig, survey: Option<&'a Survey>) -> Self {
        let beacons = pathloss::anchors(
            site,
            Orientation::Observer,
            &config.pathloss,
            config.calibration.as_ref(),
        )
        .into_iter()
        .map(|anchor| {
            anchor.map(|(_, radio)| {
                let spread = Normal::new(0.0, radio.shadowing_db).expect("validated spread");
                (radio, spread)
            })
        })
        .collect();
        Phone {
            site,
            config,
            survey,
            beacons,
            scans_per_window: (config.scan_hz * config.window_s).max(1.0),
        }
    }

    /// One scan at `t` by `observer` in `cell`, at `pos` (in grid units, from
    /// the map's corner: see [`Site::world_of_grid`]): appends the adverts
    /// heard to `events`.
    pub fn scan(
        &self,
        cell: Cell,
        pos: (f64, f64),
        t: f64,
        observer: &Arc<str>,
        rng: &mut Xoshiro256PlusPlus,
        events: &mut Vec<Event>,
    ) {
        match self.survey {
            Some(survey) => hear_survey(self.site, survey, cell, t, observer, rng, events),
            None => self.hear_model(pos, t, observer, rng, events),
        }
    }

    /// One scan from the radio model at `pos` (grid units).
    fn hear_model(
        &self,
        (gx, gy): (f64, f64),
        t: f64,
        observer: &Arc<str>,
        rng: &mut Xoshiro256PlusPlus,
        events: &mut Vec<Event>,
    ) {
        let here = self.site.world_of_grid([gx, gy]);
        for (beacon, model) in self.site.beacons.iter().zip(&self.beacons) {
            let (Some(mount), Some((radio, spread))) = (beacon.mount, model) else {
                continue;
            };
            let distance_m = mount.distance_m(here);
            // Heard in a scan with the probability that makes a window of
            // `scans_per_window` scans hear it as often as the model says.
            let in_window = radio.detection(distance_m);
            let in_scan = 1.0 - (1.0 - in_window).powf(1.0 / self.scans_per_window);
            if !rng.random_bool(in_scan) || rng.random_bool(self.config.dropout) {
                continue;
            }
            let rssi = radio.expected_rssi(distance_m) + spread.sample(rng);
            if rssi < self.config.pathloss.sensitivity_dbm {
                continue;
            }
            events.push(Event::Advert(Sighting {
                t,
                observer: observer.clone(),
                advertiser: beacon.beacon,
                // What the beacon's frame advertises, not what it measures.
                tx_power: Some(
                    beacon
                        .tx_power
                        .map_or(self.config.pathloss.tx_power_dbm, f64::from)
                        .round() as i8,
                ),
                rssi: rssi.round() as i16,
            }));
        }
    }
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

fn hear_survey(
    site: &Site,
    survey: &Survey,
    cell: Cell,
    t: f64,
    observer: &Arc<str>,
    rng: &mut Xoshiro256PlusPlus,
    events: &mut Vec<Event>,
) {
    // The survey's nearest surveyed cell stands in for cells it never visited.
    let nearest = survey
        .samples
        .iter()
        .map(|s| s.cell)
        .min_by(|a, b| a.distance(cell).total_cmp(&b.distance(cell)))
        .expect("a survey has samples");
    let rows: Vec<_> = survey
        .samples
        .iter()
        .filter(|s| s.cell == nearest)
        .collect();
    let row = rows[rng.random_range(0..rows.len())];
    for (beacon, rssi) in site.beacons.iter().zip(&row.rssi) {
        if let Some(rssi) = *rssi {
            events.push(Event::Advert(Sighting {
                t,
                observer: observer.clone(),
                advertiser: beacon.beacon,
                tx_power: beacon.tx_power,
                rssi,
            }));
        }
    }
}

/// What to simulate for path-model training data (`gangway simulate --trajectories`).
#[derive(Clone, Debug)]
pub struct WalkConfig {
    /// Walks between each pair of named places (one direction per pair: from
    /// the place that sorts first, so a frame's class is unambiguous).
    pub walks_per_pair: usize,
    /// Extra walks between random walkable cells at least `min_cells` apart,
    /// so a conditional model sees more than the named pairs.
    pub random_walks: usize,
    pub min_cells: u16,
    pub seed: u64,
    pub speed_mps: f64,
    pub start_t: f64,
}

impl Default for WalkConfig {
    fn default() -> Self {
        WalkConfig {
            walks_per_pair: 50,
            random_walks: 600,
            min_cells: 5,
            seed: 1,
            speed_mps: SimConfig::default().speed_mps,
            start_t: SimConfig::default().start_t,
        }
    }
}

/// Walks people make between places, with human variation around the shortest
/// route. Each walk draws its own preferences and hands them to A* as per-cell
/// cost factors:
/// - keeping off walls: cells next to blocked cells cost extra, by a per-walk
///   wall aversion (so walkers keep to corridor middles where there is room);
/// - taste: every cell gets a small random surcharge, so equal-length routes
///   are chosen differently and open areas are crossed on varied diagonals
///   (corners are cut wherever the floor is open: 8-connected steps);
/// - detours: with probability 0.15 the walk goes via a random cell near its
///   route (looking at a shelf), loops cut out.
///
/// Times follow a per-walk speed with ±15 % jitter per step. The same site and
/// config give the same walks.
pub fn simulate_walks(site: &Site, config: &WalkConfig) -> Vec<Trajectory> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(config.seed);
    let places: Vec<Cell> = site.places().values().copied().collect();
    let mut pairs = Vec::new();
    for (i, &a) in places.iter().enumerate() {
        for &b in &places[i + 1..] {
            if a != b {
                pairs.extend(std::iter::repeat_n((a, b), config.walks_per_pair));
            }
        }
    }
    let open = site.open_cells();
    let mut random_pairs = 0;
    // Bounded: a site too small for `min_cells` gets fewer random walks.
    for _ in 0..config.random_walks * 100 {
        if random_pairs == config.random_walks {
            break;
        }
        let a = open[rng.random_range(0..open.len())];
        let b = open[rng.random_range(0..open.len())];
        if a.chebyshev(b) >= config.min_cells {
            pairs.push((a, b));
            random_pairs += 1;
        }
    }
    let near_wall: Vec<f64> = open
        .iter()
        .map(|&c| blocked_neighbours(site, c) as f64 / 8.0)
        .collect();
    let mut walks = Vec::with_capacity(pairs.len());
    let mut t0 = config.start_t;
    for (from, to) in pairs {
        let aversion = rng.random_range(0.5..2.0);
        let taste: Vec<f64> = (0..open.len())
            .map(|_| rng.random_range(0.0..0.35))
            .collect();
        let cost = |c: Cell| {
            let i = site.open_index(c).expect("search visits walkable cells");
            1.0 + aversion * near_wall[i] + taste[i]
        };
        let Ok(route) = astar::search(site, Connectivity::Eight, from, to, cost) else {
            continue; // disconnected floor: nobody walks this pair
        };
        let mut cells = route.cells;
        if cells.len() > 2 && rng.random_bool(0.15) {
            let around = cells[rng.random_range(1..cells.len() - 1)];
            let near: Vec<Cell> = open
                .iter()
                .copied()
                .filter(|c| c.chebyshev(around) <= 3 && *c != from && *c != to)
                .collect();
            let via = near[rng.random_range(0..near.len())];
            if let (Ok(first), Ok(second)) = (
                astar::search(site, Connectivity::Eight, from, via, cost),
                astar::search(site, Connectivity::Eight, via, to, cost),
            ) {
                cells = first.cells;
                cells.extend_from_slice(&second.cells[1..]);
                cut_loops(&mut cells);
            }
        }
        let speed = (config.speed_mps * rng.random_range(0.75..1.25)).max(0.3);
        let mut t = t0;
        let mut times = vec![round_ms(t)];
        for step in cells.windows(2) {
            t += step[0].distance(step[1]) * site.cell_m / speed * rng.random_range(0.85..1.15);
            times.push(round_ms(t));
        }
        walks.push(Trajectory {
            site: site.name.clone(),
            device: format!("sim-{:04}", walks.len() + 1),
            cells,
            times,
            profile: None,
            feedback: None,
            positions_m: None,
        });
        // Walks start a few minutes apart.
        t0 = round_ms(t0 + rng.random_range(30.0..300.0));
    }
    walks
}

/// Blocked or off-grid cells among the 8 neighbours.
fn blocked_neighbours(site: &Site, c: Cell) -> usize {
    let mut n = 0;
    for dy in -1i32..=1 {
        for dx in -1i32..=1 {
            if (dx, dy) == (0, 0) {
                continue;
            }
            let (x, y) = (i32::from(c.x) + dx, i32::from(c.y) + dy);
            let walkable = x >= 0 && y >= 0 && site.walkable(Cell::new(x as u16, y as u16));
            n += usize::from(!walkable);
        }
    }
    n
}

/// Removes the loop between two visits of the same cell, so a walk with a
/// detour is still a simple path.
fn cut_loops(cells: &mut Vec<Cell>) {
    let mut out: Vec<Cell> = Vec::with_capacity(cells.len());
    for &c in cells.iter() {
        if let Some(i) = out.iter().position(|&o| o == c) {
            out.truncate(i);
        }
        out.push(c);
    }
    *cells = out;
}

#[cfg(test)]
mod walk_tests {
    use super::*;
    use std::path::Path;

    fn site() -> Site {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n##########\n##########\n##########\n####..####\n##########\n'''\n[places]\na = [0, 0]\nb = [9, 4]\nc = [9, 0]\n";
        Site::parse(text, Path::new("t.toml")).unwrap()
    }

    #[test]
    fn walks_are_valid_varied_and_reproducible() {
        let site = site();
        let config = WalkConfig {
            walks_per_pair: 20,
            random_walks: 10,
            ..WalkConfig::default()
        };
        let walks = simulate_walks(&site, &config);
        assert_eq!(walks.len(), 3 * 20 + 10);
        for w in &walks {
            w.check(&site).unwrap();
            let unique: std::collections::HashSet<_> = w.cells.iter().collect();
            assert_eq!(unique.len(), w.cells.len(), "no cell twice");
        }
        let ab: std::collections::HashSet<_> = walks[..20].iter().map(|w| &w.cells).collect();
        assert!(ab.len() > 3, "walks between one pair vary: {}", ab.len());
        assert!(
            walks[..20]
                .iter()
                .all(|w| w.source() == Cell::new(0, 0) && w.destination() == Cell::new(9, 4))
        );
        let shortest = astar::search(
            &site,
            Connectivity::Eight,
            Cell::new(0, 0),
            Cell::new(9, 4),
            |_| 1.0,
        )
        .unwrap()
        .length_m(&site);
        let mean: f64 = walks[..20]
            .iter()
            .map(|w| {
                crate::plan::Route {
                    cells: w.cells.clone(),
                }
                .length_m(&site)
            })
            .sum::<f64>()
            / 20.0;
        assert!(mean < shortest * 1.3, "near-shortest: {mean} vs {shortest}");
        assert_eq!(simulate_walks(&site, &config), walks);
    }

    #[test]
    fn cutting_loops_keeps_a_simple_path() {
        let c = |x, y| Cell::new(x, y);
        let mut cells = vec![c(0, 0), c(1, 0), c(2, 0), c(1, 0), c(1, 1)];
        cut_loops(&mut cells);
        assert_eq!(cells, vec![c(0, 0), c(1, 0), c(1, 1)]);
    }
}
