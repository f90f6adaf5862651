//! Routes across floors (`plan::floors`, `gangway plan` on a building):
//! on a building made here (three floors of half-metre cells, one reached
//! only by a lift, stairs and an escalator between the other two), and over
//! every pair of places on different floors of the real five-floor mall.

use crate::common;

mod mall;

use std::path::Path;
use std::sync::Arc;
use std::time::Instant;

use gangway::plan::floors::{BuildingPlanner, FloorCell, FloorsRoute};
use gangway::plan::{Connectivity, Destination, Planner, Profile, RouteErrorCode, astar::AStar};
use gangway::publish::floors::FloorsRouteBody;
use gangway::site::{Building, Site, SiteError};

const PROFILES: [Profile; 3] = [Profile::Default, Profile::Wheelchair, Profile::LowVision];

/// Ground (level 0), F1 (1) and F2 (2) at 0.5 m cells: a lift joins Ground
/// and F2 only, stairs and an escalator Ground and F1, so F2 is the lift's
/// alone and F1 has no step-free way in.
const BUILDING: &str = r#"
name = "annex"
[[floors]]
name = "Ground"
level = 0
site = "ground.toml"
[[floors]]
name = "F1"
level = 1
site = "f1.toml"
[[floors]]
name = "F2"
level = 2
site = "f2.toml"
[[connectors]]
id = "lift A"
kind = "lift"
stops = [{ floor = "Ground", cell = [14, 1] }, { floor = "F2", cell = [14, 1] }]
[[connectors]]
id = "west stairs"
kind = "stairs"
stops = [{ floor = "Ground", cell = [1, 5] }, { floor = "F1", cell = [1, 5] }]
[[connectors]]
id = "escalator"
kind = "escalator"
stops = [{ floor = "Ground", cell = [8, 5] }, { floor = "F1", cell = [8, 5] }]
"#;

fn floor_text(name: &str) -> String {
    let (map, places) = match name {
        "ground.toml" => (
            "################\n################\n####....########\n\
             ####....########\n################\n################",
            "entrance = [0, 0]\ncafe = [15, 5]\n\"help desk\" = [9, 1]",
        ),
        "f1.toml" => (
            "################\n################\n######..########\n\
             ######..########\n################\n################",
            "shop = [12, 3]\ntoilets = [2, 2]",
        ),
        _ => (
            "################\n#######.########\n#######.########\n\
             #######.########\n################\n################",
            "roof = [10, 5]\ngym = [3, 1]",
        ),
    };
    format!("name = \"{name}\"\ncell_m = 0.5\nmap = '''\n{map}\n'''\n[places]\n{places}\n")
}

fn annex() -> Arc<Building> {
    let load = |path: &Path| {
        let name = path.file_name().unwrap().to_string_lossy().into_owned();
        Site::parse(&floor_text(&name), path).map_err(|e: SiteError| e)
    };
    Arc::new(Building::parse(BUILDING, Path::new("annex/building.toml"), load).unwrap())
}

/// The geometric planner of every floor: A*, as `gangway plan` uses.
fn planner(building: Arc<Building>) -> BuildingPlanner {
    let floors = building
        .floors()
        .iter()
        .map(|f| Box::new(AStar::new(f.site.clone(), Connectivity::Eight)) as Box<dyn Planner>)
        .collect();
    BuildingPlanner::new(building, Connectivity::Eight, floors)
}

fn place(planner: &BuildingPlanner, floor: &str, name: &str) -> FloorCell {
    planner
        .resolve(Some(floor), &Destination::Place(name.to_owned()))
        .unwrap()
}

/// Why `route` is not a walkable route from `from` to `to` for `profile`:
/// a leg failing validation, legs that do not meet the connectors' stops,
/// or a connector the profile may not use.
fn problem(
    building: &Building,
    route: &FloorsRoute,
    from: FloorCell,
    to: FloorCell,
    profile: Profile,
) -> Option<String> {
    if route.legs.len() != route.rides.len() + 1 {
        return Some("legs and rides do not alternate".into());
    }
    let mut here = from;
    for (i, leg) in route.legs.iter().enumerate() {
        let end = match route.rides.get(i) {
            Some(ride) => FloorCell {
                floor: ride.from.floor,
                cell: ride.from.cell,
            },
            None => to,
        };
        if leg.floor != here.floor || leg.floor != end.floor {
            return Some(format!("leg {i} is on the wrong floor"));
        }
        let site = &building.floors()[leg.floor].site;
        if let Err(e) =
            leg.planned
                .route
                .validate_for(site, here.cell, end.cell, Connectivity::Eight, profile)
        {
            return Some(format!("leg {i}: {e}"));
        }
        if let Some(ride) = route.rides.get(i) {
            let kind = building.connectors()[ride.connector].kind;
            if profile.connector_factor(kind).is_none() {
                return Some(format!("takes the {} as {profile:?}", kind.name()));
            }
            here = FloorCell {
                floor: ride.to.floor,
                cell: ride.to.cell,
            };
        }
    }
    None
}

/// Routes between every place and every place on another floor, for every
/// profile, with at most `per_floor` places of each floor taken evenly in
/// name order (the mall's 1,286 places would make 3.2 million requests):
/// (pairs, invalid, wheelchair routes with steps, no step-free route, plan
/// times in µs).
fn every_pair(
    planner: &BuildingPlanner,
    per_floor: usize,
) -> (usize, usize, usize, usize, Vec<u64>) {
    let building = planner.building();
    let places: Vec<FloorCell> = building
        .floors()
        .iter()
        .enumerate()
        .flat_map(|(floor, f)| {
            let places = f.site.places();
            let step = places.len().div_ceil(per_floor).max(1);
            places
                .values()
                .step_by(step)
                .map(move |&cell| FloorCell { floor, cell })
        })
        .collect();
    let (mut pairs, mut invalid, mut violations, mut no_step_free) = (0, 0, 0, 0);
    let mut times = Vec::new();
    for &from in &places {
        for &to in places.iter().filter(|p| p.floor != from.floor) {
            for profile in PROFILES {
                pairs += 1;
                let started = Instant::now();
                let planned = planner.plan(from, to, profile);
                times.push(started.elapsed().as_micros() as u64);
                match planned {
                    Ok(route) => {
                        if let Some(why) = problem(building, &route, from, to, profile) {
                            eprintln!("{from:?} → {to:?} {profile:?}: {why}");
                            invalid += 1;
                            violations += usize::from(profile == Profile::Wheelchair);
                        }
                    }
                    Err(e) if e.code() == RouteErrorCode::NoStepFreeRoute => no_step_free += 1,
                    Err(e) => {
                        eprintln!("{from:?} → {to:?} {profile:?}: {e}");
                        invalid += 1;
                    }
                }
            }
        }
    }
    times.sort_unstable();
    (pairs, invalid, violations, no_step_free, times)
}

fn quantile(sorted: &[u64], q: f64) -> u64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

#[test]
fn a_wheelchair_takes_the_lift_and_walkers_the_quicker_way() {
    let planner = planner(annex());
    let building = planner.building();
    let (entrance, roof) = (
        place(&planner, "Ground", "entrance"),
        place(&planner, "F2", "roof"),
    );
    let route = planner.plan(entrance, roof, Profile::Wheelchair).unwrap();
    assert_eq!(
        problem(building, &route, entrance, roof, Profile::Wheelchair),
        None
    );
    let taken: Vec<&str> = route
        .rides
        .iter()
        .map(|r| building.connectors()[r.connector].id.as_str())
        .collect();
    assert_eq!(taken, ["lift A"]);
    // From F1 to F2: down to Ground by stairs or escalator, then the lift.
    let shop = place(&planner, "F1", "shop");
    let route = planner.plan(shop, roof, Profile::Default).unwrap();
    assert_eq!(
        problem(building, &route, shop, roof, Profile::Default),
        None
    );
    let kinds: Vec<&str> = route
        .rides
        .iter()
        .map(|r| building.connectors()[r.connector].kind.name())
        .collect();
    assert_eq!(kinds.len(), 2, "{kinds:?}");
    assert_eq!(kinds[1], "lift");
    // The time is the walk at 1.2 m/s plus the rides.
    let ridden: f64 = route.rides.iter().map(|r| r.seconds).sum();
    assert!((route.total_s - route.length_m() / 1.2 - ridden).abs() < 1e-9);
    // On one floor, one leg.
    let cafe = place(&planner, "Ground", "cafe");
    let route = planner.plan(entrance, cafe, Profile::Wheelchair).unwrap();
    assert_eq!((route.legs.len(), route.rides.len()), (1, 0));
}

#[test]
fn stairs_alone_give_a_wheelchair_no_step_free_route_never_a_staircase() {
    let planner = planner(annex());
    let (entrance, shop) = (
        place(&planner, "Ground", "entrance"),
        place(&planner, "F1", "shop"),
    );
    let err = planner
        .plan(entrance, shop, Profile::Wheelchair)
        .unwrap_err();
    assert_eq!(err.code(), RouteErrorCode::NoStepFreeRoute);
    let message = err.to_string();
    assert!(
        message.contains("Ground [0, 0]") && message.contains("F1 [12, 3]"),
        "{message}"
    );
    assert!(message.contains("a lift or a ramp"), "{message}");
    assert!(
        message.contains("`west stairs`") || message.contains("`escalator`"),
        "{message}"
    );
    // Walkers take them.
    for profile in [Profile::Default, Profile::LowVision] {
        planner.plan(entrance, shop, profile).unwrap();
    }
}

#[test]
fn instructions_name_the_lift_the_floor_and_leaving_it() {
    let planner = planner(annex());
    let (desk, roof) = (
        place(&planner, "Ground", "help desk"),
        place(&planner, "F2", "roof"),
    );
    let route = planner.plan(desk, roof, Profile::Wheelchair).unwrap();
    let body = FloorsRouteBody::new(&planner, Profile::Wheelchair, &route, 0);
    let texts: Vec<String> = body
        .instructions
        .iter()
        .map(|s| format!("{}: {}", s.floor, s.instruction.text))
        .collect();
    let at = |needle: &str| {
        texts
            .iter()
            .position(|t| t.contains(needle))
            .unwrap_or_else(|| panic!("no {needle:?} in {texts:#?}"))
    };
    let walk = at("to the lift.");
    let take = at("Ground: Take the lift to F2.");
    let leave = at("F2: Leave the lift on F2.");
    let arrive = at("you have arrived at roof.");
    assert!(walk < take && take < leave && leave < arrive, "{texts:#?}");
    assert_eq!(arrive, texts.len() - 1);
    assert!(texts.iter().all(|t| !t.contains("stairs")), "{texts:#?}");
    // Each leg carries its own part, and the reply the connector.
    assert_eq!(body.legs.len(), 2);
    assert_eq!(body.connectors[0].kind, "lift");
    assert_eq!(body.connectors[0].to.floor, "F2");
    let json = serde_json::to_value(&body).unwrap();
    assert_eq!(json["legs"][1]["floor"], "F2");
    assert_eq!(json["legs"][1]["level"], 2);
    assert!(json["legs"][0]["waypoints"].as_array().unwrap().len() > 1);
    // Stairs say which way.
    let shop = place(&planner, "F1", "shop");
    let route = planner.plan(shop, desk, Profile::Default).unwrap();
    let body = FloorsRouteBody::new(&planner, Profile::Default, &route, 0);
    assert!(
        body.instructions.iter().any(|s| {
            s.instruction.text == "Take the stairs down to Ground."
                || s.instruction.text == "Take the escalator down to Ground."
        }),
        "{:#?}",
        body.instructions
    );
}

#[test]
fn every_pair_of_places_on_different_floors_gets_a_valid_route() {
    let planner = planner(annex());
    let (pairs, invalid, violations, no_step_free, _) = every_pair(&planner, usize::MAX);
    assert_eq!((invalid, violations), (0, 0), "of {pairs}");
    // Only F1's two places have no step-free way in: each with the four on
    // the other floors, both ways.
    assert_eq!(no_step_free, 2 * 2 * 5);
}

#[test]
fn a_place_without_its_floor_is_found_on_its_floor_and_a_cell_needs_one() {
    let planner = planner(annex());
    let roof = planner
        .resolve(None, &Destination::Place("roof".into()))
        .unwrap();
    assert_eq!(planner.building().floors()[roof.floor].name, "F2");
    let err = planner
        .resolve(None, &Destination::Cell([1, 1]))
        .unwrap_err();
    assert_eq!(err.code(), RouteErrorCode::UnknownPlace);
    assert!(err.to_string().contains("`Ground`, `F1`, `F2`"), "{err}");
    let err = planner
        .resolve(Some("F9"), &Destination::Place("roof".into()))
        .unwrap_err();
    assert!(err.to_string().contains("unknown floor `F9`"), "{err}");
}

#[test]
fn gangway_plan_routes_across_floors_and_keeps_one_floor_sites() {
    let dir = tempfile::tempdir().unwrap();
    let building = common::write(dir.path(), "building.toml", BUILDING);
    for name in ["ground.toml", "f1.toml", "f2.toml"] {
        common::write(dir.path(), name, &floor_text(name));
    }
    let site = building.to_str().unwrap();
    let out = common::gangway_ok(&[
        "plan",
        "--site",
        site,
        "--from",
        "Ground:entrance",
        "--to",
        "F2:roof",
        "--profile",
        "wheelchair",
        "--json",
    ]);
    let reply: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(reply["legs"].as_array().unwrap().len(), 2, "{reply}");
    assert_eq!(reply["connectors"][0]["id"], "lift A");
    assert_eq!(reply["from"]["floor"], "Ground");
    assert!(reply["total_s"].as_f64().unwrap() > 0.0);
    assert!(reply["length_m"].as_f64().unwrap() > 0.0);
    let texts: Vec<&str> = reply["instructions"]
        .as_array()
        .unwrap()
        .iter()
        .map(|s| s["text"].as_str().unwrap())
        .collect();
    assert!(texts.contains(&"Take the lift to F2."), "{texts:?}");
    // A place on one floor needs no floor; a cell does.
    let text = common::gangway_ok(&["plan", "--site", site, "--from", "cafe", "--to", "F1:0,0"]);
    assert!(text.contains("- Ground: "), "{text}");
    let out = common::gangway(&[
        "plan",
        "--site",
        site,
        "--from",
        "entrance",
        "--to",
        "shop",
        "--profile",
        "wheelchair",
    ]);
    assert!(!out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("no step-free route"), "{err}");
    // A one-floor site answers as before, its floor prefix optional.
    let one = common::write(dir.path(), "one.toml", &floor_text("ground.toml"));
    let one = one.to_str().unwrap();
    let plain = common::gangway_ok(&[
        "plan", "--site", one, "--from", "entrance", "--to", "cafe", "--json",
    ]);
    let prefixed = common::gangway_ok(&[
        "plan",
        "--site",
        one,
        "--from",
        "ground.toml:entrance",
        "--to",
        "cafe",
        "--json",
    ]);
    let route =
        |out: &str| serde_json::from_str::<serde_json::Value>(out).unwrap()["waypoints"].clone();
    assert_eq!(route(&plain), route(&prefixed));
    assert!(plain.contains("\"planner\""));
}

/// Places per floor of the mall whose routes to every other floor's are
/// planned: 24 of each floor's 123–711 makes about 35,000 requests.
const PLACES_PER_FLOOR: usize = 24;

/// Every pair of sampled places on different floors of the real mall, every
/// profile: all valid, no wheelchair route over steps, and the plan time
/// (BENCHMARKS.md, "Routes across floors"; run with `--nocapture`).
#[test]
fn every_pair_of_places_on_different_floors_of_the_mall() {
    let Some(site1) = common::shared_data("indoor-location-competition-20/site1") else {
        return;
    };
    let work = tempfile::tempdir().unwrap();
    let started = Instant::now();
    let planner = planner(Arc::new(mall::building(&site1, work.path())));
    let built_s = started.elapsed().as_secs_f64();
    let (pairs, invalid, violations, no_step_free, times) = every_pair(&planner, PLACES_PER_FLOOR);
    println!(
        "mall across floors: {pairs} requests ({PLACES_PER_FLOOR} places per floor × places on other floors × 3 profiles), \
         {invalid} invalid, {violations} wheelchair violations, {no_step_free} no_step_free_route; \
         plan p50 {} µs, p99 {} µs, max {} µs; planner built in {built_s:.1} s",
        quantile(&times, 0.5),
        quantile(&times, 0.99),
        times[times.len() - 1],
    );
    assert_eq!((invalid, violations, no_step_free), (0, 0, 0));
}

/// A building whose two floors have the same grid (the sample site's), the
/// sample's trained models copied under `models/G/` only, and a config
/// naming models per floor: G's legs come from its learned planner, L1's
/// from A* (it has none), and `gangway check` says so floor by floor. A
/// mode that reads one model for every floor is refused, naming the key.
#[test]
fn each_floor_is_planned_by_its_own_models_where_the_config_names_them() {
    let dir = tempfile::tempdir().unwrap();
    let sample = std::fs::read_to_string(common::root().join("config/sites/waldo.toml")).unwrap();
    common::write(dir.path(), "G.toml", &sample);
    common::write(dir.path(), "L1.toml", &sample);
    common::write(
        dir.path(),
        "library.toml",
        "name = \"library\"\n\
         [[floors]]\nname = \"G\"\nlevel = 0\nsite = \"G.toml\"\n\
         [[floors]]\nname = \"L1\"\nlevel = 1\nsite = \"L1.toml\"\n\
         [[connectors]]\nid = \"lift\"\nkind = \"lift\"\n\
         stops = [{ floor = \"G\", cell = [9, 9] }, { floor = \"L1\", cell = [9, 9] }]\n",
    );
    let models = dir.path().join("models/G");
    std::fs::create_dir_all(&models).unwrap();
    for model in ["generator", "path_classifier", "conditional_generator"] {
        let file = format!("{model}.onnx");
        std::fs::copy(
            common::root().join("models").join(&file),
            models.join(&file),
        )
        .unwrap();
    }
    let config = common::write(
        dir.path(),
        "gangway.toml",
        "gateway_id = \"gw\"\nsite = \"library.toml\"\n[planner.models]\n\
         generator = \"models/{floor}/generator.onnx\"\n\
         path_classifier = \"models/{floor}/path_classifier.onnx\"\n\
         conditional_generator = \"models/{floor}/conditional_generator.onnx\"\n",
    );
    let config = config.to_str().unwrap();
    let reply = common::gangway_ok(&[
        "plan",
        "--config",
        config,
        "--from",
        "G:west entrance",
        "--to",
        "L1:east entrance",
        "--json",
    ]);
    let reply: serde_json::Value = serde_json::from_str(&reply).unwrap();
    let planners: Vec<(&str, &str)> = reply["legs"]
        .as_array()
        .unwrap()
        .iter()
        .map(|leg| {
            (
                leg["floor"].as_str().unwrap(),
                leg["planner"].as_str().unwrap(),
            )
        })
        .collect();
    // The sample's models serve its conditional generator (README).
    assert_eq!(planners, [("G", "conditional"), ("L1", "astar")], "{reply}");

    let stdout = common::gangway_ok(&["check", "--config", config]);
    let planner_lines: Vec<&str> = stdout
        .lines()
        .filter(|l| l.starts_with("planner:"))
        .collect();
    assert_eq!(planner_lines.len(), 2, "{stdout}");
    assert!(
        planner_lines[0].starts_with("planner: conditional serves"),
        "{stdout}"
    );
    assert!(
        planner_lines[1].starts_with("planner: astar serves"),
        "{stdout}"
    );

    // The desire lines named once for both floors: one floor's lines would
    // be served on the other.
    let one_file = common::write(
        dir.path(),
        "one.toml",
        "gateway_id = \"gw\"\nsite = \"library.toml\"\n[planner]\nmode = \"desire\"\n\
         [planner.models]\ndesire_lines = \"models/desire_lines.onnx\"\n",
    );
    let one_file = one_file.to_str().unwrap();
    let route = ["--from", "G:west entrance", "--to", "L1:east entrance"];
    for command in [
        vec!["check", "--config", one_file],
        [&["plan", "--config", one_file][..], &route].concat(),
    ] {
        let out = common::gangway(&command);
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(!out.status.success(), "{command:?}: {stderr}");
        assert!(
            stderr.contains("[planner.models] desire_lines = \"")
                && stderr.contains("put `{floor}` in its path"),
            "{command:?}: {stderr}"
        );
    }
}
