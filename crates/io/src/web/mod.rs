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
mod live;
mod metrics;
mod security;
mod survey;
mod view;

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;

use axum::Router;
use axum::extract::{DefaultBodyLimit, State};
use axum::response::{IntoResponse, Redirect, Response};
use axum::routing::get;
use tokio::net::TcpListener;
use tokio::sync::mpsc;

pub use config::WebConfig;
pub use editor::Editor;
pub(crate) use live::{Live, WebSink, WebSource};
pub use security::CONTENT_SECURITY_POLICY;

use crate::latency::Latency;
use crate::sink::Sink;
use crate::site::Site;
use crate::source::Source;

/// The site the map shows, replaced on reloads.
pub(crate) type SiteCell = Arc<std::sync::RwLock<Arc<Site>>>;

/// Largest JSON body taken (an edited site document).
const MAX_JSON_BYTES: usize = 4 << 20;

/// What one server serves: the live map, the editor, or both.
pub struct Ui {
    /// The gateway's live state (and the site it maps); none in an
    /// editor-only server.
    pub live: Option<Arc<Live>>,
    pub editor: Option<Editor>,
    survey: Option<Arc<survey::Survey>>,
}

impl Ui {
    /// The editor of one site file, alone.
    pub fn editor(editor: Editor) -> Ui {
        Ui {
            live: None,
            editor: Some(editor),
            survey: None,
        }
    }
}

#[derive(Clone)]
struct App {
    guard: Arc<security::Guard>,
    site: Option<SiteCell>,
    live: Option<Arc<Live>>,
    editor: Option<Arc<Editor>>,
    survey: Option<Arc<survey::Survey>>,
}

/// The web UI of a running gateway, ready to join its runtime.
pub struct Web {
    sink: WebSink,
    source: WebSource,
    survey: Option<Arc<survey::Survey>>,
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
/// `site`, the editor of its file `site_file`, and survey mode (its windows
/// cut as `window` says) for as
/// long as the runtime lives. With `reload` (the runtime's reloads), a site
/// saved in the editor is applied as SIGHUP applies it. A UI that cannot
/// start never stops the gateway: why is logged and added to `fallbacks`,
/// and the gateway serves without it.
pub async fn start(
    config: &WebConfig,
    site_file: &std::path::Path,
    window: &crate::locate::window::WindowConfig,
    max_devices: usize,
    site: Arc<Site>,
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
    let editor = match Editor::open(site_file, None) {
        Ok(editor) => Some(editor),
        Err(e) => {
            tracing::warn!("[web] no site editor: {e:#}");
            None
        }
    };
    let survey = config.survey_file.as_ref().and_then(|file| {
        match survey::Survey::open(file, site.clone(), window) {
            Ok(survey) => Some(Arc::new(survey)),
            Err(e) => {
                let why = format!("[web] survey mode is off: {e:#}");
                tracing::error!("{why}");
                fallbacks.push(why);
                None
            }
        }
    });
    let latency = Arc::new(Latency::default());
    let (live, sink, source) = Live::new(site, max_devices, latency.clone());
    let editor = match (editor, reload) {
        (Some(editor), Some(reload)) => Some(editor.served_by(reload, live.reloaded.subscribe())),
        (editor, _) => editor,
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
            site: ui.live.as_ref().map(|live| live.site.clone()),
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
    match app.site {
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
    access["map"] = app.site.is_some().into();
    access["live"] = app.live.is_some().into();
    access["survey"] = app.survey.is_some().into();
    axum::Json(access)
}

/// `GET /api/site`: the map's site; an editor-only server sends the editor.
async fn site(State(app): State<App>) -> Response {
    match current(&app) {
        Some(site) => {
            let url = site.floorplan().map(|_| "/api/floorplan");
            axum::Json(view::SiteView::new(&site, url)).into_response()
        }
        None => security::error(
            axum::http::StatusCode::NOT_FOUND,
            "not_found",
            "this server edits a site file and maps none; see /edit",
        ),
    }
}

/// The site the map shows now.
fn current(app: &App) -> Option<Arc<Site>> {
    let cell = app.site.as_ref()?;
    Some(cell.read().unwrap_or_else(|e| e.into_inner()).clone())
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

async fn floorplan(State(app): State<App>) -> Response {
    let site = current(&app);
    match site.as_ref().and_then(|s| s.floorplan()) {
        Some(plan) => editor::image_file(&plan.image),
        None => security::error(
            axum::http::StatusCode::NOT_FOUND,
            "not_found",
            "the site names no floor plan",
        ),
    }
}
