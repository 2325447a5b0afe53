//! Link set-up for the firmware image only (after cortex-m-quickstart / embassy).
//!
//! `memory.x` is copied into `OUT_DIR` and the linker scripts are passed with
//! `rustc-link-arg-bins`, and only when building for a bare-metal target, so host
//! builds and tests never see them.
//!
//! Issue 21 (docs/update.md): the FLASH region (ACTIVE) and the image header's place are
//! written here from the shared partition map (`update-layout`), so that the layout
//! switch stays in one place (`active.x`, `image-header.x`); and the public key the
//! updater verifies images with (`update_key.rs`): the integrator's when
//! `DOCKING_UPDATE_KEY` names its file (raw 32 bytes, or the PEM `openssl pkey -pubout`
//! writes), else the test key of `boot/keys/`.
// A build script that cannot copy its linker script must stop the build: panicking is
// how it reports that.
#![allow(clippy::expect_used)]

use std::{env, fs, path::PathBuf};

// The partition map and the image header, from the shared crate's own sources (one
// place for the layout; included rather than a build-dependency so that this script
// still compiles on its own, as host-tests/tests/build_script.rs compiles it).
#[allow(dead_code)]
#[path = "update-layout/src/header.rs"]
mod header;
#[allow(dead_code)]
#[path = "update-layout/src/layout.rs"]
mod layout;
#[path = "update-layout/src/pem.rs"]
mod pem;

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
    if let Err(e) = update_key(&out_dir) {
        println!("cargo::error={e}");
        return;
    }
    println!("cargo:rerun-if-changed=update-layout/src/layout.rs");
    println!("cargo:rerun-if-changed=update-layout/src/header.rs");
    println!("cargo:rerun-if-changed=update-layout/src/pem.rs");
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=odometer-guard.x");
    println!("cargo:rerun-if-changed=persist.x");
    println!("cargo:rerun-if-changed=ccm.x");
    println!("cargo:rerun-if-changed=hot.x");
    println!("cargo:rerun-if-changed=build.rs");
    if env::var("CARGO_CFG_TARGET_OS").as_deref() != Ok("none") {
        return;
    }
    let out = out_dir;
    fs::copy("memory.x", out.join("memory.x")).expect("copy memory.x");
    fs::copy("odometer-guard.x", out.join("odometer-guard.x")).expect("copy odometer-guard.x");
    fs::copy("persist.x", out.join("persist.x")).expect("copy persist.x");
    fs::copy("ccm.x", out.join("ccm.x")).expect("copy ccm.x");
    fs::write(out.join("active.x"), active_x()).expect("write active.x");
    fs::write(out.join("image-header.x"), image_header_x()).expect("write image-header.x");
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
    println!("cargo:rustc-link-arg-bins=-Tccm.x");
    println!("cargo:rustc-link-arg-bins=-Timage-header.x");
    // Identical code folding (issue 20): functions with the same bytes are kept once
    // (closures' vtable shims, compiler_builtins' aligned memclr/memcpy entry points):
    // -924 B of flash, nothing executed differently. Rust promises no distinct
    // function addresses, and the image compares none.
    println!("cargo:rustc-link-arg-bins=--icf=all");
}

/// The FLASH region: ACTIVE, as the shared partition map has it (memory.x includes
/// this). `.text` starts after the image header and the safety path's `.text.hot`:
/// hot.x defines `_stext` after `.text.hot`, which lands after `.image_header` (both
/// are inserted after `.vector_table`; image-header.x's assertions check the header's
/// place).
///
/// The layout is also given to the tools as symbols of the ELF (`__layout_id`,
/// `__active_start`, `__active_end`): `tools/sign-image.sh` checks the image it signs
/// against them rather than against a copy of the map.
fn active_x() -> String {
    use layout::{ACTIVE_BASE, ACTIVE_LEN, LAYOUT};
    format!(
        "/* Written by build.rs from update-layout (the partition map): ACTIVE, layout {}. */\n\
         MEMORY\n{{\n  FLASH : ORIGIN = {ACTIVE_BASE:#010x}, LENGTH = {}K\n}}\n\
         __layout_id = {};\n__active_start = ORIGIN(FLASH);\n\
         __active_end = ORIGIN(FLASH) + LENGTH(FLASH);\n",
        LAYOUT.name(),
        ACTIVE_LEN / 1024,
        LAYOUT.id()
    )
}

/// The image header's section at its fixed offset after the vector table, `.text` after
/// it (update-layout's header.rs). The gap before the header is filled with 0xFF (erased
/// flash) inside the section, so that the image has no hole: `llvm-objcopy -O binary`
/// (the signing tool's) and a probe write the same bytes.
fn image_header_x() -> String {
    use header::{HEADER_LEN, HEADER_OFFSET};
    format!(
        "/* Written by build.rs from update-layout: the image header (version, key id) at a\n\
          * fixed offset after the vector table, for the signing tool and the updater. */\n\
         SECTIONS\n{{\n  .image_header ADDR(.vector_table) + SIZEOF(.vector_table) :\n  {{\n    \
         FILL(0xFFFFFFFF);\n    . = ALIGN({HEADER_OFFSET:#x});\n    __image_header = .;\n    \
         KEEP(*(.image_header));\n  }} > FLASH\n}}\nINSERT AFTER .vector_table;\n\
         ASSERT(__image_header == ORIGIN(FLASH) + {HEADER_OFFSET:#x},\n  \
         \"the image header is not at its place: the vector table reaches it (image-header.x)\");\n\
         ASSERT(ADDR(.image_header) + SIZEOF(.image_header) == ORIGIN(FLASH) + {HEADER_OFFSET:#x} + {HEADER_LEN},\n  \
         \"the image header is not {HEADER_LEN} bytes (image-header.x)\");\n"
    )
}

/// The test key's public half (boot/keys/README.md).
const TEST_KEY_FILE: &str = "boot/keys/test-public-key.bin";

/// `update_key.rs`: `PUBLIC_KEY` (32 bytes) and `TEST_KEY` (whether it is the test key).
fn update_key(out_dir: &std::path::Path) -> Result<(), String> {
    println!("cargo:rerun-if-env-changed=DOCKING_UPDATE_KEY");
    println!("cargo:rerun-if-changed={TEST_KEY_FILE}");
    let test = fs::read(TEST_KEY_FILE).map_err(|e| format!("{TEST_KEY_FILE}: {e}"))?;
    let key = match env::var_os("DOCKING_UPDATE_KEY") {
        Some(path) => {
            let shown = PathBuf::from(&path).display().to_string();
            println!("cargo:rerun-if-changed={shown}");
            let raw = fs::read(&path).map_err(|e| format!("DOCKING_UPDATE_KEY={shown}: {e}"))?;
            public_key(&raw).ok_or_else(|| {
                format!(
                    "DOCKING_UPDATE_KEY={shown}: neither 32 raw bytes nor an ed25519 PEM public key"
                )
            })?
        }
        None => public_key(&test).ok_or("the test key is not 32 bytes")?,
    };
    let is_test = key.as_slice() == test.as_slice();
    fs::write(
        out_dir.join("update_key.rs"),
        format!(
            "/// The ed25519 public key updates are verified with.\n\
             pub const PUBLIC_KEY: [u8; 32] = {key:?};\n\
             /// Whether it is the test key of boot/keys/ (an image it signs proves nothing).\n\
             pub const TEST_KEY: bool = {is_test};\n"
        ),
    )
    .map_err(|e| e.to_string())
}

/// 32 raw bytes, or the PEM of an ed25519 SubjectPublicKeyInfo (the key is its last 32
/// bytes: `30 2a 30 05 06 03 2b 65 70 03 21 00` then the key).
fn public_key(raw: &[u8]) -> Option<[u8; 32]> {
    if let Ok(k) = <[u8; 32]>::try_from(raw) {
        return Some(k);
    }
    let text = std::str::from_utf8(raw).ok()?;
    let mut buf = [0u8; 64];
    let n = pem::der(text, &mut buf)?;
    let der = buf.get(..n)?;
    const SPKI: [u8; 12] = [
        0x30, 0x2a, 0x30, 0x05, 0x06, 0x03, 0x2b, 0x65, 0x70, 0x03, 0x21, 0x00,
    ];
    let (head, key) = der.split_at_checked(12)?;
    if head != SPKI {
        return None;
    }
    key.try_into().ok()
}
