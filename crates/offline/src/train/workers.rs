//! The trainer's threads: matrix products and Adam updates split across a
//! fixed number of threads, with the same result for a given thread count.
//!
//! How the work is split: each matrix product `C = α·A·B + β·C` is cut into
//! [`BLOCKS_PER_THREAD`] blocks per thread of C's columns (or of its rows,
//! when C is taller than it is wide), and each block is one single-threaded
//! `general_mat_mul` (the `matrixmultiply` kernels) on whichever thread takes
//! it. No element of C is shared between threads and each one is summed over
//! the inner dimension by the same kernel in the same order whatever the
//! split, so the result does not depend on which thread ran which block, nor on
//! timing: a seed and a thread count give the same weights bit for bit. The
//! cuts fall on multiples of [`ALIGN`], a multiple of every `matrixmultiply`
//! micro-kernel's tile, so the tiles and their order are those of the whole
//! product and (measured: `gan::tests`) the weights are the same for any
//! thread count on the same machine.
//!
//! Why this and not `matrixmultiply`'s own `threading` feature: that feature
//! reads its thread count once per process from `MATMUL_NUM_THREADS`, so a
//! `--threads` setting could not reach it; with the trainer's batches of 32
//! rows it splits only the micro-kernel loop and packs each weight matrix on
//! one thread, and packing is a quarter of the single-threaded step
//! (`perf`, 15,000 GAN iterations). Here each thread packs its own block.
//!
//! A training loop runs inside [`Workers::run`], on one thread of a rayon pool
//! of `threads`: each product's blocks are queued there, that thread works
//! through them and the pool's other threads take them from the other end
//! (rayon's work stealing; idle threads spin a little before they sleep). Handing blocks from a thread outside the pool
//! instead (rayon's `in_place_scope`) measured 2 threads 1.12× slower than 1
//! with other builds on the machine: each hand-off put the caller to sleep on
//! a lock and woke it (0.4 ms of system time an iteration). Products too
//! small to pay for a hand-off run on the calling thread.

use std::sync::Arc;

use ndarray::linalg::general_mat_mul;
use ndarray::{ArrayView2, ArrayViewMut2, Axis};

/// Block boundaries fall on multiples of this many rows or columns: the
/// largest `matrixmultiply` f32 tile side (16, AVX-512) times 4, which also
/// matches its row blocking (`MC` = 64).
pub(crate) const ALIGN: usize = 64;

/// Blocks per thread of each product (and parts of each Adam pass). With
/// one block per thread, 2 threads measured 1.18× slower than the one-thread
/// trainer over 15,000 GAN iterations (median of 3 pairs, 0.92–1.58) while
/// other builds loaded the machine: each of the ~30 products an iteration
/// waited for its slower thread whenever the scheduler had taken that
/// thread's core. With several blocks each, a running thread takes the blocks
/// of one that is not; under the same load 2 threads were still no faster
/// than 1 (1,500 iterations: A/B 1.09, 0.79–1.55). With a core free, 2
/// threads (one block each) were 1.35× faster than 1 (`cargo bench --bench
/// train_step`).
pub(crate) const BLOCKS_PER_THREAD: usize = 4;

/// Below this many multiply-adds (`m·k·n`) a product runs on the caller:
/// handing a block to another thread costs a few microseconds.
const MIN_SPLIT_WORK: usize = 1 << 18;

/// A fixed number of threads for the trainer's arithmetic.
#[derive(Clone, Debug)]
pub struct Workers {
    threads: usize,
    /// The pool of `threads` threads (`None` for one thread).
    helpers: Option<Arc<rayon::ThreadPool>>,
}

impl Default for Workers {
    fn default() -> Workers {
        Workers::single()
    }
}

impl Workers {
    /// Everything on the calling thread.
    pub fn single() -> Workers {
        Workers {
            threads: 1,
            helpers: None,
        }
    }

    /// `threads` threads (0 counts as 1; 1 runs everything on the caller).
    pub fn new(threads: usize) -> Workers {
        let threads = threads.max(1);
        if threads == 1 {
            return Workers::single();
        }
        let helpers = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .thread_name(|i| format!("train-{i}"))
            .build()
            .expect("the trainer's helper threads start");
        Workers {
            threads,
            helpers: Some(Arc::new(helpers)),
        }
    }

    /// The machine's available cores (at least 1): the default thread count.
    pub fn available() -> usize {
        std::thread::available_parallelism().map_or(1, |n| n.get())
    }

    pub fn threads(&self) -> usize {
        self.threads
    }

    /// Runs `f` (a training loop) on one of the pool's threads, so that its
    /// products hand blocks to the others cheaply; on the caller for one
    /// thread.
    pub(crate) fn run<R: Send>(&self, f: impl FnOnce() -> R + Send) -> R {
        match &self.helpers {
            Some(pool) => pool.install(f),
            None => f(),
        }
    }

    /// Runs `first` here and each of `rest` on another thread of the pool,
    /// and returns when all are done.
    fn fork<'s>(
        pool: &rayon::ThreadPool,
        first: impl FnOnce() + Send + 's,
        rest: impl FnOnce(&rayon::Scope<'s>) + Send + 's,
    ) {
        if pool.current_thread_index().is_some() {
            rayon::scope(|scope| {
                rest(scope);
                first();
            });
        } else {
            pool.in_place_scope(|scope| {
                rest(scope);
                first();
            });
        }
    }

    /// `c = alpha·a·b + beta·c`, split across the threads.
    pub(crate) fn gemm(
        &self,
        alpha: f32,
        a: &ArrayView2<f32>,
        b: &ArrayView2<f32>,
        beta: f32,
        c: &mut ArrayViewMut2<f32>,
    ) {
        let (m, n) = c.dim();
        let k = a.ncols();
        let Some(pool) = self
            .helpers
            .as_ref()
            .filter(|_| m * k * n >= MIN_SPLIT_WORK)
        else {
            general_mat_mul(alpha, a, b, beta, c);
            return;
        };
        // Split the longer side of C: its blocks are then the largest.
        let (axis, len) = if n >= m { (Axis(1), n) } else { (Axis(0), m) };
        let block = len
            .div_ceil(self.threads * BLOCKS_PER_THREAD)
            .next_multiple_of(ALIGN);
        if block >= len {
            general_mat_mul(alpha, a, b, beta, c);
            return;
        }
        let mut blocks = c.axis_chunks_iter_mut(axis, block).enumerate();
        let (_, mut first) = blocks.next().expect("at least one block");
        // A block of C's columns needs the same columns of b; of its rows,
        // the same rows of a.
        let operands = |i: usize, len: usize| {
            let range = i * block..i * block + len;
            if axis == Axis(1) {
                (a.view(), b.slice_axis(Axis(1), range.into()))
            } else {
                (a.slice_axis(Axis(0), range.into()), b.view())
            }
        };
        let (a0, b0) = operands(0, first.len_of(axis));
        Workers::fork(
            pool,
            move || general_mat_mul(alpha, &a0, &b0, beta, &mut first),
            |scope| {
                for (i, mut part) in blocks {
                    let (a, b) = operands(i, part.len_of(axis));
                    scope.spawn(move |_| general_mat_mul(alpha, &a, &b, beta, &mut part));
                }
            },
        );
    }

    /// Runs `f` on `threads` disjoint, contiguous parts of the slices (all of
    /// the same length) at once; `f` must treat elements independently.
    pub(crate) fn for_parts<F>(&self, p: &mut [f32], g: &[f32], m: &mut [f32], v: &mut [f32], f: F)
    where
        F: Fn(&mut [f32], &[f32], &mut [f32], &mut [f32]) + Sync,
    {
        let len = p.len();
        let Some(pool) = self.helpers.as_ref().filter(|_| len >= 1 << 14) else {
            f(p, g, m, v);
            return;
        };
        let part = len
            .div_ceil(self.threads * BLOCKS_PER_THREAD)
            .next_multiple_of(ALIGN);
        let mut parts = p
            .chunks_mut(part)
            .zip(g.chunks(part))
            .zip(m.chunks_mut(part))
            .zip(v.chunks_mut(part));
        let (((p0, g0), m0), v0) = parts.next().expect("at least one part");
        let f = &f;
        Workers::fork(
            pool,
            move || f(p0, g0, m0, v0),
            |scope| {
                for (((p, g), m), v) in parts {
                    scope.spawn(move |_| f(p, g, m, v));
                }
            },
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ndarray::Array2;

    fn filled(rows: usize, cols: usize, seed: u32) -> Array2<f32> {
        Array2::from_shape_fn((rows, cols), |(i, j)| {
            let x = (i as u32 * 7919 + j as u32 * 104_729 + seed).wrapping_mul(2_654_435_761);
            (x >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        })
    }

    /// A split product equals the single-threaded one bit for bit, for wide
    /// and tall outputs, transposed operands and β = 1.
    #[test]
    fn split_products_equal_the_whole() {
        for (m, k, n) in [
            (32, 512, 1024),
            (32, 1024, 414),
            (1024, 32, 414),
            (64, 414, 512),
        ] {
            let a = filled(m, k, 1);
            let bt = filled(n, k, 2);
            let c0 = filled(m, n, 3);
            let mut whole = c0.clone();
            general_mat_mul(1.0, &a.view(), &bt.t(), 1.0, &mut whole.view_mut());
            for threads in [2, 3, 4] {
                let mut split = c0.clone();
                Workers::new(threads).gemm(1.0, &a.view(), &bt.t(), 1.0, &mut split.view_mut());
                assert_eq!(split, whole, "{m}×{k}×{n} on {threads} threads");
            }
        }
    }
}
