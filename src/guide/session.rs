//! One device's navigation session: where along its route it is, which
//! maneuver comes next, what has been announced, and whether it has left the
//! route or arrived.
//!
//! Progress is where the walker is by now along the route's polyline of cell
//! centres ([`RouteLine`]), in metres from the start: each fix's projection
//! on it, filtered and predicted forward by the fix's lag ([`Progress`]).
//! Decision points are announced from that, once, at the fix nearest to
//! `announce_m` before them; a decision point too close after the previous
//! one to be announced on its own is told with it. The state kept is the
//! route (8 bytes a cell), its maneuvers and a few numbers: well under 1 KB
//! for the routes of a floor.

use super::{Adherence, Ending, GuidanceConfig, GuidanceEvent, Progress, RouteLine, SessionState};
use crate::plan::instructions::{Maneuver, first_sentence, maneuvers};
use crate::plan::{Profile, Route};
use crate::publish::{GUIDANCE_SCHEMA, Guidance, NextManeuver};
use crate::site::{Cell, Site};

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

#[derive(Clone, Debug)]
pub struct Session {
    request_id: Option<String>,
    profile: Profile,
    line: RouteLine,
    maneuvers: Vec<Maneuver>,
    /// Index in `maneuvers` of the next decision point.
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
    /// Time between the last two fixes, for how far the walker gets per fix.
    fix_interval_s: f64,
    walked: Walked,
}

impl Session {
    pub(super) fn new(
        site: &Site,
        config: &GuidanceConfig,
        request_id: Option<String>,
        profile: Profile,
        route: &Route,
        t: f64,
        rerouted_from: Option<Walked>,
    ) -> Session {
        let line = RouteLine::new(site, route);
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
            maneuvers: maneuvers(site, route, profile),
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
            fix_interval_s: 0.0,
            walked,
        }
    }

    pub fn state(&self) -> SessionState {
        self.state
    }

    pub fn progress_m(&self) -> f64 {
        self.progress_m
    }

    pub fn profile(&self) -> Profile {
        self.profile
    }

    pub fn request_id(&self) -> Option<&str> {
        self.request_id.as_deref()
    }

    /// The cell the route ends at.
    pub fn destination(&self) -> Cell {
        self.line.destination()
    }

    pub fn reroutes(&self) -> u32 {
        self.walked.reroutes
    }

    pub(super) fn walked(&self) -> Walked {
        self.walked
    }

    /// How the walk followed the route, for a session ending at `t`; `None`
    /// when it was never located (nothing was walked to judge).
    pub(super) fn adherence(&self, device: &str, t: f64, ending: Ending) -> Option<Adherence> {
        let w = &self.walked;
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

    /// Bytes this session holds, itself and on the heap.
    pub fn state_bytes(&self) -> usize {
        std::mem::size_of::<Session>()
            + self.line.heap_bytes()
            + self.maneuvers.capacity() * std::mem::size_of::<Maneuver>()
            + self
                .maneuvers
                .iter()
                .filter_map(|m| m.place.as_ref().map(String::capacity))
                .sum::<usize>()
            + self.request_id.as_ref().map_or(0, String::capacity)
    }

    /// The first message: the first step of the route.
    pub(super) fn depart(&self, site: &Site, device: &str, t: f64) -> Guidance {
        let event = if self.walked.reroutes > 0 {
            GuidanceEvent::Rerouted
        } else {
            GuidanceEvent::Depart
        };
        let text = first_sentence(site, self.line.cells(), &self.maneuvers);
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

    /// Follows one fix; `None` for an unknown fix (nothing is concluded
    /// from it, least of all that the walker left the route).
    pub(super) fn update(
        &mut self,
        site: &Site,
        config: &GuidanceConfig,
        fix_lag_s: f64,
        device: &str,
        cell: Option<Cell>,
        t: f64,
    ) -> Option<Guidance> {
        self.fix_interval_s = t - self.last_t;
        self.last_t = t;
        let cell = cell?;
        let (x, y) = site.metres(cell);
        let (off_m, along_m) = self
            .line
            .project(site, (x, y), self.track.at(t), config.corridor_m);
        let mut event = None;
        let mut text = None;
        let speed = self.profile.walking_speed_mps();
        self.walked.located_fixes += 1;
        if off_m > config.corridor_m {
            self.off_route_fixes += 1;
            if self.off_route_fixes >= config.off_route_fixes
                && self.state != SessionState::OffRoute
            {
                self.state = SessionState::OffRoute;
                self.walked.detours += 1;
                event = Some(GuidanceEvent::OffRoute);
                text = Some("You have left the route; finding a new one.".to_owned());
            }
        } else {
            self.walked.in_corridor_fixes += 1;
            self.off_route_fixes = 0;
            if self.state == SessionState::OffRoute {
                self.state = if self.walked.reroutes > 0 {
                    SessionState::Rerouted
                } else {
                    SessionState::Active
                };
            }
            self.track
                .update(t, along_m, config.fix_spread_m, 2.0 * speed);
            let length_m = self.line.length_m();
            // Predicted forward by the fix's lag at the profile's pace once
            // the walker is walking (the filtered speed is too noisy to lead
            // by); not at all while they stand.
            let pace = self.track.speed_mps();
            let lead_m = if pace >= speed / 4.0 { speed } else { pace } * fix_lag_s;
            self.progress_m = (self.track.at(t) + lead_m).clamp(0.0, length_m);
            while self.next < self.maneuvers.len()
                // Progress is summed in f32: a millimetre short is there.
                && self.maneuvers[self.next].along_m <= self.progress_m + 1e-3
            {
                self.next += 1;
            }
            self.announced = self.announced.max(self.next);
            // Half the walk until the next fix: the fix nearest a distance
            // is the one that says so.
            let half_step_m = self.track.speed_mps() * self.fix_interval_s.max(0.0) / 2.0;
            let to_destination = site.metres(self.destination());
            if length_m - self.progress_m <= config.arrive_m.min(half_step_m)
                || ((to_destination.0 - x).hypot(to_destination.1 - y) <= config.arrive_m
                    && self.progress_m >= config.arrive_progress_share * length_m)
            {
                self.state = SessionState::Arrived;
                self.next = self.maneuvers.len();
                event = Some(GuidanceEvent::Arrived);
                let place = self.maneuvers.last().and_then(|m| m.place.as_ref());
                text = Some(match place {
                    Some(p) => format!("You have arrived at {p}."),
                    None => "You have arrived.".to_owned(),
                });
            } else if let Some(m) = self.maneuvers.get(self.next) {
                let ahead = m.along_m - self.progress_m;
                if self.announced <= self.next && ahead <= config.announce_m + half_step_m {
                    event = Some(GuidanceEvent::Announce);
                    text = Some(self.announcement(config.announce_m));
                } else if self.progress_m - self.spoken_at_m >= config.reassure_m {
                    event = Some(GuidanceEvent::Reassure);
                    text = Some(format!("You are on the route. {}", m.sentence(ahead)));
                }
            }
            if event.is_some() {
                self.spoken_at_m = self.progress_m;
            }
        }
        Some(self.message(device, t, event, text))
    }

    /// Announces the next decision point, and with it those following it
    /// closer than `announce_m` (there is no room to announce them on their
    /// own after it), marking them all announced.
    fn announcement(&mut self, announce_m: f64) -> String {
        let first = &self.maneuvers[self.next];
        let mut text = first.sentence(first.along_m - self.progress_m);
        let mut k = self.next + 1;
        while let Some(m) = self.maneuvers.get(k)
            && m.distance_m < announce_m
        {
            text.push_str(" After that, ");
            text.push_str(&m.clause(m.distance_m));
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
            next: self.maneuvers.get(self.next).map(|m| NextManeuver {
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
