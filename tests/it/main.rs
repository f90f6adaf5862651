//! The integration tests, one harness: each module is one area of the
//! gateway tried from outside, through the built `gangway` binary, a real
//! broker (mosquitto on a free loopback port), a real browser or the library's
//! in-process runtime. One binary links the crate once (27 did before), and
//! the helpers below are shared without each file taking a different subset.
//!
//! Run one area with `cargo test --release --test it <module>::`.

// Shared helpers.
mod common;
mod floors_support;
mod mqtt_support;
mod web_support;

mod architecture;
mod bluez;
mod captures;
mod check;
mod daemon;
mod fixtures;
mod floors_daemon;
mod floors_routes;
mod guidance;
mod hass;
mod hass_discovery;
mod localization;
mod mqtt_acl;
mod mqtt_cluster;
mod mqtt_embedded;
mod mqtt_fleet;
mod mqtt_guidance;
mod mqtt_hostile;
mod mqtt_resilience;
mod mqtt_routes;
mod mqtt_schemas;
mod mqtt_store;
mod mqtt_systemd_unit;
mod mqtt_tls;
mod onnx_reference;
mod pedestrians;
mod planning;
mod planning_eval;
mod receivers;
mod record;
mod replay;
mod site_import;
mod survey;
mod waldo_site;
mod walkthrough;
mod web;
