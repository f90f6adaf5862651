//! Playing recorded (or simulated) events into the runtime at a pace: 1 is
//! the time the events say, 10 ten times faster, 0 as fast as the runtime
//! takes them. This is the one place pacing is written: `gangway replay` and
//! `gangway run --replay` both play through it, whatever the capture's format.
//!
//! Events go in batches (up to [`BATCH`], and whatever is due before the next
//! wait), so a fast replay costs the runtime one queue hand-over per batch,
//! not per advert.

use std::path::PathBuf;
use std::time::Duration;

use futures::future::BoxFuture;
use tokio::time::Instant;

use super::capture::{CaptureError, CaptureReader};
use super::{Source, SourceContext};

use crate::event::Event;

/// Most events handed to the runtime at once.
pub(crate) const BATCH: usize = 256;

/// When each event of a played log is due.
#[derive(Debug)]
pub(crate) struct Pace {
    speed: f64,
    /// The first event's time and when it was played.
    start: Option<(f64, Instant)>,
}

impl Pace {
    /// `speed` 0 plays as fast as possible.
    pub(crate) fn new(speed: f64) -> Pace {
        Pace { speed, start: None }
    }

    /// When an event of time `t` is due; `None` as fast as possible.
    pub(crate) fn due(&mut self, t: f64) -> Option<Instant> {
        if self.speed <= 0.0 {
            return None;
        }
        let (t0, started) = *self.start.get_or_insert_with(|| (t, Instant::now()));
        Some(started + Duration::from_secs_f64(((t - t0) / self.speed).max(0.0)))
    }
}

/// Plays `events` into the runtime at `speed`; stops at the first error (the
/// reader decides what an error is: with `skip_bad` it skips and counts), at
/// shutdown, or when the runtime is gone.
pub(crate) async fn play<E>(
    events: impl Iterator<Item = Result<Event, E>>,
    speed: f64,
    cx: &mut SourceContext,
) -> Result<(), E> {
    let mut pace = Pace::new(speed);
    let mut batch = Vec::with_capacity(BATCH);
    // The readers do blocking file reads; lines are short and the file local,
    // so reading them on the runtime is cheaper than a thread hop per batch.
    for event in events {
        let event = event?;
        if let Some(due) = pace.due(event.t())
            && due > Instant::now()
        {
            // What is due now goes before the wait.
            if !batch.is_empty() && cx.events(std::mem::take(&mut batch)).await.is_err() {
                return Ok(());
            }
            tokio::select! {
                () = tokio::time::sleep_until(due) => {}
                // Shutting down: stop now rather than at the next event.
                () = cx.shutdown.recv() => return Ok(()),
            }
        }
        batch.push(event);
        if batch.len() >= BATCH {
            if cx.events(std::mem::take(&mut batch)).await.is_err() {
                return Ok(());
            }
            batch.reserve(BATCH);
            if cx.shutdown.is_shutdown() {
                return Ok(());
            }
        }
    }
    if !batch.is_empty() {
        let _ = cx.events(batch).await;
    }
    Ok(())
}

/// A capture of any format ([`CaptureReader`]) played at a pace.
pub struct CaptureSource {
    path: PathBuf,
    reader: CaptureReader,
    speed: f64,
}

impl CaptureSource {
    /// Plays `reader` (opened from `path`) at `speed`.
    pub fn new(path: PathBuf, reader: CaptureReader, speed: f64) -> CaptureSource {
        CaptureSource {
            path,
            reader,
            speed,
        }
    }
}

impl Source for CaptureSource {
    fn name(&self) -> &'static str {
        "capture"
    }

    fn run(self: Box<Self>, mut cx: SourceContext) -> BoxFuture<'static, anyhow::Result<()>> {
        let CaptureSource {
            path,
            mut reader,
            speed,
        } = *self;
        Box::pin(async move {
            let played: Result<(), CaptureError> = play(reader.by_ref(), speed, &mut cx).await;
            tracing::info!(
                capture = %path.display(),
                format = ?reader.format(),
                skipped = %reader.skipped(),
                "capture played"
            );
            Ok(played?)
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn as_fast_as_possible_has_no_due_times_and_a_speed_scales_the_log() {
        assert_eq!(Pace::new(0.0).due(5.0), None);
        let mut pace = Pace::new(2.0);
        let first = pace.due(100.0).unwrap();
        let later = pace.due(104.0).unwrap();
        assert_eq!(later - first, Duration::from_secs(2));
        // Out of order: due at once, never before the start.
        assert_eq!(pace.due(90.0).unwrap(), first);
    }
}
