//! Training the path GAN: the paper's generator and discriminator, optionally
//! conditioned on the source and destination cells.
//!
//! Architecture (the paper's "Our GAN Configuration"): generator
//! `noise(100) → 256 → 512 → 1024 → W·H`, LeakyReLU(0.2) between layers and tanh
//! out; discriminator `W·H → 512 → 256 → 1`, LeakyReLU(0.2) between layers and a
//! sigmoid out (trained on its logit with binary cross-entropy; the exported
//! graph ends in the sigmoid). Adam with lr 2e-4, β₁ 0.5. Frames are fed as ±1
//! (path cell +1, other cells −1) to match the tanh range.
//!
//! Conditional variant: both networks also see the condition
//! ([`crate::model::condition`]) concatenated to their input: the generator to
//! its noise, the discriminator to the frame. Each iteration, the fake batch is
//! generated for the same conditions as the real batch.
//!
//! Access penalty (not in the paper; off with a weight of 0): the generator's
//! loss also has a hinge that pushes back any cell outside the site's
//! public-access area that a frame lights, which no walk ever does
//! ([`access_penalty`]), ramped in over the run. The adversarial loss learns
//! that only from what the discriminator notices; without the penalty the
//! conditional generator kept lighting a few blocked cells for some pairs.
//!
//! One iteration = one discriminator step on `batch` real and `batch` fake frames
//! (one matrix product of `2·batch` rows) then one generator step on the same
//! fakes. Everything is drawn from one seeded RNG: a seed gives the same weights,
//! bit for bit, on the same machine and build, whatever `GanConfig::threads`
//! ([`Workers`] splits each product by blocks of its output).

use ndarray::{Array2, ArrayView2, s};
use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

use super::mlp::{Act, Adam, Mlp, bce_with_logits};
use super::workers::Workers;

/// The discriminator's target for real frames: one-sided label smoothing.
/// With a target of 1 the discriminator grows overconfident, the generator's
/// tanh saturates and, after a few thousand iterations, it collapses to one
/// frame; 0.9 keeps it learning (measured on the sample site's walks).
pub(crate) const REAL_LABEL: f32 = 0.9;

/// Noise dimension of the generator (the paper's 100).
pub(crate) const NOISE_DIM: usize = 100;
/// Hidden widths of a GAN's generator and discriminator.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Hidden {
    pub generator: &'static [usize],
    pub discriminator: &'static [usize],
}

impl Hidden {
    /// The paper's: `256 → 512 → 1024` and `512 → 256`.
    pub const PAPER: Hidden = Hidden {
        generator: &[256, 512, 1024],
        discriminator: &[512, 256],
    };
}

/// Real paths to learn from.
pub struct GanData {
    /// One row per path, `W·H` values of ±1.
    pub frames: Array2<f32>,
    /// One row per path (the condition encoding) for a conditional GAN.
    pub conditions: Option<Array2<f32>>,
}

#[derive(Clone, Copy, Debug)]
pub struct GanConfig {
    pub iterations: usize,
    pub batch: usize,
    pub seed: u64,
    /// Threads for the matrix products and Adam ([`Workers`]): a seed and a
    /// thread count give the same weights, bit for bit.
    pub threads: usize,
    pub hidden: Hidden,
}

/// A term of the generator's loss beside the adversarial one: how far the
/// generated samples leave the site's public-access area (frames:
/// [`Access`]; lines: [`super::line_access::LineAccess`]).
pub(crate) trait Penalty: Sync {
    /// Its weight λ at the last iteration (it grows linearly, λ·i/N at
    /// iteration i of N); a penalty of weight 0 is off.
    fn weight(&self) -> f32;

    /// The penalty of the generated `out` (tanh outputs, one row per data row
    /// of `picks`) times `weight`; writes its gradient with respect to each
    /// output's pre-activation into `grad` (zero where it does not act).
    fn apply(
        &self,
        out: ArrayView2<f32>,
        picks: &[usize],
        weight: f32,
        grad: &mut Array2<f32>,
    ) -> f32;
}

/// The access penalty's settings: which cells no path may light, and how
/// much lighting them costs.
#[derive(Clone, Debug)]
pub(crate) struct Access {
    /// Frame indices of the cells outside the public-access area (the site's
    /// non-walkable cells).
    pub blocked: Vec<usize>,
    /// Weight λ of [`access_penalty`] in the generator's loss at the last
    /// iteration (it grows linearly, λ·i/N at iteration i of N); 0 trains the paper's
    /// plain loss (the same weights, bit for bit, as no penalty).
    pub weight: f32,
}

impl Penalty for Access {
    fn weight(&self) -> f32 {
        if self.blocked.is_empty() {
            0.0
        } else {
            self.weight
        }
    }

    fn apply(
        &self,
        out: ArrayView2<f32>,
        _picks: &[usize],
        weight: f32,
        grad: &mut Array2<f32>,
    ) -> f32 {
        access_penalty(out, &self.blocked, weight, grad)
    }
}

/// Losses at one iteration, for progress output.
#[derive(Clone, Copy, Debug, Default)]
pub struct GanLosses {
    pub discriminator: f32,
    /// The adversarial part of the generator's loss.
    pub generator: f32,
    /// The access penalty, weighted (0 when off).
    pub access: f32,
}

pub struct Gan {
    pub generator: Mlp,
    pub discriminator: Mlp,
}

/// Trains a GAN on `data` with the paper's loss; `progress` is called after
/// every iteration.
pub fn train(
    data: &GanData,
    config: GanConfig,
    progress: impl FnMut(usize, GanLosses) + Send,
) -> Gan {
    match train_with_checkpoints(data, config, None, None, progress, |_, _| {
        Ok::<(), std::convert::Infallible>(())
    }) {
        Ok(gan) => gan,
        Err(never) => match never {},
    }
}

/// [`train`], with the `access` penalty in the generator's loss (`None`:
/// none, as a weight of 0), and handing the networks to `checkpoint` after every `every`-th
/// iteration (`None`: never); the first error it returns stops training.
pub(crate) fn train_with_checkpoints<E: Send>(
    data: &GanData,
    config: GanConfig,
    access: Option<&dyn Penalty>,
    every: Option<std::num::NonZeroUsize>,
    mut progress: impl FnMut(usize, GanLosses) + Send,
    mut checkpoint: impl FnMut(usize, &Gan) -> Result<(), E> + Send,
) -> Result<Gan, E> {
    let n = data.frames.nrows();
    assert!(n > 0 && config.batch > 0, "a GAN needs data and a batch");
    let cells = data.frames.ncols();
    let cond_dim = data.conditions.as_ref().map_or(0, |c| c.ncols());
    let batch = config.batch;
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(config.seed);
    let workers = Workers::new(config.threads);

    let hidden = config.hidden;
    let g_sizes = [&[NOISE_DIM + cond_dim][..], hidden.generator, &[cells][..]].concat();
    let d_sizes = [&[cells + cond_dim][..], hidden.discriminator, &[1][..]].concat();
    // LeakyReLU after every hidden layer; tanh out of the generator, the
    // discriminator's logit as it is.
    let acts = |hidden: &[usize], last| {
        let mut acts = vec![Act::LeakyRelu; hidden.len()];
        acts.push(last);
        acts
    };
    let generator = Mlp::new(
        &g_sizes,
        &acts(hidden.generator, Act::Tanh),
        batch,
        rng.random(),
    )
    .with_workers(workers.clone());
    // The discriminator sees real and fake together: 2·batch rows.
    let discriminator = Mlp::new(
        &d_sizes,
        &acts(hidden.discriminator, Act::Identity),
        2 * batch,
        rng.random(),
    )
    .with_workers(workers.clone());
    let mut gan = Gan {
        generator,
        discriminator,
    };

    // The loop runs on one of the workers' threads (`Workers::run`).
    workers.run(move || {
        let mut g_input = Array2::<f32>::zeros((batch, NOISE_DIM + cond_dim));
        let mut d_input = Array2::<f32>::zeros((2 * batch, cells + cond_dim));
        let mut d_grad = Array2::<f32>::zeros((2 * batch, 1));
        let access = access.filter(|a| a.weight() != 0.0);
        // Zero where the penalty does not act; the rest is rewritten every
        // iteration.
        let mut access_grad = Array2::<f32>::zeros((batch, cells));
        let mut picks = vec![0usize; batch];
        for iteration in 1..=config.iterations {
            for p in &mut picks {
                *p = rng.random_range(0..n);
            }
            for (row, &p) in picks.iter().enumerate() {
                d_input
                    .slice_mut(s![row, ..cells])
                    .assign(&data.frames.row(p));
                if let Some(cond) = &data.conditions {
                    d_input.slice_mut(s![row, cells..]).assign(&cond.row(p));
                    d_input
                        .slice_mut(s![batch + row, cells..])
                        .assign(&cond.row(p));
                    g_input.slice_mut(s![row, NOISE_DIM..]).assign(&cond.row(p));
                }
            }
            for v in g_input.slice_mut(s![.., ..NOISE_DIM]) {
                *v = StandardNormal.sample(&mut rng);
            }

            // Discriminator step: real rows → REAL_LABEL, fake rows → 0.
            let fake = gan.generator.forward(g_input.view());
            d_input.slice_mut(s![batch.., ..cells]).assign(&fake);
            let logits = gan.discriminator.forward(d_input.view());
            let grad = d_grad.as_slice_mut().expect("contiguous");
            let (real_grad, fake_grad) = grad.split_at_mut(batch);
            let d_loss = bce_with_logits(logits.slice(s![..batch, ..]), REAL_LABEL, real_grad)
                + bce_with_logits(logits.slice(s![batch.., ..]), 0.0, fake_grad);
            gan.discriminator.backward(d_grad.view(), true, false);
            gan.discriminator.adam_step(Adam::GAN);

            // Generator step: make the updated discriminator call the fakes real.
            let logits = gan.discriminator.forward(d_input.slice(s![batch.., ..]));
            let grad = &mut d_grad.as_slice_mut().expect("contiguous")[..batch];
            let g_loss = bce_with_logits(logits, 1.0, grad);
            // The fakes the discriminator just judged are the generator's output.
            let access_loss = access.map_or(0.0, |a| {
                a.apply(
                    d_input.slice(s![batch.., ..cells]),
                    &picks,
                    // Ramped in from 0: at the start every output sits near 0 and
                    // every blocked cell counts as lit, so the full weight would
                    // drive all outputs to saturated off before the adversarial
                    // loss taught the generator any path (it then never learns
                    // one: tanh's gradient vanishes there).
                    a.weight() * iteration as f32 / config.iterations as f32,
                    &mut access_grad,
                )
            });
            let d_fake = gan
                .discriminator
                .backward(d_grad.slice(s![..batch, ..]), false, true);
            gan.generator.backward_with_logit_grad(
                d_fake.slice(s![.., ..cells]),
                access.map(|_| access_grad.view()),
                true,
                false,
            );
            gan.generator.adam_step(Adam::GAN);

            progress(
                iteration,
                GanLosses {
                    discriminator: d_loss,
                    generator: g_loss,
                    access: access_loss,
                },
            );
            if every.is_some_and(|k| iteration % k == 0) {
                checkpoint(iteration, &gan)?;
            }
        }
        Ok(gan)
    })
}

/// Output above which a blocked cell counts as lit for [`access_penalty`]:
/// halfway between off (−1) and the planner's brightness threshold (0), so a
/// cell is pushed back before it reaches a route.
pub(crate) const ACCESS_MARGIN: f32 = -0.5;

/// The access penalty of a batch of generated frames `out` (tanh outputs): a
/// hinge on each `blocked` cell's pre-activation `a = atanh(out)`,
/// `max(0, a − atanh(ACCESS_MARGIN))`, summed over those cells, averaged over
/// frames and times `weight`. Writes its gradient with respect to `a` into the
/// `blocked` columns of `grad` and returns the penalty.
///
/// Why a hinge on `a`: a cell already firmly off costs and pulls nothing, so
/// the penalty acts only on the few cells a frame wrongly lights instead of
/// pressing on all ~300 blocked cells of every frame (a cross-entropy on every
/// blocked cell did, and collapsed the generator before it cleared the worst
/// pair, docs/trajectories.md). On `a` the gradient is a constant `weight /
/// frames` for a lit cell, however saturated (through `out` it would vanish as
/// `1 − out²`).
pub(crate) fn access_penalty(
    out: ArrayView2<f32>,
    blocked: &[usize],
    weight: f32,
    grad: &mut Array2<f32>,
) -> f32 {
    let scale = weight / out.nrows() as f32;
    let threshold = ACCESS_MARGIN.atanh();
    // A saturated output rounds to 1.0 in f32, whose atanh is infinite;
    // clamped just below, its term stays finite (~8.3).
    let edge = 1.0 - f32::EPSILON;
    let mut loss = 0.0;
    for (row, mut g) in out.rows().into_iter().zip(grad.rows_mut()) {
        for &cell in blocked {
            let y = row[cell];
            let lit = y > ACCESS_MARGIN;
            if lit {
                loss += y.min(edge).atanh() - threshold;
            }
            g[cell] = if lit { scale } else { 0.0 };
        }
    }
    scale * loss
}

#[cfg(test)]
mod tests {
    use super::*;

    fn toy() -> GanData {
        // Two 9-cell "paths": a row and a column.
        let mut frames = Array2::from_elem((8, 9), -1.0f32);
        for i in 0..8 {
            if i % 2 == 0 {
                frames.slice_mut(s![i, 3..6]).fill(1.0);
            } else {
                for c in [1, 4, 7] {
                    frames[(i, c)] = 1.0;
                }
            }
        }
        GanData {
            frames,
            conditions: None,
        }
    }

    /// The toy's corners are outside its "site": no path lights them.
    fn corners(weight: f32) -> Access {
        Access {
            blocked: vec![0, 2, 6, 8],
            weight,
        }
    }

    fn train_penalized(
        data: &GanData,
        config: GanConfig,
        access: &Access,
        progress: impl FnMut(usize, GanLosses) + Send,
    ) -> Gan {
        train_with_checkpoints(data, config, Some(access), None, progress, |_, _| {
            Ok::<(), ()>(())
        })
        .unwrap()
    }

    #[test]
    fn training_is_deterministic_for_a_seed_and_reports_finite_losses() {
        let data = toy();
        let config = GanConfig {
            iterations: 5,
            batch: 4,
            seed: 11,
            threads: 1,
            hidden: Hidden::PAPER,
        };
        let mut last = GanLosses::default();
        let a = train(&data, config, |_, l| last = l);
        assert!(last.discriminator.is_finite() && last.generator.is_finite());
        let b = train(&data, config, |_, _| {});
        assert_eq!(a.generator.layers[3].w, b.generator.layers[3].w);
        let c = train(&data, GanConfig { seed: 12, ..config }, |_, _| {});
        assert_ne!(a.generator.layers[3].w, c.generator.layers[3].w);
    }

    /// Frames of the sample site's size (23 × 18 cells), big enough that
    /// every layer's products are split across threads ([`Workers`]).
    fn site_sized() -> GanData {
        let cells = 23 * 18;
        let frames =
            Array2::from_shape_fn(
                (40, cells),
                |(i, c)| {
                    if (c + 3 * i) % 7 < 2 { 1.0 } else { -1.0 }
                },
            );
        GanData {
            frames,
            conditions: None,
        }
    }

    fn weights(gan: &Gan) -> Vec<Array2<f32>> {
        let nets = [&gan.generator, &gan.discriminator];
        nets.iter()
            .flat_map(|net| net.layers.iter().map(|l| l.w.clone()))
            .collect()
    }

    /// Training on several threads gives the same weights, bit for bit, run
    /// after run, and the same as on one thread: every product is split by
    /// blocks of its output, each summed as the whole product sums it.
    #[test]
    fn threads_give_the_same_weights_run_after_run() {
        let data = site_sized();
        let config = |threads| GanConfig {
            iterations: 3,
            batch: 32,
            seed: 9,
            threads,
            hidden: Hidden::PAPER,
        };
        let two = weights(&train(&data, config(2), |_, _| {}));
        assert_eq!(two, weights(&train(&data, config(2), |_, _| {})));
        assert_eq!(two, weights(&train(&data, config(1), |_, _| {})));
        assert_eq!(two, weights(&train(&data, config(3), |_, _| {})));
    }

    #[test]
    fn checkpoints_come_every_k_iterations_without_changing_training() {
        let data = toy();
        let config = GanConfig {
            iterations: 7,
            batch: 4,
            seed: 3,
            threads: 1,
            hidden: Hidden::PAPER,
        };
        let every = std::num::NonZeroUsize::new(3);
        let mut seen = Vec::new();
        let with = train_with_checkpoints(
            &data,
            config,
            None,
            every,
            |_, _| {},
            |i, gan| {
                seen.push((i, gan.generator.layers[3].w.clone()));
                Ok::<(), ()>(())
            },
        )
        .unwrap();
        assert_eq!(seen.iter().map(|s| s.0).collect::<Vec<_>>(), [3, 6]);
        let plain = train(&data, config, |_, _| {});
        assert_eq!(with.generator.layers[3].w, plain.generator.layers[3].w);
        // The checkpoint after 6 iterations is what a 6-iteration run gives.
        let six = train(
            &data,
            GanConfig {
                iterations: 6,
                ..config
            },
            |_, _| {},
        );
        assert_eq!(seen[1].1, six.generator.layers[3].w);
        // The first failing checkpoint stops training with its error.
        let mut calls = 0;
        let failed = train_with_checkpoints(
            &data,
            config,
            None,
            std::num::NonZeroUsize::new(2),
            |_, _| {},
            |i, _| {
                calls += 1;
                if i == 4 { Err(i) } else { Ok(()) }
            },
        );
        assert_eq!(failed.err(), Some(4));
        assert_eq!(calls, 2);
    }

    /// The penalty's gradient, fed in at the pre-activation, is the gradient of
    /// the penalty it returns: checked through the whole network against
    /// finite differences of the input.
    #[test]
    fn access_penalty_gradient_matches_finite_differences() {
        let mut net = Mlp::new(&[3, 5, 4], &[Act::LeakyRelu, Act::Tanh], 2, 5);
        let x = ndarray::array![[0.4f32, -0.7, 1.2], [-1.1, 0.3, 0.6]];
        let blocked = [0, 2, 3];
        let mut grad = Array2::zeros((2, 4));
        let penalty_at = |net: &mut Mlp, x: &Array2<f32>, grad: &mut Array2<f32>| {
            let out = net.forward(x.view()).to_owned();
            access_penalty(out.view(), &blocked, 1.5, grad)
        };
        penalty_at(&mut net, &x, &mut grad);
        assert_eq!(
            grad.column(1).sum(),
            0.0,
            "only blocked columns get a gradient"
        );
        let zero = Array2::zeros((2, 4));
        let dx = net
            .backward_with_logit_grad(zero.view(), Some(grad.view()), false, true)
            .to_owned();
        let eps = 1e-2;
        for (r, c) in [(0, 0), (1, 2)] {
            let (mut up, mut down) = (x.clone(), x.clone());
            up[(r, c)] += eps;
            down[(r, c)] -= eps;
            let numeric = (penalty_at(&mut net, &up, &mut grad.clone())
                - penalty_at(&mut net, &down, &mut grad.clone()))
                / (2.0 * eps);
            assert!(
                (dx[(r, c)] - numeric).abs() < 2e-3,
                "x[{r},{c}]: {} vs {numeric}",
                dx[(r, c)]
            );
        }
    }

    /// A saturated wrongly lit cell still gets the full gradient; a cell below
    /// the margin costs and pulls nothing; other columns are left alone.
    #[test]
    fn access_penalty_acts_on_lit_cells_only_and_does_not_vanish() {
        let out = ndarray::array![[1.0f32, -1.0, 0.0, -0.6, -0.4, 0.9]];
        let mut grad = Array2::from_elem((1, 6), 7.0);
        let loss = access_penalty(out.view(), &[0, 1, 2, 3, 4], 2.0, &mut grad);
        assert_eq!(grad.row(0).to_vec(), [2.0, 0.0, 2.0, 0.0, 2.0, 7.0]);
        // The hinge on the pre-activation: a = atanh(out), margin atanh(−0.5).
        let margin = 0.5f32.atanh();
        let lit_unsaturated = 2.0 * ((0.0 + margin) + ((-0.4f32).atanh() + margin));
        let saturated = loss - lit_unsaturated;
        assert!(
            saturated.is_finite() && saturated > 2.0 * (0.999f32.atanh() + margin),
            "saturated term {saturated}"
        );
        let off = ndarray::array![[-0.9f32, -0.99]];
        let mut grad = Array2::zeros((1, 2));
        assert_eq!(access_penalty(off.view(), &[0, 1], 2.0, &mut grad), 0.0);
        assert_eq!(grad.sum(), 0.0);
    }

    /// Share of blocked-cell outputs above the penalty's margin, and the
    /// largest one, over 256 generated frames.
    fn blocked_outputs(gan: &mut Gan, blocked: &[usize]) -> (f32, f32) {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(99);
        let noise =
            Array2::from_shape_simple_fn((256, NOISE_DIM), || StandardNormal.sample(&mut rng));
        let out = gan.generator.predict(noise.view());
        let values: Vec<f32> = out
            .rows()
            .into_iter()
            .flat_map(|row| blocked.iter().map(move |&c| row[c]))
            .collect();
        let above = values.iter().filter(|&&v| v > ACCESS_MARGIN).count();
        (
            above as f32 / values.len() as f32,
            values.iter().copied().fold(f32::MIN, f32::max),
        )
    }

    #[test]
    fn the_access_penalty_drives_blocked_cells_off() {
        let data = toy();
        let config = GanConfig {
            // Short enough that the plain GAN still lights the corners.
            iterations: 80,
            batch: 4,
            seed: 5,
            threads: 1,
            hidden: Hidden::PAPER,
        };
        let access = corners(1.0);
        let mut plain = train(&data, config, |_, _| {});
        // The penalty as reported is ramped (weight λ·i/N); undone here, so
        // first and last compare what the frames light.
        let (mut first, mut last) = (None, 0.0);
        let mut penalized = train_penalized(&data, config, &access, |i, l| {
            let unramped = l.access * config.iterations as f32 / i as f32;
            first.get_or_insert(unramped);
            last = unramped;
        });
        let (plain_above, _) = blocked_outputs(&mut plain, &access.blocked);
        let (above, max) = blocked_outputs(&mut penalized, &access.blocked);
        assert!(
            plain_above > 0.1,
            "without the penalty: {plain_above} above the margin"
        );
        assert!(max < 0.0, "a blocked cell is lit: {max}");
        assert!(
            above < plain_above / 2.0,
            "{above} above the margin vs {plain_above} without"
        );
        let first = first.expect("progress was called");
        assert!(last < first / 2.0, "penalty {first} → {last}");
    }

    #[test]
    fn a_zero_access_weight_is_the_plain_loss_bit_for_bit() {
        let data = toy();
        let config = GanConfig {
            iterations: 6,
            batch: 4,
            seed: 2,
            threads: 1,
            hidden: Hidden::PAPER,
        };
        let mut losses = Vec::new();
        let plain = train(&data, config, |_, _| {});
        let zero = train_penalized(&data, config, &corners(0.0), |_, l| losses.push(l.access));
        assert!(losses.iter().all(|&l| l == 0.0));
        for (a, b) in plain.generator.layers.iter().zip(&zero.generator.layers) {
            assert_eq!((&a.w, &a.b), (&b.w, &b.b));
        }
        for (a, b) in plain
            .discriminator
            .layers
            .iter()
            .zip(&zero.discriminator.layers)
        {
            assert_eq!((&a.w, &a.b), (&b.w, &b.b));
        }
        let weighted = train_penalized(&data, config, &corners(0.5), |_, _| {});
        assert_ne!(plain.generator.layers[3].w, weighted.generator.layers[3].w);
    }

    #[test]
    fn conditional_networks_take_the_condition_as_input() {
        let mut data = toy();
        data.conditions = Some(Array2::from_elem((8, 5), 0.5));
        let gan = train(
            &data,
            GanConfig {
                iterations: 2,
                batch: 4,
                seed: 1,
                threads: 1,
                hidden: Hidden::PAPER,
            },
            |_, _| {},
        );
        assert_eq!(gan.generator.inputs(), NOISE_DIM + 5);
        assert_eq!(gan.discriminator.inputs(), 9 + 5);
    }
}
