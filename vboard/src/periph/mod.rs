//! Register-level models of the STM32F407 peripherals the image uses, one file each,
//! written from RM0090 (and the Cortex-M4 TRM for the core peripherals).
//!
//! Every model declares its register map in one place (offset, name, reset value,
//! access), restores it in `reset()`, and dispatches reads and writes by offset. An
//! access to a register that is not modelled returns [`Unmodelled`]: the board reports
//! it and stops, it is never silently read as zero.

pub mod art;
pub mod dma;
pub mod dwt;
pub mod exti;
pub mod flash;
pub mod gpio;
pub mod iwdg;
pub mod nvic;
pub mod pwr;
pub mod rcc;
pub mod systick;
pub mod tim;
pub mod usart;

/// An access the models do not implement (offset within the peripheral).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Unmodelled {
    /// Offset from the peripheral's base.
    pub offset: u32,
    /// Write (`true`) or read.
    pub write: bool,
}

/// Result of a register access.
pub type Access<T> = Result<T, Unmodelled>;

/// `Err` for an unmodelled read at `offset`.
pub fn no_read<T>(offset: u32) -> Access<T> {
    Err(Unmodelled {
        offset,
        write: false,
    })
}

/// `Err` for an unmodelled write at `offset`.
pub fn no_write<T>(offset: u32) -> Access<T> {
    Err(Unmodelled {
        offset,
        write: true,
    })
}

/// Merge a `size`-byte write of `value` at byte `lane` (offset & 3) into the 32-bit
/// register `old` (byte and half-word writes to word registers, as the AHB/APB bridges
/// do for the peripherals that allow them).
pub fn merge(old: u32, offset: u32, size: usize, value: u32) -> u32 {
    let shift = (offset & 3) * 8;
    let mask: u32 = match size {
        1 => 0xFF,
        2 => 0xFFFF,
        _ => return value,
    };
    (old & !(mask << shift)) | ((value & mask) << shift)
}

/// Extract a `size`-byte read at byte `lane` (offset & 3) from the 32-bit register `v`.
pub fn lane(v: u32, offset: u32, size: usize) -> u32 {
    let shift = (offset & 3) * 8;
    match size {
        1 => (v >> shift) & 0xFF,
        2 => (v >> shift) & 0xFFFF,
        _ => v,
    }
}
