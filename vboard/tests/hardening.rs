//! The board-hardening promises, proven on the release image's pins, clock and resets.
//! Each test is named for the defect it pins: it fails on the firmware that had it.
//! Build the image first: `cargo build --release --target thumbv7em-none-eabihf`.

use vboard::scene::{json_field, run, Options, SceneOptions, Session, PS_PER_MS};
use vboard::time::PS_PER_S;

fn flooded(rate_sps: u32) -> SceneOptions {
    SceneOptions {
        session: Options {
            rate_sps,
            ..Options::new()
        },
        cycles: 1,
        flood: true,
        cut: None,
    }
}

fn json(s: &str) -> serde_json::Value {
    serde_json::from_str(s.trim()).expect("one JSON object")
}

fn logged(s: &Session, needle: &str) -> bool {
    s.board.log.iter().any(|l| l.msg.contains(needle))
}

/// The overload trip under the worst load the console can make: the line flooded at
/// 115 200 Bd with `history 100 --json` (the full log, CRC-checked record by record),
/// `status`, `faults`, garbage and over-long lines, while the fault is logged.
fn overload_stop_during_a_flood(rate_sps: u32) {
    let r = run("overload", &flooded(rate_sps)).expect("board runs");
    assert!(
        r.scene.faults.iter().any(|f| f.kind == "overload"),
        "{}",
        r.to_text()
    );
    assert!(r.console_flood_bytes > 5_000, "{}", r.console_flood_bytes);
    let l = r.stop_latency_pins_us.expect("a trip seen on the pins");
    assert!(
        l <= 100.0,
        "DOUT falling → EN high {l} µs at {rate_sps} SPS (target ≤ 100 µs)"
    );
    // Not only the trip: every sample read while the machine ran was taken as promptly.
    assert!(
        r.sample_latency_max_us <= 100.0,
        "worst DOUT → sample read {} µs",
        r.sample_latency_max_us
    );
    // And the sampler (EXTI0, under only the E-STOP) waited for nothing but a window
    // with every interrupt masked: no lower task holds the kernel's lock, or anything
    // else at the sampler's ceiling, longer. (Allowance: the exception entry, 12 cycles,
    // the FPU's lazy stacking, and the wake from `wfi`.)
    assert!(
        r.sample_entry_latency_max_us <= r.masked_max_us + 0.25,
        "the sampler waited {} µs to start (ended in {}); longest all-masked window {} µs",
        r.sample_entry_latency_max_us,
        r.sample_entry_max_at,
        r.masked_max_us
    );
    // The board's masked-window meter missed `msr primask, lr` (the compiler keeps the
    // saved PRIMASK in lr in `clock::now_us`): a window opened there looked as long as
    // the time to the next unmask anywhere (42 µs under a Modbus flood). This run is
    // the one that showed it (`a_critical_section_restored_from_lr_was_measured_as_still_masked`
    // ran it a second time, 30 s of CI, until issue 33's CI budget).
    assert!(
        r.masked_max_us < 20.0,
        "longest all-masked window {} µs in {}",
        r.masked_max_us,
        r.masked_max_at
    );
    assert_eq!(r.samples_missed, 0);
    assert!(r.scene.motors_disabled);
    assert!(r.core_faults.is_empty(), "{:?}", r.core_faults);
    // The Modbus line flooded at the same time (reads, garbage, bad CRCs, over-long
    // frames): answered, every reply with the RS-485 driver on, nothing delayed.
    assert!(r.modbus_flood_bytes > 1_000, "{}", r.modbus_flood_bytes);
    assert!(r.modbus_reply_bytes > 0);
    assert_eq!(r.modbus_de_losses, 0);
}

#[test]
fn overload_stop_waited_for_the_main_loop_at_80_sps_during_a_console_flood() {
    overload_stop_during_a_flood(80);
}

#[test]
fn overload_stop_waited_for_the_main_loop_at_10_sps_during_a_console_flood() {
    overload_stop_during_a_flood(10);
}

#[test]
fn a_pin_reset_mid_insertion_homed_without_a_request() {
    let r = run(
        "power-cycle",
        &SceneOptions {
            session: Options::new(),
            cycles: 1,
            flood: false,
            cut: None,
        },
    )
    .expect("board runs");
    assert!(r.passed(), "{}", r.to_text());
    assert_eq!(r.motion_before_request, Some(false), "{}", r.to_text());
    assert_eq!(r.reset_causes, vec!["power_on", "pin"]);
}

#[test]
fn step_edges_came_too_close_to_dir_and_en_for_an_opto_isolated_driver() {
    let r = run(
        "nominal",
        &SceneOptions {
            session: Options::new(),
            cycles: 1,
            flood: false,
            cut: None,
        },
    )
    .expect("board runs");
    let st = r.step;
    assert!(st.pulses_pos > 1000 && st.pulses_neg > 1000, "{st:?}");
    assert_eq!(st.pulses_disabled, 0, "{st:?}");
    assert_eq!(st.setup_violations, 0, "{st:?}");
    assert_eq!(st.width_violations, 0, "{st:?}");
    assert!(st.min_setup_ns >= 5_000, "{st:?}");
    assert!(st.min_high_ns >= 2_500, "{st:?}");
    // Across the reversal the firmware's position is the carriage's.
    assert!(r.passed(), "{}", r.to_text());
}

#[test]
fn the_core_spun_instead_of_sleeping() {
    let mut s = Session::new(Options::new()).expect("board");
    // Booted, idle: samples come at 80 SPS, the control step runs, nothing moves.
    s.run_for(3 * PS_PER_S).unwrap();
    let (t0, slept0) = (s.now(), s.board.soc().clock.sleep_ps());
    s.run_for(2 * PS_PER_S).unwrap();
    let awake = 1.0 - (s.board.soc().clock.sleep_ps() - slept0) as f64 / (s.now() - t0) as f64;
    // A spinning core is awake 100 % of the time.
    assert!(awake < 0.05, "awake {:.2} % of the time", awake * 100.0);
    assert!(s.board.sleeping() || awake > 0.0);
}

/// Issue 17 item 8: the image used to program BOR by itself at its first boot (BOR off,
/// the supply possibly ramping; a cut there can set read or write protection). Now boot
/// reads and reports the level, and `bor set` (maintenance, at rest) programs it.
#[test]
fn the_brown_out_level_is_programmed_only_by_the_maintenance_step() {
    let mut s = Session::new(Options::new()).expect("board");
    let bor_lev = |s: &Session| (s.board.soc().flash.option_bytes() >> 2) & 0b11;
    assert_eq!(bor_lev(&s), 0b11, "factory: BOR off");
    s.run_for(PS_PER_S).unwrap();
    assert_eq!(bor_lev(&s), 0b11, "boot leaves the option bytes alone");
    assert!(logged(&s, "BOR level 0"), "{:?}", s.board.log);
    let reply = s.console("bor", PS_PER_S).unwrap();
    assert!(reply.contains("level=0"), "{reply}");
    for cmd in ["pin set 2468", "maint 2468"] {
        let r = s.console(cmd, 2 * PS_PER_S).unwrap();
        assert!(r.starts_with("ok"), "{cmd}: {r}");
    }
    let reply = s.console("bor set", 5 * PS_PER_S).unwrap();
    assert!(reply.starts_with("ok: BOR level 3"), "{reply}");
    assert_eq!(bor_lev(&s), 0b00, "BOR level 3 in the option bytes");
    // The next boot finds it set and says so.
    s.board.reset_pin();
    s.run_for(PS_PER_S).unwrap();
    assert!(logged(&s, "BOR level 3"), "{:?}", s.board.log);
    assert_eq!(bor_lev(&s), 0b00);
}

#[test]
fn the_reset_cause_was_not_read_counted_or_shown() {
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(PS_PER_S).unwrap();
    s.board.reset_pin();
    s.run_for(PS_PER_S).unwrap();
    assert!(logged(&s, "reset cause: pin"), "{:?}", s.board.log);
    let st = s.console_json("status --json").unwrap();
    assert_eq!(json_field(&st, "reset").as_deref(), Some("pin"), "{st}");
    let f = json(&s.console_json("faults --json").unwrap());
    assert_eq!(f["resets"]["power_on"], 1, "{f}");
    assert_eq!(f["resets"]["pin"], 1, "{f}");
    assert_eq!(f["resets"]["watchdog"], 0, "{f}");
    // Counted in flash: a board that loses power keeps them.
    s.board.power_on();
    s.run_for(PS_PER_S).unwrap();
    let f = json(&s.console_json("faults --json").unwrap());
    assert_eq!(f["resets"]["power_on"], 2, "{f}");
    assert_eq!(f["resets"]["pin"], 1, "{f}");
}

#[test]
fn an_uncalibrated_load_cell_docked() {
    let mut s = Session::new(Options {
        commissioned: false,
        ..Options::new()
    })
    .expect("board");
    s.run_for(PS_PER_S).unwrap();
    assert!(logged(&s, "load cell not calibrated"), "{:?}", s.board.log);
    s.press_dock();
    s.run_for(3 * PS_PER_S).unwrap();
    // The DOCK edge goes through the command gate: refused, with the reason logged.
    assert!(
        logged(&s, "DOCK Dock refused (Uncalibrated)"),
        "{:?}",
        s.board.log
    );
    let m = s.machine();
    let st = m.axis.step_timing();
    assert_eq!(st.pulses_pos + st.pulses_neg, 0, "no step pulse");
    assert!(!m.axis.enabled() && !m.lock.driven());
    assert!(m.lock.fraction_locked() >= 1.0);
    let status = s.console_json("status --json").unwrap();
    assert_eq!(
        json_field(&status, "calibrated").as_deref(),
        Some("false"),
        "{status}"
    );
    assert_eq!(json_field(&status, "state").as_deref(), Some("idle"));
}

#[test]
fn a_hard_fault_left_no_record_and_the_motors_running() {
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(PS_PER_S).unwrap();
    s.press_dock();
    // Moving: the driver on, pulses out.
    let t = s.now() + 5 * PS_PER_S;
    s.run_until(t, |x| {
        let st = x.machine().axis.step_timing();
        x.machine().axis.enabled() && st.pulses_pos > 200
    })
    .unwrap();
    assert!(s.machine().axis.enabled(), "the carriage moves");
    s.board.inject_bus_fault();
    // The handler makes the outputs safe before anything else, then resets.
    s.run_for(PS_PER_MS).unwrap();
    assert!(!s.machine().axis.enabled() && !s.machine().lock.driven());
    s.run_for(PS_PER_S).unwrap();
    assert_eq!(s.reset_causes(), vec!["power_on", "software"]);
    let f = json(&s.console_json("faults --json").unwrap());
    let c = &f["last_crash"];
    assert_eq!(c["kind"], "hard_fault", "{f}");
    assert_ne!(c["pc"], 0, "{f}");
    let cfsr = c["cfsr"].as_u64().unwrap_or(0);
    assert_ne!(cfsr & (1 << 10), 0, "CFSR.IMPRECISERR in {cfsr:#x}");
    assert!(logged(&s, "the last run crashed: hard_fault"));
    // Nothing moves after the reboot until asked.
    let st = s.machine().axis.step_timing();
    let pulses = st.pulses_pos + st.pulses_neg;
    s.run_for(2 * PS_PER_S).unwrap();
    let st = s.machine().axis.step_timing();
    assert_eq!(st.pulses_pos + st.pulses_neg, pulses);
    // The record is in flash: it is still reported after a power cycle.
    s.board.power_on();
    s.run_for(PS_PER_S).unwrap();
    let f = json(&s.console_json("faults --json").unwrap());
    assert_eq!(f["last_crash"]["kind"], "hard_fault", "{f}");
}

#[test]
fn a_stack_overflow_corrupted_memory_silently() {
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(PS_PER_S).unwrap();
    let (bottom, _) = s.board.image.symbol("_stack_end").expect("_stack_end");
    let first_static = s.board.image.symbol("CRASH_BLOCK").expect("CRASH_BLOCK").0;
    assert!(
        first_static >= bottom + 24 * 1024,
        "the statics sit above the stack"
    );
    // Drive the stack to 40 bytes above its bottom: the next interrupt's frame and its
    // handler's pushes run off the bottom of SRAM.
    s.board.set_msp(bottom + 40);
    s.run_for(2 * PS_PER_S).unwrap();
    let faults = s.board.faults();
    assert!(
        faults.iter().any(|f| f.what.contains("bus fault")),
        "the overflow faulted: {faults:?}"
    );
    // No handler can run on an exhausted stack: the core locks up, the watchdog resets.
    assert_eq!(s.reset_causes(), vec!["power_on", "watchdog"]);
    let f = json(&s.console_json("faults --json").unwrap());
    assert_eq!(f["last_crash"]["kind"], "stack_overflow", "{f}");
    // The statics above the stack were never touched: the odometer still reads.
    let w = json(&s.console_json("wear --json").unwrap());
    assert_eq!(w["cycles"], 0, "{w}");
    let st = s.console_json("status --json").unwrap();
    let used: u32 = json_field(&st, "stack_used").unwrap().parse().unwrap();
    let size: u32 = json_field(&st, "stack_size").unwrap().parse().unwrap();
    assert_eq!(size, 24 * 1024);
    // Init is the deepest (≈ 8 KiB: the controller is built there); a quarter stays free.
    assert!(
        used > 1024 && used < size * 3 / 4,
        "this run's stack: {used} of {size}"
    );
}

#[test]
fn a_detached_probe_blocked_the_control_loop() {
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(PS_PER_S).unwrap();
    s.board.detach_probe();
    // A whole cycle with nothing reading the log: the RTT buffer fills and the firmware
    // must drop log frames, never wait.
    s.press_dock();
    let t = s.now() + 90 * PS_PER_S;
    s.run_until(t, |x| {
        x.machine().axis.step_timing().pulses_neg > 1000
            && !x.machine().axis.enabled()
            && x.machine().lock.fraction_locked() >= 1.0
            && x.machine().axis.pos_um() <= 0.0
    })
    .unwrap();
    s.run_for(PS_PER_S).unwrap();
    let w = json(&s.console_json("wear --json").unwrap());
    assert_eq!(w["cycles"], 1, "{w}");
    assert_eq!(s.machine().hx.stats().samples_missed, 0);
    assert_eq!(s.watchdog_resets(), 0);
}

/// Dock and stop `depth_um` into the insertion (the rod in the cone, the lock released).
fn dock_to_depth(s: &mut Session, depth_um: f64) {
    s.run_for(PS_PER_S).unwrap();
    s.press_dock();
    let target = s.engage_um as f64 + depth_um;
    let t = s.now() + 60 * PS_PER_S;
    let reached = s
        .run_until(t, |x| {
            x.machine().axis.pos_um() >= target && x.machine().lock.fraction_locked() <= 0.0
        })
        .unwrap();
    assert!(reached, "did not reach {depth_um} µm into the insertion");
}

fn load_distance_nmm(s: &mut Session) -> f64 {
    let w = json(&s.console_json("wear --json").unwrap());
    w["load_distance_nmm"].as_f64().expect("load_distance_nmm")
}

#[test]
fn a_reset_mid_insertion_lost_the_cycles_load_distance() {
    let mut s = Session::new(Options::new()).expect("board");
    dock_to_depth(&mut s, 10_000.0);
    // The flash holds nothing of this cycle yet (it is written at rest); the RAM
    // journal has it.
    s.board.reset_pin();
    s.run_for(2 * PS_PER_S).unwrap();
    assert_eq!(s.reset_causes(), vec!["power_on", "pin"]);
    assert!(
        logged(&s, "recovered from RAM"),
        "{:?}",
        s.board.log.iter().map(|l| &l.msg).collect::<Vec<_>>()
    );
    let ld = load_distance_nmm(&mut s);
    // Eq. 7 over the first 10 mm of the stroke: several hundred N·mm.
    assert!(ld > 100.0, "{ld} N·mm");
    // Written to flash at the first rest: a power cut now keeps it.
    s.board.power_on();
    s.run_for(2 * PS_PER_S).unwrap();
    assert_eq!(load_distance_nmm(&mut s), ld);
}

#[test]
fn a_power_cut_mid_insertion_loses_only_the_cycle_in_progress() {
    // SRAM does not survive a power cut: the journal is noise, refused by its checks,
    // and the board boots on the flash snapshot (the documented limit).
    let mut s = Session::new(Options::new()).expect("board");
    dock_to_depth(&mut s, 10_000.0);
    s.board.power_on();
    s.run_for(2 * PS_PER_S).unwrap();
    assert_eq!(load_distance_nmm(&mut s), 0.0);
    assert!(!logged(&s, "recovered from RAM"));
    let w = json(&s.console_json("wear --json").unwrap());
    assert_eq!(w["cycles"], 0);
}

#[test]
fn a_write_protected_odometer_was_retried_at_every_step() {
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(PS_PER_S).unwrap();
    // The odometer's sectors write-protected (a bad option byte): every program is a
    // WRPERR.
    for sector in [10, 11] {
        s.board.soc_mut().flash.write_protect(sector, true);
    }
    s.press_dock();
    let t = s.now() + 120 * PS_PER_S;
    let faulted = s
        .run_until(t, |x| x.seen.faults.iter().any(|f| f.kind == "storage"))
        .unwrap();
    assert!(faulted, "{:?}", s.seen.faults);
    assert!(logged(&s, "flash failed 3 times in a row"));
    s.run_for(2 * PS_PER_S).unwrap();
    let f = json(&s.console_json("faults --json").unwrap());
    assert_eq!(f["active"], "storage", "{f}");
    let w = json(&s.console_json("wear --json").unwrap());
    assert_eq!(w["cycles"], 1, "counted in RAM: {w}");
    assert!(!s.machine().axis.enabled() && !s.machine().lock.driven());
}
