//! The default planner (`[planner] mode = "learned"`, or `mode` unset): the
//! learned planner that was measured on the site's own walks, without a
//! config edit after `gangway train`.
//!
//! In order, the first that is servable answers:
//! 1. the desire lines ([`super::desire`]), when `desire_lines.onnx` loads
//!    for the site and its metadata says it passed its training check
//!    (closer than the any-angle route on the training walks' later time
//!    folds, lines that mostly stand: [`crate::model::checks`]). That check
//!    is the same comparison `gangway eval planning` makes on held-out walks,
//!    so a model that fails it would serve routes worse than any-angle;
//! 2. the line GAN ([`super::line_gan`]), when `line_generator.onnx` loads
//!    and its metadata says it passed its training checks (walkable lines,
//!    few repaired, not collapsed): trained only when asked for (`gangway
//!    train --line-gan`), it comes after the desire lines because its checks
//!    do not compare it with the any-angle route;
//! 3. the conditional generator ([`super::conditional`]), when it loads:
//!    walks the lines did not learn from (simulated walks that come pair by
//!    pair, where whole pairs are held out) are still the GAN's to learn;
//! 4. the paper's GAN and path classifier (Algorithm 1, [`super::rejection`]),
//!    when both load and the generator's metadata says it passed its
//!    training checks (walkable frames, not collapsed, frames the classifier
//!    recognises: what Algorithm 1 needs to accept them). It comes after the
//!    conditional generator because it answers only the pairs it was trained
//!    on (others get the plain search, as in the `rejection` mode), but for
//!    those it serves what the walks taught rather than the shortest route.
//!    `gangway train` trains it by default, so its defaults leave a learned
//!    planner even on walks the desire lines cannot learn from;
//! 5. A*, with a warning: nothing learned is servable for the site.
//!
//! Which one answers, and why, is logged at start-up, written on the model
//! card by `gangway train`, reported by `gangway eval planning` (`serves`,
//! `serves_because`) and sent with every route (its `planner`). The explicit
//! modes (`desire`, `line_gan`, `conditional`, `rejection`: the paper's Algorithm 1,
//! `astar`) are unaffected: they serve their model or fail naming its file,
//! whatever its checks said.

use std::path::Path;
use std::sync::Arc;

use super::{
    BuildError, Planner, PlannerConfig, PlannerMode, build_mode, desire, line_gan_with,
    line_generator, rejection_generator, rejection_with,
};
use crate::model::checks::{Check, checks};
use crate::model::runtime::{DesireModel, LineGenerator, PathGenerator, Rows};
use crate::model::{Kind, Metadata, ModelError};
use crate::site::Site;

/// Which planner the default serves, and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Choice {
    /// The mode that answers requests: desire, conditional, rejection or
    /// astar.
    pub serves: PlannerMode,
    /// One sentence: what passed, or what was missing or failed.
    pub because: String,
}

impl Choice {
    /// Says which planner serves and why: a warning when it is A*.
    pub(crate) fn log(&self) {
        let name = self.serves.name();
        if self.serves == PlannerMode::Astar {
            tracing::warn!(
                planner = name,
                "[planner] mode = \"learned\": {}",
                self.because
            );
        } else {
            tracing::info!(
                planner = name,
                "[planner] mode = \"learned\": {}",
                self.because
            );
        }
    }
}

/// The default planner for `site` from `config`'s models, and why it is
/// the one ([`Choice::log`] says so). Never fails on a model: a model that is missing, for
/// another site or failed its check is passed over (and named in
/// [`Choice::because`]).
pub fn build(
    config: &PlannerConfig,
    site: Arc<Site>,
) -> Result<(Box<dyn Planner>, Choice), BuildError> {
    let desire_lines = &config.models.desire_lines;
    let desire_said = match DesireModel::load(desire_lines, &site) {
        Ok(model) => {
            let failed = failed_checks(model.model().metadata());
            if failed.is_empty() {
                let because = format!(
                    "the desire lines ({}) passed their training check on the site's walks ({})",
                    desire_lines.display(),
                    described(&checks(
                        Kind::DesireLines,
                        &model.model().metadata().metrics
                    ))
                );
                let planner = desire::Desire::new(site, config.connectivity, model, config.clock);
                return Ok((
                    Box::new(planner),
                    Choice {
                        serves: PlannerMode::Desire,
                        because,
                    },
                ));
            }
            format!(
                "the desire lines ({}) failed their training check: {}",
                desire_lines.display(),
                described(&failed)
            )
        }
        Err(e) => missing("desire lines", desire_lines, e, |path| {
            DesireModel::load(path, &site).map(|m| m.model().metadata().clone())
        }),
    };
    let lines = &config.models.line_generator;
    let lines_said = match line_generator(config, &site) {
        Ok(generator) => {
            let meta = generator.model().metadata();
            let failed = failed_checks(meta);
            if failed.is_empty() {
                let because = format!(
                    "{desire_said}; the line generator ({}) passed its training checks ({})",
                    lines.display(),
                    described(&checks(Kind::LineGenerator, &meta.metrics))
                );
                let planner = line_gan_with(config, site, generator)?;
                let serves = PlannerMode::LineGan;
                return Ok((planner, Choice { serves, because }));
            }
            format!(
                "the line generator ({}) failed its training checks: {}",
                lines.display(),
                described(&failed)
            )
        }
        Err(e) => missing("line generator", lines, e, |path| {
            LineGenerator::load(path, &site, Rows::Batches).map(|g| g.model().metadata().clone())
        }),
    };
    let desire_said = format!("{desire_said}; {lines_said}");
    let conditional_said = match build_mode(config, PlannerMode::Conditional, site.clone()) {
        Ok(planner) => {
            let because = format!(
                "{desire_said}; the conditional generator ({}) serves",
                config.models.conditional_generator.display()
            );
            let serves = PlannerMode::Conditional;
            return Ok((planner, Choice { serves, because }));
        }
        Err(e) => format!("no conditional generator ({})", e.cause()),
    };
    let generator = &config.models.generator;
    let rejection_said = match rejection_generator(config, &site) {
        Ok(loaded) => {
            let meta = loaded.model().metadata();
            let failed = failed_checks(meta);
            if failed.is_empty() {
                let passed = described(&checks(Kind::Generator, &meta.metrics));
                match rejection_with(config, site.clone(), loaded, PlannerMode::Learned) {
                    Ok(planner) => {
                        let because = format!(
                            "{desire_said}; {conditional_said}; the unconditional generator ({}) \
                             passed its training checks ({passed}): the paper's Algorithm 1 with \
                             the path classifier ({}) serves the pairs it was trained on, the \
                             plain search the others",
                            generator.display(),
                            config.models.path_classifier.display()
                        );
                        let serves = PlannerMode::Rejection;
                        return Ok((planner, Choice { serves, because }));
                    }
                    Err(e) => format!("the paper's Algorithm 1 cannot serve ({})", e.cause()),
                }
            } else {
                format!(
                    "the unconditional generator ({}) failed its training checks: {}",
                    generator.display(),
                    described(&failed)
                )
            }
        }
        Err(e) => missing("unconditional generator", generator, e, |path| {
            PathGenerator::load(path, &site, Rows::Batches).map(|g| g.model().metadata().clone())
        }),
    };
    let because = format!(
        "{desire_said}; {conditional_said}; {rejection_said}: nothing learned is servable, \
         A* serves (train the site's models with `gangway train`)"
    );
    let planner = build_mode(config, PlannerMode::Astar, site)?;
    let serves = PlannerMode::Astar;
    Ok((planner, Choice { serves, because }))
}

/// The checks a model's metadata says it failed.
fn failed_checks(meta: &Metadata) -> Vec<Check> {
    checks(meta.kind, &meta.metrics)
        .into_iter()
        .filter(|c| !c.passed())
        .collect()
}

fn described(checks: &[Check]) -> String {
    checks
        .iter()
        .map(Check::describe)
        .collect::<Vec<_>>()
        .join(", ")
}

/// Why the `what` at `path` cannot serve: `error`, or, when the file is
/// missing and training put a failed one in `failed/` beside it, what that
/// one failed (its metadata read by `load`). A file simply not there yet is
/// said plainly: it is the normal state of a site nobody has trained on, not
/// a fault.
fn missing(
    what: &str,
    path: &Path,
    error: ModelError,
    load: impl Fn(&Path) -> Result<Metadata, ModelError>,
) -> String {
    if let ModelError::Missing { .. } = error
        && let Some(dir) = path.parent()
        && let Some(name) = path.file_name()
    {
        let failed = dir.join("failed").join(name);
        if let Ok(meta) = load(&failed) {
            return format!(
                "the {what} did not pass the training checks ({}: {})",
                failed.display(),
                described(&failed_checks(&meta))
            );
        }
    }
    match error {
        ModelError::Missing { .. } => format!(
            "no {what} trained for the site yet ({} would hold it)",
            path.display()
        ),
        error => format!("no {what} ({error})"),
    }
}
