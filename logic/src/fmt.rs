//! Crate-internal logging macros, after embassy-sync's `fmt.rs`.
//!
//! On the board (`target_os = "none"`) they forward to `defmt` (RTT); on the host they
//! forward to the `log` facade, so the library builds and tests without defmt's linker
//! symbols (a `defmt::` call in host-linked code fails with undefined `_defmt_*`).
//! Format strings must therefore use only `{}` / `{:?}`, which both back-ends accept,
//! and arguments must implement `defmt::Format` (board) and `Debug`/`Display` (host).
#![allow(unused_macros)]

macro_rules! info {
    ($($arg:tt)*) => {{
        #[cfg(target_os = "none")]
        ::defmt::info!($($arg)*);
        #[cfg(not(target_os = "none"))]
        ::log::info!($($arg)*);
    }};
}

macro_rules! warn {
    ($($arg:tt)*) => {{
        #[cfg(target_os = "none")]
        ::defmt::warn!($($arg)*);
        #[cfg(not(target_os = "none"))]
        ::log::warn!($($arg)*);
    }};
}

macro_rules! error {
    ($($arg:tt)*) => {{
        #[cfg(target_os = "none")]
        ::defmt::error!($($arg)*);
        #[cfg(not(target_os = "none"))]
        ::log::error!($($arg)*);
    }};
}

macro_rules! debug {
    ($($arg:tt)*) => {{
        #[cfg(target_os = "none")]
        ::defmt::debug!($($arg)*);
        #[cfg(not(target_os = "none"))]
        ::log::debug!($($arg)*);
    }};
}
