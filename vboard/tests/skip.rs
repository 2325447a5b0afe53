//! The emulator's shortcuts change nothing: every scene of the test suite gives the same
//! JSON — pins, instruction counts, latencies, the log, the trace digest (every edge and
//! byte with its time, every register, SRAM) — with each shortcut on and off, at CPI 1,
//! 2 and 3 and under the ART cache model. Only what measures the emulation itself
//! differs (`wall_time_s`, `mips`, `realtime_factor`, `realtime_factor_min`, and for the
//! loop skipping `skipped_instructions`). The shortcuts:
//!
//! * **skipping polling loops** (`--no-skip` turns it off). CI runs a sample that covers
//!   each kind of loop the image polls in (the sector erase's, the brown-out level's
//!   program, the clocks' ready bits) under every timing model;
//! * **taking interrupts and sleeping inside the engine's run** (`BoardConfig::in_run`):
//!   the run loop's work between two runs, done in the block hook and at each `wfi`.
//!   CI runs a moving axis's 20 kHz SysTick with its idle loop's `wfi`, and an E-STOP
//!   under a flooded console, at two timing models.
//!
//! The whole suite is the ignored tests:
//! `cargo test --release --test skip -- --ignored` (docs/vboard.md has its last run).

use vboard::cpu::Timing;
use vboard::periph::flash::FlashTiming;
use vboard::scene::{run, Options, SceneOptions};
use vboard::update::Cut;

/// The JSON of a run without what measures the emulation rather than the board (and,
/// unless `keep_skipped`, the instructions skipped); the instructions skipped.
fn board_json(name: &str, o: &SceneOptions, keep_skipped: bool) -> (String, u64) {
    let r = run(name, o).unwrap_or_else(|e| panic!("{name}: {e}"));
    let mut v: serde_json::Value = serde_json::from_str(&r.to_json()).expect("JSON");
    let m = v.as_object_mut().expect("an object");
    let skipped: &[&str] = if keep_skipped {
        &[]
    } else {
        &["skipped_instructions"]
    };
    for &k in [
        "wall_time_s",
        "mips",
        "realtime_factor",
        "realtime_factor_min",
    ]
    .iter()
    .chain(skipped)
    {
        assert!(m.remove(k).is_some(), "{k} missing");
    }
    (v.to_string(), r.skipped_instructions)
}

/// A model of the core's timing: CPI 1, 2, 3, or the ART's cache model at CPI 1.
#[derive(Clone, Copy, Debug)]
enum Model {
    Cpi(u64),
    Art,
}

const MODELS: [Model; 4] = [Model::Cpi(1), Model::Cpi(2), Model::Cpi(3), Model::Art];

/// A shortcut of the emulator.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Shortcut {
    /// Skipping polling loops.
    Skip,
    /// Interrupts and sleep inside the engine's run.
    InRun,
}

fn with(o: &SceneOptions, m: Model, shortcut: Shortcut, on: bool) -> SceneOptions {
    let mut o = o.clone();
    match m {
        Model::Cpi(c) => o.session.board.cpi_milli = c * 1_000,
        Model::Art => o.session.board.timing = Timing::Art,
    }
    match shortcut {
        Shortcut::Skip => o.session.board.skip = on,
        Shortcut::InRun => o.session.board.in_run = on,
    }
    o
}

/// Run `name` with the skipping on and off under `m`; the instructions skipped.
fn same(name: &str, o: &SceneOptions, m: Model) -> u64 {
    same_with(name, o, m, Shortcut::Skip)
}

/// Run `name` with `shortcut` on and off under `m`; the instructions skipped.
fn same_with(name: &str, o: &SceneOptions, m: Model, shortcut: Shortcut) -> u64 {
    let t = std::time::Instant::now();
    let keep_skipped = shortcut != Shortcut::Skip;
    let (on, skipped) = board_json(name, &with(o, m, shortcut, true), keep_skipped);
    let t_on = t.elapsed().as_secs_f64();
    let (off, none) = board_json(name, &with(o, m, shortcut, false), keep_skipped);
    eprintln!(
        "{name} {m:?} {shortcut:?}: {skipped} instructions skipped; {t_on:.1} s with, {:.1} s without",
        t.elapsed().as_secs_f64() - t_on
    );
    if shortcut == Shortcut::Skip {
        assert_eq!(none, 0, "{name} {m:?}: --no-skip skipped");
    }
    if on != off {
        let a: serde_json::Value = serde_json::from_str(&on).unwrap();
        let b: serde_json::Value = serde_json::from_str(&off).unwrap();
        let diff: Vec<String> = a
            .as_object()
            .unwrap()
            .iter()
            .filter(|(k, v)| b.get(k.as_str()) != Some(v))
            .map(|(k, v)| format!("{k}: {v} with, {} without", b[k.as_str()]))
            .collect();
        panic!("{name} {m:?} differs with {shortcut:?}: {diff:#?}");
    }
    skipped
}

fn default() -> SceneOptions {
    SceneOptions::default()
}

fn typical() -> SceneOptions {
    let mut o = SceneOptions::default();
    o.session.board.flash_timing = FlashTiming::Typical;
    o
}

fn flooded(rate_sps: u32) -> SceneOptions {
    SceneOptions {
        session: Options {
            rate_sps,
            ..Options::new()
        },
        flood: true,
        ..SceneOptions::default()
    }
}

/// Every scene the test suite runs, with its options.
fn suite() -> Vec<(&'static str, SceneOptions)> {
    // The scenes with the most polling first (erases, the brown-out level's program),
    // the long flooded ones last.
    let mut v = vec![
        ("boot", default()),
        ("sector-move", {
            let mut o = default();
            o.session.board.lsi_hz = 47_000;
            o
        }),
        ("update", typical()),
        ("update-bad", typical()),
        ("update-rollback", typical()),
    ];
    for cut in [Cut::Transfer, Cut::Swap, Cut::Boot] {
        for seed in [1, 2] {
            let mut o = typical();
            o.session.seed = seed;
            o.cut = Some(cut);
            v.push(("update-cut", o));
        }
    }
    v.extend([
        ("power-cut-write", default()),
        ("power-cycle", default()),
        ("maintenance-lockout", default()),
        ("nominal", default()),
        ("overload", default()),
        ("disconnect", default()),
        ("estop", default()),
        ("estop-bounce", default()),
        ("vehicle-pull", default()),
        ("heavy-default", default()),
        ("dock-hold", default()),
        ("nominal", flooded(80)),
        ("overload", flooded(80)),
        ("overload", flooded(10)),
        ("estop", flooded(80)),
    ]);
    v
}

/// The sample CI runs: the sector erase's wait (a watchdog reload and a cycle-counter
/// timeout in every iteration, polled from SRAM with every interrupt masked) under the
/// ART's caches and at CPI 3, the first boot (the clocks' ready bits, the brown-out
/// level's program and its wait) at CPI 2.
#[test]
fn skipping_the_polling_loops_changes_nothing_in_a_sample_of_the_suite() {
    let mut erase = default();
    erase.session.board.lsi_hz = 47_000;
    let skipped = [
        same("sector-move", &erase, Model::Art),
        same("sector-move", &erase, Model::Cpi(3)),
        same("boot", &default(), Model::Cpi(2)),
    ];
    // The comparison compares something: the loops were skipped.
    assert!(
        skipped[0] > 10_000_000 && skipped[1] > 10_000_000,
        "{skipped:?}"
    );
    assert!(skipped[2] > 0, "{skipped:?}");
}

/// Every scene of the suite at every timing model (2 × 4 runs of each: about an hour
/// on two cores).
#[test]
#[ignore]
fn skipping_the_polling_loops_changes_nothing_in_any_scene_of_the_suite() {
    let mut total = 0u64;
    for (name, o) in suite() {
        for m in MODELS {
            total += same(name, &o, m);
        }
    }
    eprintln!("{total} instructions skipped in all");
    assert!(total > 0);
}

/// The sample CI runs: a moving axis (`nominal`: a SysTick at 20 kHz, each one woken from
/// the idle loop's `wfi` and taken as the loop unmasks) at CPI 1, and an E-STOP pressed
/// while the console floods (`estop --flood`: the safety input's edge, the DMA's bytes,
/// nested interrupts) at CPI 2.
#[test]
fn interrupts_and_sleep_inside_the_run_change_nothing_in_a_sample_of_the_suite() {
    same_with("nominal", &default(), Model::Cpi(1), Shortcut::InRun);
    same_with("estop", &flooded(80), Model::Cpi(2), Shortcut::InRun);
}

/// Every scene of the suite at every timing model, interrupts and sleep inside the run
/// on and off.
#[test]
#[ignore]
fn interrupts_and_sleep_inside_the_run_change_nothing_in_any_scene_of_the_suite() {
    for (name, o) in suite() {
        for m in MODELS {
            same_with(name, &o, m, Shortcut::InRun);
        }
    }
}
