//! The docking controller's bootloader, hardware-free part: the partition map
//! ([`layout`]) and the partitions embassy-boot swaps ([`part`]), both from the shared
//! `update-layout` crate, and the boot decision
//! ([`prepare`], [`bootable`]). The binary (`src/main.rs`) adds the board: the safe
//! outputs, the register-level flash driver and the jump.
//!
//! # Why embassy-boot, and its pages
//!
//! embassy-boot 0.7's swap is power-fail safe (docs/update.md, "The state record"):
//! each copy is recorded by one word program after it completes and is redone whole
//! from a source not yet overwritten. Its unit, `PAGE_SIZE`, must divide both ACTIVE and
//! DFU and be a multiple of both erase sizes. In layout C every page is one 128 KiB
//! sector: ACTIVE two (sectors 5-6), DFU three (7-9) ([`part`]); the copy goes through a
//! 4 KiB buffer (embassy-boot chunks a page by the buffer's length: no 128 KiB RAM
//! buffer is needed). A page already blank is not erased again and erased words are
//! verified rather than programmed ([`part`]'s module doc): the swap costs what the
//! image is, not what ACTIVE is.
//!
//! # The state record (sector 1; embassy-boot 0.7's format, version 1 here)
//!
//! `update_layout::state` draws it: the magic, the progress-valid word, then one
//! progress word per page copy (`2 + 4 × pages` words: 10 in layout C).
//!
//! Nothing read from flash can make this code panic: embassy-boot's assertions are on
//! the partitions' sizes (fixed, checked by the tests), every address is checked before
//! use, and integers only.
#![cfg_attr(not(test), no_std)]
#![deny(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::indexing_slicing
)]

/// The shared crate itself (its `pre_init_safe_outputs!` macro).
pub use update_layout as layout_crate;
pub use update_layout::{layout, part};

use core::cell::RefCell;

pub use embassy_boot::{BootError, State as BootState};
use embassy_boot::{BootLoader, BootLoaderConfig};

use layout::{ACTIVE_BASE, ACTIVE_LEN, SRAM};
use part::{Paged, Sectors, State};

/// The copy buffer's length: a divisor of the page.
pub const BUF_LEN: usize = 4096;
const _: () = assert!(layout::PAGE_LEN as usize % BUF_LEN == 0);

/// Word-aligned copy buffer.
#[repr(align(4))]
pub struct Buf(pub [u8; BUF_LEN]);

/// Swap or revert as STATE asks (embassy-boot's `prepare_boot`); the state found.
pub fn prepare<F: Sectors>(flash: &RefCell<F>, buf: &mut Buf) -> Result<BootState, BootError> {
    let mut boot = BootLoader::new(BootLoaderConfig {
        active: Paged::active(flash),
        dfu: Paged::dfu(flash),
        state: State::new(flash),
    });
    boot.prepare_boot(&mut buf.0)
}

/// ACTIVE's initial stack pointer and reset vector, if they make sense: the stack
/// pointer in SRAM (word-aligned, the top included), the reset vector inside ACTIVE with
/// the Thumb bit. A blank or foreign ACTIVE is never jumped to.
pub fn bootable<F: Sectors>(flash: &RefCell<F>) -> Option<(u32, u32)> {
    let mut v = [0u8; 8];
    flash.borrow_mut().read(ACTIVE_BASE, &mut v).ok()?;
    let [a, b, c, d, e, f, g, h] = v;
    let sp = u32::from_le_bytes([a, b, c, d]);
    let pc = u32::from_le_bytes([e, f, g, h]);
    let sp_ok = sp > SRAM.0 && sp <= SRAM.1 && sp % 4 == 0;
    let pc_ok = pc & 1 == 1 && pc > ACTIVE_BASE && pc < ACTIVE_BASE + ACTIVE_LEN;
    (sp_ok && pc_ok).then_some((sp, pc))
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::indexing_slicing, clippy::panic)]
mod tests {
    use super::*;
    use crate::layout::ACTIVE_PAGES;
    use crate::layout::{
        bootloader_may_write, sector_of, DFU_PAGES, FLASH_BASE, PAGE_LEN, STATE_BASE,
    };
    use crate::part::FlashError;
    use embassy_boot::BlockingFirmwareState;

    /// The F407's 1 MiB as NOR flash: programs only clear bits; a power cut at operation
    /// `cut_at` leaves that operation half done (an erase: the sector's first half erased,
    /// the rest garbage; a program: the first half of its words) and fails it and every
    /// operation after.
    struct Sim {
        mem: Vec<u8>,
        ops: u64,
        cut_at: Option<u64>,
        seed: u64,
        /// Sectors erased and words programmed, whole operations only.
        erases: u32,
        words: u32,
    }

    impl Sim {
        fn new() -> Self {
            Self {
                mem: vec![0xFF; 0x10_0000],
                ops: 0,
                cut_at: None,
                seed: 0x1234_5678,
                erases: 0,
                words: 0,
            }
        }
        fn noise(&mut self) -> u8 {
            self.seed ^= self.seed << 13;
            self.seed ^= self.seed >> 7;
            self.seed ^= self.seed << 17;
            self.seed as u8
        }
        fn at(addr: u32) -> usize {
            (addr - FLASH_BASE) as usize
        }
        /// Whether this operation runs whole (false: cut now or already off).
        fn tick(&mut self) -> Result<bool, FlashError> {
            self.ops += 1;
            match self.cut_at {
                Some(c) if self.ops > c => Err(FlashError::Timeout),
                Some(c) if self.ops == c => Ok(false),
                _ => Ok(true),
            }
        }
        fn put(&mut self, addr: u32, bytes: &[u8]) {
            let i = Self::at(addr);
            self.mem[i..i + bytes.len()].copy_from_slice(bytes);
        }
        fn get(&self, addr: u32, len: u32) -> &[u8] {
            let i = Self::at(addr);
            &self.mem[i..i + len as usize]
        }
    }

    impl Sectors for Sim {
        fn read(&mut self, addr: u32, buf: &mut [u8]) -> Result<(), FlashError> {
            if self.cut_at.is_some_and(|c| self.ops >= c) {
                return Err(FlashError::Timeout);
            }
            let i = Self::at(addr);
            buf.copy_from_slice(&self.mem[i..i + buf.len()]);
            Ok(())
        }
        fn erase_sector(&mut self, base: u32) -> Result<(), FlashError> {
            let (_, start, len) = sector_of(base).unwrap();
            assert_eq!(start, base);
            assert!(bootloader_may_write(base, len), "erase of {base:#x}");
            let whole = self.tick()?;
            self.erases += u32::from(whole);
            let i = Self::at(base);
            let half = if whole { len } else { len / 2 };
            self.mem[i..i + half as usize].fill(0xFF);
            if !whole {
                for j in half..len {
                    let n = self.noise();
                    self.mem[i + j as usize] &= n;
                }
                return Err(FlashError::Timeout);
            }
            Ok(())
        }
        fn program(&mut self, addr: u32, data: &[u8]) -> Result<(), FlashError> {
            assert!(bootloader_may_write(addr, data.len() as u32));
            assert_eq!(addr % 4, 0);
            let whole = self.tick()?;
            self.words += u32::from(whole) * (data.len() / 4) as u32;
            let n = if whole {
                data.len()
            } else {
                data.len() / 8 * 4
            };
            let i = Self::at(addr);
            for (k, b) in data[..n].iter().enumerate() {
                self.mem[i + k] &= b;
            }
            if whole {
                Ok(())
            } else {
                Err(FlashError::Timeout)
            }
        }
    }

    /// An image of all of ACTIVE: a vector table (SP, reset vector) then a pattern.
    fn image(tag: u8) -> Vec<u8> {
        let mut v: Vec<u8> = (0..ACTIVE_LEN)
            .map(|i| (i as u8) ^ tag ^ (i >> 9) as u8)
            .collect();
        v[..4].copy_from_slice(&0x2002_0000u32.to_le_bytes());
        v[4..8].copy_from_slice(&(ACTIVE_BASE + 0x201 + tag as u32 * 4).to_le_bytes());
        v
    }

    fn mark(flash: &RefCell<Sim>, f: impl FnOnce(&mut BlockingFirmwareState<State<Sim>>)) {
        let mut aligned = [0u8; 4];
        let mut st = BlockingFirmwareState::new(State::new(flash), &mut aligned);
        f(&mut st);
    }

    fn with_update(a: &[u8], b: &[u8]) -> RefCell<Sim> {
        let flash = RefCell::new(Sim::new());
        flash.borrow_mut().put(ACTIVE_BASE, a);
        flash.borrow_mut().put(DFU_PAGES[0], b);
        mark(&flash, |s| s.mark_updated().unwrap());
        flash
    }

    fn active(flash: &RefCell<Sim>) -> Vec<u8> {
        flash.borrow().get(ACTIVE_BASE, ACTIVE_LEN).to_vec()
    }

    /// Boot until `prepare` succeeds, the power cut at operation `cut` of the first try.
    fn boot(flash: &RefCell<Sim>, cut: Option<u64>) -> BootState {
        let mut buf = Buf([0; BUF_LEN]);
        flash.borrow_mut().ops = 0;
        flash.borrow_mut().cut_at = cut;
        if let Ok(s) = prepare(flash, &mut buf) {
            if cut.is_none() || flash.borrow().ops < cut.unwrap_or(0) {
                return s;
            }
        }
        flash.borrow_mut().cut_at = None;
        prepare(flash, &mut buf).unwrap()
    }

    #[test]
    fn an_update_is_swapped_in_then_rolled_back_when_it_never_confirms() {
        let (a, b) = (image(1), image(2));
        let flash = with_update(&a, &b);
        assert_eq!(boot(&flash, None), BootState::Swap);
        assert!(active(&flash) == b, "the new image runs");
        assert_eq!(bootable(&flash), Some((0x2002_0000, ACTIVE_BASE + 0x209)));
        // Reset before mark_booted: reverted.
        assert_eq!(boot(&flash, None), BootState::Swap);
        assert!(active(&flash) == a, "the old image is back");
        let mut st = State::<Sim>::new(&flash);
        let mut w = [0u8; 4];
        embedded_storage::nor_flash::ReadNorFlash::read(&mut st, 0, &mut w).unwrap();
        assert_eq!(w, [0xC0; 4], "REVERT recorded");
        // And it stays.
        assert_eq!(boot(&flash, None), BootState::Revert);
        assert!(active(&flash) == a);
    }

    #[test]
    fn a_confirmed_update_stays() {
        let (a, b) = (image(1), image(2));
        let flash = with_update(&a, &b);
        assert_eq!(boot(&flash, None), BootState::Swap);
        mark(&flash, |s| s.mark_booted().unwrap());
        for _ in 0..3 {
            assert_eq!(boot(&flash, None), BootState::Boot);
            assert!(active(&flash) == b);
        }
    }

    #[test]
    fn a_power_cut_at_any_operation_of_the_swap_or_the_revert_leaves_an_image_whole() {
        // Images of all of ACTIVE, and images under a page (whose blank pages the swap
        // skips: the skipped erases and the verified erased words under cuts too).
        for (a, b) in [(image(1), image(2)), (small(1, 100_000), small(2, 90_000))] {
            cuts_in_swap_and_revert(&a, &b);
        }
    }

    fn cuts_in_swap_and_revert(a: &[u8], b: &[u8]) {
        // How many flash operations the swap and the revert take.
        let flash = with_update(a, b);
        boot(&flash, None);
        let swap_ops = flash.borrow().ops;
        boot(&flash, None);
        let revert_ops = flash.borrow().ops;
        assert!(swap_ops > 40 && revert_ops > 40, "{swap_ops} {revert_ops}");
        for cut in 1..=swap_ops {
            let flash = with_update(a, b);
            // Cut during the swap, then boots run it to the end: the new image.
            assert_eq!(boot(&flash, Some(cut)), BootState::Swap);
            assert!(active(&flash) == b, "cut at swap operation {cut}");
        }
        for cut in 1..=revert_ops {
            let flash = with_update(a, b);
            boot(&flash, None);
            boot(&flash, Some(cut));
            assert!(active(&flash) == a, "cut at revert operation {cut}");
            // A cut between the state sector's erase and REVERT's magic reads BOOT.
            let s = boot(&flash, None);
            assert!(matches!(s, BootState::Revert | BootState::Boot), "{s:?}");
            assert!(active(&flash) == a);
        }
    }

    #[test]
    fn a_cut_while_the_update_is_marked_runs_the_old_or_the_new_image_whole() {
        let (a, b) = (image(1), image(2));
        for cut in 1..=4 {
            let flash = RefCell::new(Sim::new());
            flash.borrow_mut().put(ACTIVE_BASE, &a);
            flash.borrow_mut().put(DFU_PAGES[0], &b);
            flash.borrow_mut().cut_at = Some(cut);
            mark(&flash, |s| {
                let _ = s.mark_updated();
            });
            flash.borrow_mut().cut_at = None;
            let s = boot(&flash, None);
            let now = active(&flash);
            assert!(
                (s == BootState::Boot && now == a) || (s == BootState::Swap && now == b),
                "cut at marking operation {cut}: {s:?}"
            );
        }
    }

    #[test]
    fn a_cut_while_the_new_image_confirms_itself_leaves_one_whole_image() {
        let (a, b) = (image(1), image(2));
        for cut in 1..=4 {
            let flash = with_update(&a, &b);
            assert_eq!(boot(&flash, None), BootState::Swap);
            flash.borrow_mut().ops = 0;
            flash.borrow_mut().cut_at = Some(cut);
            mark(&flash, |s| {
                let _ = s.mark_booted();
            });
            flash.borrow_mut().cut_at = None;
            // A cut before the invalidation took leaves SWAP as it was: no confirmation,
            // so the revert (the old image, whole). After it (SWAP with the progress
            // invalid, an erased sector, BOOT) the new image is kept. Either way one
            // whole image, and it stays.
            let first = boot(&flash, None);
            let kept = active(&flash);
            assert!(
                kept == b || (cut == 1 && kept == a),
                "cut at confirming operation {cut}: {first:?}"
            );
            boot(&flash, None);
            assert!(active(&flash) == kept, "cut at confirming operation {cut}");
        }
    }

    /// `len` bytes of `image(tag)`, the rest of ACTIVE erased.
    fn small(tag: u8, len: usize) -> Vec<u8> {
        let mut v = image(tag);
        v[len..].fill(0xFF);
        v
    }

    #[test]
    fn a_small_image_swaps_and_reverts_with_the_erases_and_programs_it_needs() {
        // As the updater leaves the board: the running image (100 000 B) in ACTIVE, the
        // new one (90 000 B) received into DFU page 0, DFU page 1 erased by the
        // receiver, DFU page 2 holding the last swap's ACTIVE page 1 (blank: that image
        // was under a page too).
        let (a, b) = (small(1, 100_000), small(2, 90_000));
        let flash = with_update(&a, &b);
        flash.borrow_mut().put(DFU_PAGES[1], &[0u8; 64]);
        flash.borrow_mut().erase_sector(DFU_PAGES[1]).unwrap();
        let (e0, w0) = (flash.borrow().erases, flash.borrow().words);
        assert_eq!(boot(&flash, None), BootState::Swap);
        assert!(active(&flash) == b);
        let (erases, words) = (flash.borrow().erases - e0, flash.borrow().words - w0);
        // ACTIVE page 1 and DFU pages 1 and 2 read blank: DFU page 1 is erased all the
        // same before the old image is programmed into it (an erase cut short reads
        // blank too), ACTIVE page 0 because it holds the old image; ACTIVE page 1 and
        // DFU page 2 receive erased words only and are not erased. The old image's words
        // into DFU page 1, the new one's into ACTIVE, and 4 of the 10 progress words.
        assert_eq!(erases, 2, "the swap erased {erases} sectors");
        assert_eq!(
            words,
            (100_000 + 90_000) / 4 + 4,
            "the swap programmed {words} words"
        );
        // The revert: DFU page 0 (the new image) and ACTIVE page 0 and DFU page 1 (the
        // old image, moved back) are erased; ACTIVE page 1 stays blank.
        let (e0, w0) = (flash.borrow().erases, flash.borrow().words);
        assert_eq!(boot(&flash, None), BootState::Swap);
        assert!(active(&flash) == a, "rolled back");
        let (erases, words) = (flash.borrow().erases - e0, flash.borrow().words - w0);
        assert_eq!(
            erases,
            3 + 1,
            "the revert erased {erases} sectors (with STATE's)"
        );
        // Both images once, 4 progress words, the invalidation and REVERT's magic.
        assert_eq!(
            words,
            (90_000 + 100_000) / 4 + 4 + 2,
            "the revert programmed {words} words"
        );
        // The pages outside the images stay erased.
        assert!(flash
            .borrow()
            .get(ACTIVE_PAGES[1], PAGE_LEN)
            .iter()
            .all(|&x| x == 0xFF));
    }

    #[test]
    fn noise_in_the_state_sector_boots_the_active_image_untouched() {
        let a = image(1);
        let flash = RefCell::new(Sim::new());
        flash.borrow_mut().put(ACTIVE_BASE, &a);
        let noise: Vec<u8> = (0..layout::STATE_LEN).map(|i| (i * 7 + 3) as u8).collect();
        flash.borrow_mut().put(STATE_BASE, &noise);
        assert_eq!(boot(&flash, None), BootState::Boot);
        assert_eq!(flash.borrow().ops, 0, "nothing written");
        assert!(active(&flash) == a);
    }

    #[test]
    fn a_blank_or_foreign_active_is_not_booted() {
        let flash = RefCell::new(Sim::new());
        assert_eq!(bootable(&flash), None);
        // An image linked for 0x08000000 (no bootloader).
        let mut v = image(1);
        v[4..8].copy_from_slice(&0x0800_0189u32.to_le_bytes());
        flash.borrow_mut().put(ACTIVE_BASE, &v);
        assert_eq!(bootable(&flash), None);
        // SP outside SRAM.
        let mut v = image(1);
        v[..4].copy_from_slice(&0x1001_0000u32.to_le_bytes());
        flash.borrow_mut().put(ACTIVE_BASE, &v);
        assert_eq!(bootable(&flash), None);
    }
}
