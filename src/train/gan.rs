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
//! One iteration = one discriminator step on `batch` real and `batch` fake frames
//! (one matrix product of `2·batch` rows) then one generator step on the same
//! fakes. Everything is drawn from one seeded RNG: a seed gives the same weights,
//! bit for bit, on the same machine and build.

use ndarray::{Array2, s};
use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, StandardNormal};

use super::mlp::{Act, Adam, Mlp, bce_with_logits};

/// The discriminator's target for real frames: one-sided label smoothing.
/// With a target of 1 the discriminator grows overconfident, the generator's
/// tanh saturates and, after a few thousand iterations, it collapses to one
/// frame; 0.9 keeps it learning (measured on the sample site's walks).
pub const REAL_LABEL: f32 = 0.9;

/// Noise dimension of the generator (the paper's 100).
pub const NOISE_DIM: usize = 100;
/// Hidden widths of the generator and the discriminator.
pub const GENERATOR_HIDDEN: [usize; 3] = [256, 512, 1024];
pub const DISCRIMINATOR_HIDDEN: [usize; 2] = [512, 256];

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
}

/// Losses at one iteration, for progress output.
#[derive(Clone, Copy, Debug, Default)]
pub struct GanLosses {
    pub discriminator: f32,
    pub generator: f32,
}

pub struct Gan {
    pub generator: Mlp,
    pub discriminator: Mlp,
}

/// Trains a GAN on `data`; `progress` is called after every iteration.
pub fn train(data: &GanData, config: GanConfig, progress: impl FnMut(usize, GanLosses)) -> Gan {
    match train_with_checkpoints(data, config, None, progress, |_, _| {
        Ok::<(), std::convert::Infallible>(())
    }) {
        Ok(gan) => gan,
        Err(never) => match never {},
    }
}

/// [`train`], also handing the networks to `checkpoint` after every
/// `every`-th iteration (`None`: never); the first error it returns stops
/// training.
pub fn train_with_checkpoints<E>(
    data: &GanData,
    config: GanConfig,
    every: Option<std::num::NonZeroUsize>,
    mut progress: impl FnMut(usize, GanLosses),
    mut checkpoint: impl FnMut(usize, &Gan) -> Result<(), E>,
) -> Result<Gan, E> {
    let n = data.frames.nrows();
    assert!(n > 0 && config.batch > 0, "a GAN needs data and a batch");
    let cells = data.frames.ncols();
    let cond_dim = data.conditions.as_ref().map_or(0, |c| c.ncols());
    let batch = config.batch;
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(config.seed);

    let g_sizes = [
        &[NOISE_DIM + cond_dim][..],
        &GENERATOR_HIDDEN[..],
        &[cells][..],
    ]
    .concat();
    let d_sizes = [&[cells + cond_dim][..], &DISCRIMINATOR_HIDDEN[..], &[1][..]].concat();
    let generator = Mlp::new(
        &g_sizes,
        &[Act::LeakyRelu, Act::LeakyRelu, Act::LeakyRelu, Act::Tanh],
        batch,
        rng.random(),
    );
    // The discriminator sees real and fake together: 2·batch rows.
    let discriminator = Mlp::new(
        &d_sizes,
        &[Act::LeakyRelu, Act::LeakyRelu, Act::Identity],
        2 * batch,
        rng.random(),
    );
    let mut gan = Gan {
        generator,
        discriminator,
    };

    let mut g_input = Array2::<f32>::zeros((batch, NOISE_DIM + cond_dim));
    let mut d_input = Array2::<f32>::zeros((2 * batch, cells + cond_dim));
    let mut d_grad = Array2::<f32>::zeros((2 * batch, 1));
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
        let d_fake = gan
            .discriminator
            .backward(d_grad.slice(s![..batch, ..]), false, true);
        gan.generator
            .backward(d_fake.slice(s![.., ..cells]), true, false);
        gan.generator.adam_step(Adam::GAN);

        progress(
            iteration,
            GanLosses {
                discriminator: d_loss,
                generator: g_loss,
            },
        );
        if every.is_some_and(|k| iteration % k == 0) {
            checkpoint(iteration, &gan)?;
        }
    }
    Ok(gan)
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

    #[test]
    fn training_is_deterministic_for_a_seed_and_reports_finite_losses() {
        let data = toy();
        let config = GanConfig {
            iterations: 5,
            batch: 4,
            seed: 11,
        };
        let mut last = GanLosses::default();
        let a = train(&data, config, |_, l| last = l);
        assert!(last.discriminator.is_finite() && last.generator.is_finite());
        let b = train(&data, config, |_, _| {});
        assert_eq!(a.generator.layers[3].w, b.generator.layers[3].w);
        let c = train(&data, GanConfig { seed: 12, ..config }, |_, _| {});
        assert_ne!(a.generator.layers[3].w, c.generator.layers[3].w);
    }

    #[test]
    fn checkpoints_come_every_k_iterations_without_changing_training() {
        let data = toy();
        let config = GanConfig {
            iterations: 7,
            batch: 4,
            seed: 3,
        };
        let every = std::num::NonZeroUsize::new(3);
        let mut seen = Vec::new();
        let with = train_with_checkpoints(
            &data,
            config,
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
            },
            |_, _| {},
        );
        assert_eq!(gan.generator.inputs(), NOISE_DIM + 5);
        assert_eq!(gan.discriminator.inputs(), 9 + 5);
    }
}
