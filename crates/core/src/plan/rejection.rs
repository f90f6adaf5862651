//! The paper's Algorithm 1, batched and bounded: generate frames with the
//! unconditional GAN, classify them, and take the first frame whose class is
//! the requested (source, destination) pair.
//!
//! Differences from the paper, each to make every answer bounded, valid or fast:
//! - frames are generated and classified `batch` at a time, which costs far
//!   less per frame than one at a time;
//! - a frame counts as accepted only when it also stays inside the
//!   public-access area (deviation score 0): the paper's "minor noise" is
//!   rejected at the source instead of being filtered afterwards;
//! - accepted frames of *other* pairs are not thrown away but kept, up to
//!   `bank_per_class` per pair, and a later request for that pair takes one
//!   (each frame is used once). Every frame is an independent draw from the
//!   generator, so a banked frame is exactly as likely as a fresh one; the
//!   bank only stops Algorithm 1 from discarding the work it already did.
//!   `warm_samples` frames are sorted into the bank when the planner is built;
//! - the loop stops after `max_samples` frames (a count, not a time, so the
//!   route a request gets never depends on how busy the CPU is); then, of
//!   the frames with the fewest cells outside the public-access area, the
//!   one the classifier rated highest for the pair is repaired into a route
//!   ([`Origin::BudgetExhausted`]);
//! - a pair that is not a class of the classifier (Algorithm 1 would loop
//!   forever) is served by the profile's plain search ([`Origin::Untrained`]);
//! - the accepted frame goes through [`route_from_frame`], which filters the
//!   paper's "minor noise" and repairs gaps, so the route is always valid.

use std::collections::BTreeMap;
use std::sync::{Arc, Mutex, PoisonError};

use ndarray::Array2;
use rand::SeedableRng;
use rand::rngs::Xoshiro256PlusPlus;
use rand_distr::{Distribution, StandardNormal};
use serde::Deserialize;

use super::astar::profile_search;
use super::frame::route_from_frame;
use super::{
    Connectivity, Origin, PlanError, Planned, Planner, Profile, RequestSeeds, Timings, model_error,
};
use crate::clock::Clock;
use crate::model::PathClass;
use crate::model::runtime::{PathClassifier, PathGenerator};
use crate::site::{Cell, Site};

/// `[planner.rejection]`: the bounds on Algorithm 1's loop.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RejectionConfig {
    /// Frames generated and classified per model call.
    pub batch: usize,
    /// Frames tried before the best one is repaired: the request's budget,
    /// as a count so that a route never depends on how busy the CPU is.
    pub max_samples: usize,
    /// Accepted frames kept for each pair for later requests (0: none).
    pub bank_per_class: usize,
    /// Frames generated and sorted into the bank when the planner is built.
    pub warm_samples: usize,
}

impl Default for RejectionConfig {
    fn default() -> Self {
        RejectionConfig {
            batch: 32,
            max_samples: 32,
            bank_per_class: 4,
            warm_samples: 4096,
        }
    }
}

pub(crate) struct Rejection {
    site: Arc<Site>,
    connectivity: Connectivity,
    generator: PathGenerator,
    classifier: PathClassifier,
    class_of: BTreeMap<PathClass, usize>,
    config: RejectionConfig,
    clock: Clock,
    version: String,
    /// Each request's noise: reproducible runs, no lock.
    seeds: RequestSeeds,
    /// Accepted frames not yet used, by class.
    bank: Mutex<Vec<Vec<Vec<f32>>>>,
}

/// One generated and classified batch.
struct Batch {
    frames: Array2<f32>,
    probs: Array2<f32>,
}

impl Rejection {
    pub(crate) fn new(
        site: Arc<Site>,
        connectivity: Connectivity,
        generator: PathGenerator,
        classifier: PathClassifier,
        config: RejectionConfig,
        clock: Clock,
    ) -> Result<Rejection, String> {
        if generator.is_conditional() {
            return Err(
                "rejection mode needs the unconditional generator (kind `generator`), \
                 not a conditional one"
                    .into(),
            );
        }
        if config.batch == 0 || config.max_samples == 0 {
            return Err("[planner.rejection] batch and max_samples must be at least 1".into());
        }
        let class_of = classifier
            .classes()
            .iter()
            .enumerate()
            .map(|(i, &c)| (c, i))
            .collect();
        let version = super::model_version(&[generator.model(), classifier.model()]);
        let classes = classifier.classes().len();
        let rejection = Rejection {
            site,
            connectivity,
            generator,
            classifier,
            class_of,
            config,
            clock,
            version,
            seeds: RequestSeeds::new(),
            bank: Mutex::new(vec![Vec::new(); classes]),
        };
        rejection
            .warm_up()
            .map_err(|e| format!("rejection planner warm-up: {e}"))?;
        Ok(rejection)
    }

    /// Fills the bank with `warm_samples` frames; seeded apart from requests.
    fn warm_up(&self) -> Result<(), PlanError> {
        let mut rng = Xoshiro256PlusPlus::seed_from_u64(u64::MAX);
        let mut timings = Timings::default();
        let mut done = 0;
        while done < self.config.warm_samples {
            let rows = self.config.batch.min(self.config.warm_samples - done);
            let batch = self.sample(&mut rng, rows, &mut timings)?;
            for (frame, class) in batch.accepted(&self.site) {
                self.deposit(class, frame);
            }
            done += rows;
        }
        Ok(())
    }

    /// Generates and classifies `rows` frames.
    fn sample(
        &self,
        rng: &mut Xoshiro256PlusPlus,
        rows: usize,
        timings: &mut Timings,
    ) -> Result<Batch, PlanError> {
        let noise = Array2::from_shape_fn((rows, self.generator.noise_dim()), |_| {
            StandardNormal.sample(rng)
        });
        let t = self.clock.start();
        let frames = self
            .generator
            .generate(noise.view(), None)
            .map_err(model_error)?;
        timings.gen_us += t.elapsed_us();
        let binary = frames.mapv(|v| if v > 0.0 { 1.0 } else { 0.0 });
        let t = self.clock.start();
        let probs = self
            .classifier
            .classify(binary.view())
            .map_err(model_error)?;
        timings.classify_us += t.elapsed_us();
        Ok(Batch { frames, probs })
    }

    /// Keeps an accepted frame of `class` unless its bank is full.
    fn deposit(&self, class: usize, frame: Vec<f32>) {
        let mut bank = self.bank.lock().unwrap_or_else(PoisonError::into_inner);
        if bank[class].len() < self.config.bank_per_class {
            bank[class].push(frame);
        }
    }

    /// Takes a banked frame of `class`, if any.
    fn withdraw(&self, class: usize) -> Option<Vec<f32>> {
        self.bank
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .get_mut(class)?
            .pop()
    }
}

impl Planner for Rejection {
    fn mode(&self) -> &'static str {
        "rejection"
    }

    fn model_version(&self) -> Option<&str> {
        Some(&self.version)
    }

    fn plan(&self, from: Cell, to: Cell, profile: Profile) -> Result<Planned, PlanError> {
        let site = &*self.site;
        let Some(&class) = self.class_of.get(&PathClass {
            source: from,
            destination: to,
        }) else {
            let route = profile_search(site, self.connectivity, from, to, profile, |_| 1.0)?;
            return Ok(Planned {
                origin: Origin::Untrained,
                ..Planned::searched(route)
            });
        };
        if let Some(frame) = self.withdraw(class) {
            let (route, origin) =
                route_from_frame(site, self.connectivity, profile, &frame, from, to)?;
            return Ok(Planned {
                route,
                origin,
                samples: 0,
                frame: Some(frame),
                line: None,
                timings: Timings::default(),
            });
        }
        let mut rng = self.seeds.next();
        let mut timings = Timings::default();
        let mut samples = 0;
        let mut best: Option<(usize, f32, Vec<f32>)> = None;
        while samples < self.config.max_samples {
            let rows = self.config.batch.min(self.config.max_samples - samples);
            let batch = self.sample(&mut rng, rows, &mut timings)?;
            samples += rows;
            let mut answer = None;
            for (frame, accepted) in batch.accepted(site) {
                if accepted == class && answer.is_none() {
                    answer = Some(frame);
                } else {
                    self.deposit(accepted, frame);
                }
            }
            if let Some(frame) = answer {
                let (route, origin) =
                    route_from_frame(site, self.connectivity, profile, &frame, from, to)?;
                return Ok(Planned {
                    route,
                    origin,
                    samples,
                    frame: Some(frame),
                    line: None,
                    timings,
                });
            }
            // The best frame so far: the fewest cells outside the public
            // area (so a budget-exhausted answer stays in it whenever any
            // frame did), then the most likely to be of the class.
            for (frame, p) in batch.frames.rows().into_iter().zip(batch.probs.rows()) {
                let frame = frame.as_slice().expect("standard layout");
                let off = super::cells_off_area(site, frame);
                if best.as_ref().is_none_or(|(b_off, b_p, _)| {
                    off < *b_off || (off == *b_off && p[class] > *b_p)
                }) {
                    best = Some((off, p[class], frame.to_vec()));
                }
            }
        }
        let (_, _, frame) = best.expect("at least one batch ran");
        let (route, _) = route_from_frame(site, self.connectivity, profile, &frame, from, to)?;
        Ok(Planned {
            route,
            origin: Origin::BudgetExhausted,
            samples,
            frame: Some(frame),
            line: None,
            timings,
        })
    }
}

impl Batch {
    /// The frames Algorithm 1 accepts, with their class: the classifier's
    /// most likely class, and no bright cell outside the public-access area.
    fn accepted(&self, site: &Site) -> impl Iterator<Item = (Vec<f32>, usize)> {
        self.frames
            .rows()
            .into_iter()
            .zip(self.probs.rows())
            .filter_map(move |(frame, p)| {
                let frame = frame.as_slice().expect("standard layout");
                let class = p
                    .iter()
                    .enumerate()
                    .max_by(|a, b| a.1.total_cmp(b.1))
                    .map(|(i, _)| i)?;
                (super::cells_off_area(site, frame) == 0).then(|| (frame.to_vec(), class))
            })
    }
}
