//! The embedded broker (rumqttd) that `run` and `replay` start on 127.0.0.1
//! when no broker url is configured, so the quickstart needs nothing
//! installed. It lives as long as the process; subscribers connect to it like
//! to any broker.

use std::collections::HashMap;
use std::net::{Ipv4Addr, SocketAddr, TcpListener, TcpStream};
use std::time::{Duration, Instant};

use rumqttd::{Broker, Config, ConnectionSettings, RouterConfig, ServerSettings};

/// Starts the broker on `127.0.0.1:port` and returns its `mqtt://` url.
pub fn start(port: u16, max_payload_bytes: usize) -> anyhow::Result<String> {
    let listen = SocketAddr::from((Ipv4Addr::LOCALHOST, port));
    // rumqttd binds on a thread of its own and only logs a failure there;
    // binding once here turns a busy port into a clear error.
    drop(TcpListener::bind(listen).map_err(|e| {
        anyhow::anyhow!(
            "cannot start the embedded MQTT broker on {listen}: {e}; is another broker \
             running there? Point [mqtt] url (or --mqtt-url) at it, or set [mqtt] embedded_port"
        )
    })?);
    let server = ServerSettings {
        name: "gangway-embedded".into(),
        listen,
        tls: None,
        next_connection_delay_ms: 1,
        connections: ConnectionSettings {
            connection_timeout_ms: 60_000,
            // Room above the gateway's own limit, so that an oversized request
            // reaches the gateway and gets its error reply.
            max_payload_size: (max_payload_bytes * 4).max(1 << 20),
            max_inflight_count: 500,
            auth: None,
            external_auth: None,
            dynamic_filters: true,
        },
    };
    let config = Config {
        id: 0,
        router: RouterConfig {
            max_connections: 1000,
            max_outgoing_packet_count: 200,
            max_segment_size: 16 << 20,
            max_segment_count: 10,
            ..RouterConfig::default()
        },
        v4: Some(HashMap::from([("1".to_owned(), server)])),
        ..Config::default()
    };
    let mut broker = Broker::new(config);
    std::thread::Builder::new()
        .name("mqtt-broker".into())
        .spawn(move || {
            if let Err(e) = broker.start() {
                tracing::error!("embedded MQTT broker stopped: {e}");
            }
        })?;
    // The broker binds on its own thread; wait for it so the first connect
    // does not fail and back off.
    let deadline = Instant::now() + Duration::from_secs(5);
    while TcpStream::connect_timeout(&listen, Duration::from_millis(100)).is_err() {
        anyhow::ensure!(
            Instant::now() < deadline,
            "the embedded MQTT broker did not start listening on {listen}"
        );
        std::thread::sleep(Duration::from_millis(10));
    }
    Ok(format!("mqtt://{listen}"))
}
