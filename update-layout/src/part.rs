//! The partitions handed to embassy-boot: ACTIVE and DFU as **sector-mapped pages**,
//! STATE as sector 1.
//!
//! embassy-boot swaps in units of `PAGE_SIZE`, the larger of ACTIVE's and DFU's
//! `ERASE_SIZE`, and wants both partitions whole multiples of it. The F407's sectors are
//! 16/64/128 KiB, so ACTIVE right behind the bootloader (sectors 2-4 or 2-5) has no
//! uniform erase size. Here every partition's `ERASE_SIZE` is the whole of ACTIVE
//! ([`PAGE_LEN`]): ACTIVE is one page (erasing it erases its sectors), DFU is two
//! pages, each laid in a run of whole 128 KiB sectors of its own (its unused tail is
//! never read nor written). Reads and writes map a partition offset to its page's
//! address; nothing here panics on any offset (out of range is an error).
//!
//! The flash may be a trait object (`RefCell<dyn Sectors>`): the application's updater
//! takes it so, so that its session and embassy-boot's updater are compiled once, in the
//! logic crate at its opt-level, and not for the board's flash type (issue 21's size).

use core::cell::RefCell;

use embedded_storage::nor_flash::{
    ErrorType, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};

use crate::layout::{sector_of, whole_sectors, ACTIVE_BASE, DFU_PAGES, PAGE_LEN};
use crate::layout::{STATE_BASE, STATE_LEN};

/// Errors of the flash and the partitions.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum FlashError {
    /// Outside the partition, or outside sectors 1-9.
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
}

/// Page bases of ACTIVE: one page.
static ACTIVE_PAGES: [u32; 1] = [ACTIVE_BASE];

impl<'a, F: Sectors + ?Sized> Paged<'a, F> {
    /// ACTIVE: one page, sectors 2 on.
    pub fn active(flash: &'a RefCell<F>) -> Self {
        Self {
            flash,
            pages: &ACTIVE_PAGES,
        }
    }

    /// DFU: two pages.
    pub fn dfu(flash: &'a RefCell<F>) -> Self {
        Self {
            flash,
            pages: &DFU_PAGES,
        }
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
        let mut p = from;
        while p < to {
            let (base, _) = self.map(p).ok_or(FlashError::OutOfBounds)?;
            // The sectors the page needs: from its base up to its end, whole.
            let (_, last, last_len) =
                sector_of(base + PAGE_LEN - 1).ok_or(FlashError::OutOfBounds)?;
            erase_run(&mut *self.flash.borrow_mut(), base, last + last_len - base)?;
            p += PAGE_LEN;
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), FlashError> {
        if offset % 4 != 0 || bytes.len() % 4 != 0 {
            return Err(FlashError::NotAligned);
        }
        let flash = self.flash;
        self.each_run(offset, bytes.len(), |addr, start, n| {
            let data = bytes.get(start..start + n).ok_or(FlashError::OutOfBounds)?;
            flash.borrow_mut().program(addr, data)
        })
    }
}

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
