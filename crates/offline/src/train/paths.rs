//! The path data set: walks as frames, with their source/destination class.
//!
//! Classes are the distinct (source, destination) pairs with at least
//! `min_class_walks` walks, sorted; walks of rarer pairs (one-off walks between
//! random cells) have no class: they train the conditional generator only.

use std::collections::BTreeMap;
use std::path::Path;

use ndarray::Array2;

use super::frame::{Frame, FrameError};
use super::trajectory::Trajectory;
use crate::model::PathClass;
use crate::site::Site;

pub struct PathSet {
    pub width: u16,
    pub height: u16,
    pub walks: Vec<PathClass>,
    /// One 0/1 frame per walk, `W·H` columns.
    pub frames: Array2<f32>,
    pub classes: Vec<PathClass>,
    /// Index into `classes` per walk, when its pair is a class.
    pub labels: Vec<Option<usize>>,
}

impl PathSet {
    pub fn from_trajectories(site: &Site, walks: &[Trajectory], min_class_walks: usize) -> PathSet {
        let frames: Vec<Frame> = walks.iter().map(|w| w.frame(site)).collect();
        let pairs = walks
            .iter()
            .map(|w| PathClass {
                source: w.source(),
                destination: w.destination(),
            })
            .collect();
        PathSet::build(site, pairs, &frames, min_class_walks)
    }

    /// Frames from the paper's CSVs (every `*.csv` in `dir`, sorted by name);
    /// each frame's class is its two endpoints in row-major order.
    pub fn from_frame_dir(
        site: &Site,
        dir: &Path,
        min_class_walks: usize,
    ) -> Result<PathSet, FrameError> {
        let read_dir = |source| FrameError::Read {
            path: dir.to_owned(),
            source,
        };
        let mut files: Vec<_> = std::fs::read_dir(dir)
            .map_err(read_dir)?
            .map(|e| e.map(|e| e.path()))
            .collect::<Result<_, _>>()
            .map_err(read_dir)?;
        files.retain(|p| p.extension().is_some_and(|e| e == "csv"));
        files.sort();
        let mut frames = Vec::with_capacity(files.len());
        let mut pairs = Vec::with_capacity(files.len());
        for file in &files {
            let frame = Frame::read_csv(file, site)?;
            let ends = frame.endpoints();
            let [source, destination] = ends[..] else {
                return Err(FrameError::Shape {
                    path: file.clone(),
                    reason: format!(
                        "the path has {} end cells (cells with one neighbour on the path); \
                         a frame must be one simple walk with two ends",
                        ends.len()
                    ),
                });
            };
            pairs.push(PathClass {
                source,
                destination,
            });
            frames.push(frame);
        }
        Ok(PathSet::build(site, pairs, &frames, min_class_walks))
    }

    fn build(
        site: &Site,
        walks: Vec<PathClass>,
        frames: &[Frame],
        min_class_walks: usize,
    ) -> PathSet {
        let cells = usize::from(site.width()) * usize::from(site.height());
        let mut matrix = Array2::zeros((frames.len(), cells));
        for (mut row, frame) in matrix.rows_mut().into_iter().zip(frames) {
            frame.write_values(1.0, 0.0, row.as_slice_mut().expect("standard layout"));
        }
        let mut counts: BTreeMap<PathClass, usize> = BTreeMap::new();
        for &w in &walks {
            *counts.entry(w).or_default() += 1;
        }
        let classes: Vec<PathClass> = counts
            .into_iter()
            .filter(|&(_, n)| n >= min_class_walks)
            .map(|(c, _)| c)
            .collect();
        let labels = walks
            .iter()
            .map(|w| classes.binary_search(w).ok())
            .collect();
        PathSet {
            width: site.width(),
            height: site.height(),
            walks,
            frames: matrix,
            classes,
            labels,
        }
    }

    /// Rows of walks that belong to a class.
    pub(crate) fn classed_rows(&self) -> Vec<usize> {
        (0..self.walks.len())
            .filter(|&r| self.labels[r].is_some())
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::site::Cell;
    use std::io::Write;

    fn site() -> Site {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n####\n####\n'''\n";
        Site::parse(text, Path::new("t.toml")).unwrap()
    }

    fn walk(cells: &[[u16; 2]]) -> Trajectory {
        Trajectory {
            site: "t".into(),
            device: "d".into(),
            cells: cells.iter().map(|&c| c.into()).collect(),
            times: (0..cells.len()).map(|t| t as f64).collect(),
            profile: None,
            feedback: None,
            positions_m: None,
        }
    }

    #[test]
    fn classes_are_the_frequent_pairs() {
        let walks = vec![
            walk(&[[0, 0], [1, 0], [2, 0]]),
            walk(&[[0, 0], [1, 1], [2, 0]]),
            walk(&[[3, 1], [2, 1]]),
        ];
        let set = PathSet::from_trajectories(&site(), &walks, 2);
        assert_eq!(
            set.classes,
            vec![PathClass {
                source: Cell::new(0, 0),
                destination: Cell::new(2, 0)
            }]
        );
        assert_eq!(set.labels, vec![Some(0), Some(0), None]);
        assert_eq!(set.classed_rows(), vec![0, 1]);
        assert_eq!(
            set.frames.row(1).to_vec(),
            vec![1., 0., 1., 0., 0., 1., 0., 0.]
        );
    }

    #[test]
    fn frame_csvs_get_their_class_from_their_ends() {
        let dir = tempfile::tempdir().unwrap();
        for (name, text) in [
            ("a.csv", "1,1,1,0\n0,0,0,0\n"),
            ("b.csv", "0,0,0,1\n1,1,1,0\n"),
        ] {
            std::fs::File::create(dir.path().join(name))
                .unwrap()
                .write_all(text.as_bytes())
                .unwrap();
        }
        let set = PathSet::from_frame_dir(&site(), dir.path(), 1).unwrap();
        assert_eq!(set.walks[1].source, Cell::new(3, 0));
        assert_eq!(set.walks[1].destination, Cell::new(0, 1));
        assert_eq!(set.classes.len(), 2);
        std::fs::write(dir.path().join("c.csv"), "1,0,1,0\n0,0,0,0\n").unwrap();
        let err = PathSet::from_frame_dir(&site(), dir.path(), 1)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("c.csv: the path has 0 end cells"), "{err}");
    }
}
