//! Capture files in any supported format: picking the format, and opening a
//! file as one stream of [`Event`]s (for `replay`) or as a sink of them (for
//! `record`).
//!
//! Formats ([`Format`]): the JSON Lines advert log ([`super::log`]), CSV scan
//! logs ([`super::csvlog`], read only: a live scan has no rows), btsnoop HCI
//! captures ([`super::btsnoop`]) and pcap/pcapng captures ([`super::pcap`],
//! read only: `record` writes btsnoop for Wireshark).
//!
//! Without an explicit format, a file to read that starts with the btsnoop magic
//! is btsnoop whatever its name (Android calls its capture `btsnoop_hci.log`),
//! one that starts with a pcap or pcapng magic number is pcap, a `.pcap` or
//! `.pcapng` file is pcap too (so a damaged one is reported as such), a `.csv`
//! file is a scan log, and anything else is JSON Lines. A file to write is
//! btsnoop when named `*.btsnoop`, `*.snoop` or `*.cfa`, JSON Lines otherwise.

use std::fs::File;
use std::io::{self, BufReader, BufWriter, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::btsnoop::{BtsnoopError, BtsnoopReader, BtsnoopWriter, Datalink, MAGIC};
use super::csvlog::{CsvLog, CsvOptions};
use super::log::{LogError, LogReader, LogWriter};
use super::pcap::{self, PcapError, PcapReader};
use crate::event::Event;
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
    /// A pcap or pcapng capture (Wireshark, tcpdump, nRF Sniffer) of a Bluetooth
    /// LE linktype.
    #[value(alias = "pcapng")]
    Pcap,
}

impl Format {
    /// The format of a file to read, from its first bytes and its name.
    pub(crate) fn detect(path: &Path) -> io::Result<Format> {
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
        if let Some(&first) = magic.first_chunk::<4>()
            && got >= first.len()
            && pcap::is_magic(first)
        {
            return Ok(Format::Pcap);
        }
        Ok(match extension(path).as_deref() {
            Some("csv") => Format::Csv,
            Some("pcap" | "pcapng") => Format::Pcap,
            _ => Format::Jsonl,
        })
    }

    /// The format of a file to write, from its name.
    pub(crate) fn for_output(path: &Path) -> Format {
        match extension(path).as_deref() {
            Some("btsnoop" | "snoop" | "cfa") => Format::Btsnoop,
            Some("csv") => Format::Csv,
            Some("pcap" | "pcapng") => Format::Pcap,
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
    #[error(transparent)]
    Pcap(#[from] PcapError),
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
    /// The observer id of CSV, btsnoop and pcap captures, which do not name one.
    pub device: Option<String>,
    /// The "not heard" RSSI of CSV scan logs.
    pub not_heard: i16,
}

/// Observer id of CSV scan logs when none is given: a survey's walker.
pub(crate) const DEFAULT_CSV_DEVICE: &str = "survey";
/// Observer id of btsnoop and pcap captures when none is given.
pub(crate) const DEFAULT_BTSNOOP_DEVICE: &str = "capture";

/// Any capture, read as events in file order (CSV: time order).
pub enum CaptureReader {
    Jsonl(LogReader<BufReader<File>>),
    Csv(CsvLog),
    Btsnoop(BtsnoopReader<BufReader<File>>),
    Pcap(PcapReader<BufReader<File>>),
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
            Format::Pcap => CaptureReader::Pcap(PcapReader::open(
                path,
                device(DEFAULT_BTSNOOP_DEVICE),
                options.skip_bad,
            )?),
        })
    }

    pub(crate) fn format(&self) -> Format {
        match self {
            CaptureReader::Jsonl(_) => Format::Jsonl,
            CaptureReader::Csv(_) => Format::Csv,
            CaptureReader::Btsnoop(_) => Format::Btsnoop,
            CaptureReader::Pcap(_) => Format::Pcap,
        }
    }

    /// What was skipped so far, by reason, as `reason=count` pairs.
    pub(crate) fn skipped(&self) -> String {
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
            CaptureReader::Pcap(r) => r
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
            CaptureReader::Pcap(r) => r.next().map(|s| s.map(Event::Advert).map_err(Into::into)),
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
            Format::Pcap => {
                return Err(error(
                    "cannot record pcap: gangway writes captures as btsnoop, which Wireshark \
                     opens too; name the file .btsnoop or pass --format btsnoop"
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::event::Truth;
    use crate::sighting::{BeaconId, Sighting};
    use crate::site::Cell;

    fn site() -> Site {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n##\n'''\n";
        Site::parse(text, Path::new("t.toml")).unwrap()
    }

    fn options(format: Option<Format>, device: Option<&str>) -> ReadOptions {
        ReadOptions {
            format,
            skip_bad: false,
            device: device.map(str::to_owned),
            not_heard: -200,
        }
    }

    fn advert(t: f64, observer: &str) -> Event {
        Event::Advert(Sighting {
            t,
            observer: observer.into(),
            advertiser: BeaconId {
                uuid: uuid::Uuid::from_u128(0x5e1a6f3c_2b1d_4c8e_9a70_3d2f1c0b9e84),
                major: 1,
                minor: 3001,
            },
            tx_power: Some(-59),
            rssi: -71,
        })
    }

    #[test]
    fn formats_come_from_magic_bytes_then_the_name() {
        let dir = tempfile::tempdir().unwrap();
        let android = dir.path().join("btsnoop_hci.log");
        BtsnoopWriter::create(&android, Datalink::H4)
            .unwrap()
            .flush()
            .unwrap();
        assert_eq!(Format::detect(&android).unwrap(), Format::Btsnoop);
        let csv = dir.path().join("scan.CSV");
        std::fs::write(&csv, "t,b1\n").unwrap();
        assert_eq!(Format::detect(&csv).unwrap(), Format::Csv);
        let jsonl = dir.path().join("walk.log");
        std::fs::write(&jsonl, "").unwrap();
        assert_eq!(Format::detect(&jsonl).unwrap(), Format::Jsonl);
        assert!(Format::detect(&dir.path().join("absent")).is_err());
        // pcap and pcapng by their magic numbers whatever the name, and by name.
        for magic in [
            [0x0A, 0x0D, 0x0D, 0x0A],
            [0xD4, 0xC3, 0xB2, 0xA1],
            [0xA1, 0xB2, 0x3C, 0x4D],
        ] {
            let sniffed = dir.path().join("sniffer.log");
            std::fs::write(&sniffed, magic).unwrap();
            assert_eq!(
                Format::detect(&sniffed).unwrap(),
                Format::Pcap,
                "{magic:x?}"
            );
        }
        let damaged = dir.path().join("walk.PCAPNG");
        std::fs::write(&damaged, "{}").unwrap();
        assert_eq!(Format::detect(&damaged).unwrap(), Format::Pcap);

        assert_eq!(Format::for_output(Path::new("a.btsnoop")), Format::Btsnoop);
        assert_eq!(Format::for_output(Path::new("a.jsonl")), Format::Jsonl);
        assert_eq!(Format::for_output(Path::new("a")), Format::Jsonl);
        assert_eq!(Format::for_output(Path::new("a.pcapng")), Format::Pcap);
    }

    #[test]
    fn a_recorded_btsnoop_capture_replays_to_the_same_adverts() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("rec.btsnoop");
        let events = vec![advert(10.0, "gw-1"), advert(10.5, "gw-1")];
        let mut writer = CaptureWriter::create(&path, None).unwrap();
        for e in &events {
            writer.write(e).unwrap();
        }
        writer.flush().unwrap();
        drop(writer);
        let reader = CaptureReader::open(&path, &site(), &options(None, Some("gw-1"))).unwrap();
        assert_eq!(reader.format(), Format::Btsnoop);
        let back: Vec<Event> = reader.map(Result::unwrap).collect();
        assert_eq!(back, events);

        let reader = CaptureReader::open(&path, &site(), &options(None, None)).unwrap();
        let observers: Vec<_> = reader
            .map(|e| match e.unwrap() {
                Event::Advert(s) => s.observer.to_string(),
                _ => unreachable!("btsnoop holds adverts only"),
            })
            .collect();
        assert_eq!(observers, [DEFAULT_BTSNOOP_DEVICE; 2]);
    }

    #[test]
    fn writers_refuse_what_their_format_cannot_hold() {
        let dir = tempfile::tempdir().unwrap();
        let err = CaptureWriter::create(&dir.path().join("x.csv"), None)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("cannot record CSV"), "{err}");
        let err = CaptureWriter::create(&dir.path().join("x.pcapng"), None)
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("cannot record pcap"), "{err}");
        let mut w =
            CaptureWriter::create(&dir.path().join("x.bin"), Some(Format::Btsnoop)).unwrap();
        let truth = Event::Truth(Truth {
            t: 1.0,
            device: "d".into(),
            cell: Cell::new(0, 0),
        });
        assert!(w.write(&truth).is_err());
    }

    #[test]
    fn an_explicit_format_wins_over_detection() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("scan.txt");
        std::fs::write(&path, "t,b1\n1,-70\n").unwrap();
        let err = CaptureReader::open(&path, &site(), &options(Some(Format::Btsnoop), None))
            .err()
            .unwrap()
            .to_string();
        assert!(err.contains("not a btsnoop capture"), "{err}");
    }
}
