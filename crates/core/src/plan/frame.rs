//! From a learned path frame to a route: the step both learned planners share.
//!
//! A frame is `W·H` values, a cell on the path when its value is > 0. The
//! route is the profile's cheapest walk from source to destination where a
//! bright cell costs its usual amount and any other open cell costs
//! [`DARK_COST`] times more. When the frame holds a connected walk between
//! the endpoints that walk comes out unchanged (extraction); when it has
//! gaps, stray cells or a loop, the search bridges the gaps over the fewest
//! dark cells it can (repair), so the route stays close to what was learned.
//! The cost factors are ≥ 1, so the search's heuristic stays admissible, and
//! the result is checked with [`Route::validate_for`] like any other route.

use super::astar::profile_search;
use super::{Connectivity, Origin, PlanError, Profile, Route};
use crate::site::{Cell, Site};

/// Cost factor of an open cell the frame did not light. High enough that a
/// detour of a few bright cells beats a dark shortcut, low enough that a
/// frame with a gap is still repaired along its bright cells.
pub(crate) const DARK_COST: f64 = 4.0;

/// Whether the cell at grid index `i` is on the frame's path.
pub fn bright(frame: &[f32], i: usize) -> bool {
    frame[i] > 0.0
}

/// The route a frame describes from `from` to `to`, and whether it needed
/// repair ([`Origin::Frame`] or [`Origin::Repaired`]).
pub fn route_from_frame(
    site: &Site,
    connectivity: Connectivity,
    profile: Profile,
    frame: &[f32],
    from: Cell,
    to: Cell,
) -> Result<(Route, Origin), PlanError> {
    let lit = |c: Cell| bright(frame, site.grid_index(c));
    let route = profile_search(site, connectivity, from, to, profile, |c| {
        if lit(c) { 1.0 } else { DARK_COST }
    })?;
    route
        .validate_for(site, from, to, connectivity, profile)
        .map_err(|reason| PlanError::Invalid { reason })?;
    let inner = route
        .cells
        .get(1..route.cells.len() - 1)
        .unwrap_or_default();
    let origin = if inner.iter().all(|&c| lit(c)) {
        Origin::Frame
    } else {
        Origin::Repaired
    };
    Ok((route, origin))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn site(map: &str) -> Site {
        let text = format!("name = \"t\"\ncell_m = 1.0\nmap = '''\n{map}\n'''\n");
        Site::parse(&text, Path::new("t.toml")).unwrap()
    }

    fn frame(site: &Site, cells: &[(u16, u16)]) -> Vec<f32> {
        let mut f = vec![-1.0; usize::from(site.width()) * usize::from(site.height())];
        for &(x, y) in cells {
            f[site.grid_index(Cell::new(x, y))] = 1.0;
        }
        f
    }

    #[test]
    fn a_connected_frame_is_followed_even_when_longer() {
        // Open 3×3 room: the frame walks along the top and down the right side
        // instead of the diagonal.
        let s = site("###\n###\n###");
        let f = frame(&s, &[(0, 0), (1, 0), (2, 0), (2, 1), (2, 2)]);
        let (route, origin) = route_from_frame(
            &s,
            Connectivity::Eight,
            Profile::Default,
            &f,
            Cell::new(0, 0),
            Cell::new(2, 2),
        )
        .unwrap();
        assert_eq!(origin, Origin::Frame);
        // Never through the dark centre, although it is the shortest way.
        assert!(!route.cells.contains(&Cell::new(1, 1)), "{:?}", route.cells);
        assert!(route.cells.iter().all(|&c| f[s.grid_index(c)] > 0.0));
    }

    #[test]
    fn a_gap_is_repaired_along_the_bright_cells() {
        let s = site("#####\n#####");
        // Bright along the bottom row except (2, 1); the top row is dark.
        let f = frame(&s, &[(0, 1), (1, 1), (3, 1), (4, 1)]);
        let (route, origin) = route_from_frame(
            &s,
            Connectivity::Eight,
            Profile::Default,
            &f,
            Cell::new(0, 1),
            Cell::new(4, 1),
        )
        .unwrap();
        assert_eq!(origin, Origin::Repaired);
        assert_eq!(route.cells.len(), 5);
        assert!(route.cells.iter().all(|c| c.y == 1), "{:?}", route.cells);
    }
}
