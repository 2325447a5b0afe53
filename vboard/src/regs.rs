//! Batched register transfers: several of the core's registers in one call into the
//! engine (`uc_reg_read_batch`, `uc_reg_write_batch`), in the order given.
//!
//! Exception entry and return move about a dozen registers each, and a taken interrupt
//! (20 000 a second while the axis moves) did it one `uc_reg_read`/`uc_reg_write` at a
//! time: each call enters the engine, checks its state and leaves it again. A batch
//! does the same transfers, register by register in the same order, through one call.
//! The PC is not written here: a single write of it also tells the engine not to sync
//! it back on the way out of the block (`skip_sync_pc_on_exit`), which the batch does
//! not.
#![allow(unsafe_code)]

use std::ffi::c_void;
use unicorn_engine::{uc_error, RegisterARM, Unicorn};

/// The values of `regs` (32-bit registers; 0 for all if the engine refuses one, as a
/// single read's caller takes 0).
pub fn read<D, const N: usize>(uc: &Unicorn<'_, D>, regs: [RegisterARM; N]) -> [u32; N] {
    let ids: [i32; N] = regs.map(i32::from);
    let mut vals = [0u64; N];
    let mut ptrs: [*mut c_void; N] = [std::ptr::null_mut(); N];
    for (p, v) in ptrs.iter_mut().zip(vals.iter_mut()) {
        *p = (v as *mut u64).cast();
    }
    // SAFETY: `ids` and `ptrs` hold N entries each; every pointer is to a live u64, and
    // the engine writes at most 4 bytes through it for these registers (ARM's
    // `reg_read`: 32-bit values; no register wider than 64 bits is ever passed).
    let r = unsafe {
        unicorn_engine::uc_reg_read_batch(
            uc.get_handle(),
            ids.as_ptr(),
            ptrs.as_mut_ptr(),
            N as i32,
        )
    };
    if r != uc_error::OK {
        return [0; N];
    }
    vals.map(|v| v as u32)
}

/// Write each `(register, value)` in order. Not the PC (see the module's doc).
pub fn write<D, const N: usize>(uc: &mut Unicorn<'_, D>, regs: [(RegisterARM, u32); N]) {
    debug_assert!(regs.iter().all(|&(r, _)| r != RegisterARM::PC));
    let ids: [i32; N] = regs.map(|(r, _)| i32::from(r));
    let vals: [u64; N] = regs.map(|(_, v)| u64::from(v));
    let mut ptrs: [*mut c_void; N] = [std::ptr::null_mut(); N];
    for (p, v) in ptrs.iter_mut().zip(vals.iter()) {
        *p = (v as *const u64).cast_mut().cast();
    }
    // SAFETY: as in `read`; the engine only reads through the pointers (4 bytes each).
    let _ = unsafe {
        unicorn_engine::uc_reg_write_batch(uc.get_handle(), ids.as_ptr(), ptrs.as_ptr(), N as i32)
    };
}
