//! What guidance adds to the pipeline: per fix of a guided device, the fix
//! (its cell and the tracker's mean belief) projected on its route, the progress filter, the next maneuver,
//! announcements and the message built and encoded as JSON
//! (`guidance_update`); per other event of the device (a sighting between
//! fixes), progress judged at its time (`guidance_tick`, no message most of
//! the time). The walker walks a route across the waldo floor over and
//! over; a new session starts each time round (1 update in ~40), as a route
//! request would. `guidance_update_straying`: the same walker misses the
//! route's first turn and walks straight on until told they left the route,
//! then starts again: fixes off the route, whose move the leaving test
//! projects ahead. `guidance_walk_prior` against `guidance_tracker_step`:
//! what a guided device's fix costs the tracker more (the route's cells
//! paired with those a walk ahead, and a second belief moved by them).
//! Run: `cargo bench --bench guidance`.

use std::hint::black_box;
use std::path::Path;
use std::sync::Arc;

use criterion::{Criterion, criterion_group, criterion_main};
use gangway::guide::{GuidanceConfig, Guide, Located};
use gangway::locate::tracker::{Tracker, TrackerConfig};
use gangway::plan::{Connectivity, Profile, Route, astar};
use gangway::publish::Output;
use gangway::site::{Cell, Site};
use gangway::topics::Topics;

fn guidance(c: &mut Criterion) {
    let site = Arc::new(
        Site::load(Path::new("config/sites/waldo.toml")).expect("run from the repository root"),
    );
    let (from, to) = (
        site.place("west entrance").unwrap(),
        site.place("group rooms").unwrap(),
    );
    let route = astar::search(&site, Connectivity::Eight, from, to, |_| 1.0).unwrap();
    // Stop short of the destination: arriving would end the session.
    let walk = &route.cells[..route.cells.len() - 6];
    let topics = Topics::new("gangway/gw-lobby");
    // A fix as the pipeline passes it: the cell and the belief's mean (a
    // little off the cell's centre), both projected on the route.
    let located = |cell: Cell| {
        let centre = [f64::from(cell.x) + 0.5, f64::from(cell.y) + 0.5];
        Located::with_mean(&site, cell, [centre[0] + 0.3, centre[1] - 0.2])
    };
    let start = |guide: &mut Guide, route: &Route, t: f64| {
        let line = gangway::plan::ServedLine::of_cells(route).points;
        guide.start(
            &site,
            "phone",
            None,
            Profile::Default,
            route,
            &line,
            t,
            false,
        );
    };
    // A fix every two seconds along `walk`, a new session each time round.
    let bench_walk = |c: &mut Criterion, name: &str, walk: &[Cell]| {
        let mut guide = Guide::new(GuidanceConfig::default(), 2.0);
        let (mut i, mut t) = (0, 0.0);
        c.bench_function(name, |b| {
            b.iter(|| {
                if i == 0 {
                    start(&mut guide, &route, t);
                }
                t += 2.0;
                let message = guide.update(&site, "phone", Some(located(walk[i])), t, t);
                i = (i + 1) % walk.len();
                black_box(message.and_then(|m| topics.encode(&Output::Guidance(Box::new(m)))))
            })
        });
    };
    bench_walk(c, "guidance_update", walk);
    // On to a corner, then straight on past it while the floor is open (at
    // most 8 cells): the corner with the most room to do so.
    let step = |a: Cell, b: Cell| {
        (
            i32::from(b.x) - i32::from(a.x),
            i32::from(b.y) - i32::from(a.y),
        )
    };
    let straight_on = |i: usize| {
        let (dx, dy) = step(route.cells[i - 1], route.cells[i]);
        let mut walk = route.cells[..=i].to_vec();
        for _ in 0..8 {
            let last = *walk.last().unwrap();
            let next = match (
                u16::try_from(i32::from(last.x) + dx),
                u16::try_from(i32::from(last.y) + dy),
            ) {
                (Ok(x), Ok(y)) if site.walkable(Cell::new(x, y)) => Cell::new(x, y),
                _ => break,
            };
            walk.push(next);
        }
        walk
    };
    let stray = (1..route.cells.len() - 1)
        .filter(|&i| {
            step(route.cells[i - 1], route.cells[i]) != step(route.cells[i], route.cells[i + 1])
        })
        .map(|i| (straight_on(i), i))
        .max_by_key(|(walk, i)| walk.len() - i)
        .expect("the route turns");
    let (stray, corner) = stray;
    assert!(stray.len() > corner + 4, "room to stray past a corner");
    bench_walk(c, "guidance_update_straying", &stray);
    // Ten events between fixes two seconds apart.
    let mut guide = Guide::new(GuidanceConfig::default(), 2.0);
    let (mut k, mut t) = (0usize, 0.0);
    c.bench_function("guidance_tick", |b| {
        b.iter(|| {
            let i = (k / 10) % walk.len();
            if k % (10 * walk.len()) == 0 {
                start(&mut guide, &route, t);
            }
            t += 0.2;
            let message = if k % 10 == 0 {
                guide.update(&site, "phone", Some(located(walk[i])), t, t)
            } else {
                guide.tick(&site, "phone", t)
            };
            k += 1;
            black_box(message.and_then(|m| topics.encode(&Output::Guidance(Box::new(m)))))
        })
    });
    // What the walk prior adds to a guided device's fix: the route's cells
    // paired with those a walk ahead, and the tracker's second belief
    // moved by it (`guidance_walk_prior`, against `guidance_tracker_step`,
    // the same fix of a device nobody guides). Evidence peaked at the
    // walker's cell, as a good fix's is.
    let evidence: Vec<Vec<f32>> = walk
        .iter()
        .map(|&at| {
            site.open_cells()
                .iter()
                .map(|&c| -2.0 * c.distance(at) as f32)
                .collect()
        })
        .collect();
    for (name, guided) in [
        ("guidance_tracker_step", false),
        ("guidance_walk_prior", true),
    ] {
        let mut guide = Guide::new(GuidanceConfig::default(), 2.0);
        let mut tracker = Tracker::new(TrackerConfig::default(), site.clone());
        let device: Arc<str> = "phone".into();
        let (mut i, mut t) = (0, 0.0);
        c.bench_function(name, |b| {
            b.iter(|| {
                if i == 0 {
                    start(&mut guide, &route, t);
                }
                t += 2.0;
                let walk_prior = guided
                    .then(|| guide.expected_walk(&site, "phone", t))
                    .flatten();
                let (fix, mean) =
                    tracker.update_walking(&device, t, &evidence[i], walk_prior.as_ref());
                guide.update(&site, "phone", Some(located(walk[i])), t, t);
                i = (i + 1) % walk.len();
                black_box((fix, mean))
            })
        });
    }
    println!(
        "route of {} cells, {:.0} m; straying: {} cells past the corner at cell {corner}",
        route.cells.len(),
        route.length_m(&site),
        stray.len() - corner - 1
    );
}

criterion_group!(benches, guidance);
criterion_main!(benches);
