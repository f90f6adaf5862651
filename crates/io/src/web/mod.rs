//! The browser UI: an HTTP server (axum) with a live floor map, a site
//! editor over a floor-plan image, and the JSON they read.
//!
//! What it owns: the routes ([`router`]), who may write ([`security`]), the
//! site as the pages draw it ([`view`]), the editor's API ([`editor`]) and
//! the pages themselves ([`assets`], built into the binary). It is a sink of
//! the gateway and a front end of the site file; the pipeline knows nothing
//! of it.
//!
//! Invariants: nothing the air or the broker names is ever put into a page
//! as HTML (the scripts only set text and attributes), every response
//! carries the Content-Security-Policy of [`security`], every write passes
//! [`security::guard`], and the token is never served.

mod assets;
pub(crate) mod config;
mod editor;
mod floor;
mod live;
mod metrics;
mod security;
mod survey;
mod view;

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::Router;
use axum::extract::{DefaultBodyLimit, Query, State};
use axum::response::{IntoResponse, Redirect, Response};
use axum::routing::get;
use tokio::net::TcpListener;
use tokio::sync::mpsc;

pub use config::WebConfig;
pub use editor::Editors;
pub(crate) use live::{Live, WebSink, WebSource};
pub use security::CONTENT_SECURITY_POLICY;

use crate::latency::Latency;
use crate::sink::Sink;
use crate::site::Building;
use crate::source::Source;

/// The building the map shows (a one-floor site: a building of that one
/// floor), replaced on reloads.
pub(crate) type BuildingCell = Arc<std::sync::RwLock<Arc<Building>>>;

/// Largest JSON body taken (an edited site document).
const MAX_JSON_BYTES: usize = 4 << 20;

/// What one server serves: the live map, the editor, or both.
pub struct Ui {
    /// The gateway's live state (and the site it maps); none in an
    /// editor-only server.
    pub live: Option<Arc<Live>>,
    pub editor: Option<Editors>,
    survey: Option<Arc<survey::Surveys>>,
}

impl Ui {
    /// The editor of a site or building file, alone.
    pub fn editor(editors: Editors) -> Ui {
        Ui {
            live: None,
            editor: Some(editors),
            survey: None,
        }
    }
}

#[derive(Clone)]
struct App {
    guard: Arc<security::Guard>,
    building: Option<BuildingCell>,
    live: Option<Arc<Live>>,
    editor: Option<Arc<Editors>>,
    survey: Option<Arc<survey::Surveys>>,
}

/// The web UI of a running gateway, ready to join its runtime.
pub struct Web {
    sink: WebSink,
    source: WebSource,
    survey: Option<Arc<survey::Surveys>>,
    latency: Arc<Latency>,
}

impl Web {
    /// Adds the UI to the runtime's sources and sinks: its sink (the live
    /// map), its source (route requests from the pages), and survey mode's
    /// view of the sightings of every source already there. Returns the
    /// latency histograms `/metrics` serves, for the runtime to observe.
    pub fn add_to(
        self,
        sources: &mut Vec<Box<dyn Source>>,
        sinks: &mut Vec<Box<dyn Sink>>,
    ) -> Arc<Latency> {
        if let Some(survey) = &self.survey {
            let tapped = std::mem::take(sources).into_iter().map(|s| survey.tap(s));
            sources.extend(tapped);
        }
        sources.push(Box::new(self.source));
        sinks.push(Box::new(self.sink));
        self.latency
    }
}

/// Starts the web UI of a running gateway (`[web]`): serves the live map of
/// `building` (floor by floor), the editor of its file `site_file` (of each
/// floor's site file on a building of several), and survey mode (its
/// windows cut as `window` says, on every floor) for as long as the
/// runtime lives. With `reload` (the runtime's reloads), a site
/// saved in the editor is applied as SIGHUP applies it. A UI that cannot
/// start never stops the gateway: why is logged and added to `fallbacks`,
/// and the gateway serves without it.
pub async fn start(
    config: &WebConfig,
    site_file: &std::path::Path,
    window: &crate::locate::window::WindowConfig,
    max_devices: usize,
    building: Arc<Building>,
    fallbacks: &mut Vec<String>,
    reload: Option<mpsc::Sender<()>>,
) -> Option<Web> {
    if !config.enabled {
        return None;
    }
    let server = match Server::bind(config).await {
        Ok(server) => server,
        Err(e) => {
            let why = format!("{e:#}; serving without the web UI");
            tracing::error!("{why}");
            fallbacks.push(why);
            return None;
        }
    };
    let survey = config
        .survey_file
        .as_ref()
        .and_then(|file| survey::Surveys::open(file, &building, window, fallbacks).map(Arc::new));
    let latency = Arc::new(Latency::default());
    let (live, sink, source) = Live::new(building.clone(), max_devices, latency.clone());
    let gateway = reload.map(|reload| (reload, live.reloaded.subscribe()));
    let editor = match Editors::served(site_file, None, gateway) {
        Ok(editors) => Some(editors),
        Err(e) => {
            tracing::warn!("[web] no site editor: {e:#}");
            None
        }
    };
    tracing::info!(addr = %server.addr(), "web UI at http://{}/", server.addr());
    let ui = Ui {
        live: Some(live),
        editor,
        survey: survey.clone(),
    };
    tokio::spawn(async move {
        if let Err(e) = server.serve(ui, std::future::pending()).await {
            tracing::error!("[web] the web UI stopped: {e:#}");
        }
    });
    Some(Web {
        sink,
        source,
        survey,
        latency,
    })
}

/// A bound, not yet serving, web server.
pub struct Server {
    listener: TcpListener,
    addr: SocketAddr,
    guard: Arc<security::Guard>,
}

impl Server {
    /// Binds `[web] bind` and reads the token. A token file that is named
    /// but unreadable is an error; none at all off loopback serves the map
    /// only (and says so).
    pub async fn bind(config: &WebConfig) -> anyhow::Result<Server> {
        let token = config.token().map_err(anyhow::Error::msg)?;
        let listener = TcpListener::bind(config.bind)
            .await
            .map_err(|e| anyhow::anyhow!("[web] cannot listen on {}: {e}", config.bind))?;
        let addr = listener.local_addr()?;
        if config.needs_token() && token.is_none() && !config.read_only {
            tracing::warn!(
                %addr,
                "[web] bound off loopback without a token: serving the map only; set [web] \
                 token_file or the systemd credential {}",
                config::TOKEN_CREDENTIAL
            );
        }
        let guard = Arc::new(security::Guard::new(addr, config.read_only, token));
        Ok(Server {
            listener,
            addr,
            guard,
        })
    }

    /// Where it listens (the real port when `bind` asked for port 0).
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// Serves until `shutdown` completes.
    pub async fn serve(
        self,
        ui: Ui,
        shutdown: impl Future<Output = ()> + Send + 'static,
    ) -> anyhow::Result<()> {
        let app = App {
            guard: self.guard.clone(),
            building: ui.live.as_ref().map(|live| live.building.clone()),
            live: ui.live,
            editor: ui.editor.map(Arc::new),
            survey: ui.survey,
        };
        axum::serve(self.listener, router(app))
            .with_graceful_shutdown(shutdown)
            .await?;
        Ok(())
    }
}

fn router(app: App) -> Router {
    let mut routes = Router::new()
        .route("/", get(index))
        .route("/assets/{name}", get(assets::asset))
        .route("/healthz", get(healthz))
        .route("/api/site", get(site))
        .route("/api/floors", get(floors))
        .route("/api/floorplan", get(floorplan))
        .route("/api/access", get(access));
    if let Some(live) = &app.live {
        routes = routes.merge(
            Router::new()
                .route("/api/live", get(live::stream))
                .route("/api/heard", get(live::heard))
                .route("/api/route", axum::routing::post(live::route))
                .route("/metrics", get(metrics))
                .with_state(live.clone()),
        );
    }
    if let Some(survey) = &app.survey {
        routes = routes.merge(
            Router::new()
                .route("/api/survey", get(survey::status).post(survey::start))
                .route("/api/survey/stop", axum::routing::post(survey::stop))
                .with_state(survey.clone()),
        );
    }
    if let Some(editor) = &app.editor {
        routes = routes.route("/edit", get(assets::edit_page)).merge(
            Router::new()
                .route("/api/editor", get(editor::get))
                .route("/api/editor/check", axum::routing::post(editor::check))
                .route("/api/editor/site", axum::routing::put(editor::save))
                .route(
                    "/api/editor/connectors",
                    get(editor::connectors).put(editor::save_connectors),
                )
                .route(
                    "/api/editor/image",
                    get(editor::image)
                        .put(editor::upload)
                        .layer(DefaultBodyLimit::max(crate::site::MAX_IMAGE_BYTES as usize)),
                )
                .with_state(editor.clone()),
        );
    }
    routes
        .layer(DefaultBodyLimit::max(MAX_JSON_BYTES))
        .layer(axum::middleware::from_fn_with_state(
            app.guard.clone(),
            security::guard,
        ))
        .with_state(app)
}

/// The map, or the editor when there is no site to map.
async fn index(State(app): State<App>) -> Response {
    match app.building {
        Some(_) => assets::map_page().await.into_response(),
        None => Redirect::temporary("/edit").into_response(),
    }
}

async fn healthz() -> impl IntoResponse {
    axum::Json(serde_json::json!({ "status": "ok" }))
}

async fn access(State(app): State<App>) -> impl IntoResponse {
    let mut access = app.guard.access();
    access["editor"] = app.editor.is_some().into();
    access["map"] = app.building.is_some().into();
    access["live"] = app.live.is_some().into();
    access["survey"] = app.survey.is_some().into();
    axum::Json(access)
}

/// `GET /api/site?floor=NAME`: the map's site, that floor's (the lowest
/// when none is named), with which floor it is and the building's floors;
/// an editor-only server sends the editor.
async fn site(State(app): State<App>, Query(q): Query<floor::FloorQuery>) -> Response {
    let (building, i) = match current(&app, q.floor.as_deref()) {
        Ok(found) => found,
        Err(response) => return response.into_response(),
    };
    let floor = &building.floors()[i];
    let named = building.is_multi_floor().then_some(floor.name.as_str());
    let url = floor
        .site
        .floorplan()
        .map(|_| floor::url("/api/floorplan", named));
    let mut view = serde_json::to_value(view::SiteView::new(&floor.site, url.as_deref()))
        .expect("plain data serializes");
    view["floor"] = serde_json::json!({ "name": floor.name, "level": floor.level });
    view["floors"] = serde_json::to_value(floor::floors(&building)).expect("plain data");
    if building.is_multi_floor() {
        view["connectors"] = floor::connectors(&building, i).into();
    }
    axum::Json(view).into_response()
}

/// `GET /api/floors`: the building's name and its floors, lowest first.
async fn floors(State(app): State<App>) -> Response {
    match current(&app, None) {
        Ok((building, _)) => axum::Json(serde_json::json!({
            "building": building.name,
            "floors": floor::floors(&building),
        }))
        .into_response(),
        Err(response) => response.into_response(),
    }
}

/// The building the map shows now and the index of the floor `asked`
/// names (the lowest when none), or the 404 saying why not.
fn current(app: &App, asked: Option<&str>) -> Result<(Arc<Building>, usize), floor::NotFound> {
    let Some(cell) = app.building.as_ref() else {
        return Err(floor::NotFound {
            code: "not_found",
            message: "this server edits a site file and maps none; see /edit".into(),
        });
    };
    let building = cell.read().unwrap_or_else(|e| e.into_inner()).clone();
    let i = floor::pick(&floor::floors(&building), asked)?;
    Ok((building, i))
}

async fn metrics(State(live): State<Arc<Live>>) -> Response {
    (
        [(
            axum::http::header::CONTENT_TYPE,
            "text/plain; version=0.0.4; charset=utf-8",
        )],
        live.metrics.render(live.streams()),
    )
        .into_response()
}

/// `GET /api/floorplan?floor=NAME`: that floor's plan image.
async fn floorplan(State(app): State<App>, Query(q): Query<floor::FloorQuery>) -> Response {
    let (building, i) = match current(&app, q.floor.as_deref()) {
        Ok(found) => found,
        Err(response) => return response.into_response(),
    };
    match building.floors()[i].site.floorplan() {
        Some(plan) => editor::image_file(&plan.image),
        None => security::error(
            axum::http::StatusCode::NOT_FOUND,
            "not_found",
            "the site names no floor plan",
        ),
    }
}
