//! The capture: each sample of a stroke into its bin of the position grid
//! ([`super::grid`]) — the bin's peak and mean force and its sample count — after a
//! median-of-3 filter that takes out single-sample spikes.
//!
//! # Where it runs
//!
//! Not in the control step. The board's service task (`src/board.rs`, after each
//! control step, at the control task's priority) hands it the safety kernel's newest
//! sample ([`crate::safety::SafetyKernel::last_sample_us`] and its code, which the
//! sampler stores anyway) with the position the control step counted for it, and the
//! stroke the sequencer is in. Nothing was added to the sampler or to the control step:
//! their instructions, the stop latency and the E-STOP's reaction do not change
//! (`docs/physics.md` §10.4, "Its cost on the Cortex-M4").
//!
//! # Fixed point
//!
//! Forces are kept in **decinewtons** (`_dn`, 0.1 N, `i16`: ±3 276.7 N; a sample beyond
//! saturates), positions in µm. A bin's mean is exact: it is kept as
//! `sum = mean_dn · count + rem` with `0 ≤ rem < count`, so no sum can overflow and the
//! same samples give the same bits on every target; it is reported rounded half up.
//! A bin counts up to 255 samples (a stroke at v0 puts 2 in a bin at 10 SPS, 16 at
//! 80 SPS); more leave its mean and count as they are and still raise its peak.
//!
//! # The filter
//!
//! The value a sample enters its bin with is the median of itself and its two
//! neighbours in time (the one before and the one after, whatever stroke they belong
//! to: the filter runs on every sample, so the first and last sample of a stroke are
//! filtered too). A single-sample spike (the HX711's, or the overload guard's
//! "implausible jump") never reaches a bin; a step (the 3→4 force jump) passes
//! unchanged, at its place. A sample therefore enters its bin when the next one
//! arrives: one sample period later.

use zerocopy::FromZeros;

use super::grid::{bin_of, BINS};
use super::Stroke;

/// A sample moved by more than this by the filter counts as a spike, dN (20 N).
pub const SPIKE_DN: i32 = 200;

/// Force in mN to dN, rounded half away from zero, saturated to `i16`.
pub const fn mn_to_dn(mn: i32) -> i16 {
    let mn = mn as i64;
    let dn = if mn >= 0 {
        (mn + 50) / 100
    } else {
        (mn - 50) / 100
    };
    if dn > i16::MAX as i64 {
        i16::MAX
    } else if dn < i16::MIN as i64 {
        i16::MIN
    } else {
        dn as i16
    }
}

/// One bin while a stroke fills it (6 bytes).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, FromZeros)]
pub struct Bin {
    /// ⌊sum / count⌋ of the samples' forces, dN.
    mean_dn: i16,
    /// Highest sample, dN (meaningless while `count` is 0).
    peak_dn: i16,
    /// Samples, saturating at 255.
    count: u8,
    /// `sum − mean_dn · count`, `0..count`.
    rem: u8,
}

impl Bin {
    /// Add a sample of `f_dn`.
    fn add(&mut self, f_dn: i16) {
        if self.count == 0 || f_dn > self.peak_dn {
            self.peak_dn = f_dn;
        }
        if self.count == u8::MAX {
            return;
        }
        let c = i32::from(self.count);
        let total = i32::from(self.mean_dn) * c + i32::from(self.rem) + i32::from(f_dn);
        let c1 = c + 1;
        // |total| ≤ 256 · 32 768: no overflow; the quotient is within i16 (a mean of
        // i16 values), the remainder within 0..c1 ≤ 255.
        self.mean_dn = total.div_euclid(c1) as i16;
        self.rem = total.rem_euclid(c1) as u8;
        self.count += 1;
    }

    /// The mean, rounded half up, dN; `None` for an empty bin.
    pub fn mean_dn(&self) -> Option<i16> {
        (self.count > 0).then(|| {
            let up = 2 * u16::from(self.rem) >= u16::from(self.count);
            self.mean_dn.saturating_add(i16::from(up))
        })
    }

    /// The highest sample, dN; `None` for an empty bin.
    pub fn peak_dn(&self) -> Option<i16> {
        (self.count > 0).then_some(self.peak_dn)
    }

    /// Samples in the bin (saturating at 255).
    pub fn count(&self) -> u8 {
        self.count
    }
}

/// One stroke's curve as it is captured: its bins and what the filter saw.
#[derive(Clone, Debug, PartialEq, Eq, FromZeros)]
pub struct StrokeBins {
    bins: [Bin; BINS],
    /// Samples taken in the stroke (in a bin or not), saturating.
    pub samples: u16,
    /// Samples the filter moved by more than [`SPIKE_DN`], saturating.
    pub spikes: u16,
    /// The stroke has ended (the next sample was of another stroke or of none).
    pub ended: bool,
}

impl StrokeBins {
    /// No samples.
    pub const EMPTY: Self = Self {
        bins: [Bin {
            mean_dn: 0,
            peak_dn: 0,
            count: 0,
            rem: 0,
        }; BINS],
        samples: 0,
        spikes: 0,
        ended: false,
    };

    /// Bin `i`; an empty one past the grid.
    pub fn bin(&self, i: usize) -> Bin {
        self.bins.get(i).copied().unwrap_or_default()
    }

    /// Whether it has any sample.
    pub fn is_empty(&self) -> bool {
        self.samples == 0
    }

    /// It reached both ends of the grid (its first and last bin have samples) and
    /// ended: a whole stroke, which the evaluation judges. A stroke cut short (a fault,
    /// an undock during the insertion) is not judged.
    pub fn complete(&self) -> bool {
        self.ended && self.bin(0).count() > 0 && self.bin(BINS - 1).count() > 0
    }

    /// Add a (filtered) sample at `depth_um`.
    fn add(&mut self, depth_um: i32, f_dn: i16, spike: bool) {
        self.samples = self.samples.saturating_add(1);
        if spike {
            self.spikes = self.spikes.saturating_add(1);
        }
        if let Some(b) = bin_of(depth_um).and_then(|i| self.bins.get_mut(i)) {
            b.add(f_dn);
        }
    }
}

/// A sample waiting for the next one (the filter's centre).
#[derive(Clone, Copy, Debug, PartialEq, Eq, FromZeros)]
struct Pending {
    depth_um: i32,
    f_dn: i16,
    /// Its stroke: [`stroke_code`].
    stroke: u8,
}

/// A stroke as a byte (0: none), so that all-zero memory is a valid, empty capture.
const fn stroke_code(s: Option<Stroke>) -> u8 {
    match s {
        None => 0,
        Some(Stroke::Insertion) => 1,
        Some(Stroke::Extraction) => 2,
    }
}

/// [`stroke_code`]'s inverse.
const fn stroke_of(code: u8) -> Option<Stroke> {
    match code {
        1 => Some(Stroke::Insertion),
        2 => Some(Stroke::Extraction),
        _ => None,
    }
}

/// The capture of both strokes of the newest docking ([`Stroke::Insertion`],
/// [`Stroke::Extraction`]): 2 × 128 bins of 6 bytes. All-zero memory is an empty
/// capture (`FromZeros`: the board zeroes its buffers in place, never copies one).
#[derive(Clone, Debug, PartialEq, Eq, FromZeros)]
pub struct Capture {
    strokes: [StrokeBins; 2],
    /// The force of the sample before `pending`, dN (if `has_before`).
    before_dn: i16,
    has_before: bool,
    pending: Pending,
    has_pending: bool,
}

impl Default for Capture {
    fn default() -> Self {
        Self::new()
    }
}

/// What a sample did to the capture.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Fed {
    /// This stroke ended with the sample before (its last sample is in its bins).
    pub ended: Option<Stroke>,
    /// This stroke began with this sample (its bins were emptied).
    pub began: Option<Stroke>,
}

impl Capture {
    /// Nothing captured.
    pub const fn new() -> Self {
        Self {
            strokes: [StrokeBins::EMPTY, StrokeBins::EMPTY],
            before_dn: 0,
            has_before: false,
            pending: Pending {
                depth_um: 0,
                f_dn: 0,
                stroke: 0,
            },
            has_pending: false,
        }
    }

    /// The newest capture of `stroke` (a stroke in progress included).
    pub fn stroke(&self, stroke: Stroke) -> &StrokeBins {
        match stroke {
            Stroke::Insertion => &self.strokes[0],
            Stroke::Extraction => &self.strokes[1],
        }
    }

    fn stroke_mut(&mut self, stroke: Stroke) -> &mut StrokeBins {
        match stroke {
            Stroke::Insertion => &mut self.strokes[0],
            Stroke::Extraction => &mut self.strokes[1],
        }
    }

    /// A sample of `force_mn` at insertion depth `depth_um`, taken while the sequencer
    /// was in `stroke` (`None`: in no stroke). The sample before it enters its stroke's
    /// bins now, filtered with this one.
    pub fn sample(&mut self, depth_um: i32, force_mn: i32, stroke: Option<Stroke>) -> Fed {
        let f_dn = mn_to_dn(force_mn);
        let mut fed = Fed::default();
        let p = self.pending;
        if self.has_pending {
            let before = if self.has_before {
                self.before_dn
            } else {
                p.f_dn
            };
            let m = median3(before, p.f_dn, f_dn);
            if let Some(s) = stroke_of(p.stroke) {
                let spike = (i32::from(p.f_dn) - i32::from(m)).abs() > SPIKE_DN;
                self.stroke_mut(s).add(p.depth_um, m, spike);
                if stroke != Some(s) {
                    self.stroke_mut(s).ended = true;
                    fed.ended = Some(s);
                }
            }
            self.before_dn = p.f_dn;
            self.has_before = true;
        }
        if let Some(s) = stroke {
            if !self.has_pending || stroke_of(p.stroke) != Some(s) {
                // In place (no 768-byte temporary).
                self.stroke_mut(s).zero();
                fed.began = Some(s);
            }
        }
        self.pending = Pending {
            depth_um,
            f_dn,
            stroke: stroke_code(stroke),
        };
        self.has_pending = true;
        fed
    }

    /// Forget the filter's history (samples stopped: a fault, the sensor silent); a
    /// stroke in progress stays as it is, not ended.
    pub fn break_chain(&mut self) {
        self.has_before = false;
        self.has_pending = false;
    }
}

/// The median of three.
const fn median3(a: i16, b: i16, c: i16) -> i16 {
    let (lo, hi) = if a < b { (a, b) } else { (b, a) };
    if c < lo {
        lo
    } else if c > hi {
        hi
    } else {
        c
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::signature::grid::lo_um;

    #[test]
    fn a_bin_keeps_the_exact_mean_and_the_peak() {
        let mut b = Bin::default();
        assert_eq!(b.mean_dn(), None);
        for f in [1000, 1001, 1001] {
            b.add(f);
        }
        // 3002 / 3 = 1000.67 → 1001
        assert_eq!(b.mean_dn(), Some(1001));
        assert_eq!(b.peak_dn(), Some(1001));
        let mut n = Bin::default();
        for f in [-5, -6] {
            n.add(f);
        }
        // −5.5 rounds half up to −5
        assert_eq!(n.mean_dn(), Some(-5));
        assert_eq!(n.peak_dn(), Some(-5));
        // Saturated count: the mean stays, the peak still rises.
        let mut s = Bin::default();
        for _ in 0..300 {
            s.add(10);
        }
        s.add(99);
        assert_eq!(
            (s.count(), s.mean_dn(), s.peak_dn()),
            (255, Some(10), Some(99))
        );
    }

    #[test]
    fn mn_to_dn_rounds_and_saturates() {
        assert_eq!(mn_to_dn(112_640), 1126);
        assert_eq!(mn_to_dn(112_650), 1127);
        assert_eq!(mn_to_dn(-149), -1);
        assert_eq!(mn_to_dn(-150), -2);
        assert_eq!(mn_to_dn(i32::MAX), i16::MAX);
        assert_eq!(mn_to_dn(i32::MIN), i16::MIN);
    }

    #[test]
    fn a_single_sample_spike_never_reaches_a_bin_and_a_step_passes_at_its_place() {
        let mut c = Capture::new();
        let ins = Some(Stroke::Insertion);
        // Before the stroke, then 40 samples 100 µm apart: 100 N, a 350 N spike at
        // sample 5 and at the stroke's first sample, a step to 200 N at sample 20.
        c.sample(-100, 100_000, None);
        for k in 0..40 {
            let mut f = if k >= 20 { 200_000 } else { 100_000 };
            if k == 5 || k == 0 {
                f += 350_000;
            }
            c.sample(k * 100, f, ins);
        }
        let fed = c.sample(4_000, 200_000, None);
        assert_eq!(fed.ended, Some(Stroke::Insertion));
        let s = c.stroke(Stroke::Insertion);
        assert!(s.ended);
        assert_eq!(s.samples, 40);
        assert_eq!(s.spikes, 2);
        for i in 0..BINS {
            let b = s.bin(i);
            if b.count() == 0 {
                continue;
            }
            let want = if lo_um(i) >= 2_000 {
                2000
            } else if lo_um(i + 1) <= 2_000 {
                1000
            } else {
                continue; // the bin the step is in
            };
            assert_eq!(b.peak_dn(), Some(want), "bin {i}");
            assert_eq!(b.mean_dn(), Some(want), "bin {i}");
        }
    }

    #[test]
    fn a_new_stroke_starts_empty_and_the_other_keeps_its_curve() {
        let mut c = Capture::new();
        let fed = c.sample(0, 1, Some(Stroke::Insertion));
        assert_eq!(fed.began, Some(Stroke::Insertion));
        c.sample(30_000, 1, Some(Stroke::Insertion));
        let fed = c.sample(30_000, 1, None);
        assert_eq!(fed.ended, Some(Stroke::Insertion));
        assert!(c.stroke(Stroke::Insertion).complete());
        let fed = c.sample(30_000, 1, Some(Stroke::Extraction));
        assert_eq!(fed.began, Some(Stroke::Extraction));
        assert!(c.stroke(Stroke::Insertion).complete());
        assert!(!c.stroke(Stroke::Extraction).ended);
        let fed = c.sample(0, 1, Some(Stroke::Insertion));
        assert_eq!(fed.began, Some(Stroke::Insertion));
        assert_eq!(fed.ended, Some(Stroke::Extraction));
        assert!(c.stroke(Stroke::Insertion).is_empty());
    }
}
