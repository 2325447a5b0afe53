//! Virtual time of the board.
//!
//! Time advances three ways, never from the host's clock:
//! * **execution**: every instruction costs `cpi` core cycles (configurable, stated in
//!   every report) at the current HCLK; under the ART model (`cpu::Timing::Art`) plus
//!   the flash wait states of the fetches and reads its caches do not serve;
//! * **stalls**: a fetch from flash during a program or erase waits for its end; the core
//!   clock keeps running (DWT CYCCNT counts the stall);
//! * **sleep**: `wfi` (or a lockup) jumps to the next event; the core clock is gated, so
//!   CYCCNT does not count (SysTick and the peripherals do: they run on time, not on
//!   executed cycles).
//!
//! Master time is in picoseconds (`u64`: 213 days). Cycles are counted in milli-cycles
//! so that a fractional CPI accumulates exactly.

/// Picoseconds per second.
pub const PS_PER_S: u64 = 1_000_000_000_000;

/// The board's clock.
#[derive(Clone, Debug)]
pub struct Clock {
    hclk_hz: u64,
    cpi_milli: u64,
    /// Time at `base_mc`, ps.
    base_ps: u64,
    /// Milli-cycles at the last rebase.
    base_mc: u64,
    /// Core milli-cycles so far (execution and stalls, not sleep).
    mc: u64,
    /// Instructions executed.
    insns: u64,
    /// Time spent asleep, ps.
    sleep_ps: u64,
}

impl Clock {
    /// A clock at t = 0 with the core at `hclk_hz`, `cpi_milli` thousandths of a cycle
    /// per instruction.
    pub fn new(hclk_hz: u64, cpi_milli: u64) -> Self {
        Self {
            hclk_hz: hclk_hz.max(1),
            cpi_milli: cpi_milli.max(1),
            base_ps: 0,
            base_mc: 0,
            mc: 0,
            insns: 0,
            sleep_ps: 0,
        }
    }

    /// Now, ps since power-on.
    #[inline]
    pub fn now_ps(&self) -> u64 {
        self.base_ps + ps_of_mc(self.mc - self.base_mc, self.hclk_hz)
    }

    /// Now, ns since power-on.
    pub fn now_ns(&self) -> u64 {
        self.now_ps() / 1_000
    }

    /// Core cycles so far (execution and stalls; the basis of DWT CYCCNT).
    pub fn cycles(&self) -> u64 {
        self.mc / 1_000
    }

    /// Instructions executed so far.
    pub fn insns(&self) -> u64 {
        self.insns
    }

    /// Time spent asleep so far, ps.
    pub fn sleep_ps(&self) -> u64 {
        self.sleep_ps
    }

    /// The core clock, Hz.
    pub fn hclk_hz(&self) -> u64 {
        self.hclk_hz
    }

    /// Cycles per instruction, thousandths.
    pub fn cpi_milli(&self) -> u64 {
        self.cpi_milli
    }

    /// Account `n` executed instructions.
    #[inline]
    pub fn execute(&mut self, n: u64) {
        self.insns += n;
        self.mc += n * self.cpi_milli;
    }

    /// Account `insns` instructions and `mc` milli-cycles at once (a skipped polling
    /// loop's iterations: their execution and wait states).
    pub fn skip(&mut self, insns: u64, mc: u64) {
        self.insns += insns;
        self.mc += mc;
    }

    /// The core waits `mc` milli-cycles (wait states: stalled, clock running).
    #[inline]
    pub fn add_mc(&mut self, mc: u64) {
        self.mc += mc;
    }

    /// The core waits (stalled, clock running) until `t_ps`.
    pub fn stall_until(&mut self, t_ps: u64) {
        let now = self.now_ps();
        if t_ps > now {
            self.mc += mc_of_ps_ceil(t_ps - now, self.hclk_hz);
        }
    }

    /// The core sleeps (clock gated) until `t_ps`.
    pub fn sleep_until(&mut self, t_ps: u64) {
        let now = self.now_ps();
        if t_ps > now {
            self.sleep_ps += t_ps - now;
            self.base_ps = t_ps;
            self.base_mc = self.mc;
        }
    }

    /// The core clock changes to `hz` now.
    pub fn set_hclk(&mut self, hz: u64) {
        let now = self.now_ps();
        self.base_ps = now;
        self.base_mc = self.mc;
        self.hclk_hz = hz.max(1);
    }

    /// The clock's base: the time and milli-cycle count of its last rebase, and HCLK.
    pub fn base(&self) -> (u64, u64, u64) {
        (self.base_ps, self.base_mc, self.hclk_hz)
    }

    /// The time at milli-cycle count `mc` (after the last rebase), ps.
    pub fn time_at_mc(&self, mc: u64) -> u64 {
        self.base_ps + ps_of_mc(mc.saturating_sub(self.base_mc), self.hclk_hz)
    }

    /// The milli-cycle count at which time reaches `t_ps` (for the block hook's cheap
    /// "is an event due" compare).
    pub fn mc_at(&self, t_ps: u64) -> u64 {
        if t_ps <= self.base_ps {
            return self.base_mc;
        }
        self.base_mc
            .saturating_add(mc_of_ps_ceil(t_ps - self.base_ps, self.hclk_hz))
    }

    /// Milli-cycles so far.
    #[inline]
    pub fn mc(&self) -> u64 {
        self.mc
    }
}

/// Picoseconds of `mc` milli-cycles at `hz` (rounded down). In 64 bits while the product
/// fits (a tenth of a second of cycles since the clock's last rebase at 168 MHz: nearly
/// every call), in 128 otherwise: the same value either way, without the 128-bit
/// division's cost (it was 3 % of a run).
#[inline]
fn ps_of_mc(mc: u64, hz: u64) -> u64 {
    match mc.checked_mul(1_000_000_000) {
        Some(p) => p / hz,
        None => (mc as u128 * 1_000_000_000 / hz as u128) as u64,
    }
}

/// Milli-cycles at `hz` in `ps` picoseconds (rounded up), saturating; 64 bits while the
/// product fits, as [`ps_of_mc`].
#[inline]
fn mc_of_ps_ceil(ps: u64, hz: u64) -> u64 {
    match ps.checked_mul(hz) {
        Some(p) => p.div_ceil(1_000_000_000),
        None => (ps as u128 * hz as u128)
            .div_ceil(1_000_000_000)
            .min(u64::MAX as u128) as u64,
    }
}

/// How fast the emulation runs against the host's clock (reports only: nothing the
/// board does depends on it): virtual time per wall time over consecutive windows of
/// at least [`SpeedMeter::WINDOW`] of wall time, the slowest window kept.
#[derive(Clone, Debug, Default)]
pub struct SpeedMeter {
    /// The open window: its start (wall) and the virtual time then, ps.
    window: Option<(std::time::Instant, u64)>,
    /// The slowest complete window so far: virtual s per wall s.
    pub min_factor: Option<f64>,
}

impl SpeedMeter {
    /// Length of a window, wall time.
    pub const WINDOW: std::time::Duration = std::time::Duration::from_millis(100);

    /// The board has run to virtual time `now_ps`.
    pub fn tick(&mut self, now_ps: u64) {
        let wall = std::time::Instant::now();
        match self.window {
            None => self.window = Some((wall, now_ps)),
            Some((w0, v0)) => {
                let dt = wall.duration_since(w0);
                if dt >= Self::WINDOW {
                    let f = now_ps.saturating_sub(v0) as f64 / PS_PER_S as f64 / dt.as_secs_f64();
                    self.min_factor = Some(self.min_factor.map_or(f, |m| m.min(f)));
                    self.window = Some((wall, now_ps));
                }
            }
        }
    }
}

/// Cycles of a clock at `hz` in `ps` picoseconds (rounded down). In 64 bits while the
/// product fits, and past it (a free-running timer's time since its start: a tenth of a
/// second of a 84 MHz clock overflows) by tenths of a second while the remainder's
/// product fits (`hz` up to about 184 MHz): the same value as in 128 bits, without its
/// division.
pub fn cycles_in(ps: u64, hz: u64) -> u64 {
    const TENTH: u64 = PS_PER_S / 10;
    match ps.checked_mul(hz) {
        Some(p) => p / PS_PER_S,
        // ps·hz/10¹² = (q·10¹¹ + r)·hz/10¹² = q·hz/10 + r·hz/10¹²; with q·hz = 10a + b,
        // ⌊…⌋ = a + ⌊(b·10¹¹ + r·hz)/10¹²⌋.
        None => {
            let (q, r) = (ps / TENTH, ps % TENTH);
            q.checked_mul(hz)
                .and_then(|qh| {
                    let x = ((qh % 10) * TENTH).checked_add(r.checked_mul(hz)?)?;
                    Some(qh / 10 + x / PS_PER_S)
                })
                .unwrap_or_else(|| (ps as u128 * hz as u128 / PS_PER_S as u128) as u64)
        }
    }
}

/// Picoseconds of `n` cycles of a clock at `hz` (rounded up); 64 bits while the product
/// fits, and past it as [`cycles_in`], by whole seconds of cycles.
pub fn ps_of_cycles(n: u64, hz: u64) -> u64 {
    let hz = hz.max(1);
    match n.checked_mul(PS_PER_S) {
        Some(p) => p.div_ceil(hz),
        // n = q·hz + r: n·10¹²/hz = q·10¹² + r·10¹²/hz; with r·10⁶ = a·hz + b,
        // r·10¹²/hz = a·10⁶ + b·10⁶/hz (r, b < hz ≤ 2³²: the products fit).
        None if hz <= u64::from(u32::MAX) => {
            let (q, r) = (n / hz, n % hz);
            let x = r * 1_000_000;
            let (a, b) = (x / hz, x % hz);
            let frac = a * 1_000_000 + (b * 1_000_000).div_ceil(hz);
            match q.checked_mul(PS_PER_S).and_then(|p| p.checked_add(frac)) {
                Some(t) => t,
                None => (n as u128 * PS_PER_S as u128).div_ceil(hz as u128) as u64,
            }
        }
        None => (n as u128 * PS_PER_S as u128).div_ceil(hz as u128) as u64,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn execution_stall_and_sleep_advance_time_and_cycles_differently() {
        let mut c = Clock::new(168_000_000, 1_000);
        c.execute(168);
        assert_eq!(c.now_ps(), 1_000_000);
        assert_eq!(c.cycles(), 168);
        c.stall_until(2_000_000);
        assert_eq!(c.now_ps(), 2_000_000);
        assert_eq!(c.cycles(), 336, "a stall counts cycles");
        c.sleep_until(5_000_000);
        assert_eq!(c.now_ps(), 5_000_000);
        assert_eq!(c.cycles(), 336, "sleep does not");
        assert_eq!(c.sleep_ps(), 3_000_000);
        c.set_hclk(16_000_000);
        c.execute(16);
        assert_eq!(c.now_ps(), 6_000_000);
        assert!(c.mc_at(7_000_000) > c.mc());
    }

    #[test]
    fn the_64_bit_conversions_agree_with_128_bit_arithmetic_on_both_sides_of_overflow() {
        for hz in [
            16_000_000u64,
            84_000_000,
            168_000_000,
            184_467_440,
            1,
            7,
            4_294_967_295,
        ] {
            for x in [
                0u64,
                1,
                999,
                18_446_744_073,
                18_446_744_074,
                1 << 40,
                58_812_345_678_901,
                99_999_999_999_999,
                u64::MAX / 3,
                u64::MAX,
            ] {
                let want = (x as u128 * 1_000_000_000 / hz as u128) as u64;
                assert_eq!(ps_of_mc(x, hz), want, "ps_of_mc({x}, {hz})");
                let want = (x as u128 * hz as u128)
                    .div_ceil(1_000_000_000)
                    .min(u64::MAX as u128) as u64;
                assert_eq!(mc_of_ps_ceil(x, hz), want, "mc_of_ps_ceil({x}, {hz})");
                let want = (x as u128 * hz as u128 / PS_PER_S as u128) as u64;
                assert_eq!(cycles_in(x, hz), want, "cycles_in({x}, {hz})");
                let want = (x as u128 * PS_PER_S as u128).div_ceil(hz as u128) as u64;
                assert_eq!(ps_of_cycles(x, hz), want, "ps_of_cycles({x}, {hz})");
            }
        }
    }

    #[test]
    fn fractional_cpi_accumulates_exactly() {
        let mut c = Clock::new(1_000_000, 1_250);
        for _ in 0..4 {
            c.execute(1);
        }
        assert_eq!(c.cycles(), 5);
        assert_eq!(c.now_ps(), 5_000_000);
    }
}
