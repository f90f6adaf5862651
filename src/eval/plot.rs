//! Error CDF charts (the paper's Fig. 7), drawn with plotters as SVG.

use std::path::Path;

use plotters::prelude::*;

/// Draws one cumulative error curve per `(label, errors)` on one chart.
pub fn error_cdf_svg(
    path: &Path,
    title: &str,
    curves: &[(String, Vec<f64>)],
) -> anyhow::Result<()> {
    let max_error = curves
        .iter()
        .flat_map(|(_, e)| e.iter().copied())
        .fold(1.0f64, f64::max)
        .min(12.0);
    let root = SVGBackend::new(path, (800, 520)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d(0.0..max_error, 0.0..1.0)?;
    chart
        .configure_mesh()
        .x_desc("error (cells)")
        .y_desc("share of fixes with at most this error")
        .draw()?;
    for (i, (label, errors)) in curves.iter().enumerate() {
        let mut sorted = errors.clone();
        sorted.sort_by(f64::total_cmp);
        let n = sorted.len() as f64;
        let colour = Palette99::pick(i).stroke_width(2);
        let points = sorted
            .iter()
            .enumerate()
            .map(|(k, &e)| (e.min(max_error), (k + 1) as f64 / n));
        chart
            .draw_series(LineSeries::new(points, colour))?
            .label(label.as_str())
            .legend(move |(x, y)| {
                PathElement::new([(x, y), (x + 20, y)], Palette99::pick(i).stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .position(SeriesLabelPosition::LowerRight)
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .draw()?;
    root.present()?;
    Ok(())
}
