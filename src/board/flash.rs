//! The odometer's flash sectors (10 and 11), and the docking signature's (2, 3 and 4:
//! [`SigFlash`]), driven at register level (RM0090 §3.6).
//!
//! # Why not the HAL's flash driver
//!
//! stm32f4xx-hal 0.23's `LockedFlash` erases at PSIZE ×8 (2 s typical, **4 s maximum**
//! for a 128 KiB sector, DS8626 Table 41) and waits for the end by polling `BSY` from
//! code in flash. While an erase runs, every fetch from flash stalls the CPU, so
//! nothing runs — not the loop that feeds the independent watchdog (500 ms; 340 ms on a
//! fast LSI). The watchdog reset the chip in the middle of every sector erase, and the
//! same erase was attempted again after the reboot: a reset loop (shown by the virtual
//! board, `vboard/tests/defects.rs`; the host's simulated flash erased in zero time).
//!
//! # How this driver erases
//!
//! * PSIZE ×32 (the board runs at 3.3 V, within the 2.7–3.6 V that ×32 needs): 1 s
//!   typical, 2 s maximum per sector.
//! * The start of the erase and the wait for its end run **from SRAM**
//!   ([`erase_from_ram`], placed in `.data` and copied to RAM at boot), with
//!   interrupts masked (an interrupt's vector and handler are in flash: taking one
//!   would stall until the end). The loop feeds the watchdog while `BSY` is set, but only
//!   for [`ERASE_TIMEOUT_CYCLES`] (3 s, the datasheet's maximum plus half): a flash that
//!   never finishes is still caught by the watchdog.
//! * Everything else (unlock, clearing the sticky error flags before each operation,
//!   word programming) runs from flash: a word program stalls the CPU for at most 100 µs.
//!
//! The controller erases only while every motor is off (`storage.rs`, `controller.rs`):
//! during the erase (1–2 s) step pulses and console input stop; console bytes that
//! arrive meanwhile are lost (the USART has a one-byte data register).

use embedded_storage::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};
use stm32f4xx_hal::pac;

use super::SYSCLK_HZ;

/// Flash base address.
const FLASH_BASE: u32 = 0x0800_0000;
/// Offset of the odometer sectors from the flash base (`_odometer_start` in memory.x).
const ODOMETER_OFFSET: u32 = 0x000C_0000;
/// Size of the odometer region (2 × 128 KiB sectors).
const ODOMETER_LEN: u32 = 0x0004_0000;
/// First sector of the region.
const FIRST_SECTOR: u32 = 10;
/// Sector size, bytes.
const SECTOR_LEN: u32 = 128 * 1024;

// Registers (RM0090 §3.9).
const FLASH_ACR: *mut u32 = 0x4002_3C00 as *mut u32;
const FLASH_KEYR: *mut u32 = 0x4002_3C04 as *mut u32;
pub(crate) const FLASH_SR: *mut u32 = 0x4002_3C0C as *mut u32;
const FLASH_CR: *mut u32 = 0x4002_3C10 as *mut u32;
pub(crate) const IWDG_KR: *mut u32 = 0x4000_3000 as *mut u32;
pub(crate) const DWT_CYCCNT: *const u32 = 0xE000_1004 as *const u32;

const KEY1: u32 = 0x4567_0123;
const KEY2: u32 = 0xCDEF_89AB;
pub(crate) const SR_BSY: u32 = 1 << 16;
/// EOP and the sticky error flags (OPERR, WRPERR, PGAERR, PGPERR, PGSERR).
pub(crate) const SR_ERRORS: u32 = 0xF2;
const SR_CLEAR: u32 = SR_ERRORS | 1;
const CR_PG: u32 = 1 << 0;
const CR_SER: u32 = 1 << 1;
const CR_PSIZE_X32: u32 = 0b10 << 8;
const CR_STRT: u32 = 1 << 16;
const CR_LOCK: u32 = 1 << 31;
const ACR_ICEN: u32 = 1 << 9;
const ACR_DCEN: u32 = 1 << 10;
const ACR_ICRST: u32 = 1 << 11;
const ACR_DCRST: u32 = 1 << 12;

/// Reset the ART accelerator's instruction and data caches (RM0090 §3.5.2: a line
/// cached from a sector before its erase stays stale after it; ST's HAL does the same
/// after every erase, `FLASH_FlushCaches`). A cache is reset only while disabled, then
/// enabled again as it was.
fn flush_caches() {
    // SAFETY: FLASH_ACR, a fixed MMIO address; only the cache enable/reset bits change.
    unsafe {
        let acr = core::ptr::read_volatile(FLASH_ACR);
        let on = acr & (ACR_ICEN | ACR_DCEN);
        core::ptr::write_volatile(FLASH_ACR, acr & !(ACR_ICEN | ACR_DCEN));
        core::ptr::write_volatile(
            FLASH_ACR,
            (acr & !(ACR_ICEN | ACR_DCEN)) | ACR_ICRST | ACR_DCRST,
        );
        core::ptr::write_volatile(FLASH_ACR, acr & !(ACR_ICEN | ACR_DCEN));
        core::ptr::write_volatile(FLASH_ACR, (acr & !(ACR_ICEN | ACR_DCEN)) | on);
    }
}

/// Sector erases started since boot ([`OdometerFlash::erases`]).
static ERASES: core::sync::atomic::AtomicU32 = core::sync::atomic::AtomicU32::new(0);

/// Longest wait for a sector erase: the datasheet's 2 s maximum at ×32, plus half.
pub const ERASE_TIMEOUT_CYCLES: u32 = 3 * SYSCLK_HZ;

/// Errors of the odometer flash (`defmt::Format` for the log: `Debug2Format` would link
/// core::fmt's machinery into the image for this one message, issue 20).
#[derive(Clone, Copy, Debug, PartialEq, Eq, defmt::Format)]
pub enum OdoFlashError {
    /// Outside the two odometer sectors.
    OutOfBounds,
    /// Not a whole number of 32-bit words, or not word-aligned.
    NotAligned,
    /// The unlock sequence did not clear `CR.LOCK` (locked until the next reset).
    Locked,
    /// The controller flagged an error (the `SR` error bits).
    Status(u32),
    /// An erase still ran after [`ERASE_TIMEOUT_CYCLES`].
    Timeout,
}

impl NorFlashError for OdoFlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            Self::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            Self::NotAligned => NorFlashErrorKind::NotAligned,
            _ => NorFlashErrorKind::Other,
        }
    }
}

/// Wait (inside an `unsafe` block of a function placed in SRAM) until the flash interface
/// is no longer busy or `max_cycles` core cycles have passed, feeding the watchdog and
/// answering the Modbus line meanwhile (`modbus::busy_responder`: every request
/// for this unit gets exception 06, server device busy, within t3.5 of its end; issue
/// 31); the value is FLASH_SR at the end (BSY still set: timed out). A macro, not a
/// function, so that nothing is ever called from flash while the flash is busy (the
/// erase here, the option bytes in `options.rs`): everything it runs is inlined.
macro_rules! wait_idle_feeding {
    ($max_cycles:expr) => {{
        use $crate::board::flash::{DWT_CYCCNT, FLASH_SR, IWDG_KR, SR_BSY};
        // The responder's frame buffer, in `.bss` (a buffer on the stack would be
        // zeroed by a call to flash); one user at a time: interrupts are masked.
        let responder = &mut *core::ptr::addr_of_mut!($crate::board::modbus::RESPONDER);
        let start = core::ptr::read_volatile(DWT_CYCCNT);
        // Characters idle had not taken yet (a request that began before the wait).
        if $crate::board::modbus::RING.pending() {
            $crate::board::modbus::busy_responder(responder, start, $max_cycles);
        }
        loop {
            let sr = core::ptr::read_volatile(FLASH_SR);
            if sr & SR_BSY == 0
                || core::ptr::read_volatile(DWT_CYCCNT).wrapping_sub(start) > $max_cycles
            {
                break sr;
            }
            if $crate::board::modbus::char_waiting() {
                $crate::board::modbus::busy_responder(responder, start, $max_cycles);
            }
            core::ptr::write_volatile(IWDG_KR, 0xAAAA);
        }
    }};
}
pub(super) use wait_idle_feeding;

/// Start the erase described by `cr` (SER, SNB, PSIZE) and wait for its end, from SRAM,
/// feeding the watchdog for at most `max_cycles` core cycles. Returns `FLASH_SR` at the
/// end (`BSY` still set: timed out).
///
/// It must not touch flash: no call (everything it uses is inlined), no literal in
/// flash (it lives in `.data`, with its literals), and interrupts masked by the caller.
#[inline(never)]
#[link_section = ".data.odometer_erase_from_ram"]
fn erase_from_ram(cr: u32, max_cycles: u32) -> u32 {
    // SAFETY: fixed MMIO addresses of this chip (RM0090 §3.9, §21.4; ARMv7-M C1.8); the
    // caller owns the flash interface and has masked interrupts.
    unsafe {
        core::ptr::write_volatile(FLASH_CR, cr);
        core::ptr::write_volatile(FLASH_CR, cr | CR_STRT);
        wait_idle_feeding!(max_cycles)
    }
}

/// The odometer sectors. Owns the flash interface: nothing else programs or erases.
pub struct OdometerFlash {
    _flash: pac::FLASH,
}

impl OdometerFlash {
    /// Take the flash interface.
    pub fn new(flash: pac::FLASH) -> Self {
        Self { _flash: flash }
    }

    fn check(from: u32, len: usize) -> Result<u32, OdoFlashError> {
        let end = u32::try_from(len)
            .ok()
            .and_then(|l| from.checked_add(l))
            .ok_or(OdoFlashError::OutOfBounds)?;
        if end > ODOMETER_LEN {
            return Err(OdoFlashError::OutOfBounds);
        }
        Ok(FLASH_BASE + ODOMETER_OFFSET + from)
    }

    fn wait_idle() -> u32 {
        loop {
            // SAFETY: read of FLASH_SR, a fixed MMIO address.
            let sr = unsafe { core::ptr::read_volatile(FLASH_SR) };
            if sr & SR_BSY == 0 {
                return sr;
            }
        }
    }

    /// Unlock `CR` and clear the sticky flags of an earlier failure: a set error flag
    /// would make the next operation fail (RM0090 §3.6.2).
    // Out of line (issue 20): every erase and program starts here; inlined it was five
    // copies (-84 B). Called from flash, before `erase_from_ram` runs from RAM.
    #[inline(never)]
    fn begin() -> Result<(), OdoFlashError> {
        Self::wait_idle();
        // SAFETY: the unlock key sequence and a write-1-to-clear of FLASH_SR (fixed MMIO).
        unsafe {
            if core::ptr::read_volatile(FLASH_CR) & CR_LOCK != 0 {
                core::ptr::write_volatile(FLASH_KEYR, KEY1);
                core::ptr::write_volatile(FLASH_KEYR, KEY2);
            }
            if core::ptr::read_volatile(FLASH_CR) & CR_LOCK != 0 {
                return Err(OdoFlashError::Locked);
            }
            core::ptr::write_volatile(FLASH_SR, SR_CLEAR);
        }
        Ok(())
    }

    /// Clear PG/SER and lock `CR` again.
    fn end() {
        // SAFETY: FLASH_CR, a fixed MMIO address; writing LOCK is always allowed.
        unsafe { core::ptr::write_volatile(FLASH_CR, CR_LOCK) };
    }

    fn status(sr: u32) -> Result<(), OdoFlashError> {
        match sr & SR_ERRORS & !1 {
            0 => Ok(()),
            e => Err(OdoFlashError::Status(e)),
        }
    }

    /// Sector erases started since boot (the service runs one a rest window: issue 31).
    pub fn erases() -> u32 {
        ERASES.load(core::sync::atomic::Ordering::Relaxed)
    }

    fn erase_sector(sector: u32) -> Result<(), OdoFlashError> {
        ERASES.fetch_add(1, core::sync::atomic::Ordering::Relaxed);
        Self::begin()?;
        let cr = CR_PSIZE_X32 | CR_SER | (sector << 3);
        let sr = cortex_m::interrupt::free(|_| {
            let sr = erase_from_ram(cr, ERASE_TIMEOUT_CYCLES);
            // Before anything reads flash through a line the erase left stale.
            flush_caches();
            sr
        });
        if sr & SR_BSY != 0 {
            // Still erasing: CR cannot be written while busy; the next operation waits.
            return Err(OdoFlashError::Timeout);
        }
        Self::end();
        Self::status(sr)
    }
}

/// The bootloader's state sector (sector 1, `boot/`; docs/update.md, "The state
/// record": embassy-boot 0.7's format, its map and magics in `update-layout`). The
/// application reads its magic at boot and confirms a trial boot here; the updater
/// (`update.rs`) marks an update through embassy-boot.
const BOOT_STATE: u32 = update_layout::layout::STATE_BASE;
/// Its sector number.
const BOOT_STATE_SECTOR: u32 = 1;
const _: () = assert!(matches!(
    update_layout::layout::sector_of(BOOT_STATE),
    Some((BOOT_STATE_SECTOR, BOOT_STATE, _))
));

pub use update_layout::state::Boot as BootTrial;
use update_layout::state::{BOOT as BOOT_MAGIC, VALID_OFFSET};

impl OdometerFlash {
    /// The bootloader's state at this boot.
    pub fn boot_trial() -> BootTrial {
        // SAFETY: a word of the state sector, mapped readable flash.
        BootTrial::from_magic(unsafe { core::ptr::read_volatile(BOOT_STATE as *const u32) })
    }

    /// Confirm a trial boot (embassy-boot's `mark_booted`): invalidate the progress
    /// words, erase the state sector, write BOOT. A cut after the erase leaves an erased
    /// sector, read as BOOT by the bootloader; a cut between the invalidation and the
    /// erase, SWAP with the progress invalid, which the bootloader takes as a revert
    /// with nothing to copy (this image stays); a cut before the invalidation took, SWAP
    /// as it was: not confirmed, rolled back (boot/src/lib.rs tests each case). Only on a trial: a confirmed state is never rewritten (no erase per boot).
    /// From the flash's owner at rest (the service, `update::confirm_trial`), as the
    /// odometer's erases: interrupts masked in the erase, the watchdog fed from SRAM.
    pub fn confirm_boot() -> Result<(), OdoFlashError> {
        if Self::boot_trial() != BootTrial::Trial {
            return Ok(());
        }
        // SAFETY: the progress-valid word of the state sector, readable flash.
        let valid = unsafe { core::ptr::read_volatile((BOOT_STATE + VALID_OFFSET) as *const u32) };
        if valid == 0xFFFF_FFFF {
            Self::program_word(BOOT_STATE + VALID_OFFSET, 0)?;
        }
        Self::erase_sector(BOOT_STATE_SECTOR)?;
        Self::program_word(BOOT_STATE, BOOT_MAGIC)
    }

    #[cfg(feature = "updater")]
    /// Erase the sector at `base` for the updater (`update.rs`): a sector of the DFU
    /// pages an update fills, or STATE, from SRAM with the watchdog fed, as the
    /// odometer's. Any other sector (the bootloader, the project's sectors 2-4, ACTIVE,
    /// DFU's spare page, the odometer) is refused before a register is touched. Call
    /// only from the controller's owner, at rest.
    pub fn erase_update_sector(base: u32) -> Result<(), OdoFlashError> {
        let (n, start, len) =
            update_layout::layout::sector_of(base).ok_or(OdoFlashError::OutOfBounds)?;
        if start != base || !updater_may_write(base, len) {
            return Err(OdoFlashError::OutOfBounds);
        }
        Self::erase_sector(n)
    }

    #[cfg(feature = "updater")]
    /// Program whole words at `addr` for the updater: inside the DFU pages an update
    /// fills or STATE only (as [`Self::erase_update_sector`]). Call only from the owner,
    /// at rest.
    pub fn program_update(addr: u32, data: &[u8]) -> Result<(), OdoFlashError> {
        let len = u32::try_from(data.len()).map_err(|_| OdoFlashError::OutOfBounds)?;
        if addr % 4 != 0 || len % 4 != 0 {
            return Err(OdoFlashError::NotAligned);
        }
        if !updater_may_write(addr, len) {
            return Err(OdoFlashError::OutOfBounds);
        }
        Self::begin()?;
        // SAFETY: FLASH_CR (fixed MMIO): PG with ×32 parallelism.
        unsafe { core::ptr::write_volatile(FLASH_CR, CR_PSIZE_X32 | CR_PG) };
        let mut result = Ok(());
        for (a, w) in (addr..).step_by(4).zip(data.chunks_exact(4)) {
            let mut le = [0u8; 4];
            le.copy_from_slice(w);
            // SAFETY: a word-aligned address inside DFU or STATE (checked above),
            // PG set: the store programs it.
            unsafe { core::ptr::write_volatile(a as *mut u32, u32::from_le_bytes(le)) };
            result = Self::status(Self::wait_idle());
            if result.is_err() {
                break;
            }
        }
        Self::end();
        result
    }

    /// Program one word of the state sector.
    fn program_word(addr: u32, word: u32) -> Result<(), OdoFlashError> {
        if !(BOOT_STATE..BOOT_STATE + 0x4000).contains(&addr) || addr % 4 != 0 {
            return Err(OdoFlashError::OutOfBounds);
        }
        Self::begin()?;
        // SAFETY: FLASH_CR (fixed MMIO): PG with ×32 parallelism; then a word-aligned
        // address inside the state sector (checked above): the store programs it.
        unsafe {
            core::ptr::write_volatile(FLASH_CR, CR_PSIZE_X32 | CR_PG);
            core::ptr::write_volatile(addr as *mut u32, word);
        }
        let r = Self::status(Self::wait_idle());
        Self::end();
        r
    }
}

#[cfg(feature = "updater")]
/// Whether `[addr, addr + len)` lies in what the updater writes: the DFU pages an update
/// file fills (ACTIVE's length from DFU's start; the swap's spare page is the
/// bootloader's), or STATE.
fn updater_may_write(addr: u32, len: u32) -> bool {
    use update_layout::layout::{ACTIVE_LEN, DFU_BASE, STATE_BASE, STATE_LEN};
    let Some(end) = addr.checked_add(len) else {
        return false;
    };
    (addr >= DFU_BASE && end <= DFU_BASE + ACTIVE_LEN)
        || (addr >= STATE_BASE && end <= STATE_BASE + STATE_LEN)
}

impl ErrorType for OdometerFlash {
    type Error = OdoFlashError;
}

impl ReadNorFlash for OdometerFlash {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        let at = Self::check(offset, bytes.len())?;
        for (i, b) in (at..).zip(bytes.iter_mut()) {
            // SAFETY: `check` keeps the range inside the odometer sectors, which are
            // mapped, readable flash.
            *b = unsafe { core::ptr::read_volatile(i as *const u8) };
        }
        Ok(())
    }

    fn capacity(&self) -> usize {
        ODOMETER_LEN as usize
    }
}

impl NorFlash for OdometerFlash {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = SECTOR_LEN as usize;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        let len = to.checked_sub(from).ok_or(OdoFlashError::OutOfBounds)?;
        Self::check(from, len as usize)?;
        if from % SECTOR_LEN != 0 || len % SECTOR_LEN != 0 {
            return Err(OdoFlashError::NotAligned);
        }
        for s in (from / SECTOR_LEN)..(to / SECTOR_LEN) {
            Self::erase_sector(FIRST_SECTOR + s)?;
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let at = Self::check(offset, bytes.len())?;
        if at % 4 != 0 || bytes.len() % 4 != 0 {
            return Err(OdoFlashError::NotAligned);
        }
        Self::begin()?;
        // SAFETY: FLASH_CR (fixed MMIO): PG with ×32 parallelism.
        unsafe { core::ptr::write_volatile(FLASH_CR, CR_PSIZE_X32 | CR_PG) };
        let mut result = Ok(());
        for (addr, w) in (at..).step_by(4).zip(bytes.chunks_exact(4)) {
            let mut le = [0u8; 4];
            le.copy_from_slice(w);
            let word = u32::from_le_bytes(le);
            // SAFETY: a word-aligned address inside the odometer sectors, with PG set:
            // this store programs the word (RM0090 §3.6.4).
            unsafe { core::ptr::write_volatile(addr as *mut u32, word) };
            result = Self::status(Self::wait_idle());
            if result.is_err() {
                break;
            }
        }
        Self::end();
        result
    }
}

/// The docking signature's sectors: 2 and 3 (16 KiB each) and 4 (64 KiB), 0x0800_8000
/// to 0x0801_FFFF (update-layout's `PROJECT_FREE`), as one region of 96 KiB. Erases
/// and programs as the odometer's (×32, the erase's wait from SRAM feeding the
/// watchdog and answering the Modbus line), through the same interface, from the same
/// owner (the controller's service, at rest). `ERASE_SIZE` is the smallest sector; an
/// erase must be exactly one of the three sectors (the store never erases less).
pub struct SigFlash;

/// The signature region: its first address, length, and sectors (offset, length,
/// number).
const SIG_BASE: u32 = update_layout::layout::PROJECT_FREE.0;
const SIG_LEN: u32 = update_layout::layout::PROJECT_FREE.1;
const SIG_SECTORS: [(u32, u32, u32); 3] =
    [(0, 0x4000, 2), (0x4000, 0x4000, 3), (0x8000, 0x1_0000, 4)];
const _: () = assert!(SIG_BASE == 0x0800_8000 && SIG_LEN == 0x1_8000);
const _: () = assert!(matches!(
    update_layout::layout::sector_of(SIG_BASE + 0x8000),
    Some((4, _, 0x1_0000))
));

impl SigFlash {
    fn check(from: u32, len: usize) -> Result<u32, OdoFlashError> {
        let end = u32::try_from(len)
            .ok()
            .and_then(|l| from.checked_add(l))
            .ok_or(OdoFlashError::OutOfBounds)?;
        if end > SIG_LEN {
            return Err(OdoFlashError::OutOfBounds);
        }
        Ok(SIG_BASE + from)
    }
}

impl ErrorType for SigFlash {
    type Error = OdoFlashError;
}

impl ReadNorFlash for SigFlash {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        let at = Self::check(offset, bytes.len())?;
        for (i, b) in (at..).zip(bytes.iter_mut()) {
            // SAFETY: `check` keeps the range inside sectors 2-4, mapped readable flash.
            *b = unsafe { core::ptr::read_volatile(i as *const u8) };
        }
        Ok(())
    }

    fn capacity(&self) -> usize {
        SIG_LEN as usize
    }
}

impl NorFlash for SigFlash {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = 0x4000;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        let len = to.checked_sub(from).ok_or(OdoFlashError::OutOfBounds)?;
        Self::check(from, len as usize)?;
        let Some(&(_, _, n)) = SIG_SECTORS.iter().find(|s| s.0 == from && s.1 == len) else {
            return Err(OdoFlashError::NotAligned);
        };
        OdometerFlash::erase_sector(n)
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let at = Self::check(offset, bytes.len())?;
        if at % 4 != 0 || bytes.len() % 4 != 0 {
            return Err(OdoFlashError::NotAligned);
        }
        OdometerFlash::begin()?;
        // SAFETY: FLASH_CR (fixed MMIO): PG with ×32 parallelism.
        unsafe { core::ptr::write_volatile(FLASH_CR, CR_PSIZE_X32 | CR_PG) };
        let mut result = Ok(());
        for (addr, w) in (at..).step_by(4).zip(bytes.chunks_exact(4)) {
            let mut le = [0u8; 4];
            le.copy_from_slice(w);
            // SAFETY: a word-aligned address inside sectors 2-4 (checked above), PG
            // set: this store programs the word (RM0090 §3.6.4).
            unsafe { core::ptr::write_volatile(addr as *mut u32, u32::from_le_bytes(le)) };
            result = OdometerFlash::status(OdometerFlash::wait_idle());
            if result.is_err() {
                break;
            }
        }
        OdometerFlash::end();
        result
    }
}
