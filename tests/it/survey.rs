//! `gangway survey import` on one real floor of the mall in
//! `../shared/data/indoor-location-competition-20`: the site it writes passes
//! `gangway check`, its survey loads and `gangway eval localization` runs on
//! the two.

use serde_json::Value;

use crate::common::{self, gangway, gangway_ok, write};

#[test]
fn a_real_floor_imports_into_a_site_and_survey_the_gateway_accepts() {
    let Some(floor) = common::shared_data("indoor-location-competition-20/site1/F1") else {
        return;
    };
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("f1");
    let (floor, out_s) = (floor.to_str().unwrap(), out.to_str().unwrap());
    let report: Value = serde_json::from_str(&gangway_ok(&[
        "survey",
        "import",
        "--floor-dir",
        floor,
        "--out",
        out_s,
        "--json",
    ]))
    .unwrap();
    let count = |key: &str| {
        report[key]
            .as_u64()
            .unwrap_or_else(|| panic!("{key}: {report}"))
    };
    // The README's counts of this floor, and what a 240 × 176 m floor is at 1 m.
    assert_eq!(count("walks"), 106);
    assert_eq!(count("readings"), 21_068);
    assert_eq!(count("lines_skipped"), 0);
    assert_eq!(count("cells"), 240 * 177);
    assert!(
        (3_000..30_000).contains(&count("walkable_cells")),
        "{report}"
    );
    assert!(count("places") >= 100, "{report}");
    // The 9195B3AD…/0/0 id of hundreds of MACs all over the floor is one
    // beacon per MAC: most of the floor's readings are kept.
    assert!(count("shared_ids_split") >= 1, "{report}");
    assert!(count("readings_kept") > 20_000, "{report}");
    assert_eq!(
        count("readings_kept") + count("rare_readings_dropped"),
        21_068
    );
    assert!(count("beacons") >= 50, "{report}");
    assert!(count("rows") >= 50, "{report}");
    let refused: u64 = report["refused"]
        .as_object()
        .unwrap()
        .values()
        .map(|v| v.as_u64().unwrap())
        .sum();
    assert!(refused < count("rows"), "{report}");

    // `gangway check` accepts the site, floor plan included.
    let config = write(
        &out,
        "gangway.toml",
        "gateway_id = \"gw\"\nsite = \"site.toml\"\n",
    );
    let checked = gangway(&["check", "--config", config.to_str().unwrap()]);
    assert!(
        checked.status.success(),
        "{}",
        String::from_utf8_lossy(&checked.stderr)
    );
    let site = std::fs::read_to_string(out.join("site.toml")).unwrap();
    assert!(
        site.contains("[floorplan]\nimage = \"floor_image.png\""),
        "{site}"
    );
    assert!(site.contains("\"EYES MARK\" = ["), "a shop is a place");

    // The survey loads and the evaluation runs on the two (k-NN, one seed:
    // `auto` cross-validates every surveyed method over the floor's hundreds
    // of MAC-distinct beacons, minutes that prove nothing more here).
    let (site, survey) = (out.join("site.toml"), out.join("survey.csv"));
    let eval: Value = serde_json::from_str(&gangway_ok(&[
        "eval",
        "localization",
        "--site",
        site.to_str().unwrap(),
        "--survey",
        survey.to_str().unwrap(),
        "--split",
        "session",
        "--method",
        "knn",
        "--seeds",
        "1",
        "--json",
    ]))
    .unwrap();
    let mean = eval["mean_error_m"].as_f64().unwrap();
    assert!(mean.is_finite() && mean >= 0.0, "{eval}");

    // Importing again replaces what the first import wrote.
    gangway_ok(&["survey", "import", "--floor-dir", floor, "--out", out_s]);
}

#[test]
fn a_floor_without_its_files_is_named() {
    let dir = tempfile::tempdir().unwrap();
    let out = gangway(&[
        "survey",
        "import",
        "--floor-dir",
        dir.path().to_str().unwrap(),
        "--out",
        dir.path().join("out").to_str().unwrap(),
    ]);
    assert!(!out.status.success());
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("floor_info.json: cannot read"), "{stderr}");
}

/// A walk file of this dataset's layout: one walker along y = 1.5 m from
/// x = 1 to 9 m at 1 m/s, hearing beacon `A` (at x 2 m), `B` (x 8 m) and two
/// transmitters sharing the id `C` (x 1 m and x 11 m), then a waypoint a
/// minute later; one line is broken.
fn walk() -> String {
    const UUID: &str = "9195B3AD-A9D0-4500-85FF-9FB0F65A5201";
    let mut text = String::from("#\tstartTime:1000\n1000\tTYPE_WAYPOINT\t1.0\t1.5\n");
    for k in 0..=32 {
        let ms = 1000 + k * 250;
        let x = 1.0 + f64::from(k) / 4.0;
        for (minor, mac, at) in [(1, "AA:00:00:00:00:01", 2.0), (2, "AA:00:00:00:00:02", 8.0)]
            .into_iter()
            .chain([
                (3, "AA:00:00:00:00:03", 1.0),
                (3, "AA:00:00:00:00:04", 11.0),
            ])
        {
            let rssi = -50 - (3.0 * f64::abs(x - at)).round() as i32;
            text +=
                &format!("{ms}\tTYPE_BEACON\t{UUID}\t7\t{minor}\t-56\t{rssi}\t1.0\t{mac}\t{ms}\n");
        }
    }
    text += &format!("5000\tTYPE_BEACON\t{UUID}\t7\t1\t-56\tloud\t1.0\tAA:00:00:00:00:01\t5000\n");
    text += "9000\tTYPE_WAYPOINT\t9.0\t1.5\n70000\tTYPE_WAYPOINT\t9.0\t2.5\n";
    text += &format!("40000\tTYPE_BEACON\t{UUID}\t7\t1\t-56\t-70\t1.0\tAA:00:00:00:00:01\t40000\n");
    text
}

#[test]
fn a_floor_drawn_in_metres_imports_and_one_bad_line_is_skipped() {
    let dir = tempfile::tempdir().unwrap();
    let floor = dir.path().join("G");
    std::fs::create_dir_all(floor.join("path_data_files")).unwrap();
    write(
        &floor,
        "floor_info.json",
        r#"{"map_info": {"width": 12.0, "height": 6.0}}"#,
    );
    write(
        &floor,
        "geojson_map.json",
        r#"{"type": "FeatureCollection", "features": [
  {"type": "Feature", "properties": {"type": "floor"}, "geometry": {"type": "Polygon",
    "coordinates": [[[0, 0], [12, 0], [12, 6], [0, 6], [0, 0]]]}},
  {"type": "Feature", "properties": {"name": "kiosk"}, "geometry": {"type": "Polygon",
    "coordinates": [[[8, 3], [12, 3], [12, 6], [8, 6], [8, 3]]]}},
  {"type": "Feature", "properties": {"id": "room-7"}, "geometry": {"type": "Polygon",
    "coordinates": [[[0, 4], [3, 4], [3, 6], [0, 6], [0, 4]]]}}
]}"#,
    );
    write(&floor.join("path_data_files"), "walk.txt", &walk());
    let out = dir.path().join("out");
    let run = gangway(&[
        "survey",
        "import",
        "--floor-dir",
        floor.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--json",
    ]);
    let stderr = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "{stderr}");
    assert!(
        stderr.contains("walk.txt:135: field `rssi`: \"loud\" is not an RSSI"),
        "{stderr}"
    );
    let report: Value = serde_json::from_slice(&run.stdout).unwrap();
    let count = |key: &str| {
        report[key]
            .as_u64()
            .unwrap_or_else(|| panic!("{key}: {report}"))
    };
    assert_eq!(count("lines_skipped"), 1);
    assert_eq!((count("walks"), count("waypoints")), (1, 3));
    assert_eq!((count("cells"), count("walkable_cells")), (72, 72 - 12 - 6));
    assert_eq!((count("beacons"), count("shared_ids_split")), (4, 1));
    assert!(count("rows") >= 3, "{report}");
    // The reading at 40 s sits between waypoints a minute apart.
    assert_eq!(report["refused"]["waypoint_gap"], 1, "{report}");

    let site = std::fs::read_to_string(out.join("site.toml")).unwrap();
    assert!(site.contains("kiosk = [9, 3]"), "{site}");
    assert!(site.contains("room-7 = ["), "{site}");
    assert!(site.contains("id = \"b-9195b3ad-7-1\""), "{site}");
    let survey = std::fs::read_to_string(out.join("survey.csv")).unwrap();
    assert!(
        survey.starts_with(
            "x_m,y_m,t,b-9195b3ad-7-1,b-9195b3ad-7-2,b-9195b3ad-7-3-aa0000000003,\
             b-9195b3ad-7-3-aa0000000004\n"
        ),
        "{survey}"
    );
    // The two transmitters of `C` each where they were heard loudest.
    assert!(site.contains("mac = \"AA:00:00:00:00:03\""), "{site}");
    let beacon_c2 = site.split("mac = \"AA:00:00:00:00:04\"").next().unwrap();
    let x: f64 = beacon_c2
        .rsplit("pos = [")
        .next()
        .unwrap()
        .split(',')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    assert!(x >= 8.0, "{site}");
    let beacon_a = site.split("minor = 1\npos = [").nth(1).unwrap();
    let x: f64 = beacon_a.split(',').next().unwrap().parse().unwrap();
    assert!((1.0..=3.0).contains(&x), "{site}");
    // How loudly the floor hears `B`, the floor evidence of a building:
    // its readings' power per second walked (the waypoints span 69 s).
    let mw: f64 = (0..=32)
        .map(|k| {
            let x = 1.0 + f64::from(k) / 4.0;
            10f64.powf((-50.0 - (3.0 * (x - 8.0).abs()).round()) / 10.0)
        })
        .sum();
    let beacon_b = site.split("minor = 2\n").nth(1).unwrap();
    let heard_dbm: f64 = beacon_b
        .split("heard_dbm = ")
        .nth(1)
        .and_then(|rest| rest.lines().next())
        .unwrap_or_else(|| panic!("no heard_dbm: {site}"))
        .parse()
        .unwrap();
    let expected = 10.0 * (mw / 69.0).log10();
    assert!(
        (heard_dbm - expected).abs() < 0.006,
        "{heard_dbm} {expected}"
    );
}
