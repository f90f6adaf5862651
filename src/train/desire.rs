//! Training the desire-line model ([`crate::model::desire`]) from walks.
//!
//! The model's bank is the walks themselves: each walk, in both directions,
//! as its end cells' centres and its shape at [`POINTS`] fractions of its
//! length (from its recorded positions when it has them, else its cells'
//! centres). What is learned beyond the bank are the kernel width σ and the
//! shrinkage `c`, chosen by cross-validation on the training walks alone:
//! the walks sorted by start time are cut into [`FOLDS`] consecutive folds;
//! for each setting of the grid ([`SIGMAS_M`] × [`SHRINKS`]) every fold's
//! walks are planned with a model of the other folds' walks, through the
//! planner's own repair ([`walkable_line`]), and compared with where those
//! walkers went by DTW, as `gangway eval planning` judges, against the
//! any-angle route. The setting closer than any-angle on the most walks wins
//! (ties by the lower mean DTW). Folds by time, as the evaluation holds out
//! the latest walks: a setting must predict later walkers from earlier ones.
//!
//! What the chosen setting reached in cross-validation is the model's
//! report card (`cv_*` metrics), and the checks `gangway train` holds it to.

use std::collections::BTreeMap;
use std::sync::Arc;

use crate::model::desire::{DesireLines, POINTS};
use crate::plan::Profile;
use crate::plan::anyangle::{AnyAngle, GridPoint, centre, point_of_world, world_of_point};
use crate::plan::desire::walkable_line;
use crate::plan::lines::{Polyline, shape};
use crate::site::Site;
use crate::train::trajectory::Trajectory;

/// Consecutive time folds of the cross-validation.
pub const FOLDS: usize = 3;
/// Kernel widths tried, metres (converted to cells at the site's cell size).
pub const SIGMAS_M: [f64; 8] = [0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0];
/// Shrinkage strengths tried.
pub const SHRINKS: [f32; 8] = [0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0];

/// One walk ready for the bank and for validation.
struct Walk {
    /// Its end cells' centres, cell units: what a request for it asks.
    ends: [GridPoint; 2],
    /// Its shape normalised to run from 0 to 1, forwards.
    shape: [[f32; 2]; POINTS],
    /// Where the walker went, metres, for DTW.
    walked: Polyline,
}

/// The trained model and what cross-validation measured of it.
pub struct Trained {
    pub model: DesireLines,
    pub metrics: BTreeMap<String, f64>,
}

/// Trains on `walks` (any order; sorted by start time here).
pub fn train(site: &Arc<Site>, walks: &[Trajectory]) -> anyhow::Result<Trained> {
    let mut sorted: Vec<&Trajectory> = walks.iter().collect();
    sorted.sort_by(|a, b| a.times[0].total_cmp(&b.times[0]));
    let prepared: Vec<Walk> = sorted.iter().filter_map(|w| prepare(site, w)).collect();
    anyhow::ensure!(
        prepared.len() >= 3 * FOLDS,
        "desire lines need at least {} walks whose ends are a cell or more apart; got {} of {}",
        3 * FOLDS,
        prepared.len(),
        walks.len()
    );
    let any = AnyAngle::new(site.clone());
    let step = site.cell_m / 2.0;
    // The any-angle route's DTW for every walk, once.
    let baseline: Vec<Option<f64>> = prepared
        .iter()
        .map(|w| {
            let [a, b] = w.ends.map(cell_of);
            let r = any.route(a, b, Profile::Default).ok()?;
            let line = metres(
                site,
                &r.vertices.iter().map(|&c| centre(c)).collect::<Vec<_>>(),
            );
            shape(&line, &w.walked, step).map(|s| s.dtw_m)
        })
        .collect();
    let n = prepared.len();
    let folds: Vec<std::ops::Range<usize>> = (0..FOLDS)
        .map(|k| k * n / FOLDS..(k + 1) * n / FOLDS)
        .collect();
    let mut best: Option<(Score, f32, f32)> = None;
    for sigma_m in SIGMAS_M {
        let sigma_cells = (sigma_m / site.cell_m) as f32;
        for shrink in SHRINKS {
            let mut score = Score::default();
            for fold in &folds {
                let model = bank(
                    prepared
                        .iter()
                        .enumerate()
                        .filter(|(i, _)| !fold.contains(i))
                        .map(|(_, w)| w),
                    sigma_cells,
                    shrink,
                );
                for i in fold.clone() {
                    score.add(site, &model, &prepared[i], baseline[i], step);
                }
            }
            if best.as_ref().is_none_or(|(b, _, _)| score.better_than(b)) {
                best = Some((score, sigma_cells, shrink));
            }
        }
    }
    let (score, sigma_cells, shrink) = best.expect("a grid of settings");
    let model = bank(prepared.iter(), sigma_cells, shrink);
    let mut metrics = BTreeMap::new();
    metrics.insert("bank_lines".to_owned(), model.ends.len() as f64);
    metrics.insert("sigma_m".to_owned(), f64::from(sigma_cells) * site.cell_m);
    metrics.insert("shrink".to_owned(), f64::from(shrink));
    metrics.insert("cv_walks".to_owned(), score.walks as f64);
    metrics.insert("cv_closer_than_anyangle".to_owned(), score.share());
    metrics.insert(
        "cv_dtw_m_mean".to_owned(),
        score.dtw_sum / score.walks.max(1) as f64,
    );
    metrics.insert(
        "cv_anyangle_dtw_m_mean".to_owned(),
        score.baseline_sum / score.compared.max(1) as f64,
    );
    metrics.insert(
        "cv_repaired_share".to_owned(),
        score.repaired as f64 / score.walks.max(1) as f64,
    );
    Ok(Trained { model, metrics })
}

/// How one setting did over the validation walks.
#[derive(Clone, Debug, Default)]
struct Score {
    walks: usize,
    /// Walks where any-angle answered too.
    compared: usize,
    wins: usize,
    repaired: usize,
    dtw_sum: f64,
    baseline_sum: f64,
}

impl Score {
    fn add(
        &mut self,
        site: &Site,
        model: &DesireLines,
        walk: &Walk,
        baseline: Option<f64>,
        step: f64,
    ) {
        let [a, b] = walk.ends;
        let f32s = |p: GridPoint| [p[0] as f32, p[1] as f32];
        let points: Vec<GridPoint> = model
            .predict(f32s(a), f32s(b))
            .iter()
            .map(|p| [f64::from(p[0]), f64::from(p[1])])
            .collect();
        let Ok((line, repaired)) =
            walkable_line(site, Profile::Default, &points, cell_of(a), cell_of(b))
        else {
            return;
        };
        let Some(s) = shape(&metres(site, &line), &walk.walked, step) else {
            return;
        };
        self.walks += 1;
        self.repaired += usize::from(repaired);
        self.dtw_sum += s.dtw_m;
        if let Some(base) = baseline {
            self.compared += 1;
            self.baseline_sum += base;
            if s.dtw_m < base - 1e-6 {
                self.wins += 1;
            }
        }
    }

    fn share(&self) -> f64 {
        self.wins as f64 / self.compared.max(1) as f64
    }

    fn better_than(&self, other: &Score) -> bool {
        let mean = |s: &Score| s.dtw_sum / s.walks.max(1) as f64;
        (self.share(), -mean(self)) > (other.share(), -mean(other))
    }
}

/// A model whose bank is `walks`, each in both directions.
fn bank<'a>(walks: impl Iterator<Item = &'a Walk>, sigma_cells: f32, shrink: f32) -> DesireLines {
    let mut model = DesireLines {
        ends: Vec::new(),
        shapes: Vec::new(),
        sigma_cells,
        shrink,
    };
    for w in walks {
        let [a, b] = w.ends.map(|p| [p[0] as f32, p[1] as f32]);
        model.ends.push([a[0], a[1], b[0], b[1]]);
        model.shapes.push(w.shape);
        model.ends.push([b[0], b[1], a[0], a[1]]);
        // Backwards: u'(s) = 1 − u(1 − s).
        model.shapes.push(std::array::from_fn(|k| {
            let [re, im] = w.shape[POINTS - 1 - k];
            [1.0 - re, -im]
        }));
    }
    model
}

/// `walk` as a bank line; `None` when its recorded ends are less than a cell
/// apart (a loop or a walker standing still has no direction to learn).
fn prepare(site: &Site, walk: &Trajectory) -> Option<Walk> {
    let points: Vec<GridPoint> = match &walk.positions_m {
        Some(p) if p.len() >= 2 => p.iter().map(|&w| point_of_world(site, w)).collect(),
        _ => walk.cells.iter().map(|&c| centre(c)).collect(),
    };
    let along = resample(&points, POINTS);
    let (z0, z1) = (along[0], along[POINTS - 1]);
    let chord = [z1[0] - z0[0], z1[1] - z0[1]];
    let len2 = chord[0] * chord[0] + chord[1] * chord[1];
    if len2 < 1.0 {
        return None;
    }
    // u = (z − z0) / (z1 − z0) in complex numbers.
    let shape = std::array::from_fn(|k| {
        let d = [along[k][0] - z0[0], along[k][1] - z0[1]];
        [
            ((d[0] * chord[0] + d[1] * chord[1]) / len2) as f32,
            ((d[1] * chord[0] - d[0] * chord[1]) / len2) as f32,
        ]
    });
    Some(Walk {
        ends: [centre(walk.source()), centre(walk.destination())],
        shape,
        walked: metres(site, &points),
    })
}

/// `count` points evenly spaced by length along `points`, both ends kept.
fn resample(points: &[GridPoint], count: usize) -> Vec<GridPoint> {
    let lengths: Vec<f64> = points
        .windows(2)
        .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
        .collect();
    let total: f64 = lengths.iter().sum();
    let mut out = Vec::with_capacity(count);
    let (mut seg, mut before) = (0usize, 0.0f64);
    for k in 0..count {
        let target = total * k as f64 / (count - 1) as f64;
        while seg + 1 < lengths.len() && before + lengths[seg] < target {
            before += lengths[seg];
            seg += 1;
        }
        let (a, b) = (points[seg], points[(seg + 1).min(points.len() - 1)]);
        let t = if lengths.get(seg).is_some_and(|&l| l > 0.0) {
            ((target - before) / lengths[seg]).clamp(0.0, 1.0)
        } else {
            0.0
        };
        out.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
    }
    out
}

fn metres(site: &Site, points: &[GridPoint]) -> Polyline {
    Polyline(points.iter().map(|&p| world_of_point(site, p)).collect())
}

fn cell_of(p: GridPoint) -> crate::site::Cell {
    crate::site::Cell::new(p[0].floor() as u16, p[1].floor() as u16)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resampling_spaces_points_by_length() {
        let pts = vec![[0.0, 0.0], [4.0, 0.0], [4.0, 4.0]];
        let r = resample(&pts, 5);
        assert_eq!(r.len(), 5);
        assert_eq!(r[0], [0.0, 0.0]);
        assert!(
            (r[2][0] - 4.0).abs() < 1e-9 && r[2][1].abs() < 1e-9,
            "{r:?}"
        );
        assert_eq!(r[4], [4.0, 4.0]);
    }
}
