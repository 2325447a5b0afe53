//! What the signature shows its clients: the status the PLC's registers and `wear`
//! read ([`SignatureStatus`]), and a curve for `curve` ([`CurveView`]), copied out of
//! the monitor and the store while a client holds the controller (a few hundred
//! bytes, or one curve's 1.3 KiB), formatted after it is released.

use super::grid::BINS;
use super::monitor::{ConeCounts, HistoryCols, Monitor, SignatureMem, StrokeVerdict};
use super::objects::{Failure, SignatureConfig};
use super::records::{StoredCurve, Summary, EMPTY_DN};
use super::stepwear::{self, StepWear};
use super::store::SigStore;
use super::Stroke;
use embedded_storage::nor_flash::NorFlash;

/// The signature's state as the PLC and `wear` see it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SignatureStatus {
    /// The newest summarised docking.
    pub last: Option<Summary>,
    /// The newest stroke's verdict.
    pub newest: Option<StrokeVerdict>,
    /// Stroke verdicts since boot (wraps): a new one changes it.
    pub verdicts: u32,
    /// The current cone's counts.
    pub cone: ConeCounts,
    /// Dockings in the cone's reference so far, and how many it takes.
    pub reference_n: u8,
    /// See [`Self::reference_n`].
    pub reference_target: u8,
    /// The reference's mean 3→4 step, µm.
    pub reference_step_um: Option<i32>,
    /// The cone's wear estimated from its 3→4 step ([`super::stepwear`]); `None`
    /// before its reference and enough dockings after it.
    pub step_wear: Option<StepWear>,
    /// Records lost (not written after failed writes, or NOK curves overwritten by the
    /// next docking before a rest), and failed writes.
    pub losses: (u32, u32),
}

impl SignatureStatus {
    /// Of a monitor, with `cfg`; `spacing_um` the load cell's sample spacing at v0
    /// (the step's resolution, for the wear estimate's band).
    pub fn of<M: core::ops::DerefMut<Target = SignatureMem>>(
        m: &Monitor<M>,
        cfg: &SignatureConfig,
        spacing_um: u32,
    ) -> Self {
        let (newest, verdicts) = m.last_verdict();
        let r = m.reference();
        let cone = m.cone();
        let same = r.cone_id == cone.cone_id;
        let complete = same && r.n >= cfg.reference_n.max(1);
        let steps = m.steps();
        let step_wear = (complete && steps.cone_id() == cone.cone_id)
            .then(|| stepwear::estimate(cfg, r.step_sum, r.step_n, steps, spacing_um))
            .flatten();
        Self {
            last: m.last().copied(),
            newest,
            verdicts,
            cone,
            reference_n: if same { r.n } else { 0 },
            reference_target: cfg.reference_n,
            reference_step_um: (same && r.step_n > 0)
                .then(|| (r.step_sum / i64::from(r.step_n)) as i32),
            step_wear,
            losses: m.write_losses(),
        }
    }

    /// The reference is complete: drift is reported.
    pub fn reference_complete(&self) -> bool {
        self.reference_n >= self.reference_target.max(1)
    }
}

/// A stroke's verdict as `curve` shows it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Judgement {
    /// Not judged: in progress, cut short, or a reference.
    None,
    /// OK.
    Ok,
    /// NOK, and the first object failed (`None`: the stroke's own object is not kept —
    /// a NOK docking keeps the first failure of its first NOK stroke).
    Nok(Option<Failure>),
}

impl Judgement {
    fn of(j: Option<Option<Failure>>) -> Self {
        match j {
            None => Self::None,
            Some(None) => Self::Ok,
            Some(Some(f)) => Self::Nok(Some(f)),
        }
    }
}

/// Which curve `curve` shows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Which {
    /// The newest docking's (from RAM: since the last boot).
    Last,
    /// The current cone's reference.
    Reference,
    /// The `n`-th newest NOK docking (1: the newest), from flash.
    Nok(u8),
}

/// A curve and what it is judged by, for `curve`.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CurveView {
    /// Which.
    pub which: Which,
    /// The insertion's and the extraction's bins (a reference's means as both mean and
    /// peak).
    pub curves: [StoredCurve; 2],
    /// Each stroke's verdict.
    pub verdicts: [Judgement; 2],
    /// The docking's summary (a NOK curve's; the newest docking's once summarised).
    pub summary: Option<Summary>,
    /// The docking's lifetime cycle (0: none).
    pub cycle: u32,
    /// A reference: dockings in it.
    pub reference_n: u8,
    /// Bins the objects of phases 3–4 moved with the curve's 3→4 step
    /// ([`SignatureConfig::shift_bins`]; a reference's: its mean step).
    pub shift: usize,
    /// The objects' settings (the bands, the nominal curve).
    pub cfg: SignatureConfig,
}

impl CurveView {
    /// Nothing (before a fill).
    pub fn empty(cfg: SignatureConfig) -> Self {
        Self {
            which: Which::Last,
            curves: [StoredCurve::EMPTY, StoredCurve::EMPTY],
            verdicts: [Judgement::None, Judgement::None],
            summary: None,
            cycle: 0,
            reference_n: 0,
            shift: 0,
            cfg,
        }
    }

    /// Fill with `which`; `false`: there is none (no docking since boot, no reference
    /// yet, fewer NOK curves kept, or the store cannot be read).
    pub fn fill<F: NorFlash, M: core::ops::DerefMut<Target = SignatureMem>>(
        &mut self,
        which: Which,
        m: &Monitor<M>,
        store: Option<&mut SigStore<F>>,
        cfg: &SignatureConfig,
    ) -> bool {
        *self = Self::empty(*cfg);
        self.which = which;
        match which {
            Which::Last => {
                let c = m.capture();
                let (ins, ext) = (c.stroke(Stroke::Insertion), c.stroke(Stroke::Extraction));
                if ins.is_empty() && ext.is_empty() {
                    return false;
                }
                self.curves = [StoredCurve::of(ins), StoredCurve::of(ext)];
                let (ji, je) = m.judged();
                self.verdicts = [
                    Judgement::of(ji.map(|j| j.0)),
                    Judgement::of(je.map(|j| j.0)),
                ];
                self.cycle = m.docking().lifetime_cycle;
                self.summary = m.last().filter(|s| s.lifetime_cycle == self.cycle).copied();
                self.shift = cfg.shift_bins(ji.and_then(|j| j.1.step_um));
                true
            }
            Which::Reference => {
                let r = m.reference();
                if r.n == 0 || r.cone_id != m.cone().cone_id {
                    return false;
                }
                self.reference_n = r.n;
                self.shift = cfg
                    .shift_bins((r.step_n > 0).then(|| (r.step_sum / i64::from(r.step_n)) as i32));
                for (k, curve) in self.curves.iter_mut().enumerate() {
                    for i in 0..BINS {
                        let v = r.mean_dn(k, i).unwrap_or(EMPTY_DN);
                        if let (Some(mn), Some(pk), Some(ct)) = (
                            curve.mean_dn.get_mut(i),
                            curve.peak_dn.get_mut(i),
                            curve.count.get_mut(i),
                        ) {
                            *mn = v;
                            *pk = v;
                            *ct = r.n;
                        }
                    }
                }
                true
            }
            Which::Nok(n) => {
                let Some(st) = store else {
                    return false;
                };
                let idx = usize::from(n.saturating_sub(1));
                match st.read_nok(idx, &mut self.curves) {
                    Ok(Some(s)) => {
                        self.cycle = s.lifetime_cycle;
                        let nok = |bad: bool, own: bool| {
                            if bad {
                                Judgement::Nok(s.failure.filter(|_| own))
                            } else {
                                Judgement::Ok
                            }
                        };
                        self.verdicts = [
                            nok(s.insertion_nok, true),
                            nok(s.extraction_nok, !s.insertion_nok),
                        ];
                        self.shift = cfg.shift_bins(s.step_um);
                        self.summary = Some(s);
                        true
                    }
                    _ => false,
                }
            }
        }
    }
}

/// `history`'s signature columns of lifetime cycle `cycle` (none: not judged, or no
/// longer kept).
pub fn history_cols<M: core::ops::DerefMut<Target = SignatureMem>>(
    m: &Monitor<M>,
    cycle: u32,
) -> Option<HistoryCols> {
    m.history_cols(cycle)
}
