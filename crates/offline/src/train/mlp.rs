//! A purpose-built trainer for small dense networks (multi-layer perceptrons).
//!
//! Why not a library trainer: the paper's GAN is ~1.45M parameters and
//! ~0.4 GFLOP per iteration at batch 32, so a step is dominated by per-step
//! overhead in general frameworks. Measured on the project's 2-core machine,
//! back to back under the same load, the same GAN (same layers, BCE, Adam) at
//! batch 32: candle-nn 0.9 took 56 ms per iteration, this trainer 6.2 ms
//! (`cargo bench --bench train_step` measures ours). This trainer does the
//! same arithmetic with no allocation in the loop: every activation and
//! gradient buffer is allocated once for the largest batch, the matrix
//! products go straight to `ndarray`'s `general_mat_mul` (the
//! `matrixmultiply` kernels, which pick AVX2/FMA at run time), and Adam is one
//! fused pass over each parameter array. The matrix products are ~5 ms of the
//! ~6 ms iteration, so what is left is arithmetic.
//!
//! Threads: a network's products and its Adam pass are split across
//! [`Workers`] (`gangway train --threads`, default the machine's cores), by
//! blocks of each product's output, so the weights do not depend on the
//! thread count (see [`super::workers`] for why not `matrixmultiply`'s own
//! threading). `perf` of the 15,000-iteration GAN on one thread: the
//! `matrixmultiply` micro-kernel 52 %, packing the operands 23 %, Adam 13 %,
//! the element-wise passes 5 %. Its AVX-512 kernel (a feature ndarray leaves
//! off) was measured no faster than its AVX2/FMA one here (A/B 1.02).
//!
//! Layout: a layer's weights are `in × out` (row-major), so a batch `X` of
//! `n × in` maps to `X·W + b`. The same layout is exported to ONNX as `Gemm`.

use ndarray::{Array1, Array2, ArrayView2, Axis, Zip, s};
use rand::RngExt;
use rand::rngs::Xoshiro256PlusPlus;

use super::workers::Workers;

/// The activations and LeakyReLU slope of the exported graphs: the file
/// format owns them, the trainer implements them.
pub(crate) use crate::model::export::{Act, LEAKY_SLOPE};

/// Adam hyper-parameters.
#[derive(Clone, Copy, Debug)]
pub(crate) struct Adam {
    pub lr: f32,
    pub beta1: f32,
    pub beta2: f32,
    pub eps: f32,
}

impl Adam {
    /// The DCGAN settings the paper's Keras code uses (lr 2e-4, β₁ 0.5).
    pub(crate) const GAN: Adam = Adam {
        lr: 2e-4,
        beta1: 0.5,
        beta2: 0.999,
        eps: 1e-7,
    };
    /// Keras defaults, for classifiers.
    pub(crate) const DEFAULT: Adam = Adam {
        lr: 1e-3,
        beta1: 0.9,
        beta2: 0.999,
        eps: 1e-7,
    };
}

/// One dense layer with its gradients and Adam moments.
#[derive(Clone, Debug)]
pub struct Dense {
    pub w: Array2<f32>,
    pub b: Array1<f32>,
    pub act: Act,
    gw: Array2<f32>,
    gb: Array1<f32>,
    mw: Array2<f32>,
    vw: Array2<f32>,
    mb: Array1<f32>,
    vb: Array1<f32>,
}

impl Dense {
    /// Glorot-uniform weights and zero biases (Keras' defaults).
    fn new(inputs: usize, outputs: usize, act: Act, rng: &mut Xoshiro256PlusPlus) -> Dense {
        let limit = (6.0 / (inputs + outputs) as f32).sqrt();
        let w = Array2::from_shape_simple_fn((inputs, outputs), || rng.random_range(-limit..limit));
        let zeros2 = || Array2::zeros((inputs, outputs));
        let zeros1 = || Array1::zeros(outputs);
        Dense {
            w,
            b: zeros1(),
            act,
            gw: zeros2(),
            gb: zeros1(),
            mw: zeros2(),
            vw: zeros2(),
            mb: zeros1(),
            vb: zeros1(),
        }
    }

    pub(crate) fn inputs(&self) -> usize {
        self.w.nrows()
    }

    pub(crate) fn outputs(&self) -> usize {
        self.w.ncols()
    }
}

/// A stack of dense layers with buffers for batches of up to `max_batch` rows.
#[derive(Clone, Debug)]
pub struct Mlp {
    pub layers: Vec<Dense>,
    max_batch: usize,
    /// The last forward pass's input.
    input: Array2<f32>,
    /// Each layer's output after its activation.
    outs: Vec<Array2<f32>>,
    /// Each layer's gradient with respect to its pre-activation.
    deltas: Vec<Array2<f32>>,
    /// Gradient with respect to the network input.
    input_grad: Array2<f32>,
    /// Adam steps taken.
    steps: i32,
    /// Threads for the matrix products and Adam ([`Workers`]).
    workers: Workers,
}

impl Mlp {
    /// `sizes` are the widths from input to output; `acts` has one entry per layer.
    pub(crate) fn new(sizes: &[usize], acts: &[Act], max_batch: usize, seed: u64) -> Mlp {
        assert_eq!(sizes.len(), acts.len() + 1, "one activation per layer");
        let mut rng = rand::SeedableRng::seed_from_u64(seed);
        let layers: Vec<Dense> = sizes
            .windows(2)
            .zip(acts)
            .map(|(io, &act)| Dense::new(io[0], io[1], act, &mut rng))
            .collect();
        Mlp::from_layers(layers, max_batch)
    }

    fn from_layers(layers: Vec<Dense>, max_batch: usize) -> Mlp {
        let buffers = || -> Vec<Array2<f32>> {
            layers
                .iter()
                .map(|l| Array2::zeros((max_batch, l.outputs())))
                .collect()
        };
        let inputs = layers[0].inputs();
        Mlp {
            outs: buffers(),
            deltas: buffers(),
            input: Array2::zeros((max_batch, inputs)),
            input_grad: Array2::zeros((max_batch, inputs)),
            layers,
            max_batch,
            steps: 0,
            workers: Workers::single(),
        }
    }

    /// The same network, its arithmetic split across `workers`' threads.
    pub(crate) fn with_workers(mut self, workers: Workers) -> Mlp {
        self.workers = workers;
        self
    }

    #[cfg(test)]
    pub(crate) fn inputs(&self) -> usize {
        self.layers[0].inputs()
    }

    pub(crate) fn outputs(&self) -> usize {
        self.layers.last().expect("at least one layer").outputs()
    }

    /// Rounds every weight matrix to the nearest float16, as
    /// [`Weights::F16`](crate::model::export::Weights::F16) stores it, so what
    /// is measured of this network is what is exported.
    pub(crate) fn round_weights_to_f16(&mut self) {
        for layer in &mut self.layers {
            layer
                .w
                .mapv_inplace(|v| tract_onnx::prelude::f16::from_f32(v).to_f32());
        }
    }

    /// The layers as [`crate::model::export`] writes them.
    pub(crate) fn layer_views(&self) -> Vec<crate::model::export::Layer<'_>> {
        self.layers
            .iter()
            .map(|l| crate::model::export::Layer {
                w: l.w.view(),
                b: l.b.view(),
                act: l.act,
            })
            .collect()
    }

    /// Runs a batch of `x.nrows() ≤ max_batch` rows and returns the last layer's
    /// output (after its activation). Keeps what `backward` needs.
    pub(crate) fn forward(&mut self, x: ArrayView2<f32>) -> ArrayView2<'_, f32> {
        let n = x.nrows();
        assert!(n <= self.max_batch, "batch {n} over {}", self.max_batch);
        self.input.slice_mut(s![..n, ..]).assign(&x);
        for i in 0..self.layers.len() {
            let (before, after) = self.outs.split_at_mut(i);
            let src = if i == 0 {
                self.input.slice(s![..n, ..])
            } else {
                before[i - 1].slice(s![..n, ..])
            };
            let layer = &self.layers[i];
            let mut out = after[0].slice_mut(s![..n, ..]);
            // out = b (broadcast), then out += src·W.
            out.assign(&layer.b.broadcast((n, layer.outputs())).expect("bias row"));
            self.workers.gemm(1.0, &src, &layer.w.view(), 1.0, &mut out);
            match layer.act {
                Act::LeakyRelu => out.mapv_inplace(|v| if v > 0.0 { v } else { LEAKY_SLOPE * v }),
                Act::Tanh => out.mapv_inplace(f32::tanh),
                Act::Identity => {}
            }
        }
        self.outs.last().expect("layers").slice(s![..n, ..])
    }

    /// Back-propagates `grad_out`, the loss gradient with respect to the last
    /// forward pass's output (`n × outputs`). With `param_grads` the parameter
    /// gradients are stored for [`Mlp::adam_step`]; with `input_grad` the
    /// gradient with respect to the input is returned (for chaining networks, as
    /// the generator does through the discriminator).
    pub(crate) fn backward(
        &mut self,
        grad_out: ArrayView2<f32>,
        param_grads: bool,
        input_grad: bool,
    ) -> ArrayView2<'_, f32> {
        self.backward_with_logit_grad(grad_out, None, param_grads, input_grad)
    }

    /// [`Mlp::backward`], with `logit_grad` (the shape of `grad_out`), the
    /// gradient of a further loss with respect to the last layer's
    /// pre-activation, added to what `grad_out` gives there. A loss defined on
    /// the pre-activation must enter here, not through the output: in f32, tanh
    /// rounds to exactly ±1 beyond |a| ≈ 9, where the chain through the output
    /// would be ∞ · 0.
    pub(crate) fn backward_with_logit_grad(
        &mut self,
        grad_out: ArrayView2<f32>,
        logit_grad: Option<ArrayView2<f32>>,
        param_grads: bool,
        input_grad: bool,
    ) -> ArrayView2<'_, f32> {
        let n = grad_out.nrows();
        let last = self.layers.len() - 1;
        for i in (0..=last).rev() {
            let act = self.layers[i].act;
            // delta_i = dL/d(pre-activation) of layer i.
            {
                let out = self.outs[i].slice(s![..n, ..]);
                let (lower, upper) = self.deltas.split_at_mut(i + 1);
                let mut delta = lower[i].slice_mut(s![..n, ..]);
                if i == last {
                    delta.assign(&grad_out);
                } else {
                    // dL/d(output of i) = delta_{i+1} · W_{i+1}ᵀ
                    let next = upper[0].slice(s![..n, ..]);
                    self.workers
                        .gemm(1.0, &next, &self.layers[i + 1].w.t(), 0.0, &mut delta);
                }
                match act {
                    Act::LeakyRelu => Zip::from(&mut delta).and(&out).for_each(|d, &y| {
                        if y <= 0.0 {
                            *d *= LEAKY_SLOPE;
                        }
                    }),
                    Act::Tanh => Zip::from(&mut delta)
                        .and(&out)
                        .for_each(|d, &y| *d *= 1.0 - y * y),
                    Act::Identity => {}
                }
                if let (true, Some(extra)) = (i == last, logit_grad) {
                    delta += &extra;
                }
            }
            if param_grads {
                let src = if i == 0 {
                    self.input.slice(s![..n, ..])
                } else {
                    self.outs[i - 1].slice(s![..n, ..])
                };
                let delta = self.deltas[i].slice(s![..n, ..]);
                let layer = &mut self.layers[i];
                self.workers
                    .gemm(1.0, &src.t(), &delta, 0.0, &mut layer.gw.view_mut());
                layer.gb.assign(&delta.sum_axis(Axis(0)));
            }
        }
        if input_grad {
            let delta = self.deltas[0].slice(s![..n, ..]);
            let mut g = self.input_grad.slice_mut(s![..n, ..]);
            self.workers
                .gemm(1.0, &delta, &self.layers[0].w.t(), 0.0, &mut g);
        }
        self.input_grad.slice(s![..n, ..])
    }

    /// One Adam update from the gradients of the last `backward`.
    pub(crate) fn adam_step(&mut self, opt: Adam) {
        self.steps += 1;
        let t = self.steps;
        // Bias correction folded into the step size, as Keras and PyTorch do.
        let lr_t = opt.lr * (1.0 - opt.beta2.powi(t)).sqrt() / (1.0 - opt.beta1.powi(t));
        for layer in &mut self.layers {
            // Element by element: the same result however it is split.
            self.workers.for_parts(
                layer.w.as_slice_mut().expect("contiguous"),
                layer.gw.as_slice().expect("contiguous"),
                layer.mw.as_slice_mut().expect("contiguous"),
                layer.vw.as_slice_mut().expect("contiguous"),
                |p, g, m, v| adam_fused(p, g, m, v, opt, lr_t),
            );
            adam_fused(
                layer.b.as_slice_mut().expect("contiguous"),
                layer.gb.as_slice().expect("contiguous"),
                layer.mb.as_slice_mut().expect("contiguous"),
                layer.vb.as_slice_mut().expect("contiguous"),
                opt,
                lr_t,
            );
        }
    }

    /// Runs any number of rows in chunks of `max_batch`, returning the outputs.
    pub(crate) fn predict(&mut self, x: ArrayView2<f32>) -> Array2<f32> {
        let mut out = Array2::zeros((x.nrows(), self.outputs()));
        let step = self.max_batch;
        for start in (0..x.nrows()).step_by(step) {
            let end = (start + step).min(x.nrows());
            let y = self.forward(x.slice(s![start..end, ..]));
            out.slice_mut(s![start..end, ..]).assign(&y);
        }
        out
    }
}

/// `p -= lr_t · m / (√v + ε)` with the moments updated in the same pass: one
/// read and write of each array per step.
fn adam_fused(p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32], opt: Adam, lr_t: f32) {
    let (b1, b2) = (opt.beta1, opt.beta2);
    for (((p, &g), m), v) in p.iter_mut().zip(g).zip(m.iter_mut()).zip(v.iter_mut()) {
        *m = b1 * *m + (1.0 - b1) * g;
        *v = b2 * *v + (1.0 - b2) * g * g;
        *p -= lr_t * *m / (v.sqrt() + opt.eps);
    }
}

/// Binary cross-entropy on logits against `target`, averaged over rows; writes
/// the gradient with respect to the logits into `grad` and returns the loss.
/// The stable form: `max(z,0) − z·y + ln(1 + e^−|z|)`.
pub(crate) fn bce_with_logits(logits: ArrayView2<f32>, target: f32, grad: &mut [f32]) -> f32 {
    let n = logits.nrows() as f32;
    let mut loss = 0.0;
    for (g, &z) in grad.iter_mut().zip(logits.iter()) {
        loss += z.max(0.0) - z * target + (-z.abs()).exp().ln_1p();
        *g = (sigmoid(z) - target) / n;
    }
    loss / n
}

pub(crate) fn sigmoid(z: f32) -> f32 {
    1.0 / (1.0 + (-z).exp())
}

/// Softmax cross-entropy on logits for integer labels, averaged over rows;
/// writes the gradient with respect to the logits into `grad` (same shape) and
/// returns the loss.
pub(crate) fn softmax_cross_entropy(
    logits: ArrayView2<f32>,
    labels: &[usize],
    grad: &mut ndarray::ArrayViewMut2<f32>,
) -> f32 {
    let n = logits.nrows() as f32;
    let mut loss = 0.0;
    for ((row, mut g), &label) in logits.rows().into_iter().zip(grad.rows_mut()).zip(labels) {
        let max = row.fold(f32::NEG_INFINITY, |a, &b| a.max(b));
        let sum: f32 = row.iter().map(|&z| (z - max).exp()).sum();
        loss += sum.ln() + max - row[label];
        Zip::from(&mut g)
            .and(&row)
            .for_each(|g, &z| *g = (z - max).exp() / sum / n);
        g[label] -= 1.0 / n;
    }
    loss / n
}

/// Index of the largest value of each row.
pub(crate) fn argmax_rows(x: ArrayView2<f32>) -> Vec<usize> {
    x.rows()
        .into_iter()
        .map(|r| {
            r.iter()
                .enumerate()
                .max_by(|a, b| a.1.total_cmp(b.1))
                .map_or(0, |(i, _)| i)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::array;

    /// Finite differences agree with back-propagation through every activation.
    #[test]
    fn gradients_match_finite_differences() {
        let mut net = Mlp::new(
            &[3, 4, 5, 2],
            &[Act::LeakyRelu, Act::Tanh, Act::Identity],
            2,
            7,
        );
        let x = array![[0.5f32, -1.0, 0.25], [-0.3, 0.8, 1.5]];
        let labels = [1usize, 0];
        let loss_of = |net: &mut Mlp| {
            let y = net.forward(x.view()).to_owned();
            let mut g = Array2::zeros(y.raw_dim());
            softmax_cross_entropy(y.view(), &labels, &mut g.view_mut())
        };
        let y = net.forward(x.view()).to_owned();
        let mut g = Array2::zeros(y.raw_dim());
        softmax_cross_entropy(y.view(), &labels, &mut g.view_mut());
        let dx = net.backward(g.view(), true, true).to_owned();
        let eps = 1e-2;
        for (layer, (i, j)) in [(0, (1, 2)), (1, (3, 0)), (2, (4, 1))] {
            let analytic = net.layers[layer].gw[(i, j)];
            let orig = net.layers[layer].w[(i, j)];
            net.layers[layer].w[(i, j)] = orig + eps;
            let up = loss_of(&mut net);
            net.layers[layer].w[(i, j)] = orig - eps;
            let down = loss_of(&mut net);
            net.layers[layer].w[(i, j)] = orig;
            let numeric = (up - down) / (2.0 * eps);
            assert!(
                (analytic - numeric).abs() < 2e-3,
                "layer {layer} w[{i},{j}]: {analytic} vs {numeric}"
            );
        }
        // Input gradient: nudge x[1][0].
        let mut xp = x.clone();
        xp[(1, 0)] += eps;
        let mut xm = x.clone();
        xm[(1, 0)] -= eps;
        let mut loss_at = |x: &Array2<f32>| {
            let y = net.forward(x.view()).to_owned();
            let mut g = Array2::zeros(y.raw_dim());
            softmax_cross_entropy(y.view(), &labels, &mut g.view_mut())
        };
        let numeric = (loss_at(&xp) - loss_at(&xm)) / (2.0 * eps);
        assert!(
            (dx[(1, 0)] - numeric).abs() < 2e-3,
            "{} vs {numeric}",
            dx[(1, 0)]
        );
    }

    #[test]
    fn adam_learns_xor_and_is_deterministic() {
        let x = array![[0f32, 0.], [0., 1.], [1., 0.], [1., 1.]];
        let labels = [0usize, 1, 1, 0];
        let train = || {
            let mut net = Mlp::new(&[2, 16, 2], &[Act::LeakyRelu, Act::Identity], 4, 3);
            let mut g = Array2::zeros((4, 2));
            let opt = Adam {
                lr: 0.05,
                ..Adam::DEFAULT
            };
            for _ in 0..300 {
                let y = net.forward(x.view()).to_owned();
                softmax_cross_entropy(y.view(), &labels, &mut g.view_mut());
                net.backward(g.view(), true, false);
                net.adam_step(opt);
            }
            net
        };
        let mut a = train();
        assert_eq!(argmax_rows(a.predict(x.view()).view()), labels);
        let b = train();
        assert_eq!(a.layers[0].w, b.layers[0].w, "same seed, same weights");
    }

    #[test]
    fn bce_gradient_is_sigmoid_minus_target() {
        let z = array![[0.0f32], [2.0]];
        let mut g = [0.0; 2];
        let loss = bce_with_logits(z.view(), 1.0, &mut g);
        assert!((loss - (2f32.ln() + (1.0 + (-2f32).exp()).ln()) / 2.0).abs() < 1e-6);
        assert!((g[0] - (0.5 - 1.0) / 2.0).abs() < 1e-6);
    }
}
