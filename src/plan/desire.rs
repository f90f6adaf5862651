//! The desire-line planner: the line people walk between the requested
//! cells, learned from their walks ([`crate::model::desire`]), made walkable
//! and turned into a route.
//!
//! The model gives a polyline from the source's centre to the destination's
//! (cell units). [`walkable_line`] keeps it where the profile may walk it and
//! repairs it where not: a point on a cell the profile may not use is
//! dropped, and a segment that crosses one is replaced by the any-angle route
//! (its shortest grid route pulled taut, [`string_pulled`]: a grid search
//! and a line check per cell, much cheaper than Theta* on large sites)
//! between its ends. The route is the cells along the result ([`polyline_cells`]: 8-connected,
//! no blocked corner cut, loops cut), validated like every route; a 4-connected
//! site routes along those cells with the frame repair search. The answer
//! carries the line itself ([`Planned::line`]), which is what a walker is
//! told to follow and what `gangway eval planning` judges.
//!
//! Profile costs other than passability (low vision's narrow cells and
//! turns) are not applied to the learned line: it is where people walked.

use std::sync::Arc;
use std::time::Instant;

use super::anyangle::{GridPoint, centre, polyline_cells, segment_cells, string_pulled};
use super::astar::profile_search;
use super::frame::route_from_frame;
use super::{Connectivity, Origin, PlanError, Planned, Planner, Profile, Route, Timings};
use crate::model::runtime::DesireModel;
use crate::site::{Cell, Site};

pub struct Desire {
    site: Arc<Site>,
    connectivity: Connectivity,
    model: DesireModel,
    version: String,
}

impl Desire {
    pub fn new(site: Arc<Site>, connectivity: Connectivity, model: DesireModel) -> Desire {
        // "desire_lines@474lines/seed1": the bank is what was learned.
        let meta = model.model().metadata();
        let version = format!(
            "{}@{}lines/seed{}",
            meta.kind.name(),
            meta.metrics.get("bank_lines").copied().unwrap_or(0.0),
            meta.seed
        );
        Desire {
            site,
            connectivity,
            model,
            version,
        }
    }
}

impl Planner for Desire {
    fn mode(&self) -> &'static str {
        "desire"
    }

    fn model_version(&self) -> Option<&str> {
        Some(&self.version)
    }

    fn plan(&self, from: Cell, to: Cell, profile: Profile) -> Result<Planned, PlanError> {
        let site = &*self.site;
        for c in [from, to] {
            if !profile.passable(site, c) {
                return Err(PlanError::Blocked(c));
            }
        }
        let started = Instant::now();
        let f32s = |p: GridPoint| [p[0] as f32, p[1] as f32];
        let learned = self
            .model
            .line(f32s(centre(from)), f32s(centre(to)))
            .map_err(super::model_error)?;
        let timings = Timings {
            gen_us: started.elapsed().as_micros() as u64,
            classify_us: 0,
        };
        let points: Vec<GridPoint> = learned
            .iter()
            .map(|p| [f64::from(p[0]), f64::from(p[1])])
            .collect();
        let (line, repaired) = walkable_line(site, profile, &points, from, to)?;
        plan_along(site, self.connectivity, profile, line, repaired, from, to).map(|mut p| {
            p.timings = timings;
            p
        })
    }
}

/// The route along a walkable `line` from `from` to `to`, validated.
fn plan_along(
    site: &Site,
    connectivity: Connectivity,
    profile: Profile,
    line: Vec<GridPoint>,
    repaired: bool,
    from: Cell,
    to: Cell,
) -> Result<Planned, PlanError> {
    let passable = |c: Cell| profile.passable(site, c);
    let cells = polyline_cells(site, &line, passable);
    let direct = cells.clone().map(|cells| Route { cells }).filter(|r| {
        connectivity == Connectivity::Eight
            && r.validate_for(site, from, to, connectivity, profile)
                .is_ok()
    });
    let (route, origin) = match direct {
        Some(route) if repaired => (route, Origin::Repaired),
        Some(route) => (route, Origin::Frame),
        None => {
            // 4-connected (or a line whose cells do not chain: not expected,
            // but an answer must never depend on it): the line's cells as a
            // frame, walked by the frame repair search.
            let mut frame = vec![-1.0f32; usize::from(site.width()) * usize::from(site.height())];
            let lit =
                cells.unwrap_or_else(|| line.iter().filter_map(|&p| cell_at(site, p)).collect());
            for c in lit {
                frame[site.grid_index(c)] = 1.0;
            }
            let (route, origin) = route_from_frame(site, connectivity, profile, &frame, from, to)?;
            (route, if repaired { Origin::Repaired } else { origin })
        }
    };
    Ok(Planned {
        route,
        origin,
        samples: 1,
        frame: None,
        line: Some(line),
        timings: Timings::default(),
    })
}

/// `points` (from `from`'s centre to `to`'s) made walkable for `profile`, and
/// whether anything had to change: points on unusable cells dropped, segments
/// that cross an unusable cell replaced by the any-angle route between their
/// ends. When a repair cannot be made (a snapped point in a part of the site
/// not connected to the route), the whole line is the any-angle route.
pub fn walkable_line(
    site: &Site,
    profile: Profile,
    points: &[GridPoint],
    from: Cell,
    to: Cell,
) -> Result<(Vec<GridPoint>, bool), PlanError> {
    let passable = |c: Cell| profile.passable(site, c);
    let mut out = vec![centre(from)];
    let mut repaired = false;
    let inner = points
        .get(1..points.len().saturating_sub(1))
        .unwrap_or_default();
    for (k, &raw) in inner.iter().chain([&centre(to)]).enumerate() {
        let last = k == inner.len();
        let p = off_boundaries(raw);
        if !cell_at(site, p).is_some_and(passable) {
            // Inside a wall or off the floor: the segments either side are
            // joined round it below.
            repaired = true;
            continue;
        }
        let prev = *out.last().expect("starts with the source");
        if segment_cells(site, prev, p, passable).is_some() {
            out.push(p);
            continue;
        }
        repaired = true;
        let (a, b) = (
            cell_at(site, prev).expect("on the grid"),
            cell_at(site, p).expect("on the grid"),
        );
        match detour(site, profile, a, b) {
            Ok(leg) => {
                // Through the centre of prev's cell, where Theta*'s clear
                // segments start (prev may be anywhere in it).
                if prev != centre(a) {
                    out.push(centre(a));
                }
                out.extend(leg[1..].iter().map(|&c| centre(c)));
                if centre(b) != p {
                    out.push(p);
                }
            }
            Err(_) if !last => continue,
            Err(_) => {
                let whole = detour(site, profile, from, to)?;
                return Ok((whole.iter().map(|&c| centre(c)).collect(), true));
            }
        }
    }
    let end = centre(to);
    if out.last() != Some(&end) {
        out.push(end);
    }
    Ok((out, repaired))
}

/// The any-angle way from `a` to `b` for `profile`: its shortest grid route
/// pulled taut ([`string_pulled`]), as turning cells.
fn detour(site: &Site, profile: Profile, a: Cell, b: Cell) -> Result<Vec<Cell>, PlanError> {
    let route = profile_search(site, Connectivity::Eight, a, b, profile, |_| 1.0)?;
    Ok(string_pulled(site, &route.cells, |c| {
        profile.passable(site, c)
    }))
}

/// The cell holding `p` (cell units), when it is on the grid.
fn cell_at(site: &Site, p: GridPoint) -> Option<Cell> {
    let (x, y) = (p[0].floor(), p[1].floor());
    if !(x >= 0.0 && y >= 0.0 && x < f64::from(site.width()) && y < f64::from(site.height())) {
        return None;
    }
    Some(Cell::new(x as u16, y as u16))
}

/// `p` moved a micro-cell off any cell boundary it lies on exactly: a
/// segment ending on a boundary (or a corner) would be walked into the cell
/// beyond it by the traversal, and the next segment starts from the other.
fn off_boundaries(p: GridPoint) -> GridPoint {
    p.map(|v| {
        if (v - v.round()).abs() < 1e-9 {
            v.round() + 1e-6
        } else {
            v
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn site(map: &str) -> Arc<Site> {
        let text = format!("name = \"t\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n");
        Arc::new(Site::parse(&text, Path::new("t.toml")).unwrap())
    }

    #[test]
    fn a_bent_line_is_kept_where_walkable_and_repaired_round_walls() {
        // 9 × 5 room with a wall in the middle of the bottom rows.
        let s = site("#########\n#########\n#########\n####.####\n####.####");
        let (from, to) = (Cell::new(0, 4), Cell::new(8, 4));
        // A line bowing up over the wall: walkable as it is.
        let over: Vec<GridPoint> = (0..=8)
            .map(|k| {
                let t = f64::from(k) / 8.0;
                [0.5 + 8.0 * t, 4.5 - 8.0 * t * (1.0 - t) * 1.5]
            })
            .collect();
        let (line, repaired) = walkable_line(&s, Profile::Default, &over, from, to).unwrap();
        assert!(!repaired, "{line:?}");
        let planned = plan_along(
            &s,
            Connectivity::Eight,
            Profile::Default,
            line,
            repaired,
            from,
            to,
        )
        .unwrap();
        assert_eq!(planned.origin, Origin::Frame);
        // The straight line through the wall: repaired round it.
        let straight = vec![centre(from), [4.5, 4.5], centre(to)];
        let (line, repaired) = walkable_line(&s, Profile::Default, &straight, from, to).unwrap();
        assert!(repaired);
        let planned = plan_along(
            &s,
            Connectivity::Eight,
            Profile::Default,
            line,
            true,
            from,
            to,
        )
        .unwrap();
        assert_eq!(planned.origin, Origin::Repaired);
        assert!(!planned.route.cells.contains(&Cell::new(4, 4)));
        let four = plan_along(
            &s,
            Connectivity::Four,
            Profile::Default,
            planned.line.clone().unwrap(),
            true,
            from,
            to,
        )
        .unwrap();
        four.route
            .validate(&s, from, to, Connectivity::Four)
            .unwrap();
    }
}
