//! One floor's site from its GeoJSON floor plan (the Indoor Location
//! Competition layout: `geojson_map.json` beside `floor_info.json`).
//!
//! The plan is one feature for the floor's outline and one polygon per shop,
//! room or other closed area. The site is drawn as a `map` at the chosen cell
//! size: a cell is walkable (`#`) when its centre is inside the outline and in
//! no other polygon, so corridors, atria edges and open areas are what is
//! left between the shops. Every other polygon becomes a named place (its
//! `name`, else its `id`; a name several polygons share is numbered in file
//! order) whose cell is its door: the cell of the largest connected walkable
//! area nearest to its outline, the middle of its frontage when several are as
//! near, so routes to any place exist.
//!
//! The frame is the walks' metres: x east from the outline's west edge, y
//! north from its south edge (`y_axis = "up"`, `origin_m = [0, height]`).
//! The dataset's README says the plan is in metres, but its coordinates are
//! WGS84 longitude and latitude: projected about the outline's middle
//! latitude (equirectangular, R = 6,378,137 m), its bounding box is
//! `floor_info.json`'s width × height to the centimetre. So the importer takes
//! whichever reading of the coordinates, metres as given or degrees
//! projected, gives the outline the floor's size (within 2%), and refuses a
//! plan that matches neither, naming both sizes.
//!
//! Two things only a building needs are read too: the floor's number (the
//! `floor_num` property the plan's floor feature carries) and the areas that
//! are stairs, lifts, escalators or ramps by their name or category, at their
//! position in the plan's own coordinates, so that the floors of one building
//! can be lined up (`survey::building`).

use std::collections::{BTreeMap, VecDeque};
use std::path::Path;

use anyhow::{Context, bail};
use serde_json::Value;

use crate::site::{Cell, ConnectorKind, FloorplanDoc, ReferencePoint, SiteDoc, YAxis, probe_image};

/// Earth radius of the projection, metres (WGS84's semi-major axis).
const EARTH_RADIUS_M: f64 = 6_378_137.0;
/// How far the outline's size may be from `floor_info.json`'s, as a share.
const SIZE_TOLERANCE: f64 = 0.02;
/// How far from a polygon its door is looked for before taking the walkable
/// cell nearest its centre, metres.
const DOOR_REACH_M: f64 = 3.0;

/// A ring of a polygon, metres.
type Ring = Vec<[f64; 2]>;

/// One closed area of the plan: its rings (outer and holes, even-odd) and name.
struct Area {
    name: String,
    rings: Vec<Ring>,
}

/// The floor in metres: its size, outline and the areas on it.
pub(crate) struct FloorPlan {
    width_m: f64,
    height_m: f64,
    outline: Vec<Ring>,
    areas: Vec<Area>,
    /// The `floor_num` property of the plan's floor feature, when it has one.
    pub(crate) floor_num: Option<i64>,
    /// Whether the plan's coordinates are WGS84 degrees (else metres).
    degrees: bool,
    pub(crate) connectors: Vec<ConnectorArea>,
}

/// An area of the plan that is stairs, a lift, an escalator or a ramp.
pub(crate) struct ConnectorArea {
    /// Its place's name on the floor's site (where its door is).
    pub(crate) place: String,
    pub(crate) kind: ConnectorKind,
    /// The middle of its bounding box in the plan's own coordinates, which
    /// the floors of one building share.
    at: [f64; 2],
}

/// Which connector a word of an area's name or category says it is: English
/// and the Chinese of the plans of that competition's malls (电梯 lift, 扶梯
/// escalator, 楼梯 stairs, 坡道 ramp).
fn connector_kind(text: &str) -> Option<ConnectorKind> {
    let text = text.to_lowercase();
    let chinese = [
        ("扶梯", ConnectorKind::Escalator),
        ("电梯", ConnectorKind::Lift),
        ("直梯", ConnectorKind::Lift),
        ("楼梯", ConnectorKind::Stairs),
        ("坡道", ConnectorKind::Ramp),
    ];
    if let Some((_, kind)) = chinese.iter().find(|(word, _)| text.contains(word)) {
        return Some(*kind);
    }
    // Whole words, so that a shop called "Uplift" is not a lift.
    text.split(|c: char| !c.is_alphanumeric())
        .find_map(|word| match word {
            "lift" | "lifts" | "elevator" | "elevators" => Some(ConnectorKind::Lift),
            "stair" | "stairs" | "staircase" | "stairway" | "stairwell" => {
                Some(ConnectorKind::Stairs)
            }
            "escalator" | "escalators" => Some(ConnectorKind::Escalator),
            "ramp" | "ramps" => Some(ConnectorKind::Ramp),
            _ => None,
        })
}

/// The connector a feature's properties say it is: by `name`, `display`,
/// `type` or `category` (a string or a list of them).
fn connector_of(props: &Value) -> Option<ConnectorKind> {
    let mut texts: Vec<&str> = ["name", "display", "type", "category"]
        .iter()
        .filter_map(|key| props[*key].as_str())
        .collect();
    if let Some(list) = props["category"].as_array() {
        texts.extend(list.iter().filter_map(Value::as_str));
    }
    texts.into_iter().find_map(connector_kind)
}

/// `floor_info.json`'s `map_info` width and height, metres.
pub(crate) fn floor_size(path: &Path) -> anyhow::Result<[f64; 2]> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("{}: cannot read", path.display()))?;
    let info: Value = serde_json::from_str(&text).with_context(|| {
        format!(
            "{}: not JSON; expected {{\"map_info\": {{\"width\": W, \"height\": H}}}}",
            path.display()
        )
    })?;
    let get = |key: &str| {
        info["map_info"][key]
            .as_f64()
            .filter(|v| v.is_finite() && *v > 0.0)
            .with_context(|| {
                format!(
                    "{}: field `map_info.{key}`: missing or not a positive number of metres",
                    path.display()
                )
            })
    };
    Ok([get("width")?, get("height")?])
}

impl FloorPlan {
    /// Reads `geojson_map.json` for a floor of `size` metres.
    pub(crate) fn read(path: &Path, size: [f64; 2]) -> anyhow::Result<FloorPlan> {
        let shown = path.display();
        let text =
            std::fs::read_to_string(path).with_context(|| format!("{shown}: cannot read"))?;
        let json: Value =
            serde_json::from_str(&text).with_context(|| format!("{shown}: not JSON"))?;
        let features = json["features"].as_array().with_context(|| {
            format!("{shown}: field `features`: missing; expected a GeoJSON FeatureCollection")
        })?;
        let mut polygons = Vec::new();
        for (i, feature) in features.iter().enumerate() {
            let rings = rings_of(&feature["geometry"])
                .with_context(|| format!("{shown}: field `features[{i}].geometry`"))?;
            if !rings.is_empty() {
                polygons.push((i, rings));
            }
        }
        // The outline is the feature whose bounding box is the largest.
        let Some(outline_at) = (0..polygons.len()).max_by(|&a, &b| {
            let area = |r: &[Ring]| {
                let (lo, hi) = bounds(r);
                (hi[0] - lo[0]) * (hi[1] - lo[1])
            };
            area(&polygons[a].1).total_cmp(&area(&polygons[b].1))
        }) else {
            bail!("{shown}: no Polygon or MultiPolygon feature; the floor outline is needed");
        };
        let outline_feature = polygons[outline_at].0;
        let (lo, hi) = bounds(&polygons[outline_at].1);
        let raw = [hi[0] - lo[0], hi[1] - lo[1]];
        let scale = [
            EARTH_RADIUS_M * ((lo[1] + hi[1]) / 2.0).to_radians().cos() * 1f64.to_radians(),
            EARTH_RADIUS_M * 1f64.to_radians(),
        ];
        let projected = [raw[0] * scale[0], raw[1] * scale[1]];
        let fits = |s: [f64; 2]| (0..2).all(|k| (s[k] - size[k]).abs() <= SIZE_TOLERANCE * size[k]);
        let degrees = !fits(raw) && fits(projected);
        let to_metres: Box<dyn Fn([f64; 2]) -> [f64; 2]> = if fits(raw) {
            Box::new(|p| p)
        } else if degrees {
            Box::new(move |p| [(p[0] - lo[0]) * scale[0], (p[1] - lo[1]) * scale[1]])
        } else {
            bail!(
                "{shown}: the floor outline is {:.1} × {:.1} as metres, {:.1} × {:.1} m as WGS84 \
                 degrees, but floor_info.json says {:.1} × {:.1} m; check that both files are of \
                 the same floor",
                raw[0],
                raw[1],
                projected[0],
                projected[1],
                size[0],
                size[1]
            );
        };
        let floor_num = features
            .iter()
            .find_map(|f| f["properties"]["floor_num"].as_i64());
        let mut names: BTreeMap<String, usize> = BTreeMap::new();
        let mut areas = Vec::new();
        let mut kinds = Vec::new();
        let mut outline = Vec::new();
        for (i, rings) in polygons {
            let (lo, hi) = bounds(&rings);
            let at = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
            let rings: Vec<Ring> = rings
                .into_iter()
                .map(|r| r.into_iter().map(&to_metres).collect())
                .collect();
            if i == outline_feature {
                outline = rings;
                continue;
            }
            let props = &features[i]["properties"];
            let name = [&props["name"], &props["id"]]
                .into_iter()
                .find_map(|v| v.as_str().map(str::trim).filter(|s| !s.is_empty()))
                .map_or_else(|| format!("area {i}"), unescape);
            *names.entry(name.clone()).or_default() += 1;
            kinds.push(connector_of(props).map(|kind| (kind, at)));
            areas.push(Area { name, rings });
        }
        // A name several areas share is numbered in file order.
        let mut seen: BTreeMap<String, usize> = BTreeMap::new();
        for area in &mut areas {
            if names[&area.name] > 1 {
                let n = seen.entry(area.name.clone()).or_default();
                *n += 1;
                area.name = format!("{} #{n}", area.name);
            }
        }
        let connectors = areas
            .iter()
            .zip(kinds)
            .filter_map(|(area, kind)| {
                kind.map(|(kind, at)| ConnectorArea {
                    place: area.name.clone(),
                    kind,
                    at,
                })
            })
            .collect();
        Ok(FloorPlan {
            width_m: size[0],
            height_m: size[1],
            outline,
            areas,
            floor_num,
            degrees,
            connectors,
        })
    }

    /// Metres between a connector area of this floor and one of `other`
    /// (another floor of the same building, whose plan shares this one's
    /// coordinates); `None` when one plan is in degrees and the other in
    /// metres, which cannot be lined up.
    pub(crate) fn distance_m(
        &self,
        a: &ConnectorArea,
        other: &FloorPlan,
        b: &ConnectorArea,
    ) -> Option<f64> {
        if self.degrees != other.degrees {
            return None;
        }
        let d = [b.at[0] - a.at[0], b.at[1] - a.at[1]];
        if !self.degrees {
            return Some(d[0].hypot(d[1]));
        }
        let latitude = ((a.at[1] + b.at[1]) / 2.0).to_radians();
        let per_degree = EARTH_RADIUS_M * 1f64.to_radians();
        Some((d[0] * per_degree * latitude.cos()).hypot(d[1] * per_degree))
    }

    /// The site of this floor at `cell_m`, its places at their doors, and
    /// `image` (a file name beside the site and its size in pixels) as the plan
    /// under it.
    pub(crate) fn site(&self, name: &str, cell_m: f64, image: Option<(&str, [u32; 2])>) -> SiteDoc {
        let cols = (self.width_m / cell_m).ceil() as usize;
        let rows = (self.height_m / cell_m).ceil() as usize;
        let centre = |c: usize, r: usize| {
            [
                (c as f64 + 0.5) * cell_m,
                self.height_m - (r as f64 + 0.5) * cell_m,
            ]
        };
        let mut open = vec![false; cols * rows];
        for r in 0..rows {
            for c in 0..cols {
                let p = centre(c, r);
                open[r * cols + c] =
                    inside(&self.outline, p) && !self.areas.iter().any(|a| inside(&a.rings, p));
            }
        }
        let main = largest_component(&open, cols, rows);
        let mut places = BTreeMap::new();
        for area in &self.areas {
            let door = door(area, &main, cols, rows, cell_m, &centre);
            if let Some(i) = door {
                places.insert(
                    area.name.clone(),
                    Cell::new((i % cols) as u16, (i / cols) as u16),
                );
            }
        }
        let mut map = String::with_capacity((cols + 1) * rows);
        for r in 0..rows {
            for c in 0..cols {
                map.push(if open[r * cols + c] { '#' } else { '.' });
            }
            map.push('\n');
        }
        let floorplan = image.map(|(file, px)| FloorplanDoc {
            image: file.to_owned(),
            reference: vec![
                ReferencePoint {
                    px: [0.0, 0.0],
                    m: [0.0, self.height_m],
                },
                ReferencePoint {
                    px: [f64::from(px[0]), f64::from(px[1])],
                    m: [self.width_m, 0.0],
                },
            ],
        });
        SiteDoc {
            name: name.to_owned(),
            cell_m,
            origin_m: Some([0.0, self.height_m]),
            y_axis: Some(YAxis::Up),
            map: Some(map),
            floorplan,
            places,
            ..SiteDoc::default()
        }
    }
}

/// Reads the floor in `floor_dir` (`floor_info.json`, `geojson_map.json`
/// and `floor_image.png` when there is one), copies its image into `out`
/// (created if needed) and returns the plan and its site at `cell_m` named
/// `name`, the image under it.
pub(crate) fn import_plan(
    floor_dir: &Path,
    out: &Path,
    name: &str,
    cell_m: f64,
) -> anyhow::Result<(FloorPlan, SiteDoc)> {
    let size = floor_size(&floor_dir.join("floor_info.json"))?;
    let plan = FloorPlan::read(&floor_dir.join("geojson_map.json"), size)?;
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    let image_file = "floor_image.png";
    let image = floor_dir.join(image_file);
    let image = if image.is_file() {
        let info = probe_image(&image).map_err(anyhow::Error::msg)?;
        // Read and written rather than copied, so the copy is writable
        // (the next import replaces it) whatever the original's mode.
        let bytes =
            std::fs::read(&image).with_context(|| format!("{}: cannot read", image.display()))?;
        std::fs::write(out.join(image_file), bytes)
            .with_context(|| format!("cannot write {}", out.join(image_file).display()))?;
        Some((image_file, [info.width, info.height]))
    } else {
        None
    };
    let doc = plan.site(name, cell_m, image);
    Ok((plan, doc))
}

/// The door of `area`: among the cells of the main walkable area (`main`)
/// within [`DOOR_REACH_M`] of its bounding box, those nearest its outline
/// (within half a cell of the nearest), and of them the one nearest its
/// centre; without any, the main area's cell nearest its centre.
fn door(
    area: &Area,
    main: &[bool],
    cols: usize,
    rows: usize,
    cell_m: f64,
    centre: &dyn Fn(usize, usize) -> [f64; 2],
) -> Option<usize> {
    let (lo, hi) = bounds(&area.rings);
    let mid = [(lo[0] + hi[0]) / 2.0, (lo[1] + hi[1]) / 2.0];
    let near = |p: [f64; 2]| {
        p[0] >= lo[0] - DOOR_REACH_M
            && p[0] <= hi[0] + DOOR_REACH_M
            && p[1] >= lo[1] - DOOR_REACH_M
            && p[1] <= hi[1] + DOOR_REACH_M
    };
    let mut candidates = Vec::new();
    for r in 0..rows {
        for c in 0..cols {
            let p = centre(c, r);
            if main[r * cols + c] && near(p) {
                candidates.push((r * cols + c, edge_distance(&area.rings, p), dist(p, mid)));
            }
        }
    }
    if let Some(nearest) = candidates.iter().map(|c| c.1).min_by(f64::total_cmp) {
        return candidates
            .iter()
            .filter(|c| c.1 <= nearest + cell_m / 2.0)
            .min_by(|a, b| a.2.total_cmp(&b.2))
            .map(|c| c.0);
    }
    (0..cols * rows).filter(|&i| main[i]).min_by(|&a, &b| {
        dist(centre(a % cols, a / cols), mid).total_cmp(&dist(centre(b % cols, b / cols), mid))
    })
}

/// The cells of the largest 4-connected walkable area (routes never cut a
/// blocked corner, so diagonal neighbours alone are not connected).
fn largest_component(open: &[bool], cols: usize, rows: usize) -> Vec<bool> {
    let mut label = vec![usize::MAX; open.len()];
    let mut best = (0, usize::MAX);
    let mut queue = VecDeque::new();
    for start in 0..open.len() {
        if !open[start] || label[start] != usize::MAX {
            continue;
        }
        label[start] = start;
        queue.push_back(start);
        let mut size = 0;
        while let Some(i) = queue.pop_front() {
            size += 1;
            let (c, r) = (i % cols, i / cols);
            let neighbours = [
                (c > 0).then(|| i - 1),
                (c + 1 < cols).then(|| i + 1),
                (r > 0).then(|| i - cols),
                (r + 1 < rows).then(|| i + cols),
            ];
            for j in neighbours.into_iter().flatten() {
                if open[j] && label[j] == usize::MAX {
                    label[j] = start;
                    queue.push_back(j);
                }
            }
        }
        if size > best.0 {
            best = (size, start);
        }
    }
    label.iter().map(|&l| l == best.1).collect()
}

/// The rings of a Polygon or MultiPolygon geometry (none for other types).
fn rings_of(geometry: &Value) -> anyhow::Result<Vec<Ring>> {
    let polygons: Vec<&Value> = match geometry["type"].as_str() {
        Some("Polygon") => vec![&geometry["coordinates"]],
        Some("MultiPolygon") => geometry["coordinates"]
            .as_array()
            .context("`coordinates`: not an array of polygons")?
            .iter()
            .collect(),
        _ => return Ok(Vec::new()),
    };
    let mut rings = Vec::new();
    for polygon in polygons {
        for ring in polygon
            .as_array()
            .context("`coordinates`: not an array of rings")?
        {
            let points = ring
                .as_array()
                .context("`coordinates`: a ring is not an array of points")?
                .iter()
                .map(|p| match (p[0].as_f64(), p[1].as_f64()) {
                    (Some(x), Some(y)) if x.is_finite() && y.is_finite() => Ok([x, y]),
                    _ => bail!("`coordinates`: {p} is not a point [x, y]"),
                })
                .collect::<anyhow::Result<Ring>>()?;
            if points.len() >= 3 {
                rings.push(points);
            }
        }
    }
    Ok(rings)
}

/// A name as shown: the XML entities some plans leave in names
/// (`CHOW&amp;RAY` beside `ME&CITY`) read as their characters.
fn unescape(name: &str) -> String {
    [
        ("&lt;", "<"),
        ("&gt;", ">"),
        ("&quot;", "\""),
        ("&#39;", "'"),
        ("&amp;", "&"),
    ]
    .iter()
    .fold(name.to_owned(), |n, (entity, c)| n.replace(entity, c))
}

/// The bounding box of rings.
fn bounds(rings: &[Ring]) -> ([f64; 2], [f64; 2]) {
    let mut lo = [f64::INFINITY; 2];
    let mut hi = [f64::NEG_INFINITY; 2];
    for p in rings.iter().flatten() {
        for k in 0..2 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (lo, hi)
}

/// Whether `p` is inside `rings` by the even-odd rule (holes are outside).
fn inside(rings: &[Ring], p: [f64; 2]) -> bool {
    let mut odd = false;
    for ring in rings {
        for (k, a) in ring.iter().enumerate() {
            let b = ring[(k + 1) % ring.len()];
            if (a[1] > p[1]) != (b[1] > p[1])
                && p[0] < a[0] + (p[1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1])
            {
                odd = !odd;
            }
        }
    }
    odd
}

/// Distance from `p` to the nearest edge of `rings`.
fn edge_distance(rings: &[Ring], p: [f64; 2]) -> f64 {
    let mut best = f64::INFINITY;
    for ring in rings {
        for (k, a) in ring.iter().enumerate() {
            let b = ring[(k + 1) % ring.len()];
            let d = [b[0] - a[0], b[1] - a[1]];
            let len2 = d[0] * d[0] + d[1] * d[1];
            let s = if len2 > 0.0 {
                (((p[0] - a[0]) * d[0] + (p[1] - a[1]) * d[1]) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            best = best.min(dist(p, [a[0] + s * d[0], a[1] + s * d[1]]));
        }
    }
    best
}

fn dist(a: [f64; 2], b: [f64; 2]) -> f64 {
    (a[0] - b[0]).hypot(a[1] - b[1])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_read_as_shown() {
        assert_eq!(unescape("CHOW&amp;RAY"), "CHOW&RAY");
        assert_eq!(unescape("ME&CITY"), "ME&CITY");
        assert_eq!(unescape("&amp;lt;"), "&lt;");
    }

    #[test]
    fn connector_areas_of_two_floors_are_measured_in_metres() {
        let floor = |degrees: bool, at: [f64; 2]| FloorPlan {
            width_m: 10.0,
            height_m: 10.0,
            outline: Vec::new(),
            areas: Vec::new(),
            floor_num: None,
            degrees,
            connectors: vec![ConnectorArea {
                place: "lift".into(),
                kind: ConnectorKind::Lift,
                at,
            }],
        };
        let (a, b) = (floor(false, [1.0, 2.0]), floor(false, [4.0, 6.0]));
        let d = a.distance_m(&a.connectors[0], &b, &b.connectors[0]);
        assert_eq!(d, Some(5.0));
        // A ten-thousandth of a degree east at 60° N is half of one north.
        let (a, b) = (floor(true, [120.0, 60.0]), floor(true, [120.0001, 60.0]));
        let east = a
            .distance_m(&a.connectors[0], &b, &b.connectors[0])
            .unwrap();
        let c = floor(true, [120.0, 60.0001]);
        let north = a
            .distance_m(&a.connectors[0], &c, &c.connectors[0])
            .unwrap();
        assert!((north - 11.13).abs() < 0.01, "{north}");
        assert!((east / north - 0.5).abs() < 1e-4, "{east} {north}");
        // Plans in metres and in degrees cannot be lined up.
        let m = floor(false, [1.0, 2.0]);
        assert_eq!(a.distance_m(&a.connectors[0], &m, &m.connectors[0]), None);
    }

    #[test]
    fn connectors_are_known_by_whole_words_and_their_chinese_names() {
        assert_eq!(connector_kind("Elevator 2"), Some(ConnectorKind::Lift));
        assert_eq!(connector_kind("east-STAIRS"), Some(ConnectorKind::Stairs));
        assert_eq!(connector_kind("自动扶梯"), Some(ConnectorKind::Escalator));
        assert_eq!(connector_kind("Uplift Yoga"), None);
        assert_eq!(connector_kind("Rampage"), None);
        let props = serde_json::json!({"name": "A12", "category": ["x", "ramp"]});
        assert_eq!(connector_of(&props), Some(ConnectorKind::Ramp));
    }
}
