//! How alike routes, walks and frames are. As sets of cells: the cell-set IoU
//! of a route against a person's walk (`human_iou_*`) and the Hamming distance
//! from a generated frame to its nearest training frame (`novelty`). As
//! shapes in metres ([`Polyline`], from [`crate::plan::lines`]): dynamic time warping and the discrete
//! Fréchet distance of a route against a walk, on both resampled at the same
//! spacing so that neither measure depends on how densely a line was drawn
//! (a route's three vertices and a walk's sixty cells cover the same ground).
//!
//! Both work on [`CellBits`], a frame as packed `u64` words (bit `i` = grid
//! index `i`, on the path). Hand-written rather than a bitset crate because
//! all it needs is AND/OR/XOR and `count_ones` over a few words: on the sample
//! site's 23 × 18 grid a frame is 7 words, so the nearest of ~2,000 training
//! frames costs ~14,000 word operations, a few microseconds per generated frame.

use std::collections::HashSet;

use crate::plan::frame::bright;
pub(crate) use crate::plan::lines::{Polyline, shape};
use crate::site::{Cell, Site};
use crate::train::trajectory::Trajectory;

/// The cells of a grid that are on a path, one bit each.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub(crate) struct CellBits(Vec<u64>);

impl CellBits {
    fn empty(site: &Site) -> CellBits {
        let cells = usize::from(site.width()) * usize::from(site.height());
        CellBits(vec![0; cells.div_ceil(64)])
    }

    /// The set of `cells` (a route's or a walk's; cells off the grid ignored).
    pub(crate) fn from_cells(site: &Site, cells: &[Cell]) -> CellBits {
        let mut bits = CellBits::empty(site);
        for &c in cells.iter().filter(|&&c| site.contains(c)) {
            let i = site.grid_index(c);
            bits.0[i / 64] |= 1 << (i % 64);
        }
        bits
    }

    /// A generated frame's path cells: values above 0, the threshold every
    /// planner uses ([`bright`]).
    pub(crate) fn from_frame(site: &Site, frame: &[f32]) -> CellBits {
        let mut bits = CellBits::empty(site);
        for i in (0..frame.len()).filter(|&i| bright(frame, i)) {
            bits.0[i / 64] |= 1 << (i % 64);
        }
        bits
    }

    /// Cells in exactly one of the two sets.
    pub(crate) fn hamming(&self, other: &CellBits) -> u32 {
        self.0
            .iter()
            .zip(&other.0)
            .map(|(a, b)| (a ^ b).count_ones())
            .sum()
    }

    /// |A ∩ B| / |A ∪ B|; 1 for two empty sets.
    pub(crate) fn iou(&self, other: &CellBits) -> f64 {
        let (mut both, mut either) = (0u32, 0u32);
        for (a, b) in self.0.iter().zip(&other.0) {
            both += (a & b).count_ones();
            either += (a | b).count_ones();
        }
        if either == 0 {
            1.0
        } else {
            f64::from(both) / f64::from(either)
        }
    }
}

/// Cell-set IoU of two cell sequences on `site` (order and repeats ignored).
pub(crate) fn cell_iou(site: &Site, a: &[Cell], b: &[Cell]) -> f64 {
    CellBits::from_cells(site, a).iou(&CellBits::from_cells(site, b))
}

/// The distinct frames of the walks a generator was trained on.
pub struct TrainingFrames {
    frames: Vec<CellBits>,
}

impl TrainingFrames {
    pub fn new(site: &Site, walks: &[Trajectory]) -> TrainingFrames {
        let distinct: HashSet<CellBits> = walks
            .iter()
            .map(|w| CellBits::from_cells(site, &w.cells))
            .collect();
        TrainingFrames {
            frames: distinct.into_iter().collect(),
        }
    }

    /// Distinct training frames.
    pub(crate) fn len(&self) -> usize {
        self.frames.len()
    }

    pub(crate) fn is_empty(&self) -> bool {
        self.frames.is_empty()
    }

    /// Cells by which `frame` differs from the training frame nearest to it;
    /// `None` without training frames.
    pub(crate) fn nearest_distance(&self, frame: &CellBits) -> Option<u32> {
        let mut best: Option<u32> = None;
        for t in &self.frames {
            let d = t.hamming(frame);
            if best.is_none_or(|b| d < b) {
                best = Some(d);
                if d == 0 {
                    break;
                }
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn site() -> Site {
        // 10 × 8 = 80 cells: frames span two words.
        let row = "##########\n";
        let text = format!(
            "name = \"t\"\ncell_m = 1.0\nmap = '''\n{}'''\n",
            row.repeat(8)
        );
        Site::parse(&text, Path::new("t.toml")).unwrap()
    }

    fn walk(site: &Site, cells: &[(u16, u16)]) -> Trajectory {
        Trajectory {
            site: site.name.clone(),
            device: "d".into(),
            cells: cells.iter().map(|&(x, y)| Cell::new(x, y)).collect(),
            times: (0..cells.len()).map(|t| t as f64).collect(),
            profile: None,
            feedback: None,
            positions_m: None,
        }
    }

    #[test]
    fn iou_of_a_route_with_itself_is_one_and_counts_shared_cells() {
        let s = site();
        let a: Vec<Cell> = (0..10).map(|x| Cell::new(x, 7)).collect();
        assert_eq!(cell_iou(&s, &a, &a), 1.0);
        // Order and repeats do not matter.
        let mut b = a.clone();
        b.reverse();
        b.push(a[0]);
        assert_eq!(cell_iou(&s, &a, &b), 1.0);
        // Half the cells shared: 5 in common, 15 in the union.
        let c: Vec<Cell> = (5..15).map(|x| Cell::new(x % 10, 7 - x / 10)).collect();
        assert!((cell_iou(&s, &a, &c) - 5.0 / 15.0).abs() < 1e-12);
        let far = [Cell::new(0, 0)];
        assert_eq!(cell_iou(&s, &a, &far), 0.0);
    }

    #[test]
    fn novelty_of_a_training_frame_is_zero_and_counts_differing_cells() {
        let s = site();
        let straight = walk(&s, &[(0, 7), (1, 7), (2, 7), (3, 7)]);
        let bent = walk(&s, &[(0, 0), (1, 1), (2, 1)]);
        let training = TrainingFrames::new(&s, &[straight.clone(), bent, straight.clone()]);
        assert_eq!(training.len(), 2, "duplicate walks are one frame");
        let mut frame = vec![-1.0f32; 80];
        for c in &straight.cells {
            frame[s.grid_index(*c)] = 0.7;
        }
        let bits = CellBits::from_frame(&s, &frame);
        assert_eq!(training.nearest_distance(&bits), Some(0));
        // One cell more and one fewer: two cells differ from the nearest.
        frame[s.grid_index(Cell::new(4, 7))] = 0.2;
        frame[s.grid_index(Cell::new(0, 7))] = -0.2;
        let bits = CellBits::from_frame(&s, &frame);
        assert_eq!(training.nearest_distance(&bits), Some(2));
        assert_eq!(TrainingFrames::new(&s, &[]).nearest_distance(&bits), None);
    }
}
