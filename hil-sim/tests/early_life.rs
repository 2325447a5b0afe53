//! The wear band early in a cone's life (issue 36): the study `hil-sim accuracy` prints,
//! held to the targets, in seconds (the horizon rows of every law; the life
//! rows of a few).

use hil_sim::early_life::{
    early_life_study, firmware, horizon_rows, life_rows, EarlyComparison, EarlyStudy, Law,
    Previous, Rule, Shape, HORIZONS, LAWS,
};

/// Cones per law in the test (the report has `SEEDS`).
const SEEDS: u64 = 60;

fn study() -> EarlyComparison {
    let rows = |est: &dyn hil_sim::early_life::Estimator| EarlyStudy {
        rows: LAWS
            .iter()
            .flat_map(|&law| horizon_rows(est, law, SEEDS, &HORIZONS))
            .collect(),
        life: Vec::new(),
    };
    EarlyComparison {
        now: rows(&firmware()),
        previous: rows(&Previous),
        seeds: SEEDS,
    }
}

#[test]
fn the_early_band_holds_the_truth_and_the_estimate_beats_the_model() {
    let s = study();
    let t = s.targets();
    let table = s.to_text();
    // Coverage of the ≈ 95 % band: ≥ 90 % at every horizon 600–10 000, every law
    // (7c11783's: 0 % on running-in cones from 1 000 cycles on).
    assert!(t.worst_inside_pct >= 90.0, "{t:?}\n{table}");
    // The point estimate at 600–1 500: over the laws no worse than 7c11783's, and
    // below the model's for every law but the model's own.
    for &(h, r) in &t.err_vs_previous {
        assert!(r <= 1.0, "at {h}: {r} × 7c11783's error\n{table}");
    }
    assert!(t.worst_err_vs_model.0 < 1.0, "{t:?}\n{table}");
    assert!(t.met());
    // The previous release fails the coverage the issue reported (68 % on its cones).
    assert!(s.previous.worst_inside_pct() < 50.0, "{table}");
}

/// Laws and horizons the band's constants were not chosen on: other knees and settled
/// exponents, other exponents, checkpoints between the study's.
#[test]
fn the_band_holds_on_laws_and_horizons_it_was_not_tuned_on() {
    let held_out = [
        Law {
            name: "power-0.40",
            shape: Shape::Power(0.40),
        },
        Law {
            name: "power-0.55",
            shape: Shape::Power(0.55),
        },
        Law {
            name: "run-in-250/0.33",
            shape: Shape::RunIn {
                end: 250.0,
                settled: 0.33,
            },
        },
        Law {
            name: "run-in-350/0.28",
            shape: Shape::RunIn {
                end: 350.0,
                settled: 0.28,
            },
        },
        Law {
            name: "run-in-450/0.45",
            shape: Shape::RunIn {
                end: 450.0,
                settled: 0.45,
            },
        },
    ];
    let horizons = [700, 1_200, 2_000, 3_000, 7_000, 10_000];
    for law in held_out {
        for r in horizon_rows(&firmware(), law, SEEDS, &horizons) {
            assert!(r.inside_pct >= 90.0, "{r:?}");
        }
    }
}

/// Acting on the upper edge with a reading every 1 000 cycles: no cone's truth runs
/// past the limit, and the life it costs is a few per cent; the point estimate alone
/// would let the truth run past.
#[test]
fn the_upper_edge_covers_the_risk_for_a_few_per_cent_of_life() {
    for law in [LAWS[5], LAWS[8]] {
        let rows = life_rows(&firmware(), law, 12);
        let pick = |continued: bool, rule: Rule| {
            rows.iter()
                .find(|r| r.continued == continued && r.rule == rule)
                .cloned()
                .unwrap()
        };
        let upper = pick(true, Rule::Upper);
        assert!(upper.cones >= 10, "{upper:?}");
        assert_eq!(upper.past_pct, 0.0, "{upper:?}");
        assert!(upper.refused_pct < 8.0, "{upper:?}");
        let point = pick(true, Rule::Point);
        assert!(point.past_pct > 10.0, "{point:?}");
        let controller = pick(true, Rule::Controller);
        assert_eq!(controller.past_pct, 0.0, "{controller:?}");
    }
}

#[test]
fn the_study_reports_in_text_and_json() {
    let s = early_life_study(2, true);
    let text = s.to_text();
    for key in [
        "law             |  cycles | estimate err µm",
        "run-in-300/0.30 |    1500 |",
        "# targets:",
        "| continued | upper edge |",
    ] {
        assert!(text.contains(key), "{key} missing:\n{text}");
    }
    let json = s.to_json();
    assert!(!json.contains('\n'));
    for key in [
        "\"horizons\":[600, 800, 1000, 1500, 5000, 10000]",
        "\"targets\":{\"worst_inside_pct\":",
        "\"previous\":{\"rows\":[{\"law\":\"model\",\"at_cycles\":600,",
        "\"rule\":\"controller\"",
    ] {
        assert!(json.contains(key), "{key} missing: {json}");
    }
}
