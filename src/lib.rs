//! gangway: a BLE edge gateway.
//!
//! The workspace's crates, one layer each (docs/architecture.md has the code
//! map; a test keeps it and the crates' dependencies in agreement):
//!
//! ```text
//! gangway-core     sightings, events, site, locate, plan, guide, models, outputs, pipeline (no I/O)
//! gangway-io       sources, sinks, MQTT, web, store, config            (imports the core)
//! gangway-offline  training, evaluation, walks, simulation, pictures   (imports core, io)
//! gangway          the runtime (daemon) and the CLI                    (imports all three)
//! ```
//!
//! This crate is the runtime ([`daemon`]: the pipeline between sources and
//! sinks, reloads, admission, recalibration) and the [`cli`] that wires it.
//! The other crates' modules are re-exported under their own names for the
//! binary, the integration tests, benches and examples, which see the
//! product as one `gangway`.
//!
//! # Errors
//!
//! The binary's edge is where errors end: `main` prints the chain (`{:#}`)
//! and exits non-zero for a command; the daemon logs a failing source, sink,
//! reload or recalibration and goes on serving with what it has (a reload
//! that fails keeps the running pipeline; a model that does not load at
//! start-up is replaced by `astar` or `pathloss`). The crates below return
//! typed errors where the runtime acts on the kind.

pub use gangway_core::{
    clock, cluster, event, guide, locate, model, pipeline, plan, publish, sighting, site,
};
pub use gangway_io::{config, latency, mqtt, score, sink, source, store, throttle, topics, web};
pub use gangway_offline::{eval, picture, simulate, survey, train, walks};

pub mod cli;
pub mod daemon;
pub mod logging;
