//! Guidance over a real mosquitto while a fixture replays: a route asked for
//! over MQTT starts a session whose messages arrive on `…/guidance` as the
//! walk plays (every one matching docs/schemas/guidance.schema.json), and
//! `…/route/cancel` ends it with a `cancelled` message after which the
//! device gets no more guidance.

use crate::mqtt_support::*;

const PREFIX: &str = "gangway/gw-guide";

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn guidance_follows_a_replayed_walk_and_a_cancel_ends_it() {
    let broker = Broker::start();
    let site = repo().join("config/sites/waldo.toml");
    let config = gateway_config("gw-guide", &site, &broker, "");
    let mut client = Client::connect(&broker, "test-guidance", &[&format!("{PREFIX}/#")]).await;
    let fixture = repo().join("fixtures/walk-waldo.jsonl");
    let mut gateway = Gateway::start(
        &config.path,
        &["--replay", fixture.to_str().unwrap(), "--speed", "4"],
    );
    let guidance = format!("{PREFIX}/devices/walker-01/guidance");
    let location = format!("{PREFIX}/devices/walker-01/location");
    client
        .wait_for("a location of walker-01", |m| m.topic == location)
        .await;

    let reply = client
        .route(PREFIX, "walker-01", "east entrance", "guide-1")
        .await;
    assert!(reply.get("error").is_none(), "expected a route: {reply}");
    let depart = client
        .wait_for("the first guidance of the route", |m| {
            m.topic == guidance && m.json()["request_id"] == "guide-1"
        })
        .await
        .json();
    assert_eq!(
        (&depart["event"], &depart["state"]),
        (&"depart".into(), &"active".into()),
        "{depart}"
    );
    // The walk goes on: a guidance message per located fix of the session.
    let progress = client
        .wait_for("guidance on a later fix", |m| {
            m.topic == guidance
                && m.json()["request_id"] == "guide-1"
                && m.json()["event"] != "depart"
        })
        .await
        .json();
    check_schema("guidance", &progress).unwrap();

    client
        .publish(&format!("{PREFIX}/devices/walker-01/route/cancel"), "")
        .await;
    let cancelled = client
        .wait_for("the cancelled session's last message", |m| {
            m.topic == guidance && m.json()["state"] == "cancelled"
        })
        .await
        .json();
    assert_eq!(
        (
            &cancelled["event"],
            &cancelled["next"],
            &cancelled["request_id"]
        ),
        (
            &"cancelled".into(),
            &serde_json::Value::Null,
            &"guide-1".into()
        ),
        "{cancelled}"
    );
    // Later fixes of the device are published, but guide nobody (unless
    // the fixture's own walker asks for a route again: a new session).
    let cancelled_at = client
        .seen
        .iter()
        .position(|m| m.topic == guidance && m.json()["state"] == "cancelled")
        .unwrap();
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(20);
    while client.seen[cancelled_at..]
        .iter()
        .filter(|m| m.topic == location)
        .count()
        < 3
    {
        assert!(
            std::time::Instant::now() < deadline,
            "walker-01 was not located after the cancel"
        );
        tokio::time::sleep(std::time::Duration::from_millis(200)).await;
        client.drain();
    }
    let after: Vec<_> = client.seen[cancelled_at + 1..]
        .iter()
        .filter(|m| m.topic == guidance)
        .map(|m| m.json())
        .collect();
    assert!(
        after.iter().all(|m| m["request_id"] != "guide-1"),
        "the cancelled session still guided: {after:?}"
    );
    assert!(assert_all_valid(&client.seen) > 3);
    assert!(gateway.terminate().success());
}
