//! Shared by the example programs that drive a real gateway through a real
//! mosquitto (`loadtest`, `attack`, `throughput`): the broker, the built
//! binary, a simulated walk, process usage from /proc, percentiles.
//! Everything started is stopped on drop.

#![allow(dead_code)] // each example uses a different part of this module

use std::net::{TcpListener, TcpStream};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use rumqttc::{AsyncClient, EventLoop, MqttOptions};

/// Kills the child when dropped, so nothing outlives the run.
pub(crate) struct Guard(pub Child);

impl Drop for Guard {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

pub(crate) fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A client of the broker on loopback `port` as the load runs use it: large
/// packets allowed, room for `capacity` requests queued, and no Nagle delay
/// on small packets (like the gateway's own link).
pub(crate) fn client(id: &str, port: u16, capacity: usize) -> (AsyncClient, EventLoop) {
    let mut options = MqttOptions::new(id, "127.0.0.1", port);
    options.set_keep_alive(Duration::from_secs(30));
    options.set_max_packet_size(1 << 20, 1 << 20);
    let (client, mut eventloop) = AsyncClient::new(options, capacity);
    let mut network = eventloop.network_options();
    network.set_tcp_nodelay(true);
    eventloop.set_network_options(network);
    (client, eventloop)
}

/// The release binary next to the running example.
pub(crate) fn gangway() -> PathBuf {
    let exe = std::env::current_exe().unwrap();
    // target/release/examples/<example> → target/release/gangway
    let bin = exe.parent().unwrap().parent().unwrap().join("gangway");
    assert!(
        bin.exists(),
        "build the gateway first: cargo build --release"
    );
    bin
}

/// Starts mosquitto (Debian package `mosquitto`) on a free loopback port with
/// its files in `dir` and `extra` configuration lines; returns it and its port
/// once it listens.
pub(crate) fn mosquitto(dir: &Path, extra: &str) -> (Guard, u16) {
    let port = free_port();
    let user = Command::new("id").arg("-un").output().unwrap().stdout;
    let conf = dir.join("mosquitto.conf");
    std::fs::write(
        &conf,
        format!(
            "listener {port} 127.0.0.1\nallow_anonymous true\nuser {}\nmax_queued_messages 100000\nset_tcp_nodelay true\nlog_dest none\n{extra}",
            String::from_utf8_lossy(&user).trim()
        ),
    )
    .unwrap();
    let broker = Guard(
        Command::new("mosquitto")
            .arg("-c")
            .arg(&conf)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("mosquitto (apt-get install mosquitto)"),
    );
    let deadline = Instant::now() + Duration::from_secs(10);
    while TcpStream::connect(("127.0.0.1", port)).is_err() {
        assert!(Instant::now() < deadline, "mosquitto did not start");
        std::thread::sleep(Duration::from_millis(50));
    }
    (broker, port)
}

/// (CPU seconds, RSS now and at its peak in KiB) of a process, from /proc.
pub(crate) fn usage(pid: u32) -> (f64, u64, u64) {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).unwrap_or_default();
    let fields: Vec<&str> = stat
        .rsplit(')')
        .next()
        .unwrap_or("")
        .split_whitespace()
        .collect();
    let ticks: f64 = fields.get(11..13).map_or(0.0, |f| {
        f.iter().filter_map(|v| v.parse::<f64>().ok()).sum()
    });
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap_or_default();
    let kib = |key: &str| {
        status
            .lines()
            .find(|l| l.starts_with(key))
            .and_then(|l| l.split_whitespace().nth(1))
            .and_then(|v| v.parse().ok())
            .unwrap_or(0)
    };
    (ticks / 100.0, kib("VmRSS:"), kib("VmHWM:")) // USER_HZ is 100 on Linux
}

pub(crate) fn percentile(sorted: &[f64], p: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    sorted[((sorted.len() as f64 * p).ceil() as usize).clamp(1, sorted.len()) - 1]
}

/// Simulates `walkers` phones on `site` for `seconds` (no route requests,
/// `extra` arguments to `gangway simulate`) into `log`, each phone hearing
/// every beacon of the site in every window (a radio with a 1 km range,
/// nothing too weak to report), so the load is that of a BLE scan reporting
/// every advert, as gateways on a busy floor see it; returns how many adverts
/// the log holds.
pub(crate) fn simulate_busy_walk(
    dir: &Path,
    site: &Path,
    walkers: usize,
    seconds: u64,
    extra: &[&str],
    log: &Path,
) -> usize {
    let radio = dir.join("hear-every-beacon.toml");
    std::fs::write(
        &radio,
        format!(
            "gateway_id = \"sim\"\nsite = \"{}\"\n[localizer.pathloss]\n\
             range_m = 1000.0\nmax_detection = 1.0\nsensitivity_dbm = -127.0\n",
            site.display()
        ),
    )
    .unwrap();
    let status = Command::new(gangway())
        .args(["simulate", "--requests", "0", "--site"])
        .arg(site)
        .arg("--config")
        .arg(&radio)
        .args([
            "--walkers",
            &walkers.to_string(),
            "--duration",
            &seconds.to_string(),
        ])
        .args(extra)
        .arg("--out")
        .arg(log)
        .env("RUST_LOG", "warn")
        .status()
        .unwrap();
    assert!(status.success());
    std::fs::read_to_string(log)
        .unwrap()
        .matches("\"advert\"")
        .count()
}
