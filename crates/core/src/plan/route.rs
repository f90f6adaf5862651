//! What a planner returns, the check every returned route must pass, and
//! the line a walker is given to follow.
//!
//! A route is served twice over: as its cells (what the grid, the tracker
//! and a frame repair reason about) and as a line in metres (what a person
//! walks, a map draws and guidance measures progress on). The line is the
//! one the planner drew when it drew one (the desire lines, any-angle),
//! checked segment by segment against the walls and the cells the profile
//! may not use, else the route's cells' centres; a planner's line that
//! fails its check is replaced by the cells' line and said so
//! ([`LineSource::Fallback`]), so a line a client is given is always
//! walkable.

use serde::Serialize;

use super::anyangle::{GridPoint, centre, touches_only, world_of_point};
use super::{Connectivity, Planned, Profile};
use crate::site::{Cell, Site};

/// An ordered walk from the first cell to the last.
#[derive(Clone, Debug, PartialEq)]
pub struct Route {
    pub cells: Vec<Cell>,
}

/// One step of a route as published: the cell and its centre in metres.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Waypoint {
    pub cell: Cell,
    pub x_m: f64,
    pub y_m: f64,
}

/// A vertex of a served route's line, in the site's metres.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct LinePoint {
    pub x_m: f64,
    pub y_m: f64,
}

/// Where a served line comes from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum LineSource {
    /// The line the planner drew, checked.
    Planner,
    /// The planner drew none (A*, the GAN modes): the cells' centres.
    Cells,
    /// The planner's line failed its check (it crossed a wall, a blocked
    /// cell or one the profile may not use, or missed an end): the cells'
    /// centres were served instead.
    Fallback,
}

/// The line a walker is given for a planned route (see the module doc).
#[derive(Clone, Debug, PartialEq)]
pub struct ServedLine {
    /// Vertices in cell units, from the source's centre to the
    /// destination's, only the turning points kept.
    pub points: Vec<GridPoint>,
    pub source: LineSource,
}

/// How far (cells) a vertex of a planner's line may be from the straight
/// line its neighbours would leave to be dropped: a hundredth of a cell
/// leaves the line where it was (a centimetre on half-metre cells) while
/// dropping the many points a smooth line is drawn with where it runs
/// straight.
const LINE_TOLERANCE_CELLS: f64 = 0.01;

impl ServedLine {
    /// The line served for `planned`, a route for `profile` on `site`.
    pub fn of(site: &Site, planned: &Planned, profile: Profile) -> ServedLine {
        let cells_line = |source| ServedLine {
            source,
            ..ServedLine::of_cells(&planned.route)
        };
        let Some(drawn) = planned.line.as_deref() else {
            return cells_line(LineSource::Cells);
        };
        let simple = simplified(drawn, LINE_TOLERANCE_CELLS);
        // Dropping a vertex moves the line by a hundredth of a cell, which
        // can still touch a corner the drawn line kept clear of: the drawn
        // line is served then.
        let fallback = (simple.len() < drawn.len()).then(|| drawn.to_vec());
        std::iter::once(simple)
            .chain(fallback)
            .find(|line| walkable_line(site, profile, line, &planned.route.cells))
            .map_or_else(
                || cells_line(LineSource::Fallback),
                |points| ServedLine {
                    points,
                    source: LineSource::Planner,
                },
            )
    }

    /// The line through the centres of `route`'s cells, straight runs
    /// merged.
    pub fn of_cells(route: &Route) -> ServedLine {
        let centres: Vec<GridPoint> = route.cells.iter().map(|&c| centre(c)).collect();
        ServedLine {
            points: simplified(&centres, 0.0),
            source: LineSource::Cells,
        }
    }

    /// The vertices in the site's metres, as published.
    pub fn metres(&self, site: &Site) -> Vec<LinePoint> {
        self.points
            .iter()
            .map(|&p| {
                let [x_m, y_m] = world_of_point(site, p);
                LinePoint { x_m, y_m }
            })
            .collect()
    }

    /// Length in metres.
    pub fn length_m(&self, site: &Site) -> f64 {
        self.points
            .windows(2)
            .map(|w| (w[1][0] - w[0][0]).hypot(w[1][1] - w[0][1]))
            .sum::<f64>()
            * site.cell_m
    }
}

/// Whether `line` runs from the centre of the route's first cell to the
/// centre of its last through only cells on the grid that are walkable and
/// that `profile` may use, the two cells beside every corner it crosses
/// exactly included (a line through a corner between two walls goes
/// through the wall), and never further than a step from the route's
/// `cells` (the waypoints are the cells it crosses, and maneuvers, places
/// and junctions are looked up on them).
fn walkable_line(site: &Site, profile: Profile, line: &[GridPoint], cells: &[Cell]) -> bool {
    // foldhash, not SipHash: up to nine lookups per cell the line crosses.
    let route: foldhash::HashSet<Cell> = cells.iter().copied().collect();
    let near_route = |cell: Cell| {
        (-1i32..=1).any(|dy| {
            (-1i32..=1).any(|dx| {
                let (x, y) = (i32::from(cell.x) + dx, i32::from(cell.y) + dy);
                matches!((u16::try_from(x), u16::try_from(y)), (Ok(x), Ok(y)) if route.contains(&Cell::new(x, y)))
            })
        })
    };
    let at = |p: Option<&GridPoint>, c: Option<&Cell>| match (p, c) {
        (Some(p), Some(&c)) => {
            let want = centre(c);
            (p[0] - want[0]).abs() < 1e-6 && (p[1] - want[1]).abs() < 1e-6
        }
        _ => false,
    };
    let open = |[x, y]: [i64; 2]| {
        let (Ok(x), Ok(y)) = (u16::try_from(x), u16::try_from(y)) else {
            return false;
        };
        let cell = Cell::new(x, y);
        site.contains(cell)
            && site.walkable(cell)
            && profile.passable(site, cell)
            && near_route(cell)
    };
    at(line.first(), cells.first())
        && at(line.last(), cells.last())
        && line.windows(2).all(|w| touches_only(w[0], w[1], open))
}

/// `points` with the vertices that stray no more than `tolerance` (cells)
/// from the line between the kept ones dropped (Douglas–Peucker; with 0,
/// only the vertices a straight run passes through).
fn simplified(points: &[GridPoint], tolerance: f64) -> Vec<GridPoint> {
    kept_vertices(points, tolerance)
        .into_iter()
        .map(|i| points[i])
        .collect()
}

/// The indices of the vertices [`simplified`] keeps, in order.
pub(crate) fn kept_vertices(points: &[GridPoint], tolerance: f64) -> Vec<usize> {
    fn mark(points: &[GridPoint], a: usize, b: usize, tolerance: f64, keep: &mut [bool]) {
        if b <= a + 1 {
            return;
        }
        let ([ax, ay], [bx, by]) = (points[a], points[b]);
        let len = (bx - ax).hypot(by - ay);
        let (far, dist) = (a + 1..b)
            .map(|i| {
                let [x, y] = points[i];
                let d = if len > 0.0 {
                    ((bx - ax) * (ay - y) - (ax - x) * (by - ay)).abs() / len
                } else {
                    (x - ax).hypot(y - ay)
                };
                (i, d)
            })
            .max_by(|p, q| p.1.total_cmp(&q.1))
            .expect("b > a + 1");
        if dist > tolerance + 1e-9 {
            keep[far] = true;
            mark(points, a, far, tolerance, keep);
            mark(points, far, b, tolerance, keep);
        }
    }
    if points.len() <= 2 {
        return (0..points.len()).collect();
    }
    let mut keep = vec![false; points.len()];
    keep[0] = true;
    keep[points.len() - 1] = true;
    mark(points, 0, points.len() - 1, tolerance, &mut keep);
    (0..points.len()).filter(|&i| keep[i]).collect()
}

impl Route {
    /// Length in metres along cell centres.
    pub fn length_m(&self, site: &Site) -> f64 {
        self.cells
            .windows(2)
            .map(|w| w[0].distance(w[1]))
            .sum::<f64>()
            * site.cell_m
    }

    pub(crate) fn waypoints(&self, site: &Site) -> Vec<Waypoint> {
        self.cells
            .iter()
            .map(|&cell| {
                let (x_m, y_m) = site.metres(cell);
                Waypoint { cell, x_m, y_m }
            })
            .collect()
    }

    /// Checks that the route is walkable from `from` to `to`: exact endpoints,
    /// every cell walkable, every step allowed by `connectivity`, no cell twice.
    pub fn validate(
        &self,
        site: &Site,
        from: Cell,
        to: Cell,
        connectivity: Connectivity,
    ) -> Result<(), String> {
        self.validate_for(site, from, to, connectivity, Profile::Default)
    }

    /// [`Route::validate`] for a walker with `profile`: also no cell the
    /// profile may not use (stairs in a wheelchair), nor a diagonal past one.
    pub fn validate_for(
        &self,
        site: &Site,
        from: Cell,
        to: Cell,
        connectivity: Connectivity,
        profile: Profile,
    ) -> Result<(), String> {
        let (Some(&first), Some(&last)) = (self.cells.first(), self.cells.last()) else {
            return Err("the route is empty".into());
        };
        if first != from || last != to {
            return Err(format!(
                "the route runs {first} → {last}, not {from} → {to}"
            ));
        }
        if let Some(c) = self.cells.iter().find(|&&c| !site.walkable(c)) {
            return Err(format!("the route crosses {c}, which is not walkable"));
        }
        if let Some(c) = self.cells.iter().find(|&&c| !profile.passable(site, c)) {
            return Err(format!(
                "the route crosses {c}, which the {} profile may not use",
                profile.name()
            ));
        }
        if let Some(w) = self
            .cells
            .windows(2)
            .find(|w| !connectivity.step_ok_by(w[0], w[1], |c| profile.passable(site, c)))
        {
            return Err(format!("the step {} → {} is not allowed", w[0], w[1]));
        }
        let mut seen = std::collections::HashSet::with_capacity(self.cells.len());
        if let Some(c) = self.cells.iter().find(|&&c| !seen.insert(c)) {
            return Err(format!("the route visits {c} twice"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::anyangle::AnyAngle;
    use crate::plan::{Origin, Planner, Timings};

    fn planned(cells: &[(u16, u16)], line: Option<Vec<GridPoint>>) -> Planned {
        Planned {
            route: Route {
                cells: cells.iter().map(|&(x, y)| Cell::new(x, y)).collect(),
            },
            origin: Origin::Frame,
            samples: 1,
            frame: None,
            line,
            timings: Timings::default(),
        }
    }

    #[test]
    fn cells_are_served_with_their_straight_runs_merged() {
        let site = Site::of_map("####\n####\n");
        let served = ServedLine::of(
            &site,
            &planned(&[(0, 0), (1, 0), (2, 0), (3, 1)], None),
            Profile::Default,
        );
        assert_eq!(served.source, LineSource::Cells);
        assert_eq!(served.points, vec![[0.5, 0.5], [2.5, 0.5], [3.5, 1.5]]);
        assert_eq!(served.metres(&site).len(), 3);
        assert!((served.length_m(&site) - (2.0 + 2f64.sqrt()) * site.cell_m).abs() < 1e-9);
    }

    #[test]
    fn a_drawn_line_is_served_simplified_when_it_keeps_off_walls() {
        let site = Site::of_map("####\n####\n####\n");
        // Points along a straight diagonal, and one a thousandth of a cell
        // off it: all dropped but the ends.
        let drawn = vec![[0.5, 0.5], [1.5, 1.501], [2.5, 2.5]];
        let served = ServedLine::of(
            &site,
            &planned(&[(0, 0), (1, 1), (2, 2)], Some(drawn)),
            Profile::Default,
        );
        assert_eq!(served.source, LineSource::Planner);
        assert_eq!(served.points, vec![[0.5, 0.5], [2.5, 2.5]]);
        // Any-angle serves its own vertices.
        let any = AnyAngle::new(std::sync::Arc::new(site.clone()));
        let p = any
            .plan(Cell::new(0, 0), Cell::new(3, 2), Profile::Default)
            .unwrap();
        let served = ServedLine::of(&site, &p, Profile::Default);
        assert_eq!(served.source, LineSource::Planner);
        assert_eq!(served.points, vec![[0.5, 0.5], [3.5, 2.5]]);
    }

    #[test]
    fn a_drawn_line_through_a_wall_or_past_an_end_gives_way_to_the_cells() {
        // The wall at (1, 0): a line from (0, 0) to (2, 0) straight through
        // it, with a route round it.
        let site = Site::of_map("#.#\n###\n");
        let around = [(0, 0), (1, 1), (2, 0)];
        let through = vec![[0.5, 0.5], [2.5, 0.5]];
        let served = ServedLine::of(&site, &planned(&around, Some(through)), Profile::Default);
        assert_eq!(served.source, LineSource::Fallback);
        assert_eq!(served.points, vec![[0.5, 0.5], [1.5, 1.5], [2.5, 0.5]]);
        // Cutting the wall's corner is going through it.
        let corner = vec![[0.5, 0.5], [1.0, 1.0], [2.5, 0.5]];
        let served = ServedLine::of(&site, &planned(&around, Some(corner)), Profile::Default);
        assert_eq!(served.source, LineSource::Fallback);
        // A line that stops short of the destination's centre.
        let short = vec![[0.5, 0.5], [1.5, 1.5], [2.4, 0.6]];
        let served = ServedLine::of(&site, &planned(&around, Some(short)), Profile::Default);
        assert_eq!(served.source, LineSource::Fallback);
        // A line the route's cells do not follow (the route goes round by
        // the bottom row, the line straight along the top).
        let site = Site::of_map("######\n######\n######\n######\n######\n");
        let round: Vec<(u16, u16)> = [(0, 0), (0, 1), (0, 2), (0, 3)]
            .into_iter()
            .chain((1..5).map(|x| (x, 4)))
            .chain([(5, 3), (5, 2), (5, 1), (5, 0)])
            .collect();
        let straight = vec![[0.5, 0.5], [5.5, 0.5]];
        let served = ServedLine::of(&site, &planned(&round, Some(straight)), Profile::Default);
        assert_eq!(served.source, LineSource::Fallback);
    }
}
