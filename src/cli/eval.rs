//! `gangway eval`: measured figures, reproducible from one command.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use clap::Subcommand;

use crate::config::Config;
use crate::eval::localization::{Setup, Split, evaluate};
use crate::locate::survey::Survey;
use crate::locate::tracker::{TrackerConfig, TrackerKind};
use crate::locate::window::{WindowConfig, anchor_ids};
use crate::locate::{LocalizerConfig, Method};
use crate::site::Site;

#[derive(clap::Args)]
pub struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(Subcommand)]
enum What {
    /// Localization accuracy and speed on a labelled survey.
    Localization(LocalizationArgs),
    /// Every planner mode on place pairs and random open-cell pairs.
    Planning(PlanningArgs),
}

#[derive(clap::Args)]
struct PlanningArgs {
    #[arg(long, default_value_os_t = super::default_config())]
    config: PathBuf,
    /// Random open-cell pairs besides every ordered pair of named places.
    #[arg(long, default_value_t = 1000)]
    random_pairs: usize,
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Print one JSON object.
    #[arg(long)]
    json: bool,
}

#[derive(clap::Args)]
struct LocalizationArgs {
    /// The site file.
    #[arg(long)]
    site: PathBuf,
    /// The labelled survey (CSV).
    #[arg(long)]
    survey: PathBuf,
    /// `session` holds out whole walking sessions (honest); `random` holds out rows.
    #[arg(long, value_enum, default_value = "session")]
    split: Split,
    /// Seeds to average over.
    #[arg(long, default_value_t = 5)]
    seeds: u64,
    #[arg(long, value_enum, default_value = "knn")]
    method: Method,
    #[arg(long, value_enum, default_value = "hmm")]
    tracker: TrackerKind,
    /// Smooth each recorded walk over this many later windows (fixed-lag
    /// smoothing; 0 is the online filter a live gateway runs).
    #[arg(long, default_value_t = 0)]
    smooth_lag: usize,
    /// Take [window], [localizer] and [tracker] settings from this gateway config
    /// instead of the defaults.
    #[arg(long)]
    config: Option<PathBuf>,
    /// Print one JSON object with exactly the metric keys.
    #[arg(long)]
    json: bool,
    /// Write the error CDF of every method, with and without tracking, as SVG.
    #[arg(long)]
    plot: Option<PathBuf>,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    match args.what {
        What::Localization(args) => localization(args),
        What::Planning(args) => planning(args),
    }
}

fn planning(args: PlanningArgs) -> anyhow::Result<ExitCode> {
    let (config, site) = super::load(&args.config)?;
    let pairs = crate::eval::planning::pairs(&site, args.random_pairs, args.seed);
    let report = crate::eval::planning::evaluate(&config.planner, site, &pairs);
    if args.json {
        println!("{}", serde_json::to_string(&report)?);
    } else {
        println!("{}", serde_json::to_string_pretty(&report)?);
    }
    Ok(ExitCode::SUCCESS)
}

fn localization(args: LocalizationArgs) -> anyhow::Result<ExitCode> {
    let site = Arc::new(Site::load(&args.site)?);
    let (window, mut localizer, tracker) = match &args.config {
        Some(path) => {
            let c = Config::load(path)?;
            (c.window, c.localizer, c.tracker)
        }
        None => (
            WindowConfig::default(),
            LocalizerConfig::default(),
            TrackerConfig::default(),
        ),
    };
    localizer.knn.survey = Some(args.survey.clone());
    let survey = Survey::load(
        &args.survey,
        &site,
        &anchor_ids(&site, window.orientation),
        localizer.knn.not_heard,
    )?;
    let setup = |method: Method, kind: TrackerKind| Setup {
        split: args.split,
        seeds: args.seeds,
        method,
        localizer: localizer.clone(),
        window: window.clone(),
        tracker: TrackerConfig {
            kind,
            ..tracker.clone()
        },
        smooth_lag: args.smooth_lag,
    };
    let outcome = evaluate(&site, &survey, &setup(args.method, args.tracker))?;
    let m = &outcome.metrics;
    if args.json {
        println!("{}", serde_json::to_string(m)?);
    } else {
        println!(
            "localization on {} ({} rows), {:?} split, {} seeds, {} + tracker {:?}",
            args.survey.display(),
            survey.samples.len(),
            args.split,
            args.seeds,
            args.method.name(),
            args.tracker
        );
        println!(
            "exact {:.3}  within_1 {:.3}  within_2 {:.3}  mean_error_cells {:.3}  mean_error_m {:.3}  p90_error_cells {:.3}  us_per_fix {:.2}",
            m.errors.exact,
            m.errors.within_1,
            m.errors.within_2,
            m.errors.mean_error_cells,
            m.errors.mean_error_m,
            m.errors.p90_error_cells,
            m.us_per_fix
        );
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
