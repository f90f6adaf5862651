//! The retained `<prefix>/stats` payload: the gateway's counters, published
//! every `[mqtt] stats_interval_s` and whenever the BLE state changes; and
//! beside it the retained `<prefix>/heard` payload, the beacons heard most.
//! Schemas: docs/schemas/stats.schema.json, docs/schemas/heard.schema.json.

use serde::Serialize;

pub const STATS_SCHEMA: &str = "gangway.stats/1";
pub const HEARD_SCHEMA: &str = "gangway.heard/1";

/// Beacons listed on the `heard` topic, the most heard first: enough for a
/// building's beacons, small enough for any broker's payload limit.
pub const HEARD_PUBLISHED: usize = 100;

/// The counters in [`Stats`] that only grow, with a human name each (Home
/// Assistant discovery makes one sensor per entry).
pub const COUNTERS: [(&str, &str); 31] = [
    ("sightings", "Sightings"),
    ("sightings_ignored", "Sightings ignored"),
    ("fixes", "Fixes"),
    ("requests", "Route requests"),
    ("routes", "Routes"),
    ("request_errors", "Route errors"),
    ("route_line_fallbacks", "Routes served on their cells' line"),
    ("feedback", "Feedback"),
    ("scans", "Phone scans"),
    ("shared_in", "Shared sightings received"),
    ("shared_out", "Shared sightings sent"),
    ("rejected_messages", "Rejected messages"),
    ("oversized_messages", "Oversized messages"),
    ("inbound_dropped", "Incoming messages dropped"),
    ("bad_device_ids", "Unpublishable device ids"),
    ("queue_dropped", "Offline queue drops"),
    ("reconnects", "Reconnects"),
    ("reloads", "Reloads"),
    ("reload_failures", "Refused reloads"),
    ("recorded", "Learning records"),
    ("store_errors", "Learning store errors"),
    ("store_quota_deleted", "Learning rows over quota"),
    ("overloaded", "Requests refused: overloaded"),
    ("rate_limited", "Messages refused: rate limit"),
    ("feedback_refused", "Feedback refused"),
    ("evicted_devices", "Devices forgotten"),
    ("evicted_windows", "Fingerprint windows forgotten"),
    ("disconnects", "Broker connections lost"),
    ("unpublishable", "Unpublishable messages"),
    ("scan_restarts", "Silent scan restarts"),
    ("trackers_refused", "Fixes refused a Home Assistant tracker"),
];

/// Gauges (current values), with a human name each.
pub const GAUGES: [(&str, &str); 8] = [
    ("queue_depth", "Offline queue depth"),
    ("queue_bytes", "Offline queue bytes"),
    ("tracked", "Tracked devices"),
    ("windows", "Open fingerprint windows"),
    ("announced", "Announced device trackers"),
    ("pending_requests", "Route requests waiting"),
    ("heard", "Beacons heard"),
    ("heard_unknown", "Beacons heard the site lacks"),
];

/// One stats message.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct Stats {
    pub schema: &'static str,
    pub gateway: String,
    /// Seconds since the epoch.
    pub t: f64,
    pub uptime_s: f64,
    pub sightings: u64,
    /// Sightings of anchors the site does not know.
    pub sightings_ignored: u64,
    pub fixes: u64,
    pub requests: u64,
    pub routes: u64,
    pub request_errors: u64,
    /// Routes whose planner's line failed its check and were served on
    /// their cells' centres instead.
    pub route_line_fallbacks: u64,
    pub feedback: u64,
    pub scans: u64,
    pub shared_in: u64,
    pub shared_out: u64,
    /// Incoming messages refused (bad topic, device id or payload).
    pub rejected_messages: u64,
    /// Incoming messages over `[mqtt] max_payload_bytes`.
    pub oversized_messages: u64,
    /// Incoming messages dropped because the pipeline was behind.
    pub inbound_dropped: u64,
    /// Fixes not published because the device id cannot be a topic level.
    pub bad_device_ids: u64,
    pub queue_depth: u64,
    pub queue_bytes: u64,
    pub queue_dropped: u64,
    pub reconnects: u64,
    /// SIGHUP reloads applied, and refused (the old config kept serving).
    pub reloads: u64,
    pub reload_failures: u64,
    /// Rows written to the learning store, and failed writes.
    pub recorded: u64,
    pub store_errors: u64,
    /// Rows the learning store deleted to stay within its quotas.
    pub store_quota_deleted: u64,
    /// Route requests answered `overloaded` (too many waiting, or waited past
    /// `[limits] request_deadline_s`).
    pub overloaded: u64,
    /// Scans dropped and route requests answered `rate_limited` (`[limits]`).
    pub rate_limited: u64,
    /// Feedback for a route this gateway did not give (or already scored).
    pub feedback_refused: u64,
    /// Devices (tracks) and fingerprint windows forgotten: idle, or least
    /// recently seen past `[limits] max_devices`.
    pub evicted_devices: u64,
    pub evicted_windows: u64,
    /// MQTT connections lost after they were up.
    pub disconnects: u64,
    /// Outgoing messages no broker would take (a bad topic), dropped.
    pub unpublishable: u64,
    /// Bluetooth scans restarted after `[ble] silent_restart_s` of silence.
    pub scan_restarts: u64,
    pub tracked: u64,
    /// Entities with an open fingerprint window.
    pub windows: u64,
    /// Devices with a Home Assistant tracker config on the broker.
    pub announced: u64,
    /// Located fixes that did not make a Home Assistant tracker: of devices
    /// not in `[mqtt] ha_devices`, and over `ha_new_trackers_per_minute`.
    pub trackers_refused: u64,
    /// Route requests waiting to be planned.
    pub pending_requests: u64,
    /// Beacons heard since start (at most `[limits] max_devices`), and those
    /// of them the site does not have: the `heard` topic lists them.
    pub heard: u64,
    pub heard_unknown: u64,
    /// `connected`, `disconnected`, or `flapping` (lost repeatedly within a
    /// minute: the gateway cannot stay connected).
    pub mqtt: &'static str,
    /// The site's name and map hash, so a reload is visible.
    pub site: String,
    pub site_hash: String,
    /// Components that failed to load at start-up, each with what serves
    /// instead (empty: everything configured is serving).
    pub fallbacks: Vec<String>,
    pub ble: BleStatus,
    /// With `[localizer.recalibration]` on: what its runs did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub recalibration: Option<RecalibrationStatus>,
}

/// The recalibration of the survey-free radio model, visible to operators:
/// how many runs served a new model, how many failed, and what the last
/// one that served did on each floor.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct RecalibrationStatus {
    /// Runs that fitted and wrote a model (swapped in like a reload), and
    /// runs that failed (nothing changed).
    pub runs: u64,
    pub failures: u64,
    /// When the last run ended, seconds since the epoch.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_t: Option<f64>,
    /// Why the last run failed, when it did.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub last_error: Option<String>,
    /// The last run that served: each floor it recalibrated (one entry
    /// without `floor` on a one-floor site)...
    pub floors: Vec<FloorRecalibrated>,
    /// ...and each floor it left serving what it served, with why.
    pub skipped: Vec<FloorSkipped>,
}

/// What one floor's recalibration fitted and kept.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FloorRecalibrated {
    #[serde(skip_serializing_if = "Option::is_none")]
    pub floor: Option<String>,
    /// Fingerprint windows fitted.
    pub windows: usize,
    /// Beacons (or receivers) whose model was refitted, and of them those
    /// kept because the held-out windows are likelier with it.
    pub anchors: usize,
    pub anchors_kept: usize,
    /// Cells whose refined radio map was kept.
    pub cells_kept: usize,
    /// Log-likelihood gained per held-out window over the starting model.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub held_out_gain_per_window: Option<f64>,
}

/// A floor a recalibration left as it was.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FloorSkipped {
    pub floor: String,
    pub why: String,
}

/// The radio's state, visible to operators.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct BleStatus {
    /// `scanning`, `retrying` (adapter lost or missing), `starting`,
    /// `replay` when events come from a log, or `none` for a locator
    /// (`[cluster] role = "locator"`), which has no radio.
    pub state: &'static str,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub error: Option<String>,
    /// Failed attempts since the last successful start.
    pub failures: u64,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub retry_in_s: Option<f64>,
    /// Silent scans restarted; published as the top-level `scan_restarts`.
    #[serde(skip)]
    pub scan_restarts: u64,
}

/// One `heard` message: the beacons heard most since the gateway started,
/// known to the site or not, so a user can see what is in the air and which
/// beacons the site file lacks.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct HeardReport {
    pub schema: &'static str,
    pub gateway: String,
    /// Seconds since the epoch.
    pub t: f64,
    /// Beacons heard in all; `beacons` holds the [`HEARD_PUBLISHED`] heard most.
    pub heard: u64,
    pub heard_unknown: u64,
    /// Beacons forgotten to keep the list within `[limits] max_devices`
    /// (the least heard go first): non-zero under a flood of made-up ids.
    pub forgotten: u64,
    pub beacons: Vec<crate::sighting::heard::HeardBeacon>,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The counters are defined once, as [`Stats`]' fields, and exported to
    /// MQTT, `/metrics` and Home Assistant from [`COUNTERS`] and [`GAUGES`]:
    /// a field missing from both lists would be published on MQTT only, and
    /// a listed name that is no field would be silently absent everywhere.
    #[test]
    fn every_number_of_the_stats_is_a_listed_counter_or_gauge_and_back() {
        let json = serde_json::to_value(Stats::default()).unwrap();
        let numbers: Vec<&str> = json
            .as_object()
            .unwrap()
            .iter()
            .filter(|(_, v)| v.is_number())
            .map(|(k, _)| k.as_str())
            .collect();
        let listed: Vec<&str> = COUNTERS.iter().chain(&GAUGES).map(|(k, _)| *k).collect();
        for key in &listed {
            assert!(
                numbers.contains(key),
                "`{key}` is listed but not a number of the stats"
            );
        }
        // Time and uptime are not counters: `/metrics` writes uptime itself.
        let unlisted: Vec<&&str> = numbers
            .iter()
            .filter(|k| !listed.contains(k) && !["t", "uptime_s"].contains(k))
            .collect();
        assert!(unlisted.is_empty(), "numbers no list exports: {unlisted:?}");
    }
}
