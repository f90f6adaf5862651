//! `[mqtt]` in the gateway config, and how it becomes rumqttc client options:
//! broker address, credentials, TLS, limits and timings.
//!
//! The password is never in the config or on a command line: it is read from
//! `password_file`, or from the systemd credential `mqtt-password`
//! (`LoadCredential=`) when `password_file` is unset.

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use rumqttc::{MqttOptions, QoS, TlsConfiguration, Transport};
use rustls::pki_types::pem::PemObject;
use rustls::pki_types::{CertificateDer, PrivateKeyDer};
use serde::Deserialize;

/// Name of the systemd credential read when `password_file` is unset.
pub(crate) const PASSWORD_CREDENTIAL: &str = "mqtt-password";

/// Largest `max_payload_bytes`: far below the packets the link sends and
/// takes, so an oversized request still gets its error reply.
const MAX_PAYLOAD_LIMIT: usize = 512 * 1024;

/// `[mqtt]` in the gateway config.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct MqttConfig {
    /// `mqtt://host[:port]` (1883) or `mqtts://host[:port]` (8883). `--mqtt-url`
    /// overrides it; with neither, an embedded broker is started on 127.0.0.1.
    pub url: Option<String>,
    /// Other nodes of the same (clustered) broker, tried in turn after
    /// `url` when a connection fails or is lost.
    pub fallback_urls: Vec<String>,
    /// Defaults to `gangway-<gateway id>`.
    pub client_id: Option<String>,
    pub username: Option<String>,
    /// File holding the password (trailing newline ignored).
    pub password_file: Option<PathBuf>,
    /// PEM CA certificates for `mqtts://`; the system roots when unset.
    pub ca_file: Option<PathBuf>,
    /// PEM client certificate chain and key, for brokers that require them.
    pub client_cert: Option<PathBuf>,
    pub client_key: Option<PathBuf>,
    /// QoS of published messages and subscriptions: 0, 1 or 2.
    pub qos: u8,
    pub keep_alive_s: u64,
    /// Topic prefix; defaults to `gangway/<gateway id>`.
    pub prefix: Option<String>,
    /// Prefix shared by all gateways of one site (shared sightings); defaults to
    /// `gangway/sites/<site name>`.
    pub site_prefix: Option<String>,
    /// Port of the embedded broker started when no url is configured.
    pub embedded_port: u16,
    /// Incoming payloads larger than this are dropped and counted (a route
    /// request gets a `payload_too_large` error reply).
    pub max_payload_bytes: usize,
    /// Offline queue bounds: while the broker is unreachable, outgoing messages
    /// wait here; past either bound the oldest are dropped and counted.
    pub queue_max_messages: usize,
    pub queue_max_bytes: usize,
    /// Reconnect backoff: first delay, doubled per failure up to the cap.
    pub reconnect_min_s: f64,
    pub reconnect_max_s: f64,
    /// Seconds between retained `<prefix>/stats` messages.
    pub stats_interval_s: f64,
    /// Home Assistant MQTT discovery.
    pub ha_discovery: bool,
    pub discovery_prefix: String,
    /// Which devices get a Home Assistant tracker (`mqtt::tracker_gate`):
    /// device ids, or prefixes ending in `*`; empty, every device.
    pub ha_devices: Vec<String>,
    /// Located fixes a device needs before it gets a tracker.
    pub ha_min_fixes: u32,
    /// New trackers announced per minute at most.
    pub ha_new_trackers_per_minute: u32,
    /// Seconds a graceful shutdown waits for queued and in-flight messages.
    pub shutdown_grace_s: f64,
    /// Other gateways' sightings further ahead of this gateway's clock are
    /// refused and counted (a future time would silence a tag until then).
    pub max_clock_skew_s: f64,
    /// `[mqtt.espresense]`: ESPresense room nodes on this broker
    /// (`mqtt::receivers`); absent, they are not read.
    pub espresense: Option<super::receivers::EspresenseConfig>,
    /// `[mqtt.theengs]`: Theengs Gateway or OpenMQTTGateway on this broker.
    pub theengs: Option<super::receivers::TheengsConfig>,
}

impl Default for MqttConfig {
    fn default() -> Self {
        MqttConfig {
            url: None,
            fallback_urls: Vec::new(),
            client_id: None,
            username: None,
            password_file: None,
            ca_file: None,
            client_cert: None,
            client_key: None,
            qos: 1,
            keep_alive_s: 30,
            prefix: None,
            site_prefix: None,
            embedded_port: 1883,
            max_payload_bytes: 16 * 1024,
            queue_max_messages: 10_000,
            queue_max_bytes: 8 << 20,
            reconnect_min_s: 0.5,
            reconnect_max_s: 30.0,
            stats_interval_s: 30.0,
            ha_discovery: true,
            discovery_prefix: "homeassistant".into(),
            ha_devices: Vec::new(),
            ha_min_fixes: 3,
            ha_new_trackers_per_minute: 30,
            shutdown_grace_s: 5.0,
            max_clock_skew_s: super::inbound::DEFAULT_MAX_CLOCK_SKEW_S,
            espresense: None,
            theengs: None,
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum MqttError {
    #[error("MQTT url {url:?}: {reason}; write it as mqtt://host:port or mqtts://host:port")]
    BadUrl { url: String, reason: String },
    #[error("[mqtt] {0}")]
    Invalid(String),
    #[error("{}: {what}: {reason}", path.display())]
    File {
        path: PathBuf,
        what: &'static str,
        reason: String,
    },
    #[error("TLS setup: {0}")]
    Tls(#[from] rustls::Error),
}

impl MqttConfig {
    /// Resolves relative file paths against the config file's directory.
    pub(crate) fn resolve_paths(&mut self, base: &Path) {
        for path in [
            &mut self.password_file,
            &mut self.ca_file,
            &mut self.client_cert,
            &mut self.client_key,
        ]
        .into_iter()
        .flatten()
        {
            *path = base.join(&*path);
        }
    }

    /// Checks values that serde cannot; the message names the key.
    pub(crate) fn validate(&self) -> Result<(), MqttError> {
        qos(self.qos)?;
        let bad = |m: &str| Err(MqttError::Invalid(m.to_owned()));
        if self.client_cert.is_some() != self.client_key.is_some() {
            return bad("`client_cert` and `client_key` go together: set both or neither");
        }
        if self.password_file.is_some() && self.username.is_none() {
            return bad("`password_file` is set but `username` is not");
        }
        if self.url.is_none() && !self.fallback_urls.is_empty() {
            return bad("`fallback_urls` are other nodes of the broker `url` names: set `url` too");
        }
        for url in &self.fallback_urls {
            broker_address(url)?;
        }
        if !(self.reconnect_min_s > 0.0 && self.reconnect_max_s >= self.reconnect_min_s) {
            return bad("`reconnect_min_s` must be positive and at most `reconnect_max_s`");
        }
        if !(self.stats_interval_s >= 1.0 && self.stats_interval_s.is_finite()) {
            return bad("`stats_interval_s` must be at least 1 second");
        }
        if !(self.shutdown_grace_s >= 0.0 && self.shutdown_grace_s.is_finite()) {
            return bad("`shutdown_grace_s` must be a non-negative number of seconds");
        }
        if !(self.max_clock_skew_s >= 0.0 && self.max_clock_skew_s.is_finite()) {
            return bad("`max_clock_skew_s` must be a non-negative number of seconds");
        }
        if self.ha_min_fixes == 0 || self.ha_new_trackers_per_minute == 0 {
            return bad("`ha_min_fixes` and `ha_new_trackers_per_minute` must be at least 1");
        }
        if self.ha_devices.iter().any(|d| d.is_empty() || d == "*") {
            return bad(
                "`ha_devices` lists device ids or prefixes ending in `*`; leave it empty for every device",
            );
        }
        if self.queue_max_messages == 0 || self.queue_max_bytes == 0 {
            return bad("`queue_max_messages` and `queue_max_bytes` must be positive");
        }
        if self.max_payload_bytes == 0 || self.max_payload_bytes > MAX_PAYLOAD_LIMIT {
            return bad("`max_payload_bytes` must be between 1 and 524288");
        }
        for (key, prefix) in [
            ("prefix", self.prefix.as_deref()),
            ("site_prefix", self.site_prefix.as_deref()),
            ("discovery_prefix", Some(self.discovery_prefix.as_str())),
            (
                "espresense.topic",
                self.espresense.as_ref().map(|e| e.topic.as_str()),
            ),
            (
                "theengs.topic",
                self.theengs.as_ref().map(|t| t.topic.as_str()),
            ),
        ] {
            if let Some(p) = prefix
                && !valid_prefix(p)
            {
                return Err(MqttError::Invalid(format!(
                    "`{key}` {p:?} is not a usable topic prefix: it must be non-empty, \
                     without `+`, `#`, control characters or a leading/trailing `/`"
                )));
            }
        }
        Ok(())
    }

    pub(crate) fn qos(&self) -> QoS {
        qos(self.qos).unwrap_or(QoS::AtLeastOnce)
    }

    /// Client options for `url`: address, keep-alive, credentials and TLS.
    pub fn options(&self, url: &str, client_id: &str) -> Result<MqttOptions, MqttError> {
        let (host, port, tls) = broker_address(url)?;
        let mut options = MqttOptions::new(client_id, host, port);
        options.set_keep_alive(Duration::from_secs(self.keep_alive_s.max(5)));
        // Any packet the protocol allows is taken in, so that no message can
        // cost the connection; the link drops payloads over
        // `max_payload_bytes` before they are queued (see `link`).
        options.set_max_packet_size(
            super::link::MQTT_MAX_PACKET,
            super::link::MAX_OUTGOING_PACKET,
        );
        // A persistent session: the broker keeps the subscriptions and queues
        // route requests while the gateway is away (restart, network loss).
        // Outgoing redelivery is the link's own (see `link`): every session
        // starts with a fresh rumqttc event loop, so nothing is replayed twice.
        options.set_clean_session(false);
        if let Some(user) = &self.username {
            options.set_credentials(user, self.password()?.unwrap_or_default());
        }
        if tls {
            options.set_transport(Transport::tls_with_config(TlsConfiguration::Rustls(
                Arc::new(self.tls_config()?),
            )));
        }
        Ok(options)
    }

    /// The password from `password_file`, else from the systemd credential.
    fn password(&self) -> Result<Option<String>, MqttError> {
        let path = match &self.password_file {
            Some(p) => p.clone(),
            None => match std::env::var_os("CREDENTIALS_DIRECTORY") {
                Some(dir) => Path::new(&dir).join(PASSWORD_CREDENTIAL),
                None => return Ok(None),
            },
        };
        let text = std::fs::read_to_string(&path).map_err(|e| MqttError::File {
            path: path.clone(),
            what: "cannot read the MQTT password",
            reason: e.to_string(),
        })?;
        Ok(Some(text.trim_end_matches(['\r', '\n']).to_owned()))
    }

    /// A rustls client config on the `ring` provider (it builds with only a C
    /// compiler, unlike aws-lc-rs which the rumqttc default pulls in).
    fn tls_config(&self) -> Result<rustls::ClientConfig, MqttError> {
        let file_err = |path: &Path, what: &'static str| {
            let path = path.to_owned();
            move |e: rustls::pki_types::pem::Error| MqttError::File {
                path,
                what,
                reason: e.to_string(),
            }
        };
        let mut roots = rustls::RootCertStore::empty();
        match &self.ca_file {
            Some(ca) => {
                let what = "cannot read the CA certificates (PEM)";
                for cert in CertificateDer::pem_file_iter(ca).map_err(file_err(ca, what))? {
                    roots.add(cert.map_err(file_err(ca, what))?)?;
                }
                if roots.is_empty() {
                    return Err(MqttError::File {
                        path: ca.clone(),
                        what,
                        reason: "no certificate in the file".into(),
                    });
                }
            }
            None => {
                let native = rustls_native_certs::load_native_certs();
                roots.add_parsable_certificates(native.certs);
                if roots.is_empty() {
                    return Err(MqttError::Invalid(
                        "mqtts:// without `ca_file` needs the system CA certificates, and none \
                         were found; set `ca_file`"
                            .into(),
                    ));
                }
            }
        }
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let builder = rustls::ClientConfig::builder_with_provider(provider)
            .with_safe_default_protocol_versions()?
            .with_root_certificates(roots);
        Ok(match (&self.client_cert, &self.client_key) {
            (Some(cert), Some(key)) => {
                let what = "cannot read the client certificate (PEM)";
                let chain = CertificateDer::pem_file_iter(cert)
                    .map_err(file_err(cert, what))?
                    .collect::<Result<Vec<_>, _>>()
                    .map_err(file_err(cert, what))?;
                let key = PrivateKeyDer::from_pem_file(key)
                    .map_err(file_err(key, "cannot read the client key (PEM)"))?;
                builder.with_client_auth_cert(chain, key)?
            }
            _ => builder.with_no_client_auth(),
        })
    }
}

pub(crate) fn qos(level: u8) -> Result<QoS, MqttError> {
    match level {
        0 => Ok(QoS::AtMostOnce),
        1 => Ok(QoS::AtLeastOnce),
        2 => Ok(QoS::ExactlyOnce),
        n => Err(MqttError::Invalid(format!(
            "qos = {n}: QoS must be 0, 1 or 2"
        ))),
    }
}

/// Whether `prefix` can start topics: non-empty, no wildcards or control
/// characters, no leading or trailing `/`.
pub(crate) fn valid_prefix(prefix: &str) -> bool {
    !prefix.is_empty()
        && !prefix.starts_with('/')
        && !prefix.ends_with('/')
        && !prefix
            .chars()
            .any(|c| matches!(c, '+' | '#') || c.is_control())
}

/// The host, port and whether TLS is on, of a broker url.
fn broker_address(url: &str) -> Result<(String, u16, bool), MqttError> {
    let bad = |reason: &str| MqttError::BadUrl {
        url: url.to_owned(),
        reason: reason.to_owned(),
    };
    let parsed = url::Url::parse(url).map_err(|e| bad(&e.to_string()))?;
    let tls = match parsed.scheme() {
        "mqtt" => false,
        "mqtts" => true,
        _ => return Err(bad("the scheme must be mqtt:// or mqtts://")),
    };
    if !parsed.username().is_empty() || parsed.password().is_some() {
        return Err(bad(
            "credentials do not belong in the url; use [mqtt] username and password_file",
        ));
    }
    let host = parsed.host_str().ok_or_else(|| bad("no host"))?;
    let port = parsed.port().unwrap_or(if tls { 8883 } else { 1883 });
    Ok((host.to_owned(), port, tls))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn urls_pick_transport_and_default_port() {
        let c = MqttConfig::default();
        let o = c.options("mqtt://broker.local", "gw").unwrap();
        assert_eq!(o.broker_address(), ("broker.local".to_owned(), 1883));
        let o = c.options("mqtt://10.0.0.2:2883", "gw").unwrap();
        assert_eq!(o.broker_address(), ("10.0.0.2".to_owned(), 2883));
        for bad in ["http://x", "broker:1883", "mqtt://user:pw@host"] {
            assert!(
                matches!(c.options(bad, "gw"), Err(MqttError::BadUrl { .. })),
                "{bad}"
            );
        }
    }

    #[test]
    fn tls_with_a_ca_file_builds_and_a_missing_file_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let c = MqttConfig {
            ca_file: Some(dir.path().join("nope.pem")),
            ..MqttConfig::default()
        };
        let err = c.options("mqtts://host", "gw").unwrap_err().to_string();
        assert!(err.contains("nope.pem"), "{err}");
        let empty = dir.path().join("empty.pem");
        std::fs::write(&empty, "not a certificate\n").unwrap();
        let c = MqttConfig {
            ca_file: Some(empty),
            ..MqttConfig::default()
        };
        let err = c.options("mqtts://host", "gw").unwrap_err().to_string();
        assert!(err.contains("no certificate"), "{err}");
    }

    #[test]
    fn the_password_comes_from_its_file_without_the_newline() {
        let dir = tempfile::tempdir().unwrap();
        let file = dir.path().join("pw");
        std::fs::write(&file, "s3cret\n").unwrap();
        let c = MqttConfig {
            username: Some("gw".into()),
            password_file: Some(file),
            ..MqttConfig::default()
        };
        let o = c.options("mqtt://h", "gw").unwrap();
        let login = o.credentials().unwrap();
        assert_eq!(
            (login.username.as_str(), login.password.as_str()),
            ("gw", "s3cret")
        );
    }

    #[test]
    fn bad_values_are_refused_with_their_key() {
        let cases: [(MqttConfig, &str); 4] = [
            (
                MqttConfig {
                    qos: 3,
                    ..Default::default()
                },
                "qos",
            ),
            (
                MqttConfig {
                    client_cert: Some("c.pem".into()),
                    ..Default::default()
                },
                "client_key",
            ),
            (
                MqttConfig {
                    prefix: Some("a/#".into()),
                    ..Default::default()
                },
                "prefix",
            ),
            (
                MqttConfig {
                    reconnect_min_s: 0.0,
                    ..Default::default()
                },
                "reconnect_min_s",
            ),
        ];
        for (config, key) in cases {
            let err = config.validate().unwrap_err().to_string();
            assert!(err.contains(key), "{err}");
        }
    }
}
