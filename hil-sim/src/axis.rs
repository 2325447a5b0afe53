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

use std::cell::RefCell;
use std::rc::Rc;

use docking_controller::config::MachineConfig;
use docking_controller::hal::StepPulses;

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

/// Shared model.
#[derive(Debug)]
pub struct AxisModel {
    cfg: MachineConfig,
    /// Carriage position, steps (physical truth).
    pos_steps: i64,
    rate_hz: u32,
    /// ns·Hz accumulator for fractional pulses.
    frac: u64,
    pending_pulses: u32,
    dir_positive: bool,
    enabled: bool,
    last_ns: u64,
    fault: AxisFault,
    edges: Vec<EnableEdge>,
    /// Total carriage travel, steps (both directions).
    travel_steps: u64,
    /// Travel since the driver was last disabled, steps.
    travel_since_disable_steps: u64,
    /// µm per step (cached).
    um_per_step: f64,
    /// Hard stops and end switch, steps.
    lo_steps: i64,
    hi_steps: i64,
    end_steps: i64,
}

impl AxisModel {
    fn update(&mut self, now: u64) {
        if now <= self.last_ns {
            return;
        }
        let dt = now - self.last_ns;
        self.last_ns = now;
        if self.rate_hz == 0 {
            return;
        }
        let acc = self.frac + dt * self.rate_hz as u64;
        let n = acc / 1_000_000_000;
        self.frac = acc % 1_000_000_000;
        self.pending_pulses = self.pending_pulses.saturating_add(n as u32);
        if n > 0 && self.enabled && self.fault != AxisFault::Stalled {
            let before = self.pos_steps;
            let step = if self.dir_positive {
                n as i64
            } else {
                -(n as i64)
            };
            self.pos_steps = (self.pos_steps + step).clamp(self.lo_steps, self.hi_steps);
            let moved = (self.pos_steps - before).unsigned_abs();
            self.travel_steps += moved;
            self.travel_since_disable_steps += moved;
        }
    }

    fn pos_um(&self) -> f64 {
        self.pos_steps as f64 * self.um_per_step
    }
}

/// Handle to the simulated axis.
#[derive(Clone)]
pub struct SimAxis {
    model: Rc<RefCell<AxisModel>>,
    clock: SimClock,
}

impl SimAxis {
    /// An axis at `start_um` with the driver off.
    pub fn new(cfg: MachineConfig, clock: SimClock, start_um: i32) -> Self {
        let m = AxisModel {
            cfg,
            pos_steps: cfg.um_to_steps(start_um) as i64,
            rate_hz: 0,
            frac: 0,
            pending_pulses: 0,
            dir_positive: false,
            enabled: false,
            last_ns: clock.now_ns(),
            fault: AxisFault::None,
            edges: Vec::new(),
            travel_steps: 0,
            travel_since_disable_steps: 0,
            um_per_step: 1000.0 / cfg.steps_per_mm as f64,
            lo_steps: cfg.um_to_steps(-2_000) as i64,
            hi_steps: cfg.um_to_steps(cfg.end_switch_um + 2_000) as i64,
            end_steps: cfg.um_to_steps(cfg.end_switch_um) as i64,
        };
        Self {
            model: Rc::new(RefCell::new(m)),
            clock,
        }
    }

    fn with<R>(&self, f: impl FnOnce(&mut AxisModel) -> R) -> R {
        let mut m = self.model.borrow_mut();
        m.update(self.clock.now_ns());
        f(&mut m)
    }

    /// Carriage position now, µm.
    pub fn pos_um(&self) -> f64 {
        self.with(|m| m.pos_um())
    }

    /// Carriage position now, steps.
    pub fn pos_steps(&self) -> i64 {
        self.with(|m| m.pos_steps)
    }

    /// Whether the driver is enabled now.
    pub fn enabled(&self) -> bool {
        self.with(|m| m.enabled)
    }

    /// Inject or clear a fault.
    pub fn set_fault(&self, fault: AxisFault) {
        self.with(|m| m.fault = fault);
    }

    /// Driver-enable edges so far.
    pub fn enable_edges(&self) -> Vec<EnableEdge> {
        self.with(|m| m.edges.clone())
    }

    /// Total carriage travel so far, µm.
    pub fn travel_um(&self) -> f64 {
        self.with(|m| m.travel_steps as f64 * 1000.0 / m.cfg.steps_per_mm as f64)
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
        self.0.with(|m| m.rate_hz = rate_hz);
    }

    fn take_pulses(&mut self) -> u32 {
        self.0.with(|m| core::mem::take(&mut m.pending_pulses))
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum PinRole {
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
        let role = self.1;
        self.0.with(|m| match role {
            PinRole::EnableN => {
                let enabled = !high;
                if enabled != m.enabled {
                    m.enabled = enabled;
                    if !enabled {
                        m.travel_since_disable_steps = 0;
                    }
                    let pos_um = m.pos_um();
                    m.edges.push(EnableEdge {
                        t_ns: now,
                        enabled,
                        pos_um,
                    });
                }
            }
            PinRole::Dir => m.dir_positive = high,
            PinRole::Home | PinRole::End => {}
        });
    }
}

impl embedded_hal::digital::InputPin for AxisPin {
    fn is_high(&mut self) -> Result<bool, Self::Error> {
        let role = self.1;
        Ok(self.0.with(|m| match role {
            PinRole::Home => !(m.fault != AxisFault::HomeSwitchDead && m.pos_steps <= 0),
            PinRole::End => !(m.fault != AxisFault::EndSwitchDead && m.pos_steps >= m.end_steps),
            PinRole::EnableN => !m.enabled,
            PinRole::Dir => m.dir_positive,
        }))
    }
    fn is_low(&mut self) -> Result<bool, Self::Error> {
        self.is_high().map(|h| !h)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_hal::digital::{InputPin, OutputPin};

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
