//! gangway: a BLE edge gateway.
//!
//! Data flows one way, one module per stage:
//!
//! ```text
//! source ──Event──▶ locate::window ──Fingerprint──▶ Localizer ──▶ locate::tracker
//! (ble, capture, mqtt)                                                  │ Fix
//!                     sink ◀──publish::Output── pipeline ◀── plan, guide
//!     (mqtt, jsonl, store, score)
//! ```
//!
//! [`site`] and [`config`] describe the building and the gateway; [`pipeline`]
//! wires the stages together without doing I/O and returns typed outputs
//! ([`publish`]); the runtime ([`daemon`]) runs it between [`source`]s and
//! [`sink`]s, and the [`cli`] wires them. [`mqtt`] is the broker as a source
//! and a sink, [`store`] keeps what the daemon saw for training, and [`score`]
//! compares a replay's fixes with its log's ground truth.

// The outside surface is what main.rs, tests/it, benches, examples and fuzz
// use; everything else is pub(crate), so dead code is a warning. A `pub` that
// nothing outside can reach is one too (`cargo fix` makes it pub(crate)).
#![warn(unreachable_pub)]

pub mod cli;
pub mod config;
pub mod daemon;
pub mod eval;
pub mod event;
pub mod guide;
pub mod locate;
pub mod model;
pub mod mqtt;
pub mod pipeline;
pub mod plan;
pub mod publish;
pub(crate) mod score;
pub mod sighting;
pub mod sink;
pub mod site;
pub mod source;
pub mod store;
pub(crate) mod throttle;
pub mod train;
pub(crate) mod walks;
pub mod web;
