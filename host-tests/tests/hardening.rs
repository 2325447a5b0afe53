//! Board hardening, the logic half (the board half is proven on the virtual board,
//! `vboard/tests/hardening.rs`): force limits both ways, the uncalibrated cell, switch
//! noise, storage faults, and the load–distance of a cycle that did not finish. The real
//! controller and safety kernel against the simulated machine; each test is named for
//! the defect it pins.

use docking_logic::controller::{Event, STORAGE_ATTEMPTS};
use docking_logic::diag::ResetCause;
use docking_logic::sequencer::{FaultKind, Request, State};
use hil_sim::axis::AxisFault;
use hil_sim::flash::{SharedFlash, SimFlash};
use hil_sim::hx711::Hx711Fault;
use hil_sim::rig::{Rig, RigOptions};

fn rig() -> Rig {
    Rig::new(RigOptions::new(80))
}

use host_tests::reach;

fn inserting(rig: &Rig) -> bool {
    matches!(rig.ctrl.state(), State::Inserting { .. })
}

fn faulted_with(rig: &Rig) -> Option<FaultKind> {
    match rig.ctrl.state() {
        State::Faulted { fault } => Some(fault),
        _ => None,
    }
}

/// Start a cycle and run to `depth_um` of the insertion.
fn dock_to_depth(rig: &mut Rig, depth_um: f64) {
    reach(rig, 2_000, |r| r.ctrl.state() == State::Idle);
    rig.ctrl.request(Request::StartCycle);
    let engage = rig.ctrl.config().machine.engage_um as f64;
    reach(rig, 20_000, |r| {
        inserting(r) && r.axis.pos_um() >= engage + depth_um
    });
}

#[test]
fn a_reversed_bridge_docked_with_zero_wear_and_no_trip() {
    let mut rig = rig();
    rig.script.borrow_mut().reversed = true;
    reach(&mut rig, 2_000, |r| r.ctrl.state() == State::Idle);
    rig.ctrl.request(Request::StartCycle);
    reach(&mut rig, 40_000, |r| faulted_with(r).is_some());
    assert_eq!(faulted_with(&rig), Some(FaultKind::Tension));
    assert!(!rig.axis.enabled(), "the propulsion is off");
    // Stopped early in the cone: at the first samples beyond the tension limit.
    let depth = rig.axis.pos_um() - rig.ctrl.config().machine.engage_um as f64;
    assert!(depth < 15_000.0, "stopped {depth} µm deep");
}

#[test]
fn an_uncalibrated_load_cell_docked() {
    let mut rig = Rig::new(RigOptions {
        commissioned: false,
        ..RigOptions::new(80)
    });
    assert!(!rig.ctrl.calibrated());
    reach(&mut rig, 2_000, |r| r.ctrl.state() == State::Idle);
    rig.ctrl.request(Request::StartCycle);
    let mut refused = false;
    for _ in 0..2_000 {
        rig.tick();
        while let Some(e) = rig.ctrl.next_event() {
            refused |= e.event == Event::UncalibratedRefusal;
        }
    }
    assert!(refused, "the refusal is an event (log, PLC)");
    assert_eq!(rig.ctrl.state(), State::Idle);
    assert_eq!(rig.axis.travel_um(), 0.0, "nothing moved");
    assert!(!rig.axis.enabled());
    let status = rig.command("status --json", 200);
    assert!(status.contains("\"calibrated\":false"), "{status}");
}

#[test]
fn a_single_noisy_end_switch_reading_stopped_the_machine() {
    let mut rig = rig();
    dock_to_depth(&mut rig, 5_000.0);
    rig.axis.glitch_end_switch(1);
    reach(&mut rig, 40_000, |r| {
        r.ctrl.state() == State::Idle && r.ctrl.odometer().lifetime().cycles == 1
    });
    assert!(
        rig.ctrl.faults().next().is_none(),
        "no fault from one reading"
    );
}

#[test]
fn a_real_overtravel_stopped_more_than_one_sample_late() {
    let mut rig = rig();
    dock_to_depth(&mut rig, 5_000.0);
    let t0 = rig.clock.now_ns();
    rig.axis.set_fault(AxisFault::EndSwitchClosed);
    reach(&mut rig, 100, |r| faulted_with(r).is_some());
    assert_eq!(faulted_with(&rig), Some(FaultKind::Overtravel));
    let off = rig
        .axis
        .enable_edges()
        .iter()
        .rev()
        .find(|e| !e.enabled)
        .map(|e| e.t_ns)
        .expect("the driver was switched off");
    // The filter's cost is one sample period (12.5 ms at 80 SPS); the switch is read
    // once per step, so the stop comes within two periods of the switch closing.
    let period_ns = 12_500_000;
    assert!(
        off - t0 <= 2 * period_ns,
        "stopped {} ms after the switch closed",
        (off - t0) as f64 / 1e6
    );
}

#[test]
fn a_failing_flash_was_retried_at_every_step() {
    let mut rig = rig();
    reach(&mut rig, 2_000, |r| r.ctrl.state() == State::Idle);
    rig.ctrl.request(Request::StartCycle);
    // The cycle runs; it fails to write its snapshot at the end.
    rig.flash.with(|f| f.write_protect(true));
    let calls0 = rig.flash.with(|f| f.program_calls());
    reach(&mut rig, 40_000, |r| faulted_with(r).is_some());
    assert_eq!(faulted_with(&rig), Some(FaultKind::Storage));
    assert_eq!(rig.ctrl.odometer().lifetime().cycles, 1, "counted in RAM");
    assert_eq!(rig.ctrl.storage_errors(), u32::from(STORAGE_ATTEMPTS));
    // A few tries, not one per step (every torn try uses up a slot of the log).
    let tries = rig.flash.with(|f| f.program_calls()) - calls0;
    assert!(tries <= 3, "{tries} program calls before the storage fault");
    // No more tries while the fault stands (each try burns slots of the log).
    let calls = rig.flash.with(|f| f.program_calls());
    for _ in 0..2_000 {
        rig.tick();
    }
    assert_eq!(rig.flash.with(|f| f.program_calls()), calls);
    // Refused: no new cycle with the odometer unable to record it.
    rig.ctrl.request(Request::StartCycle);
    for _ in 0..200 {
        rig.tick();
    }
    assert_eq!(faulted_with(&rig), Some(FaultKind::Storage));
    // The flash works again (say, its protection was a bad option byte); a clear
    // writes what was kept in RAM.
    rig.flash.with(|f| f.write_protect(false));
    rig.ctrl.request(Request::ClearFault);
    reach(&mut rig, 20_000, |r| {
        r.ctrl.state() == State::Idle && !r.ctrl.persist_pending()
    });
    let flash = rig.flash.clone();
    drop(rig);
    let rebooted = Rig::with_flash(RigOptions::new(80), flash);
    assert_eq!(rebooted.ctrl.odometer().lifetime().cycles, 1);
}

#[test]
fn a_cycle_cut_short_by_a_fault_lost_its_load_distance() {
    let mut rig = rig();
    dock_to_depth(&mut rig, 12_000.0);
    let pending = rig.ctrl.odometer().pending_q1();
    assert!(pending > 0, "load–distance so far");
    let w_before = rig.ctrl.odometer().cone().w_q1;
    rig.hx.set_fault(Hx711Fault::Disconnected);
    reach(&mut rig, 2_000, |r| faulted_with(r).is_some());
    assert_eq!(faulted_with(&rig), Some(FaultKind::SensorDisconnected));
    reach(&mut rig, 2_000, |r| !r.ctrl.persist_pending());
    let o = rig.ctrl.odometer();
    assert!(o.cone().w_q1 >= w_before + pending, "in the cone's total");
    assert_eq!(o.cone().cycles, 0, "no cycle counted");
    // In flash: a power cut now keeps it.
    let w = o.cone().w_q1;
    let flash = rig.flash.clone();
    drop(rig);
    let rebooted = Rig::with_flash(RigOptions::new(80), flash);
    assert_eq!(rebooted.ctrl.odometer().cone().w_q1, w);
    assert!(rebooted.ctrl.odometer().wear_nm() > 0);
}

#[test]
fn a_reset_mid_cycle_lost_its_load_distance() {
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    let mut rig = Rig::with_flash(RigOptions::new(80), flash.clone());
    dock_to_depth(&mut rig, 12_000.0);
    // What the board keeps in its RAM journal after every step.
    let journal = rig.ctrl.journal();
    let pending = rig.ctrl.odometer().pending_q1();
    assert!(pending > 0);
    assert_eq!(rig.ctrl.odometer().cone().w_q1, 0, "nothing in flash yet");
    drop(rig); // the watchdog (or NRST) resets the MCU; SRAM keeps the journal
    let mut rig = Rig::with_flash(RigOptions::new(80), flash.clone());
    assert_eq!(
        rig.ctrl.odometer().cone().w_q1,
        0,
        "the flash alone lost it"
    );
    rig.ctrl.boot(ResetCause::Watchdog, None, &[journal]);
    assert_eq!(rig.ctrl.odometer().cone().w_q1, pending);
    // Written at the first rest (power-up: nothing moves), so a power cut keeps it.
    reach(&mut rig, 2_000, |r| !r.ctrl.persist_pending());
    drop(rig);
    let rebooted = Rig::with_flash(RigOptions::new(80), flash);
    assert_eq!(rebooted.ctrl.odometer().cone().w_q1, pending);
}

#[test]
fn a_console_line_that_lost_bytes_was_executed() {
    let mut rig = rig();
    rig.console_enabled = true;
    // A burst that fills the 256-entry receive ring: the first line (rejected) and
    // "history 1" fit; "00" and the terminator are lost.
    let mut burst = vec![b'x'; 246];
    burst.push(b'\r');
    burst.extend_from_slice(b"history 100\r\n");
    assert_eq!(burst.len(), 260);
    rig.term.send(&burst);
    let mut out = Vec::new();
    for _ in 0..50 {
        rig.tick();
        out.extend(rig.term.take_output());
    }
    // The next line ends the damaged one (its own terminator was lost).
    rig.term.send(b"status\r\n");
    for _ in 0..50 {
        rig.tick();
        out.extend(rig.term.take_output());
    }
    let out = String::from_utf8_lossy(&out);
    assert!(rig.term.rx_overruns > 0);
    assert!(
        out.contains("error: input lost (receive error or overrun); line discarded"),
        "{out}"
    );
    // The damaged line ("history 1" + "status") ran as nothing.
    assert!(!out.contains("cycle="), "{out}");
    assert!(!out.contains("state="), "{out}");
}
