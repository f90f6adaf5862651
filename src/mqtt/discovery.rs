//! Home Assistant MQTT discovery: retained config messages under
//! `<discovery prefix>/<component>/<node>/<object>/config` that make Home
//! Assistant create a `device_tracker` per tracked device (attributes x, y,
//! place, confidence) and, for the gateway, a connectivity sensor and one
//! sensor per counter of `<prefix>/stats`.

use serde_json::json;

use super::stats::{COUNTERS, GAUGES};
use crate::publish::{Message, Topics};

/// Builds discovery messages for one gateway.
pub struct Discovery {
    prefix: String,
    gateway_id: String,
    node: String,
    topics: Topics,
}

impl Discovery {
    pub fn new(discovery_prefix: &str, gateway_id: &str, topics: Topics) -> Self {
        Discovery {
            prefix: discovery_prefix.to_owned(),
            gateway_id: gateway_id.to_owned(),
            node: object_id(gateway_id),
            topics,
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

    fn config(&self, component: &str, object: &str, payload: serde_json::Value) -> Message {
        Message {
            topic: format!("{}/{component}/{}/{object}/config", self.prefix, self.node),
            payload,
            retain: true,
        }
    }

    /// The gateway's own entities: connectivity and counters.
    pub fn gateway(&self) -> Vec<Message> {
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
        out
    }

    /// A tracker for one device, sent once per device the gateway locates.
    pub fn device_tracker(&self, device: &str) -> Message {
        let object = object_id(device);
        self.config(
            "device_tracker",
            &object,
            json!({
                "name": device,
                "unique_id": format!("gangway_{}_{object}", self.node),
                "state_topic": self.topics.location(device),
                // Home Assistant reads any state other than home/not_home as
                // a location name: the place, or `home` between places.
                "value_template": "{{ value_json.place | default('home', true) }}",
                "json_attributes_topic": self.topics.location(device),
                "json_attributes_template":
                    "{{ {'x': value_json.x_m, 'y': value_json.y_m, 'place': value_json.place, \
                     'confidence': value_json.confidence, 'cell': value_json.cell} | tojson }}",
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_tracker_reads_its_state_and_attributes_from_the_location_topic() {
        let d = Discovery::new("homeassistant", "gw.1", Topics::new("gangway/gw.1"));
        let m = d.device_tracker("phone 7");
        assert_eq!(m.topic, "homeassistant/device_tracker/gw_1/phone_7/config");
        assert!(m.retain);
        assert_eq!(
            m.payload["json_attributes_topic"],
            "gangway/gw.1/devices/phone 7/location"
        );
        assert_eq!(m.payload["availability"][0]["topic"], "gangway/gw.1/status");
    }

    #[test]
    fn the_gateway_has_a_status_and_one_sensor_per_stat() {
        let d = Discovery::new("ha", "gw", Topics::new("gangway/gw"));
        let configs = d.gateway();
        assert_eq!(configs.len(), 1 + COUNTERS.len() + GAUGES.len());
        assert!(configs.iter().all(|m| m.topic.starts_with("ha/")));
    }
}
