//! The JSON Schemas in docs/schemas/ describe what the code really sends and
//! accepts: payloads from a replay of the fixture validate, and the example
//! requests that the schemas accept (or refuse) are accepted (or refused) by
//! the gateway's own reader too. Wire payloads are checked in the other
//! `mqtt_*` tests.

use std::sync::Arc;

use crate::mqtt_support::{check_schema, repo, schema_of};
use gangway::config::Config;
use gangway::event::{Event, Inbound};
use gangway::mqtt::inbound::Inbox;
use gangway::mqtt::sightings;
use gangway::pipeline::Pipeline;
use gangway::plan::RouteErrorCode;
use gangway::publish::Output;
use gangway::site::Site;
use gangway::source::log::LogReader;
use gangway::topics::Topics;
use serde_json::json;

fn pipeline() -> (Pipeline, Topics) {
    let config = Config::load(&repo().join("config/gangway.toml")).unwrap();
    let site = Arc::new(Site::load(&config.site).unwrap());
    (
        Pipeline::new(&config.pipeline(), site).unwrap(),
        Topics::new(config.topic_prefix()),
    )
}

#[test]
fn replayed_locations_routes_and_errors_match_their_schemas() {
    let (mut pipeline, topics) = pipeline();
    let mut outputs = Vec::new();
    let mut own = Vec::new();
    for event in LogReader::open(&repo().join("fixtures/walk-waldo.jsonl"), false).unwrap() {
        let event = event.unwrap();
        if let Event::Advert(s) = &event
            && own.len() < 50
        {
            own.push(s.clone());
        }
        pipeline.handle(&event, &mut outputs);
    }
    pipeline.finish(&mut outputs);
    let reject = pipeline.reject(
        "walker-01",
        Some("r".into()),
        1.0,
        RouteErrorCode::InvalidJson,
        "bad".into(),
    );
    outputs.push(Output::Route(Box::new(reject)));
    let mut out: Vec<_> = outputs.iter().filter_map(|o| topics.encode(o)).collect();
    out.push(sightings::encode(
        "gangway/sites/waldo-library",
        "gw-lobby",
        &own,
    ));
    let (mut locations, mut routes) = (0, 0);
    for m in &out {
        let name = schema_of(&m.topic).unwrap_or_else(|| panic!("no schema for {}", m.topic));
        let payload = m.value();
        check_schema(name, &payload).unwrap();
        locations += usize::from(name == "location");
        routes += usize::from(name == "path" && payload.get("waypoints").is_some());
    }
    assert!(
        locations > 100 && routes > 0,
        "{locations} locations, {routes} routes"
    );

    // A payload the schema must refuse: a location without its cell.
    let mut broken = out[0].value();
    broken.as_object_mut().unwrap().remove("cell");
    assert!(check_schema("location", &broken).is_err());
}

#[test]
fn the_request_schemas_and_the_gateway_agree_on_what_is_valid() {
    let inbox = Inbox::new(
        Topics::new("gangway/gw"),
        "gangway/sites/s".into(),
        "gw".into(),
        16 * 1024,
        true,
    );
    let uuid = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84";
    // (schema, topic, payload, valid?)
    let cases = [
        (
            "route-set",
            "gangway/gw/devices/p/route/set",
            json!({"to": "help desk"}),
            true,
        ),
        (
            "route-set",
            "gangway/gw/devices/p/route/set",
            json!({"to": [3, 4], "request_id": "r", "profile": "default"}),
            true,
        ),
        (
            "route-set",
            "gangway/gw/devices/p/route/set",
            json!({"to": {"x": 1}}),
            false,
        ),
        (
            "route-set",
            "gangway/gw/devices/p/route/set",
            json!({"to": "a", "colour": "red"}),
            false,
        ),
        (
            "route-set",
            "gangway/gw/devices/p/route/set",
            json!({"request_id": "r"}),
            false,
        ),
        (
            "feedback",
            "gangway/gw/devices/p/feedback",
            json!({"request_id": "r", "score": 5}),
            true,
        ),
        (
            "feedback",
            "gangway/gw/devices/p/feedback",
            json!({"request_id": "r", "score": 0}),
            false,
        ),
        (
            "feedback",
            "gangway/gw/devices/p/feedback",
            json!({"score": 3}),
            false,
        ),
        (
            "scan",
            "gangway/gw/scans/p",
            json!([{"uuid": uuid, "major": 1, "minor": 2, "rssi": -70}]),
            true,
        ),
        (
            "scan",
            "gangway/gw/scans/p",
            json!([{"uuid": uuid, "major": 1, "minor": 2, "rssi": -70, "tx_power": -59}]),
            true,
        ),
        (
            "scan",
            "gangway/gw/scans/p",
            json!([{"uuid": uuid, "major": 1, "minor": 2}]),
            false,
        ),
        (
            "scan",
            "gangway/gw/scans/p",
            json!([{"uuid": "not-a-uuid", "major": 1, "minor": 2, "rssi": -1}]),
            false,
        ),
        ("scan", "gangway/gw/scans/p", json!({"uuid": uuid}), false),
    ];
    for (schema, topic, payload, valid) in cases {
        let by_schema = check_schema(schema, &payload).is_ok();
        let read = inbox.read(topic, payload.to_string().as_bytes(), 0.0);
        let by_gateway = matches!(
            read,
            Ok(Inbound::Route(_) | Inbound::Feedback(_) | Inbound::Scan(_))
        );
        assert_eq!(
            (by_schema, by_gateway),
            (valid, valid),
            "{schema} {payload}: schema says {by_schema}, gateway says {read:?}"
        );
    }
}
