//! Another machine: its contact forces from the quasi-static plant
//! ([`crate::plant`]) and the controller configuration that matches it.
//!
//! # Where the configuration comes from: commissioning, on the host
//!
//! The guard's envelope, the hold force and the odometer's nominal load–distance follow
//! from the machine's parameters (mass, friction coefficients, chamfer, tilt). They are
//! computed **on the host at commissioning** ([`Tuning::for_plant`]) and given to the
//! controller as its configuration; the firmware never evaluates the plant (no floating
//! point trigonometry, no root finder, no flash for them on the board — it carries
//! tables). The paper's machine is the build's default (Eq. 7's table, computed at build
//! time). Another machine's board is built with the tables this module computes:
//! `hil-sim commission --model plant … > tuning.rs`, then
//! `DOCKING_TUNING=tuning.rs cargo build --release --target thumbv7em-none-eabihf`
//! (`build.rs` includes the file; the board applies it before the controller starts).
//! The host rig uses the same [`Tuning`] directly.
//!
//! # The margin
//!
//! Friction coefficients are the least known parameters and µ2 moves the phase-4 peak
//! most (155–289 N over µ2 0.30–0.05, `docs/physics.md` §8.2). The envelope's nominal profile is
//! the **largest N3 over µ1 ± [`MU_SPREAD`] and µ2 ± [`MU_SPREAD`]** (a 3 × 3 grid, at
//! every 10 µm of depth and at both sides of each phase boundary), and the guard then adds
//! its usual margins (×1.25 + 30 N). The hard limit follows the envelope's peak (never
//! below the default 300 N, never above the load cell's rating [`CELL_RATED_MN`]); a
//! machine whose nominal peak, spread included, comes within the absolute margin (30 N)
//! of the rating gets an error, not a guard that cannot trip.
//!
//! # Depth and time
//!
//! The controller tracks insertion depth; the plant is evaluated on Eq. 7's time axis at
//! `t = depth / v0` (v0 = 1.2 mm/s, the same mapping as Eq. 7's profile everywhere in
//! this code), with its own travel per second of that axis (`--v-model`) inside.

use crate::plant::{Plant, PlantError, PlantParams};
use docking_logic::controller::ControllerConfig;
use docking_logic::guard::{GuardConfig, NominalProfile};
use docking_logic::profile::{forces_at_depth_um, STROKE_UM, V0_UM_PER_S};
use docking_logic::signature::objects::{NominalCurve, SignatureConfig};

/// The spread of µ1 and µ2 the envelope covers, ±.
pub const MU_SPREAD: f64 = 0.02;
/// The load cell's rating, mN (500 N): no hard limit above it.
pub const CELL_RATED_MN: i32 = 500_000;

/// Where the rig's contact force comes from.
// A plant is ~450 bytes (its geometry); a rig holds one model, so boxing buys nothing.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Copy, Debug)]
pub enum ForceModel {
    /// Eq. 7, the paper's machine.
    Eq7,
    /// The quasi-static plant with these parameters.
    Plant(Plant),
}

impl ForceModel {
    /// The plant for `params`, or why not.
    pub fn plant(params: PlantParams) -> Result<Self, PlantError> {
        Plant::new(params).map(Self::Plant)
    }

    /// Nominal N3 at insertion depth `depth_um` (clamped to the stroke), N.
    pub fn n3_at_depth_um(&self, depth_um: f64) -> f64 {
        let d = depth_um.clamp(0.0, STROKE_UM as f64);
        match self {
            Self::Eq7 => forces_at_depth_um(d).n3_n,
            Self::Plant(p) => p.at_time(d / V0_UM_PER_S as f64).n3_n,
        }
    }

    /// The depths (µm) where N3 jumps: the phase boundaries.
    pub fn jumps_um(&self) -> [i32; 3] {
        match self {
            Self::Eq7 => docking_logic::profile::BOUNDARY_UM,
            Self::Plant(p) => p
                .boundaries_s()
                .map(|t| (t * V0_UM_PER_S as f64).round().clamp(0.0, 1e9) as i32),
        }
    }
}

/// Why a machine cannot be configured.
#[derive(Clone, Debug, PartialEq)]
pub enum ConfigError {
    /// A plant parameter out of range.
    Plant(PlantError),
    /// The nominal peak plus the absolute margin is above the load cell's rating, mN.
    BeyondCell(i32),
}

impl core::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Plant(e) => write!(f, "{e}"),
            Self::BeyondCell(mn) => write!(
                f,
                "this machine's nominal peak needs {:.1} N with its margin, above the load cell's {:.0} N rating",
                *mn as f64 / 1000.0,
                CELL_RATED_MN as f64 / 1000.0
            ),
        }
    }
}

/// The nominal load–distance of one cycle (insertion and extraction over the stroke) of
/// `model`, Q63.1 mN·µm: 2 × ∫ N3 d(depth), by the midpoint rule at 10 µm.
pub fn nominal_cycle_w_q1(model: &ForceModel) -> u64 {
    let step = 10.0;
    let n = (STROKE_UM as f64 / step) as u32;
    let stroke_mn_um: f64 = (0..n)
        .map(|k| model.n3_at_depth_um((k as f64 + 0.5) * step) * 1000.0 * step)
        .sum();
    // Two strokes, ×2 for Q63.1.
    (4.0 * stroke_mn_um).round().max(1.0) as u64
}

/// The docking signature's evaluation objects for `model` (the machine at its own
/// frictions: the objects' bands carry the spread): the nominal curve on the grid, and
/// how much deeper its 3→4 step lies per mm of bore wear (the wear estimate's slope),
/// measured on the plant itself: its boundary at D2 and at D2 + 0.1 mm. Eq. 7's are the
/// build's ([`SignatureConfig::DEFAULT`]).
pub fn signature_for(model: &ForceModel) -> SignatureConfig {
    let ForceModel::Plant(plant) = model else {
        return SignatureConfig::DEFAULT;
    };
    // The first µm of each phase (`from_fn` takes the step's force halfway between the
    // µm before the boundary and the boundary's own: rounded to the nearer µm, a
    // boundary at 14 933.2 µm put both in phase 3, and the step was searched for at
    // phase 3's force).
    let first_um = plant
        .boundaries_s()
        .map(|t| (t * f64::from(V0_UM_PER_S)).ceil().clamp(0.0, 1e9) as i32);
    let curve = NominalCurve::from_fn(|d| model.n3_at_depth_um(f64::from(d)), first_um);
    let p = *plant.params();
    let mut worn = p;
    worn.geometry.d2_mm += 0.1;
    let step_s = |q: PlantParams| Plant::new(q).map_or(f64::NAN, |pl| pl.boundaries_s()[2]);
    // s per 0.1 mm of wear × v0 (µm/s) × 10 = µm of depth per mm of wear.
    let slope = (step_s(worn) - step_s(p)) * f64::from(V0_UM_PER_S) * 10.0;
    SignatureConfig {
        // Commissioning runs once per machine: the curve lives as long as the program.
        nominal: Box::leak(Box::new(curve)),
        step_um_per_wear_mm: if slope.is_finite() && slope > 0.0 {
            slope.round().min(f64::from(u32::MAX)) as u32
        } else {
            0
        },
        ..SignatureConfig::DEFAULT
    }
}

/// What commissioning sets for a machine: the guard (its nominal profile and hard
/// limit), the odometer's nominal load–distance, the hold force, the docking
/// signature's nominal curve and the wear estimate's slope.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Tuning {
    /// The guard's configuration.
    pub guard: GuardConfig,
    /// Nominal load–distance per cycle, Q63.1 mN·µm.
    pub nominal_w_q1: u64,
    /// Mated contact force, mN.
    pub hold_expected_mn: i32,
    /// The docking signature's objects: the machine's nominal curve and its step's
    /// slope against wear ([`signature_for`]; the other settings the defaults).
    pub signature: SignatureConfig,
}

impl Tuning {
    /// The machine of `params`: the guard's nominal profile with the µ spread (and the
    /// default guard's margins), its hard limit, the hold force and the nominal
    /// load–distance.
    pub fn for_plant(params: PlantParams) -> Result<Self, ConfigError> {
        let nominal = ForceModel::plant(params).map_err(ConfigError::Plant)?;
        let mut spread = Vec::new();
        for d1 in [-MU_SPREAD, 0.0, MU_SPREAD] {
            for d2 in [-MU_SPREAD, 0.0, MU_SPREAD] {
                let p = PlantParams {
                    mu1: (params.mu1 + d1).max(0.0),
                    mu2: (params.mu2 + d2).max(0.0),
                    ..params
                };
                spread.push(ForceModel::plant(p).map_err(ConfigError::Plant)?);
            }
        }
        let jumps: Vec<i32> = spread.iter().flat_map(|m| m.jumps_um()).collect();
        let profile = NominalProfile::from_fn(
            |d| {
                spread
                    .iter()
                    .map(|m| m.n3_at_depth_um(d as f64))
                    .fold(0.0, f64::max)
            },
            &jumps,
        );
        let g = GuardConfig::DEFAULT;
        let peak = profile.peak_mn() as i64;
        // The envelope's own peak, capped at the cell's rating; a machine whose nominal
        // peak (spread included) leaves less than the absolute margin below the rating
        // cannot be protected by this cell.
        if peak + g.abs_mn as i64 > CELL_RATED_MN as i64 {
            return Err(ConfigError::BeyondCell((peak + g.abs_mn as i64) as i32));
        }
        let needed = (peak * (100 + g.rel_pct as i64) / 100 + g.abs_mn as i64) as i32;
        let hard = needed.clamp(g.hard_limit_mn, CELL_RATED_MN);
        Ok(Self {
            guard: GuardConfig {
                hard_limit_mn: hard,
                // Commissioning runs once per machine: the table lives as long as the
                // program.
                nominal: Box::leak(Box::new(profile)),
                ..g
            },
            nominal_w_q1: nominal_cycle_w_q1(&nominal),
            hold_expected_mn: (nominal.n3_at_depth_um(STROKE_UM as f64) * 1000.0).round() as i32,
            signature: signature_for(&nominal),
        })
    }

    /// The machine-specific part of `cfg`.
    pub fn of(cfg: &ControllerConfig) -> Self {
        Self {
            guard: cfg.guard,
            nominal_w_q1: cfg.wear.nominal_w_q1,
            hold_expected_mn: cfg.hold_expected_mn,
            signature: cfg.signature,
        }
    }

    /// The tuning as Rust source for the firmware's build (`DOCKING_TUNING=FILE cargo
    /// build --release --target thumbv7em-none-eabihf`, see `build.rs`): the guard's
    /// `static` nominal profile, the signature's nominal curve, and a function `apply`
    /// that sets the machine-specific fields. `origin` goes into the file's header (the
    /// parameters it was made from).
    pub fn to_rust(&self, origin: &str) -> String {
        let rows = |v: &[i16]| -> String {
            v.chunks(16)
                .map(|c| {
                    let v: Vec<String> = c.iter().map(|x| x.to_string()).collect();
                    format!("            {},", v.join(", "))
                })
                .collect::<Vec<_>>()
                .join("\n")
        };
        let n = self.signature.nominal;
        let b = n.boundaries_um;
        let curve = format!(
            "/// The docking signature's nominal curve (dN a bin: its mean, and its minimum and\n\
             /// maximum over the bin ± the position tolerance): what the evaluation objects sit on.\n\
             static SIG_NOMINAL: docking_logic::signature::objects::NominalCurve =\n    \
             docking_logic::signature::objects::NominalCurve {{\n        \
             mean_dn: [\n{}\n        ],\n        min_dn: [\n{}\n        ],\n        \
             max_dn: [\n{}\n        ],\n        boundaries_um: [{}, {}, {}],\n        \
             step_dn: {},\n    }};\n\n",
            rows(&n.mean_dn),
            rows(&n.min_dn),
            rows(&n.max_dn),
            b[0],
            b[1],
            b[2],
            n.step_dn,
        );
        let table: Vec<String> = self
            .guard
            .nominal
            .n3_max_mn
            .chunks(10)
            .map(|c| {
                let v: Vec<String> = c.iter().map(|x| x.to_string()).collect();
                format!("        {},", v.join(", "))
            })
            .collect();
        format!(
            "// Generated by `hil-sim commission` ({origin}); do not edit.\n\
             // The machine's tuning, included by the firmware's build (DOCKING_TUNING).\n\
             static NOMINAL: docking_logic::guard::NominalProfile =\n    \
             docking_logic::guard::NominalProfile {{\n    n3_max_mn: [\n{}\n    ],\n}};\n\n\
             {curve}\
             /// Set the machine-specific fields of `cfg`.\n\
             pub fn apply(cfg: &mut docking_logic::controller::ControllerConfig) {{\n    \
             cfg.guard.nominal = &NOMINAL;\n    \
             cfg.guard.hard_limit_mn = {};\n    \
             cfg.wear.nominal_w_q1 = {};\n    \
             cfg.hold_expected_mn = {};\n    \
             cfg.signature.nominal = &SIG_NOMINAL;\n    \
             cfg.signature.step_um_per_wear_mm = {};\n}}\n",
            table.join("\n"),
            self.guard.hard_limit_mn,
            self.nominal_w_q1,
            self.hold_expected_mn,
            self.signature.step_um_per_wear_mm,
        )
    }

    /// Apply to `cfg` (as the generated `apply` does: of the signature's settings, the
    /// nominal curve and the step's slope).
    pub fn apply(&self, cfg: &mut ControllerConfig) {
        cfg.guard = self.guard;
        cfg.wear.nominal_w_q1 = self.nominal_w_q1;
        cfg.hold_expected_mn = self.hold_expected_mn;
        cfg.signature.nominal = self.signature.nominal;
        cfg.signature.step_um_per_wear_mm = self.signature.step_um_per_wear_mm;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use docking_logic::odometer::W_NOM_Q1;

    #[test]
    fn eq7s_nominal_cycle_is_the_odometers_constant() {
        let w = nominal_cycle_w_q1(&ForceModel::Eq7) as f64;
        assert!(
            (w / W_NOM_Q1 as f64 - 1.0).abs() < 1e-4,
            "{w} vs {W_NOM_Q1}"
        );
    }

    #[test]
    fn the_paper_machine_matches_todays_configuration_within_the_residuals() {
        let cfg = Tuning::for_plant(PlantParams::PAPER).unwrap();
        // Within the µ spread's reach of Eq. 7, and never below it by more than the
        // plant's residual (phase 3: 1.7 N).
        for (i, (&m, &e)) in cfg
            .guard
            .nominal
            .n3_max_mn
            .iter()
            .zip(docking_logic::guard::EQ7_NOMINAL.n3_max_mn.iter())
            .enumerate()
        {
            assert!(m >= e - 1_800, "cell {i}: {m} < {e}");
            assert!(m <= e + 40_000, "cell {i}: {m} ≫ {e}");
        }
        // The µ spread lifts the phase-4 peak by ≈ 14 N: the hard limit follows a little.
        assert!((300_000..=310_000).contains(&cfg.guard.hard_limit_mn));
        let w = cfg.nominal_w_q1 as f64 / W_NOM_Q1 as f64;
        assert!((w - 1.0).abs() < 0.01, "{w}");
        assert!(
            (cfg.hold_expected_mn - 125_098).abs() < 1_000,
            "{}",
            cfg.hold_expected_mn
        );
    }

    /// The signature's objects from the plant (issue 34): the paper's machine's are
    /// Eq. 7's within the plant's residuals, its step's force between phase 3's and
    /// phase 4's, and its step's slope against wear the geometry's constant.
    #[test]
    fn the_paper_machines_commissioned_objects_are_eq7s_within_the_residuals() {
        let sig = Tuning::for_plant(PlantParams::PAPER).unwrap().signature;
        let (n, e) = (sig.nominal, &docking_logic::signature::objects::EQ7_CURVE);
        assert_eq!(n.boundaries_um, e.boundaries_um);
        // Eq. 7's step at 1 567 dN; the plant's phase 3 is 1.7 N off (§8.5).
        assert!((i32::from(n.step_dn) - 1_567).abs() <= 10, "{}", n.step_dn);
        for (i, (a, b)) in n.mean_dn.iter().zip(e.mean_dn.iter()).enumerate() {
            assert!((a - b).abs() <= 20, "bin {i}: {a} against Eq. 7's {b}");
        }
        assert_eq!(
            sig.step_um_per_wear_mm,
            docking_logic::profile::STEP_UM_PER_WEAR_MM
        );
        // The same settings as the build's, but the curve and the slope.
        assert_eq!(
            SignatureConfig { nominal: e, ..sig },
            SignatureConfig::DEFAULT
        );
    }

    #[test]
    fn a_heavier_machine_gets_a_higher_envelope_and_a_machine_beyond_the_cell_an_error() {
        let heavy = PlantParams {
            mass_kg: 18.0,
            mu2: 0.1,
            ..PlantParams::PAPER
        };
        let cfg = Tuning::for_plant(heavy).unwrap();
        assert!(
            cfg.guard.nominal.peak_mn() > 300_000,
            "{}",
            cfg.guard.nominal.peak_mn()
        );
        assert!(cfg.guard.hard_limit_mn > 300_000);
        assert!(cfg.nominal_w_q1 > W_NOM_Q1);
        let beyond = PlantParams {
            mass_kg: 40.0,
            mu2: 0.05,
            ..PlantParams::PAPER
        };
        assert!(matches!(
            Tuning::for_plant(beyond),
            Err(ConfigError::BeyondCell(_))
        ));
    }
}
