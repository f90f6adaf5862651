//! A trained dense network as an ONNX model (opset 13), built with
//! tract-onnx's protobuf types (`gangway-offline`'s `train::write_proto`
//! writes it to a file).
//!
//! The graph is plain: optional `Concat` of the inputs, optional `Clip` (input
//! normalization), then per layer a `Gemm` (`x·W + b`, weights `in × out`) and
//! its activation (`LeakyRelu` α = 0.2 or `Tanh`), then the head (`Sigmoid`,
//! `Softmax`, or a log-softmax spelled out in `ReduceMax`/`Exp`/`ReduceSum`/`Log`). The batch dimension is symbolic (`N`). Weights
//! are stored little-endian in `raw_data`, as f32 or, with [`Weights::F16`],
//! as float16 initializers each followed by a `Cast` to float, so every
//! runtime computes in f32 from the same rounded values. The same network
//! always gives the same bytes.

use tract_onnx::pb;
use tract_onnx::pb::attribute_proto::AttributeType;
use tract_onnx::pb::tensor_proto::DataType;
use tract_onnx::prelude::f16;

use ndarray::{ArrayView1, ArrayView2};

use super::Metadata;

/// The slope of LeakyReLU for negative inputs (as in the paper's Keras setup).
pub const LEAKY_SLOPE: f32 = 0.2;

/// What follows a layer's affine map. Defined here, with the graph that
/// spells it out, so the file format does not depend on the trainer
/// (`train::mlp` in gangway-offline trains layers of these activations).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Act {
    LeakyRelu,
    Tanh,
    /// No nonlinearity: the layer outputs logits, and the loss (or the exported
    /// graph) applies sigmoid or softmax.
    Identity,
}

/// One dense layer as exported: `x·w + b` (`w` is `in × out`), then `act`.
#[derive(Clone, Copy, Debug)]
pub struct Layer<'a> {
    pub w: ArrayView2<'a, f32>,
    pub b: ArrayView1<'a, f32>,
    pub act: Act,
}

/// ONNX operator set the graphs use.
pub(crate) const OPSET: i64 = 13;
/// ONNX IR version matching [`OPSET`].
const IR_VERSION: i64 = 8;

/// What follows the last layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Head {
    /// The last layer's own activation only.
    None,
    Sigmoid,
    Softmax,
    LogSoftmax,
}

/// Input normalization baked into the graph: `x' = (clip(x, lo, hi) + offset) · scale`.
/// The clip is a node; the affine part is folded into the first layer.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ClipScale {
    pub lo: f32,
    pub hi: f32,
    pub offset: f32,
    pub scale: f32,
}

/// How the layers' weight matrices are stored (biases are always f32).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Weights {
    F32,
    /// Rounded to float16 (nearest, ties to even): half the bytes to read per
    /// row at inference, which is what bounds a one-row generator
    /// (BENCHMARKS.md, "Path models").
    F16,
}

/// A network and how it is presented.
pub struct Spec<'a> {
    /// The network's layers, input first.
    pub layers: Vec<Layer<'a>>,
    pub weights: Weights,
    /// Named inputs with their widths, concatenated in this order.
    pub inputs: &'a [(&'a str, usize)],
    pub normalize: Option<ClipScale>,
    pub head: Head,
    pub output: &'a str,
}

impl Spec<'_> {
    /// Trainable parameters (weights and biases).
    pub fn parameters(&self) -> usize {
        self.layers.iter().map(|l| l.w.len() + l.b.len()).sum()
    }

    fn outputs(&self) -> usize {
        self.layers.last().map_or(0, |l| l.w.ncols())
    }
}

/// The ONNX model for `spec` with `meta` as its `metadata_props`.
pub fn to_onnx(spec: &Spec, meta: &Metadata) -> pb::ModelProto {
    let widths: usize = spec.inputs.iter().map(|(_, w)| w).sum();
    assert_eq!(
        widths,
        spec.layers.first().map_or(0, |l| l.w.nrows()),
        "inputs must cover the first layer"
    );
    let mut nodes = Vec::new();
    let mut initializers = Vec::new();
    let mut x = if spec.inputs.len() == 1 {
        spec.inputs[0].0.to_owned()
    } else {
        nodes.push(node(
            "Concat",
            spec.inputs.iter().map(|(n, _)| n.to_string()).collect(),
            "inputs",
            vec![int_attr("axis", 1)],
        ));
        "inputs".to_owned()
    };
    if let Some(norm) = spec.normalize {
        initializers.push(tensor("clip.lo", &[], &[norm.lo]));
        initializers.push(tensor("clip.hi", &[], &[norm.hi]));
        nodes.push(node(
            "Clip",
            vec![x, "clip.lo".into(), "clip.hi".into()],
            "clipped",
            vec![],
        ));
        x = "clipped".into();
    }
    for (i, layer) in spec.layers.iter().enumerate() {
        let (mut w, mut b) = (layer.w.to_owned(), layer.b.to_owned());
        if let (0, Some(norm)) = (i, spec.normalize) {
            // (x + o)·s·W + b = x·(s·W) + (b + o·s·colsum(W))
            b = &b + &(layer.w.sum_axis(ndarray::Axis(0)) * (norm.offset * norm.scale));
            w *= norm.scale;
        }
        let (wn, bn) = (format!("layer{i}.weight"), format!("layer{i}.bias"));
        let dims = [w.nrows() as i64, w.ncols() as i64];
        let values = w.as_standard_layout();
        let values = values.as_slice().expect("standard layout");
        match spec.weights {
            Weights::F32 => initializers.push(tensor(&wn, &dims, values)),
            Weights::F16 => {
                let stored = format!("{wn}.f16");
                initializers.push(half_tensor(&stored, &dims, values));
                nodes.push(node(
                    "Cast",
                    vec![stored],
                    &wn,
                    vec![int_attr("to", i64::from(DataType::Float as i32))],
                ));
            }
        }
        initializers.push(tensor(
            &bn,
            &[b.len() as i64],
            b.as_slice().expect("contiguous"),
        ));
        let z = format!("layer{i}.linear");
        nodes.push(node("Gemm", vec![x, wn, bn], &z, vec![]));
        x = match layer.act {
            Act::Identity => z,
            Act::LeakyRelu => {
                let h = format!("layer{i}.leaky_relu");
                nodes.push(node(
                    "LeakyRelu",
                    vec![z],
                    &h,
                    vec![float_attr("alpha", LEAKY_SLOPE)],
                ));
                h
            }
            Act::Tanh => {
                let h = format!("layer{i}.tanh");
                nodes.push(node("Tanh", vec![z], &h, vec![]));
                h
            }
        };
    }
    match spec.head {
        Head::None => nodes.push(node("Identity", vec![x], spec.output, vec![])),
        Head::Sigmoid => nodes.push(node("Sigmoid", vec![x], spec.output, vec![])),
        Head::Softmax => nodes.push(node(
            "Softmax",
            vec![x],
            spec.output,
            vec![int_attr("axis", -1)],
        )),
        Head::LogSoftmax => log_softmax(&mut nodes, &mut initializers, x, spec.output),
    }
    model_proto(
        meta,
        nodes,
        initializers,
        spec.inputs
            .iter()
            .map(|&(name, width)| value_info(name, width))
            .collect(),
        vec![value_info(spec.output, spec.outputs())],
    )
}

/// A model of `nodes` over `initializers`, with `meta` as its metadata.
pub(crate) fn model_proto(
    meta: &Metadata,
    nodes: Vec<pb::NodeProto>,
    initializers: Vec<pb::TensorProto>,
    input: Vec<pb::ValueInfoProto>,
    output: Vec<pb::ValueInfoProto>,
) -> pb::ModelProto {
    let graph = pb::GraphProto {
        name: meta.kind.name().to_owned(),
        node: nodes,
        initializer: initializers,
        input,
        output,
        ..Default::default()
    };
    pb::ModelProto {
        ir_version: IR_VERSION,
        opset_import: vec![pb::OperatorSetIdProto {
            domain: String::new(),
            version: OPSET,
        }],
        producer_name: "gangway".into(),
        producer_version: env!("CARGO_PKG_VERSION").into(),
        model_version: i64::from(meta.version),
        doc_string: format!(
            "gangway {} model for site {:?}; see models/README.md",
            meta.kind.name(),
            meta.site
        ),
        graph: Some(graph),
        metadata_props: meta
            .to_props()
            .into_iter()
            .map(|(key, value)| pb::StringStringEntryProto { key, value })
            .collect(),
        ..Default::default()
    }
}

/// `z − max(z) − ln Σ exp(z − max(z))` over the last axis, spelled out: tract
/// runs `LogSoftmax` as `ln(softmax)`, which gives −∞ for classes whose
/// probability underflows, where this form stays finite (and agrees with
/// onnxruntime's `LogSoftmax`).
fn log_softmax(
    nodes: &mut Vec<pb::NodeProto>,
    initializers: &mut Vec<pb::TensorProto>,
    z: String,
    output: &str,
) {
    initializers.push(pb::TensorProto {
        name: "log_softmax.axes".into(),
        dims: vec![1],
        data_type: DataType::Int64 as i32,
        int64_data: vec![-1],
        ..Default::default()
    });
    let axes = pb::AttributeProto {
        name: "axes".into(),
        r#type: AttributeType::Ints as i32,
        ints: vec![-1],
        ..Default::default()
    };
    nodes.push(node(
        "ReduceMax",
        vec![z.clone()],
        "log_softmax.max",
        vec![axes, int_attr("keepdims", 1)],
    ));
    nodes.push(node(
        "Sub",
        vec![z, "log_softmax.max".into()],
        "log_softmax.shifted",
        vec![],
    ));
    nodes.push(node(
        "Exp",
        vec!["log_softmax.shifted".into()],
        "log_softmax.exp",
        vec![],
    ));
    nodes.push(node(
        "ReduceSum",
        vec!["log_softmax.exp".into(), "log_softmax.axes".into()],
        "log_softmax.sum",
        vec![int_attr("keepdims", 1)],
    ));
    nodes.push(node(
        "Log",
        vec!["log_softmax.sum".into()],
        "log_softmax.log_sum",
        vec![],
    ));
    nodes.push(node(
        "Sub",
        vec!["log_softmax.shifted".into(), "log_softmax.log_sum".into()],
        output,
        vec![],
    ));
}

pub(crate) fn node(
    op: &str,
    inputs: Vec<String>,
    output: &str,
    attribute: Vec<pb::AttributeProto>,
) -> pb::NodeProto {
    pb::NodeProto {
        name: output.to_owned(),
        op_type: op.to_owned(),
        input: inputs,
        output: vec![output.to_owned()],
        attribute,
        ..Default::default()
    }
}

pub(crate) fn int_attr(name: &str, i: i64) -> pb::AttributeProto {
    pb::AttributeProto {
        name: name.to_owned(),
        r#type: AttributeType::Int as i32,
        i,
        ..Default::default()
    }
}

fn float_attr(name: &str, f: f32) -> pb::AttributeProto {
    pb::AttributeProto {
        name: name.to_owned(),
        r#type: AttributeType::Float as i32,
        f,
        ..Default::default()
    }
}

pub(crate) fn tensor(name: &str, dims: &[i64], data: &[f32]) -> pb::TensorProto {
    pb::TensorProto {
        name: name.to_owned(),
        dims: dims.to_vec(),
        data_type: DataType::Float as i32,
        raw_data: data.iter().flat_map(|v| v.to_le_bytes()).collect(),
        ..Default::default()
    }
}

/// `data` rounded to float16.
fn half_tensor(name: &str, dims: &[i64], data: &[f32]) -> pb::TensorProto {
    pb::TensorProto {
        name: name.to_owned(),
        dims: dims.to_vec(),
        data_type: DataType::Float16 as i32,
        raw_data: data
            .iter()
            .flat_map(|&v| f16::from_f32(v).to_le_bytes())
            .collect(),
        ..Default::default()
    }
}

/// A float tensor `[N, width]` with a symbolic batch.
pub(crate) fn value_info(name: &str, width: usize) -> pb::ValueInfoProto {
    use pb::tensor_shape_proto::{Dimension, dimension::Value};
    let dim = |value| Dimension {
        value: Some(value),
        ..Default::default()
    };
    pb::ValueInfoProto {
        name: name.to_owned(),
        r#type: Some(pb::TypeProto {
            value: Some(pb::type_proto::Value::TensorType(pb::type_proto::Tensor {
                elem_type: DataType::Float as i32,
                shape: Some(pb::TensorShapeProto {
                    dim: vec![
                        dim(Value::DimParam("N".into())),
                        dim(Value::DimValue(width as i64)),
                    ],
                }),
            })),
            ..Default::default()
        }),
        ..Default::default()
    }
}
