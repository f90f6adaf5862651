//! Route requests over a real mosquitto while a fixture replays: valid routes
//! for good requests, an error reply for each kind of bad one, Home Assistant
//! discovery, stats, and a graceful shutdown that leaves `offline` retained.

use crate::mqtt_support::*;
use gangway::plan::{Connectivity, Route};
use gangway::site::{Cell, Site};
use serde_json::Value;

const PREFIX: &str = "gangway/gw-test";

fn cell(v: &Value) -> Cell {
    let a: [u16; 2] = serde_json::from_value(v.clone()).expect("a cell is [x, y]");
    Cell::from(a)
}

/// The reply is a route that the site accepts from its `from` to `to`.
fn assert_valid_route(site: &Site, reply: &Value, to: Cell) {
    assert!(reply.get("error").is_none(), "expected a route: {reply}");
    assert_eq!(reply["schema"], "gangway.path/1");
    let cells: Vec<Cell> = reply["waypoints"]
        .as_array()
        .unwrap()
        .iter()
        .map(|w| cell(&w["cell"]))
        .collect();
    let from = cell(&reply["from"]);
    assert_eq!(cell(&reply["to"]), to);
    Route { cells }
        .validate(site, from, to, Connectivity::Eight)
        .unwrap_or_else(|e| panic!("invalid route {reply}: {e}"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn requests_during_a_replay_get_valid_routes_and_bad_ones_get_errors() {
    let broker = Broker::start();
    let site_path = repo().join("config/sites/waldo.toml");
    let site = Site::load(&site_path).unwrap();
    let config = gateway_config("gw-test", &site_path, &broker, "");
    let mut client = Client::connect(
        &broker,
        "test-routes",
        &[&format!("{PREFIX}/#"), "homeassistant/#"],
    )
    .await;
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let mut gateway = Gateway::start(
        &config.path,
        &["--replay", fixture.to_str().unwrap(), "--speed", "10"],
    );

    let status = client
        .wait_for("status online", |m| m.topic == format!("{PREFIX}/status"))
        .await;
    assert_eq!(status.text(), "online");
    client
        .wait_for("a location of walker-01", |m| {
            m.topic == format!("{PREFIX}/devices/walker-01/location")
        })
        .await;

    // Good requests, by place and by cell.
    let route_set = format!("{PREFIX}/devices/walker-01/route/set");
    client
        .publish(&route_set, r#"{"to":"help desk","request_id":"ok-place"}"#)
        .await;
    let reply = client.reply(PREFIX, "walker-01", "ok-place").await;
    assert_valid_route(&site, &reply, site.place("help desk").unwrap());
    client
        .publish(&route_set, r#"{"to":[13,14],"request_id":"ok-cell"}"#)
        .await;
    let reply = client.reply(PREFIX, "walker-01", "ok-cell").await;
    assert_valid_route(&site, &reply, Cell::new(13, 14));

    // Each kind of bad request gets its error reply, with the request id.
    let oversized = format!(
        r#"{{"to":"help desk","request_id":"big","pad":"{}"}}"#,
        "x".repeat(20_000)
    );
    let cases: [(&str, String, &str); 7] = [
        (
            "unknown-place",
            r#"{"to":"moon","request_id":"unknown-place"}"#.into(),
            "unknown_place",
        ),
        (
            "off-map",
            r#"{"to":[500,2],"request_id":"off-map"}"#.into(),
            "off_map",
        ),
        (
            "blocked",
            r#"{"to":[0,0],"request_id":"blocked"}"#.into(),
            "blocked_cell",
        ),
        (
            "shape",
            r#"{"to":{"x":1},"request_id":"shape"}"#.into(),
            "invalid_request",
        ),
        (
            "profile",
            r#"{"to":"help desk","profile":"jetpack","request_id":"profile"}"#.into(),
            "unknown_profile",
        ),
        ("json", "{not json".into(), "invalid_json"),
        ("big", oversized, "payload_too_large"),
    ];
    for (id, payload, _) in &cases {
        client.publish(&route_set, payload.clone()).await;
        if *id == "json" || *id == "big" {
            // These carry no readable request id: wait for each reply in turn.
            let code = cases.iter().find(|c| c.0 == *id).unwrap().2;
            let topic = format!("{PREFIX}/devices/walker-01/path");
            let m = client
                .wait_for(&format!("the {code} reply"), |m| {
                    m.topic == topic && m.json()["error"]["code"] == code
                })
                .await;
            assert!(m.json()["error"]["message"].as_str().unwrap().len() > 10);
        }
    }
    for (id, _, code) in &cases[..5] {
        let reply = client.reply(PREFIX, "walker-01", id).await;
        assert_eq!(reply["error"]["code"], *code, "{reply}");
        assert!(reply.get("waypoints").is_none());
    }
    let reply = client.route(PREFIX, "nobody", "help desk", "nobody").await;
    assert_eq!(reply["error"]["code"], "unknown_device");

    // Feedback is counted; a bad one is rejected; an oversized scan is dropped.
    let feedback = format!("{PREFIX}/devices/walker-01/feedback");
    client
        .publish(&feedback, r#"{"request_id":"ok-place","score":4}"#)
        .await;
    client
        .publish(&feedback, r#"{"request_id":"ok-place","score":9}"#)
        .await;
    client
        .publish(&format!("{PREFIX}/scans/walker-09"), vec![b' '; 20_000])
        .await;
    let stats = client
        .wait_for("stats counting feedback and drops", |m| {
            let s = m.json();
            m.topic == format!("{PREFIX}/stats")
                && s["feedback"] == 1
                && s["oversized_messages"] == 2
                && s["rejected_messages"] == 2
        })
        .await
        .json();
    assert_eq!(stats["schema"], "gangway.stats/1");
    assert!(stats["routes"].as_u64().unwrap() >= 2);
    assert!(stats["request_errors"].as_u64().unwrap() >= 8);
    assert_eq!(stats["ble"]["state"], "replay");

    // Home Assistant: a tracker for walker-01 and the gateway's status.
    let tracker = client
        .wait_for("the walker-01 tracker config", |m| {
            m.topic == "homeassistant/device_tracker/gw-test/walker-01/config"
        })
        .await
        .json();
    assert_eq!(
        tracker["json_attributes_topic"],
        format!("{PREFIX}/devices/walker-01/location")
    );
    client
        .wait_for("the gateway status config", |m| {
            m.topic == "homeassistant/binary_sensor/gw-test/status/config"
        })
        .await;

    // Everything received on the wire matches the published schemas.
    let checked = assert_all_valid(&client.seen);
    assert!(checked > 20, "only {checked} messages checked");

    // SIGTERM: a clean exit that says `offline` (retained) itself.
    assert!(gateway.terminate().success());
    let late = Client::connect(&broker, "test-routes-late", &[&format!("{PREFIX}/status")]).await;
    let mut late = late;
    let status = late
        .wait_for("retained status", |m| m.topic == format!("{PREFIX}/status"))
        .await;
    assert!(status.retain);
    assert_eq!(status.text(), "offline");
}
