//! Runs `docking_logic::odometer::reference_run` on a Cortex-M4 and prints its
//! result through semihosting; `.ci/run` compares it with the host's. First it checks
//! the image's own `memcpy` and `__aeabi_memclr` (`src/board/mem.rs`, linked here as in
//! the image: the odometer's run copies through them too) against a byte-by-byte
//! reference, every alignment of source and destination and every length to 70; then
//! the image's 64-bit division (`src/board/div.rs`: `__aeabi_uldivmod` and
//! `__aeabi_ldivmod`, called by every `/` and `%` below) against a bit-by-bit reference.
#![no_std]
#![no_main]

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};

#[path = "../../src/board/mem.rs"]
mod mem;

#[path = "../../src/board/div.rs"]
#[allow(dead_code)]
mod div;

extern "C" {
    fn memcpy(dest: *mut u8, src: *const u8, n: usize) -> *mut u8;
}
extern "aapcs" {
    fn __aeabi_memcpy4(dest: *mut u8, src: *const u8, n: usize);
    fn __aeabi_memcpy8(dest: *mut u8, src: *const u8, n: usize);
    fn __aeabi_memclr(dest: *mut u8, n: usize);
    fn __aeabi_memclr4(dest: *mut u8, n: usize);
}

/// Words, so that offset 0 is aligned.
const WORDS: usize = 24;
const FILL: u8 = 0xEE;

fn byte(buf: &[u32; WORDS], i: usize) -> u8 {
    // SAFETY: `i` < 4·WORDS at every call; volatile, so that no comparison loop below is
    // turned into a library call (the functions under test).
    unsafe { core::ptr::read_volatile((buf.as_ptr() as *const u8).add(i)) }
}

fn fill(buf: &mut [u32; WORDS], f: impl Fn(usize) -> u8) {
    for i in 0..4 * WORDS {
        // SAFETY: as in `byte`.
        unsafe { core::ptr::write_volatile((buf.as_mut_ptr() as *mut u8).add(i), f(i)) }
    }
}

/// Every alignment and length to 70: memcpy (and its aligned AEABI entry points) and
/// memclr leave exactly the bytes asked for, and nothing else, changed. The number of
/// cases checked, or the first that failed.
fn check_mem() -> Result<u32, (&'static str, usize, usize, usize)> {
    let mut src = [0u32; WORDS];
    let mut dst = [0u32; WORDS];
    fill(&mut src, |i| (i as u8).wrapping_mul(7).wrapping_add(3));
    let mut cases = 0;
    for so in 0..4 {
        for d in 0..4 {
            for n in 0..=70 {
                for entry in 0..3 {
                    if entry > 0 && (so != 0 || d != 0) {
                        continue; // the aligned entry points take aligned pointers
                    }
                    fill(&mut dst, |_| FILL);
                    let (dp, sp) = (dst.as_mut_ptr() as *mut u8, src.as_ptr() as *const u8);
                    // SAFETY: offset + n ≤ 3 + 70 < 4·WORDS for both buffers.
                    let ok_ret = unsafe {
                        let (dp, sp) = (dp.add(d), sp.add(so));
                        match entry {
                            0 => memcpy(dp, sp, n) == dp,
                            1 => {
                                __aeabi_memcpy4(dp, sp, n);
                                true
                            }
                            _ => {
                                __aeabi_memcpy8(dp, sp, n);
                                true
                            }
                        }
                    };
                    let good = (0..4 * WORDS).all(|i| {
                        let want = if (d..d + n).contains(&i) {
                            byte(&src, i - d + so)
                        } else {
                            FILL
                        };
                        byte(&dst, i) == want
                    });
                    if !ok_ret || !good {
                        return Err(("memcpy", so, d, n));
                    }
                    cases += 1;
                }
            }
        }
    }
    for d in 0..4 {
        for n in 0..=70 {
            for entry in 0..2 {
                if entry > 0 && d != 0 {
                    continue;
                }
                fill(&mut dst, |_| FILL);
                // SAFETY: d + n < 4·WORDS.
                unsafe {
                    let dp = (dst.as_mut_ptr() as *mut u8).add(d);
                    if entry == 0 {
                        __aeabi_memclr(dp, n)
                    } else {
                        __aeabi_memclr4(dp, n)
                    }
                }
                let good = (0..4 * WORDS).all(|i| {
                    let want = if (d..d + n).contains(&i) { 0 } else { FILL };
                    byte(&dst, i) == want
                });
                if !good {
                    return Err(("memclr", 0, d, n));
                }
                cases += 1;
            }
        }
    }
    Ok(cases)
}

/// `n / d` and `n % d` one bit at a time (restoring division, shifts and compares only:
/// nothing here calls the functions under test). `d` > 0.
fn reference_divmod(n: u64, d: u64) -> (u64, u64) {
    let (mut q, mut r) = (0u64, 0u64);
    for i in (0..64).rev() {
        let carry = r >> 63;
        r = (r << 1) | ((n >> i) & 1);
        q <<= 1;
        if carry != 0 || r >= d {
            r = r.wrapping_sub(d);
            q |= 1;
        }
    }
    (q, r)
}

/// The compiler's `/` and `%` on u64 and i64 (through the image's `__aeabi_uldivmod` and
/// `__aeabi_ldivmod`) against [`reference_divmod`]: operands of every bit length from a
/// fixed xorshift sequence, and the edges. The number of cases, or the first wrong one.
fn check_div() -> Result<u32, (u64, u64)> {
    use core::hint::black_box;
    let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = move || {
        x ^= x >> 12;
        x ^= x << 25;
        x ^= x >> 27;
        x.wrapping_mul(0x2545_F491_4F6C_DD1D)
    };
    let mut cases = 0;
    for i in 0..20_000u32 {
        let (a, b) = (next(), next());
        let n = a >> (a % 64);
        let d = (b >> (b % 64)).max(1);
        let (n, d) = match i {
            0 => (u64::MAX, 1),
            1 => (u64::MAX, u64::MAX),
            2 => (1 << 63, (1 << 32) + 1),
            3 => (0xFFFF_FFFF_0000_0000, 0x8000_FFFF),
            _ => (n, d),
        };
        let (q, r) = (black_box(n) / black_box(d), black_box(n) % black_box(d));
        if (q, r) != reference_divmod(n, d) {
            return Err((n, d));
        }
        // Signed, every sign combination (i64::MIN / -1 aside: Rust panics on it).
        let (sn, sd) = (n as i64, d as i64);
        for (a, b) in [(sn, sd), (sn.wrapping_neg(), sd), (sn, sd.wrapping_neg())] {
            if b == 0 || (a == i64::MIN && b == -1) {
                continue;
            }
            let (uq, ur) = reference_divmod(a.unsigned_abs(), b.unsigned_abs());
            let want_q = if (a < 0) != (b < 0) {
                (uq as i64).wrapping_neg()
            } else {
                uq as i64
            };
            let want_r = if a < 0 {
                (ur as i64).wrapping_neg()
            } else {
                ur as i64
            };
            if (black_box(a) / black_box(b), black_box(a) % black_box(b)) != (want_q, want_r) {
                return Err((a as u64, b as u64));
            }
        }
        cases += 1;
    }
    Ok(cases)
}

#[entry]
fn main() -> ! {
    match check_mem() {
        Ok(cases) => hprintln!("memcpy and memclr: {} cases ok", cases),
        Err((f, so, d, n)) => {
            hprintln!(
                "{} FAILED: source offset {}, destination offset {}, {} bytes",
                f,
                so,
                d,
                n
            );
            debug::exit(debug::EXIT_FAILURE);
        }
    }
    match check_div() {
        Ok(cases) => hprintln!("64-bit division: {} cases ok", cases),
        Err((n, d)) => {
            hprintln!("64-bit division FAILED: {:#x} / {:#x}", n, d);
            debug::exit(debug::EXIT_FAILURE);
        }
    }
    let r = docking_logic::odometer::reference_run(300);
    hprintln!("{}", r);
    debug::exit(debug::EXIT_SUCCESS);
    loop {
        cortex_m::asm::wfi();
    }
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    debug::exit(debug::EXIT_FAILURE);
    loop {
        cortex_m::asm::wfi();
    }
}
