//! # Modbus settings in flash
//!
//! [`ModbusSettings::to_bytes`] / [`ModbusSettings::from_bytes`], 6 bytes, declared once
//! as `ModbusSettingsLayout` (a `zerocopy` layout):
//!
//! ```text
//!  0        1          2                        6
//!  +--------+----------+------------------------+
//!  | unit u8| format u8| baud u32 (little-end.) |
//!  +--------+----------+------------------------+
//!  unit   1..=247
//!  format 0 = 8E1 (the only one defined; anything else is refused)
//!  baud   9600 | 19200 | 38400 | 57600 | 115200
//! ```
//!
//! A record that does not decode (wrong length, a value out of range) is refused whole:
//! the caller falls back to [`ModbusSettings::DEFAULT`].

use core::mem::size_of;

use zerocopy::byteorder::little_endian::U32;
use zerocopy::{FromBytes, Immutable, IntoBytes, KnownLayout, Unaligned};

use super::BITS_PER_CHAR;
use crate::machine::Machine;

/// The record as laid out in flash (see the module doc).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct ModbusSettingsLayout {
    unit: u8,
    format: u8,
    baud: U32,
}

/// The unit's serial-line settings (stored by a technician; see the module doc for the
/// record). The character format is fixed at 8E1.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ModbusSettings {
    /// Unit (server) address, 1–247.
    pub unit: u8,
    /// Baud rate, one of [`BAUD_RATES`](super::BAUD_RATES).
    pub baud: u32,
}

impl Default for ModbusSettings {
    fn default() -> Self {
        Self::DEFAULT
    }
}

impl ModbusSettings {
    /// Unit 1 at 19 200 baud, 8E1 (the Modbus serial line default).
    pub const DEFAULT: Self = Self {
        unit: 1,
        baud: 19_200,
    };
    /// Bytes in the record.
    pub const LEN: usize = size_of::<ModbusSettingsLayout>();
    /// The record's format byte for 8E1 (the only one defined).
    pub const FORMAT_8E1: u8 = 0;

    /// Validated settings.
    pub const fn new(unit: u8, baud: u32) -> Option<Self> {
        let s = Self { unit, baud };
        if s.is_valid() {
            Some(s)
        } else {
            None
        }
    }

    /// Unit 1–247 and a baud rate of [`BAUD_RATES`](super::BAUD_RATES).
    pub const fn is_valid(&self) -> bool {
        matches!(self.unit, 1..=247)
            && matches!(self.baud, 9_600 | 19_200 | 38_400 | 57_600 | 115_200)
    }

    /// The record (see the module doc).
    pub fn to_bytes(&self) -> [u8; Self::LEN] {
        let layout = ModbusSettingsLayout {
            unit: self.unit,
            format: Self::FORMAT_8E1,
            baud: self.baud.into(),
        };
        zerocopy::transmute!(layout)
    }

    /// From a record; `None` unless it is exactly a valid one.
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let l = ModbusSettingsLayout::read_from_bytes(b).ok()?;
        if l.format != Self::FORMAT_8E1 {
            return None;
        }
        Self::new(l.unit, l.baud.get())
    }

    /// The settings `ctrl`'s odometer log holds (record kind
    /// [`crate::odometer::kind::MODBUS`]), else [`Self::DEFAULT`]: what the board opens
    /// the line with at boot, and what the console's `modbus` shows.
    pub fn stored(ctrl: &mut dyn Machine) -> Self {
        let mut buf = [0u8; Self::LEN];
        ctrl.load_record(crate::odometer::kind::MODBUS, &mut buf)
            .and_then(|n| buf.get(..n))
            .and_then(Self::from_bytes)
            .unwrap_or(Self::DEFAULT)
    }

    /// One character (11 bits) on the line, µs, rounded up.
    pub const fn char_us(&self) -> u32 {
        (BITS_PER_CHAR * 1_000_000).div_ceil(nonzero(self.baud))
    }

    /// The longest silence allowed inside a frame (1.5 characters; 750 µs above
    /// 19 200 baud), µs, rounded up.
    pub const fn t1_5_us(&self) -> u32 {
        if self.baud > 19_200 {
            750
        } else {
            (BITS_PER_CHAR * 1_500_000).div_ceil(nonzero(self.baud))
        }
    }

    /// The silence that ends a frame (3.5 characters; 1750 µs above 19 200 baud), µs,
    /// rounded up.
    pub const fn t3_5_us(&self) -> u32 {
        if self.baud > 19_200 {
            1_750
        } else {
            (BITS_PER_CHAR * 3_500_000).div_ceil(nonzero(self.baud))
        }
    }
}

const fn nonzero(x: u32) -> u32 {
    if x == 0 {
        1
    } else {
        x
    }
}
