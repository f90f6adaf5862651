//! What the gateway publishes, as MQTT topics and JSON payloads. Every sink
//! (MQTT, `--print` on stdout) sends exactly these messages, so what a test sees
//! on stdout is what a subscriber gets from the broker.
//!
//! Topics under the prefix (default `gangway/<gateway id>`):
//! - `<prefix>/devices/<device>/location`: a [`Location`] per fix;
//! - `<prefix>/devices/<device>/path`: a [`RouteReply`] per route request,
//!   and one per route re-planned when a walker left theirs;
//! - `<prefix>/devices/<device>/guidance`: a [`Guidance`] per fix of a device
//!   being guided along a route (see `guide`);
//! - `<prefix>/devices/<device>/presence`: Home Assistant's tracker state
//!   (`mqtt::discovery`);
//! - `<prefix>/occupancy`: devices per named place (`mqtt::occupancy`);
//! - `<prefix>/status`, `<prefix>/stats` and the subscribed topics
//!   (`route/set`, `feedback`, `scans`): see `mqtt` and docs/mqtt.md.

use serde::Serialize;

use crate::plan::RouteErrorCode;
use crate::site::Cell;

/// Payload schema versions, sent in every payload's `schema` field.
pub const LOCATION_SCHEMA: &str = "gangway.location/1";
pub const PATH_SCHEMA: &str = "gangway.path/1";
pub const GUIDANCE_SCHEMA: &str = "gangway.guidance/1";

/// One outgoing message.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Message {
    pub topic: String,
    pub payload: serde_json::Value,
    #[serde(skip)]
    pub retain: bool,
}

/// A device's position after a fix. When the evidence was too weak to name a
/// cell (published confidence under `[localizer] min_confidence`) the fix is
/// an explicit unknown: `cell`, `label`, `x_m`, `y_m` and `place` are `null`,
/// never a guessed cell. Every key is always present, so templates (Home
/// Assistant's among them) can read any of them without a default.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Location {
    pub schema: &'static str,
    pub device: String,
    /// Time of the fix (end of its fingerprint window), seconds.
    pub t: f64,
    pub cell: Option<Cell>,
    /// The cell's survey label (`O02`) when the site has a label scheme.
    pub label: Option<String>,
    /// Centre of the cell in the site's world frame ([`crate::site::Site::world_of_cell`]).
    pub x_m: Option<f64>,
    pub y_m: Option<f64>,
    /// The nearest named place within two cells.
    pub place: Option<String>,
    /// Probability of being within one cell of `cell`, calibrated where the
    /// localizer has held-out truth (or, when unknown, of the best guess).
    pub confidence: f32,
    /// How many anchors were heard in the window.
    pub anchors_heard: usize,
}

/// The answer to a route request: a route or an error, never both.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RouteReply {
    pub schema: &'static str,
    pub device: String,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub request_id: Option<String>,
    pub t: f64,
    #[serde(flatten)]
    pub outcome: RouteOutcome,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(untagged)]
pub enum RouteOutcome {
    Route(RouteBody),
    Error { error: ErrorBody },
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct RouteBody {
    pub from: Cell,
    pub to: Cell,
    pub planner: &'static str,
    /// Which trained models answered (learned modes only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub model_version: Option<String>,
    /// How the route came about (see `plan::Origin`).
    pub origin: crate::plan::Origin,
    pub profile: &'static str,
    pub waypoints: Vec<crate::plan::Waypoint>,
    pub length_m: f64,
    /// Turn-by-turn, for people and screen readers.
    pub instructions: Vec<crate::plan::instructions::Instruction>,
    /// The same turns structured (depart, turns, arrive), for clients that
    /// render or speak them themselves.
    pub maneuvers: Vec<crate::plan::instructions::Maneuver>,
    /// Why a route was sent without a request: `off_route` for a route
    /// re-planned after the walker left theirs. Absent on replies.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<&'static str>,
    /// Time from request to route, microseconds.
    pub latency_us: u64,
}

impl RouteBody {
    /// The published form of a planned route.
    pub fn new(
        site: &crate::site::Site,
        planner: &dyn crate::plan::Planner,
        profile: crate::plan::Profile,
        from: Cell,
        to: Cell,
        planned: &crate::plan::Planned,
        latency_us: u64,
    ) -> RouteBody {
        RouteBody {
            from,
            to,
            planner: planner.mode(),
            model_version: planner.model_version().map(str::to_owned),
            origin: planned.origin,
            profile: profile.name(),
            waypoints: planned.route.waypoints(site),
            length_m: planned.route.length_m(site),
            instructions: crate::plan::instructions::instructions(site, &planned.route),
            maneuvers: crate::plan::instructions::maneuvers(site, &planned.route),
            reason: None,
            latency_us,
        }
    }
}

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
    pub state: crate::guide::SessionState,
    /// What this message announces; `null` for a plain progress update.
    pub event: Option<crate::guide::GuidanceEvent>,
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

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ErrorBody {
    /// Stable code, sent as its string (`unknown_place`, `off_map`, …).
    pub code: RouteErrorCode,
    pub message: String,
}

/// Topic names under one prefix.
#[derive(Clone, Debug)]
pub struct Topics {
    prefix: String,
}

impl Topics {
    pub fn new(prefix: impl Into<String>) -> Self {
        Topics {
            prefix: prefix.into(),
        }
    }

    pub fn prefix(&self) -> &str {
        &self.prefix
    }

    pub fn location(&self, device: &str) -> String {
        format!("{}/devices/{device}/location", self.prefix)
    }

    /// Plain-text tracker state for Home Assistant: place, `home` or `not_home`.
    pub fn presence(&self, device: &str) -> String {
        format!("{}/devices/{device}/presence", self.prefix)
    }

    /// Retained devices per named place.
    pub fn occupancy(&self) -> String {
        format!("{}/occupancy", self.prefix)
    }

    pub fn path(&self, device: &str) -> String {
        format!("{}/devices/{device}/path", self.prefix)
    }

    /// Retained `online` / `offline` (the last will).
    pub fn status(&self) -> String {
        format!("{}/status", self.prefix)
    }

    /// Retained counters.
    pub fn stats(&self) -> String {
        format!("{}/stats", self.prefix)
    }

    /// Guidance for a device walking a route.
    pub fn guidance(&self, device: &str) -> String {
        format!("{}/devices/{device}/guidance", self.prefix)
    }

    /// Route requests for a device.
    pub fn route_set(&self, device: &str) -> String {
        format!("{}/devices/{device}/route/set", self.prefix)
    }

    /// Feedback on a route.
    pub fn feedback(&self, device: &str) -> String {
        format!("{}/devices/{device}/feedback", self.prefix)
    }

    /// Scans a phone publishes of the beacons it hears.
    pub fn scans(&self, device: &str) -> String {
        format!("{}/scans/{device}", self.prefix)
    }

    pub fn encode_location(&self, location: &Location) -> Message {
        Message {
            topic: self.location(&location.device),
            payload: serde_json::to_value(location).expect("plain data serializes"),
            retain: false,
        }
    }

    pub fn encode_guidance(&self, guidance: &Guidance) -> Message {
        Message {
            topic: self.guidance(&guidance.device),
            payload: serde_json::to_value(guidance).expect("plain data serializes"),
            retain: false,
        }
    }

    pub fn encode_route(&self, reply: &RouteReply) -> Message {
        Message {
            topic: self.path(&reply.device),
            payload: serde_json::to_value(reply).expect("plain data serializes"),
            retain: false,
        }
    }
}

/// Whether a device id can stand as one MQTT topic level: non-empty, at most 128
/// bytes, and free of `+`, `#`, `/` and control characters.
pub fn valid_device_id(id: &str) -> bool {
    !id.is_empty()
        && id.len() <= 128
        && !id
            .chars()
            .any(|c| matches!(c, '+' | '#' | '/') || c.is_control())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn device_ids_that_break_topics_are_refused() {
        assert!(valid_device_id("phone-7"));
        assert!(valid_device_id(
            "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84-1-3001"
        ));
        for bad in ["", "a/b", "a+", "#", "tab\there", &"x".repeat(129)] {
            assert!(!valid_device_id(bad), "{bad:?}");
        }
    }

    #[test]
    fn an_error_reply_has_an_error_object_and_no_route() {
        let reply = RouteReply {
            schema: PATH_SCHEMA,
            device: "d".into(),
            request_id: Some("r1".into()),
            t: 1.0,
            outcome: RouteOutcome::Error {
                error: ErrorBody {
                    code: RouteErrorCode::UnknownPlace,
                    message: "unknown place `x`".into(),
                },
            },
        };
        let msg = Topics::new("gangway/gw").encode_route(&reply);
        assert_eq!(msg.topic, "gangway/gw/devices/d/path");
        assert_eq!(msg.payload["error"]["code"], "unknown_place");
        assert_eq!(msg.payload["request_id"], "r1");
        assert!(msg.payload.get("waypoints").is_none());
    }
}
