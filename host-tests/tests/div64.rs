//! The image's own 64-bit division (src/board/div.rs, issue 20) against the core's, on
//! the host: every pair of the values at the edges of its paths (the 32-bit case, a
//! 32-bit divisor under a wider dividend, a divisor of 2^32 or more; the correction
//! steps' boundaries), and millions of random operands of every bit length. The same
//! file is what the image links; `cargo xtask qemu` runs the symbols on the M4.
//! (Run with the test profile's overflow checks: an intermediate that overflowed would
//! panic here.)

#[path = "../../src/board/div.rs"]
#[allow(dead_code)]
mod div;

use div::{idivmod64, udivmod64};

/// Values at the edges: small, around 2^16, 2^31, 2^32, 2^48, 2^63 and the top.
fn edges() -> Vec<u64> {
    let mut v = vec![0, 1, 2, 3, 5, 7, 10, 1000, 1_000_000];
    for b in [15u32, 16, 17, 31, 32, 33, 47, 48, 49, 62, 63] {
        let p = 1u64 << b;
        v.extend([p - 1, p, p + 1, p | (p >> 1), p | 0xFFFF]);
    }
    v.extend([u64::MAX, u64::MAX - 1, u64::MAX >> 1, 0xFFFF_FFFF_0000_0000]);
    v.extend([
        0x8000_0000_FFFF_FFFF,
        0x0001_0000_0000_FFFF,
        0x7FFF_8000_0000_0001,
    ]);
    v
}

/// The simulator's seeded generator (the operands are reproducible), with values of a
/// random bit length (1..=64), so that every path is drawn often.
struct Rng(hil_sim::rng::Rng);

impl Rng {
    fn new(seed: u64) -> Self {
        Self(hil_sim::rng::Rng::new(seed))
    }

    fn next(&mut self) -> u64 {
        self.0.next_u64()
    }

    fn sized(&mut self) -> u64 {
        let bits = (self.next() % 64) + 1;
        self.next() >> (64 - bits)
    }
}

#[test]
fn unsigned_division_matches_the_core_at_every_edge() {
    let e = edges();
    for &n in &e {
        for &d in &e {
            if d == 0 {
                continue;
            }
            assert_eq!(udivmod64(n, d), (n / d, n % d), "{n} / {d}");
        }
    }
}

#[test]
fn unsigned_division_matches_the_core_on_random_operands() {
    let mut rng = Rng::new(0x9E37_79B9_7F4A_7C15);
    for _ in 0..4_000_000 {
        let n = rng.sized();
        let d = rng.sized().max(1);
        assert_eq!(udivmod64(n, d), (n / d, n % d), "{n} / {d}");
    }
}

#[test]
fn the_quotient_digit_corrections_are_exercised_and_right() {
    // Divisors whose normalized top half is small against their low half make the
    // 16-bit digit estimates too large (the correction loops run); dividends just
    // under a multiple of the divisor put the remainder at its edges.
    let mut rng = Rng::new(42);
    for _ in 0..1_000_000 {
        let d = (0x8000_0000 | (rng.next() as u32 & 0x0000_FFFF)) as u64;
        let d = if rng.next() & 1 == 0 {
            d
        } else {
            d << (rng.next() % 33)
        };
        let q = rng.sized();
        let n = q.wrapping_mul(d).wrapping_sub(rng.next() % 3);
        assert_eq!(udivmod64(n, d), (n / d, n % d), "{n} / {d}");
    }
}

#[test]
fn signed_division_truncates_toward_zero_like_rust() {
    let mut vals: Vec<i64> = Vec::new();
    for u in edges() {
        vals.push(u as i64);
        vals.push((u as i64).wrapping_neg());
    }
    vals.extend([i64::MIN, i64::MIN + 1, i64::MAX, -1, -2, -3]);
    for &a in &vals {
        for &b in &vals {
            if b == 0 {
                continue;
            }
            let want = (a.wrapping_div(b), a.wrapping_rem(b));
            assert_eq!(idivmod64(a, b), want, "{a} / {b}");
        }
    }
    let mut rng = Rng::new(7);
    for _ in 0..1_000_000 {
        let (a, b) = (rng.sized() as i64, rng.sized() as i64);
        let (a, b) = (
            if rng.next() & 1 == 0 {
                a
            } else {
                a.wrapping_neg()
            },
            if rng.next() & 1 == 0 {
                b
            } else {
                b.wrapping_neg()
            },
        );
        if b == 0 {
            continue;
        }
        assert_eq!(
            idivmod64(a, b),
            (a.wrapping_div(b), a.wrapping_rem(b)),
            "{a} / {b}"
        );
    }
}

#[test]
fn division_by_zero_gives_zero_and_keeps_the_dividend() {
    for n in edges() {
        assert_eq!(udivmod64(n, 0), (0, n));
        assert_eq!(idivmod64(n as i64, 0), (0, n as i64));
    }
}
