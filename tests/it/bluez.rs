//! The Bluetooth path against BlueZ's D-Bus API, without radios: the gateway
//! (btleplug → bluez-async → D-Bus) runs against python-dbusmock's `bluez5`
//! template on a private system bus (`tests/it/bluez_support/mock_bluez.py`),
//! with `DBUS_SYSTEM_BUS_ADDRESS` pointing at it, and publishes to a real
//! mosquitto. iBeacon adverts become sightings and locations; an unplugged
//! adapter is reported and retried, and scanning resumes when it returns; a
//! scan gone silent is restarted and counted.
//!
//! Needs `dbus-daemon` and python3-dbusmock; without them the tests are
//! skipped with a note, except under CI, where they fail.

use std::collections::HashMap;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, ChildStdout, Command, Stdio};
use std::time::{Duration, Instant};

use crate::mqtt_support::*;
use gangway::site::{Cell, Site};
use serde_json::Value;

const GATEWAY: &str = "gw-bluez";
const PREFIX: &str = "gangway/gw-bluez";
/// Where the gateway "stands": the beacons' RSSIs follow a log-distance model
/// from this cell (O04, beacon b3003's cell).
const STANDING: Cell = Cell::new(14, 3);
/// Advert period of every mock beacon.
const ADVERT_MS: u32 = 200;

/// The Python with the Debian python3-dbusmock and python3-dbus
/// (`GANGWAY_TEST_PYTHON` overrides).
fn python() -> PathBuf {
    if let Some(p) = std::env::var_os("GANGWAY_TEST_PYTHON") {
        return p.into();
    }
    let system = PathBuf::from("/usr/bin/python3");
    if system.exists() {
        system
    } else {
        "python3".into()
    }
}

/// The mock BlueZ and its private system bus, driven by line commands; both
/// stop when this is dropped (the helper exits on end of input).
struct MockBluez {
    child: Child,
    stdin: ChildStdin,
    stdout: BufReader<ChildStdout>,
    /// The private bus, for the gateway's `DBUS_SYSTEM_BUS_ADDRESS`.
    address: String,
}

impl MockBluez {
    /// `None` (with a note) when dbusmock or dbus-daemon is missing outside CI.
    fn start() -> Option<MockBluez> {
        let python = python();
        let probe = Command::new(&python)
            .args(["-c", "import dbus, dbusmock"])
            .output();
        let daemon = Command::new("dbus-daemon").arg("--version").output();
        let missing = match (&probe, &daemon) {
            (Ok(p), Ok(d)) if p.status.success() && d.status.success() => None,
            (Ok(p), _) if !p.status.success() => Some(format!(
                "{} cannot import dbusmock: {}",
                python.display(),
                String::from_utf8_lossy(&p.stderr).trim()
            )),
            (Err(e), _) => Some(format!("{}: {e}", python.display())),
            _ => Some("dbus-daemon is not installed".to_owned()),
        };
        if let Some(missing) = missing {
            crate::common::cannot_run(&format!(
                "{missing} (apt-get install dbus-daemon python3-dbusmock)"
            ));
            return None;
        }
        let mut child = Command::new(&python)
            .arg(repo().join("tests/it/bluez_support/mock_bluez.py"))
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .spawn()
            .expect("start the BlueZ mock");
        let stdin = child.stdin.take().unwrap();
        let mut stdout = BufReader::new(child.stdout.take().unwrap());
        let mut line = String::new();
        stdout.read_line(&mut line).unwrap();
        let address = line
            .strip_prefix("address ")
            .unwrap_or_else(|| panic!("the BlueZ mock did not start: {line:?}"))
            .trim()
            .to_owned();
        Some(MockBluez {
            child,
            stdin,
            stdout,
            address,
        })
    }

    /// Runs one command; returns what follows `ok`.
    fn send(&mut self, command: &str) -> String {
        writeln!(self.stdin, "{command}").unwrap();
        self.stdin.flush().unwrap();
        let mut line = String::new();
        self.stdout.read_line(&mut line).unwrap();
        match line.trim_end().strip_prefix("ok") {
            Some(rest) => rest.trim().to_owned(),
            None => panic!("mock command {command:?} failed: {line:?}"),
        }
    }

    /// How often `method` was called on the adapter.
    fn calls(&mut self, method: &str) -> u64 {
        self.send(&format!("calls hci0 {method}")).parse().unwrap()
    }

    /// Adds `hci0` with the site's beacons around [`STANDING`], advertising;
    /// returns the RSSI each beacon (by minor) is heard at.
    fn adapter_with_beacons(&mut self, site: &Site) -> HashMap<u16, i64> {
        self.send("adapter-add hci0");
        let mut heard_at = HashMap::new();
        for (i, b) in site.beacons.iter().enumerate() {
            let cell = b.cell.expect("waldo's beacons have cells");
            let d = (f64::from(cell.x) - f64::from(STANDING.x))
                .hypot(f64::from(cell.y) - f64::from(STANDING.y))
                * site.cell_m;
            // -59 dBm at 1 m, exponent 2.2: the config's path-loss model.
            let rssi = (-59.0 - 22.0 * d.max(0.5).log10()).round() as i32;
            self.send(&format!(
                "beacon hci0 C0:FF:EE:00:{:02X}:{:02X} {} {} {} -59 {rssi}",
                i >> 8,
                i & 0xff,
                b.beacon.uuid,
                b.beacon.major,
                b.beacon.minor,
            ));
            heard_at.insert(b.beacon.minor, i64::from(rssi));
        }
        // A neighbour's iBeacon: heard, but counted as ignored, not used.
        self.send("beacon hci0 C0:FF:EE:01:00:01 0b0e0e0f-0000-4000-8000-000000000001 7 7 -59 -50");
        heard_at.insert(7, -50);
        self.send(&format!("adverts {ADVERT_MS}"));
        heard_at
    }
}

impl Drop for MockBluez {
    fn drop(&mut self) {
        let _ = writeln!(self.stdin, "quit");
        let _ = self.stdin.flush();
        let deadline = Instant::now() + Duration::from_secs(5);
        while Instant::now() < deadline {
            if let Ok(Some(_)) = self.child.try_wait() {
                return;
            }
            std::thread::sleep(Duration::from_millis(50));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A gateway on the mock's bus; its log goes to `log`.
fn gateway(config: &Path, bus: &str, log: &Path) -> Gateway {
    assert_web_ui_on_a_port_of_its_own(config);
    let child = Command::new(env!("CARGO_BIN_EXE_gangway"))
        .arg("run")
        .arg("--config")
        .arg(config)
        .env("DBUS_SYSTEM_BUS_ADDRESS", bus)
        .env("RUST_LOG", "info,rumqttd=warn")
        .env("NO_COLOR", "1")
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(log).unwrap())
        .spawn()
        .expect("start the gateway");
    Gateway { child }
}

struct Setup {
    mock: MockBluez,
    _broker: Broker,
    client: Client,
    gateway: Gateway,
    _config: GatewayConfig,
    log: PathBuf,
    site: Site,
}

async fn setup(test: &str, ble: &str) -> Option<Setup> {
    let mut mock = MockBluez::start()?;
    let site_path = repo().join("config/sites/waldo.toml");
    let site = Site::load(&site_path).unwrap();
    mock.adapter_with_beacons(&site);
    let broker = Broker::start();
    let config = gateway_config(
        GATEWAY,
        &site_path,
        &broker,
        &format!("[ble]\nadapter = \"hci0\"\n{ble}"),
    );
    let mut client = Client::connect(&broker, test, &[&format!("{PREFIX}/#")]).await;
    client.ready(&format!("{PREFIX}/probe")).await;
    let log = config.dir.path().join("gateway.log");
    let gateway = gateway(&config.path, &mock.address, &log);
    Some(Setup {
        mock,
        _broker: broker,
        client,
        gateway,
        _config: config,
        log,
        site,
    })
}

fn is_stats(m: &Received) -> bool {
    m.topic == format!("{PREFIX}/stats")
}

/// Waits for a message, received after the first `seen`, that `pred` accepts.
async fn wait_after(
    client: &mut Client,
    seen: usize,
    what: &str,
    pred: impl Fn(&Received) -> bool,
) -> Value {
    let deadline = Instant::now() + WAIT;
    loop {
        client.drain();
        if let Some(m) = client.seen[seen..].iter().find(|m| pred(m)) {
            return m.json();
        }
        assert!(Instant::now() < deadline, "timed out waiting for {what}");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

/// Waits for a location published after the first `seen` messages.
async fn location_after(client: &mut Client, seen: usize, what: &str) -> Value {
    let topic = format!("{PREFIX}/devices/{GATEWAY}/location");
    wait_after(client, seen, what, |m| m.topic == topic).await
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn ibeacon_adverts_become_sightings_and_locations() {
    let Some(mut s) = setup("bluez-adverts", "").await else {
        return;
    };
    // The first window may close with only the beacons heard so far; every
    // one of the site's beacons advertises, so soon a fix hears them all.
    let anchors = s.site.beacons.len() as u64;
    let location = wait_after(&mut s.client, 0, "a location hearing every beacon", |m| {
        m.topic.ends_with("/location") && m.json()["anchors_heard"].as_u64() == Some(anchors)
    })
    .await;
    check_schema("location", &location).unwrap();
    let cell: Cell = serde_json::from_value(location["cell"].clone()).unwrap();
    assert!(
        cell.chebyshev(STANDING) <= 3,
        "located at {cell:?}, the adverts say {STANDING:?}: {location}"
    );
    let stats = s
        .client
        .wait_for("stats with sightings and ignored ones", |m| {
            is_stats(m)
                && m.json()["sightings"].as_u64() > Some(0)
                && m.json()["sightings_ignored"].as_u64() > Some(0)
        })
        .await
        .json();
    check_schema("stats", &stats).unwrap();
    assert_eq!(stats["ble"]["state"], "scanning", "{stats}");
    assert_eq!(stats["scan_restarts"], 0, "{stats}");
    // btleplug asks BlueZ for duplicate reports before discovering.
    assert!(s.mock.calls("SetDiscoveryFilter") >= 1);
    assert_eq!(s.mock.calls("StartDiscovery"), 1);
    let locations: Vec<Value> = s
        .client
        .seen
        .iter()
        .filter(|m| m.topic.ends_with("/location"))
        .map(|m| m.json())
        .collect();
    eprintln!(
        "{} locations; anchors heard: {:?}",
        locations.len(),
        locations
            .iter()
            .map(|l| l["anchors_heard"].as_u64())
            .collect::<Vec<_>>()
    );
    assert_all_valid(&s.client.seen);

    assert!(s.gateway.terminate().success());
    assert!(
        s.mock.calls("StopDiscovery") >= 1,
        "a stopped gateway leaves the adapter not discovering"
    );
    let log = std::fs::read_to_string(&s.log).unwrap();
    assert!(log.contains("Bluetooth adapter open; scanning"), "{log}");
    assert_eq!(s.site.name, stats["site"]);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_lost_adapter_is_reported_retried_and_scanning_resumes_when_it_returns() {
    let Some(mut s) = setup("bluez-loss", "").await else {
        return;
    };
    location_after(&mut s.client, 0, "a location before the adapter goes").await;

    s.mock.send("adapter-remove hci0");
    let gone = Instant::now();
    let retrying = s
        .client
        .wait_for("stats with the radio retrying", |m| {
            is_stats(m) && m.json()["ble"]["state"] == "retrying"
        })
        .await
        .json();
    let noticed_s = gone.elapsed().as_secs_f64();
    check_schema("stats", &retrying).unwrap();
    let error = retrying["ble"]["error"].as_str().unwrap_or_default();
    assert!(
        error.contains("hci0"),
        "the error names the adapter: {retrying}"
    );
    // Retried with backoff: the wait between attempts grows, up to its cap
    // (1, 2, 4, 5 s), where a long outage stays; the adapter returns then.
    let backoff = s
        .client
        .wait_for("retries at the longest wait", |m| {
            is_stats(m) && m.json()["ble"]["failures"].as_u64() >= Some(4)
        })
        .await
        .json();
    let waits: Vec<f64> = s
        .client
        .seen
        .iter()
        .filter(|m| is_stats(m) && m.json()["ble"]["state"] == "retrying")
        .filter_map(|m| m.json()["ble"]["retry_in_s"].as_f64())
        .collect();
    assert!(
        waits.windows(2).any(|w| w[1] > w[0]),
        "retry waits {waits:?} grow: {backoff}"
    );
    // However often it retries, the gateway keeps one connection to the bus.
    let pid = s.gateway.child.id();
    assert_eq!(s.mock.send(&format!("connections {pid}")), "1");

    s.client.drain();
    let seen = s.client.seen.len();
    s.mock.adapter_with_beacons(&s.site);
    let back = Instant::now();
    wait_after(
        &mut s.client,
        seen,
        "scanning after the adapter returned",
        |m| is_stats(m) && m.json()["ble"]["state"] == "scanning",
    )
    .await;
    let resumed_s = back.elapsed().as_secs_f64();
    location_after(&mut s.client, seen, "a location after the adapter returned").await;
    let located_s = back.elapsed().as_secs_f64();
    eprintln!(
        "adapter loss noticed in {noticed_s:.1} s; scanning resumed {resumed_s:.1} s \
         after the adapter returned, first new location after {located_s:.1} s"
    );
    assert!(resumed_s <= 10.0, "scanning resumed after {resumed_s:.1} s");
    assert!(s.mock.calls("StartDiscovery") >= 1);
    let log = std::fs::read_to_string(&s.log).unwrap();
    assert!(
        log.contains("went away or was powered off"),
        "the log reports the loss: {log}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_silent_scan_is_restarted_within_its_time_and_counted() {
    const SILENT_S: f64 = 2.0;
    let Some(mut s) = setup("bluez-silent", &format!("silent_restart_s = {SILENT_S}\n")).await
    else {
        return;
    };
    location_after(&mut s.client, 0, "a location while adverts flow").await;
    // Adverts every 0.2 s never look silent.
    tokio::time::sleep(Duration::from_secs_f64(SILENT_S * 1.5)).await;
    assert_eq!(
        s.mock.calls("StartDiscovery"),
        1,
        "no restart while adverts flow"
    );

    s.mock.send("adverts 0");
    let quiet = Instant::now();
    let stats = s
        .client
        .wait_for("stats counting a scan restart", |m| {
            is_stats(m) && m.json()["scan_restarts"].as_u64() >= Some(1)
        })
        .await
        .json();
    let restarted_s = quiet.elapsed().as_secs_f64();
    check_schema("stats", &stats).unwrap();
    assert_eq!(stats["ble"]["state"], "scanning", "{stats}");
    assert!(s.mock.calls("StopDiscovery") >= 1);
    assert!(s.mock.calls("StartDiscovery") >= 2);
    eprintln!(
        "silent scan restarted {restarted_s:.1} s after the last advert (limit {SILENT_S} s)"
    );
    // The restart is due SILENT_S after the last advert, which is at most one
    // advert period before the adverts stopped; allow the stats' trip on a
    // loaded machine.
    assert!(
        restarted_s <= SILENT_S + 1.0,
        "restarted {restarted_s:.1} s after going silent"
    );

    // Adverts after the restart are heard again.
    s.client.drain();
    let seen = s.client.seen.len();
    s.mock.send(&format!("adverts {ADVERT_MS}"));
    location_after(&mut s.client, seen, "a location after the restart").await;
    let log = std::fs::read_to_string(&s.log).unwrap();
    assert!(log.contains("restarting it"), "the log says why: {log}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn record_writes_the_adverts_bluez_reports() {
    let Some(mut mock) = MockBluez::start() else {
        return;
    };
    let site = Site::load(&repo().join("config/sites/waldo.toml")).unwrap();
    let heard_at = mock.adapter_with_beacons(&site);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("rec.jsonl");
    let run = Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args([
            "record",
            "--adapter",
            "hci0",
            "--observer",
            "robot-1",
            "--duration",
            "2",
        ])
        .arg("--out")
        .arg(&out)
        .env("DBUS_SYSTEM_BUS_ADDRESS", &mock.address)
        .output()
        .unwrap();
    assert!(
        run.status.success(),
        "{}",
        String::from_utf8_lossy(&run.stderr)
    );
    let mut minors = HashMap::new();
    for line in std::fs::read_to_string(&out).unwrap().lines() {
        let advert: Value = serde_json::from_str(line).unwrap();
        assert_eq!(advert["type"], "advert", "{line}");
        assert_eq!(advert["observer"], "robot-1", "{line}");
        assert_eq!(advert["tx_power"], -59, "{line}");
        let minor = advert["minor"].as_u64().unwrap() as u16;
        assert_eq!(
            advert["rssi"].as_i64(),
            heard_at.get(&minor).copied(),
            "{line}"
        );
        *minors.entry(minor).or_insert(0) += 1;
    }
    // 2 s of adverts every 0.2 s from each beacon, the foreign one included.
    assert_eq!(minors.len(), heard_at.len(), "{minors:?}");
    assert!(minors.values().all(|&n| n >= 5), "{minors:?}");
    assert!(
        mock.calls("StopDiscovery") >= 1,
        "record stops the scan it started"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_powered_off_adapter_is_waited_for_and_scanned_again_when_on() {
    let Some(mut s) = setup("bluez-power", "").await else {
        return;
    };
    location_after(&mut s.client, 0, "a location before the power goes off").await;
    s.client.drain();
    let seen = s.client.seen.len();
    s.mock.send("adapter-power hci0 off");
    let off = wait_after(
        &mut s.client,
        seen,
        "the radio retrying, powered off",
        |m| {
            is_stats(m)
                && m.json()["ble"]["state"] == "retrying"
                && m.json()["ble"]["error"]
                    .as_str()
                    .is_some_and(|e| e.contains("hci0 is powered off"))
        },
    )
    .await;
    check_schema("stats", &off).unwrap();
    // It waits with backoff instead of starting scans BlueZ would refuse.
    let starts = s.mock.calls("StartDiscovery");
    wait_after(&mut s.client, seen, "a third retry", |m| {
        is_stats(m) && m.json()["ble"]["failures"].as_u64() >= Some(3)
    })
    .await;
    assert_eq!(s.mock.calls("StartDiscovery"), starts);
    s.client.drain();
    assert!(
        !s.client.seen[seen..]
            .iter()
            .any(|m| is_stats(m) && m.json()["ble"]["state"] == "scanning"),
        "no scan while the adapter is off"
    );

    let seen = s.client.seen.len();
    s.mock.send("adapter-power hci0 on");
    wait_after(&mut s.client, seen, "scanning after power on", |m| {
        is_stats(m) && m.json()["ble"]["state"] == "scanning"
    })
    .await;
    location_after(&mut s.client, seen, "a location after power on").await;
}
