//! Live scanning with btleplug (BlueZ over D-Bus on Linux).
//!
//! BlueZ announces a new advertiser with its manufacturer data and RSSI
//! (ObjectManager `InterfacesAdded`, which btleplug reports as a discovered
//! device), reports the manufacturer data again when it changes and the RSSI
//! with every advert (btleplug asks for duplicate reports). So the scanner
//! remembers which peripherals are iBeacons, from their discovery or a change
//! of their data, and turns each RSSI update of one into a sighting.
//!
//! A scan also watches its adapter: one that disappears (unplugged, BlueZ
//! restarted) or is powered off ends the scan with [`BleError::AdapterLost`],
//! for the caller to reopen it; and a scan that reports nothing at all for
//! `[ble] silent_restart_s` is stopped and started again, since BlueZ scans
//! are known to go quiet after hours without any error.
//!
//! [`BleSource`] is the radio as a source of the runtime: a supervisor that
//! reopens the adapter with capped backoff while it is missing or lost (the
//! MQTT side keeps serving meanwhile), publishes the radio's state for the
//! stats, and at shutdown stops discovery before it returns.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Duration;

use btleplug::api::{
    Central, CentralEvent, CentralState, Manager as _, Peripheral as _, ScanFilter,
};
use btleplug::platform::PeripheralId;
pub(crate) use btleplug::platform::{Adapter, Manager};
use futures::StreamExt;
use futures::future::BoxFuture;
use serde::Deserialize;
use tokio::sync::watch;
use tokio::time::Instant;

use super::ibeacon::{self, APPLE_COMPANY_ID, IBeacon};
use super::{Shutdown, Source, SourceContext};

use crate::event::Event;
use crate::publish::stats::BleStatus;
use crate::sighting::{Mac, Sighting};
use crate::source::unix_now;

/// How often a scan asks BlueZ whether its adapter is still there and powered
/// (BlueZ's removal signal does not reach btleplug's event stream).
const ADAPTER_CHECK: Duration = Duration::from_secs(2);
/// Most iBeacon peripherals remembered: BlueZ makes a device of every random
/// address it hears, so the table is bounded like anything fed from the air.
const MAX_BEACONS: usize = 4096;
/// Backoff between attempts to open the adapter. The cap keeps a returning
/// adapter scanning within a few seconds; each attempt is one D-Bus call.
const BLE_RETRY_MIN: Duration = Duration::from_secs(1);
const BLE_RETRY_MAX: Duration = Duration::from_secs(5);

/// `[ble]` in the gateway config.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct BleConfig {
    /// Adapter to scan with, as BlueZ names it (`hci0`); the first one if unset.
    pub adapter: Option<String>,
    /// Restart the scan after this many seconds in which the adapter reported
    /// nothing; 0 never restarts.
    pub silent_restart_s: f64,
}

impl Default for BleConfig {
    fn default() -> BleConfig {
        BleConfig {
            adapter: None,
            silent_restart_s: 60.0,
        }
    }
}

impl BleConfig {
    pub(crate) fn validate(&self) -> Result<(), String> {
        if !(self.silent_restart_s.is_finite() && self.silent_restart_s >= 0.0) {
            return Err(format!(
                "[ble] `silent_restart_s` must be 0 (never) or positive seconds, not {}",
                self.silent_restart_s
            ));
        }
        Ok(())
    }

    /// How long a scan may stay silent before it is restarted.
    pub fn silent_restart(&self) -> Option<Duration> {
        (self.silent_restart_s > 0.0).then(|| Duration::from_secs_f64(self.silent_restart_s))
    }
}

#[derive(Debug, thiserror::Error)]
pub enum BleError {
    #[error(
        "cannot reach BlueZ over D-Bus ({0}); is the bluetooth service running \
         (systemctl status bluetooth) and is the system bus available?"
    )]
    NoBluez(btleplug::Error),
    #[error(
        "no Bluetooth adapter found; check `bluetoothctl list` and that the adapter is powered"
    )]
    NoAdapter,
    #[error("no adapter named {0:?}; adapters present: {1}")]
    AdapterNotFound(String, String),
    #[error(
        "the Bluetooth adapter {0} went away or was powered off; check `bluetoothctl list` \
         and `bluetoothctl show`"
    )]
    AdapterLost(String),
    #[error("the Bluetooth adapter {0} is powered off; `bluetoothctl power on` turns it on")]
    PoweredOff(String),
    #[error("BlueZ stopped sending events (the D-Bus connection closed)")]
    EventsEnded,
    #[error("Bluetooth: {0}")]
    Scan(#[from] btleplug::Error),
}

/// Connects to BlueZ over the system bus. Keep the manager for as long as the
/// process scans: each one holds a D-Bus connection (and a task serving it)
/// that stays open until the bus closes it, so connecting per attempt would
/// leak one connection per retry.
pub async fn connect() -> Result<Manager, BleError> {
    Manager::new().await.map_err(BleError::NoBluez)
}

/// Opens the configured adapter, which must be powered.
pub async fn adapter(manager: &Manager, config: &BleConfig) -> Result<Adapter, BleError> {
    let adapter = find(manager, config).await?;
    if adapter.adapter_state().await? != CentralState::PoweredOn {
        return Err(BleError::PoweredOff(name(&adapter).await));
    }
    Ok(adapter)
}

async fn find(manager: &Manager, config: &BleConfig) -> Result<Adapter, BleError> {
    let adapters = manager.adapters().await.map_err(BleError::NoBluez)?;
    let Some(name) = &config.adapter else {
        return adapters.into_iter().next().ok_or(BleError::NoAdapter);
    };
    let mut names = Vec::new();
    for a in adapters {
        let info = a.adapter_info().await.unwrap_or_default();
        if info.split_whitespace().next() == Some(name) {
            return Ok(a);
        }
        names.push(info);
    }
    Err(BleError::AdapterNotFound(name.clone(), names.join(", ")))
}

/// The adapter's name as BlueZ gives it (`hci0`).
async fn name(adapter: &Adapter) -> String {
    adapter
        .adapter_info()
        .await
        .ok()
        .and_then(|info| info.split_whitespace().next().map(str::to_owned))
        .unwrap_or_else(|| "(unnamed)".to_owned())
}

/// The radio as a source: scans for as long as the runtime runs, reopening
/// the adapter after every failure, and publishes the radio's state on its
/// status channel (the stats' `ble`, with the silent scans restarted).
pub struct BleSource {
    config: BleConfig,
    /// This host, the observer of what it hears.
    observer: Arc<str>,
    status: watch::Sender<BleStatus>,
}

impl BleSource {
    /// The source and the radio's state for the stats.
    pub fn new(config: BleConfig, observer: Arc<str>) -> (BleSource, watch::Receiver<BleStatus>) {
        let (status, rx) = watch::channel(BleStatus {
            state: "starting",
            ..BleStatus::default()
        });
        (
            BleSource {
                config,
                observer,
                status,
            },
            rx,
        )
    }
}

impl Source for BleSource {
    fn name(&self) -> &'static str {
        "ble"
    }

    fn run(self: Box<Self>, cx: SourceContext) -> BoxFuture<'static, anyhow::Result<()>> {
        Box::pin(async move {
            self.supervise(cx).await;
            Ok(())
        })
    }
}

impl BleSource {
    async fn supervise(self, mut cx: SourceContext) {
        let report =
            |state: &'static str, error: Option<String>, failures: u64, retry_in_s: Option<f64>| {
                self.status.send_modify(|s| {
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
            let opened = tokio::select! {
                opened = open(&mut manager, &self.config) => opened,
                () = cx.shutdown.recv() => return,
            };
            let error = match opened {
                Ok(adapter) => {
                    tracing::info!("Bluetooth adapter open; scanning");
                    failures = 0;
                    backoff = BLE_RETRY_MIN;
                    report("scanning", None, 0, None);
                    let restarted = || self.status.send_modify(|s| s.scan_restarts += 1);
                    let scan = scan(
                        &adapter,
                        self.observer.clone(),
                        self.config.silent_restart(),
                        &mut cx,
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
                () = tokio::time::sleep(backoff) => {}
                () = cx.shutdown.recv() => return,
            }
            backoff = (backoff * 2).min(BLE_RETRY_MAX);
        }
    }
}

/// The configured adapter, through the one BlueZ connection of `manager`
/// (made on first use).
async fn open(manager: &mut Option<Manager>, config: &BleConfig) -> Result<Adapter, BleError> {
    let manager = match manager {
        Some(m) => m,
        none => none.insert(connect().await?),
    };
    adapter(manager, config).await
}

/// Scans until shutdown or until the runtime is gone (then returns `Ok`
/// after stopping discovery), or until the adapter fails, sending one
/// [`Event::Advert`] per iBeacon advert heard; `observer` names this host. A
/// scan silent for `silent_restart` is restarted and `restarted` called.
pub async fn scan(
    adapter: &Adapter,
    observer: Arc<str>,
    silent_restart: Option<Duration>,
    cx: &mut SourceContext,
    mut restarted: impl FnMut(),
) -> Result<(), BleError> {
    let mut shutdown: Shutdown = cx.shutdown.clone();
    let name = name(adapter).await;
    let mut stream = adapter.events().await?;
    adapter.start_scan(ScanFilter::default()).await?;
    let mut heard = Heard::default();
    let mut check = tokio::time::interval(ADAPTER_CHECK);
    check.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    // Without a restart time the silence branch is off and its timer unused.
    let silent_for = silent_restart.unwrap_or(ADAPTER_CHECK);
    let mut last_event = Instant::now();
    let silence = tokio::time::sleep(silent_for);
    tokio::pin!(silence);
    let result = loop {
        tokio::select! {
            event = stream.next() => {
                let Some(event) = event else { break Err(BleError::EventsEnded) };
                last_event = Instant::now();
                if matches!(event, CentralEvent::StateUpdate(CentralState::PoweredOff)) {
                    break Err(BleError::AdapterLost(name));
                }
                if let Some((beacon, mac, rssi)) = heard.event(adapter, event).await {
                    let sighting = Sighting {
                        advertiser_mac: Some(mac),
                        t: unix_now(),
                        observer: observer.clone(),
                        advertiser: beacon.id,
                        tx_power: Some(beacon.measured_power),
                        rssi,
                    };
                    if cx.events(vec![Event::Advert(sighting)]).await.is_err() {
                        break Ok(());
                    }
                }
            }
            _ = check.tick() => {
                // A missing adapter reads as powered off.
                if adapter.adapter_state().await? != CentralState::PoweredOn {
                    break Err(BleError::AdapterLost(name));
                }
            }
            () = &mut silence, if silent_restart.is_some() => {
                let due = last_event + silent_for;
                if due > Instant::now() {
                    silence.as_mut().reset(due);
                    continue;
                }
                tracing::warn!(
                    adapter = name,
                    silent_s = silent_for.as_secs_f64(),
                    "the Bluetooth scan reported nothing for [ble] silent_restart_s; restarting it"
                );
                adapter.stop_scan().await.ok();
                adapter.start_scan(ScanFilter::default()).await?;
                restarted();
                last_event = Instant::now();
                silence.as_mut().reset(last_event + silent_for);
            }
            () = shutdown.recv() => break Ok(()),
        }
    };
    // Leave BlueZ not discovering on our account; the adapter may be gone.
    adapter.stop_scan().await.ok();
    result
}

/// The peripherals known to send iBeacon frames.
#[derive(Default)]
struct Heard {
    beacons: HashMap<PeripheralId, (IBeacon, Mac)>,
}

impl Heard {
    /// The iBeacon, its sender's address and the RSSI an event reports, if
    /// it is an advert of one.
    async fn event(
        &mut self,
        adapter: &Adapter,
        event: CentralEvent,
    ) -> Option<(IBeacon, Mac, i16)> {
        match event {
            // A new (or already known) device: its first advert's data.
            CentralEvent::DeviceDiscovered(id) => {
                let properties = adapter
                    .peripheral(&id)
                    .await
                    .ok()?
                    .properties()
                    .await
                    .ok()??;
                let mac = Mac(properties.address.into_inner());
                self.classify(id, mac, &properties.manufacturer_data);
                None
            }
            CentralEvent::ManufacturerDataAdvertisement {
                id,
                manufacturer_data,
            } => {
                let peripheral = adapter.peripheral(&id).await.ok()?;
                let properties = peripheral.properties().await.ok()??;
                let mac = Mac(properties.address.into_inner());
                let (beacon, mac) = self.classify(id, mac, &manufacturer_data)?;
                Some((beacon, mac, properties.rssi?))
            }
            CentralEvent::RssiUpdate { id, rssi } => {
                self.beacons.get(&id).map(|&(b, mac)| (b, mac, rssi))
            }
            _ => None,
        }
    }

    /// Remembers whether `id` sends iBeacon frames, judging by its latest
    /// manufacturer data.
    fn classify(
        &mut self,
        id: PeripheralId,
        mac: Mac,
        manufacturer_data: &HashMap<u16, Vec<u8>>,
    ) -> Option<(IBeacon, Mac)> {
        let Some(beacon) = manufacturer_data
            .get(&APPLE_COMPANY_ID)
            .and_then(|payload| ibeacon::parse_payload(payload))
        else {
            // The address now sends something else (addresses rotate).
            self.beacons.remove(&id);
            return None;
        };
        if self.beacons.len() >= MAX_BEACONS && !self.beacons.contains_key(&id) {
            let evicted = self.beacons.keys().next().cloned();
            if let Some(evicted) = evicted {
                self.beacons.remove(&evicted);
            }
        }
        self.beacons.insert(id, (beacon, mac));
        Some((beacon, mac))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(toml_text: &str) -> BleConfig {
        toml::from_str(toml_text).unwrap()
    }

    #[test]
    fn silent_restart_defaults_to_a_minute_and_zero_turns_it_off() {
        assert_eq!(config("").silent_restart(), Some(Duration::from_secs(60)));
        assert_eq!(config("silent_restart_s = 0").silent_restart(), None);
        assert_eq!(
            config("silent_restart_s = 2.5").silent_restart(),
            Some(Duration::from_millis(2500))
        );
    }

    #[test]
    fn a_negative_or_infinite_silent_restart_names_the_key() {
        for bad in [
            "silent_restart_s = -1",
            "silent_restart_s = inf",
            "silent_restart_s = nan",
        ] {
            let error = config(bad).validate().unwrap_err();
            assert!(error.contains("[ble] `silent_restart_s`"), "{bad}: {error}");
        }
    }
}
