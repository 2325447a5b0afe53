//! SysTick (ARMv7-M ARM B3.3): a 24-bit down-counter on the core clock (or HCLK/8),
//! reloaded from `RVR` on the tick after it reaches 0; reaching 0 from 1 sets
//! `COUNTFLAG` (cleared by reading `CSR`) and, with `TICKINT`, pends the SysTick
//! exception. It counts in time, not in executed instructions: it keeps counting while
//! the core sleeps or is stalled.
//!
//! | addr | name | reset |
//! |---|---|---|
//! | 0xE000_E010 | CSR | 0 (ENABLE 0, TICKINT 1, CLKSOURCE 2, COUNTFLAG 16) |
//! | 0xE000_E014 | RVR | unknown (0 here) |
//! | 0xE000_E018 | CVR | unknown (0 here); any write clears it and COUNTFLAG |
//! | 0xE000_E01C | CALIB | 0x4000_5207 (no reference clock... TENMS for HCLK/8 = 21 MHz) |

use super::{lane, merge, no_read, no_write, Access};

/// SysTick.
#[derive(Clone, Debug, Default)]
pub struct SysTick {
    csr: u32,
    rvr: u32,
    /// Counter at `t0`.
    cvr0: u64,
    t0: u64,
    /// Zero-reaches since `t0` already accounted (pended / COUNTFLAG).
    zeros_seen: u64,
    countflag: bool,
    /// The next zero-reach's time, ps, at the core clock then (Hz), for the state as it
    /// is: `sync` has nothing to do before it, and `next_event` returns it. Cleared by
    /// every change of the state.
    due: Option<(u64, u64)>,
}

impl SysTick {
    /// At reset.
    pub fn reset(&mut self) {
        *self = Self::default();
    }

    fn enabled(&self) -> bool {
        self.csr & 1 != 0
    }

    fn freq(&self, hclk: u64) -> u64 {
        if self.csr & 4 != 0 {
            hclk
        } else {
            hclk / 8
        }
    }

    fn ticks(&self, now: u64, hclk: u64) -> u64 {
        crate::time::cycles_in(now.saturating_sub(self.t0), self.freq(hclk))
    }

    /// Zero-reaches within the first `k` ticks.
    fn zeros_in(&self, k: u64) -> u64 {
        let period = self.rvr as u64 + 1;
        if self.rvr == 0 {
            return 0;
        }
        if self.cvr0 > 0 {
            if k < self.cvr0 {
                0
            } else {
                1 + (k - self.cvr0) / period
            }
        } else if k == 0 {
            0
        } else {
            k / period
        }
    }

    fn value(&self, k: u64) -> u64 {
        if k < self.cvr0 {
            return self.cvr0 - k;
        }
        let period = self.rvr as u64 + 1;
        let j = (k - self.cvr0) % period;
        if j == 0 {
            0
        } else {
            period - j
        }
    }

    /// Bring it up to `now`; returns the number of new zero-reaches (each pends the
    /// exception when `TICKINT` is set).
    pub fn sync(&mut self, now: u64, hclk: u64) -> u64 {
        if !self.enabled() {
            return 0;
        }
        if self.due.is_some_and(|(h, t)| h == hclk && now < t) {
            return 0;
        }
        let z = self.zeros_in(self.ticks(now, hclk));
        let new = z.saturating_sub(self.zeros_seen);
        if new > 0 {
            self.countflag = true;
            self.zeros_seen = z;
        }
        self.due = (self.rvr != 0).then(|| (hclk, self.next_zero(hclk)));
        new
    }

    /// Whether a zero-reach pends the exception.
    pub fn tickint(&self) -> bool {
        self.csr & 2 != 0
    }

    /// When it next reaches zero, if it interrupts, ps.
    pub fn next_event(&self, hclk: u64) -> Option<u64> {
        if !self.enabled() || !self.tickint() || self.rvr == 0 {
            return None;
        }
        if let Some((h, t)) = self.due {
            if h == hclk {
                return Some(t);
            }
        }
        Some(self.next_zero(hclk))
    }

    /// When it next reaches zero (enabled, `rvr` not 0), ps: the first instant at which
    /// `zeros_in(ticks(now))` exceeds `zeros_seen` (`ps_of_cycles` inverts `ticks`
    /// exactly, rounded up).
    fn next_zero(&self, hclk: u64) -> u64 {
        let n = self.zeros_seen + 1;
        let period = self.rvr as u64 + 1;
        let k = if self.cvr0 > 0 {
            self.cvr0 + (n - 1) * period
        } else {
            n * period
        };
        self.t0 + crate::time::ps_of_cycles(k, self.freq(hclk))
    }

    fn rebase(&mut self, now: u64, hclk: u64) {
        self.due = None;
        if self.enabled() {
            let k = self.ticks(now, hclk);
            self.cvr0 = self.value(k);
        }
        self.t0 = now;
        self.zeros_seen = 0;
    }

    /// The core clock changes: keep the count.
    pub fn clock_change(&mut self, now: u64, old_hclk: u64) {
        self.sync(now, old_hclk);
        self.rebase(now, old_hclk);
    }

    /// Read at `off` from 0xE000_E010.
    pub fn read(&mut self, off: u32, size: usize, now: u64, hclk: u64) -> Access<u32> {
        self.sync(now, hclk);
        let v = match off & !3 {
            0x0 => {
                let v = self.csr | if self.countflag { 1 << 16 } else { 0 };
                self.countflag = false;
                v
            }
            0x4 => self.rvr,
            0x8 => {
                if self.enabled() {
                    self.value(self.ticks(now, hclk)) as u32
                } else {
                    self.cvr0 as u32
                }
            }
            0xC => 0x4000_5207,
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off` from 0xE000_E010.
    pub fn write(&mut self, off: u32, size: usize, value: u32, now: u64, hclk: u64) -> Access<()> {
        self.sync(now, hclk);
        self.due = None;
        match off & !3 {
            0x0 => {
                self.rebase(now, hclk);
                self.csr = merge(self.csr, off, size, value) & 7;
            }
            0x4 => {
                self.rebase(now, hclk);
                self.rvr = merge(self.rvr, off, size, value) & 0x00FF_FFFF;
            }
            0x8 => {
                self.cvr0 = 0;
                self.t0 = now;
                self.zeros_seen = 0;
                self.countflag = false;
            }
            0xC => {}
            _ => return no_write(off),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn twenty_khz_tick_at_168_mhz() {
        let hclk = 168_000_000;
        let mut s = SysTick::default();
        s.write(0x4, 4, 8_399, 0, hclk).unwrap();
        s.write(0x8, 4, 0, 0, hclk).unwrap();
        s.write(0x0, 4, 7, 0, hclk).unwrap();
        assert_eq!(s.next_event(hclk), Some(50_000_000), "first at 50 µs");
        assert_eq!(s.sync(49_999_999, hclk), 0);
        assert_eq!(s.sync(50_000_000, hclk), 1);
        assert_eq!(s.next_event(hclk), Some(100_000_000));
        assert_eq!(s.sync(1_000_000_000, hclk), 19, "20 per ms in all");
        assert_ne!(s.read(0x0, 4, 1_000_000_000, hclk).unwrap() & (1 << 16), 0);
        assert_eq!(
            s.read(0x0, 4, 1_000_000_000, hclk).unwrap() & (1 << 16),
            0,
            "cleared by the read"
        );
    }

    #[test]
    fn the_kept_next_zero_misses_no_zero_reach() {
        // At the picosecond before each zero-reach, at it and after it, and between
        // them, with a write of CVR and of RVR on the way: the kept time against a
        // SysTick that computes it afresh at every step.
        let hclk = 168_000_000;
        let mut s = SysTick::default();
        s.write(0x4, 4, 8_399, 0, hclk).unwrap();
        s.write(0x0, 4, 7, 0, hclk).unwrap();
        let mut zeros = 0;
        for round in 0..12u64 {
            let mut fresh = s.clone();
            fresh.due = None;
            let e = fresh.next_event(hclk).expect("interrupts");
            for t in [e - 13_000, e - 1, e, e + 1] {
                let mut fresh = s.clone();
                fresh.due = None;
                let (a, b) = (s.sync(t, hclk), fresh.sync(t, hclk));
                assert_eq!(a, b, "zero-reaches at {t} ps");
                zeros += a;
                assert_eq!(s.next_event(hclk), fresh.next_event(hclk), "at {t} ps");
            }
            match round {
                4 => s.write(0x8, 4, 0, e + 7, hclk).unwrap(),
                8 => s.write(0x4, 4, 4_199, e + 7, hclk).unwrap(),
                _ => {}
            }
        }
        assert_eq!(zeros, 12);
    }
}
