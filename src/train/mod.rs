//! Training the path and localization models on the gateway's own hardware.
//!
//! - [`trajectory`]: the walk format (JSON Lines) and its validation;
//! - [`frame`]: walks as `W × H` 0/1 frames, and the paper's frame CSVs;
//! - [`paths`] and [`cells`]: the data sets (walks with their source/destination
//!   class; survey readings with their cell);
//! - [`mlp`]: the dense-network trainer (why it is hand-written: see there);
//! - [`gan`] and [`classifier`]: the paper's GAN and the softmax classifiers;
//! - [`desire`]: the desire-line model (the walks' shapes, settings by
//!   cross-validation);
//! - [`recorded`]: walks and rated routes from the daemon's learning store;
//! - [`job`]: what `gangway train` trains, measures and writes.
//!
//! The models are written as ONNX by [`crate::model::export`] and run by
//! [`crate::model::runtime`].

pub(crate) mod cells;
pub(crate) mod classifier;
pub mod desire;
pub(crate) mod frame;
pub mod gan;
pub(crate) mod job;
pub(crate) mod mlp;
pub mod paths;
pub(crate) mod recorded;
pub mod trajectory;
