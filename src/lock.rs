//! Adaptive-lock actuator driver: a DC gear motor on a lead screw through an H-bridge
//! (IN1 high = toward locked, IN2 high = toward released, both low = off, the safe
//! state). The locked/released end switches are read by the controller with the others.

use embedded_hal::digital::OutputPin;

/// What the lock motor is asked to do.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
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
#[cfg_attr(target_os = "none", derive(defmt::Format))]
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

    /// Drive as `cmd` says (no-op if already so). Off is applied before any direction
    /// so the bridge never sees both inputs high.
    pub fn apply(&mut self, cmd: LockCmd) -> Result<(), LockPinError> {
        if cmd == self.cmd {
            return Ok(());
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
