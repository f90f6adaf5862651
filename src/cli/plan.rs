//! `gangway plan`: one route, printed.

use std::path::PathBuf;
use std::process::ExitCode;

use anyhow::Context;

use crate::plan::{self, Destination};

#[derive(clap::Args)]
pub struct Args {
    #[arg(long, default_value_os_t = super::default_config())]
    config: PathBuf,
    /// Start: a place name or `x,y`.
    #[arg(long)]
    from: String,
    /// Destination: a place name or `x,y`.
    #[arg(long)]
    to: String,
    /// Print the route as JSON.
    #[arg(long)]
    json: bool,
}

/// `x,y` as a cell, anything else as a place name.
fn destination(text: &str) -> Destination {
    let coords: Option<Vec<i64>> = text.split(',').map(|p| p.trim().parse().ok()).collect();
    match coords.as_deref() {
        Some(&[x, y]) => Destination::Cell([x, y]),
        _ => Destination::Place(text.to_owned()),
    }
}

pub fn run(args: Args) -> anyhow::Result<ExitCode> {
    let (config, site) = super::load(&args.config)?;
    let from = destination(&args.from).resolve(&site).context("--from")?;
    let to = destination(&args.to).resolve(&site).context("--to")?;
    let planner = plan::build(&config.planner, site.clone());
    let route = planner.plan(from, to)?;
    let length_m = route.length_m(&site);
    if args.json {
        let body = serde_json::json!({
            "from": from,
            "to": to,
            "planner": planner.mode(),
            "waypoints": route.waypoints(&site),
            "length_m": length_m,
        });
        println!("{}", serde_json::to_string_pretty(&body)?);
    } else {
        println!(
            "{} → {}: {} cells, {length_m:.1} m ({})",
            args.from,
            args.to,
            route.cells.len(),
            planner.mode()
        );
        let cells: Vec<String> = route.cells.iter().map(|c| c.to_string()).collect();
        println!("{}", cells.join(" "));
    }
    Ok(ExitCode::SUCCESS)
}
