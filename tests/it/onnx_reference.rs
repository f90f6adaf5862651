//! Runs every shipped model (`models/*.onnx`), and desire lines and a line
//! GAN trained here on sample walks, through tract on fixed inputs,
//! a batch and its first row alone, checks what it says, and writes the inputs
//! and tract's outputs as JSON for `scripts/check_onnx.py`, which runs the
//! same inputs through onnxruntime.
//!
//! The JSON goes to `$GANGWAY_ONNX_REFERENCE_DIR`, or to a directory under
//! Cargo's target tmp dir.

use std::path::{Path, PathBuf};

use gangway::model::runtime::{Model, Rows};
use gangway::model::{Kind, condition, line_gan};
use gangway::plan::anyangle::centre;
use gangway::site::Site;
use gangway::train::trajectory;
use ndarray::Array2;
use rand::SeedableRng;
use rand::rngs::Xoshiro256PlusPlus;
use rand_distr::{Distribution, StandardNormal};

const ROWS: usize = 8;

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

/// Fixed inputs for one graph input of a model of `kind`, by name.
fn input_for(
    kind: Kind,
    name: &str,
    width: usize,
    site: &Site,
    walks: &[trajectory::Trajectory],
) -> Array2<f32> {
    let line_gan = matches!(kind, Kind::LineGenerator | Kind::LineDiscriminator);
    match name {
        "noise" => {
            let mut rng = Xoshiro256PlusPlus::seed_from_u64(42);
            Array2::from_shape_simple_fn((ROWS, width), || StandardNormal.sample(&mut rng))
        }
        "condition" => {
            let mut out = Array2::zeros((ROWS, width));
            for (r, walk) in walks.iter().take(ROWS).enumerate() {
                let row = out.row_mut(r).into_slice().unwrap();
                condition::encode(
                    site.width(),
                    site.height(),
                    walk.source(),
                    walk.destination(),
                    row,
                );
            }
            out
        }
        // Discriminators take ±1 frames, classifiers 0/1; both are written by
        // the caller from the walks.
        "frame" => {
            let mut out = Array2::zeros((ROWS, width));
            for (r, walk) in walks.iter().take(ROWS).enumerate() {
                walk.frame(site)
                    .write_values(1.0, 0.0, out.row_mut(r).into_slice().unwrap());
            }
            out
        }
        // The line GAN: each walk's ends as its planner asks.
        "endpoints" if line_gan => {
            let mut out = Array2::zeros((ROWS, width));
            for (r, walk) in walks.iter().take(ROWS).enumerate() {
                let ends = line_gan::endpoints(
                    site.width(),
                    site.height(),
                    centre(walk.source()),
                    centre(walk.destination()),
                );
                out.row_mut(r).assign(&ndarray::ArrayView1::from(&ends));
            }
            out
        }
        // ... and the offsets of its prior, the any-angle route between them.
        "prior" if line_gan => {
            let mut out = Array2::zeros((ROWS, width));
            for (r, walk) in walks.iter().take(ROWS).enumerate() {
                let prior = line_gan::offsets(
                    &desire_prior_points(site, walk),
                    centre(walk.source()),
                    centre(walk.destination()),
                );
                out.row_mut(r).assign(&ndarray::ArrayView1::from(&prior));
            }
            out
        }
        // Line shapes for its discriminator: offsets of up to half a chord.
        "shape" => Array2::from_shape_fn((ROWS, width), |(i, j)| {
            ((i * 7 + j * 3) % 11) as f32 / 11.0 - 0.5
        }),
        // Desire lines: each walk's end cells' centres, as a request asks.
        "endpoints" => Array2::from_shape_fn((ROWS, width), |(r, j)| {
            let w = &walks[r];
            let c = if j < 2 { w.source() } else { w.destination() };
            f32::from(if j % 2 == 0 { c.x } else { c.y }) + 0.5
        }),
        // ... and the planner's prior between them (its any-angle route,
        // evenly resampled), x then y.
        "prior" => {
            let mut out = Array2::zeros((ROWS, width));
            for (r, walk) in walks.iter().take(ROWS).enumerate() {
                let prior = desire_prior(site, walk);
                for (k, p) in prior.iter().enumerate() {
                    out[[r, k]] = p[0];
                    out[[r, prior.len() + k]] = p[1];
                }
            }
            out
        }
        "rssi" => Array2::from_shape_fn((ROWS, width), |(i, j)| {
            // Strong, weak, and "not heard" (-200) readings.
            [-200.0, -62.0, -75.0, -88.0, -99.0, -200.0, -50.0][(i + 3 * j) % 7]
        }),
        other => panic!("no reference input for `{other}`"),
    }
}

/// The prior the desire planner passes for `walk`'s ends.
fn desire_prior(site: &Site, walk: &trajectory::Trajectory) -> Vec<[f32; 2]> {
    desire_prior_points(site, walk)
        .into_iter()
        .map(|p| [p[0] as f32, p[1] as f32])
        .collect()
}

/// The any-angle prior of `walk`'s ends, evenly resampled (cell units).
fn desire_prior_points(site: &Site, walk: &trajectory::Trajectory) -> Vec<[f64; 2]> {
    use gangway::plan::desire::{prior_line, resample};
    let line = prior_line(
        site,
        gangway::plan::Profile::Default,
        walk.source(),
        walk.destination(),
    )
    .unwrap();
    resample(&line, gangway::model::desire::POINTS)
}

/// Training without progress bars.
struct Silent;

impl gangway::train::job::Progress for Silent {
    fn stage(&mut self, _: &str, _: usize) {}
    fn step(&mut self, _: usize, _: &[(&str, f32)]) {}
    fn done(&mut self) {}
}

fn tensor_json(name: &str, a: &Array2<f32>) -> serde_json::Value {
    serde_json::json!({
        "name": name,
        "shape": [a.nrows(), a.ncols()],
        "data": a.iter().copied().collect::<Vec<f32>>(),
    })
}

#[test]
fn shipped_models_run_in_tract_and_write_reference_outputs() {
    let site = Site::load(&root().join("config/sites/waldo.toml")).unwrap();
    let walks = trajectory::read(&root().join("fixtures/trajectories/waldo.jsonl"), &site).unwrap();
    let out_dir = std::env::var_os("GANGWAY_ONNX_REFERENCE_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| Path::new(env!("CARGO_TARGET_TMPDIR")).join("onnx-reference"));
    std::fs::create_dir_all(&out_dir).unwrap();
    let mut models: Vec<PathBuf> = std::fs::read_dir(root().join("models"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "onnx"))
        .collect();
    models.sort();
    assert!(
        models.len() >= 4,
        "models/ should ship the trained models: {models:?}"
    );
    // Desire lines are trained here, on some of the sample walks (seconds),
    // so their graph is checked against onnxruntime like the shipped models.
    let desire = out_dir.join("desire_lines.onnx");
    let site_arc = std::sync::Arc::new(site.clone());
    let trained = gangway::train::desire::train(&site_arc, &walks[..300]).unwrap();
    let meta = gangway::model::Metadata::for_site(Kind::DesireLines, &site);
    gangway::train::write_proto(&desire, &trained.model.to_onnx(&meta)).unwrap();
    models.push(desire);
    // A line GAN too, a few hundred iterations (seconds).
    let options = gangway::train::job::Options {
        iterations: 300,
        batch: 32,
        seed: 1,
        conditional: false,
        classifier_iterations: 0,
        heldout_share: 0.2,
        checkpoint_every: None,
        accept_failed: true,
        threads: 1,
    };
    gangway::train::job::train_lines(&site, &walks[..300], &options, 1.0, &out_dir, &mut Silent)
        .unwrap();
    models.extend(
        [Kind::LineGenerator, Kind::LineDiscriminator]
            .map(|k| out_dir.join(format!("{}.onnx", k.name()))),
    );
    let all = [
        Kind::Generator,
        Kind::ConditionalGenerator,
        Kind::Discriminator,
        Kind::ConditionalDiscriminator,
        Kind::PathClassifier,
        Kind::CellClassifier,
        Kind::DesireLines,
        Kind::LineGenerator,
        Kind::LineDiscriminator,
    ];
    for path in &models {
        let model = Model::load(path, &site, &all, Rows::AlsoSingle).unwrap();
        let kind = model.metadata().kind;
        let mut inputs: Vec<(String, Array2<f32>)> = model
            .inputs()
            .iter()
            .map(|(name, width)| (name.clone(), input_for(kind, name, *width, &site, &walks)))
            .collect();
        if matches!(kind, Kind::Discriminator | Kind::ConditionalDiscriminator) {
            inputs[0].1.mapv_inplace(|v| 2.0 * v - 1.0);
        }
        let views: Vec<_> = inputs.iter().map(|(_, a)| a.view()).collect();
        let output = model.run(&views).unwrap();
        let (out_name, out_width) = model.output();
        assert_eq!(output.dim(), (ROWS, out_width), "{}", path.display());
        assert!(output.iter().all(|v| v.is_finite()), "{}", path.display());
        match kind {
            Kind::Generator | Kind::ConditionalGenerator | Kind::LineGenerator => {
                assert!(output.iter().all(|v| (-1.0..=1.0).contains(v)));
            }
            Kind::Discriminator | Kind::ConditionalDiscriminator | Kind::LineDiscriminator => {
                assert!(output.iter().all(|v| (0.0..=1.0).contains(v)));
            }
            Kind::PathClassifier => {
                for (row, walk) in output.rows().into_iter().zip(&walks) {
                    assert!((row.sum() - 1.0).abs() < 1e-4);
                    // The fixture's first walks belong to the first class.
                    let best = row
                        .iter()
                        .enumerate()
                        .max_by(|a, b| a.1.total_cmp(b.1))
                        .unwrap()
                        .0;
                    let class = model.metadata().classes[best];
                    assert_eq!(
                        (class.source, class.destination),
                        (walk.source(), walk.destination()),
                        "a training walk is classified as its own pair"
                    );
                }
            }
            Kind::DesireLines => {
                // From the request's source to its destination, and what the
                // trainer's own arithmetic gives, the walks' share included.
                let points = out_width / 2;
                for (r, row) in output.rows().into_iter().enumerate() {
                    let x = inputs[0].1.row(r);
                    let prior = desire_prior(&site, &walks[r]);
                    let answer = trained.model.predict([x[0], x[1]], [x[2], x[3]], &prior);
                    let line = &answer.points;
                    assert!(
                        (row[2 * points] - answer.learned).abs() < 1e-4,
                        "row {r}: tract's share {}, reference {}",
                        row[2 * points],
                        answer.learned
                    );
                    for k in 0..points {
                        let (px, py) = (row[k], row[points + k]);
                        assert!(
                            (px - line[k][0]).abs() < 1e-3 && (py - line[k][1]).abs() < 1e-3,
                            "row {r} point {k}: tract ({px}, {py}), reference {:?}",
                            line[k]
                        );
                    }
                    assert!((row[0] - x[0]).abs() < 1e-3 && (row[points] - x[1]).abs() < 1e-3);
                    assert!((row[points - 1] - x[2]).abs() < 1e-3);
                }
            }
            Kind::CellClassifier => {
                assert_eq!(out_width, site.open_cells().len());
                for row in output.rows() {
                    let total: f32 = row.iter().map(|v| v.exp()).sum();
                    assert!((total - 1.0).abs() < 1e-3, "{total}");
                }
            }
        }
        // The shipped generators store float16 weights for exactly this plan.
        // (Desire lines are no generator: whether tract finds float16-exact
        // constants in their bank does not matter.)
        if kind != Kind::DesireLines {
            assert_eq!(
                model.has_single_row_plan(),
                matches!(
                    kind,
                    Kind::Generator | Kind::ConditionalGenerator | Kind::LineGenerator
                ),
                "{}",
                path.display()
            );
        }
        // One row runs its own plan when the weights are float16
        // (model::runtime); it must give that row of the batch, and
        // onnxruntime checks it as well.
        let first: Vec<(String, Array2<f32>)> = inputs
            .iter()
            .map(|(n, a)| (n.clone(), a.slice(ndarray::s![..1, ..]).to_owned()))
            .collect();
        let views: Vec<_> = first.iter().map(|(_, a)| a.view()).collect();
        let single = model.run(&views).unwrap();
        for (a, b) in single.iter().zip(output.row(0)) {
            assert!(
                (a - b).abs() < 1e-5,
                "{}: one row {a}, in a batch {b}",
                path.display()
            );
        }
        let stem = path.file_stem().unwrap().to_string_lossy();
        for (suffix, inputs, output) in [("", &inputs, &output), (".one-row", &first, &single)] {
            let reference = serde_json::json!({
                "model": path,
                "inputs": inputs.iter().map(|(n, a)| tensor_json(n, a)).collect::<Vec<_>>(),
                "output": tensor_json(out_name, output),
            });
            std::fs::write(
                out_dir.join(format!("{stem}{suffix}.json")),
                serde_json::to_string(&reference).unwrap(),
            )
            .unwrap();
        }
    }
}
