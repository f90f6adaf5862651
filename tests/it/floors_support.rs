//! A second multi-floor building, made up, so that nothing multi-floor is
//! tuned to the real mall: other cell size (0.5 m), other floor names and
//! numbering (B1, G, L1, with a ground floor 0), a floor reachable only by
//! lift, and a beacon beside a floor opening that the floor below hears too.
//!
//! One description ([`FLOORS`], [`CONNECTORS`], [`BEACONS`]) written two
//! ways: as site files and a building file ([`write_building`]), and as the
//! floor plans `gangway site import --geojson` reads ([`write_geojson`]).
//!
//! ```text
//!  y (m)                B1                    G                     L1
//!  12 ┌────────┬──┬────────────┐ ┌─────┬──┬──┬────────────┐ ┌────────────────────┐
//!     │        │St│     ┌──┐   │ │Cafe │  │St│     ┌──┐   │ │             ┌──┐   │
//!   9 │        └──┘     │El│   │ │     │  └──┘     │El│   │ │             │El│   │
//!   7 │                 └──┘   │ └─────┘ ┌────┐    └──┘   │ │             └──┘   │
//!     │                        │         │void│*          │ ├────────┐           │
//!   5 ├──────┐                 │         └────┘           │ │ Office │           │
//!     │Store │                 │                          │ │        │           │
//!   0 └──────┴─────────────────┘ └────────────────────────┘ └────────┴───────────┘
//!     0      6  8  10   16 18 20   0  5  8  10 12 16 18 20    0        8    16 18 20
//! ```
//!
//! St: stairs (B1 and G only), El: the lift (every floor), void: the atrium
//! opening on G over B1's hall, `*` the beacon at its edge.

use std::path::{Path, PathBuf};

use crate::common::write;

/// Metres per cell side.
pub(crate) const CELL_M: f64 = 0.5;
/// Every floor's size, metres; the floors share one frame (x east, y north
/// from the south-west corner).
pub(crate) const WIDTH_M: f64 = 20.0;
pub(crate) const HEIGHT_M: f64 = 12.0;

/// A closed area of a floor: its name and rectangle `[x0, y0, x1, y1]`, m.
pub(crate) type Area = (&'static str, [f64; 4]);

/// A floor: its name (its GeoJSON folder's too), level and areas.
pub(crate) struct FloorSpec {
    pub(crate) name: &'static str,
    pub(crate) level: i32,
    pub(crate) areas: &'static [Area],
}

const STAIRS: Area = ("Stairs", [8.0, 9.0, 10.0, 12.0]);
const LIFT: Area = ("Elevator", [16.0, 7.0, 18.0, 9.0]);
/// G's opening over B1's hall.
pub(crate) const ATRIUM: Area = ("Atrium void", [8.0, 3.0, 12.0, 7.0]);

pub(crate) const FLOORS: [FloorSpec; 3] = [
    FloorSpec {
        name: "B1",
        level: -1,
        areas: &[("Store", [0.0, 0.0, 6.0, 5.0]), STAIRS, LIFT],
    },
    FloorSpec {
        name: "G",
        level: 0,
        areas: &[("Cafe", [0.0, 7.0, 5.0, 12.0]), STAIRS, LIFT, ATRIUM],
    },
    FloorSpec {
        name: "L1",
        level: 1,
        areas: &[("Office", [0.0, 0.0, 8.0, 5.0]), LIFT],
    },
];

/// The connectors of the site-file building: id, kind, where its stops are
/// (metres, in front of its area) and the floors it stops on. L1 has the
/// lift only.
pub(crate) const CONNECTORS: [(&str, &str, [f64; 2], &[&str]); 2] = [
    ("lift", "lift", [17.0, 6.25], &["B1", "G", "L1"]),
    ("stairs", "stairs", [9.0, 8.25], &["B1", "G"]),
];

/// The beacons: id, floor, position (m), minor. `atrium` is on G at the
/// opening's edge, so B1 below hears it through the opening as well.
pub(crate) const BEACONS: [(&str, &str, [f64; 2], u16); 5] = [
    ("b1-west", "B1", [3.0, 8.0], 1),
    ("b1-east", "B1", [18.0, 2.0], 2),
    ("g-west", "G", [2.0, 2.0], 3),
    ("atrium", "G", [12.25, 5.0], 4),
    ("l1-east", "L1", [18.0, 2.0], 5),
];

pub(crate) const UUID: &str = "8b0c3f0e-6a51-4d27-9c1e-2f4a6b8d0e13";

/// The cell whose centre is nearest `at` (metres).
pub(crate) fn cell_of(at: [f64; 2]) -> [u16; 2] {
    [
        (at[0] / CELL_M).floor() as u16,
        ((HEIGHT_M - at[1]) / CELL_M).floor() as u16,
    ]
}

fn rect(r: [f64; 4]) -> [[f64; 2]; 5] {
    [
        [r[0], r[1]],
        [r[2], r[1]],
        [r[2], r[3]],
        [r[0], r[3]],
        [r[0], r[1]],
    ]
}

/// Writes the building as site files (`<dir>/<floor>.toml`) and the building
/// file `<dir>/building.toml`, which it returns.
pub(crate) fn write_building(dir: &Path) -> PathBuf {
    for floor in &FLOORS {
        let mut site = format!(
            "name = \"made-up {}\"\ncell_m = {CELL_M}\norigin_m = [0.0, {HEIGHT_M}]\n\
             y_axis = \"up\"\nwidth_m = {WIDTH_M}\nheight_m = {HEIGHT_M}\n",
            floor.name
        );
        for (_, r) in floor.areas {
            site += &format!("\n[[obstacles]]\npolygon = {:?}\n", &rect(*r)[..4]);
        }
        for (id, _, pos, minor) in BEACONS.iter().filter(|b| b.1 == floor.name) {
            site += &format!(
                "\n[[beacon]]\nid = \"{id}\"\nuuid = \"{UUID}\"\nmajor = 7\nminor = {minor}\n\
                 pos = {pos:?}\n"
            );
        }
        write(dir, &format!("{}.toml", floor.name), &site);
    }
    let mut building = String::from("name = \"made-up\"\n");
    for floor in &FLOORS {
        building += &format!(
            "\n[[floors]]\nname = \"{0}\"\nlevel = {1}\nsite = \"{0}.toml\"\n",
            floor.name, floor.level
        );
    }
    for (id, kind, at, floors) in &CONNECTORS {
        let stops: Vec<String> = floors
            .iter()
            .map(|f| format!("{{ floor = \"{f}\", cell = {:?} }}", cell_of(*at)))
            .collect();
        building += &format!(
            "\n[[connectors]]\nid = \"{id}\"\nkind = \"{kind}\"\nstops = [{}]\n",
            stops.join(", ")
        );
    }
    write(dir, "building.toml", &building)
}

/// Writes the floor plans as `site import --geojson` reads them: a folder per
/// floor named after it with `geojson_map.json` (in metres, no `floor_num`,
/// so levels come from the folders' names) and `floor_info.json`; returns the
/// directory.
pub(crate) fn write_geojson(dir: &Path) -> PathBuf {
    let plans = dir.join("plans");
    for floor in &FLOORS {
        let folder = plans.join(floor.name);
        std::fs::create_dir_all(&folder).unwrap();
        let polygon = |name: &str, r: [f64; 4]| {
            serde_json::json!({
                "type": "Feature",
                "properties": { "name": name },
                "geometry": { "type": "Polygon", "coordinates": [rect(r)] },
            })
        };
        let mut features = vec![polygon(floor.name, [0.0, 0.0, WIDTH_M, HEIGHT_M])];
        features.extend(floor.areas.iter().map(|(name, r)| polygon(name, *r)));
        let plan = serde_json::json!({ "type": "FeatureCollection", "features": features });
        write(&folder, "geojson_map.json", &plan.to_string());
        let info = serde_json::json!({ "map_info": { "width": WIDTH_M, "height": HEIGHT_M } });
        write(&folder, "floor_info.json", &info.to_string());
    }
    plans
}

/// Asserts that `stdout`, `gangway check`'s on the building, passed every
/// floor (20 × 12 m at 0.5 m cells) and its connectors (`kinds` counted in
/// the file's order) join every floor, step-free too.
pub(crate) fn assert_checked(stdout: &str, kinds: &str) {
    for floor in &FLOORS {
        let line = format!(
            "ok: floor {0} (level {1}): site \"made-up {0}\": 40×24 cells",
            floor.name, floor.level
        );
        assert!(stdout.contains(&line), "no {line:?} in {stdout}");
    }
    let line = format!(
        "connectors: 2 ({kinds}): all 3 floors joined; step-free (lifts and ramps only): all 3 \
         floors joined"
    );
    assert!(stdout.contains(&line), "no {line:?} in {stdout}");
}
