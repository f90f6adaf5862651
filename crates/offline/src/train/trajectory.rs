//! Trajectories: walks people made on a site, the training data of the path
//! models. JSON Lines, one walk per line (format in `docs/trajectories.md`):
//!
//! ```text
//! {"site":"waldo-library","device":"sim-0001","cells":[[11,0],[12,1]],"times":[1767225600.0,1767225601.2]}
//! ```
//!
//! Reading validates every walk against the site (same site name, walkable
//! cells, 8-connected steps, one time per cell, times not going back) and names
//! the file, line and field of the first problem.

use std::fs::File;
use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::frame::Frame;
use crate::plan::Connectivity;
use crate::site::{Cell, Site};

/// One walk.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Trajectory {
    /// The site's `name`.
    pub site: String,
    /// Who walked (an opaque id).
    pub device: String,
    /// The cells in walking order, each an 8-neighbour of the one before.
    pub cells: Vec<Cell>,
    /// When each cell was reached, Unix seconds.
    pub times: Vec<f64>,
    /// The route profile the walker used, when known (e.g. `wheelchair`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile: Option<String>,
    /// How the walker rated the route, 0 (bad) to 1 (good), when asked.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub feedback: Option<f64>,
    /// The recorded positions the cells were made from (world metres, the
    /// site's frame), when the walk was imported from a recording: routes
    /// are judged against where the person actually walked, not against the
    /// cell centres, which a grid route would match for free.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub positions_m: Option<Vec<[f64; 2]>>,
}

#[derive(Debug, thiserror::Error)]
pub enum TrajectoryError {
    #[error("{path}: cannot read the trajectories: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}:{line}: {reason}")]
    Line {
        path: PathBuf,
        line: usize,
        reason: String,
    },
}

impl Trajectory {
    pub fn source(&self) -> Cell {
        self.cells[0]
    }

    pub fn destination(&self) -> Cell {
        *self.cells.last().expect("validated walks have cells")
    }

    /// The walk's frame on `site`.
    pub fn frame(&self, site: &Site) -> Frame {
        Frame::from_cells(site, &self.cells)
    }

    /// Why this walk cannot be used on `site`, naming the field.
    pub(crate) fn check(&self, site: &Site) -> Result<(), String> {
        if self.site != site.name {
            return Err(format!(
                "`site` is {:?}, but the site file is {:?}; these walks belong to another site",
                self.site, site.name
            ));
        }
        if self.cells.len() < 2 {
            return Err("`cells` needs at least two cells (a source and a destination)".into());
        }
        if self.times.len() != self.cells.len() {
            return Err(format!(
                "`times` has {} entries but `cells` has {}; give one time per cell",
                self.times.len(),
                self.cells.len()
            ));
        }
        if let Some(c) = self.cells.iter().find(|&&c| !site.walkable(c)) {
            return Err(format!(
                "`cells` contains {c}, which is not a walkable cell of the site"
            ));
        }
        if let Some(w) = self
            .cells
            .windows(2)
            .find(|w| !Connectivity::Eight.step_ok(site, w[0], w[1]))
        {
            return Err(format!(
                "`cells` steps from {} to {}, which are not neighbouring walkable cells",
                w[0], w[1]
            ));
        }
        if let Some(i) = self.times.iter().position(|t| !t.is_finite()) {
            return Err(format!("`times`[{i}] is not a finite number of seconds"));
        }
        if let Some(i) = self.times.windows(2).position(|w| w[1] < w[0]) {
            return Err(format!(
                "`times`[{}] is earlier than `times`[{i}]; times must not go back",
                i + 1
            ));
        }
        if let Some(f) = self.feedback
            && !(0.0..=1.0).contains(&f)
        {
            return Err(format!("`feedback` is {f}; it must be between 0 and 1"));
        }
        if let Some(points) = &self.positions_m {
            if let Some(i) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
                return Err(format!(
                    "`positions_m`[{i}] is not two finite numbers of metres"
                ));
            }
            if points.is_empty() {
                return Err("`positions_m` is empty; leave it out when unknown".into());
            }
        }
        Ok(())
    }
}

/// Reads and validates every walk of a JSON Lines file for `site`.
pub fn read(path: &Path, site: &Site) -> Result<Vec<Trajectory>, TrajectoryError> {
    let file = File::open(path).map_err(|source| TrajectoryError::Read {
        path: path.to_owned(),
        source,
    })?;
    let mut walks = Vec::new();
    for (i, line) in BufReader::new(file).lines().enumerate() {
        let line = line.map_err(|source| TrajectoryError::Read {
            path: path.to_owned(),
            source,
        })?;
        if line.trim().is_empty() {
            continue;
        }
        let error = |reason: String| TrajectoryError::Line {
            path: path.to_owned(),
            line: i + 1,
            reason,
        };
        let walk: Trajectory = serde_json::from_str(&line).map_err(|e| {
            error(format!(
                "{e}; each line must be one walk (see docs/trajectories.md)"
            ))
        })?;
        walk.check(site).map_err(error)?;
        walks.push(walk);
    }
    Ok(walks)
}

/// Writes walks as JSON Lines.
pub fn write(mut out: impl Write, walks: &[Trajectory]) -> std::io::Result<()> {
    for walk in walks {
        serde_json::to_writer(&mut out, walk)?;
        out.write_all(b"\n")?;
    }
    out.flush()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn site() -> Site {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n###\n#.#\n'''\n";
        Site::parse(text, Path::new("t.toml")).unwrap()
    }

    fn read_text(text: &str) -> Result<Vec<Trajectory>, TrajectoryError> {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(text.as_bytes()).unwrap();
        read(f.path(), &site())
    }

    #[test]
    fn round_trips_and_draws_its_frame() {
        let walk = Trajectory {
            site: "t".into(),
            device: "d1".into(),
            cells: vec![Cell::new(0, 1), Cell::new(0, 0), Cell::new(1, 0)],
            times: vec![0.0, 1.0, 2.5],
            profile: None,
            feedback: Some(0.75),
            positions_m: None,
        };
        let mut buf = Vec::new();
        write(&mut buf, std::slice::from_ref(&walk)).unwrap();
        let text = String::from_utf8(buf).unwrap();
        assert_eq!(
            text,
            "{\"site\":\"t\",\"device\":\"d1\",\"cells\":[[0,1],[0,0],[1,0]],\"times\":[0.0,1.0,2.5],\"feedback\":0.75}\n"
        );
        let back = read_text(&text).unwrap();
        assert_eq!(back, vec![walk.clone()]);
        let frame = walk.frame(&site());
        assert_eq!(frame.path_cells().len(), 3);
        assert!(frame.get(Cell::new(1, 0)) && !frame.get(Cell::new(2, 0)));
    }

    #[test]
    fn names_the_line_and_field_of_a_bad_walk() {
        let good = r#"{"site":"t","device":"a","cells":[[0,0],[1,0]],"times":[0,1]}"#;
        let err = |line: &str| {
            read_text(&format!("{good}\n{line}\n"))
                .unwrap_err()
                .to_string()
        };
        assert!(
            err(r#"{"site":"u","device":"a","cells":[[0,0],[1,0]],"times":[0,1]}"#)
                .contains(":2: `site` is \"u\"")
        );
        assert!(
            err(r#"{"site":"t","device":"a","cells":[[0,0],[1,1]],"times":[0,1]}"#)
                .contains("[1, 1], which is not a walkable")
        );
        assert!(
            err(r#"{"site":"t","device":"a","cells":[[0,0],[2,0]],"times":[0,1]}"#)
                .contains("steps from [0, 0] to [2, 0]")
        );
        assert!(
            err(r#"{"site":"t","device":"a","cells":[[0,0],[1,0]],"times":[0]}"#)
                .contains("`times` has 1 entries")
        );
        assert!(
            err(r#"{"site":"t","device":"a","cells":[[0,0],[1,0]],"times":[2,1]}"#)
                .contains("`times`[1] is earlier")
        );
        assert!(
            err(r#"{"site":"t","device":"a","cells":[[0,0],[1,0]],"times":[0,1],"speed":2}"#)
                .contains(":2: unknown field `speed`")
        );
    }
}
