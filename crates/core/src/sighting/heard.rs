//! What the gateway hears: every iBeacon in its sightings, known to the site
//! or not, with how often, how loud and by whom. The answer to "which
//! beacons are here, and which of them does my site file lack?", for
//! `replay --heard`, the daemon's stats and its retained `heard` topic.
//!
//! Bounded because adverts come from the air: at most `capacity` beacons
//! (the gateway's `[limits] max_devices`), each with at most
//! [`MAX_OBSERVERS`] observer names. A new beacon on a full table replaces
//! the one heard least (the oldest among those), so a flood of made-up ids
//! pushes out only its own kind, never a beacon heard all day. The median
//! comes from a histogram over the RSSI range sightings can carry, so it is
//! exact and costs no per-advert allocation.

use std::sync::Arc;

use foldhash::HashMap;
use serde::Serialize;
use uuid::Uuid;

use super::{BeaconId, Sighting};

/// Observer names kept per beacon; more are counted, not named.
pub const MAX_OBSERVERS: usize = 8;

/// The RSSI range of the histogram, in dBm; readings outside it count at its
/// ends (no receiver reports below -127 or above +20).
const RSSI_MIN: i16 = -127;
const RSSI_MAX: i16 = 20;
const RSSI_BINS: usize = (RSSI_MAX - RSSI_MIN + 1) as usize;

/// Every beacon heard so far, bounded.
#[derive(Debug)]
pub struct HeardTable {
    beacons: HashMap<BeaconId, Tally>,
    capacity: usize,
    /// Beacons pushed out of a full table.
    replaced: u64,
}

#[derive(Debug)]
struct Tally {
    count: u64,
    last_t: f64,
    rssi: Box<[u32; RSSI_BINS]>,
    observers: Vec<Arc<str>>,
    more_observers: bool,
}

/// One beacon in a report, as `replay --heard --json` and the `heard` topic
/// give it.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct HeardBeacon {
    pub uuid: Uuid,
    pub major: u16,
    pub minor: u16,
    pub count: u64,
    pub rssi_median: i16,
    pub rssi_max: i16,
    /// Who heard it, at most [`MAX_OBSERVERS`] names in the order first heard.
    pub observers: Vec<String>,
    /// Whether more observers heard it than are named.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub more_observers: bool,
    /// Whether the site has it as a beacon.
    pub known: bool,
}

impl HeardTable {
    /// An empty table of at most `capacity` beacons (at least one).
    pub fn new(capacity: usize) -> HeardTable {
        HeardTable {
            beacons: HashMap::default(),
            capacity: capacity.max(1),
            replaced: 0,
        }
    }

    /// Counts one sighting.
    pub fn add(&mut self, sighting: &Sighting) {
        if !self.beacons.contains_key(&sighting.advertiser) && self.beacons.len() >= self.capacity {
            self.make_room();
        }
        let tally = self
            .beacons
            .entry(sighting.advertiser)
            .or_insert_with(|| Tally {
                count: 0,
                last_t: sighting.t,
                rssi: Box::new([0; RSSI_BINS]),
                observers: Vec::new(),
                more_observers: false,
            });
        tally.count += 1;
        tally.last_t = tally.last_t.max(sighting.t);
        let bin = (sighting.rssi.clamp(RSSI_MIN, RSSI_MAX) - RSSI_MIN) as usize;
        tally.rssi[bin] += 1;
        tally.heard_by(&sighting.observer);
    }

    /// Drops the eighth of the table heard least (at least one beacon), the
    /// oldest first among equals: a whole eighth at once, so that a flood of
    /// new ids costs one pass over the table per eighth of it, not per advert.
    fn make_room(&mut self) {
        let mut least: Vec<(u64, f64, BeaconId)> = self
            .beacons
            .iter()
            .map(|(id, tally)| (tally.count, tally.last_t, *id))
            .collect();
        let drop = (least.len() / 8).max(1).min(least.len());
        if drop == 0 {
            return;
        }
        least.select_nth_unstable_by(drop - 1, |a, b| a.0.cmp(&b.0).then(a.1.total_cmp(&b.1)));
        for (_, _, id) in &least[..drop] {
            self.beacons.remove(id);
        }
        self.replaced += drop as u64;
    }

    /// How many beacons were heard (at most the capacity).
    pub fn count(&self) -> usize {
        self.beacons.len()
    }

    /// Beacons heard that `which` holds for.
    pub fn count_where(&self, which: impl Fn(&BeaconId) -> bool) -> usize {
        self.beacons.keys().filter(|id| which(id)).count()
    }

    /// Beacons pushed out of the full table so far.
    pub fn replaced(&self) -> u64 {
        self.replaced
    }

    /// The beacons heard most, at most `limit`, loudest count first (ties by
    /// id, so a report is the same whatever the table's order); `known` says
    /// which the site has.
    pub fn report(&self, limit: usize, known: impl Fn(&BeaconId) -> bool) -> Vec<HeardBeacon> {
        let mut beacons: Vec<(&BeaconId, &Tally)> = self.beacons.iter().collect();
        beacons.sort_by(|(a_id, a), (b_id, b)| b.count.cmp(&a.count).then(a_id.cmp(b_id)));
        beacons
            .into_iter()
            .take(limit)
            .map(|(id, tally)| HeardBeacon {
                uuid: id.uuid,
                major: id.major,
                minor: id.minor,
                count: tally.count,
                rssi_median: tally.median(),
                rssi_max: tally.max(),
                observers: tally.observers.iter().map(|o| o.to_string()).collect(),
                more_observers: tally.more_observers,
                known: known(id),
            })
            .collect()
    }

    /// Takes in what `other` heard (a reload hands its table on).
    pub fn absorb(&mut self, other: HeardTable) {
        self.replaced += other.replaced;
        for (id, tally) in other.beacons {
            if !self.beacons.contains_key(&id) && self.beacons.len() >= self.capacity {
                self.make_room();
            }
            match self.beacons.entry(id) {
                std::collections::hash_map::Entry::Vacant(slot) => {
                    slot.insert(tally);
                }
                std::collections::hash_map::Entry::Occupied(mut slot) => {
                    let mine = slot.get_mut();
                    mine.count += tally.count;
                    mine.last_t = mine.last_t.max(tally.last_t);
                    for (bin, n) in mine.rssi.iter_mut().zip(tally.rssi.iter()) {
                        *bin += n;
                    }
                    for observer in &tally.observers {
                        mine.heard_by(observer);
                    }
                    mine.more_observers |= tally.more_observers;
                }
            }
        }
    }
}

impl Tally {
    /// Names `observer` among those that heard it, within the bound.
    fn heard_by(&mut self, observer: &Arc<str>) {
        if self.observers.iter().any(|o| o == observer) {
            return;
        }
        if self.observers.len() < MAX_OBSERVERS {
            self.observers.push(observer.clone());
        } else {
            self.more_observers = true;
        }
    }

    /// The lower median of the readings, in dBm.
    fn median(&self) -> i16 {
        let half = self.count.div_ceil(2);
        let mut seen = 0;
        for (bin, &n) in self.rssi.iter().enumerate() {
            seen += u64::from(n);
            if seen >= half {
                return RSSI_MIN + bin as i16;
            }
        }
        RSSI_MAX
    }

    fn max(&self) -> i16 {
        let top = self.rssi.iter().rposition(|&n| n > 0).unwrap_or(0);
        RSSI_MIN + top as i16
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn beacon(minor: u16) -> BeaconId {
        BeaconId {
            uuid: Uuid::from_u128(0xf7826da6_4fa2_4e98_8024_bc5b71e0893e),
            major: 1,
            minor,
        }
    }

    fn heard(table: &mut HeardTable, t: f64, observer: &str, minor: u16, rssi: i16) {
        table.add(&Sighting {
            advertiser_mac: None,
            t,
            observer: observer.into(),
            advertiser: beacon(minor),
            tx_power: None,
            rssi,
        });
    }

    #[test]
    fn counts_each_beacon_with_its_median_maximum_and_observers() {
        let mut table = HeardTable::new(16);
        for (i, rssi) in [-80, -70, -75, -90, -60].into_iter().enumerate() {
            heard(
                &mut table,
                i as f64,
                if i % 2 == 0 { "gw-a" } else { "gw-b" },
                1,
                rssi,
            );
        }
        heard(&mut table, 9.0, "gw-a", 2, -99);
        let report = table.report(10, |id| id.minor == 1);
        assert_eq!(report.len(), 2);
        let first = &report[0];
        assert_eq!((first.minor, first.count), (1, 5));
        assert_eq!((first.rssi_median, first.rssi_max), (-75, -60));
        assert_eq!(first.observers, ["gw-a", "gw-b"]);
        assert!(first.known);
        assert_eq!(
            (report[1].minor, report[1].rssi_median, report[1].known),
            (2, -99, false)
        );
        assert_eq!(table.report(1, |_| true).len(), 1, "the limit holds");
    }

    #[test]
    fn a_flood_of_new_ids_pushes_out_only_its_own_kind() {
        let mut table = HeardTable::new(4);
        for t in 0..100 {
            heard(&mut table, f64::from(t), "gw-a", 1, -70);
        }
        for minor in 1000..11_000 {
            heard(&mut table, 200.0, "attacker", minor, -40);
        }
        assert_eq!(table.count(), 4, "bounded");
        assert_eq!(table.replaced(), 10_000 - 3);
        let report = table.report(4, |_| false);
        assert_eq!(
            (report[0].minor, report[0].count),
            (1, 100),
            "the real beacon stays"
        );
    }

    #[test]
    fn observers_are_named_up_to_the_bound() {
        let mut table = HeardTable::new(4);
        for i in 0..(MAX_OBSERVERS + 5) {
            heard(&mut table, 0.0, &format!("phone-{i}"), 1, -70);
        }
        let report = table.report(1, |_| true);
        assert_eq!(report[0].observers.len(), MAX_OBSERVERS);
        assert!(report[0].more_observers);
    }

    #[test]
    fn a_reload_hands_on_what_was_heard() {
        let mut old = HeardTable::new(4);
        heard(&mut old, 0.0, "gw-a", 1, -70);
        heard(&mut old, 1.0, "gw-b", 2, -80);
        let mut new = HeardTable::new(4);
        heard(&mut new, 2.0, "gw-c", 1, -60);
        new.absorb(old);
        let report = new.report(4, |_| true);
        assert_eq!((report[0].minor, report[0].count), (1, 2));
        assert_eq!(report[0].observers, ["gw-c", "gw-a"]);
        assert_eq!(report[0].rssi_max, -60);
        assert_eq!(report[1].minor, 2);
    }
}
