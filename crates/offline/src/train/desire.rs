//! Training the desire-line model ([`crate::model::desire`]) from walks.
//!
//! The model's bank is the walks themselves: each walk, in both directions,
//! as its end cells' centres and its shape at [`POINTS`] fractions of its
//! length (from its recorded positions when it has them, else its cells'
//! centres). What is learned beyond the bank are the settings: the kernel
//! width σ, the shrinkage `c`, the prior's weight `π` and the kernel mass
//! `τ` below which the walks are not used ([`Settings`]), chosen by
//! cross-validation on the training walks alone: the walks sorted by start
//! time are cut into [`FOLDS`] consecutive folds; for each setting of the
//! grid ([`SIGMAS_M`] × [`SHRINKS`] × [`PRIOR_WEIGHTS`] × [`MIN_MASSES`])
//! every fold's walks are planned with a model of the other folds' walks,
//! through the planner's own prior and repair ([`prior_line`],
//! [`walkable_line`]), and compared with where those walkers went by DTW
//! and discrete Fréchet distance, as `gangway eval planning` judges, against
//! the any-angle route (Theta*). Folds by time, as the evaluation holds out
//! the latest walks: a setting must predict later walkers from earlier ones.
//!
//! Which setting wins ([`Score::key`]): among those whose median DTW and
//! median Fréchet distance over the validation walks are no worse than the
//! any-angle route's, the one closer than it on the most walks (ties count
//! against, as the figure counts them); then the lower mean DTW.
//! When no setting keeps both medians, the one that keeps more of them
//! first. The share of wins alone picks lines that win many walks by a
//! little and lose some by a lot (a worse median); the medians alone pick
//! timid lines that hardly ever differ from the prior.
//!
//! What the chosen setting reached in cross-validation is the model's
//! report card (`cv_*` metrics), and the checks `gangway train` holds it to.
//!
//! Threads: the per-walk work (each walk's request, kernel sums and outcome
//! under a setting) runs on the rayon pool this is called in (`gangway train`
//! installs one of `--threads`), collected in walk order: the same model for
//! any thread count.

use std::collections::BTreeMap;
use std::sync::Arc;

use rayon::prelude::*;

use crate::model::desire::{DesireLines, POINTS, Prediction, Settings, Sums, finish};
use crate::plan::Profile;
use crate::plan::anyangle::{AnyAngle, GridPoint, centre, point_of_world, world_of_point};
use crate::plan::desire::{prior_line, resample, walkable_line, warped};
use crate::plan::lines::{Polyline, Shape, shape};
use crate::site::{Cell, Site};
use crate::train::trajectory::Trajectory;

/// Consecutive time folds of the cross-validation.
pub const FOLDS: usize = 3;
/// Kernel widths tried, metres (converted to cells at the site's cell size).
pub(crate) const SIGMAS_M: [f64; 8] = [0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 4.0, 6.0];
/// Shrinkage strengths tried.
pub(crate) const SHRINKS: [f32; 8] = [0.5, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0];
/// Prior weights tried, in walks' kernel weight (a walk at the request's
/// own ends weighs 1).
pub(crate) const PRIOR_WEIGHTS: [f32; 4] = [0.001, 0.03, 0.3, 3.0];
/// Kernel masses below which the prior answers alone, tried.
pub(crate) const MIN_MASSES: [f32; 7] = [0.0, 0.003, 0.01, 0.03, 0.1, 0.3, 1.0];

/// One walk ready for the bank and for validation (and for the line GAN:
/// `train::job`).
pub(super) struct Walk {
    /// Its end cells' centres, cell units: what a request for it asks.
    pub(super) ends: [GridPoint; 2],
    /// Its shape normalised to run from 0 to 1, forwards.
    pub(super) shape: [[f32; 2]; POINTS],
    /// Where the walker went, metres, for DTW.
    walked: Polyline,
}

/// A validation walk's request as the planner would see it.
struct Request {
    /// The prior line (the any-angle route the planner blends into).
    prior: Vec<GridPoint>,
    /// The prior at [`POINTS`] fractions of its length, as the model gets it.
    samples: Vec<[f32; 2]>,
    /// The prior against the walk: what a request answered by it scores.
    prior_shape: Option<Shape>,
    /// The any-angle route (Theta*) against the walk: the judge.
    baseline: Option<Shape>,
}

/// How one setting did on one validation walk, before its threshold `τ`.
#[derive(Clone, Copy)]
struct Outcome {
    /// The kernel mass of the walks near the request.
    mass: f32,
    /// The learned line against the walk, and whether it was repaired.
    learned: Option<(Shape, bool)>,
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
    let step = site.cell_m / 2.0;
    let any = AnyAngle::new(site.clone());
    // Per walk and independent: on the threads of the rayon pool this runs
    // in, collected in walk order, so the result does not depend on them.
    let requests: Vec<Request> = prepared
        .par_iter()
        .map(|w| request(site, &any, w, step))
        .collect();
    let n = prepared.len();
    let folds: Vec<std::ops::Range<usize>> = (0..FOLDS)
        .map(|k| k * n / FOLDS..(k + 1) * n / FOLDS)
        .collect();
    // Each validation walk's fold, and the bank of the other folds.
    let banks: Vec<DesireLines> = folds
        .iter()
        .map(|fold| {
            let others = prepared
                .iter()
                .enumerate()
                .filter(|(i, _)| !fold.contains(i))
                .map(|(_, w)| w);
            bank(others, default_settings())
        })
        .collect();
    let fold_of: Vec<usize> = (0..n)
        .map(|i| {
            folds
                .iter()
                .position(|f| f.contains(&i))
                .expect("folds cover")
        })
        .collect();
    let baseline = Baseline::new(&requests);
    let mut best: Option<(Score, Settings)> = None;
    let mut outcomes: Vec<Outcome> = Vec::with_capacity(n);
    for sigma_m in SIGMAS_M {
        let sigma_cells = (sigma_m / site.cell_m) as f32;
        // The kernel sums depend on σ alone: once per walk.
        let sums: Vec<Sums> = (0..n)
            .into_par_iter()
            .map(|i| {
                let [a, b] = prepared[i].ends.map(f32s);
                banks[fold_of[i]].sums(a, b, sigma_cells)
            })
            .collect();
        for shrink in SHRINKS {
            for prior_weight in PRIOR_WEIGHTS {
                let settings = Settings {
                    sigma_cells,
                    shrink,
                    prior_weight,
                    min_mass: 0.0,
                };
                outcomes.clear();
                sums.par_iter()
                    .enumerate()
                    .map(|(i, sums)| {
                        outcome(site, &settings, sums, &prepared[i], &requests[i], step)
                    })
                    .collect_into_vec(&mut outcomes);
                for min_mass in MIN_MASSES {
                    let score = Score::of(&outcomes, &requests, &baseline, min_mass);
                    if best.as_ref().is_none_or(|(b, _)| score.key() > b.key()) {
                        best = Some((
                            score,
                            Settings {
                                min_mass,
                                ..settings
                            },
                        ));
                    }
                }
            }
        }
    }
    let (score, settings) = best.expect("a grid of settings");
    let model = bank(prepared.iter(), settings);
    let mut metrics = BTreeMap::new();
    metrics.insert("bank_lines".to_owned(), model.ends.len() as f64);
    metrics.insert(
        "sigma_m".to_owned(),
        f64::from(settings.sigma_cells) * site.cell_m,
    );
    metrics.insert("shrink".to_owned(), f64::from(settings.shrink));
    metrics.insert("prior_weight".to_owned(), f64::from(settings.prior_weight));
    metrics.insert("min_mass".to_owned(), f64::from(settings.min_mass));
    score.report(&baseline, &mut metrics);
    Ok(Trained { model, metrics })
}

/// The settings a fold's bank is built with: only its lines are used (each
/// setting finishes their sums itself).
fn default_settings() -> Settings {
    Settings {
        sigma_cells: 1.0,
        shrink: 1.0,
        prior_weight: PRIOR_WEIGHTS[0],
        min_mass: 0.0,
    }
}

fn f32s(p: GridPoint) -> [f32; 2] {
    [p[0] as f32, p[1] as f32]
}

/// The request of validation walk `w`: its prior and both its judges.
fn request(site: &Site, any: &AnyAngle, w: &Walk, step: f64) -> Request {
    let [a, b] = w.ends.map(cell_of);
    let prior = prior_line(site, Profile::Default, a, b).unwrap_or_default();
    let samples = if prior.is_empty() {
        Vec::new()
    } else {
        resample(&prior, POINTS).into_iter().map(f32s).collect()
    };
    let prior_shape = (!prior.is_empty())
        .then(|| shape(&metres(site, &prior), &w.walked, step))
        .flatten();
    let baseline = any.route(a, b, Profile::Default).ok().and_then(|r| {
        let line = metres(
            site,
            &r.vertices.iter().map(|&c| centre(c)).collect::<Vec<_>>(),
        );
        shape(&line, &w.walked, step)
    });
    Request {
        prior,
        samples,
        prior_shape,
        baseline,
    }
}

/// The learned line of `settings` for validation walk `w` from its kernel
/// `sums` over the other folds, made walkable as the planner makes it,
/// against the walk.
fn outcome(
    site: &Site,
    settings: &Settings,
    sums: &Sums,
    w: &Walk,
    r: &Request,
    step: f64,
) -> Outcome {
    let [a, b] = w.ends.map(f32s);
    if r.prior.is_empty() {
        return Outcome {
            mass: 0.0,
            learned: None,
        };
    }
    let Prediction { points, mass, .. } = finish(settings, sums, a, b, &r.samples);
    let moved = points
        .iter()
        .zip(&r.samples)
        .any(|(p, s)| (p[0] - s[0]).abs() > 1e-4 || (p[1] - s[1]).abs() > 1e-4);
    if !moved {
        // The prior itself: scored once already.
        return Outcome {
            mass,
            learned: r.prior_shape.map(|s| (s, false)),
        };
    }
    let points: Vec<GridPoint> = points
        .iter()
        .map(|p| [f64::from(p[0]), f64::from(p[1])])
        .collect();
    let line = warped(&r.prior, &r.samples, &points);
    let learned = walkable_line(
        site,
        Profile::Default,
        &line,
        cell_of(w.ends[0]),
        cell_of(w.ends[1]),
    )
    .ok()
    .and_then(|(line, repaired)| {
        shape(&metres(site, &line), &w.walked, step).map(|s| (s, repaired))
    });
    Outcome { mass, learned }
}

/// The any-angle route's figures over the validation walks.
struct Baseline {
    dtw_median: f64,
    frechet_median: f64,
}

impl Baseline {
    fn new(requests: &[Request]) -> Baseline {
        let shapes: Vec<Shape> = requests.iter().filter_map(|r| r.baseline).collect();
        Baseline {
            dtw_median: median(shapes.iter().map(|s| s.dtw_m).collect()),
            frechet_median: median(shapes.iter().map(|s| s.frechet_m).collect()),
        }
    }
}

fn median(mut v: Vec<f64>) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[(v.len() - 1) / 2]
}

/// How one setting did over the validation walks.
#[derive(Clone, Debug, Default)]
struct Score {
    walks: usize,
    /// Walks where any-angle answered too.
    compared: usize,
    wins: usize,
    /// Requests the learned line answered (kernel mass above `τ`).
    learned: usize,
    repaired: usize,
    dtw: Vec<f64>,
    frechet: Vec<f64>,
    dtw_median: f64,
    frechet_median: f64,
    /// Of the medians, how many are no worse than the any-angle route's.
    medians_kept: u8,
}

impl Score {
    /// The figures of the outcomes when the walks answer only above `min_mass`.
    fn of(outcomes: &[Outcome], requests: &[Request], baseline: &Baseline, min_mass: f32) -> Score {
        let mut score = Score::default();
        for (o, r) in outcomes.iter().zip(requests) {
            let used = o.mass > min_mass;
            let answer = if used {
                o.learned
            } else {
                r.prior_shape.map(|s| (s, false))
            };
            let Some((s, repaired)) = answer else {
                continue;
            };
            score.walks += 1;
            score.learned += usize::from(used);
            score.repaired += usize::from(repaired);
            score.dtw.push(s.dtw_m);
            score.frechet.push(s.frechet_m);
            if let Some(base) = r.baseline {
                score.compared += 1;
                if s.dtw_m < base.dtw_m - 1e-6 {
                    score.wins += 1;
                }
            }
        }
        score.dtw_median = median(score.dtw.clone());
        score.frechet_median = median(score.frechet.clone());
        score.medians_kept = u8::from(score.dtw_median <= baseline.dtw_median)
            + u8::from(score.frechet_median <= baseline.frechet_median);
        score
    }

    fn share(&self) -> f64 {
        self.wins as f64 / self.compared.max(1) as f64
    }

    fn dtw_mean(&self) -> f64 {
        self.dtw.iter().sum::<f64>() / self.dtw.len().max(1) as f64
    }

    /// What the settings are ranked by, highest best (module docs).
    fn key(&self) -> (u8, f64, f64) {
        (self.medians_kept, self.share(), -self.dtw_mean())
    }

    /// The `cv_*` metrics.
    fn report(&self, baseline: &Baseline, metrics: &mut BTreeMap<String, f64>) {
        let walks = self.walks.max(1) as f64;
        for (key, value) in [
            ("cv_walks", self.walks as f64),
            ("cv_closer_than_anyangle", self.share()),
            ("cv_dtw_m_median", self.dtw_median),
            ("cv_frechet_m_median", self.frechet_median),
            ("cv_anyangle_dtw_m_median", baseline.dtw_median),
            ("cv_anyangle_frechet_m_median", baseline.frechet_median),
            ("cv_dtw_m_mean", self.dtw_mean()),
            ("cv_learned_share", self.learned as f64 / walks),
            ("cv_repaired_share", self.repaired as f64 / walks),
        ] {
            metrics.insert(key.to_owned(), value);
        }
    }
}

/// A model whose bank is `walks`, each in both directions.
fn bank<'a>(walks: impl Iterator<Item = &'a Walk>, settings: Settings) -> DesireLines {
    let mut model = DesireLines {
        ends: Vec::new(),
        shapes: Vec::new(),
        settings,
    };
    for w in walks {
        let [a, b] = w.ends.map(f32s);
        model.ends.push([a[0], a[1], b[0], b[1]]);
        model.shapes.push(w.shape);
        model.ends.push([b[0], b[1], a[0], a[1]]);
        model.shapes.push(backwards(&w.shape));
    }
    model
}

/// A walk's shape walked the other way: `u'(s) = 1 − u(1 − s)`.
pub(super) fn backwards(shape: &[[f32; 2]; POINTS]) -> [[f32; 2]; POINTS] {
    std::array::from_fn(|k| {
        let [re, im] = shape[POINTS - 1 - k];
        [1.0 - re, -im]
    })
}

/// `walk` as a bank line; `None` when its recorded ends are less than a cell
/// apart (a loop or a walker standing still has no direction to learn).
pub(super) fn prepare(site: &Site, walk: &Trajectory) -> Option<Walk> {
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

fn metres(site: &Site, points: &[GridPoint]) -> Polyline {
    Polyline(points.iter().map(|&p| world_of_point(site, p)).collect())
}

/// The cell a point (cell units) lies in.
pub(super) fn cell_of(p: GridPoint) -> Cell {
    Cell::new(p[0].floor() as u16, p[1].floor() as u16)
}
