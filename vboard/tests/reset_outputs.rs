//! Issue 17, item 9: the motor and PLC outputs are driven to their safe levels by the
//! first instructions after a reset (`__pre_init`), not 2–3 ms later in `init`, after
//! RAM initialisation at 16 MHz, with only the board's pull resistors holding them
//! meanwhile. Checked on the GPIO registers (MODER, OTYPER, ODR) of the release image,
//! after a power-on and after a pin reset, at CPI 1 and under the ART model.
//!
//! Build the image first: `cargo build --release --target thumbv7em-none-eabihf`.
//! `VBOARD_FIRMWARE=path` runs these tests on another image.

use vboard::cpu::Timing;
use vboard::periph::gpio::Mode;
use vboard::scene::{Options, Session};
use vboard::soc::Soc;
use vboard::time::PS_PER_S;

const PS_PER_US: u64 = 1_000_000;
/// Every output safe this soon after the reset.
const WITHIN_US: u64 = 5;
/// How finely the board is stepped while watching, ps (a cycle at 16 MHz is 62.5 ns).
const STEP_PS: u64 = 50_000;

/// An output and its safe level: (port index, 0 = A; pin; level; name).
const SAFE: [(usize, u8, bool, &str); 8] = [
    (4, 11, true, "EN (PE11)"),
    (4, 9, false, "STEP (PE9)"),
    (3, 12, false, "lock IN1 (PD12)"),
    (3, 13, false, "lock IN2 (PD13)"),
    (3, 0, false, "READY (PD0)"),
    (3, 1, false, "MATED (PD1)"),
    (3, 2, false, "FAULT (PD2)"),
    (3, 3, false, "MAINTENANCE (PD3)"),
];

fn opts(timing: Timing) -> Options {
    let mut o = Options::new();
    if let Ok(f) = std::env::var("VBOARD_FIRMWARE") {
        o.firmware = f;
    }
    o.board.timing = timing;
    o
}

/// The outputs that are not a push-pull output at their safe level, as the registers
/// say.
fn not_safe(soc: &Soc) -> Vec<String> {
    SAFE.iter()
        .filter_map(|&(port, pin, high, name)| {
            let g = &soc.gpio[port];
            let otyper = g.read(0x04, 4, 0).unwrap_or(0);
            let odr = g.read(0x14, 4, 0).unwrap_or(0);
            let mode = g.mode(pin);
            let ok =
                mode == Mode::Output && otyper & (1 << pin) == 0 && (odr & (1 << pin) != 0) == high;
            (!ok).then(|| {
                format!(
                    "{name}: {mode:?}, {}, ODR {}",
                    if otyper & (1 << pin) != 0 {
                        "open-drain"
                    } else {
                        "push-pull"
                    },
                    u8::from(odr & (1 << pin) != 0)
                )
            })
        })
        .collect()
}

/// From the board's last reset, step until every output is safe (at most
/// `WITHIN_US`); returns how long it took, ps, or what is still not safe then.
fn time_to_safe(s: &mut Session) -> Result<u64, Vec<String>> {
    let (t0, _) = *s.board.resets.last().expect("a reset");
    let limit = t0 + WITHIN_US * PS_PER_US;
    loop {
        let bad = not_safe(s.board.soc());
        if bad.is_empty() {
            return Ok(s.now() - t0);
        }
        if s.now() >= limit {
            return Err(bad);
        }
        s.board.run_until((s.now() + STEP_PS).min(limit)).unwrap();
    }
}

/// They stay safe while the firmware initialises (RAM, clocks, peripherals): every
/// 10 µs for `ms` milliseconds.
fn stays_safe(s: &mut Session, ms: u64) {
    let end = s.now() + ms * 1_000 * PS_PER_US;
    while s.now() < end {
        s.board.run_until(s.now() + 10 * PS_PER_US).unwrap();
        let bad = not_safe(s.board.soc());
        assert!(bad.is_empty(), "at {} ps: {bad:?}", s.now());
    }
}

fn outputs_safe_from_the_first_instructions(timing: Timing) {
    let mut s = Session::new(opts(timing)).expect("board");
    // Power-on: every register at its reset value (inputs: the pulls hold the pins).
    assert!(!not_safe(s.board.soc()).is_empty(), "nothing driven yet");
    let t = time_to_safe(&mut s).unwrap_or_else(|bad| {
        panic!("{timing:?}: {WITHIN_US} µs after power-on, not safe: {bad:#?}")
    });
    println!(
        "{timing:?}: outputs safe {:.3} µs after power-on",
        t as f64 / 1e6
    );
    stays_safe(&mut s, 3);
    // Running, then NRST: the GPIO registers reset with the chip.
    s.run_for(PS_PER_S).unwrap();
    s.board.reset_pin();
    s.board.run_until(s.now() + 1).unwrap();
    let t = time_to_safe(&mut s).unwrap_or_else(|bad| {
        panic!("{timing:?}: {WITHIN_US} µs after a pin reset, not safe: {bad:#?}")
    });
    println!(
        "{timing:?}: outputs safe {:.3} µs after a pin reset",
        t as f64 / 1e6
    );
    assert_eq!(s.reset_causes(), vec!["power_on", "pin"]);
    stays_safe(&mut s, 3);
}

#[test]
fn outputs_were_left_to_the_pull_resistors_after_reset_at_cpi_1() {
    outputs_safe_from_the_first_instructions(Timing::Cpi);
}

#[test]
fn outputs_were_left_to_the_pull_resistors_after_reset_under_the_art_model() {
    outputs_safe_from_the_first_instructions(Timing::Art);
}
