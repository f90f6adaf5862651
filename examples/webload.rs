//! Load test of the live map: many devices on a large site, the gateway
//! playing their walk in real time with the web UI on and a headless
//! chromium watching the map, against the same run with the web UI off.
//!
//! ```sh
//! cargo build --release && cargo run --release --example webload -- --devices 1000 --side 100 --seconds 40
//! ```
//!
//! It writes a site of `--side` × `--side` cells of 1 m (10,000 cells by
//! default: an open floor with shelves, beacons every 10 m, eight places),
//! simulates `--devices` walkers whose phones scan at 1 Hz, and runs
//! `gangway run --replay … --speed 1` twice with `[window] stride_s = 1` (a
//! fix per device per second) and the cheapest localizer (`strongest`, no
//! tracker: what is measured is the map, not the localizer): once with
//! `[web] enabled = false`, once with
//! the UI on and Debian's chromium showing the map. It prints one JSON
//! object: the gateway's CPU share of one core and RSS in both runs and
//! their difference (what serving the map costs), and the page's own
//! figures (Performance API, in the page's status panel): frame work p50 and
//! p99 (script, style, layout and paint of a frame that drew fixes), frame
//! interval, and the time from the gateway sending a fix to its dot being
//! drawn, p50 and p99. Loopback only; everything it starts, it stops.

mod support;
#[path = "../tests/web_support/mod.rs"]
mod web_support;

use std::path::Path;
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use clap::Parser;
use support::{Guard, free_port, gangway, usage};

#[derive(Parser)]
struct Args {
    /// Simulated devices.
    #[arg(long, default_value_t = 1000)]
    devices: usize,
    /// Cells along each side of the square site.
    #[arg(long, default_value_t = 100)]
    side: u32,
    /// Measured span of each run, after a 10 s warm-up.
    #[arg(long, default_value_t = 40)]
    seconds: u64,
}

fn site(side: u32) -> String {
    let mut text =
        format!("name = \"webload\"\ncell_m = 1.0\nwidth_m = {side}.0\nheight_m = {side}.0\n");
    // Shelves: a 2 m deep block every 10 m, with a gap every 20 m.
    for y in (5..side.saturating_sub(5)).step_by(10) {
        for x in (4..side.saturating_sub(14)).step_by(20) {
            text.push_str(&format!(
                "\n[[obstacles]]\npolygon = [[{x}.0, {y}.0], [{}.0, {y}.0], [{}.0, {}.0], [{x}.0, {}.0]]\n",
                x + 12,
                x + 12,
                y + 2,
                y + 2
            ));
        }
    }
    let mut minor = 0;
    for y in (5..side).step_by(10) {
        for x in (5..side).step_by(10) {
            minor += 1;
            text.push_str(&format!(
                "\n[[beacon]]\nid = \"b{minor}\"\nuuid = \"5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84\"\n\
                 major = 1\nminor = {minor}\npos = [{x}.5, {y}.5]\n"
            ));
        }
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
        text.push_str(&format!("\"place {i}\" = [{x}, {y}]\n"));
    }
    text
}

/// One run of the gateway; returns (CPU share of a core, RSS MiB, page figures).
async fn run(
    dir: &Path,
    log: &Path,
    args: &Args,
    web: bool,
) -> (f64, f64, Option<serde_json::Value>) {
    let web_port = free_port();
    let config = dir.join(if web { "web.toml" } else { "plain.toml" });
    std::fs::write(
        &config,
        format!(
            "gateway_id = \"gw-load\"\nsite = \"site.toml\"\n[window]\nstride_s = 1.0\n\
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
    let browser = if web {
        let url = format!("http://127.0.0.1:{web_port}");
        let deadline = Instant::now() + Duration::from_secs(30);
        while ureq::get(&format!("{url}/healthz")).call().is_err() {
            assert!(Instant::now() < deadline, "the web UI did not start");
            tokio::time::sleep(Duration::from_millis(100)).await;
        }
        let shots = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/web-screenshots");
        let browser = web_support::Browser::start(&shots)
            .await
            .expect("chromium and chromedriver (Debian: apt install chromium chromium-driver)");
        browser.client.goto(&format!("{url}/")).await.unwrap();
        Some(browser)
    } else {
        None
    };
    tokio::time::sleep(Duration::from_secs(10)).await;
    let (cpu_before, _, _) = usage(pid);
    let started = Instant::now();
    tokio::time::sleep(Duration::from_secs(args.seconds)).await;
    let (cpu_after, rss_kib, _) = usage(pid);
    let share = (cpu_after - cpu_before) / started.elapsed().as_secs_f64();
    let page = match &browser {
        Some(b) => {
            b.screenshot("webload.png").await;
            let figures = b
                .js("const d = document.getElementById('page-stats').dataset;
                     return { frame_work_ms_p50: +d.frameP50, frame_work_ms_p99: +d.frameP99,
                              frame_interval_ms_p50: +d.intervalP50,
                              fix_to_screen_ms_p50: +d.latencyP50, fix_to_screen_ms_p99: +d.latencyP99,
                              fixes_per_s: +document.getElementById('page-stats').children[3].textContent,
                              devices_drawn: document.querySelectorAll('.layer-devices .device').length }")
                .await;
            Some(figures)
        }
        None => None,
    };
    if let Some(b) = browser {
        b.client.close().await.unwrap();
    }
    drop(gateway);
    (share, rss_kib as f64 / 1024.0, page)
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args = Args::parse();
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("site.toml"), site(args.side)).unwrap();
    let log = dir.path().join("walk.jsonl");
    let total = 2 * (args.seconds + 20);
    let status = Command::new(gangway())
        .args(["simulate", "--requests", "0", "--dropout", "0", "--site"])
        .arg(dir.path().join("site.toml"))
        .args([
            "--walkers",
            &args.devices.to_string(),
            "--duration",
            &total.to_string(),
            "--seed",
            "1",
            "--out",
        ])
        .arg(&log)
        .env("RUST_LOG", "warn")
        .status()
        .unwrap();
    assert!(status.success());
    let (plain_cpu, plain_rss, _) = run(dir.path(), &log, &args, false).await;
    let (web_cpu, web_rss, page) = run(dir.path(), &log, &args, true).await;
    let summary = serde_json::json!({
        "devices": args.devices,
        "cells": args.side * args.side,
        "seconds": args.seconds,
        "gateway_cpu_share_web_off": plain_cpu,
        "gateway_cpu_share_web_on": web_cpu,
        "web_extra_cpu_share_of_one_core": web_cpu - plain_cpu,
        "gateway_rss_mib_web_off": plain_rss,
        "gateway_rss_mib_web_on": web_rss,
        "web_extra_rss_mib": web_rss - plain_rss,
        "page": page,
    });
    println!("{}", serde_json::to_string_pretty(&summary).unwrap());
}
