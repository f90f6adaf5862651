//! The BLE receivers people already own, read from the broker the gateway
//! uses: ESPresense room nodes (ESP32) and Theengs Gateway or
//! OpenMQTTGateway. Each is a fixed receiver hearing tags, so each message
//! about an iBeacon becomes one sighting with the receiver as observer, the
//! way another gangway gateway's shared sightings are (advertiser
//! orientation). The site places each receiver as a `[[gateway]]` whose id
//! is the receiver's name: the ESPresense room, or the Theengs gateway's
//! name in its topic. Mixed deployments (gangway boxes beside ESP32 nodes)
//! are one site whose gateways are all of them.
//!
//! Payloads, as the projects publish them (`docs/receivers.md` cites where
//! each shape comes from):
//! - ESPresense: `<topic>/devices/<device id>/<room>`, `{"id", "rssi",
//!   "rssi@1m", "distance", …}`; an iBeacon's id is
//!   `iBeacon:<uuid>-<major>-<minor>`. Other devices (phones by IRK, Apple,
//!   Microsoft, Eddystone ids) are not iBeacons and are passed over.
//! - Theengs Gateway / OpenMQTTGateway: `<topic>/<gateway>/BTtoMQTT/<MAC>`,
//!   the Theengs decoder's JSON: `{"id", "rssi", "model_id": "IBEACON",
//!   "uuid", "major", "minor", "txpower", …}`; every other BLE device on
//!   the same topic is passed over.
//!
//! Neither carries a time: a sighting is stamped when it arrives, as phone
//! scans are. Readings outside -127..=20 dBm, ids that are no iBeacon's and
//! payloads that are not such JSON are refused with the reason; the size
//! bound of every inbound message applies first.

use std::sync::Arc;

use serde::Deserialize;
use serde_json::Value;
use uuid::Uuid;

use crate::sighting::{BeaconId, Sighting};

/// `[mqtt.espresense]`: read ESPresense nodes.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct EspresenseConfig {
    /// The nodes' base topic (ESPresense's default `espresense`).
    pub topic: String,
}

impl Default for EspresenseConfig {
    fn default() -> Self {
        EspresenseConfig {
            topic: "espresense".into(),
        }
    }
}

/// `[mqtt.theengs]`: read Theengs Gateway or OpenMQTTGateway.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TheengsConfig {
    /// The base topic before `<gateway>/BTtoMQTT/<MAC>` (both projects'
    /// default `home`).
    pub topic: String,
}

impl Default for TheengsConfig {
    fn default() -> Self {
        TheengsConfig {
            topic: "home".into(),
        }
    }
}

/// The topic filters of the configured receivers.
pub(crate) fn subscriptions(
    espresense: Option<&EspresenseConfig>,
    theengs: Option<&TheengsConfig>,
) -> Vec<String> {
    let mut filters = Vec::new();
    if let Some(e) = espresense {
        filters.push(format!("{}/devices/+/+", e.topic));
    }
    if let Some(t) = theengs {
        filters.push(format!("{}/+/BTtoMQTT/+", t.topic));
    }
    filters
}

/// What a receiver's message says: a sighting, or nothing about an iBeacon.
pub(crate) type Read = Result<Option<Sighting>, String>;

/// An ESPresense message about `device`, heard in `room` at `now`.
pub(crate) fn espresense(room: &str, device: &str, payload: &[u8], now: f64) -> Read {
    let Some(beacon) = espresense_ibeacon(device) else {
        return Ok(None);
    };
    let beacon = beacon.ok_or_else(|| {
        format!("{device:?} is not an iBeacon id (`iBeacon:<uuid>-<major>-<minor>`)")
    })?;
    #[derive(Deserialize)]
    struct Message {
        rssi: f64,
        #[serde(rename = "rssi@1m", default)]
        rssi_at_1m: Option<f64>,
    }
    let message: Message = serde_json::from_slice(payload)
        .map_err(|e| format!("{e}; an ESPresense message is {{\"rssi\": dBm, …}}"))?;
    Ok(Some(sighting(
        room,
        beacon,
        message.rssi,
        message.rssi_at_1m,
        now,
    )?))
}

/// The beacon of an ESPresense device id: `None` when the id is not an
/// iBeacon's at all, `Some(None)` when it claims to be one but is malformed.
fn espresense_ibeacon(device: &str) -> Option<Option<BeaconId>> {
    let rest = device
        .get(..8)
        .filter(|p| p.eq_ignore_ascii_case("ibeacon:"))
        .map(|_| &device[8..])?;
    // `<uuid>-<major>-<minor>`, the UUID with or without its own dashes
    // (firmware versions differ), so major and minor are read from the right.
    let parsed = || {
        let mut parts = rest.rsplitn(3, '-');
        let minor = parts.next()?.parse().ok()?;
        let major = parts.next()?.parse().ok()?;
        let uuid = Uuid::parse_str(parts.next()?).ok()?;
        Some(BeaconId { uuid, major, minor })
    };
    Some(parsed())
}

/// A Theengs Gateway or OpenMQTTGateway message heard by `gateway` at `now`.
pub(crate) fn theengs(gateway: &str, payload: &[u8], now: f64) -> Read {
    let message: Value = serde_json::from_slice(payload)
        .map_err(|e| format!("{e}; a BTtoMQTT message is the Theengs decoder's JSON object"))?;
    let field = |key: &str| message.get(key);
    let is_ibeacon = field("model_id").and_then(Value::as_str) == Some("IBEACON");
    if !is_ibeacon {
        return Ok(None);
    }
    let text = |key: &str| -> Result<&str, String> {
        field(key)
            .and_then(Value::as_str)
            .ok_or_else(|| format!("an IBEACON message needs `{key}` as a string"))
    };
    // Numbers, or numbers written as strings (decoders differ).
    let number = |key: &str| -> Option<f64> {
        let value = field(key)?;
        value
            .as_f64()
            .or_else(|| value.as_str().and_then(|s| s.trim().parse().ok()))
    };
    let id_part = |key: &str| -> Result<u16, String> {
        number(key)
            .filter(|v| v.fract() == 0.0 && (0.0..=65535.0).contains(v))
            .map(|v| v as u16)
            .ok_or_else(|| format!("`{key}` must be a whole number 0..=65535"))
    };
    let uuid = Uuid::parse_str(text("uuid")?).map_err(|e| format!("`uuid`: {e}"))?;
    let beacon = BeaconId {
        uuid,
        major: id_part("major")?,
        minor: id_part("minor")?,
    };
    let rssi = number("rssi").ok_or("an IBEACON message needs `rssi`")?;
    // `txpower`; decoders before it named the same byte `power`.
    let at_1m = number("txpower").or_else(|| number("power"));
    Ok(Some(sighting(gateway, beacon, rssi, at_1m, now)?))
}

/// The sighting of `beacon` by `observer`; the reading must be one a radio
/// reports.
fn sighting(
    observer: &str,
    beacon: BeaconId,
    rssi: f64,
    at_1m: Option<f64>,
    now: f64,
) -> Result<Sighting, String> {
    const RSSI_DBM: std::ops::RangeInclusive<f64> = -127.0..=20.0;
    if !RSSI_DBM.contains(&rssi) {
        return Err(format!("rssi {rssi} is outside -127..=20 dBm"));
    }
    Ok(Sighting {
        advertiser_mac: None,
        t: now,
        observer: Arc::from(observer),
        advertiser: beacon,
        // A measured power is negative; some tags report a positive byte
        // there (ESPresense issue #1286), which means nothing usable.
        tx_power: at_1m
            .filter(|v| (-127.0..0.0).contains(v))
            .map(|v| v.round() as i8),
        rssi: rssi.round() as i16,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const UUID: &str = "e2c56db5-dffb-48d2-b060-d0f5a71096e0";

    #[test]
    fn an_espresense_ibeacon_message_is_a_sighting_by_its_room() {
        let device = format!("iBeacon:{UUID}-100-2");
        let payload = br#"{"id":"iBeacon:e2c56db5-dffb-48d2-b060-d0f5a71096e0-100-2","idType":1,"rssi@1m":-59,"rssi":-71.4,"raw":2.3,"distance":2.1,"var":0.03,"int":1030}"#;
        let s = espresense("kitchen", &device, payload, 5.0)
            .unwrap()
            .unwrap();
        assert_eq!(&*s.observer, "kitchen");
        assert_eq!(s.advertiser.uuid, Uuid::parse_str(UUID).unwrap());
        assert_eq!((s.advertiser.major, s.advertiser.minor), (100, 2));
        assert_eq!((s.rssi, s.tx_power, s.t), (-71, Some(-59), 5.0));
        // The UUID without its dashes, as some firmware versions write it.
        let undashed = format!("iBeacon:{}-100-2", UUID.replace('-', ""));
        let t = espresense("kitchen", &undashed, payload, 5.0)
            .unwrap()
            .unwrap();
        assert_eq!(t.advertiser, s.advertiser);
        // A positive "rssi@1m" is no measured power: the site's applies.
        let positive = br#"{"rssi@1m":12,"rssi":-70}"#;
        let p = espresense("kitchen", &device, positive, 5.0)
            .unwrap()
            .unwrap();
        assert_eq!((p.rssi, p.tx_power), (-70, None));
    }

    #[test]
    fn other_espresense_devices_are_passed_over_and_bad_ones_refused() {
        let payload = br#"{"id":"apple:1005:9-26","rssi":-60}"#;
        assert_eq!(
            espresense("kitchen", "apple:1005:9-26", payload, 0.0),
            Ok(None)
        );
        assert_eq!(espresense("kitchen", "irk:0123", payload, 0.0), Ok(None));
        let err = espresense("kitchen", "iBeacon:not-a-uuid-1-2", payload, 0.0).unwrap_err();
        assert!(err.contains("not an iBeacon id"), "{err}");
        let device = format!("iBeacon:{UUID}-1-2");
        let err = espresense("kitchen", &device, b"{\"rssi\": 400}", 0.0).unwrap_err();
        assert!(err.contains("outside -127..=20"), "{err}");
        let err = espresense("kitchen", &device, b"[]", 0.0).unwrap_err();
        assert!(err.contains("ESPresense message"), "{err}");
    }

    #[test]
    fn a_theengs_ibeacon_message_is_a_sighting_by_its_gateway() {
        // OpenMQTTGateway's documented iBeacon message: the UUID as 32 hex
        // digits, no dashes.
        let payload = br#"{"id":"60:87:57:4C:9B:C2","mac_type":1,"rssi":-68,"distance":7.85288,"brand":"GENERIC","model":"iBeacon","model_id":"IBEACON","mfid":"4c00","uuid":"e2c56db5dffb48d2b060d0f5a71096e0","major":100,"minor":3,"txpower":-59}"#;
        let s = theengs("TheengsGateway", payload, 7.0).unwrap().unwrap();
        assert_eq!(&*s.observer, "TheengsGateway");
        assert_eq!((s.advertiser.major, s.advertiser.minor), (100, 3));
        assert_eq!((s.rssi, s.tx_power), (-68, Some(-59)));
        // Major and minor as strings, as some decoders write them.
        let strings = br#"{"rssi":-70,"model_id":"IBEACON","uuid":"e2c56db5-dffb-48d2-b060-d0f5a71096e0","major":"100","minor":"4","power":-61}"#;
        let s = theengs("omg", strings, 7.0).unwrap().unwrap();
        assert_eq!((s.advertiser.minor, s.tx_power), (4, Some(-61)));
    }

    #[test]
    fn other_theengs_devices_are_passed_over_and_bad_ones_refused() {
        let thermometer =
            br#"{"id":"A4:C1:38:00:00:01","rssi":-80,"model_id":"LYWSD03MMC_ATC","tempc":21.5}"#;
        assert_eq!(theengs("gw", thermometer, 0.0), Ok(None));
        let no_minor = br#"{"rssi":-70,"model_id":"IBEACON","uuid":"e2c56db5-dffb-48d2-b060-d0f5a71096e0","major":1}"#;
        assert!(
            theengs("gw", no_minor, 0.0)
                .unwrap_err()
                .contains("`minor`")
        );
        let huge = br#"{"rssi":-70,"model_id":"IBEACON","uuid":"e2c56db5-dffb-48d2-b060-d0f5a71096e0","major":1,"minor":70000}"#;
        assert!(theengs("gw", huge, 0.0).unwrap_err().contains("0..=65535"));
        assert!(theengs("gw", b"not json", 0.0).is_err());
    }
}
