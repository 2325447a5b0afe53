//! Independent watchdog (RM0090 §21), clocked by the LSI.
//!
//! * `KR` 0xCCCC starts it (it cannot be stopped until a reset); 0xAAAA reloads the
//!   counter from `RLR`; 0x5555 enables writes to `PR` and `RLR` (any other key
//!   disables them again).
//! * The counter counts down from `RLR` at LSI / (4·2^PR); at 0 it resets the MCU
//!   (`RCC_CSR.IWDGRSTF`).
//! * A new `PR` or `RLR` is transferred to the LSI domain in up to 5 LSI cycles (`SR.PVU`
//!   / `SR.RVU` set meanwhile); a reload uses the `RLR` value in force then.
//! * **The LSI is not a crystal**: 17–47 kHz over parts and temperature (32 kHz
//!   typical, DS8626). The board takes its frequency as a parameter, so a nominal
//!   500 ms timeout may bite after 340 ms on a fast part.
//!
//! | off | name | reset |
//! |---|---|---|
//! | 0x00 | KR | write-only |
//! | 0x04 | PR | 0 |
//! | 0x08 | RLR | 0xFFF |
//! | 0x0C | SR | 0 |

use super::{lane, no_read, no_write, Access};
use crate::time::PS_PER_S;

/// The watchdog.
#[derive(Clone, Debug)]
pub struct Iwdg {
    /// LSI frequency, Hz.
    pub lsi_hz: u64,
    running: bool,
    unlocked: bool,
    pr: u32,
    rlr: u32,
    /// Values in force in the LSI domain, and when pending writes land.
    pr_active: u32,
    rlr_active: u32,
    pr_lands: Option<u64>,
    rlr_lands: Option<u64>,
    /// Counter value at `t_ref`.
    count_ref: u64,
    t_ref: u64,
    /// Reloads since the last reset (the board notes when each was written:
    /// `Soc::feeds`).
    pub reloads: u64,
}

impl Iwdg {
    /// A stopped watchdog on an LSI of `lsi_hz`.
    pub fn new(lsi_hz: u64) -> Self {
        Self {
            lsi_hz: lsi_hz.max(1),
            running: false,
            unlocked: false,
            pr: 0,
            rlr: 0xFFF,
            pr_active: 0,
            rlr_active: 0xFFF,
            pr_lands: None,
            rlr_lands: None,
            count_ref: 0xFFF,
            t_ref: 0,
            reloads: 0,
        }
    }

    /// A system reset stops it (the option bytes select the software watchdog).
    pub fn reset(&mut self) {
        *self = Self::new(self.lsi_hz);
    }

    /// Whether it runs.
    pub fn running(&self) -> bool {
        self.running
    }

    fn tick_ps(&self) -> u64 {
        (4u64 << self.pr_active) * PS_PER_S / self.lsi_hz
    }

    fn land(&mut self, now: u64) {
        if self.pr_lands.is_some_and(|t| now >= t) {
            // The counter keeps its value; it counts at the new rate from now on.
            let c = self.count(now);
            self.count_ref = c;
            self.t_ref = now;
            self.pr_active = self.pr;
            self.pr_lands = None;
        }
        if self.rlr_lands.is_some_and(|t| now >= t) {
            self.rlr_active = self.rlr;
            self.rlr_lands = None;
        }
    }

    fn count(&self, now: u64) -> u64 {
        self.count_ref
            .saturating_sub(now.saturating_sub(self.t_ref) / self.tick_ps())
    }

    /// When it expires (resets the MCU), ps; `None` if stopped.
    pub fn expiry(&self) -> Option<u64> {
        self.running
            .then(|| self.t_ref + self.count_ref * self.tick_ps())
    }

    /// The nominal timeout in force (RLR and PR as landed), ps.
    pub fn timeout_ps(&self) -> u64 {
        self.rlr_active as u64 * self.tick_ps()
    }

    /// The next time something changes on its own (a pending PR/RLR lands, or expiry).
    pub fn next_event(&self) -> Option<u64> {
        [self.pr_lands, self.rlr_lands, self.expiry()]
            .into_iter()
            .flatten()
            .min()
    }

    /// Bring it up to `now`; `true` if it has expired.
    pub fn sync(&mut self, now: u64) -> bool {
        self.land(now);
        self.expiry().is_some_and(|t| now >= t)
    }

    /// What a read at `off` returns until the next event (a pending `PR`/`RLR` landing
    /// is one). `None`: `KR`, and offsets not modelled.
    pub fn peek(&self, off: u32, size: usize) -> Option<u32> {
        let v = match off & !3 {
            0x04 => self.pr,
            0x08 => self.rlr,
            0x0C => u32::from(self.pr_lands.is_some()) | (u32::from(self.rlr_lands.is_some()) << 1),
            _ => return None,
        };
        Some(lane(v, off, size))
    }

    /// Read at `off`.
    pub fn read(&mut self, off: u32, size: usize, now: u64) -> Access<u32> {
        self.land(now);
        let v = match off & !3 {
            0x00 => 0,
            0x04 => self.pr,
            0x08 => self.rlr,
            0x0C => u32::from(self.pr_lands.is_some()) | (u32::from(self.rlr_lands.is_some()) << 1),
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off`; returns `true` when the write started the watchdog (the LSI must
    /// run).
    pub fn write(&mut self, off: u32, value: u32, now: u64) -> Access<bool> {
        self.land(now);
        let transfer = 5 * PS_PER_S / self.lsi_hz;
        match off & !3 {
            0x00 => match value & 0xFFFF {
                0xCCCC => {
                    if !self.running {
                        self.running = true;
                        self.count_ref = self.rlr_active as u64;
                        self.t_ref = now;
                        return Ok(true);
                    }
                }
                0xAAAA => {
                    self.count_ref = self.rlr_active as u64;
                    self.t_ref = now;
                    self.reloads += 1;
                    self.unlocked = false;
                }
                0x5555 => self.unlocked = true,
                _ => self.unlocked = false,
            },
            0x04 => {
                if self.unlocked && self.pr_lands.is_none() {
                    self.pr = value & 7;
                    self.pr_lands = Some(now + transfer);
                }
            }
            0x08 => {
                if self.unlocked && self.rlr_lands.is_none() {
                    self.rlr = value & 0xFFF;
                    self.rlr_lands = Some(now + transfer);
                }
            }
            0x0C => {}
            _ => return no_write(off),
        }
        Ok(false)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000_000;

    #[test]
    fn a_500_ms_watchdog_bites_after_340_ms_on_a_47_khz_lsi() {
        // The HAL's 500 ms at 32 kHz: PR 3 (/32), RLR 500.
        for (lsi, bite_ms) in [(32_000u64, 500u64), (47_000, 340)] {
            let mut w = Iwdg::new(lsi);
            w.write(0x00, 0x5555, 0).unwrap();
            w.write(0x04, 3, 0).unwrap();
            w.write(0x08, 500, 0).unwrap();
            w.write(0x00, 0xCCCC, MS).unwrap();
            w.write(0x00, 0xAAAA, MS).unwrap();
            let t = w.expiry().unwrap() - MS;
            assert!(t.abs_diff(bite_ms * MS) < MS, "{lsi} Hz: {t} ps");
        }
    }

    #[test]
    fn feeding_postpones_and_pr_needs_the_unlock_key() {
        let mut w = Iwdg::new(32_000);
        w.write(0x04, 6, 0).unwrap();
        assert_eq!(w.read(0x0C, 4, 0).unwrap(), 0, "locked: ignored");
        w.write(0x00, 0xCCCC, 0).unwrap();
        let e1 = w.expiry().unwrap();
        w.write(0x00, 0xAAAA, e1 / 2).unwrap();
        assert_eq!(w.expiry().unwrap(), e1 / 2 + e1);
        assert!(!w.sync(e1));
        assert!(w.sync(e1 / 2 + e1));
    }
}
