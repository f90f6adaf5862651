//! The attacks of issue #17 at full size, against `gangway run` and a real
//! mosquitto on loopback: messages of 1 and 16 MiB at QoS 0, QoS 1 and
//! retained; 30,000 fake device ids × 3 scans with Home Assistant discovery
//! on; 20,000 route requests at QoS 1; a truncated learning store; a password
//! put in the config; 1 GiB of garbage replayed with `--skip-bad`, and a 1 GiB
//! single-line file.
//!
//! ```sh
//! cargo build --release && cargo run --release --example attack
//! cargo run --release --example attack -- --only poison,fakes --fakes 5000
//! ```
//!
//! Prints one JSON object per attack, with each figure beside its target.
//! The bounded versions of the same attacks are tests (`tests/it/mqtt_hostile.rs`);
//! this is where their sizes are real. Everything it starts, it stops.

mod support;

use std::collections::HashMap;
use std::io::Write;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use clap::Parser;
use rumqttc::{AsyncClient, Event, MqttOptions, Packet, QoS};
use serde_json::{Value, json};
use support::{Guard, gangway, mosquitto, percentile, usage};
use tokio::sync::mpsc;

#[derive(Parser)]
struct Args {
    /// Attacks to run, comma-separated: poison, fakes, requests, store,
    /// secrets, garbage (default all).
    #[arg(long, value_delimiter = ',')]
    only: Vec<String>,
    /// Fake device ids in the device flood (3 scans each).
    #[arg(long, default_value_t = 30_000)]
    fakes: usize,
    /// Route requests in the request flood.
    #[arg(long, default_value_t = 20_000)]
    requests: usize,
    /// Size of the garbage log and of the single-line file, MiB.
    #[arg(long, default_value_t = 1024)]
    garbage_mib: usize,
    /// Fixes in the learning store before it is truncated.
    #[arg(long, default_value_t = 200_000)]
    store_rows: usize,
}

const GATEWAY: &str = "gw-attack";
const PREFIX: &str = "gangway/gw-attack";
const UUID: &str = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84";
const MIB: usize = 1 << 20;

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

/// A broker and a place for configs and logs.
struct Rig {
    dir: tempfile::TempDir,
    _broker: Guard,
    port: u16,
}

impl Rig {
    fn new() -> Rig {
        let dir = tempfile::tempdir().unwrap();
        let (broker, port) = mosquitto(dir.path(), "persistence false\n");
        Rig {
            dir,
            _broker: broker,
            port,
        }
    }

    /// Writes a config (with `extra` TOML before `[mqtt]`) and starts the
    /// gateway on it, without Bluetooth; its log goes to `gateway.log`.
    fn gateway(&self, extra: &str) -> Guard {
        let config = self.dir.path().join("gangway.toml");
        std::fs::write(
            &config,
            format!(
                "gateway_id = \"{GATEWAY}\"\nsite = \"{}\"\n[web]\nbind = \"127.0.0.1:0\"\n\
                 [ble]\nadapter = \"hci-none\"\n{extra}\n\
                 [mqtt]\nurl = \"mqtt://127.0.0.1:{}\"\nstats_interval_s = 1\n",
                root().join("config/sites/waldo.toml").display(),
                self.port
            ),
        )
        .unwrap();
        let log = std::fs::File::create(self.dir.path().join("gateway.log")).unwrap();
        Guard(
            Command::new(gangway())
                .args(["run", "--config"])
                .arg(&config)
                .env("RUST_LOG", "info")
                .stdout(Stdio::null())
                .stderr(log)
                .spawn()
                .unwrap(),
        )
    }
}

/// An MQTT client that can send anything, and sees replies and stats.
struct Probe {
    client: AsyncClient,
    rx: mpsc::UnboundedReceiver<(String, Value, Instant)>,
    stats: Value,
}

impl Probe {
    async fn connect(port: u16, id: &str, filters: &[String]) -> Probe {
        let mut options = MqttOptions::new(id, "127.0.0.1", port);
        options.set_keep_alive(Duration::from_secs(30));
        options.set_max_packet_size(64 * MIB, 64 * MIB);
        let (client, mut eventloop) = AsyncClient::new(options, 1000);
        let mut network = eventloop.network_options();
        network.set_tcp_nodelay(true);
        eventloop.set_network_options(network);
        for f in filters {
            client.subscribe(f, QoS::AtLeastOnce).await.unwrap();
        }
        let (tx, rx) = mpsc::unbounded_channel();
        tokio::spawn(async move {
            loop {
                match eventloop.poll().await {
                    Ok(Event::Incoming(Packet::Publish(p))) => {
                        let v = serde_json::from_slice(&p.payload).unwrap_or(Value::Null);
                        if tx.send((p.topic, v, Instant::now())).is_err() {
                            return;
                        }
                    }
                    Ok(_) => {}
                    Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
                }
            }
        });
        Probe {
            client,
            rx,
            stats: Value::Null,
        }
    }

    async fn replies(port: u16, id: &str) -> Probe {
        Probe::connect(
            port,
            id,
            &[
                format!("{PREFIX}/devices/+/path"),
                format!("{PREFIX}/devices/+/location"),
                format!("{PREFIX}/stats"),
            ],
        )
        .await
    }

    async fn publish(&self, topic: String, payload: impl Into<Vec<u8>>) {
        self.client
            .publish(topic, QoS::AtLeastOnce, false, payload)
            .await
            .unwrap();
    }

    async fn scan(&self, device: &str) {
        let scan = json!([
            {"uuid": UUID, "major": 1, "minor": 3008, "rssi": -55},
            {"uuid": UUID, "major": 1, "minor": 3005, "rssi": -72},
            {"uuid": UUID, "major": 1, "minor": 3010, "rssi": -80},
        ]);
        self.publish(format!("{PREFIX}/scans/{device}"), scan.to_string())
            .await;
    }

    /// Waits up to `within` for a message `pred` accepts (keeping the latest
    /// stats seen on the way).
    async fn wait(
        &mut self,
        within: Duration,
        mut pred: impl FnMut(&str, &Value) -> bool,
    ) -> Option<(Value, Instant)> {
        let deadline = tokio::time::Instant::now() + within;
        loop {
            let (topic, value, at) = tokio::time::timeout_at(deadline, self.rx.recv())
                .await
                .ok()??;
            if topic.ends_with("/stats") {
                self.stats = value.clone();
            }
            if pred(&topic, &value) {
                return Some((value, at));
            }
        }
    }

    /// Scans as `device` until it is located.
    async fn locate(&mut self, device: &str) {
        let topic = format!("{PREFIX}/devices/{device}/location");
        for _ in 0..100 {
            self.scan(device).await;
            if self
                .wait(Duration::from_millis(300), |t, _| t == topic)
                .await
                .is_some()
            {
                return;
            }
        }
        panic!("{device} was never located");
    }

    /// Asks for a route; the reply and how long it took, or None after
    /// `within`.
    async fn route(&mut self, device: &str, id: &str, within: Duration) -> Option<(Value, f64)> {
        let sent = Instant::now();
        let body = json!({"to": "help desk", "request_id": id}).to_string();
        self.publish(format!("{PREFIX}/devices/{device}/route/set"), body)
            .await;
        let (reply, at) = self
            .wait(within, |t, v| t.ends_with("/path") && v["request_id"] == id)
            .await?;
        Some((reply, at.duration_since(sent).as_secs_f64() * 1e3))
    }

    /// The next stats message.
    async fn next_stats(&mut self) -> Value {
        self.wait(Duration::from_secs(10), |t, _| t.ends_with("/stats"))
            .await
            .map(|(v, _)| v)
            .unwrap_or(Value::Null)
    }
}

fn report(value: Value) {
    println!("{}", serde_json::to_string(&value).unwrap());
}

async fn poison() {
    let rig = Rig::new();
    let mut gateway = rig.gateway("");
    let mut probe = Probe::replies(rig.port, "attack-probe").await;
    probe.locate("probe-1").await;
    let attacker = Probe::connect(rig.port, "attacker", &[]).await;
    let mut n = 0;
    for size_mib in [1usize, 16] {
        for (mode, qos, retain) in [
            ("qos0", QoS::AtMostOnce, false),
            ("qos1", QoS::AtLeastOnce, false),
            ("retained", QoS::AtLeastOnce, true),
        ] {
            attacker
                .client
                .publish(
                    format!("{PREFIX}/scans/poison-{size_mib}-{mode}"),
                    qos,
                    retain,
                    vec![b'['; size_mib * MIB],
                )
                .await
                .unwrap();
            n += 1;
            let answer = probe
                .route("probe-1", &format!("health-{n}"), Duration::from_secs(30))
                .await;
            report(json!({
                "attack": "poison", "size_mib": size_mib, "mode": mode,
                "health_answered": answer.is_some(),
                "health_reply_ms": answer.map(|a| a.1), "target_ms": 5000,
            }));
        }
    }
    let stats = probe.next_stats().await;
    report(json!({
        "attack": "poison", "summary": true,
        "disconnects": stats["disconnects"], "reconnects": stats["reconnects"],
        "oversized_messages": stats["oversized_messages"], "mqtt": stats["mqtt"],
        "target": "disconnects 0",
    }));
    // A restart gets the three retained ones at once.
    drop(gateway);
    let started = Instant::now();
    gateway = rig.gateway("");
    probe.locate("probe-1").await;
    let answer = probe
        .route("probe-1", "after-restart", Duration::from_secs(30))
        .await;
    let stats = probe.next_stats().await;
    report(json!({
        "attack": "poison", "restart_with_retained": true,
        "start_to_answer_ms": answer.map(|_| started.elapsed().as_secs_f64() * 1e3),
        "disconnects": stats["disconnects"], "oversized_messages": stats["oversized_messages"],
    }));
    drop(gateway);
}

async fn fakes(count: usize) {
    let rig = Rig::new();
    let gateway = rig.gateway("");
    let pid = gateway.0.id();
    let mut probe = Probe::replies(rig.port, "attack-probe").await;
    let probes = ["probe-1", "probe-2", "probe-3", "probe-4"];
    for p in probes {
        probe.locate(p).await;
    }
    let (_, rss_before, _) = usage(pid);
    let flood = Probe::connect(rig.port, "attacker", &[]).await;
    let started = Instant::now();
    let flooding = tokio::spawn(async move {
        for d in 0..count {
            for _ in 0..3 {
                flood.scan(&format!("fake-{d}")).await;
            }
        }
        flood
    });
    let mut latencies = Vec::new();
    let mut lost = 0;
    let mut n = 0;
    while !flooding.is_finished() {
        let device = probes[n % probes.len()];
        // The probes keep scanning, as live phones do, so they stay tracked.
        probe.scan(device).await;
        match probe
            .route(device, &format!("health-{n}"), Duration::from_secs(5))
            .await
        {
            Some((_, ms)) => latencies.push(ms),
            None => lost += 1,
        }
        n += 1;
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    let flood_s = started.elapsed().as_secs_f64();
    let flood = flooding.await.unwrap();
    drop(flood);
    tokio::time::sleep(Duration::from_secs(3)).await;
    let (_, rss_after, rss_peak) = usage(pid);
    let stats = probe.next_stats().await;
    // What the broker retains for Home Assistant.
    let mut late = Probe::connect(
        rig.port,
        "attack-late",
        &[format!("homeassistant/device_tracker/{GATEWAY}/#")],
    )
    .await;
    let mut retained = 0;
    while late
        .wait(Duration::from_secs(3), |_, v| !v.is_null())
        .await
        .is_some()
    {
        retained += 1;
    }
    latencies.sort_by(f64::total_cmp);
    report(json!({
        "attack": "fakes", "fake_ids": count, "scans": count * 3, "flood_s": flood_s,
        "rss_growth_mib": (rss_after as f64 - rss_before as f64) / 1024.0,
        "rss_peak_mib": rss_peak as f64 / 1024.0, "target_rss_growth_mib": 64,
        "health_requests": latencies.len() + lost, "health_lost": lost,
        "health_p50_ms": percentile(&latencies, 0.5), "health_p99_ms": percentile(&latencies, 0.99),
        "health_max_ms": latencies.last(), "target_p99_ms": 200,
        "tracked": stats["tracked"], "windows": stats["windows"], "announced": stats["announced"],
        "evicted_devices": stats["evicted_devices"], "retained_tracker_configs": retained,
        "trackers_refused": stats["trackers_refused"],
        "rate_limited": stats["rate_limited"], "inbound_dropped": stats["inbound_dropped"], "queue_dropped": stats["queue_dropped"],
        "max_devices": 10_000,
    }));
}

async fn requests(count: usize) {
    for (label, extra) in [
        ("default limits", ""),
        (
            "no per-device rate limit",
            "[limits]\nrequests_per_device_per_s = 1000000\n",
        ),
    ] {
        let rig = Rig::new();
        let _gateway = rig.gateway(extra);
        let mut probe = Probe::replies(rig.port, "attack-probe").await;
        let devices = ["probe-1", "probe-2", "probe-3", "probe-4"];
        for d in devices {
            probe.locate(d).await;
        }
        let sender = Probe::connect(rig.port, "attacker", &[]).await;
        let started = Instant::now();
        let sending = tokio::spawn(async move {
            for i in 0..count {
                let device = devices[i % devices.len()];
                let body = json!({"to": "help desk", "request_id": format!("q{i}")}).to_string();
                sender
                    .publish(format!("{PREFIX}/devices/{device}/route/set"), body)
                    .await;
            }
            sender
        });
        let mut codes: HashMap<String, String> = HashMap::new();
        while codes.len() < count {
            let Some((reply, _)) = probe
                .wait(Duration::from_secs(30), |t, v| {
                    t.ends_with("/path")
                        && v["request_id"]
                            .as_str()
                            .is_some_and(|id| id.starts_with('q'))
                })
                .await
            else {
                break;
            };
            let code = reply["error"]["code"]
                .as_str()
                .unwrap_or("route")
                .to_owned();
            codes.insert(reply["request_id"].as_str().unwrap().to_owned(), code);
        }
        let elapsed = started.elapsed().as_secs_f64();
        drop(sending.await);
        let mut by_code: HashMap<String, usize> = HashMap::new();
        for c in codes.values() {
            *by_code.entry(c.clone()).or_default() += 1;
        }
        report(json!({
            "attack": "requests", "limits": label, "qos": 1, "sent": count,
            "answered": codes.len(), "target_answered": count, "seconds": elapsed,
            "by_code": by_code,
        }));
    }
}

async fn store(rows: usize) {
    let rig = Rig::new();
    let path = rig.dir.path().join("learning.sqlite");
    {
        let mut store = gangway::store::Store::open(&path).unwrap();
        let fixes: Vec<gangway::store::Record> = (0..rows)
            .map(|i| gangway::store::Record::Fix {
                device: format!("old-{}", i % 100),
                t: i as f64,
                floor: None,
                cell: gangway::site::Cell::new(1, 1),
                confidence: 0.5,
            })
            .collect();
        store.write(&fixes).unwrap();
    }
    let bytes = std::fs::read(&path).unwrap();
    std::fs::write(&path, &bytes[..bytes.len() / 2]).unwrap();
    let mut probe = Probe::replies(rig.port, "attack-probe").await;
    let started = Instant::now();
    let _gateway = rig.gateway(&format!(
        "[store]\nenabled = true\npath = \"{}\"\n",
        path.display()
    ));
    // Serving: the first request answered (an error for an unknown device is
    // an answer).
    let mut answered = None;
    for i in 0..200 {
        if probe
            .route("nobody", &format!("s{i}"), Duration::from_millis(100))
            .await
            .is_some()
        {
            answered = Some(started.elapsed().as_secs_f64());
            break;
        }
    }
    let stats = probe.next_stats().await;
    report(json!({
        "attack": "truncated store", "store_mib": bytes.len() as f64 / MIB as f64,
        "serving_after_s": answered, "target_s": 10,
        "fallbacks": stats["fallbacks"],
    }));
}

async fn secrets() {
    const SECRET: &str = "attack-Secret-5d41402abc";
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("inline.toml");
    std::fs::write(
        &config,
        format!(
            "gateway_id = \"gw\"\nsite = \"{}\"\n[mqtt]\nusername = \"u\"\npassword = \"{SECRET}\"\n",
            root().join("config/sites/waldo.toml").display()
        ),
    )
    .unwrap();
    let out = Command::new(gangway())
        .args(["check", "--config"])
        .arg(&config)
        .output()
        .unwrap();
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    report(json!({
        "attack": "secrets", "check_refused": !out.status.success(),
        "secrets_in_check_output": text.matches(SECRET).count(), "target": 0,
    }));
}

/// Runs `gangway replay --skip-bad` on `log`; (seconds, stderr lines, stderr
/// bytes, peak RSS MiB).
fn replay_skip_bad(log: &Path) -> (f64, usize, u64, f64) {
    let stderr = log.with_extension("stderr");
    let started = Instant::now();
    let mut child = Command::new(gangway())
        .args(["replay", "--skip-bad", "--print", "--config"])
        .arg(root().join("config/gangway.toml"))
        .arg(log)
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(&stderr).unwrap())
        .spawn()
        .unwrap();
    let mut peak = 0;
    while child.try_wait().unwrap().is_none() {
        peak = peak.max(usage(child.id()).2);
        std::thread::sleep(Duration::from_millis(20));
    }
    let text = std::fs::read(&stderr).unwrap();
    let lines = text.iter().filter(|&&b| b == b'\n').count();
    (
        started.elapsed().as_secs_f64(),
        lines,
        text.len() as u64,
        peak as f64 / 1024.0,
    )
}

fn garbage(mib: usize) {
    let dir = tempfile::tempdir().unwrap();
    let lines = dir.path().join("garbage.jsonl");
    {
        let mut out = std::io::BufWriter::new(std::fs::File::create(&lines).unwrap());
        let line =
            b"{\"t\": 1, \"type\": \"advert\", garbage garbage garbage garbage garbage garbage\n";
        for _ in 0..(mib * MIB / line.len()) {
            out.write_all(line).unwrap();
        }
    }
    let (seconds, stderr_lines, stderr_bytes, peak) = replay_skip_bad(&lines);
    report(json!({
        "attack": "garbage --skip-bad", "mib": mib, "seconds": seconds,
        "warning_lines": stderr_lines, "warning_bytes": stderr_bytes, "peak_rss_mib": peak,
    }));
    std::fs::remove_file(&lines).unwrap();
    let one = dir.path().join("one-line.jsonl");
    {
        let mut out = std::io::BufWriter::new(std::fs::File::create(&one).unwrap());
        let chunk = vec![b'x'; MIB];
        for _ in 0..mib {
            out.write_all(&chunk).unwrap();
        }
    }
    let (seconds, stderr_lines, _, peak) = replay_skip_bad(&one);
    report(json!({
        "attack": "one line --skip-bad", "mib": mib, "seconds": seconds,
        "warning_lines": stderr_lines, "peak_rss_mib": peak,
    }));
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args = Args::parse();
    let run = |name: &str| args.only.is_empty() || args.only.iter().any(|o| o == name);
    if run("poison") {
        poison().await;
    }
    if run("fakes") {
        fakes(args.fakes).await;
    }
    if run("requests") {
        requests(args.requests).await;
    }
    if run("store") {
        store(args.store_rows).await;
    }
    if run("secrets") {
        secrets().await;
    }
    if run("garbage") {
        garbage(args.garbage_mib);
    }
}
