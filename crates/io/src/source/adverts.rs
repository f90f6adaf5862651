//! From the advertising data in a binary capture to sightings: what the btsnoop
//! and pcap readers share.
//!
//! Both readers hand each record's adverts (an RSSI if the capture has one, and
//! the AD structures) to `Adverts`, which keeps the sightings found and counts
//! everything else by [`SkipReason`], so a capture's closing `skipped=…` line
//! reads the same whatever the format. HCI LE (Extended) Advertising Report
//! events, which btsnoop captures and pcap's H4 linktype both carry, are
//! decoded here too (`Adverts::hci_event`).

use std::collections::VecDeque;
use std::fmt;
use std::sync::Arc;

use super::ibeacon;
use crate::sighting::Sighting;

pub(super) const HCI_EVENT_LE_META: u8 = 0x3E;
pub(super) const LE_ADVERTISING_REPORT: u8 = 0x02;
const LE_EXTENDED_ADVERTISING_REPORT: u8 = 0x0D;
/// The RSSI value a controller reports when it has none.
pub(super) const RSSI_UNAVAILABLE: i8 = 127;

/// Why a record or an advert gave no sighting.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub(crate) enum SkipReason {
    /// Commands, ACL/SCO/ISO data, monitor notes and index records (per record).
    NotAnEvent,
    /// HCI events other than LE Meta (per record).
    OtherEvent,
    /// LE Meta subevents other than the two advertising reports (per record).
    OtherLeSubevent,
    /// An event whose length fields disagree with its size (per record).
    MalformedEvent,
    /// An iBeacon heard without an RSSI: 127 in an HCI report, or a link-layer
    /// capture with no signal strength (per advert).
    NoRssi,
    /// An advert with no iBeacon frame: other vendors, Apple Continuity, Eddystone… (per advert).
    NotIBeacon,
    /// The last record was cut short (only counted with `skip_bad`).
    TruncatedRecord,
    /// Link-layer packets that are not advertising PDUs (data channel PDUs,
    /// sniffer control messages) (per packet).
    NotAdvertising,
    /// Advertising PDUs that carry no advertising data: SCAN_REQ, CONNECT_IND,
    /// ADV_DIRECT_IND… (per packet).
    NoAdvData,
    /// A link-layer packet the sniffer marked as received with a bad CRC (per packet).
    BadCrc,
    /// A link-layer packet or sniffer header whose lengths disagree with its size (per packet).
    MalformedPdu,
    /// Packets of a linktype gangway does not decode (per packet).
    OtherLinktype,
    /// pcapng simple packet blocks, which carry no timestamp (per block).
    NoTimestamp,
    /// pcapng blocks whose framing is sound but whose body is not (per block).
    CorruptBlock,
}

impl SkipReason {
    /// Every reason, in declaration order: a reason's discriminant is its index
    /// here and in [`SkipCounts`].
    pub(crate) const ALL: [SkipReason; 14] = [
        SkipReason::NotAnEvent,
        SkipReason::OtherEvent,
        SkipReason::OtherLeSubevent,
        SkipReason::MalformedEvent,
        SkipReason::NoRssi,
        SkipReason::NotIBeacon,
        SkipReason::TruncatedRecord,
        SkipReason::NotAdvertising,
        SkipReason::NoAdvData,
        SkipReason::BadCrc,
        SkipReason::MalformedPdu,
        SkipReason::OtherLinktype,
        SkipReason::NoTimestamp,
        SkipReason::CorruptBlock,
    ];

    pub(crate) fn as_str(self) -> &'static str {
        match self {
            SkipReason::NotAnEvent => "not_an_event",
            SkipReason::OtherEvent => "other_event",
            SkipReason::OtherLeSubevent => "other_le_subevent",
            SkipReason::MalformedEvent => "malformed_event",
            SkipReason::NoRssi => "no_rssi",
            SkipReason::NotIBeacon => "not_ibeacon",
            SkipReason::TruncatedRecord => "truncated_record",
            SkipReason::NotAdvertising => "not_advertising",
            SkipReason::NoAdvData => "no_adv_data",
            SkipReason::BadCrc => "bad_crc",
            SkipReason::MalformedPdu => "malformed_pdu",
            SkipReason::OtherLinktype => "other_linktype",
            SkipReason::NoTimestamp => "no_timestamp",
            SkipReason::CorruptBlock => "corrupt_block",
        }
    }
}

impl fmt::Display for SkipReason {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

/// How many records or adverts were skipped, by reason.
#[derive(Clone, Debug, Default)]
pub(crate) struct SkipCounts([u64; SkipReason::ALL.len()]);

impl SkipCounts {
    pub(crate) fn add(&mut self, reason: SkipReason) {
        self.0[reason as usize] += 1;
    }

    /// The non-zero counts, in [`SkipReason::ALL`] order.
    pub(crate) fn iter(&self) -> impl Iterator<Item = (SkipReason, u64)> + '_ {
        SkipReason::ALL
            .iter()
            .zip(self.0)
            .filter(|(_, n)| *n > 0)
            .map(|(r, n)| (*r, n))
    }
}

/// The sightings decoded from a capture and not yet returned, and the skip
/// counts; every sighting is attributed to one observer, since a capture does
/// not name the host that made it.
pub(super) struct Adverts {
    observer: Arc<str>,
    pending: VecDeque<Sighting>,
    skipped: SkipCounts,
}

impl Adverts {
    pub(super) fn new(observer: Arc<str>) -> Adverts {
        Adverts {
            observer,
            pending: VecDeque::new(),
            skipped: SkipCounts::default(),
        }
    }

    pub(super) fn skip(&mut self, reason: SkipReason) {
        self.skipped.add(reason);
    }

    pub(super) fn skipped(&self) -> &SkipCounts {
        &self.skipped
    }

    pub(super) fn pop(&mut self) -> Option<Sighting> {
        self.pending.pop_front()
    }

    /// One advert heard at `t` with `rssi` (if the capture has one) carrying the
    /// AD structures `ad`: a sighting if they hold an iBeacon frame.
    pub(super) fn advert(&mut self, t: f64, rssi: Option<i16>, ad: &[u8]) {
        let Some(beacon) = ibeacon::find_in_ad(ad) else {
            return self.skip(SkipReason::NotIBeacon);
        };
        let Some(rssi) = rssi else {
            return self.skip(SkipReason::NoRssi);
        };
        self.pending.push_back(Sighting {
            advertiser_mac: None,
            t,
            observer: self.observer.clone(),
            advertiser: beacon.id,
            tx_power: Some(beacon.measured_power),
            rssi,
        });
    }

    /// An HCI event received at `t`: every report of an LE (Extended)
    /// Advertising Report event is an advert; any other event is skipped.
    pub(super) fn hci_event(&mut self, t: f64, event: &[u8]) {
        match le_reports(event) {
            Ok(reports) => {
                for (rssi, data) in reports {
                    self.advert(
                        t,
                        (rssi != RSSI_UNAVAILABLE).then_some(i16::from(rssi)),
                        data,
                    );
                }
            }
            Err(reason) => self.skip(reason),
        }
    }
}

/// The `(rssi, ad_data)` of every report of an LE (Extended) Advertising
/// Report event; any other event is a [`SkipReason`]. A malformed event
/// reports nothing, not even its well-formed first reports, since its length
/// fields cannot be trusted.
fn le_reports(event: &[u8]) -> Result<Vec<(i8, &[u8])>, SkipReason> {
    let (&code, rest) = event.split_first().ok_or(SkipReason::MalformedEvent)?;
    let (&len, params) = rest.split_first().ok_or(SkipReason::MalformedEvent)?;
    if code != HCI_EVENT_LE_META {
        return Err(SkipReason::OtherEvent);
    }
    let params = params
        .get(..usize::from(len))
        .ok_or(SkipReason::MalformedEvent)?;
    let (&subevent, params) = params.split_first().ok_or(SkipReason::MalformedEvent)?;
    // Fixed bytes of one report before its data length byte, and after its data.
    let (before_len, after_data) = match subevent {
        // event type, address type, address
        LE_ADVERTISING_REPORT => (1 + 1 + 6, 1),
        // event type (2), address type, address, primary and secondary PHY, SID,
        // TX power, RSSI, periodic interval (2), direct address type, direct address
        LE_EXTENDED_ADVERTISING_REPORT => (2 + 1 + 6 + 1 + 1 + 1 + 1 + 1 + 2 + 1 + 6, 0),
        _ => return Err(SkipReason::OtherLeSubevent),
    };
    let (&count, mut reports) = params.split_first().ok_or(SkipReason::MalformedEvent)?;
    let mut found: Vec<(i8, &[u8])> = Vec::with_capacity(usize::from(count));
    for _ in 0..count {
        let fixed = reports
            .get(..before_len + 1)
            .ok_or(SkipReason::MalformedEvent)?;
        let data_len = usize::from(fixed[before_len]);
        let end = before_len + 1 + data_len + after_data;
        let whole = reports.get(..end).ok_or(SkipReason::MalformedEvent)?;
        let data = &whole[before_len + 1..before_len + 1 + data_len];
        let rssi = if subevent == LE_ADVERTISING_REPORT {
            whole[end - 1] as i8
        } else {
            // RSSI follows event type (2), address type, address, PHYs, SID, TX power.
            whole[2 + 1 + 6 + 1 + 1 + 1 + 1] as i8
        };
        found.push((rssi, data));
        reports = &reports[end..];
    }
    Ok(found)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn skip_reasons_index_their_counters() {
        for (i, reason) in SkipReason::ALL.iter().enumerate() {
            assert_eq!(*reason as usize, i, "{reason}");
        }
    }

    #[test]
    fn an_ibeacon_without_rssi_is_no_rssi_and_anything_else_not_ibeacon() {
        let frame = ibeacon::encode_manufacturer_data(&ibeacon::IBeacon {
            id: crate::sighting::BeaconId {
                uuid: uuid::Uuid::from_u128(7),
                major: 1,
                minor: 2,
            },
            measured_power: -59,
        });
        let mut ad = vec![frame.len() as u8 + 1, ibeacon::AD_MANUFACTURER_SPECIFIC];
        ad.extend_from_slice(&frame);
        let mut adverts = Adverts::new("obs".into());
        adverts.advert(1.0, None, &ad);
        adverts.advert(1.0, Some(-60), &[0x02, 0x01, 0x06]);
        adverts.advert(2.0, Some(-61), &ad);
        let s = adverts.pop().unwrap();
        assert_eq!((s.t, s.rssi, &*s.observer), (2.0, -61, "obs"));
        assert!(adverts.pop().is_none());
        assert_eq!(
            adverts.skipped().iter().collect::<Vec<_>>(),
            [(SkipReason::NoRssi, 1), (SkipReason::NotIBeacon, 1)]
        );
    }
}
