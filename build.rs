//! Link set-up for the firmware image only (after cortex-m-quickstart / embassy).
//!
//! `memory.x` is copied into `OUT_DIR` and the linker scripts are passed with
//! `rustc-link-arg-bins`, and only when building for a bare-metal target, so host
//! builds and tests never see them.
// A build script that cannot copy its linker script must stop the build: panicking is
// how it reports that.
#![allow(clippy::expect_used)]

use std::{env, fs, path::PathBuf};

fn main() {
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=odometer-guard.x");
    println!("cargo:rerun-if-changed=build.rs");
    if env::var("CARGO_CFG_TARGET_OS").as_deref() != Ok("none") {
        return;
    }
    let out = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    fs::copy("memory.x", out.join("memory.x")).expect("copy memory.x");
    fs::copy("odometer-guard.x", out.join("odometer-guard.x")).expect("copy odometer-guard.x");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rustc-link-arg-bins=--nmagic");
    println!("cargo:rustc-link-arg-bins=-Tlink.x");
    println!("cargo:rustc-link-arg-bins=-Tdefmt.x");
    println!("cargo:rustc-link-arg-bins=-Todometer-guard.x");
}
