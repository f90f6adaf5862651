//! The pipeline every mode runs: events → fingerprint windows → localizer →
//! tracker → planner → outgoing messages, and guidance along the routes it
//! served (a session per device, see [`crate::guide`]): on each fix of a
//! guided device a guidance message, and a route re-planned from where the
//! device is when it has left its route.
//!
//! It serves a building: a one-floor site is a building of one floor. Each
//! floor has its own localizer, tracker and guidance sessions
//! ([`floor`]); the fingerprint windows span every floor's anchors, and on
//! a building of several floors each device's floor comes from what it
//! hears, changing only where and when a connector allows
//! ([`crate::locate::floor_track`]). Routes within a floor are a floor's
//! reply, as on a one-floor site; routes across floors have one leg per
//! floor, and guidance follows the walker from leg to leg.
//!
//! It does no I/O and keeps no clock of its own: the runtime (`daemon` in the
//! binary) and the tests feed it [`Event`]s and hand the typed [`Output`]s it returns
//! to the sinks. It knows no topic and writes no JSON. That keeps replay as
//! fast as the CPU allows and makes the daemon's behaviour testable from a log.

mod floor;

use std::sync::Arc;

use foldhash::HashMap;
use serde::Deserialize;

use crate::clock::{Clock, Stopwatch};
use crate::event::{Event, RouteRequest};
use crate::guide::{Guidance, GuidanceConfig, GuidanceEvent};
use crate::locate;
use crate::locate::bounds::Bounds;
use crate::locate::floor_track::{self, FloorChange, FloorTracks};
use crate::locate::floors::FloorEvidence;
use crate::locate::tracker::TrackerConfig;
use crate::locate::window::{Fingerprint, Orientation, WindowConfig, Windows};
use crate::plan::floors::{BuildingPlanner, FloorCell};
use crate::plan::instructions::{connector_noun, leave_sentence};
use crate::plan::{self, PlannerConfig, Profile, RouteErrorCode};
use crate::publish::floors::FloorsRouteBody;
use crate::publish::{
    ErrorBody, FloorName, LOCATION_SCHEMA, Location, Output, PATH_SCHEMA, RouteBody, RouteOutcome,
    RouteReply,
};
use crate::sighting::heard::{HeardBeacon, HeardTable};
use crate::sighting::valid_device_id;
use crate::site::{Building, Cell, Site};
use floor::FloorStages;

/// The sections of the gateway config a pipeline is built from (the config
/// file composes them with the I/O parts' sections; `Config::pipeline` in
/// `gangway-io` picks them out).
#[derive(Clone, Debug, Default)]
#[cfg_attr(test, derive(Deserialize), serde(default))]
pub struct PipelineConfig {
    pub window: WindowConfig,
    pub localizer: locate::LocalizerConfig,
    pub tracker: TrackerConfig,
    pub planner: PlannerConfig,
    pub guidance: GuidanceConfig,
    pub limits: LimitsConfig,
}

/// `[limits]` in the gateway config: bounds on per-device state and on the
/// work other parties can ask for. Everything from the air or the broker is
/// hostile; these are what keeps a flood of fake devices or requests from
/// exhausting the gateway.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct LimitsConfig {
    /// Devices tracked at most (fingerprint windows, tracks, Home Assistant
    /// trackers); past it the least recently seen is forgotten.
    pub max_devices: usize,
    /// A device unheard this long (seconds of event time) is forgotten.
    pub device_idle_s: f64,
    /// Route requests waiting to be planned at most; past it a request is
    /// answered `overloaded` at once.
    pub max_pending_requests: usize,
    /// A request that waited longer than this (seconds) is answered
    /// `overloaded` instead of planned.
    pub request_deadline_s: f64,
    /// Phone scans taken per device per second; more are dropped and counted.
    pub scans_per_device_per_s: u32,
    /// Phone scans taken per second from all devices together: a flood of
    /// fake ids (a few scans each) is shed here, cheaply, so that route
    /// requests behind it are still answered in time.
    pub scans_per_s: u32,
    /// Route requests taken per device per second; more are answered
    /// `rate_limited`.
    pub requests_per_device_per_s: u32,
}

impl Default for LimitsConfig {
    fn default() -> Self {
        LimitsConfig {
            max_devices: 10_000,
            device_idle_s: 900.0,
            max_pending_requests: 256,
            request_deadline_s: 2.0,
            scans_per_device_per_s: 10,
            scans_per_s: 2000,
            requests_per_device_per_s: 20,
        }
    }
}

impl LimitsConfig {
    pub fn validate(&self) -> Result<(), String> {
        if self.max_devices == 0 || self.max_pending_requests == 0 {
            return Err(
                "[limits] `max_devices` and `max_pending_requests` must be positive".into(),
            );
        }
        if !(self.device_idle_s > 0.0 && self.request_deadline_s > 0.0) {
            return Err(
                "[limits] `device_idle_s` and `request_deadline_s` must be positive seconds".into(),
            );
        }
        if self.scans_per_device_per_s == 0
            || self.scans_per_s == 0
            || self.requests_per_device_per_s == 0
        {
            return Err(
                "[limits] `scans_per_device_per_s`, `scans_per_s` and `requests_per_device_per_s` \
                 must be positive"
                    .into(),
            );
        }
        Ok(())
    }
}

/// Counters a gateway reports about its pipeline. A reload adds the
/// replaced pipeline's to the ones kept (`+=`), so every counter is summed
/// in this one place.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    pub sightings: u64,
    /// Sightings of anchors the site does not know.
    pub sightings_ignored: u64,
    pub fixes: u64,
    pub requests: u64,
    pub routes: u64,
    pub request_errors: u64,
    /// Routes served on their cells' line because the planner's own line
    /// failed its check (`plan::LineSource::Fallback`).
    pub route_line_fallbacks: u64,
    /// Entities whose id cannot be a topic level; their fixes are not published.
    pub bad_device_ids: u64,
    /// Tracks and fingerprint windows forgotten by `[limits]` (idle, or least
    /// recently seen past `max_devices`).
    pub evicted_devices: u64,
    pub evicted_windows: u64,
}

impl std::ops::AddAssign for Stats {
    fn add_assign(&mut self, other: Stats) {
        let Stats {
            sightings,
            sightings_ignored,
            fixes,
            requests,
            routes,
            request_errors,
            route_line_fallbacks,
            bad_device_ids,
            evicted_devices,
            evicted_windows,
        } = other;
        self.sightings += sightings;
        self.sightings_ignored += sightings_ignored;
        self.fixes += fixes;
        self.requests += requests;
        self.routes += routes;
        self.request_errors += request_errors;
        self.route_line_fallbacks += route_line_fallbacks;
        self.bad_device_ids += bad_device_ids;
        self.evicted_devices += evicted_devices;
        self.evicted_windows += evicted_windows;
    }
}

pub struct Pipeline {
    building: Arc<Building>,
    /// One per floor, in [`Building::floors`]' order.
    floors: Vec<FloorStages>,
    /// Each device's floor; `None` on a building of one floor.
    floor_tracks: Option<FloorTracks>,
    /// Plans within a floor with the floor's planner, across floors over
    /// the connectors.
    planner: BuildingPlanner,
    windows: Windows,
    /// Routes across floors being walked, by device.
    journeys: HashMap<Arc<str>, Journey>,
    journey_bounds: Bounds,
    /// Published confidence under which a fix is published as unknown.
    min_confidence: f32,
    /// Per floor, its anchors' ids when what is heard is kept for
    /// recalibration.
    heard_ids: Option<Vec<Vec<String>>>,
    /// Times route replies (`latency_us`); `[planner]`'s, passed in.
    clock: Clock,
    stats: Stats,
    /// Every beacon heard, known or not, bounded by `[limits] max_devices`.
    heard: HeardTable,
    /// The anchors heard in one window, for the floor's evidence.
    heard_scratch: Vec<(usize, f32)>,
}

/// A route across floors being walked: what guiding it on from floor to
/// floor needs (each floor's leg is a session of that floor's guide).
struct Journey {
    request_id: Option<String>,
    profile: Profile,
    to: FloorCell,
    /// The connector the leg being walked ends at (index into
    /// [`Building::connectors`]); none on the last leg.
    connector: Option<usize>,
    t: f64,
}

/// How many beacons a pipeline heard ([`Pipeline::heard_counts`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct HeardCounts {
    pub heard: usize,
    /// Heard, but not beacons of the site.
    pub unknown: usize,
    /// Pushed out of the bounded list by beacons heard more.
    pub forgotten: u64,
}

/// Why a pipeline could not be built: its localizer or its planner.
#[derive(Debug, thiserror::Error)]
pub enum PipelineError {
    #[error(transparent)]
    Localizer(#[from] locate::LocalizerError),
    /// The configured localizer's files failed, and so did the survey-free
    /// one that would have stood in.
    #[error("{failed}; and the pathloss localizer cannot stand in: {error}")]
    NoStandIn {
        failed: String,
        error: locate::LocalizerError,
    },
    #[error(transparent)]
    Planner(#[from] plan::BuildError),
    /// More anchors over all floors than a fingerprint can index.
    #[error(
        "the building's floors list {0} distinct anchors, more than 65535; split it into buildings"
    )]
    TooManyAnchors(usize),
}

impl Pipeline {
    /// Builds the pipeline a config describes, on an already loaded site.
    pub fn new(config: &PipelineConfig, site: Arc<Site>) -> Result<Pipeline, PipelineError> {
        Self::for_building(config, Arc::new(Building::of_site(site)))
    }

    /// [`Pipeline::new`] on a building: one floor's stages per floor, and
    /// each device's floor from what it hears.
    pub fn for_building(
        config: &PipelineConfig,
        building: Arc<Building>,
    ) -> Result<Pipeline, PipelineError> {
        Ok(Self::build(config, building, false)?.0)
    }

    /// [`Pipeline::for_building`] for a gateway starting up: a localizer or
    /// planner whose files do not load (a missing survey, a corrupt or
    /// mismatched model) is replaced by the one that needs no files,
    /// `pathloss` or `astar`, instead of stopping the gateway, so it keeps
    /// locating and routing while someone fixes the file. Config mistakes
    /// are still errors. Returns, for each replacement, what failed and
    /// what serves instead.
    pub fn with_fallbacks(
        config: &PipelineConfig,
        building: Arc<Building>,
    ) -> Result<(Pipeline, Vec<String>), PipelineError> {
        Self::build(config, building, true)
    }

    fn build(
        config: &PipelineConfig,
        building: Arc<Building>,
        fall_back: bool,
    ) -> Result<(Pipeline, Vec<String>), PipelineError> {
        let mut fallbacks = Vec::new();
        let anchors = BuildingAnchors::of(&building, config.window.orientation)?;
        let multi_floor = building.is_multi_floor();
        let mut floors = Vec::with_capacity(building.floors().len());
        let mut planners = Vec::with_capacity(building.floors().len());
        for (index, floor) in building.floors().iter().enumerate() {
            let localizer = if multi_floor {
                config.localizer.for_floor(&floor.name)?
            } else {
                config.localizer.clone()
            };
            floors.push(FloorStages::build(
                config,
                &localizer,
                floor.site.clone(),
                anchors.of_floor[index].clone(),
                fall_back,
                &mut fallbacks,
            )?);
            // Each floor's own trained models where the config names them
            // per floor (`{floor}`), else its geometry.
            let planning = if multi_floor {
                config.planner.for_floor(&floor.name)?
            } else {
                config.planner.clone()
            };
            let mode = planning.mode;
            let _floor =
                multi_floor.then(|| tracing::info_span!("floor", floor = %floor.name).entered());
            if mode != config.planner.mode {
                tracing::info!(
                    "[planner.models] names no floor's models (no `{{floor}}` in their paths): \
                     this floor is planned by A*"
                );
            }
            let on = if multi_floor {
                format!("floor `{}`: ", floor.name)
            } else {
                String::new()
            };
            let planner = match plan::build_mode(&planning, mode, floor.site.clone()) {
                Err(e @ plan::BuildError::Model { .. })
                    if fall_back && mode != plan::PlannerMode::Astar =>
                {
                    fallbacks.push(format!("{on}{e} (planning with astar instead)"));
                    plan::build_mode(&planning, plan::PlannerMode::Astar, floor.site.clone())?
                }
                built => built?,
            };
            planners.push(planner);
        }
        for fallback in &fallbacks {
            tracing::error!("{fallback}");
        }
        let limits = &config.limits;
        let floor_tracks = multi_floor.then(|| {
            FloorTracks::new(
                &building,
                FloorEvidence::of_floors(&anchors.loudness(&building, config.window.orientation)),
                floor_track::SWITCH,
                config.tracker.reset_after_s,
            )
            .bound(limits.max_devices, limits.device_idle_s)
        });
        let pipeline = Pipeline {
            windows: Windows::of_anchors(
                config.window.clone(),
                &anchors.beacons,
                &anchors.gateways(),
            )
            .bound(limits.max_devices, limits.device_idle_s),
            heard_ids: config.localizer.recalibration.enabled.then(|| {
                building
                    .floors()
                    .iter()
                    .map(|floor| locate::window::anchor_ids(&floor.site, config.window.orientation))
                    .collect()
            }),
            planner: BuildingPlanner::new(building.clone(), config.planner.connectivity, planners),
            floors,
            floor_tracks,
            journeys: HashMap::default(),
            journey_bounds: Bounds::new(limits.max_devices, limits.device_idle_s),
            min_confidence: config.localizer.min_confidence,
            building,
            clock: config.planner.clock,
            stats: Stats::default(),
            heard: HeardTable::new(limits.max_devices),
            heard_scratch: Vec::new(),
        };
        Ok((pipeline, fallbacks))
    }

    /// The building served.
    pub fn building(&self) -> &Arc<Building> {
        &self.building
    }

    /// The counters so far.
    pub fn stats(&self) -> Stats {
        Stats {
            sightings_ignored: self.windows.unknown_anchor_count(),
            evicted_windows: self.windows.evicted_count(),
            evicted_devices: self.floors.iter().map(|f| f.tracker.evicted_count()).sum(),
            ..self.stats
        }
    }

    /// The floor a device is on (always the only one of a one-floor site);
    /// `None` before it is heard on a building of several.
    fn floor_of(&self, device: &str) -> Option<usize> {
        match &self.floor_tracks {
            Some(tracks) => tracks.floor_of(device),
            None => Some(0),
        }
    }

    /// Bytes held for guiding `device`, if it has a session: the session
    /// and its tracker's belief of a walker walking the route.
    pub fn guided_bytes(&self, device: &str) -> Option<usize> {
        let floor = &self.floors[self.floor_of(device)?];
        let session = floor.guide.session(device)?;
        Some(session.state_bytes() + floor.tracker.walking_bytes(device))
    }

    /// The beacons heard most so far, at most `limit`, each marked `known`
    /// when the site has it: what a user compares with the site file.
    pub fn heard(&self, limit: usize) -> Vec<HeardBeacon> {
        let known = self.known_beacons();
        self.heard.report(limit, |id| known.contains(id))
    }

    /// How many beacons were heard (at most `[limits] max_devices`), and how
    /// many of them the site does not have.
    pub fn heard_counts(&self) -> HeardCounts {
        let known = self.known_beacons();
        HeardCounts {
            heard: self.heard.count(),
            unknown: self.heard.count_where(|id| !known.contains(id)),
            forgotten: self.heard.replaced(),
        }
    }

    fn known_beacons(&self) -> foldhash::HashSet<crate::sighting::BeaconId> {
        self.building
            .floors()
            .iter()
            .flat_map(|f| f.site.beacons.iter().map(|b| b.beacon))
            .collect()
    }

    /// Hands what this pipeline keeps per device on to the one replacing
    /// it (a reload), so that nothing starts afresh that the new building
    /// can still use: what was heard; each floor's tracks, to the floor of
    /// the same name (moved where the grid is the same, else restarted from
    /// their last place in metres: `Tracker::take_over`), so devices keep
    /// their location and their route requests their `from`; and, on the
    /// same grid, the guided sessions (on another they end,
    /// `Guide::take_over`); the devices' floors and routes across floors
    /// when the floors are the same; the open fingerprint windows where the
    /// anchors are the same (`Windows::take_over`). Tracks and sessions that
    /// end are reported with the next outputs (forgotten, adherence).
    /// Returns how many tracks were kept.
    pub fn hand_over_to(&mut self, next: &mut Pipeline) -> usize {
        let heard = std::mem::replace(&mut self.heard, HeardTable::new(1));
        next.heard.absorb(heard);
        next.windows.take_over(&mut self.windows);
        let same_floors = self.building.floors().len() == next.building.floors().len()
            && self
                .building
                .floors()
                .iter()
                .zip(next.building.floors())
                .all(|(a, b)| a.name == b.name);
        if same_floors {
            // The devices' floors move; the evidence stays the new
            // building's (its beacons may have changed).
            if let (Some(new), Some(old)) = (&mut next.floor_tracks, &mut self.floor_tracks) {
                new.take_over(old);
            }
            std::mem::swap(&mut next.journeys, &mut self.journeys);
        }
        let mut kept = 0;
        for (index, floor) in next.building.floors().iter().enumerate() {
            let Some(old) = self.building.floor_named(&floor.name) else {
                continue;
            };
            let (old, new) = (&mut self.floors[old], &mut next.floors[index]);
            new.guide
                .take_over(&mut old.guide, new.site.same_grid(&old.site));
            kept += new.tracker.take_over(&mut old.tracker);
        }
        kept
    }

    /// Number of entities with a track.
    pub fn tracked(&self) -> usize {
        self.floors.iter().map(|f| f.tracker.len()).sum()
    }

    /// Entities with an open fingerprint window.
    pub fn windows_open(&self) -> usize {
        self.windows.entity_count()
    }

    /// Handles one event, appending what it causes to publish to `out`.
    pub fn handle(&mut self, event: &Event, out: &mut Vec<Output>) {
        match event {
            Event::Advert(sighting) => {
                self.stats.sightings += 1;
                self.heard.add(sighting);
                match self.windows.push(sighting) {
                    Some(fp) => self.fix(&fp, sighting.t, out),
                    None => self.tick(sighting, out),
                }
            }
            Event::Request(request) => {
                let reply = self.route(request);
                self.reply(reply, false, out);
            }
            // Ground truth is for scoring a replay, not for the pipeline:
            // passed on for the sinks that score.
            Event::Truth(truth) => out.push(Output::Truth(truth.clone())),
        }
    }

    /// Ends the guidance session of `device` at its request, publishing its
    /// last message (`cancelled`); nothing when it has none.
    pub fn cancel(&mut self, device: &str, t: f64, out: &mut Vec<Output>) {
        self.journeys.remove(device);
        if let Some(floor) = self.floor_of(device)
            && let Some(last) = self.floors[floor].guide.cancel(device, t)
        {
            out.push(Output::Guidance(Box::new(last)));
        }
        self.forgotten_and_finished(out);
    }

    /// Closes all open windows (end of a replay).
    pub fn finish(&mut self, out: &mut Vec<Output>) {
        for fp in self.windows.flush() {
            self.fix(&fp, fp.t, out);
        }
    }

    /// What the stages let go of since the last call: devices whose tracks
    /// were forgotten, and the adherence of guidance sessions that ended.
    fn forgotten_and_finished(&mut self, out: &mut Vec<Output>) {
        for floor in &mut self.floors {
            for device in floor.tracker.take_evicted() {
                if let Some(tracks) = &mut self.floor_tracks {
                    tracks.forget(&device);
                }
                self.journeys.remove(&device);
                out.push(Output::Forgotten(device));
            }
            out.extend(
                floor
                    .guide
                    .take_finished()
                    .into_iter()
                    .map(Output::Adherence),
            );
        }
    }

    /// Guidance between fixes: the sighting's time tells a guided device's
    /// session where its walker is by now (announcements and arrival need
    /// not wait for the next fix). Devices are the observers of what they
    /// hear; a guided advertiser (a tag heard by gateways) is judged at
    /// its fixes only.
    fn tick(&mut self, sighting: &crate::sighting::Sighting, out: &mut Vec<Output>) {
        if self.orientation() != Orientation::Observer {
            return;
        }
        let Some(index) = self.floor_of(&sighting.observer) else {
            return;
        };
        let floor = &mut self.floors[index];
        if floor.guide.is_empty() {
            return;
        }
        if let Some(guidance) = floor
            .guide
            .tick(&floor.site, &sighting.observer, sighting.t)
        {
            out.push(Output::Guidance(Box::new(guidance)));
            self.forgotten_and_finished(out);
        }
    }

    /// One fix from the window `fp`, closed by an event at `now`.
    fn fix(&mut self, fp: &Fingerprint, now: f64, out: &mut Vec<Output>) {
        if fp.heard_count() == 0 {
            return;
        }
        if !valid_device_id(&fp.entity) {
            self.stats.bad_device_ids += 1;
            return;
        }
        let (index, floor_probability, entered) = match &mut self.floor_tracks {
            None => (0, 1.0, None),
            Some(tracks) => {
                self.heard_scratch.clear();
                self.heard_scratch.extend(
                    fp.heard
                        .iter()
                        .zip(&fp.rssi)
                        .enumerate()
                        .filter(|(_, (heard, _))| **heard)
                        .map(|(anchor, (_, &rssi))| (anchor, rssi)),
                );
                let before = tracks.floor_of(&fp.entity);
                let step = tracks.update(&fp.entity, fp.t, &self.heard_scratch);
                let entered = match step.change {
                    FloorChange::From(from) => Some(tracks.entries(from, step.floor).to_vec()),
                    _ => None,
                };
                if let Some(left) = before.filter(|&f| f != step.floor) {
                    self.floors[left].tracker.forget(&fp.entity);
                    self.floors[left].guide.leave(&fp.entity, fp.t);
                }
                (step.floor, step.probability, entered)
            }
        };
        let floor = &mut self.floors[index];
        let located = floor.locate(fp, entered.as_deref());
        self.stats.fixes += 1;
        let floor_known = floor_probability >= floor_track::KNOWN;
        let confidence = located.confidence * floor_probability as f32;
        let known = floor_known && confidence >= self.min_confidence;
        let cell = known.then_some(located.fix.cell);
        let world = cell.map(|c| floor.site.world_of_cell(c));
        let building_floor = &self.building.floors()[index];
        let location = Location {
            schema: LOCATION_SCHEMA,
            device: fp.entity.to_string(),
            t: fp.t,
            floor: floor_known.then(|| FloorName {
                name: building_floor.name.clone(),
                level: building_floor.level,
            }),
            cell,
            label: cell.and_then(|c| floor.site.label(c)),
            x_m: world.map(|[x, _]| x),
            y_m: world.map(|[_, y]| y),
            place: cell
                .and_then(|c| floor.site.nearest_place(c, 2.0))
                .map(str::to_owned),
            confidence,
            anchors_heard: fp.heard_count(),
        };
        out.push(Output::Location(location));
        // A window whose floor is not known would teach a floor's radio
        // model what another floor hears.
        if let Some(heard) = self
            .heard_ids
            .as_ref()
            .filter(|_| floor_known)
            .and_then(|ids| floor.heard(&fp.entity, fp.t, &ids[index]))
        {
            out.push(Output::Heard(if self.floor_tracks.is_some() {
                heard.on_floor(&building_floor.name)
            } else {
                heard
            }));
        }
        if entered.is_some() && self.journeys.contains_key(&fp.entity) {
            // Onto another floor on a route across floors: its leg there.
            self.next_leg(&fp.entity, index, located.fix.cell, fp.t, out);
            return;
        }
        // Leaving the route is judged on the fix, progress along it on the
        // belief of a walker walking it ([`Tracker::update_walking`]).
        let seen = floor.located(cell, &located.fix, located.walked_mean);
        if let Some(guidance) = floor.guide.update(&floor.site, &fp.entity, seen, fp.t, now) {
            let off_route = guidance.event == Some(GuidanceEvent::OffRoute);
            out.push(Output::Guidance(Box::new(guidance)));
            if off_route {
                self.reroute(&fp.entity, index, located.fix.cell, fp.t, out);
            }
        }
        self.forgotten_and_finished(out);
    }

    /// A device on a route across floors came onto floor `floor` at `cell`:
    /// the rest of its way is planned from there (the next leg when it took
    /// the connector it was sent to) and guided on.
    fn next_leg(
        &mut self,
        device: &Arc<str>,
        floor: usize,
        cell: Cell,
        t: f64,
        out: &mut Vec<Output>,
    ) {
        let Some(journey) = self.journeys.get(&**device) else {
            return;
        };
        let (to, profile, request_id) = (journey.to, journey.profile, journey.request_id.clone());
        let started = self.clock.start();
        match self.planner.plan(FloorCell { floor, cell }, to, profile) {
            Ok(route) => {
                let body =
                    FloorsRouteBody::new(&self.planner, profile, &route, started.elapsed_us())
                        .with_reason("next_floor");
                let reply = RouteReply {
                    schema: PATH_SCHEMA,
                    device: device.to_string(),
                    request_id,
                    t,
                    outcome: RouteOutcome::Floors(Box::new(body)),
                };
                self.reply(reply, true, out);
            }
            Err(e) => {
                tracing::warn!(
                    device = &**device,
                    code = e.code().as_str(),
                    "cannot plan on from the floor a device came onto: {e}"
                );
                self.journeys.remove(&**device);
                self.forgotten_and_finished(out);
            }
        }
    }

    /// Publishes a route reply and, for a route, starts guiding along it.
    fn reply(&mut self, reply: RouteReply, rerouted: bool, out: &mut Vec<Output>) {
        let first = match &reply.outcome {
            RouteOutcome::Route(body) => {
                self.journeys.remove(reply.device.as_str());
                Some(self.guide_along(0, &reply, body, rerouted))
            }
            RouteOutcome::Floors(body) => self.guide_across(&reply, body, rerouted),
            RouteOutcome::Error { .. } => None,
        };
        out.push(Output::Route(Box::new(reply)));
        if let Some(first) = first {
            out.push(Output::Guidance(Box::new(first)));
        }
        self.forgotten_and_finished(out);
    }

    /// Starts guiding `reply`'s device along `body`, a route just
    /// published on floor `floor`; returns the session's first message.
    fn guide_along(
        &mut self,
        floor: usize,
        reply: &RouteReply,
        body: &RouteBody,
        rerouted: bool,
    ) -> Guidance {
        let floor = &mut self.floors[floor];
        let (route, line) = body.route_and_line(&floor.site);
        let profile = Profile::parse(body.profile).unwrap_or_default();
        floor.guide.start(
            &floor.site,
            &reply.device,
            reply.request_id.clone(),
            profile,
            &route,
            &line,
            reply.t,
            rerouted,
        )
    }

    /// Starts guiding a route across floors along its first leg, to its
    /// connector, keeping what the next floors' legs need; `None` when the
    /// first leg's floor is not one of the building's (it always is: the
    /// planner drew it).
    fn guide_across(
        &mut self,
        reply: &RouteReply,
        body: &FloorsRouteBody,
        rerouted: bool,
    ) -> Option<Guidance> {
        let leg = body.legs.first()?;
        let floor = self.building.floor_named(&leg.floor)?;
        let to = FloorCell {
            floor: self.building.floor_named(&body.to.floor)?,
            cell: body.to.cell,
        };
        let connector = body.connectors.first().and_then(|c| {
            self.building
                .connectors()
                .iter()
                .position(|known| known.id == c.id)
        });
        // Came off the connector of the leg before: "Leave the lift on L1."
        let left = self
            .journeys
            .get(reply.device.as_str())
            .and_then(|j| j.connector)
            .map(|c| &self.building.connectors()[c])
            .filter(|c| rerouted && c.stops.iter().any(|s| s.floor == floor))
            .map(|c| leave_sentence(c.kind, &self.building.floors()[floor].name));
        let device: Arc<str> = Arc::from(reply.device.as_str());
        let full = self.journeys.len() >= self.journey_bounds.max()
            && !self.journeys.contains_key(&device);
        self.journey_bounds
            .make_room(&mut self.journeys, reply.t, full, |j| j.t, |_| {});
        self.journeys.insert(
            device,
            Journey {
                request_id: reply.request_id.clone(),
                profile: Profile::parse(body.profile).unwrap_or_default(),
                to,
                connector,
                t: reply.t,
            },
        );
        let mut first = self.guide_along(floor, reply, &leg.route, rerouted);
        if let (Some(c), Some(ride)) = (connector, leg.route.instructions.last()) {
            let stages = &mut self.floors[floor];
            first = stages
                .guide
                .end_at_connector(
                    &stages.site,
                    &reply.device,
                    connector_noun(self.building.connectors()[c].kind),
                    ride.text.clone(),
                    reply.t,
                )
                .unwrap_or(first);
        }
        if let Some(left) = left {
            first.text = Some(match first.text {
                Some(text) => format!("{left} {text}"),
                None => left,
            });
        }
        Some(first)
    }

    /// Re-plans the route of a device that left it, from its tracked `cell`
    /// on floor `floor` to the same destination (the end of the floor's leg
    /// on a route across floors), and publishes it with reason `off_route`.
    /// When no route can be planned the session stays off route (and the
    /// device is told so by its guidance) until it walks back or asks again.
    fn reroute(&mut self, device: &str, floor: usize, cell: Cell, t: f64, out: &mut Vec<Output>) {
        let Some(session) = self.floors[floor].guide.session(device) else {
            return;
        };
        let (to, profile) = (session.destination(), session.profile());
        let request_id = session.request_id().map(str::to_owned);
        let started = self.clock.start();
        let planner = self.planner.floor_planner(floor);
        let planned = match planner.plan(cell, to, profile) {
            Ok(planned) => planned,
            Err(e) => {
                tracing::warn!(
                    device,
                    code = e.code().as_str(),
                    "cannot re-plan a route off which the device walked: {e}"
                );
                return;
            }
        };
        let site = &self.floors[floor].site;
        let mut body = RouteBody::new(
            site,
            planner,
            profile,
            cell,
            to,
            &planned,
            started.elapsed_us(),
        );
        body.reason = Some("off_route");
        self.count_line(&body);
        let reply = RouteReply {
            schema: PATH_SCHEMA,
            device: device.to_owned(),
            request_id,
            t,
            outcome: RouteOutcome::Route(body.clone()),
        };
        // A leg of a route across floors stays one (its session still
        // walks to its connector), and the journey goes on.
        let first = self.guide_along(floor, &reply, &body, true);
        out.push(Output::Route(Box::new(reply)));
        out.push(Output::Guidance(Box::new(first)));
        self.forgotten_and_finished(out);
    }

    /// Plans a route from the device's tracked cell; every failure becomes an
    /// error reply with a stable code.
    pub(crate) fn route(&mut self, request: &RouteRequest) -> RouteReply {
        let started = self.clock.start();
        self.stats.requests += 1;
        let outcome = self.plan_request(request, started);
        match &outcome {
            RouteOutcome::Route(body) => {
                self.stats.routes += 1;
                self.count_line(body);
            }
            RouteOutcome::Floors(body) => {
                self.stats.routes += 1;
                for leg in &body.legs {
                    self.count_line(&leg.route);
                }
            }
            RouteOutcome::Error { .. } => self.stats.request_errors += 1,
        }
        RouteReply {
            schema: PATH_SCHEMA,
            device: request.device.clone(),
            request_id: request.request_id.clone(),
            t: request.t,
            outcome,
        }
    }

    fn count_line(&mut self, body: &RouteBody) {
        if body.line_from == plan::LineSource::Fallback {
            self.stats.route_line_fallbacks += 1;
        }
    }

    /// The error reply to a request that could not even be read (bad JSON,
    /// oversized payload), counted like any other failed request.
    pub fn reject(
        &mut self,
        device: &str,
        request_id: Option<String>,
        t: f64,
        code: RouteErrorCode,
        message: String,
    ) -> RouteReply {
        self.stats.requests += 1;
        self.stats.request_errors += 1;
        RouteReply {
            schema: PATH_SCHEMA,
            device: device.to_owned(),
            request_id,
            t,
            outcome: RouteOutcome::Error {
                error: ErrorBody {
                    code,
                    message,
                    retry_after_s: None,
                },
            },
        }
    }

    /// Which side of a sighting this pipeline locates.
    pub fn orientation(&self) -> Orientation {
        self.windows.config().orientation
    }

    fn plan_request(&self, request: &RouteRequest, started: Stopwatch) -> RouteOutcome {
        let error = |code: RouteErrorCode, message: String| RouteOutcome::Error {
            error: ErrorBody {
                code,
                message,
                retry_after_s: None,
            },
        };
        let profile = match request.profile.as_deref() {
            None => Profile::Default,
            Some(name) => match Profile::parse(name) {
                Some(p) => p,
                None => {
                    return error(
                        RouteErrorCode::UnknownProfile,
                        plan::unknown_profile_message(name),
                    );
                }
            },
        };
        let fix = self.floor_of(&request.device).and_then(|floor| {
            let fix = self.floors[floor].tracker.last_fix(&request.device)?;
            Some(FloorCell {
                floor,
                cell: fix.cell,
            })
        });
        let Some(from) = fix else {
            return error(
                RouteErrorCode::UnknownDevice,
                format!(
                    "device `{}` has no location yet; a device must be heard before it can ask for a route",
                    request.device
                ),
            );
        };
        let to = match self.planner.resolve(request.floor.as_deref(), &request.to) {
            Ok(to) => to,
            Err(e) => return error(e.code(), e.to_string()),
        };
        if !self.building.is_multi_floor() {
            let floor = &self.floors[0];
            let planner = self.planner.floor_planner(0);
            return match planner.plan(from.cell, to.cell, profile) {
                Ok(planned) => RouteOutcome::Route(RouteBody::new(
                    &floor.site,
                    planner,
                    profile,
                    from.cell,
                    to.cell,
                    &planned,
                    started.elapsed_us(),
                )),
                Err(e) => error(e.code(), e.to_string()),
            };
        }
        match self.planner.plan(from, to, profile) {
            Ok(route) => RouteOutcome::Floors(Box::new(FloorsRouteBody::new(
                &self.planner,
                profile,
                &route,
                started.elapsed_us(),
            ))),
            Err(e) => error(e.code(), e.to_string()),
        }
    }
}

/// Every floor's anchors listed once, in the order of the building's
/// fingerprints.
struct BuildingAnchors {
    beacons: Vec<(crate::sighting::BeaconId, Option<crate::sighting::Mac>)>,
    gateways: Vec<String>,
    /// Per floor, for each of its anchors (its site's order): the
    /// building's index of it.
    of_floor: Vec<Vec<usize>>,
}

impl BuildingAnchors {
    fn of(building: &Building, orientation: Orientation) -> Result<BuildingAnchors, PipelineError> {
        let mut anchors = BuildingAnchors {
            beacons: Vec::new(),
            gateways: Vec::new(),
            of_floor: Vec::new(),
        };
        for floor in building.floors() {
            let site = &floor.site;
            let of_floor = match orientation {
                Orientation::Observer => site
                    .beacons
                    .iter()
                    .map(|b| position_or_push(&mut anchors.beacons, (b.beacon, b.mac)))
                    .collect::<Vec<_>>(),
                Orientation::Advertiser => site
                    .gateways
                    .iter()
                    .map(|g| position_or_push(&mut anchors.gateways, g.id.clone()))
                    .collect(),
            };
            anchors.of_floor.push(of_floor);
        }
        let count = anchors.beacons.len() + anchors.gateways.len();
        if count > usize::from(u16::MAX) {
            return Err(PipelineError::TooManyAnchors(count));
        }
        Ok(anchors)
    }

    /// Per floor, each anchor it lists and how loudly it is heard over the
    /// floor (a beacon's `heard_dbm`; gateways have none), as
    /// [`FloorEvidence::of_floors`] takes them.
    fn loudness(
        &self,
        building: &Building,
        orientation: Orientation,
    ) -> Vec<Vec<(usize, Option<f64>)>> {
        self.of_floor
            .iter()
            .zip(building.floors())
            .map(|(anchors, floor)| {
                anchors
                    .iter()
                    .enumerate()
                    .map(|(i, &anchor)| {
                        let dbm = match orientation {
                            Orientation::Observer => floor.site.beacons[i].heard_dbm,
                            Orientation::Advertiser => None,
                        };
                        (anchor, dbm)
                    })
                    .collect()
            })
            .collect()
    }

    fn gateways(&self) -> Vec<&str> {
        self.gateways.iter().map(String::as_str).collect()
    }
}

/// The index of `item` in `list`, added at its end when it is not there.
fn position_or_push<T: PartialEq>(list: &mut Vec<T>, item: T) -> usize {
    list.iter().position(|x| *x == item).unwrap_or_else(|| {
        list.push(item);
        list.len() - 1
    })
}

#[cfg(test)]
mod tests {
    use std::path::{Path, PathBuf};

    use super::*;

    fn building(site: Arc<Site>) -> Arc<Building> {
        Arc::new(Building::of_site(site))
    }

    /// The repository's root, the pipeline sections of the shipped config
    /// (`config/gangway.toml`, relative paths resolved) and its site.
    fn shipped() -> (PathBuf, PipelineConfig, Arc<Site>) {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../..");
        let path = root.join("config/gangway.toml");
        let text = std::fs::read_to_string(&path).unwrap();
        let mut config: PipelineConfig = toml::from_str(&text).unwrap();
        config.localizer.resolve_paths(path.parent().unwrap());
        config.planner.resolve_paths(path.parent().unwrap());
        let site: toml::Table = toml::from_str(&text).unwrap();
        let site = path.with_file_name(site["site"].as_str().unwrap());
        (root, config, Arc::new(Site::load(&site).unwrap()))
    }

    /// The shipped config with a localizer model and a planner model that do
    /// not exist.
    fn broken_config() -> PipelineConfig {
        let (root, mut config, _) = shipped();
        config.localizer.method = locate::Method::Onnx;
        config.localizer.onnx.model = root.join("models/missing-cells.onnx");
        config.planner.mode = plan::PlannerMode::Conditional;
        config.planner.models.conditional_generator = root.join("models/missing-paths.onnx");
        config
    }

    #[test]
    fn files_that_fail_refuse_a_pipeline_or_fall_back_to_file_free_stages() {
        let config = broken_config();
        let (_, _, site) = shipped();
        assert!(Pipeline::new(&config, site.clone()).is_err());

        let (pipeline, fallbacks) = Pipeline::with_fallbacks(&config, building(site)).unwrap();
        assert_eq!(fallbacks.len(), 2, "{fallbacks:?}");
        assert!(
            fallbacks[0].starts_with("[localizer] method = \"onnx\": ")
                && fallbacks[0].contains("missing-cells.onnx")
                && fallbacks[0].ends_with(" (locating with pathloss instead)"),
            "{}",
            fallbacks[0]
        );
        assert!(
            fallbacks[1].starts_with("[planner] mode = \"conditional\": ")
                && fallbacks[1].contains("missing-paths.onnx")
                && fallbacks[1].ends_with(" (planning with astar instead)"),
            "{}",
            fallbacks[1]
        );
        // What serves instead are working stages.
        let planner = pipeline.planner.floor_planner(0);
        assert_eq!(planner.mode(), "astar");
        let site = pipeline.building().floors()[0].site.clone();
        let (from, to) = (
            site.place("help desk").unwrap(),
            site.place("printers").unwrap(),
        );
        assert!(planner.plan(from, to, Profile::Default).is_ok());
    }

    /// Only files fall back: a config mistake stops the start-up as it
    /// stops a reload.
    #[test]
    fn config_mistakes_do_not_fall_back() {
        let (_, shipped, site) = shipped();

        let mut no_survey = shipped.clone();
        no_survey.localizer.method = locate::Method::Knn;
        no_survey.localizer.knn.survey = None;
        let err = Pipeline::with_fallbacks(&no_survey, building(site.clone()))
            .err()
            .unwrap();
        assert!(format!("{err:#}").contains("set `survey`"), "{err:#}");

        let mut no_samples = shipped.clone();
        no_samples.planner.mode = plan::PlannerMode::Conditional;
        no_samples.planner.conditional.samples = 0;
        let err = Pipeline::with_fallbacks(&no_samples, building(site.clone()))
            .err()
            .unwrap();
        assert!(format!("{err:#}").contains("samples"), "{err:#}");

        // A file that fails, with nothing to stand in (no beacon has a
        // position for pathloss): both errors are told.
        let unplaced = Site::parse(
            concat!(
                "name = \"unplaced\"\ncell_m = 1.0\nmap = '''\n###\n'''\n",
                "[[beacon]]\nid = \"b1\"\nuuid = \"5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84\"\n",
                "major = 1\nminor = 1\n",
            ),
            std::path::Path::new("unplaced.toml"),
        )
        .unwrap();
        let err = Pipeline::with_fallbacks(&broken_config(), building(Arc::new(unplaced)))
            .err()
            .unwrap();
        let text = format!("{err:#}");
        assert!(
            text.contains("missing-cells.onnx") && text.contains("cannot stand in"),
            "{text}"
        );
    }

    #[test]
    fn a_reload_hands_tracks_windows_and_sessions_to_the_new_pipeline() {
        let (_, config, site) = shipped();
        let mut old = Pipeline::new(&config, site.clone()).unwrap();
        let mut out = Vec::new();
        // A phone hearing the site's beacons at 1 Hz for 9 s.
        for k in 0..10 {
            for b in &site.beacons {
                let sighting = crate::sighting::Sighting {
                    advertiser_mac: b.mac,
                    t: f64::from(k),
                    observer: "phone".into(),
                    advertiser: b.beacon,
                    tx_power: None,
                    rssi: -70,
                };
                old.handle(&Event::Advert(sighting), &mut out);
            }
        }
        assert!(old.tracked() == 1 && old.windows_open() == 1);
        let mut new = Pipeline::new(&config, site.clone()).unwrap();
        assert_eq!(old.hand_over_to(&mut new), 1);
        assert_eq!((new.tracked(), new.windows_open()), (1, 1));
        assert_eq!((old.tracked(), old.windows_open()), (0, 0));
        // The phone is served where it was, unheard since.
        let reply = new.route(&RouteRequest {
            device: "phone".into(),
            request_id: Some("r".into()),
            to: plan::Destination::Place("help desk".into()),
            floor: None,
            profile: None,
            t: 10.0,
        });
        assert!(matches!(reply.outcome, RouteOutcome::Route(_)), "{reply:?}");
    }
}
