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

use crate::publish::{FloorName, Location, Output};
use crate::site::Cell;

/// One outgoing message, its payload already written.
#[derive(Clone, Debug, PartialEq)]
pub struct Message {
    pub topic: String,
    /// JSON (or plain text: presence, status).
    pub payload: Vec<u8>,
    pub retain: bool,
}

impl Message {
    /// A JSON message. Keys come out sorted at every level (through
    /// `serde_json::Value`), as every payload has been since the first
    /// version, so a payload's bytes do not change with field order.
    pub(crate) fn json(topic: String, payload: &impl Serialize, retain: bool) -> Message {
        let value = serde_json::to_value(payload).expect("plain data serializes");
        Message {
            topic,
            payload: serde_json::to_vec(&value).expect("JSON values serialize"),
            retain,
        }
    }

    /// The payload read back as JSON (tests, tools); `Null` if it is not JSON.
    pub fn value(&self) -> serde_json::Value {
        serde_json::from_slice(&self.payload).unwrap_or_default()
    }
}

/// A location as [`Message::json`] would write it, written directly: the
/// gateway's most frequent message, so it skips building a JSON tree. Fields
/// in sorted order, and the confidence widened to `f64` as a JSON tree holds
/// it, so the bytes are the same (checked in the tests below).
#[derive(Serialize)]
struct LocationPayload<'a> {
    anchors_heard: usize,
    cell: Option<Cell>,
    confidence: f64,
    device: &'a str,
    floor: &'a Option<FloorName>,
    label: &'a Option<String>,
    place: &'a Option<String>,
    schema: &'static str,
    t: f64,
    x_m: Option<f64>,
    y_m: Option<f64>,
}

impl LocationPayload<'_> {
    fn of(l: &Location) -> LocationPayload<'_> {
        let Location {
            schema,
            device,
            t,
            floor,
            cell,
            label,
            x_m,
            y_m,
            place,
            confidence,
            anchors_heard,
        } = l;
        LocationPayload {
            anchors_heard: *anchors_heard,
            cell: *cell,
            confidence: f64::from(*confidence),
            device,
            floor,
            label,
            place,
            schema,
            t: *t,
            x_m: *x_m,
            y_m: *y_m,
        }
    }
}

/// Topic names under one prefix.
#[derive(Clone, Debug)]
pub struct Topics {
    prefix: String,
    /// Where the `devices/…` topics go: the prefix, except for a locator
    /// (`[cluster] role = "locator"`), whose devices' topics are the site's,
    /// so that a client need not know which locator holds its device.
    devices: String,
}

impl Topics {
    pub fn new(prefix: impl Into<String>) -> Self {
        let prefix = prefix.into();
        Topics {
            devices: prefix.clone(),
            prefix,
        }
    }

    /// These topics with the `devices/…` ones under `devices_prefix`.
    pub fn with_devices_under(mut self, devices_prefix: impl Into<String>) -> Self {
        self.devices = devices_prefix.into();
        self
    }

    pub(crate) fn prefix(&self) -> &str {
        &self.prefix
    }

    pub(crate) fn devices_prefix(&self) -> &str {
        &self.devices
    }

    pub(crate) fn location(&self, device: &str) -> String {
        format!("{}/devices/{device}/location", self.devices)
    }

    /// Plain-text tracker state for Home Assistant: place, `home` or `not_home`.
    pub(crate) fn presence(&self, device: &str) -> String {
        format!("{}/devices/{device}/presence", self.devices)
    }

    /// Retained devices per named place.
    pub(crate) fn occupancy(&self) -> String {
        format!("{}/occupancy", self.prefix)
    }

    pub fn path(&self, device: &str) -> String {
        format!("{}/devices/{device}/path", self.devices)
    }

    /// Retained `online` / `offline` (the last will).
    pub(crate) fn status(&self) -> String {
        format!("{}/status", self.prefix)
    }

    /// Retained counters.
    pub(crate) fn stats(&self) -> String {
        format!("{}/stats", self.prefix)
    }

    /// The beacons the gateway heard (retained, beside the stats).
    pub(crate) fn heard(&self) -> String {
        format!("{}/heard", self.prefix)
    }

    /// Guidance for a device walking a route.
    pub(crate) fn guidance(&self, device: &str) -> String {
        format!("{}/devices/{device}/guidance", self.devices)
    }

    /// Route requests for a device.
    pub fn route_set(&self, device: &str) -> String {
        format!("{}/devices/{device}/route/set", self.devices)
    }

    /// A device's request to end its guidance session.
    pub(crate) fn route_cancel(&self, device: &str) -> String {
        format!("{}/devices/{device}/route/cancel", self.devices)
    }

    /// Feedback on a route.
    pub(crate) fn feedback(&self, device: &str) -> String {
        format!("{}/devices/{device}/feedback", self.devices)
    }

    /// Scans a phone publishes of the beacons it hears.
    pub(crate) fn scans(&self, device: &str) -> String {
        format!("{}/scans/{device}", self.prefix)
    }

    /// The message an output is published as, if it is published under
    /// this prefix (shared sightings go under the site's prefix, see
    /// `mqtt::sightings`; truth, adherence, accepted feedback and forgotten
    /// devices are not published).
    pub fn encode(&self, output: &Output) -> Option<Message> {
        Some(match output {
            Output::Location(l) => {
                // A location is about 250 bytes: one allocation, no growing.
                let mut payload = Vec::with_capacity(320);
                serde_json::to_writer(&mut payload, &LocationPayload::of(l))
                    .expect("plain data serializes");
                Message {
                    topic: self.location(&l.device),
                    payload,
                    retain: false,
                }
            }
            Output::Route(r) => Message::json(self.path(&r.device), &**r, false),
            Output::Guidance(g) => Message::json(self.guidance(&g.device), &**g, false),
            Output::FeedbackRefused(f) => {
                Message::json(format!("{}/error", self.feedback(&f.device)), f, false)
            }
            Output::Stats(s) => Message::json(self.stats(), &**s, true),
            Output::HeardReport(h) => Message::json(self.heard(), &**h, true),
            Output::Truth(_)
            | Output::Forgotten(_)
            | Output::Adherence(_)
            | Output::Feedback(_)
            | Output::Sightings(_)
            | Output::Beat(_)
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
        let payload = msg.value();
        assert_eq!(payload["error"]["code"], "unknown_place");
        assert!(payload["error"].get("retry_after_s").is_none());
        assert_eq!(payload["request_id"], "r1");
        assert!(payload.get("waypoints").is_none());
    }

    fn location(device: &str, cell: Option<Cell>, confidence: f32) -> Location {
        Location {
            schema: crate::publish::LOCATION_SCHEMA,
            device: device.into(),
            t: 1_767_225_600.593,
            floor: cell.map(|_| FloorName {
                name: "G \"east\"".into(),
                level: -1,
            }),
            cell,
            label: cell.map(|_| "L03".into()),
            x_m: cell.map(|c| f64::from(c.x) + 0.5),
            y_m: cell.map(|c| f64::from(c.y) + 0.5),
            place: cell.map(|_| "north \"stacks\" \u{e9}\n".into()),
            confidence,
            anchors_heard: 2,
        }
    }

    #[test]
    fn a_location_is_written_as_its_json_tree_would_be() {
        for l in [
            location("walker-03", Some(Cell::new(11, 2)), 0.242_959_9),
            location("ph\u{f6}ne \"7\"", None, 1.0 / 3.0),
            location("x", Some(Cell::new(0, 0)), f32::NAN),
        ] {
            let direct = Topics::new("gangway/gw").encode(&Output::Location(l.clone()));
            let tree = Message::json("gangway/gw/devices/x/location".into(), &l, false);
            assert_eq!(
                String::from_utf8(direct.unwrap().payload).unwrap(),
                String::from_utf8(tree.payload).unwrap()
            );
        }
    }
}
