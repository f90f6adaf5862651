//! Training speed of the paper's GAN with the project's trainer: 50 iterations
//! at batch 32 on the fixture walks, reported per iteration (throughput), on
//! 1 and on 2 threads (`GanConfig::threads`).
//! `gangway train --json` reports the wall time of a whole run.
//!
//! `cargo bench --bench train_step`

use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use gangway::site::Site;
use gangway::train::gan::{self, GanConfig, GanData, Hidden};
use gangway::train::paths::PathSet;
use gangway::train::trajectory;

const ITERATIONS: usize = 50;

fn benches(c: &mut Criterion) {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let site = Site::load(&root.join("config/sites/waldo.toml")).expect("site");
    let walks =
        trajectory::read(&root.join("fixtures/trajectories/waldo.jsonl"), &site).expect("walks");
    let set = PathSet::from_trajectories(&site, &walks, 10);
    let data = GanData {
        frames: set.frames.mapv(|v| 2.0 * v - 1.0),
        conditions: None,
    };
    let mut group = c.benchmark_group("gan");
    group.sample_size(10);
    group.throughput(Throughput::Elements(ITERATIONS as u64));
    for threads in [1, 2] {
        group.bench_function(format!("iteration batch 32, {threads} threads"), |b| {
            b.iter(|| {
                gan::train(
                    &data,
                    GanConfig {
                        iterations: ITERATIONS,
                        batch: 32,
                        seed: 1,
                        threads,
                        hidden: Hidden::PAPER,
                    },
                    |_, _| {},
                )
            })
        });
    }
    group.finish();
}

criterion_group!(train_step, benches);
criterion_main!(train_step);
