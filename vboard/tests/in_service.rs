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

#[test]
fn estop_bounce_on_the_board_latches_every_edge_and_recovers() {
    let r = run("estop-bounce", &opts()).expect("board runs");
    assert!(r.passed(), "{}", r.to_text());
    let p = r.scene.plc.clone().expect("PLC report");
    let n = hil_sim::scene::ESTOP_BOUNCE.len() as u32;
    assert_eq!(p.estop_episodes, Some(n), "{}", r.to_text());
    assert_eq!(p.estop_faults_latched, Some(n), "{}", r.to_text());
    assert_eq!(
        p.estop_edges_latched,
        p.estop_edges_injected,
        "{}",
        r.to_text()
    );
    assert_eq!(p.clears_accepted, Some(n), "{}", r.to_text());
    assert_eq!(p.clears_refused_while_open, Some(3), "{}", r.to_text());
    assert_eq!(p.docked_after_estops, Some(true), "{}", r.to_text());
    assert!(
        r.scene.faults.iter().all(|f| f.kind == "emergency_stop"),
        "{}",
        r.to_text()
    );
    // Pre-alignment, insertion and mated: the edges while something moved, each
    // stopped within 10 µs on the pins.
    assert!(r.estop_reactions_us.len() >= 3, "{}", r.to_text());
    let worst = r.estop_off_max_us().unwrap();
    assert!(
        worst <= 10.0,
        "E-STOP edge to EN high / lock off {worst} µs"
    );
    assert_eq!(r.reset_causes, vec!["power_on"]);
}

#[test]
fn heavy_default_on_the_board_trips_once_backs_off_and_clears_out_of_the_cone() {
    let r = run("heavy-default", &opts()).expect("board runs");
    assert!(r.passed(), "{}", r.to_text());
    let kinds: Vec<_> = r.scene.faults.iter().map(|f| f.kind).collect();
    assert_eq!(kinds, ["overload"], "{}", r.to_text());
    let back = r.scene.backed_off_um.expect("a trip");
    assert!((1_900.0..=2_100.0).contains(&back), "backed off {back} µm");
    assert!(r.scene.peak_force_n > 330.0, "the heavy machine's forces");
    assert_eq!(r.scene.recovered_after_clear, Some(true), "{}", r.to_text());
}

#[test]
fn maintenance_lockout_on_the_board_refuses_remote_motion_until_maint_exit() {
    let r = run("maintenance-lockout", &opts()).expect("board runs");
    assert!(r.passed(), "{}", r.to_text());
    let p = r.scene.plc.clone().expect("PLC report");
    assert_eq!(p.ready_low_in_maintenance, Some(true));
    assert_eq!(p.maintenance_shown, Some(true));
    assert_eq!(p.modbus_dock_refused, Some(true));
    assert_eq!(p.dock_pin_ignored, Some(true));
    assert_eq!(p.docked_after_maintenance, Some(true));
    assert!(r.scene.faults.is_empty(), "{}", r.to_text());
}
