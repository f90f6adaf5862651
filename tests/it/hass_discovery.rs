//! The gateway's side of Home Assistant discovery over a real mosquitto,
//! without Home Assistant (tests/it/hass.rs has it): the retained occupancy
//! counts agree with the locations the gateway published, each tracker's
//! presence comes right before its location, and a reload onto a site
//! without a place removes that place's sensor (an empty retained config)
//! and announces the new site's.

use std::collections::BTreeMap;

use crate::mqtt_support::*;
use serde_json::Value;

const PREFIX: &str = "gangway/gw-test";
const SENSORS: &str = "homeassistant/sensor/gw-test";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn occupancy_follows_the_locations_and_a_reload_replaces_the_place_sensors() {
    let broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config("gw-test", &site, &broker, "");
    let mut client = Client::connect(
        &broker,
        "test-hass-discovery",
        &[&format!("{PREFIX}/#"), "homeassistant/#"],
    )
    .await;
    client.ready(&format!("{PREFIX}/probe")).await;
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let gateway = Gateway::start(
        &config.path,
        &["--replay", fixture.to_str().unwrap(), "--speed", "0"],
    );

    // The replay is over once the stats count as many fixes as locations
    // came (the daemon serves on after it).
    let is_location = |m: &Received| m.topic.ends_with("/location");
    client
        .wait_for("stats counting every location", |m| {
            m.topic == format!("{PREFIX}/stats") && m.json()["fixes"].as_u64() > Some(150)
        })
        .await;
    tokio::time::sleep(std::time::Duration::from_millis(1500)).await;
    client.drain();
    let fixes = client
        .seen
        .iter()
        .rev()
        .find(|m| m.topic == format!("{PREFIX}/stats"))
        .unwrap()
        .json()["fixes"]
        .as_u64()
        .unwrap();
    let deadline = std::time::Instant::now() + WAIT;
    while (client.seen.iter().filter(|m| is_location(m)).count() as u64) < fixes {
        assert!(std::time::Instant::now() < deadline, "missing locations");
        tokio::time::sleep(std::time::Duration::from_millis(100)).await;
        client.drain();
    }
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    client.drain();

    // A device gets its tracker at its third location with a cell
    // (`ha_min_fixes`): from then on each location's presence came just
    // before it, and says where it is.
    let mut places: BTreeMap<String, Option<String>> = BTreeMap::new();
    let mut located: BTreeMap<String, usize> = BTreeMap::new();
    for (i, m) in client
        .seen
        .iter()
        .enumerate()
        .filter(|(_, m)| is_location(m))
    {
        let location = m.json();
        let device = location["device"].as_str().unwrap();
        let count = located.entry(device.to_owned()).or_default();
        *count += usize::from(!location["cell"].is_null());
        let presence = &client.seen[i - 1];
        if *count < 3 {
            assert!(!presence.topic.ends_with("/presence"), "{presence:?}");
            continue;
        }
        assert_eq!(
            presence.topic,
            format!("{PREFIX}/devices/{device}/presence")
        );
        // An unknown location (no cell) is away; a located one is at its
        // place, else at home.
        let expected = match location["place"].as_str() {
            Some(place) => place,
            None if location["cell"].is_null() => "not_home",
            None => "home",
        };
        assert_eq!(presence.text(), expected, "{location}");
        places.insert(
            device.to_owned(),
            location["place"].as_str().map(str::to_owned),
        );
    }
    assert_eq!(places.len(), 3);

    // The last occupancy counts are the devices' last places.
    let occupancy = client
        .seen
        .iter()
        .rev()
        .find(|m| m.topic == format!("{PREFIX}/occupancy"))
        .expect("occupancy counts")
        .json();
    let site_places = gangway::site::Site::load(&site).unwrap();
    for place in site_places.places().keys() {
        let there = places
            .values()
            .filter(|p| p.as_deref() == Some(place))
            .count();
        assert_eq!(
            occupancy["places"][place], there as u64,
            "{place}: {occupancy}"
        );
    }
    let desk_config = format!("{SENSORS}/occupancy_help_desk/config");
    let desk = client
        .wait_for("the help desk sensor", |m| m.topic == desk_config)
        .await;
    assert_eq!(desk.json()["state_topic"], format!("{PREFIX}/occupancy"));

    // The same site with the help desk renamed: reloaded, the old sensor is
    // removed and the new one announced, and the counts start afresh.
    let renamed = config.dir.path().join("renamed.toml");
    let text = std::fs::read_to_string(&site).unwrap();
    assert!(text.contains("\"help desk\" = [9, 9]"));
    std::fs::write(
        &renamed,
        text.replace("\"help desk\" = [9, 9]", "\"quiet corner\" = [9, 9]"),
    )
    .unwrap();
    write_config(&config.path, "gw-test", &renamed, &broker, "");
    let seen_before = client.seen.len();
    signal(&gateway.child, "HUP");
    let removed = client
        .wait_for("the help desk sensor removed", |m| {
            m.topic == desk_config && m.payload.is_empty()
        })
        .await;
    assert!(removed.payload.is_empty());
    client
        .wait_for("the quiet corner sensor", |m| {
            m.topic == format!("{SENSORS}/occupancy_quiet_corner/config")
        })
        .await;
    let afresh: Value = client
        .wait_for("counts for the new site", |m| {
            m.topic == format!("{PREFIX}/occupancy")
                && m.json()["places"].get("quiet corner").is_some()
        })
        .await
        .json();
    assert!(afresh["places"].get("help desk").is_none());
    assert!(
        afresh["places"]
            .as_object()
            .unwrap()
            .values()
            .all(|n| n == 0)
    );
    assert!(client.seen.len() > seen_before);
    // Only what changed went out again: the new sensor, the removed one,
    // nothing the broker already held (the status, the counters, the other
    // places' sensors).
    tokio::time::sleep(std::time::Duration::from_millis(500)).await;
    client.drain();
    let resent: Vec<&str> = client.seen[seen_before..]
        .iter()
        .filter(|m| m.topic.starts_with("homeassistant/") && m.topic.ends_with("/config"))
        .map(|m| m.topic.as_str())
        .collect();
    assert_eq!(resent.len(), 2, "{resent:?}");
    assert_all_valid(&client.seen);
}
