//! Load test: many devices and a steady stream of route requests through a
//! real mosquitto, on loopback only, for a bounded time.
//!
//! ```sh
//! cargo build --release && cargo run --release --example loadtest -- --devices 1000 --seconds 60 --rate 100
//! ```
//!
//! It starts mosquitto (Debian package `mosquitto`) on a free loopback port,
//! simulates `--devices` walkers on the sample site whose phones scan once a
//! second and hear every beacon (`gangway simulate`), runs the gateway on that
//! log in real time
//! (`gangway run --replay … --speed 1`), and publishes `--rate` route requests a
//! second to random devices for `--seconds`, to the site's named places in
//! turn (site, planner and topics come from `--config`). With
//! `--reload-every-s S` it also sends the gateway SIGHUP (a reload of the
//! same config) every S seconds of the measured span. It prints one JSON object:
//! requests sent and answered (and answered with a route, not an error),
//! request → reply latency p50/p99/max in ms (the
//! client's clock: broker in, gateway, broker out), the gateway's CPU seconds
//! and share of one core, and its RSS at the end and at its peak. Everything
//! it starts, it stops.

mod support;

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use clap::Parser;
use gangway::config::Config;
use gangway::site::Site;
use gangway::topics::Topics;
use rumqttc::{Event, Packet, QoS};
use support::{Guard, client, gangway, mosquitto, percentile, simulate_busy_walk, usage};

#[derive(Parser)]
struct Args {
    /// Simulated devices (walkers whose phones scan every beacon at 1 Hz).
    #[arg(long, default_value_t = 1000)]
    devices: usize,
    /// Measured span, after an 8 s warm-up.
    #[arg(long, default_value_t = 60)]
    seconds: u64,
    /// Route requests per second, to the site's named places in turn.
    #[arg(long, default_value_t = 100)]
    rate: u64,
    /// The gateway config (site, planner, topic prefix), relative to the repository.
    #[arg(long, default_value = "config/gangway.toml")]
    config: PathBuf,
    /// Seconds between reloads (SIGHUP) during the measured span; 0: none.
    #[arg(long, default_value_t = 0.0)]
    reload_every_s: f64,
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args = Args::parse();
    let dir = tempfile::tempdir().unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let config_path = root.join(&args.config);
    let config = Config::load(&config_path).unwrap_or_else(|e| panic!("{e}"));
    let site = Site::load(&config.site).unwrap_or_else(|e| panic!("{e}"));
    let places: Vec<String> = site.places().keys().cloned().collect();
    assert!(
        !places.is_empty(),
        "{}: the site names no places to route to",
        config.site.display()
    );
    let topics = Topics::new(config.topic_prefix());

    // The broker.
    let (_broker, port) = mosquitto(dir.path(), "");
    let url = format!("mqtt://127.0.0.1:{port}");

    // The walk: enough for warm-up, the measured span and a tail.
    let log = dir.path().join("load.jsonl");
    let total = args.seconds + 20;
    let adverts = simulate_busy_walk(
        dir.path(),
        &config.site,
        args.devices,
        total,
        &["--dropout", "0"],
        &log,
    );

    // The gateway, playing the walk in real time.
    let gateway = Guard(
        Command::new(gangway())
            .current_dir(root)
            .args(["run", "--config"])
            .arg(&config_path)
            .args(["--mqtt-url", &url, "--speed", "1", "--replay"])
            .arg(&log)
            .env("RUST_LOG", "warn")
            .stdout(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let pid = gateway.0.id();

    // The client.
    let (client, mut eventloop) = client("loadtest", port, 10_000);
    client
        .subscribe(topics.path("+"), QoS::AtLeastOnce)
        .await
        .unwrap();
    // (request id, when the reply came, whether it is a route).
    let (tx, mut rx) = tokio::sync::mpsc::unbounded_channel::<(String, Instant, bool)>();
    tokio::spawn(async move {
        loop {
            match eventloop.poll().await {
                Ok(Event::Incoming(Packet::Publish(p))) => {
                    let v: serde_json::Value =
                        serde_json::from_slice(&p.payload).unwrap_or_default();
                    if let Some(id) = v["request_id"].as_str() {
                        let routed = v["waypoints"].is_array();
                        let _ = tx.send((id.to_owned(), Instant::now(), routed));
                    }
                }
                Ok(_) => {}
                Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    });

    // Warm up: every device gets a few fixes.
    tokio::time::sleep(Duration::from_secs(8)).await;
    let (cpu_before, _, _) = usage(pid);
    let started = Instant::now();
    let mut sent: HashMap<String, Instant> = HashMap::new();
    let mut latencies = Vec::new();
    let mut routed = 0usize;
    let interval = Duration::from_secs_f64(1.0 / args.rate as f64);
    let mut next = Instant::now();
    let mut n = 0u64;
    let (mut reloads, mut next_reload) = (0u64, args.reload_every_s);
    while started.elapsed() < Duration::from_secs(args.seconds) {
        if args.reload_every_s > 0.0 && started.elapsed().as_secs_f64() >= next_reload {
            let status = Command::new("kill")
                .args(["-HUP", &pid.to_string()])
                .status()
                .unwrap();
            assert!(status.success(), "kill -HUP {pid}");
            reloads += 1;
            next_reload += args.reload_every_s;
        }
        if Instant::now() >= next {
            let device = format!("walker-{:02}", (n * 7919) as usize % args.devices + 1);
            let id = format!("load-{n}");
            let body = serde_json::json!({
                "to": places[n as usize % places.len()],
                "request_id": &id,
            })
            .to_string();
            sent.insert(id, Instant::now());
            client
                .publish(topics.route_set(&device), QoS::AtLeastOnce, false, body)
                .await
                .unwrap();
            n += 1;
            next += interval;
        }
        while let Ok((id, at, route)) = rx.try_recv() {
            if let Some(t0) = sent.get(&id) {
                latencies.push(at.duration_since(*t0).as_secs_f64() * 1e3);
                routed += usize::from(route);
            }
        }
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    let measured = started.elapsed().as_secs_f64();
    let (cpu_after, rss_kib, peak_rss_kib) = usage(pid);
    // Stragglers.
    let deadline = Instant::now() + Duration::from_secs(5);
    while latencies.len() < sent.len() && Instant::now() < deadline {
        if let Ok(Some((id, at, route))) =
            tokio::time::timeout(Duration::from_millis(100), rx.recv()).await
            && let Some(t0) = sent.get(&id)
        {
            latencies.push(at.duration_since(*t0).as_secs_f64() * 1e3);
            routed += usize::from(route);
        }
    }
    drop(gateway);
    latencies.sort_by(f64::total_cmp);
    let cpu = cpu_after - cpu_before;
    let summary = serde_json::json!({
        "devices": args.devices,
        "adverts_in_log": adverts,
        "adverts_per_s": adverts as f64 / total as f64,
        "seconds": measured,
        "requests_sent": sent.len(),
        "requests_answered": latencies.len(),
        "requests_routed": routed,
        "routed_share": routed as f64 / sent.len().max(1) as f64,
        "reloads_sent": reloads,
        "latency_ms_p50": percentile(&latencies, 0.50),
        "latency_ms_p99": percentile(&latencies, 0.99),
        "latency_ms_max": latencies.last().copied().unwrap_or(f64::NAN),
        "gateway_cpu_s": cpu,
        "gateway_cpu_share_of_one_core": cpu / measured,
        "gateway_rss_mib": rss_kib as f64 / 1024.0,
        "gateway_peak_rss_mib": peak_rss_kib as f64 / 1024.0,
    });
    println!("{}", serde_json::to_string_pretty(&summary).unwrap());
}
