//! The advert log: JSON Lines, one event per line (format in the README, "Advert
//! log format").
//!
//! ```text
//! {"t":12.5,"type":"advert","observer":"gw-1","uuid":"…","major":1,"minor":3001,"rssi":-71,"tx_power":-59,"mac":"E0:78:A3:3D:B5:D6"}
//! {"t":13.0,"type":"request","device":"phone-7","to":"help desk","request_id":"r1"}
//! {"t":13.0,"type":"truth","device":"phone-7","cell":[9,9]}
//! ```
//!
//! The reader streams: it holds one line at a time, and a line over
//! [`MAX_LINE_BYTES`] is a bad line (read past, never held), so a log of any
//! size or shape replays in constant memory. A bad line is reported as
//! `file:line: reason`; with `skip_bad` it is counted and skipped instead, and
//! the rest of the log still plays: the first few are logged each, then one
//! summary per [`SKIP_WARN_EVERY`] (the caller logs the final count). A device
//! or observer id that cannot be an MQTT topic level makes a line bad too, as
//! it would in a message from the broker.

use foldhash::HashMap;
use std::borrow::Cow;
use std::fs::File;
use std::io::{self, BufRead, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use serde::{Deserialize, Serialize};
use uuid::Uuid;

use crate::event::{Event, FLOOR_NAME_RULE, RouteRequest, Truth, valid_floor_name};
use crate::plan::Destination;
use crate::sighting::valid_device_id;
use crate::sighting::{BeaconId, Mac, Sighting};
use crate::site::Cell;
use crate::throttle::Throttle;

mod fast;

/// One line of the log, read and written.
///
/// One flat struct rather than an enum tagged by `type`: serde reads a tagged
/// enum by first buffering every field of the line, which took a fifth of
/// replay time; a flat struct is read in one pass, and [`Line::into_event`]
/// checks which fields belong to the line's type. The fields are in the
/// order they are written, so each type's lines keep their field order.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Line<'a> {
    #[serde(rename = "type")]
    kind: Kind,
    t: f64,
    #[serde(borrow, default, skip_serializing_if = "Option::is_none")]
    observer: Option<Text<'a>>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    uuid: Option<Uuid>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    major: Option<u16>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    minor: Option<u16>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    rssi: Option<i16>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    tx_power: Option<i8>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    mac: Option<Mac>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    device: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    to: Option<Destination>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    floor: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    profile: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    request_id: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    cell: Option<Cell>,
}

#[derive(Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
enum Kind {
    Advert,
    Request,
    Truth,
}

/// A string borrowed from the line when it has no escapes (observers repeat
/// on every advert line, so replay does not allocate one per line).
#[derive(Serialize, Deserialize)]
struct Text<'a>(#[serde(borrow)] Cow<'a, str>);

impl Line<'_> {
    fn new(kind: Kind, t: f64) -> Self {
        Line {
            kind,
            t,
            observer: None,
            uuid: None,
            major: None,
            minor: None,
            rssi: None,
            tx_power: None,
            mac: None,
            device: None,
            to: None,
            floor: None,
            profile: None,
            request_id: None,
            cell: None,
        }
    }

    /// The first field present that lines of this type do not have.
    fn foreign_field(&self) -> Option<&'static str> {
        use Kind::{Advert, Request, Truth};
        let fields: [(&str, bool, &[Kind]); 13] = [
            ("observer", self.observer.is_some(), &[Advert]),
            ("uuid", self.uuid.is_some(), &[Advert]),
            ("major", self.major.is_some(), &[Advert]),
            ("minor", self.minor.is_some(), &[Advert]),
            ("rssi", self.rssi.is_some(), &[Advert]),
            ("tx_power", self.tx_power.is_some(), &[Advert]),
            ("mac", self.mac.is_some(), &[Advert]),
            ("device", self.device.is_some(), &[Request, Truth]),
            ("to", self.to.is_some(), &[Request]),
            ("floor", self.floor.is_some(), &[Request, Truth]),
            ("profile", self.profile.is_some(), &[Request]),
            ("request_id", self.request_id.is_some(), &[Request]),
            ("cell", self.cell.is_some(), &[Truth]),
        ];
        fields
            .into_iter()
            .find(|(_, present, kinds)| *present && !kinds.contains(&self.kind))
            .map(|(name, _, _)| name)
    }
}

impl Kind {
    fn name(self) -> &'static str {
        match self {
            Kind::Advert => "advert",
            Kind::Request => "request",
            Kind::Truth => "truth",
        }
    }
}

/// A field a line of its type must have.
fn required<T>(value: Option<T>, field: &str) -> Result<T, String> {
    value.ok_or_else(|| format!("missing field `{field}`"))
}

/// Longest line read, in bytes; a longer one is a bad line.
pub(crate) const MAX_LINE_BYTES: usize = 1 << 20;
/// Bad lines logged one by one with `skip_bad` before summaries start.
const SKIP_WARN_FIRST: u64 = 10;
/// Then one summary line per this period.
const SKIP_WARN_EVERY: std::time::Duration = std::time::Duration::from_secs(10);

/// An id (device, observer) that must be usable as one MQTT topic level.
fn topic_id(id: String, field: &str) -> Result<String, String> {
    if valid_device_id(&id) {
        Ok(id)
    } else {
        Err(format!(
            "`{field}` cannot be an MQTT topic level (empty, over 128 bytes, or `+`, `#`, `/`, \
             control characters)"
        ))
    }
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
    /// Summarises warnings about skipped lines.
    skip_warnings: Throttle,
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
            skip_warnings: Throttle::new(SKIP_WARN_EVERY),
            observers: HashMap::default(),
        }
    }

    /// Bad lines skipped so far (only with `skip_bad`).
    pub(crate) fn skipped(&self) -> u64 {
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
        let line = match fast::advert(text) {
            Some(line) => line,
            None => serde_json::from_str(text).map_err(|e| {
                format!(
                    "{e}; each line must be one JSON event (see the README, \"Advert log format\")"
                )
            })?,
        };
        if let Some(field) = line.foreign_field() {
            return Err(format!(
                "unknown field `{field}` in a `{}` line",
                line.kind.name()
            ));
        }
        let t = line.t;
        let event = match line.kind {
            Kind::Advert => {
                let observer = required(line.observer, "observer")?.0;
                let observer = match self.observers.get(observer.as_ref()) {
                    Some(o) => o.clone(),
                    None => {
                        let observer = topic_id(observer.into_owned(), "observer")?;
                        let o: Arc<str> = observer.as_str().into();
                        self.observers.insert(observer, o.clone());
                        o
                    }
                };
                Event::Advert(Sighting {
                    advertiser_mac: line.mac,
                    t,
                    observer,
                    advertiser: BeaconId {
                        uuid: required(line.uuid, "uuid")?,
                        major: required(line.major, "major")?,
                        minor: required(line.minor, "minor")?,
                    },
                    tx_power: line.tx_power,
                    rssi: required(line.rssi, "rssi")?,
                })
            }
            Kind::Request => Event::Request(RouteRequest {
                t,
                device: topic_id(required(line.device, "device")?, "device")?,
                to: required(line.to, "to")?,
                floor: line.floor,
                profile: line.profile,
                request_id: line.request_id,
            }),
            Kind::Truth => Event::Truth(Truth {
                t,
                device: topic_id(required(line.device, "device")?, "device")?,
                cell: required(line.cell, "cell")?,
                floor: match line.floor {
                    Some(floor) if !valid_floor_name(&floor) => return Err(FLOOR_NAME_RULE.into()),
                    floor => floor,
                },
            }),
        };
        if !event.t().is_finite() {
            return Err("`t` must be a finite number of seconds".into());
        }
        Ok(Some(event))
    }

    /// Reads the next line into `buf`; `Ok(None)` at the end, `Ok(Some(false))`
    /// for a line over [`MAX_LINE_BYTES`] (read past in bounded chunks, `buf`
    /// left empty).
    fn read_line(&mut self) -> io::Result<Option<bool>> {
        let limit = MAX_LINE_BYTES as u64 + 1;
        if (&mut self.input)
            .take(limit)
            .read_until(b'\n', &mut self.buf)?
            == 0
        {
            return Ok(None);
        }
        if self.buf.len() as u64 == limit && self.buf.last() != Some(&b'\n') {
            loop {
                self.buf.clear();
                let n = (&mut self.input)
                    .take(1 << 16)
                    .read_until(b'\n', &mut self.buf)?;
                if n == 0 || self.buf.last() == Some(&b'\n') {
                    break;
                }
            }
            self.buf.clear();
            return Ok(Some(false));
        }
        Ok(Some(true))
    }

    /// Counts a skipped line and logs it, or a summary, or nothing.
    fn skip(&mut self, reason: String) {
        self.skipped += 1;
        if self.skipped <= SKIP_WARN_FIRST {
            tracing::warn!("{}", self.error(reason));
        } else if let Some(not_logged) = self.skip_warnings.ready() {
            tracing::warn!(
                skipped = self.skipped,
                not_logged,
                "{} (bad lines are summarised from here on; the total is logged at the end)",
                self.error(reason)
            );
        }
    }
}

impl<R: BufRead> Iterator for LogReader<R> {
    type Item = Result<Event, LogError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            self.buf.clear();
            self.line_no += 1;
            let parsed = match self.read_line() {
                Ok(None) => return None,
                Ok(Some(true)) => self.parse_line(),
                Ok(Some(false)) => Err(format!(
                    "the line is longer than {MAX_LINE_BYTES} bytes; an event is one short JSON line"
                )),
                Err(e) => return Some(Err(self.error(format!("cannot read: {e}")))),
            };
            match parsed {
                Ok(Some(event)) => return Some(Ok(event)),
                Ok(None) => continue,
                Err(reason) if self.skip_bad => self.skip(reason),
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
    pub(crate) fn new(out: W) -> Self {
        LogWriter { out }
    }

    pub fn write(&mut self, event: &Event) -> io::Result<()> {
        let line = match event {
            Event::Advert(s) => Line {
                observer: Some(Text(Cow::Borrowed(&s.observer))),
                uuid: Some(s.advertiser.uuid),
                major: Some(s.advertiser.major),
                minor: Some(s.advertiser.minor),
                rssi: Some(s.rssi),
                tx_power: s.tx_power,
                mac: s.advertiser_mac,
                ..Line::new(Kind::Advert, s.t)
            },
            Event::Request(r) => Line {
                device: Some(r.device.clone()),
                to: Some(r.to.clone()),
                floor: r.floor.clone(),
                profile: r.profile.clone(),
                request_id: r.request_id.clone(),
                ..Line::new(Kind::Request, r.t)
            },
            Event::Truth(g) => Line {
                device: Some(g.device.clone()),
                cell: Some(g.cell),
                floor: g.floor.clone(),
                ..Line::new(Kind::Truth, g.t)
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

    #[test]
    fn a_line_too_long_is_a_bad_line_read_past_in_bounded_memory() {
        let mut bytes = vec![b'x'; MAX_LINE_BYTES * 3];
        bytes.push(b'\n');
        bytes.extend_from_slice(format!("{ADVERT}\n").as_bytes());
        bytes.extend(std::iter::repeat_n(b'y', MAX_LINE_BYTES + 10)); // no newline at the end
        let mut reader = LogReader::new(&bytes[..], Path::new("t.jsonl"), false);
        let err = reader.next().unwrap().unwrap_err();
        assert_eq!(err.line, 1);
        assert!(err.reason.contains("longer than"), "{}", err.reason);
        assert!(reader.buf.capacity() <= MAX_LINE_BYTES + 1 + (1 << 16));
        assert!(reader.next().unwrap().is_ok(), "the next line still reads");
        assert!(reader.next().unwrap().is_err());
        assert!(reader.next().is_none());
    }

    #[test]
    fn ids_that_cannot_be_topic_levels_are_bad_lines() {
        let (events, skipped) = read(
            concat!(
                r#"{"t":1,"type":"request","device":"a/#","to":"desk"}"#,
                "\n",
                r#"{"t":1,"type":"truth","device":"","cell":[1,2]}"#,
                "\n",
                r#"{"t":1,"type":"advert","observer":"g+w","uuid":"5e1a6f3c-2b1d-4c8e-9a70-3d2f1c0b9e84","major":1,"minor":2,"rssi":-70}"#,
                "\n",
            )
            .as_bytes(),
            true,
        );
        assert!(events.is_empty());
        assert_eq!(skipped, 3);
        let (events, _) = read(
            br#"{"t":1,"type":"request","device":"a/#","to":"desk"}"#,
            false,
        );
        let err = events[0].as_ref().unwrap_err().to_string();
        assert!(
            err.contains("`device` cannot be an MQTT topic level"),
            "{err}"
        );
    }

    #[test]
    fn fields_must_belong_to_the_line_type() {
        let (events, _) = read(
            br#"{"t":1,"type":"truth","device":"p","cell":[1,2],"rssi":-70}
{"t":1,"type":"request","device":"p"}
"#,
            false,
        );
        let err = events[0].as_ref().unwrap_err().to_string();
        assert!(
            err.ends_with(":1: unknown field `rssi` in a `truth` line"),
            "{err}"
        );
        let err = events[1].as_ref().unwrap_err().to_string();
        assert!(err.ends_with(":2: missing field `to`"), "{err}");
    }
}
