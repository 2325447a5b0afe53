//! Issue 17's proof on the virtual board: under a console and Modbus flood, over seeds
//! and timing models, the control step keeps its period, the watchdog is fed, the
//! back-off finishes and the stops are fast — measured on the NVIC, IWDG and pin
//! models, not taken from the firmware. Build the image first:
//! `cargo build --release --target thumbv7em-none-eabihf`.
//!
//! The full sweep (`vboard sweep --flood`: `overload` and `estop`, seeds 1 to 10, CPI
//! 1, 2, 3 and the ART cache model) is ignored (about half an hour on two cores); CI
//! runs one seed a model.

use vboard::cpu::{BoardConfig, Timing};
use vboard::scene::{run, SceneOptions};
use vboard::sweep::{sweep, Model, Sweep, SweepOptions};

/// CPI `cpis`, and the ART cache model (flash wait states on a miss) at CPI 1.
fn models(cpis: &[u64]) -> Vec<Model> {
    let mut m: Vec<Model> = cpis
        .iter()
        .map(|&c| Model {
            label: format!("cpi {c}"),
            board: BoardConfig {
                cpi_milli: c * 1_000,
                ..BoardConfig::default()
            },
        })
        .collect();
    m.push(Model {
        label: "art 1".into(),
        board: BoardConfig {
            timing: Timing::Art,
            ..BoardConfig::default()
        },
    });
    m
}

fn flooded(scenes: &[&str], seeds: &[u64], cpis: &[u64]) -> Sweep {
    let base = SceneOptions {
        flood: true,
        ..SceneOptions::default()
    };
    let opts = SweepOptions {
        scenes: scenes.iter().map(|s| s.to_string()).collect(),
        seeds: seeds.to_vec(),
        models: models(cpis),
        base,
        jobs: std::thread::available_parallelism().map_or(1, |n| n.get()),
    };
    sweep(&opts, &|row| eprintln!("{}", row.to_text()))
}

/// Every target of the issue, for every run; the table in the message.
fn assert_targets(s: &Sweep) {
    let w = s.worst(None);
    let table = s.to_text();
    println!("{table}");
    assert!(w.runs > 0);
    // 80 SPS: 12.5 ms + 1 ms.
    assert!(
        w.control_period_max_ms.is_some_and(|p| p <= 13.5) && w.control_late == 0,
        "control period: {}\n{table}",
        w.to_text("overall")
    );
    assert_eq!(w.watchdog_feeds_missed, 0, "missed feeds\n{table}");
    // Nothing below the step holds it (the firmware's owner.rs): before, idle held the
    // controller for a console command and the step waited 256 µs at CPI 3.
    assert!(
        w.control_entry_latency_max_us
            .is_some_and(|l| l <= vboard::sweep::ENTRY_LATENCY_TARGET_US),
        "control entry latency: {}\n{table}",
        w.to_text("overall")
    );
    let (lo, hi) = w.backed_off_um.expect("the overload scene tripped");
    assert!(
        lo >= 1_900.0 && hi <= 2_100.0,
        "back-off {lo}–{hi} µm\n{table}"
    );
    assert!(
        w.stop_latency_pins_us.is_some_and(|l| l <= 100.0),
        "overload stop latency\n{table}"
    );
    assert!(
        w.estop_us.is_some_and(|l| l <= 10.0),
        "E-STOP edge → EN high\n{table}"
    );
    assert!(s.misses().is_empty(), "{:#?}\n{table}", s.misses());
}

#[test]
fn one_seed_at_cpi_1_and_3_and_the_cache_model_under_flood_meets_the_targets() {
    assert_targets(&flooded(&["overload", "estop"], &[1], &[1, 3]));
}

#[test]
#[ignore = "the full sweep: 80 runs, about half an hour on two cores"]
fn ten_seeds_at_cpi_1_2_3_and_the_cache_model_under_flood_meet_the_targets() {
    let seeds: Vec<u64> = (1..=10).collect();
    assert_targets(&flooded(&["overload", "estop"], &seeds, &[1, 2, 3]));
}

/// Without a flood the step keeps its period at CPI 3 too: the measurement sees the
/// step's entries while the machine moves (an interval of up to one period), and the
/// watchdog's reloads with them.
#[test]
fn control_period_and_watchdog_feeds_are_measured_while_moving() {
    let mut o = SceneOptions::default();
    o.session.board.cpi_milli = 3_000;
    let r = run("overload", &o).expect("board runs");
    let t = &r.timing;
    assert!(t.moving_s > 5.0, "{t:?}");
    let p = t.period_max_ms.expect("control task entries while moving");
    assert!((5.0..=13.5).contains(&p), "{t:?}");
    assert_eq!((t.late, t.feeds_missed), (0, 0), "{t:?}");
    let g = t.feed_gap_max_ms.expect("watchdog reloads while moving");
    assert!(g <= 13.5, "{t:?}");
    let j: serde_json::Value = serde_json::from_str(&r.to_json()).unwrap();
    let json_p = j["control_period_max_ms"].as_f64().expect("a number");
    assert!((json_p - p).abs() < 1e-5, "{json_p} / {p}");
    assert_eq!(j["control_late"], 0);
    assert_eq!(j["watchdog_feeds_missed"], 0);
    assert!(r.to_text().contains("longest control period"));
    // The step's entry latency (TIM2 pending → entered): measured while moving, never
    // more than over the whole run, and well inside a period.
    let l = t
        .entry_latency_max_us
        .expect("pend → entry pairs while moving");
    let all = t.entry_latency_max_us_all.expect("pend → entry pairs");
    assert!(l <= all && all < 12_500.0, "{t:?}");
    let json_l = j["control_entry_latency_max_us"]
        .as_f64()
        .expect("a number");
    assert!((json_l - l).abs() < 1e-5, "{json_l} / {l}");
    assert!(j["control_entry_latency_max_us_all"].as_f64().is_some());
}

#[test]
fn sweep_arguments_are_checked() {
    for args in [
        &["sweep", "--seeds", "x"][..],
        &["sweep", "--scene", "nope"],
        &["sweep", "--cpi", "20"],
    ] {
        let args: Vec<String> = args.iter().map(|s| s.to_string()).collect();
        let mut out = Vec::new();
        assert!(
            matches!(
                vboard::cli::run(&args, &mut out),
                Err(vboard::cli::Failure::Usage(_))
            ),
            "{args:?}"
        );
    }
}
