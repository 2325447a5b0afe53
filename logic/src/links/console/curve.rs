//! `curve [last|ref|nok N] [--json|--csv]`: a docking's force–position curve, as a
//! compact table, one JSON line (what `hil-sim plot-curve` draws) or CSV for a
//! spreadsheet (docs/console.md lists the fields). Written from a [`CurveView`] after
//! the controller is released, like every report.
//!
//! Forces in N with one decimal (the curve is kept in 0.1 N), depths in mm; an empty
//! bin is `null` in JSON and an empty field in CSV.

use core::fmt;

use super::json::{write_fixed, write_str_escaped, write_u64, Sink};
use super::parse::CurveFormat;
use crate::signature::grid::{lo_um, BINS};
use crate::signature::objects::{Failure, Unit, POS_TOL_UM};
use crate::signature::records::{StoredCurve, EMPTY_DN};
use crate::signature::view::{CurveView, Judgement, Which};

/// Write `v` as `format`.
pub(super) fn render(o: &mut dyn Sink, v: &CurveView, format: CurveFormat) -> fmt::Result {
    match format {
        CurveFormat::Json => json(o, v),
        CurveFormat::Csv => csv(o, v),
        CurveFormat::Text => text(o, v),
    }
}

/// dN as N with one decimal; empty: `null` (or `empty` in CSV).
fn dn(o: &mut dyn Sink, v: i16, empty: &str) -> fmt::Result {
    if v == EMPTY_DN {
        o.put(empty)
    } else {
        write_fixed(o, i64::from(v), 1)
    }
}

/// µm as mm with three decimals.
fn mm(o: &mut dyn Sink, um: i32) -> fmt::Result {
    write_fixed(o, i64::from(um), 3)
}

/// mN as N with one decimal (rounded).
fn newtons(o: &mut dyn Sink, mn: i32) -> fmt::Result {
    let mn = i64::from(mn);
    write_fixed(o, (mn + if mn >= 0 { 50 } else { -50 }) / 100, 1)
}

fn which_name(w: Which) -> &'static str {
    match w {
        Which::Last => "last",
        Which::Reference => "ref",
        Which::Nok(_) => "nok",
    }
}

/// A failure's figure or limit in its unit (N or mm).
fn figure(o: &mut dyn Sink, f: &Failure, v: i32) -> fmt::Result {
    if v == i32::MIN {
        return o.put("null");
    }
    match f.unit {
        Unit::Mn => newtons(o, v),
        Unit::Um => mm(o, v),
    }
}

/// `"key":[v, v, …]` of the 128 bins.
fn array(
    o: &mut dyn Sink,
    key: &str,
    f: &mut dyn FnMut(&mut dyn Sink, usize) -> fmt::Result,
) -> fmt::Result {
    o.put(",\"")?;
    o.put(key)?;
    o.put("\":[")?;
    for i in 0..BINS {
        if i > 0 {
            o.put(",")?;
        }
        f(o, i)?;
    }
    o.put("]")
}

fn stroke_json(o: &mut dyn Sink, key: &str, c: &StoredCurve, j: Judgement) -> fmt::Result {
    o.put(",\"")?;
    o.put(key)?;
    o.put("\":{\"verdict\":")?;
    let fail = match j {
        Judgement::None => {
            o.put("null")?;
            None
        }
        Judgement::Ok => {
            o.put("\"ok\"")?;
            None
        }
        Judgement::Nok(f) => {
            o.put("\"nok\"")?;
            f
        }
    };
    o.put(",\"failed\":")?;
    match fail {
        Some(f) => {
            write_str_escaped(o, f.object.name())?;
            o.put(",\"figure\":")?;
            figure(o, &f, f.figure)?;
            o.put(",\"limit\":")?;
            figure(o, &f, f.limit)?;
            o.put(",\"unit\":")?;
            o.put(if f.unit == Unit::Um {
                "\"mm\""
            } else {
                "\"n\""
            })?;
            o.put(",\"at_mm\":")?;
            mm(o, f.depth_um)?;
        }
        None => o.put("null")?,
    }
    o.put(",")?;
    // (array() writes its own leading comma: take it back by writing the key here.)
    o.put("\"mean_n\":[")?;
    for i in 0..BINS {
        if i > 0 {
            o.put(",")?;
        }
        dn(o, c.mean_dn.get(i).copied().unwrap_or(EMPTY_DN), "null")?;
    }
    o.put("]")?;
    array(o, "peak_n", &mut |o, i| {
        dn(o, c.peak_dn.get(i).copied().unwrap_or(EMPTY_DN), "null")
    })?;
    array(o, "count", &mut |o, i| {
        write_u64(o, u64::from(c.count.get(i).copied().unwrap_or(0)))
    })?;
    o.put("}")
}

fn json(o: &mut dyn Sink, v: &CurveView) -> fmt::Result {
    let cfg = &v.cfg;
    let n = cfg.nominal;
    o.put("{\"curve\":")?;
    write_str_escaped(o, which_name(v.which))?;
    if let Which::Nok(k) = v.which {
        o.put(",\"nok\":")?;
        write_u64(o, u64::from(k))?;
    }
    o.put(",\"cycle\":")?;
    write_u64(o, u64::from(v.cycle))?;
    o.put(",\"reference_dockings\":")?;
    write_u64(o, u64::from(v.reference_n))?;
    o.put(",\"bins\":")?;
    write_u64(o, BINS as u64)?;
    o.put(",\"stroke_mm\":")?;
    mm(o, lo_um(BINS))?;
    o.put(",\"phases_mm\":[")?;
    for (k, b) in n.boundaries_um.iter().enumerate() {
        if k > 0 {
            o.put(",")?;
        }
        mm(o, *b)?;
    }
    o.put("]")?;
    let [ins, ext] = &v.curves;
    stroke_json(o, "insertion", ins, v.verdicts[0])?;
    stroke_json(o, "extraction", ext, v.verdicts[1])?;
    o.put(",\"figures\":")?;
    match &v.summary {
        None => o.put("null")?,
        Some(s) => {
            o.put("{\"work_nmm\":")?;
            write_fixed(o, i64::from(s.work_mnmm), 3)?;
            o.put(",\"plateau_n\":")?;
            newtons(o, s.plateau_mn)?;
            o.put(",\"step_mm\":")?;
            match s.step_um {
                Some(x) => mm(o, x)?,
                None => o.put("null")?,
            }
            o.put(",\"end_n\":")?;
            newtons(o, s.end_mn)?;
            o.put(",\"ext_peak_n\":")?;
            newtons(o, s.ext_peak_mn)?;
            for (key, d) in [
                ("drift_work_pct", s.drift_work_pm),
                ("drift_plateau_pct", s.drift_plateau_pm),
            ] {
                o.put(",\"")?;
                o.put(key)?;
                o.put("\":")?;
                match d {
                    Some(x) => write_fixed(o, i64::from(x), 1)?,
                    None => o.put("null")?,
                }
            }
            o.put("}")?;
        }
    }
    // The objects, as a plot draws them: a band per bin, then the boxes.
    o.put(",\"objects\":{\"band_low_n\":[")?;
    for i in 0..BINS {
        if i > 0 {
            o.put(",")?;
        }
        newtons(o, cfg.band_moved_mn(i, v.shift).0)?;
    }
    o.put("]")?;
    array(o, "band_high_n", &mut |o, i| {
        newtons(o, cfg.band_moved_mn(i, v.shift).1)
    })?;
    o.put(",\"entry\":{\"to_mm\":")?;
    mm(o, cfg.entry_max_um)?;
    o.put(",\"force_n\":")?;
    dn(o, cfg.entry_dn(), "null")?;
    let bins = cfg.plateau_bins_moved(v.shift).0;
    let pn = cfg.plateau_nominal_moved_mn(v.shift);
    let pt = pn.abs() * i32::from(cfg.plateau_pct) / 100;
    o.put("},\"plateau\":{\"from_mm\":")?;
    mm(o, lo_um(bins.start))?;
    o.put(",\"to_mm\":")?;
    mm(o, lo_um(bins.end))?;
    o.put(",\"low_n\":")?;
    newtons(o, pn - pt)?;
    o.put(",\"high_n\":")?;
    newtons(o, pn + pt)?;
    let en = cfg.end_nominal_moved_mn(v.shift);
    let et = en.abs() * i32::from(cfg.end_pct) / 100 + cfg.end_abs_mn;
    o.put("},\"end\":{\"from_mm\":")?;
    mm(o, lo_um(BINS - 1))?;
    o.put(",\"to_mm\":")?;
    mm(o, lo_um(BINS))?;
    o.put(",\"low_n\":")?;
    newtons(o, en - et)?;
    o.put(",\"high_n\":")?;
    newtons(o, en + et)?;
    let (pk, at) = cfg.peak_nominal();
    let at = at + lo_um(v.shift);
    let kt = pk.abs() * i32::from(cfg.peak_pct) / 100 + cfg.peak_abs_mn;
    o.put("},\"ext_peak\":{\"from_mm\":")?;
    mm(o, at - cfg.peak_pos_um)?;
    o.put(",\"to_mm\":")?;
    mm(o, at + cfg.peak_pos_um)?;
    o.put(",\"low_n\":")?;
    newtons(o, pk - kt)?;
    o.put(",\"high_n\":")?;
    newtons(o, pk + kt)?;
    o.put("},\"position_tolerance_mm\":")?;
    mm(o, POS_TOL_UM)?;
    o.put("}}\r\n")
}

fn csv(o: &mut dyn Sink, v: &CurveView) -> fmt::Result {
    // (A bin's end is the next one's start: 6.7 KiB in all, within the 8 KiB output ring.)
    o.put("depth_mm,phase,ins_mean_n,ins_peak_n,ins_count,ext_mean_n,ext_peak_n,ext_count,band_low_n,band_high_n\r\n")?;
    let [ins, ext] = &v.curves;
    for i in 0..BINS {
        mm(o, lo_um(i))?;
        o.put(",")?;
        write_u64(o, u64::from(v.cfg.nominal.phase_of(i)))?;
        for c in [ins, ext] {
            o.put(",")?;
            dn(o, c.mean_dn.get(i).copied().unwrap_or(EMPTY_DN), "")?;
            o.put(",")?;
            dn(o, c.peak_dn.get(i).copied().unwrap_or(EMPTY_DN), "")?;
            o.put(",")?;
            write_u64(o, u64::from(c.count.get(i).copied().unwrap_or(0)))?;
        }
        let (lo, hi) = v.cfg.band_moved_mn(i, v.shift);
        o.put(",")?;
        newtons(o, lo)?;
        o.put(",")?;
        newtons(o, hi)?;
        o.put("\r\n")?;
    }
    Ok(())
}

/// Bins a text row covers.
const ROW: usize = 4;

fn verdict_text(o: &mut dyn Sink, name: &str, j: Judgement) -> fmt::Result {
    o.put(name)?;
    match j {
        Judgement::None => o.put(" not judged"),
        Judgement::Ok => o.put(" ok"),
        Judgement::Nok(None) => o.put(" nok"),
        Judgement::Nok(Some(f)) => {
            o.put(" nok ")?;
            o.put(f.object.name())?;
            o.put(" (")?;
            figure(o, &f, f.figure)?;
            o.put(if f.figure > f.limit { " > " } else { " < " })?;
            figure(o, &f, f.limit)?;
            o.put(if f.unit == Unit::Um { " mm" } else { " N" })?;
            o.put(" at ")?;
            mm(o, f.depth_um)?;
            o.put(" mm)")
        }
    }
}

/// The mean of the non-empty means of bins `i..i + ROW`, and their highest peak, dN.
fn row_of(c: &StoredCurve, i: usize) -> (i16, i16) {
    let (mut sum, mut n, mut peak) = (0i32, 0i32, EMPTY_DN);
    for k in i..i + ROW {
        if let Some(&m) = c.mean_dn.get(k).filter(|&&m| m != EMPTY_DN) {
            sum += i32::from(m);
            n += 1;
        }
        if let Some(&p) = c.peak_dn.get(k).filter(|&&p| p != EMPTY_DN) {
            if peak == EMPTY_DN || p > peak {
                peak = p;
            }
        }
    }
    let mean = if n == 0 { EMPTY_DN } else { (sum / n) as i16 };
    (mean, peak)
}

fn text(o: &mut dyn Sink, v: &CurveView) -> fmt::Result {
    o.put("curve ")?;
    o.put(which_name(v.which))?;
    match v.which {
        Which::Reference => {
            o.put(": the mean of ")?;
            write_u64(o, u64::from(v.reference_n))?;
            o.put(" docking(s)\r\n")?;
        }
        _ => {
            o.put(": cycle ")?;
            write_u64(o, u64::from(v.cycle))?;
            o.put("; ")?;
            verdict_text(o, "insertion", v.verdicts[0])?;
            o.put("; ")?;
            verdict_text(o, "extraction", v.verdicts[1])?;
            o.put("\r\n")?;
        }
    }
    if let Some(s) = &v.summary {
        o.put("work ")?;
        write_fixed(o, i64::from(s.work_mnmm / 100), 1)?;
        o.put(" N.mm, plateau ")?;
        newtons(o, s.plateau_mn)?;
        o.put(" N, step at ")?;
        match s.step_um {
            Some(x) => mm(o, x)?,
            None => o.put("-")?,
        }
        o.put(" mm, end ")?;
        newtons(o, s.end_mn)?;
        o.put(" N, extraction peak ")?;
        newtons(o, s.ext_peak_mn)?;
        o.put(" N")?;
        if let (Some(w), Some(p)) = (s.drift_work_pm, s.drift_plateau_pm) {
            o.put("; drift: work ")?;
            write_fixed(o, i64::from(w), 1)?;
            o.put(" %, plateau ")?;
            write_fixed(o, i64::from(p), 1)?;
            o.put(" %")?;
        }
        o.put("\r\n")?;
    }
    o.put("depth_mm      ph  ins_mean  ins_peak  ext_mean  ext_peak  band_n\r\n")?;
    let [ins, ext] = &v.curves;
    for i in (0..BINS).step_by(ROW) {
        mm(o, lo_um(i))?;
        o.put("-")?;
        mm(o, lo_um(i + ROW))?;
        o.put(" ")?;
        write_u64(o, u64::from(v.cfg.nominal.phase_of(i)))?;
        for c in [ins, ext] {
            let (m, p) = row_of(c, i);
            o.put("  ")?;
            dn(o, m, "-")?;
            o.put("  ")?;
            dn(o, p, "-")?;
        }
        let band = |k: usize| v.cfg.band_moved_mn(k, v.shift);
        let lo = (i..i + ROW).map(|k| band(k).0).min().unwrap_or(0);
        let hi = (i..i + ROW).map(|k| band(k).1).max().unwrap_or(0);
        o.put("  ")?;
        newtons(o, lo)?;
        o.put("..")?;
        newtons(o, hi)?;
        o.put("\r\n")?;
    }
    Ok(())
}
