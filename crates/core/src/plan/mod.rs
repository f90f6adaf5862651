//! Planning: a walkable route from a device's cell to a destination.
//!
//! Owns what a route is ([`Route`]), how a destination is named ([`Destination`]),
//! the ways a request can fail ([`PlanError`], each with a stable [`RouteErrorCode`] for MQTT
//! error replies) and the planners behind [`Planner`]. Every planner answers with
//! a route that [`Route::validate`] accepts, or an error: never an invalid route.

//!
//! Modes (`[planner] mode`): `learned`, the default (the desire lines when
//! they passed their training check on the site's walks, else the line GAN
//! when it passed its checks, else the conditional GAN, else the paper's GAN
//! and classifier when the GAN passed its checks, else A*: [`learned`]),
//! `astar` (shortest walk, no models), `desire` (the line people walk
//! between the two cells, learned from their walks: [`desire`]), `line_gan`
//! (lines generated for the pair by a GAN whose size does not grow with the
//! site: [`line_gan`]), `rejection` (the paper's Algorithm 1, bounded:
//! [`rejection`]) and `conditional` (the conditional GAN: [`conditional`]).
//! The frame GAN modes turn frames into routes with
//! [`frame::route_from_frame`], which repairs what a frame gets wrong; the
//! line modes repair their line with the any-angle search. Profiles ([`Profile`]) change which cells a walker may use and what
//! they cost, in every mode. [`anyangle`] is the any-angle baseline the
//! learned modes are judged against (`gangway eval planning`).

pub mod anyangle;
pub mod astar;
pub(crate) mod conditional;
pub mod desire;
mod error_code;
pub mod floors;
pub mod frame;
pub mod instructions;
pub mod learned;
pub(crate) mod line_gan;
pub mod lines;
mod profile;
pub(crate) mod rejection;
mod route;

use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};

pub use error_code::RouteErrorCode;
pub use profile::{Profile, unknown_profile_message};
pub use route::{LinePoint, LineSource, Route, ServedLine, Waypoint};

use crate::clock::Clock;
use crate::model::ModelError;
use crate::model::runtime::{DesireModel, LineGenerator, PathClassifier, PathGenerator, Rows};
use crate::site::{Cell, Site};

/// Where a request wants to go: a named place or a cell.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum Destination {
    Place(String),
    Cell([i64; 2]),
}

/// Why no route was returned.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum PlanError {
    #[error("unknown place `{name}`; the site's places are: {known}")]
    UnknownPlace { name: String, known: String },
    #[error("cell [{x}, {y}] is off the {width}×{height} map")]
    OffMap {
        x: i64,
        y: i64,
        width: u16,
        height: u16,
    },
    #[error("cell {0} is blocked (not public access)")]
    Blocked(Cell),
    #[error("no walkable route from {from} to {to}")]
    Unreachable { from: Cell, to: Cell },
    /// Across floors: no connector joins the two floors along a way the
    /// walker can reach (`from` and `to` name floor and cell).
    #[error(
        "no walkable route from {from} to {to}: no connector joins their floors where the walker can reach it"
    )]
    NotJoined { from: String, to: String },
    /// The walker needs a step-free route and every route has steps: `why`
    /// says where (which stairs or escalators the only routes take).
    #[error("no step-free route from {from} to {to}: {why}")]
    NoStepFreeRoute {
        from: String,
        to: String,
        why: String,
    },
    /// A floor the building does not have.
    #[error("unknown floor `{name}`; the building's floors are: {known}")]
    UnknownFloor { name: String, known: String },
    /// A destination that does not say its floor, on a building where it
    /// must: a cell, or a place on several floors or none.
    #[error("{0}")]
    FloorUnclear(String),
    /// A model failed at run time (the planner could not produce frames).
    #[error("the path model failed: {reason}")]
    Model { reason: String },
    /// A route failed validation: a bug, reported rather than sent.
    #[error("the planner produced an invalid route ({reason}); this is a bug, please report it")]
    Invalid { reason: String },
}

impl PlanError {
    /// Stable machine-readable code, as sent in MQTT error replies.
    pub fn code(&self) -> RouteErrorCode {
        match self {
            PlanError::UnknownPlace { .. }
            | PlanError::UnknownFloor { .. }
            | PlanError::FloorUnclear(_) => RouteErrorCode::UnknownPlace,
            PlanError::OffMap { .. } => RouteErrorCode::OffMap,
            PlanError::Blocked(_) => RouteErrorCode::BlockedCell,
            PlanError::Unreachable { .. } | PlanError::NotJoined { .. } => {
                RouteErrorCode::Unreachable
            }
            PlanError::NoStepFreeRoute { .. } => RouteErrorCode::NoStepFreeRoute,
            PlanError::Model { .. } => RouteErrorCode::ModelFailed,
            PlanError::Invalid { .. } => RouteErrorCode::InvalidRoute,
        }
    }
}

impl Destination {
    /// The walkable cell this destination names on `site`.
    pub fn resolve(&self, site: &Site) -> Result<Cell, PlanError> {
        let cell = match self {
            Destination::Place(name) => {
                site.place(name).ok_or_else(|| PlanError::UnknownPlace {
                    name: name.clone(),
                    known: site
                        .places()
                        .keys()
                        .map(|k| format!("`{k}`"))
                        .collect::<Vec<_>>()
                        .join(", "),
                })?
            }
            &Destination::Cell([x, y]) => {
                let off_map = PlanError::OffMap {
                    x,
                    y,
                    width: site.width(),
                    height: site.height(),
                };
                let cell = match (u16::try_from(x), u16::try_from(y)) {
                    (Ok(x), Ok(y)) => Cell::new(x, y),
                    _ => return Err(off_map),
                };
                if !site.contains(cell) {
                    return Err(off_map);
                }
                cell
            }
        };
        if site.walkable(cell) {
            Ok(cell)
        } else {
            Err(PlanError::Blocked(cell))
        }
    }
}

/// Which moves a route may make between neighbouring cells.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Connectivity {
    /// Up, down, left, right.
    Four,
    /// Also diagonals, but never across the corner of a blocked cell.
    #[default]
    Eight,
}

impl Connectivity {
    /// Whether a single step from `a` to `b` is allowed on `site`.
    pub fn step_ok(self, site: &Site, a: Cell, b: Cell) -> bool {
        self.step_ok_by(a, b, |c| site.walkable(c))
    }

    /// [`Connectivity::step_ok`] where `passable` says which cells may be used.
    pub(crate) fn step_ok_by(self, a: Cell, b: Cell, passable: impl Fn(Cell) -> bool) -> bool {
        let (dx, dy) = (a.x.abs_diff(b.x), a.y.abs_diff(b.y));
        if !passable(b) || dx > 1 || dy > 1 || (dx == 0 && dy == 0) {
            return false;
        }
        match (dx, dy) {
            (1, 1) => {
                self == Connectivity::Eight
                    && passable(Cell::new(a.x, b.y))
                    && passable(Cell::new(b.x, a.y))
            }
            _ => true,
        }
    }
}

/// `[planner]` in the gateway config.
#[derive(Clone, Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlannerConfig {
    /// Which planner serves requests.
    #[serde(default)]
    pub mode: PlannerMode,
    #[serde(default)]
    pub connectivity: Connectivity,
    #[serde(default)]
    pub models: ModelPaths,
    #[serde(default)]
    pub rejection: rejection::RejectionConfig,
    #[serde(default)]
    pub conditional: conditional::ConditionalConfig,
    #[serde(default)]
    pub line_gan: line_gan::LineGanConfig,
    /// How planners time their model calls and the pipeline its replies
    /// (`Timings`, `latency_us`): never read from the file, set by whoever
    /// loads it (`Clock::NONE`, all 0, until then).
    #[serde(skip)]
    pub clock: Clock,
}

/// `[planner.models]`: ONNX files written by `gangway train`, relative to the
/// config file. Only the ones the mode needs are loaded.
#[derive(Clone, Debug, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ModelPaths {
    pub generator: PathBuf,
    pub path_classifier: PathBuf,
    pub conditional_generator: PathBuf,
    /// Unset in a config file: beside the conditional generator, where
    /// `gangway train --out DIR` writes both, so lines trained into the
    /// directory a config already serves are found without an edit.
    #[serde(default)]
    pub desire_lines: PathBuf,
    /// Unset in a config file: beside the conditional generator, as the
    /// desire lines.
    #[serde(default)]
    pub line_generator: PathBuf,
}

impl Default for ModelPaths {
    fn default() -> Self {
        ModelPaths {
            generator: "models/generator.onnx".into(),
            path_classifier: "models/path_classifier.onnx".into(),
            conditional_generator: "models/conditional_generator.onnx".into(),
            desire_lines: "models/desire_lines.onnx".into(),
            line_generator: "models/line_generator.onnx".into(),
        }
    }
}

impl PlannerConfig {
    /// This config for the floor called `floor` of a building of several:
    /// `{floor}` in its model paths becomes the floor's name, so each floor
    /// serves the models trained on it (`gangway train --site F1.toml --out
    /// models/F1`), and a floor whose models are missing or failed their
    /// checks is planned on its geometry, as a one-floor site would be.
    /// A model the mode reads without `{floor}` in its path would be one
    /// floor's served on every floor: refused, except that the default
    /// mode with none of its paths naming floors (the shipped sample's
    /// models) plans every floor by A*.
    pub fn for_floor(&self, floor: &str) -> Result<PlannerConfig, BuildError> {
        let mut config = self.clone();
        let mode = config.mode;
        // Which models the mode loads: (the paper's pair, conditional,
        // desire, line GAN).
        let (paper, conditional, desire, lines) = match mode {
            PlannerMode::Learned => (true, true, true, true),
            PlannerMode::Astar => (false, false, false, false),
            PlannerMode::Rejection => (true, false, false, false),
            PlannerMode::Conditional => (false, true, false, false),
            PlannerMode::Desire => (false, false, true, false),
            PlannerMode::LineGan => (false, false, false, true),
        };
        let m = &mut config.models;
        let files = [
            ("[planner.models] generator", &mut m.generator, paper),
            (
                "[planner.models] path_classifier",
                &mut m.path_classifier,
                paper,
            ),
            (
                "[planner.models] conditional_generator",
                &mut m.conditional_generator,
                conditional,
            ),
            ("[planner.models] desire_lines", &mut m.desire_lines, desire),
            (
                "[planner.models] line_generator",
                &mut m.line_generator,
                lines,
            ),
        ];
        let (mut named, mut one_floor) = (0, None);
        for (key, path, read) in files {
            if let Some(named_path) = crate::site::floor_path(path, floor) {
                *path = named_path;
                named += 1;
            } else if read {
                one_floor.get_or_insert((key, path.clone()));
            }
        }
        match one_floor {
            None => Ok(config),
            Some(_) if mode == PlannerMode::Learned && named == 0 => {
                config.mode = PlannerMode::Astar;
                Ok(config)
            }
            Some((key, path)) => Err(BuildError::OneFileForAllFloors { key, path }),
        }
    }

    /// Makes the model paths relative to `base` (the config file's directory).
    pub fn resolve_paths(&mut self, base: &Path) {
        let m = &mut self.models;
        for p in [
            &mut m.generator,
            &mut m.path_classifier,
            &mut m.conditional_generator,
        ] {
            *p = base.join(&*p);
        }
        for (path, beside) in [
            (&mut m.desire_lines, "desire_lines.onnx"),
            (&mut m.line_generator, "line_generator.onnx"),
        ] {
            *path = if path.as_os_str().is_empty() {
                m.conditional_generator.with_file_name(beside)
            } else {
                base.join(&*path)
            };
        }
    }
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum PlannerMode {
    /// The default: the learned planner that passed its training check on
    /// the site's walks, falling back down to A* ([`learned`]).
    #[default]
    Learned,
    /// Shortest walkable path.
    Astar,
    /// Algorithm 1: unconditional GAN + path classifier, bounded.
    Rejection,
    /// Conditional GAN, any pair of open cells.
    Conditional,
    /// Learned desire lines, any pair of open cells.
    Desire,
    /// Lines generated by the line GAN, any pair of open cells.
    #[serde(rename = "line_gan")]
    LineGan,
}

impl PlannerMode {
    pub const ALL: [PlannerMode; 6] = [
        PlannerMode::Learned,
        PlannerMode::Astar,
        PlannerMode::Rejection,
        PlannerMode::Conditional,
        PlannerMode::Desire,
        PlannerMode::LineGan,
    ];

    pub fn name(self) -> &'static str {
        match self {
            PlannerMode::Learned => "learned",
            PlannerMode::Astar => "astar",
            PlannerMode::Rejection => "rejection",
            PlannerMode::Conditional => "conditional",
            PlannerMode::Desire => "desire",
            PlannerMode::LineGan => "line_gan",
        }
    }
}

/// How a route came about.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Origin {
    /// A plain search (the `astar` mode).
    Search,
    /// Read off a generated frame (or a learned line) unchanged.
    Frame,
    /// A generated frame with gaps or noise, repaired by the guided search
    /// (or a learned line repaired round what it crossed).
    Repaired,
    /// Rejection mode ran out of samples or time; the frame the classifier
    /// rated best for the pair was repaired.
    BudgetExhausted,
    /// Rejection mode: the pair is not one of the classifier's classes, so
    /// the profile's plain search answered.
    Untrained,
    /// Desire lines: the training walks say too little about these
    /// endpoints (the model's kernel mass at most its threshold), so the
    /// profile's any-angle route was served.
    FewWalks,
    /// Desire lines: the learned route cost the profile more in what it pays
    /// beyond length (narrow cells, doors, turns for low vision) than its
    /// any-angle route, which was served instead.
    ProfileCosts,
}

impl Origin {
    /// Whether a learned planner served its fallback instead of what it
    /// learned.
    pub fn is_fallback(self) -> bool {
        matches!(self, Origin::FewWalks | Origin::ProfileCosts)
    }
}

/// Time spent in the models for one request, microseconds.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Timings {
    pub gen_us: u64,
    pub classify_us: u64,
}

/// A planner's answer: the route, and how it was made.
#[derive(Clone, Debug, PartialEq)]
pub struct Planned {
    pub route: Route,
    pub origin: Origin,
    /// Frames generated for this request.
    pub samples: usize,
    /// The frame the route came from (GAN modes).
    pub frame: Option<Vec<f32>>,
    /// The line the route follows (cell units, source centre to destination
    /// centre) when the planner drew one (`desire`, `anyangle`); the route
    /// is its cells. Served, once checked, as [`ServedLine`].
    pub line: Option<Vec<anyangle::GridPoint>>,
    pub timings: Timings,
}

impl Planned {
    fn searched(route: Route) -> Planned {
        Planned {
            route,
            origin: Origin::Search,
            samples: 0,
            frame: None,
            line: None,
            timings: Timings::default(),
        }
    }
}

/// Something that answers route requests on a site.
pub trait Planner: Send + Sync {
    /// The mode name reported with every route.
    fn mode(&self) -> &'static str;
    /// Which trained models answer, e.g. `generator@15000it/seed1`; `None`
    /// without models.
    fn model_version(&self) -> Option<&str>;
    /// A route that [`Route::validate_for`] accepts for `profile`, or an error.
    fn plan(&self, from: Cell, to: Cell, profile: Profile) -> Result<Planned, PlanError>;
}

/// Why a planner could not be built.
#[derive(Debug, thiserror::Error)]
pub enum BuildError {
    /// A model file did not load (missing, corrupt, for another site): a
    /// gateway starting up plans with A* instead (`Pipeline::with_fallbacks`).
    #[error("[planner] mode = \"{mode}\": loading the {what}: {error}")]
    Model {
        mode: &'static str,
        what: &'static str,
        error: ModelError,
    },
    /// The models loaded, but the settings do not fit them.
    #[error("{0}")]
    Settings(String),
    /// A building of several floors with a model file that names one
    /// floor's.
    #[error(
        "{key} = \"{}\" names one model for every floor of a building of several: a model is \
         trained on one floor's grid and walks; put `{{floor}}` in its path where each floor's \
         name goes (`models/{{floor}}/desire_lines.onnx`), or set [planner] mode = \"learned\" \
         or \"astar\"",
        path.display()
    )]
    OneFileForAllFloors {
        key: &'static str,
        path: std::path::PathBuf,
    },
}

impl BuildError {
    /// What failed underneath, without where: the model's error, or the
    /// settings' complaint.
    pub fn cause(&self) -> String {
        match self {
            BuildError::Model { error, .. } => error.to_string(),
            BuildError::Settings(why) => why.clone(),
            e @ BuildError::OneFileForAllFloors { .. } => e.to_string(),
        }
    }
}

/// Builds the configured planner for `site`, loading its models. A missing,
/// corrupt or mismatched model is an error naming the file and what to do.
pub fn build(config: &PlannerConfig, site: Arc<Site>) -> Result<Box<dyn Planner>, BuildError> {
    build_mode(config, config.mode, site)
}

/// Builds the planner of `mode` with the rest of `config`.
pub fn build_mode(
    config: &PlannerConfig,
    mode: PlannerMode,
    site: Arc<Site>,
) -> Result<Box<dyn Planner>, BuildError> {
    let context = |what: &'static str| {
        move |error| BuildError::Model {
            mode: mode.name(),
            what,
            error,
        }
    };
    Ok(match mode {
        PlannerMode::Learned => {
            let (planner, choice) = learned::build(config, site)?;
            choice.log();
            planner
        }
        PlannerMode::Astar => Box::new(astar::AStar::new(site, config.connectivity)),
        PlannerMode::Rejection => {
            let generator = rejection_generator(config, &site)
                .map_err(context("generator ([planner.models] generator)"))?;
            rejection_with(config, site, generator, mode)?
        }
        PlannerMode::Conditional => {
            let rows = Rows::for_batch(config.conditional.samples);
            let generator = PathGenerator::load(&config.models.conditional_generator, &site, rows)
                .map_err(context(
                    "conditional generator ([planner.models] conditional_generator)",
                ))?;
            Box::new(
                conditional::Conditional::new(
                    site,
                    config.connectivity,
                    generator,
                    config.conditional.clone(),
                    config.clock,
                )
                .map_err(BuildError::Settings)?,
            )
        }
        PlannerMode::Desire => {
            let model = DesireModel::load(&config.models.desire_lines, &site)
                .map_err(context("desire lines ([planner.models] desire_lines)"))?;
            Box::new(desire::Desire::new(
                site,
                config.connectivity,
                model,
                config.clock,
            ))
        }
        PlannerMode::LineGan => {
            let generator = line_generator(config, &site)
                .map_err(context("line generator ([planner.models] line_generator)"))?;
            line_gan_with(config, site, generator)?
        }
    })
}

/// The configured line generator, planned for the line GAN's samples:
/// loaded apart from [`line_gan_with`] so that the learned planner can read
/// its training checks before serving it.
fn line_generator(config: &PlannerConfig, site: &Site) -> Result<LineGenerator, ModelError> {
    LineGenerator::load(
        &config.models.line_generator,
        site,
        Rows::for_batch(config.line_gan.samples),
    )
}

/// The line GAN planner over `generator`.
fn line_gan_with(
    config: &PlannerConfig,
    site: Arc<Site>,
    generator: LineGenerator,
) -> Result<Box<dyn Planner>, BuildError> {
    Ok(Box::new(
        line_gan::LineGan::new(
            site,
            config.connectivity,
            generator,
            config.line_gan.clone(),
            config.clock,
        )
        .map_err(BuildError::Settings)?,
    ))
}

/// The configured unconditional generator, planned for the rejection
/// mode's batch: loaded apart from [`rejection_with`] so that the learned
/// planner can read its training checks before serving it.
fn rejection_generator(config: &PlannerConfig, site: &Site) -> Result<PathGenerator, ModelError> {
    PathGenerator::load(
        &config.models.generator,
        site,
        Rows::for_batch(config.rejection.batch),
    )
}

/// The paper's Algorithm 1 over `generator` and the configured path
/// classifier, built for `mode` (named in its errors: `rejection`, or
/// `learned` serving it).
fn rejection_with(
    config: &PlannerConfig,
    site: Arc<Site>,
    generator: PathGenerator,
    mode: PlannerMode,
) -> Result<Box<dyn Planner>, BuildError> {
    let classifier =
        PathClassifier::load(&config.models.path_classifier, &site).map_err(|error| {
            BuildError::Model {
                mode: mode.name(),
                what: "path classifier ([planner.models] path_classifier)",
                error,
            }
        })?;
    Ok(Box::new(
        rejection::Rejection::new(
            site,
            config.connectivity,
            generator,
            classifier,
            config.rejection.clone(),
            config.clock,
        )
        .map_err(BuildError::Settings)?,
    ))
}

/// The paper's deviation score of a frame: (|G| − |G ∩ B|) / |B| for the
/// frame's bright cells G and the site's public-access cells B.
pub fn deviation_score(site: &Site, frame: &[f32]) -> f64 {
    cells_off_area(site, frame) as f64 / site.open_cells().len() as f64
}

/// The frame's bright cells outside the public-access area, |G| − |G ∩ B|.
pub fn cells_off_area(site: &Site, frame: &[f32]) -> usize {
    site.blocked_indices()
        .iter()
        .filter(|&&i| frame::bright(frame, i))
        .count()
}

/// A short name for the models behind a planner.
fn model_version(models: &[&crate::model::runtime::Model]) -> String {
    models
        .iter()
        .map(|m| {
            let meta = m.metadata();
            format!(
                "{}@{}it/seed{}",
                meta.kind.name(),
                meta.iterations,
                meta.seed
            )
        })
        .collect::<Vec<_>>()
        .join("+")
}

/// `Err(Blocked)` naming the first of a request's ends `profile` may not
/// use.
pub(crate) fn passable_ends(
    site: &Site,
    profile: Profile,
    from: Cell,
    to: Cell,
) -> Result<(), PlanError> {
    match [from, to].into_iter().find(|&c| !profile.passable(site, c)) {
        Some(c) => Err(PlanError::Blocked(c)),
        None => Ok(()),
    }
}

/// `row` as `rows` rows: every sample a generative planner draws for a
/// request has the same condition (a model's input is laid out from the
/// view, so the row is not copied).
pub(crate) fn repeated(row: &[f32], rows: usize) -> ndarray::ArrayView2<'_, f32> {
    use ndarray::ShapeBuilder;
    // A stride of 0 between rows: the one row, seen `rows` times.
    ndarray::ArrayView2::from_shape((rows, row.len()).strides((0, 1)), row).expect("a row repeats")
}

/// Where a generative planner's randomness comes from: each request's own
/// generator, seeded by the request's number since start-up, so the same
/// requests get the same answers from one start-up to the next.
pub(crate) struct RequestSeeds(std::sync::atomic::AtomicU64);

impl RequestSeeds {
    pub(crate) fn new() -> RequestSeeds {
        RequestSeeds(std::sync::atomic::AtomicU64::new(0))
    }

    /// The next request's generator.
    pub(crate) fn next(&self) -> rand::rngs::Xoshiro256PlusPlus {
        use rand::SeedableRng;
        let n = self.0.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        rand::rngs::Xoshiro256PlusPlus::seed_from_u64(n)
    }

    /// The next request's noise: `rows × dim` standard normal values.
    pub(crate) fn noise(&self, rows: usize, dim: usize) -> ndarray::Array2<f32> {
        use rand_distr::Distribution;
        let mut rng = self.next();
        ndarray::Array2::from_shape_fn((rows, dim), |_| rand_distr::StandardNormal.sample(&mut rng))
    }
}

fn model_error(e: ModelError) -> PlanError {
    PlanError::Model {
        reason: e.to_string(),
    }
}
