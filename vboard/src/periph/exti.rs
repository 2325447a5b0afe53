//! EXTI (RM0090 §12) and the SYSCFG port selection of its GPIO lines (§9).
//!
//! Lines 0–15 follow the pin of the port `SYSCFG_EXTICRx` selects; an edge enabled in
//! `RTSR`/`FTSR` sets the line's `PR` bit, which interrupts when `IMR` has it. `PR` is
//! cleared by writing 1. Lines 16–22 (PVD, RTC, USB…) are not wired to anything here.
//!
//! | addr | name | reset |
//! |---|---|---|
//! | 0x4001_3C00 | IMR | 0 |
//! | 0x4001_3C04 | EMR | 0 |
//! | 0x4001_3C08 | RTSR | 0 |
//! | 0x4001_3C0C | FTSR | 0 |
//! | 0x4001_3C10 | SWIER | 0 |
//! | 0x4001_3C14 | PR | 0 (rc_w1) |
//! | 0x4001_3800 | SYSCFG_MEMRMP | 0 |
//! | 0x4001_3804 | SYSCFG_PMC | 0 |
//! | 0x4001_3808–14 | SYSCFG_EXTICR1–4 | 0 |
//! | 0x4001_3820 | SYSCFG_CMPCR | 0 |

use super::{lane, merge, no_read, no_write, Access};

/// The NVIC interrupt number of each EXTI line 0–15.
pub fn irq_of_line(line: u8) -> u32 {
    match line {
        0 => 6,
        1 => 7,
        2 => 8,
        3 => 9,
        4 => 10,
        5..=9 => 23,
        _ => 40,
    }
}

/// EXTI and SYSCFG.
#[derive(Clone, Debug, Default)]
pub struct Exti {
    imr: u32,
    emr: u32,
    rtsr: u32,
    ftsr: u32,
    pr: u32,
    memrmp: u32,
    pmc: u32,
    exticr: [u32; 4],
    cmpcr: u32,
    /// Last sampled level of lines 0–15.
    levels: u16,
}

impl Exti {
    /// At reset.
    pub fn reset(&mut self) {
        *self = Self::default();
    }

    /// The port (0 = A) that drives line `line` (0–15).
    pub fn port_of(&self, line: u8) -> u8 {
        let r = self.exticr[(line / 4) as usize];
        ((r >> (4 * (line % 4))) & 0xF) as u8
    }

    /// Lines that watch an edge (RTSR or FTSR), 0–15.
    pub fn armed(&self) -> u16 {
        ((self.rtsr | self.ftsr) & 0xFFFF) as u16
    }

    /// Sample line `line` at `high`: an enabled edge sets its pending bit.
    pub fn sample(&mut self, line: u8, high: bool) {
        let bit = 1u16 << line;
        let was = self.levels & bit != 0;
        if was != high {
            if (high && self.rtsr & bit as u32 != 0) || (!high && self.ftsr & bit as u32 != 0) {
                self.pr |= bit as u32;
            }
            self.levels ^= bit;
        }
    }

    /// Whether line `line`'s pending bit is set.
    pub fn pending(&self, line: u8) -> bool {
        self.pr & (1 << line) != 0
    }

    /// Set the sampled level without edge detection (after a reset or a re-selection).
    pub fn set_level(&mut self, line: u8, high: bool) {
        let bit = 1u16 << line;
        if high {
            self.levels |= bit;
        } else {
            self.levels &= !bit;
        }
    }

    /// Interrupt numbers whose line is pending and unmasked.
    pub fn irqs(&self) -> impl Iterator<Item = u32> + '_ {
        // The set bits only: this runs at every interrupt line update.
        let mut set = self.pr & self.imr & 0xFFFF;
        std::iter::from_fn(move || {
            if set == 0 {
                return None;
            }
            let l = set.trailing_zeros() as u8;
            set &= set - 1;
            Some(irq_of_line(l))
        })
    }

    /// Read an EXTI register at `off` (from 0x4001_3C00).
    pub fn read(&self, off: u32, size: usize) -> Access<u32> {
        let v = match off & !3 {
            0x00 => self.imr,
            0x04 => self.emr,
            0x08 => self.rtsr,
            0x0C => self.ftsr,
            0x10 => 0,
            0x14 => self.pr,
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write an EXTI register at `off`.
    pub fn write(&mut self, off: u32, size: usize, value: u32) -> Access<()> {
        let m = 0x007F_FFFF;
        match off & !3 {
            0x00 => self.imr = merge(self.imr, off, size, value) & m,
            0x04 => self.emr = merge(self.emr, off, size, value) & m,
            0x08 => self.rtsr = merge(self.rtsr, off, size, value) & m,
            0x0C => self.ftsr = merge(self.ftsr, off, size, value) & m,
            0x10 => self.pr |= merge(0, off, size, value) & self.imr & m,
            0x14 => self.pr &= !(merge(0, off, size, value) & m),
            _ => return no_write(off),
        }
        Ok(())
    }

    /// Read a SYSCFG register at `off` (from 0x4001_3800).
    pub fn read_syscfg(&self, off: u32, size: usize) -> Access<u32> {
        let v = match off & !3 {
            0x00 => self.memrmp,
            0x04 => self.pmc,
            0x08 | 0x0C | 0x10 | 0x14 => self.exticr[((off & !3) - 8) as usize / 4],
            0x20 => self.cmpcr,
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write a SYSCFG register at `off`.
    pub fn write_syscfg(&mut self, off: u32, size: usize, value: u32) -> Access<()> {
        match off & !3 {
            0x00 => self.memrmp = merge(self.memrmp, off, size, value) & 7,
            0x04 => self.pmc = merge(self.pmc, off, size, value),
            0x08 | 0x0C | 0x10 | 0x14 => {
                let i = ((off & !3) - 8) as usize / 4;
                self.exticr[i] = merge(self.exticr[i], off, size, value) & 0xFFFF;
            }
            0x20 => self.cmpcr = merge(self.cmpcr, off, size, value) & 1,
            _ => return no_write(off),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn falling_edge_on_pb0_pends_exti0() {
        let mut e = Exti::default();
        e.write_syscfg(0x08, 4, 1).unwrap(); // line 0 ← port B
        assert_eq!(e.port_of(0), 1);
        e.set_level(0, true);
        e.write(0x0C, 4, 1).unwrap(); // falling
        e.write(0x00, 4, 1).unwrap(); // unmasked
        e.sample(0, true);
        assert_eq!(e.irqs().count(), 0);
        e.sample(0, false);
        assert_eq!(e.irqs().collect::<Vec<_>>(), vec![6]);
        e.write(0x14, 4, 1).unwrap();
        assert_eq!(e.irqs().count(), 0);
    }
}
