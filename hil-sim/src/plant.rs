//! A quasi-static plant model of the docking contact forces: the equilibrium systems
//! behind Eq. 7 (He et al. 2025, Eqs. 3–6), solved at an insertion depth.
//!
//! Eq. 7 ([`docking_logic::profile`]) is a curve fit of one machine at one speed. This module
//! solves the equations it came from, so that other masses, friction coefficients,
//! cone angles and tilts can be simulated. The printed Eqs. 3–5 lost terms in
//! typesetting; what is implemented is the reconstruction "R" of
//! `docs/physics.md` (§8.1), which reproduces that page's table of values (§8.4) to
//! better than 1e-3 N and Eq. 7 to the residuals of its §8.5 (phases 1–2 ≤ 0.01 N,
//! phase 3 N3 1.70 N, phase 4 N3 0.35 N / N4 1.10 N).
//!
//! # Units and conventions
//!
//! Newtons, millimetres, seconds; angles in degrees at the interface, radians inside.
//! Each phase is `A·x = b` with `b = (0, m·g, 0)`: row 1 the balance along the docking
//! axis (x), row 2 the vertical balance (z), row 3 the moment balance (N·mm), written as
//! paper LHS − paper RHS = 0. Friction is `µ1·N1`, `µ1·N2` at the supports and `µ2·N3`,
//! `µ2·N4` at the rod–cone contacts. `s`, `c` are `sin θ`, `cos θ`; `sγ`, `cγ` of the cone
//! angle γ.
//!
//! # The equations as implemented
//!
//! Support moment coefficients (phases 1–3, at θ0):
//! `a1 = s·l1x − c·l1z − µ1(c·l1x + s·l1z)`,
//! `a2 = −s·l2x − c·l2z − µ1(c·l2x + s·l2z)`. The µ1 term of `a2` is the **support-2
//! friction moment**, missing from the printed Eq. 3; with it phases 1–2 match Eq. 7 to
//! its rounding.
//!
//! * Phases 1–2 (fillet on the cone chamfer, Eq. 3), x = (N1, N2, N3), θ = θ0:
//!   rows `[1, −1, −(µ2·cγ + sγ)]`, `[µ1, µ1, cγ − µ2·sγ]`,
//!   `[a1, a2, cos(γ−θ0)·l3x − sin(γ−θ0)·l3z − µ2(sin(γ−θ0)·l3x + cos(γ−θ0)·l3z)]`;
//!   phase 1 `l3x = 130.76`, `l3z = 94.94`; phase 2 `l3x = 110.2 + 25·sin(γ−θ0)`,
//!   `l3z = 72.5 + 25·cos(γ+θ0)`. The forces are constant within each phase.
//! * Phase 3 (single point, Eq. 4), x = (N1, N2, N3), θ = θ0 (constant):
//!   rows `[1, −1, −(µ2·c + s)]`, `[µ1, µ1, c − µ2·s]`, `[a1, a2, l3x(s3) − µ2·l3z]`
//!   with `l3x(s3) = 110.2 − s3/cos θ0`, `l3z = 97.5`, `s3` the depth past the start of
//!   phase 3.
//! * Phase 4 (two points, Eq. 5), x = (N1, N3, N4), N2 = 0, θ = θ(s4) from Eq. 6:
//!   rows `[1, −(µ2·c + s), −µ2]`, `[−µ1, c − µ2·s, −1]`,
//!   `[s·l1x − c·l1z + µ1(c·l1x + s·l1z), l3x(s4) − µ2·l3z, −c·l4x − s·l4z + µ2(s·l4x − c·l4z)]`
//!   with `l3x(s4) = 80.4 − s4/cos θ`, `l3z = 97.5`, `l4x = 110.2`, `l4z = 72.5`. Two
//!   repairs of the print: the moment row's `N1·cosθ·l1z` (lost in print) is restored,
//!   and support-1 friction enters the z row with a **minus** sign (it points down once
//!   the panel rotates back, as the printed moment row already has it).
//! * Eq. 6, phase 4 only: eliminating `lxt` with its second line, the tilt is the root of
//!   `G(θ) = [ly·sinθ0 + lx·cosθ0 − ly·sinθ − (lx + L0)·cosθ − s4]·sinθ
//!   + (D2 − D1·cosθ)·cosθ` (the first line multiplied through by `sinθ`, so there is no
//!   `1/θ` pole), lx 179.4, ly 198.5, D1 25, D2 26, L0 24.75 mm.
//!
//! # Insertion depth, the time axis and its default
//!
//! Quasi-static: speed only maps depth to time. Everything is computed at an insertion
//! depth ([`Plant::at_depth`], mm past the start of compliant contact); [`Plant::at_time`]
//! maps Eq. 7's time axis to depth as `depth = v_model · t`, where
//! [`PlantParams::v_model_mm_s`] is **the travel per second of Eq. 7's time axis**.
//! Default 4.0 mm/s ([`DEFAULT_V_MODEL_MM_S`]): `docs/physics.md` §8.3 shows that Eq. 7's
//! phases 3–4 correspond to 4 mm/s of travel — Eq. 6 gives the paper's θ(16 s) = 1.65°
//! only at 4.0 mm/s, the phase-3 duration 5.195 s is `L*·cosθ0/4`, and the phase-4 N3
//! residual is 0.35 N at 4.0 against 47.7 N at 1.2 mm/s. `v_model = 1.2` reproduces
//! the other reading (the paper's `v0`; with the paper's 12.445 s boundary, θ(16 s) =
//! 2.176°).
//!
//! Phase boundaries, as depths: phases 1 and 2 end at `v·t1` and `v·t2` (configuration:
//! they cannot be derived from the text; the paper's 3.75 s and 7.25 s). Phase 4 starts
//! when the engaged length reaches `L* = (D2 − D1·cosθ0)/sinθ0` (the geometry), i.e.
//! `L*·cosθ0` past the start of phase 3: `t3 = t2 + L*·cosθ0/v = 12.4443 s` at the
//! paper's values. [`PlantParams::t3_s`] overrides it with a time; the reference table
//! and Eq. 7 use the paper's printed 12.445 s ([`PlantParams::REFERENCE`]), and phase 4's
//! depth counts from the boundary in use, so the 0.7 ms between the two shifts phase-4
//! forces by up to 0.008 N (more than the table's 1e-3 N).
//!
//! # Contact set
//!
//! A contact force that would turn negative means that contact has lifted off; the
//! plant then solves the system without it ([`PlantPoint::lifted`] names it):
//!
//! * Phases 1–3, N2 < 0: support 2 lifts. With N2 = 0 the x and z rows give N1 and N3
//!   (both positive for valid parameters); the moment row cannot be balanced by the two
//!   remaining contacts at a fixed tilt (the panel would tip), so the point is marked
//!   [`PlantPoint::resolved`] = false.
//! * Phase 4, N4 < 0: the two-point contact is lost; the single-point (phase-3 form)
//!   system is solved at the current tilt and lever arm, N2 back as an unknown. If that
//!   N2 is negative too, N2 = N4 = 0 and phase 4's x and z rows give N1 and N3 (these
//!   are continuous with the two-point solution where N4 crosses 0); moment unbalanced,
//!   `resolved` = false. With the paper's values this happens from t ≈ 25.4 s.
//! * Any force still negative is set to 0 and the point is unresolved; a singular
//!   system (|det| below 1e-12 of Hadamard's bound — none with the paper's values,
//!   `docs/physics.md` §8.1, nor within the validated ranges) is never divided by and is
//!   unresolved too.
//!
//! So a returned force is never negative and never NaN.
//!
//! # The Eq. 6 root finder, and why it cannot fail
//!
//! `G(0) = D2 − D1 > 0` (validated) and `G(θ0) = sinθ0·(cosθ0·(L* − L0) − s4)`, which is
//! negative whenever `L0 > L* − s4/cosθ0`. If it is not (small θ0: the root lies above
//! θ0), the bracket's upper end doubles from θ0 up to [`THETA_MAX_DEG`] until `G < 0`.
//! Within a bracket `[lo, hi]` with `G(lo) > 0 > G(hi)` a root exists (`G` is
//! continuous); each iteration takes the Newton step on `G` when it falls strictly inside
//! the bracket, else bisects, and shrinks the bracket, so the iterate never leaves it
//! (no overshoot to θ < 0, no spurious root near 93–172°), no step divides by a zero
//! derivative, and the loop ends after [`TILT_MAX_ITER`] iterations at most (5 at the
//! paper's values, 6 over the stability sweep of `hil-sim accuracy`, bracket widenings
//! counted; bisection alone would need about 40 for the 1e-12 rad tolerance). If no
//! sign change is found below [`THETA_MAX_DEG`] (never seen with the paper's geometry
//! over the validated ranges; a custom [`Geometry`] could), the tilt is reported
//! unbracketed and the point unresolved, with θ0.
//!
//! `no_std`, `f64` with `libm`; nothing here panics, indexes or allocates. The firmware
//! does not call it (it is the simulator's plant), so it costs no flash.

use libm::{cos, fabs, sin, sqrt};

/// Default travel per second of Eq. 7's time axis, mm/s (see the module doc).
pub const DEFAULT_V_MODEL_MM_S: f64 = 4.0;

/// Duration of one stroke on Eq. 7's time axis, s.
pub const STROKE_S: f64 = docking_logic::profile::STROKE_S;

/// The paper's printed phase 3→4 boundary, s (Eqs. 5–6), used by the reference table
/// (`docs/physics.md` §8.4).
pub const PAPER_T3_S: f64 = 12.445;

/// One row of the reference table of values (`docs/physics.md` §8.4): the plant with
/// [`PlantParams::REFERENCE`] at `t_s` gives these to better than 1e-3 N and 1e-3°.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TableRow {
    /// Time on Eq. 7's axis, s.
    pub t_s: f64,
    /// Phase 1–4.
    pub phase: u8,
    /// Tilt, degrees.
    pub theta_deg: f64,
    /// N1–N4, N (4 decimals).
    pub forces_n: [f64; 4],
}

/// The reference table of `docs/physics.md` §8.4 (9 rows, both sides of the 12.445 s
/// boundary).
pub const REFERENCE_TABLE: [TableRow; 9] = [
    row(0.0, 1, 2.8400, [67.2261, 21.7502, 112.6456, 0.0]),
    row(3.75, 2, 2.8400, [61.1669, 14.7222, 115.0453, 0.0]),
    row(7.25, 3, 2.8400, [54.6225, 33.5944, 105.4766, 0.0]),
    row(10.0, 3, 2.8400, [50.2870, 28.9520, 107.0162, 0.0]),
    row(12.4449, 3, 2.8400, [46.3249, 24.7093, 108.4232, 0.0]),
    row(12.4450, 4, 2.4878, [51.2381, 0.0, 205.9897, 76.1839]),
    row(16.0, 4, 1.6537, [38.3129, 0.0, 174.4185, 47.5177]),
    row(20.0, 4, 1.1668, [28.8089, 0.0, 148.4407, 23.4990]),
    row(25.0, 4, 0.8417, [20.8151, 0.0, 124.9648, 1.5774]),
];

const fn row(t_s: f64, phase: u8, theta_deg: f64, forces_n: [f64; 4]) -> TableRow {
    TableRow {
        t_s,
        phase,
        theta_deg,
        forces_n,
    }
}

/// Upper end of the tilt bracket search, degrees.
pub const THETA_MAX_DEG: f64 = 45.0;

/// Iteration cap of the tilt solver.
pub const TILT_MAX_ITER: u32 = 100;

/// Convergence tolerance of the tilt solver (step size), rad.
pub const TILT_TOL_RAD: f64 = 1e-12;

/// Largest time or depth evaluated; beyond it the input is clamped (s, or mm).
pub const INPUT_MAX: f64 = 1.0e4;

/// Largest configurable phase boundary, s.
pub const T_MAX_S: f64 = 1.0e3;

/// Machine geometry, mm (Section 2.2 of the paper).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Geometry {
    /// Support 1 lever arms.
    pub l1x_mm: f64,
    /// Support 1, vertical arm.
    pub l1z_mm: f64,
    /// Support 2 lever arms.
    pub l2x_mm: f64,
    /// Support 2, vertical arm.
    pub l2z_mm: f64,
    /// Phase 1 rod–cone contact arm, x.
    pub p1_l3x_mm: f64,
    /// Phase 1 rod–cone contact arm, z.
    pub p1_l3z_mm: f64,
    /// Phase 2: `l3x = p2_l3x0 + r·sin(γ − θ0)`.
    pub p2_l3x0_mm: f64,
    /// Phase 2: `l3z = p2_l3z0 + r·cos(γ + θ0)`.
    pub p2_l3z0_mm: f64,
    /// Phase 2 fillet radius r.
    pub p2_r_mm: f64,
    /// Phase 3: `l3x = p3_l3x0 − s3/cos θ0`.
    pub p3_l3x0_mm: f64,
    /// Phases 3–4 contact arm l3z.
    pub l3z_mm: f64,
    /// Phase 4: `l3x = p4_l3x0 − s4/cos θ`.
    pub p4_l3x0_mm: f64,
    /// Phase 4 second contact arm, x.
    pub l4x_mm: f64,
    /// Phase 4 second contact arm, z.
    pub l4z_mm: f64,
    /// Eq. 6 lx.
    pub lx_mm: f64,
    /// Eq. 6 ly.
    pub ly_mm: f64,
    /// Eq. 6 D1.
    pub d1_mm: f64,
    /// Eq. 6 D2 (must exceed D1).
    pub d2_mm: f64,
    /// Eq. 6 L0 (the printed 24.75).
    pub l0_mm: f64,
}

impl Geometry {
    /// The paper's machine.
    pub const PAPER: Self = Self {
        l1x_mm: 90.0,
        l1z_mm: 101.0,
        l2x_mm: 70.0,
        l2z_mm: 101.0,
        p1_l3x_mm: 130.76,
        p1_l3z_mm: 94.94,
        p2_l3x0_mm: 110.2,
        p2_l3z0_mm: 72.5,
        p2_r_mm: 25.0,
        p3_l3x0_mm: 110.2,
        l3z_mm: 97.5,
        p4_l3x0_mm: 80.4,
        l4x_mm: 110.2,
        l4z_mm: 72.5,
        lx_mm: 179.4,
        ly_mm: 198.5,
        d1_mm: 25.0,
        d2_mm: 26.0,
        l0_mm: 24.75,
    };

    fn fields(&self) -> [(&'static str, f64); 19] {
        [
            ("l1x_mm", self.l1x_mm),
            ("l1z_mm", self.l1z_mm),
            ("l2x_mm", self.l2x_mm),
            ("l2z_mm", self.l2z_mm),
            ("p1_l3x_mm", self.p1_l3x_mm),
            ("p1_l3z_mm", self.p1_l3z_mm),
            ("p2_l3x0_mm", self.p2_l3x0_mm),
            ("p2_l3z0_mm", self.p2_l3z0_mm),
            ("p2_r_mm", self.p2_r_mm),
            ("p3_l3x0_mm", self.p3_l3x0_mm),
            ("l3z_mm", self.l3z_mm),
            ("p4_l3x0_mm", self.p4_l3x0_mm),
            ("l4x_mm", self.l4x_mm),
            ("l4z_mm", self.l4z_mm),
            ("lx_mm", self.lx_mm),
            ("ly_mm", self.ly_mm),
            ("d1_mm", self.d1_mm),
            ("d2_mm", self.d2_mm),
            ("l0_mm", self.l0_mm),
        ]
    }
}

/// Plant parameters.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlantParams {
    /// Panel mass, kg.
    pub mass_kg: f64,
    /// Gravity, m/s².
    pub g_m_s2: f64,
    /// Support friction coefficient µ1.
    pub mu1: f64,
    /// Rod–cone friction coefficient µ2.
    pub mu2: f64,
    /// Cone half-angle γ, degrees.
    pub gamma_deg: f64,
    /// Initial panel tilt θ0, degrees.
    pub theta0_deg: f64,
    /// Travel per second of Eq. 7's time axis, mm/s.
    pub v_model_mm_s: f64,
    /// End of phase 1 on the time axis, s (configuration).
    pub t1_s: f64,
    /// End of phase 2 on the time axis, s (configuration).
    pub t2_s: f64,
    /// End of phase 3, s: `None` from the geometry (`t2 + L*·cosθ0/v`), or a time.
    pub t3_s: Option<f64>,
    /// Lever arms and Eq. 6 dimensions.
    pub geometry: Geometry,
}

impl PlantParams {
    /// The paper's parameters (m 12.2 kg, µ1 0.17, µ2 0.15, γ 15°, θ0 2.84°), the
    /// default time axis (4 mm/s) and the phase 3→4 boundary from the geometry.
    pub const PAPER: Self = Self {
        mass_kg: 12.2,
        g_m_s2: 9.8,
        mu1: 0.17,
        mu2: 0.15,
        gamma_deg: 15.0,
        theta0_deg: 2.84,
        v_model_mm_s: DEFAULT_V_MODEL_MM_S,
        t1_s: 3.75,
        t2_s: 7.25,
        t3_s: None,
        geometry: Geometry::PAPER,
    };

    /// [`Self::PAPER`] with the paper's printed phase 3→4 boundary 12.445 s: the setting
    /// of the reference table (`docs/physics.md` §8.4) and of Eq. 7.
    pub const REFERENCE: Self = Self {
        t3_s: Some(PAPER_T3_S),
        ..Self::PAPER
    };

    /// Check every parameter: finite and within its [`Param::range`]; `t1 ≤ t2 ≤ t3`.
    pub fn validate(&self) -> Result<(), PlantError> {
        let scalars = [
            (Param::MassKg, self.mass_kg),
            (Param::G, self.g_m_s2),
            (Param::Mu1, self.mu1),
            (Param::Mu2, self.mu2),
            (Param::GammaDeg, self.gamma_deg),
            (Param::Theta0Deg, self.theta0_deg),
            (Param::VModel, self.v_model_mm_s),
        ];
        for (p, v) in scalars {
            let (min, max) = p.range();
            check(p, v, min, max)?;
        }
        check(Param::T1, self.t1_s, 0.0, T_MAX_S)?;
        check(Param::T2, self.t2_s, self.t1_s, T_MAX_S)?;
        if let Some(t3) = self.t3_s {
            check(Param::T3, t3, self.t2_s, T_MAX_S)?;
        }
        for (name, v) in self.geometry.fields() {
            check(Param::Geometry(name), v, 1e-3, 1e3)?;
        }
        let g = &self.geometry;
        // G(0) = D2 − D1 > 0 is what brackets Eq. 6's root.
        check(Param::Geometry("d2_mm"), g.d2_mm, g.d1_mm + 1e-3, 1e3)?;
        Ok(())
    }

    /// Engaged length at which two-point contact starts, `L* = (D2 − D1·cosθ0)/sinθ0`, mm.
    pub fn l_star_mm(&self) -> f64 {
        let th0 = self.theta0_deg.to_radians();
        (self.geometry.d2_mm - self.geometry.d1_mm * cos(th0)) / sin(th0)
    }

    /// Phase boundaries on the time axis, s: `[t1, t2, t3]`.
    pub fn boundaries_s(&self) -> [f64; 3] {
        let t3 = match self.t3_s {
            Some(t3) => t3,
            None => {
                self.t2_s + self.l_star_mm() * cos(self.theta0_deg.to_radians()) / self.v_model_mm_s
            }
        };
        [self.t1_s, self.t2_s, t3]
    }
}

fn check(param: Param, got: f64, min: f64, max: f64) -> Result<(), PlantError> {
    if got.is_finite() && got >= min && got <= max {
        Ok(())
    } else {
        Err(PlantError {
            param,
            min,
            max,
            got,
        })
    }
}

/// A plant parameter, for errors.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Param {
    /// [`PlantParams::mass_kg`].
    MassKg,
    /// [`PlantParams::g_m_s2`].
    G,
    /// [`PlantParams::mu1`].
    Mu1,
    /// [`PlantParams::mu2`].
    Mu2,
    /// [`PlantParams::gamma_deg`].
    GammaDeg,
    /// [`PlantParams::theta0_deg`].
    Theta0Deg,
    /// [`PlantParams::v_model_mm_s`].
    VModel,
    /// [`PlantParams::t1_s`].
    T1,
    /// [`PlantParams::t2_s`].
    T2,
    /// [`PlantParams::t3_s`].
    T3,
    /// A [`Geometry`] field, by name.
    Geometry(&'static str),
}

impl Param {
    /// The field's name.
    pub const fn name(self) -> &'static str {
        match self {
            Self::MassKg => "mass_kg",
            Self::G => "g_m_s2",
            Self::Mu1 => "mu1",
            Self::Mu2 => "mu2",
            Self::GammaDeg => "gamma_deg",
            Self::Theta0Deg => "theta0_deg",
            Self::VModel => "v_model_mm_s",
            Self::T1 => "t1_s",
            Self::T2 => "t2_s",
            Self::T3 => "t3_s",
            Self::Geometry(n) => n,
        }
    }

    /// The valid range `(min, max)`, inclusive. The times' lower ends are the previous
    /// boundary (0 for t1); geometry is 0.001–1000 mm with `D2 > D1`.
    pub const fn range(self) -> (f64, f64) {
        match self {
            Self::MassKg => (1.0, 100.0),
            Self::G => (1.0, 30.0),
            Self::Mu1 | Self::Mu2 => (0.0, 0.6),
            Self::GammaDeg => (1.0, 45.0),
            Self::Theta0Deg => (0.5, 10.0),
            Self::VModel => (0.1, 20.0),
            Self::T1 | Self::T2 | Self::T3 => (0.0, T_MAX_S),
            Self::Geometry(_) => (1e-3, 1e3),
        }
    }
}

/// An out-of-range or non-finite parameter.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlantError {
    /// Which parameter.
    pub param: Param,
    /// Smallest valid value.
    pub min: f64,
    /// Largest valid value.
    pub max: f64,
    /// The value given.
    pub got: f64,
}

impl core::fmt::Display for PlantError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "plant parameter {} must be a finite number from {} to {}, got {}",
            self.param.name(),
            self.min,
            self.max,
            self.got
        )
    }
}

/// A contact of the panel.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Contact {
    /// Support 1 (N1).
    Support1,
    /// Support 2 (N2).
    Support2,
    /// The rod–cone contact (N3).
    RodCone,
    /// The second rod–cone contact of phase 4 (N4).
    SecondPoint,
}

impl Contact {
    /// All four, in force order.
    pub const ALL: [Self; 4] = [
        Self::Support1,
        Self::Support2,
        Self::RodCone,
        Self::SecondPoint,
    ];

    /// Short name.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Support1 => "support-1",
            Self::Support2 => "support-2",
            Self::RodCone => "rod-cone",
            Self::SecondPoint => "second-point",
        }
    }

    /// Index of its force, 0–3 (N1–N4).
    pub const fn index(self) -> usize {
        match self {
            Self::Support1 => 0,
            Self::Support2 => 1,
            Self::RodCone => 2,
            Self::SecondPoint => 3,
        }
    }
}

/// The plant at one depth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PlantPoint {
    /// Contact phase 1–4 (by depth; a lift-off does not change it).
    pub phase: u8,
    /// Insertion depth past the start of compliant contact, mm.
    pub depth_mm: f64,
    /// Support reaction N1, N (≥ 0, finite).
    pub n1_n: f64,
    /// Support reaction N2, N.
    pub n2_n: f64,
    /// Rod–cone normal force N3, N.
    pub n3_n: f64,
    /// Second rod–cone contact N4 (phase 4), N.
    pub n4_n: f64,
    /// Panel tilt θ, degrees (θ0 in phases 1–3).
    pub theta_deg: f64,
    /// The contact that lifted off (a force of the phase's contact set would have been
    /// negative), or `None`.
    pub lifted: Option<Contact>,
    /// Whether the forces satisfy all three equilibrium rows: `false` when, after a
    /// lift-off, only the force rows could be satisfied (the panel would tip), a force
    /// had to be clamped to 0, a system was singular, or the tilt was not bracketed.
    pub resolved: bool,
    /// Iterations of the tilt solver (0 outside phase 4).
    pub iterations: u32,
}

impl PlantPoint {
    /// The four forces N1–N4, N.
    pub const fn forces(&self) -> [f64; 4] {
        [self.n1_n, self.n2_n, self.n3_n, self.n4_n]
    }
}

/// Eq. 6's tilt at one phase-4 depth.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tilt {
    /// θ, rad.
    pub theta_rad: f64,
    /// Solver iterations (bracket widenings included).
    pub iterations: u32,
    /// Whether a sign change of G was found (always, within the validated ranges).
    pub bracketed: bool,
    /// Whether the step fell below the tolerance (or G hit 0) within the cap.
    pub converged: bool,
}

/// `A·x = b` by Cramer's rule. `None` when |det| is below 1e-12 of Hadamard's bound
/// (the product of the row norms), so nothing is divided by ~0.
pub fn solve3(a: [[f64; 3]; 3], b: [f64; 3]) -> Option<[f64; 3]> {
    let [r0, r1, r2] = a;
    let det = det3(r0, r1, r2);
    let norm = |[x, y, z]: [f64; 3]| sqrt(x * x + y * y + z * z);
    let bound = norm(r0) * norm(r1) * norm(r2);
    if !det.is_finite() || bound == 0.0 || fabs(det) <= 1e-12 * bound {
        return None;
    }
    let [b0, b1, b2] = b;
    // Column k replaced by b.
    let with = |[x, y, z]: [f64; 3], v: f64, k: u8| -> [f64; 3] {
        match k {
            0 => [v, y, z],
            1 => [x, v, z],
            _ => [x, y, v],
        }
    };
    let xk = |k: u8| det3(with(r0, b0, k), with(r1, b1, k), with(r2, b2, k)) / det;
    let x = [xk(0), xk(1), xk(2)];
    let [x0, x1, x2] = x;
    (x0.is_finite() && x1.is_finite() && x2.is_finite()).then_some(x)
}

fn det3([a, b, c]: [f64; 3], [d, e, f]: [f64; 3], [g, h, i]: [f64; 3]) -> f64 {
    a * (e * i - f * h) - b * (d * i - f * g) + c * (d * h - e * g)
}

/// `[1, kx; mz, kz]·(N1, N3) = (0, mg)`: the two force rows with one support and the
/// rod–cone contact. `None` if singular.
fn solve2(kx: f64, mz: f64, kz: f64, mg: f64) -> Option<(f64, f64)> {
    let det = kz - kx * mz;
    let bound = sqrt(1.0 + kx * kx) * sqrt(mz * mz + kz * kz);
    if !det.is_finite() || fabs(det) <= 1e-12 * bound {
        return None;
    }
    let (n1, n3) = (-kx * mg / det, mg / det);
    (n1.is_finite() && n3.is_finite()).then_some((n1, n3))
}

/// A validated plant, with what does not depend on depth precomputed.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plant {
    p: PlantParams,
    mg: f64,
    th0: f64,
    s0: f64,
    c0: f64,
    a1: f64,
    a2: f64,
    /// Depth boundaries, mm: ends of phases 1, 2, 3.
    b_mm: [f64; 3],
    /// Phases 1 and 2 (constant forces).
    p1: PlantPoint,
    p2: PlantPoint,
    /// Tilt solver: iteration cap and step tolerance, rad.
    tilt_cap: u32,
    tilt_tol: f64,
}

impl Plant {
    /// A plant for `p`, or which parameter is out of range.
    pub fn new(p: PlantParams) -> Result<Self, PlantError> {
        p.validate()?;
        let th0 = p.theta0_deg.to_radians();
        let (s0, c0) = (sin(th0), cos(th0));
        let (a1, a2) = support_moments(&p, s0, c0);
        let [t1, t2, t3] = p.boundaries_s();
        let v = p.v_model_mm_s;
        let b_mm = [v * t1, v * t2, v * t3];
        let mut plant = Self {
            p,
            mg: p.mass_kg * p.g_m_s2,
            th0,
            s0,
            c0,
            a1,
            a2,
            b_mm,
            p1: PlantPoint::default_at(1, th0),
            p2: PlantPoint::default_at(2, th0),
            tilt_cap: TILT_MAX_ITER,
            tilt_tol: TILT_TOL_RAD,
        };
        plant.p1 = plant.fillet(1);
        plant.p2 = plant.fillet(2);
        Ok(plant)
    }

    /// The same plant with another tilt solver cap and tolerance (rad; for convergence
    /// studies). The default is [`TILT_MAX_ITER`], [`TILT_TOL_RAD`].
    pub const fn with_tilt_solver(mut self, max_iter: u32, tol_rad: f64) -> Self {
        self.tilt_cap = max_iter;
        self.tilt_tol = tol_rad;
        self
    }

    /// The parameters.
    pub const fn params(&self) -> &PlantParams {
        &self.p
    }

    /// Phase boundaries as depths past the start of compliant contact, mm.
    pub const fn boundaries_mm(&self) -> [f64; 3] {
        self.b_mm
    }

    /// Phase boundaries on the time axis, s.
    pub fn boundaries_s(&self) -> [f64; 3] {
        let v = self.p.v_model_mm_s;
        let [b1, b2, b3] = self.b_mm;
        [b1 / v, b2 / v, b3 / v]
    }

    /// The plant at time `t_s` of Eq. 7's axis: depth `v_model · t` (t clamped to
    /// `[0, INPUT_MAX]`, NaN as 0).
    pub fn at_time(&self, t_s: f64) -> PlantPoint {
        self.at_depth(self.p.v_model_mm_s * clamp_input(t_s))
    }

    /// The phase (1–4) at insertion depth `depth_mm`.
    pub fn phase_at_depth(&self, depth_mm: f64) -> u8 {
        let d = clamp_input(depth_mm);
        let [b1, b2, b3] = self.b_mm;
        if d < b1 {
            1
        } else if d < b2 {
            2
        } else if d < b3 {
            3
        } else {
            4
        }
    }

    /// The plant at insertion depth `depth_mm` past the start of compliant contact
    /// (clamped to `[0, INPUT_MAX]`, NaN as 0).
    pub fn at_depth(&self, depth_mm: f64) -> PlantPoint {
        let d = clamp_input(depth_mm);
        self.in_phase(self.phase_at_depth(d), d)
    }

    /// Phase `phase`'s system at depth `depth_mm`, whichever phase the depth is in
    /// (for one-sided limits at a boundary and per-phase integrals). A phase outside
    /// 1–4 is taken as 4.
    pub fn in_phase(&self, phase: u8, depth_mm: f64) -> PlantPoint {
        let d = clamp_input(depth_mm);
        let [_, b2, b3] = self.b_mm;
        let mut pt = match phase {
            1 => self.p1,
            2 => self.p2,
            3 => self.single_point(d - b2),
            _ => self.two_point(d - b3),
        };
        pt.depth_mm = d;
        pt
    }

    /// The phase's nominal contact set solved without switching: N1–N4 (those outside
    /// the set 0), possibly negative; `None` if singular or the tilt is unbracketed.
    pub fn nominal_forces(&self, depth_mm: f64) -> Option<[f64; 4]> {
        let d = clamp_input(depth_mm);
        let [_, b2, b3] = self.b_mm;
        match self.phase_at_depth(d) {
            1 => self.fillet_system(1).map(|[n1, n2, n3]| [n1, n2, n3, 0.0]),
            2 => self.fillet_system(2).map(|[n1, n2, n3]| [n1, n2, n3, 0.0]),
            3 => self
                .single_point_system(d - b2)
                .map(|[n1, n2, n3]| [n1, n2, n3, 0.0]),
            _ => {
                let tilt = self.tilt(d - b3);
                if !tilt.bracketed {
                    return None;
                }
                self.two_point_system(d - b3, tilt.theta_rad)
                    .map(|[n1, n3, n4]| [n1, 0.0, n3, n4])
            }
        }
    }

    /// Eq. 6's tilt at phase-4 depth `s4_mm` (past the 3→4 boundary), with the plant's
    /// solver settings.
    pub fn tilt(&self, s4_mm: f64) -> Tilt {
        self.tilt_with(s4_mm, self.tilt_cap, self.tilt_tol)
    }

    /// Eq. 6's tilt with an iteration cap and a step tolerance (rad): bracketed Newton
    /// on `G(θ) = sinθ·F(θ)` (see the module doc). Always finite, within the bracket.
    pub fn tilt_with(&self, s4_mm: f64, max_iter: u32, tol_rad: f64) -> Tilt {
        let s4 = clamp_input(s4_mm);
        let g = &self.p.geometry;
        let k = g.ly_mm * self.s0 + g.lx_mm * self.c0 - s4;
        let lxl = g.lx_mm + g.l0_mm;
        let gf = |th: f64| -> (f64, f64) {
            let (s, c) = (sin(th), cos(th));
            let pp = k - g.ly_mm * s - lxl * c;
            let val = pp * s + (g.d2_mm - g.d1_mm * c) * c;
            let der = (-g.ly_mm * c + lxl * s) * s + pp * c + 2.0 * g.d1_mm * s * c - g.d2_mm * s;
            (val, der)
        };
        let theta_max = THETA_MAX_DEG.to_radians();
        let mut iterations = 0u32;
        let mut lo = 0.0;
        let mut hi = self.th0;
        let (mut g_hi, _) = gf(hi);
        while g_hi > 0.0 && hi < theta_max {
            iterations += 1;
            lo = hi;
            hi = (2.0 * hi).min(theta_max);
            g_hi = gf(hi).0;
        }
        if g_hi > 0.0 {
            return Tilt {
                theta_rad: self.th0,
                iterations,
                bracketed: false,
                converged: false,
            };
        }
        if g_hi == 0.0 {
            return Tilt {
                theta_rad: hi,
                iterations,
                bracketed: true,
                converged: true,
            };
        }
        // Invariant: G(lo) > 0 > G(hi), lo < x <= hi.
        let mut x = hi;
        let mut converged = false;
        while iterations < max_iter {
            iterations += 1;
            let (val, der) = gf(x);
            if val == 0.0 {
                converged = true;
                break;
            }
            if val > 0.0 {
                lo = x;
            } else {
                hi = x;
            }
            let newton = if der != 0.0 { x - val / der } else { f64::NAN };
            let next = if newton > lo && newton < hi {
                newton
            } else {
                0.5 * (lo + hi)
            };
            let step = fabs(next - x);
            x = next;
            if step <= tol_rad || hi - lo <= tol_rad {
                converged = true;
                break;
            }
        }
        Tilt {
            theta_rad: x,
            iterations,
            bracketed: true,
            converged,
        }
    }

    fn fillet_system(&self, phase: u8) -> Option<[f64; 3]> {
        let p = &self.p;
        let g = &p.geometry;
        let gam = p.gamma_deg.to_radians();
        let (sg, cg) = (sin(gam), cos(gam));
        let (l3x, l3z) = if phase == 1 {
            (g.p1_l3x_mm, g.p1_l3z_mm)
        } else {
            (
                g.p2_l3x0_mm + g.p2_r_mm * sin(gam - self.th0),
                g.p2_l3z0_mm + g.p2_r_mm * cos(gam + self.th0),
            )
        };
        let (sd, cd) = (sin(gam - self.th0), cos(gam - self.th0));
        let m3 = cd * l3x - sd * l3z - p.mu2 * (sd * l3x + cd * l3z);
        solve3(
            [
                [1.0, -1.0, -(p.mu2 * cg + sg)],
                [p.mu1, p.mu1, cg - p.mu2 * sg],
                [self.a1, self.a2, m3],
            ],
            [0.0, self.mg, 0.0],
        )
    }

    fn fillet(&self, phase: u8) -> PlantPoint {
        let gam = self.p.gamma_deg.to_radians();
        let (sg, cg) = (sin(gam), cos(gam));
        let kx = -(self.p.mu2 * cg + sg);
        let kz = cg - self.p.mu2 * sg;
        self.supports_and_rod(phase, self.fillet_system(phase), kx, kz)
    }

    /// Phases 1–3 switching: N2 < 0 → support 2 lifted, N1 and N3 from the force rows.
    fn supports_and_rod(&self, phase: u8, full: Option<[f64; 3]>, kx: f64, kz: f64) -> PlantPoint {
        let mut pt = PlantPoint::default_at(phase, self.th0);
        match full {
            Some([n1, n2, n3]) if n2 >= 0.0 => {
                pt.set([n1, n2, n3, 0.0]);
            }
            other => {
                if other.is_some() {
                    pt.lifted = Some(Contact::Support2);
                }
                pt.resolved = false;
                if let Some((n1, n3)) = solve2(kx, self.p.mu1, kz, self.mg) {
                    pt.set([n1, 0.0, n3, 0.0]);
                }
            }
        }
        pt.finish()
    }

    fn single_point_rows(&self, theta: f64, l3x: f64) -> [[f64; 3]; 3] {
        let p = &self.p;
        let (s, c) = (sin(theta), cos(theta));
        let (a1, a2) = if theta == self.th0 {
            (self.a1, self.a2)
        } else {
            support_moments(p, s, c)
        };
        [
            [1.0, -1.0, -(p.mu2 * c + s)],
            [p.mu1, p.mu1, c - p.mu2 * s],
            [a1, a2, l3x - p.mu2 * p.geometry.l3z_mm],
        ]
    }

    fn single_point_system(&self, s3_mm: f64) -> Option<[f64; 3]> {
        let l3x = self.p.geometry.p3_l3x0_mm - s3_mm / self.c0;
        solve3(self.single_point_rows(self.th0, l3x), [0.0, self.mg, 0.0])
    }

    fn single_point(&self, s3_mm: f64) -> PlantPoint {
        let p = &self.p;
        let kx = -(p.mu2 * self.c0 + self.s0);
        let kz = self.c0 - p.mu2 * self.s0;
        self.supports_and_rod(3, self.single_point_system(s3_mm), kx, kz)
    }

    fn two_point_rows(&self, s4_mm: f64, theta: f64) -> [[f64; 3]; 3] {
        let p = &self.p;
        let g = &p.geometry;
        let (s, c) = (sin(theta), cos(theta));
        let l3x = g.p4_l3x0_mm - s4_mm / c;
        [
            [1.0, -(p.mu2 * c + s), -p.mu2],
            [-p.mu1, c - p.mu2 * s, -1.0],
            [
                s * g.l1x_mm - c * g.l1z_mm + p.mu1 * (c * g.l1x_mm + s * g.l1z_mm),
                l3x - p.mu2 * g.l3z_mm,
                -c * g.l4x_mm - s * g.l4z_mm + p.mu2 * (s * g.l4x_mm - c * g.l4z_mm),
            ],
        ]
    }

    fn two_point_system(&self, s4_mm: f64, theta: f64) -> Option<[f64; 3]> {
        solve3(self.two_point_rows(s4_mm, theta), [0.0, self.mg, 0.0])
    }

    fn two_point(&self, s4_mm: f64) -> PlantPoint {
        let tilt = self.tilt(s4_mm);
        let theta = tilt.theta_rad;
        let mut pt = PlantPoint::default_at(4, theta);
        pt.iterations = tilt.iterations;
        if !tilt.bracketed {
            pt.resolved = false;
        }
        let p = &self.p;
        let (s, c) = (sin(theta), cos(theta));
        let full = self.two_point_system(s4_mm, theta);
        if let Some([n1, n3, n4]) = full {
            if n4 >= 0.0 {
                pt.set([n1, 0.0, n3, n4]);
                return pt.finish();
            }
            pt.lifted = Some(Contact::SecondPoint);
        } else {
            pt.resolved = false;
        }
        // Two-point contact lost (or singular): the single-point system at this tilt
        // and lever arm, N2 back as an unknown.
        let l3x = p.geometry.p4_l3x0_mm - s4_mm / c;
        match solve3(self.single_point_rows(theta, l3x), [0.0, self.mg, 0.0]) {
            Some([n1, n2, n3]) if n2 >= 0.0 => pt.set([n1, n2, n3, 0.0]),
            _ => {
                // N2 and N4 both off: phase 4's force rows for N1 and N3 (continuous
                // with the two-point solution where N4 crosses 0); moment unbalanced.
                pt.resolved = false;
                let kx = -(p.mu2 * c + s);
                let kz = c - p.mu2 * s;
                if let Some((n1, n3)) = solve2(kx, -p.mu1, kz, self.mg) {
                    pt.set([n1, 0.0, n3, 0.0]);
                }
            }
        }
        pt.finish()
    }
}

fn support_moments(p: &PlantParams, s: f64, c: f64) -> (f64, f64) {
    let g = &p.geometry;
    let a1 = s * g.l1x_mm - c * g.l1z_mm - p.mu1 * (c * g.l1x_mm + s * g.l1z_mm);
    let a2 = -s * g.l2x_mm - c * g.l2z_mm - p.mu1 * (c * g.l2x_mm + s * g.l2z_mm);
    (a1, a2)
}

fn clamp_input(x: f64) -> f64 {
    if x.is_nan() || x < 0.0 {
        0.0
    } else if x > INPUT_MAX {
        INPUT_MAX
    } else {
        x
    }
}

impl PlantPoint {
    fn default_at(phase: u8, theta_rad: f64) -> Self {
        Self {
            phase,
            depth_mm: 0.0,
            n1_n: 0.0,
            n2_n: 0.0,
            n3_n: 0.0,
            n4_n: 0.0,
            theta_deg: theta_rad.to_degrees(),
            lifted: None,
            resolved: true,
            iterations: 0,
        }
    }

    fn set(&mut self, [n1, n2, n3, n4]: [f64; 4]) {
        (self.n1_n, self.n2_n, self.n3_n, self.n4_n) = (n1, n2, n3, n4);
    }

    /// Clamp what is still negative (or not finite) to 0: reported, unresolved.
    fn finish(mut self) -> Self {
        let mut f = self.forces();
        for (c, v) in Contact::ALL.iter().zip(f.iter_mut()) {
            if !v.is_finite() || *v < 0.0 {
                if v.is_finite() && self.lifted.is_none() {
                    self.lifted = Some(*c);
                }
                *v = 0.0;
                self.resolved = false;
            }
        }
        self.set(f);
        if !self.theta_deg.is_finite() {
            self.theta_deg = 0.0;
            self.resolved = false;
        }
        self
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use docking_logic::profile::forces_at_time;

    fn reference() -> Plant {
        Plant::new(PlantParams::REFERENCE).unwrap()
    }

    #[test]
    fn reproduces_the_reference_table() {
        let p = reference();
        for r in REFERENCE_TABLE {
            let (t, ph, th, f) = (r.t_s, r.phase, r.theta_deg, r.forces_n);
            let pt = p.at_time(t);
            assert_eq!(pt.phase, ph, "t {t}");
            assert!(
                (pt.theta_deg - th).abs() < 1e-3,
                "t {t}: θ {}",
                pt.theta_deg
            );
            for (a, b) in pt.forces().iter().zip(f) {
                // The table has 4 decimals: 5e-5 of rounding, well inside 1e-3 N.
                assert!((a - b).abs() < 1e-3, "t {t}: {:?} vs {f:?}", pt.forces());
            }
            assert_eq!(pt.lifted, None, "t {t}");
            assert!(pt.resolved, "t {t}");
        }
    }

    #[test]
    fn geometric_boundary_is_12_4443_s() {
        let p = Plant::new(PlantParams::PAPER).unwrap();
        let [t1, t2, t3] = p.boundaries_s();
        assert_eq!((t1, t2), (3.75, 7.25));
        assert!((t3 - 12.4443).abs() < 1e-4, "{t3}");
        assert!((PlantParams::PAPER.l_star_mm() - 20.8026).abs() < 1e-4);
        // 0.7 ms earlier than the paper's boundary: the table's phase-4 rows move by
        // less than 0.01 N, and 12.4449 s is already in phase 4.
        assert_eq!(p.at_time(12.4449).phase, 4);
        let r = reference();
        for t in [12.445, 16.0, 20.0, 25.0] {
            let (a, b) = (p.at_time(t), r.at_time(t));
            for (x, y) in a.forces().iter().zip(b.forces()) {
                assert!((x - y).abs() < 0.01, "t {t}");
            }
        }
    }

    #[test]
    fn residuals_against_eq7_are_those_of_the_reference() {
        let p = reference();
        let mut max = [[0.0f64; 4]; 4];
        for k in 0..=2500 {
            let t = k as f64 * 0.01;
            let pt = p.at_time(t);
            let e = forces_at_time(t);
            let d = [
                (pt.n1_n - e.n1_n).abs(),
                (pt.n2_n - e.n2_n).abs(),
                (pt.n3_n - e.n3_n).abs(),
                (pt.n4_n - e.n4_n).abs(),
            ];
            let m = &mut max[pt.phase as usize - 1];
            for (a, b) in m.iter_mut().zip(d) {
                *a = a.max(b);
            }
        }
        for ph in &max[..2] {
            assert!(ph.iter().all(|&x| x <= 0.02), "{max:?}");
        }
        let [n1, n2, n3, _] = max[2];
        assert!(n3 <= 1.71 && n1 <= 4.84 && n2 <= 5.18, "{max:?}");
        assert!(n3 > 1.6 && n1 > 4.7 && n2 > 5.0, "{max:?}");
        let [_, _, n3, n4] = max[3];
        assert!(n3 <= 0.36 && n4 <= 1.11, "{max:?}");
        assert!(n3 > 0.3 && n4 > 1.0, "{max:?}");
    }

    #[test]
    fn tilt_values_of_eq6() {
        let p = reference();
        let th = |t: f64| p.at_time(t).theta_deg;
        assert!((th(16.0) - 1.6537).abs() < 1e-4);
        assert!((th(20.0) - 1.1668).abs() < 1e-4);
        let slow = Plant::new(PlantParams {
            v_model_mm_s: 1.2,
            ..PlantParams::REFERENCE
        })
        .unwrap();
        assert!((slow.at_time(16.0).theta_deg - 2.176).abs() < 1e-3);
        // Newton on G converges in a handful of iterations.
        for k in 0..=1000 {
            let pt = p.at_time(12.445 + k as f64 * 0.02);
            assert!(pt.iterations <= 8, "{pt:?}");
        }
    }

    #[test]
    fn n3_integral_is_3377_1() {
        let p = reference();
        let [b1, b2, b3] = p.boundaries_mm();
        let end = p.params().v_model_mm_s * STROKE_S;
        let mut total = 0.0;
        for (ph, a, b) in [(1, 0.0, b1), (2, b1, b2), (3, b2, b3), (4, b3, end)] {
            let n = 20_000;
            let h = (b - a) / n as f64;
            let mut s = 0.5 * (p.in_phase(ph, a).n3_n + p.in_phase(ph, b).n3_n);
            for k in 1..n {
                s += p.in_phase(ph, a + k as f64 * h).n3_n;
            }
            total += s * h / p.params().v_model_mm_s;
        }
        assert!((total - 3377.1).abs() < 0.05, "{total}");
    }

    #[test]
    fn support_2_lifts_in_phase_2_at_mu2_0_30() {
        let p = Plant::new(PlantParams {
            mu2: 0.30,
            ..PlantParams::PAPER
        })
        .unwrap();
        let raw = p.nominal_forces(p.params().v_model_mm_s * 5.0).unwrap();
        assert!(raw[1] < 0.0, "{raw:?}");
        let pt = p.at_time(5.0);
        assert_eq!(pt.phase, 2);
        assert_eq!(pt.lifted, Some(Contact::Support2));
        assert!(!pt.resolved);
        assert_eq!(pt.n2_n, 0.0);
        assert!(pt.n1_n > 0.0 && pt.n3_n > 0.0);
        // The x and z rows still hold.
        let gam = 15f64.to_radians();
        let x = pt.n1_n - (0.3 * cos(gam) + sin(gam)) * pt.n3_n;
        let z = 0.17 * pt.n1_n + (cos(gam) - 0.3 * sin(gam)) * pt.n3_n - 12.2 * 9.8;
        assert!(x.abs() < 1e-9 && z.abs() < 1e-9);
    }

    #[test]
    fn second_point_lifts_after_25_4_s() {
        let p = reference();
        let before = p.at_time(25.35);
        assert_eq!(before.lifted, None);
        assert!(before.n4_n > 0.0);
        let pt = p.at_time(25.5);
        assert_eq!(pt.phase, 4);
        assert_eq!(pt.lifted, Some(Contact::SecondPoint));
        assert_eq!(pt.n4_n, 0.0);
        assert!(pt.n1_n >= 0.0 && pt.n2_n >= 0.0 && pt.n3_n > 0.0);
        // With the paper's values the single-point form has N2 < 0 too, so the
        // fallback is the force rows, continuous with the two-point solution.
        assert!(!pt.resolved);
        assert_eq!(pt.n2_n, 0.0);
        assert!((pt.n3_n - before.n3_n).abs() < 1.0, "{pt:?} {before:?}");
        for k in 0..200 {
            let q = p.at_time(25.0 + k as f64 * 0.5);
            assert!(
                q.forces().iter().all(|f| f.is_finite() && *f >= 0.0),
                "{q:?}"
            );
        }
    }

    #[test]
    fn single_point_fallback_when_it_holds() {
        // Within the paper's geometry the single-point form always has N2 < 0 once N4
        // lifts; a machine with a longer phase-4 arm (120 mm) and no rod friction keeps
        // support 2 loaded, and the switched system is a full equilibrium.
        let p = Plant::new(PlantParams {
            mu2: 0.0,
            geometry: Geometry {
                p4_l3x0_mm: 120.0,
                ..Geometry::PAPER
            },
            ..PlantParams::PAPER
        })
        .unwrap();
        let t = 12.5;
        let raw = p.nominal_forces(p.params().v_model_mm_s * t).unwrap();
        assert!(raw[3] < 0.0, "{raw:?}");
        let pt = p.at_time(t);
        assert_eq!(
            (pt.phase, pt.lifted, pt.resolved),
            (4, Some(Contact::SecondPoint), true)
        );
        assert!(pt.n1_n > 0.0 && pt.n2_n > 0.0 && pt.n3_n > 0.0 && pt.n4_n == 0.0);
    }

    #[test]
    fn tilt_above_theta0_is_bracketed() {
        // θ0 = 1.5°: L* = 38.5 mm > L0, so the root at the start of phase 4 is above θ0.
        let p = Plant::new(PlantParams {
            theta0_deg: 1.5,
            ..PlantParams::PAPER
        })
        .unwrap();
        let t = p.tilt(0.0);
        assert!(t.bracketed && t.converged);
        assert!(t.theta_rad > 1.5f64.to_radians(), "{t:?}");
        // Every tilt over the validated θ0 range and long travels is bracketed.
        for k in 0..=95 {
            let th0 = 0.5 + k as f64 * 0.1;
            let p = Plant::new(PlantParams {
                theta0_deg: th0,
                ..PlantParams::PAPER
            })
            .unwrap();
            for s4 in [0.0, 0.01, 1.0, 10.0, 100.0, 1000.0, INPUT_MAX] {
                let t = p.tilt(s4);
                assert!(t.bracketed && t.converged, "θ0 {th0}, s4 {s4}: {t:?}");
                assert!(t.theta_rad.is_finite() && t.theta_rad > 0.0);
            }
        }
    }

    #[test]
    fn tilt_iteration_cap_is_respected() {
        let p = reference();
        for cap in 0..6 {
            let t = p.tilt_with(50.0, cap, 0.0);
            assert!(t.iterations <= cap);
            assert!(t.theta_rad > 0.0 && t.theta_rad <= 2.84f64.to_radians());
        }
    }

    #[test]
    fn validation_names_the_parameter() {
        let bad = PlantParams {
            mu2: 0.7,
            ..PlantParams::PAPER
        };
        let e = bad.validate().unwrap_err();
        assert_eq!(e.param, Param::Mu2);
        use std::string::ToString;
        let s = e.to_string();
        assert!(
            s.contains("mu2") && s.contains("0.6") && !s.contains('\n'),
            "{s}"
        );
        for p in [
            PlantParams {
                mass_kg: f64::NAN,
                ..PlantParams::PAPER
            },
            PlantParams {
                theta0_deg: 0.0,
                ..PlantParams::PAPER
            },
            PlantParams {
                t2_s: 3.0,
                ..PlantParams::PAPER
            },
            PlantParams {
                t3_s: Some(7.0),
                ..PlantParams::PAPER
            },
            PlantParams {
                v_model_mm_s: f64::INFINITY,
                ..PlantParams::PAPER
            },
            PlantParams {
                geometry: Geometry {
                    d2_mm: 25.0,
                    ..Geometry::PAPER
                },
                ..PlantParams::PAPER
            },
        ] {
            assert!(Plant::new(p).is_err(), "{p:?}");
        }
    }

    #[test]
    fn odd_inputs_give_finite_points() {
        let p = reference();
        for t in [f64::NAN, -1.0, f64::INFINITY, f64::NEG_INFINITY, 1e300] {
            let pt = p.at_time(t);
            assert!(pt.forces().iter().all(|f| f.is_finite() && *f >= 0.0));
            assert!(pt.theta_deg.is_finite());
        }
        assert_eq!(p.at_time(f64::NAN), p.at_time(0.0));
        assert!(solve3(
            [[1.0, 2.0, 3.0], [2.0, 4.0, 6.0], [0.0, 1.0, 1.0]],
            [0.0, 1.0, 0.0]
        )
        .is_none());
    }
}
