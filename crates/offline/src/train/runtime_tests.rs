//! The tract runtime (`gangway_core::model::runtime`) against the trainer:
//! models this crate trains and exports load, run and agree with the
//! trainer's own forward pass, and refuse a foreign site or file.

use std::path::Path;

use crate::model::export::{ClipScale, Head, Spec, Weights};
use crate::model::runtime::*;
use crate::model::{CellClassifierInput, Kind, Metadata};
use crate::site::Site;
use crate::train::mlp::{Act, Mlp};
use ndarray::Array2;

fn site(map: &str) -> Site {
    let text = format!(
        "name = \"t\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n\
         [[beacon]]\nid = \"b1\"\nuuid = \"b9407f30-f5f8-466e-aff9-25556b57fe6d\"\nmajor = 1\nminor = 1\n\
         [[beacon]]\nid = \"b2\"\nuuid = \"b9407f30-f5f8-466e-aff9-25556b57fe6d\"\nmajor = 1\nminor = 2\n"
    );
    Site::parse(&text, Path::new("t.toml")).unwrap()
}

fn inputs(rows: usize, cols: usize) -> Array2<f32> {
    Array2::from_shape_fn((rows, cols), |(i, j)| {
        ((i * 7 + j * 3) % 11) as f32 / 5.0 - 1.0
    })
}

#[test]
fn tract_agrees_with_the_trainer_and_checks_the_site() {
    let s = site("###\n#.#");
    let dir = tempfile::tempdir().unwrap();
    let net = Mlp::new(&[4, 8, 6], &[Act::LeakyRelu, Act::Tanh], 3, 1);
    let mut meta = Metadata::for_site(Kind::Generator, &s);
    meta.noise_dim = 4;
    let file = dir.path().join("g.onnx");
    for weights in [Weights::F16, Weights::F32] {
        let spec = Spec {
            layers: net.layer_views(),
            weights,
            inputs: &[("noise", 4)],
            normalize: None,
            head: Head::None,
            output: "frame",
        };
        super::write_model(&file, &spec, &meta).unwrap();
        let bytes = std::fs::read(&file).unwrap();
        super::write_model(&file, &spec, &meta).unwrap();
        assert_eq!(
            std::fs::read(&file).unwrap(),
            bytes,
            "same model, same bytes"
        );

        let mut reference = net.clone();
        if weights == Weights::F16 {
            reference.round_weights_to_f16();
        }
        let batches_only = PathGenerator::load(&file, &s, Rows::Batches).unwrap();
        assert!(!batches_only.model().has_single_row_plan());
        let generator = PathGenerator::load(&file, &s, Rows::AlsoSingle).unwrap();
        assert!(!generator.is_conditional());
        assert_eq!(
            generator.model().has_single_row_plan(),
            weights == Weights::F16,
            "{weights:?}: only half-precision weights get a single-row plan"
        );
        // Rows 1 and 3 run different plans when the weights are f16.
        for rows in [1, 3, 5] {
            let x = inputs(rows, 4);
            let ours = reference.predict(x.view());
            let theirs = generator.generate(x.view(), None).unwrap();
            assert_eq!(theirs.dim(), (rows, 6));
            for (a, b) in ours.iter().zip(&theirs) {
                assert!((a - b).abs() < 1e-5, "{weights:?}: {a} vs {b}");
            }
        }
    }
    let generator = PathGenerator::load(&file, &s, Rows::Batches).unwrap();
    let err = generator
        .generate(inputs(2, 5).view(), None)
        .unwrap_err()
        .to_string();
    assert!(err.contains("`noise`") && err.contains("[2, 4]"), "{err}");

    let err = PathGenerator::load(&file, &site("###\n###"), Rows::Batches)
        .unwrap_err()
        .to_string();
    assert!(err.contains("gangway.map_hash"), "{err}");
    let err = PathClassifier::load(&file, &s).unwrap_err().to_string();
    assert!(
        err.contains("the model is a generator, but a path_classifier is needed"),
        "{err}"
    );
}

#[test]
fn truncated_or_foreign_files_are_errors() {
    let s = site("###\n#.#");
    let dir = tempfile::tempdir().unwrap();
    let net = Mlp::new(&[4, 6], &[Act::Identity], 1, 1);
    let meta = Metadata::for_site(Kind::PathClassifier, &s);
    let file = dir.path().join("c.onnx");
    let spec = Spec {
        layers: net.layer_views(),
        weights: Weights::F32,
        inputs: &[("frame", 4)],
        normalize: None,
        head: Head::Softmax,
        output: "probs",
    };
    super::write_model(&file, &spec, &meta).unwrap();
    let bytes = std::fs::read(&file).unwrap();
    for cut in [bytes.len() / 2, bytes.len() - 3, 7] {
        std::fs::write(&file, &bytes[..cut]).unwrap();
        let err = PathClassifier::load(&file, &s).unwrap_err().to_string();
        assert!(
            err.contains("not a valid ONNX model") || err.contains("metadata"),
            "{cut}: {err}"
        );
    }
    std::fs::write(&file, b"name = \"not a model\"\n").unwrap();
    assert!(PathClassifier::load(&file, &s).is_err());
    let err = PathClassifier::load(&dir.path().join("missing.onnx"), &s)
        .unwrap_err()
        .to_string();
    assert!(err.contains("no model there yet"), "{err}");
}

#[test]
fn the_cell_classifier_normalizes_raw_dbm_in_its_graph() {
    let s = site("###\n#.#");
    let dir = tempfile::tempdir().unwrap();
    let net = Mlp::new(&[2, 8, 5], &[Act::LeakyRelu, Act::Identity], 4, 2);
    let mut reference = net.clone();
    let mut meta = Metadata::for_site(Kind::CellClassifier, &s);
    meta.anchors = vec!["b1".into(), "b2".into()];
    let file = dir.path().join("cells.onnx");
    let (floor, ceil) = (
        CellClassifierInput::RSSI_FLOOR_DBM,
        CellClassifierInput::RSSI_CEIL_DBM,
    );
    let spec = Spec {
        layers: net.layer_views(),
        weights: Weights::F32,
        inputs: &[("rssi", 2)],
        normalize: Some(ClipScale {
            lo: floor,
            hi: ceil,
            offset: -floor,
            scale: 1.0 / (ceil - floor),
        }),
        head: Head::LogSoftmax,
        output: "log_probs",
    };
    super::write_model(&file, &spec, &meta).unwrap();
    let model = CellClassifier::load(&file, &s).unwrap();
    for rssi in [[-200.0f32, -70.0], [-60.0, -30.0], [-105.0, -104.0]] {
        let mut out = [0.0f32; 5];
        model.log_probs(&rssi, &mut out).unwrap();
        let normalized =
            Array2::from_shape_fn((1, 2), |(_, j)| CellClassifierInput::normalize(rssi[j]));
        let logits = reference.predict(normalized.view());
        let max = logits.iter().fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        let lse = logits.iter().map(|z| (z - max).exp()).sum::<f32>().ln() + max;
        for (o, z) in out.iter().zip(logits.iter()) {
            assert!((o - (z - lse)).abs() < 1e-5, "{rssi:?}: {o} vs {}", z - lse);
        }
    }
    let mut short = [0.0f32; 4];
    assert!(model.log_probs(&[-60.0, -60.0], &mut short).is_err());

    let mut reordered = meta.clone();
    reordered.anchors = vec!["b2".into(), "b1".into()];
    super::write_model(&file, &spec, &reordered).unwrap();
    let err = CellClassifier::load(&file, &s).unwrap_err().to_string();
    assert!(err.contains("anchors (gangway.anchors) b2,b1"), "{err}");
}
