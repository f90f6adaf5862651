//! `gangway check` loads a config with its site and names every problem.

use crate::common;

use crate::common::{gangway, gangway_ok, write};
use crate::floors_support;

const SITE: &str = r#"name = "t"
cell_m = 1.0
map = '''
###
#.#
'''
[[beacon]]
id = "b1"
uuid = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84"
major = 1
minor = 1
cell = [0, 0]

[places]
desk = [2, 1]
"#;

const CONFIG: &str = "gateway_id = \"gw\"\nsite = \"site.toml\"\n";

/// Runs `check` on a config and site written to a temp dir; returns (ok, stderr).
fn check(config: &str, site: &str) -> (bool, String) {
    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "site.toml", site);
    let config = write(dir.path(), "gangway.toml", config);
    let out = gangway(&["check", "--config", config.to_str().unwrap()]);
    (
        out.status.success(),
        String::from_utf8_lossy(&out.stderr).into_owned(),
    )
}

fn rejects(config: &str, site: &str, expected: &[&str]) {
    let (ok, stderr) = check(config, site);
    assert!(!ok, "accepted a bad config/site");
    for e in expected {
        assert!(stderr.contains(e), "expected {e:?} in:\n{stderr}");
    }
}

#[test]
fn the_shipped_config_is_valid() {
    let out = gangway(&["check", "--config", "config/gangway.toml"]);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(String::from_utf8_lossy(&out.stdout).contains("117 walkable"));
}

#[test]
fn the_metric_sample_site_is_valid() {
    let site = std::fs::read_to_string(common::root().join("config/sites/depot.toml")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "site.toml", &site);
    let config = write(dir.path(), "gangway.toml", CONFIG);
    let out = gangway(&["check", "--config", config.to_str().unwrap()]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("16×10 cells, 144 walkable, 6 beacons")
            && stdout.contains(
                "frame: 0.9 m cells, origin [250, 120] m, y up; extent x 250 to 264.4 m, y 111 \
                 to 120 m; 1 obstacles and 1 walls blocked 16 cells"
            ),
        "{stdout}"
    );
}

#[test]
fn prints_the_frame_of_a_site_in_metres() {
    let site = r#"name = "m"
cell_m = 0.5
origin_m = [-3.0, 8.0]
y_axis = "up"
width_m = 4.0
height_m = 2.0
[[obstacles]]
polygon = [[-2.0, 7.0], [-1.0, 7.0], [-1.0, 6.5], [-2.0, 6.5]]
[[walls]]
line = [[0.0, 8.0], [0.0, 7.0]]
[[beacon]]
id = "b1"
uuid = "5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84"
major = 1
minor = 1
pos = [-1.5, 6.75]
height_m = 2.4
"#;
    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "site.toml", site);
    let config = write(dir.path(), "gangway.toml", CONFIG);
    let out = gangway(&["check", "--config", config.to_str().unwrap()]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        stdout.contains("8×4 cells, 26 walkable, 1 beacons"),
        "{stdout}"
    );
    // The obstacle covers 2 × 1 cell centres; the wall runs along the edge
    // between columns 5 and 6 for two rows: 4 cells.
    assert!(
        stdout.contains(
            "frame: 0.5 m cells, origin [-3, 8] m, y up; extent x -3 to 1 m, y 6 to 8 m; \
             1 obstacles and 1 walls blocked 6 cells"
        ),
        "{stdout}"
    );
}

#[test]
fn a_good_small_site_passes() {
    let (ok, stderr) = check(CONFIG, SITE);
    assert!(ok, "{stderr}");
}

#[test]
fn names_each_kind_of_site_problem() {
    rejects(
        CONFIG,
        &SITE.replace("#.#", "#."),
        &["site.toml", "`map`", "row 1 has 2 cells but row 0 has 3"],
    );
    rejects(
        CONFIG,
        &SITE.replace("desk = [2, 1]", "desk = [5, 1]"),
        &["line 15: place `desk` is at [5, 1], off the 3×2 grid"],
    );
    rejects(
        CONFIG,
        &SITE.replace("desk = [2, 1]", "desk = [1, 1]"),
        &["place `desk` is at [1, 1], a blocked cell"],
    );
    rejects(
        CONFIG,
        &SITE.replace("cell = [0, 0]", "cell = [1, 1]"),
        &["beacon `b1` is at [1, 1], a blocked cell"],
    );
    let duplicate = SITE.replace("[places]", "[[beacon]]\nid = \"b2\"\nuuid = \"5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84\"\nmajor = 1\nminor = 1\n\n[places]");
    rejects(
        CONFIG,
        &duplicate,
        &["beacon `b2` has the same uuid/major/minor", "line 7"],
    );
    rejects(
        CONFIG,
        &SITE.replace("major = 1", "major = \"one\""),
        &["site.toml", "line 10, column 9", "expected u16"],
    );
    rejects(
        CONFIG,
        &SITE.replace("###\n#.#", "###\n#?#"),
        &["unknown glyph '?'"],
    );
    // Several problems at once are all reported.
    let two = SITE
        .replace("desk = [2, 1]", "desk = [1, 1]")
        .replace("cell = [0, 0]", "cell = [9, 9]");
    rejects(
        CONFIG,
        &two,
        &["place `desk`", "beacon `b1` is at [9, 9], off the"],
    );
}

#[test]
fn names_each_kind_of_config_problem() {
    rejects(
        "site = \"site.toml\"\n",
        SITE,
        &["gangway.toml", "missing field `gateway_id`"],
    );
    rejects(
        "gateway_id = \"gw\"\nsite = \"nope.toml\"\n",
        SITE,
        &["nope.toml", "cannot read the site file"],
    );
    rejects(
        &format!("{CONFIG}[window]\nlength_s = 0\n"),
        SITE,
        &["[window]", "positive"],
    );
    rejects(
        &format!("{CONFIG}[window]\naggregate = \"mode\"\n"),
        SITE,
        &["unknown variant `mode`", "median"],
    );
    rejects(
        &format!("{CONFIG}[tracker]\nspeed = 1\n"),
        SITE,
        &["unknown field `speed`"],
    );
    rejects(
        "gateway_id = \"gw/1\"\nsite = \"site.toml\"\n",
        SITE,
        &["gateway_id", "MQTT topics"],
    );
    let no_cells = SITE.replace("cell = [0, 0]\n", "");
    rejects(
        CONFIG,
        &no_cells,
        &["pathloss localizer needs anchor positions"],
    );
}

#[test]
fn a_learned_planner_whose_named_models_are_missing_is_a_problem() {
    // The default planner passes over missing models and serves A*: fine
    // when the config names none (the sample above), but a config that names
    // a generator expects it to serve, so `check` says what would serve.
    let config = format!(
        "{CONFIG}[planner.models]\nconditional_generator = \"missing/conditional_generator.onnx\"\n"
    );
    rejects(
        &config,
        SITE,
        &[
            "[planner.models] names conditional_generator",
            "A* would serve",
            "mode = \"astar\"",
        ],
    );
    let explicit = format!("{CONFIG}[planner]\nmode = \"astar\"\n");
    assert!(check(&explicit, SITE).0, "A* on purpose is fine");
}

#[test]
fn the_installed_config_is_the_default_outside_a_checkout() {
    // Run from a directory without config/gangway.toml, `check` reads
    // GANGWAY_CONFIG, else /etc/gangway/gangway.toml, and says which.
    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "site.toml", SITE);
    let config = write(dir.path(), "gangway.toml", CONFIG);
    let run = |env: Option<&std::path::Path>| {
        let mut command = std::process::Command::new(env!("CARGO_BIN_EXE_gangway"));
        command.arg("check").current_dir(dir.path());
        command.env_remove("GANGWAY_CONFIG");
        if let Some(path) = env {
            command.env("GANGWAY_CONFIG", path);
        }
        command.output().unwrap()
    };
    let by_env = run(Some(&config));
    assert!(
        by_env.status.success(),
        "{}",
        String::from_utf8_lossy(&by_env.stderr)
    );
    assert!(String::from_utf8_lossy(&by_env.stdout).contains("gangway.toml"));
    if !std::path::Path::new("/etc/gangway/gangway.toml").exists() {
        let installed = run(None);
        assert!(!installed.status.success());
        assert!(
            String::from_utf8_lossy(&installed.stderr).contains("/etc/gangway/gangway.toml"),
            "{}",
            String::from_utf8_lossy(&installed.stderr)
        );
    }
}

#[test]
fn a_building_is_checked_floor_by_floor_with_its_connectors() {
    let dir = tempfile::tempdir().unwrap();
    let building = floors_support::write_building(dir.path());
    let stdout = gangway_ok(&["check", "--site", building.to_str().unwrap()]);
    assert!(
        stdout.contains("(building \"made-up\": 3 floors, 2 connectors)"),
        "{stdout}"
    );
    floors_support::assert_checked(&stdout, "1 lift, 1 stairs");

    // A config pointing at the building checks it with the config's settings
    // (the pathloss localizer on each floor's beacons).
    let config = write(
        dir.path(),
        "gangway.toml",
        "gateway_id = \"gw\"\nsite = \"building.toml\"\n",
    );
    let stdout = gangway_ok(&["check", "--config", config.to_str().unwrap()]);
    floors_support::assert_checked(&stdout, "1 lift, 1 stairs");
    // A survey named once for every floor is refused: one floor's would be
    // read on all of them.
    let config = write(
        dir.path(),
        "gangway.toml",
        "gateway_id = \"gw\"\nsite = \"building.toml\"\n[localizer.knn]\nsurvey = \"survey.csv\"\n",
    );
    let out = gangway(&["check", "--config", config.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("floor `B1`: [localizer.knn] survey = ")
            && stderr.contains("put `{floor}` in it"),
        "{stderr}"
    );

    // L1 is reached by the lift alone: without it, it is apart.
    let loaded = gangway::site::Building::load(&building).unwrap();
    assert_eq!(
        loaded.floor_groups(|c| !c.kind.step_free()),
        [vec![0, 1], vec![2]]
    );
    assert_eq!(loaded.floors()[0].site.cell_m, floors_support::CELL_M);
}

#[test]
fn a_building_s_problems_name_its_file_line_and_floor() {
    let dir = tempfile::tempdir().unwrap();
    let building = floors_support::write_building(dir.path());
    // The lift's B1 stop moved into the store.
    let text = std::fs::read_to_string(&building).unwrap();
    let [x, y] = floors_support::cell_of([17.0, 6.25]);
    let store = floors_support::cell_of([3.0, 2.0]);
    let moved = text.replacen(
        &format!("{{ floor = \"B1\", cell = [{x}, {y}] }}"),
        &format!("{{ floor = \"B1\", cell = [{}, {}] }}", store[0], store[1]),
        1,
    );
    assert_ne!(moved, text);
    std::fs::write(&building, moved).unwrap();
    let out = gangway(&["check", "--site", building.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("building.toml")
            && stderr.contains(&format!(
                "connector `lift` stop on floor `B1` at [{}, {}] is a blocked cell",
                store[0], store[1]
            )),
        "{stderr}"
    );

    // A floor's own problem names the floor's file.
    write(
        dir.path(),
        "G.toml",
        "name = \"g\"\ncell_m = 0.5\nwidth_m = 2.0\n",
    );
    let out = gangway(&["check", "--site", building.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("floor `G`") && stderr.contains("G.toml"),
        "{stderr}"
    );
}

/// `calibrate` learns one floor's radio model: on a building it asks which
/// floor the captures were taken on.
#[test]
fn calibrate_asks_for_the_floor_of_a_building() {
    let dir = tempfile::tempdir().unwrap();
    floors_support::write_building(dir.path());
    let config = write(
        dir.path(),
        "gangway.toml",
        "gateway_id = \"gw\"\nsite = \"building.toml\"\n",
    );
    let capture = write(dir.path(), "capture.jsonl", "");
    let out = gangway(&[
        "calibrate",
        "--config",
        config.to_str().unwrap(),
        "--from",
        capture.to_str().unwrap(),
        "--out",
        dir.path().join("calibration.toml").to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(!out.status.success());
    assert!(
        stderr.contains("a building of 3 floors (B1, G, L1)")
            && stderr.contains("give --floor NAME"),
        "{stderr}"
    );
}
