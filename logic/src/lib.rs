//! # docking-logic — control logic of the automatic connector docking controller
//!
//! This crate is the whole control loop of the docking controller, written `no_std`
//! and hardware-free so that the same code runs on the STM32F407 board (the firmware
//! package at the repository's root: `src/main.rs`, `src/board.rs`) and on the host
//! against the simulated HAL in `hil-sim`. No HAL and no RTIC are in its dependency
//! tree; its logging goes to `defmt` with the `defmt` feature (the board's) and to the
//! `log` facade without it.
//!
//! It talks to hardware only through traits: embedded-hal 1.0 (`OutputPin`, `InputPin`,
//! `DelayNs`), `embedded-storage`'s `NorFlash`, and the small traits in [`hal`] for what
//! embedded-hal 1.0 does not cover (monotonic clock, watchdog, step-pulse generator,
//! console byte stream).
//!
//! The physics (machine, four contact phases, the Eq. 7 force profile, the wear model)
//! is restated from He et al., *Polymers* 2025, 17, 2091 in
//! `docs/physics.md`; [`profile`] implements Eq. 7.
//!
//! Units are in names: `_um` micrometres, `_mn` millinewtons, `_us` microseconds,
//! `_steps` motor steps. Fixed-point formats are stated where they are defined.
#![no_std]
#![forbid(unsafe_code)]
// Firmware paths must not panic on input (tests may): [workspace.lints.clippy].

#[macro_use]
mod fmt;

// Grouped by concern (the reader finds a module by its name): `control`, `wear`,
// `storage`, `links`; what all of them use at the top. Each module is also at the
// crate's root under its own name (`docking_logic::controller`, …), its path since
// before the grouping.
pub mod config;
pub mod control;
pub mod diag;
pub mod fixed;
pub mod hal;
pub mod links;
pub mod machine;
pub mod storage;
pub mod wear;

pub use control::{controller, guard, hx711, lock, profile, propulsion, safety, sequencer};
pub use links::{console, modbus, update, ymodem};
pub use storage::{crc, framelog};
pub use wear::{estimate, material, odometer, signature};
