//! **Control**: the loop from the load cell to the motors, run once a sample.
//!
//! Sample → guard → phase → odometer → sequencer → motors: [`hx711`] reads the load
//! cell, [`guard`] stops on overload within the sample against [`profile`]'s force
//! profile (Eq. 7) and its contact phases, [`safety`] is the kernel that owns the stop
//! (E-STOP, overload, faults), [`sequencer`] walks pre-alignment, release, insertion,
//! hold, extraction, re-lock and homing, [`propulsion`] and [`lock`] drive the two
//! motors, and [`controller`] is the step that ties them together (and what the
//! console and the Modbus server ask of it, through `crate::machine`).

pub mod controller;
pub mod guard;
pub mod hx711;
pub mod lock;
pub mod profile;
pub mod propulsion;
pub mod safety;
pub mod sequencer;
