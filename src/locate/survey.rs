//! Site surveys: RSSI readings labelled with the cell they were taken in.
//!
//! Two CSV layouts are read, both with one column per anchor named by the
//! anchor's id in the site file:
//! - the UCI BLE RSSI layout as published: `location` (a survey label such as
//!   `O02`, read with the site's `[labels]` scheme), an optional `date`
//!   (`MM-DD-YYYY HH:MM[:SS]`), then the anchors;
//! - a generic layout: `x`, `y`, an optional `t` (seconds), then the anchors.
//!
//! A reading equal to the "not heard" sentinel (default -200) means the anchor
//! was not heard. Columns that name no anchor of the site are ignored (and
//! listed by [`Survey::ignored_columns`]); a cell, time or RSSI that does not
//! parse refuses the file with its row and column.

use std::path::{Path, PathBuf};

use crate::site::{Cell, Site};

/// One labelled reading.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    pub cell: Cell,
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
    #[error("{path}: cannot read the survey: {reason}")]
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
}

enum Position {
    Label(usize),
    Xy(usize, usize),
}

enum Clock {
    None,
    Date(usize),
    Seconds(usize),
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
        let mut reader = csv::ReaderBuilder::new()
            .trim(csv::Trim::All)
            .from_path(path)
            .map_err(|e| SurveyError::Read {
                path: path.to_owned(),
                reason: e.to_string(),
            })?;
        let header_error = |reason: String| SurveyError::Header {
            path: path.to_owned(),
            reason,
        };
        let headers = reader
            .headers()
            .map_err(|e| header_error(e.to_string()))?
            .clone();
        let find = |name: &str| headers.iter().position(|h| h.eq_ignore_ascii_case(name));
        let position = match (find("location"), find("x"), find("y")) {
            (Some(i), _, _) => {
                if !site.has_labels() {
                    return Err(header_error(
                        "the survey names cells by `location` label, but the site has no \
                         `[labels]` scheme; add one to the site file or use `x`,`y` columns"
                            .into(),
                    ));
                }
                Position::Label(i)
            }
            (None, Some(x), Some(y)) => Position::Xy(x, y),
            _ => {
                return Err(header_error(
                    "no position columns; a survey needs `location` (a label such as O02) \
                     or `x` and `y`"
                        .into(),
                ));
            }
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
                !used.contains(i)
                    && !["location", "x", "y", "date", "t"]
                        .iter()
                        .any(|k| h.eq_ignore_ascii_case(k))
            })
            .map(|(_, h)| h.to_owned())
            .collect();

        let mut samples = Vec::new();
        for record in reader.records() {
            let record = record.map_err(|e| SurveyError::Read {
                path: path.to_owned(),
                reason: e.to_string(),
            })?;
            let line = record.position().map_or(0, |p| p.line());
            let field = |column: usize, reason: String| SurveyError::Field {
                path: path.to_owned(),
                line,
                column: headers.get(column).unwrap_or("?").to_owned(),
                reason,
            };
            let get = |i: usize| record.get(i).unwrap_or("");
            let cell = match position {
                Position::Label(i) => site.parse_label(get(i)).ok_or_else(|| {
                    field(
                        i,
                        format!("{:?} is not a cell label on this site's grid", get(i)),
                    )
                })?,
                Position::Xy(xi, yi) => {
                    let coord = |i: usize| {
                        get(i)
                            .parse::<u16>()
                            .map_err(|_| field(i, format!("{:?} is not a cell coordinate", get(i))))
                    };
                    let cell = Cell::new(coord(xi)?, coord(yi)?);
                    if !site.contains(cell) {
                        return Err(field(xi, format!("cell {cell} is off the site's grid")));
                    }
                    cell
                }
            };
            let t =
                match clock {
                    Clock::None => None,
                    Clock::Date(i) => Some(parse_date(get(i)).ok_or_else(|| {
                        field(
                            i,
                            format!("{:?} is not a date like 10-18-2016 11:15:21", get(i)),
                        )
                    })?),
                    Clock::Seconds(i) => Some(get(i).parse::<f64>().map_err(|_| {
                        field(i, format!("{:?} is not a number of seconds", get(i)))
                    })?),
                };
            let mut rssi = Vec::with_capacity(anchors.len());
            for column in &column_of {
                rssi.push(match column {
                    None => None,
                    Some(i) => {
                        let v: i16 = get(*i).parse().map_err(|_| {
                            field(*i, format!("{:?} is not an RSSI in whole dBm", get(*i)))
                        })?;
                        (v != not_heard).then_some(v)
                    }
                });
            }
            samples.push(Sample { cell, t, rssi });
        }
        Ok(Survey {
            samples,
            anchors: anchors.to_vec(),
            present: column_of.iter().map(Option::is_some).collect(),
            ignored_columns,
        })
    }

    /// Columns that named no anchor of the site.
    pub fn ignored_columns(&self) -> &[String] {
        &self.ignored_columns
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
    fn reads_the_generic_layout() {
        let s = load("x,y,t,b2\n2,0,1.5,-60\n").unwrap();
        assert_eq!(s.samples[0].cell, Cell::new(2, 0));
        assert_eq!(s.samples[0].rssi, vec![None, Some(-60)]);
        assert_eq!(s.present, vec![false, true]);
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
}
