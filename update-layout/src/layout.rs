//! The partition map (docs/update.md, "Partition map"), shared by the bootloader, the
//! application's updater (and its `memory.x`, written by the root's build.rs) and the
//! virtual board: one place to change it, [`BUDGET_LAYOUT`].
//!
//! STM32F407 flash sectors: 0-3 16 KiB, 4 64 KiB, 5-11 128 KiB (RM0090 table 5).
//!
//! * sector 0: the bootloader; sector 1: STATE;
//! * ACTIVE: one embassy-boot page, the sectors from sector 2 on;
//! * DFU: two pages of ACTIVE's length, each in a run of whole 128 KiB sectors;
//! * sectors 10-11: the wear odometer, in no partition.

/// Flash base address.
pub const FLASH_BASE: u32 = 0x0800_0000;
/// First address of the odometer's sectors (10 and 11), never written by the bootloader.
pub const ODOMETER_BASE: u32 = 0x080C_0000;

/// The bootloader's own sector (0).
pub const BOOT_BASE: u32 = FLASH_BASE;
/// STATE: sector 1.
pub const STATE_BASE: u32 = 0x0800_4000;
/// STATE's length (all of sector 1).
pub const STATE_LEN: u32 = 16 * 1024;

/// ACTIVE: the application, its vector table first (sector 2 on).
pub const ACTIVE_BASE: u32 = 0x0800_8000;

/// **The switch between the two layouts, and the only one**: `true` is the issue's
/// budget layout (ACTIVE sectors 2-4, 96 KiB; DFU pages in sectors 5 and 6), in force
/// since the application with its updater fits it (issue 20's size pass: 97 906 B);
/// `false` the development layout it replaced (ACTIVE sectors 2-5, 224 KiB; DFU pages in
/// sectors 6-7 and 8-9), for an image that outgrows 96 KiB while it is worked on. The
/// bootloader, the application's link (build.rs writes its FLASH region from
/// [`ACTIVE_BASE`] and [`ACTIVE_LEN`]: an image over ACTIVE fails to link) and the
/// virtual board's tests all follow it. A board must be flashed anew with a probe
/// (bootloader and application, `bash tools/flash-board.sh`) when it changes.
pub const BUDGET_LAYOUT: bool = false;

/// ACTIVE's length: 224 KiB (sectors 2-5) in the development layout, 96 KiB (sectors
/// 2-4) in the budget layout.
pub const ACTIVE_LEN: u32 = if BUDGET_LAYOUT { 96 * 1024 } else { 224 * 1024 };
/// The two DFU pages' first addresses: sectors 6-7 and 8-9 (development), or sectors 5
/// and 6 (budget).
pub const DFU_PAGES: [u32; 2] = if BUDGET_LAYOUT {
    [0x0802_0000, 0x0804_0000]
} else {
    [0x0804_0000, 0x0808_0000]
};

/// The swap's unit: all of ACTIVE.
pub const PAGE_LEN: u32 = ACTIVE_LEN;

/// The update file's trailer, bytes: the signature (64), the image's length (4) and
/// the magic (4), after the image's bytes (docking-logic's `update` module draws the
/// file; `tools/sign-image.sh` writes it).
pub const TRAILER_LEN: u32 = 72;

/// The largest application an update can carry, bytes: its file (the image's bytes from
/// ACTIVE's first address, padded to whole words, then the trailer) is received into DFU
/// page 0, so the image gets a page less the trailer, not all of ACTIVE (`cargo xtask
/// size` holds the image to it).
pub const UPDATE_IMAGE_MAX: u32 = PAGE_LEN - TRAILER_LEN;

/// The lowest and highest (exclusive) address the bootloader may erase or program:
/// sectors 1-9.
pub const WRITABLE: (u32, u32) = (STATE_BASE, ODOMETER_BASE);

/// SRAM, where the application's initial stack pointer must point.
pub const SRAM: (u32, u32) = (0x2000_0000, 0x2002_0000);

/// Sector number of `addr`, and the sector's first address and length; `None` outside
/// the 1 MiB of flash. Out of line (issue 20): the image's flash checks inlined three
/// copies (-64 B).
#[cfg_attr(target_os = "none", inline(never))]
pub const fn sector_of(addr: u32) -> Option<(u32, u32, u32)> {
    if addr < FLASH_BASE || addr >= FLASH_BASE + 0x10_0000 {
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

// The layout, checked when it is compiled.
const _: () = {
    assert!(whole_sectors(STATE_BASE, STATE_LEN));
    assert!(whole_sectors(ACTIVE_BASE, ACTIVE_LEN));
    assert!(STATE_BASE + STATE_LEN == ACTIVE_BASE);
    // Each DFU page starts a sector, and the sectors it needs lie below the next page
    // (or the odometer).
    assert!(whole_sectors(DFU_PAGES[0], DFU_PAGES[1] - DFU_PAGES[0]));
    assert!(DFU_PAGES[1] - DFU_PAGES[0] >= PAGE_LEN);
    assert!(DFU_PAGES[0] >= ACTIVE_BASE + ACTIVE_LEN);
    assert!(whole_sectors(DFU_PAGES[1], ODOMETER_BASE - DFU_PAGES[1]));
    assert!(DFU_PAGES[1] + PAGE_LEN <= ODOMETER_BASE);
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
    }
}
