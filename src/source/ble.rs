//! Live scanning with btleplug (BlueZ over D-Bus on Linux).
//!
//! BlueZ reports an advertiser's manufacturer data when it changes and its RSSI
//! with every advert (btleplug asks for duplicate reports), so the scanner
//! remembers which peripherals are iBeacons and turns each RSSI update of one
//! into a sighting.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::{SystemTime, UNIX_EPOCH};

use btleplug::api::{Central, CentralEvent, Manager as _, Peripheral as _, ScanFilter};
use btleplug::platform::{Adapter, Manager, PeripheralId};
use futures::StreamExt;
use serde::Deserialize;
use tokio::sync::mpsc;

use super::Event;
use super::ibeacon::{self, APPLE_COMPANY_ID, IBeacon};
use crate::sighting::Sighting;

/// `[ble]` in the gateway config.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BleConfig {
    /// Adapter to scan with, as BlueZ names it (`hci0`); the first one if unset.
    pub adapter: Option<String>,
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
    #[error("Bluetooth: {0}")]
    Scan(#[from] btleplug::Error),
}

/// Opens the configured adapter.
pub async fn adapter(config: &BleConfig) -> Result<Adapter, BleError> {
    let manager = Manager::new().await.map_err(BleError::NoBluez)?;
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

/// Scans until `events` is closed or the adapter fails, sending one
/// [`Event::Advert`] per iBeacon advert heard; `observer` names this host.
pub async fn scan(
    adapter: &Adapter,
    observer: Arc<str>,
    events: mpsc::Sender<Event>,
) -> Result<(), BleError> {
    let mut stream = adapter.events().await?;
    adapter.start_scan(ScanFilter::default()).await?;
    let mut beacons: HashMap<PeripheralId, IBeacon> = HashMap::new();
    while let Some(event) = stream.next().await {
        let heard = match event {
            CentralEvent::ManufacturerDataAdvertisement {
                id,
                manufacturer_data,
            } => {
                match manufacturer_data
                    .get(&APPLE_COMPANY_ID)
                    .and_then(|payload| ibeacon::parse_payload(payload))
                {
                    Some(beacon) => {
                        beacons.insert(id.clone(), beacon);
                        let rssi = match adapter.peripheral(&id).await {
                            Ok(p) => p.properties().await.ok().flatten().and_then(|p| p.rssi),
                            Err(_) => None,
                        };
                        rssi.map(|rssi| (beacon, rssi))
                    }
                    None => {
                        // The address now sends something else (addresses rotate).
                        beacons.remove(&id);
                        None
                    }
                }
            }
            CentralEvent::RssiUpdate { id, rssi } => beacons.get(&id).map(|&b| (b, rssi)),
            _ => None,
        };
        if let Some((beacon, rssi)) = heard {
            let sighting = Sighting {
                t: now(),
                observer: observer.clone(),
                advertiser: beacon.id,
                tx_power: Some(beacon.measured_power),
                rssi,
            };
            if events.send(Event::Advert(sighting)).await.is_err() {
                break;
            }
        }
    }
    adapter.stop_scan().await.ok();
    Ok(())
}

fn now() -> f64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0.0, |d| d.as_secs_f64())
}
