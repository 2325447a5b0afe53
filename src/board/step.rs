//! Step pulses from SysTick (a phase accumulator, DDS), and the safety path's stop.
//!
//! # Pulses a DM542-class driver accepts
//!
//! SysTick ticks at 20 kHz while the axis moves (its interrupt is off at rest, so the
//! core can sleep). A pulse is one tick high (50 µs ≥ 2.5 µs) and at least one tick low
//! (rates are capped at half the tick rate). DIR and EN must be settled 5 µs before a
//! STEP rising edge: the tick compares them with the last tick and holds a pulse due in a
//! tick where either changed, so the first edge after a change comes ≥ 50 µs later. Each
//! pulse is counted when it is emitted, and the propulsion driver counts it with the
//! direction it has (it reverses only through a period at rate 0, after taking the count).
//!
//! # The stop
//!
//! [`BoardStop::stop_now`] is what the safety path calls from the HX711's interrupt:
//! one store to GPIOE's set/reset register (EN high, no read-modify-write), the DDS
//! increment to zero, the latch set. [`GatedEn`](docking_logic::safety::GatedEn)
//! keeps EN from going low again until the controller re-arms the latch, and
//! [`GatedPulses`](docking_logic::safety::GatedPulses) a rate from being set; the tick
//! emits no pulse while the latch is set (a STEP edge with EN high is never made).

use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use docking_logic::hal::{StepPulses, StopLatch};
use stm32f4xx_hal::gpio::{Output, PE9};

/// Step tick rate, Hz.
pub const STEP_TICK_HZ: u32 = 20_000;

/// DDS increment per tick (rate / tick · 2^32), 0 = no pulses.
static INCREMENT: AtomicU32 = AtomicU32::new(0);
/// Pulses emitted and not yet taken by the propulsion driver.
static PULSES: AtomicU32 = AtomicU32::new(0);
/// Stops the safety path made, and its latch.
static STOPS: AtomicU32 = AtomicU32::new(0);
static LATCHED: AtomicBool = AtomicBool::new(false);

const GPIOE_ODR: *const u32 = 0x4002_1014 as *const u32;
const GPIOE_BSRR: *mut u32 = 0x4002_1018 as *mut u32;
/// DIR (PE10) and EN (PE11) in GPIOE's ODR.
const DIR_EN: u32 = (1 << 10) | (1 << 11);
const SYST_CSR: *mut u32 = 0xE000_E010 as *mut u32;
const SYST_CVR: *mut u32 = 0xE000_E018 as *mut u32;
const TICKINT: u32 = 1 << 1;

/// The generator's state, owned by the SysTick task.
pub struct StepGen {
    pin: PE9<Output>,
    phase: u32,
    pin_high: bool,
    last_dir_en: u32,
}

impl StepGen {
    /// The generator on STEP (PE9), idle.
    pub fn new(pin: PE9<Output>) -> Self {
        Self {
            pin,
            phase: 0,
            pin_high: false,
            last_dir_en: 0,
        }
    }

    /// One tick (SysTick interrupt).
    pub fn tick(&mut self) {
        if self.pin_high {
            self.pin.set_low();
            self.pin_high = false;
        }
        // SAFETY: read of GPIOE_ODR, a fixed MMIO address.
        let dir_en = unsafe { core::ptr::read_volatile(GPIOE_ODR) } & DIR_EN;
        let changed = dir_en != self.last_dir_en;
        self.last_dir_en = dir_en;
        // No pulse while a stop is latched, whatever rate was set (a rate written after
        // a stop the control step had not seen yet: issue 32, item 6; the driver's
        // `GatedPulses` refuses those too; docs/board.md, "What holds between the
        // steps", rule 7).
        let inc = if LATCHED.load(Ordering::Relaxed) {
            0
        } else {
            INCREMENT.load(Ordering::Relaxed)
        };
        if inc == 0 {
            // At rest: no more ticks once the pin is low (the core may sleep).
            self.phase = 0;
            // SAFETY: SysTick CSR; only this task clears TICKINT, the propulsion sets it
            // inside a critical section.
            critical_section::with(|_| unsafe {
                let csr = core::ptr::read_volatile(SYST_CSR);
                core::ptr::write_volatile(SYST_CSR, csr & !TICKINT);
            });
            return;
        }
        let (next, overflow) = self.phase.overflowing_add(inc);
        if overflow && changed {
            return; // DIR or EN just changed: this pulse waits a tick (setup time)
        }
        self.phase = next;
        if overflow {
            self.pin.set_high();
            self.pin_high = true;
            PULSES.fetch_add(1, Ordering::Relaxed);
        }
    }
}

/// The propulsion driver's handle on the generator.
pub struct BoardStepPulses;

impl StepPulses for BoardStepPulses {
    fn set_rate_hz(&mut self, rate_hz: u32) {
        // increment = rate / tick · 2^32; rates are capped at half the tick rate.
        let rate = u64::from(rate_hz.min(STEP_TICK_HZ / 2));
        let inc = ((rate << 32) / u64::from(STEP_TICK_HZ)) as u32;
        let was = INCREMENT.swap(inc, Ordering::Relaxed);
        if inc != 0 && was == 0 {
            // From rest: a full tick before the first one (DIR/EN settle meanwhile).
            // SAFETY: SysTick registers; TICKINT is set here inside a critical section
            // (the tick task clears it, never concurrently).
            critical_section::with(|_| unsafe {
                core::ptr::write_volatile(SYST_CVR, 0);
                let csr = core::ptr::read_volatile(SYST_CSR);
                core::ptr::write_volatile(SYST_CSR, csr | TICKINT);
            });
        }
    }

    fn take_pulses(&mut self) -> u32 {
        PULSES.swap(0, Ordering::Relaxed)
    }
}

/// The safety path's stop and its latch (statics: any number of handles).
#[derive(Clone, Copy, Debug, Default)]
pub struct BoardStop;

impl StopLatch for BoardStop {
    fn stop_now(&mut self) -> u32 {
        // SAFETY: one store to GPIOE_BSRR sets PE11 (EN, active low: driver off); a
        // set/reset register needs no read-modify-write, so nothing can interleave.
        unsafe { core::ptr::write_volatile(GPIOE_BSRR, 1 << 11) };
        INCREMENT.store(0, Ordering::Relaxed);
        LATCHED.store(true, Ordering::Relaxed);
        STOPS.fetch_add(1, Ordering::Relaxed).wrapping_add(1)
    }

    fn stops(&self) -> u32 {
        STOPS.load(Ordering::Relaxed)
    }

    fn latched(&self) -> bool {
        LATCHED.load(Ordering::Relaxed)
    }

    /// Lock-free (no critical section: a stop from any priority, the E-STOP above
    /// every masked section included, lands at once): clear the latch if no stop came
    /// after `seen`, then look again — a stop that landed between the look and the
    /// clear (it set the latch and bumped the count) is latched again here.
    fn rearm(&mut self, seen: u32) -> bool {
        if STOPS.load(Ordering::Acquire) > seen {
            return false;
        }
        LATCHED.store(false, Ordering::Release);
        if STOPS.load(Ordering::Acquire) > seen {
            LATCHED.store(true, Ordering::Release);
            return false;
        }
        true
    }
}
