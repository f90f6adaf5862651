//! Capture files in any supported format: picking the format, and opening a
//! file as one stream of [`Event`]s (for `replay`) or as a sink of them (for
//! `record`).
//!
//! Formats ([`Format`]): the JSON Lines advert log ([`super::log`]), CSV scan
//! logs ([`super::csvlog`], read only: a live scan has no rows), btsnoop HCI
//! captures ([`super::btsnoop`]) and pcap/pcapng captures ([`super::pcap`],
//! read only: `record` writes btsnoop for Wireshark).
//!
//! Without an explicit format, a file to read is known by its content, then
//! its name: one that starts with the btsnoop magic is btsnoop whatever its
//! name (Android calls its capture `btsnoop_hci.log`), one that starts with
//! a pcap or pcapng magic number is pcap; a file named `.pcap`, `.pcapng`,
//! `.btsnoop`, `.snoop` or `.cfa` is that format anyway (so a damaged one is
//! reported as such); text whose first line is a JSON object is JSON Lines,
//! text whose first line has commas (a header) is a CSV scan log. Anything
//! else (another binary format, other text) is refused with what it looks
//! like, instead of being read line by line as JSON; an empty file holds no
//! events (`replay` refuses it, `run --replay /dev/null` runs without radio). A file to
//! write is btsnoop when named `*.btsnoop`, `*.snoop` or `*.cfa`, JSON Lines
//! otherwise.

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
use crate::site::Building;

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
    /// The format of a file to read, from its first bytes, then its name;
    /// the error says what the file looks like instead.
    pub(crate) fn detect(path: &Path) -> Result<Format, String> {
        let mut head = Vec::with_capacity(SNIFF_BYTES);
        File::open(path)
            .and_then(|file| file.take(SNIFF_BYTES as u64).read_to_end(&mut head))
            .map_err(|e| format!("cannot open the capture: {e}"))?;
        // Nothing to read is no format's fault (`run --replay /dev/null`
        // runs the daemon without a radio); `replay` refuses it itself.
        if head.is_empty() {
            return Ok(Format::Jsonl);
        }
        if head.starts_with(&MAGIC) {
            return Ok(Format::Btsnoop);
        }
        if let Some(&first) = head.first_chunk::<4>()
            && pcap::is_magic(first)
        {
            return Ok(Format::Pcap);
        }
        match extension(path).as_deref() {
            Some("pcap" | "pcapng") => return Ok(Format::Pcap),
            Some("btsnoop" | "snoop" | "cfa") => return Ok(Format::Btsnoop),
            _ => {}
        }
        let text = match std::str::from_utf8(&head) {
            Ok(text) => text,
            // Cut in the middle of a character by the sniff's length.
            Err(e) if e.error_len().is_none() => {
                std::str::from_utf8(&head[..e.valid_up_to()]).expect("valid up to here")
            }
            Err(_) => return Err(binary(&head)),
        };
        if text.contains('\0') {
            return Err(binary(&head));
        }
        let first = text
            .trim_start_matches('\u{feff}')
            .lines()
            .map(str::trim)
            .find(|line| !line.is_empty())
            .unwrap_or("");
        if first.starts_with('{') {
            Ok(Format::Jsonl)
        } else if first.contains(',') || extension(path).as_deref() == Some("csv") {
            Ok(Format::Csv)
        } else if first.is_empty() {
            Err("the capture holds only blank lines: nothing to replay".into())
        } else {
            Err(format!(
                "text that is neither JSON Lines (each line one JSON object, `{{…}}`) nor a CSV \
                 scan log (a header row of comma-separated column names); its first line is \
                 {:?}",
                first.chars().take(80).collect::<String>()
            ))
        }
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

/// How much of a file detection reads: enough for a first line of text.
const SNIFF_BYTES: usize = 4096;

/// Why a binary file that is no capture was refused, naming what it looks
/// like where its magic number says (the `infer` crate knows ~200 formats).
fn binary(head: &[u8]) -> String {
    let looks_like = match infer::get(head) {
        Some(kind) if kind.matcher_type() == infer::MatcherType::Archive => format!(
            "{} data ({}), an archive or compressed file: unpack the capture from it first",
            kind.extension(),
            kind.mime_type()
        ),
        Some(kind) => format!("{} data ({})", kind.extension(), kind.mime_type()),
        None => {
            let bytes: Vec<String> = head.iter().take(8).map(|b| format!("{b:02x}")).collect();
            format!("binary data starting {}", bytes.join(" "))
        }
    };
    format!(
        "not a capture gangway reads: {looks_like}; it reads JSON Lines advert logs, CSV scan \
         logs, btsnoop (btmon -w, Android's btsnoop_hci.log), pcap and pcapng"
    )
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
    /// Opens `path`; `building`'s floors match CSV columns to beacons.
    pub fn open(
        path: &Path,
        building: &Building,
        options: &ReadOptions,
    ) -> Result<CaptureReader, CaptureError> {
        let format = match options.format {
            Some(format) => format,
            None => Format::detect(path).map_err(|reason| CaptureError::Other {
                path: path.to_owned(),
                reason,
            })?,
        };
        let device =
            |default: &str| -> Arc<str> { options.device.as_deref().unwrap_or(default).into() };
        Ok(match format {
            Format::Jsonl => CaptureReader::Jsonl(LogReader::open(path, options.skip_bad)?),
            Format::Csv => CaptureReader::Csv(CsvLog::open(
                path,
                building,
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
    use crate::site::{Cell, Site};

    fn site() -> Building {
        let text = "name = \"t\"\ncell_m = 1.0\nmap = '''\n##\n'''\n";
        Building::of_site(Arc::new(Site::parse(text, Path::new("t.toml")).unwrap()))
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
            advertiser_mac: None,
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
        std::fs::write(&jsonl, "\n{\"t\": 1}\n").unwrap();
        assert_eq!(Format::detect(&jsonl).unwrap(), Format::Jsonl);
        let named_csv_but_jsonl = dir.path().join("walk.csv");
        std::fs::write(&named_csv_but_jsonl, "{\"t\": 1}\n").unwrap();
        assert_eq!(
            Format::detect(&named_csv_but_jsonl).unwrap(),
            Format::Jsonl,
            "content wins"
        );
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
    }

    #[test]
    fn what_is_no_capture_is_refused_saying_what_it_looks_like() {
        let dir = tempfile::tempdir().unwrap();
        let refused = |name: &str, bytes: &[u8]| {
            let path = dir.path().join(name);
            std::fs::write(&path, bytes).unwrap();
            Format::detect(&path).unwrap_err()
        };
        assert!(refused("walk.jsonl", b"\n  \n").contains("only blank lines"));
        let gzip = refused("walk.jsonl", &[0x1f, 0x8b, 0x08, 0, 0, 0, 0, 0, 0, 3]);
        assert!(
            gzip.contains("gz data (application/gzip)") && gzip.contains("unpack"),
            "{gzip}"
        );
        let png = refused("plan.log", b"\x89PNG\r\n\x1a\n\0\0\0\rIHDR");
        assert!(png.contains("png data (image/png)"), "{png}");
        let random = refused(
            "random.bin",
            &[0x00, 0xff, 0x13, 0x37, 0xfe, 0x00, 0x01, 0x02, 0x03],
        );
        assert!(
            random.contains("binary data starting 00 ff 13 37"),
            "{random}"
        );
        assert!(random.contains("JSON Lines advert logs"), "{random}");
        let prose = refused("notes.txt", b"These are my notes\nabout beacons\n");
        assert!(prose.contains("\"These are my notes\""), "{prose}");
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
            floor: None,
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
