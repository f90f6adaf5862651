//! The site editor's API: open the site file as a [`SiteDoc`], check an
//! edited document exactly as `gangway check` would, save it, and take a
//! floor-plan image.
//!
//! The editor edits one file, named when the server starts (`gangway site
//! edit --site S`, or the gateway's own site); in a gateway serving a
//! building, one per floor ([`Editors`]), each floor's site file, the
//! requests naming it with `?floor=NAME`, and the building file's
//! connectors (`/api/editor/connectors`: only its `[[connectors]]` are
//! rewritten, checked with the floors as `gangway check` checks the
//! building). What the page sends is data;
//! the server writes the TOML (keeping the opened file's text where nothing
//! changed) and loads it with the same [`Site::parse`] the gateway uses, so
//! there is one validation and its messages are the CLI's. A save is refused
//! while the document has problems, and when the file changed on disk since
//! it was opened (someone else's edit is never overwritten).
//!
//! Inside the daemon the file is the site the gateway serves: a save is
//! applied as SIGHUP applies it, through the runtime's reloads (the config
//! and site loaded whole off the event loop and swapped in, or refused
//! whole), and the reply says which. Where the file cannot be written (the
//! packaged unit's read-only `/etc/gangway`), the site is saved in the
//! state directory instead and the reply says how to put it in place.

use std::collections::BTreeSet;
use std::path::{Component, Path, PathBuf};
use std::sync::{Arc, Mutex};

use axum::Json;
use axum::body::Bytes;
use axum::extract::{Query, State};
use axum::http::{StatusCode, header};
use axum::response::{IntoResponse, Response};
use serde::Deserialize;
use tokio::sync::{mpsc, watch};

use super::floor::{FloorQuery, FloorView};
use super::live::Reloaded;
use super::security::error;
use super::view::SiteView;
use crate::site::{
    Building, BuildingDoc, ConnectorDoc, ConnectorKind, MAX_IMAGE_BYTES, Site, SiteDoc,
    mime_of_bytes, probe_image, replace_connectors, write_doc,
};

/// URL the editor fetches a floor-plan image from (`?name=` relative to the
/// site file's directory).
const IMAGE_URL: &str = "/api/editor/image";
/// How long a save waits for the gateway to apply it (models may load).
const APPLY_WAIT: std::time::Duration = std::time::Duration::from_secs(20);

pub(super) struct Editor {
    /// The site file, absolute.
    path: PathBuf,
    /// Its directory, where floor-plan names resolve.
    dir: PathBuf,
    opened: Mutex<Opened>,
    /// Where a site that cannot be written is saved instead
    /// (`$STATE_DIRECTORY`, writable under systemd).
    fallback_dir: Option<PathBuf>,
    /// The gateway serving the file, when it runs in one.
    gateway: Option<Gateway>,
    /// The building floor whose site file this is, when there are several.
    floor: Option<String>,
}

/// The gateway serving the edited file: its reloads, and what became of them.
struct Gateway {
    reload: mpsc::Sender<()>,
    reloaded: watch::Receiver<Reloaded>,
}

struct Opened {
    /// The file's text when it was opened or last saved; none for a new file.
    text: Option<String>,
    /// Image names (relative to `dir`) the editor may serve: the file's
    /// floor plan, the one given on the command line, and uploads. Nothing
    /// else on the disk is ever read through the editor.
    images: BTreeSet<String>,
    /// The plan image offered for a site that names none yet.
    suggested: Option<String>,
}

impl Editor {
    /// The editor of the site file at `path` (which need not exist yet),
    /// offering `image` as the floor plan of a site that names none.
    fn open(path: &Path, image: Option<&Path>) -> anyhow::Result<Editor> {
        let path = std::path::absolute(path)?;
        let dir = path.parent().map_or_else(PathBuf::new, Path::to_owned);
        anyhow::ensure!(
            dir.is_dir(),
            "{}: the site file's directory does not exist",
            path.display()
        );
        let text = match std::fs::read_to_string(&path) {
            Ok(text) => Some(text),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => None,
            Err(e) => anyhow::bail!("{}: cannot read the site file: {e}", path.display()),
        };
        let mut images = BTreeSet::new();
        if let Some(plan) = text
            .as_deref()
            .and_then(|t| SiteDoc::parse(t).ok())
            .and_then(|d| d.floorplan)
        {
            images.insert(plan.image);
        }
        let suggested = match image {
            None => None,
            Some(image) => {
                probe_image(image).map_err(anyhow::Error::msg)?;
                let name = relative(&dir, image)?;
                images.insert(name.clone());
                Some(name)
            }
        };
        let fallback_dir = std::env::var_os("STATE_DIRECTORY")
            .and_then(|dirs| std::env::split_paths(&dirs).next())
            .filter(|d| d.is_dir() && *d != dir);
        Ok(Editor {
            path,
            dir,
            opened: Mutex::new(Opened {
                text,
                images,
                suggested,
            }),
            fallback_dir,
            gateway: None,
            floor: None,
        })
    }

    /// Saves apply to the gateway serving the file: `reload` asks for a
    /// reload (as SIGHUP does), `reloaded` tells how it went.
    pub(super) fn served_by(
        mut self,
        reload: mpsc::Sender<()>,
        reloaded: watch::Receiver<Reloaded>,
    ) -> Editor {
        self.gateway = Some(Gateway { reload, reloaded });
        self
    }

    fn path(&self) -> &Path {
        &self.path
    }

    /// Writes `doc` and loads it: the TOML, and the site or every problem
    /// (as `gangway check` words them, floor-plan image included).
    fn check(&self, doc: &SiteDoc) -> (String, Result<Site, Vec<String>>) {
        let text = write_doc(doc, self.lock().text.as_deref());
        let result = Site::parse(&text, &self.path)
            .map_err(|e| e.problems())
            .and_then(|site| match site.check_floorplan() {
                Some(problem) => Err(vec![problem]),
                None => Ok(site),
            });
        (text, result)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Opened> {
        self.opened.lock().unwrap_or_else(|e| e.into_inner())
    }

    fn image_info(&self, name: &str) -> Option<serde_json::Value> {
        let info = probe_image(&self.dir.join(name)).ok()?;
        Some(serde_json::json!({
            "name": name,
            "url": image_url(self.floor.as_deref(), name),
            "width": info.width,
            "height": info.height,
        }))
    }
}

fn image_url(floor: Option<&str>, name: &str) -> String {
    let mut url = url::Url::parse("http://x/").expect("a valid base");
    url.set_path(IMAGE_URL);
    if let Some(floor) = floor {
        url.query_pairs_mut().append_pair("floor", floor);
    }
    url.query_pairs_mut().append_pair("name", name);
    format!("{}?{}", url.path(), url.query().unwrap_or(""))
}

/// `target` relative to `dir`, with `..` where needed. Lexical (symbolic
/// links are kept, not resolved), so a path that climbs to data beside the
/// checkout stays the same wherever the checkout is.
fn relative(dir: &Path, target: &Path) -> anyhow::Result<String> {
    let normal = |p: &Path| -> std::io::Result<Vec<std::ffi::OsString>> {
        let mut out = Vec::new();
        for c in std::path::absolute(p)?.components() {
            match c {
                Component::ParentDir => {
                    out.pop();
                }
                Component::Normal(name) => out.push(name.to_owned()),
                Component::RootDir | Component::CurDir | Component::Prefix(_) => {}
            }
        }
        Ok(out)
    };
    let (a, b) = (normal(dir)?, normal(target)?);
    let common = a.iter().zip(&b).take_while(|(x, y)| x == y).count();
    let mut out = PathBuf::new();
    for _ in common..a.len() {
        out.push("..");
    }
    for name in &b[common..] {
        out.push(name);
    }
    out.into_os_string()
        .into_string()
        .map_err(|_| anyhow::anyhow!("{}: the image path is not UTF-8", target.display()))
}

/// The editors a server serves: one site file, or each floor's of a
/// building (`?floor=NAME`, the lowest floor when absent) and the building
/// file's connectors.
pub struct Editors {
    floors: Vec<FloorView>,
    /// `editors[i]` edits `floors[i]`'s file.
    editors: Vec<Arc<Editor>>,
    /// The building file, whose `[[connectors]]` the editor rewrites; none
    /// for a one-floor site.
    building: Option<Arc<Editor>>,
}

impl Editors {
    /// The editors of the file at `path` (which need not exist yet): a
    /// one-floor site file's, offering `image` as the floor plan of a site
    /// that names none; or a building file's floors and connectors. The
    /// building file is read as data, unchecked, so that a building whose
    /// connectors have problems opens to fix them.
    pub fn open(path: &Path, image: Option<&Path>) -> anyhow::Result<Editors> {
        Editors::served(path, image, None)
    }

    /// [`Editors::open`] within a gateway: with `gateway` (its reloads and
    /// what became of them), saves apply as SIGHUP does.
    pub(super) fn served(
        path: &Path,
        image: Option<&Path>,
        gateway: Option<(mpsc::Sender<()>, watch::Receiver<Reloaded>)>,
    ) -> anyhow::Result<Editors> {
        let serve = |editor: Editor| match &gateway {
            Some((reload, reloaded)) => editor.served_by(reload.clone(), reloaded.clone()),
            None => editor,
        };
        let building_text = std::fs::read_to_string(path)
            .ok()
            .filter(|text| Building::is_building_file(text));
        let Some(text) = building_text else {
            return Ok(Editors {
                floors: Vec::new(),
                editors: vec![Arc::new(serve(Editor::open(path, image)?))],
                building: None,
            });
        };
        anyhow::ensure!(
            image.is_none(),
            "{}: a building file names no plan image; give --image with one floor's site file",
            path.display()
        );
        let doc = BuildingDoc::parse(&text)
            .map_err(|e| anyhow::anyhow!("{}: not a building file: {e}", path.display()))?;
        let dir = path.parent().unwrap_or(Path::new("."));
        let mut floors = doc.floors;
        floors.sort_by_key(|f| f.level);
        let mut editors = Vec::new();
        for floor in &floors {
            let mut editor = serve(Editor::open(&dir.join(&floor.site), None)?);
            editor.floor = Some(floor.name.clone());
            editors.push(Arc::new(editor));
        }
        Ok(Editors {
            floors: floors
                .into_iter()
                .map(|f| FloorView {
                    name: f.name,
                    level: f.level,
                })
                .collect(),
            editors,
            building: Some(Arc::new(serve(Editor::open(path, None)?))),
        })
    }

    /// The file opened: the building file, or the one site file.
    pub fn path(&self) -> &Path {
        self.building.as_ref().unwrap_or(&self.editors[0]).path()
    }
}

/// The editor a request is for: its `?floor=`'s.
pub(super) struct OnFloor(Arc<Editor>);

impl axum::extract::FromRequestParts<Arc<Editors>> for OnFloor {
    type Rejection = super::floor::NotFound;

    async fn from_request_parts(
        parts: &mut axum::http::request::Parts,
        editors: &Arc<Editors>,
    ) -> Result<OnFloor, super::floor::NotFound> {
        if editors.floors.is_empty() {
            return Ok(OnFloor(editors.editors[0].clone()));
        }
        let asked = FloorQuery::of(&parts.uri).floor;
        let i = super::floor::pick(&editors.floors, asked.as_deref())?;
        Ok(OnFloor(editors.editors[i].clone()))
    }
}

/// `GET /api/editor`: the file as a document, and the plan image to show;
/// on a building, which floor it is and the floors to choose from.
pub(super) async fn get(State(editors): State<Arc<Editors>>, OnFloor(editor): OnFloor) -> Response {
    let (text, suggested) = {
        let opened = editor.lock();
        (opened.text.clone(), opened.suggested.clone())
    };
    let (doc, open_error) = match text.as_deref().map(SiteDoc::parse) {
        None => (None, None),
        Some(Ok(doc)) => (Some(doc), None),
        Some(Err(e)) => (None, Some(format!("{}: {e}", editor.path.display()))),
    };
    let image = doc
        .as_ref()
        .and_then(|d| d.floorplan.as_ref())
        .map(|f| f.image.clone())
        .or(suggested)
        .and_then(|name| editor.image_info(&name));
    Json(serde_json::json!({
        "path": editor.path.display().to_string(),
        "exists": text.is_some(),
        "doc": doc,
        "open_error": open_error,
        "image": image,
        "served_by_gateway": editor.gateway.is_some(),
        "floor": editor.floor,
        "floors": editors.floors,
    }))
    .into_response()
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct DocBody {
    doc: SiteDoc,
}

/// `POST /api/editor/check`: the TOML the document would be saved as, and
/// its problems or its view.
pub(super) async fn check(OnFloor(editor): OnFloor, Json(body): Json<DocBody>) -> Response {
    let (toml, result) = editor.check(&body.doc);
    let (problems, view) = match result {
        Ok(site) => (Vec::new(), Some(SiteView::new(&site, None))),
        Err(problems) => (problems, None),
    };
    Json(serde_json::json!({
        "ok": problems.is_empty(),
        "problems": problems,
        "toml": toml,
        "view": view,
    }))
    .into_response()
}

/// `PUT /api/editor/site`: saves a document without problems and, in a
/// gateway, applies it ([`Editor::store`]).
pub(super) async fn save(OnFloor(editor): OnFloor, Json(body): Json<DocBody>) -> Response {
    let (toml, result) = editor.check(&body.doc);
    if let Err(problems) = result {
        let message = format!("not saved: {}", problems.join("; "));
        return error(StatusCode::UNPROCESSABLE_ENTITY, "invalid_site", message);
    }
    editor.store(toml).await
}

/// The building file's editor, for the connectors' routes; a 404 on a
/// one-floor site.
pub(super) struct OfBuilding(Arc<Editor>);

impl axum::extract::FromRequestParts<Arc<Editors>> for OfBuilding {
    type Rejection = Response;

    async fn from_request_parts(
        _: &mut axum::http::request::Parts,
        editors: &Arc<Editors>,
    ) -> Result<OfBuilding, Response> {
        editors.building.clone().map(OfBuilding).ok_or_else(|| {
            error(
                StatusCode::NOT_FOUND,
                "not_a_building",
                "this editor edits one site file; connectors join the floors of a building file \
                 (see docs/floors.md)",
            )
        })
    }
}

/// Every problem of the building file `text` at `path`, as `gangway check`
/// words them; loads each floor's site file, off the event loop.
async fn building_problems(text: String, path: PathBuf) -> Vec<String> {
    tokio::task::spawn_blocking(move || {
        Building::parse(&text, &path, Site::load).map_or_else(|e| e.problems(), |_| Vec::new())
    })
    .await
    .unwrap_or_else(|e| vec![format!("checking the building failed: {e}")])
}

/// `GET /api/editor/connectors`: the building file's connectors, its
/// problems, and each kind's defaults and whether it is step-free.
pub(super) async fn connectors(OfBuilding(building): OfBuilding) -> Response {
    let text = building.lock().text.clone().unwrap_or_default();
    let connectors = match BuildingDoc::parse(&text) {
        Ok(doc) => doc.connectors,
        Err(e) => return invalid_building(format!("{}: {e}", building.path.display())),
    };
    let problems = building_problems(text, building.path.clone()).await;
    let kinds: Vec<_> = [
        ConnectorKind::Stairs,
        ConnectorKind::Lift,
        ConnectorKind::Escalator,
        ConnectorKind::Ramp,
    ]
    .into_iter()
    .map(|kind| {
        serde_json::json!({
            "kind": kind,
            "step_free": kind.step_free(),
            "s_per_level": kind.default_s_per_level(),
            "wait_s": kind.default_wait_s(),
        })
    })
    .collect();
    Json(serde_json::json!({
        "path": building.path.display().to_string(),
        "connectors": connectors,
        "problems": problems,
        "kinds": kinds,
    }))
    .into_response()
}

/// The 422 of a building file that does not parse or check.
fn invalid_building(message: String) -> Response {
    error(
        StatusCode::UNPROCESSABLE_ENTITY,
        "invalid_building",
        message,
    )
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct ConnectorsBody {
    connectors: Vec<ConnectorDoc>,
}

/// `PUT /api/editor/connectors`: replaces the building file's
/// `[[connectors]]` (nothing else in it changes) when the building, floors
/// and all, then passes `gangway check`; applies it as a site save does.
pub(super) async fn save_connectors(
    OfBuilding(building): OfBuilding,
    Json(body): Json<ConnectorsBody>,
) -> Response {
    let text = building.lock().text.clone().unwrap_or_default();
    let toml = match replace_connectors(&text, &body.connectors) {
        Ok(toml) => toml,
        Err(e) => return invalid_building(format!("{}: {e}", building.path.display())),
    };
    let problems = building_problems(toml.clone(), building.path.clone()).await;
    if !problems.is_empty() {
        return invalid_building(format!("not saved: {}", problems.join("; ")));
    }
    building.store(toml).await
}

impl Editor {
    /// Writes `toml`, checked, over the file, unless it changed on disk
    /// since it was opened or saved; applies it where a gateway serves it.
    /// The reply: `saved` (where), `applied` (true: the gateway serves it
    /// now; false: it does not; null: no gateway serves this file here) and
    /// `message`, what the page shows.
    async fn store(&self, toml: String) -> Response {
        let path = self.path.display().to_string();
        let written = {
            let mut opened = self.lock();
            let on_disk = std::fs::read_to_string(&self.path).ok();
            if on_disk != opened.text {
                return error(
                    StatusCode::CONFLICT,
                    "changed_on_disk",
                    format!(
                        "{path} changed on disk since the editor opened it; reload the editor to see \
                         it (nothing was saved)"
                    ),
                );
            }
            let written = write_atomically(&self.path, toml.as_bytes());
            if written.is_ok() {
                opened.text = Some(toml.clone());
            }
            written
        };
        if let Err(e) = written {
            return self.save_elsewhere(&toml, &e);
        }
        tracing::info!(path, "saved from the editor");
        let (applied, message) = match &self.gateway {
            None => (
                serde_json::Value::Null,
                format!(
                    "saved {path}; a gateway serving this file applies it when it reloads \
                     (`systemctl reload gangway`)"
                ),
            ),
            Some(gateway) => match gateway.apply().await {
                Ok(()) => (
                    true.into(),
                    format!("saved {path}; the gateway reloaded it and serves it now"),
                ),
                Err(why) => (false.into(), format!("saved {path}, but {why}")),
            },
        };
        Json(serde_json::json!({
            "saved": path,
            "toml": toml,
            "applied": applied,
            "message": message,
        }))
        .into_response()
    }

    /// The site file cannot be written (`why`): saves the site in the state
    /// directory instead, or, without one, says where it must go.
    fn save_elsewhere(&self, toml: &str, why: &std::io::Error) -> Response {
        let path = self.path.display();
        let file_name = self.path.file_name().unwrap_or_default();
        let put = |from: &str| {
            format!(
                "to serve it, put it in place as root: `sudo install -m 644 {from} {path} && sudo \
                 systemctl reload gangway`"
            )
        };
        if let Some(dir) = &self.fallback_dir {
            let instead = dir.join(file_name);
            match write_atomically(&instead, toml.as_bytes()) {
                Ok(()) => {
                    tracing::warn!(%path, instead = %instead.display(), "cannot write the site file ({why}); saved it in the state directory");
                    let shown = instead.display().to_string();
                    let message = format!(
                        "cannot write {path} ({why}); saved to {shown} instead; {}",
                        put(&shown)
                    );
                    return Json(serde_json::json!({
                        "saved": shown,
                        "instead_of": path.to_string(),
                        "toml": toml,
                        "applied": false,
                        "message": message,
                    }))
                    .into_response();
                }
                Err(e) => tracing::warn!("cannot save in {} either: {e}", dir.display()),
            }
        }
        error(
            StatusCode::INTERNAL_SERVER_ERROR,
            "write_failed",
            format!(
                "cannot write {path} ({why}); nothing was saved. Download the site file (below) \
                 and {}",
                put("<downloaded file>")
            ),
        )
    }
}

impl Gateway {
    /// Asks the gateway to reload and waits for how it went.
    async fn apply(&self) -> Result<(), String> {
        let mut reloaded = self.reloaded.clone();
        let before = reloaded.borrow_and_update().count;
        // A full queue is a reload not started yet: it reads the new file.
        if let Err(mpsc::error::TrySendError::Closed(())) = self.reload.try_send(()) {
            return Err("the gateway is stopping: it did not reload it".into());
        }
        match tokio::time::timeout(APPLY_WAIT, reloaded.wait_for(|r| r.count > before)).await {
            Ok(Ok(r)) => match &r.refused {
                None => Ok(()),
                Some(why) => Err(format!(
                    "the gateway refused to reload it and still serves the previous site: {why}"
                )),
            },
            Ok(Err(_)) => Err("the gateway is stopping: it did not reload it".into()),
            Err(_) => Err(format!(
                "the gateway has not finished reloading after {} s (models may still be \
                 loading); the map shows the new site once it has",
                APPLY_WAIT.as_secs()
            )),
        }
    }
}

/// Replaces `path` by `bytes` all at once: a reader (the gateway on
/// SIGHUP) sees the old file or the new one, never half of it.
fn write_atomically(path: &Path, bytes: &[u8]) -> std::io::Result<()> {
    use std::io::Write;
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut tmp = tempfile::NamedTempFile::new_in(dir)?;
    tmp.write_all(bytes)?;
    tmp.as_file().sync_all()?;
    if let Ok(meta) = std::fs::metadata(path) {
        tmp.as_file().set_permissions(meta.permissions())?;
    }
    tmp.persist(path).map_err(|e| e.error)?;
    Ok(())
}

#[derive(Deserialize)]
pub(super) struct ImageQuery {
    name: String,
}

/// `GET /api/editor/image?name=…`: one of the images the editor knows.
pub(super) async fn image(OnFloor(editor): OnFloor, Query(q): Query<ImageQuery>) -> Response {
    if !editor.lock().images.contains(&q.name) {
        return error(
            StatusCode::NOT_FOUND,
            "not_found",
            "no such floor-plan image in this editor",
        );
    }
    image_file(&editor.dir.join(&q.name))
}

/// A floor-plan image file as a response.
pub(super) fn image_file(path: &Path) -> Response {
    let info = match probe_image(path) {
        Ok(info) => info,
        Err(why) => return error(StatusCode::NOT_FOUND, "not_found", why),
    };
    match std::fs::read(path) {
        Ok(bytes) => (
            [
                (header::CONTENT_TYPE, info.mime),
                (header::CACHE_CONTROL, "no-cache"),
            ],
            bytes,
        )
            .into_response(),
        Err(e) => error(StatusCode::NOT_FOUND, "not_found", e.to_string()),
    }
}

/// `PUT /api/editor/image?name=…`: stores an uploaded plan image beside the
/// site file under that (plain) name.
pub(super) async fn upload(
    OnFloor(editor): OnFloor,
    Query(q): Query<ImageQuery>,
    bytes: Bytes,
) -> Response {
    let name = q.name.trim();
    let plain = !name.is_empty()
        && name.len() <= 100
        && !name.starts_with('.')
        && name
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || "._-".contains(c));
    let named = crate::site::floorplan_mime_of_name(name);
    let (Ok(named), true) = (named, plain) else {
        return error(
            StatusCode::BAD_REQUEST,
            "bad_name",
            "name the image with letters, digits, '.', '_' or '-', ending .png, .jpg or .webp",
        );
    };
    if bytes.len() as u64 > MAX_IMAGE_BYTES || mime_of_bytes(&bytes) != Some(named) {
        return error(
            StatusCode::BAD_REQUEST,
            "bad_image",
            format!(
                "the upload is not a {named} image of at most {} MiB",
                MAX_IMAGE_BYTES >> 20
            ),
        );
    }
    let path = editor.dir.join(name);
    match std::fs::read(&path) {
        Ok(existing) if existing != bytes.as_ref() => {
            return error(
                StatusCode::CONFLICT,
                "exists",
                format!(
                    "{} already exists and is another image; rename yours",
                    path.display()
                ),
            );
        }
        Ok(_) => {}
        Err(_) => {
            if let Err(e) = write_atomically(&path, &bytes) {
                return error(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    "write_failed",
                    format!(
                        "cannot store the image as {} ({e}): copy it there as root (`sudo install \
                         -m 644 {name} {}`) and open the editor again",
                        path.display(),
                        path.display()
                    ),
                );
            }
        }
    }
    editor.lock().images.insert(name.to_owned());
    match editor.image_info(name) {
        Some(info) => Json(info).into_response(),
        None => error(
            StatusCode::BAD_REQUEST,
            "bad_image",
            "cannot read the image's size",
        ),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn relative_paths_climb_out_of_the_site_directory() {
        let dir = tempfile::tempdir().unwrap();
        let sites = dir.path().join("config/sites");
        let data = dir.path().join("data");
        std::fs::create_dir_all(&sites).unwrap();
        std::fs::create_dir_all(&data).unwrap();
        std::fs::write(data.join("plan.png"), b"x").unwrap();
        std::fs::write(sites.join("here.png"), b"x").unwrap();
        assert_eq!(
            relative(&sites, &data.join("plan.png")).unwrap(),
            "../../data/plan.png"
        );
        assert_eq!(
            relative(&sites, &sites.join("here.png")).unwrap(),
            "here.png"
        );
        // Through a link, the path the user gave, not where the link points.
        let elsewhere = tempfile::tempdir().unwrap();
        std::fs::write(elsewhere.path().join("plan.png"), b"x").unwrap();
        std::os::unix::fs::symlink(elsewhere.path(), dir.path().join("shared")).unwrap();
        let linked = sites.join("../../shared/plan.png");
        assert_eq!(relative(&sites, &linked).unwrap(), "../../shared/plan.png");
    }
}
