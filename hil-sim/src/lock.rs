//! The simulated adaptive-lock actuator: a DC gear motor on a lead screw that moves the
//! homing cone, driven through an H-bridge (IN1 high = toward locked, IN2 high =
//! toward released, both low = stopped, the safe state), with a *locked* and a
//! *released* end switch (active low).
//!
//! Fault: `Stuck` — the screw does not move (seized, motor open-circuit).

use std::cell::Cell;
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

/// The lock's state. Every field is a `Cell` (all are `Copy`): the pins read and drive
/// it several times per control step, and a `Cell` needs no borrow bookkeeping.
#[derive(Debug)]
struct LockModel {
    /// Screw position, nm (exact integration): 0 = released.
    pos_nm: Cell<u64>,
    in1: Cell<bool>,
    in2: Cell<bool>,
    last_ns: Cell<u64>,
    fault: Cell<LockFault>,
}

impl LockModel {
    fn driven(&self) -> bool {
        self.in1.get() != self.in2.get()
    }

    /// Move the screw up to `now`: only a driven screw moves (the pins read it several
    /// times a step, and it is driven 0.8 s of a 58 s cycle); `last_ns` is where its
    /// motion was integrated up to, set when the drive changes ([`LockPin::drive`]).
    #[inline]
    fn update(&self, now: u64) {
        if self.driven() {
            self.integrate(now);
        }
    }

    fn integrate(&self, now: u64) {
        let last = self.last_ns.get();
        if now <= last {
            return; // moved up to now already
        }
        self.last_ns.set(now);
        if self.fault.get() == LockFault::Stuck {
            return;
        }
        // dt ns · v µm/s · 1e-9 s/ns · 1e3 nm/µm = dt·v/1e6 nm
        let d_nm = now.saturating_sub(last) * LOCK_SPEED_UM_PER_S / 1_000_000;
        let max = LOCK_TRAVEL_UM * 1_000;
        let pos = self.pos_nm.get();
        self.pos_nm.set(if self.in1.get() {
            (pos + d_nm).min(max)
        } else {
            pos.saturating_sub(d_nm)
        });
    }
}

/// Handle to the simulated lock.
#[derive(Clone)]
pub struct SimLock {
    model: Rc<LockModel>,
    clock: SimClock,
}

impl SimLock {
    /// A lock that starts locked (the state the machine is parked in).
    pub fn new_locked(clock: SimClock) -> Self {
        let m = LockModel {
            pos_nm: Cell::new(LOCK_TRAVEL_UM * 1_000),
            in1: Cell::new(false),
            in2: Cell::new(false),
            last_ns: Cell::new(clock.now_ns()),
            fault: Cell::new(LockFault::None),
        };
        Self {
            model: Rc::new(m),
            clock,
        }
    }

    /// The model, moved up to now.
    #[inline]
    fn now(&self) -> &LockModel {
        self.model.update(self.clock.now_ns());
        &self.model
    }

    /// Inject or clear a fault.
    pub fn set_fault(&self, fault: LockFault) {
        self.now().fault.set(fault);
    }

    /// Whether the motor is driven now.
    pub fn driven(&self) -> bool {
        self.now().driven()
    }

    /// Screw position, 0 = released, 1 = locked.
    pub fn fraction_locked(&self) -> f64 {
        self.now().pos_nm.get() as f64 / (LOCK_TRAVEL_UM * 1_000) as f64
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

impl LockPin {
    fn drive(&mut self, high: bool) {
        let now = self.0.clock.now_ns();
        let m = self.0.now();
        match self.1 {
            LockRole::In1 => m.in1.set(high),
            LockRole::In2 => m.in2.set(high),
            LockRole::LockedSw | LockRole::ReleasedSw => {}
        }
        // A drive that starts now moves the screw from now.
        m.last_ns.set(now);
    }
}

impl embedded_hal::digital::OutputPin for LockPin {
    fn set_high(&mut self) -> Result<(), Self::Error> {
        self.drive(true);
        Ok(())
    }
    fn set_low(&mut self) -> Result<(), Self::Error> {
        self.drive(false);
        Ok(())
    }
}

impl embedded_hal::digital::InputPin for LockPin {
    fn is_high(&mut self) -> Result<bool, Self::Error> {
        let m = self.0.now();
        Ok(match self.1 {
            LockRole::LockedSw => m.pos_nm.get() < LOCK_TRAVEL_UM * 1_000,
            LockRole::ReleasedSw => m.pos_nm.get() > 0,
            LockRole::In1 => m.in1.get(),
            LockRole::In2 => m.in2.get(),
        })
    }
    fn is_low(&mut self) -> Result<bool, Self::Error> {
        self.is_high().map(|h| !h)
    }
}

/// The locked switch alone: [`LockPin`]'s line with its role fixed by the type, so the
/// controller's read (every control step of a long run) is the check itself.
pub struct LockedSwitch(SimLock);

/// The released switch alone (see [`LockedSwitch`]).
pub struct ReleasedSwitch(SimLock);

impl SimLock {
    /// Locked switch (active low), as its own type.
    pub fn locked_switch_line(&self) -> LockedSwitch {
        LockedSwitch(self.clone())
    }
    /// Released switch (active low), as its own type.
    pub fn released_switch_line(&self) -> ReleasedSwitch {
        ReleasedSwitch(self.clone())
    }
}

input_line!(LockedSwitch, |l| l.now().pos_nm.get()
    < LOCK_TRAVEL_UM * 1_000);
input_line!(ReleasedSwitch, |l| l.now().pos_nm.get() > 0);

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_hal::digital::{InputPin, OutputPin};

    /// The screw is moved only while driven; a drive that starts after a long time
    /// without a read moves it from the drive's start, not from the last read.
    #[test]
    fn a_drive_moves_the_screw_from_its_start() {
        let clk = SimClock::new();
        let l = SimLock::new_locked(clk.clone());
        let (mut in2, mut locked) = (l.in2(), l.locked_switch());
        assert!(locked.is_low().unwrap());
        clk.advance_ns(10_000_000_000);
        in2.set_high().unwrap();
        assert!(locked.is_low().unwrap(), "still locked as the drive starts");
        clk.advance_ns(200_000_000);
        assert!(
            (l.fraction_locked() - 0.5).abs() < 1e-9,
            "{}",
            l.fraction_locked()
        );
    }

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
