//! The live map's side of the gateway: a [`Sink`] that keeps what the map
//! shows (every tracked device with its recent trail, the last route and
//! guidance of each, the gateway's stats) and streams it to the pages as
//! Server-Sent Events, and a [`Source`] through which the pages ask for
//! routes exactly as MQTT clients do (the runtime's admission, rate limits
//! and planner; the reply comes back as the same route output).
//!
//! Bounded everywhere: devices and their routes follow the pipeline's
//! `[limits]` (a `Forgotten` output drops them, and the table never holds
//! more than `max_devices`), trails are [`TRAIL`] fixes, event streams are
//! [`MAX_STREAMS`] pages at once, each with a queue of [`STREAM_QUEUE`]
//! events; a page that falls behind gets a fresh snapshot instead of what it
//! missed, and never holds the gateway back.
//!
//! Fixes are sent in batches, each when the runtime goes idle (its
//! [`Sink::flush`]), so under load a page gets a few messages a second
//! rather than one per fix, and an idle gateway sends each fix at once.

use std::collections::{HashMap, VecDeque};
use std::convert::Infallible;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex};

use axum::Json;
use axum::extract::State;
use axum::http::StatusCode;
use axum::response::sse::{Event as SseEvent, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use futures::future::BoxFuture;
use futures::stream;
use serde::{Deserialize, Serialize};
use tokio::sync::{broadcast, mpsc, watch};

use super::metrics::Metrics;
use super::security::error;
use crate::plan::Destination;
use crate::publish::Output;
use crate::publish::stats::Stats;
use crate::sink::Sink;
use crate::site::{Building, Cell};
use crate::source::{Source, SourceContext};

use crate::event::{FLOOR_NAME_RULE, Inbound, RouteRequest, valid_floor_name};

/// Fixes kept per device for its trail.
pub(crate) const TRAIL: usize = 20;
/// Pages streaming at once.
const MAX_STREAMS: usize = 32;
/// Events queued per page before it is resynchronised with a snapshot.
const STREAM_QUEUE: usize = 256;
/// Route requests from pages waiting for the runtime.
const REQUEST_QUEUE: usize = 64;

/// One fix as the page draws it.
#[derive(Clone, Debug, Serialize)]
struct FixView {
    #[serde(serialize_with = "as_str")]
    device: Arc<str>,
    t: f64,
    /// None: an unknown location (shown as such).
    cell: Option<Cell>,
    /// The floor's name; none when it is unknown.
    floor: Option<String>,
    confidence: f32,
    place: Option<String>,
    /// The recent located cells, oldest first (snapshots only).
    #[serde(skip_serializing_if = "Option::is_none")]
    trail: Option<Vec<Cell>>,
}

struct Device {
    last: FixView,
    trail: VecDeque<Cell>,
}

#[derive(Default)]
struct Tables {
    devices: HashMap<Arc<str>, Device>,
    /// The last route reply and guidance message of each device (JSON as on MQTT).
    routes: HashMap<Arc<str>, serde_json::Value>,
    guidance: HashMap<Arc<str>, serde_json::Value>,
    stats: Option<serde_json::Value>,
    /// The last list of beacons heard, for the site editor to offer.
    heard: Option<serde_json::Value>,
    /// Fixes not yet sent, and devices forgotten since the last batch.
    pending: Vec<FixView>,
    forgotten: Vec<Arc<str>>,
    /// When the oldest pending fix was taken (ms since the epoch).
    pending_since_ms: Option<f64>,
}

/// What became of the reloads so far: how many there were, and why the
/// last was refused if it was.
#[derive(Clone, Debug, Default)]
pub(super) struct Reloaded {
    pub count: u64,
    pub refused: Option<String>,
}

/// What the pages stream from; shared by the sink, the source and the server.
pub struct Live {
    /// The building the map shows, replaced on reloads.
    pub(super) building: super::BuildingCell,
    tables: Mutex<Tables>,
    events: broadcast::Sender<Arc<Frame>>,
    streams: AtomicUsize,
    max_devices: usize,
    requests: mpsc::Sender<Inbound>,
    request_ids: AtomicU64,
    pub(super) metrics: Metrics,
    pub(super) reloaded: watch::Sender<Reloaded>,
}

/// One event for the pages, encoded once for all of them.
#[derive(Debug)]
struct Frame {
    name: &'static str,
    data: String,
}

impl Live {
    /// The live state, the sink that feeds it and the source that carries
    /// the pages' requests.
    pub(crate) fn new(
        building: Arc<Building>,
        max_devices: usize,
        latency: Arc<crate::latency::Latency>,
    ) -> (Arc<Live>, WebSink, WebSource) {
        let (events, _) = broadcast::channel(STREAM_QUEUE);
        let (requests, rx) = mpsc::channel(REQUEST_QUEUE);
        let live = Arc::new(Live {
            building: Arc::new(std::sync::RwLock::new(building)),
            tables: Mutex::new(Tables::default()),
            events,
            streams: AtomicUsize::new(0),
            max_devices: max_devices.max(1),
            requests,
            request_ids: AtomicU64::new(0),
            metrics: Metrics::new(latency),
            reloaded: watch::Sender::new(Reloaded::default()),
        });
        (
            live.clone(),
            WebSink { live: live.clone() },
            WebSource { requests: rx },
        )
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Tables> {
        self.tables.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn broadcast(&self, name: &'static str, data: String) {
        // No page listening is not an error.
        let _ = self.events.send(Arc::new(Frame { name, data }));
    }

    /// Takes outputs from the runtime.
    fn take(&self, outputs: &[Output]) {
        let mut t = self.lock();
        for output in outputs {
            match output {
                Output::Location(l) => {
                    t.pending_since_ms.get_or_insert_with(unix_ms);
                    let device: Arc<str> = l.device.as_str().into();
                    if !t.devices.contains_key(&device) && t.devices.len() >= self.max_devices {
                        let oldest = t
                            .devices
                            .iter()
                            .min_by(|a, b| a.1.last.t.total_cmp(&b.1.last.t))
                            .map(|(id, _)| id.clone());
                        if let Some(id) = oldest {
                            t.forget(&id);
                        }
                    }
                    let view = FixView {
                        device: device.clone(),
                        t: l.t,
                        cell: l.cell,
                        floor: l.floor.as_ref().map(|f| f.name.clone()),
                        confidence: l.confidence,
                        place: l.place.clone(),
                        trail: None,
                    };
                    let entry = t.devices.entry(device).or_insert_with(|| Device {
                        last: view.clone(),
                        trail: VecDeque::with_capacity(TRAIL),
                    });
                    if let Some(cell) = l.cell
                        && entry.trail.back() != Some(&cell)
                    {
                        if entry.trail.len() == TRAIL {
                            entry.trail.pop_front();
                        }
                        entry.trail.push_back(cell);
                    }
                    entry.last = view.clone();
                    t.pending.push(view);
                }
                Output::Route(reply) => {
                    let json = serde_json::to_value(reply).expect("plain data serializes");
                    let device: Arc<str> = reply.device.as_str().into();
                    if t.routes.len() < self.max_devices || t.routes.contains_key(&device) {
                        t.routes.insert(device, json.clone());
                    }
                    self.broadcast("path", json.to_string());
                }
                Output::Guidance(g) => {
                    let json = serde_json::to_value(g).expect("plain data serializes");
                    if t.guidance.len() < self.max_devices
                        || t.guidance.contains_key(g.device.as_str())
                    {
                        t.guidance.insert(g.device.as_str().into(), json.clone());
                    }
                    self.broadcast("guidance", json.to_string());
                }
                Output::Forgotten(device) => t.forget(device),
                Output::Stats(stats) => {
                    let json = serde_json::to_value(stats).expect("plain data serializes");
                    self.metrics.set_stats(stats);
                    self.broadcast("status", json.to_string());
                    t.stats = Some(json);
                }
                Output::HeardReport(heard) => {
                    t.heard = Some(serde_json::to_value(heard).expect("plain data serializes"));
                }
                _ => {}
            }
        }
    }

    /// Sends the fixes taken since the last batch, in one event.
    fn send_batch(&self) {
        let (fixes, forgotten, taken_ms) = {
            let mut t = self.lock();
            (
                std::mem::take(&mut t.pending),
                std::mem::take(&mut t.forgotten),
                t.pending_since_ms.take(),
            )
        };
        if !forgotten.is_empty() {
            self.broadcast(
                "forget",
                serde_json::to_string(&forgotten.iter().map(|d| &**d).collect::<Vec<&str>>())
                    .expect("strings"),
            );
        }
        if fixes.is_empty() {
            return;
        }
        // `taken_ms`: when the oldest of these fixes reached this sink, so
        // the page measures fix to screen for the slowest fix of a batch.
        let data = serde_json::json!({
            "sent_ms": unix_ms(),
            "taken_ms": taken_ms,
            "fixes": fixes,
        })
        .to_string();
        self.metrics.batches.fetch_add(1, Ordering::Relaxed);
        self.broadcast("fixes", data);
    }

    /// Everything a page needs when it connects (or falls behind).
    fn snapshot(&self) -> String {
        let t = self.lock();
        let devices: Vec<FixView> = t
            .devices
            .values()
            .map(|d| FixView {
                trail: Some(d.trail.iter().copied().collect()),
                ..d.last.clone()
            })
            .collect();
        serde_json::json!({
            "sent_ms": unix_ms(),
            "devices": devices,
            "routes": t.routes.values().collect::<Vec<_>>(),
            "guidance": t.guidance.values().collect::<Vec<_>>(),
            "stats": t.stats,
        })
        .to_string()
    }

    pub(super) fn streams(&self) -> usize {
        self.streams.load(Ordering::Relaxed)
    }
}

impl Tables {
    fn forget(&mut self, device: &Arc<str>) {
        if self.devices.remove(device).is_some() {
            self.forgotten.push(device.clone());
        }
        self.routes.remove(device);
        self.guidance.remove(device);
        self.pending.retain(|f| f.device != *device);
    }
}

fn as_str<S: serde::Serializer>(s: &Arc<str>, out: S) -> Result<S::Ok, S::Error> {
    out.serialize_str(s)
}

fn unix_ms() -> f64 {
    crate::source::unix_now() * 1000.0
}

/// The web UI as a sink of the gateway.
pub(crate) struct WebSink {
    live: Arc<Live>,
}

impl Sink for WebSink {
    fn name(&self) -> &'static str {
        "web"
    }

    fn send(&mut self, outputs: &[Output]) -> anyhow::Result<()> {
        self.live.take(outputs);
        Ok(())
    }

    fn flush(&mut self) -> BoxFuture<'_, anyhow::Result<()>> {
        self.live.send_batch();
        Box::pin(std::future::ready(Ok(())))
    }

    fn tick(&mut self, _now: f64) {
        self.live.send_batch();
    }

    fn counters(&mut self, stats: &Stats) {
        self.live.metrics.set_stats(stats);
    }

    fn reload(&mut self, building: &Building) {
        *self
            .live
            .building
            .write()
            .unwrap_or_else(|e| e.into_inner()) = Arc::new(building.clone());
        self.live.broadcast("site", String::from("{}"));
        self.live.reloaded.send_modify(|r| {
            r.count += 1;
            r.refused = None;
        });
    }

    fn reload_refused(&mut self, why: &str) {
        self.live.reloaded.send_modify(|r| {
            r.count += 1;
            r.refused = Some(why.to_owned());
        });
    }

    fn shutdown(self: Box<Self>) -> BoxFuture<'static, anyhow::Result<()>> {
        self.live.send_batch();
        Box::pin(std::future::ready(Ok(())))
    }
}

/// The pages' route requests as a source of the gateway.
pub(crate) struct WebSource {
    requests: mpsc::Receiver<Inbound>,
}

impl Source for WebSource {
    fn name(&self) -> &'static str {
        "web"
    }

    fn run(self: Box<Self>, cx: SourceContext) -> BoxFuture<'static, anyhow::Result<()>> {
        let mut requests = self.requests;
        let mut shutdown = cx.shutdown.clone();
        Box::pin(async move {
            loop {
                tokio::select! {
                    request = requests.recv() => match request {
                        Some(request) => if cx.inbound(request).await.is_err() { return Ok(()) },
                        None => return Ok(()),
                    },
                    () = shutdown.recv() => return Ok(()),
                }
            }
        })
    }
}

/// `GET /api/heard`: the beacons the gateway heard most (the retained
/// `heard` payload), so the site editor can offer the unknown ones to place;
/// 204 before the first list.
pub(super) async fn heard(State(live): State<Arc<Live>>) -> Response {
    match live.lock().heard.clone() {
        Some(heard) => Json(heard).into_response(),
        None => StatusCode::NO_CONTENT.into_response(),
    }
}

/// `GET /api/live`: the event stream of one page.
pub(super) async fn stream(State(live): State<Arc<Live>>) -> Response {
    if live.streams.fetch_add(1, Ordering::Relaxed) >= MAX_STREAMS {
        live.streams.fetch_sub(1, Ordering::Relaxed);
        return error(
            StatusCode::SERVICE_UNAVAILABLE,
            "overloaded",
            format!("{MAX_STREAMS} pages are watching already; try again later"),
        );
    }
    // Subscribed before the snapshot is taken, so nothing falls between.
    let rx = live.events.subscribe();
    let first = SseEvent::default().event("snapshot").data(live.snapshot());
    let guard = StreamGuard(live.clone());
    let events = stream::unfold(
        (rx, guard, Some(first)),
        |(mut rx, guard, first)| async move {
            if let Some(first) = first {
                return Some((Ok::<_, Infallible>(first), (rx, guard, None)));
            }
            let event = match rx.recv().await {
                Ok(frame) => SseEvent::default().event(frame.name).data(&frame.data),
                // Fell behind: start again from what is now.
                Err(broadcast::error::RecvError::Lagged(_)) => {
                    rx = rx.resubscribe();
                    SseEvent::default()
                        .event("snapshot")
                        .data(guard.0.snapshot())
                }
                Err(broadcast::error::RecvError::Closed) => return None,
            };
            Some((Ok(event), (rx, guard, None)))
        },
    );
    Sse::new(events)
        .keep_alive(KeepAlive::default())
        .into_response()
}

/// Counts a page's stream until it ends.
struct StreamGuard(Arc<Live>);

impl Drop for StreamGuard {
    fn drop(&mut self) {
        self.0.streams.fetch_sub(1, Ordering::Relaxed);
    }
}

/// `POST /api/route`: a route request from a page.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct RouteBody {
    device: String,
    to: Destination,
    #[serde(default)]
    floor: Option<String>,
    #[serde(default)]
    profile: Option<String>,
}

pub(super) async fn route(State(live): State<Arc<Live>>, Json(body): Json<RouteBody>) -> Response {
    if !crate::sighting::valid_device_id(&body.device) {
        return error(
            StatusCode::BAD_REQUEST,
            "invalid_request",
            "not a device id (1 to 128 bytes, no '+', '#', '/' or control characters)",
        );
    }
    if !body.floor.as_deref().is_none_or(valid_floor_name) {
        return error(StatusCode::BAD_REQUEST, "invalid_request", FLOOR_NAME_RULE);
    }
    let n = live.request_ids.fetch_add(1, Ordering::Relaxed) + 1;
    let request_id = format!("web-{n}");
    let request = Inbound::Route(RouteRequest {
        t: crate::source::unix_now(),
        device: body.device,
        to: body.to,
        floor: body.floor,
        profile: body.profile,
        request_id: Some(request_id.clone()),
    });
    match live.requests.try_send(request) {
        Ok(()) => Json(serde_json::json!({ "request_id": request_id })).into_response(),
        Err(_) => error(
            StatusCode::SERVICE_UNAVAILABLE,
            "overloaded",
            "too many route requests from the web waiting; try again in a second",
        ),
    }
}
