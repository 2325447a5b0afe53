//! The partitions handed to embassy-boot: ACTIVE and DFU as **pages** of
//! [`PAGE_LEN`] bytes (one 128 KiB sector each in layout C), STATE as sector 1.
//!
//! embassy-boot swaps in units of `PAGE_SIZE`, the larger of ACTIVE's and DFU's
//! `ERASE_SIZE`, and wants both partitions whole multiples of it. A partition here is a
//! table of page addresses (`layout::Layout::active_pages`, `dfu_pages`), each page a
//! run of whole sectors; reads and writes map a partition offset to its page's
//! address; nothing here panics on any offset (out of range is an error).
//!
//! # The swap costs what the image is, not what the partition is
//!
//! ACTIVE is 256 KiB and an image about 100 KB: most of every page the swap copies is
//! erased flash. So:
//!
//! * an erased word (`FFFF_FFFF`) is **not programmed** ([`NorFlash::write`]): it is
//!   read back instead, and a word that does not read `FFFF_FFFF` fails the write as a
//!   program that read back wrong would ([`FlashError::Verify`]), so the copy is
//!   verified whole either way;
//! * a page is erased **lazily** ([`NorFlash::erase`]): one that reads blank is not
//!   erased at once but marked; it is erased (really, blank or not) before the first
//!   word that is not erased is programmed into it. A page that only ever receives
//!   erased words is not erased at all: it reads blank, which is what the copy wants.
//!
//! Why not simply skip the erase of a page that reads blank: an erase cut short by a
//! power cut can leave cells that read `FF` without the margin a completed erase
//! verifies, and data programmed there may not be retained (the odometer's log trusts
//! no sector for reading blank either: `docking-logic`'s storage.rs, "Interrupted
//! erases"). Here nothing is ever programmed into a page that was not erased to the end
//! in the same run of the copy: a cut during that erase has the copy redone, and the
//! redo erases again.
//!
//! A page of the image's tail that is blank in both images then costs its check only:
//! the swap of a 100 KB image in layout C's 256 KiB erases and programs what the image
//! holds, about what layout B's swap of a 96 KiB ACTIVE did (docs/update.md, "Swap
//! time"). The application's updater erases every DFU page it programs
//! ([`Paged::erase_page`]) and leaves the pages the file does not reach reading blank
//! ([`Paged::clear_page`]).
//!
//! The flash may be a trait object (`RefCell<dyn Sectors>`): the application's updater
//! takes it so, so that its session and embassy-boot's updater are compiled once, in the
//! logic crate, and not for the board's flash type.

use core::cell::RefCell;

use embedded_storage::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};

use crate::layout::{sector_of, whole_sectors, ACTIVE_PAGES, DFU_PAGES, PAGE_LEN};
use crate::layout::{STATE_BASE, STATE_LEN};

/// Errors of the flash and the partitions.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlashError {
    /// Outside the partition, or outside STATE, ACTIVE and DFU.
    OutOfBounds,
    /// Not word-aligned, or not whole words.
    NotAligned,
    /// The controller stayed locked after the key sequence.
    Locked,
    /// An error flag of FLASH_SR (the register's value).
    Status(u32),
    /// An operation still busy after its time-out.
    Timeout,
    /// A programmed word read back different.
    Verify,
}

impl NorFlashError for FlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            Self::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            Self::NotAligned => NorFlashErrorKind::NotAligned,
            _ => NorFlashErrorKind::Other,
        }
    }
}

/// The raw flash, by absolute address: the board's register driver ([`crate`]'s binary)
/// or a model in the tests.
pub trait Sectors {
    /// Read `buf.len()` bytes at `addr`.
    fn read(&mut self, addr: u32, buf: &mut [u8]) -> Result<(), FlashError>;
    /// Erase the sector that starts at `base`.
    fn erase_sector(&mut self, base: u32) -> Result<(), FlashError>;
    /// Program whole words at `addr` (word-aligned).
    fn program(&mut self, addr: u32, data: &[u8]) -> Result<(), FlashError>;
}

/// Erase every sector of `[base, base + len)` (a run of whole sectors in 1-9).
fn erase_run<F: Sectors + ?Sized>(f: &mut F, base: u32, len: u32) -> Result<(), FlashError> {
    if !whole_sectors(base, len) {
        return Err(FlashError::OutOfBounds);
    }
    let mut a = base;
    while a < base + len {
        let Some((_, start, l)) = sector_of(a) else {
            return Err(FlashError::OutOfBounds);
        };
        f.erase_sector(start)?;
        a = start + l;
    }
    Ok(())
}

/// A partition of pages of [`PAGE_LEN`] bytes, page `i` at `pages[i]`.
pub struct Paged<'a, F: ?Sized> {
    flash: &'a RefCell<F>,
    pages: &'static [u32],
    /// Pages asked to be erased that read blank: bit `i` for page `i`. Erased before
    /// the first word that is not erased is programmed into them (the module doc).
    pending: core::cell::Cell<u32>,
}

/// Bytes read at a time by the blank check and the erased words' verification.
const CHUNK: usize = 64;

impl<'a, F: Sectors + ?Sized> Paged<'a, F> {
    /// ACTIVE: its pages (two in layout C).
    pub fn active(flash: &'a RefCell<F>) -> Self {
        Self {
            flash,
            pages: ACTIVE_PAGES,
            pending: core::cell::Cell::new(0),
        }
    }

    /// DFU: its pages (ACTIVE's and one more).
    pub fn dfu(flash: &'a RefCell<F>) -> Self {
        Self {
            flash,
            pages: DFU_PAGES,
            pending: core::cell::Cell::new(0),
        }
    }

    /// Page `page`'s first address and the length of its sectors, whole.
    fn page_sectors(&self, page: u32) -> Result<(u32, u32), FlashError> {
        let base = *self
            .pages
            .get(page as usize)
            .ok_or(FlashError::OutOfBounds)?;
        let (_, last, last_len) = sector_of(base + PAGE_LEN - 1).ok_or(FlashError::OutOfBounds)?;
        Ok((base, last + last_len - base))
    }

    /// Erase page `page` now, blank or not (the updater, before it programs the page).
    pub fn erase_page(&mut self, page: u32) -> Result<(), FlashError> {
        self.erase_now(page)
    }

    fn erase_now(&self, page: u32) -> Result<(), FlashError> {
        let (base, len) = self.page_sectors(page)?;
        erase_run(&mut *self.flash.borrow_mut(), base, len)?;
        self.pending.set(self.pending.get() & !(1 << page));
        Ok(())
    }

    /// Leave page `page` reading blank: erased when it does not (the updater, for the
    /// DFU pages a file does not reach: the swap copies them, and nothing is programmed
    /// into them). Whether an erase ran.
    pub fn clear_page(&mut self, page: u32) -> Result<bool, FlashError> {
        let (base, len) = self.page_sectors(page)?;
        if self.blank(base, len)? {
            return Ok(false);
        }
        self.erase_page(page)?;
        Ok(true)
    }

    /// Whether `[addr, addr + len)` reads erased (every byte `FF`).
    fn blank(&self, addr: u32, len: u32) -> Result<bool, FlashError> {
        let mut buf = [0u8; CHUNK];
        let mut a = addr;
        let end = addr.checked_add(len).ok_or(FlashError::OutOfBounds)?;
        while a < end {
            let n = ((end - a) as usize).min(CHUNK);
            let chunk = buf.get_mut(..n).ok_or(FlashError::OutOfBounds)?;
            self.flash.borrow_mut().read(a, chunk)?;
            if chunk.iter().any(|&b| b != 0xFF) {
                return Ok(false);
            }
            a += n as u32;
        }
        Ok(true)
    }

    /// Capacity, bytes.
    fn len(&self) -> u32 {
        PAGE_LEN.saturating_mul(self.pages.len() as u32)
    }

    /// The absolute address of partition offset `off` and the bytes left in its page.
    fn map(&self, off: u32) -> Option<(u32, u32)> {
        let page = self.pages.get((off / PAGE_LEN) as usize)?;
        let within = off % PAGE_LEN;
        Some((page + within, PAGE_LEN - within))
    }

    /// Split `[off, off + len)` into runs within pages and call `f(address, start, n)`
    /// for each (start: bytes from `off`).
    fn each_run(
        &self,
        off: u32,
        len: usize,
        mut f: impl FnMut(u32, usize, usize) -> Result<(), FlashError>,
    ) -> Result<(), FlashError> {
        let end = (off as u64).saturating_add(len as u64);
        if end > self.len() as u64 {
            return Err(FlashError::OutOfBounds);
        }
        let mut done = 0usize;
        while done < len {
            let o = off + done as u32;
            let (addr, left) = self.map(o).ok_or(FlashError::OutOfBounds)?;
            let n = (left as usize).min(len - done);
            f(addr, done, n)?;
            done += n;
        }
        Ok(())
    }
}

impl<F: ?Sized> ErrorType for Paged<'_, F> {
    type Error = FlashError;
}

impl<F: Sectors + ?Sized> ReadNorFlash for Paged<'_, F> {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), FlashError> {
        let flash = self.flash;
        self.each_run(offset, bytes.len(), |addr, start, n| {
            let buf = bytes
                .get_mut(start..start + n)
                .ok_or(FlashError::OutOfBounds)?;
            flash.borrow_mut().read(addr, buf)
        })
    }

    fn capacity(&self) -> usize {
        self.len() as usize
    }
}

impl<F: Sectors + ?Sized> NorFlash for Paged<'_, F> {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = PAGE_LEN as usize;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), FlashError> {
        if from % PAGE_LEN != 0 || to % PAGE_LEN != 0 || to < from || to > self.len() {
            return Err(FlashError::OutOfBounds);
        }
        for page in from / PAGE_LEN..to / PAGE_LEN {
            // A page that reads blank is erased only when something is programmed
            // into it (the module doc).
            let (base, len) = self.page_sectors(page)?;
            if self.blank(base, len)? {
                self.pending.set(self.pending.get() | 1 << page);
            } else {
                self.erase_page(page)?;
            }
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), FlashError> {
        if offset % 4 != 0 || bytes.len() % 4 != 0 {
            return Err(FlashError::NotAligned);
        }
        let mut at = offset;
        self.each_run(offset, bytes.len(), |addr, start, n| {
            let data = bytes.get(start..start + n).ok_or(FlashError::OutOfBounds)?;
            let page = at / PAGE_LEN;
            at += n as u32;
            // A page whose erase was put off: erased now, before a word is programmed.
            if self.pending.get() & (1 << page) != 0 && !data.iter().all(|&b| b == 0xFF) {
                self.erase_now(page)?;
            }
            self.program_skipping_erased(addr, data)
        })
    }
}

impl<F: Sectors + ?Sized> Paged<'_, F> {
    /// Program `data` (whole words) at `addr`, skipping what is erased: a run of at
    /// least [`SKIP_WORDS`] words `FFFF_FFFF` is read back instead of programmed and
    /// must read erased (the module doc); everything between such runs is programmed in
    /// one call (a shorter run of erased words among it is programmed as it is, which
    /// leaves erased flash erased: one call rather than many, each of which the
    /// application's updater runs in a window of its own).
    fn program_skipping_erased(&self, addr: u32, data: &[u8]) -> Result<(), FlashError> {
        let words = data.len() / 4;
        let erased = |i: usize| {
            data.get(4 * i..4 * i + 4)
                .is_some_and(|w| w.iter().all(|&b| b == 0xFF))
        };
        let at = |word: usize| addr + 4 * word as u32;
        // Words [start, i) are still to be programmed.
        let mut start = 0;
        let mut i = 0;
        while i < words {
            if !erased(i) {
                i += 1;
                continue;
            }
            let mut end = i;
            while end < words && erased(end) {
                end += 1;
            }
            if end - i >= SKIP_WORDS {
                self.program_words(at(start), data, start, i)?;
                if !self.blank(at(i), 4 * (end - i) as u32)? {
                    return Err(FlashError::Verify);
                }
                start = end;
            }
            i = end;
        }
        self.program_words(at(start), data, start, words)
    }

    /// Program words `[from, to)` of `data` at `addr` (nothing when empty).
    fn program_words(
        &self,
        addr: u32,
        data: &[u8],
        from: usize,
        to: usize,
    ) -> Result<(), FlashError> {
        if to <= from {
            return Ok(());
        }
        let run = data.get(4 * from..4 * to).ok_or(FlashError::OutOfBounds)?;
        self.flash.borrow_mut().program(addr, run)
    }
}

/// The shortest run of erased words a page write skips rather than programs (64 B).
pub const SKIP_WORDS: usize = 16;

/// STATE: sector 1, erased whole.
pub struct State<'a, F: ?Sized> {
    flash: &'a RefCell<F>,
}

impl<'a, F: Sectors + ?Sized> State<'a, F> {
    /// Sector 1.
    pub fn new(flash: &'a RefCell<F>) -> Self {
        Self { flash }
    }
}

impl<F: ?Sized> ErrorType for State<'_, F> {
    type Error = FlashError;
}

impl<F: Sectors + ?Sized> ReadNorFlash for State<'_, F> {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), FlashError> {
        let end = (offset as u64).saturating_add(bytes.len() as u64);
        if end > STATE_LEN as u64 {
            return Err(FlashError::OutOfBounds);
        }
        self.flash.borrow_mut().read(STATE_BASE + offset, bytes)
    }

    fn capacity(&self) -> usize {
        STATE_LEN as usize
    }
}

impl<F: Sectors + ?Sized> NorFlash for State<'_, F> {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = STATE_LEN as usize;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), FlashError> {
        match (from, to) {
            (0, 0) => Ok(()),
            (0, STATE_LEN) => erase_run(&mut *self.flash.borrow_mut(), STATE_BASE, STATE_LEN),
            _ => Err(FlashError::OutOfBounds),
        }
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), FlashError> {
        if offset % 4 != 0 || bytes.len() % 4 != 0 {
            return Err(FlashError::NotAligned);
        }
        let end = (offset as u64).saturating_add(bytes.len() as u64);
        if end > STATE_LEN as u64 {
            return Err(FlashError::OutOfBounds);
        }
        self.flash.borrow_mut().program(STATE_BASE + offset, bytes)
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::indexing_slicing)]
mod tests {
    use super::*;
    use crate::layout::{FLASH_BASE, FLASH_END};

    /// The 1 MiB as NOR flash that counts its erases and programmed words.
    struct Counting {
        mem: std::vec::Vec<u8>,
        erases: u32,
        programmed_words: u32,
    }

    impl Counting {
        fn new() -> Self {
            Self {
                mem: std::vec![0xFF; (FLASH_END - FLASH_BASE) as usize],
                erases: 0,
                programmed_words: 0,
            }
        }
        fn at(addr: u32) -> usize {
            (addr - FLASH_BASE) as usize
        }
    }

    impl Sectors for Counting {
        fn read(&mut self, addr: u32, buf: &mut [u8]) -> Result<(), FlashError> {
            let i = Self::at(addr);
            buf.copy_from_slice(&self.mem[i..i + buf.len()]);
            Ok(())
        }
        fn erase_sector(&mut self, base: u32) -> Result<(), FlashError> {
            let (_, start, len) = sector_of(base).unwrap();
            assert_eq!(start, base);
            self.erases += 1;
            let i = Self::at(base);
            self.mem[i..i + len as usize].fill(0xFF);
            Ok(())
        }
        fn program(&mut self, addr: u32, data: &[u8]) -> Result<(), FlashError> {
            self.programmed_words += (data.len() / 4) as u32;
            let i = Self::at(addr);
            for (k, b) in data.iter().enumerate() {
                self.mem[i + k] &= b;
            }
            Ok(())
        }
    }

    #[test]
    fn a_blank_page_is_erased_only_before_something_is_programmed_into_it() {
        let flash = RefCell::new(Counting::new());
        let mut dfu = Paged::dfu(&flash);
        let all = PAGE_LEN * DFU_PAGES.len() as u32;
        dfu.erase(0, all).unwrap();
        assert_eq!(
            flash.borrow().erases,
            0,
            "every DFU page reads blank: put off"
        );
        // Erased words into a page put off: nothing to erase, they read erased.
        dfu.write(16, &[0xFF; 64]).unwrap();
        assert_eq!(flash.borrow().erases, 0);
        // A word that is not erased: the page is erased first (blank or not: an erase
        // cut short reads blank too), once.
        dfu.write(PAGE_LEN + 8, &[1, 2, 3, 4]).unwrap();
        assert_eq!(
            flash.borrow().erases,
            1,
            "the page erased before its first program"
        );
        dfu.write(PAGE_LEN + 12, &[5, 6, 7, 8]).unwrap();
        assert_eq!(flash.borrow().erases, 1, "once");
        // The next copy: the page written is erased at once, the others put off.
        let mut dfu = Paged::dfu(&flash);
        dfu.erase(0, all).unwrap();
        assert_eq!(flash.borrow().erases, 2, "only the page written");
        let mut w = [0u8; 4];
        dfu.read(PAGE_LEN + 8, &mut w).unwrap();
        assert_eq!(w, [0xFF; 4]);
        // The updater's own: a page erased whatever it reads, a blank one cleared
        // without an erase, a written one cleared by one.
        dfu.erase_page(0).unwrap();
        assert_eq!(flash.borrow().erases, 3);
        assert_eq!(dfu.clear_page(2), Ok(false));
        dfu.write(2 * PAGE_LEN, &[0; 4]).unwrap();
        assert_eq!(dfu.clear_page(2), Ok(true));
        assert!(dfu.erase_page(DFU_PAGES.len() as u32).is_err());
    }

    #[test]
    fn erased_words_are_verified_not_programmed() {
        let flash = RefCell::new(Counting::new());
        let mut active = Paged::active(&flash);
        // 4 KiB: 8 words of data, 1000 erased words, 8 words of data; 3 erased words
        // inside the first run are programmed with it (shorter than SKIP_WORDS).
        let mut data = std::vec![0xFFu8; 4096];
        data[..32].fill(0x11);
        data[8..20].fill(0xFF);
        data[4096 - 32..].fill(0x22);
        active.write(0, &data).unwrap();
        assert_eq!(flash.borrow().programmed_words, 16);
        let mut back = std::vec![0u8; 4096];
        active.read(0, &mut back).unwrap();
        assert_eq!(back, data);
        // An erased word of the data over flash that is not erased: the copy fails as
        // a program that reads back wrong does.
        let flash = RefCell::new(Counting::new());
        flash.borrow_mut().mem[Counting::at(ACTIVE_PAGES[0]) + 2000] = 0x7F;
        let mut active = Paged::active(&flash);
        assert_eq!(active.write(0, &data), Err(FlashError::Verify));
    }

    #[test]
    fn a_write_crossing_pages_lands_in_both() {
        let flash = RefCell::new(Counting::new());
        let mut dfu = Paged::dfu(&flash);
        let data = [0x5Au8; 128];
        dfu.write(PAGE_LEN - 64, &data).unwrap();
        let mut back = [0u8; 128];
        dfu.read(PAGE_LEN - 64, &mut back).unwrap();
        assert_eq!(back, data);
        let m = &flash.borrow().mem;
        assert_eq!(m[Counting::at(DFU_PAGES[1])], 0x5A);
        assert_eq!(m[Counting::at(DFU_PAGES[0] + PAGE_LEN - 64)], 0x5A);
        assert!(dfu
            .read(PAGE_LEN * DFU_PAGES.len() as u32 - 2, &mut back)
            .is_err());
    }
}
