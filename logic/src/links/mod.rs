//! **Links**: the people and machines that talk to the controller.
//!
//! [`console`] is the technician's serial console; [`modbus`] the PLC's Modbus RTU
//! server; [`ymodem`] and [`update`] receive and check a firmware update over the
//! console. All of them reach the controller only through `crate::machine::Machine`.

pub mod console;
pub mod modbus;
pub mod update;
pub mod ymodem;
