//! Running exported models with tract: loading checks the file, its metadata
//! and its graph against the configured site, then keeps an optimized typed
//! plan with a symbolic batch, so one call runs any number of rows.
//!
//! A model whose weights are float16 values (stored as
//! [`Weights::F16`](super::export::Weights::F16); the values are what is
//! checked) gets a second plan for one-row calls that keeps those weights in
//! half precision:
//! one row multiplies each weight once, so its time is the time to read the
//! weights, and tract's kernel for f16 weights and f32 activations reads half
//! the bytes. It computes the same products (f16 → f32 is exact) in f32.
//! Batches keep f32 weights, which tract's matrix kernels run faster. The
//! second plan holds another, half-size copy of the weights, so it is built
//! only for callers that ask for it ([`Rows::AlsoSingle`]): the daemon's
//! planners generate two or more rows per call unless configured otherwise.
//!
//! One type per model kind, each with the one call its users need:
//! [`PathGenerator::generate`], [`Discriminator::score`],
//! [`PathClassifier::classify`], [`CellClassifier::log_probs`]. All are
//! `Send + Sync`; a call allocates its own run state.

use std::collections::BTreeMap;
use std::panic::AssertUnwindSafe;
use std::path::Path;
use std::sync::Arc;

use ndarray::{Array2, ArrayView2};
use tract_onnx::pb;
use tract_onnx::prelude::*;

use super::{Kind, Metadata, ModelError, PathClass};
use crate::site::Site;

/// The batch sizes a model is planned for.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rows {
    /// One plan, for any number of rows.
    Batches,
    /// Also a plan for one-row calls, when the weights are float16.
    AlsoSingle,
}

impl Rows {
    /// What a caller that runs `rows` rows per call needs.
    pub(crate) fn for_batch(rows: usize) -> Rows {
        if rows == 1 {
            Rows::AlsoSingle
        } else {
            Rows::Batches
        }
    }
}

/// A loaded model of any kind.
#[derive(Clone)]
pub struct Model {
    path: String,
    meta: Metadata,
    plan: Arc<TypedRunnableModel>,
    /// For one-row calls, when asked for and some weights are exactly float16.
    single_row_plan: Option<Arc<TypedRunnableModel>>,
    /// Graph inputs in order, with their widths.
    inputs: Vec<(String, usize)>,
    output: (String, usize),
}

impl std::fmt::Debug for Model {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Model")
            .field("path", &self.path)
            .field("kind", &self.meta.kind)
            .finish()
    }
}

impl Model {
    /// Loads a model for `site`, planned for `rows`, and checks it is one of
    /// `kinds`.
    pub fn load(path: &Path, site: &Site, kinds: &[Kind], rows: Rows) -> Result<Model, ModelError> {
        let name = path.display().to_string();
        let bytes = std::fs::read(path).map_err(|e| match e.kind() {
            std::io::ErrorKind::NotFound => ModelError::Missing { path: name.clone() },
            _ => ModelError::Read {
                path: name.clone(),
                reason: e.to_string(),
            },
        })?;
        let proto = <pb::ModelProto as prost::Message>::decode(bytes.as_slice()).map_err(|e| {
            ModelError::Corrupt {
                path: name.clone(),
                reason: e.to_string(),
            }
        })?;
        drop(bytes);
        let props: BTreeMap<String, String> = proto
            .metadata_props
            .iter()
            .map(|e| (e.key.clone(), e.value.clone()))
            .collect();
        let meta = Metadata::from_props(&props, &name)?;
        if !kinds.contains(&meta.kind) {
            return Err(ModelError::Metadata {
                path: name,
                key: "gangway.kind",
                reason: format!(
                    "the model is a {}, but a {} is needed here",
                    meta.kind.name(),
                    kinds
                        .iter()
                        .map(|k| k.name())
                        .collect::<Vec<_>>()
                        .join(" or ")
                ),
            });
        }
        meta.check_site(site, &name)?;
        let graph = proto.graph.as_ref().ok_or_else(|| ModelError::Corrupt {
            path: name.clone(),
            reason: "no graph".into(),
        })?;
        let corrupt = |reason: String| ModelError::Corrupt {
            path: name.clone(),
            reason,
        };
        let inputs = graph
            .input
            .iter()
            .map(|v| {
                Ok((
                    v.name.clone(),
                    batch_width(v).ok_or_else(|| {
                        corrupt(format!("input `{}` is not [N, width] float", v.name))
                    })?,
                ))
            })
            .collect::<Result<Vec<_>, ModelError>>()?;
        let output = match graph.output.as_slice() {
            [v] => (
                v.name.clone(),
                batch_width(v).ok_or_else(|| {
                    corrupt(format!("output `{}` is not [N, width] float", v.name))
                })?,
            ),
            _ => return Err(corrupt("the graph must have exactly one output".into())),
        };
        // tract asserts on some malformed graphs; a bad file must be an error,
        // not a crash of the daemon.
        // The protobuf goes as soon as tract has its own graph: each form of
        // the weights alive at once adds to the daemon's peak memory.
        let plan_name = name.clone();
        let plans = std::panic::catch_unwind(AssertUnwindSafe(move || -> TractResult<_> {
            let graph = tract_onnx::onnx().model_for_proto_model(&proto)?;
            drop(proto);
            let graph = graph.into_typed()?.into_decluttered()?;
            let single_row_plan = match rows {
                Rows::AlsoSingle => single_row_plan(&graph).unwrap_or_else(|e| {
                    // Only a speed-up: the batch plan still serves one row.
                    tracing::warn!(model = %plan_name, "no single-row plan: {e:#}");
                    None
                }),
                Rows::Batches => None,
            };
            Ok((graph.into_optimized()?.into_runnable()?, single_row_plan))
        }))
        .map_err(|_| ModelError::Runtime {
            path: name.clone(),
            reason: "tract panicked while loading the graph".into(),
        })?
        .map_err(|e| ModelError::Runtime {
            path: name.clone(),
            reason: format!("{e:#}"),
        })?;
        let (plan, single_row_plan) = plans;
        Ok(Model {
            path: name,
            meta,
            plan,
            single_row_plan,
            inputs,
            output,
        })
    }

    pub fn metadata(&self) -> &Metadata {
        &self.meta
    }

    /// The graph's input names and widths, in order.
    pub fn inputs(&self) -> &[(String, usize)] {
        &self.inputs
    }

    /// Whether one-row calls run their own plan with float16 weights.
    pub fn has_single_row_plan(&self) -> bool {
        self.single_row_plan.is_some()
    }

    /// The graph's output name and width.
    pub fn output(&self) -> (&str, usize) {
        (&self.output.0, self.output.1)
    }

    /// Runs one batch: one array per graph input, all with the same rows.
    pub fn run(&self, inputs: &[ArrayView2<f32>]) -> Result<Array2<f32>, ModelError> {
        if inputs.len() != self.inputs.len() {
            return Err(ModelError::Input(format!(
                "{} takes {} inputs ({}), got {}",
                self.path,
                self.inputs.len(),
                self.input_names(),
                inputs.len()
            )));
        }
        let rows = inputs.first().map_or(0, |a| a.nrows());
        let mut values = TVec::new();
        for (array, (name, width)) in inputs.iter().zip(&self.inputs) {
            if array.ncols() != *width || array.nrows() != rows {
                return Err(ModelError::Input(format!(
                    "`{name}` of {} must be [{rows}, {width}], got [{}, {}]",
                    self.path,
                    array.nrows(),
                    array.ncols()
                )));
            }
            let tensor: Tensor = array.as_standard_layout().into_owned().into();
            values.push(tensor.into());
        }
        let plan = match (&self.single_row_plan, rows) {
            (Some(single_row), 1) => single_row,
            _ => &self.plan,
        };
        let out = plan.run(values).map_err(|e| ModelError::Runtime {
            path: self.path.clone(),
            reason: format!("{e:#}"),
        })?;
        out[0]
            .to_plain_array_view::<f32>()
            .and_then(|v| Ok(v.into_dimensionality::<ndarray::Ix2>()?.to_owned()))
            .map_err(|e| ModelError::Runtime {
                path: self.path.clone(),
                reason: format!("{e:#}"),
            })
    }

    fn input_names(&self) -> String {
        self.inputs
            .iter()
            .map(|(n, _)| format!("`{n}`"))
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// The plan of `model` with its float16-exact weights held as float16
/// ([`with_half_weights`]); `None` when it has none.
fn single_row_plan(model: &TypedModel) -> TractResult<Option<Arc<TypedRunnableModel>>> {
    match with_half_weights(model)? {
        Some(half) => Ok(Some(half.into_optimized()?.into_runnable()?)),
        None => Ok(None),
    }
}

/// `model` with every matrix-product weight whose values are all exactly
/// float16 held as float16; `None` when there is none. tract folds the
/// exported `Cast` to f32 into the constant while decluttering, so the values
/// are checked rather than the file's types: the result multiplies exactly
/// the values `model` does (only the kernels, hence the order of the sums,
/// differ).
fn with_half_weights(model: &TypedModel) -> TractResult<Option<TypedModel>> {
    use tract_onnx::tract_core::ops::einsum::EinSum;
    use tract_onnx::tract_core::ops::konst::Const;

    let mut half = model.clone();
    let mut changed = false;
    for node in model.nodes().iter().filter(|n| n.op_is::<EinSum>()) {
        for input in &node.inputs {
            let source = model.node(input.node);
            let Some(weights) = source.op_as::<Const>().map(|c| c.val()) else {
                continue;
            };
            if weights.datum_type() != f32::datum_type() || source.outputs[0].successors.len() != 1
            {
                continue;
            }
            let rounded = weights.cast_to::<f16>()?.into_owned();
            if *rounded.cast_to::<f32>()? != **weights {
                continue;
            }
            let rounded = rounded.into_arc_tensor();
            let target = half.node_mut(source.id);
            target.outputs[0].fact = TypedFact::try_from(rounded.clone())?;
            target.op = Box::new(Const::new(rounded)?);
            changed = true;
        }
    }
    Ok(changed.then_some(half))
}

/// The width of a `[N, width]` float input or output.
fn batch_width(v: &pb::ValueInfoProto) -> Option<usize> {
    use pb::tensor_shape_proto::dimension::Value;
    let pb::type_proto::Value::TensorType(t) = v.r#type.as_ref()?.value.as_ref()?;
    if t.elem_type != pb::tensor_proto::DataType::Float as i32 {
        return None;
    }
    match t.shape.as_ref()?.dim.as_slice() {
        [_, d] => match d.value {
            Some(Value::DimValue(w)) if w > 0 => usize::try_from(w).ok(),
            _ => None,
        },
        _ => None,
    }
}

/// Generates path frames from noise (and conditions).
#[derive(Clone, Debug)]
pub struct PathGenerator(Model);

impl PathGenerator {
    /// Loads a generator planned for `rows` per call.
    pub fn load(path: &Path, site: &Site, rows: Rows) -> Result<PathGenerator, ModelError> {
        Model::load(
            path,
            site,
            &[Kind::Generator, Kind::ConditionalGenerator],
            rows,
        )
        .map(PathGenerator)
    }

    pub fn model(&self) -> &Model {
        &self.0
    }

    pub fn noise_dim(&self) -> usize {
        self.0.meta.noise_dim
    }

    /// Whether [`PathGenerator::generate`] needs conditions
    /// ([`crate::model::condition::encode`]).
    pub fn is_conditional(&self) -> bool {
        self.0.meta.kind == Kind::ConditionalGenerator
    }

    /// One frame (`W·H` values in (−1, 1), on the path when > 0) per noise row.
    pub fn generate(
        &self,
        noise: ArrayView2<f32>,
        conditions: Option<ArrayView2<f32>>,
    ) -> Result<Array2<f32>, ModelError> {
        match (self.is_conditional(), conditions) {
            (false, None) => self.0.run(&[noise]),
            (true, Some(c)) => self.0.run(&[noise, c]),
            (true, None) => Err(ModelError::Input(
                "a conditional generator needs a condition per row".into(),
            )),
            (false, Some(_)) => Err(ModelError::Input(
                "this generator is not conditional; pass no conditions".into(),
            )),
        }
    }
}

/// Generates walk-like lines between two points ([`super::line_gan`]).
#[derive(Clone, Debug)]
pub struct LineGenerator(Model);

impl LineGenerator {
    /// Loads a line generator planned for `rows` per call, checking its
    /// input and output widths.
    pub fn load(path: &Path, site: &Site, rows: Rows) -> Result<LineGenerator, ModelError> {
        use super::line_gan::{ENDPOINTS_LEN, SHAPE_LEN};
        let model = Model::load(path, site, &[Kind::LineGenerator], rows)?;
        let widths: Vec<usize> = model.inputs.iter().map(|i| i.1).collect();
        if widths != [model.meta.noise_dim, ENDPOINTS_LEN, SHAPE_LEN] || model.output.1 != SHAPE_LEN
        {
            return Err(ModelError::Corrupt {
                path: model.path.clone(),
                reason: format!(
                    "a line generator takes `noise` [N, {}], `endpoints` [N, {ENDPOINTS_LEN}] and \
                     `prior` [N, {SHAPE_LEN}] and gives `shape` [N, {SHAPE_LEN}]; a model from an \
                     older gangway must be retrained (`gangway train --line-gan`)",
                    model.meta.noise_dim
                ),
            });
        }
        Ok(LineGenerator(model))
    }

    pub fn model(&self) -> &Model {
        &self.0
    }

    pub fn noise_dim(&self) -> usize {
        self.0.meta.noise_dim
    }

    /// One sample ([`super::line_gan::SHAPE_LEN`] values) per noise row,
    /// for the request of the same row of `endpoints`
    /// ([`super::line_gan::endpoints`]) and `prior` (its prior's
    /// [`super::line_gan::offsets`]).
    pub fn generate(
        &self,
        noise: ArrayView2<f32>,
        endpoints: ArrayView2<f32>,
        prior: ArrayView2<f32>,
    ) -> Result<Array2<f32>, ModelError> {
        self.0.run(&[noise, endpoints, prior])
    }
}

/// Says which source/destination pair a path frame belongs to.
#[derive(Clone, Debug)]
pub struct PathClassifier(Model);

impl PathClassifier {
    pub fn load(path: &Path, site: &Site) -> Result<PathClassifier, ModelError> {
        Model::load(path, site, &[Kind::PathClassifier], Rows::Batches).map(PathClassifier)
    }

    pub fn model(&self) -> &Model {
        &self.0
    }

    /// The classes, in output column order.
    pub fn classes(&self) -> &[PathClass] {
        &self.0.meta.classes
    }

    /// Class probabilities (`[N, classes]`) of 0/1 frames (`[N, W·H]`).
    pub fn classify(&self, frames: ArrayView2<f32>) -> Result<Array2<f32>, ModelError> {
        self.0.run(&[frames])
    }
}

/// Where people walk between two points ([`super::desire`]).
#[derive(Clone, Debug)]
pub(crate) struct DesireModel(Model);

impl DesireModel {
    pub(crate) fn load(path: &Path, site: &Site) -> Result<DesireModel, ModelError> {
        use super::desire::POINTS;
        let model = Model::load(path, site, &[Kind::DesireLines], Rows::Batches)?;
        let widths: Vec<usize> = model.inputs.iter().map(|i| i.1).collect();
        if widths != [4, 2 * POINTS] || model.output.1 != 2 * POINTS + 1 {
            return Err(ModelError::Corrupt {
                path: model.path.clone(),
                reason: format!(
                    "a desire-line model takes `endpoints` [N, 4] and `prior` [N, {}] and gives \
                     `line` [N, {}]; a model from an older gangway must be retrained \
                     (`gangway train`)",
                    2 * POINTS,
                    2 * POINTS + 1
                ),
            });
        }
        Ok(DesireModel(model))
    }

    pub(crate) fn model(&self) -> &Model {
        &self.0
    }

    /// The learned line from `a` to `b` (cell units), `a` first, blended
    /// into `prior` ([`super::desire::POINTS`] points from `a` to `b`), and
    /// the walks' share of it (0: the prior alone answered).
    pub(crate) fn line(
        &self,
        a: [f32; 2],
        b: [f32; 2],
        prior: &[[f32; 2]],
    ) -> Result<(Vec<[f32; 2]>, f32), ModelError> {
        let ends = ndarray::arr2(&[[a[0], a[1], b[0], b[1]]]);
        let prior = ndarray::Array2::from_shape_fn((1, 2 * prior.len()), |(_, j)| {
            prior[j % prior.len()][j / prior.len()]
        });
        let out = self.0.run(&[ends.view(), prior.view()])?;
        let row = out.row(0);
        let points = row.len() / 2;
        Ok((
            (0..points).map(|k| [row[k], row[points + k]]).collect(),
            row[2 * points],
        ))
    }
}

/// Locates a device from what it hears: a distribution over the site's open cells.
#[derive(Clone, Debug)]
pub struct CellClassifier(Model);

impl CellClassifier {
    pub fn load(path: &Path, site: &Site) -> Result<CellClassifier, ModelError> {
        let model = Model::load(path, site, &[Kind::CellClassifier], Rows::Batches)?;
        let open = site.open_cells().len();
        if model.output.1 != open {
            return Err(ModelError::Metadata {
                path: model.path.clone(),
                key: "gangway.map_hash",
                reason: format!(
                    "the model scores {} cells but the site has {open} open cells",
                    model.output.1
                ),
            });
        }
        Ok(CellClassifier(model))
    }

    /// Writes the log-probability of each open cell (`Site::open_cells` order)
    /// for one fingerprint: `rssi` in dBm, one per site anchor, anything at or
    /// below [`super::CellClassifierInput::RSSI_FLOOR_DBM`] meaning not heard.
    pub fn log_probs(&self, rssi: &[f32], out: &mut [f32]) -> Result<(), ModelError> {
        let input = ArrayView2::from_shape((1, rssi.len()), rssi)
            .map_err(|e| ModelError::Input(e.to_string()))?;
        let result = self.log_probs_batch(input)?;
        if out.len() != result.len() {
            return Err(ModelError::Input(format!(
                "the output buffer has {} slots for {} cells",
                out.len(),
                result.len()
            )));
        }
        out.copy_from_slice(result.as_slice().expect("standard layout"));
        Ok(())
    }

    /// [`CellClassifier::log_probs`] for a batch (`[N, anchors]` → `[N, cells]`).
    pub(crate) fn log_probs_batch(&self, rssi: ArrayView2<f32>) -> Result<Array2<f32>, ModelError> {
        self.0.run(&[rssi])
    }
}
