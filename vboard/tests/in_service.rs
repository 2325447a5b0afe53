//! In service on the virtual board: DOCK as a level, the hold, the vehicle pulling, the
//! E-STOP measured on the pins. Build the image first:
//! `cargo build --release --target thumbv7em-none-eabihf`.

use vboard::scene::{run, Options, SceneOptions, Session};
use vboard::time::PS_PER_S;

fn opts() -> SceneOptions {
    SceneOptions::default()
}

#[test]
fn dock_hold_an_hour_on_the_board_counts_one_cycle_without_wear_while_mated() {
    let r = run("dock-hold", &opts()).expect("board runs");
    assert!(r.passed(), "{}", r.to_text());
    assert!(r.scene.faults.is_empty(), "{}", r.to_text());
    assert_eq!(r.scene.cycles_completed, 1);
    let p = r.scene.plc.clone().expect("PLC report");
    assert!(p.mated_s >= 3_600.0, "{}", r.to_text());
    assert_eq!(p.hold_load_distance_q1, Some(0));
    assert_eq!(p.mated_low_before_extraction, Some(true));
    assert_eq!(r.scene.final_state, "idle");
}

#[test]
fn vehicle_pull_on_the_board_latches_hold_force_and_holds_the_axis() {
    let r = run("vehicle-pull", &opts()).expect("board runs");
    assert!(r.passed(), "{}", r.to_text());
    let kinds: Vec<_> = r.scene.faults.iter().map(|f| f.kind).collect();
    assert_eq!(kinds, ["hold_force"], "{}", r.to_text());
    assert_eq!(r.scene.plc.clone().unwrap().axis_held, Some(true));
}

#[test]
fn estop_edge_to_en_high_on_the_pins_and_the_clear_needs_the_input_closed() {
    let r = run("estop", &opts()).expect("board runs");
    assert!(r.passed(), "{}", r.to_text());
    let kinds: Vec<_> = r.scene.faults.iter().map(|f| f.kind).collect();
    assert_eq!(kinds, ["emergency_stop"], "{}", r.to_text());
    let p = r.scene.plc.clone().unwrap();
    let l = p.estop_latency_s.expect("EN rose after the E-STOP edge");
    assert!(l > 0.0 && l <= 100e-6, "E-STOP to EN high {l} s");
    assert_eq!(p.lock_off_after_estop, Some(true));
    assert_eq!(p.clear_refused_while_open, Some(true));
    assert_eq!(p.clear_accepted_when_closed, Some(true));
}

#[test]
fn a_broken_estop_wire_at_power_on_is_a_stop_and_nothing_moves() {
    let mut s = Session::new(Options::new()).expect("board");
    s.set_estop(true);
    s.set_dock(true);
    s.run_for(3 * PS_PER_S).unwrap();
    let st = s.console_json("status --json").unwrap();
    assert!(st.contains("\"fault\":\"emergency_stop\""), "{st}");
    assert!(st.contains("\"in_estop_open\":true"), "{st}");
    let out = s.plc_out();
    assert!(out.fault && !out.ready && !out.mated, "{out:?}");
    assert!(!s.machine().axis.enabled() && !s.machine().lock.driven());
}
