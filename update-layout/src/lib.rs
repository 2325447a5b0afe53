//! The field update's shared map (issue 21, docs/update.md): the flash partitions
//! ([`layout`], with its one switch between the development and the budget layout), the
//! partitions as embassy-boot sees them ([`part`]: sector-mapped pages), the state
//! record's magics ([`state`]), the image header ([`header`]: version, layout and key
//! id, stamped by the signing tool) and the outputs' safe levels ([`safe`], the stores
//! both images make first at reset). `no_std`, no dependency but `embedded-storage`: the
//! bootloader (`boot/`), the application (its updater, and `memory.x` through build.rs)
//! and the virtual board (`vboard/`) use this one copy.
#![cfg_attr(not(test), no_std)]
#![deny(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

pub mod header;
pub mod layout;
pub mod part;
pub mod pem;
pub mod safe;
pub mod state;
