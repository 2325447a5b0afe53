//! The partition map (docs/update.md, "Partition map"), shared by the bootloader, the
//! application's updater (and its `memory.x`, written by the root's build.rs), the
//! virtual board and the tools: one place to change it, [`LAYOUT`].
//!
//! STM32F407 flash sectors: 0-3 16 KiB, 4 64 KiB, 5-11 128 KiB (RM0090 table 5).
//!
//! **Layout C** (in force; issue 31), sized for the product's life on the 1 MiB part:
//!
//! ```text
//!  sector  0        1       2   3   4        5     6      7     8     9      10    11
//!         +--------+-------+-----------+   +------------+ +------------------+ +----------+
//!         | boot   | STATE | free for  |   | ACTIVE     | | DFU              | | odometer |
//!         | 16 KiB | 16 KiB| the project|  | 2 x 128 KiB| | 3 x 128 KiB      | | 2 x 128  |
//!         +--------+-------+-----------+   +------------+ +------------------+ +----------+
//!  0x0800_0000  0x0800_4000  0x0800_8000     0x0802_0000    0x0806_0000        0x080C_0000
//! ```
//!
//! * sector 0: the bootloader; sector 1: STATE (embassy-boot's magic and progress words);
//! * sectors 2-4 (96 KiB of small, fast-erasing sectors, [`PROJECT_FREE`]): in no
//!   partition, never erased or programmed by the bootloader or an update: the
//!   project's own (the docking signature's curves, issue 34);
//! * ACTIVE: sectors 5-6, two embassy-boot pages of one 128 KiB sector each, the
//!   application's vector table first;
//! * DFU: sectors 7-9, three pages (ACTIVE's two and the swap's spare, as embassy-boot
//!   wants): the update as received, then the image the swap replaced;
//! * sectors 10-11: the wear odometer, in no partition.
//!
//! The layouts before it ([`Layout::A`], [`Layout::B`]) are kept as data, so that a
//! file built for one of them is named and refused (an image header names its layout
//! since layout C; an older header names none).

/// Flash base address.
pub const FLASH_BASE: u32 = 0x0800_0000;
/// First address past the flash (1 MiB).
pub const FLASH_END: u32 = FLASH_BASE + 0x10_0000;
/// First address of the odometer's sectors (10 and 11), never written by the bootloader.
pub const ODOMETER_BASE: u32 = 0x080C_0000;

/// The bootloader's own sector (0).
pub const BOOT_BASE: u32 = FLASH_BASE;
/// The bootloader's sector's length: an application image holds nothing below
/// `BOOT_BASE + BOOT_LEN + STATE_LEN` (the virtual board loads the two as a probe does).
pub const BOOT_LEN: u32 = 16 * 1024;
/// STATE: sector 1.
pub const STATE_BASE: u32 = 0x0800_4000;
/// STATE's length (all of sector 1).
pub const STATE_LEN: u32 = 16 * 1024;

/// A partition map of the update: where ACTIVE and DFU are, in pages of [`Self::page_len`]
/// bytes. Its number is what an image header names (`header::Header::layout`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[repr(u8)]
pub enum Layout {
    /// The development layout (until 97900f2): ACTIVE sectors 2-5 (224 KiB, one page),
    /// DFU pages in sectors 6-7 and 8-9. Its images' headers name no layout.
    A = 1,
    /// The budget layout (97900f2 to issue 31): ACTIVE sectors 2-4 (96 KiB, one page),
    /// DFU pages in sectors 5 and 6. Its images' headers name no layout.
    B = 2,
    /// Layout C (issue 31): ACTIVE sectors 5-6 (two 128 KiB pages), DFU sectors 7-9.
    C = 3,
}

/// **The layout in force, and the only switch**: the bootloader, the application's link
/// (build.rs writes its FLASH region from [`ACTIVE_BASE`] and [`ACTIVE_LEN`]: an image
/// over ACTIVE fails to link), its updater, the virtual board and the tools all follow
/// it. A board's layout is fixed at its probe flash: one flashed with another layout is
/// flashed anew with a probe (bootloader and application, `bash tools/flash-board.sh`).
pub const LAYOUT: Layout = Layout::C;

impl Layout {
    /// The layout an image header's number names (`None`: 0, an image from before
    /// headers named one, or a number this build does not know).
    pub const fn from_id(id: u8) -> Option<Self> {
        match id {
            1 => Some(Self::A),
            2 => Some(Self::B),
            3 => Some(Self::C),
            _ => None,
        }
    }

    /// Its number in an image header.
    pub const fn id(self) -> u8 {
        self as u8
    }

    /// Its name, for people (`A`, `B`, `C`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::A => "A",
            Self::B => "B",
            Self::C => "C",
        }
    }

    /// The swap's unit (embassy-boot's `PAGE_SIZE`), bytes.
    pub const fn page_len(self) -> u32 {
        match self {
            Self::A => 224 * 1024,
            Self::B => 96 * 1024,
            Self::C => 128 * 1024,
        }
    }

    /// ACTIVE's pages' first addresses (its vector table at the first).
    pub const fn active_pages(self) -> &'static [u32] {
        match self {
            Self::A | Self::B => &[0x0800_8000],
            Self::C => &[0x0802_0000, 0x0804_0000],
        }
    }

    /// DFU's pages' first addresses: one more than ACTIVE's (embassy-boot's swap).
    pub const fn dfu_pages(self) -> &'static [u32] {
        match self {
            Self::A => &[0x0804_0000, 0x0808_0000],
            Self::B => &[0x0802_0000, 0x0804_0000],
            Self::C => &[0x0806_0000, 0x0808_0000, 0x080A_0000],
        }
    }

    /// ACTIVE's first address.
    pub const fn active_base(self) -> u32 {
        match self.active_pages() {
            [first, ..] => *first,
            [] => 0,
        }
    }

    /// ACTIVE's length, bytes.
    pub const fn active_len(self) -> u32 {
        self.page_len() * self.active_pages().len() as u32
    }

    /// Whether `addr` lies in this layout's ACTIVE.
    pub const fn in_active(self, addr: u32) -> bool {
        addr >= self.active_base() && addr - self.active_base() < self.active_len()
    }

    /// The largest image an update can carry, bytes: its file (the image padded to
    /// words, then the trailer) is received into the DFU pages the swap copies to
    /// ACTIVE, so the image gets ACTIVE less the trailer.
    pub const fn update_image_max(self) -> u32 {
        self.active_len() - TRAILER_LEN
    }
}

/// ACTIVE's pages in force.
pub const ACTIVE_PAGES: &[u32] = LAYOUT.active_pages();
/// DFU's pages in force.
pub const DFU_PAGES: &[u32] = LAYOUT.dfu_pages();
/// ACTIVE: the application, its vector table first.
pub const ACTIVE_BASE: u32 = LAYOUT.active_base();
/// ACTIVE's length, bytes.
pub const ACTIVE_LEN: u32 = LAYOUT.active_len();
/// The swap's unit: one 128 KiB sector in layout C.
pub const PAGE_LEN: u32 = LAYOUT.page_len();
/// DFU's first address.
pub const DFU_BASE: u32 = match DFU_PAGES {
    [first, ..] => *first,
    [] => 0,
};
/// First address past DFU's last page.
pub const DFU_END: u32 = match DFU_PAGES {
    [.., last] => *last + PAGE_LEN,
    [] => 0,
};

/// Sectors 2-4 of layout C: in no partition; the project's own (first address, length).
pub const PROJECT_FREE: (u32, u32) = (STATE_BASE + STATE_LEN, 96 * 1024);

/// The update file's trailer, bytes: the signature (64), the image's length (4) and
/// the magic (4), after the image's bytes (docking-logic's `update` module draws the
/// file; `tools/sign-image.sh` writes it).
pub const TRAILER_LEN: u32 = 72;

/// The largest application an update can carry, bytes (`cargo xtask size` holds the
/// image to it).
pub const UPDATE_IMAGE_MAX: u32 = LAYOUT.update_image_max();

/// The span of the partitions, lowest and highest (exclusive) address: sectors 1-9
/// (inside it the bootloader writes only [`bootloader_may_write`]'s).
pub const WRITABLE: (u32, u32) = (STATE_BASE, ODOMETER_BASE);

/// Whether `[addr, addr + len)` lies in what the bootloader may erase or program:
/// STATE, ACTIVE or DFU (never the bootloader's sector, the project's sectors 2-4 or
/// the odometer's).
pub const fn bootloader_may_write(addr: u32, len: u32) -> bool {
    let end = match addr.checked_add(len) {
        Some(e) => e,
        None => return false,
    };
    (addr >= STATE_BASE && end <= STATE_BASE + STATE_LEN) || (addr >= ACTIVE_BASE && end <= DFU_END)
}

/// SRAM, where the application's initial stack pointer must point.
pub const SRAM: (u32, u32) = (0x2000_0000, 0x2002_0000);

/// Sector number of `addr`, and the sector's first address and length; `None` outside
/// the 1 MiB of flash.
pub const fn sector_of(addr: u32) -> Option<(u32, u32, u32)> {
    if addr < FLASH_BASE || addr >= FLASH_END {
        return None;
    }
    let off = addr - FLASH_BASE;
    if off < 0x1_0000 {
        let n = off / 0x4000;
        Some((n, FLASH_BASE + n * 0x4000, 0x4000))
    } else if off < 0x2_0000 {
        Some((4, FLASH_BASE + 0x1_0000, 0x1_0000))
    } else {
        let n = 4 + off / 0x2_0000;
        Some((n, FLASH_BASE + (n - 4) * 0x2_0000, 0x2_0000))
    }
}

/// Whether `[base, base + len)` is a run of whole sectors inside `WRITABLE`.
pub const fn whole_sectors(base: u32, len: u32) -> bool {
    let end = match base.checked_add(len) {
        Some(e) => e,
        None => return false,
    };
    if base < WRITABLE.0 || end > WRITABLE.1 || len == 0 {
        return false;
    }
    let mut a = base;
    while a < end {
        match sector_of(a) {
            Some((_, start, l)) if start == a => a += l,
            _ => return false,
        }
    }
    a == end
}

/// Whether `[base, base + len)` overlaps the project's sectors 2-4.
const fn overlaps_project(base: u32, len: u32) -> bool {
    base < PROJECT_FREE.0 + PROJECT_FREE.1 && PROJECT_FREE.0 < base + len
}

/// Whether every page of `pages` is a run of whole sectors in `WRITABLE`, outside the
/// project's sectors, each page's sectors below the next page.
const fn pages_fit(mut pages: &[u32], page_len: u32) -> bool {
    while let [base, rest @ ..] = pages {
        if !whole_sectors(*base, page_len) || overlaps_project(*base, page_len) {
            return false;
        }
        if let [next, ..] = rest {
            if *base + page_len > *next {
                return false;
            }
        }
        pages = rest;
    }
    true
}

/// Whether `pages` follow each other without a gap (ACTIVE: the application is linked
/// over all of them).
const fn contiguous(mut pages: &[u32], page_len: u32) -> bool {
    while let [base, rest @ ..] = pages {
        if let [next, ..] = rest {
            if *base + page_len != *next {
                return false;
            }
        }
        pages = rest;
    }
    true
}

// The layout in force, checked when it is compiled.
const _: () = {
    assert!(whole_sectors(STATE_BASE, STATE_LEN));
    assert!(BOOT_BASE + BOOT_LEN == STATE_BASE);
    assert!(pages_fit(ACTIVE_PAGES, PAGE_LEN));
    assert!(pages_fit(DFU_PAGES, PAGE_LEN));
    // embassy-boot's swap: DFU one page larger than ACTIVE.
    assert!(DFU_PAGES.len() == ACTIVE_PAGES.len() + 1);
    assert!(contiguous(ACTIVE_PAGES, PAGE_LEN));
    // DFU after ACTIVE, below the odometer.
    assert!(DFU_BASE >= ACTIVE_BASE + ACTIVE_LEN);
    assert!(DFU_END <= ODOMETER_BASE);
    // The project's sectors 2-4 are whole sectors between STATE and ACTIVE.
    assert!(PROJECT_FREE.0 + PROJECT_FREE.1 <= ACTIVE_BASE);
};

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sectors_follow_rm0090() {
        assert_eq!(sector_of(0x0800_0000), Some((0, 0x0800_0000, 0x4000)));
        assert_eq!(sector_of(0x0800_7FFF), Some((1, 0x0800_4000, 0x4000)));
        assert_eq!(sector_of(0x0800_C000), Some((3, 0x0800_C000, 0x4000)));
        assert_eq!(sector_of(0x0801_0000), Some((4, 0x0801_0000, 0x1_0000)));
        assert_eq!(sector_of(0x0802_0000), Some((5, 0x0802_0000, 0x2_0000)));
        assert_eq!(sector_of(0x080C_0000), Some((10, 0x080C_0000, 0x2_0000)));
        assert_eq!(sector_of(0x080F_FFFF), Some((11, 0x080E_0000, 0x2_0000)));
        assert_eq!(sector_of(0x0810_0000), None);
        assert_eq!(sector_of(0x07FF_FFFF), None);
    }

    #[test]
    fn no_partition_reaches_the_bootloader_or_the_odometer() {
        assert!(!whole_sectors(BOOT_BASE, 0x4000));
        assert!(!whole_sectors(0x080A_0000, 0x4_0000));
        assert!(whole_sectors(0x080A_0000, 0x2_0000));
        // Not a sector boundary.
        assert!(!whole_sectors(0x0800_9000, 0x1000));
        // The bootloader writes STATE, ACTIVE and DFU only.
        assert!(bootloader_may_write(STATE_BASE, STATE_LEN));
        assert!(bootloader_may_write(ACTIVE_BASE, ACTIVE_LEN));
        assert!(bootloader_may_write(DFU_BASE, 3 * PAGE_LEN));
        assert!(!bootloader_may_write(BOOT_BASE, 4));
        assert!(!bootloader_may_write(PROJECT_FREE.0, 4));
        assert!(!bootloader_may_write(
            PROJECT_FREE.0 + PROJECT_FREE.1 - 4,
            4
        ));
        assert!(!bootloader_may_write(ODOMETER_BASE, 4));
        assert!(!bootloader_may_write(ODOMETER_BASE - 4, 8));
        assert!(!bootloader_may_write(u32::MAX - 3, 8));
    }

    #[test]
    fn layout_c_is_the_issues_map() {
        assert_eq!(LAYOUT, Layout::C);
        // ACTIVE: sectors 5-6; DFU: 7-9; the project's: 2-4.
        let sectors = |pages: &[u32]| -> Vec<u32> {
            pages.iter().map(|&p| sector_of(p).unwrap().0).collect()
        };
        assert_eq!(sectors(ACTIVE_PAGES), [5, 6]);
        assert_eq!(sectors(DFU_PAGES), [7, 8, 9]);
        assert_eq!(ACTIVE_BASE, 0x0802_0000);
        assert_eq!(ACTIVE_LEN, 256 * 1024);
        assert_eq!(sector_of(PROJECT_FREE.0).unwrap().0, 2);
        assert_eq!(sector_of(PROJECT_FREE.0 + PROJECT_FREE.1 - 1).unwrap().0, 4);
        assert_eq!(UPDATE_IMAGE_MAX, 256 * 1024 - 72);
    }

    #[test]
    fn every_layout_is_named_by_its_id_and_fits_the_part() {
        for l in [Layout::A, Layout::B, Layout::C] {
            assert_eq!(Layout::from_id(l.id()), Some(l));
            assert_eq!(l.dfu_pages().len(), l.active_pages().len() + 1);
            assert!(l.in_active(l.active_base()));
            assert!(!l.in_active(l.active_base() + l.active_len()));
        }
        assert_eq!(
            Layout::from_id(0),
            None,
            "a header from before layouts had ids"
        );
        assert_eq!(Layout::from_id(4), None);
        // B's image (linked at 0x0800_8000) is outside C's ACTIVE, and C's outside B's.
        assert!(!Layout::C.in_active(Layout::B.active_base() + 0x201));
        assert!(!Layout::B.in_active(Layout::C.active_base() + 0x201));
    }
}
