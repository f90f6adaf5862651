//! One device's navigation session: where along its route it is, which
//! maneuver comes next, what has been announced, and whether it has left the
//! route or arrived.
//!
//! Progress is where the walker is by now along the route's polyline of cell
//! centres ([`RouteLine`]), in metres from the start: each fix's projection
//! on it (of the mean belief when given, [`super::Located`]), filtered and predicted forward from the moment the walker was
//! there ([`Progress`]). Announcements and arrival are judged on that at
//! every event of the device, not only at its fixes (sightings arrive many
//! times a second, fixes every stride), so a decision point is announced
//! when it is truly about `announce_m` ahead; a decision point too close
//! after the previous one to be announced on its own is told with it.
//!
//! Leaving the route is judged on fixes only, never on an unknown one: a fix
//! outside the corridor counts towards it, and so does a fix already a third
//! of the corridor off that moved away from the route, across the way the
//! route goes there or so that its move, carried on for the fix's lag (as
//! far as the move stands out of the fixes' noise), leaves the corridor (a
//! wrong turn shows so a fix or two before the lagging fixes leave the
//! corridor); a fix stalled off the route neither counts nor resets, and
//! anything else resets the count.
//!
//! The state kept is bounded so that a session stays under 1 KB however
//! long its route: the route as a chain code (half a byte a cell,
//! [`RouteLine`]), a window of the next [`WINDOW_MANEUVERS`] maneuvers
//! (each some 60 bytes with its place's name; those of a longer route are
//! worked out again from the route as the walker reaches the end of the
//! window), the destination's name and a few numbers.

use super::{
    Adherence, Ending, GuidanceConfig, GuidanceEvent, Located, Progress, RouteLine, SessionState,
};
use super::{GUIDANCE_SCHEMA, Guidance, NextManeuver};
use crate::plan::Profile;
use crate::plan::instructions::{Maneuver, first_sentence};
use crate::site::{Cell, Site};

/// Least angle between the way a fix moved and the way the route goes
/// there for the move to count as turning off it, degrees: what the
/// maneuvers call a plain turn (a slight bend is under 60°).
const TURNING_OFF_DEG: f64 = 60.0;

/// Most maneuvers a session holds at once, from the next one on: enough
/// for the next decision point and those close after it that are
/// announced with it. A route with more has the rest worked out again
/// from the route when fewer than [`MANEUVERS_AHEAD`] are left in the
/// window.
pub(crate) const WINDOW_MANEUVERS: usize = 6;

/// Maneuvers from the next one on that the window keeps loaded.
const MANEUVERS_AHEAD: usize = 3;

/// What a session has seen of the walk, carried across re-routes: what its
/// adherence is made of.
#[derive(Clone, Copy, Debug)]
pub(super) struct Walked {
    started_t: f64,
    /// The first route's length at the profile's pace, seconds.
    expected_s: f64,
    located_fixes: u32,
    in_corridor_fixes: u32,
    /// Times the walker left the route.
    detours: u32,
    reroutes: u32,
}

/// The last located fix: where, how far off the route, when (its time).
#[derive(Clone, Copy, Debug)]
struct LastFix {
    x: f32,
    y: f32,
    off_m: f32,
    t: f64,
}

/// What one fix says about leaving the route.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Leaving {
    /// Outside the corridor, or turned off the route: counts.
    Yes,
    /// Off the route but not moving: neither counts nor resets.
    Stalled,
    /// On the route, or back towards it: resets the count.
    No,
}

/// The connector a floor's leg ends at.
#[derive(Clone, Debug)]
pub(super) struct LegEnd {
    /// What the walk goes to: "the lift".
    noun: String,
    /// What to do there: "Take the lift to L1."
    ride: String,
}

#[derive(Clone, Debug)]
pub(crate) struct Session {
    request_id: Option<String>,
    profile: Profile,
    line: RouteLine,
    /// The route's maneuvers from `window_start` on, at most
    /// [`WINDOW_MANEUVERS`] of them.
    window: Vec<Maneuver>,
    /// Index in the route's maneuvers of `window[0]`.
    window_start: u16,
    /// How many maneuvers the route has.
    maneuver_count: u16,
    /// The named place or landmark the route arrives at.
    destination_place: Option<String>,
    /// Where one floor's leg of a route across floors ends: the route
    /// walks to it rather than arriving, and its arrival is the
    /// connector's announcement. Boxed: most sessions have none.
    leg_end: Option<Box<LegEnd>>,
    /// Index in the route's maneuvers of the next decision point.
    next: usize,
    /// Maneuvers before this index have been announced.
    announced: usize,
    state: SessionState,
    /// Where the walker is by now, metres along the route.
    progress_m: f64,
    /// The filter behind `progress_m`.
    track: Progress,
    /// Progress at the last spoken message, for reassurance.
    spoken_at_m: f64,
    off_route_fixes: u32,
    /// Time of the last fix, known or not.
    last_t: f64,
    /// When progress was last judged (a fix or another event).
    judged_t: f64,
    last_fix: Option<LastFix>,
    /// Located fixes since the walker was told they had arrived: an
    /// arrival is watched for twice as many fixes as leaving the route
    /// takes, and one more, in case it was told too soon (the fixes of a
    /// walker who walked on trail them by a fix or two before they leave
    /// the corridor: `gangway eval guidance`, docs/guidance.md).
    since_arrival: u32,
    walked: Walked,
}

impl Session {
    pub(super) fn new(
        site: &Site,
        config: &GuidanceConfig,
        request_id: Option<String>,
        profile: Profile,
        line: RouteLine,
        t: f64,
        rerouted_from: Option<Walked>,
    ) -> Session {
        let all = line.maneuvers(site, profile);
        let destination_place = all.last().and_then(|m| m.place.clone());
        let maneuver_count = u16::try_from(all.len()).unwrap_or(u16::MAX);
        let walked = match rerouted_from {
            Some(before) => Walked {
                reroutes: before.reroutes + 1,
                ..before
            },
            None => Walked {
                started_t: t,
                expected_s: line.length_m() / profile.walking_speed_mps(),
                located_fixes: 0,
                in_corridor_fixes: 0,
                detours: 0,
                reroutes: 0,
            },
        };
        let reroutes = walked.reroutes;
        Session {
            request_id,
            profile,
            line,
            window: Vec::new(),
            window_start: 0,
            maneuver_count,
            destination_place,
            leg_end: None,
            next: 1,
            announced: 1,
            state: if reroutes > 0 {
                SessionState::Rerouted
            } else {
                SessionState::Active
            },
            progress_m: 0.0,
            track: Progress::new(t, profile.walking_speed_mps(), config.fix_spread_m),
            spoken_at_m: 0.0,
            off_route_fixes: 0,
            last_t: t,
            judged_t: t,
            last_fix: None,
            since_arrival: 0,
            walked,
        }
        .with_window(all, 0)
    }

    /// Keeps the maneuvers of `all` (the route's) from `start` on in the
    /// window.
    fn with_window(mut self, all: Vec<Maneuver>, start: usize) -> Session {
        self.load_window(all, start);
        self
    }

    fn load_window(&mut self, mut all: Vec<Maneuver>, start: usize) {
        let start = start.min(all.len());
        all.truncate((start + WINDOW_MANEUVERS).min(all.len()));
        all.drain(..start);
        // Held as long as the window: no room spare.
        all.shrink_to_fit();
        self.window = all;
        self.window_start = start as u16;
    }

    /// The route's maneuver `k`, when the window holds it.
    fn maneuver(&self, k: usize) -> Option<&Maneuver> {
        self.window
            .get(k.checked_sub(usize::from(self.window_start))?)
    }

    /// Works the window out again from the route when fewer than
    /// [`MANEUVERS_AHEAD`] maneuvers from the next one on are in it and
    /// the route has more (only routes with more than
    /// [`WINDOW_MANEUVERS`] maneuvers ever do this).
    fn refill_window(&mut self, site: &Site) {
        let loaded_to = usize::from(self.window_start) + self.window.len();
        let count = usize::from(self.maneuver_count);
        if loaded_to >= count || self.next + MANEUVERS_AHEAD <= loaded_to {
            return;
        }
        let all = self.line.maneuvers(site, self.profile);
        self.load_window(all, self.next);
    }

    pub(crate) fn state(&self) -> SessionState {
        self.state
    }

    pub(crate) fn profile(&self) -> Profile {
        self.profile
    }

    pub(crate) fn request_id(&self) -> Option<&str> {
        self.request_id.as_deref()
    }

    /// The cell the route ends at.
    pub(crate) fn destination(&self) -> Cell {
        self.line.destination()
    }

    pub(super) fn walked(&self) -> Walked {
        self.walked
    }

    /// How the walk followed the route, for a session ending at `t` (or
    /// when it arrived); `None` when it was never located (nothing was
    /// walked to judge).
    pub(super) fn adherence(&self, device: &str, t: f64, ending: Ending) -> Option<Adherence> {
        let w = &self.walked;
        // Judged no more once arrived: the moment it arrived.
        let t = if self.state == SessionState::Arrived {
            self.judged_t
        } else {
            t
        };
        (w.located_fixes > 0).then(|| Adherence {
            device: device.to_owned(),
            request_id: self.request_id.clone(),
            started_t: w.started_t,
            t,
            ending,
            in_corridor_share: f64::from(w.in_corridor_fixes) / f64::from(w.located_fixes),
            detours: w.detours,
            arrived: ending == Ending::Arrived,
            expected_s: w.expected_s,
            taken_s: (t - w.started_t).max(0.0),
        })
    }

    pub(super) fn last_t(&self) -> f64 {
        self.last_t
    }

    /// Where the walker would be by `t` (a fix's time) had they walked on
    /// along the route at the pace progress is predicted at since the last
    /// fix: each cell of the route and the cell that far ahead of it.
    /// `None` unless following the route (not off it, not on the way off
    /// it, not arrived) and walking.
    pub(super) fn expected_walk(&self, site: &Site, t: f64) -> Option<Vec<(Cell, Cell)>> {
        let following = matches!(self.state, SessionState::Active | SessionState::Rerouted)
            && self.off_route_fixes == 0;
        let walk_m = self.speed_mps() * (t - self.last_t);
        (following && walk_m > 0.0).then(|| self.line.ahead(site, walk_m))
    }

    /// The pace progress is predicted on: the profile's once the walker is
    /// walking (the filtered speed follows the tracker's stalls and jumps),
    /// the filtered one while they stand.
    fn speed_mps(&self) -> f64 {
        let pace = self.profile.walking_speed_mps();
        let filtered = self.track.speed_mps();
        if filtered >= pace / 4.0 {
            pace
        } else {
            filtered
        }
    }

    /// Whether the session is over: arrived, and watched long enough that
    /// the walker did not walk on off the route.
    pub(super) fn is_over(&self, config: &GuidanceConfig) -> bool {
        self.state == SessionState::Arrived && self.since_arrival > 2 * config.off_route_fixes
    }

    /// Bytes this session holds, itself and on the heap.
    pub(crate) fn state_bytes(&self) -> usize {
        std::mem::size_of::<Session>()
            + self.line.heap_bytes()
            + self.window.capacity() * std::mem::size_of::<Maneuver>()
            + self
                .window
                .iter()
                .filter_map(|m| m.place.as_ref().map(String::capacity))
                .sum::<usize>()
            + self.destination_place.as_ref().map_or(0, String::capacity)
            + self.leg_end.as_ref().map_or(0, |end| {
                std::mem::size_of::<LegEnd>() + end.noun.capacity() + end.ride.capacity()
            })
            + self.request_id.as_ref().map_or(0, String::capacity)
    }

    /// Makes this session one floor's leg of a route across floors, ending
    /// at a connector: walked to `noun` ("the lift"), and `ride` ("Take
    /// the lift to L1.") said on arrival.
    pub(super) fn end_at_connector(&mut self, noun: String, ride: String) {
        self.leg_end = Some(Box::new(LegEnd { noun, ride }));
    }

    /// The connector this session's leg ends at, when it ends at
    /// `destination`: a route re-planned to the same end keeps it.
    pub(super) fn leg_end_at(&self, destination: Cell) -> Option<Box<LegEnd>> {
        self.leg_end
            .clone()
            .filter(|_| self.destination() == destination)
    }

    pub(super) fn with_leg_end(mut self, leg_end: Option<Box<LegEnd>>) -> Session {
        self.leg_end = leg_end;
        self
    }

    fn towards(&self) -> Option<&str> {
        self.leg_end.as_ref().map(|end| end.noun.as_str())
    }

    /// The first message: the first step of the route.
    pub(super) fn depart(&self, site: &Site, device: &str, t: f64) -> Guidance {
        let event = if self.walked.reroutes > 0 {
            GuidanceEvent::Rerouted
        } else {
            GuidanceEvent::Depart
        };
        // The first maneuvers, in the window until the walker moves on.
        let start: Vec<Cell> = self.line.cells().take(4).collect();
        let text = first_sentence(site, &start, &self.window, self.towards());
        self.message(device, t, Some(event), text)
    }

    /// The last message of a session ended from outside.
    pub(super) fn end(&self, device: &str, t: f64, state: SessionState) -> Guidance {
        let (event, text) = match state {
            SessionState::Expired => (GuidanceEvent::Expired, "Guidance has ended."),
            _ => (GuidanceEvent::Cancelled, "Guidance cancelled."),
        };
        let mut message = self.message(device, t, Some(event), Some(text.into()));
        message.state = state;
        message.next = None;
        message
    }

    /// Follows one fix of time `fix_t` (the end of its window), arriving at
    /// `now`; `None` for an unknown fix (nothing is concluded from it, least
    /// of all that the walker left the route).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn update(
        &mut self,
        site: &Site,
        config: &GuidanceConfig,
        fix_lag_s: f64,
        device: &str,
        fix: Option<Located>,
        fix_t: f64,
        now: f64,
    ) -> Option<Guidance> {
        self.last_t = fix_t;
        let fix = fix?;
        // Leaving the route is judged on the cell (a belief split between
        // two corridors has its mean in neither); progress on the mean.
        let (x, y) = site.metres(fix.cell);
        // When the walker was where the fix places them (not before the
        // route was served: they stood at its start).
        let was_t = (fix_t - fix_lag_s).max(self.walked.started_t);
        let (off_m, along_m) =
            self.line
                .project(site, (x, y), self.track.at(was_t), config.corridor_m);
        let leaving = self.leaving(site, config, fix_lag_s, (x, y, fix_t), off_m, along_m);
        let along_m = match fix.mean_m {
            Some(mean) => {
                self.line
                    .project(site, mean, self.track.at(was_t), config.corridor_m)
                    .1
            }
            None => along_m,
        };
        self.last_fix = Some(LastFix {
            x: x as f32,
            y: y as f32,
            off_m: off_m as f32,
            t: fix_t,
        });
        self.walked.located_fixes += 1;
        if off_m <= config.corridor_m {
            self.walked.in_corridor_fixes += 1;
        }
        match leaving {
            Leaving::Yes => self.off_route_fixes += 1,
            Leaving::Stalled => {}
            Leaving::No => self.off_route_fixes = 0,
        }
        let arrived = self.state == SessionState::Arrived;
        if arrived {
            self.since_arrival += 1;
        }
        if self.off_route_fixes >= config.off_route_fixes {
            if self.state == SessionState::OffRoute {
                return Some(self.message(device, fix_t, None, None));
            }
            self.state = SessionState::OffRoute;
            self.next = self
                .next
                .min(usize::from(self.maneuver_count).saturating_sub(1));
            self.refill_window(site);
            self.walked.detours += 1;
            let text = if arrived {
                "You have walked on past the destination; finding the way back.".to_owned()
            } else {
                "You have left the route; finding a new one.".to_owned()
            };
            return Some(self.message(device, fix_t, Some(GuidanceEvent::OffRoute), Some(text)));
        }
        if arrived {
            // Told; watched quietly until over (`is_over`).
            return None;
        }
        if self.state == SessionState::OffRoute && leaving == Leaving::No {
            self.state = if self.walked.reroutes > 0 {
                SessionState::Rerouted
            } else {
                SessionState::Active
            };
        }
        if leaving == Leaving::No {
            let speed = self.profile.walking_speed_mps();
            self.track
                .update(was_t, along_m, config.fix_spread_m, 2.0 * speed);
        }
        let (event, text) = self.judge(site, config, fix_lag_s, now).unzip();
        Some(self.message(device, fix_t, event, text))
    }

    /// Judges progress at `now`, an event of the device between fixes: a
    /// message only when there is something to say (an announcement,
    /// reassurance, arrival).
    pub(super) fn tick(
        &mut self,
        site: &Site,
        config: &GuidanceConfig,
        fix_lag_s: f64,
        device: &str,
        now: f64,
    ) -> Option<Guidance> {
        if now <= self.judged_t || self.last_fix.is_none() {
            return None;
        }
        let (event, text) = self.judge(site, config, fix_lag_s, now)?;
        Some(self.message(device, now, Some(event), Some(text)))
    }

    /// What a located fix at `(x, y)`, `off_m` from the route and
    /// `along_m` along it, says about leaving the route (see the module).
    fn leaving(
        &self,
        site: &Site,
        config: &GuidanceConfig,
        fix_lag_s: f64,
        (x, y, t): (f64, f64, f64),
        off_m: f64,
        along_m: f64,
    ) -> Leaving {
        if off_m > config.corridor_m {
            return Leaving::Yes;
        }
        // A fix one cell off is the grid's resolution, not a turn.
        let least_m = (config.corridor_m / 3.0).max(site.cell_m);
        let Some(last) = self.last_fix else {
            return Leaving::No;
        };
        if off_m <= least_m {
            return Leaving::No;
        }
        let (dx, dy) = (x - f64::from(last.x), y - f64::from(last.y));
        let moved_m = dx.hypot(dy);
        // Cells sit a whole number of metres apart: a step of one counts.
        if moved_m + 1e-6 < least_m {
            return if self.off_route_fixes > 0 && off_m >= f64::from(last.off_m) - 1e-6 {
                Leaving::Stalled
            } else {
                Leaving::No
            };
        }
        // Where this fix's own move, carried on for the fix's lag, puts the
        // walker by now: a walker who missed a turn is already outside the
        // corridor while the lagging fix is inside it. The move between two
        // fixes is itself noisy (each is `fix_spread_m` off), so it is
        // trusted as far as a walk at the profile's pace stands out of
        // that noise: the weight a least-squares estimate gives it.
        let gap_s = t - last.t;
        if off_m > f64::from(last.off_m) && gap_s > 0.0 {
            let walk_m = self.profile.walking_speed_mps() * gap_s;
            let noise = 2.0 * config.fix_spread_m * config.fix_spread_m;
            let trust = walk_m * walk_m / (walk_m * walk_m + noise);
            let k = (trust * fix_lag_s / gap_s).min(1.0);
            let (ahead_off_m, _) =
                self.line
                    .project(site, (x + dx * k, y + dy * k), along_m, config.corridor_m);
            if ahead_off_m > config.corridor_m {
                return Leaving::Yes;
            }
        }
        let (ux, uy) = self.line.direction(site, along_m);
        let across = (dx * ux + dy * uy) <= moved_m * TURNING_OFF_DEG.to_radians().cos();
        if across && off_m - f64::from(last.off_m) >= least_m / 2.0 {
            Leaving::Yes
        } else {
            Leaving::No
        }
    }

    /// Where the walker is at `now`, and what to tell them then, if
    /// anything: arrival, the next decision point about `announce_m`
    /// ahead, or reassurance.
    fn judge(
        &mut self,
        site: &Site,
        config: &GuidanceConfig,
        fix_lag_s: f64,
        now: f64,
    ) -> Option<(GuidanceEvent, String)> {
        if matches!(self.state, SessionState::OffRoute | SessionState::Arrived) {
            return None;
        }
        let since_s = (now - self.judged_t).max(0.0);
        self.judged_t = self.judged_t.max(now);
        let length_m = self.line.length_m();
        let pace = self.profile.walking_speed_mps();
        let speed = self.speed_mps();
        self.progress_m = self.track.at_speed(now, speed).clamp(0.0, length_m);
        // Progress is summed in f32: a millimetre short is there.
        while self
            .maneuver(self.next)
            .is_some_and(|m| m.along_m <= self.progress_m + 1e-3)
        {
            self.next += 1;
            self.refill_window(site);
        }
        self.announced = self.announced.max(self.next);
        let last = self.last_fix?;
        let (dx, dy) = site.metres(self.destination());
        let fix_to_destination = (dx - f64::from(last.x)).hypot(dy - f64::from(last.y));
        // Arrived: predicted at the destination, the last fix as near it as
        // a fix lags behind and not leaving the route; or a fix at the
        // destination once enough of the route is walked (a route that
        // starts or passes near its destination is not over at once).
        let predicted = self.progress_m >= length_m - 1e-3
            && fix_to_destination <= config.arrive_m + pace * fix_lag_s
            && self.off_route_fixes == 0;
        let at_it = fix_to_destination <= config.arrive_m
            && self.progress_m >= config.arrive_progress_share * length_m;
        let said = if predicted || at_it {
            self.state = SessionState::Arrived;
            self.next = usize::from(self.maneuver_count);
            let place = self.destination_place.as_ref();
            Some(match (&self.leg_end, place) {
                (Some(end), _) => (GuidanceEvent::Connector, end.ride.clone()),
                (None, Some(p)) => (GuidanceEvent::Arrived, format!("You have arrived at {p}.")),
                (None, None) => (GuidanceEvent::Arrived, "You have arrived.".to_owned()),
            })
        } else if let Some(m) = self.maneuver(self.next) {
            let ahead = m.along_m - self.progress_m;
            // Half the walk until the next judgement (as long again as
            // since this one): the moment nearest the distance says so.
            let half_step_m = speed * since_s / 2.0;
            if self.announced <= self.next && ahead <= config.announce_m + half_step_m {
                Some((
                    GuidanceEvent::Announce,
                    self.announcement(config.announce_m),
                ))
            } else if self.progress_m - self.spoken_at_m >= config.reassure_m {
                Some((
                    GuidanceEvent::Reassure,
                    format!(
                        "You are on the route. {}",
                        m.sentence(ahead, self.towards())
                    ),
                ))
            } else {
                None
            }
        } else {
            None
        };
        if said.is_some() {
            self.spoken_at_m = self.progress_m;
        }
        said
    }

    /// Announces the next decision point, and with it those following it
    /// closer than `announce_m` (there is no room to announce them on their
    /// own after it), marking them all announced.
    fn announcement(&mut self, announce_m: f64) -> String {
        let Some(first) = self.maneuver(self.next) else {
            return String::new();
        };
        let towards = self.towards();
        let mut text = first.sentence(first.along_m - self.progress_m, towards);
        let mut k = self.next + 1;
        while let Some(m) = self.maneuver(k)
            && m.distance_m < announce_m
        {
            text.push_str(" After that, ");
            text.push_str(&m.clause(m.distance_m, towards));
            text.push('.');
            k += 1;
        }
        self.announced = k;
        text
    }

    fn message(
        &self,
        device: &str,
        t: f64,
        event: Option<GuidanceEvent>,
        text: Option<String>,
    ) -> Guidance {
        let remaining_m = (self.line.length_m() - self.progress_m).max(0.0);
        Guidance {
            schema: GUIDANCE_SCHEMA,
            device: device.to_owned(),
            t,
            request_id: self.request_id.clone(),
            state: self.state,
            event,
            text,
            next: self.maneuver(self.next).map(|m| NextManeuver {
                kind: m.kind,
                modifier: m.modifier,
                distance_m: (m.along_m - self.progress_m).max(0.0),
                at: m.at,
                place: m.place.clone(),
            }),
            progress_m: self.progress_m,
            remaining_m,
            eta_s: remaining_m / self.profile.walking_speed_mps(),
            off_route_fixes: self.off_route_fixes,
            reroutes: self.walked.reroutes,
        }
    }
}
