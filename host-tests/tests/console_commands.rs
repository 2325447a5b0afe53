//! The technician console end to end: commands typed on the simulated serial link,
//! executed by the real console service against the real controller.

use docking_logic::odometer::kind;
use hil_sim::rig::{Rig, RigOptions};
use hil_sim::scene::{run, SceneOptions};
use serde_json::Value;

fn rig() -> Rig {
    let mut r = Rig::new(RigOptions::new(80));
    r.console_enabled = true;
    // Boot to idle.
    for _ in 0..hil_sim::rig::BOOT_TICKS {
        r.tick();
    }
    r
}

fn json(reply: &str) -> Value {
    assert_eq!(reply.matches("\r\n").count(), 1, "one line: {reply:?}");
    serde_json::from_str(reply.trim_end()).unwrap_or_else(|e| panic!("not JSON ({e}): {reply:?}"))
}

use host_tests::run_cycles;

/// Every key a text reply shows, with the keys of its `key …` object lines.
fn text_keys(text: &str) -> std::collections::BTreeSet<String> {
    let mut keys = std::collections::BTreeSet::new();
    for line in text.lines() {
        let mut words = line.split(' ');
        if let Some(first) = words.next() {
            match first.split_once('=') {
                Some((k, _)) => keys.insert(k.to_string()),
                None => keys.insert(first.to_string()), // an object's line: `resets a=1`
            };
        }
        for w in words {
            if let Some((k, _)) = w.split_once('=') {
                keys.insert(k.to_string());
            }
        }
    }
    keys
}

/// Every key of a JSON reply: the object's, its nested objects' and its records'.
fn json_keys(v: &Value, keys: &mut std::collections::BTreeSet<String>, top: bool) {
    if let Some(o) = v.as_object() {
        for (k, x) in o {
            // A list of records is named by its key in JSON and by its lines in text.
            if !(top && x.is_array()) {
                keys.insert(k.clone());
            }
            json_keys(x, keys, false);
        }
    } else if let Some(a) = v.as_array() {
        for x in a {
            json_keys(x, keys, false);
        }
    }
}

/// Issue 18: the text said `cycles=` and `in_estop=open` where the JSON said
/// `cycles_completed` and `in_estop_open`. Each report is now one field list rendered
/// both ways: the same keys, in text and in JSON.
#[test]
fn text_and_json_reports_name_every_field_the_same_way() {
    let mut r = rig();
    assert!(r.command("pin set 2468", 10).starts_with("ok"));
    assert!(r.command("maint 2468", 10).starts_with("ok"));
    let m = r.command("measure --baseline 25.993", 200);
    assert!(m.starts_with("ok"), "{m}");
    assert!(
        r.command("maint exit", 10).starts_with("ok"),
        "leave maintenance"
    );
    run_cycles(&mut r, 2);
    assert!(r.command("maint 2468", 10).starts_with("ok"));
    let m = r.command("measure 26.004", 200);
    assert!(m.starts_with("ok"), "{m}");
    for cmd in ["status", "wear", "faults", "measurements", "history"] {
        let text = r.command(cmd, 10);
        let j = json(&r.command(&format!("{cmd} --json"), 10));
        let mut jk = std::collections::BTreeSet::new();
        json_keys(&j, &mut jk, true);
        assert!(!jk.is_empty(), "{cmd}: {j}");
        assert_eq!(text_keys(&text), jk, "{cmd}:\n{text}\n{j}");
    }
}

#[test]
fn read_commands_in_text_and_json() {
    let mut r = rig();
    run_cycles(&mut r, 3);
    let v = r.command("version", 10);
    assert!(v.starts_with("docking-controller "), "{v}");
    assert_eq!(
        json(&r.command("version --json", 10))["name"],
        "docking-controller"
    );

    let s = r.command("status", 10);
    assert!(
        s.starts_with("state=idle phase=none force_n=")
            && s.contains(" cycles_completed=3 fault=none"),
        "{s}"
    );
    let s = json(&r.command("status --json", 10));
    assert_eq!(s["state"], "idle");
    assert_eq!(s["cycles_completed"], 3);
    assert!(s["fault"].is_null());

    let w = r.command("wear", 10);
    assert!(
        w.starts_with("cone=1 material=zqsn5-2 ")
            && w.contains(" cycles=3 load_distance_nmm=")
            && w.contains(" wear_mm=0.00"),
        "{w}"
    );
    let w = json(&r.command("wear --json", 10));
    assert_eq!(w["cycles"], 3);
    assert_eq!(w["level"], "ok");
    assert_eq!(w["lifetime_cycles"], 3);
    let wear_mm = w["wear_mm"].as_f64().unwrap();
    assert!(wear_mm > 0.005 && wear_mm < 0.01, "{wear_mm}");
    // The cone's total: three cycles of ≈ 8 087 N·mm each (Eq. 7 over the stroke).
    let ld = w["load_distance_nmm"].as_f64().unwrap();
    assert!((24_000.0..24_600.0).contains(&ld), "{ld}");
    assert!(w["remaining_cycles"].as_u64().unwrap() > 45_000);

    let h = r.command("history 2", 10);
    assert_eq!(h.lines().count(), 2, "{h}");
    assert!(
        h.starts_with("cycle=3 cone=1 cone_cycle=3 load_distance_nmm=80"),
        "{h}"
    );
    let h = json(&r.command("history --json", 10));
    let arr = h["history"].as_array().unwrap();
    assert_eq!(arr.len(), 3);
    assert_eq!(arr[0]["cycle"], 3);
    let w_nmm = arr[0]["load_distance_nmm"].as_f64().unwrap();
    assert!((w_nmm - 8085.46).abs() / 8085.46 < 0.01, "{w_nmm}");

    let f = json(&r.command("faults --json", 10));
    assert!(f["active"].is_null());
    assert_eq!(f["faults"].as_array().unwrap().len(), 0);
    assert!(r
        .command("help", 10)
        .contains("cone replace <material> <serial>"));
}

#[test]
fn bad_input_gets_one_line_errors_and_changes_nothing() {
    let mut r = rig();
    // Everything but the lifetime peak force (which rises with sensor noise while idle).
    let counters = |r: &mut Rig| {
        let mut v = json(&r.command("wear --json", 10));
        v.as_object_mut().unwrap().remove("peak_force_n");
        v
    };
    let before = counters(&mut r);
    for bad in [
        "frobnicate",
        "history 0",
        "history 101",
        "wear --xml",
        "status extra",
        "cone replace unobtainium SN1",
        "measure 26.0001",
    ] {
        let e = r.command(bad, 10);
        assert!(
            e.starts_with("error: ") && e.matches("\r\n").count() == 1,
            "{bad:?} -> {e:?}"
        );
    }
    // Binary junk, control characters, an overlong line.
    r.term
        .send(&[0xFF, 0xFE, b'\r', b'\n', 0x01, b'x', b'\r', b'\n']);
    // 300 bytes at line rate (a burst of 300 would overrun the 256-byte UART ring).
    r.term.send(&[b'a'; 200]);
    for _ in 0..10 {
        r.tick();
    }
    r.term.send(&[b'a'; 100]);
    let e = r.command("", 50);
    assert!(e.contains("error: "), "{e:?}");
    assert_eq!(counters(&mut r), before, "no state change");
}

#[test]
fn state_changing_commands_need_maintenance_and_a_machine_at_rest() {
    let mut r = rig();
    run_cycles(&mut r, 1);
    // Commissioning: no PIN yet, so `pin set` is allowed once without maintenance.
    assert!(r
        .command("cone replace qsn6-6-3 SN-2", 10)
        .contains("maintenance mode required"));
    assert!(r.command("pin set 2468", 10).starts_with("ok: PIN set"));
    assert!(
        r.command("pin set 1111", 10)
            .contains("maintenance mode required"),
        "a PIN exists now"
    );
    // Wrong PIN ×5 → locked out, even the right one.
    for _ in 0..4 {
        assert!(r.command("maint 0000", 10).starts_with("error: "));
    }
    let e = r.command("maint 0000", 10);
    assert!(e.contains("locked"), "{e}");
    assert!(r.command("maint 2468", 10).contains("locked"));

    // A fresh machine on the same flash (reboot clears the RAM lockout; the PIN stays).
    let flash = r.flash.clone();
    let mut r = Rig::with_flash(RigOptions::new(80), flash);
    r.console_enabled = true;
    for _ in 0..100 {
        r.tick();
    }
    assert!(r
        .command("maint 2468", 10)
        .starts_with("ok: maintenance mode"));
    let w0 = json(&r.command("wear --json", 10));
    assert_eq!(w0["lifetime_cycles"], 1);
    let ok = r.command("cone replace qsn6-6-3 SN-2", 10);
    assert!(
        ok.starts_with("ok: cone 2 installed (qsn6-6-3, serial SN-2)"),
        "{ok}"
    );
    let w = json(&r.command("wear --json", 10));
    assert_eq!(
        (
            w["cone"].as_u64(),
            w["cycles"].as_u64(),
            w["material"].as_str()
        ),
        (Some(2), Some(0), Some("qsn6-6-3"))
    );
    assert_eq!(
        w["lifetime_cycles"], 1,
        "lifetime totals survive a cone replacement"
    );
    // The wear is the bore's growth, not halved (`docs/physics.md` §7); with no baseline
    // measured, from the nominal 26.000 mm, and the reply says so.
    let m = r.command("measure 26.050", 10);
    assert!(
        m.starts_with(
            "ok: bore_mm=26.050 cone_cycle=0 measured_wear_mm=0.050000 model_wear_mm=0.000000"
        ) && m.contains("baseline_assumed=yes"),
        "{m}"
    );
    assert!(r.command("clear-fault", 10).contains("no fault to clear"));
    // Refused while moving.
    use docking_logic::sequencer::{Request, State};
    r.ctrl.request(Request::StartCycle);
    for _ in 0..400 {
        r.tick();
        if matches!(r.ctrl.state(), State::Inserting { .. }) {
            break;
        }
    }
    assert!(matches!(r.ctrl.state(), State::Inserting { .. }));
    assert!(r
        .command("cone replace zqsn5-2 SN-3", 1)
        .contains("refused while a docking is moving"));
    assert!(r
        .command("calibrate tare", 1)
        .contains("refused while a docking is moving"));
    // History survived the replacement: the old cone's cycle is still there.
    let h = json(&r.command("history --json", 1));
    assert_eq!(h["history"][0]["cone"], 1);
}

#[test]
fn clear_fault_recovers_and_is_audited() {
    let mut r = rig();
    assert!(r.command("pin set 1357", 10).starts_with("ok"));
    assert!(r.command("maint 1357", 10).starts_with("ok"));
    r.hx.set_fault(hil_sim::hx711::Hx711Fault::Disconnected);
    for _ in 0..20 {
        r.tick();
    }
    let f = json(&r.command("faults --json", 10));
    assert_eq!(f["active"], "sensor_disconnected");
    r.hx.set_fault(hil_sim::hx711::Hx711Fault::None);
    assert!(r
        .command("clear-fault", 10)
        .starts_with("ok: fault cleared"));
    for _ in 0..400 {
        r.tick();
    }
    assert_eq!(json(&r.command("status --json", 10))["state"], "idle");
    let mut audits = 0;
    r.ctrl
        .records(docking_logic::odometer::kind::AUDIT, 10, |_| audits += 1);
    assert_eq!(audits, 2, "pin set and clear-fault are audited");
}

#[test]
fn calibration_tare_and_span_persist() {
    let mut r = rig();
    assert!(r.command("pin set 9999", 10).starts_with("ok"));
    assert!(r.command("maint 9999", 10).starts_with("ok"));
    for _ in 0..20 {
        r.tick();
    }
    let t = r.command("calibrate tare", 10);
    assert!(t.starts_with("ok: tare offset_counts="), "{t}");
    // Hang a known 100 N on the idle cell.
    r.script.borrow_mut().offset_n = 100.0;
    for _ in 0..20 {
        r.tick();
    }
    let s = r.command("calibrate span 100.000", 10);
    assert!(s.starts_with("ok: span set"), "{s}");
    let force = json(&r.command("status --json", 10))["force_n"]
        .as_f64()
        .unwrap();
    assert!((force - 100.0).abs() < 1.0, "{force}");
    // It survives a reboot.
    let cal = r.ctrl.calibration();
    let r2 = Rig::with_flash(RigOptions::new(80), r.flash.clone());
    assert_eq!(r2.ctrl.calibration(), cal);
}

#[test]
fn console_flood_does_not_delay_the_overload_stop() {
    for rate in [10, 80] {
        let opts = SceneOptions {
            seed: 3,
            ..SceneOptions::new(rate)
        };
        let quiet = run("overload", opts).unwrap();
        let flooded = hil_sim::scene::run_with_console_flood("overload", opts).unwrap();
        assert!(
            flooded.console_bytes > 10_000,
            "the console was flooded: {}",
            flooded.console_bytes
        );
        assert_eq!(flooded.report.faults.len(), 1);
        assert_eq!(
            flooded.report.stop_latency_s, quiet.stop_latency_s,
            "stop latency unchanged at {rate} SPS"
        );
        assert!(flooded.report.stop_latency_s.unwrap() <= 1.0 / rate as f64);
    }
}

#[test]
fn dock_undock_stop_from_the_console_with_their_gates() {
    use docking_logic::sequencer::State;
    let mut r = rig();
    assert!(r.command("pin set 1357", 10).starts_with("ok"));
    // dock and undock need maintenance mode; stop never does.
    assert!(r.command("dock", 10).contains("maintenance mode required"));
    assert!(r.command("maint 1357", 10).starts_with("ok"));
    assert!(r.command("undock", 10).contains("nothing to undock"));
    assert!(r.command("home", 10).contains("already homed"));
    assert!(r.command("dock", 10).starts_with("ok: docking"), "dock");
    let mut held = false;
    for _ in 0..6_000 {
        r.tick();
        if r.ctrl.handshake().mated {
            held = true;
            break;
        }
    }
    assert!(held, "mated");
    assert!(r.command("dock", 10).contains("refused"), "already docking");
    let s = json(&r.command("status --json", 10));
    assert_eq!(
        (s["out_mated"].as_bool(), s["out_ready"].as_bool()),
        (Some(true), Some(false))
    );
    let t = r.command("status", 10);
    assert!(
        t.contains(" in_estop_open=no out_ready=no out_mated=yes"),
        "{t}"
    );
    // Undock runs while the machine is not at rest.
    assert!(r.command("undock", 10).starts_with("ok: undocking"));
    for _ in 0..6_000 {
        r.tick();
        if r.ctrl.state() == State::Idle {
            break;
        }
    }
    assert_eq!(r.ctrl.odometer().lifetime().cycles, 1);
    // Stop without maintenance mode, mid-docking: latched `stopped`.
    assert!(r.command("maint exit", 10).starts_with("ok"));
    r.ctrl
        .command(docking_logic::sequencer::Request::Dock)
        .unwrap();
    for _ in 0..200 {
        r.tick();
    }
    assert!(r.command("stop", 10).starts_with("ok: stopped"));
    r.tick();
    assert_eq!(
        json(&r.command("faults --json", 10))["active"],
        "stopped",
        "latched"
    );
    assert!(!r.axis.enabled() && !r.lock.driven(), "all motion off");
    let s = json(&r.command("status --json", 10));
    assert_eq!(s["out_fault"], true);
}

#[test]
fn modbus_settings_are_stored_checked_and_shown() {
    let mut r = rig();
    assert!(r
        .command("modbus", 10)
        .starts_with("modbus unit=1 baud=19200 format=8E1"));
    assert!(r.command("pin set 1357", 10).starts_with("ok"));
    assert!(r
        .command("modbus 7 38400", 10)
        .contains("maintenance mode required"));
    assert!(r.command("maint 1357", 10).starts_with("ok"));
    for bad in [
        "modbus 0 19200",
        "modbus 248 19200",
        "modbus 7 19201",
        "modbus 7",
        "modbus x 9600",
    ] {
        let e = r.command(bad, 10);
        assert!(e.starts_with("error: "), "{bad}: {e}");
    }
    assert!(r
        .command("modbus 7 38400", 10)
        .starts_with("ok: Modbus settings stored"));
    assert!(r
        .command("modbus", 10)
        .starts_with("modbus unit=7 baud=38400"));
    // Stored: a reboot on the same flash reads them back.
    let flash = r.flash.clone();
    let mut r = Rig::with_flash(RigOptions::new(80), flash);
    r.console_enabled = true;
    let m = r.command("modbus", 100);
    assert!(m.starts_with("modbus unit=7 baud=38400"), "{m:?}");
}

/// Defect (issue 17, item 5): `store_record` asked only `is_quiet()`, which included
/// the pulled-while-mated fault where the axis is driven, holding the vehicle; the
/// clear-fault audit record was programmed (and a sector move erased, every interrupt
/// masked for up to 2 s) with the driver energised. Now it waits for the rest.
#[test]
fn audit_record_waits_for_rest_while_the_axis_is_held() {
    use docking_logic::odometer::kind::AUDIT;
    use docking_logic::sequencer::{FaultKind, State};
    let mut r = rig();
    assert!(r.command("pin set 1357", 10).starts_with("ok"));
    assert!(r.command("maint 1357", 10).starts_with("ok"));
    r.ctrl
        .command(docking_logic::sequencer::Request::Dock)
        .unwrap();
    assert!(host_tests::run_until(&mut r, 6_000, |r| r
        .ctrl
        .handshake()
        .mated));
    r.script.borrow_mut().pull_n_per_s = 200.0;
    let held = State::Faulted {
        fault: FaultKind::HoldForce,
    };
    assert!(host_tests::run_until(&mut r, 400, |r| r.ctrl.state() == held));
    r.script.borrow_mut().pull_n_per_s = 0.0;
    assert!(r.axis.enabled(), "the axis holds the vehicle, driven");
    assert!(!r.ctrl.at_rest());
    let audits = |r: &mut Rig| r.ctrl.records(AUDIT, 10, |_| {});
    let before = audits(&mut r);
    assert!(
        r.ctrl.store_record(AUDIT, &[1; 8]).is_err(),
        "no record while held"
    );
    assert!(r.command("clear-fault", 1).starts_with("ok: fault cleared"));
    assert_eq!(
        audits(&mut r),
        before,
        "not written while the axis is driven"
    );
    assert_eq!(r.ctrl.records_queued(), 1);
    let f = json(&r.command("faults --json", 1));
    assert_eq!(
        (f["records_queued"].as_u64(), f["records_dropped"].as_u64()),
        (Some(1), Some(0)),
        "{f}"
    );
    assert!(host_tests::run_until(&mut r, 8_000, |r| r.ctrl.state() == State::Idle));
    r.tick();
    assert_eq!(r.ctrl.records_queued(), 0);
    assert_eq!(audits(&mut r), before + 1, "written at the rest");
}

/// Defect (issue 17, item 8): the firmware programmed the BOR option bytes by itself at
/// its first boot (BOR still off, the supply possibly ramping) and judged success by
/// re-reading OPTCR only. Now boot only reads the level; `bor set` programs it, in
/// maintenance mode at rest, audited, and a failure says so.
#[test]
fn bor_is_programmed_only_by_an_explicit_maintenance_step() {
    let mut r = rig();
    assert_eq!(r.options.bor.get(), 0, "boot left the option bytes alone");
    assert!(r.command("bor", 10).contains("level=0"));
    assert!(r
        .command("bor set", 10)
        .contains("maintenance mode required"));
    assert!(r.command("pin set 1357", 10).starts_with("ok"));
    assert!(r.command("maint 1357", 10).starts_with("ok"));
    r.options.locked.set(true);
    assert!(r
        .command("bor set", 10)
        .starts_with("error: the option bytes"));
    assert_eq!(r.options.bor.get(), 0);
    r.options.locked.set(false);
    let mut audits = 0;
    r.ctrl
        .records(docking_logic::odometer::kind::AUDIT, 10, |_| audits += 1);
    assert!(r.command("bor set", 10).starts_with("ok: BOR level 3"));
    assert_eq!(r.options.bor.get(), 3);
    let mut after = 0;
    r.ctrl
        .records(docking_logic::odometer::kind::AUDIT, 10, |_| after += 1);
    assert_eq!(after, audits + 1, "audited");
    assert!(r.command("bor", 10).contains("level=3 (2.70 V)"));
    assert!(r.command("bor set", 10).contains("set already"));
}

/// A console command holds the controller on the board (idle's lock, which the control
/// step waits for): it must not walk the flash log then. Every command looked up the
/// PIN record in flash (a walk of the log) to decide its gate, and `modbus` the stored
/// settings; both now come from RAM.
#[test]
fn console_commands_read_no_flash_under_the_controller() {
    let mut r = rig();
    run_cycles(&mut r, 2);
    // A PIN and Modbus settings stored, so the lookups find something.
    r.command("pin set 2468", 10);
    r.command("maint 2468", 10);
    r.command("modbus 7 19200", 10);
    r.command("maint exit", 10);
    for _ in 0..20 {
        r.tick();
    }
    let reads = |r: &Rig| r.flash.with(|f| f.read_calls());
    let before = reads(&r);
    for cmd in [
        "status",
        "status --json",
        "wear --json",
        "faults",
        "history 5",
        "measurements",
        "modbus",
        "help",
        "version",
        "dock",
        "maint 1111",
        "pin set 1357",
    ] {
        let reply = r.command(cmd, 10);
        assert!(!reply.is_empty(), "{cmd}: no reply");
    }
    assert_eq!(reads(&r) - before, 0, "flash reads while serving commands");
    // And the cached records are the stored ones.
    assert!(r
        .command("modbus", 10)
        .starts_with("modbus unit=7 baud=19200"));
    r.command("maint 2468", 10);
    assert!(r.command("status", 10).contains("maintenance=yes"));
}

/// Defect (found by the virtual board's control-entry latency): `pin set` hashed the
/// new PIN (257 SHA-256 compressions, ~650 k instructions) while holding the
/// controller, delaying the control step by 5–18 ms. The hash now runs in `finish`,
/// without it, and the record is stored in a fourth phase, `store`.
#[test]
fn pin_set_hashes_without_the_controller() {
    let mut r = rig();
    let now_ms = r.clock.now_ns() / 1_000_000;
    let mut buf = [0u8; 64];
    // With the controller: no hash, nothing stored yet.
    let hashes = r.console.run_line(&mut r.ctrl, "pin set 2468", now_ms);
    assert_eq!(hashes, 0);
    assert!(r.ctrl.load_record(kind::PIN, &mut buf).is_none());
    // Without it: the hash.
    assert_eq!(r.console.finish(now_ms), 1);
    assert!(r.console.store_due());
    // With it again: the store.
    r.console.store(&mut r.ctrl, now_ms);
    assert!(!r.console.store_due());
    assert!(r.ctrl.load_record(kind::PIN, &mut buf).is_some());
    assert!(r
        .command("maint 2468", 10)
        .starts_with("ok: maintenance mode"));
}

/// A bore read below the cone's baseline is reported as such (a worn bore only grows:
/// the reading or the baseline is wrong), not as a plain negative wear.
#[test]
fn a_bore_below_its_baseline_is_reported_as_such() {
    let mut r = rig();
    assert!(r.command("pin set 2468", 10).starts_with("ok"));
    assert!(r.command("maint 2468", 10).starts_with("ok"));
    assert!(r.command("measure --baseline 26.010", 10).starts_with("ok"));
    let ok = r.command("measure 26.015", 10);
    assert!(
        ok.starts_with("ok:") && !ok.contains("below_baseline"),
        "{ok}"
    );
    let low = r.command("measure 26.002", 10);
    assert!(
        low.contains(" measured_wear_mm=-0.008000")
            && low.contains(" below_baseline=yes (the bore reads smaller than the cone's baseline"),
        "{low}"
    );
}
