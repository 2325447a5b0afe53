//! General-purpose and advanced timers (RM0090 §14–§18): the time base (CNT, PSC, ARR,
//! one-pulse mode, update event and interrupt). Enough for stm32f4xx-hal's timer delay
//! and a free-running counter; capture/compare channels and the break input are not
//! modelled (an access to them is reported).
//!
//! The counter is derived from time when it runs: `CNT(t) = CNT0 + (t − t0)·f / (PSC+1)`,
//! wrapping at `ARR+1` (up-counting). In one-pulse mode the counter stops at the first
//! update event (CEN clears). `EGR.UG` reloads PSC, zeroes the counter and sets UIF
//! unless `CR1.URS` is set.
//!
//! | off | name | reset |
//! |---|---|---|
//! | 0x00 | CR1 | 0 (CEN 0, UDIS 1, URS 2, OPM 3, DIR 4, ARPE 7) |
//! | 0x04 | CR2 | 0 |
//! | 0x08 | SMCR | 0 (only 0: internal clock) |
//! | 0x0C | DIER | 0 (UIE 0) |
//! | 0x10 | SR | 0 (UIF 0; rc_w0) |
//! | 0x14 | EGR | write-only (UG 0) |
//! | 0x24 | CNT | 0 |
//! | 0x28 | PSC | 0 (buffered: takes effect at the next update) |
//! | 0x2C | ARR | 0xFFFF (0xFFFF_FFFF on TIM2/TIM5) |

use super::{lane, merge, no_read, no_write, Access};
use crate::time::PS_PER_S;

/// One timer's time base.
#[derive(Clone, Debug)]
pub struct Tim {
    /// Name (reports).
    pub name: &'static str,
    /// 32-bit counter (TIM2, TIM5) or 16-bit.
    wide: bool,
    cr1: u32,
    cr2: u32,
    smcr: u32,
    dier: u32,
    sr: u32,
    /// Counter value at `t0` (and while stopped).
    cnt0: u64,
    t0: u64,
    /// Update events since `t0` already accounted.
    updates_seen: u64,
    /// Active and preload prescaler.
    psc: u32,
    psc_preload: u32,
    arr: u32,
    /// The next update event's time, ps, at the timer clock then (Hz), for the state as
    /// it is: `sync` has nothing to do before it (a division less at each of the 60 000
    /// model updates a second of a moving axis). Cleared by every change of the state.
    due: Option<(u64, u64)>,
}

impl Tim {
    /// A timer at reset.
    pub fn new(name: &'static str, wide: bool) -> Self {
        let mut t = Self {
            name,
            wide,
            cr1: 0,
            cr2: 0,
            smcr: 0,
            dier: 0,
            sr: 0,
            cnt0: 0,
            t0: 0,
            updates_seen: 0,
            psc: 0,
            psc_preload: 0,
            arr: 0,
            due: None,
        };
        t.reset();
        t
    }

    /// Registers to reset values.
    pub fn reset(&mut self) {
        self.due = None;
        self.cr1 = 0;
        self.cr2 = 0;
        self.smcr = 0;
        self.dier = 0;
        self.sr = 0;
        self.cnt0 = 0;
        self.t0 = 0;
        self.updates_seen = 0;
        self.psc = 0;
        self.psc_preload = 0;
        self.arr = if self.wide { 0xFFFF_FFFF } else { 0xFFFF };
    }

    fn running(&self) -> bool {
        self.cr1 & 1 != 0
    }

    fn period_ticks(&self) -> u64 {
        self.arr as u64 + 1
    }

    /// Counter ticks from `t0` to `now`.
    fn ticks_since(&self, now: u64, clk: u64) -> u64 {
        // ⌊⌊t·clk/10¹²⌋/(PSC+1)⌋ = ⌊t·clk/(10¹²·(PSC+1))⌋; `cycles_in` stays in 64 bits
        // while it can (a 128-bit division at every timer access and event was 1.6 % of
        // a moving axis's run).
        crate::time::cycles_in(now.saturating_sub(self.t0), clk) / (self.psc as u64 + 1)
    }

    /// Time of `ticks` counter ticks after `t0`, ps (rounded up).
    fn time_of(&self, ticks: u64, clk: u64) -> u64 {
        let psc = self.psc as u64 + 1;
        self.t0
            + match ticks.checked_mul(psc) {
                Some(cycles) => crate::time::ps_of_cycles(cycles, clk),
                None => (ticks as u128 * PS_PER_S as u128 * psc as u128)
                    .div_ceil(clk.max(1) as u128) as u64,
            }
    }

    /// The counter now (running: derived from `t0`/`cnt0`).
    fn count(&self, now: u64, clk: u64) -> u64 {
        if self.running() && self.arr != 0 {
            (self.cnt0 + self.ticks_since(now, clk)) % self.period_ticks()
        } else {
            self.cnt0
        }
    }

    /// Restart the time reference at `now` from the current count.
    fn rebase(&mut self, now: u64, clk: u64) {
        self.due = None;
        self.cnt0 = self.count(now, clk);
        self.t0 = now;
        self.updates_seen = 0;
    }

    /// Bring the counter up to `now` (timer clock `clk` Hz): update events set UIF, a
    /// buffered prescaler takes effect at the first one, and in one-pulse mode the first
    /// one stops the counter.
    pub fn sync(&mut self, now: u64, clk: u64) {
        if self.due.is_some_and(|(c, t)| c == clk && now < t) {
            return;
        }
        self.due = None;
        while self.running() && self.arr != 0 {
            let period = self.period_ticks();
            let updates = (self.cnt0 + self.ticks_since(now, clk)) / period;
            if updates <= self.updates_seen {
                // The next one is due when the ticks reach the next multiple of the
                // period: `time_of` inverts `ticks_since` exactly (rounded up).
                let k = period * (self.updates_seen + 1) - self.cnt0;
                self.due = Some((clk, self.time_of(k, clk)));
                return;
            }
            if self.cr1 & 2 == 0 {
                self.sr |= 1; // UIF (UDIS clear)
            }
            let t_up = self.time_of(period * (self.updates_seen + 1) - self.cnt0, clk);
            if self.cr1 & 8 != 0 {
                // One-pulse: the counter stops at the update, back at 0.
                self.cr1 &= !1;
                self.cnt0 = 0;
                self.t0 = t_up;
                self.updates_seen = 0;
                self.psc = self.psc_preload;
                return;
            }
            if self.psc_preload != self.psc {
                self.t0 = t_up;
                self.cnt0 = 0;
                self.psc = self.psc_preload;
                self.updates_seen = 0;
                continue;
            }
            self.updates_seen = updates;
        }
    }

    /// When the next update event happens, if the counter runs and its interrupt is
    /// enabled, ps.
    pub fn next_event(&self, clk: u64) -> Option<u64> {
        if !self.running() || self.dier & 1 == 0 || self.arr == 0 {
            return None;
        }
        if let Some((c, t)) = self.due {
            if c == clk {
                return Some(t);
            }
        }
        Some(self.time_of(
            self.period_ticks() * (self.updates_seen + 1) - self.cnt0,
            clk,
        ))
    }

    /// The update interrupt line.
    pub fn irq(&self) -> bool {
        self.dier & 1 != 0 && self.sr & 1 != 0
    }

    /// Read at `off` (timer clock `clk`).
    pub fn read(&mut self, off: u32, size: usize, now: u64, clk: u64) -> Access<u32> {
        self.sync(now, clk);
        let v = match off & !3 {
            0x00 => self.cr1,
            0x04 => self.cr2,
            0x08 => self.smcr,
            0x0C => self.dier,
            0x10 => self.sr,
            0x14 => 0,
            0x24 => self.count(now, clk) as u32,
            0x28 => self.psc_preload,
            0x2C => self.arr,
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off`.
    pub fn write(&mut self, off: u32, size: usize, value: u32, now: u64, clk: u64) -> Access<()> {
        self.sync(now, clk);
        self.due = None;
        let o = off & !3;
        match o {
            0x00 => {
                let v = merge(self.cr1, off, size, value) & 0x3FF;
                self.rebase(now, clk);
                self.cr1 = v;
            }
            0x04 => self.cr2 = merge(self.cr2, off, size, value),
            0x08 => {
                let v = merge(self.smcr, off, size, value);
                if v != 0 {
                    return no_write(off); // slave modes / external clock not modelled
                }
                self.smcr = v;
            }
            0x0C => self.dier = merge(self.dier, off, size, value),
            0x10 => {
                // rc_w0: writing 0 clears, 1 leaves.
                let v = merge(0xFFFF_FFFF, off, size, value);
                self.sr &= v;
            }
            0x14 => {
                if merge(0, off, size, value) & 1 != 0 {
                    // UG: reload the prescaler, zero the counter, UIF unless URS.
                    self.psc = self.psc_preload;
                    self.cnt0 = 0;
                    self.t0 = now;
                    self.updates_seen = 0;
                    if self.cr1 & 4 == 0 {
                        self.sr |= 1;
                    }
                }
            }
            0x24 => {
                let v = merge(self.count(now, clk) as u32, off, size, value);
                self.cnt0 = if self.wide {
                    v as u64
                } else {
                    (v & 0xFFFF) as u64
                };
                self.t0 = now;
                self.updates_seen = 0;
            }
            0x28 => self.psc_preload = merge(self.psc_preload, off, size, value) & 0xFFFF,
            0x2C => {
                self.rebase(now, clk);
                let v = merge(self.arr, off, size, value);
                self.arr = if self.wide { v } else { v & 0xFFFF };
            }
            _ => return no_write(off),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn one_pulse_delay_as_the_hal_runs_it() {
        // TIM5 at 84 MHz, PSC 83 (1 MHz), ARR 999: CEN clears after 1 ms.
        let clk = 84_000_000;
        let mut t = Tim::new("TIM5", true);
        t.write(0x28, 4, 83, 0, clk).unwrap();
        t.write(0x2C, 4, 999, 0, clk).unwrap();
        t.write(0x14, 4, 1, 0, clk).unwrap();
        t.write(0x10, 4, 0, 0, clk).unwrap();
        t.write(0x00, 4, 1 | 8, 0, clk).unwrap();
        assert_eq!(t.read(0x00, 4, 999_999_999, clk).unwrap() & 1, 1);
        assert_eq!(
            t.read(0x00, 4, 1_000_000_000, clk).unwrap() & 1,
            0,
            "stopped at 1 ms"
        );
        assert_eq!(t.read(0x10, 4, 1_000_000_000, clk).unwrap() & 1, 1, "UIF");
    }

    #[test]
    fn the_kept_next_update_misses_no_update() {
        // At the picosecond before each update, at it and after it, and between them,
        // with writes of CNT, ARR and PSC on the way: against a timer that computes it
        // afresh at every step.
        let clk = 84_000_000;
        let mut t = Tim::new("TIM2", true);
        t.write(0x28, 4, 83, 0, clk).unwrap();
        t.write(0x2C, 4, 999, 0, clk).unwrap();
        t.write(0x14, 4, 1, 0, clk).unwrap();
        t.write(0x10, 4, 0, 0, clk).unwrap();
        t.write(0x0C, 4, 1, 0, clk).unwrap();
        t.write(0x00, 4, 1, 0, clk).unwrap();
        let mut updates = 0;
        for round in 0..12u64 {
            let mut fresh = t.clone();
            fresh.due = None;
            let e = fresh.next_event(clk).expect("updates interrupt");
            for now in [e - 13_000, e - 1, e, e + 1] {
                let mut fresh = t.clone();
                fresh.due = None;
                t.sync(now, clk);
                fresh.sync(now, clk);
                assert_eq!(t.sr, fresh.sr, "UIF at {now} ps");
                assert_eq!(t.next_event(clk), fresh.next_event(clk), "at {now} ps");
                if t.sr & 1 != 0 {
                    updates += 1;
                    t.write(0x10, 4, 0, now, clk).unwrap();
                }
            }
            match round {
                3 => t.write(0x24, 4, 500, e + 7, clk).unwrap(),
                6 => t.write(0x2C, 4, 499, e + 7, clk).unwrap(),
                9 => t.write(0x28, 4, 41, e + 7, clk).unwrap(),
                _ => {}
            }
        }
        assert_eq!(updates, 12);
    }

    #[test]
    fn free_running_counter_wraps() {
        let clk = 1_000_000;
        let mut t = Tim::new("TIM3", false);
        t.write(0x2C, 4, 9, 0, clk).unwrap();
        t.write(0x00, 4, 1, 0, clk).unwrap();
        assert_eq!(t.read(0x24, 4, 7_000_000, clk).unwrap(), 7);
        assert_eq!(t.read(0x24, 4, 13_000_000, clk).unwrap(), 3);
        assert!(
            t.read(0x34, 4, 0, clk).is_err(),
            "capture/compare not modelled"
        );
    }
}
