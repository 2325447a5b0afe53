//! What a stroke's curve measures: the figures the evaluation objects judge and the
//! drift and the wear study follow ([`InsertionFigures`], [`ExtractionFigures`]).
//!
//! All in integers from the bins' means (dN) and the grid (µm): the same curve gives the
//! same figures on the board and on the host. An empty bin (none at v0: a sample every
//! 15 µm at 80 SPS, every 120 µm at 10 SPS, bins 234 µm wide) counts with the mean of
//! the bin before it.

use super::capture::StrokeBins;
use super::grid::{lo_um, width_um, BINS};
use crate::profile::STROKE_UM;

/// The insertion's figures.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct InsertionFigures {
    /// Where the curve first reached the entry threshold, µm of depth (the first depth
    /// of that bin); `None`: never.
    pub entry_um: Option<i32>,
    /// Insertion work ∫F·dx over the stroke, mN·mm (µJ).
    pub work_mnmm: u32,
    /// Phase-4 plateau: the mean force over phase 4 (its bins, the position tolerance
    /// off both ends), mN.
    pub plateau_mn: i32,
    /// Where the force steps from single- to two-point contact (3→4), µm of depth,
    /// interpolated inside the bin the step is in; `None`: no step found.
    pub step_um: Option<i32>,
    /// Force at the end of the stroke (the mated position's bin), mN.
    pub end_mn: i32,
}

/// The extraction's figures.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ExtractionFigures {
    /// The highest force of the stroke (a bin's peak), mN.
    pub peak_mn: i32,
    /// Where it was (that bin's middle), µm of depth.
    pub peak_um: i32,
    /// Extraction work ∫F·dx, mN·mm.
    pub work_mnmm: u32,
}

/// The stroke's bin means (dN), empty bins holding the value before them (leading
/// empty bins: the first value found; an empty stroke: zeros).
pub fn filled_means(s: &StrokeBins) -> [i16; BINS] {
    let first = (0..BINS).find_map(|i| s.bin(i).mean_dn()).unwrap_or(0);
    let mut out = [0i16; BINS];
    let mut last = first;
    for (i, o) in out.iter_mut().enumerate() {
        if let Some(m) = s.bin(i).mean_dn() {
            last = m;
        }
        *o = last;
    }
    out
}

/// ∫F·dx over the grid, mN·mm, from bin means in dN.
pub fn work_mnmm(means: &[i16; BINS]) -> u32 {
    // dN · µm / 10 = mN · mm.
    let sum: i64 = means
        .iter()
        .enumerate()
        .map(|(i, &m)| i64::from(m) * i64::from(width_um(i)))
        .sum();
    u32::try_from((sum / 10).max(0)).unwrap_or(u32::MAX)
}

/// The bins whose whole width lies within `[from_um, to_um]`.
pub fn bins_within(from_um: i32, to_um: i32) -> core::ops::Range<usize> {
    let first = (0..BINS).find(|&i| lo_um(i) >= from_um).unwrap_or(BINS);
    let end = (first..BINS)
        .find(|&i| lo_um(i + 1) > to_um)
        .unwrap_or(BINS);
    first..end
}

/// The mean of `means` over `bins`, mN (0 for no bins).
pub fn mean_mn(means: &[i16; BINS], bins: core::ops::Range<usize>) -> i32 {
    let n = bins.len() as i64;
    if n == 0 {
        return 0;
    }
    let sum: i64 = means
        .get(bins)
        .map_or(0, |b| b.iter().map(|&m| i64::from(m)).sum());
    // dN → mN, rounded half away from zero.
    let x = sum * 100;
    let r = if x >= 0 {
        (x + n / 2) / n
    } else {
        (x - n / 2) / n
    };
    i32::try_from(r).unwrap_or(if r > 0 { i32::MAX } else { i32::MIN })
}

/// Where the insertion's 3→4 step is, µm: the first bin `j` at or after
/// `search_from_um` whose mean reaches `threshold_dn`; the step lies in bin `j − 1` or
/// `j` (a bin part of whose samples are past it has a mean between the levels on either
/// side). With `L` the mean of bin `j − 2` (before the step) and `H` that of bin `j + 1`
/// (after it), bins `j − 1` and `j` hold `e = (m[j−1] − L + m[j] − L)/(H − L)` bin widths
/// past the step, which is placed that far before the end of bin `j`. `None` if no bin
/// reaches the threshold.
pub fn step_um(means: &[i16; BINS], search_from_um: i32, threshold_dn: i16) -> Option<i32> {
    let start = bins_within(search_from_um, STROKE_UM).start;
    let j = (start..BINS).find(|&i| means.get(i).is_some_and(|&m| m >= threshold_dn))?;
    let at = |i: usize| i64::from(means.get(i).copied().unwrap_or(0));
    if j < 2 || j + 1 >= BINS {
        return Some(lo_um(j));
    }
    let (lo, hi) = (at(j - 2), at(j + 1));
    if hi <= lo {
        return Some(lo_um(j));
    }
    // Excess in bin widths × (hi − lo), each bin's share clamped to one width.
    let part = |m: i64| (m - lo).clamp(0, hi - lo);
    let (w1, w0) = (i64::from(width_um(j - 1)), i64::from(width_um(j)));
    let past = part(at(j - 1)) * w1 + part(at(j)) * w0;
    let step = i64::from(lo_um(j + 1)) - past / (hi - lo);
    i32::try_from(step).ok()
}

/// The insertion's figures from its bins: `entry_dn` the entry threshold, `plateau` the
/// phase-4 bins, `step_from_um` and `step_dn` where and at what force the 3→4 step is
/// searched.
pub fn insertion(
    s: &StrokeBins,
    entry_dn: i16,
    plateau: core::ops::Range<usize>,
    step_from_um: i32,
    step_dn: i16,
) -> InsertionFigures {
    let means = filled_means(s);
    let entry_um = (0..BINS)
        .find(|&i| s.bin(i).mean_dn().is_some_and(|m| m >= entry_dn))
        .map(lo_um);
    let end = (0..BINS)
        .rev()
        .find_map(|i| s.bin(i).mean_dn())
        .unwrap_or(0);
    InsertionFigures {
        entry_um,
        work_mnmm: work_mnmm(&means),
        plateau_mn: mean_mn(&means, plateau),
        step_um: step_um(&means, step_from_um, step_dn),
        end_mn: i32::from(end) * 100,
    }
}

/// The extraction's figures from its bins.
pub fn extraction(s: &StrokeBins) -> ExtractionFigures {
    let means = filled_means(s);
    let mut peak: Option<(i16, usize)> = None;
    for i in 0..BINS {
        if let Some(p) = s.bin(i).peak_dn() {
            if peak.is_none_or(|(q, _)| p > q) {
                peak = Some((p, i));
            }
        }
    }
    let (p, i) = peak.unwrap_or((0, 0));
    ExtractionFigures {
        peak_mn: i32::from(p) * 100,
        peak_um: super::grid::mid_um(i),
        work_mnmm: work_mnmm(&means),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signature::capture::Capture;
    use crate::signature::Stroke;

    /// A stroke sampled every `step_um` µm from `f(depth)` N.
    fn stroke(step_um: i32, f: impl Fn(i32) -> f64) -> StrokeBins {
        let mut c = Capture::new();
        c.sample(-step_um, (f(0) * 1000.0) as i32, None);
        let mut d = 0;
        while d <= STROKE_UM {
            c.sample(d, (f(d) * 1000.0).round() as i32, Some(Stroke::Insertion));
            d += step_um;
        }
        c.sample(STROKE_UM, (f(STROKE_UM) * 1000.0) as i32, None);
        c.stroke(Stroke::Insertion).clone()
    }

    #[test]
    fn the_work_of_a_constant_force_is_force_times_stroke() {
        let s = stroke(15, |_| 100.0);
        let f = insertion(&s, 500, bins_within(15_434, 29_500), 8_700, 1567);
        // 100 N × 30 mm = 3 000 N·mm.
        assert_eq!(f.work_mnmm, 3_000_000);
        assert_eq!(f.plateau_mn, 100_000);
        assert_eq!(f.entry_um, Some(0));
        assert_eq!(f.end_mn, 100_000);
        assert_eq!(f.step_um, None);
    }

    #[test]
    fn the_step_is_found_inside_its_bin_to_the_sample_spacing() {
        for (spacing, tol) in [(15, 16), (120, 121)] {
            for step in [14_934, 15_100, 16_000, 17_017] {
                let s = stroke(spacing, |d| if d < step { 107.0 } else { 206.0 });
                let got = step_um(&filled_means(&s), 8_700, 1567).unwrap();
                assert!(
                    (got - step).abs() <= tol,
                    "spacing {spacing}: step at {step}, found {got}"
                );
            }
        }
    }

    #[test]
    fn a_late_entry_is_seen_where_the_force_rises() {
        let s = stroke(15, |d| if d < 2_000 { 0.5 } else { 112.0 });
        let f = insertion(&s, 560, bins_within(15_434, 29_500), 8_700, 1567);
        let e = f.entry_um.unwrap();
        assert!((1_800..=2_110).contains(&e), "{e}");
        let none = insertion(&stroke(15, |_| 1.0), 560, 0..0, 8_700, 1567);
        assert_eq!(none.entry_um, None);
    }

    #[test]
    fn the_extraction_peak_and_its_place() {
        let s = stroke(15, |d| {
            if (14_934..15_500).contains(&d) {
                206.0
            } else {
                120.0
            }
        });
        let f = extraction(&s);
        assert_eq!(f.peak_mn, 206_000);
        assert!((14_700..15_500).contains(&f.peak_um), "{}", f.peak_um);
    }
}
