//! Training walks: whole walks between places as trajectories, with human
//! variation around the shortest route (`gangway simulate --trajectories`).

use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};

use super::{SimConfig, round_ms};
use crate::plan::{Connectivity, astar};
use crate::site::{Cell, Site};
use crate::train::trajectory::Trajectory;

/// What to simulate for path-model training data (`gangway simulate --trajectories`).
#[derive(Clone, Debug)]
pub struct WalkConfig {
    /// Walks between each pair of named places (one direction per pair: from
    /// the place that sorts first, so a frame's class is unambiguous).
    pub walks_per_pair: usize,
    /// Extra walks between random walkable cells at least `min_cells` apart,
    /// so a conditional model sees more than the named pairs.
    pub random_walks: usize,
    pub min_cells: u16,
    pub seed: u64,
    pub speed_mps: f64,
    pub start_t: f64,
}

impl Default for WalkConfig {
    fn default() -> Self {
        WalkConfig {
            walks_per_pair: 50,
            random_walks: 600,
            min_cells: 5,
            seed: 1,
            speed_mps: SimConfig::default().speed_mps,
            start_t: SimConfig::default().start_t,
        }
    }
}

/// Walks people make between places, with human variation around the shortest
/// route. Each walk draws its own preferences and hands them to A* as per-cell
/// cost factors:
/// - keeping off walls: cells next to blocked cells cost extra, by a per-walk
///   wall aversion (so walkers keep to corridor middles where there is room);
/// - taste: every cell gets a small random surcharge, so equal-length routes
///   are chosen differently and open areas are crossed on varied diagonals
///   (corners are cut wherever the floor is open: 8-connected steps);
/// - detours: with probability 0.15 the walk goes via a random cell near its
///   route (looking at a shelf), loops cut out.
///
/// Times follow a per-walk speed with ±15 % jitter per step. The same site and
/// config give the same walks.
pub fn simulate_walks(site: &Site, config: &WalkConfig) -> Vec<Trajectory> {
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(config.seed);
    let places: Vec<Cell> = site.places().values().copied().collect();
    let mut pairs = Vec::new();
    for (i, &a) in places.iter().enumerate() {
        for &b in &places[i + 1..] {
            if a != b {
                pairs.extend(std::iter::repeat_n((a, b), config.walks_per_pair));
            }
        }
    }
    let open = site.open_cells();
    let mut random_pairs = 0;
    // Bounded: a site too small for `min_cells` gets fewer random walks.
    for _ in 0..config.random_walks * 100 {
        if random_pairs == config.random_walks {
            break;
        }
        let a = open[rng.random_range(0..open.len())];
        let b = open[rng.random_range(0..open.len())];
        if a.chebyshev(b) >= config.min_cells {
            pairs.push((a, b));
            random_pairs += 1;
        }
    }
    let near_wall: Vec<f64> = open
        .iter()
        .map(|&c| blocked_neighbours(site, c) as f64 / 8.0)
        .collect();
    let mut walks = Vec::with_capacity(pairs.len());
    let mut t0 = config.start_t;
    for (from, to) in pairs {
        let aversion = rng.random_range(0.5..2.0);
        let taste: Vec<f64> = (0..open.len())
            .map(|_| rng.random_range(0.0..0.35))
            .collect();
        let cost = |c: Cell| {
            let i = site.open_index(c).expect("search visits walkable cells");
            1.0 + aversion * near_wall[i] + taste[i]
        };
        let Ok(route) = astar::search(site, Connectivity::Eight, from, to, cost) else {
            continue; // disconnected floor: nobody walks this pair
        };
        let mut cells = route.cells;
        if cells.len() > 2 && rng.random_bool(0.15) {
            let around = cells[rng.random_range(1..cells.len() - 1)];
            let near: Vec<Cell> = open
                .iter()
                .copied()
                .filter(|c| c.chebyshev(around) <= 3 && *c != from && *c != to)
                .collect();
            let via = near[rng.random_range(0..near.len())];
            if let (Ok(first), Ok(second)) = (
                astar::search(site, Connectivity::Eight, from, via, cost),
                astar::search(site, Connectivity::Eight, via, to, cost),
            ) {
                cells = first.cells;
                cells.extend_from_slice(&second.cells[1..]);
                cut_loops(&mut cells);
            }
        }
        let speed = (config.speed_mps * rng.random_range(0.75..1.25)).max(0.3);
        let mut t = t0;
        let mut times = vec![round_ms(t)];
        for step in cells.windows(2) {
            t += step[0].distance(step[1]) * site.cell_m / speed * rng.random_range(0.85..1.15);
            times.push(round_ms(t));
        }
        walks.push(Trajectory {
            site: site.name.clone(),
            device: format!("sim-{:04}", walks.len() + 1),
            cells,
            times,
            profile: None,
            feedback: None,
            positions_m: None,
        });
        // Walks start a few minutes apart.
        t0 = round_ms(t0 + rng.random_range(30.0..300.0));
    }
    walks
}

/// Blocked or off-grid cells among the 8 neighbours.
fn blocked_neighbours(site: &Site, c: Cell) -> usize {
    let mut n = 0;
    for dy in -1i32..=1 {
        for dx in -1i32..=1 {
            if (dx, dy) == (0, 0) {
                continue;
            }
            let (x, y) = (i32::from(c.x) + dx, i32::from(c.y) + dy);
            let walkable = x >= 0 && y >= 0 && site.walkable(Cell::new(x as u16, y as u16));
            n += usize::from(!walkable);
        }
    }
    n
}

/// Removes the loop between two visits of the same cell, so a walk with a
/// detour is still a simple path.
fn cut_loops(cells: &mut Vec<Cell>) {
    let mut out: Vec<Cell> = Vec::with_capacity(cells.len());
    for &c in cells.iter() {
        if let Some(i) = out.iter().position(|&o| o == c) {
            out.truncate(i);
        }
        out.push(c);
    }
    *cells = out;
}

#[cfg(test)]
mod walk_tests {
    use super::*;
    use std::path::Path;

    fn site() -> Site {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n##########\n##########\n##########\n####..####\n##########\n'''\n[places]\na = [0, 0]\nb = [9, 4]\nc = [9, 0]\n";
        Site::parse(text, Path::new("t.toml")).unwrap()
    }

    #[test]
    fn walks_are_valid_varied_and_reproducible() {
        let site = site();
        let config = WalkConfig {
            walks_per_pair: 20,
            random_walks: 10,
            ..WalkConfig::default()
        };
        let walks = simulate_walks(&site, &config);
        assert_eq!(walks.len(), 3 * 20 + 10);
        for w in &walks {
            w.check(&site).unwrap();
            let unique: std::collections::HashSet<_> = w.cells.iter().collect();
            assert_eq!(unique.len(), w.cells.len(), "no cell twice");
        }
        let ab: std::collections::HashSet<_> = walks[..20].iter().map(|w| &w.cells).collect();
        assert!(ab.len() > 3, "walks between one pair vary: {}", ab.len());
        assert!(
            walks[..20]
                .iter()
                .all(|w| w.source() == Cell::new(0, 0) && w.destination() == Cell::new(9, 4))
        );
        let shortest = astar::search(
            &site,
            Connectivity::Eight,
            Cell::new(0, 0),
            Cell::new(9, 4),
            |_| 1.0,
        )
        .unwrap()
        .length_m(&site);
        let mean: f64 = walks[..20]
            .iter()
            .map(|w| {
                crate::plan::Route {
                    cells: w.cells.clone(),
                }
                .length_m(&site)
            })
            .sum::<f64>()
            / 20.0;
        assert!(mean < shortest * 1.3, "near-shortest: {mean} vs {shortest}");
        assert_eq!(simulate_walks(&site, &config), walks);
    }

    #[test]
    fn cutting_loops_keeps_a_simple_path() {
        let c = |x, y| Cell::new(x, y);
        let mut cells = vec![c(0, 0), c(1, 0), c(2, 0), c(1, 0), c(1, 1)];
        cut_loops(&mut cells);
        assert_eq!(cells, vec![c(0, 0), c(1, 0), c(1, 1)]);
    }
}
