//! `gangway plan`: one route, printed, and optionally drawn; on a building
//! of several floors, a route across them (`plan::floors`).

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use anyhow::Context;

use crate::plan::floors::BuildingPlanner;
use crate::plan::{self, Destination, PlannerConfig, Profile};
use crate::publish::RouteBody;
use crate::publish::floors::FloorsRouteBody;
use crate::site::{Building, Site};

#[derive(clap::Args)]
pub(super) struct Args {
    #[command(flatten)]
    planner: super::PlannerSource,
    /// Start: a place name or `x,y`, after its floor on a building of
    /// several floors (`F1:entrance`, `B1:40,12`; a place on one floor only
    /// may go without).
    #[arg(long)]
    from: String,
    /// Destination: as --from.
    #[arg(long)]
    to: String,
    /// Walker profile: default, wheelchair or low-vision.
    #[arg(long, default_value = "default")]
    profile: String,
    /// Print the route as JSON (the route part of the MQTT path message).
    #[arg(long)]
    json: bool,
    /// Draw the route on the site grid into this PNG file (across floors,
    /// one file per leg, the floor's name added: `route-F1.png`).
    #[arg(long, conflicts_with = "svg")]
    png: Option<PathBuf>,
    /// Draw the route on the site grid into this SVG file (as --png).
    #[arg(long)]
    svg: Option<PathBuf>,
}

/// `F1:rest` as the floor `F1` and `rest` when `F1` is one of `building`'s
/// floors, else no floor and all of `text`.
fn on_floor<'a>(building: &Building, text: &'a str) -> (Option<&'a str>, &'a str) {
    match text.split_once(':') {
        Some((floor, rest)) if building.floor_named(floor).is_some() => (Some(floor), rest),
        _ => (None, text),
    }
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
    let (config, path) = args.planner.settings()?;
    let building = Building::load(&path)?;
    let profile = Profile::parse(&args.profile).ok_or_else(|| {
        anyhow::anyhow!(
            "--profile: {}",
            plan::unknown_profile_message(&args.profile)
        )
    })?;
    if building.is_multi_floor() {
        across_floors(&args, &config, Arc::new(building), profile)
    } else {
        on_one_floor(&args, &config, &building, profile)
    }
}

/// A site of one floor: its planner as configured, a floor prefix
/// optional.
fn on_one_floor(
    args: &Args,
    config: &PlannerConfig,
    building: &Building,
    profile: Profile,
) -> anyhow::Result<ExitCode> {
    let site = building.floors()[0].site.clone();
    let from = destination(on_floor(building, &args.from).1)
        .resolve(&site)
        .context("--from")?;
    let to = destination(on_floor(building, &args.to).1)
        .resolve(&site)
        .context("--to")?;
    let planner = plan::build(config, site.clone())?;
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

/// A building of several floors: each floor's legs planned by the models
/// the config names for it (`{floor}` in their paths), else by A*, joined by
/// the connectors the profile may use.
fn across_floors(
    args: &Args,
    config: &PlannerConfig,
    building: Arc<Building>,
    profile: Profile,
) -> anyhow::Result<ExitCode> {
    let floors = building
        .floors()
        .iter()
        .map(|floor| {
            let planning = config.for_floor(&floor.name)?;
            plan::build_mode(&planning, planning.mode, floor.site.clone())
                .with_context(|| format!("floor `{}`", floor.name))
        })
        .collect::<anyhow::Result<Vec<_>>>()?;
    let planner = BuildingPlanner::new(building.clone(), config.connectivity, floors);
    let end = |text: &str, flag: &str| {
        let (floor, rest) = on_floor(&building, text);
        planner
            .resolve(floor, &destination(rest))
            .with_context(|| flag.to_owned())
    };
    let (from, to) = (end(&args.from, "--from")?, end(&args.to, "--to")?);
    let started = Instant::now();
    let route = planner.plan(from, to, profile)?;
    let latency_us = started.elapsed().as_micros() as u64;
    let body = FloorsRouteBody::new(&planner, profile, &route, latency_us);
    if args.json {
        println!("{}", serde_json::to_string_pretty(&body)?);
    } else {
        println!(
            "{} → {}: {} legs, {:.1} m walked, {:.0} s (profile {})",
            args.from,
            args.to,
            body.legs.len(),
            body.length_m,
            body.total_s,
            body.profile,
        );
        for (i, leg) in body.legs.iter().enumerate() {
            println!(
                "{}: {} cells, {:.1} m",
                leg.floor,
                leg.route.waypoints.len(),
                leg.route.length_m
            );
            if let Some(c) = body.connectors.get(i) {
                println!(
                    "{} `{}`: {} → {}, {:.0} s",
                    c.kind, c.id, c.from.floor, c.to.floor, c.seconds
                );
            }
        }
        for step in &body.instructions {
            println!("- {}: {}", step.floor, step.instruction.text);
        }
    }
    if let Some(path) = args.png.as_ref().or(args.svg.as_ref()) {
        for leg in &route.legs {
            let floor = &building.floors()[leg.floor];
            draw_leg(&floor.site, &floor.name, &leg.planned.route, path)?;
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// Draws one floor's leg into `path` with the floor's name added to its
/// stem (`route.svg` → `route-F1.svg`).
fn draw_leg(site: &Site, floor: &str, route: &plan::Route, path: &Path) -> anyhow::Result<()> {
    let stem = path.file_stem().unwrap_or_default().to_string_lossy();
    let name = match path.extension() {
        Some(ext) => format!("{stem}-{floor}.{}", ext.to_string_lossy()),
        None => format!("{stem}-{floor}"),
    };
    crate::picture::draw(site, route, &path.with_file_name(name))
}
