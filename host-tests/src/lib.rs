//! Host tests live in `tests/`; this crate has no code of its own (and is an empty
//! `no_std` crate on bare metal, so a workspace-wide thumb build works).
#![no_std]
