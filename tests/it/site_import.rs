//! `gangway site import --geojson DIR`: a building's floor plans as its
//! floors' site files and a building file that `gangway check` accepts, on
//! the made-up building of `floors_support` (its stairs and lift found in
//! the plans) and on the real five-floor mall (no connectors in its plans).

use std::path::Path;

use serde_json::Value;

use crate::common::{self, gangway, gangway_ok};
use crate::floors_support;

/// `site import` of `plans` into `out` (the building file) with `extra`
/// flags: what it prints.
fn import(plans: &Path, out: &Path, extra: &[&str]) -> String {
    let (plans, out) = (plans.to_str().unwrap(), out.to_str().unwrap());
    let args = [
        &["site", "import", "--geojson", plans, "--out", out][..],
        extra,
    ];
    gangway_ok(&args.concat())
}

/// `gangway check --site building`'s output, failing the test when it fails.
fn check_site(building: &Path) -> String {
    gangway_ok(&["check", "--site", building.to_str().unwrap()])
}

#[test]
fn the_made_up_plans_import_with_their_lift_and_stairs_as_connectors() {
    let dir = tempfile::tempdir().unwrap();
    let plans = floors_support::write_geojson(dir.path());
    let out = dir.path().join("made-up/building.toml");
    std::fs::create_dir_all(out.parent().unwrap()).unwrap();
    let report: Value = serde_json::from_str(&import(
        &plans,
        &out,
        &["--cell-m", "0.5", "--name", "made-up", "--json"],
    ))
    .unwrap();

    // Levels from the folders' names: a building with a G keeps B1 at -1 and
    // L1 at 1.
    let floors: Vec<(&str, i64, &str)> = report["floors"]
        .as_array()
        .unwrap()
        .iter()
        .map(|f| {
            (
                f["name"].as_str().unwrap(),
                f["level"].as_i64().unwrap(),
                f["level_from"].as_str().unwrap(),
            )
        })
        .collect();
    assert_eq!(
        floors,
        [
            ("B1", -1, "folder name"),
            ("G", 0, "folder name"),
            ("L1", 1, "folder name")
        ]
    );
    // The lift on every floor is one connector; the stairs stop at G.
    let connectors: Vec<(&str, &str, Vec<&str>)> = report["connectors"]
        .as_array()
        .unwrap()
        .iter()
        .map(|c| {
            (
                c["id"].as_str().unwrap(),
                c["kind"].as_str().unwrap(),
                c["floors"]
                    .as_array()
                    .unwrap()
                    .iter()
                    .map(|f| f.as_str().unwrap())
                    .collect(),
            )
        })
        .collect();
    assert_eq!(
        connectors,
        [
            ("Stairs", "stairs", vec!["B1", "G"]),
            ("Elevator", "lift", vec!["B1", "G", "L1"]),
        ]
    );
    assert_eq!(report["unjoined"], serde_json::json!([]), "{report}");

    // Each floor's site is beside the building file, at 0.5 m cells.
    let site = std::fs::read_to_string(out.parent().unwrap().join("L1/site.toml")).unwrap();
    assert!(site.contains("cell_m = 0.5"), "{site}");
    floors_support::assert_checked(&check_site(&out), "1 stairs, 1 lift");
    let building = gangway::site::Building::load(&out).unwrap();
    let lift = &building.connectors()[1];
    assert!(lift.kind.step_free());
    // Its stops are at the lift's door on every floor: a cell beside it.
    for stop in &lift.stops {
        let site = &building.floors()[stop.floor].site;
        let [x, y] = site.world_of_cell(stop.cell);
        let inside = (16.0..=18.0).contains(&x) && (7.0..=9.0).contains(&y);
        let beside = (15.5..=18.5).contains(&x) && (6.5..=9.5).contains(&y);
        assert!(beside && !inside, "{stop:?} at {x}, {y}");
    }
}

#[test]
fn a_floor_without_a_number_says_what_to_rename() {
    let dir = tempfile::tempdir().unwrap();
    let plans = floors_support::write_geojson(dir.path());
    std::fs::rename(plans.join("L1"), plans.join("Mezzanine")).unwrap();
    let out = gangway(&[
        "site",
        "import",
        "--geojson",
        plans.to_str().unwrap(),
        "--out",
        dir.path().join("b.toml").to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("Mezzanine: its geojson_map.json gives no `floor_num`")
            && stderr.contains("rename the folder B1, B2"),
        "{stderr}"
    );
}

#[test]
fn the_real_mall_imports_as_five_floors_without_connectors() {
    let Some(plans) = common::shared_data("indoor-location-competition-20/site1") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("mall.toml");
    let stdout = import(&plans, &out, &[]);
    // The plans number B1 -1 and F1 1 with no floor 0: F1 is the ground floor.
    for (floor, level) in [("B1", -1), ("F1", 0), ("F2", 1), ("F3", 2), ("F4", 3)] {
        assert!(
            stdout.contains(&format!(
                "floor {floor} (level {level}, from its floor_num)"
            )),
            "{stdout}"
        );
    }
    assert!(stdout.contains("no connectors found"), "{stdout}");
    assert!(stdout.contains("5 floors, 0 connectors"), "{stdout}");
    let checked = check_site(&out);
    assert!(
        checked.contains("(building \"site1\": 5 floors, 0 connectors)")
            && checked.contains("floors apart: B1 | F1 | F2 | F3 | F4"),
        "{checked}"
    );
    assert!(dir.path().join("F3/floor_image.png").is_file());
}
