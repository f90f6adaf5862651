//! `gangway calibrate`: fits the survey-free radio model to what was heard,
//! with no positions, and writes the calibration file `[localizer.pathloss]
//! calibration` loads.
//!
//! One floor at a time: on a building of several floors, `--floor NAME` says
//! which floor the captures were taken on, and that floor's beacons and grid
//! are fitted (each floor's file is then named with `{floor}` in the config).

use std::collections::BTreeMap;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;

use anyhow::Context;

use crate::event::Event;
use crate::locate::calibrate::{FitOptions, Window, calibrate};
use crate::locate::pathloss::anchors;
use crate::locate::window::{Windows, anchor_ids};
use crate::source::capture::{CaptureReader, Format, ReadOptions};

#[derive(clap::Args)]
pub(super) struct Args {
    #[command(flatten)]
    config: super::ConfigFile,
    /// Captures heard on this site (any format `replay` reads: JSON Lines
    /// advert logs, CSV scan logs with or without positions, btsnoop, pcap). Rows
    /// with a position (a few surveyed points) are used as such.
    #[arg(long, required = true, num_args = 1..)]
    from: Vec<PathBuf>,
    /// The capture format; detected per file by default.
    #[arg(long, value_enum)]
    format: Option<Format>,
    /// RSSI value that means "not heard" in CSV scan logs.
    #[arg(long, default_value_t = -200, allow_negative_numbers = true)]
    not_heard: i16,
    /// Where to write the calibration (TOML).
    #[arg(long)]
    out: PathBuf,
    /// On a building of several floors: the floor the captures were taken
    /// on, by its name in the building file.
    #[arg(long, value_name = "NAME")]
    floor: Option<String>,
    /// EM iterations.
    #[arg(long, default_value_t = crate::locate::calibrate::CALIBRATION_ITERATIONS)]
    iterations: usize,
    /// Then refine a radio map per cell by EM, for this many iterations
    /// (default 8 when given without a value): for captures of the phones and
    /// floor area the gateway will localize, not of other ones.
    #[arg(long, num_args = 0..=1, default_missing_value = "8")]
    cells: Option<usize>,
    /// Weight of the per-anchor model in each refined cell, in readings.
    #[arg(long, default_value_t = crate::locate::calibrate::DEFAULT_CELL_PRIOR_READINGS)]
    cell_prior_readings: f64,
    /// Print the report as one JSON object.
    #[arg(long)]
    json: bool,
}

pub(super) fn run(args: Args) -> anyhow::Result<ExitCode> {
    let (config, building) = super::load(&args.config.path)?;
    let names = || {
        let names: Vec<&str> = building.floors().iter().map(|f| f.name.as_str()).collect();
        names.join(", ")
    };
    let floor = match &args.floor {
        Some(name) => building.floor_named(name).with_context(|| {
            format!(
                "--floor {name}: {} has no such floor; its floors are {}",
                args.config.path.display(),
                names()
            )
        })?,
        None if building.is_multi_floor() => anyhow::bail!(
            "{}: the config's site is a building of {} floors ({}); `calibrate` fits one \
             floor's radio model from captures taken on it: give --floor NAME",
            args.config.path.display(),
            building.floors().len(),
            names()
        ),
        None => 0,
    };
    let site = building.floors()[floor].site.clone();
    // The captures are read as that floor's alone: a CSV scan log's columns
    // must be its beacons, and truths on other floors are not its cells.
    let (name, lowest) = (&building.floors()[floor].name, &building.floors()[0].name);
    let multi_floor = building.is_multi_floor();
    let on_floor = |truth: Option<&str>| !multi_floor || truth.unwrap_or(lowest) == name;
    let floor_site = crate::site::Building::of_site(site.clone());
    let orientation = config.window.orientation;
    let ids = anchor_ids(&site, orientation);
    let mut trajectories = Vec::new();
    for path in &args.from {
        trajectories.extend(read(&args, path, &floor_site, &on_floor, &config.window)?);
    }
    let windows: usize = trajectories.iter().map(Vec::len).sum();
    anyhow::ensure!(
        windows > 0,
        "no fingerprint windows in {:?}: do the captures hear the site's beacons?",
        args.from
    );
    // Starts from the configured model, without any calibration it names.
    let pathloss = &config.localizer.pathloss;
    let start = anchors(&site, orientation, pathloss, None);
    let started = std::time::Instant::now();
    let options = FitOptions {
        iterations: args.iterations,
        cell_iterations: args.cells.unwrap_or(0),
        cell_prior_readings: args.cell_prior_readings,
    };
    let fitted = calibrate(
        &site,
        &ids,
        &start,
        &config.tracker,
        &trajectories,
        &options,
    )?;
    let seconds = started.elapsed().as_secs_f64();
    let (floor_arg, load_as) = match &args.floor {
        Some(name) => (
            format!(" --floor {name}"),
            "<each floor's file, relative to the gateway config, with {floor} where the floor's \
             name goes>",
        ),
        None => (String::new(), "<this file, relative to the gateway config>"),
    };
    let text = format!(
        "# Written by `gangway calibrate{floor_arg} --from {} --out {}` ({} windows).\n# Load it \
         with [localizer.pathloss] calibration = \"{load_as}\".\n{}",
        args.from
            .iter()
            .map(|p| p.display().to_string())
            .collect::<Vec<_>>()
            .join(" "),
        args.out.display(),
        windows,
        fitted.calibration.to_toml()
    );
    std::fs::write(&args.out, text)
        .with_context(|| format!("cannot write {}", args.out.display()))?;
    if args.json {
        let report = serde_json::json!({
            "windows": windows,
            "trajectories": trajectories.len(),
            "iterations": args.iterations,
            "seconds": seconds,
            "log_likelihood_per_window": fitted.log_likelihood_per_window,
            "held_out": fitted.held_out,
            "anchors": fitted.changes,
            "cells": fitted.cells,
        });
        println!("{report}");
    } else {
        let kept = fitted.changes.iter().filter(|c| c.kept).count();
        println!(
            "calibrated {} anchors from {windows} windows ({} trajectories) in {seconds:.1} s; \
             kept {kept}; wrote {}",
            fitted.changes.len(),
            trajectories.len(),
            args.out.display()
        );
        if let Some(held_out) = &fitted.held_out {
            println!(
                "checked on {} held-out windows: what was kept makes them likelier by {:.3} nats \
                 a window than the model you started from",
                held_out.windows, held_out.gain_per_window
            );
        }
        println!(
            "anchor    heard  tx dBm   n     σ dB  range m  slope  p_max   Δrssi dB  Δdetect  \
             held-out gain  verdict"
        );
        for c in &fitted.changes {
            let r = &c.after;
            let gain = c
                .held_out_gain
                .map_or_else(|| "—".to_owned(), |g| format!("{g:+.4}"));
            println!(
                "{:<9} {:>5}  {:>6.1}  {:>4.2}  {:>5.1}  {:>7.1}  {:>5.1}  {:>5.2}  {:>+8.1}  {:>+7.3}  {gain:>13}  {}",
                c.id,
                c.heard,
                r.tx_dbm,
                r.exponent,
                r.shadowing_db,
                r.range_m,
                r.range_slope,
                r.max_detection,
                c.rssi_shift_db,
                c.detection_shift,
                c.why.describe()
            );
        }
        if let Some(cells) = &fitted.cells {
            println!(
                "refined the radio map of {} cells, kept {} (the others made held-out windows less \
                 likely, or the map as a whole gained nothing clear): detection moved {:.3} on average, mean RSSI {:.1} dB",
                cells.refined, cells.cells, cells.detection_shift, cells.rssi_shift_db
            );
        }
    }
    Ok(ExitCode::SUCCESS)
}

/// The fingerprint windows of one capture, one trajectory per device, through
/// the config's windows (what the daemon localizes), with the capture's
/// truths as known positions (those whose floor `on_floor` takes).
fn read(
    args: &Args,
    path: &std::path::Path,
    building: &crate::site::Building,
    on_floor: &dyn Fn(Option<&str>) -> bool,
    window: &crate::locate::window::WindowConfig,
) -> anyhow::Result<Vec<Vec<Window>>> {
    let site = &building.floors()[0].site;
    let reader = CaptureReader::open(
        path,
        building,
        &ReadOptions {
            format: args.format,
            skip_bad: false,
            device: None,
            not_heard: args.not_heard,
        },
    )?;
    let mut windows = Windows::new(window.clone(), site);
    let mut by_device: BTreeMap<Arc<str>, Vec<Window>> = BTreeMap::new();
    let mut truths: BTreeMap<String, Vec<(f64, crate::site::Cell)>> = BTreeMap::new();
    let mut push = |f: crate::locate::window::Fingerprint| {
        let rssi = f
            .rssi
            .iter()
            .zip(&f.heard)
            .map(|(&r, &h)| h.then_some(r))
            .collect();
        by_device.entry(f.entity).or_default().push(Window {
            t: f.t,
            rssi,
            cell: None,
        });
    };
    for event in reader {
        match event? {
            Event::Advert(s) => {
                if let Some(f) = windows.push(&s) {
                    push(f);
                }
            }
            Event::Truth(truth) => {
                if on_floor(truth.floor.as_deref()) {
                    truths
                        .entry(truth.device)
                        .or_default()
                        .push((truth.t, truth.cell));
                }
            }
            Event::Request(_) => {}
        }
    }
    windows.flush().into_iter().for_each(&mut push);
    Ok(by_device
        .into_iter()
        .map(|(device, mut trajectory)| {
            trajectory.sort_by(|a, b| a.t.total_cmp(&b.t));
            if let Some(known) = truths.get(&*device) {
                for w in &mut trajectory {
                    w.cell = at(known, w.t, window.length_s);
                }
            }
            trajectory
        })
        .collect())
}

/// The truth within `tolerance_s` of `t`, if any.
fn at(truths: &[(f64, crate::site::Cell)], t: f64, tolerance_s: f64) -> Option<crate::site::Cell> {
    truths
        .iter()
        .filter(|(tt, _)| (tt - t).abs() <= tolerance_s)
        .min_by(|a, b| (a.0 - t).abs().total_cmp(&(b.0 - t).abs()))
        .map(|&(_, cell)| cell)
}
