//! Rate-limited warnings: when hostile input or overload repeats thousands of
//! times a second, the log gets the first occurrence and then one line per
//! period with how many were not logged, instead of a line each (which would
//! fill the disk and slow the gateway down).

use std::time::{Duration, Instant};

/// Says when a repeated warning may be logged again.
#[derive(Debug)]
pub struct Throttle {
    period: Duration,
    last: Option<Instant>,
    suppressed: u64,
}

impl Throttle {
    pub fn new(period: Duration) -> Self {
        Throttle {
            period,
            last: None,
            suppressed: 0,
        }
    }

    /// Call once per occurrence: `Some(n)` when this one may be logged, `n`
    /// being how many were not since the last one logged; `None` otherwise.
    pub fn ready(&mut self) -> Option<u64> {
        let now = Instant::now();
        if self
            .last
            .is_some_and(|last| now.duration_since(last) < self.period)
        {
            self.suppressed += 1;
            return None;
        }
        self.last = Some(now);
        Some(std::mem::take(&mut self.suppressed))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_first_is_logged_then_one_per_period_with_the_count_between() {
        let mut t = Throttle::new(Duration::from_millis(50));
        assert_eq!(t.ready(), Some(0));
        for _ in 0..1000 {
            assert_eq!(t.ready(), None);
        }
        std::thread::sleep(Duration::from_millis(60));
        assert_eq!(t.ready(), Some(1000));
        std::thread::sleep(Duration::from_millis(60));
        assert_eq!(t.ready(), Some(0));
    }
}
