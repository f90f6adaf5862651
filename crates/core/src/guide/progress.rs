//! How far along its route a walker is, from the progress of each located
//! fix: a constant-velocity Kalman filter along the route, predicted to any
//! moment at the walker's pace.
//!
//! A fix is late and noisy: it stands for the middle of its fingerprint
//! window, and the tracker, which would rather a walker stood still, holds
//! it back for a fix or two after they set off and then lets it jump ahead
//! (`gangway eval guidance`: a fix's progress lies from 3 m behind to 1 m
//! ahead of where the walker was half a window earlier, p10 to p90). So
//! the filter places each fix at the time the walker was there (`t` minus
//! the fix's lag), trusts it only as far as that spread, and starts a
//! walker off at their profile's pace: someone who has just been given a
//! route sets off. Between fixes the progress is predicted forward, so a
//! decision point can be announced at the moment it truly is about
//! `announce_m` ahead rather than at the next fix.

/// How quickly a walker following a route changes pace, m/s²: the filter's
/// process noise. People keep a steady pace along a route and take a few
/// seconds to slow down or stop; this is a property of walking, not of a
/// site. (0.5 m/s² followed the tracker's stalls and jumps: `gangway eval
/// guidance` put 0.1 m/s² a third nearer the truth, docs/guidance.md.)
const PACE_CHANGE_MPS2: f64 = 0.1;

/// The filter's state: progress and speed along the route with their
/// covariance (kept in f32, computed in f64: every guided session holds one).
#[derive(Clone, Copy, Debug)]
pub(crate) struct Progress {
    /// Filtered progress at `t`, metres from the route's start.
    m: f32,
    /// Walking speed along the route, m/s (never negative: walking back
    /// along the route shows as leaving it, not as progress).
    v: f32,
    /// Covariance of (m, v): [mm, mv, vv].
    p: [f32; 3],
    /// When the walker was where the last fix folded in placed them.
    t: f64,
}

impl Progress {
    /// A walker setting off from the route's start at `t` at about
    /// `speed_mps` (within a quarter of it, one standard deviation);
    /// `spread_m` is how far a fix's progress strays from the truth.
    pub(crate) fn new(t: f64, speed_mps: f64, spread_m: f64) -> Progress {
        let speed_spread = speed_mps / 4.0;
        Progress {
            m: 0.0,
            v: speed_mps as f32,
            p: [
                (spread_m * spread_m) as f32,
                0.0,
                (speed_spread * speed_spread) as f32,
            ],
            t,
        }
    }

    /// Filtered progress predicted to time `t` at the filtered speed.
    pub(crate) fn at(&self, t: f64) -> f64 {
        self.at_speed(t, self.speed_mps())
    }

    /// Filtered progress predicted to time `t` at `speed_mps`.
    pub(crate) fn at_speed(&self, t: f64, speed_mps: f64) -> f64 {
        f64::from(self.m) + speed_mps * (t - self.t).max(0.0)
    }

    /// Filtered speed along the route, m/s.
    pub(crate) fn speed_mps(&self) -> f64 {
        f64::from(self.v)
    }

    /// Folds in the progress `z` (metres along the route) the walker had at
    /// `t`, as a fix of spread `spread_m` says; the speed stays within
    /// `0..=max_mps`. A fix from before the last one moves nothing.
    pub(crate) fn update(&mut self, t: f64, z: f64, spread_m: f64, max_mps: f64) {
        if t < self.t {
            return;
        }
        let dt = t - self.t;
        self.t = t;
        // Predict: progress moves on at the speed; both grow uncertain by
        // how much the pace may have changed.
        let q = PACE_CHANGE_MPS2 * PACE_CHANGE_MPS2;
        let [mm, mv, vv] = self.p.map(f64::from);
        let (m, v) = (
            f64::from(self.m) + f64::from(self.v) * dt,
            f64::from(self.v),
        );
        let mm = mm + 2.0 * dt * mv + dt * dt * vv + q * dt.powi(4) / 4.0;
        let mv = mv + dt * vv + q * dt.powi(3) / 2.0;
        let vv = vv + q * dt * dt;
        // Correct by the fix.
        let s = mm + spread_m * spread_m;
        let (gain_m, gain_v) = (mm / s, mv / s);
        let residual = z - m;
        self.m = (m + gain_m * residual) as f32;
        self.v = (v + gain_v * residual).clamp(0.0, max_mps) as f32;
        self.p = [(1.0 - gain_m) * mm, (1.0 - gain_m) * mv, vv - gain_v * mv].map(|x| x as f32);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn learns_the_pace_and_predicts_ahead_of_late_fixes() {
        // A walker at 0.9 m/s (the profile says 1.2) whose fixes, every
        // 2 s, show where they were 2 s before, give or take a metre.
        let mut progress = Progress::new(0.0, 1.2, 1.0);
        let jitter = [0.8, -0.5, 0.3, -0.9, 0.6, -0.2, 0.9, -0.7, 0.1, -0.4];
        for k in 1..=30 {
            let t = 2.0 * f64::from(k);
            let was = t - 2.0;
            progress.update(was, 0.9 * was + jitter[k as usize % 10], 1.0, 2.4);
        }
        assert!((progress.speed_mps() - 0.9).abs() < 0.1, "{progress:?}");
        let now = progress.at(60.0);
        assert!(
            (now - 54.0).abs() < 1.0,
            "at 60 s, 2 s after the last fix: {now}"
        );
    }

    #[test]
    fn a_walker_standing_still_is_not_predicted_forward() {
        let mut progress = Progress::new(0.0, 1.2, 2.0);
        for k in 1..=20 {
            progress.update(2.0 * f64::from(k), 5.0, 2.0, 2.4);
        }
        assert!(progress.speed_mps() < 0.3, "{progress:?}");
        assert!((progress.at(43.0) - 5.0).abs() < 1.0, "{progress:?}");
        // Fixes out of order change nothing.
        let before = progress.at(50.0);
        progress.update(10.0, 30.0, 2.0, 2.4);
        assert_eq!(progress.at(50.0), before);
    }
}
