//! Adaptive-lock actuator driver: a DC gear motor on a lead screw through an H-bridge
//! (IN1 high = toward locked, IN2 high = toward released, both low = off, the safe
//! state). The locked/released end switches are read by the controller with the others.

use embedded_hal::digital::OutputPin;

/// What the lock motor is asked to do.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum LockCmd {
    /// Motor off (both bridge inputs low).
    Off,
    /// Drive toward the locked switch.
    ToLocked,
    /// Drive toward the released switch.
    ToReleased,
}

/// The H-bridge could not be driven.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct LockPinError;

/// The lock motor.
pub struct LockActuator<IN1, IN2> {
    in1: IN1,
    in2: IN2,
    cmd: LockCmd,
}

impl<IN1: OutputPin, IN2: OutputPin> LockActuator<IN1, IN2> {
    /// A lock motor, switched off.
    pub fn new(in1: IN1, in2: IN2) -> Result<Self, LockPinError> {
        let mut l = Self {
            in1,
            in2,
            cmd: LockCmd::ToLocked,
        };
        l.apply(LockCmd::Off)?;
        Ok(l)
    }

    /// Drive as `cmd` says. Off is applied before any direction so the bridge never
    /// sees both inputs high. A command already in force is **driven again** (its
    /// active input set high, the other left alone: no glitch): the E-STOP interrupt
    /// and the stop latch can pull the bridge low behind this driver's back, and once
    /// the latch is re-armed the command must take hold again
    /// (`lock_command_is_reasserted_after_the_stop_latch_releases`).
    pub fn apply(&mut self, cmd: LockCmd) -> Result<(), LockPinError> {
        if cmd == self.cmd {
            return match cmd {
                LockCmd::Off => Ok(()),
                LockCmd::ToLocked => self.in1.set_high().map_err(|_| LockPinError),
                LockCmd::ToReleased => self.in2.set_high().map_err(|_| LockPinError),
            };
        }
        self.in1.set_low().map_err(|_| LockPinError)?;
        self.in2.set_low().map_err(|_| LockPinError)?;
        self.cmd = LockCmd::Off;
        match cmd {
            LockCmd::Off => {}
            LockCmd::ToLocked => self.in1.set_high().map_err(|_| LockPinError)?,
            LockCmd::ToReleased => self.in2.set_high().map_err(|_| LockPinError)?,
        }
        self.cmd = cmd;
        Ok(())
    }

    /// The command in force.
    pub fn cmd(&self) -> LockCmd {
        self.cmd
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::hal::test_pin::CellPin as Pin;
    use core::cell::Cell;

    #[test]
    fn lock_command_is_reasserted_after_the_stop_latch_releases() {
        let (a, b) = (Cell::new(false), Cell::new(false));
        let mut l = LockActuator::new(Pin(&a), Pin(&b)).unwrap();
        l.apply(LockCmd::ToLocked).unwrap();
        assert!(a.get() && !b.get());
        a.set(false); // the E-STOP's store to the bridge
        l.apply(LockCmd::ToLocked).unwrap();
        assert!(a.get(), "the command in force takes hold again");
        l.apply(LockCmd::ToReleased).unwrap();
        assert!(!a.get() && b.get());
    }
}
