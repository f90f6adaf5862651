//! `GET /metrics`: the gateway's counters and gauges in the Prometheus text
//! format, named `gangway_…`, plus histograms of fix age and route latency.
//!
//! The counters and gauges are the ones the retained MQTT stats carry
//! ([`COUNTERS`], [`GAUGES`]), read from the last stats output, so the two
//! never disagree. The text format is written here: it is three lines a
//! series, and the values already exist as numbers.

use std::fmt::Write;
use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};

use crate::publish::stats::{COUNTERS, GAUGES, Stats};

/// Upper bounds (seconds) of the fix-age buckets: a fix is at least half a
/// window old when it is made.
const FIX_AGE_BOUNDS: [f64; 10] = [0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 6.0, 10.0, 30.0];
/// Upper bounds (seconds) of the route-latency buckets.
const ROUTE_BOUNDS: [f64; 10] = [
    0.000_25, 0.000_5, 0.001, 0.002, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5,
];
/// A fix further than this from the wall clock is a replayed one: its age
/// says nothing about the gateway and is not observed.
const LIVE_CLOCK_S: f64 = 3600.0;

#[derive(Default)]
pub struct Metrics {
    stats: Mutex<Option<serde_json::Value>>,
    fix_age: Histogram<10>,
    route_latency: Histogram<10>,
    /// Batches of fixes sent to the pages.
    pub batches: AtomicU64,
}

struct Histogram<const N: usize> {
    counts: [AtomicU64; N],
    count: AtomicU64,
    /// Sum in microseconds.
    sum_us: AtomicU64,
}

impl<const N: usize> Default for Histogram<N> {
    fn default() -> Self {
        Histogram {
            counts: std::array::from_fn(|_| AtomicU64::new(0)),
            count: AtomicU64::new(0),
            sum_us: AtomicU64::new(0),
        }
    }
}

impl<const N: usize> Histogram<N> {
    fn observe(&self, bounds: &[f64; N], seconds: f64) {
        if let Some(i) = bounds.iter().position(|&b| seconds <= b) {
            self.counts[i].fetch_add(1, Ordering::Relaxed);
        }
        self.count.fetch_add(1, Ordering::Relaxed);
        self.sum_us
            .fetch_add((seconds * 1e6).max(0.0) as u64, Ordering::Relaxed);
    }

    fn write(&self, out: &mut String, name: &str, help: &str, bounds: &[f64; N]) {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut cumulative = 0;
        for (bound, count) in bounds.iter().zip(&self.counts) {
            cumulative += count.load(Ordering::Relaxed);
            let _ = writeln!(out, "{name}_bucket{{le=\"{bound}\"}} {cumulative}");
        }
        let count = self.count.load(Ordering::Relaxed);
        let sum = self.sum_us.load(Ordering::Relaxed) as f64 / 1e6;
        let _ = writeln!(
            out,
            "{name}_bucket{{le=\"+Inf\"}} {count}\n{name}_sum {sum}\n{name}_count {count}"
        );
    }
}

impl Metrics {
    /// A fix of time `t` reached the sinks now.
    pub fn observe_fix(&self, t: f64) {
        let age = crate::sighting::unix_now() - t;
        if age.abs() < LIVE_CLOCK_S {
            self.fix_age.observe(&FIX_AGE_BOUNDS, age);
        }
    }

    pub fn observe_route(&self, latency_us: u64) {
        self.route_latency
            .observe(&ROUTE_BOUNDS, latency_us as f64 / 1e6);
    }

    pub fn set_stats(&self, stats: &Stats) {
        let json = serde_json::to_value(stats).expect("plain data serializes");
        *self.stats.lock().unwrap_or_else(|e| e.into_inner()) = Some(json);
    }

    /// The exposition text; `streams` pages are watching.
    pub fn render(&self, streams: usize) -> String {
        let mut out = String::new();
        let stats = self.stats.lock().unwrap_or_else(|e| e.into_inner()).clone();
        if let Some(stats) = &stats {
            for (key, help) in COUNTERS {
                if let Some(v) = stats[key].as_f64() {
                    let name = format!("gangway_{key}_total");
                    let _ = writeln!(
                        out,
                        "# HELP {name} {help}.\n# TYPE {name} counter\n{name} {v}"
                    );
                }
            }
            for (key, help) in GAUGES {
                if let Some(v) = stats[key].as_f64() {
                    let name = format!("gangway_{key}");
                    let _ = writeln!(
                        out,
                        "# HELP {name} {help}.\n# TYPE {name} gauge\n{name} {v}"
                    );
                }
            }
            if let Some(v) = stats["uptime_s"].as_f64() {
                let _ = writeln!(
                    out,
                    "# HELP gangway_uptime_seconds Seconds since the gateway started.\n\
                     # TYPE gangway_uptime_seconds gauge\ngangway_uptime_seconds {v}"
                );
            }
            let connected = stats["mqtt"] == "connected";
            let _ = writeln!(
                out,
                "# HELP gangway_mqtt_connected Whether the broker link is up.\n\
                 # TYPE gangway_mqtt_connected gauge\ngangway_mqtt_connected {}",
                u8::from(connected)
            );
            let fallbacks = stats["fallbacks"].as_array().map_or(0, Vec::len);
            let _ = writeln!(
                out,
                "# HELP gangway_fallbacks Parts serving a fallback (listed in the stats).\n\
                 # TYPE gangway_fallbacks gauge\ngangway_fallbacks {fallbacks}"
            );
        }
        self.fix_age.write(
            &mut out,
            "gangway_fix_age_seconds",
            "How old a fix is when it reaches the sinks (its window's end to now; live clocks only).",
            &FIX_AGE_BOUNDS,
        );
        self.route_latency.write(
            &mut out,
            "gangway_route_latency_seconds",
            "Time from a route request to its route.",
            &ROUTE_BOUNDS,
        );
        let _ = writeln!(
            out,
            "# HELP gangway_web_streams Pages streaming the live map.\n\
             # TYPE gangway_web_streams gauge\ngangway_web_streams {streams}\n\
             # HELP gangway_web_batches_total Batches of fixes sent to the pages.\n\
             # TYPE gangway_web_batches_total counter\ngangway_web_batches_total {}",
            self.batches.load(Ordering::Relaxed)
        );
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn histograms_are_cumulative_and_counters_come_from_the_stats() {
        let m = Metrics::default();
        for us in [200, 800, 800, 3000, 900_000] {
            m.observe_route(us);
        }
        m.set_stats(&Stats {
            fixes: 42,
            tracked: 7,
            ..Stats::default()
        });
        let text = m.render(1);
        for line in [
            "gangway_fixes_total 42",
            "# TYPE gangway_fixes_total counter",
            "gangway_tracked 7",
            "gangway_route_latency_seconds_bucket{le=\"0.00025\"} 1",
            "gangway_route_latency_seconds_bucket{le=\"0.001\"} 3",
            "gangway_route_latency_seconds_bucket{le=\"0.005\"} 4",
            "gangway_route_latency_seconds_bucket{le=\"+Inf\"} 5",
            "gangway_route_latency_seconds_count 5",
            "gangway_web_streams 1",
        ] {
            assert!(text.lines().any(|l| l == line), "{line} missing:\n{text}");
        }
    }
}
