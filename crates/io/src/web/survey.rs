//! Survey mode: an operator picks a device (a phone sending scans, or a
//! tag), clicks where it stands, and the gateway records that device's
//! fingerprints there into a survey file in the generic layout
//! (`x_m,y_m,t,<anchor ids…>`, what `[localizer.knn] survey` and `gangway
//! eval localization --survey` read), then shows what the file covers.
//!
//! The fingerprints are the pipeline's own ([`Windows`] with the gateway's
//! `[window]` settings), made from the same sightings: a [`Tap`] wraps each
//! source and copies the sightings of the one device being surveyed, so
//! nothing else is held and the pipeline is untouched. One spot is recorded
//! at a time on each floor, for a bounded number of windows.
//!
//! On a building of several floors each floor is surveyed into a file of
//! its own ([`floor_file`]): a floor's fingerprints have that floor's
//! beacons as columns and its spots are in its own plan's metres, which is
//! what that floor's localizer reads (`survey = "survey-{floor}.csv"`).

use std::collections::HashMap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};

use axum::Json;
use axum::extract::{Query, State};
use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use futures::future::BoxFuture;
use serde::Deserialize;
use tokio::sync::mpsc;

use super::floor::{FloorQuery, FloorView};
use super::security::error;
use crate::locate::window::{Orientation, Windows, anchor_ids};
use crate::sighting::Sighting;
use crate::site::{Building, Cell, Site, floor_file};
use crate::source::{Input, Source, SourceContext};

use crate::event::{Event, Inbound};

/// One recorded window: the spot's cell and metres, the window's end, and
/// each anchor's reading (none: not heard).
type Row = (Cell, [f64; 2], f64, Vec<Option<i16>>);

/// Windows recorded at one spot unless the request says otherwise.
const DEFAULT_SAMPLES: usize = 10;
/// The most windows one request may ask for.
const MAX_SAMPLES: usize = 600;
/// What the file writes for an anchor not heard in a window.
const NOT_HEARD: i16 = -200;

/// Survey mode on every floor: each floor's [`Survey`], or why it is off
/// there (its file cannot be appended to), lowest floor first.
pub(super) struct Surveys {
    floors: Vec<FloorView>,
    surveys: Vec<Result<Survey, String>>,
}

impl Surveys {
    /// Survey mode on each floor of `building`, writing to `file` as
    /// [`floor_file`] names it per floor. A floor whose file cannot be
    /// taken has survey mode off, why in `fallbacks`; none at all when no
    /// floor can be surveyed.
    pub(super) fn open(
        file: &Path,
        building: &Building,
        window: &crate::locate::window::WindowConfig,
        fallbacks: &mut Vec<String>,
    ) -> Option<Surveys> {
        let several = building.is_multi_floor();
        let surveys: Vec<Result<Survey, String>> = building
            .floors()
            .iter()
            .map(|floor| {
                let file = floor_file(file, &floor.name, several);
                Survey::open(&file, floor.site.clone(), window).map_err(|e| {
                    let on = if several {
                        format!(" on floor {}", floor.name)
                    } else {
                        String::new()
                    };
                    let why = format!("[web] survey mode is off{on}: {e:#}");
                    tracing::error!("{why}");
                    fallbacks.push(why.clone());
                    why
                })
            })
            .collect();
        surveys.iter().any(Result::is_ok).then(|| Surveys {
            floors: super::floor::floors(building),
            surveys,
        })
    }

    /// The survey of the floor `query` names (the lowest when none), or
    /// why there is none.
    fn of(&self, query: &FloorQuery) -> Result<&Survey, NoSurvey> {
        let i = super::floor::pick(&self.floors, query.floor.as_deref()).map_err(|e| NoSurvey {
            status: StatusCode::NOT_FOUND,
            code: e.code,
            message: e.message,
        })?;
        self.surveys[i].as_ref().map_err(|why| NoSurvey {
            status: StatusCode::CONFLICT,
            code: "survey_off",
            message: why.clone(),
        })
    }

    /// A source whose sightings every floor's survey sees too.
    pub(super) fn tap(self: &Arc<Self>, inner: Box<dyn Source>) -> Box<dyn Source> {
        Box::new(Tap {
            inner,
            surveys: self.clone(),
        })
    }
}

/// Why a request's floor has no survey: the building has no such floor
/// (404), or survey mode is off on it (409).
pub(super) struct NoSurvey {
    status: StatusCode,
    code: &'static str,
    message: String,
}

impl IntoResponse for NoSurvey {
    fn into_response(self) -> Response {
        error(self.status, self.code, self.message)
    }
}

struct Survey {
    file: PathBuf,
    site: Arc<Site>,
    anchors: Vec<String>,
    orientation: Orientation,
    window: crate::locate::window::WindowConfig,
    state: Mutex<SurveyState>,
}

#[derive(Default)]
struct SurveyState {
    spot: Option<Spot>,
    /// Samples per cell and per-anchor RSSI sums, from the file and this run.
    cells: HashMap<Cell, CellStats>,
    recorded: u64,
    /// Why the last write failed, if it did.
    write_error: Option<String>,
}

struct Spot {
    device: Arc<str>,
    at: [f64; 2],
    cell: Cell,
    wanted: usize,
    taken: usize,
    windows: Windows,
}

#[derive(Clone, Default)]
struct CellStats {
    samples: u32,
    /// Sum and count of heard readings per anchor.
    rssi: Vec<(f64, u32)>,
}

impl Survey {
    /// Survey mode writing to `file` (created with its header when missing;
    /// an existing file must be in the generic layout with this site's
    /// anchors, and is counted for coverage).
    fn open(
        file: &Path,
        site: Arc<Site>,
        window: &crate::locate::window::WindowConfig,
    ) -> anyhow::Result<Survey> {
        let orientation = window.orientation;
        let anchors = anchor_ids(&site, orientation);
        let survey = Survey {
            file: file.to_owned(),
            site,
            anchors,
            orientation,
            window: window.clone(),
            state: Mutex::new(SurveyState::default()),
        };
        survey.load_existing()?;
        Ok(survey)
    }

    fn header(&self) -> String {
        format!("x_m,y_m,t,{}", self.anchors.join(","))
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, SurveyState> {
        self.state.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn load_existing(&self) -> anyhow::Result<()> {
        let Ok(text) = std::fs::read_to_string(&self.file) else {
            return Ok(());
        };
        let mut lines = text.lines();
        let header = lines.next().unwrap_or_default();
        anyhow::ensure!(
            header.trim() == self.header(),
            "{}: line 1: the survey file's columns are {header:?}; survey mode appends \
             {:?} (move the file aside to start a new survey)",
            self.file.display(),
            self.header()
        );
        let mut state = self.lock();
        for (n, line) in lines.enumerate() {
            let fields: Vec<&str> = line.split(',').collect();
            let number = |i: usize| fields.get(i).and_then(|f| f.trim().parse::<f64>().ok());
            let (Some(x), Some(y)) = (number(0), number(1)) else {
                anyhow::bail!("{}: line {}: not `x_m,y_m,…`", self.file.display(), n + 2);
            };
            let Some(cell) = self.site.cell_of_world([x, y]) else {
                continue;
            };
            let rssi: Vec<Option<i16>> = (0..self.anchors.len())
                .map(|i| number(3 + i).map(|v| v as i16).filter(|&v| v > NOT_HEARD))
                .collect();
            state.add(cell, &rssi, self.anchors.len());
        }
        Ok(())
    }

    /// Sightings from a source, before the pipeline sees them.
    fn observe(&self, input: &Input) {
        let rows = {
            let mut state = self.lock();
            let Some(spot) = state.spot.as_mut() else {
                return;
            };
            let mut rows = Vec::new();
            let mut take = |s: &Sighting| rows.extend(self.push(spot, s));
            match input {
                Input::Events(events) => {
                    for event in events {
                        if let Event::Advert(s) = event {
                            take(s);
                        }
                    }
                }
                Input::Inbound(Inbound::Scan(s) | Inbound::Shared(s)) => s.iter().for_each(take),
                Input::Inbound(_) => {}
            }
            rows
        };
        self.write(rows);
    }

    /// The rows one sighting completes for the spot.
    fn push(&self, spot: &mut Spot, s: &Sighting) -> Option<Row> {
        if spot.taken >= spot.wanted {
            return None;
        }
        if self.orientation == Orientation::Observer && *s.observer != *spot.device {
            return None;
        }
        let fingerprint = spot.windows.push(s)?;
        if *fingerprint.entity != *spot.device {
            return None;
        }
        spot.taken += 1;
        let rssi = fingerprint
            .rssi
            .iter()
            .zip(&fingerprint.heard)
            .map(|(&v, &heard)| heard.then_some(v.round() as i16))
            .collect();
        Some((spot.cell, spot.at, fingerprint.t, rssi))
    }

    fn write(&self, rows: Vec<Row>) {
        if rows.is_empty() {
            return;
        }
        let mut text = String::new();
        let fresh = !self.file.exists();
        if fresh {
            text.push_str(&self.header());
            text.push('\n');
        }
        for (_, at, t, rssi) in &rows {
            let values: Vec<String> = rssi
                .iter()
                .map(|r| r.unwrap_or(NOT_HEARD).to_string())
                .collect();
            text.push_str(&format!(
                "{},{},{t:.3},{}\n",
                at[0],
                at[1],
                values.join(",")
            ));
        }
        let result = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(&self.file)
            .and_then(|mut f| f.write_all(text.as_bytes()));
        let mut state = self.lock();
        match result {
            Ok(()) => {
                for (cell, _, _, rssi) in &rows {
                    state.add(*cell, rssi, self.anchors.len());
                }
                state.recorded += rows.len() as u64;
                state.write_error = None;
            }
            Err(e) => {
                let why = format!("{}: cannot write the survey: {e}", self.file.display());
                tracing::error!("{why}");
                state.write_error = Some(why);
            }
        }
    }
}

impl SurveyState {
    fn add(&mut self, cell: Cell, rssi: &[Option<i16>], anchors: usize) {
        let stats = self.cells.entry(cell).or_insert_with(|| CellStats {
            samples: 0,
            rssi: vec![(0.0, 0); anchors],
        });
        stats.samples += 1;
        for (slot, r) in stats.rssi.iter_mut().zip(rssi) {
            if let Some(r) = r {
                slot.0 += f64::from(*r);
                slot.1 += 1;
            }
        }
    }
}

/// A source with the surveys looking over its shoulder.
struct Tap {
    inner: Box<dyn Source>,
    surveys: Arc<Surveys>,
}

impl Source for Tap {
    fn name(&self) -> &'static str {
        self.inner.name()
    }

    fn run(self: Box<Self>, cx: SourceContext) -> BoxFuture<'static, anyhow::Result<()>> {
        let Tap { inner, surveys } = *self;
        Box::pin(async move {
            let (events, mut events_rx) = mpsc::channel(cx.events.max_capacity());
            let (inbound, mut inbound_rx) = mpsc::channel(cx.inbound.max_capacity());
            let inner_cx = SourceContext::new(events, inbound, cx.shutdown.clone());
            let run = inner.run(inner_cx);
            let forward = async {
                let (mut events_open, mut inbound_open) = (true, true);
                while events_open || inbound_open {
                    let (input, to) = tokio::select! {
                        input = events_rx.recv(), if events_open => match input {
                            Some(i) => (i, &cx.events),
                            None => { events_open = false; continue }
                        },
                        input = inbound_rx.recv(), if inbound_open => match input {
                            Some(i) => (i, &cx.inbound),
                            None => { inbound_open = false; continue }
                        },
                    };
                    for survey in surveys.surveys.iter().flatten() {
                        survey.observe(&input);
                    }
                    if to.send(input).await.is_err() {
                        return;
                    }
                }
            };
            let (result, ()) = tokio::join!(run, forward);
            result
        })
    }
}

/// `GET /api/survey?floor=NAME`: the spot being recorded on that floor
/// (the lowest when none is named) and what its file covers.
pub(super) async fn status(
    State(surveys): State<Arc<Surveys>>,
    Query(query): Query<FloorQuery>,
) -> Result<Response, NoSurvey> {
    let survey = surveys.of(&query)?;
    let state = survey.lock();
    let spot = state.spot.as_ref().map(|s| {
        serde_json::json!({
            "device": &*s.device, "x_m": s.at[0], "y_m": s.at[1], "cell": s.cell,
            "taken": s.taken, "wanted": s.wanted,
        })
    });
    let cells: Vec<serde_json::Value> = state
        .cells
        .iter()
        .map(|(cell, stats)| {
            let rssi: Vec<Option<f64>> = stats
                .rssi
                .iter()
                .map(|&(sum, n)| (n > 0).then(|| sum / f64::from(n)))
                .collect();
            serde_json::json!({ "cell": cell, "samples": stats.samples, "rssi": rssi })
        })
        .collect();
    Ok(Json(serde_json::json!({
        "file": survey.file.display().to_string(),
        "anchors": survey.anchors,
        "spot": spot,
        "recorded": state.recorded,
        "cells": cells,
        "error": state.write_error,
    }))
    .into_response())
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct SpotBody {
    device: String,
    x_m: f64,
    y_m: f64,
    #[serde(default)]
    samples: Option<usize>,
}

/// `POST /api/survey?floor=NAME`: record `device` standing at (`x_m`,
/// `y_m`) of that floor (the lowest when none is named).
pub(super) async fn start(
    State(surveys): State<Arc<Surveys>>,
    Query(query): Query<FloorQuery>,
    Json(body): Json<SpotBody>,
) -> Result<Response, NoSurvey> {
    let survey = surveys.of(&query)?;
    if !crate::sighting::valid_device_id(&body.device) {
        return Ok(error(
            StatusCode::BAD_REQUEST,
            "invalid_request",
            "not a device id",
        ));
    }
    let at = [body.x_m, body.y_m];
    let Some(cell) = survey
        .site
        .cell_of_world(at)
        .filter(|&c| survey.site.walkable(c))
    else {
        return Ok(error(
            StatusCode::BAD_REQUEST,
            "not_walkable",
            "the spot is off the grid or on a blocked cell; a survey stands where people walk",
        ));
    };
    let wanted = body
        .samples
        .unwrap_or(DEFAULT_SAMPLES)
        .clamp(1, MAX_SAMPLES);
    let windows =
        Windows::new(survey.window.clone(), &survey.site).bound(4, survey.window.length_s * 4.0);
    survey.lock().spot = Some(Spot {
        device: body.device.as_str().into(),
        at,
        cell,
        wanted,
        taken: 0,
        windows,
    });
    tracing::info!(
        device = body.device,
        x_m = at[0],
        y_m = at[1],
        "survey spot started"
    );
    Ok(Json(serde_json::json!({ "cell": cell, "wanted": wanted })).into_response())
}

/// `POST /api/survey/stop?floor=NAME`: stop recording that floor's spot.
pub(super) async fn stop(
    State(surveys): State<Arc<Surveys>>,
    Query(query): Query<FloorQuery>,
) -> Result<Response, NoSurvey> {
    let survey = surveys.of(&query)?;
    survey.lock().spot = None;
    Ok(Json(serde_json::json!({ "stopped": true })).into_response())
}
