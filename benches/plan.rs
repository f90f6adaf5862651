//! Planning speed: A* and the any-angle baseline (Theta*) on the sample
//! site, the frame-guided repair every
//! learned route goes through, and, when trained models are in `models/`
//! (see docs/planning.md), the learned modes themselves. Targets (issue 5):
//! plan p50 ≤ 100 µs, p99 ≤ 1 ms including repair.

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
    for mode in [PlannerMode::Rejection, PlannerMode::Conditional] {
        match plan::build_mode(&config, mode, site.clone()) {
            Ok(planner) => {
                c.bench_function(&format!("{} place to place", mode.name()), |b| {
                    b.iter(|| black_box(planner.plan(from, to, Profile::Default)))
                });
            }
            Err(e) => eprintln!("skipping {}: {e:#}", mode.name()),
        }
    }
}

criterion_group!(benches, planning);
criterion_main!(benches);
