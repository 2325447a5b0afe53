//! The signature monitor: a docking from its first sample to its summary in flash.
//!
//! [`Monitor::tap`] takes each sample (off the control step, see [`super::capture`]);
//! when a stroke ends it is judged ([`super::objects`]) and its verdict returned (for
//! the log, the controller's events and the PLC); when the extraction ends the docking
//! is summarised: its figures, its drift from the cone's reference, the cone's counts
//! and trend, and what must be written (the summary; the curves if NOK; the reference
//! while it is learnt), which [`Monitor::persist`] writes at the next rest.
//!
//! # The reference and the drift
//!
//! After `cone replace` the first [`SignatureConfig::reference_n`] dockings judged OK
//! are summed into the cone's reference (a NOK docking — debris, a catch — is not the
//! cone's normal curve); from then on every docking reports its **drift** from the
//! reference's mean: the insertion work ∫F·dx and the phase-4 plateau, in ‰, and their
//! **trend** per cone (a moving average, α = 1/16, kept ×16 in integers).
//!
//! # Memory
//!
//! The capture, the reference's sums, the ring of the newest summaries for `history` and
//! the wear estimate's window of steps ([`SignatureMem`], about 4.8 KiB) live wherever the board puts them: on the STM32F407
//! in the CCM RAM, which the bootloader uses only before it starts the application
//! (`memory.x`); the monitor itself is a few hundred bytes of the controller.

use super::capture::Capture;
use super::figures::{self, ExtractionFigures, InsertionFigures};
use super::objects::{Failure, SignatureConfig};
use super::records::{Reference, Summary};
use super::stepwear::{StepWindow, WINDOW_MAX};
use super::store::{SigStore, StoreError};
use super::Stroke;
use embedded_storage::nor_flash::NorFlash;
use zerocopy::FromZeros;

/// Summaries `history` can show.
pub const RING: usize = 100;

/// Failed writes in a row after which what waits is dropped (and counted).
pub const WRITE_ATTEMPTS: u8 = 3;

/// One docking's `history` columns.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, FromZeros)]
pub struct HistoryCols {
    /// Lifetime cycle number.
    pub cycle: u32,
    /// First object failed (its code), 0: OK.
    pub failed: u8,
    /// Insertion work, N·mm (saturating).
    pub work_nmm: u16,
    /// Phase-4 plateau, dN (saturating).
    pub plateau_dn: u16,
    /// Drift of the work, ‰ (`i16::MIN`: none).
    pub drift_work_pm: i16,
    /// Drift of the plateau, ‰ (`i16::MIN`: none).
    pub drift_plateau_pm: i16,
}

impl HistoryCols {
    /// From a summary.
    pub fn of(s: &Summary) -> Self {
        Self {
            cycle: s.lifetime_cycle,
            failed: s.failure.map_or(0, |f| f.object.code()),
            work_nmm: u16::try_from(s.work_mnmm / 1000).unwrap_or(u16::MAX),
            plateau_dn: u16::try_from((s.plateau_mn.max(0) + 50) / 100).unwrap_or(u16::MAX),
            drift_work_pm: s.drift_work_pm.unwrap_or(i16::MIN),
            drift_plateau_pm: s.drift_plateau_pm.unwrap_or(i16::MIN),
        }
    }
}

/// The monitor's large buffers (see the module doc for where they live). All-zero
/// memory is a valid, empty one (`FromZeros`, checked by the compiler): the board
/// zeroes its static in place.
#[derive(FromZeros)]
pub struct SignatureMem {
    /// Both strokes of the newest docking.
    pub capture: Capture,
    /// The cone's reference as learnt so far.
    pub reference: Reference,
    /// The 3→4 steps of the cone's newest OK dockings after its reference (the wear
    /// estimate's window, [`super::stepwear`]).
    pub steps: StepWindow,
    /// The newest summaries: a ring of `ring_len` from `ring_start`, oldest first.
    ring: [HistoryCols; RING],
    ring_start: u8,
    ring_len: u8,
}

impl SignatureMem {
    /// An empty one, by value (the host's; the board zeroes its static in place).
    pub fn zeroed() -> Self {
        Self::new_zeroed()
    }

    /// The `i`-th oldest summary in the ring.
    fn ring_get(&self, i: usize) -> Option<HistoryCols> {
        if i >= usize::from(self.ring_len) {
            return None;
        }
        self.ring
            .get((usize::from(self.ring_start) + i) % RING)
            .copied()
    }

    /// Add a newest summary (the oldest goes when full).
    fn ring_push(&mut self, c: HistoryCols) {
        let len = usize::from(self.ring_len);
        let at = (usize::from(self.ring_start) + len) % RING;
        if let Some(slot) = self.ring.get_mut(at) {
            *slot = c;
        }
        if len == RING {
            self.ring_start = ((usize::from(self.ring_start) + 1) % RING) as u8;
        } else {
            self.ring_len += 1;
        }
    }
}

/// The docking a stroke belongs to (the odometer's numbers while it runs).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Docking {
    /// Lifetime cycle number it will get.
    pub lifetime_cycle: u32,
    /// Its number on its cone.
    pub cone_cycle: u32,
    /// The cone.
    pub cone_id: u16,
}

/// A stroke's verdict.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct StrokeVerdict {
    /// Lifetime cycle number of its docking.
    pub cycle: u32,
    /// Which stroke.
    pub stroke: Stroke,
    /// `None`: OK; else the first object failed.
    pub failure: Option<Failure>,
}

/// A judged stroke: its first failed object (`None`: OK) and its figures; `None`
/// before it is judged.
pub type Judged<T> = Option<(Option<Failure>, T)>;

/// Per-cone counts and trend.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ConeCounts {
    /// The cone.
    pub cone_id: u16,
    /// Dockings judged.
    pub judged: u32,
    /// NOK dockings.
    pub nok: u32,
    /// Trend of the work's drift, ‰ × 16.
    pub trend_work_x16: Option<i32>,
    /// Trend of the plateau's drift, ‰ × 16.
    pub trend_plateau_x16: Option<i32>,
}

/// What waits for a rest.
const PENDING_SUMMARY: u8 = 1;
const PENDING_NOK: u8 = 2;
const PENDING_REFERENCE: u8 = 4;

/// The monitor.
pub struct Monitor<M> {
    mem: M,
    last_t_us: Option<u64>,
    docking: Docking,
    ins: Judged<InsertionFigures>,
    ext: Judged<ExtractionFigures>,
    last: Option<Summary>,
    last_verdict: Option<StrokeVerdict>,
    verdicts: u32,
    cone: ConeCounts,
    pending: u8,
    /// The record being written in parts (a `PENDING_*` bit; 0 none).
    writing: u8,
    /// Records whose data changed since their write began (`PENDING_*` bits): a frame
    /// in parts is begun again.
    changed: u8,
    /// Strokes ended and not judged yet (bit 0 the insertion, bit 1 the extraction).
    judge_due: u8,
    failures: u8,
    dropped: u32,
    write_errors: u32,
}

/// A stroke's bit in `judge_due`.
const fn bit(s: Stroke) -> u8 {
    match s {
        Stroke::Insertion => 1,
        Stroke::Extraction => 2,
    }
}

/// `x·1000/of − 1000`, ‰, within `i16` (never `i16::MIN`, which means none).
fn drift_pm(x: i64, of: i64) -> Option<i16> {
    if of <= 0 {
        return None;
    }
    let d = (x - of) * 1000 / of;
    Some(d.clamp(i64::from(i16::MIN) + 1, i64::from(i16::MAX)) as i16)
}

/// The next trend (α = 1/16) after `drift` (‰), ×16.
fn trend(t: Option<i32>, drift: Option<i16>) -> Option<i32> {
    let d = i32::from(drift?) * 16;
    Some(match t {
        None => d,
        Some(t) => t + (d - t) / 16,
    })
}

impl<M: core::ops::DerefMut<Target = SignatureMem>> Monitor<M> {
    /// A monitor with its buffers.
    pub fn new(mut mem: M) -> Self {
        mem.zero();
        Self {
            mem,
            last_t_us: None,
            docking: Docking::default(),
            ins: None,
            ext: None,
            last: None,
            last_verdict: None,
            verdicts: 0,
            cone: ConeCounts::default(),
            pending: 0,
            writing: 0,
            changed: 0,
            judge_due: 0,
            failures: 0,
            dropped: 0,
            write_errors: 0,
        }
    }

    /// A sample: `t_us` its time (a sample seen before is ignored), `force_mn` at
    /// `depth_um` of insertion depth, taken in `stroke` of `docking`. A stroke that ended
    /// with the sample before is judged later, by [`Self::judge_due`] (the board runs it
    /// in the service's window: a judgement is thousands of instructions, a sample a few
    /// hundred); only if the same stroke starts again first is it judged here, and that
    /// verdict returned.
    pub fn tap(
        &mut self,
        cfg: &SignatureConfig,
        t_us: u64,
        depth_um: i32,
        force_mn: i32,
        stroke: Option<Stroke>,
        docking: Docking,
    ) -> Option<StrokeVerdict> {
        if self.last_t_us == Some(t_us) {
            return None;
        }
        self.last_t_us = Some(t_us);
        // A stroke about to start again is judged first (its bins are emptied).
        let mut verdict = None;
        if let Some(s) = stroke {
            if self.judge_due & bit(s) != 0 && self.mem.capture.stroke(s).ended {
                self.judge_due &= !bit(s);
                verdict = self.judge(cfg, s);
            }
        }
        let fed = self.mem.capture.sample(depth_um, force_mn, stroke);
        if let Some(s) = fed.ended {
            self.judge_due |= bit(s);
        }
        if fed.began.is_some() {
            // The capture a NOK record is written from.
            self.changed |= PENDING_NOK;
        }
        match fed.began {
            Some(Stroke::Insertion) => {
                self.docking = docking;
                self.ins = None;
                self.ext = None;
                if self.pending & PENDING_NOK != 0 {
                    // Its curves are being overwritten: the summary still goes.
                    self.pending &= !PENDING_NOK;
                    self.dropped = self.dropped.saturating_add(1);
                }
            }
            Some(Stroke::Extraction) => self.ext = None,
            None => {}
        }
        verdict
    }

    /// Judge a stroke that ended, if one waits (the insertion first); its verdict.
    pub fn judge_due(&mut self, cfg: &SignatureConfig) -> Option<StrokeVerdict> {
        for s in [Stroke::Insertion, Stroke::Extraction] {
            if self.judge_due & bit(s) != 0 {
                self.judge_due &= !bit(s);
                return self.judge(cfg, s);
            }
        }
        None
    }

    /// Samples stopped (a fault, a silent sensor): a stroke in progress is not judged.
    pub fn break_chain(&mut self) {
        self.mem.capture.break_chain();
    }

    /// Judge stroke `s`, just ended; finish the docking after its extraction.
    fn judge(&mut self, cfg: &SignatureConfig, s: Stroke) -> Option<StrokeVerdict> {
        let bins = self.mem.capture.stroke(s);
        if !bins.complete() {
            return None;
        }
        let failure = match s {
            Stroke::Insertion => {
                let f = cfg.insertion_figures(bins);
                let fail = cfg.judge_insertion(bins, &f);
                self.ins = Some((fail, f));
                fail
            }
            Stroke::Extraction => {
                let f = figures::extraction(bins);
                let step = self.ins.and_then(|(_, fi)| fi.step_um);
                let fail = cfg.judge_extraction(bins, &f, step);
                self.ext = Some((fail, f));
                fail
            }
        };
        let v = StrokeVerdict {
            cycle: self.docking.lifetime_cycle,
            stroke: s,
            failure,
        };
        match failure {
            None => info!("signature: cycle {=u32} {=str} ok", v.cycle, s.name()),
            Some(f) => warn!(
                "signature: cycle {=u32} {=str} nok {=str} figure {=i32} limit {=i32} at {=i32} um",
                v.cycle,
                s.name(),
                f.object.name(),
                f.figure,
                f.limit,
                f.depth_um
            ),
        }
        self.last_verdict = Some(v);
        self.verdicts = self.verdicts.wrapping_add(1);
        if s == Stroke::Extraction {
            self.finish(cfg);
        }
        Some(v)
    }

    /// Summarise the docking whose strokes were both judged.
    fn finish(&mut self, cfg: &SignatureConfig) {
        let (Some((fi, ins)), Some((fe, ext))) = (self.ins, self.ext) else {
            return;
        };
        let d = self.docking;
        if self.cone.cone_id != d.cone_id {
            self.cone = ConeCounts {
                cone_id: d.cone_id,
                ..ConeCounts::default()
            };
        }
        if self.mem.reference.cone_id != d.cone_id {
            self.mem.reference = Reference::empty(d.cone_id);
        }
        if self.mem.steps.cone_id() != d.cone_id {
            self.mem.steps.clear(d.cone_id);
        }
        let r = &self.mem.reference;
        let complete = r.n >= cfg.reference_n.max(1);
        let n = i64::from(r.n.max(1));
        let (drift_w, drift_p) = if complete {
            (
                drift_pm(i64::from(ins.work_mnmm), (r.work_sum as i64) / n),
                drift_pm(i64::from(ins.plateau_mn), r.plateau_sum / n),
            )
        } else {
            (None, None)
        };
        let nok = fi.is_some() || fe.is_some();
        self.cone.judged = self.cone.judged.saturating_add(1);
        if nok {
            self.cone.nok = self.cone.nok.saturating_add(1);
        }
        self.cone.trend_work_x16 =
            trend(self.cone.trend_work_x16, drift_w).or(self.cone.trend_work_x16);
        self.cone.trend_plateau_x16 =
            trend(self.cone.trend_plateau_x16, drift_p).or(self.cone.trend_plateau_x16);
        let learn = !nok && !complete;
        if !nok && complete {
            // After the reference: the wear estimate's window.
            if let Some(st) = ins.step_um {
                self.mem.steps.push(st);
            }
        }
        if learn {
            let mem = &mut *self.mem;
            let rf = &mut mem.reference;
            for (k, s) in [Stroke::Insertion, Stroke::Extraction]
                .into_iter()
                .enumerate()
            {
                let means = figures::filled_means(mem.capture.stroke(s));
                if let Some(sums) = rf.sums.get_mut(k) {
                    for (sum, m) in sums.iter_mut().zip(means) {
                        *sum = sum.saturating_add(i32::from(m));
                    }
                }
            }
            rf.n = rf.n.saturating_add(1);
            rf.work_sum = rf.work_sum.saturating_add(u64::from(ins.work_mnmm));
            rf.plateau_sum = rf.plateau_sum.saturating_add(i64::from(ins.plateau_mn));
            if let Some(st) = ins.step_um {
                rf.step_n = rf.step_n.saturating_add(1);
                rf.step_sum = rf.step_sum.saturating_add(i64::from(st));
            }
            self.pending |= PENDING_REFERENCE;
            self.changed |= PENDING_REFERENCE;
        }
        let s = Summary {
            lifetime_cycle: d.lifetime_cycle,
            cone_cycle: d.cone_cycle,
            cone_id: d.cone_id,
            insertion_nok: fi.is_some(),
            extraction_nok: fe.is_some(),
            in_reference: learn,
            failure: fi.or(fe),
            work_mnmm: ins.work_mnmm,
            plateau_mn: ins.plateau_mn,
            step_um: ins.step_um,
            end_mn: ins.end_mn,
            ext_peak_mn: ext.peak_mn,
            drift_work_pm: drift_w,
            drift_plateau_pm: drift_p,
            cone_judged: self.cone.judged,
            cone_nok: self.cone.nok,
            trend_work_x16: self.cone.trend_work_x16,
            trend_plateau_x16: self.cone.trend_plateau_x16,
            prev: None,
        };
        self.last = Some(s);
        self.pending |= PENDING_SUMMARY;
        self.changed |= PENDING_SUMMARY | PENDING_NOK;
        if nok {
            self.pending |= PENDING_NOK;
        }
        self.push_ring(&s);
        info!(
            "signature: cycle {=u32} {=str}, work {=u32} mN·mm, plateau {=i32} mN; cone {=u16}: {=u32} NOK of {=u32}",
            s.lifetime_cycle,
            if nok { "NOK" } else { "OK" },
            s.work_mnmm,
            s.plateau_mn,
            s.cone_id,
            s.cone_nok,
            s.cone_judged
        );
    }

    fn push_ring(&mut self, s: &Summary) {
        self.mem.ring_push(HistoryCols::of(s));
    }

    /// A new cone: its counts and reference start from nothing.
    pub fn on_cone(&mut self, cone_id: u16) {
        self.cone = ConeCounts {
            cone_id,
            ..ConeCounts::default()
        };
        self.mem.reference = Reference::empty(cone_id);
        self.mem.steps.clear(cone_id);
        self.pending &= !PENDING_REFERENCE;
    }

    /// Whether something waits for a rest.
    pub fn persist_pending(&self) -> bool {
        self.pending != 0
    }

    /// Write what waits (at rest only), `budget` bytes of it this call (at least one
    /// 64-byte piece): the summary first (one part: it is small), then the NOK curves,
    /// then the reference — one record at a time, each whole before the next begins. A
    /// record in parts whose data changes in between (a new docking's capture, summary
    /// or reference) is left torn and begun again with the new data, or dropped if it
    /// no longer waits (a NOK curve a new docking overwrote: counted).
    pub fn persist<F: NorFlash>(&mut self, store: &mut SigStore<F>, budget: usize) {
        if self.writing != 0
            && (self.pending & self.writing == 0
                || self.changed & self.writing != 0
                || store.writing().is_none())
        {
            store.abandon();
            self.writing = 0;
        }
        self.changed = 0;
        if self.pending == 0 {
            return;
        }
        let next = if self.writing != 0 {
            self.writing
        } else if self.pending & PENDING_SUMMARY != 0 {
            PENDING_SUMMARY
        } else if self.pending & PENDING_NOK != 0 {
            PENDING_NOK
        } else {
            PENDING_REFERENCE
        };
        let r: Result<bool, StoreError<F::Error>> = match (next, self.last) {
            (PENDING_REFERENCE, _) => store.write_reference(&self.mem.reference, budget),
            (PENDING_NOK, Some(s)) => store.write_nok(&s, &self.mem.capture, budget),
            (PENDING_SUMMARY, Some(s)) => store.write_summary(&s, budget),
            // Nothing to write it from.
            _ => Ok(true),
        };
        match r {
            Ok(done) => {
                self.failures = 0;
                if done {
                    self.pending &= !next;
                    self.writing = 0;
                } else {
                    self.writing = next;
                }
            }
            Err(_) => {
                store.abandon();
                self.writing = 0;
                self.write_errors = self.write_errors.saturating_add(1);
                self.failures = self.failures.saturating_add(1);
                error!("signature: a record was not written");
                if self.failures >= WRITE_ATTEMPTS {
                    self.pending = 0;
                    self.failures = 0;
                    self.dropped = self.dropped.saturating_add(1);
                }
            }
        }
    }

    /// At boot: the newest summary (the last docking, and the cone's counts if it is
    /// `cone_id`'s), the cone's reference, the ring of summaries for `history`.
    pub fn load<F: NorFlash>(&mut self, store: &mut SigStore<F>, cone_id: u16) {
        self.cone = ConeCounts {
            cone_id,
            ..ConeCounts::default()
        };
        self.mem.reference = Reference::empty(cone_id);
        if let Ok(Some((s, _))) = store.newest_summary() {
            self.last = Some(s);
            if s.cone_id == cone_id {
                self.cone = ConeCounts {
                    cone_id,
                    judged: s.cone_judged,
                    nok: s.cone_nok,
                    trend_work_x16: s.trend_work_x16,
                    trend_plateau_x16: s.trend_plateau_x16,
                };
            }
        }
        let mem = &mut *self.mem;
        if store.read_reference(cone_id, &mut mem.reference).is_err() {
            mem.reference = Reference::empty(cone_id);
        }
        // Newest first from the walk: kept in a ring whose start moves back. The wear
        // estimate's window from the same walk: the cone's OK dockings after its
        // reference, with a step (newest first, pushed oldest first below).
        mem.ring_len = 0;
        mem.ring_start = 0;
        let mut n = 0usize;
        let ring = &mut mem.ring;
        let mut steps = [0i32; WINDOW_MAX];
        let mut n_steps = 0usize;
        let _ = store.walk_summaries(RING, &mut |s| {
            n += 1;
            if let Some(slot) = ring.get_mut(RING - n) {
                *slot = HistoryCols::of(s);
            }
            if s.cone_id == cone_id && !s.nok() && !s.in_reference {
                if let (Some(st), Some(slot)) = (s.step_um, steps.get_mut(n_steps)) {
                    *slot = st;
                    n_steps += 1;
                }
            }
            true
        });
        mem.ring_start = ((RING - n) % RING) as u8;
        mem.ring_len = n as u8;
        mem.steps.clear(cone_id);
        for &st in steps.iter().take(n_steps).rev() {
            mem.steps.push(st);
        }
    }

    /// The newest docking's capture.
    pub fn capture(&self) -> &Capture {
        &self.mem.capture
    }

    /// The cone's reference as learnt so far.
    pub fn reference(&self) -> &Reference {
        &self.mem.reference
    }

    /// The 3→4 steps of the cone's newest OK dockings after its reference.
    pub fn steps(&self) -> &StepWindow {
        &self.mem.steps
    }

    /// The last summarised docking.
    pub fn last(&self) -> Option<&Summary> {
        self.last.as_ref()
    }

    /// The newest stroke verdict, and how many there were since boot.
    pub fn last_verdict(&self) -> (Option<StrokeVerdict>, u32) {
        (self.last_verdict, self.verdicts)
    }

    /// The newest docking's judged strokes.
    pub fn judged(&self) -> (Judged<InsertionFigures>, Judged<ExtractionFigures>) {
        (self.ins, self.ext)
    }

    /// The docking the newest strokes belong to.
    pub fn docking(&self) -> Docking {
        self.docking
    }

    /// The current cone's counts.
    pub fn cone(&self) -> ConeCounts {
        self.cone
    }

    /// `history`'s columns of lifetime cycle `cycle`, if kept.
    pub fn history_cols(&self, cycle: u32) -> Option<HistoryCols> {
        (0..usize::from(self.mem.ring_len))
            .rev()
            .filter_map(|i| self.mem.ring_get(i))
            .find(|c| c.cycle == cycle)
    }

    /// Records not written (dropped after failed writes, or NOK curves overwritten by
    /// the next docking before a rest), and failed writes.
    pub fn write_losses(&self) -> (u32, u32) {
        (self.dropped, self.write_errors)
    }
}
