//! The desire-line planner: the line people walk between the requested
//! cells, learned from their walks ([`crate::model::desire`]), made walkable
//! and turned into a route.
//!
//! A request first gets its prior ([`prior_line`]): the profile's any-angle
//! route, the straight line where the profile may walk it, else its cheapest
//! grid route pulled taut ([`anyangle_cells`]: a grid search and a line check
//! per cell, much cheaper than Theta* on large sites). The model blends the
//! walks near the request's ends into it, where they are many and agree,
//! and says how much of the answer they made.
//!
//! - No walk near enough (the model's kernel mass at most its threshold):
//!   the prior is served as it is (`origin: few_walks`), not a guess.
//! - Otherwise the learned line, the prior's turning points kept where the
//!   walks left it alone ([`warped`]), is kept where the profile may walk it
//!   and repaired where not ([`walkable_line`]: a point on a cell the
//!   profile may not use is dropped, and a segment that crosses one is
//!   replaced by the any-angle way between its ends): `origin: frame` as
//!   learned, `repaired` when changed.
//! - A profile with costs beyond passability (low vision: narrow cells,
//!   doors, turns) gets its prior instead when the learned route costs it
//!   more in those than the prior does (`origin: profile_costs`): people's
//!   usual way through a narrow gap is not the way for them.
//!
//! The route is the cells along the line ([`polyline_cells`]: 8-connected,
//! no blocked corner cut, loops cut), validated like every route; a
//! 4-connected site routes along those cells with the frame repair search.
//! The answer carries the line itself ([`Planned::line`]), which is what a
//! walker is told to follow and what `gangway eval planning` judges.

use std::sync::Arc;

use super::anyangle::{GridPoint, centre, clear, polyline_cells, segment_cells, string_pulled};
use super::astar::profile_search;
use super::frame::route_from_frame;
use super::instructions::{ManeuverType, maneuvers};
use super::{
    Connectivity, Origin, PlanError, Planned, Planner, Profile, Route, Timings, passable_ends,
};
use crate::clock::Clock;
use crate::model::desire::POINTS;
use crate::model::runtime::DesireModel;
use crate::site::{Cell, Site};

pub(crate) struct Desire {
    site: Arc<Site>,
    connectivity: Connectivity,
    model: DesireModel,
    clock: Clock,
    version: String,
}

impl Desire {
    pub(crate) fn new(
        site: Arc<Site>,
        connectivity: Connectivity,
        model: DesireModel,
        clock: Clock,
    ) -> Desire {
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
            clock,
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
        passable_ends(site, profile, from, to)?;
        let prior = prior_line(site, profile, from, to)?;
        let started = self.clock.start();
        let f32s = |p: GridPoint| [p[0] as f32, p[1] as f32];
        let samples: Vec<[f32; 2]> = resample(&prior, POINTS).into_iter().map(f32s).collect();
        let (learned, share) = self
            .model
            .line(f32s(centre(from)), f32s(centre(to)), &samples)
            .map_err(super::model_error)?;
        let timings = Timings {
            gen_us: started.elapsed_us(),
            classify_us: 0,
        };
        if share <= 0.0 {
            let planned = plan_along(
                site,
                self.connectivity,
                profile,
                prior,
                Origin::FewWalks,
                from,
                to,
            )?;
            return Ok(Planned { timings, ..planned });
        }
        let learned: Vec<GridPoint> = learned
            .iter()
            .map(|p| [f64::from(p[0]), f64::from(p[1])])
            .collect();
        let line = warped(&prior, &samples, &learned);
        let walkable = walkable_line(site, profile, &line, from, to)?;
        let planned = serve_walkable(site, self.connectivity, profile, walkable, from, to, || {
            Ok(prior)
        })?;
        Ok(Planned { timings, ..planned })
    }
}

/// The route along a learned line made walkable ([`walkable_line`]: the
/// line and whether it was repaired), `origin: frame` or `repaired`; for a
/// profile with costs beyond passability, its `prior` line instead
/// (`origin: profile_costs`) when the learned route costs it more in those
/// than the prior's does. Shared by the learned-line planners (the desire
/// lines, the line GAN).
pub(crate) fn serve_walkable(
    site: &Site,
    connectivity: Connectivity,
    profile: Profile,
    (line, repaired): (Vec<GridPoint>, bool),
    from: Cell,
    to: Cell,
    prior: impl FnOnce() -> Result<Vec<GridPoint>, PlanError>,
) -> Result<Planned, PlanError> {
    let origin = if repaired {
        Origin::Repaired
    } else {
        Origin::Frame
    };
    let planned = plan_along(site, connectivity, profile, line, origin, from, to)?;
    if profile.has_costs() {
        let instead = plan_along(
            site,
            connectivity,
            profile,
            prior()?,
            Origin::ProfileCosts,
            from,
            to,
        )?;
        if profile_cost(site, profile, &planned.route)
            > profile_cost(site, profile, &instead.route) + 1e-9
        {
            return Ok(instead);
        }
    }
    Ok(planned)
}

/// What `route` costs `profile` beyond its length: the extra of the cells
/// it enters (a narrow cell's 4× is 3 more cell lengths) and the profile's
/// cost per turn a walker is told to make (turns as the instructions count
/// them, not the staircase steps of a slanted line). 0 for a profile
/// without such costs.
fn profile_cost(site: &Site, profile: Profile, route: &Route) -> f64 {
    if !profile.has_costs() {
        return 0.0;
    }
    let cells: f64 = route
        .cells
        .windows(2)
        .map(|w| w[0].distance(w[1]) * (profile.cell_cost(site, w[1]) - 1.0))
        .sum();
    let turns = maneuvers(site, route, profile)
        .iter()
        .filter(|m| m.kind == ManeuverType::Turn)
        .count();
    cells + profile.turn_cost() * turns as f64
}

/// The route along a walkable `line` from `from` to `to`, validated.
fn plan_along(
    site: &Site,
    connectivity: Connectivity,
    profile: Profile,
    line: Vec<GridPoint>,
    origin: Origin,
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
    let route = match direct {
        Some(route) => route,
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
            route_from_frame(site, connectivity, profile, &frame, from, to)?.0
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

/// The profile's any-angle route from `from` to `to` as a line through cell
/// centres: the straight line where the profile may walk it and it enters
/// no cell the profile pays extra for, else [`anyangle_cells`]. What the
/// planner serves without walks, and the prior the walks are blended into.
pub fn prior_line(
    site: &Site,
    profile: Profile,
    from: Cell,
    to: Cell,
) -> Result<Vec<GridPoint>, PlanError> {
    let free = |c: Cell| profile.passable(site, c) && profile.cell_cost(site, c) <= 1.0;
    if from == to {
        return Ok(vec![centre(from)]);
    }
    if clear(site, from, to, free) {
        return Ok(vec![centre(from), centre(to)]);
    }
    Ok(anyangle_cells(site, profile, from, to)?
        .into_iter()
        .map(centre)
        .collect())
}

/// The any-angle way from `a` to `b` for `profile`, as turning cells: its
/// cheapest grid route (cell and turn costs included) pulled taut
/// ([`string_pulled`]) without cutting across cells the profile pays extra
/// for that the route itself kept clear of.
pub(crate) fn anyangle_cells(
    site: &Site,
    profile: Profile,
    a: Cell,
    b: Cell,
) -> Result<Vec<Cell>, PlanError> {
    let route = profile_search(site, Connectivity::Eight, a, b, profile, |_| 1.0)?;
    if !profile.has_costs() {
        return Ok(string_pulled(site, &route.cells, |c| {
            profile.passable(site, c)
        }));
    }
    let on_route: foldhash::HashSet<Cell> = route.cells.iter().copied().collect();
    Ok(string_pulled(site, &route.cells, |c| {
        profile.passable(site, c) && (profile.cell_cost(site, c) <= 1.0 || on_route.contains(&c))
    }))
}

/// `count` points evenly spaced by length along `points`, both ends kept
/// (`count` copies of a single point).
pub fn resample(points: &[GridPoint], count: usize) -> Vec<GridPoint> {
    let lengths: Vec<f64> = points
        .windows(2)
        .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
        .collect();
    let total: f64 = lengths.iter().sum();
    let mut out = Vec::with_capacity(count);
    let (mut seg, mut before) = (0usize, 0.0f64);
    for k in 0..count {
        let target = total * k as f64 / (count - 1) as f64;
        while seg + 1 < lengths.len() && before + lengths[seg] < target {
            before += lengths[seg];
            seg += 1;
        }
        let (a, b) = (points[seg], points[(seg + 1).min(points.len() - 1)]);
        let t = if lengths.get(seg).is_some_and(|&l| l > 0.0) {
            ((target - before) / lengths[seg]).clamp(0.0, 1.0)
        } else {
            0.0
        };
        out.push([a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])]);
    }
    out
}

/// The learned line as the `prior` moved by what the walks changed: the
/// learned points (at the fractions of length the `samples` of the prior
/// were taken at) and, between them, the prior's own turning points moved
/// by the change interpolated there. Where the walks left the prior alone
/// this is the prior exactly, corners included, which [`POINTS`] samples
/// of it would cut.
pub fn warped(prior: &[GridPoint], samples: &[[f32; 2]], learned: &[GridPoint]) -> Vec<GridPoint> {
    let shift: Vec<GridPoint> = samples
        .iter()
        .zip(learned)
        .map(|(s, l)| [l[0] - f64::from(s[0]), l[1] - f64::from(s[1])])
        .collect();
    let total: f64 = prior
        .windows(2)
        .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
        .sum();
    if total <= 0.0 || prior.len() <= 2 {
        return learned.to_vec();
    }
    // The inner turning points, each at its fraction of the length.
    let mut along = 0.0;
    let mut corners = Vec::new();
    for w in prior.windows(2).take(prior.len() - 2) {
        along += (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]);
        corners.push((along / total, w[1]));
    }
    let segments = (learned.len() - 1) as f64;
    let mut out = Vec::with_capacity(learned.len() + corners.len());
    let mut corners = corners.into_iter().peekable();
    for (k, &point) in learned.iter().enumerate() {
        while let Some(&(f, corner)) = corners.peek() {
            let at = f * segments;
            if at > k as f64 - 1e-9 {
                break;
            }
            let j = at.floor() as usize;
            let t = at - j as f64;
            let (s0, s1) = (shift[j], shift[(j + 1).min(shift.len() - 1)]);
            out.push([
                corner[0] + s0[0] + t * (s1[0] - s0[0]),
                corner[1] + s0[1] + t * (s1[1] - s0[1]),
            ]);
            corners.next();
        }
        // A turning point at a sample's own fraction is that sample.
        if let Some(&(f, _)) = corners.peek()
            && (f * segments - k as f64).abs() <= 1e-9
        {
            corners.next();
        }
        out.push(point);
    }
    out
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
        match anyangle_cells(site, profile, a, b) {
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
                let whole = anyangle_cells(site, profile, from, to)?;
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

    fn site(map: &str) -> Arc<Site> {
        Arc::new(Site::of_map(map))
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
            Origin::Frame,
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
            Origin::Repaired,
            from,
            to,
        )
        .unwrap();
        assert!(!planned.route.cells.contains(&Cell::new(4, 4)));
        let four = plan_along(
            &s,
            Connectivity::Four,
            Profile::Default,
            planned.line.clone().unwrap(),
            Origin::Repaired,
            from,
            to,
        )
        .unwrap();
        four.route
            .validate(&s, from, to, Connectivity::Four)
            .unwrap();
    }

    #[test]
    fn the_prior_is_the_profiles_any_angle_route_and_keeps_its_corners() {
        // The wall of the bottom rows again: the prior goes over it.
        let s = site("#########\n#########\n#########\n####.####\n####.####");
        let (from, to) = (Cell::new(0, 4), Cell::new(8, 4));
        let prior = prior_line(&s, Profile::Default, from, to).unwrap();
        assert_eq!(prior.first(), Some(&centre(from)));
        assert_eq!(prior.last(), Some(&centre(to)));
        assert!(prior.len() > 2, "{prior:?}");
        let samples: Vec<[f32; 2]> = resample(&prior, POINTS)
            .into_iter()
            .map(|p| [p[0] as f32, p[1] as f32])
            .collect();
        // Unchanged by the walks: the prior, corners and all.
        let same: Vec<GridPoint> = samples
            .iter()
            .map(|p| [f64::from(p[0]), f64::from(p[1])])
            .collect();
        let line = warped(&prior, &samples, &same);
        for corner in &prior {
            assert!(
                line.iter()
                    .any(|p| (p[0] - corner[0]).abs() < 1e-6 && (p[1] - corner[1]).abs() < 1e-6),
                "{corner:?} not in {line:?}"
            );
        }
        let (_, repaired) = walkable_line(&s, Profile::Default, &line, from, to).unwrap();
        assert!(!repaired);
        // Moved one cell up everywhere: the corners move with it.
        let up: Vec<GridPoint> = same.iter().map(|p| [p[0], p[1] - 1.0]).collect();
        let line = warped(&prior, &samples, &up);
        assert!(line.iter().all(|p| prior.iter().all(|c| c != p)));
        // Straight where the profile may walk it.
        assert_eq!(
            prior_line(&s, Profile::Default, Cell::new(0, 0), Cell::new(8, 0)).unwrap(),
            vec![[0.5, 0.5], [8.5, 0.5]]
        );
    }

    #[test]
    fn low_vision_priors_keep_off_narrow_cells_the_straight_line_crosses() {
        // Narrow cells in the middle of an open room: low vision walks round
        // them (two turns, 2 cell lengths each, cost less than 3 × 3 extra).
        let s = site("#########\n#########\n###nnn###\n#########\n#########");
        let (from, to) = (Cell::new(0, 2), Cell::new(8, 2));
        assert_eq!(prior_line(&s, Profile::Default, from, to).unwrap().len(), 2);
        let prior = prior_line(&s, Profile::LowVision, from, to).unwrap();
        assert!(prior.len() > 2, "{prior:?}");
        let cells = polyline_cells(&s, &prior, |c| Profile::LowVision.passable(&s, c)).unwrap();
        assert!(
            (3..6).all(|x| !cells.contains(&Cell::new(x, 2))),
            "{cells:?}"
        );
    }
}
