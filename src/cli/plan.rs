//! `gangway plan`: one route, printed, and optionally drawn.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

use anyhow::Context;

use crate::plan::{self, Destination, Profile};
use crate::publish::RouteBody;

#[derive(clap::Args)]
pub(super) struct Args {
    #[command(flatten)]
    planner: super::PlannerSource,
    /// Start: a place name or `x,y`.
    #[arg(long)]
    from: String,
    /// Destination: a place name or `x,y`.
    #[arg(long)]
    to: String,
    /// Walker profile: default, wheelchair or low-vision.
    #[arg(long, default_value = "default")]
    profile: String,
    /// Print the route as JSON (the route part of the MQTT path message).
    #[arg(long)]
    json: bool,
    /// Draw the route on the site grid into this PNG file.
    #[arg(long, conflicts_with = "svg")]
    png: Option<PathBuf>,
    /// Draw the route on the site grid into this SVG file.
    #[arg(long)]
    svg: Option<PathBuf>,
}

/// `x,y` as a cell, anything else as a place name.
fn destination(text: &str) -> Destination {
    let coords: Option<Vec<i64>> = text.split(',').map(|p| p.trim().parse().ok()).collect();
    match coords.as_deref() {
        Some(&[x, y]) => Destination::Cell([x, y]),
        _ => Destination::Place(text.to_owned()),
    }
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let (config, site) = args.planner.load()?;
    let profile = Profile::parse(&args.profile).ok_or_else(|| {
        anyhow::anyhow!(
            "--profile: {}",
            plan::unknown_profile_message(&args.profile)
        )
    })?;
    let from = destination(&args.from).resolve(&site).context("--from")?;
    let to = destination(&args.to).resolve(&site).context("--to")?;
    let planner = plan::build(&config, site.clone())?;
    let started = Instant::now();
    let planned = planner.plan(from, to, profile)?;
    let latency_us = started.elapsed().as_micros() as u64;
    let body = RouteBody::new(&site, &*planner, profile, from, to, &planned, latency_us);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&body)?);
    } else {
        println!(
            "{} → {}: {} cells, {:.1} m ({}, {}, profile {})",
            args.from,
            args.to,
            planned.route.cells.len(),
            body.length_m,
            body.planner,
            serde_json::to_value(body.origin)?
                .as_str()
                .unwrap_or_default(),
            body.profile,
        );
        let cells: Vec<String> = planned.route.cells.iter().map(|c| c.to_string()).collect();
        println!("{}", cells.join(" "));
        for step in &body.instructions {
            println!("- {}", step.text);
        }
    }
    if let Some(path) = args.png.as_ref().or(args.svg.as_ref()) {
        crate::picture::draw(&site, &planned.route, path)?;
    }
    Ok(ExitCode::SUCCESS)
}
