//! The quickstart path: with no broker configured, `run` starts the embedded
//! broker on 127.0.0.1 and serves on it (retained status, last will, routes),
//! and `replay` publishes a whole log to a broker, waiting for room in a small
//! queue rather than dropping, and exits once all of it is acknowledged.

use std::net::TcpListener;
use std::process::{Command, Stdio};

use crate::mqtt_support::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn run_without_a_url_serves_on_an_embedded_broker() {
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let dir = tempfile::tempdir().unwrap();
    let config = dir.path().join("gangway.toml");
    std::fs::write(
        &config,
        format!(
            "gateway_id = \"gw-embedded\"\nsite = \"{}\"\n[web]\nbind = \"127.0.0.1:0\"\n\
             [mqtt]\nembedded_port = {port}\n",
            repo().join("config/sites/waldo.toml").display()
        ),
    )
    .unwrap();
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let mut gateway = Gateway::start(
        &config,
        &["--replay", fixture.to_str().unwrap(), "--speed", "10"],
    );
    let broker = Broker::at_port(port);
    let prefix = "gangway/gw-embedded";
    let mut client = Client::connect(&broker, "test-embedded", &[&format!("{prefix}/#")]).await;
    let status = client
        .wait_for("retained online", |m| m.topic == format!("{prefix}/status"))
        .await;
    assert_eq!(status.text(), "online");
    client
        .wait_for("a location", |m| {
            m.topic == format!("{prefix}/devices/walker-02/location")
        })
        .await;
    let reply = client.route(prefix, "walker-02", "printers", "e1").await;
    assert!(reply["waypoints"].is_array(), "{reply}");
    assert!(gateway.terminate().success());
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn replay_publishes_every_message_before_it_exits() {
    let broker = Broker::start();
    // A queue far smaller than the log: replay must wait for the broker
    // rather than drop.
    let site = repo().join("config/sites/waldo.toml");
    let dir = gateway_config("gw-replay", &site, &broker, "");
    let config = dir.path.clone();
    let text = std::fs::read_to_string(&config).unwrap();
    std::fs::write(&config, format!("{text}queue_max_messages = 4\n")).unwrap();
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let printed = Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args(["replay", "--print", "--config"])
        .arg(&config)
        .arg(&fixture)
        .stderr(Stdio::null())
        .output()
        .unwrap();
    assert!(printed.status.success());
    // Subscribed only now: the --print run above published too (the config
    // has a url), and those must not count.
    let mut client = Client::connect(&broker, "test-replay", &["gangway/#"]).await;
    client.ready("gangway/probe").await;
    let expected = printed
        .stdout
        .split(|&b| b == b'\n')
        .filter(|l| !l.is_empty())
        .count();
    let status = Command::new(env!("CARGO_BIN_EXE_gangway"))
        .args(["replay", "--config"])
        .arg(&config)
        .arg(&fixture)
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success());
    let mut count = 0;
    client
        .wait_for(&format!("all {expected} messages"), |m| {
            count += usize::from(m.topic.starts_with("gangway/gw-replay/devices/"));
            count == expected
        })
        .await;
}
