//! `gangway replay` runs the whole pipeline on a log: every walker is located,
//! close to where it really was, and every request is answered.

use crate::common;

use std::collections::{BTreeMap, BTreeSet};

use crate::common::{gangway, gangway_ok, write};
use serde_json::Value;

const FIXTURE: &str = "fixtures/walk-waldo.jsonl";

fn log_events() -> Vec<Value> {
    std::fs::read_to_string(common::root().join(FIXTURE))
        .unwrap()
        .lines()
        .map(|l| serde_json::from_str(l).unwrap())
        .collect()
}

fn printed(stdout: &str) -> Vec<Value> {
    stdout
        .lines()
        .map(|l| serde_json::from_str(l).expect("one JSON message per line"))
        .collect()
}

#[test]
fn every_observer_is_located_near_its_truth() {
    let events = log_events();
    let observers: BTreeSet<&str> = events
        .iter()
        .filter(|e| e["type"] == "advert")
        .map(|e| e["observer"].as_str().unwrap())
        .collect();
    // Truth per device and whole second.
    let truth: BTreeMap<(String, i64), (i64, i64)> = events
        .iter()
        .filter(|e| e["type"] == "truth")
        .map(|e| {
            let key = (
                e["device"].as_str().unwrap().to_owned(),
                e["t"].as_f64().unwrap() as i64,
            );
            (
                key,
                (
                    e["cell"][0].as_i64().unwrap(),
                    e["cell"][1].as_i64().unwrap(),
                ),
            )
        })
        .collect();

    let messages = printed(&gangway_ok(&["replay", FIXTURE, "--speed", "0", "--print"]));
    let locations: Vec<&Value> = messages
        .iter()
        .filter(|m| m["topic"].as_str().unwrap().ends_with("/location"))
        .collect();
    let located: BTreeSet<&str> = locations
        .iter()
        .map(|m| m["payload"]["device"].as_str().unwrap())
        .collect();
    assert_eq!(
        located, observers,
        "a location for every observer in the log"
    );

    let mut errors = Vec::new();
    let mut unknown = 0;
    for m in &locations {
        let p = &m["payload"];
        // Too little heard for a cell: published as an unknown location.
        if p["cell"].is_null() {
            unknown += 1;
            continue;
        }
        assert_eq!(
            m["topic"],
            format!(
                "gangway/gw-lobby/devices/{}/location",
                p["device"].as_str().unwrap()
            )
        );
        let key = (
            p["device"].as_str().unwrap().to_owned(),
            p["t"].as_f64().unwrap().round() as i64,
        );
        if let Some(&(tx, ty)) = truth.get(&key) {
            let (x, y) = (
                p["cell"][0].as_i64().unwrap(),
                p["cell"][1].as_i64().unwrap(),
            );
            errors.push((((x - tx).pow(2) + (y - ty).pow(2)) as f64).sqrt());
        }
    }
    assert!(
        unknown * 4 < locations.len(),
        "{unknown} of {} locations unknown",
        locations.len()
    );
    assert!(
        errors.len() >= (locations.len() - unknown) / 2,
        "fixes line up with truth events"
    );
    let mean = errors.iter().sum::<f64>() / errors.len() as f64;
    // A guard on what the calibrated path-loss localizer with tracking reaches
    // on this fixture (about 2.5 cells: the real floor's beacons are heard
    // sparsely), with room for noise; a broken pipeline is far off.
    assert!(mean < 3.5, "mean error {mean:.2} cells");
}

#[test]
fn every_request_gets_a_route_or_an_error() {
    let events = log_events();
    let requests: BTreeSet<&str> = events
        .iter()
        .filter(|e| e["type"] == "request")
        .map(|e| e["request_id"].as_str().unwrap())
        .collect();
    assert!(!requests.is_empty());
    let messages = printed(&gangway_ok(&["replay", FIXTURE, "--print"]));
    let replies: Vec<&Value> = messages
        .iter()
        .filter(|m| m["topic"].as_str().unwrap().ends_with("/path"))
        .map(|m| &m["payload"])
        .collect();
    let answered: BTreeSet<&str> = replies
        .iter()
        .map(|p| p["request_id"].as_str().unwrap())
        .collect();
    assert_eq!(answered, requests);
    for reply in replies {
        let waypoints = reply["waypoints"]
            .as_array()
            .expect("a route, not an error");
        assert_eq!(waypoints.first().unwrap()["cell"], reply["from"]);
        assert_eq!(waypoints.last().unwrap()["cell"], reply["to"]);
    }
}

#[test]
fn scripted_requests_get_precise_errors() {
    let dir = tempfile::tempdir().unwrap();
    let uuid = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84";
    let mut log = String::new();
    for t in 0..6 {
        log += &format!(
            "{{\"t\":{t},\"type\":\"advert\",\"observer\":\"p1\",\"uuid\":\"{uuid}\",\"major\":1,\"minor\":3008,\"rssi\":-60}}\n"
        );
    }
    log += "{\"t\":6,\"type\":\"request\",\"device\":\"p1\",\"to\":\"nowhere\",\"request_id\":\"a\"}\n";
    log += "{\"t\":6,\"type\":\"request\",\"device\":\"p1\",\"to\":[99,0],\"request_id\":\"b\"}\n";
    log += "{\"t\":6,\"type\":\"request\",\"device\":\"p1\",\"to\":[0,0],\"request_id\":\"c\"}\n";
    log += "{\"t\":6,\"type\":\"request\",\"device\":\"ghost\",\"to\":\"help desk\",\"request_id\":\"d\"}\n";
    log += "{\"t\":6,\"type\":\"request\",\"device\":\"p1\",\"to\":\"help desk\",\"request_id\":\"e\"}\n";
    let path = write(dir.path(), "requests.jsonl", &log);
    let messages = printed(&gangway_ok(&["replay", path.to_str().unwrap(), "--print"]));
    let code = |id: &str| {
        messages
            .iter()
            .find(|m| m["payload"]["request_id"] == id)
            .map(|m| m["payload"]["error"]["code"].clone())
            .unwrap_or_else(|| panic!("no reply to {id}"))
    };
    assert_eq!(code("a"), "unknown_place");
    assert_eq!(code("b"), "off_map");
    assert_eq!(code("c"), "blocked_cell");
    assert_eq!(code("d"), "unknown_device");
    assert_eq!(code("e"), Value::Null, "a good request gets a route");
}

#[test]
fn a_bad_line_is_named_or_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let good = std::fs::read_to_string(common::root().join(FIXTURE)).unwrap();
    let mut lines: Vec<&str> = good.lines().take(200).collect();
    lines.insert(100, "{\"t\": 1, \"type\": \"advert\", \"observer\": \"x\"}");
    let path = write(dir.path(), "bad.jsonl", &(lines.join("\n") + "\n"));

    let out = gangway(&["replay", path.to_str().unwrap()]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("bad.jsonl:101: missing field `uuid`"),
        "{stderr}"
    );

    let out = gangway(&["replay", path.to_str().unwrap(), "--skip-bad", "--print"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("/location"));
}

#[test]
fn heard_lists_every_beacon_known_or_not_and_the_counts_agree_with_the_log() {
    let dir = tempfile::tempdir().unwrap();
    let good = std::fs::read_to_string(common::root().join(FIXTURE)).unwrap();
    // The fixture, plus a beacon the site does not have, heard by two phones.
    let stranger = "0f0e0d0c-0b0a-4908-8706-050403020100";
    let mut log = good.clone();
    for (i, (observer, rssi)) in [("walker-01", -80), ("walker-02", -70), ("walker-01", -90)]
        .into_iter()
        .enumerate()
    {
        log.push_str(&format!(
            "{{\"type\":\"advert\",\"t\":{},\"observer\":\"{observer}\",\"uuid\":\"{stranger}\",\"major\":7,\"minor\":1,\"rssi\":{rssi}}}\n",
            1_767_225_700 + i
        ));
    }
    let path = write(dir.path(), "with-stranger.jsonl", &log);
    let out = gangway(&["replay", path.to_str().unwrap(), "--heard", "--json"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let stdout = String::from_utf8_lossy(&out.stdout);
    let heard: Value = serde_json::from_str(stdout.trim()).expect("one JSON line");
    let heard = heard["heard"].as_array().unwrap();

    // Counted against the log itself.
    let mut expected: BTreeMap<(String, u64), u64> = BTreeMap::new();
    for e in log_events().iter().filter(|e| e["type"] == "advert") {
        let key = (
            e["uuid"].as_str().unwrap().to_owned(),
            e["minor"].as_u64().unwrap(),
        );
        *expected.entry(key).or_default() += 1;
    }
    assert_eq!(heard.len(), expected.len() + 1);
    for b in heard {
        let key = (
            b["uuid"].as_str().unwrap().to_owned(),
            b["minor"].as_u64().unwrap(),
        );
        if key.0 == stranger {
            assert_eq!(b["count"], 3);
            assert_eq!(b["known"], false);
            assert_eq!(
                (b["rssi_median"].as_i64(), b["rssi_max"].as_i64()),
                (Some(-80), Some(-70))
            );
            assert_eq!(
                b["observers"],
                serde_json::json!(["walker-01", "walker-02"])
            );
        } else {
            assert_eq!(b["count"].as_u64(), expected.get(&key).copied(), "{b}");
            assert_eq!(b["known"], true, "{b}");
        }
    }
    let counts: Vec<u64> = heard.iter().map(|b| b["count"].as_u64().unwrap()).collect();
    assert!(
        counts.windows(2).all(|w| w[0] >= w[1]),
        "most heard first: {counts:?}"
    );

    // Without --heard, the replay says that some beacons are not in the site.
    let out = gangway(&["replay", path.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("1 of the 14 beacons heard are not in the site file")
            && stderr.contains("--heard"),
        "{stderr}"
    );
}

#[test]
fn what_is_no_capture_is_refused_and_an_empty_one_fails() {
    let dir = tempfile::tempdir().unwrap();
    let binary = dir.path().join("random.jsonl");
    // The start of an x86-64 executable's ELF header.
    let mut elf = vec![
        0x7f, b'E', b'L', b'F', 2, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 2, 0, 0x3e,
    ];
    elf.resize(64, 0);
    std::fs::write(&binary, elf).unwrap();
    let out = gangway(&["replay", binary.to_str().unwrap()]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("random.jsonl: not a capture gangway reads: elf data"),
        "{stderr}"
    );

    let empty = write(dir.path(), "empty.jsonl", "");
    let out = gangway(&["replay", empty.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("empty (0 bytes)"));

    // A capture of nothing but ground truth: read, but nothing to replay.
    let truths = write(
        dir.path(),
        "truth-only.jsonl",
        "{\"type\":\"truth\",\"t\":1.0,\"device\":\"p\",\"cell\":[1,1]}\n",
    );
    let out = gangway(&["replay", truths.to_str().unwrap()]);
    assert!(!out.status.success());
    assert!(
        String::from_utf8_lossy(&out.stderr).contains("no sightings and no route requests"),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}
