//! The code sectors' bytes: one array the engine maps twice, at the boot alias (0) and
//! at the flash's base, read/execute only, and the board changes in place.
//!
//! The board writes the flash interface's results (a program, an erase) and undoes the
//! engine's raw stores to the sectors here, in the array. Through the engine's own
//! `uc_mem_write` a read-only region is made writable and read-only again for each
//! write, and each change rebuilds the engine's whole memory map (unicorn 2.1.5, uc.c
//! `uc_mem_write`, `readonly_mem`; `phys_page_compact`): six rebuilds for every word a
//! flash program wrote, a fifth of an update's run. Mapping the regions over the
//! board's own array (`uc_mem_map_ptr`) is the engine's way to share memory, and the
//! only unsafe code of the crate: the array must outlive the engine's mapping of it.
#![allow(unsafe_code)]

use crate::soc::Soc;
use unicorn_engine::{uc_error, Prot, Unicorn};

/// The array (see the module doc).
pub struct CodeMem {
    ptr: *mut u8,
    len: usize,
}

impl CodeMem {
    /// `len` bytes of erased flash (0xFF).
    pub fn new(len: usize) -> Self {
        let b = vec![0xFFu8; len].into_boxed_slice();
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
        // engine: the board keeps it in the engine's own data (`Soc::code_mem`), which
        // `Unicorn` drops after it has closed the engine.
        unsafe { uc.mem_map_ptr(base, self.len as u64, perms, self.ptr.cast()) }
    }

    /// Store `bytes` at offset `off` from the sectors' start (as much as fits).
    pub fn write(&mut self, off: usize, bytes: &[u8]) {
        let n = bytes.len().min(self.len.saturating_sub(off));
        // SAFETY: `off + n <= len`. The engine reads the array only while it runs, on
        // this thread, never while the board writes.
        unsafe { std::ptr::copy_nonoverlapping(bytes.as_ptr(), self.ptr.add(off), n) }
    }
}

impl Drop for CodeMem {
    fn drop(&mut self) {
        // SAFETY: `ptr` came from `Box::into_raw` of a slice of `len` bytes.
        drop(unsafe { Box::from_raw(std::ptr::slice_from_raw_parts_mut(self.ptr, self.len)) });
    }
}
