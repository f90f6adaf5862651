//! `gangway survey import`: one floor of walks with timed waypoints (the
//! Indoor Location Competition layout) as a site, a labelled survey and the
//! beacons' estimated positions (`survey`).

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use clap::Subcommand;

use crate::survey::{Options, import};

#[derive(clap::Args)]
pub(super) struct Args {
    #[command(subcommand)]
    what: What,
}

#[derive(Subcommand)]
enum What {
    /// One floor's directory (`floor_info.json`, `geojson_map.json`,
    /// `floor_image.png`, `path_data_files/*.txt`) as `site.toml`,
    /// `survey.csv` and the floor image in `--out`: walkable cells and
    /// places from the floor plan, survey rows interpolated between the
    /// walks' waypoints, beacons placed where they were heard loudest.
    Import(ImportArgs),
}

#[derive(clap::Args)]
struct ImportArgs {
    /// The floor's directory.
    #[arg(long)]
    floor_dir: PathBuf,
    /// Where to write `site.toml`, `survey.csv` and the floor image
    /// (created if needed; files of those names are replaced).
    #[arg(long)]
    out: PathBuf,
    /// Metres per cell side.
    #[arg(long, default_value_t = 1.0)]
    cell_m: f64,
    /// The site's name [default: the floor directory's name].
    #[arg(long)]
    name: Option<String>,
    /// Seconds of readings in one survey row (as `[window] length_s`).
    #[arg(long, default_value_t = Options::default().window_s)]
    window_s: f64,
    /// Seconds between rows (as `[window] stride_s`).
    #[arg(long, default_value_t = Options::default().stride_s)]
    stride_s: f64,
    /// Rows between waypoints further apart than this (seconds) are refused.
    #[arg(long, default_value_t = Options::default().max_gap_s)]
    max_gap_s: f64,
    /// Rows between waypoints implying a faster walk (m/s) are refused.
    #[arg(long, default_value_t = Options::default().max_speed_mps)]
    max_speed: f64,
    /// Print one JSON object with the counts.
    #[arg(long)]
    json: bool,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let What::Import(args) = args.what;
    let options = Options {
        name: args.name,
        cell_m: args.cell_m,
        window_s: args.window_s,
        stride_s: args.stride_s,
        max_gap_s: args.max_gap_s,
        max_speed_mps: args.max_speed,
    };
    let started = Instant::now();
    let report = import(&args.floor_dir, &args.out, &options)?;
    let seconds = started.elapsed().as_secs_f64();
    for problem in report.shown_problems() {
        eprintln!("warning: {problem}");
    }
    if args.json {
        let mut json = serde_json::to_value(&report)?;
        json["seconds"] = seconds.into();
        println!("{json}");
        return Ok(ExitCode::SUCCESS);
    }
    let r = &report;
    println!(
        "read {} walks: {} waypoints, {} iBeacon readings ({} lines skipped)",
        r.walks, r.waypoints, r.readings, r.lines_skipped
    );
    println!(
        "wrote {}: {} × {} m cells, {} of {} walkable, {} places, {} beacons",
        r.site.display(),
        options.cell_m,
        options.cell_m,
        r.walkable_cells,
        r.cells,
        r.places,
        r.beacons
    );
    let f = &r.refused;
    println!(
        "wrote {}: {} rows; refused {} before the first waypoint, {} after the last, {} across \
         a gap over {} s, {} faster than {} m/s, {} off the walkable cells",
        r.survey.display(),
        r.rows,
        f.before_first_waypoint,
        f.after_last_waypoint,
        f.waypoint_gap,
        options.max_gap_s,
        f.implausible_speed,
        options.max_speed_mps,
        f.off_walkable
    );
    println!(
        "beacons: kept {} readings; {} ids heard from several MACs, one beacon per MAC; dropped \
         {} heard under 3 times at a known position ({} readings)",
        r.readings_kept, r.shared_ids_split, r.rare_ids_dropped, r.rare_readings_dropped
    );
    println!("took {seconds:.1} s");
    Ok(ExitCode::SUCCESS)
}
