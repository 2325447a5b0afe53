//! Power-cut-safe, wear-levelled record log in NOR flash (the wear odometer's store).
//!
//! [`RecordLog`] appends small records (≤ [`PAYLOAD_MAX`] = 48 bytes, tagged with a
//! *kind* `0..MAX_KINDS`) to flash sectors reserved for it, through
//! `embedded_storage::nor_flash::NorFlash`, and returns the newest record of each kind.
//! The odometer appends one record per completed docking cycle, plus rare config and
//! audit records.
//!
//! # Guarantees
//!
//! * **Power cuts.** A cut at any byte of any write or erase loses at most the record
//!   being appended: after [`RecordLog::open`], [`RecordLog::latest`] of every kind
//!   returns the last record whose [`RecordLog::append`] returned `Ok`, or — if the cut
//!   hit an append that never returned — that append's record. Old or new, never
//!   older, never anything else.
//! * **Corruption.** A record whose bits flipped fails its CRC-32; it is skipped and
//!   counted ([`OpenReport::corrupt`]), and the previous valid record of its kind (if one
//!   still exists) is returned instead.
//! * **`open` always succeeds** on any flash content (garbage, all zeros, half-erased
//!   sectors); only flash read errors and an unusable geometry fail it. It only reads.
//! * **Erases only in `append` and `maintain`**, both documented "call only while the
//!   machine is idle": a sector erase stalls the STM32F4 CPU for ~1–2 s.
//! * **Wear levelling.** Sectors are used round-robin, so their erase counts differ by at
//!   most one (plus erases redone after power cuts, and the first erase of a new chip's
//!   blank sectors).
//! * No heap, no panics, no `unsafe`; about 1 KiB of stack in a sector move.
//!
//! # Why not `sequential-storage`
//!
//! Written by hand rather than with `sequential-storage` 8 because that crate is
//! async-only (our control loop is a synchronous superloop); its `store_item` erases
//! whenever it needs room, but we may erase only while no docking is moving; and it has
//! open bug #136 (after two interrupted initial stores, a later clean `store_item` can
//! vanish after a reboot). This log is small enough to check exhaustively against every
//! power-cut point (`host-tests/tests/storage_log.rs`).
//!
//! # On-flash format
//!
//! The region is `sectors` erase sectors (at least 2) of `S` fixed 64-byte slots each.
//! One slot (multi-byte fields little-endian), declared once as the `zerocopy` layout
//! `SlotLayout` (`SlotBody`, the bytes the CRC covers, then the CRC and the marker):
//!
//! ```text
//!  0        4      5     6       7      8                      56       60            64
//!  +--------+------+-----+-------+------+----------------------+--------+-------------+
//!  |  seq   | kind | len | carry | rsvd |       payload        |  crc   |   commit    |
//!  | u32 LE |  u8  | u8  |  u8   | 0xFF | len bytes, then 0xFF | u32 LE | 00 00 00 00 |
//!  +--------+------+-----+-------+------+----------------------+--------+-------------+
//!  |<----------- CRC-32/ISO-HDLC over bytes 0..56 ------------>|
//!  |<---------------------------- write 1 ----------------------------->|<- write 2 ->|
//! ```
//!
//! * `seq`: global record number, strictly increasing over the life of the log.
//! * `kind`: `0..16` (15 is the log's own, [`ERASED_KIND`]); `len`: payload bytes used,
//!   `0..=48`.
//! * `carry`: `0xFF` for a record written by [`RecordLog::append`]; `n` in
//!   `1..=MAX_BATCH` (64) for a copy carried forward into a new sector as one of a batch
//!   of `n` (below).
//! * `commit`: programmed **last, in its own write**, once the rest of the slot is in
//!   flash. With `WRITE_SIZE` > 4 the second write is the slot's last write unit
//!   (`64 − WRITE_SIZE ..64`, the marker still at its end); with `WRITE_SIZE` = 64 the
//!   slot is a single write and only the CRC guards against a torn program.
//!
//! A slot is **blank** if all 64 bytes are 0xFF, otherwise **used**: a used slot is
//! never programmed again, whether it is valid, torn or corrupt. It is **valid** if the
//! commit marker is 0, the CRC matches, `len` ≤ 48, `kind` < 16 and `carry` is 0xFF or
//! `1..=64`. The newest record of a kind is its valid slot with the highest `seq`.
//!
//! A sector fills from slot 0 upward; the first `n` slots of a sector that was moved
//! into hold the carried batch:
//!
//! ```text
//!  +-----------+-----+-------------+----------+----------+-----+------+-----+------+
//!  | carried 1 | ... | carried n   | appended | appended | ... | 0xFF | ... | 0xFF |
//!  | carry = n |     | carry = n   | carry=FF |          |     |      |     |      |
//!  +-----------+-----+-------------+----------+----------+-----+------+-----+------+
//!   slot 0             slot n-1     slot n                      next free slot
//! ```
//!
//! # Moving to the next sector
//!
//! When the current sector is full, `append` moves to the next sector (round-robin):
//! 1. it reads the newest valid record of every kind (from any sector) into RAM — the
//!    newest *n* of a kind the log was opened to keep deeper ([`Keep`]: the
//!    micrometer readings keep their history this way, whatever the log's depth);
//! 2. unless [`RecordLog::maintain`] erased the next sector and certified it (below),
//!    it erases it — its contents are older than the current sector's, whose carried
//!    batch and appends hold the newest record of every kind;
//! 3. it writes those records (all but the erase certificate) to slots `0..n` of the
//!    next sector, oldest first, with new
//!    `seq` numbers and `carry = n`, and only then makes that sector current in RAM;
//! 4. it writes the new record.
//!
//! [`RecordLog::needs_maintenance`] / [`RecordLog::maintain`] let the idle loop do step 2
//! early, so that `append` rarely erases.
//!
//! # Interrupted erases
//!
//! A sector erase cut short by a reset or a power cut can leave cells that read 0xFF
//! without the margin a completed erase verifies; data programmed there may not be
//! retained. So a sector is never trusted because it reads blank: `maintain` erases the
//! next sector (blank or not) and then appends a certificate — a record of the log's
//! own kind [`ERASED_KIND`] naming that sector — to the current sector. The move skips
//! its erase only when the newest certificate is in the current sector, names the next
//! one, and that sector reads blank; anything else (no certificate, the erase cut before
//! its certificate was written, a certificate from an earlier round, which lies in an
//! older sector) erases again. Certificates are not carried. The one sector trusted
//! without an erase is sector 0 of a region that holds no record at all (a new chip,
//! or after a verified mass erase by the probe).
//!
//! # Why a power cut loses nothing older
//!
//! * A slot counts only once its commit marker, written last, is complete and its CRC
//!   matches, so a cut inside a write leaves the previous record of the kind the newest.
//!   The torn slot is *used*: later appends skip it.
//! * `seq` only grows (open resumes above the highest `seq` found anywhere), so no
//!   leftover — such as the old, CRC-valid records in the unerased half of a sector
//!   whose erase was cut — can outrank newer data.
//! * A sector is erased only while the current sector holds a complete carried batch,
//!   i.e. a copy of the newest record of every kind; the sector before it stays intact
//!   until the next move.
//! * If `open` finds that the newest sector's carried batch is unfinished (fewer than `n`
//!   valid slots at its start and no slot after them used), that sector is ignored: the
//!   full sector before it is current again and the next `append` redoes the whole move
//!   (erase, carry, write). A failed move does the same without a reboot.
//!
//! Bit flips are outside that argument: if the newest copy of a kind is corrupt, an
//! older copy is used while one exists; if that older copy lies in the sector a move is
//! about to erase, the move carries it through RAM (lost if the power fails then).
//!
//! # Costs
//!
//! `open` reads every slot once, plus the next sector once more to learn whether it is
//! erased, and keeps an index in RAM: current sector and write slot, next `seq`, and the
//! offset of the newest record of each kind. `append` is two writes (64 bytes); a move
//! adds maybe an erase and the carried batch (≤ 15 records by default, ≤ 64 with a
//! [`Keep`]; located before the erase, read again as they are copied: 8 bytes of RAM
//! each, plus a record held whole for each that survives only in the erased sector).
//! `latest` reads one slot. `for_each_newest_first` reads backwards until it has `max`
//! records.
//!
//! **Storage** (this module and its two below): the record log here, [`framelog`]'s
//! frames for larger records (the docking signature's curves), and [`crc`], the
//! checksums of every persisted record and every frame on a line.

pub mod crc;
pub mod framelog;

use embedded_storage::nor_flash::NorFlash;
use zerocopy::byteorder::little_endian::U32;
use zerocopy::{FromBytes, Immutable, IntoBytes, KnownLayout, Unaligned};

/// Size of one record slot, bytes.
pub const SLOT_SIZE: usize = 64;
/// Largest record payload, bytes.
pub const PAYLOAD_MAX: usize = 48;
/// Number of record kinds; a kind is `0..MAX_KINDS`.
pub const MAX_KINDS: u8 = 16;
/// The log's own kind: the certificate of a completed pre-erase (payload: the sector
/// erased, one byte). [`RecordLog::append`] refuses it.
pub const ERASED_KIND: u8 = MAX_KINDS - 1;
/// Fewest slots a sector must have with the default [`Keep`] (the newest record of
/// each kind): a full carried batch plus the record being appended.
pub const MIN_SLOTS_PER_SECTOR: usize = MAX_KINDS as usize + 1;
/// Most records a move may carry (the sum of a [`Keep`]).
pub const MAX_BATCH: usize = 64;
/// Records a move can hold in RAM because they survive only in the sector it erases.
const HELD_MAX: usize = 4;
/// Marks a batch entry held in RAM (an offset never has it: regions are < 2 GiB).
const HELD_BIT: u32 = 1 << 31;

/// How many of the newest records of each kind a move carries into the next sector
/// (`0` counts as 1: the newest record of every kind is always carried). The default
/// keeps one of each; a kind whose history matters beyond one sector's depth (the
/// micrometer readings, say) keeps more. The sum may not exceed [`MAX_BATCH`], and a
/// sector must hold the whole batch plus one record.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Keep(pub [u8; MAX_KINDS as usize]);

impl Keep {
    /// The newest record of each kind.
    pub const ONE_EACH: Self = Self([1; MAX_KINDS as usize]);

    /// Records kind `k` carries (at least 1): the depth of its history that every sector
    /// move preserves.
    pub fn of(&self, k: u8) -> usize {
        usize::from(self.0.get(usize::from(k)).copied().unwrap_or(1).max(1))
    }

    /// Records a move carries at most (the certificate kind is never carried).
    pub fn batch(&self) -> usize {
        (0..ERASED_KIND).map(|k| self.of(k)).sum()
    }
}

/// Length of the commit marker at the end of a slot, bytes.
const MARKER_LEN: usize = 4;
/// The commit marker of a committed slot.
const COMMITTED: [u8; MARKER_LEN] = [0; MARKER_LEN];
/// Value of erased flash.
const ERASED: u8 = 0xFF;
/// `carry` byte of a record written by `append` (not a carried copy).
const NOT_CARRIED: u8 = 0xFF;
/// Number of kinds, as an array length.
const KINDS: usize = MAX_KINDS as usize;
/// Slot size as a flash offset.
const SLOT_SIZE_U32: u32 = SLOT_SIZE as u32;

/// One record as read back from flash.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Record {
    /// Global record number (strictly increasing; a carried copy gets a new one).
    pub seq: u32,
    /// Record kind, `0..MAX_KINDS`.
    pub kind: u8,
    /// Payload bytes used, `0..=PAYLOAD_MAX`.
    pub len: u8,
    /// Payload; bytes from `len` on are 0xFF.
    pub payload: [u8; PAYLOAD_MAX],
}

impl Record {
    /// The payload bytes in use, `payload[..len]` (clamped to `PAYLOAD_MAX`).
    pub fn data(&self) -> &[u8] {
        self.payload
            .get(..usize::from(self.len))
            .unwrap_or(&self.payload)
    }
}

/// What [`RecordLog::open`] found in flash.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct OpenReport {
    /// Valid records (committed, CRC good), in all sectors.
    pub valid: u32,
    /// Used slots that are not valid: torn by a power cut, bit-flipped, or garbage.
    pub corrupt: u32,
    /// Sectors that are entirely erased (0xFF).
    pub erased_sectors: u32,
    /// Highest `seq` of any valid record; the next append gets a higher one.
    pub last_seq: Option<u32>,
    /// A move to a new sector was cut short; the next `append` redoes it (and
    /// `needs_maintenance` is true, so `maintain` can do its erase first).
    pub unfinished_move: bool,
}

/// Why a log operation failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum StorageError<E> {
    /// The flash driver failed (the log stays consistent; a retry may succeed).
    Flash(E),
    /// Payload longer than `PAYLOAD_MAX` = 48 bytes.
    TooLarge,
    /// Kind not in `0..MAX_KINDS - 1` (the last is the log's own).
    BadKind,
    /// Region unusable: fewer than 2 sectors, a sector not a whole number of at least
    /// `MIN_SLOTS_PER_SECTOR` slots, `WRITE_SIZE`/`READ_SIZE` not dividing 64, or more
    /// than 4 GiB.
    Geometry,
    /// All 2^32 sequence numbers used (at one record per second: after 136 years).
    SeqExhausted,
    /// A move found more than a few of the records it must carry only in the sector it
    /// has to erase (their copies went bad): it stops rather than lose them.
    Unmovable,
    /// An internal invariant failed (a bug in this module).
    LogicBug,
}

impl<E: core::fmt::Debug> core::fmt::Display for StorageError<E> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Flash(e) => write!(f, "flash error: {e:?}"),
            Self::TooLarge => f.write_str("record payload longer than 48 bytes"),
            Self::BadKind => f.write_str("record kind must be 0..15"),
            Self::Geometry => f.write_str(
                "flash region unusable: need >= 2 sectors of >= 17 64-byte slots, \
                 WRITE_SIZE and READ_SIZE dividing 64, <= 4 GiB",
            ),
            Self::SeqExhausted => f.write_str("record sequence numbers exhausted"),
            Self::Unmovable => {
                f.write_str("records to carry survive only in the sector the move must erase")
            }
            Self::LogicBug => f.write_str("internal error in the record log"),
        }
    }
}

/// The log: an index in RAM over the flash region it owns.
#[derive(Clone, Debug)]
pub struct RecordLog<F: NorFlash> {
    flash: F,
    /// Erase sector size, bytes (a multiple of `SLOT_SIZE`).
    sector_size: u32,
    /// Number of sectors in the region (≥ 2).
    sectors: u32,
    /// Slots per sector (≥ `MIN_SLOTS_PER_SECTOR`).
    slots_per_sector: u32,
    /// Sector being appended to.
    cur: u32,
    /// Next free slot in `cur`; `slots_per_sector` when full.
    next_slot: u32,
    /// `seq` of the next record; `None` when all are used.
    next_seq: Option<u32>,
    /// Byte offset of the newest valid record of each kind.
    newest: [Option<u32>; KINDS],
    /// The sector after `cur` is known to be erased, by an erase that completed: a
    /// certificate for it is in `cur` (see "Interrupted erases").
    next_ready: bool,
    /// Records of each kind a move carries.
    keep: Keep,
}

/// Contents of one slot.
enum Slot {
    /// All 0xFF: never programmed since the last erase.
    Blank,
    /// Programmed but not valid: torn, bit-flipped, or garbage.
    Invalid,
    /// A committed record with a good CRC; `carry` is the batch size of a carried copy.
    Valid { rec: Record, carry: Option<u8> },
}

/// A slot's header and payload: the bytes its CRC covers.
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct SlotBody {
    seq: U32,
    kind: u8,
    len: u8,
    carry: u8,
    reserved: u8,
    payload: [u8; PAYLOAD_MAX],
}

/// One slot as laid out in flash (drawn in the module doc).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct SlotLayout {
    body: SlotBody,
    crc: U32,
    commit: [u8; MARKER_LEN],
}

/// The 64 bytes of a committed slot holding `rec`.
fn encode(rec: &Record, carry: u8) -> [u8; SLOT_SIZE] {
    let body = SlotBody {
        seq: rec.seq.into(),
        kind: rec.kind,
        len: rec.len,
        carry,
        reserved: ERASED,
        payload: rec.payload,
    };
    let slot = SlotLayout {
        crc: crate::crc::crc32(body.as_bytes()).into(),
        body,
        commit: COMMITTED,
    };
    zerocopy::transmute!(slot)
}

/// Classify the 64 bytes of a slot.
fn decode(bytes: &[u8; SLOT_SIZE]) -> Slot {
    if bytes.iter().all(|&b| b == ERASED) {
        return Slot::Blank;
    }
    let slot: SlotLayout = zerocopy::transmute!(*bytes);
    let SlotBody {
        seq,
        kind,
        len,
        carry,
        payload,
        ..
    } = slot.body;
    let valid = slot.commit == COMMITTED
        && slot.crc.get() == crate::crc::crc32(slot.body.as_bytes())
        && usize::from(len) <= PAYLOAD_MAX
        && kind < MAX_KINDS
        && (carry == NOT_CARRIED || (1..=MAX_BATCH).contains(&usize::from(carry)));
    if !valid {
        return Slot::Invalid;
    }
    let rec = Record {
        seq: seq.get(),
        kind,
        len,
        payload,
    };
    let carry = (carry != NOT_CARRIED).then_some(carry);
    Slot::Valid { rec, carry }
}

/// What `open` learns about one sector.
struct SectorScan {
    sector: u32,
    /// Highest `seq` of a valid slot.
    max_seq: Option<u32>,
    /// Index of the last used (non-blank) slot.
    last_used: Option<u32>,
    /// Number of valid slots from slot 0 up to the first slot that is not.
    valid_prefix: u32,
    /// Still counting `valid_prefix`.
    in_prefix: bool,
    /// Batch size `n` of the carried copies found.
    carry_batch: Option<u8>,
    /// A valid record written by `append` was found.
    has_appended: bool,
}

impl SectorScan {
    fn new(sector: u32) -> Self {
        Self {
            sector,
            max_seq: None,
            last_used: None,
            valid_prefix: 0,
            in_prefix: true,
            carry_batch: None,
            has_appended: false,
        }
    }

    fn add(&mut self, index: u32, slot: &Slot) {
        match slot {
            Slot::Blank => self.in_prefix = false,
            Slot::Invalid => {
                self.last_used = Some(index);
                self.in_prefix = false;
            }
            Slot::Valid { rec, carry } => {
                self.last_used = Some(index);
                if self.in_prefix {
                    self.valid_prefix += 1;
                }
                self.max_seq = self.max_seq.max(Some(rec.seq));
                match carry {
                    Some(n) => {
                        self.carry_batch.get_or_insert(*n);
                    }
                    None => self.has_appended = true,
                }
            }
        }
    }

    fn is_blank(&self) -> bool {
        self.last_used.is_none()
    }

    /// The carried batch at the start of this sector is complete: all `n` copies are
    /// valid, or something was written after them (which happens only once it was).
    fn move_finished(&self) -> bool {
        match self.carry_batch {
            None => true,
            Some(n) => {
                let n = u32::from(n);
                self.has_appended
                    || self.valid_prefix >= n
                    || self.last_used.is_some_and(|i| i >= n)
            }
        }
    }
}

/// A record location found by `open`.
#[derive(Clone, Copy)]
struct Found {
    seq: u32,
    offset: u32,
    sector: u32,
}

/// What `open` learns about one kind: its newest record, and its newest record in a
/// sector other than that one (used if that sector turns out to be an unfinished move).
#[derive(Clone, Copy, Default)]
struct KindScan {
    newest: Option<Found>,
    newest_elsewhere: Option<Found>,
}

impl KindScan {
    fn add(&mut self, rec: Found) {
        match self.newest {
            Some(n) if rec.seq <= n.seq => {
                let better = self.newest_elsewhere.is_none_or(|e| rec.seq > e.seq);
                if rec.sector != n.sector && better {
                    self.newest_elsewhere = Some(rec);
                }
            }
            Some(n) => {
                if n.sector != rec.sector {
                    self.newest_elsewhere = Some(n);
                }
                self.newest = Some(rec);
            }
            None => self.newest = Some(rec),
        }
    }
}

impl<F: NorFlash> RecordLog<F> {
    /// Bytes written by the commit write: the marker, widened to one write unit.
    const COMMIT_LEN: usize = if F::WRITE_SIZE > MARKER_LEN {
        F::WRITE_SIZE
    } else {
        MARKER_LEN
    };

    /// Open the log over the whole of `flash`, one sector per `F::ERASE_SIZE` bytes.
    /// Only reads; succeeds on any content (see [`OpenReport`] for what it found).
    pub fn open(flash: F) -> Result<(Self, OpenReport), StorageError<F::Error>> {
        Self::open_with_sector_size(flash, F::ERASE_SIZE)
    }

    /// Open the log with sectors of `sector_size` bytes, which must be whole erase
    /// sectors of the device (for drivers whose `ERASE_SIZE` is not the sector size,
    /// such as the simulator built with small sectors). The region is the first
    /// `capacity / sector_size` sectors of `flash`.
    pub fn open_with_sector_size(
        flash: F,
        sector_size: usize,
    ) -> Result<(Self, OpenReport), StorageError<F::Error>> {
        Self::open_keeping(flash, sector_size, Keep::ONE_EACH)
    }

    /// Open the log (as [`Self::open_with_sector_size`]) carrying `keep` records of each
    /// kind at every move. A log must always be opened with the same `keep`.
    pub fn open_keeping(
        flash: F,
        sector_size: usize,
        keep: Keep,
    ) -> Result<(Self, OpenReport), StorageError<F::Error>> {
        let sizes_ok = F::WRITE_SIZE > 0
            && SLOT_SIZE % F::WRITE_SIZE == 0
            && F::READ_SIZE > 0
            && SLOT_SIZE % F::READ_SIZE == 0
            && sector_size % SLOT_SIZE == 0
            && sector_size / SLOT_SIZE >= MIN_SLOTS_PER_SECTOR
            && keep.batch() <= MAX_BATCH
            && sector_size / SLOT_SIZE > keep.batch();
        if !sizes_ok {
            return Err(StorageError::Geometry);
        }
        let sectors = flash.capacity() / sector_size;
        let region = sectors.saturating_mul(sector_size);
        let (Ok(sectors), Ok(sector_size), Ok(_)) = (
            u32::try_from(sectors),
            u32::try_from(sector_size),
            u32::try_from(region),
        ) else {
            return Err(StorageError::Geometry);
        };
        if sectors < 2 {
            return Err(StorageError::Geometry);
        }
        let mut log = Self {
            flash,
            sector_size,
            sectors,
            slots_per_sector: sector_size / SLOT_SIZE_U32,
            cur: 0,
            next_slot: 0,
            next_seq: Some(0),
            newest: [None; KINDS],
            next_ready: false,
            keep,
        };
        let report = log.scan()?;
        info!(
            "storage: {=u32} valid, {=u32} corrupt records; sector {=u32} slot {=u32}; unfinished move: {=bool}",
            report.valid, report.corrupt, log.cur, log.next_slot, report.unfinished_move
        );
        Ok((log, report))
    }

    /// Read every slot and rebuild the RAM index (reads only).
    fn scan(&mut self) -> Result<OpenReport, StorageError<F::Error>> {
        let mut report = OpenReport::default();
        let mut kinds = [KindScan::default(); KINDS];
        let mut newest_sector: Option<SectorScan> = None;
        let mut sector0_last_used = None;
        for sector in 0..self.sectors {
            let mut scan = SectorScan::new(sector);
            for index in 0..self.slots_per_sector {
                let offset = self.slot_offset(sector, index);
                let slot = self.read_slot(offset)?;
                scan.add(index, &slot);
                match slot {
                    Slot::Blank => {}
                    Slot::Invalid => report.corrupt += 1,
                    Slot::Valid { rec, .. } => {
                        report.valid += 1;
                        let found = Found {
                            seq: rec.seq,
                            offset,
                            sector,
                        };
                        if let Some(k) = kinds.get_mut(usize::from(rec.kind)) {
                            k.add(found);
                        }
                    }
                }
            }
            if scan.is_blank() {
                report.erased_sectors += 1;
            }
            if sector == 0 {
                sector0_last_used = scan.last_used;
            }
            if scan.max_seq > newest_sector.as_ref().and_then(|s| s.max_seq) {
                newest_sector = Some(scan);
            }
        }

        let mut abandoned = None;
        match &newest_sector {
            // Nothing valid anywhere: append to sector 0 after its last used slot.
            None => {
                self.cur = 0;
                self.next_slot = sector0_last_used.map_or(0, |i| i + 1);
            }
            Some(s) if s.move_finished() => {
                self.cur = s.sector;
                self.next_slot = s.last_used.map_or(0, |i| i + 1);
            }
            // The newest sector holds an unfinished carried batch: ignore it; the sector
            // before it (full) is current, so the next append redoes the move.
            Some(s) => {
                warn!("storage: move to sector {=u32} was cut short", s.sector);
                abandoned = Some(s.sector);
                self.cur = (s.sector + self.sectors - 1) % self.sectors;
                self.next_slot = self.slots_per_sector;
                report.unfinished_move = true;
            }
        }
        report.last_seq = newest_sector.and_then(|s| s.max_seq);
        self.next_seq = report.last_seq.map_or(Some(0), |s| s.checked_add(1));
        for (slot, k) in self.newest.iter_mut().zip(&kinds) {
            let pick = match k.newest {
                Some(n) if Some(n.sector) == abandoned => k.newest_elsewhere,
                other => other,
            };
            *slot = pick.map(|f| f.offset);
        }
        self.next_ready =
            self.certified(self.next_sector())? && self.sector_is_blank(self.next_sector())?;
        Ok(report)
    }

    /// Append a record; may move to (and erase) the next sector: call only while the
    /// machine is idle. Returns the record's `seq`.
    pub fn append(&mut self, kind: u8, data: &[u8]) -> Result<u32, StorageError<F::Error>> {
        if kind == ERASED_KIND {
            return Err(StorageError::BadKind);
        }
        self.append_any(kind, data)
    }

    fn append_any(&mut self, kind: u8, data: &[u8]) -> Result<u32, StorageError<F::Error>> {
        let k = kind_index(kind)?;
        if data.len() > PAYLOAD_MAX {
            return Err(StorageError::TooLarge);
        }
        let len = u8::try_from(data.len()).map_err(|_| StorageError::TooLarge)?;
        // The data, then erased bytes: built byte by byte (a 0xFF fill first linked
        // compiler_builtins' memset for this alone).
        let payload: [u8; PAYLOAD_MAX] =
            core::array::from_fn(|i| data.get(i).copied().unwrap_or(ERASED));
        if self.next_slot >= self.slots_per_sector {
            self.move_to_next_sector()?;
        }
        if self.next_slot >= self.slots_per_sector {
            return Err(StorageError::LogicBug);
        }
        let seq = self.take_seq()?;
        let offset = self.slot_offset(self.cur, self.next_slot);
        // The slot is used from the first byte programmed on, whatever happens next.
        self.next_slot += 1;
        let rec = Record {
            seq,
            kind,
            len,
            payload,
        };
        self.program(offset, &rec, NOT_CARRIED)?;
        if let Some(n) = self.newest.get_mut(k) {
            *n = Some(offset);
        }
        Ok(seq)
    }

    /// The newest valid record of `kind`, if any.
    pub fn latest(&mut self, kind: u8) -> Result<Option<Record>, StorageError<F::Error>> {
        let k = kind_index(kind)?;
        let Some(offset) = self.newest.get(k).copied().flatten() else {
            return Ok(None);
        };
        if let Slot::Valid { rec, .. } = self.read_slot(offset)? {
            if rec.kind == kind {
                return Ok(Some(rec));
            }
        }
        // The slot changed since it was indexed (bit flips): use the newest intact one.
        warn!(
            "storage: record at {=u32} went bad; looking for an older one",
            offset
        );
        let mut found = None;
        self.walk_newest_first(kind, 1, &mut |off, rec| {
            found = Some((off, *rec));
            true
        })?;
        if let Some(n) = self.newest.get_mut(k) {
            *n = found.map(|(off, _)| off);
        }
        Ok(found.map(|(_, rec)| rec))
    }

    /// Up to `max` newest valid records of `kind`, newest first, calling `f` for each;
    /// returns how many. Walks back through the current and older sectors; a carried
    /// copy and its original count once (as the copy).
    pub fn for_each_newest_first(
        &mut self,
        kind: u8,
        max: usize,
        mut f: impl FnMut(&Record),
    ) -> Result<usize, StorageError<F::Error>> {
        kind_index(kind)?;
        self.walk_newest_first(kind, max, &mut |_, rec| {
            f(rec);
            true
        })
    }

    /// The newest valid records of `kind`, newest first, while `f` returns `true`:
    /// the walk stops at the first `false` and reads no further slot (a history of the
    /// last N cycles reads N-odd slots, not the whole log). Returns how many `f` saw.
    pub fn for_each_newest_first_while(
        &mut self,
        kind: u8,
        mut f: impl FnMut(&Record) -> bool,
    ) -> Result<usize, StorageError<F::Error>> {
        kind_index(kind)?;
        self.walk_newest_first(kind, usize::MAX, &mut |_, rec| f(rec))
    }

    /// True when the next sector is not known to be erased and the current one is at
    /// least 90 % full, with a slot left for the erase certificate; [`Self::maintain`]
    /// then erases it so that `append` rarely has to. (A full current sector — after a
    /// move that was cut short — leaves the erase to the next append's move.)
    pub fn needs_maintenance(&self) -> bool {
        !self.next_ready
            && self.next_slot * 10 >= self.slots_per_sector * 9
            && self.next_slot < self.slots_per_sector
    }

    /// Erase the next sector if [`Self::needs_maintenance`], and certify the completed
    /// erase with a record in the current sector; call only while the machine is idle
    /// (an erase stalls the STM32F4 CPU for ~1–2 s). A next sector that merely reads
    /// blank is erased all the same: an erase cut short can leave it reading 0xFF.
    pub fn maintain(&mut self) -> Result<(), StorageError<F::Error>> {
        if !self.needs_maintenance() {
            return Ok(());
        }
        let next = self.next_sector();
        // (The erase certificate is not carried: it may lie there.)
        if self
            .newest
            .iter()
            .take(usize::from(ERASED_KIND))
            .flatten()
            .any(|&o| o / self.sector_size == next)
        {
            // Only after bit flips in the current sector; the move rescues it via RAM.
            warn!(
                "storage: sector {=u32} holds a newest record; not erased early",
                next
            );
            return Ok(());
        }
        self.erase_sector(next)?;
        let sector = u8::try_from(next).map_err(|_| StorageError::LogicBug)?;
        self.append_any(ERASED_KIND, &[sector])?;
        self.next_ready = true;
        Ok(())
    }

    /// Records of each kind a move carries.
    pub fn keep(&self) -> Keep {
        self.keep
    }

    /// The flash device.
    pub fn flash(&self) -> &F {
        &self.flash
    }

    /// The flash device, mutably; writing to the log's region behind its back voids
    /// its guarantees.
    pub fn flash_mut(&mut self) -> &mut F {
        &mut self.flash
    }

    /// Give the flash device back.
    pub fn into_inner(self) -> F {
        self.flash
    }

    /// Free slots left in the current sector (0: the next append moves on).
    pub fn slots_free_in_sector(&self) -> usize {
        to_usize(self.slots_per_sector.saturating_sub(self.next_slot))
    }

    /// Slots in the whole region (sectors × slots per sector).
    pub fn capacity_slots(&self) -> usize {
        to_usize(self.sectors).saturating_mul(to_usize(self.slots_per_sector))
    }

    /// Slots per sector.
    pub fn slots_per_sector(&self) -> usize {
        to_usize(self.slots_per_sector)
    }

    /// Index of the sector being appended to, `0..sectors`.
    pub fn current_sector(&self) -> usize {
        to_usize(self.cur)
    }

    // --- internals -------------------------------------------------------------------

    /// Move to the next sector: erase it if needed, carry forward the newest record of
    /// every kind. RAM state changes only once the carried batch is complete, so a
    /// failure leaves the current sector full and the next call starts over.
    // Out of line: only a move needs its frame (a few hundred bytes), not every append.
    #[inline(never)]
    fn move_to_next_sector(&mut self) -> Result<(), StorageError<F::Error>> {
        let next = self.next_sector();
        // 1. Where the newest records of every kind are (as many as `keep` says), found
        // while every sector is intact: (seq, offset). (Not the erase certificate: it
        // names the sector being moved into, and is spent once the move is done.) A
        // record that survives only in the sector about to be erased (its copies went
        // bad) is held in RAM; a few at most.
        let mut batch: heapless::Vec<(u32, u32), MAX_BATCH> = heapless::Vec::new();
        let mut held: heapless::Vec<Record, HELD_MAX> = heapless::Vec::new();
        let mut found: heapless::Vec<(u32, u32), MAX_BATCH> = heapless::Vec::new();
        for kind in 0..ERASED_KIND {
            found.clear();
            if self.keep.of(kind) == 1 {
                // The index (repaired by `latest` if its slot went bad).
                if self.latest(kind)?.is_some() {
                    if let Some(off) = self.newest.get(usize::from(kind)).copied().flatten() {
                        let _ = found.push((0, off));
                    }
                }
            } else {
                let mut full = false;
                self.walk_newest_first(kind, self.keep.of(kind), &mut |off, _| {
                    full |= found.push((0, off)).is_err();
                    true
                })?;
                if full {
                    return Err(StorageError::LogicBug);
                }
            }
            for &(_, off) in &found {
                let Slot::Valid { rec, .. } = self.read_slot(off)? else {
                    return Err(StorageError::LogicBug);
                };
                let at = if off / self.sector_size == next {
                    held.push(rec).map_err(|_| StorageError::Unmovable)?;
                    HELD_BIT | (held.len() as u32 - 1)
                } else {
                    off
                };
                batch
                    .push((rec.seq, at))
                    .map_err(|_| StorageError::LogicBug)?;
            }
        }
        // At most MAX_BATCH entries: an insertion sort by seq (the library sort costs
        // ~2.5 KiB of flash on the target for nothing).
        let recs = batch.as_mut_slice();
        for i in 1..recs.len() {
            let mut j = i;
            while j > 0 && recs.get(j - 1).map(|r| r.0) > recs.get(j).map(|r| r.0) {
                recs.swap(j - 1, j);
                j -= 1;
            }
        }
        let n = u8::try_from(batch.len()).map_err(|_| StorageError::LogicBug)?;
        // 2. A blank next sector: erased and certified by `maintain`, or erased now
        // (even if it reads blank: see "Interrupted erases").
        if !self.next_ready {
            self.erase_sector(next)?;
        }
        // 3. The carried batch, oldest first, in slots 0..n.
        let mut moved: [Option<u32>; KINDS] = [None; KINDS];
        for (index, &(_, at)) in (0..).zip(&batch) {
            let old = if at & HELD_BIT != 0 {
                *held
                    .get((at & !HELD_BIT) as usize)
                    .ok_or(StorageError::LogicBug)?
            } else {
                match self.read_slot(at)? {
                    Slot::Valid { rec, .. } => rec,
                    _ => return Err(StorageError::LogicBug),
                }
            };
            let rec = Record {
                seq: self.take_seq()?,
                ..old
            };
            let offset = self.slot_offset(next, index);
            self.program(offset, &rec, n)?;
            if let Some(m) = moved.get_mut(usize::from(rec.kind)) {
                *m = Some(offset);
            }
        }
        debug!(
            "storage: moved to sector {=u32}, carried {=u8} records",
            next, n
        );
        self.cur = next;
        self.next_slot = u32::from(n);
        self.next_ready = false;
        self.newest = moved;
        Ok(())
    }

    /// Call `f(offset, record)` for up to `max` valid records of `kind`, newest first.
    ///
    /// Slots are visited newest first (current sector downward from the write slot, then
    /// the sectors before it). A record whose `seq` is not below every `seq` seen so far
    /// is out of place (a copy from an unfinished move) and ignored. The carried copies
    /// of `kind` in a sector are the newest records of `kind` of the sectors before it,
    /// in the same order: walking on into the next older sector, those originals (same
    /// payload, in order) are skipped, the copies having been reported.
    // One copy for every caller (`f` is dynamic): each closure type made one before,
    // ~900 bytes apiece.
    #[inline(never)]
    fn walk_newest_first(
        &mut self,
        kind: u8,
        max: usize,
        f: &mut dyn FnMut(u32, &Record) -> bool,
    ) -> Result<usize, StorageError<F::Error>> {
        let mut count = 0;
        let mut more = true;
        let mut floor: Option<u32> = None;
        // Payload digests of the carried copies of `kind` in the sector walked last,
        // newest first: the originals expected in the sector walked next.
        let mut copies: heapless::Vec<u32, MAX_BATCH> = heapless::Vec::new();
        for back in 0..self.sectors {
            if count >= max || !more {
                break;
            }
            let sector = (self.cur + self.sectors - back) % self.sectors;
            let top = if back == 0 {
                self.next_slot
            } else {
                self.slots_per_sector
            };
            let expect = core::mem::take(&mut copies);
            let mut matched = 0;
            for index in (0..top).rev() {
                let offset = self.slot_offset(sector, index);
                let Slot::Valid { rec, carry } = self.read_slot(offset)? else {
                    continue;
                };
                if floor.is_some_and(|fl| rec.seq >= fl) {
                    continue;
                }
                floor = Some(rec.seq);
                if rec.kind != kind {
                    continue;
                }
                let digest = crate::crc::crc32(rec.data());
                if carry.is_some() {
                    // More copies than a batch holds cannot be: ignore the excess.
                    let _ = copies.push(digest);
                }
                // The original of a copy reported from the sector before (an original
                // that went bad is passed over).
                if let Some(p) = expect
                    .get(matched..)
                    .and_then(|rest| rest.iter().position(|&d| d == digest))
                {
                    matched += p + 1;
                    continue;
                }
                more = f(offset, &rec);
                count += 1;
                if count >= max || !more {
                    break;
                }
            }
        }
        Ok(count)
    }

    /// Program one slot: everything but the commit write unit, then the commit.
    fn program(
        &mut self,
        offset: u32,
        rec: &Record,
        carry: u8,
    ) -> Result<(), StorageError<F::Error>> {
        let slot = encode(rec, carry);
        let (body, commit) = slot
            .split_at_checked(SLOT_SIZE - Self::COMMIT_LEN)
            .ok_or(StorageError::LogicBug)?;
        if !body.is_empty() {
            self.flash
                .write(offset, body)
                .map_err(StorageError::Flash)?;
        }
        let commit_offset = offset + SLOT_SIZE_U32 - to_u32(Self::COMMIT_LEN);
        self.flash
            .write(commit_offset, commit)
            .map_err(StorageError::Flash)
    }

    fn read_slot(&mut self, offset: u32) -> Result<Slot, StorageError<F::Error>> {
        let mut bytes = [0u8; SLOT_SIZE];
        self.flash
            .read(offset, &mut bytes)
            .map_err(StorageError::Flash)?;
        Ok(decode(&bytes))
    }

    fn sector_is_blank(&mut self, sector: u32) -> Result<bool, StorageError<F::Error>> {
        for index in 0..self.slots_per_sector {
            if !matches!(
                self.read_slot(self.slot_offset(sector, index))?,
                Slot::Blank
            ) {
                return Ok(false);
            }
        }
        Ok(true)
    }

    /// Whether the newest erase certificate lies in the current sector and names
    /// `sector` (a certificate in an older sector predates the move into the current
    /// one, and with it any use of the sectors after).
    fn certified(&mut self, sector: u32) -> Result<bool, StorageError<F::Error>> {
        let Some(off) = self.newest.get(usize::from(ERASED_KIND)).copied().flatten() else {
            return Ok(false);
        };
        if off / self.sector_size != self.cur {
            return Ok(false);
        }
        Ok(match self.read_slot(off)? {
            Slot::Valid { rec, .. } => {
                rec.kind == ERASED_KIND && rec.data().first().map(|&b| u32::from(b)) == Some(sector)
            }
            _ => false,
        })
    }

    fn erase_sector(&mut self, sector: u32) -> Result<(), StorageError<F::Error>> {
        let from = sector * self.sector_size;
        self.next_ready = false;
        self.flash
            .erase(from, from + self.sector_size)
            .map_err(StorageError::Flash)?;
        debug!("storage: erased sector {=u32}", sector);
        Ok(())
    }

    fn take_seq(&mut self) -> Result<u32, StorageError<F::Error>> {
        let seq = self.next_seq.ok_or(StorageError::SeqExhausted)?;
        self.next_seq = seq.checked_add(1);
        Ok(seq)
    }

    fn next_sector(&self) -> u32 {
        (self.cur + 1) % self.sectors
    }

    /// Byte offset of slot `index` of `sector` (in range by construction: the region
    /// fits in `u32`).
    fn slot_offset(&self, sector: u32, index: u32) -> u32 {
        sector * self.sector_size + index * SLOT_SIZE_U32
    }
}

/// `kind` as an index into per-kind tables, or `BadKind`.
fn kind_index<E>(kind: u8) -> Result<usize, StorageError<E>> {
    if kind < MAX_KINDS {
        Ok(usize::from(kind))
    } else {
        Err(StorageError::BadKind)
    }
}

/// `u32` to `usize` (lossless on every target this runs on: 32- and 64-bit).
fn to_usize(v: u32) -> usize {
    usize::try_from(v).unwrap_or(usize::MAX)
}

/// A slot-sized length to `u32`.
fn to_u32(v: usize) -> u32 {
    u32::try_from(v).unwrap_or(u32::MAX)
}
