//! A real Home Assistant (core 2024.1 with its MQTT integration) against a
//! real mosquitto, fed by `gangway run --replay fixtures/walk-waldo.jsonl`.
//! Checked through Home Assistant's own APIs, as a user's automations would
//! see it: every discovery config becomes an entity; a tracker per replayed
//! device whose state (the place, `home` or `not_home`) and attributes follow
//! the gateway's location messages; occupancy sensors that add up to the
//! trackers at named places; a route request sent with Home Assistant's
//! `mqtt.publish` service is answered; and Home Assistant logs no error or
//! warning about any of it.
//!
//! Home Assistant comes from the virtualenv `.ci/run` makes (`.venv-hass`, or
//! `GANGWAY_HASS` naming its `hass`). It runs with `--skip-pip`: `.ci/run`
//! installs the MQTT integration's requirements, so nothing is fetched at test
//! time. Without it the test fails in CI and is skipped elsewhere.

use std::collections::{BTreeMap, BTreeSet};
use std::net::TcpStream;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::mqtt_support::*;
use futures::{SinkExt, StreamExt};
use serde_json::{Value, json};
use tokio::sync::mpsc;
use tokio_tungstenite::tungstenite::Message as WsMessage;

const GATEWAY: &str = "gw-hass";
const PREFIX: &str = "gangway/gw-hass";
/// The Home Assistant line the test pins (the last on Python 3.11).
const HASS_VERSION: &str = "2024.1.";
/// Home Assistant's start, login, and catching up with the gateway.
const HASS_WAIT: Duration = Duration::from_secs(120);
/// The two-minute walk played in real time, with room to spare.
const REPLAY_WAIT: Duration = Duration::from_secs(240);

/// The `hass` executable, if installed.
fn hass_binary() -> Option<PathBuf> {
    let path = std::env::var_os("GANGWAY_HASS")
        .map(PathBuf::from)
        .unwrap_or_else(|| repo().join(".venv-hass/bin/hass"));
    if path.exists() {
        return Some(path);
    }
    crate::common::cannot_run(&format!(
        "no Home Assistant at {} (.ci/run installs it, or set GANGWAY_HASS)",
        path.display()
    ));
    None
}

/// Runs a blocking HTTP call without stalling the runtime's other tasks.
fn blocking<T>(f: impl FnOnce() -> T) -> T {
    tokio::task::block_in_place(f)
}

/// A Home Assistant of the test's own: configuration in a temporary
/// directory, HTTP on a free loopback port, the MQTT integration's config
/// entry written before start (what the UI's config flow would store), and a
/// user whose access token the test gets through the login flow.
struct HomeAssistant {
    child: Child,
    dir: tempfile::TempDir,
    base: String,
    token: String,
}

impl HomeAssistant {
    fn start(hass: &Path, broker: &Broker) -> HomeAssistant {
        let version = Command::new(hass).arg("--version").output().unwrap();
        let version = String::from_utf8_lossy(&version.stdout);
        assert!(
            version.trim().starts_with(HASS_VERSION),
            "Home Assistant {version} is not the pinned {HASS_VERSION}x"
        );
        let dir = tempfile::tempdir().unwrap();
        let port = free_port();
        // Only what the test uses: no default_config, cloud, frontend or
        // recorder. `auth` serves the login flow, `api` the REST API.
        std::fs::write(
            dir.path().join("configuration.yaml"),
            format!(
                "homeassistant:\n  name: gangway test\n  latitude: 0\n  longitude: 0\n  \
                 elevation: 0\n  unit_system: metric\n  time_zone: UTC\n  country: DE\n  \
                 currency: EUR\nhttp:\n  server_host: 127.0.0.1\n  server_port: {port}\n\
                 auth:\napi:\nwebsocket_api:\n"
            ),
        )
        .unwrap();
        let storage = dir.path().join(".storage");
        std::fs::create_dir(&storage).unwrap();
        let entry = json!({
            "version": 1, "minor_version": 1, "key": "core.config_entries",
            "data": {"entries": [{
                "entry_id": "0123456789abcdef0123456789abcdef",
                "version": 1, "minor_version": 1, "domain": "mqtt", "title": "mosquitto",
                "data": {"broker": "127.0.0.1", "port": broker.port,
                         "discovery": true, "discovery_prefix": "homeassistant"},
                "options": {}, "pref_disable_new_entities": false,
                "pref_disable_polling": false, "source": "user",
                "unique_id": null, "disabled_by": null,
            }]},
        });
        std::fs::write(storage.join("core.config_entries"), entry.to_string()).unwrap();
        let password = "gangway-test-password";
        let auth = Command::new(hass)
            .args(["--script", "auth", "-c"])
            .arg(dir.path())
            .args(["add", "gangway", password])
            .output()
            .unwrap();
        assert!(
            auth.status.success(),
            "hass --script auth: {}",
            String::from_utf8_lossy(&auth.stderr)
        );
        let log = dir.path().join("home-assistant.log");
        let child = Command::new(hass)
            .arg("-c")
            .arg(dir.path())
            .arg("--skip-pip")
            .arg("--log-file")
            .arg(&log)
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .spawn()
            .expect("start Home Assistant");
        let base = format!("http://127.0.0.1:{port}");
        let mut ha = HomeAssistant {
            child,
            dir,
            base,
            token: String::new(),
        };
        let deadline = Instant::now() + HASS_WAIT;
        while TcpStream::connect(("127.0.0.1", port)).is_err() {
            assert!(
                ha.child.try_wait().unwrap().is_none(),
                "Home Assistant exited at start:\n{}",
                ha.log()
            );
            assert!(
                Instant::now() < deadline,
                "Home Assistant did not start:\n{}",
                ha.log()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        ha.token = ha.login("gangway", password);
        ha
    }

    /// The login flow a browser goes through: credentials for a code, the
    /// code for an access token.
    fn login(&self, user: &str, password: &str) -> String {
        let client_id = format!("{}/", self.base);
        let flow: Value = ureq::post(format!("{}/auth/login_flow", self.base))
            .send_json(
                json!({"client_id": client_id, "handler": ["homeassistant", null],
                              "redirect_uri": client_id}),
            )
            .unwrap()
            .body_mut()
            .read_json()
            .unwrap();
        let flow_id = flow["flow_id"].as_str().expect("a login flow id");
        let done: Value = ureq::post(format!("{}/auth/login_flow/{flow_id}", self.base))
            .send_json(json!({"client_id": client_id, "username": user, "password": password}))
            .unwrap()
            .body_mut()
            .read_json()
            .unwrap();
        let code = done["result"]
            .as_str()
            .unwrap_or_else(|| panic!("login: {done}"));
        let token: Value = ureq::post(format!("{}/auth/token", self.base))
            .send_form([
                ("grant_type", "authorization_code"),
                ("code", code),
                ("client_id", client_id.as_str()),
            ])
            .unwrap()
            .body_mut()
            .read_json()
            .unwrap();
        token["access_token"]
            .as_str()
            .expect("an access token")
            .to_owned()
    }

    fn get(&self, path: &str) -> Value {
        ureq::get(format!("{}{path}", self.base))
            .header("Authorization", format!("Bearer {}", self.token))
            .call()
            .unwrap_or_else(|e| panic!("GET {path}: {e}"))
            .body_mut()
            .read_json()
            .unwrap()
    }

    fn post(&self, path: &str, body: Value) -> Value {
        ureq::post(format!("{}{path}", self.base))
            .header("Authorization", format!("Bearer {}", self.token))
            .send_json(body)
            .unwrap_or_else(|e| panic!("POST {path}: {e}"))
            .body_mut()
            .read_json()
            .unwrap()
    }

    /// Every entity's state, by entity id.
    fn states(&self) -> BTreeMap<String, Value> {
        let states = self.get("/api/states");
        states
            .as_array()
            .expect("a list of states")
            .iter()
            .map(|s| (s["entity_id"].as_str().unwrap().to_owned(), s.clone()))
            .collect()
    }

    fn log(&self) -> String {
        std::fs::read_to_string(self.dir.path().join("home-assistant.log")).unwrap_or_default()
    }

    /// Every `state_changed` event from now on, as `(entity_id, new_state)`,
    /// through the websocket API.
    async fn state_changes(&self) -> mpsc::UnboundedReceiver<(String, Value)> {
        let url = format!("{}/api/websocket", self.base.replacen("http", "ws", 1));
        let (mut ws, _) = tokio_tungstenite::connect_async(url).await.unwrap();
        let Some(Ok(WsMessage::Text(hello))) = ws.next().await else {
            panic!("no greeting on the websocket")
        };
        let hello: Value = serde_json::from_str(&hello).unwrap();
        assert_eq!(hello["type"], "auth_required");
        let send = |v: Value| WsMessage::Text(v.to_string().into());
        ws.send(send(json!({"type": "auth", "access_token": self.token})))
            .await
            .unwrap();
        ws.send(send(
            json!({"id": 1, "type": "subscribe_events", "event_type": "state_changed"}),
        ))
        .await
        .unwrap();
        let (tx, rx) = mpsc::unbounded_channel();
        tokio::spawn(async move {
            while let Some(Ok(message)) = ws.next().await {
                let WsMessage::Text(text) = message else {
                    continue;
                };
                let v: Value = serde_json::from_str(&text).unwrap();
                match v["type"].as_str() {
                    Some("auth_ok") => {}
                    Some("result") => assert_eq!(v["success"], true, "subscribe: {v}"),
                    Some("event") => {
                        let data = &v["event"]["data"];
                        let entity = data["entity_id"].as_str().unwrap_or_default().to_owned();
                        if tx.send((entity, data["new_state"].clone())).is_err() {
                            return;
                        }
                    }
                    _ => panic!("unexpected websocket message: {v}"),
                }
            }
        });
        rx
    }
}

impl Drop for HomeAssistant {
    fn drop(&mut self) {
        signal(&self.child, "TERM");
        let deadline = Instant::now() + Duration::from_secs(20);
        while self.child.try_wait().unwrap().is_none() && Instant::now() < deadline {
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Home Assistant's entity id for one of our devices: its object id rules.
fn tracker_entity(device: &str) -> String {
    let slug: String = device
        .to_lowercase()
        .chars()
        .map(|c| if c.is_ascii_alphanumeric() { c } else { '_' })
        .collect();
    format!("device_tracker.{slug}")
}

/// The tracker state a location message should give.
fn expected_state(location: &Value) -> Value {
    if location["cell"].is_null() {
        json!("not_home")
    } else {
        location["place"]
            .as_str()
            .map_or(json!("home"), |p| json!(p))
    }
}

/// The log records (a line with a level and its continuation lines) at
/// WARNING or above.
fn warnings(log: &str) -> Vec<String> {
    let mut records: Vec<String> = Vec::new();
    for line in log.lines() {
        let starts_record =
            line.len() > 24 && line.as_bytes()[4] == b'-' && line.as_bytes()[10] == b' ';
        match records.last_mut() {
            Some(last) if !starts_record => {
                last.push('\n');
                last.push_str(line);
            }
            _ => records.push(line.to_owned()),
        }
    }
    records
        .into_iter()
        .filter(|r| {
            [" WARNING ", " ERROR ", " CRITICAL "]
                .iter()
                .any(|l| r.contains(l))
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn home_assistant_tracks_counts_and_routes_what_the_gateway_publishes() {
    let Some(hass) = hass_binary() else { return };
    let broker = Broker::start();
    let ha = blocking(|| HomeAssistant::start(&hass, &broker));
    let mut changes = ha.state_changes().await;
    let mut client = Client::connect(
        &broker,
        "test-hass",
        &[&format!("{PREFIX}/#"), "homeassistant/#"],
    )
    .await;
    client.ready(&format!("{PREFIX}/probe")).await;

    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config(GATEWAY, &site, &broker, "");
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let _gateway = Gateway::start(
        &config.path,
        // Real time, as a gateway runs: Home Assistant misses what comes
        // before it has subscribed to a newly discovered tracker (about a
        // second), which faster playback would inflate.
        &["--replay", fixture.to_str().unwrap(), "--speed", "1"],
    );

    // The replay is over when the stats count every location seen and none
    // has come for a while (the daemon keeps serving after it).
    let is_location = |m: &Received| {
        m.topic.starts_with(&format!("{PREFIX}/devices/")) && m.topic.ends_with("/location")
    };
    client.wait_for("a first location", is_location).await;
    let deadline = Instant::now() + REPLAY_WAIT;
    let mut quiet_since = Instant::now();
    let mut seen = 0;
    loop {
        tokio::time::sleep(Duration::from_millis(500)).await;
        client.drain();
        let locations = client.seen.iter().filter(|m| is_location(m)).count();
        if locations != seen {
            seen = locations;
            quiet_since = Instant::now();
        }
        let fixes = client
            .seen
            .iter()
            .rev()
            .find(|m| m.topic == format!("{PREFIX}/stats"))
            .map(|m| m.json()["fixes"].as_u64().unwrap_or(0));
        if fixes == Some(seen as u64) && quiet_since.elapsed() > Duration::from_secs(4) {
            break;
        }
        assert!(Instant::now() < deadline, "the replay did not finish");
    }
    let locations: Vec<Value> = client
        .seen
        .iter()
        .filter(|m| is_location(m))
        .map(Received::json)
        .collect();
    let devices: BTreeSet<&str> = locations
        .iter()
        .map(|l| l["device"].as_str().unwrap())
        .collect();
    assert_eq!(
        devices.len(),
        3,
        "walk-waldo has three walkers: {devices:?}"
    );
    assert!(locations.len() > 150, "only {} locations", locations.len());
    // Gateway side: every location carries `place` (null at no named place).
    assert!(locations.iter().all(|l| l.get("place").is_some()));
    assert!(locations.iter().any(|l| l["place"].is_null()));
    assert!(locations.iter().any(|l| l["place"].is_string()));

    // Every state change Home Assistant made, until it has caught up with
    // each device's last location.
    let mut events: Vec<(String, Value)> = Vec::new();
    let last_t: BTreeMap<String, f64> = locations
        .iter()
        .map(|l| {
            (
                tracker_entity(l["device"].as_str().unwrap()),
                l["t"].as_f64().unwrap(),
            )
        })
        .collect();
    let deadline = tokio::time::Instant::now() + HASS_WAIT;
    while !last_t.iter().all(|(entity, t)| {
        events
            .iter()
            .any(|(e, s)| e == entity && s["attributes"]["t"].as_f64() == Some(*t))
    }) {
        match tokio::time::timeout_at(deadline, changes.recv()).await {
            Ok(Some(change)) => events.push(change),
            _ => panic!(
                "Home Assistant did not catch up with the last locations; log:\n{}",
                ha.log()
            ),
        }
    }

    // And what followed them (the last occupancy counts).
    tokio::time::sleep(Duration::from_secs(2)).await;
    while let Ok(change) = changes.try_recv() {
        events.push(change);
    }

    // State and attributes of each location of a device with a tracker
    // (from its third location with a cell on: `[mqtt] ha_min_fixes`,
    // default 3): the
    // first change that carries its attributes (its presence came just
    // before, so the state is set).
    let mut located: BTreeMap<&str, usize> = BTreeMap::new();
    let tracked: Vec<&Value> = locations
        .iter()
        .filter(|l| {
            let count = located.entry(l["device"].as_str().unwrap()).or_default();
            *count += usize::from(!l["cell"].is_null());
            *count >= 3
        })
        .collect();
    let (mut state_ok, mut attributes_ok) = (0, 0);
    let mut wrong = Vec::new();
    for l in &tracked {
        let entity = tracker_entity(l["device"].as_str().unwrap());
        let Some((_, s)) = events
            .iter()
            .find(|(e, s)| *e == entity && s["attributes"]["t"] == l["t"])
        else {
            wrong.push(format!("no change for {l}"));
            continue;
        };
        if s["state"] == expected_state(l) {
            state_ok += 1;
        } else {
            wrong.push(format!("state {} for {l}", s["state"]));
        }
        let a = &s["attributes"];
        if a["x"] == l["x_m"]
            && a["y"] == l["y_m"]
            && a["place"] == l["place"]
            && a["cell"] == l["cell"]
        {
            attributes_ok += 1;
        } else {
            wrong.push(format!("attributes {a} for {l}"));
        }
    }
    let n = tracked.len() as f64;
    println!(
        "{} locations: state right for {:.1}%, attributes right for {:.1}%",
        tracked.len(),
        100.0 * state_ok as f64 / n,
        100.0 * attributes_ok as f64 / n
    );
    assert!(
        state_ok as f64 >= 0.95 * n && attributes_ok as f64 >= 0.95 * n,
        "state right {state_ok}/{n}, attributes right {attributes_ok}/{n}; first wrong: {:#?}",
        &wrong[..wrong.len().min(5)]
    );

    // Every discovery config became an entity: a tracker per device, the
    // gateway's status, its stats sensors and one occupancy sensor per place.
    let configs: BTreeSet<String> = client
        .seen
        .iter()
        .filter(|m| m.topic.starts_with("homeassistant/") && m.topic.ends_with("/config"))
        .map(|m| m.topic.clone())
        .collect();
    let places = gangway::site::Site::load(&site).unwrap().places().len();
    let states = blocking(|| ha.states());
    let ours: Vec<&String> = states
        .keys()
        .filter(|e| e.contains("gangway_gw_hass") || e.starts_with("device_tracker."))
        .collect();
    assert_eq!(
        ours.len(),
        configs.len(),
        "entities {ours:#?} for configs {configs:#?}"
    );
    for device in &devices {
        let entity = tracker_entity(device);
        let tracker = &states[&entity];
        assert_eq!(tracker["attributes"]["friendly_name"], *device);
        assert_eq!(tracker["attributes"]["source_type"], "bluetooth_le");
    }
    assert_eq!(
        states["binary_sensor.gangway_gw_hass_status"]["state"],
        "on"
    );
    assert_ne!(states["sensor.gangway_gw_hass_fixes"]["state"], "unknown");

    // Occupancy: each place's sensor counts the trackers at that place, and
    // the sensors add up to the trackers at named places.
    let occupancy: BTreeMap<&str, u64> = states
        .iter()
        .filter(|(e, _)| e.ends_with("_occupancy"))
        .map(|(_, s)| {
            let name = s["attributes"]["friendly_name"].as_str().unwrap();
            let place = name
                .trim_start_matches("gangway gw-hass ")
                .trim_end_matches(" occupancy");
            (place, s["state"].as_str().unwrap().parse::<u64>().unwrap())
        })
        .collect();
    assert_eq!(occupancy.len(), places, "{occupancy:?}");
    let at_places: Vec<&str> = devices
        .iter()
        .map(|d| states[&tracker_entity(d)]["state"].as_str().unwrap())
        .filter(|s| !["home", "not_home"].contains(s))
        .collect();
    for (place, count) in &occupancy {
        let trackers = at_places.iter().filter(|p| *p == place).count() as u64;
        assert_eq!(
            *count, trackers,
            "{place}: sensor {count}, trackers {at_places:?}"
        );
    }
    assert_eq!(occupancy.values().sum::<u64>(), at_places.len() as u64);
    println!("trackers at the end: {at_places:?} at places; occupancy {occupancy:?}");
    // Along the way, each sensor went through the gateway's counts for its
    // place (from the latest retained one when Home Assistant subscribed).
    let published: Vec<Value> = client
        .seen
        .iter()
        .filter(|m| m.topic == format!("{PREFIX}/occupancy"))
        .map(Received::json)
        .collect();
    let mut moved = 0;
    for (entity, s) in states.iter().filter(|(e, _)| e.ends_with("_occupancy")) {
        let place = s["attributes"]["friendly_name"]
            .as_str()
            .unwrap()
            .trim_start_matches("gangway gw-hass ")
            .trim_end_matches(" occupancy");
        let mut sent: Vec<String> = published
            .iter()
            .map(|o| o["places"][place].to_string())
            .collect();
        sent.dedup();
        let shown: Vec<String> = events
            .iter()
            .filter(|(e, _)| e == entity)
            .map(|(_, s)| s["state"].as_str().unwrap().to_owned())
            .filter(|state| !["unknown", "unavailable"].contains(&state.as_str()))
            .collect();
        assert!(
            sent.ends_with(&shown),
            "{place}: the gateway sent {sent:?}, Home Assistant showed {shown:?}"
        );
        moved += shown.iter().filter(|n| *n != "0").count();
    }
    assert!(moved > 0, "no occupancy sensor ever counted a device");

    // A route request through Home Assistant's mqtt.publish service.
    let request = json!({"to": "help desk", "request_id": "via-hass"});
    blocking(|| {
        ha.post(
            "/api/services/mqtt/publish",
            json!({"topic": format!("{PREFIX}/devices/walker-01/route/set"),
                   "payload": request.to_string()}),
        )
    });
    let reply = client.reply(PREFIX, "walker-01", "via-hass").await;
    assert!(reply.get("error").is_none(), "{reply}");
    assert!(!reply["waypoints"].as_array().unwrap().is_empty());

    // Any warning is printed; one about gangway's entities or topics fails.
    let warnings = warnings(&ha.log());
    for w in &warnings {
        println!("Home Assistant: {}", w.lines().next().unwrap_or_default());
    }
    let problems: Vec<&str> = warnings
        .iter()
        .map(String::as_str)
        .filter(|r| {
            ["gangway", "walker", "gw-hass", "gw_hass"]
                .iter()
                .any(|w| r.contains(w))
        })
        .collect();
    assert!(
        problems.is_empty(),
        "Home Assistant logged {} errors or warnings about gangway:\n{}",
        problems.len(),
        problems.join("\n")
    );
    assert_all_valid(&client.seen);
}
