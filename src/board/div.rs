//! 64-bit division for the image, small (issue 20): `__aeabi_uldivmod` and
//! `__aeabi_ldivmod`, the run-time functions every `u64`/`i64` `/` and `%` calls on a
//! 32-bit Arm core (RTABI §4.3.1).
//!
//! Why by hand: the Rust toolchain links compiler_builtins' `u64_div_rem` behind them,
//! prebuilt with the target's `core` for speed: with its `__udivmoddi4` and
//! `__divmoddi4` wrappers, 1 068 bytes of flash. Here the same results come from the
//! M4's 32/32 `udiv` by the textbook method (Warren, *Hacker's Delight*, 2nd ed.,
//! §9.4–9.5: `divlu` and `udivdi3`) in 602 bytes (the image −468 B, on b57bb1f), and
//! the control step runs 11 instructions fewer (743.69 → 732.27 a step, the virtual
//! board's flooded `overload` scene). A divisor below 2^32 takes one `udiv` while the
//! dividend fits in 32 bits too (most of what the control step divides: a time in µs by
//! 1 000, a distance by a speed), three when it does not; a divisor of 2^32 or more (the
//! estimate's Q32.32 arithmetic, at rest) takes two. Defining the symbols here keeps
//! compiler_builtins' objects out of the link, as `mem.rs` does for `memcpy`.
//!
//! Division by zero: Rust checks every divisor before it calls these (and panics), so
//! they never see 0 from the firmware; given one, they return a quotient of 0 and the
//! dividend as the remainder, and never fault.
//!
//! Tested on the host against the core's division (host-tests/tests/div64.rs: the edge
//! cases of every path and millions of random operands of every size) and on the M4 by
//! `cargo xtask qemu` (qemu-check calls the symbols as the compiler does).

/// `n / d` for 32-bit operands: the M4's `udiv`, 0 for `d` = 0 (as `udiv` gives).
#[inline(always)]
fn div32(n: u32, d: u32) -> u32 {
    n.checked_div(d).unwrap_or(0)
}

/// `(u1·2^32 + u0) / v` and the remainder, for `u1 < v` (so the quotient fits in 32
/// bits and `v` > 0): *Hacker's Delight* Figure 9–3 (`divlu`). `v` is normalized (its
/// top bit set) and the quotient found as two 16-bit digits, each estimated by one
/// `udiv` by `v`'s top half and corrected at most twice. Out of line: both paths of
/// [`udivmod64`] that need it share one copy.
#[inline(never)]
fn divlu(u1: u32, u0: u32, v: u32) -> (u32, u32) {
    const B: u32 = 1 << 16;
    let s = v.leading_zeros();
    let v = v << s;
    let (vn1, vn0) = (v >> 16, v & 0xFFFF);
    // `u0 >> (32 - s)` without the shift by 32 when s = 0.
    let un32 = (u1 << s) | ((u0 >> 1) >> (31 - s));
    let un10 = u0 << s;
    let (un1, un0) = (un10 >> 16, un10 & 0xFFFF);
    // First digit. `q1·vn0` is only formed for q1 < B, and rhat stays below B while the
    // loop compares: neither product overflows.
    let mut q1 = div32(un32, vn1);
    let mut rhat = un32 - q1 * vn1;
    while q1 >= B || q1 * vn0 > B * rhat + un1 {
        q1 -= 1;
        rhat += vn1;
        if rhat >= B {
            break;
        }
    }
    // The partial remainder, below v: exact modulo 2^32.
    let un21 = un32
        .wrapping_mul(B)
        .wrapping_add(un1)
        .wrapping_sub(q1.wrapping_mul(v));
    // Second digit.
    let mut q0 = div32(un21, vn1);
    let mut rhat = un21 - q0 * vn1;
    while q0 >= B || q0 * vn0 > B * rhat + un0 {
        q0 -= 1;
        rhat += vn1;
        if rhat >= B {
            break;
        }
    }
    let r = un21
        .wrapping_mul(B)
        .wrapping_add(un0)
        .wrapping_sub(q0.wrapping_mul(v))
        >> s;
    (q1 * B + q0, r)
}

/// `(n / d, n % d)`; `(0, n)` for `d` = 0.
#[inline(always)]
pub fn udivmod64(n: u64, d: u64) -> (u64, u64) {
    let mut r = 0;
    let q = docking_udivmod64(n, d, &mut r);
    (q, r)
}

/// The unsigned division, once in the image: what `__aeabi_uldivmod` (below) and
/// [`idivmod64`] call; the quotient returned, the remainder through `rem` (libgcc's
/// `__udivmoddi4` contract, under a name of the image's own). No 64-bit division inside
/// (it would call itself): 32-bit `udiv`, shifts, and 64-bit multiplications (`umull`).
#[no_mangle]
pub extern "C" fn docking_udivmod64(n: u64, d: u64, rem: &mut u64) -> u64 {
    let (q, r) = udivmod64_inner(n, d);
    *rem = r;
    q
}

#[inline(always)]
fn udivmod64_inner(n: u64, d: u64) -> (u64, u64) {
    let (n1, n0) = ((n >> 32) as u32, n as u32);
    let (d1, d0) = ((d >> 32) as u32, d as u32);
    if d1 == 0 {
        if n1 == 0 {
            let q = div32(n0, d0);
            return (u64::from(q), u64::from(n0 - q * d0));
        }
        if d0 == 0 {
            return (0, n);
        }
        // High digit by one udiv, then the rest (its high word now below d0).
        let q1 = div32(n1, d0);
        let k = n1 - q1 * d0;
        let (q0, r) = divlu(k, n0, d0);
        return ((u64::from(q1) << 32) | u64::from(q0), u64::from(r));
    }
    // d ≥ 2^32: the quotient fits in 32 bits (Figure 9–5, `udivdi3`). The top word of
    // the normalized divisor into n/2 gives it, or one more than it, after the shift
    // back; one correction against the full divisor.
    if n < d {
        return (0, n);
    }
    let s = d1.leading_zeros();
    let v1 = ((d << s) >> 32) as u32;
    let u = n >> 1;
    let (q1, _) = divlu((u >> 32) as u32, u as u32, v1);
    let mut q = (u64::from(q1) << s) >> 31;
    q = q.saturating_sub(1);
    // q is the quotient or one less: q·d ≤ n.
    let mut r = n - q * d;
    if r >= d {
        q += 1;
        r -= d;
    }
    (q, r)
}

/// `(a / b, a % b)` truncated toward zero, as Rust's `/` and `%` (the remainder takes
/// the dividend's sign; `i64::MIN / -1` wraps to `i64::MIN`, as the hardware would);
/// `(0, a)` for `b` = 0.
pub fn idivmod64(a: i64, b: i64) -> (i64, i64) {
    let (q, r) = udivmod64(a.unsigned_abs(), b.unsigned_abs());
    let q = if (a < 0) != (b < 0) {
        (q as i64).wrapping_neg()
    } else {
        q as i64
    };
    let r = if a < 0 {
        (r as i64).wrapping_neg()
    } else {
        r as i64
    };
    (q, r)
}

/// What `__aeabi_ldivmod` calls (as [`docking_udivmod64`]).
#[no_mangle]
pub extern "C" fn docking_idivmod64(a: i64, b: i64, rem: &mut i64) -> i64 {
    let (q, r) = idivmod64(a, b);
    *rem = r;
    q
}

// The AEABI entry points return the quotient in r0:r1 and the remainder in r2:r3, which
// no C or Rust function can: each calls the function above with the remainder's slot on
// its stack (the stack kept 8-byte aligned) and loads it into r2:r3.
#[cfg(target_arch = "arm")]
core::arch::global_asm!(
    ".section .text.docking_uldivmod,\"ax\",%progbits",
    ".p2align 1",
    ".global __aeabi_uldivmod",
    ".type __aeabi_uldivmod,%function",
    ".thumb_func",
    "__aeabi_uldivmod:",
    "    push    {{r4, lr}}",
    "    sub     sp, sp, #16",
    "    add     r4, sp, #8",
    "    str     r4, [sp]",
    "    bl      docking_udivmod64",
    "    ldrd    r2, r3, [sp, #8]",
    "    add     sp, sp, #16",
    "    pop     {{r4, pc}}",
    ".size __aeabi_uldivmod, . - __aeabi_uldivmod",
    ".section .text.docking_ldivmod,\"ax\",%progbits",
    ".p2align 1",
    ".global __aeabi_ldivmod",
    ".type __aeabi_ldivmod,%function",
    ".thumb_func",
    "__aeabi_ldivmod:",
    "    push    {{r4, lr}}",
    "    sub     sp, sp, #16",
    "    add     r4, sp, #8",
    "    str     r4, [sp]",
    "    bl      docking_idivmod64",
    "    ldrd    r2, r3, [sp, #8]",
    "    add     sp, sp, #16",
    "    pop     {{r4, pc}}",
    ".size __aeabi_ldivmod, . - __aeabi_ldivmod",
);
