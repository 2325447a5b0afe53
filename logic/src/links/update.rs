//! The update file's format (issue 21, docs/update.md), checked before anything is
//! marked for the swap: the application's bytes, then a 72-byte trailer.
//!
//! ```text
//!  0                      len          len+64        len+68   len+72
//!  +----------------------+-------------+-------------+--------+
//!  | image (len B, words) | signature   | len, u32 LE | "DCS1" |
//!  +----------------------+-------------+-------------+--------+
//!  signature: ed25519(key, SHA-512(image)) — what embassy-boot's
//!  verify_and_mark_updated(public key, signature, len) checks against DFU page 0
//! ```
//!
//! `tools/sign-image.sh` writes it. Format version 1 is the magic `DCS1`; another
//! format takes another magic. The image must be an application linked behind the
//! bootloader of this board's layout ([`check_head`]: the vector table by the
//! bootloader's own rule, [`vector_table_ok`], and the image header naming the layout,
//! `update_layout::layout::LAYOUT`): a file built for 0x0800_0000, for another layout,
//! or not an image at all, is refused by its first block, before anything is erased,
//! and again before its signature is looked at. Nothing here panics on any input.

use update_layout::header::{Header, HEADER_LEN, HEADER_OFFSET};
use update_layout::layout::{Layout, ACTIVE_BASE, ACTIVE_LEN, LAYOUT};

/// Length of the trailer (the partition map's, which sizes the largest image by it).
pub const TRAILER_LEN: usize = update_layout::layout::TRAILER_LEN as usize;
/// Format version 1.
pub const MAGIC: [u8; 4] = *b"DCS1";

/// The trailer of a well-formed file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Trailer {
    /// The image's length, bytes (the file less the trailer).
    pub len: u32,
    /// The ed25519 signature of the image's SHA-512.
    pub signature: [u8; 64],
}

/// Why a file is refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// Shorter than a vector table and a trailer.
    TooShort,
    /// No `DCS1` at the end: not an update file, or truncated.
    NoMagic,
    /// The trailer's length is not the file's less the trailer (truncated or padded).
    Length,
    /// The image is not whole words.
    NotWords,
    /// The image does not fit the application's partition.
    TooLarge,
    /// The image's vector table does not point into the application's partition.
    NotBootable,
    /// No image header (`update_layout::header`): not built by this project, its layout
    /// unknown.
    NoHeader,
    /// Built for another partition map than this board's (the layout its header or its
    /// vector table names; `None`: a header from before layout C, which names none).
    OtherLayout(Option<Layout>),
}

impl Refusal {
    /// For the technician: one line.
    pub fn text(self) -> &'static str {
        match self {
            Self::TooShort => "too short",
            Self::NoMagic => "no update trailer (unsigned or truncated)",
            Self::Length => "trailer's length is not the file's",
            Self::NotWords => "not whole words",
            Self::TooLarge => "image larger than ACTIVE",
            Self::NotBootable => "not linked behind the bootloader",
            Self::NoHeader => "no image header (not built by this project's build)",
            Self::OtherLayout(l) => other_layout_text(l),
        }
    }
}

/// The refusal of an image built for layout `l` (this board's is [`LAYOUT`]): a board's
/// layout changes only by a probe (docs/update.md, "Migration").
const fn other_layout_text(l: Option<Layout>) -> &'static str {
    match l {
        None => "built for an earlier layout (A or B); this board has layout C: flash it with a probe (tools/flash-board.sh)",
        Some(Layout::A) => "built for layout A; this board has layout C: flash it with a probe (tools/flash-board.sh)",
        Some(Layout::B) => "built for layout B; this board has layout C: flash it with a probe (tools/flash-board.sh)",
        Some(Layout::C) => "built for layout C; this board has another: flash it with a probe (tools/flash-board.sh)",
    }
}

// The texts above name layout C as this board's.
const _: () = assert!(matches!(LAYOUT, Layout::C));

/// The first bytes of a file (`head`: its first block, or more) checked before anything
/// is erased: the vector table must point into this layout's ACTIVE
/// ([`vector_table_ok`]; one that points into another layout's names it), and the image
/// header, once `head` reaches it, must name this layout. A `head` shorter than the
/// header (a sender's 128-byte first block) is checked for its vector table only; the
/// whole check runs again on the received file ([`check`]'s caller).
pub fn check_head(head: &[u8]) -> Result<(), Refusal> {
    let Some(vt) = head.first_chunk::<8>() else {
        return Err(Refusal::TooShort);
    };
    if !vector_table_ok(vt, ACTIVE_BASE, ACTIVE_LEN) {
        let [_, _, _, _, e, f, g, h] = *vt;
        let pc = u32::from_le_bytes([e, f, g, h]);
        let other = [Layout::A, Layout::B, Layout::C]
            .into_iter()
            .find(|l| *l != LAYOUT && l.in_active(pc));
        return Err(match other {
            // A and B share ACTIVE's address: their files name neither.
            Some(Layout::A | Layout::B) => Refusal::OtherLayout(None),
            Some(l) => Refusal::OtherLayout(Some(l)),
            None => Refusal::NotBootable,
        });
    }
    let at = HEADER_OFFSET as usize;
    let Some(bytes) = head.get(at..at + HEADER_LEN) else {
        return Ok(());
    };
    let mut h = [0u8; HEADER_LEN];
    h.copy_from_slice(bytes);
    let header = Header::parse(&h).ok_or(Refusal::NoHeader)?;
    match header.layout_id() {
        id if id == LAYOUT.id() => Ok(()),
        id => Err(Refusal::OtherLayout(Layout::from_id(id))),
    }
}

/// Check a received file of `file_len` bytes by its last [`TRAILER_LEN`] bytes `tail`
/// and its first 8 (`head`: the vector table's SP and reset vector), for a partition of
/// `partition_len` bytes at `partition_base` (the trailer must fit in it too).
pub fn check(
    file_len: u32,
    head: &[u8; 8],
    tail: &[u8; TRAILER_LEN],
    partition_base: u32,
    partition_len: u32,
) -> Result<Trailer, Refusal> {
    if (file_len as usize) < TRAILER_LEN + 8 {
        return Err(Refusal::TooShort);
    }
    let [s @ .., m0, m1, m2, m3] = *tail;
    if [m0, m1, m2, m3] != MAGIC {
        return Err(Refusal::NoMagic);
    }
    let [sig @ .., l0, l1, l2, l3] = s;
    let len = u32::from_le_bytes([l0, l1, l2, l3]);
    if len as u64 + TRAILER_LEN as u64 != file_len as u64 {
        return Err(Refusal::Length);
    }
    if len % 4 != 0 {
        return Err(Refusal::NotWords);
    }
    if file_len > partition_len {
        return Err(Refusal::TooLarge);
    }
    if !vector_table_ok(head, partition_base, partition_len) {
        return Err(Refusal::NotBootable);
    }
    Ok(Trailer {
        len,
        signature: sig,
    })
}

/// The bootloader's rule for a vector table it jumps to: the initial SP in SRAM
/// (word-aligned, the top included), the reset vector inside the partition with the
/// Thumb bit.
pub fn vector_table_ok(head: &[u8; 8], base: u32, len: u32) -> bool {
    let [a, b, c, d, e, f, g, h] = *head;
    let sp = u32::from_le_bytes([a, b, c, d]);
    let pc = u32::from_le_bytes([e, f, g, h]);
    let sp_ok = sp > 0x2000_0000 && sp <= 0x2002_0000 && sp % 4 == 0;
    let pc_ok = pc & 1 == 1 && pc > base && pc < base.saturating_add(len);
    sp_ok && pc_ok
}

// --- The images: what runs, what ran before, what was rolled back -----------------------

pub use update_layout::header::{Version, VERSION_TEXT_MAX};
use zerocopy::{FromBytes, Immutable, IntoBytes, KnownLayout, Unaligned};

use crate::machine::Machine;
use crate::odometer::kind;

/// What `version` and Modbus device identification report about the images (issue
/// 21). The board finds it at boot ([`at_boot`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ImageReport {
    /// The running image's version, from its header in flash (`None`: no header).
    pub running: Option<Version>,
    /// The key built into this image is the test key (`boot/keys/`): an image it
    /// accepts proves nothing.
    pub test_key: bool,
    /// The image this one replaced by an update (`None`: flashed with a probe, or not
    /// known).
    pub previous: Option<Version>,
    /// The bootloader rolled the last update back: this image runs again after a
    /// newer one never confirmed itself.
    pub rolled_back: bool,
    /// The version of the image rolled back, if known.
    pub rolled_back_version: Option<Version>,
    /// Whether this image runs on trial after an update, and how its confirmation
    /// stands (issue 31: `version` and Modbus identification say so, and `update` is
    /// refused on trial: DFU holds the image a rollback needs).
    pub trial: Trial,
}

/// Where a new image stands after its swap (the state record's SWAP at boot).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Trial {
    /// Confirmed (or never updated): the image is kept.
    No,
    /// On trial: it confirms itself at rest once the load cell has answered; a reset
    /// before that rolls it back.
    Waiting,
    /// On trial, and its confirmation could not be written (the state sector's flash,
    /// every attempt): the next reset rolls it back.
    Failed,
}

impl Trial {
    /// `version`'s word, and Modbus identification's object 0x84.
    pub const fn word(self) -> &'static str {
        match self {
            Self::No => "no",
            Self::Waiting => "yes",
            Self::Failed => "failed",
        }
    }

    /// What a technician does about it (`version`'s text; `None`: nothing to do).
    pub const fn advice(self) -> Option<&'static str> {
        match self {
            Self::No => None,
            Self::Waiting => Some(
                "on trial: it confirms itself at rest once the load cell answers; a reset before that rolls it back; update is refused until then",
            ),
            Self::Failed => Some(
                "on trial and its confirmation failed (state sector flash): the next reset rolls it back; check the board and update again",
            ),
        }
    }
}

impl ImageReport {
    /// Before the board has said anything.
    pub const UNKNOWN: Self = Self {
        running: None,
        test_key: false,
        previous: None,
        rolled_back: false,
        rolled_back_version: None,
        trial: Trial::No,
    };
}

/// What the board reads at boot, before [`at_boot`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct BootFacts {
    /// The state record's word on this boot: [`update_layout::state::Boot::Trial`]
    /// when this image runs on trial (it confirms itself later, once its self-test
    /// has passed: [`confirmed`]).
    pub boot: update_layout::state::Boot,
    /// This image's version (its header).
    pub running: Option<Version>,
    /// The image in DFU page 1 (after a swap: the one it replaced).
    pub page1: Option<Version>,
    /// The built-in key is the test key.
    pub test_key: bool,
}

/// Image record events (the first byte of a [`kind::IMAGE`] record).
pub mod event {
    /// An update was verified and marked for the swap (`other`: its version).
    pub const MARKED: u8 = 1;
    /// A trial image confirmed itself (`previous`: the image it replaced).
    pub const CONFIRMED: u8 = 2;
    /// The image rolled back to recorded the rollback (`other`: the image rolled back).
    pub const ROLLED_BACK: u8 = 3;
}

/// An image record (kind [`kind::IMAGE`]), 27 bytes; each one carries the whole report
/// (the log keeps the newest record of a kind through its sector moves):
///
/// ```text
///  0       1          9       10         18      19         27
///  +-------+----------+-------+----------+-------+----------+
///  | event | running  | prev? | previous | oth.? | other    |
///  | u8    | version  | u8    | version  | u8    | version  |
///  +-------+----------+-------+----------+-------+----------+
///  version: major u8, minor u8, patch u16 LE, build u32 LE (the image header's);
///  prev? / oth.?: 1 when the version after it is known, else 0
/// ```
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned, Clone, Copy)]
#[repr(C)]
pub struct ImageRecord {
    event: u8,
    running: [u8; 8],
    previous_known: u8,
    previous: [u8; 8],
    other_known: u8,
    other: [u8; 8],
}

impl ImageRecord {
    /// A record of `event`.
    pub fn new(
        event: u8,
        running: Option<Version>,
        previous: Option<Version>,
        other: Option<Version>,
    ) -> Self {
        let v = |x: Option<Version>| x.map_or([0; 8], Version::to_bytes);
        Self {
            event,
            running: v(running),
            previous_known: u8::from(previous.is_some()),
            previous: v(previous),
            other_known: u8::from(other.is_some()),
            other: v(other),
        }
    }

    /// Its bytes in the log.
    pub fn bytes(&self) -> &[u8] {
        self.as_bytes()
    }

    fn parse(b: &[u8]) -> Option<Self> {
        Self::read_from_bytes(b).ok()
    }

    fn previous(&self) -> Option<Version> {
        (self.previous_known == 1).then(|| Version::from_bytes(self.previous))
    }

    fn other(&self) -> Option<Version> {
        (self.other_known == 1).then(|| Version::from_bytes(self.other))
    }
}

/// The record an update writes once it is marked for the swap: the report as it
/// stands, and the version marked.
pub fn marked_record(report: &ImageReport, new: Option<Version>) -> ImageRecord {
    ImageRecord::new(event::MARKED, report.running, report.previous, new)
}

/// `v`'s text in `buf` (`major.minor.patch`, and `+build` when the build is not 0, as
/// `update_layout`'s `Version::write_text`), or `otherwise` without a version. Written by
/// the console's decimal writer: one routine for every number the image prints, no
/// core::fmt.
pub fn version_or<'a>(
    v: Option<Version>,
    otherwise: &'a str,
    buf: &'a mut [u8; VERSION_TEXT_MAX],
) -> &'a str {
    use crate::console::json::{write_u64, Sink};
    let Some(v) = v else { return otherwise };
    let n = {
        let mut w = Buf { buf, n: 0 };
        let w_: &mut dyn Sink = &mut w;
        let parts: [(&str, u32); 4] = [
            ("", v.major.into()),
            (".", v.minor.into()),
            (".", v.patch.into()),
            ("+", v.build),
        ];
        for (i, (sep, x)) in parts.into_iter().enumerate() {
            if i == 3 && x == 0 {
                break;
            }
            // 24 bytes hold the longest version: never an error.
            let _ = w_.put(sep).and_then(|()| write_u64(w_, x.into()));
        }
        w.n
    };
    core::str::from_utf8(buf.get(..n).unwrap_or(&[])).unwrap_or("?")
}

/// A byte buffer as the console's writers' sink.
struct Buf<'a> {
    buf: &'a mut [u8],
    n: usize,
}

impl core::fmt::Write for Buf<'_> {
    fn write_str(&mut self, s: &str) -> core::fmt::Result {
        let end = self.n + s.len();
        let dst = self.buf.get_mut(self.n..end).ok_or(core::fmt::Error)?;
        dst.copy_from_slice(s.as_bytes());
        self.n = end;
        Ok(())
    }
}

/// At boot: the report, from the facts and the newest image record, and the record
/// this boot owes: a rollback not yet recorded, or a confirmation whose record a power
/// cut lost (the trial wrote BOOT to the state, then the power went before
/// [`confirmed`] wrote CONFIRMED). A trial's confirmation comes later and writes its own
/// record ([`confirmed`]). Nothing else is written.
pub fn at_boot(ctrl: &mut dyn Machine, facts: BootFacts) -> ImageReport {
    use update_layout::state::Boot;
    let mut r = ImageReport {
        running: facts.running,
        test_key: facts.test_key,
        previous: None,
        rolled_back: facts.boot == Boot::RolledBack,
        rolled_back_version: None,
        trial: match facts.boot {
            Boot::Trial => Trial::Waiting,
            _ => Trial::No,
        },
    };
    let mut buf = [0u8; core::mem::size_of::<ImageRecord>()];
    let running = facts.running.map(Version::to_bytes);
    let newest = ctrl
        .load_record(kind::IMAGE, &mut buf)
        .and_then(|n| ImageRecord::parse(buf.get(..n)?));
    // The record this boot owes: its event and `other` (with the report's running and
    // previous images).
    let write = match (facts.boot, newest) {
        (Boot::Trial, _) => {
            // Swapped in: DFU page 1 holds the image this one replaced.
            r.previous = facts.page1;
            None
        }
        (_, None) => None,
        (boot, Some(rec)) if Some(rec.running) != running => {
            // Another image's record. If it is the one that marked this image for the
            // swap and the state says BOOT, the trial confirmed itself and the power
            // went before its CONFIRMED record was written: it is written now, as the
            // confirmation would have written it.
            (boot == Boot::Confirmed
                && rec.event == event::MARKED
                && rec.other_known == 1
                && Some(rec.other) == running)
                .then(|| {
                    r.previous = facts.page1;
                    (event::CONFIRMED, None)
                })
        }
        (boot, Some(rec)) => {
            r.previous = rec.previous();
            match (boot, rec.event) {
                (Boot::RolledBack, event::MARKED) => {
                    r.rolled_back_version = rec.other();
                    Some((event::ROLLED_BACK, rec.other()))
                }
                (Boot::RolledBack, event::ROLLED_BACK) => {
                    r.rolled_back_version = rec.other();
                    None
                }
                _ => None,
            }
        }
    };
    if let Some((event, other)) = write {
        store_image_record(ctrl, &ImageRecord::new(event, r.running, r.previous, other));
    }
    r
}

/// The trial boot confirmed (its self-test passed, STATE says BOOT): the record it
/// owes, of the image `r` reports running and the one it replaced; the report says the
/// image is kept.
pub fn confirmed(ctrl: &mut dyn Machine, r: &ImageReport) {
    store_image_record(
        ctrl,
        &ImageRecord::new(event::CONFIRMED, r.running, r.previous, None),
    );
    ctrl.set_images(ImageReport {
        trial: Trial::No,
        ..*r
    });
}

fn store_image_record(ctrl: &mut dyn Machine, rec: &ImageRecord) {
    if ctrl.store_record(kind::IMAGE, rec.bytes()).is_err() {
        error!("update: the image record was not written");
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::indexing_slicing)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec;
    use std::vec::Vec;

    const BASE: u32 = 0x0800_8000;
    const LEN: u32 = 224 * 1024;

    fn file(image_len: usize) -> Vec<u8> {
        let mut f: Vec<u8> = (0..image_len).map(|i| i as u8).collect();
        f[..4].copy_from_slice(&0x2000_6000u32.to_le_bytes());
        f[4..8].copy_from_slice(&0x0800_8189u32.to_le_bytes());
        f.extend([0x5A; 64]);
        f.extend((image_len as u32).to_le_bytes());
        f.extend(MAGIC);
        f
    }

    fn run(f: &[u8]) -> Result<Trailer, Refusal> {
        let head: [u8; 8] = f[..8].try_into().unwrap();
        let tail: [u8; TRAILER_LEN] = f[f.len() - TRAILER_LEN..].try_into().unwrap();
        check(f.len() as u32, &head, &tail, BASE, LEN)
    }

    #[test]
    fn a_signed_image_is_taken_with_its_length_and_signature() {
        let t = run(&file(104_912)).unwrap();
        assert_eq!(t.len, 104_912);
        assert_eq!(t.signature, [0x5A; 64]);
    }

    #[test]
    fn truncated_padded_foreign_and_oversized_files_are_refused() {
        let f = file(4096);
        // Truncated: the magic is gone.
        assert_eq!(run(&f[..f.len() - 100]), Err(Refusal::NoMagic));
        // Cut inside the image but the trailer kept (a bad concatenation).
        let mut cut = f[..1000].to_vec();
        cut.extend(&f[f.len() - TRAILER_LEN..]);
        assert_eq!(run(&cut), Err(Refusal::Length));
        // Not whole words.
        let g = file(4098);
        assert_eq!(run(&g), Err(Refusal::NotWords));
        // Linked at 0x08000000 (no bootloader).
        let mut h = file(4096);
        h[4..8].copy_from_slice(&0x0800_0189u32.to_le_bytes());
        assert_eq!(run(&h), Err(Refusal::NotBootable));
        // Larger than the partition.
        assert_eq!(run(&file(LEN as usize)), Err(Refusal::TooLarge));
        assert_eq!(run(&[0u8; 79]), Err(Refusal::TooShort));
        for r in [Refusal::TooShort, Refusal::NoMagic, Refusal::NotBootable] {
            assert!(!r.text().is_empty());
        }
    }

    /// The first KiB of an image linked at `base` whose header names layout `id`.
    fn head(base: u32, id: Option<u8>) -> Vec<u8> {
        let mut f = vec![0xFFu8; 1024];
        f[..4].copy_from_slice(&0x2000_6000u32.to_le_bytes());
        f[4..8].copy_from_slice(&(base + 0x1001).to_le_bytes());
        if let Some(id) = id {
            let h = Header {
                version: Version::default(),
                flags: u32::from(id) << update_layout::header::LAYOUT_SHIFT,
                key_id: [0; 16],
            };
            f[HEADER_OFFSET as usize..][..HEADER_LEN].copy_from_slice(&h.to_bytes());
        }
        f
    }

    #[test]
    fn a_file_for_another_layout_is_refused_by_its_first_block() {
        let c = Layout::C.active_base();
        assert_eq!(check_head(&head(c, Some(3))), Ok(()));
        // Linked for layouts A and B (ACTIVE at 0x0800_8000), whose headers name none.
        let r = check_head(&head(0x0800_8000, Some(0)));
        assert_eq!(r, Err(Refusal::OtherLayout(None)));
        assert!(r.unwrap_err().text().contains("flash it with a probe"));
        // Linked for C but naming another layout, or none, or no header at all.
        assert_eq!(
            check_head(&head(c, Some(2))),
            Err(Refusal::OtherLayout(Some(Layout::B)))
        );
        assert_eq!(
            check_head(&head(c, Some(0))),
            Err(Refusal::OtherLayout(None))
        );
        assert_eq!(
            check_head(&head(c, Some(9))),
            Err(Refusal::OtherLayout(None))
        );
        assert_eq!(check_head(&head(c, None)), Err(Refusal::NoHeader));
        // Not an image (no vector table into any ACTIVE).
        assert_eq!(
            check_head(&head(0x0800_0000, Some(3))),
            Err(Refusal::NotBootable)
        );
        assert_eq!(check_head(&[0u8; 7]), Err(Refusal::TooShort));
        // A 128-byte first block: its vector table only; the header is checked later.
        assert_eq!(check_head(&head(c, None)[..128]), Ok(()));
        assert_eq!(
            check_head(&head(0x0800_8000, None)[..128]),
            Err(Refusal::OtherLayout(None))
        );
    }
}
