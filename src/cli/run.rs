//! `gangway run`: the daemon.

use std::path::PathBuf;
use std::process::ExitCode;

#[derive(clap::Args)]
pub struct Args {
    #[arg(long, default_value_os_t = super::default_config())]
    config: PathBuf,
    /// Publish to this broker (mqtt://host:port), overriding [mqtt] url.
    #[arg(long)]
    mqtt_url: Option<String>,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let (config, site) = super::load(&args.config)?;
    super::runtime()?.block_on(crate::daemon::run(config, site, args.mqtt_url))?;
    Ok(ExitCode::SUCCESS)
}
