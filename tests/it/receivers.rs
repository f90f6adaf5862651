//! ESPresense nodes and Theengs gateways as the site's receivers: their MQTT
//! messages locate tags exactly as a JSON Lines capture of the same
//! sightings does, in-process and through a real mosquitto, in one site
//! that mixes both kinds.

use std::sync::Arc;

use gangway::config::Config;
use gangway::event::{Event, Inbound};
use gangway::mqtt::inbound::Inbox;
use gangway::mqtt::receivers::{EspresenseConfig, TheengsConfig};
use gangway::pipeline::Pipeline;
use gangway::publish::Output;
use gangway::sighting::{BeaconId, Sighting};
use gangway::site::{Cell, Site};
use gangway::topics::Topics;

use crate::mqtt_support::*;

const TAG_UUID: &str = "0f0e0d0c-0b0a-4908-8706-050403020100";

/// Four receivers of the sample floor: two ESPresense rooms, two Theengs
/// gateways, at the ends of its corridors.
const RECEIVERS: [(&str, [u16; 2], Kind); 4] = [
    ("lobby", [3, 12], Kind::Espresense),
    ("stacks", [11, 0], Kind::Espresense),
    ("theengs-printers", [13, 14], Kind::Theengs),
    ("theengs-lab", [18, 7], Kind::Theengs),
];

/// Three tags, each standing still in one cell.
const TAGS: [(u16, [u16; 2]); 3] = [(1, [9, 9]), (2, [16, 14]), (3, [15, 2])];

#[derive(Clone, Copy, PartialEq)]
enum Kind {
    Espresense,
    Theengs,
}

/// The site: the sample floor with the receivers as its gateways.
fn site_file(dir: &std::path::Path) -> std::path::PathBuf {
    let waldo = std::fs::read_to_string(repo().join("config/sites/waldo.toml")).unwrap();
    let (body, places) = waldo.split_once("[places]").unwrap();
    let gateways: String = RECEIVERS
        .iter()
        .map(|(id, [x, y], _)| format!("[[gateway]]\nid = \"{id}\"\ncell = [{x}, {y}]\n\n"))
        .collect();
    let path = dir.join("site.toml");
    std::fs::write(&path, format!("{body}{gateways}[places]{places}")).unwrap();
    path
}

/// What the receivers hear in `seconds`: every tag by every receiver within
/// 16 cells (three or four of them), once a second, louder when nearer, with
/// a fixed wobble.
fn sightings(seconds: u32, t0: f64) -> Vec<Sighting> {
    let uuid = uuid::Uuid::parse_str(TAG_UUID).unwrap();
    let mut out = Vec::new();
    for s in 0..seconds {
        for (minor, [tx, ty]) in TAGS {
            for (i, (id, [rx, ry], _)) in RECEIVERS.iter().enumerate() {
                let d = f64::from(tx.abs_diff(*rx)).hypot(f64::from(ty.abs_diff(*ry)));
                if d > 16.0 {
                    continue;
                }
                let wobble = f64::from((s * 7 + u32::from(minor) * 3 + i as u32 * 5) % 7) - 3.0;
                let rssi = (-59.0 - 20.0 * d.max(0.5).log10() + wobble).round() as i16;
                out.push(Sighting {
                    advertiser_mac: None,
                    t: t0 + f64::from(s) + 0.1 * i as f64,
                    observer: Arc::from(*id),
                    advertiser: BeaconId {
                        uuid,
                        major: 7,
                        minor,
                    },
                    tx_power: Some(-59),
                    rssi,
                });
            }
        }
    }
    out
}

/// The MQTT message a real receiver publishes for `s`: the payload shapes of
/// ESPresense's and the Theengs decoder's documentation (docs/receivers.md).
fn message(s: &Sighting) -> (String, String) {
    let kind = RECEIVERS
        .iter()
        .find(|(id, ..)| *id == &*s.observer)
        .unwrap()
        .2;
    let b = s.advertiser;
    match kind {
        Kind::Espresense => {
            let id = format!("iBeacon:{}-{}-{}", b.uuid, b.major, b.minor);
            let distance = 10f64.powf(f64::from(-59 - s.rssi) / 20.0);
            (
                format!("espresense/devices/{id}/{}", s.observer),
                format!(
                    r#"{{"id":"{id}","idType":1,"rssi@1m":-59,"rssi":{},"raw":{distance:.2},"distance":{distance:.2},"var":0.04,"int":1020}}"#,
                    s.rssi
                ),
            )
        }
        Kind::Theengs => {
            let mac = format!("C4:7C:8D:6A:3E:{:02X}", b.minor);
            (
                format!("home/{}/BTtoMQTT/{}", s.observer, mac.replace(':', "")),
                format!(
                    r#"{{"id":"{mac}","mac_type":1,"rssi":{},"brand":"GENERIC","model":"iBeacon","model_id":"IBEACON","mfid":"4c00","uuid":"{}","major":{},"minor":{},"txpower":-59}}"#,
                    s.rssi,
                    b.uuid.simple(),
                    b.major,
                    b.minor
                ),
            )
        }
    }
}

/// The config of a gateway that reads both kinds of receiver.
fn config_text(site: &std::path::Path) -> String {
    format!(
        "gateway_id = \"gw\"\nsite = \"{}\"\n[window]\norientation = \"advertiser\"\n\
         [planner]\nmode = \"astar\"\n[mqtt.espresense]\n[mqtt.theengs]\n",
        site.display()
    )
}

/// Each fix's (device, cell, confidence) from what the pipeline published.
fn fixes(outputs: &[Output]) -> Vec<(String, Option<Cell>, u32)> {
    outputs
        .iter()
        .filter_map(|o| match o {
            Output::Location(l) => Some((l.device.clone(), l.cell, l.confidence.to_bits())),
            _ => None,
        })
        .collect()
}

/// Mean distance in cells from each fix to its tag's cell.
fn mean_error(fixes: &[(String, Option<Cell>, u32)]) -> f64 {
    let errors: Vec<f64> = fixes
        .iter()
        .filter_map(|(device, cell, _)| {
            let cell = (*cell)?;
            let minor: u16 = device.rsplit('-').next()?.parse().ok()?;
            let [x, y] = TAGS.iter().find(|(m, _)| *m == minor)?.1;
            Some(f64::from(cell.x.abs_diff(x)).hypot(f64::from(cell.y.abs_diff(y))))
        })
        .collect();
    errors.iter().sum::<f64>() / errors.len() as f64
}

#[test]
fn receiver_messages_locate_tags_exactly_as_the_capture_of_the_same_sightings() {
    let dir = tempfile::tempdir().unwrap();
    let site_path = site_file(dir.path());
    let config_path = dir.path().join("gangway.toml");
    std::fs::write(&config_path, config_text(&site_path)).unwrap();
    let config = Config::load(&config_path).unwrap();
    let site = Arc::new(Site::load(&config.site).unwrap());
    let heard = sightings(40, 1_767_225_600.0);

    // The JSON Lines capture's events, straight into a pipeline.
    let mut captured = Pipeline::new(&config.pipeline(), site.clone()).unwrap();
    let mut out_captured = Vec::new();
    for s in &heard {
        captured.handle(&Event::Advert(s.clone()), &mut out_captured);
    }
    captured.finish(&mut out_captured);

    // The same sightings as ESPresense and Theengs messages, read by the
    // gateway's inbox at the time each was heard.
    let inbox = Inbox::new(
        Topics::new("gangway/gw"),
        "gangway/sites/waldo-library".into(),
        "gw".into(),
        16 * 1024,
        true,
    )
    .with_receivers(
        Some(EspresenseConfig::default()),
        Some(TheengsConfig::default()),
    );
    let mut received = Pipeline::new(&config.pipeline(), site).unwrap();
    let mut out_received = Vec::new();
    for s in &heard {
        let (topic, payload) = message(s);
        match inbox.read(&topic, payload.as_bytes(), s.t) {
            Ok(Inbound::Shared(sightings)) => {
                assert_eq!(sightings, std::slice::from_ref(s), "{topic}");
                for s in sightings {
                    received.handle(&Event::Advert(s), &mut out_received);
                }
            }
            other => panic!("{topic} {payload}: {other:?}"),
        }
    }
    received.finish(&mut out_received);

    let (a, b) = (fixes(&out_captured), fixes(&out_received));
    assert!(a.len() >= 45, "{} fixes", a.len());
    assert_eq!(a, b, "the same fixes, cells and confidences");
    let error = mean_error(&a);
    println!(
        "{} fixes of 3 tags by 4 receivers: mean error {error:.2} cells, capture and receivers alike",
        a.len()
    );
    // The survey-free default on four receivers and a made-up radio: not a
    // figure of merit, only better than a guess (about 8 cells on this floor).
    assert!(error < 6.0, "mean error {error:.2} cells");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn espresense_and_theengs_messages_on_a_real_broker_locate_the_tags() {
    let broker = Broker::start();
    let dir = tempfile::tempdir().unwrap();
    let site = site_file(dir.path());
    let config = dir.path().join("gangway.toml");
    write_config(
        &config,
        "gw-receivers",
        &site,
        &broker,
        "[window]\norientation = \"advertiser\"\n[planner]\nmode = \"astar\"\n",
    );
    let mut text = std::fs::read_to_string(&config).unwrap();
    text.push_str("[mqtt.espresense]\n[mqtt.theengs]\n");
    std::fs::write(&config, text).unwrap();
    let mut client = Client::connect(&broker, "test-receivers", &["gangway/#"]).await;
    let _gateway = Gateway::start(&config, &["--replay", "/dev/null"]);
    client.ready("gangway/test-probe").await;

    // Ten seconds of what the receivers hear, published as they hear it,
    // with a thermometer the Theengs gateway also reports (passed over).
    let heard = sightings(10, 0.0);
    for second in 0..10 {
        for s in heard.iter().filter(|s| s.t as u32 == second) {
            let (topic, payload) = message(s);
            client.publish(&topic, payload).await;
        }
        client
            .publish(
                "home/theengs-lab/BTtoMQTT/A4C138000001",
                r#"{"id":"A4:C1:38:00:00:01","rssi":-80,"model_id":"LYWSD03MMC_ATC","tempc":21.5}"#,
            )
            .await;
        tokio::time::sleep(std::time::Duration::from_secs(1)).await;
    }
    for (minor, _) in TAGS {
        let topic = format!("gangway/gw-receivers/devices/{TAG_UUID}-7-{minor}/location");
        client
            .wait_for(&format!("tag {minor} located by 3+ receivers"), |m| {
                m.topic == topic && m.json()["anchors_heard"].as_u64() >= Some(3)
            })
            .await;
    }
    let located: Vec<(String, Option<Cell>, u32)> = client
        .seen
        .iter()
        .filter(|m| m.topic.ends_with("/location"))
        .map(|m| {
            let fix = m.json();
            let cell = serde_json::from_value::<Option<[u16; 2]>>(fix["cell"].clone()).unwrap();
            (
                fix["device"].as_str().unwrap().to_owned(),
                cell.map(|[x, y]| Cell::new(x, y)),
                0,
            )
        })
        .collect();
    // Stamped as they arrive, the windows are not the capture's, so the
    // fixes are close to the in-process ones rather than the same.
    let error = mean_error(&located);
    assert!(
        error < 6.0,
        "mean error {error:.2} cells over {} fixes",
        located.len()
    );
    let stats = client
        .wait_for("stats counting the receivers' sightings", |m| {
            m.topic == "gangway/gw-receivers/stats" && m.json()["shared_in"].as_u64() > Some(30)
        })
        .await
        .json();
    assert_eq!(stats["rejected_messages"], 0, "{stats}");
    assert_all_valid(&client.seen);
}
