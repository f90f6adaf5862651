//! iBeacon frames inside BLE manufacturer-specific data.
//!
//! Layout of the manufacturer data as BlueZ/btleplug hand it over (company id
//! first, little-endian, as on the air):
//!
//! ```text
//! 4C 00 | 02 15 | 16-byte proximity UUID | major (BE u16) | minor (BE u16) | measured power (i8)
//! ```
//!
//! btleplug already splits the company id off into a map key, so [`parse_payload`]
//! takes the bytes after it; [`parse_manufacturer_data`] takes the whole field,
//! and [`find_in_ad`] searches an advert's AD structures for it (btsnoop and
//! pcap captures and other raw sources).

use uuid::Uuid;

use crate::sighting::BeaconId;

/// Apple's Bluetooth SIG company identifier, which iBeacon frames carry.
pub(crate) const APPLE_COMPANY_ID: u16 = 0x004C;

/// The AD type of manufacturer-specific data, where iBeacon frames travel.
pub(crate) const AD_MANUFACTURER_SPECIFIC: u8 = 0xFF;

/// The iBeacon type (0x02) and remaining length (0x15 = 21 bytes).
const IBEACON_PREFIX: [u8; 2] = [0x02, 0x15];

/// Length of the payload after the company id: prefix, UUID, major, minor, power.
pub(crate) const PAYLOAD_LEN: usize = 2 + 16 + 2 + 2 + 1;

/// What an iBeacon frame says about its sender.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct IBeacon {
    pub id: BeaconId,
    /// Calibrated RSSI at 1 m, in dBm.
    pub measured_power: i8,
}

/// Parses the manufacturer data of an advert, company id included.
/// Returns `None` for anything that is not an Apple iBeacon frame.
pub fn parse_manufacturer_data(data: &[u8]) -> Option<IBeacon> {
    let (company, payload) = data.split_first_chunk::<2>()?;
    if u16::from_le_bytes(*company) != APPLE_COMPANY_ID {
        return None;
    }
    parse_payload(payload)
}

/// Parses the bytes that follow the Apple company id. Apple uses the same company
/// id for many other frames (Continuity, AirDrop, Find My...), so the 0x02 0x15
/// prefix and the exact length are both required.
pub fn parse_payload(payload: &[u8]) -> Option<IBeacon> {
    let frame: &[u8; PAYLOAD_LEN] = payload.try_into().ok()?;
    if frame[..2] != IBEACON_PREFIX {
        return None;
    }
    let uuid = Uuid::from_bytes(frame[2..18].try_into().ok()?);
    let major = u16::from_be_bytes([frame[18], frame[19]]);
    let minor = u16::from_be_bytes([frame[20], frame[21]]);
    Some(IBeacon {
        id: BeaconId { uuid, major, minor },
        measured_power: frame[22] as i8,
    })
}

/// The first iBeacon frame among an advert's AD structures
/// (`length | type | data`; a zero length ends the list, and a structure that
/// runs past the end ends the search).
pub(crate) fn find_in_ad(mut ad: &[u8]) -> Option<IBeacon> {
    while let Some((&len, rest)) = ad.split_first() {
        let len = usize::from(len);
        if len == 0 || len > rest.len() {
            return None;
        }
        let (structure, next) = rest.split_at(len);
        if structure[0] == AD_MANUFACTURER_SPECIFIC
            && let Some(beacon) = parse_manufacturer_data(&structure[1..])
        {
            return Some(beacon);
        }
        ad = next;
    }
    None
}

/// Builds the manufacturer data (company id included) of an iBeacon frame; the
/// inverse of [`parse_manufacturer_data`], used by `record` to write btsnoop-style
/// raw frames and by tests.
pub fn encode_manufacturer_data(beacon: &IBeacon) -> [u8; 2 + PAYLOAD_LEN] {
    let mut out = [0u8; 2 + PAYLOAD_LEN];
    out[..2].copy_from_slice(&APPLE_COMPANY_ID.to_le_bytes());
    out[2..4].copy_from_slice(&IBEACON_PREFIX);
    out[4..20].copy_from_slice(beacon.id.uuid.as_bytes());
    out[20..22].copy_from_slice(&beacon.id.major.to_be_bytes());
    out[22..24].copy_from_slice(&beacon.id.minor.to_be_bytes());
    out[24] = beacon.measured_power as u8;
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    /// A frame as an Estimote/Kontakt-style beacon sends it: UUID
    /// B9407F30-F5F8-466E-AFF9-25556B57FE6D, major 1, minor 3001, -59 dBm at 1 m.
    const REAL_FRAME: [u8; 25] = [
        0x4C, 0x00, 0x02, 0x15, 0xB9, 0x40, 0x7F, 0x30, 0xF5, 0xF8, 0x46, 0x6E, 0xAF, 0xF9, 0x25,
        0x55, 0x6B, 0x57, 0xFE, 0x6D, 0x00, 0x01, 0x0B, 0xB9, 0xC5,
    ];

    #[test]
    fn parses_a_real_ibeacon_frame() {
        let b = parse_manufacturer_data(&REAL_FRAME).expect("an iBeacon");
        assert_eq!(
            b.id.uuid,
            Uuid::parse_str("b9407f30-f5f8-466e-aff9-25556b57fe6d").unwrap()
        );
        assert_eq!(b.id.major, 1);
        assert_eq!(b.id.minor, 3001);
        assert_eq!(b.measured_power, -59);
        assert_eq!(parse_payload(&REAL_FRAME[2..]), Some(b));
    }

    #[test]
    fn encode_is_the_inverse_of_parse() {
        let b = parse_manufacturer_data(&REAL_FRAME).unwrap();
        assert_eq!(encode_manufacturer_data(&b), REAL_FRAME);
    }

    #[test]
    fn ignores_other_vendors_and_other_apple_frames() {
        let mut other_vendor = REAL_FRAME;
        other_vendor[0] = 0x59; // Nordic Semiconductor
        assert_eq!(parse_manufacturer_data(&other_vendor), None);

        // Apple Continuity "nearby info" frame: company id 0x004C, type 0x10.
        let continuity = [0x4C, 0x00, 0x10, 0x05, 0x01, 0x18, 0x44, 0x1C, 0x2D];
        assert_eq!(parse_manufacturer_data(&continuity), None);

        let mut wrong_len_byte = REAL_FRAME;
        wrong_len_byte[3] = 0x14;
        assert_eq!(parse_manufacturer_data(&wrong_len_byte), None);
    }

    #[test]
    fn ignores_short_and_long_frames() {
        for len in 0..REAL_FRAME.len() {
            assert_eq!(
                parse_manufacturer_data(&REAL_FRAME[..len]),
                None,
                "len {len}"
            );
        }
        let mut long = REAL_FRAME.to_vec();
        long.push(0);
        assert_eq!(parse_manufacturer_data(&long), None);
    }

    #[test]
    fn finds_the_frame_among_ad_structures() {
        // Flags, a 16-bit service UUID list, then the frame.
        let mut ad = vec![
            0x02,
            0x01,
            0x06,
            0x03,
            0x03,
            0xAA,
            0xFE,
            26,
            AD_MANUFACTURER_SPECIFIC,
        ];
        ad.extend_from_slice(&REAL_FRAME);
        let b = find_in_ad(&ad).expect("an iBeacon");
        assert_eq!(b.id.minor, 3001);
        // Cut one byte short: the last structure runs past the end.
        assert_eq!(find_in_ad(&ad[..ad.len() - 1]), None);
        // A zero length ends the list before the frame.
        let mut ended = vec![0x00];
        ended.extend_from_slice(&ad);
        assert_eq!(find_in_ad(&ended), None);
        assert_eq!(find_in_ad(&[]), None);
    }

    proptest! {
        #[test]
        fn arbitrary_bytes_never_panic(data in proptest::collection::vec(any::<u8>(), 0..64)) {
            let _ = parse_manufacturer_data(&data);
            let _ = parse_payload(&data);
            let _ = find_in_ad(&data);
        }

        #[test]
        fn any_ibeacon_round_trips(uuid in any::<[u8; 16]>(), major in any::<u16>(),
                                   minor in any::<u16>(), power in any::<i8>()) {
            let b = IBeacon { id: BeaconId { uuid: Uuid::from_bytes(uuid), major, minor }, measured_power: power };
            prop_assert_eq!(parse_manufacturer_data(&encode_manufacturer_data(&b)), Some(b));
        }
    }
}
