//! The Bluetooth LE linktypes of pcap and pcapng captures: from one packet to
//! its adverts.
//!
//! | linktype | name                          | written by                                  | RSSI from                         |
//! |----------|-------------------------------|---------------------------------------------|-----------------------------------|
//! | 201      | `BLUETOOTH_HCI_H4_WITH_PHDR`  | Wireshark/tcpdump on a Linux `bluetooth0`   | each advertising report           |
//! | 251      | `BLUETOOTH_LE_LL`             | sniffers without radio metadata             | none: iBeacons count as `no_rssi` |
//! | 256      | `BLUETOOTH_LE_LL_WITH_PHDR`   | Ubertooth, Sniffle, other SDR sniffers      | the signal power, when flagged valid |
//! | 272      | `NORDIC_BLE`                  | nRF Sniffer for Bluetooth LE (Wireshark)    | the Nordic header's RSSI sample   |
//!
//! HCI packets go to `Adverts::hci_event` (LE Advertising Report and LE
//! Extended Advertising Report events). Link-layer packets are decoded here:
//! an advertising physical channel PDU (access address 0x8E89BED6) of type
//! ADV_IND, ADV_NONCONN_IND, ADV_SCAN_IND or SCAN_RSP carries its AdvData after
//! the 6-byte advertiser address; the extended PDUs (type 7: ADV_EXT_IND,
//! AUX_ADV_IND, AUX_SCAN_RSP, AUX_SYNC_IND, AUX_CHAIN_IND) carry it after the
//! extended header, whose length is the low six bits of the payload's first
//! byte. On the LE Coded PHY a coding indicator byte follows the access address.
//! Packets a sniffer marks as failing their CRC are skipped, as are data channel
//! PDUs and PDUs without advertising data; every skip is counted.

use super::adverts::{Adverts, SkipReason};
use super::btsnoop::H4_EVENT;

/// The access address of every advertising physical channel PDU.
pub(super) const ADVERTISING_ACCESS_ADDRESS: u32 = 0x8E89_BED6;
pub(super) const ADV_IND: u8 = 0x0;
pub(super) const ADV_NONCONN_IND: u8 = 0x2;
pub(super) const SCAN_RSP: u8 = 0x4;
const ADV_SCAN_IND: u8 = 0x6;
/// ADV_EXT_IND on the primary channels, AUX_* on the secondary ones.
const ADV_EXT: u8 = 0x7;
/// The advertiser address that starts a legacy advertising PDU's payload.
const ADV_A_LEN: usize = 6;

/// `BLUETOOTH_LE_LL_WITH_PHDR` pseudo-header: channel, signal, noise, access
/// address offenses, reference access address (4), flags (2).
const PHDR_LEN: usize = 10;
const PHDR_SIGNAL_VALID: u16 = 0x0002;
/// Bits 7-9: 0 advertising or data (told apart by access address), 1
/// auxiliary advertising, 2-6 data and isochronous.
const PHDR_PDU_TYPE: u16 = 0x0380;
const PHDR_CRC_CHECKED: u16 = 0x0400;
const PHDR_CRC_VALID: u16 = 0x0800;
/// Bits 14-15: 0 LE 1M, 1 LE 2M, 2 LE Coded.
const PHDR_PHY: u16 = 0xC000;
const PHY_CODED: u16 = 2;

/// Where the link-layer packet starts in a `NORDIC_BLE` packet, in every
/// header version: board id and a 6-byte header (or the 0xBEEF marker and a
/// 6-byte legacy header), then length, flags, channel, RSSI, event counter (2)
/// and timestamp (4).
const NORDIC_LL_START: usize = 17;
const NORDIC_FLAGS: usize = 8;
const NORDIC_RSSI: usize = 10;
const NORDIC_LEGACY_MARKER: [u8; 2] = [0xBE, 0xEF];
const NORDIC_CRC_OK: u8 = 0x01;
const NORDIC_PHY_CODED: u8 = 2;
/// Packet ids: an advertising PDU (protocol version 3), any PDU (earlier
/// versions: the access address tells) or a data PDU (version 3).
const NORDIC_EVENT_PACKET_ADVERTISING: u8 = 0x02;
const NORDIC_EVENT_PACKET_DATA: u8 = 0x06;

/// A linktype gangway decodes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Linktype {
    /// 201: H4 HCI packets after a 4-byte direction header.
    HciH4WithPhdr,
    /// 251: link-layer packets, access address first.
    LeLl,
    /// 256: link-layer packets after a 10-byte radio pseudo-header.
    LeLlWithPhdr,
    /// 272: nRF Sniffer packets.
    NordicBle,
}

impl Linktype {
    /// The linktypes gangway reads, for error messages.
    pub(crate) const SUPPORTED: &'static str = "201 (BLUETOOTH_HCI_H4_WITH_PHDR), 251 \
        (BLUETOOTH_LE_LL), 256 (BLUETOOTH_LE_LL_WITH_PHDR) and 272 (NORDIC_BLE)";

    pub(crate) fn from_code(code: u32) -> Option<Linktype> {
        match code {
            201 => Some(Linktype::HciH4WithPhdr),
            251 => Some(Linktype::LeLl),
            256 => Some(Linktype::LeLlWithPhdr),
            272 => Some(Linktype::NordicBle),
            _ => None,
        }
    }

    /// Hands the adverts of one packet heard at `t` to `adverts`, or counts
    /// why it has none.
    pub(super) fn decode(self, t: f64, packet: &[u8], adverts: &mut Adverts) {
        let decoded = match self {
            Linktype::HciH4WithPhdr => match packet.get(4..).and_then(<[u8]>::split_first) {
                Some((&H4_EVENT, event)) => return adverts.hci_event(t, event),
                Some(_) => Err(SkipReason::NotAnEvent),
                None => Err(SkipReason::MalformedEvent),
            },
            Linktype::LeLl => adv_data(packet, false).map(|ad| (None, ad)),
            Linktype::LeLlWithPhdr => with_phdr(packet),
            Linktype::NordicBle => nordic(packet),
        };
        match decoded {
            Ok((rssi, ad)) => adverts.advert(t, rssi, ad),
            Err(reason) => adverts.skip(reason),
        }
    }
}

/// The RSSI and AdvData of a `BLUETOOTH_LE_LL_WITH_PHDR` packet.
fn with_phdr(packet: &[u8]) -> Result<(Option<i16>, &[u8]), SkipReason> {
    let (phdr, ll) = packet
        .split_first_chunk::<PHDR_LEN>()
        .ok_or(SkipReason::MalformedPdu)?;
    let flags = u16::from_le_bytes([phdr[8], phdr[9]]);
    if (flags & PHDR_PDU_TYPE) >> 7 > 1 {
        return Err(SkipReason::NotAdvertising);
    }
    if flags & PHDR_CRC_CHECKED != 0 && flags & PHDR_CRC_VALID == 0 {
        return Err(SkipReason::BadCrc);
    }
    let coded = (flags & PHDR_PHY) >> 14 == PHY_CODED;
    let rssi = (flags & PHDR_SIGNAL_VALID != 0).then_some(i16::from(phdr[1] as i8));
    Ok((rssi, adv_data(ll, coded)?))
}

/// The RSSI and AdvData of a `NORDIC_BLE` packet (header versions 0 to 3, as
/// Wireshark's `nordic_ble` dissector reads them).
fn nordic(packet: &[u8]) -> Result<(Option<i16>, &[u8]), SkipReason> {
    if packet.len() < NORDIC_LL_START {
        return Err(SkipReason::MalformedPdu);
    }
    // (header length, payload length, protocol version, packet id)
    let (header_len, payload_len, version, id) = if packet[..2] == NORDIC_LEGACY_MARKER {
        (8, usize::from(packet[7]), 0, packet[2])
    } else {
        match packet[3] {
            // board id, header length, payload length, version, counter (2), id
            1 => (
                1 + usize::from(packet[1]),
                usize::from(packet[2]),
                1,
                packet[6],
            ),
            // board id, payload length (2), version, counter (2), id
            version => (
                7,
                usize::from(u16::from_le_bytes([packet[1], packet[2]])),
                version,
                packet[6],
            ),
        }
    };
    if header_len + payload_len != packet.len() {
        return Err(SkipReason::MalformedPdu);
    }
    let advertising =
        id == NORDIC_EVENT_PACKET_ADVERTISING || (id == NORDIC_EVENT_PACKET_DATA && version < 3);
    if !advertising {
        return Err(SkipReason::NotAdvertising);
    }
    let flags = packet[NORDIC_FLAGS];
    if flags & NORDIC_CRC_OK == 0 {
        return Err(SkipReason::BadCrc);
    }
    let coded = (flags >> 4) & 0x7 == NORDIC_PHY_CODED;
    // The radio's RSSI sample is the magnitude of a negative dBm value.
    let rssi = -i16::from(packet[NORDIC_RSSI]);
    Ok((Some(rssi), adv_data(&packet[NORDIC_LL_START..], coded)?))
}

/// The AdvData of a link-layer packet (access address, [coding indicator],
/// PDU header, payload, CRC), if it is an advertising PDU that carries any.
fn adv_data(ll: &[u8], coded: bool) -> Result<&[u8], SkipReason> {
    let (access_address, rest) = ll
        .split_first_chunk::<4>()
        .ok_or(SkipReason::MalformedPdu)?;
    if u32::from_le_bytes(*access_address) != ADVERTISING_ACCESS_ADDRESS {
        return Err(SkipReason::NotAdvertising);
    }
    let rest = if coded {
        rest.get(1..).ok_or(SkipReason::MalformedPdu)?
    } else {
        rest
    };
    let [header, len, rest @ ..] = rest else {
        return Err(SkipReason::MalformedPdu);
    };
    let payload = rest
        .get(..usize::from(*len))
        .ok_or(SkipReason::MalformedPdu)?;
    match header & 0x0F {
        ADV_IND | ADV_NONCONN_IND | SCAN_RSP | ADV_SCAN_IND => {
            payload.get(ADV_A_LEN..).ok_or(SkipReason::MalformedPdu)
        }
        ADV_EXT => {
            let (&ext_header, rest) = payload.split_first().ok_or(SkipReason::MalformedPdu)?;
            rest.get(usize::from(ext_header & 0x3F)..)
                .ok_or(SkipReason::MalformedPdu)
        }
        _ => Err(SkipReason::NoAdvData),
    }
}
