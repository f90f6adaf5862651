//! Which locator of a site locates which device, when several share the work
//! (`[cluster] role = "locator"`): devices are cut into a fixed number of
//! shards by a stable hash of their id, and each shard belongs to exactly one
//! of the locators alive, chosen by rendezvous (highest random weight)
//! hashing over their ids.
//!
//! Why rendezvous hashing: every locator computes the same owner from the
//! same member list with no exchange beyond the list itself, and a locator
//! that joins or leaves moves only the shards it takes or gives (about
//! 1/N of them), so the other locators keep their devices' tracks.
//!
//! Why a membership of our own at all: the brokers gateways run (mosquitto,
//! NATS, RabbitMQ) deliver a shared subscription's messages round-robin, not
//! by key, so nothing in them keeps one device with one consumer. What this
//! module keeps is the smallest lease that gives that guarantee: each
//! locator announces itself every `heartbeat` on the broker, and one not
//! heard for `lease` is gone (`docs/scaling.md`).
//!
//! A locator starting up listens for one lease before it serves
//! ([`BeatState::Joining`]), so it learns who is there before it claims a
//! shard; the locators already serving give it its share only once it says
//! it serves, so a shard is never left without an owner by a join.
//!
//! Nothing here does I/O or reads a clock: times are passed in (seconds).

use std::collections::BTreeMap;

/// Locators a membership keeps at most: ids past it are refused, so a
/// flood of forged heartbeats cannot grow it without bound.
pub const MAX_LOCATORS: usize = 256;

/// The shard of a device: FNV-1a (64-bit) of its id's bytes, modulo
/// `shards`. Written out (not `std`'s hasher, whose output may change
/// between Rust releases) because edges and locators built at different
/// times must agree, and so that a client in another language can compute
/// it: the offset basis 0xcbf29ce484222325, prime 0x100000001b3.
pub fn shard_of(device: &str, shards: u16) -> u16 {
    (fnv1a(device.as_bytes(), FNV_OFFSET) % u64::from(shards.max(1))) as u16
}

const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;
const FNV_PRIME: u64 = 0x0100_0000_01b3;

fn fnv1a(bytes: &[u8], basis: u64) -> u64 {
    bytes
        .iter()
        .fold(basis, |h, &b| (h ^ u64::from(b)).wrapping_mul(FNV_PRIME))
}

/// A locator's weight for a shard: the locator's id hashed, then the shard
/// mixed in and finished with splitmix64's avalanche, so that weights of
/// ids differing in one character are unrelated.
fn weight(locator: &str, shard: u16) -> u64 {
    let mut z = fnv1a(&shard.to_le_bytes(), fnv1a(locator.as_bytes(), FNV_OFFSET));
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
    z ^ (z >> 31)
}

/// What a locator says of itself in a heartbeat.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BeatState {
    /// Listening for the others before it serves: owns nothing yet.
    Joining,
    /// Owns its share of the shards.
    Serving,
    /// Shutting down: its shards go to the others now, not after a lease.
    Leaving,
}

impl BeatState {
    pub fn as_str(self) -> &'static str {
        match self {
            BeatState::Joining => "joining",
            BeatState::Serving => "serving",
            BeatState::Leaving => "leaving",
        }
    }

    pub fn parse(s: &str) -> Option<BeatState> {
        match s {
            "joining" => Some(BeatState::Joining),
            "serving" => Some(BeatState::Serving),
            "leaving" => Some(BeatState::Leaving),
            _ => None,
        }
    }
}

/// A locator's heartbeat: who it is, in which state, which shards it owns
/// (for the others to see and for monitoring) and how many shards it cuts
/// the devices into (locators that disagree on it would both own devices).
#[derive(Clone, Debug, PartialEq)]
pub struct Beat {
    pub locator: String,
    pub state: BeatState,
    pub shards: u16,
    pub owned: Vec<u16>,
    pub t: f64,
}

/// Why another locator's heartbeat was not taken.
#[derive(Debug, PartialEq, thiserror::Error)]
pub enum BeatRefused {
    #[error(
        "locator {locator:?} cuts devices into {theirs} shards and this one into {ours}: \
         set the same [cluster] shards on every locator of the site"
    )]
    ShardsDiffer {
        locator: String,
        theirs: u16,
        ours: u16,
    },
    #[error(
        "locator {locator:?} ignored: {MAX_LOCATORS} locators are known already \
         (a forged heartbeat? restrict who may publish on the site's locators topic)"
    )]
    TooMany { locator: String },
}

/// What changed in this locator's shards.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Change {
    /// Shards it owns now and did not before.
    pub gained: Vec<u16>,
    /// Shards it owned and another owns now.
    pub lost: Vec<u16>,
    /// Whether the gained shards come from a locator that left or was not
    /// heard for a lease (not from this one starting to serve): requests
    /// for them may have reached no one.
    pub taken_over: bool,
}

impl Change {
    pub fn is_empty(&self) -> bool {
        self.gained.is_empty() && self.lost.is_empty()
    }
}

/// This locator's view of the site's locators, and the shards it owns.
#[derive(Debug)]
pub struct Membership {
    me: String,
    shards: u16,
    lease_s: f64,
    state: BeatState,
    /// Until when this locator listens before it serves.
    joining_until: f64,
    /// The other locators serving, with when each was last heard.
    others: BTreeMap<String, f64>,
    /// Whether this locator owns each shard now.
    owned: Vec<bool>,
}

impl Membership {
    /// A locator `me` starting at `now`: it owns nothing for one lease.
    pub fn new(me: impl Into<String>, shards: u16, lease_s: f64, now: f64) -> Membership {
        let shards = shards.max(1);
        Membership {
            me: me.into(),
            shards,
            lease_s,
            state: BeatState::Joining,
            joining_until: now + lease_s,
            others: BTreeMap::new(),
            owned: vec![false; usize::from(shards)],
        }
    }

    pub fn shards(&self) -> u16 {
        self.shards
    }

    /// Whether this locator owns `device` now.
    pub fn owns_device(&self, device: &str) -> bool {
        self.owns(shard_of(device, self.shards))
    }

    pub fn owns(&self, shard: u16) -> bool {
        self.owned.get(usize::from(shard)).copied().unwrap_or(false)
    }

    /// The shards this locator owns, in order.
    pub fn owned(&self) -> Vec<u16> {
        (0..self.shards).filter(|&s| self.owns(s)).collect()
    }

    /// The other locators serving, by id.
    pub fn others(&self) -> impl Iterator<Item = &str> {
        self.others.keys().map(String::as_str)
    }

    /// This locator's heartbeat at `now`.
    pub fn beat(&self, now: f64) -> Beat {
        Beat {
            locator: self.me.clone(),
            state: self.state,
            shards: self.shards,
            owned: self.owned(),
            t: now,
        }
    }

    /// Another locator's heartbeat, heard at `now` (its own `t` is not
    /// trusted: clocks differ). A locator's own heartbeat, echoed by the
    /// broker, changes nothing.
    pub fn heard(&mut self, beat: &Beat, now: f64) -> Result<Change, BeatRefused> {
        if beat.locator == self.me {
            return Ok(Change::default());
        }
        if beat.shards != self.shards {
            return Err(BeatRefused::ShardsDiffer {
                locator: beat.locator.clone(),
                theirs: beat.shards,
                ours: self.shards,
            });
        }
        match beat.state {
            BeatState::Serving => {
                if !self.others.contains_key(&beat.locator) && self.others.len() >= MAX_LOCATORS {
                    return Err(BeatRefused::TooMany {
                        locator: beat.locator.clone(),
                    });
                }
                let new = self.others.insert(beat.locator.clone(), now).is_none();
                Ok(if new {
                    self.reassign(false)
                } else {
                    Change::default()
                })
            }
            // A joining locator owns nothing yet: the shards stay where they are.
            BeatState::Joining => Ok(Change::default()),
            BeatState::Leaving => {
                let left = self.others.remove(&beat.locator).is_some();
                Ok(if left {
                    self.reassign(true)
                } else {
                    Change::default()
                })
            }
        }
    }

    /// Time passing: a locator not heard for a lease is gone, and this one
    /// serves once it has listened for one.
    pub fn tick(&mut self, now: f64) -> Change {
        let before = self.others.len();
        let lease = self.lease_s;
        self.others.retain(|_, heard| now - *heard <= lease);
        let expired = self.others.len() < before;
        if self.state == BeatState::Joining && now >= self.joining_until {
            self.state = BeatState::Serving;
        }
        self.reassign(expired)
    }

    /// Stops serving: owns nothing from now on, and says so in its beats.
    pub fn leave(&mut self) -> Change {
        self.state = BeatState::Leaving;
        self.reassign(false)
    }

    /// Recomputes the shards owned; `taken_over` when a member went away.
    fn reassign(&mut self, member_gone: bool) -> Change {
        let mut change = Change {
            taken_over: member_gone,
            ..Change::default()
        };
        for shard in 0..self.shards {
            let mine = self.state == BeatState::Serving && {
                let own = weight(&self.me, shard);
                self.others
                    .keys()
                    .all(|other| (weight(other, shard), other.as_str()) < (own, self.me.as_str()))
            };
            let was = std::mem::replace(&mut self.owned[usize::from(shard)], mine);
            match (was, mine) {
                (false, true) => change.gained.push(shard),
                (true, false) => change.lost.push(shard),
                _ => {}
            }
        }
        if change.gained.is_empty() {
            change.taken_over = false;
        }
        change
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn serving(locator: &str, shards: u16) -> Beat {
        Beat {
            locator: locator.into(),
            state: BeatState::Serving,
            shards,
            owned: Vec::new(),
            t: 0.0,
        }
    }

    #[test]
    fn the_shard_hash_is_fnv_1a_as_documented() {
        // FNV-1a 64 of "a" is 0xaf63dc4c8601ec8c (the published test vector).
        assert_eq!(fnv1a(b"a", FNV_OFFSET), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(shard_of("a", 64), (0xaf63_dc4c_8601_ec8c_u64 % 64) as u16);
        assert_eq!(shard_of("anything", 1), 0);
    }

    #[test]
    fn a_locator_owns_nothing_until_it_has_listened_for_a_lease() {
        let mut m = Membership::new("loc-a", 16, 3.0, 100.0);
        assert!(m.tick(101.0).is_empty());
        assert!(m.owned().is_empty());
        let change = m.tick(103.0);
        assert_eq!(change.gained.len(), 16);
        assert!(!change.taken_over, "starting to serve takes over nothing");
        assert_eq!(m.beat(103.0).state, BeatState::Serving);
    }

    #[test]
    fn two_locators_split_the_shards_with_neither_gap_nor_overlap() {
        let (mut a, mut b) = (
            Membership::new("loc-a", 64, 3.0, 0.0),
            Membership::new("loc-b", 64, 3.0, 0.0),
        );
        a.tick(3.0);
        b.tick(3.0);
        a.heard(&b.beat(3.0), 3.0).unwrap();
        b.heard(&a.beat(3.0), 3.0).unwrap();
        for shard in 0..64 {
            assert!(a.owns(shard) ^ b.owns(shard), "shard {shard}");
        }
        // Rendezvous hashing spreads them: neither gets fewer than a quarter.
        assert!((16..=48).contains(&a.owned().len()), "{:?}", a.owned());
    }

    #[test]
    fn a_locator_not_heard_for_a_lease_has_its_shards_taken_over() {
        let mut a = Membership::new("loc-a", 32, 3.0, 0.0);
        a.tick(3.0);
        let joined = a.heard(&serving("loc-b", 32), 4.0).unwrap();
        assert!(!joined.lost.is_empty() && joined.gained.is_empty());
        assert!(a.tick(6.5).is_empty(), "heard 2.5 s ago: still there");
        let gone = a.tick(7.5);
        assert_eq!(gone.gained, joined.lost);
        assert!(gone.taken_over);
        assert_eq!(a.owned().len(), 32);
    }

    #[test]
    fn a_third_locator_moves_only_the_shards_it_takes() {
        let mut a = Membership::new("loc-a", 128, 3.0, 0.0);
        a.tick(3.0);
        a.heard(&serving("loc-b", 128), 3.0).unwrap();
        let before = a.owned();
        let change = a.heard(&serving("loc-c", 128), 3.5).unwrap();
        assert!(
            change.gained.is_empty(),
            "a join gives nothing to the others"
        );
        let after = a.owned();
        assert!(after.iter().all(|s| before.contains(s)));
        assert_eq!(before.len() - after.len(), change.lost.len());
    }

    #[test]
    fn a_leaving_locator_hands_over_at_once_and_joining_ones_take_nothing() {
        let mut a = Membership::new("loc-a", 32, 3.0, 0.0);
        a.tick(3.0);
        let mut joining = serving("loc-b", 32);
        joining.state = BeatState::Joining;
        assert!(a.heard(&joining, 3.0).unwrap().is_empty());
        assert_eq!(a.owned().len(), 32);
        a.heard(&serving("loc-b", 32), 3.1).unwrap();
        joining.state = BeatState::Leaving;
        let change = a.heard(&joining, 3.2).unwrap();
        assert!(change.taken_over);
        assert_eq!(a.owned().len(), 32);
        assert_eq!(a.leave().lost.len(), 32);
        assert_eq!(a.beat(4.0).state, BeatState::Leaving);
    }

    #[test]
    fn bad_and_excess_heartbeats_are_refused_and_own_echoes_ignored() {
        let mut a = Membership::new("loc-a", 32, 3.0, 0.0);
        a.tick(3.0);
        let err = a.heard(&serving("loc-b", 16), 3.0).unwrap_err();
        assert!(err.to_string().contains("[cluster] shards"), "{err}");
        assert!(a.heard(&serving("loc-a", 32), 3.0).unwrap().is_empty());
        for i in 0..MAX_LOCATORS {
            a.heard(&serving(&format!("forged-{i}"), 32), 3.0).unwrap();
        }
        let err = a.heard(&serving("one-more", 32), 3.0).unwrap_err();
        assert!(matches!(err, BeatRefused::TooMany { .. }), "{err}");
    }
}
