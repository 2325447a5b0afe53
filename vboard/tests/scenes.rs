//! The release image on the virtual board, end to end: what `.ci/run` proves about the
//! board. Build the image first: `cargo build --release --target thumbv7em-none-eabihf`.

use vboard::scene::{json_field, run, Options, SceneOptions, Session, PS_PER_MS};
use vboard::time::PS_PER_S;

fn opts() -> SceneOptions {
    SceneOptions::default()
}

#[test]
fn one_nominal_cycle_through_the_four_contact_phases() {
    let r = run("nominal", &opts()).expect("board runs");
    assert_eq!(r.scene.cycles_completed, 1, "{}", r.to_text());
    assert!(r.scene.faults.is_empty(), "{:?}", r.scene.faults);
    assert_eq!(r.scene.insertion_phases, vec![vec![1, 2, 3, 4]]);
    assert_eq!(r.scene.final_state, "idle");
    assert!(r.scene.motors_disabled);
    // Eq. 7's N3 peak is 206.34 N; the cell's noise is ≈ 0.3 N RMS.
    assert!(
        (205.0..209.0).contains(&r.scene.peak_force_n),
        "{}",
        r.scene.peak_force_n
    );
    assert_eq!(r.reset_causes, vec!["power_on"]);
    assert_eq!(r.samples_missed, 0);
}

#[test]
fn overload_trips_within_one_sample_and_backs_off() {
    let r = run("overload", &opts()).expect("board runs");
    assert!(
        r.scene.faults.iter().any(|f| f.kind == "overload"),
        "{}",
        r.to_text()
    );
    let l = r.stop_latency_pins_us.expect("a trip seen on the pins");
    assert!(
        l > 0.0 && l < 12_500.0,
        "stop latency {l} µs, one sample is 12 500 µs"
    );
    assert!(
        r.scene.forward_after_trip_um.unwrap() < 10.0,
        "{:?}",
        r.scene.forward_after_trip_um
    );
    let back = r.scene.backed_off_um.unwrap();
    assert!((1_900.0..=2_100.0).contains(&back), "backed off {back} µm");
    assert!(r.scene.motors_disabled);
    assert_eq!(r.scene.final_state, "faulted");
}

#[test]
fn a_silent_load_cell_is_sensor_disconnected() {
    let r = run("disconnect", &opts()).expect("board runs");
    assert_eq!(
        r.scene.faults.first().map(|f| f.kind),
        Some("sensor_disconnected"),
        "{}",
        r.to_text()
    );
    assert!(r.scene.motors_disabled);
}

#[test]
fn a_reset_in_the_middle_of_a_record_write_loses_no_counter() {
    let r = run("power-cut-write", &opts()).expect("board runs");
    assert!(r.passed(), "{}", r.to_text());
    assert_eq!(r.reset_causes, vec!["power_on", "pin"]);
}

#[test]
fn wear_is_read_as_json_over_usart2() {
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(PS_PER_S).unwrap();
    let reply = s.console_json("wear --json").unwrap();
    let v: serde_json::Value = serde_json::from_str(reply.trim()).expect("one JSON object");
    assert_eq!(v["material"], "zqsn5-2");
    assert_eq!(v["cycles"], 0);
    assert_eq!(json_field(&reply, "level").as_deref(), Some("ok"));
    assert_eq!(s.board.soc().console_pin_losses, 0);
}

#[test]
fn the_same_scene_twice_gives_the_same_result() {
    let strip = |j: String| {
        let mut v: serde_json::Value = serde_json::from_str(&j).unwrap();
        for k in [
            "wall_time_s",
            "mips",
            "realtime_factor",
            "realtime_factor_min",
        ] {
            v.as_object_mut().unwrap().remove(k);
        }
        v
    };
    let a = strip(run("boot", &opts()).unwrap().to_json());
    let b = strip(run("boot", &opts()).unwrap().to_json());
    assert_eq!(a, b);
}

/// With nothing moving there is no all-masked window to measure (its site stays 0), and
/// the report named a defmt string as the window's site: `function_at(0)` took the
/// `.defmt` section's symbols, which start at address 0, for functions.
#[test]
fn a_run_without_a_masked_window_named_a_defmt_string_as_its_site() {
    let r = run("boot", &opts()).expect("board runs");
    assert_eq!(r.masked_max_us, 0.0, "{}", r.to_text());
    assert_eq!(r.masked_max_at, "-");
}

#[test]
fn nothing_moves_after_power_on_before_the_boot_completes() {
    // From power-on the motor outputs float until the firmware drives them: the
    // board's pulls hold EN high (driver off) and the bridge inputs low.
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(5 * PS_PER_MS).unwrap();
    let m = s.machine();
    assert!(!m.axis.enabled());
    assert!(!m.lock.driven());
    assert_eq!(
        m.axis.step_timing().pulses_pos + m.axis.step_timing().pulses_neg,
        0
    );
}
