//! The exact sign test: whether one side of paired comparisons wins more
//! often than chance. The planning evaluation judges a route against a
//! baseline walk by walk with it, and calibration judges a fitted radio
//! model against the one it started from, held-out walk by walk; both care
//! about how often one side wins, not by how much (a few walks far off
//! would sway a mean).
//!
//! The binomial tail is summed here rather than taken from a statistics
//! crate (none is a dependency): it is a few lines, in log space so that
//! thousands of comparisons do not underflow.

/// Two-sided exact sign test: the chance of a split at least as uneven as
/// `wins` against `losses` (ties left out) if either side were equally
/// likely to win each comparison.
pub fn sign_test(wins: usize, losses: usize) -> f64 {
    let n = wins + losses;
    if n == 0 {
        return 1.0;
    }
    let k = wins.min(losses);
    // ln C(n, i) built up term by term: C(n, i+1) = C(n, i) (n − i) / (i + 1).
    let mut ln_choose = 0.0f64;
    let mut tail = 0.0f64;
    let ln_half_n = n as f64 * std::f64::consts::LN_2;
    for i in 0..=k {
        tail += (ln_choose - ln_half_n).exp();
        ln_choose += ((n - i) as f64).ln() - ((i + 1) as f64).ln();
    }
    (2.0 * tail).min(1.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sign_test_matches_the_binomial_tail() {
        // 9 wins, 1 loss: P(X ≤ 1) = 11/1024 for X ~ Bin(10, 1/2), doubled.
        assert!((sign_test(9, 1) - 22.0 / 1024.0).abs() < 1e-12);
        assert!((sign_test(1, 9) - 22.0 / 1024.0).abs() < 1e-12);
        assert_eq!(sign_test(5, 5), 1.0);
        assert_eq!(sign_test(0, 0), 1.0);
        // Large counts do not underflow: 600 against 400 is far from chance.
        let p = sign_test(600, 400);
        assert!(p > 0.0 && p < 1e-9, "{p}");
    }
}
