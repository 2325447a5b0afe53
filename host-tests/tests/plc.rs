//! The PLC handshake on the host rig: DOCK (level, filtered, edges), E-STOP (normally
//! closed), READY / MATED / FAULT / MAINTENANCE.

use docking_logic::sequencer::State;
use hil_sim::rig::{Rig, RigOptions};

fn rig() -> Rig {
    Rig::booted(RigOptions::new(80))
}

use host_tests::run_until;

/// The machine is latched in `fault`; with the PLC's DOCK released, a clear brings it
/// home to idle, and the next DOCK mates.
fn recovers_from(r: &mut Rig, fault: docking_logic::sequencer::FaultKind) {
    assert_eq!(r.ctrl.state(), State::Faulted { fault });
    r.dock_line.set(true);
    r.ctrl
        .command(docking_logic::sequencer::Request::ClearFault)
        .unwrap();
    assert!(run_until(r, 8_000, |r| r.ctrl.state() == State::Idle));
    r.dock_line.set(false);
    assert!(run_until(r, 6_000, |r| r.ctrl.handshake().mated));
}

#[test]
fn dock_asserted_across_a_reset_is_not_a_request() {
    // DOCK low (asserted) from before the controller booted.
    let mut r = Rig::new(RigOptions::new(80));
    r.dock_line.set(false);
    host_tests::run_without_motion(&mut r, 800, "moved without a request");
    assert_eq!(r.ctrl.state(), State::Idle);
    assert!(r.ctrl.handshake().dock, "the input is seen");
    // The PLC releases and asserts it again: that is a request.
    r.dock_line.set(true);
    for _ in 0..5 {
        r.tick();
    }
    r.dock_line.set(false);
    assert!(run_until(&mut r, 50, |r| r.ctrl.state().is_docking()));
}

#[test]
fn a_one_step_dock_glitch_is_filtered() {
    let mut r = rig();
    r.dock_line.set(false);
    r.tick();
    r.dock_line.set(true);
    for _ in 0..200 {
        r.tick();
        assert_eq!(r.ctrl.state(), State::Idle);
    }
}

#[test]
fn outputs_follow_the_machine() {
    let mut r = rig();
    let h = r.ctrl.handshake();
    assert!(h.ready && !h.mated && !h.fault && !h.maintenance, "{h:?}");
    r.dock_line.set(false);
    assert!(run_until(&mut r, 6_000, |r| r.ctrl.handshake().mated));
    let h = r.ctrl.handshake();
    assert!(!h.ready && !h.fault, "{h:?}");
    // Undock: MATED drops before the carriage moves back.
    let pos = r.axis.pos_um();
    r.dock_line.set(true);
    assert!(run_until(&mut r, 50, |r| !r.ctrl.handshake().mated));
    assert!(
        r.axis.pos_um() >= pos - 1.0,
        "still in place when MATED fell"
    );
    assert!(run_until(&mut r, 6_000, |r| r.ctrl.state() == State::Idle));
    assert!(r.ctrl.handshake().ready);
    assert_eq!(r.ctrl.odometer().lifetime().cycles, 1);
    // E-STOP open at rest: FAULT, not READY, and no clear while open.
    r.estop_line.set(true);
    r.tick();
    r.tick();
    let h = r.ctrl.handshake();
    assert!(h.fault && h.estop && !h.ready, "{h:?}");
    assert!(r
        .ctrl
        .command(docking_logic::sequencer::Request::ClearFault)
        .is_err());
}

#[test]
fn a_pending_stop_is_not_replaced_by_a_later_request() {
    use docking_logic::sequencer::{FaultKind, Request};
    let mut r = rig();
    // Stop, then (before the next step) a dock: the stop wins.
    r.ctrl.command(Request::Stop).unwrap();
    let _ = r.ctrl.command(Request::Dock);
    r.ctrl.request(Request::StartCycle);
    r.tick();
    r.tick();
    assert_eq!(
        r.ctrl.state(),
        State::Faulted {
            fault: FaultKind::Stopped
        }
    );
    assert!(!r.axis.enabled());
}

/// Defect (issue 17, item 3): a 300 µs E-STOP pulse between two control steps stopped
/// the propulsion and latched the stop, but no step ever read the input open: READY
/// stayed high, no fault, every later dock ended in `axis_stall`, and `clear-fault`
/// had nothing to clear.
#[test]
fn short_estop_pulse_latches_a_fault_and_the_machine_recovers() {
    use docking_logic::sequencer::{FaultKind, Request};
    let mut r = rig();
    assert!(r.ctrl.handshake().ready);
    r.estop_pulse(300);
    r.tick();
    r.tick();
    assert_eq!(
        r.ctrl.state(),
        State::Faulted {
            fault: FaultKind::EmergencyStop
        }
    );
    let h = r.ctrl.handshake();
    assert!(h.fault && !h.ready && !h.estop, "{h:?}");
    // The input is closed: the clear works, and the next dock completes.
    r.ctrl.command(Request::ClearFault).unwrap();
    assert!(run_until(&mut r, 6_000, |r| r.ctrl.state() == State::Idle));
    assert!(r.ctrl.handshake().ready);
    r.dock_line.set(false);
    assert!(
        run_until(&mut r, 6_000, |r| r.ctrl.handshake().mated),
        "docked after the E-STOP: {:?}",
        r.ctrl.status().fault
    );
}

/// A bouncing release (open, closed, open, closed within a step) during the insertion:
/// every edge stops, the fault latches, the clear works once the input stays closed.
#[test]
fn estop_release_bounce_is_latched_and_recoverable() {
    use docking_logic::sequencer::FaultKind;
    let mut r = rig();
    r.dock_line.set(false);
    assert!(run_until(&mut r, 6_000, |r| matches!(
        r.ctrl.state(),
        State::Inserting { .. }
    )));
    r.estop_line.set(true);
    r.tick();
    assert!(!r.axis.enabled() && !r.lock.driven());
    r.estop_line.set(false);
    r.estop_pulse(80);
    r.estop_pulse(40);
    for _ in 0..3 {
        r.tick();
        assert!(!r.axis.enabled(), "nothing moves after the E-STOP");
    }
    recovers_from(&mut r, FaultKind::EmergencyStop);
}

/// A stop the controller never heard of (its event lost) held the driver off and the
/// docking stalled (`axis_stall` seconds later, or nothing at all at rest): now the
/// refused re-enable is a named fault within two steps, and a clear recovers.
#[test]
fn a_stop_never_reported_is_a_fault_not_a_stall() {
    use docking_logic::hal::StopLatch;
    use docking_logic::sequencer::FaultKind;
    let mut r = rig();
    r.stop.stop_now(); // latched, no event, no E-STOP edge
    r.dock_line.set(false);
    assert!(run_until(&mut r, 400, |r| matches!(
        r.ctrl.state(),
        State::Faulted { .. }
    )));
    recovers_from(&mut r, FaultKind::UnseenStop);
}

/// Pulled while mated holds the axis driven; an E-STOP then must turn it off and keep
/// it off (the fault takes the E-STOP's place), not be re-armed by the next step.
#[test]
fn estop_during_a_hold_force_fault_turns_the_axis_off() {
    use docking_logic::sequencer::FaultKind;
    let mut r = rig();
    r.dock_line.set(false);
    assert!(run_until(&mut r, 6_000, |r| r.ctrl.handshake().mated));
    r.script.borrow_mut().pull_n_per_s = 200.0;
    let hold = State::Faulted {
        fault: FaultKind::HoldForce,
    };
    assert!(run_until(&mut r, 400, |r| r.ctrl.state() == hold));
    r.script.borrow_mut().pull_n_per_s = 0.0;
    assert!(r.axis.enabled(), "held, driven");
    r.estop_line.set(true);
    for _ in 0..5 {
        r.tick();
        assert!(!r.axis.enabled());
    }
    assert_eq!(
        r.ctrl.state(),
        State::Faulted {
            fault: FaultKind::EmergencyStop
        }
    );
}
