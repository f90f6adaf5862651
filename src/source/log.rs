//! The advert log: JSON Lines, one event per line (format in the README, "Advert
//! log format").
//!
//! ```text
//! {"t":12.5,"type":"advert","observer":"gw-1","uuid":"…","major":1,"minor":3001,"rssi":-71,"tx_power":-59}
//! {"t":13.0,"type":"request","device":"phone-7","to":"help desk","request_id":"r1"}
//! {"t":13.0,"type":"truth","device":"phone-7","cell":[9,9]}
//! ```
//!
//! The reader streams: it holds one line at a time, so a log of any size replays
//! in constant memory. A bad line is reported as `file:line: reason`; with
//! `skip_bad` it is counted and skipped instead, and the rest of the log still
//! plays.

use std::borrow::Cow;
use std::collections::HashMap;
use std::fs::File;
use std::io::{self, BufRead, BufReader, BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use uuid::Uuid;

use super::{Event, RouteRequest, Truth};
use crate::plan::Destination;
use crate::sighting::{BeaconId, Sighting};
use crate::site::Cell;

/// One line of the log, as written.
#[derive(Serialize, Deserialize)]
#[serde(tag = "type", rename_all = "lowercase", deny_unknown_fields)]
enum Line<'a> {
    Advert {
        t: f64,
        /// `Cow` because a JSON string with escapes cannot be borrowed.
        #[serde(borrow)]
        observer: Cow<'a, str>,
        uuid: Uuid,
        major: u16,
        minor: u16,
        rssi: i16,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        tx_power: Option<i8>,
    },
    Request {
        t: f64,
        device: String,
        to: Destination,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        profile: Option<String>,
        #[serde(default, skip_serializing_if = "Option::is_none")]
        request_id: Option<String>,
    },
    Truth {
        t: f64,
        device: String,
        cell: Cell,
    },
}

/// A line that could not be used.
#[derive(Debug, thiserror::Error)]
#[error("{}:{line}: {reason}", path.display())]
pub struct LogError {
    pub path: PathBuf,
    pub line: u64,
    pub reason: String,
}

/// Streams events from a log.
pub struct LogReader<R> {
    input: R,
    path: PathBuf,
    line_no: u64,
    buf: Vec<u8>,
    skip_bad: bool,
    skipped: u64,
    /// Observers repeat on every line; sharing one `Arc<str>` per observer keeps
    /// replay from allocating a string per advert.
    observers: HashMap<String, Arc<str>>,
}

impl LogReader<BufReader<File>> {
    /// Opens a log file.
    pub fn open(path: &Path, skip_bad: bool) -> Result<Self, LogError> {
        let file = File::open(path).map_err(|e| LogError {
            path: path.to_owned(),
            line: 0,
            reason: format!("cannot open the log: {e}"),
        })?;
        Ok(LogReader::new(
            BufReader::with_capacity(1 << 16, file),
            path,
            skip_bad,
        ))
    }
}

impl<R: BufRead> LogReader<R> {
    /// Reads from any buffered input; `path` names it in errors.
    pub fn new(input: R, path: &Path, skip_bad: bool) -> Self {
        LogReader {
            input,
            path: path.to_owned(),
            line_no: 0,
            buf: Vec::new(),
            skip_bad,
            skipped: 0,
            observers: HashMap::new(),
        }
    }

    /// Bad lines skipped so far (only with `skip_bad`).
    pub fn skipped(&self) -> u64 {
        self.skipped
    }

    fn error(&self, reason: String) -> LogError {
        LogError {
            path: self.path.clone(),
            line: self.line_no,
            reason,
        }
    }

    fn parse_line(&mut self) -> Result<Option<Event>, String> {
        let text = std::str::from_utf8(&self.buf)
            .map_err(|e| format!("the line is not UTF-8 text ({e})"))?
            .trim();
        if text.is_empty() {
            return Ok(None);
        }
        let line: Line = serde_json::from_str(text).map_err(|e| {
            format!("{e}; each line must be one JSON event (see the README, \"Advert log format\")")
        })?;
        let event = match line {
            Line::Advert {
                t,
                observer,
                uuid,
                major,
                minor,
                rssi,
                tx_power,
            } => {
                let observer = match self.observers.get(observer.as_ref()) {
                    Some(o) => o.clone(),
                    None => {
                        let o: Arc<str> = observer.as_ref().into();
                        self.observers.insert(observer.into_owned(), o.clone());
                        o
                    }
                };
                Event::Advert(Sighting {
                    t,
                    observer,
                    advertiser: BeaconId { uuid, major, minor },
                    tx_power,
                    rssi,
                })
            }
            Line::Request {
                t,
                device,
                to,
                profile,
                request_id,
            } => Event::Request(RouteRequest {
                t,
                device,
                to,
                profile,
                request_id,
            }),
            Line::Truth { t, device, cell } => Event::Truth(Truth { t, device, cell }),
        };
        if !event.t().is_finite() {
            return Err("`t` must be a finite number of seconds".into());
        }
        Ok(Some(event))
    }
}

impl<R: BufRead> Iterator for LogReader<R> {
    type Item = Result<Event, LogError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            self.buf.clear();
            self.line_no += 1;
            match self.input.read_until(b'\n', &mut self.buf) {
                Ok(0) => return None,
                Ok(_) => {}
                Err(e) => return Some(Err(self.error(format!("cannot read: {e}")))),
            }
            match self.parse_line() {
                Ok(Some(event)) => return Some(Ok(event)),
                Ok(None) => continue,
                Err(reason) if self.skip_bad => {
                    self.skipped += 1;
                    tracing::warn!("{}", self.error(reason));
                }
                Err(reason) => return Some(Err(self.error(reason))),
            }
        }
    }
}

/// Writes events as JSON Lines.
pub struct LogWriter<W: Write> {
    out: W,
}

impl LogWriter<BufWriter<File>> {
    pub fn create(path: &Path) -> io::Result<Self> {
        Ok(LogWriter::new(BufWriter::new(File::create(path)?)))
    }
}

impl<W: Write> LogWriter<W> {
    pub fn new(out: W) -> Self {
        LogWriter { out }
    }

    pub fn write(&mut self, event: &Event) -> io::Result<()> {
        let line = match event {
            Event::Advert(s) => Line::Advert {
                t: s.t,
                observer: Cow::Borrowed(&s.observer),
                uuid: s.advertiser.uuid,
                major: s.advertiser.major,
                minor: s.advertiser.minor,
                rssi: s.rssi,
                tx_power: s.tx_power,
            },
            Event::Request(r) => Line::Request {
                t: r.t,
                device: r.device.clone(),
                to: r.to.clone(),
                profile: r.profile.clone(),
                request_id: r.request_id.clone(),
            },
            Event::Truth(g) => Line::Truth {
                t: g.t,
                device: g.device.clone(),
                cell: g.cell,
            },
        };
        serde_json::to_writer(&mut self.out, &line)?;
        self.out.write_all(b"\n")
    }

    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn read(text: &[u8], skip_bad: bool) -> (Vec<Result<Event, LogError>>, u64) {
        let mut reader = LogReader::new(text, Path::new("t.jsonl"), skip_bad);
        let events = reader.by_ref().collect();
        (events, reader.skipped())
    }

    const ADVERT: &str = r#"{"t":1.5,"type":"advert","observer":"gw","uuid":"5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84","major":1,"minor":2,"rssi":-70,"tx_power":-59}"#;

    #[test]
    fn round_trips_every_event_type() {
        let text = format!(
            "{ADVERT}\n\n{}\n{}\n",
            r#"{"t":2,"type":"request","device":"p","to":[3,4],"request_id":"r"}"#,
            r#"{"t":3,"type":"truth","device":"p","cell":[1,2]}"#
        );
        let (events, _) = read(text.as_bytes(), false);
        let events: Vec<Event> = events.into_iter().map(Result::unwrap).collect();
        assert_eq!(events.len(), 3, "blank lines are ignored");
        let mut out = Vec::new();
        let mut writer = LogWriter::new(&mut out);
        for e in &events {
            writer.write(e).unwrap();
        }
        let (again, _) = read(&out, false);
        assert_eq!(
            again.into_iter().map(Result::unwrap).collect::<Vec<_>>(),
            events
        );
    }

    #[test]
    fn bad_lines_are_named_or_skipped_and_counted() {
        let mut bytes = format!("{ADVERT}\nnot json\n").into_bytes();
        bytes.extend_from_slice(b"\xff\xfe\n"); // not UTF-8
        bytes.extend_from_slice(format!("{ADVERT}\n{{\"t\":1,\"type\":\"dance\"}}\n").as_bytes());
        let (events, _) = read(&bytes, false);
        assert!(events[0].is_ok());
        let err = events[1].as_ref().unwrap_err().to_string();
        assert!(err.starts_with("t.jsonl:2: expected ident"), "{err}");

        let (events, skipped) = read(&bytes, true);
        assert_eq!(events.iter().filter(|e| e.is_ok()).count(), 2);
        assert_eq!(skipped, 3);
    }

    #[test]
    fn a_line_cut_short_is_an_error_with_its_number() {
        let text = format!("{ADVERT}\n{}", &ADVERT[..40]);
        let (events, _) = read(text.as_bytes(), false);
        let err = events[1].as_ref().unwrap_err();
        assert_eq!(err.line, 2);
        assert!(err.reason.contains("EOF"), "{}", err.reason);
    }
}
