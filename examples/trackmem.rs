//! Memory of tracking at building scale (issue #28): many phones on one
//! large floor, the whole gateway replaying their walk as fast as it can.
//!
//! ```sh
//! cargo build --release && cargo run --release --example trackmem -- --devices 1000 --seconds 60
//! ```
//!
//! It writes a `--width` × `--height` m floor at 1 m cells (240 × 180 by
//! default: 43,200 cells, shelves a 2 m deep block every 10 m), a beacon
//! every `--beacon-every` metres (14: 204 beacons) and eight places, and a
//! gateway config for it (the survey-free `pathloss` localizer with its
//! default radio model but a 12 m range, so that phones between beacons
//! hear some; the `hmm` tracker; routes by `astar`); simulates
//! `--devices` walkers there for `--seconds` (`gangway simulate`, the
//! phones hearing the beacons as that radio model says, once a second);
//! then replays the log through the gateway as fast as it goes (`gangway
//! replay`) under `/usr/bin/time -v`. It prints one JSON object: the site's
//! open cells, the adverts, and the replay's wall time, CPU seconds, peak
//! RSS and its RSS last sampled (every 100 ms) before it exited: the
//! steady state with every device tracked, where the tracks' beliefs show
//! (the peak can be the localizer's start-up rehearsal), and every 30 s.
//! `--gangway PATH` replays with another build of the gateway (the same
//! log: the simulation is seeded). `--keep DIR` writes the site, config and log there and
//! keeps them. Everything it starts, it stops.

mod support;

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::process::Command;

use std::time::Duration;

use clap::Parser;
use support::{gangway, usage};

#[derive(Parser)]
struct Args {
    /// Simulated devices (walkers whose phones scan at 1 Hz).
    #[arg(long, default_value_t = 1000)]
    devices: usize,
    /// Seconds of simulated walking.
    #[arg(long, default_value_t = 60)]
    seconds: u64,
    /// The floor's width, metres (1 m cells).
    #[arg(long, default_value_t = 240)]
    width: u32,
    /// The floor's height, metres.
    #[arg(long, default_value_t = 180)]
    height: u32,
    /// Metres between beacons, along both axes.
    #[arg(long, default_value_t = 14)]
    beacon_every: u32,
    /// Write the site, config and log here (and keep them).
    #[arg(long)]
    keep: Option<PathBuf>,
    /// Replay with this gateway binary instead of the one built here (to
    /// compare builds on the same log).
    #[arg(long)]
    gangway: Option<PathBuf>,
}

const UUID: &str = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84";

/// The floor: shelves (2 m deep, 12 m long, a gap every 20 m, every 10 m),
/// beacons on a square grid, a place at each corner and mid-side.
fn site(args: &Args) -> String {
    let (w, h) = (args.width, args.height);
    let mut text =
        format!("name = \"trackmem\"\ncell_m = 1.0\nwidth_m = {w}.0\nheight_m = {h}.0\n");
    for y in (5..h.saturating_sub(5)).step_by(10) {
        for x in (4..w.saturating_sub(14)).step_by(20) {
            let (x1, y1) = (x + 12, y + 2);
            let _ = write!(
                text,
                "\n[[obstacles]]\npolygon = [[{x}, {y}], [{x1}, {y}], [{x1}, {y1}], [{x}, {y1}]]\n"
            );
        }
    }
    let every = args.beacon_every.max(1);
    let mut minor = 0;
    for y in (every / 2..h).step_by(every as usize) {
        for x in (every / 2..w).step_by(every as usize) {
            minor += 1;
            let _ = write!(
                text,
                "\n[[beacon]]\nid = \"b{minor}\"\nuuid = \"{UUID}\"\nmajor = 1\nminor = {minor}\npos = [{}.5, {}.5]\n",
                x, y
            );
        }
    }
    text.push_str("\n[places]\n");
    let (sx, sy) = (w - 2, h - 2);
    let places = [
        (1, 1),
        (sx, 1),
        (1, sy),
        (sx, sy),
        (w / 2, 1),
        (w / 2, sy),
        (1, h / 2),
        (sx, h / 2),
    ];
    for (i, (x, y)) in places.into_iter().enumerate() {
        let _ = writeln!(text, "\"place {i}\" = [{x}, {y}]");
    }
    text
}

fn config(site: &Path) -> String {
    format!(
        "gateway_id = \"trackmem\"\nsite = \"{}\"\n\
         [localizer]\nmethod = \"pathloss\"\n\
         [localizer.pathloss]\nrange_m = 12.0\n\
         [tracker]\nkind = \"hmm\"\n\
         [planner]\nmode = \"astar\"\n",
        site.display()
    )
}

/// `/usr/bin/time -v`'s value for `key` (the text after "key: ").
fn time_field<'a>(report: &'a str, key: &str) -> Option<&'a str> {
    report
        .lines()
        .find_map(|l| l.trim().strip_prefix(key)?.strip_prefix(": "))
}

fn main() {
    let args = Args::parse();
    let tmp = tempfile::tempdir().unwrap();
    let dir = args.keep.clone().unwrap_or_else(|| tmp.path().to_owned());
    std::fs::create_dir_all(&dir).unwrap();
    let site_path = dir.join("site.toml");
    std::fs::write(&site_path, site(&args)).unwrap();
    let config_path = dir.join("gangway.toml");
    std::fs::write(&config_path, config(&site_path)).unwrap();
    let log = dir.join("walk.jsonl");

    let status = Command::new(gangway())
        .args(["simulate", "--requests", "0", "--site"])
        .arg(&site_path)
        .arg("--config")
        .arg(&config_path)
        .args(["--walkers", &args.devices.to_string()])
        .args(["--duration", &args.seconds.to_string()])
        .arg("--out")
        .arg(&log)
        .env("RUST_LOG", "warn")
        .status()
        .unwrap();
    assert!(status.success(), "gangway simulate failed");
    let adverts = std::fs::read_to_string(&log)
        .unwrap()
        .matches("\"advert\"")
        .count();

    // The replay under `/usr/bin/time -v` (its peak RSS), and its RSS
    // sampled meanwhile: the last sample is the tracks' steady state, past
    // the start-up's peak (the localizer's rehearsal).
    let time_report = dir.join("time.txt");
    let mut timed = Command::new("/usr/bin/time")
        .arg("-v")
        .arg("-o")
        .arg(&time_report)
        .arg(args.gangway.clone().unwrap_or_else(gangway))
        .args(["replay", "--config"])
        .arg(&config_path)
        .arg(&log)
        .env("RUST_LOG", "warn")
        .spawn()
        .unwrap();
    let children = format!("/proc/{0}/task/{0}/children", timed.id());
    let mut replay_pid = None;
    let mut last_rss_kib = 0;
    let mut every_30s = Vec::new();
    let mut samples = 0u64;
    let status = loop {
        if let Some(status) = timed.try_wait().unwrap() {
            break status;
        }
        if replay_pid.is_none() {
            replay_pid = std::fs::read_to_string(&children)
                .ok()
                .and_then(|c| c.split_whitespace().next()?.parse::<u32>().ok());
        }
        if let Some(pid) = replay_pid {
            let (_, rss, _) = usage(pid);
            if rss > 0 {
                last_rss_kib = rss;
                if samples.is_multiple_of(300) {
                    every_30s.push((rss as f64 / 1024.0).round());
                }
                samples += 1;
            }
        }
        std::thread::sleep(Duration::from_millis(100));
    };
    let report = std::fs::read_to_string(&time_report).unwrap_or_default();
    assert!(status.success(), "gangway replay failed:\n{report}");
    let number = |key: &str| -> f64 {
        time_field(&report, key)
            .and_then(|v| v.parse().ok())
            .unwrap_or(f64::NAN)
    };
    let open_cells = gangway::site::Site::load(&site_path)
        .map(|s| s.open_cells().len())
        .ok();
    let summary = serde_json::json!({
        "devices": args.devices,
        "seconds": args.seconds,
        "open_cells": open_cells,
        "adverts": adverts,
        "replay_wall": time_field(&report, "Elapsed (wall clock) time (h:mm:ss or m:ss)"),
        "replay_cpu_s": number("User time (seconds)") + number("System time (seconds)"),
        "replay_peak_rss_mib": number("Maximum resident set size (kbytes)") / 1024.0,
        "replay_last_sampled_rss_mib": last_rss_kib as f64 / 1024.0,
        "replay_rss_mib_every_30s": every_30s,
    });
    println!("{}", serde_json::to_string_pretty(&summary).unwrap());
}
