//! Capture files in any supported format: picking the format, and opening a
//! file as one stream of [`Event`]s (for `replay`) or as a sink of them (for
//! `record`).
//!
//! Formats ([`Format`]): the JSON Lines advert log ([`super::log`]), CSV scan
//! logs ([`super::csvlog`], read only: a live scan has no rows) and btsnoop HCI
//! captures ([`super::btsnoop`]).
//!
//! Without an explicit format, a file to read that starts with the btsnoop magic
//! is btsnoop whatever its name (Android calls its capture `btsnoop_hci.log`), a
//! `.csv` file is a scan log, and anything else is JSON Lines. A file to write
//! is btsnoop when named `*.btsnoop`, `*.snoop` or `*.cfa`, JSON Lines otherwise.

use std::fs::File;
use std::io::{self, BufReader, BufWriter, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::Event;
use super::btsnoop::{BtsnoopError, BtsnoopReader, BtsnoopWriter, Datalink, MAGIC};
use super::csvlog::{CsvLog, CsvOptions};
use super::log::{LogError, LogReader, LogWriter};
use crate::locate::survey::SurveyError;
use crate::site::Site;

/// A capture file format.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Format {
    /// The advert log: one JSON event per line.
    Jsonl,
    /// A scan log: one row per scan, one RSSI column per beacon.
    Csv,
    /// An HCI capture as written by `btmon -w` or Android's HCI snoop log.
    Btsnoop,
}

impl Format {
    /// The format of a file to read, from its first bytes and its name.
    pub fn detect(path: &Path) -> io::Result<Format> {
        let mut magic = [0u8; MAGIC.len()];
        let mut file = File::open(path)?;
        let mut got = 0;
        while got < magic.len() {
            match file.read(&mut magic[got..])? {
                0 => break,
                n => got += n,
            }
        }
        if got == magic.len() && magic == MAGIC {
            return Ok(Format::Btsnoop);
        }
        Ok(match extension(path).as_deref() {
            Some("csv") => Format::Csv,
            _ => Format::Jsonl,
        })
    }

    /// The format of a file to write, from its name.
    pub fn for_output(path: &Path) -> Format {
        match extension(path).as_deref() {
            Some("btsnoop" | "snoop" | "cfa") => Format::Btsnoop,
            Some("csv") => Format::Csv,
            _ => Format::Jsonl,
        }
    }
}

fn extension(path: &Path) -> Option<String> {
    path.extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase)
}

/// Why a capture could not be read or created.
#[derive(Debug, thiserror::Error)]
pub enum CaptureError {
    #[error(transparent)]
    Log(#[from] LogError),
    #[error(transparent)]
    Csv(#[from] SurveyError),
    #[error(transparent)]
    Btsnoop(#[from] BtsnoopError),
    #[error("{}: {reason}", path.display())]
    Other { path: PathBuf, reason: String },
}

/// How to read a capture.
#[derive(Clone, Debug)]
pub struct ReadOptions {
    /// The format; detected from the file when `None`.
    pub format: Option<Format>,
    /// Skip and count bad lines, rows and truncated records instead of stopping.
    pub skip_bad: bool,
    /// The observer id of CSV and btsnoop captures, which do not name one.
    pub device: Option<String>,
    /// The "not heard" RSSI of CSV scan logs.
    pub not_heard: i16,
}

/// Observer id of CSV scan logs when none is given: a survey's walker.
pub const DEFAULT_CSV_DEVICE: &str = "survey";
/// Observer id of btsnoop captures when none is given.
pub const DEFAULT_BTSNOOP_DEVICE: &str = "capture";

/// Any capture, read as events in file order (CSV: time order).
pub enum CaptureReader {
    Jsonl(LogReader<BufReader<File>>),
    Csv(CsvLog),
    Btsnoop(BtsnoopReader<BufReader<File>>),
}

impl CaptureReader {
    /// Opens `path`; `site` matches CSV columns to beacons.
    pub fn open(
        path: &Path,
        site: &Site,
        options: &ReadOptions,
    ) -> Result<CaptureReader, CaptureError> {
        let format = match options.format {
            Some(format) => format,
            None => Format::detect(path).map_err(|e| CaptureError::Other {
                path: path.to_owned(),
                reason: format!("cannot open the capture: {e}"),
            })?,
        };
        let device =
            |default: &str| -> Arc<str> { options.device.as_deref().unwrap_or(default).into() };
        Ok(match format {
            Format::Jsonl => CaptureReader::Jsonl(LogReader::open(path, options.skip_bad)?),
            Format::Csv => CaptureReader::Csv(CsvLog::open(
                path,
                site,
                &CsvOptions {
                    device: device(DEFAULT_CSV_DEVICE),
                    not_heard: options.not_heard,
                    skip_bad: options.skip_bad,
                },
            )?),
            Format::Btsnoop => CaptureReader::Btsnoop(BtsnoopReader::open(
                path,
                device(DEFAULT_BTSNOOP_DEVICE),
                options.skip_bad,
            )?),
        })
    }

    pub fn format(&self) -> Format {
        match self {
            CaptureReader::Jsonl(_) => Format::Jsonl,
            CaptureReader::Csv(_) => Format::Csv,
            CaptureReader::Btsnoop(_) => Format::Btsnoop,
        }
    }

    /// What was skipped so far, by reason, as `reason=count` pairs.
    pub fn skipped(&self) -> String {
        let counts: Vec<(String, u64)> = match self {
            CaptureReader::Jsonl(r) => vec![("bad_lines".into(), r.skipped())],
            CaptureReader::Csv(r) => vec![
                ("bad_rows".into(), r.skipped_rows()),
                ("ignored_columns".into(), r.ignored_columns().len() as u64),
            ],
            CaptureReader::Btsnoop(r) => r
                .skipped()
                .map(|(reason, n)| (reason.to_string(), n))
                .collect(),
        };
        counts
            .iter()
            .filter(|(_, n)| *n > 0)
            .map(|(reason, n)| format!("{reason}={n}"))
            .collect::<Vec<_>>()
            .join(" ")
    }
}

impl Iterator for CaptureReader {
    type Item = Result<Event, CaptureError>;

    fn next(&mut self) -> Option<Self::Item> {
        match self {
            CaptureReader::Jsonl(r) => r.next().map(|e| e.map_err(Into::into)),
            CaptureReader::Csv(r) => r.next().map(Ok),
            CaptureReader::Btsnoop(r) => r.next().map(|s| s.map(Event::Advert).map_err(Into::into)),
        }
    }
}

/// Any capture being written.
pub enum CaptureWriter {
    Jsonl(LogWriter<BufWriter<File>>),
    Btsnoop(BtsnoopWriter<BufWriter<File>>),
}

impl CaptureWriter {
    /// Creates `path` in `format` (from its name when `None`). CSV is refused:
    /// adverts heard live do not come in rows of one scan.
    pub fn create(path: &Path, format: Option<Format>) -> Result<CaptureWriter, CaptureError> {
        let error = |reason: String| CaptureError::Other {
            path: path.to_owned(),
            reason,
        };
        let created = match format.unwrap_or_else(|| Format::for_output(path)) {
            Format::Jsonl => LogWriter::create(path).map(CaptureWriter::Jsonl),
            Format::Btsnoop => {
                BtsnoopWriter::create(path, Datalink::Monitor).map(CaptureWriter::Btsnoop)
            }
            Format::Csv => {
                return Err(error(
                    "cannot record CSV: live adverts arrive one at a time, not in rows of one \
                     scan; record jsonl or btsnoop"
                        .into(),
                ));
            }
        };
        created.map_err(|e| error(format!("cannot create the capture: {e}")))
    }

    /// Writes one event; btsnoop holds adverts only.
    pub fn write(&mut self, event: &Event) -> io::Result<()> {
        match (self, event) {
            (CaptureWriter::Jsonl(w), _) => w.write(event),
            (CaptureWriter::Btsnoop(w), Event::Advert(s)) => w.write(s),
            (CaptureWriter::Btsnoop(_), _) => Err(io::Error::new(
                io::ErrorKind::InvalidInput,
                "a btsnoop capture holds adverts only, not requests or truth",
            )),
        }
    }

    pub fn flush(&mut self) -> io::Result<()> {
        match self {
            CaptureWriter::Jsonl(w) => w.flush(),
            CaptureWriter::Btsnoop(w) => w.flush(),
        }
    }
}
