//! `hil-sim signature-study` (issue 34, "can it see wear?"): the 3→4 step's depth moves
//! with the bore's wear as the plant's geometry says and tells a few µm of wear after
//! 20 dockings at either rate, untouched by a friction drift; the forces' figures move
//! less with wear than with a ± 20 % friction drift; and a worn cone is not NOK for
//! its step's move. The full study (40 dockings a
//! point, both rates, 0.7 s in release): `cargo run --release -p hil-sim --
//! signature-study`.

use hil_sim::sigstudy::{run, true_step_um};

#[test]
fn the_step_sees_wear_and_the_forces_see_friction() {
    let studies = run(8, &[10, 80], 3);
    // The plant's geometry: L* = (D2 − D1·cos θ0)/sin θ0, on the firmware's depth axis
    // (×1.2/4 of Eq. 7's time axis, docs/physics.md §8.3): ≈ 6.05 µm of depth a µm.
    let geometric = (true_step_um(100.0) - true_step_um(0.0)) / 100.0;
    assert!((5.9..6.2).contains(&geometric), "{geometric}");
    for r in &studies {
        let step = &r.sensitivity[0];
        assert_eq!(step.figure, "step_um");
        assert!(
            (step.slope / geometric - 1.0).abs() < 0.1,
            "{} SPS: step slope {} against {geometric}",
            r.rate_sps,
            step.slope
        );
        // After 20 dockings: a few µm of wear; a friction drift moves it by < 1 µm.
        assert!(step.min_wear_um[1] < 10.0, "{} SPS: {step:?}", r.rate_sps);
        assert!(step.floor_um < 1.0, "{} SPS: {step:?}", r.rate_sps);
        // The objects move with a worn cone's step: no band of phase 4 and no
        // extraction peak fails at any wear of the study (0–400 µm; they all did from
        // 100–200 µm on while the objects sat on the new cone's step).
        for l in &r.levels {
            let moved_wrong: Vec<_> = l
                .failed
                .iter()
                .filter(|(o, _)| {
                    ["band3", "band4", "ext_band3", "ext_band4", "ext_peak"].contains(o)
                })
                .collect();
            assert!(
                moved_wrong.is_empty(),
                "{} SPS, {} µm: {moved_wrong:?}",
                r.rate_sps,
                l.wear_um
            );
        }
        for f in &r.sensitivity[1..] {
            assert!(
                f.floor_um > 100.0,
                "{} SPS: {} is mimicked by a friction drift only above 100 µm: {f:?}",
                r.rate_sps,
                f.figure
            );
        }
    }
}
