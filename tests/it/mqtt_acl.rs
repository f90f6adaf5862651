//! The broker's ACL of docs/security.md, `config/mosquitto/gangway.acl`
//! as shipped, on a real mosquitto with `allow_anonymous false`: nobody
//! connects without an account; a phone asks for its own route, and its
//! requests, scans and feedback for another device, a forged status, forged
//! shared sightings and a deleted discovery config never reach anyone; Home
//! Assistant reads the discovery configs and cannot change them; the gateway
//! serves through it all.

use std::path::Path;
use std::process::Command;
use std::time::Duration;

use crate::mqtt_support::*;
use rumqttc::{AsyncClient, ConnectionError, Event, MqttOptions, Packet, QoS};

const PREFIX: &str = "gangway/gw-lobby";

fn password(user: &str) -> String {
    format!("{user}-s3cret")
}

/// Options that log in as `user`.
fn login(broker: &Broker, user: &str) -> MqttOptions {
    let mut options = MqttOptions::new(format!("acl-{user}"), "127.0.0.1", broker.port);
    options.set_credentials(user, password(user));
    options.set_keep_alive(Duration::from_secs(5));
    options.set_max_packet_size(1 << 20, 1 << 20);
    options
}

/// How the broker answers a connection with `options`: `Ok` once accepted.
async fn connect_answer(options: MqttOptions) -> Result<(), String> {
    let (_client, mut eventloop) = AsyncClient::new(options, 10);
    let answer = tokio::time::timeout(Duration::from_secs(10), async {
        loop {
            match eventloop.poll().await {
                Ok(Event::Incoming(Packet::ConnAck(_))) => return Ok(()),
                Ok(_) => {}
                Err(ConnectionError::ConnectionRefused(code)) => return Err(format!("{code:?}")),
                Err(e) => return Err(e.to_string()),
            }
        }
    });
    answer.await.expect("the broker answers a connection")
}

fn write_passwords(file: &Path, users: &[&str]) {
    for (i, user) in users.iter().enumerate() {
        let mut command = Command::new("mosquitto_passwd");
        command.arg("-b");
        if i == 0 {
            command.arg("-c");
        }
        let made = command
            .arg(file)
            .args([*user, &password(user)])
            .status()
            .expect("mosquitto_passwd (package mosquitto)");
        assert!(made.success());
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_brokers_acl_ties_every_topic_to_its_account() {
    let dir = tempfile::tempdir().unwrap();
    let passwd = dir.path().join("passwd");
    write_passwords(
        &passwd,
        &[
            "gw-lobby",
            "walker-01",
            "visitor",
            "homeassistant",
            "operator",
        ],
    );
    let acl = repo().join("config/mosquitto/gangway.acl");
    let broker = Broker::start_with(|_| {
        format!(
            "allow_anonymous false\npassword_file {}\nacl_file {}\n",
            passwd.display(),
            acl.display()
        )
    });

    // No account, or a wrong password: refused.
    let anonymous = MqttOptions::new("acl-anonymous", "127.0.0.1", broker.port);
    let refused = connect_answer(anonymous).await;
    assert!(refused.is_err(), "an anonymous client was let in");
    let mut wrong = login(&broker, "visitor");
    wrong.set_credentials("visitor", "guessed");
    assert!(connect_answer(wrong).await.is_err());

    let mut operator = Client::connect_with(
        login(&broker, "operator"),
        &["gangway/#", "homeassistant/#"],
    )
    .await;
    operator.ready("gangway/operator-probe").await;

    let secret = dir.path().join("gw-lobby.password");
    std::fs::write(&secret, password("gw-lobby") + "\n").unwrap();
    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config("gw-lobby", &site, &broker, "");
    let mut text = std::fs::read_to_string(&config.path).unwrap();
    text.push_str(&format!(
        "username = \"gw-lobby\"\npassword_file = \"{}\"\n",
        secret.display()
    ));
    std::fs::write(&config.path, text).unwrap();
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let mut gateway = Gateway::start(
        &config.path,
        &["--replay", fixture.to_str().unwrap(), "--speed", "10"],
    );
    let status = format!("{PREFIX}/status");
    operator
        .wait_for("the gateway online", |m| {
            m.topic == status && m.text() == "online"
        })
        .await;
    operator
        .wait_for("walker-01 located", |m| {
            m.topic == format!("{PREFIX}/devices/walker-01/location")
        })
        .await;
    let discovery = operator
        .wait_for("a discovery config of the gateway's", |m| {
            m.topic.starts_with("homeassistant/")
                && m.topic.contains("/gw-lobby/")
                && m.topic.ends_with("/config")
                && !m.payload.is_empty()
        })
        .await
        .topic;

    // A phone asks for its own route: answered.
    let mut walker_01 = Client::connect_with(
        login(&broker, "walker-01"),
        &[&format!("{PREFIX}/devices/walker-01/#")],
    )
    .await;
    let request = |id: &str| serde_json::json!({"to": "help desk", "request_id": id}).to_string();
    // `client` asks for `device`'s route to the help desk.
    let ask = async |client: &Client, device: &str, id: &str| {
        let topic = format!("{PREFIX}/devices/{device}/route/set");
        client.publish(&topic, request(id)).await;
    };
    ask(&walker_01, "walker-01", "own-1").await;
    let reply = operator.reply(PREFIX, "walker-01", "own-1").await;
    assert!(reply["waypoints"].is_array(), "{reply}");

    // Another phone (a visitor) forges all it can; its own request comes last.
    // It may read what the gateway says about walker-01 no more than write.
    let mut visitor = Client::connect_with(
        login(&broker, "visitor"),
        &[&format!("{PREFIX}/devices/walker-01/#"), "gangway/#"],
    )
    .await;
    let forged: Vec<(String, Vec<u8>, bool)> = vec![
        (
            format!("{PREFIX}/devices/walker-01/route/set"),
            request("forged-1").into_bytes(),
            false,
        ),
        (
            format!("{PREFIX}/devices/walker-01/route/cancel"),
            b"{}".to_vec(),
            false,
        ),
        (
            format!("{PREFIX}/devices/walker-01/feedback"),
            br#"{"request_id": "own-1", "rating": 1}"#.to_vec(),
            false,
        ),
        (
            format!("{PREFIX}/scans/walker-01"),
            br#"{"t": 0, "sightings": []}"#.to_vec(),
            false,
        ),
        (status.clone(), b"offline".to_vec(), true),
        (
            "gangway/sites/waldo-library/sightings/gw-b".into(),
            br#"{"schema":"gangway.sightings/1","gateway":"gw-b","sightings":[]}"#.to_vec(),
            false,
        ),
        (discovery.clone(), Vec::new(), true),
    ];
    for (topic, payload, retain) in &forged {
        visitor
            .client
            .publish(topic, QoS::AtLeastOnce, *retain, payload.clone())
            .await
            .unwrap();
    }
    ask(&visitor, "visitor", "own-2").await;
    // The visitor was never heard: its own request is answered, with an error.
    let reply = operator.reply(PREFIX, "visitor", "own-2").await;
    assert_eq!(reply["error"]["code"], "unknown_device", "{reply}");

    // Home Assistant reads the configs and cannot delete one.
    let mut hass =
        Client::connect_with(login(&broker, "homeassistant"), &["homeassistant/#"]).await;
    hass.wait_for("the gateway's discovery config", |m| m.topic == discovery)
        .await;
    hass.client
        .publish(&discovery, QoS::AtLeastOnce, true, Vec::new())
        .await
        .unwrap();
    hass.publish("homeassistant/status", "online").await;
    operator
        .wait_for("Home Assistant's birth message", |m| {
            m.topic == "homeassistant/status" && m.text() == "online"
        })
        .await;

    // The gateway still serves walker-01, and nothing forged reached anyone.
    ask(&walker_01, "walker-01", "own-3").await;
    let reply = operator.reply(PREFIX, "walker-01", "own-3").await;
    assert!(reply["waypoints"].is_array(), "{reply}");
    // walker-01 reads its own replies; the visitor only its own.
    walker_01.reply(PREFIX, "walker-01", "own-3").await;
    visitor.drain();
    let read: Vec<&str> = visitor.seen.iter().map(|m| m.topic.as_str()).collect();
    assert!(
        read.iter()
            .all(|t| t.starts_with(&format!("{PREFIX}/devices/visitor/"))),
        "the visitor read {read:?}"
    );
    assert!(!read.is_empty(), "the visitor got not even its own reply");
    operator.drain();
    for (topic, payload, _) in &forged {
        let leaked = operator
            .seen
            .iter()
            .find(|m| &m.topic == topic && &m.payload == payload);
        assert!(leaked.is_none(), "the visitor's message reached {topic}");
    }
    assert!(
        !operator
            .seen
            .iter()
            .any(|m| m.json()["request_id"] == "forged-1"),
        "the gateway answered a forged request"
    );
    assert!(
        !operator
            .seen
            .iter()
            .any(|m| m.topic == discovery && m.payload.is_empty()),
        "a discovery config was deleted"
    );
    assert!(gateway.terminate().success());
}
