//! The `hil-sim profile` command, run as a user runs it.

mod common;

use common::{run, usage_error};

fn rows(csv: &str) -> Vec<Vec<f64>> {
    let mut lines = csv.lines();
    assert_eq!(lines.next(), Some("t_s,phase,n1_n,n2_n,n3_n,n4_n"));
    lines
        .map(|l| l.split(',').map(|x| x.parse().unwrap()).collect())
        .collect()
}

#[test]
fn insertion_peak_and_integral_at_a_fine_rate() {
    let (code, out, _) = run(&["profile", "--rate", "2000"]);
    assert_eq!(code, 0);
    let r = rows(&out);
    assert_eq!(r.first().unwrap()[0], 0.0);
    assert_eq!(r.last().unwrap()[0], 25.0);
    let peak = r.iter().max_by(|a, b| a[4].total_cmp(&b[4])).unwrap();
    assert!(
        (peak[4] - 206.34).abs() < 0.005 && (peak[0] - 12.445).abs() < 1e-9,
        "{peak:?}"
    );
    assert_eq!(peak[1], 4.0);
    // Trapezoid over the printed samples.
    let integral: f64 = r
        .windows(2)
        .map(|w| (w[1][0] - w[0][0]) * (w[0][4] + w[1][4]) / 2.0)
        .sum();
    let rel = (integral - 3368.94).abs() / 3368.94;
    assert!(rel < 0.001, "integral {integral} off by {rel}");
    // Phases in order 1→2→3→4.
    let phases: Vec<f64> = r.iter().map(|x| x[1]).collect();
    assert!(phases
        .windows(2)
        .all(|w| w[1] == w[0] || w[1] == w[0] + 1.0));
}

#[test]
fn extraction_is_the_mirror_of_insertion() {
    let (_, ins, _) = run(&["profile", "--rate", "40"]);
    let (code, ext, _) = run(&["profile", "--rate", "40", "--stroke", "extract"]);
    assert_eq!(code, 0);
    let (i, e) = (rows(&ins), rows(&ext));
    assert_eq!(i.len(), e.len());
    for (a, b) in i.iter().zip(e.iter().rev()) {
        assert_eq!(&a[1..], &b[1..]);
    }
    assert_eq!(e.first().unwrap()[1], 4.0);
    assert_eq!(e.last().unwrap()[1], 1.0);
}

#[test]
fn bad_arguments_get_one_line_and_exit_2() {
    for args in [
        &["profile", "--rate", "0"][..],
        &["profile", "--rate", "-80"],
        &["profile", "--rate", "abc"],
        &["profile", "--rate", "NaN"],
        &["profile", "--rate"],
        &["profile", "--stroke", "sideways"],
        &["profile", "--bogus", "1"],
        // No command or an unknown one: the commands, one a line
        // (scene_cli.rs, `no_command_or_an_unknown_one_prints_the_commands_one_a_line`).
    ] {
        usage_error(args);
    }
}
