//! The gateway daemon: live BLE sightings through the pipeline to MQTT, until
//! SIGTERM or SIGINT.

use std::sync::Arc;

use anyhow::Context;
use tokio::signal::unix::{SignalKind, signal};
use tokio::sync::mpsc;

use crate::config::Config;
use crate::mqtt::Publisher;
use crate::pipeline::Pipeline;
use crate::site::Site;
use crate::source::ble;

/// Runs until a shutdown signal; `mqtt_url` overrides `[mqtt] url`.
pub async fn run(config: Config, site: Arc<Site>, mqtt_url: Option<String>) -> anyhow::Result<()> {
    let mut pipeline = Pipeline::new(&config, site)?;
    let url = mqtt_url.or_else(|| config.mqtt.url.clone()).context(
        "no MQTT broker: set [mqtt] url in the config or pass --mqtt-url mqtt://host:port",
    )?;
    let client_id = config
        .mqtt
        .client_id
        .clone()
        .unwrap_or_else(|| format!("gangway-{}", config.gateway_id));
    let publisher = Publisher::connect(&url, &client_id, &config.mqtt).await?;
    tracing::info!(%url, prefix = pipeline.topics().prefix(), "connected to the broker");

    let adapter = ble::adapter(&config.ble).await?;
    let (tx, mut rx) = mpsc::channel(4096);
    let observer: Arc<str> = config.gateway_id.as_str().into();
    let scanner = tokio::spawn(async move { ble::scan(&adapter, observer, tx).await });
    tracing::info!("scanning");
    // Tell systemd (Type=notify) we are up; a no-op outside systemd.
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Ready]);

    let mut terminate = signal(SignalKind::terminate())?;
    let mut out = Vec::new();
    loop {
        tokio::select! {
            event = rx.recv() => {
                let Some(event) = event else { break };
                pipeline.handle(&event, &mut out);
                for message in out.drain(..) {
                    publisher.send(&message).await?;
                }
            }
            _ = terminate.recv() => break,
            _ = tokio::signal::ctrl_c() => break,
        }
    }
    tracing::info!("shutting down");
    let _ = sd_notify::notify(&[sd_notify::NotifyState::Stopping]);
    drop(rx);
    scanner.abort();
    publisher.close().await?;
    Ok(())
}
