//! Issue 32 on the host rig: what happens **between** the steps — a request accepted and
//! the step that runs it, a mode granted and the step after it, samples queued behind a
//! long job. Each test is named for the defect it pins and failed on 7c11783. The
//! invariants they pin are written once, in docs/board.md ("What holds between the
//! steps"); `interleavings.rs` checks them over random sequences.
//!
//! The board halves (the same defects on the release image, at µs instants the rig
//! cannot place) are in `vboard/tests/between_steps.rs`.

use docking_logic::controller::Source;
use docking_logic::odometer::kind::AUDIT;
use docking_logic::sequencer::{FaultKind, Request, State};
use hil_sim::rig::{Rig, RigOptions};
use host_tests::{reach, run_until};

fn rig(rate_sps: u32) -> Rig {
    Rig::booted(RigOptions::new(rate_sps))
}

fn faulted(r: &Rig) -> Option<FaultKind> {
    match r.ctrl.state() {
        State::Faulted { fault } => Some(fault),
        _ => None,
    }
}

/// Neither motor driven for `ticks` ticks, and the machine still latched.
fn stays_latched(r: &mut Rig, ticks: usize, what: &str) {
    for i in 0..ticks {
        r.tick();
        assert!(
            !r.axis.enabled() && !r.lock.driven(),
            "{what}: driven {i} ticks after the E-STOP pulse ({:?})",
            r.ctrl.state()
        );
    }
    assert_eq!(faulted(r), Some(FaultKind::EmergencyStop), "{what}");
}

/// Defect (issue 32, item 1): a clear accepted while faulted (console or Modbus coil 2),
/// then an E-STOP pulse before the step that runs it: the step consumed the pulse's
/// edges without a fault (the state was already `Faulted{EmergencyStop}`; from
/// `Faulted{Stopped}` the sequencer dropped the fault it detected while faulted) and ran
/// the clear in the same step — the machine recovered, driving the lock or the axis
/// after a 50 µs or 5 ms pulse at 80 SPS, a 50 ms press at 10 SPS. An E-STOP edge after
/// a clear was accepted latches, whatever the step does with the clear; a clear issued
/// after the edge recovers.
#[test]
fn an_estop_pulse_after_an_accepted_clear_was_swallowed_and_the_machine_moved() {
    for (rate, pulses_us) in [(80, [50, 5_000]), (10, [50, 50_000])] {
        for open_us in pulses_us {
            for from in [FaultKind::EmergencyStop, FaultKind::Stopped] {
                let what = format!("{rate} SPS, {open_us} µs pulse, from {}", from.name());
                let mut r = rig(rate);
                match from {
                    FaultKind::EmergencyStop => r.estop_pulse(300),
                    _ => r.ctrl.command(Request::Stop).unwrap(),
                }
                r.tick();
                r.tick();
                assert_eq!(faulted(&r), Some(from), "{what}");
                // The clear is accepted (the input reads closed)…
                r.ctrl.command(Request::ClearFault).unwrap();
                // …and the pulse comes before the step that runs it.
                r.estop_pulse(open_us);
                stays_latched(&mut r, 3 * rate as usize, &what);
                // A clear issued after the edge recovers.
                r.ctrl.command(Request::ClearFault).unwrap();
                assert!(
                    run_until(&mut r, 6_000, |r| r.ctrl.state() == State::Idle),
                    "{what}: {:?}",
                    r.ctrl.state()
                );
            }
        }
    }
}

/// Defect (issue 32, item 4): `write_queued_records` took a record off the queue before
/// writing it and dropped it when the write failed: an audit record queued while a
/// Modbus reply held the flash, then one failed rest — gone, no retry, no storage fault,
/// `records_dropped` still 0. A queued record leaves the queue only when it is written,
/// or counted as dropped.
#[test]
fn a_queued_record_was_lost_after_one_failed_write() {
    let mut r = rig(80);
    let audits = |r: &mut Rig| r.ctrl.records(AUDIT, 100, |_| {});
    let before = audits(&mut r);
    // A reply on the Modbus line: the audit record waits for the rest.
    r.ctrl.set_bus_busy(true);
    assert!(r.ctrl.write_or_queue_record(AUDIT, &[7; 24]));
    assert_eq!(r.ctrl.records_queued(), 1);
    r.ctrl.set_bus_busy(false);
    // One rest with a failing flash.
    r.flash.with(|f| f.write_protect(true));
    r.tick();
    assert_eq!(audits(&mut r), before);
    assert_eq!(
        (r.ctrl.records_queued(), r.ctrl.records_dropped()),
        (1, 0),
        "the record is still queued, not lost"
    );
    assert!(r.ctrl.storage_errors() >= 1, "the failure is counted");
    // The flash works again: written at the next rest, once.
    r.flash.with(|f| f.write_protect(false));
    r.tick();
    r.tick();
    assert_eq!(r.ctrl.records_queued(), 0);
    assert_eq!(audits(&mut r), before + 1);
    assert_eq!(r.ctrl.records_dropped(), 0);
}

/// A flash that keeps failing: the queued record is tried once per rest, three times,
/// then the `storage` fault latches with the record still queued; the clear tries
/// again and writes it.
#[test]
fn a_queued_record_that_keeps_failing_is_a_storage_fault_and_a_clear_writes_it() {
    let mut r = rig(80);
    let audits = |r: &mut Rig| r.ctrl.records(AUDIT, 100, |_| {});
    let before = audits(&mut r);
    r.ctrl.set_bus_busy(true);
    assert!(r.ctrl.write_or_queue_record(AUDIT, &[9; 24]));
    r.ctrl.set_bus_busy(false);
    r.flash.with(|f| f.write_protect(true));
    let calls0 = r.flash.with(|f| f.program_calls());
    assert!(run_until(&mut r, 200, |r| faulted(r).is_some()));
    assert_eq!(faulted(&r), Some(FaultKind::Storage));
    let tries = r.flash.with(|f| f.program_calls()) - calls0;
    assert!(tries <= 3, "{tries} program calls before the storage fault");
    for _ in 0..200 {
        r.tick();
    }
    assert_eq!(
        r.flash.with(|f| f.program_calls()) - calls0,
        tries,
        "no more tries"
    );
    assert_eq!((r.ctrl.records_queued(), r.ctrl.records_dropped()), (1, 0));
    r.flash.with(|f| f.write_protect(false));
    r.ctrl.command(Request::ClearFault).unwrap();
    assert!(run_until(&mut r, 6_000, |r| r.ctrl.state() == State::Idle
        && r.ctrl.records_queued() == 0));
    assert_eq!(audits(&mut r), before + 1);
}

/// Defect (issue 32, item 5): an E-STOP during the pre-alignment, then a clear, counted
/// a docking cycle (the return after the recovery took `ends_cycle` from "a cycle is in
/// progress"): cone and lifetime cycles 0 → 1 with the rod 15 mm short of the cone. Only
/// a cycle that reached the cone counts; the same for a stop in the release.
#[test]
fn an_estop_in_pre_alignment_then_a_clear_counted_a_docking_cycle() {
    let engage = |r: &Rig| r.ctrl.config().machine.engage_um as f64;
    type Before = fn(&Rig, f64) -> bool;
    let cases: [(&str, Before); 2] = [
        ("pre-alignment, 5 mm", |r, _| {
            matches!(r.ctrl.state(), State::PreAlign { .. }) && r.axis.pos_um() >= 5_000.0
        }),
        ("the release", |r, _| {
            matches!(r.ctrl.state(), State::Releasing { .. })
        }),
    ];
    for (what, at) in cases {
        let mut r = rig(80);
        r.ctrl.command(Request::Dock).unwrap();
        let e = engage(&r);
        reach(&mut r, 6_000, |r| at(r, e));
        r.estop_pulse(300);
        r.tick();
        assert_eq!(faulted(&r), Some(FaultKind::EmergencyStop), "{what}");
        assert!(r.axis.pos_um() <= e + 10.0, "{what}: not in the cone");
        r.tick();
        r.ctrl.command(Request::ClearFault).unwrap();
        assert!(run_until(&mut r, 6_000, |r| r.ctrl.state() == State::Idle));
        let o = r.ctrl.odometer();
        assert_eq!(
            (
                o.cone().cycles,
                o.lifetime().cycles,
                r.ctrl.status().cycles_completed
            ),
            (0, 0, 0),
            "{what}: a cycle that never reached the cone was counted"
        );
        // A docking that does reach it counts, once.
        r.ctrl.command(Request::StartCycle).unwrap();
        assert!(run_until(&mut r, 8_000, |r| r
            .ctrl
            .odometer()
            .lifetime()
            .cycles
            == 1
            && r.ctrl.state() == State::Idle));
    }
}

/// An E-STOP in the insertion, then a clear: the rod was in the cone, so the recovery's
/// return counts the cycle (an insertion and an extraction, as an undock there does).
#[test]
fn an_estop_in_the_insertion_then_a_clear_counts_the_cycle() {
    let mut r = rig(80);
    r.ctrl.command(Request::Dock).unwrap();
    let engage = r.ctrl.config().machine.engage_um as f64;
    reach(&mut r, 8_000, |r| {
        matches!(r.ctrl.state(), State::Inserting { .. }) && r.axis.pos_um() > engage + 5_000.0
    });
    r.estop_pulse(300);
    r.tick();
    r.tick();
    r.ctrl.command(Request::ClearFault).unwrap();
    assert!(run_until(&mut r, 8_000, |r| r.ctrl.state() == State::Idle));
    assert_eq!(r.ctrl.odometer().lifetime().cycles, 1);
}

/// What the board's control task does when it runs after a job that held the
/// controller for `samples` sample periods (`src/board.rs`, `control`): the samples the
/// safety kernel read meanwhile are queued, the PLC's inputs are read **once**, and the
/// step runs once per queued sample, back to back.
fn control_run_after_a_long_job(r: &mut Rig, samples: usize, dock_asserted: bool) {
    let mut queued = Vec::new();
    for _ in 0..samples {
        let t = r.hx.next_conversion_ns();
        r.clock.advance_to_ns(t);
        if let Some(ev) = r.kernel.on_ready(t / 1_000, &mut r.stop) {
            queued.push(ev);
        }
    }
    assert_eq!(queued.len(), samples, "the kernel read every sample");
    let now_us = r.clock.now_ns() / 1_000 + 300;
    r.ctrl
        .set_plc(dock_asserted, false, r.estop_edges.snapshot());
    for ev in queued {
        let _ = r.ctrl.step(now_us, Some(ev));
    }
    r.kernel.configure(r.ctrl.kernel_config(), now_us);
    r.ctrl.background();
}

/// Item 6 (suspected, reproduced here): one control run processes several queued
/// samples, the PLC's inputs read once and the step run once per sample — the two-step
/// DOCK filter took the same reading twice, so a one-sample DOCK glitch after a long job
/// at rest started a docking. The filters take a reading only at a step a good part of a
/// period after the last (`FILTER_GAP`): back-to-back steps are one reading. (That the
/// board does queue samples behind a long job at rest is shown on the virtual board:
/// `vboard/tests/between_steps.rs`.)
#[test]
fn a_dock_glitch_read_once_for_several_queued_samples_started_a_docking() {
    for samples in [2, 3, 8] {
        let mut r = rig(80);
        assert!(r.ctrl.handshake().ready);
        // The glitch: DOCK asserted at the one reading of the catch-up run only.
        control_run_after_a_long_job(&mut r, samples, true);
        for _ in 0..400 {
            r.tick();
            assert_eq!(
                r.ctrl.state(),
                State::Idle,
                "{samples} queued samples: a one-reading DOCK glitch started a docking"
            );
        }
        // A real request (the line held over two readings a period apart) docks.
        r.dock_line.set(false);
        assert!(run_until(&mut r, 20, |r| r.ctrl.state().is_docking()));
    }
}

/// A DOCK the PLC really asserts across a catch-up run is still taken, at the next
/// step a period later (the filter's cost is unchanged: one period).
#[test]
fn a_dock_held_across_a_catch_up_run_is_taken_a_period_later() {
    let mut r = rig(80);
    r.dock_line.set(false);
    control_run_after_a_long_job(&mut r, 4, true);
    assert_eq!(r.ctrl.state(), State::Idle, "one reading only so far");
    assert!(run_until(&mut r, 3, |r| r.ctrl.state().is_docking()));
}

/// Found by the interleaving checker (issue 32): the PLC asserted DOCK as READY rose at
/// the end of a cycle; the dock was accepted and waited for the tare's zero-load samples
/// (about 100 ms at 80 SPS); the PLC released DOCK meanwhile ("be undocked") — and the
/// machine docked anyway, with DOCK released, and held (the release had been consumed
/// while idle). A release of DOCK withdraws a docking of the PLC's not yet started, as
/// it aborts one under way.
#[test]
fn a_dock_released_while_its_docking_waited_for_the_tare_docked_anyway() {
    for rate in [80, 10] {
        let mut r = rig(rate);
        // A cycle: at its end the tare's samples start again from none.
        r.ctrl.command(Request::StartCycle).unwrap();
        assert!(run_until(&mut r, 20_000, |r| r
            .ctrl
            .odometer()
            .lifetime()
            .cycles
            == 1
            && r.ctrl.state() == State::Idle));
        assert!(r.ctrl.handshake().ready);
        // DOCK asserted at once, read twice, accepted: the docking waits for the tare.
        r.dock_line.set(false);
        r.tick();
        r.tick();
        r.tick();
        assert_eq!(r.ctrl.state(), State::Idle, "waiting for the tare");
        // The PLC releases it.
        r.dock_line.set(true);
        for _ in 0..40 {
            r.tick();
            assert_eq!(
                r.ctrl.state(),
                State::Idle,
                "{rate} SPS: docked after the PLC released DOCK"
            );
        }
        // Asserted again, it docks.
        r.dock_line.set(false);
        assert!(run_until(&mut r, 40, |r| r.ctrl.state().is_docking()));
    }
}

/// Found by the interleaving checker (issue 32): an E-STOP edge and an overload trip in
/// the same step — the step kept the first fault it found, the overload, and the
/// sequencer answered it with the controlled back-off: the axis drove 2 mm after the
/// E-STOP (for one step with the input held open, to the end with a pulse). The E-STOP
/// is the fault of any step that sees its edges or its input open.
#[test]
fn an_estop_edge_in_the_step_of_an_overload_trip_backed_off_anyway() {
    for hold in [false, true] {
        let mut r = rig(80);
        r.ctrl.command(Request::Dock).unwrap();
        let engage = r.ctrl.config().machine.engage_um as f64;
        reach(&mut r, 8_000, |r| {
            matches!(r.ctrl.state(), State::Inserting { .. }) && r.axis.pos_um() > engage + 5_000.0
        });
        // A load over every limit from the next sample: held one sample (a jump), then
        // the trip.
        r.script.borrow_mut().offset_n = 250.0;
        r.tick();
        assert!(matches!(r.ctrl.state(), State::Inserting { .. }));
        // The E-STOP before the step that trips.
        if hold {
            r.estop_input(true);
        } else {
            r.estop_pulse(50);
        }
        let travel = r.axis.travel_um();
        for i in 0..200 {
            r.tick();
            assert!(
                !r.axis.enabled() && r.axis.travel_um() == travel,
                "held {hold}: the axis drove {} ticks after the E-STOP ({:?})",
                i,
                r.ctrl.state()
            );
        }
        assert_eq!(faulted(&r), Some(FaultKind::EmergencyStop), "held {hold}");
    }
}

/// Found by the virtual board's campaign (issue 32): a clear on its way (a Modbus frame
/// takes 4.6 ms at 19 200 Bd) as a 50 µs E-STOP pulse came; the step after the pulse
/// consumed its edges (the machine latched already), the clear arrived and was accepted
/// after that step, and its own step ran it: the machine moved 18 ms after the pulse on
/// a clear its PLC had sent before it. A request says when it was issued
/// (`Controller::issued_at`: the frame's first character, a console line's); a clear
/// issued before an E-STOP edge is refused at its step.
#[test]
fn a_clear_on_its_way_as_an_estop_pulse_came_ran_after_it() {
    let mut r = rig(80);
    r.estop_pulse(300);
    r.tick();
    r.tick();
    assert_eq!(faulted(&r), Some(FaultKind::EmergencyStop));
    // The PLC starts sending its clear…
    let issued = (r.clock.now_ns() / 1_000) as u32;
    r.clock.advance_ns(1_000_000);
    // …a pulse 1 ms into the frame, and a step that consumes its edges…
    r.estop_pulse(50);
    r.tick();
    assert_eq!(faulted(&r), Some(FaultKind::EmergencyStop));
    // …then the frame's end: the clear accepted, issued before the pulse.
    r.ctrl.issued_at(Some(issued));
    r.ctrl
        .command_from(Source::Plc, Request::ClearFault)
        .unwrap();
    r.ctrl.issued_at(None);
    stays_latched(&mut r, 240, "a clear issued before the pulse");
    // One issued after it recovers.
    r.ctrl.issued_at(Some((r.clock.now_ns() / 1_000) as u32));
    r.ctrl
        .command_from(Source::Plc, Request::ClearFault)
        .unwrap();
    r.ctrl.issued_at(None);
    assert!(run_until(&mut r, 6_000, |r| r.ctrl.state() == State::Idle));
}

/// Issue 32's review: a control run without a step (TIM2 between two sample steps, or
/// pended by the service) wrote the handshake as of the last step: after the E-STOP
/// interrupt drove MATED low, MATED went high again until the step that latched the
/// fault (low, high, low on the PLC's input).
#[test]
fn mated_was_driven_high_again_by_a_control_run_without_a_step_after_an_estop_edge() {
    let mut r = Rig::booted(RigOptions::new(80));
    r.ctrl.command(Request::Dock).unwrap();
    assert!(run_until(&mut r, 20_000, |r| r.ctrl.handshake().mated));
    // The E-STOP interrupt counts its edge; the input closes again (a pulse).
    r.estop_input(true);
    r.estop_input(false);
    // A control run that does not step: the pins and the edges read, the handshake
    // written.
    r.ctrl.set_plc(false, false, r.estop_edges.snapshot());
    let h = r.ctrl.handshake();
    assert!(!h.mated && !h.ready, "{h:?}");
    // The step takes the edge and latches the fault.
    r.tick();
    assert!(
        matches!(r.ctrl.state(), State::Faulted { .. }),
        "{:?}",
        r.ctrl.state()
    );
    assert!(!r.ctrl.handshake().mated);
}

/// Issue 32's review: a PLC docking started by a step just before a technician's grant
/// could not be withdrawn by the PLC (its DOCK release refused in maintenance mode):
/// the machine mated and held with a technician logged in — item 2's outcome.
#[test]
fn a_plc_docking_started_before_a_grant_could_not_be_withdrawn_by_the_plc() {
    let mut r = Rig::booted(RigOptions::new(80));
    r.dock_line.set(false);
    assert!(run_until(&mut r, 60, |r| r.ctrl.state().is_docking()));
    // The console's grant job.
    r.ctrl.set_maintenance_mode(true);
    // The PLC releases DOCK: its docking is withdrawn.
    r.dock_line.set(true);
    assert!(
        run_until(&mut r, 4_000, |r| r.ctrl.state() == State::Idle),
        "{:?}",
        r.ctrl.state()
    );
    assert!(!r.ctrl.handshake().mated);
    // A docking the console started in maintenance mode is not the PLC's to withdraw.
    r.ctrl.command(Request::Dock).unwrap();
    assert!(run_until(&mut r, 60, |r| r.ctrl.state().is_docking()));
    assert_eq!(
        r.ctrl.command_from(Source::Plc, Request::Undock),
        Err(docking_logic::controller::Refusal::MaintenanceMode)
    );
}
