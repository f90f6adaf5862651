//! Inference through tract with the shipped models (`models/`), single-threaded
//! (tract's default): one generated path (batch 1, and batch 32 reported per
//! path), the conditional generator at batch 1 and 2 (the daemon's default of
//! 2 samples), one path classification, one cell classification.
//!
//! `cargo bench --bench path_models`

use std::path::PathBuf;

use criterion::{Criterion, Throughput, criterion_group, criterion_main};
use gangway::model::condition;
use gangway::model::runtime::{CellClassifier, PathClassifier, PathGenerator, Rows};
use gangway::site::Site;
use gangway::train::trajectory;
use ndarray::Array2;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Fixed noise in [−1, 1] for `batch` rows.
fn noise(batch: usize, dim: usize) -> Array2<f32> {
    Array2::from_shape_fn((batch, dim), |(i, j)| {
        ((i * 31 + j * 17) % 13) as f32 / 6.0 - 1.0
    })
}

fn benches(c: &mut Criterion) {
    let site = Site::load(&root().join("config/sites/waldo.toml")).expect("site");
    let generator = PathGenerator::load(
        &root().join("models/generator.onnx"),
        &site,
        Rows::AlsoSingle,
    )
    .expect("generator");
    let classifier = PathClassifier::load(&root().join("models/path_classifier.onnx"), &site)
        .expect("classifier");
    let walks =
        trajectory::read(&root().join("fixtures/trajectories/waldo.jsonl"), &site).expect("walks");
    let cells = usize::from(site.width()) * usize::from(site.height());

    let mut group = c.benchmark_group("generate");
    for batch in [1usize, 32] {
        let noise = noise(batch, generator.noise_dim());
        group.throughput(Throughput::Elements(batch as u64));
        group.bench_function(format!("batch {batch}"), |b| {
            b.iter(|| generator.generate(noise.view(), None).expect("runs"))
        });
    }
    group.finish();

    // The daemon's default planner: the conditional generator, 2 samples.
    let conditional = PathGenerator::load(
        &root().join("models/conditional_generator.onnx"),
        &site,
        Rows::AlsoSingle,
    )
    .expect("conditional generator");
    let mut group = c.benchmark_group("generate conditional");
    for batch in [1usize, 2] {
        let noise = noise(batch, conditional.noise_dim());
        let mut conditions = Array2::zeros((batch, condition::len(site.width(), site.height())));
        for mut row in conditions.rows_mut() {
            condition::encode(
                site.width(),
                site.height(),
                walks[0].source(),
                walks[0].destination(),
                row.as_slice_mut().expect("contiguous"),
            );
        }
        group.throughput(Throughput::Elements(batch as u64));
        group.bench_function(format!("batch {batch}"), |b| {
            b.iter(|| {
                conditional
                    .generate(noise.view(), Some(conditions.view()))
                    .expect("runs")
            })
        });
    }
    group.finish();

    let mut frame = Array2::zeros((1, cells));
    walks[0]
        .frame(&site)
        .write_values(1.0, 0.0, frame.as_slice_mut().expect("contiguous"));
    c.bench_function("classify path/batch 1", |b| {
        b.iter(|| classifier.classify(frame.view()).expect("runs"))
    });

    // The cell classifier is trained from the survey; benchmark it when present.
    let cell_model = root().join("models/cell_classifier.onnx");
    if cell_model.exists() {
        let model = CellClassifier::load(&cell_model, &site).expect("cell classifier");
        let rssi: Vec<f32> = (0..site.beacons.len())
            .map(|i| if i % 3 == 0 { -70.0 } else { -105.0 })
            .collect();
        let mut out = vec![0.0; site.open_cells().len()];
        c.bench_function("classify cell/batch 1", |b| {
            b.iter(|| model.log_probs(&rssi, &mut out).expect("runs"))
        });
    }
}

criterion_group!(path_models, benches);
criterion_main!(path_models);
