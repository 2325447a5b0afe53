//! The console's reports (`status`, `wear`, `faults`, `measurements`, `history`): each
//! one field list ([`Fields`]), rendered as `key=value` text or as one JSON line by the
//! service, so the two name every field the same way (docs/console.md lists them).
//!
//! A report's data is copied from the controller into a view (`*_view`, while the
//! console holds the controller) and written out later from the view (`*_fields`),
//! so the control step never waits for formatting.

use core::fmt;

use super::fields::Fields;
use crate::controller::HistoryEntry;
use crate::machine::Machine;

/// The entries of one `history` reply.
pub(super) type HistoryEntries =
    heapless::Vec<HistoryEntry, { super::parse::HISTORY_MAX as usize }>;

/// An entry's docking signature (issue 34), as compact as `history` needs it (10
/// bytes: a reply holds 100).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(super) struct SigCols {
    /// 0 not judged (or no longer kept), 1 OK, 2 NOK.
    verdict: u8,
    /// First failed object's code.
    failed: u8,
    work_nmm: u16,
    plateau_dn: u16,
    drift_work_pm: i16,
    drift_plateau_pm: i16,
}

impl SigCols {
    fn of(c: Option<crate::signature::monitor::HistoryCols>) -> Self {
        match c {
            None => Self::default(),
            Some(c) => Self {
                verdict: if c.failed == 0 { 1 } else { 2 },
                failed: c.failed,
                work_nmm: c.work_nmm,
                plateau_dn: c.plateau_dn,
                drift_work_pm: c.drift_work_pm,
                drift_plateau_pm: c.drift_plateau_pm,
            },
        }
    }
}

/// `history`'s signature columns, one per entry.
pub(super) type HistorySig = heapless::Vec<SigCols, { super::parse::HISTORY_MAX as usize }>;

/// The signature columns of `entries`.
pub(super) fn history_sig(ctrl: &dyn Machine, entries: &HistoryEntries) -> HistorySig {
    entries
        .iter()
        .map(|e| SigCols::of(ctrl.signature_history(e.lifetime_cycle)))
        .collect()
}

/// `status`.
pub(super) struct StatusView {
    s: crate::controller::Status,
    calibrated: bool,
    reset: Option<crate::diag::ResetCause>,
    stack: Option<(u32, u32)>,
    maint: bool,
}

/// `wear`.
pub(super) struct WearView {
    cone: crate::odometer::Cone,
    life: crate::odometer::Lifetime,
    wear_nm: u32,
    remaining: u32,
    limit_nm: u64,
    warn_nm: i64,
    level: crate::odometer::WearLevel,
    est: crate::estimate::Estimate,
    base: u32,
    measured: Option<i64>,
    /// The cone's load–distance, thousandths of N·mm.
    cone_nmm_milli: i64,
    /// The cycle in progress (counted into the cone at its end), same unit.
    in_cycle_nmm_milli: i64,
    readings: usize,
    /// The docking signature's counts, reference and drift (issue 34).
    sig: crate::signature::view::SignatureStatus,
}

/// `faults`.
pub(super) struct FaultsView {
    active: Option<&'static str>,
    count: u32,
    overloads: u32,
    recs: heapless::Vec<crate::controller::FaultRecord, 16>,
    resets: crate::diag::ResetCounts,
    queued: usize,
    dropped: u32,
    crash: Option<crate::diag::Crash>,
}

/// `measurements`.
pub(super) struct MeasurementsView {
    base: u32,
    assumed: bool,
    cone: u16,
    list: heapless::Vec<crate::odometer::Measurement, { crate::odometer::READINGS_KEPT }>,
}

/// An optional value: the value, or `none` / `null`.
fn opt(f: &mut dyn Fields, key: &str, v: Option<&str>) -> fmt::Result {
    match v {
        Some(v) => f.str(key, v),
        None => f.none(key),
    }
}

/// `phase`: the contact phase's number, or none outside the cone.
fn phase_field(f: &mut dyn Fields, phase: Option<crate::profile::ContactPhase>) -> fmt::Result {
    match phase {
        Some(p) => f.u64("phase", p.number() as u64),
        None => f.none("phase"),
    }
}

/// `status` (docs/console.md).
pub(super) fn status_fields(f: &mut dyn Fields, v: &StatusView) -> fmt::Result {
    let StatusView {
        s,
        calibrated,
        reset,
        stack,
        maint,
    } = *v;
    f.group("state")?;
    f.str("state", s.state.name())?;
    phase_field(f, s.phase)?;
    f.group("motion")?;
    f.fixed("force_n", s.force_mn as i64, 3)?;
    f.fixed("limit_n", s.limit_mn as i64, 3)?;
    f.fixed("pos_mm", s.pos_um as i64, 3)?;
    f.u64("cycles_completed", s.cycles_completed as u64)?;
    f.group("fault")?;
    opt(f, "fault", s.fault.map(|x| x.name()))?;
    f.bool("warning", s.warning)?;
    f.fixed("peak_force_n", s.peak_force_mn as i64, 3)?;
    f.group("board")?;
    f.bool("maintenance", maint)?;
    f.bool("calibrated", calibrated)?;
    opt(f, "reset", reset.map(|r| r.name()))?;
    match stack {
        Some((used, size)) => {
            f.u64("stack_used", used as u64)?;
            f.u64("stack_size", size as u64)?;
        }
        None => {
            f.none("stack_used")?;
            f.none("stack_size")?;
        }
    }
    let h = s.handshake;
    f.group("plc")?;
    f.bool("in_dock", h.dock)?;
    f.bool("in_estop_open", h.estop)?;
    f.bool("out_ready", h.ready)?;
    f.bool("out_mated", h.mated)?;
    f.bool("out_fault", h.fault)?;
    f.bool("out_maintenance", h.maintenance)
}

/// `wear` (docs/console.md).
pub(super) fn wear_fields(f: &mut dyn Fields, v: &WearView) -> fmt::Result {
    let WearView {
        ref cone,
        ref life,
        wear_nm,
        remaining,
        limit_nm,
        warn_nm,
        level,
        ref est,
        base,
        measured,
        cone_nmm_milli,
        in_cycle_nmm_milli,
        readings,
        ref sig,
    } = *v;
    f.group("cone")?;
    f.u64("cone", cone.id as u64)?;
    f.str("material", cone.material.name())?;
    // An unset serial is `none` / null, as every missing value (issue 35: it was
    // `serial=` and `"serial":""`).
    opt(
        f,
        "serial",
        Some(cone.serial_str()).filter(|s| !s.is_empty()),
    )?;
    f.u64("cycles", cone.cycles as u64)?;
    f.group("odometer")?;
    f.fixed("load_distance_nmm", cone_nmm_milli, 3)?;
    f.fixed("load_distance_in_cycle_nmm", in_cycle_nmm_milli, 3)?;
    f.fixed("wear_mm", wear_nm as i64, 6)?;
    f.u64("remaining_cycles", remaining as u64)?;
    f.group("level")?;
    f.str("level", level.name())?;
    f.fixed("limit_mm", limit_nm as i64, 6)?;
    f.fixed("warn_mm", warn_nm, 6)?;
    f.group("lifetime")?;
    f.u64("lifetime_cycles", life.cycles as u64)?;
    f.u64("cones_installed", life.cones_installed as u64)?;
    f.u64("overload_events", life.overload_events as u64)?;
    f.u64("faults", life.faults as u64)?;
    f.fixed("peak_force_n", life.peak_force_mn as i64, 3)?;
    f.group("estimate")?;
    match measured {
        Some(m) => f.fixed("wear_measured_mm", m, 6)?,
        None => f.none("wear_measured_mm")?,
    }
    f.fixed("wear_estimate_mm", est.wear_nm as i64, 6)?;
    f.fixed("estimate_low_mm", est.low_nm as i64, 6)?;
    f.fixed("estimate_high_mm", est.high_nm as i64, 6)?;
    f.u64("remaining_estimate_cycles", est.remaining_cycles as u64)?;
    f.u64(
        "remaining_estimate_low_cycles",
        est.remaining_low_cycles as u64,
    )?;
    f.u64(
        "remaining_estimate_high_cycles",
        est.remaining_high_cycles as u64,
    )?;
    // Beside the reading and the model: the wear the docking signature's 3→4 step
    // tells (issue 34), with its band and what it rests on; `none` until the cone's
    // reference and enough dockings after it.
    match sig.step_wear {
        Some(w) => {
            f.fixed("signature_wear_estimate_mm", i64::from(w.wear_nm), 6)?;
            f.fixed("signature_wear_band_mm", i64::from(w.band_nm), 6)?;
            f.u64("signature_wear_dockings", u64::from(w.dockings))?;
            f.u64("signature_wear_reference", u64::from(w.reference_n))?;
        }
        None => {
            f.none("signature_wear_estimate_mm")?;
            f.none("signature_wear_band_mm")?;
            f.none("signature_wear_dockings")?;
            f.none("signature_wear_reference")?;
        }
    }
    f.group("readings")?;
    f.fixed("baseline_bore_mm", base as i64, 3)?;
    f.bool("baseline_assumed", cone.baseline().is_none())?;
    f.u64("readings", readings as u64)?;
    // On the same line (object): `wear` stays one line for the scripts that read it.
    signature_fields(f, sig)
}

/// An optional per mille as a per cent with one decimal, or `none`.
fn pct(f: &mut dyn Fields, key: &str, pm: Option<i64>) -> fmt::Result {
    match pm {
        Some(v) => f.fixed(key, v, 1),
        None => f.none(key),
    }
}

/// `wear`'s docking signature (docs/console.md): the cone's judged and NOK dockings,
/// its reference, the newest docking's verdict and drift, the trend.
fn signature_fields(
    f: &mut dyn Fields,
    s: &crate::signature::view::SignatureStatus,
) -> fmt::Result {
    f.u64("signature_judged", u64::from(s.cone.judged))?;
    f.u64("signature_nok", u64::from(s.cone.nok))?;
    f.u64("reference_dockings", u64::from(s.reference_n))?;
    f.u64("reference_of", u64::from(s.reference_target))?;
    let last = s.last.filter(|l| l.cone_id == s.cone.cone_id);
    match last {
        Some(l) => {
            f.u64("signature_cycle", u64::from(l.lifetime_cycle))?;
            f.str("signature", if l.nok() { "nok" } else { "ok" })?;
            opt(f, "signature_failed", l.failure.map(|x| x.object.name()))?;
            pct(f, "drift_work_pct", l.drift_work_pm.map(i64::from))?;
            pct(f, "drift_plateau_pct", l.drift_plateau_pm.map(i64::from))?;
        }
        None => {
            f.none("signature_cycle")?;
            f.none("signature")?;
            f.none("signature_failed")?;
            f.none("drift_work_pct")?;
            f.none("drift_plateau_pct")?;
        }
    }
    pct(
        f,
        "trend_work_pct",
        s.cone.trend_work_x16.map(|t| i64::from(t) / 16),
    )?;
    pct(
        f,
        "trend_plateau_pct",
        s.cone.trend_plateau_x16.map(|t| i64::from(t) / 16),
    )?;
    f.u64("signature_records_lost", u64::from(s.losses.0))
}

/// `faults` (docs/console.md).
pub(super) fn faults_fields(f: &mut dyn Fields, v: &FaultsView) -> fmt::Result {
    let FaultsView {
        active,
        count,
        overloads,
        ref recs,
        ref resets,
        queued,
        dropped,
        crash,
    } = *v;
    opt(f, "active", active)?;
    f.u64("count_since_boot", count as u64)?;
    f.u64("overload_events_lifetime", overloads as u64)?;
    f.u64("records_queued", queued as u64)?;
    f.u64("records_dropped", dropped as u64)?;
    f.object("resets", &mut |r| {
        for c in crate::diag::ResetCause::ALL {
            r.u64(c.name(), resets.of(c) as u64)?;
        }
        Ok(())
    })?;
    match crash {
        Some(c) => f.object("last_crash", &mut |x| {
            x.str("kind", c.kind.name())?;
            x.hex32("pc", c.pc)?;
            x.hex32("lr", c.lr)?;
            x.hex32("cfsr", c.cfsr)?;
            x.hex32("hfsr", c.hfsr)?;
            x.str("file", c.file_str())?;
            x.u64("line", c.line as u64)
        })?,
        None => f.none("last_crash")?,
    }
    f.records("faults", recs.len(), &mut |i, x| {
        let Some(r) = recs.get(i) else {
            return Ok(());
        };
        x.str("kind", r.kind.name())?;
        x.u64("cycle", r.cycle as u64)?;
        phase_field(x, r.phase)?;
        x.fixed("t_s", r.t_ms as i64, 3)?;
        x.fixed("peak_force_n", r.peak_force_mn as i64, 3)
    })
}

/// `measurements` (docs/console.md).
pub(super) fn measurements_fields(f: &mut dyn Fields, v: &MeasurementsView) -> fmt::Result {
    let MeasurementsView {
        base,
        assumed,
        cone,
        ref list,
    } = *v;
    f.u64("cone", cone as u64)?;
    f.fixed("baseline_bore_mm", base as i64, 3)?;
    f.bool("baseline_assumed", assumed)?;
    f.records("readings", list.len(), &mut |i, x| {
        let Some(m) = list.get(i) else {
            return Ok(());
        };
        x.u64("cone_cycle", m.cone_cycle as u64)?;
        x.u64("cycle", m.lifetime_cycle as u64)?;
        x.fixed("bore_mm", m.bore_um as i64, 3)?;
        x.fixed("wear_mm", m.wear_nm(base) as i64, 6)?;
        x.fixed("model_wear_mm", m.model_nm as i64, 6)
    })
}

/// `status`'s data (with the controller).
pub(super) fn status_view(ctrl: &dyn Machine, maint: bool) -> StatusView {
    StatusView {
        s: ctrl.status(),
        calibrated: ctrl.calibrated(),
        reset: ctrl.last_reset(),
        stack: ctrl.stack_usage(),
        maint,
    }
}

/// `wear`'s data (with the controller).
pub(super) fn wear_view(ctrl: &dyn Machine) -> WearView {
    let odo = ctrl.odometer();
    let cone = *odo.cone();
    let cfg = *odo.config();
    // The level acted on (the estimate's band once measured), the estimate, the last
    // reading.
    let base = ctrl.baseline_or_nominal();
    WearView {
        cone,
        life: *odo.lifetime(),
        wear_nm: odo.wear_nm(),
        remaining: odo.remaining_cycles(),
        limit_nm: cfg.limit_nm as u64,
        warn_nm: (cfg.limit_nm as u64 * cfg.warn_pct as u64 / 100) as i64,
        level: ctrl.wear_level(),
        est: ctrl.wear_estimate(),
        base,
        measured: ctrl.measurements().last().map(|m| m.wear_nm(base) as i64),
        // The cone's load–distance (Q63.1 mN·µm) in thousandths of N·mm.
        cone_nmm_milli: (cone.w_q1 / 2_000).min(i64::MAX as u64) as i64,
        in_cycle_nmm_milli: (ctrl.journal().cone_w_q1.saturating_sub(cone.w_q1) / 2_000)
            .min(i64::MAX as u64) as i64,
        readings: ctrl.measurements().len(),
        sig: ctrl.signature_status(),
    }
}

/// The recent faults, copied field by field: a whole-record copy out of the
/// controller (not provably apart from the view) is a `memmove`, and it and
/// [`crate::controller::Controller::history`]'s were the last callers of its 1.5 KB (issue 20).
fn fault_records(ctrl: &dyn Machine) -> heapless::Vec<crate::controller::FaultRecord, 16> {
    let mut recs = heapless::Vec::new();
    ctrl.each_fault(&mut |r| {
        let _ = recs.push(crate::controller::FaultRecord {
            kind: r.kind,
            cycle: r.cycle,
            phase: r.phase,
            t_ms: r.t_ms,
            peak_force_mn: r.peak_force_mn,
        });
    });
    recs
}

/// `faults`' data (with the controller).
pub(super) fn faults_view(ctrl: &dyn Machine) -> FaultsView {
    FaultsView {
        active: ctrl.status().fault.map(|f| f.name()),
        count: ctrl.fault_count(),
        overloads: ctrl.odometer().lifetime().overload_events,
        recs: fault_records(ctrl),
        resets: ctrl.reset_counts(),
        // Records waiting for a rest to be written, and those the full queue dropped.
        queued: ctrl.records_queued(),
        dropped: ctrl.records_dropped(),
        crash: ctrl.last_crash(),
    }
}

/// `measurements`' data (with the controller).
pub(super) fn measurements_view(ctrl: &dyn Machine) -> MeasurementsView {
    MeasurementsView {
        base: ctrl.baseline_or_nominal(),
        assumed: ctrl.odometer().cone().baseline().is_none(),
        cone: ctrl.odometer().cone().id,
        list: ctrl.measurements().iter().copied().collect(),
    }
}

/// `history` (docs/console.md): one record a completed cycle.
pub(super) fn history_fields(
    f: &mut dyn Fields,
    entries: &HistoryEntries,
    sig: &HistorySig,
) -> fmt::Result {
    // W in Q63.1 mN·µm → N·mm with 3 decimals: q1 / 2 / 1000 (mN·µm → 1e-3 N·mm units).
    f.records("history", entries.len(), &mut |i, x| {
        let Some(e) = entries.get(i) else {
            return Ok(());
        };
        x.u64("cycle", e.lifetime_cycle as u64)?;
        x.u64("cone", e.cone_id as u64)?;
        x.u64("cone_cycle", e.cone_cycle as u64)?;
        x.fixed("load_distance_nmm", (e.w_q1 / 2_000) as i64, 3)?;
        x.fixed("wear_mm", e.wear_nm as i64, 6)?;
        // The docking's signature (issue 34), when judged and still kept.
        let s = sig.get(i).copied().unwrap_or_default();
        if s.verdict == 0 {
            return x.none("signature");
        }
        x.str("signature", if s.verdict == 2 { "nok" } else { "ok" })?;
        opt(
            x,
            "failed",
            crate::signature::objects::Object::from_code(s.failed).map(|o| o.name()),
        )?;
        x.u64("work_nmm", u64::from(s.work_nmm))?;
        x.fixed("plateau_n", i64::from(s.plateau_dn), 1)?;
        let d = |v: i16| (v != i16::MIN).then_some(i64::from(v));
        pct(x, "drift_work_pct", d(s.drift_work_pm))?;
        pct(x, "drift_plateau_pct", d(s.drift_plateau_pm))
    })
}
