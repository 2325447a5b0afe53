//! The docking contact-force profile (Eq. 7 of He et al. 2025) and the four contact
//! phases (`docs/physics.md` §2–§3).
//!
//! `t` is seconds from the start of compliant contact at the nominal speed
//! `v0 = 1.2 mm/s`; the firmware evaluates the profile at an **insertion depth**
//! (`depth = v0 · t`), never at wall time, so that a slower or paused axis sees the
//! force of where it is. The 3→4 boundary is 12.445 s (not the 12.55 s printed in
//! Eq. 7): only with it does the stated peak `N3(12.445) = 206.34 N` come out.
//!
//! Only `+ - * /` on `f64` are used (no `powf`, no `ln`), so host and target give
//! bit-identical results (IEEE 754 basic operations are correctly rounded) and no
//! `micromath`/`std` shadowing question arises.

/// Nominal docking speed v0, µm/s (the force model holds for v ≤ v0).
pub const V0_UM_PER_S: u32 = 1_200;
/// Duration of one compliant stroke at v0, s.
pub const STROKE_S: f64 = 25.0;
/// Compliant insertion travel, contact start to mated, µm (25 s × 1.2 mm/s).
pub const STROKE_UM: i32 = 30_000;
/// Phase boundaries in time from the start of compliant contact, s.
pub const BOUNDARY_S: [f64; 3] = [3.75, 7.25, 12.445];
/// Phase boundaries as insertion depth, µm (`v0 · BOUNDARY_S`).
pub const BOUNDARY_UM: [i32; 3] = [4_500, 8_700, 14_934];

/// The rod's tilt in single-point contact (phases 1–3), θ0, degrees (Eq. 6; `hil-sim`'s
/// `PlantParams::PAPER`, a test there checks they agree).
pub const THETA0_DEG: f64 = 2.84;
/// Eq. 7's time axis in phases 3–4: the travel per second of its `t`, µm/s
/// (`docs/physics.md` §8.3; `hil-sim`'s `DEFAULT_V_MODEL_MM_S`).
pub const V_MODEL_UM_PER_S: u32 = 4_000;

/// How much deeper the 3→4 force step lies per mm of bore wear, µm of insertion depth.
/// Two-point contact begins at the engaged length `L* = (D2 − D1·cos θ0)/sin θ0`
/// (Eq. 6), reached on Eq. 7's axis at `t3 = t2 + L*·cos θ0 / v_model`, i.e. at the
/// depth `v0·t3`: so `d(depth)/d(D2) = (v0 / v_model) · cos θ0 / sin θ0` = 6.047 µm a
/// µm (`docs/physics.md` §10.5). Computed by the compiler from [`THETA0_DEG`],
/// [`V0_UM_PER_S`] and [`V_MODEL_UM_PER_S`]: 6 047.
pub const STEP_UM_PER_WEAR_MM: u32 = {
    let x = THETA0_DEG * core::f64::consts::PI / 180.0;
    // Taylor series to x^13 (|x| < 0.1 rad here: exact to the last bit of the rounding
    // below).
    let (mut s, mut c, mut term_s, mut term_c) = (0.0, 0.0, x, 1.0);
    let mut k = 0;
    while k < 7 {
        s += term_s;
        c += term_c;
        let n = (2 * k + 2) as f64;
        term_s = -term_s * x * x / (n * (n + 1.0));
        term_c = -term_c * x * x / ((n - 1.0) * n);
        k += 1;
    }
    let v = V0_UM_PER_S as f64 / V_MODEL_UM_PER_S as f64 * c / s * 1000.0;
    (v + 0.5) as u32
};

/// One of the four contact phases of a compliant insertion (`docs/physics.md` §2).
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum ContactPhase {
    /// 1: the rod slides on the cone's first fillet (0–4.5 mm).
    FirstFillet = 1,
    /// 2: second fillet (4.5–8.7 mm).
    SecondFillet = 2,
    /// 3: single-point rod–cone contact (8.7–14.934 mm); N3 rises to 107 N.
    SinglePoint = 3,
    /// 4: two-point contact (14.934–30 mm); N3 jumps to its 206.34 N peak.
    TwoPoint = 4,
}

impl ContactPhase {
    /// Phase number 1–4 as the paper counts them.
    pub const fn number(self) -> u8 {
        self as u8
    }

    /// The phase with number `n` (1–4), or `None`.
    pub const fn from_number(n: u8) -> Option<Self> {
        match n {
            1 => Some(Self::FirstFillet),
            2 => Some(Self::SecondFillet),
            3 => Some(Self::SinglePoint),
            4 => Some(Self::TwoPoint),
            _ => None,
        }
    }

    /// The phase at time `t_s` from the start of compliant contact (clamped to the stroke).
    pub fn at_time(t_s: f64) -> Self {
        if t_s < BOUNDARY_S[0] {
            Self::FirstFillet
        } else if t_s < BOUNDARY_S[1] {
            Self::SecondFillet
        } else if t_s < BOUNDARY_S[2] {
            Self::SinglePoint
        } else {
            Self::TwoPoint
        }
    }

    /// The phase at insertion depth `depth_um` (µm past the start of compliant contact);
    /// `None` before contact (negative depth).
    pub const fn at_depth_um(depth_um: i32) -> Option<Self> {
        if depth_um < 0 {
            None
        } else if depth_um < BOUNDARY_UM[0] {
            Some(Self::FirstFillet)
        } else if depth_um < BOUNDARY_UM[1] {
            Some(Self::SecondFillet)
        } else if depth_um < BOUNDARY_UM[2] {
            Some(Self::SinglePoint)
        } else {
            Some(Self::TwoPoint)
        }
    }
}

/// The four contact forces of Eq. 7, newtons.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Forces {
    /// Support reaction N1 of the compliant platform, N.
    pub n1_n: f64,
    /// Support reaction N2, N.
    pub n2_n: f64,
    /// Rod–cone normal force N3 (the wear-relevant load), N.
    pub n3_n: f64,
    /// Second rod–cone contact of the two-point phase, N.
    pub n4_n: f64,
}

/// Eq. 7 at time `t_s` from the start of compliant contact. `t_s` is clamped to
/// `[0, 25]` s (a mated axis that overshoots sees the end-of-stroke force).
pub fn forces_at_time(t_s: f64) -> Forces {
    let t = if t_s.is_nan() || t_s < 0.0 {
        0.0
    } else if t_s > STROKE_S {
        STROKE_S
    } else {
        t_s
    };
    match ContactPhase::at_time(t) {
        ContactPhase::FirstFillet => Forces {
            n1_n: 67.22,
            n2_n: 21.75,
            n3_n: 112.64,
            n4_n: 0.0,
        },
        ContactPhase::SecondFillet => Forces {
            n1_n: 61.16,
            n2_n: 14.72,
            n3_n: 115.05,
            n4_n: 0.0,
        },
        ContactPhase::SinglePoint => Forces {
            n1_n: (351.6 * t - 12534.0) / (t - 175.2),
            n2_n: (351.6 * t - 9059.1) / (t - 175.2),
            n3_n: 17429.0 / (175.2 - t),
            n4_n: 0.0,
        },
        ContactPhase::TwoPoint => Forces {
            n1_n: 364.9 / (t - 3.64),
            n2_n: 0.0,
            n3_n: 3989.0 / (t + 6.887),
            n4_n: 0.2 * t * t - 13.37 * t + 210.5,
        },
    }
}

/// Eq. 7 at insertion depth `depth_um`; zero before contact (negative depth).
pub fn forces_at_depth_um(depth_um: f64) -> Forces {
    if depth_um.is_nan() || depth_um < 0.0 {
        return Forces::default();
    }
    forces_at_time(depth_um / V0_UM_PER_S as f64)
}

/// Exact ∫N3 dt over one stroke, N·s, from the closed form of Eq. 7 (the
/// logarithms evaluated offline): 112.64·3.75 + 115.05·3.5
/// + 17429·ln(167.95/162.755) + 3989·ln(31.887/19.332).
pub const N3_STROKE_INTEGRAL_NS: f64 = 3368.94;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn peak_is_at_the_3_to_4_boundary() {
        let f = forces_at_time(12.445);
        assert!((f.n3_n - 206.34).abs() < 0.005, "{}", f.n3_n);
        let before = forces_at_time(12.444_999);
        assert!((before.n3_n - 107.09).abs() < 0.01, "{}", before.n3_n);
    }

    #[test]
    fn phase_one_solves_to_the_papers_constants() {
        let f = forces_at_time(0.0);
        assert_eq!(
            (f.n1_n, f.n2_n, f.n3_n, f.n4_n),
            (67.22, 21.75, 112.64, 0.0)
        );
    }

    #[test]
    fn depth_and_time_boundaries_agree() {
        for (b_s, b_um) in BOUNDARY_S.iter().zip(BOUNDARY_UM) {
            assert_eq!((b_s * 1200.0).round() as i32, b_um);
            let p_t = ContactPhase::at_time(*b_s);
            assert_eq!(ContactPhase::at_depth_um(b_um), Some(p_t));
            assert!(ContactPhase::at_depth_um(b_um - 1) < Some(p_t));
        }
        assert_eq!(ContactPhase::at_depth_um(-1), None);
    }

    #[test]
    fn fine_midpoint_integral_matches_closed_form() {
        // Midpoint rule at 1 µs; the jumps cost at most one step each.
        let n = 2_500_000u32;
        let dt = STROKE_S / n as f64;
        let mut sum = 0.0;
        for k in 0..n {
            sum += forces_at_time((k as f64 + 0.5) * dt).n3_n * dt;
        }
        assert!((sum - N3_STROKE_INTEGRAL_NS).abs() < 0.01, "{sum}");
    }

    #[test]
    fn clamps_outside_the_stroke() {
        assert_eq!(forces_at_time(-3.0), forces_at_time(0.0));
        assert_eq!(forces_at_time(99.0), forces_at_time(25.0));
        assert_eq!(forces_at_depth_um(-1.0), Forces::default());
        assert_eq!(forces_at_time(f64::NAN), forces_at_time(0.0));
    }
}
