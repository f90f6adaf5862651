//! The five-floor mall of the Indoor Location Competition data
//! (`../shared/data/indoor-location-competition-20/site1`) as a building,
//! built where it is used (never copied into the repository): each floor's
//! site by the importer `gangway survey import --floor-dir` runs, and
//! connectors placed by a rule that knows nothing of the mall, since the
//! dataset gives none. Used by the floors tests.
//!
//! The rule: the candidates are the points (the lowest floor's cell centres,
//! in metres) whose cell is walkable on every floor and in that floor's
//! largest walkable area (8-connected), so every stop is reached from the
//! floor's shops; of those, [`CONNECTORS`] spread apart by farthest-point
//! sampling (the first the candidate nearest their centroid, each next the
//! one farthest from those chosen), alternately a lift and stairs, each
//! stopping on every floor at its defaults' times.

use std::collections::VecDeque;
use std::path::Path;

use gangway::site::{Building, Cell, Site};

/// Connectors placed: two lifts and two pairs of stairs.
pub(super) const CONNECTORS: usize = 4;

/// The mall's floors, lowest first, with their levels.
const FLOORS: [(&str, i32); 5] = [("B1", -1), ("F1", 0), ("F2", 1), ("F3", 2), ("F4", 3)];

/// The mall from `site_dir` (the dataset's `site1`), its floors imported
/// into `work` at 1 m cells.
pub(super) fn building(site_dir: &Path, work: &Path) -> Building {
    let mut sites = Vec::new();
    let mut text = String::from("name = \"site1\"\n");
    for (name, level) in FLOORS {
        let out = work.join(name);
        let options = gangway::survey::Options {
            cell_m: 1.0,
            ..Default::default()
        };
        gangway::survey::import(&site_dir.join(name), &out, &options)
            .unwrap_or_else(|e| panic!("importing floor {name}: {e:#}"));
        text.push_str(&format!(
            "[[floors]]\nname = \"{name}\"\nlevel = {level}\nsite = \"{name}/site.toml\"\n"
        ));
        sites.push(Site::load(&out.join("site.toml")).unwrap());
    }
    let main: Vec<Vec<bool>> = sites.iter().map(largest_area).collect();
    let on_every_floor = |world: [f64; 2]| -> Option<Vec<Cell>> {
        sites
            .iter()
            .zip(&main)
            .map(|(site, main)| {
                let cell = site.cell_of_world(world)?;
                main[site.grid_index(cell)].then_some(cell)
            })
            .collect()
    };
    let candidates: Vec<([f64; 2], Vec<Cell>)> = sites[0]
        .open_cells()
        .iter()
        .filter_map(|&c| {
            let world = sites[0].world_of_cell(c);
            on_every_floor(world).map(|cells| (world, cells))
        })
        .collect();
    assert!(
        candidates.len() >= CONNECTORS,
        "only {} points are walkable on every floor",
        candidates.len()
    );
    let n = candidates.len() as f64;
    let centroid = candidates
        .iter()
        .fold([0.0, 0.0], |s, (w, _)| [s[0] + w[0] / n, s[1] + w[1] / n]);
    let dist = |a: [f64; 2], b: [f64; 2]| (a[0] - b[0]).hypot(a[1] - b[1]);
    let mut chosen = vec![
        (0..candidates.len())
            .min_by(|&a, &b| {
                dist(candidates[a].0, centroid).total_cmp(&dist(candidates[b].0, centroid))
            })
            .unwrap(),
    ];
    while chosen.len() < CONNECTORS {
        let nearest_chosen = |i: usize| {
            chosen
                .iter()
                .map(|&j| dist(candidates[i].0, candidates[j].0))
                .fold(f64::INFINITY, f64::min)
        };
        let next = (0..candidates.len())
            .max_by(|&a, &b| nearest_chosen(a).total_cmp(&nearest_chosen(b)))
            .unwrap();
        chosen.push(next);
    }
    for (k, &i) in chosen.iter().enumerate() {
        let kind = if k % 2 == 0 { "lift" } else { "stairs" };
        let stops: Vec<String> = FLOORS
            .iter()
            .zip(&candidates[i].1)
            .map(|((name, _), c)| format!("{{ floor = \"{name}\", cell = [{}, {}] }}", c.x, c.y))
            .collect();
        text.push_str(&format!(
            "[[connectors]]\nid = \"{kind} {}\"\nkind = \"{kind}\"\nstops = [{}]\n",
            k / 2 + 1,
            stops.join(", ")
        ));
    }
    let path = work.join("building.toml");
    std::fs::write(&path, &text).unwrap();
    Building::load(&path).unwrap_or_else(|e| panic!("{e}"))
}

/// Which cells (by grid index) are in `site`'s largest 8-connected walkable
/// area.
fn largest_area(site: &Site) -> Vec<bool> {
    let cells = usize::from(site.width()) * usize::from(site.height());
    let mut area = vec![usize::MAX; cells];
    let mut sizes = Vec::new();
    for &start in site.open_cells() {
        if area[site.grid_index(start)] != usize::MAX {
            continue;
        }
        let id = sizes.len();
        let mut size = 0;
        let mut queue = VecDeque::from([start]);
        area[site.grid_index(start)] = id;
        while let Some(here) = queue.pop_front() {
            size += 1;
            for (dx, dy) in [
                (-1, -1),
                (0, -1),
                (1, -1),
                (-1, 0),
                (1, 0),
                (-1, 1),
                (0, 1),
                (1, 1),
            ] {
                let (Some(x), Some(y)) =
                    (here.x.checked_add_signed(dx), here.y.checked_add_signed(dy))
                else {
                    continue;
                };
                let next = Cell::new(x, y);
                if site.walkable(next)
                    && gangway::plan::Connectivity::Eight.step_ok(site, here, next)
                    && area[site.grid_index(next)] == usize::MAX
                {
                    area[site.grid_index(next)] = id;
                    queue.push_back(next);
                }
            }
        }
        sizes.push(size);
    }
    let biggest = (0..sizes.len()).max_by_key(|&i| sizes[i]);
    area.into_iter().map(|a| Some(a) == biggest).collect()
}
