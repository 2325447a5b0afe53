//! The firmware image: the release ELF, loaded the way a probe flashes it (every
//! loadable segment at its physical address: code, constants and the initial values
//! of `.data` into flash), plus the symbols the board needs (the RTT control block).

use object::{Object, ObjectSegment, ObjectSymbol};

use crate::periph::flash::{FLASH_BASE, ODOMETER_BASE};
use update_layout::layout::{ACTIVE_BASE, BOOT_LEN, STATE_BASE, STATE_LEN};

/// A loaded image.
pub struct Image {
    /// The ELF file.
    pub elf: Vec<u8>,
    /// Path it came from.
    pub path: String,
    /// Flash contents from `FLASH_BASE` up to the odometer sectors (0xFF where nothing
    /// is loaded).
    pub flash: Vec<u8>,
    /// Bytes of flash the image occupies (its highest loaded address − base).
    pub flash_used: u32,
    /// Address of `_SEGGER_RTT`, if the image has one.
    pub rtt: Option<u32>,
    /// Name, address, size, and whether it is a function (`STT_FUNC`: what
    /// [`Image::function_at`] names; the `.defmt` section's symbols are not, and start at
    /// address 0).
    symbols: Vec<(String, u32, u32, bool)>,
}

impl Image {
    /// Load `path`. Errors: unreadable, not an ELF, a segment outside the code flash,
    /// and — for the default image ([`default_path`]) — an image older than a source it
    /// is built from (a stale build would be tested silently).
    pub fn load(path: &str) -> Result<Self, String> {
        if path == default_path() {
            let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("..");
            if let Some(src) = newer_source(std::path::Path::new(path), &root) {
                return Err(format!(
                    "firmware image {path} is older than {} : rebuild it with `cargo build --release --target thumbv7em-none-eabihf` at the repository root",
                    src.display()
                ));
            }
        }
        let elf = std::fs::read(path).map_err(|e| {
            format!("cannot read firmware image {path}: {e} (build it with `cargo build --release --target thumbv7em-none-eabihf` at the repository root)")
        })?;
        let img = Self::from_bytes(elf, path)?;
        if img.behind_bootloader() {
            let boot = Self::load_bootloader(&bootloader_path())?;
            return img.under_bootloader(&boot);
        }
        Ok(img)
    }

    /// Whether this is an application linked behind the bootloader (nothing below
    /// ACTIVE, a vector table at its first address: update-layout's map): a probe
    /// flashes it together with the bootloader, and so does [`Image::load`].
    pub fn behind_bootloader(&self) -> bool {
        let active = (ACTIVE_BASE - FLASH_BASE) as usize;
        self.flash[..active].iter().all(|&b| b == 0xFF)
            && self.flash[active..active + 8].iter().any(|&b| b != 0xFF)
    }

    /// Load the bootloader image `path` (`boot/`'s release build by default,
    /// [`bootloader_path`]); the default is refused when older than its sources.
    pub fn load_bootloader(path: &str) -> Result<Self, String> {
        let build = "build it with `cargo build --release` in boot/";
        if path == bootloader_default_path() {
            let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../boot");
            if let Some(src) = newer_file(
                std::path::Path::new(path),
                // The partition map it is built on (update-layout) too.
                &[root.join("src"), root.join("../update-layout/src")],
                &["Cargo.toml", "Cargo.lock", "build.rs", "memory.x"].map(|f| root.join(f)),
            ) {
                return Err(format!(
                    "bootloader image {path} is older than {} : {build}",
                    src.display()
                ));
            }
        }
        let elf = std::fs::read(path)
            .map_err(|e| format!("cannot read bootloader image {path}: {e} ({build})"))?;
        Self::from_bytes(elf, path)
    }

    /// Load an ELF from memory.
    pub fn from_bytes(elf: Vec<u8>, path: &str) -> Result<Self, String> {
        let file =
            object::File::parse(&*elf).map_err(|e| format!("{path}: not an ELF file: {e}"))?;
        let code_len = (ODOMETER_BASE - FLASH_BASE) as usize;
        let mut flash = vec![0xFFu8; code_len];
        let mut used = 0u32;
        for seg in file.segments() {
            let (off, size) = seg.file_range();
            if size == 0 {
                continue;
            }
            let data = seg.data().map_err(|e| format!("{path}: segment: {e}"))?;
            // Physical (load) address: what a probe programs.
            let paddr = match &file {
                object::File::Elf32(f) => {
                    let _ = off;
                    f.elf_program_headers()
                        .iter()
                        .find(|ph| {
                            use object::read::elf::ProgramHeader;
                            ph.p_offset(f.endian()) as u64 == off
                                && ph.p_filesz(f.endian()) as u64 == size
                        })
                        .map(|ph| {
                            use object::read::elf::ProgramHeader;
                            ph.p_paddr(f.endian()) as u64
                        })
                        .unwrap_or(seg.address())
                }
                _ => return Err(format!("{path}: not a 32-bit ARM ELF")),
            };
            let start = paddr
                .checked_sub(FLASH_BASE as u64)
                .filter(|s| s + size <= code_len as u64)
                .ok_or_else(|| {
                    format!("{path}: a segment loads at {paddr:#x}, outside the code flash (sectors 0-9)")
                })?;
            flash[start as usize..(start + size) as usize].copy_from_slice(data);
            used = used.max((start + size) as u32);
        }
        let mut symbols = Vec::new();
        for s in file.symbols() {
            if let Ok(name) = s.name() {
                let func = s.kind() == object::SymbolKind::Text;
                symbols.push((name.to_string(), s.address() as u32, s.size() as u32, func));
            }
        }
        let rtt = symbols
            .iter()
            .find(|(n, ..)| n == "_SEGGER_RTT")
            .map(|&(_, a, ..)| a);
        Ok(Self {
            elf,
            path: path.to_string(),
            flash,
            flash_used: used,
            rtt,
            symbols,
        })
    }

    /// Address and size of symbol `name`.
    pub fn symbol(&self, name: &str) -> Option<(u32, u32)> {
        self.symbols
            .iter()
            .find(|(n, ..)| n == name)
            .map(|&(_, a, s, _)| (a, s))
    }

    /// Address and size of the first symbol whose (mangled) name contains `part`.
    pub fn symbol_containing(&self, part: &str) -> Option<(u32, u32)> {
        self.symbols
            .iter()
            .find(|(n, _, s, _)| *s > 0 && n.contains(part))
            .map(|&(_, a, s, _)| (a, s))
    }

    /// The function containing `addr` (for fault reports), by symbol size. Functions
    /// only: the `.defmt` section's strings are symbols too, at addresses from 0, and a
    /// report with no masked window (its site 0) named one of them.
    pub fn function_at(&self, addr: u32) -> Option<&str> {
        let a = addr & !1;
        self.symbols
            .iter()
            .filter(|(_, s, n, func)| *func && *n > 0 && (s & !1) <= a && a < (s & !1) + n)
            .min_by_key(|(_, _, n, _)| *n)
            .map(|(name, ..)| name.as_str())
    }

    /// This image (an application linked behind the bootloader, at ACTIVE's first
    /// address) with the bootloader image `boot` in sector 0, as a probe flashes the
    /// pair: sectors 0 and 1 (the bootloader and its state) must be blank in this image,
    /// and `boot` must load nothing past its sector. The symbols (the RTT control block)
    /// stay this image's.
    pub fn under_bootloader(mut self, boot: &Image) -> Result<Self, String> {
        const BOOT_END: usize = (STATE_BASE + STATE_LEN - FLASH_BASE) as usize;
        if self.flash[..BOOT_END].iter().any(|&b| b != 0xFF) {
            return Err(format!(
                "{}: the application loads into sectors 0-1 (linked at 0x08000000): link it behind the bootloader, at {ACTIVE_BASE:#010x}",
                self.path
            ));
        }
        if boot.flash_used > BOOT_LEN {
            return Err(format!(
                "{}: the bootloader loads past sector 0 ({} B)",
                boot.path, boot.flash_used
            ));
        }
        self.flash[..BOOT_END].copy_from_slice(&boot.flash[..BOOT_END]);
        Ok(self)
    }

    /// Write `bytes` into the flash at `addr` before the board runs (a state sector, an
    /// update in the DFU partition, a test's application), as a probe would.
    pub fn put(&mut self, addr: u32, bytes: &[u8]) -> Result<(), String> {
        let start = addr
            .checked_sub(FLASH_BASE)
            .map(|s| s as usize)
            .filter(|s| s + bytes.len() <= self.flash.len())
            .ok_or_else(|| format!("{addr:#x} + {} B: outside the code flash", bytes.len()))?;
        self.flash[start..start + bytes.len()].copy_from_slice(bytes);
        self.flash_used = self.flash_used.max((start + bytes.len()) as u32);
        Ok(())
    }

    /// The initial stack pointer and reset vector (words 0 and 1 of the vector table).
    pub fn reset_vector(&self) -> (u32, u32) {
        let w = |i: usize| {
            u32::from_le_bytes([
                self.flash[i],
                self.flash[i + 1],
                self.flash[i + 2],
                self.flash[i + 3],
            ])
        };
        (w(0), w(4))
    }
}

/// A source of the image (under `root`: `src/` and the logic crate's `logic/src/`, the
/// manifests and lock file, the build script, the linker scripts) changed after the
/// image `elf` was built; `None` when
/// the image is newer than all of them, or when it is missing (the load says so).
pub fn newer_source(elf: &std::path::Path, root: &std::path::Path) -> Option<std::path::PathBuf> {
    newer_file(
        elf,
        &[
            root.join("src"),
            root.join("logic/src"),
            root.join("update-layout/src"),
        ],
        &[
            "Cargo.toml",
            "logic/Cargo.toml",
            "Cargo.lock",
            "build.rs",
            "memory.x",
            "odometer-guard.x",
            "persist.x",
            "hot.x",
        ]
        .map(|f| root.join(f)),
    )
}

/// The first of `files`, or of the files under `dirs`, modified after `elf` was built.
fn newer_file(
    elf: &std::path::Path,
    dirs: &[std::path::PathBuf],
    files: &[std::path::PathBuf],
) -> Option<std::path::PathBuf> {
    let built = std::fs::metadata(elf).and_then(|m| m.modified()).ok()?;
    let mut stack: Vec<std::path::PathBuf> = dirs.to_vec();
    let mut files: Vec<std::path::PathBuf> = files.to_vec();
    while let Some(dir) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                files.push(p);
            }
        }
    }
    files.into_iter().find(|f| {
        std::fs::metadata(f)
            .and_then(|m| m.modified())
            .is_ok_and(|t| t > built)
    })
}

/// The default image: the release build at the repository root.
pub fn default_path() -> String {
    concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../target/thumbv7em-none-eabihf/release/docking-controller"
    )
    .to_string()
}

/// The bootloader's release image (`boot/`), the one CI builds.
pub fn bootloader_default_path() -> String {
    concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../boot/target/thumbv7em-none-eabihf/release/docking-boot"
    )
    .to_string()
}

/// The bootloader image an application behind it is loaded with: `VBOARD_BOOTLOADER`,
/// or [`bootloader_default_path`].
pub fn bootloader_path() -> String {
    std::env::var("VBOARD_BOOTLOADER").unwrap_or_else(|_| bootloader_default_path())
}

#[cfg(test)]
mod stale_tests {
    use super::newer_source;
    use std::time::{Duration, SystemTime};

    #[test]
    fn an_image_older_than_a_source_is_found_stale() {
        let root = std::env::temp_dir().join(format!("vboard-stale-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        std::fs::create_dir_all(root.join("src/board")).unwrap();
        let t0 = SystemTime::now() - Duration::from_secs(100);
        let touch = |p: &std::path::Path, t: SystemTime| {
            std::fs::write(p, b"x").unwrap();
            std::fs::File::options()
                .write(true)
                .open(p)
                .unwrap()
                .set_modified(t)
                .unwrap();
        };
        let elf = root.join("image.elf");
        touch(&root.join("src/main.rs"), t0);
        touch(&root.join("Cargo.toml"), t0);
        touch(&elf, t0 + Duration::from_secs(10));
        assert_eq!(newer_source(&elf, &root), None);
        // A board file edited after the build: stale, and named.
        let changed = root.join("src/board/flash.rs");
        touch(&changed, t0 + Duration::from_secs(20));
        assert_eq!(newer_source(&elf, &root), Some(changed));
        // Rebuilt: fresh again.
        touch(&elf, t0 + Duration::from_secs(30));
        assert_eq!(newer_source(&elf, &root), None);
        // A logic file edited after the build: stale too (the image links the logic).
        std::fs::create_dir_all(root.join("logic/src")).unwrap();
        let logic = root.join("logic/src/guard.rs");
        touch(&logic, t0 + Duration::from_secs(40));
        assert_eq!(newer_source(&elf, &root), Some(logic));
        touch(&elf, t0 + Duration::from_secs(50));
        assert_eq!(newer_source(&elf, &root), None);
        // No image at all: the load reports that, not staleness.
        assert_eq!(newer_source(&root.join("missing.elf"), &root), None);
        let _ = std::fs::remove_dir_all(&root);
    }
}
