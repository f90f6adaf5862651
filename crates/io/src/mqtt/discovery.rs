//! Home Assistant MQTT discovery: retained config messages under
//! `<discovery prefix>/<component>/<node>/<object>/config` that make Home
//! Assistant create
//! - a `device_tracker` per tracked device: state from the plain-text
//!   `<prefix>/devices/<device>/presence` ([`Discovery::presence`]), attributes
//!   floor, level, x, y, place, confidence, cell, label and t from its
//!   location messages;
//! - for the gateway: a connectivity sensor, one sensor per counter of
//!   `<prefix>/stats`, and one occupancy sensor per named place of the site
//!   and, on a building of several floors, per floor, reading
//!   `<prefix>/occupancy` (see `occupancy`).
//!
//! Why a separate presence topic: Home Assistant's MQTT device tracker (up to
//! 2024.1 at least) compares a value template's result only with
//! `payload_home` / `payload_not_home` and otherwise takes the *raw* payload
//! as the location name, so a tracker reading the location JSON shows the
//! whole JSON whenever the device is at a named place. A payload that already
//! is the state is read the same way by every version.

use serde_json::json;

use super::occupancy::place_key;
use crate::publish::Location;
use crate::publish::stats::{COUNTERS, GAUGES};
use crate::topics::{Message, Topics};

/// Tracker state of a device located in the building but at no named place.
pub(crate) const HOME: &str = "home";
/// Tracker state of a device whose location is unknown.
pub(crate) const NOT_HOME: &str = "not_home";

/// The tracker's attributes, from one location message. `get` keeps keys the
/// message leaves out (an older gateway's `label`) from failing the template:
/// every message updates every attribute, null when it has no value.
const TRACKER_ATTRIBUTES: &str = "{{ {'floor': (value_json.get('floor') or {}).get('name'), \
     'level': (value_json.get('floor') or {}).get('level'), \
     'x': value_json.get('x_m'), 'y': value_json.get('y_m'), \
     'place': value_json.get('place'), 'confidence': value_json.get('confidence'), \
     'cell': value_json.get('cell'), 'label': value_json.get('label'), \
     't': value_json.get('t')} | tojson }}";

/// Builds discovery messages for one gateway.
pub(crate) struct Discovery {
    prefix: String,
    gateway_id: String,
    node: String,
    topics: Topics,
    /// The named places (by `occupancy::place_key`) with the object id of
    /// each one's occupancy sensor, in the building's order.
    places: Vec<(String, String)>,
    /// A building's floors with the object id of each one's sensor; none on
    /// a one-floor site.
    floors: Vec<(String, String)>,
}

impl Discovery {
    pub(crate) fn new(
        discovery_prefix: &str,
        gateway_id: &str,
        topics: Topics,
        places: Vec<String>,
        floors: Vec<String>,
    ) -> Self {
        Discovery {
            prefix: discovery_prefix.to_owned(),
            gateway_id: gateway_id.to_owned(),
            node: object_id(gateway_id),
            topics,
            places: with_object_ids("occupancy", places),
            floors: with_object_ids("floor", floors),
        }
    }

    fn gateway_device(&self) -> serde_json::Value {
        json!({
            "identifiers": [format!("gangway_{}", self.node)],
            "name": format!("gangway {}", self.gateway_id),
            "manufacturer": "gangway",
            "model": "BLE gateway",
            "sw_version": env!("CARGO_PKG_VERSION"),
        })
    }

    fn availability(&self) -> serde_json::Value {
        json!([{
            "topic": self.topics.status(),
            "payload_available": "online",
            "payload_not_available": "offline",
        }])
    }

    fn config_topic(&self, component: &str, object: &str) -> String {
        format!("{}/{component}/{}/{object}/config", self.prefix, self.node)
    }

    fn config(&self, component: &str, object: &str, payload: serde_json::Value) -> Message {
        Message::json(self.config_topic(component, object), &payload, true)
    }

    /// The gateway's own entities: connectivity, counters and one occupancy
    /// sensor per named place.
    pub(crate) fn gateway(&self) -> Vec<Message> {
        let mut out = vec![self.config(
            "binary_sensor",
            "status",
            json!({
                "name": "Status",
                "unique_id": format!("gangway_{}_status", self.node),
                "device_class": "connectivity",
                "state_topic": self.topics.status(),
                "payload_on": "online",
                "payload_off": "offline",
                "device": self.gateway_device(),
            }),
        )];
        let sensors = COUNTERS
            .iter()
            .map(|c| (c, "total_increasing"))
            .chain(GAUGES.iter().map(|g| (g, "measurement")));
        for (&(key, name), state_class) in sensors {
            out.push(self.config(
                "sensor",
                key,
                json!({
                    "name": name,
                    "unique_id": format!("gangway_{}_{key}", self.node),
                    "state_topic": self.topics.stats(),
                    "value_template": format!("{{{{ value_json.{key} }}}}"),
                    "state_class": state_class,
                    "entity_category": "diagnostic",
                    "availability": self.availability(),
                    "device": self.gateway_device(),
                }),
            ));
        }
        for (place, object) in &self.places {
            out.push(self.occupancy_sensor("places", &format!("{place} occupancy"), place, object));
        }
        for (floor, object) in &self.floors {
            out.push(self.occupancy_sensor(
                "floors",
                &format!("Devices on {floor}"),
                floor,
                object,
            ));
        }
        out
    }

    /// A sensor of the count under `key` in the occupancy message's
    /// `counts` (`places` or `floors`).
    fn occupancy_sensor(&self, counts: &str, name: &str, key: &str, object: &str) -> Message {
        // A JSON string is also a Jinja string literal: quotes and backslashes
        // in a place's name stay inside it.
        let key = serde_json::Value::from(key).to_string();
        self.config(
            "sensor",
            object,
            json!({
                "name": name,
                "unique_id": format!("gangway_{}_{object}", self.node),
                "state_topic": self.topics.occupancy(),
                "value_template": format!("{{{{ value_json.{counts}[{key}] | default(0) }}}}"),
                "unit_of_measurement": "devices",
                "state_class": "measurement",
                "icon": "mdi:account-group",
                "availability": self.availability(),
                "device": self.gateway_device(),
            }),
        )
    }

    /// The config topics of the occupancy sensors, places' and floors': an
    /// empty retained message on one removes its sensor.
    pub(crate) fn sensor_config_topics(&self) -> impl Iterator<Item = String> + '_ {
        self.places
            .iter()
            .chain(&self.floors)
            .map(|(_, object)| self.config_topic("sensor", object))
    }

    /// The config topic of `place`'s occupancy sensor (`None` for a name the
    /// site does not have).
    #[cfg(test)]
    fn occupancy_config_topic(&self, place: &str) -> Option<String> {
        self.places
            .iter()
            .find(|(name, _)| name == place)
            .map(|(_, object)| self.config_topic("sensor", object))
    }

    /// The config topic of `device`'s tracker: an empty retained message there
    /// removes the tracker from Home Assistant and the broker.
    pub(crate) fn tracker_config_topic(&self, device: &str) -> String {
        self.config_topic("device_tracker", &device_object_id(device))
    }

    /// A tracker for one device, sent once per device the gateway locates.
    pub(crate) fn device_tracker(&self, device: &str) -> Message {
        let object = device_object_id(device);
        self.config(
            "device_tracker",
            &object,
            json!({
                // No entity name of its own: the tracker is the device, and
                // Home Assistant names it after the device (an entity name
                // equal to the device name draws a warning and is replaced).
                "name": null,
                "unique_id": format!("gangway_{}_{object}", self.node),
                "state_topic": self.topics.presence(device),
                "json_attributes_topic": self.topics.location(device),
                "json_attributes_template": TRACKER_ATTRIBUTES,
                "source_type": "bluetooth_le",
                "availability": self.availability(),
                "device": {
                    "identifiers": [format!("gangway_{}_{object}", self.node)],
                    "name": device,
                    "via_device": format!("gangway_{}", self.node),
                },
            }),
        )
    }

    /// The tracker state a location sets, as `(topic, payload)`: the named
    /// place, [`HOME`] in the building at no named place, or [`NOT_HOME`]
    /// when the location is unknown (no cell).
    pub(crate) fn presence(&self, location: &Location) -> (String, String) {
        let floor = location
            .floor
            .as_ref()
            .map(|f| f.name.as_str())
            .filter(|_| !self.floors.is_empty());
        let state = match (location.cell, &location.place) {
            (None, _) => NOT_HOME.to_owned(),
            (Some(_), Some(place)) => place_key(floor, place),
            (Some(_), None) => HOME.to_owned(),
        };
        (self.topics.presence(&location.device), state)
    }
}

/// Home Assistant object ids allow `[a-zA-Z0-9_-]`; anything else becomes `_`.
fn object_id(id: &str) -> String {
    id.chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || c == '-' || c == '_' {
                c
            } else {
                '_'
            }
        })
        .collect()
}

/// A device's object id, one-to-one: letters, digits and `-` stay, every
/// other byte (`_` included) becomes `_` and two hex digits, so `alice.phone`,
/// `alice:phone` and `alice_phone` are three trackers, never one. Device ids
/// come from the air and the broker, so two of them must never share a
/// tracker (gateway and place ids come from the config and keep
/// [`object_id`]).
fn device_object_id(id: &str) -> String {
    use std::fmt::Write;
    let mut out = String::with_capacity(id.len());
    for byte in id.bytes() {
        if byte.is_ascii_alphanumeric() || byte == b'-' {
            out.push(char::from(byte));
        } else {
            let _ = write!(out, "_{byte:02x}");
        }
    }
    out
}

/// Each of `names` with its object id `<kind>_<name>`, made unique among
/// them: names that map to the same object id (`a b`, `a_b`) each get a
/// short hash of their own name.
fn with_object_ids(kind: &str, names: Vec<String>) -> Vec<(String, String)> {
    use sha2::Digest;
    let ids: Vec<String> = names.iter().map(|n| object_id(n)).collect();
    names
        .into_iter()
        .zip(&ids)
        .map(|(name, id)| {
            let object = if ids.iter().filter(|&other| other == id).count() == 1 {
                format!("{kind}_{id}")
            } else {
                let hash = sha2::Sha256::digest(name.as_bytes());
                format!(
                    "{kind}_{id}_{:02x}{:02x}{:02x}{:02x}",
                    hash[0], hash[1], hash[2], hash[3]
                )
            };
            (name, object)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::site::Cell;

    fn discovery() -> Discovery {
        Discovery::new(
            "homeassistant",
            "gw.1",
            Topics::new("gangway/gw.1"),
            vec!["help desk".into(), "north stacks".into()],
            Vec::new(),
        )
    }

    #[test]
    fn a_tracker_reads_its_state_from_presence_and_attributes_from_the_location_topic() {
        let d = discovery();
        let m = d.device_tracker("phone 7");
        assert_eq!(
            m.topic,
            "homeassistant/device_tracker/gw_1/phone_207/config"
        );
        assert_eq!(m.topic, d.tracker_config_topic("phone 7"));
        assert!(m.retain);
        assert_eq!(
            m.value()["state_topic"],
            "gangway/gw.1/devices/phone 7/presence"
        );
        assert!(m.value().get("value_template").is_none());
        assert_eq!(
            m.value()["json_attributes_topic"],
            "gangway/gw.1/devices/phone 7/location"
        );
        assert!(m.value()["name"].is_null());
        assert_eq!(m.value()["device"]["name"], "phone 7");
        assert_eq!(m.value()["availability"][0]["topic"], "gangway/gw.1/status");
    }

    fn location(place: Option<&str>, cell: Option<Cell>) -> Location {
        crate::test_support::location("phone 7", 1.0, cell, place)
    }

    #[test]
    fn presence_is_the_place_home_between_places_and_not_home_when_unknown() {
        let d = discovery();
        let topic = "gangway/gw.1/devices/phone 7/presence".to_owned();
        let at = |place, cell| d.presence(&location(place, cell));
        assert_eq!(
            at(Some("help desk"), Some(Cell::new(9, 9))),
            (topic.clone(), "help desk".into())
        );
        assert_eq!(
            at(None, Some(Cell::new(3, 4))),
            (topic.clone(), HOME.into())
        );
        assert_eq!(at(None, None), (topic, NOT_HOME.into()));
    }

    #[test]
    fn the_gateway_has_a_status_one_sensor_per_stat_and_one_per_place() {
        let d = discovery();
        let configs = d.gateway();
        assert_eq!(configs.len(), 1 + COUNTERS.len() + GAUGES.len() + 2);
        assert!(
            configs
                .iter()
                .all(|m| m.topic.starts_with("homeassistant/"))
        );
        let desk = configs
            .iter()
            .find(|m| Some(&m.topic) == d.occupancy_config_topic("help desk").as_ref())
            .expect("a help desk occupancy sensor");
        assert_eq!(
            desk.topic,
            "homeassistant/sensor/gw_1/occupancy_help_desk/config"
        );
        assert_eq!(desk.value()["state_topic"], "gangway/gw.1/occupancy");
        assert_eq!(
            desk.value()["value_template"],
            "{{ value_json.places[\"help desk\"] | default(0) }}"
        );
        assert_eq!(d.occupancy_config_topic("moon"), None);
    }

    #[test]
    fn devices_whose_ids_differ_get_distinct_trackers() {
        let d = discovery();
        let ids = [
            "alice.phone",
            "alice:phone",
            "alice_phone",
            "alice_2ephone",
            "alice phone",
        ];
        let topics: std::collections::BTreeSet<String> =
            ids.iter().map(|id| d.tracker_config_topic(id)).collect();
        assert_eq!(topics.len(), ids.len(), "{topics:?}");
        let unique_ids: std::collections::BTreeSet<String> = ids
            .iter()
            .map(|id| d.device_tracker(id).value()["unique_id"].to_string())
            .collect();
        assert_eq!(unique_ids.len(), ids.len(), "{unique_ids:?}");
        // Ids made of letters, digits and dashes (tags, walkers) keep theirs.
        assert!(
            d.tracker_config_topic("0f0e0d0c-0b0a-4908-8706-050403020100-7-1")
                .contains("/0f0e0d0c-0b0a-4908-8706-050403020100-7-1/")
        );
    }

    #[test]
    fn places_with_the_same_object_id_get_distinct_sensors() {
        let names = ["a b", "a_b", "c"].map(String::from).to_vec();
        let d = Discovery::new("ha", "gw", Topics::new("gangway/gw"), names, Vec::new());
        let topics: Vec<_> = ["a b", "a_b", "c"]
            .iter()
            .map(|p| d.occupancy_config_topic(p).unwrap())
            .collect();
        assert_ne!(topics[0], topics[1]);
        assert!(topics[0].starts_with("ha/sensor/gw/occupancy_a_b_"));
        assert_eq!(topics[2], "ha/sensor/gw/occupancy_c/config");
    }

    #[test]
    fn a_building_has_a_sensor_per_floor_and_places_named_with_their_floor() {
        let d = Discovery::new(
            "ha",
            "gw",
            Topics::new("gangway/gw"),
            vec!["B1/Store".into(), "G/Store".into()],
            vec!["B1".into(), "G".into()],
        );
        let configs = d.gateway();
        let b1 = configs
            .iter()
            .find(|m| m.topic == "ha/sensor/gw/floor_B1/config")
            .expect("a sensor for B1");
        assert_eq!(b1.value()["name"], "Devices on B1");
        assert_eq!(
            b1.value()["value_template"],
            "{{ value_json.floors[\"B1\"] | default(0) }}"
        );
        assert_eq!(d.sensor_config_topics().count(), 4);
        let mut at = crate::test_support::location("p", 1.0, Some(Cell::new(1, 1)), Some("Store"));
        at.floor = Some(crate::publish::FloorName {
            name: "G".into(),
            level: 0,
        });
        assert_eq!(d.presence(&at).1, "G/Store");
    }
}
