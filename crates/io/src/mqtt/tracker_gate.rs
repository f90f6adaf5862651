//! Which devices get a Home Assistant tracker. Device ids come from the air
//! and the broker, so without a gate anyone can fill Home Assistant with
//! phantom devices (500 made-up ids × 2 scans made 503 trackers). A device
//! is announced only when it is listed (`[mqtt] ha_devices`, every device
//! when the list is empty), after `ha_min_fixes` located fixes (a device
//! heard in passing, or a made-up id sent once or twice, never gets one),
//! and while fewer than `ha_new_trackers_per_minute` trackers were
//! announced in the last minute (a flood of ids that each send enough
//! fixes still reaches Home Assistant at that pace at most). A device held
//! back by the cap is announced at a later fix; an unlisted one never.
//! Refusals are counted (stats `trackers_refused`).

use std::collections::VecDeque;
use std::sync::Arc;

use foldhash::HashMap;

use crate::locate::bounds::Bounds;

/// The settings of `[mqtt]` the gate reads.
#[derive(Clone, Debug, PartialEq)]
pub(crate) struct GateConfig {
    /// Device ids, or prefixes ending in `*`; empty: every device.
    pub listed: Vec<String>,
    pub min_fixes: u32,
    pub per_minute: u32,
}

pub(crate) struct TrackerGate {
    config: GateConfig,
    /// Located fixes of devices not announced yet, with the time of the
    /// latest, bounded like the tracks.
    waiting: HashMap<Arc<str>, (u32, f64)>,
    bounds: Bounds,
    /// Times of the announcements of the last minute.
    recent: VecDeque<f64>,
    refused: u64,
}

impl TrackerGate {
    pub(crate) fn new(config: GateConfig, max_devices: usize, idle_s: f64) -> TrackerGate {
        TrackerGate {
            config,
            waiting: HashMap::default(),
            bounds: Bounds::new(max_devices, idle_s),
            recent: VecDeque::new(),
            refused: 0,
        }
    }

    /// A located fix (not an unknown one) at `t` of a device that has no
    /// tracker yet: whether to announce it now.
    pub(crate) fn admit(&mut self, device: &str, t: f64) -> bool {
        if !self.listed(device) {
            self.refused += 1;
            return false;
        }
        let full = !self.waiting.contains_key(device) && self.waiting.len() >= self.bounds.max();
        self.bounds
            .make_room(&mut self.waiting, t, full, |&(_, seen)| seen, |_| {});
        let fixes = match self.waiting.get_mut(device) {
            Some(entry) => {
                *entry = (entry.0.saturating_add(1), entry.1.max(t));
                entry.0
            }
            None => {
                self.waiting.insert(device.into(), (1, t));
                1
            }
        };
        if fixes < self.config.min_fixes {
            return false;
        }
        while self.recent.front().is_some_and(|&at| at <= t - 60.0) {
            self.recent.pop_front();
        }
        if self.recent.len() >= self.config.per_minute as usize {
            self.refused += 1;
            return false;
        }
        self.recent.push_back(t);
        self.waiting.remove(device);
        true
    }

    /// A device the gateway forgot: it starts again from no fixes.
    pub(crate) fn forget(&mut self, device: &str) {
        self.waiting.remove(device);
    }

    /// Located fixes refused so far: of unlisted devices, and over the
    /// per-minute cap (a device refused at each of its fixes counts each).
    pub(crate) fn refused(&self) -> u64 {
        self.refused
    }

    fn listed(&self, device: &str) -> bool {
        self.config.listed.is_empty()
            || self
                .config
                .listed
                .iter()
                .any(|id| match id.strip_suffix('*') {
                    Some(prefix) => device.starts_with(prefix),
                    None => device == id,
                })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn gate(listed: &[&str], min_fixes: u32, per_minute: u32) -> TrackerGate {
        let config = GateConfig {
            listed: listed.iter().map(|s| s.to_string()).collect(),
            min_fixes,
            per_minute,
        };
        TrackerGate::new(config, 1000, 600.0)
    }

    #[test]
    fn a_device_is_announced_at_its_third_fix() {
        let mut g = gate(&[], 3, 30);
        assert!(!g.admit("phone", 0.0));
        assert!(!g.admit("phone", 2.0));
        assert!(g.admit("phone", 4.0));
        assert_eq!(g.refused(), 0);
        // Forgotten, it starts again.
        g.forget("phone");
        assert!(!g.admit("phone", 10.0));
    }

    #[test]
    fn a_flood_of_made_up_ids_gets_no_tracker_and_a_patient_one_the_cap() {
        let mut g = gate(&[], 3, 20);
        for i in 0..500 {
            for t in [0.0, 1.0] {
                assert!(!g.admit(&format!("fake-{i}"), t));
            }
        }
        let admitted = (0..500)
            .filter(|i| g.admit(&format!("fake-{i}"), 2.0))
            .count();
        assert_eq!(admitted, 20);
        assert_eq!(g.refused(), 480);
        // A minute later, the next twenty.
        let admitted = (0..500)
            .filter(|i| g.admit(&format!("fake-{i}"), 62.5))
            .count();
        assert_eq!(admitted, 20);
    }

    #[test]
    fn only_listed_devices_and_prefixes_are_announced() {
        let mut g = gate(&["walker-01", "staff-*"], 1, 30);
        assert!(g.admit("walker-01", 0.0));
        assert!(g.admit("staff-anna", 0.0));
        assert!(!g.admit("walker-02", 0.0));
        assert!(!g.admit("walker-011", 0.0));
        assert_eq!(g.refused(), 2);
    }

    #[test]
    fn the_devices_waiting_are_bounded() {
        let config = GateConfig {
            listed: Vec::new(),
            min_fixes: 3,
            per_minute: 30,
        };
        let mut g = TrackerGate::new(config, 64, 600.0);
        for i in 0..10_000 {
            g.admit(&format!("fake-{i}"), f64::from(i) / 1000.0);
        }
        assert!(g.waiting.len() <= 64, "{}", g.waiting.len());
    }
}
