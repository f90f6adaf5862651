//! gangway-offline: what a user runs before and beside the gateway.
//!
//! Training the path models and the cell classifier ([`train`], written as
//! ONNX by [`model::export`]), the evaluations that judge every stage on real
//! data against the simple baselines ([`eval`]), recorded walks of real
//! scenes ([`walks`]), surveys and sites imported from walks with timed
//! waypoints ([`survey`]), simulated walkers and their phones ([`simulate`]) and
//! pictures of routes ([`picture`]). None of it runs in the daemon.

// The core's and the I/O crate's modules under their own names, so a path
// reads the same in every crate of the workspace (`crate::site::Site`).
use gangway_core::{
    csv_line, event, guide, locate, model, pipeline, plan, publish, sighting, sign_test, site,
};
use gangway_io::{config, score, store};

pub mod eval;
pub mod picture;
pub mod simulate;
pub mod survey;
pub mod train;
pub mod walks;
