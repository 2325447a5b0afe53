//! The cone's wear estimated from where its 3→4 force step lies: an estimate **beside**
//! the micrometer's reading and the odometer's model, never in their place.
//!
//! # Why the step
//!
//! Two-point contact begins at the engaged length `L* = (D2 − D1·cos θ0)/sin θ0`
//! (Eq. 6): a bore worn by `w` moves the insertion's 3→4 force step
//! `s = (v0 / v_model)·cot θ0` deeper per µm — 6.047 µm a µm on Eq. 7's machine
//! ([`crate::profile::STEP_UM_PER_WEAR_MM`], from its geometry; another machine's from
//! its plant at commissioning: [`SignatureConfig::step_um_per_wear_mm`]) — while the
//! forces at a given depth change by well under 1 % (`docs/physics.md` §10.5: the step
//! tells a few µm of wear after 20 dockings; no force figure tells less than 30 µm).
//! The step's depth is the one the objects already move with: the insertion's figure
//! [`super::figures::InsertionFigures::step_um`] (no second step finder).
//!
//! # The estimate
//!
//! The reference is the cone's own step: the mean `r̄` of the steps of the `N` dockings
//! in its reference (the first `reference_n` OK dockings after `cone replace`,
//! [`super::records::Reference`]'s `step_sum / step_n`). After it, each OK docking's
//! step enters a window ([`StepWindow`]: the newest [`WINDOW_MAX`], kept per cone); the
//! newest `m ≤ M` ([`SignatureConfig::wear_window`], 20) of them, mean `x̄` and sample
//! standard deviation `sd`, give, once `m ≥` [`SignatureConfig::wear_min`] (5):
//!
//! ```text
//!   wear   = (x̄ − r̄) / s                                   the wear since `cone replace`
//!   band   = max( t(m−1) · sd · √(1/m + 1/N),  q_floor ) / s       ± , 95 %
//!   q_floor = q   if sd < q/2,  else 0
//! ```
//!
//! * `t(m−1)`: Student's t at 97.5 % with `m − 1` degrees of freedom (the spread is
//!   taken from the window: 2.09 at m = 20; 1.96 is its large-sample value), the
//!   reference's steps assumed as spread as the window's (their spread is not kept).
//! * `q`: the sample spacing, `v0 / rate` (15 µm at 80 SPS, 120 µm at 10 SPS): the step
//!   finder places the step to one sample. Unless the steps spread by half a spacing
//!   or more (then the quantisation is dithered: its residual bias on a mean,
//!   `(q/π)·exp(−2π²·sd²/q²)`, is under 1 % of `q`), it is not averaged away — the
//!   sample phase against the stroke repeats from one docking to the next — and the
//!   window's mean and the reference's may each be off by up to `q/2`, in opposite
//!   directions: the band is then at least `q`. (Measured on the rig, wear every 3 µm
//!   from 0 to 120 µm: a band of 95 % of the difference of two independent uniform
//!   errors, `0.776·q`, held 37 of 41 at 80 SPS, the error reaching 0.97·q; see
//!   `docs/physics.md` §10.5.)
//!
//! A wear below zero (a new cone's noise) is reported as it is, with its band.
//!
//! # Fixed point
//!
//! Steps in µm (`i32`, clamped to the stroke, 0–30 000); the window's sums in `i64`
//! (`m·Σx² − (Σx)²` ≤ 2.3·10¹¹, exact); the variance in nm² (`i64`, ×10⁶, ≤ 2.3·10¹⁴),
//! its root by [`crate::propulsion`]'s integer square root; the slope `s` in µm of
//! depth per mm of wear (`u32`); t in thousandths. The estimate is in **nm** of wear
//! (`i32`, rounded half away from zero) and its band in nm (`u32`, rounded up): the
//! same bits on the board and the host. Nothing of it is persisted: the window is
//! rebuilt at boot from the summaries in flash (each holds its docking's step,
//! verdict and whether it went into the reference, [`super::records`]), the reference's
//! step from the reference record.

use super::objects::SignatureConfig;
use crate::profile::STROKE_UM;
use zerocopy::FromZeros;

/// Steps kept per cone (the window M is at most this).
pub const WINDOW_MAX: usize = 32;

/// Student's t at 97.5 % (two-sided 95 %), thousandths, for 1..=31 degrees of freedom.
const T975_MILLI: [u16; 31] = [
    12_706, 4_303, 3_182, 2_776, 2_571, 2_447, 2_365, 2_306, 2_262, 2_228, 2_201, 2_179, 2_160,
    2_145, 2_131, 2_120, 2_110, 2_101, 2_093, 2_086, 2_080, 2_074, 2_069, 2_064, 2_060, 2_056,
    2_052, 2_048, 2_045, 2_042, 2_040,
];

/// The step depths of a cone's newest OK dockings after its reference (a ring; all
/// zero: empty).
#[derive(Clone, Copy, Debug, PartialEq, Eq, FromZeros)]
pub struct StepWindow {
    cone_id: u16,
    len: u8,
    next: u8,
    steps_um: [i32; WINDOW_MAX],
}

impl StepWindow {
    /// Empty, for `cone_id`.
    pub fn clear(&mut self, cone_id: u16) {
        *self = Self::new_zeroed();
        self.cone_id = cone_id;
    }

    /// The cone whose steps these are.
    pub fn cone_id(&self) -> u16 {
        self.cone_id
    }

    /// Steps kept.
    pub fn len(&self) -> usize {
        usize::from(self.len)
    }

    /// None kept.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }

    /// A newest step, µm (clamped to the stroke); the oldest goes when full.
    pub fn push(&mut self, step_um: i32) {
        let at = usize::from(self.next) % WINDOW_MAX;
        if let Some(slot) = self.steps_um.get_mut(at) {
            *slot = step_um.clamp(0, STROKE_UM);
        }
        self.next = ((at + 1) % WINDOW_MAX) as u8;
        if usize::from(self.len) < WINDOW_MAX {
            self.len += 1;
        }
    }

    /// The newest `m` steps (fewer if fewer are kept), newest first.
    pub fn newest(&self, m: usize) -> impl Iterator<Item = i32> + '_ {
        let n = m.min(self.len());
        (1..=n).filter_map(move |k| {
            let i = (usize::from(self.next) + WINDOW_MAX - k) % WINDOW_MAX;
            self.steps_um.get(i).copied()
        })
    }
}

/// The wear estimated from the step (see the module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StepWear {
    /// Wear since `cone replace`, nm (may be below zero within its band).
    pub wear_nm: i32,
    /// Its 95 % band, ± nm.
    pub band_nm: u32,
    /// Dockings in the window it rests on (m).
    pub dockings: u8,
    /// Dockings with a step in the reference it is taken against (N).
    pub reference_n: u8,
    /// The band is the grid's quantisation floor (the steps spread less than a random
    /// sample phase would make them).
    pub quantised: bool,
}

/// `a / b` rounded half away from zero (`b > 0`).
fn div_round(a: i64, b: i64) -> i64 {
    if a >= 0 {
        (a + b / 2) / b
    } else {
        (a - b / 2) / b
    }
}

/// The estimate from the reference's steps (`ref_step_sum_um` over `ref_step_n`
/// dockings), the window and the sample spacing `spacing_um`; `None` before the
/// reference holds a step or the window [`SignatureConfig::wear_min`] dockings, or
/// with no slope.
pub fn estimate(
    cfg: &SignatureConfig,
    ref_step_sum_um: i64,
    ref_step_n: u8,
    window: &StepWindow,
    spacing_um: u32,
) -> Option<StepWear> {
    let slope = i64::from(cfg.step_um_per_wear_mm);
    let m_max = usize::from(cfg.wear_window).clamp(2, WINDOW_MAX);
    let m = window.len().min(m_max);
    if slope == 0 || ref_step_n == 0 || m < usize::from(cfg.wear_min).max(2) {
        return None;
    }
    let (mi, n) = (m as i64, i64::from(ref_step_n));
    let (mut s, mut q) = (0i64, 0i64);
    for x in window.newest(m) {
        let x = i64::from(x);
        s += x;
        q += x * x;
    }
    // The reference's sum, within the stroke (a record is checked, but never trusted
    // beyond it).
    let r = ref_step_sum_um.clamp(0, n * i64::from(STROKE_UM));
    // x̄ − r̄ in nm of depth, then nm of wear (s: µm of depth per mm of wear).
    let d_nm = div_round((s * n - r * mi) * 1_000, mi * n);
    let wear_nm = div_round(d_nm * 1_000, slope);
    // The window's sample variance, nm².
    let var_nm2 = (mi * q - s * s).max(0) * 1_000_000 / (mi * (mi - 1));
    let t = i64::from(
        T975_MILLI
            .get(m - 2)
            .or(T975_MILLI.last())
            .copied()
            .unwrap_or(1_960),
    );
    let root = crate::propulsion::isqrt((var_nm2 * (mi + n) / (mi * n)) as u64) as i64;
    let stat_nm = root * t / 1_000;
    let q_nm = i64::from(spacing_um.min(STROKE_UM as u32)) * 1_000;
    // sd < q/2: the quantisation is not dithered; its floor, one spacing.
    let quantised = 4 * var_nm2 < q_nm * q_nm && q_nm > stat_nm;
    let band_depth_nm = if quantised { q_nm } else { stat_nm };
    let band_nm = (band_depth_nm * 1_000 + slope - 1) / slope;
    Some(StepWear {
        wear_nm: wear_nm.clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32,
        band_nm: u32::try_from(band_nm).unwrap_or(u32::MAX),
        dockings: m as u8,
        reference_n: ref_step_n,
        quantised,
    })
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;

    fn window(steps: &[i32]) -> StepWindow {
        let mut w = StepWindow::new_zeroed();
        w.clear(1);
        for &s in steps {
            w.push(s);
        }
        w
    }

    #[test]
    fn the_slope_is_the_geometrys() {
        // (v0 / v_model)·cot θ0 = 0.3 · cot 2.84°, in µm a mm.
        let th = 2.84f64.to_radians();
        let want = 0.3 * th.cos() / th.sin() * 1000.0;
        assert_eq!(
            SignatureConfig::DEFAULT.step_um_per_wear_mm,
            want.round() as u32
        );
        assert_eq!(crate::profile::STEP_UM_PER_WEAR_MM, 6_047);
    }

    #[test]
    fn the_estimate_is_the_step_move_over_the_slope() {
        let c = SignatureConfig::DEFAULT;
        // Reference: 20 dockings at 14 934 µm; now 20 dockings alternating ±30 µm
        // around 14 934 + 604.7 (100 µm of wear).
        let steps: std::vec::Vec<i32> = (0..20)
            .map(|k| 15_539 + if k % 2 == 0 { 30 } else { -30 } - (k % 2))
            .collect();
        let w = window(&steps);
        let e = estimate(&c, 14_934 * 20, 20, &w, 120).unwrap();
        // Mean 15 538.5: (15 538.5 − 14 934)/6.047 = 99.966 µm.
        assert_eq!(e.wear_nm, 99_967);
        assert_eq!((e.dockings, e.reference_n), (20, 20));
        // sd of ±30.5 (alternating, n = 20): 31.29; the statistics' band
        // 2.093·31.29·√(2/20)/6.047 = 3.4 µm; but 31.3 < 120/2: at 10 SPS the floor,
        // one spacing, 120 / 6.047 = 19.845 µm.
        assert!(e.quantised);
        assert_eq!(e.band_nm, 19_845);
        // At 80 SPS (15 µm) the statistics dominate.
        let e = estimate(&c, 14_934 * 20, 20, &w, 15).unwrap();
        assert!(!e.quantised);
        let sd = (20.0f64 * 30.5 * 30.5 / 19.0).sqrt();
        let want = 2.093 * sd * (0.1f64).sqrt() / 6.047 * 1000.0;
        assert!(
            (f64::from(e.band_nm) - want).abs() < 2.0,
            "{} vs {want}",
            e.band_nm
        );
        // A window shallower than the reference: a negative estimate, as it is.
        let w = window(&[14_900; 10]);
        let e = estimate(&c, 14_934 * 20, 20, &w, 15).unwrap();
        assert_eq!(e.wear_nm, -5_623);
        // No spread at all: the grid's floor (15 µm / 6.047).
        assert!(e.quantised);
        assert_eq!(e.band_nm, 2_481);
    }

    #[test]
    fn no_estimate_before_the_reference_and_enough_dockings() {
        let c = SignatureConfig::DEFAULT;
        let four = window(&[15_000, 15_010, 14_990, 15_005]);
        assert_eq!(estimate(&c, 14_934 * 20, 20, &four, 15), None);
        let mut five = four;
        five.push(15_002);
        assert!(estimate(&c, 14_934 * 20, 20, &five, 15).is_some());
        // No reference step, no slope.
        assert_eq!(estimate(&c, 0, 0, &five, 15), None);
        let flat = SignatureConfig {
            step_um_per_wear_mm: 0,
            ..c
        };
        assert_eq!(estimate(&flat, 14_934 * 20, 20, &five, 15), None);
    }

    #[test]
    fn the_band_shrinks_as_the_window_fills() {
        let c = SignatureConfig::DEFAULT;
        // A spread of steps (sd ≈ 47 µm, as at 10 SPS) around 100 µm of wear.
        let mut rng = 0x1234_5678u32;
        let mut w = StepWindow::new_zeroed();
        w.clear(1);
        let mut bands = std::vec::Vec::new();
        for _ in 0..20 {
            rng = rng.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let u = (rng >> 8) as i32 % 161 - 80;
            w.push(15_539 + u);
            if let Some(e) = estimate(&c, 14_934 * 20, 20, &w, 15) {
                bands.push(e.band_nm);
            }
        }
        assert_eq!(bands.len(), 16);
        assert!(
            bands.last().unwrap() * 3 < bands[0] * 2,
            "5 dockings: ±{} nm, 20: ±{} nm",
            bands[0],
            bands.last().unwrap()
        );
        // And with M: the same steps, a window of 10 against one of 20.
        let m10 = SignatureConfig {
            wear_window: 10,
            ..c
        };
        let (a, b) = (
            estimate(&m10, 14_934 * 20, 20, &w, 15).unwrap(),
            estimate(&c, 14_934 * 20, 20, &w, 15).unwrap(),
        );
        assert_eq!((a.dockings, b.dockings), (10, 20));
        assert!(b.band_nm < a.band_nm, "{a:?} {b:?}");
    }

    #[test]
    fn the_window_keeps_the_newest_and_clamps_to_the_stroke() {
        let mut w = StepWindow::new_zeroed();
        w.clear(3);
        for k in 0..40 {
            w.push(k);
        }
        assert_eq!(w.len(), WINDOW_MAX);
        let newest: std::vec::Vec<i32> = w.newest(3).collect();
        assert_eq!(newest, [39, 38, 37]);
        w.push(i32::MAX);
        w.push(-5);
        let newest: std::vec::Vec<i32> = w.newest(2).collect();
        assert_eq!(newest, [0, STROKE_UM]);
        // Corrupt sums and extreme steps neither panic nor overflow.
        let c = SignatureConfig::DEFAULT;
        assert!(estimate(&c, i64::MAX, 255, &w, u32::MAX).is_some());
        assert!(estimate(&c, i64::MIN, 1, &w, 0).is_some());
    }
}
