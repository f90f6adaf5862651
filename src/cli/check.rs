//! `gangway check`: load everything the daemon would load and name every
//! problem, without starting anything.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use crate::config::Config;
use crate::pipeline::Pipeline;
use crate::site::Site;

#[derive(clap::Args)]
pub(super) struct Args {
    #[arg(long, default_value_os_t = super::default_config())]
    config: PathBuf,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let mut problems: Vec<String> = Vec::new();
    match Config::load(&args.config) {
        Err(e) => problems.push(e.to_string()),
        Ok(config) => match Site::load(&config.site) {
            Err(e) => problems.push(e.to_string()),
            Ok(site) => {
                problems.extend(site.check_floorplan());
                let site = Arc::new(site);
                if let Err(e) = Pipeline::new(&config.pipeline(), site.clone()) {
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
                    println!("{}", frame(&site));
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

/// The site's metric frame and what its obstacles and walls drew, so that a
/// site drawn in metres can be checked against its plan.
fn frame(site: &Site) -> String {
    let (lo, hi) = site.extent_m();
    let [ox, oy] = site.origin_m();
    let shapes = site.shapes();
    format!(
        "frame: {} m cells, origin [{ox}, {oy}] m, y {}; extent x {} to {} m, y {} to {} m; \
         {} obstacles and {} walls blocked {} cells",
        site.cell_m,
        site.y_axis(),
        lo[0],
        hi[0],
        lo[1],
        hi[1],
        shapes.obstacles,
        shapes.walls,
        shapes.cells_blocked
    )
}
