//! Line charts drawn with plotters as SVG, all in one style: the error CDF
//! (the paper's Fig. 7) and the deviation score against training iterations
//! (Fig. 10).

use std::ops::Range;
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
    let series: Vec<(String, Vec<(f64, f64)>)> = curves
        .iter()
        .map(|(label, errors)| {
            let mut sorted = errors.clone();
            sorted.sort_by(f64::total_cmp);
            let n = sorted.len() as f64;
            let points = sorted
                .iter()
                .enumerate()
                .map(|(k, &e)| (e.min(max_error), (k + 1) as f64 / n))
                .collect();
            (label.clone(), points)
        })
        .collect();
    draw(
        path,
        title,
        ("error (cells)", "share of fixes with at most this error"),
        (0.0..max_error, 0.0..1.0),
        &series,
        SeriesLabelPosition::LowerRight,
        false,
    )
}

/// Draws one line per `(label, points)`, each point marked, axes fitted to
/// the points (the y axis from 0).
pub(super) fn line_svg(
    path: &Path,
    title: &str,
    axes: (&str, &str),
    series: &[(String, Vec<(f64, f64)>)],
) -> anyhow::Result<()> {
    let points = || series.iter().flat_map(|(_, p)| p.iter().copied());
    let x_min = points().map(|p| p.0).fold(f64::INFINITY, f64::min);
    let x_max = points().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
    let y_max = points().map(|p| p.1).fold(0.0, f64::max);
    anyhow::ensure!(x_min.is_finite(), "{}: nothing to plot", path.display());
    // A single point or a flat line still gets a visible range.
    let x_range = if x_max > x_min {
        x_min..x_max
    } else {
        x_min - 1.0..x_max + 1.0
    };
    let y_range = 0.0..if y_max > 0.0 { y_max * 1.1 } else { 1.0 };
    draw(
        path,
        title,
        axes,
        (x_range, y_range),
        series,
        SeriesLabelPosition::UpperRight,
        true,
    )
}

fn draw(
    path: &Path,
    title: &str,
    (x_desc, y_desc): (&str, &str),
    (x_range, y_range): (Range<f64>, Range<f64>),
    series: &[(String, Vec<(f64, f64)>)],
    legend: SeriesLabelPosition,
    markers: bool,
) -> anyhow::Result<()> {
    let root = SVGBackend::new(path, (800, 520)).into_drawing_area();
    root.fill(&WHITE)?;
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(16)
        .x_label_area_size(44)
        .y_label_area_size(56)
        .build_cartesian_2d(x_range, y_range)?;
    chart
        .configure_mesh()
        .x_desc(x_desc)
        .y_desc(y_desc)
        .draw()?;
    for (i, (label, points)) in series.iter().enumerate() {
        let colour = Palette99::pick(i).stroke_width(2);
        chart
            .draw_series(LineSeries::new(points.iter().copied(), colour))?
            .label(label.as_str())
            .legend(move |(x, y)| {
                PathElement::new([(x, y), (x + 20, y)], Palette99::pick(i).stroke_width(2))
            });
        if markers {
            chart.draw_series(
                points
                    .iter()
                    .map(|&p| Circle::new(p, 3, Palette99::pick(i).filled())),
            )?;
        }
    }
    chart
        .configure_series_labels()
        .position(legend)
        .background_style(WHITE.mix(0.9))
        .border_style(BLACK)
        .draw()?;
    root.present()?;
    Ok(())
}
