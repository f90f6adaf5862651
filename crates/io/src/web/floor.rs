//! Which floor of a building a request is about: `?floor=NAME` on the map's
//! site, floor plan and the editor's API, the lowest floor when absent (a
//! one-floor site's only floor), and a 404 naming the floors for a name the
//! building does not have.

use axum::http::StatusCode;
use axum::response::{IntoResponse, Response};
use serde::{Deserialize, Serialize};

use super::security::error;
use crate::site::Building;

/// `?floor=NAME`.
#[derive(Deserialize)]
pub(super) struct FloorQuery {
    pub(super) floor: Option<String>,
}

impl FloorQuery {
    /// The query of `uri` (a malformed one names no floor).
    pub(super) fn of(uri: &axum::http::Uri) -> FloorQuery {
        axum::extract::Query::<FloorQuery>::try_from_uri(uri)
            .map_or(FloorQuery { floor: None }, |q| q.0)
    }
}

/// A floor as the pages list it.
#[derive(Clone, Debug, Serialize)]
pub(super) struct FloorView {
    pub(super) name: String,
    pub(super) level: i32,
}

/// The floors of `building`, lowest first.
pub(super) fn floors(building: &Building) -> Vec<FloorView> {
    building
        .floors()
        .iter()
        .map(|f| FloorView {
            name: f.name.clone(),
            level: f.level,
        })
        .collect()
}

/// The stops of `building`'s connectors on floor `i`, as the map draws
/// them: id, kind, cell and the floors it goes to from there.
pub(super) fn connectors(building: &Building, i: usize) -> Vec<serde_json::Value> {
    let floors = building.floors();
    building
        .connectors()
        .iter()
        .filter_map(|c| {
            let here = c.stops.iter().find(|s| s.floor == i)?;
            let to: Vec<&str> = c
                .stops
                .iter()
                .filter(|s| s.floor != i)
                .map(|s| floors[s.floor].name.as_str())
                .collect();
            Some(serde_json::json!({
                "id": c.id, "kind": c.kind.name(), "cell": here.cell, "to": to,
            }))
        })
        .collect()
}

/// The index in `floors` of the floor `asked` names (none: the first, the
/// lowest), or the 404 that says which floors there are.
pub(super) fn pick(floors: &[FloorView], asked: Option<&str>) -> Result<usize, NotFound> {
    let Some(asked) = asked else { return Ok(0) };
    floors.iter().position(|f| f.name == asked).ok_or_else(|| {
        let names: Vec<&str> = floors.iter().map(|f| f.name.as_str()).collect();
        NotFound {
            code: "unknown_floor",
            message: format!(
                "no floor {asked:?} here; the floors are {}",
                names.join(", ")
            ),
        }
    })
}

/// A floor (or a map) a request asks for that is not here: a 404.
pub(super) struct NotFound {
    pub(super) code: &'static str,
    pub(super) message: String,
}

impl IntoResponse for NotFound {
    fn into_response(self) -> Response {
        error(StatusCode::NOT_FOUND, self.code, self.message)
    }
}

/// `path` with `?floor=NAME` when `floor` is given.
pub(super) fn url(path: &str, floor: Option<&str>) -> String {
    match floor {
        None => path.to_owned(),
        Some(name) => {
            let name: String = url::form_urlencoded::byte_serialize(name.as_bytes()).collect();
            format!("{path}?floor={name}")
        }
    }
}
