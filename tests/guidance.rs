//! Guidance through the whole pipeline: `gangway replay --print` of the
//! fixture (whose simulated walkers ask for routes but do not follow them)
//! starts a session per served route, sends a guidance message per fix of
//! a guided walker, notices the walkers leaving their routes and sends them
//! re-planned routes; every message matches docs/schemas.

mod common;
mod mqtt_support;

use std::collections::BTreeMap;

use common::gangway_ok;
use mqtt_support::check_schema;
use serde_json::Value;

#[test]
fn served_routes_are_guided_and_walkers_who_leave_them_are_re_routed() {
    let stdout = gangway_ok(&["replay", "fixtures/walk-waldo.jsonl", "--print"]);
    let messages: Vec<Value> = stdout
        .lines()
        .map(|l| serde_json::from_str(l).expect("one JSON message per line"))
        .collect();
    let kind = |m: &Value| {
        m["topic"]
            .as_str()
            .unwrap()
            .rsplit('/')
            .next()
            .unwrap()
            .to_owned()
    };
    let mut guided: BTreeMap<String, usize> = BTreeMap::new();
    let mut last_location: BTreeMap<String, f64> = BTreeMap::new();
    let (mut departs, mut off_route, mut rerouted_paths) = (0, 0, 0);
    for (i, m) in messages.iter().enumerate() {
        let payload = &m["payload"];
        let device = payload["device"].as_str().unwrap_or_default().to_owned();
        match kind(m).as_str() {
            "location" => {
                last_location.insert(device, payload["t"].as_f64().unwrap());
            }
            "path" if payload["reason"] == "off_route" => {
                rerouted_paths += 1;
                check_schema("path", payload).unwrap();
                // Re-planned because the guidance just said the walker left.
                assert_eq!(messages[i - 1]["payload"]["event"], "off_route", "{m}");
            }
            "path" => {
                check_schema("path", payload).unwrap();
                assert!(payload["maneuvers"][0]["type"] == "depart", "{m}");
                // Every served route starts a session at once.
                let next = &messages[i + 1]["payload"];
                assert_eq!(
                    (next["event"].as_str(), next["request_id"].as_str()),
                    (Some("depart"), payload["request_id"].as_str())
                );
            }
            "guidance" => {
                check_schema("guidance", payload).unwrap_or_else(|e| panic!("{e}: {m}"));
                *guided.entry(device.clone()).or_default() += 1;
                match payload["event"].as_str() {
                    Some("depart") | Some("rerouted") => departs += 1,
                    Some("off_route") => off_route += 1,
                    // A progress message follows the fix it is about.
                    _ => assert_eq!(last_location.get(&device), payload["t"].as_f64().as_ref()),
                }
                assert!(payload["remaining_m"].as_f64().unwrap() >= 0.0);
            }
            _ => {}
        }
    }
    assert!(departs >= 6, "a session per request: {departs}");
    assert!(guided.len() >= 3, "{guided:?}");
    assert!(
        guided.values().sum::<usize>() > departs,
        "progress per fix, not just at the start"
    );
    assert!(off_route > 0 && rerouted_paths > 0 && rerouted_paths <= off_route);
}

#[test]
fn eval_guidance_reports_every_figure() {
    let stdout = gangway_ok(&["eval", "guidance", "--trips", "12", "--seed", "3", "--json"]);
    let report: Value = serde_json::from_str(stdout.trim()).expect("one JSON object");
    // A trip whose walker is never located at the start gets no route.
    assert_eq!(
        report["trips"].as_u64().unwrap() + report["refused_trips"].as_u64().unwrap(),
        12,
        "{report}"
    );
    assert!(report["trips"].as_u64().unwrap() >= 8, "{report}");
    assert!(report["km"].as_f64().unwrap() > 0.1, "{report}");
    for share in ["arrival_detected_share", "announced_in_window_share"] {
        let v = report[share].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&v), "{share}: {report}");
    }
    for key in [
        "false_off_route_per_km",
        "reroutes_per_trip",
        "wrong_turn_detect_fixes_p90",
        "max_session_bytes",
    ] {
        assert!(report.get(key).is_some(), "{key}: {report}");
    }
    // Reproducible: same seed, same figures.
    assert_eq!(
        stdout,
        gangway_ok(&["eval", "guidance", "--trips", "12", "--seed", "3", "--json"])
    );
}
