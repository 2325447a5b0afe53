//! The simulated propulsion axis: a step/dir stepper driver on a lead screw, with home
//! and end (overtravel) switches, moving in virtual time.
//!
//! * EN is active low (high = driver off, the safe state); DIR high = toward the male
//!   panel (+). Pulses that arrive while the driver is off are counted by the pulse
//!   generator but do not move the carriage, like a real driver.
//! * Switches are active low (closed = pin low), home closed at x ≤ 0, end closed at
//!   x ≥ `end_switch_um`. Hard stops 2 mm beyond either switch.
//! * Faults: `Stalled` (the carriage does not move: lost steps / jam), a dead switch
//!   (never closes).
//!
//! The axis keeps a motion log (driver enable edges with time and position) so tests
//! can prove that nothing moved after a trip except the commanded back-off.
//!
//! Two ways to drive it, one model: the host rig gives a pulse *rate* through
//! [`AxisPulses`] (the board's step generator, abstracted); the virtual board drives
//! the **STEP pin** ([`SimAxis::step`]): every rising edge is one pulse, in the direction
//! DIR has at that edge, like a DM542/TB6600-class driver. On the pin path the model
//! also checks what such a driver's opto-coupled inputs need ([`StepTiming`]): DIR and
//! EN settled at least [`DIR_EN_SETUP_NS`] before a STEP rising edge, STEP high at least
//! [`STEP_HIGH_MIN_NS`] and low at least [`STEP_LOW_MIN_NS`].

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use docking_logic::config::MachineConfig;
use docking_logic::hal::StepPulses;

use crate::clock::SimClock;

/// Injected axis faults.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AxisFault {
    /// Working normally.
    None,
    /// The carriage does not move whatever the pulses (stall, jam, broken coupling).
    Stalled,
    /// The home switch never closes.
    HomeSwitchDead,
    /// The end switch never closes.
    EndSwitchDead,
    /// The end switch reads closed wherever the carriage is (an overtravel the model's
    /// geometry does not produce: a misadjusted stop, a bent actuator).
    EndSwitchClosed,
}

/// One driver-enable edge.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct EnableEdge {
    /// Virtual time, ns.
    pub t_ns: u64,
    /// Driver enabled after the edge.
    pub enabled: bool,
    /// Carriage position at the edge, µm.
    pub pos_um: f64,
}

/// DIR and EN must be stable this long before a STEP rising edge, ns (DM542: 5 µs).
pub const DIR_EN_SETUP_NS: u64 = 5_000;
/// Shortest STEP high time the driver registers, ns (DM542: 2.5 µs).
pub const STEP_HIGH_MIN_NS: u64 = 2_500;
/// Shortest STEP low time the driver registers, ns (DM542: 2.5 µs).
pub const STEP_LOW_MIN_NS: u64 = 2_500;

/// What the STEP/DIR/EN pins did, as a DM542-class driver sees it (pin path only).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StepTiming {
    /// STEP rising edges while enabled with DIR high (+).
    pub pulses_pos: u64,
    /// STEP rising edges while enabled with DIR low (−).
    pub pulses_neg: u64,
    /// STEP rising edges while the driver was off (ignored by the driver).
    pub pulses_disabled: u64,
    /// Rising edges whose DIR or EN changed less than [`DIR_EN_SETUP_NS`] before.
    pub setup_violations: u64,
    /// Pulses whose high or low phase was shorter than the minimum.
    pub width_violations: u64,
    /// Shortest DIR/EN-change-to-STEP-edge time seen, ns (`u64::MAX`: none).
    pub min_setup_ns: u64,
    /// Shortest STEP high time seen, ns (`u64::MAX`: none).
    pub min_high_ns: u64,
}

/// Shared model. The state every pin touches each control step is in `Cell`s (all
/// `Copy`): a `Cell` needs no borrow bookkeeping, and the controller reads or drives the
/// axis several times per step.
#[derive(Debug)]
pub struct AxisModel {
    cfg: MachineConfig,
    /// Carriage position, steps (physical truth).
    pos_steps: Cell<i64>,
    rate_hz: Cell<u32>,
    /// ns·Hz accumulator for fractional pulses, as of `last_ns`.
    frac: Cell<u64>,
    /// When the accumulator reaches the next whole pulse at the latest, ns (`u64::MAX`
    /// while the rate is 0): before it nothing moves, so a read before it changes
    /// nothing. (It may be a nanosecond early, never late: see `pulse_recip`.)
    next_pulse_ns: Cell<u64>,
    /// ⌊(2⁶⁴ − 1) / rate⌋: the time to the next pulse is ⌈(1e9 − frac) / rate⌉ ns, taken
    /// as the high word of a product instead of a division — equal or one less.
    pulse_recip: Cell<u64>,
    /// The last interval `advance` divided (`0`: none at this rate) and its quotient and
    /// remainder: `⌊dt·rate / 1e9⌋`, `dt·rate mod 1e9`. The control loop reads the axis
    /// once a sample period, so the next interval is usually the same, and its pulses
    /// are the quotient plus a carry from the remainder (exact: both remainders are
    /// below 1e9) instead of another division.
    interval: Cell<(u64, u64, u64)>,
    pending_pulses: Cell<u32>,
    dir_positive: Cell<bool>,
    enabled: Cell<bool>,
    last_ns: Cell<u64>,
    fault: Cell<AxisFault>,
    /// Reads of the end switch still to come out closed (electrical noise).
    end_noise_reads: Cell<u32>,
    edges: RefCell<Vec<EnableEdge>>,
    /// Total carriage travel, steps (both directions).
    travel_steps: Cell<u64>,
    /// Pulses that reached the driver while it was off (either drive path): none should
    /// (a pulse counted with the carriage still is a counted position drifting).
    pulses_while_off: Cell<u64>,
    /// µm per step (cached).
    um_per_step: f64,
    /// Hard stops and end switch, steps.
    lo_steps: i64,
    hi_steps: i64,
    end_steps: i64,
    /// STEP pin level, the time of its last edge, and the last DIR/EN change (pin path).
    step_high: Cell<bool>,
    step_edge_ns: Cell<Option<u64>>,
    dir_en_change_ns: Cell<Option<u64>>,
    timing: Cell<StepTiming>,
}

impl AxisModel {
    /// Move the carriage to where the pulses since the last update put it. Several
    /// lines are read at one instant each control step, and most reads come before the
    /// next pulse: only a read at or after it moves the model.
    #[inline]
    fn update(&self, now: u64) {
        if now >= self.next_pulse_ns.get() {
            self.advance(now);
        }
    }

    /// The position at `now`, steps: the model moved there first if a pulse is due.
    /// (Returned rather than read back by the caller: the load of a value just stored
    /// would wait for the store, on the way from the clock to the load cell's code.)
    #[inline]
    fn pos_at(&self, now: u64) -> i64 {
        if now >= self.next_pulse_ns.get() {
            return self.advance_inline(now);
        }
        self.pos_steps.get()
    }

    /// The pulses from `last_ns` to `now` (`now` at or past `next_pulse_ns`: usually one
    /// or more, none if that was the nanosecond before the pulse); the position after
    /// them.
    fn advance(&self, now: u64) -> i64 {
        self.advance_inline(now)
    }

    /// [`Self::advance`], inlined where the load cell reads the position.
    #[inline(always)]
    fn advance_inline(&self, now: u64) -> i64 {
        let dt = now - self.last_ns.get();
        let (last_dt, q, r) = self.interval.get();
        // `frac + dt·rate` split as `(frac + r) + q·1e9`: `frac + r` < 2e9, so it carries
        // at most one pulse.
        let (n, frac) = if dt == last_dt {
            let f = self.frac.get() + r;
            if f >= 1_000_000_000 {
                (q + 1, f - 1_000_000_000)
            } else {
                (q, f)
            }
        } else {
            let rate = self.rate_hz.get() as u64;
            let p = dt * rate;
            self.interval
                .set((dt, p / 1_000_000_000, p % 1_000_000_000));
            let acc = self.frac.get() + p;
            (acc / 1_000_000_000, acc % 1_000_000_000)
        };
        self.frac.set(frac);
        self.last_ns.set(now);
        let to_pulse = ((1_000_000_000 - frac) as u128 * self.pulse_recip.get() as u128) >> 64;
        self.next_pulse_ns.set(now + to_pulse as u64);
        self.pending_pulses
            .set(self.pending_pulses.get().saturating_add(n as u32));
        self.move_steps(n)
    }

    /// Account for the pulses up to `now` exactly (before the rate changes: the
    /// accumulator is kept at the old rate up to here).
    fn settle(&self, now: u64) {
        let rate = self.rate_hz.get() as u64;
        if rate != 0 {
            let acc = self.frac.get() + (now - self.last_ns.get()) * rate;
            let n = acc / 1_000_000_000;
            self.frac.set(acc % 1_000_000_000);
            if n != 0 {
                self.pending_pulses
                    .set(self.pending_pulses.get().saturating_add(n as u32));
                let _ = self.move_steps(n);
            }
        }
        self.last_ns.set(now);
    }

    /// The pulse generator's rate from `now` on.
    fn set_rate_hz(&self, rate_hz: u32, now: u64) {
        self.settle(now);
        self.rate_hz.set(rate_hz);
        self.interval.set((0, 0, 0));
        self.pulse_recip.set(u64::MAX / rate_hz.max(1) as u64);
        self.next_pulse_ns.set(match rate_hz {
            0 => u64::MAX,
            r => now + (1_000_000_000 - self.frac.get()).div_ceil(r as u64),
        });
    }

    /// `n` pulses reach the driver: the carriage moves in the DIR direction if the driver
    /// is on and nothing stalls it, up to the hard stops. Both drive paths end here. The
    /// position after them.
    fn move_steps(&self, n: u64) -> i64 {
        let before = self.pos_steps.get();
        if self.enabled.get() && self.fault.get() != AxisFault::Stalled {
            let step = if self.dir_positive.get() {
                n as i64
            } else {
                -(n as i64)
            };
            let after = (before + step).clamp(self.lo_steps, self.hi_steps);
            self.pos_steps.set(after);
            let moved = (after - before).unsigned_abs();
            self.travel_steps.set(self.travel_steps.get() + moved);
            return after;
        }
        if !self.enabled.get() {
            self.pulses_while_off
                .set(self.pulses_while_off.get().saturating_add(n));
        }
        before
    }

    /// The STEP pin goes to `high` at `now` (pin path).
    fn step_pin(&self, high: bool, now: u64) {
        if high == self.step_high.get() {
            return;
        }
        let mut t = self.timing.get();
        // The first edge has no previous phase to measure.
        let since = self
            .step_edge_ns
            .get()
            .map_or(u64::MAX, |t| now.saturating_sub(t));
        self.step_high.set(high);
        self.step_edge_ns.set(Some(now));
        if !high {
            t.min_high_ns = t.min_high_ns.min(since);
            if since < STEP_HIGH_MIN_NS {
                t.width_violations += 1;
            }
            self.timing.set(t);
            return;
        }
        if since < STEP_LOW_MIN_NS {
            t.width_violations += 1;
        }
        if !self.enabled.get() {
            t.pulses_disabled += 1;
        } else {
            if let Some(c) = self.dir_en_change_ns.get() {
                let setup = now.saturating_sub(c);
                t.min_setup_ns = t.min_setup_ns.min(setup);
                if setup < DIR_EN_SETUP_NS {
                    t.setup_violations += 1;
                }
            }
            if self.dir_positive.get() {
                t.pulses_pos += 1;
            } else {
                t.pulses_neg += 1;
            }
        }
        self.timing.set(t);
        let _ = self.move_steps(1);
    }

    fn pos_um(&self) -> f64 {
        self.pos_steps.get() as f64 * self.um_per_step
    }
}

/// Handle to the simulated axis.
#[derive(Clone)]
pub struct SimAxis {
    model: Rc<AxisModel>,
    clock: SimClock,
}

impl SimAxis {
    /// An axis at `start_um` with the driver off.
    pub fn new(cfg: MachineConfig, clock: SimClock, start_um: i32) -> Self {
        let m = AxisModel {
            cfg,
            pos_steps: Cell::new(cfg.um_to_steps(start_um) as i64),
            rate_hz: Cell::new(0),
            frac: Cell::new(0),
            next_pulse_ns: Cell::new(u64::MAX),
            pulse_recip: Cell::new(0),
            interval: Cell::new((0, 0, 0)),
            pending_pulses: Cell::new(0),
            dir_positive: Cell::new(false),
            enabled: Cell::new(false),
            last_ns: Cell::new(clock.now_ns()),
            fault: Cell::new(AxisFault::None),
            end_noise_reads: Cell::new(0),
            edges: RefCell::new(Vec::new()),
            travel_steps: Cell::new(0),
            pulses_while_off: Cell::new(0),
            um_per_step: 1000.0 / cfg.steps_per_mm as f64,
            lo_steps: cfg.um_to_steps(-2_000) as i64,
            hi_steps: cfg.um_to_steps(cfg.end_switch_um + 2_000) as i64,
            end_steps: cfg.um_to_steps(cfg.end_switch_um) as i64,
            step_high: Cell::new(false),
            step_edge_ns: Cell::new(None),
            dir_en_change_ns: Cell::new(None),
            timing: Cell::new(StepTiming {
                min_setup_ns: u64::MAX,
                min_high_ns: u64::MAX,
                ..StepTiming::default()
            }),
        };
        Self {
            model: Rc::new(m),
            clock,
        }
    }

    /// The model, moved up to now.
    #[inline]
    fn now(&self) -> &AxisModel {
        self.model.update(self.clock.now_ns());
        &self.model
    }

    /// Carriage position now, µm.
    pub fn pos_um(&self) -> f64 {
        self.now().pos_um()
    }

    /// Carriage position now, steps.
    #[inline]
    pub fn pos_steps(&self) -> i64 {
        self.model.pos_at(self.clock.now_ns())
    }

    /// Whether DIR points toward the male panel (+) now.
    pub fn forward(&self) -> bool {
        self.model.dir_positive.get()
    }

    /// Whether the driver is enabled now.
    pub fn enabled(&self) -> bool {
        self.now().enabled.get()
    }

    /// Inject or clear a fault.
    pub fn set_fault(&self, fault: AxisFault) {
        self.now().fault.set(fault);
    }

    /// Electrical noise on the end-switch line: its next `reads` reads see it closed.
    pub fn glitch_end_switch(&self, reads: u32) {
        self.now().end_noise_reads.set(reads);
    }

    /// Driver-enable edges so far.
    pub fn enable_edges(&self) -> Vec<EnableEdge> {
        self.now().edges.borrow().clone()
    }

    /// Total carriage travel so far, µm.
    pub fn travel_um(&self) -> f64 {
        let m = self.now();
        m.travel_steps.get() as f64 * 1000.0 / m.cfg.steps_per_mm as f64
    }

    /// Pulses that reached the driver while it was off, so far (both drive paths).
    pub fn pulses_while_off(&self) -> u64 {
        self.now().pulses_while_off.get()
    }

    /// What the STEP/DIR/EN pins did so far (pin path).
    pub fn step_timing(&self) -> StepTiming {
        self.model.timing.get()
    }

    /// The STEP pin (rising edge = one pulse), for a board that drives it directly.
    pub fn step(&self) -> AxisPin {
        AxisPin(self.clone(), PinRole::Step)
    }

    /// The step-pulse generator (for the propulsion driver).
    pub fn pulses(&self) -> AxisPulses {
        AxisPulses(self.clone())
    }
    /// EN pin (active low).
    pub fn enable_n(&self) -> AxisPin {
        AxisPin(self.clone(), PinRole::EnableN)
    }
    /// DIR pin (high = +).
    pub fn dir(&self) -> AxisPin {
        AxisPin(self.clone(), PinRole::Dir)
    }
    /// Home switch (active low).
    pub fn home_switch(&self) -> AxisPin {
        AxisPin(self.clone(), PinRole::Home)
    }
    /// End switch (active low).
    pub fn end_switch(&self) -> AxisPin {
        AxisPin(self.clone(), PinRole::End)
    }
}

/// The axis's pulse generator.
pub struct AxisPulses(SimAxis);

impl StepPulses for AxisPulses {
    fn set_rate_hz(&mut self, rate_hz: u32) {
        let now = self.0.clock.now_ns();
        self.0.now().set_rate_hz(rate_hz, now);
    }

    fn take_pulses(&mut self) -> u32 {
        self.0.now().pending_pulses.replace(0)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PinRole {
    Step,
    EnableN,
    Dir,
    Home,
    End,
}

/// One of the axis's digital lines.
pub struct AxisPin(SimAxis, PinRole);

impl embedded_hal::digital::ErrorType for AxisPin {
    type Error = core::convert::Infallible;
}

impl embedded_hal::digital::OutputPin for AxisPin {
    fn set_high(&mut self) -> Result<(), Self::Error> {
        self.set(true);
        Ok(())
    }
    fn set_low(&mut self) -> Result<(), Self::Error> {
        self.set(false);
        Ok(())
    }
}

impl AxisPin {
    fn set(&mut self, high: bool) {
        let now = self.0.clock.now_ns();
        let m = self.0.now();
        match self.1 {
            PinRole::EnableN => {
                let enabled = !high;
                if enabled != m.enabled.get() {
                    m.enabled.set(enabled);
                    m.dir_en_change_ns.set(Some(now));
                    m.edges.borrow_mut().push(EnableEdge {
                        t_ns: now,
                        enabled,
                        pos_um: m.pos_um(),
                    });
                }
            }
            PinRole::Dir => {
                if high != m.dir_positive.get() {
                    m.dir_positive.set(high);
                    m.dir_en_change_ns.set(Some(now));
                }
            }
            PinRole::Step => m.step_pin(high, now),
            PinRole::Home | PinRole::End => {}
        }
    }
}

impl AxisModel {
    /// The home switch's line (active low: closed at x <= 0 unless dead).
    #[inline]
    fn home_high(&self) -> bool {
        self.pos_steps.get() > 0 || self.fault.get() == AxisFault::HomeSwitchDead
    }

    /// The end switch's line (active low); a read consumes one of the noise reads.
    #[inline]
    fn end_high(&self) -> bool {
        if self.end_noise_reads.get() == 0 && self.fault.get() == AxisFault::None {
            return self.pos_steps.get() < self.end_steps; // the usual read
        }
        self.end_high_other()
    }

    /// [`Self::end_high`] with noise on the line or a fault.
    #[inline(never)]
    fn end_high_other(&self) -> bool {
        let noise = self.end_noise_reads.get();
        if noise > 0 {
            self.end_noise_reads.set(noise - 1);
            return false;
        }
        let closed = match self.fault.get() {
            AxisFault::EndSwitchDead => false,
            AxisFault::EndSwitchClosed => true,
            _ => self.pos_steps.get() >= self.end_steps,
        };
        !closed
    }
}

impl embedded_hal::digital::InputPin for AxisPin {
    fn is_high(&mut self) -> Result<bool, Self::Error> {
        let m = self.0.now();
        Ok(match self.1 {
            PinRole::Home => m.home_high(),
            PinRole::End => m.end_high(),
            PinRole::EnableN => !m.enabled.get(),
            PinRole::Dir => m.dir_positive.get(),
            PinRole::Step => m.step_high.get(),
        })
    }
    fn is_low(&mut self) -> Result<bool, Self::Error> {
        self.is_high().map(|h| !h)
    }
}

/// The home switch alone: [`AxisPin`]'s home line with its role fixed by the type, so
/// the controller's read (every control step of a long run) compiles to the check
/// itself, without the dispatch over the roles.
pub struct HomeSwitch(SimAxis);

/// The end switch alone (see [`HomeSwitch`]).
pub struct EndSwitch(SimAxis);

impl SimAxis {
    /// Home switch (active low), as its own type.
    pub fn home_switch_line(&self) -> HomeSwitch {
        HomeSwitch(self.clone())
    }
    /// End switch (active low), as its own type.
    pub fn end_switch_line(&self) -> EndSwitch {
        EndSwitch(self.clone())
    }
}

input_line!(HomeSwitch, |a| a.now().home_high());
input_line!(EndSwitch, |a| a.now().end_high());

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_hal::digital::{InputPin, OutputPin};

    /// The model moves only at reads at or after the next pulse; whenever it is read
    /// (often, seldom, with rate changes between), the pulses and the position are those
    /// of a generator that counts every nanosecond: `⌊Σ rate·dt / 1e9⌋`.
    #[test]
    fn reads_at_any_times_see_the_pulses_of_every_nanosecond() {
        let clk = SimClock::new();
        let ax = SimAxis::new(MachineConfig::DEFAULT, clk.clone(), 0);
        let (mut p, mut en, mut dir) = (ax.pulses(), ax.enable_n(), ax.dir());
        dir.set_high().unwrap();
        en.set_low().unwrap();
        let mut rng = crate::rng::Rng::new(3);
        // ns·Hz since t = 0, summed exactly.
        let (mut exact, mut rate, mut t, mut taken) = (0u128, 0u32, 0u64, 0u64);
        for i in 0..20_000 {
            // Half the reads land on the next pulse's nanosecond or the one before it.
            let to_pulse =
                (1_000_000_000 - (exact % 1_000_000_000) as u64).div_ceil(rate.max(1) as u64);
            let dt = match (rate, i % 4) {
                (0, _) | (_, 0 | 1) => rng.next_u64() % 3_000_000,
                (_, 2) => to_pulse - 1,
                _ => to_pulse,
            };
            exact += dt as u128 * rate as u128;
            t += dt;
            clk.advance_to_ns(t);
            if i % 7 == 0 {
                taken += p.take_pulses() as u64;
            }
            if i % 500 == 0 {
                rate = [0, 240, 333, 1_000, 7][(i / 500) % 5];
                p.set_rate_hz(rate);
            }
            let pulses = (exact / 1_000_000_000) as u64;
            assert_eq!(ax.pos_steps() as u64, pulses, "read {i} at {t} ns");
            if i % 3 == 0 {
                assert_eq!(taken + p.take_pulses() as u64, pulses, "read {i}");
                taken = pulses;
            }
        }
    }

    /// Reads a sample period apart (the control loop's: each interval's pulses from the
    /// previous interval's quotient and remainder), with rate changes and odd intervals
    /// between: the pulses of a generator that counts every nanosecond.
    #[test]
    fn reads_a_period_apart_see_the_pulses_of_every_nanosecond() {
        let clk = SimClock::new();
        let ax = SimAxis::new(MachineConfig::DEFAULT, clk.clone(), 0);
        let (mut p, mut en, mut dir) = (ax.pulses(), ax.enable_n(), ax.dir());
        dir.set_high().unwrap();
        en.set_low().unwrap();
        let (mut exact, mut rate, mut t, mut taken) = (0u128, 0u32, 0u64, 0u128);
        for i in 0..30_000u64 {
            // Mostly 12.5 ms (80 SPS) or 100 ms (10 SPS), sometimes 25.5 µs more (a
            // readout) or an odd interval.
            let dt = match i % 97 {
                0 => 12_525_500,
                1 => 7_777_777,
                _ if (i / 3_000) % 2 == 0 => 12_500_000,
                _ => 100_000_000,
            };
            exact += dt as u128 * rate as u128;
            t += dt;
            clk.advance_to_ns(t);
            if i % 1_000 == 0 {
                rate = [240, 333, 1_000, 7, 80_001, 12_345][(i / 1_000) as usize % 6];
                p.set_rate_hz(rate);
            }
            // The pulses (the carriage stops at the hard stop; the generator does not).
            taken += p.take_pulses() as u128;
            assert_eq!(taken, exact / 1_000_000_000, "read {i} at {t} ns");
        }
    }

    #[test]
    fn moves_at_the_pulse_rate_only_when_enabled() {
        let clk = SimClock::new();
        let ax = SimAxis::new(MachineConfig::DEFAULT, clk.clone(), 0);
        let (mut p, mut en, mut dir, mut home) =
            (ax.pulses(), ax.enable_n(), ax.dir(), ax.home_switch());
        assert!(home.is_low().unwrap());
        dir.set_high().unwrap();
        p.set_rate_hz(240); // 1.2 mm/s at 200 steps/mm
        clk.advance_ns(1_000_000_000);
        assert_eq!(ax.pos_um(), 0.0, "driver off: no motion");
        assert_eq!(p.take_pulses(), 240);
        en.set_low().unwrap();
        clk.advance_ns(1_000_000_000);
        assert_eq!(ax.pos_um(), 1_200.0);
        assert!(home.is_high().unwrap());
        ax.set_fault(AxisFault::Stalled);
        clk.advance_ns(1_000_000_000);
        assert_eq!(ax.pos_um(), 1_200.0);
        assert_eq!(ax.enable_edges().len(), 1);
    }

    #[test]
    fn step_pin_moves_one_step_per_rising_edge_and_checks_driver_timing() {
        let clk = SimClock::new();
        let ax = SimAxis::new(MachineConfig::DEFAULT, clk.clone(), 0);
        let (mut step, mut en, mut dir) = (ax.step(), ax.enable_n(), ax.dir());
        let pulse = |step: &mut AxisPin, high_ns: u64| {
            step.set_high().unwrap();
            clk.advance_ns(high_ns);
            step.set_low().unwrap();
            clk.advance_ns(10_000);
        };
        pulse(&mut step, 3_000); // driver off: ignored
        dir.set_high().unwrap();
        en.set_low().unwrap();
        clk.advance_ns(6_000);
        pulse(&mut step, 3_000);
        pulse(&mut step, 3_000);
        assert_eq!(ax.pos_steps(), 2);
        dir.set_low().unwrap();
        clk.advance_ns(1_000); // DIR changed only 1 µs before the edge: a violation
        pulse(&mut step, 1_000); // and a 1 µs high phase: another
        assert_eq!(
            ax.pos_steps(),
            1,
            "counted in the direction DIR had at the edge"
        );
        let t = ax.step_timing();
        assert_eq!((t.pulses_pos, t.pulses_neg, t.pulses_disabled), (2, 1, 1));
        assert_eq!((t.setup_violations, t.width_violations), (1, 1));
        assert_eq!((t.min_setup_ns, t.min_high_ns), (1_000, 1_000));
    }

    #[test]
    fn end_switch_and_hard_stop() {
        let clk = SimClock::new();
        let cfg = MachineConfig::DEFAULT;
        let ax = SimAxis::new(cfg, clk.clone(), cfg.end_switch_um - 10);
        let (mut p, mut en, mut dir, mut end) =
            (ax.pulses(), ax.enable_n(), ax.dir(), ax.end_switch());
        assert!(end.is_high().unwrap());
        dir.set_high().unwrap();
        en.set_low().unwrap();
        p.set_rate_hz(2_000);
        clk.advance_ns(10_000_000_000);
        assert!(end.is_low().unwrap());
        assert_eq!(ax.pos_um(), (cfg.end_switch_um + 2_000) as f64);
    }
}
