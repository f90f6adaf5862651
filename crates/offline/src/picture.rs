//! Pictures of routes on the site grid, like the paper's path figures: open
//! cells light, blocked cells dark, attribute cells tinted, the route's cells
//! filled and joined, start and end marked. SVG or PNG by file extension; the
//! pictures carry no text, so PNG needs no font library.
//!
//! [`draw_samples`] draws a sheet for the paper's Fig. 9: each generated frame
//! (its path cells shaded by the generator's value) beside the route the
//! planner made of it.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use crate::plan::Route;
use crate::site::{Cell, Site, Tile};

/// Pixels per cell.
const CELL_PX: u32 = 24;
/// Gap between the panels of a sheet, pixels.
const GAP_PX: u32 = CELL_PX / 2;

/// Draws `route` on `site` into `path` (`.svg` or `.png`).
pub fn draw(site: &Site, route: &Route, path: &Path) -> anyhow::Result<()> {
    draw_panels(site, &[Panel::Route(route)], 1, path)
}

/// Draws one row per `(frame, route)` sample, the frame on the left and the
/// route on the right, into `path` (`.svg` or `.png`).
pub(crate) fn draw_samples(
    site: &Site,
    samples: &[(&[f32], &Route)],
    path: &Path,
) -> anyhow::Result<()> {
    let panels: Vec<Panel> = samples
        .iter()
        .flat_map(|&(frame, route)| [Panel::Frame(frame), Panel::Route(route)])
        .collect();
    draw_panels(site, &panels, 2, path)
}

/// What one site-sized panel shows.
enum Panel<'a> {
    Route(&'a Route),
    /// A generated frame, `W·H` values; path cells are > 0.
    Frame(&'a [f32]),
}

/// Draws `panels` row by row, `columns` per row, with a gap between them.
fn draw_panels(site: &Site, panels: &[Panel], columns: usize, path: &Path) -> anyhow::Result<()> {
    let (w, h) = (
        u32::from(site.width()) * CELL_PX,
        u32::from(site.height()) * CELL_PX,
    );
    let rows = panels.len().div_ceil(columns).max(1) as u32;
    let columns = columns as u32;
    let size = (
        columns * w + (columns - 1) * GAP_PX,
        rows * h + (rows - 1) * GAP_PX,
    );
    match path.extension().and_then(|e| e.to_str()) {
        Some("svg") => paint_panels(
            site,
            panels,
            columns,
            &SVGBackend::new(path, size).into_drawing_area(),
        ),
        Some("png") => paint_panels(
            site,
            panels,
            columns,
            &BitMapBackend::new(path, size).into_drawing_area(),
        ),
        _ => anyhow::bail!("{}: give the picture a .svg or .png name", path.display()),
    }
}

fn paint_panels<DB: DrawingBackend>(
    site: &Site,
    panels: &[Panel],
    columns: u32,
    area: &DrawingArea<DB, Shift>,
) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    area.fill(&WHITE)?;
    let (w, h) = (
        u32::from(site.width()) * CELL_PX,
        u32::from(site.height()) * CELL_PX,
    );
    for (i, panel) in panels.iter().enumerate() {
        let (col, row) = (i as u32 % columns, i as u32 / columns);
        let at = area
            .clone()
            .shrink((col * (w + GAP_PX), row * (h + GAP_PX)), (w, h));
        match panel {
            Panel::Route(route) => paint_route(site, route, &at)?,
            Panel::Frame(frame) => paint_frame(site, frame, &at)?,
        }
    }
    area.present()?;
    Ok(())
}

fn px(c: Cell) -> (i32, i32) {
    (
        i32::from(c.x) * CELL_PX as i32,
        i32::from(c.y) * CELL_PX as i32,
    )
}

fn centre(c: Cell) -> (i32, i32) {
    let (x, y) = px(c);
    (x + CELL_PX as i32 / 2, y + CELL_PX as i32 / 2)
}

fn square(c: Cell, style: ShapeStyle) -> Rectangle<(i32, i32)> {
    let (x, y) = px(c);
    Rectangle::new(
        [
            (x + 1, y + 1),
            (x + CELL_PX as i32 - 1, y + CELL_PX as i32 - 1),
        ],
        style,
    )
}

/// The site's tiles: open cells light, blocked dark, attributes tinted.
fn paint_tiles<DB: DrawingBackend>(site: &Site, area: &DrawingArea<DB, Shift>) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    for y in 0..site.height() {
        for x in 0..site.width() {
            let c = Cell::new(x, y);
            let colour = match site.tile(c) {
                Some(Tile::Blocked) | None => RGBColor(60, 60, 60),
                Some(Tile::Open) => RGBColor(235, 235, 235),
                Some(Tile::Stairs) => RGBColor(230, 190, 150),
                Some(Tile::Elevator) => RGBColor(170, 210, 240),
                Some(Tile::Door) => RGBColor(200, 230, 180),
                Some(Tile::Narrow) => RGBColor(240, 220, 130),
            };
            area.draw(&square(c, colour.filled()))?;
        }
    }
    Ok(())
}

/// The frame's path cells (value > 0) in orange, stronger where the value is
/// higher; one on a dark (blocked) tile is what the deviation score counts.
fn paint_frame<DB: DrawingBackend>(
    site: &Site,
    frame: &[f32],
    area: &DrawingArea<DB, Shift>,
) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    paint_tiles(site, area)?;
    for y in 0..site.height() {
        for x in 0..site.width() {
            let c = Cell::new(x, y);
            let v = frame[site.grid_index(c)];
            if v > 0.0 {
                let strength = 0.35 + 0.65 * f64::from(v.min(1.0));
                area.draw(&square(c, RGBColor(230, 120, 20).mix(strength).filled()))?;
            }
        }
    }
    Ok(())
}

fn paint_route<DB: DrawingBackend>(
    site: &Site,
    route: &Route,
    area: &DrawingArea<DB, Shift>,
) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    paint_tiles(site, area)?;
    for &c in &route.cells {
        area.draw(&square(c, RGBColor(250, 250, 250).filled()))?;
        area.draw(&square(c, BLUE.stroke_width(2)))?;
    }
    area.draw(&PathElement::new(
        route.cells.iter().map(|&c| centre(c)).collect::<Vec<_>>(),
        BLUE.stroke_width(3),
    ))?;
    if let (Some(&first), Some(&last)) = (route.cells.first(), route.cells.last()) {
        area.draw(&Circle::new(
            centre(first),
            CELL_PX as i32 / 3,
            GREEN.filled(),
        ))?;
        area.draw(&Circle::new(centre(last), CELL_PX as i32 / 3, RED.filled()))?;
    }
    Ok(())
}
