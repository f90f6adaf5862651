//! Offline evaluation: how well the stages do on labelled data, measured the
//! same way every time so that figures in notes and CI can be rerun.
//!
//! - [`localization`]: `gangway eval localization` on a labelled survey;
//! - [`floors`]: `gangway eval localization --walks` in a building of several
//!   floors, beside a k-NN baseline;
//! - [`guidance`]: `gangway eval guidance`, simulated walkers guided along
//!   their routes, some taking a wrong turn;
//! - [`planning`]: `gangway eval planning`, every planner mode on place pairs,
//!   random pairs and held-out walks;
//! - [`similarity`]: cell-set IoU and nearest-training-frame distance;
//! - [`figures`]: the planning figures (sample routes per class, deviation
//!   over training checkpoints); `plot` draws the line charts.

pub mod figures;
pub mod floors;
pub mod guidance;
pub mod localization;
pub mod planning;
mod plot;
pub mod similarity;

pub use plot::error_cdf_svg;
