//! Two gateways of one site on one broker share their sightings and both
//! localize a tag that each of them alone hears with a single anchor.

use std::fmt::Write as _;

use crate::mqtt_support::*;

const TAG_UUID: &str = "0f0e0d0c-0b0a-4908-8706-050403020100";

/// A log of the tag as heard by one gateway: every 0.5 s for 60 s.
fn log_of(gateway: &str, rssi: i16) -> String {
    let mut log = String::new();
    for i in 0..120 {
        let t = 1_767_225_600.0 + f64::from(i) * 0.5;
        writeln!(
            log,
            r#"{{"type":"advert","t":{t},"observer":"{gateway}","uuid":"{TAG_UUID}","major":7,"minor":1,"rssi":{rssi}}}"#
        )
        .unwrap();
    }
    log
}

/// The sample site plus two fixed gateways: the help desk (J10) and the
/// printers (N15).
fn two_gateway_site(dir: &std::path::Path) -> std::path::PathBuf {
    site_with_gateways(dir, &[("gw-a", [9, 9]), ("gw-b", [13, 14])])
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_gateways_share_sightings_and_both_localize_a_tag() {
    let broker = Broker::start();
    let dir = tempfile::tempdir().unwrap();
    let site = two_gateway_site(dir.path());
    // Two receivers cannot place a tag within a cell, and its published
    // confidence says so; where it puts the tag is still what this checks.
    let advertiser = "[window]\norientation = \"advertiser\"\n[localizer]\nmin_confidence = 0.0\n";
    let mut client = Client::connect(&broker, "test-fleet", &["gangway/#"]).await;
    let mut running = Vec::new();
    let mut configs = Vec::new();
    for (id, rssi) in [("gw-a", -62), ("gw-b", -80)] {
        let log = dir.path().join(format!("{id}.jsonl"));
        std::fs::write(&log, log_of(id, rssi)).unwrap();
        let config = gateway_config(id, &site, &broker, advertiser);
        // 60 s of log at 4×: the first batches may reach the other gateway
        // before it has subscribed, the rest cannot.
        running.push(Gateway::start(
            &config.path,
            &["--replay", log.to_str().unwrap(), "--speed", "4"],
        ));
        configs.push(config);
    }

    let tag = format!("{TAG_UUID}-7-1");
    for gw in ["gw-a", "gw-b"] {
        let topic = format!("gangway/{gw}/devices/{tag}/location");
        let fix = client
            .wait_for(&format!("{gw} locating the tag from both gateways"), |m| {
                m.topic == topic && m.json()["anchors_heard"] == 2
            })
            .await
            .json();
        // Heard far louder by gw-a: the tag is on gw-a's side of the floor.
        let cell: [u16; 2] = serde_json::from_value(fix["cell"].clone()).unwrap();
        let to_a = cell[0].abs_diff(9).max(cell[1].abs_diff(9));
        let to_b = cell[0].abs_diff(13).max(cell[1].abs_diff(14));
        assert!(to_a < to_b, "{gw} placed the tag at {cell:?}");
    }
    let stats = client
        .wait_for("gw-a stats with shared sightings both ways", |m| {
            let s = m.json();
            m.topic == "gangway/gw-a/stats"
                && s["shared_in"].as_u64() > Some(0)
                && s["shared_out"].as_u64() > Some(0)
        })
        .await
        .json();
    assert_eq!(stats["rejected_messages"], 0, "{stats}");
    assert!(
        client.seen.iter().any(|m| m.topic.contains("/sightings/")),
        "the shared sightings are on the broker"
    );
    assert_all_valid(&client.seen);
    drop(running);
    drop(configs);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_forged_batch_from_the_future_does_not_silence_a_tag() {
    // The attack of issue #29: one batch on another gateway's sightings
    // topic, dated 1e300, used to move the tag's window into the future
    // and silence it for the rest of the run.
    let broker = Broker::start();
    let dir = tempfile::tempdir().unwrap();
    let site = two_gateway_site(dir.path());
    let mut client = Client::connect(&broker, "test-forger", &["gangway/#"]).await;
    let log = dir.path().join("gw-a.jsonl");
    std::fs::write(&log, log_of("gw-a", -62)).unwrap();
    let config = gateway_config(
        "gw-a",
        &site,
        &broker,
        "[window]\norientation = \"advertiser\"\n",
    );
    // Real time: the log's 60 s play over 60 s, so the attack lands mid-run.
    let _gateway = Gateway::start(
        &config.path,
        &["--replay", log.to_str().unwrap(), "--speed", "1"],
    );
    let topic = format!("gangway/gw-a/devices/{TAG_UUID}-7-1/location");
    client
        .wait_for("the tag located before the attack", |m| m.topic == topic)
        .await;
    client
        .publish(
            "gangway/sites/waldo-library/sightings/gw-b",
            format!(
                r#"{{"schema":"gangway.sightings/1","gateway":"gw-b","sightings":[{{"t":1e300,"uuid":"{TAG_UUID}","major":7,"minor":1,"rssi":-40}}]}}"#
            ),
        )
        .await;
    let attacked = client.seen.len();
    let stats = client
        .wait_for("the forged batch refused and counted", |m| {
            m.topic == "gangway/gw-a/stats" && m.json()["rejected_messages"].as_u64() >= Some(1)
        })
        .await
        .json();
    assert_eq!(stats["shared_in"], 0, "{stats}");
    // The tag goes on being located: three more fixes within 20 s.
    let mut fixes_after = 0;
    for _ in 0..20 {
        tokio::time::sleep(std::time::Duration::from_secs(1)).await;
        client.drain();
        fixes_after = client.seen[attacked..]
            .iter()
            .filter(|m| m.topic == topic)
            .count();
        if fixes_after >= 3 {
            break;
        }
    }
    assert!(fixes_after >= 3, "{fixes_after} fixes after the attack");
}
