//! A site for a recorded scene, built rather than drawn by hand: the grid
//! covers where people walked (plus a margin) or the obstacle image's ground,
//! at the chosen cell size, in the scene's own world frame (`origin_m`,
//! `y_axis`), so the scene's walks land on it through the site's transform.
//!
//! Which cells are walkable:
//! - with an obstacle image (a `map.png` and the homography taking its pixels
//!   to world metres): every cell holding an obstacle pixel is blocked (thin
//!   walls of one or two pixels still block the cells they cross, which a
//!   test of cell centres alone would miss), and so is every cell whose
//!   centre falls outside the image (ground nobody mapped);
//! - without one: the cells any walk passes through (the supercover of each
//!   step between two recorded points), everything else blocked. Where people
//!   never walked nothing says it is open, so nothing is claimed.

use std::fmt::Write as _;
use std::path::Path;

use super::{Homography, Track};
use crate::plan::anyangle::traverse;
use crate::site::{Cell, Site, YAxis};

/// Which pixels of an obstacle image are obstacles.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Obstacles {
    /// Dark pixels (below mid-grey).
    Dark,
    /// Light pixels (mid-grey and above): the ETH `map.png` files draw their
    /// walls white on black.
    Light,
}

/// An obstacle image with its pixel → world homography.
pub struct ObstacleImage {
    pub pixels: image::GrayImage,
    /// `[column, row]` pixel → world metres.
    pub to_world: Homography,
    pub obstacles: Obstacles,
}

impl ObstacleImage {
    pub fn load(path: &Path, to_world: Homography, obstacles: Obstacles) -> anyhow::Result<Self> {
        let pixels = image::open(path)
            .map_err(|e| anyhow::anyhow!("{}: cannot read the image: {e}", path.display()))?
            .to_luma8();
        Ok(ObstacleImage {
            pixels,
            to_world,
            obstacles,
        })
    }

    fn is_obstacle(&self, value: u8) -> bool {
        match self.obstacles {
            Obstacles::Dark => value < 128,
            Obstacles::Light => value >= 128,
        }
    }

    /// The world bounding box of the image's four corners.
    fn extent(&self) -> Option<([f64; 2], [f64; 2])> {
        let (w, h) = (
            f64::from(self.pixels.width()),
            f64::from(self.pixels.height()),
        );
        let corners = [[0.0, 0.0], [w, 0.0], [0.0, h], [w, h]]
            .iter()
            .map(|&p| self.to_world.apply(p))
            .collect::<Option<Vec<_>>>()?;
        Some(bounds(corners.into_iter()))
    }
}

/// What to build.
pub struct Scene<'a> {
    pub name: String,
    pub cell_m: f64,
    pub y_axis: YAxis,
    /// Metres added around the walks' bounding box.
    pub margin_m: f64,
    pub image: Option<&'a ObstacleImage>,
    /// The scene's walks: they set the extent (with the margin) and, without
    /// an image, the walkable cells.
    pub walks: &'a [Track],
    /// How the site was built, for the file's header comment.
    pub command: String,
}

/// The largest grid built (cells): past it, ask for bigger cells.
const MAX_CELLS: usize = 4_000_000;

fn bounds(points: impl Iterator<Item = [f64; 2]>) -> ([f64; 2], [f64; 2]) {
    points.fold(
        ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]),
        |(lo, hi), [x, y]| ([lo[0].min(x), lo[1].min(y)], [hi[0].max(x), hi[1].max(y)]),
    )
}

/// The site file (TOML) for `scene`, and the site it parses to.
pub fn build(scene: &Scene) -> anyhow::Result<(String, Site)> {
    anyhow::ensure!(
        scene.cell_m.is_finite() && scene.cell_m > 0.0,
        "--cell-m must be a positive number of metres"
    );
    let (lo, hi) = if scene.walks.iter().any(|t| !t.points.is_empty()) {
        let (lo, hi) = bounds(
            scene
                .walks
                .iter()
                .flat_map(|t| t.points.iter().map(|p| p.1)),
        );
        let m = scene.margin_m;
        ([lo[0] - m, lo[1] - m], [hi[0] + m, hi[1] + m])
    } else {
        scene.image.and_then(ObstacleImage::extent).ok_or_else(|| {
            anyhow::anyhow!("no walks and no image to take the scene's extent from")
        })?
    };
    let cells = |span: f64| (span / scene.cell_m).ceil().max(1.0);
    let (width, height) = (cells(hi[0] - lo[0]), cells(hi[1] - lo[1]));
    anyhow::ensure!(
        width * height <= MAX_CELLS as f64 && width <= f64::from(u16::MAX),
        "the scene is {:.0} × {:.0} m, {width:.0} × {height:.0} cells of {} m; \
         more than {MAX_CELLS} cells: choose a larger --cell-m",
        hi[0] - lo[0],
        hi[1] - lo[1],
        scene.cell_m
    );
    let (width, height) = (width as usize, height as usize);
    let origin = match scene.y_axis {
        YAxis::Up => [lo[0], hi[1]],
        YAxis::Down => [lo[0], lo[1]],
    };
    // The frame alone, every cell open: its transform places what follows.
    let open_row = "#".repeat(width);
    let frame = site_text(scene, origin, &vec![open_row; height].join("\n"));
    let grid = Site::parse(&frame, Path::new("(scene frame)"))?;
    let mut walkable = vec![scene.image.is_some(); width * height];
    let index = |c: Cell| usize::from(c.y) * width + usize::from(c.x);
    match scene.image {
        Some(image) => {
            let to_image = image
                .to_world
                .inverse()
                .ok_or_else(|| anyhow::anyhow!("the homography cannot be inverted (singular)"))?;
            let (iw, ih) = (
                f64::from(image.pixels.width()),
                f64::from(image.pixels.height()),
            );
            for &cell in grid.open_cells() {
                let inside = to_image
                    .apply(grid.world_of_cell(cell))
                    .is_some_and(|[u, v]| (0.0..iw).contains(&u) && (0.0..ih).contains(&v));
                if !inside {
                    walkable[index(cell)] = false;
                }
            }
            for (u, v, p) in image.pixels.enumerate_pixels() {
                if !image.is_obstacle(p.0[0]) {
                    continue;
                }
                if let Some(cell) = image
                    .to_world
                    .apply([f64::from(u), f64::from(v)])
                    .and_then(|w| grid.cell_of_world(w))
                {
                    walkable[index(cell)] = false;
                }
            }
        }
        None => {
            for track in scene.walks {
                for w in track.points.windows(2) {
                    let (a, b) = (grid.grid_of_world(w[0].1), grid.grid_of_world(w[1].1));
                    for [x, y] in traverse(a, b).cells {
                        if (0..width as i64).contains(&x) && (0..height as i64).contains(&y) {
                            walkable[y as usize * width + x as usize] = true;
                        }
                    }
                }
            }
        }
    }
    let map: Vec<String> = walkable
        .chunks(width)
        .map(|row| row.iter().map(|&w| if w { '#' } else { '.' }).collect())
        .collect();
    let text = site_text(scene, origin, &map.join("\n"));
    let site = Site::parse(&text, Path::new("(built site)"))?;
    Ok((text, site))
}

fn site_text(scene: &Scene, origin: [f64; 2], map: &str) -> String {
    let mut text = String::new();
    let _ = writeln!(text, "# Built by: {}", scene.command);
    let _ = writeln!(
        text,
        "# Walkable: {}",
        if scene.image.is_some() {
            "cells without an obstacle pixel, inside the image"
        } else {
            "the cells the walks passed through"
        }
    );
    let _ = writeln!(text, "name = {:?}", scene.name);
    let _ = writeln!(text, "cell_m = {}", scene.cell_m);
    let _ = writeln!(text, "origin_m = [{:.3}, {:.3}]", origin[0], origin[1]);
    let _ = writeln!(text, "y_axis = \"{}\"", scene.y_axis);
    let _ = writeln!(text, "map = '''\n{map}\n'''");
    text
}

#[cfg(test)]
mod tests {
    use super::*;

    fn track(points: &[[f64; 2]]) -> Track {
        Track {
            id: "a".into(),
            points: points
                .iter()
                .enumerate()
                .map(|(i, &p)| (i as f64, p))
                .collect(),
        }
    }

    fn scene<'a>(walks: &'a [Track], image: Option<&'a ObstacleImage>) -> Scene<'a> {
        Scene {
            name: "scene".into(),
            cell_m: 1.0,
            y_axis: YAxis::Up,
            margin_m: 1.0,
            image,
            walks,
            command: "test".into(),
        }
    }

    #[test]
    fn without_an_image_the_walked_cells_are_open() {
        let walks = [track(&[[0.5, 0.5], [4.5, 0.5]])];
        let (text, site) = build(&scene(&walks, None)).unwrap();
        assert!(text.contains("origin_m = [-0.500, 1.500]"), "{text}");
        // 4 m + 2 m of margin wide, 0 + 2 m high.
        assert_eq!((site.width(), site.height()), (6, 2));
        assert_eq!(site.open_cells().len(), 5);
        assert_eq!(site.cell_of_world([0.5, 0.5]), Some(Cell::new(1, 1)));
        assert!(site.walkable(Cell::new(1, 1)) && !site.walkable(Cell::new(1, 0)));
    }

    #[test]
    fn obstacle_pixels_block_their_cells() {
        // A 40 × 40 image, 0.1 m per pixel, with a light wall down column 20
        // for half the image: world x = u / 10, y = v / 10.
        let mut pixels = image::GrayImage::new(40, 40);
        for v in 0..20 {
            pixels.put_pixel(20, v, image::Luma([255]));
        }
        let image = ObstacleImage {
            pixels,
            to_world: Homography([[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 1.0]]),
            obstacles: Obstacles::Light,
        };
        let walks = [track(&[[0.5, 0.5], [3.5, 3.5]])];
        let (_, site) = build(&Scene {
            margin_m: 1.5,
            ..scene(&walks, Some(&image))
        })
        .unwrap();
        let at = |x: f64, y: f64| site.cell_of_world([x, y]).unwrap();
        assert!(!site.walkable(at(2.05, 1.5)), "the wall");
        assert!(site.walkable(at(2.05, 3.5)), "past the end of the wall");
        assert!(site.walkable(at(0.5, 0.5)));
        // The margin reaches past the image's edge: unmapped, so blocked.
        assert!(!site.walkable(at(-0.9, 0.5)));
    }
}
