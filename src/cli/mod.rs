//! The `gangway` command line: one file per subcommand, each a clap `Args`
//! struct and a `run` function. Subcommands only wire stages together; the work
//! is in the library modules.

mod calibrate;
mod check;
mod eval;
mod plan;
mod record;
mod replay;
mod run;
mod simulate;
mod site;
mod train;
mod walks;

use std::path::PathBuf;
use std::process::ExitCode;

use clap::{Parser, Subcommand};

/// BLE edge gateway: hears iBeacons, locates people and devices on a site grid,
/// and publishes locations and walkable routes over MQTT.
#[derive(Parser)]
#[command(name = "gangway", version, about, long_about = None)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Scan with the local Bluetooth adapter and write what this host hears to a log.
    Record(record::Args),
    /// Run the gateway pipeline over a recorded log.
    Replay(replay::Args),
    /// Simulate walkers on a site and write their adverts, truth and requests to a log.
    Simulate(simulate::Args),
    /// Run the gateway daemon: scan BLE, locate, plan, publish over MQTT.
    Run(run::Args),
    /// Fit the survey-free radio model to captures, with no positions needed.
    Calibrate(calibrate::Args),
    /// Load and validate a config with its site, survey and models.
    Check(check::Args),
    /// Plan one route on a site and print it.
    Plan(plan::Args),
    /// Train path models from walks and the localization cell classifier from a survey.
    Train(train::Args),
    /// Evaluate localization on a labelled survey.
    Eval(eval::Args),
    /// Real walks in: import recorded tracks onto a site, build a scene's site.
    Walks(walks::Args),
    /// Site files: edit one over its floor plan in the browser.
    Site(site::Args),
}

/// Where `--config` points when it is not given.
fn default_config() -> PathBuf {
    PathBuf::from("config/gangway.toml")
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
        }
    }
}

/// Loads a config and its site.
fn load(
    config: &std::path::Path,
) -> anyhow::Result<(crate::config::Config, std::sync::Arc<crate::site::Site>)> {
    let config = crate::config::Config::load(config)?;
    let site = crate::site::Site::load(&config.site)?;
    Ok((config, std::sync::Arc::new(site)))
}

/// Where a planning command gets its site, models and planner settings: a
/// gateway config, or a site file and a directory of trained models given
/// directly, so that what `gangway train --out DIR` wrote is served without
/// writing a config.
#[derive(clap::Args)]
struct PlannerSource {
    /// The gateway config [default: config/gangway.toml unless --site is given].
    #[arg(long)]
    config: Option<PathBuf>,
    /// Plan on this site file instead of the config's (without --config, the
    /// planner settings are the defaults).
    #[arg(long)]
    site: Option<PathBuf>,
    /// Serve the models in this directory (`generator.onnx`,
    /// `path_classifier.onnx`, `conditional_generator.onnx`,
    /// `desire_lines.onnx`, as `gangway train --out` writes them) instead of
    /// the config's `[planner.models]`.
    #[arg(long)]
    models: Option<PathBuf>,
    /// The planner mode instead of the config's `[planner] mode`: learned
    /// (the default: desire lines when they passed their training check,
    /// else the conditional generator, else astar), astar, rejection,
    /// conditional or desire.
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
        let (mut planner, site) = match (&self.config, &self.site) {
            (None, Some(site)) => (
                crate::plan::PlannerConfig::default(),
                std::sync::Arc::new(crate::site::Site::load(site)?),
            ),
            (config, site) => {
                let config = crate::config::Config::load(
                    config.clone().unwrap_or_else(default_config).as_path(),
                )?;
                let site = crate::site::Site::load(site.as_ref().unwrap_or(&config.site))?;
                (config.planner, std::sync::Arc::new(site))
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
