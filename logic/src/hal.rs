//! Traits for what embedded-hal 1.0 does not cover.
//!
//! embedded-hal 1.0 has no timer, watchdog or serial traits. The control logic needs
//! exactly four such things and no more; the board implements them in `src/board.rs`,
//! the simulator in `hil-sim`.

/// A monotonic clock that never goes backwards, in microseconds since boot.
pub trait Monotonic {
    /// Current time, µs since boot. Must be non-decreasing.
    fn now_us(&mut self) -> u64;
}

/// The independent watchdog. Feed it only from a healthy control loop.
pub trait Watchdog {
    /// Reload the watchdog counter.
    fn feed(&mut self);
}

/// Step-pulse generator of a step/dir driver (a timer on the board).
///
/// The direction and enable lines are ordinary `OutputPin`s owned by the driver in
/// [`crate`]; this trait only produces pulses at a rate and counts them.
pub trait StepPulses {
    /// Emit step pulses at `rate_hz` (0 stops the pulse train).
    fn set_rate_hz(&mut self, rate_hz: u32);
    /// Number of pulses emitted since the previous call.
    fn take_pulses(&mut self) -> u32;
}

/// A byte stream to a technician's serial terminal (a USART on the board).
pub trait ConsoleIo {
    /// Next received byte, `WouldBlock` when none is waiting. Receive errors
    /// (framing, overrun, noise) are reported as `Err(Other(()))` and the byte dropped.
    fn read_byte(&mut self) -> nb::Result<u8, ()>;
    /// Queue bytes for transmission; returns how many were taken (never blocks: a
    /// full transmit buffer drops the rest rather than stalling the control loop).
    fn write(&mut self, bytes: &[u8]) -> usize;
}

/// A load-cell ADC that delivers raw conversion codes (the HX711 driver on the board).
pub trait LoadCellAdc {
    /// The next conversion code, `WouldBlock` while none is ready; `Err(Other(()))` if
    /// the device could not be read.
    fn read_code(&mut self) -> nb::Result<i32, ()>;
}

/// The MCU's option bytes: the brown-out reset level (the board's; the simulator's).
///
/// Programming them is an explicit maintenance step at rest (console `bor set`), never
/// something the firmware does on its own at boot: a power cut while option bytes are
/// programmed can leave read protection or write protection set.
pub trait OptionBytes {
    /// The brown-out reset level now: 3 (2.70 V), 2 (2.40 V), 1 (2.10 V) or 0 (off).
    fn bor_level(&self) -> u8;
    /// Program BOR level 3. `Err(sr)`: the flash interface's status register (its
    /// error bits), or the level read back was not 3.
    fn program_bor_level_3(&mut self) -> Result<(), u32>;
}

/// The safety path's hold on the propulsion: an immediate stop that latches, so the
/// driver stays off until the controller has seen every stop.
///
/// The board implements it on the EN pin's set/reset register and the step generator
/// (usable from the highest-priority interrupt); the simulator on the simulated pins.
/// Stops are numbered so that the controller re-arms only after it has processed the
/// last one: a stop the safety path makes while the controller is busy is never
/// cleared by it unseen.
pub trait StopLatch {
    /// Disable the propulsion driver (EN high) and halt its step pulses, now; latch.
    /// Returns this stop's number (1, 2, … since boot).
    fn stop_now(&mut self) -> u32;
    /// Stops so far.
    fn stops(&self) -> u32;
    /// Whether the latch is set (the driver may not be enabled).
    fn latched(&self) -> bool;
    /// Clear the latch unless a stop came after stop number `seen`; returns whether it
    /// is clear now.
    fn rearm(&mut self, seen: u32) -> bool;
}

/// Test doubles shared by the library's unit tests.
#[cfg(test)]
pub(crate) mod test_pin {
    use core::cell::Cell;

    /// An output pin whose level is a `Cell` the test reads — and may change behind the
    /// driver's back, as the E-STOP's stores do.
    pub(crate) struct CellPin<'a>(pub(crate) &'a Cell<bool>);

    impl embedded_hal::digital::ErrorType for CellPin<'_> {
        type Error = core::convert::Infallible;
    }

    impl embedded_hal::digital::OutputPin for CellPin<'_> {
        fn set_high(&mut self) -> Result<(), Self::Error> {
            self.0.set(true);
            Ok(())
        }
        fn set_low(&mut self) -> Result<(), Self::Error> {
            self.0.set(false);
            Ok(())
        }
    }
}
