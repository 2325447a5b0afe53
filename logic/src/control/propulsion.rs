//! Propulsion driver: a step/dir stepper on the docking axis with a trapezoidal
//! acceleration ramp, open-loop position in steps.
//!
//! The driver owns the EN (active low) and DIR (high = toward the male panel) lines and a
//! [`StepPulses`] generator. It is updated once per control step with the elapsed time;
//! between updates the generator emits pulses at a constant rate. Position is the count
//! of pulses actually emitted, signed by the direction they were emitted in.
//!
//! [`Propulsion::disable`] is the emergency path: pulses stop and the driver's power stage
//! is switched off in the same call (the overload guard uses it within the control step
//! that sees the sample).

use embedded_hal::digital::OutputPin;

use crate::config::MachineConfig;
use crate::hal::StepPulses;

/// Errors of the propulsion driver.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum PropulsionError {
    /// An EN or DIR line could not be driven.
    Pin,
}

/// A stepper axis with a ramp.
pub struct Propulsion<EN, DIR, P> {
    en_n: EN,
    dir: DIR,
    pulses: P,
    cfg: MachineConfig,
    /// Counted position, steps from home.
    pos_steps: i32,
    /// The same in µm (cached: converting divides by steps/mm).
    pos_um: i32,
    /// µm per step when steps/mm divides 1000 (5 at 200 steps/mm), else 0: the
    /// position in µm is then a product, the same as the truncating division gives.
    um_per_step: i32,
    /// Current commanded velocity, steps/s (signed).
    vel_sps: i32,
    /// Target position, steps (`None` = stop where the ramp ends).
    target_steps: Option<i32>,
    /// Speed limit of the current move, steps/s.
    max_sps: u32,
    /// Acceleration, steps/s².
    accel_sps2: u32,
    enabled: bool,
    dir_positive: bool,
    /// The last `move_to` command (target µm, speed µm/s).
    last_move: Option<(i32, u32)>,
    /// The rate the pulse generator was last set to, Hz.
    rate_hz: u32,
    /// Cruise shortcut of [`plan`](Self::plan), set while the move cruises at its speed
    /// limit and cleared by anything that changes the move (see [`Cruise`]).
    cruise: Option<Cruise>,
}

/// How long a move at its speed limit keeps cruising: the full ramp computation of
/// [`Propulsion::plan`] returns the same velocity (so nothing is reprogrammed) as long as
/// the distance left is at least [`Cruise::min_dist_steps`] — the stopping distance plus
/// one period's travel, and short of the final-approach window. Set after a ramp step
/// that ends at the speed limit, as the position up to which that holds for this period.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
struct Cruise {
    /// The control period it was derived for, µs.
    dt_us: u64,
    /// Cruise on while the position is at most this (moving +) or at least this (moving
    /// −), steps.
    until_steps: i64,
}

impl Cruise {
    /// Least distance to the target, steps, from which a move at `max_sps` keeps
    /// cruising for a period of `dt_us` (`None`: never, with no acceleration).
    fn min_dist_steps(dt_us: u64, max_sps: u32, accel_sps2: u32) -> Option<i64> {
        if accel_sps2 == 0 {
            return None;
        }
        let max = max_sps as i64;
        let dv = ((accel_sps2 as u64 * dt_us) / 1_000_000).max(1) as i64;
        let lead = (max * dt_us as i64) / 1_000_000;
        let two_a = 2 * accel_sps2 as i64;
        // v_stop = max  ⟺  max² ≤ 2a·(D − lead)  ⟺  D ≥ lead + ⌈max² / 2a⌉
        let stop = lead + (max * max + two_a - 1) / two_a;
        // not the final approach  ⟺  D > max(lead, 1) + dv·dt/1e6 + 1
        let approach = lead.max(1) + dv * dt_us as i64 / 1_000_000 + 2;
        Some(stop.max(approach))
    }
}

/// Arrival tolerance, steps (5 µm at 200 steps/mm).
pub const ARRIVAL_TOLERANCE_STEPS: i32 = 1;

/// Integer square root (floor) of a u64, by Newton's iteration from above.
///
/// By hand (issue 20): core's `u64::isqrt` is 614 bytes of code inlined into the
/// control step and a 512-byte table, this is about 70 bytes. Below 2³² (every value
/// the ramp meets while `max_sps` < 65 536: it takes the root only of a `2·a·d` under
/// `max_sps²`) the iteration runs in u32, each step one hardware `udiv`; above, the same
/// in u64 (a library division). Exact: from a start x₀ ≥ √v the iterate
/// x' = ⌊(x + ⌊v/x⌋)/2⌋ decreases strictly while x > ⌊√v⌋ and never goes below it, so
/// the first x' ≥ x is ⌊√v⌋; tested against core's `isqrt`
/// (`isqrt_is_cores_isqrt`). Five or six steps from the start 2^⌈bits/2⌉.
pub(crate) const fn isqrt(v: u64) -> u64 {
    if v >> 32 == 0 {
        return isqrt_u32(v as u32) as u64;
    }
    // v ≥ 2³²: bits in 33..=64, x ≤ 2³², and x + v/x ≤ 2³³ (v/x ≤ √v ≤ 2³²).
    let mut x = 1u64 << (64 - v.leading_zeros()).div_ceil(2);
    loop {
        let y = (x + v / x) / 2;
        if y >= x {
            return x;
        }
        x = y;
    }
}

/// [`isqrt`] below 2³²: x ≤ 2¹⁶ and x + v/x ≤ 2¹⁷; x ≥ ⌊√v⌋ ≥ 1 for v ≥ 1 (no
/// division by zero).
const fn isqrt_u32(v: u32) -> u32 {
    if v == 0 {
        return 0;
    }
    let mut x = 1u32 << (32 - v.leading_zeros()).div_ceil(2);
    loop {
        let y = (x + v / x) / 2;
        if y >= x {
            return x;
        }
        x = y;
    }
}

impl<EN: OutputPin, DIR: OutputPin, P: StepPulses> Propulsion<EN, DIR, P> {
    /// A driver at position 0, disabled (EN high), no pulses.
    pub fn new(en_n: EN, dir: DIR, pulses: P, cfg: MachineConfig) -> Result<Self, PropulsionError> {
        let accel_sps2 = cfg.speed_to_step_hz(cfg.accel_um_per_s2);
        let mut p = Self {
            en_n,
            dir,
            pulses,
            cfg,
            pos_steps: 0,
            pos_um: 0,
            um_per_step: match cfg.steps_per_mm {
                0 => 0,
                n if 1000 % n == 0 => (1000 / n) as i32,
                _ => 0,
            },
            vel_sps: 0,
            target_steps: None,
            max_sps: 0,
            accel_sps2,
            enabled: false,
            dir_positive: false,
            last_move: None,
            rate_hz: 0,
            cruise: None,
        };
        p.disable()?;
        Ok(p)
    }

    /// Emergency stop: pulses stop and the power stage is switched off, now.
    pub fn disable(&mut self) -> Result<(), PropulsionError> {
        self.cruise = None;
        self.pulses.set_rate_hz(0);
        self.rate_hz = 0;
        self.vel_sps = 0;
        self.target_steps = None;
        self.enabled = false;
        self.en_n.set_high().map_err(|_| PropulsionError::Pin)
    }

    /// Switch the power stage on (holding torque, no motion).
    pub fn enable(&mut self) -> Result<(), PropulsionError> {
        if self.enabled {
            return Ok(()); // already on: no pin traffic every control step
        }
        self.en_n.set_low().map_err(|_| PropulsionError::Pin)?;
        self.enabled = true;
        Ok(())
    }

    /// Whether the power stage is on.
    pub fn is_enabled(&self) -> bool {
        self.enabled
    }

    /// Move to `target_um` at no more than `speed_um_per_s`, ramping.
    pub fn move_to(&mut self, target_um: i32, speed_um_per_s: u32) {
        if self.last_move == Some((target_um, speed_um_per_s)) && self.target_steps.is_some() {
            return; // the same command as last step: nothing to convert
        }
        self.last_move = Some((target_um, speed_um_per_s));
        self.cruise = None;
        self.target_steps = Some(self.cfg.um_to_steps(target_um));
        self.max_sps = self.cfg.speed_to_step_hz(speed_um_per_s);
    }

    /// Ramp down to a stop wherever that ends.
    pub fn stop(&mut self) {
        self.cruise = None;
        self.target_steps = None;
    }

    /// Stop pulses at once, keeping the power stage as it is (at a switch).
    pub fn halt(&mut self) {
        self.cruise = None;
        self.pulses.set_rate_hz(0);
        self.rate_hz = 0;
        self.vel_sps = 0;
        self.target_steps = None;
    }

    /// Declare the current position to be `pos_um` (homing).
    pub fn set_position_um(&mut self, pos_um: i32) {
        self.cruise = None;
        self.pos_steps = self.cfg.um_to_steps(pos_um);
        self.pos_um = self.steps_to_um(self.pos_steps);
    }

    /// Counted position, µm from home.
    pub fn position_um(&self) -> i32 {
        self.pos_um
    }

    /// Counted position, steps.
    pub fn position_steps(&self) -> i32 {
        self.pos_steps
    }

    /// Current commanded velocity, µm/s (signed).
    pub fn velocity_um_per_s(&self) -> i32 {
        self.cfg.steps_to_um(self.vel_sps)
    }

    /// True when no move is in progress and the axis stands still.
    pub fn is_idle(&self) -> bool {
        self.vel_sps == 0
            && self
                .target_steps
                .is_none_or(|t| (t - self.pos_steps).abs() <= ARRIVAL_TOLERANCE_STEPS)
    }

    /// Account for the pulses emitted since the last call (updates the position).
    pub fn sync(&mut self) {
        let n = self.pulses.take_pulses() as i32;
        if n != 0 {
            self.pos_steps = if self.dir_positive {
                self.pos_steps.saturating_add(n)
            } else {
                self.pos_steps.saturating_sub(n)
            };
            self.pos_um = self.steps_to_um(self.pos_steps);
        }
    }

    /// [`MachineConfig::steps_to_um`], as a multiplication when steps/mm divides 1000
    /// (no division at every step that moves).
    fn steps_to_um(&self, steps: i32) -> i32 {
        if self.um_per_step != 0 {
            // (steps·1000)/spm = steps·(1000/spm) exactly when spm divides 1000.
            (steps as i64 * self.um_per_step as i64) as i32
        } else {
            self.cfg.steps_to_um(steps)
        }
    }

    /// [`sync`](Self::sync), then [`plan`](Self::plan).
    pub fn update(&mut self, dt_us: u32) -> Result<(), PropulsionError> {
        self.sync();
        self.plan(dt_us)
    }

    /// Set the pulse rate for the next `dt_us` (the control period), following the ramp
    /// toward the target.
    pub fn plan(&mut self, dt_us: u32) -> Result<(), PropulsionError> {
        if !self.enabled {
            self.pulses.set_rate_hz(0);
            self.rate_hz = 0;
            self.vel_sps = 0;
            return Ok(());
        }
        let dt_us = dt_us.clamp(1, 1_000_000) as u64;
        if self.cruises_on(dt_us) {
            // Cruising at the speed limit, far from the target: nothing changes (the
            // common case; `Cruise` says why the ramp computation would agree).
            return Ok(());
        }
        self.plan_ramp(dt_us)?;
        self.cruise = self.cruise_ahead(dt_us);
        Ok(())
    }

    /// Whether the recorded cruise still holds for a period of `dt_us` here.
    fn cruises_on(&self, dt_us: u64) -> bool {
        self.cruise.is_some_and(|c| {
            let pos = self.pos_steps as i64;
            c.dt_us == dt_us
                && if self.dir_positive {
                    pos <= c.until_steps
                } else {
                    pos >= c.until_steps
                }
        })
    }

    /// After a ramp step: how far the move now cruises unchanged, if it is at its limit.
    fn cruise_ahead(&self, dt_us: u64) -> Option<Cruise> {
        let t = self.target_steps? as i64;
        let max = self.max_sps;
        let v = self.vel_sps as i64;
        let cruising = max > 0
            && v.unsigned_abs() == max as u64
            && self.rate_hz == max
            && self.dir_positive == (v > 0);
        if !cruising {
            return None;
        }
        let d = Cruise::min_dist_steps(dt_us, max, self.accel_sps2)?;
        Some(Cruise {
            dt_us,
            until_steps: if v > 0 { t - d } else { t + d },
        })
    }

    /// The full ramp computation of [`plan`](Self::plan) for an enabled driver.
    fn plan_ramp(&mut self, dt_us: u64) -> Result<(), PropulsionError> {
        // Speed change allowed this period (at least 1 step/s so a ramp always progresses).
        let dv = ((self.accel_sps2 as u64 * dt_us) / 1_000_000).max(1) as i64;
        let v = self.vel_sps as i64;
        let mut final_approach = false;
        let desired: i64 = match self.target_steps {
            None => 0,
            Some(t) => {
                let dist = t as i64 - self.pos_steps as i64;
                // Fastest speed from which the ramp can still stop in what is left of
                // `dist` after this period's travel (discrete, so conservative).
                let lead = (v.abs() * dt_us as i64) / 1_000_000;
                let d_eff = (dist.abs() - lead).max(0) as u64;
                let two_a_d = 2 * self.accel_sps2 as u64 * d_eff;
                let max = self.max_sps as u64;
                // Far from the target the speed limit binds; only near it is the root needed.
                let v_stop = if max * max <= two_a_d {
                    max as i64
                } else {
                    isqrt(two_a_d) as i64
                };
                let v_cap = if dist.abs() <= lead.max(1) + dv * dt_us as i64 / 1_000_000 + 1 {
                    // Final approach: cover exactly the remaining steps in one period (a
                    // stepper stops from these few hundred steps/s without a ramp).
                    final_approach = true;
                    (dist.abs() * 1_000_000) / dt_us as i64
                } else {
                    v_stop.min(self.max_sps as i64)
                };
                if dist.abs() <= ARRIVAL_TOLERANCE_STEPS as i64 && (final_approach || v.abs() <= dv)
                {
                    // Arrived: a rate generator cannot place the last pulse exactly (its
                    // fractional carry may add one), so ±1 step counts as there.
                    self.target_steps = None;
                    0
                } else {
                    dist.signum() * v_cap.min(self.max_sps as i64).max(1)
                }
            }
        };
        let new_v = if final_approach && desired.abs() <= v.abs() && desired.signum() != -v.signum()
        {
            desired
        } else if desired > v {
            (v + dv).min(desired)
        } else {
            (v - dv).max(desired)
        };
        // Reverse only through zero: stop this period, change DIR next.
        let new_v = if (new_v > 0 && v < 0) || (new_v < 0 && v > 0) {
            0
        } else {
            new_v
        };
        self.vel_sps = new_v as i32;
        if new_v != 0 {
            let positive = new_v > 0;
            if positive != self.dir_positive {
                let r = if positive {
                    self.dir.set_high()
                } else {
                    self.dir.set_low()
                };
                r.map_err(|_| PropulsionError::Pin)?;
                self.dir_positive = positive;
            }
        }
        let rate = new_v.unsigned_abs() as u32;
        if rate != self.rate_hz {
            // Reprogram the generator only on a change (cruising, nothing to do).
            self.pulses.set_rate_hz(rate);
            self.rate_hz = rate;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn isqrt_is_cores_isqrt() {
        // Every value below 2^22, the squares around every root below 2^16 and around
        // powers of two and the ends of u64, and a spread of others.
        for v in 0..1u64 << 22 {
            assert_eq!(isqrt(v), v.isqrt(), "{v}");
        }
        let edge = |v: u64| assert_eq!(isqrt(v), v.isqrt(), "{v}");
        for r in (0..1u64 << 16).chain([(1 << 32) - 1, 1 << 31, 3_037_000_499]) {
            let sq = r * r;
            edge(sq);
            edge(sq.saturating_sub(1));
            edge(sq + 1);
            edge(sq + 2 * r);
        }
        for k in 0..64 {
            edge(1 << k);
            edge((1 << k) - 1);
            edge((1 << k) + 1);
        }
        edge(u64::MAX);
        edge(u64::MAX - 1);
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        for _ in 0..200_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            edge(x);
            edge(x >> 20);
        }
    }
    use core::cell::Cell;
    use core::convert::Infallible;

    #[derive(Default)]
    struct Line(Cell<bool>);
    impl embedded_hal::digital::ErrorType for &Line {
        type Error = Infallible;
    }
    impl OutputPin for &Line {
        fn set_high(&mut self) -> Result<(), Infallible> {
            self.0.set(true);
            Ok(())
        }
        fn set_low(&mut self) -> Result<(), Infallible> {
            self.0.set(false);
            Ok(())
        }
    }
    /// Pulses emitted at the last rate for exactly one period of `dt_us`.
    struct Gen {
        rate: u32,
        frac: u64,
        dt_us: u64,
    }
    impl Gen {
        fn new(dt_us: u32) -> Self {
            Self {
                rate: 0,
                frac: 0,
                dt_us: dt_us as u64,
            }
        }
    }
    const PERIOD_US: u32 = 12_500;
    impl StepPulses for Gen {
        fn set_rate_hz(&mut self, r: u32) {
            self.rate = r;
        }
        fn take_pulses(&mut self) -> u32 {
            let acc = self.frac + self.rate as u64 * self.dt_us;
            self.frac = acc % 1_000_000;
            (acc / 1_000_000) as u32
        }
    }

    /// The counted position in µm, a product where steps/mm divides 1000, is the
    /// configuration's truncating division for every steps/mm and count.
    #[test]
    fn position_in_um_is_the_configurations_division() {
        let (en, dir) = (Line::default(), Line::default());
        for spm in [1u32, 3, 7, 8, 125, 200, 250, 333, 400, 1_000, 1_024, 10_000] {
            let cfg = MachineConfig {
                steps_per_mm: spm,
                ..MachineConfig::DEFAULT
            };
            let p = Propulsion::new(&en, &dir, Gen::new(PERIOD_US), cfg).unwrap();
            for s in [0, 1, -1, 199, -201, 12_345, -99_999, i32::MAX, i32::MIN] {
                assert_eq!(p.steps_to_um(s), cfg.steps_to_um(s), "{spm} steps/mm, {s}");
            }
        }
    }

    #[test]
    fn ramps_to_target_without_overshoot_and_reverses() {
        let (en, dir) = (Line::default(), Line::default());
        let cfg = MachineConfig::DEFAULT;
        let mut p = Propulsion::new(&en, &dir, Gen::new(PERIOD_US), cfg).unwrap();
        assert!(en.0.get(), "starts disabled");
        p.enable().unwrap();
        p.move_to(20_000, cfg.fast_speed_um_per_s);
        let mut max_v = 0;
        for _ in 0..2_000 {
            p.update(PERIOD_US).unwrap();
            max_v = max_v.max(p.velocity_um_per_s());
            assert!(p.position_um() <= 20_005, "overshoot {}", p.position_um());
            if p.is_idle() {
                break;
            }
        }
        assert!(p.is_idle());
        assert!((p.position_um() - 20_000).abs() <= 5, "{}", p.position_um());
        assert_eq!(max_v, 10_000);
        p.move_to(0, 1_200);
        for _ in 0..3_000 {
            p.update(PERIOD_US).unwrap();
            assert!(p.velocity_um_per_s() >= -1_200);
        }
        assert!(p.position_um().abs() <= 5, "{}", p.position_um());
        assert!(p.is_idle());
    }

    /// The cruise shortcut of `plan` changes nothing: a driver using it and one that
    /// always runs the full ramp computation step through the same moves (ramps, cruise,
    /// arrival, reversal, a new target mid-cruise, a stop) in lockstep, for a grid of
    /// periods, speed limits and accelerations.
    #[test]
    fn cruise_shortcut_matches_the_full_ramp() {
        let (en, dir) = (Line::default(), Line::default());
        let (mut shortcuts, mut steps) = (0u32, 0u32);
        for dt_us in [999u32, 3_125, 12_500, 100_000] {
            for speed_um_per_s in [5u32, 400, 1_200, 10_000, 20_000] {
                for accel_sps2 in [1u32, 7, 4_000, 100_000] {
                    let mk = || {
                        let mut p =
                            Propulsion::new(&en, &dir, Gen::new(dt_us), MachineConfig::DEFAULT)
                                .unwrap();
                        p.accel_sps2 = accel_sps2;
                        p.enable().unwrap();
                        p
                    };
                    let (mut a, mut b) = (mk(), mk());
                    let moves: [(i32, u32); 5] = [
                        (30_000, 60),
                        (12_000, 25),
                        (40_000, 8),
                        (-1_000, 80),
                        (20_000, 80),
                    ];
                    for (k, &(target_um, n)) in moves.iter().enumerate() {
                        for p in [&mut a, &mut b] {
                            p.move_to(target_um, speed_um_per_s);
                        }
                        for i in 0..n * 10 {
                            if k == 2 && i == 20 {
                                a.stop();
                                b.stop();
                            }
                            a.sync();
                            b.sync();
                            let took = a.cruises_on(dt_us as u64);
                            a.plan(dt_us).unwrap();
                            b.plan_ramp(dt_us as u64).unwrap();
                            shortcuts += took as u32;
                            steps += 1;
                            assert_eq!(
                                (a.vel_sps, a.rate_hz, a.dir_positive, a.target_steps, a.pos_steps),
                                (b.vel_sps, b.rate_hz, b.dir_positive, b.target_steps, b.pos_steps),
                                "dt {dt_us} µs, {speed_um_per_s} µm/s, {accel_sps2} steps/s², move {k}, step {i}"
                            );
                        }
                    }
                }
            }
        }
        // Both paths ran, the shortcut most of the time.
        assert!(
            shortcuts > steps / 3 && shortcuts < steps,
            "{shortcuts}/{steps}"
        );
    }

    #[test]
    fn disable_stops_at_once() {
        let (en, dir) = (Line::default(), Line::default());
        let mut p =
            Propulsion::new(&en, &dir, Gen::new(PERIOD_US), MachineConfig::DEFAULT).unwrap();
        p.enable().unwrap();
        p.move_to(50_000, 1_200);
        for _ in 0..100 {
            p.update(PERIOD_US).unwrap();
        }
        p.disable().unwrap();
        assert!(en.0.get());
        assert_eq!(p.velocity_um_per_s(), 0);
        let before = p.position_steps();
        p.update(PERIOD_US).unwrap();
        assert_eq!(p.position_steps(), before, "no pulses after disable");
    }
}
