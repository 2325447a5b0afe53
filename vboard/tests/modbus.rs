//! Modbus RTU on the image's USART3 (PB10/PB11, RS-485 DE on PB14), 19200 8E1, unit 1:
//! the PLC's frames at their line rate, the replies as they reach the bus. Build the
//! image first: `cargo build --release --target thumbv7em-none-eabihf`.

use docking_logic::modbus::{crc16, ir, status};
use vboard::scene::{rtu, Options, Session, PS_PER_MS};
use vboard::time::PS_PER_S;

fn booted() -> Session {
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(2 * PS_PER_S).unwrap();
    s
}

/// A reply's registers (function 3/4), its CRC checked.
fn registers(reply: &[u8]) -> Vec<u16> {
    let (body, crc) = reply.split_at(reply.len() - 2);
    assert_eq!(crc16(body).to_le_bytes(), crc, "CRC of {reply:02x?}");
    assert_eq!(body[2] as usize, body.len() - 3, "{reply:02x?}");
    body[3..]
        .chunks_exact(2)
        .map(|c| u16::from_be_bytes([c[0], c[1]]))
        .collect()
}

fn read_inputs(s: &mut Session, addr: u16, n: u16) -> Vec<u16> {
    let [ah, al] = addr.to_be_bytes();
    let r = s
        .modbus(&rtu(1, &[0x04, ah, al, 0, n as u8]), PS_PER_S)
        .unwrap();
    assert_eq!(&r[..2], &[1, 0x04], "{r:02x?}");
    registers(&r)
}

#[test]
fn the_plc_reads_identification_and_wear_over_rs485() {
    let mut s = booted();
    // Device identification, the unit's serial (object 0x80: the chip's unique ID).
    let r = s
        .modbus(&rtu(1, &[0x2B, 0x0E, 0x04, 0x80]), PS_PER_S)
        .unwrap();
    assert!(r.len() > 10, "{r:02x?}");
    let (body, crc) = r.split_at(r.len() - 2);
    assert_eq!(crc16(body).to_le_bytes(), crc);
    let text = String::from_utf8_lossy(body);
    assert!(
        body.windows(24)
            .any(|w| w.iter().all(|b| b.is_ascii_hexdigit())),
        "{text:?}"
    );
    // The basic objects: vendor, product, revision.
    let r = s
        .modbus(&rtu(1, &[0x2B, 0x0E, 0x01, 0x00]), PS_PER_S)
        .unwrap();
    let text = String::from_utf8_lossy(&r);
    assert!(text.contains(env!("CARGO_PKG_VERSION").split('.').next().unwrap()));
    // Status and counters.
    let st = read_inputs(&mut s, ir::STATUS, 1)[0];
    assert!(st & status::READY != 0, "READY after boot: {st:#06x}");
    let life = read_inputs(&mut s, ir::LIFETIME_CYCLES, 2);
    assert_eq!(life, [0, 0]);
    // The reply came with the driver enabled throughout, and it was released after.
    assert_eq!(s.board.soc().modbus_de_losses, 0);
    assert_eq!(s.board.soc().modbus_collisions, 0);
    // A wrong CRC: no reply.
    let mut bad = rtu(1, &[0x04, 0, 0, 0, 1]);
    *bad.last_mut().unwrap() ^= 1;
    assert!(s.modbus(&bad, 200 * PS_PER_MS).unwrap().is_empty());
    // An address past the map: exception 02.
    let r = s
        .modbus(&rtu(1, &[0x04, 0x7F, 0x00, 0, 1]), PS_PER_S)
        .unwrap();
    assert_eq!(&r[..3], &[1, 0x84, 0x02], "{r:02x?}");
}

#[test]
fn the_plc_docks_and_undocks_through_the_map_and_the_reply_waits_t3_5() {
    let mut s = booted();
    // Coil 0 = dock.
    let t0 = s.now();
    let r = s
        .modbus(&rtu(1, &[0x05, 0, 0, 0xFF, 0x00]), PS_PER_S)
        .unwrap();
    assert_eq!(r, rtu(1, &[0x05, 0, 0, 0xFF, 0x00]), "echo");
    // The reply begins at least t3.5 (2.005 ms at 19200) after the request's end and
    // within a few ms: request 8 chars + reply 8 chars at 573 µs each.
    let first = s
        .board
        .soc()
        .modbus_out
        .iter()
        .find(|(t, _)| *t > t0)
        .unwrap()
        .0;
    let char_ps = 11 * PS_PER_S / 19_200;
    let req_end = t0 + 8 * char_ps;
    let gap_us = (first - char_ps).saturating_sub(req_end) as f64 * 1e-6;
    println!("turnaround {gap_us:.1} µs");
    assert!(
        (2_005.0..6_000.0).contains(&gap_us),
        "turnaround {gap_us} µs"
    );
    let t = s.now() + 60 * PS_PER_S;
    assert!(s.run_until(t, |x| x.plc_out().mated).unwrap(), "mated");
    let st = read_inputs(&mut s, ir::STATUS, 1)[0];
    assert!(
        st & status::MATED != 0 && st & status::READY == 0,
        "{st:#06x}"
    );
    // Holding register 0 = 2: undock.
    let r = s.modbus(&rtu(1, &[0x06, 0, 0, 0, 2]), PS_PER_S).unwrap();
    assert_eq!(r, rtu(1, &[0x06, 0, 0, 0, 2]));
    let t = s.now() + 60 * PS_PER_S;
    assert!(s
        .run_until(t, |x| x.at_rest() && x.plc_out().ready)
        .unwrap());
    assert_eq!(read_inputs(&mut s, ir::LIFETIME_CYCLES, 2), [0, 1]);
    // A dock refused (E-STOP open): exception 01 (the wrong state), never silence.
    s.set_estop(true);
    s.run_for(100 * PS_PER_MS).unwrap();
    let r = s
        .modbus(&rtu(1, &[0x05, 0, 0, 0xFF, 0x00]), PS_PER_S)
        .unwrap();
    assert_eq!(&r[..3], &[1, 0x85, 0x01], "{r:02x?}");
    assert_eq!(s.board.soc().modbus_de_losses, 0);
}

#[test]
fn stored_modbus_settings_take_effect_on_the_board_after_a_reset() {
    let mut s = booted();
    for cmd in ["pin set 2468", "maint 2468"] {
        assert!(s.console(cmd, PS_PER_S).unwrap().starts_with("ok"), "{cmd}");
    }
    let r = s.console("modbus 7 38400", 2 * PS_PER_S).unwrap();
    assert!(r.starts_with("ok"), "{r}");
    // Until the next boot the line keeps 19200 and unit 1.
    assert_eq!(read_inputs(&mut s, ir::STATUS, 1).len(), 1);
    s.board.reset_pin();
    s.run_for(2 * PS_PER_S).unwrap();
    // The old settings get nothing now (a 19200 master garbles at 38400: framing errors).
    assert!(s
        .modbus(&rtu(1, &[0x04, 0, 0, 0, 1]), 300 * PS_PER_MS)
        .unwrap()
        .is_empty());
    s.board.soc_mut().usart3.far_baud = 38_400;
    // Unit 1 is no longer ours; unit 7 answers.
    assert!(s
        .modbus(&rtu(1, &[0x04, 0, 0, 0, 1]), 300 * PS_PER_MS)
        .unwrap()
        .is_empty());
    let r = s.modbus(&rtu(7, &[0x04, 0, 0, 0, 1]), PS_PER_S).unwrap();
    assert_eq!(&r[..2], &[7, 0x04], "{r:02x?}");
    assert_eq!(s.board.soc().modbus_de_losses, 0);
}
