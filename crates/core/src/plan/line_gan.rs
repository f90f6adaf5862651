//! The line GAN planner: lines generated for the requested pair itself by a
//! conditional GAN whose size does not grow with the site
//! ([`crate::model::line_gan`]), checked against the site and turned into a
//! route.
//!
//! A request first gets its prior ([`super::desire::prior_line`]: the
//! any-angle route, what the planner serves without walks), which the
//! generator is conditioned on ([`crate::model::line_gan`]). `samples`
//! lines are generated in one call. Each is made walkable as a
//! desire line is ([`super::desire::walkable_line`]: a point on a cell the profile
//! may not use is dropped, a segment that crosses one is replaced by the
//! any-angle way between its ends); the winner is the one that needed no
//! repair, then the shorter. A profile with costs beyond passability gets
//! the any-angle prior instead when the learned route costs it more in
//! those ([`super::desire::serve_walkable`]). The answer carries the line
//! ([`Planned::line`]): what a walker is told to follow.

use std::sync::Arc;

use serde::Deserialize;

use super::anyangle::{GridPoint, centre};
use super::desire::{prior_line, resample, serve_walkable, walkable_line};
use super::{
    Connectivity, PlanError, Planned, Planner, Profile, RequestSeeds, Timings, model_error,
    passable_ends, repeated,
};
use crate::clock::Clock;
use crate::model::desire::POINTS;
use crate::model::line_gan;
use crate::model::runtime::LineGenerator;
use crate::site::{Cell, Site};

/// `[planner.line_gan]`.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LineGanConfig {
    /// Lines generated per request; the best is kept.
    pub samples: usize,
}

impl Default for LineGanConfig {
    fn default() -> Self {
        LineGanConfig { samples: 2 }
    }
}

pub(crate) struct LineGan {
    site: Arc<Site>,
    connectivity: Connectivity,
    generator: LineGenerator,
    config: LineGanConfig,
    clock: Clock,
    version: String,
    seeds: RequestSeeds,
}

impl LineGan {
    pub(crate) fn new(
        site: Arc<Site>,
        connectivity: Connectivity,
        generator: LineGenerator,
        config: LineGanConfig,
        clock: Clock,
    ) -> Result<LineGan, String> {
        if config.samples == 0 {
            return Err("[planner.line_gan] samples must be at least 1".into());
        }
        let version = super::model_version(&[generator.model()]);
        Ok(LineGan {
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

impl Planner for LineGan {
    fn mode(&self) -> &'static str {
        "line_gan"
    }

    fn model_version(&self) -> Option<&str> {
        Some(&self.version)
    }

    fn plan(&self, from: Cell, to: Cell, profile: Profile) -> Result<Planned, PlanError> {
        let site = &*self.site;
        passable_ends(site, profile, from, to)?;
        let rows = self.config.samples;
        let noise = self.seeds.noise(rows, self.generator.noise_dim());
        let (a, b) = (centre(from), centre(to));
        let prior = prior_line(site, profile, from, to)?;
        let prior_offsets = line_gan::offsets(&resample(&prior, POINTS), a, b);
        let ends = line_gan::endpoints(site.width(), site.height(), a, b);
        let started = self.clock.start();
        let shapes = self
            .generator
            .generate(
                noise.view(),
                repeated(&ends, rows),
                repeated(&prior_offsets, rows),
            )
            .map_err(model_error)?;
        let timings = Timings {
            gen_us: started.elapsed_us(),
            classify_us: 0,
        };
        // The walkable line and whether it was repaired, ranked by that
        // and then by its length.
        let mut best: Option<(Vec<GridPoint>, bool, f64)> = None;
        for sample in shapes.rows() {
            let sample = sample
                .as_slice()
                .expect("a model's output is laid out by row");
            let line = line_gan::line(a, b, &prior_offsets, sample);
            let (line, repaired) = walkable_line(site, profile, &line, from, to)?;
            let length = length(&line);
            if best
                .as_ref()
                .is_none_or(|&(_, r, l)| (repaired, length) < (r, l))
            {
                best = Some((line, repaired, length));
            }
        }
        let (line, repaired, _) = best.expect("samples ≥ 1");
        let walkable = (line, repaired);
        let planned = serve_walkable(site, self.connectivity, profile, walkable, from, to, || {
            Ok(prior)
        })?;
        Ok(Planned {
            samples: rows,
            timings,
            ..planned
        })
    }
}

/// A line's length, cells.
fn length(line: &[GridPoint]) -> f64 {
    line.windows(2)
        .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
        .sum()
}
