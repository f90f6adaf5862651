//! `gangway eval guidance`: simulated walkers ask the pipeline for a route
//! between two places, then walk it while their phones scan (the path-loss
//! model, or with a survey real readings resampled in the walker's cell), at
//! a steady pace or at the second-by-second pace of recorded walks of real
//! people, and the pipeline's guidance is scored against where they really
//! were:
//!
//! - false off-route per km: off-route while the walker was following
//!   (before a wrong turn too);
//! - wrong turns: with a given probability a walker misses a turn and walks
//!   on to a cell well outside the corridor, where they wait to be told;
//!   counted are the fixes from the first fix of the walker truly outside
//!   the corridor to the off-route message (undetected after a minute
//!   waiting: never);
//! - arrival: detected within one fix of the fix where the walker reached
//!   the destination; an arrival told to a walker who never got there
//!   counts against it;
//! - announcements: how far (truly, along the route, when the message was
//!   sent) each decision point was when announced; in the window when
//!   within 2 m of `announce_m`.
//!
//! A walker told of a re-planned route walks that one.

use std::sync::Arc;

use rand::rngs::Xoshiro256PlusPlus;
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};
use serde::Serialize;

use crate::config::Config;
use crate::eval::planning::percentile;
use crate::event::{Event, RouteRequest};
use crate::guide::{GuidanceEvent, RouteLine};
use crate::locate::survey::Survey;
use crate::pipeline::Pipeline;
use crate::plan::{Connectivity, Destination, Route, astar};
use crate::publish::{Output, RouteOutcome, RouteReply};
use crate::simulate::{Phone, SimConfig};
use crate::site::{Cell, Site};
use crate::walks::Track;

/// What to simulate.
#[derive(Clone, Debug)]
pub struct Setup {
    pub trips: usize,
    pub seed: u64,
    /// Chance that a walker strays at a turn.
    pub wrong_turn_probability: f64,
    /// Mean walking speed; each trip draws its own around it.
    pub speed_mps: f64,
    /// Recorded paces (m/s, second by second: [`paces`]); when given, each
    /// trip walks at the pace of a recorded walk (and of another when the
    /// route outlasts it) instead of a steady speed.
    pub paces: Vec<Vec<f64>>,
}

impl Default for Setup {
    fn default() -> Self {
        Setup {
            trips: 100,
            seed: 1,
            wrong_turn_probability: 0.3,
            speed_mps: 1.1,
            paces: Vec::new(),
        }
    }
}

#[derive(Clone, Debug, Default, Serialize)]
pub struct Report {
    pub trips: usize,
    /// Trips whose request got an error instead of a route.
    pub refused_trips: usize,
    pub km: f64,
    /// Recorded walks whose pace the walkers took (0: a steady pace).
    pub paces_from_walks: usize,
    pub fixes: usize,
    pub false_off_route: usize,
    pub false_off_route_per_km: f64,
    pub wrong_turns: usize,
    pub wrong_turns_undetected: usize,
    /// `null` when more than a tenth of the wrong turns went undetected.
    pub wrong_turn_detect_fixes_p90: Option<f64>,
    pub wrong_turn_detect_fixes_p50: Option<f64>,
    /// Trips that reached their destination.
    pub reached: usize,
    /// Trips told they had arrived that never reached the destination.
    pub false_arrivals: usize,
    /// Share of the trips that reached the destination or were told so
    /// whose arrival was told within one fix of the walker reaching it.
    pub arrival_detected_share: f64,
    /// Decision points passed with room to announce them on their own
    /// (at least `announce_m` after the previous maneuver): the
    /// announcements scored.
    pub decision_points: usize,
    /// Decision points passed closer than that: told with the one before.
    pub decision_points_told_with_previous: usize,
    pub announced_in_window_share: f64,
    pub announced_m_p50: Option<f64>,
    pub reroutes_per_trip: f64,
    /// How far, along the route, the walker truly was ahead of the located
    /// fix when it was published, while following (metres, median), and
    /// how long before the fix's time the walker was where it placed them
    /// (seconds, median): the lag guidance predicts forward from
    /// (`[guidance] fix_lag_s`).
    pub fix_lag_m_p50: Option<f64>,
    pub fix_lag_s_p50: Option<f64>,
    /// Largest state of one session seen, bytes: the session's and its
    /// tracker's belief of a walker walking the route.
    pub max_session_bytes: usize,
}

/// The route a walker is following, as served.
struct Served {
    /// The route's cells, as the reply listed them.
    cells: Vec<Cell>,
    line: RouteLine,
    /// Decision points: where, and metres from the route's start.
    decisions: Vec<(Cell, f64)>,
    /// Decision points the walker truly passed, and how far ahead each was
    /// announced.
    passed: Vec<bool>,
    announced: Vec<Option<f64>>,
    /// The walker's true progress along it.
    truth_m: f64,
}

impl Served {
    /// The route of a reply; `None` for an error.
    fn read(site: &Site, reply: &RouteReply) -> Option<Served> {
        let RouteOutcome::Route(body) = &reply.outcome else {
            return None;
        };
        let (route, line) = body.route_and_line(site);
        let cells = route.cells.clone();
        let decisions: Vec<(Cell, f64)> = body
            .maneuvers
            .iter()
            .filter(|m| m.is_decision())
            .map(|m| (m.at, m.along_m))
            .collect();
        Some(Served {
            line: RouteLine::along(site, &route, &line),
            cells,
            passed: vec![false; decisions.len()],
            announced: vec![None; decisions.len()],
            decisions,
            truth_m: 0.0,
        })
    }
}

/// Where a walker is: metres along its planned cells.
struct Walker {
    plan: Vec<Cell>,
    along: Vec<f64>,
    walked_m: f64,
}

impl Walker {
    fn new(site: &Site, plan: Vec<Cell>) -> Walker {
        let mut along = vec![0.0];
        for w in plan.windows(2) {
            along.push(along.last().unwrap() + w[0].distance(w[1]) * site.cell_m);
        }
        Walker {
            plan,
            along,
            walked_m: 0.0,
        }
    }

    fn done(&self) -> bool {
        self.walked_m >= *self.along.last().unwrap()
    }

    /// The cell the walker is in and its position in cells.
    fn at(&self) -> (Cell, (f64, f64)) {
        let i = self.along.partition_point(|&a| a <= self.walked_m);
        let centre = |c: Cell| (f64::from(c.x) + 0.5, f64::from(c.y) + 0.5);
        if i >= self.plan.len() {
            let c = *self.plan.last().unwrap();
            return (c, centre(c));
        }
        let (a, b) = (self.plan[i - 1], self.plan[i]);
        let f = (self.walked_m - self.along[i - 1]) / (self.along[i] - self.along[i - 1]);
        let ((ax, ay), (bx, by)) = (centre(a), centre(b));
        (
            if f < 0.5 { a } else { b },
            (ax + (bx - ax) * f, ay + (by - ay) * f),
        )
    }
}

/// Runs the trips of `setup` through a pipeline built from `config`.
pub fn evaluate(
    config: &Config,
    site: Arc<Site>,
    survey: Option<&Survey>,
    setup: &Setup,
) -> anyhow::Result<Report> {
    let mut pipeline = Pipeline::new(&config.pipeline(), site.clone())?;
    let sim = SimConfig::hearing(config, &site)?;
    let phone = Phone::new(&site, &sim, survey);
    let guidance = config.guidance.clone();
    let corridor_m = guidance.corridor_m;
    let places: Vec<(&String, Cell)> = site.places().iter().map(|(n, &c)| (n, c)).collect();
    anyhow::ensure!(
        places.len() >= 2,
        "the site needs at least two named places"
    );
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(setup.seed);
    let mut report = Report {
        paces_from_walks: setup.paces.len(),
        ..Report::default()
    };
    let (mut detect, mut announced_m, mut arrivals_ok, mut reroutes) =
        (Vec::new(), Vec::new(), 0, 0);
    let (mut lag_m, mut lag_s) = (Vec::new(), Vec::new());
    for trip in 0..setup.trips {
        let device: Arc<str> = format!("trip-{trip:04}").into();
        let (from, to) = loop {
            let a = places[rng.random_range(0..places.len())];
            let b = places[rng.random_range(0..places.len())];
            if a.1.distance(b.1) * site.cell_m >= 10.0 {
                break (a.1, b.0.clone());
            }
        };
        let mut pace = Pace::new(setup, &mut rng);
        let mut t = sim.start_t + trip as f64 * 10_000.0;
        let mut walker = Walker::new(&site, vec![from]);
        let mut out = Vec::new();
        // Stand at the start until located, then ask.
        for _ in 0..8 {
            scan(
                &mut pipeline,
                &phone,
                &walker,
                &device,
                t,
                &mut rng,
                &mut out,
            );
            t += 1.0;
        }
        out.clear();
        let request = RouteRequest {
            t,
            device: device.to_string(),
            to: Destination::Place(to),
            floor: None,
            profile: None,
            request_id: Some(format!("{device}-r")),
        };
        pipeline.handle(&Event::Request(request), &mut out);
        let Some(mut served) = out.iter().find_map(|o| match o {
            Output::Route(reply) => Served::read(&site, reply),
            _ => None,
        }) else {
            report.refused_trips += 1;
            continue;
        };
        report.trips += 1;
        out.clear();
        let destination = served.line.destination();
        walker = follow(&site, walker.at().0, &served);
        // A wrong turn: at the first turn where another way is open, off
        // to a cell well outside the corridor, there to wait until told. It
        // counts once the walker has passed the turn (a re-route before
        // that cancels it).
        let mut wrong: Option<WrongTurn> = None;
        if rng.random_bool(setup.wrong_turn_probability)
            && let Some((i, away)) = served
                .decisions
                .iter()
                .filter(|d| d.0 != destination && d.1 >= 5.0)
                .find_map(|&(turn, _)| {
                    let i = walker.plan.iter().position(|&c| c == turn)?;
                    Some((i, stray_walk(&site, &served, turn, corridor_m, &mut rng)?))
                })
        {
            let mut plan = walker.plan[..=i].to_vec();
            plan.extend_from_slice(&away[1..]);
            walker = Walker::new(&site, plan);
            wrong = Some(WrongTurn {
                turn_m: walker.along[i],
                diverged: false,
                first_out: None,
            });
        }
        let (mut fixes, mut reach_fix, mut arrived_fix) = (0usize, None, None);
        let mut end_t = None;
        let started = t;
        // The walker's true progress along the route served, over time.
        let mut truth = vec![(t, 0.0)];
        while t - started < 900.0 && end_t.is_none_or(|e| t < e) {
            t += 1.0;
            let before = walker.walked_m;
            walker.walked_m += pace.next(&mut rng);
            report.km +=
                (walker.walked_m.min(*walker.along.last().unwrap()) - before).max(0.0) / 1000.0;
            if walker.done() && end_t.is_none() {
                // At the destination, or lost and waiting to be told.
                end_t = Some(t + if wrong.is_some() { 60.0 } else { 10.0 });
            }
            if let Some(w) = &mut wrong
                && !w.diverged
                && walker.walked_m > w.turn_m
            {
                w.diverged = true;
                report.wrong_turns += 1;
            }
            scan(
                &mut pipeline,
                &phone,
                &walker,
                &device,
                t,
                &mut rng,
                &mut out,
            );
            let (cell, pos) = walker.at();
            let [x_m, y_m] = site.world_of_grid([pos.0, pos.1]);
            let (off_m, progress) =
                served
                    .line
                    .project(&site, (x_m, y_m), served.truth_m, corridor_m);
            let following = off_m <= corridor_m;
            if following {
                served.truth_m = progress;
                truth.push((t, progress));
                for (k, d) in served.decisions.iter().enumerate() {
                    served.passed[k] |= d.1 <= progress + 0.5;
                }
            }
            for output in out.drain(..) {
                if let Output::Location(location) = &output {
                    fixes += 1;
                    let fix = location.cell;
                    if let Some(w) = &mut wrong
                        && w.diverged
                        && w.first_out.is_none()
                        && !following
                    {
                        w.first_out = Some(fixes);
                    }
                    if following
                        && wrong.as_ref().is_none_or(|w| !w.diverged)
                        && !walker.done()
                        && let Some(fix) = fix
                    {
                        let (fix_off, fix_m) =
                            served
                                .line
                                .project(&site, site.metres(fix), progress, corridor_m);
                        if fix_off <= corridor_m {
                            lag_m.push(progress - fix_m);
                            if let Some(was_t) = when_at(&truth, fix_m) {
                                lag_s.push(location.t - was_t);
                            }
                        }
                    }
                    if cell == destination && reach_fix.is_none() {
                        reach_fix = Some(fixes);
                    }
                } else if let Output::Guidance(message) = &output {
                    match message.event {
                        Some(GuidanceEvent::Announce) => {
                            let at = message.next.as_ref().map(|n| n.at);
                            if let Some(k) = served.decisions.iter().position(|d| Some(d.0) == at) {
                                served.announced[k]
                                    .get_or_insert(served.decisions[k].1 - served.truth_m);
                            }
                        }
                        Some(GuidanceEvent::OffRoute) => match wrong.take() {
                            Some(WrongTurn {
                                diverged: true,
                                first_out,
                                ..
                            }) => {
                                detect.push(
                                    fixes.saturating_sub(first_out.unwrap_or(fixes)) as f64 + 1.0,
                                );
                            }
                            // Noise before the turn: the walker will be
                            // re-routed from where they are and follows that.
                            _ => report.false_off_route += 1,
                        },
                        // The walk goes on to the destination: an arrival
                        // told early is scored as such.
                        Some(GuidanceEvent::Arrived) => arrived_fix = arrived_fix.or(Some(fixes)),
                        _ => {}
                    }
                    if let Some(bytes) = pipeline.guided_bytes(&device) {
                        report.max_session_bytes = report.max_session_bytes.max(bytes);
                    }
                } else if let Output::Route(reply) = &output
                    && matches!(&reply.outcome, RouteOutcome::Route(b) if b.reason == Some("off_route"))
                {
                    reroutes += 1;
                    score_announcements(
                        &served,
                        guidance.announce_m,
                        &mut announced_m,
                        &mut report,
                    );
                    if let Some(next) = Served::read(&site, reply) {
                        served = next;
                        truth = vec![(t, 0.0)];
                        walker = follow(&site, cell, &served);
                        end_t = None;
                    }
                }
            }
        }
        report.fixes += fixes;
        score_announcements(&served, guidance.announce_m, &mut announced_m, &mut report);
        match (reach_fix, arrived_fix) {
            (Some(reached), arrived) => {
                report.reached += 1;
                if arrived.is_some_and(|a| a.abs_diff(reached) <= 1) {
                    arrivals_ok += 1;
                }
            }
            (None, Some(_)) => report.false_arrivals += 1,
            (None, None) => {}
        }
        if wrong.is_some_and(|w| w.diverged) {
            report.wrong_turns_undetected += 1;
        }
    }
    let in_window = announced_m
        .iter()
        .filter(|&&m: &&f64| (m - guidance.announce_m).abs() <= 2.0)
        .count();
    report.false_off_route_per_km = report.false_off_route as f64 / report.km.max(f64::EPSILON);
    let mut all_detect = detect.clone();
    all_detect.extend(std::iter::repeat_n(
        f64::INFINITY,
        report.wrong_turns_undetected,
    ));
    report.wrong_turn_detect_fixes_p90 = percentile(&mut all_detect, 0.9).filter(|p| p.is_finite());
    report.wrong_turn_detect_fixes_p50 = percentile(&mut all_detect, 0.5).filter(|p| p.is_finite());
    report.arrival_detected_share =
        arrivals_ok as f64 / (report.reached + report.false_arrivals).max(1) as f64;
    report.announced_in_window_share = in_window as f64 / report.decision_points.max(1) as f64;
    report.announced_m_p50 = percentile(&mut announced_m, 0.5);
    report.fix_lag_m_p50 = percentile(&mut lag_m, 0.5);
    report.fix_lag_s_p50 = percentile(&mut lag_s, 0.5);
    report.reroutes_per_trip = reroutes as f64 / report.trips.max(1) as f64;
    Ok(report)
}

/// A wrong turn a walker is taking.
#[derive(Clone, Copy)]
struct WrongTurn {
    /// Metres along the walker's plan of the turn they miss.
    turn_m: f64,
    /// Whether they have walked past it.
    diverged: bool,
    /// The fix at which they were first truly outside the corridor.
    first_out: Option<usize>,
}

/// When the walker's true progress (`truth`: time, metres, in time order)
/// first reached `progress_m`, interpolated; `None` if it has not.
fn when_at(truth: &[(f64, f64)], progress_m: f64) -> Option<f64> {
    let i = truth.iter().position(|&(_, m)| m >= progress_m)?;
    if i == 0 {
        return Some(truth[0].0);
    }
    let ((t0, m0), (t1, m1)) = (truth[i - 1], truth[i]);
    Some(t0 + (t1 - t0) * (progress_m - m0) / (m1 - m0).max(f64::EPSILON))
}

/// How fast a walker goes each second.
struct Pace<'a> {
    steady_mps: f64,
    recorded: &'a [Vec<f64>],
    walk: usize,
    second: usize,
}

impl<'a> Pace<'a> {
    /// A steady speed around `setup.speed_mps`, or a recorded walk from a
    /// random second of it.
    fn new(setup: &'a Setup, rng: &mut Xoshiro256PlusPlus) -> Pace<'a> {
        let steady_mps = setup.speed_mps * rng.random_range(0.85..1.15);
        let recorded = &setup.paces[..];
        let (walk, second) = if recorded.is_empty() {
            (0, 0)
        } else {
            let walk = rng.random_range(0..recorded.len());
            (walk, rng.random_range(0..recorded[walk].len()))
        };
        Pace {
            steady_mps,
            recorded,
            walk,
            second,
        }
    }

    /// Metres walked in the next second.
    fn next(&mut self, rng: &mut Xoshiro256PlusPlus) -> f64 {
        if self.recorded.is_empty() {
            return self.steady_mps;
        }
        if self.second >= self.recorded[self.walk].len() {
            self.walk = rng.random_range(0..self.recorded.len());
            self.second = 0;
        }
        self.second += 1;
        self.recorded[self.walk][self.second - 1]
    }
}

/// Least mean speed of a recorded track that is a walk (not someone
/// standing about), m/s.
pub const WALKING_MPS: f64 = 0.5;

/// Least duration of a recorded track to take a pace from, seconds.
pub const PACE_MIN_S: f64 = 4.0;

/// The second-by-second pace (m/s) of each recorded track that walks: its
/// positions sampled once a second (interpolated), kept when it lasts at
/// least [`PACE_MIN_S`] and its mean speed is at least [`WALKING_MPS`]
/// (pauses within a walk are kept: people slow down and stop).
pub fn paces(tracks: &[Track]) -> Vec<Vec<f64>> {
    tracks
        .iter()
        .filter_map(|track| {
            let points = &track.points;
            let (t0, t1) = (points.first()?.0, points.last()?.0);
            if t1 - t0 < PACE_MIN_S {
                return None;
            }
            let at = |t: f64| {
                let i = points
                    .partition_point(|p| p.0 <= t)
                    .clamp(1, points.len() - 1);
                let ((ta, a), (tb, b)) = (points[i - 1], points[i]);
                let f = if tb > ta {
                    ((t - ta) / (tb - ta)).clamp(0.0, 1.0)
                } else {
                    1.0
                };
                [a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f]
            };
            let seconds = (t1 - t0).floor() as usize;
            let pace: Vec<f64> = (0..seconds)
                .map(|k| {
                    let (a, b) = (at(t0 + k as f64), at(t0 + k as f64 + 1.0));
                    (b[0] - a[0]).hypot(b[1] - a[1])
                })
                .collect();
            let mean = pace.iter().sum::<f64>() / pace.len() as f64;
            (mean >= WALKING_MPS).then_some(pace)
        })
        .collect()
}

/// A walker at `from` setting off along `served`: to the route's cell
/// nearest to them (the first of those as near), then along it. A person
/// told the way from where the gateway placed them, a cell or two from
/// where they stand, joins the route where it is, as any walker would; they
/// do not walk back to the cell the fix put them in.
fn follow(site: &Site, from: Cell, served: &Served) -> Walker {
    let cells = &served.cells;
    let join = (0..cells.len())
        .min_by(|&a, &b| {
            from.distance(cells[a])
                .total_cmp(&from.distance(cells[b]))
                .then(a.cmp(&b))
        })
        .unwrap_or(0);
    let mut plan = astar::search(site, Connectivity::Eight, from, cells[join], |_| 1.0)
        .map(|r| r.cells)
        .unwrap_or_else(|_| vec![from]);
    plan.extend_from_slice(&cells[join + 1..]);
    Walker::new(site, plan)
}

/// Where a walker who takes a wrong turn at `turn` walks: to a walkable
/// cell 8–20 m from the turn and at least `corridor_m + 3` m from every cell
/// of the route, by a path that leaves the corridor within `2 × corridor_m`
/// of walking past the turn and does not come back into it (a wrong turn at
/// the decision point, not a walk on along the route that leaves it later).
/// `None` when no such cell is there.
fn stray_walk(
    site: &Site,
    served: &Served,
    turn: Cell,
    corridor_m: f64,
    rng: &mut Xoshiro256PlusPlus,
) -> Option<Vec<Cell>> {
    let cells = &served.cells;
    let mut candidates: Vec<Cell> = site
        .open_cells()
        .iter()
        .copied()
        .filter(|&c| {
            (8.0..=20.0).contains(&(c.distance(turn) * site.cell_m))
                && cells
                    .iter()
                    .all(|&r| r.distance(c) * site.cell_m >= corridor_m + 3.0)
        })
        .collect();
    candidates.shuffle(rng);
    candidates.into_iter().find_map(|stray| {
        let away = astar::search(site, Connectivity::Eight, turn, stray, |_| 1.0).ok()?;
        let outside: Vec<bool> = away
            .cells
            .iter()
            .map(|&c| served.line.project(site, site.metres(c), 0.0, 0.0).0 > corridor_m)
            .collect();
        let leaves = outside.iter().position(|&o| o)?;
        let walked_m = Route {
            cells: away.cells[..=leaves].to_vec(),
        }
        .length_m(site);
        (walked_m <= 2.0 * corridor_m && outside[leaves..].iter().all(|&o| o)).then_some(away.cells)
    })
}

/// Adds the decision points of `served` the walker truly passed and how far
/// ahead each was announced; one never announced counts as out of the
/// window. Those less than `announce_m` after the previous maneuver (or the
/// start) cannot be announced on their own at `announce_m`: guidance tells
/// them with the previous one, and they are only counted.
fn score_announcements(
    served: &Served,
    announce_m: f64,
    announced_m: &mut Vec<f64>,
    report: &mut Report,
) {
    let mut previous_m = 0.0;
    for (k, &(_, along)) in served.decisions.iter().enumerate() {
        let leg_m = along - std::mem::replace(&mut previous_m, along);
        if !served.passed[k] {
            continue;
        }
        if leg_m >= announce_m {
            report.decision_points += 1;
            announced_m.extend(served.announced[k]);
        } else {
            report.decision_points_told_with_previous += 1;
        }
    }
}

/// One scan of the walker's phone, through the pipeline.
fn scan(
    pipeline: &mut Pipeline,
    phone: &Phone,
    walker: &Walker,
    device: &Arc<str>,
    t: f64,
    rng: &mut Xoshiro256PlusPlus,
    out: &mut Vec<Output>,
) {
    let (cell, pos) = walker.at();
    let mut events = Vec::new();
    phone.scan(cell, pos, t, device, rng, &mut events);
    for e in &events {
        pipeline.handle(e, out);
    }
}
