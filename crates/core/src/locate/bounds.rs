//! Bounds on per-entity tables ([`window`](super::window) and
//! [`tracker`](super::tracker)): entities come from the air and the broker, so
//! anyone can make new ones. An entity unheard for the idle time is forgotten,
//! and past the maximum the least recently heard go first; both are counted.

use std::hash::{BuildHasher, Hash};

use std::collections::HashMap;

/// How many entities a table keeps and for how long, and how many it forgot.
#[derive(Clone, Debug)]
pub struct Bounds {
    max: usize,
    idle_s: f64,
    /// Latest event time seen: the clock idle time is measured on (event
    /// time, so a replay at any speed expires what real time would).
    latest_t: f64,
    next_sweep_t: f64,
    evicted: u64,
}

impl Default for Bounds {
    /// No bound.
    fn default() -> Self {
        Bounds::new(usize::MAX, f64::INFINITY)
    }
}

impl Bounds {
    pub fn new(max: usize, idle_s: f64) -> Self {
        Bounds {
            max: max.max(1),
            idle_s,
            latest_t: f64::NEG_INFINITY,
            next_sweep_t: f64::NEG_INFINITY,
            evicted: 0,
        }
    }

    pub fn max(&self) -> usize {
        self.max
    }

    /// Entities forgotten so far.
    pub(crate) fn evicted(&self) -> u64 {
        self.evicted
    }

    /// Called before an entity is touched at time `t`, with `full` when it is
    /// a new one and `map` holds `max` already. Forgets idle entities once per
    /// quarter of the idle time, and, when full, the least recently seen
    /// sixteenth: amortised O(1) per call, without a recency list to keep in
    /// order. `forgotten` gets each key removed.
    pub fn make_room<K: Eq + Hash + Clone, V, S: BuildHasher>(
        &mut self,
        map: &mut HashMap<K, V, S>,
        t: f64,
        full: bool,
        last_seen: impl Fn(&V) -> f64,
        mut forgotten: impl FnMut(&K),
    ) {
        self.latest_t = self.latest_t.max(t);
        let mut cutoff = f64::NEG_INFINITY;
        if self.latest_t >= self.next_sweep_t {
            cutoff = self.latest_t - self.idle_s;
            self.next_sweep_t = self.latest_t + self.idle_s / 4.0;
        }
        if full && map.len() >= self.max {
            let mut seen: Vec<f64> = map.values().map(&last_seen).collect();
            let k = (seen.len() / 16).max(1) - 1;
            let (_, &mut oldest, _) = seen.select_nth_unstable_by(k, f64::total_cmp);
            // Strictly after the oldest kept: at least one entry goes.
            cutoff = cutoff.max(next_up(oldest));
        }
        if cutoff > f64::NEG_INFINITY {
            let before = map.len();
            map.retain(|k, v| {
                let keep = last_seen(v) >= cutoff;
                if !keep {
                    forgotten(k);
                }
                keep
            });
            self.evicted += (before - map.len()) as u64;
        }
    }
}

/// The smallest float above `x` (for finite `x`).
fn next_up(x: f64) -> f64 {
    if x.is_finite() {
        let bits = x.to_bits();
        f64::from_bits(if x >= 0.0 { bits + 1 } else { bits - 1 })
    } else {
        x
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_least_recently_seen_go_when_full_and_the_idle_ones_in_time() {
        let mut map: HashMap<u32, f64> = HashMap::new();
        let mut bounds = Bounds::new(32, 100.0);
        let mut gone = Vec::new();
        for i in 0..40u32 {
            let t = f64::from(i);
            let full = map.len() >= bounds.max() && !map.contains_key(&i);
            bounds.make_room(&mut map, t, full, |&v| v, |&k| gone.push(k));
            map.insert(i, t);
        }
        assert!(map.len() <= 32, "{}", map.len());
        assert_eq!(bounds.evicted() as usize, gone.len());
        // The ones forgotten are the oldest.
        assert!(gone.iter().all(|&k| k < 10), "{gone:?}");
        // Much later, everything is idle and goes, but the one touched now.
        bounds.make_room(&mut map, 1000.0, false, |&v| v, |_| {});
        map.insert(99, 1000.0);
        assert_eq!(map.len(), 1);
        assert_eq!(bounds.evicted(), 40);
    }
}
