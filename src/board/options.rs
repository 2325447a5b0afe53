//! The option bytes: the brown-out reset level.
//!
//! A board whose supply sags must reset cleanly rather than run on at a voltage where
//! flash writes and the clock are no longer guaranteed. BOR level 3 (2.70 V, the highest)
//! keeps the STM32F407 in reset below the voltage its flash needs at ×32 parallelism
//! (RM0090 §3.7.1, DS8626 Table 21). The factory default is BOR off.
//!
//! # An explicit step, never at boot
//!
//! The firmware reads the level at every boot and reports it (the boot log line,
//! console `bor`, `status`); it never programs it on its own. Programming at boot would
//! run with BOR still off and the supply possibly still ramping, and a cut during
//! option-byte programming can leave read protection at level 1 or sectors
//! write-protected (the recovery is a mass erase: the odometer lost). So it is a
//! **maintenance command at rest** (`bor set`, in maintenance mode, audited): a person
//! at the machine, on a steady supply, with nothing moving. A console command rather than
//! an end-of-line probe step because the technician's console is what every machine in
//! the field has, and the step can be checked and repeated there (`bor`).
//!
//! Programming: unlock OPTCR (OPTKEYR), write the level, set OPTSTRT, wait for BSY to
//! clear from SRAM (the flash interface is busy meanwhile) while feeding the watchdog,
//! then judge by FLASH_SR's error bits **and** the level read back; OPTCR is locked
//! again once the interface is idle (a timed-out wait leaves that to the next reset).

use super::flash::{FLASH_SR, IWDG_KR, SR_BSY as BSY, SR_ERRORS};

const FLASH_OPTKEYR: *mut u32 = 0x4002_3C08 as *mut u32;
const FLASH_OPTCR: *mut u32 = 0x4002_3C14 as *mut u32;
const OPTKEY1: u32 = 0x0819_2A3B;
const OPTKEY2: u32 = 0x4C5D_6E7F;
const OPTLOCK: u32 = 1 << 0;
const OPTSTRT: u32 = 1 << 1;
const BOR_LEV: u32 = 0b11 << 2;
/// Longest wait for the option bytes: as long as a sector erase may take, plus half.
const PROGRAM_TIMEOUT_CYCLES: u32 = super::flash::ERASE_TIMEOUT_CYCLES;

/// The BOR level: 3 (2.70 V), 2, 1, or 0 (off).
pub fn bor_level() -> u8 {
    // SAFETY: read of FLASH_OPTCR (fixed MMIO).
    let optcr = unsafe { core::ptr::read_volatile(FLASH_OPTCR) };
    3 - ((optcr & BOR_LEV) >> 2) as u8
}

/// Write `optcr` with OPTSTRT and wait for the end, from SRAM, feeding the watchdog for
/// at most `max_cycles`. Returns FLASH_SR at the end (BSY still set: timed out). Touches
/// no flash (in `.data`, everything inlined); the caller masks interrupts.
#[inline(never)]
#[link_section = ".data.option_bytes_from_ram"]
fn program_from_ram(optcr: u32, max_cycles: u32) -> u32 {
    // SAFETY: fixed MMIO addresses (RM0090 §3.6.5, §3.9); the caller owns the flash
    // interface (at rest) and has masked interrupts.
    unsafe {
        core::ptr::write_volatile(FLASH_OPTCR, optcr | OPTSTRT);
        super::flash::wait_idle_feeding!(max_cycles)
    }
}

/// The board's option bytes.
#[derive(Debug, Default)]
pub struct BoardOptions;

impl docking_logic::hal::OptionBytes for BoardOptions {
    fn bor_level(&self) -> u8 {
        bor_level()
    }

    fn program_bor_level_3(&mut self) -> Result<(), u32> {
        let sr = cortex_m::interrupt::free(|_| {
            // SAFETY: the option-byte unlock sequence, FLASH_SR's write-1-to-clear
            // error flags and OPTCR (RM0090 §3.6.5); the controller calls this only at
            // rest, when nothing else uses the flash interface.
            unsafe {
                while core::ptr::read_volatile(FLASH_SR) & BSY != 0 {
                    core::ptr::write_volatile(IWDG_KR, 0xAAAA);
                }
                core::ptr::write_volatile(FLASH_SR, SR_ERRORS);
                core::ptr::write_volatile(FLASH_OPTKEYR, OPTKEY1);
                core::ptr::write_volatile(FLASH_OPTKEYR, OPTKEY2);
                let optcr = core::ptr::read_volatile(FLASH_OPTCR);
                if optcr & OPTLOCK != 0 {
                    return u32::MAX; // the keys did not unlock it
                }
                let sr = program_from_ram(optcr & !BOR_LEV & !OPTSTRT, PROGRAM_TIMEOUT_CYCLES);
                if sr & BSY == 0 {
                    let now = core::ptr::read_volatile(FLASH_OPTCR);
                    core::ptr::write_volatile(FLASH_OPTCR, now | OPTLOCK);
                }
                sr
            }
        });
        if sr & (SR_ERRORS | BSY) != 0 || bor_level() != 3 {
            Err(sr)
        } else {
            Ok(())
        }
    }
}
