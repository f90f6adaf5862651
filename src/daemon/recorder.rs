//! Feeds the learning store ([`crate::store`]) from what the daemon publishes:
//! every location is a point of a device's smoothed trajectory, every route
//! reply a route given, plus the feedback received. Records are buffered and
//! written once a second in one transaction; a failing disk is logged and
//! counted, and never stops the daemon (the buffer is dropped, so memory stays
//! bounded). A store that cannot be opened is moved aside and started afresh
//! ([`Store::open_or_move_aside`]); one that cannot even be created leaves
//! the gateway serving without recording. Either way it is listed in the
//! stats' fallbacks.

use serde::Deserialize;

use crate::publish::{LOCATION_SCHEMA, Message, PATH_SCHEMA};
use crate::site::Cell;
use crate::store::{Record, Store, StoreConfig, StoreError};

/// How often old rows are pruned, in seconds.
const PRUNE_EVERY_S: f64 = 3600.0;
/// How often the quotas are enforced, in seconds.
const QUOTA_EVERY_S: f64 = 60.0;
/// Records buffered at most between two writes.
const MAX_PENDING: usize = 100_000;

pub struct Recorder {
    store: Store,
    config: StoreConfig,
    pending: Vec<Record>,
    last_prune: f64,
    last_quota: f64,
    pub errors: u64,
    pub written: u64,
    /// Rows deleted to stay within the quotas.
    pub quota_deleted: u64,
}

#[derive(Deserialize)]
struct LocationFields {
    device: String,
    t: f64,
    cell: Cell,
    confidence: f32,
}

#[derive(Deserialize)]
struct Waypoint {
    cell: Cell,
}

#[derive(Deserialize)]
struct RouteFields {
    device: String,
    request_id: Option<String>,
    t: f64,
    planner: String,
    waypoints: Vec<Waypoint>,
}

impl Recorder {
    /// Opens the store, moving a broken one aside; returns the recorder and,
    /// when the store had to be moved aside, what happened.
    /// The first prune is an hour after `now` (seconds since the epoch), not
    /// at once: a replayed log's old timestamps would be pruned as they come.
    pub fn open(config: &StoreConfig, now: f64) -> Result<(Recorder, Option<String>), StoreError> {
        let path = config.resolved_path();
        let (store, moved) = Store::open_or_move_aside(&path)?;
        if let Some(moved) = &moved {
            tracing::error!("{moved}");
        }
        tracing::info!(path = %path.display(), "recording trajectories, routes and feedback");
        let recorder = Recorder {
            store,
            config: config.clone(),
            pending: Vec::new(),
            last_prune: now,
            last_quota: f64::NEG_INFINITY,
            errors: 0,
            written: 0,
            quota_deleted: 0,
        };
        Ok((recorder, moved))
    }

    /// Keeps what a published message teaches: fixes and routes given.
    pub fn published(&mut self, message: &Message) {
        let schema = &message.payload["schema"];
        let record = if *schema == LOCATION_SCHEMA {
            LocationFields::deserialize(&message.payload)
                .ok()
                .map(|l| Record::Fix {
                    device: l.device,
                    t: l.t,
                    cell: l.cell,
                    confidence: l.confidence,
                })
        } else if *schema == PATH_SCHEMA {
            // Error replies have no waypoints and teach nothing.
            RouteFields::deserialize(&message.payload)
                .ok()
                .map(|r| Record::Route {
                    device: r.device,
                    request_id: r.request_id,
                    t: r.t,
                    planner: r.planner,
                    cells: r.waypoints.into_iter().map(|w| w.cell).collect(),
                })
        } else {
            None
        };
        if let Some(record) = record {
            self.push(record);
        }
    }

    pub fn push(&mut self, record: Record) {
        if self.pending.len() < MAX_PENDING {
            self.pending.push(record);
        }
    }

    /// Writes what is buffered, and prunes once an hour.
    pub fn flush(&mut self, now: f64) {
        if !self.pending.is_empty() {
            match self.store.write(&self.pending) {
                Ok(()) => self.written += self.pending.len() as u64,
                Err(e) => {
                    self.errors += 1;
                    tracing::error!(lost = self.pending.len(), "learning store: {e}");
                }
            }
            self.pending.clear();
        }
        if now - self.last_quota >= QUOTA_EVERY_S {
            self.last_quota = now;
            match self.store.enforce_quotas(&self.config) {
                Ok(0) => {}
                Ok(n) => {
                    self.quota_deleted += n as u64;
                    tracing::warn!(
                        deleted = n,
                        "learning store over its quota: oldest rows deleted"
                    );
                }
                Err(e) => {
                    self.errors += 1;
                    tracing::error!("learning store: {e}");
                }
            }
        }
        if now - self.last_prune >= PRUNE_EVERY_S {
            self.last_prune = now;
            let retention_s = self.config.retention_days * 86_400.0;
            match self.store.prune(now, retention_s, self.config.max_fixes) {
                Ok(0) => {}
                Ok(n) => tracing::info!(deleted = n, "learning store pruned"),
                Err(e) => {
                    self.errors += 1;
                    tracing::error!("learning store: {e}");
                }
            }
        }
    }
}
