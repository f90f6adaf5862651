//! `gangway run`: the daemon.

use std::path::PathBuf;
use std::process::ExitCode;

use crate::daemon::{self, source::Replay};

#[derive(clap::Args)]
pub struct Args {
    #[arg(long, default_value_os_t = super::default_config())]
    config: PathBuf,
    /// Use this broker (mqtt://host:port or mqtts://host:port), overriding
    /// [mqtt] url. Without either, an embedded broker starts on 127.0.0.1.
    #[arg(long)]
    mqtt_url: Option<String>,
    /// Play this advert log instead of scanning Bluetooth (demos, tests, and
    /// gateways fed by another recorder); MQTT is served as in a live run.
    #[arg(long, value_name = "LOG")]
    replay: Option<PathBuf>,
    /// Playback speed of --replay: 1 is real time, 0 as fast as possible.
    #[arg(long, default_value_t = 1.0, requires = "replay")]
    speed: f64,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    anyhow::ensure!(
        args.speed >= 0.0 && args.speed.is_finite(),
        "--speed must be 0 (as fast as possible) or a positive factor"
    );
    let options = daemon::Options {
        config_path: args.config,
        mqtt_url: args.mqtt_url,
        replay: args.replay.map(|log| Replay {
            log,
            speed: args.speed,
        }),
    };
    super::runtime()?.block_on(daemon::run(options))?;
    Ok(ExitCode::SUCCESS)
}
