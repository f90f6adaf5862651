//! gangway-core: what the gateway computes, with no I/O.
//!
//! Data flows one way, one module per stage:
//!
//! ```text
//! Event ──▶ locate::window ──Fingerprint──▶ Localizer ──▶ locate::tracker
//!                                                               │ Fix
//!                           publish::Output ◀── pipeline ◀── plan, guide
//! ```
//!
//! [`sighting`] and [`event`] are what comes in, [`site`] the building,
//! [`locate`], [`plan`] and [`guide`] the stages, [`model`] the trained
//! models at run time, [`publish`] the typed outputs, and [`pipeline`] wires
//! the stages without doing I/O; [`clock`] is the only time it measures, and
//! it is passed in. This crate opens no socket and starts no
//! runtime; sources, sinks and the runtime that feed it live in
//! `gangway-io` and the `gangway` binary, so a stage that reached for the
//! network would not compile.
//!
//! # Errors
//!
//! Every fallible function returns its stage's own error type (thiserror):
//! a message that names the file, line, field or setting and says what to
//! do, and variants a caller acts on (a gateway starting up falls back to
//! `pathloss` or `astar` on a `LocalizerError` that is a file failure or a
//! `plan::BuildError::Model`, and on nothing else). No `anyhow` here: it is
//! not among this crate's dependencies, and the architecture test keeps it
//! out of them. Some settings checks still return
//! `Result<_, String>` (one message, nothing to match on); typing them is
//! left to do. Nothing here panics on input: a panic is a bug.

pub mod clock;
pub mod cluster;
pub mod csv_line;
pub mod event;
pub mod guide;
pub mod locate;
pub mod model;
pub mod pipeline;
pub mod plan;
pub mod publish;
pub mod sighting;
pub mod sign_test;
pub mod site;
