//! How far along its route a walker is by now, from the progress of each
//! located fix: a constant-velocity Kalman filter along the route.
//!
//! A fix is late and noisy: it stands for the middle of a fingerprint window,
//! the tracker settles behind the walker, and its projection on the route
//! jumps by metres from one fix to the next. Announcing from the raw
//! projection came a few metres late and scattered; filtering the progress
//! and its speed, then predicting forward by the fix's lag at that speed,
//! places the walker where they are now, so a decision point can be
//! announced when it truly is about `announce_m` ahead. A walker who stands
//! still has no speed to predict with, so is not told early.

/// How quickly a walker changes pace, m/s²: the filter's process noise.
/// People speed up, slow down and stop within a second or two; this is a
/// property of walking, not of a site.
const PACE_CHANGE_MPS2: f64 = 0.5;

/// The filter's state: progress and speed along the route with their
/// covariance (kept in f32, computed in f64: every guided session holds one).
#[derive(Clone, Copy, Debug)]
pub struct Progress {
    /// Filtered progress at `t`, metres from the route's start.
    m: f32,
    /// Walking speed along the route, m/s (never negative: walking back
    /// along the route shows as leaving it, not as progress).
    v: f32,
    /// Covariance of (m, v): [mm, mv, vv].
    p: [f32; 3],
    /// Time of the last fix folded in.
    t: f64,
}

impl Progress {
    /// A walker at the route's start at `t`, standing still but able to
    /// walk at up to about `speed_mps`; `spread_m` is how far a fix's
    /// progress strays from the truth (one standard deviation).
    pub fn new(t: f64, speed_mps: f64, spread_m: f64) -> Progress {
        Progress {
            m: 0.0,
            v: 0.0,
            p: [
                (spread_m * spread_m) as f32,
                0.0,
                (speed_mps * speed_mps) as f32,
            ],
            t,
        }
    }

    /// Filtered progress predicted to time `t` at the filtered speed.
    pub fn at(&self, t: f64) -> f64 {
        f64::from(self.m) + f64::from(self.v) * (t - self.t).max(0.0)
    }

    /// Filtered speed along the route, m/s.
    pub fn speed_mps(&self) -> f64 {
        f64::from(self.v)
    }

    /// Folds in the progress `z` (metres along the route) of a fix at `t`,
    /// whose spread is `spread_m`; the speed stays within `0..=max_mps`.
    pub fn update(&mut self, t: f64, z: f64, spread_m: f64, max_mps: f64) {
        let dt = (t - self.t).max(0.0);
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
        // A walker at 1.1 m/s whose fixes, every 2 s, show them 3 s late.
        let mut progress = Progress::new(0.0, 1.2, 2.0);
        for k in 1..=15 {
            let t = 2.0 * f64::from(k);
            progress.update(t, (1.1 * (t - 3.0)).max(0.0), 2.0, 2.4);
        }
        assert!((progress.speed_mps() - 1.1).abs() < 0.1, "{progress:?}");
        let now = progress.at(30.0 + 3.0);
        assert!((now - 33.0).abs() < 1.0, "at 30 s with 3 s of lag: {now}");
    }

    #[test]
    fn a_walker_standing_still_is_not_predicted_forward() {
        let mut progress = Progress::new(0.0, 1.2, 2.0);
        for k in 1..=10 {
            progress.update(2.0 * f64::from(k), 5.0, 2.0, 2.4);
        }
        assert!(progress.speed_mps() < 0.1, "{progress:?}");
        assert!((progress.at(23.0) - 5.0).abs() < 0.5);
    }
}
