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
//! [`Site::world_of_grid`] is the one place that transform is written; every
//! metric position the gateway computes or publishes goes through it.
//!
//! Validation happens once, at load, so every later stage may assume a consistent
//! site: places and anchors sit on walkable cells, ids are unique, the grid is
//! rectangular. Errors name the file, the TOML line and what to change.

use std::collections::{BTreeMap, HashMap};
use std::fmt;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use toml::Spanned;
use uuid::Uuid;

use crate::sighting::BeaconId;

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
    pub const GLYPHS: &'static str = "#.sedn";

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

    pub fn glyph(self) -> char {
        match self {
            Tile::Open => '#',
            Tile::Blocked => '.',
            Tile::Stairs => 's',
            Tile::Elevator => 'e',
            Tile::Door => 'd',
            Tile::Narrow => 'n',
        }
    }

    pub fn walkable(self) -> bool {
        self != Tile::Blocked
    }
}

/// A fixed iBeacon: an anchor when devices localize themselves from what they hear.
#[derive(Clone, Debug, PartialEq)]
pub struct Beacon {
    /// The anchor id used in surveys and logs (for example a CSV column name).
    pub id: String,
    pub beacon: BeaconId,
    /// Where the beacon is mounted, when known. The path-loss localizer and the
    /// simulator need it; survey-based localizers do not.
    pub cell: Option<Cell>,
    /// Calibrated RSSI at 1 m in dBm, overriding what the frame advertises.
    pub tx_power: Option<i8>,
}

/// A fixed gateway: an anchor when gateways localize the tags they hear.
#[derive(Clone, Debug, PartialEq)]
pub struct Gateway {
    pub id: String,
    pub cell: Option<Cell>,
}

/// How survey labels such as `O02` name cells: a column letter (`A` is x = 0)
/// followed by a row number (`first_row` is y = 0).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LabelScheme {
    pub first_row: u16,
}

/// Which way world y runs against the grid's rows.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Deserialize)]
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
    /// World coordinates (metres) of the outer top-left corner of cell [0, 0].
    origin_m: [f64; 2],
    y_axis: YAxis,
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
    map: Spanned<String>,
    #[serde(default)]
    labels: Option<LabelScheme>,
    #[serde(default, rename = "beacon")]
    beacons: Vec<Spanned<BeaconEntry>>,
    #[serde(default, rename = "gateway")]
    gateways: Vec<Spanned<GatewayEntry>>,
    #[serde(default)]
    places: BTreeMap<String, Spanned<Cell>>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BeaconEntry {
    id: String,
    uuid: Uuid,
    major: u16,
    minor: u16,
    cell: Option<Cell>,
    tx_power: Option<i8>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct GatewayEntry {
    id: String,
    cell: Option<Cell>,
}

impl Site {
    /// Loads and validates a site file.
    pub fn load(path: &Path) -> Result<Site, SiteError> {
        let text = std::fs::read_to_string(path).map_err(|source| SiteError::Read {
            path: path.to_owned(),
            source,
        })?;
        Site::parse(&text, path)
    }

    /// Parses and validates site TOML; `path` is only used in messages.
    pub fn parse(text: &str, path: &Path) -> Result<Site, SiteError> {
        let file: SiteFile = toml::from_str(text).map_err(|source| SiteError::Toml {
            path: path.to_owned(),
            source,
        })?;
        let line_of = |span: std::ops::Range<usize>| line_at(text, span.start);
        let mut problems = Vec::new();

        if !(file.cell_m.is_finite() && file.cell_m > 0.0) {
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

        let map_line = line_of(file.map.span());
        let (width, height, tiles) = match parse_map(file.map.get_ref()) {
            Ok(grid) => grid,
            Err(msg) => {
                problems.push(format!("line {map_line}: `map`: {msg}"));
                (0, 0, Vec::new())
            }
        };
        let tile_at = |c: Cell| -> Option<Tile> {
            (c.x < width && c.y < height)
                .then(|| tiles[usize::from(c.y) * usize::from(width) + usize::from(c.x)])
        };
        let check_cell = |what: String, line: usize, cell: Cell, problems: &mut Vec<String>| {
            if tiles.is_empty() {
                return; // the map itself is broken; already reported
            }
            match tile_at(cell) {
                None => problems.push(format!(
                    "line {line}: {what} is at {cell}, off the {width}×{height} grid \
                     (x must be below {width}, y below {height})"
                )),
                Some(Tile::Blocked) => problems.push(format!(
                    "line {line}: {what} is at {cell}, a blocked cell ('.'); \
                     move it to a walkable cell or open that cell in `map`"
                )),
                Some(_) => {}
            }
        };

        let mut beacons = Vec::with_capacity(file.beacons.len());
        let mut seen_ids: HashMap<String, usize> = HashMap::new();
        let mut seen_beacons: HashMap<BeaconId, usize> = HashMap::new();
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
            if let Some(first) = seen_beacons.insert(beacon, line) {
                problems.push(format!(
                    "line {line}: beacon `{}` has the same uuid/major/minor ({beacon}) as the \
                     beacon at line {first}; each physical beacon needs its own major/minor",
                    b.id
                ));
            }
            if let Some(cell) = b.cell {
                check_cell(format!("beacon `{}`", b.id), line, cell, &mut problems);
            }
            beacons.push(Beacon {
                id: b.id.clone(),
                beacon,
                cell: b.cell,
                tx_power: b.tx_power,
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
            if let Some(cell) = g.cell {
                check_cell(format!("gateway `{}`", g.id), line, cell, &mut problems);
            }
            gateways.push(Gateway {
                id: g.id.clone(),
                cell: g.cell,
            });
        }

        let mut places = BTreeMap::new();
        for (name, cell) in &file.places {
            let line = line_of(cell.span());
            if name.trim().is_empty() {
                problems.push(format!("line {line}: a place needs a non-empty name"));
            }
            check_cell(
                format!("place `{name}`"),
                line,
                *cell.get_ref(),
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
        Ok(Site {
            name: file.name,
            cell_m: file.cell_m,
            origin_m,
            y_axis: file.y_axis,
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
            map_hash,
        })
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
        self.origin_m
    }

    /// Which way world y runs against the rows.
    pub fn y_axis(&self) -> YAxis {
        self.y_axis
    }

    /// World coordinates (metres) of a point given in grid units: `[gx, gy]`
    /// cells right of and below the outer top-left corner of cell [0, 0]
    /// (so `[x + 0.5, y + 0.5]` is the centre of cell `[x, y]`). The only
    /// place the site's frame is applied; [`Site::grid_of_world`] inverts it.
    pub fn world_of_grid(&self, [gx, gy]: [f64; 2]) -> [f64; 2] {
        let [ox, oy] = self.origin_m;
        let y = match self.y_axis {
            YAxis::Down => oy + gy * self.cell_m,
            YAxis::Up => oy - gy * self.cell_m,
        };
        [ox + gx * self.cell_m, y]
    }

    /// Grid units (see [`Site::world_of_grid`]) of a point in world metres.
    pub fn grid_of_world(&self, [x, y]: [f64; 2]) -> [f64; 2] {
        let [ox, oy] = self.origin_m;
        let gy = match self.y_axis {
            YAxis::Down => (y - oy) / self.cell_m,
            YAxis::Up => (oy - y) / self.cell_m,
        };
        [(x - ox) / self.cell_m, gy]
    }

    /// Centre of a cell in world metres.
    pub fn world_of_cell(&self, cell: Cell) -> [f64; 2] {
        self.world_of_grid([f64::from(cell.x) + 0.5, f64::from(cell.y) + 0.5])
    }

    /// The cell containing a point in world metres; `None` outside the grid
    /// (or for a non-finite point). A point on the edge between two cells
    /// belongs to the one right of it and, in grid rows, below it.
    pub fn cell_of_world(&self, world: [f64; 2]) -> Option<Cell> {
        let [gx, gy] = self.grid_of_world(world);
        let inside = |g: f64, cells: u16| (0.0..f64::from(cells)).contains(&g);
        (inside(gx, self.width) && inside(gy, self.height))
            .then(|| Cell::new(gx.floor() as u16, gy.floor() as u16))
    }

    /// The grid's extent in world metres: the smallest and largest x and y.
    pub fn extent_m(&self) -> ([f64; 2], [f64; 2]) {
        let a = self.world_of_grid([0.0, 0.0]);
        let b = self.world_of_grid([f64::from(self.width), f64::from(self.height)]);
        ([a[0].min(b[0]), a[1].min(b[1])], [a[0].max(b[0]), a[1].max(b[1])])
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

    /// The beacon with this identity, as an index into [`Site::beacons`].
    pub fn beacon_index(&self, id: &BeaconId) -> Option<usize> {
        self.beacons.iter().position(|b| b.beacon == *id)
    }

    /// Whether the site names cells with survey labels (`[labels]`).
    pub fn has_labels(&self) -> bool {
        self.labels.is_some()
    }

    /// Parses a survey label such as `O02` with the site's `[labels]` scheme.
    pub fn parse_label(&self, label: &str) -> Option<Cell> {
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

    #[test]
    fn map_hash_depends_on_the_map_only() {
        let a = parse(SMALL).unwrap();
        let renamed = parse(&SMALL.replace("name = \"test\"", "name = \"other\"")).unwrap();
        assert_eq!(a.map_hash(), renamed.map_hash());
        let reopened = parse(&SMALL.replace("##.", "###")).unwrap();
        assert_ne!(a.map_hash(), reopened.map_hash());
    }
}
