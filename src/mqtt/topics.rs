//! Topics and JSON payloads: where each [`Output`] goes and how it is
//! written. The MQTT sink publishes what [`Topics::encode`] makes and the
//! JSON Lines sink (`--print`, `--out`) writes the same messages, so the two
//! cannot drift apart.
//!
//! Topics under the prefix (default `gangway/<gateway id>`):
//! - `<prefix>/devices/<device>/location`: a location per fix;
//! - `<prefix>/devices/<device>/path`: a route reply per route request,
//!   and one per route re-planned when a walker left theirs;
//! - `<prefix>/devices/<device>/guidance`: guidance per fix of a device
//!   being guided along a route (see `guide`);
//! - `<prefix>/devices/<device>/feedback/error`: refused feedback;
//! - `<prefix>/devices/<device>/presence`: Home Assistant's tracker state
//!   (`mqtt::discovery`);
//! - `<prefix>/occupancy`: devices per named place (`mqtt::occupancy`);
//! - `<prefix>/status`, `<prefix>/stats` and the subscribed topics
//!   (`route/set`, `route/cancel`, `feedback`, `scans`): see docs/mqtt.md.

use serde::Serialize;

use crate::publish::Output;

/// One outgoing message.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Message {
    pub topic: String,
    pub payload: serde_json::Value,
    #[serde(skip)]
    pub retain: bool,
}

impl Message {
    fn of(topic: String, payload: &impl Serialize, retain: bool) -> Message {
        Message {
            topic,
            payload: serde_json::to_value(payload).expect("plain data serializes"),
            retain,
        }
    }
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

    /// A device's request to end its guidance session.
    pub fn route_cancel(&self, device: &str) -> String {
        format!("{}/devices/{device}/route/cancel", self.prefix)
    }

    /// Feedback on a route.
    pub fn feedback(&self, device: &str) -> String {
        format!("{}/devices/{device}/feedback", self.prefix)
    }

    /// Scans a phone publishes of the beacons it hears.
    pub fn scans(&self, device: &str) -> String {
        format!("{}/scans/{device}", self.prefix)
    }

    /// The message an output is published as, if it is published under
    /// this prefix (shared sightings go under the site's prefix, see
    /// `mqtt::sightings`; truth, adherence, accepted feedback and forgotten
    /// devices are not published).
    pub fn encode(&self, output: &Output) -> Option<Message> {
        Some(match output {
            Output::Location(l) => Message::of(self.location(&l.device), l, false),
            Output::Route(r) => Message::of(self.path(&r.device), &**r, false),
            Output::Guidance(g) => Message::of(self.guidance(&g.device), &**g, false),
            Output::FeedbackRefused(f) => {
                Message::of(format!("{}/error", self.feedback(&f.device)), f, false)
            }
            Output::Stats(s) => Message::of(self.stats(), &**s, true),
            Output::Truth(_)
            | Output::Forgotten(_)
            | Output::Adherence(_)
            | Output::Feedback(_)
            | Output::Sightings(_)
            | Output::Heard(_) => return None,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::RouteErrorCode;
    use crate::publish::{ErrorBody, PATH_SCHEMA, RouteOutcome, RouteReply};

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
                    retry_after_s: None,
                },
            },
        };
        let msg = Topics::new("gangway/gw")
            .encode(&Output::Route(Box::new(reply)))
            .unwrap();
        assert_eq!(msg.topic, "gangway/gw/devices/d/path");
        assert_eq!(msg.payload["error"]["code"], "unknown_place");
        assert!(msg.payload["error"].get("retry_after_s").is_none());
        assert_eq!(msg.payload["request_id"], "r1");
        assert!(msg.payload.get("waypoints").is_none());
    }
}
