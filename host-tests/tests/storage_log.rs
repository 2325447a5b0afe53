//! The power-cut-safe record log (`docking_logic::storage`) on the simulated NOR
//! flash: round trips, every power-cut point of a scripted run, bit flips, garbage,
//! wear levelling on the board's 2 × 128 KiB, and pre-erasing by `maintain`.
//!
//! Small tests use sectors of `MIN_SLOTS_PER_SECTOR` = 17 slots (1088 bytes), the
//! smallest the log accepts (a full carried batch of 16 kinds + 1): the log moves between
//! sectors every few appends. Power-cut campaigns replay a script with the power cut
//! after every programmed byte / erase (`Cuts::All`), or after every one within a window
//! of appends that includes sector moves plus random ones elsewhere (`Cuts::Window`).

use std::fmt::Debug;
use std::ops::Range;

use docking_logic::storage::{
    Keep, OpenReport, RecordLog, StorageError, ERASED_KIND, MAX_KINDS, MIN_SLOTS_PER_SECTOR,
    PAYLOAD_MAX, SLOT_SIZE,
};
use embedded_storage::nor_flash::{ErrorType, NorFlash, ReadNorFlash};
use hil_sim::flash::{SimFlash, SimFlashError, SECTOR_SIZE};
use hil_sim::rng::Rng;

/// Smallest sector the log accepts, bytes.
const SMALL: usize = MIN_SLOTS_PER_SECTOR * SLOT_SIZE;

// --- helpers ---------------------------------------------------------------------------

/// A flash whose power can be cut: the simulator, or the simulator behind another
/// `WRITE_SIZE`.
trait CutFlash: NorFlash + Clone + Debug {
    /// Cut the power after `n` more units (programmed bytes; an erase is one).
    fn arm_cut(&mut self, n: u64);
    /// Power back on.
    fn reboot(&mut self);
    /// Units spent so far (bytes programmed + erases done).
    fn units(&self) -> u64;
    /// Erases done so far.
    fn erases(&self) -> u64;
}

impl CutFlash for SimFlash {
    fn arm_cut(&mut self, n: u64) {
        self.cut_after_bytes(n);
    }
    fn reboot(&mut self) {
        self.power_on();
    }
    fn units(&self) -> u64 {
        self.bytes_written() + self.erases()
    }
    fn erases(&self) -> u64 {
        self.erase_counts().iter().map(|&c| u64::from(c)).sum()
    }
}

/// The simulator behind a `WRITE_SIZE` of `W` (1 like the board, 4 like the simulator,
/// 8, 64) that checks how the log programs it: whole aligned units of `W`; no byte
/// programmed twice between erases; a slot's commit marker (its last 4 bytes) written
/// last, by a write of its own (the slot's last write unit when `W` > 4), after every
/// other byte of the slot.
#[derive(Clone, Debug)]
struct Checked<const W: usize> {
    sim: SimFlash,
    /// Bytes programmed by a completed write since their sector's last erase.
    programmed: Vec<bool>,
}

impl<const W: usize> Checked<W> {
    fn new(sectors: usize, sector_size: usize) -> Self {
        Self {
            sim: SimFlash::new(sectors, sector_size),
            programmed: vec![false; sectors * sector_size],
        }
    }
}

impl<const W: usize> ErrorType for Checked<W> {
    type Error = SimFlashError;
}

impl<const W: usize> ReadNorFlash for Checked<W> {
    const READ_SIZE: usize = 1;
    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.sim.read(offset, bytes)
    }
    fn capacity(&self) -> usize {
        self.sim.capacity()
    }
}

impl<const W: usize> NorFlash for Checked<W> {
    const WRITE_SIZE: usize = W;
    const ERASE_SIZE: usize = SimFlash::ERASE_SIZE;
    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        self.sim.erase(from, to)?;
        self.programmed[from as usize..to as usize].fill(false);
        Ok(())
    }
    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let (start, end) = (offset as usize, offset as usize + bytes.len());
        assert!(
            start % W == 0 && end % W == 0,
            "write {start}..{end} not in units of {W}"
        );
        assert!(
            !self.programmed[start..end].contains(&true),
            "write {start}..{end} programs bytes a second time"
        );
        let slot = start / SLOT_SIZE * SLOT_SIZE;
        assert!(
            end <= slot + SLOT_SIZE,
            "write {start}..{end} spans two slots"
        );
        if end > slot + SLOT_SIZE - 4 {
            // The commit write: the slot's last max(W, 4) bytes, after all the others.
            let commit_start = slot + SLOT_SIZE - W.max(4);
            assert_eq!(
                (start, end),
                (commit_start, slot + SLOT_SIZE),
                "commit write"
            );
            assert!(
                !self.programmed[slot..start].contains(&false),
                "commit marker of slot {slot} written before the rest of the slot"
            );
        }
        self.sim.write(offset, bytes)?;
        self.programmed[start..end].fill(true);
        Ok(())
    }
}

impl<const W: usize> CutFlash for Checked<W> {
    fn arm_cut(&mut self, n: u64) {
        self.sim.cut_after_bytes(n);
    }
    fn reboot(&mut self) {
        self.sim.power_on();
    }
    fn units(&self) -> u64 {
        self.sim.units()
    }
    fn erases(&self) -> u64 {
        self.sim.erases()
    }
}

thread_local! {
    /// What `open` keeps per kind (a test that wants more than one sets it first).
    static KEEP: std::cell::Cell<Keep> = const { std::cell::Cell::new(Keep::ONE_EACH) };
}

fn open<F: NorFlash>(flash: F, sector_size: usize) -> (RecordLog<F>, OpenReport) {
    RecordLog::open_keeping(flash, sector_size, KEEP.with(|k| k.get()))
        .expect("open fails only on read errors")
}

/// Power back on and reopen.
fn reboot<F: CutFlash>(log: RecordLog<F>, sector_size: usize) -> (RecordLog<F>, OpenReport) {
    let keep = log.keep();
    let mut flash = log.into_inner();
    flash.reboot();
    RecordLog::open_keeping(flash, sector_size, keep).expect("open fails only on read errors")
}

fn latest_data<F: NorFlash>(log: &mut RecordLog<F>, kind: u8) -> Option<Vec<u8>> {
    log.latest(kind).expect("latest").map(|r| r.data().to_vec())
}

fn history<F: NorFlash>(log: &mut RecordLog<F>, kind: u8, max: usize) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let n = log
        .for_each_newest_first(kind, max, |r| {
            assert_eq!(r.kind, kind);
            out.push(r.data().to_vec());
        })
        .expect("for_each_newest_first");
    assert_eq!(n, out.len());
    out
}

/// Check the log against the expected history of every kind (`expected(kind)`, newest
/// first): `latest` must be its first entry; the walk (up to `walk_max` records) must
/// be a non-empty prefix of it — older entries may have been erased, none may be
/// missing, reordered or invented.
fn check_log<F: NorFlash>(
    log: &mut RecordLog<F>,
    walk_max: usize,
    expected: impl Fn(u8) -> Vec<Vec<u8>>,
    ctx: &dyn Fn() -> String,
) {
    for kind in 0..ERASED_KIND {
        let want = expected(kind);
        assert_eq!(
            latest_data(log, kind),
            want.first().cloned(),
            "kind {kind}: {}",
            ctx()
        );
        if want.is_empty() {
            continue;
        }
        // The depth every move preserves is always there.
        let kept = want.len().min(log.keep().of(kind));
        assert_eq!(
            history(log, kind, kept)[..],
            want[..kept],
            "kind {kind}: the {kept} kept records: {}",
            ctx()
        );
        let got = history(log, kind, walk_max);
        assert!(
            !got.is_empty() && got.len() <= want.len(),
            "kind {kind}: {}",
            ctx()
        );
        assert_eq!(got[..], want[..got.len()], "kind {kind} history: {}", ctx());
    }
}

/// A unique payload (its first two bytes are `tag`), 2..=48 bytes long.
fn unique_payload(tag: u16, len_seed: usize) -> Vec<u8> {
    let len = 2 + len_seed % (PAYLOAD_MAX - 1);
    let mut d: Vec<u8> = (0..len).map(|j| (j * 37 + len_seed) as u8).collect();
    d[..2].copy_from_slice(&tag.to_le_bytes());
    d
}

/// A script of `n` appends over `kinds` kinds (kind 0 most often), unique payloads.
fn script(n: usize, kinds: u8) -> Vec<(u8, Vec<u8>)> {
    (0..n)
        .map(|i| {
            let kind = if i % 2 == 0 {
                0
            } else {
                (i / 2 % kinds as usize) as u8
            };
            (kind, unique_payload(i as u16, i * 7))
        })
        .collect()
}

/// Newest-first history of `kind` in `entries` (oldest first).
fn newest_first<'a>(
    entries: impl DoubleEndedIterator<Item = &'a (u8, Vec<u8>)>,
    kind: u8,
) -> Vec<Vec<u8>> {
    entries
        .rev()
        .filter(|(k, _)| *k == kind)
        .map(|(_, d)| d.clone())
        .collect()
}

// --- 1. round trip ---------------------------------------------------------------------

#[test]
fn round_trip_across_many_sector_moves() {
    let (mut log, report) = open(SimFlash::new(3, SMALL), SMALL);
    assert_eq!(
        report,
        OpenReport {
            erased_sectors: 3,
            ..OpenReport::default()
        }
    );
    assert_eq!(log.capacity_slots(), 3 * MIN_SLOTS_PER_SECTOR);
    assert_eq!(log.slots_per_sector(), MIN_SLOTS_PER_SECTOR);

    // Kind 9 is written once and must be carried through every move.
    let mut model: Vec<(u8, Vec<u8>)> = vec![(9, b"commissioned 2025-06-01".to_vec())];
    log.append(9, &model[0].1).unwrap();
    let mut rng = Rng::new(1);
    let mut sectors_seen = vec![log.current_sector()];
    let mut last_seq = 0;
    for i in 0..600u32 {
        let kind = [0, 0, 0, 1, 2, 3][(rng.next_u64() % 6) as usize];
        // Empty payloads, full payloads, and repeats of the previous one of the kind.
        let data = match rng.next_u64() % 8 {
            0 => Vec::new(),
            1 => vec![i as u8; PAYLOAD_MAX],
            2 => newest_first(model.iter(), kind)
                .first()
                .cloned()
                .unwrap_or_default(),
            _ => unique_payload(i as u16, rng.next_u64() as usize),
        };
        let seq = log.append(kind, &data).unwrap();
        assert!(seq > last_seq, "seq must increase");
        last_seq = seq;
        model.push((kind, data.clone()));
        let rec = log.latest(kind).unwrap().unwrap();
        assert_eq!((rec.seq, rec.kind, rec.data()), (seq, kind, &data[..]));
        if sectors_seen.last() != Some(&log.current_sector()) {
            sectors_seen.push(log.current_sector());
        }
        if i % 97 == 0 {
            log = reboot(log, SMALL).0;
        }
        check_log(&mut log, 6, |k| newest_first(model.iter(), k), &|| {
            format!("append {i}")
        });
    }
    // Round-robin 0 → 1 → 2 → 0 …, many times.
    assert!(sectors_seen.len() > 30, "{sectors_seen:?}");
    for w in sectors_seen.windows(2) {
        assert_eq!(w[1], (w[0] + 1) % 3);
    }
    let (mut log, report) = reboot(log, SMALL);
    assert_eq!(report.corrupt, 0);
    assert_eq!(report.last_seq, Some(last_seq));
    check_log(
        &mut log,
        usize::MAX,
        |k| newest_first(model.iter(), k),
        &|| "final".into(),
    );
    // The walk reaches back through older sectors, not only the current one.

    // The walk reaches back through every sector not yet erased, carried copies once:
    // 40 records of one kind over 3 sectors (17 + 1 carried + 15 + 1 carried + 8).
    let (mut log, _) = open(SimFlash::new(3, SMALL), SMALL);
    for i in 0..40u8 {
        log.append(4, &[i]).unwrap();
    }
    assert_eq!(log.current_sector(), 2);
    let all: Vec<Vec<u8>> = (0..40u8).rev().map(|i| vec![i]).collect();
    assert_eq!(history(&mut log, 4, usize::MAX), all);
    assert_eq!(history(&mut log, 4, 3), all[..3]);
}

#[test]
fn every_user_kind_survives_moves_on_minimum_sectors() {
    let (mut log, _) = open(SimFlash::new(2, SMALL), SMALL);
    assert_eq!(log.append(ERASED_KIND, &[0]), Err(StorageError::BadKind));
    let mut model = Vec::new();
    for i in 0..200u16 {
        let kind = (i % u16::from(ERASED_KIND)) as u8;
        let data = unique_payload(i, i as usize);
        log.append(kind, &data).unwrap();
        model.push((kind, data));
        // Each move carries 15 records into a 17-slot sector: one append in two moves.
        assert!(i < 17 || log.slots_free_in_sector() <= 1);
    }
    let (mut log, report) = reboot(log, SMALL);
    assert_eq!(report.corrupt, 0);
    check_log(
        &mut log,
        usize::MAX,
        |k| newest_first(model.iter(), k),
        &|| "16 kinds".into(),
    );
}

#[test]
fn bad_arguments_and_geometry_are_refused() {
    let (mut log, _) = open(SimFlash::new(2, SMALL), SMALL);
    assert_eq!(log.append(MAX_KINDS, b"x"), Err(StorageError::BadKind));
    assert_eq!(
        log.append(0, &[0; PAYLOAD_MAX + 1]),
        Err(StorageError::TooLarge)
    );
    assert_eq!(log.latest(MAX_KINDS), Err(StorageError::BadKind));
    assert!(log.for_each_newest_first(200, 1, |_| ()).is_err());
    assert_eq!(log.append(0, &[7; PAYLOAD_MAX]), Ok(0));
    assert_eq!(
        log.for_each_newest_first(0, 0, |_| panic!("max = 0")),
        Ok(0)
    );

    let geometry =
        |flash: SimFlash, sector: usize| RecordLog::open_with_sector_size(flash, sector).err();
    assert_eq!(
        geometry(SimFlash::new(1, SMALL), SMALL),
        Some(StorageError::Geometry)
    );
    assert_eq!(
        geometry(SimFlash::new(3, 1024), 1024),
        Some(StorageError::Geometry),
        "16 slots"
    );
    assert_eq!(
        geometry(SimFlash::new(3, SMALL), SMALL + 4),
        Some(StorageError::Geometry)
    );
    // `open` takes ERASE_SIZE (128 KiB) as the sector size.
    assert!(matches!(
        RecordLog::open(SimFlash::new(3, SMALL)),
        Err(StorageError::Geometry)
    ));
    let (log, report) = RecordLog::open(SimFlash::stm32f407_odometer()).unwrap();
    assert_eq!(report.erased_sectors, 2);
    assert_eq!(log.capacity_slots(), 2 * SECTOR_SIZE / SLOT_SIZE);
}

// --- 2. power cuts ---------------------------------------------------------------------

/// A cut-free run of a script: the log before each append and the units spent by then.
/// The simulator is deterministic, so replaying append `i` from `before[i]` with a cut
/// armed is the same as replaying the whole script from scratch with that cut
/// (`power_cut_replay_from_scratch` checks it).
struct Reference<F: CutFlash> {
    before: Vec<RecordLog<F>>,
    /// `units[i]`: units spent before append `i`; last entry: the total.
    units: Vec<u64>,
    /// Append `i` moved to the next sector.
    moved: Vec<bool>,
}

impl<F: CutFlash> Reference<F> {
    fn run(fresh: F, sector: usize, script: &[(u8, Vec<u8>)]) -> Self {
        let (mut log, _) = open(fresh, sector);
        let (mut before, mut units, mut moved) = (Vec::new(), Vec::new(), Vec::new());
        for (kind, data) in script {
            before.push(log.clone());
            units.push(log.flash().units());
            let sector = log.current_sector();
            log.append(*kind, data).unwrap();
            moved.push(log.current_sector() != sector);
        }
        units.push(log.flash().units());
        Self {
            before,
            units,
            moved,
        }
    }

    /// The append in which unit `n` is spent, if any.
    fn append_at(&self, n: u64) -> Option<usize> {
        let i = self.units.partition_point(|&u| u <= n) - 1;
        (i < self.before.len()).then_some(i)
    }

    /// Replay append `i` of `script` with the power cut after unit `n`; returns the log
    /// with the power off.
    fn cut(&self, script: &[(u8, Vec<u8>)], i: usize, n: u64) -> RecordLog<F> {
        let mut log = self.before[i].clone();
        log.flash_mut().arm_cut(n - self.units[i]);
        let (kind, data) = &script[i];
        assert!(
            log.append(*kind, data).is_err(),
            "cut {n} must hit append {i}"
        );
        log
    }
}

/// Which cut points a power-cut campaign tries (in units of the cut-free run).
enum Cuts {
    /// Every one.
    All,
    /// Every unit spent by the appends in `appends`, plus `random` others anywhere.
    Window {
        appends: Range<usize>,
        random: usize,
    },
}

/// What to do after the cut.
#[derive(Clone, Copy, PartialEq)]
enum After {
    /// Power on and reopen (a reboot); on odd cut points also `maintain` if due.
    Reboot,
    /// Power on and carry on with the same log object (as after a failed flash
    /// operation): retry the append.
    Retry,
}

/// What a power-cut campaign covered.
#[derive(Debug)]
struct Coverage {
    /// Cut points tried.
    cut_points: usize,
    /// Sector moves whose every unit (erase, carried batch, new record) was cut.
    moves_cut_everywhere: usize,
    /// Reboots that found a move cut short (`OpenReport::unfinished_move`).
    unfinished_moves_seen: usize,
}

/// For each cut point of `cuts`: replay `script` with the power cut there, recover
/// (`after`), and check that every kind's latest record is the last acknowledged one or
/// the one in flight and that its history is intact; then append `extra` more records
/// (so that the log moves on past the damage, through sector moves and erases), reopen
/// and check that nothing was lost.
fn power_cut_campaign<F: CutFlash>(
    fresh: F,
    sector: usize,
    script: &[(u8, Vec<u8>)],
    extra: usize,
    cuts: Cuts,
    after: After,
) -> Coverage {
    let reference = Reference::run(fresh, sector, script);
    let total = *reference.units.last().unwrap();
    let (cuts, window) = match cuts {
        Cuts::All => ((0..=total).collect::<Vec<_>>(), 0..script.len()),
        Cuts::Window { appends, random } => {
            let mut rng = Rng::new(appends.start as u64);
            let units = &reference.units;
            let mut v: Vec<u64> = (units[appends.start]..units[appends.end]).collect();
            v.extend((0..random).map(|_| rng.next_u64() % (total + 1)));
            (v, appends)
        }
    };
    let mut coverage = Coverage {
        cut_points: cuts.len(),
        moves_cut_everywhere: reference.moved[window].iter().filter(|&&m| m).count(),
        unfinished_moves_seen: 0,
    };
    let extra_records: Vec<(u8, Vec<u8>)> = (0..extra)
        .map(|j| ((j % 3) as u8, unique_payload(0xE000 + j as u16, j)))
        .collect();

    for n in cuts {
        let Some(i) = reference.append_at(n) else {
            continue; // no cut: the reference run itself
        };
        let ctx = |what: &str| format!("cut after {n} units (in append {i}), {what}");
        let mut log = reference.cut(script, i, n);
        let (kind, data) = &script[i];
        let acked = match after {
            After::Reboot => {
                let (mut l, report) = reboot(log, sector);
                assert!(
                    report.corrupt <= 1,
                    "{}: {report:?}",
                    ctx("one torn slot at most")
                );
                coverage.unfinished_moves_seen += usize::from(report.unfinished_move);
                if report.unfinished_move {
                    // The full sector before is current: the next append redoes the move.
                    assert_eq!(l.slots_free_in_sector(), 0, "{}", ctx("redo the move"));
                }
                let landed = latest_data(&mut l, *kind).as_ref() == Some(data);
                let acked = &script[..i + usize::from(landed)];
                check_log(&mut l, 4, |k| newest_first(acked.iter(), k), &|| {
                    ctx("rebooted")
                });
                if n % 2 == 1 && l.needs_maintenance() {
                    l.maintain()
                        .unwrap_or_else(|e| panic!("{}: {e:?}", ctx("maintain")));
                    assert!(!l.needs_maintenance(), "{}", ctx("maintained"));
                    let erases = l.flash().erases();
                    l.append(script[0].0, &script[0].1).unwrap(); // moves if full: no erase
                    assert_eq!(
                        l.flash().erases(),
                        erases,
                        "{}",
                        ctx("erase after maintain")
                    );
                    log = l;
                    [acked, &script[..1]].concat()
                } else {
                    log = l;
                    acked.to_vec()
                }
            }
            After::Retry => {
                log.flash_mut().reboot();
                log.append(*kind, data)
                    .unwrap_or_else(|e| panic!("{}: {e:?}", ctx("retry")));
                let acked = &script[..=i];
                check_log(&mut log, 4, |k| newest_first(acked.iter(), k), &|| {
                    ctx("retried")
                });
                acked.to_vec()
            }
        };

        // Keep going: the torn slot is skipped, unfinished moves are redone.
        for (k, d) in &extra_records {
            log.append(*k, d)
                .unwrap_or_else(|e| panic!("{}: {e:?}", ctx("append after recovery")));
        }
        let (mut log, report) = reboot(log, sector);
        assert!(report.corrupt <= 1, "{}: {report:?}", ctx("second reboot"));
        let all_acked = || acked.iter().chain(&extra_records);
        check_log(&mut log, 4, |k| newest_first(all_acked(), k), &|| {
            ctx("after more appends")
        });
    }
    coverage
}

#[test]
fn power_cut_at_every_unit_of_a_scripted_run() {
    // The board's layout (2 sectors), 3 kinds, 200 appends: every cut point.
    let script = script(200, 3);
    let extra = 2 * MIN_SLOTS_PER_SECTOR; // through two more moves (and an erase)
    let flash = Checked::<4>::new(2, SMALL);
    let c = power_cut_campaign(flash, SMALL, &script, extra, Cuts::All, After::Reboot);
    println!("2 sectors: {c:?}");
    assert!(
        c.cut_points > 200 * SLOT_SIZE && c.moves_cut_everywhere >= 10,
        "{c:?}"
    );
    assert!(c.unfinished_moves_seen > 0, "{c:?}");

    // 3 sectors: every cut point of appends 40..80, random ones elsewhere.
    let cuts = Cuts::Window {
        appends: 40..80,
        random: 500,
    };
    let flash = Checked::<4>::new(3, SMALL);
    let c = power_cut_campaign(flash, SMALL, &script, extra, cuts, After::Reboot);
    println!("3 sectors: {c:?}");
    assert!(
        c.moves_cut_everywhere >= 2 && c.unfinished_moves_seen > 0,
        "{c:?}"
    );
}

#[test]
fn a_kind_kept_deep_keeps_its_history_through_sector_moves() {
    // Kind 2 keeps its 10 newest records through every move (the micrometer readings'
    // use); the other kinds the newest one. 30-slot sectors (the batch: at most 24).
    let mut keep = Keep::ONE_EACH;
    keep.0[2] = 10;
    const SECTOR: usize = 30 * SLOT_SIZE;
    let (mut log, _) = RecordLog::open_keeping(SimFlash::new(2, SECTOR), SECTOR, keep).unwrap();
    let mut model: Vec<(u8, Vec<u8>)> = Vec::new();
    let mut moves = 0;
    for i in 0..400u16 {
        let kind = [0, 2, 1, 2, 2][usize::from(i) % 5];
        let data = unique_payload(i, usize::from(i) % 40);
        let sector = log.current_sector();
        log.append(kind, &data).unwrap();
        moves += usize::from(log.current_sector() != sector);
        model.push((kind, data));
        let want = newest_first(model.iter(), 2);
        let got = history(&mut log, 2, 10);
        assert_eq!(got[..], want[..want.len().min(10)], "after append {i}");
    }
    assert!(moves > 20, "{moves} moves");
    // And after a reboot.
    let (mut log, report) = reboot(log, SECTOR);
    assert_eq!(report.corrupt, 0);
    assert_eq!(
        history(&mut log, 2, 10)[..],
        newest_first(model.iter(), 2)[..10]
    );
    // A keep that does not fit the sector is refused.
    let mut big = Keep::ONE_EACH;
    big.0[2] = 30;
    assert!(RecordLog::open_keeping(SimFlash::new(2, SECTOR), SECTOR, big).is_err());
}

#[test]
fn power_cut_with_a_kind_kept_deep() {
    let mut keep = Keep::ONE_EACH;
    keep.0[1] = 6;
    keep.0[2] = 4;
    KEEP.with(|k| k.set(keep));
    const SECTOR: usize = 28 * SLOT_SIZE; // batch 22 + appends
    let script = script(160, 3);
    let flash = Checked::<4>::new(2, SECTOR);
    let c = power_cut_campaign(flash, SECTOR, &script, 40, Cuts::All, After::Reboot);
    println!("kept deep: {c:?}");
    assert!(
        c.moves_cut_everywhere >= 5 && c.unfinished_moves_seen > 0,
        "{c:?}"
    );
}

#[test]
fn power_cut_with_every_user_kind() {
    // Full carried batches (15 records): cuts inside a batch, and erases cut short that
    // leave part of a batch in the sector's second half. From the 18th append on, one
    // in two moves; every cut point of six of them, random ones elsewhere.
    let script = script(30, ERASED_KIND);
    let script: Vec<_> = (0..ERASED_KIND)
        .map(|k| (k, unique_payload(0x100 + u16::from(k), k as usize)))
        .chain(script)
        .collect();
    let cuts = Cuts::Window {
        appends: 16..22,
        random: 300,
    };
    let flash = Checked::<4>::new(2, SMALL);
    let c = power_cut_campaign(flash, SMALL, &script, 4, cuts, After::Reboot);
    println!("15 kinds: {c:?}");
    assert!(
        c.moves_cut_everywhere >= 3 && c.unfinished_moves_seen > 0,
        "{c:?}"
    );
}

#[test]
fn power_cut_with_other_write_sizes() {
    // WRITE_SIZE 1 (the board), 8 (commit = last 8 bytes), 64 (one write per slot);
    // every cut point of 40 appends (2 moves).
    let script = script(40, 3);
    let extra = 2 * MIN_SLOTS_PER_SECTOR;
    let all = || Cuts::All;
    let c = power_cut_campaign(
        Checked::<1>::new(2, SMALL),
        SMALL,
        &script,
        extra,
        all(),
        After::Reboot,
    );
    assert!(c.moves_cut_everywhere >= 2, "{c:?}");
    power_cut_campaign(
        Checked::<8>::new(2, SMALL),
        SMALL,
        &script,
        extra,
        all(),
        After::Reboot,
    );
    power_cut_campaign(
        Checked::<64>::new(3, SMALL),
        SMALL,
        &script,
        extra,
        all(),
        After::Reboot,
    );
}

#[test]
fn failed_writes_without_reboot_leave_the_log_consistent() {
    // A write or erase fails (here: the power goes and comes back) and the firmware
    // carries on with the same log: a retry succeeds and nothing is lost.
    let script = script(60, 3);
    let cuts = Cuts::Window {
        appends: 10..40,
        random: 200,
    };
    let flash = Checked::<4>::new(2, SMALL);
    let c = power_cut_campaign(flash, SMALL, &script, 20, cuts, After::Retry);
    assert!(c.moves_cut_everywhere >= 2, "{c:?}");
}

#[test]
fn power_cut_replay_from_scratch() {
    // The campaigns replay one append from a snapshot; replaying the whole script
    // with the cut armed from the start must leave the very same flash.
    let script = script(120, 3);
    let reference = Reference::run(SimFlash::new(2, SMALL), SMALL, &script);
    let mut rng = Rng::new(42);
    for _ in 0..60 {
        let n = rng.next_u64() % reference.units.last().unwrap();
        let (mut log, _) = open(SimFlash::new(2, SMALL), SMALL);
        log.flash_mut().cut_after_bytes(n);
        let mut i = 0;
        while log.append(script[i].0, &script[i].1).is_ok() {
            i += 1;
        }
        assert_eq!(Some(i), reference.append_at(n), "cut {n}");
        let snapshot = reference.cut(&script, i, n);
        assert!(
            log.flash().contents() == snapshot.flash().contents(),
            "cut {n}"
        );
    }
}

#[test]
fn a_record_counts_only_once_its_commit_marker_is_written() {
    let (mut log, _) = open(SimFlash::new(2, SMALL), SMALL);
    log.append(2, b"old").unwrap();
    // Cut after the slot's first write (60 bytes: header, payload, CRC), as the commit
    // write starts: its first byte is left half-programmed.
    log.flash_mut().cut_after_bytes(60);
    assert!(log.append(2, b"new").is_err());
    let (mut log, report) = reboot(log, SMALL);
    let slot = &log.flash().contents()[SLOT_SIZE..2 * SLOT_SIZE];
    assert_eq!(&slot[8..11], b"new", "body programmed");
    assert_eq!(&slot[60..], [0xF0, 0xFF, 0xFF, 0xFF], "marker not");
    assert_eq!((report.valid, report.corrupt), (1, 1));
    assert_eq!(latest_data(&mut log, 2).as_deref(), Some(&b"old"[..]));
    // The marker cut after 3 of its 4 bytes (the 4th half-programmed): still not valid.
    log.flash_mut().cut_after_bytes(63);
    assert!(log.append(2, b"newer").is_err());
    let (mut log, report) = reboot(log, SMALL);
    assert_eq!((report.valid, report.corrupt), (1, 2));
    assert_eq!(latest_data(&mut log, 2).as_deref(), Some(&b"old"[..]));
}

#[test]
fn two_interrupted_first_appends_then_a_clean_one_survives() {
    // sequential-storage #136: after two interrupted initial stores, a later clean
    // store could vanish after reboot. Every cut point of both interrupted appends.
    for first in 0..SLOT_SIZE as u64 {
        for second in 0..SLOT_SIZE as u64 {
            let mut flash = SimFlash::new(2, SMALL);
            for (cut, data) in [(first, b"interrupted 1"), (second, b"interrupted 2")] {
                let (mut log, _) = open(flash, SMALL);
                log.flash_mut().cut_after_bytes(cut);
                assert!(log.append(0, data).is_err());
                flash = log.into_inner();
                flash.power_on();
            }
            let (mut log, _) = open(flash, SMALL);
            log.append(0, b"clean").unwrap();
            let (mut log, report) = reboot(log, SMALL);
            let ctx = format!("cuts {first}, {second}: {report:?}");
            assert_eq!(
                latest_data(&mut log, 0).as_deref(),
                Some(&b"clean"[..]),
                "{ctx}"
            );
            assert_eq!(report.valid, 1, "{ctx}");
            // Torn slots stay skipped: 30 more appends (two moves) lose nothing.
            for j in 0..30u8 {
                log.append(1, &[j]).unwrap();
            }
            let (mut log, _) = reboot(log, SMALL);
            assert_eq!(
                latest_data(&mut log, 0).as_deref(),
                Some(&b"clean"[..]),
                "{ctx}"
            );
            assert_eq!(latest_data(&mut log, 1), Some(vec![29]), "{ctx}");
        }
    }
}

// --- 3. bit flips ----------------------------------------------------------------------

#[test]
fn bit_flip_in_the_newest_record_is_detected_and_skipped() {
    // Every byte of the slot (header, payload, padding, CRC, commit marker).
    for byte in 0..SLOT_SIZE {
        for mask in [0x01, 0x80] {
            let (mut log, _) = open(SimFlash::new(2, SMALL), SMALL);
            log.append(0, b"v1").unwrap();
            log.append(1, b"other").unwrap();
            log.append(0, b"v2").unwrap(); // slot 2
            let mut flash = log.into_inner();
            flash.corrupt(2 * SLOT_SIZE + byte, mask);
            let (mut log, report) = open(flash, SMALL);
            let ctx = format!("byte {byte} ^ {mask:#x}: {report:?}");
            assert_eq!((report.valid, report.corrupt), (2, 1), "{ctx}");
            assert_eq!(
                latest_data(&mut log, 0).as_deref(),
                Some(&b"v1"[..]),
                "{ctx}"
            );
            assert_eq!(history(&mut log, 0, 10), [b"v1".to_vec()], "{ctx}");
            assert_eq!(
                latest_data(&mut log, 1).as_deref(),
                Some(&b"other"[..]),
                "{ctx}"
            );
            // The bad slot is used for good: the next append goes after it.
            log.append(0, b"v3").unwrap();
            let (mut log, report) = reboot(log, SMALL);
            assert_eq!((report.valid, report.corrupt), (3, 1), "{ctx}");
            assert_eq!(
                latest_data(&mut log, 0).as_deref(),
                Some(&b"v3"[..]),
                "{ctx}"
            );
        }
    }
}

#[test]
fn bit_flip_after_open_and_in_a_carried_copy() {
    let (mut log, _) = open(SimFlash::new(3, SMALL), SMALL);
    log.append(5, b"config A").unwrap(); // slot 0 of sector 0
    for i in 0..MIN_SLOTS_PER_SECTOR as u8 {
        log.append(0, &[i]).unwrap(); // the 17th moves to sector 1, carrying kinds 5 and 0
    }
    assert_eq!(log.current_sector(), 1);
    // The carried copy of kind 5 (slot 0 of sector 1) rots while the log is open.
    log.flash_mut().corrupt(SMALL + 10, 0x04);
    assert_eq!(
        latest_data(&mut log, 5).as_deref(),
        Some(&b"config A"[..]),
        "original"
    );
    assert_eq!(history(&mut log, 5, 5), [b"config A".to_vec()]);
    let (mut log, report) = reboot(log, SMALL);
    assert_eq!(report.corrupt, 1);
    assert_eq!(
        latest_data(&mut log, 5).as_deref(),
        Some(&b"config A"[..]),
        "after reboot"
    );
    // The next move carries the intact original on.
    for i in 0..MIN_SLOTS_PER_SECTOR as u8 {
        log.append(0, &[100 + i]).unwrap();
    }
    let (mut log, _) = reboot(log, SMALL);
    assert_eq!(log.current_sector(), 2);
    assert_eq!(
        latest_data(&mut log, 5).as_deref(),
        Some(&b"config A"[..]),
        "carried on"
    );
}

#[test]
fn a_record_whose_copy_rotted_is_carried_out_of_the_sector_being_erased() {
    // Two sectors: the rotted copy's original lives in the very sector the next move
    // erases; the move holds it in RAM across the erase.
    let (mut log, _) = open(SimFlash::new(2, SMALL), SMALL);
    log.append(5, b"config A").unwrap();
    for i in 0..MIN_SLOTS_PER_SECTOR as u8 {
        log.append(0, &[i]).unwrap();
    }
    assert_eq!(log.current_sector(), 1);
    log.flash_mut().corrupt(SMALL + 10, 0x04);
    for i in 0..MIN_SLOTS_PER_SECTOR as u8 {
        log.append(0, &[100 + i]).unwrap();
    }
    assert_eq!(
        log.current_sector(),
        0,
        "moved into the sector the original was in"
    );
    let (mut log, _) = reboot(log, SMALL);
    assert_eq!(
        latest_data(&mut log, 5).as_deref(),
        Some(&b"config A"[..]),
        "carried through RAM"
    );
}

// --- 4. garbage ------------------------------------------------------------------------

/// A small flash whose every byte is `fill(offset)`.
fn flash_filled(sectors: usize, sector: usize, fill: impl Fn(usize) -> u8) -> SimFlash {
    let mut f = SimFlash::new(sectors, sector);
    for off in 0..sectors * sector {
        f.corrupt(off, 0xFF ^ fill(off)); // erased 0xFF ^ mask = wanted byte
    }
    f
}

#[test]
fn open_never_fails_on_garbage_and_appends_work_after() {
    let mut rng = Rng::new(7);
    let random: Vec<u8> = (0..3 * SMALL).map(|_| rng.next_u64() as u8).collect();
    let cases: [(&str, SimFlash); 5] = [
        ("all zeros", flash_filled(3, SMALL, |_| 0)),
        ("random", flash_filled(3, SMALL, |o| random[o])),
        (
            "half-erased",
            flash_filled(
                3,
                SMALL,
                |o| if o % SMALL < SMALL / 2 { 0xFF } else { 0x5A },
            ),
        ),
        (
            "erased but one byte per sector",
            flash_filled(3, SMALL, |o| if o % SMALL == 777 { 0 } else { 0xFF }),
        ),
        (
            "zeros in sector 2 only",
            flash_filled(3, SMALL, |o| if o >= 2 * SMALL { 0 } else { 0xFF }),
        ),
    ];
    for (name, flash) in cases {
        let (mut log, report) = open(flash, SMALL);
        assert_eq!(report.valid, 0, "{name}");
        assert_eq!(report.last_seq, None, "{name}");
        for k in 0..MAX_KINDS {
            assert_eq!(log.latest(k).unwrap(), None, "{name}");
        }
        let script = script(100, 3);
        for (i, (kind, data)) in script.iter().enumerate() {
            log.append(*kind, data)
                .unwrap_or_else(|e| panic!("{name}: append {i}: {e:?}"));
        }
        let (mut log, report) = reboot(log, SMALL);
        assert!(report.last_seq.is_some(), "{name}: {report:?}");
        check_log(&mut log, 8, |k| newest_first(script.iter(), k), &|| {
            name.into()
        });
    }
    // The board's geometry, all zeros (a flash programmed by a wrong image).
    let mut flash = SimFlash::stm32f407_odometer();
    for off in 0..2 * SECTOR_SIZE {
        flash.corrupt(off, 0xFF);
    }
    let (mut log, report) = RecordLog::open(flash).unwrap();
    assert_eq!(report.corrupt as usize, 2 * SECTOR_SIZE / SLOT_SIZE);
    log.append(3, b"fresh start").unwrap();
    let (mut log, _) = RecordLog::open(log.into_inner()).unwrap();
    assert_eq!(
        latest_data(&mut log, 3).as_deref(),
        Some(&b"fresh start"[..])
    );
}

// --- 5. endurance ----------------------------------------------------------------------

#[test]
fn endurance_100k_appends_on_the_board_geometry() {
    let (mut log, _) = RecordLog::open(SimFlash::stm32f407_odometer()).unwrap();
    let mut data = [0u8; PAYLOAD_MAX];
    let mut moves = 0;
    for i in 0..100_000u32 {
        data[..4].copy_from_slice(&i.to_le_bytes());
        let sector = log.current_sector();
        let seq = log.append(0, &data).unwrap();
        if log.current_sector() != sector {
            moves += 1; // one carried copy took a seq
        }
        assert_eq!(seq, i + moves, "seq of append {i}");
    }
    let counts = log.flash().erase_counts().to_vec();
    println!("erase counts per sector after 100 000 appends: {counts:?}");
    let (min, max) = (*counts.iter().min().unwrap(), *counts.iter().max().unwrap());
    assert!(max <= 100, "{counts:?}");
    assert!(max - min <= 1, "{counts:?}");
    // 2048 records in sector 0, then 2047 new + 1 carried per sector; every move
    // erased (the first too: a sector is not trusted for reading blank).
    assert_eq!(moves, 1 + (100_000 - 2048) / 2047);
    assert_eq!(counts.iter().sum::<u32>(), moves, "{counts:?}");
    let (mut log, report) = RecordLog::open(log.into_inner()).unwrap();
    assert_eq!(report.corrupt, 0);
    assert_eq!(latest_data(&mut log, 0), Some(data.to_vec()));
}

// --- 6. maintenance --------------------------------------------------------------------

#[test]
fn maintain_pre_erases_so_that_the_moving_append_does_not() {
    let (mut log, _) = open(SimFlash::new(2, SMALL), SMALL);
    let mut i = 0u8;
    let mut append = |log: &mut RecordLog<SimFlash>| {
        i += 1;
        log.append(i % 2, &[i]).unwrap();
    };
    // Fill a sector up to the 90 % mark, checking when maintenance is due.
    let fill_to_mark = |log: &mut RecordLog<SimFlash>,
                        append: &mut dyn FnMut(&mut RecordLog<SimFlash>)| loop {
        let used = MIN_SLOTS_PER_SECTOR - log.slots_free_in_sector();
        assert_eq!(
            log.needs_maintenance(),
            used * 10 >= MIN_SLOTS_PER_SECTOR * 9,
            "{used}"
        );
        if log.needs_maintenance() {
            break;
        }
        log.maintain().unwrap(); // not due: does nothing
        append(log);
    };
    // Sector 0 fills. Sector 1 reads blank, but no completed erase of it is on record
    // (a new chip's sector): it is erased all the same.
    fill_to_mark(&mut log, &mut append);
    assert_eq!(log.flash().erase_counts(), &[0, 0], "not before the mark");
    log.maintain().unwrap();
    assert_eq!(log.flash().erase_counts(), &[0, 1]);
    assert!(!log.needs_maintenance());
    log.maintain().unwrap(); // nothing to do
    assert_eq!(log.flash().erase_counts(), &[0, 1]);
    // Fill up and move: the moving append erases nothing.
    while log.slots_free_in_sector() > 0 {
        append(&mut log);
    }
    append(&mut log);
    assert_eq!(
        (log.current_sector(), log.flash().erase_counts()),
        (1, &[0, 1][..])
    );
    // The same in sector 1, whose next sector holds old records.
    fill_to_mark(&mut log, &mut append);
    log.maintain().unwrap();
    assert_eq!(log.flash().erase_counts(), &[1, 1]);
    while log.slots_free_in_sector() > 0 {
        append(&mut log);
    }
    append(&mut log);
    assert_eq!(
        (log.current_sector(), log.flash().erase_counts()),
        (0, &[1, 1][..])
    );

    // A cut during maintain's erase: the half-erased sector is erased again later.
    while !log.needs_maintenance() {
        append(&mut log);
    }
    let before: Vec<_> = (0..2).map(|k| latest_data(&mut log, k)).collect();
    log.flash_mut().cut_after_bytes(0);
    assert!(log.maintain().is_err());
    let (mut log, report) = reboot(log, SMALL);
    // 17-slot sectors: the erase stopped in the middle of slot 8.
    assert_eq!(report.corrupt, 1, "{report:?}");
    assert!(log.needs_maintenance(), "half-erased sector is not blank");
    assert_eq!(
        (0..2).map(|k| latest_data(&mut log, k)).collect::<Vec<_>>(),
        before
    );
    log.maintain().unwrap();
    assert_eq!(log.flash().erase_counts(), &[1, 2]);
}

#[test]
fn an_erase_cut_short_that_reads_blank_was_trusted() {
    // An erase stopped late by a reset: the sector reads all 0xFF, but its cells lack
    // the margin a completed erase verifies, and what is programmed there is lost at
    // the next power cycle (the simulator's model of it).
    let mut flash = SimFlash::new(2, SMALL);
    let mut model: Vec<(u8, Vec<u8>)> = Vec::new();
    let (mut log, _) = open(flash.clone(), SMALL);
    for i in 0..(MIN_SLOTS_PER_SECTOR as u16 + 3) {
        let rec = ((i % 3) as u8, unique_payload(i, i as usize));
        log.append(rec.0, &rec.1).unwrap();
        model.push(rec);
    }
    assert_eq!(log.current_sector(), 1);
    while !log.needs_maintenance() {
        let i = model.len() as u16;
        let rec = ((i % 3) as u8, unique_payload(i, i as usize));
        log.append(rec.0, &rec.1).unwrap();
        model.push(rec);
    }
    // maintain() starts erasing sector 0; a reset stops it at 95 % of its time.
    flash = log.into_inner();
    flash.abort_erase(0, 950);
    let erases = flash.erase_counts().to_vec();
    let (mut log, _) = open(flash, SMALL);
    // Whatever the sector reads, it is erased again before anything goes there.
    log.maintain().unwrap();
    let mut after_move = 0;
    while after_move < 5 {
        let i = model.len() as u16;
        let rec = ((i % 3) as u8, unique_payload(i, i as usize));
        log.append(rec.0, &rec.1).unwrap();
        model.push(rec);
        after_move += usize::from(log.current_sector() == 0);
    }
    let mut flash = log.into_inner();
    assert_eq!(
        flash.marginal_programs(),
        0,
        "nothing programmed on a marginal erase"
    );
    assert_eq!(flash.erase_counts()[0], erases[0] + 1);
    // A power cycle: everything acknowledged is still there.
    flash.power_on();
    let (mut log, report) = open(flash, SMALL);
    assert_eq!(report.corrupt, 0, "{report:?}");
    check_log(&mut log, 4, |k| newest_first(model.iter(), k), &|| {
        "after the power cycle".into()
    });
}
