//! Localization quality: the gate CI holds on the real survey, and a made-up
//! site showing that nothing assumes the sample site's grid or anchors.

use crate::common;

use std::fmt::Write;

use crate::common::{gangway_ok, gangway_refused, write};
use serde_json::Value;

fn eval(args: &[&str]) -> Value {
    let out = gangway_ok(&[&["eval", "localization", "--json"], args].concat());
    serde_json::from_str(out.trim()).expect("one JSON object")
}

/// What `eval localization --walks` does not use is refused by name, not
/// silently ignored (clap refuses before any file is read).
#[test]
fn walks_refuse_the_survey_s_options() {
    for (flag, value) in [
        ("--seeds", "3"),
        ("--split", "random"),
        ("--smooth-lag", "2"),
        ("--plot", "cdf.svg"),
        ("--calibrate", "crowd.csv"),
    ] {
        eval_refused(&["--site", "b.toml", "--walks", "walks", flag, value], flag);
    }
    eval_refused(
        &[
            "--site",
            "s.toml",
            "--survey",
            "s.csv",
            "--floor-switch",
            "0.1",
        ],
        "--floor-switch",
    );
}

/// `gangway eval localization` with `args` must refuse, saying `says`.
fn eval_refused(args: &[&str], says: &str) {
    gangway_refused(&[&["eval", "localization"], args].concat(), says);
}

fn figure(v: &Value, key: &str) -> f64 {
    v[key].as_f64().unwrap_or_else(|| panic!("no {key} in {v}"))
}

/// The targets this project has reached on ../shared/data/uci-ble-rssi; the
/// evaluation is deterministic (fixed seeds), so a drop is a real regression.
#[test]
fn the_real_survey_stays_at_or_above_the_reached_targets() {
    let Some(survey) = common::uci_survey() else {
        return;
    };
    let survey = survey.to_str().unwrap();
    let site = "config/sites/waldo.toml";

    let session = eval(&[
        "--site", site, "--survey", survey, "--split", "session", "--method", "knn",
    ]);
    assert_eq!(
        session.as_object().unwrap().keys().collect::<Vec<_>>(),
        [
            "confidence_gap_max",
            "confidence_gap_mean",
            "exact",
            "mean_error_cells",
            "mean_error_m",
            "median_error_cells",
            "median_error_m",
            "p75_error_cells",
            "p75_error_m",
            "p90_error_cells",
            "p90_error_m",
            "reliability",
            "us_per_fix",
            "within_1",
            "within_2"
        ]
    );
    // k-NN + hmm: 1.056 / 0.793 measured.
    assert!(
        figure(&session, "mean_error_cells") <= 1.10,
        "session split: {session}"
    );
    assert!(
        figure(&session, "within_2") >= 0.78,
        "session split: {session}"
    );

    // 1.118 / 0.804 / 0.396 measured.
    let random = eval(&[
        "--site", site, "--survey", survey, "--split", "random", "--method", "knn",
    ]);
    assert!(
        figure(&random, "mean_error_cells") <= 1.20,
        "random split: {random}"
    );
    assert!(
        figure(&random, "within_2") >= 0.78,
        "random split: {random}"
    );
    assert!(figure(&random, "exact") >= 0.37, "random split: {random}");

    // The shipped default with a survey: 1.032 / 0.805 / 0.439 measured
    // (issue #14's targets: ≤ 1.05, ≥ 0.80, ≥ 0.45).
    let auto = eval(&["--site", site, "--survey", survey, "--method", "auto"]);
    assert!(figure(&auto, "mean_error_cells") <= 1.06, "auto: {auto}");
    assert!(figure(&auto, "within_2") >= 0.79, "auto: {auto}");
    assert!(figure(&auto, "exact") >= 0.42, "auto: {auto}");
}

/// Published confidence stays as honest as it has become on the real floor
/// (`confidence_gap_max`, target 0.05): surveyed methods map it through
/// held-out sessions, survey-free ones through rehearsal
/// (`locate::rehearsal`). Before either: auto 0.228, knn 0.26, pathloss
/// 0.79, calibrated 0.48, strongest 0.52. Calibrated, the mean gap over
/// fixes too: 0.091 while a calibration narrowed the rehearsal's doubt,
/// 0.049 since it does not; `auto`'s 0.092 before its held-out fixes were
/// weighed by the ground they stood on (`locate::crossval`), 0.056 since,
/// 0.062 once no block of a map publishes above the rule of succession.
#[test]
fn published_confidence_stays_as_honest_as_reached() {
    let Some(survey) = common::uci_survey() else {
        return;
    };
    let unlabelled = survey.with_file_name("iBeacon_RSSI_Unlabeled.csv");
    let (survey, unlabelled) = (survey.to_str().unwrap(), unlabelled.to_str().unwrap());
    let site = "config/sites/waldo.toml";
    // (method flags, the largest gap allowed, the mean gap allowed where
    // one is guarded), measured gaps beside each.
    let cases: [(&[&str], f64, Option<f64>); 6] = [
        (&["--method", "auto"], 0.14, Some(0.065)), // 0.118, 0.062 measured
        (&["--method", "radiomap"], 0.10, None),    // 0.068
        (&["--method", "knn"], 0.18, None),         // 0.167
        (&["--method", "pathloss"], 0.33, None),    // 0.307
        (
            &["--method", "pathloss", "--calibrate", unlabelled],
            0.13,
            Some(0.06),
        ), // 0.123, 0.050
        (&["--method", "strongest"], 0.26, None),   // 0.243
    ];
    for (flags, largest, mean) in cases {
        let m = eval(&[&["--site", site, "--survey", survey][..], flags].concat());
        assert!(
            figure(&m, "confidence_gap_max") <= largest,
            "{flags:?}: {m}"
        );
        if let Some(mean) = mean {
            assert!(figure(&m, "confidence_gap_mean") <= mean, "{flags:?}: {m}");
        }
    }
}

/// On the simulated metric site (`config/sites/depot.toml`: twenty walkers
/// for ten minutes, the simulator's own radio world), the survey-free
/// model's published confidence, as `gangway replay --score` judges what
/// was published (`min_confidence = 0`, so every fix is), is within 0.08 of
/// the share of fixes within one cell in every tenth of 30+ fixes: #31's
/// target for a simulated site (reached 0.047).
#[test]
fn survey_free_confidence_is_honest_on_the_simulated_metric_site() {
    let dir = tempfile::tempdir().unwrap();
    let path = |p: &std::path::Path| p.to_str().unwrap().to_owned();
    let site = path(&write(dir.path(), "depot.toml", METRIC_SITE));
    let config = path(&write(
        dir.path(),
        "gangway.toml",
        "gateway_id = \"depot\"\nsite = \"depot.toml\"\n\
         [localizer]\nmethod = \"pathloss\"\nmin_confidence = 0.0\n",
    ));
    let log = path(&dir.path().join("walkers.jsonl"));
    gangway_ok(&[
        "simulate",
        "--site",
        &site,
        "--out",
        &log,
        "--walkers",
        "20",
        "--duration",
        "600",
        "--seed",
        "3",
    ]);
    let out = gangway_ok(&["replay", &log, "--config", &config, "--score", "--json"]);
    let score: Value = serde_json::from_str(out.trim()).unwrap();
    let binned: u64 = score["reliability"]
        .as_array()
        .unwrap()
        .iter()
        .map(|bin| bin["fixes"].as_u64().unwrap())
        .sum();
    assert_eq!(binned, score["matched"].as_u64().unwrap(), "{score}");
    assert!(binned >= 1_000, "{score}");
    assert!(figure(&score, "confidence_gap_max") <= 0.08, "{score}");
}

/// The survey-free model calibrated on the crowd-sourced file alone (no
/// position known) and the cross-validated radio map hold what they reached
/// on the real floor; the radio map's published confidence stays honest.
#[test]
fn calibration_and_the_radio_map_hold_their_figures() {
    let Some(survey) = common::uci_survey() else {
        return;
    };
    let unlabelled = survey.with_file_name("iBeacon_RSSI_Unlabeled.csv");
    let site = "config/sites/waldo.toml";
    let survey = survey.to_str().unwrap();
    // The survey-free model calibrated on `from` first (`extra` flags too),
    // its mean error and within-2 share.
    let calibrated = |from: &str, extra: &[&str]| {
        let base = [
            "--site",
            site,
            "--survey",
            survey,
            "--method",
            "pathloss",
            "--calibrate",
            from,
        ];
        let m = eval(&[&base[..], extra].concat());
        (figure(&m, "mean_error_cells"), figure(&m, "within_2"))
    };
    // On the crowd file: 1.718 / 0.626 measured.
    let (mean, within_2) = calibrated(unlabelled.to_str().unwrap(), &[]);
    assert!(
        mean <= 1.80 && within_2 >= 0.60,
        "calibrated on the crowd file: {mean} / {within_2}"
    );
    // On the survey's own scans, their labels unused, with a radio map
    // refined per cell: 1.750 / 0.612 measured. (1.645 / 0.635 before
    // cells had to make held-out windows likelier: the scans include the
    // rows scored, so a map that learned their noise was flattered.)
    let (mean, within_2) = calibrated(survey, &["--calibrate-cells"]);
    assert!(
        mean <= 1.80 && within_2 >= 0.60,
        "self-calibrated with cells: {mean} / {within_2}"
    );
    let map = eval(&["--site", site, "--survey", survey, "--method", "radiomap"]);
    assert!(figure(&map, "mean_error_cells") <= 1.40, "radiomap: {map}");

    // The calibration file round-trips into a config the gateway accepts.
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("calibration.toml");
    let out = gangway_ok(&[
        "calibrate",
        "--from",
        unlabelled.to_str().unwrap(),
        "--out",
        file.to_str().unwrap(),
        "--cells",
        "--json",
    ]);
    let report: Value = serde_json::from_str(out.trim()).expect("one JSON object");
    // Every anchor's change is reported with its verdict; on the crowd file
    // the held-out walks keep all 13 and 32 of the 99 refined cells.
    let anchors = report["anchors"].as_array().unwrap();
    assert_eq!(anchors.len(), 13, "{report}");
    assert!(
        anchors
            .iter()
            .all(|a| a["kept"].is_boolean() && a["why"].is_string() && a["held_out_gain"].is_f64()),
        "{report}"
    );
    assert!(
        report["held_out"]["windows"].as_u64().unwrap() > 500,
        "{report}"
    );
    assert!(
        report["held_out"]["gain_per_window"].as_f64().unwrap() > 0.0,
        "{report}"
    );
    let cells = report["cells"]["cells"].as_u64().unwrap();
    assert!(
        cells > 20 && cells <= report["cells"]["refined"].as_u64().unwrap(),
        "{report}"
    );
    // The shipped config, its relative paths made absolute, with the file
    // in place of the shipped calibration (`check` refuses one that does
    // not load).
    let root = common::root();
    let shipped = std::fs::read_to_string(root.join("config/gangway.toml")).unwrap();
    let calibration = "\"sites/waldo-calibration.toml\"";
    assert!(shipped.contains(calibration));
    let config = shipped
        .replace(calibration, &format!("\"{}\"", file.display()))
        .replace("\"../", &format!("\"{}/", root.display()))
        .replace("\"sites/", &format!("\"{}/config/sites/", root.display()));
    let config = write(dir.path(), "gangway.toml", &config);
    gangway_ok(&["check", "--config", config.to_str().unwrap()]);
}

/// A fixed split, per-row fixes, and the errors a user meets first: a
/// positive "not heard" value and rows without a position.
#[test]
fn fixed_splits_rows_and_clear_errors() {
    let dir = tempfile::tempdir().unwrap();
    let site = write(dir.path(), "workshop.toml", SMALL_SITE);
    let survey = small_survey();
    let (header, rows) = survey.split_once('\n').unwrap();
    let rows: Vec<&str> = rows.lines().collect();
    let (train, test) = rows.split_at(rows.len() * 2 / 3);
    let train = write(
        dir.path(),
        "train.csv",
        &format!("{header}\n{}\n", train.join("\n")),
    );
    let test = write(
        dir.path(),
        "test.csv",
        &format!("{header}\n{}\n", test.join("\n")),
    );
    let per_row = dir.path().join("rows.csv");
    let m = eval(&[
        "--site",
        site.to_str().unwrap(),
        "--train",
        train.to_str().unwrap(),
        "--test",
        test.to_str().unwrap(),
        "--method",
        "radiomap",
        "--rows",
        per_row.to_str().unwrap(),
    ]);
    assert!(figure(&m, "mean_error_cells") < 1.5, "{m}");
    let written = std::fs::read_to_string(&per_row).unwrap();
    assert_eq!(written.lines().count(), rows.len() - rows.len() * 2 / 3 + 1);

    let hundred = write(
        dir.path(),
        "hundred.csv",
        &format!("{header}\n0,0,0,100,-70,-80,-90\n"),
    );
    let run = common::gangway(&[
        "eval",
        "localization",
        "--site",
        site.to_str().unwrap(),
        "--survey",
        hundred.to_str().unwrap(),
    ]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success());
    assert!(
        stderr.contains("hundred.csv:2") && stderr.contains("--not-heard 100"),
        "{stderr}"
    );
}

/// The `onnx` method trains a cell classifier per split, exports it and runs it
/// through tract; it must locate far better than chance (about 0.12 within 2
/// cells on this site).
#[test]
fn the_onnx_localizer_trains_exports_and_locates_per_split() {
    let Some(survey) = common::uci_survey() else {
        return;
    };
    let m = eval(&[
        "--site",
        "config/sites/waldo.toml",
        "--survey",
        survey.to_str().unwrap(),
        "--method",
        "onnx",
        "--seeds",
        "1",
    ]);
    assert!(figure(&m, "within_2") > 0.35, "{m}");
}

#[test]
fn the_shipped_cell_classifier_serves_the_pipeline() {
    let dir = tempfile::tempdir().unwrap();
    let root = common::root();
    // A config using the onnx localizer with `model`, written to `name`.
    let config_with = |name: &str, model: &std::path::Path| {
        write(
            dir.path(),
            name,
            &format!(
                "gateway_id = \"gw\"\nsite = \"{}\"\n[localizer]\nmethod = \"onnx\"\n[localizer.onnx]\nmodel = \"{}\"\n",
                root.join("config/sites/waldo.toml").display(),
                model.display()
            ),
        )
    };
    let shipped = root.join("models/cell_classifier.onnx");
    let config = config_with("gangway.toml", &shipped);
    let out = gangway_ok(&[
        "replay",
        "fixtures/walk-waldo.jsonl",
        "--config",
        config.to_str().unwrap(),
        "--print",
    ]);
    assert!(out.lines().any(|l| l.contains("/location")));

    // A truncated model is refused with a message naming the file.
    let bytes = std::fs::read(&shipped).unwrap();
    let broken = dir.path().join("broken.onnx");
    std::fs::write(&broken, &bytes[..bytes.len() / 2]).unwrap();
    let config = config_with("broken.toml", &broken);
    let run = common::gangway(&["check", "--config", config.to_str().unwrap()]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(!run.status.success());
    assert!(
        stderr.contains("broken.onnx") && !stderr.contains("panicked"),
        "{stderr}"
    );
}

const SMALL_SITE: &str = r#"name = "workshop"
cell_m = 2.0
map = '''
########
##....##
########
##....##
########
'''
[[beacon]]
id = "north-west"
uuid = "0b1c2d3e-4f50-6172-8394-a5b6c7d8e9f0"
major = 7
minor = 1
cell = [0, 0]
[[beacon]]
id = "north-east"
uuid = "0b1c2d3e-4f50-6172-8394-a5b6c7d8e9f0"
major = 7
minor = 2
cell = [7, 0]
[[beacon]]
id = "south-west"
uuid = "0b1c2d3e-4f50-6172-8394-a5b6c7d8e9f0"
major = 7
minor = 3
cell = [0, 4]
[[beacon]]
id = "south-east"
uuid = "0b1c2d3e-4f50-6172-8394-a5b6c7d8e9f0"
major = 7
minor = 4
cell = [7, 4]

[places]
bench = [0, 2]
door = [7, 2]
"#;

/// A generic-layout survey of the small site: three readings per walkable
/// cell from a path-loss formula with a fixed ±1 dB pattern.
fn small_survey() -> String {
    let beacons = [(0.0, 0.0), (7.0, 0.0), (0.0, 4.0), (7.0, 4.0)];
    let map = ["########", "##....##", "########", "##....##", "########"];
    let mut csv = String::from("x,y,t,north-west,north-east,south-west,south-east\n");
    let mut t = 0;
    for (y, row) in map.iter().enumerate() {
        for (x, c) in row.chars().enumerate() {
            if c != '#' {
                continue;
            }
            for rep in 0..3 {
                t += 2;
                write!(csv, "{x},{y},{t}").unwrap();
                for (i, (bx, by)) in beacons.iter().enumerate() {
                    let d = 2.0 * ((x as f64 - bx).powi(2) + (y as f64 - by).powi(2)).sqrt();
                    let noise = [(-1.0), 0.0, 1.0][(rep + i + x) % 3];
                    let rssi = -59.0 - 22.0 * d.max(0.5).log10() + noise;
                    write!(csv, ",{}", rssi.round() as i32).unwrap();
                }
                csv.push('\n');
            }
        }
    }
    csv
}

#[test]
fn another_site_with_other_anchors_and_size_works_from_its_own_files() {
    let dir = tempfile::tempdir().unwrap();
    let site = write(dir.path(), "workshop.toml", SMALL_SITE);
    let survey = write(dir.path(), "survey.csv", &small_survey());
    let (site, survey) = (site.to_str().unwrap(), survey.to_str().unwrap());

    for method in ["knn", "pathloss"] {
        let m = eval(&[
            "--site",
            site,
            "--survey",
            survey,
            "--split",
            "random",
            "--method",
            method,
            "--tracker",
            "none",
        ]);
        assert!(figure(&m, "mean_error_cells") < 1.0, "{method}: {m}");
        assert_eq!(
            figure(&m, "mean_error_m"),
            2.0 * figure(&m, "mean_error_cells"),
            "cell_m = 2"
        );
    }

    // The whole pipeline on that site: simulate, then replay with the survey.
    let log = dir.path().join("walk.jsonl");
    gangway_ok(&[
        "simulate",
        "--site",
        site,
        "--out",
        log.to_str().unwrap(),
        "--walkers",
        "2",
        "--duration",
        "40",
    ]);
    let config = write(
        dir.path(),
        "gangway.toml",
        "gateway_id = \"gw-w\"\nsite = \"workshop.toml\"\n[localizer]\nmethod = \"knn\"\n[localizer.knn]\nsurvey = \"survey.csv\"\n",
    );
    let out = gangway_ok(&[
        "replay",
        log.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--print",
    ]);
    let located: std::collections::BTreeSet<String> = out
        .lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
        .filter(|m| m["topic"].as_str().unwrap().ends_with("/location"))
        .map(|m| m["payload"]["device"].as_str().unwrap().to_owned())
        .collect();
    assert_eq!(located, ["walker-01", "walker-02"].map(String::from).into());
}

/// A second site in metres, unlike the sample floor in every way the site
/// file can say: 0.9 m cells, its grid at x 250 m, y 120 m with y up, an open
/// floor with a shelf block (obstacle polygon) and a partition (thin wall)
/// drawn on it, beacons placed by `pos` on the shelf, on the partition and on
/// the outer walls, some with a mounting height.
const METRIC_SITE: &str = include_str!("../../config/sites/depot.toml");

/// Where a world point falls on `METRIC_SITE`'s grid (cell column, row), and
/// the centre of a cell in world metres: the frame written out independently
/// of the code under test.
const DEPOT_CELL_M: f64 = 0.9;
fn depot_cell(x: f64, y: f64) -> (i64, i64) {
    (
        ((x - 250.0) / DEPOT_CELL_M).floor() as i64,
        ((120.0 - y) / DEPOT_CELL_M).floor() as i64,
    )
}
fn depot_centre(cx: i64, cy: i64) -> (f64, f64) {
    (
        250.0 + (cx as f64 + 0.5) * DEPOT_CELL_M,
        120.0 - (cy as f64 + 0.5) * DEPOT_CELL_M,
    )
}

/// `METRIC_SITE`'s anchors as the radio sees them: (x, y, height above the
/// phone), in the order of [`DEPOT_HEADER`]'s columns.
const DEPOT_BEACONS: [(f64, f64, f64); 6] = [
    (250.0, 120.0, 1.3),
    (256.7, 116.4, 0.6),
    (261.0, 118.0, 0.0),
    (264.4, 111.0, 1.3),
    (250.0, 113.5, 0.0),
    (258.0, 111.0, 1.3),
];
const DEPOT_HEADER: &str = "t,x_m,y_m,door,shelf,partition,far-corner,west,south";

/// Whether `METRIC_SITE` blocks a cell: the shelf (cell centres inside it)
/// and the partition (the cells x = 261 m runs through, from the top down to
/// y = 114.6 m, the edge between rows 5 and 6).
fn depot_blocked((cx, cy): (i64, i64)) -> bool {
    let (x, y) = depot_centre(cx, cy);
    let shelf = (254.5..259.0).contains(&x) && (115.5..117.3).contains(&y);
    let partition = cx == depot_cell(261.0, 120.0).0 && cy <= 5;
    shelf || partition
}

/// Nothing tuned to the sample floor: on `METRIC_SITE`, a survey in metres
/// (`x_m`,`y_m`, points anywhere on the walkable floor, not cell centres)
/// simulated with drop-outs and shadowing, split by rows into fixed files,
/// the radio map and the default surveyed method (`auto`) beat a plain kNN
/// regressor computed here on the same split
/// (the scikit-learn default: 5 neighbours, uniform weights, Euclidean
/// distance on raw RSSI with "not heard" as a floor value, mean position).
/// Both are scored in metres against where each row was really taken.
#[test]
fn the_surveyed_methods_beat_a_plain_knn_regressor_on_a_metric_site() {
    use rand::{RngExt, SeedableRng};
    let dir = tempfile::tempdir().unwrap();
    let site_file = write(dir.path(), "depot.toml", METRIC_SITE);
    let site = site_file.to_str().unwrap();
    let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(11);
    let header = DEPOT_HEADER;
    // (true position, readings with -200 for "not heard").
    let mut rows: Vec<((f64, f64), Vec<i32>)> = Vec::new();
    while rows.len() < 900 {
        // To the millimetre, as written to the files.
        let mm = |v: f64| (v * 1000.0).round() / 1000.0;
        let (x, y) = (
            mm(rng.random_range(250.0..264.4)),
            mm(rng.random_range(111.0..120.0)),
        );
        if depot_blocked(depot_cell(x, y)) {
            continue;
        }
        let readings = DEPOT_BEACONS
            .iter()
            .map(|&(bx, by, dh)| {
                let d: f64 = ((x - bx) * (x - bx) + (y - by) * (y - by) + dh * dh).sqrt();
                // Drop-outs rise with distance; shadowing of ±6 dB.
                let heard = rng.random_bool(0.9 / (1.0 + (d / 7.0).powi(3)));
                let shadowing: f64 = rng.random_range(-6.0..6.0);
                if heard {
                    (-60.0 - 22.0 * d.max(0.5).log10() + shadowing).round() as i32
                } else {
                    -200
                }
            })
            .collect();
        rows.push(((x, y), readings));
    }
    let csv = |rows: &[((f64, f64), Vec<i32>)], first_t: usize| {
        let mut out = format!("{header}\n");
        for (i, ((x, y), r)) in rows.iter().enumerate() {
            let r: Vec<String> = r.iter().map(i32::to_string).collect();
            // A minute apart: every row its own walking session.
            let t = (first_t + i) * 60;
            out.push_str(&format!("{t},{x:.3},{y:.3},{}\n", r.join(",")));
        }
        out
    };
    // Every third row held out.
    let (test, train): (Vec<_>, Vec<_>) = rows
        .iter()
        .cloned()
        .enumerate()
        .partition(|(i, _)| i % 3 == 0);
    let train: Vec<_> = train.into_iter().map(|(_, r)| r).collect();
    let test: Vec<_> = test.into_iter().map(|(_, r)| r).collect();
    let train_file = write(dir.path(), "train.csv", &csv(&train, 0));
    let test_file = write(dir.path(), "test.csv", &csv(&test, train.len()));
    // A surveyed method's mean error in metres (its fix is a cell, whose
    // centre in world metres is set against the row's true position) and
    // the largest gap of its published confidence.
    let surveyed_error = |method: &str| -> (f64, f64) {
        let per_row = dir.path().join(format!("rows-{method}.csv"));
        let metrics = eval(&[
            "--site",
            site,
            "--train",
            train_file.to_str().unwrap(),
            "--test",
            test_file.to_str().unwrap(),
            "--method",
            method,
            "--tracker",
            "none",
            "--rows",
            per_row.to_str().unwrap(),
        ]);
        let fixes = std::fs::read_to_string(&per_row).unwrap();
        let mut lines = fixes.lines();
        let columns: Vec<&str> = lines.next().unwrap().split(',').collect();
        let col = |name: &str| columns.iter().position(|c| *c == name).unwrap();
        let (row_col, x_col, y_col) = (col("row"), col("x"), col("y"));
        let mut error = 0.0;
        let mut fixed = 0;
        for line in lines {
            let f: Vec<&str> = line.split(',').collect();
            // Rows count through the training file, then the test file.
            let i = f[row_col].parse::<usize>().unwrap() - train.len();
            let (tx, ty) = test[i].0;
            let (cx, cy) = (f[x_col].parse().unwrap(), f[y_col].parse().unwrap());
            assert!(
                !depot_blocked((cx, cy)),
                "{method}: a fix on a blocked cell: {line}"
            );
            let (x, y) = depot_centre(cx, cy);
            error += (x - tx).hypot(y - ty);
            fixed += 1;
        }
        assert_eq!(fixed, test.len(), "{method}: one fix per held-out row");
        (error / fixed as f64, figure(&metrics, "confidence_gap_max"))
    };

    // The plain regressor on the same split.
    let value = |v: i32| if v == -200 { -105.0 } else { f64::from(v) };
    let mut knn_error = 0.0;
    for ((tx, ty), r) in &test {
        let mut by_distance: Vec<(f64, (f64, f64))> = train
            .iter()
            .map(|(at, q)| {
                let d: f64 = r
                    .iter()
                    .zip(q)
                    .map(|(a, b)| (value(*a) - value(*b)).powi(2))
                    .sum();
                (d, *at)
            })
            .collect();
        by_distance.sort_by(|a, b| a.0.total_cmp(&b.0));
        let (x, y) = by_distance[..5]
            .iter()
            .fold((0.0, 0.0), |acc, (_, (x, y))| {
                (acc.0 + x / 5.0, acc.1 + y / 5.0)
            });
        knn_error += (x - tx).hypot(y - ty);
    }
    knn_error /= test.len() as f64;
    // The radio map, and the shipped default (`auto`: the k-NN vote for
    // fingerprints the survey recorded, the map for the others).
    for method in ["radiomap", "auto"] {
        let (error, gap) = surveyed_error(method);
        assert!(
            error < knn_error,
            "{method} {error:.3} m against a plain kNN regressor {knn_error:.3} m"
        );
        eprintln!(
            "{method} {error:.3} m, plain kNN regressor {knn_error:.3} m; confidence gap {gap:.3}"
        );
    }
}

/// Calibration does no harm (#31): on `METRIC_SITE`, phones walk in two
/// worlds, one whose beacons are as loud as the defaults say and one where
/// they are quieter, fall off faster and reach further; the survey-free
/// model calibrated on unlabelled walks locates other walks at least as well
/// as the defaults do, in both.
#[test]
fn calibration_is_never_worse_than_none_on_a_metric_site() {
    use rand::{RngExt, SeedableRng};
    use rand_distr::{Distribution, Normal};
    struct World {
        name: &'static str,
        tx_dbm: [f64; 6],
        exponent: f64,
        shadowing_db: f64,
        range_m: f64,
        range_slope: f64,
        max_detection: f64,
    }
    // The first as `[localizer.pathloss]`'s defaults, written out here.
    let worlds = [
        World {
            name: "as the defaults",
            tx_dbm: [-59.0; 6],
            exponent: 2.2,
            shadowing_db: 5.0,
            range_m: 5.0,
            range_slope: 3.0,
            max_detection: 0.9,
        },
        World {
            name: "quieter beacons",
            tx_dbm: [-71.0, -68.0, -74.0, -70.0, -66.0, -72.0],
            exponent: 2.7,
            shadowing_db: 6.0,
            range_m: 7.0,
            range_slope: 2.5,
            max_detection: 0.85,
        },
    ];
    let dir = tempfile::tempdir().unwrap();
    let site_file = write(dir.path(), "depot.toml", METRIC_SITE);
    for (w, world) in worlds.iter().enumerate() {
        let mut rng = rand::rngs::Xoshiro256PlusPlus::seed_from_u64(31 + w as u64);
        let shadow = Normal::new(0.0, world.shadowing_db).unwrap();
        // `walks` walks of `seconds` windows, a minute apart, as a survey in
        // metres: walkers turn where the floor ends or a cell is blocked.
        let mut walks = |walks: usize, seconds: usize, first_t: usize| {
            let mut csv = format!("{DEPOT_HEADER}\n");
            for walk in 0..walks {
                let (mut x, mut y): (f64, f64);
                loop {
                    (x, y) = (
                        rng.random_range(250.5..264.0),
                        rng.random_range(111.5..119.5),
                    );
                    if !depot_blocked(depot_cell(x, y)) {
                        break;
                    }
                }
                let mut heading: f64 = rng.random_range(0.0..std::f64::consts::TAU);
                for s in 0..seconds {
                    let t = first_t + walk * (seconds + 60) + s;
                    let readings: Vec<String> = DEPOT_BEACONS
                        .iter()
                        .zip(world.tx_dbm)
                        .map(|(&(bx, by, dh), tx)| {
                            let d = ((x - bx).powi(2) + (y - by).powi(2) + dh * dh)
                                .sqrt()
                                .max(0.5);
                            let p = world.max_detection
                                / (1.0 + (d / world.range_m).powf(world.range_slope));
                            let rssi =
                                tx - 10.0 * world.exponent * d.log10() + shadow.sample(&mut rng);
                            if rng.random_bool(p) && rssi >= -100.0 {
                                format!("{}", rssi.round())
                            } else {
                                "-200".to_owned()
                            }
                        })
                        .collect();
                    writeln!(csv, "{t},{x:.3},{y:.3},{}", readings.join(",")).unwrap();
                    // About a metre a second, turning a little, more at walls.
                    heading += rng.random_range(-0.4..0.4);
                    let speed = rng.random_range(0.6..1.3);
                    for _ in 0..20 {
                        let (nx, ny) = (x + speed * heading.cos(), y + speed * heading.sin());
                        // A centimetre clear of blocked cells and the edges,
                        // so that no rounding puts it in one.
                        let clear = [(-0.01, -0.01), (-0.01, 0.01), (0.01, -0.01), (0.01, 0.01)]
                            .iter()
                            .all(|(dx, dy)| {
                                let (cx, cy) = depot_cell(nx + dx, ny + dy);
                                (0..16).contains(&cx)
                                    && (0..10).contains(&cy)
                                    && !depot_blocked((cx, cy))
                            });
                        if clear {
                            (x, y) = (nx, ny);
                            break;
                        }
                        heading = rng.random_range(0.0..std::f64::consts::TAU);
                    }
                }
            }
            csv
        };
        let heard = write(dir.path(), "heard.csv", &walks(40, 60, 0));
        let test = write(dir.path(), "test.csv", &walks(15, 60, 100_000));
        let error = |calibrate: bool| {
            let mut args = vec![
                "--site",
                site_file.to_str().unwrap(),
                "--train",
                heard.to_str().unwrap(),
                "--test",
                test.to_str().unwrap(),
                "--method",
                "pathloss",
            ];
            if calibrate {
                args.extend(["--calibrate", heard.to_str().unwrap()]);
            }
            figure(&eval(&args), "mean_error_m")
        };
        let (none, calibrated) = (error(false), error(true));
        eprintln!(
            "{}: mean error {none:.2} m with the defaults, {calibrated:.2} m calibrated",
            world.name
        );
        assert!(
            calibrated <= none,
            "{}: calibrated {calibrated:.3} m, worse than the defaults' {none:.3} m",
            world.name
        );
        // Where the defaults are wrong, calibration is what fixes them (5.20
        // → 2.20 m measured).
        if w == 1 {
            assert!(
                calibrated < 0.8 * none,
                "{}: calibrated {calibrated:.3} m against the defaults' {none:.3} m",
                world.name
            );
        }
    }
}

/// The whole pipeline on the metric site: walkers simulated with the beacons'
/// metric mounts, located by the survey-free model, published in the site's
/// world metres (the centre of the fix's cell in the plan's coordinates).
#[test]
fn a_metric_site_publishes_world_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "depot.toml", METRIC_SITE);
    let log = dir.path().join("walk.jsonl");
    gangway_ok(&[
        "simulate",
        "--site",
        dir.path().join("depot.toml").to_str().unwrap(),
        "--out",
        log.to_str().unwrap(),
        "--walkers",
        "2",
        "--duration",
        "60",
    ]);
    let config = write(
        dir.path(),
        "gangway.toml",
        "gateway_id = \"gw-d\"\nsite = \"depot.toml\"\n",
    );
    let out = gangway_ok(&[
        "replay",
        log.to_str().unwrap(),
        "--config",
        config.to_str().unwrap(),
        "--print",
    ]);
    let mut known = 0;
    for m in out
        .lines()
        .map(|l| serde_json::from_str::<Value>(l).unwrap())
        .filter(|m| m["topic"].as_str().unwrap().ends_with("/location"))
    {
        let p = &m["payload"];
        if p["cell"].is_null() {
            continue;
        }
        known += 1;
        let cell = (
            p["cell"][0].as_i64().unwrap(),
            p["cell"][1].as_i64().unwrap(),
        );
        let (x, y) = depot_centre(cell.0, cell.1);
        let (x_m, y_m) = (p["x_m"].as_f64().unwrap(), p["y_m"].as_f64().unwrap());
        assert!(
            (x_m - x).abs() < 1e-9 && (y_m - y).abs() < 1e-9,
            "{p}: the centre of {cell:?} is ({x}, {y})"
        );
        assert!(
            (250.0..264.4).contains(&x_m) && (111.0..120.0).contains(&y_m),
            "{p}"
        );
    }
    assert!(known > 10, "only {known} located fixes:\n{out}");
}

/// A sink that counts the pipeline swaps the runtime announces (reloads and
/// recalibrations both swap the whole pipeline).
#[derive(Clone, Default)]
struct Swaps(std::sync::Arc<std::sync::atomic::AtomicUsize>);

impl gangway::sink::Sink for Swaps {
    fn name(&self) -> &'static str {
        "swaps"
    }

    fn send(&mut self, _: &[gangway::publish::Output]) -> anyhow::Result<()> {
        Ok(())
    }

    fn reload(&mut self, _: &gangway::site::Building) {
        self.0.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
    }

    fn shutdown(self: Box<Self>) -> futures::future::BoxFuture<'static, anyhow::Result<()>> {
        Box::pin(std::future::ready(Ok(())))
    }
}

/// Polls `done` every 50 ms for up to 60 s.
async fn eventually(what: &str, mut done: impl FnMut() -> bool) {
    for _ in 0..1200 {
        if done() {
            return;
        }
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
    panic!("no {what} within 60 s");
}

/// The daemon gathers what it hears into the learning store and, asked to,
/// recalibrates the survey-free model from it off the event loop, writes the
/// file and serves it (swapped in like a reload); a restart serves it too.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_daemon_recalibrates_from_what_it_heard_and_serves_it() {
    use gangway::daemon::{self, state};
    use gangway::event::Event;
    use gangway::sighting::{BeaconId, Sighting};
    use gangway::source::{ChannelSource, Input};
    use std::sync::atomic::Ordering;

    let dir = tempfile::tempdir().unwrap();
    write(dir.path(), "workshop.toml", SMALL_SITE);
    let store = dir.path().join("learning.sqlite");
    let config = write(
        dir.path(),
        "gangway.toml",
        &format!(
            "gateway_id = \"gw-w\"\nsite = \"workshop.toml\"\n[planner]\nmode = \"astar\"\n\
             [store]\nenabled = true\npath = \"{}\"\n\
             [localizer.recalibration]\nenabled = true\nevery_h = 0\nmin_windows = 100\n",
            store.display()
        ),
    );
    let serving = state::load_at_start(&config).unwrap();
    // Heard in the last minutes: the store prunes what is older than its
    // retention.
    let now = gangway::source::unix_now();
    let recorder = gangway::sink::recorder::Recorder::open(&serving.config.store, now)
        .unwrap()
        .keep_heard(serving.config.localizer.recalibration.max_windows);
    let swaps = Swaps::default();
    let (feed, source) = ChannelSource::new(64);
    let (ask, asked) = tokio::sync::mpsc::channel(1);
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let (_reload, reloads) = tokio::sync::mpsc::channel(1);
    let options = daemon::Options {
        recalibrate: Some(asked),
        ..daemon::Options::default()
    };
    let daemon = tokio::spawn(daemon::run(
        serving,
        options,
        vec![Box::new(source)],
        vec![Box::new(recorder), Box::new(swaps.clone())],
        async {
            let _ = stopped.await;
        },
        reloads,
    ));

    // Two phones pacing the workshop's corridors, each beacon heard once a
    // second when near enough, louder when nearer.
    let uuid = uuid::Uuid::parse_str("0b1c2d3e-4f50-6172-8394-a5b6c7d8e9f0").unwrap();
    let beacons = [(0.0, 0.0), (7.0, 0.0), (0.0, 4.0), (7.0, 4.0)];
    for phone in ["phone-a", "phone-b"] {
        let observer: std::sync::Arc<str> = phone.into();
        let mut events = Vec::new();
        for s in 0..1600u32 {
            let x = f64::from((s / 8 + u32::from(phone == "phone-b") * 3) % 8);
            let y = if (s / 64) % 2 == 0 { 0.0 } else { 4.0 };
            for (minor, (bx, by)) in (1u16..).zip(beacons) {
                let d = 2.0 * ((x - bx) * (x - bx) + (y - by) * (y - by)).sqrt();
                if d > 9.0 || (s + u32::from(minor)) % 3 == 0 {
                    continue;
                }
                events.push(Event::Advert(Sighting {
                    advertiser_mac: None,
                    t: now - 2_000.0 + f64::from(s),
                    observer: observer.clone(),
                    advertiser: BeaconId {
                        uuid,
                        major: 7,
                        minor,
                    },
                    tx_power: None,
                    rssi: (-66.0 - 25.0 * d.max(0.5).log10()) as i16,
                }));
            }
        }
        for batch in events.chunks(64) {
            feed.send(Input::Events(batch.to_vec())).await.unwrap();
        }
    }
    let heard = || {
        gangway::store::Store::open_read_only(&store)
            .and_then(|s| s.heard(10_000, None))
            .map_or(0, |rows| rows.len())
    };
    // Enough that a quarter held out in blocks of 30 windows can judge
    // the fit (`locate::calibrate`).
    eventually("heard windows in the store", || heard() >= 700).await;

    ask.send(()).await.unwrap();
    eventually("the recalibrated pipeline", || {
        swaps.0.load(Ordering::SeqCst) == 1
    })
    .await;
    let file = dir.path().join("calibration.toml");
    let site = gangway::site::Site::load(&dir.path().join("workshop.toml")).unwrap();
    let calibration = gangway::locate::calibration::Calibration::load(&file, &site).unwrap();
    assert_eq!(calibration.anchors.len(), 4);
    assert!(calibration.windows >= 700, "{}", calibration.windows);

    stop.send(()).unwrap();
    let stats = daemon.await.unwrap().unwrap().stats;
    assert_eq!(stats.reload_failures, 0);
    // A restart serves what was learned.
    let restarted = state::load_at_start(&config).unwrap();
    assert_eq!(
        restarted.config.localizer.pathloss.calibration.as_deref(),
        Some(file.as_path())
    );
}

/// The five-floor mall's walks (`../shared`), and its plans imported into
/// `dir` as a building: `None` without the data.
fn imported_mall(dir: &std::path::Path) -> Option<(String, String)> {
    let site1 = common::shared_data("indoor-location-competition-20/site1")?;
    let site1 = site1.to_str().unwrap().to_owned();
    let building = dir.join("mall.toml").to_str().unwrap().to_owned();
    gangway_ok(&["site", "import", "--geojson", &site1, "--out", &building]);
    Some((site1, building))
}

/// `eval localization`'s arguments for the imported mall's walks, then `more`.
fn on_the_mall<'a>(building: &'a str, site1: &'a str, more: &[&'a str]) -> Vec<&'a str> {
    [&["--site", building, "--walks", site1][..], more].concat()
}

/// The five-floor mall: its plans imported as a building, its walks split by
/// time (the later 30% of each floor's held out), located floor by floor
/// with the surveyed k-NN beside the plain k-NN regressor baseline on the
/// same split (BENCHMARKS.md, "Floors"), each window's floor decided by
/// the gateway's own floor tracks. Guards what is reached: the floor told
/// apart at least as often as the baseline does, and the published
/// confidence (times the floor's probability) as honest as it is. The
/// issue's targets (floor ≥ 97%, error on the right floor 15% below the
/// baseline's) are not met; the figures are printed, not gated. `--rows`
/// writes the windows those figures were counted from.
#[test]
fn the_mall_s_floors_are_told_apart_at_least_as_well_as_the_baseline() {
    let dir = tempfile::tempdir().unwrap();
    let Some((site1, building)) = imported_mall(dir.path()) else {
        return;
    };
    let (site1, building) = (site1.as_str(), building.as_str());
    let rows = dir.path().join("rows.csv");
    let v = eval(&on_the_mall(
        building,
        site1,
        &["--method", "knn", "--rows", rows.to_str().unwrap()],
    ));
    let mut windows = csv::Reader::from_path(&rows).unwrap();
    let header = windows.headers().unwrap().clone();
    let column = |name: &str| header.iter().position(|h| h == name).unwrap();
    let (floor, walk, located, known, error) = (
        column("floor"),
        column("walk"),
        column("located_floor"),
        column("floor_known"),
        column("error_m"),
    );
    let (mut count, mut right, mut error_sum) = (0usize, 0usize, 0.0f64);
    for window in windows.records() {
        let window = window.unwrap();
        assert!(!window[walk].is_empty(), "{window:?}");
        assert_eq!(
            window[error].is_empty(),
            window[floor] != window[located],
            "an error only on the walk's floor: {window:?}"
        );
        count += 1;
        if window[floor] == window[located] && &window[known] == "true" {
            right += 1;
            error_sum += window[error].parse::<f64>().unwrap();
        }
    }
    assert_eq!(count as f64, figure(&v, "fixes"), "one row per fix");
    assert!((right as f64 / count as f64 - figure(&v, "floor_accuracy")).abs() < 1e-9);
    assert!((error_sum / right as f64 - figure(&v, "mean_error_m")).abs() < 0.01);
    let baseline = &v["baseline"];
    println!(
        "mall, knn: floor {:.3} (baseline {:.3}), mean {:.1} m (baseline {:.1} m) over {} fixes",
        figure(&v, "floor_accuracy"),
        figure(baseline, "floor_accuracy"),
        figure(&v, "mean_error_m"),
        figure(baseline, "mean_error_m"),
        figure(&v, "fixes"),
    );
    assert!(figure(&v, "fixes") >= 1_000.0, "{v}");
    assert_eq!(figure(&v, "fixes"), figure(baseline, "fixes"), "same split");
    assert!(
        figure(&v, "floor_accuracy") >= figure(baseline, "floor_accuracy"),
        "{v}"
    );
    // Measured with the gateway's own floor rules since 2026-12-05 (a
    // floor published as unknown counts as wrong): 0.771.
    assert!(figure(&v, "floor_accuracy") >= 0.76, "reached 0.771: {v}");
    assert!(
        figure(&v, "confidence_gap_max") <= 0.08,
        "reached 0.063: {v}"
    );
}

/// The mall served survey-free: each floor's beacons placed from its
/// training walks, and its radio model recalibrated from what those walks
/// heard (positions unused), as the gateway's recalibration fits what it
/// hears on each floor. Guards what is reached (BENCHMARKS.md, "Floors"):
/// the error on the right floor no worse than the k-NN regressor's, mean,
/// median and p90 alike; without the recalibration the median is 5% above
/// the baseline's. Its published confidence is as honest as reached (mean
/// gap over fixes 0.085; 0.161 while a calibration narrowed the rehearsal's
/// doubt).
#[test]
fn the_mall_served_survey_free_and_recalibrated_is_no_worse_than_the_baseline() {
    let dir = tempfile::tempdir().unwrap();
    let Some((site1, building)) = imported_mall(dir.path()) else {
        return;
    };
    let (site1, building) = (site1.as_str(), building.as_str());
    eval_refused(
        &on_the_mall(building, site1, &["--method", "knn", "--recalibrate"]),
        "give --method pathloss",
    );
    // The daemon's default waits for 2,000 windows; a floor's training walks
    // hold 1,000–1,700. Cells off: the same figures to 0.03 m, a third faster.
    let config = write(
        dir.path(),
        "gangway.toml",
        "gateway_id = \"mall\"\nsite = \"mall.toml\"\n\
         [localizer.recalibration]\nmin_windows = 500\ncells = false\n",
    );
    let v = eval(&on_the_mall(
        building,
        site1,
        &[
            "--method",
            "pathloss",
            "--recalibrate",
            "--config",
            config.to_str().unwrap(),
        ],
    ));
    let baseline = &v["baseline"];
    for key in ["mean_error_m", "median_error_m", "p90_error_m"] {
        println!(
            "mall, pathloss recalibrated: {key} {:.2} (baseline {:.2})",
            figure(&v, key),
            figure(baseline, key)
        );
        assert!(figure(&v, key) <= figure(baseline, key), "{key}: {v}");
    }
    assert!(figure(&v, "confidence_gap_mean") <= 0.10, "{v}");
    let floors = v["recalibrated"].as_object().unwrap();
    assert_eq!(floors.len(), 5, "{v}");
    for (floor, said) in floors {
        let said = said.as_str().unwrap();
        assert!(!said.starts_with("the defaults kept"), "{floor}: {said}");
    }
}

/// `[localizer] device_gains`: a phone 8 dB deafer than the model (the world
/// simulated with beacons 8 dB quieter than the config says), replayed
/// through the gateway's pipeline on the office site, is found closer once
/// its gain is learned than with every window read as heard (measured 4.81
/// → 3.98 m over 20 minutes a walker; 4.90 → 4.65 m over 7.5: learning
/// takes a few hundred windows); and a phone the model describes is found
/// as well as without (3.40 m both).
#[test]
fn a_deaf_phone_is_found_closer_once_its_gain_is_learned() {
    let dir = tempfile::tempdir().unwrap();
    let site = common::root().join("fixtures/sites/office.toml");
    let site = site.to_str().unwrap();
    let mean_error_m = |world_tx_dbm: f64, gains: bool| {
        let world = write(
            dir.path(),
            "world.toml",
            &format!(
                "gateway_id = \"world\"\nsite = \"{site}\"\n[localizer.pathloss]\ntx_power_dbm = {world_tx_dbm:.1}\n"
            ),
        );
        let log = dir.path().join("walks.jsonl");
        gangway_ok(&[
            "simulate",
            "--site",
            site,
            "--out",
            log.to_str().unwrap(),
            "--walkers",
            "3",
            "--duration",
            "2400",
            "--config",
            world.to_str().unwrap(),
        ]);
        let config = write(
            dir.path(),
            "gangway.toml",
            &format!(
                "gateway_id = \"gw\"\nsite = \"{site}\"\n[planner]\nmode = \"astar\"\n[localizer]\nmethod = \"pathloss\"\ndevice_gains = {gains}\n"
            ),
        );
        let out = gangway_ok(&[
            "replay",
            log.to_str().unwrap(),
            "--config",
            config.to_str().unwrap(),
            "--score",
            "--json",
        ]);
        let score: Value = serde_json::from_str(out.lines().last().unwrap()).unwrap();
        score["mean_error_m"].as_f64().unwrap()
    };
    let (deaf_without, deaf_with) = (mean_error_m(-67.0, false), mean_error_m(-67.0, true));
    eprintln!(
        "8 dB deafer phone: mean error {deaf_without:.2} m without gains, {deaf_with:.2} m with"
    );
    assert!(
        deaf_with < 0.9 * deaf_without,
        "{deaf_with:.2} m with gains, {deaf_without:.2} m without"
    );
    let (as_model_without, as_model_with) = (mean_error_m(-59.0, false), mean_error_m(-59.0, true));
    eprintln!("a phone as the model: {as_model_without:.2} m without, {as_model_with:.2} m with");
    assert!(
        as_model_with <= 1.02 * as_model_without,
        "{as_model_with:.2} m with gains, {as_model_without:.2} m without"
    );
}
