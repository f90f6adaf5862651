//! The site: the building's grid, which cells are walkable, where the anchors are
//! and which places have names. Everything site-specific comes from a site file
//! (TOML); nothing in the code knows about any particular building.
//!
//! Coordinates: a cell `[x, y]` is column `x` from 0 (left) and row `y` from 0
//! (top row of `map`). A cell is `cell_m` metres square. The site's metric
//! frame places the grid in the building's own coordinates ("world" metres):
//! `origin_m` is where the outer top-left corner of cell `[0, 0]` is, and
//! `y_axis` says whether world y grows with the row index (`down`, the
//! default) or shrinks with it (`up`, as on survey drawings). With the defaults
//! a cell's centre is at `((x + 0.5) * cell_m, (y + 0.5) * cell_m)`.
//! The private `Frame` is the one place that transform is written
//! ([`Site::world_of_grid`], [`Site::world_of_cell`], [`Site::cell_of_world`]);
//! every metric position the gateway computes or publishes goes through it.
//!
//! The grid is a character `map`, or an open floor of `width_m` × `height_m`;
//! obstacle polygons and walls given in world metres are rasterised onto it at
//! load (the rules are on `Raster`), so the rest of the gateway only ever sees
//! walkable and blocked cells. Anchors have a metric [`Mount`] (a `pos`
//! anywhere near the grid, or the centre of a `cell`), which every distance
//! model uses.
//!
//! Validation happens once, at load, so every later stage may assume a consistent
//! site: places and anchors given by cell sit on walkable cells, anchors given
//! by `pos` lie near the grid, ids are unique, the grid is rectangular and
//! bounded. Errors name the file, the TOML line and what to change.

use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use toml::Spanned;
use uuid::Uuid;

use crate::sighting::{BeaconId, Mac};

mod building;
mod doc;
mod floorplan;

pub use building::{
    Building, BuildingDoc, Connector, ConnectorDoc, ConnectorKind, Floor, FloorDoc, Stop, StopDoc,
    floor_file, floor_path, replace_connectors,
};

pub use doc::{BeaconDoc, FloorplanDoc, SiteDoc, write_doc};
pub use floorplan::{
    Floorplan, MAX_IMAGE_BYTES, ReferencePoint, mime_of_bytes,
    mime_of_name as floorplan_mime_of_name, probe_image,
};

/// A grid cell, serialized as `[x, y]`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(from = "[u16; 2]", into = "[u16; 2]")]
pub struct Cell {
    pub x: u16,
    pub y: u16,
}

impl Cell {
    pub const fn new(x: u16, y: u16) -> Self {
        Cell { x, y }
    }

    /// Chebyshev distance: the number of 8-connected steps between two cells on
    /// an empty grid.
    pub fn chebyshev(self, other: Cell) -> u16 {
        self.x.abs_diff(other.x).max(self.y.abs_diff(other.y))
    }

    /// Euclidean distance in cells. A plain square root, not `hypot`: grid
    /// coordinates cannot overflow or underflow the sum of squares, and the
    /// tracker's median takes hundreds of distances per fix.
    pub fn distance(self, other: Cell) -> f64 {
        let dx = f64::from(self.x) - f64::from(other.x);
        let dy = f64::from(self.y) - f64::from(other.y);
        (dx * dx + dy * dy).sqrt()
    }
}

impl From<[u16; 2]> for Cell {
    fn from([x, y]: [u16; 2]) -> Self {
        Cell { x, y }
    }
}

impl From<Cell> for [u16; 2] {
    fn from(c: Cell) -> Self {
        [c.x, c.y]
    }
}

impl fmt::Display for Cell {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "[{}, {}]", self.x, self.y)
    }
}

/// What one character of the map says about a cell. Everything but `Blocked` is
/// walkable; the attributes let route profiles (wheelchair, low vision) treat
/// cells differently.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Tile {
    /// `.`: not public access (walls, shelving, staff areas).
    Blocked,
    /// `#`: open public-access floor.
    Open,
    /// `s`: stairs.
    Stairs,
    /// `e`: elevator.
    Elevator,
    /// `d`: door.
    Door,
    /// `n`: narrow passage (under ~1 m clear width).
    Narrow,
}

impl Tile {
    /// The glyphs a map may use, in the order of the documentation.
    pub(crate) const GLYPHS: &'static str = "#.sedn";

    fn from_glyph(c: char) -> Option<Tile> {
        Some(match c {
            '#' => Tile::Open,
            '.' => Tile::Blocked,
            's' => Tile::Stairs,
            'e' => Tile::Elevator,
            'd' => Tile::Door,
            'n' => Tile::Narrow,
            _ => return None,
        })
    }

    pub(crate) fn glyph(self) -> char {
        match self {
            Tile::Open => '#',
            Tile::Blocked => '.',
            Tile::Stairs => 's',
            Tile::Elevator => 'e',
            Tile::Door => 'd',
            Tile::Narrow => 'n',
        }
    }

    pub(crate) fn walkable(self) -> bool {
        self != Tile::Blocked
    }
}

/// A fixed iBeacon: an anchor when devices localize themselves from what they hear.
#[derive(Clone, Debug, PartialEq)]
pub struct Beacon {
    /// The anchor id used in surveys and logs (for example a CSV column name).
    pub id: String,
    pub beacon: BeaconId,
    /// The grid cell the beacon is in, when it is on the grid.
    pub cell: Option<Cell>,
    /// Where the beacon is mounted, when known (`cell` or `pos`). The
    /// path-loss localizer, the radio map's prior, calibration and the
    /// simulator need it; survey-based localizers do not.
    pub mount: Option<Mount>,
    /// Calibrated RSSI at 1 m in dBm, overriding what the frame advertises.
    pub tx_power: Option<i8>,
    /// The beacon's address, when several transmitters share its
    /// UUID/major/minor: it then stands only for sightings from this MAC.
    pub mac: Option<Mac>,
    /// How loudly the beacon is heard over this floor: 10·log10 of its
    /// readings' power (mW) per second walked in the survey
    /// (`gangway survey import` writes it). On a building, which floor a
    /// device is on is judged by how each beacon it hears is heard from
    /// each floor; without it, equally from every floor listing it.
    pub heard_dbm: Option<f64>,
}

/// A fixed gateway: an anchor when gateways localize the tags they hear.
#[derive(Clone, Debug, PartialEq)]
pub struct Gateway {
    pub id: String,
    /// The grid cell the gateway is in, when it is on the grid.
    pub cell: Option<Cell>,
    /// Where the gateway is mounted, when known.
    pub mount: Option<Mount>,
}

/// Height above the floor at which a person carries a phone, metres: the
/// other end of an anchor's distance when its mounting height is known.
pub(crate) const DEVICE_HEIGHT_M: f64 = 1.2;

/// Where an anchor is mounted.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Mount {
    /// World metres: `pos` as given, or the centre of the given `cell`.
    pub at: [f64; 2],
    /// Mounting height above the floor, when the site file gives one.
    pub height_m: Option<f64>,
}

impl Mount {
    /// Metres from the anchor to a device at `here` (world metres): in 3-D to
    /// a phone held at [`DEVICE_HEIGHT_M`] when the mounting height is known,
    /// else along the floor plan.
    pub fn distance_m(&self, here: [f64; 2]) -> f64 {
        let flat = (here[0] - self.at[0]).hypot(here[1] - self.at[1]);
        match self.height_m {
            Some(h) => flat.hypot(h - DEVICE_HEIGHT_M),
            None => flat,
        }
    }
}

/// How survey labels such as `O02` name cells: a column letter (`A` is x = 0)
/// followed by a row number (`first_row` is y = 0).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabelScheme {
    pub first_row: u16,
}

/// Which way world y runs against the grid's rows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum YAxis {
    /// World y grows with the row index (row 0 is the smallest y): screen
    /// coordinates, and what sites without a frame mean.
    #[default]
    Down,
    /// World y shrinks as the row index grows (row 0 is the largest y): survey
    /// drawings and most pedestrian datasets.
    Up,
}

impl fmt::Display for YAxis {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            YAxis::Down => "down",
            YAxis::Up => "up",
        })
    }
}

/// A loaded, validated site.
#[derive(Clone, Debug)]
pub struct Site {
    pub name: String,
    /// Metres per cell side.
    pub cell_m: f64,
    frame: Frame,
    width: u16,
    height: u16,
    tiles: Vec<Tile>,
    /// Walkable cells in row-major order; a posterior over the site is indexed
    /// like this vector.
    open_cells: Vec<Cell>,
    /// For each grid cell, its index in `open_cells`, or `u32::MAX`.
    open_index: Vec<u32>,
    /// Grid indices of the blocked cells, row-major.
    blocked_indices: Vec<usize>,
    pub beacons: Vec<Beacon>,
    pub gateways: Vec<Gateway>,
    places: BTreeMap<String, Cell>,
    labels: Option<LabelScheme>,
    map_hash: String,
    shapes: Shapes,
    floorplan: Option<Floorplan>,
    /// Per grid cell, the ways out of it that route instructions count to
    /// find junctions (`plan::instructions`): a search around the cell that
    /// depends on the map alone, so it is done once per cell and site, the
    /// first time a route passes there, rather than for every route.
    ways_out: CellCache,
}

/// A number per grid cell worked out from the map on first use and kept
/// ([`Site::cached`]); `u16::MAX` until then. Atomics, so routes planned on
/// several threads fill it without a lock: two threads that race work out
/// the same number.
struct CellCache(Box<[std::sync::atomic::AtomicU16]>);

impl CellCache {
    const UNKNOWN: u16 = u16::MAX;

    fn new(cells: usize) -> CellCache {
        CellCache(
            (0..cells)
                .map(|_| std::sync::atomic::AtomicU16::new(Self::UNKNOWN))
                .collect(),
        )
    }
}

impl Clone for CellCache {
    fn clone(&self) -> CellCache {
        use std::sync::atomic::{AtomicU16, Ordering};
        CellCache(
            self.0
                .iter()
                .map(|v| AtomicU16::new(v.load(Ordering::Relaxed)))
                .collect(),
        )
    }
}

impl fmt::Debug for CellCache {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str("CellCache")
    }
}

/// What a site's `obstacles` and `walls` drew onto its grid.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Shapes {
    pub obstacles: usize,
    pub walls: usize,
    /// Cells the map (or the open floor) left walkable that they blocked.
    pub cells_blocked: usize,
}

/// Why a site file was refused.
#[derive(Debug, thiserror::Error)]
pub enum SiteError {
    #[error("{path}: cannot read the site file: {source}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path}: {source}")]
    Toml {
        path: PathBuf,
        source: toml::de::Error,
    },
    #[error("{path}: {}", problems.join("\n  "))]
    Invalid {
        path: PathBuf,
        problems: Vec<String>,
    },
}

impl SiteError {
    /// Each problem on its own, prefixed with the file as in the message.
    pub fn problems(&self) -> Vec<String> {
        match self {
            SiteError::Invalid { path, problems } => problems
                .iter()
                .map(|p| format!("{}: {p}", path.display()))
                .collect(),
            other => vec![other.to_string()],
        }
    }
}

/// The site file as written; see `config/sites/README.md` for every key.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct SiteFile {
    name: String,
    cell_m: f64,
    #[serde(default)]
    origin_m: Option<Spanned<[f64; 2]>>,
    #[serde(default)]
    y_axis: YAxis,
    #[serde(default)]
    map: Option<Spanned<String>>,
    #[serde(default)]
    width_m: Option<Spanned<f64>>,
    #[serde(default)]
    height_m: Option<Spanned<f64>>,
    #[serde(default)]
    obstacles: Vec<Spanned<ObstacleEntry>>,
    #[serde(default)]
    walls: Vec<Spanned<WallEntry>>,
    #[serde(default)]
    labels: Option<LabelScheme>,
    #[serde(default, rename = "beacon")]
    beacons: Vec<Spanned<BeaconEntry>>,
    #[serde(default, rename = "gateway")]
    gateways: Vec<Spanned<GatewayEntry>>,
    #[serde(default)]
    places: BTreeMap<String, Spanned<Cell>>,
    #[serde(default)]
    floorplan: Option<floorplan::FloorplanEntry>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BeaconEntry {
    id: String,
    uuid: Uuid,
    major: u16,
    minor: u16,
    cell: Option<Cell>,
    pos: Option<Spanned<[f64; 2]>>,
    height_m: Option<Spanned<f64>>,
    tx_power: Option<i8>,
    mac: Option<Spanned<String>>,
    heard_dbm: Option<f64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GatewayEntry {
    id: String,
    cell: Option<Cell>,
    pos: Option<Spanned<[f64; 2]>>,
    height_m: Option<Spanned<f64>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ObstacleEntry {
    polygon: Spanned<Vec<[f64; 2]>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WallEntry {
    line: Spanned<Vec<[f64; 2]>>,
    #[serde(default)]
    thickness_m: Option<Spanned<f64>>,
}

/// The most cells a site may have: 2000 × 2000, a 500 m square floor at
/// 0.25 m. Posteriors and likelihood tables are per cell, so a typo such as
/// `cell_m = 0.001` must be refused, not allocated.
const MAX_CELLS: usize = 4_000_000;
/// How far outside the grid an anchor placed by `pos` may be, in cells (or
/// [`ANCHOR_MARGIN_MIN_M`], whichever is more): on the outer wall, not in
/// the car park.
const ANCHOR_MARGIN_CELLS: f64 = 3.0;
const ANCHOR_MARGIN_MIN_M: f64 = 1.0;
/// The highest mounting height taken as metres; more is probably centimetres.
const MAX_HEIGHT_M: f64 = 50.0;

impl Site {
    /// Loads and validates a site file.
    pub fn load(path: &Path) -> Result<Site, SiteError> {
        let text = std::fs::read_to_string(path).map_err(|source| SiteError::Read {
            path: path.to_owned(),
            source,
        })?;
        Site::parse(&text, path)
    }

    /// A site of 1 m cells with only `map`'s rows (unit tests' small sites).
    #[cfg(test)]
    pub(crate) fn of_map(map: &str) -> Site {
        let text = format!("name = \"t\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n");
        Site::parse(&text, Path::new("t.toml")).expect("a valid test map")
    }

    /// Parses and validates site TOML; `path` is only used in messages.
    pub fn parse(text: &str, path: &Path) -> Result<Site, SiteError> {
        let file: SiteFile = toml::from_str(text).map_err(|source| SiteError::Toml {
            path: path.to_owned(),
            source,
        })?;
        let line_of = |span: std::ops::Range<usize>| line_at(text, span.start);
        let mut problems = Vec::new();

        let cell_m_ok = file.cell_m.is_finite() && file.cell_m > 0.0;
        if !cell_m_ok {
            problems.push(format!(
                "`cell_m` is {}; it must be a positive number of metres per cell",
                file.cell_m
            ));
        }
        let origin_m = match &file.origin_m {
            None => [0.0, 0.0],
            Some(origin) => {
                let [x, y] = *origin.get_ref();
                if !(x.is_finite() && y.is_finite()) {
                    problems.push(format!(
                        "line {}: `origin_m` is [{x}, {y}]; it must be two finite numbers of metres",
                        line_of(origin.span())
                    ));
                }
                [x, y]
            }
        };
        let frame = Frame {
            cell_m: file.cell_m,
            origin_m,
            y_axis: file.y_axis,
        };

        let (width, height, mut tiles) =
            match grid(&file, cell_m_ok, &line_of).and_then(|(w, h, tiles)| {
                let cells = usize::from(w) * usize::from(h);
                if cells > MAX_CELLS {
                    Err(format!(
                        "the grid is {w}×{h} = {cells} cells, more than the {MAX_CELLS} a site \
                         may have; use larger cells (`cell_m`)"
                    ))
                } else {
                    Ok((w, h, tiles))
                }
            }) {
                Ok(grid) => grid,
                Err(msg) => {
                    problems.push(msg);
                    (0, 0, Vec::new())
                }
            };

        // Obstacles and walls, once the grid and its frame are sound.
        let walkable_before = tiles.iter().filter(|t| t.walkable()).count();
        if !tiles.is_empty() && problems.is_empty() {
            let raster = Raster {
                frame: &frame,
                width,
                height,
            };
            for entry in &file.obstacles {
                let polygon = &entry.get_ref().polygon;
                let line = line_of(polygon.span());
                match raster.polygon(polygon.get_ref()) {
                    Ok(cells) => block(&mut tiles, width, cells),
                    Err(msg) => problems.push(format!("line {line}: obstacle `polygon`: {msg}")),
                }
            }
            for entry in &file.walls {
                let wall = entry.get_ref();
                let line = line_of(wall.line.span());
                let thickness_m = match &wall.thickness_m {
                    None => 0.0,
                    Some(t) if t.get_ref().is_finite() && *t.get_ref() >= 0.0 => *t.get_ref(),
                    Some(t) => {
                        problems.push(format!(
                            "line {}: wall `thickness_m` is {}; it must be zero or more metres",
                            line_of(t.span()),
                            t.get_ref()
                        ));
                        continue;
                    }
                };
                match raster.wall(wall.line.get_ref(), thickness_m) {
                    Ok(cells) => block(&mut tiles, width, cells),
                    Err(msg) => problems.push(format!("line {line}: wall `line`: {msg}")),
                }
            }
            if problems.is_empty() && !tiles.iter().any(|t| t.walkable()) {
                problems.push(
                    "no cell is walkable once obstacles and walls are drawn; check their \
                     coordinates against `origin_m` and `y_axis`"
                        .into(),
                );
            }
        }
        let shapes = Shapes {
            obstacles: file.obstacles.len(),
            walls: file.walls.len(),
            cells_blocked: walkable_before - tiles.iter().filter(|t| t.walkable()).count(),
        };

        let tile_at = |c: Cell| -> Option<Tile> {
            (c.x < width && c.y < height)
                .then(|| tiles[usize::from(c.y) * usize::from(width) + usize::from(c.x)])
        };
        // `or` is the other fix offered for a blocked cell.
        let check_cell =
            |what: &str, line: usize, cell: Cell, or: &str, problems: &mut Vec<String>| {
                if tiles.is_empty() {
                    return; // the grid itself is broken; already reported
                }
                match tile_at(cell) {
                    None => problems.push(format!(
                        "line {line}: {what} is at {cell}, off the {width}×{height} grid \
                     (x must be below {width}, y below {height})"
                    )),
                    Some(Tile::Blocked) => problems.push(format!(
                        "line {line}: {what} is at {cell}, a blocked cell ('.', an obstacle or a \
                     wall); move it to a walkable cell or open that cell in `map`{or}"
                    )),
                    Some(_) => {}
                }
            };
        // Where an anchor is: a walkable `cell`, or `pos` in metres anywhere
        // near the grid (walls, shelves and blocked cells included).
        let margin_cells = ANCHOR_MARGIN_CELLS.max(ANCHOR_MARGIN_MIN_M / file.cell_m);
        let place_anchor = |what: &str,
                            line: usize,
                            cell: Option<Cell>,
                            pos: Option<&Spanned<[f64; 2]>>,
                            height_m: Option<&Spanned<f64>>,
                            problems: &mut Vec<String>|
         -> (Option<Cell>, Option<Mount>) {
            let mount_height = height_m.and_then(|h| {
                let v = *h.get_ref();
                if (0.0..=MAX_HEIGHT_M).contains(&v) {
                    Some(v)
                } else {
                    problems.push(format!(
                        "line {}: {what}: `height_m` is {v}; it must be metres above the floor, \
                         0 to {MAX_HEIGHT_M}",
                        line_of(h.span())
                    ));
                    None
                }
            });
            match (cell, pos) {
                (Some(_), Some(pos)) => {
                    problems.push(format!(
                        "line {}: {what} has both `cell` and `pos`; give one",
                        line_of(pos.span())
                    ));
                    (None, None)
                }
                (Some(cell), None) => {
                    let or = ", or give its position in metres with `pos = [x, y]`, which may \
                              be on a blocked cell";
                    check_cell(what, line, cell, or, problems);
                    let at = frame.world_of_cell(cell);
                    (
                        Some(cell),
                        Some(Mount {
                            at,
                            height_m: mount_height,
                        }),
                    )
                }
                (None, Some(pos)) => {
                    if tiles.is_empty() || !cell_m_ok {
                        return (None, None); // no grid to place it on; already reported
                    }
                    let at = *pos.get_ref();
                    let [gx, gy] = frame.grid_of_world(at);
                    let near = |g: f64, cells: u16| {
                        (-margin_cells..=f64::from(cells) + margin_cells).contains(&g)
                    };
                    if !(near(gx, width) && near(gy, height)) {
                        let (lo, hi) = frame.extent_m(width, height);
                        problems.push(format!(
                            "line {}: {what} is at `pos` = [{}, {}], outside the site (x {} to \
                             {} m, y {} to {} m, give or take {:.1} m); check it against \
                             `origin_m` and `y_axis`",
                            line_of(pos.span()),
                            at[0],
                            at[1],
                            lo[0],
                            hi[0],
                            lo[1],
                            hi[1],
                            margin_cells * file.cell_m
                        ));
                        return (None, None);
                    }
                    let cell = frame.cell_of_world(at, width, height);
                    (
                        cell,
                        Some(Mount {
                            at,
                            height_m: mount_height,
                        }),
                    )
                }
                (None, None) => {
                    if let Some(h) = height_m {
                        problems.push(format!(
                            "line {}: {what} has `height_m` but no `cell` or `pos`",
                            line_of(h.span())
                        ));
                    }
                    (None, None)
                }
            }
        };

        let mut beacons = Vec::with_capacity(file.beacons.len());
        let mut seen_ids: HashMap<String, usize> = HashMap::new();
        let mut seen_beacons: HashMap<(BeaconId, Option<Mac>), usize> = HashMap::new();
        for entry in &file.beacons {
            let line = line_of(entry.span());
            let b = entry.get_ref();
            let beacon = BeaconId {
                uuid: b.uuid,
                major: b.major,
                minor: b.minor,
            };
            if let Some(first) = seen_ids.insert(b.id.clone(), line) {
                problems.push(format!(
                    "line {line}: anchor id `{}` is already used at line {first}; ids must be unique",
                    b.id
                ));
            }
            let mac = b
                .mac
                .as_ref()
                .and_then(|mac| match mac.get_ref().parse::<Mac>() {
                    Ok(parsed) => Some(parsed),
                    Err(e) => {
                        problems.push(format!(
                            "line {}: beacon `{}`: `mac`: {e}",
                            line_of(mac.span()),
                            b.id
                        ));
                        None
                    }
                });
            if let Some(first) = seen_beacons.insert((beacon, mac), line) {
                let what = match mac {
                    Some(mac) => format!("uuid/major/minor ({beacon}) and mac ({mac})"),
                    None => format!("uuid/major/minor ({beacon})"),
                };
                problems.push(format!(
                    "line {line}: beacon `{}` has the same {what} as the beacon at line {first}; \
                     each physical beacon needs its own major/minor, or its `mac`",
                    b.id
                ));
            }
            let (cell, mount) = place_anchor(
                &format!("beacon `{}`", b.id),
                line,
                b.cell,
                b.pos.as_ref(),
                b.height_m.as_ref(),
                &mut problems,
            );
            if let Some(dbm) = b.heard_dbm.filter(|d| !(-150.0..=30.0).contains(d)) {
                problems.push(format!(
                    "line {line}: beacon `{}` `heard_dbm` is {dbm}; it is how loudly the beacon \
                     is heard over the floor, in dBm between -150 and 30 (`gangway survey \
                     import` writes it; delete it to judge floors by the beacon lists alone)",
                    b.id
                ));
            }
            beacons.push(Beacon {
                id: b.id.clone(),
                beacon,
                cell,
                mount,
                tx_power: b.tx_power,
                mac,
                heard_dbm: b.heard_dbm,
            });
        }

        let mut gateways = Vec::with_capacity(file.gateways.len());
        for entry in &file.gateways {
            let line = line_of(entry.span());
            let g = entry.get_ref();
            if let Some(first) = seen_ids.insert(g.id.clone(), line) {
                problems.push(format!(
                    "line {line}: anchor id `{}` is already used at line {first}; ids must be unique",
                    g.id
                ));
            }
            let (cell, mount) = place_anchor(
                &format!("gateway `{}`", g.id),
                line,
                g.cell,
                g.pos.as_ref(),
                g.height_m.as_ref(),
                &mut problems,
            );
            gateways.push(Gateway {
                id: g.id.clone(),
                cell,
                mount,
            });
        }

        let floorplan = file.floorplan.as_ref().and_then(|entry| {
            let dir = path.parent().unwrap_or(Path::new(""));
            let frame = cell_m_ok.then_some(&frame)?;
            entry.validate(|m| frame.grid_of_world(m), dir, &line_of, &mut problems)
        });

        let mut places = BTreeMap::new();
        for (name, cell) in &file.places {
            let line = line_of(cell.span());
            if name.trim().is_empty() {
                problems.push(format!("line {line}: a place needs a non-empty name"));
            }
            check_cell(
                &format!("place `{name}`"),
                line,
                *cell.get_ref(),
                "",
                &mut problems,
            );
            places.insert(name.clone(), *cell.get_ref());
        }

        if !problems.is_empty() {
            return Err(SiteError::Invalid {
                path: path.to_owned(),
                problems,
            });
        }

        let mut open_cells = Vec::new();
        let mut open_index = vec![u32::MAX; tiles.len()];
        let mut blocked_indices = Vec::new();
        for (i, tile) in tiles.iter().enumerate() {
            if tile.walkable() {
                open_index[i] = open_cells.len() as u32;
                let (y, x) = (i / usize::from(width), i % usize::from(width));
                open_cells.push(Cell::new(x as u16, y as u16));
            } else {
                blocked_indices.push(i);
            }
        }
        let map_hash = hash_map(width, height, &tiles);
        let ways_out = CellCache::new(tiles.len());
        Ok(Site {
            name: file.name,
            cell_m: file.cell_m,
            frame,
            width,
            height,
            tiles,
            open_cells,
            open_index,
            blocked_indices,
            beacons,
            gateways,
            places,
            labels: file.labels,
            ways_out,
            map_hash,
            shapes,
            floorplan,
        })
    }

    /// The ways out of `cell` as route instructions count them, worked out
    /// by `compute` the first time it is asked for that cell (it must depend
    /// on the map and `cell` alone), then kept.
    pub(crate) fn cached_ways_out(&self, cell: Cell, compute: impl FnOnce() -> usize) -> usize {
        use std::sync::atomic::Ordering;
        let slot = &self.ways_out.0[self.grid_index(cell)];
        match slot.load(Ordering::Relaxed) {
            CellCache::UNKNOWN => {
                let ways = compute();
                // Beyond u16 (never on a real ring) it is simply not kept.
                if let Ok(kept) = u16::try_from(ways)
                    && kept != CellCache::UNKNOWN
                {
                    slot.store(kept, Ordering::Relaxed);
                }
                ways
            }
            ways => usize::from(ways),
        }
    }

    pub fn width(&self) -> u16 {
        self.width
    }

    pub fn height(&self) -> u16 {
        self.height
    }

    /// The tile at `cell`, or `None` off the grid.
    pub fn tile(&self, cell: Cell) -> Option<Tile> {
        self.contains(cell)
            .then(|| self.tiles[self.grid_index(cell)])
    }

    pub fn contains(&self, cell: Cell) -> bool {
        cell.x < self.width && cell.y < self.height
    }

    pub fn walkable(&self, cell: Cell) -> bool {
        self.tile(cell).is_some_and(Tile::walkable)
    }

    /// Row-major index of a cell on the full grid; `cell` must be on the grid.
    pub fn grid_index(&self, cell: Cell) -> usize {
        usize::from(cell.y) * usize::from(self.width) + usize::from(cell.x)
    }

    /// All walkable cells, row-major. Posteriors over the site use this order.
    pub fn open_cells(&self) -> &[Cell] {
        &self.open_cells
    }

    /// Grid indices ([`Site::grid_index`]) of the cells outside the
    /// public-access area, row-major: the cells no path frame may light.
    pub fn blocked_indices(&self) -> &[usize] {
        &self.blocked_indices
    }

    /// Index of a walkable cell in [`Site::open_cells`].
    pub fn open_index(&self, cell: Cell) -> Option<usize> {
        if !self.contains(cell) {
            return None;
        }
        match self.open_index[self.grid_index(cell)] {
            u32::MAX => None,
            i => Some(i as usize),
        }
    }

    /// World coordinates (metres) of the outer top-left corner of cell [0, 0].
    pub fn origin_m(&self) -> [f64; 2] {
        self.frame.origin_m
    }

    /// Which way world y runs against the rows.
    pub fn y_axis(&self) -> YAxis {
        self.frame.y_axis
    }

    /// World coordinates (metres) of a point given in grid units: `[gx, gy]`
    /// cells right of and below the outer top-left corner of cell [0, 0]
    /// (so `[x + 0.5, y + 0.5]` is the centre of cell `[x, y]`).
    /// [`Site::grid_of_world`] inverts it.
    pub fn world_of_grid(&self, grid: [f64; 2]) -> [f64; 2] {
        self.frame.world_of_grid(grid)
    }

    /// Grid units (see [`Site::world_of_grid`]) of a point in world metres.
    pub fn grid_of_world(&self, world: [f64; 2]) -> [f64; 2] {
        self.frame.grid_of_world(world)
    }

    /// Centre of a cell in world metres.
    pub fn world_of_cell(&self, cell: Cell) -> [f64; 2] {
        self.frame.world_of_cell(cell)
    }

    /// The cell containing a point in world metres; `None` outside the grid
    /// (or for a non-finite point). A point on the edge between two cells
    /// belongs to the one right of it and, in grid rows, below it.
    pub fn cell_of_world(&self, world: [f64; 2]) -> Option<Cell> {
        self.frame.cell_of_world(world, self.width, self.height)
    }

    /// The grid's extent in world metres: the smallest and largest x and y.
    pub fn extent_m(&self) -> ([f64; 2], [f64; 2]) {
        self.frame.extent_m(self.width, self.height)
    }

    /// The floor-plan image and how its pixels sit on the grid, when the
    /// site names one (`[floorplan]`).
    pub fn floorplan(&self) -> Option<&Floorplan> {
        self.floorplan.as_ref()
    }

    /// Why the floor-plan image cannot be shown, if the site names one and
    /// it cannot (missing, unreadable, too large, not what its name says).
    /// Not a load error: a gateway serves without its picture; `gangway
    /// check` and the editor report it.
    pub fn check_floorplan(&self) -> Option<String> {
        self.floorplan.as_ref()?.probe().err()
    }

    /// What the site's obstacles and walls drew onto the grid.
    pub fn shapes(&self) -> Shapes {
        self.shapes
    }

    /// [`Site::world_of_cell`] as a pair, for callers that destructure it.
    pub fn metres(&self, cell: Cell) -> (f64, f64) {
        let [x, y] = self.world_of_cell(cell);
        (x, y)
    }

    pub fn places(&self) -> &BTreeMap<String, Cell> {
        &self.places
    }

    pub fn place(&self, name: &str) -> Option<Cell> {
        self.places.get(name).copied()
    }

    /// The named place at or nearest to `cell` within `max_cells`, for messages
    /// such as "near help desk".
    pub fn nearest_place(&self, cell: Cell, max_cells: f64) -> Option<&str> {
        self.places
            .iter()
            .map(|(name, &c)| (name, c.distance(cell)))
            .filter(|&(_, d)| d <= max_cells)
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .map(|(name, _)| name.as_str())
    }

    /// Whether the site names cells with survey labels (`[labels]`).
    pub(crate) fn has_labels(&self) -> bool {
        self.labels.is_some()
    }

    /// Parses a survey label such as `O02` with the site's `[labels]` scheme.
    pub(crate) fn parse_label(&self, label: &str) -> Option<Cell> {
        let scheme = self.labels?;
        let label = label.trim();
        let split = label.find(|c: char| !c.is_ascii_alphabetic())?;
        let (letters, digits) = label.split_at(split);
        let mut x: u32 = 0;
        for c in letters.chars() {
            // Checked: a long run of letters in a CSV must not overflow.
            x = x
                .checked_mul(26)?
                .checked_add(c.to_ascii_uppercase() as u32 - 'A' as u32 + 1)?;
        }
        let x = x.checked_sub(1)?;
        let row: u16 = digits.parse().ok()?;
        let cell = Cell::new(u16::try_from(x).ok()?, row.checked_sub(scheme.first_row)?);
        self.contains(cell).then_some(cell)
    }

    /// The survey label of a cell (`O02`), when the site has a label scheme.
    pub fn label(&self, cell: Cell) -> Option<String> {
        let scheme = self.labels?;
        let mut letters = Vec::new();
        let mut x = u32::from(cell.x) + 1;
        while x > 0 {
            let rem = (x - 1) % 26;
            letters.push(char::from(b'A' + rem as u8));
            x = (x - 1) / 26;
        }
        let letters: String = letters.iter().rev().collect();
        Some(format!(
            "{letters}{:02}",
            u32::from(cell.y) + u32::from(scheme.first_row)
        ))
    }

    /// SHA-256 of the grid size and tiles: models trained on one access map refuse
    /// to serve another.
    pub fn map_hash(&self) -> &str {
        &self.map_hash
    }

    /// Whether `other` has the same grid: the same tiles in the same place
    /// in the world, so a cell (and an index into the open cells) means the
    /// same on both.
    pub fn same_grid(&self, other: &Site) -> bool {
        self.map_hash == other.map_hash && self.frame == other.frame
    }

    /// The map as text, one row per line, as in the site file.
    pub fn map_text(&self) -> String {
        let mut out = String::with_capacity(self.tiles.len() + usize::from(self.height));
        for row in self.tiles.chunks(usize::from(self.width)) {
            out.extend(row.iter().map(|t| t.glyph()));
            out.push('\n');
        }
        out
    }
}

/// The site's metric frame: the one place grid units and world metres meet.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Frame {
    cell_m: f64,
    origin_m: [f64; 2],
    y_axis: YAxis,
}

impl Frame {
    fn world_of_grid(&self, [gx, gy]: [f64; 2]) -> [f64; 2] {
        let [ox, oy] = self.origin_m;
        let y = match self.y_axis {
            YAxis::Down => oy + gy * self.cell_m,
            YAxis::Up => oy - gy * self.cell_m,
        };
        [ox + gx * self.cell_m, y]
    }

    fn grid_of_world(&self, [x, y]: [f64; 2]) -> [f64; 2] {
        let [ox, oy] = self.origin_m;
        let gy = match self.y_axis {
            YAxis::Down => (y - oy) / self.cell_m,
            YAxis::Up => (oy - y) / self.cell_m,
        };
        [(x - ox) / self.cell_m, gy]
    }

    fn world_of_cell(&self, cell: Cell) -> [f64; 2] {
        self.world_of_grid([f64::from(cell.x) + 0.5, f64::from(cell.y) + 0.5])
    }

    /// The cell of a `width` × `height` grid containing `world`.
    fn cell_of_world(&self, world: [f64; 2], width: u16, height: u16) -> Option<Cell> {
        let [gx, gy] = self.grid_of_world(world);
        let inside = |g: f64, cells: u16| (0.0..f64::from(cells)).contains(&g);
        (inside(gx, width) && inside(gy, height))
            .then(|| Cell::new(gx.floor() as u16, gy.floor() as u16))
    }

    /// The smallest and largest world x and y of a `width` × `height` grid.
    fn extent_m(&self, width: u16, height: u16) -> ([f64; 2], [f64; 2]) {
        let a = self.world_of_grid([0.0, 0.0]);
        let b = self.world_of_grid([f64::from(width), f64::from(height)]);
        (
            [a[0].min(b[0]), a[1].min(b[1])],
            [a[0].max(b[0]), a[1].max(b[1])],
        )
    }
}

/// The grid before obstacles and walls: the `map`, or an open floor of
/// `width_m` × `height_m` (partial cells at the right and bottom edges count
/// as whole cells). An empty grid when `cell_m` is broken (already reported).
fn grid(
    file: &SiteFile,
    cell_m_ok: bool,
    line_of: &dyn Fn(std::ops::Range<usize>) -> usize,
) -> Result<(u16, u16, Vec<Tile>), String> {
    let (width, height, tiles) = match (&file.map, &file.width_m, &file.height_m) {
        (Some(map), None, None) => parse_map(map.get_ref())
            .map_err(|msg| format!("line {}: `map`: {msg}", line_of(map.span())))?,
        (None, Some(w), Some(h)) => {
            let mut cells = [0u16; 2];
            for (n, (key, metres)) in cells.iter_mut().zip([("width_m", w), ("height_m", h)]) {
                let m = *metres.get_ref();
                let line = line_of(metres.span());
                if !(m.is_finite() && m > 0.0) {
                    return Err(format!(
                        "line {line}: `{key}` is {m}; it must be a positive number of metres"
                    ));
                }
                if !cell_m_ok {
                    return Ok((0, 0, Vec::new()));
                }
                // Less a hair, so 10 m of 0.1 m cells is 100 cells, not 101.
                let count = (m / file.cell_m - 1e-9).ceil().max(1.0);
                // `as` saturates, so an absurd count fails the conversion too.
                *n = u16::try_from(count as u64).map_err(|_| {
                    format!(
                        "line {line}: `{key}` is {count} cells of {} m, more than 65535; use \
                             larger cells",
                        file.cell_m
                    )
                })?;
            }
            let [width, height] = cells;
            check_size(width, height)?;
            let tiles = vec![Tile::Open; usize::from(width) * usize::from(height)];
            (width, height, tiles)
        }
        (Some(_), w, h) => {
            let line = line_of(w.as_ref().or(h.as_ref()).expect("one is given").span());
            return Err(format!(
                "line {line}: give either `map` or `width_m` and `height_m`, not both"
            ));
        }
        (None, _, _) => {
            return Err(
                "the site needs a `map`, or `width_m` and `height_m` for an open floor \
                 (with `obstacles` and `walls` drawn on it)"
                    .into(),
            );
        }
    };
    Ok((width, height, tiles))
}

fn check_size(width: u16, height: u16) -> Result<(), String> {
    let cells = usize::from(width) * usize::from(height);
    if cells > MAX_CELLS {
        return Err(format!(
            "the grid is {width}×{height} = {cells} cells, more than the {MAX_CELLS} a site may \
             have; use larger cells (`cell_m`)"
        ));
    }
    Ok(())
}

/// Marks `cells` blocked.
fn block(tiles: &mut [Tile], width: u16, cells: Vec<Cell>) {
    for c in cells {
        tiles[usize::from(c.y) * usize::from(width) + usize::from(c.x)] = Tile::Blocked;
    }
}

/// Draws obstacles and walls, given in world metres, onto the grid. Geometry
/// is done in grid units (cell `[x, y]` is the square `[x, x+1] × [y, y+1]`),
/// where the frame's flip and offset no longer matter. Two small routines
/// (even-odd point in polygon, Liang–Barsky clipping) rather than a geometry
/// crate and its dependencies.
struct Raster<'a> {
    frame: &'a Frame,
    width: u16,
    height: u16,
}

impl Raster<'_> {
    /// The cells whose centre is inside the polygon (even-odd rule: where an
    /// outline crosses itself, the overlap counts as outside).
    fn polygon(&self, polygon: &[[f64; 2]]) -> Result<Vec<Cell>, String> {
        if polygon.len() < 3 {
            return Err(format!(
                "has {} corners; a polygon needs at least 3",
                polygon.len()
            ));
        }
        let corners = self.to_grid(polygon)?;
        let (lo, hi) = self.bounds(&corners, 0.0)?;
        Ok(self
            .cells_in(lo, hi)
            .filter(|c| inside(&corners, [f64::from(c.x) + 0.5, f64::from(c.y) + 0.5]))
            .collect())
    }

    /// The cells a wall along the polyline `line` passes through. Each
    /// segment of a wall `thickness_m` thick is a rectangle that wide, its
    /// ends flush with the segment's points, and blocks every cell whose
    /// square it overlaps by a non-zero area. A thin wall (no thickness)
    /// blocks every cell its line runs through for a non-zero length: both
    /// cells when it runs exactly along the edge between them, neither when it
    /// only touches a corner, so a wall ending on a cell's edge leaves that
    /// cell (a doorway) open. A wall crossing the grid diagonally blocks a
    /// chain of cells that may touch only at corners; no move crosses it,
    /// because routes and the tracker never cut a blocked corner.
    fn wall(&self, line: &[[f64; 2]], thickness_m: f64) -> Result<Vec<Cell>, String> {
        if line.len() < 2 {
            return Err(format!(
                "has {} points; a wall needs at least 2",
                line.len()
            ));
        }
        let points = self.to_grid(line)?;
        if points.windows(2).all(|w| w[0] == w[1]) {
            return Err("its points are all the same; a wall needs two distinct points".into());
        }
        let half = thickness_m / 2.0 / self.frame.cell_m;
        self.bounds(&points, half)?;
        let mut cells = Vec::new();
        for w in points.windows(2) {
            let (a, b) = (w[0], w[1]);
            if a == b {
                continue;
            }
            let (lo, hi) = corners_of(&[a, b], half);
            cells.extend(self.cells_in(lo, hi).filter(|c| {
                let lo = [f64::from(c.x), f64::from(c.y)];
                let hi = [lo[0] + 1.0, lo[1] + 1.0];
                if half > 0.0 {
                    rectangle_overlaps(a, b, half, lo, hi)
                } else {
                    clipped_length(a, b, lo, hi) > OVERLAP_EPS
                }
            }));
        }
        Ok(cells)
    }

    /// `points` in grid units, refusing non-finite coordinates.
    fn to_grid(&self, points: &[[f64; 2]]) -> Result<Vec<[f64; 2]>, String> {
        points
            .iter()
            .enumerate()
            .map(|(i, &[x, y])| {
                if x.is_finite() && y.is_finite() {
                    Ok(self.frame.grid_of_world([x, y]))
                } else {
                    Err(format!(
                        "point {i} is [{x}, {y}], not two finite numbers of metres"
                    ))
                }
            })
            .collect()
    }

    /// The bounding box of `points` grown by `grow`, refused when it misses
    /// the grid entirely (the usual sign of a wrong origin or y axis).
    fn bounds(&self, points: &[[f64; 2]], grow: f64) -> Result<([f64; 2], [f64; 2]), String> {
        let (lo, hi) = corners_of(points, grow);
        let misses = hi[0] < 0.0
            || hi[1] < 0.0
            || lo[0] > f64::from(self.width)
            || lo[1] > f64::from(self.height);
        if misses {
            let (wlo, whi) = self.frame.extent_m(self.width, self.height);
            return Err(format!(
                "lies outside the grid (x {} to {} m, y {} to {} m); check its coordinates \
                 against `origin_m` and `y_axis`",
                wlo[0], whi[0], wlo[1], whi[1]
            ));
        }
        Ok((lo, hi))
    }

    /// The grid cells overlapping the box `lo`..`hi` (grid units), edges included.
    fn cells_in(&self, lo: [f64; 2], hi: [f64; 2]) -> impl Iterator<Item = Cell> {
        let range = |lo: f64, hi: f64, cells: u16| {
            // Cell x spans [x, x + 1]: it touches the box when x + 1 >= lo.
            let first = (lo - 1.0).ceil().clamp(0.0, f64::from(cells)) as u16;
            let last = (hi.floor() + 1.0).clamp(0.0, f64::from(cells)) as u16;
            first..last
        };
        let xs = range(lo[0], hi[0], self.width);
        range(lo[1], hi[1], self.height).flat_map(move |y| xs.clone().map(move |x| Cell::new(x, y)))
    }
}

/// The bounding box of `points`, grown by `grow` on every side.
fn corners_of(points: &[[f64; 2]], grow: f64) -> ([f64; 2], [f64; 2]) {
    let mut lo = [f64::INFINITY; 2];
    let mut hi = [f64::NEG_INFINITY; 2];
    for p in points {
        for k in 0..2 {
            lo[k] = lo[k].min(p[k] - grow);
            hi[k] = hi[k].max(p[k] + grow);
        }
    }
    (lo, hi)
}

/// Even-odd rule: a ray from `p` towards +x crosses the outline an odd
/// number of times when `p` is inside.
fn inside(corners: &[[f64; 2]], p: [f64; 2]) -> bool {
    let mut odd = false;
    let mut prev = corners[corners.len() - 1];
    for &c in corners {
        if (c[1] > p[1]) != (prev[1] > p[1]) {
            let x = c[0] + (p[1] - c[1]) * (prev[0] - c[0]) / (prev[1] - c[1]);
            if p[0] < x {
                odd = !odd;
            }
        }
        prev = c;
    }
    odd
}

/// Overlaps shorter than this (grid units) are touching, not crossing.
const OVERLAP_EPS: f64 = 1e-9;

/// Whether the rectangle `half` wide on each side of segment `a`–`b` (ends
/// flush with `a` and `b`) and the box `lo`..`hi` overlap by a non-zero area:
/// by the separating-axis test, their projections overlap by more than a
/// touch on the box's two axes and the rectangle's two.
fn rectangle_overlaps(a: [f64; 2], b: [f64; 2], half: f64, lo: [f64; 2], hi: [f64; 2]) -> bool {
    let length = (b[0] - a[0]).hypot(b[1] - a[1]);
    let along = [(b[0] - a[0]) / length, (b[1] - a[1]) / length];
    let across = [-along[1], along[0]];
    let dot = |p: [f64; 2], axis: [f64; 2]| p[0] * axis[0] + p[1] * axis[1];
    let box_corners = [lo, [hi[0], lo[1]], hi, [lo[0], hi[1]]];
    let rectangle_corners = [-half, half]
        .map(|side| [a, b].map(|p| [p[0] + side * across[0], p[1] + side * across[1]]));
    let rectangle_corners = rectangle_corners.as_flattened();
    let overlap = |(lo1, hi1): (f64, f64), (lo2, hi2): (f64, f64)| hi1.min(hi2) - lo1.max(lo2);
    let span = |points: &[[f64; 2]], axis: [f64; 2]| {
        points
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &p| {
                (lo.min(dot(p, axis)), hi.max(dot(p, axis)))
            })
    };
    [[1.0, 0.0], [0.0, 1.0], along, across]
        .into_iter()
        .all(|axis| overlap(span(&box_corners, axis), span(rectangle_corners, axis)) > OVERLAP_EPS)
}

/// Length of the part of segment `a`–`b` inside the closed box `lo`..`hi`
/// (Liang–Barsky); a segment lying on the box's edge is inside.
fn clipped_length(a: [f64; 2], b: [f64; 2], lo: [f64; 2], hi: [f64; 2]) -> f64 {
    let d = [b[0] - a[0], b[1] - a[1]];
    let (mut t0, mut t1) = (0.0f64, 1.0f64);
    for k in 0..2 {
        for (p, q) in [(-d[k], a[k] - lo[k]), (d[k], hi[k] - a[k])] {
            if p == 0.0 {
                if q < 0.0 {
                    return 0.0;
                }
            } else {
                let t = q / p;
                if p < 0.0 {
                    t0 = t0.max(t);
                } else {
                    t1 = t1.min(t);
                }
            }
        }
    }
    (t1 - t0).max(0.0) * d[0].hypot(d[1])
}

/// Parses the `map` string into (width, height, row-major tiles).
fn parse_map(map: &str) -> Result<(u16, u16, Vec<Tile>), String> {
    let rows: Vec<&str> = map
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect();
    let Some(first) = rows.first() else {
        return Err("the map is empty; write one line per row of cells".into());
    };
    let width = first.chars().count();
    let mut tiles = Vec::with_capacity(width * rows.len());
    for (y, row) in rows.iter().enumerate() {
        let len = row.chars().count();
        if len != width {
            return Err(format!(
                "row {y} has {len} cells but row 0 has {width}; every row needs the same width \
                 (pad with '.' for blocked cells)"
            ));
        }
        for (x, c) in row.chars().enumerate() {
            let tile = Tile::from_glyph(c).ok_or_else(|| {
                format!(
                    "row {y}, column {x}: unknown glyph {c:?}; use one of {:?}",
                    Tile::GLYPHS
                )
            })?;
            tiles.push(tile);
        }
    }
    let width = u16::try_from(width).map_err(|_| "the map is wider than 65535 cells")?;
    let height = u16::try_from(rows.len()).map_err(|_| "the map is taller than 65535 cells")?;
    check_size(width, height)?;
    if !tiles.iter().any(|t| t.walkable()) {
        return Err("no cell is walkable; mark open cells with '#'".into());
    }
    Ok((width, height, tiles))
}

fn hash_map(width: u16, height: u16, tiles: &[Tile]) -> String {
    let mut h = Sha256::new();
    h.update(width.to_le_bytes());
    h.update(height.to_le_bytes());
    h.update(tiles.iter().map(|t| t.glyph() as u8).collect::<Vec<u8>>());
    h.finalize().iter().map(|b| format!("{b:02x}")).collect()
}

/// 1-based line number of a byte offset.
fn line_at(text: &str, offset: usize) -> usize {
    text[..offset.min(text.len())]
        .bytes()
        .filter(|&b| b == b'\n')
        .count()
        + 1
}

#[cfg(test)]
mod tests {
    use super::*;

    const SMALL: &str = r#"
name = "test"
cell_m = 2.0
map = '''
##.
#s#
'''
[labels]
first_row = 1

[[beacon]]
id = "b1"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 1
cell = [0, 0]

[places]
door = [2, 1]
"#;

    fn parse(text: &str) -> Result<Site, SiteError> {
        Site::parse(text, Path::new("test.toml"))
    }

    #[test]
    fn parses_a_small_site() {
        let site = parse(SMALL).unwrap();
        assert_eq!((site.width(), site.height()), (3, 2));
        assert_eq!(site.open_cells().len(), 5);
        assert_eq!(site.tile(Cell::new(1, 1)), Some(Tile::Stairs));
        assert!(!site.walkable(Cell::new(2, 0)));
        assert_eq!(site.open_index(Cell::new(0, 1)), Some(2));
        assert_eq!(site.place("door"), Some(Cell::new(2, 1)));
        assert_eq!(site.metres(Cell::new(1, 0)), (3.0, 1.0));
        assert_eq!(site.map_text(), "##.\n#s#\n");
    }

    #[test]
    fn labels_round_trip() {
        let site = parse(SMALL).unwrap();
        assert_eq!(site.parse_label("B02"), Some(Cell::new(1, 1)));
        assert_eq!(site.label(Cell::new(1, 1)).as_deref(), Some("B02"));
        assert_eq!(site.parse_label("Z01"), None, "off the grid");
        assert_eq!(site.parse_label("B00"), None, "row before first_row");
        assert_eq!(site.parse_label("02"), None);
    }

    fn problems(text: &str) -> String {
        parse(text).unwrap_err().to_string()
    }

    #[test]
    fn a_beacon_s_loudness_over_the_floor_is_checked() {
        let base = SMALL.replace("[places]\ndoor = [2, 1]\n", "");
        let beacon = |heard: &str| {
            format!(
                "{base}[[beacon]]\nid = \"b2\"\nuuid = \"b9407f30-f5f8-466e-aff9-25556b57fe6d\"\n\
                 major = 1\nminor = 2\ncell = [0, 0]\nheard_dbm = {heard}\n"
            )
        };
        let site = parse(&beacon("-81.5")).unwrap();
        assert_eq!(site.beacons.last().unwrap().heard_dbm, Some(-81.5));
        let message = problems(&beacon("40.0"));
        assert!(
            message.contains("beacon `b2` `heard_dbm` is 40; it is how loudly"),
            "{message}"
        );
    }

    #[test]
    fn beacons_sharing_uuid_major_minor_are_told_apart_by_mac() {
        let twin = |id: &str, mac: &str| {
            format!(
                "[[beacon]]\nid = \"{id}\"\nuuid = \"b9407f30-f5f8-466e-aff9-25556b57fe6d\"\n\
                 major = 1\nminor = 1\ncell = [0, 0]\n{mac}"
            )
        };
        let base = SMALL.replace("[places]\ndoor = [2, 1]\n", "");
        let two = format!(
            "{base}{}{}",
            twin("b2", "mac = \"e0:78:a3:3d:b5:d6\"\n"),
            twin("b3", "mac = \"E0:78:A3:3D:B5:D7\"\n")
        );
        let site = parse(&two).unwrap();
        assert_eq!(site.beacons[0].mac, None);
        assert_eq!(
            site.beacons[1].mac.map(|m| m.to_string()).as_deref(),
            Some("E0:78:A3:3D:B5:D6")
        );

        let same_mac = format!(
            "{base}{}{}",
            twin("b2", "mac = \"E0:78:A3:3D:B5:D6\"\n"),
            twin("b3", "mac = \"E0:78:A3:3D:B5:D6\"\n")
        );
        let msg = problems(&same_mac);
        assert!(
            msg.contains("has the same uuid/major/minor (b9407f30-f5f8-466e-aff9-25556b57fe6d/1/1) and mac (E0:78:A3:3D:B5:D6)"),
            "{msg}"
        );
        let bad = format!("{base}{}", twin("b2", "mac = \"E0:78:A3\"\n"));
        let msg = problems(&bad);
        assert!(
            msg.contains("line 24: beacon `b2`: `mac`: `E0:78:A3` is not a MAC address"),
            "{msg}"
        );
    }

    #[test]
    fn names_each_problem() {
        let ragged = SMALL.replace("#s#\n", "#s\n");
        assert!(problems(&ragged).contains("row 1 has 2 cells but row 0 has 3"));

        let off_grid = SMALL.replace("door = [2, 1]", "door = [7, 1]");
        let msg = problems(&off_grid);
        assert!(
            msg.contains("line 19: place `door` is at [7, 1], off the 3×2 grid"),
            "{msg}"
        );

        let blocked = SMALL.replace("cell = [0, 0]", "cell = [2, 0]");
        assert!(problems(&blocked).contains("beacon `b1` is at [2, 0], a blocked cell"));

        let dup = format!(
            "{SMALL}\n[[beacon]]\nid = \"b1\"\nuuid = \"b9407f30-f5f8-466e-aff9-25556b57fe6d\"\nmajor = 1\nminor = 1\n"
        );
        let msg = problems(&dup);
        assert!(
            msg.contains("anchor id `b1` is already used at line 11"),
            "{msg}"
        );
        assert!(msg.contains("same uuid/major/minor"), "{msg}");

        let glyph = SMALL.replace("#s#", "#x#");
        assert!(problems(&glyph).contains("unknown glyph 'x'"));

        let toml_err = SMALL.replace("cell_m = 2.0", "cell_m = ");
        assert!(
            problems(&toml_err).contains("line 3"),
            "{}",
            problems(&toml_err)
        );

        let unknown_key = SMALL.replace("cell_m = 2.0", "cell_m = 2.0\ncolour = 1");
        assert!(problems(&unknown_key).contains("colour"));
    }

    #[test]
    fn the_default_frame_is_the_grid_in_metres() {
        let site = parse(SMALL).unwrap();
        assert_eq!((site.origin_m(), site.y_axis()), ([0.0, 0.0], YAxis::Down));
        assert_eq!(site.world_of_cell(Cell::new(1, 0)), [3.0, 1.0]);
        assert_eq!(site.metres(Cell::new(2, 1)), (5.0, 3.0));
        assert_eq!(site.cell_of_world([5.9, 3.9]), Some(Cell::new(2, 1)));
        assert_eq!(site.cell_of_world([6.0, 1.0]), None, "right of the grid");
        assert_eq!(site.cell_of_world([-0.1, 1.0]), None);
        assert_eq!(site.cell_of_world([f64::NAN, 1.0]), None);
        assert_eq!(site.extent_m(), ([0.0, 0.0], [6.0, 4.0]));
    }

    #[test]
    fn an_origin_and_y_up_place_the_grid_in_the_world() {
        let text = SMALL.replace(
            "cell_m = 2.0",
            "cell_m = 0.5\norigin_m = [10.0, 20.0]\ny_axis = \"up\"",
        );
        let site = parse(&text).unwrap();
        assert_eq!(site.y_axis(), YAxis::Up);
        // Row 0 is the top: the largest y, just under the origin's.
        assert_eq!(site.world_of_cell(Cell::new(0, 0)), [10.25, 19.75]);
        assert_eq!(site.world_of_cell(Cell::new(2, 1)), [11.25, 19.25]);
        assert_eq!(site.extent_m(), ([10.0, 19.0], [11.5, 20.0]));
        for &cell in site.open_cells() {
            assert_eq!(site.cell_of_world(site.world_of_cell(cell)), Some(cell));
        }
        assert_eq!(site.cell_of_world([10.1, 19.1]), Some(Cell::new(0, 1)));
        assert_eq!(site.cell_of_world([10.1, 20.1]), None, "above row 0");
        assert_eq!(site.cell_of_world([10.1, 18.9]), None, "below the last row");
        let [gx, gy] = site.grid_of_world([11.0, 19.5]);
        assert!((gx - 2.0).abs() < 1e-12 && (gy - 1.0).abs() < 1e-12);

        let bad = SMALL.replace("cell_m = 2.0", "cell_m = 2.0\norigin_m = [1.0, nan]");
        assert!(
            problems(&bad).contains("line 4: `origin_m` is [1, NaN]"),
            "{}",
            problems(&bad)
        );
        let axis = SMALL.replace("cell_m = 2.0", "cell_m = 2.0\ny_axis = \"north\"");
        assert!(problems(&axis).contains("y_axis"), "{}", problems(&axis));
    }

    /// A floor in metres: 10 × 6 cells of 0.5 m, y up, an obstacle, three
    /// walls and anchors on blocked cells and just off the grid.
    const METRIC: &str = r#"
name = "metric"
cell_m = 0.5
origin_m = [100.0, 50.0]
y_axis = "up"
width_m = 5.0
height_m = 3.0

[[obstacles]]
polygon = [[101.0, 49.0], [102.0, 49.0], [102.0, 48.0], [101.0, 48.0]]

[[walls]]
line = [[103.5, 50.0], [103.5, 48.5]]

[[walls]]
line = [[100.0, 47.25], [101.0, 47.25]]
thickness_m = 0.1

[[walls]]
line = [[104.0, 50.0], [105.0, 49.0]]

[[beacon]]
id = "shelf"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 1
pos = [101.5, 48.5]
height_m = 2.0

[[beacon]]
id = "corner"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 2
cell = [0, 0]

[[gateway]]
id = "porch"
pos = [99.8, 47.2]
"#;

    #[test]
    fn a_metric_site_rasterises_its_obstacles_and_walls() {
        let site = parse(METRIC).unwrap();
        assert_eq!((site.width(), site.height()), (10, 6));
        assert_eq!(site.extent_m(), ([100.0, 47.0], [105.0, 50.0]));
        let blocked: Vec<Cell> = (0..6)
            .flat_map(|y| (0..10).map(move |x| Cell::new(x, y)))
            .filter(|&c| !site.walkable(c))
            .collect();
        #[rustfmt::skip]
        let expected = [
            // The thin wall along the edge between columns 6 and 7 blocks
            // both for rows 0-2; its end on the edge of row 3 leaves row 3
            // open. The diagonal wall blocks (8, 0) and (9, 1), not (9, 0)
            // or (8, 1) whose corners it only touches.
            (6, 0), (7, 0), (8, 0),
            (6, 1), (7, 1), (9, 1),
            (2, 2), (3, 2), (6, 2), (7, 2),
            // The obstacle: the cells whose centres are inside the square.
            (2, 3), (3, 3),
            // The 0.1 m wall through row 5's centres, its end flush at x = 101 m.
            (0, 5), (1, 5),
        ]
        .map(|(x, y)| Cell::new(x, y));
        assert_eq!(blocked, expected);
        assert_eq!(
            site.shapes(),
            Shapes {
                obstacles: 1,
                walls: 3,
                cells_blocked: 14
            }
        );

        let shelf = &site.beacons[0];
        assert_eq!(shelf.cell, Some(Cell::new(3, 3)), "on the obstacle");
        let mount = shelf.mount.unwrap();
        assert_eq!(
            mount,
            Mount {
                at: [101.5, 48.5],
                height_m: Some(2.0)
            }
        );
        assert!((mount.distance_m([101.5, 48.5]) - (2.0 - DEVICE_HEIGHT_M)).abs() < 1e-12);
        assert!((mount.distance_m([104.5, 44.5]) - 5.0f64.hypot(0.8)).abs() < 1e-12);
        let corner = site.beacons[1].mount.unwrap();
        assert_eq!(corner.at, site.world_of_cell(Cell::new(0, 0)));
        assert_eq!(corner.at, [100.25, 49.75]);
        assert_eq!(
            corner.distance_m([100.25, 46.75]),
            3.0,
            "no height: on the plan"
        );
        let porch = &site.gateways[0];
        assert_eq!(porch.cell, None, "just off the grid");
        assert_eq!(porch.mount.unwrap().at, [99.8, 47.2]);
    }

    #[test]
    fn a_map_takes_walls_too() {
        // A thin wall on the edge between rows 0 and 1, across column 1.
        let text = SMALL.replace(
            "[labels]",
            "[[walls]]\nline = [[2.0, 2.0], [4.0, 2.0]]\n[labels]",
        );
        let site = parse(&text).unwrap();
        let open = [(0, 0), (0, 1), (2, 1)].map(|(x, y)| Cell::new(x, y));
        assert_eq!(site.open_cells(), open);
        assert_eq!(site.shapes().cells_blocked, 2);
        assert_ne!(site.map_hash(), parse(SMALL).unwrap().map_hash());
    }

    #[test]
    fn names_each_metric_problem() {
        let cases = [
            (
                METRIC.replace("pos = [101.5, 48.5]", "pos = [90.0, 47.0]"),
                "line 27: beacon `shelf` is at `pos` = [90, 47], outside the site (x 100 to 105 \
                 m, y 47 to 50 m, give or take 1.5 m)",
            ),
            (
                METRIC.replace("cell = [0, 0]", "cell = [0, 0]\npos = [101.0, 49.0]"),
                "beacon `corner` has both `cell` and `pos`",
            ),
            (
                METRIC.replace("height_m = 2.0", "height_m = 250.0"),
                "line 28: beacon `shelf`: `height_m` is 250",
            ),
            (
                METRIC.replace("cell = [0, 0]", "cell = [2, 2]"),
                "beacon `corner` is at [2, 2], a blocked cell ('.', an obstacle or a wall); move \
                 it to a walkable cell or open that cell in `map`, or give its position in \
                 metres with `pos = [x, y]`",
            ),
            (
                METRIC.replace(
                    "polygon = [[101.0, 49.0], [102.0, 49.0], [102.0, 48.0], [101.0, 48.0]]",
                    "polygon = [[101.0, 49.0], [102.0, 49.0]]",
                ),
                "line 10: obstacle `polygon`: has 2 corners; a polygon needs at least 3",
            ),
            (
                METRIC
                    .replace("[101.0, 49.0], [102.0, 49.0]", "[1.0, 49.0], [2.0, 49.0]")
                    .replace("[102.0, 48.0], [101.0, 48.0]", "[2.0, 48.0], [1.0, 48.0]"),
                "line 10: obstacle `polygon`: lies outside the grid (x 100 to 105 m, y 47 to 50 \
                 m); check its coordinates against `origin_m` and `y_axis`",
            ),
            (
                METRIC.replace("thickness_m = 0.1", "thickness_m = -1.0"),
                "line 17: wall `thickness_m` is -1",
            ),
            (
                METRIC.replace("[103.5, 48.5]]", "[103.5, nan]]"),
                "line 13: wall `line`: point 1 is [103.5, NaN], not two finite numbers",
            ),
            (
                METRIC.replace("height_m = 3.0", "height_m = 3.0\nmap = '''\n#\n'''"),
                "give either `map` or `width_m` and `height_m`, not both",
            ),
            (
                METRIC.replace("width_m = 5.0\n", ""),
                "the site needs a `map`, or `width_m` and `height_m`",
            ),
            (
                METRIC.replace("cell_m = 0.5", "cell_m = 0.00005"),
                "line 6: `width_m` is 100000 cells of 0.00005 m, more than 65535",
            ),
            (
                METRIC.replace("cell_m = 0.5", "cell_m = 0.001"),
                "the grid is 5000×3000 = 15000000 cells, more than the 4000000",
            ),
        ];
        for (text, expected) in cases {
            let msg = problems(&text);
            assert!(msg.contains(expected), "{msg}\nshould contain\n{expected}");
        }
    }

    #[test]
    fn map_hash_depends_on_the_map_only() {
        let a = parse(SMALL).unwrap();
        let renamed = parse(&SMALL.replace("name = \"test\"", "name = \"other\"")).unwrap();
        assert_eq!(a.map_hash(), renamed.map_hash());
        let reopened = parse(&SMALL.replace("##.", "###")).unwrap();
        assert_ne!(a.map_hash(), reopened.map_hash());
    }
}
