//! The wear estimate on the image: the micrometer readings entered on the board's
//! console give the same estimate, to the bit, as the host's controller; and what a fit
//! costs the Cortex-M4 (`vboard estimate-cost`).

use hil_sim::rig::{Rig, RigOptions};
use vboard::scene::{estimate_cost, json_field, Options, Session};
use vboard::time::PS_PER_S;

const SESSION: [&str; 6] = [
    "pin set 2468",
    "maint 2468",
    "measure --baseline 25.993",
    "measure 26.004",
    "measure 26.019",
    "measure 26.031",
];

#[test]
fn the_board_and_the_host_estimate_the_same_wear() {
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(PS_PER_S).unwrap();
    for cmd in SESSION {
        let r = s.console(cmd, 5 * PS_PER_S).unwrap();
        assert!(r.starts_with("ok"), "{cmd}: {r}");
    }
    let board = s.console_json("wear --json").unwrap();
    let mut rig = Rig::new(RigOptions::new(80));
    for _ in 0..200 {
        rig.tick();
    }
    for cmd in SESSION {
        let r = rig.command(cmd, 200);
        assert!(r.starts_with("ok"), "{cmd}: {r}");
    }
    let host = rig.command("wear --json", 200);
    for key in [
        "wear_measured_mm",
        "wear_estimate_mm",
        "estimate_low_mm",
        "estimate_high_mm",
        "remaining_estimate_cycles",
        "remaining_estimate_low_cycles",
        "remaining_estimate_high_cycles",
        "baseline_bore_mm",
        "baseline_assumed",
        "readings",
    ] {
        let (b, h) = (json_field(&board, key), json_field(&host, key));
        assert!(b.is_some(), "{key} missing on the board: {board}");
        assert_eq!(b, h, "{key}: board {board} / host {host}");
    }
    assert_eq!(
        json_field(&board, "wear_measured_mm").as_deref(),
        Some("0.038000")
    );
}

#[test]
fn a_fit_is_metered_on_the_cortex_m4() {
    let c = estimate_cost(&Options::new(), 5).expect("board runs");
    assert_eq!(c.fit.len(), 5);
    assert!(c.fit.windows(2).all(|w| w[1].1 > w[0].1), "{c:?}");
    // Each reading adds a bounded cost (the logarithms and roots of one point).
    let per = (c.fit[4].1 - c.fit[0].1) / 4;
    assert!(
        (5_000..60_000).contains(&per),
        "{per} instructions per reading"
    );
    assert!(c.at > 1_000 && c.at < 100_000, "{}", c.at);
}
