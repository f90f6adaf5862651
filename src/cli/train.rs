//! `gangway train`: path models from walks, and the localization cell
//! classifier from a survey, written as ONNX to a directory, with a summary
//! of what passed its checks and which planner the default mode serves.
//! The exit code says whether what was asked for is servable ([`Verdict`]).

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use anyhow::Context;
use indicatif::{ProgressBar, ProgressStyle};

use crate::locate::survey::Survey;
use crate::model::Kind;
use crate::model::checks::held_to_checks;
use crate::plan::learned::Choice;
use crate::plan::{self, PlannerConfig, PlannerMode};
use crate::site::Site;
use crate::train::job::{self, Options, Progress, Trained};
use crate::train::paths::PathSet;
use crate::train::{recorded, trajectory};

#[derive(clap::Args)]
pub(super) struct Args {
    /// The site file.
    #[arg(long)]
    site: PathBuf,
    /// Walks to learn paths from: a JSON Lines trajectory file, or a directory
    /// of the paper's frame CSVs.
    #[arg(long)]
    trajectories: Option<PathBuf>,
    /// Also learn from the daemon's learning store (SQLite, `[store]`): its
    /// recorded walks and the routes it gave, weighted by their feedback.
    #[arg(long)]
    from_store: Option<PathBuf>,
    /// With --from-store in a building: learn from the walks recorded on
    /// this floor (its name in the building file), the floor whose site
    /// file --site is. Needed once the store holds several floors' walks.
    #[arg(long, requires = "from_store")]
    floor: Option<String>,
    /// Directory for the ONNX files (created if missing).
    #[arg(long)]
    out: PathBuf,
    /// GAN iterations (one discriminator and one generator step each).
    #[arg(long, default_value_t = 15_000)]
    iterations: usize,
    #[arg(long, default_value_t = 32)]
    batch: usize,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Threads for the networks' arithmetic (default: the machine's cores).
    /// A seed and a thread count give the same models, bit for bit.
    #[arg(long)]
    threads: Option<usize>,
    /// Also train a generator conditioned on source and destination cells;
    /// the run then exits 0 only if it passes its checks.
    #[arg(long)]
    conditional: bool,
    /// Also train the line GAN from walks in JSON Lines: a conditional GAN
    /// whose samples are lines between the requested points, not frames, so
    /// its size does not grow with the site (`line_generator.onnx`, planner
    /// mode `line_gan`); the run then exits 0 only if it passes its checks.
    #[arg(long, conflicts_with = "desire_only")]
    line_gan: bool,
    /// Weight of the conditional generator's access penalty: a hinge that
    /// pushes back any non-walkable cell a generated frame lights (no walk
    /// lights one), ramped in linearly over the run; and of the line GAN's,
    /// which pushes back its lines' points off the floor. 0 trains the
    /// paper's plain loss. The unconditional GAN always keeps the paper's loss. On the sample
    /// site 1 removes every off-area cell and keeps routes human-like
    /// (docs/trajectories.md).
    #[arg(long, default_value_t = 1.0)]
    access_weight: f32,
    /// Iterations of the path classifier and of the cell classifier.
    #[arg(long, default_value_t = 3_000)]
    classifier_iterations: usize,
    /// Source/destination pairs with fewer walks are not classes.
    #[arg(long, default_value_t = 10)]
    min_class_walks: usize,
    /// Share of walks (and survey sessions) held out to measure the classifiers.
    #[arg(long, default_value_t = 0.2)]
    heldout: f64,
    /// Also train the localization cell classifier from this survey (CSV).
    #[arg(long)]
    survey: Option<PathBuf>,
    /// "Not heard" value in the survey.
    #[arg(long, default_value_t = -200, allow_negative_numbers = true)]
    not_heard: i16,
    /// Also write the GANs every this many iterations to
    /// `OUT/checkpoints/iter-<N>/` (for `gangway eval planning --checkpoints`).
    #[arg(long)]
    checkpoint_every: Option<std::num::NonZeroUsize>,
    /// Do not train the desire lines (`desire_lines.onnx`), which are
    /// otherwise trained from walks in JSON Lines (settings cross-validated
    /// on them, seconds) and served by the default planner when they pass
    /// their check.
    #[arg(long, conflicts_with = "desire_only")]
    no_desire: bool,
    /// Train only the desire lines from the walks (and the cell classifier
    /// with --survey), not the GAN models: large sites, or walks whose
    /// endpoints are all distinct pairs. The run exits 0 only if they pass
    /// their check.
    #[arg(long)]
    desire_only: bool,
    /// Print the summary as JSON instead of text.
    #[arg(long)]
    json: bool,
    /// Write generators that fail their checks (endpoint hits, walkable
    /// share, repair rate, distinct frames) where planners load them anyway,
    /// and exit 0: for experiments and plumbing tests with a few iterations.
    #[arg(long)]
    accept_failed: bool,
}

impl Args {
    /// `--threads`, or the machine's cores.
    fn threads(&self) -> usize {
        self.threads
            .unwrap_or_else(crate::train::workers::Workers::available)
    }
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.trajectories.is_some() || args.from_store.is_some() || args.survey.is_some(),
        "nothing to train: give --trajectories and/or --from-store (path models), and/or --survey (cell classifier)"
    );
    anyhow::ensure!(args.batch > 0, "--batch must be at least 1");
    anyhow::ensure!(args.threads != Some(0), "--threads must be at least 1");
    let threads = args.threads();
    anyhow::ensure!(
        args.access_weight.is_finite() && args.access_weight >= 0.0,
        "--access-weight must be a number ≥ 0 (0 turns the access penalty off)"
    );
    anyhow::ensure!(
        args.heldout > 0.0 && args.heldout < 1.0,
        "--heldout must be between 0 and 1"
    );
    let site = Site::load(&args.site)?;
    std::fs::create_dir_all(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    let options = Options {
        iterations: args.iterations,
        batch: args.batch,
        seed: args.seed,
        conditional: args.conditional,
        classifier_iterations: args.classifier_iterations,
        heldout_share: args.heldout,
        checkpoint_every: args.checkpoint_every,
        accept_failed: args.accept_failed,
        threads,
    };
    let started = Instant::now();
    let mut bars = Bars::new(args.json);
    let mut written: Vec<Trained> = Vec::new();
    // What was left out, and why: printed, and on the model card.
    let mut notes: Vec<String> = Vec::new();
    let mut walks = None;
    if args.trajectories.is_some() || args.from_store.is_some() {
        let set = match (&args.trajectories, &args.from_store) {
            (Some(dir), None) if dir.is_dir() => {
                for (asked, flag) in [
                    (args.desire_only, "--desire-only"),
                    (args.line_gan, "--line-gan"),
                ] {
                    anyhow::ensure!(
                        !asked,
                        "{flag} learns from walks in JSON Lines, not from a directory of \
                         frame CSVs (they carry no walking order)"
                    );
                }
                if !args.no_desire {
                    notes.push(
                        "desire lines not trained: frame CSVs carry no walking order (give \
                         walks in JSON Lines)"
                            .into(),
                    );
                }
                PathSet::from_frame_dir(&site, dir, args.min_class_walks)?
            }
            (Some(dir), Some(_)) if dir.is_dir() => anyhow::bail!(
                "--from-store combines with walks in JSON Lines, not with a directory of frame CSVs"
            ),
            (shipped, store) => {
                let mut all = match shipped {
                    Some(path) => trajectory::read(path, &site)?,
                    None => Vec::new(),
                };
                if let Some(db) = store {
                    let floor = match &args.floor {
                        Some(name) => recorded::FloorChoice::Named(name),
                        None => recorded::FloorChoice::Only,
                    };
                    let recorded = recorded::walks_from_store(db, &site, floor)?;
                    tracing::info!(walks = recorded.len(), store = %db.display(), "walks from the learning store");
                    all.extend(recorded);
                }
                let all = recorded::weighted(all);
                if !args.no_desire {
                    match job::train_desire(&site, &all, &options, &args.out, &mut bars) {
                        Ok(trained) => written.push(trained),
                        // Trained by default beside the other models: too
                        // few walks for them leaves the others to train.
                        Err(e) if !args.desire_only => {
                            notes.push(format!("desire lines not trained: {e:#}"))
                        }
                        Err(e) => return Err(e),
                    }
                }
                if args.line_gan {
                    written.extend(job::train_lines(
                        &site,
                        &all,
                        &options,
                        args.access_weight,
                        &args.out,
                        &mut bars,
                    )?);
                }
                PathSet::from_trajectories(&site, &all, args.min_class_walks)
            }
        };
        walks = Some((set.walks.len(), set.classes.len()));
        let rejection = job::rejection_trainable(&set);
        if let Err(why) = &rejection
            && !args.desire_only
            && (args.conditional || !written.is_empty())
        {
            // Walks whose endpoints are nearly all distinct: the other
            // models need no classes.
            notes.push(format!(
                "the paper's GAN and path classifier (rejection mode) not trained: {why} \
                 (--min-class-walks)"
            ));
        }
        let paths_wanted = args.conditional || rejection.is_ok() || written.is_empty();
        if !args.desire_only && paths_wanted {
            written.extend(job::train_paths(
                &site,
                &set,
                &options,
                args.access_weight,
                &args.out,
                &mut bars,
            )?);
        }
    }
    if let Some(path) = &args.survey {
        let anchors: Vec<String> = site.beacons.iter().map(|b| b.id.clone()).collect();
        let survey = Survey::load(path, &site, &anchors, args.not_heard)?;
        written.push(job::train_cells(
            &site, &survey, &options, &args.out, &mut bars,
        )?);
    }
    // What the default planner will serve from this directory: found the
    // way a gateway finds it.
    let default_planner = match walks {
        Some(_) => Some(default_planner(&site, &args.out)?),
        None => None,
    };
    let wall = started.elapsed().as_secs_f64();
    let verdict = Verdict::of(&args, &written, default_planner);
    let card = args.out.join("MODEL_CARD.md");
    let text = model_card(&site, &args, walks, &written, &notes, &verdict, wall);
    std::fs::write(&card, text).with_context(|| format!("cannot write {}", card.display()))?;
    if args.json {
        let models: Vec<_> = written
            .iter()
            .map(|t| {
                serde_json::json!({
                    "file": t.file,
                    "kind": t.kind.name(),
                    "parameters": t.parameters,
                    "bytes": t.bytes,
                    "seconds": t.seconds,
                    "metrics": t.metrics,
                    "checks": t.checks.iter().map(|c| serde_json::json!({
                        "metric": c.metric,
                        "value": c.value,
                        "bound": c.bound,
                        "at_most": c.at_most,
                        "passed": c.passed(),
                    })).collect::<Vec<_>>(),
                    "passed": t.passed(),
                })
            })
            .collect();
        let summary = serde_json::json!({
            "wall_seconds": wall,
            "walks": walks.map(|w| w.0),
            "classes": walks.map(|w| w.1),
            "iterations": args.iterations,
            "batch": args.batch,
            "seed": args.seed,
            "threads": threads,
            // Only the conditional generators have the penalty.
            "access_weight": if args.conditional || args.line_gan { args.access_weight } else { 0.0 },
            "models": models,
            "notes": notes,
            "default_planner": verdict.default_planner.as_ref().map(|c| serde_json::json!({
                "serves": c.serves.name(),
                "because": c.because,
            })),
            "servable": verdict.unmet.is_empty(),
            "unmet": verdict.unmet,
        });
        println!("{}", serde_json::to_string_pretty(&summary)?);
    } else {
        if let Some((n, classes)) = walks {
            println!("{n} walks, {classes} source/destination classes");
        }
        for t in &written {
            print_model(t, args.accept_failed);
        }
        for note in &notes {
            println!("note: {note}");
        }
        if let Some(c) = &verdict.default_planner {
            println!(
                "the default planner (mode `learned`) serves {}: {}",
                c.serves.name(),
                c.because
            );
        }
        println!("wall time {wall:.1} s");
    }
    // Loud on standard error whatever the output format: a failed model
    // is an error when it leaves what was asked for unservable, else a
    // warning (the default planner serves something else).
    for t in written
        .iter()
        .filter(|t| held_to_checks(t.kind) && !t.passed())
    {
        let what: Vec<String> = t
            .checks
            .iter()
            .filter(|c| !c.passed())
            .map(|c| c.describe())
            .collect();
        let at = if args.accept_failed {
            format!("written to {} anyway (--accept-failed)", t.file.display())
        } else {
            format!(
                "written to {}, where planners do not load it",
                t.file.display()
            )
        };
        let said = format!(
            "{} failed its checks: {}; {at}",
            t.kind.name(),
            what.join(", ")
        );
        if verdict.blames(t.kind) {
            tracing::error!("{said}");
        } else {
            tracing::warn!("{said}");
        }
    }
    if verdict.unmet.is_empty() || args.accept_failed {
        return Ok(ExitCode::SUCCESS);
    }
    tracing::error!(
        "not servable: {}. {} (models that failed are in {}; see {})",
        verdict.unmet.join("; "),
        verdict.hint(),
        args.out.join("failed").display(),
        card.display()
    );
    Ok(ExitCode::FAILURE)
}

/// What the run was asked for, what the default planner serves, and what
/// of the request is not servable: the models named by a flag
/// (`--desire-only`, `--conditional`) must pass their checks, and path
/// models trained from walks must leave the default planner something
/// learned to serve. A model trained only by default that fails is passed
/// over by the default planner, so it is a warning, not a failed run.
struct Verdict {
    /// What the default planner serves from the output directory (when
    /// path models were trained).
    default_planner: Option<Choice>,
    /// The kinds asked for by a flag.
    asked: Vec<Kind>,
    /// Why what was asked for is not servable (empty: it is).
    unmet: Vec<String>,
    /// Failed models behind `unmet`, for [`Verdict::hint`].
    failed: Vec<Kind>,
}

impl Verdict {
    fn of(args: &Args, written: &[Trained], default_planner: Option<Choice>) -> Verdict {
        let mut asked = Vec::new();
        if args.desire_only {
            asked.push(Kind::DesireLines);
        }
        if args.conditional {
            asked.push(Kind::ConditionalGenerator);
        }
        if args.line_gan {
            asked.push(Kind::LineGenerator);
        }
        let mut unmet = Vec::new();
        let mut failed = Vec::new();
        for t in written
            .iter()
            .filter(|t| asked.contains(&t.kind) && !t.passed())
        {
            unmet.push(format!(
                "{} was asked for ({}) and failed its checks",
                t.kind.name(),
                match t.kind {
                    Kind::DesireLines => "--desire-only",
                    Kind::LineGenerator => "--line-gan",
                    _ => "--conditional",
                }
            ));
            failed.push(t.kind);
        }
        if let Some(choice) = &default_planner
            && choice.serves == PlannerMode::Astar
        {
            unmet.push("nothing learned is servable: the default planner would serve A*".into());
            failed.extend(
                written
                    .iter()
                    .filter(|t| held_to_checks(t.kind) && !t.passed())
                    .map(|t| t.kind),
            );
        }
        Verdict {
            default_planner,
            asked,
            unmet,
            failed,
        }
    }

    /// Whether a failed model of `kind` is why the run is not servable.
    fn blames(&self, kind: Kind) -> bool {
        self.failed.contains(&kind)
    }

    /// What to try for the failed models behind `unmet`.
    fn hint(&self) -> String {
        let mut tries = Vec::new();
        if self.blames(Kind::DesireLines) {
            // Their check is against later walkers: more of the same
            // simulated walks do not help, walks of real people do.
            tries.push(
                "give the desire lines more walks (recorded walks of real people: --from-store)",
            );
        }
        if [
            Kind::Generator,
            Kind::ConditionalGenerator,
            Kind::LineGenerator,
        ]
        .iter()
        .any(|&k| self.blames(k))
        {
            tries.push(
                "train the generators longer or on more walks (more --iterations, more walks \
                 per source/destination pair, coarser cells, fewer rare pairs: --min-class-walks)",
            );
        }
        if self.asked.contains(&Kind::DesireLines) {
            tries.push("train the GAN models too (without --desire-only)");
        } else if !self.asked.contains(&Kind::ConditionalGenerator) {
            tries.push("train the conditional generator too (--conditional)");
        }
        format!(
            "Try to {}; meanwhile, serve the astar mode",
            tries.join("; or ")
        )
    }
}

/// One model's lines of the text summary: its kind, whether it passed its
/// checks and where it was written (not servable in `failed/`), the checks
/// with their figures and bounds, then its size, time and metrics.
fn print_model(t: &Trained, accept_failed: bool) {
    let verdict = if t.checks.is_empty() {
        "no checks"
    } else if t.passed() {
        "passed"
    } else {
        "FAILED"
    };
    let served = match (t.checks.is_empty() || t.passed(), accept_failed) {
        (true, _) => "",
        (false, true) => " (written where planners load it: --accept-failed)",
        (false, false) => " (not served)",
    };
    println!(
        "{:<26} {verdict:<9} {}{served}",
        t.kind.name(),
        t.file.display()
    );
    // A discriminator carries its generator's checks, printed above.
    if held_to_checks(t.kind) {
        println!("    checks: {}", check_words(t).join(", "));
    }
    println!(
        "    {} params, {:.1} KiB, {:.1} s: {}",
        t.parameters,
        t.bytes as f64 / 1024.0,
        t.seconds,
        metric_words(t).join(", ")
    );
}

/// Each check of a written model, its figure against its bound and the
/// verdict: "walkable_share 0.995 ≥ 0.9 pass".
fn check_words(t: &Trained) -> Vec<String> {
    t.checks
        .iter()
        .map(|c| {
            let verdict = if c.passed() { "pass" } else { "FAIL" };
            format!("{} {verdict}", c.describe())
        })
        .collect()
}

/// Each metric of a written model, shortened: "seconds 37.2".
fn metric_words(t: &Trained) -> Vec<String> {
    t.metrics
        .iter()
        .map(|(k, v)| format!("{k} {}", short(*v)))
        .collect()
}

/// Which planner the default mode serves from the models in `dir`, built
/// as a gateway builds it (`plan::learned`).
fn default_planner(site: &Site, dir: &Path) -> anyhow::Result<Choice> {
    let mut config = PlannerConfig::default();
    super::serve_models_from(&mut config, dir);
    Ok(plan::learned::build(&config, Arc::new(site.clone()))?.1)
}

/// `MODEL_CARD.md`: what was trained, from what, what it measured, whether
/// it passed its checks, which planner the default mode serves, and
/// whether what the run was asked for is servable.
fn model_card(
    site: &Site,
    args: &Args,
    walks: Option<(usize, usize)>,
    written: &[Trained],
    notes: &[String],
    verdict: &Verdict,
    wall: f64,
) -> String {
    use std::fmt::Write as _;
    let mut card = String::new();
    let _ = writeln!(
        card,
        "# Models in this directory
"
    );
    let _ = writeln!(
        card,
        "Written by `{}` in {wall:.0} s.
",
        std::env::args().collect::<Vec<_>>().join(" ")
    );
    let _ = writeln!(
        card,
        "- site: `{}`, {} × {} cells of {} m ({} walkable), map hash `{}`",
        site.name,
        site.width(),
        site.height(),
        site.cell_m,
        site.open_cells().len(),
        &site.map_hash()[..16]
    );
    if let Some((n, classes)) = walks {
        let _ = writeln!(
            card,
            "- walks: {n} (`{}`), {classes} source/destination classes (pairs with {}+ walks)",
            args.trajectories
                .as_ref()
                .map_or("the learning store".into(), |p| p.display().to_string()),
            args.min_class_walks
        );
    }
    if !args.desire_only {
        let _ = writeln!(
            card,
            "- GAN iterations {}, batch {}, seed {}, {} threads",
            args.iterations,
            args.batch,
            args.seed,
            args.threads()
        );
    }
    for t in written.iter().filter(|t| t.kind == Kind::DesireLines) {
        let m = |k: &str| t.metrics.get(k).copied().unwrap_or(f64::NAN);
        let _ = writeln!(
            card,
            "- `desire_lines.onnx` is no neural network: a kernel regression over the \
             shapes of {:.0} walks (each both ways) conditioned on the endpoints' coordinates, \
             blended into the profile's any-angle route and shrunk towards it where the \
             neighbouring walks disagree; kernel width σ {} m, shrinkage {}, prior weight {} \
             and evidence threshold {} chosen by {} time-ordered folds of these walks \
             (docs/planning.md, \"Desire lines\")",
            m("bank_lines") / 2.0,
            m("sigma_m"),
            m("shrink"),
            m("prior_weight"),
            m("min_mass"),
            crate::train::desire::FOLDS
        );
    }
    if let Some(c) = &verdict.default_planner {
        let _ = writeln!(
            card,
            "- default planner (`[planner] mode` unset or `learned`): serves **{}**: {}",
            c.serves.name(),
            c.because
        );
    }
    for note in notes {
        let _ = writeln!(card, "- {note}");
    }
    if verdict.unmet.is_empty() {
        let _ = writeln!(card, "- servable: what this run was asked for passed");
    } else {
        let _ = writeln!(
            card,
            "- **not servable**: {}{}",
            verdict.unmet.join("; "),
            if args.accept_failed {
                " (written where planners load them anyway: --accept-failed)"
            } else {
                ""
            }
        );
    }
    let _ = writeln!(card);
    let _ = writeln!(card, "| file | kind | servable | metrics | checks |");
    let _ = writeln!(card, "|---|---|---|---|---|");
    for t in written {
        let (metrics, checks) = (metric_words(t), check_words(t));
        let _ = writeln!(
            card,
            "| `{}` | {} | {} | {} | {} |",
            t.file.display(),
            t.kind.name(),
            if t.passed() || args.accept_failed {
                "yes"
            } else {
                "no"
            },
            metrics.join(", "),
            if checks.is_empty() {
                "–".to_owned()
            } else {
                checks.join("; ")
            }
        );
    }
    card
}

fn short(v: f64) -> String {
    if v.fract() == 0.0 && v.abs() < 1e9 {
        format!("{v:.0}")
    } else {
        format!("{v:.4}")
    }
}

/// One progress bar per stage, with the latest losses; hidden with `--json`
/// or when stderr is not a terminal.
struct Bars {
    hidden: bool,
    bar: Option<ProgressBar>,
    last_draw: Instant,
}

impl Bars {
    fn new(hidden: bool) -> Bars {
        Bars {
            hidden,
            bar: None,
            last_draw: Instant::now(),
        }
    }
}

impl Progress for Bars {
    fn stage(&mut self, name: &str, iterations: usize) {
        let bar = if self.hidden {
            ProgressBar::hidden()
        } else {
            ProgressBar::new(iterations as u64)
        };
        bar.set_style(
            ProgressStyle::with_template(
                "{prefix:>16} [{bar:30}] {pos}/{len} {elapsed_precise} eta {eta} {msg}",
            )
            .expect("valid template")
            .progress_chars("=> "),
        );
        bar.set_prefix(name.to_owned());
        self.bar = Some(bar);
    }

    fn step(&mut self, iteration: usize, losses: &[(&str, f32)]) {
        let Some(bar) = &self.bar else { return };
        // Formatting losses every iteration would cost more than a small step.
        if self.last_draw.elapsed() < Duration::from_millis(100) {
            return;
        }
        self.last_draw = Instant::now();
        bar.set_position(iteration as u64);
        let text: Vec<String> = losses.iter().map(|(k, v)| format!("{k} {v:.3}")).collect();
        bar.set_message(text.join(" "));
    }

    fn done(&mut self) {
        if let Some(bar) = self.bar.take() {
            bar.finish_and_clear();
        }
    }
}
