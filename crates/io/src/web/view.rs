//! The site as the pages draw it: the final grid (map, obstacles and walls
//! rasterised), anchors and places in grid units and world metres, and where
//! the floor-plan image sits. Grid units (`[gx, gy]`, cell `[x, y]` spans
//! `x..x+1`, `y..y+1`, y down) are what the SVG is drawn in, whichever way
//! the site's world y runs.

use serde::Serialize;

use crate::site::{Cell, Site};

#[derive(Serialize)]
pub(super) struct SiteView {
    pub name: String,
    pub cell_m: f64,
    pub origin_m: [f64; 2],
    pub y_axis: String,
    pub width: u16,
    pub height: u16,
    /// One glyph per cell, row-major (`#` open, `.` blocked, `s`, `e`, `d`, `n`).
    pub tiles: String,
    pub walkable: usize,
    pub beacons: Vec<AnchorView>,
    pub gateways: Vec<AnchorView>,
    pub places: Vec<PlaceView>,
    pub floorplan: Option<FloorplanView>,
    pub map_hash: String,
}

#[derive(Serialize)]
pub(super) struct AnchorView {
    pub id: String,
    /// Where it is mounted, grid units and metres; none when the file does
    /// not say.
    pub grid: Option<[f64; 2]>,
    pub m: Option<[f64; 2]>,
}

#[derive(Serialize)]
pub(super) struct PlaceView {
    pub name: String,
    pub cell: Cell,
    pub label: Option<String>,
}

#[derive(Serialize)]
pub(super) struct FloorplanView {
    pub url: String,
    /// Pixels to grid units, an SVG `matrix(a, b, c, d, e, f)`.
    pub matrix: [f64; 6],
    pub width: u32,
    pub height: u32,
}

impl SiteView {
    /// The view of `site`; `floorplan_url` is where the page fetches the
    /// image (none when it cannot be shown).
    pub(super) fn new(site: &Site, floorplan_url: Option<&str>) -> SiteView {
        let anchor = |id: &str, mount: Option<crate::site::Mount>| AnchorView {
            id: id.to_owned(),
            grid: mount.map(|m| site.grid_of_world(m.at)),
            m: mount.map(|m| m.at),
        };
        let floorplan = site.floorplan().zip(floorplan_url).and_then(|(plan, url)| {
            let info = plan.probe().ok()?;
            Some(FloorplanView {
                url: url.to_owned(),
                matrix: plan.pixels_to_grid,
                width: info.width,
                height: info.height,
            })
        });
        SiteView {
            name: site.name.clone(),
            cell_m: site.cell_m,
            origin_m: site.origin_m(),
            y_axis: site.y_axis().to_string(),
            width: site.width(),
            height: site.height(),
            tiles: site.map_text().replace('\n', ""),
            walkable: site.open_cells().len(),
            beacons: site
                .beacons
                .iter()
                .map(|b| anchor(&b.id, b.mount))
                .collect(),
            gateways: site
                .gateways
                .iter()
                .map(|g| anchor(&g.id, g.mount))
                .collect(),
            places: site
                .places()
                .iter()
                .map(|(name, &cell)| PlaceView {
                    name: name.clone(),
                    cell,
                    label: site.label(cell),
                })
                .collect(),
            floorplan,
            map_hash: site.map_hash().to_owned(),
        }
    }
}
