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

pub mod config;
pub mod console;
pub mod controller;
pub mod crc;
pub mod diag;
pub mod estimate;
pub mod fixed;
pub mod framelog;
pub mod guard;
pub mod hal;
pub mod hx711;
pub mod lock;
pub mod machine;
pub mod material;
pub mod modbus;
pub mod odometer;
pub mod profile;
pub mod propulsion;
pub mod safety;
pub mod sequencer;
pub mod signature;
pub mod storage;
pub mod update;
pub mod ymodem;
