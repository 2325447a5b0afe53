//! Firmware entry point for the STM32F407VGTx controller board.
//!
//! The control logic is the `docking_logic` library; this binary is the thin board
//! layer (`board.rs`): safe outputs, clocks, pins, drivers, and the control loop. It is
//! compiled only for `target_os = "none"`; on the host the binary is a stub that says so.
#![cfg_attr(target_os = "none", no_std)]
#![cfg_attr(target_os = "none", no_main)]
// No unwrap, expect, panic or unchecked indexing: [workspace.lints.clippy].

#[cfg(target_os = "none")]
mod board;

#[cfg(not(target_os = "none"))]
fn main() {
    eprintln!(
        "docking-controller is firmware for thumbv7em-none-eabihf: flash it with `cargo board` \
         (see docs/board.md); on the host run `cargo run --release -p hil-sim -- scene nominal`"
    );
    std::process::exit(2);
}
