//! Load test of the live map: many devices on a large site, each located
//! every second, the gateway playing their walk in real time with the web UI
//! on and a headless chromium watching the map, against the same run with
//! the web UI off.
//!
//! ```sh
//! cargo build --release && cargo run --release --example webload -- --devices 1000 --side 100 --seconds 40 --runs 3
//! ```
//!
//! It writes a site of `--side` × `--side` cells of 1 m (10,000 cells by
//! default: an open floor with shelves, a beacon every `--beacon-every`
//! metres, eight places) and a log of `--devices` phones walking it, each
//! scanning once a second and hearing every beacon within 1.2 beacon
//! spacings (path loss of the gateway's default radio model: -59 dBm at 1 m,
//! exponent 2.2, 5 dB shadowing), so every phone hears several beacons in
//! every scan. The gateway replays it with `gangway run --replay … --speed 1`,
//! `[window] length_s = stride_s = 1` (one fix per device per second, each
//! from one scan) and the cheapest localizer (`strongest`, no tracker: what
//! is measured is the map, not the localizer), alternately with `[web]
//! enabled = false` and with the UI on and Debian's chromium showing the
//! map, `--runs` times each. It prints one JSON object: per run and as
//! medians, the gateway's CPU share of one core and RSS (and their
//! differences: what serving the map costs), and the page's own figures
//! (Performance API, the page's "This page" panel, reset after the warm-up):
//! fixes and dot moves a second, frame work p50 and p99 (script, style,
//! layout and paint of a frame that drew fixes), frame interval, and the time
//! from the gateway's web sink taking a fix to its dot being drawn, p50 and
//! p99.
//!
//! `--page URL` watches another page instead of the gateway's own, with
//! `{port}` in the URL replaced by the gateway's web port, and runs only
//! with the UI on: how the map-library comparison in docs/web.md was
//! measured (`examples/webload-leaflet.html`, a page from the file system,
//! gets a browser that lets it read the gateway cross-origin). Loopback
//! only; everything it starts, it stops.

mod support;
#[path = "../tests/it/web_support/mod.rs"]
#[allow(dead_code)] // the load uses the browser, not the test helpers
mod web_support;

use std::fmt::Write as _;
use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use clap::Parser;
use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal};
use support::{Guard, free_port, gangway, usage};

#[derive(Parser)]
struct Args {
    /// Simulated devices.
    #[arg(long, default_value_t = 1000)]
    devices: usize,
    /// Cells along each side of the square site.
    #[arg(long, default_value_t = 100)]
    side: u32,
    /// Metres between beacons, along both axes.
    #[arg(long, default_value_t = 5)]
    beacon_every: u32,
    /// Measured span of each run, after a 10 s warm-up.
    #[arg(long, default_value_t = 40)]
    seconds: u64,
    /// Runs with the UI off and on (alternating), for medians.
    #[arg(long, default_value_t = 3)]
    runs: usize,
    /// Watch this page instead of the gateway's map (`{port}`: the web port).
    #[arg(long)]
    page: Option<String>,
}

/// Warm-up before each measured span: the page loads, the first snapshot.
const WARM_UP: Duration = Duration::from_secs(10);
const UUID: &str = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84";

/// Shelves: a 2 m deep block every 10 m, 12 m long, a gap every 20 m.
fn shelves(side: u32) -> Vec<[f64; 4]> {
    let mut out = Vec::new();
    for y in (5..side.saturating_sub(5)).step_by(10) {
        for x in (4..side.saturating_sub(14)).step_by(20) {
            out.push([x as f64, y as f64, x as f64 + 12.0, y as f64 + 2.0]);
        }
    }
    out
}

/// Beacon positions (metres), minor = index + 1.
fn beacons(args: &Args) -> Vec<[f64; 2]> {
    let every = args.beacon_every.max(1);
    let mut out = Vec::new();
    for y in (every / 2..args.side).step_by(every as usize) {
        for x in (every / 2..args.side).step_by(every as usize) {
            out.push([x as f64 + 0.5, y as f64 + 0.5]);
        }
    }
    out
}

fn site(args: &Args) -> String {
    let side = args.side;
    let mut text =
        format!("name = \"webload\"\ncell_m = 1.0\nwidth_m = {side}.0\nheight_m = {side}.0\n");
    for [x0, y0, x1, y1] in shelves(side) {
        let _ = write!(
            text,
            "\n[[obstacles]]\npolygon = [[{x0}, {y0}], [{x1}, {y0}], [{x1}, {y1}], [{x0}, {y1}]]\n"
        );
    }
    for (i, [x, y]) in beacons(args).into_iter().enumerate() {
        let _ = write!(
            text,
            "\n[[beacon]]\nid = \"b{}\"\nuuid = \"{UUID}\"\nmajor = 1\nminor = {}\npos = [{x}, {y}]\n",
            i + 1,
            i + 1
        );
    }
    text.push_str("\n[places]\n");
    let s = side - 2;
    for (i, (x, y)) in [
        (1, 1),
        (s, 1),
        (1, s),
        (s, s),
        (side / 2, 1),
        (side / 2, s),
        (1, side / 2),
        (s, side / 2),
    ]
    .into_iter()
    .enumerate()
    {
        let _ = writeln!(text, "\"place {i}\" = [{x}, {y}]");
    }
    text
}

/// The phones' log: every device scans once a second (each at its own
/// phase) while walking straight lines at 0.8–1.6 m/s, turning at walls
/// and shelves, and hears every beacon within 1.2 spacings (at least the four around
/// it).
fn walk_log(args: &Args, seconds: u64) -> String {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(1);
    let side = f64::from(args.side);
    let shelves = shelves(args.side);
    let beacons = beacons(args);
    let hears_within = 1.2 * f64::from(args.beacon_every.max(1));
    let shadowing = Normal::new(0.0, 5.0).expect("a valid spread");
    let open = |[x, y]: [f64; 2]| {
        (0.5..side - 0.5).contains(&x)
            && (0.5..side - 0.5).contains(&y)
            && !shelves
                .iter()
                .any(|s| x >= s[0] - 0.3 && x <= s[2] + 0.3 && y >= s[1] - 0.3 && y <= s[3] + 0.3)
    };
    struct Walker {
        id: usize,
        at: [f64; 2],
        heading: f64,
        speed: f64,
        phase: f64,
    }
    let mut walkers: Vec<Walker> = (0..args.devices)
        .map(|id| {
            let at = loop {
                let p = [
                    rng.random_range(0.5..side - 0.5),
                    rng.random_range(0.5..side - 0.5),
                ];
                if open(p) {
                    break p;
                }
            };
            Walker {
                id: id + 1,
                at,
                heading: rng.random_range(0.0..std::f64::consts::TAU),
                speed: rng.random_range(0.8..1.6),
                phase: rng.random_range(0.0..1.0),
            }
        })
        .collect();
    let t0 = 1_767_225_600.0;
    // Each second's scans in time order, as a radio hears them: playback
    // waits for each.
    walkers.sort_by(|a, b| a.phase.total_cmp(&b.phase));
    let mut log = String::new();
    for second in 0..seconds {
        for w in walkers.iter_mut() {
            for _ in 0..8 {
                let next = [
                    w.at[0] + w.heading.cos() * w.speed,
                    w.at[1] + w.heading.sin() * w.speed,
                ];
                if open(next) {
                    w.at = next;
                    break;
                }
                w.heading = rng.random_range(0.0..std::f64::consts::TAU);
            }
            let t = t0 + second as f64 + w.phase;
            for (b, at) in beacons.iter().enumerate() {
                let d = ((at[0] - w.at[0]).powi(2) + (at[1] - w.at[1]).powi(2)).sqrt();
                if d > hears_within {
                    continue;
                }
                let rssi = -59.0 - 22.0 * d.max(0.5).log10() + shadowing.sample(&mut rng);
                let _ = writeln!(
                    log,
                    "{{\"type\":\"advert\",\"t\":{t:.3},\"observer\":\"phone-{:04}\",\"uuid\":\"{UUID}\",\
                     \"major\":1,\"minor\":{},\"rssi\":{},\"tx_power\":-59}}",
                    w.id,
                    b + 1,
                    rssi.round().max(-100.0)
                );
            }
        }
    }
    log
}

/// One run of the gateway: its CPU share of a core and RSS (MiB), and the
/// page's figures when the UI is on.
async fn run(
    dir: &Path,
    log: &Path,
    args: &Args,
    browser: Option<&web_support::Browser>,
) -> (f64, f64, Option<serde_json::Value>) {
    let web = browser.is_some();
    let web_port = free_port();
    let config = dir.join(if web { "web.toml" } else { "plain.toml" });
    std::fs::write(
        &config,
        format!(
            "gateway_id = \"gw-load\"\nsite = \"site.toml\"\n[window]\nlength_s = 1.0\nstride_s = 1.0\n\
             [localizer]\nmethod = \"strongest\"\nmin_confidence = 0.0\n[tracker]\nkind = \"none\"\n\
             [planner]\nmode = \"astar\"\n\
             [limits]\nscans_per_s = 100000\n[mqtt]\nembedded_port = {}\n\
             [web]\nenabled = {web}\nbind = \"127.0.0.1:{web_port}\"\n",
            free_port()
        ),
    )
    .unwrap();
    let gateway = Guard(
        Command::new(gangway())
            .args(["run", "--config"])
            .arg(&config)
            .args(["--speed", "1", "--replay"])
            .arg(log)
            .env("RUST_LOG", "error")
            .stdout(Stdio::null())
            .spawn()
            .unwrap(),
    );
    let pid = gateway.0.id();
    if let Some(b) = browser {
        let url = format!("http://127.0.0.1:{web_port}");
        let deadline = Instant::now() + Duration::from_secs(30);
        while ureq::get(&format!("{url}/healthz")).call().is_err() {
            assert!(Instant::now() < deadline, "the web UI did not start");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let page = match &args.page {
            Some(page) => page.replace("{port}", &web_port.to_string()),
            None => format!("{url}/"),
        };
        b.client.goto(&page).await.unwrap();
    }
    tokio::time::sleep(WARM_UP).await;
    if let Some(b) = browser {
        b.click_id("page-reset").await;
    }
    let (cpu_before, _, _) = usage(pid);
    let started = Instant::now();
    tokio::time::sleep(Duration::from_secs(args.seconds)).await;
    let (cpu_after, rss_kib, _) = usage(pid);
    let share = (cpu_after - cpu_before) / started.elapsed().as_secs_f64();
    let page = match browser {
        Some(b) => {
            let shot = if args.page.is_some() {
                "webload-page.png"
            } else {
                "webload.png"
            };
            b.screenshot(shot).await;
            let figures = b
                .js("const d = document.getElementById('page-stats').dataset;
                     return { frame_work_ms_p50: +d.frameP50, frame_work_ms_p99: +d.frameP99,
                              frame_interval_ms_p50: +d.intervalP50,
                              fix_to_screen_ms_p50: +d.latencyP50, fix_to_screen_ms_p99: +d.latencyP99,
                              fixes_per_s: +d.fixesPerS, dots_moved_per_s: +d.movedPerS,
                              frames: +d.frames, devices_drawn: +d.devices }")
                .await;
            // Leave the map before the gateway goes, so the page does not
            // spend the next run's first seconds reconnecting.
            b.client.goto("about:blank").await.unwrap();
            Some(figures)
        }
        None => None,
    };
    drop(gateway);
    (share, rss_kib as f64 / 1024.0, page)
}

fn median(mut values: Vec<f64>) -> f64 {
    values.sort_by(f64::total_cmp);
    match values.len() {
        0 => f64::NAN,
        n if n % 2 == 1 => values[n / 2],
        n => (values[n / 2 - 1] + values[n / 2]) / 2.0,
    }
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args = Args::parse();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("site.toml"), site(&args)).unwrap();
    let log = dir.path().join("walk.jsonl");
    std::fs::write(&log, walk_log(&args, args.seconds + 30)).unwrap();
    let shots = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/web-screenshots");
    // A page from the file system (the Leaflet comparison) reads the
    // gateway's stream cross-origin, which the gateway grants no page.
    let extra: &[&str] = match &args.page {
        Some(page) if page.starts_with("file://") => {
            &["--disable-web-security", "--allow-file-access-from-files"]
        }
        _ => &[],
    };
    let browser = web_support::Browser::start_with(&shots, extra)
        .await
        .unwrap_or_else(|missing| panic!("{missing}"));
    let mut off = Vec::new();
    let mut on = Vec::new();
    for _ in 0..args.runs.max(1) {
        if args.page.is_none() {
            off.push(run(dir.path(), &log, &args, None).await);
        }
        on.push(run(dir.path(), &log, &args, Some(&browser)).await);
    }
    browser.client.close().await.unwrap();
    let cpu =
        |runs: &[(f64, f64, Option<serde_json::Value>)]| median(runs.iter().map(|r| r.0).collect());
    let rss =
        |runs: &[(f64, f64, Option<serde_json::Value>)]| median(runs.iter().map(|r| r.1).collect());
    let pages: Vec<&serde_json::Value> = on.iter().filter_map(|r| r.2.as_ref()).collect();
    let page_median = |key: &str| median(pages.iter().filter_map(|p| p[key].as_f64()).collect());
    let keys = [
        "fixes_per_s",
        "dots_moved_per_s",
        "frame_work_ms_p50",
        "frame_work_ms_p99",
        "frame_interval_ms_p50",
        "fix_to_screen_ms_p50",
        "fix_to_screen_ms_p99",
        "devices_drawn",
    ];
    let page: serde_json::Map<String, serde_json::Value> = keys
        .iter()
        .map(|&k| (k.to_owned(), page_median(k).into()))
        .collect();
    let summary = serde_json::json!({
        "devices": args.devices,
        "cells": args.side * args.side,
        "beacons": beacons(&args).len(),
        "seconds": args.seconds,
        "runs": args.runs,
        "page_url": args.page,
        "gateway_cpu_share_web_off": cpu(&off),
        "gateway_cpu_share_web_on": cpu(&on),
        "web_extra_cpu_share_of_one_core": cpu(&on) - cpu(&off),
        "gateway_rss_mib_web_off": rss(&off),
        "gateway_rss_mib_web_on": rss(&on),
        "web_extra_rss_mib": rss(&on) - rss(&off),
        "page_median": page,
        "per_run": {
            "off": off.iter().map(|r| serde_json::json!({"cpu_share": r.0, "rss_mib": r.1})).collect::<Vec<_>>(),
            "on": on.iter().map(|r| serde_json::json!({"cpu_share": r.0, "rss_mib": r.1, "page": r.2})).collect::<Vec<_>>(),
        },
    });
    println!("{}", serde_json::to_string_pretty(&summary).unwrap());
}
