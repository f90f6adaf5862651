//! The gateway daemon: sightings from the radio (or a replayed log), phone
//! scans and other gateways' sightings over MQTT, and route requests, all fed
//! through one [`Pipeline`]; what it returns goes out over the [`Link`].
//!
//! The daemon owns the process's life: systemd readiness and watchdog,
//! SIGHUP reloads ([`state`]), SIGTERM/SIGINT graceful shutdown, and the
//! retained stats. The radio being missing never stops it: MQTT keeps serving
//! while [`source::radio`] retries.

pub mod recorder;
pub mod source;
pub mod state;

use std::collections::HashSet;
use std::path::PathBuf;
use std::sync::atomic::Ordering;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use tokio::signal::unix::{SignalKind, signal};
use tokio::sync::{mpsc, watch};
use tokio::time::{Instant, MissedTickBehavior};

use crate::locate::window::Orientation;
use crate::mqtt::discovery::Discovery;
use crate::mqtt::inbound::{Inbound, Inbox, Rejected};
use crate::mqtt::stats::{BleStatus, STATS_SCHEMA, Stats};
use crate::mqtt::{self, Link, sightings};
use crate::pipeline;
use crate::publish::{LOCATION_SCHEMA, Message, Topics};
use crate::sighting::Sighting;
use crate::source::Event;
use crate::store::Record;
use recorder::Recorder;
use state::Loaded;

/// How often this gateway's own sightings go out to the other gateways.
const SHARE_INTERVAL: Duration = Duration::from_millis(250);
/// Largest batch of shared sightings in one message.
const SHARE_BATCH: usize = 256;
/// How long the source gets at shutdown to stop (a scan stops discovery).
const SOURCE_STOP: Duration = Duration::from_secs(2);
/// How often the learning store is written.
const RECORD_INTERVAL: Duration = Duration::from_secs(1);

/// What `gangway run` asks for.
pub struct Options {
    pub config_path: PathBuf,
    /// Overrides `[mqtt] url`.
    pub mqtt_url: Option<String>,
    /// Play a log instead of scanning.
    pub replay: Option<source::Replay>,
}

/// Counters the daemon keeps beside the pipeline's.
#[derive(Default)]
struct Counters {
    feedback: u64,
    scans: u64,
    shared_in: u64,
    shared_out: u64,
    rejected: u64,
    oversized: u64,
    reloads: u64,
    reload_failures: u64,
    /// Pipeline counters of pipelines replaced by reloads.
    retired: pipeline::Stats,
    retired_ignored: u64,
}

struct Daemon {
    state: Loaded,
    topics: Topics,
    inbox: Inbox,
    link: Link,
    discovery: Option<Discovery>,
    /// Devices with a published discovery config.
    announced: HashSet<String>,
    site_prefix: String,
    /// Own sightings waiting to be shared (advertiser orientation only).
    share: Option<Vec<Sighting>>,
    counters: Counters,
    /// The learning store, when `[store] enabled`.
    recorder: Option<Recorder>,
    ble: watch::Receiver<BleStatus>,
    started: Instant,
    out: Vec<Message>,
}

/// Runs until SIGTERM or SIGINT.
pub async fn run(options: Options) -> anyhow::Result<()> {
    let state = state::load_at_start(&options.config_path)?;
    let config = &state.config;
    let topics = state.pipeline.topics().clone();
    let site_prefix = config.site_prefix(&state.site.name);
    let sharing = state.pipeline.orientation() == Orientation::Advertiser;
    anyhow::ensure!(
        mqtt::config::valid_prefix(&site_prefix),
        "the site name {:?} cannot be part of a topic ({site_prefix:?}); set [mqtt] site_prefix",
        state.site.name
    );
    let recorder = if config.store.enabled {
        Some(Recorder::open(&config.store)?)
    } else {
        None
    };
    let url = mqtt::broker_url(&config.mqtt, options.mqtt_url)?;
    let inbox = Inbox::new(
        topics.clone(),
        site_prefix.clone(),
        config.gateway_id.clone(),
        config.mqtt.max_payload_bytes,
        sharing,
    );
    let settings = mqtt::link_settings(
        &config.mqtt,
        &url,
        &config.client_id(),
        Some(topics.status()),
        inbox.subscriptions(),
    )?;
    let (link, mut inbound) = Link::start(settings);
    let discovery = config.mqtt.ha_discovery.then(|| {
        Discovery::new(
            &config.mqtt.discovery_prefix,
            &config.gateway_id,
            topics.clone(),
        )
    });
    if let Some(d) = &discovery {
        link.set_birth(&d.gateway(), true);
    }
    tracing::info!(
        broker = %url,
        prefix = topics.prefix(),
        site = state.site.name,
        sharing,
        "gateway {} serving",
        config.gateway_id
    );

    let (events_tx, mut events) = mpsc::channel(4096);
    let (ble_tx, ble_rx) = watch::channel(BleStatus {
        state: "starting",
        ..BleStatus::default()
    });
    let mut source_task = match options.replay {
        Some(replay) => {
            ble_tx.send_replace(BleStatus {
                state: "replay",
                ..BleStatus::default()
            });
            tokio::spawn(async move {
                if let Err(e) = source::replay(replay, events_tx).await {
                    tracing::error!("replay stopped: {e:#}; still serving MQTT");
                }
            })
        }
        None => tokio::spawn(source::radio(
            config.ble.clone(),
            config.gateway_id.as_str().into(),
            events_tx,
            ble_tx,
        )),
    };
    let stats_every = Duration::from_secs_f64(config.mqtt.stats_interval_s);

    let mut daemon = Daemon {
        topics,
        inbox,
        link,
        discovery,
        announced: HashSet::new(),
        site_prefix,
        share: sharing.then(Vec::new),
        counters: Counters::default(),
        recorder,
        ble: ble_rx,
        started: Instant::now(),
        out: Vec::new(),
        state,
    };

    let mut terminate = signal(SignalKind::terminate())?;
    let mut interrupt = signal(SignalKind::interrupt())?;
    let mut hangup = signal(SignalKind::hangup())?;
    let mut stats_tick = tokio::time::interval(stats_every);
    let mut record_tick = tokio::time::interval(RECORD_INTERVAL);
    let mut share_tick = tokio::time::interval(SHARE_INTERVAL);
    share_tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    // systemd's watchdog wants a ping at least every WATCHDOG_USEC; pinging from
    // this loop means a stuck loop gets the service restarted.
    let watchdog = sd_notify::watchdog_enabled();
    let mut watchdog_tick =
        tokio::time::interval(watchdog.map_or(Duration::from_secs(3600), |every| every / 2));
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Ready]);
    let mut source_open = true;

    loop {
        tokio::select! {
            event = events.recv(), if source_open => match event {
                Some(event) => daemon.own_event(&event),
                None => {
                    source_open = false;
                    daemon.state.pipeline.finish(&mut daemon.out);
                    daemon.send();
                }
            },
            Some(message) = inbound.recv() => daemon.inbound(&message.topic, &message.payload),
            _ = share_tick.tick(), if daemon.share.is_some() => daemon.flush_shared(),
            _ = record_tick.tick(), if daemon.recorder.is_some() => daemon.flush_records(),
            _ = stats_tick.tick() => daemon.publish_stats(),
            Ok(()) = daemon.ble.changed() => daemon.publish_stats(),
            _ = watchdog_tick.tick(), if watchdog.is_some() => {
                let _ = sd_notify::notify(&[sd_notify::NotifyState::Watchdog]);
            }
            _ = hangup.recv() => daemon.reload(&options.config_path),
            _ = terminate.recv() => break,
            _ = interrupt.recv() => break,
        }
    }
    tracing::info!("shutting down: sending what is queued, then `offline`");
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
    // Closing the channel lets a scan stop discovery before it returns.
    drop(events);
    if tokio::time::timeout(SOURCE_STOP, &mut source_task)
        .await
        .is_err()
    {
        source_task.abort();
    }
    daemon.flush_shared();
    daemon.flush_records();
    daemon.publish_stats();
    daemon.link.shutdown().await;
    Ok(())
}

impl Daemon {
    /// A sighting (or scripted request) from this gateway's own source.
    fn own_event(&mut self, event: &Event) {
        if let (Some(batch), Event::Advert(s)) = (&mut self.share, event)
            && *s.observer == *self.state.config.gateway_id
        {
            batch.push(s.clone());
            if batch.len() >= SHARE_BATCH {
                self.flush_shared();
            }
        }
        self.state.pipeline.handle(event, &mut self.out);
        self.send();
    }

    fn inbound(&mut self, topic: &str, payload: &[u8]) {
        let pipeline = &mut self.state.pipeline;
        match self.inbox.read(topic, payload, now()) {
            Ok(Inbound::Route(request)) => {
                pipeline.handle(&Event::Request(request), &mut self.out);
            }
            Ok(Inbound::BadRoute {
                device,
                request_id,
                code,
                message,
            }) => {
                tracing::warn!(%topic, code, "refused route request: {message}");
                if code == "payload_too_large" {
                    self.counters.oversized += 1;
                }
                let reply = pipeline.reject(&device, request_id, now(), code, message);
                self.out.push(self.topics.encode_route(&reply));
            }
            Ok(Inbound::Feedback(feedback)) => {
                self.counters.feedback += 1;
                tracing::info!(
                    device = feedback.device,
                    request_id = feedback.request_id,
                    score = feedback.score,
                    "route feedback"
                );
                if let Some(recorder) = &mut self.recorder {
                    recorder.push(Record::Feedback {
                        device: feedback.device,
                        request_id: feedback.request_id,
                        t: feedback.t,
                        score: feedback.score,
                    });
                }
            }
            Ok(Inbound::Scan(scan)) => {
                if pipeline.orientation() != Orientation::Observer {
                    self.counters.rejected += 1;
                    tracing::warn!(
                        %topic,
                        "phone scan ignored: this gateway locates tags ([window] orientation = \
                         \"advertiser\"), and a phone's scan needs orientation = \"observer\""
                    );
                    return;
                }
                self.counters.scans += 1;
                for s in scan {
                    pipeline.handle(&Event::Advert(s), &mut self.out);
                }
            }
            Ok(Inbound::Shared(shared)) => {
                self.counters.shared_in += shared.len() as u64;
                for s in shared {
                    pipeline.handle(&Event::Advert(s), &mut self.out);
                }
            }
            Err(Rejected::Own { .. }) => {}
            Err(e) => {
                self.counters.rejected += 1;
                if e.is_oversized() {
                    self.counters.oversized += 1;
                }
                tracing::warn!("ignored message: {e}");
            }
        }
        self.send();
    }

    /// Publishes what the pipeline produced, announcing new devices to Home
    /// Assistant before their first location.
    fn send(&mut self) {
        let mut announced = false;
        for message in self.out.drain(..) {
            if let Some(discovery) = &self.discovery
                && message.payload["schema"] == LOCATION_SCHEMA
                && let Some(device) = message.payload["device"].as_str()
                && !self.announced.contains(device)
            {
                self.announced.insert(device.to_owned());
                self.link.publish(&discovery.device_tracker(device));
                announced = true;
            }
            if let Some(recorder) = &mut self.recorder {
                recorder.published(&message);
            }
            self.link.publish(&message);
        }
        if announced {
            self.refresh_birth();
        }
    }

    /// Keeps the discovery configs re-sent after a reconnect in step with the
    /// devices announced so far (a restarted broker may have lost them).
    fn refresh_birth(&self) {
        let Some(discovery) = &self.discovery else {
            return;
        };
        let mut birth = discovery.gateway();
        let mut devices: Vec<_> = self.announced.iter().collect();
        devices.sort();
        birth.extend(devices.into_iter().map(|d| discovery.device_tracker(d)));
        self.link.set_birth(&birth, false);
    }

    fn flush_records(&mut self) {
        if let Some(recorder) = &mut self.recorder {
            recorder.flush(now());
        }
    }

    fn flush_shared(&mut self) {
        let Some(batch) = &mut self.share else { return };
        if batch.is_empty() {
            return;
        }
        let message = sightings::encode(&self.site_prefix, &self.state.config.gateway_id, batch);
        self.counters.shared_out += batch.len() as u64;
        batch.clear();
        self.link.publish(&message);
    }

    fn stats(&self) -> Stats {
        let p = self.state.pipeline.stats();
        let r = &self.counters.retired;
        let link = self.link.stats();
        let c = &self.counters;
        Stats {
            schema: STATS_SCHEMA,
            gateway: self.state.config.gateway_id.clone(),
            t: now(),
            uptime_s: self.started.elapsed().as_secs_f64(),
            sightings: p.sightings + r.sightings,
            sightings_ignored: self.state.pipeline.unknown_anchor_sightings() + c.retired_ignored,
            fixes: p.fixes + r.fixes,
            requests: p.requests + r.requests,
            routes: p.routes + r.routes,
            request_errors: p.request_errors + r.request_errors,
            feedback: c.feedback,
            scans: c.scans,
            shared_in: c.shared_in,
            shared_out: c.shared_out,
            rejected_messages: c.rejected,
            oversized_messages: c.oversized,
            inbound_dropped: link.inbound_dropped.load(Ordering::Relaxed),
            bad_device_ids: p.bad_device_ids + r.bad_device_ids,
            queue_depth: link.queue_depth.load(Ordering::Relaxed),
            queue_bytes: link.queue_bytes.load(Ordering::Relaxed),
            queue_dropped: link.queue_dropped.load(Ordering::Relaxed),
            reconnects: link.reconnects.load(Ordering::Relaxed),
            reloads: c.reloads,
            reload_failures: c.reload_failures,
            recorded: self.recorder.as_ref().map_or(0, |r| r.written),
            store_errors: self.recorder.as_ref().map_or(0, |r| r.errors),
            scan_restarts: self.ble.borrow().scan_restarts,
            tracked: self.state.pipeline.tracked() as u64,
            site: self.state.site.name.clone(),
            site_hash: self.state.site.map_hash().to_owned(),
            ble: self.ble.borrow().clone(),
            fallbacks: self.state.fallbacks.clone(),
        }
    }

    fn publish_stats(&mut self) {
        let stats = self.stats();
        let payload = serde_json::to_value(&stats).expect("plain data serializes");
        self.link.publish(&Message {
            topic: self.topics.stats(),
            payload,
            retain: true,
        });
    }

    /// SIGHUP: load everything anew; swap only if all of it loads.
    fn reload(&mut self, config_path: &std::path::Path) {
        let _ = sd_notify::notify(&[sd_notify::NotifyState::Reloading]);
        let refused = match state::load(config_path) {
            Err(e) => Some(format!("{e:#}")),
            Ok(new) => match state::restart_needed(&self.state, &new) {
                Some(why) => Some(format!("{why}; restart the gateway to apply it")),
                None => {
                    let old = std::mem::replace(&mut self.state, new);
                    let s = old.pipeline.stats();
                    let r = &mut self.counters.retired;
                    r.sightings += s.sightings;
                    r.fixes += s.fixes;
                    r.requests += s.requests;
                    r.routes += s.routes;
                    r.request_errors += s.request_errors;
                    r.bad_device_ids += s.bad_device_ids;
                    self.counters.retired_ignored += old.pipeline.unknown_anchor_sightings();
                    tracing::info!(
                        site = self.state.site.name,
                        site_hash = self.state.site.map_hash(),
                        "reloaded config and site; tracks start afresh"
                    );
                    self.counters.reloads += 1;
                    None
                }
            },
        };
        if let Some(why) = refused {
            self.counters.reload_failures += 1;
            tracing::error!("reload refused, still serving the previous config: {why}");
        }
        self.publish_stats();
        let _ = sd_notify::notify(&[sd_notify::NotifyState::Ready]);
    }
}

fn now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}
