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
mod train;

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
