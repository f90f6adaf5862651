//! CSV scan logs: one row per scan, one RSSI column per beacon, replayed as
//! adverts (and, when rows are labelled, as ground truth).
//!
//! The layout is the survey layout ([`crate::locate::survey`], whose row reader
//! this uses): a time column (`date` as `MM-DD-YYYY HH:MM[:SS]`, or `t` in
//! seconds), one column per beacon named by its `id` in the site file, and
//! optionally the cell the scan was taken in (`location` label, `x` and `y`, or
//! `x_m` and `y_m` in metres).
//! The UCI BLE RSSI survey is such a log as published.
//!
//! Every row becomes one advert per beacon heard (any value but the "not heard"
//! sentinel) at the row's time, observed by one device id, plus a `truth` event
//! for that device when the row names its cell. The beacon's identity comes from
//! the site file (with its `mac`, where it has one); a scan log has no
//! measured power, so adverts carry none.
//!
//! A scan log is one floor's: on a building of several floors, the floor is
//! the one whose beacons its columns name (every beacon is written in one
//! floor's site file), and its truths are on that floor. A log naming
//! beacons of several floors is refused, saying which floor each is on.
//!
//! Rows are replayed in time order whatever their order in the file (the UCI
//! survey lists its newest rows first). That needs the whole file before the
//! first event, so the reader holds the events in memory: scan logs are
//! hand-made surveys of a few thousand rows, and a long capture belongs in the
//! streaming JSON Lines or btsnoop formats. Rows with equal times keep their file
//! order, or the reverse of it when the file runs backwards overall, so a
//! newest-first file whose times lack seconds still plays forwards.

use std::path::Path;
use std::sync::Arc;

use crate::event::{Event, Truth};
use crate::locate::survey::{Row, SurveyError, SurveyRows};
use crate::sighting::Sighting;
use crate::site::{Building, Floor};

/// How to read a scan log.
#[derive(Clone, Debug)]
pub(crate) struct CsvOptions {
    /// The observer of every advert and the device of every truth event.
    pub device: Arc<str>,
    /// The RSSI value that means "not heard".
    pub not_heard: i16,
    /// Skip and count bad rows and unknown columns instead of refusing the file.
    pub skip_bad: bool,
}

/// A scan log's events in time order.
pub struct CsvLog {
    events: std::vec::IntoIter<Event>,
    #[cfg(test)]
    rows: u64,
    skipped_rows: u64,
    ignored_columns: Vec<String>,
    /// Whether the rows had to be sorted (logged when read; kept for tests).
    #[cfg(test)]
    reordered: bool,
}

impl CsvLog {
    /// Reads a scan log whose beacon columns are named after the beacons of
    /// one floor of `building`.
    pub(crate) fn open(
        path: &Path,
        building: &Building,
        options: &CsvOptions,
    ) -> Result<CsvLog, SurveyError> {
        let header_error = |reason: String| SurveyError::Header {
            path: path.to_owned(),
            reason,
        };
        let floor = floor_of_columns(path, building)?;
        let site = &*building.floors()[floor].site;
        let beacon_ids: Vec<String> = site.beacons.iter().map(|b| b.id.clone()).collect();
        let mut reader = SurveyRows::open(path, site, &beacon_ids, options.not_heard)?;
        if !reader.has_clock() {
            return Err(header_error(
                "no time column; a scan log needs `date` (MM-DD-YYYY HH:MM:SS) or `t` (seconds)"
                    .into(),
            ));
        }
        let ignored_columns = reader.ignored_columns().to_vec();
        if let Some(column) = ignored_columns.first() {
            let reason = match floor_of_beacon(building, column) {
                Some(other) => format!(
                    "is a beacon of floor {}, and the log's other beacons are floor {}'s; a scan \
                     log is one floor's: split it by floor, or pass --skip-bad to ignore such \
                     columns",
                    other.name,
                    building.floors()[floor].name
                ),
                None => format!(
                    "names no beacon of the {} beacons: {}); rename it after a beacon's `id`, \
                     or pass --skip-bad to ignore such columns",
                    if building.is_multi_floor() {
                        format!("building (floor {}'s", building.floors()[floor].name)
                    } else {
                        "site (its".into()
                    },
                    beacon_ids.join(", ")
                ),
            };
            if !options.skip_bad {
                return Err(SurveyError::Field {
                    path: path.to_owned(),
                    line: 1,
                    column: column.clone(),
                    reason,
                });
            }
            tracing::warn!(
                path = %path.display(),
                columns = ?ignored_columns,
                "ignoring columns that name no beacon of the site"
            );
        }

        let mut rows: Vec<Row> = Vec::new();
        let mut skipped_rows = 0;
        for row in reader.by_ref() {
            match row {
                Ok(row) => rows.push(row),
                Err(e) if options.skip_bad => {
                    skipped_rows += 1;
                    tracing::warn!("{e}");
                }
                Err(e) => return Err(e),
            }
        }
        let reordered = sort_by_time(&mut rows);
        if reordered {
            tracing::info!(
                path = %path.display(),
                rows = rows.len(),
                "rows were not in time order; replaying them sorted by time"
            );
        }

        // A one-floor site's truths name no floor, as they always have.
        let floor_name = building
            .is_multi_floor()
            .then(|| building.floors()[floor].name.clone());
        let mut events = Vec::new();
        for row in &rows {
            let t = row.t.expect("checked: the log has a time column");
            if let Some(cell) = row.cell {
                events.push(Event::Truth(Truth {
                    t,
                    device: options.device.to_string(),
                    cell,
                    floor: floor_name.clone(),
                }));
            }
            for (beacon, rssi) in site.beacons.iter().zip(&row.rssi) {
                if let Some(rssi) = *rssi {
                    events.push(Event::Advert(Sighting {
                        // The column is the site's beacon, so its address too.
                        advertiser_mac: beacon.mac,
                        t,
                        observer: options.device.clone(),
                        advertiser: beacon.beacon,
                        // A scan log carries no frame, so no measured power;
                        // the site's `tx_power`, if any, applies downstream.
                        tx_power: None,
                        rssi,
                    }));
                }
            }
        }
        Ok(CsvLog {
            events: events.into_iter(),
            #[cfg(test)]
            rows: rows.len() as u64,
            skipped_rows,
            ignored_columns,
            #[cfg(test)]
            reordered,
        })
    }

    /// Bad rows skipped (only with `skip_bad`).
    pub(crate) fn skipped_rows(&self) -> u64 {
        self.skipped_rows
    }

    /// Columns ignored because they name no beacon (only with `skip_bad`).
    pub(crate) fn ignored_columns(&self) -> &[String] {
        &self.ignored_columns
    }
}

impl Iterator for CsvLog {
    type Item = Event;

    fn next(&mut self) -> Option<Event> {
        self.events.next()
    }
}

/// The floor of `building` whose site file has the beacon `id`.
fn floor_of_beacon<'a>(building: &'a Building, id: &str) -> Option<&'a Floor> {
    building
        .floors()
        .iter()
        .find(|f| f.site.beacons.iter().any(|b| b.id == id))
}

/// The floor of `building` whose beacons the log's columns name most of (a
/// tie, or none named, is refused: the log does not say its floor).
fn floor_of_columns(path: &Path, building: &Building) -> Result<usize, SurveyError> {
    if !building.is_multi_floor() {
        return Ok(0);
    }
    let read_error = |e: csv::Error| SurveyError::Read {
        path: path.to_owned(),
        reason: e.to_string(),
    };
    let mut reader = csv::Reader::from_path(path).map_err(read_error)?;
    let columns: Vec<String> = reader
        .headers()
        .map_err(read_error)?
        .iter()
        .map(|c| c.trim().to_owned())
        .collect();
    let named: Vec<usize> = building
        .floors()
        .iter()
        .map(|f| {
            columns
                .iter()
                .filter(|c| f.site.beacons.iter().any(|b| b.id == **c))
                .count()
        })
        .collect();
    let most = *named.iter().max().expect("a building has floors");
    let best: Vec<&str> = (0..named.len())
        .filter(|&i| named[i] == most)
        .map(|i| building.floors()[i].name.as_str())
        .collect();
    let header_error = |reason: String| SurveyError::Header {
        path: path.to_owned(),
        reason,
    };
    if most == 0 {
        return Err(header_error(
            "no column names a beacon of the building; name the RSSI columns after the `id`s \
             of the beacons of the floor the log was taken on"
                .into(),
        ));
    }
    if best.len() > 1 {
        let of: Vec<String> = columns
            .iter()
            .filter_map(|c| {
                let floor = floor_of_beacon(building, c)?;
                Some(format!("{c} on {}", floor.name))
            })
            .collect();
        return Err(header_error(format!(
            "its columns name as many beacons of {} ({}); a scan log is one floor's: split it \
             by floor",
            best.join(" as of "),
            of.join(", ")
        )));
    }
    Ok(named.iter().position(|&n| n == most).expect("found"))
}

/// Sorts rows by time; returns whether they were out of order.
fn sort_by_time(rows: &mut [Row]) -> bool {
    let t = |r: &Row| r.t.unwrap_or(f64::NAN);
    let (mut forward, mut backward) = (0usize, 0usize);
    for pair in rows.windows(2) {
        match t(&pair[0]).total_cmp(&t(&pair[1])) {
            std::cmp::Ordering::Less => forward += 1,
            std::cmp::Ordering::Greater => backward += 1,
            std::cmp::Ordering::Equal => {}
        }
    }
    if backward == 0 {
        return false;
    }
    if backward > forward {
        rows.reverse();
    }
    rows.sort_by(|a, b| t(a).total_cmp(&t(b)));
    true
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::site::{Cell, Site};
    use std::io::Write;

    impl CsvLog {
        /// Rows read (not counting skipped ones).
        fn rows(&self) -> u64 {
            self.rows
        }

        /// Whether the rows had to be sorted into time order.
        fn reordered(&self) -> bool {
            self.reordered
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
tx_power = -61
"#;

    fn site() -> Site {
        Site::parse(SITE, Path::new("t.toml")).unwrap()
    }

    fn options(skip_bad: bool) -> CsvOptions {
        CsvOptions {
            device: "survey".into(),
            not_heard: -200,
            skip_bad,
        }
    }

    fn open_with(csv: &str, options: &CsvOptions) -> Result<(CsvLog, Vec<Event>), SurveyError> {
        let mut f = tempfile::NamedTempFile::new().unwrap();
        f.write_all(csv.as_bytes()).unwrap();
        let building = Building::of_site(Arc::new(site()));
        let mut log = CsvLog::open(f.path(), &building, options)?;
        let events = log.by_ref().collect();
        Ok((log, events))
    }

    fn open(csv: &str) -> Result<Vec<Event>, SurveyError> {
        open_with(csv, &options(false)).map(|(_, events)| events)
    }

    fn error(csv: &str) -> String {
        open(csv).unwrap_err().to_string()
    }

    #[test]
    fn a_newest_first_uci_log_replays_forwards_with_truth() {
        let (log, events) = open_with(
            "location,date,b1,b2\n\
             B02,10-18-2016 11:15:24,-200,-70\n\
             A01,10-18-2016 11:15:21,-75,-200\n",
            &options(false),
        )
        .unwrap();
        assert!(log.reordered());
        assert_eq!(log.rows(), 2);
        let site = site();
        let t0 = 1_476_789_321.0;
        assert_eq!(
            events,
            vec![
                Event::Truth(Truth {
                    t: t0,
                    device: "survey".into(),
                    cell: Cell::new(0, 0),
                    floor: None,
                }),
                Event::Advert(Sighting {
                    advertiser_mac: None,
                    t: t0,
                    observer: "survey".into(),
                    advertiser: site.beacons[0].beacon,
                    tx_power: None,
                    rssi: -75,
                }),
                Event::Truth(Truth {
                    t: t0 + 3.0,
                    device: "survey".into(),
                    cell: Cell::new(1, 1),
                    floor: None,
                }),
                Event::Advert(Sighting {
                    advertiser_mac: None,
                    t: t0 + 3.0,
                    observer: "survey".into(),
                    advertiser: site.beacons[1].beacon,
                    tx_power: None,
                    rssi: -70,
                }),
            ]
        );
    }

    #[test]
    fn rows_with_equal_times_in_a_backwards_file_are_reversed_too() {
        // Newest first, and the two oldest rows lack seconds (same time).
        let events = open(
            "location,date,b1\n\
             C02,10-18-2016 11:16:05,-70\n\
             B01,10-18-2016 11:15,-71\n\
             A01,10-18-2016 11:15,-72\n",
        )
        .unwrap();
        let rssi: Vec<i16> = events
            .iter()
            .filter_map(|e| match e {
                Event::Advert(s) => Some(s.rssi),
                _ => None,
            })
            .collect();
        assert_eq!(rssi, vec![-72, -71, -70]);
    }

    #[test]
    fn a_forward_log_without_labels_keeps_its_order_and_has_no_truth() {
        let (log, events) = open_with("t,b1,b2\n1.5,-60,-100\n2.5,-100,-100\n", &{
            let mut o = options(false);
            o.not_heard = -100;
            o
        })
        .unwrap();
        assert!(!log.reordered());
        assert_eq!(events.len(), 1);
        assert!(matches!(&events[0], Event::Advert(s) if s.t == 1.5 && s.rssi == -60));
    }

    #[test]
    fn bad_rows_name_their_row_and_column_or_are_skipped_and_counted() {
        let csv = "location,t,b1,b2\nA01,1,-70,-6x\nA02,2,-70\nA01,3,-71,-200\n";
        let err = error(csv);
        assert!(
            err.contains(":2: column `b2`: \"-6x\" is not an RSSI"),
            "{err}"
        );
        let (log, events) = open_with(csv, &options(true)).unwrap();
        assert_eq!(log.skipped_rows(), 2);
        assert_eq!(log.rows(), 1);
        assert_eq!(events.len(), 2); // truth + one advert of row 4
        let err = error("location,t,b1,b2\nA01,1,-70\n");
        assert!(err.contains(":2: column `b2`: missing"), "{err}");
        let err = error("location,t,b1\nA01,soon,-70\n");
        assert!(
            err.contains(":2: column `t`: \"soon\" is not a number"),
            "{err}"
        );
    }

    #[test]
    fn unknown_anchor_columns_are_refused_or_ignored_with_the_flag() {
        let csv = "t,b1,b7\n1,-70,-60\n";
        let err = error(csv);
        assert!(
            err.contains(":1: column `b7`: names no beacon of the site"),
            "{err}"
        );
        let (log, events) = open_with(csv, &options(true)).unwrap();
        assert_eq!(log.ignored_columns(), ["b7"]);
        assert_eq!(events.len(), 1);
    }

    #[test]
    fn a_log_needs_a_clock_and_a_beacon_column() {
        assert!(error("location,b1\nA01,-70\n").contains("no time column"));
        assert!(error("t,c1\n1,-70\n").contains("no column names an anchor"));
    }
}
