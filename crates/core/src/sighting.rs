//! What every source produces and every later stage consumes: one radio sighting.
//!
//! A sighting is "observer `o` heard advertiser `a` at `rssi` dBm at time `t`".
//! It is deliberately orientation-free: when a phone or robot localizes itself the
//! observer is the entity and the beacons are the anchors; when a fleet of gateways
//! localizes tags, the advertiser is the entity and the gateways are the anchors.
//! The fingerprint windows (`locate::window`) pick the orientation, not the sources.

pub mod heard;

use std::fmt;
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use uuid::Uuid;

/// An iBeacon's identity: proximity UUID plus major and minor.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct BeaconId {
    pub uuid: Uuid,
    pub major: u16,
    pub minor: u16,
}

impl BeaconId {
    /// The id a tag is located and published under when fixed receivers
    /// hear it (`[window] orientation = "advertiser"`): `uuid-major-minor`,
    /// a single topic level.
    pub fn device_id(&self) -> String {
        format!("{}-{}-{}", self.uuid, self.major, self.minor)
    }
}

impl fmt::Display for BeaconId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}/{}/{}", self.uuid, self.major, self.minor)
    }
}

/// One advert heard by one observer.
#[derive(Clone, Debug, PartialEq)]
pub struct Sighting {
    /// Seconds since the Unix epoch (or since the start of a simulated log).
    pub t: f64,
    /// Who heard it: a gateway id, or the id of the phone/robot that scanned.
    /// Shared because one observer produces many sightings.
    pub observer: Arc<str>,
    /// Who was heard.
    pub advertiser: BeaconId,
    /// The beacon's calibrated RSSI at 1 m ("measured power"), when it sent one.
    pub tx_power: Option<i8>,
    /// Received signal strength in dBm.
    pub rssi: i16,
}

/// Whether a device id (an observer, a tag, a phone) can stand as one MQTT
/// topic level: non-empty, at most 128 bytes, and free of `+`, `#`, `/` and
/// control characters. Checked where ids come in (logs, the broker, the
/// config), so no later stage meets one that cannot be published.
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
}
