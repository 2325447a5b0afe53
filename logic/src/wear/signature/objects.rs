//! The evaluation objects a stroke is judged by, and the judgement: OK, or NOK with the
//! first object it failed and the figure that failed it.
//!
//! The objects are placed on the **design's force profile** ([`NominalCurve`]: Eq. 7 by
//! default, computed at build time; another machine's from its plant at commissioning:
//! `hil-sim commission --model plant …` writes its curve, [`NominalCurve::from_fn`] on the
//! host, into the tuning file the board is built with, whose `apply` sets
//! [`SignatureConfig::nominal`] as it sets the guard's profile), as a press-fit monitor
//! places its windows and envelopes on a master curve:
//!
//! ```text
//!  force                     plateau (phase-4 mean ± plateau_pct)
//!    ^            band 3   ┌─────────────────────────────────────┐
//!    |  band 1  band 2  ┌──┤▓ step                                 │  end
//!    |┌───────┬───────┬─┘  │ ▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓▓  band 4       │ ┌──┐
//!    |│▓▓▓▓▓▓▓│▓▓▓▓▓▓▓│▓▓▓▓▓▓▓▓▓▓   (each bin inside its band)   ▓▓▓▓│ │▓▓│ at MATED
//!    |└───────┴───────┴──────┤                                    ▓▓▓│ └──┘
//!    |entry ┐                └─────────────────────────────────────┘
//!    |window│                                                          depth
//!    +──────┴──────────────────────────────────────────────────────────────>
//!     0    1 mm     4.5      8.7       14.934                          30 mm
//! ```
//!
//! **Insertion**, judged in this order (the first failed is the one reported):
//! 1. `entry` — where the rod meets the cone: the first bin whose mean reaches
//!    `entry_pct` of the phase-1 nominal force lies within `entry_max_um` of the
//!    engagement point (a late entry: lateral misalignment);
//! 2. `band1`, `band2`, `band3` — one band per contact phase: every bin of the phase
//!    inside `[min·(1 − rel) − abs, max·(1 + rel) + abs]`, `min`/`max` the nominal force
//!    over the bin ± [`POS_TOL_UM`] (so a bin beside a phase boundary, whose position is
//!    known to that much, accepts both sides of the jump; and within it of the
//!    engagement point, the force before contact: the axis is zeroed on its home switch
//!    to within one control period of its creep, up to 55 µm at 10 SPS);
//! 3. `plateau` — the phase-4 plateau: the mean force over phase 4 within
//!    `plateau_pct` of the nominal's (a dry guide, debris in the bore: the whole
//!    plateau moves);
//! 4. `band4` — phase 4's band, as the others (but its last bin, the end object's);
//! 5. `end` — the force at the end of the stroke (MATED) within `end_pct` + `end_abs`
//!    of the nominal.
//!
//! **Extraction** (traversed from the mated position out): `ext_band4` … `ext_band1`,
//! the bands of the insertion's phases, then `ext_peak` — the stroke's highest force
//! within `peak_pct` + `peak_abs` of the nominal peak and within `peak_pos_um` of its
//! place (the 3→4 step). A catch on the way out breaks its phase's band.
//!
//! A NOK does not stop the machine (only the overload guard does): it is for people and
//! the PLC. Object codes (persisted, and the Modbus map's) never change meaning.

use super::capture::StrokeBins;
use super::figures::{self, bins_within, ExtractionFigures, InsertionFigures};
use super::grid::{lo_um, mid_um, BINS};
use crate::profile::{BOUNDARY_UM, STROKE_UM};

/// A phase boundary's position is trusted to this much, µm (as the overload guard's
/// envelope: `guard::ENVELOPE_WINDOW_UM`).
pub const POS_TOL_UM: i32 = 500;

/// An evaluation object. The codes are persisted and on Modbus: never reused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum Object {
    /// The entry window (insertion).
    Entry = 1,
    /// Phase 1's band (insertion).
    Band1 = 2,
    /// Phase 2's band.
    Band2 = 3,
    /// Phase 3's band.
    Band3 = 4,
    /// The phase-4 plateau.
    Plateau = 5,
    /// Phase 4's band.
    Band4 = 6,
    /// The end force at MATED.
    End = 7,
    /// Phase 4's band on the way out.
    ExtBand4 = 8,
    /// Phase 3's band on the way out.
    ExtBand3 = 9,
    /// Phase 2's band on the way out.
    ExtBand2 = 10,
    /// Phase 1's band on the way out.
    ExtBand1 = 11,
    /// The extraction's peak.
    ExtPeak = 12,
}

impl Object {
    /// Every object, in code order.
    pub const ALL: [Self; 12] = [
        Self::Entry,
        Self::Band1,
        Self::Band2,
        Self::Band3,
        Self::Plateau,
        Self::Band4,
        Self::End,
        Self::ExtBand4,
        Self::ExtBand3,
        Self::ExtBand2,
        Self::ExtBand1,
        Self::ExtPeak,
    ];

    /// The persisted code.
    pub const fn code(self) -> u8 {
        self as u8
    }

    /// The object of `code`.
    pub fn from_code(code: u8) -> Option<Self> {
        Self::ALL.iter().copied().find(|o| o.code() == code)
    }

    /// Its name, as the console, the log and the scenes say it.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Entry => "entry",
            Self::Band1 => "band1",
            Self::Band2 => "band2",
            Self::Band3 => "band3",
            Self::Plateau => "plateau",
            Self::Band4 => "band4",
            Self::End => "end",
            Self::ExtBand4 => "ext_band4",
            Self::ExtBand3 => "ext_band3",
            Self::ExtBand2 => "ext_band2",
            Self::ExtBand1 => "ext_band1",
            Self::ExtPeak => "ext_peak",
        }
    }

    /// The band of contact phase `p` (1–4) on the insertion or the extraction.
    const fn band(p: u8, extraction: bool) -> Self {
        match (p, extraction) {
            (1, false) => Self::Band1,
            (2, false) => Self::Band2,
            (3, false) => Self::Band3,
            (_, false) => Self::Band4,
            (1, true) => Self::ExtBand1,
            (2, true) => Self::ExtBand2,
            (3, true) => Self::ExtBand3,
            (_, true) => Self::ExtBand4,
        }
    }
}

/// Unit of a figure.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum Unit {
    /// Force, mN.
    Mn = 0,
    /// Depth, µm.
    Um = 1,
}

impl Unit {
    /// The unit of `code`.
    pub const fn from_code(code: u8) -> Self {
        if code == 1 {
            Self::Um
        } else {
            Self::Mn
        }
    }
}

/// Why a stroke is NOK: the first object it failed, with the figure that failed it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Failure {
    /// The object.
    pub object: Object,
    /// The figure judged (the bin's mean for a band, the plateau, the end force, the
    /// peak; the entry depth or the peak's place), in `unit`; `i32::MIN`: none (the
    /// curve never entered).
    pub figure: i32,
    /// The limit it broke, in `unit`.
    pub limit: i32,
    /// `figure`'s and `limit`'s unit.
    pub unit: Unit,
    /// Where on the stroke, µm of depth.
    pub depth_um: i32,
}

/// The design's force along the stroke, on the grid: what the objects are placed on.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct NominalCurve {
    /// The nominal force averaged over each bin, dN.
    pub mean_dn: [i16; BINS],
    /// Its minimum over the bin ± [`POS_TOL_UM`], dN.
    pub min_dn: [i16; BINS],
    /// Its maximum over the bin ± [`POS_TOL_UM`], dN.
    pub max_dn: [i16; BINS],
    /// Where the contact phases change, µm of depth.
    pub boundaries_um: [i32; 3],
    /// The force halfway across the 3→4 step, dN (where the step is found).
    pub step_dn: i16,
}

/// `x` N to dN, rounded, saturated.
const fn n_to_dn(x: f64) -> i16 {
    let v = x * 10.0;
    let r = if v >= 0.0 { v + 0.5 } else { v - 0.5 };
    if r >= i16::MAX as f64 {
        i16::MAX
    } else if r <= i16::MIN as f64 {
        i16::MIN
    } else {
        r as i16
    }
}

/// Eq. 7's curve, computed by the compiler (no floating point in the image for it).
// Evaluated at build time: an index out of range fails the build (and `get_mut` is not
// usable in const context).
#[allow(clippy::indexing_slicing)]
pub static EQ7_CURVE: NominalCurve = {
    let mut c = NominalCurve {
        mean_dn: [0; BINS],
        min_dn: [0; BINS],
        max_dn: [0; BINS],
        boundaries_um: BOUNDARY_UM,
        step_dn: n_to_dn(
            (crate::guard::n3_at_depth_n(BOUNDARY_UM[2] - 1)
                + crate::guard::n3_at_depth_n(BOUNDARY_UM[2]))
                / 2.0,
        ),
    };
    let mut i = 0;
    while i < BINS {
        // The mean over the bin, every 1 µm (midpoints).
        let (lo, hi) = (lo_um(i), lo_um(i + 1));
        let mut sum = 0.0;
        let mut d = lo;
        while d < hi {
            sum += crate::guard::n3_at_depth_n(d);
            d += 1;
        }
        c.mean_dn[i] = n_to_dn(sum / (hi - lo) as f64);
        // Min and max over the bin ± the tolerance, every 10 µm and both sides of
        // each jump.
        let wlo = if lo - POS_TOL_UM < 0 {
            0
        } else {
            lo - POS_TOL_UM
        };
        let whi = if hi + POS_TOL_UM > STROKE_UM {
            STROKE_UM
        } else {
            hi + POS_TOL_UM
        };
        // Within the tolerance of the engagement point the rod may not touch yet: the
        // force before contact (0) is in the window too.
        let (mut mn, mut mx) = (if lo - POS_TOL_UM < 0 { 0.0 } else { f64::MAX }, 0.0f64);
        let mut d = wlo;
        loop {
            let f = crate::guard::n3_at_depth_n(if d > whi { whi } else { d });
            if f < mn {
                mn = f;
            }
            if f > mx {
                mx = f;
            }
            if d >= whi {
                break;
            }
            d += 10;
        }
        let mut b = 0;
        while b < 3 {
            let j = BOUNDARY_UM[b];
            if wlo <= j && j <= whi {
                let (f0, f1) = (
                    crate::guard::n3_at_depth_n(j - 1),
                    crate::guard::n3_at_depth_n(j),
                );
                if f0 < mn {
                    mn = f0;
                }
                if f1 < mn {
                    mn = f1;
                }
                if f0 > mx {
                    mx = f0;
                }
                if f1 > mx {
                    mx = f1;
                }
            }
            b += 1;
        }
        c.min_dn[i] = n_to_dn(mn);
        c.max_dn[i] = n_to_dn(mx);
        i += 1;
    }
    c
};

impl NominalCurve {
    /// From a force model (commissioning, on the host): `n3_n(depth_um)` the nominal N3
    /// at a depth (N), `boundaries_um` where the phases change (N3 may jump there).
    /// Non-finite values count as 0.
    pub fn from_fn(n3_n: impl Fn(i32) -> f64, boundaries_um: [i32; 3]) -> Self {
        let f = |d: i32| {
            let v = n3_n(d.clamp(0, STROKE_UM));
            if v.is_finite() {
                v
            } else {
                0.0
            }
        };
        let mut c = Self {
            mean_dn: [0; BINS],
            min_dn: [0; BINS],
            max_dn: [0; BINS],
            boundaries_um,
            step_dn: n_to_dn((f(boundaries_um[2] - 1) + f(boundaries_um[2])) / 2.0),
        };
        for i in 0..BINS {
            let (lo, hi) = (lo_um(i), lo_um(i + 1));
            let sum: f64 = (lo..hi).map(f).sum();
            let wlo = (lo - POS_TOL_UM).max(0);
            let whi = (hi + POS_TOL_UM).min(STROKE_UM);
            let mut pts: heapless::Vec<i32, 8> = heapless::Vec::new();
            for j in boundaries_um {
                if (wlo..=whi).contains(&j) {
                    let _ = pts.push(j - 1);
                    let _ = pts.push(j);
                }
            }
            let vals = (wlo..=whi)
                .step_by(10)
                .chain(core::iter::once(whi))
                .chain(pts)
                .map(f);
            // Within the tolerance of the engagement point the rod may not touch yet.
            let start = if lo - POS_TOL_UM < 0 { 0.0 } else { f64::MAX };
            let (mn, mx) = vals.fold((start, 0.0f64), |(a, b), v| (a.min(v), b.max(v)));
            if let (Some(m), Some(lo_), Some(hi_)) = (
                c.mean_dn.get_mut(i),
                c.min_dn.get_mut(i),
                c.max_dn.get_mut(i),
            ) {
                *m = n_to_dn(sum / f64::from(hi - lo));
                *lo_ = n_to_dn(mn);
                *hi_ = n_to_dn(mx);
            }
        }
        c
    }

    /// The contact phase (1–4) bin `i` is in, by its middle.
    pub fn phase_of(&self, i: usize) -> u8 {
        let m = mid_um(i);
        1 + self.boundaries_um.iter().filter(|&&b| m >= b).count() as u8
    }

    /// The phase-4 plateau's bins: phase 4 less the position tolerance at both ends.
    pub fn plateau_bins(&self) -> core::ops::Range<usize> {
        bins_within(self.boundaries_um[2] + POS_TOL_UM, STROKE_UM - POS_TOL_UM)
    }
}

/// The evaluation objects' settings (part of the machine configuration).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SignatureConfig {
    /// The design's curve the objects sit on.
    pub nominal: &'static NominalCurve,
    /// Bands: relative margin, % of the nominal.
    pub band_pct: u8,
    /// Bands: absolute margin, mN.
    pub band_abs_mn: i32,
    /// The entry window's force: this % of the phase-1 nominal.
    pub entry_pct: u8,
    /// The entry window's depth: the force must be reached this close to the
    /// engagement point, µm.
    pub entry_max_um: i32,
    /// The phase-4 plateau: within this % of the nominal plateau.
    pub plateau_pct: u8,
    /// The end force: relative margin, %.
    pub end_pct: u8,
    /// The end force: absolute margin, mN.
    pub end_abs_mn: i32,
    /// The extraction's peak: relative margin, %.
    pub peak_pct: u8,
    /// The extraction's peak: absolute margin, mN.
    pub peak_abs_mn: i32,
    /// The extraction's peak: its place within this of the nominal's, µm.
    pub peak_pos_um: i32,
    /// Dockings averaged into a cone's reference curve after `cone replace`.
    pub reference_n: u8,
    /// How much deeper than the design the 3→4 step may lie, µm: the bore's growth
    /// over the cone's life moves it (docs/physics.md §10.5: 6.05 µm of depth a µm of
    /// wear on Eq. 7's machine, 4.8 mm at the 0.8 mm limit). A step found within this
    /// of the design's boundary moves the objects of phases 3–4 with it (the bands from
    /// the step on, the plateau, the end force, the extraction's peak), so a worn cone
    /// is judged against its own step, not the new cone's.
    pub step_travel_um: i32,
    /// How much deeper the 3→4 step lies per mm of bore wear, µm (the wear estimate's
    /// slope, [`super::stepwear`]): Eq. 7's machine's from its geometry
    /// ([`crate::profile::STEP_UM_PER_WEAR_MM`], 6 047); another machine's from its
    /// plant at commissioning.
    pub step_um_per_wear_mm: u32,
    /// The wear estimate's window: the step depths of the cone's last this many OK
    /// dockings after its reference (M, at most [`super::stepwear::WINDOW_MAX`]).
    pub wear_window: u8,
    /// The wear estimate is offered from this many dockings in its window on.
    pub wear_min: u8,
}

impl SignatureConfig {
    /// The defaults, on Eq. 7 (why these margins: `docs/physics.md`, "The docking
    /// signature": they clear the load cell's noise and the µ spread commissioning
    /// allows, and catch the scenes' faults).
    pub const DEFAULT: Self = Self {
        nominal: &EQ7_CURVE,
        band_pct: 10,
        band_abs_mn: 8_000,
        entry_pct: 50,
        entry_max_um: 1_000,
        plateau_pct: 8,
        end_pct: 10,
        end_abs_mn: 5_000,
        peak_pct: 10,
        peak_abs_mn: 8_000,
        peak_pos_um: 1_000,
        reference_n: 20,
        step_travel_um: 5_000,
        step_um_per_wear_mm: crate::profile::STEP_UM_PER_WEAR_MM,
        wear_window: 20,
        wear_min: 5,
    };

    /// Bins the objects of phases 3–4 move by for a stroke whose 3→4 step was found
    /// at `step_um`: its depth past the design's boundary (0 if shallower, none
    /// found, or deeper than [`Self::step_travel_um`]: then the objects stay and
    /// judge it), in whole bins.
    pub fn shift_bins(&self, step_um: Option<i32>) -> usize {
        let Some(st) = step_um else {
            return 0;
        };
        let d = st - self.nominal.boundaries_um[2];
        if d <= 0 || d > self.step_travel_um {
            return 0;
        }
        ((d * BINS as i32 + STROKE_UM / 2) / STROKE_UM) as usize
    }

    /// The first bin the objects' move applies to: the first starting at or after half
    /// a tolerance before the design's step (`bins_within`'s start, without its
    /// search).
    fn moved_from(&self) -> usize {
        // ≤ 30 000 · 128: fits i32.
        let x = (self.nominal.boundaries_um[2] - POS_TOL_UM).clamp(0, STROKE_UM);
        ((x * BINS as i32 + STROKE_UM - 1) / STROKE_UM) as usize
    }

    /// The design's bin that bin `i` is judged as when the objects move by `shift`
    /// bins: from [`Self::moved_from`] on, `shift` bins back.
    fn moved(&self, i: usize, shift: usize) -> usize {
        moved_at(i, shift, self.moved_from())
    }

    /// The band of bin `i` with the objects moved by `shift` bins
    /// ([`Self::shift_bins`]): `(low, high)`, mN.
    pub fn band_moved_mn(&self, i: usize, shift: usize) -> (i32, i32) {
        self.band_mn(self.moved(i, shift))
    }

    /// The phase-4 plateau's bins with the objects moved by `shift` bins: where the
    /// stroke's plateau is taken, and the design's bins it is compared with.
    pub fn plateau_bins_moved(
        &self,
        shift: usize,
    ) -> (core::ops::Range<usize>, core::ops::Range<usize>) {
        let b = self.nominal.plateau_bins();
        let shift = shift.min(b.len().saturating_sub(1));
        (b.start + shift..b.end, b.start..b.end - shift)
    }

    /// The nominal plateau over the design's bins of [`Self::plateau_bins_moved`], mN.
    pub fn plateau_nominal_moved_mn(&self, shift: usize) -> i32 {
        figures::mean_mn(&self.nominal.mean_dn, self.plateau_bins_moved(shift).1)
    }

    /// The nominal end force with the objects moved by `shift` bins, mN: the design's
    /// force that much before the end.
    pub fn end_nominal_moved_mn(&self, shift: usize) -> i32 {
        let i = (BINS - 1).saturating_sub(shift);
        i32::from(self.nominal.mean_dn.get(i).copied().unwrap_or(0)) * 100
    }

    /// The band of bin `i`: `(low, high)`, mN.
    pub fn band_mn(&self, i: usize) -> (i32, i32) {
        let n = self.nominal;
        let lo = i32::from(n.min_dn.get(i).copied().unwrap_or(0)) * 100;
        let hi = i32::from(n.max_dn.get(i).copied().unwrap_or(0)) * 100;
        let pct = i32::from(self.band_pct);
        (
            lo - lo.abs() * pct / 100 - self.band_abs_mn,
            hi + hi.abs() * pct / 100 + self.band_abs_mn,
        )
    }

    /// The entry threshold, dN.
    pub fn entry_dn(&self) -> i16 {
        let f0 = i32::from(self.nominal.mean_dn.first().copied().unwrap_or(0));
        i16::try_from(f0 * i32::from(self.entry_pct) / 100).unwrap_or(i16::MAX)
    }

    /// The nominal phase-4 plateau, mN.
    pub fn plateau_nominal_mn(&self) -> i32 {
        figures::mean_mn(&self.nominal.mean_dn, self.nominal.plateau_bins())
    }

    /// The nominal end force, mN (the last bin's).
    pub fn end_nominal_mn(&self) -> i32 {
        i32::from(self.nominal.mean_dn.last().copied().unwrap_or(0)) * 100
    }

    /// The nominal extraction peak and its place: (mN, µm).
    pub fn peak_nominal(&self) -> (i32, i32) {
        let mut best = (i16::MIN, 0usize);
        for (i, &m) in self.nominal.max_dn.iter().enumerate() {
            // The highest bin mean, not the windowed maximum (which a bin half a
            // millimetre from the step shares).
            let mean = self.nominal.mean_dn.get(i).copied().unwrap_or(m);
            if mean > best.0 {
                best = (mean, i);
            }
        }
        // The peak of the profile is its maximum, at the step.
        let peak = self.nominal.max_dn.iter().copied().max().unwrap_or(0);
        (i32::from(peak) * 100, mid_um(best.1))
    }

    /// The insertion's figures (the plateau over the bins the objects moved to with
    /// the step: [`Self::shift_bins`]).
    pub fn insertion_figures(&self, s: &StrokeBins) -> InsertionFigures {
        let mut f = figures::insertion(
            s,
            self.entry_dn(),
            self.nominal.plateau_bins(),
            self.nominal.boundaries_um[1] + POS_TOL_UM,
            self.nominal.step_dn,
        );
        let shift = self.shift_bins(f.step_um);
        if shift > 0 {
            let bins = self.plateau_bins_moved(shift).0;
            f.plateau_mn = figures::mean_mn(&figures::filled_means(s), bins);
        }
        f
    }

    /// Judge an insertion: the first object it failed, if any (the objects of phases
    /// 3–4 moved with its step: [`Self::shift_bins`]).
    pub fn judge_insertion(&self, s: &StrokeBins, f: &InsertionFigures) -> Option<Failure> {
        let shift = self.shift_bins(f.step_um);
        match f.entry_um {
            Some(e) if e <= self.entry_max_um => {}
            other => {
                return Some(Failure {
                    object: Object::Entry,
                    figure: other.unwrap_or(i32::MIN),
                    limit: self.entry_max_um,
                    unit: Unit::Um,
                    depth_um: other.unwrap_or(0),
                })
            }
        }
        for p in 1..=3 {
            if let Some(fail) = self.bands(s, p, false, shift) {
                return Some(fail);
            }
        }
        let nom = self.plateau_nominal_moved_mn(shift);
        let tol = nom.abs() * i32::from(self.plateau_pct) / 100;
        if (f.plateau_mn - nom).abs() > tol {
            let limit = if f.plateau_mn > nom {
                nom + tol
            } else {
                nom - tol
            };
            let bins = self.plateau_bins_moved(shift).0;
            return Some(Failure {
                object: Object::Plateau,
                figure: f.plateau_mn,
                limit,
                unit: Unit::Mn,
                depth_um: (lo_um(bins.start) + lo_um(bins.end)) / 2,
            });
        }
        if let Some(fail) = self.bands(s, 4, false, shift) {
            return Some(fail);
        }
        let nom = self.end_nominal_moved_mn(shift);
        let tol = nom.abs() * i32::from(self.end_pct) / 100 + self.end_abs_mn;
        if (f.end_mn - nom).abs() > tol {
            return Some(Failure {
                object: Object::End,
                figure: f.end_mn,
                limit: if f.end_mn > nom { nom + tol } else { nom - tol },
                unit: Unit::Mn,
                depth_um: STROKE_UM,
            });
        }
        None
    }

    /// Judge an extraction: the first object it failed, if any; the objects of phases
    /// 3–4 moved with the 3→4 step its docking's insertion found (`step_um`:
    /// [`Self::shift_bins`]).
    pub fn judge_extraction(
        &self,
        s: &StrokeBins,
        f: &ExtractionFigures,
        step_um: Option<i32>,
    ) -> Option<Failure> {
        let shift = self.shift_bins(step_um);
        for p in (1..=4).rev() {
            if let Some(fail) = self.bands(s, p, true, shift) {
                return Some(fail);
            }
        }
        let (nom, at) = self.peak_nominal();
        let at = at + lo_um(shift);
        let tol = nom.abs() * i32::from(self.peak_pct) / 100 + self.peak_abs_mn;
        if (f.peak_mn - nom).abs() > tol {
            return Some(Failure {
                object: Object::ExtPeak,
                figure: f.peak_mn,
                limit: if f.peak_mn > nom {
                    nom + tol
                } else {
                    nom - tol
                },
                unit: Unit::Mn,
                depth_um: f.peak_um,
            });
        }
        if (f.peak_um - at).abs() > self.peak_pos_um {
            return Some(Failure {
                object: Object::ExtPeak,
                figure: f.peak_um,
                limit: if f.peak_um > at {
                    at + self.peak_pos_um
                } else {
                    at - self.peak_pos_um
                },
                unit: Unit::Um,
                depth_um: f.peak_um,
            });
        }
        None
    }

    /// The first bin of phase `p` outside its band, in the stroke's direction, with
    /// the objects moved by `shift` bins (a bin the step's move puts in phase 3 is
    /// judged by phase 3's band).
    fn bands(&self, s: &StrokeBins, p: u8, extraction: bool, shift: usize) -> Option<Failure> {
        let from = self.moved_from();
        let check = |i: usize| -> Option<Failure> {
            let j = moved_at(i, shift, from);
            // The last bin is the end object's (the mated position).
            if self.nominal.phase_of(j) != p || (i == BINS - 1 && !extraction) {
                return None;
            }
            let m = i32::from(s.bin(i).mean_dn()?) * 100;
            let (lo, hi) = self.band_mn(j);
            (m < lo || m > hi).then(|| Failure {
                object: Object::band(p, extraction),
                figure: m,
                limit: if m > hi { hi } else { lo },
                unit: Unit::Mn,
                depth_um: mid_um(i),
            })
        };
        if extraction {
            (0..BINS).rev().find_map(check)
        } else {
            (0..BINS).find_map(check)
        }
    }
}

/// Bin `i` moved `shift` bins back if it is at or after bin `from`.
const fn moved_at(i: usize, shift: usize, from: usize) -> usize {
    if i >= from {
        i.saturating_sub(shift)
    } else {
        i
    }
}

impl Default for SignatureConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::signature::capture::Capture;
    use crate::signature::Stroke;

    /// A stroke sampled every 15 µm from `f(depth)` N.
    fn stroke(stroke: Stroke, f: impl Fn(i32) -> f64) -> StrokeBins {
        let mut c = Capture::new();
        let depths: std::vec::Vec<i32> = match stroke {
            Stroke::Insertion => (0..=STROKE_UM).step_by(15).collect(),
            Stroke::Extraction => (0..=STROKE_UM).rev().step_by(15).collect(),
        };
        let d0 = depths[0];
        c.sample(d0, (f(d0) * 1000.0) as i32, None);
        for &d in &depths {
            c.sample(d, (f(d) * 1000.0).round() as i32, Some(stroke));
        }
        let last = *depths.last().unwrap();
        c.sample(last, (f(last) * 1000.0) as i32, None);
        c.stroke(stroke).clone()
    }

    fn eq7(d: i32) -> f64 {
        crate::profile::forces_at_depth_um(f64::from(d)).n3_n
    }

    #[test]
    fn eq7s_curve_from_the_compiler_is_the_hosts() {
        let host = NominalCurve::from_fn(eq7, BOUNDARY_UM);
        assert_eq!(host, EQ7_CURVE);
        assert_eq!(EQ7_CURVE.step_dn, 1567);
        assert_eq!(EQ7_CURVE.mean_dn[0], 1126);
        assert_eq!(EQ7_CURVE.max_dn.iter().max(), Some(&2063));
    }

    #[test]
    fn the_design_curve_itself_is_ok_both_ways() {
        let c = SignatureConfig::DEFAULT;
        let ins = stroke(Stroke::Insertion, eq7);
        let f = c.insertion_figures(&ins);
        assert_eq!(c.judge_insertion(&ins, &f), None, "{f:?}");
        let step = f.step_um.unwrap();
        assert!((step - 14_934).abs() <= 15, "{step}");
        let ext = stroke(Stroke::Extraction, eq7);
        let fe = figures::extraction(&ext);
        assert_eq!(c.judge_extraction(&ext, &fe, f.step_um), None, "{fe:?}");
    }

    impl SignatureConfig {
        /// The insertion's figures with its step hidden: judged where a new cone's
        /// objects sit.
        fn unmoved(&self, s: &StrokeBins) -> InsertionFigures {
            let mut f = figures::insertion(
                s,
                self.entry_dn(),
                self.nominal.plateau_bins(),
                self.nominal.boundaries_um[1] + POS_TOL_UM,
                self.nominal.step_dn,
            );
            f.step_um = None;
            f
        }
    }

    /// Eq. 7 with its 3→4 step `shift_um` deeper (phase 3 continued up to it, phase 4
    /// from it on): a worn cone's curve (docs/physics.md §10.5).
    fn worn(shift_um: i32) -> impl Fn(i32) -> f64 {
        move |d| {
            let b = BOUNDARY_UM[2];
            if d < b {
                eq7(d)
            } else if d < b + shift_um {
                eq7(b - 1)
            } else {
                eq7(d - shift_um)
            }
        }
    }

    /// The defect: the objects sat on the new cone's step, and a cone worn 100–200 µm
    /// (its step 0.6–1.2 mm deeper) failed band4 at every docking. They now move with
    /// the step, as far as a cone's life moves it; a step deeper still, or a fault on
    /// a worn cone, is NOK as before.
    #[test]
    fn a_worn_cones_deeper_step_moves_the_objects_with_it() {
        let c = SignatureConfig::DEFAULT;
        for shift in [300, 600, 1_200, 2_400, 4_800] {
            let ins = stroke(Stroke::Insertion, worn(shift));
            let f = c.insertion_figures(&ins);
            let step = f.step_um.unwrap();
            assert!((step - 14_934 - shift).abs() <= 60, "{shift}: {step}");
            assert_eq!(c.judge_insertion(&ins, &f), None, "{shift}: {f:?}");
            let ext = stroke(Stroke::Extraction, worn(shift));
            let fe = figures::extraction(&ext);
            assert_eq!(c.judge_extraction(&ext, &fe, f.step_um), None, "{shift}");
            // Judged as the new cone's, a step past the position tolerance fails (what
            // the objects did before).
            if shift > 2 * POS_TOL_UM {
                assert_ne!(c.judge_insertion(&ins, &c.unmoved(&ins)), None, "{shift}");
                assert_ne!(c.judge_extraction(&ext, &fe, None), None, "{shift}");
            }
        }
        // Beyond the cone's life: the objects stay, and phase 4's band fails.
        let ins = stroke(Stroke::Insertion, worn(6_000));
        let f = c.insertion_figures(&ins);
        assert_eq!(c.shift_bins(f.step_um), 0);
        assert_eq!(
            c.judge_insertion(&ins, &f).map(|x| x.object),
            Some(Object::Band4)
        );
        // Debris in phase 3 of a worn cone is still band3's, a dry guide the plateau's.
        let debris = |d: i32| {
            worn(1_200)(d)
                + if (10_500..11_500).contains(&d) {
                    30.0
                } else {
                    0.0
                }
        };
        let ins = stroke(Stroke::Insertion, debris);
        assert_eq!(
            c.judge_insertion(&ins, &c.insertion_figures(&ins))
                .map(|x| x.object),
            Some(Object::Band3)
        );
        let low = |d: i32| {
            let f = worn(1_200)(d);
            if d >= 14_934 + 1_200 {
                f * 0.88
            } else {
                f
            }
        };
        let ins = stroke(Stroke::Insertion, low);
        assert_eq!(
            c.judge_insertion(&ins, &c.insertion_figures(&ins))
                .map(|x| x.object),
            Some(Object::Plateau)
        );
    }

    #[test]
    fn each_fault_fails_its_own_object() {
        let c = SignatureConfig::DEFAULT;
        let judge = |f: &dyn Fn(i32) -> f64| {
            let s = stroke(Stroke::Insertion, f);
            c.judge_insertion(&s, &c.insertion_figures(&s))
                .map(|x| x.object)
        };
        // Late entry: the profile 2 mm later.
        assert_eq!(
            judge(&|d| if d < 2_000 { 0.3 } else { eq7(d - 2_000) }),
            Some(Object::Entry)
        );
        // Debris: +30 N over a millimetre of phase 3.
        assert_eq!(
            judge(&|d| eq7(d)
                + if (10_500..11_500).contains(&d) {
                    30.0
                } else {
                    0.0
                }),
            Some(Object::Band3)
        );
        // Phase 4 12 % low throughout: the plateau before its band.
        assert_eq!(
            judge(&|d| if d >= 14_934 { eq7(d) * 0.88 } else { eq7(d) }),
            Some(Object::Plateau)
        );
        // The end 25 N high.
        assert_eq!(
            judge(&|d| eq7(d) + if d > 29_800 { 25.0 } else { 0.0 }),
            Some(Object::End)
        );
        // A catch on the way out: +40 N over a millimetre of phase 4.
        let s = stroke(Stroke::Extraction, |d| {
            eq7(d)
                + if (21_500..22_500).contains(&d) {
                    40.0
                } else {
                    0.0
                }
        });
        let fail = c
            .judge_extraction(&s, &figures::extraction(&s), Some(14_934))
            .unwrap();
        assert_eq!(fail.object, Object::ExtBand4);
        assert!((21_500..22_500).contains(&fail.depth_um), "{fail:?}");
        assert!(fail.figure > fail.limit);
    }

    #[test]
    fn the_moved_objects_start_where_bins_within_says() {
        let c = SignatureConfig::DEFAULT;
        let from = bins_within(BOUNDARY_UM[2] - POS_TOL_UM, STROKE_UM).start;
        assert_eq!(c.moved(from, 3), from - 3);
        assert_eq!(c.moved(from - 1, 3), from - 1);
    }

    #[test]
    fn object_codes_are_stable() {
        for o in Object::ALL {
            assert_eq!(Object::from_code(o.code()), Some(o));
        }
        assert_eq!(Object::from_code(0), None);
        assert_eq!(Object::from_code(13), None);
        assert_eq!(Object::Entry.code(), 1);
        assert_eq!(Object::ExtPeak.code(), 12);
    }
}
