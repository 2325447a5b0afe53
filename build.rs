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
    // The machine's tuning (guard envelope, hard limit, hold force, nominal
    // load-distance): `hil-sim commission` writes it for another machine; without
    // DOCKING_TUNING the board runs the paper's machine (the library's defaults).
    println!("cargo:rerun-if-env-changed=DOCKING_TUNING");
    let out_dir = PathBuf::from(env::var_os("OUT_DIR").expect("cargo sets OUT_DIR"));
    let tuning = out_dir.join("tuning.rs");
    match env::var_os("DOCKING_TUNING") {
        Some(path) => {
            let shown = PathBuf::from(&path).display().to_string();
            println!("cargo:rerun-if-changed={shown}");
            if let Err(e) = fs::copy(&path, &tuning) {
                // One line naming the file, not a panic's backtrace.
                println!("cargo::error=DOCKING_TUNING={shown}: {e}");
                return;
            }
        }
        None => fs::write(
            &tuning,
            "/// The paper's machine: the library's defaults.\n\
             pub fn apply(_cfg: &mut docking_logic::controller::ControllerConfig) {}\n",
        )
        .expect("write the default tuning"),
    }
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=odometer-guard.x");
    println!("cargo:rerun-if-changed=persist.x");
    println!("cargo:rerun-if-changed=hot.x");
    println!("cargo:rerun-if-changed=build.rs");
    if env::var("CARGO_CFG_TARGET_OS").as_deref() != Ok("none") {
        return;
    }
    let out = out_dir;
    fs::copy("memory.x", out.join("memory.x")).expect("copy memory.x");
    fs::copy("odometer-guard.x", out.join("odometer-guard.x")).expect("copy odometer-guard.x");
    fs::copy("persist.x", out.join("persist.x")).expect("copy persist.x");
    fs::copy("hot.x", out.join("hot.x")).expect("copy hot.x");
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rustc-link-arg-bins=--nmagic");
    // Before link.x: its input sections (the safety path's handlers) must be taken before
    // link.x's `*(.text .text.*)` takes every function (hot.x).
    println!("cargo:rustc-link-arg-bins=-Thot.x");
    println!("cargo:rustc-link-arg-bins=-Tlink.x");
    println!("cargo:rustc-link-arg-bins=-Tdefmt.x");
    println!("cargo:rustc-link-arg-bins=-Todometer-guard.x");
    println!("cargo:rustc-link-arg-bins=-Tpersist.x");
    // Identical code folding (issue 20): functions with the same bytes are kept once
    // (closures' vtable shims, compiler_builtins' aligned memclr/memcpy entry points):
    // -924 B of flash, nothing executed differently. Rust promises no distinct
    // function addresses, and the image compares none.
    println!("cargo:rustc-link-arg-bins=--icf=all");
}
