//! What comes into the gateway, as plain data below every stage: a source's
//! [`Event`]s (sightings heard, scripted route requests, ground truth) and
//! the [`Inbound`] messages others send (requests, cancels, feedback, phone
//! scans, other gateways' sightings). Sources make them, the runtime and the
//! pipeline consume them; this module depends on nothing but the data types
//! they carry.
//!
//! (Two of those still live one layer up and belong here: `plan::Destination`
//! and `plan::RouteErrorCode`, moved once the planner's files are free.)

use serde::{Deserialize, Serialize};

use crate::plan::{Destination, RouteErrorCode};
use crate::sighting::Sighting;
use crate::site::Cell;

/// One thing that happened, in time order.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// An advert was heard.
    Advert(Sighting),
    /// A device asked for a route (served exactly like an MQTT `route/set`).
    Request(RouteRequest),
    /// Where a device really was: the ground truth of a recorded or simulated walk.
    Truth(Truth),
}

impl Event {
    pub fn t(&self) -> f64 {
        match self {
            Event::Advert(s) => s.t,
            Event::Request(r) => r.t,
            Event::Truth(g) => g.t,
        }
    }
}

/// The rule for a request's `floor`, said to whoever broke it: a building's
/// floor names are short ("B1", "Ground"), and the name is echoed in errors.
pub const FLOOR_NAME_RULE: &str = "`floor` must be a floor's name, 1 to 64 bytes";

/// Whether `floor`, from a request (the broker, the web API) or a log's
/// truth, may be a floor's name ([`FLOOR_NAME_RULE`]).
pub fn valid_floor_name(floor: &str) -> bool {
    (1..=64).contains(&floor.len())
}

/// A route request: from the device's current location to `to`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RouteRequest {
    pub t: f64,
    pub device: String,
    pub to: Destination,
    /// The floor `to` is on, by name; needed on a building of several
    /// floors unless `to` is a place only one floor has.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub floor: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub request_id: Option<String>,
}

/// Ground truth: `device` was in `cell` at `t`.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Truth {
    pub t: f64,
    pub device: String,
    pub cell: Cell,
    /// The floor `cell` is on, by name, on a building of several floors;
    /// none: the lowest (the only floor of a one-floor site).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub floor: Option<String>,
}

/// A message from someone else (a phone, a client, another gateway), read:
/// what the runtime serves besides its own events. Today they come over MQTT
/// (`mqtt::inbound` reads them); any other front end makes the same.
#[derive(Debug, PartialEq)]
pub enum Inbound {
    /// A route request, admitted (rate limits, a bounded queue) before it is planned.
    Route(RouteRequest),
    /// A route request that could not be read; it still gets an error reply.
    BadRoute {
        device: String,
        request_id: Option<String>,
        code: RouteErrorCode,
        message: String,
    },
    /// End the guidance session of `device` (received at `t`).
    Cancel {
        device: String,
        t: f64,
    },
    Feedback(Feedback),
    /// A phone's scan: sightings with the phone as observer.
    Scan(Vec<Sighting>),
    /// Another gateway's sightings.
    Shared(Vec<Sighting>),
    /// Another locator's heartbeat (`[cluster] role = "locator"`).
    Beat(crate::cluster::Beat),
    /// A message refused before it could be read (its source logged why);
    /// counted.
    Refused {
        oversized: bool,
    },
}

/// A score for a route the gateway gave.
#[derive(Clone, Debug, PartialEq)]
pub struct Feedback {
    pub t: f64,
    pub device: String,
    pub request_id: String,
    pub score: u8,
}
