#!/usr/bin/env bash
# Flash a board with a probe: the bootloader (sector 0, boot/) and the application behind
# it (0x08008000), then run the application with its defmt log (issue 21,
# docs/update.md). A new board needs both; `cargo board` alone reflashes the application
# and leaves the bootloader and its state sector as they are.
#
#   bash tools/flash-board.sh        (probe-rs: cargo install probe-rs-tools)
set -euo pipefail
cd "$(dirname "$0")/.."
CHIP=STM32F407VGTx
(cd boot && cargo build --release)
cargo build --release --target thumbv7em-none-eabihf
probe-rs download --chip "$CHIP" boot/target/thumbv7em-none-eabihf/release/docking-boot
exec cargo board
