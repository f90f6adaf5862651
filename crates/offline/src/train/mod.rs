//! Training the path and localization models on the gateway's own hardware.
//!
//! - [`trajectory`]: the walk format (JSON Lines) and its validation;
//! - [`frame`]: walks as `W × H` 0/1 frames, and the paper's frame CSVs;
//! - [`paths`] and [`cells`]: the data sets (walks with their source/destination
//!   class; survey readings with their cell);
//! - [`mlp`]: the dense-network trainer (why it is hand-written: see there);
//! - [`workers`]: its threads (matrix products split by output blocks, so a
//!   seed and a thread count give the same weights);
//! - [`gan`] and [`classifier`]: the paper's GAN and the softmax classifiers;
//! - [`line_access`]: the line GAN's access penalty;
//! - [`desire`]: the desire-line model (the walks' shapes, settings by
//!   cross-validation);
//! - [`recorded`]: walks and rated routes from the daemon's learning store;
//! - [`job`]: what `gangway train` trains, measures and writes.
//!
//! The models are built as ONNX by [`crate::model::export`], written by
//! [`write_proto`], and run by
//! [`crate::model::runtime`].

pub(crate) mod cells;
pub(crate) mod classifier;
pub mod desire;
pub(crate) mod frame;
pub mod gan;
pub mod job;
pub(crate) mod line_access;
pub(crate) mod mlp;
pub mod paths;
pub mod recorded;
pub mod trajectory;
pub mod workers;

#[cfg(test)]
mod runtime_tests;

use std::path::Path;

use prost::Message;
use tract_onnx::pb;

use crate::model::Metadata;
use crate::model::export::{Spec, to_onnx};

/// Writes a trained network to `path` as the ONNX model
/// [`crate::model::export`] builds.
pub(crate) fn write_model(path: &Path, spec: &Spec, meta: &Metadata) -> std::io::Result<()> {
    write_proto(path, &to_onnx(spec, meta))
}

/// Writes an ONNX model built elsewhere (e.g.
/// [`crate::model::desire::DesireLines::to_onnx`]) to `path`.
pub fn write_proto(path: &Path, model: &pb::ModelProto) -> std::io::Result<()> {
    std::fs::write(path, model.encode_to_vec())
}
