//! `hil-sim accuracy`: numerical error against run time.
//!
//! For each load-cell rate of [`RATES_SPS`] one docking cycle runs through the closed
//! loop (the real `Controller`, the simulated HAL) and the odometer's own integral is
//! split into its two strokes: the insertion is the pending load–distance at the first
//! step in `Holding`, the extraction the rest of the cycle. Each is compared with the
//! exact stroke integral of Eq. 7, [`EXACT_STROKE_N_MM`] = 4042.7297 N·mm. Then the
//! wall time per simulated cycle is measured at that rate with the default sensor noise,
//! and finally the fixed-point odometer is compared with an `f64` reference over 45 000
//! and 10^6 cycles ([`fixed_vs_f64_from`]).
//!
//! "Noise-free" means a 1-count RMS dither ([`DITHER_COUNTS`], 0.12 mN): with exactly
//! zero noise the controller's stuck-converter check (32 identical codes) latches a
//! fault before the first cycle.
//!
//! ## Where the stroke error comes from (measured, first cycle of a fresh rig)
//!
//! Every source below was isolated by recording the samples of the chain and
//! recomputing the trapezoid with the exact Eq. 7 forces at the same positions; N·mm
//! per stroke, 1 % = 40.4 N·mm.
//!
//! * **The jumps.** Across a jump of `ΔF` at `x_j` inside a sample interval
//!   `[x0, x1]` the trapezoid errs by `ΔF · (x_j − (x0 + x1)/2)`: zero when the jump sits
//!   mid-interval, `±ΔF · Δx/2` at worst, and which one a cycle gets is the sampling
//!   phase. N3's 107.1 → 206.3 N jump at 14.934 mm dominates (ΔF = 99.25 N; the other
//!   two are +2.41 N at 4.5 mm and −11.28 N at 8.7 mm). Bound for jump 3: 5.96 N·mm
//!   (0.147 %) at 10 SPS (Δx = 120 µm), 0.74 N·mm at 80 SPS (15 µm), and from 320 SPS on
//!   the axis's 5-µm step, not the rate, sets Δx: 14.934 mm falls inside the step
//!   [14 930, 14 935] µm, +0.149 N·mm at 320 and 1280 SPS alike. Measured: 10 SPS
//!   −0.61, 80 SPS +0.149 (jump 3) and −0.085 (jump 2, whose sample lands exactly on
//!   8.700 mm), 320/1280 SPS +0.149.
//! * **The contact edges.** The cone's edge is a fourth jump (0 → 112.64 N at depth 0),
//!   and where each stroke's chain begins and ends is decided by the sequencer, not the
//!   integrator. The insertion chain starts at the first sample taken in `Inserting`
//!   (10 SPS: one period, 120 µm, into the stroke), and the sequencer accepts arrival
//!   within one step (5 µm): at 320/1280 SPS pre-alignment stops at −5 µm (+0.28 N·mm
//!   credited for no contact) and the mate at 29 995 µm (−0.63 N·mm); the extraction
//!   ends at +5 µm at 80–1280 SPS (−0.56 N·mm).
//! * **The homing overshoot.** The home switch is read once per control step, so a
//!   carriage moving onto it stops up to `v · T` past it and that point is called zero.
//!   The homing now creeps onto the switch (0.4 mm/s: 5 µm per period at 80 SPS), so
//!   the counted offset measures 0 µm at every rate (the `# counted depth` lines of the
//!   report); earlier firmware homed at full speed and lost ≈ 0.37 % per stroke at 10
//!   SPS to a 120 µm overshoot.
//! * **Load conversion.** The odometer's forces minus the exact forces at the same
//!   positions: −0.0095 N·mm per stroke (−2.3e-6): the floor of the counts → mN
//!   conversion (−0.5 mN mean), whole-count codes (±0.06 mN) and the tare mean's
//!   truncation to whole counts. Negligible.
//!
//! Totals as measured now (`hil-sim accuracy`, the table in docs/simulator.md), per stroke
//! (insertion / extraction): 10 SPS −0.015 % / +0.263 % (the contact edges and the
//! jumps at a 120 µm sample spacing, above), 80 SPS +0.0003 % /
//! +0.0078 %, 320 and 1280 SPS −0.0056 % both (identical: every 5-µm step is sampled
//! from 320 SPS on, so the one-step floor, not the rate, sets the error).
//! With the default noise (0.3 N RMS) the tare's
//! error (≈ 0.075 N over the stroke) makes cycles scatter by ≈ ±0.1 % at every rate.

use std::time::Instant;

use docking_logic::controller::PollResult;
use docking_logic::estimate::{Fit, Reading};
use docking_logic::material::Material;
use docking_logic::odometer::{
    depth_nm, e_at_depth_q32, equivalent_cycles_q32, wear_factor_q32, WearConfig, W_NOM_MN_UM,
    W_NOM_Q1,
};
use docking_logic::sequencer::{Request, State};

use crate::rig::{Rig, RigOptions};

/// Load-cell rates compared, SPS (the CLI's 10/80/320 and a 1280 SPS part).
pub const RATES_SPS: [u32; 4] = [10, 80, 320, 1280];

/// Exact load–distance of one stroke of Eq. 7 at v0, N·mm (half of
/// [`W_NOM_MN_UM`]: 1.2 mm/s × 3368.94 N·s = 4042.729725 N·mm).
pub const EXACT_STROKE_N_MM: f64 = W_NOM_MN_UM as f64 / 2.0 / 1e6;

/// Load-cell noise of the "noise-free" stroke runs, RMS counts (≈ 0.12 mN). Exactly zero
/// cannot run the closed loop: identical codes trip the controller's stuck-converter
/// check (32 equal codes in a row: 3.2 s at 10 SPS idle, or phase 1's constant force).
pub const DITHER_COUNTS: f64 = 1.0;

/// Cycle counts of the fixed-point vs `f64` comparison: inside the life, and far past it.
pub const FIXED_CYCLES: [u32; 2] = [45_000, 1_000_000];

/// Spread of the per-cycle load–distance in the fixed-point comparison, ± ppm (5 %).
pub const PERTURB_PPM: u64 = 50_000;

/// Seed of the perturbation (xorshift64).
pub const PERTURB_SEED: u64 = 0x5EED_0D0C_2025_0001;

/// Rate of the noisy reference cycle whose load–distance the comparison perturbs, SPS.
pub const REFERENCE_RATE_SPS: u32 = 80;

/// Longest virtual time one docking cycle may take before the run is declared stuck, s
/// (a nominal cycle takes ≈ 57 s).
const CYCLE_TIMEOUT_S: f64 = 300.0;

/// Cycles timed at `rate_sps` for the wall-time column.
pub fn timing_cycles(rate_sps: u32) -> u32 {
    match rate_sps {
        0..=80 => 200,
        81..=320 => 100,
        _ => 30,
    }
}

/// Q63.1 mN·µm to N·mm.
pub fn q1_to_n_mm(q1: u64) -> f64 {
    q1 as f64 / 2.0 / 1e6
}

/// Signed relative error of `n_mm` against the exact stroke, %.
pub fn stroke_err_pct(n_mm: f64) -> f64 {
    (n_mm / EXACT_STROKE_N_MM - 1.0) * 100.0
}

/// Run a rig's closed loop until `cycles` docking cycles have completed (counted on the
/// cone) and the controller is idle again, calling `on_tick(rig, state_before, poll)`
/// after every control step.
///
/// # Panics
/// If the controller latches a fault or a cycle overruns [`CYCLE_TIMEOUT_S`] of virtual
/// time: neither happens on a healthy simulated machine, and the numbers would mean
/// nothing.
fn drive(rig: &mut Rig, cycles: u32, mut on_tick: impl FnMut(&Rig, State, PollResult)) {
    let deadline_s = rig.clock.now_s() + CYCLE_TIMEOUT_S * (cycles as f64 + 1.0);
    loop {
        let before = rig.ctrl.state();
        let poll = rig.tick();
        on_tick(rig, before, poll);
        match rig.ctrl.state() {
            State::Idle if !rig.ctrl.persist_pending() => {
                if rig.ctrl.odometer().cone().cycles >= cycles {
                    return;
                }
                rig.ctrl.request(Request::StartCycle);
            }
            State::Faulted { fault } => panic!(
                "accuracy run: fault {} at {:.3} s (cycle {})",
                fault.name(),
                rig.clock.now_s(),
                rig.ctrl.odometer().cone().cycles + 1
            ),
            _ => {}
        }
        if rig.clock.now_s() > deadline_s {
            panic!(
                "accuracy run: {} cycle(s) not done after {:.0} s of virtual time (state {})",
                cycles,
                rig.clock.now_s(),
                rig.ctrl.state().name()
            );
        }
    }
}

/// One closed-loop docking cycle's two strokes as the odometer measured them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StrokeMeasurement {
    /// Load-cell rate, SPS.
    pub rate_sps: u32,
    /// Insertion stroke: the odometer's pending load–distance at the first step in
    /// `Holding`, Q63.1 mN·µm.
    pub insertion_q1: u64,
    /// Extraction stroke: the rest of the cycle (`last_cycle_q1 − insertion`), Q63.1.
    pub extraction_q1: u64,
    /// Counted minus true carriage position when the cycle starts, µm (a homing that
    /// overshoots the switch by one control period leaves the count ahead of the truth).
    pub position_offset_um: f64,
    /// Counted insertion depth of the first and last sample of the insertion chain, µm.
    pub insertion_span_um: (i32, i32),
    /// Counted insertion depth of the first and last sample of the extraction, µm.
    pub extraction_span_um: (i32, i32),
}

impl StrokeMeasurement {
    /// Insertion stroke, N·mm.
    pub fn insertion_n_mm(&self) -> f64 {
        q1_to_n_mm(self.insertion_q1)
    }

    /// Extraction stroke, N·mm.
    pub fn extraction_n_mm(&self) -> f64 {
        q1_to_n_mm(self.extraction_q1)
    }

    /// Insertion error against [`EXACT_STROKE_N_MM`], signed %.
    pub fn insertion_err_pct(&self) -> f64 {
        stroke_err_pct(self.insertion_n_mm())
    }

    /// Extraction error against [`EXACT_STROKE_N_MM`], signed %.
    pub fn extraction_err_pct(&self) -> f64 {
        stroke_err_pct(self.extraction_n_mm())
    }
}

/// Measure both strokes of the first docking cycle of a fresh rig at `rate_sps` with the
/// load cell dithered by [`DITHER_COUNTS`] (practically noise-free).
///
/// # Panics
/// If the simulated machine latches a fault or a cycle overruns 300 s of virtual time
/// (neither happens on a healthy simulated machine). The same holds for every function
/// of this module that runs the closed loop.
pub fn measure_strokes(rate_sps: u32) -> StrokeMeasurement {
    let mut rig = Rig::new(RigOptions {
        noise_counts: Some(DITHER_COUNTS),
        ..RigOptions::new(rate_sps)
    });
    let engage_um = rig.ctrl.config().machine.engage_um;
    let mut offset_um: Option<f64> = None;
    let mut insertion_q1: Option<u64> = None;
    let mut ins_first: Option<i32> = None;
    let mut ins_last = 0;
    let mut ext_last = 0;
    drive(&mut rig, 1, |rig, before, poll| {
        let now = rig.ctrl.state();
        if offset_um.is_none() && matches!(now, State::PreAlign { .. }) {
            offset_um = Some(rig.ctrl.status().pos_um as f64 - rig.axis.pos_um());
        }
        if poll.sampled {
            let depth = rig.ctrl.status().pos_um - engage_um;
            match before {
                State::Inserting { .. } => {
                    ins_first.get_or_insert(depth);
                    ins_last = depth;
                }
                State::Extracting { .. } => ext_last = depth,
                _ => {}
            }
        }
        if insertion_q1.is_none() && matches!(now, State::Holding { .. }) {
            insertion_q1 = Some(rig.ctrl.odometer().pending_q1());
        }
    });
    let total_q1 = rig.ctrl.odometer().last_cycle_q1();
    let insertion_q1 = insertion_q1.unwrap_or(0);
    StrokeMeasurement {
        rate_sps,
        insertion_q1,
        extraction_q1: total_q1.saturating_sub(insertion_q1),
        position_offset_um: offset_um.unwrap_or(0.0),
        insertion_span_um: (ins_first.unwrap_or(0), ins_last),
        extraction_span_um: (ins_last, ext_last),
    }
}

/// Insertion and extraction load–distance of one closed-loop cycle at `rate_sps`, N·mm.
pub fn stroke_integrals(rate_sps: u32) -> (f64, f64) {
    let m = measure_strokes(rate_sps);
    (m.insertion_n_mm(), m.extraction_n_mm())
}

/// Wall time per simulated docking cycle at `rate_sps`: `cycles` closed-loop cycles of a
/// fresh rig with the load cell's default noise (boot and homing included), s.
pub fn wall_s_per_cycle(rate_sps: u32, cycles: u32) -> f64 {
    let cycles = cycles.max(1);
    let started = Instant::now();
    let mut rig = Rig::new(RigOptions::new(rate_sps));
    drive(&mut rig, cycles, |_, _, _| {});
    started.elapsed().as_secs_f64() / cycles as f64
}

/// Load–distance of the first cycle of a fresh rig at `rate_sps` with the load cell's
/// default noise (≈ 0.3 N RMS, seed 1), Q63.1 mN·µm.
pub fn noisy_cycle_q1(rate_sps: u32) -> u64 {
    let mut rig = Rig::new(RigOptions::new(rate_sps));
    drive(&mut rig, 1, |_, _, _| {});
    rig.ctrl.odometer().last_cycle_q1()
}

/// xorshift64 (Marsaglia's 13/7/17), enough for a reproducible perturbation.
#[derive(Clone, Debug)]
struct XorShift64(u64);

impl XorShift64 {
    fn next(&mut self) -> u64 {
        let mut x = self.0;
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
        self.0 = x;
        x
    }
}

/// The per-cycle load–distances of the comparison: `base_q1 × (1 + u)`, `u` uniform on
/// ±[`PERTURB_PPM`] in whole ppm, from [`PERTURB_SEED`]; rounded down to Q63.1 integers.
pub fn perturbed_cycles(base_q1: u64) -> impl Iterator<Item = u64> {
    let mut rng = XorShift64(PERTURB_SEED | 1);
    std::iter::repeat_with(move || {
        let ppm = 1_000_000 - PERTURB_PPM + rng.next() % (2 * PERTURB_PPM + 1);
        (base_q1 as u128 * ppm as u128 / 1_000_000) as u64
    })
}

/// Eq. 17 reduced-order constants in `f64` (mm).
const A_MM: f64 = 0.01372;
const B: f64 = 0.3813;
const C_MM: f64 = 0.01774;

/// `m0 = (c/a)^(1/b)` in `f64`.
pub fn m0_f64() -> f64 {
    (C_MM / A_MM).powf(1.0 / B)
}

/// Depth after `e` equivalent nominal cycles, `f64` reference, nm.
pub fn depth_f64_nm(e: f64) -> f64 {
    (A_MM * (e + m0_f64()).powf(B) - C_MM) * 1e6
}

/// Equivalent cycles at which the depth reaches `limit_nm`, `f64` reference.
pub fn e_limit_f64(limit_nm: u32) -> f64 {
    ((limit_nm as f64 / 1e6 + C_MM) / A_MM).powf(1.0 / B) - m0_f64()
}

/// The fixed-point odometer against an `f64` reference after `cycles` cycles (ZQSn5-2).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct FixedReport {
    /// Cycles accumulated.
    pub cycles: u32,
    /// Unperturbed per-cycle load–distance, Q63.1 mN·µm.
    pub base_q1: u64,
    /// Sum of the perturbed load–distances (the odometer's `u64` saturating sum), Q63.1.
    pub sum_q1: u64,
    /// Equivalent nominal cycles, fixed point (Q32.32 as a number).
    pub e_fixed: f64,
    /// Equivalent nominal cycles, `f64` (`Σ W_i / W_NOM_Q1`).
    pub e_f64: f64,
    /// Depth, fixed point (`depth_nm`), nm.
    pub depth_fixed_nm: u32,
    /// Depth, `f64` (`a·(E + m0)^b − c` with `powf`), nm.
    pub depth_f64_nm: f64,
    /// Remaining life as the odometer computes it (nominal cycles, floor), `None` past
    /// the 0.8 mm limit.
    pub remaining_fixed: Option<u32>,
    /// Remaining life in `f64` (`E_limit − E`), `None` past the limit.
    pub remaining_f64: Option<f64>,
}

impl FixedReport {
    /// `E` fixed − `f64`, relative to `f64`.
    pub fn e_rel_diff(&self) -> f64 {
        (self.e_fixed - self.e_f64) / self.e_f64
    }

    /// Depth fixed − `f64`, nm.
    pub fn depth_abs_diff_nm(&self) -> f64 {
        self.depth_fixed_nm as f64 - self.depth_f64_nm
    }

    /// Depth fixed − `f64`, relative to `f64`.
    pub fn depth_rel_diff(&self) -> f64 {
        self.depth_abs_diff_nm() / self.depth_f64_nm
    }

    /// Remaining life fixed − `f64`, cycles (both within the life only).
    pub fn remaining_diff(&self) -> Option<f64> {
        Some(self.remaining_fixed? as f64 - self.remaining_f64?)
    }

    fn to_json(self) -> String {
        let opt = |v: Option<f64>| v.map_or("null".to_string(), |x| format!("{x}"));
        format!(
            "{{\"cycles\":{},\"base_q1\":{},\"sum_q1\":{},\"e_fixed\":{},\"e_f64\":{},\"e_rel_diff\":{:e},\"depth_fixed_nm\":{},\"depth_f64_nm\":{},\"depth_abs_diff_nm\":{},\"depth_rel_diff\":{:e},\"remaining_fixed\":{},\"remaining_f64\":{},\"remaining_diff\":{}}}",
            self.cycles,
            self.base_q1,
            self.sum_q1,
            self.e_fixed,
            self.e_f64,
            self.e_rel_diff(),
            self.depth_fixed_nm,
            self.depth_f64_nm,
            self.depth_abs_diff_nm(),
            self.depth_rel_diff(),
            opt(self.remaining_fixed.map(f64::from)),
            opt(self.remaining_f64),
            opt(self.remaining_diff()),
        )
    }
}

/// Accumulate `cycles` perturbed copies of `base_q1` both ways (ZQSn5-2, 0.8 mm limit):
/// (a) as the odometer does — `u64` saturating sum, [`equivalent_cycles_q32`],
/// [`depth_nm`], remaining `(E_limit − E) / k`; (b) in `f64` — `E += W_i / W_NOM_Q1`,
/// `h = a·(E + m0)^b − c` with `powf`.
pub fn fixed_vs_f64_from(base_q1: u64, cycles: u32) -> FixedReport {
    let material = Material::ZQSn5_2;
    let limit_nm = WearConfig::DEFAULT.limit_nm;
    let mut sum_q1 = 0u64;
    let mut e_f64 = 0.0f64;
    for w in perturbed_cycles(base_q1).take(cycles as usize) {
        sum_q1 = sum_q1.saturating_add(w);
        e_f64 += w as f64 / W_NOM_Q1 as f64;
    }
    let e_q32 = equivalent_cycles_q32(sum_q1, material);
    let e_limit_q32 = e_at_depth_q32(limit_nm);
    let k = wear_factor_q32(material).max(1) as u128;
    let remaining_fixed = (e_q32 < e_limit_q32)
        .then(|| ((e_limit_q32 - e_q32) as u128 / k).min(u32::MAX as u128) as u32);
    let e_limit = e_limit_f64(limit_nm);
    FixedReport {
        cycles,
        base_q1,
        sum_q1,
        e_fixed: e_q32 as f64 / 4_294_967_296.0,
        e_f64,
        depth_fixed_nm: depth_nm(e_q32),
        depth_f64_nm: depth_f64_nm(e_f64),
        remaining_fixed,
        remaining_f64: (e_f64 < e_limit).then_some(e_limit - e_f64),
    }
}

/// [`fixed_vs_f64_from`] with the load–distance of a noisy closed-loop cycle at
/// [`REFERENCE_RATE_SPS`] ([`noisy_cycle_q1`]).
pub fn fixed_vs_f64(cycles: u32) -> FixedReport {
    fixed_vs_f64_from(noisy_cycle_q1(REFERENCE_RATE_SPS), cycles)
}

/// One row of the rate table.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RateRow {
    /// The two strokes of one dithered cycle.
    pub strokes: StrokeMeasurement,
    /// Cycles timed.
    pub timing_cycles: u32,
    /// Wall time per simulated cycle (default noise), s.
    pub wall_s_per_cycle: f64,
}

/// Everything `hil-sim accuracy` reports.
#[derive(Clone, Debug, PartialEq)]
pub struct AccuracyReport {
    /// One row per rate of [`RATES_SPS`].
    pub rows: Vec<RateRow>,
    /// Fixed point vs `f64`, one per [`FIXED_CYCLES`].
    pub fixed: Vec<FixedReport>,
    /// The wear estimate against cones that do not follow the model.
    pub estimate: EstimateStudy,
    /// The wear band early in a cone's life (issue 36).
    pub early: crate::early_life::EarlyComparison,
}

/// A cone's true wear law (the wear estimate's test cases), µm after `m` nominal
/// cycles.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WearLaw {
    /// Eq. 17 itself (the model's reduced-order form).
    Model,
    /// Eq. 17 × 1.3 (a softer batch).
    Scaled,
    /// A flatter power law, exponent 0.33 instead of 0.3813, at the model's a.
    Flatter,
    /// A steeper one, 0.43, 20 % smaller.
    Steeper,
    /// Running-in: 25 µm in the first few hundred cycles, then 0.9 × Eq. 17.
    RunningIn,
}

impl WearLaw {
    /// Every law.
    pub const ALL: [Self; 5] = [
        Self::Model,
        Self::Scaled,
        Self::Flatter,
        Self::Steeper,
        Self::RunningIn,
    ];

    /// Name for reports.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Model => "model",
            Self::Scaled => "scaled-1.3",
            Self::Flatter => "exponent-0.33",
            Self::Steeper => "exponent-0.43",
            Self::RunningIn => "running-in",
        }
    }

    /// Wear after `m` nominal cycles, µm.
    pub fn um(self, m: f64) -> f64 {
        let a = 13.72;
        let m0 = m0_f64();
        let model = depth_f64_nm(m) / 1000.0;
        match self {
            Self::Model => model,
            Self::Scaled => 1.3 * model,
            Self::Flatter => a * ((m + m0).powf(0.33) - m0.powf(0.33)),
            Self::Steeper => 0.8 * a * ((m + m0).powf(0.43) - m0.powf(0.43)),
            Self::RunningIn => 0.9 * model + 25.0 * (1.0 - (-m / 300.0).exp()),
        }
    }

    /// A technician's reading at `m` cycles (nominal load: E = m): the truth, noise
    /// σ = 3 µm, rounded to the micrometer's 1 µm.
    pub fn reading(self, m: u32, rng: &mut crate::rng::Rng) -> Reading {
        let y_um = (self.um(m as f64) + 3.0 * rng.normal()).round();
        Reading {
            e_q32: (m as u64) << 32,
            wear_nm: (y_um * 1000.0) as i32,
        }
    }

    /// Readings every 1 000 cycles up to `last`, seeded.
    pub fn readings(self, last: u32, seed: u64) -> Vec<Reading> {
        let mut rng = crate::rng::Rng::new(seed);
        (1..=last / 1000)
            .map(|k| self.reading(k * 1000, &mut rng))
            .collect()
    }
}

/// Where the estimate is judged, cycles.
pub const ESTIMATE_AT: u32 = 30_000;
/// Readings counts compared (the first k of one every 1 000 cycles).
pub const ESTIMATE_READINGS: [usize; 6] = [0, 1, 3, 10, 20, 30];
/// Seeds per case.
pub const ESTIMATE_SEEDS: u64 = 20;

/// One law, one readings count.
#[derive(Clone, Debug, PartialEq)]
pub struct EstimateRow {
    /// The true law.
    pub law: WearLaw,
    /// Readings used (every 1 000 cycles from 1 000).
    pub readings: usize,
    /// Mean |estimate − truth| at [`ESTIMATE_AT`], µm.
    pub estimate_err_um: f64,
    /// |model − truth| there, µm.
    pub model_err_um: f64,
    /// Mean band width there, µm.
    pub band_um: f64,
    /// Share of seeds whose band holds the truth, %.
    pub inside_pct: f64,
    /// The previous release's (7c11783, [`crate::previous_estimate`]) mean error, µm.
    pub previous_err_um: f64,
    /// Its mean band width, µm.
    pub previous_band_um: f64,
}

/// The estimate study.
#[derive(Clone, Debug, PartialEq)]
pub struct EstimateStudy {
    /// Rows by law, then readings.
    pub rows: Vec<EstimateRow>,
    /// Host wall time of one fit over 30 readings, µs (median of 200).
    pub update_us: f64,
}

/// Run the estimate study.
pub fn estimate_study() -> EstimateStudy {
    let mut rows = Vec::new();
    for law in WearLaw::ALL {
        let truth = law.um(ESTIMATE_AT as f64);
        let model_err_um = (depth_f64_nm(ESTIMATE_AT as f64) / 1000.0 - truth).abs();
        for k in ESTIMATE_READINGS {
            let (mut err, mut band, mut inside) = (0.0, 0.0, 0);
            let (mut prev_err, mut prev_band) = (0.0, 0.0);
            for seed in 0..ESTIMATE_SEEDS {
                let r = law.readings(ESTIMATE_AT, seed);
                let prev = crate::previous_estimate::Fit::new(&r[..k.min(r.len())]).at(
                    (ESTIMATE_AT as u64) << 32,
                    800_000,
                    Material::ZQSn5_2,
                );
                prev_err += (prev.wear_nm as f64 / 1000.0 - truth).abs();
                prev_band += (prev.high_nm - prev.low_nm) as f64 / 1000.0;
                let est = Fit::new(&r[..k.min(r.len())]).at(
                    (ESTIMATE_AT as u64) << 32,
                    800_000,
                    Material::ZQSn5_2,
                );
                let (w, lo, hi) = (
                    est.wear_nm as f64 / 1000.0,
                    est.low_nm as f64 / 1000.0,
                    est.high_nm as f64 / 1000.0,
                );
                err += (w - truth).abs();
                band += hi - lo;
                inside += usize::from(lo <= truth && truth <= hi);
            }
            let n = ESTIMATE_SEEDS as f64;
            rows.push(EstimateRow {
                law,
                readings: k,
                estimate_err_um: err / n,
                model_err_um,
                band_um: band / n,
                inside_pct: 100.0 * inside as f64 / n,
                previous_err_um: prev_err / n,
                previous_band_um: prev_band / n,
            });
        }
    }
    let r = WearLaw::Scaled.readings(ESTIMATE_AT, 1);
    let mut times: Vec<f64> = (0..200)
        .map(|_| {
            let t = std::time::Instant::now();
            std::hint::black_box(Fit::new(std::hint::black_box(&r)));
            t.elapsed().as_secs_f64() * 1e6
        })
        .collect();
    times.sort_by(f64::total_cmp);
    EstimateStudy {
        rows,
        update_us: times[times.len() / 2],
    }
}

/// Run everything: per-rate stroke errors and wall time, then the fixed-point
/// comparison (a few seconds in release, dominated by the 1280 SPS timing run).
pub fn run() -> AccuracyReport {
    let rows = RATES_SPS
        .iter()
        .map(|&rate| {
            let n = timing_cycles(rate);
            RateRow {
                strokes: measure_strokes(rate),
                timing_cycles: n,
                wall_s_per_cycle: wall_s_per_cycle(rate, n),
            }
        })
        .collect();
    let base_q1 = noisy_cycle_q1(REFERENCE_RATE_SPS);
    let fixed = FIXED_CYCLES
        .iter()
        .map(|&n| fixed_vs_f64_from(base_q1, n))
        .collect();
    AccuracyReport {
        rows,
        fixed,
        estimate: estimate_study(),
        early: crate::early_life::early_life_study(crate::early_life::SEEDS, true),
    }
}

impl AccuracyReport {
    /// One JSON object on one line.
    pub fn to_json(&self) -> String {
        let rows: Vec<String> = self
            .rows
            .iter()
            .map(|r| {
                let s = &r.strokes;
                format!(
                    "{{\"rate_sps\":{},\"insertion_n_mm\":{},\"insertion_err_pct\":{},\"extraction_n_mm\":{},\"extraction_err_pct\":{},\"position_offset_um\":{},\"insertion_span_um\":[{},{}],\"extraction_span_um\":[{},{}],\"timing_cycles\":{},\"wall_ms_per_cycle\":{}}}",
                    s.rate_sps,
                    s.insertion_n_mm(),
                    s.insertion_err_pct(),
                    s.extraction_n_mm(),
                    s.extraction_err_pct(),
                    s.position_offset_um,
                    s.insertion_span_um.0,
                    s.insertion_span_um.1,
                    s.extraction_span_um.0,
                    s.extraction_span_um.1,
                    r.timing_cycles,
                    r.wall_s_per_cycle * 1e3
                )
            })
            .collect();
        let fixed: Vec<String> = self.fixed.iter().map(|f| f.to_json()).collect();
        let est: Vec<String> = self
            .estimate
            .rows
            .iter()
            .map(|r| {
                format!(
                    "{{\"law\":\"{}\",\"readings\":{},\"estimate_err_um\":{:.3},\"model_err_um\":{:.3},\"band_um\":{:.3},\"inside_pct\":{:.1},\"previous_err_um\":{:.3},\"previous_band_um\":{:.3}}}",
                    r.law.name(),
                    r.readings,
                    r.estimate_err_um,
                    r.model_err_um,
                    r.band_um,
                    r.inside_pct,
                    r.previous_err_um,
                    r.previous_band_um
                )
            })
            .collect();
        let est = format!(
            ",\"estimate\":{{\"at_cycles\":{ESTIMATE_AT},\"seeds\":{ESTIMATE_SEEDS},\"update_us_host\":{:.2},\"rows\":[{}]}}",
            self.estimate.update_us,
            est.join(",")
        );
        let early = self.early.to_json();
        format!(
            "{{\"exact_stroke_n_mm\":{},\"dither_counts\":{},\"rates\":[{}],\"fixed\":{{\"material\":\"{}\",\"reference_rate_sps\":{},\"perturb_ppm\":{},\"seed\":{},\"runs\":[{}]}}{est},\"early_life\":{early}}}",
            EXACT_STROKE_N_MM,
            DITHER_COUNTS,
            rows.join(","),
            Material::ZQSn5_2.name(),
            REFERENCE_RATE_SPS,
            PERTURB_PPM,
            PERTURB_SEED,
            fixed.join(",")
        )
    }

    /// Tables for a terminal.
    pub fn to_text(&self) -> String {
        let mut s = format!(
            "# per-stroke load-distance vs the exact {EXACT_STROKE_N_MM:.4} N·mm (closed loop, 1st cycle, load cell dithered {DITHER_COUNTS} count RMS)\n"
        );
        s += "rate_sps | insertion N·mm |    err % | extraction N·mm |    err % | wall ms/cycle\n";
        for r in &self.rows {
            let m = &r.strokes;
            s += &format!(
                "{:>8} | {:>14.4} | {:>+8.4} | {:>15.4} | {:>+8.4} | {:>13.3}\n",
                m.rate_sps,
                m.insertion_n_mm(),
                m.insertion_err_pct(),
                m.extraction_n_mm(),
                m.extraction_err_pct(),
                r.wall_s_per_cycle * 1e3
            );
        }
        s += "# counted depth of each stroke's first/last sample, µm, and counted-minus-true position (homing overshoot)\n";
        for r in &self.rows {
            let m = &r.strokes;
            s += &format!(
                "#   {:>4} SPS: insertion {} → {}, extraction {} → {}, offset {} µm; wall time over {} cycles (default noise)\n",
                m.rate_sps,
                m.insertion_span_um.0,
                m.insertion_span_um.1,
                m.extraction_span_um.0,
                m.extraction_span_um.1,
                m.position_offset_um,
                r.timing_cycles
            );
        }
        if let Some(f) = self.fixed.first() {
            s += &format!(
                "# fixed-point odometer vs f64 ({}): W_i = {:.4} N·mm ({} SPS noisy cycle) × (1 ± {} %), xorshift seed {:#x}\n",
                Material::ZQSn5_2.name(),
                q1_to_n_mm(f.base_q1),
                REFERENCE_RATE_SPS,
                PERTURB_PPM as f64 / 1e4,
                PERTURB_SEED
            );
        }
        s += "  cycles |        E fixed |          E f64 | E rel diff | depth fixed nm |   depth f64 nm | diff nm |  rel diff | remaining fixed / f64\n";
        for f in &self.fixed {
            let remaining = match (f.remaining_fixed, f.remaining_f64) {
                (Some(a), Some(b)) => format!("{a} / {b:.3} (diff {:+.3})", a as f64 - b),
                _ => "past the 0.8 mm limit".to_string(),
            };
            s += &format!(
                "{:>8} | {:>14.6} | {:>14.6} | {:>+10.2e} | {:>14} | {:>14.3} | {:>+7.3} | {:>+9.2e} | {}\n",
                f.cycles,
                f.e_fixed,
                f.e_f64,
                f.e_rel_diff(),
                f.depth_fixed_nm,
                f.depth_f64_nm,
                f.depth_abs_diff_nm(),
                f.depth_rel_diff(),
                remaining
            );
        }
        s += &format!(
            "# wear estimate at {ESTIMATE_AT} cycles from the first k micrometer readings (one per 1 000 cycles, σ 3 µm, 1 µm resolution), mean over {ESTIMATE_SEEDS} seeds, against cones that follow other laws; the model alone beside it\n"
        );
        s += "law           |  k | estimate err µm | model err µm | band µm | truth in band % | 7c11783: err µm | band µm | band now / then\n";
        for r in &self.estimate.rows {
            s += &format!(
                "{:<13} | {:>2} | {:>15.1} | {:>12.1} | {:>7.1} | {:>15.0} | {:>15.1} | {:>7.1} | {:>15.2}\n",
                r.law.name(),
                r.readings,
                r.estimate_err_um,
                r.model_err_um,
                r.band_um,
                r.inside_pct,
                r.previous_err_um,
                r.previous_band_um,
                r.band_um / r.previous_band_um
            );
        }
        s += &format!(
            "# one update (a fit over 30 readings): {:.1} µs on this host; on the Cortex-M4, instructions: `cd vboard && cargo run --release -- estimate-cost`\n",
            self.estimate.update_us
        );
        s += &self.early.to_text();
        s
    }
}

// ---------------------------------------------------------------------------------------
// The plant model (`crate::plant`): the equilibrium systems behind Eq. 7.
// ---------------------------------------------------------------------------------------

use crate::plant::{Contact, Plant, PlantParams, REFERENCE_TABLE, TILT_MAX_ITER, TILT_TOL_RAD};
use docking_logic::profile::forces_at_time;

/// Sampling step of the plant's residuals against Eq. 7, s.
pub const PLANT_RESIDUAL_STEP_S: f64 = 0.001;

/// Trapezoid steps of the ∫N3 dt convergence, s.
pub const PLANT_INTEGRAL_STEPS_S: [f64; 4] = [1.0, 0.1, 0.01, 0.001];

/// The reference ∫N3 dt of the plant over 0–25 s (`docs/physics.md` §8.5), N·s.
pub const PLANT_N3_INTEGRAL_REF_NS: f64 = 3377.1;

/// Tilt solver iteration caps compared (with no tolerance: exactly that many).
pub const PLANT_TILT_CAPS: [u32; 6] = [1, 2, 3, 4, 5, 6];

/// Tilt solver tolerances compared, rad.
pub const PLANT_TILT_TOLS_RAD: [f64; 3] = [1e-3, 1e-6, 1e-9];

/// Plant evaluations timed.
pub const PLANT_TIMED_EVALS: u32 = 200_000;

/// Stability sweep grid: mass kg, µ1, µ2, γ °, θ0 °, v_model mm/s.
pub const SWEEP_MASS_KG: [f64; 4] = [8.0, 12.0, 16.0, 20.0];
/// µ1 values of the sweep.
pub const SWEEP_MU1: [f64; 5] = [0.05, 0.1125, 0.175, 0.2375, 0.3];
/// µ2 values of the sweep.
pub const SWEEP_MU2: [f64; 5] = [0.05, 0.1125, 0.175, 0.2375, 0.3];
/// γ values of the sweep, degrees.
pub const SWEEP_GAMMA_DEG: [f64; 4] = [10.0, 15.0, 20.0, 25.0];
/// θ0 values of the sweep, degrees.
pub const SWEEP_THETA0_DEG: [f64; 5] = [1.5, 2.125, 2.75, 3.375, 4.0];
/// Both readings of Eq. 7's time axis, mm/s.
pub const SWEEP_V_MODEL: [f64; 2] = [1.2, 4.0];
/// Sweep times: 0 to this, s (the 25 s stroke and 5 s of overtravel, where N4 lifts).
pub const SWEEP_T_END_S: f64 = 30.0;
/// Sweep time step, s.
pub const SWEEP_DT_S: f64 = 0.05;

/// ∫N3 dt at one step size.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct IntegralRow {
    /// Step, s.
    pub step_s: f64,
    /// Trapezoid per phase (boundaries hit exactly, each phase's own system at both
    /// ends: no smoothing across the jumps), N·s.
    pub per_phase_ns: f64,
    /// Trapezoid on a uniform grid from 0 across the jumps, N·s.
    pub uniform_ns: f64,
}

/// The tilt at one solver setting, against the converged tilt.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TiltRow {
    /// Iteration cap.
    pub cap: u32,
    /// Step tolerance, rad.
    pub tol_rad: f64,
    /// Largest |θ − θ converged| over the phase-4 samples, degrees.
    pub max_theta_err_deg: f64,
    /// Largest force difference that causes, N.
    pub max_force_err_n: f64,
    /// Largest iteration count used.
    pub worst_iterations: u32,
}

/// The stability sweep's counts.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct SweepCounts {
    /// Parameter sets.
    pub param_sets: u64,
    /// Evaluations.
    pub evaluations: u64,
    /// Evaluations with a NaN or infinite output (must be 0).
    pub nan: u64,
    /// Evaluations with a negative force (must be 0).
    pub negative: u64,
    /// Parameter sets whose evaluation panicked (must be 0).
    pub panics: u64,
    /// Evaluations reporting a lift-off, by contact (N1–N4).
    pub lifted: [u64; 4],
    /// Parameter sets with at least one lift-off, by contact.
    pub sets_lifted: [u64; 4],
    /// Evaluations not resolved (moment unbalanced after a lift-off, or clamped).
    pub unresolved: u64,
    /// Evaluations whose nominal contact set had a negative force but no lift-off was
    /// reported (must be 0).
    pub unreported: u64,
    /// Evaluations reporting a lift-off with no negative nominal force (must be 0).
    pub spurious: u64,
    /// Singular nominal systems or unbracketed tilts.
    pub singular: u64,
    /// Worst tilt-solver iteration count.
    pub worst_iterations: u32,
    /// Phase-4 evaluations (those that run the tilt solver).
    pub phase4: u64,
    /// Wall time of the sweep, s.
    pub wall_s: f64,
}

/// Everything the accuracy report says about the plant.
#[derive(Clone, Debug, PartialEq)]
pub struct PlantStudy {
    /// Largest force error against the reference's table ([`PlantParams::REFERENCE`]), N.
    pub table_max_err_n: f64,
    /// Largest tilt error there, degrees.
    pub table_max_err_theta_deg: f64,
    /// The default (geometric) phase 3→4 boundary, s.
    pub geometric_t3_s: f64,
    /// Largest force difference, default boundary minus the table, over the table rows
    /// that stay in their phase (all but 12.4449 s), N.
    pub geometric_table_max_dev_n: f64,
    /// Max |plant − Eq. 7| per phase (rows) and force N1–N4 (columns), N.
    pub residuals_n: [[f64; 4]; 4],
    /// ∫N3 dt against the step.
    pub integral: Vec<IntegralRow>,
    /// ∫N3 dt with the default (geometric) boundary, per phase at 0.001 s, N·s.
    pub integral_geometric_ns: f64,
    /// θ error against the solver's cap and tolerance.
    pub tilt: Vec<TiltRow>,
    /// Wall time per evaluation over the stroke, ns.
    pub ns_per_eval: f64,
    /// Wall time per phase-4 evaluation (tilt solver included), ns.
    pub ns_per_eval_phase4: f64,
    /// The stability sweep.
    pub sweep: SweepCounts,
}

fn max_abs_diff(a: [f64; 4], b: [f64; 4]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f64::max)
}

/// ∫N3 dt over 0–25 s of Eq. 7's axis by the trapezoid, per phase and uniform.
pub fn plant_n3_integral(plant: &Plant, step_s: f64) -> IntegralRow {
    let v = plant.params().v_model_mm_s;
    let [t1, t2, t3] = plant.boundaries_s();
    let end = crate::plant::STROKE_S;
    let mut per_phase = 0.0;
    for (ph, a, b) in [(1u8, 0.0, t1), (2, t1, t2), (3, t2, t3), (4, t3, end)] {
        let (a, b) = (a.min(end), b.min(end));
        if b <= a {
            continue;
        }
        let n = ((b - a) / step_s).ceil().max(1.0) as u64;
        let h = (b - a) / n as f64;
        let f = |t: f64| plant.in_phase(ph, v * t).n3_n;
        let mut s = 0.5 * (f(a) + f(b));
        for k in 1..n {
            s += f(a + k as f64 * h);
        }
        per_phase += s * h;
    }
    let n = (end / step_s).round() as u64;
    let h = end / n as f64;
    let f = |t: f64| plant.at_time(t).n3_n;
    let mut s = 0.5 * (f(0.0) + f(end));
    for k in 1..n {
        s += f(k as f64 * h);
    }
    IntegralRow {
        step_s,
        per_phase_ns: per_phase,
        uniform_ns: s * h,
    }
}

/// Run the stability sweep over the grid of `SWEEP_*`.
pub fn plant_sweep() -> SweepCounts {
    let started = Instant::now();
    let mut c = SweepCounts::default();
    let samples = (SWEEP_T_END_S / SWEEP_DT_S).round() as u64;
    for &mass_kg in &SWEEP_MASS_KG {
        for &mu1 in &SWEEP_MU1 {
            for &mu2 in &SWEEP_MU2 {
                for &gamma_deg in &SWEEP_GAMMA_DEG {
                    for &theta0_deg in &SWEEP_THETA0_DEG {
                        for &v_model_mm_s in &SWEEP_V_MODEL {
                            let p = PlantParams {
                                mass_kg,
                                mu1,
                                mu2,
                                gamma_deg,
                                theta0_deg,
                                v_model_mm_s,
                                ..PlantParams::PAPER
                            };
                            c.param_sets += 1;
                            let one = std::panic::catch_unwind(|| sweep_one(p, samples));
                            match one {
                                Ok(Some(s)) => c.add(&s),
                                _ => c.panics += 1,
                            }
                        }
                    }
                }
            }
        }
    }
    c.wall_s = started.elapsed().as_secs_f64();
    c
}

impl SweepCounts {
    fn add(&mut self, s: &SweepCounts) {
        self.evaluations += s.evaluations;
        self.nan += s.nan;
        self.negative += s.negative;
        for k in 0..4 {
            self.lifted[k] += s.lifted[k];
            self.sets_lifted[k] += u64::from(s.lifted[k] > 0);
        }
        self.unresolved += s.unresolved;
        self.unreported += s.unreported;
        self.spurious += s.spurious;
        self.singular += s.singular;
        self.worst_iterations = self.worst_iterations.max(s.worst_iterations);
        self.phase4 += s.phase4;
    }

    /// Whether every invariant holds: no NaN, no negative force, no panic, every
    /// lift-off reported and none reported without cause.
    pub fn ok(&self) -> bool {
        self.nan == 0
            && self.negative == 0
            && self.panics == 0
            && self.unreported == 0
            && self.spurious == 0
    }
}

/// One parameter set of the sweep; `None` if the parameters are invalid (they never are).
fn sweep_one(p: PlantParams, samples: u64) -> Option<SweepCounts> {
    let plant = Plant::new(p).ok()?;
    let mut c = SweepCounts::default();
    for k in 0..=samples {
        let t = k as f64 * SWEEP_DT_S;
        let pt = plant.at_time(t);
        c.evaluations += 1;
        let f = pt.forces();
        if f.iter().any(|x| !x.is_finite()) || !pt.theta_deg.is_finite() {
            c.nan += 1;
        }
        if f.iter().any(|&x| x < 0.0) {
            c.negative += 1;
        }
        if let Some(l) = pt.lifted {
            c.lifted[l.index()] += 1;
        }
        if !pt.resolved {
            c.unresolved += 1;
        }
        if pt.phase == 4 {
            c.phase4 += 1;
            c.worst_iterations = c.worst_iterations.max(pt.iterations);
        }
        match plant.nominal_forces(pt.depth_mm) {
            None => c.singular += 1,
            Some(raw) => {
                let negative = raw.iter().any(|&x| x < 0.0);
                if negative && pt.lifted.is_none() {
                    c.unreported += 1;
                }
                if !negative && pt.lifted.is_some() {
                    c.spurious += 1;
                }
            }
        }
    }
    Some(c)
}

/// Wall time per `at_time` evaluation over `times`, ns (at least [`PLANT_TIMED_EVALS`]).
fn ns_per_eval(plant: &Plant, times: &[f64]) -> f64 {
    let rounds = (PLANT_TIMED_EVALS as usize).div_ceil(times.len().max(1));
    let started = Instant::now();
    let mut acc = 0.0;
    for _ in 0..rounds {
        for &t in times {
            acc += std::hint::black_box(plant)
                .at_time(std::hint::black_box(t))
                .n3_n;
        }
    }
    std::hint::black_box(acc);
    started.elapsed().as_secs_f64() * 1e9 / (rounds * times.len()) as f64
}

/// Run the plant study (about a second in release, most of it the sweep).
pub fn plant_study() -> PlantStudy {
    let reference = Plant::new(PlantParams::REFERENCE).expect("reference parameters are valid");
    let geometric = Plant::new(PlantParams::PAPER).expect("paper parameters are valid");

    let (mut table_max_err_n, mut table_max_err_theta_deg, mut geo_dev) = (0.0f64, 0.0f64, 0.0f64);
    for r in REFERENCE_TABLE {
        let pt = reference.at_time(r.t_s);
        table_max_err_n = table_max_err_n.max(max_abs_diff(pt.forces(), r.forces_n));
        table_max_err_theta_deg = table_max_err_theta_deg.max((pt.theta_deg - r.theta_deg).abs());
        let g = geometric.at_time(r.t_s);
        if g.phase == r.phase {
            geo_dev = geo_dev.max(max_abs_diff(g.forces(), r.forces_n));
        }
    }

    let mut residuals_n = [[0.0f64; 4]; 4];
    let n = (crate::plant::STROKE_S / PLANT_RESIDUAL_STEP_S).round() as u64;
    for k in 0..=n {
        let t = k as f64 * PLANT_RESIDUAL_STEP_S;
        let pt = reference.at_time(t);
        let e = forces_at_time(t);
        let d = [
            (pt.n1_n - e.n1_n).abs(),
            (pt.n2_n - e.n2_n).abs(),
            (pt.n3_n - e.n3_n).abs(),
            (pt.n4_n - e.n4_n).abs(),
        ];
        if let Some(row) = residuals_n.get_mut(usize::from(pt.phase.saturating_sub(1))) {
            for (a, b) in row.iter_mut().zip(d) {
                *a = a.max(b);
            }
        }
    }

    let integral = PLANT_INTEGRAL_STEPS_S
        .iter()
        .map(|&h| plant_n3_integral(&reference, h))
        .collect();
    let integral_geometric_ns = plant_n3_integral(&geometric, 0.001).per_phase_ns;

    // Tilt: every 0.01 s of phase 4 (12.445–25 s), against the default solver.
    let phase4_times: Vec<f64> = (0..=1255).map(|k| 12.445 + k as f64 * 0.01).collect();
    let converged: Vec<_> = phase4_times.iter().map(|&t| reference.at_time(t)).collect();
    let settings = PLANT_TILT_CAPS
        .iter()
        .map(|&cap| (cap, 0.0))
        .chain(PLANT_TILT_TOLS_RAD.iter().map(|&tol| (TILT_MAX_ITER, tol)));
    let tilt = settings
        .map(|(cap, tol_rad)| {
            let p = reference.with_tilt_solver(cap, tol_rad);
            let mut row = TiltRow {
                cap,
                tol_rad,
                max_theta_err_deg: 0.0,
                max_force_err_n: 0.0,
                worst_iterations: 0,
            };
            for (&t, c) in phase4_times.iter().zip(&converged) {
                let pt = p.at_time(t);
                row.max_theta_err_deg = row
                    .max_theta_err_deg
                    .max((pt.theta_deg - c.theta_deg).abs());
                row.max_force_err_n = row
                    .max_force_err_n
                    .max(max_abs_diff(pt.forces(), c.forces()));
                row.worst_iterations = row.worst_iterations.max(pt.iterations);
            }
            row
        })
        .collect();

    let stroke_times: Vec<f64> = (0..=2500).map(|k| k as f64 * 0.01).collect();
    let ns_per_eval = ns_per_eval(&geometric, &stroke_times);
    let ns_per_eval_phase4 = self::ns_per_eval(&reference, &phase4_times);

    PlantStudy {
        table_max_err_n,
        table_max_err_theta_deg,
        geometric_t3_s: geometric.boundaries_s()[2],
        geometric_table_max_dev_n: geo_dev,
        residuals_n,
        integral,
        integral_geometric_ns,
        tilt,
        ns_per_eval,
        ns_per_eval_phase4,
        sweep: plant_sweep(),
    }
}

impl PlantStudy {
    /// The plant's fields, as a JSON object.
    pub fn to_json(&self) -> String {
        let res: Vec<String> = self
            .residuals_n
            .iter()
            .enumerate()
            .map(|(k, r)| {
                format!(
                    "{{\"phase\":{},\"n1_n\":{:.4},\"n2_n\":{:.4},\"n3_n\":{:.4},\"n4_n\":{:.4}}}",
                    k + 1,
                    r[0],
                    r[1],
                    r[2],
                    r[3]
                )
            })
            .collect();
        let int: Vec<String> = self
            .integral
            .iter()
            .map(|r| {
                format!(
                    "{{\"step_s\":{},\"per_phase_ns\":{:.6},\"uniform_ns\":{:.6}}}",
                    r.step_s, r.per_phase_ns, r.uniform_ns
                )
            })
            .collect();
        let tilt: Vec<String> = self
            .tilt
            .iter()
            .map(|r| {
                format!(
                    "{{\"cap\":{},\"tol_rad\":{:e},\"max_theta_err_deg\":{:e},\"max_force_err_n\":{:e},\"worst_iterations\":{}}}",
                    r.cap, r.tol_rad, r.max_theta_err_deg, r.max_force_err_n, r.worst_iterations
                )
            })
            .collect();
        let s = &self.sweep;
        let list = |v: &[f64]| {
            v.iter()
                .map(|x| x.to_string())
                .collect::<Vec<_>>()
                .join(",")
        };
        let by_contact = |v: [u64; 4]| {
            Contact::ALL
                .iter()
                .zip(v)
                .map(|(c, n)| format!("\"{}\":{n}", c.name()))
                .collect::<Vec<_>>()
                .join(",")
        };
        format!(
            "{{\"table_max_err_n\":{:e},\"table_max_err_theta_deg\":{:e},\"geometric_t3_s\":{:.6},\"geometric_table_max_dev_n\":{:.6},\"residual_step_s\":{PLANT_RESIDUAL_STEP_S},\"residuals_vs_eq7\":[{}],\"n3_integral_ref_ns\":{PLANT_N3_INTEGRAL_REF_NS},\"n3_integral\":[{}],\"n3_integral_geometric_ns\":{:.6},\"tilt_default\":{{\"cap\":{TILT_MAX_ITER},\"tol_rad\":{TILT_TOL_RAD:e}}},\"tilt\":[{}],\"ns_per_eval\":{:.1},\"ns_per_eval_phase4\":{:.1},\"sweep\":{{\"mass_kg\":[{}],\"mu1\":[{}],\"mu2\":[{}],\"gamma_deg\":[{}],\"theta0_deg\":[{}],\"v_model_mm_s\":[{}],\"t_end_s\":{SWEEP_T_END_S},\"dt_s\":{SWEEP_DT_S},\"param_sets\":{},\"evaluations\":{},\"nan\":{},\"negative\":{},\"panics\":{},\"lifted\":{{{}}},\"sets_lifted\":{{{}}},\"unresolved\":{},\"unreported\":{},\"spurious\":{},\"singular\":{},\"phase4\":{},\"worst_iterations\":{},\"ok\":{},\"wall_s\":{:.3}}}}}",
            self.table_max_err_n,
            self.table_max_err_theta_deg,
            self.geometric_t3_s,
            self.geometric_table_max_dev_n,
            res.join(","),
            int.join(","),
            self.integral_geometric_ns,
            tilt.join(","),
            self.ns_per_eval,
            self.ns_per_eval_phase4,
            list(&SWEEP_MASS_KG),
            list(&SWEEP_MU1),
            list(&SWEEP_MU2),
            list(&SWEEP_GAMMA_DEG),
            list(&SWEEP_THETA0_DEG),
            list(&SWEEP_V_MODEL),
            s.param_sets,
            s.evaluations,
            s.nan,
            s.negative,
            s.panics,
            by_contact(s.lifted),
            by_contact(s.sets_lifted),
            s.unresolved,
            s.unreported,
            s.spurious,
            s.singular,
            s.phase4,
            s.worst_iterations,
            s.ok(),
            s.wall_s
        )
    }

    /// The plant's tables for a terminal.
    pub fn to_text(&self) -> String {
        let mut s = format!(
            "# plant (equilibrium systems of Eqs. 3–6, hil-sim/src/plant.rs) vs the reference's table (t3 = 12.445 s): max |ΔN| {:.2e} N, max |Δθ| {:.2e}°\n",
            self.table_max_err_n, self.table_max_err_theta_deg
        );
        s += &format!(
            "# default t3 from the geometry: {:.4} s; the table's rows that stay in their phase move by up to {:.4} N with it\n",
            self.geometric_t3_s, self.geometric_table_max_dev_n
        );
        s += &format!(
            "# max |plant − Eq. 7| every {PLANT_RESIDUAL_STEP_S} s, N (t3 = 12.445 s as Eq. 7)\nphase |     N1 |     N2 |     N3 |     N4\n"
        );
        for (k, r) in self.residuals_n.iter().enumerate() {
            s += &format!(
                "{:>5} | {:>6.3} | {:>6.3} | {:>6.3} | {:>6.3}\n",
                k + 1,
                r[0],
                r[1],
                r[2],
                r[3]
            );
        }
        s += &format!(
            "# ∫N3 dt over 0–25 s, N·s (reference {PLANT_N3_INTEGRAL_REF_NS}; Eq. 7 {:.2}); default t3: {:.4}\n  step s | per phase      | uniform grid (across the jumps)\n",
            docking_logic::profile::N3_STROKE_INTEGRAL_NS,
            self.integral_geometric_ns
        );
        for r in &self.integral {
            s += &format!(
                "{:>8} | {:>14.6} | {:>14.6}\n",
                r.step_s, r.per_phase_ns, r.uniform_ns
            );
        }
        s += &format!(
            "# Eq. 6 tilt (bracketed Newton on G) against the default solver (cap {TILT_MAX_ITER}, tol {TILT_TOL_RAD:e} rad), every 0.01 s of phase 4\n  cap | tol rad | max |Δθ| ° | max |ΔN| N | worst iterations\n"
        );
        for r in &self.tilt {
            let tol = if r.tol_rad > 0.0 {
                format!("{:.0e}", r.tol_rad)
            } else {
                "-".to_string()
            };
            s += &format!(
                "{:>5} | {:>7} | {:>10.2e} | {:>10.2e} | {:>3}\n",
                r.cap, tol, r.max_theta_err_deg, r.max_force_err_n, r.worst_iterations
            );
        }
        s += &format!(
            "# wall time per evaluation on this host: {:.0} ns over the stroke, {:.0} ns in phase 4 ({} evaluations each)\n",
            self.ns_per_eval, self.ns_per_eval_phase4, PLANT_TIMED_EVALS
        );
        let w = &self.sweep;
        let by = |v: [u64; 4]| {
            Contact::ALL
                .iter()
                .zip(v)
                .map(|(c, n)| format!("{} {n}", c.name()))
                .collect::<Vec<_>>()
                .join(", ")
        };
        s += &format!(
            "# stability sweep: mass {:?} kg × µ1 {:?} × µ2 {:?} × γ {:?}° × θ0 {:?}° × v_model {:?} mm/s, t 0–{SWEEP_T_END_S} s every {SWEEP_DT_S} s\n",
            SWEEP_MASS_KG, SWEEP_MU1, SWEEP_MU2, SWEEP_GAMMA_DEG, SWEEP_THETA0_DEG, SWEEP_V_MODEL
        );
        s += &format!(
            "sweep: {} parameter sets, {} evaluations ({} in phase 4) in {:.2} s: NaN {}, negative {}, panics {}, unreported lift-offs {}, spurious {}, singular {}; lift-offs (evaluations): {}; (parameter sets): {}; unresolved {}; worst tilt iterations {} — {}\n",
            w.param_sets,
            w.evaluations,
            w.phase4,
            w.wall_s,
            w.nan,
            w.negative,
            w.panics,
            w.unreported,
            w.spurious,
            w.singular,
            by(w.lifted),
            by(w.sets_lifted),
            w.unresolved,
            w.worst_iterations,
            if w.ok() { "ok" } else { "FAILED" }
        );
        s
    }
}

/// The accuracy report's JSON with the plant study as its `plant` field.
pub fn json_with_plant(report: &AccuracyReport, plant: &PlantStudy) -> String {
    let mut j = report.to_json();
    if j.ends_with('}') {
        j.pop();
        j += &format!(",\"plant\":{}}}", plant.to_json());
    }
    j
}
