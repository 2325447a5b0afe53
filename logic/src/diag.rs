//! Why the MCU reset, and the crash that made it reset: read at boot, logged, counted in
//! flash, shown by the console's `status` and `faults`.
//!
//! * [`ResetCause`] from `RCC_CSR` (RM0090 §7.3.21): the board reads the flags before
//!   clearing them (`RMVF`). Every reset source also pulls NRST, so `PINRSTF` alone
//!   means a pin reset; the others take precedence in the order low-power, watchdog,
//!   software, power-on, brown-out.
//! * [`Crash`]: what a panic or a HardFault leaves in a RAM block that survives the
//!   reset (the board's `.uninit` section; `board/crash.rs`), checked by its CRC, or a
//!   stack found exhausted at boot.
//!
//! # Persisted formats (little-endian)
//!
//! Each is declared once, as a `zerocopy` layout (`ResetCountsLayout`, `CrashLayout`:
//! `#[repr(C)]`, byte-aligned little-endian fields, no padding), drawn here:
//!
//! Reset counts, record kind [`crate::odometer::kind::RESETS`], 24 bytes:
//!
//! ```text
//!  0          4        8          12         16          20          24
//!  +----------+--------+----------+----------+-----------+-----------+
//!  | power_on | pin    | watchdog | software | brown_out | low_power |   u32 each
//!  +----------+--------+----------+----------+-----------+-----------+
//! ```
//!
//! Crash, record kind [`crate::odometer::kind::CRASH`] and the RAM block's body, 44 bytes:
//!
//! ```text
//!  0      1       4      8      12      16      20      24                      44
//!  +------+-------+------+------+-------+-------+-------+------------------------+
//!  | kind | 0 0 0 |  pc  |  lr  | cfsr  | hfsr  | line  | file (20 bytes, 0-pad) |
//!  +------+-------+------+------+-------+-------+-------+------------------------+
//!  kind: 1 panic, 2 HardFault, 3 stack overflow; line: a panic's source line
//! ```

use core::mem::size_of;

use zerocopy::byteorder::little_endian::U32;
use zerocopy::{FromBytes, Immutable, IntoBytes, KnownLayout, Unaligned};

/// Why the MCU reset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ResetCause {
    /// Power applied (POR/PDR).
    PowerOn,
    /// The NRST pin (a button, a debugger, a supervisor chip).
    Pin,
    /// A watchdog expired.
    Watchdog,
    /// Software (`SYSRESETREQ`: the firmware reset itself, after a crash for instance).
    Software,
    /// The supply fell below the brown-out level.
    BrownOut,
    /// A low-power mode entry with its reset option.
    LowPower,
}

impl ResetCause {
    /// Every cause, in the order of [`ResetCounts`].
    pub const ALL: [Self; 6] = [
        Self::PowerOn,
        Self::Pin,
        Self::Watchdog,
        Self::Software,
        Self::BrownOut,
        Self::LowPower,
    ];

    /// From the reset flags of `RCC_CSR` (bits 25–31).
    pub const fn from_csr(csr: u32) -> Self {
        const BORRSTF: u32 = 1 << 25;
        const PORRSTF: u32 = 1 << 27;
        const SFTRSTF: u32 = 1 << 28;
        const IWDGRSTF: u32 = 1 << 29;
        const WWDGRSTF: u32 = 1 << 30;
        const LPWRRSTF: u32 = 1 << 31;
        if csr & LPWRRSTF != 0 {
            Self::LowPower
        } else if csr & (IWDGRSTF | WWDGRSTF) != 0 {
            Self::Watchdog
        } else if csr & SFTRSTF != 0 {
            Self::Software
        } else if csr & PORRSTF != 0 {
            Self::PowerOn
        } else if csr & BORRSTF != 0 {
            Self::BrownOut
        } else {
            Self::Pin
        }
    }

    /// Stable snake-case name.
    pub const fn name(self) -> &'static str {
        match self {
            Self::PowerOn => "power_on",
            Self::Pin => "pin",
            Self::Watchdog => "watchdog",
            Self::Software => "software",
            Self::BrownOut => "brown_out",
            Self::LowPower => "low_power",
        }
    }

    const fn index(self) -> usize {
        self as usize
    }
}

/// Resets since the controller was first commissioned, by cause.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ResetCounts {
    /// Counts in the order of [`ResetCause::ALL`].
    pub counts: [u32; 6],
}

/// A [`ResetCounts`] record as laid out in flash (see the module doc).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct ResetCountsLayout {
    counts: [U32; 6],
}

/// Bytes of a [`ResetCounts`] record.
pub const RESET_COUNTS_LEN: usize = size_of::<ResetCountsLayout>();

impl ResetCounts {
    /// One more reset of `cause` (saturating).
    pub fn count(&mut self, cause: ResetCause) {
        if let Some(c) = self.counts.get_mut(cause.index()) {
            *c = c.saturating_add(1);
        }
    }

    /// Resets of `cause`.
    pub fn of(&self, cause: ResetCause) -> u32 {
        self.counts.get(cause.index()).copied().unwrap_or(0)
    }

    /// The record.
    pub fn to_bytes(&self) -> [u8; RESET_COUNTS_LEN] {
        let layout = ResetCountsLayout {
            counts: self.counts.map(U32::new),
        };
        zerocopy::transmute!(layout)
    }

    /// From a record; `None` if it is not one.
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let layout = ResetCountsLayout::read_from_bytes(b).ok()?;
        Some(Self {
            counts: layout.counts.map(U32::get),
        })
    }
}

/// What crashed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum CrashKind {
    /// A Rust panic.
    Panic,
    /// A HardFault (a bus, memory or usage fault escalated).
    HardFault,
    /// The stack reached its bottom (found at boot by the stack paint).
    StackOverflow,
}

impl CrashKind {
    /// Stable snake-case name.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Panic => "panic",
            Self::HardFault => "hard_fault",
            Self::StackOverflow => "stack_overflow",
        }
    }
}

/// A crash record.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Crash {
    /// What.
    pub kind: CrashKind,
    /// Where: the faulting instruction (HardFault) or the panic's caller.
    pub pc: u32,
    /// Link register at the fault.
    pub lr: u32,
    /// Configurable fault status (HardFault), 0 otherwise.
    pub cfsr: u32,
    /// HardFault status (HardFault), 0 otherwise.
    pub hfsr: u32,
    /// Source line of a panic, 0 otherwise.
    pub line: u32,
    /// Source file of a panic (its last 20 bytes, zero-padded).
    pub file: [u8; 20],
}

/// A [`Crash`] record as laid out in flash and in the RAM block (see the module doc).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct CrashLayout {
    kind: u8,
    /// Zero when written; not read.
    pad: [u8; 3],
    pc: U32,
    lr: U32,
    cfsr: U32,
    hfsr: U32,
    line: U32,
    file: [u8; 20],
}

/// Bytes of a [`Crash`] record.
pub const CRASH_LEN: usize = size_of::<CrashLayout>();

impl CrashKind {
    /// The record's `kind` byte.
    const fn code(self) -> u8 {
        match self {
            Self::Panic => 1,
            Self::HardFault => 2,
            Self::StackOverflow => 3,
        }
    }

    const fn from_code(c: u8) -> Option<Self> {
        match c {
            1 => Some(Self::Panic),
            2 => Some(Self::HardFault),
            3 => Some(Self::StackOverflow),
            _ => None,
        }
    }
}

impl Crash {
    /// The record.
    pub fn to_bytes(&self) -> [u8; CRASH_LEN] {
        let layout = CrashLayout {
            kind: self.kind.code(),
            pad: [0; 3],
            pc: self.pc.into(),
            lr: self.lr.into(),
            cfsr: self.cfsr.into(),
            hfsr: self.hfsr.into(),
            line: self.line.into(),
            file: self.file,
        };
        zerocopy::transmute!(layout)
    }

    /// From a record; `None` if it is not one.
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let l = CrashLayout::read_from_bytes(b).ok()?;
        Some(Self {
            kind: CrashKind::from_code(l.kind)?,
            pc: l.pc.get(),
            lr: l.lr.get(),
            cfsr: l.cfsr.get(),
            hfsr: l.hfsr.get(),
            line: l.line.get(),
            file: l.file,
        })
    }

    /// The file name as text (up to the first zero; lossy).
    pub fn file_str(&self) -> &str {
        let n = self
            .file
            .iter()
            .position(|&c| c == 0)
            .unwrap_or(self.file.len());
        core::str::from_utf8(self.file.get(..n).unwrap_or(&[])).unwrap_or("?")
    }
}

/// The last `file.len()` bytes of `path` (a panic's file), zero-padded.
pub fn file_tail(path: &str) -> [u8; 20] {
    let mut f = [0u8; 20];
    let b = path.as_bytes();
    let tail = b.get(b.len().saturating_sub(f.len())..).unwrap_or(b);
    for (d, s) in f.iter_mut().zip(tail) {
        *d = *s;
    }
    f
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reset_cause_from_the_csr_flags() {
        // Every reset pulls NRST: PINRSTF comes with all of them.
        let pin = 1 << 26;
        assert_eq!(ResetCause::from_csr(pin), ResetCause::Pin);
        assert_eq!(
            ResetCause::from_csr(pin | (1 << 27) | (1 << 25)),
            ResetCause::PowerOn
        );
        assert_eq!(ResetCause::from_csr(pin | (1 << 29)), ResetCause::Watchdog);
        assert_eq!(ResetCause::from_csr(pin | (1 << 28)), ResetCause::Software);
        assert_eq!(ResetCause::from_csr(pin | (1 << 25)), ResetCause::BrownOut);
        assert_eq!(ResetCause::from_csr(pin | (1 << 31)), ResetCause::LowPower);
    }

    #[test]
    fn records_round_trip() {
        let mut r = ResetCounts::default();
        r.count(ResetCause::Watchdog);
        r.count(ResetCause::Watchdog);
        assert_eq!(ResetCounts::from_bytes(&r.to_bytes()), Some(r));
        assert_eq!(r.of(ResetCause::Watchdog), 2);
        let c = Crash {
            kind: CrashKind::Panic,
            pc: 0x0800_1234,
            lr: 0x0800_5679,
            cfsr: 0,
            hfsr: 0,
            line: 417,
            file: file_tail("src/very/long/path/controller.rs"),
        };
        assert_eq!(Crash::from_bytes(&c.to_bytes()), Some(c));
        assert_eq!(c.file_str(), "g/path/controller.rs");
        assert_eq!(Crash::from_bytes(&[9; CRASH_LEN]), None);
    }
}
