//! Pictures of routes on the site grid, like the paper's path figures: open
//! cells light, blocked cells dark, attribute cells tinted, the route's cells
//! filled and joined, start and end marked. SVG or PNG by file extension; the
//! pictures carry no text, so PNG needs no font library.

use std::path::Path;

use plotters::coord::Shift;
use plotters::prelude::*;

use super::Route;
use crate::site::{Cell, Site, Tile};

/// Pixels per cell.
const CELL_PX: u32 = 24;

/// Draws `route` on `site` into `path` (`.svg` or `.png`).
pub fn draw(site: &Site, route: &Route, path: &Path) -> anyhow::Result<()> {
    let size = (
        u32::from(site.width()) * CELL_PX,
        u32::from(site.height()) * CELL_PX,
    );
    match path.extension().and_then(|e| e.to_str()) {
        Some("svg") => paint(
            site,
            route,
            &SVGBackend::new(path, size).into_drawing_area(),
        ),
        Some("png") => paint(
            site,
            route,
            &BitMapBackend::new(path, size).into_drawing_area(),
        ),
        _ => anyhow::bail!("{}: give the picture a .svg or .png name", path.display()),
    }
}

fn paint<DB: DrawingBackend>(
    site: &Site,
    route: &Route,
    area: &DrawingArea<DB, Shift>,
) -> anyhow::Result<()>
where
    DB::ErrorType: 'static,
{
    area.fill(&WHITE)?;
    let px = |c: Cell| {
        (
            i32::from(c.x) * CELL_PX as i32,
            i32::from(c.y) * CELL_PX as i32,
        )
    };
    let centre = |c: Cell| {
        let (x, y) = px(c);
        (x + CELL_PX as i32 / 2, y + CELL_PX as i32 / 2)
    };
    let square = |c: Cell, style: ShapeStyle| {
        let (x, y) = px(c);
        Rectangle::new(
            [
                (x + 1, y + 1),
                (x + CELL_PX as i32 - 1, y + CELL_PX as i32 - 1),
            ],
            style,
        )
    };
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
    area.present()?;
    Ok(())
}
