//! pcap and pcapng captures: iBeacon sightings read from what Wireshark, tcpdump
//! and the nRF Sniffer for Bluetooth LE save.
//!
//! Containers (either byte order, told by the magic number):
//!
//! ```text
//! pcap:    a1b2c3d4 (µs) or a1b23c4d (ns) | version (2+2) | thiszone | sigfigs | snaplen | linktype
//!          then records: seconds u32 | fraction u32 | captured length u32 | original length u32 | packet
//! pcapng:  blocks: type u32 | total length u32 | body | total length u32
//!          Section Header (0x0A0D0D0A; byte-order magic 1a2b3c4d, version 1.x) starts a section,
//!          Interface Description (1) declares an interface: linktype, options (if_tsresol, if_tsoffset),
//!          Enhanced Packet (6) and the obsolete Packet (2) blocks carry packets with a timestamp
//!          in the units of their interface's if_tsresol (default µs) since 1970.
//! ```
//!
//! Each packet is decoded by its interface's linktype ([`Linktype`]: 201, 251,
//! 256, 272); a sighting gets the packet's timestamp, the RSSI the linktype
//! carries and the `--device` observer. Simple Packet blocks carry no timestamp
//! and are counted (`no_timestamp`); other blocks (name resolution, statistics,
//! custom) are passed over. Nothing in a packet stops the reader: what is not
//! an iBeacon advert is counted by [`SkipReason`].
//!
//! Bounds and errors: a pcapng block whose framing holds (its trailing length
//! repeats its leading one) but whose body does not (a packet longer than the
//! block, an unknown interface, options running past the block, a packet over
//! 1 MiB) is skipped, counted `corrupt_block` and logged with its block number
//! and byte offset (up to ten warnings per file). A broken frame (a length
//! under the minimum, not a multiple of four, or whose trailing copy
//! disagrees; a pcap record over 1 MiB) ends the file with an error naming the
//! block or record and byte offset, since nothing after it can be found; a
//! block or record cut short at the end is the same error, or with `skip_bad`
//! counted `truncated_record`. At most [`MAX_INTERFACES`] interfaces per
//! section are kept.
//!
//! Hand-written rather than built on the `pcap-file` crate: its released
//! version (2.0) reads Enhanced Packet timestamps as nanoseconds whatever
//! if_tsresol says (microsecond captures, the default, come out 1000× off);
//! if_tsresol is honoured only in 3.0 release candidates, which hold an 8 MB
//! read buffer per reader and extend borrows with `unsafe` transmutes. The
//! framing is a few fixed headers; the BLE linktypes are decoded in
//! [`pcap_link`](super::pcap_link).

use std::fs::File;
use std::io::{self, BufReader, Read};
use std::path::{Path, PathBuf};
use std::sync::Arc;

use super::adverts::{Adverts, SkipReason};
use super::btsnoop::read_full;
pub(crate) use super::pcap_link::Linktype;
use crate::sighting::Sighting;

/// The first four bytes of a pcapng file: a Section Header Block's type, the
/// same in both byte orders.
pub(crate) const PCAPNG_MAGIC: [u8; 4] = [0x0A, 0x0D, 0x0D, 0x0A];
const PCAP_MAGIC_US: u32 = 0xA1B2_C3D4;
const PCAP_MAGIC_NS: u32 = 0xA1B2_3C4D;
const BYTE_ORDER_MAGIC: u32 = 0x1A2B_3C4D;
const PCAP_HEADER_LEN: usize = 24;
const PCAP_RECORD_HEADER_LEN: usize = 16;
/// libpcap keeps the linktype in the low 26 bits; the rest flag FCS lengths.
const PCAP_LINKTYPE_MASK: u32 = 0x03FF_FFFF;
/// Block type, total length, trailing total length.
const BLOCK_FRAME_LEN: u32 = 12;
/// A Section Header Block: frame, byte-order magic, version, section length.
const SHB_MIN_LEN: u32 = BLOCK_FRAME_LEN + 4 + 4 + 8;
const BLOCK_IDB: u32 = 1;
const BLOCK_PACKET_OBSOLETE: u32 = 2;
const BLOCK_SIMPLE_PACKET: u32 = 3;
const BLOCK_EPB: u32 = 6;
const OPT_END: u16 = 0;
const OPT_IF_TSRESOL: u16 = 9;
const OPT_IF_TSOFFSET: u16 = 14;
/// Larger than any packet a capture tool writes (libpcap's snaplen tops out
/// at 256 KiB): a longer packet means corruption, and buffering it would only
/// waste memory. Blocks that carry no packet may be longer; they are read
/// through, not buffered.
const MAX_PACKET_LEN: u32 = 1 << 20;
/// Interfaces kept per pcapng section; a capture has a handful.
pub(crate) const MAX_INTERFACES: usize = 1024;
/// Warnings (corrupt blocks, interfaces of other linktypes) logged one by
/// one; later ones are only counted, so a hostile file cannot flood the log.
const WARNINGS_LOGGED: u64 = 10;

/// Whether a file starting with `magic` is a pcap or pcapng capture.
pub(crate) fn is_magic(magic: [u8; 4]) -> bool {
    magic == PCAPNG_MAGIC
        || [PCAP_MAGIC_US, PCAP_MAGIC_NS]
            .iter()
            .any(|m| magic == m.to_be_bytes() || magic == m.to_le_bytes())
}

#[derive(Debug, thiserror::Error)]
pub enum PcapError {
    #[error("{path}: cannot read the capture: {source}")]
    Io { path: PathBuf, source: io::Error },
    #[error("{path}: not a pcap or pcapng capture gangway reads: {reason}")]
    Header { path: PathBuf, reason: String },
    #[error(
        "{path}: {unit} {number} at byte {offset} is truncated ({have} of {need} bytes); \
         the capture was cut off. Replay with --skip-bad to use what comes before it"
    )]
    Truncated {
        path: PathBuf,
        unit: &'static str,
        number: u64,
        offset: u64,
        have: u64,
        need: u64,
    },
    #[error("{path}: {unit} {number} at byte {offset}: {reason}; the file is corrupt from here on")]
    Corrupt {
        path: PathBuf,
        unit: &'static str,
        number: u64,
        offset: u64,
        reason: String,
    },
}

/// How integers are stored: pcap and pcapng files are written in the byte
/// order of the machine that wrote them.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct ByteOrder {
    big: bool,
}

impl ByteOrder {
    fn u16(self, b: [u8; 2]) -> u16 {
        if self.big {
            u16::from_be_bytes(b)
        } else {
            u16::from_le_bytes(b)
        }
    }

    fn u32(self, b: [u8; 4]) -> u32 {
        if self.big {
            u32::from_be_bytes(b)
        } else {
            u32::from_le_bytes(b)
        }
    }

    /// The u32 at `at` in `bytes`, which the caller has checked is long enough.
    fn u32_at(self, bytes: &[u8], at: usize) -> u32 {
        self.u32(bytes[at..at + 4].try_into().expect("4 bytes"))
    }
}

/// The unit of a timestamp: 10^-n or 2^-n seconds.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Resolution {
    Decimal(u32),
    Binary(u32),
}

impl Resolution {
    const MICROS: Resolution = Resolution::Decimal(6);

    /// The if_tsresol option's byte: the top bit picks base 2 over base 10.
    fn from_option(byte: u8) -> Resolution {
        if byte & 0x80 == 0 {
            Resolution::Decimal(u32::from(byte))
        } else {
            Resolution::Binary(u32::from(byte & 0x7F))
        }
    }

    /// Seconds in `ticks` of this unit, as exactly as an f64 holds them.
    fn seconds(self, ticks: u64) -> f64 {
        match self {
            Resolution::Decimal(exp) => match 10u64.checked_pow(exp) {
                // One division of exact integers rounds once.
                Some(per_s) if ticks < 1 << f64::MANTISSA_DIGITS => ticks as f64 / per_s as f64,
                Some(per_s) => (ticks / per_s) as f64 + (ticks % per_s) as f64 / per_s as f64,
                None => ticks as f64 / 10f64.powi(exp as i32),
            },
            Resolution::Binary(exp) => ticks as f64 / 2f64.powi(exp as i32),
        }
    }
}

/// A pcapng interface: how its packets are decoded and timed.
#[derive(Clone, Copy, Debug)]
struct Interface {
    /// Why its packets are skipped, when they are.
    linktype: Result<Linktype, SkipReason>,
    resolution: Resolution,
    /// if_tsoffset: seconds to add to every timestamp.
    offset_s: i64,
}

impl Interface {
    /// An interface whose description could not be read: its packets are
    /// skipped as corrupt.
    const UNREADABLE: Interface = Interface {
        linktype: Err(SkipReason::CorruptBlock),
        resolution: Resolution::MICROS,
        offset_s: 0,
    };
}

/// An Interface Description Block's body: linktype (2), reserved (2),
/// snaplen (4), options (code u16, length u16, value padded to 4 bytes).
fn parse_interface(body: &[u8], order: ByteOrder) -> Result<Interface, String> {
    let Some((fixed, mut options)) = body.split_first_chunk::<8>() else {
        return Err(format!(
            "is an interface description of {} bytes, under 8",
            body.len()
        ));
    };
    let code = u32::from(order.u16([fixed[0], fixed[1]]));
    let mut interface = Interface {
        linktype: Linktype::from_code(code).ok_or(SkipReason::OtherLinktype),
        resolution: Resolution::MICROS,
        offset_s: 0,
    };
    while let Some((head, rest)) = options.split_first_chunk::<4>() {
        let option = order.u16([head[0], head[1]]);
        let len = usize::from(order.u16([head[2], head[3]]));
        if option == OPT_END {
            break;
        }
        let value = rest
            .get(..len)
            .ok_or_else(|| format!("has option {option} running past the block"))?;
        match (option, value) {
            (OPT_IF_TSRESOL, &[byte]) => interface.resolution = Resolution::from_option(byte),
            (OPT_IF_TSOFFSET, value) if len == 8 => {
                let bytes: [u8; 8] = value.try_into().expect("8 bytes");
                interface.offset_s = if order.big {
                    i64::from_be_bytes(bytes)
                } else {
                    i64::from_le_bytes(bytes)
                };
            }
            (OPT_IF_TSRESOL | OPT_IF_TSOFFSET, _) => {
                return Err(format!("has option {option} of {len} bytes"));
            }
            _ => {}
        }
        options = rest.get(len.next_multiple_of(4)..).unwrap_or_default();
    }
    Ok(interface)
}

#[derive(Debug)]
enum Container {
    Pcap {
        order: ByteOrder,
        resolution: Resolution,
        linktype: Linktype,
    },
    PcapNg {
        order: ByteOrder,
        interfaces: Vec<Interface>,
    },
}

/// Streams iBeacon sightings from a pcap or pcapng capture, one block in
/// memory at a time.
pub struct PcapReader<R> {
    input: R,
    path: PathBuf,
    skip_bad: bool,
    container: Container,
    /// Records (pcap) or blocks (pcapng) read so far, the current one's number.
    number: u64,
    /// Byte offset of the next record or block.
    offset: u64,
    buf: Vec<u8>,
    adverts: Adverts,
    /// Warnings logged so far.
    warnings: u64,
    done: bool,
}

impl PcapReader<BufReader<File>> {
    /// Opens a capture; every sighting is attributed to `observer`, since a
    /// capture does not name the host that made it.
    pub(crate) fn open(path: &Path, observer: Arc<str>, skip_bad: bool) -> Result<Self, PcapError> {
        let file = File::open(path).map_err(|source| PcapError::Io {
            path: path.to_owned(),
            source,
        })?;
        PcapReader::new(
            BufReader::with_capacity(1 << 16, file),
            path,
            observer,
            skip_bad,
        )
    }
}

impl<R: Read> PcapReader<R> {
    /// Reads the file header (pcap) or first Section Header Block (pcapng)
    /// from `input`; `path` names it in errors.
    pub fn new(
        input: R,
        path: &Path,
        observer: Arc<str>,
        skip_bad: bool,
    ) -> Result<Self, PcapError> {
        let mut reader = PcapReader {
            input,
            path: path.to_owned(),
            skip_bad,
            container: Container::PcapNg {
                order: ByteOrder { big: false },
                interfaces: Vec::new(),
            },
            number: 0,
            offset: 0,
            buf: Vec::new(),
            adverts: Adverts::new(observer),
            warnings: 0,
            done: false,
        };
        let mut magic = [0u8; 4];
        let got = read_full(&mut reader.input, &mut magic).map_err(|e| reader.io(e))?;
        let header = |reason: String| PcapError::Header {
            path: path.to_owned(),
            reason,
        };
        if got == magic.len() && magic == PCAPNG_MAGIC {
            reader.section(magic).map_err(|e| match e {
                PcapError::Corrupt { reason, .. } => header(reason),
                other => other,
            })?;
            return Ok(reader);
        }
        if got < magic.len() || !is_magic(magic) {
            return Err(header(format!(
                "it starts with {}, neither pcapng's 0a0d0d0a nor pcap's a1b2c3d4 or a1b23c4d \
                 in either byte order; save captures from Wireshark as pcapng or pcap",
                hex(&magic[..got])
            )));
        }
        let order = ByteOrder {
            big: matches!(u32::from_be_bytes(magic), PCAP_MAGIC_US | PCAP_MAGIC_NS),
        };
        let resolution = if order.u32(magic) == PCAP_MAGIC_NS {
            Resolution::Decimal(9)
        } else {
            Resolution::MICROS
        };
        let mut rest = [0u8; PCAP_HEADER_LEN - 4];
        let got = read_full(&mut reader.input, &mut rest).map_err(|e| reader.io(e))?;
        if got < rest.len() {
            return Err(header(format!(
                "the pcap file header is cut off after {} of {PCAP_HEADER_LEN} bytes",
                got + 4
            )));
        }
        let major = order.u16([rest[0], rest[1]]);
        if major != 2 {
            return Err(header(format!(
                "pcap version {major}; only version 2 exists"
            )));
        }
        let code = order.u32_at(&rest, 16) & PCAP_LINKTYPE_MASK;
        let linktype = Linktype::from_code(code).ok_or_else(|| {
            header(format!(
                "linktype {code} is not Bluetooth LE; gangway reads {}. Capture with the nRF \
                 Sniffer, or from a Linux bluetooth interface",
                Linktype::SUPPORTED
            ))
        })?;
        reader.container = Container::Pcap {
            order,
            resolution,
            linktype,
        };
        reader.offset = PCAP_HEADER_LEN as u64;
        Ok(reader)
    }

    /// How many packets or adverts were skipped, by reason (zero counts left out).
    pub(crate) fn skipped(&self) -> impl Iterator<Item = (SkipReason, u64)> + '_ {
        self.adverts.skipped().iter()
    }

    fn io(&self, source: io::Error) -> PcapError {
        PcapError::Io {
            path: self.path.clone(),
            source,
        }
    }

    fn unit(&self) -> &'static str {
        match self.container {
            Container::Pcap { .. } => "record",
            Container::PcapNg { .. } => "block",
        }
    }

    fn truncated(&self, offset: u64, have: u64, need: u64) -> PcapError {
        PcapError::Truncated {
            path: self.path.clone(),
            unit: self.unit(),
            number: self.number,
            offset,
            have,
            need,
        }
    }

    fn corrupt(&self, offset: u64, reason: String) -> PcapError {
        PcapError::Corrupt {
            path: self.path.clone(),
            unit: self.unit(),
            number: self.number,
            offset,
            reason,
        }
    }

    /// Reads exactly `buf.len()` bytes of the unit that started at `start`,
    /// `have` bytes of which were read before; a short read is truncation.
    fn read_exact_of(
        &mut self,
        buf: &mut [u8],
        start: u64,
        have: u64,
        need: u64,
    ) -> Result<(), PcapError> {
        let got = read_full(&mut self.input, buf).map_err(|e| self.io(e))?;
        if got < buf.len() {
            return Err(self.truncated(start, have + got as u64, need));
        }
        Ok(())
    }

    /// Reads the next record or block and decodes its packet; `Ok(false)` at a
    /// clean end of file.
    fn step(&mut self) -> Result<bool, PcapError> {
        let start = self.offset;
        let mut head = [0u8; 8];
        let got = read_full(&mut self.input, &mut head).map_err(|e| self.io(e))?;
        if got == 0 {
            return Ok(false);
        }
        self.number += 1;
        match self.container {
            Container::Pcap {
                order,
                resolution,
                linktype,
            } => self.pcap_record(start, got, head, order, resolution, linktype)?,
            Container::PcapNg { .. } if head[..4] == PCAPNG_MAGIC => {
                if got < head.len() {
                    return Err(self.truncated(start, got as u64, u64::from(SHB_MIN_LEN)));
                }
                self.section_after(head)?;
            }
            Container::PcapNg { order, .. } => {
                if got < head.len() {
                    return Err(self.truncated(start, got as u64, u64::from(BLOCK_FRAME_LEN)));
                }
                let kind = order.u32_at(&head, 0);
                let total = order.u32_at(&head, 4);
                self.block(start, kind, total, order)?;
            }
        }
        Ok(true)
    }

    fn pcap_record(
        &mut self,
        start: u64,
        got: usize,
        head: [u8; 8],
        order: ByteOrder,
        resolution: Resolution,
        linktype: Linktype,
    ) -> Result<(), PcapError> {
        let need = PCAP_RECORD_HEADER_LEN as u64;
        if got < head.len() {
            return Err(self.truncated(start, got as u64, need));
        }
        let mut lengths = [0u8; 8];
        self.read_exact_of(&mut lengths, start, head.len() as u64, need)?;
        let captured = order.u32_at(&lengths, 0);
        if captured > MAX_PACKET_LEN {
            return Err(self.corrupt(
                start,
                format!("claims a {captured}-byte packet, more than any capture holds"),
            ));
        }
        let mut packet = std::mem::take(&mut self.buf);
        packet.resize(captured as usize, 0);
        let read = self.read_exact_of(&mut packet, start, need, need + u64::from(captured));
        self.buf = packet;
        read?;
        self.offset = start + need + u64::from(captured);
        let (seconds, fraction) = (order.u32_at(&head, 0), order.u32_at(&head, 4));
        let ticks_per_s = match resolution {
            Resolution::Decimal(9) => 1_000_000_000,
            _ => 1_000_000,
        };
        let t = resolution.seconds(u64::from(seconds) * ticks_per_s + u64::from(fraction));
        linktype.decode(t, &self.buf, &mut self.adverts);
        Ok(())
    }

    /// Reads the first Section Header Block, whose type `magic` was read.
    fn section(&mut self, magic: [u8; 4]) -> Result<(), PcapError> {
        self.number = 1;
        let mut head = [0u8; 8];
        head[..4].copy_from_slice(&magic);
        self.read_exact_of(&mut head[4..], 0, 4, u64::from(SHB_MIN_LEN))?;
        self.section_after(head)
    }

    /// Reads a Section Header Block after its type and length (`head`); it sets
    /// the byte order of what follows and forgets the interfaces before it.
    fn section_after(&mut self, head: [u8; 8]) -> Result<(), PcapError> {
        let start = self.offset;
        let mut magic = [0u8; 4];
        self.read_exact_of(&mut magic, start, 8, u64::from(SHB_MIN_LEN))?;
        let order = match u32::from_be_bytes(magic) {
            BYTE_ORDER_MAGIC => ByteOrder { big: true },
            m if m.swap_bytes() == BYTE_ORDER_MAGIC => ByteOrder { big: false },
            _ => {
                return Err(self.corrupt(
                    start,
                    format!(
                        "section header's byte-order magic is {}, not 1a2b3c4d in either byte \
                         order",
                        hex(&magic)
                    ),
                ));
            }
        };
        let total = order.u32_at(&head, 4);
        self.check_frame(start, total, SHB_MIN_LEN)?;
        if total - BLOCK_FRAME_LEN > MAX_PACKET_LEN {
            return Err(self.corrupt(
                start,
                format!("section header claims {total} bytes, over 1 MiB"),
            ));
        }
        let body = self.read_body(start, total, 12)?;
        let (major, minor) = (order.u16([body[0], body[1]]), order.u16([body[2], body[3]]));
        if major != 1 {
            return Err(self.corrupt(
                start,
                format!("pcapng version {major}.{minor}; only 1.x exists"),
            ));
        }
        self.container = Container::PcapNg {
            order,
            interfaces: Vec::new(),
        };
        Ok(())
    }

    /// Refuses a block length no pcapng writer produces.
    fn check_frame(&self, start: u64, total: u32, min: u32) -> Result<(), PcapError> {
        if total < min || !total.is_multiple_of(4) {
            return Err(self.corrupt(
                start,
                format!("claims a length of {total} bytes, not a multiple of 4 of at least {min}"),
            ));
        }
        Ok(())
    }

    /// Reads the rest of a `total`-byte block of which `have` bytes were read:
    /// the body into `self.buf` (returned), then the trailing length, which
    /// must repeat `total`.
    fn read_body(&mut self, start: u64, total: u32, have: u32) -> Result<Vec<u8>, PcapError> {
        let mut body = std::mem::take(&mut self.buf);
        body.resize((total - have - 4) as usize, 0);
        let mut trailer = [0u8; 4];
        let read = self
            .read_exact_of(&mut body, start, u64::from(have), u64::from(total))
            .and_then(|()| {
                self.read_exact_of(&mut trailer, start, u64::from(total - 4), u64::from(total))
            });
        if let Err(e) = read {
            self.buf = body;
            return Err(e);
        }
        self.check_trailer(start, total, trailer)?;
        Ok(body)
    }

    fn check_trailer(&mut self, start: u64, total: u32, trailer: [u8; 4]) -> Result<(), PcapError> {
        let order = match self.container {
            Container::PcapNg { order, .. } => order,
            Container::Pcap { order, .. } => order,
        };
        // A new section's byte order is not set yet: accept either.
        let trailing = order.u32(trailer);
        if trailing != total && trailing.swap_bytes() != total {
            return Err(self.corrupt(
                start,
                format!("ends with a length of {trailing} bytes where it began with {total}"),
            ));
        }
        self.offset = start + u64::from(total);
        Ok(())
    }

    /// Reads a block other than a section header and acts on it.
    fn block(
        &mut self,
        start: u64,
        kind: u32,
        total: u32,
        order: ByteOrder,
    ) -> Result<(), PcapError> {
        self.check_frame(start, total, BLOCK_FRAME_LEN)?;
        let carries_packet = matches!(
            kind,
            BLOCK_EPB | BLOCK_PACKET_OBSOLETE | BLOCK_SIMPLE_PACKET
        );
        if kind != BLOCK_IDB && !carries_packet {
            return self.pass_over(start, total);
        }
        if total - BLOCK_FRAME_LEN > MAX_PACKET_LEN {
            self.pass_over(start, total)?;
            if kind == BLOCK_IDB {
                // Counted below whether or not the section had room for it.
                let _ = self.push_interface(Interface::UNREADABLE);
            }
            self.corrupt_block(start, format!("is {total} bytes long, over 1 MiB"));
            return Ok(());
        }
        let body = self.read_body(start, total, 8)?;
        let outcome = match kind {
            BLOCK_IDB => self.interface(&body, order),
            BLOCK_SIMPLE_PACKET => {
                self.adverts.skip(SkipReason::NoTimestamp);
                Ok(())
            }
            _ => self.packet(&body, kind, order),
        };
        self.buf = body;
        if let Err(reason) = outcome {
            self.corrupt_block(start, reason);
        }
        Ok(())
    }

    /// Reads through a block that carries nothing gangway uses, without
    /// holding it in memory.
    fn pass_over(&mut self, start: u64, total: u32) -> Result<(), PcapError> {
        let body = u64::from(total - BLOCK_FRAME_LEN);
        let skipped =
            io::copy(&mut (&mut self.input).take(body), &mut io::sink()).map_err(|e| self.io(e))?;
        if skipped < body {
            return Err(self.truncated(start, 8 + skipped, u64::from(total)));
        }
        let mut trailer = [0u8; 4];
        self.read_exact_of(&mut trailer, start, u64::from(total - 4), u64::from(total))?;
        self.check_trailer(start, total, trailer)
    }

    fn corrupt_block(&mut self, start: u64, reason: String) {
        self.adverts.skip(SkipReason::CorruptBlock);
        self.warn(format!(
            "block {} at byte {start} {reason}; skipped",
            self.number
        ));
    }

    /// Logs a warning about the file, up to [`WARNINGS_LOGGED`] of them.
    fn warn(&mut self, message: String) {
        self.warnings += 1;
        if self.warnings <= WARNINGS_LOGGED {
            let more = if self.warnings == WARNINGS_LOGGED {
                " (further warnings about this file are not logged; the skip counts \
                 at the end of the replay count them)"
            } else {
                ""
            };
            tracing::warn!("{}: {message}{more}", self.path.display());
        }
    }

    /// An Interface Description Block: the next interface of the section.
    fn interface(&mut self, body: &[u8], order: ByteOrder) -> Result<(), String> {
        let (interface, outcome) = match parse_interface(body, order) {
            Ok(interface) => (interface, Ok(())),
            // Kept as unreadable, so later interfaces keep their ids.
            Err(reason) => (Interface::UNREADABLE, Err(reason)),
        };
        let id = self.push_interface(interface)?;
        if let Err(SkipReason::OtherLinktype) = interface.linktype {
            self.warn(format!(
                "interface {id} (block {}) is not Bluetooth LE; its packets are skipped \
                 (gangway reads linktypes {})",
                self.number,
                Linktype::SUPPORTED
            ));
        }
        outcome
    }

    /// Adds an interface to the current section; its id, or why not.
    fn push_interface(&mut self, interface: Interface) -> Result<usize, String> {
        let Container::PcapNg { interfaces, .. } = &mut self.container else {
            unreachable!("blocks are read from pcapng files only");
        };
        if interfaces.len() >= MAX_INTERFACES {
            return Err(format!(
                "declares an interface over the {MAX_INTERFACES} a section may have"
            ));
        }
        interfaces.push(interface);
        Ok(interfaces.len() - 1)
    }

    /// An Enhanced Packet Block (interface u32, timestamp high and low u32,
    /// captured and original length u32, packet) or an obsolete Packet Block
    /// (interface u16, drops u16, then the same).
    fn packet(&mut self, body: &[u8], kind: u32, order: ByteOrder) -> Result<(), String> {
        let Container::PcapNg { interfaces, .. } = &self.container else {
            unreachable!("blocks are read from pcapng files only");
        };
        let Some(fixed) = body.get(..20) else {
            return Err(format!(
                "is a packet block of {} bytes, under 20",
                body.len()
            ));
        };
        let id = if kind == BLOCK_EPB {
            order.u32_at(fixed, 0)
        } else {
            u32::from(order.u16([fixed[0], fixed[1]]))
        };
        let captured = order.u32_at(fixed, 12);
        let packet = body
            .get(20..)
            .and_then(|rest| rest.get(..captured as usize))
            .ok_or_else(|| format!("has a {captured}-byte packet, longer than the block"))?;
        let interface = interfaces.get(id as usize).ok_or_else(|| {
            format!(
                "names interface {id}, but its section declares {}",
                interfaces.len()
            )
        })?;
        let linktype = match interface.linktype {
            Ok(linktype) => linktype,
            Err(reason) => {
                self.adverts.skip(reason);
                return Ok(());
            }
        };
        let ticks = (u64::from(order.u32_at(fixed, 4)) << 32) | u64::from(order.u32_at(fixed, 8));
        let t = interface.resolution.seconds(ticks) + interface.offset_s as f64;
        linktype.decode(t, packet, &mut self.adverts);
        Ok(())
    }
}

impl<R: Read> Iterator for PcapReader<R> {
    type Item = Result<Sighting, PcapError>;

    fn next(&mut self) -> Option<Self::Item> {
        while !self.done {
            if let Some(sighting) = self.adverts.pop() {
                return Some(Ok(sighting));
            }
            match self.step() {
                Ok(true) => {}
                Ok(false) => self.done = true,
                Err(e) => {
                    // Nothing after a broken frame can be found.
                    self.done = true;
                    if self.skip_bad && matches!(e, PcapError::Truncated { .. }) {
                        self.adverts.skip(SkipReason::TruncatedRecord);
                        tracing::warn!("{e}");
                    } else {
                        return Some(Err(e));
                    }
                }
            }
        }
        self.adverts.pop().map(Ok)
    }
}

fn hex(bytes: &[u8]) -> String {
    if bytes.is_empty() {
        return "nothing (the file is empty)".into();
    }
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::sighting::BeaconId;
    use crate::source::pcap_link::{
        ADV_IND, ADV_NONCONN_IND, ADVERTISING_ACCESS_ADDRESS, SCAN_RSP,
    };
    use proptest::prelude::*;
    use uuid::Uuid;

    /// 2023-11-14 22:13:20.25 UTC, in microseconds.
    const T0_US: u64 = 1_700_000_000_250_000;
    const T0: f64 = 1_700_000_000.25;

    /// Flags, then the manufacturer-specific AD structure of a real iBeacon:
    /// UUID B9407F30-F5F8-466E-AFF9-25556B57FE6D, major 1, minor 3001, -59 dBm at 1 m.
    const IBEACON_AD: [u8; 30] = [
        0x02, 0x01, 0x06, 0x1A, 0xFF, 0x4C, 0x00, 0x02, 0x15, 0xB9, 0x40, 0x7F, 0x30, 0xF5, 0xF8,
        0x46, 0x6E, 0xAF, 0xF9, 0x25, 0x55, 0x6B, 0x57, 0xFE, 0x6D, 0x00, 0x01, 0x0B, 0xB9, 0xC5,
    ];
    /// Apple Continuity "nearby info": Apple's company id, but no iBeacon.
    const CONTINUITY_AD: [u8; 11] = [
        0x0A, 0xFF, 0x4C, 0x00, 0x10, 0x05, 0x01, 0x18, 0x44, 0x1C, 0x2D,
    ];
    const ADV_ADDRESS: [u8; 6] = [0x11, 0x22, 0x33, 0x44, 0x55, 0xC6];

    fn beacon() -> BeaconId {
        BeaconId {
            uuid: Uuid::parse_str("b9407f30-f5f8-466e-aff9-25556b57fe6d").unwrap(),
            major: 1,
            minor: 3001,
        }
    }

    /// A link-layer packet: access address, PDU header, payload, CRC.
    fn ll(access_address: u32, header: u8, payload: &[u8]) -> Vec<u8> {
        let mut out = access_address.to_le_bytes().to_vec();
        out.extend_from_slice(&[header, payload.len() as u8]);
        out.extend_from_slice(payload);
        out.extend_from_slice(&[0xAB, 0xCD, 0xEF]);
        out
    }

    /// A legacy advertising PDU from a random address.
    fn legacy(pdu_type: u8, ad: &[u8]) -> Vec<u8> {
        let mut payload = ADV_ADDRESS.to_vec();
        payload.extend_from_slice(ad);
        ll(ADVERTISING_ACCESS_ADDRESS, 0x40 | pdu_type, &payload)
    }

    /// An AUX_ADV_IND: extended header with AdvA and ADI, then AdvData.
    fn aux_adv_ind(ad: &[u8]) -> Vec<u8> {
        let mut payload = vec![9, 0x09];
        payload.extend_from_slice(&ADV_ADDRESS);
        payload.extend_from_slice(&[0x01, 0x10]);
        payload.extend_from_slice(ad);
        ll(ADVERTISING_ACCESS_ADDRESS, 0x07, &payload)
    }

    /// `BLUETOOTH_LE_LL_WITH_PHDR`: channel 37, signal, noise, offenses,
    /// reference access address, flags, then the packet.
    fn with_phdr(signal: i8, flags: u16, ll: &[u8]) -> Vec<u8> {
        let mut out = vec![0, signal as u8, 0x9C, 0];
        out.extend_from_slice(&ADVERTISING_ACCESS_ADDRESS.to_le_bytes());
        out.extend_from_slice(&flags.to_le_bytes());
        out.extend_from_slice(ll);
        out
    }

    /// Dewhitened, signal valid, CRC checked and valid.
    const PHDR_GOOD: u16 = 0x0001 | 0x0002 | 0x0400 | 0x0800;

    /// `NORDIC_BLE`, header version 3: board, payload length, version,
    /// counter, packet id, then length, flags, channel, RSSI, event counter,
    /// timestamp and the packet.
    fn nordic(id: u8, flags: u8, rssi: u8, ll: &[u8]) -> Vec<u8> {
        let payload_len = (10 + ll.len()) as u16;
        let mut out = vec![0x01];
        out.extend_from_slice(&payload_len.to_le_bytes());
        out.extend_from_slice(&[3, 0x34, 0x12, id, 10, flags, 37, rssi, 0, 0, 1, 2, 3, 4]);
        out.extend_from_slice(ll);
        out
    }

    /// `BLUETOOTH_HCI_H4_WITH_PHDR`: direction "received", H4 event.
    fn h4_event(event: &[u8]) -> Vec<u8> {
        let mut out = vec![0, 0, 0, 1, 0x04];
        out.extend_from_slice(event);
        out
    }

    fn le_meta(subevent: u8, report: &[u8]) -> Vec<u8> {
        let mut out = vec![0x3E, (report.len() + 2) as u8, subevent, 1];
        out.extend_from_slice(report);
        out
    }

    fn legacy_report(ad: &[u8], rssi: i8) -> Vec<u8> {
        let mut report = vec![0x03, 0x01];
        report.extend_from_slice(&ADV_ADDRESS);
        report.push(ad.len() as u8);
        report.extend_from_slice(ad);
        report.push(rssi as u8);
        le_meta(0x02, &report)
    }

    fn extended_report(ad: &[u8], rssi: i8) -> Vec<u8> {
        let mut report = vec![0x00, 0x00, 0x01];
        report.extend_from_slice(&ADV_ADDRESS);
        report.extend_from_slice(&[0x01, 0x02, 0x03, 0x7F, rssi as u8, 0, 0, 0]);
        report.extend_from_slice(&[0; 6]);
        report.push(ad.len() as u8);
        report.extend_from_slice(ad);
        le_meta(0x0D, &report)
    }

    /// A pcapng file being built, in either byte order.
    struct Ng {
        out: Vec<u8>,
        big: bool,
    }

    impl Ng {
        fn new(big: bool) -> Ng {
            let mut ng = Ng {
                out: Vec::new(),
                big,
            };
            ng.section();
            ng
        }

        fn u16(&self, v: u16) -> [u8; 2] {
            if self.big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        }

        fn u32(&self, v: u32) -> [u8; 4] {
            if self.big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        }

        fn block(&mut self, kind: u32, body: &[u8]) -> &mut Ng {
            let padded = body.len().next_multiple_of(4);
            let total = self.u32((12 + padded) as u32);
            self.out.extend_from_slice(&self.u32(kind));
            self.out.extend_from_slice(&total);
            self.out.extend_from_slice(body);
            self.out.resize(self.out.len() + padded - body.len(), 0);
            self.out.extend_from_slice(&total);
            self
        }

        fn section(&mut self) -> &mut Ng {
            let mut body = self.u32(BYTE_ORDER_MAGIC).to_vec();
            body.extend_from_slice(&self.u16(1));
            body.extend_from_slice(&self.u16(0));
            body.extend_from_slice(&[0xFF; 8]); // section length unknown
            self.block(0x0A0D_0D0A, &body)
        }

        /// An interface, with options as (code, value).
        fn interface(&mut self, linktype: u16, options: &[(u16, &[u8])]) -> &mut Ng {
            let mut body = self.u16(linktype).to_vec();
            body.extend_from_slice(&[0, 0]);
            body.extend_from_slice(&self.u32(0x40000));
            for (code, value) in options {
                body.extend_from_slice(&self.u16(*code));
                body.extend_from_slice(&self.u16(value.len() as u16));
                body.extend_from_slice(value);
                body.resize(body.len().next_multiple_of(4), 0);
            }
            if !options.is_empty() {
                body.extend_from_slice(&[0; 4]);
            }
            self.block(BLOCK_IDB, &body)
        }

        fn packet(&mut self, interface: u32, ticks: u64, packet: &[u8]) -> &mut Ng {
            let mut body = self.u32(interface).to_vec();
            body.extend_from_slice(&self.u32((ticks >> 32) as u32));
            body.extend_from_slice(&self.u32(ticks as u32));
            body.extend_from_slice(&self.u32(packet.len() as u32));
            body.extend_from_slice(&self.u32(packet.len() as u32));
            body.extend_from_slice(packet);
            self.block(BLOCK_EPB, &body)
        }
    }

    fn pcap(big: bool, nanos: bool, linktype: u32) -> Vec<u8> {
        let magic = if nanos { PCAP_MAGIC_NS } else { PCAP_MAGIC_US };
        let u32b = |v: u32| {
            if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        };
        let u16b = |v: u16| {
            if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        };
        let mut out = u32b(magic).to_vec();
        out.extend_from_slice(&u16b(2));
        out.extend_from_slice(&u16b(4));
        out.extend_from_slice(&[0; 8]);
        out.extend_from_slice(&u32b(0x40000));
        out.extend_from_slice(&u32b(linktype));
        out
    }

    fn pcap_record(out: &mut Vec<u8>, big: bool, seconds: u32, fraction: u32, packet: &[u8]) {
        let u32b = |v: u32| {
            if big {
                v.to_be_bytes()
            } else {
                v.to_le_bytes()
            }
        };
        for v in [seconds, fraction, packet.len() as u32, packet.len() as u32] {
            out.extend_from_slice(&u32b(v));
        }
        out.extend_from_slice(packet);
    }

    type Read = (Vec<Result<Sighting, PcapError>>, Vec<(SkipReason, u64)>);

    fn read(bytes: &[u8], skip_bad: bool) -> Read {
        let mut reader =
            PcapReader::new(bytes, Path::new("cap.pcapng"), "sniffer".into(), skip_bad).unwrap();
        let items: Vec<_> = reader.by_ref().collect();
        (items, reader.skipped().collect())
    }

    fn sightings(bytes: &[u8]) -> (Vec<Sighting>, Vec<(SkipReason, u64)>) {
        let (items, skipped) = read(bytes, false);
        (items.into_iter().map(Result::unwrap).collect(), skipped)
    }

    fn open_error(bytes: &[u8]) -> String {
        PcapReader::new(bytes, Path::new("x.pcapng"), "p".into(), false)
            .err()
            .expect("refused")
            .to_string()
    }

    #[test]
    fn every_linktype_gives_sightings_from_legacy_and_extended_adverts() {
        let mut ng = Ng::new(false);
        ng.interface(201, &[])
            .interface(251, &[])
            .interface(256, &[])
            .interface(272, &[]);
        let cases: [(u32, Vec<u8>, Option<i16>); 8] = [
            (0, h4_event(&legacy_report(&IBEACON_AD, -61)), Some(-61)),
            (0, h4_event(&extended_report(&IBEACON_AD, -62)), Some(-62)),
            (1, legacy(ADV_NONCONN_IND, &IBEACON_AD), None),
            (1, aux_adv_ind(&IBEACON_AD), None),
            (
                2,
                with_phdr(-63, PHDR_GOOD, &legacy(ADV_IND, &IBEACON_AD)),
                Some(-63),
            ),
            // Auxiliary advertising on a secondary channel (PDU type 1).
            (
                2,
                with_phdr(-64, PHDR_GOOD | 0x0080, &aux_adv_ind(&IBEACON_AD)),
                Some(-64),
            ),
            (
                3,
                nordic(0x02, 0x01, 65, &legacy(SCAN_RSP, &IBEACON_AD)),
                Some(-65),
            ),
            (
                3,
                nordic(0x02, 0x01, 66, &aux_adv_ind(&IBEACON_AD)),
                Some(-66),
            ),
        ];
        for (i, (interface, packet, _)) in cases.iter().enumerate() {
            ng.packet(*interface, T0_US + i as u64, packet);
        }
        let (s, skipped) = sightings(&ng.out);
        let rssi: Vec<i16> = s.iter().map(|s| s.rssi).collect();
        let expected: Vec<i16> = cases.iter().filter_map(|c| c.2).collect();
        assert_eq!(rssi, expected);
        assert!(
            s.iter()
                .all(|s| s.advertiser == beacon() && s.tx_power == Some(-59))
        );
        assert!(s.iter().all(|s| &*s.observer == "sniffer"));
        assert_eq!(s[0].t, T0);
        assert_eq!(s[1].t, 1_700_000_000.250_001);
        // Linktype 251 has no signal strength: its iBeacons are counted.
        assert_eq!(skipped, [(SkipReason::NoRssi, 2)]);
    }

    #[test]
    fn coded_phy_packets_skip_the_coding_indicator() {
        let mut coded = legacy(ADV_NONCONN_IND, &IBEACON_AD);
        coded.insert(4, 0x01); // CI: S2
        let mut ng = Ng::new(false);
        ng.interface(256, &[]).interface(272, &[]);
        ng.packet(0, T0_US, &with_phdr(-70, PHDR_GOOD | 0x8000, &coded));
        ng.packet(1, T0_US, &nordic(0x02, 0x01 | 0x20, 71, &coded));
        let (s, skipped) = sightings(&ng.out);
        assert_eq!(s.iter().map(|s| s.rssi).collect::<Vec<_>>(), [-70, -71]);
        assert!(skipped.is_empty(), "{skipped:?}");
    }

    #[test]
    fn what_is_not_an_ibeacon_advert_is_skipped_and_counted() {
        let mut ng = Ng::new(false);
        ng.interface(256, &[])
            .interface(272, &[])
            .interface(1, &[]) // Ethernet
            .interface(201, &[]);
        let data_pdu = ll(0x5065_4A3B, 0x01, &[0x00]);
        // not_advertising: a data channel PDU, a PHDR data PDU type, a Nordic data packet.
        ng.packet(0, T0_US, &with_phdr(-60, PHDR_GOOD, &data_pdu));
        ng.packet(
            0,
            T0_US,
            &with_phdr(-60, PHDR_GOOD | 0x0100, &legacy(ADV_IND, &IBEACON_AD)),
        );
        ng.packet(1, T0_US, &nordic(0x06, 0x01, 60, &data_pdu));
        // no_adv_data: SCAN_REQ and ADV_DIRECT_IND.
        ng.packet(
            0,
            T0_US,
            &with_phdr(-60, PHDR_GOOD, &legacy(0x3, &ADV_ADDRESS)),
        );
        ng.packet(
            1,
            T0_US,
            &nordic(0x02, 0x01, 60, &legacy(0x1, &ADV_ADDRESS)),
        );
        // bad_crc, by either header.
        ng.packet(
            0,
            T0_US,
            &with_phdr(-60, PHDR_GOOD & !0x0800, &legacy(ADV_IND, &IBEACON_AD)),
        );
        ng.packet(
            1,
            T0_US,
            &nordic(0x02, 0x00, 60, &legacy(ADV_IND, &IBEACON_AD)),
        );
        // not_ibeacon
        ng.packet(
            1,
            T0_US,
            &nordic(0x02, 0x01, 60, &legacy(ADV_IND, &CONTINUITY_AD)),
        );
        // malformed_pdu: a length byte past the packet, a Nordic length that disagrees.
        let mut long = legacy(ADV_IND, &IBEACON_AD);
        long[5] = 0xF0;
        ng.packet(0, T0_US, &with_phdr(-60, PHDR_GOOD, &long));
        let mut bad_nordic = nordic(0x02, 0x01, 60, &legacy(ADV_IND, &IBEACON_AD));
        bad_nordic.pop();
        ng.packet(1, T0_US, &bad_nordic);
        // other_linktype
        ng.packet(2, T0_US, &[0; 60]);
        // not_an_event: an HCI command; other_event: Command Complete.
        ng.packet(3, T0_US, &[0, 0, 0, 0, 0x01, 0x0C, 0x20, 0x02, 0x01, 0x00]);
        ng.packet(3, T0_US, &h4_event(&[0x0E, 0x04, 0x01, 0x0C, 0x20, 0x00]));
        // no_timestamp: a simple packet block; name resolution and statistics pass unseen.
        let spb = [ng.u32(10).to_vec(), vec![0; 10]].concat();
        ng.block(BLOCK_SIMPLE_PACKET, &spb);
        ng.block(4, &[0; 4]);
        ng.block(5, &[0; 12]);
        // And a good one after all of it.
        ng.packet(
            1,
            T0_US,
            &nordic(0x02, 0x01, 60, &legacy(ADV_IND, &IBEACON_AD)),
        );
        let (s, skipped) = sightings(&ng.out);
        assert_eq!(s.len(), 1);
        assert_eq!(
            skipped,
            [
                (SkipReason::NotAnEvent, 1),
                (SkipReason::OtherEvent, 1),
                (SkipReason::NotIBeacon, 1),
                (SkipReason::NotAdvertising, 3),
                (SkipReason::NoAdvData, 2),
                (SkipReason::BadCrc, 2),
                (SkipReason::MalformedPdu, 2),
                (SkipReason::OtherLinktype, 1),
                (SkipReason::NoTimestamp, 1),
            ]
        );
    }

    #[test]
    fn timestamps_follow_if_tsresol_and_if_tsoffset_in_either_byte_order() {
        for big in [false, true] {
            let mut ng = Ng::new(big);
            let offset = if big {
                (-100i64).to_be_bytes()
            } else {
                (-100i64).to_le_bytes()
            };
            ng.interface(272, &[(OPT_IF_TSRESOL, &[9]), (2, b"nRF Sniffer")])
                .interface(
                    272,
                    &[(OPT_IF_TSRESOL, &[0x80 | 10]), (OPT_IF_TSOFFSET, &offset)],
                )
                .interface(272, &[]);
            let packet = nordic(0x02, 0x01, 60, &legacy(ADV_IND, &IBEACON_AD));
            ng.packet(0, T0_US * 1000 + 500, &packet);
            ng.packet(1, 1_700_000_000 * 1024 + 256, &packet);
            ng.packet(2, T0_US, &packet);
            let (s, _) = sightings(&ng.out);
            let t: Vec<f64> = s.iter().map(|s| s.t).collect();
            assert!((t[0] - 1_700_000_000.250_000_5).abs() < 1e-6, "{t:?}");
            assert_eq!(t[1], 1_699_999_900.25, "binary resolution, offset -100 s");
            assert_eq!(t[2], T0, "microseconds by default");
        }
    }

    #[test]
    fn a_new_section_sets_its_own_byte_order_and_interfaces() {
        let packet = nordic(0x02, 0x01, 60, &legacy(ADV_IND, &IBEACON_AD));
        let mut first = Ng::new(false);
        first.interface(272, &[]).packet(0, T0_US, &packet);
        let mut second = Ng::new(true);
        // Interface 0 of the second section is Ethernet: its packet is not Nordic.
        second.interface(1, &[]).packet(0, T0_US, &packet);
        let mut bytes = first.out.clone();
        bytes.extend_from_slice(&second.out);
        let (s, skipped) = sightings(&bytes);
        assert_eq!(s.len(), 1);
        assert_eq!(skipped, [(SkipReason::OtherLinktype, 1)]);
    }

    #[test]
    fn classic_pcap_in_both_byte_orders_and_resolutions() {
        let packet = with_phdr(-58, PHDR_GOOD, &legacy(ADV_NONCONN_IND, &IBEACON_AD));
        for (big, nanos) in [(false, false), (true, false), (false, true), (true, true)] {
            let mut file = pcap(big, nanos, 256);
            let fraction = if nanos { 250_000_000 } else { 250_000 };
            pcap_record(&mut file, big, 1_700_000_000, fraction, &packet);
            pcap_record(&mut file, big, 1_700_000_001, fraction, &packet);
            let (s, skipped) = sightings(&file);
            let t: Vec<f64> = s.iter().map(|s| s.t).collect();
            assert_eq!(t, [T0, T0 + 1.0], "big {big} nanos {nanos}");
            assert_eq!(s[0].rssi, -58);
            assert!(skipped.is_empty());
        }
    }

    #[test]
    fn a_corrupt_block_is_skipped_and_reading_goes_on() {
        let packet = nordic(0x02, 0x01, 60, &legacy(ADV_IND, &IBEACON_AD));
        let mut ng = Ng::new(false);
        ng.interface(272, &[]);
        // A packet naming an interface the section lacks, one longer than its
        // block, and an interface whose option runs past its block.
        ng.packet(7, T0_US, &packet);
        let start = ng.out.len();
        ng.packet(0, T0_US, &packet);
        ng.out[start + 20..start + 24].copy_from_slice(&500u32.to_le_bytes());
        ng.block(
            BLOCK_IDB,
            &[0x10, 0x01, 0, 0, 0, 0, 0, 0, 0x09, 0x00, 0x40, 0x00],
        );
        ng.packet(1, T0_US, &packet); // on the unreadable interface
        ng.packet(0, T0_US + 1, &packet);
        let (s, skipped) = sightings(&ng.out);
        assert_eq!(s.len(), 1);
        assert_eq!(s[0].t, 1_700_000_000.250_001);
        assert_eq!(skipped, [(SkipReason::CorruptBlock, 4)]);
    }

    #[test]
    fn a_truncated_last_block_is_an_error_naming_block_and_offset() {
        let packet = nordic(0x02, 0x01, 60, &legacy(ADV_IND, &IBEACON_AD));
        let mut ng = Ng::new(false);
        ng.interface(272, &[]).packet(0, T0_US, &packet);
        let offset = ng.out.len();
        ng.packet(0, T0_US + 1, &packet);
        ng.out.truncate(ng.out.len() - 10);
        let (items, _) = read(&ng.out, false);
        assert_eq!(items.len(), 2);
        let err = items[1].as_ref().unwrap_err().to_string();
        assert!(
            err.contains(&format!("block 4 at byte {offset} is truncated")),
            "{err}"
        );
        assert!(err.contains("--skip-bad"), "{err}");
        let (items, skipped) = read(&ng.out, true);
        assert_eq!(items.len(), 1);
        assert_eq!(skipped, [(SkipReason::TruncatedRecord, 1)]);

        // Cut in a pcap record header too.
        let mut file = pcap(false, false, 272);
        pcap_record(&mut file, false, 1, 0, &packet);
        let offset = file.len();
        file.extend_from_slice(&[0; 5]);
        let (items, _) = read(&file, false);
        let err = items[1].as_ref().unwrap_err().to_string();
        assert!(
            err.contains(&format!(
                "record 2 at byte {offset} is truncated (5 of 16 bytes)"
            )),
            "{err}"
        );
    }

    #[test]
    fn a_broken_frame_stops_with_an_error() {
        let packet = nordic(0x02, 0x01, 60, &legacy(ADV_IND, &IBEACON_AD));
        let mut ng = Ng::new(false);
        ng.interface(272, &[]).packet(0, T0_US, &packet);
        let offset = ng.out.len();
        ng.packet(0, T0_US, &packet);
        let mut mismatched = ng.out.clone();
        let end = mismatched.len();
        mismatched[end - 4] ^= 0x10;
        let (items, _) = read(&mismatched, true);
        let err = items.last().unwrap().as_ref().unwrap_err().to_string();
        assert!(
            err.contains(&format!("block 4 at byte {offset}: ends with a length")),
            "{err}"
        );
        assert!(err.contains("corrupt from here on"), "{err}");

        let mut odd = ng.out.clone();
        odd[offset + 4] = 0x0D;
        let (items, _) = read(&odd, true);
        let err = items.last().unwrap().as_ref().unwrap_err().to_string();
        assert!(err.contains("not a multiple of 4"), "{err}");

        let mut file = pcap(false, false, 272);
        file.extend_from_slice(&[0, 0, 0, 0, 0, 0, 0, 0, 0xFF, 0xFF, 0xFF, 0xFF, 0, 0, 0, 0]);
        let (items, _) = read(&file, true);
        let err = items[0].as_ref().unwrap_err().to_string();
        assert!(
            err.contains("record 1 at byte 24: claims a 4294967295-byte packet"),
            "{err}"
        );
    }

    #[test]
    fn refuses_files_that_are_not_pcap_of_a_ble_linktype() {
        assert!(open_error(b"{\"t\":1}\n").contains("it starts with 7b227422"));
        assert!(open_error(b"").contains("the file is empty"));
        assert!(open_error(&pcap(false, false, 1)).contains("linktype 1 is not Bluetooth LE"));
        let mut v3 = pcap(true, false, 272);
        v3[5] = 3;
        assert!(open_error(&v3).contains("pcap version 3"));
        assert!(open_error(&pcap(false, false, 272)[..20]).contains("cut off after 20"));
        // A section header whose byte-order magic is neither order.
        let mut ng = Ng::new(false);
        ng.out[8..12].copy_from_slice(&[0x1A, 0x2B, 0x3C, 0x4E]);
        let err = open_error(&ng.out);
        assert!(err.contains("byte-order magic is 1a2b3c4e"), "{err}");
        let mut v2 = Ng::new(true);
        v2.out[13] = 2;
        assert!(open_error(&v2.out).contains("pcapng version 2.0"));
    }

    proptest! {
        #[test]
        fn arbitrary_bytes_after_a_valid_header_never_panic(
            linktype in prop::sample::select(vec![201u16, 251, 256, 272]),
            classic: bool,
            body in prop::collection::vec(any::<u8>(), 0..400),
            skip_bad: bool,
        ) {
            let mut file = if classic {
                pcap(false, false, u32::from(linktype))
            } else {
                let mut ng = Ng::new(false);
                ng.interface(linktype, &[]);
                ng.out
            };
            file.extend_from_slice(&body);
            let (items, _) = read(&file, skip_bad);
            let errors = items.iter().filter(|i| i.is_err()).count();
            prop_assert!(errors <= 1);
            if errors == 1 {
                prop_assert!(items.last().unwrap().is_err());
            }
        }

        #[test]
        fn mutated_captures_never_panic(
            flips in prop::collection::vec((any::<prop::sample::Index>(), any::<u8>()), 1..8),
            cut in any::<prop::sample::Index>(),
            skip_bad: bool,
        ) {
            let mut ng = Ng::new(false);
            ng.interface(201, &[(OPT_IF_TSRESOL, &[9])]).interface(256, &[]).interface(272, &[]);
            ng.packet(0, T0_US, &h4_event(&extended_report(&IBEACON_AD, -60)));
            ng.packet(1, T0_US, &with_phdr(-60, PHDR_GOOD, &aux_adv_ind(&IBEACON_AD)));
            ng.packet(2, T0_US, &nordic(0x02, 0x01, 60, &legacy(ADV_IND, &IBEACON_AD)));
            let mut file = ng.out;
            for (at, byte) in flips {
                let i = at.index(file.len());
                file[i] = byte;
            }
            file.truncate(cut.index(file.len() + 1));
            if let Ok(mut reader) = PcapReader::new(&file[..], Path::new("m"), "m".into(), skip_bad) {
                let errors = reader.by_ref().filter(Result::is_err).count();
                prop_assert!(errors <= 1);
            }
        }
    }
}
