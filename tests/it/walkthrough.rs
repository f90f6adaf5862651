//! `docs/your-building.md`, step by step, on recorded data: the paper's
//! floor as a user's building (its real survey and crowd scans in
//! `../shared`), the commands the guide gives, in its order, with what the
//! guide says you should see. If the guide and the product part ways, this
//! fails.

use crate::common;
use crate::mqtt_support::*;

/// Runs `gangway` with `args` from `dir` (a user's own folder, not the
/// checkout), returning (success, stdout, stderr).
fn gangway_in(dir: &std::path::Path, args: &[&str]) -> (bool, String, String) {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args(args)
        .current_dir(dir)
        .env("RUST_LOG", "warn")
        .env_remove("GANGWAY_CONFIG")
        .output()
        .unwrap();
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stdout).into_owned(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_your_building_guide_runs_as_written() {
    let (Some(crowd), Some(labelled)) = (
        common::shared_data("uci-ble-rssi/iBeacon_RSSI_Unlabeled.csv"),
        common::uci_survey(),
    ) else {
        return;
    };
    let broker = Broker::start();
    let dir = tempfile::tempdir().unwrap();
    let home = dir.path();

    // Step 1: the site as the editor saves it (its plan and beacons; the
    // editor itself is tested in a browser by tests/it/web.rs).
    std::fs::copy(
        repo().join("config/sites/waldo.toml"),
        home.join("building.toml"),
    )
    .unwrap();
    // Step 2: the gateway config of the guide, survey-free.
    let config = format!(
        "gateway_id = \"gw-home\"\nsite = \"building.toml\"\n\
         [localizer]\nmethod = \"pathloss\"\n\
         [mqtt]\nurl = \"{}\"\nstats_interval_s = 1\n[web]\nbind = \"127.0.0.1:0\"\n",
        broker.url()
    );
    std::fs::write(home.join("gangway.toml"), &config).unwrap();

    // Step 3: `gangway check --config gangway.toml` says ok.
    let (ok, stdout, stderr) = gangway_in(home, &["check", "--config", "gangway.toml"]);
    assert!(ok, "{stderr}");
    assert!(stdout.starts_with("ok: gangway.toml"), "{stdout}");
    assert!(stdout.contains("13 beacons"), "{stdout}");

    // Step 4: what the building's air holds: every beacon of the site heard.
    let crowd = crowd.to_str().unwrap();
    let (ok, stdout, stderr) = gangway_in(
        home,
        &[
            "replay",
            crowd,
            "--config",
            "gangway.toml",
            "--heard",
            "--json",
        ],
    );
    assert!(ok, "{stderr}");
    let heard: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let heard = heard["heard"].as_array().unwrap();
    assert_eq!(heard.len(), 13, "{heard:?}");
    assert!(heard.iter().all(|b| b["known"] == true), "{heard:?}");

    // Step 5: calibrate the radio on the crowd's scans, no positions needed.
    let (ok, _, stderr) = gangway_in(
        home,
        &[
            "calibrate",
            "--config",
            "gangway.toml",
            "--from",
            crowd,
            "--out",
            "building-calibration.toml",
        ],
    );
    assert!(ok, "{stderr}");
    let calibrated = config.replace(
        "method = \"pathloss\"\n",
        "method = \"pathloss\"\n[localizer.pathloss]\ncalibration = \"building-calibration.toml\"\n",
    );
    std::fs::write(home.join("gangway.toml"), &calibrated).unwrap();
    let (ok, _, stderr) = gangway_in(home, &["check", "--config", "gangway.toml"]);
    assert!(ok, "{stderr}");

    // Step 6: how well it locates, on a walk with known positions: the
    // guide's figure (1.84 cells, from 3.30 uncalibrated).
    let labelled = labelled.to_str().unwrap();
    let (ok, stdout, stderr) = gangway_in(
        home,
        &[
            "replay",
            labelled,
            "--config",
            "gangway.toml",
            "--score",
            "--json",
        ],
    );
    assert!(ok, "{stderr}");
    let score: serde_json::Value = serde_json::from_str(stdout.trim()).unwrap();
    let mean = score["mean_error_cells"].as_f64().unwrap();
    assert!(mean <= 2.0, "{score}");

    // Step 7: the gateway on the broker: Home Assistant gets a tracker, and
    // the walker's locations follow.
    let mut client = Client::connect(&broker, "test-walkthrough", &["#"]).await;
    let _gateway = Gateway::start(
        &home.join("gangway.toml"),
        &["--replay", labelled, "--speed", "0"],
    );
    client
        .wait_for("the tracker announced to Home Assistant", |m| {
            m.topic == "homeassistant/device_tracker/gw-home/survey/config"
        })
        .await;
    client
        .wait_for("a location", |m| {
            m.topic == "gangway/gw-home/devices/survey/location"
        })
        .await;
}
