//! `gangway eval planning`: every planner mode on every ordered pair of named
//! places plus random open-cell pairs, with the figures of issue 5.
//!
//! Every mode is measured, `learned` (the default) as a gateway builds it:
//! its report says which planner it `serves` and why (`serves_because`).
//!
//! Measured here: pairs, valid_rate (every answer re-validated), the paper's
//! deviation score (|G| − |G ∩ B|) / |B| of the frame each learned route came
//! from, length_ratio_mean (to the shortest route), classifier_error (the
//! path classifier's held-out error as measured by `gangway train` on walks it
//! never saw, read from the model's metadata), rejection_acceptance_rate
//! (share of rejection requests for trained pairs answered by an accepted
//! frame), and the model and total times per request.
//!
//! Against recorded walks ([`Walks`]; a key is `null` when its walks are not
//! given): `human_iou_gan` is the mean cell-set IoU between the mode's route
//! and each held-out walk for the walk's (first cell, last cell), in the
//! learned modes; `human_iou_astar` the same for the shortest route (the
//! baseline, the same value in every mode's entry); `novelty` the mean number
//! of cells by which a generated frame (the one behind each learned route for
//! the evaluated pairs) differs from its nearest training frame, and
//! `heldout_novelty` the same for the held-out walks themselves (how far a new
//! walk by people is from the training walks) and `heldout_seen_share` the
//! share of held-out walks whose cells equal a training walk's (both `null`
//! without both files). `human_iou_gan_unseen` and `human_iou_astar_unseen`
//! are the IoUs over only the other, unseen held-out walks, which a generator
//! cannot match by reproducing a training walk.
//!
//! Fair judges on the held-out walks (`baselines`, and `heldout` in each
//! mode): beside A*, the any-angle route ([`plan::anyangle`], Theta*) and the
//! straight line where the profile may walk it. Every planner is judged by
//! what its route reply holds: the reply is built as a gateway builds it
//! ([`RouteBody::new`]) and its `line`, the metric polyline a user is given,
//! is what is measured (the straight line, which no planner serves, by its
//! segment). Each walk is its recorded positions in metres when it has
//! them, else its cells' centres. Compared in metres ([`shape`]: DTW and
//! discrete Fréchet on both resampled every half cell), by cell IoU and by
//! length ratio (route over walk). `closer_than` gives, per baseline, how
//! often the mode's route is closer to the walk by DTW than the baseline's
//! (wins, losses, ties: within a micrometre), the share of wins among the
//! walks both answered, and the two-sided sign-test p-value of wins against
//! losses.
//!
//! Side by side, under `cells` in each summary and each `closer_than`, the
//! same figures for the reply's cells' centres (its `waypoints`): what was
//! measured before replies carried a line. A staircase of cells is judged
//! close to a walk's own staircase of cells for being made of cells, so
//! those figures flatter any route of cells; they are kept to show how far.

use std::sync::Arc;
use std::time::Instant;

use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use serde_json::{Value, json};

use super::similarity::{CellBits, Polyline, TrainingFrames, cell_iou, shape};
use crate::model::runtime::PathClassifier;
use crate::plan::{self, Origin, PlannerConfig, PlannerMode, Profile};
use crate::publish::RouteBody;
use crate::sign_test::sign_test;
use crate::site::{Cell, Site};
use crate::train::trajectory::Trajectory;

/// Recorded walks the routes and frames are compared with.
#[derive(Default)]
pub struct Walks {
    /// Walks no model was trained on (`human_iou_*`).
    pub heldout: Option<Vec<Trajectory>>,
    /// The frames of the walks the generators were trained on (`novelty`).
    pub training: Option<TrainingFrames>,
}

/// The pairs every mode is evaluated on: all ordered pairs of distinct named
/// places, then `random` random pairs of distinct open cells (seeded).
pub fn pairs(site: &Site, random: usize, seed: u64) -> Vec<(Cell, Cell)> {
    let mut out = place_pairs(site);
    let open = site.open_cells();
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let wanted = out.len() + random;
    while out.len() < wanted {
        let (a, b) = (
            open[rng.random_range(0..open.len())],
            open[rng.random_range(0..open.len())],
        );
        if a != b {
            out.push((a, b));
        }
    }
    out
}

/// Every ordered pair of distinct named places, in the places' name order.
pub(crate) fn place_pairs(site: &Site) -> Vec<(Cell, Cell)> {
    let places: Vec<Cell> = site.places().values().copied().collect();
    places
        .iter()
        .flat_map(|&a| places.iter().map(move |&b| (a, b)))
        .filter(|(a, b)| a != b)
        .collect()
}

/// The report: top-level keys for `config.mode`, and every mode under `modes`.
pub fn evaluate(
    config: &PlannerConfig,
    site: Arc<Site>,
    pairs: &[(Cell, Cell)],
    walks: &Walks,
) -> Value {
    let shortest = plan::astar::AStar::new(site.clone(), config.connectivity);
    let astar_ious = walks
        .heldout
        .as_deref()
        .map(|w| human_iou(&site, &shortest, w));
    // How far each held-out walk is from the training walks: the scale for
    // `novelty`, and which held-out walks repeat a training walk exactly.
    let heldout_distances: Option<Vec<f64>> = match (&walks.heldout, &walks.training) {
        (Some(heldout), Some(training)) if !training.is_empty() => Some(
            heldout
                .iter()
                .map(|w| {
                    let bits = CellBits::from_cells(&site, &w.cells);
                    f64::from(training.nearest_distance(&bits).expect("training frames"))
                })
                .collect(),
        ),
        _ => None,
    };
    let unseen: Option<Vec<bool>> = heldout_distances
        .as_ref()
        .map(|d| d.iter().map(|&d| d > 0.0).collect());
    let judged = walks
        .heldout
        .as_deref()
        .map(|heldout| Judged::new(&site, config.connectivity, heldout));
    let mut modes = serde_json::Map::new();
    for mode in PlannerMode::ALL {
        // The default mode through the path a gateway takes (`learned`),
        // saying which planner it serves.
        let built = match mode {
            PlannerMode::Learned => {
                plan::learned::build(config, site.clone()).map(|(p, choice)| (p, Some(choice)))
            }
            _ => plan::build_mode(config, mode, site.clone()).map(|p| (p, None)),
        };
        let report = match built {
            Ok((planner, choice)) => {
                let mut report = evaluate_mode(
                    config,
                    &site,
                    &*planner,
                    &shortest,
                    pairs,
                    walks,
                    unseen.as_deref(),
                );
                let (all, unseen) = iou_means(astar_ious.as_deref(), unseen.as_deref());
                report["human_iou_astar"] = json!(all);
                report["human_iou_astar_unseen"] = json!(unseen);
                report["heldout"] = match (&judged, &walks.heldout) {
                    (Some(judged), Some(heldout)) => {
                        judged.mode_report(&judge_planner(&site, &*planner, heldout))
                    }
                    _ => Value::Null,
                };
                if let Some(choice) = choice {
                    report["serves"] = json!(choice.serves.name());
                    report["serves_because"] = json!(choice.because);
                }
                report
            }
            Err(e) => json!({ "unavailable": format!("{e:#}") }),
        };
        modes.insert(mode.name().to_owned(), report);
    }
    let mut top = modes[config.mode.name()]
        .as_object()
        .cloned()
        .unwrap_or_default();
    top.insert("mode".into(), json!(config.mode.name()));
    top.insert(
        "heldout_walks".into(),
        json!(walks.heldout.as_ref().map(Vec::len)),
    );
    top.insert(
        "training_frames".into(),
        json!(walks.training.as_ref().map(TrainingFrames::len)),
    );
    if let Some(d) = &heldout_distances {
        top.insert("heldout_novelty".into(), json!(mean(d)));
        top.insert(
            "heldout_seen_share".into(),
            json!(d.iter().filter(|&&d| d == 0.0).count() as f64 / d.len().max(1) as f64),
        );
        top.insert(
            "heldout_unseen_walks".into(),
            json!(d.iter().filter(|&&d| d > 0.0).count()),
        );
    } else {
        top.insert("heldout_novelty".into(), Value::Null);
        top.insert("heldout_seen_share".into(), Value::Null);
        top.insert("heldout_unseen_walks".into(), Value::Null);
    }
    top.insert(
        "baselines".into(),
        judged
            .as_ref()
            .map_or(Value::Null, Judged::baselines_report),
    );
    top.insert("modes".into(), Value::Object(modes));
    Value::Object(top)
}

/// How one judge's route compares with one held-out walk.
#[derive(Clone, Copy, Debug)]
struct Score {
    /// Of the served line.
    dtw_m: f64,
    frechet_m: f64,
    /// Of the route's cells' centres.
    cells_dtw_m: f64,
    cells_frechet_m: f64,
    iou: f64,
    length_ratio: f64,
    /// The learned frame or line behind the route needed repair.
    repaired: bool,
    /// The planner served its fallback instead of what it learned
    /// (`few_walks`, `profile_costs`).
    fallback: bool,
    /// The planner's line failed its check and the reply's line is its
    /// cells' centres (`line_from: fallback`).
    line_fallback: bool,
}

/// Scores of the baselines on every held-out walk (`None`: no route, e.g.
/// the straight line is blocked).
struct Judged {
    astar: Vec<Option<Score>>,
    anyangle: Vec<Option<Score>>,
    straight: Vec<Option<Score>>,
}

/// The profile a walk names, or the default one.
fn walk_profile(w: &Trajectory) -> Profile {
    w.profile
        .as_deref()
        .and_then(Profile::parse)
        .unwrap_or(Profile::Default)
}

/// A route (its cells, and the line it walks in metres) scored against a
/// walk: against its recorded positions when it has them, else its cells'
/// centres.
fn score(site: &Site, walk: &Trajectory, cells: &[Cell], line: &Polyline) -> Option<Score> {
    let walked = match &walk.positions_m {
        Some(points) => Polyline(points.clone()),
        None => Polyline::of_cells(site, &walk.cells),
    };
    let step_m = site.cell_m / 2.0;
    let s = shape(line, &walked, step_m)?;
    let by_cells = shape(&Polyline::of_cells(site, cells), &walked, step_m)?;
    let walk_m = walked.length_m();
    Some(Score {
        dtw_m: s.dtw_m,
        frechet_m: s.frechet_m,
        cells_dtw_m: by_cells.dtw_m,
        cells_frechet_m: by_cells.frechet_m,
        iou: cell_iou(site, cells, &walk.cells),
        length_ratio: if walk_m > 0.0 {
            line.length_m() / walk_m
        } else {
            1.0
        },
        repaired: false,
        fallback: false,
        line_fallback: false,
    })
}

/// `planner`'s route for each walk's ends and profile, scored.
fn judge_planner(
    site: &Site,
    planner: &dyn plan::Planner,
    walks: &[Trajectory],
) -> Vec<Option<Score>> {
    walks
        .iter()
        .map(|w| {
            let (from, to, profile) = (w.source(), w.destination(), walk_profile(w));
            let planned = planner.plan(from, to, profile).ok()?;
            // What the gateway would publish for this request.
            let reply = RouteBody::new(site, planner, profile, from, to, &planned, 0);
            let cells: Vec<Cell> = reply.waypoints.iter().map(|p| p.cell).collect();
            let line = Polyline(reply.line.iter().map(|p| [p.x_m, p.y_m]).collect());
            let repaired = planned.origin == Origin::Repaired;
            let fallback = planned.origin.is_fallback();
            let line_fallback = reply.line_from == plan::LineSource::Fallback;
            score(site, w, &cells, &line).map(|s| Score {
                repaired,
                fallback,
                line_fallback,
                ..s
            })
        })
        .collect()
}

impl Judged {
    fn new(site: &Arc<Site>, connectivity: plan::Connectivity, walks: &[Trajectory]) -> Judged {
        let shortest = plan::astar::AStar::new(site.clone(), connectivity);
        let any = plan::anyangle::AnyAngle::new(site.clone());
        Judged {
            astar: judge_planner(site, &shortest, walks),
            anyangle: judge_planner(site, &any, walks),
            straight: walks
                .iter()
                .map(|w| {
                    let r = any.straight(w.source(), w.destination(), walk_profile(w))?;
                    score(
                        site,
                        w,
                        &r.route.cells,
                        &Polyline::of_cells(site, &r.vertices),
                    )
                })
                .collect(),
        }
    }

    fn baselines(&self) -> [(&'static str, &[Option<Score>]); 3] {
        [
            ("astar", &self.astar),
            ("anyangle", &self.anyangle),
            ("straight", &self.straight),
        ]
    }

    fn baselines_report(&self) -> Value {
        Value::Object(
            self.baselines()
                .into_iter()
                .map(|(name, scores)| (name.to_owned(), summary(scores)))
                .collect(),
        )
    }

    /// A mode's summary and how often it is closer to the walks than each
    /// baseline.
    fn mode_report(&self, scores: &[Option<Score>]) -> Value {
        let mut report = summary(scores);
        let closer: serde_json::Map<String, Value> = self
            .baselines()
            .into_iter()
            .map(|(name, baseline)| (name.to_owned(), closer_than(scores, baseline)))
            .collect();
        report["closer_than"] = Value::Object(closer);
        report
    }
}

/// Medians of DTW and Fréchet, means of IoU and length ratio, over the walks
/// a judge answered; `answered_share` says how many that is.
fn summary(scores: &[Option<Score>]) -> Value {
    let answered: Vec<Score> = scores.iter().flatten().copied().collect();
    let column = |f: fn(&Score) -> f64| answered.iter().map(f).collect::<Vec<f64>>();
    json!({
        "walks": answered.len(),
        "answered_share": answered.len() as f64 / scores.len().max(1) as f64,
        "dtw_m_median": percentile(&mut column(|s| s.dtw_m), 0.5),
        "cells": {
            "dtw_m_median": percentile(&mut column(|s| s.cells_dtw_m), 0.5),
            "frechet_m_median": percentile(&mut column(|s| s.cells_frechet_m), 0.5),
        },
        "dtw_m_mean": mean(&column(|s| s.dtw_m)),
        "frechet_m_median": percentile(&mut column(|s| s.frechet_m), 0.5),
        "iou_mean": mean(&column(|s| s.iou)),
        "length_ratio_mean": mean(&column(|s| s.length_ratio)),
        "repaired_share": mean(&column(|s| f64::from(u8::from(s.repaired)))),
        "fallback_share": mean(&column(|s| f64::from(u8::from(s.fallback)))),
        "line_fallback_share": mean(&column(|s| f64::from(u8::from(s.line_fallback)))),
        "repaired_share_learned": repaired_among_learned(&answered),
    })
}

/// The share of the routes served from what the planner learned (not its
/// fallback) that needed repair.
fn repaired_among_learned(scores: &[Score]) -> Option<f64> {
    let learned: Vec<f64> = scores
        .iter()
        .filter(|s| !s.fallback)
        .map(|s| f64::from(u8::from(s.repaired)))
        .collect();
    mean(&learned)
}

/// Wins, losses and ties by DTW of `mode`'s lines against `baseline`'s over
/// the walks both answered, with the share of wins and the sign test's
/// p-value; under `cells` the same by the routes' cells.
fn closer_than(mode: &[Option<Score>], baseline: &[Option<Score>]) -> Value {
    let mut report = wins_by(mode, baseline, |s| s.dtw_m);
    report["cells"] = wins_by(mode, baseline, |s| s.cells_dtw_m);
    report
}

fn wins_by(mode: &[Option<Score>], baseline: &[Option<Score>], dtw: fn(&Score) -> f64) -> Value {
    const TIE_M: f64 = 1e-6;
    let (mut wins, mut losses, mut ties) = (0usize, 0usize, 0usize);
    for (m, b) in mode.iter().zip(baseline) {
        let (Some(m), Some(b)) = (m, b) else { continue };
        if dtw(m) < dtw(b) - TIE_M {
            wins += 1;
        } else if dtw(m) > dtw(b) + TIE_M {
            losses += 1;
        } else {
            ties += 1;
        }
    }
    let compared = wins + losses + ties;
    json!({
        "walks": compared,
        "wins": wins,
        "losses": losses,
        "ties": ties,
        "share": (compared > 0).then(|| wins as f64 / compared as f64),
        "sign_test_p": sign_test(wins, losses),
    })
}

fn evaluate_mode(
    config: &PlannerConfig,
    site: &Site,
    planner: &dyn plan::Planner,
    shortest: &plan::astar::AStar,
    pairs: &[(Cell, Cell)],
    walks: &Walks,
    unseen: Option<&[bool]>,
) -> Value {
    use plan::Planner;
    let (mut valid, mut ratios, mut deviations) = (0usize, Vec::new(), Vec::new());
    let (mut plan_us, mut gen_us, mut classify_us) = (Vec::new(), Vec::new(), Vec::new());
    let (mut trained, mut accepted, mut repaired) = (0usize, 0usize, 0usize);
    let (mut answered, mut fallback) = (0usize, 0usize);
    let mut novelty = Vec::new();
    for &(from, to) in pairs {
        let started = Instant::now();
        let answer = planner.plan(from, to, Profile::Default);
        plan_us.push(started.elapsed().as_secs_f64() * 1e6);
        let Ok(planned) = answer else { continue };
        answered += 1;
        if planned
            .route
            .validate(site, from, to, config.connectivity)
            .is_ok()
        {
            valid += 1;
        }
        if let Ok(best) = shortest.plan(from, to, Profile::Default) {
            let best_m = best.route.length_m(site);
            if best_m > 0.0 {
                ratios.push(planned.route.length_m(site) / best_m);
            }
        }
        if let Some(frame) = &planned.frame {
            deviations.push(plan::deviation_score(site, frame));
            if let Some(training) = &walks.training
                && let Some(d) = training.nearest_distance(&CellBits::from_frame(site, frame))
            {
                novelty.push(f64::from(d));
            }
        }
        // Model times of the requests that ran the models (rejection mode
        // answers some from frames generated for earlier requests).
        if planned.samples > 0 {
            gen_us.push(planned.timings.gen_us as f64);
            if planned.timings.classify_us > 0 {
                classify_us.push(planned.timings.classify_us as f64);
            }
        }
        match planned.origin {
            Origin::Frame => accepted += 1,
            Origin::Repaired => repaired += 1,
            origin if origin.is_fallback() => fallback += 1,
            _ => {}
        }
        if !matches!(planned.origin, Origin::Untrained)
            && !planned.origin.is_fallback()
            && (planned.frame.is_some() || planned.line.is_some())
        {
            trained += 1;
        }
    }
    let learned = planner.model_version().is_some();
    let (human_iou_gan, human_iou_gan_unseen) = match &walks.heldout {
        Some(heldout) if learned => iou_means(Some(&human_iou(site, planner, heldout)), unseen),
        _ => (None, None),
    };
    let is_rejection = planner.mode() == "rejection";
    let classifier_error = if is_rejection {
        PathClassifier::load(&config.models.path_classifier, site)
            .ok()
            .and_then(|c| c.model().metadata().metrics.get("heldout_error").copied())
    } else {
        None
    };
    // Accepted frames may still need repair; both count as accepted by the
    // classifier, budget-exhausted ones do not.
    let acceptance =
        (is_rejection && trained > 0).then(|| (accepted + repaired) as f64 / trained as f64);
    json!({
        "pairs": pairs.len(),
        "valid_rate": valid as f64 / pairs.len().max(1) as f64,
        "deviation_score_mean": mean(&deviations),
        "deviation_score_max": deviations.iter().copied().reduce(f64::max),
        "length_ratio_mean": mean(&ratios),
        "classifier_error": classifier_error,
        "novelty": mean(&novelty),
        "human_iou_gan": human_iou_gan,
        "human_iou_gan_unseen": human_iou_gan_unseen,
        "human_iou_astar": Value::Null,
        "human_iou_astar_unseen": Value::Null,
        "rejection_acceptance_rate": acceptance,
        "learned_pairs": trained,
        "repaired_share": (trained > 0).then(|| repaired as f64 / trained as f64),
        "fallback_share": (learned && answered > 0).then(|| fallback as f64 / answered as f64),
        "repaired_share_all": (learned && answered > 0).then(|| repaired as f64 / answered as f64),
        "model_version": planner.model_version(),
        "gen_us_p50": percentile(&mut gen_us, 0.5),
        "classify_us_p50": percentile(&mut classify_us, 0.5),
        "plan_us_p50": percentile(&mut plan_us, 0.5),
        "plan_us_p99": percentile(&mut plan_us, 0.99),
    })
}

/// Mean IoU over every held-out walk, and over those `unseen` marks (no
/// training walk repeats them exactly; `None` without training walks): a
/// planner that memorised training walks scores well on the others for free.
fn iou_means(ious: Option<&[f64]>, unseen: Option<&[bool]>) -> (Option<f64>, Option<f64>) {
    let Some(ious) = ious else {
        return (None, None);
    };
    let over_unseen = unseen.and_then(|keep| {
        let kept: Vec<f64> = ious
            .iter()
            .zip(keep)
            .filter(|&(_, &k)| k)
            .map(|(&v, _)| v)
            .collect();
        mean(&kept)
    });
    (mean(ious), over_unseen)
}

/// Cell-set IoU of `planner`'s route with each walk, planned for the walk's
/// first and last cell and its profile (default when it names none or one
/// this gateway does not know); a request that fails scores 0 (it shares no
/// cell).
fn human_iou(site: &Site, planner: &dyn plan::Planner, walks: &[Trajectory]) -> Vec<f64> {
    walks
        .iter()
        .map(|w| {
            planner
                .plan(w.source(), w.destination(), walk_profile(w))
                .map_or(0.0, |p| cell_iou(site, &p.route.cells, &w.cells))
        })
        .collect()
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

pub(crate) fn percentile(v: &mut [f64], q: f64) -> Option<f64> {
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    Some(v[((v.len() - 1) as f64 * q).round() as usize])
}
