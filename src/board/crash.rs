//! What survives a reset in RAM: crash records, the odometer's journal; and the stack's
//! deepest use.
//!
//! A panic or a HardFault writes a [`Crash`] (what and where) into [`CRASH_BLOCK`], in
//! RAM that no reset initialises (`.persist`, at an address fixed across versions:
//! `persist.x`, so that an image updated or rolled back to finds it; the bootloader never
//! touches SRAM), then resets the MCU; the next boot finds it (checked by its CRC),
//! reports it and stores it in flash.
//!
//! A stack overflow runs off the bottom of SRAM (the stack sits below the statics, see
//! `memory.x`) and faults; exception entry cannot stack on an exhausted stack, so the
//! core locks up until the watchdog resets it — no handler runs. It is found at the next
//! boot instead: cortex-m-rt paints the stack at every reset (`paint-stack`), and before
//! that, in `__pre_init`, the guard zone at the bottom ([`STACK_GUARD_B`]) is looked at.
//! If the last run had painted its stack ([`PAINTED`]) and a word there is paint no
//! more, the stack reached its bottom.
//!
//! `__pre_init` also drives every motor and PLC output to its safe level (EN high,
//! STEP, lock IN1/IN2, READY/MATED/FAULT/MAINTENANCE low, as push-pull outputs) as its
//! first instructions after a reset, before RAM initialisation: the outputs are never
//! left to the board's pull resistors for the 2-3 ms `init` takes at 16 MHz.
//!
//! The odometer's journal ([`ODO_JOURNAL`], format in
//! `docking_logic::odometer::Journal`) keeps the counters of the cycle in progress
//! through a reset; the flash snapshot is written only at rest.
//!
//! Layout of the crash block (`#[repr(C)]`, words):
//!
//! ```text
//!  0       4     8                       52        56         60
//!  +-------+-----+-----------------------+---------+----------+
//!  | magic | crc | crash (44 B, diag.rs) | painted | overflow |
//!  +-------+-----+-----------------------+---------+----------+
//!  crc: CRC-32/ISO-HDLC of the 44 crash bytes; overflow: OVERFLOWED when __pre_init
//!  found paint scrubbed in the stack's guard zone
//! ```

use core::mem::MaybeUninit;
use core::ptr::addr_of_mut;

use docking_logic::diag::{Crash, CrashKind, CRASH_LEN};
use docking_logic::odometer::{Journal, JOURNAL_WORDS};

/// A crash is recorded.
const MAGIC: u32 = 0xC4A5_4BAD;
/// The last run painted its stack (set at boot, after cortex-m-rt painted it).
pub const PAINTED: u32 = 0x57AC_0C0C;
/// `__pre_init` found paint scrubbed in the stack's guard zone.
pub const OVERFLOWED: u32 = 0x0F10_0D0D;
/// The guard zone at the stack's bottom, bytes: a run whose stack reached into it is
/// taken as overflowed. A push that would cross the bottom faults before it writes
/// (the lowest address first), so the bottom word itself may still hold paint after an
/// overflow; the exception frames the core then tries to stack (32 or 104 bytes) and
/// the pushes before the faulting one land in the zone.
pub const STACK_GUARD_B: u32 = 128;
/// cortex-m-rt's stack paint.
pub const STACK_PAINT: u32 = 0xCCCC_CCCC;

/// The block.
#[repr(C)]
pub struct CrashBlock {
    magic: u32,
    crc: u32,
    body: [u8; CRASH_LEN],
    painted: u32,
    overflow: u32,
}

/// The block, in RAM no reset initialises.
#[no_mangle]
#[link_section = ".persist.CRASH_BLOCK"]
pub static mut CRASH_BLOCK: MaybeUninit<CrashBlock> = MaybeUninit::uninit();

extern "C" {
    static _stack_end: u32;
    static _stack_start: u32;
}

// Runs before RAM is initialised and before cortex-m-rt paints the stack: look at the
// stack's bottom word while it still holds what the last run left there. Assembly,
// because no Rust may run before RAM initialisation.
update_layout::pre_init_safe_outputs!(
    // Motor and PLC outputs safe first (the macro, update-layout's `safe`: the same
    // stores as the bootloader's and `force_safe_outputs`), before .bss/.data are set up
    // (2-3 ms at 16 MHz): until now only the board's pull resistors held them. Then the
    // stack's bottom, while it still holds what the last run left there.
    "    ldr r0, =CRASH_BLOCK",
    "    ldr r1, [r0, #52]", // painted
    "    ldr r2, ={painted}",
    "    cmp r1, r2",
    "    bne 1f",
    "    ldr r3, =_stack_end",
    "    add r1, r3, #{guard}",
    "    ldr r2, ={paint}",
    "2:  ldr r12, [r3], #4",
    "    cmp r12, r2",
    "    bne 3f",
    "    cmp r3, r1",
    "    blo 2b",
    "    b 1f",
    "3:  ldr r1, ={overflowed}",
    "    str r1, [r0, #56]", // overflow
    "1:  bx lr";
    painted = const PAINTED,
    paint = const STACK_PAINT,
    overflowed = const OVERFLOWED,
    guard = const STACK_GUARD_B,
);

/// Record `c` (from the panic or HardFault handler: no allocation, no panic).
pub fn record(c: &Crash) {
    let body = c.to_bytes();
    let crc = docking_logic::crc::crc32(&body);
    // SAFETY: raw writes into the block (no reference is made); the handlers that call
    // this run with nothing else running after them but the reset.
    unsafe {
        let b = addr_of_mut!(CRASH_BLOCK) as *mut CrashBlock;
        addr_of_mut!((*b).body).write(body);
        addr_of_mut!((*b).crc).write(crc);
        addr_of_mut!((*b).magic).write(MAGIC);
    }
}

/// At boot: the crash the last run left (a valid record, or a stack overflow found by
/// `__pre_init`), once; then mark this run's stack as painted.
pub fn take() -> Option<Crash> {
    // SAFETY: init runs alone; raw reads and writes of the block.
    unsafe {
        let b = addr_of_mut!(CRASH_BLOCK) as *mut CrashBlock;
        let magic = addr_of_mut!((*b).magic).read();
        let crc = addr_of_mut!((*b).crc).read();
        let body = addr_of_mut!((*b).body).read();
        let overflow = addr_of_mut!((*b).overflow).read();
        addr_of_mut!((*b).magic).write(0);
        addr_of_mut!((*b).overflow).write(0);
        addr_of_mut!((*b).painted).write(PAINTED);
        let recorded = (magic == MAGIC && docking_logic::crc::crc32(&body) == crc)
            .then(|| Crash::from_bytes(&body))
            .flatten();
        recorded.or((overflow == OVERFLOWED).then_some(Crash {
            kind: CrashKind::StackOverflow,
            pc: 0,
            lr: 0,
            cfsr: 0,
            hfsr: 0,
            line: 0,
            file: [0; 20],
        }))
    }
}

/// The stack's deepest use so far and its size, bytes (from the paint left).
pub fn stack_usage() -> (u32, u32) {
    // SAFETY: the linker's symbols bound the stack region; reading painted words there
    // (volatile, word by word from the bottom) has no side effect.
    unsafe {
        let bottom = core::ptr::addr_of!(_stack_end) as u32;
        let top = core::ptr::addr_of!(_stack_start) as u32;
        let mut a = bottom;
        while a < top && core::ptr::read_volatile(a as *const u32) == STACK_PAINT {
            a += 4;
        }
        (top - a, top - bottom)
    }
}

/// The odometer's RAM journal ([`Journal`]): two slots, written alternately after every
/// control step, so that a reset in the middle of one update leaves the other (one step
/// older) whole. In `.persist` RAM (`persist.x`), like the crash block.
#[no_mangle]
#[link_section = ".persist.ODO_JOURNAL"]
static mut ODO_JOURNAL: MaybeUninit<[[u32; JOURNAL_WORDS]; 2]> = MaybeUninit::uninit();

/// The slot the next [`journal_write`] goes to.
static mut JOURNAL_NEXT: usize = 0;

/// Keep `j` in the journal (from the control task only: one writer).
pub fn journal_write(j: &Journal) {
    let words = j.to_words();
    // SAFETY: the control task is the only writer (and `journal_take` runs in init,
    // before it); raw volatile word writes into the `.persist` block, no reference made.
    unsafe {
        let next = addr_of_mut!(JOURNAL_NEXT);
        let slot = next.read() & 1;
        let base = (addr_of_mut!(ODO_JOURNAL) as *mut u32).add(slot * JOURNAL_WORDS);
        for (i, w) in words.iter().enumerate() {
            base.add(i).write_volatile(*w);
        }
        next.write(slot ^ 1);
    }
}

/// At boot: the journals the last run left (either slot may be torn or, after a power
/// cut, noise; the checks of [`Journal::from_words`] refuse those).
pub fn journal_take() -> [Option<Journal>; 2] {
    // SAFETY: init runs alone; raw reads of the block.
    unsafe {
        let b = addr_of_mut!(ODO_JOURNAL) as *mut [u32; JOURNAL_WORDS];
        [
            Journal::from_words(&b.read_volatile()),
            Journal::from_words(&b.add(1).read_volatile()),
        ]
    }
}
