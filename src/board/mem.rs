//! `memcpy` and `memclr` for the image, small (issue 20): the word loop when both
//! pointers are word-aligned, else the byte loop.
//!
//! Why by hand: the Rust toolchain links compiler_builtins' versions, prebuilt with the
//! target's `core` for speed (whatever the profile's opt-level): `memcpy` and its
//! `__aeabi_memcpy{4,8}` entry points are 886 bytes of flash and `__aeabi_memclr{4,8}`
//! 174, unrolled and aligned for copies of kilobytes. This image copies tens of bytes at
//! a time (a record, a reply, a log frame) and never a block on the safety path: the
//! control step and the interrupts in `.text.hot` call neither (the size report's
//! `--baseline` lists who does: init, the idle loop, the console, the record log and
//! defmt's RTT writes). Defining the symbols here keeps the archive's objects out of the
//! link (an archive member is linked only for a symbol nothing else defines); a build
//! that linked both would fail on the duplicate symbol, never pick one silently.
//!
//! The same contract as the C and AEABI functions (RTABI §4.3.4): `dest` and `src` do not
//! overlap; `memcpy` returns `dest` (r0 is never changed); the `4`/`8` variants may
//! assume aligned pointers, and take the same path (the alignment is checked anyway).
//! Unaligned word accesses are never made. Tested on the host against `copy_from_slice`
//! and on the target by everything that copies (`cargo xtask qemu`, the virtual board).

core::arch::global_asm!(
    ".section .text.docking_memcpy,\"ax\",%progbits",
    ".p2align 1",
    ".global memcpy",
    ".type memcpy,%function",
    ".thumb_func",
    "memcpy:",
    "    mov     r3, r0",
    "    orr     r12, r0, r1",
    "    lsls    r12, r12, #30",
    "    bne     2f",
    // Words while 4 or more bytes are left (C clear: the subtraction borrowed).
    "1:  subs    r2, r2, #4",
    "    bcc     3f",
    "    ldr     r12, [r1], #4",
    "    str     r12, [r3], #4",
    "    b       1b",
    "3:  adds    r2, r2, #4",
    // Bytes.
    "2:  subs    r2, r2, #1",
    "    bcc     4f",
    "    ldrb    r12, [r1], #1",
    "    strb    r12, [r3], #1",
    "    b       2b",
    "4:  bx      lr",
    ".size memcpy, . - memcpy",
    ".global __aeabi_memcpy",
    ".thumb_set __aeabi_memcpy, memcpy",
    ".global __aeabi_memcpy4",
    ".thumb_set __aeabi_memcpy4, memcpy",
    ".global __aeabi_memcpy8",
    ".thumb_set __aeabi_memcpy8, memcpy",
    // __aeabi_memclr(dest, n): n zero bytes at dest.
    ".section .text.docking_memclr,\"ax\",%progbits",
    ".p2align 1",
    ".global __aeabi_memclr",
    ".type __aeabi_memclr,%function",
    ".thumb_func",
    "__aeabi_memclr:",
    "    movs    r2, #0",
    "    lsls    r3, r0, #30",
    "    bne     2f",
    "1:  subs    r1, r1, #4",
    "    bcc     3f",
    "    str     r2, [r0], #4",
    "    b       1b",
    "3:  adds    r1, r1, #4",
    "2:  subs    r1, r1, #1",
    "    bcc     4f",
    "    strb    r2, [r0], #1",
    "    b       2b",
    "4:  bx      lr",
    ".size __aeabi_memclr, . - __aeabi_memclr",
    ".global __aeabi_memclr4",
    ".thumb_set __aeabi_memclr4, __aeabi_memclr",
    ".global __aeabi_memclr8",
    ".thumb_set __aeabi_memclr8, __aeabi_memclr",
);
