//! GPIO port (RM0090 §8): mode, output type, pulls, input and output data, atomic
//! set/reset, alternate functions.
//!
//! The model keeps the registers; what a pin *does* (drive a device input, read a
//! device output, float to a pull-up) is the board's wiring (`world.rs`). After every
//! write the port reports which pins changed their driven level ([`Gpio::driven`]).
//!
//! | off | name | reset (A / B / others) |
//! |---|---|---|
//! | 0x00 | MODER | 0xA800_0000 / 0x0000_0280 / 0 |
//! | 0x04 | OTYPER | 0 |
//! | 0x08 | OSPEEDR | 0x0C00_0000 / 0x0000_00C0 / 0 |
//! | 0x0C | PUPDR | 0x6400_0000 / 0x0000_0100 / 0 |
//! | 0x10 | IDR | read-only: the pins' levels |
//! | 0x14 | ODR | 0 |
//! | 0x18 | BSRR | write-only: set (15:0), reset (31:16); set wins |
//! | 0x1C | LCKR | 0 (lock sequence not modelled: the image never locks) |
//! | 0x20 | AFRL | 0 |
//! | 0x24 | AFRH | 0 |

use super::{lane, merge, no_read, no_write, Access};

/// A pin's mode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Mode {
    /// Input.
    Input,
    /// General-purpose output.
    Output,
    /// Alternate function.
    Alternate,
    /// Analog.
    Analog,
}

/// A pin's pull resistor.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pull {
    /// None.
    None,
    /// Pull-up.
    Up,
    /// Pull-down.
    Down,
}

/// One GPIO port.
#[derive(Clone, Debug)]
pub struct Gpio {
    /// Port index (0 = A).
    pub port: u8,
    moder: u32,
    otyper: u32,
    ospeedr: u32,
    pupdr: u32,
    odr: u32,
    lckr: u32,
    afr: [u32; 2],
}

impl Gpio {
    /// Port `port` (0 = A) at reset.
    pub fn new(port: u8) -> Self {
        let mut g = Self {
            port,
            moder: 0,
            otyper: 0,
            ospeedr: 0,
            pupdr: 0,
            odr: 0,
            lckr: 0,
            afr: [0; 2],
        };
        g.reset();
        g
    }

    /// Registers to their reset values (every pin floats).
    pub fn reset(&mut self) {
        let (moder, ospeedr, pupdr) = match self.port {
            0 => (0xA800_0000, 0x0C00_0000, 0x6400_0000),
            1 => (0x0000_0280, 0x0000_00C0, 0x0000_0100),
            _ => (0, 0, 0),
        };
        self.moder = moder;
        self.otyper = 0;
        self.ospeedr = ospeedr;
        self.pupdr = pupdr;
        self.odr = 0;
        self.lckr = 0;
        self.afr = [0; 2];
    }

    /// Mode of pin `n`.
    pub fn mode(&self, n: u8) -> Mode {
        match (self.moder >> (2 * n)) & 3 {
            0 => Mode::Input,
            1 => Mode::Output,
            2 => Mode::Alternate,
            _ => Mode::Analog,
        }
    }

    /// Internal pull of pin `n`.
    pub fn pull(&self, n: u8) -> Pull {
        match (self.pupdr >> (2 * n)) & 3 {
            1 => Pull::Up,
            2 => Pull::Down,
            _ => Pull::None,
        }
    }

    /// What the MCU drives on pin `n`: `Some(level)` for a push-pull output,
    /// `Some(false)` for an open-drain output at 0, `None` when it does not drive (input,
    /// analog, alternate function, open-drain at 1).
    pub fn driven(&self, n: u8) -> Option<bool> {
        if self.mode(n) != Mode::Output {
            return None;
        }
        let high = self.odr & (1 << n) != 0;
        if self.otyper & (1 << n) != 0 && high {
            None
        } else {
            Some(high)
        }
    }

    /// Read at `off`; `pins` is the level of every pin (IDR).
    pub fn read(&self, off: u32, size: usize, pins: u16) -> Access<u32> {
        let v = match off & !3 {
            0x00 => self.moder,
            0x04 => self.otyper,
            0x08 => self.ospeedr,
            0x0C => self.pupdr,
            0x10 => pins as u32,
            0x14 => self.odr,
            0x18 => 0,
            0x1C => self.lckr,
            0x20 => self.afr[0],
            0x24 => self.afr[1],
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off`.
    pub fn write(&mut self, off: u32, size: usize, value: u32) -> Access<()> {
        match off & !3 {
            0x00 => self.moder = merge(self.moder, off, size, value),
            0x04 => self.otyper = merge(self.otyper, off, size, value) & 0xFFFF,
            0x08 => self.ospeedr = merge(self.ospeedr, off, size, value),
            0x0C => self.pupdr = merge(self.pupdr, off, size, value),
            0x10 => {} // IDR is read-only: writes are ignored
            0x14 => self.odr = merge(self.odr, off, size, value) & 0xFFFF,
            0x18 => {
                let v = merge(0, off, size, value);
                let set = v & 0xFFFF;
                let reset = v >> 16;
                self.odr = (self.odr & !reset) | set;
            }
            0x1C => self.lckr = merge(self.lckr, off, size, value),
            0x20 => self.afr[0] = merge(self.afr[0], off, size, value),
            0x24 => self.afr[1] = merge(self.afr[1], off, size, value),
            _ => return no_write(off),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bsrr_set_wins_and_open_drain_releases_high() {
        let mut g = Gpio::new(4);
        assert_eq!(g.driven(11), None, "input after reset");
        g.write(0x18, 4, (1 << 11) | (1 << (11 + 16))).unwrap();
        g.write(0x00, 4, 1 << 22).unwrap();
        assert_eq!(g.driven(11), Some(true), "set wins over reset");
        g.write(0x18, 2, 0).unwrap();
        g.write(0x1A, 2, 1 << 11).unwrap(); // half-word write to the reset half
        assert_eq!(g.driven(11), Some(false));
        g.write(0x04, 4, 1 << 11).unwrap();
        g.write(0x18, 4, 1 << 11).unwrap();
        assert_eq!(g.driven(11), None, "open drain at 1 does not drive");
        assert!(g.read(0x28, 4, 0).is_err());
    }
}
