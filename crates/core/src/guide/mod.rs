//! Guidance while walking: once a route is served, a navigation session per
//! device follows each fix along it, tells the walker the next maneuver and
//! how far it is, announces decision points a set distance ahead, reassures
//! at intervals, notices when the walker has left the route (so the pipeline
//! can re-plan) and when they have arrived.
//!
//! Owns the sessions ([`Guide`], bounded in number and in idle time, since
//! devices come from the air) and the state machine of one ([`Session`]).
//! It does no I/O and keeps no clock: the pipeline feeds it fixes and the
//! time of every other event of a guided device ([`Guide::tick`]: progress
//! is predicted between fixes, so announcements and arrival need not wait
//! for the next one), and sends the [`Guidance`] messages it
//! returns. The maneuvers are
//! the route's own ([`crate::plan::instructions::maneuvers`]), so what is
//! announced is what the route reply listed.
//!
//! Each finished session (arrived, cancelled, expired or replaced by a new
//! request) leaves an [`Adherence`]: how well the walk followed the route,
//! the implicit feedback the learning store keeps and training weighs walks
//! and routes by (`gangway train --from-store`).
//!
//! Thresholds follow the Wayfindr open standard (ITU-T F.921): a decision
//! point is announced about 6 m ahead, reassurance about every 10 m.

mod line;
mod progress;
mod session;

use std::collections::{HashMap, VecDeque};

use serde::{Deserialize, Serialize};

pub use line::RouteLine;
pub(crate) use progress::Progress;
pub(crate) use session::Session;

use crate::locate::tracker::ExpectedWalk;
use crate::plan::anyangle::GridPoint;
use crate::plan::{Profile, Route};
use crate::site::{Cell, Site};

/// `[guidance]` in the config file.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct GuidanceConfig {
    /// Announce a decision point when the walker is this far from it, metres.
    pub announce_m: f64,
    /// Reassure the walker after this much progress without a message, metres.
    pub reassure_m: f64,
    /// Half-width of the corridor around the route, metres: a fix farther
    /// than this from the route counts towards leaving it.
    pub corridor_m: f64,
    /// Consecutive fixes outside the corridor before the walker is off the
    /// route (hysteresis against localization noise). Unknown fixes neither
    /// count nor reset the count.
    pub off_route_fixes: u32,
    /// The walker has arrived within this distance of the destination, metres.
    pub arrive_m: f64,
    /// A fix near the destination means arrival only once the walker has
    /// come this share of the route (a route that starts or passes near
    /// its destination is not over at once).
    pub arrive_progress_share: f64,
    /// How far, one standard deviation, a fix's progress along the route
    /// strays from the walker's, metres: how much the progress filter
    /// trusts one fix.
    pub fix_spread_m: f64,
    /// How long before a fix's time (the end of its window) the walker was
    /// where it places them, seconds: progress is predicted forward from
    /// then. Default: half of `[window] length_s` (a fix stands for the
    /// middle of its window). `gangway eval guidance` reports the lag it
    /// measured (`fix_lag_s_p50`).
    pub fix_lag_s: Option<f64>,
    /// Share of a guided walker's mass the tracker walks on along their
    /// route at their pace from one fix to the next, in the second belief
    /// progress is read off (the rest spreads as anyone's does): people
    /// told the way walk it. 0: none.
    pub walk_prior: f32,
    /// Most sessions kept at once; starting one more ends the least
    /// recently updated.
    pub max_sessions: usize,
    /// A session whose device has not been located for this long expires,
    /// seconds.
    pub expire_after_s: f64,
}

impl Default for GuidanceConfig {
    fn default() -> Self {
        GuidanceConfig {
            announce_m: 6.0,
            reassure_m: 10.0,
            corridor_m: 3.0,
            off_route_fixes: 2,
            arrive_m: 2.0,
            arrive_progress_share: 0.5,
            fix_spread_m: 2.0,
            fix_lag_s: None,
            walk_prior: 0.5,
            max_sessions: 1024,
            expire_after_s: 600.0,
        }
    }
}

impl GuidanceConfig {
    /// `fix_lag_s`, or its default for fixes from `window`.
    pub(crate) fn fix_lag_s(&self, window: &crate::locate::window::WindowConfig) -> f64 {
        self.fix_lag_s.unwrap_or(window.length_s / 2.0)
    }

    pub fn validate(&self) -> Result<(), String> {
        let positive = [
            ("announce_m", self.announce_m),
            ("reassure_m", self.reassure_m),
            ("corridor_m", self.corridor_m),
            ("arrive_m", self.arrive_m),
            ("fix_spread_m", self.fix_spread_m),
            ("expire_after_s", self.expire_after_s),
        ];
        if let Some((name, _)) = positive.iter().find(|(_, v)| !(*v > 0.0 && v.is_finite())) {
            return Err(format!("[guidance] `{name}` must be a positive number"));
        }
        if !(0.0..=1.0).contains(&self.arrive_progress_share) {
            return Err("[guidance] `arrive_progress_share` must be between 0 and 1".into());
        }
        if !(0.0..=1.0).contains(&self.walk_prior) {
            return Err("[guidance] `walk_prior` must be between 0 and 1".into());
        }
        if self
            .fix_lag_s
            .is_some_and(|lag| !(lag >= 0.0 && lag.is_finite()))
        {
            return Err("[guidance] `fix_lag_s` must be a number of seconds, 0 or more".into());
        }
        if self.off_route_fixes == 0 || self.max_sessions == 0 {
            return Err(
                "[guidance] `off_route_fixes` and `max_sessions` must be at least 1".into(),
            );
        }
        Ok(())
    }
}

/// Where a session stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SessionState {
    /// Following the route as served.
    Active,
    /// Left the corridor for `off_route_fixes` fixes; a new plan is due.
    OffRoute,
    /// Following a route re-planned after leaving the first one.
    Rerouted,
    /// At the destination; the session is over.
    Arrived,
    /// Ended by the device or replaced by a new request.
    Cancelled,
    /// Not located for `expire_after_s`; the session is over.
    Expired,
}

/// What a guidance message says beyond the progress every one carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum GuidanceEvent {
    /// A route was served: the first step.
    Depart,
    /// A re-planned route was served after leaving the route.
    Rerouted,
    /// The next decision point is about `announce_m` ahead.
    Announce,
    /// Still on the route, `reassure_m` after the last message.
    Reassure,
    OffRoute,
    Arrived,
    /// At the connector that ends one floor's leg of a route across
    /// floors: the text says which to take and to which floor, and the
    /// next floor's leg is guided once the walker is located there.
    Connector,
    Cancelled,
    Expired,
}

/// How a session ended, for its adherence.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Ending {
    Arrived,
    Cancelled,
    Expired,
    /// A new request of the device replaced it (or, the table being full,
    /// another device's session needed its room, or a reload onto another
    /// grid ended it).
    Replaced,
}

impl Ending {
    pub fn name(self) -> &'static str {
        match self {
            Ending::Arrived => "arrived",
            Ending::Cancelled => "cancelled",
            Ending::Expired => "expired",
            Ending::Replaced => "replaced",
        }
    }

    pub fn parse(name: &str) -> Option<Ending> {
        [
            Ending::Arrived,
            Ending::Cancelled,
            Ending::Expired,
            Ending::Replaced,
        ]
        .into_iter()
        .find(|e| e.name() == name)
    }
}

/// How a finished session's walk followed its route (re-routes included):
/// the implicit feedback of someone who was guided.
#[derive(Clone, Debug, PartialEq)]
pub struct Adherence {
    pub device: String,
    /// The request whose route was followed.
    pub request_id: Option<String>,
    pub started_t: f64,
    /// When the session ended.
    pub t: f64,
    pub ending: Ending,
    /// Share of the located fixes within the corridor around the route.
    pub in_corridor_share: f64,
    /// Times the walker left the route.
    pub detours: u32,
    pub arrived: bool,
    /// The route's length at the profile's walking speed, seconds.
    pub expected_s: f64,
    /// Time from the route being served to the session's end, seconds.
    pub taken_s: f64,
}

impl Adherence {
    /// The walk's adherence as feedback in [0, 1]: the share walked within
    /// the corridor, times the pace against the expected time (at most 1),
    /// divided by one more than the detours, halved when the walker never
    /// arrived. A route followed to its end at the expected pace scores 1;
    /// one left twice and abandoned scores little.
    pub fn score(&self) -> f64 {
        let pace = if self.taken_s > 0.0 {
            (self.expected_s / self.taken_s).min(1.0)
        } else {
            1.0
        };
        let arrived = if self.arrived { 1.0 } else { 0.5 };
        (self.in_corridor_share * pace * arrived / (1.0 + f64::from(self.detours))).clamp(0.0, 1.0)
    }
}

/// The schema of a guidance payload, sent in its `schema` field.
pub(crate) const GUIDANCE_SCHEMA: &str = "gangway.guidance/1";

/// Where a guided device stands on its route, after a fix or a change of
/// session. Every key is always present (`null` when it does not apply), so
/// Home Assistant templates can read any of them.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Guidance {
    pub schema: &'static str,
    pub device: String,
    pub t: f64,
    /// The request the route answered.
    pub request_id: Option<String>,
    pub state: SessionState,
    /// What this message announces; `null` for a plain progress update.
    pub event: Option<GuidanceEvent>,
    /// The sentence to speak with `event`.
    pub text: Option<String>,
    /// The next decision point (turn or arrival); `null` once the session is over.
    pub next: Option<NextManeuver>,
    /// Metres walked along the route.
    pub progress_m: f64,
    /// Metres left to the destination.
    pub remaining_m: f64,
    /// Seconds left at the profile's walking speed.
    pub eta_s: f64,
    /// Consecutive fixes outside the corridor around the route.
    pub off_route_fixes: u32,
    /// Routes re-planned in this session after leaving the route.
    pub reroutes: u32,
}

/// The next maneuver of a guided walk and how far it is.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct NextManeuver {
    #[serde(rename = "type")]
    pub kind: crate::plan::instructions::ManeuverType,
    pub modifier: Option<crate::plan::instructions::Modifier>,
    /// Metres along the route from the device to the maneuver.
    pub distance_m: f64,
    pub at: Cell,
    pub place: Option<String>,
}

/// The sessions of all devices, bounded in number and time.
pub struct Guide {
    config: GuidanceConfig,
    fix_lag_s: f64,
    sessions: HashMap<String, Session>,
    /// Adherence of finished sessions not yet taken (at most
    /// `max_sessions`: the oldest go when nobody takes them).
    finished: VecDeque<Adherence>,
}

/// A located fix as guidance follows it: the tracker's cell, and where its
/// belief is on average (metres; the cell's centre when not given).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Located {
    pub cell: Cell,
    /// The mean of the tracker's belief (the pipeline passes that of the
    /// belief walked along the route, `Tracker::update_walking`, while
    /// there is one): how far along the route the walker is reads off it
    /// rather than off the cell, which moves a whole cell at a time and
    /// sticks while the belief drifts on (`gangway eval guidance`,
    /// docs/guidance.md: announcements 85.0 % → 85.7 %; 90.1 % walked).
    pub mean_m: Option<(f64, f64)>,
}

impl Located {
    /// The tracker's `cell` with its belief's mean at `mean_grid` (grid
    /// coordinates, cell centres at + 0.5: [`crate::locate::tracker::Fix`]).
    pub fn with_mean(site: &Site, cell: Cell, mean_grid: [f64; 2]) -> Located {
        let [x, y] = site.world_of_grid(mean_grid);
        Located {
            cell,
            mean_m: Some((x, y)),
        }
    }
}

impl From<Cell> for Located {
    fn from(cell: Cell) -> Located {
        Located { cell, mean_m: None }
    }
}

impl Guide {
    /// `fix_lag_s`: how long ago the walker was where a fix places them
    /// ([`GuidanceConfig::fix_lag_s`]).
    pub fn new(config: GuidanceConfig, fix_lag_s: f64) -> Guide {
        Guide {
            config,
            fix_lag_s,
            sessions: HashMap::new(),
            finished: VecDeque::new(),
        }
    }

    /// The adherence of the sessions finished since the last call.
    pub(crate) fn take_finished(&mut self) -> Vec<Adherence> {
        self.finished.drain(..).collect()
    }

    /// Keeps the adherence of `session` of `device`, ending at `t` (a
    /// session that arrived ends so, however it is then dropped).
    fn finish(&mut self, device: &str, session: &Session, t: f64, ending: Ending) {
        let ending = if session.state() == SessionState::Arrived {
            Ending::Arrived
        } else {
            ending
        };
        if let Some(adherence) = session.adherence(device, t, ending) {
            if self.finished.len() >= self.config.max_sessions {
                self.finished.pop_front();
            }
            self.finished.push_back(adherence);
        }
    }

    /// Active sessions.
    #[cfg(test)]
    pub(crate) fn len(&self) -> usize {
        self.sessions.len()
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.sessions.is_empty()
    }

    /// After a reload: takes over the sessions of `old`, the guide being
    /// replaced, when the new site has the same grid (at most this guide's
    /// `max_sessions`, the most recently updated first), and the adherence
    /// of those finished. On another grid the routes' cells may no longer
    /// be walkable: the sessions end `replaced`, their adherence kept, and
    /// their devices ask again.
    pub(crate) fn take_over(&mut self, old: &mut Guide, same_grid: bool) {
        let mut sessions: Vec<(String, Session)> = old.sessions.drain().collect();
        sessions.sort_by(|a, b| b.1.last_t().total_cmp(&a.1.last_t()));
        let keep = if same_grid {
            self.config.max_sessions.min(sessions.len())
        } else {
            0
        };
        for (device, session) in &sessions[keep..] {
            old.finish(device, session, session.last_t(), Ending::Replaced);
        }
        sessions.truncate(keep);
        self.sessions.extend(sessions);
        self.finished.extend(old.finished.drain(..));
        while self.finished.len() > self.config.max_sessions {
            self.finished.pop_front();
        }
    }

    pub(crate) fn session(&self, device: &str) -> Option<&Session> {
        self.sessions.get(device)
    }

    /// Starts guiding `device` along `route`, walked along `line` (cell
    /// units, the reply's line: [`crate::plan::ServedLine`]), replacing any
    /// session it had, and returns the first message. `rerouted` marks a route re-planned
    /// after the walker left the previous one. Sessions idle past
    /// `expire_after_s` are dropped, and when the table is full the least
    /// recently updated session makes room.
    #[allow(clippy::too_many_arguments)]
    pub fn start(
        &mut self,
        site: &Site,
        device: &str,
        request_id: Option<String>,
        profile: Profile,
        route: &Route,
        line: &[GridPoint],
        t: f64,
        rerouted: bool,
    ) -> Guidance {
        let expire = self.config.expire_after_s;
        let idle: Vec<(String, Session)> = self
            .sessions
            .extract_if(|_, s| t - s.last_t() > expire)
            .collect();
        for (d, s) in idle {
            self.finish(&d, &s, t, Ending::Expired);
        }
        let end = route.cells.last().copied();
        let (rerouted_from, leg_end) = match self.sessions.remove(device) {
            // Re-planned to the end of a floor's leg: still walks to its
            // connector.
            Some(old) if rerouted => (Some(old.walked()), end.and_then(|end| old.leg_end_at(end))),
            Some(old) => {
                self.finish(device, &old, t, Ending::Replaced);
                (None, None)
            }
            None => (None, None),
        };
        if self.sessions.len() >= self.config.max_sessions
            && let Some(oldest) = self
                .sessions
                .iter()
                .min_by(|a, b| a.1.last_t().total_cmp(&b.1.last_t()))
                .map(|(d, _)| d.clone())
            && let Some(old) = self.sessions.remove(&oldest)
        {
            self.finish(&oldest, &old, t, Ending::Replaced);
        }
        let session = Session::new(
            site,
            &self.config,
            request_id,
            profile,
            RouteLine::along(site, route, line),
            t,
            rerouted_from,
        )
        .with_leg_end(leg_end);
        let first = session.depart(site, device, t);
        self.sessions.insert(device.to_owned(), session);
        first
    }

    /// Follows one fix of `device` (a cell or a [`Located`]; `None`:
    /// location unknown) of time `t`
    /// (the end of its window), made at `now` (the event that closed the
    /// window). Returns a message when the device has a session and the
    /// fix was known, or when the session just expired; a session that
    /// expired ends with its message. One that arrived is watched quietly
    /// for `off_route_fixes` fixes and one more: a walker who walks on off
    /// the route (told of arriving too soon) gets `off_route`, and a new
    /// route, like any other.
    pub fn update(
        &mut self,
        site: &Site,
        device: &str,
        fix: Option<impl Into<Located>>,
        t: f64,
        now: f64,
    ) -> Option<Guidance> {
        let session = self.sessions.get_mut(device)?;
        if t - session.last_t() > self.config.expire_after_s {
            let last = (session.state() != SessionState::Arrived)
                .then(|| session.end(device, t, SessionState::Expired));
            let session = self.sessions.remove(device)?;
            self.finish(device, &session, t, Ending::Expired);
            return last;
        }
        let fix = fix.map(Into::into);
        let message = session.update(site, &self.config, self.fix_lag_s, device, fix, t, now);
        if session.is_over(&self.config)
            && let Some(session) = self.sessions.remove(device)
        {
            self.finish(device, &session, t, Ending::Arrived);
        }
        message
    }

    /// Judges the progress of `device` at `now`, the time of one of its
    /// events between fixes (a sighting): a message only when its session
    /// has something to say then (an announcement, reassurance, arrival).
    /// Cheap for a device without a session, and for the many events of
    /// one moment (judged once).
    pub fn tick(&mut self, site: &Site, device: &str, now: f64) -> Option<Guidance> {
        let session = self.sessions.get_mut(device)?;
        session.tick(site, &self.config, self.fix_lag_s, device, now)
    }

    /// How `device`, if it is being guided and following its route, is
    /// expected to have walked by the fix of time `t`: for its tracker.
    pub fn expected_walk(&self, site: &Site, device: &str, t: f64) -> Option<ExpectedWalk> {
        if self.config.walk_prior <= 0.0 {
            return None;
        }
        let moves = self.sessions.get(device)?.expected_walk(site, t)?;
        Some(ExpectedWalk {
            moves,
            share: self.config.walk_prior,
        })
    }

    /// Makes the session of `device` one floor's leg of a route across
    /// floors, ending at a connector (`Session::end_at_connector`); returns
    /// its first message, which walks to the connector.
    pub(crate) fn end_at_connector(
        &mut self,
        site: &Site,
        device: &str,
        noun: String,
        ride: String,
        t: f64,
    ) -> Option<Guidance> {
        let session = self.sessions.get_mut(device)?;
        session.end_at_connector(noun, ride);
        Some(session.depart(site, device, t))
    }

    /// Ends the session of `device`, if it has one, without a message: it
    /// left this floor, and the next floor's guide takes it on.
    pub(crate) fn leave(&mut self, device: &str, t: f64) {
        if let Some(session) = self.sessions.remove(device) {
            self.finish(device, &session, t, Ending::Replaced);
        }
    }

    /// Ends the session of `device`, if it has one (one that has arrived
    /// has nothing left to cancel).
    pub(crate) fn cancel(&mut self, device: &str, t: f64) -> Option<Guidance> {
        let session = self.sessions.remove(device)?;
        self.finish(device, &session, t, Ending::Cancelled);
        (session.state() != SessionState::Arrived)
            .then(|| session.end(device, t, SessionState::Cancelled))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    /// An open 25 × 20 floor with a desk at the corner of an L-shaped route
    /// and an exit at its end.
    fn site() -> Site {
        let row = "#".repeat(25);
        let map = vec![row; 20].join("\n");
        let text = format!(
            "name = \"t\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n[places]\ndesk = [20, 0]\nexit = [20, 15]\n"
        );
        Site::parse(&text, Path::new("t.toml")).unwrap()
    }

    /// East along the top row to the desk, then south to the exit: 35 m.
    fn route() -> Route {
        let east = (0..=20).map(|x| Cell::new(x, 0));
        let south = (1..=15).map(|y| Cell::new(20, y));
        Route {
            cells: east.chain(south).collect(),
        }
    }

    fn start(guide: &mut Guide, site: &Site, device: &str, t: f64) -> Guidance {
        guide.start(
            site,
            device,
            Some("r1".into()),
            Profile::Default,
            &route(),
            &cells_line(&route()),
            t,
            false,
        )
    }

    fn cells_line(route: &Route) -> Vec<GridPoint> {
        crate::plan::ServedLine::of_cells(route).points
    }

    /// Where a walker at the profile's pace (1.2 m/s) truly is along
    /// `route()` at `t`, in metres, and the route cell there.
    fn walked(t: f64) -> (f64, Cell) {
        let m = (1.2 * t).clamp(0.0, 35.0);
        (m, route().cells[m.round() as usize])
    }

    #[test]
    fn a_walk_is_announced_in_time_between_late_fixes_and_arrives() {
        let site = site();
        // Fixes every 2 s showing where the walker was 2 s before; the
        // device's other events every half second.
        let mut guide = Guide::new(GuidanceConfig::default(), 2.0);
        let first = start(&mut guide, &site, "p", 0.0);
        assert_eq!(first.event, Some(GuidanceEvent::Depart));
        assert_eq!(
            first.text.as_deref(),
            Some("Walk 20 metres, then turn right at desk.")
        );
        assert_eq!(first.remaining_m, 35.0);
        assert!((first.eta_s - 35.0 / 1.2).abs() < 1e-9);
        let mut events = Vec::new();
        for k in 1..=80 {
            let now = 0.5 * f64::from(k);
            let m = if k % 4 == 0 {
                let fix = walked(now - 2.0).1;
                guide.update(&site, "p", Some(fix), now, now)
            } else {
                guide.tick(&site, "p", now)
            };
            let Some(m) = m else { continue };
            if let Some(e) = m.event {
                events.push((walked(now).0, e, m.text.clone().unwrap()));
            }
            if m.state == SessionState::Arrived {
                break;
            }
        }
        let got: Vec<GuidanceEvent> = events.iter().map(|e| e.1).collect();
        assert_eq!(
            got,
            [
                GuidanceEvent::Reassure,
                GuidanceEvent::Announce,
                GuidanceEvent::Reassure,
                GuidanceEvent::Announce,
                GuidanceEvent::Arrived,
            ],
            "{events:?}"
        );
        // Announced when truly 6 m before the turn and the exit (give or
        // take half a cell: the fixes are whole cells), not up to a fix late.
        assert!((20.0 - events[1].0 - 6.0).abs() <= 0.5, "{events:?}");
        assert_eq!(events[1].2, "Walk 6 metres, then turn right at desk.");
        assert!((35.0 - events[3].0 - 6.0).abs() <= 0.5, "{events:?}");
        assert_eq!(events[3].2, "Walk 6 metres; you have arrived at exit.");
        assert!(events[4].0 >= 35.0 - 0.6, "{events:?}");
        assert_eq!(events[4].2, "You have arrived at exit.");
        // Watched quietly for a few fixes more (the walker stays), then over.
        let exit = Some(Cell::new(20, 15));
        for k in 0..5 {
            let t = 40.0 + 2.0 * f64::from(k);
            assert_eq!(guide.update(&site, "p", exit, t, t), None);
            assert_eq!(guide.tick(&site, "p", t + 1.0), None);
        }
        assert!(guide.is_empty(), "an arrived session ends");
        assert_eq!(guide.take_finished()[0].ending, Ending::Arrived);
    }

    #[test]
    fn a_walker_told_of_arriving_who_walks_on_is_told_they_left() {
        let site = site();
        let mut guide = Guide::new(GuidanceConfig::default(), 0.0);
        start(&mut guide, &site, "p", 0.0);
        let mut t = 0.0;
        let told = loop {
            t += 1.0;
            let m = guide.update(&site, "p", Some(walked(t).1), t, t).unwrap();
            if m.state == SessionState::Arrived {
                break t;
            }
        };
        // On past the exit, 4 and 4 m off the end of the route.
        let past = Some(Cell::new(20, 19));
        assert_eq!(guide.update(&site, "p", past, told + 2.0, told + 2.0), None);
        let left = guide
            .update(&site, "p", past, told + 4.0, told + 4.0)
            .unwrap();
        assert_eq!(
            (left.state, left.event),
            (SessionState::OffRoute, Some(GuidanceEvent::OffRoute))
        );
        assert!(left.text.unwrap().contains("past the destination"));
        assert!(guide.session("p").is_some(), "kept for the new route");
    }

    #[test]
    fn leaving_the_route_takes_consecutive_known_fixes() {
        let site = site();
        let mut guide = Guide::new(GuidanceConfig::default(), 0.0);
        start(&mut guide, &site, "p", 0.0);
        let on = Some(Cell::new(5, 1));
        let off = Some(Cell::new(5, 8));
        let state = |m: Option<Guidance>| m.map(|m| (m.state, m.event, m.off_route_fixes));
        // One stray fix, then back: noise, not a wrong turn.
        assert_eq!(
            state(guide.update(&site, "p", off, 1.0, 1.0)),
            Some((SessionState::Active, None, 1))
        );
        assert_eq!(
            state(guide.update(&site, "p", on, 2.0, 2.0)),
            Some((SessionState::Active, None, 0))
        );
        // Unknown fixes between stray ones neither count nor reset.
        guide.update(&site, "p", off, 3.0, 3.0);
        assert_eq!(guide.update(&site, "p", None::<Cell>, 4.0, 4.0), None);
        assert_eq!(
            state(guide.update(&site, "p", off, 5.0, 5.0)),
            Some((SessionState::OffRoute, Some(GuidanceEvent::OffRoute), 2))
        );
        // Said once, not on every fix off the route.
        assert_eq!(
            state(guide.update(&site, "p", off, 6.0, 6.0)),
            Some((SessionState::OffRoute, None, 3))
        );
        // A re-planned route keeps the count of re-routes.
        let detour = Route {
            cells: (8..=15).map(|y| Cell::new(5, y)).collect(),
        };
        let first = guide.start(
            &site,
            "p",
            None,
            Profile::Default,
            &detour,
            &cells_line(&detour),
            7.0,
            true,
        );
        assert_eq!(
            (first.state, first.event, first.reroutes),
            (SessionState::Rerouted, Some(GuidanceEvent::Rerouted), 1)
        );
    }

    #[test]
    fn sessions_are_bounded_in_number_and_time() {
        let site = site();
        let mut guide = Guide::new(
            GuidanceConfig {
                max_sessions: 2,
                expire_after_s: 60.0,
                ..GuidanceConfig::default()
            },
            0.0,
        );
        start(&mut guide, &site, "a", 0.0);
        start(&mut guide, &site, "b", 1.0);
        guide.update(&site, "a", Some(Cell::new(1, 0)), 2.0, 2.0);
        // Full: the least recently updated ("b") makes room.
        start(&mut guide, &site, "c", 3.0);
        assert_eq!(guide.len(), 2);
        assert!(guide.session("b").is_none() && guide.session("a").is_some());
        // A new request replaces a device's session.
        start(&mut guide, &site, "c", 4.0);
        assert_eq!(guide.len(), 2);
        // Not located for longer than expire_after_s: the session ends.
        let last = guide
            .update(&site, "a", Some(Cell::new(2, 0)), 100.0, 100.0)
            .unwrap();
        assert_eq!(
            (last.state, last.event, last.next),
            (SessionState::Expired, Some(GuidanceEvent::Expired), None)
        );
        assert!(guide.session("a").is_none());
        // Idle sessions are also swept when another starts.
        start(&mut guide, &site, "d", 200.0);
        assert_eq!(guide.len(), 1);
        let cancelled = guide.cancel("d", 201.0).unwrap();
        assert_eq!(cancelled.state, SessionState::Cancelled);
        assert!(guide.is_empty() && guide.cancel("d", 202.0).is_none());
    }

    #[test]
    fn every_finished_session_leaves_its_adherence() {
        let site = site();
        let mut guide = Guide::new(GuidanceConfig::default(), 0.0);
        // Followed to the end at the expected pace (1.2 m/s): adherence 1.
        start(&mut guide, &site, "p", 0.0);
        for (i, &cell) in route().cells.iter().enumerate().skip(1) {
            let t = i as f64 / 1.2;
            if guide.update(&site, "p", Some(cell), t, t).unwrap().state == SessionState::Arrived {
                break;
            }
        }
        assert!(guide.take_finished().is_empty(), "watched after arriving");
        for k in 1..=5 {
            let t = 30.0 + f64::from(k);
            guide.update(&site, "p", Some(Cell::new(20, 15)), t, t);
        }
        let done = guide.take_finished();
        assert_eq!(done.len(), 1);
        let a = &done[0];
        assert_eq!((a.ending, a.arrived, a.detours), (Ending::Arrived, true, 0));
        assert_eq!(a.request_id.as_deref(), Some("r1"));
        assert!(a.score() > 0.95, "{a:?}");
        // Strayed off the route, re-routed, then cancelled: detours count,
        // the re-route belongs to the same walk, and the score is low.
        start(&mut guide, &site, "q", 100.0);
        guide.update(&site, "q", Some(Cell::new(3, 0)), 102.0, 102.0);
        for k in 0..3 {
            guide.update(
                &site,
                "q",
                Some(Cell::new(3, 10)),
                104.0 + f64::from(k),
                104.0 + f64::from(k),
            );
        }
        let detour = Route {
            cells: (0..=10).map(|y| Cell::new(3, 10 - y)).collect(),
        };
        guide.start(
            &site,
            "q",
            None,
            Profile::Default,
            &detour,
            &cells_line(&detour),
            107.0,
            true,
        );
        assert!(guide.take_finished().is_empty(), "a re-route goes on");
        guide.cancel("q", 110.0);
        let a = &guide.take_finished()[0];
        assert_eq!(
            (a.ending, a.arrived, a.detours),
            (Ending::Cancelled, false, 1)
        );
        assert!((a.in_corridor_share - 0.25).abs() < 1e-9, "{a:?}");
        assert_eq!((a.started_t, a.t), (100.0, 110.0));
        assert!(a.score() < 0.1, "{a:?}");
        // Replaced by a new request, or never located: only the first counts.
        start(&mut guide, &site, "r", 200.0);
        guide.update(&site, "r", Some(Cell::new(1, 0)), 201.0, 201.0);
        start(&mut guide, &site, "r", 202.0);
        start(&mut guide, &site, "s", 203.0);
        guide.cancel("s", 204.0);
        let endings: Vec<Ending> = guide.take_finished().iter().map(|a| a.ending).collect();
        assert_eq!(endings, [Ending::Replaced]);
    }

    #[test]
    fn a_session_stays_under_a_kilobyte() {
        let site = site();
        let mut guide = Guide::new(GuidanceConfig::default(), 0.0);
        start(&mut guide, &site, "p", 0.0);
        let bytes = guide.session("p").unwrap().state_bytes();
        assert!(bytes < 1024, "{bytes} bytes for a 35 m route");
    }

    #[test]
    fn a_long_route_is_guided_through_a_window_of_its_maneuvers() {
        // A 40 × 40 floor walked to and fro along every third row (3 m
        // apart: never as near the destination as `arrive_m` before it).
        let row = "#".repeat(40);
        let map = vec![row; 40].join("\n");
        let text = format!("name = \"t\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n");
        let site = Site::parse(&text, Path::new("t.toml")).unwrap();
        let mut cells = Vec::new();
        for y in 0..=36u16 {
            match y % 6 {
                0 => cells.extend((0..40).map(|x| Cell::new(x, y))),
                3 => cells.extend((0..40).rev().map(|x| Cell::new(x, y))),
                1 | 2 => cells.push(Cell::new(39, y)),
                _ => cells.push(Cell::new(0, y)),
            }
        }
        let route = Route { cells };
        let all = crate::plan::instructions::maneuvers(&site, &route, Profile::Default);
        assert!(all.len() > 4 * session::WINDOW_MANEUVERS, "{}", all.len());
        let mut guide = Guide::new(GuidanceConfig::default(), 0.0);
        guide.start(
            &site,
            "p",
            None,
            Profile::Default,
            &route,
            &cells_line(&route),
            0.0,
            false,
        );
        // Walked cell by cell with exact fixes: every maneuver is next in
        // turn, in the route's order, and the session stays small.
        let mut told = vec![all[1].at];
        let mut largest = 0;
        for (i, &cell) in route.cells.iter().enumerate().skip(1) {
            let t = i as f64 / 1.2;
            let m = guide.update(&site, "p", Some(cell), t, t).unwrap();
            largest = largest.max(guide.session("p").unwrap().state_bytes());
            if let Some(next) = m.next
                && told.last() != Some(&next.at)
            {
                told.push(next.at);
            }
            if m.state == SessionState::Arrived {
                break;
            }
        }
        let expected: Vec<Cell> = all[1..].iter().map(|m| m.at).collect();
        assert_eq!(told, expected);
        let metres = route.length_m(&site);
        assert!(largest < 1024, "{largest} bytes for a {metres} m route");
    }

    #[test]
    fn bad_settings_are_named() {
        let bad = GuidanceConfig {
            corridor_m: 0.0,
            ..GuidanceConfig::default()
        };
        assert!(bad.validate().unwrap_err().contains("`corridor_m`"));
        let none = GuidanceConfig {
            off_route_fixes: 0,
            ..GuidanceConfig::default()
        };
        assert!(none.validate().is_err());
        assert!(GuidanceConfig::default().validate().is_ok());
    }
}
