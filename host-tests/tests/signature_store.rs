//! The docking signature's store (`docking_logic::framelog`, sectors 2–4) on the
//! simulated NOR flash: round trips over sectors of unequal sizes, a power cut at every
//! byte of a scripted run (writes, sector moves, pre-erases), an erase cut late (the
//! sector reads blank), bit flips, garbage; and the signature's own records through the
//! controller (`curve`'s NOK curves, the reference, the summaries `history` walks).
//!
//! Small tests use sectors of 1, 1 and 2 KiB (the board's 16, 16 and 64 KiB scaled
//! down), frames of at most 96 bytes, and keep 1, 1 and 2 frames of kinds 0, 1 and 2:
//! the log moves between sectors every few appends.

use std::fmt::Debug;

use docking_logic::framelog::{frame_size, FrameError, FrameLog, OpenReport, KINDS};
use embedded_storage::nor_flash::{ErrorType, NorFlash, ReadNorFlash};
use hil_sim::flash::{SimFlash, SimFlashError};
use hil_sim::rng::Rng;

/// The simulator with 1 KiB erase units (the log's geometry says which are sectors),
/// checking how the log programs it: whole 4-byte units, no byte programmed twice
/// between erases, a frame's commit (its last 4 bytes) by a write of its own after
/// every other byte of the frame.
#[derive(Clone, Debug)]
struct Small {
    sim: SimFlash,
    programmed: Vec<bool>,
}

const UNIT: usize = 1024;
const SIZES: [u32; 3] = [1024, 1024, 2048];
const MAX: usize = 96;
const KEEP: [u8; KINDS] = [1, 1, 2, 0, 0, 0, 0, 0];

impl Small {
    fn new() -> Self {
        Self {
            sim: SimFlash::new(4, UNIT),
            programmed: vec![false; 4 * UNIT],
        }
    }
}

impl ErrorType for Small {
    type Error = SimFlashError;
}

impl ReadNorFlash for Small {
    const READ_SIZE: usize = 1;
    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.sim.read(offset, bytes)
    }
    fn capacity(&self) -> usize {
        self.sim.capacity()
    }
}

impl NorFlash for Small {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = UNIT;
    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        for s in (from as usize / UNIT)..(to as usize / UNIT) {
            self.sim.erase_sector(s)?;
            self.programmed[s * UNIT..(s + 1) * UNIT].fill(false);
        }
        Ok(())
    }
    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        let (start, end) = (offset as usize, offset as usize + bytes.len());
        assert!(
            start % 4 == 0 && end % 4 == 0,
            "write {start}..{end} not in words"
        );
        assert!(
            !self.programmed[start..end].contains(&true),
            "write {start}..{end} programs bytes a second time"
        );
        self.sim.program(offset, bytes)?;
        self.programmed[start..end].fill(true);
        Ok(())
    }
}

fn open(flash: Small) -> (FrameLog<Small>, OpenReport) {
    FrameLog::open(flash, &SIZES, KEEP, MAX).expect("open fails only on read errors")
}

fn reboot(log: FrameLog<Small>) -> (FrameLog<Small>, OpenReport) {
    let mut f = log.into_inner();
    f.sim.power_on();
    open(f)
}

fn append(
    log: &mut FrameLog<Small>,
    kind: u8,
    data: &[u8],
) -> Result<(), FrameError<SimFlashError>> {
    log.append(kind, data.len(), &mut |at, dst| {
        dst.copy_from_slice(&data[at..at + dst.len()]);
    })
    .map(|_| ())
}

/// The newest `n` payloads of `kind`, newest first.
fn newest(log: &mut FrameLog<Small>, kind: u8, n: usize) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    for i in 0..n {
        let Some(f) = log.newest(kind, i).expect("newest") else {
            break;
        };
        assert_eq!(f.kind, kind);
        let mut b = vec![0u8; f.len as usize];
        log.read(&f, 0, &mut b).expect("read");
        out.push(b);
    }
    out
}

/// A unique payload (its first two bytes are `tag`), 2..=MAX bytes.
fn payload(tag: u16, seed: usize) -> Vec<u8> {
    let len = 2 + seed % (MAX - 1);
    let mut d: Vec<u8> = (0..len).map(|j| (j * 31 + seed) as u8).collect();
    d[..2].copy_from_slice(&tag.to_le_bytes());
    d
}

/// A script: `n` appends over kinds 0..3, and a `maintain` every few.
fn script(n: usize) -> Vec<(u8, Vec<u8>)> {
    (0..n)
        .map(|i| ((i % 3) as u8, payload(i as u16, i * 13 + 5)))
        .collect()
}

/// What the index must hold after the first `done` steps of `s`: per kind, newest first.
fn model(s: &[(u8, Vec<u8>)], done: usize, kind: u8) -> Vec<Vec<u8>> {
    s[..done]
        .iter()
        .rev()
        .filter(|(k, _)| *k == kind)
        .take(KEEP[kind as usize] as usize)
        .map(|(_, d)| d.clone())
        .collect()
}

fn check(log: &mut FrameLog<Small>, s: &[(u8, Vec<u8>)], done: usize, ctx: &str) {
    for kind in 0..3u8 {
        let want = model(s, done, kind);
        let got = newest(log, kind, KEEP[kind as usize] as usize);
        assert_eq!(got, want, "kind {kind} after {done} steps: {ctx}");
    }
}

#[test]
fn frames_round_trip_across_sector_moves_of_unequal_sectors() {
    let (mut log, report) = open(Small::new());
    assert_eq!(report.valid, 0);
    assert_eq!(report.erased_sectors, 3);
    let s = script(200);
    let mut sectors_seen = std::collections::BTreeSet::new();
    for (i, (k, d)) in s.iter().enumerate() {
        append(&mut log, *k, d).unwrap();
        if i % 7 == 0 {
            log.maintain().unwrap();
        }
        sectors_seen.insert(log.position().0);
        check(&mut log, &s, i + 1, "live");
    }
    assert_eq!(sectors_seen.len(), 3, "every sector used");
    let (mut log, report) = reboot(log);
    assert_eq!(report.corrupt, 0);
    assert!(!report.unfinished_move);
    check(&mut log, &s, s.len(), "after reopen");
    // Wear levelling: round robin, so erases differ by at most one per sector unit.
    let counts = log.flash().sim.erase_counts().to_vec();
    assert!(counts.iter().all(|&c| c > 2), "{counts:?}");
}

#[test]
fn a_frame_too_large_or_a_bad_kind_is_refused_and_nothing_is_written() {
    let (mut log, _) = open(Small::new());
    assert_eq!(
        append(&mut log, 7, &[1]),
        Err(FrameError::BadKind),
        "the certificate kind is the log's"
    );
    let big = vec![0u8; 3000];
    assert_eq!(append(&mut log, 0, &big), Err(FrameError::TooLarge));
    assert_eq!(log.position(), (0, 0));
    // A geometry whose batch does not fit its smallest sector is refused.
    assert!(matches!(
        FrameLog::open(Small::new(), &[256, 1024, 2048], KEEP, MAX),
        Err(FrameError::Geometry)
    ));
}

/// Run the script with the power cut after `cut` units (programmed bytes; an erase is
/// one); reboot and check: every kind holds the newest frames of the appends that
/// returned, or those with the one cut short. Then the log goes on: the rest of the
/// script appended after the reboot reads back.
///
/// With `parts`, every frame is written as the signature writes at rest: begun, then
/// one 64-byte piece a call (`FrameLog::resume`); and every fourth is first begun, one
/// piece written and abandoned (its data changed: a torn frame left behind).
fn cut_run(s: &[(u8, Vec<u8>)], cut: u64, parts: bool) -> bool {
    let mut flash = Small::new();
    flash.sim.cut_after_bytes(cut);
    let (mut log, _) = open(flash);
    let mut done = 0;
    let mut hit = false;
    for (i, (k, d)) in s.iter().enumerate() {
        let write = |log: &mut FrameLog<Small>| {
            if parts {
                if i % 4 == 1 {
                    // MAX bytes: more than one piece, so one call leaves it unfinished.
                    log.begin(*k, MAX)?;
                    let whole = log.resume(1, &mut |_, dst| dst.fill(0x5A))?;
                    assert!(whole.is_none());
                    log.abandon();
                }
                append_in_parts(log, *k, d)
            } else {
                append(log, *k, d)
            }
        };
        let r = if i % 5 == 4 {
            log.maintain().and_then(|_| write(&mut log))
        } else {
            write(&mut log)
        };
        match r {
            Ok(()) => done = i + 1,
            Err(FrameError::Flash(SimFlashError::PowerLost)) => {
                hit = true;
                break;
            }
            Err(e) => panic!("step {i}: {e:?}"),
        }
    }
    let (mut log, _) = reboot(log);
    let ctx = format!("cut after {cut} units");
    // Old or new.
    let old_ok =
        (0..3u8).all(|k| newest(&mut log, k, KEEP[k as usize] as usize) == model(s, done, k));
    let new_ok = done < s.len()
        && (0..3u8)
            .all(|k| newest(&mut log, k, KEEP[k as usize] as usize) == model(s, done + 1, k));
    assert!(old_ok || new_ok, "neither the old nor the new state: {ctx}");
    let base = if old_ok { done } else { done + 1 };
    // The log goes on: the rest of the script, then a reopen.
    for (i, (k, d)) in s.iter().enumerate().skip(base) {
        append(&mut log, *k, d).unwrap_or_else(|e| panic!("{ctx}: append {i}: {e:?}"));
    }
    let (mut log, _) = reboot(log);
    check(&mut log, s, s.len(), &format!("{ctx}, then the rest"));
    hit
}

#[test]
fn a_power_cut_at_every_byte_loses_at_most_the_frame_being_written() {
    let s = script(40);
    let mut cut = 0;
    let mut cuts = 0;
    while cut_run(&s, cut, false) {
        cut += 1;
        cuts += 1;
    }
    // The script's whole run: several sector moves (carried batches), pre-erases,
    // thousands of bytes.
    assert!(cuts > 2_000, "{cuts} cut points");
}

/// The same with every frame written in parts, and some abandoned half way (what the
/// signature does at rest, a budget of bytes a turn).
#[test]
fn a_power_cut_at_every_byte_of_frames_written_in_parts_loses_at_most_that_frame() {
    let s = script(40);
    let mut cut = 0;
    while cut_run(&s, cut, true) {
        cut += 1;
    }
    assert!(cut > 2_000, "{cut} cut points");
}

/// Append `data` as the signature does at rest: begun, then a piece a call.
fn append_in_parts(
    log: &mut FrameLog<Small>,
    kind: u8,
    data: &[u8],
) -> Result<(), FrameError<SimFlashError>> {
    log.begin(kind, data.len())?;
    let mut calls = 0;
    loop {
        calls += 1;
        let r = log.resume(1, &mut |at, dst| {
            dst.copy_from_slice(&data[at..at + dst.len()]);
        })?;
        if r.is_some() {
            // One 64-byte piece a call: header, payload and CRC in ⌈size / 64⌉ calls.
            assert_eq!(calls, (frame_size(data.len()) - 4).div_ceil(64));
            assert_eq!(log.writing(), None);
            return Ok(());
        }
        assert_eq!(log.writing(), Some(kind), "in parts");
    }
}

#[test]
fn nothing_else_is_appended_or_erased_while_a_frame_is_written_in_parts() {
    let (mut log, _) = open(Small::new());
    // Fill the first sector to its maintenance mark.
    let mut i = 0;
    while !log.needs_maintenance() {
        append(&mut log, (i % 3) as u8, &payload(i as u16, i)).unwrap();
        i += 1;
    }
    let data = payload(900, 3);
    log.begin(1, data.len()).unwrap();
    assert!(
        !log.needs_maintenance(),
        "no pre-erase under a frame in parts"
    );
    assert_eq!(append(&mut log, 0, b"other"), Err(FrameError::Busy));
    assert_eq!(log.begin(0, 4), Err(FrameError::Busy));
    while log
        .resume(1, &mut |at, dst| {
            dst.copy_from_slice(&data[at..at + dst.len()])
        })
        .unwrap()
        .is_none()
    {}
    assert_eq!(newest(&mut log, 1, 1), vec![data.clone()]);
    assert!(log.needs_maintenance(), "then the pre-erase");
    // An abandoned frame is a torn one: skipped after a reboot, the older one read.
    log.begin(1, MAX).unwrap();
    assert_eq!(log.resume(1, &mut |_, dst| dst.fill(1)), Ok(None));
    log.abandon();
    append(&mut log, 0, b"after").unwrap();
    let (mut log, report) = reboot(log);
    assert_eq!(report.corrupt, 1, "the abandoned frame");
    assert_eq!(newest(&mut log, 1, 1), vec![data]);
    assert_eq!(newest(&mut log, 0, 1), vec![b"after".to_vec()]);
}

#[test]
fn an_erase_cut_late_that_reads_blank_is_erased_again_before_use() {
    let s = script(60);
    let (mut log, _) = open(Small::new());
    // Run until a pre-erase has certified the next sector.
    let mut i = 0;
    while i < s.len() {
        append(&mut log, s[i].0, &s[i].1).unwrap();
        i += 1;
        if log.needs_maintenance() {
            break;
        }
    }
    let (cur, _) = log.position();
    let next = ((cur + 1) % 3) as usize;
    // The erase of the next sector is cut at 90 %: it reads blank, but is marginal.
    let first_unit = SIZES[..next].iter().sum::<u32>() as usize / UNIT;
    let units = SIZES[next] as usize / UNIT;
    let mut f = log.into_inner();
    for u in first_unit..first_unit + units {
        f.sim.abort_erase(u, 900);
    }
    f.sim.power_on();
    let (mut log, _) = open(f);
    let erases_before: u32 = log.flash().sim.erase_counts().iter().sum();
    for (k, d) in &s[i..] {
        append(&mut log, *k, d).unwrap();
    }
    let erases_after: u32 = log.flash().sim.erase_counts().iter().sum();
    assert!(
        erases_after > erases_before,
        "the marginal sector was erased again"
    );
    assert_eq!(
        log.flash().sim.marginal_programs(),
        0,
        "nothing programmed into it"
    );
    let (mut log, _) = reboot(log);
    check(&mut log, &s, s.len(), "after the marginal sector");
}

#[test]
fn a_flipped_bit_is_skipped_and_an_older_frame_read() {
    let s = script(9);
    let (mut log, _) = open(Small::new());
    for (k, d) in &s {
        append(&mut log, *k, d).unwrap();
    }
    // Flip a payload bit of the newest kind-2 frame.
    let f = log.newest(2, 0).unwrap().unwrap();
    let mut flash = log.into_inner();
    flash.sim.corrupt(f.offset as usize + 20, 0x04);
    let (mut log, report) = open(flash);
    assert_eq!(report.corrupt, 1);
    let got = newest(&mut log, 2, 2);
    // The newest is gone; the ones before it are read instead.
    let older: Vec<Vec<u8>> = s
        .iter()
        .rev()
        .filter(|(k, _)| *k == 2)
        .skip(1)
        .take(2)
        .map(|(_, d)| d.clone())
        .collect();
    assert_eq!(got, older);
}

#[test]
fn garbage_zeros_and_an_old_image_never_stop_open_and_the_log_goes_on() {
    let mut rng = Rng::new(34);
    for fill in 0..3 {
        let mut flash = Small::new();
        let bytes: Vec<u8> = (0..4 * UNIT)
            .map(|i| match fill {
                0 => 0,
                1 => (rng.next_u64() & 0xFF) as u8,
                // Code: what layouts A and B left in sectors 2-4.
                _ => include_bytes!("signature_store.rs")[i % 1000],
            })
            .collect();
        flash.sim.program(0, &bytes).unwrap();
        flash.programmed.fill(true);
        let (mut log, _) = open(flash);
        for (i, (k, d)) in script(12).iter().enumerate() {
            // Sectors full of garbage are erased as the log reaches them.
            log.flash_mut().programmed.fill(false);
            append(&mut log, *k, d).unwrap_or_else(|e| panic!("fill {fill} step {i}: {e:?}"));
        }
        let (mut log, _) = reboot(log);
        check(&mut log, &script(12), 12, &format!("fill {fill}"));
    }
}

#[test]
fn frame_sizes_are_the_drawing() {
    assert_eq!(frame_size(0), 24);
    assert_eq!(frame_size(1), 28);
    assert_eq!(frame_size(68), 92);
    assert_eq!(frame_size(1348), 1372);
}
