//! Surveys from walks with timed waypoints: one floor of the Indoor Location
//! Competition layout (`floor_info.json`, `geojson_map.json`,
//! `floor_image.png`, `path_data_files/*.txt`) in, a site, a labelled survey
//! and estimated beacon positions out (`gangway survey import`).
//!
//! Its own module because it is the one place that knows that layout: the
//! site comes from the floor plan ([`floor`]), the survey rows are written in
//! the project's metric survey CSV (`x_m,y_m,t,<beacon ids>`, read by
//! `locate::survey`), and what it writes is loaded back with the gateway's
//! own loaders before it is reported, so an import that succeeds is one
//! `gangway check` and `gangway eval localization` accept.
//!
//! - **Rows.** Each walk's iBeacon readings are cut into the gateway's own
//!   windows (4 s long every 2 s by default, the strongest reading per
//!   beacon, as `[window]`'s defaults), one row per window. A row is labelled
//!   at the mean time of its readings, its position interpolated in time
//!   between the two waypoints around it (the surveyor walked roughly straight
//!   between taps). Refused and counted: rows before a walk's first or after
//!   its last waypoint, between waypoints further apart in time than
//!   `max_gap_s`, or whose waypoints imply walking faster than
//!   `max_speed_mps`, and rows whose position is off the grid or on a blocked
//!   cell (the survey loader refuses those).
//! - **Beacons.** See [`estimate`]; an iBeacon id (uuid/major/minor) heard
//!   from several MAC addresses is several transmitters, so each (id, MAC)
//!   becomes its own beacon with its `mac` set (the gateway matches those
//!   only to sightings from that address), not one averaged position nowhere
//!   near any of them. An id heard from one MAC stays an id without `mac`,
//!   so it is matched from any address, as a hand-written site would be.
//! - **Bad lines.** A line that does not parse is reported with its file,
//!   line and field and skipped; the rest of the walk is read.

pub mod building;
mod floor;

use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use anyhow::Context;
use serde::Serialize;
use uuid::Uuid;

use crate::locate::survey::Survey;
use crate::locate::window::WindowConfig;
use crate::sighting::{BeaconId, Mac};
use crate::site::{BeaconDoc, Site, write_doc};

/// The "not heard" value the survey is written with (`[localizer.knn]
/// not_heard`'s default).
const NOT_HEARD: i16 = -200;
/// Readings within this many dB of a beacon's strongest are the ones its
/// position is estimated from.
const STRONGEST_DB: f64 = 6.0;
/// A beacon heard fewer times than this (labelled readings) gets no position.
const MIN_READINGS: usize = 3;
/// Problems printed one by one; the rest are counted.
const SHOWN_PROBLEMS: usize = 20;

/// What an import is asked for.
#[derive(Clone, Debug)]
pub struct Options {
    /// The site's name (default: the floor directory's name).
    pub name: Option<String>,
    pub cell_m: f64,
    /// The rows' windows, seconds.
    pub window_s: f64,
    pub stride_s: f64,
    /// Rows between waypoints further apart in time are refused.
    pub max_gap_s: f64,
    /// Rows between waypoints implying a faster walk are refused, m/s.
    pub max_speed_mps: f64,
}

impl Default for Options {
    fn default() -> Self {
        let window = WindowConfig::default();
        Options {
            name: None,
            cell_m: 1.0,
            window_s: window.length_s,
            stride_s: window.stride_s,
            max_gap_s: 30.0,
            max_speed_mps: 2.5,
        }
    }
}

/// What an import read, wrote and refused.
#[derive(Clone, Debug, Default, Serialize)]
pub struct Report {
    pub site: PathBuf,
    pub survey: PathBuf,
    pub walks: usize,
    pub waypoints: usize,
    /// iBeacon readings read.
    pub readings: usize,
    /// Lines that did not parse (skipped).
    pub lines_skipped: usize,
    pub cells: usize,
    pub walkable_cells: usize,
    pub places: usize,
    pub rows: usize,
    pub refused: Refused,
    pub beacons: usize,
    /// Readings of the beacons kept (with a labelled position).
    pub readings_kept: usize,
    /// Ids heard from several MACs, each MAC then a beacon of its own.
    pub shared_ids_split: usize,
    /// Beacons (ids, or an id's MACs) heard fewer than [`MIN_READINGS`]
    /// times at a known position.
    pub rare_ids_dropped: usize,
    pub rare_readings_dropped: usize,
    /// The problems found, the first few in full.
    pub problems: Vec<String>,
}

/// Rows refused, by reason.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize)]
pub struct Refused {
    pub before_first_waypoint: usize,
    pub after_last_waypoint: usize,
    pub waypoint_gap: usize,
    pub implausible_speed: usize,
    pub off_walkable: usize,
}

/// A transmitter as the site knows it: its id, and its MAC where the id is
/// heard from several.
pub(crate) type Key = (BeaconId, Option<Mac>);

/// Why a moment of a walk has no position.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Refusal {
    BeforeFirst,
    AfterLast,
    Gap,
    Speed,
    OffWalkable,
}

impl Refused {
    fn count(&mut self, why: Refusal) {
        *match why {
            Refusal::BeforeFirst => &mut self.before_first_waypoint,
            Refusal::AfterLast => &mut self.after_last_waypoint,
            Refusal::Gap => &mut self.waypoint_gap,
            Refusal::Speed => &mut self.implausible_speed,
            Refusal::OffWalkable => &mut self.off_walkable,
        } += 1;
    }
}

/// One iBeacon reading of a walk.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct Reading {
    /// Seconds (Unix time).
    pub(crate) t: f64,
    pub(crate) id: BeaconId,
    pub(crate) mac: Mac,
    pub(crate) tx_power: i8,
    pub(crate) rssi: i16,
}

/// One walk file: its waypoints (seconds, metres) in time order and readings.
#[derive(Clone, Debug, Default, PartialEq)]
pub(crate) struct Walk {
    /// The file's name without its extension: how reports name the walk.
    pub(crate) name: String,
    pub(crate) waypoints: Vec<(f64, [f64; 2])>,
    pub(crate) readings: Vec<Reading>,
}

/// Reads one walk file's text; each line that does not parse adds a problem
/// naming `path`, its line and field, and is skipped.
pub(crate) fn read_walk(path: &Path, text: &str, problems: &mut Vec<String>) -> Walk {
    let mut walk = Walk {
        name: path
            .file_stem()
            .map_or_else(String::new, |stem| stem.to_string_lossy().into_owned()),
        ..Walk::default()
    };
    for (n, line) in text.lines().enumerate() {
        let line = line.trim_end_matches('\r');
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let fields: Vec<&str> = line.split('\t').collect();
        let problem = |field: &str, reason: String| {
            format!(
                "{}:{}: field `{field}`: {reason}; the line is skipped",
                path.display(),
                n + 1
            )
        };
        let parsed = match fields.get(1).copied() {
            Some("TYPE_WAYPOINT") => waypoint(&fields).map(|w| walk.waypoints.push(w)),
            Some("TYPE_BEACON") => reading(&fields).map(|r| walk.readings.push(r)),
            // Other sensors (WiFi, IMU) have nothing a survey needs.
            Some(_) => Ok(()),
            None => Err((
                "type",
                "missing: expected `<unix ms>\\t<TYPE_…>\\t…`".into(),
            )),
        };
        if let Err((field, reason)) = parsed {
            problems.push(problem(field, reason));
        }
    }
    walk.waypoints.sort_by(|a, b| a.0.total_cmp(&b.0));
    walk.readings.sort_by(|a, b| a.t.total_cmp(&b.t));
    walk
}

type FieldError = (&'static str, String);

fn field<'a>(fields: &[&'a str], i: usize, name: &'static str) -> Result<&'a str, FieldError> {
    fields.get(i).map(|f| f.trim()).ok_or((
        name,
        format!("missing: the line has {} fields", fields.len()),
    ))
}

fn number<T: std::str::FromStr>(
    fields: &[&str],
    i: usize,
    name: &'static str,
    what: &str,
) -> Result<T, FieldError> {
    let text = field(fields, i, name)?;
    text.parse()
        .map_err(|_| (name, format!("{text:?} is not {what}")))
}

fn time(fields: &[&str]) -> Result<f64, FieldError> {
    let ms: i64 = number(fields, 0, "time", "a Unix time in milliseconds")?;
    Ok(ms as f64 / 1000.0)
}

fn waypoint(fields: &[&str]) -> Result<(f64, [f64; 2]), FieldError> {
    let metres = |i, name| {
        number::<f64>(fields, i, name, "a number of metres").and_then(|v| {
            if v.is_finite() {
                Ok(v)
            } else {
                Err((name, format!("{v} is not finite")))
            }
        })
    };
    Ok((time(fields)?, [metres(2, "x")?, metres(3, "y")?]))
}

fn reading(fields: &[&str]) -> Result<Reading, FieldError> {
    let uuid = field(fields, 2, "uuid")?;
    let uuid = Uuid::parse_str(uuid).map_err(|_| ("uuid", format!("{uuid:?} is not a UUID")))?;
    let rssi: i16 = number(fields, 6, "rssi", "an RSSI in whole dBm")?;
    if !(-127..0).contains(&rssi) {
        return Err((
            "rssi",
            format!("{rssi} dBm is not an RSSI a receiver reports"),
        ));
    }
    Ok(Reading {
        t: time(fields)?,
        id: BeaconId {
            uuid,
            major: number(fields, 3, "major", "a major number (0-65535)")?,
            minor: number(fields, 4, "minor", "a minor number (0-65535)")?,
        },
        tx_power: number(fields, 5, "tx power", "a power in whole dBm")?,
        mac: {
            let mac = field(fields, 8, "mac")?;
            mac.parse().map_err(|e| ("mac", e))?
        },
        rssi,
    })
}

/// Where the walker was at `t`, interpolated in time between the waypoints
/// around it, or why that is not known well enough.
pub(crate) fn position_at(
    waypoints: &[(f64, [f64; 2])],
    t: f64,
    max_gap_s: f64,
    max_speed_mps: f64,
) -> Result<[f64; 2], Refusal> {
    let after = waypoints.partition_point(|w| w.0 <= t);
    let Some(a) = after.checked_sub(1).map(|i| waypoints[i]) else {
        return Err(Refusal::BeforeFirst);
    };
    if a.0 == t {
        return Ok(a.1);
    }
    let Some(&b) = waypoints.get(after) else {
        return Err(Refusal::AfterLast);
    };
    let gap = b.0 - a.0;
    if gap > max_gap_s {
        return Err(Refusal::Gap);
    }
    if (b.1[0] - a.1[0]).hypot(b.1[1] - a.1[1]) > max_speed_mps * gap {
        return Err(Refusal::Speed);
    }
    let s = (t - a.0) / gap;
    Ok([
        a.1[0] + s * (b.1[0] - a.1[0]),
        a.1[1] + s * (b.1[1] - a.1[1]),
    ])
}

/// [`position_at`], also refusing a position the site does not let anyone stand on.
pub(crate) fn labelled(
    site: &Site,
    walk: &Walk,
    t: f64,
    options: &Options,
) -> Result<[f64; 2], Refusal> {
    let at = position_at(&walk.waypoints, t, options.max_gap_s, options.max_speed_mps)?;
    match site.cell_of_world(at) {
        Some(cell) if site.walkable(cell) => Ok(at),
        _ => Err(Refusal::OffWalkable),
    }
}

/// A beacon's position from labelled readings (RSSI dBm, where heard): the
/// centroid of where it was heard within [`STRONGEST_DB`] of its strongest,
/// weighted by received power (mW).
///
/// Why this and not a least-squares path-loss fit: the walks run along
/// corridors, so a beacon in a shop is seen from one side only, and a fit of
/// position, transmit power and exponent together slides along the corridor
/// with nothing to hold it (the RSSI of one phone varies by ±6 dB at one
/// spot, as much as 10 m of path loss changes it). The strongest readings
/// are where the walkers came closest, which is the best this data says; the
/// position is pulled towards the walked area by up to the corridor's half
/// width, an error the path-loss model's shadowing absorbs. `None` under
/// [`MIN_READINGS`] readings.
pub(crate) fn estimate(heard: &[(i16, [f64; 2])]) -> Option<[f64; 2]> {
    if heard.len() < MIN_READINGS {
        return None;
    }
    let strongest = f64::from(heard.iter().map(|h| h.0).max()?);
    let (mut sum, mut weight) = ([0.0; 2], 0.0);
    for &(rssi, at) in heard {
        let rssi = f64::from(rssi);
        if rssi >= strongest - STRONGEST_DB {
            let w = 10f64.powf((rssi - strongest) / 10.0);
            sum[0] += w * at[0];
            sum[1] += w * at[1];
            weight += w;
        }
    }
    Some([sum[0] / weight, sum[1] / weight])
}

/// Imports the floor in `floor_dir` into `out` (created if needed):
/// `site.toml`, `survey.csv` and the floor image.
pub fn import(floor_dir: &Path, out: &Path, options: &Options) -> anyhow::Result<Report> {
    anyhow::ensure!(
        options.cell_m > 0.0 && options.window_s > 0.0 && options.stride_s > 0.0,
        "--cell-m, --window-s and --stride-s must be positive"
    );
    let name = options.name.clone().unwrap_or_else(|| {
        floor_dir
            .file_name()
            .map_or_else(|| "floor".into(), |n| n.to_string_lossy().into_owned())
    });
    let (_, mut doc) = floor::import_plan(floor_dir, out, &name, options.cell_m)?;
    let site_path = out.join("site.toml");
    let site = Site::parse(&write_doc(&doc, None), &site_path)?;
    let mut report = Report {
        site: site_path.clone(),
        survey: out.join("survey.csv"),
        cells: usize::from(site.width()) * usize::from(site.height()),
        walkable_cells: site.open_cells().len(),
        places: site.places().len(),
        ..Report::default()
    };
    let walks = read_walks(&floor_dir.join("path_data_files"), &mut report)?;

    let keys = Keys::of(&walks);
    report.shared_ids_split = keys.shared.len();
    let kept = estimate_beacons(&site, &walks, &keys, options, &mut report);
    doc.beacons = beacon_docs(&kept);
    report.beacons = doc.beacons.len();

    let text = format!(
        "# Written by `gangway survey import --floor-dir {}` ({} walks, {} beacons estimated from \
         them).\n{}",
        floor_dir.display(),
        report.walks,
        report.beacons,
        write_doc(&doc, None)
    );
    let site = Site::parse(&text, &site_path)?;
    std::fs::write(&site_path, &text)
        .with_context(|| format!("cannot write {}", site_path.display()))?;

    let ids: Vec<Key> = kept.keys().copied().collect();
    let mut csv = String::from("x_m,y_m,t");
    for b in &doc.beacons {
        write!(csv, ",{}", b.id)?;
    }
    csv.push('\n');
    for walk in &walks {
        rows(&site, walk, &keys, &ids, options, &mut report, &mut csv)?;
    }
    std::fs::write(&report.survey, &csv)
        .with_context(|| format!("cannot write {}", report.survey.display()))?;
    let anchors: Vec<String> = doc.beacons.iter().map(|b| b.id.clone()).collect();
    if !anchors.is_empty() {
        Survey::load(&report.survey, &site, &anchors, NOT_HEARD)?;
    }
    Ok(report)
}

/// A beacon estimated from the walks: where, the transmit power its frames
/// advertised most often, and how loudly it is heard over the floor
/// ([`crate::site::Beacon::heard_dbm`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(crate) struct Estimate {
    pub(crate) at: [f64; 2],
    pub(crate) tx_power: Option<i8>,
    pub(crate) heard_dbm: f64,
}

/// Every beacon of `keys` heard in `walks` often enough at a labelled
/// position, placed by [`estimate`]; the readings kept and dropped are
/// counted in `report`.
pub(crate) fn estimate_beacons<'a>(
    site: &Site,
    walks: impl IntoIterator<Item = &'a Walk>,
    keys: &Keys,
    options: &Options,
    report: &mut Report,
) -> BTreeMap<Key, Estimate> {
    let mut heard: BTreeMap<Key, Vec<(i16, [f64; 2])>> = BTreeMap::new();
    let mut tx_powers: BTreeMap<Key, BTreeMap<i8, usize>> = BTreeMap::new();
    let mut readings_of: BTreeMap<Key, usize> = BTreeMap::new();
    let mut power_mw: BTreeMap<Key, f64> = BTreeMap::new();
    let mut walked_s = 0.0;
    for walk in walks {
        walked_s += walk
            .waypoints
            .first()
            .zip(walk.waypoints.last())
            .map_or(0.0, |(first, last)| last.0 - first.0);
        for r in &walk.readings {
            let key = keys.key(r);
            *readings_of.entry(key).or_default() += 1;
            *power_mw.entry(key).or_default() += 10f64.powf(f64::from(r.rssi) / 10.0);
            if let Ok(at) = labelled(site, walk, r.t, options) {
                heard.entry(key).or_default().push((r.rssi, at));
                *tx_powers
                    .entry(key)
                    .or_default()
                    .entry(r.tx_power)
                    .or_default() += 1;
            }
        }
    }
    let mut kept = BTreeMap::new();
    for (key, &count) in &readings_of {
        let Some(at) = estimate(heard.get(key).map_or(&[][..], Vec::as_slice)) else {
            report.rare_ids_dropped += 1;
            report.rare_readings_dropped += count;
            continue;
        };
        report.readings_kept += count;
        let tx_power = tx_powers
            .get(key)
            .and_then(|p| p.iter().max_by_key(|(_, n)| **n).map(|(tx, _)| *tx));
        // Per second walked, not summed: floors are walked for very
        // different times, and a beacon heard as loudly from two floors
        // must not point at the one surveyed longer.
        let heard_dbm = 10.0 * (power_mw[key] / walked_s.max(1.0)).log10();
        kept.insert(
            *key,
            Estimate {
                at,
                tx_power,
                heard_dbm: (heard_dbm * 100.0).round() / 100.0,
            },
        );
    }
    kept
}

/// Which ids are heard from several MACs, so that each MAC is a beacon.
pub(crate) struct Keys {
    shared: std::collections::BTreeSet<BeaconId>,
}

impl Keys {
    pub(crate) fn of<'a>(walks: impl IntoIterator<Item = &'a Walk>) -> Keys {
        let mut macs: BTreeMap<BeaconId, std::collections::BTreeSet<Mac>> = BTreeMap::new();
        for r in walks.into_iter().flat_map(|w| &w.readings) {
            macs.entry(r.id).or_default().insert(r.mac);
        }
        Keys {
            shared: macs
                .into_iter()
                .filter(|(_, m)| m.len() > 1)
                .map(|(id, _)| id)
                .collect(),
        }
    }

    /// The beacon a reading is from.
    pub(crate) fn key(&self, r: &Reading) -> Key {
        (r.id, self.shared.contains(&r.id).then_some(r.mac))
    }
}

/// Every `*.txt` walk in `dir`, in name order.
pub(crate) fn read_walks(dir: &Path, report: &mut Report) -> anyhow::Result<Vec<Walk>> {
    let mut paths: Vec<PathBuf> = std::fs::read_dir(dir)
        .with_context(|| format!("{}: cannot read the walks' directory", dir.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|e| e == "txt"))
        .collect();
    paths.sort();
    let mut walks = Vec::with_capacity(paths.len());
    let mut problems = Vec::new();
    for path in &paths {
        let text =
            std::fs::read(path).with_context(|| format!("{}: cannot read", path.display()))?;
        let walk = read_walk(path, &String::from_utf8_lossy(&text), &mut problems);
        report.waypoints += walk.waypoints.len();
        report.readings += walk.readings.len();
        walks.push(walk);
    }
    report.walks = walks.len();
    report.lines_skipped = problems.len();
    report.problems.extend(problems);
    Ok(walks)
}

/// The site's beacons: each kept id (or id and MAC) at its estimated
/// position (to the centimetre) with the transmit power its frames
/// advertised most often. Ids are `b-<uuid's first 8 digits>-<major>-<minor>`,
/// then `-<mac's 12 digits>` for an id heard from several MACs.
pub(crate) fn beacon_docs(kept: &BTreeMap<Key, Estimate>) -> Vec<BeaconDoc> {
    let mac_suffix = |mac: &Option<Mac>| {
        mac.map_or_else(String::new, |m| {
            format!("-{}", m.to_string().replace(':', "").to_ascii_lowercase())
        })
    };
    let short = |(id, mac): &Key| {
        let uuid = id.uuid.simple().to_string();
        format!(
            "b-{}-{}-{}{}",
            &uuid[..8],
            id.major,
            id.minor,
            mac_suffix(mac)
        )
    };
    let mut seen: BTreeMap<String, usize> = BTreeMap::new();
    for id in kept.keys() {
        *seen.entry(short(id)).or_default() += 1;
    }
    kept.iter()
        .map(|(key, estimate)| {
            let (id, mac) = key;
            let name = short(key);
            BeaconDoc {
                // Two uuids alike in their first 8 digits keep them whole.
                id: if seen[&name] > 1 {
                    format!(
                        "b-{}-{}-{}{}",
                        id.uuid.simple(),
                        id.major,
                        id.minor,
                        mac_suffix(mac)
                    )
                } else {
                    name
                },
                uuid: id.uuid,
                major: id.major,
                minor: id.minor,
                cell: None,
                pos: Some(estimate.at.map(|v| (v * 100.0).round() / 100.0)),
                height_m: None,
                tx_power: estimate.tx_power,
                mac: *mac,
                heard_dbm: Some(estimate.heard_dbm),
            }
        })
        .collect()
}

/// One walk's windows over the beacons `ids` (sorted): the mean time of
/// each window's readings and the strongest reading of each beacon heard
/// (index into `ids`, dBm). A window holding the same readings as the one
/// before is left out (the same row again).
pub(crate) fn windows(
    walk: &Walk,
    keys: &Keys,
    ids: &[Key],
    options: &Options,
) -> Vec<(f64, Vec<(usize, i16)>)> {
    let readings: Vec<(f64, usize, i16)> = walk
        .readings
        .iter()
        .filter_map(|r| Some((r.t, ids.binary_search(&keys.key(r)).ok()?, r.rssi)))
        .collect();
    let mut out = Vec::new();
    let (Some(first), Some(last)) = (readings.first(), readings.last()) else {
        return out;
    };
    let (start, last) = (first.0, last.0);
    let (mut lo, mut hi, mut previous) = (0, 0, None);
    for k in 1.. {
        let end = start + f64::from(k) * options.stride_s;
        if end - options.window_s >= last {
            break;
        }
        while hi < readings.len() && readings[hi].0 <= end {
            hi += 1;
        }
        while lo < hi && readings[lo].0 <= end - options.window_s {
            lo += 1;
        }
        if lo == hi || previous == Some((lo, hi)) {
            continue;
        }
        previous = Some((lo, hi));
        let window = &readings[lo..hi];
        let t = window.iter().map(|r| r.0).sum::<f64>() / window.len() as f64;
        let mut strongest: BTreeMap<usize, i16> = BTreeMap::new();
        for &(_, i, rssi) in window {
            let s = strongest.entry(i).or_insert(rssi);
            *s = (*s).max(rssi);
        }
        out.push((t, strongest.into_iter().collect()));
    }
    out
}

/// One walk's survey rows, appended to `csv`: one per window of the kept
/// beacons' readings, labelled at the mean time of its readings.
fn rows(
    site: &Site,
    walk: &Walk,
    keys: &Keys,
    ids: &[Key],
    options: &Options,
    report: &mut Report,
    csv: &mut String,
) -> anyhow::Result<()> {
    for (t, heard) in windows(walk, keys, ids, options) {
        let at = match labelled(site, walk, t, options) {
            Ok(at) => at,
            Err(why) => {
                report.refused.count(why);
                continue;
            }
        };
        let mut strongest = vec![NOT_HEARD; ids.len()];
        for (i, rssi) in heard {
            strongest[i] = rssi;
        }
        write!(csv, "{:.3},{:.3},{t:.3}", at[0], at[1])?;
        for v in strongest {
            write!(csv, ",{v}")?;
        }
        csv.push('\n');
        report.rows += 1;
    }
    Ok(())
}

impl Report {
    /// The problems worth printing: the first few in full, then how many more.
    pub fn shown_problems(&self) -> Vec<String> {
        let mut shown: Vec<String> = self.problems.iter().take(SHOWN_PROBLEMS).cloned().collect();
        if self.problems.len() > SHOWN_PROBLEMS {
            shown.push(format!(
                "… and {} more",
                self.problems.len() - SHOWN_PROBLEMS
            ));
        }
        shown
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const WAYPOINTS: [(f64, [f64; 2]); 4] = [
        (10.0, [0.0, 0.0]),
        (20.0, [10.0, 0.0]),
        // 60 s later: a gap.
        (80.0, [10.0, 10.0]),
        // 100 m in 5 s: a jump.
        (85.0, [110.0, 10.0]),
    ];

    #[test]
    fn positions_are_interpolated_between_waypoints_and_refused_outside_them() {
        let at = |t| position_at(&WAYPOINTS, t, 30.0, 2.5);
        assert_eq!(at(10.0), Ok([0.0, 0.0]));
        assert_eq!(at(12.5), Ok([2.5, 0.0]));
        assert_eq!(at(20.0), Ok([10.0, 0.0]));
        assert_eq!(at(9.9), Err(Refusal::BeforeFirst));
        assert_eq!(at(50.0), Err(Refusal::Gap));
        assert_eq!(at(82.0), Err(Refusal::Speed));
        assert_eq!(at(85.0), Ok([110.0, 10.0]));
        assert_eq!(at(85.1), Err(Refusal::AfterLast));
        // A longer bound accepts the gap.
        assert_eq!(position_at(&WAYPOINTS, 50.0, 90.0, 2.5), Ok([10.0, 5.0]));
    }

    #[test]
    fn a_bad_line_is_reported_and_skipped_and_the_rest_is_read() {
        let text = "#\tstartTime:1000\n\
                    1000\tTYPE_WAYPOINT\t1.5\t2.5\n\
                    1500\tTYPE_BEACON\t9195B3AD-A9D0-4500-85FF-9FB0F65A5201\t0\t7\t-56\t-80\t3.1\te0:78:a3:3d:b5:d6\t1500\n\
                    1600\tTYPE_BEACON\tnot-a-uuid\t0\t7\t-56\t-80\t3.1\tE0:78:A3:3D:B5:D6\t1600\n\
                    1700\tTYPE_BEACON\t9195B3AD-A9D0-4500-85FF-9FB0F65A5201\t0\t7\t-56\t12\t3.1\tE0:78:A3:3D:B5:D6\t1700\n\
                    1800\tTYPE_WAYPOINT\tnear\t2.5\n\
                    1900\tTYPE_WIFI\tssid\n\
                    2000\tTYPE_WAYPOINT\t3.5\t2.5\n";
        let mut problems = Vec::new();
        let walk = read_walk(Path::new("walk.txt"), text, &mut problems);
        assert_eq!(walk.waypoints, vec![(1.0, [1.5, 2.5]), (2.0, [3.5, 2.5])]);
        assert_eq!(walk.readings.len(), 1);
        assert_eq!(walk.readings[0].mac.to_string(), "E0:78:A3:3D:B5:D6");
        assert_eq!((walk.readings[0].id.minor, walk.readings[0].rssi), (7, -80));
        assert_eq!(problems.len(), 3, "{problems:?}");
        assert!(problems[0].starts_with("walk.txt:4: field `uuid`: \"not-a-uuid\""));
        assert!(problems[1].starts_with("walk.txt:5: field `rssi`: 12 dBm"));
        assert!(problems[2].starts_with("walk.txt:6: field `x`: \"near\" is not a number"));
        assert!(problems.iter().all(|p| p.ends_with("the line is skipped")));
    }

    #[test]
    fn a_beacon_is_placed_where_it_was_heard_loudest() {
        let heard = [(-60, [10.0, 0.0]), (-60, [12.0, 0.0]), (-90, [50.0, 0.0])];
        assert_eq!(estimate(&heard), Some([11.0, 0.0]));
        assert_eq!(estimate(&heard[..2]), None);
    }
}
