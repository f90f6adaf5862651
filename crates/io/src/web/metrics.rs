//! `GET /metrics`: the gateway's counters and gauges in the Prometheus text
//! format, named `gangway_…`, plus the runtime's histograms of fix and route
//! latency ([`Latency`]).
//!
//! The counters and gauges are the ones the retained MQTT stats carry
//! ([`COUNTERS`], [`GAUGES`]), read from the last stats output, so the two
//! never disagree. The text format is written here: it is three lines a
//! series, and the values already exist as numbers.

use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use crate::latency::Latency;
use crate::publish::stats::{COUNTERS, GAUGES, Stats};

pub(super) struct Metrics {
    stats: Mutex<Option<serde_json::Value>>,
    /// Observed by the runtime.
    pub latency: Arc<Latency>,
    /// Batches of fixes sent to the pages.
    pub batches: AtomicU64,
}

impl Metrics {
    pub(super) fn new(latency: Arc<Latency>) -> Metrics {
        Metrics {
            stats: Mutex::new(None),
            latency,
            batches: AtomicU64::new(0),
        }
    }

    pub(super) fn set_stats(&self, stats: &Stats) {
        let json = serde_json::to_value(stats).expect("plain data serializes");
        *self.stats.lock().unwrap_or_else(|e| e.into_inner()) = Some(json);
    }

    /// The exposition text; `streams` pages are watching.
    pub(super) fn render(&self, streams: usize) -> String {
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
        self.latency.write_prometheus(&mut out);
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
    fn counters_and_gauges_come_from_the_stats_beside_the_histograms() {
        let m = Metrics::new(Arc::default());
        m.latency.observe_fix(std::time::Duration::from_micros(40));
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
            "# TYPE gangway_fix_latency_seconds histogram",
            "gangway_fix_latency_seconds_count 1",
            "gangway_route_latency_seconds_count 0",
            "gangway_web_streams 1",
        ] {
            assert!(text.lines().any(|l| l == line), "{line} missing:\n{text}");
        }
    }
}
