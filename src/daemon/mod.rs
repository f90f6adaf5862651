//! The runtime every mode of the gateway runs: sources feed one
//! [`Pipeline`], and what it (and the runtime) produce goes to every sink.
//!
//! ```text
//! sources ──own events──▶ ┌─────────┐            ┌──▶ mqtt (broker, Home Assistant)
//! (ble, capture,          │ runtime │──Outputs──▶├──▶ jsonl (--print, --out)
//!  simulation, mqtt)──▶   │pipeline │            ├──▶ store (learning store)
//!        others' messages └─────────┘            └──▶ score (replay --score)
//! ```
//!
//! [`run`] is the whole life of the gateway in the shape of tokio's
//! mini-redis: it is given its sources, its sinks, a `shutdown` future and a
//! stream of reload requests, and knows nothing of signals (`cli/run.rs` turns
//! SIGTERM/SIGINT into `shutdown` and SIGHUP into reloads), so a test drives
//! it in-process. `gangway run` is this runtime with the radio (or a capture)
//! and the broker; `gangway replay` is the same runtime with a capture as its
//! only source and no messages from others: it ends when the capture does.
//!
//! What the runtime owns:
//! - admission of what others send ([`admission`]): route requests wait in a
//!   bounded queue and are answered `overloaded` rather than dropped,
//!   per-device rates are limited, feedback is taken only for routes given;
//!   nothing from others is taken while a sink is backed up;
//! - reloads ([`state`]): the new config, site and pipeline are built off the
//!   event loop and swapped in whole, or refused whole;
//! - its part among the site's gateways (`[cluster]`): an edge shares what
//!   it hears and locates nothing; a locator ([`cluster`]) locates only the
//!   devices of the shards it owns, sends its heartbeats and answers the
//!   requests of shards it takes over;
//! - recalibration (`[localizer.recalibration]`, [`recalibration`]):
//!   on its schedule or on request, the survey-free model is refitted from
//!   what the store gathered, on a blocking thread, and the pipeline built
//!   with it is swapped in like a reload;
//! - the gateway's counters, summed in one place ([`Runtime::stats`]);
//! - systemd readiness, watchdog and status line (no-ops without systemd);
//! - the order of shutdown: sources stop first (a scan stops discovering),
//!   then every sink delivers what it holds.
//!
//! A bad input never stops it: every message from others becomes an output
//! or a counted refusal, and a source that fails is logged (and, in the
//! daemon, the rest keeps serving).

mod admission;
mod cluster;
pub(crate) mod recalibration;
pub mod state;

use std::future::Future;
use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{mpsc, watch};
use tokio::task::{JoinHandle, JoinSet};
use tokio::time::{Instant, MissedTickBehavior};

use admission::{Admit, Issued, PerSecond, Requests};
use state::Loaded;

use crate::locate::recalibrate::{self, Schedule};
use crate::locate::window::Orientation;
use crate::mqtt::cluster::Role;
use crate::pipeline;
use crate::plan::RouteErrorCode;
use crate::publish::stats::{
    BleStatus, HEARD_PUBLISHED, HEARD_SCHEMA, HeardReport, RecalibrationStatus, STATS_SCHEMA, Stats,
};
use crate::publish::{FeedbackRefused, Output, RouteOutcome};
use crate::sighting::Sighting;
use crate::sighting::heard::HeardBeacon;
use crate::sink::Sink;
use crate::source::unix_now;
use crate::source::{Input, Shutdown, Source, SourceContext};
use recalibration::Job;

use crate::event::{Event, Feedback, Inbound, RouteRequest};
use crate::throttle::Throttle;

/// How often a single gateway's own sightings go out to the other gateways
/// (an edge's: `[cluster] batch_s`).
const SHARE_INTERVAL: Duration = Duration::from_millis(250);
/// Own sightings an edge gathers at most before it sends them early (an
/// edge cuts them into messages per shard; a single gateway sends at most
/// one message's worth at a time).
const EDGE_PENDING_MAX: usize = 16_384;
/// How long the sources get at shutdown to stop (a scan stops discovery).
const SOURCE_STOP: Duration = Duration::from_secs(2);
/// Routes remembered for feedback.
const ISSUED_ROUTES: usize = 10_000;
/// At most one line per this period for each kind of repeated refusal.
const WARN_EVERY: Duration = Duration::from_secs(10);
/// How often a backed-up sink is checked for room again.
const BACKLOG_POLL: Duration = Duration::from_millis(5);
/// What an `overloaded` or `rate_limited` reply suggests waiting, seconds.
const RETRY_AFTER_S: f64 = 1.0;
/// Batches of own events queued at most (a radio sends one event a batch, a
/// capture up to `source::playback::BATCH`).
const EVENTS_QUEUE: usize = 32;
/// Messages from others queued at most: few, since while the runtime does
/// not take them the broker holds the rest (unacknowledged).
const INBOUND_QUEUE: usize = 16;
/// Inputs handled at most between two flushes of the sinks, under load.
const FLUSH_EVERY: usize = 16;
/// How often sinks get their periodic work done.
const TICK: Duration = Duration::from_secs(1);

/// How the runtime runs.
#[derive(Debug, Default)]
pub struct Options {
    /// The config file reloads read; without it reloads are refused.
    pub config_path: Option<PathBuf>,
    /// Publish the counters every `[mqtt] stats_interval_s` (and when the
    /// radio's state changes).
    pub stats: bool,
    /// End when every source has ended (a replay), and fail with the first
    /// source that fails; otherwise serve until `shutdown`.
    pub until_sources_end: bool,
    /// Send this gateway's own sightings to the site's other gateways
    /// ([`Output::Sightings`], advertiser orientation).
    pub share_sightings: bool,
    /// The radio's state, for the stats.
    pub radio: Option<watch::Receiver<BleStatus>>,
    /// What failed at start-up outside the pipeline (the store), listed in
    /// the stats' fallbacks.
    pub fallbacks: Vec<String>,
    /// Where to observe how long inputs take to reach the sinks.
    pub latency: Option<Arc<crate::latency::Latency>>,
    /// Requests to recalibrate now (`[localizer.recalibration]`).
    pub recalibrate: Option<mpsc::Receiver<()>>,
}

/// What a run leaves: its final counters and every beacon it heard (the
/// most heard first), for `replay` to report.
#[derive(Debug)]
pub struct Finished {
    pub stats: Stats,
    pub heard: Vec<HeardBeacon>,
}

/// Runs the gateway until `shutdown` completes (or, with
/// [`Options::until_sources_end`], until its sources are done); each item of
/// `reloads` reloads the config. Returns the final counters and what was heard.
pub async fn run(
    serving: Loaded,
    options: Options,
    sources: Vec<Box<dyn Source>>,
    sinks: Vec<Box<dyn Sink>>,
    shutdown: impl Future<Output = ()>,
    mut reloads: mpsc::Receiver<()>,
) -> anyhow::Result<Finished> {
    let mut options = options;
    let mut recalibrate_requests = options.recalibrate.take();
    let (events_tx, mut events) = mpsc::channel(EVENTS_QUEUE);
    let (inbound_tx, mut inbound) = mpsc::channel(INBOUND_QUEUE);
    let (stop_sources, sources_shutdown) = Shutdown::new();
    let mut tasks = JoinSet::new();
    for source in sources {
        let name = source.name();
        let cx = SourceContext::new(
            events_tx.clone(),
            inbound_tx.clone(),
            sources_shutdown.clone(),
        );
        tasks.spawn(async move { (name, source.run(cx).await) });
    }
    // Only the sources hold senders: a queue closes when they are all done.
    drop((events_tx, inbound_tx));

    let mut runtime = Runtime::new(serving, sinks, &options);
    let stats_every = Duration::from_secs_f64(runtime.state.config.mqtt.stats_interval_s);
    let mut stats_tick = tokio::time::interval(stats_every);
    let mut tick = tokio::time::interval(TICK);
    tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let mut share_tick = tokio::time::interval(if runtime.edge {
        Duration::from_secs_f64(runtime.state.config.cluster.batch_s)
    } else {
        SHARE_INTERVAL
    });
    share_tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let mut beat_tick = tokio::time::interval(Duration::from_secs_f64(
        runtime.state.config.cluster.heartbeat_s,
    ));
    beat_tick.set_missed_tick_behavior(MissedTickBehavior::Delay);
    // systemd's watchdog wants a ping at least every WATCHDOG_USEC; pinging
    // from this loop means a stuck loop gets the service restarted.
    let watchdog = sd_notify::watchdog_enabled();
    let mut watchdog_tick =
        tokio::time::interval(watchdog.map_or(Duration::from_secs(3600), |every| every / 2));
    let mut radio = options.radio.clone();
    let mut reload: Option<JoinHandle<anyhow::Result<Loaded>>> = None;
    let mut reload_again = false;
    let mut failed = None;
    let mut since_flush = 0;
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Ready]);
    tokio::pin!(shutdown);

    loop {
        let room = runtime.sinks.iter().all(|s| s.has_room());
        let step = tokio::select! {
            () = &mut shutdown => Step::Shutdown,
            Some(input) = events.recv() => Step::Input(input),
            // Nothing from others is taken while a sink is backed up: the
            // replies would push older messages out of its queue; the broker
            // (and the link's unacknowledged hold) keeps them meanwhile. A
            // backlog drains with the broker's acknowledgements, so poll.
            Some(input) = inbound.recv(), if room => Step::Input(input),
            () = tokio::time::sleep(BACKLOG_POLL), if !room => Step::Idle,
            // Planning is the costly part: one request per turn, so that
            // reading (and answering `overloaded`) keeps pace with the broker.
            () = std::future::ready(()), if !runtime.requests.is_empty() => Step::ServeRequest,
            _ = share_tick.tick(), if runtime.share.is_some() => Step::Share,
            _ = beat_tick.tick(), if runtime.locator.is_some() => Step::Beat,
            _ = tick.tick() => Step::Tick,
            _ = stats_tick.tick(), if options.stats => Step::Stats,
            Ok(()) = changed(&mut radio) => Step::RadioChanged,
            _ = watchdog_tick.tick(), if watchdog.is_some() => Step::Watchdog,
            Some(()) = reloads.recv() => Step::Reload,
            Some(()) = requested(&mut recalibrate_requests) => Step::Recalibrate,
            done = recalibrated(&mut runtime.recalibration) => Step::Recalibrated(Box::new(done)),
            loaded = join(&mut reload), if reload.is_some() => Step::Reloaded(Box::new(loaded)),
            Some(joined) = tasks.join_next() => Step::SourceEnded(joined),
        };
        runtime.entered = std::time::Instant::now();
        match step {
            Step::Shutdown => break,
            Step::Input(input) => runtime.input(input),
            Step::Idle => {}
            Step::ServeRequest => runtime.serve_next(),
            Step::Share => runtime.share_sightings(),
            Step::Beat => runtime.beat(),
            Step::Tick => {
                runtime.tick();
                runtime.recalibrate_if_due(false);
            }
            Step::Recalibrate => runtime.recalibrate_if_due(true),
            Step::Recalibrated(done) => runtime.recalibrated(*done),
            Step::Stats => {
                runtime.publish_stats();
                runtime.notify_status();
            }
            Step::RadioChanged => runtime.publish_stats(),
            Step::Watchdog => {
                // Fed from this loop, so a stuck loop is restarted; and not
                // fed once a sink stopped working (the MQTT link's task
                // only ends by panicking), since nothing would be served.
                if let Some(dead) = runtime.sinks.iter().find(|s| !s.is_alive()) {
                    tracing::error!(
                        sink = dead.name(),
                        "a sink stopped working; no more watchdog pings, so systemd restarts the gateway"
                    );
                } else {
                    let _ = sd_notify::notify(&[sd_notify::NotifyState::Watchdog]);
                }
                runtime.notify_status();
            }
            Step::Reload => match (&reload, &options.config_path) {
                (Some(_), _) => reload_again = true,
                (None, Some(path)) => reload = Some(runtime.start_reload(path.clone())),
                (None, None) => tracing::warn!("reload ignored: no config file to reload"),
            },
            Step::Reloaded(loaded) => {
                reload = None;
                runtime.swap(*loaded);
                if std::mem::take(&mut reload_again)
                    && let Some(path) = &options.config_path
                {
                    reload = Some(runtime.start_reload(path.clone()));
                }
            }
            Step::SourceEnded(joined) => {
                // Everything the source sent is queued by now: take it first.
                while let Ok(input) = events.try_recv() {
                    runtime.input(input);
                    runtime.dispatch()?;
                }
                let (name, result) = match joined {
                    Ok(ended) => ended,
                    Err(e) => (
                        "(panicked)",
                        Err(anyhow::anyhow!("the source task failed: {e}")),
                    ),
                };
                match result {
                    Ok(()) => {
                        tracing::info!(source = name, "source done");
                        // Its devices will not be heard again: close their windows.
                        runtime.finish();
                    }
                    Err(e) if options.until_sources_end => {
                        failed = Some(e.context(format!("{name} source")));
                        break;
                    }
                    Err(e) => tracing::error!("{name} source stopped: {e:#}; still serving"),
                }
                if options.until_sources_end && tasks.is_empty() {
                    break;
                }
            }
        }
        runtime.dispatch()?;
        since_flush += 1;
        if (events.is_empty() && inbound.is_empty()) || since_flush >= FLUSH_EVERY {
            runtime.flush().await?;
            since_flush = 0;
        }
    }

    if failed.is_none() && !options.until_sources_end {
        tracing::info!("shutting down: sources stop, then every sink sends what it holds");
    }
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
    stop_sources.trigger();
    // A source waiting for room in a queue sees it closed and stops.
    drop((events, inbound));
    let stopped = async {
        while let Some(joined) = tasks.join_next().await {
            if let Ok((name, Err(e))) = joined {
                tracing::warn!("{name} source: {e:#}");
            }
        }
    };
    if tokio::time::timeout(SOURCE_STOP, stopped).await.is_err() {
        tracing::warn!("a source did not stop in time; stopping it now");
        tasks.abort_all();
    }
    runtime.share_sightings();
    if let Some(locator) = &mut runtime.locator {
        locator.leave(unix_now(), &mut runtime.out);
    }
    if options.stats {
        runtime.publish_stats();
    }
    runtime.dispatch()?;
    runtime.flush().await?;
    let finished = Finished {
        stats: runtime.stats(),
        heard: runtime.state.pipeline.heard(usize::MAX),
    };
    for sink in runtime.sinks {
        let name = sink.name();
        if let Err(e) = sink.shutdown().await {
            failed.get_or_insert(e.context(format!("{name} sink")));
        }
    }
    match failed {
        Some(e) => Err(e),
        None => Ok(finished),
    }
}

/// What one turn of the loop does.
enum Step {
    Shutdown,
    Input(Input),
    Idle,
    ServeRequest,
    Share,
    Beat,
    Tick,
    Stats,
    RadioChanged,
    Watchdog,
    Reload,
    /// Boxed: a loaded pipeline is large, the other steps small.
    Reloaded(Box<anyhow::Result<Loaded>>),
    Recalibrate,
    /// Boxed like `Reloaded`.
    Recalibrated(Box<RecalibrationDone>),
    SourceEnded(Result<(&'static str, anyhow::Result<()>), tokio::task::JoinError>),
}

async fn changed(
    radio: &mut Option<watch::Receiver<BleStatus>>,
) -> Result<(), watch::error::RecvError> {
    match radio {
        Some(radio) => radio.changed().await,
        None => std::future::pending().await,
    }
}

async fn requested(requests: &mut Option<mpsc::Receiver<()>>) -> Option<()> {
    match requests {
        Some(requests) => requests.recv().await,
        None => std::future::pending().await,
    }
}

/// The end of the running recalibration, if one runs.
async fn recalibrated(recalibration: &mut Option<Recalibration>) -> RecalibrationDone {
    match recalibration.as_mut().and_then(|r| r.task.as_mut()) {
        Some(task) => {
            let done = task
                .await
                .unwrap_or_else(|e| Err(anyhow::anyhow!("the recalibration failed: {e}")));
            if let Some(r) = recalibration.as_mut() {
                r.task = None;
                r.schedule.finished();
            }
            done
        }
        None => std::future::pending().await,
    }
}

/// A finished recalibration: each floor recalibrated, and the state that
/// serves them.
type RecalibrationDone = anyhow::Result<(recalibration::Ran, Loaded)>;

/// Recalibration of the survey-free model from what the store gathered.
struct Recalibration {
    schedule: Schedule,
    /// Windows heard since start.
    heard: u64,
    task: Option<JoinHandle<RecalibrationDone>>,
    /// What the stats say of the runs.
    status: RecalibrationStatus,
}

impl Recalibration {
    /// When `state`'s config recalibrates what it serves.
    fn new(state: &Loaded) -> Option<Recalibration> {
        let localizer = &state.config.localizer;
        if !localizer.recalibration.enabled {
            return None;
        }
        if !recalibrate::applies(localizer) {
            tracing::warn!(
                method = localizer.method.name(),
                "[localizer.recalibration] is on, but the localizer is surveyed: \
                 what is heard is kept, nothing is recalibrated"
            );
            return None;
        }
        Some(Recalibration {
            schedule: Schedule::new(&localizer.recalibration, unix_now()),
            heard: 0,
            task: None,
            status: RecalibrationStatus::default(),
        })
    }
}

async fn join(reload: &mut Option<JoinHandle<anyhow::Result<Loaded>>>) -> anyhow::Result<Loaded> {
    match reload {
        Some(task) => task
            .await
            .unwrap_or_else(|e| Err(anyhow::anyhow!("the reload failed: {e}"))),
        None => std::future::pending().await,
    }
}

/// Counters the runtime keeps beside the pipeline's.
#[derive(Debug, Default)]
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
}

/// Repeated warnings, each logged at most once per [`WARN_EVERY`].
struct Throttles {
    overloaded: Throttle,
    rate_limited: Throttle,
    rejected: Throttle,
}

/// The runtime's state between two turns of its loop.
struct Runtime {
    state: Loaded,
    sinks: Vec<Box<dyn Sink>>,
    /// What the current turn produced, for the sinks.
    out: Vec<Output>,
    /// Counters of the pipelines replaced by reloads.
    retired: pipeline::Stats,
    counters: Counters,
    requests: Requests,
    scan_rate: PerSecond,
    /// All scans together (one key).
    scan_total: PerSecond,
    request_rate: PerSecond,
    issued: Issued,
    throttles: Throttles,
    /// Own sightings waiting to be shared (advertiser orientation only).
    share: Option<Vec<Sighting>>,
    /// An edge (`[cluster] role = "edge"`) shares what it hears and locates
    /// nothing.
    edge: bool,
    /// A locator's membership (`[cluster] role = "locator"`).
    locator: Option<cluster::Locator>,
    radio: Option<watch::Receiver<BleStatus>>,
    fallbacks: Vec<String>,
    /// The last status line given to systemd.
    status: String,
    started: Instant,
    latency: Option<Arc<crate::latency::Latency>>,
    /// When the input of this turn entered the runtime.
    entered: std::time::Instant,
    recalibration: Option<Recalibration>,
}

impl Runtime {
    fn new(state: Loaded, sinks: Vec<Box<dyn Sink>>, options: &Options) -> Runtime {
        let limits = state.config.limits.clone();
        Runtime {
            sinks,
            out: Vec::new(),
            retired: pipeline::Stats::default(),
            counters: Counters::default(),
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
            share: options.share_sightings.then(Vec::new),
            edge: state.config.cluster.role == Role::Edge,
            locator: (state.config.cluster.role == Role::Locator).then(|| {
                cluster::Locator::new(&state.config.cluster, &state.config.gateway_id, unix_now())
            }),
            radio: options.radio.clone(),
            fallbacks: options.fallbacks.clone(),
            status: String::new(),
            started: Instant::now(),
            latency: options.latency.clone(),
            entered: std::time::Instant::now(),
            recalibration: Recalibration::new(&state),
            state,
        }
    }

    fn input(&mut self, input: Input) {
        match input {
            Input::Events(events) => {
                for event in &events {
                    self.own_event(event);
                }
            }
            Input::Inbound(message) => self.inbound(message),
        }
    }

    /// A sighting (or scripted request, or truth) from this gateway's own source.
    fn own_event(&mut self, event: &Event) {
        if let (Some(batch), Event::Advert(s)) = (&mut self.share, event)
            && *s.observer == *self.state.config.gateway_id
        {
            batch.push(s.clone());
            let most = if self.edge {
                EDGE_PENDING_MAX
            } else {
                crate::mqtt::sightings::MAX_PER_MESSAGE
            };
            if batch.len() >= most {
                self.share_sightings();
            }
        }
        if !self.edge {
            self.state.pipeline.handle(event, &mut self.out);
        }
    }

    fn inbound(&mut self, message: Inbound) {
        let now = unix_now();
        match message {
            Inbound::Route(request) => {
                let request = match &mut self.locator {
                    Some(locator) => match locator.route(request, now) {
                        Some(request) => request,
                        None => return,
                    },
                    None => request,
                };
                self.admit(request, now);
            }
            // Another locator's device: its owner answers.
            Inbound::BadRoute { device, .. }
            | Inbound::Cancel { device, .. }
            | Inbound::Feedback(Feedback { device, .. })
                if self.locator.as_ref().is_some_and(|l| !l.owns(&device)) => {}
            Inbound::BadRoute {
                device,
                request_id,
                code,
                message,
            } => {
                if let Some(more) = self.throttles.rejected.ready() {
                    tracing::warn!(
                        device,
                        code = code.as_str(),
                        not_logged = more,
                        "refused route request: {message}"
                    );
                }
                if code == RouteErrorCode::PayloadTooLarge {
                    self.counters.oversized += 1;
                }
                let reply = self
                    .state
                    .pipeline
                    .reject(&device, request_id, now, code, message);
                self.out.push(Output::Route(Box::new(reply)));
            }
            Inbound::Cancel { device, t } => self.state.pipeline.cancel(&device, t, &mut self.out),
            Inbound::Feedback(feedback) => self.feedback(feedback),
            Inbound::Scan(scan) => {
                let pipeline = &mut self.state.pipeline;
                if pipeline.orientation() != Orientation::Observer {
                    self.counters.rejected += 1;
                    if let Some(more) = self.throttles.rejected.ready() {
                        tracing::warn!(
                            not_logged = more,
                            "phone scan ignored: this gateway locates tags ([window] orientation = \
                             \"advertiser\"), and a phone's scan needs orientation = \"observer\""
                        );
                    }
                    return;
                }
                if let Some(device) = scan.first().map(|s| s.observer.clone())
                    && !(self.scan_total.allow("", now) && self.scan_rate.allow(&device, now))
                {
                    self.counters.rate_limited += 1;
                    if let Some(more) = self.throttles.rate_limited.ready() {
                        tracing::warn!(%device, not_logged = more, "phone scans over [limits] scans_per_s or scans_per_device_per_s dropped");
                    }
                    return;
                }
                self.counters.scans += 1;
                for s in scan {
                    pipeline.handle(&Event::Advert(s), &mut self.out);
                }
            }
            // An edge passes its receivers' sightings on.
            Inbound::Shared(shared) if self.edge => {
                if let Some(batch) = &mut self.share {
                    batch.extend(shared);
                    if batch.len() >= EDGE_PENDING_MAX {
                        self.share_sightings();
                    }
                }
            }
            Inbound::Shared(shared) => {
                self.counters.shared_in += shared.len() as u64;
                for s in shared {
                    // Sightings of a shard just handed over may still come.
                    if let Some(locator) = &self.locator
                        && !locator.owns(&s.advertiser.device_id())
                    {
                        continue;
                    }
                    self.state.pipeline.handle(&Event::Advert(s), &mut self.out);
                }
            }
            Inbound::Beat(beat) => {
                let Some(locator) = &mut self.locator else {
                    return;
                };
                match locator.heard(&beat, now, &mut self.out) {
                    Ok(requests) => {
                        for request in requests {
                            self.admit(request, now);
                        }
                    }
                    Err(()) => self.counters.rejected += 1,
                }
            }
            Inbound::Refused { oversized } => {
                self.counters.rejected += 1;
                self.counters.oversized += u64::from(oversized);
            }
        }
    }

    /// A route request into the queue, or refused (`rate_limited`,
    /// `overloaded`).
    fn admit(&mut self, request: RouteRequest, now: f64) {
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

    /// A locator's heartbeat and what follows from time passing: shards
    /// taken over from a locator that went away bring their held requests.
    fn beat(&mut self) {
        let now = unix_now();
        if let Some(locator) = &mut self.locator {
            for request in locator.beat(now, &mut self.out) {
                self.admit(request, now);
            }
        }
    }

    /// Plans the next waiting route request (or answers `overloaded` if it
    /// waited too long).
    fn serve_next(&mut self) {
        if let Some(received) = self.requests.next_received() {
            self.entered = received;
        }
        match self.requests.take_next() {
            // Through the pipeline's event path, so a served route also
            // starts the device's guidance session.
            Some(Admit::Serve(request)) => self
                .state
                .pipeline
                .handle(&Event::Request(request), &mut self.out),
            Some(Admit::Overloaded(request, why)) => {
                self.refuse_route(&request, RouteErrorCode::Overloaded, why)
            }
            None => {}
        }
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
        let mut reply = self.state.pipeline.reject(
            &request.device,
            request.request_id.clone(),
            request.t,
            code,
            message,
        );
        if let RouteOutcome::Error { error } = &mut reply.outcome {
            error.retry_after_s = Some(RETRY_AFTER_S);
        }
        self.out.push(Output::Route(Box::new(reply)));
    }

    /// Feedback is taken once for a route this gateway gave; anything else
    /// is refused with an error on `…/feedback/error`.
    fn feedback(&mut self, feedback: Feedback) {
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
            self.out
                .push(Output::FeedbackRefused(FeedbackRefused::new(&feedback)));
            return;
        }
        self.counters.feedback += 1;
        tracing::info!(
            device = feedback.device,
            request_id = feedback.request_id,
            score = feedback.score,
            "route feedback"
        );
        self.out.push(Output::Feedback(feedback));
    }

    /// Closes every open window (a capture ended).
    fn finish(&mut self) {
        self.state.pipeline.finish(&mut self.out);
    }

    /// Hands what this turn produced to every sink, noting the routes given
    /// (feedback is taken only for those).
    fn dispatch(&mut self) -> anyhow::Result<()> {
        if let Some(locator) = &self.locator {
            self.out.retain(|o| locator.keeps(o));
        }
        if self.out.is_empty() {
            return Ok(());
        }
        for output in &self.out {
            if let Output::Route(reply) = output
                && let (RouteOutcome::Route(_) | RouteOutcome::Floors(_), Some(id)) =
                    (&reply.outcome, &reply.request_id)
            {
                self.issued.insert(&reply.device, id);
            }
            if let (Output::Heard(_), Some(r)) = (output, &mut self.recalibration) {
                r.heard += 1;
            }
        }
        if let Some(latency) = &self.latency {
            let took = self.entered.elapsed();
            for output in &self.out {
                match output {
                    Output::Location(_) => latency.observe_fix(took),
                    Output::Route(reply) if matches!(reply.outcome, RouteOutcome::Route(_)) => {
                        latency.observe_route(took)
                    }
                    _ => {}
                }
            }
        }
        for sink in &mut self.sinks {
            sink.send(&self.out)
                .map_err(|e| e.context(format!("{} sink", sink.name())))?;
        }
        self.out.clear();
        Ok(())
    }

    async fn flush(&mut self) -> anyhow::Result<()> {
        for sink in &mut self.sinks {
            let name = sink.name();
            sink.flush()
                .await
                .map_err(|e| e.context(format!("{name} sink")))?;
        }
        Ok(())
    }

    fn tick(&mut self) {
        let now = unix_now();
        for sink in &mut self.sinks {
            sink.tick(now);
        }
        let stats = self.stats();
        for sink in &mut self.sinks {
            sink.counters(&stats);
        }
    }

    /// Sends the own sightings gathered since the last time.
    fn share_sightings(&mut self) {
        if let Some(batch) = &mut self.share
            && !batch.is_empty()
        {
            self.counters.shared_out += batch.len() as u64;
            self.out.push(Output::Sightings(std::mem::take(batch)));
        }
    }

    /// The gateway's counters: the pipeline's (with those of the pipelines
    /// replaced by reloads), the runtime's, the radio's and every sink's.
    fn stats(&self) -> Stats {
        let mut p = self.state.pipeline.stats();
        p += self.retired;
        let c = &self.counters;
        let ble = self
            .radio
            .as_ref()
            .map(|r| r.borrow().clone())
            .unwrap_or_default();
        let mut fallbacks = self.state.fallbacks.clone();
        fallbacks.extend(self.fallbacks.iter().cloned());
        let heard = self.state.pipeline.heard_counts();
        let mut stats = Stats {
            schema: STATS_SCHEMA,
            gateway: self.state.config.gateway_id.clone(),
            t: unix_now(),
            uptime_s: self.started.elapsed().as_secs_f64(),
            sightings: p.sightings,
            sightings_ignored: p.sightings_ignored,
            fixes: p.fixes,
            requests: p.requests,
            routes: p.routes,
            request_errors: p.request_errors,
            route_line_fallbacks: p.route_line_fallbacks,
            bad_device_ids: p.bad_device_ids,
            evicted_devices: p.evicted_devices,
            evicted_windows: p.evicted_windows,
            feedback: c.feedback,
            scans: c.scans,
            shared_in: c.shared_in,
            shared_out: c.shared_out,
            rejected_messages: c.rejected,
            oversized_messages: c.oversized,
            overloaded: c.overloaded,
            rate_limited: c.rate_limited,
            feedback_refused: c.feedback_refused,
            reloads: c.reloads,
            reload_failures: c.reload_failures,
            windows: self.state.pipeline.windows_open() as u64,
            tracked: self.state.pipeline.tracked() as u64,
            pending_requests: self.requests.len() as u64,
            heard: heard.heard as u64,
            heard_unknown: heard.unknown as u64,
            scan_restarts: ble.scan_restarts,
            ble,
            site: self.state.building.name.clone(),
            site_hash: self.state.building.map_hash(),
            fallbacks,
            recalibration: self.recalibration.as_ref().map(|r| r.status.clone()),
            ..Stats::default()
        };
        for sink in &self.sinks {
            sink.report(&mut stats);
        }
        stats
    }

    /// Publishes the counters, and before them the beacons heard most.
    fn publish_stats(&mut self) {
        let stats = self.stats();
        self.out.push(Output::HeardReport(Box::new(HeardReport {
            schema: HEARD_SCHEMA,
            gateway: stats.gateway.clone(),
            t: stats.t,
            heard: stats.heard,
            heard_unknown: stats.heard_unknown,
            forgotten: self.state.pipeline.heard_counts().forgotten,
            beacons: self.state.pipeline.heard(HEARD_PUBLISHED),
        })));
        self.out.push(Output::Stats(Box::new(stats)));
    }

    /// Tells systemd (`systemctl status`) how the gateway is doing, when
    /// that changed.
    fn notify_status(&mut self) {
        let mut parts: Vec<String> = self.sinks.iter().filter_map(|s| s.status()).collect();
        parts.push(format!(
            "{} devices tracked, {} route requests waiting",
            self.state.pipeline.tracked(),
            self.requests.len()
        ));
        let status = parts.join("; ");
        if status != self.status {
            let _ = sd_notify::notify(&[sd_notify::NotifyState::Status(&status)]);
            self.status = status;
        }
    }

    /// Starts loading the config anew, off the event loop (models take a
    /// while to load); the gateway serves from the old state meanwhile.
    /// Starts a recalibration on a blocking thread when one is due (or,
    /// with `now`, asked for).
    fn recalibrate_if_due(&mut self, asked: bool) {
        let Some(r) = &mut self.recalibration else {
            if asked {
                tracing::warn!(
                    "recalibration asked for, but [localizer.recalibration] is off \
                     (or the localizer is surveyed)"
                );
            }
            return;
        };
        if asked {
            r.schedule.request();
        }
        let now = unix_now();
        if !r.schedule.due(now, r.heard) {
            return;
        }
        r.schedule.started(now, r.heard);
        let (config, building) = (self.state.config.clone(), self.state.building.clone());
        let jobs = Job::of_floors(
            &building,
            config.window.orientation,
            &config.localizer,
            &config.tracker,
            &config.store.resolved_path(),
        );
        tracing::info!(
            heard = r.heard,
            "recalibrating the radio model from what was heard"
        );
        r.task = Some(tokio::task::spawn_blocking(move || {
            let ran = recalibration::run_floors(&jobs)?;
            let loaded = state::recalibrated(&config, &building, &ran.done)?;
            Ok((ran, loaded))
        }));
    }

    /// A recalibration ended: its pipeline is swapped in like a reload.
    fn recalibrated(&mut self, done: RecalibrationDone) {
        if let Some(r) = &mut self.recalibration {
            let ran = done
                .as_ref()
                .map(|(ran, _)| ran)
                .map_err(|e| format!("{e:#}"));
            recalibration::record(&mut r.status, ran, unix_now());
        }
        match done {
            Ok((ran, loaded)) => {
                for done in &ran.done {
                    // What the stats say of it, and what only the log does.
                    let said = done.status();
                    tracing::info!(
                        floor = said.floor.as_deref(),
                        windows = said.windows,
                        trajectories = done.trajectories,
                        anchors = said.anchors,
                        anchors_kept = said.anchors_kept,
                        held_out_windows = done.held_out.as_ref().map_or(0, |h| h.windows),
                        held_out_gain_per_window = said.held_out_gain_per_window.unwrap_or(0.0),
                        seconds = done.seconds,
                        file = %done.path.display(),
                        cells = said.cells_kept,
                        "recalibrated the radio model; serving it"
                    );
                }
                self.swap(Ok(loaded));
            }
            Err(e) => {
                tracing::error!("recalibration failed, serving the previous model: {e:#}");
                self.publish_stats();
            }
        }
    }

    fn start_reload(&self, path: PathBuf) -> JoinHandle<anyhow::Result<Loaded>> {
        let _ = sd_notify::notify(&[sd_notify::NotifyState::Reloading]);
        tokio::task::spawn_blocking(move || state::load(&path))
    }

    /// Swaps in a loaded state if all of it loaded and nothing in it needs
    /// a restart; otherwise keeps serving the old one.
    fn swap(&mut self, loaded: anyhow::Result<Loaded>) {
        let refused = match loaded {
            Err(e) => Some(format!("{e:#}")),
            Ok(new) => match state::restart_needed(&self.state, &new) {
                Some(why) => Some(format!("{why}; restart the gateway to apply it")),
                None => {
                    let mut old = std::mem::replace(&mut self.state, new);
                    self.retired += old.pipeline.stats();
                    let kept = old.pipeline.hand_over_to(&mut self.state.pipeline);
                    let (before, after) = (&old.config.localizer, &self.state.config.localizer);
                    if before.recalibration != after.recalibration
                        || recalibrate::applies(before) != recalibrate::applies(after)
                    {
                        self.recalibration = Recalibration::new(&self.state);
                    }
                    tracing::info!(
                        site = self.state.building.name,
                        site_hash = self.state.building.map_hash(),
                        tracks_kept = kept,
                        "reloaded config and site"
                    );
                    self.counters.reloads += 1;
                    for sink in &mut self.sinks {
                        sink.reload(&self.state.building);
                    }
                    None
                }
            },
        };
        if let Some(why) = refused {
            self.counters.reload_failures += 1;
            tracing::error!("reload refused, still serving the previous config: {why}");
            for sink in &mut self.sinks {
                sink.reload_refused(&why);
            }
        }
        self.publish_stats();
        let _ = sd_notify::notify(&[sd_notify::NotifyState::Ready]);
    }
}
