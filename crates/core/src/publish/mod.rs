//! What the gateway publishes, as typed outputs: the pipeline and the runtime
//! produce [`Output`]s, and every sink (MQTT, `--print` on stdout, `--out`
//! files, the learning store, the scorer, the web map) takes the same ones.
//! Nothing here knows a topic or writes JSON: the types derive `Serialize`
//! because each one *is* its payload's schema (docs/schemas), and the MQTT
//! encoder (`gangway_io::topics`) names the topic and writes the bytes, for the
//! broker and for stdout alike, so what a test sees on stdout is what a
//! subscriber gets from the broker.
//!
//! - [`Location`]: a fix, known (a cell) or unknown (`cell` null);
//! - [`RouteReply`]: the answer to a route request, a route or an error with
//!   its [`RouteErrorCode`], and routes re-planned off route;
//! - [`crate::guide::Guidance`]: progress along a served route;
//! - and what the runtime adds: feedback, adherence, forgotten devices, shared
//!   sightings and the counters ([`stats`]).

pub mod floors;
pub mod stats;

use std::sync::Arc;

use serde::Serialize;

use crate::plan::RouteErrorCode;
use crate::site::Cell;

/// Payload schema versions, sent in every payload's `schema` field.
pub const LOCATION_SCHEMA: &str = "gangway.location/1";
pub const PATH_SCHEMA: &str = "gangway.path/1";

/// Everything a sink can be given, in the order it happened. Sinks take
/// what they use and pass over the rest (`_ => {}`), so a new kind of output
/// costs only the sinks that want it.
#[derive(Clone, Debug, PartialEq)]
pub enum Output {
    /// A fix of a device: where it is, or an unknown location.
    Location(Location),
    /// A route or a route error, answering a request or re-planned off route.
    Route(Box<RouteReply>),
    /// Guidance along a route being walked.
    Guidance(Box<crate::guide::Guidance>),
    /// Where a device really was (a replayed log's `truth`), passed through
    /// the pipeline untouched for scoring.
    Truth(crate::event::Truth),
    /// A device whose track was forgotten (`[limits]`): sinks drop what they
    /// keep about it.
    Forgotten(Arc<str>),
    /// How well a finished guidance session followed its route (implicit
    /// feedback for the learning store).
    Adherence(crate::guide::Adherence),
    /// A score for a route this gateway gave.
    Feedback(crate::event::Feedback),
    /// Feedback refused: no such route was given to the device.
    FeedbackRefused(FeedbackRefused),
    /// This gateway's own sightings, for the other gateways of its site
    /// (advertiser orientation).
    Sightings(Vec<crate::sighting::Sighting>),
    /// A locator's heartbeat (`[cluster] role = "locator"`), naming the
    /// shards it owns: sinks subscribe to those.
    Beat(crate::cluster::Beat),
    /// The gateway's counters.
    Stats(Box<stats::Stats>),
    /// The beacons the gateway heard, known or not.
    HeardReport(Box<stats::HeardReport>),
    /// What a device heard in one fingerprint window, for recalibrating the
    /// radio model (`[localizer.recalibration]`; the learning store keeps it).
    Heard(crate::locate::recalibrate::Heard),
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
    /// The floor the device is on; `null` when no floor is more likely
    /// than the others together (then `cell` is `null` too). A one-floor
    /// site's floor is the site (its name, level 0).
    pub floor: Option<FloorName>,
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

/// A floor as people name it, and its level (0 the entrance floor,
/// negative below it).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FloorName {
    // Fields in key order: the MQTT encoder writes a location's keys sorted
    // (`gangway_io::topics`), and so does serde here.
    pub level: i32,
    pub name: String,
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
    /// A route across floors (a building of several), one leg per floor.
    Floors(Box<floors::FloorsRouteBody>),
    Error {
        error: ErrorBody,
    },
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
    /// The route's cells, each with its centre in metres.
    pub waypoints: Vec<crate::plan::Waypoint>,
    /// The line to walk, vertices in metres from the source's centre to the
    /// destination's, through the waypoints' cells (`plan::ServedLine`).
    pub line: Vec<crate::plan::LinePoint>,
    /// Where `line` comes from: `planner`, `cells`, or `fallback` when the
    /// planner's own line failed its check.
    pub line_from: crate::plan::LineSource,
    /// Metres along `line`.
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
        let line = crate::plan::ServedLine::of(site, planned, profile);
        let maneuvers =
            crate::plan::instructions::maneuvers_along(site, &planned.route, &line.points, profile);
        RouteBody {
            from,
            to,
            planner: planner.mode(),
            model_version: planner.model_version().map(str::to_owned),
            origin: planned.origin,
            profile: profile.name(),
            waypoints: planned.route.waypoints(site),
            line: line.metres(site),
            line_from: line.source,
            length_m: line.length_m(site),
            instructions: crate::plan::instructions::instructions(site, &planned.route, &maneuvers),
            maneuvers,
            reason: None,
            latency_us,
        }
    }
}

impl RouteBody {
    /// The route's cells and the line to walk in cell units, as guidance
    /// follows them: a line the planner drew read back from metres, else
    /// the cells' own line exactly (read back from metres it would differ
    /// from it in the last bits, and guidance would hold it as a drawn line).
    pub fn route_and_line(
        &self,
        site: &crate::site::Site,
    ) -> (crate::plan::Route, Vec<crate::plan::anyangle::GridPoint>) {
        let route = crate::plan::Route {
            cells: self.waypoints.iter().map(|w| w.cell).collect(),
        };
        let line = match self.line_from {
            crate::plan::LineSource::Planner => self
                .line
                .iter()
                .map(|p| crate::plan::anyangle::point_of_world(site, [p.x_m, p.y_m]))
                .collect(),
            _ => crate::plan::ServedLine::of_cells(&route).points,
        };
        (route, line)
    }
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ErrorBody {
    /// Stable code, sent as its string (`unknown_place`, `off_map`, …).
    pub code: RouteErrorCode,
    pub message: String,
    /// With `overloaded` and `rate_limited`: seconds to wait before asking again.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub retry_after_s: Option<f64>,
}

/// Schema id of the error answered to refused feedback.
pub(crate) const FEEDBACK_ERROR_SCHEMA: &str = "gangway.feedback-error/1";

/// The answer to feedback on a route this gateway did not give the device
/// (or that was scored already).
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FeedbackRefused {
    pub schema: &'static str,
    pub device: String,
    pub request_id: String,
    pub t: f64,
    pub error: FeedbackError,
}

#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FeedbackError {
    /// Always `unknown_request`.
    pub code: &'static str,
    pub message: &'static str,
}

impl FeedbackRefused {
    pub fn new(feedback: &crate::event::Feedback) -> FeedbackRefused {
        FeedbackRefused {
            schema: FEEDBACK_ERROR_SCHEMA,
            device: feedback.device.clone(),
            request_id: feedback.request_id.clone(),
            t: feedback.t,
            error: FeedbackError {
                code: "unknown_request",
                message: "feedback is taken once for a route this gateway gave the device \
                          recently; this request id is not one of them",
            },
        }
    }
}
