//! The runtime's part as a locator (`[cluster] role = "locator"`): which
//! devices it locates, its heartbeats, and the route requests of devices it
//! does not own yet.
//!
//! Every locator of a site subscribes to every device's route requests (they
//! are few), and only the owner of a device's shard answers. A locator that
//! dies may take requests with it that reached the broker after its last
//! heartbeat, and nobody would answer them. So each locator holds the
//! requests of devices it does not own for one lease and a heartbeat: when it
//! takes over a shard from a locator that went away, it answers those of
//! that shard (a route or, if it has not located the device yet, an error).
//! A request can then be answered twice, never not at all.

use std::collections::VecDeque;

use crate::cluster::{Beat, Change, Membership, shard_of};
use crate::event::RouteRequest;
use crate::mqtt::cluster::ClusterConfig;
use crate::publish::Output;
use crate::throttle::Throttle;

/// Requests of devices this locator does not own, held at most.
const HELD_MAX: usize = 1024;

/// This locator's membership, and what it holds for a takeover.
pub(super) struct Locator {
    membership: Membership,
    /// How long a request of another locator's device is held, seconds.
    hold_s: f64,
    /// Requests of devices this locator does not own, with when they came.
    held: VecDeque<(f64, RouteRequest)>,
    refused: Throttle,
}

impl Locator {
    pub(super) fn new(config: &ClusterConfig, id: &str, now: f64) -> Locator {
        tracing::info!(
            locator = id,
            shards = config.shards,
            lease_s = config.lease_s,
            "locator: listening for the site's other locators for one lease before serving"
        );
        Locator {
            membership: Membership::new(id, config.shards, config.lease_s, now),
            hold_s: config.lease_s + config.heartbeat_s,
            held: VecDeque::new(),
            refused: Throttle::new(super::WARN_EVERY),
        }
    }

    /// Whether this locator locates `device` now.
    pub(super) fn owns(&self, device: &str) -> bool {
        self.membership.owns_device(device)
    }

    /// Whether an output goes out: a device's location and guidance only
    /// from its owner (a shard just handed over may still close a window).
    pub(super) fn keeps(&self, output: &Output) -> bool {
        match output {
            Output::Location(l) => self.owns(&l.device),
            Output::Guidance(g) => self.owns(&g.device),
            _ => true,
        }
    }

    /// Time passing (every heartbeat): this locator's heartbeat goes out,
    /// and requests of shards taken over are returned to be answered.
    pub(super) fn beat(&mut self, now: f64, out: &mut Vec<Output>) -> Vec<RouteRequest> {
        let change = self.membership.tick(now);
        self.changed(&change, now);
        out.push(Output::Beat(self.membership.beat(now)));
        self.take_over(&change, now)
    }

    /// Another locator's heartbeat. A change of shards is announced at once
    /// (so the sink follows it); requests of shards taken over are returned.
    pub(super) fn heard(
        &mut self,
        beat: &Beat,
        now: f64,
        out: &mut Vec<Output>,
    ) -> Result<Vec<RouteRequest>, ()> {
        let change = match self.membership.heard(beat, now) {
            Ok(change) => change,
            Err(e) => {
                if let Some(more) = self.refused.ready() {
                    tracing::warn!(not_logged = more, "heartbeat refused: {e}");
                }
                return Err(());
            }
        };
        if !change.is_empty() {
            self.changed(&change, now);
            out.push(Output::Beat(self.membership.beat(now)));
        }
        Ok(self.take_over(&change, now))
    }

    /// A route request: `Some` to serve it here, `None` when another
    /// locator owns the device (held for a takeover).
    pub(super) fn route(&mut self, request: RouteRequest, now: f64) -> Option<RouteRequest> {
        if self.owns(&request.device) {
            return Some(request);
        }
        self.forget_old(now);
        if self.held.len() == HELD_MAX {
            self.held.pop_front();
        }
        self.held.push_back((now, request));
        None
    }

    /// Stops serving (shutdown): the last heartbeat says so, and the others
    /// take the shards over at once.
    pub(super) fn leave(&mut self, now: f64, out: &mut Vec<Output>) {
        self.membership.leave();
        out.push(Output::Beat(self.membership.beat(now)));
    }

    fn changed(&self, change: &Change, now: f64) {
        if change.is_empty() {
            return;
        }
        let others: Vec<&str> = self.membership.others().collect();
        tracing::info!(
            gained = change.gained.len(),
            lost = change.lost.len(),
            owned = self.membership.owned().len(),
            taken_over = change.taken_over,
            ?others,
            t = now,
            "locator: shards changed"
        );
    }

    /// The held requests of the shards `change` took over from a locator
    /// that went away.
    fn take_over(&mut self, change: &Change, now: f64) -> Vec<RouteRequest> {
        self.forget_old(now);
        if !change.taken_over {
            return Vec::new();
        }
        let shards = self.membership.shards();
        let (mine, others): (VecDeque<_>, VecDeque<_>) = std::mem::take(&mut self.held)
            .into_iter()
            .partition(|(_, r)| change.gained.contains(&shard_of(&r.device, shards)));
        self.held = others;
        mine.into_iter().map(|(_, r)| r).collect()
    }

    fn forget_old(&mut self, now: f64) {
        while self
            .held
            .front()
            .is_some_and(|(at, _)| now - at > self.hold_s)
        {
            self.held.pop_front();
        }
    }
}
