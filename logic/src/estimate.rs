//! The micrometer teaches the odometer: a wear estimate that starts as the model and
//! follows the cone's own bore readings, with an uncertainty band.
//!
//! ## Model and prior
//! The odometer's model is Eq. 17 driven by the measured load–distance: after `E`
//! equivalent nominal cycles the depth is `h = a·(E + m0)^b − c` (`logic/src/odometer.rs`).
//! Taking logarithms, `z = log2(h + c) = α + β·u` is a straight line in
//! `u = log2(E + m0) − u_p` (`u_p` = 10, a pivot at E ≈ 1 000 that keeps α and β nearly
//! uncorrelated in the prior). The model is the line `α0 = log2 a + b·u_p`, `β0 = b`.
//! A real cone follows a curve of the same family with its own scale and exponent —
//! the paper's cones are 14.6 % off the model on average, a cone of another material or
//! batch can be further off, and its curve need not have the model's shape — so the
//! **prior** is Gaussian around the model: `σ(α) = 0.5` (a factor 1.41 at E ≈ 1 000),
//! `σ(β) = 0.08` (the exponent 0.38 ± 0.08), independent.
//!
//! ## Readings
//! A reading is the wear the micrometer shows, `y = bore − baseline` (the paper's depth:
//! the diameter's growth, not halved; `docs/physics.md` §7), at the `E` the odometer had
//! when it was taken. In the line's coordinates it is `z = log2(y + c)`, with the noise
//! of a reading (σ = 3 µm: the 1 µm resolution and the 3σ-filtered mean of 15 points)
//! carried through the logarithm, `σ_z = 3 µm / ((y + c)·ln 2)`: a reading near zero wear
//! says little about the curve, a reading at 300 µm a lot. Each reading's variance also
//! carries a floor, `σ_shape = 0.01` (0.7 % of `h + c`): no power law fits a real cone
//! exactly, and without the floor a dozen late readings would claim a precision the
//! shape of the curve does not have.
//!
//! ## Estimator
//! Bayesian linear regression of `z` on `u` with the prior above (a 2 × 2 system, in
//! closed form), made robust by iteratively reweighted least squares with Huber's
//! weights (k = 2.5 standard deviations, 3 passes): a reading far off the others counts
//! with a weight that falls as its residual grows, so one outlier moves the estimate by
//! a bounded amount. The exponent is kept within 0.05–1 (a fit outside, from readings
//! that contradict any wear law, takes the best line at the bound). The estimate at the
//! cone's current `E` is `h = 2^(α + β·u) − c`;
//! its band is `±2` standard deviations of the line at `u` (the posterior covariance)
//! plus the shape floor, mapped through the same curve (≈ 95 %). The remaining life is
//! where the fitted curve reaches the wear limit: `(E_limit − E) / k` nominal cycles of
//! the cone's material (`k` its wear factor), as the model's own. With no reading, the
//! estimate is the model and the band the prior's.
//!
//! Assumptions: readings are of the same cone, after its baseline, at known `E` (the
//! odometer's at the time); the wear law is monotone and close to a power law in `E`
//! (the paper's family, running-in included approximately); the noise is independent
//! between readings.
//!
//! ## Arithmetic
//! Fixed point only (Q32.32 in `i64`/`i128`, `log2`/`exp2` from [`crate::fixed`], an
//! integer square root), so host and target compute the same bits. A fit over 40
//! readings is a few thousand wide multiplies: it runs when a reading is added, not in
//! the control step.

use crate::fixed::{div_i128, div_u128, exp2_q32, log2_q32};
use crate::material::Material;
use crate::odometer::{depth_nm, wear_factor_q32, A_NM, B_Q32, C_NM, M0_Q32};

const ONE: i128 = 1 << 32;
/// `u_p`: the pivot of `u`, log2 units, Q32.32.
const PIVOT_Q32: i64 = 10 << 32;
/// Prior precision of α: 1/0.5², Q32.32.
const PRIOR_PREC_ALPHA: i128 = 4 * ONE;
/// Prior precision of β: 1/0.08² = 156.25, Q32.32.
const PRIOR_PREC_BETA: i128 = 15_625 * ONE / 100;
/// A reading's standard deviation, µm (Q32.32).
const SIGMA_READ_UM: i128 = 3 * ONE;
/// `σ_shape²` = 0.01² = 0.0001, Q32.32.
const SHAPE_VAR: i128 = ONE / 10_000;
/// log2(e), Q32.32.
const LOG2_E: i128 = 6_196_328_019;
/// Huber's k, Q32.32.
const HUBER_K: i128 = 5 * ONE / 2;
/// IRLS passes.
const PASSES: usize = 3;
/// Readings a fit uses at most (the newest; the odometer keeps 40).
pub const MAX_READINGS: usize = 48;
/// Bounds of the fitted exponent (a wear law that does not grow, or grows faster than
/// linearly, is not a cone's).
const BETA_MIN: i128 = ONE / 20;
const BETA_MAX: i128 = ONE;
/// `c` in µm, Q32.32.
const C_UM: i128 = (C_NM as i128) * ONE / 1000;

/// One micrometer reading as the estimator sees it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Reading {
    /// Equivalent nominal cycles of the cone when it was taken, Q32.32.
    pub e_q32: u64,
    /// Measured wear, `bore − baseline`, nm (negative: a bore read smaller than the
    /// baseline, within the micrometer's noise).
    pub wear_nm: i32,
}

/// The fitted line and its covariance (Q32.32).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Fit {
    alpha: i64,
    beta: i64,
    c00: i64,
    c01: i64,
    c11: i64,
    /// Readings that went in.
    pub readings: u16,
}

/// The estimate at one `E`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Estimate {
    /// Estimated wear depth, nm.
    pub wear_nm: u32,
    /// Lower edge of the band (≈ 95 %), nm.
    pub low_nm: u32,
    /// Upper edge of the band, nm.
    pub high_nm: u32,
    /// Remaining life to `limit_nm` on the estimated curve, nominal cycles of the
    /// cone's material.
    pub remaining_cycles: u32,
}

// Out of line: inlined, each wide multiply or divide is dozens of Thumb instructions,
// and the fit has many (12 KiB of flash inlined, against a few hundred bytes).
#[inline(never)]
fn mul(a: i128, b: i128) -> i128 {
    (a * b) >> 32
}

/// `a·b − c·d` (Q32.32): the 2 × 2 system's cross products, out of line (issue 20).
#[inline(never)]
fn cross(a: i128, b: i128, c: i128, d: i128) -> i128 {
    mul(a, b) - mul(c, d)
}

/// `(a·b) >> 32` for operands and a result within i64 (`mul`'s arithmetic).
#[inline(never)]
fn mul64(a: i64, b: i64) -> i64 {
    ((i128::from(a) * i128::from(b)) >> 32) as i64
}

// (0 for b = 0: `div_i128`'s.) Out of line too: the 128-bit shift and the signs inlined
// at each of the fit's divisions cost 0.9 KB (issue 20).
#[inline(never)]
fn div(a: i128, b: i128) -> i128 {
    div_i128(a << 32, b)
}

/// Integer square root of a non-negative Q32.32 value, as Q32.32.
fn sqrt_q32(v: i128) -> i128 {
    if v <= 0 {
        return 0;
    }
    let n = (v as u128) << 32; // sqrt(v·2^32·2^32) = sqrt(v)·2^32
                               // Newton from above: converges for any start ≥ the root.
    let mut x: u128 = 1 << ((128 - n.leading_zeros()).div_ceil(2));
    loop {
        let y = (x + div_u128(n, x)) >> 1;
        if y >= x {
            return x as i128;
        }
        x = y;
    }
}

fn log2_i(v_q32: i128) -> i128 {
    let v = v_q32.clamp(1, u64::MAX as i128) as u64;
    log2_q32(v).unwrap_or(i64::MIN >> 1) as i128
}

fn exp2_i(y_q32: i128) -> i128 {
    let y = y_q32.clamp(i64::MIN as i128 >> 1, i64::MAX as i128 >> 1) as i64;
    exp2_q32(y) as i128
}

/// `u = log2(E + m0) − u_p`, Q32.32.
fn u_of(e_q32: u64) -> i128 {
    log2_i(e_q32.saturating_add(M0_Q32) as i128) - PIVOT_Q32 as i128
}

/// The wear depth on the curve at `z = log2(y + c)`, nm (out of line: three uses).
#[inline(never)]
fn depth(z: i128) -> u32 {
    let nm = mul(exp2_i(z) - C_UM, 1000 * ONE) >> 32;
    nm.clamp(0, u32::MAX as i128) as u32
}

/// The model's line: α0 = log2(a µm) + b·u_p, β0 = b.
fn prior_line() -> (i128, i128) {
    let log2_a = log2_i(A_NM as i128 * ONE / 1000);
    let b = B_Q32 as i128;
    (log2_a + mul(b, PIVOT_Q32 as i128), b)
}

impl Fit {
    /// The prior alone: the model, with its band.
    pub fn prior() -> Self {
        let (a0, b0) = prior_line();
        Self {
            alpha: a0 as i64,
            beta: b0 as i64,
            c00: div(ONE, PRIOR_PREC_ALPHA) as i64,
            c01: 0,
            c11: div(ONE, PRIOR_PREC_BETA) as i64,
            readings: 0,
        }
    }

    /// Fit the line to `readings` (any order; at most a few dozen).
    #[inline(never)]
    pub fn new(readings: &[Reading]) -> Self {
        if readings.is_empty() {
            return Self::prior();
        }
        let (a0, b0) = prior_line();
        // Per reading, once: u, z, its base weight and Huber's threshold. The
        // logarithms, roots and divisions are the costly part on the target (software
        // 128-bit arithmetic): the passes below only multiply (a down-weighted outlier
        // costs one division).
        let mut pts: heapless::Vec<(i64, i64, i64, i64), MAX_READINGS> = heapless::Vec::new();
        let newest = readings.len().saturating_sub(MAX_READINGS);
        for r in readings.get(newest..).unwrap_or(&[]) {
            let u = u_of(r.e_q32);
            // y + c in µm, kept above c/4 (a bore read far below its baseline).
            let v = (div_i128(r.wear_nm as i128 * ONE, 1000) + C_UM).max(C_UM / 4);
            let z = log2_i(v);
            let sz = mul(div(SIGMA_READ_UM, v), LOG2_E);
            let var = mul(sz, sz) + SHAPE_VAR;
            // (u, z, base weight 1/var, Huber's threshold k·sd)
            let _ = pts.push((
                u as i64,
                z as i64,
                div(ONE, var) as i64,
                mul(HUBER_K, sqrt_q32(var)) as i64,
            ));
        }
        let (mut alpha, mut beta) = (a0, b0);
        let mut cov = (0i128, 0i128, 0i128);
        for pass in 0..PASSES {
            // The sums in i64 (issue 20: the loop's 128-bit adds were most of the fit's
            // code), exact because none can leave i64 (Q32.32; |v| < 2^k means the
            // value's magnitude): |u| < 42·2^32 < 2^37.4 and |z| < 2^37 (`log2_i` of a
            // u64 is in [-32, 32), `u` less the pivot 10); 0 ≤ w ≤ w0 = 2^64 / var ≤
            // 2^64 / SHAPE_VAR < 2^45.3 (Huber only lowers it); so |w·u|, |w·z| < 2^50.7,
            // |w·u·u|, |w·u·z| < 2^56.1, and over at most MAX_READINGS = 48 < 2^5.6 of
            // them, with the prior's terms (< 2^40), every sum stays below 2^61.8 < 2^63.
            // The slope is within [BETA_MIN, BETA_MAX] at every pass (the prior's, or
            // clamped below), so `beta·u` < 2^37.4 too; only the residual against the
            // intercept, which the data do not bound, stays in i128. Each product is
            // the same `(a·b) >> 32` as `mul`'s; `fit_in_i64_is_the_i128_fit` checks
            // the bits against the 128-bit loop.
            let beta64 = beta as i64;
            let (mut p00, mut p01, mut p11) =
                (PRIOR_PREC_ALPHA as i64, 0i64, PRIOR_PREC_BETA as i64);
            let (mut r0, mut r1) = (
                mul(PRIOR_PREC_ALPHA, a0) as i64,
                mul(PRIOR_PREC_BETA, b0) as i64,
            );
            for &(u, z, w0, ksd) in &pts {
                // Huber: beyond k standard deviations the weight falls as 1/|r|, i.e.
                // w = w0 · k·sd/|e|.
                let e = if pass > 0 {
                    (i128::from(z) - (alpha + i128::from(mul64(beta64, u)))).abs()
                } else {
                    0
                };
                let ksd = i128::from(ksd);
                let w = if e > ksd {
                    mul64(w0, div(ksd, e) as i64)
                } else {
                    w0
                };
                let wu = mul64(w, u);
                p00 += w;
                p01 += wu;
                p11 += mul64(wu, u);
                r0 += mul64(w, z);
                r1 += mul64(wu, z);
            }
            let (p00, p01, p11) = (i128::from(p00), i128::from(p01), i128::from(p11));
            let (r0, r1) = (i128::from(r0), i128::from(r1));
            let det = cross(p00, p11, p01, p01);
            if det <= 0 {
                return Self::prior();
            }
            alpha = div(cross(p11, r0, p01, r1), det);
            beta = div(cross(p00, r1, p01, r0), det);
            if !(BETA_MIN..=BETA_MAX).contains(&beta) {
                // The exponent at its bound: the best line with that slope.
                beta = beta.clamp(BETA_MIN, BETA_MAX);
                alpha = div(r0 - mul(p01, beta), p00);
            }
            cov = (div(p11, det), -div(p01, det), div(p00, det));
        }
        let n = u16::try_from(pts.len()).unwrap_or(u16::MAX);
        Self {
            alpha: alpha as i64,
            beta: beta as i64,
            c00: cov.0 as i64,
            c01: cov.1 as i64,
            c11: cov.2 as i64,
            readings: n,
        }
    }

    /// The estimate at `e_q32` equivalent cycles, with the remaining life to
    /// `limit_nm` on `material`. With no reading the wear is exactly the model's.
    pub fn at(&self, e_q32: u64, limit_nm: u32, material: Material) -> Estimate {
        let u = u_of(e_q32);
        let (alpha, beta) = (self.alpha as i128, self.beta as i128);
        let m = alpha + mul(beta, u);
        let var = self.c00 as i128
            + 2 * mul(self.c01 as i128, u)
            + mul(mul(self.c11 as i128, u), u)
            + SHAPE_VAR;
        let sd2 = 2 * sqrt_q32(var);
        let wear_nm = if self.readings == 0 {
            depth_nm(e_q32)
        } else {
            depth(m)
        };
        // Where the curve reaches the limit: log2(E_lim + m0) = u_p + (z_lim − α)/β.
        let z_lim = log2_i(div_i128(limit_nm as i128 * ONE, 1000) + C_UM);
        let x_lim = PIVOT_Q32 as i128 + div(z_lim - alpha, beta.max(BETA_MIN));
        let e_lim = exp2_i(x_lim) - M0_Q32 as i128;
        let k = wear_factor_q32(material).max(1) as i128;
        let left = div((e_lim - e_q32 as i128).max(0), k) >> 32;
        Estimate {
            wear_nm,
            low_nm: depth(m - sd2).min(wear_nm),
            high_nm: depth(m + sd2).max(wear_nm),
            remaining_cycles: left.clamp(0, u32::MAX as i128) as u32,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::odometer::e_at_depth_q32;

    fn e(n: u32) -> u64 {
        (n as u64) << 32
    }

    /// Issue 20's fit, its sums in i64, against the 128-bit loop it replaced (kept here
    /// as it was): the same bits for readings anywhere in their types' ranges.
    #[test]
    fn fit_in_i64_is_the_i128_fit() {
        let mut x: u64 = 0x2545_f491_4f6c_dd1d;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let extremes_e = [0, 1, 1 << 32, 45_000 << 32, u64::MAX / 3, u64::MAX];
        let extremes_w = [i32::MIN, -1_000_000, -1, 0, 1, 7_000, 800_000, i32::MAX];
        for case in 0..400 {
            let n = 1 + (next() % 60) as usize;
            let rs: heapless::Vec<Reading, 64> = (0..n)
                .map(|i| {
                    let r = next();
                    let e_q32 = match case % 4 {
                        0 => extremes_e[(r % 6) as usize],
                        1 => r,
                        _ => (i as u64 * 700 + (r % 500)) << 32,
                    };
                    let wear_nm = match case % 3 {
                        0 => extremes_w[((r >> 8) % 8) as usize],
                        1 => (r >> 16) as i32,
                        _ => (i as i32) * 900 + ((r >> 20) % 4_000) as i32 - 2_000,
                    };
                    Reading { e_q32, wear_nm }
                })
                .collect();
            assert_eq!(Fit::new(&rs), fit_i128(&rs), "case {case}: {rs:?}");
        }
    }

    fn fit_i128(readings: &[Reading]) -> Fit {
        if readings.is_empty() {
            return Fit::prior();
        }
        let (a0, b0) = prior_line();
        // Per reading, once: u, z, its base weight and Huber's threshold. The
        // logarithms, roots and divisions are the costly part on the target (software
        // 128-bit arithmetic): the passes below only multiply (a down-weighted outlier
        // costs one division).
        let mut pts: heapless::Vec<(i64, i64, i64, i64), MAX_READINGS> = heapless::Vec::new();
        let newest = readings.len().saturating_sub(MAX_READINGS);
        for r in readings.get(newest..).unwrap_or(&[]) {
            let u = u_of(r.e_q32);
            // y + c in µm, kept above c/4 (a bore read far below its baseline).
            let v = (div_i128(r.wear_nm as i128 * ONE, 1000) + C_UM).max(C_UM / 4);
            let z = log2_i(v);
            let sz = mul(div(SIGMA_READ_UM, v), LOG2_E);
            let var = mul(sz, sz) + SHAPE_VAR;
            // (u, z, base weight 1/var, Huber's threshold k·sd)
            let _ = pts.push((
                u as i64,
                z as i64,
                div(ONE, var) as i64,
                mul(HUBER_K, sqrt_q32(var)) as i64,
            ));
        }
        let (mut alpha, mut beta) = (a0, b0);
        let mut cov = (0i128, 0i128, 0i128);
        for pass in 0..PASSES {
            let (mut p00, mut p01, mut p11) = (PRIOR_PREC_ALPHA, 0i128, PRIOR_PREC_BETA);
            let (mut r0, mut r1) = (mul(PRIOR_PREC_ALPHA, a0), mul(PRIOR_PREC_BETA, b0));
            for &(u, z, w0, ksd) in &pts {
                let (u, z, w0, ksd) = (u as i128, z as i128, w0 as i128, ksd as i128);
                // Huber: beyond k standard deviations the weight falls as 1/|r|, i.e.
                // w = w0 · k·sd/|e|.
                let e = if pass > 0 {
                    (z - (alpha + mul(beta, u))).abs()
                } else {
                    0
                };
                let w = if e > ksd { mul(w0, div(ksd, e)) } else { w0 };
                let wu = mul(w, u);
                p00 += w;
                p01 += wu;
                p11 += mul(wu, u);
                r0 += mul(w, z);
                r1 += mul(wu, z);
            }
            let det = cross(p00, p11, p01, p01);
            if det <= 0 {
                return Fit::prior();
            }
            alpha = div(cross(p11, r0, p01, r1), det);
            beta = div(cross(p00, r1, p01, r0), det);
            if !(BETA_MIN..=BETA_MAX).contains(&beta) {
                // The exponent at its bound: the best line with that slope.
                beta = beta.clamp(BETA_MIN, BETA_MAX);
                alpha = div(r0 - mul(p01, beta), p00);
            }
            cov = (div(p11, det), -div(p01, det), div(p00, det));
        }
        let n = u16::try_from(pts.len()).unwrap_or(u16::MAX);
        Fit {
            alpha: alpha as i64,
            beta: beta as i64,
            c00: cov.0 as i64,
            c01: cov.1 as i64,
            c11: cov.2 as i64,
            readings: n,
        }
    }

    #[test]
    fn square_root() {
        for v in [0u64, 1, 2, 4, 10, 1_000_000, 123_456_789] {
            let r = sqrt_q32(v as i128 * ONE) as f64 / ONE as f64;
            assert!((r - (v as f64).sqrt()).abs() < 1e-6, "{v}: {r}");
        }
        assert!((sqrt_q32(ONE / 4) as f64 / ONE as f64 - 0.5).abs() < 1e-9);
    }

    #[test]
    fn with_no_reading_the_estimate_is_the_model() {
        let f = Fit::new(&[]);
        for n in [0, 100, 1_000, 10_000, 45_000] {
            let est = f.at(e(n), 800_000, Material::ZQSn5_2);
            assert_eq!(est.wear_nm, depth_nm(e(n)), "{n}");
            assert!(est.low_nm <= est.wear_nm && est.wear_nm <= est.high_nm);
        }
        // The prior's remaining life is the model's, within a cycle.
        let est = f.at(e(10_000), 800_000, Material::ZQSn5_2);
        let model_left = ((e_at_depth_q32(800_000) - e(10_000)) >> 32) as i64;
        assert!(
            (est.remaining_cycles as i64 - model_left).abs() <= 2,
            "{est:?}"
        );
    }

    #[test]
    fn readings_on_the_model_keep_the_model_and_narrow_the_band() {
        let readings: heapless::Vec<Reading, 16> = [1_000u32, 3_000, 6_000, 10_000]
            .iter()
            .map(|&n| Reading {
                e_q32: e(n),
                wear_nm: depth_nm(e(n)) as i32,
            })
            .collect();
        let prior = Fit::prior().at(e(12_000), 800_000, Material::ZQSn5_2);
        let est = Fit::new(&readings).at(e(12_000), 800_000, Material::ZQSn5_2);
        let model = depth_nm(e(12_000));
        assert!(est.wear_nm.abs_diff(model) < 2_000, "{est:?} vs {model}");
        assert!(est.high_nm - est.low_nm < (prior.high_nm - prior.low_nm) / 3);
    }
}
