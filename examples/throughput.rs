//! Replay throughput, with and without a real broker: how many adverts a
//! second `gangway replay --speed 0` gets through on one core, printing to
//! /dev/null and publishing every message at QoS 1 to mosquitto running on
//! the other core.
//!
//! ```sh
//! cargo build --release && cargo run --release --example throughput -- --runs 5
//! ```
//!
//! It simulates `--walkers` phones on the sample site for `--seconds`, each
//! hearing every beacon in every window (`gangway simulate`, seed 3), starts
//! mosquitto (Debian package `mosquitto`) on a free loopback port pinned to
//! CPU 0 and runs the gateway pinned to CPU 1 (`taskset`, util-linux; on a
//! one-CPU machine both share it), `--runs` times each way. It prints one
//! JSON object: adverts and messages, and per way the median wall time, the
//! gateway's median CPU time (user + system, from the kernel's accounting of
//! the finished child) and adverts per second of each. Everything it
//! starts, it stops.

mod support;

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::Instant;

use clap::Parser;
use gangway::config::Config;
use support::{gangway, mosquitto, simulate_busy_walk};

#[derive(Parser)]
struct Args {
    /// Simulated phones.
    #[arg(long, default_value_t = 200)]
    walkers: usize,
    /// Simulated seconds.
    #[arg(long, default_value_t = 300)]
    seconds: u64,
    /// Scans per second of each phone.
    #[arg(long, default_value_t = 2.0)]
    scan_hz: f64,
    /// Runs of each way; the medians are printed.
    #[arg(long, default_value_t = 5)]
    runs: usize,
    /// The gateway config (site, localizer, planner, topics), relative to the repository.
    #[arg(long, default_value = "config/gangway.toml")]
    config: PathBuf,
}

/// Wall and CPU seconds of one run of the gateway.
fn run(cpu: Option<&str>, args: &[&str], stdout_to_null: bool) -> (f64, f64) {
    let mut command = match cpu {
        Some(cpu) => {
            let mut c = Command::new("taskset");
            c.args(["-c", cpu]).arg(gangway());
            c
        }
        None => Command::new(gangway()),
    };
    command
        .current_dir(Path::new(env!("CARGO_MANIFEST_DIR")))
        .args(args)
        .env("RUST_LOG", "warn")
        .stderr(Stdio::inherit());
    if stdout_to_null {
        command.stdout(Stdio::null());
    }
    let before = children_cpu_s();
    let started = Instant::now();
    let status = command.status().expect("the gateway runs");
    let wall = started.elapsed().as_secs_f64();
    assert!(status.success(), "gangway {args:?} failed");
    (wall, children_cpu_s() - before)
}

/// User + system seconds of every finished child so far.
fn children_cpu_s() -> f64 {
    // SAFETY: getrusage only writes the struct it is given.
    let usage = unsafe {
        let mut usage = std::mem::zeroed::<libc::rusage>();
        libc::getrusage(libc::RUSAGE_CHILDREN, &mut usage);
        usage
    };
    let s = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 / 1e6;
    s(usage.ru_utime) + s(usage.ru_stime)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
}

fn main() {
    let args = Args::parse();
    let dir = tempfile::tempdir().unwrap();
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let config_path = root.join(&args.config);
    let config = Config::load(&config_path).unwrap_or_else(|e| panic!("{e}"));
    let log = dir.path().join("busy.jsonl");
    let scan_hz = args.scan_hz.to_string();
    let adverts = simulate_busy_walk(
        dir.path(),
        &config.site,
        args.walkers,
        args.seconds,
        &["--seed", "3", "--scan-hz", &scan_hz],
        &log,
    );
    let two_cpus = std::thread::available_parallelism().is_ok_and(|n| n.get() >= 2);
    let (broker_cpu, gateway_cpu) = if two_cpus {
        (Some("0"), Some("1"))
    } else {
        (None, None)
    };
    let (_broker, port) = mosquitto(dir.path(), "");
    if let Some(cpu) = broker_cpu {
        // The broker is running: move it (and its one thread) to its CPU.
        let pid = _broker.0.id().to_string();
        let pinned = Command::new("taskset").args(["-pc", cpu, &pid]).output();
        assert!(
            pinned.is_ok_and(|o| o.status.success()),
            "taskset -pc {cpu} {pid}"
        );
    }
    let log = log.to_str().unwrap();
    let config = config_path.to_str().unwrap();
    let messages = {
        let out = Command::new(gangway())
            .args(["replay", log, "--speed", "0", "--print", "--config", config])
            .env("RUST_LOG", "warn")
            .output()
            .unwrap();
        out.stdout.iter().filter(|&&b| b == b'\n').count()
    };
    let url = format!("mqtt://127.0.0.1:{port}");
    let ways: [(&str, Vec<&str>, bool); 2] = [
        (
            "print_to_dev_null",
            vec!["replay", log, "--speed", "0", "--print", "--config", config],
            true,
        ),
        (
            "mosquitto_qos1",
            vec![
                "replay",
                log,
                "--speed",
                "0",
                "--mqtt-url",
                &url,
                "--config",
                config,
            ],
            false,
        ),
    ];
    let mut summary = serde_json::json!({
        "adverts": adverts,
        "messages": messages,
        "runs": args.runs,
        "pinned": two_cpus,
    });
    for (name, run_args, to_null) in ways {
        let (mut walls, mut cpus) = (Vec::new(), Vec::new());
        for _ in 0..args.runs.max(1) {
            let (wall, cpu) = run(gateway_cpu, &run_args, to_null);
            walls.push(wall);
            cpus.push(cpu);
        }
        let (wall, cpu) = (median(walls), median(cpus));
        summary[name] = serde_json::json!({
            "wall_s": wall,
            "cpu_s": cpu,
            "adverts_per_s": adverts as f64 / wall,
            "adverts_per_cpu_s": adverts as f64 / cpu,
        });
    }
    println!("{}", serde_json::to_string_pretty(&summary).unwrap());
}
