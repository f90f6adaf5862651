//! Training softmax classifiers (the path classifier and the localization cell
//! classifier) and measuring them on held-out rows.
//!
//! Hidden layers use LeakyReLU(0.2); the output layer gives logits, trained
//! with softmax cross-entropy and Adam (Keras defaults); the exported graph
//! ends in `Softmax` or `LogSoftmax`. Batches are drawn with replacement from
//! the training rows by a seeded RNG, so a seed gives the same weights.

use ndarray::{Array2, ArrayView2, s};
use rand::rngs::Xoshiro256PlusPlus;
use rand::seq::SliceRandom;
use rand::{RngExt, SeedableRng};

use super::mlp::{Act, Adam, Mlp, argmax_rows, softmax_cross_entropy};
use super::workers::Workers;

#[derive(Clone, Debug)]
pub(crate) struct ClassifierConfig {
    pub hidden: Vec<usize>,
    pub iterations: usize,
    pub batch: usize,
    pub seed: u64,
    pub adam: Adam,
    /// Threads for the arithmetic ([`Workers`]).
    pub threads: usize,
}

/// Trains on the rows `train_rows` of `x` with `labels` (one per row of `x`);
/// `progress` gets the iteration and the batch loss.
pub(crate) fn train(
    x: ArrayView2<f32>,
    labels: &[usize],
    classes: usize,
    train_rows: &[usize],
    config: &ClassifierConfig,
    mut progress: impl FnMut(usize, f32) + Send,
) -> Mlp {
    assert!(!train_rows.is_empty(), "no training rows");
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(config.seed);
    let sizes = [&[x.ncols()][..], &config.hidden, &[classes]].concat();
    let mut acts = vec![Act::LeakyRelu; config.hidden.len()];
    acts.push(Act::Identity);
    let workers = Workers::new(config.threads);
    let mut net = Mlp::new(&sizes, &acts, config.batch, rng.random()).with_workers(workers.clone());
    // The loop runs on one of the workers' threads (`Workers::run`).
    workers.run(move || {
        let mut batch_x = Array2::zeros((config.batch, x.ncols()));
        let mut batch_labels = vec![0; config.batch];
        let mut grad = Array2::zeros((config.batch, classes));
        for iteration in 1..=config.iterations {
            for (row, label) in batch_labels.iter_mut().enumerate() {
                let pick = train_rows[rng.random_range(0..train_rows.len())];
                batch_x.row_mut(row).assign(&x.row(pick));
                *label = labels[pick];
            }
            let logits = net.forward(batch_x.view());
            let loss = softmax_cross_entropy(logits, &batch_labels, &mut grad.view_mut());
            net.backward(grad.view(), true, false);
            net.adam_step(config.adam);
            progress(iteration, loss);
        }
        net
    })
}

/// Share of `rows` whose most likely class is not their label.
pub(crate) fn error_rate(
    net: &mut Mlp,
    x: ArrayView2<f32>,
    labels: &[usize],
    rows: &[usize],
) -> f64 {
    if rows.is_empty() {
        return f64::NAN;
    }
    let predicted = predict(net, x, rows);
    let wrong = rows
        .iter()
        .zip(&predicted)
        .filter(|&(&r, &p)| labels[r] != p)
        .count();
    wrong as f64 / rows.len() as f64
}

/// The most likely class of each of `rows`.
pub(crate) fn predict(net: &mut Mlp, x: ArrayView2<f32>, rows: &[usize]) -> Vec<usize> {
    let mut picked = Array2::zeros((rows.len(), x.ncols()));
    for (i, &r) in rows.iter().enumerate() {
        picked.slice_mut(s![i, ..]).assign(&x.row(r));
    }
    argmax_rows(net.predict(picked.view()).view())
}

/// Splits rows into (train, held-out) by group: every group goes wholly to one
/// side, so rows that are near-copies of each other (a surveyor's session, one
/// walker's repeats) cannot leak across. Within each stratum (e.g. class),
/// about `heldout_share` of the groups are held out, at least one when the
/// stratum has two or more groups.
pub(crate) fn split_by_group(
    strata: &[usize],
    groups: &[usize],
    heldout_share: f64,
    seed: u64,
) -> (Vec<usize>, Vec<usize>) {
    use std::collections::BTreeMap;
    let mut by_stratum: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
    for (&s, &g) in strata.iter().zip(groups) {
        let list = by_stratum.entry(s).or_default();
        if !list.contains(&g) {
            list.push(g);
        }
    }
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(seed);
    let mut held = std::collections::BTreeSet::new();
    for (_, mut list) in by_stratum {
        list.sort_unstable();
        list.shuffle(&mut rng);
        let k = if list.len() < 2 {
            0
        } else {
            ((list.len() as f64 * heldout_share).round() as usize).clamp(1, list.len() - 1)
        };
        held.extend(list.into_iter().take(k));
    }
    (0..groups.len()).partition(|&r| !held.contains(&groups[r]))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn group_split_keeps_groups_whole_and_holds_out_per_stratum() {
        let strata = [0, 0, 0, 0, 1, 1, 1, 1, 1];
        let groups = [1, 1, 2, 3, 4, 4, 5, 6, 7];
        let (train, held) = split_by_group(&strata, &groups, 0.34, 9);
        assert_eq!(train.len() + held.len(), 9);
        for g in 1..=7 {
            let sides: Vec<bool> = (0..9)
                .filter(|&r| groups[r] == g)
                .map(|r| held.contains(&r))
                .collect();
            assert!(sides.windows(2).all(|w| w[0] == w[1]), "group {g} split");
        }
        assert!(held.iter().any(|&r| strata[r] == 0) && held.iter().any(|&r| strata[r] == 1));
        assert_eq!(split_by_group(&strata, &groups, 0.34, 9), (train, held));
    }

    #[test]
    fn learns_separable_classes() {
        // Class = which of 4 inputs is hot, with noise.
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(1);
        let n = 200;
        let labels: Vec<usize> = (0..n).map(|i| i % 4).collect();
        let x = Array2::from_shape_fn((n, 4), |(i, j)| {
            f32::from(u8::from(labels[i] == j)) + rng.random_range(-0.3..0.3)
        });
        let (train_rows, held) = split_by_group(&labels, &(0..n).collect::<Vec<_>>(), 0.2, 2);
        let config = ClassifierConfig {
            hidden: vec![16],
            iterations: 300,
            batch: 16,
            seed: 5,
            adam: Adam::DEFAULT,
            threads: 1,
        };
        let mut net = train(x.view(), &labels, 4, &train_rows, &config, |_, _| {});
        assert_eq!(error_rate(&mut net, x.view(), &labels, &held), 0.0);
    }
}
