//! What the signature keeps in flash (sectors 2–4, [`crate::framelog`]'s frames): the
//! per-docking summary, each cone's reference, the last NOK curves. Every format is
//! drawn here; each is a frame kind whose payload never changes meaning (a new field is
//! a new kind, or a longer payload whose old length still reads).
//!
//! # Kinds
//!
//! | kind | what | payload | kept (carried at every sector move) |
//! |---|---|---|---|
//! | 0 [`kind::SUMMARY`] | one judged docking | [`Summary`], 68 B | the newest; older ones stay until their sector is erased (`history`) |
//! | 1 [`kind::REFERENCE`] | a cone's reference, as far as it is learnt | [`RefHeader`] + sums, 1 056 B | the newest |
//! | 2 [`kind::NOK`] | a NOK docking's curves | [`Summary`] + two curves (below), 1 348 B | the newest [`NOK_KEPT`] |
//! | 7 | the log's erase certificate | sector index, 1 B | no |
//!
//! # Summary (68 bytes, little-endian)
//!
//! ```text
//!  0          4          8        10      11       12       16       20
//!  +----------+----------+--------+-------+--------+--------+--------+----------+
//!  | lifetime | cone     | cone id| flags | failed | figure | limit  | fail at  |
//!  | cycle u32| cycle u32| u16    | u8    | object | i32    | i32    | µm, i32  |
//!  +----------+----------+--------+-------+--------+--------+--------+----------+
//!  24         28          32        36       40          44         46
//!  +----------+-----------+---------+--------+-----------+----------+-----------+
//!  | work     | plateau   | step    | end    | ext. peak | drift    | drift     |
//!  | mN·mm u32| mN i32    | µm i32  | mN i32 | mN i32    | work ‰i16| plateau ‰ |
//!  +----------+-----------+---------+--------+-----------+----------+-----------+
//!  48          52          56              60                64            68
//!  +-----------+-----------+---------------+-----------------+-------------+
//!  | cone's    | cone's    | trend, work   | trend, plateau  | prev        |
//!  | dockings  | NOK u32   | ‰ × 16, i32   | ‰ × 16, i32     | summary u32 |
//!  +-----------+-----------+---------------+-----------------+-------------+
//! ```
//!
//! `flags`: bit 0 the insertion NOK, bit 1 the extraction NOK, bit 2 the docking went
//! into its cone's reference, bit 3 `figure` and `limit` are µm (else mN). `failed`:
//! the first object failed ([`super::objects::Object`]'s code; the insertion's before
//! the extraction's), 0 none. A figure that does not exist is `i32::MIN` (`i16::MIN` for
//! a drift: no complete reference yet). `prev`: the offset of the summary before it in
//! the region (`u32::MAX`: none), so that `history` walks back frame by frame.
//!
//! # Reference (32 + 1 024 bytes)
//!
//! ```text
//!  0        2     3        4            12             20            28        32
//!  +--------+-----+--------+------------+--------------+-------------+---------+
//!  | cone id| n   | step n | Σ work     | Σ plateau    | Σ step      | 0xFFFF  |
//!  | u16    | u8  | u8     | mN·mm u64  | mN i64       | µm i64      | FFFF    |
//!  +--------+-----+--------+------------+--------------+-------------+---------+
//!  32: Σ insertion bin means [i32; 128] (dN)   544: Σ extraction bin means [i32; 128]
//! ```
//!
//! The reference is the mean of the first `n` OK dockings of the cone after `cone
//! replace` (`SignatureConfig::reference_n`, default 20): sums, so a mean is exact.
//!
//! # A curve (640 bytes, in a NOK frame after its summary: insertion, then extraction)
//!
//! ```text
//!  0                       256                     512                 640
//!  +-----------------------+-----------------------+-------------------+
//!  | bin means i16 × 128   | bin peaks i16 × 128   | counts u8 × 128   |
//!  | dN (0x8000: empty)    | dN (0x8000: empty)    |                   |
//!  +-----------------------+-----------------------+-------------------+
//! ```

use zerocopy::byteorder::little_endian::{I16, I32, I64, U16, U32, U64};
use zerocopy::{FromBytes, FromZeros, Immutable, IntoBytes, KnownLayout, Unaligned};

use super::capture::StrokeBins;
use super::grid::BINS;
use super::objects::{Failure, Object, Unit};
use crate::framelog::KINDS;

/// Frame kinds.
pub mod kind {
    /// [`super::Summary`]: one judged docking.
    pub const SUMMARY: u8 = 0;
    /// [`super::RefHeader`] and sums: a cone's reference.
    pub const REFERENCE: u8 = 1;
    /// A NOK docking: its [`super::Summary`] and both curves.
    pub const NOK: u8 = 2;
}

/// NOK curves kept.
pub const NOK_KEPT: usize = 4;

/// Frames of each kind the store keeps and carries.
pub const KEEP: [u8; KINDS] = [1, 1, NOK_KEPT as u8, 0, 0, 0, 0, 0];

/// The store's sectors (2, 3 and 4 of the STM32F407), bytes.
pub const SECTORS: [u32; 3] = [16 * 1024, 16 * 1024, 64 * 1024];

/// One curve's bytes.
pub const CURVE_LEN: usize = BINS * 5;
/// A summary's bytes.
pub const SUMMARY_LEN: usize = 68;
/// A reference's bytes.
pub const REFERENCE_LEN: usize = 32 + 2 * BINS * 4;
/// A NOK frame's bytes.
pub const NOK_LEN: usize = SUMMARY_LEN + 2 * CURVE_LEN;
/// The largest frame's payload.
pub const MAX_LEN: usize = NOK_LEN;

/// An empty bin in a stored curve.
pub const EMPTY_DN: i16 = i16::MIN;

/// One judged docking, as persisted (drawn in the module doc).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Summary {
    /// Lifetime cycle number of the docking.
    pub lifetime_cycle: u32,
    /// Its number on its cone.
    pub cone_cycle: u32,
    /// The cone.
    pub cone_id: u16,
    /// The insertion was NOK.
    pub insertion_nok: bool,
    /// The extraction was NOK.
    pub extraction_nok: bool,
    /// The docking went into its cone's reference.
    pub in_reference: bool,
    /// The first object failed (insertion first).
    pub failure: Option<Failure>,
    /// Insertion work, mN·mm.
    pub work_mnmm: u32,
    /// Phase-4 plateau, mN.
    pub plateau_mn: i32,
    /// The 3→4 step, µm.
    pub step_um: Option<i32>,
    /// End force at MATED, mN.
    pub end_mn: i32,
    /// The extraction's peak, mN.
    pub ext_peak_mn: i32,
    /// Drift of the work from the cone's reference, ‰.
    pub drift_work_pm: Option<i16>,
    /// Drift of the plateau from the cone's reference, ‰.
    pub drift_plateau_pm: Option<i16>,
    /// The cone's judged dockings, this one included.
    pub cone_judged: u32,
    /// The cone's NOK dockings, this one included.
    pub cone_nok: u32,
    /// The trend of the work's drift (its moving average, α = 1/16), ‰ × 16.
    pub trend_work_x16: Option<i32>,
    /// The trend of the plateau's drift, ‰ × 16.
    pub trend_plateau_x16: Option<i32>,
    /// Offset of the summary before it (`None`: none).
    pub prev: Option<u32>,
}

impl Summary {
    /// Whether the docking was NOK.
    pub fn nok(&self) -> bool {
        self.insertion_nok || self.extraction_nok
    }
}

/// A [`Summary`] as laid out in flash.
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct SummaryLayout {
    lifetime_cycle: U32,
    cone_cycle: U32,
    cone_id: U16,
    flags: u8,
    failed: u8,
    figure: I32,
    limit: I32,
    fail_at_um: I32,
    work_mnmm: U32,
    plateau_mn: I32,
    step_um: I32,
    end_mn: I32,
    ext_peak_mn: I32,
    drift_work_pm: I16,
    drift_plateau_pm: I16,
    cone_judged: U32,
    cone_nok: U32,
    trend_work_x16: I32,
    trend_plateau_x16: I32,
    prev: U32,
}

const _: () = assert!(core::mem::size_of::<SummaryLayout>() == SUMMARY_LEN);

impl Summary {
    /// The 68 bytes.
    pub fn to_bytes(&self) -> [u8; SUMMARY_LEN] {
        let f = self.failure;
        let flags = u8::from(self.insertion_nok)
            | u8::from(self.extraction_nok) << 1
            | u8::from(self.in_reference) << 2
            | u8::from(f.is_some_and(|f| f.unit == Unit::Um)) << 3;
        let l = SummaryLayout {
            lifetime_cycle: self.lifetime_cycle.into(),
            cone_cycle: self.cone_cycle.into(),
            cone_id: self.cone_id.into(),
            flags,
            failed: f.map_or(0, |f| f.object.code()),
            figure: f.map_or(i32::MIN, |f| f.figure).into(),
            limit: f.map_or(i32::MIN, |f| f.limit).into(),
            fail_at_um: f.map_or(i32::MIN, |f| f.depth_um).into(),
            work_mnmm: self.work_mnmm.into(),
            plateau_mn: self.plateau_mn.into(),
            step_um: self.step_um.unwrap_or(i32::MIN).into(),
            end_mn: self.end_mn.into(),
            ext_peak_mn: self.ext_peak_mn.into(),
            drift_work_pm: self.drift_work_pm.unwrap_or(i16::MIN).into(),
            drift_plateau_pm: self.drift_plateau_pm.unwrap_or(i16::MIN).into(),
            cone_judged: self.cone_judged.into(),
            cone_nok: self.cone_nok.into(),
            trend_work_x16: self.trend_work_x16.unwrap_or(i32::MIN).into(),
            trend_plateau_x16: self.trend_plateau_x16.unwrap_or(i32::MIN).into(),
            prev: self.prev.unwrap_or(u32::MAX).into(),
        };
        zerocopy::transmute!(l)
    }

    /// Decode (`None`: too short, or an object code that does not exist).
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let l = SummaryLayout::read_from_prefix(b).ok()?.0;
        let opt = |v: i32| (v != i32::MIN).then_some(v);
        let opt16 = |v: i16| (v != i16::MIN).then_some(v);
        let failure = match l.failed {
            0 => None,
            c => Some(Failure {
                object: Object::from_code(c)?,
                figure: l.figure.get(),
                limit: l.limit.get(),
                unit: Unit::from_code((l.flags >> 3) & 1),
                depth_um: l.fail_at_um.get(),
            }),
        };
        Some(Self {
            lifetime_cycle: l.lifetime_cycle.get(),
            cone_cycle: l.cone_cycle.get(),
            cone_id: l.cone_id.get(),
            insertion_nok: l.flags & 1 != 0,
            extraction_nok: l.flags & 2 != 0,
            in_reference: l.flags & 4 != 0,
            failure,
            work_mnmm: l.work_mnmm.get(),
            plateau_mn: l.plateau_mn.get(),
            step_um: opt(l.step_um.get()),
            end_mn: l.end_mn.get(),
            ext_peak_mn: l.ext_peak_mn.get(),
            drift_work_pm: opt16(l.drift_work_pm.get()),
            drift_plateau_pm: opt16(l.drift_plateau_pm.get()),
            cone_judged: l.cone_judged.get(),
            cone_nok: l.cone_nok.get(),
            trend_work_x16: opt(l.trend_work_x16.get()),
            trend_plateau_x16: opt(l.trend_plateau_x16.get()),
            prev: (l.prev.get() != u32::MAX).then_some(l.prev.get()),
        })
    }
}

/// A reference's header, as laid out in flash (drawn in the module doc).
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned,
)]
#[repr(C)]
pub struct RefHeader {
    /// The cone.
    pub cone_id: U16,
    /// Dockings summed.
    pub n: u8,
    /// Of them, those with a 3→4 step.
    pub step_n: u8,
    /// Σ insertion work, mN·mm.
    pub work_sum: U64,
    /// Σ phase-4 plateau, mN.
    pub plateau_sum: I64,
    /// Σ 3→4 step, µm.
    pub step_sum: I64,
    /// 0xFFFF_FFFF.
    pub reserved: U32,
}

const _: () = assert!(core::mem::size_of::<RefHeader>() == 32);

/// A cone's reference in RAM: the sums of its first OK dockings (all-zero: cone 0,
/// nothing learnt).
#[derive(Clone, Debug, PartialEq, Eq, FromZeros)]
pub struct Reference {
    /// The cone.
    pub cone_id: u16,
    /// Dockings summed.
    pub n: u8,
    /// Of them, those with a 3→4 step.
    pub step_n: u8,
    /// Σ insertion work, mN·mm.
    pub work_sum: u64,
    /// Σ phase-4 plateau, mN.
    pub plateau_sum: i64,
    /// Σ 3→4 step, µm.
    pub step_sum: i64,
    /// Σ bin means, dN: `[insertion, extraction]`.
    pub sums: [[i32; BINS]; 2],
}

impl Reference {
    /// Nothing learnt, for `cone_id`.
    pub const fn empty(cone_id: u16) -> Self {
        Self {
            cone_id,
            n: 0,
            step_n: 0,
            work_sum: 0,
            plateau_sum: 0,
            step_sum: 0,
            sums: [[0; BINS]; 2],
        }
    }

    /// The header.
    pub fn header(&self) -> RefHeader {
        RefHeader {
            cone_id: self.cone_id.into(),
            n: self.n,
            step_n: self.step_n,
            work_sum: self.work_sum.into(),
            plateau_sum: self.plateau_sum.into(),
            step_sum: self.step_sum.into(),
            reserved: u32::MAX.into(),
        }
    }

    /// Payload byte `at` of its frame.
    pub fn byte(&self, at: usize) -> u8 {
        let h = self.header();
        if let Some(b) = h.as_bytes().get(at) {
            return *b;
        }
        let i = at - 32;
        let (stroke, bin, byte) = (i / (BINS * 4), (i / 4) % BINS, i % 4);
        self.sums
            .get(stroke)
            .and_then(|s| s.get(bin))
            .map_or(0xFF, |v| v.to_le_bytes().get(byte).copied().unwrap_or(0xFF))
    }

    /// Take the header of a frame (the sums follow with [`Self::set_sum_bytes`]).
    pub fn from_header(h: &RefHeader) -> Self {
        Self {
            cone_id: h.cone_id.get(),
            n: h.n,
            step_n: h.step_n,
            work_sum: h.work_sum.get(),
            plateau_sum: h.plateau_sum.get(),
            step_sum: h.step_sum.get(),
            sums: [[0; BINS]; 2],
        }
    }

    /// Set the sums from the frame's bytes `32..` read in pieces: `at` the piece's
    /// offset past the header (a multiple of 4), `bytes` whole words.
    pub fn set_sum_bytes(&mut self, at: usize, bytes: &[u8]) {
        for (k, w) in bytes.chunks_exact(4).enumerate() {
            let i = at / 4 + k;
            let mut le = [0u8; 4];
            le.copy_from_slice(w);
            let v = i32::from_le_bytes(le);
            if let Some(s) = self
                .sums
                .get_mut(i / BINS)
                .and_then(|s| s.get_mut(i % BINS))
            {
                *s = v;
            }
        }
    }

    /// The mean of a stroke's bin, dN (`None` before any docking).
    pub fn mean_dn(&self, stroke: usize, bin: usize) -> Option<i16> {
        if self.n == 0 {
            return None;
        }
        let s = i64::from(*self.sums.get(stroke)?.get(bin)?);
        let n = i64::from(self.n);
        let m = if s >= 0 {
            (s + n / 2) / n
        } else {
            (s - n / 2) / n
        };
        i16::try_from(m).ok()
    }
}

/// Byte `at` of a stored curve of `s` (drawn in the module doc).
pub fn curve_byte(s: &StrokeBins, at: usize) -> u8 {
    let (part, i) = (at / (BINS * 2), at % (BINS * 2));
    match part {
        0 | 1 => {
            let b = s.bin(i / 2);
            let v = if part == 0 { b.mean_dn() } else { b.peak_dn() }.unwrap_or(EMPTY_DN);
            v.to_le_bytes().get(i % 2).copied().unwrap_or(0xFF)
        }
        _ => s.bin(at - 4 * BINS).count(),
    }
}

/// A stored curve, read back: per bin mean and peak (dN, `None` empty) and count.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct StoredCurve {
    /// Bin means, dN ([`EMPTY_DN`]: no sample).
    pub mean_dn: [i16; BINS],
    /// Bin peaks, dN.
    pub peak_dn: [i16; BINS],
    /// Samples per bin.
    pub count: [u8; BINS],
}

impl StoredCurve {
    /// All empty.
    pub const EMPTY: Self = Self {
        mean_dn: [EMPTY_DN; BINS],
        peak_dn: [EMPTY_DN; BINS],
        count: [0; BINS],
    };

    /// The capture of a stroke, as it would be stored.
    pub fn of(s: &StrokeBins) -> Self {
        let mut c = Self::EMPTY;
        for i in 0..BINS {
            let b = s.bin(i);
            if let (Some(m), Some(p), Some(cm), Some(cp), Some(cc)) = (
                b.mean_dn(),
                b.peak_dn(),
                c.mean_dn.get_mut(i),
                c.peak_dn.get_mut(i),
                c.count.get_mut(i),
            ) {
                *cm = m;
                *cp = p;
                *cc = b.count();
            }
        }
        c
    }

    /// Set bytes `at..` of its stored form.
    pub fn set_bytes(&mut self, at: usize, bytes: &[u8]) {
        for (k, &b) in bytes.iter().enumerate() {
            let a = at + k;
            let (part, i) = (a / (BINS * 2), a % (BINS * 2));
            let word = match part {
                0 => self.mean_dn.get_mut(i / 2),
                1 => self.peak_dn.get_mut(i / 2),
                _ => {
                    if let Some(c) = self.count.get_mut(a - 4 * BINS) {
                        *c = b;
                    }
                    continue;
                }
            };
            if let Some(w) = word {
                let mut le = w.to_le_bytes();
                if let Some(x) = le.get_mut(i % 2) {
                    *x = b;
                }
                *w = i16::from_le_bytes(le);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use crate::signature::capture::Capture;
    use crate::signature::Stroke;

    fn summary() -> Summary {
        Summary {
            lifetime_cycle: 1234,
            cone_cycle: 56,
            cone_id: 3,
            insertion_nok: true,
            extraction_nok: false,
            in_reference: false,
            failure: Some(Failure {
                object: Object::Band3,
                figure: 137_000,
                limit: 125_500,
                unit: Unit::Mn,
                depth_um: 11_017,
            }),
            work_mnmm: 4_042_700,
            plateau_mn: 158_300,
            step_um: Some(14_931),
            end_mn: 125_100,
            ext_peak_mn: 206_300,
            drift_work_pm: Some(-12),
            drift_plateau_pm: None,
            cone_judged: 56,
            cone_nok: 2,
            trend_work_x16: Some(-200),
            trend_plateau_x16: None,
            prev: Some(0x1234),
        }
    }

    #[test]
    fn a_summary_round_trips_and_its_layout_is_the_drawing() {
        let s = summary();
        let b = s.to_bytes();
        assert_eq!(Summary::from_bytes(&b), Some(s));
        assert_eq!(&b[0..4], &1234u32.to_le_bytes());
        assert_eq!(b[10], 1, "flags: insertion NOK");
        assert_eq!(b[11], Object::Band3.code());
        assert_eq!(&b[44..46], &(-12i16).to_le_bytes());
        assert_eq!(&b[46..48], &i16::MIN.to_le_bytes(), "no drift");
        assert_eq!(&b[64..68], &0x1234u32.to_le_bytes());
        let ok = Summary {
            failure: None,
            insertion_nok: false,
            prev: None,
            step_um: None,
            ..s
        };
        assert_eq!(Summary::from_bytes(&ok.to_bytes()), Some(ok));
        let mut bad = b;
        bad[11] = 99;
        assert_eq!(Summary::from_bytes(&bad), None, "an unknown object");
        assert_eq!(Summary::from_bytes(&b[..67]), None);
    }

    #[test]
    fn a_reference_and_a_curve_round_trip_through_their_bytes() {
        let mut r = Reference::empty(7);
        r.n = 3;
        r.work_sum = 12_000_000;
        for (i, s) in r.sums[1].iter_mut().enumerate() {
            *s = i as i32 * 3 - 100;
        }
        let bytes: std::vec::Vec<u8> = (0..REFERENCE_LEN).map(|a| r.byte(a)).collect();
        let h = RefHeader::read_from_bytes(&bytes[..32]).unwrap();
        let mut back = Reference::from_header(&h);
        back.set_sum_bytes(0, &bytes[32..]);
        assert_eq!(back, r);
        assert_eq!(r.mean_dn(1, 100), Some(67));

        let mut c = Capture::new();
        c.sample(0, 100_000, None);
        for d in (0..30_000).step_by(100) {
            c.sample(d, 100_000 + d, Some(Stroke::Insertion));
        }
        c.sample(0, 0, None);
        let s = c.stroke(Stroke::Insertion);
        let bytes: std::vec::Vec<u8> = (0..CURVE_LEN).map(|a| curve_byte(s, a)).collect();
        let mut back = StoredCurve::EMPTY;
        back.set_bytes(0, &bytes[..300]);
        back.set_bytes(300, &bytes[300..]);
        assert_eq!(back, StoredCurve::of(s));
        assert_eq!(back.count[0], 3);
    }
}
