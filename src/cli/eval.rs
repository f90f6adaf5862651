//! `gangway eval`: measured figures, reproducible from one command.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;
use clap::Subcommand;

use crate::config::Config;
use crate::eval::floors::{FloorsSetup, WindowFix};
use crate::eval::localization::{Holdout, RowFix, Setup, Split, UnlabelledRows, evaluate};
use crate::eval::similarity::TrainingFrames;
use crate::locate::survey::{Survey, SurveyRows};
use crate::locate::tracker::{TrackerConfig, TrackerKind};
use crate::locate::window::{WindowConfig, anchor_ids};
use crate::locate::{LocalizerConfig, Method};
use crate::site::{Building, Site};
use crate::train::trajectory;

#[derive(clap::Args)]
pub(super) struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(Subcommand)]
enum What {
    /// Localization accuracy and speed on a labelled survey.
    Localization(LocalizationArgs),
    /// Every planner mode on place pairs and random open-cell pairs.
    Planning(PlanningArgs),
    /// Simulated walkers guided along their routes, some taking a wrong turn.
    Guidance(GuidanceArgs),
}

#[derive(clap::Args)]
struct GuidanceArgs {
    #[command(flatten)]
    config: super::ConfigFile,
    /// A labelled survey (CSV): phones hear real readings resampled in the
    /// walker's cell instead of the path-loss model.
    #[arg(long)]
    survey: Option<PathBuf>,
    /// Recorded walks of real people (`track,t,x,y` CSV or ETH/UCY
    /// `obsmat.txt`; repeatable): the walkers walk at their second-by-second
    /// pace, slowing and stopping as people do, instead of a steady speed.
    #[arg(long)]
    walks: Vec<PathBuf>,
    #[command(flatten)]
    walk_format: super::walks::TrackSource,
    #[arg(long, default_value_t = 100)]
    trips: usize,
    /// Chance that a walker strays at a turn.
    #[arg(long, default_value_t = 0.3)]
    wrong_turn_probability: f64,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct PlanningArgs {
    #[command(flatten)]
    planner: super::PlannerSource,
    /// Random open-cell pairs besides every ordered pair of named places.
    #[arg(long, default_value_t = 1000)]
    random_pairs: usize,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
    /// Walks by people that no model was trained on (trajectory JSON Lines):
    /// gives `human_iou_gan` and `human_iou_astar`. Without it they are `null`.
    #[arg(long)]
    heldout_walks: Option<PathBuf>,
    /// The walks the generators were trained on (trajectory JSON Lines):
    /// gives `novelty`. Without it, it is `null`.
    #[arg(long)]
    training_walks: Option<PathBuf>,
    /// Write the figures here: sample routes per class (Fig. 9) and, with
    /// `--checkpoints`, deviation against training iterations (Fig. 10).
    #[arg(long)]
    pictures: Option<PathBuf>,
    /// Routes drawn per class in `--pictures`.
    #[arg(long, default_value_t = 3)]
    samples_per_class: usize,
    /// Generator checkpoints written by `gangway train --checkpoint-every`
    /// (the `checkpoints` directory): adds `checkpoints` to the report.
    #[arg(long)]
    checkpoints: Option<PathBuf>,
    /// Frames generated per checkpoint to measure its deviation score.
    #[arg(long, default_value_t = 256)]
    checkpoint_frames: usize,
}

#[derive(clap::Args)]
struct LocalizationArgs {
    /// The site file.
    #[arg(long)]
    site: PathBuf,
    /// The labelled survey (CSV), split 70/30 by `--split` (`session`: 30%
    /// of the walking sessions, so the share of rows held out varies with
    /// their lengths).
    #[arg(
        long,
        required_unless_present_any = ["train", "walks"],
        conflicts_with_all = ["train", "test", "walks"]
    )]
    survey: Option<PathBuf>,
    /// Instead of a survey: walks with timed waypoints, one folder per floor
    /// of `--site` (a building file, or a one-floor site) named after it,
    /// each with `path_data_files/` (the Indoor Location Competition
    /// layout). The later 30% of each floor's walks by time are held out;
    /// prints floor accuracy and errors on the right floor, beside a k-NN
    /// baseline on the same split.
    #[arg(long, conflicts_with_all = ["train", "test"])]
    walks: Option<PathBuf>,
    /// With `--walks`: the floor filter's probability of changing floor
    /// between two windows (the gateway's own by default).
    #[arg(long, conflicts_with_all = ["survey", "train"], default_value_t = crate::locate::floor_track::SWITCH)]
    floor_switch: f64,
    /// With `--walks` and `--method pathloss`: first fit each floor's radio
    /// model to what its training walks heard, their positions unused, as
    /// the gateway's own recalibration fits what it hears (the config's
    /// `[localizer.recalibration]` settings, its held-out check included).
    #[arg(long, requires = "walks")]
    recalibrate: bool,
    /// A fixed split instead: the labelled rows to build from (CSV)...
    #[arg(long, requires = "test")]
    train: Option<PathBuf>,
    /// ...and the labelled rows to measure on (CSV); evaluated once.
    #[arg(long, requires = "train")]
    test: Option<PathBuf>,
    /// A gap longer than this (seconds) between rows starts a new walking session.
    #[arg(long, conflicts_with = "walks", default_value_t = crate::eval::localization::SESSION_GAP_S)]
    session_gap: f64,
    /// Write every held-out row's fix as CSV (seed, session, row, t, truth,
    /// fix, confidence, error in cells); with `--walks`, every held-out
    /// window with a known position (floor, walk, t, truth, the floor
    /// located on and whether it is known, fix, confidence, error in
    /// metres on the right floor).
    #[arg(long)]
    rows: Option<PathBuf>,
    /// `session` holds out whole walking sessions (honest); `random` holds out rows.
    #[arg(long, value_enum, conflicts_with = "walks", default_value = "session")]
    split: Split,
    /// Seeds to average over.
    #[arg(long, conflicts_with = "walks", default_value_t = 5)]
    seeds: u64,
    /// The localizer [default: what the daemon would use: `--config`'s
    /// `[localizer] method`, else `auto`, the default with a survey].
    #[arg(long, value_enum)]
    method: Option<Method>,
    /// The tracker [default: `--config`'s `[tracker] kind`, else `hmm`].
    #[arg(long, value_enum)]
    tracker: Option<TrackerKind>,
    /// Smooth each recorded walk over this many later windows (fixed-lag
    /// smoothing; 0 is the online filter a live gateway runs).
    #[arg(long, conflicts_with = "walks", default_value_t = 0)]
    smooth_lag: usize,
    /// Add this many dB to every held-out reading: what a phone that hears
    /// that much louder (negative: deafer) than the survey's and the
    /// model's would get.
    #[arg(long, default_value_t = 0.0, allow_negative_numbers = true)]
    receiver_offset_db: f32,
    /// Take [window], [localizer] and [tracker] settings from this gateway config
    /// instead of the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Print one JSON object with exactly the metric keys.
    #[arg(long)]
    json: bool,
    /// Write the error CDF of every method, with and without tracking, as SVG.
    #[arg(long, conflicts_with = "walks")]
    plot: Option<PathBuf>,
    /// The files' "not heard" RSSI value (default: the config's
    /// `[localizer.knn] not_heard`, -200).
    #[arg(long, conflicts_with = "walks", allow_negative_numbers = true)]
    not_heard: Option<i16>,
    /// Unlabelled scans (the same CSV layouts; `location` may be `?`) that
    /// the survey-free model is calibrated on before measuring, as `gangway
    /// calibrate` does. Only `--method pathloss` uses them (with `--walks`:
    /// `--recalibrate`).
    #[arg(long, conflicts_with = "walks")]
    calibrate: Option<PathBuf>,
    /// With `--calibrate`: then refine a radio map per cell by EM for this
    /// many iterations (8 when given without a value), as `gangway calibrate
    /// --cells` does.
    #[arg(long, requires = "calibrate", conflicts_with = "walks", num_args = 0..=1, default_missing_value = "8")]
    calibrate_cells: Option<usize>,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    match args.what {
        What::Localization(args) => localization(args),
        What::Planning(args) => planning(args),
        What::Guidance(args) => guidance(args),
    }
}

fn guidance(args: GuidanceArgs) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        (0.0..=1.0).contains(&args.wrong_turn_probability),
        "--wrong-turn-probability must be between 0 and 1"
    );
    let config = Config::load(&args.config.path)?;
    let site = Arc::new(Site::load(&config.site)?);
    let survey = match &args.survey {
        Some(path) => Some(Survey::load(
            path,
            &site,
            &anchor_ids(&site, config.window.orientation),
            config.localizer.knn.not_heard,
        )?),
        None => None,
    };
    let mut paces = Vec::new();
    for path in &args.walks {
        use crate::eval::guidance::{PACE_MIN_S, WALKING_MPS, paces as walked};
        let walks = walked(&args.walk_format.read(path, None)?);
        anyhow::ensure!(
            !walks.is_empty(),
            "{}: no track walks for {PACE_MIN_S} s or more at {WALKING_MPS} m/s or more; --walks needs recorded walks of people",
            path.display()
        );
        paces.extend(walks);
    }
    let setup = crate::eval::guidance::Setup {
        trips: args.trips,
        seed: args.seed,
        wrong_turn_probability: args.wrong_turn_probability,
        paces,
        ..Default::default()
    };
    let report = crate::eval::guidance::evaluate(&config, site, survey.as_ref(), &setup)?;
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(ExitCode::SUCCESS)
}

fn planning(args: PlanningArgs) -> anyhow::Result<ExitCode> {
    use crate::eval::{figures, planning};
    let (planner, site) = args.planner.load()?;
    let read = |path: &Option<PathBuf>| -> anyhow::Result<_> {
        Ok(match path {
            Some(p) => Some(trajectory::read(p, &site)?),
            None => None,
        })
    };
    let walks = planning::Walks {
        heldout: read(&args.heldout_walks)?,
        training: read(&args.training_walks)?.map(|w| TrainingFrames::new(&site, &w)),
    };
    // Checkpoints first: a wrong directory fails before the long evaluation.
    let checkpoints = match &args.checkpoints {
        Some(dir) => Some(figures::checkpoint_deviation(
            &site,
            dir,
            args.checkpoint_frames,
            args.seed,
        )?),
        None => None,
    };
    let pairs = planning::pairs(&site, args.random_pairs, args.seed);
    let mut report = planning::evaluate(&planner, site.clone(), &pairs, &walks);
    if let Some(points) = &checkpoints {
        report["checkpoints"] = serde_json::to_value(points)?;
        if let Some(out) = &args.pictures {
            std::fs::create_dir_all(out)
                .with_context(|| format!("cannot create {}", out.display()))?;
            let file = out.join("deviation-vs-iterations.svg");
            figures::deviation_svg(&file, points)?;
            eprintln!("wrote {}", file.display());
        }
    }
    if let Some(out) = &args.pictures {
        let written = figures::sample_routes(&planner, site.clone(), args.samples_per_class, out)?;
        eprintln!("wrote {} sample sheets to {}", written.len(), out.display());
    }
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
        return Ok(ExitCode::SUCCESS);
    }
    println!("{}", serde_json::to_string_pretty(&report)?);
    if args.heldout_walks.is_none() {
        println!(
            "human_iou_gan and human_iou_astar are null: give --heldout-walks FILE, walks by \
             people that no model was trained on"
        );
    }
    if args.training_walks.is_none() {
        println!(
            "novelty is null: give --training-walks FILE, the walks the generators were trained on"
        );
    }
    if planner.mode == crate::plan::PlannerMode::Astar {
        println!(
            "the configured mode is astar: novelty and human_iou_gan are under `modes` \
             (rejection, conditional)"
        );
    }
    Ok(ExitCode::SUCCESS)
}

/// `--config`'s `[window]`, `[localizer]` and `[tracker]`, else the defaults.
fn settings(
    args: &LocalizationArgs,
) -> anyhow::Result<(WindowConfig, LocalizerConfig, TrackerConfig)> {
    Ok(match &args.config {
        Some(path) => {
            let c = Config::load(path)?;
            (c.window, c.localizer, c.tracker)
        }
        None => (
            WindowConfig::default(),
            LocalizerConfig::default(),
            TrackerConfig::default(),
        ),
    })
}

/// `eval localization --walks`: a building's floors from walks.
fn floors(args: &LocalizationArgs, walks: &Path) -> anyhow::Result<ExitCode> {
    let building = Building::load(&args.site)?;
    let (window, localizer, tracker) = settings(args)?;
    let method = args.method.unwrap_or(localizer.method);
    anyhow::ensure!(
        !args.recalibrate || method == Method::Pathloss,
        "--recalibrate fits the survey-free model, and the method is `{}`: \
         give --method pathloss",
        method.name()
    );
    let setup = FloorsSetup {
        method,
        localizer,
        window,
        tracker: TrackerConfig {
            kind: args.tracker.unwrap_or(tracker.kind),
            ..tracker
        },
        floor_switch: args.floor_switch,
        recalibrate: args.recalibrate,
        receiver_offset_db: args.receiver_offset_db,
    };
    let started = Instant::now();
    let (report, window_fixes) = crate::eval::floors::evaluate(&building, walks, &setup)?;
    if let Some(path) = &args.rows {
        write_window_fixes(path, &window_fixes)?;
    }
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
        return Ok(ExitCode::SUCCESS);
    }
    let line = |name: &str, m: &crate::eval::floors::FloorMetrics| {
        println!(
            "{name:>10}: floor right {:.1}% (unknown {:.1}%), on the right floor mean {:.2} m, \
             median {:.2} m, p90 {:.2} m ({} fixes)",
            100.0 * m.floor_accuracy,
            100.0 * m.floor_unknown,
            m.mean_error_m,
            m.median_error_m,
            m.p90_error_m,
            m.fixes
        )
    };
    println!(
        "{} floors, {} walks trained on, {} held out (the later 30% of each floor's), method {}",
        building.floors().len(),
        report.train_walks,
        report.test_walks,
        report.method
    );
    for (name, said) in &report.recalibrated {
        println!("recalibrated {name}: {said}");
    }
    line("ours", &report.ours.overall);
    line("k-NN", &report.baseline.overall);
    for (name, m) in &report.ours.floors {
        line(&format!("ours {name}"), m);
        line(&format!("k-NN {name}"), &report.baseline.floors[name]);
    }
    println!("{}", report.confidence);
    eprintln!("took {:.1} s", started.elapsed().as_secs_f64());
    Ok(ExitCode::SUCCESS)
}

fn localization(args: LocalizationArgs) -> anyhow::Result<ExitCode> {
    if let Some(walks) = &args.walks {
        return floors(&args, walks);
    }
    let site = Arc::new(Site::load(&args.site)?);
    let (window, mut localizer, tracker) = settings(&args)?;
    if let Some(not_heard) = args.not_heard {
        localizer.knn.not_heard = not_heard;
    }
    let anchors = anchor_ids(&site, window.orientation);
    let load = |path: &PathBuf| Survey::load(path, &site, &anchors, localizer.knn.not_heard);
    let (survey, holdout, source) = match (&args.survey, &args.train, &args.test) {
        (Some(path), _, _) => (
            load(path)?,
            Holdout::Drawn(args.split),
            path.display().to_string(),
        ),
        (None, Some(train), Some(test)) => {
            let (train_rows, test_rows) = (load(train)?, load(test)?);
            let mut held = vec![false; train_rows.samples.len()];
            held.resize(train_rows.samples.len() + test_rows.samples.len(), true);
            let mut survey = train_rows;
            survey.samples.extend(test_rows.samples);
            let source = format!("{} → {}", train.display(), test.display());
            (survey, Holdout::Fixed(held), source)
        }
        _ => unreachable!("clap requires --survey or --train and --test"),
    };
    let calibrate_from = match &args.calibrate {
        Some(path) => Some(unlabelled(path, &site, &anchors, localizer.knn.not_heard)?),
        None => None,
    };
    let setup = |method: Method, kind: TrackerKind| Setup {
        holdout: holdout.clone(),
        session_gap_s: args.session_gap,
        seeds: args.seeds,
        method,
        localizer: localizer.clone(),
        window: window.clone(),
        tracker: TrackerConfig {
            kind,
            ..tracker.clone()
        },
        smooth_lag: args.smooth_lag,
        calibrate_from: calibrate_from.clone(),
        calibrate_cells: args.calibrate_cells.unwrap_or(0),
        receiver_offset_db: args.receiver_offset_db,
    };
    let method = args.method.unwrap_or(localizer.method);
    let tracker_kind = args.tracker.unwrap_or(tracker.kind);
    let outcome = evaluate(&site, &survey, &setup(method, tracker_kind))?;
    if let Some(path) = &args.rows {
        write_rows(path, &outcome.rows)?;
    }
    let m = &outcome.metrics;
    if args.json {
        println!("{}", serde_json::to_string(m)?);
    } else {
        println!(
            "localization on {} ({} rows), {}, {} + tracker {:?}",
            source,
            survey.samples.len(),
            match &holdout {
                Holdout::Drawn(split) => format!("{split:?} split, {} seeds", args.seeds),
                Holdout::Fixed(_) => "fixed split".to_owned(),
            },
            method.name(),
            tracker_kind
        );
        let e = &m.errors;
        println!(
            "exact {:.3}  within_1 {:.3}  within_2 {:.3}  us_per_fix {:.2}",
            e.exact, e.within_1, e.within_2, m.us_per_fix
        );
        println!(
            "error cells: mean {:.3}  median {:.3}  p75 {:.3}  p90 {:.3}",
            e.mean_error_cells, e.median_error_cells, e.p75_error_cells, e.p90_error_cells
        );
        println!(
            "error m:     mean {:.3}  median {:.3}  p75 {:.3}  p90 {:.3}",
            e.mean_error_m, e.median_error_m, e.p75_error_m, e.p90_error_m
        );
        println!("{}", m.confidence);
    }
    if let Some(path) = &args.plot {
        let mut curves = Vec::new();
        for method in [Method::Knn, Method::Onnx, Method::Pathloss] {
            for kind in [TrackerKind::None, TrackerKind::Hmm] {
                let o = evaluate(&site, &survey, &setup(method, kind))?;
                let label = format!(
                    "{} + {:?} (mean {:.2})",
                    method.name(),
                    kind,
                    o.metrics.errors.mean_error_cells
                );
                curves.push((label.to_lowercase(), o.errors));
            }
        }
        let title = format!("Localization error CDF, {:?} split", args.split).to_lowercase();
        crate::eval::error_cdf_svg(path, &title, &curves)?;
        eprintln!("wrote {}", path.display());
    }
    Ok(ExitCode::SUCCESS)
}

/// Reads scans with times and any (or no) positions for calibration.
fn unlabelled(
    path: &std::path::Path,
    site: &Site,
    anchors: &[String],
    not_heard: i16,
) -> anyhow::Result<UnlabelledRows> {
    let rows = SurveyRows::open(path, site, anchors, not_heard)?;
    if !rows.has_clock() {
        anyhow::bail!(
            "{}: no time column; calibration follows walks in time, so it needs `date` or `t`",
            path.display()
        );
    }
    let rows = rows
        .map(|row| row.map(|r| (r.t.expect("checked: the file has a clock"), r.rssi)))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(UnlabelledRows { rows })
}

/// Writes per-window fixes of `--walks` as CSV.
fn write_window_fixes(path: &std::path::Path, fixes: &[WindowFix]) -> anyhow::Result<()> {
    let header = [
        "floor",
        "walk",
        "t",
        "truth_x_m",
        "truth_y_m",
        "located_floor",
        "floor_known",
        "x_m",
        "y_m",
        "confidence",
        "error_m",
    ];
    let records = fixes.iter().map(|f| {
        [
            f.floor.clone(),
            f.walk.clone(),
            format!("{:.3}", f.t),
            format!("{:.2}", f.truth[0]),
            format!("{:.2}", f.truth[1]),
            f.located_floor.clone(),
            f.floor_known.to_string(),
            format!("{:.2}", f.fix[0]),
            format!("{:.2}", f.fix[1]),
            format!("{:.4}", f.confidence),
            f.error_m.map_or_else(String::new, |e| format!("{e:.2}")),
        ]
    });
    write_csv(path, header, records)
}

/// Writes per-row fixes as CSV.
fn write_rows(path: &std::path::Path, rows: &[RowFix]) -> anyhow::Result<()> {
    let header = [
        "seed",
        "session",
        "row",
        "t",
        "truth_x",
        "truth_y",
        "x",
        "y",
        "confidence",
        "error_cells",
    ];
    let records = rows.iter().map(|r| {
        [
            r.seed.to_string(),
            r.session.to_string(),
            r.row.to_string(),
            r.t.to_string(),
            r.truth.x.to_string(),
            r.truth.y.to_string(),
            r.cell.x.to_string(),
            r.cell.y.to_string(),
            format!("{:.4}", r.confidence),
            format!("{:.4}", r.error_cells),
        ]
    });
    write_csv(path, header, records)
}

/// Writes `header` then `records` to `path` as CSV.
fn write_csv<const N: usize>(
    path: &std::path::Path,
    header: [&str; N],
    records: impl Iterator<Item = [String; N]>,
) -> anyhow::Result<()> {
    let mut out =
        csv::Writer::from_path(path).with_context(|| format!("cannot write {}", path.display()))?;
    out.write_record(header)?;
    for record in records {
        out.write_record(record)?;
    }
    out.flush()?;
    Ok(())
}
