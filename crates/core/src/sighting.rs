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

/// A Bluetooth device address (the advertiser's MAC), written
/// `AA:BB:CC:DD:EE:FF`. Part of a beacon's identity where several
/// transmitters share one UUID/major/minor and differ only by address.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub struct Mac(pub [u8; 6]);

impl fmt::Display for Mac {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let [a, b, c, d, e, g] = self.0;
        write!(f, "{a:02X}:{b:02X}:{c:02X}:{d:02X}:{e:02X}:{g:02X}")
    }
}

impl std::str::FromStr for Mac {
    type Err = String;

    /// Six hexadecimal bytes separated by `:` (or `-`), in either case.
    fn from_str(text: &str) -> Result<Self, String> {
        let bad = || format!("`{text}` is not a MAC address (six hex bytes: AA:BB:CC:DD:EE:FF)");
        let mut bytes = [0u8; 6];
        let mut parts = text.split([':', '-']);
        for byte in &mut bytes {
            let part = parts.next().ok_or_else(bad)?;
            if part.len() != 2 {
                return Err(bad());
            }
            *byte = u8::from_str_radix(part, 16).map_err(|_| bad())?;
        }
        if parts.next().is_some() {
            return Err(bad());
        }
        Ok(Mac(bytes))
    }
}

impl Serialize for Mac {
    fn serialize<S: serde::Serializer>(&self, serializer: S) -> Result<S::Ok, S::Error> {
        serializer.collect_str(self)
    }
}

impl<'de> Deserialize<'de> for Mac {
    fn deserialize<D: serde::Deserializer<'de>>(deserializer: D) -> Result<Self, D::Error> {
        let text = String::deserialize(deserializer)?;
        text.parse().map_err(serde::de::Error::custom)
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
    /// The advertiser's address, when the source knows it (the radio, a
    /// capture or phone scan that gives it); what tells apart beacons that
    /// share one UUID/major/minor.
    pub advertiser_mac: Option<Mac>,
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
    fn macs_read_back_as_written_and_bad_ones_are_named() {
        let mac: Mac = "e0:78:a3:3d:b5:d6".parse().unwrap();
        assert_eq!(mac, Mac([0xE0, 0x78, 0xA3, 0x3D, 0xB5, 0xD6]));
        assert_eq!(mac.to_string(), "E0:78:A3:3D:B5:D6");
        assert_eq!("E0-78-A3-3D-B5-D6".parse::<Mac>(), Ok(mac));
        for bad in [
            "",
            "E0:78:A3:3D:B5",
            "E0:78:A3:3D:B5:D6:00",
            "E0:78:A3:3D:B5:G6",
            "E078:A3:3D:B5:D6:0",
        ] {
            let err = bad.parse::<Mac>().unwrap_err();
            assert!(err.contains("is not a MAC address"), "{bad:?}: {err}");
        }
    }

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
