//! Maintenance-mode PIN: storage format, verification, lockout and session timeout.
//!
//! * **Storage.** The PIN is never stored: a [`PinRecord`] holds a 16-byte random
//!   salt and an iterated, salted SHA-256 hash:
//!   `h0 = SHA256(salt || pin)`, `h(i+1) = SHA256(h(i) || salt)`, stored hash =
//!   `h(PIN_HASH_ROUNDS)`. Every step is one 64-byte block, so a check costs
//!   `PIN_HASH_ROUNDS + 1` = 257 SHA-256 compressions: about 3 ms on a Cortex-M4 at
//!   168 MHz (estimated at roughly 2,000 cycles per compression). That slows offline
//!   guessing of a 4-12 digit PIN read out of flash (~10^4..10^12 candidates) by
//!   the same factor, while staying cheap enough to run inside one console poll.
//! * **Verification** compares hashes in constant time (OR-fold of XORs).
//! * **Lockout.** [`MAX_FAILURES`] consecutive wrong PINs lock PIN entry for
//!   [`LOCKOUT_MS`] from the last failure; while locked even the right PIN is refused
//!   and no hash is computed (so a flood of attempts costs no CPU). A success resets
//!   the count; after a lockout expires the count starts again from zero. The state
//!   is in RAM: a reset clears it (a reboot takes far longer than a guess, and the
//!   PIN is only accepted on the local serial port).
//! * **Session.** A successful entry opens a maintenance session that ends after
//!   [`SESSION_IDLE_MS`] without [`MaintenanceAuth::touch`], or on
//!   [`MaintenanceAuth::exit`].
//! * **Time** is the caller's monotonic milliseconds; nothing here reads a clock.
//!   No allocation, no panic.

use core::fmt;
use core::mem::size_of;

use zerocopy::{FromBytes, Immutable, IntoBytes, KnownLayout, Unaligned};

use super::parse::is_pin;

/// Extra SHA-256 iterations after the first hash (`h(PIN_HASH_ROUNDS)` is stored).
pub const PIN_HASH_ROUNDS: u32 = 256;
/// Consecutive wrong PINs that trigger a lockout.
pub const MAX_FAILURES: u8 = 5;
/// Lockout length after the last of [`MAX_FAILURES`] wrong PINs, ms (5 min).
pub const LOCKOUT_MS: u64 = 300_000;
/// Maintenance session idle timeout, ms (10 min).
pub const SESSION_IDLE_MS: u64 = 600_000;

/// Why a PIN operation failed.
#[non_exhaustive]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum AuthError {
    /// No PIN has been set yet (commissioning: set one with `pin set`).
    NoPinSet,
    /// The PIN is wrong; this many attempts remain before a lockout.
    WrongPin {
        /// Attempts left before the lockout (1..=4).
        attempts_left: u8,
    },
    /// Too many wrong PINs; PIN entry is refused for this long.
    LockedOut {
        /// Seconds until PIN entry is accepted again (rounded up, >= 1).
        remaining_s: u32,
    },
    /// A new PIN is not 4..=12 ASCII digits.
    InvalidPin,
}

impl AuthError {
    /// Write the message (one line; `Display` writes the same), without core::fmt
    /// (issue 20).
    pub fn write_message(&self, f: &mut dyn super::json::Sink) -> fmt::Result {
        let (head, n, tail) = match *self {
            Self::NoPinSet => ("no maintenance PIN set; use 'pin set <new_pin>'", None, ""),
            Self::WrongPin { attempts_left } => (
                "wrong PIN; ",
                Some(u64::from(attempts_left)),
                " attempt(s) left",
            ),
            Self::LockedOut { remaining_s } => (
                "too many wrong PINs; locked for ",
                Some(u64::from(remaining_s)),
                " s",
            ),
            Self::InvalidPin => ("PIN must be 4-12 digits", None, ""),
        };
        f.put(head)?;
        if let Some(n) = n {
            super::json::write_u64(f, n)?;
        }
        f.put(tail)
    }
}

impl fmt::Display for AuthError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.write_message(f)
    }
}

/// The stored form of the maintenance PIN: salt and iterated salted SHA-256 hash,
/// record kind [`crate::odometer::kind::PIN`], laid out as declared (48 bytes):
///
/// ```text
///  0                16                                 48
///  +----------------+----------------------------------+
///  | salt (16 B)    | hash h(PIN_HASH_ROUNDS) (32 B)   |
///  +----------------+----------------------------------+
/// ```
#[derive(Clone, Copy, Debug, FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
pub struct PinRecord {
    /// Random salt, unique per record.
    pub salt: [u8; 16],
    /// `h(PIN_HASH_ROUNDS)` (see the module doc).
    pub hash: [u8; 32],
}

impl PinRecord {
    /// Serialised length: salt then hash.
    pub const LEN: usize = size_of::<Self>();

    /// Serialise as `salt || hash`.
    pub fn to_bytes(&self) -> [u8; Self::LEN] {
        zerocopy::transmute!(*self)
    }

    /// Deserialise exactly [`Self::LEN`] bytes; `None` for another length or blank
    /// flash (all 0xFF or all 0x00).
    pub fn from_bytes(bytes: &[u8]) -> Option<Self> {
        if bytes.iter().all(|&b| b == 0xFF) || bytes.iter().all(|&b| b == 0x00) {
            return None;
        }
        Self::read_from_bytes(bytes).ok()
    }

    /// Whether `pin` matches (constant-time comparison; a malformed PIN never does).
    pub fn verify(&self, pin: &str) -> bool {
        is_pin(pin) && ct_eq(&hash_pin(&self.salt, pin), &self.hash)
    }
}

/// Hash a new PIN (4..=12 ASCII digits) with the given random salt.
pub fn make_pin_record(pin: &str, salt: [u8; 16]) -> Result<PinRecord, AuthError> {
    if !is_pin(pin) {
        return Err(AuthError::InvalidPin);
    }
    Ok(PinRecord {
        salt,
        hash: hash_pin(&salt, pin),
    })
}

/// `h(PIN_HASH_ROUNDS)` of the module doc.
fn hash_pin(salt: &[u8; 16], pin: &str) -> [u8; 32] {
    let mut h = sha256_short(&[salt, pin.as_bytes()]);
    for _ in 0..PIN_HASH_ROUNDS {
        h = sha256_short(&[&h, salt]);
    }
    h
}

/// SHA-256's initial hash value (FIPS 180-4, 5.3.3).
const SHA256_H0: [u32; 8] = [
    0x6a09_e667,
    0xbb67_ae85,
    0x3c6e_f372,
    0xa54f_f53a,
    0x510e_527f,
    0x9b05_688c,
    0x1f83_d9ab,
    0x5be0_cd19,
];

/// SHA-256 of the concatenation of `parts`, a message of at most 55 bytes: one padded
/// block through sha2's compression function. Every hash the console takes is that
/// short (a PIN step: 48 bytes; a salt: 44), and sha2's `Digest` wrapper (its buffering
/// and finalisation, generic) cost 0.4 KB more of flash for them (issue 20). The same
/// digest as `Sha256::digest` (tested); a longer message is cut at 55 bytes.
pub(crate) fn sha256_short(parts: &[&[u8]]) -> [u8; 32] {
    let mut block = [0u8; 64];
    let mut n = 0usize;
    for &b in parts.iter().flat_map(|p| p.iter()).take(55) {
        if let Some(x) = block.get_mut(n) {
            *x = b;
        }
        n += 1;
    }
    if let Some(x) = block.get_mut(n) {
        *x = 0x80;
    }
    let bits = (n as u64 * 8).to_be_bytes();
    if let Some(tail) = block.get_mut(56..) {
        tail.copy_from_slice(&bits);
    }
    let mut state = SHA256_H0;
    sha2::compress256(&mut state, &[block.into()]);
    let mut out = [0u8; 32];
    for (o, w) in out.chunks_exact_mut(4).zip(state) {
        o.copy_from_slice(&w.to_be_bytes());
    }
    out
}

/// Constant-time equality of two hashes.
fn ct_eq(a: &[u8; 32], b: &[u8; 32]) -> bool {
    let diff = a
        .iter()
        .zip(b.iter())
        .fold(0u8, |acc, (x, y)| core::hint::black_box(acc | (x ^ y)));
    diff == 0
}

/// Maintenance-mode gate: failure count, lockout and session (RAM only).
#[derive(Clone, Debug, Default)]
pub struct MaintenanceAuth {
    /// Consecutive wrong PINs since the last success or expired lockout.
    failures: u8,
    /// PIN entry refused until this time, ms.
    locked_until_ms: Option<u64>,
    /// Time of the session's last activity, ms; `None` when no session.
    session_last_ms: Option<u64>,
}

impl MaintenanceAuth {
    /// No session, no failures.
    pub const fn new() -> Self {
        Self {
            failures: 0,
            locked_until_ms: None,
            session_last_ms: None,
        }
    }

    /// Check `pin` against `rec` and open a session on success (see the module doc).
    pub fn try_enter(
        &mut self,
        now_ms: u64,
        pin: &str,
        rec: Option<&PinRecord>,
    ) -> Result<(), AuthError> {
        if let Some(remaining_s) = self.lockout_remaining_s(now_ms) {
            return Err(AuthError::LockedOut { remaining_s });
        }
        if self.locked_until_ms.take().is_some() {
            // An expired lockout: a fresh set of attempts.
            self.failures = 0;
        }
        let rec = rec.ok_or(AuthError::NoPinSet)?;
        if rec.verify(pin) {
            self.failures = 0;
            self.session_last_ms = Some(now_ms);
            return Ok(());
        }
        self.failures = self.failures.saturating_add(1);
        if self.failures >= MAX_FAILURES {
            self.locked_until_ms = Some(now_ms.saturating_add(LOCKOUT_MS));
            return Err(AuthError::LockedOut {
                remaining_s: ceil_s(LOCKOUT_MS),
            });
        }
        Err(AuthError::WrongPin {
            attempts_left: MAX_FAILURES - self.failures,
        })
    }

    /// Seconds (rounded up) until PIN entry is accepted again; `None` when not locked.
    pub fn lockout_remaining_s(&self, now_ms: u64) -> Option<u32> {
        let until = self.locked_until_ms?;
        (now_ms < until).then(|| ceil_s(until - now_ms))
    }

    /// Consecutive wrong PINs counted so far.
    pub const fn failures(&self) -> u8 {
        self.failures
    }

    /// Whether a maintenance session is open and not idle for [`SESSION_IDLE_MS`].
    pub fn is_active(&self, now_ms: u64) -> bool {
        self.session_last_ms
            .is_some_and(|t| now_ms.saturating_sub(t) < SESSION_IDLE_MS)
    }

    /// Record session activity (restarts the idle timeout); ends an expired session.
    pub fn touch(&mut self, now_ms: u64) {
        self.session_last_ms = if self.is_active(now_ms) {
            Some(now_ms)
        } else {
            None
        };
    }

    /// End the maintenance session.
    pub fn exit(&mut self) {
        self.session_last_ms = None;
    }
}

/// Milliseconds to whole seconds, rounded up, saturating.
fn ceil_s(ms: u64) -> u32 {
    u32::try_from(ms.div_ceil(1000)).unwrap_or(u32::MAX)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn hex(b: &[u8; 32]) -> [u8; 64] {
        let mut out = [0u8; 64];
        for (i, x) in b.iter().enumerate() {
            out[2 * i] = b"0123456789abcdef"[usize::from(x >> 4)];
            out[2 * i + 1] = b"0123456789abcdef"[usize::from(x & 15)];
        }
        out
    }

    /// Known answers computed independently (Python hashlib).
    #[test]
    fn known_answer() {
        let mut salt = [0u8; 16];
        for (i, s) in salt.iter_mut().enumerate() {
            *s = i as u8;
        }
        let r = make_pin_record("1234", salt).unwrap();
        assert_eq!(
            &hex(&r.hash),
            b"678fe14c0f62b6a879267dcbcd20022b46e2a7ecf5d2483fa0e96caa4cddbbd0"
        );
        let r = make_pin_record("000000000000", [0xA5; 16]).unwrap();
        assert_eq!(
            &hex(&r.hash),
            b"8abd6cb1c58dc366d5877c730602abceee068ead5f019023f60ca1a97051b5dc"
        );
    }

    /// The one-block hash is SHA-256 for every length it takes (0..=55 bytes, split
    /// anywhere), as sha2's `Digest` computes it.
    #[test]
    fn the_short_hash_is_sha256() {
        use sha2::{Digest, Sha256};
        let msg: [u8; 55] = core::array::from_fn(|i| (i as u8).wrapping_mul(37) ^ 0x5a);
        for len in 0..=55 {
            for cut in [0, len / 3, len] {
                let (a, b) = msg[..len].split_at(cut);
                let want: [u8; 32] = Sha256::digest(&msg[..len]).into();
                assert_eq!(sha256_short(&[a, b]), want, "len {len} cut {cut}");
            }
        }
    }

    #[test]
    fn bytes_roundtrip_and_blank() {
        let r = make_pin_record("98765", [7; 16]).unwrap();
        let b = r.to_bytes();
        let back = PinRecord::from_bytes(&b).unwrap();
        assert_eq!((back.salt, back.hash), (r.salt, r.hash));
        assert!(PinRecord::from_bytes(&[0xFF; 48]).is_none());
        assert!(PinRecord::from_bytes(&[0x00; 48]).is_none());
        assert!(PinRecord::from_bytes(&b[..47]).is_none());
    }
}
