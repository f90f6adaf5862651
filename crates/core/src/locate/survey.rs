//! Site surveys: RSSI readings labelled with the cell they were taken in, and
//! the CSV row reader that surveys and CSV scan logs (`source::csvlog`) share.
//!
//! Three CSV layouts are read, all with one column per anchor named by the
//! anchor's id in the site file:
//! - the UCI BLE RSSI layout as published: `location` (a survey label such as
//!   `O02`, read with the site's `[labels]` scheme), an optional `date`
//!   (`MM-DD-YYYY HH:MM[:SS]`), then the anchors;
//! - a metric layout: `x_m`, `y_m` (world metres in the site's frame, see
//!   `crate::site`), an optional `t` (seconds), then the anchors. A row keeps
//!   its true position ([`Sample::at`]) beside the cell it falls in; a
//!   position off the grid or on a blocked cell refuses the file, naming the
//!   row and column, since the walker cannot have stood there;
//! - a generic layout: `x`, `y` (cell column and row), an optional `t`
//!   (seconds), then the anchors.
//!
//! When a file has more than one kind of position column, `x_m`,`y_m` win,
//! then `location`, then `x`,`y`.
//!
//! A reading equal to the "not heard" sentinel (default -200) means the anchor
//! was not heard. Columns that name no anchor of the site are ignored (and
//! listed by [`Survey::ignored_columns`]); a cell, time or RSSI that does not
//! parse refuses the file with its row and column.
//!
//! [`SurveyRows`] reads such a file one row at a time; a survey needs a position
//! in every row, a scan log needs a time in every row and a position only when
//! it carries ground truth, so each caller checks [`SurveyRows::has_position`]
//! and [`SurveyRows::has_clock`] for what it needs.

use std::path::{Path, PathBuf};

use crate::csv_line::LineCounter;
use crate::site::{Cell, Site};

/// A gap longer than this (seconds) between survey rows starts a new walking
/// session, unless the caller says otherwise.
pub const SESSION_GAP_S: f64 = 20.0;

/// Rows in time order and the walking session of each (numbered from 0 in
/// time order): a gap over `gap_s` seconds starts a new one.
pub fn sessions(times: &[f64], gap_s: f64) -> (Vec<usize>, Vec<usize>) {
    let mut order: Vec<usize> = (0..times.len()).collect();
    order.sort_by(|&a, &b| times[a].total_cmp(&times[b]));
    let mut session = vec![0usize; times.len()];
    for w in order.windows(2) {
        session[w[1]] = session[w[0]] + usize::from(times[w[1]] - times[w[0]] > gap_s);
    }
    (order, session)
}

/// The weakest RSSI a BLE controller can report.
const MIN_RSSI_DBM: i16 = -127;

/// One labelled reading.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    pub cell: Cell,
    /// Where it was taken, world metres: the row's `x_m`,`y_m`, else the
    /// centre of `cell`.
    pub at: [f64; 2],
    /// Seconds (Unix time for `date`), when the survey has a time column.
    pub t: Option<f64>,
    /// One entry per site anchor, in the site's anchor order.
    pub rssi: Vec<Option<i16>>,
}

/// A loaded survey, its columns matched to the site's anchors.
#[derive(Clone, Debug)]
pub struct Survey {
    pub samples: Vec<Sample>,
    /// Anchor ids in the site's order (every entry of `Sample::rssi` follows it).
    pub anchors: Vec<String>,
    /// Which site anchors the survey has a column for.
    pub present: Vec<bool>,
    ignored_columns: Vec<String>,
}

#[derive(Debug, thiserror::Error)]
pub enum SurveyError {
    #[error("{path}: cannot read the CSV file: {reason}")]
    Read { path: PathBuf, reason: String },
    #[error("{path}: {reason}")]
    Header { path: PathBuf, reason: String },
    #[error("{path}:{line}: column `{column}`: {reason}")]
    Field {
        path: PathBuf,
        line: u64,
        column: String,
        reason: String,
    },
    #[error("{path}:{line}: {reason}")]
    Row {
        path: PathBuf,
        line: u64,
        reason: String,
    },
}

enum Position {
    Label(usize),
    Xy(usize, usize),
    Metres(usize, usize),
}

enum Clock {
    None,
    Date(usize),
    Seconds(usize),
}

/// Columns with a meaning of their own; every other column should name an anchor.
const KNOWN_COLUMNS: [&str; 7] = ["location", "x", "y", "x_m", "y_m", "date", "t"];

/// One row of a survey or scan log, its anchors in the caller's anchor order.
#[derive(Clone, Debug, PartialEq)]
pub struct Row {
    /// Line of the row in the file (the header is line 1).
    pub line: u64,
    /// Where the row was taken, when the file has position columns.
    pub cell: Option<Cell>,
    /// The same in world metres: `x_m`,`y_m` as given, else the cell's centre.
    pub at: Option<[f64; 2]>,
    /// Seconds (Unix time for `date`), when the file has a time column.
    pub t: Option<f64>,
    /// One entry per anchor; `None` where the anchor was not heard or has no column.
    pub rssi: Vec<Option<i16>>,
}

/// A survey-layout CSV file opened for reading row by row, its columns matched
/// to a list of anchors.
pub struct SurveyRows<'a> {
    reader: csv::Reader<std::io::Cursor<Vec<u8>>>,
    record: csv::StringRecord,
    lines: LineCounter,
    path: PathBuf,
    site: &'a Site,
    headers: csv::StringRecord,
    position: Option<Position>,
    clock: Clock,
    column_of: Vec<Option<usize>>,
    ignored_columns: Vec<String>,
    not_heard: i16,
}

impl<'a> SurveyRows<'a> {
    /// Opens `path` and matches its header to `anchors` (ids as in the site
    /// file); `not_heard` is the RSSI sentinel for "not heard". Refuses a file
    /// whose header names no anchor, or that names cells by label on a site
    /// without a label scheme.
    pub fn open(
        path: &Path,
        site: &'a Site,
        anchors: &[String],
        not_heard: i16,
    ) -> Result<SurveyRows<'a>, SurveyError> {
        // Read whole, so that a row's line is counted from its byte offset
        // (`csv_line`); surveys are small beside the memory of a gateway.
        let text = std::fs::read(path).map_err(|e| SurveyError::Read {
            path: path.to_owned(),
            reason: e.to_string(),
        })?;
        let mut reader = csv::ReaderBuilder::new()
            .trim(csv::Trim::All)
            // Short rows are reported per missing column, with the column's name,
            // rather than as the csv crate's bare field-count mismatch.
            .flexible(true)
            .from_reader(std::io::Cursor::new(text));
        let header_error = |reason: String| SurveyError::Header {
            path: path.to_owned(),
            reason,
        };
        let headers = reader
            .headers()
            .map_err(|e| header_error(e.to_string()))?
            .clone();
        let find = |name: &str| headers.iter().position(|h| h.eq_ignore_ascii_case(name));
        let position = match (
            find("x_m"),
            find("y_m"),
            find("location"),
            find("x"),
            find("y"),
        ) {
            (Some(x), Some(y), ..) => Some(Position::Metres(x, y)),
            (_, _, Some(i), _, _) => {
                if !site.has_labels() {
                    return Err(header_error(
                        "the file names cells by `location` label, but the site has no \
                         `[labels]` scheme; add one to the site file or use `x`,`y` columns"
                            .into(),
                    ));
                }
                Some(Position::Label(i))
            }
            (_, _, None, Some(x), Some(y)) => Some(Position::Xy(x, y)),
            _ => None,
        };
        let clock = match (find("date"), find("t")) {
            (Some(i), _) => Clock::Date(i),
            (None, Some(i)) => Clock::Seconds(i),
            (None, None) => Clock::None,
        };
        let column_of: Vec<Option<usize>> = anchors
            .iter()
            .map(|a| headers.iter().position(|h| h == a))
            .collect();
        if column_of.iter().all(Option::is_none) {
            return Err(header_error(format!(
                "no column names an anchor of the site (anchors: {}); name the RSSI columns \
                 after the site's beacon or gateway ids",
                anchors.join(", ")
            )));
        }
        let used: Vec<usize> = column_of.iter().flatten().copied().collect();
        let ignored_columns = headers
            .iter()
            .enumerate()
            .filter(|(i, h)| {
                !used.contains(i) && !KNOWN_COLUMNS.iter().any(|k| h.eq_ignore_ascii_case(k))
            })
            .map(|(_, h)| h.to_owned())
            .collect();
        Ok(SurveyRows {
            reader,
            record: csv::StringRecord::new(),
            lines: LineCounter::default(),
            path: path.to_owned(),
            site,
            headers,
            position,
            clock,
            column_of,
            ignored_columns,
            not_heard,
        })
    }

    /// Whether rows say where they were taken (`x_m` and `y_m`, `location`,
    /// or `x` and `y`).
    pub(crate) fn has_position(&self) -> bool {
        self.position.is_some()
    }

    /// Whether rows say when they were taken (`date` or `t`).
    pub fn has_clock(&self) -> bool {
        !matches!(self.clock, Clock::None)
    }

    /// Which anchors the file has a column for.
    pub(crate) fn present(&self) -> Vec<bool> {
        self.column_of.iter().map(Option::is_some).collect()
    }

    /// Columns that name no anchor and have no meaning of their own.
    pub fn ignored_columns(&self) -> &[String] {
        &self.ignored_columns
    }

    fn field_error(&self, line: u64, column: usize, reason: String) -> SurveyError {
        SurveyError::Field {
            path: self.path.clone(),
            line,
            column: self.headers.get(column).unwrap_or("?").to_owned(),
            reason,
        }
    }

    /// Field `i` of the row in `self.record`.
    fn get(&self, line: u64, i: usize) -> Result<&str, SurveyError> {
        self.record.get(i).ok_or_else(|| {
            self.field_error(
                line,
                i,
                format!(
                    "missing: the row has {} fields and the header {}",
                    self.record.len(),
                    self.headers.len()
                ),
            )
        })
    }

    /// The line `position` is on in the file.
    fn line(&mut self, position: Option<&csv::Position>) -> u64 {
        position.map_or(0, |p| self.lines.line(self.reader.get_ref().get_ref(), p))
    }

    /// Parses the row in `self.record`, which starts on `line`.
    fn parse(&self, line: u64) -> Result<Row, SurveyError> {
        let field = |column: usize, reason: String| self.field_error(line, column, reason);
        let get = |i: usize| self.get(line, i);
        let cell = match self.position {
            None => None,
            Some(Position::Label(i)) => {
                let label = get(i)?;
                // Crowd-sourced rows (the UCI unlabelled file) say `?`: heard
                // somewhere, position unknown.
                if matches!(label.trim(), "" | "?") {
                    return self.finish(line, None);
                }
                Some(self.site.parse_label(label).ok_or_else(|| {
                    field(
                        i,
                        format!("{label:?} is not a cell label on this site's grid"),
                    )
                })?)
            }
            Some(Position::Xy(xi, yi)) => {
                let coord = |i: usize| {
                    let text = get(i)?;
                    text.parse::<u16>()
                        .map_err(|_| field(i, format!("{text:?} is not a cell coordinate")))
                };
                let cell = Cell::new(coord(xi)?, coord(yi)?);
                if !self.site.contains(cell) {
                    return Err(field(xi, format!("cell {cell} is off the site's grid")));
                }
                Some(cell)
            }
            Some(Position::Metres(xi, yi)) => {
                let metres = |i: usize| {
                    let text = get(i)?;
                    text.parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| field(i, format!("{text:?} is not a number of metres")))
                };
                let at = [metres(xi)?, metres(yi)?];
                let Some(cell) = self.site.cell_of_world(at) else {
                    let (lo, hi) = self.site.extent_m();
                    return Err(field(
                        xi,
                        format!(
                            "[{}, {}] m is off the site's grid (x {} to {} m, y {} to {} m); \
                             check the survey against the site's `origin_m` and `y_axis`",
                            at[0], at[1], lo[0], hi[0], lo[1], hi[1]
                        ),
                    ));
                };
                if !self.site.walkable(cell) {
                    return Err(field(
                        xi,
                        format!(
                            "[{}, {}] m is in cell {cell}, which the site blocks ('.', an \
                             obstacle or a wall); fix the position or open that part of the site",
                            at[0], at[1]
                        ),
                    ));
                }
                return self.finish(line, Some((cell, at)));
            }
        };
        self.finish(line, cell.map(|c| (c, self.site.world_of_cell(c))))
    }

    /// Parses the time and readings of the row in `self.record`, taken in
    /// `position` (its cell and world metres).
    fn finish(&self, line: u64, position: Option<(Cell, [f64; 2])>) -> Result<Row, SurveyError> {
        let field = |column: usize, reason: String| self.field_error(line, column, reason);
        let get = |i: usize| self.get(line, i);
        let t = match self.clock {
            Clock::None => None,
            Clock::Date(i) => {
                let text = get(i)?;
                Some(parse_date(text).ok_or_else(|| {
                    field(
                        i,
                        format!("{text:?} is not a date like 10-18-2016 11:15:21"),
                    )
                })?)
            }
            Clock::Seconds(i) => {
                let text = get(i)?;
                Some(
                    text.parse::<f64>()
                        .ok()
                        .filter(|t| t.is_finite())
                        .ok_or_else(|| field(i, format!("{text:?} is not a number of seconds")))?,
                )
            }
        };
        let mut rssi = Vec::with_capacity(self.column_of.len());
        for column in &self.column_of {
            rssi.push(match column {
                None => None,
                Some(i) => {
                    let text = get(*i)?;
                    let v: i16 = text
                        .parse()
                        .map_err(|_| field(*i, format!("{text:?} is not an RSSI in whole dBm")))?;
                    if v > 0 && v != self.not_heard {
                        return Err(field(
                            *i,
                            format!(
                                "{v} is a positive RSSI, which no receiver reports; if it marks \
                                 \"not heard\" in this file, say so (`--not-heard {v}`, or \
                                 `not_heard = {v}`)"
                            ),
                        ));
                    }
                    // Below -127 dBm is outside what BLE reports (an i8): such
                    // values are "not heard" markers of their own (the UCI
                    // files have a few -198 and -199 beside -200).
                    (v != self.not_heard && v >= MIN_RSSI_DBM).then_some(v)
                }
            });
        }
        Ok(Row {
            line,
            cell: position.map(|(c, _)| c),
            at: position.map(|(_, at)| at),
            t,
            rssi,
        })
    }
}

impl Iterator for SurveyRows<'_> {
    type Item = Result<Row, SurveyError>;

    fn next(&mut self) -> Option<Self::Item> {
        match self.reader.read_record(&mut self.record) {
            Ok(false) => None,
            Ok(true) => {
                let position = self.record.position().cloned();
                let line = self.line(position.as_ref());
                Some(self.parse(line))
            }
            Err(e) => Some(Err(SurveyError::Row {
                path: self.path.clone(),
                line: self.line(e.position()),
                reason: format!("not a CSV row: {e}"),
            })),
        }
    }
}

impl Survey {
    /// Reads a survey for `site`; `anchors` are the ids of the site's anchors in
    /// the orientation in use, `not_heard` the sentinel for "not heard".
    pub fn load(
        path: &Path,
        site: &Site,
        anchors: &[String],
        not_heard: i16,
    ) -> Result<Survey, SurveyError> {
        let rows = SurveyRows::open(path, site, anchors, not_heard)?;
        if !rows.has_position() {
            return Err(SurveyError::Header {
                path: path.to_owned(),
                reason: "no position columns; a survey needs `x_m` and `y_m` (metres), \
                         `location` (a label such as O02) or `x` and `y` (cells)"
                    .into(),
            });
        }
        let present = rows.present();
        let ignored_columns = rows.ignored_columns().to_vec();
        let samples = rows
            .map(|row| {
                let row = row?;
                let (Some(cell), Some(at)) = (row.cell, row.at) else {
                    return Err(SurveyError::Field {
                        path: path.to_owned(),
                        line: row.line,
                        column: "location".into(),
                        reason: "no position (`?`): a survey needs every row's cell; give \
                                 unlabelled rows to `gangway calibrate` or `--calibrate` instead"
                            .into(),
                    });
                };
                Ok(Sample {
                    cell,
                    at,
                    t: row.t,
                    rssi: row.rssi,
                })
            })
            .collect::<Result<_, _>>()?;
        Ok(Survey {
            samples,
            anchors: anchors.to_vec(),
            present,
            ignored_columns,
        })
    }

    /// The survey restricted to some of its rows (a training split).
    pub fn subset(&self, rows: &[usize]) -> Survey {
        Survey {
            samples: rows.iter().map(|&r| self.samples[r].clone()).collect(),
            anchors: self.anchors.clone(),
            present: self.present.clone(),
            ignored_columns: self.ignored_columns.clone(),
        }
    }
}

/// `MM-DD-YYYY HH:MM[:SS]` as Unix seconds (the survey's local time, taken as UTC).
fn parse_date(s: &str) -> Option<f64> {
    use chrono::NaiveDateTime;
    NaiveDateTime::parse_from_str(s, "%m-%d-%Y %H:%M:%S")
        .or_else(|_| NaiveDateTime::parse_from_str(s, "%m-%d-%Y %H:%M"))
        .ok()
        .map(|d| d.and_utc().timestamp() as f64)
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;

    impl Survey {
        /// Columns that named no anchor of the site.
        fn ignored_columns(&self) -> &[String] {
            &self.ignored_columns
        }
    }

    const SITE: &str = r#"
name = "t"
cell_m = 1.0
map = '''
###
###
'''
[labels]
first_row = 1
[[beacon]]
id = "b1"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 1
[[beacon]]
id = "b2"
uuid = "b9407f30-f5f8-466e-aff9-25556b57fe6d"
major = 1
minor = 2
"#;

    fn load(csv: &str) -> Result<Survey, SurveyError> {
        let site = Site::parse(SITE, Path::new("t.toml")).unwrap();
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(csv.as_bytes()).unwrap();
        Survey::load(f.path(), &site, &["b1".into(), "b2".into()], -200)
    }

    #[test]
    fn reads_the_uci_layout() {
        let s = load("location,date,b1,b2,b9\nB02,10-18-2016 11:15:21,-70,-200,-80\nA01,10-18-2016 11:15,-200,-65,-200\n").unwrap();
        assert_eq!(s.samples.len(), 2);
        assert_eq!(s.samples[0].cell, Cell::new(1, 1));
        assert_eq!(s.samples[0].rssi, vec![Some(-70), None]);
        assert_eq!(s.samples[1].t, Some(1_476_789_300.0));
        assert_eq!(s.ignored_columns(), ["b9"]);
    }

    #[test]
    fn errors_name_the_line_of_the_bad_value_whatever_the_line_endings() {
        for csv in [
            "x,y,t,b2\n2,0,1.5,-60\n2,0,2.5,loud\n",
            "x,y,t,b2\r\n2,0,1.5,-60\r\n2,0,2.5,loud\r\n",
            "x,y,t,b2\n\n2,0,2.5,loud\n",
        ] {
            let err = load(csv).unwrap_err().to_string();
            assert!(err.contains(":3: column `b2`"), "{csv:?}: {err}");
        }
    }

    #[test]
    fn reads_the_generic_layout() {
        let s = load("x,y,t,b2\n2,0,1.5,-60\n").unwrap();
        assert_eq!(s.samples[0].cell, Cell::new(2, 0));
        assert_eq!(s.samples[0].rssi, vec![None, Some(-60)]);
        assert_eq!(s.present, vec![false, true]);
    }

    #[test]
    fn reads_the_metric_layout_in_the_sites_frame() {
        // The same grid placed at x 10 m, y 5 m with y up; cell [1, 1] blocked.
        let site = SITE
            .replace(
                "cell_m = 1.0",
                "cell_m = 1.0\norigin_m = [10.0, 5.0]\ny_axis = \"up\"",
            )
            .replace("###\n###", "###\n#.#");
        let site = Site::parse(&site, Path::new("t.toml")).unwrap();
        let load = |csv: &str| {
            let mut f = tempfile::NamedTempFile::new().unwrap();
            f.write_all(csv.as_bytes()).unwrap();
            Survey::load(f.path(), &site, &["b1".into(), "b2".into()], -200)
        };
        let s = load("t,x_m,y_m,b1,b2,location\n0,12.25,4.5,-70,-200,A01\n").unwrap();
        assert_eq!(
            s.samples[0].cell,
            Cell::new(2, 0),
            "x_m,y_m win over location"
        );
        assert_eq!(s.samples[0].at, [12.25, 4.5], "the true position is kept");
        let by_cell = load("x,y,b1\n2,0,-70\n").unwrap();
        assert_eq!(by_cell.samples[0].at, [12.5, 4.5], "a cell's centre");

        let err = load("x_m,y_m,b1\n12.5,4.5,-70\n11.2,3.4,-70\n")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(
                ":3: column `x_m`: [11.2, 3.4] m is in cell [1, 1], which the site blocks"
            ),
            "{err}"
        );
        let err = load("x_m,y_m,b1\n12.5,5.5,-70\n").unwrap_err().to_string();
        assert!(
            err.contains(
                ":2: column `x_m`: [12.5, 5.5] m is off the site's grid (x 10 to 13 m, y 3 to 5 m)"
            ),
            "{err}"
        );
        let err = load("x_m,y_m,b1\n12.5,north,-70\n")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(":2: column `y_m`: \"north\" is not a number of metres"),
            "{err}"
        );
    }

    #[test]
    fn names_the_row_and_column_of_bad_fields() {
        let err = load("location,b1,b2\nA01,-70,-6x\n")
            .unwrap_err()
            .to_string();
        assert!(
            err.contains(":2: column `b2`: \"-6x\" is not an RSSI"),
            "{err}"
        );
        let err = load("location,b1\nZ09,-70\n").unwrap_err().to_string();
        assert!(err.contains("column `location`"), "{err}");
        let err = load("where,b1\nA01,-70\n").unwrap_err().to_string();
        assert!(err.contains("no position columns"), "{err}");
        let err = load("location,c1\nA01,-70\n").unwrap_err().to_string();
        assert!(err.contains("no column names an anchor"), "{err}");
    }

    #[test]
    fn a_short_row_names_the_missing_column() {
        let err = load("location,b1,b2\nA01,-70\n").unwrap_err().to_string();
        assert!(
            err.contains(":2: column `b2`: missing: the row has 2 fields and the header 3"),
            "{err}"
        );
    }

    #[test]
    fn reads_dates_without_leading_zeros_and_rejects_absurd_labels() {
        let s = load("location,date,b1\nA01,4-19-2016 9:37:36,-70\n").unwrap();
        assert_eq!(s.samples[0].t, Some(1_461_058_656.0));
        let long = format!("location,b1\n{}01,-70\n", "Z".repeat(40));
        let err = load(&long).unwrap_err().to_string();
        assert!(err.contains("is not a cell label"), "{err}");
    }
}
