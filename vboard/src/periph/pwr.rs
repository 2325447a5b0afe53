//! PWR (RM0090 §5): the voltage scaling and the status of the regulator. The image's
//! clock set-up writes `CR.VOS`; nothing else of the power controller is modelled.
//!
//! | off | name | reset |
//! |---|---|---|
//! | 0x00 | CR | 0x0000_4000 (VOS scale 1) |
//! | 0x04 | CSR | 0x0000_4000 (VOSRDY) |

use super::{lane, merge, no_read, no_write, Access};

/// PWR.
#[derive(Clone, Debug)]
pub struct Pwr {
    cr: u32,
}

impl Default for Pwr {
    fn default() -> Self {
        Self { cr: 0x4000 }
    }
}

impl Pwr {
    /// At reset.
    pub fn reset(&mut self) {
        *self = Self::default();
    }

    /// Read at `off`.
    pub fn read(&self, off: u32, size: usize) -> Access<u32> {
        let v = match off & !3 {
            0x0 => self.cr,
            0x4 => 0x4000,
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off`.
    pub fn write(&mut self, off: u32, size: usize, value: u32) -> Access<()> {
        match off & !3 {
            0x0 => self.cr = merge(self.cr, off, size, value) & 0x0000_43FF,
            0x4 => {}
            _ => return no_write(off),
        }
        Ok(())
    }
}
