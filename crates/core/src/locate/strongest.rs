//! The strongest-beacon rule: a device is wherever the anchor it hears
//! loudest is. It is what most presence systems do and what a user would try
//! first, so it is the baseline every other localizer must beat
//! (`gangway eval localization --method strongest --tracker none`).
//!
//! As a [`Localizer`] it scores each walkable cell by its squared distance to
//! that anchor, in cells: the argmax (`--tracker none`) is the walkable cell
//! nearest the anchor, which is the rule itself, and under the motion tracker
//! it becomes "near the loudest anchor" with one cell of spread. It needs
//! anchor positions and nothing else: no survey, no radio model.

use std::sync::Arc;

use super::window::Orientation;
use super::{Localizer, LocalizerError, pathloss};
use crate::site::{Mount, Site};

pub struct Strongest {
    /// Each walkable cell's centre, world metres.
    cells_m: Vec<[f64; 2]>,
    /// Where each anchor is mounted, in the orientation's anchor order.
    anchors: Vec<Option<Mount>>,
    cell_m: f64,
}

impl Strongest {
    pub fn new(
        config: &pathloss::PathLossConfig,
        site: &Arc<Site>,
        orientation: Orientation,
    ) -> Result<Self, LocalizerError> {
        // Positions only: the radio models that come with them are unused.
        let anchors: Vec<Option<Mount>> = pathloss::anchors(site, orientation, config, None)
            .into_iter()
            .map(|a| a.map(|(mount, _)| mount))
            .collect();
        if anchors.iter().all(Option::is_none) {
            return Err(LocalizerError::NoAnchorPositions);
        }
        Ok(Strongest {
            cells_m: site
                .open_cells()
                .iter()
                .map(|&c| site.world_of_cell(c))
                .collect(),
            anchors,
            cell_m: site.cell_m,
        })
    }
}

impl Localizer for Strongest {
    fn method(&self) -> &'static str {
        "strongest"
    }

    fn log_likelihood(&mut self, rssi: &[f32], heard: &[bool], out: &mut [f32]) {
        let loudest = (0..rssi.len())
            .filter(|&a| heard[a])
            .filter_map(|a| self.anchors[a].map(|mount| (rssi[a], mount)))
            .max_by(|a, b| a.0.total_cmp(&b.0));
        match loudest {
            // Nothing placed was heard: no evidence either way.
            None => out.fill(0.0),
            Some((_, mount)) => {
                for (slot, &here) in out.iter_mut().zip(&self.cells_m) {
                    let d = mount.distance_m(here) / self.cell_m;
                    *slot = (-0.5 * d * d) as f32;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::locate::pathloss::PathLossConfig;

    #[test]
    fn the_cell_nearest_the_loudest_placed_anchor_wins() {
        let text = "name = \"t\"\ncell_m = 2.0\nmap = '''\n######\n'''\n\
            [[beacon]]\nid = \"west\"\nuuid = \"f7826da6-4fa2-4e98-8024-bc5b71e0893e\"\nmajor = 1\nminor = 1\ncell = [0, 0]\n\
            [[beacon]]\nid = \"east\"\nuuid = \"f7826da6-4fa2-4e98-8024-bc5b71e0893e\"\nmajor = 1\nminor = 2\ncell = [5, 0]\n\
            [[beacon]]\nid = \"unplaced\"\nuuid = \"f7826da6-4fa2-4e98-8024-bc5b71e0893e\"\nmajor = 1\nminor = 3\n";
        let site = Arc::new(Site::parse(text, std::path::Path::new("t.toml")).unwrap());
        let mut rule =
            Strongest::new(&PathLossConfig::default(), &site, Orientation::Observer).unwrap();
        let argmax = |out: &[f32]| {
            (0..out.len())
                .max_by(|&a, &b| out[a].total_cmp(&out[b]))
                .unwrap()
        };
        let mut out = vec![0.0; 6];
        // East is louder than west; the unplaced anchor, loudest of all, cannot vote.
        rule.log_likelihood(&[-80.0, -60.0, -40.0], &[true, true, true], &mut out);
        assert_eq!(argmax(&out), 5);
        rule.log_likelihood(&[-60.0, -80.0, -40.0], &[true, true, false], &mut out);
        assert_eq!(argmax(&out), 0);
        // Only the unplaced anchor heard: every cell is as likely as any other.
        rule.log_likelihood(&[0.0, 0.0, -40.0], &[false, false, true], &mut out);
        assert!(out.iter().all(|&v| v == 0.0));
    }
}
