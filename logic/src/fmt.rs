//! Crate-internal logging macros, after embassy-sync's `fmt.rs`.
//!
//! With the `defmt` feature (the board turns it on) they forward to `defmt` (RTT);
//! without it, to the `log` facade, so the library builds and tests on the host without
//! defmt's linker symbols (a `defmt::` call in host-linked code fails with undefined
//! `_defmt_*`).
//! Format strings must therefore use only `{}` / `{:?}`, which both back-ends accept,
//! and arguments must implement `defmt::Format` (board) and `Debug`/`Display` (host).
#![allow(unused_macros)]

macro_rules! info {
    ($($arg:tt)*) => {{
        #[cfg(feature = "defmt")]
        ::defmt::info!($($arg)*);
        #[cfg(not(feature = "defmt"))]
        ::log::info!($($arg)*);
    }};
}

macro_rules! warn {
    ($($arg:tt)*) => {{
        #[cfg(feature = "defmt")]
        ::defmt::warn!($($arg)*);
        #[cfg(not(feature = "defmt"))]
        ::log::warn!($($arg)*);
    }};
}

macro_rules! error {
    ($($arg:tt)*) => {{
        #[cfg(feature = "defmt")]
        ::defmt::error!($($arg)*);
        #[cfg(not(feature = "defmt"))]
        ::log::error!($($arg)*);
    }};
}

macro_rules! debug {
    ($($arg:tt)*) => {{
        #[cfg(feature = "defmt")]
        ::defmt::debug!($($arg)*);
        #[cfg(not(feature = "defmt"))]
        ::log::debug!($($arg)*);
    }};
}
