//! Real walks in: trajectories recorded by someone else (pedestrian datasets,
//! camera trackers, surveys), read as tracks in metres and turned into the
//! cell walks `gangway train` and `gangway eval planning` read
//! ([`crate::train::trajectory`]), with a time-ordered train/held-out split.
//!
//! Its own module rather than a `source`: sources feed the live pipeline with
//! sightings; these are offline files of positions, used to learn and to judge
//! routes.
//!
//! - [`read`]: a `track,t,x,y` CSV (metres, or pixels with a homography) or
//!   the `obsmat.txt` layout of the ETH/UCY datasets
//!   (`frame person x z y vx vz vy`);
//! - [`Homography`]: the 3×3 image → world map of `H.txt` files;
//! - [`rasterise`]: a track onto a site's cells;
//! - [`scene`]: a site for a recorded scene, from its obstacle image or from
//!   where people walked.

pub mod scene;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde::Deserialize;

use crate::csv_line::LineCounter;
use crate::plan::anyangle::{extend_walk, traverse, without_loops};
use crate::site::{Cell, Site};
use crate::train::trajectory::Trajectory;

/// One person's recorded positions, in time order.
#[derive(Clone, Debug, PartialEq)]
pub struct Track {
    pub id: String,
    /// (seconds, world `[x, y]` metres), sorted by time.
    pub points: Vec<(f64, [f64; 2])>,
}

/// Why a walk file was refused.
#[derive(Debug, thiserror::Error)]
pub enum WalkError {
    #[error("{}: cannot read: {source}", path.display())]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{}:{line}: {reason}", path.display())]
    Line {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    #[error("{}: {reason}", path.display())]
    File { path: PathBuf, reason: String },
}

/// The layouts [`read`] understands.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// CSV with a header naming `track`, `t` (seconds), `x`, `y` (other
    /// columns ignored).
    Csv,
    /// ETH/UCY `obsmat.txt`: whitespace-separated `frame person x z y vx vz
    /// vy`; times from the frame numbers (see [`read`]).
    Obsmat,
}

impl Format {
    /// `obsmat` for files named `obsmat*.txt`, otherwise `csv`.
    pub fn guess(path: &Path) -> Format {
        let name = path
            .file_name()
            .map(|n| n.to_string_lossy().to_lowercase())
            .unwrap_or_default();
        if name.starts_with("obsmat") {
            Format::Obsmat
        } else {
            Format::Csv
        }
    }
}

/// How a homography file addresses image pixels.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum PixelOrder {
    /// `[column, row]` (x then y): the usual order.
    ColRow,
    /// `[row, column]`: the ETH files' `H.txt`.
    RowCol,
}

impl Homography {
    /// Reads `H.txt` for pixels given in `order`, as a `[column, row]` map.
    pub fn load_ordered(path: &Path, order: PixelOrder) -> Result<Homography, WalkError> {
        let h = Homography::load(path)?;
        Ok(match order {
            PixelOrder::ColRow => h,
            PixelOrder::RowCol => h.row_first(),
        })
    }
}

/// How a file's numbers become tracks in world metres.
#[derive(Clone, Debug)]
pub struct ReadOptions {
    pub format: Format,
    /// Pixel → world map for files in image pixels.
    pub homography: Option<Homography>,
    /// Obsmat: annotated positions per second. Seconds per frame number are
    /// this rate's period over the commonest step between a person's frames.
    pub annotation_hz: f64,
}

/// Reads the tracks of a walk file. Every problem names the file, the line
/// and the field.
pub fn read(path: &Path, options: &ReadOptions) -> Result<Vec<Track>, WalkError> {
    let text = std::fs::read_to_string(path).map_err(|source| WalkError::Read {
        path: path.to_owned(),
        source,
    })?;
    let mut rows = match options.format {
        Format::Csv => csv_rows(path, &text)?,
        Format::Obsmat => obsmat_rows(path, &text, options.annotation_hz)?,
    };
    if let Some(h) = &options.homography {
        for row in &mut rows {
            row.2 = h.apply(row.2).ok_or_else(|| WalkError::Line {
                path: path.to_owned(),
                line: row.3,
                reason: "the homography maps this point to infinity; check --homography".into(),
            })?;
        }
    }
    let mut tracks: BTreeMap<String, Vec<(f64, [f64; 2])>> = BTreeMap::new();
    for (id, t, p, _) in rows {
        tracks.entry(id).or_default().push((t, p));
    }
    Ok(tracks
        .into_iter()
        .map(|(id, mut points)| {
            points.sort_by(|a, b| a.0.total_cmp(&b.0));
            Track { id, points }
        })
        .collect())
}

/// (track, seconds, point, line) per row.
type Row = (String, f64, [f64; 2], usize);

fn csv_rows(path: &Path, text: &str) -> Result<Vec<Row>, WalkError> {
    #[derive(Deserialize)]
    struct CsvRow {
        track: String,
        t: f64,
        x: f64,
        y: f64,
    }
    let mut reader = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_reader(text.as_bytes());
    let what = "each row needs `track`, `t` (seconds), `x` and `y` (metres, or pixels with \
                --homography) under a header naming them";
    let headers = reader
        .headers()
        .map_err(|e| WalkError::Line {
            path: path.to_owned(),
            line: 1,
            reason: format!("{e}; {what}"),
        })?
        .clone();
    let mut rows = Vec::new();
    let mut lines = LineCounter::default();
    let mut line_of = |position: Option<&csv::Position>| {
        position.map_or(0, |p| lines.line(text.as_bytes(), p) as usize)
    };
    for record in reader.records() {
        let error = |line: usize, e: csv::Error| WalkError::Line {
            path: path.to_owned(),
            line,
            reason: format!("{e}; {what}"),
        };
        let record = record.map_err(|e| {
            let line = line_of(e.position());
            error(line, e)
        })?;
        let line = line_of(record.position());
        let record: CsvRow = record
            .deserialize(Some(&headers))
            .map_err(|e| error(line, e))?;
        for (field, v) in [("t", record.t), ("x", record.x), ("y", record.y)] {
            if !v.is_finite() {
                return Err(WalkError::Line {
                    path: path.to_owned(),
                    line,
                    reason: format!("`{field}` is {v}; it must be a finite number"),
                });
            }
        }
        rows.push((record.track, record.t, [record.x, record.y], line));
    }
    Ok(rows)
}

fn obsmat_rows(path: &Path, text: &str, annotation_hz: f64) -> Result<Vec<Row>, WalkError> {
    const FIELDS: [&str; 8] = ["frame", "person", "x", "z", "y", "vx", "vz", "vy"];
    // (frame, person, point, line)
    let mut raw: Vec<(f64, String, [f64; 2], usize)> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let fields: Vec<&str> = line.split_whitespace().collect();
        if fields.is_empty() {
            continue;
        }
        let error = |reason: String| WalkError::Line {
            path: path.to_owned(),
            line: i + 1,
            reason,
        };
        if fields.len() != FIELDS.len() {
            return Err(error(format!(
                "{} fields; obsmat rows have 8: {}",
                fields.len(),
                FIELDS.join(" ")
            )));
        }
        let mut v = [0.0f64; 8];
        for (k, f) in fields.iter().enumerate() {
            v[k] = f
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| error(format!("`{}` is {f:?}, not a number", FIELDS[k])))?;
        }
        if v[0].fract() != 0.0 || v[1].fract() != 0.0 {
            return Err(error("`frame` and `person` must be whole numbers".into()));
        }
        raw.push((v[0], format!("{}", v[1] as i64), [v[2], v[4]], i + 1));
    }
    if raw.is_empty() {
        return Err(WalkError::File {
            path: path.to_owned(),
            reason: "no rows".into(),
        });
    }
    let seconds_per_frame = frame_period(&raw, annotation_hz).ok_or_else(|| WalkError::File {
        path: path.to_owned(),
        reason: "no person is seen in two frames, so the frame rate is unknown".into(),
    })?;
    Ok(raw
        .into_iter()
        .map(|(frame, person, p, line)| (person, frame * seconds_per_frame, p, line))
        .collect())
}

/// Seconds per frame number: the annotation period over the commonest step
/// between consecutive frames of one person (ETH steps by 6, UCY by 10, both
/// annotated at 2.5 Hz).
fn frame_period(rows: &[(f64, String, [f64; 2], usize)], annotation_hz: f64) -> Option<f64> {
    let mut frames: BTreeMap<&str, Vec<f64>> = BTreeMap::new();
    for (frame, person, _, _) in rows {
        frames.entry(person).or_default().push(*frame);
    }
    let mut steps: BTreeMap<i64, usize> = BTreeMap::new();
    for list in frames.values_mut() {
        list.sort_by(f64::total_cmp);
        for w in list.windows(2) {
            let step = (w[1] - w[0]) as i64;
            if step > 0 {
                *steps.entry(step).or_default() += 1;
            }
        }
    }
    let (&step, _) = steps.iter().max_by_key(|&(s, n)| (*n, -s))?;
    Some(1.0 / annotation_hz / step as f64)
}

/// A 3×3 homography from image pixels to world metres, as in `H.txt` (three
/// rows of three numbers): `[x, y, w]ᵀ = H · [u, v, 1]ᵀ`, world `(x/w, y/w)`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Homography(pub [[f64; 3]; 3]);

impl Homography {
    /// Reads `H.txt`: nine numbers, three per line.
    pub(crate) fn load(path: &Path) -> Result<Homography, WalkError> {
        let text = std::fs::read_to_string(path).map_err(|source| WalkError::Read {
            path: path.to_owned(),
            source,
        })?;
        let mut m = [[0.0; 3]; 3];
        let rows: Vec<&str> = text.lines().filter(|l| !l.trim().is_empty()).collect();
        let shape_error = || WalkError::File {
            path: path.to_owned(),
            reason: format!(
                "{} non-empty lines; a homography is 3 lines of 3 numbers",
                rows.len()
            ),
        };
        if rows.len() != 3 {
            return Err(shape_error());
        }
        for (r, line) in rows.iter().enumerate() {
            let values: Vec<&str> = line.split_whitespace().collect();
            if values.len() != 3 {
                return Err(WalkError::Line {
                    path: path.to_owned(),
                    line: r + 1,
                    reason: format!("{} numbers; each line needs 3", values.len()),
                });
            }
            for (c, v) in values.iter().enumerate() {
                m[r][c] = v
                    .parse()
                    .ok()
                    .filter(|v: &f64| v.is_finite())
                    .ok_or_else(|| WalkError::Line {
                        path: path.to_owned(),
                        line: r + 1,
                        reason: format!("{v:?} is not a number"),
                    })?;
            }
        }
        let h = Homography(m);
        if h.inverse().is_none() {
            return Err(WalkError::File {
                path: path.to_owned(),
                reason: "the matrix is singular: it maps the image onto a line".into(),
            });
        }
        Ok(h)
    }

    /// The world point of `[u, v]`; `None` on the horizon line (w = 0).
    pub(crate) fn apply(&self, [u, v]: [f64; 2]) -> Option<[f64; 2]> {
        let m = &self.0;
        let x = m[0][0] * u + m[0][1] * v + m[0][2];
        let y = m[1][0] * u + m[1][1] * v + m[1][2];
        let w = m[2][0] * u + m[2][1] * v + m[2][2];
        (w.abs() > 1e-12).then(|| [x / w, y / w])
    }

    /// The inverse map (world → image); `None` for a singular matrix.
    pub(crate) fn inverse(&self) -> Option<Homography> {
        let m = &self.0;
        let cofactor = |r: usize, c: usize| {
            let (r1, r2) = ((r + 1) % 3, (r + 2) % 3);
            let (c1, c2) = ((c + 1) % 3, (c + 2) % 3);
            m[r1][c1] * m[r2][c2] - m[r1][c2] * m[r2][c1]
        };
        let det: f64 = (0..3).map(|c| m[0][c] * cofactor(0, c)).sum();
        if det.abs() < 1e-15 || !det.is_finite() {
            return None;
        }
        // The inverse is the transposed cofactor matrix over the determinant.
        let mut inv = [[0.0; 3]; 3];
        for (r, row) in inv.iter_mut().enumerate() {
            for (c, v) in row.iter_mut().enumerate() {
                *v = cofactor(c, r) / det;
            }
        }
        Some(Homography(inv))
    }

    /// The same map for images addressed `[row, column]` instead of `[x, y]`
    /// (the ETH files' `H.txt` takes the row first).
    pub(crate) fn row_first(&self) -> Homography {
        let m = &self.0;
        Homography([
            [m[0][1], m[0][0], m[0][2]],
            [m[1][1], m[1][0], m[1][2]],
            [m[2][1], m[2][0], m[2][2]],
        ])
    }
}

/// How tracks become walks on a site.
#[derive(Clone, Debug)]
pub struct RasterOptions {
    /// Pieces with fewer cells are dropped.
    pub min_cells: usize,
    /// Snap each end to a named place within this many metres.
    pub snap_m: Option<f64>,
}

/// What rasterising tracks did, for the summary.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct RasterStats {
    pub tracks: usize,
    pub points: usize,
    /// Points off the grid or on a blocked cell (they end a piece).
    pub points_outside: usize,
    pub walks: usize,
    /// Pieces dropped for having fewer than `min_cells` cells.
    pub short_pieces: usize,
    pub snapped_ends: usize,
}

/// A track as walks on `site`: each pair of consecutive points joined by the
/// cells of the straight segment between them ([`extend_walk`]: repeats
/// dropped, thin 8-connected steps, corners never cut), each cell timed by
/// linear interpolation. Where the track leaves the grid or crosses a blocked
/// cell the walk ends, and a new one starts where it is back on walkable
/// cells. Loops are cut ([`without_loops`]): at half-metre cells, annotation
/// jitter makes a person standing still step back and forth. Ends are then
/// snapped to places (`snap_m`), and pieces shorter than `min_cells` dropped.
/// Walk `device`s are the track id, with `#2`, `#3`… for later pieces.
pub fn rasterise(
    site: &Site,
    track: &Track,
    options: &RasterOptions,
    stats: &mut RasterStats,
) -> Vec<Trajectory> {
    stats.tracks += 1;
    stats.points += track.points.len();
    let ok = |c: Cell| site.walkable(c);
    let mut pieces: Vec<Vec<(Cell, f64)>> = vec![Vec::new()];

    let mut previous: Option<(f64, [f64; 2])> = None;
    for &(t, world) in &track.points {
        let g = site.grid_of_world(world);
        let here = site.cell_of_world(world).filter(|&c| ok(c));
        if here.is_none() {
            stats.points_outside += 1;
        }
        match previous {
            None => {
                if let Some(c) = here {
                    pieces.last_mut().expect("a piece").push((c, t));
                }
            }
            Some((t0, g0)) => {
                let raw = traverse(g0, g).cells;
                let steps = raw.len().saturating_sub(1).max(1) as f64;
                for (k, [x, y]) in raw.into_iter().enumerate() {
                    let cell = u16::try_from(x)
                        .ok()
                        .zip(u16::try_from(y).ok())
                        .map(|(x, y)| Cell::new(x, y))
                        .filter(|&c| ok(c));
                    let at = t0 + (t - t0) * k as f64 / steps;
                    let piece = pieces.last_mut().expect("a piece");
                    let went_on = cell.is_some_and(|c| extend_walk(piece, c, at, ok));
                    if !went_on && !piece.is_empty() {
                        pieces.push(Vec::new());
                    }
                    if let (Some(c), false) = (cell, went_on) {
                        pieces.last_mut().expect("a piece").push((c, at));
                    }
                }
            }
        }
        previous = Some((t, g));
    }
    let mut walks = Vec::new();
    for piece in pieces {
        let mut piece = without_loops(piece, |&(c, _)| c);
        if let Some(radius) = options.snap_m {
            stats.snapped_ends += snap_ends(site, &mut piece, radius);
        }
        if piece.len() < options.min_cells.max(2) {
            if !piece.is_empty() {
                stats.short_pieces += 1;
            }
            continue;
        }
        let device = match walks.len() {
            0 => track.id.clone(),
            n => format!("{}#{}", track.id, n + 1),
        };
        let (start, end) = (piece[0].1, piece[piece.len() - 1].1);
        let positions: Vec<[f64; 2]> = track
            .points
            .iter()
            .filter(|&&(t, p)| (start..=end).contains(&t) && site.cell_of_world(p).is_some())
            .map(|&(_, p)| p)
            .collect();
        walks.push(Trajectory {
            site: site.name.clone(),
            device,
            cells: piece.iter().map(|&(c, _)| c).collect(),
            times: piece.iter().map(|&(_, t)| t).collect(),
            profile: None,
            feedback: None,
            positions_m: (positions.len() >= 2).then_some(positions),
        });
    }
    stats.walks += walks.len();
    walks
}

/// Extends each end of `piece` along a straight walkable segment to the
/// nearest named place within `radius_m` metres; returns how many ends moved.
fn snap_ends(site: &Site, piece: &mut Vec<(Cell, f64)>, radius_m: f64) -> usize {
    let mut snapped = 0;
    for at_start in [true, false] {
        let Some(&(end, t)) = (if at_start {
            piece.first()
        } else {
            piece.last()
        }) else {
            return snapped;
        };
        let Some(place) = site.nearest_place(end, radius_m / site.cell_m) else {
            continue;
        };
        let target = site.place(place).expect("a named place");
        if target == end {
            continue;
        }
        let centre = |c: Cell| [f64::from(c.x) + 0.5, f64::from(c.y) + 0.5];
        let Some(leg) =
            crate::plan::anyangle::segment_cells(site, centre(end), centre(target), |_| true)
        else {
            continue;
        };
        let mut extended: Vec<(Cell, f64)> = Vec::with_capacity(piece.len() + leg.len());
        if at_start {
            extended.extend(leg.iter().rev().map(|&c| (c, t)));
            extended.extend(piece.iter().skip(1));
        } else {
            extended.extend(piece.iter());
            extended.extend(leg.iter().skip(1).map(|&c| (c, t)));
        }
        *piece = without_loops(extended, |&(c, _)| c);
        snapped += 1;
    }
    snapped
}

/// Splits walks by time: the last `holdout` share by start time are held
/// out. Returns (training, held out, the first held-out start time).
pub fn split_by_time(
    mut walks: Vec<Trajectory>,
    holdout: f64,
) -> (Vec<Trajectory>, Vec<Trajectory>, Option<f64>) {
    walks.sort_by(|a, b| a.times[0].total_cmp(&b.times[0]));
    let held = ((walks.len() as f64) * holdout).round() as usize;
    let heldout = walks.split_off(walks.len() - held.min(walks.len()));
    let cutoff = heldout.first().map(|w| w.times[0]);
    (walks, heldout, cutoff)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::Connectivity;
    use std::io::Write;

    fn site(extra: &str) -> Site {
        // 8 × 4 half-metre cells; world x 10..14, y up from 0 to 2 at the top.
        let text = format!(
            "name = \"t\"\ncell_m = 0.5\norigin_m = [10.0, 2.0]\ny_axis = \"up\"\n\
             map = '''\n########\n####.###\n########\n########\n'''\n{extra}"
        );
        Site::parse(&text, Path::new("t.toml")).unwrap()
    }

    fn file(text: &str) -> tempfile::NamedTempFile {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(text.as_bytes()).unwrap();
        f
    }

    fn options(format: Format) -> ReadOptions {
        ReadOptions {
            format,
            homography: None,
            annotation_hz: 2.5,
        }
    }

    #[test]
    fn reads_csv_and_obsmat_and_names_bad_lines() {
        let csv = file("track,t,x,y,extra\nb,2,1.0,2.0,z\na,1,0.5,0.5,z\nb,1,0.0,0.0,z\n");
        let tracks = read(csv.path(), &options(Format::Csv)).unwrap();
        assert_eq!(tracks.len(), 2);
        assert_eq!(tracks[1].id, "b");
        assert_eq!(tracks[1].points, vec![(1.0, [0.0, 0.0]), (2.0, [1.0, 2.0])]);
        let bad = file("track,t,x,y\na,1,0.5,0.5\na,x,1,1\n");
        let err = read(bad.path(), &options(Format::Csv))
            .unwrap_err()
            .to_string();
        assert!(err.contains(":3:"), "{err}");
        // Frames step by 6 at 2.5 Hz: 1/15 s per frame number.
        let obsmat = file(
            " 6.0 1.0 8.0 0.0 3.0 0.0 0.0 0.0\n 12.0 1.0 8.5 0.0 3.5 0.0 0.0 0.0\n\
             18.0 2.0 1.0 0.0 1.0 0.0 0.0 0.0\n 24.0 2.0 1.0 0.0 1.4 0.0 0.0 0.0\n",
        );
        let tracks = read(obsmat.path(), &options(Format::Obsmat)).unwrap();
        assert_eq!(tracks[0].points[1].1, [8.5, 3.5], "x then y, z skipped");
        assert!((tracks[0].points[1].0 - 0.8).abs() < 1e-9);
        let short = file("1 2 3\n");
        let err = read(short.path(), &options(Format::Obsmat))
            .unwrap_err()
            .to_string();
        assert!(err.contains(":1: 3 fields"), "{err}");
    }

    #[test]
    fn homographies_map_invert_and_swap() {
        let h = Homography([[0.02, 0.0, 7.5], [0.0, 0.03, 6.8], [0.0, 0.0, 1.0]]);
        let w = h.apply([100.0, 200.0]).unwrap();
        assert!((w[0] - 9.5).abs() < 1e-12 && (w[1] - 12.8).abs() < 1e-12);
        let back = h.inverse().unwrap().apply(w).unwrap();
        assert!((back[0] - 100.0).abs() < 1e-9 && (back[1] - 200.0).abs() < 1e-9);
        assert_eq!(h.row_first().apply([200.0, 100.0]), h.apply([100.0, 200.0]));
        let f = file("1 0 0\n0 1 0\n");
        assert!(
            Homography::load(f.path())
                .unwrap_err()
                .to_string()
                .contains("2 non-empty lines")
        );
        let f = file("1 0 0\n0 1 0\n0 0 1\n");
        assert_eq!(
            Homography::load(f.path()).unwrap().apply([3.0, 4.0]),
            Some([3.0, 4.0])
        );
    }

    #[test]
    fn tracks_become_thin_walks_split_at_walls() {
        let s = site("");
        // Along the second row from the left edge to the right, through the
        // blocked cell [4, 1]: two pieces.
        let track = Track {
            id: "p".into(),
            points: vec![(0.0, [10.1, 1.2]), (4.0, [13.9, 1.2])],
        };
        let mut stats = RasterStats::default();
        let walks = rasterise(
            &s,
            &track,
            &RasterOptions {
                min_cells: 2,
                snap_m: None,
            },
            &mut stats,
        );
        assert_eq!(walks.len(), 2);
        assert_eq!(
            walks[0].cells,
            (0..4).map(|x| Cell::new(x, 1)).collect::<Vec<_>>()
        );
        assert_eq!(walks[1].device, "p#2");
        for w in &walks {
            w.check(&s).unwrap();
        }
        // A slanted walk: thin, 8-connected, timed in order.
        let track = Track {
            id: "q".into(),
            points: vec![(0.0, [10.1, 1.9]), (1.0, [11.0, 1.4]), (3.0, [11.9, 0.1])],
        };
        let walks = rasterise(
            &s,
            &track,
            &RasterOptions {
                min_cells: 2,
                snap_m: None,
            },
            &mut stats,
        );
        assert_eq!(walks.len(), 1);
        let w = &walks[0];
        w.check(&s).unwrap();
        assert_eq!(w.source(), Cell::new(0, 0));
        assert_eq!(w.destination(), Cell::new(3, 3));
        assert_eq!(w.positions_m.as_ref().map(Vec::len), Some(3));
        assert!(
            w.cells
                .windows(2)
                .any(|p| p[0].x != p[1].x && p[0].y != p[1].y)
        );
        assert!(
            crate::plan::Route {
                cells: w.cells.clone()
            }
            .validate(&s, w.source(), w.destination(), Connectivity::Eight)
            .is_ok()
        );
    }

    #[test]
    fn ends_snap_to_places_and_the_split_is_by_time() {
        let s = site("[places]\ndoor = [7, 3]\n");
        let track = Track {
            id: "p".into(),
            points: vec![(0.0, [10.1, 0.3]), (1.0, [13.2, 0.3])],
        };
        let mut stats = RasterStats::default();
        let walks = rasterise(
            &s,
            &track,
            &RasterOptions {
                min_cells: 2,
                snap_m: Some(1.0),
            },
            &mut stats,
        );
        assert_eq!(walks[0].destination(), Cell::new(7, 3));
        assert_eq!(stats.snapped_ends, 1);
        walks[0].check(&s).unwrap();
        let at = |t: f64| Trajectory {
            times: vec![t, t + 1.0],
            ..walks[0].clone()
        };
        let (train, held, cutoff) = split_by_time(vec![at(5.0), at(1.0), at(3.0), at(2.0)], 0.3);
        assert_eq!(train.len(), 3);
        assert_eq!(held.len(), 1);
        assert_eq!(cutoff, Some(5.0));
        assert!(train.iter().all(|w| w.times[0] < 5.0));
    }
}
