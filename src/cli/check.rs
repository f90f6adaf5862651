//! `gangway check`: load everything the daemon would load and name every
//! problem, without starting anything.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use crate::config::Config;
use crate::pipeline::Pipeline;
use crate::site::Site;

#[derive(clap::Args)]
pub struct Args {
    #[arg(long, default_value_os_t = super::default_config())]
    config: PathBuf,
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let mut problems: Vec<String> = Vec::new();
    match Config::load(&args.config) {
        Err(e) => problems.push(e.to_string()),
        Ok(config) => match Site::load(&config.site) {
            Err(e) => problems.push(e.to_string()),
            Ok(site) => {
                let site = Arc::new(site);
                if let Err(e) = Pipeline::new(&config, site.clone()) {
                    problems.push(format!("{}: {e:#}", args.config.display()));
                }
                if problems.is_empty() {
                    println!(
                        "ok: {} (site {:?}: {}×{} cells, {} walkable, {} beacons, {} gateways, {} places)",
                        args.config.display(),
                        site.name,
                        site.width(),
                        site.height(),
                        site.open_cells().len(),
                        site.beacons.len(),
                        site.gateways.len(),
                        site.places().len()
                    );
                }
            }
        },
    }
    if problems.is_empty() {
        return Ok(ExitCode::SUCCESS);
    }
    for p in &problems {
        eprintln!("error: {p}");
    }
    Ok(ExitCode::FAILURE)
}
