//! `gangway simulate`: walkers on a site, written as an advert log; or, with
//! `--trajectories`, walks between places written as trajectories.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use anyhow::Context;

use crate::config::Config;
use crate::locate::survey::Survey;
use crate::simulate::{SimConfig, WalkConfig, simulate, simulate_walks};
use crate::site::Site;
use crate::source::log::LogWriter;
use crate::train::trajectory;

#[derive(clap::Args)]
pub(super) struct Args {
    /// The site file.
    #[arg(long)]
    site: PathBuf,
    /// The log to write (JSON Lines).
    #[arg(long)]
    out: PathBuf,
    /// Write walks between places as trajectories (path-model training data)
    /// instead of an advert log.
    #[arg(long)]
    trajectories: bool,
    /// With --trajectories: walks between each pair of named places.
    #[arg(long, default_value_t = WalkConfig::default().walks_per_pair)]
    walks_per_pair: usize,
    /// With --trajectories: walks between random cells, besides the place pairs.
    #[arg(long, default_value_t = WalkConfig::default().random_walks)]
    random_walks: usize,
    #[arg(long, default_value_t = SimConfig::default().walkers)]
    walkers: usize,
    /// Seconds of simulated time.
    #[arg(long, default_value_t = SimConfig::default().duration_s)]
    duration: f64,
    #[arg(long, default_value_t = SimConfig::default().seed)]
    seed: u64,
    /// Scans per second of each walker's phone.
    #[arg(long, default_value_t = SimConfig::default().scan_hz)]
    scan_hz: f64,
    /// Share of adverts lost.
    #[arg(long, default_value_t = SimConfig::default().dropout)]
    dropout: f64,
    /// Route requests per walker.
    #[arg(long, default_value_t = SimConfig::default().requests_per_walker)]
    requests: usize,
    /// Replay real readings from this survey (CSV) at each walker's cell instead
    /// of the path-loss model.
    #[arg(long)]
    survey: Option<PathBuf>,
    /// "Not heard" value in the survey.
    #[arg(long, default_value_t = -200, allow_negative_numbers = true)]
    not_heard: i16,
    /// Phones hear the beacons as this gateway config's `[localizer.pathloss]`
    /// radio model (and its calibration file) describes them, with its
    /// `[window] length_s`; without it, the model's defaults.
    #[arg(long)]
    config: Option<PathBuf>,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    if args.trajectories {
        return run_walks(&args);
    }
    anyhow::ensure!(args.scan_hz > 0.0, "--scan-hz must be positive");
    anyhow::ensure!(
        (0.0..1.0).contains(&args.dropout),
        "--dropout must be in [0, 1)"
    );
    anyhow::ensure!(args.duration > 0.0, "--duration must be positive seconds");
    let site = Arc::new(Site::load(&args.site)?);
    let survey = match &args.survey {
        Some(path) => {
            let anchors: Vec<String> = site.beacons.iter().map(|b| b.id.clone()).collect();
            let survey = Survey::load(path, &site, &anchors, args.not_heard)?;
            anyhow::ensure!(
                !survey.samples.is_empty(),
                "{}: the survey has no rows",
                path.display()
            );
            Some(survey)
        }
        None => None,
    };
    let hearing = match &args.config {
        Some(path) => SimConfig::hearing(&Config::load(path)?, &site)?,
        None => SimConfig::default(),
    };
    let config = SimConfig {
        walkers: args.walkers,
        duration_s: args.duration,
        seed: args.seed,
        scan_hz: args.scan_hz,
        dropout: args.dropout,
        requests_per_walker: args.requests,
        ..hearing
    };
    let events = simulate(&site, &config, survey.as_ref());
    let mut writer = LogWriter::create(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    for event in &events {
        writer.write(event)?;
    }
    writer.flush()?;
    tracing::info!(events = events.len(), out = %args.out.display(), "simulation written");
    Ok(ExitCode::SUCCESS)
}

fn run_walks(args: &Args) -> anyhow::Result<ExitCode> {
    let site = Site::load(&args.site)?;
    let config = WalkConfig {
        walks_per_pair: args.walks_per_pair,
        random_walks: args.random_walks,
        seed: args.seed,
        ..WalkConfig::default()
    };
    let walks = simulate_walks(&site, &config);
    let file = std::fs::File::create(&args.out)
        .with_context(|| format!("cannot create {}", args.out.display()))?;
    trajectory::write(std::io::BufWriter::new(file), &walks)
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    tracing::info!(walks = walks.len(), out = %args.out.display(), "walks written");
    Ok(ExitCode::SUCCESS)
}
