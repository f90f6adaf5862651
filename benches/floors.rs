//! Buildings of several floors (issue #28): what serving a building costs
//! over serving one floor. A made-up building of three open floors of
//! 120 × 90 m at 1 m cells (10,800 cells each), a beacon every 15 m, a lift
//! in the middle and stairs at a corner, written to a temporary directory:
//!
//! - `fix on one floor`: the pipeline of one floor, a phone hearing that
//!   floor's beacons, one fingerprint window (and its fix) per iteration;
//! - `fix on a building of 3 floors`: the same phone in the building's
//!   pipeline, hearing every floor's beacons it can (18 dB lost per floor):
//!   the floor evidence and filter on top of the same floor's fix;
//! - `route across 3 floors`: a wheelchair user's route from a corner of
//!   the lowest floor to the far corner of the top one (legs by A*, the
//!   lift).
//!
//! Run: `cargo bench --bench floors`.

use std::fmt::Write as _;
use std::hint::black_box;
use std::path::Path;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use gangway::event::Event;
use gangway::pipeline::{Pipeline, PipelineConfig};
use gangway::plan::floors::{BuildingPlanner, FloorCell};
use gangway::plan::{self, Connectivity, PlannerConfig, PlannerMode, Profile};
use gangway::sighting::{BeaconId, Sighting};
use gangway::site::{Building, Cell};

const WIDTH_M: u32 = 120;
const HEIGHT_M: u32 = 90;
const SPACING_M: u32 = 15;
const FLOORS: [&str; 3] = ["B1", "G", "L1"];
const UUID: &str = "3d2f1c0b-9e84-4c8e-9a70-5e1a6f3c2b1d";

/// Writes the building into `dir`; returns the building file.
fn write_building(dir: &Path) -> std::path::PathBuf {
    let mut building = String::from("name = \"bench\"\n");
    for (f, name) in FLOORS.iter().enumerate() {
        let mut site = format!(
            "name = \"bench {name}\"\ncell_m = 1.0\nwidth_m = {WIDTH_M}.0\nheight_m = {HEIGHT_M}.0\n"
        );
        for (k, (x, y)) in beacon_positions().enumerate() {
            let minor = f * 1000 + k;
            write!(
                site,
                "\n[[beacon]]\nid = \"{name}-{k}\"\nuuid = \"{UUID}\"\nmajor = 1\nminor = {minor}\n\
                 pos = [{x}.0, {y}.0]\n"
            )
            .unwrap();
        }
        std::fs::write(dir.join(format!("{name}.toml")), site).unwrap();
        write!(
            building,
            "\n[[floors]]\nname = \"{name}\"\nlevel = {}\nsite = \"{name}.toml\"\n",
            f as i32 - 1
        )
        .unwrap();
    }
    let stops = |x: u32, y: u32, floors: &[&str]| {
        floors
            .iter()
            .map(|f| format!("{{ floor = \"{f}\", cell = [{x}, {y}] }}"))
            .collect::<Vec<_>>()
            .join(", ")
    };
    write!(
        building,
        "\n[[connectors]]\nid = \"lift\"\nkind = \"lift\"\nstops = [{}]\n\
         \n[[connectors]]\nid = \"stairs\"\nkind = \"stairs\"\nstops = [{}]\n",
        stops(WIDTH_M / 2, HEIGHT_M / 2, &FLOORS),
        stops(2, 2, &FLOORS),
    )
    .unwrap();
    let path = dir.join("building.toml");
    std::fs::write(&path, building).unwrap();
    path
}

fn beacon_positions() -> impl Iterator<Item = (u32, u32)> {
    (0..HEIGHT_M / SPACING_M)
        .flat_map(|j| (0..WIDTH_M / SPACING_M).map(move |i| (i * SPACING_M + 7, j * SPACING_M + 7)))
}

/// One scan of the phone at `at` on floor `floor`: every beacon of the
/// floors in `heard` above −95 dBm (−59 dBm at 1 m, exponent 2.5, 18 dB per
/// floor between).
fn scan(at: (f64, f64), floor: usize, heard: &[usize], t: f64) -> Vec<Sighting> {
    let observer: Arc<str> = "phone".into();
    let mut out = Vec::new();
    for &f in heard {
        for (k, (x, y)) in beacon_positions().enumerate() {
            let d = (f64::from(x) - at.0).hypot(f64::from(y) - at.1).max(0.5);
            let dbm = -59.0 - 25.0 * d.log10() - 18.0 * f.abs_diff(floor) as f64;
            if dbm >= -95.0 {
                out.push(Sighting {
                    advertiser_mac: None,
                    t,
                    observer: observer.clone(),
                    advertiser: BeaconId {
                        uuid: UUID.parse().unwrap(),
                        major: 1,
                        minor: (f * 1000 + k) as u16,
                    },
                    tx_power: None,
                    rssi: dbm.round() as i16,
                });
            }
        }
    }
    out
}

/// Feeds `pipeline` a scan per second of the phone walking along y = 40 m
/// on floor 1, `heard` floors' beacons; each call closes one window.
fn walker(heard: &'static [usize]) -> impl FnMut(&mut Pipeline) -> usize {
    let mut t = 0.0;
    let mut out = Vec::new();
    move |pipeline| {
        out.clear();
        // The default window's stride is 2 s: two scans close one.
        for _ in 0..2 {
            t += 1.0;
            let x = 10.0 + (t % 100.0);
            for sighting in scan((x, 40.0), 1, heard, t) {
                pipeline.handle(&Event::Advert(sighting), &mut out);
            }
        }
        out.len()
    }
}

fn benches(c: &mut Criterion) {
    let dir = tempfile::tempdir().unwrap();
    let building = Arc::new(Building::load(&write_building(dir.path())).unwrap());
    let config = PipelineConfig::default();

    let floor = building.floors()[1].site.clone();
    let mut one = Pipeline::new(&config, floor).unwrap();
    let mut step = walker(&[1]);
    c.bench_function("floors/fix on one floor of 10,800 cells", |b| {
        b.iter(|| black_box(step(&mut one)))
    });

    let mut all = Pipeline::for_building(&config, building.clone()).unwrap();
    let mut step = walker(&[0, 1, 2]);
    c.bench_function("floors/fix on a building of 3 floors", |b| {
        b.iter(|| black_box(step(&mut all)))
    });

    let planners = building
        .floors()
        .iter()
        .map(|f| {
            plan::build_mode(
                &PlannerConfig::default(),
                PlannerMode::Astar,
                f.site.clone(),
            )
        })
        .collect::<Result<Vec<_>, _>>()
        .unwrap();
    let planner = BuildingPlanner::new(building.clone(), Connectivity::Eight, planners);
    let from = FloorCell {
        floor: 0,
        cell: Cell::new(5, 85),
    };
    let to = FloorCell {
        floor: 2,
        cell: Cell::new(115, 5),
    };
    c.bench_function("floors/route across 3 floors", |b| {
        b.iter(|| black_box(planner.plan(from, to, Profile::Wheelchair).unwrap()))
    });
}

criterion_group!(floors, benches);
criterion_main!(floors);
