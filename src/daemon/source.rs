//! Where the daemon's own sightings come from: the Bluetooth adapter, kept
//! alive by a supervisor that retries with capped backoff while the adapter is
//! missing or lost, or a log played back at a given speed (`run --replay`).
//! Both feed the same channel; the MQTT side keeps serving meanwhile.

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use tokio::sync::{mpsc, watch};
use tokio::time::Instant;

use crate::mqtt::stats::BleStatus;
use crate::source::Event;
use crate::source::ble::{self, BleConfig};
use crate::source::log::LogReader;

/// Backoff between attempts to open the adapter. The cap keeps a returning
/// adapter scanning within a few seconds; each attempt is one D-Bus call.
const BLE_RETRY_MIN: Duration = Duration::from_secs(1);
const BLE_RETRY_MAX: Duration = Duration::from_secs(5);

/// Scans for as long as `events` is open, reopening the adapter after every
/// failure; publishes the radio's state on `status` (and counts the silent
/// scans restarted there).
pub async fn radio(
    config: BleConfig,
    observer: Arc<str>,
    events: mpsc::Sender<Event>,
    status: watch::Sender<BleStatus>,
) {
    let report =
        |state: &'static str, error: Option<String>, failures: u64, retry_in_s: Option<f64>| {
            status.send_modify(|s| {
                s.state = state;
                s.error = error;
                s.failures = failures;
                s.retry_in_s = retry_in_s;
            });
        };
    let mut manager = None;
    let mut backoff = BLE_RETRY_MIN;
    let mut failures = 0u64;
    loop {
        let error = match open(&mut manager, &config).await {
            Ok(adapter) => {
                tracing::info!("Bluetooth adapter open; scanning");
                failures = 0;
                backoff = BLE_RETRY_MIN;
                report("scanning", None, 0, None);
                let restarted = || status.send_modify(|s| s.scan_restarts += 1);
                let scan = ble::scan(
                    &adapter,
                    observer.clone(),
                    config.silent_restart(),
                    events.clone(),
                    restarted,
                );
                match scan.await {
                    Ok(()) => return,
                    Err(e) => e.to_string(),
                }
            }
            Err(e) => e.to_string(),
        };
        failures += 1;
        // Every retry is in the stats; the log gets the first few and then
        // ever fewer, so a machine without Bluetooth does not fill it.
        if failures.is_power_of_two() {
            tracing::warn!(
                retry_in_s = backoff.as_secs_f64(),
                failures,
                "Bluetooth unavailable: {error}; MQTT keeps serving, retrying"
            );
        }
        report(
            "retrying",
            Some(error),
            failures,
            Some(backoff.as_secs_f64()),
        );
        tokio::select! {
            _ = tokio::time::sleep(backoff) => {}
            _ = events.closed() => return,
        }
        backoff = (backoff * 2).min(BLE_RETRY_MAX);
    }
}

/// The configured adapter, through the one BlueZ connection of `manager`
/// (made on first use).
async fn open(
    manager: &mut Option<ble::Manager>,
    config: &BleConfig,
) -> Result<ble::Adapter, ble::BleError> {
    let manager = match manager {
        Some(m) => m,
        none => none.insert(ble::connect().await?),
    };
    ble::adapter(manager, config).await
}

/// A log to play instead of the radio.
#[derive(Clone, Debug)]
pub struct Replay {
    pub log: PathBuf,
    /// 1 is real time, 0 as fast as possible.
    pub speed: f64,
}

/// Plays `replay` into `events`, keeping the log's pace scaled by its speed;
/// a bad line is logged and skipped (the daemon never stops on input).
pub async fn replay(replay: Replay, events: mpsc::Sender<Event>) -> anyhow::Result<()> {
    let mut reader = LogReader::open(&replay.log, true)?;
    let started = Instant::now();
    let mut first_t = None;
    // The reader does blocking file reads; lines are short and the file local,
    // so reading them on the runtime is cheaper than a thread hop per line.
    for event in reader.by_ref() {
        let event = event?;
        if replay.speed > 0.0 {
            let t0 = *first_t.get_or_insert(event.t());
            let due = Duration::from_secs_f64(((event.t() - t0) / replay.speed).max(0.0));
            tokio::select! {
                _ = tokio::time::sleep_until(started + due) => {}
                // Shutting down: stop now rather than at the next advert.
                _ = events.closed() => break,
            }
        }
        if events.send(event).await.is_err() {
            break;
        }
    }
    tracing::info!(
        log = %replay.log.display(),
        skipped_lines = reader.skipped(),
        "replay finished; still serving MQTT"
    );
    Ok(())
}
