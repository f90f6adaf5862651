//! Time the core may measure but never decides by: how long a model call or
//! a route took (`plan::Timings`, a reply's `latency_us`).
//!
//! The core reads no clock. Whoever builds it passes one in: the gateway's
//! config loader sets the process's monotonic clock
//! (`gangway_io::config::Config::load`), and a test or a pipeline built by
//! hand keeps [`Clock::NONE`], whose measurements are all 0. Nothing the
//! core outputs apart from those measurements may depend on the clock, so
//! the daemon's behaviour stays testable from a log (budgets are counts,
//! such as `[planner.rejection] max_samples`; time comes with the events).

use std::fmt;

/// A monotonic clock in microseconds, or none.
#[derive(Clone, Copy, Default)]
pub struct Clock(Option<fn() -> u64>);

impl Clock {
    /// No clock: every measurement is 0.
    pub const NONE: Clock = Clock(None);

    /// A clock reading `micros`, which must not go backwards.
    pub const fn new(micros: fn() -> u64) -> Clock {
        Clock(Some(micros))
    }

    /// Starts a measurement.
    pub(crate) fn start(self) -> Stopwatch {
        Stopwatch {
            clock: self,
            started: self.0.map_or(0, |micros| micros()),
        }
    }
}

impl fmt::Debug for Clock {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(if self.0.is_some() {
            "Clock"
        } else {
            "Clock::NONE"
        })
    }
}

/// A measurement in progress.
#[derive(Clone, Copy)]
pub(crate) struct Stopwatch {
    clock: Clock,
    started: u64,
}

impl Stopwatch {
    /// Microseconds since [`Clock::start`] (0 without a clock).
    pub(crate) fn elapsed_us(self) -> u64 {
        self.clock
            .0
            .map_or(0, |micros| micros().saturating_sub(self.started))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn no_clock_measures_nothing_and_a_clock_measures_its_ticks() {
        assert_eq!(Clock::NONE.start().elapsed_us(), 0);
        fn ticking() -> u64 {
            use std::sync::atomic::{AtomicU64, Ordering};
            static NOW: AtomicU64 = AtomicU64::new(0);
            NOW.fetch_add(7, Ordering::Relaxed)
        }
        let watch = Clock::new(ticking).start();
        assert_eq!(watch.elapsed_us(), 7);
    }
}
