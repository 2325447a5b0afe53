//! Deterministic fixed-point `log2`, `exp2` and `pow` on integers only.
//!
//! The wear odometer needs `x^b` (Eq. 17's power law). Floating-point `powf` is not the
//! same function on the host (`std`, which silently shadows `micromath`) and on the
//! target (`libm`/`micromath` approximations), so two machines fed the same samples
//! would disagree in the last bits. These routines use only integer shifts, multiplies
//! and compares, so they give bit-identical results everywhere, and they are `const fn`
//! so model constants are computed at build time.
//!
//! Format: **Q32.32** — a `u64` (or `i64` for logarithms) holding `value · 2^32`.
//! Accuracy: `log2` exact to 2^-32 (bit-by-bit squaring), `exp2` to ~2^-60 relative
//! (product of 2^(2^-i) constants), so `pow` is good to ~1e-9 relative — far below
//! the model's own 1 % tolerance.

/// One in Q32.32.
pub const ONE_Q32: u64 = 1 << 32;

/// `n / d` in `u128` (0 for `d` = 0). Out of line, and the only 128-bit division in
/// the image: Thumb has no 128-bit divide and no library routine for one, so each `/`
/// on `u128`/`i128` was expanded in place into a ~600-byte shift-and-subtract loop
/// (issue 20). Operands that fit in 64 bits take the 64-bit division; wider ones the
/// restoring division below, one quotient bit an iteration from the divisor aligned
/// under the dividend's top bit: what the compiler's expansion of `/` did, in 392 bytes
/// less, and fewer instructions (a fit of 30 readings 353 098 -> 250 845 on the M4,
/// `vboard estimate-cost`). Exact: the result is the operator's.
#[inline(never)]
pub const fn div_u128(n: u128, d: u128) -> u128 {
    if d == 0 {
        return 0;
    }
    if n >> 64 == 0 && d >> 64 == 0 {
        return (n as u64 / d as u64) as u128;
    }
    if n < d {
        return 0;
    }
    let shift = d.leading_zeros() - n.leading_zeros();
    let mut d = d << shift;
    let mut r = n;
    let mut q = 0;
    let mut i = 0;
    while i <= shift {
        q <<= 1;
        if r >= d {
            r -= d;
            q |= 1;
        }
        d >>= 1;
        i += 1;
    }
    q
}

/// `a / b` in `i128`, truncated toward zero like `/` (0 for `b` = 0; `i128::MIN / -1`
/// wraps instead of panicking). See [`div_u128`].
pub const fn div_i128(a: i128, b: i128) -> i128 {
    let q = div_u128(a.unsigned_abs(), b.unsigned_abs()) as i128;
    if (a < 0) != (b < 0) {
        q.wrapping_neg()
    } else {
        q
    }
}

/// 2^(2^-i) for i = 1..=32, in Q2.62 (computed to 60 digits offline). Each is below
/// 2^63: `u64` (a `u128` table spent 256 bytes of flash on zeros).
const EXP2_FRAC_Q62: [u64; 32] = [
    6521908912666391106,
    5484249825272419512,
    5029079263719320435,
    4815862801830788490,
    4712668792719003884,
    4661903986662671290,
    4636727017470743990,
    4624189567668517720,
    4617933561212708776,
    4614808732577250068,
    4613247111281068008,
    4612466498810092975,
    4612076242109103707,
    4611881126141011236,
    4611783571252412754,
    4611734794581956353,
    4611710406440186476,
    4611698212417665819,
    4611692115418496524,
    4611689066921934630,
    4611687542674409371,
    4611686780550835664,
    4611686399489096040,
    4611686208958238036,
    4611686113692811986,
    4611686066060099699,
    4611686042243743740,
    4611686030335565807,
    4611686024381476851,
    4611686021404432377,
    4611686019915910140,
    4611686019171649022,
];

/// log2 of a positive Q32.32 value, as signed Q32.32; `None` for 0.
pub const fn log2_q32(x_q32: u64) -> Option<i64> {
    if x_q32 == 0 {
        return None;
    }
    let msb = 63 - x_q32.leading_zeros() as i64; // x in [2^msb, 2^(msb+1))
    let int_part = msb - 32;
    // Mantissa in [1, 2) as Q1.63.
    let mut m: u128 = (x_q32 as u128) << (63 - msb);
    let mut frac: i64 = 0;
    let mut i = 0;
    while i < 32 {
        m = (m * m) >> 63; // square: [1, 4) in Q2.63
        frac <<= 1;
        if m >= (1u128 << 64) {
            m >>= 1;
            frac |= 1;
        }
        i += 1;
    }
    Some((int_part << 32) + frac)
}

/// 2^y for a signed Q32.32 exponent, as Q32.32 (saturating at `u64::MAX`, 0 below 2^-32).
// The only index is the loop counter over the table's own length (32), in a const fn
// where `<[T]>::get` is not available: it cannot go out of bounds whatever the input.
#[allow(clippy::indexing_slicing)]
pub const fn exp2_q32(y_q32: i64) -> u64 {
    let int_part = y_q32 >> 32; // floor
    let frac = (y_q32 & 0xFFFF_FFFF) as u64;
    // 2^frac in Q2.62 as the product of 2^(2^-i) over the set bits of frac.
    let mut m: u128 = 1 << 62;
    let mut i = 0;
    while i < 32 {
        if frac & (1 << (31 - i)) != 0 {
            m = (m * EXP2_FRAC_Q62[i] as u128) >> 62;
        }
        i += 1;
    }
    // value = m / 2^62 · 2^int; Q32.32 = m · 2^(int - 30).
    let shift = int_part - 30;
    if shift >= 0 {
        if shift >= 64 || (m >> (64 - shift)) != 0 {
            return u64::MAX;
        }
        let v = m << shift;
        if v > u64::MAX as u128 {
            u64::MAX
        } else {
            v as u64
        }
    } else if -shift >= 128 {
        0
    } else {
        let v = m >> (-shift);
        if v > u64::MAX as u128 {
            u64::MAX
        } else {
            v as u64
        }
    }
}

/// x^e for positive Q32.32 `x` and Q32.32 exponent `e` (0^e = 0).
pub const fn pow_q32(x_q32: u64, e_q32: i64) -> u64 {
    match log2_q32(x_q32) {
        None => 0,
        Some(l) => {
            let y = (l as i128 * e_q32 as i128) >> 32;
            if y > i64::MAX as i128 {
                u64::MAX
            } else if y < i64::MIN as i128 {
                0
            } else {
                exp2_q32(y as i64)
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn q(x: f64) -> u64 {
        (x * 4294967296.0).round() as u64
    }
    fn f(x: u64) -> f64 {
        x as f64 / 4294967296.0
    }

    #[test]
    fn log2_and_exp2_against_f64() {
        for x in [1.0, 1.5, 2.0, 3.0, 0.01372, 59.6, 45_270.0, 1e9, 1.0 / 3.0] {
            let l = log2_q32(q(x)).unwrap() as f64 / 4294967296.0;
            assert!((l - x.log2()).abs() < 1e-8, "log2({x}) = {l}");
        }
        for y in [-10.0, -1.5, -0.25, 0.0, 0.3813, 1.0, 7.77, 20.0] {
            let e = f(exp2_q32((y * 4294967296.0f64).round() as i64));
            assert!((e / 2f64.powf(y) - 1.0).abs() < 1e-8, "2^{y} = {e}");
        }
        assert_eq!(log2_q32(0), None);
        assert_eq!(exp2_q32(40 << 32), u64::MAX);
        assert_eq!(exp2_q32(-40 << 32), 0);
    }

    #[test]
    fn pow_matches_f64() {
        let b = (0.3813 * 4294967296.0f64).round() as i64;
        for x in [1.96, 200.0, 1_000.0, 45_270.0, 1e7] {
            let p = f(pow_q32(q(x), b));
            assert!((p / x.powf(0.3813) - 1.0).abs() < 1e-8, "{x}^b = {p}");
        }
    }

    #[test]
    fn wide_division_is_the_operators() {
        let vals: [i128; 12] = [
            0,
            1,
            -1,
            7,
            -7,
            1000,
            (1 << 64) - 1,
            1 << 64,
            -(1 << 70) + 3,
            i128::MAX,
            i128::MIN + 1,
            123_456_789_012_345_678_901_234_567,
        ];
        for &a in &vals {
            for &b in &vals {
                if b != 0 {
                    assert_eq!(div_i128(a, b), a / b, "{a} / {b}");
                    let (ua, ub) = (a.unsigned_abs(), b.unsigned_abs());
                    assert_eq!(div_u128(ua, ub), ua / ub, "{ua} / {ub}");
                }
            }
            assert_eq!(div_i128(a, 0), 0);
        }
        assert_eq!(div_u128(u128::MAX, 3), u128::MAX / 3);
    }

    #[test]
    fn wide_division_matches_the_operator_on_random_operands() {
        // Operands of every bit length (so the loop runs from 1 to 128 times), from a
        // fixed xorshift sequence.
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        let mut next = move || {
            x ^= x >> 12;
            x ^= x << 25;
            x ^= x >> 27;
            x.wrapping_mul(0x2545_F491_4F6C_DD1D)
        };
        let mut wide = || {
            let v = (u128::from(next()) << 64) | u128::from(next());
            v >> (next() % 128)
        };
        for _ in 0..300_000 {
            let (n, d) = (wide(), wide().max(1));
            assert_eq!(div_u128(n, d), n / d, "{n} / {d}");
        }
    }

    #[test]
    fn pow_is_monotone() {
        let b = (0.3813 * 4294967296.0f64).round() as i64;
        let mut prev = 0;
        let mut x = ONE_Q32;
        while x < (100_000u64 << 32) {
            let p = pow_q32(x, b);
            assert!(p >= prev);
            prev = p;
            x += x / 97 + 1;
        }
    }
}
