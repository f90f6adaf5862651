//! The broker as a sink: every output is published as [`Topics::encode`]
//! writes it, over the [`Link`] (which reconnects, queues while the broker is
//! away and redelivers). A gateway's sink also keeps Home Assistant informed
//! (a tracker announced before a device's first location, its presence
//! before each location, withdrawn when the device is forgotten, bounded like
//! the tracks by `[limits]`) and publishes the retained occupancy counts
//! whenever they change.
//!
//! Two uses: the daemon's ([`gateway`]), which never waits for the broker
//! (the offline queue keeps the newest messages while it is away, so the
//! gateway keeps locating), and a replay's ([`publisher`]), which waits for
//! room instead and so loses nothing however fast the log plays.

use std::sync::Arc;
use std::sync::atomic::Ordering;

use foldhash::HashMap;
use futures::future::BoxFuture;
use rumqttc::QoS;

use super::MqttConfig;
use super::cluster::{self, Role};
use super::discovery::Discovery;
use super::inbound::Inbox;
use super::occupancy::{Occupancy, places_and_floors};
use super::source::MqttSource;
use super::tracker_gate::{GateConfig, TrackerGate};
use super::{Link, LinkStats, MqttError, sightings};
use crate::locate::bounds::Bounds;
use crate::publish::Output;
use crate::publish::stats::Stats;
use crate::sink::Sink;
use crate::site::Building;
use crate::source::unix_now;
use crate::topics::{Message, Topics};

/// Publishes outputs to the broker.
pub struct MqttSink {
    link: Link,
    topics: Topics,
    /// The site's prefix and this gateway's id: where shared sightings go.
    site_prefix: String,
    gateway_id: String,
    /// Home Assistant discovery, when `[mqtt] ha_discovery`.
    discovery: Option<Discovery>,
    discovery_prefix: String,
    /// Devices with a published tracker config, with the time of their
    /// latest location.
    announced: HashMap<Arc<str>, f64>,
    announced_bounds: Bounds,
    /// Which of the others get a tracker, and when.
    gate: TrackerGate,
    /// Devices per named place (the gateway's sink only).
    occupancy: Option<Occupancy>,
    /// Wait for room rather than let the offline queue drop (a replay).
    lossless: bool,
    /// Messages to hand to the link at the next flush, in one batch.
    pending: Vec<Message>,
    /// Messages a newer one soon replaces (an edge's sightings, a locator's
    /// heartbeat): sent at QoS 0, so that no broker stores or redelivers
    /// them (NATS would write each QoS 1 one to its JetStream).
    pending_ephemeral: Vec<Message>,
    /// What this gateway does among the site's, and into how many shards
    /// the site's devices are cut (`[cluster]`).
    role: Role,
    shards: u16,
    /// The shards whose sightings a locator subscribes to now.
    subscribed_shards: Vec<u16>,
}

/// Who this gateway is on the broker, and what it keeps per device: what
/// the sink needs from the config file beyond `[mqtt]` (the config composes
/// it, `Config::broker_identity`, so this module never reads the whole file).
#[derive(Clone, Debug)]
pub struct Identity {
    pub gateway_id: String,
    pub client_id: String,
    /// This gateway's topics (`Topics::new`).
    pub topic_prefix: String,
    /// The topics the site's gateways share.
    pub site_prefix: String,
    /// The site's gateways exchange sightings (they are the anchors).
    pub shares_sightings: bool,
    /// Its part among the site's gateways, and the shards of the site's
    /// devices (`[cluster]`).
    pub role: Role,
    pub shards: u16,
    /// Devices announced to Home Assistant, bounded like the tracks
    /// (`[limits]`).
    pub max_devices: usize,
    pub device_idle_s: f64,
}

impl Identity {
    /// This gateway's topics: a locator's device topics are the site's.
    pub fn topics(&self) -> Topics {
        let topics = Topics::new(self.topic_prefix.clone());
        match self.role {
            Role::Locator => topics.with_devices_under(self.site_prefix.clone()),
            Role::Single | Role::Edge => topics,
        }
    }
}

/// The daemon's connection to `url`: a sink for everything it publishes
/// (with a retained `online`/`offline` status and Home Assistant discovery)
/// and a source of what it subscribes to (route requests, feedback, phone
/// scans, other gateways' sightings).
pub fn gateway(
    config: &MqttConfig,
    identity: &Identity,
    building: &Building,
    url: &str,
) -> anyhow::Result<(MqttSink, MqttSource)> {
    let topics = identity.topics();
    let site_prefix = identity.site_prefix.clone();
    anyhow::ensure!(
        super::config::valid_prefix(&site_prefix),
        "the site name {:?} cannot be part of a topic ({site_prefix:?}); set [mqtt] site_prefix",
        building.name
    );
    let inbox = Inbox::new(
        topics.clone(),
        site_prefix.clone(),
        identity.gateway_id.clone(),
        config.max_payload_bytes,
        identity.shares_sightings,
    )
    .with_role(identity.role)
    .with_receivers(config.espresense.clone(), config.theengs.clone())
    .with_max_clock_skew(config.max_clock_skew_s);
    let settings = super::link_settings(
        config,
        url,
        &identity.client_id,
        Some(topics.status()),
        inbox.subscriptions(),
        true,
    )?;
    let (link, inbound) = Link::start(settings);
    link.subscribe(inbox.stream_subscriptions(), QoS::AtMostOnce);
    let mut sink = MqttSink::new(config, identity, link, topics, false);
    // A locator knows only its own devices: a count per place, or a tracker
    // that moves between locators, would mislead (docs/scaling.md).
    if identity.role != Role::Locator {
        sink.occupancy = Some(occupancy(building));
        sink.publish_occupancy();
    }
    if config.ha_discovery {
        let discovery = sink.discovery_for(building);
        sink.link.set_birth(&discovery.gateway(), true);
        sink.discovery = Some(discovery);
    }
    Ok((sink, MqttSource::new(inbound, inbox)))
}

/// A replay's connection to `url`: publishes outputs and waits for the broker
/// rather than drop any; no status, no subscriptions, no discovery.
pub fn publisher(
    config: &MqttConfig,
    identity: &Identity,
    url: &str,
) -> Result<MqttSink, MqttError> {
    let client_id = format!("{}-replay", identity.client_id);
    // Nobody waits for a reply: let the kernel gather messages into packets.
    let settings = super::link_settings(config, url, &client_id, None, Vec::new(), false)?;
    let (link, _) = Link::start(settings);
    Ok(MqttSink::new(
        config,
        identity,
        link,
        identity.topics(),
        true,
    ))
}

/// Occupancy of the building's places and floors, everyone away.
fn occupancy(building: &Building) -> Occupancy {
    let (places, floors) = places_and_floors(building);
    Occupancy::new(places, floors)
}

impl MqttSink {
    fn new(
        config: &MqttConfig,
        identity: &Identity,
        link: Link,
        topics: Topics,
        lossless: bool,
    ) -> MqttSink {
        MqttSink {
            link,
            topics,
            site_prefix: identity.site_prefix.clone(),
            gateway_id: identity.gateway_id.clone(),
            discovery: None,
            discovery_prefix: config.discovery_prefix.clone(),
            announced: HashMap::default(),
            announced_bounds: Bounds::new(identity.max_devices, identity.device_idle_s),
            gate: TrackerGate::new(
                GateConfig {
                    listed: config.ha_devices.clone(),
                    min_fixes: config.ha_min_fixes,
                    per_minute: config.ha_new_trackers_per_minute,
                },
                identity.max_devices,
                identity.device_idle_s,
            ),
            occupancy: None,
            lossless,
            pending: Vec::new(),
            pending_ephemeral: Vec::new(),
            role: identity.role,
            shards: identity.shards,
            // A locator's persistent session may still hold the shards it
            // had before a restart: its first heartbeat drops all but its own.
            subscribed_shards: match identity.role {
                Role::Locator => (0..identity.shards).collect(),
                Role::Single | Role::Edge => Vec::new(),
            },
        }
    }

    /// Subscribes to the sightings of the shards a locator owns now, and
    /// only those.
    fn follow_shards(&mut self, owned: &[u16]) {
        if owned == self.subscribed_shards.as_slice() {
            return;
        }
        let filter = |&shard: &u16| cluster::shard_topic(&self.site_prefix, shard, "+");
        let gone = self.subscribed_shards.iter().filter(|s| !owned.contains(s));
        self.link.unsubscribe(gone.map(filter).collect());
        let new = owned.iter().filter(|s| !self.subscribed_shards.contains(s));
        self.link
            .subscribe(new.map(filter).collect(), QoS::AtMostOnce);
        self.subscribed_shards = owned.to_vec();
    }

    /// Home Assistant discovery for `building`'s places and floors.
    fn discovery_for(&self, building: &Building) -> Discovery {
        let (mut places, mut floors) = places_and_floors(building);
        if self.occupancy.is_none() {
            places.clear();
            floors.clear();
        }
        Discovery::new(
            &self.discovery_prefix,
            &self.gateway_id,
            self.topics.clone(),
            places,
            floors,
        )
    }

    /// Hands what is pending to the link now (before a command that must
    /// come after it).
    fn hand_over(&mut self) {
        self.link.publish_batch(std::mem::take(&mut self.pending));
        self.link
            .publish_batch_at(std::mem::take(&mut self.pending_ephemeral), QoS::AtMostOnce);
    }

    /// Notes a location of `device` at `t` (`located`: with a cell, not
    /// unknown), announcing the device when the gate lets a located one
    /// through; whether it has a tracker.
    fn announce(&mut self, device: &str, t: f64, located: bool) -> bool {
        if self.discovery.is_none() || self.role == Role::Locator {
            return false;
        }
        if let Some(seen) = self.announced.get_mut(device) {
            *seen = seen.max(t);
            return true;
        }
        if !(located && self.gate.admit(device, t)) {
            return false;
        }
        self.hand_over();
        let discovery = self.discovery.as_ref().expect("checked above");
        let mut forgotten = Vec::new();
        let full = self.announced.len() >= self.announced_bounds.max();
        self.announced_bounds.make_room(
            &mut self.announced,
            t,
            full,
            |&seen| seen,
            |id| forgotten.push(id.clone()),
        );
        for id in forgotten {
            self.link
                .clear_retained(discovery.tracker_config_topic(&id));
        }
        self.announced.insert(device.into(), t);
        // Sent now and kept for every reconnect (a restarted broker may have
        // lost it); the link keeps births by topic, so this costs one config.
        self.link
            .set_birth(&[discovery.device_tracker(device)], true);
        true
    }

    /// Removes a forgotten device from the occupancy counts, and its tracker
    /// from Home Assistant (an empty retained config) and from the configs
    /// re-sent after a reconnect.
    fn withdraw(&mut self, device: &str) {
        if let Some(occupancy) = &mut self.occupancy {
            occupancy.forget(device);
        }
        self.gate.forget(device);
        if self.discovery.is_some() && self.announced.remove(device).is_some() {
            self.hand_over();
            let discovery = self.discovery.as_ref().expect("checked above");
            self.link
                .clear_retained(discovery.tracker_config_topic(device));
        }
    }

    /// The occupancy counts, if they changed since they were last sent.
    fn publish_occupancy(&mut self) {
        if let Some(counts) = self
            .occupancy
            .as_mut()
            .and_then(|o| o.update(&self.topics, unix_now()))
        {
            self.pending.push(counts);
        }
    }
}

impl Sink for MqttSink {
    fn name(&self) -> &'static str {
        "mqtt"
    }

    /// Publishes each output, announcing new devices to Home Assistant
    /// before their first location (one config per new device), withdrawing
    /// those forgotten, and giving each tracker its state before the
    /// location that carries its attributes; then the occupancy counts, if
    /// they changed.
    fn send(&mut self, outputs: &[Output]) -> anyhow::Result<()> {
        for output in outputs {
            match output {
                Output::Location(location) => {
                    // A tracker's state goes before the location that
                    // carries its attributes; a device without one has none.
                    if self.announce(&location.device, location.t, location.cell.is_some()) {
                        let (topic, state) = self
                            .discovery
                            .as_ref()
                            .expect("checked above")
                            .presence(location);
                        self.pending.push(Message {
                            topic,
                            payload: state.into_bytes(),
                            retain: false,
                        });
                    }
                    if let Some(occupancy) = &mut self.occupancy {
                        occupancy.observe(location);
                    }
                }
                Output::Forgotten(device) => self.withdraw(device),
                Output::Sightings(batch) if self.role == Role::Edge => {
                    let messages = cluster::encode_by_shard(
                        &self.site_prefix,
                        &self.gateway_id,
                        self.shards,
                        batch,
                    );
                    self.pending_ephemeral.extend(messages);
                }
                Output::Sightings(batch) => {
                    let message = sightings::encode(&self.site_prefix, &self.gateway_id, batch);
                    self.pending.push(message);
                }
                Output::Beat(beat) => {
                    self.pending_ephemeral
                        .push(cluster::encode_beat(&self.site_prefix, beat));
                    self.follow_shards(&beat.owned);
                }
                _ => {}
            }
            if let Some(message) = self.topics.encode(output) {
                self.pending.push(message);
            }
        }
        self.publish_occupancy();
        Ok(())
    }

    /// Hands the messages of the last outputs to the link in one batch; a
    /// lossless sink hands over only what fits under the link's bound at a
    /// time, waiting for the broker in between.
    fn flush(&mut self) -> BoxFuture<'_, anyhow::Result<()>> {
        Box::pin(async move {
            if !self.lossless {
                self.hand_over();
                return Ok(());
            }
            while !self.pending.is_empty() {
                self.link.wait_for_room().await;
                let n = self.link.room().min(self.pending.len());
                let batch: Vec<Message> = self.pending.drain(..n).collect();
                self.link.publish_batch(batch);
            }
            Ok(())
        })
    }

    /// After a reload: occupancy starts afresh with the tracks, and Home
    /// Assistant gets sensors for the new site's places (and loses those of
    /// places it no longer has).
    fn reload(&mut self, building: &Building) {
        if self.occupancy.is_some() {
            self.occupancy = Some(occupancy(building));
            self.publish_occupancy();
        }
        let Some(old) = self.discovery.take() else {
            return;
        };
        let new = self.discovery_for(building);
        for gone in old.sensor_config_topics() {
            if !new.sensor_config_topics().any(|t| t == gone) {
                self.link.clear_retained(gone);
            }
        }
        // Sent now and kept for every reconnect, by topic.
        self.link.set_birth(&new.gateway(), true);
        self.discovery = Some(new);
    }

    fn report(&self, stats: &mut Stats) {
        let link = self.link.stats();
        let count = |c: &std::sync::atomic::AtomicU64| c.load(Ordering::Relaxed);
        stats.inbound_dropped = count(&link.inbound_dropped);
        stats.disconnects = count(&link.disconnects);
        stats.unpublishable = count(&link.unpublishable);
        stats.queue_depth = count(&link.queue_depth);
        stats.queue_bytes = count(&link.queue_bytes);
        stats.queue_dropped = count(&link.queue_dropped);
        stats.reconnects = count(&link.reconnects);
        stats.mqtt = state(link);
        stats.announced = self.announced.len() as u64;
        stats.trackers_refused = self.gate.refused();
    }

    fn has_room(&self) -> bool {
        self.link.has_room()
    }

    fn is_alive(&self) -> bool {
        self.link.is_alive()
    }

    fn status(&self) -> Option<String> {
        let link = self.link.stats();
        Some(match state(link) {
            "connected" => "broker connected".to_owned(),
            "flapping" => format!(
                "CANNOT STAY CONNECTED to the broker ({} connections lost; see the log)",
                link.disconnects.load(Ordering::Relaxed)
            ),
            _ => "broker unreachable, retrying (see the log)".to_owned(),
        })
    }

    fn shutdown(mut self: Box<Self>) -> BoxFuture<'static, anyhow::Result<()>> {
        Box::pin(async move {
            self.flush().await?;
            let dropped = self.link.stats().queue_dropped.load(Ordering::Relaxed);
            if dropped > 0 {
                tracing::warn!(dropped, "MQTT messages dropped from the full offline queue");
            }
            self.link.shutdown().await;
            Ok(())
        })
    }
}

/// The connection's state for the stats and systemd's status line.
fn state(link: &LinkStats) -> &'static str {
    if link.flapping.load(Ordering::Relaxed) {
        "flapping"
    } else if link.connected.load(Ordering::Relaxed) {
        "connected"
    } else {
        "disconnected"
    }
}
