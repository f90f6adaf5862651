//! Guidance while walking: once a route is served, a navigation session per
//! device follows each fix along it, tells the walker the next maneuver and
//! how far it is, announces decision points a set distance ahead, reassures
//! at intervals, notices when the walker has left the route (so the pipeline
//! can re-plan) and when they have arrived.
//!
//! Owns the sessions ([`Guide`], bounded in number and in idle time, since
//! devices come from the air) and the state machine of one ([`Session`]).
//! It does no I/O and keeps no clock: the pipeline feeds it fixes and sends
//! the [`crate::publish::Guidance`] messages it returns. The maneuvers are
//! the route's own ([`crate::plan::instructions::maneuvers`]), so what is
//! announced is what the route reply listed.
//!
//! Thresholds follow the Wayfindr open standard (ITU-T F.921): a decision
//! point is announced about 6 m ahead, reassurance about every 10 m.

mod session;

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

pub use session::Session;

use crate::plan::{Profile, Route};
use crate::publish::Guidance;
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
            max_sessions: 1024,
            expire_after_s: 600.0,
        }
    }
}

impl GuidanceConfig {
    pub fn validate(&self) -> Result<(), String> {
        let positive = [
            ("announce_m", self.announce_m),
            ("reassure_m", self.reassure_m),
            ("corridor_m", self.corridor_m),
            ("arrive_m", self.arrive_m),
            ("expire_after_s", self.expire_after_s),
        ];
        if let Some((name, _)) = positive.iter().find(|(_, v)| !(*v > 0.0 && v.is_finite())) {
            return Err(format!("[guidance] `{name}` must be a positive number"));
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
    Cancelled,
    Expired,
}

/// The sessions of all devices, bounded in number and time.
pub struct Guide {
    config: GuidanceConfig,
    sessions: HashMap<String, Session>,
}

impl Guide {
    pub fn new(config: GuidanceConfig) -> Guide {
        Guide {
            config,
            sessions: HashMap::new(),
        }
    }

    pub fn config(&self) -> &GuidanceConfig {
        &self.config
    }

    /// Active sessions.
    pub fn len(&self) -> usize {
        self.sessions.len()
    }

    pub fn is_empty(&self) -> bool {
        self.sessions.is_empty()
    }

    pub fn session(&self, device: &str) -> Option<&Session> {
        self.sessions.get(device)
    }

    /// Starts guiding `device` along `route` (replacing any session it had),
    /// and returns the first message. `rerouted` marks a route re-planned
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
        t: f64,
        rerouted: bool,
    ) -> Guidance {
        let expire = self.config.expire_after_s;
        self.sessions.retain(|_, s| t - s.last_t() <= expire);
        let reroutes = match self.sessions.remove(device) {
            Some(old) if rerouted => old.reroutes() + 1,
            _ => 0,
        };
        if self.sessions.len() >= self.config.max_sessions
            && let Some(oldest) = self
                .sessions
                .iter()
                .min_by(|a, b| a.1.last_t().total_cmp(&b.1.last_t()))
                .map(|(d, _)| d.clone())
        {
            self.sessions.remove(&oldest);
        }
        let session = Session::new(site, request_id, profile, route, t, reroutes);
        let first = session.depart(device, t);
        self.sessions.insert(device.to_owned(), session);
        first
    }

    /// Follows one fix of `device` (`None`: location unknown). Returns a
    /// message when the device has a session and the fix was known, or
    /// when the session just expired; a session that arrived or expired
    /// ends with its message.
    pub fn update(
        &mut self,
        site: &Site,
        device: &str,
        cell: Option<Cell>,
        t: f64,
    ) -> Option<Guidance> {
        let session = self.sessions.get_mut(device)?;
        if t - session.last_t() > self.config.expire_after_s {
            let last = session.end(device, t, SessionState::Expired);
            self.sessions.remove(device);
            return Some(last);
        }
        let message = session.update(site, &self.config, device, cell, t)?;
        if message.state == SessionState::Arrived {
            self.sessions.remove(device);
        }
        Some(message)
    }

    /// Ends the session of `device`, if it has one.
    pub fn cancel(&mut self, device: &str, t: f64) -> Option<Guidance> {
        let session = self.sessions.remove(device)?;
        Some(session.end(device, t, SessionState::Cancelled))
    }
}
