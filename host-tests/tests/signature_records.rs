//! The docking signature's persisted format never changes silently (issue 34): the
//! flashes of a machine that docked three times with the first release of the store
//! (`fixtures/signature-records-v1.txt`: two OK dockings learning the reference, then a
//! NOK one, `debris`) are read by today's code to what that release showed — `curve nok
//! 1`, `curve ref`, `history`'s signature columns, `wear`, the PLC's registers — and its
//! summary and reference frames are what today's code writes for the values it reads
//! back, byte for byte.
//!
//! To record the fixture again (only for an intended change of the format, with the
//! change drawn in `logic/src/wear/signature/records.rs` and a reader for the old one):
//! `SIGNATURE_RECORD=1 cargo test -p host-tests --test signature_records`.

use docking_logic::modbus::{input_registers, ir, status};
use docking_logic::sequencer::{Request, State};
use docking_logic::signature::records::{kind, Reference, Summary, REFERENCE_LEN, SUMMARY_LEN};
use hil_sim::flash::{SharedFlash, SimFlash};
use hil_sim::rig::{sig_flash_array, Rig, RigOptions};

const FIXTURE: &str = "fixtures/signature-records-v1.txt";

/// Bytes a fixture line holds.
const LINE: usize = 64;

/// The machine the fixture was recorded on: two dockings, then one with debris in the
/// bore, each followed by its rest (the records written).
fn record() -> (SharedFlash, SharedFlash) {
    let mut rig = Rig::booted(RigOptions::new(80));
    for k in 0..3 {
        if k == 2 {
            rig.devices().script.borrow_mut().bump = Some(hil_sim::sigscene::DEBRIS);
        }
        let done = rig.ctrl.status().cycles_completed;
        rig.ctrl.request(Request::StartCycle);
        while !(rig.ctrl.state() == State::Idle && rig.ctrl.status().cycles_completed > done) {
            rig.tick();
            while rig.ctrl.next_event().is_some() {}
        }
        for _ in 0..60 {
            rig.tick();
        }
    }
    (rig.flash.clone(), rig.sig_flash.clone())
}

/// `name offset hex` lines of every 64-byte piece of `f` that is not erased.
fn dump(name: &str, f: &SharedFlash, out: &mut String) {
    let bytes = f.with(|f| f.contents().to_vec());
    for (k, piece) in bytes.chunks(LINE).enumerate() {
        if piece.iter().any(|&b| b != 0xFF) {
            let hex: String = piece.iter().map(|b| format!("{b:02x}")).collect();
            out.push_str(&format!("{name} {:06x} {hex}\n", k * LINE));
        }
    }
}

/// The fixture's flashes: the odometer's and the signature's.
fn load() -> (SharedFlash, SharedFlash) {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/fixtures/signature-records-v1.txt"
    );
    if std::env::var_os("SIGNATURE_RECORD").is_some() {
        let (odo, sig) = record();
        let mut out = String::from(
            "# The docking signature's flash after three dockings (two OK, one NOK: debris), written by issue 34's first store; host-tests/tests/signature_records.rs\n",
        );
        dump("odometer", &odo, &mut out);
        dump("signature", &sig, &mut out);
        std::fs::write(path, out).expect("write the fixture");
    }
    let text = std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{FIXTURE}: {e}"));
    let (odo, sig) = (
        SharedFlash::new(SimFlash::stm32f407_odometer()),
        SharedFlash::new(sig_flash_array()),
    );
    for line in text.lines().filter(|l| !l.starts_with('#')) {
        let mut w = line.split(' ');
        let (Some(name), Some(at), Some(hex)) = (w.next(), w.next(), w.next()) else {
            panic!("{FIXTURE}: {line}");
        };
        let at = u32::from_str_radix(at, 16).unwrap();
        let bytes: Vec<u8> = (0..hex.len())
            .step_by(2)
            .map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap())
            .collect();
        let f = match name {
            "odometer" => &odo,
            "signature" => &sig,
            _ => panic!("{FIXTURE}: {line}"),
        };
        f.with(|f| f.program(at, &bytes)).unwrap();
    }
    (odo, sig)
}

#[test]
fn a_machine_on_the_first_releases_records_shows_what_it_showed() {
    let (odo, sig) = load();
    let mut rig = Rig::with_flashes(RigOptions::new(80), odo, sig);
    for _ in 0..100 {
        rig.tick();
    }
    let nok = rig.command("curve nok 1 --json", 400);
    for want in [
        "{\"curve\":\"nok\",\"nok\":1,\"cycle\":3,",
        "\"insertion\":{\"verdict\":\"nok\",\"failed\":\"band3\",\"figure\":134.7,\"limit\":123.6,\"unit\":\"n\",\"at_mm\":10.663,",
        "\"extraction\":{\"verdict\":\"ok\",\"failed\":null,",
        "\"figures\":{\"work_nmm\":4068.154,\"plateau_n\":158.9,\"step_mm\":14.936,\"end_n\":125.4,\"ext_peak_n\":206.0,",
    ] {
        assert!(nok.contains(want), "{want}: {nok}");
    }
    let reference = rig.command("curve ref --json", 400);
    assert!(
        reference.starts_with("{\"curve\":\"ref\",\"cycle\":0,\"reference_dockings\":2,"),
        "{reference}"
    );
    let h = rig.command("history 3", 400);
    let rows: Vec<&str> = h.lines().collect();
    assert_eq!(rows.len(), 3, "{h}");
    assert!(rows[0].contains(" signature=nok failed=band3 "), "{h}");
    assert!(rows[1].contains(" signature=ok failed=none "), "{h}");
    assert!(rows[2].contains(" signature=ok failed=none "), "{h}");
    let w = rig.command("wear", 400);
    assert!(
        w.contains(" signature_judged=3 signature_nok=1 reference_dockings=2 reference_of=20 signature_cycle=3 signature=nok signature_failed=band3 "),
        "{w}"
    );
    let regs = input_registers(&rig.ctrl);
    assert_ne!(regs[0] & status::SIGNATURE_NOK, 0);
    assert_eq!(regs[usize::from(ir::SIG_VERDICT)], 2);
    assert_eq!(regs[usize::from(ir::SIG_FAILED)], 4, "band3");
}

#[test]
fn its_summary_and_reference_frames_are_what_todays_code_writes() {
    let (odo, sig) = load();
    let mut rig = Rig::with_flashes(RigOptions::new(80), odo, sig);
    let store = rig.ctrl.signature_store().expect("the store opens");
    // The newest summary: decoded, then encoded again.
    let (s, at) = store.newest_summary().unwrap().expect("a summary");
    assert_eq!((s.lifetime_cycle, s.cone_id, s.cone_nok), (3, 1, 1));
    let log = store.log_mut();
    let f = log.newest(kind::SUMMARY, 0).unwrap().unwrap();
    assert_eq!(f.offset, at);
    let mut bytes = [0u8; SUMMARY_LEN];
    log.read(&f, 0, &mut bytes).unwrap();
    assert_eq!(
        Summary::from_bytes(&bytes).map(|s| s.to_bytes()),
        Some(bytes)
    );
    // The reference: read back, then its bytes as today's code writes them.
    let mut r = Reference::empty(1);
    assert!(store.read_reference(1, &mut r).unwrap());
    assert_eq!((r.cone_id, r.n), (1, 2));
    let log = store.log_mut();
    let f = log.newest(kind::REFERENCE, 0).unwrap().unwrap();
    let mut bytes = vec![0u8; REFERENCE_LEN];
    log.read(&f, 0, &mut bytes).unwrap();
    let again: Vec<u8> = (0..REFERENCE_LEN).map(|a| r.byte(a)).collect();
    assert_eq!(again, bytes);
}
