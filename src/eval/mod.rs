//! Offline evaluation: how well the stages do on labelled data, measured the
//! same way every time so that figures in notes and CI can be rerun.

pub mod figures;
pub mod localization;
pub mod planning;
mod plot;
pub mod similarity;

pub use plot::{error_cdf_svg, line_svg};
