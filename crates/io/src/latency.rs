//! How long the runtime takes: wall time from an input entering the runtime
//! (taken off its queue; for a route request, queued for planning) to the
//! outputs it made reaching the sinks, as histograms of fixes and of routes.
//!
//! Wall time on the gateway's own clock, never the events' time, so a
//! replayed log counts as a live radio does. Shared (atomics) between the
//! runtime, which observes, and whoever exports them (the web UI's
//! `/metrics`, as Prometheus histograms); here, beside the stats, because
//! both sides may import `publish` and neither may import the other.

use std::fmt::Write;
use std::sync::OnceLock;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use crate::clock::Clock;

/// The gateway's monotonic clock, for the core to time model calls and
/// route replies with (the core reads none itself: `gangway_core::clock`).
pub const MONOTONIC: Clock = Clock::new(monotonic_us);

/// Microseconds since the first reading in this process.
fn monotonic_us() -> u64 {
    static START: OnceLock<Instant> = OnceLock::new();
    START.get_or_init(Instant::now).elapsed().as_micros() as u64
}

/// Upper bounds (seconds) of the fix-latency buckets.
const FIX_BOUNDS: [f64; 12] = [
    0.000_05, 0.000_1, 0.000_25, 0.000_5, 0.001, 0.002_5, 0.005, 0.01, 0.025, 0.05, 0.1, 0.5,
];
/// Upper bounds (seconds) of the route-latency buckets: planning and the
/// wait in the admission queue.
const ROUTE_BOUNDS: [f64; 12] = [
    0.000_25, 0.000_5, 0.001, 0.002_5, 0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0,
];

/// The runtime's latency histograms.
#[derive(Debug, Default)]
pub struct Latency {
    fix: Histogram,
    route: Histogram,
}

impl Latency {
    pub fn observe_fix(&self, took: Duration) {
        self.fix.observe(&FIX_BOUNDS, took);
    }

    pub fn observe_route(&self, took: Duration) {
        self.route.observe(&ROUTE_BOUNDS, took);
    }

    /// Both histograms in the Prometheus text format.
    pub(crate) fn write_prometheus(&self, out: &mut String) {
        self.fix.write(
            out,
            "gangway_fix_latency_seconds",
            "Wall time from the input that made a fix entering the runtime to the fix reaching the sinks.",
            &FIX_BOUNDS,
        );
        self.route.write(
            out,
            "gangway_route_latency_seconds",
            "Wall time from a route request entering the runtime to its route reaching the sinks.",
            &ROUTE_BOUNDS,
        );
    }
}

/// A cumulative histogram of fixed bounds.
#[derive(Debug)]
struct Histogram {
    counts: [AtomicU64; 12],
    count: AtomicU64,
    sum_ns: AtomicU64,
}

impl Default for Histogram {
    fn default() -> Self {
        Histogram {
            counts: std::array::from_fn(|_| AtomicU64::new(0)),
            count: AtomicU64::new(0),
            sum_ns: AtomicU64::new(0),
        }
    }
}

impl Histogram {
    fn observe(&self, bounds: &[f64; 12], took: Duration) {
        let seconds = took.as_secs_f64();
        if let Some(i) = bounds.iter().position(|&b| seconds <= b) {
            self.counts[i].fetch_add(1, Ordering::Relaxed);
        }
        self.count.fetch_add(1, Ordering::Relaxed);
        let ns = u64::try_from(took.as_nanos()).unwrap_or(u64::MAX);
        self.sum_ns.fetch_add(ns, Ordering::Relaxed);
    }

    fn write(&self, out: &mut String, name: &str, help: &str, bounds: &[f64; 12]) {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} histogram");
        let mut cumulative = 0;
        for (bound, count) in bounds.iter().zip(&self.counts) {
            cumulative += count.load(Ordering::Relaxed);
            let _ = writeln!(out, "{name}_bucket{{le=\"{bound}\"}} {cumulative}");
        }
        let count = self.count.load(Ordering::Relaxed);
        let sum = self.sum_ns.load(Ordering::Relaxed) as f64 / 1e9;
        let _ = writeln!(
            out,
            "{name}_bucket{{le=\"+Inf\"}} {count}\n{name}_sum {sum}\n{name}_count {count}"
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn buckets_are_cumulative_and_the_sum_is_in_seconds() {
        let latency = Latency::default();
        for us in [200, 800, 800, 3000, 900_000] {
            latency.observe_route(Duration::from_micros(us));
        }
        latency.observe_fix(Duration::from_micros(30));
        let mut text = String::new();
        latency.write_prometheus(&mut text);
        for line in [
            "# TYPE gangway_route_latency_seconds histogram",
            "gangway_route_latency_seconds_bucket{le=\"0.00025\"} 1",
            "gangway_route_latency_seconds_bucket{le=\"0.001\"} 3",
            "gangway_route_latency_seconds_bucket{le=\"0.005\"} 4",
            "gangway_route_latency_seconds_bucket{le=\"1\"} 5",
            "gangway_route_latency_seconds_bucket{le=\"+Inf\"} 5",
            "gangway_route_latency_seconds_count 5",
            "gangway_route_latency_seconds_sum 0.9048",
            "gangway_fix_latency_seconds_bucket{le=\"0.00005\"} 1",
            "gangway_fix_latency_seconds_count 1",
        ] {
            assert!(text.lines().any(|l| l == line), "{line} missing:\n{text}");
        }
    }
}
