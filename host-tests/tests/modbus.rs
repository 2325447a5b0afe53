//! The Modbus RTU server against the real controller on the host rig: device
//! identification, the register map, exceptions, commands and their gates, broadcast,
//! the framer's timing, and fuzzing.
//!
//! Every reply is checked by `check_reply` with a CRC written here independently of the
//! library's. The properties feed arbitrary frames — random bytes, and random PDUs with
//! a valid CRC (a wrong CRC would hide everything behind it) — to controllers in several
//! states (idle, faulted, inserting, uncalibrated, power-up, E-STOP open), and byte
//! streams with random gaps to a `Server`; they check that nothing panics, that a reply
//! is none or a well-formed frame answering the request (its function or function |
//! 0x80), and that reads change nothing (an idle rig that only ever sees reads is stepped
//! after each one: it must stay idle, with the same counters). 256 cases each in
//! `cargo test`; `fuzz_modbus_million` runs 1,000,000 cases by hand:
//!
//! ```text
//! cargo test --release -p host-tests --test modbus -- --ignored
//! ```
//!
//! `corpus_frames_keep_invariants` replays every file of `fuzz-corpus/modbus/` (one raw
//! frame per file, CRC included) through both `handle_frame` and a `Server`.

use std::cell::RefCell;

use docking_logic::controller::{FaultRecord, Status};
use docking_logic::material::Material;
use docking_logic::modbus::{
    handle_frame, ir, status, Command, ModbusSettings, Server, BROADCAST, MAX_FRAME,
};
use docking_logic::odometer::{Cone, Lifetime, WearLevel};
use docking_logic::sequencer::{FaultKind, Request, State};
use hil_sim::rig::{Rig, RigOptions};
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;

const UNIT: u8 = 1;
const SERIAL: &str = "DC407-000123";

// ---------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------

/// CRC-16/MODBUS, bit by bit as the serial line spec describes it (not the library's).
fn crc_ref(data: &[u8]) -> [u8; 2] {
    let mut crc: u16 = 0xFFFF;
    for &b in data {
        crc ^= u16::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
        }
    }
    crc.to_le_bytes()
}

fn crc_ok(frame: &[u8]) -> bool {
    frame.len() >= 2 && crc_ref(&frame[..frame.len() - 2]) == frame[frame.len() - 2..]
}

fn frame(unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut f = vec![unit];
    f.extend_from_slice(pdu);
    let c = crc_ref(&f);
    f.extend_from_slice(&c);
    f
}

fn be(hi_lo: &[u8]) -> u16 {
    u16::from_be_bytes([hi_lo[0], hi_lo[1]])
}

fn pdu(fc: u8, a: u16, b: u16) -> Vec<u8> {
    let mut p = vec![fc];
    p.extend_from_slice(&a.to_be_bytes());
    p.extend_from_slice(&b.to_be_bytes());
    p
}

/// A reply to `request` as unit [`UNIT`] is well formed: valid CRC, our address, the
/// request's function (or | 0x80 with an exception code 1–4), and a body that matches
/// the request. `Err` says why not.
fn check_reply(request: &[u8], reply: &[u8]) -> Result<(), String> {
    if !crc_ok(request) || request.len() < 4 || request.len() > MAX_FRAME {
        return Err("a reply to a frame with a bad CRC or length".into());
    }
    if request[0] != UNIT {
        return Err(format!("a reply to unit {}", request[0]));
    }
    if reply.len() < 5 || reply.len() > MAX_FRAME || !crc_ok(reply) {
        return Err(format!("bad reply frame {reply:02x?}"));
    }
    if reply[0] != UNIT {
        return Err(format!("reply from unit {}", reply[0]));
    }
    let (fc, rfc) = (request[1], reply[1]);
    let body = &reply[2..reply.len() - 2];
    let req = &request[2..request.len() - 2];
    if rfc & 0x80 != 0 {
        if rfc != fc | 0x80 {
            return Err(format!("exception {rfc:#x} to function {fc:#x}"));
        }
        if body.len() != 1 || !(1..=4).contains(&body[0]) {
            return Err(format!("exception body {body:02x?}"));
        }
        return Ok(());
    }
    if rfc != fc {
        return Err(format!("function {rfc:#x} answers {fc:#x}"));
    }
    match fc {
        0x01..=0x04 => {
            if req.len() != 4 {
                return Err(format!("a normal reply to a malformed read {req:02x?}"));
            }
            let qty = usize::from(be(&req[2..4]));
            let bytes = if fc <= 2 { qty.div_ceil(8) } else { 2 * qty };
            if body.len() != 1 + bytes || usize::from(body[0]) != bytes {
                return Err(format!("read reply {body:02x?} to {req:02x?}"));
            }
        }
        0x05 | 0x06 | 0x0F | 0x10 => {
            let well_formed = if fc <= 0x06 {
                req.len() == 4
            } else {
                req.len() >= 5 && req.len() == 5 + usize::from(req[4])
            };
            if !well_formed {
                return Err(format!("a normal reply to a malformed write {req:02x?}"));
            }
            if body.len() != 4 || body != &req[..4] {
                return Err(format!("write reply {body:02x?} to {req:02x?}"));
            }
        }
        0x2B => {
            let [mei, code, conformity, more, next, count, ref objs @ ..] = *body else {
                return Err(format!("short 0x2B reply {body:02x?}"));
            };
            if req.len() != 3
                || mei != 0x0E
                || Some(&code) != req.get(1)
                || conformity != 0x83
                || !matches!(more, 0 | 0xFF)
            {
                return Err(format!("0x2B header {body:02x?}"));
            }
            if more == 0 && next != 0 {
                return Err("next object without more follows".into());
            }
            let mut rest = objs;
            for _ in 0..count {
                let [_, len, ref tail @ ..] = *rest else {
                    return Err("object list truncated".into());
                };
                if tail.len() < usize::from(len) {
                    return Err("object value truncated".into());
                }
                rest = &tail[usize::from(len)..];
            }
            if !rest.is_empty() {
                return Err("bytes after the objects".into());
            }
        }
        _ => return Err(format!("a normal reply to function {fc:#x}")),
    }
    Ok(())
}

/// Send `pdu` to `unit` through `handle_frame`; the checked reply.
fn ask(r: &mut Rig, unit: u8, pdu: &[u8]) -> Option<Vec<u8>> {
    let f = frame(unit, pdu);
    let mut out = [0u8; MAX_FRAME];
    let n = handle_frame(&f, UNIT, &mut r.ctrl, SERIAL, &mut out)?;
    let reply = out[..n].to_vec();
    if let Err(e) = check_reply(&f, &reply) {
        panic!("{pdu:02x?}: {e}");
    }
    Some(reply)
}

/// The reply's PDU (address and CRC stripped); `Err(code)` for an exception.
fn call(r: &mut Rig, pdu: &[u8]) -> Result<Vec<u8>, u8> {
    let reply = ask(r, UNIT, pdu).unwrap_or_else(|| panic!("no reply to {pdu:02x?}"));
    if reply[1] & 0x80 != 0 {
        Err(reply[2])
    } else {
        Ok(reply[1..reply.len() - 2].to_vec())
    }
}

fn exception(r: &mut Rig, pdu: &[u8]) -> u8 {
    match call(r, pdu) {
        Err(code) => code,
        Ok(p) => panic!("{pdu:02x?} answered {p:02x?}"),
    }
}

fn read_inputs(r: &mut Rig, addr: u16, qty: u16) -> Result<Vec<u16>, u8> {
    let p = call(r, &pdu(0x04, addr, qty))?;
    Ok(p[2..].chunks(2).map(be).collect())
}

fn coil(r: &mut Rig, c: Command, on: bool) -> Result<(), u8> {
    call(r, &pdu(0x05, c.coil(), if on { 0xFF00 } else { 0 })).map(|_| ())
}

fn u32_at(regs: &[u16], addr: u16) -> u32 {
    let a = usize::from(addr);
    u32::from(regs[a]) << 16 | u32::from(regs[a + 1])
}

fn dn(mn: i32) -> i16 {
    ((f64::from(mn) / 100.0).round() as i64).clamp(-32_768, 32_767) as i16
}

fn rig_with(opts: RigOptions) -> Rig {
    Rig::booted(opts)
}

fn rig() -> Rig {
    rig_with(RigOptions::new(80))
}

use host_tests::run_until;

use host_tests::run_cycles;

/// What a read must not change.
#[derive(Debug, PartialEq)]
struct Snap {
    status: Status,
    cone: Cone,
    life: Lifetime,
    faults: u32,
    trips: u32,
    records: Vec<FaultRecord>,
    calibrated: bool,
    level: WearLevel,
}

fn snap(r: &Rig) -> Snap {
    let c = &r.ctrl;
    Snap {
        status: c.status(),
        cone: *c.odometer().cone(),
        life: *c.odometer().lifetime(),
        faults: c.fault_count(),
        trips: c.overload_trips(),
        records: c.faults().copied().collect(),
        calibrated: c.calibrated(),
        level: c.wear_level(),
    }
}

/// A request over the line: bytes one character apart from `*t_us`, then polls every
/// 100 µs until the server answers or 5 ms pass.
fn transact(r: &mut Rig, srv: &mut Server, t_us: &mut u64, bytes: &[u8]) -> Option<Vec<u8>> {
    let c = u64::from(srv.settings().char_us());
    for &b in bytes {
        *t_us += c;
        srv.on_byte(b, *t_us);
    }
    let end = *t_us;
    let t35 = u64::from(srv.settings().t3_5_us());
    let mut reply = None;
    while *t_us < end + 5_000 {
        *t_us += 100;
        if let Some(x) = srv.poll(*t_us, &mut r.ctrl, SERIAL) {
            assert!(*t_us - end >= t35, "answered before t3.5");
            reply = Some(x.to_vec());
            break;
        }
    }
    *t_us += 5_000;
    reply
}

// ---------------------------------------------------------------------------------
// Device identification
// ---------------------------------------------------------------------------------

/// The objects of a 0x2B reply: (more follows, next id, [(id, value)]).
fn objects(reply: &[u8]) -> (u8, u8, Vec<(u8, String)>) {
    let body = &reply[2..reply.len() - 2];
    let mut rest = &body[6..];
    let mut objs = Vec::new();
    for _ in 0..body[5] {
        let (id, len) = (rest[0], usize::from(rest[1]));
        objs.push((id, String::from_utf8(rest[2..2 + len].to_vec()).unwrap()));
        rest = &rest[2 + len..];
    }
    (body[3], body[4], objs)
}

fn package_version() -> &'static str {
    // The firmware package's version, from its manifest (not from the library).
    let manifest = include_str!("../../Cargo.toml");
    let pkg = &manifest[manifest.find("[package]").unwrap()..];
    let line = pkg.lines().find(|l| l.starts_with("version")).unwrap();
    line.split('"').nth(1).unwrap()
}

#[test]
fn device_identification_basic_regular_extended_and_individual() {
    let mut r = rig();
    let version = package_version();
    let basic = ask(&mut r, UNIT, &[0x2B, 0x0E, 0x01, 0x00]).unwrap();
    let (more, _, objs) = objects(&basic);
    assert_eq!(more, 0);
    let ids: Vec<u8> = objs.iter().map(|o| o.0).collect();
    assert_eq!(ids, [0, 1, 2]);
    assert!(!objs[0].1.is_empty(), "vendor");
    assert_eq!(objs[1].1, "docking-controller");
    assert_eq!(objs[2].1, version);

    let regular = ask(&mut r, UNIT, &[0x2B, 0x0E, 0x02, 0x00]).unwrap();
    let (_, _, objs) = objects(&regular);
    let ids: Vec<u8> = objs.iter().map(|o| o.0).collect();
    assert_eq!(ids, [0, 1, 2, 4, 5]);
    assert!(objs[3].1.contains("docking controller"), "{objs:?}");
    assert_eq!(objs[4].1, "STM32F407");

    let extended = ask(&mut r, UNIT, &[0x2B, 0x0E, 0x03, 0x00]).unwrap();
    let (_, _, objs) = objects(&extended);
    // The serial, then the images (issue 21; the trial, issue 31): the simulator has
    // no image header and runs no trial.
    assert_eq!(
        objs[objs.len() - 5..],
        [
            (0x80, SERIAL.to_owned()),
            (0x81, "none".to_owned()),
            (0x82, "unknown".to_owned()),
            (0x83, "no".to_owned()),
            (0x84, "no".to_owned())
        ]
    );

    // A stream from a given object; from one that does not exist: from the start.
    let (_, _, objs) = objects(&ask(&mut r, UNIT, &[0x2B, 0x0E, 0x02, 0x02]).unwrap());
    assert_eq!(objs.iter().map(|o| o.0).collect::<Vec<_>>(), [2, 4, 5]);
    let (_, _, objs) = objects(&ask(&mut r, UNIT, &[0x2B, 0x0E, 0x01, 0x42]).unwrap());
    assert_eq!(objs.iter().map(|o| o.0).collect::<Vec<_>>(), [0, 1, 2]);

    // Individual access: the serial, the revision; an unknown object is exception 2.
    let (_, _, objs) = objects(&ask(&mut r, UNIT, &[0x2B, 0x0E, 0x04, 0x80]).unwrap());
    assert_eq!(objs, [(0x80, SERIAL.to_owned())]);
    let (_, _, objs) = objects(&ask(&mut r, UNIT, &[0x2B, 0x0E, 0x04, 0x02]).unwrap());
    assert_eq!(objs, [(0x02, version.to_owned())]);
    for obj in [0x03, 0x06, 0x7F, 0x85, 0xFF] {
        assert_eq!(exception(&mut r, &[0x2B, 0x0E, 0x04, obj]), 2, "{obj:#x}");
    }
    // Bad read device id code: 3; another MEI type: 1; wrong length: 3.
    for code in [0x00, 0x05, 0xFF] {
        assert_eq!(exception(&mut r, &[0x2B, 0x0E, code, 0x00]), 3, "{code:#x}");
    }
    assert_eq!(exception(&mut r, &[0x2B, 0x0D, 0x01, 0x00]), 1);
    assert_eq!(exception(&mut r, &[0x2B, 0x0E, 0x01]), 3);
    assert_eq!(exception(&mut r, &[0x2B, 0x0E, 0x01, 0x00, 0x00]), 3);
    assert_eq!(exception(&mut r, &[0x2B]), 3);
    // Broadcast: never a reply.
    assert_eq!(ask(&mut r, BROADCAST, &[0x2B, 0x0E, 0x01, 0x00]), None);
}

#[test]
fn a_long_serial_is_cut_to_32_bytes() {
    let mut r = rig();
    let long = "S".repeat(300);
    let f = frame(UNIT, &[0x2B, 0x0E, 0x04, 0x80]);
    let mut out = [0u8; MAX_FRAME];
    let n = handle_frame(&f, UNIT, &mut r.ctrl, &long, &mut out).unwrap();
    check_reply(&f, &out[..n]).unwrap();
    let (_, _, objs) = objects(&out[..n]);
    assert_eq!(objs[0].1.len(), 32);
}

// ---------------------------------------------------------------------------------
// Register map
// ---------------------------------------------------------------------------------

#[test]
fn input_registers_match_status_and_odometer() {
    let mut r = rig();
    r.ctrl
        .replace_cone(Material::QSn6_6_3, "SN-0042_x")
        .unwrap();
    run_cycles(&mut r, 2);
    // A latched fault (stop), so that the fault registers say something.
    coil(&mut r, Command::Stop, true).unwrap();
    assert!(run_until(&mut r, 10, |r| matches!(
        r.ctrl.state(),
        State::Faulted { .. }
    )));
    for _ in 0..3 {
        r.tick();
    }

    let regs = read_inputs(&mut r, 0, ir::COUNT).unwrap();
    assert_eq!(regs.len(), usize::from(ir::COUNT));
    let s = r.ctrl.status();
    let h = s.handshake;
    let odo = r.ctrl.odometer();
    let mut word = 0u16;
    for (on, bit) in [
        (h.ready, 0),
        (h.mated, 1),
        (s.state.is_moving(), 2),
        (h.fault, 3),
        (s.warning, 4),
        (h.maintenance, 5),
        (r.ctrl.calibrated(), 6),
        (h.estop, 7),
        (h.dock, 8),
        (s.wear_level == WearLevel::Limit, 9),
        (s.state.is_docking(), 10),
    ] {
        word |= u16::from(on) << bit;
    }
    assert_eq!(regs[0], word, "status word");
    assert_eq!(regs[0] & status::FAULT, status::FAULT);
    assert_eq!(regs[0] & (status::READY | status::MOVING), 0);
    assert_ne!(regs[0] & status::CALIBRATED, 0);
    assert_eq!(regs[usize::from(ir::STATE)], 11, "faulted");
    assert_eq!(regs[usize::from(ir::PHASE)], 0);
    assert_eq!(regs[usize::from(ir::FORCE)] as i16, dn(s.force_mn));
    assert_eq!(regs[usize::from(ir::FORCE_LIMIT)] as i16, dn(s.limit_mn));
    assert_eq!(
        regs[usize::from(ir::POSITION)] as i16,
        (f64::from(s.pos_um) / 10.0).round() as i16
    );
    assert_eq!(
        regs[usize::from(ir::ACTIVE_FAULT)],
        u16::from(FaultKind::Stopped.code())
    );
    assert_eq!(
        regs[usize::from(ir::PEAK_FORCE)] as i16,
        dn(s.peak_force_mn)
    );
    assert!(
        dn(s.peak_force_mn) > 2_000,
        "two cycles went through phase 4"
    );
    assert_eq!(u32_at(&regs, ir::LIFETIME_CYCLES), odo.lifetime().cycles);
    assert_eq!(odo.lifetime().cycles, 2);
    assert_eq!(u32_at(&regs, ir::CONE_CYCLES), odo.cone().cycles);
    assert_eq!(u32_at(&regs, ir::WEAR_NM), odo.wear_nm());
    assert!(odo.wear_nm() > 0);
    assert_eq!(
        u32::from(regs[usize::from(ir::WEAR_UM)]),
        odo.wear_nm() / 1000
    );
    assert_eq!(regs[usize::from(ir::WEAR_LEVEL)], 0);
    assert_eq!(u32_at(&regs, ir::REMAINING_CYCLES), odo.remaining_cycles());
    assert_eq!(
        u64::from(regs[usize::from(ir::WEAR_PERMILLE)]),
        u64::from(odo.wear_nm()) * 1000 / u64::from(odo.config().limit_nm)
    );
    assert_eq!(regs[usize::from(ir::WEAR_LIMIT_UM)], 800);
    assert_eq!(
        u32_at(&regs, ir::OVERLOAD_EVENTS),
        odo.lifetime().overload_events
    );
    assert_eq!(u32_at(&regs, ir::FAULTS_LIFETIME), odo.lifetime().faults);
    assert_eq!(u32_at(&regs, ir::FAULTS_SINCE_BOOT), r.ctrl.fault_count());
    assert_eq!(r.ctrl.fault_count(), 1);
    assert_eq!(
        u32_at(&regs, ir::OVERLOAD_TRIPS_SINCE_BOOT),
        r.ctrl.overload_trips()
    );
    let last = *r.ctrl.faults().last().unwrap();
    assert_eq!(
        regs[usize::from(ir::LAST_FAULT_CODE)],
        u16::from(last.kind.code())
    );
    assert_eq!(u32_at(&regs, ir::LAST_FAULT_CYCLE), last.cycle);
    assert_eq!(
        regs[usize::from(ir::LAST_FAULT_PEAK_FORCE)] as i16,
        dn(last.peak_force_mn)
    );
    assert_eq!(regs[usize::from(ir::LAST_FAULT_PHASE)], 0);
    assert_eq!(regs[usize::from(ir::CONE_ID)], odo.cone().id);
    assert_eq!(regs[usize::from(ir::CONE_ID)], 2, "the second cone");
    assert_eq!(
        regs[usize::from(ir::CONE_MATERIAL)],
        u16::from(Material::QSn6_6_3.code())
    );
    let serial: Vec<u8> = regs[usize::from(ir::CONE_SERIAL)..][..10]
        .iter()
        .flat_map(|w| w.to_be_bytes())
        .collect();
    assert_eq!(&serial[..9], b"SN-0042_x");
    assert!(serial[9..].iter().all(|&b| b == 0), "NUL padded");
    let v: Vec<u16> = package_version()
        .split('.')
        .map(|p| p.parse().unwrap())
        .collect();
    assert_eq!(regs[64..67], v[..]);
    assert_eq!(
        regs[67], 4,
        "map version (2: maintenance mode, register 10 and bit 11; 3: the docking signature, 68-92 and bit 12; 4: the wear estimate from its step, 93-95)"
    );
    // Reserved addresses read 0; handle_frame keeps no last command.
    for a in [8, 9, 11, 15, 36, 39, 45, 47, 60, 63] {
        assert_eq!(regs[a], 0, "address {a}");
    }
    // Any window reads the same values.
    assert_eq!(
        read_inputs(&mut r, ir::CONE_SERIAL, 10).unwrap(),
        regs[50..60]
    );
    assert_eq!(read_inputs(&mut r, 67, 1).unwrap(), [4]);
}

#[test]
fn discrete_inputs_coils_and_holding_read_as_documented() {
    let mut r = rig();
    let word = read_inputs(&mut r, 0, 1).unwrap()[0];
    assert_ne!(word & status::READY, 0, "idle and ready");
    let p = call(&mut r, &pdu(0x02, 0, status::COUNT)).unwrap();
    assert_eq!(p[1], 2);
    assert_eq!(u16::from_le_bytes([p[2], p[3]]), word);
    // Every single discrete input.
    for i in 0..status::COUNT {
        let p = call(&mut r, &pdu(0x02, i, 1)).unwrap();
        assert_eq!(u16::from(p[2]), word >> i & 1, "input {i}");
    }
    // Momentary coils and the command register read 0.
    assert_eq!(call(&mut r, &pdu(0x01, 0, 5)).unwrap(), [0x01, 1, 0]);
    assert_eq!(call(&mut r, &pdu(0x03, 0, 1)).unwrap(), [0x03, 2, 0, 0]);
}

// ---------------------------------------------------------------------------------
// Errors
// ---------------------------------------------------------------------------------

#[test]
fn wrong_crc_short_frames_and_other_units_get_no_reply() {
    let mut r = rig();
    let before = snap(&r);
    let good = frame(UNIT, &pdu(0x04, 0, 1));
    let mut out = [0u8; MAX_FRAME];
    assert!(handle_frame(&good, UNIT, &mut r.ctrl, SERIAL, &mut out).is_some());
    for i in 0..good.len() {
        for bit in [0x01, 0x80] {
            let mut bad = good.clone();
            bad[i] ^= bit;
            assert_eq!(
                handle_frame(&bad, UNIT, &mut r.ctrl, SERIAL, &mut out),
                None,
                "byte {i} bit {bit:#x}"
            );
        }
    }
    // A wrong CRC on a write, and on an unknown function: no reply, nothing done.
    for p in [
        pdu(0x05, 0, 0xFF00),
        vec![0x07],
        vec![0x2B, 0x0E, 0x01, 0x00],
    ] {
        let mut f = frame(UNIT, &p);
        let n = f.len();
        f[n - 1] ^= 0x55;
        assert_eq!(handle_frame(&f, UNIT, &mut r.ctrl, SERIAL, &mut out), None);
    }
    // Under 4 bytes, even with a "valid" CRC.
    for f in [vec![], vec![UNIT], vec![UNIT, 0x04], frame(UNIT, &[])] {
        assert_eq!(
            handle_frame(&f, UNIT, &mut r.ctrl, SERIAL, &mut out),
            None,
            "{f:02x?}"
        );
    }
    // Other units.
    for unit in [2, 247, 248, 255] {
        assert_eq!(ask(&mut r, unit, &pdu(0x04, 0, 1)), None);
        assert_eq!(ask(&mut r, unit, &pdu(0x05, 0, 0xFF00)), None);
    }
    for _ in 0..20 {
        r.tick();
    }
    assert_eq!(r.ctrl.state(), State::Idle, "no dock ran");
    let after = snap(&r);
    // (The peak force at rest is the noise's running maximum: it may rise.)
    let no_peak = |l: Lifetime| Lifetime {
        peak_force_mn: 0,
        ..l
    };
    assert_eq!(no_peak(after.life), no_peak(before.life));
    assert_eq!(after.faults, before.faults);
}

#[test]
fn unknown_function_is_exception_1() {
    let mut r = rig();
    for fc in [
        0x00u8, 0x07, 0x08, 0x0B, 0x11, 0x14, 0x16, 0x17, 0x18, 0x2A, 0x41, 0x7F,
    ] {
        let reply = ask(&mut r, UNIT, &[fc, 0, 0, 0, 1]).unwrap();
        assert_eq!(reply[1..3], [fc | 0x80, 1], "{fc:#x}");
    }
    // Function codes with the exception bit: exception 1, function unchanged.
    for fc in [0x80u8, 0x81, 0x84, 0xAB, 0xFF] {
        let reply = ask(&mut r, UNIT, &[fc]).unwrap();
        assert_eq!(reply[1..3], [fc, 1], "{fc:#x}");
    }
    // Broadcast: no reply.
    assert_eq!(ask(&mut r, BROADCAST, &[0x07]), None);
}

#[test]
fn bad_address_is_exception_2() {
    let mut r = rig();
    let cases = [
        pdu(0x04, ir::COUNT, 1),
        pdu(0x04, ir::COUNT - 1, 2),
        pdu(0x04, ir::COUNT - 5, 10),
        pdu(0x04, 0xFFFF, 2),
        pdu(0x04, 0xFFFF, 1),
        pdu(0x03, 1, 1),
        pdu(0x03, 0, 2),
        pdu(0x01, 5, 1),
        pdu(0x01, 0, 6),
        pdu(0x01, 0, 2_000),
        pdu(0x02, status::COUNT, 1),
        pdu(0x02, 0, status::COUNT + 1),
        pdu(0x05, 5, 0xFF00),
        pdu(0x05, 0xFFFF, 0),
        pdu(0x06, 1, 1),
        pdu(0x06, 0xFFFF, 0),
        [pdu(0x0F, 4, 2), vec![1, 0]].concat(),
        [pdu(0x10, 0, 2), vec![4, 0, 1, 0, 0]].concat(),
        [pdu(0x10, 1, 1), vec![2, 0, 1]].concat(),
    ];
    for p in &cases {
        assert_eq!(exception(&mut r, p), 2, "{p:02x?}");
    }
    // The limits themselves are fine.
    assert!(read_inputs(&mut r, 0, ir::COUNT).is_ok());
    assert!(read_inputs(&mut r, ir::COUNT - 1, 1).is_ok());
    assert!(call(&mut r, &pdu(0x01, 4, 1)).is_ok());
    assert!(call(&mut r, &pdu(0x02, 0, status::COUNT)).is_ok());
}

#[test]
fn bad_quantity_length_or_value_is_exception_3() {
    let mut r = rig();
    let cases = [
        pdu(0x04, 0, 0),
        pdu(0x04, 0, 126),
        pdu(0x03, 0, 0),
        pdu(0x01, 0, 0),
        pdu(0x01, 0, 2_001),
        pdu(0x02, 0, 0),
        pdu(0x05, 0, 0x0001),
        pdu(0x05, 0, 0xFFFF),
        pdu(0x06, 0, 6),
        pdu(0x06, 0, 0xFFFF),
        vec![0x04],
        vec![0x04, 0, 0, 0],
        [pdu(0x04, 0, 1), vec![0]].concat(),
        [pdu(0x06, 0, 1), vec![0]].concat(),
        [pdu(0x0F, 0, 1), vec![2, 1, 0]].concat(), // byte count ≠ ⌈qty/8⌉
        [pdu(0x0F, 0, 0), vec![0]].concat(),
        [pdu(0x0F, 0, 1_969), vec![247]].concat(),
        [pdu(0x0F, 0, 1), vec![1]].concat(), // data missing
        [pdu(0x10, 0, 1), vec![4, 0, 1, 0, 0]].concat(),
        [pdu(0x10, 0, 0), vec![0]].concat(),
        [pdu(0x10, 0, 124), vec![248]].concat(),
        [pdu(0x10, 0, 1), vec![2, 0]].concat(),
        [pdu(0x10, 0, 1), vec![2, 0, 1, 9]].concat(),
        [pdu(0x10, 0, 1), vec![2, 0, 7]].concat(), // unknown command code
        vec![0x10, 0, 0, 0, 1],
    ];
    for p in &cases {
        assert_eq!(exception(&mut r, p), 3, "{p:02x?}");
    }
    for _ in 0..20 {
        r.tick();
    }
    assert_eq!(r.ctrl.state(), State::Idle, "nothing ran");
}

// ---------------------------------------------------------------------------------
// Commands
// ---------------------------------------------------------------------------------

#[test]
fn broadcast_motion_is_ignored_broadcast_stop_stops() {
    let mut r = rig();
    for p in [
        pdu(0x05, Command::Dock.coil(), 0xFF00),
        pdu(0x06, 0, Command::Dock.code()),
        [pdu(0x10, 0, 1), vec![2, 0, 1]].concat(),
        [pdu(0x0F, 0, 1), vec![1, 1]].concat(),
        pdu(0x05, Command::Home.coil(), 0xFF00),
        pdu(0x04, 0, 1),
        pdu(0x05, 0, 0x1234), // even an exception is not sent to a broadcast
    ] {
        assert_eq!(ask(&mut r, BROADCAST, &p), None, "{p:02x?}");
    }
    for _ in 0..40 {
        r.tick();
        assert_eq!(r.ctrl.state(), State::Idle, "a broadcast dock moved");
        assert!(!r.axis.enabled());
    }
    // Stop is safe: it runs on a broadcast (no reply).
    assert_eq!(
        ask(&mut r, BROADCAST, &pdu(0x05, Command::Stop.coil(), 0xFF00)),
        None
    );
    assert!(run_until(&mut r, 5, |r| r.ctrl.state()
        == State::Faulted {
            fault: FaultKind::Stopped
        }));
}

#[test]
fn dock_when_ready_leaves_idle_and_undock_brings_it_back() {
    let mut r = rig();
    assert!(r.ctrl.handshake().ready);
    let reply = ask(&mut r, UNIT, &pdu(0x05, Command::Dock.coil(), 0xFF00)).unwrap();
    assert_eq!(reply, frame(UNIT, &pdu(0x05, 0, 0xFF00)), "echo");
    assert!(run_until(&mut r, 50, |r| r.ctrl.state() != State::Idle));
    assert!(r.ctrl.state().is_docking(), "{:?}", r.ctrl.state());
    // Dock again while docking: refused (not idle).
    assert_eq!(coil(&mut r, Command::Dock, true), Err(1));
    assert!(run_until(&mut r, 3_000, |r| matches!(
        r.ctrl.state(),
        State::Inserting { .. }
    )));
    assert_ne!(read_inputs(&mut r, 0, 1).unwrap()[0] & status::DOCKING, 0);
    coil(&mut r, Command::Undock, true).unwrap();
    assert!(run_until(&mut r, 6_000, |r| r.ctrl.state() == State::Idle));
    assert_eq!(
        r.ctrl.odometer().lifetime().cycles,
        1,
        "an aborted insertion counts"
    );
    // Nothing to undock now.
    assert_eq!(coil(&mut r, Command::Undock, true), Err(1));
}

#[test]
fn dock_and_hold_then_undock_through_the_command_register() {
    let mut r = rig();
    call(&mut r, &pdu(0x06, 0, Command::Dock.code())).unwrap();
    assert!(run_until(&mut r, 6_000, |r| r.ctrl.handshake().mated));
    let regs = read_inputs(&mut r, 0, 2).unwrap();
    assert_ne!(regs[0] & status::MATED, 0);
    assert_eq!(regs[1], 7, "holding");
    let p = [pdu(0x10, 0, 1), vec![2, 0, Command::Undock.code() as u8]].concat();
    assert_eq!(call(&mut r, &p).unwrap(), pdu(0x10, 0, 1));
    assert!(run_until(&mut r, 6_000, |r| r.ctrl.state() == State::Idle));
    assert_eq!(r.ctrl.odometer().lifetime().cycles, 1);
}

#[test]
fn dock_when_not_ready_is_exception_4() {
    // Not calibrated.
    let mut opts = RigOptions::new(80);
    opts.commissioned = false;
    let mut r = rig_with(opts);
    assert_eq!(r.ctrl.state(), State::Idle);
    assert!(!r.ctrl.handshake().ready);
    assert_eq!(coil(&mut r, Command::Dock, true), Err(1));
    assert_eq!(call(&mut r, &pdu(0x06, 0, 1)), Err(1));
    assert_eq!(
        read_inputs(&mut r, 0, 1).unwrap()[0] & status::CALIBRATED,
        0
    );
    for _ in 0..40 {
        r.tick();
    }
    assert_eq!(r.ctrl.state(), State::Idle, "nothing moved");

    // Faulted.
    let mut r = rig();
    coil(&mut r, Command::Stop, true).unwrap();
    assert!(run_until(&mut r, 5, |r| matches!(
        r.ctrl.state(),
        State::Faulted { .. }
    )));
    assert_eq!(coil(&mut r, Command::Dock, true), Err(1));

    // E-STOP open at rest.
    let mut r = rig();
    r.estop_line.set(true);
    r.tick();
    r.tick();
    assert_eq!(coil(&mut r, Command::Dock, true), Err(1));
    assert_ne!(
        read_inputs(&mut r, 0, 1).unwrap()[0] & status::ESTOP_OPEN,
        0
    );
}

#[test]
fn stop_and_clear_fault_paths() {
    let mut r = rig();
    assert_eq!(coil(&mut r, Command::ClearFault, true), Err(1), "no fault");
    // Stop while docking; then the clear recovers to home.
    coil(&mut r, Command::Dock, true).unwrap();
    assert!(run_until(&mut r, 3_000, |r| matches!(
        r.ctrl.state(),
        State::Inserting { .. }
    )));
    coil(&mut r, Command::Stop, true).unwrap();
    assert!(run_until(&mut r, 5, |r| r.ctrl.state()
        == State::Faulted {
            fault: FaultKind::Stopped
        }));
    // A stop when stopped already is answered normally (never refused).
    coil(&mut r, Command::Stop, true).unwrap();
    assert_eq!(coil(&mut r, Command::Undock, true), Err(1));
    // E-STOP open: the clear is refused.
    r.estop_line.set(true);
    r.tick();
    r.tick();
    assert_eq!(coil(&mut r, Command::ClearFault, true), Err(1));
    r.estop_line.set(false);
    r.tick();
    r.tick();
    call(&mut r, &pdu(0x06, 0, Command::ClearFault.code())).unwrap();
    assert!(run_until(&mut r, 5, |r| !matches!(
        r.ctrl.state(),
        State::Faulted { .. }
    )));
    assert!(run_until(&mut r, 8_000, |r| r.ctrl.state() == State::Idle));
    assert!(r.ctrl.handshake().ready);
}

#[test]
fn one_command_a_request_but_a_stop_always_runs() {
    let mut r = rig();
    // Dock and undock at once: exception 3, nothing runs.
    let both = [pdu(0x0F, 0, 2), vec![1, 0b11]].concat();
    assert_eq!(exception(&mut r, &both), 3);
    for _ in 0..40 {
        r.tick();
    }
    assert_eq!(r.ctrl.state(), State::Idle);
    // Dock with stop: exception 3, the stop ran.
    let with_stop = [pdu(0x0F, 0, 4), vec![1, 0b1001]].concat();
    assert_eq!(exception(&mut r, &with_stop), 3);
    assert!(run_until(&mut r, 5, |r| r.ctrl.state()
        == State::Faulted {
            fault: FaultKind::Stopped
        }));
    // A single command through a multiple write is fine.
    let clear = [pdu(0x0F, 2, 1), vec![1, 1]].concat();
    assert_eq!(call(&mut r, &clear).unwrap(), pdu(0x0F, 2, 1));
}

#[test]
fn writing_zero_is_a_no_op_answered_normally() {
    let mut r = rig();
    for c in Command::ALL {
        coil(&mut r, c, false).unwrap();
    }
    call(&mut r, &pdu(0x06, 0, 0)).unwrap();
    call(&mut r, &[pdu(0x10, 0, 1), vec![2, 0, 0]].concat()).unwrap();
    call(&mut r, &[pdu(0x0F, 0, 5), vec![1, 0]].concat()).unwrap();
    for _ in 0..40 {
        r.tick();
    }
    assert_eq!(r.ctrl.state(), State::Idle);
    assert_eq!(r.ctrl.fault_count(), 0);
}

#[test]
fn home_only_after_a_reset() {
    // Before the first step the controller is at power-up.
    let mut r = Rig::new(RigOptions::new(80));
    assert_eq!(r.ctrl.state(), State::PowerUp);
    assert_eq!(read_inputs(&mut r, ir::STATE, 1).unwrap(), [0]);
    coil(&mut r, Command::Home, true).unwrap();
    assert!(run_until(&mut r, 100, |r| r.ctrl.state() == State::Idle));
    assert_eq!(coil(&mut r, Command::Home, true), Err(1), "homed already");
}

// ---------------------------------------------------------------------------------
// Server: the line
// ---------------------------------------------------------------------------------

#[test]
fn server_answers_over_the_line_and_counts() {
    let mut r = rig();
    let mut srv = Server::new(ModbusSettings::DEFAULT);
    let mut t = 1_000_000u64;
    let req = frame(UNIT, &pdu(0x04, 0, 2));
    let reply = transact(&mut r, &mut srv, &mut t, &req).unwrap();
    check_reply(&req, &reply).unwrap();
    // Bad CRC, another unit, a broadcast: silence.
    let mut bad = req.clone();
    bad[3] ^= 1;
    assert_eq!(transact(&mut r, &mut srv, &mut t, &bad), None);
    assert_eq!(
        transact(&mut r, &mut srv, &mut t, &frame(9, &pdu(0x04, 0, 2))),
        None
    );
    assert_eq!(
        transact(&mut r, &mut srv, &mut t, &frame(0, &pdu(0x05, 0, 0xFF00))),
        None
    );
    // An exception; then a refused command and the last-command registers.
    let e = transact(&mut r, &mut srv, &mut t, &frame(UNIT, &pdu(0x04, 0, 0))).unwrap();
    assert_eq!(e[1..3], [0x84, 3]);
    let e = transact(
        &mut r,
        &mut srv,
        &mut t,
        &frame(UNIT, &pdu(0x05, 2, 0xFF00)),
    )
    .unwrap();
    assert_eq!(
        e[1..3],
        [0x85, 1],
        "no fault to clear: exception 01, the wrong state"
    );
    assert_eq!(srv.last_command(), (Command::ClearFault.code(), 7));
    let regs = transact(&mut r, &mut srv, &mut t, &frame(UNIT, &pdu(0x04, 8, 2))).unwrap();
    assert_eq!(regs[3..7], [0, 3, 0, 7], "clear fault: no fault (7)");
    // An accepted one.
    let ok = transact(
        &mut r,
        &mut srv,
        &mut t,
        &frame(UNIT, &pdu(0x05, 0, 0xFF00)),
    )
    .unwrap();
    check_reply(&frame(UNIT, &pdu(0x05, 0, 0xFF00)), &ok).unwrap();
    assert_eq!(srv.last_command(), (Command::Dock.code(), 0));
    let st = srv.stats();
    assert_eq!(st.frames_ok, 6, "{st:?}");
    assert_eq!(st.crc_errors, 1);
    assert_eq!(st.other_unit, 1);
    assert_eq!(st.replies, 5);
    assert_eq!(st.exceptions, 2);
    assert_eq!(st.commands, 1);
    assert_eq!((st.framing_errors, st.overruns), (0, 0));
    assert!(run_until(&mut r, 50, |r| r.ctrl.state().is_docking()));
}

#[test]
fn server_discards_frames_split_by_t1_5_overlong_and_unpolled() {
    let mut r = rig();
    for baud in [9_600, 19_200, 115_200] {
        let settings = ModbusSettings::new(UNIT, baud).unwrap();
        let mut srv = Server::new(settings);
        let (c, t15, t35) = (
            u64::from(settings.char_us()),
            u64::from(settings.t1_5_us()),
            u64::from(settings.t3_5_us()),
        );
        let req = frame(UNIT, &pdu(0x04, 0, 1));
        let mut t = 10_000u64;
        // A silence of t1.5 inside the frame is fine; one µs more discards it.
        for (gap, answered) in [(t15, true), (t15 + 1, false)] {
            for (i, &b) in req.iter().enumerate() {
                t += c + if i == 4 { gap } else { 0 };
                srv.on_byte(b, t);
                assert_eq!(srv.poll(t, &mut r.ctrl, SERIAL), None);
            }
            assert_eq!(srv.poll(t + t35 - 1, &mut r.ctrl, SERIAL), None);
            let reply = srv.poll(t + t35, &mut r.ctrl, SERIAL).map(<[u8]>::to_vec);
            assert_eq!(reply.is_some(), answered, "{baud} baud, gap {gap} µs");
            t += 10 * t35;
        }
        assert_eq!(srv.stats().framing_errors, 1);
        // Two requests t3.5 apart, polled only after the second: the first is dropped.
        for &b in &req {
            t += c;
            srv.on_byte(b, t);
        }
        t += t35;
        let second = frame(UNIT, &pdu(0x04, 1, 1));
        let reply = transact(&mut r, &mut srv, &mut t, &second).unwrap();
        check_reply(&second, &reply).unwrap();
        assert_eq!(srv.stats().overruns, 1);
        // Over 256 bytes: discarded whole, and the next request is answered.
        let mut long = frame(UNIT, &pdu(0x04, 0, 1));
        long.resize(300, 0x55);
        assert_eq!(transact(&mut r, &mut srv, &mut t, &long), None);
        assert_eq!(srv.stats().framing_errors, 2);
        assert!(transact(&mut r, &mut srv, &mut t, &req).is_some());
        // A character with a parity error spoils its frame.
        for (i, &b) in req.iter().enumerate() {
            t += c;
            if i == 2 {
                srv.on_line_error(t);
            } else {
                srv.on_byte(b, t);
            }
        }
        assert_eq!(srv.poll(t + t35, &mut r.ctrl, SERIAL), None);
        assert_eq!(srv.stats().framing_errors, 3);
        assert_eq!(srv.stats().replies, 3);
    }
}

#[test]
fn server_settings_fall_back_to_the_default_and_can_change() {
    let srv = Server::new(ModbusSettings { unit: 0, baud: 1 });
    assert_eq!(srv.settings(), ModbusSettings::DEFAULT);
    let mut srv = Server::new(ModbusSettings::DEFAULT);
    assert!(!srv.set_settings(ModbusSettings {
        unit: 248,
        baud: 19_200
    }));
    let s = ModbusSettings::new(7, 115_200).unwrap();
    assert!(srv.set_settings(s));
    assert_eq!(srv.settings(), s);
    assert_eq!(ModbusSettings::from_bytes(&s.to_bytes()), Some(s));
    // Unit 7 now.
    let mut r = rig();
    let mut t = 0;
    let req = frame(7, &pdu(0x04, 0, 1));
    let reply = transact(&mut r, &mut srv, &mut t, &req).unwrap();
    assert_eq!(reply[0], 7);
    assert_eq!(
        transact(&mut r, &mut srv, &mut t, &frame(UNIT, &pdu(0x04, 0, 1))),
        None
    );
}

// ---------------------------------------------------------------------------------
// Fuzzing
// ---------------------------------------------------------------------------------

/// Controllers in several states, built once per test thread. `reader` only ever sees
/// frames that are not writes, and is stepped after each: it must stay idle.
struct Rigs {
    reader: Rig,
    writers: Vec<Rig>,
}

impl Rigs {
    fn new() -> Self {
        let idle = rig();
        let mut faulted = rig();
        faulted.ctrl.request(Request::Stop);
        for _ in 0..3 {
            faulted.tick();
        }
        let mut inserting = rig();
        inserting.ctrl.request(Request::Dock);
        assert!(run_until(&mut inserting, 3_000, |r| matches!(
            r.ctrl.state(),
            State::Inserting { .. }
        )));
        let mut opts = RigOptions::new(80);
        opts.commissioned = false;
        let uncalibrated = rig_with(opts);
        let power_up = Rig::new(RigOptions::new(80));
        let mut estop = rig();
        estop.estop_line.set(true);
        estop.tick();
        estop.tick();
        Self {
            reader: rig(),
            writers: vec![idle, faulted, inserting, uncalibrated, power_up, estop],
        }
    }
}

thread_local! {
    static RIGS: RefCell<Option<Rigs>> = const { RefCell::new(None) };
    /// An idle rig for the server streams (never stepped: commands only queue).
    static STREAM_RIG: RefCell<Option<Rig>> = const { RefCell::new(None) };
}

fn is_write(frame: &[u8]) -> bool {
    frame
        .get(1)
        .is_some_and(|f| matches!(f, 0x05 | 0x06 | 0x0F | 0x10))
}

/// What a run saw (the corpus test checks the corpus reaches every kind).
#[derive(Debug, Default)]
struct Seen {
    replies: usize,
    exceptions: [usize; 5],
    silent: usize,
}

/// Handle `frame` on the rig it belongs to (writes: `writer % 6`) and check the
/// invariants.
fn check_frame(frame: &[u8], writer: usize) -> Result<Seen, TestCaseError> {
    RIGS.with(|cell| {
        let mut cell = cell.borrow_mut();
        let rigs = cell.get_or_insert_with(Rigs::new);
        let write = is_write(frame);
        let r = if write {
            let n = rigs.writers.len();
            &mut rigs.writers[writer % n]
        } else {
            &mut rigs.reader
        };
        let before = snap(r);
        let mut out = [0xEEu8; MAX_FRAME];
        let reply = handle_frame(frame, UNIT, &mut r.ctrl, SERIAL, &mut out);
        let mut seen = Seen::default();
        match reply {
            None => seen.silent += 1,
            Some(n) => {
                prop_assert!(n <= MAX_FRAME);
                check_reply(frame, &out[..n]).map_err(TestCaseError::fail)?;
                seen.replies += 1;
                if out[1] & 0x80 != 0 {
                    seen.exceptions[usize::from(out[2])] += 1;
                }
            }
        }
        // Nothing is stepped in here: no frame changes what the controller reports.
        prop_assert_eq!(&snap(r), &before, "frame {:02x?}", frame);
        if !write {
            // A read that had queued a request would show at the next step.
            r.tick();
            let after = snap(r);
            prop_assert_eq!(after.status.state, State::Idle, "frame {:02x?}", frame);
            // (The lifetime peak force follows the sensor noise at rest.)
            let life = |l: Lifetime| Lifetime {
                peak_force_mn: 0,
                ..l
            };
            prop_assert_eq!(life(after.life), life(before.life));
            prop_assert_eq!(after.cone, before.cone);
            prop_assert_eq!(after.faults, before.faults);
        }
        Ok(seen)
    })
}

fn any_unit() -> impl Strategy<Value = u8> {
    prop_oneof![12 => Just(UNIT), 2 => Just(BROADCAST), 1 => Just(2u8), 1 => any::<u8>()]
}

fn address() -> impl Strategy<Value = u16> {
    prop_oneof![
        6 => prop::sample::select(vec![
            0u16, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 15, 16, 35, 36, 40, 44, 47, 48, 49,
            50, 59, 60, 63, 64, 66, 67, 68, 69, 125, 0x7FFF, 0xFFFE, 0xFFFF,
        ]),
        1 => any::<u16>(),
    ]
}

fn quantity() -> impl Strategy<Value = u16> {
    prop_oneof![
        6 => prop::sample::select(vec![
            0u16, 1, 2, 3, 4, 5, 6, 8, 10, 11, 12, 17, 67, 68, 69, 122, 123, 124, 125, 126,
            1_968, 1_969, 2_000, 2_001, 0xFFFF,
        ]),
        1 => any::<u16>(),
    ]
}

fn value() -> impl Strategy<Value = u16> {
    prop_oneof![
        6 => prop::sample::select(vec![0u16, 1, 2, 3, 4, 5, 6, 7, 0xFF00, 0x00FF, 0xFFFF]),
        1 => any::<u16>(),
    ]
}

/// PDUs that reach every branch: each function with boundary addresses and
/// quantities, byte counts right and wrong, 0x2B variants, unknown functions.
fn request_pdu() -> impl Strategy<Value = Vec<u8>> {
    let function = prop_oneof![
        10 => prop::sample::select(vec![0x01u8, 0x02, 0x03, 0x04, 0x05, 0x06, 0x0F, 0x10, 0x2B]),
        1 => prop::sample::select(vec![0x00u8, 0x07, 0x08, 0x11, 0x17, 0x2A, 0x80, 0x85, 0xAB, 0xFF]),
        1 => any::<u8>(),
    ];
    (
        function,
        address(),
        quantity(),
        prop::collection::vec(value(), 0..8),
        prop::collection::vec(any::<u8>(), 0..260),
        0u8..8,
        prop::bool::weighted(0.4),
    )
        .prop_map(|(fc, addr, qty, values, junk, mode, inside)| {
            // Inside the map: an address and quantity of the function's block.
            let (addr, qty) = match (inside, fc) {
                (false, _) => (addr, qty),
                (true, 0x01 | 0x05 | 0x0F) => in_block(addr, qty, 5),
                (true, 0x02) => in_block(addr, qty, 11),
                (true, 0x04) => in_block(addr, qty, 68),
                (true, _) => (0, 1),
            };
            let values = match (inside, fc) {
                (true, 0x05) => vec![[0xFF00, 0][usize::from(qty) % 2]],
                (true, 0x06 | 0x10) => vec![values.first().copied().unwrap_or(0) % 7],
                _ => values,
            };
            let mut p = vec![fc];
            match fc {
                0x01..=0x04 => p = pdu(fc, addr, qty),
                0x05 | 0x06 => p = pdu(fc, addr, values.first().copied().unwrap_or(0xFF00)),
                0x0F | 0x10 => {
                    p = pdu(fc, addr, qty);
                    let need = if fc == 0x0F {
                        usize::from(qty).div_ceil(8)
                    } else {
                        2 * usize::from(qty)
                    };
                    let count = if mode == 0 {
                        junk.len() % 256
                    } else {
                        need.min(255)
                    };
                    p.push(count as u8);
                    let mut data: Vec<u8> = values.iter().flat_map(|v| v.to_be_bytes()).collect();
                    data.extend_from_slice(&junk);
                    data.resize(
                        if mode == 1 {
                            need.saturating_sub(1)
                        } else {
                            need
                        },
                        0,
                    );
                    p.extend(data.iter().take(250));
                }
                0x2B => {
                    let mei = if mode == 0 {
                        junk.first().copied().unwrap_or(0)
                    } else {
                        0x0E
                    };
                    let code = [0, 1, 2, 3, 4, 5, 0xFF][usize::from(qty) % 7];
                    let object =
                        [0, 1, 2, 3, 4, 5, 6, 0x7F, 0x80, 0x81, 0xFF][usize::from(addr) % 11];
                    p.extend_from_slice(&[mei, code, object]);
                    if mode == 1 {
                        p.pop();
                    }
                }
                _ => p.extend(junk.iter().take(usize::from(mode) * 3)),
            }
            match mode {
                6 => p.truncate(junk.len() % (p.len() + 1)), // truncated
                7 => p.extend(junk.iter().take(4)),          // trailing bytes
                _ => {}
            }
            p
        })
}

/// `addr..addr + qty` moved inside a block of `len`.
fn in_block(addr: u16, qty: u16, len: u16) -> (u16, u16) {
    let a = addr % len;
    (a, 1 + qty % (len - a))
}

/// Whole frames: valid CRC mostly; a wrong one, random bytes and odd lengths too.
fn any_frame() -> impl Strategy<Value = Vec<u8>> {
    prop_oneof![
        12 => (any_unit(), request_pdu()).prop_map(|(u, p)| frame(u, &p)),
        1 => (any_unit(), request_pdu(), any::<u8>()).prop_map(|(u, p, x)| {
            let mut f = frame(u, &p);
            let n = f.len();
            f[n - 1] ^= x | 1;
            f
        }),
        2 => prop::collection::vec(any::<u8>(), 0..300),
        1 => (any_unit(), prop::collection::vec(any::<u8>(), 0..300))
            .prop_map(|(u, p)| frame(u, &p)),
    ]
}

/// A byte stream with gaps, for the server: (byte, silence before it in µs).
fn stream() -> impl Strategy<Value = Vec<(Vec<u8>, u64)>> {
    let gap = prop_oneof![
        4 => Just(0u64),
        2 => Just(2_006u64),
        1 => 0u64..900,
        1 => 800u64..2_100,
        1 => 2_000u64..50_000,
    ];
    prop::collection::vec((any_frame(), gap), 0..12)
}

proptest! {
    #[test]
    fn prop_frames_never_panic_and_replies_are_well_formed(
        frame in any_frame(),
        writer in 0usize..6,
    ) {
        check_frame(&frame, writer)?;
    }

    #[test]
    fn prop_server_streams_never_panic(chunks in stream(), split in any::<u8>()) {
        STREAM_RIG.with(|cell| {
        let mut cell = cell.borrow_mut();
        let r = cell.get_or_insert_with(rig);
        let mut srv = Server::new(ModbusSettings::DEFAULT);
        let c = u64::from(ModbusSettings::DEFAULT.char_us());
        let mut t = 0u64;
        let mut replies = 0u32;
        for (bytes, gap) in &chunks {
            t += gap;
            for (i, &b) in bytes.iter().enumerate() {
                t += c;
                if i == usize::from(split) {
                    t += u64::from(split) * 10; // a gap of up to 2.5 ms mid-frame
                }
                srv.on_byte(b, t);
                if let Some(reply) = srv.poll(t, &mut r.ctrl, SERIAL) {
                    prop_assert!(false, "a reply mid-frame: {:02x?}", reply);
                }
            }
            if let Some(reply) = srv.poll(t + 2_006, &mut r.ctrl, SERIAL) {
                replies += 1;
                prop_assert!(reply.len() >= 5 && crc_ok(reply) && reply[0] == UNIT);
                if reply[1] & 0x80 != 0 {
                    prop_assert!(reply.len() == 5 && (1..=4).contains(&reply[2]));
                }
            }
        }
        let st = srv.stats();
        prop_assert_eq!(st.replies, replies);
        prop_assert!(st.exceptions <= st.replies && st.replies <= st.frames_ok);
        Ok(())
        })?;
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1_000_000))]

    /// 1,000,000 cases of the frame property; run by hand (see the module doc).
    #[test]
    #[ignore = "long-running fuzz; run with --release -- --ignored"]
    fn fuzz_modbus_million(frame in any_frame(), writer in 0usize..6) {
        check_frame(&frame, writer)?;
    }
}

#[test]
fn corpus_frames_keep_invariants() {
    let files = host_tests::corpus_files("modbus");
    let mut total = Seen::default();
    for path in &files {
        let bytes = std::fs::read(path).unwrap();
        for writer in 0..6 {
            let seen =
                check_frame(&bytes, writer).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            total.replies += seen.replies;
            total.silent += seen.silent;
            for (t, s) in total.exceptions.iter_mut().zip(seen.exceptions) {
                *t += s;
            }
        }
        // Over the line, a fresh server answers as handle_frame does.
        let mut r = rig();
        let mut srv = Server::new(ModbusSettings::DEFAULT);
        let mut t = 0;
        let over_line = transact(&mut r, &mut srv, &mut t, &bytes);
        let mut r2 = rig();
        let mut out = [0u8; MAX_FRAME];
        let direct =
            handle_frame(&bytes, UNIT, &mut r2.ctrl, SERIAL, &mut out).map(|n| out[..n].to_vec());
        let expect = if bytes.len() > MAX_FRAME {
            None
        } else {
            direct
        };
        assert_eq!(over_line, expect, "{}", path.display());
    }
    assert!(
        total.replies >= 60 && total.silent >= 30 && total.exceptions[1..4].iter().all(|&n| n >= 6),
        "{total:?}"
    );
    // A refused command is exception 01 (the wrong state), never 04: the device has not
    // failed (issue 18).
    assert_eq!(total.exceptions[4], 0, "{total:?}");
}

/// Defect (issue 17, item 7): a Modbus dock or the DOCK pin moved the machine while a
/// technician was in maintenance mode at the console, and no register showed the mode.
#[test]
fn maintenance_mode_locks_out_plc_motion() {
    use docking_logic::controller::Refusal;
    let mut r = rig();
    assert!(r.command("pin set 1357", 10).starts_with("ok"));
    assert!(r.command("maint 1357", 10).starts_with("ok"));
    assert!(r.ctrl.maintenance_mode());
    assert!(!r.ctrl.handshake().ready, "READY drops in maintenance");
    let regs = read_inputs(&mut r, 0, 11).unwrap();
    assert_ne!(regs[0] & status::MAINTENANCE_MODE, 0, "status bit 11");
    assert_eq!(regs[0] & status::MAINTENANCE, 0, "bit 5 keeps its meaning");
    assert_eq!(regs[usize::from(ir::MAINTENANCE_MODE)], 1);
    // Modbus dock: refused, with the reason in input register 9.
    assert_eq!(coil(&mut r, Command::Dock, true), Err(0x01));
    assert_eq!(
        r.ctrl
            .command_from(docking_logic::controller::Source::Plc, Request::Dock),
        Err(Refusal::MaintenanceMode)
    );
    assert_eq!(Refusal::MaintenanceMode.code(), 9);
    // The DOCK pin: ignored.
    r.dock_line.set(false);
    host_tests::run_without_motion(&mut r, 200, "moved in maintenance");
    assert_eq!(r.ctrl.state(), State::Idle);
    // A stop is never refused, whoever sends it.
    assert!(r
        .ctrl
        .command_from(docking_logic::controller::Source::Plc, Request::Stop)
        .is_ok());
    // Maintenance ends: READY again after the stop is cleared, and the PLC docks.
    r.dock_line.set(true);
    assert!(r.command("clear-fault", 10).starts_with("ok"));
    assert!(run_until(&mut r, 8_000, |r| r.ctrl.state() == State::Idle));
    assert!(r.command("maint exit", 10).starts_with("ok"));
    r.tick();
    assert!(!r.ctrl.maintenance_mode());
    assert!(r.ctrl.handshake().ready);
    assert_eq!(read_inputs(&mut r, ir::MAINTENANCE_MODE, 1).unwrap(), [0]);
    assert_eq!(coil(&mut r, Command::Dock, true), Ok(()));
    assert!(run_until(&mut r, 50, |r| r.ctrl.state().is_docking()));
}

/// VendorName and ProductName are the machine builder's, from the commissioning file
/// (`hil-sim commission --vendor … --product …` writes `cfg.identity`), not a
/// placeholder.
#[test]
fn device_identification_names_come_from_the_commissioning_config() {
    let mut r = rig_with(RigOptions {
        identity: docking_logic::controller::Identity {
            vendor: "ACME Docking GmbH",
            product: "AutoDock 18",
        },
        ..RigOptions::new(80)
    });
    let (_, _, objs) = objects(&ask(&mut r, UNIT, &[0x2B, 0x0E, 0x02, 0x00]).unwrap());
    assert_eq!(objs[0], (0, "ACME Docking GmbH".to_owned()));
    assert_eq!(objs[3], (4, "AutoDock 18".to_owned()));
    // Without one: the defaults.
    let mut r = rig();
    let (_, _, objs) = objects(&ask(&mut r, UNIT, &[0x2B, 0x0E, 0x02, 0x00]).unwrap());
    assert_eq!(objs[0].1, docking_logic::modbus::VENDOR_NAME);
}
