//! The `gangway` command line: one file per subcommand, each a clap `Args`
//! struct and a `run` function. Subcommands only wire stages together; the work
//! is in the library modules.

mod calibrate;
mod check;
mod eval;
pub mod examples;
mod plan;
mod record;
mod replay;
mod run;
mod simulate;
mod site;
mod survey;
mod train;
mod walks;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// BLE edge gateway: hears iBeacons, locates people and devices on a site grid,
/// and publishes locations and walkable routes over MQTT.
#[derive(Parser)]
#[command(name = "gangway", version, about, long_about = None, after_long_help = examples::GANGWAY)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Scan with the local Bluetooth adapter and write what this host hears to a log.
    #[command(after_long_help = examples::RECORD)]
    Record(record::Args),
    /// Run the gateway pipeline over a recorded log.
    #[command(after_long_help = examples::REPLAY)]
    Replay(replay::Args),
    /// Simulate walkers on a site and write their adverts, truth and requests to a log.
    #[command(after_long_help = examples::SIMULATE)]
    Simulate(simulate::Args),
    /// Run the gateway daemon: scan BLE, locate, plan, publish over MQTT.
    #[command(after_long_help = examples::RUN)]
    Run(run::Args),
    /// Fit the survey-free radio model to captures, with no positions needed.
    #[command(after_long_help = examples::CALIBRATE)]
    Calibrate(calibrate::Args),
    /// Load and validate a config with its site, survey and models.
    #[command(after_long_help = examples::CHECK)]
    Check(check::Args),
    /// Plan one route on a site and print it.
    #[command(after_long_help = examples::PLAN)]
    Plan(plan::Args),
    /// Train path models from walks and the localization cell classifier from a survey.
    #[command(after_long_help = examples::TRAIN)]
    Train(train::Args),
    /// Evaluate localization, planning or guidance against known answers.
    #[command(after_long_help = examples::EVAL)]
    Eval(eval::Args),
    /// Real walks in: import recorded tracks onto a site, build a scene's site.
    #[command(after_long_help = examples::WALKS)]
    Walks(walks::Args),
    /// Site files: edit one over its floor plan in the browser, import a building's floor plans.
    #[command(after_long_help = examples::SITE)]
    Site(site::Args),
    /// Surveys from walks with timed waypoints: a floor's site, labelled survey and beacon positions.
    #[command(after_long_help = examples::SURVEY)]
    Survey(survey::Args),
}

/// The sample config of a checkout of the repository, relative to it.
const CHECKOUT_CONFIG: &str = "config/gangway.toml";
/// The config the Debian package installs (and the systemd unit runs).
const INSTALLED_CONFIG: &str = "/etc/gangway/gangway.toml";

/// Where `--config` points when neither it nor `GANGWAY_CONFIG` is given:
/// the checkout's sample when gangway runs in a checkout, else the
/// installed config. Run from anywhere else, an installed gateway finds its
/// config without being told.
fn default_config() -> PathBuf {
    if std::path::Path::new(CHECKOUT_CONFIG).is_file() {
        PathBuf::from(CHECKOUT_CONFIG)
    } else {
        PathBuf::from(INSTALLED_CONFIG)
    }
}

/// `--config FILE`, for the commands that need a gateway config.
#[derive(clap::Args)]
struct ConfigFile {
    /// The gateway config [default: config/gangway.toml in a checkout of the
    /// repository, else /etc/gangway/gangway.toml].
    #[arg(
        id = "config",
        long = "config",
        value_name = "FILE",
        env = "GANGWAY_CONFIG",
        default_value_os_t = default_config(),
        hide_default_value = true
    )]
    path: PathBuf,
}

impl Cli {
    pub fn run(self) -> anyhow::Result<ExitCode> {
        match self.command {
            Command::Record(args) => record::run(args),
            Command::Replay(args) => replay::run(args),
            Command::Simulate(args) => simulate::run(args),
            Command::Run(args) => run::run(args),
            Command::Calibrate(args) => calibrate::run(args),
            Command::Check(args) => check::run(args),
            Command::Plan(args) => plan::run(args),
            Command::Train(args) => train::run(args),
            Command::Eval(args) => eval::run(args),
            Command::Walks(args) => walks::run(args),
            Command::Site(args) => site::run(args),
            Command::Survey(args) => survey::run(args),
        }
    }
}

/// Loads a config and its site, a building of one floor or several, as
/// the daemon serves it.
fn load(
    config: &std::path::Path,
) -> anyhow::Result<(crate::config::Config, std::sync::Arc<crate::site::Building>)> {
    let config = crate::config::Config::load(config)?;
    let building = std::sync::Arc::new(crate::site::Building::load(&config.site)?);
    Ok((config, building))
}

/// Where a planning command gets its site, models and planner settings: a
/// gateway config, or a site file and a directory of trained models given
/// directly, so that what `gangway train --out DIR` wrote is served without
/// writing a config.
#[derive(clap::Args)]
struct PlannerSource {
    /// The gateway config [default: config/gangway.toml in a checkout of the
    /// repository, else /etc/gangway/gangway.toml; neither when --site is
    /// given].
    #[arg(long, value_name = "FILE", env = "GANGWAY_CONFIG")]
    config: Option<PathBuf>,
    /// Plan on this site file instead of the config's (without --config, the
    /// planner settings are the defaults).
    #[arg(long)]
    site: Option<PathBuf>,
    /// Serve the models in this directory (`generator.onnx`,
    /// `path_classifier.onnx`, `conditional_generator.onnx`,
    /// `desire_lines.onnx`, `line_generator.onnx`, as `gangway train --out`
    /// writes them) instead of the config's `[planner.models]`.
    #[arg(long)]
    models: Option<PathBuf>,
    /// The planner mode instead of the config's `[planner] mode`: learned
    /// (the default: desire lines when they passed their training check,
    /// else the line GAN when it passed its checks, else the conditional
    /// generator, else rejection when its generator passed its checks, else
    /// astar), astar, rejection, conditional, desire or line_gan.
    #[arg(long, value_parser = parse_mode)]
    mode: Option<crate::plan::PlannerMode>,
}

fn parse_mode(text: &str) -> Result<crate::plan::PlannerMode, String> {
    use crate::plan::PlannerMode;
    PlannerMode::ALL
        .into_iter()
        .find(|m| m.name() == text)
        .ok_or_else(|| {
            let names: Vec<&str> = PlannerMode::ALL.iter().map(|m| m.name()).collect();
            format!("unknown mode `{text}`; use one of {}", names.join(", "))
        })
}

impl PlannerSource {
    /// The planner settings and the site they plan on.
    fn load(
        &self,
    ) -> anyhow::Result<(
        crate::plan::PlannerConfig,
        std::sync::Arc<crate::site::Site>,
    )> {
        let (planner, site) = self.settings()?;
        Ok((
            planner,
            std::sync::Arc::new(crate::site::Site::load(&site)?),
        ))
    }

    /// The planner settings and the path of the site file they plan on
    /// (a building file, for a command that plans across floors).
    fn settings(&self) -> anyhow::Result<(crate::plan::PlannerConfig, PathBuf)> {
        let (mut planner, site) = match (&self.config, &self.site) {
            (None, Some(site)) => (crate::plan::PlannerConfig::default(), site.clone()),
            (config, site) => {
                let config = crate::config::Config::load(
                    config.clone().unwrap_or_else(default_config).as_path(),
                )?;
                (config.planner, site.clone().unwrap_or(config.site))
            }
        };
        if let Some(dir) = &self.models {
            serve_models_from(&mut planner, dir);
        }
        if let Some(mode) = self.mode {
            planner.mode = mode;
        }
        Ok((planner, site))
    }
}

/// Points `planner` at the models in `dir`, named as `gangway train --out`
/// writes them.
fn serve_models_from(planner: &mut crate::plan::PlannerConfig, dir: &std::path::Path) {
    use crate::model::Kind;
    let file = |kind: Kind| dir.join(format!("{}.onnx", kind.name()));
    let m = &mut planner.models;
    m.generator = file(Kind::Generator);
    m.path_classifier = file(Kind::PathClassifier);
    m.conditional_generator = file(Kind::ConditionalGenerator);
    m.desire_lines = file(Kind::DesireLines);
    m.line_generator = file(Kind::LineGenerator);
}

/// A tokio runtime for the long-running subcommands (`run`, `record`):
/// worker threads, so one busy task never holds up the broker link.
fn runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()?)
}

/// A one-thread runtime for batch work (`replay`): the pipeline and the MQTT
/// link take turns on one thread, so handing each message to the link costs
/// no cross-thread wake-up (a third of replay's time with the multi-thread
/// runtime).
fn batch_runtime() -> anyhow::Result<tokio::runtime::Runtime> {
    Ok(tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?)
}
