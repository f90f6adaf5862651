//! The gateway daemon: sightings from the radio (or a replayed log), phone
//! scans and other gateways' sightings over MQTT, and route requests, all fed
//! through one [`Pipeline`]; what it returns goes out over the [`Link`].
//!
//! The daemon owns the process's life: systemd readiness and watchdog,
//! SIGHUP reloads ([`state`]), SIGTERM/SIGINT graceful shutdown, and the
//! retained stats. The radio being missing never stops it: MQTT keeps serving
//! while [`source::radio`] retries.
//!
//! Everything from the broker is hostile: route requests wait in a bounded
//! queue and are answered `overloaded` rather than dropped ([`admission`]),
//! per-device rates are limited, and the Home Assistant trackers it announced
//! are bounded like the tracks (`[limits]`) and withdrawn when forgotten.

pub mod admission;
pub mod recorder;
pub mod source;
pub mod state;

use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::Ordering;
use std::time::{Duration, SystemTime, UNIX_EPOCH};

use tokio::signal::unix::{SignalKind, signal};
use tokio::sync::{mpsc, watch};
use tokio::time::{Instant, MissedTickBehavior};

use admission::{Admit, Issued, PerSecond, Requests};
use foldhash::HashMap;

use crate::locate::bounds::Bounds;
use crate::locate::window::Orientation;
use crate::mqtt::discovery::Discovery;
use crate::mqtt::inbound::{Inbound, Inbox, Rejected};
use crate::mqtt::occupancy::Occupancy;
use crate::mqtt::stats::{BleStatus, STATS_SCHEMA, Stats};
use crate::mqtt::{self, Link, Received, sightings};
use crate::pipeline;
use crate::plan::RouteErrorCode;
use crate::publish::{LOCATION_SCHEMA, Message, PATH_SCHEMA, Topics};
use crate::sighting::Sighting;
use crate::source::{Event, RouteRequest};
use crate::store::Record;
use crate::throttle::Throttle;
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
/// Routes remembered for feedback.
const ISSUED_ROUTES: usize = 10_000;
/// At most one line per this period for each kind of repeated refusal.
const WARN_EVERY: Duration = Duration::from_secs(10);
/// How often a backed-up link is checked for room again.
const BACKLOG_POLL: Duration = Duration::from_millis(5);
/// What an `overloaded` or `rate_limited` reply suggests waiting, seconds.
const RETRY_AFTER_S: f64 = 1.0;

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
    overloaded: u64,
    rate_limited: u64,
    feedback_refused: u64,
    /// Pipeline counters of pipelines replaced by reloads.
    retired: pipeline::Stats,
    retired_ignored: u64,
    /// Windows and tracks forgotten by pipelines replaced by reloads.
    retired_evicted: (u64, u64),
}

/// Repeated warnings, each logged at most once per [`WARN_EVERY`].
struct Throttles {
    overloaded: Throttle,
    rate_limited: Throttle,
    rejected: Throttle,
}

struct Daemon {
    state: Loaded,
    topics: Topics,
    inbox: Inbox,
    link: Link,
    discovery: Option<Discovery>,
    /// Devices with a published discovery config, with the time of their
    /// latest location, bounded like the tracks.
    announced: HashMap<Arc<str>, f64>,
    announced_bounds: Bounds,
    requests: Requests,
    scan_rate: PerSecond,
    /// All scans together (one key).
    scan_total: PerSecond,
    request_rate: PerSecond,
    issued: Issued,
    throttles: Throttles,
    /// Why the learning store is not the configured file, if it is not.
    store_fallback: Option<String>,
    /// The last status line given to systemd.
    status: String,
    /// Devices per named place, sent when it changes.
    occupancy: Occupancy,
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
    // A store that cannot be opened never stops the gateway: it is moved
    // aside (or, if even that fails, the gateway serves without recording).
    let (recorder, store_fallback) = if config.store.enabled {
        match Recorder::open(&config.store, now()) {
            Ok((recorder, moved)) => (Some(recorder), moved),
            Err(e) => {
                let why = format!("[store] {e}; serving without recording");
                tracing::error!("{why}");
                (None, Some(why))
            }
        }
    } else {
        (None, None)
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
    let discovery = config.mqtt.ha_discovery.then(|| discovery(&state));
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

    let limits = config.limits.clone();
    let mut daemon = Daemon {
        topics,
        inbox,
        link,
        discovery,
        announced: HashMap::default(),
        announced_bounds: Bounds::new(limits.max_devices, limits.device_idle_s),
        requests: Requests::new(
            limits.max_pending_requests,
            Duration::from_secs_f64(limits.request_deadline_s),
        ),
        scan_rate: PerSecond::new(limits.scans_per_device_per_s),
        scan_total: PerSecond::new(limits.scans_per_s),
        request_rate: PerSecond::new(limits.requests_per_device_per_s),
        issued: Issued::new(ISSUED_ROUTES),
        throttles: Throttles {
            overloaded: Throttle::new(WARN_EVERY),
            rate_limited: Throttle::new(WARN_EVERY),
            rejected: Throttle::new(WARN_EVERY),
        },
        store_fallback,
        status: String::new(),
        occupancy: occupancy(&state),
        site_prefix,
        share: sharing.then(Vec::new),
        counters: Counters::default(),
        recorder,
        ble: ble_rx,
        started: Instant::now(),
        out: Vec::new(),
        state,
    };
    daemon.publish_occupancy();

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
            // Nothing is taken in while the link is backed up: the replies
            // would push older ones out of its queue; the broker (and the
            // link's unacknowledged hold) keeps the requests meanwhile. A
            // backlog drains with the broker's acknowledgements, so poll.
            Some(message) = inbound.recv(), if daemon.link.has_room() => daemon.inbound(&message),
            () = tokio::time::sleep(BACKLOG_POLL), if !daemon.link.has_room() => {}
            // Planning is the costly part: one request per turn, so that
            // reading (and answering `overloaded`) keeps pace with the broker.
            () = std::future::ready(()), if !daemon.requests.is_empty() => daemon.serve_next(),
            _ = share_tick.tick(), if daemon.share.is_some() => daemon.flush_shared(),
            _ = record_tick.tick(), if daemon.recorder.is_some() => daemon.flush_records(),
            _ = stats_tick.tick() => {
                daemon.publish_stats();
                daemon.notify_status();
            }
            Ok(()) = daemon.ble.changed() => daemon.publish_stats(),
            _ = watchdog_tick.tick(), if watchdog.is_some() => {
                // Fed from this loop, so a stuck loop is restarted; and not
                // fed once the MQTT link's task is gone (it only ends by
                // panicking), since nothing would be served any more.
                if daemon.link.is_alive() {
                    let _ = sd_notify::notify(&[sd_notify::NotifyState::Watchdog]);
                } else {
                    tracing::error!("the MQTT link stopped; no more watchdog pings, so systemd restarts the gateway");
                }
                daemon.notify_status();
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

    fn inbound(&mut self, message: &Received) {
        let topic = message.topic.as_str();
        let now = now();
        match self
            .inbox
            .read_sized(topic, &message.payload, message.size, now)
        {
            Ok(Inbound::Route(request)) => {
                if !self.request_rate.allow(&request.device, now) {
                    let why = format!(
                        "more than {} route requests per second from this device",
                        self.state.config.limits.requests_per_device_per_s
                    );
                    self.refuse_route(&request, RouteErrorCode::RateLimited, why);
                } else if let Some((request, why)) = self.requests.push(request) {
                    self.refuse_route(&request, RouteErrorCode::Overloaded, why);
                }
            }
            Ok(Inbound::BadRoute {
                device,
                request_id,
                code,
                message,
            }) => {
                if let Some(more) = self.throttles.rejected.ready() {
                    tracing::warn!(%topic, code = code.as_str(), not_logged = more, "refused route request: {message}");
                }
                if code == RouteErrorCode::PayloadTooLarge {
                    self.counters.oversized += 1;
                }
                let reply = self
                    .state
                    .pipeline
                    .reject(&device, request_id, now, code, message);
                self.out.push(self.topics.encode_route(&reply));
            }
            Ok(Inbound::Feedback(feedback)) => self.feedback(feedback),
            Ok(Inbound::Scan(scan)) => {
                let pipeline = &mut self.state.pipeline;
                if pipeline.orientation() != Orientation::Observer {
                    self.counters.rejected += 1;
                    tracing::warn!(
                        %topic,
                        "phone scan ignored: this gateway locates tags ([window] orientation = \
                         \"advertiser\"), and a phone's scan needs orientation = \"observer\""
                    );
                    return;
                }
                let device = scan.first().map(|s| s.observer.clone());
                if let Some(device) = device
                    && !(self.scan_total.allow("", now) && self.scan_rate.allow(&device, now))
                {
                    self.counters.rate_limited += 1;
                    if let Some(more) = self.throttles.rate_limited.ready() {
                        tracing::warn!(%topic, not_logged = more, "phone scans over [limits] scans_per_s or scans_per_device_per_s dropped");
                    }
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
                    self.state.pipeline.handle(&Event::Advert(s), &mut self.out);
                }
            }
            Err(Rejected::Own { .. }) => {}
            Err(e) => {
                self.counters.rejected += 1;
                if e.is_oversized() {
                    self.counters.oversized += 1;
                }
                if let Some(more) = self.throttles.rejected.ready() {
                    tracing::warn!(not_logged = more, "ignored message: {e}");
                }
            }
        }
        self.send();
    }

    /// Plans the next waiting route request (or answers `overloaded` if it
    /// waited too long).
    fn serve_next(&mut self) {
        match self.requests.take_next() {
            Some(Admit::Serve(request)) => {
                // Through the pipeline's event path, so a served route also
                // starts the device's guidance session.
                self.state
                    .pipeline
                    .handle(&Event::Request(request), &mut self.out);
            }
            Some(Admit::Overloaded(request, why)) => {
                self.refuse_route(&request, RouteErrorCode::Overloaded, why)
            }
            None => return,
        }
        self.send();
    }

    /// Answers a route request with an error that says when to try again,
    /// counts it, and logs it (at most once per [`WARN_EVERY`] per kind).
    fn refuse_route(&mut self, request: &RouteRequest, code: RouteErrorCode, why: String) {
        let (count, throttle) = if code == RouteErrorCode::Overloaded {
            (
                &mut self.counters.overloaded,
                &mut self.throttles.overloaded,
            )
        } else {
            (
                &mut self.counters.rate_limited,
                &mut self.throttles.rate_limited,
            )
        };
        *count += 1;
        if let Some(more) = throttle.ready() {
            tracing::warn!(
                device = request.device,
                code = code.as_str(),
                not_logged = more,
                total = *count,
                "route request refused: {why}"
            );
        }
        let message = format!("{why}; retry in {RETRY_AFTER_S} s");
        let reply = self.state.pipeline.reject(
            &request.device,
            request.request_id.clone(),
            request.t,
            code,
            message,
        );
        let mut encoded = self.topics.encode_route(&reply);
        encoded.payload["error"]["retry_after_s"] = RETRY_AFTER_S.into();
        self.out.push(encoded);
    }

    /// Feedback is taken once for a route this gateway gave; anything else
    /// is refused with an error on `…/feedback/error`.
    fn feedback(&mut self, feedback: crate::mqtt::inbound::Feedback) {
        if !self.issued.take(&feedback.device, &feedback.request_id) {
            self.counters.feedback_refused += 1;
            if let Some(more) = self.throttles.rejected.ready() {
                tracing::warn!(
                    device = feedback.device,
                    not_logged = more,
                    "feedback refused: no route {:?} given to this device, or it was scored already",
                    feedback.request_id
                );
            }
            self.out.push(Message {
                topic: format!("{}/error", self.topics.feedback(&feedback.device)),
                payload: serde_json::json!({
                    "schema": FEEDBACK_ERROR_SCHEMA,
                    "device": feedback.device,
                    "request_id": feedback.request_id,
                    "t": feedback.t,
                    "error": {
                        "code": "unknown_request",
                        "message": "feedback is taken once for a route this gateway gave the \
                                    device recently; this request id is not one of them",
                    },
                }),
                retain: false,
            });
            return;
        }
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

    /// Publishes what the pipeline produced, announcing new devices to Home
    /// Assistant before their first location (one config per new device),
    /// withdrawing those of devices forgotten, and giving each tracker its
    /// state before the location that carries its attributes; then the
    /// occupancy counts, if they changed.
    fn send(&mut self) {
        for device in self.state.pipeline.take_evicted() {
            self.withdraw(&device);
        }
        let mut out = std::mem::take(&mut self.out);
        for message in out.drain(..) {
            let schema = &message.payload["schema"];
            if *schema == LOCATION_SCHEMA
                && let Some(device) = message.payload["device"].as_str()
            {
                self.announce(device, message.payload["t"].as_f64().unwrap_or(0.0));
            } else if *schema == PATH_SCHEMA
                && message.payload.get("waypoints").is_some()
                && let (Some(device), Some(id)) = (
                    message.payload["device"].as_str(),
                    message.payload["request_id"].as_str(),
                )
            {
                self.issued.insert(device, id);
            }
            if let Some((topic, state)) = self.discovery.as_ref().and_then(|d| d.presence(&message))
            {
                self.link.publish_raw(topic, state.into_bytes(), false);
            }
            self.occupancy.observe(&message);
            if let Some(recorder) = &mut self.recorder {
                recorder.published(&message);
            }
            self.link.publish(&message);
        }
        self.out = out;
        self.publish_occupancy();
    }

    /// Notes a location of `device` at `t`; the first one announces it.
    fn announce(&mut self, device: &str, t: f64) {
        let Some(discovery) = &self.discovery else {
            return;
        };
        if let Some(seen) = self.announced.get_mut(device) {
            *seen = seen.max(t);
            return;
        }
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
    }

    /// Removes a forgotten device from the occupancy counts, and its tracker
    /// from Home Assistant (an empty retained config) and from the configs
    /// re-sent after a reconnect.
    fn withdraw(&mut self, device: &str) {
        self.occupancy.forget(device);
        if let Some(discovery) = &self.discovery
            && self.announced.remove(device).is_some()
        {
            self.link
                .clear_retained(discovery.tracker_config_topic(device));
        }
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
        let evicted = self.state.pipeline.evicted();
        let mut fallbacks = self.state.fallbacks.clone();
        fallbacks.extend(self.store_fallback.clone());
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
            store_quota_deleted: self.recorder.as_ref().map_or(0, |r| r.quota_deleted),
            overloaded: c.overloaded,
            rate_limited: c.rate_limited,
            feedback_refused: c.feedback_refused,
            evicted_devices: evicted.1 + c.retired_evicted.1,
            evicted_windows: evicted.0 + c.retired_evicted.0,
            disconnects: link.disconnects.load(Ordering::Relaxed),
            unpublishable: link.unpublishable.load(Ordering::Relaxed),
            windows: self.state.pipeline.windows_open() as u64,
            announced: self.announced.len() as u64,
            pending_requests: self.requests.len() as u64,
            mqtt: mqtt_state(link),
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
            fallbacks,
        }
    }

    /// Tells systemd (`systemctl status`) how the gateway is doing, when
    /// that changed.
    fn notify_status(&mut self) {
        let link = self.link.stats();
        let broker = match mqtt_state(link) {
            "connected" => "broker connected".to_owned(),
            "flapping" => format!(
                "CANNOT STAY CONNECTED to the broker ({} connections lost; see the log)",
                link.disconnects.load(Ordering::Relaxed)
            ),
            _ => "broker unreachable, retrying (see the log)".to_owned(),
        };
        let status = format!(
            "{broker}; {} devices tracked, {} route requests waiting",
            self.state.pipeline.tracked(),
            self.requests.len()
        );
        if status != self.status {
            let _ = sd_notify::notify(&[sd_notify::NotifyState::Status(&status)]);
            self.status = status;
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

    /// After a reload: occupancy starts afresh with the tracks, and Home
    /// Assistant gets sensors for the new site's places (and loses those of
    /// places it no longer has).
    fn reload_places(&mut self) {
        self.occupancy = occupancy(&self.state);
        self.publish_occupancy();
        let Some(old) = self.discovery.replace(discovery(&self.state)) else {
            return;
        };
        let new = self.discovery.as_ref().expect("just set");
        for place in old.place_names() {
            let topic = old.occupancy_config_topic(place);
            if let Some(gone) =
                topic.filter(|t| new.occupancy_config_topic(place).as_ref() != Some(t))
            {
                self.link.clear_retained(gone);
            }
        }
        // Sent now and kept for every reconnect, by topic.
        self.link.set_birth(&new.gateway(), true);
    }

    /// The occupancy counts, if they changed since they were last sent.
    fn publish_occupancy(&mut self) {
        if let Some(counts) = self.occupancy.update(&self.topics, now()) {
            self.link.publish(&counts);
        }
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
                    let (windows, tracks) = old.pipeline.evicted();
                    self.counters.retired_evicted.0 += windows;
                    self.counters.retired_evicted.1 += tracks;
                    tracing::info!(
                        site = self.state.site.name,
                        site_hash = self.state.site.map_hash(),
                        "reloaded config and site; tracks start afresh"
                    );
                    self.counters.reloads += 1;
                    self.reload_places();
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

/// Home Assistant discovery for the loaded config and site.
fn discovery(state: &Loaded) -> Discovery {
    Discovery::new(
        &state.config.mqtt.discovery_prefix,
        &state.config.gateway_id,
        state.pipeline.topics().clone(),
        state.site.places().keys().map(String::as_str),
    )
}

/// Occupancy of the loaded site's places, everyone away.
fn occupancy(state: &Loaded) -> Occupancy {
    Occupancy::new(state.site.places().keys().map(String::as_str))
}

/// Schema id of the error answered to refused feedback.
pub const FEEDBACK_ERROR_SCHEMA: &str = "gangway.feedback-error/1";

/// The connection's state for the stats and systemd's status line.
fn mqtt_state(link: &mqtt::LinkStats) -> &'static str {
    if link.flapping.load(Ordering::Relaxed) {
        "flapping"
    } else if link.connected.load(Ordering::Relaxed) {
        "connected"
    } else {
        "disconnected"
    }
}

fn now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}
