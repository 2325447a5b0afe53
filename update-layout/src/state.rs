//! The state record in STATE (sector 1): embassy-boot 0.7's format (docs/update.md, "The
//! state record"). The magics and the words' offsets, for the application that reads
//! them at boot (and the virtual board's tests); embassy-boot writes them.
//!
//! ```text
//!  offset  0        4        8        12       16       20       24 ... 16 KiB
//!         +--------+--------+--------+--------+--------+--------+-----------+
//!         | magic  | valid  | swap 0 | swap 1 | rev. 0 | rev. 1 |  erased   |
//!         +--------+--------+--------+--------+--------+--------+-----------+
//!  magic: F0F0F0F0 SWAP, D0D0D0D0 BOOT, C0C0C0C0 REVERT; anything else = BOOT
//!  valid: FFFFFFFF = progress words valid; anything else = "every step done"
//!  swap 0: ACTIVE -> DFU page 1  swap 1: DFU page 0 -> ACTIVE   (00000000 = done)
//!  rev. 0: ACTIVE -> DFU page 0  rev. 1: DFU page 1 -> ACTIVE
//! ```

/// An update was verified and marked: swap at the next reset (and, swapped, the new
/// image's trial until it confirms).
pub const SWAP: u32 = 0xF0F0_F0F0;
/// Booted and confirmed.
pub const BOOT: u32 = 0xD0D0_D0D0;
/// The last trial image was rolled back.
pub const REVERT: u32 = 0xC0C0_C0C0;
/// Offset of the magic word.
pub const MAGIC_OFFSET: u32 = 0;
/// Offset of the progress-valid word.
pub const VALID_OFFSET: u32 = 4;

/// What the state record says about the image that runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Boot {
    /// A confirmed image (or a board that never had an update).
    Confirmed,
    /// A new image on trial: it must confirm itself, or the next reset rolls it back.
    Trial,
    /// A trial image was rolled back: this is the image before it.
    RolledBack,
}

impl Boot {
    /// From the magic word.
    pub const fn from_magic(magic: u32) -> Self {
        match magic {
            SWAP => Self::Trial,
            REVERT => Self::RolledBack,
            _ => Self::Confirmed,
        }
    }
}
