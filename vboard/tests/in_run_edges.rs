//! Taking interrupts and sleeping inside the engine's run (`BoardConfig::in_run`) at the
//! edges no scene of the suite reaches (tests/skip.rs compares the scenes): code
//! programmed over a `wfi` the board has hooked (by the bootloader's swap, by the image
//! itself), a `wfi` an update brings, an exception entry whose vector cannot be read,
//! and the debugging hooks (`Board::at_pc`, `Board::watch_pc`) on a `wfi`, placed
//! before the first run or after it. Each runs a small image of its own through the
//! real bootloader, with `in_run` off and on, and the two must agree.

use hil_sim::flash::{SharedFlash, SimFlash};
use hil_sim::rig::{Machine, RigOptions};
use update_layout::layout::{ACTIVE_BASE as ACTIVE, DFU_PAGES, PAGE_LEN, STATE_BASE as STATE};
use update_layout::state::SWAP;
use vboard::cpu::{Board, BoardConfig};
use vboard::image::Image;
use vboard::world::World;

/// Where the images below store their result.
const MARK: u32 = 0x2001_F000;
/// An image's length: past one page, so that the bootloader's swap copies two.
const APP_LEN: usize = PAGE_LEN as usize + 16 * 1024;
const MS: u64 = 1_000_000_000;

/// The vector table's head: the stack's top and the reset vector (the code at 0x40),
/// SysTick's vector (`systick`: an offset of the image) if any, the rest erased.
fn head(systick: Option<u32>) -> Vec<u8> {
    let mut v = Vec::new();
    v.extend(0x2002_0000u32.to_le_bytes());
    v.extend((ACTIVE + 0x41).to_le_bytes());
    v.resize(0x40, 0xFF);
    if let Some(off) = systick {
        v[0x3C..0x40].copy_from_slice(&(ACTIVE + off + 1).to_le_bytes());
    }
    v
}

/// An image: `head`, then Thumb halfwords from 0x40 and literal words after them, then
/// filler (`tag` makes two images' filler differ) to `APP_LEN`.
fn image(head: Vec<u8>, code: &[u16], literals: &[u32], tag: u32) -> Vec<u8> {
    let mut v = head;
    for hw in code {
        v.extend(hw.to_le_bytes());
    }
    for w in literals {
        v.extend(w.to_le_bytes());
    }
    while v.len() < APP_LEN {
        v.push((v.len() as u32 ^ tag) as u8 | 1);
    }
    v
}

/// Nops, a `wfi` at 0x4C, `b .`: never runs (the swap installs another image first),
/// but the board hooks its `wfi` at power-on.
fn wfi_at_4c() -> Vec<u8> {
    let code = [
        0xBF00, 0xBF00, 0xBF00, 0xBF00, 0xBF00, 0xBF00, 0xBF30, 0xE7FE,
    ];
    image(head(None), &code, &[], 0xA)
}

/// Masks interrupts, pends PendSV (so that a `wfi` would not sleep), then adds 5 and 7
/// to r1 at 0x4C and 0x4E (0x4C: where `wfi_at_4c` has its `wfi`) and stores r1 at
/// MARK: 12 when both additions run.
fn adds_at_4c() -> Vec<u8> {
    let code = [
        0xB672, // 40 cpsid i
        0x4905, // 42 ldr r1, [pc, #20]: ICSR
        0x4A05, // 44 ldr r2, [pc, #20]: PENDSVSET
        0x600A, // 46 str r2, [r1]
        0x2100, // 48 movs r1, #0
        0xE7FF, // 4A b 0x4C
        0x3105, // 4C adds r1, #5
        0x3107, // 4E adds r1, #7
        0x4803, // 50 ldr r0, [pc, #12]: MARK
        0x6001, // 52 str r1, [r0]
        0xE7FE, // 54 b .
        0xBF00, // 56
    ];
    image(head(None), &code, &[0xE000_ED04, 1 << 28, MARK], 0xB)
}

/// SysTick every 2 000 cycles, VTOR at ACTIVE, then `wfi` (at 0x54) in a loop; the
/// handler (0x58) reloads the watchdog (the bootloader may have started it) and returns.
fn ticks_and_wfi() -> Vec<u8> {
    let code = [
        0x4807, // 40 ldr r0, [pc, #28]: SysTick
        0x4908, // 42 ldr r1, [pc, #32]: reload
        0x4A08, // 44 ldr r2, [pc, #32]: VTOR
        0x4B09, // 46 ldr r3, [pc, #36]: ACTIVE
        0x6013, // 48 str r3, [r2]
        0x6041, // 4A str r1, [r0, #4]: LOAD
        0x2100, // 4C movs r1, #0
        0x6081, // 4E str r1, [r0, #8]: VAL
        0x2107, // 50 movs r1, #7
        0x6001, // 52 str r1, [r0]: CTRL (enable, interrupt, core clock)
        0xBF30, // 54 wfi
        0xE7FD, // 56 b 0x54
        0x4805, // 58 ldr r0, [pc, #20]: IWDG_KR
        0x4906, // 5A ldr r1, [pc, #24]: reload key
        0x6001, // 5C str r1, [r0]
        0x4770, // 5E bx lr
    ];
    let literals = [0xE000_E010, 1_999, 0xE000_ED08, ACTIVE, 0x4000_3000, 0xAAAA];
    image(head(Some(0x58)), &code, &literals, 0xC)
}

/// The `wfi` of `ticks_and_wfi`.
const TICKS_WFI: u32 = ACTIVE + 0x54;

/// A board with the bootloader, `active` in ACTIVE and, if any, `dfu` in the DFU
/// partition with a swap requested (the bootloader installs it at power-on).
fn board(active: &[u8], dfu: Option<&[u8]>, in_run: bool) -> Board {
    let mut img = Image::load_bootloader(&vboard::image::bootloader_path()).expect("bootloader");
    img.put(ACTIVE, active).expect("ACTIVE");
    if let Some(dfu) = dfu {
        img.put(DFU_PAGES[0], dfu).expect("DFU");
        img.put(STATE, &SWAP.to_le_bytes()).expect("state");
    }
    let world = World::new(
        Machine::new(&RigOptions::new(80)),
        SharedFlash::new(SimFlash::stm32f407_odometer()),
    );
    let cfg = BoardConfig {
        in_run,
        ..BoardConfig::default()
    };
    let mut b = Board::new(img, world, cfg).expect("board");
    b.power_on();
    b
}

/// Run until the core is in `done` (or `limit_ms` passed): the word at MARK, when, and
/// the trace digest. In small steps near the image's code, so that the run ends soon
/// after.
fn run_to(b: &mut Board, done: std::ops::Range<u32>, limit_ms: u64) -> (Option<u32>, u64, u64) {
    let end = b.now() + limit_ms * MS;
    while b.now() < end && !done.contains(&b.pc()) {
        let near = (ACTIVE..ACTIVE + 0x100).contains(&b.pc());
        let t = b.now() + if near { MS / 1_000 } else { MS };
        b.run_until(t).expect("run");
    }
    (b.peek(MARK), b.now(), b.trace_digest())
}

#[test]
fn a_wfi_hook_left_where_an_update_programmed_other_code_skips_nothing() {
    let run = |in_run| {
        let mut b = board(&wfi_at_4c(), Some(&adds_at_4c()), in_run);
        let before = sleeps_at(&b, ACTIVE + 0x4C);
        let end = run_to(&mut b, ACTIVE + 0x54..ACTIVE + 0x56, 60_000);
        (end, before, sleeps_at(&b, ACTIVE + 0x4C))
    };
    let off = run(false);
    assert_eq!(
        off.0 .0,
        Some(12),
        "the swapped-in image ran both additions"
    );
    let on = run(true);
    assert_eq!(
        (on.1, on.2),
        (true, false),
        "a sleep at the old image's wfi, not at the new image's addition"
    );
    assert_eq!(on.0, off.0);
}

/// The vector table moved to unmapped memory (0x3000_0000), then interrupts unmasked
/// with PendSV pending: the entry fails at its vector read.
fn vector_table_unmapped() -> Vec<u8> {
    let code = [
        0xB672, // 40 cpsid i
        0x4805, // 42 ldr r0, [pc, #20]: VTOR
        0x4906, // 44 ldr r1, [pc, #24]: 0x3000_0000
        0x6001, // 46 str r1, [r0]
        0x4804, // 48 ldr r0, [pc, #16]: ICSR
        0x4906, // 4A ldr r1, [pc, #24]: PENDSVSET
        0x6001, // 4C str r1, [r0]
        0xE7FF, // 4E b 0x50
        0xB662, // 50 cpsie i: PendSV taken in the block hook after it
        0xE7FE, // 52 b .
        0xBF00, 0xBF00,
    ];
    image(
        head(None),
        &code,
        &[0xE000_ED08, 0xE000_ED04, 0x3000_0000, 1 << 28],
        0xD,
    )
}

#[test]
fn an_unreadable_vector_stacks_one_frame_and_locks_up_inside_the_run_too() {
    let run = |in_run| {
        let mut b = board(&vector_table_unmapped(), None, in_run);
        b.run_until(b.now() + 2_000 * MS).expect("run");
        let stack: Vec<Option<u32>> = (0..32).map(|i| b.peek(0x2002_0000 - 128 + 4 * i)).collect();
        let faults: Vec<String> = b
            .faults()
            .iter()
            .map(|f| format!("{} at {:#010x}", f.what, f.pc))
            .collect();
        (b.trace_digest(), faults, b.soc().locked_up, stack)
    };
    let off = run(false);
    // As the ARMv7-M entry: PendSV's frame stacked (its return address, after the
    // `cpsie`, at the frame's sixth word), its vector unreadable (HFSR.VECTTBL), and so
    // HardFault's from the same table: a lockup, with one frame on the stack.
    assert_eq!(
        off.3[32 - 2],
        Some(ACTIVE + 0x52),
        "PendSV's frame: {:x?}",
        off.3
    );
    assert_eq!(off.1.len(), 1, "{:?}", off.1);
    assert!(off.1[0].contains("HFSR.VECTTBL") && off.1[0].contains("exception 14"));
    assert!(off.2, "locked up");
    assert_eq!(run(true), off);
}

#[test]
fn a_debugging_hook_placed_after_the_first_run_sees_every_execution() {
    let run = |in_run| {
        let mut b = board(&ticks_and_wfi(), None, in_run);
        b.run_until(b.now() + 10 * MS).expect("run");
        let hits = b.watch_pc(TICKS_WFI + 2);
        let seen = std::rc::Rc::new(std::cell::Cell::new(0u64));
        let s = seen.clone();
        b.at_pc(TICKS_WFI, move |_| {
            s.set(s.get() + 1);
            false
        });
        b.run_until(b.now() + 50 * MS).expect("run");
        (hits.get(), seen.get(), b.trace_digest())
    };
    let off = run(false);
    assert!(
        off.0 > 0 && off.0 == off.1,
        "the wfi and the branch after it: {off:?}"
    );
    assert_eq!(run(true), off);
}

#[test]
fn a_debugging_hook_on_a_wfi_runs_before_the_sleep() {
    let run = |in_run| {
        let mut b = board(&ticks_and_wfi(), None, in_run);
        let seen = std::rc::Rc::new(std::cell::RefCell::new(Vec::new()));
        let s = seen.clone();
        b.at_pc(TICKS_WFI, move |soc| {
            s.borrow_mut().push(soc.now());
            false
        });
        b.run_until(b.now() + 300 * MS).expect("run");
        let first: Vec<u64> = seen.borrow().iter().take(8).copied().collect();
        (first, b.trace_digest())
    };
    let off = run(false);
    assert_eq!(off.0.len(), 8, "the wfi ran at every tick");
    assert_eq!(run(true), off);
}

/// Whether the board sleeps inside the run at a `wfi` at `addr`.
fn sleeps_at(b: &Board, addr: u32) -> bool {
    b.soc()
        .wfi_hooked
        .iter()
        .any(|&(a, len)| a == addr && len.is_some())
}

#[test]
fn a_wfi_an_update_brings_is_hooked_and_changes_nothing() {
    let run = |in_run| {
        let mut b = board(&wfi_at_4c(), Some(&ticks_and_wfi()), in_run);
        let before = sleeps_at(&b, TICKS_WFI);
        run_to(&mut b, TICKS_WFI..TICKS_WFI + 4, 60_000);
        let (starts, t) = (b.soc().engine_starts, b.now());
        b.run_until(t + 100 * MS).expect("run");
        let s = b.soc();
        let hooked = sleeps_at(&b, TICKS_WFI);
        (before, hooked, s.engine_starts - starts, b.trace_digest())
    };
    let off = run(false);
    let on = run(true);
    assert!(
        !on.0 && on.1,
        "the new image's wfi is hooked once it is installed"
    );
    // Its sleeps are inside the run: the engine starts at the RTT polls (1 ms), not at
    // each of the 8 kHz ticks.
    assert!(
        on.2 * 4 < off.2,
        "engine starts: {} on, {} off",
        on.2,
        off.2
    );
    assert_eq!(on.3, off.3);
}

/// Interrupts masked, PendSV pending, the flash unlocked, `adds r1, #16` (0x3110: bits
/// of 0xBF30 only) programmed over the `wfi` at 0x5E, the flash's BSY polled until the
/// program ends; then the code at 0x5E runs and r1 + 1 goes to MARK: 17 where the
/// programmed addition ran.
fn programs_a_wfi_then_runs_it() -> Vec<u8> {
    let code = [
        0xB672, // 40 cpsid i
        0x480F, // 42 ldr r0, [pc, #60]: ICSR
        0x490F, // 44 ldr r1, [pc, #60]: PENDSVSET
        0x6001, // 46 str r1, [r0]
        0x480F, // 48 ldr r0, [pc, #60]: FLASH_KEYR
        0x4910, // 4A ldr r1, [pc, #64]: key 1
        0x6001, // 4C str r1, [r0]
        0x4910, // 4E ldr r1, [pc, #64]: key 2
        0x6001, // 50 str r1, [r0]
        0x4910, // 52 ldr r1, [pc, #64]: PG, 16-bit
        0x60C1, // 54 str r1, [r0, #12]: FLASH_CR
        0x4A10, // 56 ldr r2, [pc, #64]: the wfi's address
        0x4B10, // 58 ldr r3, [pc, #64]: 0x3110
        0xE003, // 5A b 0x64 (the program, then the poll)
        0xBF00, // 5C
        0xBF30, // 5E wfi, then adds r1, #16
        0x3101, // 60 adds r1, #1
        0xE009, // 62 b 0x78 (the store)
        0x8013, // 64 strh r3, [r2]
        0x2100, // 66 movs r1, #0
        0x6883, // 68 ldr r3, [r0, #8]: FLASH_SR
        0x03DB, // 6A lsls r3, r3, #15: BSY (bit 16) to the sign
        0xD4FC, // 6C bmi 0x68
        0xE7F6, // 6E b 0x5E
        0xBF00, 0xBF00, 0xBF00, 0xBF00, // 70..76
        0x4809, // 78 ldr r0, [pc, #36]: MARK
        0x6001, // 7A str r1, [r0]
        0xE7FE, // 7C b .
        0xBF00, // 7E
    ];
    let literals = [
        0xE000_ED04,
        1 << 28,
        0x4002_3C04,
        0x4567_0123,
        0xCDEF_89AB,
        0x101,
        ACTIVE + 0x5E,
        0x3110,
        MARK,
    ];
    image(head(None), &code, &literals, 0xE)
}

#[test]
fn a_wfi_programmed_over_runs_the_new_code_there() {
    let run = |in_run| {
        let mut b = board(&programs_a_wfi_then_runs_it(), None, in_run);
        run_to(&mut b, ACTIVE + 0x7C..ACTIVE + 0x7E, 3_000)
    };
    let off = run(false);
    assert_eq!(off.0, Some(17), "the addition programmed over the wfi ran");
    assert_eq!(run(true), off);
}

/// `ticks_and_wfi` with VTOR at unmapped memory (0x3000_0000, not ACTIVE): the first
/// SysTick wakes the `wfi`, and its entry locks up.
fn ticks_and_wfi_vtor_unmapped() -> Vec<u8> {
    let mut v = ticks_and_wfi();
    // The literal stored to VTOR: the fourth, from 0x60.
    v[0x6C..0x70].copy_from_slice(&0x3000_0000u32.to_le_bytes());
    v
}

#[test]
fn a_lockup_at_the_entry_from_a_wfi_leaves_the_pc_after_it_inside_the_run_too() {
    let run = |in_run| {
        let mut b = board(&ticks_and_wfi_vtor_unmapped(), None, in_run);
        b.run_until(b.now() + 50 * MS).expect("run");
        (
            b.pc(),
            b.soc().locked_up,
            b.faults().len(),
            b.trace_digest(),
        )
    };
    let off = run(false);
    assert_eq!(
        (off.0, off.1),
        (TICKS_WFI + 2, true),
        "locked up after the wfi"
    );
    assert_eq!(run(true), off);
}

/// VTOR at 0x1000_FF80 (the last 128 bytes of CCM): HardFault's vector (written there)
/// readable, IRQ16's (exception 32, at 0x1001_0000) past the CCM; IRQ16 enabled and
/// pended. HardFault's handler (0x58) spins.
fn vecttbl_hardfault_taken() -> Vec<u8> {
    let code = [
        0x4806, // 40 ldr r0, [pc, #24]: HardFault's vector in the new table
        0x4907, // 42 ldr r1, [pc, #28]: the handler
        0x6001, // 44 str r1, [r0]
        0x4807, // 46 ldr r0, [pc, #28]: VTOR
        0x4907, // 48 ldr r1, [pc, #28]: the table
        0x6001, // 4A str r1, [r0]
        0x4807, // 4C ldr r0, [pc, #28]: NVIC_ISER0
        0x4908, // 4E ldr r1, [pc, #32]: IRQ16
        0x6001, // 50 str r1, [r0]
        0x4808, // 52 ldr r0, [pc, #32]: NVIC_ISPR0
        0x6001, // 54 str r1, [r0]
        0xE7FE, // 56 b .
        0xE7FE, // 58 HardFault: b .
        0xBF00, // 5A
    ];
    let literals = [
        0x1000_FF8C,
        ACTIVE + 0x58 + 1,
        0xE000_ED08,
        0x1000_FF80,
        0xE000_E100,
        1 << 16,
        0xE000_E200,
    ];
    image(head(None), &code, &literals, 0x1F)
}

#[test]
fn an_unreadable_vector_with_a_readable_hardfault_vector_takes_hardfault_and_leaves_it_pending() {
    let run = |in_run| {
        let mut b = board(&vecttbl_hardfault_taken(), None, in_run);
        b.run_until(b.now() + 5 * MS).expect("run");
        let (hfsr, ispr0) = (b.peek(0xE000_ED2C), b.peek(0xE000_E200));
        let active = b.soc().nvic.active_stack().to_vec();
        (b.pc(), hfsr, ispr0, active, b.trace_digest())
    };
    let off = run(false);
    assert_eq!(off.0, ACTIVE + 0x58, "in HardFault's handler");
    assert_eq!(off.1, Some(2), "HFSR.VECTTBL");
    assert_eq!(off.2, Some(1 << 16), "IRQ16 still pending");
    assert_eq!(off.3, vec![3], "HardFault active");
    assert_eq!(run(true), off);
}

#[test]
fn a_debugging_hook_at_an_odd_address_counts_the_instruction_there() {
    let run = |in_run| {
        let mut b = board(&ticks_and_wfi(), None, in_run);
        let odd = b.watch_pc(TICKS_WFI + 2 + 1);
        let even = b.watch_pc(TICKS_WFI + 2);
        b.run_until(b.now() + 20 * MS).expect("run");
        (odd.get(), even.get())
    };
    let off = run(false);
    assert!(off.0 > 0 && off.0 == off.1, "{off:?}");
    assert_eq!(run(true), off);
}
