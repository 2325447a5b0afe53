//! Power-cut proof of the wear odometer, through the real controller in the closed loop.
//!
//! Over more than 1,000 docking cycles on the board's flash geometry (2 × 128 KiB, aged
//! so that a sector move falls inside the run), the power is cut:
//! * at **every byte offset** of the writes of a window of cycles — the cycle whose
//!   write moves the log to the next sector (erase + carried records + new record) and
//!   a few ordinary ones — each offset replayed from the same flash snapshot;
//! * at random offsets in half of the other cycles.
//!
//! After every cut the controller reboots on the same flash: its counters must equal
//! the last committed cycle or the cycle in flight — never older, never garbage — and
//! never decrease; and it always boots.

use docking_logic::sequencer::{Request, State};
use hil_sim::flash::{SharedFlash, SimFlash};
use hil_sim::rig::{Rig, RigOptions};
use hil_sim::rng::Rng;

const FILLER_KIND: u8 = 14;

fn opts() -> RigOptions {
    RigOptions::new(80)
}

fn boot(flash: &SharedFlash) -> Rig {
    Rig::with_flash(opts(), flash.clone())
}

fn lifetime_cycles(rig: &Rig) -> u32 {
    rig.ctrl.odometer().lifetime().cycles
}

/// Run one docking cycle to its committed record, or until the power is lost.
/// Returns `true` if the power was lost.
fn run_cycle(rig: &mut Rig) -> bool {
    let start = lifetime_cycles(rig);
    for _ in 0..20_000 {
        rig.tick();
        if rig.flash.with(|f| f.power_lost()) {
            return true;
        }
        let done = lifetime_cycles(rig) > start && !rig.ctrl.persist_pending();
        match rig.ctrl.state() {
            State::Idle if done => return false,
            State::Idle => rig.ctrl.request(Request::StartCycle),
            State::Faulted { fault } => panic!("unexpected fault {fault:?}"),
            _ => {}
        }
    }
    panic!("cycle did not finish");
}

/// Reboot after a cut and check the restored counters against what was committed.
fn reboot_and_check(
    flash: &SharedFlash,
    committed: u32,
    in_flight: bool,
    floor: &mut u32,
) -> (Rig, u32) {
    flash.with(|f| f.power_on());
    let rig = boot(flash);
    let got = lifetime_cycles(&rig);
    let hi = committed + in_flight as u32;
    assert!(
        got >= committed && got <= hi,
        "restored {got} cycles, committed {committed} (in flight: {in_flight})"
    );
    assert!(got >= *floor, "counters went backwards: {got} < {floor}");
    assert_eq!(
        rig.ctrl.odometer().cone().cycles,
        got,
        "per-cone counter matches lifetime on one cone"
    );
    *floor = got;
    (rig, got)
}

#[test]
fn power_cut_at_every_byte_of_a_window_and_randomly_elsewhere_loses_nothing_committed() {
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    // Age the log: leave ~180 free slots in the first sector so that the move to the
    // second sector happens around cycle 180.
    {
        let (mut log, _) = docking_logic::odometer::open_log(flash.clone()).unwrap();
        while log.slots_free_in_sector() > 180 {
            log.append(FILLER_KIND, &[0xA5; 40]).unwrap();
        }
    }
    let mut rig = boot(&flash);
    let mut committed = lifetime_cycles(&rig);
    assert_eq!(committed, 0);
    let mut floor = 0u32;
    let mut rng = Rng::new(2026);
    let mut exhaustive_windows = 0;
    let mut ordinary_windows = 0;
    let mut cuts = 0u32;
    let mut moves_covered = 0;

    while committed < 1_000 {
        let free = rig
            .ctrl
            .log_mut()
            .map(|l| l.slots_free_in_sector())
            .unwrap();
        let moving = free == 0; // this cycle's record goes to the next sector
        let ordinary = !moving && ordinary_windows < 3 && committed % 97 == 5;
        if moving || ordinary {
            // Every byte offset of this cycle's writes, each from the same snapshot.
            let snapshot = flash.with(|f| f.clone());
            let mut k = 0u64;
            loop {
                flash.with(|f| *f = snapshot.clone());
                let mut trial = boot(&flash);
                assert_eq!(lifetime_cycles(&trial), committed);
                flash.with(|f| f.cut_after_bytes(k));
                let lost = run_cycle(&mut trial);
                drop(trial);
                if !lost {
                    // The whole write fit in k units: every offset has been cut.
                    flash.with(|f| f.power_on());
                    break;
                }
                cuts += 1;
                let (_, got) = reboot_and_check(&flash, committed, true, &mut floor);
                // After a cut, the same flash keeps working: the next cycle commits.
                let mut after = boot(&flash);
                assert!(!run_cycle(&mut after));
                assert_eq!(lifetime_cycles(&after), got + 1);
                floor = committed; // the replay restarts from the snapshot
                k += 1;
            }
            assert!(
                k >= 64,
                "a record write is at least one 64-byte slot, cut {k} times"
            );
            if moving {
                moves_covered += 1;
                assert!(k > 64 * 2, "a sector move carries records: {k} units");
            } else {
                ordinary_windows += 1;
            }
            exhaustive_windows += 1;
            // Now the real run goes on from the snapshot, without a cut.
            flash.with(|f| *f = snapshot);
            rig = boot(&flash);
            assert!(!run_cycle(&mut rig));
            committed += 1;
            floor = committed;
            continue;
        }
        if rng.uniform() < 0.5 {
            let k = (rng.uniform() * 70.0) as u64;
            flash.with(|f| f.cut_after_bytes(k));
            let lost = run_cycle(&mut rig);
            if lost {
                cuts += 1;
                let (r, got) = reboot_and_check(&flash, committed, true, &mut floor);
                rig = r;
                committed = got;
            } else {
                flash.with(|f| f.power_on()); // disarm
                committed += 1;
            }
        } else {
            assert!(!run_cycle(&mut rig));
            committed += 1;
            if committed % 50 == 0 {
                let (r, _) = reboot_and_check(&flash, committed, false, &mut floor);
                rig = r;
            }
        }
    }
    assert!(moves_covered >= 1, "the window must include a sector move");
    assert_eq!(exhaustive_windows, moves_covered + ordinary_windows);
    assert!(cuts > 300, "{cuts} cuts");
    let (_, got) = reboot_and_check(&flash, committed, false, &mut floor);
    assert_eq!(got, committed, "zero committed cycles lost");
    println!(
        "{committed} cycles, {cuts} power cuts, {moves_covered} sector move(s) cut at every byte"
    );
}
