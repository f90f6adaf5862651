//! Fingerprint windows: sightings per tracked entity, aggregated per anchor over
//! a sliding window into one RSSI vector in the site's anchor order.
//!
//! The same code serves both orientations ([`Orientation`]): a phone or robot
//! that hears fixed beacons (entity = observer, anchors = the site's beacons), or
//! tags heard by fixed gateways (entity = advertiser, anchors = the site's
//! gateways).
//!
//! Windows close on time, not on count: a window ending at boundary `b` holds the
//! sightings with `b - length < t <= b` and is emitted when the first sighting
//! after `b` arrives (or at [`Windows::flush`]). Sightings that share a timestamp,
//! as the adverts of one scan do, therefore always land in the same window.
//!
//! Entities come from the air and the broker, so their number is bounded
//! ([`Windows::bound`], [`Bounds`]).

use std::collections::hash_map::Entry;

// foldhash, not std's SipHash: these maps are looked up once per advert,
// and a seeded fast hash keeps that a small share of replay time.
use foldhash::HashMap;
use std::collections::VecDeque;
use std::sync::Arc;

use serde::Deserialize;

use super::bounds::Bounds;
use crate::sighting::{BeaconId, Mac, Sighting};
use crate::site::Site;

/// `[window]` in the gateway config.
#[derive(Clone, Debug, PartialEq, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct WindowConfig {
    /// Seconds of sightings in one fingerprint.
    pub length_s: f64,
    /// Seconds between fingerprints of one entity.
    pub stride_s: f64,
    /// How the readings of one anchor in a window become one number.
    pub aggregate: Aggregate,
    /// The value an anchor not heard in the window takes, in dBm.
    pub missing_dbm: f32,
    pub orientation: Orientation,
}

impl WindowConfig {
    /// Checks what serde cannot: a message naming the key and what to do.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.length_s > 0.0 && self.stride_s > 0.0) {
            return Err("[window] `length_s` and `stride_s` must be positive seconds".into());
        }
        Ok(())
    }
}

impl Default for WindowConfig {
    fn default() -> Self {
        WindowConfig {
            length_s: 4.0,
            stride_s: 2.0,
            aggregate: Aggregate::Max,
            missing_dbm: -105.0,
            orientation: Orientation::Observer,
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Aggregate {
    Median,
    Mean,
    Max,
}

/// Which side of a sighting is the entity being located.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Orientation {
    /// The observer (phone, robot) is located from the beacons it hears.
    Observer,
    /// The advertiser (tag) is located from the gateways that hear it.
    Advertiser,
}

/// The ids of the site's anchors in `orientation`, in the order of every
/// fingerprint vector: beacon ids, or gateway ids.
pub fn anchor_ids(site: &Site, orientation: Orientation) -> Vec<String> {
    match orientation {
        Orientation::Observer => site.beacons.iter().map(|b| b.id.clone()).collect(),
        Orientation::Advertiser => site.gateways.iter().map(|g| g.id.clone()).collect(),
    }
}

/// One aggregated window for one entity.
#[derive(Clone, Debug, PartialEq)]
pub struct Fingerprint {
    pub entity: Arc<str>,
    /// End of the window.
    pub t: f64,
    /// One value per anchor, in the site's anchor order; `missing_dbm` where the
    /// anchor was not heard.
    pub rssi: Vec<f32>,
    /// Which anchors were heard in the window.
    pub heard: Vec<bool>,
}

impl Fingerprint {
    pub(crate) fn heard_count(&self) -> usize {
        self.heard.iter().filter(|&&h| h).count()
    }
}

/// Sightings one entity's window holds at most (the oldest go first): a
/// window of real adverts holds a few hundred.
const MAX_SAMPLES: usize = 4096;

struct EntityWindow {
    /// (time, anchor index, rssi), oldest first.
    samples: VecDeque<(f64, u16, i16)>,
    /// Time of the latest sighting.
    last_seen: f64,
    /// The end of the window that closes next.
    boundary: f64,
    /// The end of the last window emitted.
    emitted: f64,
}

/// The fingerprint windows of every entity a gateway tracks.
pub struct Windows {
    config: WindowConfig,
    n_anchors: usize,
    /// The site's beacons by identity: a beacon with a `mac` under
    /// `(id, Some(mac))`, one without under `(id, None)`.
    beacon_anchors: HashMap<(BeaconId, Option<Mac>), u16>,
    gateway_anchors: HashMap<Arc<str>, u16>,
    /// Entity ids of advertisers, made once per tag (`uuid-major-minor`).
    advertiser_ids: HashMap<BeaconId, Arc<str>>,
    entities: HashMap<Arc<str>, EntityWindow>,
    unknown_anchor: u64,
    /// Reused per-anchor buffers for aggregation.
    scratch: Vec<Vec<i16>>,
    bounds: Bounds,
}

impl Windows {
    pub fn new(config: WindowConfig, site: &Site) -> Self {
        let beacons: Vec<_> = site.beacons.iter().map(|b| (b.beacon, b.mac)).collect();
        let gateways: Vec<&str> = site.gateways.iter().map(|g| g.id.as_str()).collect();
        Self::of_anchors(config, &beacons, &gateways)
    }

    /// Windows over anchors listed in their fingerprint order: beacons by
    /// identity (`None` for a beacon heard from any MAC), gateways by id. A
    /// building's pipeline lists every floor's anchors once.
    pub fn of_anchors(
        config: WindowConfig,
        beacons: &[(BeaconId, Option<Mac>)],
        gateways: &[&str],
    ) -> Self {
        let beacon_anchors = beacons
            .iter()
            .enumerate()
            .map(|(i, &key)| (key, i as u16))
            .collect();
        let gateway_anchors = gateways
            .iter()
            .enumerate()
            .map(|(i, &g)| (Arc::from(g), i as u16))
            .collect();
        let n_anchors = match config.orientation {
            Orientation::Observer => beacons.len(),
            Orientation::Advertiser => gateways.len(),
        };
        Windows {
            config,
            n_anchors,
            beacon_anchors,
            gateway_anchors,
            advertiser_ids: HashMap::default(),
            entities: HashMap::default(),
            unknown_anchor: 0,
            scratch: vec![Vec::new(); n_anchors],
            bounds: Bounds::default(),
        }
    }

    /// Keeps at most `max` entities, and none unheard for `idle_s` seconds.
    pub fn bound(mut self, max: usize, idle_s: f64) -> Self {
        self.bounds = Bounds::new(max, idle_s);
        self
    }

    /// Entities forgotten (idle or least recently heard past the maximum).
    pub(crate) fn evicted_count(&self) -> u64 {
        self.bounds.evicted()
    }

    pub(crate) fn config(&self) -> &WindowConfig {
        &self.config
    }

    /// Sightings whose anchor is not in the site (other beacons, other gateways).
    pub(crate) fn unknown_anchor_count(&self) -> u64 {
        self.unknown_anchor
    }

    /// Number of entities with an open window.
    pub(crate) fn entity_count(&self) -> usize {
        self.entities.len()
    }

    /// After a reload: takes over the open windows of `old` when they mean
    /// the same here (the same `[window]` settings and the same anchors in
    /// the same order), so a device's next fingerprint is not a window
    /// late. Otherwise they start afresh.
    pub(crate) fn take_over(&mut self, old: &mut Windows) {
        if self.config == old.config
            && self.beacon_anchors == old.beacon_anchors
            && self.gateway_anchors == old.gateway_anchors
        {
            self.entities = std::mem::take(&mut old.entities);
        }
    }

    /// The site beacon a sighting is from: the one with its UUID/major/minor
    /// and its MAC, else the one with its UUID/major/minor and no `mac`
    /// (which stands for that id from any address).
    fn beacon_anchor(&self, s: &Sighting) -> Option<u16> {
        s.advertiser_mac
            .and_then(|mac| self.beacon_anchors.get(&(s.advertiser, Some(mac))))
            .or_else(|| self.beacon_anchors.get(&(s.advertiser, None)))
            .copied()
    }

    /// Adds a sighting; returns the window it closed, if any.
    pub fn push(&mut self, s: &Sighting) -> Option<Fingerprint> {
        let (entity, anchor) = match self.config.orientation {
            Orientation::Observer => (s.observer.clone(), self.beacon_anchor(s)),
            Orientation::Advertiser => {
                let id = self
                    .advertiser_ids
                    .entry(s.advertiser)
                    .or_insert_with(|| s.advertiser.device_id().into())
                    .clone();
                (id, self.gateway_anchors.get(&s.observer).copied())
            }
        };
        let Some(anchor) = anchor else {
            self.unknown_anchor += 1;
            return None;
        };
        // Looked up only when full: this runs once per advert.
        let full = self.entities.len() >= self.bounds.max() && !self.entities.contains_key(&entity);
        self.bounds
            .make_room(&mut self.entities, s.t, full, |w| w.last_seen, |_| {});
        if self.advertiser_ids.len() > self.bounds.max().saturating_mul(2) {
            // A cache of formatted ids: cheaper to rebuild than to bound.
            self.advertiser_ids.clear();
        }
        let stride = self.config.stride_s;
        let (window, closed_at) = match self.entities.entry(entity.clone()) {
            Entry::Vacant(v) => (
                v.insert(EntityWindow {
                    samples: VecDeque::new(),
                    last_seen: s.t,
                    boundary: s.t,
                    emitted: f64::NEG_INFINITY,
                }),
                None,
            ),
            Entry::Occupied(o) => {
                let w = o.into_mut();
                let closed = (s.t > w.boundary).then_some(w.boundary);
                if let Some(end) = closed {
                    w.emitted = end;
                    // Skip boundaries with no sightings: a silent entity gets no
                    // fixes, and the tracker sees the gap as elapsed time.
                    let steps = ((s.t - w.boundary) / stride).ceil().max(1.0);
                    w.boundary += steps * stride;
                }
                (w, closed)
            }
        };
        let fingerprint = closed_at.map(|end| {
            aggregate(
                &self.config,
                self.n_anchors,
                &mut self.scratch,
                window,
                entity,
                end,
            )
        });
        if window.samples.len() >= MAX_SAMPLES {
            window.samples.pop_front();
        }
        window.samples.push_back((s.t, anchor, s.rssi));
        window.last_seen = window.last_seen.max(s.t);
        fingerprint
    }

    /// Closes every open window (end of a replay): one last fingerprint per entity
    /// that has sightings since its last one.
    pub fn flush(&mut self) -> Vec<Fingerprint> {
        let mut out = Vec::new();
        let mut entities: Vec<_> = self.entities.drain().collect();
        entities.sort_by(|a, b| a.0.cmp(&b.0));
        for (entity, mut window) in entities {
            let Some(&(last_t, _, _)) = window.samples.back() else {
                continue;
            };
            if last_t > window.emitted {
                out.push(aggregate(
                    &self.config,
                    self.n_anchors,
                    &mut self.scratch,
                    &mut window,
                    entity,
                    last_t,
                ));
            }
        }
        out
    }
}

fn aggregate(
    config: &WindowConfig,
    n_anchors: usize,
    scratch: &mut [Vec<i16>],
    window: &mut EntityWindow,
    entity: Arc<str>,
    end: f64,
) -> Fingerprint {
    let start = end - config.length_s;
    while window.samples.front().is_some_and(|&(t, _, _)| t <= start) {
        window.samples.pop_front();
    }
    for buf in scratch.iter_mut() {
        buf.clear();
    }
    for &(t, anchor, rssi) in &window.samples {
        if t <= end {
            scratch[usize::from(anchor)].push(rssi);
        }
    }
    let mut rssi = vec![config.missing_dbm; n_anchors];
    let mut heard = vec![false; n_anchors];
    for (i, buf) in scratch.iter_mut().enumerate() {
        if buf.is_empty() {
            continue;
        }
        heard[i] = true;
        rssi[i] = match config.aggregate {
            Aggregate::Max => f32::from(*buf.iter().max().expect("non-empty")),
            Aggregate::Mean => buf.iter().map(|&v| f32::from(v)).sum::<f32>() / buf.len() as f32,
            Aggregate::Median => {
                buf.sort_unstable();
                let mid = buf.len() / 2;
                if buf.len() % 2 == 1 {
                    f32::from(buf[mid])
                } else {
                    (f32::from(buf[mid - 1]) + f32::from(buf[mid])) / 2.0
                }
            }
        };
    }
    Fingerprint {
        entity,
        t: end,
        rssi,
        heard,
    }
}

#[cfg(test)]
mod tests {
    use std::path::Path;

    use super::*;

    const UUID: &str = "b9407f30-f5f8-466e-aff9-25556b57fe6d";

    /// A site whose beacons `a` and `b` share one UUID/major/minor and differ
    /// by MAC, and whose beacon `c` has no `mac`.
    fn site() -> Site {
        let beacon = |id: &str, minor: u16, mac: &str| {
            format!(
                "[[beacon]]\nid = \"{id}\"\nuuid = \"{UUID}\"\nmajor = 0\nminor = {minor}\n\
                 cell = [0, 0]\n{mac}\n"
            )
        };
        let text = format!(
            "name = \"t\"\ncell_m = 1.0\nmap = '''\n##\n'''\n{}{}{}",
            beacon("a", 0, "mac = \"AA:00:00:00:00:01\""),
            beacon("b", 0, "mac = \"AA:00:00:00:00:02\""),
            beacon("c", 7, "")
        );
        Site::parse(&text, Path::new("t.toml")).unwrap()
    }

    fn heard(minor: u16, mac: Option<&str>, rssi: i16, t: f64) -> Sighting {
        Sighting {
            t,
            observer: Arc::from("phone"),
            advertiser: BeaconId {
                uuid: UUID.parse().unwrap(),
                major: 0,
                minor,
            },
            advertiser_mac: mac.map(|m| m.parse().unwrap()),
            tx_power: None,
            rssi,
        }
    }

    fn window_of(sightings: &[Sighting]) -> (Fingerprint, u64) {
        let mut windows = Windows::new(WindowConfig::default(), &site());
        for s in sightings {
            assert_eq!(windows.push(s), None);
        }
        let unknown = windows.unknown_anchor_count();
        (windows.flush().remove(0), unknown)
    }

    #[test]
    fn a_beacon_with_a_mac_stands_only_for_sightings_from_that_mac() {
        let (fp, unknown) = window_of(&[
            heard(0, Some("AA:00:00:00:00:02"), -60, 1.0),
            heard(0, Some("AA:00:00:00:00:01"), -70, 1.0),
            // Another transmitter with the same id, and one with no address:
            // neither is `a` nor `b`.
            heard(0, Some("AA:00:00:00:00:03"), -50, 1.0),
            heard(0, None, -50, 1.0),
        ]);
        assert_eq!(fp.rssi[..2], [-70.0, -60.0]);
        assert_eq!(fp.heard, [true, true, false]);
        assert_eq!(unknown, 2);
    }

    #[test]
    fn a_beacon_without_a_mac_stands_for_its_id_from_any_mac() {
        let (fp, unknown) = window_of(&[
            heard(7, Some("BB:00:00:00:00:01"), -80, 1.0),
            heard(7, Some("BB:00:00:00:00:02"), -65, 1.0),
            heard(7, None, -75, 1.0),
        ]);
        assert_eq!(fp.heard, [false, false, true]);
        assert_eq!(fp.rssi[2], -65.0, "the strongest of the three");
        assert_eq!(unknown, 0);
    }
}
