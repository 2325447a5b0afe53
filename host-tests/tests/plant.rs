//! Acceptance of the plant model (`hil_sim::plant`): the reference's table of
//! values and residuals against Eq. 7 (`docs/physics.md` §8.4–§8.5), the
//! contact-set invariants over the stability sweep's ranges, a property test over random
//! valid parameters and times, and `hil-sim profile --model plant` / `accuracy` in
//! process.

use docking_logic::profile::forces_at_time;
use hil_sim::plant::{Contact, Plant, PlantParams, STROKE_S};
use proptest::prelude::*;

/// `docs/physics.md` §8.4, transcribed here independently of the library's copy:
/// t s, phase, θ °, N1, N2, N3, N4.
const TABLE: [(f64, u8, f64, [f64; 4]); 9] = [
    (0.0, 1, 2.8400, [67.2261, 21.7502, 112.6456, 0.0]),
    (3.75, 2, 2.8400, [61.1669, 14.7222, 115.0453, 0.0]),
    (7.25, 3, 2.8400, [54.6225, 33.5944, 105.4766, 0.0]),
    (10.0, 3, 2.8400, [50.2870, 28.9520, 107.0162, 0.0]),
    (12.4449, 3, 2.8400, [46.3249, 24.7093, 108.4232, 0.0]),
    (12.4450, 4, 2.4878, [51.2381, 0.0, 205.9897, 76.1839]),
    (16.0, 4, 1.6537, [38.3129, 0.0, 174.4185, 47.5177]),
    (20.0, 4, 1.1668, [28.8089, 0.0, 148.4407, 23.4990]),
    (25.0, 4, 0.8417, [20.8151, 0.0, 124.9648, 1.5774]),
];

fn reference() -> Plant {
    Plant::new(PlantParams::REFERENCE).unwrap()
}

fn valid(p: &hil_sim::plant::PlantPoint) -> bool {
    p.forces().iter().all(|f| f.is_finite() && *f >= 0.0)
        && p.theta_deg.is_finite()
        && (1..=4).contains(&p.phase)
}

#[test]
fn reference_table_to_1e_3() {
    let p = reference();
    assert_eq!(PlantParams::REFERENCE.v_model_mm_s, 4.0);
    for (t, phase, theta, f) in TABLE {
        let pt = p.at_time(t);
        assert_eq!(pt.phase, phase, "t {t}");
        assert!((pt.theta_deg - theta).abs() < 1e-3, "t {t}: {pt:?}");
        for (a, b) in pt.forces().iter().zip(f) {
            assert!((a - b).abs() < 1e-3, "t {t}: {pt:?}");
        }
    }
}

#[test]
fn residuals_against_eq7_are_the_references_r_column() {
    let p = reference();
    let mut max = [[0.0f64; 4]; 4];
    for k in 0..=25_000 {
        let t = k as f64 * 0.001;
        let pt = p.at_time(t);
        let e = forces_at_time(t);
        let d = [e.n1_n, e.n2_n, e.n3_n, e.n4_n];
        for (m, (a, b)) in max[pt.phase as usize - 1]
            .iter_mut()
            .zip(pt.forces().iter().zip(d))
        {
            *m = m.max((a - b).abs());
        }
    }
    // §4, column R: phases 1–2 to Eq. 7's rounding.
    assert!(max[0].iter().chain(&max[1]).all(|&x| x <= 0.02), "{max:?}");
    assert!(
        max[2][0] <= 4.84 && max[2][1] <= 5.18 && max[2][2] <= 1.71,
        "{max:?}"
    );
    assert!(max[3][2] <= 0.36 && max[3][3] <= 1.11, "{max:?}");
    // ... and not better: the model is the reconstruction, not a refit.
    assert!(
        max[2][2] > 1.69 && max[3][2] > 0.34 && max[3][3] > 1.09,
        "{max:?}"
    );
}

#[test]
fn both_readings_of_the_time_axis() {
    let fast = reference();
    assert!((fast.at_time(16.0).theta_deg - 1.6537).abs() < 1e-4);
    let slow = Plant::new(PlantParams {
        v_model_mm_s: 1.2,
        ..PlantParams::REFERENCE
    })
    .unwrap();
    assert!((slow.at_time(16.0).theta_deg - 2.176).abs() < 1e-3);
    // With the geometric boundary the slow reading reaches phase 4 only at
    // 7.25 + L*·cosθ0/1.2 = 24.56 s.
    let geo = Plant::new(PlantParams {
        v_model_mm_s: 1.2,
        ..PlantParams::PAPER
    })
    .unwrap();
    let t3 = geo.boundaries_s()[2];
    assert!((t3 - 24.5642).abs() < 1e-3, "{t3}");
    assert_eq!(geo.at_time(16.0).phase, 3);
    // Depths, not times, are what the plant computes: the same depth past the start of
    // a phase gives the same forces on either time axis.
    for (ph, past) in [(3u8, 4.0), (4, 10.0)] {
        let b = |p: &Plant| p.boundaries_mm()[ph as usize - 2] + past;
        let (x, y) = (slow.in_phase(ph, b(&slow)), fast.in_phase(ph, b(&fast)));
        assert_eq!((x.forces(), x.theta_deg), (y.forces(), y.theta_deg));
    }
}

/// The sweep's ranges (issue): mass 8–20 kg, µ1 0.05–0.3, µ2 0.05–0.3, γ 10–25°,
/// θ0 1.5–4°, both time axes, 0–30 s.
#[test]
fn sweep_invariants() {
    let mut lifts = [0u64; 4];
    for mass_kg in [8.0, 20.0] {
        for mu1 in [0.05, 0.17, 0.3] {
            for mu2 in [0.05, 0.15, 0.3] {
                for gamma_deg in [10.0, 15.0, 25.0] {
                    for theta0_deg in [1.5, 2.84, 4.0] {
                        for v_model_mm_s in [1.2, 4.0] {
                            let p = Plant::new(PlantParams {
                                mass_kg,
                                mu1,
                                mu2,
                                gamma_deg,
                                theta0_deg,
                                v_model_mm_s,
                                ..PlantParams::PAPER
                            })
                            .unwrap();
                            for k in 0..=300 {
                                let pt = p.at_time(k as f64 * 0.1);
                                assert!(valid(&pt), "{pt:?}");
                                let raw = p.nominal_forces(pt.depth_mm).unwrap();
                                let negative = raw.iter().any(|&f| f < 0.0);
                                // Every lift-off reported, none without cause.
                                assert_eq!(negative, pt.lifted.is_some(), "{raw:?} {pt:?}");
                                if let Some(c) = pt.lifted {
                                    lifts[c.index()] += 1;
                                    assert_eq!(pt.forces()[c.index()], 0.0);
                                }
                                if pt.phase == 4 {
                                    assert!(pt.iterations <= 8, "{pt:?}");
                                }
                            }
                        }
                    }
                }
            }
        }
    }
    // The reference's sweeps: N2 < 0 in phase 2 for µ2 = 0.30 or γ = 25°, N4 < 0 for
    // µ2 ≥ 0.25 or µ1 = 0.05 before 25 s, and for all after 25.4 s.
    assert!(lifts[Contact::Support2.index()] > 0, "{lifts:?}");
    assert!(lifts[Contact::SecondPoint.index()] > 0, "{lifts:?}");
}

#[test]
fn mass_scales_every_force() {
    let a = reference();
    let b = Plant::new(PlantParams {
        mass_kg: 24.4,
        ..PlantParams::REFERENCE
    })
    .unwrap();
    for k in 0..=300 {
        let t = k as f64 * 0.1;
        let (x, y) = (a.at_time(t), b.at_time(t));
        for (f, g) in x.forces().iter().zip(y.forces()) {
            assert!((2.0 * f - g).abs() < 1e-9 * g.max(1.0), "t {t}");
        }
        assert_eq!(x.lifted, y.lifted);
    }
}

#[test]
fn stroke_integral_of_n3() {
    // Per-phase trapezoid at 1 ms; the reference's 3377.1 N·s.
    let p = reference();
    let [t1, t2, t3] = p.boundaries_s();
    let v = p.params().v_model_mm_s;
    let mut total = 0.0;
    for (ph, a, b) in [(1, 0.0, t1), (2, t1, t2), (3, t2, t3), (4, t3, STROKE_S)] {
        let n = ((b - a) / 0.001).ceil() as u32;
        let h = (b - a) / n as f64;
        let f = |t: f64| p.in_phase(ph, v * t).n3_n;
        total += h * (0.5 * (f(a) + f(b)) + (1..n).map(|k| f(a + k as f64 * h)).sum::<f64>());
    }
    assert!((total - 3377.1).abs() < 0.05, "{total}");
}

fn params() -> impl Strategy<Value = PlantParams> {
    (
        1.0..100.0f64,
        0.0..=0.6f64,
        0.0..=0.6f64,
        1.0..=45.0f64,
        0.5..=10.0f64,
        0.1..=20.0f64,
        prop::option::of(0.0..30.0f64),
    )
        .prop_map(
            |(mass_kg, mu1, mu2, gamma_deg, theta0_deg, v, t3)| PlantParams {
                mass_kg,
                mu1,
                mu2,
                gamma_deg,
                theta0_deg,
                v_model_mm_s: v,
                t3_s: t3.map(|d| PlantParams::PAPER.t2_s + d),
                ..PlantParams::PAPER
            },
        )
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(256))]

    /// Any valid parameters, any time (including before contact and far past the
    /// stroke): finite, non-negative outputs, and a lift-off whenever the phase's
    /// nominal system has a negative force.
    #[test]
    fn prop_outputs_are_finite_and_non_negative(
        p in params(),
        times in prop::collection::vec(-5.0..200.0f64, 1..64),
    ) {
        let plant = Plant::new(p).unwrap();
        for t in times {
            let pt = plant.at_time(t);
            prop_assert!(valid(&pt), "{:?} at {}: {:?}", p, t, pt);
            if let Some(raw) = plant.nominal_forces(pt.depth_mm) {
                if raw.iter().any(|&f| f < 0.0) {
                    prop_assert!(pt.lifted.is_some(), "{:?} {:?}", raw, pt);
                }
            } else {
                prop_assert!(!pt.resolved);
            }
            if pt.phase == 4 {
                let tilt = plant.tilt(pt.depth_mm - plant.boundaries_mm()[2]);
                prop_assert!(tilt.bracketed && tilt.converged, "{:?}", tilt);
                prop_assert!(tilt.iterations <= 12, "{:?}", tilt);
            }
        }
    }
}

fn cli(args: &[&str]) -> Result<String, String> {
    let args: Vec<String> = args.iter().map(|s| s.to_string()).collect();
    let mut out = Vec::new();
    hil_sim::cli::run(&args, &mut out).map_err(|e| e.0)?;
    Ok(String::from_utf8(out).unwrap())
}

#[test]
fn profile_model_plant_prints_the_table() {
    let eq7 = cli(&["profile", "--rate", "10"]).unwrap();
    assert_eq!(
        eq7,
        cli(&["profile", "--rate", "10", "--model", "eq7"]).unwrap()
    );
    assert!(eq7.starts_with("t_s,phase,n1_n,n2_n,n3_n,n4_n\n"));
    let csv = cli(&[
        "profile", "--model", "plant", "--rate", "10000", "--t3-s", "12.445",
    ])
    .unwrap();
    let mut lines = csv.lines();
    assert_eq!(
        lines.next(),
        Some("t_s,phase,n1_n,n2_n,n3_n,n4_n,theta_deg")
    );
    let rows: Vec<Vec<f64>> = lines
        .map(|l| l.split(',').map(|x| x.parse().unwrap()).collect())
        .collect();
    assert_eq!(rows.len(), 250_001);
    for (t, phase, theta, f) in TABLE {
        let r = rows.iter().find(|r| (r[0] - t).abs() < 1e-7).unwrap();
        assert_eq!(r[1], phase as f64, "t {t}");
        assert!((r[6] - theta).abs() < 1e-3, "{r:?}");
        for (a, b) in r[2..6].iter().zip(f) {
            assert!((a - b).abs() < 1e-3, "{r:?}");
        }
    }
    // Default boundary from the geometry: 12.4449 s is already phase 4.
    let csv = cli(&["profile", "--model", "plant", "--rate", "10000"]).unwrap();
    assert!(csv.contains("\n12.444900,4,"), "boundary");
    // Extraction is the mirror.
    let ins = cli(&["profile", "--model", "plant", "--rate", "8", "--mu2", "0.3"]).unwrap();
    let ext = cli(&[
        "profile", "--model", "plant", "--rate", "8", "--mu2", "0.3", "--stroke", "extract",
    ])
    .unwrap();
    let strip = |s: &str| -> Vec<String> {
        s.lines()
            .skip(1)
            .map(|l| l.split_once(',').unwrap().1.to_string())
            .collect()
    };
    let (mut a, b) = (strip(&ins), strip(&ext));
    a.reverse();
    assert_eq!(a, b);
}

#[test]
fn profile_plant_bad_options_are_usage_errors() {
    for args in [
        &["profile", "--mu1", "0.2"][..],
        &["profile", "--model", "eq7", "--v-model", "1.2"],
        &["profile", "--model", "spline"],
        &["profile", "--model", "plant", "--mass-kg", "0"],
        &["profile", "--model", "plant", "--mass-kg", "abc"],
        &["profile", "--model", "plant", "--mu1", "-0.1"],
        &["profile", "--model", "plant", "--mu2", "0.61"],
        &["profile", "--model", "plant", "--gamma-deg", "90"],
        &["profile", "--model", "plant", "--theta0-deg", "NaN"],
        &["profile", "--model", "plant", "--theta0-deg", "inf"],
        &["profile", "--model", "plant", "--v-model", "0"],
        &["profile", "--model", "plant", "--t3-s", "7"],
        &["profile", "--model", "plant", "--mu2"],
    ] {
        let e = cli(args).unwrap_err();
        assert!(!e.contains('\n'), "{args:?}: {e}");
        assert!(e.starts_with("--"), "{args:?}: {e}");
    }
    let e = cli(&["profile", "--model", "plant", "--mu2", "0.61"]).unwrap_err();
    assert_eq!(e, "--mu2 must be a number from 0 to 0.6, got '0.61'");
}

#[test]
fn accuracy_plant_section() {
    let s = hil_sim::accuracy::plant_study();
    assert!(
        s.table_max_err_n < 1e-3 && s.table_max_err_theta_deg < 1e-3,
        "{s:?}"
    );
    assert!(s.sweep.ok(), "{:?}", s.sweep);
    assert!(s.sweep.evaluations >= 1_000_000);
    assert!(s.sweep.lifted.iter().sum::<u64>() > 0);
    assert!(s.sweep.worst_iterations <= 8, "{:?}", s.sweep);
    let j = s.to_json();
    assert!(!j.contains('\n'));
    for key in [
        "\"table_max_err_n\"",
        "\"residuals_vs_eq7\":[{\"phase\":1",
        "\"n3_integral\":[{\"step_s\":1,",
        "\"tilt\":[{\"cap\":1,",
        "\"ns_per_eval\"",
        "\"sweep\":{\"mass_kg\":[8,12,16,20]",
        "\"nan\":0,\"negative\":0,\"panics\":0",
        "\"ok\":true",
    ] {
        assert!(j.contains(key), "{key} missing: {j}");
    }
    let t = s.to_text();
    assert!(t.contains("stability sweep") && t.contains("— ok"), "{t}");
}
