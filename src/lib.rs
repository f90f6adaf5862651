//! gangway: a BLE edge gateway.
//!
//! Data flows one way, one module per stage:
//!
//! ```text
//! source ──Event──▶ locate::window ──Fingerprint──▶ Localizer ──▶ locate::tracker
//!    (ble, log, simulate)                                               │ Fix
//!                                  publish ◀──Location / RouteReply── pipeline ◀── plan
//!                                     │
//!                               mqtt, --print
//! ```
//!
//! [`site`] and [`config`] describe the building and the gateway; [`pipeline`]
//! wires the stages together without doing I/O; [`daemon`] and the [`cli`]
//! drive it, [`mqtt`] connects it to the broker, and [`store`] keeps what the
//! daemon saw for training. [`score`] compares a replay's fixes with its log's
//! ground truth.

pub mod cli;
pub mod config;
pub mod daemon;
pub mod eval;
pub mod guide;
pub mod locate;
pub mod model;
pub mod mqtt;
pub mod pipeline;
pub mod plan;
pub mod publish;
pub mod score;
pub mod sighting;
pub mod site;
pub mod source;
pub mod store;
pub mod throttle;
pub mod train;
pub mod walks;
pub mod web;
