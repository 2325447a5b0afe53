//! The PLC handshake on the host rig: DOCK (level, filtered, edges), E-STOP (normally
//! closed), READY / MATED / FAULT / MAINTENANCE.

use docking_controller::sequencer::State;
use hil_sim::rig::{Rig, RigOptions};

fn rig() -> Rig {
    let mut r = Rig::new(RigOptions::new(80));
    for _ in 0..100 {
        r.tick();
    }
    r
}

use host_tests::run_until;

#[test]
fn dock_asserted_across_a_reset_is_not_a_request() {
    // DOCK low (asserted) from before the controller booted.
    let mut r = Rig::new(RigOptions::new(80));
    r.dock_line.set(false);
    for _ in 0..800 {
        r.tick();
        assert!(
            !r.axis.enabled() && !r.lock.driven(),
            "moved without a request"
        );
    }
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
        .command(docking_controller::sequencer::Request::ClearFault)
        .is_err());
}

#[test]
fn a_pending_stop_is_not_replaced_by_a_later_request() {
    use docking_controller::sequencer::{FaultKind, Request};
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
