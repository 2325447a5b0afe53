//! The board's monotonic clock: TIM5, a 32-bit timer counting microseconds, extended to
//! 64 bits.
//!
//! Why not the DWT cycle counter: it does not count while the core sleeps (`wfi`), and
//! the core sleeps whenever it has nothing to do. TIM5 runs on its bus clock whatever
//! the core does. Its 32 bits wrap every 71.6 minutes; [`now_us`] is called at least
//! every sample period (the control task), so every wrap is seen.

use core::sync::atomic::{AtomicU32, Ordering};

use stm32f4xx_hal::pac;
use stm32f4xx_hal::rcc::{Enable, Rcc, Reset};

/// TIM5 counter register (µs; the flash's SRAM wait reads it directly: `flash.rs`).
pub(crate) const TIM5_CNT: *const u32 = 0x4000_0C24 as *const u32;

/// The last counter value read, and the wraps seen.
static LAST: AtomicU32 = AtomicU32::new(0);
static WRAPS: AtomicU32 = AtomicU32::new(0);

/// Start TIM5 free-running at 1 MHz (timer clock `tim_hz`). It takes the peripheral
/// so that nothing else configures it; from then on only its counter is read, through
/// `TIM5_CNT`, from any context.
pub fn start(tim5: pac::TIM5, rcc: &mut Rcc, tim_hz: u32) {
    pac::TIM5::enable(rcc);
    pac::TIM5::reset(rcc);
    tim5.psc()
        .write(|w| w.psc().set((tim_hz / 1_000_000).saturating_sub(1) as u16));
    tim5.arr().write(|w| w.arr().set(u32::MAX));
    tim5.egr().write(|w| w.ug().set_bit());
    tim5.cr1().write(|w| w.cen().set_bit());
}

/// The low 32 bits of [`now_us`] (TIM5's count itself): one register read, no critical
/// section, for the E-STOP's interrupt.
pub fn now_us_low() -> u32 {
    // SAFETY: read of TIM5_CNT, a fixed MMIO address of this chip.
    unsafe { core::ptr::read_volatile(TIM5_CNT) }
}

/// Microseconds since boot.
pub fn now_us() -> u64 {
    critical_section::with(|_| {
        // SAFETY: read of TIM5_CNT, a fixed MMIO address of this chip.
        let now = unsafe { core::ptr::read_volatile(TIM5_CNT) };
        if now < LAST.load(Ordering::Relaxed) {
            WRAPS.fetch_add(1, Ordering::Relaxed);
        }
        LAST.store(now, Ordering::Relaxed);
        (u64::from(WRAPS.load(Ordering::Relaxed)) << 32) | u64::from(now)
    })
}
