//! `[cluster]`: many gateways of one site on one (clustered) broker, each
//! device located once. A gateway is an **edge** (its radio's sightings go
//! out, batched, on the topic of each tag's shard; it locates nothing), a
//! **locator** (it subscribes to the shards it owns, locates their devices
//! and publishes under the site's prefix) or, the default, **single**: the
//! one box that does both, as before `[cluster]` existed.
//!
//! Topics, under the site prefix (see docs/scaling.md):
//! - `shards/<k>/sightings/<edge>`: an edge's sightings of the tags of
//!   shard `k` (`gangway_core::cluster::shard_of` of the tag's id); the
//!   payload is the shared-sightings batch (`mqtt::sightings`);
//! - `locators/<locator>`: a locator's heartbeat (schema
//!   `gangway.locator/1`, docs/schemas/locator.schema.json), which the
//!   others' `Membership` reads;
//! - `devices/<device>/…`: what locators publish and take about a device
//!   (location, path, guidance; route requests, cancels, feedback), so a
//!   client never needs to know which locator holds its device.
//!
//! Why shard topics rather than one topic per edge: a locator subscribes
//! only to its shards, so the broker sends each sighting to one locator,
//! not to all of them.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::cluster::{Beat, BeatState, shard_of};
use crate::sighting::Sighting;
use crate::topics::Message;

pub(crate) const LOCATOR_SCHEMA: &str = "gangway.locator/1";

/// Largest `[cluster] shards`: a locator subscribes to a topic per shard it
/// owns, and a thousand shards is already more locators than a site needs.
const MAX_SHARDS: u16 = 1024;

/// What a gateway does in a site with several.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Role {
    /// Radio in, locations out: one box does it all.
    #[default]
    Single,
    /// Radio in, sightings out by shard; locates nothing.
    Edge,
    /// Sightings of its shards in; locations, routes and guidance out.
    Locator,
}

/// `[cluster]` in the gateway config.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ClusterConfig {
    pub role: Role,
    /// Shards the site's devices are cut into: the most locators that can
    /// share the work. The same on every edge and locator of a site. An
    /// edge sends a message per shard it heard a tag of, so fewer shards
    /// also means fuller messages: 16 keeps a site of 50 edges near two
    /// sightings a message at 1,000 tags (examples/cluster.rs).
    pub shards: u16,
    /// Seconds between a locator's heartbeats.
    pub heartbeat_s: f64,
    /// A locator not heard for this long is gone and its shards are taken
    /// over: what a locator that dies costs its devices, beside a window.
    pub lease_s: f64,
    /// Seconds an edge gathers its sightings before it sends them, one
    /// message per shard: longer means fuller messages (fewer of them on
    /// the broker) and fixes that much later.
    pub batch_s: f64,
}

impl Default for ClusterConfig {
    fn default() -> Self {
        ClusterConfig {
            role: Role::Single,
            shards: 16,
            heartbeat_s: 1.0,
            lease_s: 3.0,
            batch_s: 1.0,
        }
    }
}

impl ClusterConfig {
    pub(crate) fn validate(&self) -> Result<(), String> {
        if !(1..=MAX_SHARDS).contains(&self.shards) {
            return Err(format!(
                "[cluster] shards = {} must be 1 to {MAX_SHARDS}",
                self.shards
            ));
        }
        if !(self.heartbeat_s.is_finite() && self.heartbeat_s > 0.0) {
            return Err("[cluster] heartbeat_s must be a positive number of seconds".into());
        }
        if !(self.batch_s.is_finite() && self.batch_s > 0.0 && self.batch_s <= 2.0) {
            return Err(format!(
                "[cluster] batch_s = {} must be more than 0 and at most 2 seconds \
                 (a fix waits for it)",
                self.batch_s
            ));
        }
        // Two heartbeats can be lost (or late) before a live locator loses
        // its shards.
        if !(self.lease_s.is_finite() && self.lease_s >= 2.0 * self.heartbeat_s) {
            return Err(format!(
                "[cluster] lease_s = {} must be at least twice heartbeat_s = {}",
                self.lease_s, self.heartbeat_s
            ));
        }
        Ok(())
    }
}

/// The topic of an edge's sightings of one shard's tags.
pub(crate) fn shard_topic(site_prefix: &str, shard: u16, edge: &str) -> String {
    format!("{site_prefix}/shards/{shard}/sightings/{edge}")
}

/// The topic of a locator's heartbeats.
pub(crate) fn locator_topic(site_prefix: &str, locator: &str) -> String {
    format!("{site_prefix}/locators/{locator}")
}

/// An edge's sightings as one batch per shard of the tags heard (in shard
/// order, each batch in the order heard).
pub fn encode_by_shard(
    site_prefix: &str,
    edge: &str,
    shards: u16,
    sightings: &[Sighting],
) -> Vec<Message> {
    let mut by_shard: BTreeMap<u16, Vec<&Sighting>> = BTreeMap::new();
    for s in sightings {
        let shard = shard_of(&s.advertiser.device_id(), shards);
        by_shard.entry(shard).or_default().push(s);
    }
    by_shard
        .into_iter()
        .flat_map(|(shard, batch)| {
            batch
                .chunks(super::sightings::MAX_PER_MESSAGE)
                .map(|chunk| {
                    let topic = shard_topic(site_prefix, shard, edge);
                    super::sightings::encode_to(topic, edge, chunk.iter().copied())
                })
                .collect::<Vec<_>>()
        })
        .collect()
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct BeatPayload {
    schema: String,
    locator: String,
    state: String,
    shards: u16,
    owned: Vec<u16>,
    t: f64,
}

/// A locator's heartbeat as a message (not retained: a heartbeat says the
/// locator is alive now, which a stored one cannot).
pub(crate) fn encode_beat(site_prefix: &str, beat: &Beat) -> Message {
    let payload = BeatPayload {
        schema: LOCATOR_SCHEMA.into(),
        locator: beat.locator.clone(),
        state: beat.state.as_str().into(),
        shards: beat.shards,
        owned: beat.owned.clone(),
        t: beat.t,
    };
    Message::json(locator_topic(site_prefix, &beat.locator), &payload, false)
}

/// Reads a heartbeat; `locator` is the topic's last level and must match
/// the payload's.
pub(crate) fn decode_beat(locator: &str, payload: &[u8]) -> Result<Beat, String> {
    let p: BeatPayload = serde_json::from_slice(payload).map_err(|e| e.to_string())?;
    if p.schema != LOCATOR_SCHEMA {
        return Err(format!("schema {:?} is not {LOCATOR_SCHEMA:?}", p.schema));
    }
    if p.locator != locator {
        return Err(format!(
            "payload locator {:?} differs from the topic's {locator:?}",
            p.locator
        ));
    }
    let state = BeatState::parse(&p.state)
        .ok_or_else(|| format!("state {:?} is not joining, serving or leaving", p.state))?;
    if !(1..=MAX_SHARDS).contains(&p.shards) || p.owned.iter().any(|&s| s >= p.shards) {
        return Err(format!(
            "shards {} (or an owned shard past it) is out of range",
            p.shards
        ));
    }
    Ok(Beat {
        locator: p.locator,
        state,
        shards: p.shards,
        owned: p.owned,
        t: p.t,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_heartbeat_round_trips_and_bad_ones_say_why() {
        let beat = Beat {
            locator: "loc-a".into(),
            state: BeatState::Serving,
            shards: 8,
            owned: vec![1, 5],
            t: 12.0,
        };
        let m = encode_beat("gangway/sites/x", &beat);
        assert_eq!(m.topic, "gangway/sites/x/locators/loc-a");
        assert!(!m.retain);
        assert_eq!(decode_beat("loc-a", &m.payload).unwrap(), beat);
        assert!(
            decode_beat("loc-b", &m.payload)
                .unwrap_err()
                .contains("differs")
        );
        let forged = String::from_utf8(m.payload)
            .unwrap()
            .replace("[1,5]", "[1,9]");
        assert!(
            decode_beat("loc-a", forged.as_bytes())
                .unwrap_err()
                .contains("out of range")
        );
    }

    #[test]
    fn an_edge_cuts_its_sightings_by_shard_into_messages_a_gateway_takes() {
        let tag = |minor| crate::sighting::BeaconId {
            uuid: uuid::Uuid::nil(),
            major: 1,
            minor,
        };
        let sighting = |minor, t| Sighting {
            advertiser_mac: None,
            t,
            observer: "edge-1".into(),
            advertiser: tag(minor),
            tx_power: None,
            rssi: -70,
        };
        let mut heard: Vec<Sighting> = (0..300).map(|i| sighting(1, f64::from(i))).collect();
        heard.push(sighting(2, 0.0));
        let messages = encode_by_shard("s", "edge-1", 64, &heard);
        let shard = |minor| shard_of(&tag(minor).device_id(), 64);
        let on = |minor| shard_topic("s", shard(minor), "edge-1");
        assert_eq!(messages.iter().filter(|m| m.topic == on(1)).count(), 3);
        assert!(messages.iter().any(|m| m.topic == on(2)));
        for m in &messages {
            let batch = super::super::sightings::decode("edge-1", &m.payload).unwrap();
            assert!(batch.len() <= super::super::sightings::MAX_PER_MESSAGE);
            assert!(m.payload.len() < 16 * 1024, "{} bytes", m.payload.len());
        }
    }

    #[test]
    fn a_lease_shorter_than_two_heartbeats_is_refused() {
        let mut c = ClusterConfig::default();
        assert!(c.validate().is_ok());
        c.lease_s = 1.5;
        assert!(c.validate().unwrap_err().contains("lease_s"));
        c = ClusterConfig {
            shards: 0,
            ..ClusterConfig::default()
        };
        assert!(c.validate().unwrap_err().contains("shards"));
    }
}
