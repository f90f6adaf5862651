//! `gangway check`: load everything the daemon would load and name every
//! problem, without starting anything. A building is checked floor by floor
//! as a one-floor site is (floor plan, pipeline, planner), and its
//! connectors by which floors they join.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;

use crate::config::Config;
use crate::daemon::recalibration::{self, RecalibratedFile};
use crate::locate::LocalizerError;
use crate::pipeline::{Pipeline, PipelineConfig, PipelineError};
use crate::plan::{PlannerConfig, PlannerMode};
use crate::site::{Building, Site};
use crate::store::StoreConfig;

#[derive(clap::Args)]
pub(super) struct Args {
    /// The gateway config [default: config/gangway.toml in a checkout of the
    /// repository, else /etc/gangway/gangway.toml; neither when --site is
    /// given].
    #[arg(long, value_name = "FILE", env = "GANGWAY_CONFIG")]
    config: Option<PathBuf>,
    /// Check this site or building file instead of the config's `site`
    /// (without --config, with the default settings).
    #[arg(long, value_name = "SITE.toml")]
    site: Option<PathBuf>,
}

/// What the floors are checked with: the file named in messages, the
/// pipeline's settings, the models the config itself names and whether a
/// config chose the settings.
struct Settings {
    shown: PathBuf,
    pipeline: PipelineConfig,
    named_models: Vec<String>,
    configured: bool,
    /// The config's store, beside which recalibrated files are kept (none
    /// without a config).
    store: Option<StoreConfig>,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let mut problems: Vec<String> = Vec::new();
    let loaded = match (&args.config, &args.site) {
        (None, Some(site)) => Ok((
            site.clone(),
            Settings {
                shown: site.clone(),
                pipeline: PipelineConfig::default(),
                named_models: Vec::new(),
                configured: false,
                store: None,
            },
        )),
        (config, site) => {
            let path = config.clone().unwrap_or_else(super::default_config);
            Config::load(&path).map(|config| {
                (
                    site.clone().unwrap_or(config.site.clone()),
                    Settings {
                        named_models: named_models(&path),
                        shown: path,
                        pipeline: config.pipeline(),
                        configured: true,
                        store: Some(config.store.clone()),
                    },
                )
            })
        }
    };
    match loaded {
        Err(e) => problems.push(e.to_string()),
        Ok((site, settings)) => match Building::load(&site) {
            Err(e) => problems.push(e.to_string()),
            Ok(building) => check(&building, &settings, &mut problems),
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

/// Checks every floor of `building` and prints what passed; a one-floor
/// site prints as it always has.
fn check(building: &Building, settings: &Settings, problems: &mut Vec<String>) {
    let shown = settings.shown.display();
    let mut lines = Vec::new();
    // What the gateway would serve: an earlier recalibration's files in
    // place of the configured calibration.
    let mut configured = settings.pipeline.clone();
    let mut recalibrated = Vec::new();
    if let Some(store) = &settings.store {
        let serving = recalibration::serving(&configured.localizer, store, building);
        configured.localizer = serving.config;
        recalibrated = serving.files;
    }
    for floor in building.floors() {
        let site = &floor.site;
        // A building's problems say which floor they are on.
        let on = if building.is_multi_floor() {
            format!("{shown}: floor `{}`", floor.name)
        } else {
            shown.to_string()
        };
        let found = problems.len();
        problems.extend(site.check_floorplan());
        let mut localizer = None;
        // Each floor as the daemon builds it: its own files where the
        // config names them per floor.
        let mut pipeline = configured.clone();
        if building.is_multi_floor() {
            let localizer = pipeline.localizer.for_floor(&floor.name);
            let planner = pipeline.planner.for_floor(&floor.name);
            match (localizer, planner) {
                (Ok(localizer), Ok(planner)) => {
                    pipeline.localizer = localizer;
                    pipeline.planner = planner;
                }
                (Err(e), _) => {
                    problems.push(format!("{on}: {e}"));
                    continue;
                }
                (_, Err(e)) => {
                    problems.push(format!("{on}: {e}"));
                    continue;
                }
            }
        }
        match Pipeline::new(&pipeline, site.clone()) {
            Ok(_) => {}
            // A site no config has asked to locate on may not have its
            // beacons placed yet (`site import` writes none): that is what to
            // do next, not a fault of the file.
            Err(PipelineError::Localizer(LocalizerError::NoAnchorPositions))
                if !settings.configured =>
            {
                localizer = Some(
                    "localizer: none can locate here yet, no beacon has a position; `gangway \
                     survey import` estimates them from walks, `gangway site edit` places them",
                );
            }
            Err(e) => problems.push(format!("{on}: {e:#}")),
        }
        // A floor of a building without models of its own is planned on its
        // geometry (docs/floors.md): not a problem.
        let named: &[String] = if building.is_multi_floor() {
            &[]
        } else {
            &settings.named_models
        };
        let planner = if pipeline.planner.mode == settings.pipeline.planner.mode {
            planner_serving(&pipeline.planner, site, named)
        } else {
            one_floor_s_models(&settings.named_models)
        };
        match planner {
            Err(problem) => problems.push(format!("{on}: {problem}")),
            Ok(serving) if problems.len() == found => {
                let summary = summary(site);
                lines.push(if building.is_multi_floor() {
                    format!(
                        "ok: floor {} (level {}): {summary}",
                        floor.name, floor.level
                    )
                } else {
                    format!("ok: {shown} ({summary})")
                });
                lines.push(frame(site));
                lines.extend(localizer.map(str::to_owned));
                let name = building.is_multi_floor().then_some(floor.name.as_str());
                let file = recalibrated.iter().find(|f| f.floor.as_deref() == name);
                lines.extend(file.map(recalibrated_line));
                lines.push(format!("planner: {serving}"));
            }
            Ok(_) => {}
        }
    }
    if !problems.is_empty() {
        return;
    }
    if building.is_multi_floor() {
        println!(
            "ok: {shown} (building {:?}: {} floors, {} connectors)",
            building.name,
            building.floors().len(),
            building.connectors().len()
        );
    }
    for line in lines {
        println!("{line}");
    }
    if building.is_multi_floor() {
        println!("{}", connectors(building));
    }
}

/// What serves a floor that an earlier recalibration fitted, in one line.
fn recalibrated_line(file: &RecalibratedFile) -> String {
    let path = file.path.display();
    match &file.loaded {
        Ok(calibration) => format!(
            "localizer: recalibrated on this gateway from {} windows ({} beacons, {} cells \
             refined): {path}",
            calibration.windows,
            calibration.anchors.len(),
            calibration.cells.len()
        ),
        Err(e) => format!(
            "localizer: the recalibrated file does not load, the configured calibration \
             serves until the next recalibration rewrites it: {e}"
        ),
    }
}

/// A floor's site in one line.
fn summary(site: &Site) -> String {
    format!(
        "site {:?}: {}×{} cells, {} walkable, {} beacons, {} gateways, {} places",
        site.name,
        site.width(),
        site.height(),
        site.open_cells().len(),
        site.beacons.len(),
        site.gateways.len(),
        site.places().len()
    )
}

/// The connectors by kind, and which floors they join: all of them, and
/// those a wheelchair may use (lifts and ramps only).
fn connectors(building: &Building) -> String {
    let floors = building.floors();
    let joined = |groups: Vec<Vec<usize>>| {
        if groups.len() == 1 {
            return format!("all {} floors joined", floors.len());
        }
        let shown: Vec<String> = groups
            .iter()
            .map(|g| {
                g.iter()
                    .map(|&f| floors[f].name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            })
            .collect();
        format!("floors apart: {}", shown.join(" | "))
    };
    if building.connectors().is_empty() {
        return format!(
            "connectors: none, so no route or walker can change floor; add [[connectors]] to \
             the building file (docs/floors.md); {}",
            joined(building.floor_groups(|_| true))
        );
    }
    let mut kinds: Vec<(&str, usize)> = Vec::new();
    for c in building.connectors() {
        match kinds.iter_mut().find(|k| k.0 == c.kind.name()) {
            Some(k) => k.1 += 1,
            None => kinds.push((c.kind.name(), 1)),
        }
    }
    let kinds: Vec<String> = kinds.iter().map(|(k, n)| format!("{n} {k}")).collect();
    format!(
        "connectors: {} ({}): {}; step-free (lifts and ramps only): {}",
        building.connectors().len(),
        kinds.join(", "),
        joined(building.floor_groups(|_| true)),
        joined(building.floor_groups(|c| c.kind.step_free()))
    )
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

/// A building's floor under `[planner] mode = "learned"` whose config names
/// no model per floor (no `{floor}` in a path): planned by A*, which is a
/// problem only when the config names models, one floor's then.
fn one_floor_s_models(named: &[String]) -> Result<String, String> {
    if named.is_empty() {
        return Ok(
            "astar serves: no [planner.models] path names `{floor}`, so no floor has \
                   models of its own (train each floor's with `gangway train --site FLOOR.toml \
                   --out models/FLOOR` and name `models/{floor}/…`)"
                .to_owned(),
        );
    }
    Err(format!(
        "[planner.models] names {} for every floor of a building of several: a model is trained \
         on one floor; put `{{floor}}` in each path where the floor's name goes \
         (`models/{{floor}}/desire_lines.onnx`)",
        named.join(", ")
    ))
}

/// The keys of `[planner.models]` the config file itself sets (the
/// defaults name files that need not exist).
fn named_models(path: &Path) -> Vec<String> {
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
