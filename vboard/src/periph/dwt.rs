//! DWT cycle counter and the debug control block (ARMv7-M ARM C1.8, C1.6).
//!
//! `CYCCNT` counts core cycles while `DWT_CTRL.CYCCNTENA` and `DEMCR.TRCENA` are set.
//! Core cycles are executed and stalled cycles: **it does not count while the core
//! sleeps** (`wfi`, clock gated), so it is not a wall clock for a sleeping firmware.
//!
//! | addr | name | reset |
//! |---|---|---|
//! | 0xE000_1000 | DWT_CTRL | 0x4000_0000 (NUMCOMP 4) |
//! | 0xE000_1004 | DWT_CYCCNT | 0 |
//! | 0xE000_1FB0 | DWT_LAR | write-only (ignored: no lock on the M4) |
//! | 0xE000_1FB4 | DWT_LSR | 0 (lock not implemented) |
//! | 0xE000_EDF0 | DHCSR | 0 (no debugger) |
//! | 0xE000_EDFC | DEMCR | 0 (TRCENA 24) |

use super::{lane, merge, no_read, no_write, Access};

/// DWT + DCB.
#[derive(Clone, Debug, Default)]
pub struct Dwt {
    ctrl: u32,
    demcr: u32,
    /// CYCCNT at `cycles_ref` core cycles.
    cyccnt_ref: u32,
    cycles_ref: u64,
}

impl Dwt {
    /// At reset (a system reset does not reset the debug logic on a real part, but with
    /// no debugger attached TRCENA is 0 after power-on; the image sets it at boot).
    pub fn reset(&mut self) {
        *self = Self {
            ctrl: 0x4000_0000,
            ..Self::default()
        };
    }

    /// Whether CYCCNT counts (`CYCCNTENA` and `TRCENA`).
    pub fn counting(&self) -> bool {
        self.ctrl & 1 != 0 && self.demcr & (1 << 24) != 0
    }

    /// CYCCNT at `cycles` core cycles.
    pub fn cyccnt(&self, cycles: u64) -> u32 {
        if self.counting() {
            self.cyccnt_ref
                .wrapping_add(cycles.wrapping_sub(self.cycles_ref) as u32)
        } else {
            self.cyccnt_ref
        }
    }

    fn freeze(&mut self, cycles: u64) {
        self.cyccnt_ref = self.cyccnt(cycles);
        self.cycles_ref = cycles;
    }

    /// Read at DWT offset `off` (from 0xE000_1000).
    pub fn read(&self, off: u32, size: usize, cycles: u64) -> Access<u32> {
        let v = match off & !3 {
            0x000 => self.ctrl,
            0x004 => self.cyccnt(cycles),
            0xFB4 => 0,
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at DWT offset `off`.
    pub fn write(&mut self, off: u32, size: usize, value: u32, cycles: u64) -> Access<()> {
        match off & !3 {
            0x000 => {
                self.freeze(cycles);
                self.ctrl = (merge(self.ctrl, off, size, value) & 0x0FFF_FFFF) | 0x4000_0000;
            }
            0x004 => {
                self.cyccnt_ref = merge(self.cyccnt(cycles), off, size, value);
                self.cycles_ref = cycles;
            }
            0xFB0 => {}
            _ => return no_write(off),
        }
        Ok(())
    }

    /// Read at debug offset `off` (from 0xE000_EDF0).
    pub fn read_dcb(&self, off: u32, size: usize) -> Access<u32> {
        let v = match off & !3 {
            0x0 => 0,
            0xC => self.demcr,
            _ => return no_read(0xDF0 + off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at debug offset `off` (from 0xE000_EDF0).
    pub fn write_dcb(&mut self, off: u32, size: usize, value: u32, cycles: u64) -> Access<()> {
        match off & !3 {
            0x0 => {} // DHCSR: needs the debug key and a debugger
            0xC => {
                self.freeze(cycles);
                self.demcr = merge(self.demcr, off, size, value) & 0x010F_07F1;
            }
            _ => return no_write(0xDF0 + off),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_only_when_enabled_at_both_places() {
        let mut d = Dwt::default();
        d.reset();
        d.write(0x0, 4, 1, 100).unwrap();
        assert_eq!(d.cyccnt(200), 0, "TRCENA still clear");
        d.write_dcb(0xC, 4, 1 << 24, 300).unwrap();
        assert_eq!(d.cyccnt(1_300), 1_000);
    }
}
