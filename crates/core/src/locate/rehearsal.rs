//! Published confidence where no position is known: the survey-free model
//! rehearses.
//!
//! A surveyed localizer learns what its confidence is worth from held-out
//! sessions of its survey ([`super::crossval`]). The survey-free model has no
//! truth to learn from, and its raw belief trusts its own radio model
//! completely: one beacon heard once puts nearly all the mass next to that
//! beacon, so the raw "within one cell" is 0.99 while the fix is right one
//! time in seven on the paper's floor. What the model does know is how
//! little it knows: tx power, path-loss exponent and range were defaults or
//! fitted from unlabelled scans, and walls, shelves and bodies are not in it.
//!
//! So before it serves, it rehearses: simulated walkers cross the site's
//! walkable cells at walking pace, each in a world drawn around the model's
//! own radio by that doubt (the receiver's gain, each anchor's power, a
//! fixed shadow per cell and anchor, detection odds off by a factor, the
//! anchor hung a little off its place in the site file), hear what that world
//! makes them hear, and are localized by the model through the same tracker
//! the gateway runs. Their (raw confidence, error) pairs fit the
//! [`ConfidenceMap`] the published confidence goes through, exactly as
//! held-out survey rows do for a surveyed localizer. Confidence then means
//! "within one cell this often, were the world as far from the model as the
//! model admits": a fix (one beacon heard once, say) is published at the
//! rate fixes like it earned in rehearsal, per class of window where that
//! scores better ([`ConfidenceMap::fit`]).
//!
//! The doubt itself is not fitted to any site: it is the spread of what
//! these parameters are in real installations (iBeacon measured power is
//! set per product, −50 to −80 dBm; indoor shadowing of 4–8 dB). It stays
//! that wide after a calibration: a radio fitted to unlabelled scans fits
//! what was heard along the positions its own fit guessed, and may be
//! confidently wrong where they were. Narrowing the doubt for fitted anchors
//! (tx 3 dB, receiver 2 dB, detection odds e^N(0, 0.5)) made published
//! confidence less honest on both real sets it was measured on: the paper's
//! floor calibrated on its crowd file (mean |gap| 0.091 → 0.049 without it)
//! and the five-floor mall recalibrated from its walks (0.161 → 0.085).

use std::sync::Arc;

use rand::rngs::Xoshiro256PlusPlus;
use rand::{RngExt, SeedableRng};
use rand_distr::{Distribution, Normal, StandardNormal};

use super::calibration::Calibration;
use super::pathloss::{DETECTION_BOUNDS, PathLoss, PathLossConfig};
use super::reliability::{ConfidenceMap, KnownFix, Mapped};
use super::strongest::Strongest;
use super::tracker::{Tracker, TrackerConfig, open_neighbours};
use super::window::WindowConfig;
use super::{Localizer, LocalizerError};
use crate::site::Site;

/// How far the world may be from the model.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Doubt {
    /// Spread of the receiver's gain, dB, common to every anchor it hears:
    /// phones and dongles differ by several dB.
    receiver_db: f64,
    /// Spread of each anchor's real power at 1 m around the model's, dB: its
    /// measured power may be anything real products ship with.
    tx_db: f64,
    /// Spread of a fixed shadow per cell and anchor (walls and shelves), dB.
    shadow_db: f64,
    /// Spread of the log of the factor each anchor's real detection odds are
    /// off by.
    detection_log_odds: f64,
    /// Spread of where each anchor really hangs around where the site file
    /// puts it, metres per axis (read off a plan, paced out, moved since).
    position_m: f64,
}

/// The doubt every rehearsal draws its worlds with.
const DOUBT: Doubt = Doubt {
    receiver_db: 6.0,
    tx_db: 6.0,
    shadow_db: 4.0,
    detection_log_odds: 1.0,
    position_m: 1.0,
};

/// The survey-free localizer the gateway serves: the config's path-loss
/// model with `calibration` applied (the config's file when `None` is
/// given and it names one), its confidence rehearsed.
pub fn path_loss(
    config: &PathLossConfig,
    calibration: Option<&Calibration>,
    site: &Arc<Site>,
    windows: &WindowConfig,
    tracker: &TrackerConfig,
) -> Result<Box<dyn Localizer>, LocalizerError> {
    let loaded = match calibration {
        Some(_) => None,
        None => config.load_calibration(site)?,
    };
    let calibration = calibration.or(loaded.as_ref());
    let model = PathLoss::calibrated(site, windows.orientation, config, calibration)?;
    // The model is both the localizer and its world: scored through a
    // borrow, never cloned.
    let fixes = rehearse(
        &mut model.borrowed(),
        &model,
        site,
        tracker,
        windows.stride_s,
    );
    Ok(Box::new(Mapped::new(model, ConfidenceMap::fit(&fixes))))
}

/// The strongest-beacon baseline, its confidence rehearsed in the worlds of
/// the config's path-loss model: a baseline's confidence is published too,
/// and must mean the same.
pub fn strongest(
    config: &PathLossConfig,
    site: &Arc<Site>,
    windows: &WindowConfig,
    tracker: &TrackerConfig,
) -> Result<Box<dyn Localizer>, LocalizerError> {
    let calibration = config.load_calibration(site)?;
    let world = PathLoss::calibrated(site, windows.orientation, config, calibration.as_ref())?;
    Ok(rehearsed(
        Strongest::new(config, site, windows.orientation)?,
        &world,
        site,
        tracker,
        windows.stride_s,
    ))
}

/// Rehearsed fixes: enough for a map per class of window on a small site…
const MOST_WINDOWS: usize = 4000;
/// …and never fewer, however large the site: below this a map's bins are
/// noise.
const FEWEST_WINDOWS: usize = 600;
/// Cell-anchor terms a rehearsal may evaluate before it settles for fewer
/// windows (about a second of one core): a 200 × 200 m floor at 1 m cells
/// with 50 beacons costs 2.4 M terms per window, so it rehearses 600
/// windows where the paper's floor rehearses 4,000.
const BUDGET_TERMS: usize = 400_000_000;

/// Windows to rehearse on a site of `cells` open cells and `anchors` anchors:
/// each costs a likelihood per cell and anchor and a tracker step (about
/// nine terms per cell).
fn windows_for(cells: usize, anchors: usize) -> usize {
    (BUDGET_TERMS / (cells * (anchors + 9)).max(1)).clamp(FEWEST_WINDOWS, MOST_WINDOWS)
}

/// Windows per simulated walk: long enough for the tracker to settle, short
/// enough to see many starts (a track's first fixes are its worst).
const WALK_WINDOWS: usize = 20;
/// Walking pace range, m/s (standing still to brisk).
const PACE_M_S: (f64, f64) = (0.0, 1.4);

/// `localizer` with its confidence fitted on fixes rehearsed in worlds
/// drawn around `world` (its own radio model, or the one a baseline is
/// judged against) with [`DOUBT`], windows `stride_s` apart through `tracker`.
fn rehearsed<L: Localizer + 'static>(
    mut localizer: L,
    world: &PathLoss,
    site: &Arc<Site>,
    tracker: &TrackerConfig,
    stride_s: f64,
) -> Box<dyn Localizer> {
    let fixes = rehearse(&mut localizer, world, site, tracker, stride_s);
    Box::new(Mapped::new(localizer, ConfidenceMap::fit(&fixes)))
}

/// A known fix of every rehearsed window that heard anything. Seeded: the
/// same model on the same site always publishes the same confidence.
fn rehearse(
    localizer: &mut impl Localizer,
    world: &PathLoss,
    site: &Arc<Site>,
    tracker: &TrackerConfig,
    stride_s: f64,
) -> Vec<KnownFix> {
    let cells = site.open_cells();
    let n_anchors = world.inv_sigma().len();
    if cells.is_empty() || n_anchors == 0 {
        return Vec::new();
    }
    let mut rng = Xoshiro256PlusPlus::seed_from_u64(0x5eed_c0f1);
    let mut tracker_run = Tracker::new(tracker.clone(), site.clone());
    let noise: Vec<Normal<f64>> = world
        .inv_sigma()
        .iter()
        .map(|&s| Normal::new(0.0, 1.0 / f64::from(s).max(1e-3)).expect("finite spread"))
        .collect();
    let neighbours = open_neighbours(site);
    let windows = windows_for(cells.len(), n_anchors);
    let mut fixes = Vec::with_capacity(windows);
    let (mut rssi, mut heard) = (vec![0.0f32; n_anchors], vec![false; n_anchors]);
    let mut ll = vec![0.0f32; cells.len()];
    // One track: a gap longer than the tracker's reset starts each walk afresh.
    let entity: Arc<str> = Arc::from("rehearsal");
    let mut start = 0.0;
    let mut walk = 0;
    while fixes.len() < windows {
        walk += 1;
        // A new world per walk: the doubt is about the world, not the window.
        let receiver = DOUBT.receiver_db * normal(&mut rng);
        let offset: Vec<f64> = (0..n_anchors)
            .map(|_| receiver + DOUBT.tx_db * normal(&mut rng))
            .collect();
        let odds: Vec<f64> = (0..n_anchors)
            .map(|_| DOUBT.detection_log_odds * normal(&mut rng))
            .collect();
        // Reading the model at a cell displaced by (dx, dy) is hearing the
        // anchor as if it hung (−dx, −dy) from where the site file says.
        let spread_cells = DOUBT.position_m / site.cell_m;
        let moved: Vec<(i32, i32)> = (0..n_anchors)
            .map(|_| {
                let mut draw = || (spread_cells * normal(&mut rng)).round() as i32;
                (draw(), draw())
            })
            .collect();
        let world_seed: u64 = rng.random();
        let pace = rng.random_range(PACE_M_S.0..=PACE_M_S.1);
        let cells_per_window = pace * stride_s / site.cell_m;
        let mut here = rng.random_range(0..cells.len());
        let mut owed = 0.0;
        for k in 0..WALK_WINDOWS {
            owed += cells_per_window;
            while owed >= 1.0 {
                // The cell itself comes first: a step goes to one of the others.
                let next = &neighbours[here][1..];
                if !next.is_empty() {
                    here = next[rng.random_range(0..next.len())] as usize;
                }
                owed -= 1.0;
            }
            for a in 0..n_anchors {
                let cell = displaced(site, cells[here], moved[a]).unwrap_or(here);
                let Some((mu, detection)) = world.heard_at(cell, a) else {
                    heard[a] = false;
                    continue;
                };
                let p = shifted(detection, odds[a]);
                heard[a] = rng.random::<f64>() < p;
                let shadow = DOUBT.shadow_db * shadow(world_seed, here, a);
                rssi[a] = (f64::from(mu) + offset[a] + shadow + noise[a].sample(&mut rng)) as f32;
            }
            if !heard.contains(&true) {
                continue;
            }
            localizer.log_likelihood(&rssi, &heard, &mut ll);
            let fix = tracker_run.update(&entity, start + k as f64 * stride_s, &ll);
            fixes.push(KnownFix {
                raw: fix.confidence,
                error_cells: fix.cell.distance(cells[here]),
                heard: heard.iter().filter(|&&h| h).count(),
                group: walk,
                weight: 1.0,
            });
        }
        start += (WALK_WINDOWS as f64 + 1.0) * stride_s + tracker.reset_after_s;
    }
    fixes
}

/// The open index of `cell` moved by `by`, if that cell is open.
fn displaced(site: &Site, cell: crate::site::Cell, by: (i32, i32)) -> Option<usize> {
    let x = u16::try_from(i32::from(cell.x) + by.0).ok()?;
    let y = u16::try_from(i32::from(cell.y) + by.1).ok()?;
    site.open_index(crate::site::Cell::new(x, y))
}

/// A standard normal draw.
fn normal(rng: &mut Xoshiro256PlusPlus) -> f64 {
    StandardNormal.sample(rng)
}

/// `p` with its odds multiplied by `e^log_odds`, kept in the model's bounds.
fn shifted(p: f64, log_odds: f64) -> f64 {
    let odds = p / (1.0 - p) * log_odds.exp();
    (odds / (1.0 + odds)).clamp(DETECTION_BOUNDS.0, DETECTION_BOUNDS.1)
}

/// One world's fixed shadow at (cell, anchor), in standard deviations: the
/// same every time that world is asked, drawn from a hash of the three so
/// that the field of a 40,000-cell floor is never built whole.
fn shadow(world_seed: u64, cell: usize, anchor: usize) -> f64 {
    let key = ((cell as u64) << 20 | anchor as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    normal(&mut Xoshiro256PlusPlus::seed_from_u64(world_seed ^ key))
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    /// A 12 × 8 m hall with a beacon in each corner.
    fn hall() -> Arc<Site> {
        let mut text = String::from("name = \"hall\"\ncell_m = 1.0\nmap = '''\n");
        for _ in 0..8 {
            text.push_str(&"#".repeat(12));
            text.push('\n');
        }
        text.push_str("'''\n");
        for (i, (x, y)) in [(0, 0), (11, 0), (0, 7), (11, 7)].into_iter().enumerate() {
            text.push_str(&format!(
                "[[beacon]]\nid = \"b{i}\"\nuuid = \"b9407f30-f5f8-466e-aff9-25556b57fe6d\"\nmajor = 1\nminor = {i}\ncell = [{x}, {y}]\n"
            ));
        }
        Arc::new(Site::parse(&text, Path::new("hall.toml")).unwrap())
    }

    fn survey_free(site: &Arc<Site>) -> Box<dyn Localizer> {
        path_loss(
            &PathLossConfig::default(),
            None,
            site,
            &WindowConfig::default(),
            &TrackerConfig::default(),
        )
        .unwrap()
    }

    #[test]
    fn one_beacon_heard_once_is_not_published_as_certain() {
        let site = hall();
        let mut localizer = survey_free(&site);
        // Only the first corner's beacon, loud: the raw belief piles up next
        // to it.
        let (rssi, heard) = ([-60.0, -105.0, -105.0, -105.0], [true, false, false, false]);
        let mut ll = vec![0.0; site.open_cells().len()];
        localizer.log_likelihood(&rssi, &heard, &mut ll);
        let mut tracker = Tracker::new(TrackerConfig::default(), site.clone());
        let fix = tracker.update(&Arc::from("phone"), 0.0, &ll);
        let published = localizer.confidence(fix.confidence, 1);
        assert!(
            fix.confidence > 0.5,
            "raw {} published {published}",
            fix.confidence
        );
        assert!(
            published < 0.6 && published < fix.confidence - 0.3,
            "raw {} published {published}",
            fix.confidence
        );
    }

    #[test]
    fn the_same_site_and_model_always_publish_the_same_confidence() {
        let site = hall();
        let (a, b) = (survey_free(&site), survey_free(&site));
        for raw in [0.05, 0.3, 0.6, 0.9, 0.99] {
            for heard in 1..=4 {
                assert_eq!(a.confidence(raw, heard), b.confidence(raw, heard));
            }
        }
    }
}
