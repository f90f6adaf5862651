//! MQTT: everything between the runtime and the broker. Topics and payloads
//! are documented in docs/mqtt.md, with JSON Schemas in docs/schemas/.
//!
//! - [`sink`]: the broker as a sink of outputs (with Home Assistant discovery,
//!   presence and occupancy), and [`source`]: as a source of what the gateway
//!   subscribes to; both over one [`link`];
//! - `crate::topics` (beside this module, since `--print` and `--out` use it
//!   too): topic names, and outputs encoded as JSON messages;
//! - [`config`]: `[mqtt]`, client options, credentials, TLS (rustls on ring);
//! - [`link`]: the connection task: reconnects, offline [`queue`], redelivery,
//!   retained status with last will;
//! - [`inbound`]: subscribed topics (route requests, feedback, phone scans,
//!   shared sightings) read into what the runtime consumes;
//! - [`sightings`]: the shared-sightings payload between gateways of a site;
//! - [`cluster`]: `[cluster]`, an edge's sightings by shard and a
//!   locator's heartbeats (many gateways, each device located once);
//! - [`occupancy`]: the retained devices-per-place payload;
//! - [`discovery`]: Home Assistant MQTT discovery, and [`tracker_gate`]:
//!   which devices get a tracker there;
//! - [`broker`]: the embedded broker used when no url is configured.

pub mod broker;
pub mod cluster;
pub(crate) mod config;
pub(crate) mod discovery;
pub mod inbound;
pub(crate) mod link;
pub(crate) mod occupancy;
pub(crate) mod queue;
pub mod receivers;
pub mod sightings;
pub mod sink;
pub(crate) mod source;
pub(crate) mod tracker_gate;

use std::time::Duration;

pub use config::MqttConfig;
pub(crate) use config::MqttError;
pub(crate) use link::{Link, LinkSettings, LinkStats, Received};

/// The broker to use: `override_url`, else `[mqtt] url`, else an embedded
/// broker started now on 127.0.0.1.
pub fn broker_url(config: &MqttConfig, override_url: Option<String>) -> anyhow::Result<String> {
    if let Some(url) = override_url.or_else(|| config.url.clone()) {
        return Ok(url);
    }
    let url = broker::start(config.embedded_port, config.max_payload_bytes)?;
    tracing::info!(
        %url,
        "no [mqtt] url configured: started an embedded MQTT broker on 127.0.0.1; \
         subscribers connect to {url}"
    );
    Ok(url)
}

/// Link settings for `url` from `[mqtt]`; `status` is `Some(topic)` for a
/// gateway that announces itself (retained `online`, last will `offline`);
/// `low_latency` sends each message at once (see [`LinkSettings`]).
pub(crate) fn link_settings(
    config: &MqttConfig,
    url: &str,
    client_id: &str,
    status: Option<String>,
    subscriptions: Vec<String>,
    low_latency: bool,
) -> Result<LinkSettings, MqttError> {
    Ok(LinkSettings {
        brokers: std::iter::once(url)
            .chain(config.fallback_urls.iter().map(String::as_str))
            .map(|url| config.options(url, client_id))
            .collect::<Result<_, _>>()?,
        qos: config.qos(),
        status: status.map(|topic| (topic, "online".to_owned(), "offline".to_owned())),
        subscriptions: subscriptions
            .into_iter()
            .map(|f| (f, config.qos()))
            .collect(),
        queue_max_messages: config.queue_max_messages,
        queue_max_bytes: config.queue_max_bytes,
        reconnect_min: Duration::from_secs_f64(config.reconnect_min_s),
        reconnect_max: Duration::from_secs_f64(config.reconnect_max_s),
        shutdown_grace: Duration::from_secs_f64(config.shutdown_grace_s),
        low_latency,
        inbound_capacity: 1024,
        max_inbound_payload: config.max_payload_bytes,
    })
}
