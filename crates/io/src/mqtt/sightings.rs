//! Shared sightings: the gateways of one site publish what they hear on
//! `<site prefix>/sightings/<gateway>` and localize tags from everyone's
//! sightings together (with `[window] orientation = "advertiser"`, the
//! gateways are the anchors). Payload schema: docs/schemas/sightings.schema.json.

use std::sync::Arc;

use serde::{Deserialize, Serialize};
use uuid::Uuid;

use crate::sighting::{BeaconId, Sighting};
use crate::topics::Message;

pub(crate) const SIGHTINGS_SCHEMA: &str = "gangway.sightings/1";

/// Sightings in one message at most: about 100 bytes each, so a message
/// stays under the receiving gateways' default `[mqtt] max_payload_bytes`
/// (16 KiB), past which they would refuse it.
pub const MAX_PER_MESSAGE: usize = 128;

/// One sighting as sent between gateways (the observer is the sending gateway).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub(crate) struct SharedSighting {
    pub t: f64,
    pub uuid: Uuid,
    pub major: u16,
    pub minor: u16,
    pub rssi: i16,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tx_power: Option<i8>,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Batch {
    schema: String,
    gateway: String,
    sightings: Vec<SharedSighting>,
}

/// The topic a gateway publishes its sightings on.
pub(crate) fn topic(site_prefix: &str, gateway: &str) -> String {
    format!("{site_prefix}/sightings/{gateway}")
}

/// A batch of this gateway's own sightings.
pub fn encode(site_prefix: &str, gateway: &str, sightings: &[Sighting]) -> Message {
    encode_to(topic(site_prefix, gateway), gateway, sightings)
}

/// A batch of this gateway's own sightings, on `topic`.
pub(crate) fn encode_to<'a>(
    topic: String,
    gateway: &str,
    sightings: impl IntoIterator<Item = &'a Sighting>,
) -> Message {
    let batch = Batch {
        schema: SIGHTINGS_SCHEMA.into(),
        gateway: gateway.into(),
        sightings: sightings
            .into_iter()
            .map(|s| SharedSighting {
                t: s.t,
                uuid: s.advertiser.uuid,
                major: s.advertiser.major,
                minor: s.advertiser.minor,
                rssi: s.rssi,
                tx_power: s.tx_power,
            })
            .collect(),
    };
    Message::json(topic, &batch, false)
}

/// Reads another gateway's batch; `gateway` is the topic's last level and must
/// match the payload's.
pub(crate) fn decode(gateway: &str, payload: &[u8]) -> Result<Vec<Sighting>, String> {
    let batch: Batch = serde_json::from_slice(payload).map_err(|e| e.to_string())?;
    if batch.schema != SIGHTINGS_SCHEMA {
        return Err(format!(
            "schema {:?} is not {SIGHTINGS_SCHEMA:?}",
            batch.schema
        ));
    }
    if batch.gateway != gateway {
        return Err(format!(
            "payload gateway {:?} differs from the topic's {gateway:?}",
            batch.gateway
        ));
    }
    let observer: Arc<str> = gateway.into();
    batch
        .sightings
        .into_iter()
        .map(|s| {
            if !s.t.is_finite() {
                return Err("`t` must be a finite number of seconds".to_owned());
            }
            Ok(Sighting {
                advertiser_mac: None,
                t: s.t,
                observer: observer.clone(),
                advertiser: BeaconId {
                    uuid: s.uuid,
                    major: s.major,
                    minor: s.minor,
                },
                tx_power: s.tx_power,
                rssi: s.rssi,
            })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_batch_round_trips_and_names_its_gateway() {
        let s = Sighting {
            advertiser_mac: None,
            t: 12.5,
            observer: "gw-a".into(),
            advertiser: BeaconId {
                uuid: Uuid::nil(),
                major: 1,
                minor: 7,
            },
            tx_power: Some(-59),
            rssi: -70,
        };
        let m = encode("gangway/sites/x", "gw-a", std::slice::from_ref(&s));
        assert_eq!(m.topic, "gangway/sites/x/sightings/gw-a");
        let bytes = m.payload.clone();
        assert_eq!(decode("gw-a", &bytes).unwrap(), vec![s]);
        let err = decode("gw-b", &bytes).unwrap_err();
        assert!(err.contains("differs"), "{err}");
    }
}
