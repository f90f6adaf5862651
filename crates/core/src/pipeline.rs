//! The pipeline every mode runs: events → fingerprint windows → localizer →
//! tracker → planner → outgoing messages, and guidance along the routes it
//! served (a session per device, see [`crate::guide`]): on each fix of a
//! guided device a guidance message, and a route re-planned from where the
//! device is when it has left its route.
//!
//! It does no I/O and keeps no clock of its own: the runtime (`daemon` in the
//! binary) and the tests feed it [`Event`]s and hand the typed [`Output`]s it returns
//! to the sinks. It knows no topic and writes no JSON. That keeps replay as
//! fast as the CPU allows and makes the daemon's behaviour testable from a log.

use std::sync::Arc;

use serde::Deserialize;

use crate::clock::{Clock, Stopwatch};
use crate::event::{Event, RouteRequest};
use crate::guide::{GuidanceConfig, GuidanceEvent, Guide, Located};
use crate::locate::tracker::{Tracker, TrackerConfig};
use crate::locate::window::{Fingerprint, Orientation, WindowConfig, Windows};
use crate::locate::{self, Localizer};
use crate::plan::{self, Planner, PlannerConfig, Profile, RouteErrorCode};
use crate::publish::{
    ErrorBody, LOCATION_SCHEMA, Location, Output, PATH_SCHEMA, RouteBody, RouteOutcome, RouteReply,
};
use crate::sighting::heard::{HeardBeacon, HeardTable};
use crate::sighting::valid_device_id;
use crate::site::{Cell, Site};

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
    site: Arc<Site>,
    windows: Windows,
    localizer: Box<dyn Localizer>,
    tracker: Tracker,
    planner: Box<dyn Planner>,
    guide: Guide,
    log_likelihood: Vec<f32>,
    /// Published confidence under which a fix is published as unknown.
    min_confidence: f32,
    /// The anchors' ids when what is heard is kept for recalibration.
    heard_ids: Option<Vec<String>>,
    /// Times route replies (`latency_us`); `[planner]`'s, passed in.
    clock: Clock,
    stats: Stats,
    /// Every beacon heard, known or not, bounded by `[limits] max_devices`.
    heard: HeardTable,
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
}

impl Pipeline {
    /// Builds the pipeline a config describes, on an already loaded site.
    pub fn new(config: &PipelineConfig, site: Arc<Site>) -> Result<Pipeline, PipelineError> {
        Ok(Self::build(config, site, false)?.0)
    }

    /// [`Pipeline::new`] for a gateway starting up: a localizer or planner
    /// whose files do not load (a missing survey, a corrupt or mismatched
    /// model) is replaced by the one that needs no files, `pathloss` or
    /// `astar`, instead of stopping the gateway, so it keeps locating and
    /// routing while someone fixes the file. Config mistakes are still errors.
    /// Returns, for each replacement, what failed and what serves instead.
    pub fn with_fallbacks(
        config: &PipelineConfig,
        site: Arc<Site>,
    ) -> Result<(Pipeline, Vec<String>), PipelineError> {
        Self::build(config, site, true)
    }

    fn build(
        config: &PipelineConfig,
        site: Arc<Site>,
        fall_back: bool,
    ) -> Result<(Pipeline, Vec<String>), PipelineError> {
        let mut fallbacks = Vec::new();
        let build = |localizer: &locate::LocalizerConfig| {
            locate::build(localizer, &site, &config.window, &config.tracker)
        };
        let localizer = match build(&config.localizer) {
            Err(e) if fall_back && e.is_file_failure() => {
                let failed = format!(
                    "[localizer] method = \"{}\": {e}",
                    config.localizer.method.name()
                );
                // The survey-free model stands in; without its calibration
                // file when that is what failed.
                let mut pathloss = locate::LocalizerConfig {
                    method: locate::Method::Pathloss,
                    ..config.localizer.clone()
                };
                if matches!(e, locate::LocalizerError::Calibration(_)) {
                    pathloss.pathloss.calibration = None;
                }
                let localizer = build(&pathloss).map_err(|error| PipelineError::NoStandIn {
                    failed: failed.clone(),
                    error,
                })?;
                fallbacks.push(format!("{failed} (locating with pathloss instead)"));
                localizer
            }
            built => built?,
        };
        let planner = match plan::build(&config.planner, site.clone()) {
            Err(e @ plan::BuildError::Model { .. })
                if fall_back && config.planner.mode != plan::PlannerMode::Astar =>
            {
                fallbacks.push(format!("{e} (planning with astar instead)"));
                plan::build_mode(&config.planner, plan::PlannerMode::Astar, site.clone())?
            }
            built => built?,
        };
        for fallback in &fallbacks {
            tracing::error!("{fallback}");
        }
        let pipeline = Pipeline {
            windows: Windows::new(config.window.clone(), &site)
                .bound(config.limits.max_devices, config.limits.device_idle_s),
            localizer,
            tracker: Tracker::new(config.tracker.clone(), site.clone())
                .bound(config.limits.max_devices, config.limits.device_idle_s),
            planner,
            guide: Guide::new(
                config.guidance.clone(),
                config.guidance.fix_lag_s(&config.window),
            ),
            log_likelihood: vec![0.0; site.open_cells().len()],
            min_confidence: config.localizer.min_confidence,
            heard_ids: config
                .localizer
                .recalibration
                .enabled
                .then(|| locate::window::anchor_ids(&site, config.window.orientation)),
            site,
            clock: config.planner.clock,
            stats: Stats::default(),
            heard: HeardTable::new(config.limits.max_devices),
        };
        Ok((pipeline, fallbacks))
    }

    /// The counters so far.
    pub fn stats(&self) -> Stats {
        Stats {
            sightings_ignored: self.windows.unknown_anchor_count(),
            evicted_windows: self.windows.evicted_count(),
            evicted_devices: self.tracker.evicted_count(),
            ..self.stats
        }
    }

    /// Bytes held for guiding `device`, if it has a session: the session
    /// and its tracker's belief of a walker walking the route.
    pub fn guided_bytes(&self, device: &str) -> Option<usize> {
        let session = self.guide.session(device)?;
        Some(session.state_bytes() + self.tracker.walking_bytes(device))
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
        self.site.beacons.iter().map(|b| b.beacon).collect()
    }

    /// Hands what this pipeline keeps per device on to the one replacing
    /// it (a reload), so that nothing starts afresh that the new site can
    /// still use: what was heard; the tracks (moved where the grid is the
    /// same, else restarted from their last place in metres:
    /// `Tracker::take_over`), so devices keep their location and their
    /// route requests their `from`; and, on the same grid, the guided
    /// sessions (on another they end, `Guide::take_over`); the open
    /// fingerprint windows where the anchors are the same
    /// (`Windows::take_over`). Tracks and sessions that end are reported
    /// with the next outputs (forgotten, adherence). Returns how many tracks
    /// were kept.
    pub fn hand_over_to(&mut self, next: &mut Pipeline) -> usize {
        let heard = std::mem::replace(&mut self.heard, HeardTable::new(1));
        next.heard.absorb(heard);
        next.windows.take_over(&mut self.windows);
        next.guide
            .take_over(&mut self.guide, next.site.same_grid(&self.site));
        next.tracker.take_over(&mut self.tracker)
    }

    /// Number of entities with a track.
    pub fn tracked(&self) -> usize {
        self.tracker.len()
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
        if let Some(last) = self.guide.cancel(device, t) {
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
        out.extend(
            self.tracker
                .take_evicted()
                .into_iter()
                .map(Output::Forgotten),
        );
        out.extend(
            self.guide
                .take_finished()
                .into_iter()
                .map(Output::Adherence),
        );
    }

    /// Guidance between fixes: the sighting's time tells a guided device's
    /// session where its walker is by now (announcements and arrival need
    /// not wait for the next fix). Devices are the observers of what they
    /// hear; a guided advertiser (a tag heard by gateways) is judged at
    /// its fixes only.
    fn tick(&mut self, sighting: &crate::sighting::Sighting, out: &mut Vec<Output>) {
        if self.guide.is_empty() || self.orientation() != Orientation::Observer {
            return;
        }
        if let Some(guidance) = self.guide.tick(&self.site, &sighting.observer, sighting.t) {
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
        self.localizer
            .log_likelihood(&fp.rssi, &fp.heard, &mut self.log_likelihood);
        let walk = self.guide.expected_walk(&self.site, &fp.entity, fp.t);
        let (fix, walked_mean) =
            self.tracker
                .update_walking(&fp.entity, fp.t, &self.log_likelihood, walk.as_ref());
        self.stats.fixes += 1;
        let confidence = self.localizer.confidence(fix.confidence, fp.heard_count());
        let known = confidence >= self.min_confidence;
        let cell = known.then_some(fix.cell);
        let world = cell.map(|c| self.site.world_of_cell(c));
        let location = Location {
            schema: LOCATION_SCHEMA,
            device: fp.entity.to_string(),
            t: fp.t,
            cell,
            label: cell.and_then(|c| self.site.label(c)),
            x_m: world.map(|[x, _]| x),
            y_m: world.map(|[_, y]| y),
            place: cell
                .and_then(|c| self.site.nearest_place(c, 2.0))
                .map(str::to_owned),
            confidence,
            anchors_heard: fp.heard_count(),
        };
        out.push(Output::Location(location));
        if let Some(heard) = self
            .heard_ids
            .as_ref()
            .and_then(|ids| locate::recalibrate::Heard::of(fp, ids))
        {
            out.push(Output::Heard(heard));
        }
        // Leaving the route is judged on the fix, progress along it on the
        // belief of a walker walking it ([`Tracker::update_walking`]).
        let mean = walked_mean.unwrap_or(fix.mean);
        let located = cell.map(|cell| Located::with_mean(&self.site, cell, mean.map(f64::from)));
        if let Some(guidance) = self
            .guide
            .update(&self.site, &fp.entity, located, fp.t, now)
        {
            let off_route = guidance.event == Some(GuidanceEvent::OffRoute);
            out.push(Output::Guidance(Box::new(guidance)));
            if off_route {
                self.reroute(&fp.entity, fix.cell, fp.t, out);
            }
        }
        self.forgotten_and_finished(out);
    }

    /// Publishes a route reply and, for a route, starts guiding along it.
    fn reply(&mut self, reply: RouteReply, rerouted: bool, out: &mut Vec<Output>) {
        if let RouteOutcome::Route(body) = &reply.outcome {
            let first = self.guide_along(&reply, body, rerouted);
            out.push(Output::Route(Box::new(reply)));
            out.push(Output::Guidance(Box::new(first)));
        } else {
            out.push(Output::Route(Box::new(reply)));
        }
        self.forgotten_and_finished(out);
    }

    /// Starts guiding a device along a route just published; returns the
    /// session's first message.
    fn guide_along(
        &mut self,
        reply: &RouteReply,
        body: &RouteBody,
        rerouted: bool,
    ) -> crate::guide::Guidance {
        let (route, line) = body.route_and_line(&self.site);
        let profile = Profile::parse(body.profile).unwrap_or_default();
        self.guide.start(
            &self.site,
            &reply.device,
            reply.request_id.clone(),
            profile,
            &route,
            &line,
            reply.t,
            rerouted,
        )
    }

    /// Re-plans the route of a device that left it, from its tracked `cell`
    /// to the same destination, and publishes it with reason `off_route`.
    /// When no route can be planned the session stays off route (and the
    /// device is told so by its guidance) until it walks back or asks again.
    fn reroute(&mut self, device: &str, cell: Cell, t: f64, out: &mut Vec<Output>) {
        let Some(session) = self.guide.session(device) else {
            return;
        };
        let (to, profile) = (session.destination(), session.profile());
        let request_id = session.request_id().map(str::to_owned);
        let started = self.clock.start();
        let planned = match self.planner.plan(cell, to, profile) {
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
        let mut body = RouteBody::new(
            &self.site,
            &*self.planner,
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
            outcome: RouteOutcome::Route(body),
        };
        self.reply(reply, true, out);
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
        let Some(fix) = self.tracker.last_fix(&request.device) else {
            return error(
                RouteErrorCode::UnknownDevice,
                format!(
                    "device `{}` has no location yet; a device must be heard before it can ask for a route",
                    request.device
                ),
            );
        };
        let to = match request.to.resolve(&self.site) {
            Ok(cell) => cell,
            Err(e) => return error(e.code(), e.to_string()),
        };
        match self.planner.plan(fix.cell, to, profile) {
            Ok(planned) => RouteOutcome::Route(RouteBody::new(
                &self.site,
                &*self.planner,
                profile,
                fix.cell,
                to,
                &planned,
                started.elapsed_us(),
            )),
            Err(e) => error(e.code(), e.to_string()),
        }
    }
}

#[cfg(test)]
mod tests {
    use std::path::{Path, PathBuf};

    use super::*;

    impl Pipeline {
        fn site(&self) -> &Arc<Site> {
            &self.site
        }
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

        let (pipeline, fallbacks) = Pipeline::with_fallbacks(&config, site).unwrap();
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
        assert_eq!(pipeline.planner.mode(), "astar");
        let site = pipeline.site().clone();
        let (from, to) = (
            site.place("help desk").unwrap(),
            site.place("printers").unwrap(),
        );
        assert!(pipeline.planner.plan(from, to, Profile::Default).is_ok());
    }

    /// Only files fall back: a config mistake stops the start-up as it
    /// stops a reload.
    #[test]
    fn config_mistakes_do_not_fall_back() {
        let (_, shipped, site) = shipped();

        let mut no_survey = shipped.clone();
        no_survey.localizer.method = locate::Method::Knn;
        no_survey.localizer.knn.survey = None;
        let err = Pipeline::with_fallbacks(&no_survey, site.clone())
            .err()
            .unwrap();
        assert!(format!("{err:#}").contains("set `survey`"), "{err:#}");

        let mut no_samples = shipped.clone();
        no_samples.planner.mode = plan::PlannerMode::Conditional;
        no_samples.planner.conditional.samples = 0;
        let err = Pipeline::with_fallbacks(&no_samples, site.clone())
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
        let err = Pipeline::with_fallbacks(&broken_config(), Arc::new(unplaced))
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
            profile: None,
            t: 10.0,
        });
        assert!(matches!(reply.outcome, RouteOutcome::Route(_)), "{reply:?}");
    }
}
