//! Power-cut-safe log of variable-length frames in NOR flash, over sectors of unequal
//! sizes (the docking signature's store: flash sectors 2–4, 16 + 16 + 64 KiB).
//!
//! [`FrameLog`] is [`crate::storage::RecordLog`]'s design — and its guarantees — for
//! records too big for a 64-byte slot (a stroke's curve is 640 bytes): frames of up to
//! [`MAX_LEN`] bytes, written whole or not at all, a sequence number each, round-robin
//! over the sectors, the newest frames of each kind carried into a sector before the
//! sector after it is erased. Read `storage.rs`'s module doc first; what differs is said
//! here.
//!
//! # Guarantees
//!
//! * **Power cuts.** A cut at any byte of any write or erase loses at most the frame
//!   being appended: after [`FrameLog::open`] the newest `keep` frames of each kind
//!   ([`FrameLog::newest`]) are those of the last appends that returned `Ok`, or — if
//!   the cut hit an append that never returned — with that append's frame. Old or new,
//!   never anything else (`host-tests/tests/signature_store.rs` cuts at every byte).
//! * **Corruption.** A frame whose bits flipped fails its CRC and is skipped (counted in
//!   [`OpenReport::corrupt`]); a frame header that cannot be read closes its sector
//!   (nothing after it is parsed: the frame's length is not known), which the next
//!   append leaves for the next sector.
//! * **`open` always succeeds** on any content (garbage, an old image's code — sectors
//!   2–4 held the application in layouts A and B, zeros); it only reads.
//! * **Erases only in `append` and `maintain`**, which the controller calls at rest only.
//! * **Interrupted erases** as in `storage.rs`: a sector is trusted blank only if a
//!   certificate ([`CERT_KIND`]) written after its completed erase, in the current
//!   sector, names it; else the move erases it again.
//!
//! # On-flash format
//!
//! A sector holds frames from its start, back to back, 4-byte aligned; the rest is
//! erased (0xFF). One frame (multi-byte fields little-endian):
//!
//! ```text
//!  0       4       8      9       10     12      16                16+P      20+P   24+P
//!  +-------+-------+------+-------+------+-------+-----------------+---------+--------+
//!  | seq   | id    | kind | carry | len  | hcrc  | payload, padded | crc     | commit |
//!  | u32   | u32   | u8   | u8    | u16  | u32   | to P = ⌈len/4⌉·4| u32     | 0 0 0 0|
//!  +-------+-------+------+-------+------+-------+-----------------+---------+--------+
//!  |<---- hcrc: CRC-32 of 0..12 -->|            (padding 0xFF)     |
//!  |<------------------ crc: CRC-32/ISO-HDLC of 0..16+P ---------->|
//!  |<------------------------- write 1 ------------------------------------->|write 2 |
//! ```
//!
//! * `seq`: strictly increasing over the life of the log; `id`: the `seq` the frame was
//!   appended with (a carried copy keeps its original's `id`, so a copy and its original
//!   are one frame: the one with the higher `seq` counts).
//! * `kind`: `0..KINDS` ([`CERT_KIND`] the log's own); `carry`: 0xFF for an append, `n`
//!   (1..=[`MAX_BATCH`]) for a copy carried into a new sector as one of a batch of `n`;
//!   `len`: payload bytes, `0..=MAX_LEN`.
//! * `hcrc` lets a scan trust `len` (and so find the next frame) before the rest is
//!   read; `commit` is programmed last, by a write of its own.
//!
//! A frame is **valid** if its header is, its CRC matches and its commit is 0. A used
//! region is never programmed again: appends continue after the last frame whose header
//! is good (valid or torn), and a sector with a bad header is full from there.
//!
//! # Moving to the next sector
//!
//! When a frame does not fit in what is left of the current sector, `append` erases the
//! next sector (unless certified), copies into it, oldest first, the newest `keep[k]`
//! frames of each kind `k` (new `seq`, same `id`, `carry = n`), and only then makes it
//! current; the batch must fit in the smallest sector with room to spare (checked at
//! `open`). A batch cut short leaves that sector unfinished (fewer than `n` valid
//! copies at its start and nothing after): `open` ignores it and the next append redoes
//! the move. A newest frame that survives only in the sector about to be erased (its
//! copy went bad) cannot be held in RAM as `storage.rs` holds a 48-byte record: it is
//! dropped, and counted ([`FrameLog::dropped`]).
//!
//! # Costs
//!
//! `open` reads every frame once (the 96 KiB of sectors 2–4: about 1 ms at 168 MHz);
//! RAM: the sector table and the offsets of the newest frames, ≈ 160 bytes. An append
//! streams its payload through a 64-byte buffer (no frame is ever held whole).

use embedded_storage::nor_flash::NorFlash;

use crate::crc::Crc32;

/// Header bytes.
pub const HEADER_LEN: usize = 16;
/// CRC and commit marker after the payload, bytes.
pub const TRAILER_LEN: usize = 8;
/// Largest payload, bytes.
pub const MAX_LEN: usize = 2048;
/// Frame kinds, `0..KINDS`.
pub const KINDS: usize = 8;
/// The log's own kind: the certificate of a completed pre-erase (payload: the sector
/// index, one byte).
pub const CERT_KIND: u8 = KINDS as u8 - 1;
/// Most frames of one kind the index keeps (and a move carries).
pub const KEEP_MAX: usize = 4;
/// Most frames a move carries.
pub const MAX_BATCH: usize = KEEP_MAX * (KINDS - 1);
/// Most sectors a region may have.
pub const MAX_SECTORS: usize = 4;
/// `carry` of an appended frame.
const NOT_CARRIED: u8 = 0xFF;
/// No frame, in the index (which holds offset + 1: an all-zero index is empty, and
/// builds without a 0xFF fill).
const NONE: u32 = 0;
/// Streaming buffer, bytes.
const CHUNK: usize = 64;

/// The size on flash of a frame with `len` payload bytes.
pub const fn frame_size(len: usize) -> usize {
    HEADER_LEN + len.div_ceil(4) * 4 + TRAILER_LEN
}

/// Why a log operation failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum FrameError<E> {
    /// The flash driver failed (the log stays consistent; a retry may succeed).
    Flash(E),
    /// A payload longer than [`MAX_LEN`], or a frame that cannot fit beside the
    /// carried batch.
    TooLarge,
    /// A kind out of range (or the log's own).
    BadKind,
    /// The region cannot hold this log: sector sizes not whole erase units or not
    /// multiples of 4, more than [`MAX_SECTORS`] or fewer than 2, larger than the
    /// device, a `keep` whose batch and largest frame do not fit the smallest sector,
    /// or a `WRITE_SIZE` not dividing 4.
    Geometry,
    /// All 2^32 sequence numbers used.
    SeqExhausted,
    /// A frame is being written in parts ([`FrameLog::begin`]): nothing else is
    /// appended until it is finished or abandoned.
    Busy,
}

impl<E: core::fmt::Debug> core::fmt::Display for FrameError<E> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Flash(e) => write!(f, "flash error: {e:?}"),
            Self::TooLarge => f.write_str("frame too large"),
            Self::BadKind => f.write_str("bad frame kind"),
            Self::Geometry => f.write_str("flash region unusable for the frame log"),
            Self::SeqExhausted => f.write_str("frame sequence numbers exhausted"),
            Self::Busy => f.write_str("a frame is being written"),
        }
    }
}

/// A valid frame as found in flash.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Frame {
    /// Byte offset of the frame in the region.
    pub offset: u32,
    /// Its sequence number.
    pub seq: u32,
    /// The `seq` it was appended with.
    pub id: u32,
    /// Kind.
    pub kind: u8,
    /// Payload bytes.
    pub len: u16,
}

/// What [`FrameLog::open`] found.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct OpenReport {
    /// Valid frames.
    pub valid: u32,
    /// Frames with a good header but a bad CRC or no commit (torn, bit-flipped), and
    /// headers that closed their sector.
    pub corrupt: u32,
    /// Sectors entirely erased.
    pub erased_sectors: u32,
    /// A move was cut short; the next append redoes it.
    pub unfinished_move: bool,
}

/// What one parse of a frame position gave.
enum Parsed {
    /// Erased from here on (the first header word at least).
    Blank,
    /// A header that cannot be trusted: the sector is closed here.
    Broken,
    /// A frame whose header is good: its size, `carry`, and whether it is valid.
    Frame {
        frame: Frame,
        carry: u8,
        valid: bool,
        size: u32,
    },
}

/// Per-sector facts `open` gathers.
#[derive(Clone, Copy, Default)]
struct SectorScan {
    max_seq: Option<u32>,
    /// Where appends would continue (the sector's size if closed).
    wp: u32,
    /// Frames (valid or torn) in it.
    used: u32,
    /// Valid frames from its start up to the first that is not.
    valid_prefix: u32,
    in_prefix: bool,
    /// `n` of its carried batch.
    batch: Option<u8>,
    /// A valid appended frame is in it.
    appended: bool,
    blank: bool,
}

impl SectorScan {
    fn move_finished(&self) -> bool {
        match self.batch {
            None => true,
            Some(n) => {
                self.appended || self.valid_prefix >= u32::from(n) || self.used > u32::from(n)
            }
        }
    }
}

/// The newest frames of a kind: `(id, seq, offset)`, newest (highest id) first.
type Newest = [(u32, u32, u32); KEEP_MAX];
const NO_NEWEST: Newest = [(0, 0, NONE); KEEP_MAX];

/// Insert a frame into a kind's newest list (a copy and its original: the higher seq).
fn insert(list: &mut Newest, keep: usize, id: u32, seq: u32, off: u32) {
    let keep = keep.clamp(1, KEEP_MAX);
    if let Some(e) = list.iter_mut().find(|e| e.2 != NONE && e.0 == id) {
        if seq > e.1 {
            *e = (id, seq, off);
        }
        return;
    }
    let Some(pos) = list.iter().take(keep).position(|e| e.2 == NONE || id > e.0) else {
        return;
    };
    let mut carry = (id, seq, off);
    for e in list.iter_mut().skip(pos).take(keep - pos) {
        core::mem::swap(e, &mut carry);
    }
}

/// The log.
#[derive(Debug)]
pub struct FrameLog<F: NorFlash> {
    flash: F,
    /// Sector sizes, bytes.
    sizes: [u32; MAX_SECTORS],
    sectors: u8,
    /// Current sector and where the next frame goes in it (its size when full).
    cur: u8,
    wp: u32,
    next_seq: Option<u32>,
    /// Offsets + 1 of the newest frames of each kind, newest first ([`NONE`]: none).
    newest: [[u32; KEEP_MAX]; KINDS],
    keep: [u8; KINDS],
    /// The sector after `cur` is known erased (a certificate in `cur` names it).
    next_ready: bool,
    dropped: u32,
    /// The frame being written in parts ([`Self::begin`], [`Self::resume`]).
    writing: Option<Writing>,
}

/// A frame being written in parts: where its body has got to, and its CRC so far.
#[derive(Clone, Copy, Debug)]
struct Writing {
    frame: Frame,
    /// Body bytes (header, payload and padding, CRC) written.
    pos: usize,
    crc: Crc32,
}

impl<F: NorFlash> FrameLog<F> {
    /// Open the log over sectors of `sizes` bytes from the start of `flash`, keeping
    /// (and carrying) the newest `keep[k]` frames of kind `k` (≤ [`KEEP_MAX`]; the
    /// certificate kind is never carried) and frames of at most `max_len` bytes. Reads
    /// only.
    pub fn open(
        flash: F,
        sizes: &[u32],
        keep: [u8; KINDS],
        max_len: usize,
    ) -> Result<(Self, OpenReport), FrameError<F::Error>> {
        let mut s = [0u32; MAX_SECTORS];
        let n = sizes.len();
        let erase = u32::try_from(F::ERASE_SIZE).unwrap_or(u32::MAX).max(1);
        let total: u64 = sizes.iter().map(|&x| u64::from(x)).sum();
        let batch: usize = keep
            .iter()
            .take(KINDS - 1)
            .map(|&k| usize::from(k).min(KEEP_MAX) * frame_size(max_len))
            .sum();
        let smallest = sizes.iter().copied().min().unwrap_or(0) as usize;
        let ok = (2..=MAX_SECTORS).contains(&n)
            && 4 % F::WRITE_SIZE.max(1) == 0
            && F::WRITE_SIZE > 0
            && max_len <= MAX_LEN
            && sizes.iter().all(|&x| x > 0 && x % erase == 0 && x % 4 == 0)
            && total <= flash.capacity() as u64
            && batch + 2 * frame_size(max_len) + frame_size(1) <= smallest;
        if !ok {
            return Err(FrameError::Geometry);
        }
        for (d, &x) in s.iter_mut().zip(sizes) {
            *d = x;
        }
        let mut log = Self {
            flash,
            sizes: s,
            sectors: n as u8,
            cur: 0,
            wp: 0,
            next_seq: Some(0),
            newest: [[NONE; KEEP_MAX]; KINDS],
            keep,
            next_ready: false,
            dropped: 0,
            writing: None,
        };
        let report = log.scan()?;
        Ok((log, report))
    }

    /// The first byte of sector `i`.
    fn base(&self, i: u8) -> u32 {
        self.sizes.iter().take(usize::from(i)).sum()
    }

    fn size(&self, i: u8) -> u32 {
        self.sizes.get(usize::from(i)).copied().unwrap_or(0)
    }

    fn next_sector(&self) -> u8 {
        (self.cur + 1) % self.sectors.max(1)
    }

    /// Read and classify the frame position `off` (absolute) in sector `sector`.
    fn parse(&mut self, sector: u8, off: u32) -> Result<Parsed, FrameError<F::Error>> {
        let end = self.base(sector) + self.size(sector);
        if off + HEADER_LEN as u32 + TRAILER_LEN as u32 > end {
            return Ok(Parsed::Broken);
        }
        let mut h = [0u8; HEADER_LEN];
        self.flash.read(off, &mut h).map_err(FrameError::Flash)?;
        if h.iter().take(4).all(|&b| b == 0xFF) {
            return Ok(if h.iter().all(|&b| b == 0xFF) {
                Parsed::Blank
            } else {
                Parsed::Broken
            });
        }
        let word = |i: usize| {
            let mut w = [0u8; 4];
            if let Some(s) = h.get(i..i + 4) {
                w.copy_from_slice(s);
            }
            u32::from_le_bytes(w)
        };
        let (seq, id) = (word(0), word(4));
        let (kind, carry) = (h.get(8).copied(), h.get(9).copied());
        let len = u16::from_le_bytes([
            h.get(10).copied().unwrap_or(0xFF),
            h.get(11).copied().unwrap_or(0xFF),
        ]);
        let hcrc_ok = crate::crc::crc32(h.get(..12).unwrap_or(&[])) == word(12);
        let (Some(kind), Some(carry)) = (kind, carry) else {
            return Ok(Parsed::Broken);
        };
        let size = frame_size(usize::from(len)) as u32;
        let header_ok = hcrc_ok
            && usize::from(kind) < KINDS
            && usize::from(len) <= MAX_LEN
            && (carry == NOT_CARRIED || (1..=MAX_BATCH as u8).contains(&carry))
            && off + size <= end;
        if !header_ok {
            return Ok(Parsed::Broken);
        }
        // The CRC over header and payload, then the CRC and the commit.
        let body = size - TRAILER_LEN as u32;
        let mut crc = Crc32::new();
        crc.update(&h);
        let mut buf = [0u8; CHUNK];
        let mut at = HEADER_LEN as u32;
        while at < body {
            let n = (body - at).min(CHUNK as u32) as usize;
            let b = buf.get_mut(..n).ok_or(FrameError::Geometry)?;
            self.flash.read(off + at, b).map_err(FrameError::Flash)?;
            crc.update(b);
            at += n as u32;
        }
        let mut t = [0u8; TRAILER_LEN];
        self.flash
            .read(off + body, &mut t)
            .map_err(FrameError::Flash)?;
        let stored = u32::from_le_bytes([t[0], t[1], t[2], t[3]]);
        let valid = stored == crc.finalize() && t[4..] == [0, 0, 0, 0];
        Ok(Parsed::Frame {
            frame: Frame {
                offset: off,
                seq,
                id,
                kind,
                len,
            },
            carry,
            valid,
            size,
        })
    }

    /// Walk sector `i`'s frames, calling `f` for each valid one (with its `carry`).
    fn scan_sector(
        &mut self,
        i: u8,
        report: &mut OpenReport,
        f: &mut dyn FnMut(&Frame),
    ) -> Result<SectorScan, FrameError<F::Error>> {
        let (base, size) = (self.base(i), self.size(i));
        let mut s = SectorScan {
            in_prefix: true,
            ..SectorScan::default()
        };
        let mut off = base;
        loop {
            match self.parse(i, off)? {
                Parsed::Blank => {
                    s.wp = off - base;
                    break;
                }
                Parsed::Broken => {
                    // Counted unless it is only the sector's unusable tail.
                    if off + (HEADER_LEN + TRAILER_LEN) as u32 <= base + size {
                        report.corrupt += 1;
                    }
                    s.wp = size;
                    break;
                }
                Parsed::Frame {
                    frame,
                    carry,
                    valid,
                    size: fs,
                } => {
                    s.used += 1;
                    if valid {
                        report.valid += 1;
                        if s.in_prefix {
                            s.valid_prefix += 1;
                        }
                        s.max_seq = s.max_seq.max(Some(frame.seq));
                        if carry == NOT_CARRIED {
                            s.appended = true;
                        } else {
                            s.batch.get_or_insert(carry);
                        }
                        f(&frame);
                    } else {
                        report.corrupt += 1;
                        s.in_prefix = false;
                    }
                    off += fs;
                }
            }
        }
        s.blank = s.used == 0 && s.wp == 0;
        Ok(s)
    }

    /// Read every sector and rebuild the index (reads only).
    fn scan(&mut self) -> Result<OpenReport, FrameError<F::Error>> {
        let mut report = OpenReport::default();
        let mut scans = [SectorScan::default(); MAX_SECTORS];
        let mut max_seq: Option<u32> = None;
        for i in 0..self.sectors {
            let s = self.scan_sector(i, &mut report, &mut |_| {})?;
            max_seq = max_seq.max(s.max_seq);
            if s.blank {
                report.erased_sectors += 1;
            }
            if let Some(d) = scans.get_mut(usize::from(i)) {
                *d = s;
            }
        }
        // The newest sector is current, unless its move was cut short.
        let newest = (0..self.sectors)
            .filter(|&i| {
                scans
                    .get(usize::from(i))
                    .is_some_and(|s| s.max_seq.is_some())
            })
            .max_by_key(|&i| scans.get(usize::from(i)).and_then(|s| s.max_seq));
        let mut abandoned = None;
        match newest {
            None => {
                self.cur = 0;
                self.wp = scans.first().map_or(0, |s| s.wp);
            }
            Some(i)
                if scans
                    .get(usize::from(i))
                    .is_some_and(SectorScan::move_finished) =>
            {
                self.cur = i;
                self.wp = scans.get(usize::from(i)).map_or(0, |s| s.wp);
            }
            Some(i) => {
                warn!("framelog: move to sector {=u8} was cut short", i);
                abandoned = Some(i);
                self.cur = (i + self.sectors - 1) % self.sectors;
                self.wp = self.size(self.cur);
                report.unfinished_move = true;
            }
        }
        self.next_seq = max_seq.map_or(Some(0), |s| s.checked_add(1));
        // The index, without the abandoned sector's copies.
        let mut lists = [NO_NEWEST; KINDS];
        let keep = self.keep;
        let mut dummy = OpenReport::default();
        for i in 0..self.sectors {
            if Some(i) == abandoned {
                continue;
            }
            self.scan_sector(i, &mut dummy, &mut |fr| {
                let k = usize::from(fr.kind);
                let n = if fr.kind == CERT_KIND {
                    1
                } else {
                    usize::from(keep.get(k).copied().unwrap_or(1))
                };
                if let Some(l) = lists.get_mut(k) {
                    insert(l, n, fr.id, fr.seq, fr.offset + 1);
                }
            })?;
        }
        for (dst, l) in self.newest.iter_mut().zip(&lists) {
            for (d, e) in dst.iter_mut().zip(l) {
                *d = e.2;
            }
        }
        let next = self.next_sector();
        self.next_ready = self.certified(next)? && self.sector_blank(next)?;
        info!(
            "framelog: {=u32} valid, {=u32} corrupt frames; sector {=u8} at {=u32}",
            report.valid, report.corrupt, self.cur, self.wp
        );
        Ok(report)
    }

    /// Whether sector `i` reads erased throughout.
    fn sector_blank(&mut self, i: u8) -> Result<bool, FrameError<F::Error>> {
        let (base, size) = (self.base(i), self.size(i));
        let mut buf = [0u8; CHUNK];
        let mut at = 0;
        while at < size {
            let n = (size - at).min(CHUNK as u32) as usize;
            let b = buf.get_mut(..n).ok_or(FrameError::Geometry)?;
            self.flash.read(base + at, b).map_err(FrameError::Flash)?;
            if b.iter().any(|&x| x != 0xFF) {
                return Ok(false);
            }
            at += n as u32;
        }
        Ok(true)
    }

    /// Whether the newest certificate lies in the current sector and names `sector`.
    fn certified(&mut self, sector: u8) -> Result<bool, FrameError<F::Error>> {
        let Some(off) = self.newest_offset(CERT_KIND, 0) else {
            return Ok(false);
        };
        let (base, size) = (self.base(self.cur), self.size(self.cur));
        if !(base..base + size).contains(&off) {
            return Ok(false);
        }
        let mut b = [0u8; 1];
        self.flash
            .read(off + HEADER_LEN as u32, &mut b)
            .map_err(FrameError::Flash)?;
        Ok(b[0] == sector)
    }

    fn newest_offset(&self, kind: u8, n: usize) -> Option<u32> {
        self.newest
            .get(usize::from(kind))
            .and_then(|l| l.get(n))
            .copied()
            .filter(|&o| o != NONE)
            .map(|o| o - 1)
    }

    /// The `n`-th newest frame of `kind` (0: the newest), re-read and checked.
    pub fn newest(&mut self, kind: u8, n: usize) -> Result<Option<Frame>, FrameError<F::Error>> {
        let Some(off) = self.newest_offset(kind, n) else {
            return Ok(None);
        };
        self.frame_at(off)
    }

    /// The valid frame at `offset`, if there is one (any offset: a stale link reads as
    /// `None`, or as a frame its caller must check the kind and `seq` of).
    pub fn frame_at(&mut self, offset: u32) -> Result<Option<Frame>, FrameError<F::Error>> {
        let Some(sector) = (0..self.sectors)
            .find(|&i| (self.base(i)..self.base(i) + self.size(i)).contains(&offset))
        else {
            return Ok(None);
        };
        if offset % 4 != 0 {
            return Ok(None);
        }
        Ok(match self.parse(sector, offset)? {
            Parsed::Frame {
                frame, valid: true, ..
            } => Some(frame),
            _ => None,
        })
    }

    /// Read `buf.len()` payload bytes of `frame` from `at` (the payload's byte `at`);
    /// bytes past the payload read 0xFF.
    pub fn read(
        &mut self,
        frame: &Frame,
        at: usize,
        buf: &mut [u8],
    ) -> Result<(), FrameError<F::Error>> {
        let len = usize::from(frame.len);
        let n = buf.len().min(len.saturating_sub(at));
        for (i, x) in buf.iter_mut().enumerate() {
            if i >= n {
                *x = 0xFF;
            }
        }
        if n == 0 {
            return Ok(());
        }
        let dst = buf.get_mut(..n).ok_or(FrameError::Geometry)?;
        let off = frame.offset + (HEADER_LEN + at) as u32;
        self.flash.read(off, dst).map_err(FrameError::Flash)
    }

    /// Append a frame of `kind` with `len` payload bytes, which `fill(at, chunk)` writes
    /// piece by piece (`chunk` is payload bytes `at..at + chunk.len()`). Returns it. May
    /// move to (and erase) the next sector: call only at rest.
    pub fn append(
        &mut self,
        kind: u8,
        len: usize,
        fill: &mut dyn FnMut(usize, &mut [u8]),
    ) -> Result<Frame, FrameError<F::Error>> {
        if usize::from(kind) >= KINDS - 1 {
            return Err(FrameError::BadKind);
        }
        self.append_any(kind, len, fill)
    }

    fn append_any(
        &mut self,
        kind: u8,
        len: usize,
        fill: &mut dyn FnMut(usize, &mut [u8]),
    ) -> Result<Frame, FrameError<F::Error>> {
        self.begin_any(kind, len)?;
        self.resume(usize::MAX, fill)?.ok_or(FrameError::Busy)
    }

    /// Begin a frame of `kind` with `len` payload bytes, written in parts by
    /// [`Self::resume`] (so that no single call programs more than its budget: a word
    /// program stalls the CPU). Its place is taken now — and moving to the next sector,
    /// if needed, done now: call only at rest. Until it is finished or
    /// [`Self::abandon`]ed nothing else is appended ([`FrameError::Busy`]). A power cut
    /// before its last part leaves it torn, which `open` skips: the same guarantee as a
    /// cut inside [`Self::append`].
    pub fn begin(&mut self, kind: u8, len: usize) -> Result<(), FrameError<F::Error>> {
        if usize::from(kind) >= KINDS - 1 {
            return Err(FrameError::BadKind);
        }
        self.begin_any(kind, len)
    }

    fn begin_any(&mut self, kind: u8, len: usize) -> Result<(), FrameError<F::Error>> {
        if self.writing.is_some() {
            return Err(FrameError::Busy);
        }
        if len > MAX_LEN {
            return Err(FrameError::TooLarge);
        }
        let size = frame_size(len) as u32;
        if self.wp + size > self.size(self.cur) {
            self.move_to_next()?;
            if self.wp + size > self.size(self.cur) {
                return Err(FrameError::TooLarge);
            }
        }
        let seq = self.take_seq()?;
        let off = self.base(self.cur) + self.wp;
        // Used from its first byte on, whatever happens next.
        self.wp += size;
        self.writing = Some(Writing {
            frame: Frame {
                offset: off,
                seq,
                id: seq,
                kind,
                len: len as u16,
            },
            pos: 0,
            crc: Crc32::new(),
        });
        Ok(())
    }

    /// Write the next part of the frame [`Self::begin`] began: body bytes in pieces of
    /// 64 until `budget` bytes are written (at least one piece), the payload's bytes
    /// from `fill(at, chunk)` as [`Self::append`]'s — which must give the same bytes
    /// at every call. `Some(frame)` once it is whole (its commit written last); `None`
    /// while parts remain, or if none is being written. A flash error abandons it.
    pub fn resume(
        &mut self,
        budget: usize,
        fill: &mut dyn FnMut(usize, &mut [u8]),
    ) -> Result<Option<Frame>, FrameError<F::Error>> {
        let Some(mut w) = self.writing.take() else {
            return Ok(None);
        };
        if !self.program(&mut w, NOT_CARRIED, budget, fill)? {
            self.writing = Some(w);
            return Ok(None);
        }
        self.note(w.frame.kind, w.frame.offset);
        Ok(Some(w.frame))
    }

    /// The kind of the frame being written in parts, if one is.
    pub fn writing(&self) -> Option<u8> {
        self.writing.map(|w| w.frame.kind)
    }

    /// Give up the frame being written in parts (its data changed): its place stays
    /// used, a torn frame `open` skips.
    pub fn abandon(&mut self) {
        self.writing = None;
    }

    /// Put a new newest frame of `kind` at the head of its list.
    fn note(&mut self, kind: u8, off: u32) {
        if let Some(l) = self.newest.get_mut(usize::from(kind)) {
            // Shift by hand (`rotate_right` links a memmove).
            let mut carry = off + 1;
            for e in l.iter_mut() {
                core::mem::swap(e, &mut carry);
            }
            let keep = if kind == CERT_KIND {
                1
            } else {
                usize::from(self.keep.get(usize::from(kind)).copied().unwrap_or(1))
                    .clamp(1, KEEP_MAX)
            };
            for e in l.iter_mut().skip(keep) {
                *e = NONE;
            }
        }
    }

    /// Write `w`'s frame's header, payload and CRC from where it got to, at least one
    /// piece and then until `budget` bytes are written; once they are all written, its
    /// commit. Whether the frame is whole.
    fn program(
        &mut self,
        w: &mut Writing,
        carry: u8,
        budget: usize,
        fill: &mut dyn FnMut(usize, &mut [u8]),
    ) -> Result<bool, FrameError<F::Error>> {
        let frame = w.frame;
        let len = usize::from(frame.len);
        let padded = len.div_ceil(4) * 4;
        let mut h = [0u8; HEADER_LEN];
        h[0..4].copy_from_slice(&frame.seq.to_le_bytes());
        h[4..8].copy_from_slice(&frame.id.to_le_bytes());
        h[8] = frame.kind;
        h[9] = carry;
        h[10..12].copy_from_slice(&frame.len.to_le_bytes());
        let hcrc = crate::crc::crc32(&h[..12]);
        h[12..16].copy_from_slice(&hcrc.to_le_bytes());
        if w.pos == 0 {
            w.crc.update(&h);
        }
        // Body: header, payload (+ padding), CRC — in chunks of CHUNK bytes.
        let body = HEADER_LEN + padded + 4;
        let mut buf = [0u8; CHUNK];
        let mut pos = w.pos;
        let mut written = 0;
        while pos < body && (written == 0 || written < budget) {
            let n = (body - pos).min(CHUNK);
            let chunk = buf.get_mut(..n).ok_or(FrameError::Geometry)?;
            // The header where it is, erased-flash padding elsewhere (no separate fill:
            // it would link a memset).
            for (i, b) in chunk.iter_mut().enumerate() {
                *b = h.get(pos + i).copied().unwrap_or(0xFF);
            }
            // The payload's share of this chunk.
            let p0 = pos.max(HEADER_LEN);
            let p1 = (pos + n).min(HEADER_LEN + len);
            if p0 < p1 {
                if let Some(dst) = chunk.get_mut(p0 - pos..p1 - pos) {
                    fill(p0 - HEADER_LEN, dst);
                }
            }
            // The CRC covers everything before it.
            let c0 = pos.max(HEADER_LEN);
            let c1 = (pos + n).min(HEADER_LEN + padded);
            if c0 < c1 {
                if let Some(part) = chunk.get(c0 - pos..c1 - pos) {
                    w.crc.update(part);
                }
            }
            if pos + n == body {
                let v = w.crc.finalize().to_le_bytes();
                let at = n - 4;
                if let Some(dst) = chunk.get_mut(at..) {
                    dst.copy_from_slice(&v);
                }
            }
            self.flash
                .write(frame.offset + pos as u32, chunk)
                .map_err(FrameError::Flash)?;
            pos += n;
            written += n;
            w.pos = pos;
        }
        if pos < body {
            return Ok(false);
        }
        self.flash
            .write(frame.offset + body as u32, &[0; 4])
            .map_err(FrameError::Flash)?;
        Ok(true)
    }

    /// Move to the next sector: erase it unless certified, copy the newest frames of
    /// every kind into it. The RAM state changes only once the batch is complete.
    #[inline(never)]
    fn move_to_next(&mut self) -> Result<(), FrameError<F::Error>> {
        let next = self.next_sector();
        let (nbase, nsize) = (self.base(next), self.size(next));
        // The batch: (id, offset, kind), oldest first; frames found only in the sector
        // to be erased are dropped.
        let mut batch: heapless::Vec<(u32, u32, u8), MAX_BATCH> = heapless::Vec::new();
        for kind in 0..(KINDS as u8 - 1) {
            let keep = usize::from(self.keep.get(usize::from(kind)).copied().unwrap_or(0));
            for n in 0..keep.min(KEEP_MAX) {
                let Some(off) = self.newest_offset(kind, n) else {
                    continue;
                };
                if (nbase..nbase + nsize).contains(&off) {
                    self.dropped = self.dropped.saturating_add(1);
                    warn!("framelog: a frame only in the sector to erase is dropped");
                    continue;
                }
                match self.frame_at(off)? {
                    Some(fr) => {
                        let _ = batch.push((fr.id, off, kind));
                    }
                    None => self.dropped = self.dropped.saturating_add(1),
                }
            }
        }
        let items = batch.as_mut_slice();
        for i in 1..items.len() {
            let mut j = i;
            while j > 0 && items.get(j - 1).map(|e| e.0) > items.get(j).map(|e| e.0) {
                items.swap(j - 1, j);
                j -= 1;
            }
        }
        let n = u8::try_from(batch.len()).map_err(|_| FrameError::TooLarge)?;
        if !self.next_ready {
            self.erase(next)?;
        }
        let mut newest = [[NONE; KEEP_MAX]; KINDS];
        let mut wp = 0u32;
        for &(_, off, kind) in batch.iter() {
            let Some(old) = self.frame_at(off)? else {
                return Err(FrameError::TooLarge);
            };
            let size = frame_size(usize::from(old.len)) as u32;
            if wp + size > nsize {
                return Err(FrameError::TooLarge);
            }
            let copy = Frame {
                offset: nbase + wp,
                seq: self.take_seq()?,
                ..old
            };
            wp += size;
            self.copy_frame(&old, &copy, n)?;
            if let Some(l) = newest.get_mut(usize::from(kind)) {
                if let Some(slot) = l.iter_mut().find(|e| **e == NONE) {
                    *slot = copy.offset + 1;
                }
            }
        }
        // Newest first in the index (the batch went oldest first).
        for l in newest.iter_mut() {
            let k = l.iter().filter(|&&o| o != NONE).count();
            if let Some(s) = l.get_mut(..k) {
                s.reverse();
            }
        }
        debug!(
            "framelog: moved to sector {=u8}, carried {=u8} frames",
            next, n
        );
        self.cur = next;
        self.wp = wp;
        self.next_ready = false;
        self.newest = newest;
        Ok(())
    }

    /// Write `copy` (header and commit new) with `old`'s payload, read back piece by
    /// piece.
    fn copy_frame(
        &mut self,
        old: &Frame,
        copy: &Frame,
        batch: u8,
    ) -> Result<(), FrameError<F::Error>> {
        // The payload goes through a CHUNK buffer, read from the original and written
        // to the copy piece by piece.
        let len = usize::from(old.len);
        let padded = len.div_ceil(4) * 4;
        let mut h = [0u8; HEADER_LEN];
        h[0..4].copy_from_slice(&copy.seq.to_le_bytes());
        h[4..8].copy_from_slice(&copy.id.to_le_bytes());
        h[8] = copy.kind;
        h[9] = batch;
        h[10..12].copy_from_slice(&copy.len.to_le_bytes());
        let hcrc = crate::crc::crc32(&h[..12]);
        h[12..16].copy_from_slice(&hcrc.to_le_bytes());
        let mut crc = Crc32::new();
        crc.update(&h);
        self.flash
            .write(copy.offset, &h)
            .map_err(FrameError::Flash)?;
        let mut buf = [0u8; CHUNK];
        let mut at = 0;
        while at < padded {
            let n = (padded - at).min(CHUNK);
            let b = buf.get_mut(..n).ok_or(FrameError::Geometry)?;
            let real = len.saturating_sub(at).min(n);
            // The padding past the payload (written before the read fills the rest).
            for (i, x) in b.iter_mut().enumerate() {
                if i >= real {
                    *x = 0xFF;
                }
            }
            if let Some(r) = b.get_mut(..real) {
                self.flash
                    .read(old.offset + (HEADER_LEN + at) as u32, r)
                    .map_err(FrameError::Flash)?;
            }
            crc.update(b);
            self.flash
                .write(copy.offset + (HEADER_LEN + at) as u32, b)
                .map_err(FrameError::Flash)?;
            at += n;
        }
        let end = copy.offset + (HEADER_LEN + padded) as u32;
        self.flash
            .write(end, &crc.finalize().to_le_bytes())
            .map_err(FrameError::Flash)?;
        self.flash
            .write(end + 4, &[0; 4])
            .map_err(FrameError::Flash)
    }

    fn erase(&mut self, i: u8) -> Result<(), FrameError<F::Error>> {
        let (base, size) = (self.base(i), self.size(i));
        self.next_ready = false;
        self.flash
            .erase(base, base + size)
            .map_err(FrameError::Flash)?;
        debug!("framelog: erased sector {=u8}", i);
        Ok(())
    }

    fn take_seq(&mut self) -> Result<u32, FrameError<F::Error>> {
        let seq = self.next_seq.ok_or(FrameError::SeqExhausted)?;
        self.next_seq = seq.checked_add(1);
        Ok(seq)
    }

    /// Bytes left in the current sector.
    pub fn free_in_sector(&self) -> u32 {
        self.size(self.cur).saturating_sub(self.wp)
    }

    /// True when the next sector is not known to be erased and the current one has less
    /// than a quarter left (but room for the certificate); [`Self::maintain`] then
    /// erases it, so that an append rarely has to.
    pub fn needs_maintenance(&self) -> bool {
        let free = self.free_in_sector();
        self.writing.is_none()
            && !self.next_ready
            && free * 4 < self.size(self.cur)
            && free >= frame_size(1) as u32
    }

    /// Erase the next sector if [`Self::needs_maintenance`] and certify it with a frame
    /// in the current one. At rest only.
    pub fn maintain(&mut self) -> Result<(), FrameError<F::Error>> {
        if !self.needs_maintenance() {
            return Ok(());
        }
        let next = self.next_sector();
        let (nb, ns) = (self.base(next), self.size(next));
        let holds_newest = self
            .newest
            .iter()
            .take(KINDS - 1)
            .flatten()
            .any(|&o| o != NONE && (nb..nb + ns).contains(&(o - 1)));
        if holds_newest {
            // Only after bit flips: the move carries what it can.
            return Ok(());
        }
        self.erase(next)?;
        self.append_any(CERT_KIND, 1, &mut |_, d| {
            if let Some(b) = d.first_mut() {
                *b = next;
            }
        })?;
        self.next_ready = true;
        Ok(())
    }

    /// Frames a move had to drop (their only copy was in the sector it erased).
    pub fn dropped(&self) -> u32 {
        self.dropped
    }

    /// The current sector and where its next frame goes (offset in the sector).
    pub fn position(&self) -> (u8, u32) {
        (self.cur, self.wp)
    }

    /// The flash device.
    pub fn flash(&self) -> &F {
        &self.flash
    }

    /// The flash device, mutably (writing behind the log's back voids its guarantees).
    pub fn flash_mut(&mut self) -> &mut F {
        &mut self.flash
    }

    /// Give the flash device back.
    pub fn into_inner(self) -> F {
        self.flash
    }
}
