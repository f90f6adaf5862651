//! What `gangway train` does: which models it trains from which data, what it
//! measures on them and which files it writes.
//!
//! From walks: `desire_lines.onnx` ([`train_desire`], walks in JSON Lines),
//! `path_classifier.onnx` (trained on ~80 % of the walks of each
//! class, error measured on the rest), `generator.onnx` and
//! `discriminator.onnx` (the paper's GAN on the classed walks; only when the
//! walks have two classes or more) and, with
//! `conditional`, `conditional_generator.onnx` and
//! `conditional_discriminator.onnx` (on every walk, each in both directions).
//! From a survey: `cell_classifier.onnx`, with sessions held out.
//!
//! Each generator is then checked against [`Check`]s (endpoint hit rate,
//! walkable share, repair rate, distinct frames): training that produced a
//! generator unfit to serve says so instead of writing it where planners
//! load models. A failed pair goes to `failed/` inside the output directory
//! (kept for inspection) unless `accept_failed`, and the caller exits
//! non-zero naming every failed check and what to try.
//!
//! With `checkpoint_every`, each GAN's generator and discriminator are also
//! written every that many iterations to `checkpoints/iter-<N>/`, the same
//! files with `iterations` = N in their metadata, so a checkpoint directory
//! loads like any models directory (`gangway eval planning --checkpoints`
//! plots the deviation score over them).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use anyhow::Context;
use ndarray::{Array2, ArrayView1, ArrayView2, Axis, s};
use rand::SeedableRng;
use rand::rngs::Xoshiro256PlusPlus;
use rand_distr::{Distribution, StandardNormal};
use rayon::prelude::*;

use super::cells::CellSet;
use super::classifier::{self, ClassifierConfig};
use super::desire::{self, cell_of};
use super::gan::{self, GanConfig, GanData, Hidden, NOISE_DIM};
use super::line_access::{LineAccess, LineRequest};
use super::mlp::{Adam, Mlp};
use super::paths::PathSet;
use super::trajectory::Trajectory;
use crate::locate::survey::Survey;
use crate::model::checks::{Check, checks};
use crate::model::desire::POINTS;
use crate::model::export::{ClipScale, Head, Spec, Weights};
use crate::model::line_gan::{self, ENDPOINTS_LEN, SHAPE_LEN};
use crate::model::{CellClassifierInput, Kind, Metadata, condition};
use crate::plan::anyangle::{GridPoint, centre, on_grid, traverse};
use crate::plan::desire::{prior_line, resample, walkable_line};
use crate::plan::frame::{bright, route_from_frame};
use crate::plan::{Connectivity, Origin, Profile, cells_off_area};
use crate::site::{Cell, Site};

#[derive(Clone, Debug)]
pub struct Options {
    pub iterations: usize,
    pub batch: usize,
    pub seed: u64,
    pub conditional: bool,
    /// Iterations of the path classifier and of the cell classifier.
    pub classifier_iterations: usize,
    pub heldout_share: f64,
    /// Also write the GANs every this many iterations (`checkpoints/`).
    pub checkpoint_every: Option<std::num::NonZeroUsize>,
    /// Write generators that fail their checks where planners load them
    /// anyway (experiments, tests of the plumbing with a few iterations).
    pub accept_failed: bool,
    /// Threads for the networks' arithmetic ([`super::workers`]); a seed and
    /// a thread count give the same weights.
    pub threads: usize,
}

/// A model written by a training run.
#[derive(Clone, Debug)]
pub struct Trained {
    pub file: PathBuf,
    pub kind: Kind,
    pub parameters: usize,
    pub bytes: u64,
    pub seconds: f64,
    pub metrics: BTreeMap<String, f64>,
    /// What the model was held to (generators; empty for the others).
    pub checks: Vec<Check>,
}

impl Trained {
    /// Whether every check passed.
    pub fn passed(&self) -> bool {
        self.checks.iter().all(Check::passed)
    }
}

/// Told about each training stage and iteration (the CLI draws progress bars);
/// `Send`: the training loops run on the trainer's own threads
/// ([`super::workers::Workers::run`]).
pub trait Progress: Send {
    fn stage(&mut self, name: &str, iterations: usize);
    fn step(&mut self, iteration: usize, losses: &[(&str, f32)]);
    fn done(&mut self);
}

/// Generated samples drawn to measure a generator.
const EVAL_SAMPLES: usize = 1024;
/// Walks' endpoint pairs the conditional generator is measured on when the
/// walks have no classes.
const EVAL_PAIRS: usize = 64;
/// A generated frame counts as recognised when the classifier gives its class
/// at least this probability.
const CONFIDENT: f32 = 0.9;

/// The line GAN's hidden widths. Its samples are 30 numbers and its
/// condition 4, not `W·H` each: a generator of the paper's widths would
/// spend most of a request's time in its 1024-wide layer for no better
/// lines (measured on the sample site's walks, BENCHMARKS.md "Path models").
const LINE_HIDDEN: Hidden = Hidden {
    generator: &[256, 256],
    discriminator: &[256, 128],
};
/// Walks' end pairs (each direction one request) the line generator is
/// measured on, at most.
const LINE_EVAL_REQUESTS: usize = 256;
/// Width of the line GAN's condition: the request's ends, then its prior.
const CONDITION_LEN: usize = ENDPOINTS_LEN + SHAPE_LEN;
/// The step, in chords, to which two line shapes must differ to count as
/// distinct.
const SHAPE_STEP: f32 = 0.05;

/// Whether `set` has the classes the paper's models (path classifier and
/// GAN, the rejection mode) need: `Err` says why not.
pub fn rejection_trainable(set: &PathSet) -> Result<(), String> {
    if set.classes.len() >= 2 {
        Ok(())
    } else {
        Err(format!(
            "the walks have {} source/destination pairs with enough walks to be a class; \
             a path classifier needs at least 2",
            set.classes.len()
        ))
    }
}

/// Trains the path models on `set` and writes them to `out`: the paper's
/// path classifier and GAN when the walks have the classes for them
/// ([`rejection_trainable`]; else only with `conditional`, which needs no
/// classes), and with `conditional` the conditional generator with the
/// access penalty of `access_weight` ([`gan::access_penalty`], 0: the
/// paper's plain loss). The unconditional GAN always keeps the paper's loss:
/// its planner (the paper's Algorithm 1) rejects frames that leave the
/// public-access area anyway.
pub fn train_paths(
    site: &Site,
    set: &PathSet,
    options: &Options,
    access_weight: f32,
    out: &Path,
    progress: &mut dyn Progress,
) -> anyhow::Result<Vec<Trained>> {
    let mut written = Vec::new();
    match rejection_trainable(set) {
        Ok(()) => written.extend(train_rejection(site, set, options, out, progress)?),
        Err(why) if !options.conditional => anyhow::bail!(why),
        Err(_) => {}
    }
    if options.conditional {
        let conditional = GanRun {
            stage: "conditional GAN",
            kinds: [Kind::ConditionalGenerator, Kind::ConditionalDiscriminator],
            data: conditional_data(set),
            io: Io {
                sample: ("frame", set.frames.ncols()),
                condition: vec![("condition", condition::len(set.width, set.height))],
            },
            penalty: Some(Box::new(gan::Access {
                blocked: site.blocked_indices().to_vec(),
                weight: access_weight,
            })),
            meta: gan_metadata(
                Kind::ConditionalGenerator,
                site,
                set,
                options,
                access_weight,
            ),
        };
        written.extend(train_gan(
            out,
            conditional,
            gan_config(options, Hidden::PAPER),
            options,
            progress,
            |generator| measure_conditional(site, set, generator, options.seed),
        )?);
    }
    Ok(written)
}

/// Trains the line GAN ([`crate::model::line_gan`]) on `walks`, each in both
/// directions, with the access penalty of `access_weight`
/// ([`super::line_access`], 0: the plain loss), measures its generator on the
/// walks' ends and writes the pair to `out` (to `failed/` when it fails its
/// checks, unless `accept_failed`).
pub fn train_lines(
    site: &Site,
    walks: &[Trajectory],
    options: &Options,
    access_weight: f32,
    out: &Path,
    progress: &mut dyn Progress,
) -> anyhow::Result<Vec<Trained>> {
    let prepared: Vec<desire::Walk> = walks
        .iter()
        .filter_map(|w| desire::prepare(site, w))
        .collect();
    anyhow::ensure!(
        prepared.len() >= 2,
        "the line GAN needs at least 2 walks whose ends are a cell or more apart; got {} of {}",
        prepared.len(),
        walks.len()
    );
    // Each walk in both directions, with the prior its request gets (the
    // any-angle route: per walk and independent, on the threads of the
    // rayon pool this runs in, collected in walk order); a walk whose ends
    // no route joins is left out.
    let directions: Vec<([GridPoint; 2], [[f32; 2]; POINTS])> = prepared
        .iter()
        .flat_map(|w| {
            let [a, b] = w.ends;
            [([a, b], w.shape), ([b, a], desire::backwards(&w.shape))]
        })
        .collect();
    let rows: Vec<(LineRequest, [[f32; 2]; POINTS])> = directions
        .par_iter()
        .filter_map(|&([a, b], shape)| {
            let prior = prior_line(site, Profile::Default, cell_of(a), cell_of(b)).ok()?;
            let prior = line_gan::offsets(&resample(&prior, POINTS), a, b);
            Some((
                LineRequest {
                    ends: [a, b],
                    prior,
                },
                shape,
            ))
        })
        .collect();
    let (w, h) = (site.width(), site.height());
    let mut frames = Array2::zeros((rows.len(), SHAPE_LEN));
    let mut conditions = Array2::zeros((rows.len(), CONDITION_LEN));
    let mut requests = Vec::new();
    let mut seen = std::collections::HashSet::new();
    for (row, (request, shape)) in rows.iter().enumerate() {
        let [a, b] = request.ends;
        frames
            .row_mut(row)
            .assign(&ArrayView1::from(&line_gan::shape_sample(
                shape,
                &request.prior,
            )));
        let mut condition = conditions.row_mut(row);
        condition
            .slice_mut(s![..ENDPOINTS_LEN])
            .assign(&ArrayView1::from(&line_gan::endpoints(w, h, a, b)));
        condition
            .slice_mut(s![ENDPOINTS_LEN..])
            .assign(&ArrayView1::from(&request.prior));
        let pair = (cell_of(a), cell_of(b));
        if requests.len() < LINE_EVAL_REQUESTS && seen.insert(pair) {
            requests.push((pair, row));
        }
    }
    let mut meta = Metadata::for_site(Kind::LineGenerator, site);
    meta.noise_dim = NOISE_DIM;
    meta.iterations = options.iterations;
    meta.seed = options.seed;
    meta.access_weight = access_weight;
    let measured: Vec<usize> = requests.iter().map(|r| r.1).collect();
    let walked = frames.select(Axis(0), &measured);
    let asked = conditions.select(Axis(0), &measured);
    let requests: Vec<(Cell, Cell)> = requests.into_iter().map(|r| r.0).collect();
    let penalty = LineAccess::new(site, rows.into_iter().map(|r| r.0).collect(), access_weight);
    let run = GanRun {
        stage: "line GAN",
        kinds: [Kind::LineGenerator, Kind::LineDiscriminator],
        data: GanData {
            frames,
            conditions: Some(conditions),
        },
        io: Io {
            sample: ("shape", SHAPE_LEN),
            condition: vec![("endpoints", ENDPOINTS_LEN), ("prior", SHAPE_LEN)],
        },
        penalty: Some(Box::new(penalty)),
        meta,
    };
    train_gan(
        out,
        run,
        gan_config(options, LINE_HIDDEN),
        options,
        progress,
        |generator| {
            measure_lines(
                site,
                &requests,
                asked.view(),
                walked.view(),
                generator,
                options.seed,
            )
        },
    )
}

/// The paper's models (rejection mode): the path classifier, 0/1 frames →
/// class, and the GAN on the classed walks.
fn train_rejection(
    site: &Site,
    set: &PathSet,
    options: &Options,
    out: &Path,
    progress: &mut dyn Progress,
) -> anyhow::Result<Vec<Trained>> {
    let classed = set.classed_rows();
    let mut written = Vec::new();
    // Path classifier: 0/1 frames → class.
    let started = Instant::now();
    let labels: Vec<usize> = set.labels.iter().map(|l| l.unwrap_or(usize::MAX)).collect();
    let strata: Vec<usize> = classed.iter().map(|&r| labels[r]).collect();
    let (train_rows, held_rows) = {
        let (t, h) =
            classifier::split_by_group(&strata, &classed, options.heldout_share, options.seed);
        (
            t.iter().map(|&i| classed[i]).collect::<Vec<_>>(),
            h.iter().map(|&i| classed[i]).collect::<Vec<_>>(),
        )
    };
    let config = ClassifierConfig {
        hidden: vec![256],
        iterations: options.classifier_iterations,
        batch: options.batch,
        seed: options.seed,
        adam: Adam::DEFAULT,
        threads: options.threads,
    };
    progress.stage("path classifier", config.iterations);
    let mut path_classifier = classifier::train(
        set.frames.view(),
        &labels,
        set.classes.len(),
        &train_rows,
        &config,
        |i, loss| progress.step(i, &[("loss", loss)]),
    );
    progress.done();
    let error =
        classifier::error_rate(&mut path_classifier, set.frames.view(), &labels, &held_rows);
    let mut meta = Metadata::for_site(Kind::PathClassifier, site);
    meta.classes = set.classes.clone();
    meta.iterations = config.iterations;
    meta.seed = options.seed;
    meta.metrics.insert("heldout_error".into(), error);
    meta.metrics
        .insert("heldout_walks".into(), held_rows.len() as f64);
    meta.metrics
        .insert("train_walks".into(), train_rows.len() as f64);
    written.push(write(
        out,
        &Spec {
            layers: path_classifier.layer_views(),
            weights: Weights::F32,
            inputs: &[("frame", set.frames.ncols())],
            normalize: None,
            head: Head::Softmax,
            output: "probs",
        },
        meta,
        started,
    )?);

    // The paper's GAN on the classed walks.
    let frames = to_signed(&set.frames, &classed);
    let data = GanData {
        frames,
        conditions: None,
    };
    let plain = GanRun {
        stage: "GAN",
        kinds: [Kind::Generator, Kind::Discriminator],
        data,
        io: Io {
            sample: ("frame", set.frames.ncols()),
            condition: Vec::new(),
        },
        penalty: None,
        meta: gan_metadata(Kind::Generator, site, set, options, 0.0),
    };
    written.extend(train_gan(
        out,
        plain,
        gan_config(options, Hidden::PAPER),
        options,
        progress,
        |generator| measure_generator(site, generator, &mut path_classifier, options.seed),
    )?);
    Ok(written)
}

fn gan_config(options: &Options, hidden: Hidden) -> GanConfig {
    GanConfig {
        iterations: options.iterations,
        batch: options.batch,
        seed: options.seed,
        threads: options.threads,
        hidden,
    }
}

/// One GAN to train: its progress stage, what it learns from and the model
/// kinds it is written as.
struct GanRun<'a> {
    stage: &'a str,
    kinds: [Kind; 2],
    data: GanData,
    io: Io,
    /// The generator's access penalty (`None`: the paper's plain loss).
    penalty: Option<Box<dyn gan::Penalty>>,
    meta: Metadata,
}

/// What a GAN's networks are fed, as its exported graphs name them: the
/// sample (a frame, or a line's shape) and the condition's parts, if any;
/// the generator takes `noise` and the condition, the discriminator the
/// sample and the condition.
struct Io {
    sample: (&'static str, usize),
    condition: Vec<(&'static str, usize)>,
}

/// Trains `run` (writing checkpoints when asked for), measures its generator
/// with `measure`, adds the training time and writes the pair to `out`.
fn train_gan(
    out: &Path,
    run: GanRun,
    config: GanConfig,
    options: &Options,
    progress: &mut dyn Progress,
    measure: impl FnOnce(&mut Mlp) -> BTreeMap<String, f64>,
) -> anyhow::Result<Vec<Trained>> {
    let started = Instant::now();
    progress.stage(run.stage, config.iterations);
    let mut trained = gan::train_with_checkpoints(
        &run.data,
        config,
        run.penalty.as_deref(),
        options.checkpoint_every,
        |i, l| progress.step(i, &gan_losses(l)),
        |i, gan| write_checkpoint(out, i, run.kinds, gan, &run.io, &run.meta),
    )?;
    progress.done();
    let seconds = started.elapsed().as_secs_f64();
    trained.generator.round_weights_to_f16();
    let mut metrics = measure(&mut trained.generator);
    metrics.insert("train_seconds".into(), seconds);
    let checks = checks(run.kinds[0], &metrics);
    let dir = destination(out, &checks, options)?;
    let mut written = write_gan(
        &dir, run.kinds, &trained, &run.io, run.meta, &metrics, started,
    )?;
    for t in &mut written {
        t.checks = checks.clone();
    }
    Ok(written)
}

/// Where a model that was held to `checks` is written: `out` when it passed
/// them (or `accept_failed`), else `out/failed/`, where planners do not look.
fn destination(out: &Path, checks: &[Check], options: &Options) -> anyhow::Result<PathBuf> {
    if checks.iter().all(Check::passed) || options.accept_failed {
        return Ok(out.to_owned());
    }
    let dir = out.join("failed");
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    Ok(dir)
}

/// Trains the desire lines on `walks` (cross-validating their settings) and
/// writes `desire_lines.onnx` to `out`, or to `out/failed/` when it fails its
/// checks (unless `accept_failed`).
pub fn train_desire(
    site: &Site,
    walks: &[Trajectory],
    options: &Options,
    out: &Path,
    progress: &mut dyn Progress,
) -> anyhow::Result<Trained> {
    let started = Instant::now();
    progress.stage("desire lines", 1);
    // Its per-walk work on `options.threads` threads (same model for any).
    let site_arc = std::sync::Arc::new(site.clone());
    let trained = rayon::ThreadPoolBuilder::new()
        .num_threads(options.threads.max(1))
        .build()?
        .install(|| desire::train(&site_arc, walks))?;
    progress.done();
    let mut meta = Metadata::for_site(Kind::DesireLines, site);
    meta.seed = options.seed;
    meta.metrics = trained.metrics;
    meta.metrics
        .insert("train_seconds".into(), started.elapsed().as_secs_f64());
    let checks = checks(Kind::DesireLines, &meta.metrics);
    let dir = destination(out, &checks, options)?;
    let file = dir.join(format!("{}.onnx", Kind::DesireLines.name()));
    if dir != out {
        // Lines from an earlier run must not be served as this run's.
        let stale = out.join(file.file_name().expect("a file name"));
        if stale.is_file() {
            std::fs::remove_file(&stale)
                .with_context(|| format!("cannot remove {}", stale.display()))?;
        }
    }
    super::write_proto(&file, &trained.model.to_onnx(&meta))
        .with_context(|| format!("cannot write {}", file.display()))?;
    let m = &trained.model;
    Ok(Trained {
        bytes: std::fs::metadata(&file)?.len(),
        file,
        kind: Kind::DesireLines,
        // Per bank line: 4 endpoint coordinates and the shape's 2 per point.
        parameters: m.ends.len() * (4 + 2 * crate::model::desire::POINTS) + 2,
        seconds: started.elapsed().as_secs_f64(),
        metrics: meta.metrics,
        checks,
    })
}

/// Trains the localization cell classifier on `survey` and writes it to `out`.
pub fn train_cells(
    site: &Site,
    survey: &Survey,
    options: &Options,
    out: &Path,
    progress: &mut dyn Progress,
) -> anyhow::Result<Trained> {
    let started = Instant::now();
    let set = CellSet::from_survey(site, survey).map_err(anyhow::Error::msg)?;
    anyhow::ensure!(!set.labels.is_empty(), "the survey has no rows");
    let strata = vec![0; set.labels.len()];
    let (train_rows, held_rows) =
        classifier::split_by_group(&strata, &set.sessions, options.heldout_share, options.seed);
    let config = ClassifierConfig {
        hidden: vec![128, 128],
        iterations: options.classifier_iterations,
        batch: 64,
        seed: options.seed,
        adam: Adam::DEFAULT,
        threads: options.threads,
    };
    progress.stage("cell classifier", config.iterations);
    let cells = site.open_cells();
    let mut net = classifier::train(
        set.features.view(),
        &set.labels,
        cells.len(),
        &train_rows,
        &config,
        |i, loss| progress.step(i, &[("loss", loss)]),
    );
    progress.done();
    let predicted = classifier::predict(&mut net, set.features.view(), &held_rows);
    let mut meta = Metadata::for_site(Kind::CellClassifier, site);
    meta.anchors = survey.anchors.clone();
    meta.iterations = config.iterations;
    meta.seed = options.seed;
    if !held_rows.is_empty() {
        let wrong = held_rows
            .iter()
            .zip(&predicted)
            .filter(|&(&r, &p)| set.labels[r] != p)
            .count();
        let metres: f64 = held_rows
            .iter()
            .zip(&predicted)
            .map(|(&r, &p)| cells[set.labels[r]].distance(cells[p]) * site.cell_m)
            .sum();
        meta.metrics.insert(
            "heldout_error".into(),
            wrong as f64 / held_rows.len() as f64,
        );
        meta.metrics.insert(
            "heldout_mean_error_m".into(),
            metres / held_rows.len() as f64,
        );
    }
    meta.metrics
        .insert("heldout_rows".into(), held_rows.len() as f64);
    meta.metrics
        .insert("train_rows".into(), train_rows.len() as f64);
    let floor = CellClassifierInput::RSSI_FLOOR_DBM;
    let ceil = CellClassifierInput::RSSI_CEIL_DBM;
    write(
        out,
        &Spec {
            layers: net.layer_views(),
            weights: Weights::F32,
            inputs: &[("rssi", survey.anchors.len())],
            normalize: Some(ClipScale {
                lo: floor,
                hi: ceil,
                offset: -floor,
                scale: 1.0 / (ceil - floor),
            }),
            head: Head::LogSoftmax,
            output: "log_probs",
        },
        meta,
        started,
    )
}

fn gan_metadata(
    kind: Kind,
    site: &Site,
    set: &PathSet,
    options: &Options,
    access_weight: f32,
) -> Metadata {
    let mut meta = Metadata::for_site(kind, site);
    meta.classes = set.classes.clone();
    meta.noise_dim = NOISE_DIM;
    meta.iterations = options.iterations;
    meta.seed = options.seed;
    meta.access_weight = access_weight;
    meta
}

/// What the progress bar shows of a GAN iteration.
fn gan_losses(l: gan::GanLosses) -> [(&'static str, f32); 3] {
    [
        ("d", l.discriminator),
        ("g", l.generator),
        ("access", l.access),
    ]
}

/// Writes a trained GAN's generator and discriminator (`kinds`, in that order)
/// with the same metadata and metrics, fed as `io` says.
fn write_gan(
    out: &Path,
    kinds: [Kind; 2],
    trained: &gan::Gan,
    io: &Io,
    meta: Metadata,
    metrics: &BTreeMap<String, f64>,
    started: Instant,
) -> anyhow::Result<Vec<Trained>> {
    let with_condition = |first: (&'static str, usize)| {
        let mut inputs = vec![first];
        inputs.extend(io.condition.iter().copied());
        inputs
    };
    let [generator, discriminator] = kinds;
    [
        (
            generator,
            &trained.generator,
            Weights::F16,
            with_condition(("noise", NOISE_DIM)),
            io.sample.0,
            Head::None,
        ),
        (
            discriminator,
            &trained.discriminator,
            Weights::F32,
            with_condition(io.sample),
            "real",
            Head::Sigmoid,
        ),
    ]
    .into_iter()
    .map(|(kind, net, weights, inputs, output, head)| {
        let meta = Metadata {
            kind,
            metrics: metrics.clone(),
            ..meta.clone()
        };
        write(
            out,
            &Spec {
                layers: net.layer_views(),
                weights,
                inputs: &inputs,
                normalize: None,
                head,
                output,
            },
            meta,
            started,
        )
    })
    .collect()
}

/// Writes the GAN as it is after `iteration` iterations to
/// `out/checkpoints/iter-<iteration>/` with [`write_gan`]; its metadata says
/// `iteration` iterations and carries no metrics (none are measured mid-run).
fn write_checkpoint(
    out: &Path,
    iteration: usize,
    kinds: [Kind; 2],
    gan: &gan::Gan,
    io: &Io,
    meta: &Metadata,
) -> anyhow::Result<()> {
    let dir = out.join("checkpoints").join(format!("iter-{iteration:07}"));
    std::fs::create_dir_all(&dir).with_context(|| format!("cannot create {}", dir.display()))?;
    let meta = Metadata {
        iterations: iteration,
        ..meta.clone()
    };
    write_gan(&dir, kinds, gan, io, meta, &BTreeMap::new(), Instant::now())?;
    Ok(())
}

fn write(out: &Path, spec: &Spec, meta: Metadata, started: Instant) -> anyhow::Result<Trained> {
    let file = out.join(format!("{}.onnx", meta.kind.name()));
    super::write_model(&file, spec, &meta)
        .with_context(|| format!("cannot write {}", file.display()))?;
    Ok(Trained {
        bytes: std::fs::metadata(&file)?.len(),
        file,
        kind: meta.kind,
        parameters: spec.parameters(),
        seconds: started.elapsed().as_secs_f64(),
        metrics: meta.metrics,
        checks: Vec::new(),
    })
}

/// The chosen rows of 0/1 frames as ±1, the generator's range.
fn to_signed(frames: &Array2<f32>, rows: &[usize]) -> Array2<f32> {
    frames.select(Axis(0), rows).mapv(|v| 2.0 * v - 1.0)
}

/// Every walk, once per direction: frames carry no direction, so the
/// condition (a, b) and (b, a) must both give the walk.
fn conditional_data(set: &PathSet) -> GanData {
    let n = set.walks.len();
    let all: Vec<usize> = (0..n).collect();
    let once = to_signed(&set.frames, &all);
    let frames = ndarray::concatenate(Axis(0), &[once.view(), once.view()]).expect("same widths");
    let len = condition::len(set.width, set.height);
    let mut conditions = Array2::zeros((2 * n, len));
    for (i, walk) in set.walks.iter().enumerate() {
        let (a, b) = (walk.source, walk.destination);
        for (row, (from, to)) in [(i, (a, b)), (n + i, (b, a))] {
            let out = conditions
                .row_mut(row)
                .into_slice()
                .expect("standard layout");
            condition::encode(set.width, set.height, from, to, out);
        }
    }
    GanData {
        frames,
        conditions: Some(conditions),
    }
}

fn noise(rows: usize, seed: u64) -> Array2<f32> {
    // A seed apart from training's, so measurement does not replay training noise.
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed ^ 0x5eed_e7a1);
    Array2::from_shape_simple_fn((rows, NOISE_DIM), || StandardNormal.sample(&mut rng))
}

/// How walk-like the unconditional generator's frames are: the share of their
/// path cells that are walkable, the share the classifier recognises with at
/// least [`CONFIDENT`] probability, their mean size and how many differ.
fn measure_generator(
    site: &Site,
    generator: &mut Mlp,
    classifier: &mut Mlp,
    seed: u64,
) -> BTreeMap<String, f64> {
    let frames = generator.predict(noise(EVAL_SAMPLES, seed).view());
    let binary = frames.mapv(|v| f32::from(u8::from(v > 0.0)));
    let (on, walkable) = lit_cells(site, &frames);
    let logits = classifier.predict(binary.view());
    let confident = logits
        .rows()
        .into_iter()
        .filter(|row| {
            let max = row.fold(f32::NEG_INFINITY, |a, &b| a.max(b));
            let sum: f32 = row.iter().map(|&z| (z - max).exp()).sum();
            1.0 / sum >= CONFIDENT
        })
        .count();
    BTreeMap::from([
        (
            "walkable_share".to_owned(),
            walkable as f64 / on.max(1) as f64,
        ),
        (
            "confident_share".to_owned(),
            confident as f64 / EVAL_SAMPLES as f64,
        ),
        (
            "mean_path_cells".to_owned(),
            on as f64 / EVAL_SAMPLES as f64,
        ),
        ("distinct_share".to_owned(), distinct_share(&binary)),
    ])
}

/// Cells on the path (> 0) in generated `frames`, and how many of them are
/// walkable.
fn lit_cells(site: &Site, frames: &Array2<f32>) -> (usize, usize) {
    let (mut on, mut off_area) = (0usize, 0usize);
    for row in frames.rows() {
        let row = row.to_slice().expect("standard layout");
        on += (0..row.len()).filter(|&i| bright(row, i)).count();
        off_area += cells_off_area(site, row);
    }
    (on, on - off_area)
}

/// Share of distinct frames among generated ones: near 0 means the generator
/// collapsed to a few frames.
fn distinct_share(binary: &Array2<f32>) -> f64 {
    let distinct: std::collections::HashSet<Vec<bool>> = binary
        .rows()
        .into_iter()
        .map(|r| r.iter().map(|&v| v > 0.0).collect())
        .collect();
    distinct.len() as f64 / binary.nrows().max(1) as f64
}

/// How well the line generator answers `requests` (source and destination
/// cells), [`EVAL_SAMPLES`] lines in all: the share of the cells its lines
/// cross, as generated, that are walkable; the share the planner must
/// repair ([`walkable_line`]: a wall or the floor's edge crossed); and how
/// many distinct shapes it gives for the requests, one line each, against
/// how many the `walked` shapes of those requests' walks have (both to
/// [`SHAPE_STEP`] of the chord): near `1/requests` when it collapsed to one
/// shape. Against the walks, because people's walks between most pairs of
/// a plaza are near straight lines: the same shape, to any step a map would
/// show. (Whether it heeds the walls between the ends it is asked for is
/// what the walkable and repaired shares measure.)
fn measure_lines(
    site: &Site,
    requests: &[(Cell, Cell)],
    conditions: ArrayView2<f32>,
    walked: ArrayView2<f32>,
    generator: &mut Mlp,
    seed: u64,
) -> BTreeMap<String, f64> {
    let per = EVAL_SAMPLES / requests.len().max(1) + 1;
    let rows = per * requests.len();
    let mut input = Array2::zeros((rows, NOISE_DIM + CONDITION_LEN));
    input
        .slice_mut(s![.., ..NOISE_DIM])
        .assign(&noise(rows, seed));
    for row in 0..rows {
        input
            .slice_mut(s![row, NOISE_DIM..])
            .assign(&conditions.row(row / per));
    }
    let samples = generator.predict(input.view());
    let (mut crossed, mut walkable, mut repaired) = (0usize, 0usize, 0usize);
    for (row, k) in samples.rows().into_iter().zip(0..) {
        let (from, to) = requests[k / per];
        let sample = row.to_slice().expect("standard layout");
        let condition = conditions.row(k / per);
        let prior = &condition.as_slice().expect("standard layout")[ENDPOINTS_LEN..];
        let line = line_gan::line(centre(from), centre(to), prior, sample);
        for (i, seg) in line.windows(2).enumerate() {
            // Each segment after the first starts in the cell the one
            // before ended in.
            for &raw in &traverse(seg[0], seg[1]).cells[usize::from(i > 0)..] {
                crossed += 1;
                walkable += usize::from(on_grid(site, raw).is_some_and(|c| site.walkable(c)));
            }
        }
        if !matches!(
            walkable_line(site, Profile::Default, &line, from, to),
            Ok((_, false))
        ) {
            repaired += 1;
        }
    }
    let distinct = |shapes: ArrayView2<f32>| {
        let steps: std::collections::HashSet<Vec<i32>> = shapes
            .rows()
            .into_iter()
            .map(|r| r.iter().map(|&v| (v / SHAPE_STEP).round() as i32).collect())
            .collect();
        steps.len() as f64
    };
    let firsts: Vec<usize> = (0..requests.len()).map(|k| k * per).collect();
    let generated = distinct(samples.select(Axis(0), &firsts).view());
    let walks = distinct(walked);
    BTreeMap::from([
        (
            "walkable_share".to_owned(),
            walkable as f64 / crossed.max(1) as f64,
        ),
        ("repaired_share".to_owned(), repaired as f64 / rows as f64),
        (
            "distinct_share".to_owned(),
            generated / requests.len().max(1) as f64,
        ),
        (
            "walks_distinct_share".to_owned(),
            walks / requests.len().max(1) as f64,
        ),
        ("distinct_vs_walks".to_owned(), generated / walks.max(1.0)),
        ("requests".to_owned(), requests.len() as f64),
    ])
}

/// How well the conditional generator answers each class pair (or, without
/// classes, up to [`EVAL_PAIRS`] walks' endpoint pairs; both directions): the share of its frames that have both the source and the
/// destination on the path, their mean size (a frame with every cell on would
/// hit trivially) and the share of their path cells that are walkable.
fn measure_conditional(
    site: &Site,
    set: &PathSet,
    generator: &mut Mlp,
    seed: u64,
) -> BTreeMap<String, f64> {
    // The classes' pairs; walks whose endpoints are all distinct pairs have
    // no classes, and are asked for their own endpoints instead.
    let mut pairs: Vec<(Cell, Cell)> = set
        .classes
        .iter()
        .map(|c| (c.source, c.destination))
        .collect();
    if pairs.is_empty() {
        let mut seen = std::collections::HashSet::new();
        pairs = set
            .walks
            .iter()
            .map(|w| (w.source, w.destination))
            .filter(|p| seen.insert(*p))
            .take(EVAL_PAIRS)
            .collect();
    }
    let per_class = EVAL_SAMPLES / (2 * pairs.len()).max(1) + 1;
    let rows = per_class * 2 * pairs.len();
    let len = condition::len(set.width, set.height);
    let mut input = Array2::zeros((rows, NOISE_DIM + len));
    input
        .slice_mut(s![.., ..NOISE_DIM])
        .assign(&noise(rows, seed));
    let mut ends = Vec::with_capacity(rows);
    for (k, &(source, destination)) in pairs.iter().enumerate() {
        for (d, (from, to)) in [(source, destination), (destination, source)]
            .into_iter()
            .enumerate()
        {
            for j in 0..per_class {
                let row = (2 * k + d) * per_class + j;
                let mut cond = input.slice_mut(s![row, NOISE_DIM..]);
                condition::encode(
                    set.width,
                    set.height,
                    from,
                    to,
                    cond.as_slice_mut().expect("contiguous row"),
                );
                ends.push((from, to));
            }
        }
    }
    let frames = generator.predict(input.view());
    let w = usize::from(set.width);
    let index = |c: Cell| usize::from(c.y) * w + usize::from(c.x);
    let hits = frames
        .rows()
        .into_iter()
        .zip(&ends)
        .filter(|(row, (a, b))| row[index(*a)] > 0.0 && row[index(*b)] > 0.0)
        .count();
    let (on, walkable) = lit_cells(site, &frames);
    // Routes the planner would make of these frames that needed the repair
    // search (frames whose ends are off the floor count as repaired).
    let repaired = frames
        .rows()
        .into_iter()
        .zip(&ends)
        .filter(|(row, (a, b))| {
            let frame = row.to_slice().expect("standard layout");
            !matches!(
                route_from_frame(site, Connectivity::Eight, Profile::Default, frame, *a, *b),
                Ok((_, Origin::Frame))
            )
        })
        .count();
    // One frame per class (its first sample, source to destination): a
    // generator that gives the same frame whatever pair it is asked for
    // collapsed; one that ignores only its noise did not.
    let per_class_rows: Vec<usize> = (0..pairs.len()).map(|k| 2 * k * per_class).collect();
    let firsts = frames
        .select(Axis(0), &per_class_rows)
        .mapv(|v| f32::from(u8::from(v > 0.0)));
    BTreeMap::from([
        ("endpoint_hit_share".to_owned(), hits as f64 / rows as f64),
        ("repaired_share".to_owned(), repaired as f64 / rows as f64),
        ("distinct_class_share".to_owned(), distinct_share(&firsts)),
        ("mean_path_cells".to_owned(), on as f64 / rows as f64),
        (
            "walkable_share".to_owned(),
            walkable as f64 / on.max(1) as f64,
        ),
    ])
}
