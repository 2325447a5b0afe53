//! The bootloader image (sector 0): safe outputs, swap or revert as the state sector
//! asks, then the application at ACTIVE's first address (`0x0802_0000` in layout C;
//! docs/update.md).
//!
//! 1. `__pre_init`, its first instructions, before any RAM is set up: every motor and
//!    PLC output to its safe level (EN high, STEP low, lock IN1/IN2 low, READY, MATED,
//!    FAULT, MAINTENANCE low), the same stores as the application's `__pre_init`.
//! 2. [`docking_boot::prepare`]: embassy-boot's swap or revert, through [`Flash`], a
//!    register-level driver that refuses anything but STATE, ACTIVE and DFU
//!    (`layout::bootloader_may_write`: never its own sector, the project's sectors 2-4
//!    or the odometer's).
//! 3. ACTIVE's vector table checked ([`docking_boot::bootable`]); VTOR set; the
//!    application's stack pointer loaded and its reset vector taken.
//!
//! RAM: the CCM RAM only (`memory.x`): the application's SRAM (crash record, odometer
//! journal, stack paint) is never read nor written. No interrupt is enabled. The
//! independent watchdog is started first (8.2 s) and left running for the application:
//! a trial image that hangs before it sets its own is reset, and so rolled back. A flash
//! error waits 1 s and resets (the swap resumes from its progress words); a blank or
//! foreign ACTIVE is never jumped to: the core sleeps with the outputs safe.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {}

#[cfg(target_os = "none")]
mod board {
    use core::cell::RefCell;

    use cortex_m_rt::entry;
    use docking_boot::layout::{bootloader_may_write, sector_of, ACTIVE_BASE};
    use docking_boot::part::{FlashError, Sectors};
    use docking_boot::{bootable, prepare, Buf, BUF_LEN};

    // Registers (RM0090 §3.9, §10.4, §19.4; ARMv7-M SCB).
    const FLASH_KEYR: *mut u32 = 0x4002_3C04 as *mut u32;
    const FLASH_SR: *mut u32 = 0x4002_3C0C as *mut u32;
    const FLASH_CR: *mut u32 = 0x4002_3C10 as *mut u32;
    const IWDG_KR: *mut u32 = 0x4000_3000 as *mut u32;
    const IWDG_PR: *mut u32 = 0x4000_3004 as *mut u32;
    const IWDG_RLR: *mut u32 = 0x4000_3008 as *mut u32;
    const IWDG_SR: *mut u32 = 0x4000_300C as *mut u32;
    const SCB_VTOR: *mut u32 = 0xE000_ED08 as *mut u32;

    const KEY1: u32 = 0x4567_0123;
    const KEY2: u32 = 0xCDEF_89AB;
    const SR_BSY: u32 = 1 << 16;
    /// OPERR, WRPERR, PGAERR, PGPERR, PGSERR.
    const SR_ERRORS: u32 = 0xF2;
    /// EOP and the error flags, cleared by writing 1.
    const SR_CLEAR: u32 = SR_ERRORS | 1;
    const CR_PG: u32 = 1 << 0;
    const CR_SER: u32 = 1 << 1;
    const CR_PSIZE_X32: u32 = 0b10 << 8;
    const CR_STRT: u32 = 1 << 16;
    const CR_LOCK: u32 = 1 << 31;
    /// Busy-wait polls before an operation is given up: far beyond a 128 KiB erase's 2 s
    /// at ×32 (the core stalls on the flash meanwhile, so few polls run).
    const BUSY_POLLS: u32 = 50_000_000;
    /// The core's clock out of reset (HSI): 1 s of `delay`.
    const ONE_SECOND: u32 = 16_000_000;

    // The outputs safe as the first instructions, before any RAM is set up: the same
    // stores as the application's (update-layout's `safe`).
    docking_boot::layout_crate::pre_init_safe_outputs!("    bx lr";);

    fn rd(r: *mut u32) -> u32 {
        // SAFETY: a fixed MMIO register of the flash interface.
        unsafe { core::ptr::read_volatile(r) }
    }

    fn wr(r: *mut u32, v: u32) {
        // SAFETY: a fixed MMIO register of the flash interface, the watchdog or the SCB.
        unsafe { core::ptr::write_volatile(r, v) }
    }

    /// Reload the independent watchdog (started by [`start_watchdog`]) between flash
    /// operations.
    fn feed() {
        wr(IWDG_KR, 0xAAAA);
    }

    /// Start the independent watchdog at LSI / 64, reload 4095: 8.2 s at the nominal
    /// 32 kHz, 5.6 s on the fastest LSI (47 kHz), longer than any one flash operation of
    /// the swap (a 128 KiB erase: 2 s at most; fed between operations). It runs on into
    /// the application, whose init sets its own period: a trial image that hangs before
    /// that, or never feeds it, is reset, and the reset rolls it back.
    fn start_watchdog() {
        wr(IWDG_KR, 0x5555);
        wr(IWDG_PR, 4); // /64
        wr(IWDG_RLR, 0xFFF);
        // PVU/RVU: the new values reach the LSI domain within a few LSI cycles.
        let mut n = 0u32;
        while rd(IWDG_SR) & 3 != 0 && n < 100_000 {
            n += 1;
        }
        wr(IWDG_KR, 0xCCCC);
        feed();
    }

    /// The flash, STATE, ACTIVE and DFU writable (register level, PSIZE ×32: the board
    /// runs at 3.3 V).
    pub struct Flash;

    impl Flash {
        fn unlock(&mut self) -> Result<(), FlashError> {
            if rd(FLASH_CR) & CR_LOCK != 0 {
                wr(FLASH_KEYR, KEY1);
                wr(FLASH_KEYR, KEY2);
            }
            if rd(FLASH_CR) & CR_LOCK != 0 {
                return Err(FlashError::Locked);
            }
            Ok(())
        }

        fn wait(&mut self) -> Result<(), FlashError> {
            let mut n = 0u32;
            while rd(FLASH_SR) & SR_BSY != 0 {
                n += 1;
                if n >= BUSY_POLLS {
                    return Err(FlashError::Timeout);
                }
            }
            let sr = rd(FLASH_SR);
            if sr & SR_ERRORS != 0 {
                return Err(FlashError::Status(sr));
            }
            Ok(())
        }

        fn begin(&mut self) -> Result<(), FlashError> {
            self.wait().or_else(|e| match e {
                FlashError::Status(_) => Ok(()),
                e => Err(e),
            })?;
            wr(FLASH_SR, SR_CLEAR);
            self.unlock()
        }

        /// Lock the controller again (before the application runs).
        pub fn lock(&mut self) {
            wr(FLASH_CR, rd(FLASH_CR) | CR_LOCK);
        }
    }

    fn in_writable(addr: u32, len: usize) -> bool {
        u32::try_from(len).is_ok_and(|len| bootloader_may_write(addr, len))
    }

    impl Sectors for Flash {
        fn read(&mut self, addr: u32, buf: &mut [u8]) -> Result<(), FlashError> {
            let end = addr as u64 + buf.len() as u64;
            if addr < 0x0800_0000 || end > 0x0810_0000 {
                return Err(FlashError::OutOfBounds);
            }
            for (i, b) in buf.iter_mut().enumerate() {
                // SAFETY: inside the 1 MiB of flash, checked above.
                *b = unsafe { core::ptr::read_volatile((addr as usize + i) as *const u8) };
            }
            Ok(())
        }

        fn erase_sector(&mut self, base: u32) -> Result<(), FlashError> {
            let Some((n, start, len)) = sector_of(base) else {
                return Err(FlashError::OutOfBounds);
            };
            if start != base || !in_writable(base, len as usize) {
                return Err(FlashError::OutOfBounds);
            }
            feed();
            self.begin()?;
            wr(FLASH_CR, CR_PSIZE_X32 | CR_SER | (n << 3));
            wr(FLASH_CR, CR_PSIZE_X32 | CR_SER | (n << 3) | CR_STRT);
            let r = self.wait();
            wr(FLASH_CR, 0);
            feed();
            r
        }

        fn program(&mut self, addr: u32, data: &[u8]) -> Result<(), FlashError> {
            if addr % 4 != 0 || data.len() % 4 != 0 {
                return Err(FlashError::NotAligned);
            }
            if !in_writable(addr, data.len()) {
                return Err(FlashError::OutOfBounds);
            }
            feed();
            self.begin()?;
            wr(FLASH_CR, CR_PSIZE_X32 | CR_PG);
            let mut r = Ok(());
            for (i, w) in data.chunks_exact(4).enumerate() {
                let [a, b, c, d] = [w[0], w[1], w[2], w[3]];
                let v = u32::from_le_bytes([a, b, c, d]);
                let p = (addr as usize + 4 * i) as *mut u32;
                // SAFETY: a word inside STATE, ACTIVE or DFU (checked above), PG set: a program.
                unsafe { core::ptr::write_volatile(p, v) };
                cortex_m::asm::dsb();
                r = self.wait();
                // SAFETY: the word just programmed.
                if r.is_ok() && unsafe { core::ptr::read_volatile(p) } != v {
                    r = Err(FlashError::Verify);
                }
                if r.is_err() {
                    break;
                }
            }
            wr(FLASH_CR, 0);
            r
        }
    }

    /// Wait about 1 s, then reset the MCU (a swap resumes from its progress words).
    fn retry_later() -> ! {
        cortex_m::asm::delay(ONE_SECOND);
        cortex_m::peripheral::SCB::sys_reset()
    }

    static mut BUF: Buf = Buf([0; BUF_LEN]);

    #[entry]
    fn main() -> ! {
        start_watchdog();
        let flash = RefCell::new(Flash);
        // SAFETY: the only reference to BUF, taken once (entry runs once).
        let buf = unsafe { &mut *core::ptr::addr_of_mut!(BUF) };
        if prepare(&flash, buf).is_err() {
            flash.borrow_mut().lock();
            retry_later();
        }
        flash.borrow_mut().lock();
        match bootable(&flash) {
            Some(_) => {
                wr(SCB_VTOR, ACTIVE_BASE);
                cortex_m::asm::dsb();
                cortex_m::asm::isb();
                // SAFETY: ACTIVE's vector table was checked (SP in SRAM, reset vector in
                // ACTIVE, Thumb); nothing of the bootloader is needed after the jump.
                unsafe { cortex_m::asm::bootload(ACTIVE_BASE as *const u32) }
            }
            None => loop {
                // No interrupt is enabled: sleeps with the outputs safe until a reset.
                cortex_m::asm::wfi();
            },
        }
    }

    #[panic_handler]
    fn panic(_: &core::panic::PanicInfo) -> ! {
        // The outputs were made safe before anything ran and nothing here drives them.
        retry_later()
    }
}
