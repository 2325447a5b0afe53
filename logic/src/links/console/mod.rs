//! Technician console, input side: bytes from a serial terminal → validated lines →
//! parsed commands, plus the maintenance-PIN gate and a JSON writer for replies.
//!
//! The console is polled from the control loop, so everything here is built to never
//! delay it or fail on input:
//!
//! * **Bounded work.** [`line::LineReader::push`] does O(1) work per byte except at a
//!   line terminator, where it does O(N) for an N-byte line; the controller reads at
//!   most [`line::MAX_BYTES_PER_POLL`] bytes per control step, so input floods are
//!   absorbed by the UART/ring buffer, never by the control loop. [`parse::parse`] is
//!   O(line length). A PIN check ([`auth`]) costs a fixed, documented number of
//!   SHA-256 compressions and is refused without hashing while locked out.
//! * **No allocation, no panic.** Fixed-capacity buffers only; every input (any byte
//!   sequence) yields a line, an error or nothing, never a panic.
//! * **No control characters echoed.** Error messages ([`line::LineError`],
//!   [`parse::ParseError`], [`auth::AuthError`]) display as one line of printable
//!   ASCII; JSON output ([`json`]) escapes control characters and stays on one line.
//!
//! Flow: `ConsoleIo::read_byte` → [`line::LineReader::push`] → [`parse::parse`] →
//! the caller executes the [`parse::Command`] (gating state-changing commands with
//! [`auth::MaintenanceAuth`]) and replies, in JSON via [`json::JsonObject`] when asked.

pub mod auth;
mod curve;
pub mod fields;
pub mod json;
pub mod line;
pub mod parse;
mod reports;
pub mod service;
pub mod update;
