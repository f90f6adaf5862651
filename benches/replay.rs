//! Replay end to end: a JSON Lines advert log read, parsed and run through
//! the whole pipeline (windows, localizer, tracker, messages), reported as
//! adverts per second on one thread. The log is simulated on the sample site
//! (50 walkers for a minute, no route requests) and written to a temp file,
//! so the figure includes file reading and JSON parsing like
//! `gangway replay --speed 0`.
//!
//! `cargo bench --bench replay`

use std::path::PathBuf;
use std::sync::Arc;

use criterion::{BatchSize, Criterion, Throughput, criterion_group, criterion_main};
use gangway::config::Config;
use gangway::pipeline::Pipeline;
use gangway::plan::PlannerMode;
use gangway::site::Site;
use gangway::source::Event;
use gangway::source::capture::{CaptureReader, CaptureWriter, ReadOptions};
use gangway::source::simulate::{SimConfig, simulate};

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn benches(c: &mut Criterion) {
    let mut config = Config::load(&root().join("config/gangway.toml")).expect("config");
    // No route requests in the log, so no planner models to load.
    config.planner.mode = PlannerMode::Astar;
    let site = Arc::new(Site::load(&config.site).expect("site"));
    let events = simulate(
        &site,
        &SimConfig {
            walkers: 50,
            duration_s: 60.0,
            requests_per_walker: 0,
            ..SimConfig::default()
        },
        None,
    );
    let adverts = events
        .iter()
        .filter(|e| matches!(e, Event::Advert(_)))
        .count();
    let dir = tempfile::tempdir().expect("temp dir");
    let log = dir.path().join("walk.jsonl");
    let mut writer = CaptureWriter::create(&log, None).expect("log");
    for event in &events {
        writer.write(event).expect("write");
    }
    writer.flush().expect("flush");

    let mut group = c.benchmark_group("replay");
    group.throughput(Throughput::Elements(adverts as u64));
    group.sample_size(20);
    group.bench_function("jsonl end to end", |b| {
        b.iter_batched(
            || Pipeline::new(&config, site.clone()).expect("pipeline"),
            |mut pipeline| {
                let reader = CaptureReader::open(
                    &log,
                    &site,
                    &ReadOptions {
                        format: None,
                        skip_bad: false,
                        device: None,
                        not_heard: -200,
                    },
                )
                .expect("open");
                let mut out = Vec::new();
                for event in reader {
                    pipeline.handle(&event.expect("event"), &mut out);
                    out.clear();
                }
                pipeline.finish(&mut out);
                out.len()
            },
            BatchSize::PerIteration,
        )
    });
    group.finish();
}

criterion_group!(replay, benches);
criterion_main!(replay);
