//! # vboard — the virtual board
//!
//! Runs the **unmodified release image** of the docking controller on an emulated
//! STM32F407 (the unicorn engine for the Cortex-M4 core, register-level models of the
//! peripherals the image uses), its pins wired to the simulated machine of `hil-sim`.
//!
//! * [`cpu`]: the core, time, exceptions, sleep, reset;
//! * [`hostmem`]: memory the board owns and the engine maps (the code sectors, SRAM;
//!   with the engine's batched register transfers in [`regs`] and its TLB fill in [`tlb`],
//!   the crate's unsafe code);
//! * [`soc`]: the bus map, events, interrupt lines, pins;
//! * [`periph`]: one model per peripheral;
//! * [`world`]: the board's wiring to hil-sim's devices;
//! * [`rtt`]: the defmt log, read over RTT as a probe would;
//! * [`scene`]: the scenes of `vboard scene`;
//! * [`realtime`]: the control step's period, the watchdog's feeding and the E-STOP's
//!   reaction, measured on the peripheral models;
//! * [`sweep`]: scenes over seeds and timing models, the worst figures;
//! * [`skip`]: polling loops recognised and jumped over, exactly.
//!
//! GPL-2.0 (it links unicorn); nothing of the firmware depends on it.

pub mod cli;
pub mod cpu;
pub mod hostmem;
pub mod image;
pub mod loops;
pub mod periph;
pub mod poller;
pub mod realtime;
pub mod regs;
pub mod rtt;
pub mod scene;
pub mod serve;
pub mod skip;
pub mod soc;
pub mod swap;
pub mod sweep;
pub mod time;
pub mod tlb;
pub mod update;
pub mod world;
