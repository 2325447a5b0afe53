//! The firmware image: the release ELF, loaded the way a probe flashes it (every
//! loadable segment at its physical address: code, constants and the initial values
//! of `.data` into flash), plus the symbols the board needs (the RTT control block).

use object::{Object, ObjectSegment, ObjectSymbol};

use crate::periph::flash::{FLASH_BASE, ODOMETER_BASE};

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
    symbols: Vec<(String, u32, u32)>,
}

impl Image {
    /// Load `path`. Errors: unreadable, not an ELF, a segment outside the code flash.
    pub fn load(path: &str) -> Result<Self, String> {
        let elf = std::fs::read(path).map_err(|e| {
            format!("cannot read firmware image {path}: {e} (build it with `cargo build --release --target thumbv7em-none-eabihf` at the repository root)")
        })?;
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
                symbols.push((name.to_string(), s.address() as u32, s.size() as u32));
            }
        }
        let rtt = symbols
            .iter()
            .find(|(n, _, _)| n == "_SEGGER_RTT")
            .map(|&(_, a, _)| a);
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
            .find(|(n, _, _)| n == name)
            .map(|&(_, a, s)| (a, s))
    }

    /// Address and size of the first symbol whose (mangled) name contains `part`.
    pub fn symbol_containing(&self, part: &str) -> Option<(u32, u32)> {
        self.symbols
            .iter()
            .find(|(n, _, s)| *s > 0 && n.contains(part))
            .map(|&(_, a, s)| (a, s))
    }

    /// The function containing `addr` (for fault reports), by symbol size.
    pub fn function_at(&self, addr: u32) -> Option<&str> {
        let a = addr & !1;
        self.symbols
            .iter()
            .filter(|(_, s, n)| *n > 0 && (s & !1) <= a && a < (s & !1) + n)
            .min_by_key(|(_, _, n)| *n)
            .map(|(name, _, _)| name.as_str())
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

/// The default image: the release build at the repository root.
pub fn default_path() -> String {
    concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../target/thumbv7em-none-eabihf/release/docking-controller"
    )
    .to_string()
}
