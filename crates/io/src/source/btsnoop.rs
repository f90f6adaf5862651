//! btsnoop captures: iBeacon sightings read from, and written to, HCI traces as
//! `btmon -w` (Linux) and Android's "Bluetooth HCI snoop log" write them.
//!
//! File layout (all integers big-endian; RFC 1761 "snoop" with Bluetooth
//! datalinks):
//!
//! ```text
//! header:  "btsnoop\0" | version u32 = 1 | datalink u32
//! record:  original length u32 | included length u32 | flags u32 | drops u32 |
//!          timestamp i64 (µs since 0000-01-01) | included-length bytes of packet
//! ```
//!
//! Datalinks read: 1001 (HCI without framing: flags bit 1 marks commands and
//! events, bit 0 the direction), 1002 (H4/HCI-UART: the packet starts with the H4
//! type byte, 0x04 for an event; Android writes this) and 2001 (the Linux monitor
//! format btmon writes: flags = adapter index << 16 | opcode, opcode 3 for an
//! event). From HCI events only LE Meta (0x3E) subevents LE Advertising Report
//! (0x02) and LE Extended Advertising Report (0x0D) are used: each report's AD
//! structures are searched for manufacturer-specific data (type 0xFF) holding an
//! iBeacon frame ([`ibeacon::find_in_ad`]), which becomes a sighting with the
//! record's timestamp and the report's RSSI ([`super::adverts`], shared with
//! the pcap reader). Everything else (commands, ACL, other events, other
//! adverts) is skipped and counted by [`SkipReason`]; a malformed packet never
//! stops the reader. Only a broken record frame (a truncated last record, an
//! impossible length) ends the file, with an error naming the record number
//! and byte offset.
//!
//! Hand-written rather than built on a crate: the btsnoop crates on crates.io
//! (`btsnoop`, `btsnoop_parser`) parse a whole file held in memory and fail it
//! as a whole on a truncated record, neither writes files nor decodes LE
//! advertising reports, and `btsnoop_parser` pulls in JNI. The framing is two
//! fixed-size headers, so a streaming reader is shorter than the glue would be.
//!
//! The writer emits what `gangway record --format btsnoop` hears as synthesized
//! LE Advertising Report events, so a capture opens in Wireshark and btmon and
//! reads back to the same sightings (timestamps to the microsecond).

use std::fs::File;
use std::io::{self, BufReader, BufWriter, Read, Write};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::adverts::{
    Adverts, HCI_EVENT_LE_META, LE_ADVERTISING_REPORT, RSSI_UNAVAILABLE, SkipReason,
};
use super::ibeacon::{self, AD_MANUFACTURER_SPECIFIC, IBeacon};
use crate::sighting::{BeaconId, Sighting};

/// The first eight bytes of every btsnoop file.
pub const MAGIC: [u8; 8] = *b"btsnoop\0";
const VERSION: u32 = 1;
const FILE_HEADER_LEN: usize = 16;
const RECORD_HEADER_LEN: usize = 24;
/// btsnoop timestamps count microseconds from 0000-01-01; this is 1970-01-01.
const UNIX_EPOCH_US: i64 = 0x00dc_ddb3_0f2f_8000;
/// Larger than any HCI packet or monitor frame (ACL payloads stop at 64 KiB): a
/// longer record means the framing is corrupt, and reading it would only waste
/// memory.
const MAX_RECORD_LEN: u32 = 1 << 20;

/// The H4 packet type byte of an HCI event.
pub(super) const H4_EVENT: u8 = 0x04;
const MONITOR_NEW_INDEX: u16 = 0;
const MONITOR_EVENT_PKT: u16 = 3;
/// Flags of an H1/H4 record: bit 0 = received (controller → host), bit 1 =
/// command or event rather than data.
const FLAGS_RECEIVED_EVENT: u32 = 0b11;

/// How packets are framed in the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Datalink {
    /// 1001: HCI packets without framing.
    H1,
    /// 1002: H4 / HCI-UART (Android's HCI snoop log).
    H4,
    /// 2001: the Linux monitor format (`btmon -w`).
    Monitor,
}

impl Datalink {
    fn code(self) -> u32 {
        match self {
            Datalink::H1 => 1001,
            Datalink::H4 => 1002,
            Datalink::Monitor => 2001,
        }
    }

    fn from_code(code: u32) -> Option<Datalink> {
        match code {
            1001 => Some(Datalink::H1),
            1002 => Some(Datalink::H4),
            2001 => Some(Datalink::Monitor),
            _ => None,
        }
    }

    /// The HCI event in a record of this datalink, if it holds one.
    fn event(self, flags: u32, packet: &[u8]) -> Option<&[u8]> {
        match self {
            Datalink::H1 => {
                (flags & FLAGS_RECEIVED_EVENT == FLAGS_RECEIVED_EVENT).then_some(packet)
            }
            Datalink::H4 => match packet.split_first() {
                Some((&H4_EVENT, event)) => Some(event),
                _ => None,
            },
            Datalink::Monitor => ((flags & 0xFFFF) as u16 == MONITOR_EVENT_PKT).then_some(packet),
        }
    }
}

#[derive(Debug, thiserror::Error)]
pub enum BtsnoopError {
    #[error("{path}: cannot read the capture: {source}")]
    Io { path: PathBuf, source: io::Error },
    #[error("{path}: not a btsnoop capture: {reason}")]
    Header { path: PathBuf, reason: String },
    #[error(
        "{path}: record {record} at byte {offset} is truncated ({have} of {need} bytes); \
         the capture was cut off. Replay with --skip-bad to use the records before it"
    )]
    Truncated {
        path: PathBuf,
        record: u64,
        offset: u64,
        have: usize,
        need: usize,
    },
    #[error(
        "{path}: record {record} at byte {offset} claims {length} bytes, more than any HCI \
         packet; the file is corrupt from here on"
    )]
    Corrupt {
        path: PathBuf,
        record: u64,
        offset: u64,
        length: u32,
    },
}

/// Streams iBeacon sightings from a btsnoop capture, one record in memory at a
/// time.
pub struct BtsnoopReader<R> {
    input: R,
    path: PathBuf,
    datalink: Datalink,
    skip_bad: bool,
    /// Records read so far; the current record's number.
    record: u64,
    /// Byte offset of the next record.
    offset: u64,
    packet: Vec<u8>,
    /// Sightings not yet returned (a report event can carry several reports),
    /// and the skip counts.
    adverts: Adverts,
    done: bool,
}

impl BtsnoopReader<BufReader<File>> {
    /// Opens a capture; every sighting is attributed to `observer`, since a
    /// capture does not name the host that made it.
    pub(crate) fn open(
        path: &Path,
        observer: Arc<str>,
        skip_bad: bool,
    ) -> Result<Self, BtsnoopError> {
        let file = File::open(path).map_err(|source| BtsnoopError::Io {
            path: path.to_owned(),
            source,
        })?;
        BtsnoopReader::new(
            BufReader::with_capacity(1 << 16, file),
            path,
            observer,
            skip_bad,
        )
    }
}

impl<R: Read> BtsnoopReader<R> {
    /// Reads the file header from `input`; `path` names it in errors.
    pub fn new(
        mut input: R,
        path: &Path,
        observer: Arc<str>,
        skip_bad: bool,
    ) -> Result<Self, BtsnoopError> {
        let header_error = |reason: String| BtsnoopError::Header {
            path: path.to_owned(),
            reason,
        };
        let mut header = [0u8; FILE_HEADER_LEN];
        let got = read_full(&mut input, &mut header).map_err(|source| BtsnoopError::Io {
            path: path.to_owned(),
            source,
        })?;
        if got < FILE_HEADER_LEN || header[..8] != MAGIC {
            return Err(header_error(
                "it does not start with \"btsnoop\\0\"; capture with `btmon -w FILE` or take \
                 btsnoop_hci.log from an Android bug report"
                    .into(),
            ));
        }
        let version = be32(&header[8..12]);
        if version != VERSION {
            return Err(header_error(format!(
                "version {version}, only version 1 exists"
            )));
        }
        let code = be32(&header[12..16]);
        let datalink = Datalink::from_code(code).ok_or_else(|| {
            header_error(format!(
                "datalink {code} is not supported; gangway reads 1001 (HCI), 1002 (H4, \
                 Android) and 2001 (Linux monitor, btmon)"
            ))
        })?;
        Ok(BtsnoopReader {
            input,
            path: path.to_owned(),
            datalink,
            skip_bad,
            record: 0,
            offset: FILE_HEADER_LEN as u64,
            packet: Vec::new(),
            adverts: Adverts::new(observer),
            done: false,
        })
    }

    /// How many records or reports were skipped, by reason (zero counts left out).
    pub(crate) fn skipped(&self) -> impl Iterator<Item = (SkipReason, u64)> + '_ {
        self.adverts.skipped().iter()
    }

    /// Reads the next record into `self.packet`; `Ok(None)` at a clean end.
    fn read_record(&mut self) -> Result<Option<(u32, i64)>, BtsnoopError> {
        let offset = self.offset;
        let record = self.record + 1;
        let io_error = |source| BtsnoopError::Io {
            path: self.path.clone(),
            source,
        };
        let mut header = [0u8; RECORD_HEADER_LEN];
        let got = read_full(&mut self.input, &mut header).map_err(io_error)?;
        if got == 0 {
            return Ok(None);
        }
        self.record = record;
        let truncated = |have, need| BtsnoopError::Truncated {
            path: self.path.clone(),
            record,
            offset,
            have,
            need,
        };
        if got < RECORD_HEADER_LEN {
            return Err(truncated(got, RECORD_HEADER_LEN));
        }
        let included = be32(&header[4..8]);
        let flags = be32(&header[8..12]);
        let timestamp = i64::from_be_bytes(header[16..24].try_into().expect("8 bytes"));
        if included > MAX_RECORD_LEN {
            return Err(BtsnoopError::Corrupt {
                path: self.path.clone(),
                record,
                offset,
                length: included,
            });
        }
        self.packet.resize(included as usize, 0);
        let got =
            read_full(&mut self.input, &mut self.packet).map_err(|source| BtsnoopError::Io {
                path: self.path.clone(),
                source,
            })?;
        if got < self.packet.len() {
            return Err(truncated(
                RECORD_HEADER_LEN + got,
                RECORD_HEADER_LEN + self.packet.len(),
            ));
        }
        self.offset = offset + (RECORD_HEADER_LEN + self.packet.len()) as u64;
        Ok(Some((flags, timestamp)))
    }

    /// Turns the record in `self.packet` into pending sightings, counting what
    /// it skips.
    fn decode(&mut self, flags: u32, timestamp: i64) {
        let Some(event) = self.datalink.event(flags, &self.packet) else {
            return self.adverts.skip(SkipReason::NotAnEvent);
        };
        let t = timestamp.saturating_sub(UNIX_EPOCH_US) as f64 / 1e6;
        self.adverts.hci_event(t, event);
    }
}

impl<R: Read> Iterator for BtsnoopReader<R> {
    type Item = Result<Sighting, BtsnoopError>;

    fn next(&mut self) -> Option<Self::Item> {
        loop {
            if let Some(sighting) = self.adverts.pop() {
                return Some(Ok(sighting));
            }
            if self.done {
                return None;
            }
            match self.read_record() {
                Ok(Some((flags, timestamp))) => self.decode(flags, timestamp),
                Ok(None) => self.done = true,
                Err(e) => {
                    // The framing cannot be trusted past a broken record.
                    self.done = true;
                    if self.skip_bad && matches!(e, BtsnoopError::Truncated { .. }) {
                        self.adverts.skip(SkipReason::TruncatedRecord);
                        tracing::warn!("{e}");
                    } else {
                        return Some(Err(e));
                    }
                }
            }
        }
    }
}

/// Writes sightings as a btsnoop capture of synthesized LE Advertising Report
/// events, one record per sighting.
pub struct BtsnoopWriter<W: Write> {
    out: W,
    datalink: Datalink,
    /// Whether the monitor "new index" record that names the adapter is written.
    announced: bool,
}

impl BtsnoopWriter<BufWriter<File>> {
    pub fn create(path: &Path, datalink: Datalink) -> io::Result<Self> {
        BtsnoopWriter::new(BufWriter::new(File::create(path)?), datalink)
    }
}

impl<W: Write> BtsnoopWriter<W> {
    /// Writes the file header.
    pub(crate) fn new(mut out: W, datalink: Datalink) -> io::Result<Self> {
        out.write_all(&MAGIC)?;
        out.write_all(&VERSION.to_be_bytes())?;
        out.write_all(&datalink.code().to_be_bytes())?;
        Ok(BtsnoopWriter {
            out,
            datalink,
            announced: datalink != Datalink::Monitor,
        })
    }

    /// Writes one sighting. Its observer is not stored (a capture is what one
    /// adapter heard), and the advertiser address is synthesized from the
    /// beacon's identity, since a sighting does not keep the radio address.
    pub fn write(&mut self, sighting: &Sighting) -> io::Result<()> {
        let tx_power = sighting.tx_power.ok_or_else(|| {
            io::Error::new(
                io::ErrorKind::InvalidInput,
                "a btsnoop capture stores the iBeacon frame, which needs the beacon's tx power",
            )
        })?;
        let rssi = i8::try_from(sighting.rssi)
            .ok()
            .filter(|&r| r != RSSI_UNAVAILABLE)
            .ok_or_else(|| {
                io::Error::new(
                    io::ErrorKind::InvalidInput,
                    format!("RSSI {} dBm does not fit an HCI report", sighting.rssi),
                )
            })?;
        let frame = ibeacon::encode_manufacturer_data(&IBeacon {
            id: sighting.advertiser,
            measured_power: tx_power,
        });
        // Flags (LE General Discoverable, BR/EDR not supported), as beacons send.
        let mut ad = vec![
            0x02,
            0x01,
            0x06,
            (frame.len() + 1) as u8,
            AD_MANUFACTURER_SPECIFIC,
        ];
        ad.extend_from_slice(&frame);
        let mut params = vec![
            LE_ADVERTISING_REPORT,
            1,
            0x03, /* ADV_NONCONN_IND */
            0x01, /* random */
        ];
        params.extend_from_slice(&address(&sighting.advertiser));
        params.push(ad.len() as u8);
        params.extend_from_slice(&ad);
        params.push(rssi as u8);
        let mut packet = Vec::with_capacity(3 + params.len());
        if self.datalink == Datalink::H4 {
            packet.push(H4_EVENT);
        }
        packet.push(HCI_EVENT_LE_META);
        packet.push(params.len() as u8);
        packet.extend_from_slice(&params);
        let flags = match self.datalink {
            Datalink::H1 | Datalink::H4 => FLAGS_RECEIVED_EVENT,
            Datalink::Monitor => u32::from(MONITOR_EVENT_PKT),
        };
        let timestamp = UNIX_EPOCH_US.saturating_add((sighting.t * 1e6).round() as i64);
        if !self.announced {
            // The "new index" record btmon starts with, so tools name the
            // adapter; stamped with the first sighting's time, not 1970.
            // type 0 (primary controller), bus 0 (virtual), address, name[8]
            let mut new_index = [0u8; 16];
            new_index[8..15].copy_from_slice(b"gangway");
            self.record(u32::from(MONITOR_NEW_INDEX), timestamp, &new_index)?;
            self.announced = true;
        }
        self.record(flags, timestamp, &packet)
    }

    fn record(&mut self, flags: u32, timestamp: i64, packet: &[u8]) -> io::Result<()> {
        let len = (packet.len() as u32).to_be_bytes();
        self.out.write_all(&len)?;
        self.out.write_all(&len)?;
        self.out.write_all(&flags.to_be_bytes())?;
        self.out.write_all(&0u32.to_be_bytes())?;
        self.out.write_all(&timestamp.to_be_bytes())?;
        self.out.write_all(packet)
    }

    pub fn flush(&mut self) -> io::Result<()> {
        self.out.flush()
    }
}

/// A static random address (top two bits set) made from a beacon's identity:
/// stable per beacon, so Wireshark groups each beacon's adverts. Little-endian,
/// as HCI sends addresses.
fn address(id: &BeaconId) -> [u8; 6] {
    let [minor_hi, minor_lo] = id.minor.to_be_bytes();
    let [major_hi, major_lo] = id.major.to_be_bytes();
    let uuid = id.uuid.as_bytes();
    [
        minor_lo,
        minor_hi,
        major_lo,
        major_hi,
        uuid[15],
        uuid[14] | 0xC0,
    ]
}

fn be32(bytes: &[u8]) -> u32 {
    u32::from_be_bytes(bytes[..4].try_into().expect("4 bytes"))
}

/// Reads until `buf` is full or the input ends; returns how much was read.
pub(super) fn read_full(input: &mut impl Read, buf: &mut [u8]) -> io::Result<usize> {
    let mut got = 0;
    while got < buf.len() {
        match input.read(&mut buf[got..]) {
            Ok(0) => break,
            Ok(n) => got += n,
            Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
            Err(e) => return Err(e),
        }
    }
    Ok(got)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;
    use uuid::Uuid;

    impl<R> BtsnoopReader<R> {
        fn datalink(&self) -> Datalink {
            self.datalink
        }
    }

    const T0_US: i64 = 1_700_000_000_250_000; // 2023-11-14 22:13:20.25 UTC

    /// The manufacturer-specific AD structure of a real iBeacon advert: UUID
    /// B9407F30-F5F8-466E-AFF9-25556B57FE6D, major 1, minor 3001, -59 dBm at 1 m.
    const IBEACON_AD: [u8; 27] = [
        0x1A, 0xFF, 0x4C, 0x00, 0x02, 0x15, 0xB9, 0x40, 0x7F, 0x30, 0xF5, 0xF8, 0x46, 0x6E, 0xAF,
        0xF9, 0x25, 0x55, 0x6B, 0x57, 0xFE, 0x6D, 0x00, 0x01, 0x0B, 0xB9, 0xC5,
    ];
    /// Eddystone-UID (service UUID list + service data for 0xFEAA: frame type,
    /// TX power, 10-byte namespace, 6-byte instance, 2 reserved), not an iBeacon.
    const EDDYSTONE_AD: [u8; 28] = [
        0x03, 0x03, 0xAA, 0xFE, 0x17, 0x16, 0xAA, 0xFE, 0x00, 0xEE, 0x01, 0x02, 0x03, 0x04, 0x05,
        0x06, 0x07, 0x08, 0x09, 0x0A, 0x11, 0x12, 0x13, 0x14, 0x15, 0x16, 0x00, 0x00,
    ];
    /// Apple Continuity "nearby info": Apple's company id, but no iBeacon.
    const CONTINUITY_AD: [u8; 11] = [
        0x0A, 0xFF, 0x4C, 0x00, 0x10, 0x05, 0x01, 0x18, 0x44, 0x1C, 0x2D,
    ];

    fn beacon() -> BeaconId {
        BeaconId {
            uuid: Uuid::parse_str("b9407f30-f5f8-466e-aff9-25556b57fe6d").unwrap(),
            major: 1,
            minor: 3001,
        }
    }

    fn header(datalink: u32) -> Vec<u8> {
        let mut out = MAGIC.to_vec();
        out.extend_from_slice(&1u32.to_be_bytes());
        out.extend_from_slice(&datalink.to_be_bytes());
        out
    }

    fn record(out: &mut Vec<u8>, flags: u32, t_us: i64, packet: &[u8]) {
        let len = (packet.len() as u32).to_be_bytes();
        out.extend_from_slice(&len);
        out.extend_from_slice(&len);
        out.extend_from_slice(&flags.to_be_bytes());
        out.extend_from_slice(&0u32.to_be_bytes());
        out.extend_from_slice(&(UNIX_EPOCH_US + t_us).to_be_bytes());
        out.extend_from_slice(packet);
    }

    /// An LE Meta event: code, parameter length, subevent, parameters.
    fn le_meta(subevent: u8, params: &[u8]) -> Vec<u8> {
        let mut out = vec![0x3E, (params.len() + 1) as u8, subevent];
        out.extend_from_slice(params);
        out
    }

    /// One legacy report: ADV_NONCONN_IND from a random address.
    fn legacy_report(ad: &[u8], rssi: i8) -> Vec<u8> {
        let mut out = vec![
            0x03,
            0x01,
            0x11,
            0x22,
            0x33,
            0x44,
            0x55,
            0xC6,
            ad.len() as u8,
        ];
        out.extend_from_slice(ad);
        out.push(rssi as u8);
        out
    }

    /// One extended report: legacy non-connectable PDU on LE 1M, no SID.
    fn extended_report(ad: &[u8], rssi: i8) -> Vec<u8> {
        let mut out = vec![0x10, 0x00, 0x01, 0x11, 0x22, 0x33, 0x44, 0x55, 0xC6];
        out.extend_from_slice(&[0x01, 0x00, 0xFF, 0x7F, rssi as u8, 0x00, 0x00, 0x00]);
        out.extend_from_slice(&[0; 6]);
        out.push(ad.len() as u8);
        out.extend_from_slice(ad);
        out
    }

    fn reports(subevent: u8, reports: &[Vec<u8>]) -> Vec<u8> {
        let mut params = vec![reports.len() as u8];
        for r in reports {
            params.extend_from_slice(r);
        }
        le_meta(subevent, &params)
    }

    type Read = (Vec<Result<Sighting, BtsnoopError>>, Vec<(SkipReason, u64)>);

    fn read(bytes: &[u8], skip_bad: bool) -> Read {
        let mut reader =
            BtsnoopReader::new(bytes, Path::new("cap.btsnoop"), "phone".into(), skip_bad).unwrap();
        let items: Vec<_> = reader.by_ref().collect();
        (items, reader.skipped().collect())
    }

    fn flags_ad_then(ad: &[u8]) -> Vec<u8> {
        let mut out = vec![0x02, 0x01, 0x06];
        out.extend_from_slice(ad);
        out
    }

    #[test]
    fn h4_legacy_report_gives_a_sighting_with_record_time_and_report_rssi() {
        let mut file = header(1002);
        let mut packet = vec![0x04];
        packet.extend(reports(
            0x02,
            &[legacy_report(&flags_ad_then(&IBEACON_AD), -67)],
        ));
        record(&mut file, 0b11, T0_US, &packet);
        let (items, skipped) = read(&file, false);
        let s = items.into_iter().map(Result::unwrap).collect::<Vec<_>>();
        assert_eq!(
            s,
            vec![Sighting {
                advertiser_mac: None,
                t: 1_700_000_000.25,
                observer: "phone".into(),
                advertiser: beacon(),
                tx_power: Some(-59),
                rssi: -67,
            }]
        );
        assert!(skipped.is_empty());
    }

    #[test]
    fn monitor_extended_report_skips_non_ibeacons_and_counts_them() {
        let mut file = header(2001);
        // adapter 0 "new index", then an extended report with three adverts.
        record(&mut file, 0, 0, &[0; 16]);
        let event = reports(
            0x0D,
            &[
                extended_report(&EDDYSTONE_AD, -80),
                extended_report(&flags_ad_then(&IBEACON_AD), -71),
                extended_report(&CONTINUITY_AD, -60),
            ],
        );
        record(&mut file, (1 << 16) | 3, T0_US, &event);
        let (items, skipped) = read(&file, false);
        let s: Vec<_> = items.into_iter().map(Result::unwrap).collect();
        assert_eq!(s.len(), 1);
        assert_eq!((s[0].rssi, s[0].advertiser), (-71, beacon()));
        assert_eq!(
            skipped,
            vec![(SkipReason::NotAnEvent, 1), (SkipReason::NotIBeacon, 2)]
        );
    }

    #[test]
    fn several_reports_in_one_event_keep_their_order() {
        let mut file = header(1002);
        let mut packet = vec![0x04];
        packet.extend(reports(
            0x02,
            &[
                legacy_report(&IBEACON_AD, -50),
                legacy_report(&IBEACON_AD, 127), // controller had no RSSI
                legacy_report(&IBEACON_AD, -90),
            ],
        ));
        record(&mut file, 0b11, T0_US, &packet);
        let (items, skipped) = read(&file, false);
        let rssi: Vec<i16> = items.into_iter().map(|s| s.unwrap().rssi).collect();
        assert_eq!(rssi, vec![-50, -90]);
        assert_eq!(skipped, vec![(SkipReason::NoRssi, 1)]);
    }

    #[test]
    fn other_hci_traffic_and_unknown_event_codes_are_skipped_and_counted() {
        let mut file = header(2001);
        // LE Set Scan Enable command (monitor opcode 2), Command Complete event,
        // an event code no spec defines, LE Connection Complete, ACL data, and a
        // report whose data length runs past the event.
        record(&mut file, 2, T0_US, &[0x0C, 0x20, 0x02, 0x01, 0x00]);
        record(&mut file, 3, T0_US, &[0x0E, 0x04, 0x01, 0x0C, 0x20, 0x00]);
        record(&mut file, 3, T0_US, &[0xF7, 0x02, 0xAB, 0xCD]);
        record(&mut file, 3, T0_US, &le_meta(0x01, &[0x00; 18]));
        record(&mut file, 5, T0_US, &[0x40, 0x00, 0x01, 0x00, 0xFF]);
        let mut bad = reports(0x02, &[legacy_report(&IBEACON_AD, -60)]);
        bad[12] = 0xF0; // data length
        record(&mut file, 3, T0_US, &bad);
        record(&mut file, 3, T0_US, &[0x3E]); // no length byte
        // And a good one after all of it.
        record(
            &mut file,
            3,
            T0_US + 1,
            &reports(0x02, &[legacy_report(&IBEACON_AD, -60)]),
        );
        let (items, skipped) = read(&file, false);
        assert_eq!(items.len(), 1);
        assert!(items[0].is_ok());
        assert_eq!(
            skipped,
            vec![
                (SkipReason::NotAnEvent, 2),
                (SkipReason::OtherEvent, 2),
                (SkipReason::OtherLeSubevent, 1),
                (SkipReason::MalformedEvent, 2),
            ]
        );
    }

    #[test]
    fn h1_datalink_uses_the_flags_to_find_events() {
        let mut file = header(1001);
        let event = reports(0x02, &[legacy_report(&IBEACON_AD, -60)]);
        record(&mut file, 0b10, T0_US, &event); // sent by the host: not an event
        record(&mut file, 0b11, T0_US, &event);
        let (items, skipped) = read(&file, false);
        assert_eq!(items.len(), 1);
        assert_eq!(skipped, vec![(SkipReason::NotAnEvent, 1)]);
    }

    #[test]
    fn a_truncated_last_record_is_an_error_naming_record_and_offset() {
        let mut file = header(1002);
        let mut packet = vec![0x04];
        packet.extend(reports(0x02, &[legacy_report(&IBEACON_AD, -60)]));
        record(&mut file, 0b11, T0_US, &packet);
        let second_offset = file.len();
        record(&mut file, 0b11, T0_US + 2_000_000, &packet);
        file.truncate(file.len() - 10);

        let (items, _) = read(&file, false);
        assert_eq!(items.len(), 2);
        assert!(items[0].is_ok());
        let err = items[1].as_ref().unwrap_err().to_string();
        assert!(
            err.contains(&format!("record 2 at byte {second_offset} is truncated")),
            "{err}"
        );

        let (items, skipped) = read(&file, true);
        assert_eq!(items.len(), 1);
        assert_eq!(skipped, vec![(SkipReason::TruncatedRecord, 1)]);

        // Cut inside the record header too.
        file.truncate(second_offset + 5);
        let (items, _) = read(&file, false);
        let err = items[1].as_ref().unwrap_err().to_string();
        assert!(err.contains("(5 of 24 bytes)"), "{err}");
    }

    #[test]
    fn an_impossible_record_length_stops_with_an_error() {
        let mut file = header(2001);
        file.extend_from_slice(&[0xFF; 24]);
        let (items, _) = read(&file, true);
        let err = items[0].as_ref().unwrap_err().to_string();
        assert!(
            err.contains("record 1 at byte 16 claims 4294967295 bytes"),
            "{err}"
        );
    }

    #[test]
    fn refuses_files_that_are_not_btsnoop() {
        let open = |bytes: &[u8]| {
            BtsnoopReader::new(bytes, Path::new("x"), "p".into(), false)
                .err()
                .unwrap()
                .to_string()
        };
        assert!(open(b"{\"t\":1}\n").contains("does not start with"));
        assert!(open(&header(1003)).contains("datalink 1003 is not supported"));
        let mut v2 = header(1002);
        v2[11] = 2;
        assert!(open(&v2).contains("version 2"));
    }

    #[test]
    fn writer_output_reads_back_to_the_same_sightings_on_every_datalink() {
        let sightings: Vec<Sighting> = (0..20)
            .map(|i| Sighting {
                advertiser_mac: None,
                t: 1_700_000_000.0 + f64::from(i) * 0.125,
                observer: "gw".into(),
                advertiser: BeaconId {
                    minor: 3001 + (i % 3) as u16,
                    ..beacon()
                },
                tx_power: Some(-59 + (i % 2) as i8),
                rssi: -40 - i as i16,
            })
            .collect();
        for datalink in [Datalink::H1, Datalink::H4, Datalink::Monitor] {
            let mut writer = BtsnoopWriter::new(Vec::new(), datalink).unwrap();
            for s in &sightings {
                writer.write(s).unwrap();
            }
            let bytes = writer.out;
            let reader =
                BtsnoopReader::new(&bytes[..], Path::new("rt"), "gw".into(), false).unwrap();
            assert_eq!(reader.datalink(), datalink);
            let back: Vec<Sighting> = reader.map(Result::unwrap).collect();
            assert_eq!(back, sightings, "{datalink:?}");
        }
    }

    #[test]
    fn writer_refuses_what_a_report_cannot_carry() {
        let mut writer = BtsnoopWriter::new(Vec::new(), Datalink::Monitor).unwrap();
        let s = Sighting {
            advertiser_mac: None,
            t: 0.0,
            observer: "gw".into(),
            advertiser: beacon(),
            tx_power: None,
            rssi: -60,
        };
        assert!(writer.write(&s).is_err());
        assert!(
            writer
                .write(&Sighting {
                    advertiser_mac: None,
                    tx_power: Some(-59),
                    rssi: -300,
                    ..s
                })
                .is_err()
        );
    }

    proptest! {
        #[test]
        fn arbitrary_bytes_after_a_valid_header_never_panic(
            datalink in prop::sample::select(vec![1001u32, 1002, 2001]),
            body in prop::collection::vec(any::<u8>(), 0..512),
            skip_bad: bool,
        ) {
            let mut file = header(datalink);
            file.extend_from_slice(&body);
            let (items, _) = read(&file, skip_bad);
            // At most one error, and it is the last item.
            let errors = items.iter().filter(|i| i.is_err()).count();
            prop_assert!(errors <= 1);
            if errors == 1 {
                prop_assert!(items.last().unwrap().is_err());
            }
        }

        #[test]
        fn arbitrary_le_meta_events_in_valid_records_never_panic(
            subevent in prop::sample::select(vec![0x02u8, 0x0D, 0x01]),
            params in prop::collection::vec(any::<u8>(), 0..300),
        ) {
            let mut file = header(2001);
            let mut event = vec![0x3E, params.len().min(255) as u8, subevent];
            event.extend_from_slice(&params);
            record(&mut file, 3, T0_US, &event);
            let (items, _) = read(&file, false);
            prop_assert!(items.iter().all(Result::is_ok));
        }
    }
}
