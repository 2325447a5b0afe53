//! FLASH interface (RM0090 §3) with the timing of DS8626 Table 41.
//!
//! * `KEYR`: KEY1 0x4567_0123 then KEY2 0xCDEF_89AB clears `CR.LOCK`; a wrong sequence
//!   locks `CR` until the next reset. `CR` is not writable while locked.
//! * **Program**: with `CR.PG` set, a CPU store to flash of the size `PSIZE` selects
//!   (x8/x16/x32) starts a program; its data is ANDed into the cell when it ends
//!   (NOR: bits only clear). A store without PG, or while an error flag is still set, is
//!   a `PGSERR` and programs nothing; a store of the wrong size a `PGPERR`; a misaligned
//!   one a `PGAERR`. **The error flags are sticky** until written 1.
//! * **Erase**: `CR.STRT` with `SER` erases sector `SNB` (0–3 16 KiB, 4 64 KiB, 5–11
//!   128 KiB), with `MER` the whole bank.
//! * **Timing** (word program; sector erase by PSIZE, typical / maximum):
//!
//!   | | x8 | x16 | x32 |
//!   |---|---|---|---|
//!   | program | 16 / 100 µs | 16 / 100 µs | 16 / 100 µs |
//!   | erase 16 KiB | 400 / 800 ms | 300 / 600 ms | 250 / 500 ms |
//!   | erase 64 KiB | 1.2 / 2.4 s | 0.7 / 1.4 s | 0.55 / 1.1 s |
//!   | erase 128 KiB | 2 / 4 s | 1.3 / 2.6 s | 1 / 2 s |
//!
//!   Which column applies is [`FlashTiming`] (the board defaults to the maximum: a model
//!   is never kinder than its datasheet).
//! * While `SR.BSY` is set, **any fetch or read from flash stalls the CPU** until the
//!   operation ends (the board does this: see `soc.rs`); code in SRAM keeps running.
//! * A reset during an erase leaves the sector partly erased (in proportion to the time
//!   that had passed); during a program, the word is left as far as it got.
//! * `ACR`: wait states, prefetch, the caches' enables and resets: the ART accelerator
//!   ([`super::art`]), which the board times fetches and reads through under
//!   [`crate::cpu::Timing::Art`].
//! * `OPTCR` holds the option bytes (BOR level, RDP, WDG_SW, nWRP): `OPTKEYR` 0x0819_2A3B,
//!   0x4C5D_6E7F clears `OPTLOCK`; `OPTSTRT` programs them (as long as a 16 KiB erase);
//!   they survive resets, like the flash.
//!
//! | off | name | reset |
//! |---|---|---|
//! | 0x00 | ACR | 0 |
//! | 0x04 | KEYR | write-only |
//! | 0x08 | OPTKEYR | write-only |
//! | 0x0C | SR | 0 |
//! | 0x10 | CR | 0x8000_0000 (LOCK) |
//! | 0x14 | OPTCR | option bytes, OPTLOCK set (factory: 0x0FFF_AAED) |

use super::art::Art;
use super::{lane, merge, no_read, no_write, Access};

/// Flash base address.
pub const FLASH_BASE: u32 = 0x0800_0000;
/// Flash size (STM32F407VG), bytes.
pub const FLASH_SIZE: u32 = 0x0010_0000;
/// First address of the odometer sectors (10 and 11).
pub const ODOMETER_BASE: u32 = 0x080C_0000;

/// SR bits.
pub mod sr {
    /// End of operation.
    pub const EOP: u32 = 1 << 0;
    /// Operation error.
    pub const OPERR: u32 = 1 << 1;
    /// Write-protection error.
    pub const WRPERR: u32 = 1 << 4;
    /// Programming alignment error.
    pub const PGAERR: u32 = 1 << 5;
    /// Programming parallelism error.
    pub const PGPERR: u32 = 1 << 6;
    /// Programming sequence error.
    pub const PGSERR: u32 = 1 << 7;
    /// Busy.
    pub const BSY: u32 = 1 << 16;
    /// All error flags.
    pub const ERRORS: u32 = OPERR | WRPERR | PGAERR | PGPERR | PGSERR;
}

const KEY1: u32 = 0x4567_0123;
const KEY2: u32 = 0xCDEF_89AB;
const OPTKEY1: u32 = 0x0819_2A3B;
const OPTKEY2: u32 = 0x4C5D_6E7F;
/// Factory option bytes (OPTCR view): BOR off, RDP level 0, software watchdog,
/// no write protection.
pub const OPTCR_FACTORY: u32 = 0x0FFF_AAEC;

/// Which datasheet column the flash timing follows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlashTiming {
    /// Typical program and erase times.
    Typical,
    /// Maximum program and erase times (the default).
    Max,
}

impl FlashTiming {
    /// Word (any PSIZE) program time, ps.
    pub const fn program_ps(self) -> u64 {
        match self {
            Self::Typical => 16_000_000,
            Self::Max => 100_000_000,
        }
    }

    /// Erase time of a sector of `kib` KiB at PSIZE `psize` (0 = x8, 1 = x16, 2/3 = x32), ps.
    pub const fn erase_ps(self, kib: u32, psize: u32) -> u64 {
        let col = if psize > 2 { 2 } else { psize as usize };
        // [x8, x16, x32] typical, ms
        let typ_ms: [u64; 3] = match kib {
            16 => [400, 300, 250],
            64 => [1_200, 700, 550],
            _ => [2_000, 1_300, 1_000],
        };
        let ms = typ_ms[col] * if matches!(self, Self::Max) { 2 } else { 1 };
        ms * 1_000_000_000
    }
}

/// Size of sector `n` of the 1 MiB single bank, KiB.
pub fn sector_kib(n: u32) -> u32 {
    match n {
        0..=3 => 16,
        4 => 64,
        _ => 128,
    }
}

/// Start address of sector `n`.
pub fn sector_base(n: u32) -> u32 {
    match n {
        0..=4 => FLASH_BASE + n * 0x4000,
        _ => FLASH_BASE + 0x2_0000 * (n - 4),
    }
}

/// The operation in progress.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Op {
    /// Program `size` bytes of `value` at `addr`.
    Program {
        /// Address.
        addr: u32,
        /// Bytes.
        size: usize,
        /// Data (little-endian).
        value: u64,
    },
    /// Erase sector `sector`.
    Erase {
        /// Sector number.
        sector: u32,
    },
    /// Erase every sector.
    MassErase,
    /// Program the option bytes.
    Options {
        /// New OPTCR value.
        optcr: u32,
    },
}

/// What an operation did to the array, applied by the board.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Done {
    /// The operation.
    pub op: Op,
    /// Fraction of it that happened, ‰ (1000 = complete; less when a reset cut it).
    pub permille: u32,
}

/// The flash interface.
#[derive(Clone, Debug)]
pub struct FlashCtl {
    acr: u32,
    sr: u32,
    cr: u32,
    /// Option bytes as programmed (survive resets).
    optcr_nv: u32,
    optcr: u32,
    key_stage: u8,
    key_lockout: bool,
    optkey_stage: u8,
    /// Operation in progress: (op, start, end), ps.
    busy: Option<(Op, u64, u64)>,
    /// Finished by a register read, not yet applied.
    done: Option<Done>,
    /// Timing column.
    pub timing: FlashTiming,
    /// Operations started.
    pub ops_started: u64,
    /// Sector erases started (see [`FlashCtl::erase_log`]).
    erases: Vec<(u64, u64, u32)>,
    /// The ART accelerator's caches and buffers (`ACR`'s enables, resets and wait
    /// states); the board times reads through it under [`crate::cpu::Timing::Art`].
    pub art: Art,
}

impl FlashCtl {
    /// At power-on, with factory option bytes.
    pub fn new(timing: FlashTiming) -> Self {
        let mut f = Self {
            acr: 0,
            sr: 0,
            cr: 0,
            optcr_nv: OPTCR_FACTORY,
            optcr: 0,
            key_stage: 0,
            key_lockout: false,
            optkey_stage: 0,
            busy: None,
            done: None,
            timing,
            ops_started: 0,
            erases: Vec::new(),
            art: Art::new(),
        };
        f.reset_regs();
        f
    }

    fn reset_regs(&mut self) {
        self.acr = 0;
        self.art.reset();
        self.sr = 0;
        self.cr = 1 << 31;
        self.optcr = self.optcr_nv | 1;
        self.key_stage = 0;
        self.key_lockout = false;
        self.optkey_stage = 0;
    }

    /// A system reset at `now`: an operation in progress is cut short (returned, with how
    /// far it got, for the board to apply); registers to reset values.
    pub fn reset(&mut self, now: u64) -> Option<Done> {
        let cut = self.busy.take().map(|(op, start, end)| Done {
            op,
            permille: ((now.saturating_sub(start)) as u128 * 1000 / (end - start).max(1) as u128)
                .min(999) as u32,
        });
        self.reset_regs();
        cut
    }

    /// The programmed option bytes (OPTCR layout).
    pub fn option_bytes(&self) -> u32 {
        self.optcr_nv
    }

    /// Write-protect sector `sector` (clear its nWRP bit), or lift the protection, as a
    /// probe programming the option bytes would. Takes effect at once.
    pub fn write_protect(&mut self, sector: u32, on: bool) {
        let bit = 1 << (16 + sector.min(11));
        if on {
            self.optcr_nv &= !bit;
        } else {
            self.optcr_nv |= bit;
        }
        self.optcr = (self.optcr & !bit) | (self.optcr_nv & bit);
    }

    /// Flash wait states (ACR.LATENCY).
    pub fn latency(&self) -> u32 {
        self.acr & 7
    }

    /// The access control register (wait states, prefetch, cache enables).
    #[inline]
    pub fn acr(&self) -> u32 {
        self.acr
    }

    /// When the operation in progress ends, ps.
    pub fn busy_until(&self) -> Option<u64> {
        self.busy.map(|(_, _, end)| end)
    }

    /// An operation finished during a register read, for the board to apply.
    pub fn take_done(&mut self) -> Option<Done> {
        self.done.take()
    }

    /// Finish the operation if it has ended by `now`; returns it for the board to apply.
    pub fn complete(&mut self, now: u64) -> Option<Done> {
        match self.busy {
            Some((op, _, end)) if now >= end => {
                self.busy = None;
                self.sr |= sr::EOP;
                if let Op::Options { optcr } = op {
                    self.optcr_nv = optcr & !3;
                }
                Some(Done { op, permille: 1000 })
            }
            _ => None,
        }
    }

    /// The interface's interrupt line (EOPIE / ERRIE).
    pub fn irq(&self) -> bool {
        (self.cr & (1 << 24) != 0 && self.sr & sr::EOP != 0)
            || (self.cr & (1 << 25) != 0 && self.sr & sr::OPERR != 0)
    }

    fn start(&mut self, op: Op, now: u64) {
        let d = match op {
            Op::Program { .. } => self.timing.program_ps(),
            Op::Erase { sector } => self.timing.erase_ps(sector_kib(sector), (self.cr >> 8) & 3),
            Op::MassErase => self.timing.erase_ps(128, (self.cr >> 8) & 3) * 8,
            Op::Options { .. } => self.timing.erase_ps(16, 2),
        };
        self.busy = Some((op, now, now + d));
        self.ops_started += 1;
        if let Op::Erase { sector } = op {
            self.erases.push((now, now + d, sector));
        }
    }

    /// Every sector erase started since power-on: (start, end as timed, sector), ps (an
    /// erase a reset cut ends at the cut).
    pub fn erase_log(&self) -> &[(u64, u64, u32)] {
        &self.erases
    }

    /// Write-protected sector? (nWRP bit clear)
    fn protected(&self, sector: u32) -> bool {
        self.optcr_nv & (1 << (16 + sector)) == 0
    }

    /// A CPU store of `size` bytes at flash address `addr` (the board has already waited
    /// for any operation in progress). Returns whether a program started.
    pub fn store(&mut self, addr: u32, size: usize, value: u64, now: u64) -> bool {
        if self.cr & 1 == 0 || self.cr & (1 << 31) != 0 || self.sr & sr::ERRORS != 0 {
            self.sr |= sr::PGSERR;
            return false;
        }
        let want = 1usize << ((self.cr >> 8) & 3);
        if size != want {
            self.sr |= sr::PGPERR;
            return false;
        }
        if addr as usize % size != 0 {
            self.sr |= sr::PGAERR;
            return false;
        }
        let sector = (0..12).rev().find(|&n| addr >= sector_base(n)).unwrap_or(0);
        if self.protected(sector) {
            self.sr |= sr::WRPERR;
            return false;
        }
        self.start(Op::Program { addr, size, value }, now);
        true
    }

    /// What a read at `off` returns before the operation in progress ends (it does not
    /// change with time until then: the end is an event of the board). `None`: a
    /// register a polling loop is not skipped over.
    pub fn peek(&self, off: u32, size: usize) -> Option<u32> {
        let v = match off & !3 {
            0x00 => self.acr,
            0x0C => self.sr | if self.busy.is_some() { sr::BSY } else { 0 },
            0x10 => self.cr,
            0x14 => self.optcr,
            _ => return None,
        };
        Some(lane(v, off, size))
    }

    /// Read at `off`.
    pub fn read(&mut self, off: u32, size: usize, now: u64) -> Access<u32> {
        // An operation that has ended by now is finished before software looks; the board
        // applies its effect on the array (`take_done`) right after this access.
        if let Some(d) = self.complete(now) {
            self.done = Some(d);
        }
        let v = match off & !3 {
            0x00 => self.acr,
            0x0C => self.sr | if self.busy.is_some() { sr::BSY } else { 0 },
            0x10 => self.cr,
            0x14 => self.optcr,
            0x04 | 0x08 => 0,
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off`.
    pub fn write(&mut self, off: u32, size: usize, value: u32, now: u64) -> Access<()> {
        let o = off & !3;
        match o {
            0x00 => {
                let new = merge(self.acr, off, size, value) & 0x1F07;
                self.acr = self.art.write_acr(self.acr, new);
            }
            0x04 => {
                if self.key_lockout || self.cr & (1 << 31) == 0 {
                    if self.cr & (1 << 31) != 0 {
                        self.key_lockout = true;
                    }
                    return Ok(());
                }
                match (self.key_stage, value) {
                    (0, KEY1) => self.key_stage = 1,
                    (1, KEY2) => {
                        self.key_stage = 0;
                        self.cr &= !(1 << 31);
                    }
                    _ => {
                        self.key_stage = 0;
                        self.key_lockout = true;
                    }
                }
            }
            0x08 => match (self.optkey_stage, value) {
                (0, OPTKEY1) => self.optkey_stage = 1,
                (1, OPTKEY2) => {
                    self.optkey_stage = 0;
                    self.optcr &= !1;
                }
                _ => self.optkey_stage = 0,
            },
            0x0C => {
                // Write 1 to clear EOP and the error flags.
                let v = merge(0, off, size, value);
                self.sr &= !(v & (sr::EOP | sr::ERRORS));
            }
            0x10 => {
                if self.cr & (1 << 31) != 0 {
                    return Ok(()); // locked: not writable
                }
                let v = merge(self.cr, off, size, value) & 0x8301_03FF;
                self.cr = v & !(1 << 16);
                if v & (1 << 16) != 0 {
                    if self.busy.is_some() || self.sr & sr::ERRORS != 0 {
                        self.sr |= sr::PGSERR;
                    } else if v & (1 << 2) != 0 {
                        self.start(Op::MassErase, now);
                    } else if v & (1 << 1) != 0 {
                        let sector = (v >> 3) & 0xF;
                        if sector > 11 {
                            self.sr |= sr::PGSERR;
                        } else if self.protected(sector) {
                            self.sr |= sr::WRPERR;
                        } else {
                            self.start(Op::Erase { sector }, now);
                        }
                    } else {
                        self.sr |= sr::PGSERR;
                    }
                }
            }
            0x14 => {
                if self.optcr & 1 != 0 {
                    return Ok(()); // OPTLOCK
                }
                let v = merge(self.optcr, off, size, value) & 0x0FFF_FFEF;
                self.optcr = v & !2;
                if v & 2 != 0 {
                    if self.busy.is_some() {
                        self.sr |= sr::PGSERR;
                    } else {
                        self.start(Op::Options { optcr: v }, now);
                    }
                }
            }
            _ => return no_write(off),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn unlocked() -> FlashCtl {
        let mut f = FlashCtl::new(FlashTiming::Max);
        f.write(0x04, 4, KEY1, 0).unwrap();
        f.write(0x04, 4, KEY2, 0).unwrap();
        assert_eq!(f.read(0x10, 4, 0).unwrap() >> 31, 0, "unlocked");
        f
    }

    #[test]
    fn erase_takes_the_datasheet_time_by_psize() {
        let mut f = unlocked();
        f.write(0x10, 4, (2 << 8) | (10 << 3) | 2, 0).unwrap(); // x32, SER, SNB 10
        f.write(0x10, 4, (2 << 8) | (10 << 3) | 2 | (1 << 16), 0)
            .unwrap();
        assert_eq!(
            f.busy_until(),
            Some(2_000_000_000_000),
            "128 KiB x32 max: 2 s"
        );
        assert_ne!(f.read(0x0C, 4, 1).unwrap() & sr::BSY, 0);
        assert!(f.complete(1_999_999_999_999).is_none());
        let d = f.complete(2_000_000_000_000).unwrap();
        assert_eq!(
            d,
            Done {
                op: Op::Erase { sector: 10 },
                permille: 1000
            }
        );
        assert_eq!(f.read(0x0C, 4, 0).unwrap(), sr::EOP);
    }

    #[test]
    fn sticky_errors_refuse_the_next_program_until_cleared() {
        let mut f = unlocked();
        assert!(!f.store(ODOMETER_BASE, 4, 0, 0), "no PG: sequence error");
        assert_eq!(f.read(0x0C, 4, 0).unwrap(), sr::PGSERR);
        f.write(0x10, 4, (2 << 8) | 1, 0).unwrap(); // PG, x32
        assert!(!f.store(ODOMETER_BASE, 4, 0, 0), "sticky PGSERR refuses it");
        f.write(0x0C, 4, sr::ERRORS, 0).unwrap();
        assert!(
            !f.store(ODOMETER_BASE, 1, 0, 0),
            "byte store at x32: parallelism"
        );
        assert_eq!(f.read(0x0C, 4, 0).unwrap(), sr::PGPERR);
        f.write(0x0C, 4, sr::ERRORS, 0).unwrap();
        assert!(f.store(ODOMETER_BASE, 4, 0x1234, 0));
        assert_eq!(f.busy_until(), Some(100_000_000));
    }

    #[test]
    fn wrong_key_locks_until_reset_and_a_reset_cuts_an_erase() {
        let mut f = FlashCtl::new(FlashTiming::Typical);
        f.write(0x04, 4, 0x1111, 0).unwrap();
        f.write(0x04, 4, KEY1, 0).unwrap();
        f.write(0x04, 4, KEY2, 0).unwrap();
        assert_ne!(f.read(0x10, 4, 0).unwrap() >> 31, 0, "still locked");
        let mut f = unlocked();
        f.write(0x10, 4, (11 << 3) | 2 | (1 << 16), 0).unwrap(); // x8: 2 s typical... max 4 s
        let end = f.busy_until().unwrap();
        let cut = f.reset(end / 4).unwrap();
        assert_eq!(cut.permille, 250);
        assert_eq!(
            f.read(0x10, 4, 0).unwrap() >> 31,
            1,
            "locked again after reset"
        );
    }
}
