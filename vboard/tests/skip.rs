//! Skipping polling loops changes nothing: every scene of the test suite gives the same
//! JSON — pins, instruction counts, latencies, the log, the trace digest (every edge and
//! byte with its time, every register, SRAM) — with the skipping on and with `--no-skip`,
//! at CPI 1, 2 and 3 and under the ART cache model. Only what measures the emulation
//! itself differs (`wall_time_s`, `mips`, `realtime_factor`, `realtime_factor_min`,
//! `skipped_instructions`).
//!
//! CI runs a sample that covers each kind of loop the image polls in (the sector
//! erase's, the brown-out level's program, the clocks' ready bits) under every timing
//! model; the whole suite is the ignored test:
//! `cargo test --release --test skip -- --ignored` (docs/vboard.md has its last run).

use vboard::cpu::Timing;
use vboard::periph::flash::FlashTiming;
use vboard::scene::{run, Options, SceneOptions};
use vboard::update::Cut;

/// The JSON of a run without what measures the emulation rather than the board.
fn board_json(name: &str, o: &SceneOptions) -> (String, u64) {
    let r = run(name, o).unwrap_or_else(|e| panic!("{name}: {e}"));
    let mut v: serde_json::Value = serde_json::from_str(&r.to_json()).expect("JSON");
    let m = v.as_object_mut().expect("an object");
    for k in [
        "wall_time_s",
        "mips",
        "realtime_factor",
        "realtime_factor_min",
        "skipped_instructions",
    ] {
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

fn with(o: &SceneOptions, m: Model, skip: bool) -> SceneOptions {
    let mut o = o.clone();
    match m {
        Model::Cpi(c) => o.session.board.cpi_milli = c * 1_000,
        Model::Art => o.session.board.timing = Timing::Art,
    }
    o.session.board.skip = skip;
    o
}

/// Run `name` with the skipping on and off under `m`; the instructions skipped.
fn same(name: &str, o: &SceneOptions, m: Model) -> u64 {
    let t = std::time::Instant::now();
    let (on, skipped) = board_json(name, &with(o, m, true));
    let t_on = t.elapsed().as_secs_f64();
    let (off, none) = board_json(name, &with(o, m, false));
    eprintln!(
        "{name} {m:?}: {skipped} instructions skipped; {t_on:.1} s with, {:.1} s without",
        t.elapsed().as_secs_f64() - t_on
    );
    assert_eq!(none, 0, "{name} {m:?}: --no-skip skipped");
    if on != off {
        let a: serde_json::Value = serde_json::from_str(&on).unwrap();
        let b: serde_json::Value = serde_json::from_str(&off).unwrap();
        let diff: Vec<String> = a
            .as_object()
            .unwrap()
            .iter()
            .filter(|(k, v)| b.get(k.as_str()) != Some(v))
            .map(|(k, v)| format!("{k}: {v} skipping, {} not", b[k.as_str()]))
            .collect();
        panic!("{name} {m:?} differs with the skipping: {diff:#?}");
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
