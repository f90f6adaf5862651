//! Planning speed: A* and the any-angle baseline (Theta*) on the sample
//! site, the frame-guided repair every
//! learned route goes through, and, when trained models are in `models/`
//! (see docs/planning.md), the learned modes themselves. Targets (issue 5):
//! plan p50 ≤ 100 µs, p99 ≤ 1 ms including repair. `… route reply`: the
//! reply built from a planned route (its checked line, maneuvers and
//! instructions).
//!
//! `scale` (issue 16): desire lines trained and served on open floors with
//! pillars of ~100, ~1,000 and ~10,000 walkable cells (simulated walks, as
//! many as a tenth of the cells, at least 200). Prints the training time and
//! the p50 / p99 of 1,000 random requests per size (A* and Theta* beside
//! them), and draws them against the number of cells into
//! `target/criterion/plan-scale.svg` (BENCHMARKS.md, "Planning at scale").

use std::hint::black_box;
use std::path::Path;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use gangway::plan::frame::route_from_frame;
use gangway::plan::{self, Connectivity, PlannerConfig, PlannerMode, Profile};
use gangway::site::Site;

fn planning(c: &mut Criterion) {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let site = Arc::new(Site::load(&root.join("config/sites/waldo.toml")).unwrap());
    let places: Vec<_> = site.places().values().copied().collect();
    let (from, to) = (places[0], places[places.len() - 1]);

    let astar = plan::astar::AStar::new(site.clone(), Connectivity::Eight);
    c.bench_function("astar place to place", |b| {
        b.iter(|| black_box(plan::Planner::plan(&astar, from, to, Profile::Default)))
    });
    c.bench_function("astar low-vision (turn costs)", |b| {
        b.iter(|| black_box(plan::Planner::plan(&astar, from, to, Profile::LowVision)))
    });
    reply_bench(c, &site, &astar, from, to);
    let anyangle = plan::anyangle::AnyAngle::new(site.clone());
    c.bench_function("anyangle place to place", |b| {
        b.iter(|| black_box(anyangle.route(from, to, Profile::Default)))
    });

    // A frame with the shortest route's cells lit except a gap: repair work.
    let route = plan::Planner::plan(&astar, from, to, Profile::Default)
        .unwrap()
        .route;
    let mut frame = vec![-1.0f32; usize::from(site.width()) * usize::from(site.height())];
    for (i, &cell) in route.cells.iter().enumerate() {
        if i % 5 != 2 {
            frame[site.grid_index(cell)] = 1.0;
        }
    }
    c.bench_function("route_from_frame with gaps", |b| {
        b.iter(|| {
            black_box(route_from_frame(
                &site,
                Connectivity::Eight,
                Profile::Default,
                &frame,
                from,
                to,
            ))
        })
    });

    let mut config = PlannerConfig::default();
    config.resolve_paths(root);
    for mode in [
        PlannerMode::Rejection,
        PlannerMode::Conditional,
        PlannerMode::Desire,
    ] {
        match plan::build_mode(&config, mode, site.clone()) {
            Ok(planner) => {
                c.bench_function(&format!("{} place to place", mode.name()), |b| {
                    b.iter(|| black_box(planner.plan(from, to, Profile::Default)))
                });
                reply_bench(c, &site, &*planner, from, to);
            }
            Err(e) => eprintln!("skipping {}: {e:#}", mode.name()),
        }
    }
}

/// Building the route reply of a planned route (issue 34: its line checked
/// and simplified, maneuvers and instructions along it): the work a
/// gateway adds to the planner's for every route it publishes.
fn reply_bench(
    c: &mut Criterion,
    site: &Site,
    planner: &dyn plan::Planner,
    from: gangway::site::Cell,
    to: gangway::site::Cell,
) {
    let planned = planner.plan(from, to, Profile::Default).unwrap();
    c.bench_function(&format!("{} route reply", planner.mode()), |b| {
        b.iter(|| {
            black_box(gangway::publish::RouteBody::new(
                site,
                planner,
                Profile::Default,
                from,
                to,
                &planned,
                0,
            ))
        })
    });
}

/// An open `side × side` floor with a 2 × 2 pillar every 8 cells.
fn pillared_site(side: usize) -> Site {
    let mut map = String::new();
    for y in 0..side {
        for x in 0..side {
            map.push(if x % 8 >= 4 && x % 8 < 6 && y % 8 >= 4 && y % 8 < 6 {
                '.'
            } else {
                '#'
            });
        }
        map.push('\n');
    }
    let text = format!("name = \"scale-{side}\"\ncell_m = 1.0\nmap = '''\n{map}'''\n");
    Site::parse(&text, Path::new("scale.toml")).unwrap()
}

/// Sorted request times of `planner` over `pairs`, µs.
/// Each request's time in µs, sorted: as first answered (what a walker
/// waits, preemptions on a loaded machine included), and the least of
/// `RUNS` answers (what the request itself costs: a preemption is a ~4 ms
/// scheduler slice that rarely strikes the same request in every run).
fn request_times(
    planner: &dyn plan::Planner,
    pairs: &[(gangway::site::Cell, gangway::site::Cell)],
) -> (Vec<f64>, Vec<f64>) {
    const RUNS: usize = 3;
    let (mut first, mut least): (Vec<f64>, Vec<f64>) = pairs
        .iter()
        .map(|&(a, b)| {
            let runs: Vec<f64> = (0..RUNS)
                .map(|_| {
                    let started = std::time::Instant::now();
                    black_box(planner.plan(a, b, Profile::Default)).ok();
                    started.elapsed().as_secs_f64() * 1e6
                })
                .collect();
            (runs[0], runs.iter().copied().fold(f64::INFINITY, f64::min))
        })
        .unzip();
    first.sort_by(f64::total_cmp);
    least.sort_by(f64::total_cmp);
    (first, least)
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    sorted[((sorted.len() - 1) as f64 * q).round() as usize]
}

fn scale(c: &mut Criterion) {
    // Training three sites takes a minute: only when no filter is given or
    // the filter names these rows, so `--bench plan -- "route reply"` stays
    // quick.
    let filters: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-') && a.parse::<f64>().is_err())
        .collect();
    if !filters.is_empty() && !filters.iter().any(|f| f.contains("desire at")) {
        return;
    }
    use gangway::model::{Kind, Metadata};
    use gangway::simulate::{WalkConfig, simulate_walks};
    use gangway::train::write_proto;
    let dir = tempfile::tempdir().unwrap();
    // (walkable cells, train s, desire p50, p99, A* p99, Theta* p99)
    let mut rows: Vec<[f64; 6]> = Vec::new();
    for side in [10, 33, 104] {
        let site = Arc::new(pillared_site(side));
        let cells = site.open_cells().len();
        let walks = simulate_walks(
            &site,
            &WalkConfig {
                walks_per_pair: 0,
                random_walks: (cells / 10).max(200),
                ..WalkConfig::default()
            },
        );
        let started = std::time::Instant::now();
        let trained = gangway::train::desire::train(&site, &walks).unwrap();
        let train_s = started.elapsed().as_secs_f64();
        let file = dir.path().join(format!("desire-{side}.onnx"));
        let meta = Metadata::for_site(Kind::DesireLines, &site);
        write_proto(&file, &trained.model.to_onnx(&meta)).unwrap();
        let mut config = PlannerConfig::default();
        config.models.desire_lines = file;
        let desire = plan::build_mode(&config, PlannerMode::Desire, site.clone()).unwrap();
        let astar = plan::astar::AStar::new(site.clone(), Connectivity::Eight);
        let anyangle = plan::anyangle::AnyAngle::new(site.clone());
        let pairs = gangway::eval::planning::pairs(&site, 1000, 1);
        let (d_first, d) = request_times(&*desire, &pairs);
        let (_, a) = request_times(&astar, &pairs);
        let (_, t) = request_times(&anyangle, &pairs);
        eprintln!(
            "scale: {cells} walkable cells, {} walks: desire lines trained in {train_s:.1} s; \
             plan p50/p99 (least of 3 per request) desire {:.0}/{:.0} µs, A* {:.0}/{:.0} µs, \
             Theta* {:.0}/{:.0} µs; desire as first answered {:.0}/{:.0} µs",
            walks.len(),
            quantile(&d, 0.5),
            quantile(&d, 0.99),
            quantile(&a, 0.5),
            quantile(&a, 0.99),
            quantile(&t, 0.5),
            quantile(&t, 0.99),
            quantile(&d_first, 0.5),
            quantile(&d_first, 0.99),
        );
        rows.push([
            cells as f64,
            train_s,
            quantile(&d, 0.5),
            quantile(&d, 0.99),
            quantile(&a, 0.99),
            quantile(&t, 0.99),
        ]);
        let (from, to) = pairs[pairs.len() / 2];
        c.bench_function(&format!("desire at {cells} cells"), |b| {
            b.iter(|| black_box(desire.plan(from, to, Profile::Default)))
        });
    }
    draw_scale(&rows);
}

/// Training seconds and request times against walkable cells, log-log.
fn draw_scale(rows: &[[f64; 6]]) {
    use plotters::prelude::*;
    let out = Path::new(env!("CARGO_MANIFEST_DIR")).join("target/criterion/plan-scale.svg");
    std::fs::create_dir_all(out.parent().unwrap()).unwrap();
    let root = SVGBackend::new(&out, (720, 420)).into_drawing_area();
    root.fill(&WHITE).unwrap();
    let mut chart = ChartBuilder::on(&root)
        .caption(
            "desire lines: cost against walkable cells",
            ("sans-serif", 18),
        )
        .margin(12)
        .x_label_area_size(40)
        .y_label_area_size(60)
        .build_cartesian_2d((50f64..20_000f64).log_scale(), (1f64..1e8f64).log_scale())
        .unwrap();
    chart
        .configure_mesh()
        .x_desc("walkable cells")
        .y_desc("µs")
        .draw()
        .unwrap();
    let series = [
        ("training (whole run)", 1usize, RED),
        ("desire plan p50", 2, BLUE),
        ("desire plan p99", 3, CYAN),
        ("A* p99", 4, BLACK),
        ("Theta* p99", 5, MAGENTA),
    ];
    for (name, column, colour) in series {
        let points: Vec<(f64, f64)> = rows
            .iter()
            .map(|r| (r[0], if column == 1 { r[1] * 1e6 } else { r[column] }))
            .collect();
        chart
            .draw_series(LineSeries::new(points.clone(), colour.stroke_width(2)))
            .unwrap()
            .label(name)
            .legend(move |(x, y)| PathElement::new(vec![(x, y), (x + 16, y)], colour));
        chart
            .draw_series(points.iter().map(|&p| Circle::new(p, 3, colour.filled())))
            .unwrap();
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.8))
        .border_style(BLACK)
        .position(SeriesLabelPosition::UpperLeft)
        .draw()
        .unwrap();
    root.present().unwrap();
    eprintln!("scale: drew {}", out.display());
}

criterion_group!(benches, planning, scale);
criterion_main!(benches);
