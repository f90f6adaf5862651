//! Replay end to end: a JSON Lines advert log read, parsed and run through
//! the gateway's runtime (windows, localizer, tracker, typed outputs) and
//! every output encoded as the JSON Lines `--print` writes, to a sink that
//! drops them; reported as adverts per second on one thread. The log is
//! simulated on the sample site (50 walkers for a minute, no route
//! requests) and written to a temp file, so the figure includes file reading
//! and JSON parsing: it is `gangway replay --speed 0 --print > /dev/null`
//! without the process start.
//!
//! `cargo bench --bench replay`

use std::path::PathBuf;
use std::sync::Arc;

use criterion::{BatchSize, Criterion, Throughput, criterion_group, criterion_main};
use gangway::config::Config;
use gangway::daemon::{self, state::Loaded};
use gangway::event::Event;
use gangway::pipeline::Pipeline;
use gangway::plan::PlannerMode;
use gangway::simulate::{SimConfig, simulate};
use gangway::sink::jsonl::JsonLines;
use gangway::site::Site;
use gangway::source::capture::{CaptureReader, CaptureWriter, ReadOptions};
use gangway::source::playback::CaptureSource;
use gangway::topics::Topics;

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
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");

    let mut group = c.benchmark_group("replay");
    group.throughput(Throughput::Elements(adverts as u64));
    group.sample_size(20);
    group.bench_function("jsonl end to end", |b| {
        b.iter_batched(
            || Pipeline::new(&config.pipeline(), site.clone()).expect("pipeline"),
            |pipeline| {
                let reader = CaptureReader::open(
                    &log,
                    pipeline.building(),
                    &ReadOptions {
                        format: None,
                        skip_bad: false,
                        device: None,
                        not_heard: -200,
                    },
                )
                .expect("open");
                let serving = Loaded {
                    config: config.clone(),
                    building: pipeline.building().clone(),
                    site: site.clone(),
                    pipeline,
                    fallbacks: Vec::new(),
                };
                let print = JsonLines::new(
                    Topics::new(config.topic_prefix()),
                    std::io::sink(),
                    "nowhere",
                );
                let options = daemon::Options {
                    until_sources_end: true,
                    ..daemon::Options::default()
                };
                let (_, reloads) = tokio::sync::mpsc::channel(1);
                let stats = runtime
                    .block_on(daemon::run(
                        serving,
                        options,
                        vec![Box::new(CaptureSource::new(log.clone(), reader, 0.0))],
                        vec![Box::new(print)],
                        std::future::pending(),
                        reloads,
                    ))
                    .expect("replay")
                    .stats;
                assert_eq!(stats.sightings, adverts as u64);
                stats.fixes
            },
            BatchSize::PerIteration,
        )
    });
    group.finish();
}

criterion_group!(replay, benches);
criterion_main!(replay);
