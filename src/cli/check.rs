//! `gangway check`: load everything the daemon would load and name every
//! problem, without starting anything.

use std::process::ExitCode;
use std::sync::Arc;

use crate::config::Config;
use crate::pipeline::Pipeline;
use crate::plan::{PlannerConfig, PlannerMode};
use crate::site::Site;

#[derive(clap::Args)]
pub(super) struct Args {
    #[command(flatten)]
    config: super::ConfigFile,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let mut problems: Vec<String> = Vec::new();
    match Config::load(&args.config.path) {
        Err(e) => problems.push(e.to_string()),
        Ok(config) => match Site::load(&config.site) {
            Err(e) => problems.push(e.to_string()),
            Ok(site) => {
                problems.extend(site.check_floorplan());
                let site = Arc::new(site);
                if let Err(e) = Pipeline::new(&config.pipeline(), site.clone()) {
                    problems.push(format!("{}: {e:#}", args.config.path.display()));
                }
                let planner =
                    planner_serving(&config.planner, &site, &named_models(&args.config.path));
                if let Err(problem) = &planner {
                    problems.push(format!("{}: {problem}", args.config.path.display()));
                }
                if problems.is_empty() {
                    println!(
                        "ok: {} (site {:?}: {}×{} cells, {} walkable, {} beacons, {} gateways, {} places)",
                        args.config.path.display(),
                        site.name,
                        site.width(),
                        site.height(),
                        site.open_cells().len(),
                        site.beacons.len(),
                        site.gateways.len(),
                        site.places().len()
                    );
                    println!("{}", frame(&site));
                    if let Ok(serving) = planner {
                        println!("planner: {serving}");
                    }
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

/// Which planner would answer route requests, and why. `[planner] mode =
/// "learned"` passes over models that are missing or failed their checks
/// and serves A* when none is left: when the config names models
/// (`named`), the daemon would run, but not what the config asks for, so
/// that is a problem here rather than a line in its log.
fn planner_serving(
    config: &PlannerConfig,
    site: &Arc<Site>,
    named: &[String],
) -> Result<String, String> {
    if config.mode != PlannerMode::Learned {
        return Ok(format!("{} (the configured mode)", config.mode.name()));
    }
    let choice = match crate::plan::learned::build(config, site.clone()) {
        Ok((_, choice)) => choice,
        // Pipeline::new has named the error already.
        Err(e) => return Ok(format!("none ({e})")),
    };
    if choice.serves == PlannerMode::Astar && !named.is_empty() {
        return Err(format!(
            "[planner.models] names {}, but none of them can serve: {}; A* would serve \
             instead (set [planner] mode = \"astar\" to serve it on purpose)",
            named.join(", "),
            choice.because
        ));
    }
    Ok(format!(
        "{} serves: {}",
        choice.serves.name(),
        choice.because
    ))
}

/// The keys of `[planner.models]` the config file itself sets (the
/// defaults name files that need not exist).
fn named_models(path: &std::path::Path) -> Vec<String> {
    let table = std::fs::read_to_string(path)
        .ok()
        .and_then(|text| text.parse::<toml::Table>().ok());
    table
        .as_ref()
        .and_then(|t| t.get("planner")?.get("models")?.as_table())
        .map(|models| models.keys().cloned().collect())
        .unwrap_or_default()
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
