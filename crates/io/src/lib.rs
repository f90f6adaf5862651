//! gangway-io: where the world comes in and goes out.
//!
//! Sources ([`source`]: the radio, captures of every format; [`mqtt`]'s
//! subscriptions; [`web`]'s pages) turn what they read into the core's events;
//! sinks ([`sink`], [`mqtt`], [`web`], [`score`]) deliver the core's typed
//! outputs. [`config`] composes every component's section of the gateway's
//! config file, and [`store`] is the learning store on disk. Nothing here runs
//! the pipeline: the runtime in the `gangway` binary wires these parts to it.
//!
//! # Errors
//!
//! What arrives from the air, the broker or a page is hostile until checked:
//! a bad message becomes an error reply or a counted refusal, a bad line of
//! a capture is skipped and counted (or named with its file and line), and
//! none of it stops a source or a sink. Errors a caller acts on are typed
//! (`MqttError`, the store's, the config's, naming file, line and field);
//! a source or sink that fails reports an `anyhow::Error` to the runtime,
//! which logs it and keeps the others serving.

// The core's modules under their own names, so a path reads the same in
// every crate of the workspace (`crate::site::Site`).
use gangway_core::{clock, cluster, event, guide, locate, pipeline, plan, publish, sighting, site};

pub mod config;
pub mod latency;
pub mod mqtt;
pub mod score;
pub mod sink;
pub mod source;
pub mod store;
pub mod throttle;
pub mod topics;
pub mod web;

/// Helpers the unit tests of several modules share.
#[cfg(test)]
mod test_support {
    use crate::publish::{LOCATION_SCHEMA, Location};
    use crate::site::Cell;

    /// A fix for tests: `device` at `cell` (unknown when `None`), near `place`.
    pub(crate) fn location(
        device: &str,
        t: f64,
        cell: Option<Cell>,
        place: Option<&str>,
    ) -> Location {
        Location {
            schema: LOCATION_SCHEMA,
            device: device.into(),
            t,
            floor: None,
            cell,
            label: None,
            x_m: None,
            y_m: None,
            place: place.map(str::to_owned),
            confidence: 0.5,
            anchors_heard: 3,
        }
    }
}
