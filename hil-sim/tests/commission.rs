//! `hil-sim commission`: another machine's tuning as Rust source for the firmware's build
//! (`DOCKING_TUNING=FILE`). The example in `docs/` is compiled here exactly as `build.rs`
//! gives it to the board, and must be what the command makes today.

mod common;

use common::{run, usage_error};

mod example {
    include!("../../docs/tuning-example-18kg.rs");
}

/// A tuning file as `hil-sim commission` wrote it before the logic had its own crate
/// (its paths say `docking_controller::`), included the way the board's `tuning` module
/// includes one (src/board.rs).
mod before_crate_split {
    #[allow(unused_imports)]
    use docking_logic as docking_controller;
    include!("fixtures/tuning-before-crate-split.rs");
}

#[test]
fn a_tuning_file_written_before_the_crate_split_still_builds_and_sets_the_same() {
    let new = || {
        docking_logic::controller::ControllerConfig::new(
            80,
            docking_logic::hx711::Calibration::SIM_DEFAULT,
        )
    };
    let (mut old_cfg, mut new_cfg) = (new(), new());
    before_crate_split::apply(&mut old_cfg);
    example::apply(&mut new_cfg);
    let (old, new) = (
        hil_sim::machine::Tuning::of(&old_cfg),
        hil_sim::machine::Tuning::of(&new_cfg),
    );
    // A file from before the signature's objects were commissioned (issue 34) leaves
    // the default objects; everything else it sets as today's.
    assert_eq!(
        old.signature,
        docking_logic::signature::objects::SignatureConfig::DEFAULT
    );
    assert_eq!(
        hil_sim::machine::Tuning {
            signature: new.signature,
            ..old
        },
        new
    );
}

fn heavy() -> hil_sim::plant::PlantParams {
    hil_sim::plant::PlantParams {
        mass_kg: 18.0,
        mu2: 0.1,
        ..hil_sim::plant::PlantParams::PAPER
    }
}

#[test]
fn the_generated_tuning_compiles_and_sets_what_commissioning_computed() {
    let mut cfg = docking_logic::controller::ControllerConfig::new(
        80,
        docking_logic::hx711::Calibration::SIM_DEFAULT,
    );
    example::apply(&mut cfg);
    let want = hil_sim::machine::Tuning::for_plant(heavy()).unwrap();
    assert_eq!(hil_sim::machine::Tuning::of(&cfg), want);
    // The docking signature's objects sit on this machine's curve (issue 34), not on
    // Eq. 7's: its phase-4 forces are 1.7 times the paper machine's.
    assert_ne!(
        cfg.signature.nominal,
        &docking_logic::signature::objects::EQ7_CURVE
    );
    assert_eq!(cfg.signature.nominal, want.signature.nominal);
    assert_eq!(cfg.signature.step_um_per_wear_mm, 6_047);
    // The builder's names for Modbus device identification.
    assert_eq!(cfg.identity.vendor, "Example Machines Ltd");
    assert_eq!(cfg.identity.product, "AutoDock 18 (example)");
}

#[test]
fn the_example_is_what_the_command_makes_today() {
    let (code, out, _) = run(&[
        "commission",
        "--model",
        "plant",
        "--mass-kg",
        "18",
        "--mu2",
        "0.1",
        "--vendor",
        "Example Machines Ltd",
        "--product",
        "AutoDock 18 (example)",
    ]);
    assert_eq!(code, 0);
    let kept = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../docs/tuning-example-18kg.rs"
    ))
    .unwrap();
    assert_eq!(out, kept, "regenerate: hil-sim commission --model plant --mass-kg 18 --mu2 0.1 --vendor 'Example Machines Ltd' --product 'AutoDock 18 (example)' > docs/tuning-example-18kg.rs");
}

#[test]
fn commission_refuses_what_it_cannot_tune() {
    for bad in [
        &["commission"][..],
        &["commission", "--model", "eq7"],
        &[
            "commission",
            "--model",
            "plant",
            "--mass-kg",
            "40",
            "--mu2",
            "0.05",
        ],
        &["commission", "--model", "plant", "--mu1", "x"],
        &["commission", "--model", "plant", "--vendor", ""],
        &["commission", "--model", "plant", "--product", "Tab\there"],
    ] {
        usage_error(bad);
    }
}
