//! The connection to the broker: one task that owns it, reconnects with capped
//! exponential backoff, keeps outgoing messages in the [`OfflineQueue`] while
//! the broker is away, and redelivers what the broker had not acknowledged
//! when the connection dropped.
//!
//! Each connection attempt is a fresh rumqttc client and event loop (a
//! "session"). When a session fails, everything still pending in it is taken
//! back into the queue and the session is thrown away, so no request left in a
//! dead client's channel can be replayed twice or lost. QoS 1 delivery is
//! tracked here: a message handed to rumqttc stays ours until its PUBACK.
//!
//! On every connect the link subscribes again and sends its birth messages
//! (retained `online`, discovery configs) before the queue; the last will makes
//! the broker publish the retained `offline` if the process dies.
//!
//! The birth topics are the gateway's own, and anyone who may publish can
//! overwrite a retained message: a forged `offline` would show every Home
//! Assistant entity of the gateway unavailable, an empty config delete a
//! tracker. So the link subscribes to its birth topics too, and when one
//! carries something other than its own message (its own echo is equal) it
//! publishes its own again, at most once per [`REASSERT_EVERY`] a topic, so
//! two writers cannot make it flood the broker.
//!
//! Incoming messages are hostile. The client accepts any packet the protocol
//! allows, so no message can make it drop the connection (a broker redelivers
//! a QoS 1 message on every reconnect, so one that broke the connection would
//! break every later one too); a payload over the application limit is cut
//! off here, before it is queued for the daemon, and counted. Acknowledgements
//! are manual: a QoS 1 message is acknowledged only once the daemon's channel
//! took it, so a daemon that falls behind holds the broker back (its inflight
//! window) instead of losing what was acknowledged.

use std::collections::{BTreeMap, VecDeque};
use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use bytes::Bytes;
use foldhash::HashMap;
use rumqttc::{
    AsyncClient, ConnectionError, Event, EventLoop, LastWill, MqttOptions, Outgoing as Out, Packet,
    Publish, QoS,
};
use tokio::sync::{Notify, mpsc, oneshot};
use tokio::time::Instant;

use super::queue::{OfflineQueue, Outgoing};

/// Capacity of a session's rumqttc request channel; the link never hands over
/// more than this many unacknowledged messages at once.
const SESSION_WINDOW: usize = 256;

/// Session events handled at most in one turn of the link's loop.
const EVENT_BURST: usize = 1024;

/// Largest packet MQTT allows (a 268,435,455-byte remaining length and its
/// 5-byte fixed header). The client accepts all of them, so a big message is
/// dropped by the link and never costs the connection.
pub(crate) const MQTT_MAX_PACKET: usize = 268_435_455 + 5;

/// Largest packet the link sends: far above any payload the gateway makes, so
/// only a message that would make rumqttc fail the connection is refused.
pub(crate) const MAX_OUTGOING_PACKET: usize = 1 << 20;

/// QoS 0 messages held back while the daemon's channel is full, at most;
/// past it they are dropped and counted (QoS 1 and 2 are bounded by the
/// broker's inflight window and stay held).
const HELD_MAX: usize = 4096;

/// How often one birth topic is re-asserted at most, against someone who
/// keeps overwriting it.
const REASSERT_EVERY: Duration = Duration::from_secs(2);

/// A window over which lost connections are counted: losing the broker this
/// many times within it is logged as an error (the gateway cannot stay
/// connected), not just a warning.
const FLAP_WINDOW: Duration = Duration::from_secs(60);
const FLAP_COUNT: usize = 5;

/// What a link is set up with.
#[derive(Clone, Debug)]
pub(crate) struct LinkSettings {
    /// The broker's nodes, tried in turn: the first, and after a failure
    /// the next (`[mqtt] fallback_urls`), so a client of a clustered
    /// broker moves to another node when its node dies. Never empty.
    pub brokers: Vec<MqttOptions>,
    pub qos: QoS,
    /// `(topic, online payload, offline payload)`: retained birth and last will.
    pub status: Option<(String, String, String)>,
    /// Topic filters, each with the QoS it is subscribed at.
    pub subscriptions: Vec<(String, QoS)>,
    pub queue_max_messages: usize,
    pub queue_max_bytes: usize,
    pub reconnect_min: Duration,
    pub reconnect_max: Duration,
    /// How long [`Link::shutdown`] waits for queued and in-flight messages.
    pub shutdown_grace: Duration,
    /// Send each message at once (TCP_NODELAY): what a gateway answering
    /// requests wants. Without it the kernel gathers small messages into
    /// fewer packets while earlier ones are unacknowledged (Nagle): what a
    /// replay publishing as fast as it can wants.
    pub low_latency: bool,
    /// Capacity of the channel of received messages.
    pub inbound_capacity: usize,
    /// Received payloads larger than this reach the daemon empty, with their
    /// size, so it can refuse them (and answer a route request) without
    /// holding them.
    pub max_inbound_payload: usize,
}

/// A received message, as the daemon gets it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub(crate) struct Received {
    pub topic: String,
    /// Empty when the payload was over [`LinkSettings::max_inbound_payload`].
    pub payload: Bytes,
    /// The payload's size as received.
    pub size: usize,
}

/// Counters the link shares with whoever reports stats.
#[derive(Debug, Default)]
pub(crate) struct LinkStats {
    pub connected: AtomicBool,
    /// Successful connections after the first.
    pub reconnects: AtomicU64,
    pub connect_failures: AtomicU64,
    pub queue_depth: AtomicU64,
    pub queue_bytes: AtomicU64,
    pub queue_dropped: AtomicU64,
    pub published: AtomicU64,
    /// Received messages dropped because the consumer was behind (QoS 0 only:
    /// QoS 1 and 2 are held unacknowledged instead).
    pub inbound_dropped: AtomicU64,
    /// Outgoing messages refused because no broker would take them (a topic
    /// with a wildcard, empty, or a packet over the outgoing limit).
    pub unpublishable: AtomicU64,
    /// Connections lost after they were up.
    pub disconnects: AtomicU64,
    /// Whether the connection was lost [`FLAP_COUNT`] times within
    /// [`FLAP_WINDOW`]: the gateway cannot stay connected.
    pub flapping: AtomicBool,
    /// Messages taken in, and messages queued or in flight: with the
    /// handle's count of messages sent, what [`Link::wait_for_room`] needs.
    commands_taken: AtomicU64,
    outstanding: AtomicU64,
    /// Woken whenever the link took messages in or the broker acknowledged
    /// some, for [`Link::wait_for_room`].
    progress: Notify,
}

enum Command {
    /// Messages to publish, in order.
    Publish(Vec<Outgoing>),
    /// Replaces the birth messages sent after each connect; sends them now too
    /// when the flag is set.
    Birth(Vec<Outgoing>, bool),
    /// Drops a birth message and publishes an empty retained payload on its
    /// topic.
    ClearRetained(String),
    /// Subscribes to these filters at this QoS from now on (and on every
    /// reconnect).
    Subscribe(Vec<String>, QoS),
    /// Stops subscribing to these filters.
    Unsubscribe(Vec<String>),
    Shutdown(oneshot::Sender<()>),
}

/// A handle on the link task.
pub(crate) struct Link {
    commands: mpsc::UnboundedSender<Command>,
    stats: Arc<LinkStats>,
    task: tokio::task::JoinHandle<()>,
    qos: QoS,
    /// Messages sent to the link task.
    submitted: AtomicU64,
    queue_max_messages: usize,
}

impl Link {
    /// Starts the link task; returns the handle and the channel of received
    /// messages (on the subscribed topics).
    pub(crate) fn start(settings: LinkSettings) -> (Link, mpsc::Receiver<Received>) {
        let (commands, commands_rx) = mpsc::unbounded_channel();
        let (inbound_tx, inbound_rx) = mpsc::channel(settings.inbound_capacity.max(1));
        let stats = Arc::new(LinkStats::default());
        let qos = settings.qos;
        let queue_max_messages = settings.queue_max_messages;
        let controller = Controller::new(settings, stats.clone(), inbound_tx);
        let task = tokio::spawn(controller.run(commands_rx));
        (
            Link {
                commands,
                stats,
                task,
                qos,
                submitted: AtomicU64::new(0),
                queue_max_messages,
            },
            inbound_rx,
        )
    }

    pub(crate) fn stats(&self) -> &Arc<LinkStats> {
        &self.stats
    }

    /// Whether the link task still runs (it ends only after a shutdown, or
    /// if it panicked).
    pub(crate) fn is_alive(&self) -> bool {
        !self.task.is_finished()
    }

    /// Queues messages, in order, in one hand-over to the link task; never
    /// blocks.
    pub(crate) fn publish_batch(&self, messages: Vec<crate::topics::Message>) {
        self.publish_batch_at(messages, self.qos);
    }

    /// [`Link::publish_batch`] at `qos` rather than `[mqtt] qos`.
    pub(crate) fn publish_batch_at(&self, messages: Vec<crate::topics::Message>, qos: QoS) {
        if messages.is_empty() {
            return;
        }
        self.submitted
            .fetch_add(messages.len() as u64, Ordering::Relaxed);
        let batch = messages
            .into_iter()
            .map(|m| Outgoing {
                topic: m.topic,
                payload: m.payload,
                qos,
                retain: m.retain,
            })
            .collect();
        let _ = self.commands.send(Command::Publish(batch));
    }

    /// Waits until at most half the queue bound is waiting or in flight. A
    /// producer that must not lose messages (`replay` at full speed) calls it
    /// between publications, handing over at most [`Link::room`] at a time;
    /// the daemon does not, so that it keeps locating while the broker is
    /// away (it checks [`Link::has_room`] before taking requests instead).
    pub(crate) async fn wait_for_room(&self) {
        loop {
            let progress = self.stats.progress.notified();
            if self.has_room() {
                return;
            }
            // Woken by the link task as it takes messages in and the broker
            // acknowledges them; the timeout only guards against a wake-up
            // lost to a race with the counters.
            let _ = tokio::time::timeout(Duration::from_millis(50), progress).await;
        }
    }

    /// Whether at most half the queue bound is waiting or in flight (or the
    /// link is gone, when waiting would be forever). The daemon takes no
    /// request while it is not: replies it could not send would push older
    /// ones out of the queue, so the broker holds the requests instead.
    pub(crate) fn has_room(&self) -> bool {
        self.room() > 0
    }

    /// How many more messages fit under half the queue bound (all of them
    /// when the link is gone, and waiting would be forever).
    pub(crate) fn room(&self) -> usize {
        if self.task.is_finished() {
            return usize::MAX;
        }
        let limit = (self.queue_max_messages / 2).max(1) as u64;
        let backlog = self.submitted.load(Ordering::Relaxed)
            - self.stats.commands_taken.load(Ordering::Relaxed)
            + self.stats.outstanding.load(Ordering::Relaxed);
        limit.saturating_sub(backlog) as usize
    }

    /// Adds (or replaces, by topic) messages sent (before the queue) after
    /// every connect; with `send_now` those that are new or changed are also
    /// sent on the current connection (a reload re-states every discovery
    /// config; only what changed goes out). Costs the messages given, not
    /// the birth already kept.
    pub(crate) fn set_birth(&self, messages: &[crate::topics::Message], send_now: bool) {
        let birth = messages
            .iter()
            .map(|m| Outgoing {
                topic: m.topic.clone(),
                payload: m.payload.clone(),
                qos: self.qos,
                retain: m.retain,
            })
            .collect();
        let _ = self.commands.send(Command::Birth(birth, send_now));
    }

    /// Removes the birth message of `topic` (a device that is no longer
    /// tracked) and clears its retained message on the broker now.
    pub(crate) fn clear_retained(&self, topic: String) {
        let _ = self.commands.send(Command::ClearRetained(topic));
    }

    /// Subscribes to `filters` at `qos` now and after every reconnect (a
    /// locator's shards, as it comes to own them).
    pub(crate) fn subscribe(&self, filters: Vec<String>, qos: QoS) {
        if !filters.is_empty() {
            let _ = self.commands.send(Command::Subscribe(filters, qos));
        }
    }

    /// Stops subscribing to `filters`.
    pub(crate) fn unsubscribe(&self, filters: Vec<String>) {
        if !filters.is_empty() {
            let _ = self.commands.send(Command::Unsubscribe(filters));
        }
    }

    /// Publishes the offline status, waits (up to the grace period) until every
    /// queued and in-flight message is acknowledged, and disconnects.
    pub(crate) async fn shutdown(self) {
        let (done, wait) = oneshot::channel();
        if self.commands.send(Command::Shutdown(done)).is_ok() {
            let _ = wait.await;
        }
        let _ = self.task.await;
    }
}

enum Conn {
    /// Waiting to try again at this instant.
    Down { retry_at: Instant },
    /// A session is connecting or connected.
    Session {
        id: u64,
        client: AsyncClient,
        connected: bool,
    },
}

type SessionEvent = (u64, Result<Event, ConnectionError>);

/// What the daemon's channel had no room for, in two lines: QoS 1 and 2
/// messages (route requests, feedback) go first, so that a request is not kept
/// waiting behind a backlog of QoS 0 sightings and heartbeats, which are soon
/// stale anyway. Order is kept within each line; PUBACKs, which only QoS 1
/// has, stay in the order the broker sent the messages.
#[derive(Default)]
struct Held {
    /// QoS 1 and 2: acknowledged once the daemon's channel takes them.
    acknowledged: VecDeque<(Received, Publish)>,
    /// QoS 0: at most [`HELD_MAX`].
    lossy: VecDeque<(Received, Publish)>,
}

impl Held {
    fn is_empty(&self) -> bool {
        self.acknowledged.is_empty() && self.lossy.is_empty()
    }

    /// Whether a message of `qos` arriving now has to wait behind what is
    /// held (its own line, and for QoS 0 the other too).
    fn ahead_of(&self, qos: QoS) -> bool {
        match qos {
            QoS::AtMostOnce => !self.is_empty(),
            QoS::AtLeastOnce | QoS::ExactlyOnce => !self.acknowledged.is_empty(),
        }
    }

    fn push(&mut self, received: Received, publish: Publish) {
        match publish.qos {
            QoS::AtMostOnce => self.lossy.push_back((received, publish)),
            QoS::AtLeastOnce | QoS::ExactlyOnce => {
                self.acknowledged.push_back((received, publish));
            }
        }
    }

    fn pop_front(&mut self) -> Option<(Received, Publish)> {
        self.acknowledged
            .pop_front()
            .or_else(|| self.lossy.pop_front())
    }
}

struct Controller {
    settings: LinkSettings,
    stats: Arc<LinkStats>,
    inbound: mpsc::Sender<Received>,
    /// Received, not yet taken by the daemon's channel (full), and so not
    /// yet acknowledged.
    held: Held,
    queue: OfflineQueue,
    /// Sent after every connect, by topic.
    birth: BTreeMap<String, Outgoing>,
    /// When each birth topic was last re-asserted (see the module doc).
    reasserted: HashMap<String, Instant>,
    /// Warnings about overwritten birth topics, at most one per ten seconds.
    overwritten: crate::throttle::Throttle,
    /// When connections were lost recently (within [`FLAP_WINDOW`]).
    losses: VecDeque<Instant>,
    /// Acknowledgements the session's channel had no room for yet (payloads
    /// dropped: only the packet id and QoS matter). A lost one would hold a
    /// slot of the broker's inflight window until the next session.
    acks: VecDeque<Publish>,
    /// Handed to the current session, in order, not yet seen on the wire.
    handed: VecDeque<Outgoing>,
    /// Written with this packet id, awaiting PUBACK; the sequence number
    /// keeps their original order for redelivery.
    awaiting: BTreeMap<u64, (u16, Outgoing)>,
    /// The sequence number in `awaiting` of each packet id.
    awaiting_pkid: HashMap<u16, u64>,
    next_seq: u64,
    backoff: Duration,
    /// The node of `settings.brokers` tried or used now.
    broker: usize,
    ever_connected: bool,
    conn: Conn,
    next_session: u64,
    events_tx: mpsc::UnboundedSender<SessionEvent>,
    events_rx: mpsc::UnboundedReceiver<SessionEvent>,
    shutdown: Option<(oneshot::Sender<()>, Instant)>,
    disconnect_sent: bool,
}

impl Controller {
    fn new(settings: LinkSettings, stats: Arc<LinkStats>, inbound: mpsc::Sender<Received>) -> Self {
        let (events_tx, events_rx) = mpsc::unbounded_channel();
        Controller {
            queue: OfflineQueue::new(settings.queue_max_messages, settings.queue_max_bytes),
            backoff: settings.reconnect_min,
            broker: 0,
            settings,
            stats,
            inbound,
            held: Held::default(),
            birth: BTreeMap::new(),
            reasserted: HashMap::default(),
            overwritten: crate::throttle::Throttle::new(Duration::from_secs(10)),
            losses: VecDeque::new(),
            acks: VecDeque::new(),
            handed: VecDeque::new(),
            awaiting: BTreeMap::new(),
            awaiting_pkid: HashMap::default(),
            next_seq: 0,
            ever_connected: false,
            conn: Conn::Down {
                retry_at: Instant::now(),
            },
            next_session: 0,
            events_tx,
            events_rx,
            shutdown: None,
            disconnect_sent: false,
        }
    }

    async fn run(mut self, mut commands: mpsc::UnboundedReceiver<Command>) {
        loop {
            let retry_at = match &self.conn {
                Conn::Down { retry_at } => Some(*retry_at),
                Conn::Session { .. } => None,
            };
            let deadline = self.shutdown.as_ref().map(|(_, d)| *d);
            // A sender of our own, so that waiting for room does not borrow
            // the controller the branches below change.
            let holding = !self.held.is_empty();
            let inbound = holding.then(|| self.inbound.clone());
            tokio::select! {
                Ok(permit) = reserve(inbound.as_ref()), if holding => {
                    if let Some((received, publish)) = self.held.pop_front() {
                        permit.send(received);
                        self.ack(&publish);
                    }
                }
                command = commands.recv(), if self.shutdown.is_none() => match command {
                    Some(Command::Publish(batch)) => {
                        self.stats
                            .commands_taken
                            .fetch_add(batch.len() as u64, Ordering::Relaxed);
                        for m in batch {
                            self.queue.push(m);
                        }
                        self.flush();
                    }
                    Some(Command::Birth(birth, send_now)) => {
                        let connected = self.is_connected();
                        for m in birth {
                            // The broker holds the same retained message
                            // already (a reload re-states every discovery
                            // config): sent only when new or changed.
                            let changed = self.birth.get(&m.topic).is_none_or(|old| {
                                old.payload != m.payload || old.retain != m.retain
                            });
                            if send_now && connected && changed {
                                self.queue.push(m.clone());
                            }
                            if !self.birth.contains_key(&m.topic) {
                                self.watch(&m.topic);
                            }
                            self.birth.insert(m.topic.clone(), m);
                        }
                        self.flush();
                    }
                    Some(Command::ClearRetained(topic)) => {
                        if self.birth.remove(&topic).is_some() {
                            self.reasserted.remove(&topic);
                            if let Conn::Session { client, .. } = &self.conn {
                                let _ = client.try_unsubscribe(&topic);
                            }
                        }
                        self.queue.push(Outgoing {
                            topic,
                            payload: Vec::new(),
                            qos: self.settings.qos,
                            retain: true,
                        });
                        self.flush();
                    }
                    Some(Command::Subscribe(filters, qos)) => {
                        for filter in filters {
                            if !self.settings.subscriptions.iter().any(|(f, _)| *f == filter) {
                                self.subscribe(&filter, qos);
                                self.settings.subscriptions.push((filter, qos));
                            }
                        }
                    }
                    Some(Command::Unsubscribe(filters)) => {
                        self.settings.subscriptions.retain(|(f, _)| !filters.contains(f));
                        if let Conn::Session { client, connected: true, .. } = &self.conn {
                            for filter in &filters {
                                let _ = client.try_unsubscribe(filter);
                            }
                        }
                    }
                    Some(Command::Shutdown(done)) => self.begin_shutdown(done),
                    // Every handle is gone: nobody can ask for a clean
                    // shutdown any more, so do one now.
                    None => {
                        let (done, _) = oneshot::channel();
                        self.begin_shutdown(done);
                    }
                },
                Some((session, event)) = self.events_rx.recv() => {
                    let mut done = self.current_session() == Some(session) && self.on_event(event);
                    // What else the session reported meanwhile (a burst of
                    // acknowledgements), before handing over more once.
                    let mut more = EVENT_BURST;
                    while !done && more > 0 && let Ok((session, event)) = self.events_rx.try_recv() {
                        done = self.current_session() == Some(session) && self.on_event(event);
                        more -= 1;
                    }
                    if done {
                        break;
                    }
                    self.flush();
                }
                _ = sleep_until(retry_at), if retry_at.is_some() => self.connect(),
                _ = sleep_until(deadline), if deadline.is_some() => {
                    tracing::warn!(
                        queued = self.queue.len(),
                        in_flight = self.handed.len() + self.awaiting.len(),
                        "MQTT shutdown grace period over; giving up on unsent messages"
                    );
                    break;
                }
            }
            self.publish_stats();
            if self.shutdown.is_some()
                && !self.disconnect_sent
                && self.drained()
                && let Conn::Session {
                    client,
                    connected: true,
                    ..
                } = &self.conn
            {
                let _ = client.try_disconnect();
                self.disconnect_sent = true;
            }
        }
        self.stats.connected.store(false, Ordering::Relaxed);
        if let Some((done, _)) = self.shutdown.take() {
            let _ = done.send(());
        }
    }

    fn begin_shutdown(&mut self, done: oneshot::Sender<()>) {
        if let Some((topic, _, offline)) = &self.settings.status {
            // A clean DISCONNECT suppresses the last will, so say it ourselves.
            self.queue.push(Outgoing {
                topic: topic.clone(),
                payload: offline.clone().into_bytes(),
                qos: self.settings.qos,
                retain: true,
            });
        }
        self.shutdown = Some((done, Instant::now() + self.settings.shutdown_grace));
        self.flush();
    }

    fn drained(&self) -> bool {
        self.queue.is_empty() && self.handed.is_empty() && self.awaiting.is_empty()
    }

    fn is_connected(&self) -> bool {
        matches!(
            self.conn,
            Conn::Session {
                connected: true,
                ..
            }
        )
    }

    fn current_session(&self) -> Option<u64> {
        match self.conn {
            Conn::Session { id, .. } => Some(id),
            Conn::Down { .. } => None,
        }
    }

    /// Starts a new session: a fresh client and event loop, polled on a task
    /// that forwards every event here and ends with the session.
    fn connect(&mut self) {
        let mut options = self.settings.brokers[self.broker].clone();
        if let Some((topic, _, offline)) = &self.settings.status {
            options.set_last_will(LastWill::new(
                topic,
                offline.clone(),
                self.settings.qos,
                true,
            ));
        }
        // Acknowledged only once the daemon's channel takes them (`deliver`).
        options.set_manual_acks(true);
        // As many unacknowledged publications on the wire as the link hands
        // over (rumqttc's default, 100, would hold the rest back a round
        // trip when the broker is slow to acknowledge).
        options.set_inflight(SESSION_WINDOW as u16);
        // Room for a full window of publications and as many acknowledgements.
        let (client, mut eventloop) = AsyncClient::new(options, 2 * SESSION_WINDOW);
        // Route replies are small and wanted now: without TCP_NODELAY, Nagle's
        // algorithm holds a reply until the broker acknowledges the last
        // packet, which with delayed ACKs cost tens of milliseconds per reply.
        let mut network = eventloop.network_options();
        network.set_tcp_nodelay(self.settings.low_latency);
        eventloop.set_network_options(network);
        let id = self.next_session;
        self.next_session += 1;
        tokio::spawn(poll_session(id, eventloop, self.events_tx.clone()));
        self.conn = Conn::Session {
            id,
            client,
            connected: false,
        };
    }

    /// Handles one event of the current session; true when the link is done.
    /// The caller hands over more messages ([`Controller::flush`]) after.
    fn on_event(&mut self, event: Result<Event, ConnectionError>) -> bool {
        match event {
            Ok(Event::Incoming(Packet::ConnAck(_))) => self.on_connected(),
            Ok(Event::Incoming(Packet::Publish(p))) => self.deliver(p),
            Ok(Event::Incoming(Packet::PubAck(ack))) => self.acked(ack.pkid),
            Ok(Event::Incoming(Packet::PubComp(comp))) => self.acked(comp.pkid),
            Ok(Event::Outgoing(Out::Publish(pkid))) => {
                if let Some(m) = self.handed.pop_front() {
                    self.stats.published.fetch_add(1, Ordering::Relaxed);
                    if m.qos != QoS::AtMostOnce {
                        self.awaiting.insert(self.next_seq, (pkid, m));
                        // A packet id the broker never acknowledged and
                        // rumqttc reused: the older message is redelivered
                        // with the rest if the session fails.
                        self.awaiting_pkid.insert(pkid, self.next_seq);
                        self.next_seq += 1;
                    }
                }
            }
            Ok(Event::Outgoing(Out::Disconnect)) => return true,
            Ok(_) => {}
            Err(e) => self.on_lost(e),
        }
        false
    }

    /// Subscribes to one of the gateway's own birth topics, if connected
    /// (on connect, all of them are).
    fn watch(&self, topic: &str) {
        self.subscribe(topic, self.settings.qos);
    }

    /// Subscribes to `topic` at `qos`, if connected (on connect, every
    /// subscription is made again).
    fn subscribe(&self, topic: &str, qos: QoS) {
        if let Conn::Session {
            client,
            connected: true,
            ..
        } = &self.conn
            && let Err(e) = client.try_subscribe(topic, qos)
        {
            tracing::error!(%topic, "cannot subscribe: {e}");
        }
    }

    /// The gateway's own message on `topic`, if it has one there now.
    fn own(&self, topic: &str) -> Option<Outgoing> {
        if let Some((status, online, _)) = &self.settings.status
            && status == topic
        {
            // While shutting down, `offline` is the gateway's own word.
            return self.shutdown.is_none().then(|| Outgoing {
                topic: status.clone(),
                payload: online.clone().into_bytes(),
                qos: self.settings.qos,
                retain: true,
            });
        }
        self.birth.get(topic).cloned()
    }

    /// Whether `publish` is on one of the gateway's own birth topics: then it
    /// is not the daemon's, and if it is not the gateway's own message it is
    /// put back (rate-limited).
    fn defend(&mut self, publish: &Publish) -> bool {
        let topic = publish.topic.as_str();
        let is_status = self
            .settings
            .status
            .as_ref()
            .is_some_and(|(status, ..)| status == topic);
        if !is_status && !self.birth.contains_key(topic) {
            return false;
        }
        // What the broker kept from before, sent on subscribing (retain
        // flag set): the birth messages of this connect overwrite it anyway.
        if publish.retain {
            return true;
        }
        let Some(own) = self.own(topic) else {
            return true;
        };
        if *publish.payload == own.payload[..] {
            return true;
        }
        let now = Instant::now();
        if self
            .reasserted
            .get(topic)
            .is_some_and(|last| now.duration_since(*last) < REASSERT_EVERY)
        {
            return true;
        }
        self.reasserted.insert(topic.to_owned(), now);
        if let Some(more) = self.overwritten.ready() {
            tracing::warn!(
                %topic,
                not_logged = more,
                "someone else published on the gateway's own retained topic; publishing the \
                 gateway's message there again (restrict who may write it: docs/mqtt.md)"
            );
        }
        self.queue.push(own);
        self.flush();
        true
    }

    /// Hands a received message to the daemon, cut off if over the limit;
    /// acknowledges it once handed over.
    fn deliver(&mut self, publish: Publish) {
        if self.defend(&publish) {
            self.ack(&publish);
            return;
        }
        let size = publish.payload.len();
        // The daemon counts and answers it from its size.
        let payload = if size > self.settings.max_inbound_payload {
            Bytes::new()
        } else {
            publish.payload.clone()
        };
        let received = Received {
            topic: publish.topic.clone(),
            payload,
            size,
        };
        if self.held.ahead_of(publish.qos) {
            self.hold(received, publish);
            return;
        }
        match self.inbound.try_send(received) {
            Ok(()) => self.ack(&publish),
            Err(mpsc::error::TrySendError::Full(received)) => self.hold(received, publish),
            // The daemon is gone (shutting down): nothing will read it.
            Err(mpsc::error::TrySendError::Closed(_)) => {}
        }
    }

    /// Keeps a message the daemon's channel has no room for, unacknowledged,
    /// so the broker holds back what follows; past [`HELD_MAX`] a QoS 0
    /// message (which nobody redelivers anyway) is dropped and counted.
    fn hold(&mut self, received: Received, publish: Publish) {
        if publish.qos == QoS::AtMostOnce && self.held.lossy.len() >= HELD_MAX {
            let dropped = self.stats.inbound_dropped.fetch_add(1, Ordering::Relaxed) + 1;
            if dropped.is_power_of_two() {
                tracing::warn!(
                    dropped,
                    topic = %received.topic,
                    "the gateway is behind: QoS 0 messages dropped (use QoS 1 for requests)"
                );
            }
            return;
        }
        self.held.push(received, publish);
    }

    /// Acknowledges a message now, or as soon as the session's channel has
    /// room (acknowledgements go before publications, see `flush`).
    fn ack(&mut self, publish: &Publish) {
        if publish.qos == QoS::AtMostOnce {
            return;
        }
        let mut ack = publish.clone();
        ack.payload = Bytes::new();
        self.acks.push_back(ack);
        self.send_acks();
    }

    fn send_acks(&mut self) {
        let Conn::Session { client, .. } = &self.conn else {
            return;
        };
        while let Some(ack) = self.acks.front() {
            if client.try_ack(ack).is_err() {
                return;
            }
            self.acks.pop_front();
        }
    }

    fn acked(&mut self, pkid: u16) {
        if let Some(seq) = self.awaiting_pkid.remove(&pkid) {
            self.awaiting.remove(&seq);
        }
    }

    fn on_connected(&mut self) {
        let Conn::Session {
            client, connected, ..
        } = &mut self.conn
        else {
            return;
        };
        *connected = true;
        let own = self
            .settings
            .status
            .iter()
            .map(|(status, ..)| status)
            .chain(self.birth.keys());
        let qos = self.settings.qos;
        let own = own.map(|topic| (topic, qos));
        let subscriptions = self.settings.subscriptions.iter().map(|(f, q)| (f, *q));
        for (topic, qos) in subscriptions.chain(own) {
            if let Err(e) = client.try_subscribe(topic, qos) {
                tracing::error!(%topic, "cannot subscribe: {e}");
            }
        }
        let url = broker_address(&self.settings.brokers[self.broker]);
        if self.ever_connected {
            self.stats.reconnects.fetch_add(1, Ordering::Relaxed);
            tracing::info!(broker = %url, queued = self.queue.len(), "reconnected to the MQTT broker");
        } else {
            tracing::info!(broker = %url, "connected to the MQTT broker");
        }
        self.ever_connected = true;
        self.backoff = self.settings.reconnect_min;
        self.stats.connected.store(true, Ordering::Relaxed);
        let mut birth = Vec::with_capacity(self.birth.len() + 1);
        if let Some((topic, online, _)) = &self.settings.status
            && self.shutdown.is_none()
        {
            birth.push(Outgoing {
                topic: topic.clone(),
                payload: online.clone().into_bytes(),
                qos: self.settings.qos,
                retain: true,
            });
        }
        birth.extend(self.birth.values().cloned());
        self.queue.requeue_front(birth.into_iter());
    }

    /// The session failed: take back what it had not delivered and wait.
    fn on_lost(&mut self, error: ConnectionError) {
        let was_connected = self.is_connected();
        self.awaiting_pkid.clear();
        let undelivered: Vec<Outgoing> = std::mem::take(&mut self.awaiting)
            .into_values()
            .map(|(_, m)| m)
            .chain(self.handed.drain(..))
            .collect();
        self.queue.requeue_front(undelivered.into_iter());
        // Unacknowledged messages come again from the broker on the next
        // session; only QoS 0 ones, which nobody redelivers, are kept.
        self.held.acknowledged.clear();
        self.acks.clear();
        self.stats.connected.store(false, Ordering::Relaxed);
        self.stats.connect_failures.fetch_add(1, Ordering::Relaxed);
        let broker = broker_address(&self.settings.brokers[self.broker]);
        // The next node of a clustered broker is tried at once; the backoff
        // grows once every node was tried.
        self.broker = (self.broker + 1) % self.settings.brokers.len();
        let wait = if self.broker == 0 {
            let wait = self.backoff;
            self.backoff = (self.backoff * 2).min(self.settings.reconnect_max);
            wait
        } else {
            self.settings.reconnect_min
        };
        if was_connected {
            self.stats.disconnects.fetch_add(1, Ordering::Relaxed);
            self.losses.push_back(Instant::now());
            self.publish_stats();
            if self.stats.flapping.load(Ordering::Relaxed) {
                tracing::error!(
                    %broker,
                    lost = self.losses.len(),
                    within_s = FLAP_WINDOW.as_secs(),
                    retry_in_s = wait.as_secs_f64(),
                    "cannot stay connected to the MQTT broker: {error}"
                );
            } else {
                tracing::warn!(%broker, retry_in_s = wait.as_secs_f64(), queued = self.queue.len(), "lost the MQTT broker: {error}");
            }
        } else {
            tracing::warn!(%broker, retry_in_s = wait.as_secs_f64(), "cannot connect to the MQTT broker: {error}");
        }
        self.conn = Conn::Down {
            retry_at: Instant::now() + wait,
        };
        self.disconnect_sent = false;
    }

    /// Moves queued messages into the connected session, up to its window.
    fn flush(&mut self) {
        self.send_acks();
        let Conn::Session {
            client,
            connected: true,
            ..
        } = &self.conn
        else {
            return;
        };
        while self.handed.len() + self.awaiting.len() < SESSION_WINDOW {
            let Some(m) = self.queue.pop() else { break };
            if let Some(why) = unpublishable(&m) {
                // rumqttc would refuse it forever (a wildcard) or fail the
                // connection on it (too large): drop it, never retry it.
                let n = self.stats.unpublishable.fetch_add(1, Ordering::Relaxed) + 1;
                if n.is_power_of_two() {
                    tracing::error!(topic = %m.topic, refused = n, "not published: {why}");
                }
                continue;
            }
            match client.try_publish(&m.topic, m.qos, m.retain, m.payload.clone()) {
                Ok(()) => self.handed.push_back(m),
                Err(e) => {
                    // Channel full or closed: keep the message for later.
                    tracing::debug!("MQTT client busy: {e}");
                    self.queue.requeue_front(std::iter::once(m));
                    break;
                }
            }
        }
    }

    fn publish_stats(&mut self) {
        // Flapping ends once the window holds fewer losses again.
        let now = Instant::now();
        while self
            .losses
            .front()
            .is_some_and(|&t| now.duration_since(t) > FLAP_WINDOW)
        {
            self.losses.pop_front();
        }
        let s = &self.stats;
        s.flapping
            .store(self.losses.len() >= FLAP_COUNT, Ordering::Relaxed);
        s.outstanding.store(
            (self.queue.len() + self.handed.len() + self.awaiting.len()) as u64,
            Ordering::Relaxed,
        );
        s.queue_depth
            .store(self.queue.len() as u64, Ordering::Relaxed);
        s.queue_bytes
            .store(self.queue.bytes() as u64, Ordering::Relaxed);
        s.queue_dropped
            .store(self.queue.dropped(), Ordering::Relaxed);
        s.progress.notify_waiters();
    }
}

/// Why no broker would take `m`, if so.
fn unpublishable(m: &Outgoing) -> Option<&'static str> {
    if m.topic.is_empty() || m.topic.contains(['+', '#', '\0']) {
        Some("the topic is empty or has a wildcard or NUL")
    } else if m.topic.len() > usize::from(u16::MAX) {
        Some("the topic is over 65535 bytes")
    } else if m.size() + 16 > MAX_OUTGOING_PACKET {
        Some("the message is over the 1 MiB packet limit")
    } else {
        None
    }
}

async fn poll_session(
    id: u64,
    mut eventloop: EventLoop,
    events: mpsc::UnboundedSender<SessionEvent>,
) {
    loop {
        let event = eventloop.poll().await;
        let last = matches!(event, Err(_) | Ok(Event::Outgoing(Out::Disconnect)));
        if events.send((id, event)).is_err() || last {
            return;
        }
    }
}

/// Room in the daemon's channel, when there is a channel to wait for.
async fn reserve(
    inbound: Option<&mpsc::Sender<Received>>,
) -> Result<mpsc::Permit<'_, Received>, mpsc::error::SendError<()>> {
    match inbound {
        Some(inbound) => inbound.reserve().await,
        None => std::future::pending().await,
    }
}

async fn sleep_until(at: Option<Instant>) {
    match at {
        Some(at) => tokio::time::sleep_until(at).await,
        None => std::future::pending().await,
    }
}

fn broker_address(options: &MqttOptions) -> String {
    let (host, port) = options.broker_address();
    format!("{host}:{port}")
}

#[cfg(test)]
mod tests {
    use super::*;

    fn message(topic: &str, qos: QoS) -> (Received, Publish) {
        let received = Received {
            topic: topic.to_owned(),
            payload: Bytes::new(),
            size: 0,
        };
        (received, Publish::new(topic, qos, Vec::new()))
    }

    #[test]
    fn a_held_request_goes_before_the_sightings_held_ahead_of_it() {
        let mut held = Held::default();
        for topic in ["sightings/1", "sightings/2"] {
            let (received, publish) = message(topic, QoS::AtMostOnce);
            held.push(received, publish);
        }
        // A request arriving now need not wait behind QoS 0 messages…
        assert!(!held.ahead_of(QoS::AtLeastOnce));
        // …but a sighting waits behind them, and behind a held request.
        assert!(held.ahead_of(QoS::AtMostOnce));
        for topic in ["route/set/1", "route/set/2"] {
            let (received, publish) = message(topic, QoS::AtLeastOnce);
            held.push(received, publish);
        }
        assert!(held.ahead_of(QoS::AtLeastOnce));
        let order: Vec<String> = std::iter::from_fn(|| held.pop_front())
            .map(|(r, _)| r.topic)
            .collect();
        assert_eq!(
            order,
            ["route/set/1", "route/set/2", "sightings/1", "sightings/2"]
        );
        assert!(held.is_empty());
    }
}
