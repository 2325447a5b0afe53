//! The simulated adaptive-lock actuator: a DC gear motor on a lead screw that moves the
//! homing cone, driven through an H-bridge (IN1 high = toward locked, IN2 high =
//! toward released, both low = stopped, the safe state), with a *locked* and a
//! *released* end switch (active low).
//!
//! Fault: `Stuck` — the screw does not move (seized, motor open-circuit).

use std::cell::RefCell;
use std::rc::Rc;

use crate::clock::SimClock;

/// Lead-screw travel between the released and locked switches, µm.
pub const LOCK_TRAVEL_UM: u64 = 4_000;
/// Screw speed, µm/s (so a full stroke takes 400 ms).
pub const LOCK_SPEED_UM_PER_S: u64 = 10_000;

/// Injected lock faults.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LockFault {
    /// Working normally.
    None,
    /// The screw does not move.
    Stuck,
}

#[derive(Debug)]
struct LockModel {
    /// Screw position, nm (exact integration): 0 = released.
    pos_nm: u64,
    in1: bool,
    in2: bool,
    last_ns: u64,
    fault: LockFault,
}

impl LockModel {
    fn update(&mut self, now: u64) {
        if self.fault == LockFault::Stuck || self.in1 == self.in2 {
            self.last_ns = self.last_ns.max(now);
            return;
        }
        let dt = now.saturating_sub(self.last_ns);
        self.last_ns = self.last_ns.max(now);
        // dt ns · v µm/s · 1e-9 s/ns · 1e3 nm/µm = dt·v/1e6 nm
        let d_nm = dt * LOCK_SPEED_UM_PER_S / 1_000_000;
        let max = LOCK_TRAVEL_UM * 1_000;
        self.pos_nm = if self.in1 {
            (self.pos_nm + d_nm).min(max)
        } else {
            self.pos_nm.saturating_sub(d_nm)
        };
    }
}

/// Handle to the simulated lock.
#[derive(Clone)]
pub struct SimLock {
    model: Rc<RefCell<LockModel>>,
    clock: SimClock,
}

impl SimLock {
    /// A lock that starts locked (the state the machine is parked in).
    pub fn new_locked(clock: SimClock) -> Self {
        let m = LockModel {
            pos_nm: LOCK_TRAVEL_UM * 1_000,
            in1: false,
            in2: false,
            last_ns: clock.now_ns(),
            fault: LockFault::None,
        };
        Self {
            model: Rc::new(RefCell::new(m)),
            clock,
        }
    }

    fn with<R>(&self, f: impl FnOnce(&mut LockModel) -> R) -> R {
        let mut m = self.model.borrow_mut();
        m.update(self.clock.now_ns());
        f(&mut m)
    }

    /// Inject or clear a fault.
    pub fn set_fault(&self, fault: LockFault) {
        self.with(|m| m.fault = fault);
    }

    /// Whether the motor is driven now.
    pub fn driven(&self) -> bool {
        self.with(|m| m.in1 != m.in2)
    }

    /// Screw position, 0 = released, 1 = locked.
    pub fn fraction_locked(&self) -> f64 {
        self.with(|m| m.pos_nm as f64 / (LOCK_TRAVEL_UM * 1_000) as f64)
    }

    /// IN1 (drive toward locked).
    pub fn in1(&self) -> LockPin {
        LockPin(self.clone(), LockRole::In1)
    }
    /// IN2 (drive toward released).
    pub fn in2(&self) -> LockPin {
        LockPin(self.clone(), LockRole::In2)
    }
    /// Locked switch (active low).
    pub fn locked_switch(&self) -> LockPin {
        LockPin(self.clone(), LockRole::LockedSw)
    }
    /// Released switch (active low).
    pub fn released_switch(&self) -> LockPin {
        LockPin(self.clone(), LockRole::ReleasedSw)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum LockRole {
    In1,
    In2,
    LockedSw,
    ReleasedSw,
}

/// One of the lock's digital lines.
pub struct LockPin(SimLock, LockRole);

impl embedded_hal::digital::ErrorType for LockPin {
    type Error = core::convert::Infallible;
}

impl embedded_hal::digital::OutputPin for LockPin {
    fn set_high(&mut self) -> Result<(), Self::Error> {
        let r = self.1;
        self.0.with(|m| match r {
            LockRole::In1 => m.in1 = true,
            LockRole::In2 => m.in2 = true,
            _ => {}
        });
        Ok(())
    }
    fn set_low(&mut self) -> Result<(), Self::Error> {
        let r = self.1;
        self.0.with(|m| match r {
            LockRole::In1 => m.in1 = false,
            LockRole::In2 => m.in2 = false,
            _ => {}
        });
        Ok(())
    }
}

impl embedded_hal::digital::InputPin for LockPin {
    fn is_high(&mut self) -> Result<bool, Self::Error> {
        let r = self.1;
        Ok(self.0.with(|m| match r {
            LockRole::LockedSw => m.pos_nm < LOCK_TRAVEL_UM * 1_000,
            LockRole::ReleasedSw => m.pos_nm > 0,
            LockRole::In1 => m.in1,
            LockRole::In2 => m.in2,
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
    fn travels_between_switches_in_400ms() {
        let clk = SimClock::new();
        let l = SimLock::new_locked(clk.clone());
        let (mut in2, mut locked, mut released) = (l.in2(), l.locked_switch(), l.released_switch());
        assert!(locked.is_low().unwrap() && released.is_high().unwrap());
        in2.set_high().unwrap();
        clk.advance_ns(399_000_000);
        assert!(locked.is_high().unwrap() && released.is_high().unwrap());
        clk.advance_ns(1_000_000);
        assert!(released.is_low().unwrap());
        l.set_fault(LockFault::Stuck);
        let mut in1 = l.in1();
        in2.set_low().unwrap();
        in1.set_high().unwrap();
        clk.advance_ns(1_000_000_000);
        assert!(released.is_low().unwrap(), "stuck: never leaves released");
    }
}
