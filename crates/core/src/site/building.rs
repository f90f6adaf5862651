//! A building: its floors, each a one-floor [`Site`] with its own grid, frame,
//! plan image, beacons and places, and the connectors between them (stairs,
//! lifts, escalators, ramps).
//!
//! A building file lists its floors by name and level and points at each
//! floor's site file; the floors are not inlined so that every one-floor tool
//! (the editor, `check`, the radio map, calibration) keeps working on one
//! floor at a time, and a floor's errors keep naming its own file and line.
//! A one-floor site file is a building of that one floor (named after the
//! site, level 0), so every site file people already have loads unchanged.
//!
//! ```toml
//! name = "mall"
//!
//! [[floors]]
//! name = "B1"
//! level = -1
//! site = "B1/site.toml"        # relative to this file
//!
//! [[connectors]]
//! id = "lift east"
//! kind = "lift"                # stairs | lift | escalator | ramp
//! s_per_level = 12.0           # optional: the kind's default
//! stops = [{ floor = "B1", cell = [40, 12] }, { floor = "F1", cell = [41, 12] }]
//! ```
//!
//! Which walkers may use a connector is the planner's rule (a wheelchair only
//! where the connector is step-free); the site only says what it is.

use std::collections::{BTreeSet, HashMap};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use toml::Spanned;
use toml_edit::{Array, DocumentMut, Item, Value};

use super::{Cell, Site, SiteError, line_at};

/// The most floors a building may have: per-device state and route searches
/// grow with it, so a file listing thousands is a mistake, not a building.
const MAX_FLOORS: usize = 128;
/// The most connectors a building may have, for the same reason.
const MAX_CONNECTORS: usize = 4096;

/// What joins two or more floors.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ConnectorKind {
    Stairs,
    Lift,
    Escalator,
    Ramp,
}

impl ConnectorKind {
    /// Whether someone who cannot take a step can use it.
    pub fn step_free(self) -> bool {
        matches!(self, ConnectorKind::Lift | ConnectorKind::Ramp)
    }

    /// Seconds per level when the file gives none: a storey of about 4 m
    /// climbed on stairs at 0.3 m/s vertical, ridden on an escalator of
    /// about 12 m at 0.5 m/s, walked up a 1:12 ramp of about 50 m, or in a
    /// lift (the wait is [`Connector::wait_s`]).
    pub fn default_s_per_level(self) -> f64 {
        match self {
            ConnectorKind::Stairs => 15.0,
            ConnectorKind::Lift => 5.0,
            ConnectorKind::Escalator => 25.0,
            ConnectorKind::Ramp => 45.0,
        }
    }

    /// Seconds waited before moving when the file gives none: a lift's
    /// typical wait in a busy building; nothing for the others.
    pub fn default_wait_s(self) -> f64 {
        match self {
            ConnectorKind::Lift => 30.0,
            _ => 0.0,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            ConnectorKind::Stairs => "stairs",
            ConnectorKind::Lift => "lift",
            ConnectorKind::Escalator => "escalator",
            ConnectorKind::Ramp => "ramp",
        }
    }
}

/// One floor: its name (as people say it: "B1", "Ground"), its level (0 is
/// the entrance floor, negative below it) and its site.
#[derive(Clone, Debug)]
pub struct Floor {
    pub name: String,
    pub level: i32,
    pub site: Arc<Site>,
    /// The site file it was loaded from (a building file's floor resolved
    /// against its directory); none for a site given in memory.
    pub file: Option<PathBuf>,
}

/// Where a connector can be entered or left on one floor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Stop {
    /// Index into [`Building::floors`].
    pub floor: usize,
    /// A walkable cell of that floor.
    pub cell: Cell,
}

/// Stairs, a lift, an escalator or a ramp, with a stop on every floor it
/// joins (at least two).
#[derive(Clone, Debug)]
pub struct Connector {
    pub id: String,
    pub kind: ConnectorKind,
    /// Seconds to move one level.
    pub s_per_level: f64,
    /// Seconds before moving (a lift's wait).
    pub wait_s: f64,
    /// Ordered by level.
    pub stops: Vec<Stop>,
}

impl Connector {
    /// Seconds from `from`'s floor to `to`'s, two of its stops.
    pub fn seconds(&self, building: &Building, from: Stop, to: Stop) -> f64 {
        let levels = building.floors[from.floor]
            .level
            .abs_diff(building.floors[to.floor].level);
        self.wait_s + self.s_per_level * f64::from(levels)
    }
}

/// A loaded, validated building.
#[derive(Clone, Debug)]
pub struct Building {
    pub name: String,
    /// Ordered by level, lowest first.
    floors: Vec<Floor>,
    connectors: Vec<Connector>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct BuildingFile {
    name: String,
    floors: Vec<Spanned<FloorDoc>>,
    #[serde(default)]
    connectors: Vec<Spanned<ConnectorDoc>>,
}

/// A building file as data, for the tools that write one (`gangway site
/// import`, the editor); [`BuildingDoc::to_toml`] writes it,
/// [`Building::parse`] checks it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuildingDoc {
    pub name: String,
    pub floors: Vec<FloorDoc>,
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub connectors: Vec<ConnectorDoc>,
}

/// One `[[floors]]` entry.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FloorDoc {
    pub name: String,
    pub level: i32,
    /// The floor's site file, relative to the building file.
    pub site: PathBuf,
}

/// One `[[connectors]]` entry.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ConnectorDoc {
    pub id: String,
    pub kind: ConnectorKind,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub s_per_level: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub wait_s: Option<f64>,
    pub stops: Vec<StopDoc>,
}

/// One stop of a connector: a floor by name and a cell of its grid.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StopDoc {
    pub floor: String,
    pub cell: Cell,
}

impl BuildingDoc {
    /// Reads a building file as data, unchecked: the editor opens a file
    /// whose connectors have problems, to fix them.
    pub fn parse(text: &str) -> Result<BuildingDoc, toml::de::Error> {
        toml::from_str(text)
    }

    /// The building file's TOML, each connector's `stops` on one line as in
    /// the hand-written example above.
    pub fn to_toml(&self) -> String {
        written_with_inline_stops(self)
    }
}

/// `path` for the floor called `floor`: `{floor}` in it becomes the floor's
/// name, which is how a config names each floor's file of a building
/// (`surveys/{floor}.csv`); `None` when the path names no floor.
pub fn floor_path(path: &Path, floor: &str) -> Option<PathBuf> {
    let text = path.to_string_lossy();
    text.contains("{floor}")
        .then(|| text.replace("{floor}", floor).into())
}

/// The file the gateway writes for floor `floor` (a survey, a
/// recalibration): `{floor}` in `file` becomes its name; on a building of
/// `several` floors, a path without it gets `-NAME` before its extension
/// (`survey.csv` → `survey-B1.csv`), so no two floors ever write one file.
pub fn floor_file(file: &Path, floor: &str, several: bool) -> PathBuf {
    if let Some(named) = floor_path(file, floor) {
        return named;
    }
    if !several {
        return file.to_owned();
    }
    let stem = file.file_stem().unwrap_or_default().to_string_lossy();
    let name = match file.extension() {
        Some(ext) => format!("{stem}-{floor}.{}", ext.to_string_lossy()),
        None => format!("{stem}-{floor}"),
    };
    file.with_file_name(name)
}

/// `text`, a building file, with its `[[connectors]]` replaced by
/// `connectors` (after everything else); every other line is kept as
/// written, comments included, so the editor placing a lift leaves the
/// floors as the user wrote them.
pub fn replace_connectors(
    text: &str,
    connectors: &[ConnectorDoc],
) -> Result<String, toml_edit::TomlError> {
    let mut doc: DocumentMut = text.parse()?;
    doc.remove("connectors");
    let mut out = doc.to_string();
    if !connectors.is_empty() {
        #[derive(Serialize)]
        struct Connectors<'a> {
            connectors: &'a [ConnectorDoc],
        }
        if !out.is_empty() && !out.ends_with("\n\n") {
            out.push_str(if out.ends_with('\n') { "\n" } else { "\n\n" });
        }
        out.push_str(&written_with_inline_stops(&Connectors { connectors }));
    }
    Ok(out)
}

/// `data` as TOML, each `[[connectors]]`' `stops` an inline array.
fn written_with_inline_stops(data: &impl Serialize) -> String {
    let text = toml::to_string(data).expect("a building document is plain TOML data");
    let mut doc: DocumentMut = text.parse().expect("the TOML the toml crate wrote parses");
    if let Some(connectors) = doc
        .get_mut("connectors")
        .and_then(Item::as_array_of_tables_mut)
    {
        for connector in connectors.iter_mut() {
            if let Some(Item::ArrayOfTables(stops)) = connector.get_mut("stops") {
                let inline: Array = std::mem::take(stops)
                    .into_iter()
                    .map(|stop| Value::InlineTable(stop.into_inline_table()))
                    .collect();
                connector.insert("stops", Item::Value(Value::Array(inline)));
            }
        }
    }
    doc.to_string()
}

impl Building {
    /// Loads a building file, or a one-floor site file as a building of one
    /// floor.
    pub fn load(path: &Path) -> Result<Building, SiteError> {
        let text = std::fs::read_to_string(path).map_err(|source| SiteError::Read {
            path: path.to_owned(),
            source,
        })?;
        Building::parse(&text, path, Site::load)
    }

    /// A building of one floor: `site`, named after it, at level 0.
    pub fn of_site(site: Arc<Site>) -> Building {
        Building {
            name: site.name.clone(),
            floors: vec![Floor {
                name: site.name.clone(),
                level: 0,
                site,
                file: None,
            }],
            connectors: Vec::new(),
        }
    }

    /// Whether `text` is a building file (it lists `floors`) rather than a
    /// one-floor site file.
    pub fn is_building_file(text: &str) -> bool {
        text.parse::<toml::Table>()
            .is_ok_and(|table| table.contains_key("floors"))
    }

    /// Parses and validates `text`; `path` names the file in messages and
    /// floors' site paths are relative to its directory. `load_floor` reads
    /// one floor's site file (tests give sites from memory).
    pub fn parse(
        text: &str,
        path: &Path,
        load_floor: impl Fn(&Path) -> Result<Site, SiteError>,
    ) -> Result<Building, SiteError> {
        if !Building::is_building_file(text) {
            let mut building = Building::of_site(Arc::new(Site::parse(text, path)?));
            building.floors[0].file = Some(path.to_owned());
            return Ok(building);
        }
        let file: BuildingFile = toml::from_str(text).map_err(|source| SiteError::Toml {
            path: path.to_owned(),
            source,
        })?;
        let invalid = |problems: Vec<String>| SiteError::Invalid {
            path: path.to_owned(),
            problems,
        };
        let line_of = |span: std::ops::Range<usize>| line_at(text, span.start);
        let mut problems = Vec::new();
        if file.name.trim().is_empty() {
            problems.push("`name` is empty; give the building a name".to_owned());
        }
        if file.floors.is_empty() {
            problems.push("`floors` is empty; list at least one `[[floors]]`".to_owned());
        }
        if file.floors.len() > MAX_FLOORS {
            problems.push(format!(
                "{} floors, more than the {MAX_FLOORS} a building may have",
                file.floors.len()
            ));
        }
        if file.connectors.len() > MAX_CONNECTORS {
            problems.push(format!(
                "{} connectors, more than the {MAX_CONNECTORS} a building may have",
                file.connectors.len()
            ));
        }
        if !problems.is_empty() {
            return Err(invalid(problems));
        }

        let dir = path.parent().unwrap_or(Path::new("."));
        let mut names = HashMap::new();
        let mut levels = HashMap::new();
        let mut floors = Vec::new();
        for entry in &file.floors {
            let line = line_of(entry.span());
            let floor = entry.get_ref();
            if floor.name.trim().is_empty() {
                problems.push(format!("line {line}: a floor's `name` is empty"));
            } else if let Some(first) = names.insert(floor.name.clone(), line) {
                problems.push(format!(
                    "line {line}: floor `{}` is also on line {first}; floor names must differ",
                    floor.name
                ));
            }
            if let Some(first) = levels.insert(floor.level, line) {
                problems.push(format!(
                    "line {line}: floor `{}` has level {}, as has the floor on line {first}; \
                     each floor needs its own level",
                    floor.name, floor.level
                ));
            }
            let file = dir.join(&floor.site);
            match load_floor(&file) {
                Ok(site) => floors.push(Floor {
                    name: floor.name.clone(),
                    level: floor.level,
                    site: Arc::new(site),
                    file: Some(file),
                }),
                Err(e) => problems.push(format!(
                    "line {line}: floor `{}`: {}",
                    floor.name,
                    e.problems().join("; ")
                )),
            }
        }
        if !problems.is_empty() {
            return Err(invalid(problems));
        }
        floors.sort_by_key(|f| f.level);
        let index: HashMap<&str, usize> = floors
            .iter()
            .enumerate()
            .map(|(i, f)| (f.name.as_str(), i))
            .collect();

        let mut ids = HashMap::new();
        let mut connectors = Vec::new();
        for entry in &file.connectors {
            let line = line_of(entry.span());
            let c = entry.get_ref();
            if c.id.trim().is_empty() {
                problems.push(format!(
                    "line {line}: a connector's `id` is empty; name it (\"lift east\")"
                ));
            } else if let Some(first) = ids.insert(c.id.clone(), line) {
                problems.push(format!(
                    "line {line}: connector `{}` is also on line {first}; ids must differ",
                    c.id
                ));
            }
            let seconds = |key: &str, value: Option<f64>, default: f64, problems: &mut Vec<_>| {
                let v = value.unwrap_or(default);
                if !(v.is_finite() && v >= 0.0) {
                    problems.push(format!(
                        "line {line}: connector `{}` `{key}` is {v}; it must be zero or more seconds",
                        c.id
                    ));
                }
                v
            };
            let s_per_level = seconds(
                "s_per_level",
                c.s_per_level,
                c.kind.default_s_per_level(),
                &mut problems,
            );
            let wait_s = seconds("wait_s", c.wait_s, c.kind.default_wait_s(), &mut problems);
            let mut stops = Vec::new();
            let mut joined = BTreeSet::new();
            for stop in &c.stops {
                let Some(&floor) = index.get(stop.floor.as_str()) else {
                    problems.push(format!(
                        "line {line}: connector `{}` stops on floor `{}`, which is not in \
                         `floors` ({})",
                        c.id,
                        stop.floor,
                        floors
                            .iter()
                            .map(|f| f.name.as_str())
                            .collect::<Vec<_>>()
                            .join(", ")
                    ));
                    continue;
                };
                if !joined.insert(floor) {
                    problems.push(format!(
                        "line {line}: connector `{}` stops twice on floor `{}`; give one stop \
                         per floor",
                        c.id, stop.floor
                    ));
                }
                let site = &floors[floor].site;
                if !site.walkable(stop.cell) {
                    problems.push(format!(
                        "line {line}: connector `{}` stop on floor `{}` at {} is {}; put it on a \
                         walkable cell of that floor's grid ({}×{})",
                        c.id,
                        stop.floor,
                        stop.cell,
                        if site.contains(stop.cell) {
                            "a blocked cell"
                        } else {
                            "off the grid"
                        },
                        site.width(),
                        site.height()
                    ));
                }
                stops.push(Stop {
                    floor,
                    cell: stop.cell,
                });
            }
            if c.stops.len() < 2 {
                problems.push(format!(
                    "line {line}: connector `{}` has {} stop(s); it must join at least two floors",
                    c.id,
                    c.stops.len()
                ));
            }
            stops.sort_by_key(|s| s.floor);
            connectors.push(Connector {
                id: c.id.clone(),
                kind: c.kind,
                s_per_level,
                wait_s,
                stops,
            });
        }
        if !problems.is_empty() {
            return Err(invalid(problems));
        }
        Ok(Building {
            name: file.name,
            floors,
            connectors,
        })
    }

    /// The floors, lowest level first.
    pub fn floors(&self) -> &[Floor] {
        &self.floors
    }

    /// The index of the floor called `name`.
    pub fn floor_named(&self, name: &str) -> Option<usize> {
        self.floors.iter().position(|f| f.name == name)
    }

    pub fn connectors(&self) -> &[Connector] {
        &self.connectors
    }

    /// What models and stats identify the building's maps by: a one-floor
    /// site's own [`Site::map_hash`]; for several floors, SHA-256 of each
    /// floor's name and map hash in order.
    pub fn map_hash(&self) -> String {
        if let [floor] = &self.floors[..] {
            return floor.site.map_hash().to_owned();
        }
        use sha2::Digest;
        let mut hash = sha2::Sha256::new();
        for floor in &self.floors {
            hash.update(format!("{}:{}\n", floor.name, floor.site.map_hash()));
        }
        hash.finalize().iter().map(|b| format!("{b:02x}")).collect()
    }

    /// Whether it has more than one floor.
    pub fn is_multi_floor(&self) -> bool {
        self.floors.len() > 1
    }

    /// The floors one can move between through the connectors `usable`
    /// accepts, as groups of floor indices (each lowest first, the groups by
    /// their lowest floor): one group when every floor reaches every other.
    pub fn floor_groups(&self, usable: impl Fn(&Connector) -> bool) -> Vec<Vec<usize>> {
        let mut group: Vec<usize> = (0..self.floors.len()).collect();
        fn root(group: &mut [usize], mut f: usize) -> usize {
            while group[f] != f {
                group[f] = group[group[f]];
                f = group[f];
            }
            f
        }
        for connector in self.connectors.iter().filter(|c| usable(c)) {
            for pair in connector.stops.windows(2) {
                let (a, b) = (
                    root(&mut group, pair[0].floor),
                    root(&mut group, pair[1].floor),
                );
                group[a.max(b)] = a.min(b);
            }
        }
        let mut groups: Vec<Vec<usize>> = Vec::new();
        let mut of_root = HashMap::new();
        for f in 0..self.floors.len() {
            let r = root(&mut group, f);
            let at = *of_root.entry(r).or_insert_with(|| {
                groups.push(Vec::new());
                groups.len() - 1
            });
            groups[at].push(f);
        }
        groups
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_floor_of_a_building_gets_a_file_of_its_own_to_write() {
        let file = |path: &str, several| floor_file(Path::new(path), "B1", several);
        assert_eq!(file("/s/survey.csv", false), Path::new("/s/survey.csv"));
        assert_eq!(file("/s/survey.csv", true), Path::new("/s/survey-B1.csv"));
        assert_eq!(file("/s/survey", true), Path::new("/s/survey-B1"));
        assert_eq!(file("/s/{floor}/fp.csv", true), Path::new("/s/B1/fp.csv"));
        // A one-floor site names its floor where the path asks for it.
        assert_eq!(file("/s/fp-{floor}.csv", false), Path::new("/s/fp-B1.csv"));
    }

    fn floor_site(name: &str, map: &str) -> String {
        format!("name = \"{name}\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n")
    }

    /// Floor sites from memory: `B1.toml` and `F1.toml` (3×3 open), `F2.toml`
    /// (centre blocked).
    fn load_floor(path: &Path) -> Result<Site, SiteError> {
        let text = match path.file_name().and_then(|n| n.to_str()) {
            Some("B1.toml") => floor_site("b1", "###\n###\n###"),
            Some("F1.toml") => floor_site("f1", "###\n###\n###"),
            Some("F2.toml") => floor_site("f2", "###\n#.#\n###"),
            _ => {
                return Err(SiteError::Read {
                    path: path.to_owned(),
                    source: std::io::Error::from(std::io::ErrorKind::NotFound),
                });
            }
        };
        Site::parse(&text, path)
    }

    fn parse(text: &str) -> Result<Building, SiteError> {
        Building::parse(text, Path::new("dir/b.toml"), load_floor)
    }

    const FLOORS: &str = r#"
name = "test"
[[floors]]
name = "F1"
level = 0
site = "F1.toml"
[[floors]]
name = "B1"
level = -1
site = "B1.toml"
[[floors]]
name = "F2"
level = 1
site = "F2.toml"
"#;

    #[test]
    fn floors_are_ordered_by_level_and_connectors_join_them() {
        let text = format!(
            "{FLOORS}[[connectors]]\nid = \"lift\"\nkind = \"lift\"\n\
             stops = [{{ floor = \"F2\", cell = [0, 0] }}, {{ floor = \"B1\", cell = [2, 2] }}]\n"
        );
        let b = parse(&text).unwrap();
        let names: Vec<_> = b.floors().iter().map(|f| f.name.as_str()).collect();
        assert_eq!(names, ["B1", "F1", "F2"]);
        assert_eq!(b.floor_named("F2"), Some(2));
        let lift = &b.connectors()[0];
        assert_eq!(lift.stops[0].floor, 0, "stops ordered by level");
        assert!(lift.kind.step_free());
        // Two levels at 5 s each after a 30 s wait.
        assert_eq!(lift.seconds(&b, lift.stops[0], lift.stops[1]), 40.0);
        // The lift skips F1.
        assert_eq!(b.floor_groups(|_| true), [vec![0, 2], vec![1]]);
        assert_eq!(b.floor_groups(|c| !c.kind.step_free()), [[0], [1], [2]]);
    }

    #[test]
    fn a_one_floor_site_file_is_a_building_of_one_floor() {
        let b = parse(&floor_site("hall", "##\n##")).unwrap();
        assert!(!b.is_multi_floor());
        assert_eq!(b.floors()[0].name, "hall");
        assert_eq!(b.floors()[0].level, 0);
    }

    #[test]
    fn errors_name_the_line_and_what_to_change() {
        let text = format!(
            "{FLOORS}[[floors]]\nname = \"F1\"\nlevel = 0\nsite = \"missing.toml\"\n\
             [[connectors]]\nid = \"s\"\nkind = \"stairs\"\n\
             stops = [{{ floor = \"F2\", cell = [1, 1] }}, {{ floor = \"F9\", cell = [0, 0] }}]\n"
        );
        let err = parse(&text).unwrap_err().to_string();
        assert!(
            err.contains("line 15: floor `F1` is also on line 3"),
            "{err}"
        );
        assert!(
            err.contains("has level 0, as has the floor on line 3"),
            "{err}"
        );
        assert!(err.contains("missing.toml"), "{err}");
        // Floor problems stop the check before connectors are read.
        let text = format!(
            "{FLOORS}[[connectors]]\nid = \"s\"\nkind = \"stairs\"\n\
             stops = [{{ floor = \"F2\", cell = [1, 1] }}, {{ floor = \"F9\", cell = [0, 0] }}]\n"
        );
        let err = parse(&text).unwrap_err().to_string();
        assert!(err.contains("dir/b.toml"), "{err}");
        assert!(
            err.contains("stop on floor `F2` at [1, 1] is a blocked cell"),
            "{err}"
        );
        assert!(
            err.contains("stops on floor `F9`, which is not in `floors` (B1, F1, F2)"),
            "{err}"
        );
    }

    #[test]
    fn a_written_building_reads_back_as_written() {
        let doc = BuildingDoc {
            name: "two \"quoted\" floors".into(),
            floors: vec![
                FloorDoc {
                    name: "B1".into(),
                    level: -1,
                    site: "B1.toml".into(),
                },
                FloorDoc {
                    name: "F1".into(),
                    level: 0,
                    site: "F1.toml".into(),
                },
            ],
            connectors: vec![ConnectorDoc {
                id: "lift".into(),
                kind: ConnectorKind::Lift,
                s_per_level: None,
                wait_s: Some(10.0),
                stops: vec![
                    StopDoc {
                        floor: "B1".into(),
                        cell: Cell::new(1, 1),
                    },
                    StopDoc {
                        floor: "F1".into(),
                        cell: Cell::new(2, 2),
                    },
                ],
            }],
        };
        let text = doc.to_toml();
        assert!(
            text.contains(
                "stops = [{ floor = \"B1\", cell = [1, 1] }, { floor = \"F1\", cell = [2, 2] }]"
            ),
            "{text}"
        );
        let b = parse(&text).unwrap();
        assert_eq!(b.name, doc.name);
        assert_eq!(b.floors().len(), 2);
        assert_eq!(b.connectors()[0].wait_s, 10.0);
        assert_eq!(b.connectors()[0].stops[1].cell, Cell::new(2, 2));
    }

    #[test]
    fn a_connector_must_join_two_floors_once_each() {
        let text = format!(
            "{FLOORS}[[connectors]]\nid = \"r\"\nkind = \"ramp\"\ns_per_level = -1.0\n\
             stops = [{{ floor = \"F1\", cell = [0, 0] }}, {{ floor = \"F1\", cell = [1, 0] }}]\n"
        );
        let err = parse(&text).unwrap_err().to_string();
        assert!(err.contains("stops twice on floor `F1`"), "{err}");
        assert!(err.contains("`s_per_level` is -1"), "{err}");
        let text = format!(
            "{FLOORS}[[connectors]]\nid = \"r\"\nkind = \"ramp\"\n\
             stops = [{{ floor = \"F1\", cell = [0, 0] }}]\n"
        );
        let err = parse(&text).unwrap_err().to_string();
        assert!(
            err.contains("has 1 stop(s); it must join at least two floors"),
            "{err}"
        );
        let text = format!(
            "{FLOORS}[[connectors]]\nid = \" \"\nkind = \"lift\"\n\
             stops = [{{ floor = \"F1\", cell = [0, 0] }}, {{ floor = \"B1\", cell = [0, 0] }}]\n"
        );
        let err = parse(&text).unwrap_err().to_string();
        assert!(err.contains("a connector's `id` is empty"), "{err}");
    }

    #[test]
    fn replacing_the_connectors_keeps_the_rest_of_the_file() {
        let text = format!(
            "# the test building\n{FLOORS}\n[[connectors]]\nid = \"old\"\nkind = \"stairs\"\n\
             stops = [{{ floor = \"F1\", cell = [0, 0] }}, {{ floor = \"B1\", cell = [0, 0] }}]\n"
        );
        let lift = ConnectorDoc {
            id: "lift".into(),
            kind: ConnectorKind::Lift,
            s_per_level: None,
            wait_s: Some(20.0),
            stops: vec![
                StopDoc {
                    floor: "B1".into(),
                    cell: Cell::new(2, 2),
                },
                StopDoc {
                    floor: "F2".into(),
                    cell: Cell::new(0, 1),
                },
            ],
        };
        let replaced = replace_connectors(&text, std::slice::from_ref(&lift)).unwrap();
        assert!(
            replaced.starts_with(&format!("# the test building\n{FLOORS}")),
            "{replaced}"
        );
        assert!(!replaced.contains("old"), "{replaced}");
        assert!(
            replaced.contains(
                "stops = [{ floor = \"B1\", cell = [2, 2] }, { floor = \"F2\", cell = [0, 1] }]"
            ),
            "{replaced}"
        );
        assert_eq!(BuildingDoc::parse(&replaced).unwrap().connectors, [lift]);
        let b = parse(&replaced).unwrap();
        assert_eq!(b.connectors()[0].wait_s, 20.0);
        // No connectors: none written, the floors unchanged.
        let none = replace_connectors(&text, &[]).unwrap();
        assert!(none.starts_with(&format!("# the test building\n{FLOORS}")));
        assert!(BuildingDoc::parse(&none).unwrap().connectors.is_empty());
    }
}
