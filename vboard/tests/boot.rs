//! Issue 21: the bootloader (`boot/`, the unmodified release image) on the virtual
//! board, in sector 0, with an application behind it in ACTIVE (update-layout's map,
//! sectors 5-6 at 0x0802_0000 in layout C): it drives the
//! outputs safe, leaves the SRAM untouched, jumps to the application (VTOR and MSP
//! set), swaps in an update marked in its state sector, rolls it back at the next reset
//! when it was never confirmed, and finishes a swap cut by a power cut.
//!
//! The applications here are two hand-assembled images (a vector table and ten
//! instructions that write a tag, their SP and VTOR to SRAM, then a body that reaches
//! into ACTIVE's second page, so that the swap copies both pages), so that the
//! bootloader is tested alone; the real firmware behind the bootloader is tested too
//! (`the_release_image_swapped_in_confirms_itself_and_is_kept`).
//!
//! Build the bootloader first: `cd boot && cargo build --release`.
//! `VBOARD_BOOTLOADER=path` runs these tests on another bootloader image.

use hil_sim::flash::{SharedFlash, SimFlash};
use hil_sim::rig::{Machine, RigOptions};
use vboard::cpu::{Board, BoardConfig};
use vboard::image::Image;
use vboard::periph::gpio::Mode;
use vboard::world::World;

use update_layout::layout::{
    ACTIVE_BASE as ACTIVE, ACTIVE_LEN, DFU_PAGES, PAGE_LEN, STATE_BASE as STATE,
};
use update_layout::state::{BOOT, REVERT, SWAP};
use vboard::periph::flash::FlashTiming;
/// Where the test applications write their tag, SP and VTOR.
const MARK: u32 = 0x2001_F000;
const APP_SP: u32 = 0x2002_0000;
const PS_PER_MS: u64 = 1_000_000_000;

fn bootloader() -> Image {
    Image::load_bootloader(&vboard::image::bootloader_path()).unwrap_or_else(|e| panic!("{e}"))
}

/// The test applications' length: into ACTIVE's second page, so that every copy of the
/// swap and of the revert has words to program.
const APP_LEN: usize = PAGE_LEN as usize + 16 * 1024;

/// A test application: a vector table (SP, reset vector), then code that stores `tag`,
/// its SP and VTOR at MARK, MARK+4, MARK+8 and spins, then a body of [`APP_LEN`].
fn app(tag: u32) -> Vec<u8> {
    let mut v = Vec::new();
    v.extend(APP_SP.to_le_bytes());
    v.extend((ACTIVE + 0x40 + 1).to_le_bytes());
    v.resize(0x40, 0xFF);
    for hw in [
        0x4804u16, // ldr r0, [pc, #16]  (MARK)
        0x4905,    // ldr r1, [pc, #20]  (tag)
        0x6001,    // str r1, [r0]
        0x466A,    // mov r2, sp
        0x6042,    // str r2, [r0, #4]
        0x4B04,    // ldr r3, [pc, #16]  (VTOR's address)
        0x681B,    // ldr r3, [r3]
        0x6083,    // str r3, [r0, #8]
        0xE7FE,    // b .
        0xBF00,    // nop
    ] {
        v.extend(hw.to_le_bytes());
    }
    for w in [MARK, tag, 0xE000_ED08] {
        v.extend(w.to_le_bytes());
    }
    // A recognisable body (no run of erased words: every word is programmed).
    while v.len() < APP_LEN {
        v.push((v.len() as u32 ^ tag) as u8 | 1);
    }
    v
}

const A: u32 = 0xA0A0_0001;
const B: u32 = 0xB0B0_0002;

/// A board with the bootloader, application A in ACTIVE, and optionally application B in
/// DFU page 0 with the state sector saying SWAP (an update verified and marked).
fn board(update: bool) -> Board {
    let mut img = bootloader();
    img.put(ACTIVE, &app(A)).unwrap();
    if update {
        img.put(DFU_PAGES[0], &app(B)).unwrap();
        img.put(STATE, &SWAP.to_le_bytes()).unwrap();
    }
    let world = World::new(
        Machine::new(&RigOptions::new(80)),
        SharedFlash::new(SimFlash::stm32f407_odometer()),
    );
    let mut b = Board::new(img, world, BoardConfig::default()).unwrap();
    b.power_on();
    b
}

/// Run until the word at MARK is `tag` (true) or `limit_ms` of virtual time passed.
fn run_until_tag(b: &mut Board, tag: u32, limit_ms: u64) -> bool {
    let end = b.now() + limit_ms * PS_PER_MS;
    while b.now() < end {
        let t = b.now() + 10 * PS_PER_MS;
        b.run_until(t).unwrap();
        if b.peek(MARK) == Some(tag) {
            return true;
        }
    }
    false
}

/// ACTIVE's bytes as the core reads them.
fn active(b: &Board) -> Vec<u8> {
    (0..ACTIVE_LEN / 4)
        .flat_map(|i| b.peek(ACTIVE + 4 * i).unwrap_or(0).to_le_bytes())
        .collect()
}

/// `image` padded with erased flash to ACTIVE's length.
fn padded(image: &[u8]) -> Vec<u8> {
    let mut v = image.to_vec();
    v.resize(ACTIVE_LEN as usize, 0xFF);
    v
}

#[test]
fn the_bootloader_starts_the_application_behind_it_with_outputs_safe_and_sram_untouched() {
    let mut b = board(false);
    // What the power-on left in SRAM (noise): none of it may change but what A writes.
    let before: Vec<Option<u32>> = (0..0x8000).map(|i| b.peek(0x2000_0000 + 4 * i)).collect();
    assert!(run_until_tag(&mut b, A, 200), "application A never ran");
    assert_eq!(
        b.peek(MARK + 4),
        Some(APP_SP),
        "MSP from the application's table"
    );
    assert_eq!(b.peek(MARK + 8), Some(ACTIVE), "VTOR at the application");
    for (i, w) in before.iter().enumerate() {
        let a = 0x2000_0000 + 4 * i as u32;
        if (MARK..MARK + 12).contains(&a) {
            continue;
        }
        assert_eq!(b.peek(a), *w, "SRAM at {a:#x} changed");
    }
    // Every motor and PLC output a push-pull output at its safe level.
    let soc = b.soc();
    for (port, pin, high, name) in [
        (4usize, 11u8, true, "EN"),
        (4, 9, false, "STEP"),
        (3, 12, false, "IN1"),
        (3, 13, false, "IN2"),
        (3, 0, false, "READY"),
        (3, 1, false, "MATED"),
        (3, 2, false, "FAULT"),
        (3, 3, false, "MAINTENANCE"),
    ] {
        let g = &soc.gpio[port];
        let odr = g.read(0x14, 4, 0).unwrap_or(0);
        assert_eq!(g.mode(pin), Mode::Output, "{name}");
        assert_eq!(odr & (1 << pin) != 0, high, "{name}");
    }
    assert_eq!(soc.code_erases + soc.code_programs, 0, "nothing written");
}

#[test]
fn a_blank_application_sector_is_never_jumped_to() {
    let world = World::new(
        Machine::new(&RigOptions::new(80)),
        SharedFlash::new(SimFlash::stm32f407_odometer()),
    );
    let mut b = Board::new(bootloader(), world, BoardConfig::default()).unwrap();
    b.power_on();
    b.run_until(200 * PS_PER_MS).unwrap();
    assert!(b.pc() < ACTIVE, "pc {:#x}: in the bootloader", b.pc());
    assert!(b.faults().is_empty(), "{:?}", b.faults());
}

#[test]
fn an_update_is_swapped_in_then_rolled_back_at_the_next_reset_unless_confirmed() {
    let mut b = board(true);
    assert!(run_until_tag(&mut b, B, 60_000), "the update never ran");
    let swapped_at_ms = b.now() / PS_PER_MS;
    assert!(
        active(&b) == padded(&app(B)),
        "ACTIVE holds the update, whole"
    );
    // The previous image kept in DFU pages 1-2 (embassy-boot's swap moves it one page up).
    let kept: Vec<u8> = (0..APP_LEN as u32 / 4)
        .flat_map(|i| b.peek(DFU_PAGES[1] + 4 * i).unwrap_or(0).to_le_bytes())
        .collect();
    assert!(kept == app(A), "DFU pages 1-2 hold the previous image");
    // The swap erased every page it programmed (ACTIVE's two, DFU page 1, which B's
    // second page reached, and DFU page 2, blank, before A's second page went in) and
    // programmed both images' words once and its four progress words: what the images
    // are, nothing more.
    let (erases, programs) = (b.soc().code_erases, b.soc().code_programs);
    assert_eq!(erases, 4, "the swap's erases");
    assert_eq!(
        programs,
        2 * APP_LEN as u64 / 4 + 4,
        "the swap's programmed words"
    );
    assert!(
        swapped_at_ms.abs_diff(SWAP_MS) < SWAP_MS / 10,
        "the swap took {swapped_at_ms} ms (SWAP_MS {SWAP_MS})"
    );
    // A reset before the update confirmed itself (B never does): rolled back.
    b.reset_pin();
    assert!(run_until_tag(&mut b, A, 60_000), "never rolled back");
    assert!(active(&b) == padded(&app(A)));
    assert_eq!(b.peek(STATE), Some(REVERT), "REVERT recorded");
    // And it stays: the next reset boots A without copying.
    let writes = b.soc().code_programs;
    b.reset_pin();
    b.run_until(b.now() + 100 * PS_PER_MS).unwrap();
    assert_eq!(b.peek(MARK), Some(A));
    assert_eq!(b.soc().code_programs, writes, "nothing written");
}

#[test]
fn a_trial_image_that_hangs_is_reset_by_the_watchdog_and_rolled_back() {
    // B never confirms and never starts a watchdog of its own: the bootloader's (8.2 s at
    // 32 kHz) resets it, and that reset reverts.
    let mut b = board(true);
    assert!(run_until_tag(&mut b, B, 60_000), "the update never ran");
    let at = b.now();
    assert!(run_until_tag(&mut b, A, 60_000), "never rolled back");
    let waited_s = (b.now() - at) / (1000 * PS_PER_MS);
    assert!(
        waited_s >= 8,
        "rolled back after {waited_s} s: not by the watchdog"
    );
    assert_eq!(b.peek(STATE), Some(REVERT), "REVERT recorded");
    assert!(active(&b) == padded(&app(A)));
}

/// The release image as an update of itself: swapped in by the bootloader, it boots on
/// trial, confirms itself (the state sector says BOOT), and the next reset keeps it.
#[test]
fn the_release_image_swapped_in_confirms_itself_and_is_kept() {
    let mut img = Image::load(&vboard::image::default_path()).unwrap_or_else(|e| panic!("{e}"));
    let start = (ACTIVE - 0x0800_0000) as usize;
    let app: Vec<u8> = img.flash[start..img.flash_used as usize].to_vec();
    img.put(DFU_PAGES[0], &app).unwrap();
    img.put(STATE, &SWAP.to_le_bytes()).unwrap();
    let odometer = SharedFlash::new(SimFlash::stm32f407_odometer());
    let world = World::new(Machine::new(&RigOptions::new(80)), odometer.clone());
    let mut b = Board::new(img, world, BoardConfig::default()).unwrap();
    b.power_on();
    let end = 60_000 * PS_PER_MS;
    while b.now() < end && b.peek(STATE) != Some(BOOT) {
        let t = b.now() + 50 * PS_PER_MS;
        b.run_until(t).unwrap();
    }
    assert_eq!(b.peek(STATE), Some(BOOT), "the trial boot never confirmed");
    let active_now: Vec<u8> = (0..app.len() as u32 / 4)
        .flat_map(|i| b.peek(ACTIVE + 4 * i).unwrap_or(0).to_le_bytes())
        .collect();
    assert!(
        active_now == app[..active_now.len()],
        "ACTIVE is the update"
    );
    let confirmed = |b: &Board| {
        b.log
            .iter()
            .filter(|l| l.msg.contains("trial boot confirmed"))
            .count()
    };
    assert_eq!(confirmed(&b), 1, "the image said it confirmed");
    // The next reset boots it as it is: nothing copied, nothing confirmed again.
    let programs = b.soc().code_programs;
    b.reset_pin();
    b.run_until(b.now() + 3_000 * PS_PER_MS).unwrap();
    assert_eq!(
        b.soc().code_programs,
        programs,
        "nothing written by the reset"
    );
    assert_eq!(b.peek(STATE), Some(BOOT));
    assert_eq!(confirmed(&b), 1);
    assert!(
        b.log.iter().filter(|l| l.msg.contains("booted")).count() >= 2,
        "the image ran after both boots"
    );
    // The odometer's sectors were never erased by the swap or the confirmation.
    assert_eq!(odometer.with(|f| f.erase_counts().to_vec()), vec![0, 0]);
}

/// The power cut at `permille` of the swap's duration: the board powers up again and
/// must run the update, whole.
fn cut_during_swap(permille: u64, swap_ms: u64) {
    let mut b = board(true);
    b.run_until(swap_ms * PS_PER_MS * permille / 1000).unwrap();
    b.power_on();
    assert!(
        run_until_tag(&mut b, B, 60_000),
        "cut at {permille} per mille of the swap: the update never ran"
    );
    assert!(
        active(&b) == padded(&app(B)),
        "cut at {permille} per mille: ACTIVE not whole"
    );
}

/// The swap's duration from power-on to the update running, virtual ms, at the
/// datasheet's maximum flash timing, derived from the layout and the flash model: the
/// four 128 KiB sectors it erases (ACTIVE's two pages and DFU pages 1 and 2: the images
/// reach into their second pages), the words it programs (both images once, the
/// progress words), and the bootloader's own time (its reads and blank checks at 16 MHz:
/// a few per cent of the rest; checked by the rollback test above within 10 %).
const SWAP_MS: u64 = {
    let t = FlashTiming::Max;
    let erase = t.erase_ps(PAGE_LEN / 1024, 2);
    let ps = 4 * erase + (2 * APP_LEN as u64 / 4 + 4) * t.program_ps();
    ps / PS_PER_MS * 103 / 100
};

fn swap_duration_ms() -> u64 {
    let mut b = board(true);
    assert!(run_until_tag(&mut b, B, 60_000));
    b.now() / PS_PER_MS
}

/// Two instants in CI, one in each page's copies (the swap copies the last page first:
/// ACTIVE page 1's copies take the first quarter or so); 200 in the ignored test below.
#[test]
fn a_power_cut_during_the_swap_still_boots_the_update_whole() {
    for permille in [150, 777] {
        cut_during_swap(permille, SWAP_MS);
    }
}

/// 200 instants over the swap (`cargo test --release -- --ignored`).
#[test]
#[ignore]
fn a_power_cut_at_200_instants_of_the_swap_still_boots_the_update_whole() {
    let swap_ms = swap_duration_ms();
    let mut x = 0x2545_F491_4F6C_DD1Du64;
    for _ in 0..200 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        cut_during_swap(x % 1000, swap_ms);
    }
}
