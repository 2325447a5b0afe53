//! **Wear**: what the machine learns of its guide cones.
//!
//! [`odometer`] integrates the Archard wear of every docking in fixed point and keeps
//! it in flash; [`material`] holds each cone material's wear coefficient; [`estimate`]
//! follows the micrometer's bore readings with an uncertainty band and the remaining
//! life; [`signature`] records each docking's force–position curve and judges it by
//! contact phase.

pub mod estimate;
pub mod material;
pub mod odometer;
pub mod signature;
