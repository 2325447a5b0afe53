//! The engine's TLB fill, the board's: data pages without execute (all but the SRAM
//! pages code runs from), so that stores to SRAM stay on the engine's fast path.
//!
//! **Why.** With the MPU off, QEMU's MMU model of an M profile grants execute to every
//! page of the default map below 0x4000_0000 (ARMv7-M B3.1), the stack's and `.bss`'s
//! too, and unicorn 2.1.5 never marks a TLB entry that has a code address dirty
//! (cputlb.c `notdirty_write`; its dirty bitmap is a stub: `tlb_protect_code` does
//! nothing, so an executable entry is how it sees self-modifying code). Every store to
//! SRAM and to the CCM went through the engine's slow path: `store_helper`, two
//! memory-map lookups, the self-modifying-code check. That was 37 % of the CPU time of
//! `overload --flood` (13.3 s → 8.4 s with the same JSON).
//!
//! **How.** The engine's virtual-TLB mode (`UC_TLB_VIRTUAL`) calls
//! `unicorn_fill_tlb_arm` to fill a TLB entry. unicorn's own (qemu/softmmu/unicorn_vtlb.c)
//! calls `cpu_restore_state` at every fill, and the translated code goes on running
//! after it: a fill inside a Thumb IT block leaves the IT bits the translator had zeroed
//! (translate.c `arm_tr_tb_start`) set in the CPU state after the block, and the next
//! block runs conditional. The virtual board saw it: `overload --flood --cpi 3` hit an
//! undefined instruction in `write_str_escaped`, and `overload --flood` ran 413
//! instructions more. So the board defines the symbol itself, and the linker takes it
//! before unicorn's (unicorn_vtlb.c's object defines nothing else the engine needs, so it
//! is never pulled out of the archive): a fetch is filled by the CPU's own MMU model
//! (`arm_cpu_tlb_fill`, as in the engine's default mode: the same permissions, the same
//! faults), a load or a store by a read/write entry of its page. [`fills`] counts the
//! fills, and `Board` refuses to go on if the engine never called this one.
//!
//! **Self-modifying code** stays seen. Only SRAM pages granted EXEC (a RAM function's,
//! `Board::grant_sram_exec`) and the code sectors hold translations. A load or a store to
//! a granted page is filled by the CPU's own fill too ([`mark_executable`]): its entry
//! keeps a code address, so every store to the page goes through the slow path and
//! invalidates what it overwrites, as before. (A read/write entry would do that for its
//! first store only: `tlb_set_dirty` then clears the check for the whole page, and a
//! second copy of `.data` over a RAM function, after a reset into another build, would
//! have run the old translation. Found by review; no scene copies different bytes there.)
//! The code sectors' stores all reach the board's flash hook, whose presence keeps their
//! entries checked (`uc_mem_hook_installed`).
#![allow(unsafe_code)]

use std::ffi::c_void;
use std::sync::atomic::{AtomicU64, Ordering};

/// The engine's page (ARM, an M profile: 1 KiB; `Board::new` checks it).
pub const PAGE: u32 = 1024;

const PAGE_READ: i32 = 1;
const PAGE_WRITE: i32 = 2;
/// `MMUAccessType::MMU_INST_FETCH`.
const MMU_INST_FETCH: i32 = 2;

static FILLS: AtomicU64 = AtomicU64::new(0);

/// SRAM's pages any board of this process has made executable, bit n for page n: a
/// superset of each board's own (the same image puts its RAM functions on the same
/// pages), which costs a board only the fast path of a page it does not execute.
static SRAM_EXEC: [AtomicU64; 2] = [AtomicU64::new(0), AtomicU64::new(0)];

/// The SRAM page of `addr`, if it is in SRAM.
fn sram_page(addr: u32) -> Option<usize> {
    let page = (addr.wrapping_sub(crate::cpu::SRAM) / PAGE) as usize;
    (page < (crate::cpu::SRAM_SIZE / PAGE) as usize).then_some(page)
}

/// The SRAM page at `addr` is executable from now on: its loads and stores are filled by
/// the CPU's own fill (see the module doc). Call it before the engine runs again.
pub fn mark_executable(addr: u32) {
    if let Some(page) = sram_page(addr) {
        SRAM_EXEC[page / 64].fetch_or(1 << (page % 64), Ordering::Relaxed);
    }
}

/// Whether the SRAM page at `addr` may hold code (any board of this process made it
/// executable).
pub fn executable(addr: u32) -> bool {
    sram_page(addr)
        .is_some_and(|page| SRAM_EXEC[page / 64].load(Ordering::Relaxed) & (1 << (page % 64)) != 0)
}

/// Fills made by [`unicorn_fill_tlb_arm`] in this process (0 after an engine ran: the
/// linker took unicorn's).
pub fn fills() -> u64 {
    FILLS.load(Ordering::Relaxed)
}

extern "C" {
    // qemu/accel/tcg/cputlb.c: `void tlb_set_page(CPUState *cpu, target_ulong vaddr,
    // hwaddr paddr, int prot, int mmu_idx, target_ulong size)`; ARM's target_ulong is
    // 32 bits, hwaddr 64.
    fn tlb_set_page_arm(
        cpu: *mut c_void,
        vaddr: u32,
        paddr: u64,
        prot: i32,
        mmu_idx: i32,
        size: u32,
    );
    // qemu/target/arm/tlb_helper.c: `bool arm_cpu_tlb_fill(CPUState *cs, vaddr address,
    // int size, MMUAccessType access_type, int mmu_idx, bool probe, uintptr_t retaddr)`.
    fn arm_cpu_tlb_fill_arm(
        cs: *mut c_void,
        address: u64,
        size: i32,
        access_type: i32,
        mmu_idx: i32,
        probe: bool,
        retaddr: usize,
    ) -> bool;
}

/// The engine's TLB fill in `UC_TLB_VIRTUAL` mode (the signature of unicorn_vtlb.c's
/// `unicorn_fill_tlb`).
///
/// # Safety
///
/// Called by the engine only, with its CPU, during a run.
#[no_mangle]
pub unsafe extern "C" fn unicorn_fill_tlb_arm(
    cs: *mut c_void,
    address: u64,
    size: i32,
    access_type: i32,
    mmu_idx: i32,
    probe: bool,
    retaddr: usize,
) -> bool {
    FILLS.fetch_add(1, Ordering::Relaxed);
    if access_type == MMU_INST_FETCH || executable(address as u32) {
        // SAFETY: the engine's own fill, with the arguments the engine gave.
        return unsafe {
            arm_cpu_tlb_fill_arm(cs, address, size, access_type, mmu_idx, probe, retaddr)
        };
    }
    let page = address as u32 & !(PAGE - 1);
    // SAFETY: `cs` is the engine's CPU; the entry maps the page to itself (the board
    // has no MMU), for the index the engine asked for, one page long.
    unsafe {
        tlb_set_page_arm(
            cs,
            page,
            u64::from(page),
            PAGE_READ | PAGE_WRITE,
            mmu_idx,
            PAGE,
        )
    };
    true
}
