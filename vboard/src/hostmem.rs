//! Memory the board owns and the engine maps over it (`uc_mem_map_ptr`): the code
//! sectors' bytes and SRAM.
//!
//! **The code sectors**: one array the engine maps twice, at the boot alias (0) and at
//! the flash's base, read/execute only, and the board changes in place. The board writes
//! the flash interface's results (a program, an erase) and undoes the engine's raw
//! stores to the sectors here, in the array. Through the engine's own `uc_mem_write` a
//! read-only region is made writable and read-only again for each write, and each
//! change rebuilds the engine's whole memory map (unicorn 2.1.5, uc.c `uc_mem_write`,
//! `readonly_mem`; `phys_page_compact`): six rebuilds for every word a flash program
//! wrote, a fifth of an update's run. The vector table is read here at every exception
//! entry.
//!
//! **SRAM**: the exception frames are stacked and unstacked here, without a walk of the
//! engine's memory map for each (`uc_mem_read`/`uc_mem_write`: 6 % of a run at 20 000
//! interrupts a second), except on a page code has run from, whose translations a store
//! must invalidate: there the board stores through the engine.
//!
//! Mapping a region over the board's own array is the engine's way to share memory, and
//! the array must outlive the engine's mapping of it.
#![allow(unsafe_code)]

use crate::soc::Soc;
use unicorn_engine::{uc_error, Prot, Unicorn};

/// An array of bytes the engine maps (see the module doc).
pub struct HostMem {
    ptr: *mut u8,
    len: usize,
}

impl HostMem {
    /// `len` bytes of `fill` (erased flash: 0xFF; SRAM as the engine maps it: 0).
    pub fn new(len: usize, fill: u8) -> Self {
        let b = vec![fill; len].into_boxed_slice();
        Self {
            ptr: Box::into_raw(b).cast::<u8>(),
            len,
        }
    }

    /// Map the array at `base` in `uc`, with `perms`.
    pub fn map(
        &mut self,
        uc: &mut Unicorn<'_, Soc>,
        base: u64,
        perms: Prot,
    ) -> Result<(), uc_error> {
        // SAFETY: the array is `len` bytes, never reallocated, and lives as long as the
        // engine: the board keeps it in the engine's own data (`Soc::code_mem`,
        // `Soc::sram_mem`), which `Unicorn` drops after it has closed the engine.
        unsafe { uc.mem_map_ptr(base, self.len as u64, perms, self.ptr.cast()) }
    }

    /// The bytes at offset `off` from the array's start, as the engine reads them; false
    /// (and `buf` untouched) if they are not all inside.
    pub fn read(&self, off: usize, buf: &mut [u8]) -> bool {
        if off.checked_add(buf.len()).is_none_or(|end| end > self.len) {
            return false;
        }
        // SAFETY: `off + buf.len() <= len`; as in `write`, nothing else touches it now.
        unsafe { std::ptr::copy_nonoverlapping(self.ptr.add(off), buf.as_mut_ptr(), buf.len()) }
        true
    }

    /// Store `bytes` at offset `off` from the array's start (as much as fits).
    pub fn write(&mut self, off: usize, bytes: &[u8]) {
        let n = bytes.len().min(self.len.saturating_sub(off));
        // SAFETY: `off + n <= len`. The engine touches the array only from translated
        // code on this thread, which does not run while the board does (between runs or
        // in a hook).
        unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), self.ptr.add(off), n) }
    }
}

impl Drop for HostMem {
    fn drop(&mut self) {
        // SAFETY: `ptr` came from `Box::into_raw` of a slice of `len` bytes.
        drop(unsafe { Box::from_raw(std::ptr::slice_from_raw_parts_mut(self.ptr, self.len)) });
    }
}
