//! The gateway against a broker that goes away, a process that is killed, a
//! radio that is missing, a model that is corrupt, and a config that is
//! reloaded.

use std::time::Duration;

use crate::mqtt_support::*;

const PREFIX: &str = "gangway/gw-test";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn requests_around_a_broker_restart_are_answered_after_reconnect() {
    let mut broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config("gw-test", &site, &broker, "");
    let mut client = Client::connect(&broker, "test-restart", &[&format!("{PREFIX}/#")]).await;
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    // 120 s of walking at 4× speed: the replay is still running throughout.
    let _gateway = Gateway::start(
        &config.path,
        &["--replay", fixture.to_str().unwrap(), "--speed", "4"],
    );
    let route_set = format!("{PREFIX}/devices/walker-01/route/set");
    let location = format!("{PREFIX}/devices/walker-01/location");
    client.wait_for("a location", |m| m.topic == location).await;
    client
        .publish(&route_set, r#"{"to":"help desk","request_id":"before"}"#)
        .await;
    assert!(client.reply(PREFIX, "walker-01", "before").await["waypoints"].is_array());
    let before_outage = client.seen.len();

    broker.stop();
    // A request made while the broker is down waits in the client; the
    // gateway keeps locating and queues what it cannot send.
    client
        .publish(&route_set, r#"{"to":"printers","request_id":"during"}"#)
        .await;
    tokio::time::sleep(Duration::from_secs(3)).await;
    broker.restart();
    client
        .publish(&route_set, r#"{"to":"reading room","request_id":"after"}"#)
        .await;

    for id in ["during", "after"] {
        let reply = client.reply(PREFIX, "walker-01", id).await;
        assert!(reply["waypoints"].is_array(), "{reply}");
    }
    let stats = client
        .wait_for("stats after the reconnect", |m| {
            m.topic == format!("{PREFIX}/stats") && m.json()["reconnects"].as_u64() >= Some(1)
        })
        .await
        .json();
    assert_eq!(stats["queue_dropped"], 0, "{stats}");
    // The status is re-published on reconnect (the restarted broker would
    // otherwise still hold the last will's `offline` from the outage).
    client
        .wait_for("status online after the restart", |m| {
            m.topic == format!("{PREFIX}/status") && m.text() == "online"
        })
        .await;
    // Locations made during the outage came through the offline queue: the
    // fix times of walker-01 have no gap as long as the outage (3 s of wall
    // time is 12 s of log time at 4×; fixes come every 2 s of log time).
    let mut times: Vec<f64> = client.seen[before_outage..]
        .iter()
        .filter(|m| m.topic == location)
        .map(|m| m.json()["t"].as_f64().unwrap())
        .collect();
    times.sort_by(f64::total_cmp);
    let gap = times.windows(2).map(|w| w[1] - w[0]).fold(0.0, f64::max);
    assert!(times.len() > 6, "{times:?}");
    assert!(gap < 8.0, "a {gap} s hole in the locations: {times:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_killed_gateway_leaves_the_retained_offline_of_its_last_will() {
    let broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config("gw-test", &site, &broker, "");
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let mut gateway = Gateway::start(&config.path, &["--replay", fixture.to_str().unwrap()]);
    let status = format!("{PREFIX}/status");
    let mut client = Client::connect(&broker, "test-will", &[&status]).await;
    client
        .wait_for("online", |m| m.topic == status && m.text() == "online")
        .await;
    signal(&gateway.child, "KILL");
    gateway.child.wait().unwrap();
    client
        .wait_for("offline", |m| m.topic == status && m.text() == "offline")
        .await;
    let mut late = Client::connect(&broker, "test-will-late", &[&status]).await;
    let m = late
        .wait_for("the retained status", |m| m.topic == status)
        .await;
    assert!(m.retain);
    assert_eq!(m.text(), "offline");
}

/// No Bluetooth on CI machines (nor in most containers): `run` scans nothing,
/// says so in its stats, retries, and serves phones over MQTT all the while.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn without_bluetooth_the_gateway_serves_phone_scans_and_routes() {
    let broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    // An adapter name no machine has, so the test means the same everywhere.
    let config = gateway_config(
        "gw-test",
        &site,
        &broker,
        "[ble]\nadapter = \"hci-gangway-test-none\"\n",
    );
    let mut client = Client::connect(&broker, "test-noble", &[&format!("{PREFIX}/#")]).await;
    let _gateway = Gateway::start(&config.path, &[]);
    let stats = client
        .wait_for("stats with the radio retrying", |m| {
            m.topic == format!("{PREFIX}/stats") && m.json()["ble"]["state"] == "retrying"
        })
        .await
        .json();
    assert!(stats["ble"]["error"].as_str().is_some(), "{stats}");

    // A phone near beacon b3008 (the help desk, J10) publishes its scans.
    let uuid = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84";
    let scan = serde_json::json!([
        {"uuid": uuid, "major": 1, "minor": 3008, "rssi": -55},
        {"uuid": uuid, "major": 1, "minor": 3005, "rssi": -72},
        {"uuid": uuid, "major": 1, "minor": 3010, "rssi": -80},
    ]);
    let fix = client.scan_until_located(PREFIX, "phone-1", &scan).await;
    let fix = fix.expect("a location from the phone's scans");
    let cell: [u16; 2] = serde_json::from_value(fix["cell"].clone()).unwrap();
    let (dx, dy) = (cell[0].abs_diff(9), cell[1].abs_diff(9));
    assert!(dx.max(dy) <= 3, "phone-1 placed at {cell:?}, far from J10");

    let reply = client.route(PREFIX, "phone-1", "printers", "p1").await;
    assert!(reply["waypoints"].is_array(), "{reply}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn sighup_applies_a_good_config_and_refuses_a_bad_one() {
    let broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config("gw-test", &site, &broker, "");
    let stats_topic = format!("{PREFIX}/stats");
    let mut client = Client::connect(&broker, "test-hup", &[&format!("{PREFIX}/#")]).await;
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let gateway = Gateway::start(
        &config.path,
        &["--replay", fixture.to_str().unwrap(), "--speed", "4"],
    );
    client.wait_for("stats", |m| m.topic == stats_topic).await;

    // A site with a ragged map: refused, and the gateway keeps serving.
    let bad_site = config.dir.path().join("bad.toml");
    std::fs::write(
        &bad_site,
        "name = \"x\"\ncell_m = 1.0\nmap = '''\n##\n#\n'''\n",
    )
    .unwrap();
    write_config(&config.path, "gw-test", &bad_site, &broker, "");
    signal(&gateway.child, "HUP");
    client
        .wait_for("a refused reload", |m| {
            m.topic == stats_topic && m.json()["reload_failures"] == 1
        })
        .await;
    let reply = client
        .route(PREFIX, "walker-02", "help desk", "still")
        .await;
    assert!(reply["waypoints"].is_array() || reply["error"]["code"] == "unknown_device");

    // The good config again, with a different planner setting: applied.
    write_config(
        &config.path,
        "gw-test",
        &site,
        &broker,
        "[planner]\nconnectivity = \"four\"\n",
    );
    let stats = reload_applied(&mut client, &gateway).await;
    assert_eq!(stats["reload_failures"], 1);
}

/// A corrupt planner model at start-up: the gateway serves with `astar` and
/// says so in its stats; once the file is fixed, a reload brings the learned
/// planner back and empties the list.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_corrupt_model_at_start_up_falls_back_to_astar_until_a_reload() {
    let broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    let planner = |model: &std::path::Path| {
        format!(
            "[planner]\nmode = \"conditional\"\n[planner.models]\nconditional_generator = \"{}\"\n",
            model.display()
        )
    };
    let config = gateway_config("gw-test", &site, &broker, "");
    let corrupt = config.dir.path().join("conditional_generator.onnx");
    std::fs::write(&corrupt, b"\x08\x07not a model").unwrap();
    write_config(&config.path, "gw-test", &site, &broker, &planner(&corrupt));
    let stats_topic = format!("{PREFIX}/stats");
    let mut client = Client::connect(&broker, "test-corrupt", &[&format!("{PREFIX}/#")]).await;
    let gateway = Gateway::start(&config.path, &[]);
    let stats = client
        .wait_for("stats", |m| m.topic == stats_topic)
        .await
        .json();
    check_schema("stats", &stats).unwrap();
    let fallbacks = stats["fallbacks"].as_array().expect("a list").clone();
    assert_eq!(fallbacks.len(), 1, "{stats}");
    let why = fallbacks[0].as_str().unwrap();
    assert!(
        why.contains("conditional_generator.onnx") && why.contains("astar"),
        "{why}"
    );

    // Routes are still answered: a phone near the help desk asks for one.
    let uuid = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84";
    let scan = serde_json::json!([{"uuid": uuid, "major": 1, "minor": 3008, "rssi": -55}]);
    client
        .scan_until_located(PREFIX, "phone-1", &scan)
        .await
        .expect("a location from the phone's scans");
    let reply = client
        .route(PREFIX, "phone-1", "printers", "degraded")
        .await;
    assert!(reply["waypoints"].is_array(), "{reply}");
    assert_eq!(reply["planner"], "astar", "{reply}");

    // The real model in place of the corrupt one: the reload applies it.
    let model = repo().join("models/conditional_generator.onnx");
    write_config(&config.path, "gw-test", &site, &broker, &planner(&model));
    let stats = reload_applied(&mut client, &gateway).await;
    assert_eq!(stats["fallbacks"], serde_json::json!([]), "{stats}");
}

/// Sends SIGHUP to `gateway` and waits for the stats of its first applied
/// reload.
async fn reload_applied(client: &mut Client, gateway: &Gateway) -> serde_json::Value {
    signal(&gateway.child, "HUP");
    let stats_topic = format!("{PREFIX}/stats");
    client
        .wait_for("an applied reload", |m| {
            m.topic == stats_topic && m.json()["reloads"] == 1
        })
        .await
        .json()
}

/// A queue bound smaller than what piles up during an outage: the oldest
/// messages go, the count says how many, and the newest still arrive.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn past_the_queue_bound_the_oldest_messages_are_dropped_and_counted() {
    let mut broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config("gw-test", &site, &broker, "");
    let text = std::fs::read_to_string(&config.path).unwrap();
    std::fs::write(&config.path, format!("{text}queue_max_messages = 5\n")).unwrap();
    let mut client = Client::connect(&broker, "test-bound", &[&format!("{PREFIX}/#")]).await;
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let _gateway = Gateway::start(
        &config.path,
        &["--replay", fixture.to_str().unwrap(), "--speed", "4"],
    );
    client
        .wait_for("a location", |m| m.topic.ends_with("/location"))
        .await;
    broker.stop();
    tokio::time::sleep(Duration::from_secs(3)).await;
    broker.restart();
    let stats = client
        .wait_for("stats counting drops", |m| {
            m.topic == format!("{PREFIX}/stats") && m.json()["queue_dropped"].as_u64() > Some(0)
        })
        .await
        .json();
    assert!(stats["queue_depth"].as_u64() <= Some(5), "{stats}");
}

/// SIGTERM while the broker is unreachable: the gateway gives up after the
/// grace period instead of hanging.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn shutdown_without_a_broker_ends_after_the_grace_period() {
    let mut broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config("gw-test", &site, &broker, "");
    let text = std::fs::read_to_string(&config.path).unwrap();
    std::fs::write(&config.path, format!("{text}shutdown_grace_s = 1.0\n")).unwrap();
    let status = format!("{PREFIX}/status");
    let mut client = Client::connect(&broker, "test-grace", &[&status]).await;
    let mut gateway = Gateway::start(&config.path, &["--replay", "/dev/null"]);
    client
        .wait_for("online", |m| m.topic == status && m.text() == "online")
        .await;
    broker.stop();
    // `terminate` fails the test if the gateway is still running after 30 s;
    // without the grace period it would wait for the broker forever.
    assert!(gateway.terminate().success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_sighup_while_the_gateway_starts_is_a_reload_not_its_end() {
    // Issue #29: a SIGHUP 10 to 50 ms after start used to kill the process
    // (the handler came after the models had loaded).
    let broker = Broker::start();
    let mut client = Client::connect(&broker, "test-early-hup", &["gangway/#"]).await;
    for delay_ms in [10, 30, 50] {
        let id = format!("gw-hup-{delay_ms}");
        let config = gateway_config(&id, &repo().join("config/sites/waldo.toml"), &broker, "");
        let mut gateway = Gateway::start(&config.path, &["--replay", "/dev/null"]);
        tokio::time::sleep(Duration::from_millis(delay_ms)).await;
        signal(&gateway.child, "HUP");
        let stats = format!("gangway/{id}/stats");
        client
            .wait_for(&format!("{id} serving after an early SIGHUP"), |m| {
                m.topic == stats && m.json()["mqtt"] == "connected"
            })
            .await;
        assert!(
            gateway.child.try_wait().unwrap().is_none(),
            "{id} ended after SIGHUP at {delay_ms} ms"
        );
        assert!(gateway.terminate().success(), "{id}");
    }
}
