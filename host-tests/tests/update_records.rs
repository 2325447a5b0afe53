//! Issue 21: an image rolled back to reads the records a newer image wrote. A record of
//! a kind this image does not know (what a newer image may add) is skipped at boot —
//! no fault, the counters restored as they were — and carried through the log's sector
//! moves, so that the newer image finds it again after the next update.

use docking_logic::odometer::{self, open_log};
use docking_logic::sequencer::State;
use docking_logic::update::Version;
use hil_sim::flash::{SharedFlash, SimFlash};
use hil_sim::rig::{Rig, RigOptions, BOOT_TICKS};
use host_tests::{run_cycles, run_until};

/// A kind no record of this image uses (odometer::kind ends at 12, the image records of
/// issue 21; 14 is the tests' filler, 15 the log's own).
const NEWER_KIND: u8 = 13;
/// Filler records of another unknown kind, to bring the log to its sector move.
const FILLER_KIND: u8 = 14;

fn boot(flash: &SharedFlash) -> Rig {
    let mut r = Rig::with_flash(RigOptions::new(80), flash.clone());
    for _ in 0..BOOT_TICKS {
        r.tick();
    }
    r
}

/// Version 0.1.`patch`.
fn v(patch: u16) -> Version {
    Version {
        major: 0,
        minor: 1,
        patch,
        build: 0,
    }
}

/// The newest image record's bytes (its first is its event: logic/src/links/update.rs,
/// `ImageRecord`), `None` without one.
fn image_record(r: &mut Rig) -> Option<Vec<u8>> {
    let mut buf = [0u8; 64];
    let n = r.ctrl.load_record(odometer::kind::IMAGE, &mut buf)?;
    Some(buf[..n].to_vec())
}

fn counters(r: &Rig) -> (u32, u32) {
    (
        r.ctrl.odometer().lifetime().cycles,
        r.ctrl.odometer().cone().cycles,
    )
}

#[test]
fn a_record_of_a_kind_this_image_does_not_know_is_skipped_at_boot_and_kept_through_a_sector_move() {
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    let mut r = boot(&flash);
    run_cycles(&mut r, 3);
    let before = counters(&r);
    drop(r);

    // The newer image wrote a record of a kind this one does not know.
    let newer: Vec<u8> = (0..40u8).map(|i| i ^ 0xA5).collect();
    {
        let (mut log, _) = open_log(flash.clone()).unwrap();
        log.append(NEWER_KIND, &newer).unwrap();
    }

    // Rolled back to this image: it boots, skips the record, keeps its counters.
    let mut r = boot(&flash);
    assert_eq!(r.ctrl.state(), State::Idle, "boots to idle, no fault");
    assert_eq!(counters(&r), before, "counters restored as they were");
    run_cycles(&mut r, 2);
    assert_eq!(counters(&r), (before.0 + 2, before.1 + 2));
    let after = counters(&r);
    drop(r);

    // Fill the log up to its maintenance mark with more unknown records; this image's
    // next idle moment moves the log to the next sector.
    {
        let (mut log, _) = open_log(flash.clone()).unwrap();
        while !log.needs_maintenance() {
            log.append(FILLER_KIND, &[0x3C; 16]).unwrap();
        }
    }
    let erases_before: u32 = flash.with(|f| f.erase_counts().iter().sum());
    let mut r = boot(&flash);
    assert!(
        run_until(&mut r, 20_000, |r| {
            r.flash.with(|f| f.erase_counts().iter().sum::<u32>()) > erases_before
                && !r.ctrl.persist_pending()
        }),
        "the log never moved"
    );
    // Settle after the move.
    for _ in 0..200 {
        r.tick();
    }
    assert_eq!(counters(&r), after);
    drop(r);

    // After the move the newer image's record is still the newest of its kind, and
    // this image's counters reboot as they were.
    let (mut log, report) = open_log(flash.clone()).unwrap();
    assert_eq!(report.corrupt, 0);
    let rec = log
        .latest(NEWER_KIND)
        .unwrap()
        .expect("carried through the move");
    assert_eq!(rec.data(), &newer[..]);
    assert!(log.latest(odometer::kind::STATE).unwrap().is_some());
    drop(log);
    let r = boot(&flash);
    assert_eq!(counters(&r), after);
}

/// Issue 21's trial boot: at boot a trial image reports the image it replaced but
/// writes no record; only its confirmation (after the self-test, the load cell's live
/// sample included) records CONFIRMED, which the next boots read back. A trial that
/// never confirms leaves no record claiming it did.
#[test]
fn a_trial_writes_no_image_record_at_boot_and_its_confirmation_writes_confirmed() {
    use docking_logic::update::{at_boot, confirmed, BootFacts};
    use update_layout::state::Boot;
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    let mut r = boot(&flash);
    let trial = BootFacts {
        boot: Boot::Trial,
        running: Some(v(1)),
        page1: Some(v(0)),
        test_key: true,
    };
    let report = at_boot(&mut r.ctrl, trial);
    assert_eq!(
        report.previous,
        Some(v(0)),
        "on trial: the image it replaced"
    );
    assert_eq!(
        image_record(&mut r),
        None,
        "nothing recorded before the confirmation"
    );

    confirmed(&mut r.ctrl, &report);
    assert_eq!(
        image_record(&mut r).map(|rec| rec[0]),
        Some(docking_logic::update::event::CONFIRMED)
    );
    drop(r);

    // The next boot (STATE says BOOT) reads the confirmation back.
    let mut r = boot(&flash);
    let later = at_boot(
        &mut r.ctrl,
        BootFacts {
            boot: Boot::Confirmed,
            page1: None,
            ..trial
        },
    );
    assert_eq!(later.previous, Some(v(0)));
    assert!(!later.rolled_back);
}

/// A power cut between the trial's confirmation (STATE says BOOT) and its CONFIRMED
/// record: the newest record is still the old image's MARKED one, which names this image.
/// The next boot, a confirmed one, writes the record the cut lost, naming the image
/// this one replaced; the boot after it writes nothing more. (Before, the record was
/// lost and `previous` stayed unknown.) A MARKED record that names another image is
/// left alone.
#[test]
fn a_power_cut_between_the_confirmation_and_its_record_is_recorded_at_the_next_boot() {
    use docking_logic::update::{at_boot, event, marked_record, BootFacts};
    use update_layout::state::Boot;
    // 0.1.1's confirmed boots, swapped in over 0.1.0.
    let facts = BootFacts {
        boot: Boot::Confirmed,
        running: Some(v(1)),
        page1: Some(v(0)),
        test_key: true,
    };
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    // 0.1.0 marks 0.1.1 for the swap.
    let mut r = boot(&flash);
    let old = at_boot(
        &mut r.ctrl,
        BootFacts {
            running: Some(v(0)),
            page1: None,
            ..facts
        },
    );
    let marked = marked_record(&old, Some(v(1)));
    r.ctrl
        .store_record(odometer::kind::IMAGE, marked.bytes())
        .unwrap();
    drop(r);

    // A confirmed boot of another image (0.1.2) leaves 0.1.1's MARKED record alone.
    let mut r = boot(&flash);
    let other = at_boot(
        &mut r.ctrl,
        BootFacts {
            running: Some(v(2)),
            ..facts
        },
    );
    assert_eq!(other.previous, None);
    assert_eq!(image_record(&mut r).unwrap()[0], event::MARKED);
    drop(r);

    // 0.1.1 confirmed itself; the power went before its record. The next boot:
    let mut r = boot(&flash);
    let report = at_boot(&mut r.ctrl, facts);
    assert_eq!(report.previous, Some(v(0)), "the image it replaced");
    assert!(!report.rolled_back);
    let rec = image_record(&mut r).unwrap();
    assert_eq!(rec[0], event::CONFIRMED, "the record the cut lost, written");
    drop(r);

    // And the boot after reads it back, writing nothing.
    let seq = |f: &SharedFlash| {
        let (mut log, _) = open_log(f.clone()).unwrap();
        log.latest(odometer::kind::IMAGE).unwrap().map(|r| r.seq)
    };
    let written = seq(&flash);
    let mut r = boot(&flash);
    let again = at_boot(&mut r.ctrl, facts);
    assert_eq!(again.previous, Some(v(0)));
    assert_eq!(image_record(&mut r).unwrap(), rec);
    drop(r);
    assert_eq!(seq(&flash), written, "no record more");
}

/// Issue 31, fix 3: the running image on trial says so, and what to do, in `version`
/// (text and JSON) and Modbus identification (object 0x84: `host-tests/tests/modbus.rs`
/// reads `no`); its confirmation clears it. And `update` is refused while on trial,
/// before anything is erased: in layout C, DFU holds the image a rollback copies back.
#[test]
fn an_image_on_trial_says_so_in_version_and_refuses_an_update_until_it_confirms() {
    use docking_logic::controller::MaintError;
    use docking_logic::update::{at_boot, confirmed, BootFacts, Trial};
    use update_layout::state::Boot;
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    let mut r = boot(&flash);
    let report = at_boot(
        &mut r.ctrl,
        BootFacts {
            boot: Boot::Trial,
            running: Some(v(1)),
            page1: Some(v(0)),
            test_key: true,
        },
    );
    assert_eq!(report.trial, Trial::Waiting);
    r.ctrl.set_images(report);
    r.console_enabled = true;
    let text = r.command("version", 10);
    assert!(text.contains(" trial=yes"), "{text}");
    assert!(text.contains("a reset before that rolls it back"), "{text}");
    let json = r.command("version --json", 10);
    assert!(json.contains("\"trial\":\"yes\""), "{json}");
    assert!(json.contains("\"trial_advice\":\"on trial:"), "{json}");
    assert_eq!(r.ctrl.begin_update(), Err(MaintError::OnTrial));
    assert!(!r.ctrl.updating());

    confirmed(&mut r.ctrl, &report);
    assert_eq!(r.ctrl.images().trial, Trial::No);
    let text = r.command("version", 10);
    assert!(text.contains(" trial=no"), "{text}");
    let json = r.command("version --json", 10);
    assert!(json.contains("\"trial_advice\":null"), "{json}");

    // A confirmation that failed on its last attempt: `failed`, and what it means.
    r.ctrl.set_images(docking_logic::update::ImageReport {
        trial: Trial::Failed,
        ..report
    });
    let text = r.command("version", 10);
    assert!(text.contains(" trial=failed"), "{text}");
    assert!(text.contains("the next reset rolls it back"), "{text}");
}

/// `update` typed while a Modbus reply to a polling PLC was on the line was refused
/// ("the flash is written only at rest"): begin_update writes nothing, and the update's
/// flash jobs wait for the line themselves. The flash writers that write at once still
/// wait for it.
#[test]
fn an_update_was_refused_while_a_modbus_reply_was_on_the_line() {
    use docking_logic::controller::MaintError;
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    let mut r = boot(&flash);
    r.ctrl.set_bus_busy(true);
    assert!(
        !r.ctrl.at_rest(),
        "a reply on the line holds the flash back"
    );
    assert_eq!(r.ctrl.begin_update(), Ok(()));
    assert!(r.ctrl.updating());
    r.ctrl.end_update();
    assert_eq!(
        r.ctrl.store_record(0x7E, b"x"),
        Err(MaintError::NotAtRest),
        "a record written at once still waits for the line"
    );
}
