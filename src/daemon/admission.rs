//! What the daemon takes from others, bounded: route requests wait in a
//! bounded queue and are answered `overloaded` when it is full or they waited
//! too long (never dropped in silence); scans and requests are rate-limited
//! per device; feedback is taken only for routes this gateway gave.

use std::collections::{HashSet, VecDeque};
use std::time::{Duration, Instant};

use foldhash::HashMap;

use crate::event::RouteRequest;

/// Counts per key within the current second of event time: a fixed window,
/// emptied every second, so it holds only the keys of the last second.
pub(super) struct PerSecond {
    limit: u32,
    second: i64,
    counts: HashMap<String, u32>,
}

impl PerSecond {
    pub(super) fn new(limit: u32) -> Self {
        PerSecond {
            limit,
            second: i64::MIN,
            counts: HashMap::default(),
        }
    }

    /// Counts one for `key` at `now` (seconds); false past the limit.
    pub(super) fn allow(&mut self, key: &str, now: f64) -> bool {
        let second = now.floor() as i64;
        if second != self.second {
            self.second = second;
            self.counts.clear();
        }
        let count = match self.counts.get_mut(key) {
            Some(c) => c,
            None => self.counts.entry(key.to_owned()).or_insert(0),
        };
        *count = count.saturating_add(1);
        *count <= self.limit
    }
}

/// A route request waiting to be planned.
pub(super) struct Waiting {
    pub request: RouteRequest,
    pub received: Instant,
}

/// Route requests waiting to be planned, bounded in number and in wait.
pub(super) struct Requests {
    queue: VecDeque<Waiting>,
    max: usize,
    deadline: Duration,
}

/// What to do with a request.
pub(super) enum Admit {
    /// Plan it.
    Serve(RouteRequest),
    /// Answer `overloaded`; the message says why.
    Overloaded(RouteRequest, String),
}

impl Requests {
    pub(super) fn new(max: usize, deadline: Duration) -> Self {
        Requests {
            queue: VecDeque::new(),
            max,
            deadline,
        }
    }

    pub(super) fn len(&self) -> usize {
        self.queue.len()
    }

    pub(super) fn is_empty(&self) -> bool {
        self.queue.is_empty()
    }

    /// Queues a request; when the queue is full, hands it back to be
    /// answered `overloaded`, with why.
    pub(super) fn push(&mut self, request: RouteRequest) -> Option<(RouteRequest, String)> {
        if self.queue.len() >= self.max {
            let why = format!(
                "the gateway is overloaded: {} route requests are waiting",
                self.queue.len()
            );
            return Some((request, why));
        }
        self.queue.push_back(Waiting {
            request,
            received: Instant::now(),
        });
        None
    }

    /// When the next request was queued.
    pub(super) fn next_received(&self) -> Option<Instant> {
        self.queue.front().map(|w| w.received)
    }

    /// The next request, to plan or, if it waited past the deadline, to
    /// answer `overloaded`.
    pub(super) fn take_next(&mut self) -> Option<Admit> {
        let w = self.queue.pop_front()?;
        let waited = w.received.elapsed();
        Some(if waited > self.deadline {
            let why = format!(
                "the gateway is overloaded: the request waited {:.1} s, past its {:.1} s deadline",
                waited.as_secs_f64(),
                self.deadline.as_secs_f64()
            );
            Admit::Overloaded(w.request, why)
        } else {
            Admit::Serve(w.request)
        })
    }
}

/// The routes this gateway gave recently, by device and request id: feedback
/// is taken once for each, and refused for anything else. The oldest are
/// forgotten past the bound.
pub(super) struct Issued {
    max: usize,
    order: VecDeque<(String, String)>,
    open: HashSet<(String, String)>,
}

impl Issued {
    pub(super) fn new(max: usize) -> Self {
        Issued {
            max,
            order: VecDeque::new(),
            open: HashSet::new(),
        }
    }

    pub(super) fn insert(&mut self, device: &str, request_id: &str) {
        let key = (device.to_owned(), request_id.to_owned());
        if self.open.insert(key.clone()) {
            self.order.push_back(key);
        }
        while self.order.len() > self.max {
            if let Some(old) = self.order.pop_front() {
                self.open.remove(&old);
            }
        }
    }

    /// Whether feedback on this route is taken now (given, and not scored
    /// yet); a route is scored once.
    pub(super) fn take(&mut self, device: &str, request_id: &str) -> bool {
        self.open
            .remove(&(device.to_owned(), request_id.to_owned()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::Destination;

    fn request(id: &str) -> RouteRequest {
        RouteRequest {
            t: 0.0,
            device: "p".into(),
            to: Destination::Place("x".into()),
            floor: None,
            profile: None,
            request_id: Some(id.into()),
        }
    }

    #[test]
    fn a_full_queue_and_a_late_request_are_answered_overloaded() {
        let mut q = Requests::new(2, Duration::from_millis(30));
        assert!(q.push(request("a")).is_none());
        assert!(q.push(request("b")).is_none());
        assert!(
            matches!(q.push(request("c")), Some((r, _)) if r.request_id.as_deref() == Some("c"))
        );
        assert!(matches!(q.take_next(), Some(Admit::Serve(_))));
        std::thread::sleep(Duration::from_millis(40));
        assert!(
            matches!(q.take_next(), Some(Admit::Overloaded(_, why)) if why.contains("deadline"))
        );
        assert!(q.take_next().is_none());
    }

    #[test]
    fn rates_are_per_key_and_per_second() {
        let mut r = PerSecond::new(2);
        assert!(r.allow("a", 10.1) && r.allow("a", 10.2));
        assert!(!r.allow("a", 10.3));
        assert!(r.allow("b", 10.4));
        assert!(r.allow("a", 11.0));
    }

    #[test]
    fn feedback_is_taken_once_for_routes_given_and_only_the_latest_are_kept() {
        let mut issued = Issued::new(2);
        issued.insert("p", "r1");
        issued.insert("p", "r2");
        issued.insert("p", "r3");
        assert!(!issued.take("p", "r1"), "forgotten past the bound");
        assert!(!issued.take("q", "r2"), "another device's route");
        assert!(issued.take("p", "r2"));
        assert!(!issued.take("p", "r2"), "scored once");
        assert!(!issued.take("p", "never"));
    }
}
