//! The paper's Algorithm 1, batched and bounded: generate frames with the
//! unconditional GAN, classify them, and take the first frame whose class is
//! the requested (source, destination) pair.
//!
//! Differences from the paper, each to make every answer bounded and valid:
//! - frames are generated and classified `batch` at a time, which costs about
//!   the same per call as one frame;
//! - the loop stops after `max_samples` frames or `time_budget_ms`; then the
//!   frame the classifier rated highest for the pair is repaired into a route
//!   ([`Origin::BudgetExhausted`]);
//! - a pair that is not a class of the classifier (Algorithm 1 would loop
//!   forever) is served by the profile's plain search ([`Origin::Untrained`]);
//! - the accepted frame goes through [`route_from_frame`], which filters the
//!   paper's "minor noise" and repairs gaps, so the route is always valid.

use std::collections::BTreeMap;
use std::sync::Arc;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use ndarray::{Array2, Axis};
use rand::SeedableRng;
use rand::rngs::Xoshiro256PlusPlus;
use rand_distr::{Distribution, StandardNormal};
use serde::Deserialize;

use super::astar::profile_search;
use super::frame::route_from_frame;
use super::{Connectivity, Origin, PlanError, Planned, Planner, Profile, Timings, model_error};
use crate::model::PathClass;
use crate::model::runtime::{PathClassifier, PathGenerator};
use crate::site::{Cell, Site};

/// `[planner.rejection]`: the bounds on Algorithm 1's loop.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct RejectionConfig {
    /// Frames generated and classified per model call.
    pub batch: usize,
    /// Frames tried before the best one is repaired.
    pub max_samples: usize,
    /// Time tried before the best frame is repaired, milliseconds.
    pub time_budget_ms: u64,
}

impl Default for RejectionConfig {
    fn default() -> Self {
        RejectionConfig {
            batch: 64,
            max_samples: 1024,
            time_budget_ms: 20,
        }
    }
}

pub struct Rejection {
    site: Arc<Site>,
    connectivity: Connectivity,
    generator: PathGenerator,
    classifier: PathClassifier,
    class_of: BTreeMap<PathClass, usize>,
    config: RejectionConfig,
    version: String,
    /// Seeds the noise of each request: reproducible runs, no lock.
    requests: AtomicU64,
}

impl Rejection {
    pub fn new(
        site: Arc<Site>,
        connectivity: Connectivity,
        generator: PathGenerator,
        classifier: PathClassifier,
        config: RejectionConfig,
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
        Ok(Rejection {
            site,
            connectivity,
            generator,
            classifier,
            class_of,
            config,
            version,
            requests: AtomicU64::new(0),
        })
    }

    /// The (source, destination) pairs this planner serves from frames.
    pub fn classes(&self) -> &[PathClass] {
        self.classifier.classes()
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
        let started = Instant::now();
        let budget = Duration::from_millis(self.config.time_budget_ms);
        let mut rng =
            Xoshiro256PlusPlus::seed_from_u64(self.requests.fetch_add(1, Ordering::Relaxed));
        let mut timings = Timings::default();
        let mut samples = 0;
        let mut best: Option<(f32, Vec<f32>)> = None;
        while samples < self.config.max_samples && (samples == 0 || started.elapsed() < budget) {
            let rows = self.config.batch.min(self.config.max_samples - samples);
            let noise = Array2::from_shape_fn((rows, self.generator.noise_dim()), |_| {
                StandardNormal.sample(&mut rng)
            });
            let t = Instant::now();
            let frames = self
                .generator
                .generate(noise.view(), None)
                .map_err(model_error)?;
            timings.gen_us += t.elapsed().as_micros() as u64;
            let binary = frames.mapv(|v| if v > 0.0 { 1.0 } else { 0.0 });
            let t = Instant::now();
            let probs = self
                .classifier
                .classify(binary.view())
                .map_err(model_error)?;
            timings.classify_us += t.elapsed().as_micros() as u64;
            samples += rows;
            for (frame, p) in frames.axis_iter(Axis(0)).zip(probs.axis_iter(Axis(0))) {
                let argmax = p
                    .iter()
                    .enumerate()
                    .max_by(|a, b| a.1.total_cmp(b.1))
                    .map(|(i, _)| i);
                let frame = frame.to_vec();
                if argmax == Some(class) {
                    let (route, origin) =
                        route_from_frame(site, self.connectivity, profile, &frame, from, to)?;
                    return Ok(Planned {
                        route,
                        origin,
                        samples,
                        frame: Some(frame),
                        timings,
                    });
                }
                if best.as_ref().is_none_or(|(b, _)| p[class] > *b) {
                    best = Some((p[class], frame));
                }
            }
        }
        let (_, frame) = best.expect("at least one batch ran");
        let (route, _) = route_from_frame(site, self.connectivity, profile, &frame, from, to)?;
        Ok(Planned {
            route,
            origin: Origin::BudgetExhausted,
            samples,
            frame: Some(frame),
            timings,
        })
    }
}
