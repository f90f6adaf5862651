//! The conditional GAN planner: frames generated for the requested pair
//! itself, so any pair of open cells is served, trained or not.
//!
//! `samples` frames are generated in one call; the winner has the fewest
//! bright cells outside the public-access area (the paper's deviation), then
//! the fewest route cells outside the frame, then the shorter route. Each goes
//! through [`route_from_frame`], so a noisy frame is repaired, never returned
//! as is.

use std::sync::Arc;

use serde::Deserialize;

use super::frame::{bright, route_from_frame};
use super::{
    Connectivity, PlanError, Planned, Planner, Profile, RequestSeeds, Timings, model_error,
    repeated,
};
use crate::clock::Clock;
use crate::model::condition;
use crate::model::runtime::PathGenerator;
use crate::site::{Cell, Site};

/// `[planner.conditional]`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ConditionalConfig {
    /// Frames generated per request; the best is kept.
    pub samples: usize,
}

impl Default for ConditionalConfig {
    fn default() -> Self {
        ConditionalConfig { samples: 2 }
    }
}

pub(crate) struct Conditional {
    site: Arc<Site>,
    connectivity: Connectivity,
    generator: PathGenerator,
    config: ConditionalConfig,
    clock: Clock,
    version: String,
    seeds: RequestSeeds,
}

impl Conditional {
    pub(crate) fn new(
        site: Arc<Site>,
        connectivity: Connectivity,
        generator: PathGenerator,
        config: ConditionalConfig,
        clock: Clock,
    ) -> Result<Conditional, String> {
        if !generator.is_conditional() {
            return Err("conditional mode needs a conditional generator (kind \
                 `conditional_generator`); train one with `gangway train --conditional`"
                .into());
        }
        if config.samples == 0 {
            return Err("[planner.conditional] samples must be at least 1".into());
        }
        let version = super::model_version(&[generator.model()]);
        Ok(Conditional {
            site,
            connectivity,
            generator,
            config,
            clock,
            version,
            seeds: RequestSeeds::new(),
        })
    }
}

impl Planner for Conditional {
    fn mode(&self) -> &'static str {
        "conditional"
    }

    fn model_version(&self) -> Option<&str> {
        Some(&self.version)
    }

    fn plan(&self, from: Cell, to: Cell, profile: Profile) -> Result<Planned, PlanError> {
        let site = &*self.site;
        let (w, h) = (site.width(), site.height());
        let rows = self.config.samples;
        let noise = self.seeds.noise(rows, self.generator.noise_dim());
        // Every sample has the same condition: encoded once, its row
        // repeated (the model's input is laid out from the view).
        let mut condition = vec![0.0; condition::len(w, h)];
        condition::encode(w, h, from, to, &mut condition);
        let conditions = repeated(&condition, rows);
        let started = self.clock.start();
        let frames = self
            .generator
            .generate(noise.view(), Some(conditions))
            .map_err(model_error)?;
        let timings = Timings {
            gen_us: started.elapsed_us(),
            classify_us: 0,
        };
        let mut best: Option<((usize, usize), f64, Planned)> = None;
        for frame in frames.rows() {
            let frame = frame
                .as_slice()
                .expect("a model's output is laid out by row");
            let (route, origin) =
                route_from_frame(site, self.connectivity, profile, frame, from, to)?;
            let dark = route
                .cells
                .iter()
                .filter(|&&c| !bright(frame, site.grid_index(c)))
                .count();
            let rank = (super::cells_off_area(site, frame), dark);
            let length = route.length_m(site);
            if best
                .as_ref()
                .is_none_or(|(r, l, _)| (rank, length) < (*r, *l))
            {
                best = Some((
                    rank,
                    length,
                    Planned {
                        route,
                        origin,
                        samples: rows,
                        // Copied only for the best so far, not every sample.
                        frame: Some(frame.to_vec()),
                        line: None,
                        timings,
                    },
                ));
            }
        }
        Ok(best.expect("samples ≥ 1").2)
    }
}
