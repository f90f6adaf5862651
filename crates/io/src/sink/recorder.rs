//! The learning store ([`crate::store`]) as a sink: every known location is
//! a point of a device's smoothed trajectory, every route a route given, plus
//! the feedback accepted, each finished guidance session's adherence and,
//! with recalibration on, what was heard per window (the newest
//! [`Recorder::keep_heard`] kept).
//! Records are buffered and written once a second in one transaction; a
//! failing disk is logged and counted, and never stops the daemon (the buffer
//! is dropped, so memory stays bounded). A store that cannot be opened is moved aside and started afresh
//! ([`Store::open_or_move_aside`]); one that cannot even be created leaves
//! the gateway serving without recording. Either way it is listed in the
//! stats' fallbacks.

use futures::future::BoxFuture;

use super::Sink;
use crate::publish::stats::Stats;
use crate::publish::{Output, RouteOutcome};
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
    /// Why the store is not the configured file, if it had to be moved aside.
    fallback: Option<String>,
    errors: u64,
    written: u64,
    /// Rows deleted to stay within the quotas.
    quota_deleted: u64,
    /// Heard windows kept at most ([`Recorder::keep_heard`]).
    max_heard: Option<usize>,
}

impl Recorder {
    /// Opens the store, moving a broken one aside; returns the recorder and,
    /// when the store had to be moved aside, what happened.
    /// The first prune is an hour after `now` (seconds since the epoch), not
    /// at once: a replayed log's old timestamps would be pruned as they come.
    pub fn open(config: &StoreConfig, now: f64) -> Result<Recorder, StoreError> {
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
            fallback: moved,
            errors: 0,
            written: 0,
            quota_deleted: 0,
            max_heard: None,
        };
        Ok(recorder)
    }

    /// Keeps at most the newest `max` heard windows (recalibration's
    /// `max_windows`), checked with the quotas.
    pub fn keep_heard(mut self, max: usize) -> Recorder {
        self.max_heard = Some(max);
        self
    }

    /// What an output teaches, if anything, handed to `keep`: a record,
    /// or a route across floors as a route per floor.
    fn record(output: &Output, mut keep: impl FnMut(Record)) {
        keep(match output {
            // An unknown location is no point of a walk.
            Output::Location(l) => Record::Fix {
                device: l.device.clone(),
                t: l.t,
                floor: l.floor.as_ref().map(|f| f.name.clone()),
                cell: match l.cell {
                    Some(cell) => cell,
                    None => return,
                },
                confidence: l.confidence,
            },
            // Error replies teach nothing.
            Output::Route(reply) => match &reply.outcome {
                RouteOutcome::Route(body) => Record::Route {
                    device: reply.device.clone(),
                    request_id: reply.request_id.clone(),
                    t: reply.t,
                    floor: None,
                    planner: body.planner.to_owned(),
                    cells: body.waypoints.iter().map(|w| w.cell).collect(),
                },
                // The store learns walks per floor: each leg is a route on
                // its floor's grid, rated by the feedback on the whole.
                RouteOutcome::Floors(body) => {
                    for leg in &body.legs {
                        keep(Record::Route {
                            device: reply.device.clone(),
                            request_id: reply.request_id.clone(),
                            t: reply.t,
                            floor: Some(leg.floor.clone()),
                            planner: leg.route.planner.to_owned(),
                            cells: leg.route.waypoints.iter().map(|w| w.cell).collect(),
                        });
                    }
                    return;
                }
                RouteOutcome::Error { .. } => return,
            },
            Output::Feedback(f) => Record::Feedback {
                device: f.device.clone(),
                request_id: f.request_id.clone(),
                t: f.t,
                score: f.score,
            },
            Output::Adherence(a) => Record::Adherence(a.clone()),
            Output::Heard(h) => Record::Heard {
                device: h.device.clone(),
                t: h.t,
                floor: h.floor.clone(),
                readings: h.readings.clone(),
            },
            _ => return,
        })
    }

    fn push(&mut self, record: Record) {
        if self.pending.len() < MAX_PENDING {
            self.pending.push(record);
        }
    }

    /// Writes what is buffered, and prunes once an hour.
    fn write(&mut self, now: f64) {
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
            if let Some(max) = self.max_heard
                && let Err(e) = self.store.keep_newest_heard(max)
            {
                self.errors += 1;
                tracing::error!("learning store: {e}");
            }
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

impl Sink for Recorder {
    fn name(&self) -> &'static str {
        "store"
    }

    fn send(&mut self, outputs: &[Output]) -> anyhow::Result<()> {
        for output in outputs {
            Recorder::record(output, |record| self.push(record));
        }
        Ok(())
    }

    fn tick(&mut self, now: f64) {
        self.write(now);
    }

    fn report(&self, stats: &mut Stats) {
        stats.recorded = self.written;
        stats.store_errors = self.errors;
        stats.store_quota_deleted = self.quota_deleted;
        stats.fallbacks.extend(self.fallback.clone());
    }

    fn shutdown(mut self: Box<Self>) -> BoxFuture<'static, anyhow::Result<()>> {
        self.write(crate::source::unix_now());
        Box::pin(std::future::ready(Ok(())))
    }
}
