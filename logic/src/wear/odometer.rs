//! The wear odometer: cumulative guide-cone wear from the measured load, per cycle, in
//! integer and fixed-point arithmetic only (`docs/physics.md` §4–§5).
//!
//! ## Model
//! Archard: wear is proportional to load × sliding distance. For every sample in the
//! cone (both strokes) the odometer adds the trapezoid `(F_prev + F) · |Δx|`, with `F`
//! the measured rod–cone load and `Δx` the axis travel **from the counted position**
//! (not an assumed speed), so a cycle with more load or more travel wears more, in
//! proportion. The sum is exact (integers, no rounding per sample), so loads far below
//! any state resolution accumulate without loss.
//!
//! The cone's state is its total load–distance `W`. Converted to **equivalent nominal
//! cycles** `E = k · W / W_nom` (`k` the material's calibrated wear factor, `W_nom` the
//! exact load–distance of one nominal cycle of Eq. 7), the depth is the reduced-order
//! solution of the paper's power law (Eq. 17), which integrates exactly:
//!
//! ```text
//!   h(E) = a · (E + m0)^b − c        a = 0.01372 mm, b = 0.3813, c = 0.01774 mm,
//!                                    m0 = (c/a)^(1/b) = 1.96192  (so h(0) = 0)
//!   E_limit = ((h_limit + c)/a)^(1/b) − m0        (45 268.2 at 0.8 mm)
//!   remaining (nominal cycles of this material) = (E_limit − E) / k
//! ```
//!
//! At nominal load this is within 0.5 % of Eq. 17 from 200 cycles on and reaches 0.8 mm
//! at 45 268 cycles (Eq. 17: 45 270). `h` is monotone in `E` and `E` in `W`, so wear
//! never decreases, and an off-nominal cycle simply advances `E` more or less.
//!
//! ## Formats
//! * load–distance: `u64`, **Q63.1 mN·µm** (units of 0.5 mN·µm: the trapezoid's halving
//!   is kept exact); saturating;
//! * `E`: `u64` Q32.32 nominal cycles; powers via [`crate::fixed`] (bit-identical on host
//!   and target);
//! * depth: `u32` nm; force: `i32` mN; positions: `i32` µm.
//!
//! ## Records
//! Every persisted record (kinds in [`kind`]) is declared once, as a `zerocopy` layout of
//! little-endian fields (`#[repr(C)]`, byte-aligned, no padding): [`StateRecord`],
//! [`Measurement`], [`RetiredCone`] and the cone record ([`cone_to_bytes`]), the last two
//! sharing the cone's identity; each is drawn at its type.

use core::mem::size_of;

use zerocopy::byteorder::little_endian::{I32, U16, U32, U64};
use zerocopy::{FromBytes, Immutable, IntoBytes, KnownLayout, Unaligned};

use crate::fixed::{pow_q32, ONE_Q32};
use crate::material::Material;

/// Load–distance of one nominal cycle (both strokes of Eq. 7 at 1.2 mm/s), mN·µm:
/// 2 · 1.2 mm/s · ∫N3 dt (3368.9414 N·s) = 8085.4594 N·mm.
pub const W_NOM_MN_UM: u64 = 8_085_459_450;
/// The same in Q63.1 (the odometer's unit).
pub const W_NOM_Q1: u64 = 2 * W_NOM_MN_UM;
/// Eq. 17 `a`, nm.
pub const A_NM: u64 = 13_720;
/// Eq. 17 `c`, nm.
pub const C_NM: u64 = 17_740;
/// Eq. 17 exponent `b` = 0.3813 in Q32.32.
pub const B_Q32: i64 = 1_637_671_030;
/// `1/b` in Q32.32.
pub const INV_B_Q32: i64 = 11_264_010_742;
/// `m0 = (c/a)^(1/b)` in Q32.32 (computed at build time).
pub const M0_Q32: u64 = pow_q32((C_NM << 32) / A_NM, INV_B_Q32);

/// The material's wear per unit load–distance relative to ZQSn5-2, Q32.32.
///
/// Archard's `Km / H` per material, calibrated, not from hardness alone:
/// * ZQSn5-2: Km = 3.3e-5, HV 213.77 → 1 (the paper's baseline);
/// * QSn6-6-3: measured 42.99 % lower wear rate → 0.5701 (hardness alone, 213.77/242.8,
///   would give 0.88): Km ≈ 2.14e-5 at HV 242.8;
/// * carbon-fibre PEEK: the paper's projection of 90 540 cycles to 0.8 mm →
///   45 268.2 / 90 540 = 0.49998.
pub const fn wear_factor_q32(m: Material) -> u64 {
    match m {
        Material::ZQSn5_2 => ONE_Q32,
        Material::QSn6_6_3 => 2_448_560_855,
        Material::CfPeek => 2_147_398_218,
    }
}

/// Wear limit and warning level.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WearConfig {
    /// Wear depth at which the cone is worn out, nm (0.8 mm by default: the pose
    /// tolerance gives 0.91 mm).
    pub limit_nm: u32,
    /// Warn from this percentage of the limit on (80 % by default).
    pub warn_pct: u8,
    /// This machine's nominal load–distance per cycle, Q63.1 mN·µm: the unit of the
    /// remaining-life figure ([`Odometer::remaining_cycles`]). The paper's machine
    /// ([`W_NOM_Q1`]) by default; another machine's from its force model. The wear
    /// itself does not depend on it (it follows the measured load–distance).
    pub nominal_w_q1: u64,
}

impl WearConfig {
    /// 0.8 mm, warning at 80 %.
    pub const DEFAULT: Self = Self {
        limit_nm: 800_000,
        warn_pct: 80,
        nominal_w_q1: W_NOM_Q1,
    };

    /// Validate: limit 10 µm – 5 mm, warning 1–99 %.
    pub const fn new(limit_nm: u32, warn_pct: u8) -> Option<Self> {
        if limit_nm < 10_000 || limit_nm > 5_000_000 || warn_pct == 0 || warn_pct > 99 {
            None
        } else {
            Some(Self {
                limit_nm,
                warn_pct,
                nominal_w_q1: W_NOM_Q1,
            })
        }
    }
}

impl Default for WearConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Equivalent nominal cycles (Q32.32) at which the depth reaches `depth_nm`.
pub const fn e_at_depth_q32(depth_nm: u32) -> u64 {
    // In u128: (depth + c) << 32 overflows u64 for depths near u32::MAX.
    let x = crate::fixed::div_u128((depth_nm as u128 + C_NM as u128) << 32, A_NM as u128) as u64;
    pow_q32(x, INV_B_Q32).saturating_sub(M0_Q32)
}

/// Depth (nm) after `e_q32` equivalent nominal cycles.
pub const fn depth_nm(e_q32: u64) -> u32 {
    let p = pow_q32(e_q32.saturating_add(M0_Q32), B_Q32);
    // Rounded to the nearest nm (so the depth read at `e_at_depth_q32(d)` is `d`).
    let h = ((A_NM as u128 * p as u128 + (1 << 31)) >> 32) as u64;
    let d = h.saturating_sub(C_NM);
    if d > u32::MAX as u64 {
        u32::MAX
    } else {
        d as u32
    }
}

/// Equivalent nominal cycles (Q32.32) of a load–distance `w_q1` on `material`.
pub const fn equivalent_cycles_q32(w_q1: u64, material: Material) -> u64 {
    let e = crate::fixed::div_u128(
        wear_factor_q32(material) as u128 * w_q1 as u128,
        W_NOM_Q1 as u128,
    );
    if e > u64::MAX as u128 {
        u64::MAX
    } else {
        e as u64
    }
}

/// How worn the cone is.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum WearLevel {
    /// Below the warning level.
    Ok,
    /// At or above the warning level: warn on every cycle.
    Warning,
    /// At or above the limit: no new docking until the cone is replaced.
    Limit,
}

impl WearLevel {
    /// Stable name.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Ok => "ok",
            Self::Warning => "warning",
            Self::Limit => "limit",
        }
    }
}

/// Longest cone serial, bytes.
pub const SERIAL_MAX: usize = 20;

/// The installed cone and its own counters.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Cone {
    /// Sequence number of the installation (1 = the first cone).
    pub id: u16,
    /// Material.
    pub material: Material,
    /// Serial number (ASCII, `serial_len` bytes used).
    pub serial: [u8; SERIAL_MAX],
    /// Bytes of `serial` used.
    pub serial_len: u8,
    /// Lifetime cycle count when it was installed.
    pub installed_at_cycle: u32,
    /// Docking cycles on this cone.
    pub cycles: u32,
    /// Load–distance on this cone, Q63.1 mN·µm.
    pub w_q1: u64,
    /// The cone's own bore when new, µm (0: not measured; the nominal 26.000 mm is
    /// assumed then). Measured wear is the bore's growth from it (`docs/physics.md` §7).
    pub baseline_um: u32,
}

impl Cone {
    /// A new cone with zero counters.
    pub fn new(id: u16, material: Material, serial: &str, installed_at_cycle: u32) -> Self {
        let mut s = [0u8; SERIAL_MAX];
        let n = serial.len().min(SERIAL_MAX);
        if let (Some(dst), Some(src)) = (s.get_mut(..n), serial.as_bytes().get(..n)) {
            dst.copy_from_slice(src);
        }
        Self {
            id,
            material,
            serial: s,
            serial_len: n as u8,
            installed_at_cycle,
            cycles: 0,
            w_q1: 0,
            baseline_um: 0,
        }
    }

    /// The baseline bore, µm, if one was measured.
    pub fn baseline(&self) -> Option<u32> {
        (self.baseline_um != 0).then_some(self.baseline_um)
    }

    /// The serial as text (lossy for non-UTF-8 garbage: empty).
    pub fn serial_str(&self) -> &str {
        self.serial
            .get(..self.serial_len as usize)
            .and_then(|b| core::str::from_utf8(b).ok())
            .unwrap_or("")
    }
}

/// Totals over the machine's life, all cones; never reset.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Lifetime {
    /// Docking cycles completed.
    pub cycles: u32,
    /// Load–distance, Q63.1 mN·µm.
    pub w_q1: u64,
    /// Overload trips.
    pub overload_events: u32,
    /// Faults latched (all kinds).
    pub faults: u32,
    /// Highest force ever measured, mN.
    pub peak_force_mn: i32,
    /// Cones installed (the first counts).
    pub cones_installed: u16,
}

/// Integrates `(F_prev + F) · |Δx|` over consecutive samples in contact.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct StrokeIntegrator {
    last: Option<(i32, i32)>,
}

impl StrokeIntegrator {
    /// Add the sample (`pos_um`, `force_mn`); returns the Q63.1 increment. Negative
    /// forces (noise around zero) count as zero: wear never runs backwards.
    pub fn add(&mut self, pos_um: i32, force_mn: i32) -> u64 {
        let f = force_mn.max(0) as u64;
        let inc = match self.last {
            Some((p0, f0)) => (f0.max(0) as u64 + f) * pos_um.abs_diff(p0) as u64,
            None => 0,
        };
        self.last = Some((pos_um, force_mn));
        inc
    }

    /// Break the chain (the rod left the cone, or samples stopped).
    pub fn break_chain(&mut self) {
        self.last = None;
    }
}

/// What a completed cycle did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct CycleSummary {
    /// Lifetime cycle number.
    pub lifetime_cycle: u32,
    /// Cycle number on this cone.
    pub cone_cycle: u32,
    /// This cycle's load–distance, Q63.1 mN·µm.
    pub w_q1: u64,
    /// Cone wear depth after it, nm.
    pub wear_nm: u32,
    /// Remaining life after it, nominal cycles.
    pub remaining_cycles: u32,
    /// Wear level after it.
    pub level: WearLevel,
}

/// The odometer.
#[derive(Clone, Debug)]
pub struct Odometer {
    cfg: WearConfig,
    cone: Cone,
    life: Lifetime,
    integ: StrokeIntegrator,
    /// Load–distance since the last completed cycle, Q63.1.
    pending_q1: u64,
    /// Load–distance of the cycle in progress already counted into the cone by
    /// [`Odometer::fold_pending`] (a fault's rest), Q63.1: it is still the cycle's, and
    /// its history entry carries it when the cycle completes (issue 35).
    cycle_folded_q1: u64,
    last_cycle_q1: u64,
    e_limit_q32: u64,
    e_warn_q32: u64,
    /// Derived values, refreshed whenever the cone's load–distance changes (the power
    /// law costs ~64 wide multiplies: not something to redo on every status read).
    derived: Derived,
}

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Derived {
    e_q32: u64,
    wear_nm: u32,
    remaining_cycles: u32,
}

impl Odometer {
    /// An odometer with restored (or fresh) counters.
    pub fn new(cfg: WearConfig, cone: Cone, life: Lifetime) -> Self {
        let warn_nm = (cfg.limit_nm as u64 * cfg.warn_pct as u64 / 100) as u32;
        let mut o = Self {
            cfg,
            cone,
            life,
            integ: StrokeIntegrator::default(),
            pending_q1: 0,
            cycle_folded_q1: 0,
            last_cycle_q1: 0,
            e_limit_q32: e_at_depth_q32(cfg.limit_nm),
            e_warn_q32: e_at_depth_q32(warn_nm),
            derived: Derived::default(),
        };
        o.refresh();
        o
    }

    fn refresh(&mut self) {
        let e_q32 = equivalent_cycles_q32(self.cone.w_q1, self.cone.material);
        let left = self.e_limit_q32.saturating_sub(e_q32) as u128;
        let k = wear_factor_q32(self.cone.material).max(1) as u128;
        // Equivalent nominal cycles of the paper's machine → this machine's cycles.
        let per_cycle = k * self.cfg.nominal_w_q1.max(1) as u128;
        self.derived = Derived {
            e_q32,
            wear_nm: depth_nm(e_q32),
            remaining_cycles: crate::fixed::div_u128(left * W_NOM_Q1 as u128, per_cycle)
                .min(u32::MAX as u128) as u32,
        };
    }

    /// A sample while the rod is in the cone.
    pub fn on_contact_sample(&mut self, pos_um: i32, force_mn: i32) {
        let inc = self.integ.add(pos_um, force_mn);
        self.pending_q1 = self.pending_q1.saturating_add(inc);
    }

    /// The rod is out of the cone (or sampling stopped): the next sample starts a chain.
    pub fn end_contact(&mut self) {
        self.integ.break_chain();
    }

    /// A docking cycle starts: nothing of an earlier cycle is its.
    pub fn start_cycle(&mut self) {
        self.cycle_folded_q1 = 0;
    }

    /// Close a completed docking cycle: its load–distance goes to the cone and the
    /// lifetime totals; both cycle counters advance. The cycle's load–distance
    /// ([`CycleSummary::w_q1`], the history entry's) is the whole cycle's: what a fault's
    /// rest counted into the cone already ([`Self::fold_pending`]) and the rest. (Until
    /// issue 35 it was the rest only: after a `stop` during extraction and a
    /// `clear-fault`, the entry read the recovery's last millimetres, 0.106 N·mm, while
    /// the cone had grown by the whole cycle.)
    pub fn complete_cycle(&mut self) -> CycleSummary {
        self.integ.break_chain();
        let w = core::mem::take(&mut self.pending_q1);
        let whole = w.saturating_add(core::mem::take(&mut self.cycle_folded_q1));
        self.last_cycle_q1 = whole;
        self.cone.w_q1 = self.cone.w_q1.saturating_add(w);
        self.cone.cycles = self.cone.cycles.saturating_add(1);
        self.life.w_q1 = self.life.w_q1.saturating_add(w);
        self.life.cycles = self.life.cycles.saturating_add(1);
        self.refresh();
        CycleSummary {
            lifetime_cycle: self.life.cycles,
            cone_cycle: self.cone.cycles,
            w_q1: whole,
            wear_nm: self.wear_nm(),
            remaining_cycles: self.remaining_cycles(),
            level: self.level(),
        }
    }

    /// A cycle cut short (a fault, an overload): the load–distance it put on the cone so
    /// far goes to the cone and the lifetime totals now, without counting a cycle, so
    /// that the next snapshot carries it. Returns the amount, Q63.1.
    pub fn fold_pending(&mut self) -> u64 {
        let w = core::mem::take(&mut self.pending_q1);
        self.cycle_folded_q1 = self.cycle_folded_q1.saturating_add(w);
        if w > 0 {
            self.cone.w_q1 = self.cone.w_q1.saturating_add(w);
            self.life.w_q1 = self.life.w_q1.saturating_add(w);
            self.refresh();
        }
        w
    }

    /// What a reset must not lose: the counters as they are now, the cycle in progress
    /// included (see [`Journal`]).
    // Out of line: the boot, the control task after every step and the console read
    // it; inlined at each, the image is 328 B larger (issue 31's measurement, which
    // kept this hint and dropped the ones under 256 B; a call more a step).
    #[inline(never)]
    pub fn journal(&self) -> Journal {
        Journal {
            cone_id: self.cone.id,
            cone_cycles: self.cone.cycles,
            cone_w_q1: self.cone.w_q1.saturating_add(self.pending_q1),
            life_cycles: self.life.cycles,
            life_w_q1: self.life.w_q1.saturating_add(self.pending_q1),
        }
    }

    /// After a reset: take what the RAM journal knew beyond the restored counters (the
    /// load–distance of a cycle the reset cut short, or a cycle completed but not yet
    /// written). Every counter only grows: each is the larger of the two, so applying
    /// a journal twice changes nothing. A journal of another cone is ignored. Returns
    /// the cone load–distance recovered, Q63.1 (0: nothing changed).
    pub fn recover(&mut self, j: &Journal) -> u64 {
        if j.cone_id != self.cone.id {
            return 0;
        }
        let gained = j.cone_w_q1.saturating_sub(self.cone.w_q1);
        let changed = gained > 0
            || j.cone_cycles > self.cone.cycles
            || j.life_cycles > self.life.cycles
            || j.life_w_q1 > self.life.w_q1;
        if changed {
            self.cone.w_q1 = self.cone.w_q1.max(j.cone_w_q1);
            self.cone.cycles = self.cone.cycles.max(j.cone_cycles);
            self.life.w_q1 = self.life.w_q1.max(j.life_w_q1);
            self.life.cycles = self.life.cycles.max(j.life_cycles);
            self.refresh();
        }
        gained
    }

    /// Count an overload trip with its force.
    pub fn record_overload(&mut self, force_mn: i32) {
        self.life.overload_events = self.life.overload_events.saturating_add(1);
        self.record_force(force_mn);
    }

    /// Count a latched fault.
    pub fn record_fault(&mut self) {
        self.life.faults = self.life.faults.saturating_add(1);
    }

    /// Track the lifetime peak force.
    pub fn record_force(&mut self, force_mn: i32) {
        self.life.peak_force_mn = self.life.peak_force_mn.max(force_mn);
    }

    /// Record the cone's baseline bore (its diameter when new), µm.
    pub fn set_baseline(&mut self, baseline_um: u32) {
        self.cone.baseline_um = baseline_um;
    }

    /// Install a new cone: new per-cone counters; lifetime totals untouched. Any wear of
    /// an unfinished cycle belongs to the old cone and is dropped with it.
    pub fn replace_cone(&mut self, material: Material, serial: &str) -> &Cone {
        self.life.cones_installed = self.life.cones_installed.saturating_add(1);
        self.cone = Cone::new(
            self.life.cones_installed,
            material,
            serial,
            self.life.cycles,
        );
        self.pending_q1 = 0;
        self.cycle_folded_q1 = 0;
        self.integ.break_chain();
        self.refresh();
        &self.cone
    }

    /// Equivalent nominal cycles of the cone, Q32.32.
    pub fn equivalent_cycles_q32(&self) -> u64 {
        self.derived.e_q32
    }

    /// Cone wear depth, nm.
    pub fn wear_nm(&self) -> u32 {
        self.derived.wear_nm
    }

    /// Remaining life in nominal cycles of this cone's material.
    pub fn remaining_cycles(&self) -> u32 {
        self.derived.remaining_cycles
    }

    /// Wear level.
    pub fn level(&self) -> WearLevel {
        let e = self.equivalent_cycles_q32();
        if e >= self.e_limit_q32 {
            WearLevel::Limit
        } else if e >= self.e_warn_q32 {
            WearLevel::Warning
        } else {
            WearLevel::Ok
        }
    }

    /// The installed cone.
    pub fn cone(&self) -> &Cone {
        &self.cone
    }

    /// Lifetime totals.
    pub fn lifetime(&self) -> &Lifetime {
        &self.life
    }

    /// Load–distance of the last completed cycle, Q63.1.
    pub fn last_cycle_q1(&self) -> u64 {
        self.last_cycle_q1
    }

    /// Load–distance of the cycle in progress so far, Q63.1.
    pub fn pending_q1(&self) -> u64 {
        self.pending_q1
    }

    /// Configuration.
    pub fn config(&self) -> &WearConfig {
        &self.cfg
    }
}

/// Record kinds in the flash log (every user of the log, in one place).
pub mod kind {
    /// Counter snapshot ([`super::StateRecord`]), after every cycle and every event.
    pub const STATE: u8 = 1;
    /// Cone installation ([`super::Cone`] identity).
    pub const CONE: u8 = 2;
    /// A technician's bore measurement (console `measure`).
    pub const MEASURE: u8 = 3;
    /// Load-cell calibration (offset, Q32.32 mN per count).
    pub const CALIBRATION: u8 = 4;
    /// Maintenance PIN, salted and hashed.
    pub const PIN: u8 = 5;
    /// Audit record of a maintenance action.
    pub const AUDIT: u8 = 6;
    /// Resets by cause ([`crate::diag::ResetCounts`]).
    pub const RESETS: u8 = 7;
    /// The last crash ([`crate::diag::Crash`]).
    pub const CRASH: u8 = 8;
    /// Machine settings ([`crate::controller::Settings`]).
    pub const SETTINGS: u8 = 9;
    /// A retired cone's summary ([`super::RetiredCone`]), written when it is replaced.
    pub const RETIRED: u8 = 10;
    /// The Modbus line's settings ([`crate::modbus::ModbusSettings`]): unit address and
    /// baud rate (console `modbus`).
    pub const MODBUS: u8 = 11;
    /// The images (issue 21, [`crate::update::ImageRecord`]): an update marked, a trial
    /// confirmed, a rollback; what `version` reports as the previous image.
    pub const IMAGE: u8 = 12;
}

/// What the odometer's log keeps through its sector moves: the last
/// [`READINGS_KEPT`] micrometer readings and the last [`RETIRED_KEPT`] retired cones,
/// the newest record of every other kind.
// Indexing in a constant is evaluated by the compiler: out of bounds fails the build, it
// cannot panic at run time.
#[allow(clippy::indexing_slicing)]
pub const LOG_KEEP: crate::storage::Keep = {
    let mut k = crate::storage::Keep::ONE_EACH;
    k.0[kind::MEASURE as usize] = READINGS_KEPT as u8;
    k.0[kind::RETIRED as usize] = RETIRED_KEPT as u8;
    k
};
/// Open the odometer's log on `flash` (one sector per erase sector) with [`LOG_KEEP`]:
/// every user of the odometer's flash opens it this way.
pub fn open_log<F: embedded_storage::nor_flash::NorFlash>(
    flash: F,
) -> Result<
    (crate::storage::RecordLog<F>, crate::storage::OpenReport),
    crate::storage::StorageError<F::Error>,
> {
    crate::storage::RecordLog::open_keeping(flash, F::ERASE_SIZE, LOG_KEEP)
}

/// Nominal bore of a new cone, µm (D2 = 26 mm, `docs/physics.md` §1): assumed as the baseline of
/// a cone whose own was not measured.
pub const NOMINAL_BORE_UM: u32 = 26_000;

/// Micrometer readings the log keeps (all cones together: the current cone's last 32
/// at least, as a replacement adds a baseline or none).
pub const READINGS_KEPT: usize = 40;
/// Retired cones' summaries the log keeps (at 45 000 cycles a cone, centuries of use).
pub const RETIRED_KEPT: usize = 8;

/// A technician's bore reading (console `measure`), as persisted: record kind
/// [`kind::MEASURE`], 19 bytes (`MeasurementLayout`); records of 18 bytes, from before
/// the flags byte, are readings (`ReadingLayout`):
///
/// ```text
///  0         4                8         10         14         18      19
///  +---------+----------------+---------+----------+----------+-------+
///  | bore_um | lifetime cycle | cone id | cone     | model    | flags |
///  | u32     | u32            | u16     | cycle u32| wear nm  | u8    |
///  +---------+----------------+---------+----------+----------+-------+
///  model wear: the odometer's at the time (it gives the reading's E)
///  flags bit 0: the cone's baseline, its bore when new
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Measurement {
    /// Bore diameter, µm.
    pub bore_um: u32,
    /// Lifetime cycle count when taken.
    pub lifetime_cycle: u32,
    /// The cone measured.
    pub cone_id: u16,
    /// The cone's cycle count when taken.
    pub cone_cycle: u32,
    /// The model's wear then, nm.
    pub model_nm: u32,
    /// The cone's baseline (bore when new), not a wear reading.
    pub baseline: bool,
}

/// The first 18 bytes of a [`Measurement`] record: the whole record before the flags
/// byte existed.
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct ReadingLayout {
    bore_um: U32,
    lifetime_cycle: U32,
    cone_id: U16,
    cone_cycle: U32,
    model_nm: U32,
}

/// A [`Measurement`] record (drawn there).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct MeasurementLayout {
    reading: ReadingLayout,
    flags: u8,
}

/// Bytes of a persisted [`Measurement`].
pub const MEASUREMENT_LEN: usize = size_of::<MeasurementLayout>();

impl Measurement {
    /// Encode.
    pub fn to_bytes(&self) -> [u8; MEASUREMENT_LEN] {
        let layout = MeasurementLayout {
            reading: ReadingLayout {
                bore_um: self.bore_um.into(),
                lifetime_cycle: self.lifetime_cycle.into(),
                cone_id: self.cone_id.into(),
                cone_cycle: self.cone_cycle.into(),
                model_nm: self.model_nm.into(),
            },
            flags: u8::from(self.baseline),
        };
        zerocopy::transmute!(layout)
    }

    /// Decode (19 bytes, or 18 from before the flags byte).
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let (r, flags) = match MeasurementLayout::read_from_bytes(b) {
            Ok(m) => (m.reading, m.flags),
            Err(_) => (ReadingLayout::read_from_bytes(b).ok()?, 0),
        };
        Some(Self {
            bore_um: r.bore_um.get(),
            lifetime_cycle: r.lifetime_cycle.get(),
            cone_id: r.cone_id.get(),
            cone_cycle: r.cone_cycle.get(),
            model_nm: r.model_nm.get(),
            baseline: flags & 1 == 1,
        })
    }

    /// Measured wear against `baseline_um`: the bore's growth (not halved: the wear is
    /// one-sided, `docs/physics.md` §7), nm. Out of line: five callers.
    #[inline(never)]
    pub fn wear_nm(&self, baseline_um: u32) -> i32 {
        let d = self.bore_um as i64 - baseline_um as i64;
        (d * 1000).clamp(i32::MIN as i64, i32::MAX as i64) as i32
    }

    /// As the estimator sees it.
    pub fn reading(&self, baseline_um: u32) -> crate::estimate::Reading {
        crate::estimate::Reading {
            e_q32: e_at_depth_q32(self.model_nm),
            wear_nm: self.wear_nm(baseline_um),
        }
    }
}

/// A cone's identity, the first 28 bytes of a cone record and of a retired cone's
/// summary (little-endian):
///
/// ```text
///  0         2          3            4                      24                  28
///  +---------+----------+------------+----------------------+-------------------+
///  | cone id | material | serial_len | serial (20 B, 0-pad) | installed at      |
///  | u16     | u8 code  | u8 ≤ 20    |                      | lifetime cycle u32|
///  +---------+----------+------------+----------------------+-------------------+
/// ```
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct ConeIdLayout {
    id: U16,
    material: u8,
    serial_len: u8,
    serial: [u8; SERIAL_MAX],
    installed_at_cycle: U32,
}

impl ConeIdLayout {
    fn of(c: &Cone) -> Self {
        Self {
            id: c.id.into(),
            material: c.material.code(),
            serial_len: c.serial_len,
            serial: c.serial,
            installed_at_cycle: c.installed_at_cycle.into(),
        }
    }

    /// The cone, with the counters and baseline its record holds beside the identity
    /// (`w_q1` is never in a record); `None` for an unknown material or a serial
    /// longer than [`SERIAL_MAX`].
    fn cone(&self, cycles: u32, baseline_um: u32) -> Option<Cone> {
        if usize::from(self.serial_len) > SERIAL_MAX {
            return None;
        }
        Some(Cone {
            id: self.id.get(),
            material: Material::from_code(self.material)?,
            serial: self.serial,
            serial_len: self.serial_len,
            installed_at_cycle: self.installed_at_cycle.get(),
            cycles,
            w_q1: 0,
            baseline_um,
        })
    }
}

/// A retired cone's summary, as persisted: record kind [`kind::RETIRED`], 48 bytes
/// (`RetiredLayout`, little-endian):
///
/// ```text
///  0                  28       32            36               40            44        48
///  +------------------+--------+-------------+----------------+-------------+---------+
///  | cone identity    | cycles | model wear  | last measured  | baseline µm | readings|
///  | (ConeIdLayout)   | u32    | nm u32      | wear nm i32    | u32 (0:none)| taken   |
///  +------------------+--------+-------------+----------------+-------------+---------+
///  last measured wear: i32::MIN if never measured
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct RetiredCone {
    /// The cone (id, material, serial, installation, cycles, baseline).
    pub cone: Cone,
    /// The model's wear at retirement, nm.
    pub model_nm: u32,
    /// The last reading's measured wear, nm.
    pub measured_nm: Option<i32>,
    /// Readings taken on it.
    pub readings: u32,
}

/// A [`RetiredCone`] record (drawn there).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct RetiredLayout {
    cone: ConeIdLayout,
    cycles: U32,
    model_nm: U32,
    measured_nm: I32,
    baseline_um: U32,
    readings: U32,
}

/// Bytes of a persisted [`RetiredCone`].
pub const RETIRED_LEN: usize = size_of::<RetiredLayout>();

impl RetiredCone {
    /// Encode.
    pub fn to_bytes(&self) -> [u8; RETIRED_LEN] {
        let layout = RetiredLayout {
            cone: ConeIdLayout::of(&self.cone),
            cycles: self.cone.cycles.into(),
            model_nm: self.model_nm.into(),
            measured_nm: self.measured_nm.unwrap_or(i32::MIN).into(),
            baseline_um: self.cone.baseline_um.into(),
            readings: self.readings.into(),
        };
        zerocopy::transmute!(layout)
    }

    /// Decode.
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let l = RetiredLayout::read_from_bytes(b).ok()?;
        let measured = l.measured_nm.get();
        Some(Self {
            cone: l.cone.cone(l.cycles.get(), l.baseline_um.get())?,
            model_nm: l.model_nm.get(),
            measured_nm: (measured != i32::MIN).then_some(measured),
            readings: l.readings.get(),
        })
    }
}

/// Snapshot of every counter, as persisted: record kind [`kind::STATE`], 48 bytes
/// (`StateLayout`, little-endian):
///
/// ```text
///  0          4          8             16            24               28
///  +----------+----------+-------------+-------------+----------------+---------------+
///  | lifetime | cone     | cone.w_q1   | lifetime    | overload_events| peak_force_mn |
///  | cycles   | cycles   | u64         | w_q1 u64    | u32            | i32           |
///  +----------+----------+-------------+-------------+----------------+---------------+
///  32         36        38         39      40                 48
///  +----------+---------+----------+-------+------------------+
///  | lifetime | cone id | material | flags | last_cycle_q1    |
///  | faults   | u16     | u8 code  | u8    | u64              |
///  +----------+---------+----------+-------+------------------+
///  flags bit 0: written at the end of a cycle
/// ```
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StateRecord {
    /// Lifetime totals (cones_installed is restored from the cone record).
    pub life: Lifetime,
    /// Cone id the per-cone counters belong to.
    pub cone_id: u16,
    /// Cone material.
    pub material: Material,
    /// Cone cycles.
    pub cone_cycles: u32,
    /// Cone load–distance, Q63.1.
    pub cone_w_q1: u64,
    /// The last completed cycle's load–distance, Q63.1.
    pub last_cycle_q1: u64,
    /// Written at the end of a cycle (a history entry).
    pub cycle_end: bool,
}

/// A [`StateRecord`] (drawn there).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct StateLayout {
    life_cycles: U32,
    cone_cycles: U32,
    cone_w_q1: U64,
    life_w_q1: U64,
    overload_events: U32,
    peak_force_mn: I32,
    faults: U32,
    cone_id: U16,
    material: u8,
    flags: u8,
    last_cycle_q1: U64,
}

/// Bytes of a persisted [`StateRecord`].
pub const STATE_LEN: usize = size_of::<StateLayout>();

/// A cone record, kind [`kind::CONE`], 32 bytes (little-endian): the identity, then the
/// baseline bore (0: none; records written before the baseline existed hold 0 there).
///
/// ```text
///  0                  28            32
///  +------------------+-------------+
///  | cone identity    | baseline µm |
///  | (ConeIdLayout)   | u32         |
///  +------------------+-------------+
/// ```
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct ConeLayout {
    cone: ConeIdLayout,
    baseline_um: U32,
}

/// Bytes of a persisted cone record.
pub const CONE_LEN: usize = size_of::<ConeLayout>();

impl StateRecord {
    /// Snapshot of an odometer.
    pub fn of(o: &Odometer, cycle_end: bool) -> Self {
        Self {
            life: o.life,
            cone_id: o.cone.id,
            material: o.cone.material,
            cone_cycles: o.cone.cycles,
            cone_w_q1: o.cone.w_q1,
            last_cycle_q1: o.last_cycle_q1,
            cycle_end,
        }
    }

    /// Encode.
    pub fn to_bytes(&self) -> [u8; STATE_LEN] {
        let layout = StateLayout {
            life_cycles: self.life.cycles.into(),
            cone_cycles: self.cone_cycles.into(),
            cone_w_q1: self.cone_w_q1.into(),
            life_w_q1: self.life.w_q1.into(),
            overload_events: self.life.overload_events.into(),
            peak_force_mn: self.life.peak_force_mn.into(),
            faults: self.life.faults.into(),
            cone_id: self.cone_id.into(),
            material: self.material.code(),
            flags: u8::from(self.cycle_end),
            last_cycle_q1: self.last_cycle_q1.into(),
        };
        zerocopy::transmute!(layout)
    }

    /// Decode; `None` if the bytes are not a state record.
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let l = StateLayout::read_from_bytes(b).ok()?;
        Some(Self {
            life: Lifetime {
                cycles: l.life_cycles.get(),
                w_q1: l.life_w_q1.get(),
                overload_events: l.overload_events.get(),
                peak_force_mn: l.peak_force_mn.get(),
                faults: l.faults.get(),
                cones_installed: 0,
            },
            cone_id: l.cone_id.get(),
            material: Material::from_code(l.material)?,
            cone_cycles: l.cone_cycles.get(),
            cone_w_q1: l.cone_w_q1.get(),
            last_cycle_q1: l.last_cycle_q1.get(),
            cycle_end: l.flags & 1 == 1,
        })
    }
}

/// Encode a cone's identity and baseline (a cone record, drawn at `ConeLayout`).
pub fn cone_to_bytes(c: &Cone) -> [u8; CONE_LEN] {
    let layout = ConeLayout {
        cone: ConeIdLayout::of(c),
        baseline_um: c.baseline_um.into(),
    };
    zerocopy::transmute!(layout)
}

/// Decode a cone record (counters zero; they come from the state record).
pub fn cone_from_bytes(b: &[u8]) -> Option<Cone> {
    let l = ConeLayout::read_from_bytes(b).ok()?;
    l.cone.cone(0, l.baseline_um.get())
}

/// The counters as a reset must find them: kept by the board in RAM that no reset
/// initialises, rewritten after every control step, read back at boot
/// ([`Odometer::recover`]). The flash snapshot is written only at rest (an erase or a
/// program stalls the CPU); the journal covers a reset between (watchdog, pin, crash,
/// brown-out with the supply still holding SRAM). A power cut loses SRAM and with it
/// at most the cycle in progress.
///
/// In RAM, 16 words: a magic word, then every field followed by its bitwise complement
/// (a field of a torn update, or SRAM that lost power, fails the check):
///
/// ```text
///  word  0       1..3        3..5           5..9            9..11           11..15
///       +-------+-----------+--------------+---------------+---------------+---------------+
///       | magic | id, !id   | cone_cycles, | cone_w_q1 lo, | life_cycles,  | life_w_q1 lo, |
///       |       | (u16 in   | !cone_cycles | hi, !lo, !hi  | !life_cycles  | hi, !lo, !hi  |
///       |       |  a word)  |              |               |               |               |
///       +-------+-----------+--------------+---------------+---------------+---------------+
///  word 15: JOURNAL_MAGIC again (written last)
/// ```
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Journal {
    /// Cone the per-cone counters belong to.
    pub cone_id: u16,
    /// Cone cycles completed.
    pub cone_cycles: u32,
    /// Cone load–distance, the cycle in progress included, Q63.1 mN·µm.
    pub cone_w_q1: u64,
    /// Lifetime cycles completed.
    pub life_cycles: u32,
    /// Lifetime load–distance, the cycle in progress included, Q63.1 mN·µm.
    pub life_w_q1: u64,
}

/// Words of a [`Journal`] in RAM.
pub const JOURNAL_WORDS: usize = 16;
/// The journal's magic word (first and last).
pub const JOURNAL_MAGIC: u32 = 0x70DC_1A11;

impl Journal {
    /// The RAM image.
    pub fn to_words(&self) -> [u32; JOURNAL_WORDS] {
        let (cw, lw) = (self.cone_w_q1, self.life_w_q1);
        let f = [
            self.cone_id as u32,
            self.cone_cycles,
            cw as u32,
            (cw >> 32) as u32,
            self.life_cycles,
            lw as u32,
            (lw >> 32) as u32,
        ];
        [
            JOURNAL_MAGIC,
            f[0],
            !f[0],
            f[1],
            !f[1],
            f[2],
            f[3],
            !f[2],
            !f[3],
            f[4],
            !f[4],
            f[5],
            f[6],
            !f[5],
            !f[6],
            JOURNAL_MAGIC,
        ]
    }

    /// From a RAM image; `None` unless every check holds.
    pub fn from_words(w: &[u32; JOURNAL_WORDS]) -> Option<Self> {
        let [m0, id, nid, cc, ncc, cwl, cwh, ncwl, ncwh, lc, nlc, lwl, lwh, nlwl, nlwh, m1] = *w;
        let ok = m0 == JOURNAL_MAGIC
            && m1 == JOURNAL_MAGIC
            && id == !nid
            && id <= u16::MAX as u32
            && cc == !ncc
            && cwl == !ncwl
            && cwh == !ncwh
            && lc == !nlc
            && lwl == !nlwl
            && lwh == !nlwh;
        ok.then_some(Self {
            cone_id: id as u16,
            cone_cycles: cc,
            cone_w_q1: (cwh as u64) << 32 | cwl as u64,
            life_cycles: lc,
            life_w_q1: (lwh as u64) << 32 | lwl as u64,
        })
    }
}

/// Rebuild an odometer from the latest cone and state records (either may be absent:
/// a fresh machine starts with cone 1 of `default_material`). State records of another
/// cone than the latest cone record (a cut between the two writes of a replacement)
/// keep the lifetime totals and start the new cone at zero.
pub fn restore(
    cfg: WearConfig,
    cone: Option<Cone>,
    state: Option<StateRecord>,
    default_material: Material,
) -> Odometer {
    let mut life = state.map(|s| s.life).unwrap_or_default();
    let mut cone = cone.unwrap_or_else(|| Cone::new(1, default_material, "", 0));
    life.cones_installed = cone.id.max(1);
    if let Some(s) = state {
        if s.cone_id == cone.id && s.material == cone.material {
            cone.cycles = s.cone_cycles;
            cone.w_q1 = s.cone_w_q1;
        }
    }
    let mut o = Odometer::new(cfg, cone, life);
    if let Some(s) = state {
        o.last_cycle_q1 = s.last_cycle_q1;
    }
    o
}

#[cfg(test)]
mod tests {
    use super::*;

    fn eq17_nm(m: f64) -> f64 {
        (0.01372 * m.powf(0.3813) - 0.01774) * 1e6
    }

    #[test]
    fn remaining_life_counts_in_this_machines_own_cycles() {
        // A machine whose nominal cycle carries 1.5× the load–distance: the same wear,
        // two thirds of the remaining cycles.
        let mut c = Cone::new(1, Material::ZQSn5_2, "A1", 0);
        c.w_q1 = W_NOM_Q1 * 3;
        let cfg = WearConfig {
            nominal_w_q1: W_NOM_Q1 * 3 / 2,
            ..WearConfig::DEFAULT
        };
        let heavy = Odometer::new(cfg, c, Lifetime::default());
        let paper = Odometer::new(WearConfig::DEFAULT, c, Lifetime::default());
        assert_eq!(heavy.wear_nm(), paper.wear_nm());
        let (h, p) = (
            heavy.remaining_cycles() as i64,
            paper.remaining_cycles() as i64,
        );
        assert!((h - p * 2 / 3).abs() <= 1, "{h} vs {p}");
    }

    fn nominal(n: u32) -> Odometer {
        let mut c = Cone::new(1, Material::ZQSn5_2, "A1", 0);
        c.w_q1 = W_NOM_Q1 * n as u64;
        c.cycles = n;
        Odometer::new(WearConfig::DEFAULT, c, Lifetime::default())
    }

    #[test]
    fn depth_at_the_limit_reads_the_limit() {
        for d in [640_000, 800_000, 10_000, 5_000_000] {
            assert_eq!(depth_nm(e_at_depth_q32(d)), d);
        }
        assert!(
            e_at_depth_q32(u32::MAX) > e_at_depth_q32(5_000_000),
            "no overflow at the top"
        );
    }

    #[test]
    fn a_cut_short_cycle_lost_its_load_distance() {
        let mut o = nominal(10);
        let w0 = o.cone().w_q1;
        for (i, f) in [(0, 10_000), (500, 20_000), (1_000, 30_000)] {
            o.on_contact_sample(i, f);
        }
        let pending = o.pending_q1();
        assert!(pending > 0);
        // A fault ends the cycle early: its wear is the cone's, no cycle is counted.
        assert_eq!(o.fold_pending(), pending);
        assert_eq!(o.cone().w_q1, w0 + pending);
        assert_eq!(o.cone().cycles, 10);
        assert_eq!(o.pending_q1(), 0);
        assert_eq!(o.fold_pending(), 0, "folded once");
    }

    /// Issue 35: a cycle stopped (its load–distance so far folded into the cone at the
    /// fault's rest) and then completed by the recovery: its summary, the history
    /// entry's, is the whole cycle's; the cone counts each part once.
    #[test]
    fn a_cycle_folded_at_a_fault_and_completed_after_is_summed_whole() {
        let mut o = nominal(10);
        let w0 = o.cone().w_q1;
        o.start_cycle();
        o.on_contact_sample(0, 10_000);
        o.on_contact_sample(1_000, 30_000);
        let first = o.fold_pending();
        o.end_contact();
        o.on_contact_sample(1_000, 20_000);
        o.on_contact_sample(1_500, 5_000);
        let rest = o.pending_q1();
        let c = o.complete_cycle();
        assert_eq!(c.w_q1, first + rest, "the whole cycle");
        assert_eq!(o.last_cycle_q1(), first + rest);
        assert_eq!(o.cone().w_q1, w0 + first + rest, "each part once");
        assert_eq!(o.cone().cycles, 11);
        // A folded part of a cycle that never completed is not the next cycle's.
        o.on_contact_sample(0, 10_000);
        o.on_contact_sample(1_000, 10_000);
        assert!(o.fold_pending() > 0);
        o.start_cycle();
        o.on_contact_sample(0, 10_000);
        o.on_contact_sample(500, 10_000);
        let only = o.pending_q1();
        assert_eq!(o.complete_cycle().w_q1, only);
    }

    #[test]
    fn a_reset_mid_cycle_lost_its_load_distance() {
        let mut before = nominal(10);
        before.on_contact_sample(0, 10_000);
        before.on_contact_sample(2_000, 50_000);
        let j = before.journal();
        let words = j.to_words();
        assert_eq!(Journal::from_words(&words), Some(j));
        // Rebooted from the flash snapshot (10 cycles, no pending wear).
        let mut after = nominal(10);
        let gained = after.recover(&j);
        assert_eq!(gained, before.pending_q1());
        assert_eq!(after.cone().w_q1, before.journal().cone_w_q1);
        assert!(after.wear_nm() >= before.wear_nm());
        // Twice is once; a stale journal never takes anything back.
        assert_eq!(after.recover(&j), 0);
        let mut stale = j;
        stale.cone_w_q1 = 0;
        stale.cone_cycles = 0;
        assert_eq!(after.recover(&stale), 0);
        assert_eq!(after.cone().w_q1, j.cone_w_q1);
        // Another cone's journal is not this cone's wear.
        let mut other = nominal(10);
        let mut j2 = j;
        j2.cone_id = 2;
        assert_eq!(other.recover(&j2), 0);
        assert_eq!(other.cone().w_q1, nominal(10).cone().w_q1);
    }

    #[test]
    fn a_torn_or_powered_off_journal_is_refused() {
        let j = nominal(3).journal();
        let w = j.to_words();
        for i in 0..JOURNAL_WORDS {
            let mut t = w;
            t[i] ^= 1 << (i % 32);
            assert_eq!(Journal::from_words(&t), None, "word {i} flipped");
        }
        assert_eq!(Journal::from_words(&[0; JOURNAL_WORDS]), None);
        assert_eq!(Journal::from_words(&[u32::MAX; JOURNAL_WORDS]), None);
    }

    #[test]
    fn constants() {
        assert!((M0_Q32 as f64 / 4294967296.0 - 1.961_921_5).abs() < 1e-6);
        assert!((e_at_depth_q32(800_000) as f64 / 4294967296.0 - 45_268.199).abs() < 0.01);
        assert_eq!(depth_nm(0), 0);
    }

    #[test]
    fn within_one_percent_of_eq17_from_200_cycles_to_the_limit() {
        let mut m = 200;
        while m <= 45_270 {
            let h = nominal(m).wear_nm() as f64;
            let rel = (h - eq17_nm(m as f64)).abs() / eq17_nm(m as f64);
            assert!(
                rel < 0.01,
                "m = {m}: {h} nm vs Eq.17 {} nm ({rel})",
                eq17_nm(m as f64)
            );
            m += 97;
        }
        assert_eq!(nominal(45_268).level(), WearLevel::Warning);
        assert_eq!(nominal(45_269).level(), WearLevel::Limit);
        assert_eq!(nominal(1).remaining_cycles(), 45_267);
    }

    #[test]
    fn materials_have_their_own_lives() {
        let life = |m: Material| {
            let o = Odometer::new(
                WearConfig::DEFAULT,
                Cone::new(1, m, "", 0),
                Lifetime::default(),
            );
            o.remaining_cycles()
        };
        assert_eq!(life(Material::ZQSn5_2), 45_268);
        let q = life(Material::QSn6_6_3) as f64;
        assert!((q - 45_268.2 / 0.5701).abs() < 2.0, "{q}");
        let p = life(Material::CfPeek) as f64;
        assert!((p - 90_540.0).abs() / 90_540.0 < 0.005, "{p}");
    }

    #[test]
    fn warning_at_80_percent_and_configurable() {
        let e_warn = e_at_depth_q32(640_000) >> 32;
        assert_eq!(nominal(e_warn as u32).level(), WearLevel::Ok);
        assert_eq!(nominal(e_warn as u32 + 1).level(), WearLevel::Warning);
        assert!(WearConfig::new(800_000, 0).is_none());
        assert!(WearConfig::new(5_000, 80).is_none());
        let cfg = WearConfig::new(400_000, 50).unwrap();
        let o = Odometer::new(
            cfg,
            Cone::new(1, Material::ZQSn5_2, "", 0),
            Lifetime::default(),
        );
        assert!(o.remaining_cycles() < 10_000);
    }

    #[test]
    fn records_round_trip() {
        let mut o = nominal(1234);
        o.record_overload(250_000);
        o.record_fault();
        let r = StateRecord::of(&o, true);
        assert_eq!(StateRecord::from_bytes(&r.to_bytes()), Some(r));
        let c = Cone::new(3, Material::CfPeek, "SN-0042_x", 777);
        assert_eq!(cone_from_bytes(&cone_to_bytes(&c)), Some(c));
        assert_eq!(cone_from_bytes(&[0xFF; CONE_LEN]), None);
        assert_eq!(StateRecord::from_bytes(&[0; 7]), None);
        let back = restore(
            WearConfig::DEFAULT,
            Some(c),
            Some(StateRecord {
                cone_id: 3,
                material: Material::CfPeek,
                ..r
            }),
            Material::ZQSn5_2,
        );
        assert_eq!(back.cone().cycles, 1234);
        assert_eq!(back.lifetime().overload_events, 1);
        assert_eq!(back.lifetime().cones_installed, 3);
    }
}

/// Result of [`reference_run`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ReferenceRun {
    /// Cycles run.
    pub cycles: u32,
    /// Equivalent nominal cycles, Q32.32.
    pub e_q32: u64,
    /// Wear depth, nm.
    pub wear_nm: u32,
    /// Remaining life, cycles.
    pub remaining_cycles: u32,
    /// The persisted counter snapshot.
    pub record: [u8; STATE_LEN],
    /// The wear estimate fitted to a fixed set of readings (1.2 × the model, ± a few µm)
    /// at the run's end: the estimator's arithmetic, host against target.
    pub estimate: crate::estimate::Estimate,
    /// The same from five readings of a cone running in (every 100 cycles to 500,
    /// near-linear then bending), 5 000 cycles on: both laws of the fit and their
    /// weighing.
    pub estimate_early: crate::estimate::Estimate,
}

/// A deterministic odometer workload in integers only — a load shaped like Eq. 7 (four
/// phases, the 3→4 jump) with ±2 N of pseudo-random noise, sampled at irregular 10–29 µm
/// steps over both strokes, `cycles` times — for comparing host and target bit for bit
/// (the firmware image's arithmetic under QEMU against the host's: see `.ci/run`).
pub fn reference_run(cycles: u32) -> ReferenceRun {
    let mut odo = Odometer::new(
        WearConfig::DEFAULT,
        Cone::new(1, Material::ZQSn5_2, "REF", 0),
        Lifetime::default(),
    );
    let mut x: u32 = 0x9E37_79B9;
    let mut rnd = move || {
        x ^= x << 13;
        x ^= x >> 17;
        x ^= x << 5;
        x
    };
    // Piecewise load in mN at depth d (µm): constants, then rising, then the jump.
    let load = |d: i32| -> i32 {
        match d {
            i32::MIN..=4_499 => 112_640,
            4_500..=8_699 => 115_050,
            8_700..=14_933 => 103_770 + (d - 8_700) / 2,
            _ => 206_340 - (d - 14_934) * 5,
        }
    };
    for _ in 0..cycles {
        let mut d = 0i32;
        while d <= 30_000 {
            let noise = (rnd() % 4_001) as i32 - 2_000;
            odo.on_contact_sample(d, load(d) + noise);
            d += 10 + (rnd() % 20) as i32;
        }
        while d >= 0 {
            let noise = (rnd() % 4_001) as i32 - 2_000;
            odo.on_contact_sample(d, load(d) + noise);
            d -= 10 + (rnd() % 20) as i32;
        }
        odo.complete_cycle();
    }
    let readings: heapless::Vec<crate::estimate::Reading, 12> = (1..=12u64)
        .map(|k| {
            let e = k * 2_500;
            let noise = (rnd() % 7_001) as i32 - 3_500;
            crate::estimate::Reading {
                e_q32: e << 32,
                wear_nm: (depth_nm(e << 32) as i32).saturating_mul(6) / 5 + noise,
            }
        })
        .collect();
    let estimate = crate::estimate::Fit::new(&readings).at(
        odo.equivalent_cycles_q32().saturating_add(20_000 << 32),
        WearConfig::DEFAULT.limit_nm,
        Material::ZQSn5_2,
    );
    let early: heapless::Vec<crate::estimate::Reading, 5> =
        [40_000, 76_000, 104_000, 124_000, 139_000]
            .iter()
            .zip(1..)
            .map(|(&nm, k): (&i32, u64)| {
                let noise = (rnd() % 3_001) as i32 - 1_500;
                crate::estimate::Reading {
                    e_q32: (k * 100) << 32,
                    wear_nm: nm + noise,
                }
            })
            .collect();
    let estimate_early = crate::estimate::Fit::new(&early).at(
        5_000 << 32,
        WearConfig::DEFAULT.limit_nm,
        Material::ZQSn5_2,
    );
    ReferenceRun {
        cycles,
        e_q32: odo.equivalent_cycles_q32(),
        wear_nm: odo.wear_nm(),
        remaining_cycles: odo.remaining_cycles(),
        record: StateRecord::of(&odo, true).to_bytes(),
        estimate,
        estimate_early,
    }
}

impl core::fmt::Display for ReferenceRun {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "odometer reference: cycles={} e_q32={} wear_nm={} remaining={} record=",
            self.cycles, self.e_q32, self.wear_nm, self.remaining_cycles
        )?;
        for b in self.record {
            write!(f, "{b:02x}")?;
        }
        for (name, e) in [
            ("estimate", &self.estimate),
            ("early", &self.estimate_early),
        ] {
            write!(
                f,
                " {name}={},{},{},{},{},{}",
                e.wear_nm,
                e.low_nm,
                e.high_nm,
                e.remaining_cycles,
                e.remaining_low_cycles,
                e.remaining_high_cycles
            )?;
        }
        Ok(())
    }
}
