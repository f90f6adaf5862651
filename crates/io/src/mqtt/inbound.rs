//! Messages the gateway subscribes to, from topic and bytes to what the
//! runtime consumes. Nothing here panics or gives up on bad input: every
//! message becomes an [`Inbound`] or a [`Rejected`] that says why.
//!
//! - `<prefix>/devices/<device>/route/set`: `{"to": place | [x, y], "profile"?, "request_id"?}`;
//!   a request that cannot be read still becomes a reply ([`Inbound::BadRoute`]);
//! - `<prefix>/devices/<device>/route/cancel`: any payload (empty, `{}`);
//!   ends the device's guidance session;
//! - `<prefix>/devices/<device>/feedback`: `{"request_id": "...", "score": 1..5}`;
//! - `<prefix>/scans/<device>`: `[{"uuid", "major", "minor", "rssi", "tx_power"?}]`,
//!   a phone's own scan, localized with the phone as observer;
//! - `<site prefix>/sightings/<gateway>`: another gateway's sightings;
//! - a locator's (`[cluster] role = "locator"`, [`super::cluster`]): the
//!   device topics above under the site prefix, the edges' sightings of the
//!   shards it owns (`<site prefix>/shards/<k>/sightings/<edge>`) and the
//!   other locators' heartbeats (`<site prefix>/locators/<locator>`);
//! - ESPresense nodes and Theengs Gateway / OpenMQTTGateway, when
//!   configured ([`super::receivers`]): their iBeacon messages, as sightings
//!   by the receiver.

use std::sync::Arc;

use serde::Deserialize;
use uuid::Uuid;

use super::cluster::{self, Role};
use super::receivers::{self, EspresenseConfig, TheengsConfig};
use super::sightings;
use crate::event::{FLOOR_NAME_RULE, Feedback, Inbound, RouteRequest, valid_floor_name};
use crate::plan::{Destination, RouteErrorCode};
use crate::sighting::valid_device_id;
use crate::sighting::{BeaconId, Mac, Sighting};
use crate::topics::Topics;

/// Why a message was not used; the daemon logs it and counts it.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum Rejected {
    #[error("{topic}: not a topic this gateway serves")]
    UnknownTopic { topic: String },
    #[error(
        "{topic}: the device id cannot be a topic level (empty, over 128 bytes, or `+`, `#`, `/`, control characters)"
    )]
    BadDevice { topic: String },
    #[error(
        "{topic}: payload of {size} bytes is over the {max}-byte limit ([mqtt] max_payload_bytes)"
    )]
    TooLarge {
        topic: String,
        size: usize,
        max: usize,
    },
    #[error("{topic}: {reason}")]
    BadPayload { topic: String, reason: String },
    /// This gateway's own shared sightings, echoed by the broker.
    #[error("{topic}: own sightings")]
    Own { topic: String },
    /// A receiver's message about a device that is no iBeacon (ESPresense
    /// and Theengs report every BLE device they hear): nothing to do.
    #[error("{topic}: not an iBeacon")]
    NotAnIbeacon { topic: String },
}

impl Rejected {
    pub(crate) fn is_oversized(&self) -> bool {
        matches!(self, Rejected::TooLarge { .. })
    }
}

/// Reads the topics one gateway subscribes to.
pub struct Inbox {
    topics: Topics,
    site_prefix: String,
    gateway_id: String,
    max_payload: usize,
    /// Whether shared sightings are exchanged (advertiser orientation).
    share: bool,
    /// What this gateway does among the site's (`[cluster] role`).
    role: Role,
    espresense: Option<EspresenseConfig>,
    theengs: Option<TheengsConfig>,
    /// How far ahead of this gateway's clock another gateway's sighting may
    /// be: one from further ahead would move its tag's window into the
    /// future and silence the tag until then.
    max_clock_skew_s: f64,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct RouteSet {
    to: Destination,
    #[serde(default)]
    floor: Option<String>,
    #[serde(default)]
    profile: Option<String>,
    #[serde(default)]
    request_id: Option<String>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct FeedbackBody {
    request_id: String,
    score: u8,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ScanEntry {
    uuid: Uuid,
    major: u16,
    minor: u16,
    rssi: i16,
    #[serde(default)]
    tx_power: Option<i8>,
    /// Parsed whole (six hex bytes) or the scan is refused: it comes from
    /// anyone who can publish.
    #[serde(default)]
    mac: Option<Mac>,
}

impl Inbox {
    pub fn new(
        topics: Topics,
        site_prefix: String,
        gateway_id: String,
        max_payload: usize,
        share: bool,
    ) -> Self {
        Inbox {
            topics,
            site_prefix,
            gateway_id,
            max_payload,
            share,
            role: Role::Single,
            espresense: None,
            theengs: None,
            max_clock_skew_s: DEFAULT_MAX_CLOCK_SKEW_S,
        }
    }

    /// Refuses other gateways' sightings more than `seconds` ahead of this
    /// gateway's clock (`[mqtt] max_clock_skew_s`).
    pub fn with_max_clock_skew(mut self, seconds: f64) -> Self {
        self.max_clock_skew_s = seconds;
        self
    }

    /// Reads what a gateway of `role` takes: an edge nothing, a locator the
    /// site's device topics, shards and heartbeats.
    pub fn with_role(mut self, role: Role) -> Self {
        self.role = role;
        self
    }

    /// Also reads the receivers `[mqtt.espresense]` and `[mqtt.theengs]`
    /// configure.
    pub fn with_receivers(
        mut self,
        espresense: Option<EspresenseConfig>,
        theengs: Option<TheengsConfig>,
    ) -> Self {
        self.espresense = espresense;
        self.theengs = theengs;
        self
    }

    /// The topic filters to subscribe to (a locator's shards come and go:
    /// the sink subscribes to them as it owns them).
    pub(crate) fn subscriptions(&self) -> Vec<String> {
        let device_topics = [
            self.topics.route_set("+"),
            self.topics.route_cancel("+"),
            self.topics.feedback("+"),
        ];
        match self.role {
            Role::Single => {}
            // An edge passes its receivers' sightings on, by shard.
            Role::Edge => {
                return receivers::subscriptions(self.espresense.as_ref(), self.theengs.as_ref());
            }
            Role::Locator => return device_topics.to_vec(),
        }
        let mut filters = device_topics.to_vec();
        filters.push(self.topics.scans("+"));
        if self.share {
            filters.push(sightings::topic(&self.site_prefix, "+"));
        }
        filters.extend(receivers::subscriptions(
            self.espresense.as_ref(),
            self.theengs.as_ref(),
        ));
        filters
    }

    /// The topic filters of streams a newer message soon replaces, to
    /// subscribe to at QoS 0: the other locators' heartbeats.
    pub(crate) fn stream_subscriptions(&self) -> Vec<String> {
        match self.role {
            Role::Locator => vec![cluster::locator_topic(&self.site_prefix, "+")],
            Role::Single | Role::Edge => Vec::new(),
        }
    }

    /// Reads one message received at `now` (seconds since the epoch).
    pub fn read(&self, topic: &str, payload: &[u8], now: f64) -> Result<Inbound, Rejected> {
        self.read_sized(topic, payload, payload.len(), now)
    }

    /// [`Inbox::read`] of a message of `size` bytes whose payload the link
    /// cut off (empty) for being over the limit.
    pub(crate) fn read_sized(
        &self,
        topic: &str,
        payload: &[u8],
        size: usize,
        now: f64,
    ) -> Result<Inbound, Rejected> {
        let unknown = || Rejected::UnknownTopic {
            topic: topic.to_owned(),
        };
        let (kind, id) = self.classify(topic).ok_or_else(unknown)?;
        if !valid_device_id(id) {
            return Err(Rejected::BadDevice {
                topic: topic.to_owned(),
            });
        }
        let too_large = size.max(payload.len()) > self.max_payload;
        let bad = |reason: String| Rejected::BadPayload {
            topic: topic.to_owned(),
            reason,
        };
        match kind {
            Kind::RouteSet => Ok(self.route(id, payload, size, now)),
            _ if too_large => Err(Rejected::TooLarge {
                topic: topic.to_owned(),
                size,
                max: self.max_payload,
            }),
            // What a cancel says is all in its topic.
            Kind::RouteCancel => Ok(Inbound::Cancel {
                device: id.to_owned(),
                t: now,
            }),
            Kind::Feedback => {
                let body: FeedbackBody = serde_json::from_slice(payload).map_err(|e| {
                    bad(format!(
                        "{e}; feedback is {{\"request_id\": \"...\", \"score\": 1..5}}"
                    ))
                })?;
                if !(1..=5).contains(&body.score) {
                    return Err(bad(format!("score {} is not 1..5", body.score)));
                }
                if !valid_request_id(&body.request_id) {
                    return Err(bad(REQUEST_ID_RULE.to_owned()));
                }
                Ok(Inbound::Feedback(Feedback {
                    t: now,
                    device: id.to_owned(),
                    request_id: body.request_id,
                    score: body.score,
                }))
            }
            Kind::Scan => {
                let entries: Vec<ScanEntry> = serde_json::from_slice(payload).map_err(|e| {
                    bad(format!(
                        "{e}; a scan is [{{\"uuid\", \"major\", \"minor\", \"rssi\", optional \"tx_power\", \"mac\"}}, ...]"
                    ))
                })?;
                let observer: Arc<str> = id.into();
                Ok(Inbound::Scan(
                    entries
                        .into_iter()
                        .map(|e| Sighting {
                            advertiser_mac: e.mac,
                            t: now,
                            observer: observer.clone(),
                            advertiser: BeaconId {
                                uuid: e.uuid,
                                major: e.major,
                                minor: e.minor,
                            },
                            tx_power: e.tx_power,
                            rssi: e.rssi,
                        })
                        .collect(),
                ))
            }
            Kind::Sightings if id == self.gateway_id => Err(Rejected::Own {
                topic: topic.to_owned(),
            }),
            Kind::Sightings => {
                let shared = sightings::decode(id, payload).map_err(bad)?;
                if let Some(ahead) = shared.iter().map(|s| s.t - now).reduce(f64::max)
                    && ahead > self.max_clock_skew_s
                {
                    return Err(bad(format!(
                        "a sighting is {ahead:.3e} s ahead of this gateway's clock, more than \
                         [mqtt] max_clock_skew_s = {}; the batch is refused (is the sender's \
                         clock set, NTP?)",
                        self.max_clock_skew_s
                    )));
                }
                Ok(Inbound::Shared(shared))
            }
            Kind::Beat => Ok(Inbound::Beat(
                cluster::decode_beat(id, payload).map_err(bad)?,
            )),
            Kind::Espresense { device } => {
                receiver(receivers::espresense(id, device, payload, now), topic)
            }
            Kind::Theengs => receiver(receivers::theengs(id, payload, now), topic),
        }
    }

    fn route(&self, device: &str, payload: &[u8], size: usize, now: f64) -> Inbound {
        let bad = |request_id, code, message| Inbound::BadRoute {
            device: device.to_owned(),
            request_id,
            code,
            message,
        };
        if size.max(payload.len()) > self.max_payload {
            return bad(
                None,
                RouteErrorCode::PayloadTooLarge,
                format!(
                    "the request is {size} bytes; the limit is {}",
                    self.max_payload
                ),
            );
        }
        let value: serde_json::Value = match serde_json::from_slice(payload) {
            Ok(v) => v,
            Err(e) => {
                return bad(
                    None,
                    RouteErrorCode::InvalidJson,
                    format!("the request is not JSON: {e}"),
                );
            }
        };
        // Echo the request id even when the rest of the request is wrong
        // (but not one too long to be an id: it would be echoed and stored).
        let request_id = value
            .get("request_id")
            .and_then(|id| id.as_str())
            .filter(|id| valid_request_id(id))
            .map(str::to_owned);
        match serde_json::from_value::<RouteSet>(value) {
            Ok(r) if !r.request_id.as_deref().is_none_or(valid_request_id) => bad(
                None,
                RouteErrorCode::InvalidRequest,
                REQUEST_ID_RULE.to_owned(),
            ),
            Ok(r) if !r.floor.as_deref().is_none_or(valid_floor_name) => bad(
                request_id,
                RouteErrorCode::InvalidRequest,
                FLOOR_NAME_RULE.to_owned(),
            ),
            Ok(r) => Inbound::Route(RouteRequest {
                t: now,
                device: device.to_owned(),
                to: r.to,
                floor: r.floor,
                profile: r.profile,
                request_id: r.request_id,
            }),
            Err(e) => bad(
                request_id,
                RouteErrorCode::InvalidRequest,
                format!(
                    "{e}; a request is {{\"to\": \"<place>\" or [x, y], \"floor\"?: \"<floor>\", \"profile\"?: \"...\", \"request_id\"?: \"...\"}}"
                ),
            ),
        }
    }

    /// What a topic is, and the id of whom it is about (the device, or the
    /// gateway or receiver that heard).
    fn classify<'t>(&self, topic: &'t str) -> Option<(Kind<'t>, &'t str)> {
        if let Some(base) = self.espresense.as_ref().map(|e| e.topic.as_str())
            && let Some(rest) = strip(topic, base).and_then(|r| r.strip_prefix("devices/"))
        {
            let (device, room) = rest.split_once('/')?;
            return Some((Kind::Espresense { device }, room));
        }
        if let Some(base) = self.theengs.as_ref().map(|t| t.topic.as_str())
            && let Some(rest) = strip(topic, base)
            && let Some((gateway, mac)) = rest.split_once("/BTtoMQTT/")
            && !mac.contains('/')
        {
            return Some((Kind::Theengs, gateway));
        }
        if let Some(rest) = strip(topic, self.topics.devices_prefix())
            .and_then(|rest| rest.strip_prefix("devices/"))
        {
            if let Some(device) = rest.strip_suffix("/route/set") {
                return Some((Kind::RouteSet, device));
            }
            if let Some(device) = rest.strip_suffix("/route/cancel") {
                return Some((Kind::RouteCancel, device));
            }
            if let Some(device) = rest.strip_suffix("/feedback") {
                return Some((Kind::Feedback, device));
            }
            return None;
        }
        if self.role == Role::Single
            && let Some(device) =
                strip(topic, self.topics.prefix()).and_then(|rest| rest.strip_prefix("scans/"))
        {
            return Some((Kind::Scan, device));
        }
        let rest = strip(topic, &self.site_prefix)?;
        match self.role {
            Role::Single => {
                let gateway = rest.strip_prefix("sightings/")?;
                self.share.then_some((Kind::Sightings, gateway))
            }
            Role::Edge => None,
            Role::Locator => {
                if let Some(locator) = rest.strip_prefix("locators/") {
                    return Some((Kind::Beat, locator));
                }
                let (shard, edge) = rest.strip_prefix("shards/")?.split_once("/sightings/")?;
                shard
                    .parse::<u16>()
                    .is_ok()
                    .then_some((Kind::Sightings, edge))
            }
        }
    }
}

/// `[mqtt] max_clock_skew_s` unless set: clocks kept by NTP agree within
/// milliseconds, and a batch waits at most a share interval to be sent.
pub const DEFAULT_MAX_CLOCK_SKEW_S: f64 = 5.0;

/// Longest request id, in bytes: ids are echoed in replies and kept in the
/// learning store, so a client cannot make them large.
pub(crate) const MAX_REQUEST_ID_BYTES: usize = 128;

const REQUEST_ID_RULE: &str = "`request_id` must be 1 to 128 bytes without control characters";

fn valid_request_id(id: &str) -> bool {
    !id.is_empty() && id.len() <= MAX_REQUEST_ID_BYTES && !id.chars().any(char::is_control)
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind<'t> {
    RouteSet,
    RouteCancel,
    Feedback,
    Scan,
    Sightings,
    /// A locator's heartbeat (the id names the locator).
    Beat,
    /// An ESPresense node's message about `device` (the id names its room).
    Espresense {
        device: &'t str,
    },
    /// A Theengs Gateway or OpenMQTTGateway message (the id names the gateway).
    Theengs,
}

/// A receiver's message as what the runtime takes: its sighting, or nothing
/// to do for a device that is not an iBeacon.
fn receiver(read: receivers::Read, topic: &str) -> Result<Inbound, Rejected> {
    match read {
        Ok(Some(sighting)) => Ok(Inbound::Shared(vec![sighting])),
        Ok(None) => Err(Rejected::NotAnIbeacon {
            topic: topic.to_owned(),
        }),
        Err(reason) => Err(Rejected::BadPayload {
            topic: topic.to_owned(),
            reason,
        }),
    }
}

/// `topic` without `prefix/`.
fn strip<'t>(topic: &'t str, prefix: &str) -> Option<&'t str> {
    topic.strip_prefix(prefix)?.strip_prefix('/')
}

#[cfg(test)]
mod tests {
    use super::*;

    fn inbox() -> Inbox {
        Inbox::new(
            Topics::new("gangway/gw"),
            "gangway/sites/s".into(),
            "gw".into(),
            1000,
            true,
        )
    }

    fn code(inbound: Inbound) -> (RouteErrorCode, Option<String>) {
        match inbound {
            Inbound::BadRoute {
                code, request_id, ..
            } => (code, request_id),
            other => panic!("expected an error reply, got {other:?}"),
        }
    }

    #[test]
    fn a_route_request_is_read_from_its_topic() {
        let r = inbox()
            .read(
                "gangway/gw/devices/phone-1/route/set",
                br#"{"to":"help desk","request_id":"r1"}"#,
                5.0,
            )
            .unwrap();
        assert_eq!(
            r,
            Inbound::Route(RouteRequest {
                t: 5.0,
                device: "phone-1".into(),
                to: Destination::Place("help desk".into()),
                floor: None,
                profile: None,
                request_id: Some("r1".into()),
            })
        );
    }

    #[test]
    fn a_floor_name_is_bounded() {
        let i = inbox();
        let t = "gangway/gw/devices/p/route/set";
        let long = format!(
            r#"{{"to":[1,2],"floor":"{}","request_id":"r1"}}"#,
            "F".repeat(65)
        );
        assert_eq!(
            code(i.read(t, long.as_bytes(), 0.0).unwrap()),
            (RouteErrorCode::InvalidRequest, Some("r1".into()))
        );
        let named = i.read(t, br#"{"to":[1,2],"floor":"L1"}"#, 0.0).unwrap();
        assert!(
            matches!(&named, Inbound::Route(r) if r.floor.as_deref() == Some("L1")),
            "{named:?}"
        );
    }

    #[test]
    fn unreadable_route_requests_become_error_replies_with_their_id() {
        let i = inbox();
        let t = "gangway/gw/devices/p/route/set";
        assert_eq!(
            code(i.read(t, b"{nope", 0.0).unwrap()),
            (RouteErrorCode::InvalidJson, None)
        );
        assert_eq!(
            code(
                i.read(t, br#"{"request_id":"r9","to":{"x":1}}"#, 0.0)
                    .unwrap()
            ),
            (RouteErrorCode::InvalidRequest, Some("r9".into()))
        );
        assert_eq!(
            code(i.read(t, &vec![b' '; 1001], 0.0).unwrap()).0,
            RouteErrorCode::PayloadTooLarge
        );
        // Cut off by the link: empty, with the size it had.
        assert_eq!(
            code(i.read_sized(t, b"", 16 << 20, 0.0).unwrap()).0,
            RouteErrorCode::PayloadTooLarge
        );
        let long_id = format!(r#"{{"to":"x","request_id":"{}"}}"#, "i".repeat(129));
        assert_eq!(
            code(i.read(t, long_id.as_bytes(), 0.0).unwrap()),
            (RouteErrorCode::InvalidRequest, None)
        );
    }

    #[test]
    fn a_cancel_is_read_from_its_topic_whatever_its_payload() {
        let i = inbox();
        let t = "gangway/gw/devices/phone-1/route/cancel";
        for payload in [&b""[..], b"{}", b"please stop"] {
            assert_eq!(
                i.read(t, payload, 5.0),
                Ok(Inbound::Cancel {
                    device: "phone-1".into(),
                    t: 5.0
                })
            );
        }
        assert!(
            i.subscriptions()
                .contains(&"gangway/gw/devices/+/route/cancel".to_owned())
        );
        assert!(matches!(
            i.read(t, &vec![b' '; 1001], 0.0),
            Err(Rejected::TooLarge { .. })
        ));
    }

    #[test]
    fn scans_feedback_and_shared_sightings_are_read_or_refused() {
        let i = inbox();
        let scan = br#"[{"uuid":"5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84","major":1,"minor":3001,"rssi":-70}]"#;
        let Inbound::Scan(s) = i.read("gangway/gw/scans/phone-2", scan, 9.0).unwrap() else {
            panic!()
        };
        assert_eq!((&*s[0].observer, s[0].t, s[0].rssi), ("phone-2", 9.0, -70));
        assert_eq!(s[0].advertiser_mac, None);
        let with_mac = br#"[{"uuid":"5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84","major":1,"minor":3001,"rssi":-70,"mac":"e0:78:a3:3d:b5:d6"}]"#;
        let Inbound::Scan(s) = i.read("gangway/gw/scans/phone-2", with_mac, 9.0).unwrap() else {
            panic!()
        };
        assert_eq!(
            s[0].advertiser_mac.unwrap().to_string(),
            "E0:78:A3:3D:B5:D6"
        );
        for mac in [
            "\"E0:78\"",
            "\"E0:78:A3:3D:B5:D6:00\"",
            "\"zz:78:A3:3D:B5:D6\"",
            "7",
        ] {
            let scan = format!(
                r#"[{{"uuid":"5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84","major":1,"minor":3001,"rssi":-70,"mac":{mac}}}]"#
            );
            let err = i
                .read("gangway/gw/scans/phone-2", scan.as_bytes(), 9.0)
                .unwrap_err();
            assert!(matches!(err, Rejected::BadPayload { .. }), "{mac}: {err}");
        }
        assert!(matches!(
            i.read(
                "gangway/gw/devices/p/feedback",
                br#"{"request_id":"r","score":6}"#,
                0.0
            ),
            Err(Rejected::BadPayload { .. })
        ));
        assert!(matches!(
            i.read("gangway/gw/scans/p", &vec![b'['; 2000], 0.0),
            Err(Rejected::TooLarge { .. })
        ));
        assert!(matches!(
            i.read("gangway/sites/s/sightings/gw", b"{}", 0.0),
            Err(Rejected::Own { .. })
        ));
        assert!(matches!(
            i.read("gangway/gw/devices/a\u{1}b/route/set", b"{}", 0.0),
            Err(Rejected::BadDevice { .. })
        ));
        assert!(matches!(
            i.read("gangway/gw/other", b"{}", 0.0),
            Err(Rejected::UnknownTopic { .. })
        ));
    }

    #[test]
    fn sightings_from_a_clock_far_ahead_are_refused() {
        let i = inbox().with_max_clock_skew(5.0);
        let batch = |t: f64| {
            format!(
                r#"{{"schema":"gangway.sightings/1","gateway":"gw-b","sightings":[{{"t":{t},"uuid":"0f0e0d0c-0b0a-4908-8706-050403020100","major":7,"minor":1,"rssi":-40}}]}}"#
            )
        };
        let topic = "gangway/sites/s/sightings/gw-b";
        let now = 1_767_225_600.0;
        // The attack: one sighting dated 1e300 would silence the tag for good.
        let err = i.read(topic, batch(1e300).as_bytes(), now).unwrap_err();
        assert!(
            err.to_string().contains("ahead of this gateway's clock"),
            "{err}"
        );
        assert!(i.read(topic, batch(now + 60.0).as_bytes(), now).is_err());
        for t in [now + 4.0, now, now - 30.0] {
            assert!(
                matches!(
                    i.read(topic, batch(t).as_bytes(), now),
                    Ok(Inbound::Shared(_))
                ),
                "{t}"
            );
        }
    }

    #[test]
    fn a_locator_reads_the_site_s_device_topics_its_shards_and_heartbeats() {
        let site = "gangway/sites/s";
        let i = Inbox::new(
            Topics::new("gangway/loc-1").with_devices_under(site),
            site.into(),
            "loc-1".into(),
            1000,
            false,
        )
        .with_role(Role::Locator);
        let subscriptions = i.subscriptions();
        assert!(subscriptions.contains(&format!("{site}/devices/+/route/set")));
        assert_eq!(i.stream_subscriptions(), [format!("{site}/locators/+")]);
        assert!(!subscriptions.iter().any(|f| f.contains("sightings")));
        let now = 1_767_225_600.0;
        let request = i
            .read(
                &format!("{site}/devices/tag-1/route/set"),
                br#"{"to":"x"}"#,
                now,
            )
            .unwrap();
        assert!(matches!(&request, Inbound::Route(r) if r.device == "tag-1"));
        let batch = br#"{"schema":"gangway.sightings/1","gateway":"gw-b","sightings":[]}"#;
        let shard = i.read(&format!("{site}/shards/3/sightings/gw-b"), batch, now);
        assert!(matches!(shard, Ok(Inbound::Shared(_))), "{shard:?}");
        let beat = br#"{"schema":"gangway.locator/1","locator":"loc-2","state":"serving","shards":8,"owned":[1],"t":1}"#;
        let heard = i.read(&format!("{site}/locators/loc-2"), beat, now);
        assert!(
            matches!(&heard, Ok(Inbound::Beat(b)) if b.locator == "loc-2"),
            "{heard:?}"
        );
        // What a single gateway reads is not a locator's.
        for topic in [
            format!("{site}/sightings/gw-b"),
            format!("{site}/shards/x/sightings/gw-b"),
            "gangway/loc-1/scans/phone".to_owned(),
            "gangway/loc-1/devices/tag-1/route/set".to_owned(),
        ] {
            let read = i.read(&topic, batch, now);
            assert!(
                matches!(read, Err(Rejected::UnknownTopic { .. })),
                "{topic}: {read:?}"
            );
        }
        // An edge reads nothing but its receivers.
        assert!(inbox().with_role(Role::Edge).subscriptions().is_empty());
    }
}
