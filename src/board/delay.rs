//! A busy-wait delay counted in core cycles (DWT CYCCNT), for the HX711's clock phases.
//!
//! Why not the HAL's timer delay: stm32f4xx-hal 0.23.0 (the newest release)
//! implements `DelayNs::delay_ns` for its timer delays as
//! `self.delay(ns.micros_at_least())` (`src/timer/hal_1.rs`): it waits **microseconds**.
//! A 1 µs PD_SCK high phase became 1 ms, and over 60 µs the HX711 powers down: no
//! sample was ever read. The virtual board showed it (`vboard/tests/defects.rs`); the
//! host rig could not, its delay being the simulated clock.
//!
//! CYCCNT counts core cycles whenever the core runs (it is enabled at boot in
//! `main`); the wait works with interrupts masked, which the HX711 driver needs (it
//! masks them for each clock-high phase). It is not a clock for a core that sleeps:
//! CYCCNT stops in `wfi`.

use embedded_hal::delay::DelayNs;

use super::SYSCLK_HZ;

/// Busy-waits at least the requested time, to one core cycle (6 ns at 168 MHz).
pub struct CycleDelay;

/// Core cycles per microsecond.
const CYCLES_PER_US: u32 = SYSCLK_HZ / 1_000_000;

impl DelayNs for CycleDelay {
    #[inline]
    fn delay_ns(&mut self, ns: u32) {
        // The short waits of the HX711's clock phases in 32-bit arithmetic (a division
        // by a constant: no library call in the stop path); long ones in 64 bits.
        let cycles = if ns <= u32::MAX / CYCLES_PER_US {
            u64::from((ns * CYCLES_PER_US).div_ceil(1_000))
        } else {
            (u64::from(ns) * u64::from(CYCLES_PER_US)).div_ceil(1_000)
        };
        // Waits longer than one CYCCNT wrap (25.5 s) are split; none is asked for here.
        let mut left = cycles;
        while left > 0 {
            let chunk = left.min(u64::from(u32::MAX / 2)) as u32;
            let start = cortex_m::peripheral::DWT::cycle_count();
            while cortex_m::peripheral::DWT::cycle_count().wrapping_sub(start) < chunk {}
            left -= u64::from(chunk);
        }
    }
}
