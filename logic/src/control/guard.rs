//! Overload protection and load-cell health.
//!
//! ## Overload
//! Two limits, checked on every sample:
//! * a **hard limit** (default 300 N: the nominal peak is 206.34 N, the cell is rated
//!   500 N), always;
//! * a **per-phase envelope** while the rod is in the cone: the nominal Eq. 7 force of
//!   the current depth, maximised over ±`window_um` (so a position error of up to half a
//!   millimetre at a phase boundary cannot trip it), times `1 + rel_pct/100`, plus
//!   `abs_mn` (defaults 25 % and 30 N: with 0.3 N RMS sensor noise the nominal profile
//!   stays ≥ 50 N below it, while a jam crosses it within a few newtons of extra load).
//!
//! **Both ways.** A pulling force (the load cell in tension) beyond `tension_mn`, or a
//! bridge wired in reverse (compression then reads negative), is its own verdict,
//! [`Verdict::Tension`]: not "zero force, no wear, no trip".
//!
//! **Spike rejection without delay.** A sample over a limit trips at once if it is
//! *plausible*: the previous sample was over the limit too, or this one is within
//! `slew_mn` of the previous one (a load that grows, as a jam does). An implausible jump
//! over the limit is held for one sample: if the next sample is over as well, it trips
//! then. So an isolated single-sample spike never trips, a ramping overload trips on its
//! first over-limit sample, and a step overload is delayed by at most one sample period.
//!
//! **Warning with hysteresis**: above `warn_pct` % of the limit in force the guard warns;
//! the warning clears below `warn_clear_pct` %.
//!
//! ## Sensor health ([`SensorMonitor`])
//! No sample for 3 sample periods (disconnect: the HX711's DOUT stays high), 2 samples
//! in a row at an ADC rail (saturation), 32 identical codes in a row (stuck converter:
//! a live HX711 at gain 128 has tens of counts of noise), and an implausible tare are
//! named faults.

use crate::profile::{BOUNDARY_UM, STROKE_UM};

/// Overload-guard configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct GuardConfig {
    /// Hard force limit, mN (any state).
    pub hard_limit_mn: i32,
    /// Largest pulling force (negative reading), mN, as a positive number.
    pub tension_mn: i32,
    /// Envelope: relative margin over the nominal force, percent.
    pub rel_pct: u32,
    /// Envelope: absolute margin over the nominal force, mN.
    pub abs_mn: i32,
    /// Largest sample-to-sample change taken as a real load change, mN.
    pub slew_mn: i32,
    /// Warn above this percentage of the limit in force.
    pub warn_pct: u32,
    /// Clear the warning below this percentage.
    pub warn_clear_pct: u32,
    /// The machine's nominal contact force along the stroke (the envelope's base): Eq. 7
    /// by default ([`EQ7_NOMINAL`]); another machine's from its force model
    /// ([`NominalProfile::from_fn`], computed on the host at commissioning).
    pub nominal: &'static NominalProfile,
}

/// A machine's nominal N3 per 0.1 mm cell of insertion depth over the 30 mm stroke,
/// maximised over the cell ± [`ENVELOPE_WINDOW_UM`], mN (`i32`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NominalProfile {
    /// The table, cell `i` covering depths `[100·i, 100·(i+1))` µm.
    pub n3_max_mn: [i32; ENV_LEN],
}

/// Eq. 7's nominal profile, computed at build time: the paper's machine.
pub static EQ7_NOMINAL: NominalProfile = NominalProfile {
    n3_max_mn: NOMINAL_MAX_MN,
};

impl NominalProfile {
    /// From a force model: `n3_n(depth_um)` is the nominal N3 at a depth (N); `jumps`
    /// are the depths where it is discontinuous (each is sampled exactly, as well as
    /// every 10 µm), so the maximum over each window is found. Non-finite or negative
    /// values count as 0; values are clamped to ±2 000 N.
    pub fn from_fn(n3_n: impl Fn(i32) -> f64, jumps: &[i32]) -> Self {
        let mut t = [0i32; ENV_LEN];
        for (i, cell) in t.iter_mut().enumerate() {
            let lo = (i as i32 * ENV_STEP_UM - ENVELOPE_WINDOW_UM).max(0);
            let hi = ((i as i32 + 1) * ENV_STEP_UM + ENVELOPE_WINDOW_UM).min(STROKE_UM);
            let mut max_n = 0.0f64;
            let mut take = |d: i32| {
                let f = n3_n(d);
                if f.is_finite() && f > max_n {
                    max_n = f.min(2_000.0);
                }
            };
            let mut d = lo;
            while d <= hi {
                take(d);
                d += 10;
            }
            for &j in jumps {
                // Both sides of a jump inside the window.
                if (lo..=hi).contains(&j) {
                    take(j);
                }
                if (lo..=hi).contains(&(j - 1)) {
                    take(j - 1);
                }
            }
            *cell = (max_n * 1000.0) as i32;
        }
        Self { n3_max_mn: t }
    }

    /// The largest nominal N3 over the stroke, mN.
    pub fn peak_mn(&self) -> i32 {
        self.n3_max_mn.iter().copied().max().unwrap_or(0)
    }
}

impl GuardConfig {
    /// Defaults (see the module doc for why).
    pub const DEFAULT: Self = Self {
        hard_limit_mn: 300_000,
        // Ten times the cell's noise and beyond a 20 N tare drift; the docking forces are
        // all compressive (N3 ≥ 107 N in the cone), so a reversed bridge trips at the mouth.
        tension_mn: 30_000,
        rel_pct: 25,
        abs_mn: 30_000,
        slew_mn: 40_000,
        warn_pct: 90,
        warn_clear_pct: 80,
        nominal: &EQ7_NOMINAL,
    };
}

impl Default for GuardConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Resolution of the envelope table, µm.
pub const ENV_STEP_UM: i32 = 100;
/// Entries of the envelope table (0..=30 mm).
pub const ENV_LEN: usize = (STROKE_UM / ENV_STEP_UM) as usize + 1;
/// The nominal force is maximised over ±this depth around each table cell, µm (half a
/// millimetre of position error at a phase boundary cannot trip the envelope).
pub const ENVELOPE_WINDOW_UM: i32 = 500;

/// Eq. 7's N3 at insertion depth `depth_um` (clamped to the stroke), N: a `const fn`
/// twin of [`crate::profile::forces_at_depth_um`] (tested bit-equal) so the envelope is
/// computed at build time and the firmware carries no floating-point code for it.
pub(crate) const fn n3_at_depth_n(depth_um: i32) -> f64 {
    let d = if depth_um < 0 {
        0
    } else if depth_um > STROKE_UM {
        STROKE_UM
    } else {
        depth_um
    };
    let t = d as f64 / 1200.0;
    if d < BOUNDARY_UM[0] {
        112.64
    } else if d < BOUNDARY_UM[1] {
        115.05
    } else if d < BOUNDARY_UM[2] {
        17429.0 / (175.2 - t)
    } else {
        3989.0 / (t + 6.887)
    }
}

/// Nominal N3 maximised over each cell ± [`ENVELOPE_WINDOW_UM`], mN, computed at build
/// time (the profile is monotone between boundaries, so sampling every 10 µm plus the
/// 14.934 mm jump itself finds the maximum).
// Evaluated by the compiler: an out-of-range index here fails the build, it cannot panic
// on the board (and `get_mut` is not usable in const context).
#[allow(clippy::indexing_slicing)]
const NOMINAL_MAX_MN: [i32; ENV_LEN] = {
    let mut t = [0i32; ENV_LEN];
    let mut i = 0;
    while i < ENV_LEN {
        let lo = i as i32 * ENV_STEP_UM - ENVELOPE_WINDOW_UM;
        let hi = (i as i32 + 1) * ENV_STEP_UM + ENVELOPE_WINDOW_UM;
        let mut max_n = 0.0f64;
        let mut d = if lo < 0 { 0 } else { lo };
        while d <= hi && d <= STROKE_UM {
            let f = n3_at_depth_n(d);
            if f > max_n {
                max_n = f;
            }
            d += 10;
        }
        if lo <= BOUNDARY_UM[2] && BOUNDARY_UM[2] <= hi {
            let f = n3_at_depth_n(BOUNDARY_UM[2]);
            if f > max_n {
                max_n = f;
            }
        }
        t[i] = (max_n * 1000.0) as i32;
        i += 1;
    }
    t
};

/// What the guard says about one sample.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Verdict {
    /// Within limits.
    Ok,
    /// Above the warning level (with hysteresis).
    Warn,
    /// Over a limit that is held for one sample as a possible spike.
    Suspect,
    /// Overload: stop now.
    Trip {
        /// The limit that was exceeded, mN.
        limit_mn: i32,
    },
    /// Tension (or a reversed bridge): stop now.
    Tension {
        /// The (negative) limit that was passed, mN.
        limit_mn: i32,
    },
}

impl Verdict {
    /// Whether the propulsion must stop.
    pub const fn stops(&self) -> bool {
        matches!(self, Self::Trip { .. } | Self::Tension { .. })
    }
}

/// The overload guard.
pub struct OverloadGuard {
    cfg: GuardConfig,
    /// Upper envelope per 0.1 mm of depth, mN.
    envelope_mn: [i32; ENV_LEN],
    prev_mn: Option<i32>,
    prev_over: bool,
    warning: bool,
    spikes_rejected: u32,
}

impl OverloadGuard {
    /// A guard with its envelope from the configuration's nominal profile.
    pub fn new(cfg: GuardConfig) -> Self {
        // Integer margins over the nominal table.
        let mut envelope_mn = [0i32; ENV_LEN];
        for (e, &nominal_mn) in envelope_mn.iter_mut().zip(cfg.nominal.n3_max_mn.iter()) {
            let scaled = nominal_mn as i64 * (100 + cfg.rel_pct as i64) / 100;
            *e = (scaled + cfg.abs_mn as i64).min(cfg.hard_limit_mn as i64) as i32;
        }
        Self {
            cfg,
            envelope_mn,
            prev_mn: None,
            prev_over: false,
            warning: false,
            spikes_rejected: 0,
        }
    }

    /// The limit in force at `depth_um` (`None` = not in the cone: hard limit only), mN.
    pub fn limit_mn(&self, depth_um: Option<i32>) -> i32 {
        match depth_um {
            Some(d) if (0..=STROKE_UM).contains(&d) => {
                let i = (d / ENV_STEP_UM) as usize;
                self.envelope_mn
                    .get(i)
                    .copied()
                    .unwrap_or(self.cfg.hard_limit_mn)
            }
            _ => self.cfg.hard_limit_mn,
        }
    }

    /// Judge one sample of `force_mn` at `depth_um`.
    pub fn check(&mut self, force_mn: i32, depth_um: Option<i32>) -> Verdict {
        self.check_against(force_mn, self.limit_mn(depth_um))
    }

    /// Judge one sample of `force_mn` against `limit` (from [`Self::limit_mn`]).
    pub fn check_against(&mut self, force_mn: i32, limit: i32) -> Verdict {
        let pull = force_mn < -self.cfg.tension_mn;
        let over = force_mn > limit || pull;
        let verdict = if over {
            // Over a limit: a stop, unless the jump from the last sample is implausible
            // (a spike is held one sample).
            let plausible = self.prev_over
                || self
                    .prev_mn
                    .is_none_or(|p| force_mn.abs_diff(p) <= self.cfg.slew_mn as u32);
            if !plausible {
                Verdict::Suspect
            } else if pull {
                Verdict::Tension {
                    limit_mn: -self.cfg.tension_mn,
                }
            } else {
                Verdict::Trip { limit_mn: limit }
            }
        } else {
            if self.prev_over && !self.warning {
                // The previous sample was over the limit and this one is not: a spike.
                self.spikes_rejected = self.spikes_rejected.saturating_add(1);
            }
            // Percent of the limit, compared by multiplication (no division per sample).
            let f100 = force_mn.max(0) as i64 * 100;
            if f100 >= self.cfg.warn_pct as i64 * limit as i64 {
                self.warning = true;
            } else if f100 < self.cfg.warn_clear_pct as i64 * limit as i64 {
                self.warning = false;
            }
            if self.warning {
                Verdict::Warn
            } else {
                Verdict::Ok
            }
        };
        self.prev_over = over;
        self.prev_mn = Some(force_mn);
        verdict
    }

    /// Forget the sample history (after a gap in samples or a fault clear).
    pub fn reset(&mut self) {
        self.prev_mn = None;
        self.prev_over = false;
        self.warning = false;
    }

    /// Single-sample spikes rejected so far.
    pub fn spikes_rejected(&self) -> u32 {
        self.spikes_rejected
    }

    /// Configuration.
    pub fn config(&self) -> &GuardConfig {
        &self.cfg
    }
}

/// Load-cell faults.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SensorFault {
    /// No sample for 3 sample periods.
    Disconnected,
    /// Two samples in a row at an ADC rail.
    Saturated,
    /// 32 identical codes in a row.
    Stuck,
}

/// Samples at a rail in a row that mean saturation.
pub const RAIL_SAMPLES: u8 = 2;
/// Identical codes in a row that mean a stuck converter.
pub const STUCK_SAMPLES: u16 = 32;
/// Sample periods without a sample that mean a disconnect.
pub const DISCONNECT_PERIODS: u64 = 3;

/// Watches the raw sample stream.
pub struct SensorMonitor {
    period_us: u64,
    last_sample_us: u64,
    last_code: Option<i32>,
    same_count: u16,
    rail_count: u8,
}

impl SensorMonitor {
    /// A monitor for `rate_sps`, started at `now_us`; the first sample is allowed the
    /// HX711's settling time (4 periods) on top of the disconnect timeout.
    pub fn new(rate_sps: u32, now_us: u64) -> Self {
        let period_us = 1_000_000 / rate_sps.max(1) as u64;
        Self {
            period_us,
            last_sample_us: now_us + 4 * period_us,
            last_code: None,
            same_count: 0,
            rail_count: 0,
        }
    }

    /// Sample period, µs.
    pub fn period_us(&self) -> u64 {
        self.period_us
    }

    /// A sample `code` arrived at `now_us`.
    pub fn on_sample(
        &mut self,
        code: i32,
        now_us: u64,
        rail_min: i32,
        rail_max: i32,
    ) -> Option<SensorFault> {
        self.last_sample_us = now_us;
        if code <= rail_min || code >= rail_max {
            self.rail_count = self.rail_count.saturating_add(1);
        } else {
            self.rail_count = 0;
        }
        if self.last_code == Some(code) {
            self.same_count = self.same_count.saturating_add(1);
        } else {
            self.same_count = 1;
        }
        self.last_code = Some(code);
        if self.rail_count >= RAIL_SAMPLES {
            Some(SensorFault::Saturated)
        } else if self.same_count >= STUCK_SAMPLES {
            Some(SensorFault::Stuck)
        } else {
            None
        }
    }

    /// The latest code, if the load cell answers with it: a sample has arrived (since
    /// the start or the last [`Self::reset`]) and it is neither at a rail nor the end of
    /// a stuck run. The trial boot after a field update asks (issue 21: "flash and
    /// sensor answer"), and confirms only on two different codes: one code alone is
    /// also what a stuck converter, or a readout that reads a constant, gives before
    /// [`STUCK_SAMPLES`] have passed. Nothing on the sample path reads it.
    pub fn answered_code(&self) -> Option<i32> {
        self.last_code
            .filter(|_| self.rail_count == 0 && self.same_count < STUCK_SAMPLES)
    }

    /// When the last sample arrived, µs; `None` before the first and after a reset.
    pub fn last_sample_us(&self) -> Option<u64> {
        self.last_code.map(|_| self.last_sample_us)
    }

    /// Check for a disconnect at `now_us` (no sample for 3 periods).
    pub fn check_timeout(&self, now_us: u64) -> Option<SensorFault> {
        (now_us.saturating_sub(self.last_sample_us) > DISCONNECT_PERIODS * self.period_us)
            .then_some(SensorFault::Disconnected)
    }

    /// Restart the timeout and counters (after a fault clear).
    pub fn reset(&mut self, now_us: u64) {
        self.last_sample_us = now_us;
        self.last_code = None;
        self.same_count = 0;
        self.rail_count = 0;
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    #[test]
    fn a_nominal_profile_from_eq7_is_the_build_time_table() {
        let p = NominalProfile::from_fn(
            |d| crate::profile::forces_at_depth_um(d as f64).n3_n,
            &BOUNDARY_UM,
        );
        assert_eq!(p, EQ7_NOMINAL);
        assert_eq!(p.peak_mn(), 206_341);
    }

    #[test]
    fn a_heavier_machine_gets_its_own_envelope() {
        // Everything ×1.5: the envelope follows, nothing NaN or negative leaks in.
        static HEAVY: std::sync::OnceLock<NominalProfile> = std::sync::OnceLock::new();
        let heavy = HEAVY.get_or_init(|| {
            NominalProfile::from_fn(
                |d| 1.5 * crate::profile::forces_at_depth_um(d as f64).n3_n,
                &BOUNDARY_UM,
            )
        });
        let g0 = OverloadGuard::new(GuardConfig::DEFAULT);
        let g = OverloadGuard::new(GuardConfig {
            hard_limit_mn: 450_000,
            nominal: heavy,
            ..GuardConfig::DEFAULT
        });
        let d = Some(20_000);
        assert!(g.limit_mn(d) > g0.limit_mn(d) + 50_000);
        let junk = NominalProfile::from_fn(|d| if d % 20 == 0 { f64::NAN } else { -5.0 }, &[]);
        assert_eq!(junk.peak_mn(), 0);
    }
    use crate::profile::forces_at_depth_um;

    #[test]
    fn const_n3_twin_equals_the_profile() {
        for d in (-100..=30_100).step_by(7) {
            let want = forces_at_depth_um(d.clamp(0, STROKE_UM) as f64).n3_n;
            assert_eq!(n3_at_depth_n(d).to_bits(), want.to_bits(), "depth {d}");
        }
    }

    fn nominal_mn(d: i32) -> i32 {
        (forces_at_depth_um(d as f64).n3_n * 1000.0) as i32
    }

    #[test]
    fn envelope_clears_the_nominal_profile_everywhere() {
        let g = OverloadGuard::new(GuardConfig::DEFAULT);
        for d in (0..=STROKE_UM).step_by(7) {
            // Half a millimetre of position error either way is still inside.
            for e in [-500, 0, 500] {
                let n = nominal_mn((d + e).clamp(0, STROKE_UM));
                assert!(
                    g.limit_mn(Some(d)) - n >= 29_000,
                    "depth {d}: limit {} nominal {n}",
                    g.limit_mn(Some(d))
                );
            }
        }
        assert_eq!(g.limit_mn(None), 300_000);
        // Two-point peak 206.34 N × 1.25 + 30 N.
        assert!(
            (287_400..=288_000).contains(&g.limit_mn(Some(15_000))),
            "{}",
            g.limit_mn(Some(15_000))
        );
    }

    #[test]
    fn spike_is_held_ramp_trips_at_once_step_within_one_sample() {
        let mut g = OverloadGuard::new(GuardConfig::DEFAULT);
        let d = Some(2_000);
        let lim = g.limit_mn(d);
        // isolated spike
        assert_eq!(g.check(112_000, d), Verdict::Ok);
        assert_eq!(g.check(450_000, d), Verdict::Suspect);
        assert_eq!(g.check(112_500, d), Verdict::Ok);
        assert_eq!(g.spikes_rejected(), 1);
        // ramp: trips on the first over-limit sample
        g.reset();
        let mut f = 112_000;
        loop {
            f += 2_500;
            match g.check(f, d) {
                Verdict::Trip { limit_mn } => {
                    assert_eq!(limit_mn, lim);
                    assert!(f > lim && f - 2_500 <= lim);
                    break;
                }
                Verdict::Suspect => panic!("a ramp is not a spike"),
                _ => {}
            }
        }
        // step: one sample late at most
        g.reset();
        assert_eq!(g.check(112_000, d), Verdict::Ok);
        assert_eq!(g.check(400_000, d), Verdict::Suspect);
        assert_eq!(g.check(400_000, d), Verdict::Trip { limit_mn: lim });
    }

    #[test]
    fn tension_and_a_reversed_bridge_are_a_verdict_not_zero_force() {
        let mut g = OverloadGuard::new(GuardConfig::DEFAULT);
        assert_eq!(
            g.check(-25_000, None),
            Verdict::Ok,
            "within the tension limit"
        );
        g.reset();
        // A reversed bridge at the cone mouth: −112 N out of the blue is held one sample
        // like any jump, then trips.
        assert_eq!(g.check(-300, Some(0)), Verdict::Ok);
        assert_eq!(g.check(-112_000, Some(10)), Verdict::Suspect);
        assert_eq!(
            g.check(-112_300, Some(20)),
            Verdict::Tension { limit_mn: -30_000 }
        );
        // A growing pull trips on its first sample past the limit.
        g.reset();
        assert_eq!(g.check(-29_000, None), Verdict::Ok);
        assert!(g.check(-31_000, None).stops());
    }

    #[test]
    fn warning_has_hysteresis() {
        let mut g = OverloadGuard::new(GuardConfig::DEFAULT);
        let lim = g.limit_mn(None);
        assert_eq!(g.check(lim * 91 / 100, None), Verdict::Warn);
        assert_eq!(g.check(lim * 85 / 100, None), Verdict::Warn);
        assert_eq!(g.check(lim * 79 / 100, None), Verdict::Ok);
    }

    #[test]
    fn sensor_faults() {
        let mut m = SensorMonitor::new(80, 0);
        assert_eq!(
            m.check_timeout(4 * 12_500 + 3 * 12_500),
            None,
            "settling grace"
        );
        assert_eq!(m.on_sample(100, 62_500, -8_388_608, 8_388_607), None);
        assert_eq!(m.check_timeout(62_500 + 37_500), None);
        assert_eq!(
            m.check_timeout(62_500 + 37_501),
            Some(SensorFault::Disconnected)
        );
        assert_eq!(m.on_sample(8_388_607, 75_000, -8_388_608, 8_388_607), None);
        assert_eq!(
            m.on_sample(8_388_607, 87_500, -8_388_608, 8_388_607),
            Some(SensorFault::Saturated)
        );
        let mut m = SensorMonitor::new(80, 0);
        let mut r = None;
        for i in 0..STUCK_SAMPLES {
            r = m.on_sample(5, i as u64, -8_388_608, 8_388_607);
        }
        assert_eq!(r, Some(SensorFault::Stuck));
    }

    /// The trial boot's check of the sensor: no answer before a sample, none from a
    /// sample at a rail or a stuck run, the code of a live sample; a reset forgets it.
    #[test]
    fn sensor_answers_only_with_a_live_sample() {
        let (lo, hi) = (-8_388_608, 8_388_607);
        let mut m = SensorMonitor::new(80, 0);
        assert_eq!(m.answered_code(), None, "no sample yet");
        m.on_sample(hi, 62_500, lo, hi);
        assert_eq!(m.answered_code(), None, "at the rail");
        m.on_sample(31_000, 75_000, lo, hi);
        assert_eq!(m.answered_code(), Some(31_000), "a live sample");
        for i in 1..STUCK_SAMPLES {
            m.on_sample(31_000, 75_000 + i as u64 * 12_500, lo, hi);
        }
        assert_eq!(m.answered_code(), None, "stuck");
        m.on_sample(31_001, 500_000, lo, hi);
        assert_eq!(m.answered_code(), Some(31_001));
        m.reset(600_000);
        assert_eq!(m.answered_code(), None, "forgotten by a reset");
    }
}
