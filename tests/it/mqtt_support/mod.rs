//! Shared by the `mqtt_*` integration tests: a real mosquitto on a free
//! loopback port (never the system service), gateways run as child processes
//! of the built binary, and a rumqttc client that survives broker restarts.
//! Every wait has a timeout, so a broken gateway fails a test instead of
//! hanging it.

use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use serde_json::Value;
use tokio::sync::mpsc;

pub(crate) mod rabbitmq;

pub(crate) const WAIT: Duration = Duration::from_secs(30);

pub(crate) fn repo() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

pub(crate) fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn mosquitto_binary() -> PathBuf {
    for dir in ["/usr/sbin", "/usr/bin", "/usr/local/sbin", "/usr/local/bin"] {
        let p = Path::new(dir).join("mosquitto");
        if p.exists() {
            return p;
        }
    }
    panic!(
        "mosquitto is not installed; the MQTT integration tests need it (apt-get install mosquitto)"
    );
}

/// A mosquitto of the test's own, with persistence in a temporary directory
/// so that a stop (SIGTERM) and restart keeps sessions, as a production
/// broker would.
pub(crate) struct Broker {
    pub port: u16,
    dir: tempfile::TempDir,
    child: Option<Child>,
}

impl Broker {
    pub(crate) fn start() -> Broker {
        Broker::start_with(|_| "allow_anonymous true\n".into())
    }

    /// A broker whose listener and security options `settings` writes, given
    /// the broker's directory (for certificate and password files).
    pub(crate) fn start_with(settings: impl FnOnce(&Path) -> String) -> Broker {
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        let conf = dir.path().join("mosquitto.conf");
        // Started as root, mosquitto would switch to the `mosquitto` user and
        // could not write its database into our directory: stay who we are.
        let user = Command::new("id").arg("-un").output().unwrap().stdout;
        std::fs::write(
            &conf,
            format!(
                "listener {port} 127.0.0.1\n{}user {}\npersistence true\n\
                 persistence_location {}/\nlog_dest stderr\nlog_type error\nlog_type warning\n",
                settings(dir.path()),
                String::from_utf8_lossy(&user).trim(),
                dir.path().display()
            ),
        )
        .unwrap();
        let mut broker = Broker {
            port,
            dir,
            child: None,
        };
        broker.spawn();
        broker
    }

    /// A broker that something else (the gateway's embedded one) runs.
    pub(crate) fn at_port(port: u16) -> Broker {
        let deadline = Instant::now() + Duration::from_secs(20);
        while TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(Instant::now() < deadline, "nothing listens on port {port}");
            std::thread::sleep(Duration::from_millis(50));
        }
        Broker {
            port,
            dir: tempfile::tempdir().unwrap(),
            child: None,
        }
    }

    pub(crate) fn url(&self) -> String {
        format!("mqtt://127.0.0.1:{}", self.port)
    }

    fn spawn(&mut self) {
        let child = Command::new(mosquitto_binary())
            .arg("-c")
            .arg(self.dir.path().join("mosquitto.conf"))
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start mosquitto");
        self.child = Some(child);
        let deadline = Instant::now() + Duration::from_secs(10);
        while TcpStream::connect(("127.0.0.1", self.port)).is_err() {
            assert!(
                Instant::now() < deadline,
                "mosquitto did not start listening"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    /// Stops the broker (SIGTERM: it saves its sessions) and waits for it.
    pub(crate) fn stop(&mut self) {
        if let Some(mut child) = self.child.take() {
            signal(&child, "TERM");
            child.wait().unwrap();
        }
    }

    pub(crate) fn restart(&mut self) {
        self.stop();
        self.spawn();
    }
}

impl Drop for Broker {
    fn drop(&mut self) {
        if let Some(mut child) = self.child.take() {
            let _ = child.kill();
            let _ = child.wait();
        }
    }
}

/// Sends a signal (`"TERM"`, `"KILL"`, `"HUP"`, `"INT"`) to a child.
pub(crate) fn signal(child: &Child, name: &str) {
    use rustix::process::{Pid, Signal, kill_process};
    let sig = match name {
        "TERM" => Signal::TERM,
        "KILL" => Signal::KILL,
        "HUP" => Signal::HUP,
        "INT" => Signal::INT,
        "USR1" => Signal::USR1,
        other => panic!("no signal {other} in the tests"),
    };
    let pid = Pid::from_raw(child.id() as i32).expect("a child has a pid");
    kill_process(pid, sig).unwrap_or_else(|e| panic!("kill -{name}: {e}"));
}

/// A gateway config in a temporary directory. `extra` is appended (TOML).
pub(crate) struct GatewayConfig {
    pub dir: tempfile::TempDir,
    pub path: PathBuf,
}

pub(crate) fn gateway_config(
    gateway_id: &str,
    site: &Path,
    broker: &Broker,
    extra: &str,
) -> GatewayConfig {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("gangway.toml");
    write_config(&path, gateway_id, site, broker, extra);
    GatewayConfig { dir, path }
}

pub(crate) fn write_config(
    path: &Path,
    gateway_id: &str,
    site: &Path,
    broker: &Broker,
    extra: &str,
) {
    std::fs::write(
        path,
        format!(
            "gateway_id = \"{gateway_id}\"\nsite = \"{}\"\n{extra}\n\
             # The web UI on a port of its own, so gateways of tests run at once never\n\
             # compete for the default one. ([mqtt] stays last: tests append to it.)\n\
             [web]\nbind = \"127.0.0.1:0\"\n[mqtt]\nurl = \"{}\"\n\
             stats_interval_s = 1\nreconnect_min_s = 0.2\nreconnect_max_s = 1.0\n",
            site.display(),
            broker.url()
        ),
    )
    .unwrap();
}

/// The sample site (`config/sites/waldo.toml`) with `gateways` as fixed
/// receivers (`[[gateway]]`: id and cell), written into `dir`.
pub(crate) fn site_with_gateways(dir: &Path, gateways: &[(&str, [u16; 2])]) -> PathBuf {
    let site = dir.join("site.toml");
    let waldo = std::fs::read_to_string(repo().join("config/sites/waldo.toml")).unwrap();
    let (body, places) = waldo.split_once("[places]").unwrap();
    let gateways: String = gateways
        .iter()
        .map(|(id, [x, y])| format!("[[gateway]]\nid = \"{id}\"\ncell = [{x}, {y}]\n\n"))
        .collect();
    std::fs::write(&site, format!("{body}{gateways}[places]{places}")).unwrap();
    site
}

/// Tests run at once: a gateway's web UI must be off or on port 0, never
/// on the default port, which two gateways would compete for (the loser
/// would serve without its UI, listed in its fallbacks).
pub(crate) fn assert_web_ui_on_a_port_of_its_own(config: &Path) {
    let text = std::fs::read_to_string(config).unwrap();
    let config: toml::Table = toml::from_str(&text).unwrap();
    let web = config.get("web").and_then(|w| w.as_table());
    let enabled = web
        .and_then(|w| w.get("enabled"))
        .and_then(|e| e.as_bool())
        .unwrap_or(true);
    let bind = web.and_then(|w| w.get("bind")).and_then(|b| b.as_str());
    assert!(
        !enabled || bind.is_some_and(|b| b.ends_with(":0")),
        "a test gateway's [web] must be `enabled = false` or `bind = \"127.0.0.1:0\"`:\n{text}"
    );
}

/// No stats message lists the web UI among its fallbacks (it failed to start).
fn check_no_web_fallback(m: &Received) {
    if m.topic.ends_with("/stats") {
        let stats = m.json();
        let fallbacks = stats["fallbacks"].as_array().cloned().unwrap_or_default();
        assert!(
            !fallbacks
                .iter()
                .any(|f| f.as_str().is_some_and(|f| f.starts_with("[web]"))),
            "the web UI fell back: {stats}"
        );
    }
}

/// Gateway logs go to the test's stderr with GANGWAY_TEST_LOGS=1.
fn test_logs() -> Stdio {
    if std::env::var_os("GANGWAY_TEST_LOGS").is_some() {
        Stdio::inherit()
    } else {
        Stdio::null()
    }
}

/// A gateway process; killed when dropped.
pub(crate) struct Gateway {
    pub child: Child,
}

impl Gateway {
    pub(crate) fn start(config: &Path, args: &[&str]) -> Gateway {
        Gateway::spawn(
            config,
            args,
            "info,rumqttd=warn,rumqttd::server::broker=off",
            test_logs(),
        )
    }

    /// A gateway whose log (at `filter`, e.g. `debug`) goes to `log`, for
    /// tests that read it.
    pub(crate) fn start_logged(config: &Path, args: &[&str], filter: &str, log: &Path) -> Gateway {
        let file = std::fs::File::create(log).unwrap();
        Gateway::spawn(config, args, filter, Stdio::from(file))
    }

    fn spawn(config: &Path, args: &[&str], filter: &str, stderr: Stdio) -> Gateway {
        assert_web_ui_on_a_port_of_its_own(config);
        let child = Command::new(env!("CARGO_BIN_EXE_gangway"))
            .arg("run")
            .arg("--config")
            .arg(config)
            .args(args)
            .env("RUST_LOG", filter)
            .stdout(Stdio::null())
            .stderr(stderr)
            .spawn()
            .expect("start the gateway");
        Gateway { child }
    }

    /// SIGTERM, then the exit status (within the timeout).
    pub(crate) fn terminate(&mut self) -> std::process::ExitStatus {
        signal(&self.child, "TERM");
        let deadline = Instant::now() + WAIT;
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(
                Instant::now() < deadline,
                "the gateway did not stop on SIGTERM"
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

impl Drop for Gateway {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One received message.
#[derive(Clone, Debug)]
pub(crate) struct Received {
    pub topic: String,
    pub payload: Vec<u8>,
    pub retain: bool,
}

impl Received {
    pub(crate) fn json(&self) -> Value {
        serde_json::from_slice(&self.payload).unwrap_or(Value::Null)
    }

    pub(crate) fn text(&self) -> String {
        String::from_utf8_lossy(&self.payload).into_owned()
    }
}

/// A test client: a persistent session that reconnects and resubscribes, so it
/// receives what was published for it while the broker was down.
pub(crate) struct Client {
    pub client: AsyncClient,
    rx: mpsc::UnboundedReceiver<Received>,
    /// Everything received so far, in order.
    pub seen: Vec<Received>,
}

impl Client {
    pub(crate) async fn connect(broker: &Broker, id: &str, filters: &[&str]) -> Client {
        let mut options = MqttOptions::new(id, "127.0.0.1", broker.port);
        options.set_keep_alive(Duration::from_secs(5));
        options.set_clean_session(false);
        options.set_max_packet_size(1 << 20, 1 << 20);
        Client::connect_with(options, filters).await
    }

    pub(crate) async fn connect_with(options: MqttOptions, filters: &[&str]) -> Client {
        let (client, mut eventloop) = AsyncClient::new(options, 100);
        let (tx, rx) = mpsc::unbounded_channel();
        let filters: Vec<String> = filters.iter().map(|f| f.to_string()).collect();
        let sub = client.clone();
        tokio::spawn(async move {
            loop {
                match eventloop.poll().await {
                    Ok(Event::Incoming(Packet::ConnAck(_))) => {
                        for f in &filters {
                            let _ = sub.subscribe(f, QoS::AtLeastOnce).await;
                        }
                    }
                    Ok(Event::Incoming(Packet::Publish(p))) => {
                        let _ = tx.send(Received {
                            topic: p.topic.clone(),
                            payload: p.payload.to_vec(),
                            retain: p.retain,
                        });
                    }
                    Ok(_) => {}
                    Err(_) => tokio::time::sleep(Duration::from_millis(100)).await,
                }
                if tx.is_closed() {
                    return;
                }
            }
        });
        Client {
            client,
            rx,
            seen: Vec::new(),
        }
    }

    pub(crate) async fn publish(&self, topic: &str, payload: impl Into<Vec<u8>>) {
        self.client
            .publish(topic, QoS::AtLeastOnce, false, payload)
            .await
            .unwrap();
    }

    /// Returns once the subscriptions are in place: a message published on
    /// `topic` (which the filters must match) has come back.
    pub(crate) async fn ready(&mut self, topic: &str) {
        let deadline = Instant::now() + WAIT;
        loop {
            self.publish(topic, "probe").await;
            tokio::time::sleep(Duration::from_millis(100)).await;
            self.drain();
            if self.seen.iter().any(|m| m.topic == topic) {
                return;
            }
            assert!(
                Instant::now() < deadline,
                "the subscriptions never took effect"
            );
        }
    }

    /// Moves everything received so far into `seen`, without waiting.
    pub(crate) fn drain(&mut self) {
        while let Ok(m) = self.rx.try_recv() {
            check_no_web_fallback(&m);
            self.seen.push(m);
        }
    }

    /// Waits for the first message (already seen or new) that `pred` accepts.
    pub(crate) async fn wait_for(
        &mut self,
        what: &str,
        mut pred: impl FnMut(&Received) -> bool,
    ) -> Received {
        if let Some(m) = self.seen.iter().find(|m| pred(m)) {
            return m.clone();
        }
        let deadline = tokio::time::Instant::now() + WAIT;
        loop {
            match tokio::time::timeout_at(deadline, self.rx.recv()).await {
                Ok(Some(m)) => {
                    check_no_web_fallback(&m);
                    self.seen.push(m.clone());
                    if pred(&m) {
                        return m;
                    }
                }
                Ok(None) => panic!("client closed while waiting for {what}"),
                Err(_) => panic!(
                    "timed out waiting for {what}; last messages: {:#?}",
                    self.seen
                        .iter()
                        .rev()
                        .take(5)
                        .map(|m| (&m.topic, m.text()))
                        .collect::<Vec<_>>()
                ),
            }
        }
    }

    /// Asks for a route from `device`'s position to the place `to` and waits
    /// for the reply.
    pub(crate) async fn route(
        &mut self,
        prefix: &str,
        device: &str,
        to: &str,
        request_id: &str,
    ) -> Value {
        let request = serde_json::json!({"to": to, "request_id": request_id});
        self.publish(
            &format!("{prefix}/devices/{device}/route/set"),
            request.to_string(),
        )
        .await;
        self.reply(prefix, device, request_id).await
    }

    /// Publishes `scan` as `device`'s phone scan every half second until the
    /// gateway publishes the device's location (at most 30 s); returns it.
    pub(crate) async fn scan_until_located(
        &mut self,
        prefix: &str,
        device: &str,
        scan: &Value,
    ) -> Option<Value> {
        let location = format!("{prefix}/devices/{device}/location");
        for _ in 0..60 {
            self.publish(&format!("{prefix}/scans/{device}"), scan.to_string())
                .await;
            tokio::time::sleep(std::time::Duration::from_millis(500)).await;
            self.drain();
            if let Some(m) = self.seen.iter().find(|m| m.topic == location) {
                return Some(m.json());
            }
        }
        None
    }

    /// Waits for the reply on `…/devices/<device>/path` to `request_id`.
    pub(crate) async fn reply(&mut self, prefix: &str, device: &str, request_id: &str) -> Value {
        let topic = format!("{prefix}/devices/{device}/path");
        self.wait_for(&format!("the reply to {request_id}"), |m| {
            m.topic == topic && m.json()["request_id"] == request_id
        })
        .await
        .json()
    }
}

/// Validates `value` against `docs/schemas/<name>.schema.json`.
pub(crate) fn check_schema(name: &str, value: &Value) -> Result<(), String> {
    let path = repo().join(format!("docs/schemas/{name}.schema.json"));
    let schema: Value = serde_json::from_str(&std::fs::read_to_string(&path).unwrap()).unwrap();
    let validator = jsonschema::options()
        .should_validate_formats(true)
        .build(&schema)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let errors: Vec<String> = validator
        .iter_errors(value)
        .map(|e| format!("{} at {}", e, e.instance_path()))
        .collect();
    if errors.is_empty() {
        Ok(())
    } else {
        Err(format!("{name}: {}: {value}", errors.join("; ")))
    }
}

/// The schema of what the gateway publishes on `topic`, if it has one of ours
/// (status is plain text; Home Assistant configs follow Home Assistant's).
pub(crate) fn schema_of(topic: &str) -> Option<&'static str> {
    if topic.ends_with("/config") {
        return None;
    }
    let last = topic.rsplit('/').next()?;
    Some(match last {
        "location" => "location",
        "path" => "path",
        "guidance" => "guidance",
        "stats" => "stats",
        "heard" => "heard",
        "occupancy" => "occupancy",
        "error" if topic.ends_with("/feedback/error") => "feedback-error",
        _ if topic.contains("/sightings/") => "sightings",
        _ if topic.contains("/locators/") => "locator",
        _ => return None,
    })
}

/// Every gateway message seen so far matches its schema.
pub(crate) fn assert_all_valid(seen: &[Received]) -> usize {
    let mut checked = 0;
    for m in seen {
        if let Some(name) = schema_of(&m.topic) {
            check_schema(name, &m.json()).unwrap_or_else(|e| panic!("{}: {e}", m.topic));
            checked += 1;
        }
    }
    checked
}
