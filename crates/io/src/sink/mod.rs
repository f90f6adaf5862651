//! Sinks: where the gateway's [`Output`]s go out. A [`Sink`] is given every
//! output in order, in batches, by the runtime (`daemon::run` in the binary):
//! - `mqtt::sink`: the broker (topics and JSON from `crate::topics`, Home
//!   Assistant discovery, presence and occupancy, the retained stats);
//! - [`jsonl`]: the same messages as JSON Lines on stdout (`--print`) or in a
//!   file (`--out FILE`);
//! - [`recorder`]: the learning store (fixes, routes, feedback, adherence);
//! - `score`: a replay's fixes against its log's truth.
//!
//! A new sink is one module with a type that implements [`Sink`], and one
//! line in the wiring (`cli/run.rs`, `cli/replay.rs`) that adds it.
//!
//! The contract: [`Sink::send`] must not block for long (buffer, or hand
//! over to a task of the sink's own); [`Sink::flush`] delivers what is
//! buffered and may wait for room (a lossless replay to a broker), which
//! holds the runtime back; [`Sink::shutdown`] delivers everything left
//! before the process exits. A sink that fails (stdout closed) stops the
//! runtime with its error; one that must never stop the gateway (the store
//! on a failing disk) counts and logs its failures instead.

pub mod jsonl;
// Public for the in-process daemon tests that record what the runtime hears.
pub mod recorder;

use futures::future::BoxFuture;

use crate::publish::Output;
use crate::publish::stats::Stats;
use crate::site::Building;

/// Where outputs go. Everything but [`Sink::name`], [`Sink::send`] and
/// [`Sink::shutdown`] has a default that does nothing.
pub trait Sink: Send {
    /// What the logs call this sink.
    fn name(&self) -> &'static str;

    /// Takes the next outputs, in order.
    fn send(&mut self, outputs: &[Output]) -> anyhow::Result<()>;

    /// Delivers what [`Sink::send`] buffered. The runtime calls it whenever
    /// no more input is waiting (and at least every few batches under load),
    /// so a sink can batch without adding latency when the gateway is idle.
    fn flush(&mut self) -> BoxFuture<'_, anyhow::Result<()>> {
        Box::pin(std::future::ready(Ok(())))
    }

    /// Once a second, for periodic work (`now` in seconds since the epoch).
    fn tick(&mut self, _now: f64) {}

    /// A reload swapped the building (floors and places may have changed).
    fn reload(&mut self, _building: &Building) {}

    /// A reload was refused (`why`): the gateway serves what it served.
    fn reload_refused(&mut self, _why: &str) {}

    /// Adds this sink's counters to the gateway's stats.
    fn report(&self, _stats: &mut Stats) {}

    /// The gateway's counters as they are now, once a second: for a sink
    /// that serves them when asked (`/metrics`) rather than publishing them,
    /// so an answer is never a whole stats interval old.
    fn counters(&mut self, _stats: &Stats) {}

    /// Whether the sink can take the replies to more requests now; the
    /// runtime takes no message from others while one cannot, so that the
    /// replies do not push older messages out of a full queue.
    fn has_room(&self) -> bool {
        true
    }

    /// Whether the sink still works at all (systemd's watchdog is fed only
    /// while every sink does).
    fn is_alive(&self) -> bool {
        true
    }

    /// How the sink is doing, for systemd's status line.
    fn status(&self) -> Option<String> {
        None
    }

    /// Delivers everything left and lets go of the sink's resources.
    fn shutdown(self: Box<Self>) -> BoxFuture<'static, anyhow::Result<()>>;
}
