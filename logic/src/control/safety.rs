//! The safety path: load-cell sample → sensor health → overload guard → stop, in one
//! short call, apart from the rest of the control step.
//!
//! # Why apart
//!
//! The stop must not wait for anything else the controller does. The board runs
//! [`SafetyKernel::on_ready`] in its highest-priority interrupt, the HX711's
//! data-ready edge: nothing the console, the flash or the log does can delay it (see
//! `src/board.rs`). The host rig calls it just before the control step, in the same
//! virtual instant. Both run this code.
//!
//! # What it guarantees
//!
//! * A sample over the overload limit of its depth, a pull beyond the tension limit, or
//!   a sensor fault (rail, stuck converter, no sample for three periods, a pin error)
//!   **stops the propulsion within the call** that sees it ([`StopLatch::stop_now`]:
//!   driver off, pulses halted) and latches the stop. The verdicts are the guard's
//!   ([`crate::guard`]): an isolated implausible spike is held one sample, never more.
//! * Every sample and fault is handed to the controller as a [`KernelEvent`], in order,
//!   with the number of the stop it caused; the controller re-arms the latch only for
//!   stops it has seen ([`StopLatch::rearm`]).
//! * It knows nothing of the sequencer: the controller tells it, after every control
//!   step, which limit applies ([`KernelConfig`]: the calibration in force and the
//!   depth in the cone, or the hard limit only). The depth it uses is the controller's
//!   latest: at most one sample period old (15 µm at 1.2 mm/s and 80 SPS, 120 µm at
//!   10 SPS), well inside the envelope's ±0.5 mm window.
//! * No allocation, no panic, no float; bounded time (one HX711 readout plus integer
//!   arithmetic).

use core::sync::atomic::{AtomicU32, Ordering};

use embedded_hal::digital::OutputPin;

use crate::guard::{GuardConfig, OverloadGuard, SensorFault, SensorMonitor, Verdict};
use crate::hal::{LoadCellAdc, StepPulses, StopLatch};
use crate::hx711::{Calibration, CODE_MAX, CODE_MIN};

/// Which limit applies to the next samples.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum GuardMode {
    /// Outside the cone: the hard limits (compression and tension).
    Free,
    /// In the cone at this insertion depth (µm): the per-depth envelope.
    Cone {
        /// Insertion depth, µm.
        depth_um: i32,
    },
    /// Retreating from an overload: the load is high and should fall as the panel
    /// moves away. A sample is judged against the hard limit or `ceiling_mn`, whichever
    /// is higher: a load still over the hard limit but no higher than at the trip lets
    /// the retreat finish; only a load that keeps rising while retreating (a jam on the
    /// way out) trips it, and then the axis is left off.
    BackOff {
        /// The force at the trip plus [`BACKOFF_RISE_MN`], mN.
        ceiling_mn: i32,
    },
}

/// How far the load may rise above the force at the trip while the panel backs off
/// before the retreat is cut as a jam on the way out, mN (30 sigma of the cell's
/// 0.3 N noise; a retreat relieves the contact, so its load falls by far more).
pub const BACKOFF_RISE_MN: i32 = 10_000;

/// What the controller tells the kernel after each control step.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct KernelConfig {
    /// Calibration in force (the offset re-tared before each cycle).
    pub cal: Calibration,
    /// Limit in force.
    pub mode: GuardMode,
    /// Bumped by the controller when a fault is cleared: the kernel forgets its sample
    /// history and restarts its timeout.
    pub clear: u32,
}

/// A judged sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Sample {
    /// Raw HX711 code.
    pub code: i32,
    /// When it was read, µs since boot.
    pub t_us: u64,
    /// Force, mN (calibration in force).
    pub force_mn: i32,
    /// Limit it was judged against, mN.
    pub limit_mn: i32,
    /// The guard's verdict.
    pub verdict: Verdict,
    /// A sensor fault this sample shows.
    pub sensor: Option<SensorFault>,
    /// The stop it caused (its number), if it stopped the propulsion.
    pub stop: Option<u32>,
}

/// What the kernel hands to the controller.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum KernelEvent {
    /// A sample.
    Sample(Sample),
    /// No sample for three periods: the load cell is silent.
    Silent {
        /// When noticed, µs.
        t_us: u64,
        /// The stop it caused.
        stop: u32,
    },
    /// The load cell could not be read (a pin error).
    Io {
        /// When, µs.
        t_us: u64,
        /// The stop it caused.
        stop: u32,
    },
}

impl KernelEvent {
    /// The stop this event caused, if any.
    pub fn stop(&self) -> Option<u32> {
        match self {
            Self::Sample(s) => s.stop,
            Self::Silent { stop, .. } | Self::Io { stop, .. } => Some(*stop),
        }
    }
}

/// The safety path.
pub struct SafetyKernel<A> {
    adc: A,
    cfg: KernelConfig,
    guard: OverloadGuard,
    sensor: SensorMonitor,
    /// A disconnect has been reported (once until a sample or a clear).
    silent_reported: bool,
}

impl<A: LoadCellAdc> SafetyKernel<A> {
    /// A kernel on `adc` sampling at `rate_sps`, with `cal`, started at `now_us` (the
    /// first sample is allowed the HX711's settling time).
    pub fn new(adc: A, guard: GuardConfig, rate_sps: u32, cal: Calibration, now_us: u64) -> Self {
        Self {
            adc,
            cfg: KernelConfig {
                cal,
                mode: GuardMode::Free,
                clear: 0,
            },
            guard: OverloadGuard::new(guard),
            sensor: SensorMonitor::new(rate_sps, now_us),
            silent_reported: false,
        }
    }

    /// Take the controller's word on the calibration and the limit in force (at
    /// `now_us`: a cleared fault restarts the timeout from there).
    pub fn configure(&mut self, cfg: KernelConfig, now_us: u64) {
        if cfg.clear != self.cfg.clear {
            self.clear(now_us);
        }
        self.cfg = cfg;
    }

    /// The configuration in force.
    pub fn config(&self) -> KernelConfig {
        self.cfg
    }

    /// Forget the sample history and restart the timeout (after a fault is cleared).
    pub fn clear(&mut self, now_us: u64) {
        self.guard.reset();
        self.sensor.reset(now_us);
        self.silent_reported = false;
    }

    /// The sample period, µs.
    pub fn period_us(&self) -> u64 {
        self.sensor.period_us()
    }

    /// The latest code, if the load cell answers with it
    /// ([`SensorMonitor::answered_code`]) and has not gone silent since: the trial
    /// boot's check of the sensor (issue 21).
    pub fn answered_code(&self) -> Option<i32> {
        if self.silent_reported {
            None
        } else {
            self.sensor.answered_code()
        }
    }

    /// When the newest sample was read, µs (`None` before the first, and after a
    /// clear until the next): the docking signature's tap (`Controller::capture`), read
    /// off the sample path from what the sensor monitor keeps anyway.
    pub fn last_sample_us(&self) -> Option<u64> {
        self.sensor.last_sample_us()
    }

    /// Single-sample spikes the guard has rejected.
    pub fn spikes_rejected(&self) -> u32 {
        self.guard.spikes_rejected()
    }

    /// The limit in force in `mode`, mN.
    pub fn limit_mn(&self, mode: GuardMode) -> i32 {
        self.guard.limit_mn(match mode {
            GuardMode::Cone { depth_um } => Some(depth_um),
            GuardMode::Free => None,
            GuardMode::BackOff { ceiling_mn } => {
                return self.guard.limit_mn(None).max(ceiling_mn);
            }
        })
    }

    /// The load cell may have a sample (its data-ready edge, or a poll): read it, judge
    /// it, stop the propulsion if it must. `None`: nothing ready.
    pub fn on_ready<S: StopLatch>(&mut self, now_us: u64, stop: &mut S) -> Option<KernelEvent> {
        let code = match self.adc.read_code() {
            Ok(c) => c,
            Err(nb::Error::WouldBlock) => return None,
            Err(nb::Error::Other(())) => {
                return Some(KernelEvent::Io {
                    t_us: now_us,
                    stop: stop.stop_now(),
                })
            }
        };
        self.silent_reported = false;
        let force_mn = self.cfg.cal.to_force_mn(code);
        let sensor = self.sensor.on_sample(code, now_us, CODE_MIN, CODE_MAX);
        let limit_mn = self.limit_mn(self.cfg.mode);
        let verdict = self.guard.check_against(force_mn, limit_mn);
        let stop = (verdict.stops() || sensor.is_some()).then(|| stop.stop_now());
        Some(KernelEvent::Sample(Sample {
            code,
            t_us: now_us,
            force_mn,
            limit_mn,
            verdict,
            sensor,
            stop,
        }))
    }

    /// Called at least once a sample period: a load cell silent for three periods
    /// stops the propulsion (reported once until it speaks again).
    pub fn check<S: StopLatch>(&mut self, now_us: u64, stop: &mut S) -> Option<KernelEvent> {
        if self.silent_reported || self.sensor.check_timeout(now_us).is_none() {
            return None;
        }
        self.silent_reported = true;
        Some(KernelEvent::Silent {
            t_us: now_us,
            stop: stop.stop_now(),
        })
    }
}

/// What the E-STOP's interrupt has recorded, as the control step reads it
/// ([`EstopEdges::snapshot`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct EstopEvents {
    /// Edges of the input since boot, opening and closing: each one stopped the machine
    /// in the interrupt that counted it (wraps).
    pub edges: u32,
    /// The number of the stop ([`StopLatch::stop_now`]) the latest edge made.
    pub stop: u32,
    /// When the input last opened, and last closed: µs since boot, low 32 bits (a
    /// pulse's length is their wrapping difference).
    pub opened_us: u32,
    /// See `opened_us`.
    pub closed_us: u32,
}

/// The E-STOP input's edges, **events rather than a level**: a pulse or a bounce the
/// control step never samples open is still counted, and every edge it has not
/// consumed latches `emergency_stop`.
///
/// Written only by the E-STOP's interrupt ([`Self::on_edge`], after it has stopped
/// the machine), read by the control step ([`Self::snapshot`]). Lock-free (atomics
/// only, no critical section, no log), so nothing at the E-STOP's priority waits.
#[derive(Debug, Default)]
pub struct EstopEdges {
    edges: AtomicU32,
    stop: AtomicU32,
    opened_us: AtomicU32,
    closed_us: AtomicU32,
}

impl EstopEdges {
    /// No edge yet.
    pub const fn new() -> Self {
        Self {
            edges: AtomicU32::new(0),
            stop: AtomicU32::new(0),
            opened_us: AtomicU32::new(0),
            closed_us: AtomicU32::new(0),
        }
    }

    /// From the E-STOP's interrupt, after [`StopLatch::stop_now`] returned `stop`: the
    /// input read `open` at `now_us` (µs since boot, low 32 bits: durations are wrapping
    /// differences). The stop number is stored before the count.
    pub fn on_edge(&self, stop: u32, open: bool, now_us: u32) {
        if open {
            self.opened_us.store(now_us, Ordering::Relaxed);
        } else {
            self.closed_us.store(now_us, Ordering::Relaxed);
        }
        self.stop.store(stop, Ordering::Release);
        self.edges.fetch_add(1, Ordering::Release);
    }

    /// What has been recorded. The stop number is read before the count: an edge that
    /// lands between the two reads is seen by its count (and latched) while its stop
    /// stays unseen (and the driver off), never the other way round.
    pub fn snapshot(&self) -> EstopEvents {
        let stop = self.stop.load(Ordering::Acquire);
        let opened_us = self.opened_us.load(Ordering::Relaxed);
        let closed_us = self.closed_us.load(Ordering::Relaxed);
        let edges = self.edges.load(Ordering::Acquire);
        EstopEvents {
            edges,
            stop,
            opened_us,
            closed_us,
        }
    }
}

/// The propulsion driver's EN line behind the safety path's latch: it cannot be driven
/// low (driver on) while a stop is latched (see [`GatedEn::set_low`] for how a stop
/// racing the write is handled without a critical section).
pub struct GatedEn<P, L> {
    pin: P,
    latch: L,
}

/// Why the gated EN line refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum GateError<E> {
    /// A stop is latched: the driver stays off.
    Latched,
    /// The pin itself failed.
    Pin(E),
}

impl<E: core::fmt::Debug> embedded_hal::digital::Error for GateError<E> {
    fn kind(&self) -> embedded_hal::digital::ErrorKind {
        embedded_hal::digital::ErrorKind::Other
    }
}

impl<P, L> GatedEn<P, L> {
    /// Gate `pin` (EN, active low) with `latch`.
    pub fn new(pin: P, latch: L) -> Self {
        Self { pin, latch }
    }
}

impl<P: OutputPin, L> embedded_hal::digital::ErrorType for GatedEn<P, L> {
    type Error = GateError<P::Error>;
}

impl<P: OutputPin, L: StopLatch> OutputPin for GatedEn<P, L> {
    fn set_high(&mut self) -> Result<(), Self::Error> {
        self.pin.set_high().map_err(GateError::Pin)
    }

    /// Lock-free, so a stop at any priority (the E-STOP above every masked section
    /// included) is never delayed by it: checked, written, checked again. A stop that
    /// lands between the first check and the write finds EN set high by its own store,
    /// the write sets it low, and the second check sets it high again within a few
    /// instructions — with the step pulses already halted by the stop, so nothing moves.
    fn set_low(&mut self) -> Result<(), Self::Error> {
        if self.latch.latched() {
            return Err(GateError::Latched);
        }
        self.pin.set_low().map_err(GateError::Pin)?;
        if self.latch.latched() {
            self.pin.set_high().map_err(GateError::Pin)?;
            return Err(GateError::Latched);
        }
        Ok(())
    }
}

/// The step-pulse generator behind the safety path's latch: **no step rate is set while
/// a stop is latched** (a rate asked for then is 0), checked, written, checked again as
/// [`GatedEn`]'s EN.
///
/// The control step sets the rate last (`Propulsion::plan`, after the driver's EN and
/// the lock): a stop that landed after the step's own check of the latch and before
/// that write found its rate of zero overwritten, and the pulses went on with EN high
/// until the next step — the counted position drifting (issue 32, item 6: shown on the
/// virtual board, `an_estop_edge_between_the_gate_and_the_rate_left_pulses_running`).
/// A stop that lands between this write and the second check sets the rate to zero
/// itself and is seen by that check; the board's step tick emits no pulse while the
/// latch is set either (`src/board/step.rs`). Docs/board.md, "What holds between the
/// steps", rule 7.
pub struct GatedPulses<P, L> {
    pulses: P,
    latch: L,
}

impl<P, L> GatedPulses<P, L> {
    /// Gate `pulses` with `latch`.
    pub fn new(pulses: P, latch: L) -> Self {
        Self { pulses, latch }
    }
}

impl<P: StepPulses, L: StopLatch> StepPulses for GatedPulses<P, L> {
    fn set_rate_hz(&mut self, rate_hz: u32) {
        if rate_hz != 0 && self.latch.latched() {
            self.pulses.set_rate_hz(0);
            return;
        }
        self.pulses.set_rate_hz(rate_hz);
        if rate_hz != 0 && self.latch.latched() {
            self.pulses.set_rate_hz(0);
        }
    }

    fn take_pulses(&mut self) -> u32 {
        self.pulses.take_pulses()
    }
}

/// An active-high motor output (the lock's bridge inputs) behind the safety path's
/// latch: while a stop is latched it is held low, whatever it is told (an emergency stop
/// overrides the lock's command).
pub struct GatedHigh<P, L> {
    pin: P,
    latch: L,
}

impl<P, L> GatedHigh<P, L> {
    /// Gate `pin` (active high) with `latch`.
    pub fn new(pin: P, latch: L) -> Self {
        Self { pin, latch }
    }
}

impl<P: OutputPin, L> embedded_hal::digital::ErrorType for GatedHigh<P, L> {
    type Error = P::Error;
}

impl<P: OutputPin, L: StopLatch> OutputPin for GatedHigh<P, L> {
    /// Lock-free, as [`GatedEn`]'s: checked, written, checked again.
    fn set_high(&mut self) -> Result<(), Self::Error> {
        if self.latch.latched() {
            return self.pin.set_low();
        }
        self.pin.set_high()?;
        if self.latch.latched() {
            self.pin.set_low()?;
        }
        Ok(())
    }

    fn set_low(&mut self) -> Result<(), Self::Error> {
        self.pin.set_low()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use core::cell::Cell;

    struct Codes<'a>(&'a Cell<Option<i32>>);
    impl LoadCellAdc for Codes<'_> {
        fn read_code(&mut self) -> nb::Result<i32, ()> {
            self.0.take().ok_or(nb::Error::WouldBlock)
        }
    }

    #[derive(Default)]
    struct Latch {
        stops: u32,
        latched: bool,
    }
    impl StopLatch for Latch {
        fn stop_now(&mut self) -> u32 {
            self.stops += 1;
            self.latched = true;
            self.stops
        }
        fn stops(&self) -> u32 {
            self.stops
        }
        fn latched(&self) -> bool {
            self.latched
        }
        fn rearm(&mut self, seen: u32) -> bool {
            if seen >= self.stops {
                self.latched = false;
            }
            !self.latched
        }
    }

    const CAL: Calibration = Calibration::SIM_DEFAULT;

    fn code_for(force_n: i32) -> i32 {
        CAL.offset_counts + force_n * 8_590
    }

    #[test]
    fn an_overload_stops_in_the_call_that_reads_it() {
        let next = Cell::new(None);
        let mut k = SafetyKernel::new(Codes(&next), GuardConfig::DEFAULT, 80, CAL, 0);
        k.configure(
            KernelConfig {
                cal: CAL,
                mode: GuardMode::Cone { depth_um: 2_000 },
                clear: 0,
            },
            0,
        );
        let mut latch = Latch::default();
        assert_eq!(k.on_ready(60_000, &mut latch), None, "nothing ready");
        let mut f = 112;
        let stopped = loop {
            f += 3;
            next.set(Some(code_for(f)));
            let Some(KernelEvent::Sample(s)) = k.on_ready(60_000, &mut latch) else {
                panic!("a sample");
            };
            if let Some(n) = s.stop {
                assert!(matches!(s.verdict, Verdict::Trip { .. }));
                break n;
            }
        };
        assert_eq!(stopped, 1);
        assert!(latch.latched(), "latched until the controller re-arms");
        assert!(!latch.rearm(0), "a stop it has not seen is not cleared");
        assert!(latch.rearm(1));
    }

    #[test]
    fn a_silent_cell_stops_once_after_three_periods() {
        let next = Cell::new(None);
        let mut k = SafetyKernel::new(Codes(&next), GuardConfig::DEFAULT, 80, CAL, 0);
        let mut latch = Latch::default();
        next.set(Some(code_for(0)));
        assert!(k.on_ready(50_000, &mut latch).is_some());
        assert_eq!(k.check(50_000 + 37_500, &mut latch), None);
        assert_eq!(
            k.check(50_000 + 37_501, &mut latch),
            Some(KernelEvent::Silent {
                t_us: 87_501,
                stop: 1
            })
        );
        assert_eq!(k.check(200_000, &mut latch), None, "reported once");
    }

    #[test]
    fn the_gate_keeps_the_driver_off_while_latched() {
        use crate::hal::test_pin::CellPin as En;
        let level = Cell::new(true);
        let mut latch = Latch::default();
        latch.stop_now();
        let mut g = GatedEn::new(En(&level), latch);
        assert_eq!(g.set_low(), Err(GateError::Latched));
        assert!(level.get(), "EN stays high: driver off");
    }
}
