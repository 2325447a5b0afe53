//! `hil-sim profile`: the Eq. 7 contact-force profile over one stroke, as CSV.
//!
//! Insertion: `t_s` from the start of compliant contact, forces at depth `v0·t`.
//! Extraction is the mirror: at extraction time `t` the panel is at the insertion
//! depth of `25 − t`, and the forces are those of that depth.

use std::io::Write;

use docking_controller::profile::{forces_at_time, ContactPhase, STROKE_S};

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
) -> (f64, ContactPhase, docking_controller::profile::Forces) {
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
