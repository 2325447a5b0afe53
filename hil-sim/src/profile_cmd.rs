//! `hil-sim profile`: the Eq. 7 contact-force profile over one stroke, as CSV.
//!
//! Insertion: `t_s` from the start of compliant contact, forces at depth `v0·t`.
//! Extraction is the mirror: at extraction time `t` the panel is at the insertion
//! depth of `25 − t`, and the forces are those of that depth.
//!
//! `--model plant` prints the equilibrium systems of `crate::plant` instead
//! of Eq. 7 (same columns plus `theta_deg`), with the paper's parameters unless
//! `--mass-kg`, `--mu1`, `--mu2`, `--gamma-deg`, `--theta0-deg`, `--v-model` (the travel
//! per second of Eq. 7's time axis, default 4 mm/s) or `--t3-s` (the phase 3→4 boundary;
//! default from the geometry, 12.4443 s; the paper's 12.445 reproduces the table of
//! `docs/physics.md` §8.4) say otherwise.

use std::io::Write;

use crate::plant::{Contact, Param, Plant, PlantParams};
use docking_logic::profile::{forces_at_time, ContactPhase, STROKE_S};

use crate::cli::{Opts, UsageError};

/// Which stroke to print.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stroke {
    /// Insertion, depth increasing.
    Insert,
    /// Extraction, depth decreasing.
    Extract,
}

/// CSV header.
pub const HEADER: &str = "t_s,phase,n1_n,n2_n,n3_n,n4_n";

/// One profile row: (t_s, phase, forces) for sample `k` at `rate_hz`.
pub fn row(
    k: u64,
    rate_hz: f64,
    stroke: Stroke,
) -> (f64, ContactPhase, docking_logic::profile::Forces) {
    let t = k as f64 / rate_hz;
    let t_ins = match stroke {
        Stroke::Insert => t,
        Stroke::Extract => STROKE_S - t,
    };
    (t, ContactPhase::at_time(t_ins), forces_at_time(t_ins))
}

/// Number of samples in `[0, 25]` s at `rate_hz`.
pub fn sample_count(rate_hz: f64) -> u64 {
    (STROKE_S * rate_hz).floor() as u64 + 1
}

/// Write the CSV to `out`.
pub fn write_csv(out: &mut impl Write, rate_hz: f64, stroke: Stroke) -> std::io::Result<()> {
    writeln!(out, "{HEADER}")?;
    for k in 0..sample_count(rate_hz) {
        let (t, phase, f) = row(k, rate_hz, stroke);
        writeln!(
            out,
            "{:.6},{},{:.4},{:.4},{:.4},{:.4}",
            t,
            phase.number(),
            f.n1_n,
            f.n2_n,
            f.n3_n,
            f.n4_n
        )?;
    }
    Ok(())
}

/// Which force model `profile` prints.
#[derive(Clone, Copy, Debug, PartialEq)]
// One per command run: boxing the plant would buy nothing.
#[allow(clippy::large_enum_variant)]
pub enum Model {
    /// Eq. 7 as printed (`logic/src/control/profile.rs`), the default.
    Eq7,
    /// The equilibrium systems of Eqs. 3–6 (`hil-sim/src/plant.rs`).
    Plant(Plant),
}

/// Options of `profile` that only `--model plant` takes, with the plant field each sets.
pub const PLANT_OPTIONS: [(&str, Param); 7] = [
    ("mass-kg", Param::MassKg),
    ("mu1", Param::Mu1),
    ("mu2", Param::Mu2),
    ("gamma-deg", Param::GammaDeg),
    ("theta0-deg", Param::Theta0Deg),
    ("v-model", Param::VModel),
    ("t3-s", Param::T3),
];

/// Every option name of `profile` (for `Opts::parse`), besides `rate`, `stroke`, `plot`.
pub const MODEL_OPTIONS: [&str; 8] = [
    "model",
    "mass-kg",
    "mu1",
    "mu2",
    "gamma-deg",
    "theta0-deg",
    "v-model",
    "t3-s",
];

/// The model chosen by `--model eq7|plant` and the plant's options: plant-only options
/// with Eq. 7, unparsable numbers and out-of-range parameters are usage errors naming
/// the option and its range.
pub fn model(o: &Opts) -> Result<Model, UsageError> {
    let plant = match o.get("model") {
        None | Some("eq7") => false,
        Some("plant") => true,
        Some(m) => {
            return Err(UsageError(format!(
                "--model must be 'eq7' or 'plant', got '{m}'"
            )))
        }
    };
    if !plant {
        if let Some((name, _)) = PLANT_OPTIONS.iter().find(|(n, _)| o.get(n).is_some()) {
            return Err(UsageError(format!(
                "--{name} is an option of the plant model: add --model plant"
            )));
        }
        return Ok(Model::Eq7);
    }
    let mut p = PlantParams::PAPER;
    for (name, param) in PLANT_OPTIONS {
        let Some(v) = o.get(name) else { continue };
        let x = match v.trim().parse::<f64>() {
            Ok(x) if x.is_finite() => x,
            _ => return Err(UsageError(format!("--{name} must be a number, got '{v}'"))),
        };
        match param {
            Param::MassKg => p.mass_kg = x,
            Param::Mu1 => p.mu1 = x,
            Param::Mu2 => p.mu2 = x,
            Param::GammaDeg => p.gamma_deg = x,
            Param::Theta0Deg => p.theta0_deg = x,
            Param::VModel => p.v_model_mm_s = x,
            _ => p.t3_s = Some(x),
        }
    }
    Plant::new(p).map(Model::Plant).map_err(|e| {
        let flag = PLANT_OPTIONS
            .iter()
            .find(|(_, q)| *q == e.param)
            .map_or(e.param.name(), |(n, _)| n);
        UsageError(format!(
            "--{flag} must be a number from {} to {}, got '{}'",
            e.min,
            e.max,
            o.get(flag).unwrap_or_default()
        ))
    })
}

/// CSV header of the plant.
pub const PLANT_HEADER: &str = "t_s,phase,n1_n,n2_n,n3_n,n4_n,theta_deg";

/// What the plant reported over one printed stroke.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PlantSummary {
    /// Rows printed.
    pub rows: u64,
    /// Rows with a lift-off, by contact (N1–N4).
    pub lifted: [u64; 4],
    /// Rows whose forces do not satisfy all three equilibrium rows.
    pub unresolved: u64,
    /// First and last row with a lift-off or an unresolved state, (t_s) × 1e6 rounded.
    pub first_last_us: Option<(u64, u64)>,
}

/// Write the plant's CSV (Eq. 7's columns plus `theta_deg`) to `out`: sample `k` at
/// `t = k/rate`, the insertion time being `t` or `25 − t` (extraction).
pub fn write_plant_csv(
    out: &mut impl Write,
    plant: &Plant,
    rate_hz: f64,
    stroke: Stroke,
) -> std::io::Result<PlantSummary> {
    writeln!(out, "{PLANT_HEADER}")?;
    let mut sum = PlantSummary::default();
    for k in 0..sample_count(rate_hz) {
        let t = k as f64 / rate_hz;
        let t_ins = match stroke {
            Stroke::Insert => t,
            Stroke::Extract => STROKE_S - t,
        };
        let p = plant.at_time(t_ins);
        writeln!(
            out,
            "{:.6},{},{:.4},{:.4},{:.4},{:.4},{:.4}",
            t, p.phase, p.n1_n, p.n2_n, p.n3_n, p.n4_n, p.theta_deg
        )?;
        sum.rows += 1;
        if let Some(c) = p.lifted {
            if let Some(n) = sum.lifted.get_mut(c.index()) {
                *n += 1;
            }
        }
        if !p.resolved {
            sum.unresolved += 1;
        }
        if p.lifted.is_some() || !p.resolved {
            let us = (t * 1e6).round() as u64;
            sum.first_last_us = Some(match sum.first_last_us {
                None => (us, us),
                Some((a, _)) => (a, us),
            });
        }
    }
    Ok(sum)
}

impl PlantSummary {
    /// One line for stderr when a contact lifted off or a state was unresolved, else
    /// `None`.
    pub fn note(&self) -> Option<String> {
        let (a, b) = self.first_last_us?;
        let lifted: Vec<String> = Contact::ALL
            .iter()
            .zip(self.lifted)
            .filter(|(_, n)| *n > 0)
            .map(|(c, n)| format!("{} lifted off in {n} rows", c.name()))
            .collect();
        Some(format!(
            "note: plant contact set switched between t = {:.6} and {:.6} s: {}; {} of {} rows unresolved (moment unbalanced or a force clamped to 0)",
            a as f64 / 1e6,
            b as f64 / 1e6,
            if lifted.is_empty() {
                "no lift-off".to_string()
            } else {
                lifted.join(", ")
            },
            self.unresolved,
            self.rows
        ))
    }
}
