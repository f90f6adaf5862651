//! The MQTT connection (rumqttc): broker address, client options, and a
//! publisher that drives the client's event loop in the background.

use std::time::Duration;

use rumqttc::{AsyncClient, Event, EventLoop, MqttOptions, Outgoing, QoS};
use serde::Deserialize;

use crate::publish::Message;

/// `[mqtt]` in the gateway config.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MqttConfig {
    /// `mqtt://host:port`. `--mqtt-url` overrides it.
    pub url: Option<String>,
    /// Defaults to `gangway-<gateway id>`.
    pub client_id: Option<String>,
    /// Topic prefix; defaults to `gangway/<gateway id>`.
    pub prefix: Option<String>,
    /// QoS of published messages: 0, 1 or 2.
    pub qos: u8,
    pub keep_alive_s: u64,
}

impl Default for MqttConfig {
    fn default() -> Self {
        MqttConfig {
            url: None,
            client_id: None,
            prefix: None,
            qos: 1,
            keep_alive_s: 30,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum MqttError {
    #[error("MQTT url {url:?}: {reason}; write it as mqtt://host:port")]
    BadUrl { url: String, reason: String },
    #[error("[mqtt] qos = {0}: QoS must be 0, 1 or 2")]
    BadQos(u8),
    #[error("MQTT: {0}")]
    Client(#[from] rumqttc::ClientError),
    #[error("MQTT connection to {url}: {source}")]
    Connection {
        url: String,
        source: rumqttc::ConnectionError,
    },
}

/// Client options for `url` (`mqtt://host[:port]`, port 1883 by default).
pub fn options(url: &str, client_id: &str, keep_alive_s: u64) -> Result<MqttOptions, MqttError> {
    let bad = |reason: &str| MqttError::BadUrl {
        url: url.to_owned(),
        reason: reason.to_owned(),
    };
    let parsed = url::Url::parse(url).map_err(|e| bad(&e.to_string()))?;
    if parsed.scheme() != "mqtt" {
        return Err(bad("only the mqtt:// scheme is supported"));
    }
    let host = parsed.host_str().ok_or_else(|| bad("no host"))?;
    let port = parsed.port().unwrap_or(1883);
    let mut options = MqttOptions::new(client_id, host, port);
    options.set_keep_alive(Duration::from_secs(keep_alive_s.max(5)));
    Ok(options)
}

pub fn qos(level: u8) -> Result<QoS, MqttError> {
    match level {
        0 => Ok(QoS::AtMostOnce),
        1 => Ok(QoS::AtLeastOnce),
        2 => Ok(QoS::ExactlyOnce),
        n => Err(MqttError::BadQos(n)),
    }
}

/// Publishes messages on one connection. The event loop runs on a task of its
/// own; [`Publisher::close`] waits until everything queued has gone out.
pub struct Publisher {
    client: AsyncClient,
    qos: QoS,
    driver: tokio::task::JoinHandle<Result<(), MqttError>>,
}

impl Publisher {
    /// Connects to `url` and waits for the broker's CONNACK.
    pub async fn connect(
        url: &str,
        client_id: &str,
        config: &MqttConfig,
    ) -> Result<Self, MqttError> {
        let qos = qos(config.qos)?;
        let (client, mut eventloop) =
            AsyncClient::new(options(url, client_id, config.keep_alive_s)?, 1024);
        wait_connected(&mut eventloop, url).await?;
        let url = url.to_owned();
        let driver = tokio::spawn(async move { drive(eventloop, url).await });
        Ok(Publisher {
            client,
            qos,
            driver,
        })
    }

    pub async fn send(&self, message: &Message) -> Result<(), MqttError> {
        let payload = serde_json::to_vec(&message.payload).expect("JSON values serialize");
        self.client
            .publish(&message.topic, self.qos, message.retain, payload)
            .await?;
        Ok(())
    }

    /// Disconnects after everything queued before it has been sent.
    pub async fn close(self) -> Result<(), MqttError> {
        self.client.disconnect().await?;
        self.driver.await.expect("the MQTT driver does not panic")
    }
}

async fn wait_connected(eventloop: &mut EventLoop, url: &str) -> Result<(), MqttError> {
    loop {
        match eventloop.poll().await {
            Ok(Event::Incoming(rumqttc::Packet::ConnAck(_))) => return Ok(()),
            Ok(_) => {}
            Err(source) => {
                return Err(MqttError::Connection {
                    url: url.to_owned(),
                    source,
                });
            }
        }
    }
}

/// Polls the event loop until the client's DISCONNECT has gone out.
async fn drive(mut eventloop: EventLoop, url: String) -> Result<(), MqttError> {
    loop {
        match eventloop.poll().await {
            Ok(Event::Outgoing(Outgoing::Disconnect)) => return Ok(()),
            Ok(_) => {}
            Err(source) => return Err(MqttError::Connection { url, source }),
        }
    }
}
