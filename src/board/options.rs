//! The option bytes: the brown-out reset level.
//!
//! A board whose supply sags must reset cleanly rather than run on at a voltage where
//! flash writes and the clock are no longer guaranteed. BOR level 3 (2.70 V, the highest)
//! keeps the STM32F407 in reset below the voltage its flash needs at ×32 parallelism
//! (RM0090 §3.7.1, DS8626 Table 21). The factory default is BOR off. At boot the
//! firmware checks the level and programs it if needed, before it starts the watchdog
//! (programming the option bytes takes as long as a small sector erase).

const FLASH_SR: *mut u32 = 0x4002_3C0C as *mut u32;
const FLASH_OPTKEYR: *mut u32 = 0x4002_3C08 as *mut u32;
const FLASH_OPTCR: *mut u32 = 0x4002_3C14 as *mut u32;
const OPTKEY1: u32 = 0x0819_2A3B;
const OPTKEY2: u32 = 0x4C5D_6E7F;
const OPTLOCK: u32 = 1 << 0;
const OPTSTRT: u32 = 1 << 1;
const BOR_LEV: u32 = 0b11 << 2;
const BSY: u32 = 1 << 16;

/// The BOR level: 3 (2.70 V), 2, 1, or 0 (off).
pub fn bor_level() -> u8 {
    // SAFETY: read of FLASH_OPTCR (fixed MMIO).
    let optcr = unsafe { core::ptr::read_volatile(FLASH_OPTCR) };
    3 - ((optcr & BOR_LEV) >> 2) as u8
}

/// What [`ensure_bor_level_3`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq, defmt::Format)]
pub enum Bor {
    /// It was level 3 already.
    WasSet,
    /// It was `from`; it is level 3 now.
    Programmed {
        /// The level found.
        from: u8,
    },
    /// Programming did not take (the option bytes are locked or write-protected).
    Failed {
        /// The level found.
        from: u8,
    },
}

fn wait_idle() {
    // SAFETY: read of FLASH_SR (fixed MMIO).
    while unsafe { core::ptr::read_volatile(FLASH_SR) } & BSY != 0 {}
}

/// Make the BOR level 3.
pub fn ensure_bor_level_3() -> Bor {
    let from = bor_level();
    if from == 3 {
        return Bor::WasSet;
    }
    wait_idle();
    // SAFETY: the option-byte unlock sequence and program of FLASH_OPTCR (RM0090
    // §3.6.5); nothing else touches the flash interface during init.
    unsafe {
        core::ptr::write_volatile(FLASH_OPTKEYR, OPTKEY1);
        core::ptr::write_volatile(FLASH_OPTKEYR, OPTKEY2);
        let optcr = core::ptr::read_volatile(FLASH_OPTCR);
        if optcr & OPTLOCK == 0 {
            core::ptr::write_volatile(FLASH_OPTCR, optcr & !BOR_LEV & !OPTSTRT);
            core::ptr::write_volatile(FLASH_OPTCR, (optcr & !BOR_LEV) | OPTSTRT);
            wait_idle();
            let now = core::ptr::read_volatile(FLASH_OPTCR);
            core::ptr::write_volatile(FLASH_OPTCR, now | OPTLOCK);
        }
    }
    if bor_level() == 3 {
        Bor::Programmed { from }
    } else {
        Bor::Failed { from }
    }
}
