//! Every Modbus reply, byte for byte, against a transcript recorded on 927460b (issue
//! 20's base): the replies of functions 0x01–0x06, 0x0F and 0x10 were built by rmodbus
//! there and are built by hand now, and must be the same bytes (docs/modbus.md: the map
//! and its replies are stable).
//!
//! The frames: every function code 0x00–0x2C and 0x80–0x81 with addresses and quantities
//! at and across the map's edges, every command coil and command register value, bad
//! coil values, byte counts and lengths, broadcast, other units, bad CRCs; then 600
//! request PDUs from a fixed pseudo-random sequence (valid CRC), answered by controllers
//! idle, faulted, and docking. To record the transcript again (only for an intended
//! change of a reply, with docs/modbus.md): `TRANSCRIPT_RECORD=1 cargo test -p host-tests
//! --test modbus_transcript`.

use std::fmt::Write as _;

use docking_logic::modbus::{handle_frame, MAX_FRAME};
use docking_logic::sequencer::Request;
use hil_sim::rig::{Rig, RigOptions};

const TRANSCRIPT: &str = "fixtures/modbus-transcript-927460b.txt";
const UNIT: u8 = 1;
const SERIAL: &str = "DC407-000123";

fn crc(data: &[u8]) -> [u8; 2] {
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

fn frame(unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut f = vec![unit];
    f.extend_from_slice(pdu);
    let c = crc(&f);
    f.extend_from_slice(&c);
    f
}

fn pdu(fc: u8, a: u16, b: u16) -> Vec<u8> {
    let mut p = vec![fc];
    p.extend_from_slice(&a.to_be_bytes());
    p.extend_from_slice(&b.to_be_bytes());
    p
}

fn multi(fc: u8, a: u16, qty: u16, data: &[u8]) -> Vec<u8> {
    let mut p = pdu(fc, a, qty);
    p.push(data.len() as u8);
    p.extend_from_slice(data);
    p
}

fn rig() -> Rig {
    let mut r = Rig::new(RigOptions::new(80));
    for _ in 0..hil_sim::rig::BOOT_TICKS {
        r.tick();
    }
    r
}

fn hex(b: &[u8]) -> String {
    b.iter().map(|x| format!("{x:02x}")).collect()
}

/// The hand-picked frames.
fn edge_frames() -> Vec<Vec<u8>> {
    let mut f = Vec::new();
    for fc in (0x00..=0x2Cu8).chain([0x80, 0x81, 0xAB]) {
        for (a, q) in [
            (0, 1),
            (0, 0),
            (0, 8),
            (1, 11),
            (5, 30),
            (0, 125),
            (0, 126),
            (40, 2),
        ] {
            f.push(frame(UNIT, &pdu(fc, a, q)));
        }
    }
    for (a, q) in [
        (0u16, 2001u16),
        (0, 2000),
        (11, 1),
        (12, 1),
        (0, 12),
        (0, 13),
    ] {
        f.push(frame(UNIT, &pdu(0x01, a, q)));
        f.push(frame(UNIT, &pdu(0x02, a, q)));
    }
    for reg in [0u16, 7, 8, 9, 20, 29, 30, 31, 32, 40, 60] {
        f.push(frame(UNIT, &pdu(0x04, reg, 1)));
        f.push(frame(UNIT, &pdu(0x04, reg, 2)));
        f.push(frame(UNIT, &pdu(0x03, reg, 1)));
    }
    for coil in 0..8u16 {
        for v in [0x0000u16, 0xFF00, 0x00FF, 0x1234] {
            f.push(frame(UNIT, &pdu(0x05, coil, v)));
        }
    }
    for reg in 0..3u16 {
        for v in 0..8u16 {
            f.push(frame(UNIT, &pdu(0x06, reg, v)));
        }
    }
    for (a, q, d) in [
        (0u16, 1u16, vec![0x01u8]),
        (0, 5, vec![0x00]),
        (0, 5, vec![0x10]),
        (0, 8, vec![0x03]),
        (2, 2, vec![0x01]),
        (0, 9, vec![0x00, 0x01]),
        (0, 0, vec![]),
        (0, 16, vec![0x00]),
        (6, 4, vec![0x0F]),
    ] {
        f.push(frame(UNIT, &multi(0x0F, a, q, &d)));
    }
    for (a, q, d) in [
        (0u16, 1u16, vec![0x00u8, 0x01]),
        (0, 1, vec![0x00, 0x05]),
        (0, 1, vec![0x00, 0x63]),
        (0, 2, vec![0x00, 0x01, 0x00, 0x02]),
        (1, 1, vec![0x00, 0x01]),
        (0, 1, vec![0x00]),
        (0, 0, vec![]),
    ] {
        f.push(frame(UNIT, &multi(0x10, a, q, &d)));
    }
    // Broadcast, another unit, a bad CRC, short and long frames.
    f.push(frame(0, &pdu(0x05, 3, 0xFF00)));
    f.push(frame(0, &pdu(0x05, 0, 0xFF00)));
    f.push(frame(0, &pdu(0x04, 0, 2)));
    f.push(frame(0, &multi(0x10, 0, 1, &[0, 1])));
    f.push(frame(2, &pdu(0x04, 0, 2)));
    let mut bad = frame(UNIT, &pdu(0x04, 0, 2));
    bad[3] ^= 1;
    f.push(bad);
    f.push(frame(UNIT, &[0x04]));
    f.push(frame(UNIT, &[0x04, 0, 0, 0]));
    f.push(frame(UNIT, &[0x04, 0, 0, 0, 1, 0]));
    f.push(frame(UNIT, &[0x2B, 0x0E, 0x01, 0x00]));
    f.push(frame(UNIT, &[0x2B, 0x0E, 0x04, 0x80]));
    f.push(frame(UNIT, &[0x2B, 0x0E, 0x03, 0x00]));
    f.push(vec![UNIT, 0x04, 0x00]);
    f.push(frame(UNIT, &[0x10; 260]));
    f
}

/// 600 PDUs from a fixed linear congruential sequence: a function code biased to the
/// implemented ones, then 4–9 bytes.
fn random_frames() -> Vec<Vec<u8>> {
    let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
    let mut next = move || {
        x = x
            .wrapping_mul(6_364_136_223_846_793_005)
            .wrapping_add(1_442_695_040_888_963_407);
        (x >> 33) as u32
    };
    const FC: [u8; 12] = [1, 2, 3, 4, 5, 6, 15, 16, 0x2B, 7, 0x11, 0x83];
    (0..600)
        .map(|_| {
            let fc = FC[(next() % 12) as usize];
            let len = 4 + (next() % 6) as usize;
            let mut p = vec![fc];
            for i in 0..len {
                let b = next() as u8;
                // Small addresses and quantities, mostly: the map is small.
                p.push(match i {
                    0 | 2 => b & 0x01,
                    1 => b & 0x3F,
                    3 => b & 0x1F,
                    _ => b,
                });
            }
            frame(UNIT, &p)
        })
        .collect()
}

fn session() -> String {
    let mut t = String::new();
    let run = |t: &mut String, name: &str, r: &mut Rig, frames: &[Vec<u8>]| {
        let _ = writeln!(t, "# {name}");
        for f in frames {
            let mut out = [0u8; MAX_FRAME];
            let reply = handle_frame(f, UNIT, &mut r.ctrl, SERIAL, &mut out);
            let shown = reply.map_or("-".to_string(), |n| hex(&out[..n]));
            let _ = writeln!(t, "{} {shown}", hex(f));
            r.tick();
        }
    };
    let edges = edge_frames();
    let random = random_frames();
    let mut idle = rig();
    run(&mut t, "idle", &mut idle, &edges);
    let mut faulted = rig();
    faulted.ctrl.request(Request::Stop);
    for _ in 0..20 {
        faulted.tick();
    }
    run(&mut t, "faulted", &mut faulted, &edges);
    run(&mut t, "random, idle", &mut rig(), &random);
    let mut docking = rig();
    docking.ctrl.request(Request::Dock);
    for _ in 0..200 {
        docking.tick();
    }
    run(&mut t, "random, docking", &mut docking, &random);
    t
}

#[test]
fn every_reply_is_the_bytes_it_was_before_rmodbus_left_the_image() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join(TRANSCRIPT);
    let now = session();
    if std::env::var_os("TRANSCRIPT_RECORD").is_some() {
        std::fs::write(&path, &now).unwrap();
        return;
    }
    let before = std::fs::read_to_string(&path).unwrap();
    for (i, (a, b)) in before.lines().zip(now.lines()).enumerate() {
        assert_eq!(a, b, "transcript line {} differs", i + 1);
    }
    assert_eq!(
        before.lines().count(),
        now.lines().count(),
        "transcript length"
    );
}
