//! The learning store fills from a live run: each walker's trajectory, the
//! route given over MQTT and the feedback on it, readable by training.

use crate::mqtt_support::*;
use gangway::store::Store;

const PREFIX: &str = "gangway/gw-test";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_run_records_trajectories_routes_and_feedback() {
    let broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config(
        "gw-test",
        &site,
        &broker,
        // Every fix kept, however unsure: this is about what the store
        // records, and the uncalibrated survey-free model publishes some of
        // the fixture's fixes below `min_confidence` (as it should).
        "[store]\nenabled = true\npath = \"learning.sqlite\"\n[localizer]\nmin_confidence = 0.0\n",
    );
    let mut client = Client::connect(&broker, "test-store", &[&format!("{PREFIX}/#")]).await;
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let mut gateway = Gateway::start(
        &config.path,
        &["--replay", fixture.to_str().unwrap(), "--speed", "0"],
    );
    client
        .wait_for("a location", |m| {
            m.topic == format!("{PREFIX}/devices/walker-03/location")
        })
        .await;
    let reply = client.route(PREFIX, "walker-03", "help desk", "s1").await;
    let given = reply["waypoints"].as_array().unwrap().len();
    client
        .publish(
            &format!("{PREFIX}/devices/walker-03/feedback"),
            r#"{"request_id":"s1","score":5}"#,
        )
        .await;
    client
        .wait_for("stats with the feedback recorded", |m| {
            m.topic == format!("{PREFIX}/stats") && m.json()["feedback"] == 1
        })
        .await;
    // Let the replay reach the end of the fixture (two minutes from
    // 1767225600) before stopping, so every walk is recorded whole.
    for walker in ["walker-01", "walker-02", "walker-03"] {
        client
            .wait_for("a location near the end of the fixture", |m| {
                m.topic == format!("{PREFIX}/devices/{walker}/location")
                    && m.json()["t"]
                        .as_f64()
                        .is_some_and(|t| t > 1_767_225_600.0 + 110.0)
            })
            .await;
    }
    assert!(gateway.terminate().success());

    let store = Store::open_read_only(&config.dir.path().join("learning.sqlite")).unwrap();
    let walks = store.trajectories(30.0).unwrap();
    for walker in ["walker-01", "walker-02", "walker-03"] {
        let points: usize = walks
            .iter()
            .filter(|w| w.device == walker)
            .map(|w| w.points.len())
            .sum();
        assert!(points > 20, "{walker}: {points} fixes recorded");
    }
    let routes = store.routes().unwrap();
    // Guidance may re-route walker-03 under the same request id (the
    // fixture's walk does not follow the route), and a re-route is stamped
    // with the log's clock, which sorts before the request's wall clock: so
    // the route given is one of the rows with that id, not the first.
    let s1: Vec<_> = routes
        .iter()
        .filter(|r| r.request_id.as_deref() == Some("s1"))
        .collect();
    assert!(
        s1.iter().any(|r| r.cells.len() == given),
        "the MQTT route is recorded: {:?}",
        s1.iter().map(|r| r.cells.len()).collect::<Vec<_>>()
    );
    assert!(s1.iter().all(|r| r.score == Some(5.0)));
    // The fixture's own scripted requests are recorded too, without feedback.
    assert!(routes.iter().filter(|r| r.score.is_none()).count() >= 1);

    // What was recorded trains the path models (`train --from-store`), with
    // the rated route among the walks.
    let db = config.dir.path().join("learning.sqlite");
    let out = config.dir.path().join("models");
    let trained = std::process::Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args(["train", "--site"])
        .arg(&site)
        .arg("--from-store")
        .arg(&db)
        .arg("--out")
        .arg(&out)
        .args([
            "--iterations",
            "20",
            "--classifier-iterations",
            "20",
            "--min-class-walks",
            "1",
            "--accept-failed",
            "--json",
        ])
        .output()
        .unwrap();
    assert!(
        trained.status.success(),
        "{}",
        String::from_utf8_lossy(&trained.stderr)
    );
    assert!(out.join("generator.onnx").exists());
}
