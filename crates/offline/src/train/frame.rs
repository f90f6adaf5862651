//! Path frames: a walk drawn on the site grid as a `W × H` matrix of 0/1, the
//! form the paper's GAN and path classifier learn from.
//!
//! A frame forgets order and timing: only which cells the walk touched. Its
//! endpoints are recovered as the path cells with exactly one 8-neighbour on
//! the path, which is how frames read from the paper's CSVs get their class.
//!
//! The paper's frame CSV: one file per path, `H` lines (rows, `y` from the top)
//! of `W` values (`x` from the left), each `0` or `1`, separated by commas or
//! whitespace.

use std::path::{Path, PathBuf};

use crate::site::{Cell, Site};

/// A `width × height` grid of path cells, row-major.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Frame {
    width: u16,
    height: u16,
    cells: Vec<bool>,
}

#[derive(Debug, thiserror::Error)]
pub enum FrameError {
    #[error("{path}: cannot read the frame: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}:{line}: {reason}")]
    Parse {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    #[error("{path}: {reason}")]
    Shape { path: PathBuf, reason: String },
}

impl Frame {
    pub(crate) fn empty(width: u16, height: u16) -> Frame {
        Frame {
            width,
            height,
            cells: vec![false; usize::from(width) * usize::from(height)],
        }
    }

    /// The frame of a walk through `cells` on `site` (cells off the grid are
    /// ignored; callers validate walks first).
    pub(crate) fn from_cells(site: &Site, cells: &[Cell]) -> Frame {
        let mut frame = Frame::empty(site.width(), site.height());
        for &c in cells {
            if site.contains(c) {
                frame.cells[site.grid_index(c)] = true;
            }
        }
        frame
    }

    /// A frame from model output or any row-major values: a cell is on the path
    /// when its value is above `threshold`.
    #[cfg(test)]
    pub(crate) fn from_values(width: u16, height: u16, values: &[f32], threshold: f32) -> Frame {
        assert_eq!(values.len(), usize::from(width) * usize::from(height));
        Frame {
            width,
            height,
            cells: values.iter().map(|&v| v > threshold).collect(),
        }
    }

    pub(crate) fn get(&self, cell: Cell) -> bool {
        cell.x < self.width
            && cell.y < self.height
            && self.cells[usize::from(cell.y) * usize::from(self.width) + usize::from(cell.x)]
    }

    /// The path cells, row-major.
    pub(crate) fn path_cells(&self) -> Vec<Cell> {
        let w = usize::from(self.width);
        self.cells
            .iter()
            .enumerate()
            .filter(|(_, on)| **on)
            .map(|(i, _)| Cell::new((i % w) as u16, (i / w) as u16))
            .collect()
    }

    /// Path cells with exactly one 8-neighbour on the path, row-major. A clean
    /// walk has two; loops and blobs have other counts.
    pub(crate) fn endpoints(&self) -> Vec<Cell> {
        self.path_cells()
            .into_iter()
            .filter(|&c| {
                let mut neighbours = 0;
                for dy in -1i32..=1 {
                    for dx in -1i32..=1 {
                        let (x, y) = (i32::from(c.x) + dx, i32::from(c.y) + dy);
                        if (dx, dy) != (0, 0)
                            && x >= 0
                            && y >= 0
                            && self.get(Cell::new(x as u16, y as u16))
                        {
                            neighbours += 1;
                        }
                    }
                }
                neighbours == 1
            })
            .collect()
    }

    /// The frame as network input: `on` for path cells, `off` for the rest.
    pub fn write_values(&self, on: f32, off: f32, out: &mut [f32]) {
        for (o, &c) in out.iter_mut().zip(&self.cells) {
            *o = if c { on } else { off };
        }
    }

    /// Reads one of the paper's frame CSVs and checks it has `site`'s grid size.
    pub(crate) fn read_csv(path: &Path, site: &Site) -> Result<Frame, FrameError> {
        let text = std::fs::read_to_string(path).map_err(|source| FrameError::Read {
            path: path.to_owned(),
            source,
        })?;
        let (w, h) = (usize::from(site.width()), usize::from(site.height()));
        let mut cells = Vec::with_capacity(w * h);
        let mut rows = 0;
        for (i, line) in text.lines().enumerate() {
            let line = line.trim();
            if line.is_empty() {
                continue;
            }
            let parse = |reason: String| FrameError::Parse {
                path: path.to_owned(),
                line: i + 1,
                reason,
            };
            let values: Vec<&str> = line
                .split(|c: char| c == ',' || c.is_whitespace())
                .filter(|v| !v.is_empty())
                .collect();
            if values.len() != w {
                return Err(parse(format!(
                    "{} values, but the site's grid is {w} cells wide ({w}×{h}); \
                     write one line per row of {w} values",
                    values.len()
                )));
            }
            for (x, v) in values.iter().enumerate() {
                cells.push(match *v {
                    "0" | "0.0" => false,
                    "1" | "1.0" => true,
                    other => {
                        return Err(parse(format!("column {x}: {other:?} is not 0 or 1")));
                    }
                });
            }
            rows += 1;
        }
        if rows != h {
            return Err(FrameError::Shape {
                path: path.to_owned(),
                reason: format!(
                    "{rows} rows, but the site's grid is {h} cells high ({w}×{h}); \
                     is the frame for another site?"
                ),
            });
        }
        Ok(Frame {
            width: site.width(),
            height: site.height(),
            cells,
        })
    }

    /// The frame as CSV, the layout [`Frame::read_csv`] reads.
    #[cfg(test)]
    pub(crate) fn to_csv(&self) -> String {
        let mut out = String::new();
        for row in self.cells.chunks(usize::from(self.width)) {
            let line: Vec<&str> = row.iter().map(|&c| if c { "1" } else { "0" }).collect();
            out.push_str(&line.join(","));
            out.push('\n');
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    fn site() -> Site {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n####\n####\n####\n'''\n";
        Site::parse(text, Path::new("t.toml")).unwrap()
    }

    #[test]
    fn a_walk_round_trips_through_csv_and_keeps_its_endpoints() {
        let site = site();
        let walk = [
            Cell::new(0, 0),
            Cell::new(1, 1),
            Cell::new(2, 1),
            Cell::new(3, 2),
        ];
        let frame = Frame::from_cells(&site, &walk);
        assert_eq!(frame.endpoints(), vec![Cell::new(0, 0), Cell::new(3, 2)]);
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(frame.to_csv().as_bytes()).unwrap();
        assert_eq!(Frame::read_csv(f.path(), &site).unwrap(), frame);
        let mut values = vec![0.0; 12];
        frame.write_values(1.0, -1.0, &mut values);
        assert_eq!(Frame::from_values(4, 3, &values, 0.0), frame);
    }

    #[test]
    fn refuses_frames_of_another_size_or_with_other_values() {
        let site = site();
        let read = |text: &str| {
            let mut f = tempfile::NamedTempFile::new().unwrap();
            f.write_all(text.as_bytes()).unwrap();
            Frame::read_csv(f.path(), &site).unwrap_err().to_string()
        };
        assert!(read("0,0,0\n0,0,0\n0,0,0\n").contains(":1: 3 values, but the site's grid is 4"));
        assert!(read("0 0 0 0\n0 0 0 0\n").contains("2 rows"));
        assert!(read("0,0,0,0\n0,2,0,0\n0,0,0,0\n").contains(":2: column 1: \"2\""));
    }
}
