//! Sources: where sightings (and scripted requests and ground truth) come from.
//!
//! Every source yields the same [`Event`]s, so the pipeline cannot tell a live
//! BLE scan from a replayed log or a simulation. A [`Source`] is one task of
//! the runtime (`daemon::run` in the binary): it sends what it reads through its
//! [`SourceContext`] and stops when told ([`Shutdown`]). The sources:
//! - [`ble`]: a live scan through btleplug on BlueZ ([`ble::BleSource`]);
//! - [`playback`]: any capture (or a simulation) played at a pace
//!   ([`playback::CaptureSource`]), the one place pacing is written;
//! - `mqtt::source`: phone scans, shared sightings and route requests from
//!   the broker, as [`Inbound`] messages;
//! - [`ChannelSource`]: whatever a program (or a test) sends on a channel.
//!
//! A new source is one module with a type that implements [`Source`], and one
//! line in the wiring (`cli/run.rs` or `cli/replay.rs`) that adds it.
//!
//! The readers and formats behind them:
//! - [`log`]: the JSON Lines advert log (`gangway record` writes it, `replay` reads it);
//! - [`csvlog`]: CSV scan logs such as the UCI survey (replay only);
//! - [`btsnoop`]: HCI captures from `btmon -w` or Android's HCI snoop log;
//! - [`pcap`]: pcap and pcapng captures from Wireshark, tcpdump and the nRF
//!   Sniffer (Bluetooth LE linktypes: [`pcap_link`]);
//! - [`adverts`]: what the btsnoop and pcap readers share, from advertising
//!   data to sightings and skip counts;
//! - [`capture`]: picks one of those formats for a file and opens it.
//!
//! Simulated walkers live in `gangway-offline` (`simulate`): they are test
//! and evaluation input, not something a gateway reads.

pub(crate) mod adverts;
pub mod ble;
pub mod btsnoop;
pub mod capture;
pub(crate) mod csvlog;
pub mod ibeacon;
pub mod log;
pub mod pcap;
pub(crate) mod pcap_link;
pub mod playback;

use futures::future::BoxFuture;
use tokio::sync::{mpsc, watch};

use crate::event::{Event, Inbound};

/// Now, in seconds since the Unix epoch: the clock of live sightings and of
/// everything the gateway stamps itself.
pub fn unix_now() -> f64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}

/// A source of events: a task of the runtime that sends what it reads
/// through its [`SourceContext`] until it is done or told to shut down.
///
/// Errors end the source: the runtime logs them and keeps serving (the
/// daemon), or stops with them (a replay, whose file is all it serves).
pub trait Source: Send {
    /// What the logs call this source.
    fn name(&self) -> &'static str;
    /// Runs the source to its end. It returns soon after
    /// [`SourceContext::shutdown`] says so, having let go of what it holds
    /// (a scan stops discovering).
    fn run(self: Box<Self>, cx: SourceContext) -> BoxFuture<'static, anyhow::Result<()>>;
}

/// What a source sends to the runtime.
#[derive(Debug)]
pub enum Input {
    /// This gateway's own events, in time order.
    Events(Vec<Event>),
    /// Someone else's message.
    Inbound(Inbound),
}

/// A source's way into the runtime: its own events and others' messages go
/// through separate bounded queues, so that the runtime can stop taking
/// others' messages (which cause replies) while its sinks are backed up and
/// keep locating meanwhile.
pub struct SourceContext {
    pub(crate) events: mpsc::Sender<Input>,
    pub(crate) inbound: mpsc::Sender<Input>,
    pub shutdown: Shutdown,
}

/// The runtime is gone: the source should stop.
#[derive(Debug, thiserror::Error)]
#[error("the gateway's runtime stopped")]
pub(crate) struct Closed;

impl SourceContext {
    /// A context sending into the runtime's two queues, stopped by `shutdown`.
    pub fn new(
        events: mpsc::Sender<Input>,
        inbound: mpsc::Sender<Input>,
        shutdown: Shutdown,
    ) -> SourceContext {
        SourceContext {
            events,
            inbound,
            shutdown,
        }
    }

    /// Sends own events (a batch, in time order); waits while the runtime is
    /// behind.
    pub(crate) async fn events(&self, events: Vec<Event>) -> Result<(), Closed> {
        self.events
            .send(Input::Events(events))
            .await
            .map_err(|_| Closed)
    }

    /// Sends someone else's message; waits while the runtime is not taking them.
    pub(crate) async fn inbound(&self, message: Inbound) -> Result<(), Closed> {
        self.inbound
            .send(Input::Inbound(message))
            .await
            .map_err(|_| Closed)
    }
}

/// Tells a task that the gateway is shutting down (the shape of tokio's
/// mini-redis): every task holds one and checks it at each wait.
#[derive(Clone, Debug)]
pub struct Shutdown {
    notify: watch::Receiver<bool>,
}

/// Starts shutdown for every [`Shutdown`] it made.
#[derive(Debug)]
pub struct ShutdownTrigger {
    notify: watch::Sender<bool>,
}

impl Shutdown {
    /// A trigger and the first receiver.
    pub fn new() -> (ShutdownTrigger, Shutdown) {
        let (notify, rx) = watch::channel(false);
        (ShutdownTrigger { notify }, Shutdown { notify: rx })
    }

    pub(crate) fn is_shutdown(&self) -> bool {
        *self.notify.borrow()
    }

    /// Waits until shutdown starts (or the trigger is gone).
    pub(crate) async fn recv(&mut self) {
        let _ = self.notify.wait_for(|&down| down).await;
    }
}

impl ShutdownTrigger {
    pub fn trigger(&self) {
        self.notify.send_replace(true);
    }
}

/// A source fed by a channel: whatever a program (or a test) sends on it is
/// passed on, own events and others' messages alike. It ends when every
/// sender is gone, or at shutdown.
pub struct ChannelSource {
    rx: mpsc::Receiver<Input>,
}

impl ChannelSource {
    /// A source and the sender that feeds it (`capacity` messages waiting at most).
    pub fn new(capacity: usize) -> (mpsc::Sender<Input>, ChannelSource) {
        let (tx, rx) = mpsc::channel(capacity.max(1));
        (tx, ChannelSource { rx })
    }
}

impl Source for ChannelSource {
    fn name(&self) -> &'static str {
        "channel"
    }

    fn run(self: Box<Self>, mut cx: SourceContext) -> BoxFuture<'static, anyhow::Result<()>> {
        let mut rx = self.rx;
        Box::pin(async move {
            loop {
                let fed = tokio::select! {
                    fed = rx.recv() => fed,
                    () = cx.shutdown.recv() => None,
                };
                let sent = match fed {
                    None => return Ok(()),
                    Some(input @ Input::Events(_)) => cx.events.send(input).await,
                    Some(input @ Input::Inbound(_)) => cx.inbound.send(input).await,
                };
                if sent.is_err() {
                    return Ok(());
                }
            }
        })
    }
}
