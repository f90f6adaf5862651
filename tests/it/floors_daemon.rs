//! The gateway serving a building of several floors (the made-up one of
//! [`floors_support`]): a phone walks on B1 to the lift, rides it to L1 and
//! walks on. Its published locations carry its floor, which changes once,
//! from B1 to L1, through the lift; a wheelchair user's route to L1 asked
//! for on B1 has a leg per floor joined by the lift, never the stairs;
//! guidance announces the lift at the end of the first leg and follows the
//! walker onto L1 with the rest of the way.
//!
//! The phone's readings come from a plain path-loss law with a loss per
//! floor between beacon and phone, not from the gateway's own model.

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::common::{gangway, gangway_ok, write};
use crate::floors_support::{self, BEACONS, FLOORS, UUID};
use crate::mqtt_support::*;

/// Where the walk starts on B1, the lift's stop (every floor) and where it
/// ends on L1, metres.
const START: [f64; 2] = [9.0, 2.0];
const LIFT: [f64; 2] = [17.0, 6.25];
const END: [f64; 2] = [11.0, 2.5];
/// When the phone reaches the lift, enters it (after waiting for it) and
/// leaves it on L1, seconds from the start: heard by nobody in the car (it
/// shields the phone).
const AT_LIFT_S: f64 = 10.0;
const BOARD_S: f64 = 24.0;
const LEAVE_S: f64 = 40.0;
const END_S: f64 = 60.0;
const T0: f64 = 1_767_225_600.0;

/// Where the phone is at `s` seconds: its floor's index and position.
fn walker(s: f64) -> Option<(usize, [f64; 2])> {
    let between = |a: [f64; 2], b: [f64; 2], f: f64| {
        let f = f.clamp(0.0, 1.0);
        [a[0] + (b[0] - a[0]) * f, a[1] + (b[1] - a[1]) * f]
    };
    if s <= BOARD_S {
        Some((0, between(START, LIFT, s / AT_LIFT_S)))
    } else if s < LEAVE_S {
        None
    } else {
        Some((2, between(LIFT, END, (s - LEAVE_S) / 12.0)))
    }
}

/// RSSI of beacon `b` heard at `at` on floor `floor`: −59 dBm at 1 m,
/// exponent 2.5, 18 dB per floor between, a small deterministic ripple;
/// `None` under −95 dBm.
fn rssi(b: usize, floor: usize, at: [f64; 2], k: u32) -> Option<i16> {
    let (_, beacon_floor, pos, _) = BEACONS[b];
    let beacon_floor = FLOORS.iter().position(|f| f.name == beacon_floor).unwrap();
    let d = ((pos[0] - at[0]).powi(2) + (pos[1] - at[1]).powi(2))
        .sqrt()
        .max(0.5);
    let floors = beacon_floor.abs_diff(floor) as f64;
    let ripple = f64::from((k * 7 + b as u32 * 3) % 5) - 2.0;
    let dbm = -59.0 - 25.0 * d.log10() - 18.0 * floors + ripple;
    (dbm >= -95.0).then_some(dbm.round() as i16)
}

/// The walk as a JSON Lines capture (an advert per beacon heard per
/// second), and `extra` lines after the advert of second `at`.
pub(crate) fn capture(dir: &Path, extra: &[(f64, Value)]) -> PathBuf {
    let mut lines = Vec::new();
    for k in 0..=END_S as u32 {
        let s = f64::from(k);
        if let Some((floor, at)) = walker(s) {
            for (b, beacon) in BEACONS.iter().enumerate() {
                if let Some(rssi) = rssi(b, floor, at, k) {
                    lines.push(serde_json::json!({
                        "type": "advert", "t": T0 + s, "observer": "phone",
                        "uuid": UUID, "major": 7, "minor": beacon.3, "rssi": rssi,
                    }));
                }
            }
        }
        for (at, line) in extra.iter().filter(|(at, _)| *at == s) {
            let mut line = line.clone();
            line["t"] = (T0 + at).into();
            lines.push(line);
        }
    }
    let text: Vec<String> = lines.iter().map(Value::to_string).collect();
    write(dir, "walk.jsonl", &(text.join("\n") + "\n"))
}

fn request_to_l1(request_id: &str) -> Value {
    serde_json::json!({
        "to": floors_support::cell_of(END),
        "floor": "L1",
        "profile": "wheelchair",
        "request_id": request_id,
    })
}

/// The made-up building in `dir` and a config replaying on it. Five
/// beacons over three floors of 0.5 m cells: a fix is rarely within one
/// cell, so every fix is published (and guided).
fn replay_config(dir: &Path) -> PathBuf {
    floors_support::write_building(dir);
    write(
        dir,
        "gangway.toml",
        "gateway_id = \"gw\"\nsite = \"building.toml\"\n[localizer]\nmin_confidence = 0.0\n",
    )
}

#[test]
fn a_walk_from_b1_to_l1_by_lift_is_located_routed_and_guided_floor_by_floor() {
    let dir = tempfile::tempdir().unwrap();
    let config = replay_config(dir.path());
    let mut request = request_to_l1("r1");
    request["type"] = "request".into();
    request["device"] = "phone".into();
    let walk = capture(dir.path(), &[(4.0, request)]);
    let printed = gangway_ok(&[
        "replay",
        walk.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--print",
    ]);
    let messages: Vec<(String, Value)> = printed
        .lines()
        .map(|l| {
            let v: Value = serde_json::from_str(l).unwrap();
            (
                v["topic"].as_str().unwrap().to_owned(),
                v["payload"].clone(),
            )
        })
        .collect();
    let of = |suffix: &str| -> Vec<&Value> {
        messages
            .iter()
            .filter(|(topic, _)| topic.ends_with(suffix))
            .map(|(_, p)| p)
            .collect()
    };

    // Every location names its floor (or none), and the floor changes once,
    // B1 to L1, no sooner than the lift can carry the phone there.
    let locations = of("/devices/phone/location");
    let floors: Vec<(f64, Option<&str>)> = locations
        .iter()
        .map(|l| (l["t"].as_f64().unwrap() - T0, l["floor"]["name"].as_str()))
        .collect();
    let named: Vec<(f64, &str)> = floors.iter().filter_map(|&(t, f)| Some((t, f?))).collect();
    assert!(named.len() >= 10, "{floors:?}");
    assert_eq!(named.first().unwrap().1, "B1", "{floors:?}");
    assert_eq!(named.last().unwrap().1, "L1", "{floors:?}");
    let changes: Vec<_> = named.windows(2).filter(|w| w[0].1 != w[1].1).collect();
    assert_eq!(changes.len(), 1, "{floors:?}");
    // Two levels of the lift move in 10 s at least.
    assert!(changes[0][1].0 >= BOARD_S + 10.0, "{floors:?}");
    for l in &locations {
        check_schema("location", l).unwrap();
        if l["floor"].is_null() {
            assert!(l["cell"].is_null(), "a cell on an unknown floor: {l}");
        }
    }

    // The route: a leg on B1 to the lift, the lift, a leg on L1.
    let paths = of("/devices/phone/path");
    let route = paths
        .iter()
        .find(|p| p["request_id"] == "r1" && p.get("reason").is_none())
        .expect("the reply to r1");
    check_schema("path", route).unwrap();
    let legs: Vec<&str> = route["legs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|l| l["floor"].as_str().unwrap())
        .collect();
    assert_eq!(legs, ["B1", "L1"], "{route}");
    assert_eq!(route["connectors"][0]["kind"], "lift", "{route}");
    let said: Vec<&str> = route["instructions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|i| i["text"].as_str().unwrap())
        .collect();
    assert!(said.contains(&"Take the lift to L1."), "{said:?}");

    // Guidance: the lift announced on B1, then the rest of the way planned
    // from where the phone came onto L1, and guided there.
    let guidance = of("/devices/phone/guidance");
    let connector = guidance
        .iter()
        .position(|g| g["event"] == "connector")
        .unwrap_or_else(|| panic!("no connector announced: {guidance:?}"));
    assert_eq!(
        guidance[connector]["text"], "Take the lift to L1.",
        "{}",
        guidance[connector]
    );
    let next = paths
        .iter()
        .find(|p| p["reason"] == "next_floor")
        .unwrap_or_else(|| panic!("no route on from L1: {paths:?}"));
    check_schema("path", next).unwrap();
    assert_eq!(next["legs"].as_array().unwrap().len(), 1, "{next}");
    assert_eq!(next["legs"][0]["floor"], "L1", "{next}");
    assert_eq!(next["request_id"], "r1");
    assert!(
        guidance[connector..].iter().any(|g| g["text"]
            .as_str()
            .is_some_and(|t| t.starts_with("Leave the lift on L1."))),
        "{guidance:?}"
    );
    for g in &guidance {
        check_schema("guidance", g).unwrap();
    }
}

/// The same walk served by `gangway run` from a real mosquitto: the phone
/// is counted on its floor, and the route request arrives over MQTT, names
/// the floor, and is refused for a floor the building does not have.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn route_requests_across_floors_arrive_over_mqtt() {
    let dir = tempfile::tempdir().unwrap();
    let building = floors_support::write_building(dir.path());
    let walk = capture(dir.path(), &[]);
    let broker = Broker::start();
    let config = gateway_config("gw-floors", &building, &broker, "");
    let prefix = "gangway/gw-floors";
    let mut client = Client::connect(&broker, "test-floors", &[&format!("{prefix}/#")]).await;
    let mut gateway = Gateway::start(&config.path, &["--replay", walk.to_str().unwrap()]);
    let location = format!("{prefix}/devices/phone/location");
    let first = client
        .wait_for("a location of the phone", |m| m.topic == location)
        .await
        .json();
    assert_eq!(first["floor"]["name"], "B1", "{first}");
    // Occupancy counts the phone on its floor.
    let occupancy = format!("{prefix}/occupancy");
    let counts = client
        .wait_for("the phone counted on B1", |m| {
            m.topic == occupancy && m.json()["floors"]["B1"] == 1
        })
        .await
        .json();
    check_schema("occupancy", &counts).unwrap();
    assert_eq!(counts["floors"]["L1"], 0, "{counts}");

    let set = format!("{prefix}/devices/phone/route/set");
    client.publish(&set, request_to_l1("m1").to_string()).await;
    let reply = client.reply(prefix, "phone", "m1").await;
    check_schema("path", &reply).unwrap();
    assert_eq!(reply["legs"][1]["floor"], "L1", "{reply}");
    assert_eq!(reply["connectors"][0]["kind"], "lift", "{reply}");

    let mut wrong = request_to_l1("m2");
    wrong["floor"] = "L9".into();
    client.publish(&set, wrong.to_string()).await;
    let reply = client.reply(prefix, "phone", "m2").await;
    assert_eq!(reply["error"]["code"], "unknown_place", "{reply}");
    let message = reply["error"]["message"].as_str().unwrap();
    assert!(message.contains("`B1`, `G`, `L1`"), "{message}");
    assert!(gateway.terminate().success());
}

/// `replay --score` on a building: each truth names its floor, and the
/// score says on what share of the fixes the floor was right, counting
/// errors in cells on the right floor only.
#[test]
fn a_replay_of_a_building_is_scored_floor_by_floor() {
    let dir = tempfile::tempdir().unwrap();
    let config = replay_config(dir.path());
    let truths: Vec<(f64, Value)> = (0..=END_S as u32)
        .filter_map(|k| {
            let s = f64::from(k);
            let (floor, at) = walker(s)?;
            let truth = serde_json::json!({
                "type": "truth", "device": "phone",
                "cell": floors_support::cell_of(at), "floor": FLOORS[floor].name,
            });
            Some((s, truth))
        })
        .collect();
    let walk = capture(dir.path(), &truths);
    let printed = gangway_ok(&[
        "replay",
        walk.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--score",
        "--json",
    ]);
    let score: Value = serde_json::from_str(printed.lines().last().unwrap()).unwrap();
    assert_eq!(score["truths"], truths.len(), "{score}");
    assert!(score["matched"].as_u64().unwrap() >= 20, "{score}");
    // The phone's floor is right but for the lift's move being believed a
    // little late; errors are counted on the right floor, in its cells.
    let floor_accuracy = score["floor_accuracy"].as_f64().unwrap();
    assert!((0.8..=1.0).contains(&floor_accuracy), "{score}");
    let (cells, metres) = (
        score["mean_error_cells"].as_f64().unwrap(),
        score["mean_error_m"].as_f64().unwrap(),
    );
    assert!(
        (metres - cells * floors_support::CELL_M).abs() < 1e-9,
        "{score}"
    );

    // A truth naming a floor longer than a floor's name may be is refused
    // with the line it is on.
    let mut bad = truths[0].1.clone();
    bad["floor"] = "F".repeat(65).into();
    let walk = capture(dir.path(), &[(0.0, bad)]);
    let out = gangway(&[
        "replay",
        walk.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--score",
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        stderr.contains("`floor` must be a floor's name"),
        "{stderr}"
    );
}

/// A CSV scan log of one floor (survey mode's layout, `x_m,y_m,t` and the
/// floor's beacons) replays on the building it was taken in: its columns
/// name G's beacons, so its truths are on G and so are the fixes. A log
/// naming beacons of two floors is refused, saying which floor each is on.
#[test]
fn a_floor_s_scan_log_replays_on_that_floor() {
    let dir = tempfile::tempdir().unwrap();
    let config = replay_config(dir.path());
    // Standing at four spots along the south of G, 8 s each.
    let (g_west, atrium) = (2, 3);
    let mut csv = String::from("x_m,y_m,t,g-west,atrium\n");
    for k in 0..32u32 {
        let at = [4.0 + f64::from(k / 8) * 4.0, 2.0];
        let heard = |b| rssi(b, 1, at, k).unwrap_or(-200);
        csv += &format!(
            "{},{},{},{},{}\n",
            at[0],
            at[1],
            T0 + f64::from(k),
            heard(g_west),
            heard(atrium)
        );
    }
    let log = write(dir.path(), "survey-G.csv", &csv);
    let printed = gangway_ok(&[
        "replay",
        log.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--score",
        "--json",
    ]);
    let score: Value = serde_json::from_str(printed.lines().last().unwrap()).unwrap();
    assert_eq!(score["truths"], 32, "{score}");
    assert!(score["matched"].as_u64().unwrap() >= 10, "{score}");
    assert_eq!(score["floor_accuracy"], 1.0, "{score}");

    // Refused: one of B1's beacons among G's; as many of B1's as of L1's.
    for (name, columns, says) in [
        (
            "mostly-g.csv",
            "g-west,atrium,b1-west",
            "is a beacon of floor B1",
        ),
        (
            "halves.csv",
            "b1-west,l1-east",
            "b1-west on B1, l1-east on L1",
        ),
    ] {
        let values = vec!["-80"; columns.split(',').count()].join(",");
        let log = write(
            dir.path(),
            name,
            &format!("x_m,y_m,t,{columns}\n4,2,{T0},{values}\n"),
        );
        let out = gangway(&[
            "replay",
            log.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
        ]);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{stderr}");
        assert!(
            stderr.contains(name) && stderr.contains(says) && stderr.contains("split it by floor"),
            "{stderr}"
        );
    }
}

/// Five phones on each of `floors` (indices into [`FLOORS`]) walking to
/// and fro across its south for five minutes, as a JSON Lines capture.
fn walks_on(dir: &Path, floors: &[usize]) -> PathBuf {
    let mut lines = Vec::new();
    for k in 0..300u32 {
        for &floor in floors {
            for phone in 0..5u32 {
                // 9 to 17 m east and back at 0.8 m/s, each phone 1.6 m apart.
                let along = (f64::from(k) * 0.8 + f64::from(phone) * 1.6) % 16.0;
                let x = 9.0 + if along < 8.0 { along } else { 16.0 - along };
                let at = [x, 1.5 + f64::from(phone) * 0.5];
                let observer = format!("{}-phone-{phone}", FLOORS[floor].name);
                for (b, beacon) in BEACONS.iter().enumerate() {
                    if let Some(rssi) = rssi(b, floor, at, k + phone) {
                        lines.push(
                            serde_json::json!({
                                "type": "advert", "t": T0 + f64::from(k), "observer": observer,
                                "uuid": UUID, "major": 7, "minor": beacon.3, "rssi": rssi,
                            })
                            .to_string(),
                        );
                    }
                }
            }
        }
    }
    let names: Vec<&str> = floors.iter().map(|&f| FLOORS[f].name).collect();
    write(
        dir,
        &format!("walks-{}.jsonl", names.join("-")),
        &(lines.join("\n") + "\n"),
    )
}

/// `calibrate` on a building fits the floor the captures were taken on:
/// phones walking on each floor calibrate that floor's beacons with
/// `--floor`, each file naming its floor's beacons only, and a config
/// naming the files with `{floor}` loads them; an unknown floor is refused
/// with the building's floors.
#[test]
fn calibrate_fits_each_floor_of_a_building_from_its_captures() {
    let dir = tempfile::tempdir().unwrap();
    let config = replay_config(dir.path());
    let calibrate = |floor: usize| {
        let name = FLOORS[floor].name;
        let out = dir.path().join(format!("calibration-{name}.toml"));
        let printed = gangway_ok(&[
            "calibrate",
            "--config",
            config.to_str().unwrap(),
            "--floor",
            name,
            "--from",
            walks_on(dir.path(), &[floor]).to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--json",
        ]);
        let report: Value = serde_json::from_str(printed.trim()).unwrap();
        let anchors: Vec<String> = report["anchors"]
            .as_array()
            .unwrap()
            .iter()
            .map(|a| a["id"].as_str().unwrap().to_owned())
            .collect();
        (report, anchors, std::fs::read_to_string(out).unwrap())
    };
    let (b1, b1_anchors, b1_file) = calibrate(0);
    assert_eq!(b1_anchors, ["b1-west", "b1-east"], "{b1}");
    assert!(b1["windows"].as_u64().unwrap() >= 600, "{b1}");
    assert!(
        b1_file.contains("--floor B1") && !b1_file.contains("l1-east"),
        "{b1_file}"
    );
    assert_eq!(calibrate(1).1, ["g-west", "atrium"]);
    let (l1, l1_anchors, _) = calibrate(2);
    assert_eq!(l1_anchors, ["l1-east"], "{l1}");

    let served = write(
        dir.path(),
        "calibrated.toml",
        "gateway_id = \"gw\"\nsite = \"building.toml\"\n[localizer]\nmethod = \"pathloss\"\n\
         [localizer.pathloss]\ncalibration = \"calibration-{floor}.toml\"\n",
    );
    gangway_ok(&["check", "--config", served.to_str().unwrap()]);
    // What `check` read: a floor without its file is refused.
    std::fs::remove_file(dir.path().join("calibration-G.toml")).unwrap();
    let out = gangway(&["check", "--config", served.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(
        !out.status.success() && stderr.contains("calibration-G.toml"),
        "{stderr}"
    );

    let out = gangway(&[
        "calibrate",
        "--config",
        config.to_str().unwrap(),
        "--floor",
        "L9",
        "--from",
        dir.path().join("walks-B1.jsonl").to_str().unwrap(),
        "--out",
        dir.path().join("x.toml").to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("--floor L9") && stderr.contains("B1, G, L1"),
        "{stderr}"
    );
}

/// A gateway serving a building recalibrates each floor from what was
/// heard on it. Phones walking on B1 and on L1 (nobody on G) fill the
/// learning store with windows that name their floor; asked to (SIGUSR1),
/// the gateway fits B1 and L1 each from its own windows, writes
/// `calibration-B1.toml` and `calibration-L1.toml` with that floor's
/// beacons only, and serves them (swapped in like a reload); G, which
/// heard nothing, keeps serving what it served. The stats say so, floor by
/// floor. A restart serves both files.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_gateway_recalibrates_each_floor_from_what_was_heard_there() {
    use gangway::locate::calibration::Calibration;
    let dir = tempfile::tempdir().unwrap();
    let building = floors_support::write_building(dir.path());
    let walks = walks_on(dir.path(), &[0, 2]);
    let broker = Broker::start();
    let config = gateway_config(
        "gw-recal",
        &building,
        &broker,
        "[store]\nenabled = true\npath = \"learning.sqlite\"\n\
         [localizer.recalibration]\nenabled = true\nevery_h = 0\nmin_windows = 300\n",
    );
    let prefix = "gangway/gw-recal";
    let mut client = Client::connect(&broker, "test-recal", &[&format!("{prefix}/stats")]).await;
    let mut gateway = Gateway::start(
        &config.path,
        &["--replay", walks.to_str().unwrap(), "--speed", "0"],
    );
    let db = config.dir.path().join("learning.sqlite");
    let heard_on = |floor: &str| {
        gangway::store::Store::open_read_only(&db)
            .and_then(|store| store.heard(100_000, Some(floor)))
            .map_or(0, |rows| rows.len())
    };
    let started = std::time::Instant::now();
    while heard_on("B1") < 600 || heard_on("L1") < 600 {
        assert!(
            started.elapsed().as_secs() < 60,
            "windows heard on B1: {}, on L1: {}",
            heard_on("B1"),
            heard_on("L1")
        );
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    }
    assert_eq!(heard_on("G"), 0, "nobody walked on G");

    signal(&gateway.child, "USR1");
    let stats = client
        .wait_for("the recalibrated pipeline swapped in", |m| {
            m.json()["reloads"] == 1
        })
        .await
        .json();
    // The stats say what the run did on each floor.
    check_schema("stats", &stats).unwrap();
    let status = &stats["recalibration"];
    assert_eq!(status["runs"], 1, "{status}");
    assert_eq!(status["failures"], 0, "{status}");
    let floors: Vec<&str> = status["floors"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| f["floor"].as_str().unwrap())
        .collect();
    assert_eq!(floors, ["B1", "L1"], "{status}");
    assert_eq!(status["floors"][0]["anchors"], 2, "{status}");
    assert_eq!(status["floors"][1]["anchors"], 1, "{status}");
    assert_eq!(status["skipped"][0]["floor"], "G", "{status}");
    assert!(
        status["skipped"][0]["why"]
            .as_str()
            .unwrap()
            .contains("min_windows"),
        "{status}"
    );
    assert!(gateway.terminate().success());
    let out = config.dir.path();
    for (floor, beacons) in [
        ("B1", ["b1-west", "b1-east"].as_slice()),
        ("L1", &["l1-east"]),
    ] {
        let site = gangway::site::Site::load(&dir.path().join(format!("{floor}.toml"))).unwrap();
        let file = out.join(format!("calibration-{floor}.toml"));
        let calibration = Calibration::load(&file, &site).unwrap();
        let ids: Vec<&str> = calibration.anchors.iter().map(|a| a.id.as_str()).collect();
        assert_eq!(ids, beacons, "{}", file.display());
        assert!(
            calibration.windows >= 600,
            "{floor}: {}",
            calibration.windows
        );
    }
    assert!(!out.join("calibration-G.toml").exists());
    assert!(!out.join("calibration.toml").exists());

    // A restart serves each floor's file, and G what it was configured with.
    let restarted = gangway::daemon::state::load_at_start(&config.path).unwrap();
    let served: Vec<(&str, PathBuf)> = restarted
        .config
        .localizer
        .recalibrated
        .iter()
        .map(|(floor, path)| (floor.as_str(), path.clone()))
        .collect();
    assert_eq!(
        served,
        [
            ("B1", out.join("calibration-B1.toml")),
            ("L1", out.join("calibration-L1.toml"))
        ]
    );
    assert!(restarted.fallbacks.is_empty(), "{:?}", restarted.fallbacks);

    // `gangway check` says which floors serve what was heard, and a file
    // that no longer loads, with what serves instead.
    let checked = gangway_ok(&["check", "--config", config.path.to_str().unwrap()]);
    let recalibrated: Vec<&str> = checked
        .lines()
        .filter(|l| l.starts_with("localizer: recalibrated on this gateway"))
        .collect();
    assert_eq!(recalibrated.len(), 2, "{checked}");
    for (line, floor) in recalibrated.iter().zip(["B1", "L1"]) {
        assert!(
            line.ends_with(&format!("calibration-{floor}.toml")),
            "{line}"
        );
    }
    assert!(recalibrated[0].contains("(2 beacons"), "{checked}");
    std::fs::write(out.join("calibration-L1.toml"), "anchor = 3\n").unwrap();
    let checked = gangway_ok(&["check", "--config", config.path.to_str().unwrap()]);
    let l1 = checked
        .split("ok: floor")
        .find(|floor| floor.starts_with(" L1"))
        .unwrap_or_else(|| panic!("{checked}"));
    assert!(
        l1.contains("localizer: the recalibrated file does not load")
            && l1.contains("calibration-L1.toml"),
        "{checked}"
    );
}

/// The learning store of a gateway serving a building keeps each fix's
/// floor: the phone's walk is recorded as a walk on B1 and one on L1 (each
/// on its floor's grid), its route to L1 as a leg on each floor (and the
/// rest of the way from the lift), rated by the feedback on the route, and `train --from-store` learns a floor's
/// site from that floor's walks and legs only, asking which floor when the
/// store has several.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_learning_store_keeps_each_floor_s_walks_apart() {
    let dir = tempfile::tempdir().unwrap();
    let building = floors_support::write_building(dir.path());
    let mut request = request_to_l1("r1");
    request["type"] = "request".into();
    request["device"] = "phone".into();
    let walk = capture(dir.path(), &[(4.0, request)]);
    let broker = Broker::start();
    let config = gateway_config(
        "gw-store",
        &building,
        &broker,
        "[store]\nenabled = true\npath = \"learning.sqlite\"\n[localizer]\nmin_confidence = 0.0\n",
    );
    let prefix = "gangway/gw-store";
    let mut client = Client::connect(&broker, "test-store", &[&format!("{prefix}/#")]).await;
    let mut gateway = Gateway::start(
        &config.path,
        &["--replay", walk.to_str().unwrap(), "--speed", "0"],
    );
    let location = format!("{prefix}/devices/phone/location");
    client
        .wait_for("the phone's last location, on L1", |m| {
            m.topic == location
                && m.json()["floor"]["name"] == "L1"
                && m.json()["t"]
                    .as_f64()
                    .is_some_and(|t| t >= T0 + END_S - 2.0)
        })
        .await;
    let db = config.dir.path().join("learning.sqlite");
    client
        .publish(
            &format!("{prefix}/devices/phone/feedback"),
            r#"{"request_id": "r1", "score": 5}"#,
        )
        .await;
    let rated = || {
        let store = gangway::store::Store::open_read_only(&db).ok()?;
        let routes = store.routes().ok()?;
        routes
            .iter()
            .all(|r| r.score == Some(5.0))
            .then_some(routes)
    };
    let started = std::time::Instant::now();
    let routes = loop {
        match rated() {
            Some(routes) if !routes.is_empty() => break routes,
            _ if started.elapsed().as_secs() > 20 => panic!("the feedback was not recorded"),
            _ => tokio::time::sleep(std::time::Duration::from_millis(200)).await,
        }
    };
    assert!(gateway.terminate().success());
    let legs: Vec<(Option<&str>, Option<&str>)> = routes
        .iter()
        .map(|r| (r.floor.as_deref(), r.request_id.as_deref()))
        .collect();
    // The reply's two legs, then the rest of the way planned when the phone
    // came onto L1 (`next_floor`), all rated by the feedback on `r1`.
    assert_eq!(
        legs,
        [
            (Some("B1"), Some("r1")),
            (Some("L1"), Some("r1")),
            (Some("L1"), Some("r1"))
        ]
    );

    let walks = gangway::store::Store::open_read_only(&db)
        .unwrap()
        .trajectories(30.0)
        .unwrap();
    let floors: Vec<Option<&str>> = walks.iter().map(|w| w.floor.as_deref()).collect();
    assert_eq!(floors, [Some("B1"), Some("L1")], "{walks:?}");

    let train = |floor: Option<&str>| {
        let mut args = vec![
            "train".to_owned(),
            "--site".into(),
            dir.path().join("B1.toml").display().to_string(),
            "--from-store".into(),
            db.display().to_string(),
            "--out".into(),
            config.dir.path().join("models").display().to_string(),
            "--desire-only".into(),
            "--json".into(),
        ];
        if let Some(floor) = floor {
            args.extend(["--floor".into(), floor.into()]);
        }
        gangway(&args.iter().map(String::as_str).collect::<Vec<_>>())
    };
    let unsaid = train(None);
    let stderr = String::from_utf8_lossy(&unsaid.stderr);
    assert!(!unsaid.status.success());
    assert!(
        stderr.contains("walks on 2 floors (B1, L1)") && stderr.contains("--floor"),
        "{stderr}"
    );
    let unknown = train(Some("L9"));
    let stderr = String::from_utf8_lossy(&unknown.stderr);
    assert!(
        !unknown.status.success() && stderr.contains("no walks on floor `L9`"),
        "{stderr}"
    );
    // B1's walk and B1's leg of the route: too few walks for desire lines,
    // which say how many they were given (L1's walk and legs are not B1's).
    let b1 = train(Some("B1"));
    let stderr = String::from_utf8_lossy(&b1.stderr);
    assert!(stderr.contains("got 2 of 2"), "{stderr}");
}
