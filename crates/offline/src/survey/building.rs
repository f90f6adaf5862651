//! A building's floor plans in, its site files and building file out
//! (`gangway site import --geojson DIR`): one folder per floor in the Indoor
//! Location Competition layout, each drawn as `survey import` draws one floor
//! ([`super::floor`]), the floors numbered and the connectors between them
//! found in the plans.
//!
//! - **Levels.** A building file's level 0 is the entrance floor, negative
//!   below it. A floor's number is its plan's `floor_num` when the plan has
//!   one, else read from its folder's name (`B2` → -2; `F3`, `L3`, `3` → 3;
//!   `G`, `GF`, `F0`, `L0`, `0` → 0). Buildings number their floors two
//!   ways: with a floor 0 (the ground floor, the next one up is 1) or without
//!   (`F1`, `1` is the ground floor and the first basement `B1`, `-1`: that
//!   mall's plans say `floor_num = 1` for F1 and `-1` for B1, a storey
//!   apart). So when no floor is numbered 0, floors numbered above it move
//!   down by one to make the ground floor level 0; a building with a floor 0
//!   keeps its numbers.
//! - **Connectors.** Areas whose name or category says stairs, lift,
//!   escalator or ramp ([`super::floor`]) are joined to the nearest area of
//!   the same kind on the next floor up when the two are within
//!   [`JOIN_M`] in the plans' shared coordinates, and such joins chain into
//!   one connector stopping on every floor it reaches, at each area's door.
//!   An area joined to nothing is reported, not guessed at.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use anyhow::{Context, bail};
use serde::Serialize;

use super::floor::{FloorPlan, import_plan};
use crate::site::{
    Building, BuildingDoc, ConnectorDoc, ConnectorKind, FloorDoc, Site, SiteDoc, StopDoc, write_doc,
};

/// How far apart (metres, in the plans' shared coordinates) the areas of one
/// connector may be on two floors: a lift shaft lines up to a metre or two,
/// but a plan may draw an escalator's or a ramp's run from its foot on one
/// floor and from its head on the next.
pub const JOIN_M: f64 = 10.0;

/// What an import is asked for.
#[derive(Clone, Debug)]
pub struct Options {
    /// The building's name (default: the folder's name).
    pub name: Option<String>,
    pub cell_m: f64,
}

/// What an import wrote.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Report {
    /// The building file.
    pub building: PathBuf,
    pub name: String,
    /// Lowest level first.
    pub floors: Vec<FloorReport>,
    pub connectors: Vec<ConnectorReport>,
    /// Connector areas of the plans joined to no other floor, as
    /// "floor: place (kind)".
    pub unjoined: Vec<String>,
    /// Folders of the directory that hold no floor plan.
    pub skipped: Vec<PathBuf>,
}

/// One floor written.
#[derive(Clone, Debug, Default, Serialize)]
pub struct FloorReport {
    pub name: String,
    pub level: i32,
    /// Where the level came from: `floor_num` or `folder name`.
    pub level_from: &'static str,
    pub site: PathBuf,
    pub cells: usize,
    pub walkable_cells: usize,
    pub places: usize,
    /// Areas of its plan that are stairs, lifts, escalators or ramps.
    pub connector_areas: usize,
}

/// One connector found.
#[derive(Clone, Debug, Serialize)]
pub struct ConnectorReport {
    pub id: String,
    pub kind: ConnectorKind,
    /// The floors it stops on, lowest first.
    pub floors: Vec<String>,
}

/// A floor read and drawn, before the building's levels are known.
struct Drawn {
    name: String,
    /// Its number as the plan or folder gives it.
    number: i64,
    plan: FloorPlan,
    doc: SiteDoc,
    report: FloorReport,
}

/// Imports every floor folder of `dir` and writes the building file `out`,
/// each floor's site in `<out's folder>/<floor>/`; `on_floor` hears of each
/// floor as it is written.
pub fn import(
    dir: &Path,
    out: &Path,
    options: &Options,
    on_floor: &mut dyn FnMut(&FloorReport),
) -> anyhow::Result<Report> {
    anyhow::ensure!(
        options.cell_m.is_finite() && options.cell_m > 0.0,
        "--cell-m {} is not a positive number of metres",
        options.cell_m
    );
    let name = options.name.clone().unwrap_or_else(|| {
        dir.canonicalize()
            .ok()
            .and_then(|d| d.file_name().map(|n| n.to_string_lossy().into_owned()))
            .unwrap_or_else(|| "building".into())
    });
    let base = out.parent().unwrap_or(Path::new(""));
    let mut report = Report {
        building: out.to_owned(),
        name: name.clone(),
        ..Report::default()
    };
    let mut folders: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("{}: cannot read the floors' directory", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.is_dir())
        .collect();
    folders.sort();
    let mut drawn = Vec::new();
    for folder in folders {
        if !folder.join("geojson_map.json").is_file() {
            report.skipped.push(folder);
            continue;
        }
        drawn.push(draw(&folder, base, &name, options.cell_m)?);
    }
    if drawn.is_empty() {
        bail!(
            "{}: no floor folders; give one folder per floor, named after it (B1, F1, …), each \
             with geojson_map.json and floor_info.json (and floor_image.png)",
            dir.display()
        );
    }
    let levels = levels(&drawn.iter().map(|d| d.number).collect::<Vec<_>>());
    for (floor, level) in drawn.iter_mut().zip(levels) {
        floor.report.level = level;
    }
    drawn.sort_by_key(|d| d.report.level);
    for pair in drawn.windows(2) {
        if pair[0].report.level == pair[1].report.level {
            bail!(
                "floors `{}` and `{}` both have level {} (by {} and by {}); rename one folder, or \
                 fix the `floor_num` of its geojson_map.json",
                pair[0].name,
                pair[1].name,
                pair[0].report.level,
                pair[0].report.level_from,
                pair[1].report.level_from
            );
        }
    }
    for floor in &drawn {
        on_floor(&floor.report);
    }

    let (connectors, unjoined) = connectors(&drawn);
    report.unjoined = unjoined;
    let doc = BuildingDoc {
        name,
        floors: drawn
            .iter()
            .map(|d| FloorDoc {
                name: d.name.clone(),
                level: d.report.level,
                site: Path::new(&d.name).join("site.toml"),
            })
            .collect(),
        connectors,
    };
    report.connectors = doc
        .connectors
        .iter()
        .map(|c| ConnectorReport {
            id: c.id.clone(),
            kind: c.kind,
            floors: c.stops.iter().map(|s| s.floor.clone()).collect(),
        })
        .collect();
    let text = format!(
        "# Written by `gangway site import --geojson {}`: its floors, and the connectors found \
         in their plans.\n{}",
        dir.display(),
        doc.to_toml()
    );
    std::fs::write(out, &text).with_context(|| format!("cannot write {}", out.display()))?;
    // What was written is what the gateway loads.
    Building::load(out)?;
    report.floors = drawn.into_iter().map(|d| d.report).collect();
    Ok(report)
}

/// Draws the floor in `folder` and writes its site and image to
/// `<base>/<folder's name>/`.
fn draw(folder: &Path, base: &Path, building: &str, cell_m: f64) -> anyhow::Result<Drawn> {
    let name = folder
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .context("a floor folder has no name")?;
    let out = base.join(&name);
    let (plan, doc) = import_plan(folder, &out, &format!("{building} {name}"), cell_m)?;
    let (number, level_from) = match (plan.floor_num, floor_number(&name)) {
        (Some(n), _) => (n, "floor_num"),
        (None, Some(n)) => (n, "folder name"),
        (None, None) => bail!(
            "{}: its geojson_map.json gives no `floor_num` and `{name}` is not a floor's name; \
             rename the folder B1, B2 … below ground, F1, F2 … (or L1, 1 …) above, G or 0 for \
             a ground floor numbered 0",
            folder.display()
        ),
    };
    let site_path = out.join("site.toml");
    let text = format!(
        "# Written by `gangway site import --geojson`: floor {name} of {building}, from {}.\n{}",
        folder.display(),
        write_doc(&doc, None)
    );
    let site = Site::parse(&text, &site_path)?;
    std::fs::write(&site_path, &text)
        .with_context(|| format!("cannot write {}", site_path.display()))?;
    let report = FloorReport {
        name: name.clone(),
        level: 0,
        level_from,
        site: site_path,
        cells: usize::from(site.width()) * usize::from(site.height()),
        walkable_cells: site.open_cells().len(),
        places: site.places().len(),
        connector_areas: plan.connectors.len(),
    };
    Ok(Drawn {
        name,
        number,
        plan,
        doc,
        report,
    })
}

/// A floor's number from its folder's name: `B2` → -2, `F3`/`L3`/`3` → 3,
/// `G`/`GF`/`F0`/`L0`/`0` → 0, `-1` → -1 (any case).
fn floor_number(name: &str) -> Option<i64> {
    let upper = name.trim().to_uppercase();
    if matches!(upper.as_str(), "G" | "GF" | "GROUND") {
        return Some(0);
    }
    let digits = |s: &str| {
        (!s.is_empty() && s.bytes().all(|b| b.is_ascii_digit()))
            .then(|| s.parse::<i64>().ok())
            .flatten()
    };
    if let Some(rest) = upper.strip_prefix('B') {
        return digits(rest).filter(|&n| n > 0).map(|n| -n);
    }
    if let Some(rest) = upper.strip_prefix('-') {
        return digits(rest).map(|n| -n);
    }
    let rest = upper
        .strip_prefix('F')
        .or_else(|| upper.strip_prefix('L'))
        .unwrap_or(&upper);
    digits(rest)
}

/// Levels from the floors' numbers: numbered without a 0, the floors above
/// ground move down one so that 1 (the ground floor) is level 0.
fn levels(numbers: &[i64]) -> Vec<i32> {
    let shift = i64::from(!numbers.contains(&0));
    numbers
        .iter()
        .map(|&n| {
            let level = if n > 0 { n - shift } else { n };
            i32::try_from(level).unwrap_or(if level < 0 { i32::MIN } else { i32::MAX })
        })
        .collect()
}

/// The connectors the plans' connector areas make (floors lowest first), and
/// the areas joined to no other floor.
fn connectors(floors: &[Drawn]) -> (Vec<ConnectorDoc>, Vec<String>) {
    // `up[f][a]`: the area of floor f + 1 that area a of floor f joins.
    let mut up: Vec<BTreeMap<usize, usize>> = vec![BTreeMap::new(); floors.len()];
    for (f, pair) in floors.windows(2).enumerate() {
        let (lower, upper) = (&pair[0].plan, &pair[1].plan);
        let mut pairs = Vec::new();
        for (a, below) in lower.connectors.iter().enumerate() {
            for (b, above) in upper.connectors.iter().enumerate() {
                if below.kind != above.kind {
                    continue;
                }
                if let Some(d) = lower
                    .distance_m(below, upper, above)
                    .filter(|&d| d <= JOIN_M)
                {
                    pairs.push((d, a, b));
                }
            }
        }
        // Nearest first, each area joined once.
        pairs.sort_by(|x, y| x.0.total_cmp(&y.0));
        let mut taken = BTreeSet::new();
        for (_, a, b) in pairs {
            if !up[f].contains_key(&a) && !taken.contains(&b) {
                up[f].insert(a, b);
                taken.insert(b);
            }
        }
    }
    let joined_from_below: Vec<BTreeSet<usize>> = std::iter::once(BTreeSet::new())
        .chain(up.iter().map(|m| m.values().copied().collect()))
        .collect();
    let mut docs: Vec<ConnectorDoc> = Vec::new();
    let mut unjoined = Vec::new();
    for (f, floor) in floors.iter().enumerate() {
        for (a, area) in floor.plan.connectors.iter().enumerate() {
            if joined_from_below[f].contains(&a) {
                continue;
            }
            // A chain starts here: follow it up.
            let mut stops = Vec::new();
            let (mut g, mut at) = (f, Some(a));
            while let Some(i) = at {
                let place = &floors[g].plan.connectors[i].place;
                if let Some(&cell) = floors[g].doc.places.get(place) {
                    stops.push(StopDoc {
                        floor: floors[g].name.clone(),
                        cell,
                    });
                }
                at = up[g].get(&i).copied();
                g += 1;
            }
            if stops.len() < 2 {
                unjoined.push(format!(
                    "{}: `{}` ({})",
                    floor.name,
                    area.place,
                    area.kind.name()
                ));
                continue;
            }
            let mut id = area.place.clone();
            if docs.iter().any(|d| d.id == id) {
                id = format!("{} ({})", area.place, floor.name);
            }
            docs.push(ConnectorDoc {
                id,
                kind: area.kind,
                s_per_level: None,
                wait_s: None,
                stops,
            });
        }
    }
    (docs, unjoined)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn floors_are_numbered_from_their_folders_names() {
        assert_eq!(floor_number("B1"), Some(-1));
        assert_eq!(floor_number("b2"), Some(-2));
        assert_eq!(floor_number("F4"), Some(4));
        assert_eq!(floor_number("L1"), Some(1));
        assert_eq!(floor_number("3"), Some(3));
        assert_eq!(floor_number("-1"), Some(-1));
        assert_eq!(floor_number("GF"), Some(0));
        assert_eq!(floor_number("F0"), Some(0));
        assert_eq!(floor_number("B0"), None);
        assert_eq!(floor_number("Mezzanine"), None);
        assert_eq!(floor_number("F"), None);
    }

    #[test]
    fn the_ground_floor_is_level_0_either_way_buildings_number_it() {
        // That mall: B1, F1 … F4 with no floor 0.
        assert_eq!(levels(&[-1, 1, 2, 3, 4]), [-1, 0, 1, 2, 3]);
        // A building with a ground floor 0 keeps its numbers.
        assert_eq!(levels(&[-1, 0, 1, 2]), [-1, 0, 1, 2]);
    }
}
