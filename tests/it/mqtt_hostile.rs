//! The gateway against hostile input, with a real mosquitto: messages far over
//! any limit (at QoS 0, 1 and retained), a flood of route requests, a flood of
//! fake devices with Home Assistant discovery on, a truncated learning store,
//! feedback for routes never given, replay lines whose ids cannot be topics,
//! and a password that must never show. Sizes are bounded so that CI stays
//! fast; `examples/attack.rs` runs the full-size versions and prints figures.

use std::collections::HashMap;
use std::path::Path;
use std::time::Duration;

use crate::mqtt_support::*;
use rumqttc::{AsyncClient, MqttOptions, QoS};
use serde_json::{Value, json};

const PREFIX: &str = "gangway/gw-test";
const MIB: usize = 1 << 20;

fn fixture() -> String {
    repo()
        .join("fixtures/walk-waldo.jsonl")
        .to_string_lossy()
        .into_owned()
}

fn waldo() -> std::path::PathBuf {
    repo().join("config/sites/waldo.toml")
}

/// A client that can send messages of any size (the test client's limit is
/// 1 MiB), polled in the background.
fn attacker(broker: &Broker, id: &str) -> AsyncClient {
    let mut options = MqttOptions::new(id, "127.0.0.1", broker.port);
    options.set_max_packet_size(64 * MIB, 64 * MIB);
    options.set_keep_alive(Duration::from_secs(30));
    let (client, mut eventloop) = AsyncClient::new(options, 16);
    tokio::spawn(async move {
        loop {
            if eventloop.poll().await.is_err() {
                tokio::time::sleep(Duration::from_millis(100)).await;
            }
        }
    });
    client
}

/// Filters for a test client that must not receive the attack itself.
fn replies_and_stats() -> Vec<String> {
    vec![
        format!("{PREFIX}/devices/+/path"),
        format!("{PREFIX}/devices/+/location"),
        format!("{PREFIX}/devices/+/feedback/error"),
        format!("{PREFIX}/stats"),
        format!("{PREFIX}/status"),
    ]
}

async fn client(broker: &Broker, id: &str, filters: &[String]) -> Client {
    let filters: Vec<&str> = filters.iter().map(String::as_str).collect();
    Client::connect(broker, id, &filters).await
}

async fn located(client: &mut Client, device: &str) {
    let topic = format!("{PREFIX}/devices/{device}/location");
    client
        .wait_for(&format!("a location of {device}"), |m| m.topic == topic)
        .await;
}

async fn stats_where(client: &mut Client, what: &str, pred: impl Fn(&Value) -> bool) -> Value {
    let topic = format!("{PREFIX}/stats");
    client
        .wait_for(what, |m| m.topic == topic && pred(&m.json()))
        .await
        .json()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn messages_of_any_size_never_cost_the_connection() {
    let broker = Broker::start();
    let config = gateway_config("gw-test", &waldo(), &broker, "");
    let mut client = client(&broker, "test-poison", &replies_and_stats()).await;
    let gateway = Gateway::start(&config.path, &["--replay", &fixture(), "--speed", "4"]);
    located(&mut client, "walker-01").await;
    let attacker = attacker(&broker, "test-attacker");
    let cases = [
        ("scans/poison", MIB, QoS::AtMostOnce, false),
        ("scans/poison", 2 * MIB, QoS::AtLeastOnce, false),
        (
            "devices/walker-01/feedback",
            MIB + 1,
            QoS::AtLeastOnce,
            false,
        ),
        (
            "devices/walker-01/route/set",
            2 * MIB,
            QoS::AtLeastOnce,
            false,
        ),
        // Retained: every (re)subscription gets it again.
        ("scans/poison", 16 * MIB, QoS::AtLeastOnce, true),
    ];
    for (i, &(topic, size, qos, retain)) in cases.iter().enumerate() {
        attacker
            .publish(format!("{PREFIX}/{topic}"), qos, retain, vec![b'['; size])
            .await
            .unwrap();
        // The gateway still answers right after each.
        let id = format!("health-{i}");
        let reply = client.route(PREFIX, "walker-01", "help desk", &id).await;
        assert!(reply["waypoints"].is_array(), "after {size} bytes: {reply}");
    }
    // The oversized request got its error reply, with its size.
    let refused = client
        .wait_for("the reply to the 2 MiB request", |m| {
            m.json()["error"]["code"] == "payload_too_large"
        })
        .await
        .json();
    assert!(
        refused["error"]["message"]
            .as_str()
            .unwrap()
            .contains(&(2 * MIB).to_string()),
        "{refused}"
    );
    let stats = stats_where(&mut client, "stats counting the five", |s| {
        s["oversized_messages"].as_u64() >= Some(5)
    })
    .await;
    assert_eq!(stats["disconnects"], 0, "{stats}");
    assert_eq!(stats["reconnects"], 0, "{stats}");
    assert_eq!(stats["mqtt"], "connected", "{stats}");

    // A restarted gateway gets the retained 16 MiB message at once, and
    // serves all the same.
    drop(gateway);
    let _gateway = Gateway::start(&config.path, &["--replay", &fixture(), "--speed", "4"]);
    client.seen.clear();
    located(&mut client, "walker-01").await;
    let reply = client
        .route(PREFIX, "walker-01", "printers", "after-restart")
        .await;
    assert!(reply["waypoints"].is_array(), "{reply}");
    let stats = stats_where(&mut client, "stats of the new gateway", |s| {
        s["oversized_messages"].as_u64() >= Some(1)
    })
    .await;
    assert_eq!(stats["disconnects"], 0, "{stats}");
    client
        .wait_for("status online", |m| {
            m.topic.ends_with("/status") && m.text() == "online"
        })
        .await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_request_of_a_flood_is_answered() {
    const N: usize = 2000;
    let broker = Broker::start();
    let config = gateway_config(
        "gw-test",
        &waldo(),
        &broker,
        "[limits]\nmax_pending_requests = 8\nrequests_per_device_per_s = 200\n",
    );
    let mut client = client(&broker, "test-flood", &replies_and_stats()).await;
    let _gateway = Gateway::start(&config.path, &["--replay", &fixture(), "--speed", "4"]);
    located(&mut client, "walker-01").await;
    let route_set = format!("{PREFIX}/devices/walker-01/route/set");
    for i in 0..N {
        let request = json!({"to": "help desk", "request_id": format!("f{i}")});
        client.publish(&route_set, request.to_string()).await;
    }
    let path = format!("{PREFIX}/devices/walker-01/path");
    let mut codes: HashMap<String, String> = HashMap::new();
    let deadline = tokio::time::Instant::now() + Duration::from_secs(60);
    let mut last_stats = Value::Null;
    while codes.len() < N {
        assert!(
            tokio::time::Instant::now() < deadline,
            "{} of {N} requests answered; {last_stats}",
            codes.len()
        );
        client.drain();
        for m in client.seen.drain(..) {
            let reply = m.json();
            if m.topic.ends_with("/stats") {
                last_stats = reply.clone();
            }
            let Some(id) = reply["request_id"].as_str().filter(|_| m.topic == path) else {
                continue;
            };
            let code = if reply["waypoints"].is_array() {
                "route".to_owned()
            } else {
                let code = reply["error"]["code"].as_str().unwrap().to_owned();
                assert_eq!(reply["error"]["retry_after_s"], 1.0, "{reply}");
                check_schema("path", &reply).unwrap();
                code
            };
            codes.insert(id.to_owned(), code);
        }
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    let count = |code: &str| codes.values().filter(|c| *c == code).count() as u64;
    assert!(count("route") >= 1, "{codes:?}");
    assert!(count("rate_limited") >= 1);
    assert_eq!(
        count("route") + count("rate_limited") + count("overloaded"),
        N as u64
    );
    let stats = stats_where(&mut client, "stats counting the refusals", |s| {
        s["rate_limited"].as_u64() == Some(count("rate_limited"))
    })
    .await;
    assert_eq!(stats["overloaded"].as_u64(), Some(count("overloaded")));
    assert_eq!(stats["inbound_dropped"], 0);
    assert_eq!(stats["pending_requests"], 0);
    check_schema("stats", &stats).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn fake_devices_are_bounded_and_their_trackers_withdrawn() {
    const FAKES: usize = 100;
    const MAX: u64 = 20;
    let broker = Broker::start();
    let config = gateway_config(
        "gw-test",
        &waldo(),
        &broker,
        &format!("[ble]\nadapter = \"hci-gangway-test-none\"\n[limits]\nmax_devices = {MAX}\n"),
    );
    // Every fake gets a tracker at its first fix here: what is bounded is
    // the table, and each forgotten tracker is withdrawn (the gate that
    // keeps fakes out of Home Assistant is the next test's).
    let (trackers, mut client, _gateway, scan) = tracker_rig(
        &broker,
        &config.path,
        "test-fakes",
        "ha_min_fixes = 1\nha_new_trackers_per_minute = 1000\n",
    )
    .await;
    for d in 0..FAKES {
        // Two scans: the second closes the first's window, a fix.
        for _ in 0..2 {
            client
                .publish(&format!("{PREFIX}/scans/fake-{d}"), scan.clone())
                .await;
            tokio::time::sleep(Duration::from_millis(5)).await;
        }
    }
    let stats = stats_where(&mut client, "stats with the fakes forgotten", |s| {
        s["evicted_devices"].as_u64() >= Some(FAKES as u64 - MAX)
    })
    .await;
    for gauge in ["tracked", "windows", "announced"] {
        assert!(stats[gauge].as_u64().unwrap() <= MAX, "{gauge}: {stats}");
    }
    // Each forgotten device's tracker was withdrawn (an empty retained config).
    let deadline = tokio::time::Instant::now() + WAIT;
    loop {
        client.drain();
        let withdrawn = client
            .seen
            .iter()
            .filter(|m| {
                m.topic.starts_with("homeassistant/device_tracker/") && m.payload.is_empty()
            })
            .count();
        if withdrawn >= FAKES - MAX as usize {
            break;
        }
        assert!(
            tokio::time::Instant::now() < deadline,
            "{withdrawn} withdrawn"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // What the broker retains is at most the bound: a new subscriber gets
    // only the live trackers.
    let mut late = client_with(&broker, "test-late", &trackers).await;
    tokio::time::sleep(Duration::from_secs(2)).await;
    late.drain();
    let retained = late.seen.iter().filter(|m| m.retain).count();
    assert!(
        (1..=MAX as usize).contains(&retained),
        "{retained} trackers retained"
    );
}

async fn client_with(broker: &Broker, id: &str, filter: &str) -> Client {
    Client::connect(broker, id, &[filter]).await
}

/// The gateway of `config` started with `mqtt_lines` added to its `[mqtt]`,
/// and a client watching its replies, stats and Home Assistant trackers
/// (once the first stats came); with the trackers' filter and a phone scan
/// that hears two of the site's beacons.
async fn tracker_rig(
    broker: &Broker,
    config: &std::path::Path,
    client_id: &str,
    mqtt_lines: &str,
) -> (String, Client, Gateway, String) {
    append_mqtt(config, mqtt_lines);
    let trackers = "homeassistant/device_tracker/gw-test/#".to_owned();
    let mut filters = replies_and_stats();
    filters.push(trackers.clone());
    let mut client = client(broker, client_id, &filters).await;
    let gateway = Gateway::start(config, &[]);
    stats_where(&mut client, "the first stats", |_| true).await;
    let uuid = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84";
    let scan = json!([
        {"uuid": uuid, "major": 1, "minor": 3008, "rssi": -55},
        {"uuid": uuid, "major": 1, "minor": 3005, "rssi": -72},
    ])
    .to_string();
    (trackers, client, gateway, scan)
}

/// Appends `lines` to the config's `[mqtt]` table (the last one).
fn append_mqtt(config: &std::path::Path, lines: &str) {
    let mut text = std::fs::read_to_string(config).unwrap();
    text.push_str(lines);
    std::fs::write(config, text).unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn made_up_ids_get_no_home_assistant_tracker_and_new_ones_come_at_the_capped_pace() {
    const CAP: usize = 10;
    let broker = Broker::start();
    let config = gateway_config(
        "gw-test",
        &waldo(),
        &broker,
        "[ble]\nadapter = \"hci-gangway-test-none\"\n",
    );
    let (_, mut client, _gateway, scan) = tracker_rig(
        &broker,
        &config.path,
        "test-flood",
        &format!("ha_new_trackers_per_minute = {CAP}\n"),
    )
    .await;
    let send = async |client: &Client, device: &str, scans: usize| {
        for _ in 0..scans {
            client
                .publish(&format!("{PREFIX}/scans/{device}"), scan.clone())
                .await;
            tokio::time::sleep(Duration::from_millis(2)).await;
        }
    };
    // 500 made-up ids, two scans each (one fix): located, never announced.
    for d in 0..500 {
        send(&client, &format!("fake-{d}"), 2).await;
    }
    stats_where(&mut client, "stats with the fakes located", |s| {
        s["fixes"].as_u64() >= Some(500)
    })
    .await;
    // 3 × CAP ids that keep scanning for 10 s (a fix per window, every
    // 2 s): CAP of them announced this minute.
    for _ in 0..10 {
        for d in 0..3 * CAP {
            send(&client, &format!("patient-{d}"), 1).await;
        }
        tokio::time::sleep(Duration::from_secs(1)).await;
    }
    let stats = stats_where(&mut client, "stats with the patient ones refused", |s| {
        s["trackers_refused"].as_u64() >= Some(2 * CAP as u64)
    })
    .await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    client.drain();
    let announced: Vec<&str> = client
        .seen
        .iter()
        .filter(|m| m.topic.starts_with("homeassistant/device_tracker/") && !m.payload.is_empty())
        .map(|m| m.topic.as_str())
        .collect();
    assert_eq!(announced.len(), CAP, "{announced:?}; {stats}");
    assert!(
        announced.iter().all(|t| t.contains("/patient-")),
        "{announced:?}"
    );
    assert_eq!(stats["announced"], CAP as u64, "{stats}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_truncated_store_is_moved_aside_and_feedback_needs_a_route_given() {
    let broker = Broker::start();
    let dir = tempfile::tempdir().unwrap();
    let store_path = dir.path().join("learning.sqlite");
    {
        let mut store = gangway::store::Store::open(&store_path).unwrap();
        let fixes: Vec<gangway::store::Record> = (0..5000)
            .map(|i| gangway::store::Record::Fix {
                device: "old".into(),
                t: f64::from(i),
                floor: None,
                cell: gangway::site::Cell::new(1, 1),
                confidence: 0.5,
            })
            .collect();
        store.write(&fixes).unwrap();
    }
    let bytes = std::fs::read(&store_path).unwrap();
    std::fs::write(&store_path, &bytes[..bytes.len() / 2]).unwrap();
    let config = gateway_config(
        "gw-test",
        &waldo(),
        &broker,
        &format!(
            "[store]\nenabled = true\npath = \"{}\"\n",
            store_path.display()
        ),
    );
    let mut client = client(&broker, "test-store", &replies_and_stats()).await;
    let _gateway = Gateway::start(&config.path, &["--replay", &fixture(), "--speed", "4"]);
    let stats = stats_where(&mut client, "stats listing the store's fallback", |s| {
        s["fallbacks"].to_string().contains("moved it aside")
    })
    .await;
    assert!(
        stats["fallbacks"].to_string().contains("learning.sqlite"),
        "{stats}"
    );
    located(&mut client, "walker-03").await;
    let reply = client.route(PREFIX, "walker-03", "help desk", "s1").await;
    assert!(reply["waypoints"].is_array(), "{reply}");

    let feedback = format!("{PREFIX}/devices/walker-03/feedback");
    client
        .publish(&feedback, r#"{"request_id":"s1","score":5}"#)
        .await;
    for never in ["never-given", "s1"] {
        // A route never given, and one already scored.
        client
            .publish(
                &feedback,
                format!(r#"{{"request_id":"{never}","score":1}}"#),
            )
            .await;
        let error = client
            .wait_for("the feedback error", |m| {
                m.topic == format!("{feedback}/error") && m.json()["request_id"] == never
            })
            .await
            .json();
        assert_eq!(error["error"]["code"], "unknown_request", "{error}");
    }
    let stats = stats_where(&mut client, "stats with the feedback", |s| {
        s["feedback"] == 1 && s["feedback_refused"] == 2 && s["recorded"].as_u64() > Some(0)
    })
    .await;
    assert_eq!(stats["store_errors"], 0, "{stats}");
    assert!(assert_all_valid(&client.seen) > 3);
    use std::os::unix::fs::PermissionsExt;
    let mode = std::fs::metadata(&store_path).unwrap().permissions().mode();
    assert_eq!(mode & 0o777, 0o600, "the new store is private");
    let aside = std::fs::read_dir(dir.path())
        .unwrap()
        .filter(|e| {
            let name = e.as_ref().unwrap().file_name();
            name.to_string_lossy()
                .starts_with("learning.sqlite.broken-")
        })
        .count();
    assert!(aside >= 1, "the broken store is kept for inspection");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_lines_whose_ids_cannot_be_topics_are_refused_per_line() {
    let broker = Broker::start();
    let dir = tempfile::tempdir().unwrap();
    let log = dir.path().join("hostile.jsonl");
    let mut text: String = std::fs::read_to_string(fixture())
        .unwrap()
        .lines()
        .take(1500)
        .map(|l| format!("{l}\n"))
        .collect();
    let t = 1_767_225_610.0;
    for bad in [
        json!({"type": "request", "t": t, "device": "evil/#", "to": "help desk", "request_id": "x"}),
        json!({"type": "request", "t": t, "device": "a+b", "to": "help desk"}),
        json!({"type": "advert", "t": t, "observer": "spy/#", "uuid": "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84", "major": 1, "minor": 3001, "rssi": -60}),
    ] {
        text.push_str(&format!("{bad}\n"));
    }
    text.push_str(&format!(
        "{}\n",
        json!({"type": "request", "t": t + 1.0, "device": "walker-01", "to": "help desk", "request_id": "good"})
    ));
    std::fs::write(&log, text).unwrap();
    let config = gateway_config("gw-test", &waldo(), &broker, "");
    let mut client = client(&broker, "test-ids", &replies_and_stats()).await;
    let _gateway = Gateway::start(
        &config.path,
        &["--replay", log.to_str().unwrap(), "--speed", "0"],
    );
    let reply = client.reply(PREFIX, "walker-01", "good").await;
    assert!(reply["waypoints"].is_array(), "{reply}");
    let reply = client.route(PREFIX, "walker-01", "printers", "live").await;
    assert!(reply["waypoints"].is_array(), "{reply}");
    let stats = stats_where(&mut client, "stats", |s| s["requests"].as_u64() >= Some(2)).await;
    assert_eq!(stats["disconnects"], 0, "{stats}");
    assert_eq!(stats["unpublishable"], 0, "{stats}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn no_password_appears_in_any_output() {
    const SECRET: &str = "Sekr1t-9f8e7d-never-print-me";
    let broker = Broker::start_with(|dir: &Path| {
        let passwd = dir.join("passwd");
        let status = std::process::Command::new("mosquitto_passwd")
            .args(["-b", "-c"])
            .arg(&passwd)
            .args(["gangway", SECRET])
            .status()
            .expect("mosquitto_passwd (package mosquitto)");
        assert!(status.success());
        format!("allow_anonymous true\npassword_file {}\n", passwd.display())
    });
    let config = gateway_config("gw-test", &waldo(), &broker, "");
    std::fs::write(config.dir.path().join("pw"), format!("{SECRET}\n")).unwrap();
    let good = std::fs::read_to_string(&config.path).unwrap()
        + "username = \"gangway\"\npassword_file = \"pw\"\n";
    std::fs::write(&config.path, &good).unwrap();
    let mut client = Client::connect(&broker, "test-secret", &["#"]).await;
    let log = config.dir.path().join("gateway.log");
    let gateway = Gateway::start_logged(
        &config.path,
        &["--replay", &fixture(), "--speed", "4"],
        "debug",
        &log,
    );
    located(&mut client, "walker-01").await;
    let reply = client.route(PREFIX, "walker-01", "help desk", "r1").await;
    assert!(reply["waypoints"].is_array(), "{reply}");

    // Someone puts the password in the config itself: `check` and a reload
    // refuse it without repeating it.
    let inline = good.replace(
        "password_file = \"pw\"",
        &format!("password = \"{SECRET}\""),
    );
    let inline_path = config.dir.path().join("inline.toml");
    std::fs::write(&inline_path, &inline).unwrap();
    let check = std::process::Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args(["check", "--config"])
        .arg(&inline_path)
        .output()
        .unwrap();
    assert!(!check.status.success());
    let check_output = format!(
        "{}{}",
        String::from_utf8_lossy(&check.stdout),
        String::from_utf8_lossy(&check.stderr)
    );
    assert!(check_output.contains("password_file"), "{check_output}");
    std::fs::write(&config.path, &inline).unwrap();
    signal(&gateway.child, "HUP");
    stats_where(&mut client, "the refused reload", |s| {
        s["reload_failures"] == 1
    })
    .await;
    tokio::time::sleep(Duration::from_secs(1)).await;
    client.drain();

    let log_text = std::fs::read_to_string(&log).unwrap();
    assert!(log_text.contains("reload refused"), "the log is read");
    assert!(log_text.contains("password_file"));
    for (what, text) in [
        ("check", check_output.as_str()),
        ("the log", log_text.as_str()),
    ] {
        assert!(!text.contains(SECRET), "the password is in {what}");
    }
    let mut messages = 0;
    for m in &client.seen {
        assert!(
            !String::from_utf8_lossy(&m.payload).contains(SECRET) && !m.topic.contains(SECRET),
            "the password is in {}",
            m.topic
        );
        messages += 1;
    }
    assert!(messages > 10, "{messages} messages checked");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_gateway_that_cannot_stay_connected_says_so() {
    let mut broker = Broker::start();
    let config = gateway_config("gw-test", &waldo(), &broker, "");
    let mut client = client(&broker, "test-flap", &replies_and_stats()).await;
    let log = config.dir.path().join("gateway.log");
    let _gateway = Gateway::start_logged(&config.path, &[], "info", &log);
    stats_where(&mut client, "the first stats", |s| s["mqtt"] == "connected").await;
    // Five connections lost within a minute.
    for lost in 1..=5u64 {
        broker.restart();
        stats_where(&mut client, "stats after the reconnect", |s| {
            s["reconnects"].as_u64() >= Some(lost)
        })
        .await;
    }
    let stats = stats_where(&mut client, "stats saying so", |s| s["mqtt"] == "flapping").await;
    assert!(stats["disconnects"].as_u64() >= Some(5), "{stats}");
    let log = std::fs::read_to_string(&log).unwrap();
    assert!(
        log.contains("cannot stay connected to the MQTT broker"),
        "{log}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_payload_cannot_forge_a_log_line() {
    // Issue #29: an unknown key holding a newline, a fake ERROR line and
    // escape sequences used to reach the log raw through serde's error text.
    let broker = Broker::start();
    let config = gateway_config("gw-test", &waldo(), &broker, "");
    let mut client = client(&broker, "test-forge-log", &replies_and_stats()).await;
    let log = config.dir.path().join("gateway.log");
    let _gateway = Gateway::start_logged(&config.path, &[], "info", &log);
    stats_where(&mut client, "the first stats", |s| s["mqtt"] == "connected").await;
    let forged = "x\n2026-12-04T00:00:00.000000Z ERROR gangway: the gateway was compromised\r\u{1b}[2J\u{1b}]0;pwned\u{7}";
    let payload = serde_json::json!({ "request_id": "r", "score": 3, forged: 1 }).to_string();
    client
        .publish("gangway/gw-test/devices/phone-1/feedback", payload)
        .await;
    stats_where(&mut client, "the forged feedback refused", |s| {
        s["rejected_messages"].as_u64() >= Some(1)
    })
    .await;
    let log = std::fs::read_to_string(&log).unwrap();
    let refused = log
        .lines()
        .find(|l| l.contains("ignored message"))
        .unwrap_or_else(|| panic!("no line about the message:\n{log}"));
    assert!(
        refused.contains("\\n2026-12-04T00:00:00.000000Z ERROR"),
        "{refused}"
    );
    assert!(
        !log.lines()
            .any(|l| l.contains("ERROR gangway: the gateway was compromised")
                && !l.contains("ignored message")),
        "a forged line:\n{log}"
    );
    assert!(
        !log.chars()
            .any(|c| c.is_control() && c != '\n' && c != '\t'),
        "a raw control character in the log:\n{log:?}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_gateway_puts_back_its_own_retained_topics_when_overwritten() {
    // Issue #29: a forged retained `offline` on the status topic left every
    // Home Assistant entity of the gateway unavailable, and an empty retained
    // config deleted a tracker for good.
    let broker = Broker::start();
    let config = gateway_config("gw-test", &waldo(), &broker, "");
    let trackers = "homeassistant/device_tracker/gw-test/#";
    let status = format!("{PREFIX}/status");
    let mut filters = replies_and_stats();
    filters.push(trackers.to_owned());
    filters.push(status.clone());
    let mut client = client(&broker, "test-overwrite", &filters).await;
    let _gateway = Gateway::start(&config.path, &[]);
    stats_where(&mut client, "the first stats", |_| true).await;
    // A phone located: its tracker announced.
    let uuid = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84";
    let scan = json!([{"uuid": uuid, "major": 1, "minor": 3008, "rssi": -55}]).to_string();
    // Its third fix (`ha_min_fixes`; a fix per window of scans, every 2 s):
    // its tracker announced.
    for _ in 0..10 {
        client
            .publish(&format!("{PREFIX}/scans/phone-1"), scan.clone())
            .await;
        tokio::time::sleep(Duration::from_millis(1000)).await;
    }
    let tracker = "homeassistant/device_tracker/gw-test/phone-1/config";
    client
        .wait_for("phone-1's tracker", |m| {
            m.topic == tracker && !m.payload.is_empty()
        })
        .await;

    for (topic, forged) in [(status.as_str(), "offline"), (tracker, "")] {
        let overwritten = client.seen.len();
        client
            .client
            .publish(topic, rumqttc::QoS::AtLeastOnce, true, forged)
            .await
            .unwrap();
        // Put back within 5 s: the forged message, then the gateway's.
        let started = std::time::Instant::now();
        let restored = loop {
            client.drain();
            let after = &client.seen[overwritten..];
            let forged_at = after
                .iter()
                .position(|m| m.topic == topic && m.payload == forged.as_bytes());
            if let Some(i) = forged_at
                && let Some(m) = after[i..]
                    .iter()
                    .find(|m| m.topic == topic && m.payload != forged.as_bytes())
            {
                break m.clone();
            }
            assert!(
                started.elapsed() < Duration::from_secs(5),
                "{topic} not put back: {:?}",
                after
                    .iter()
                    .map(|m| (&m.topic, m.text()))
                    .collect::<Vec<_>>()
            );
            tokio::time::sleep(Duration::from_millis(50)).await;
        };
        // A new subscriber (Home Assistant after a restart) gets the
        // gateway's message, not the forged one.
        let mut late = client_with(&broker, &format!("test-late-{}", forged.len()), topic).await;
        let retained = late
            .wait_for(&format!("{topic} as retained"), |m| {
                m.topic == topic && m.retain
            })
            .await;
        assert_eq!(retained.payload, restored.payload, "{topic}");
    }
}
