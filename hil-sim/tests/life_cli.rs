//! `hil-sim life`, `accuracy` and `endurance` on the command line.

mod common;

use common::{run, usage_error};

fn field(json: &str, key: &str) -> f64 {
    let at = json
        .find(&format!("\"{key}\":"))
        .unwrap_or_else(|| panic!("{key} missing in {json}"))
        + key.len()
        + 3;
    let rest = &json[at..];
    let end = rest.find([',', '}', ']']).unwrap();
    rest[..end].parse().unwrap()
}

#[test]
fn life_json_has_the_documented_fields_and_follows_eq17() {
    let (code, out, _) = run(&["life", "--cycles", "60", "--at", "1,50,60", "--json"]);
    assert_eq!(code, 0);
    assert_eq!(out.lines().count(), 1);
    assert!(
        out.starts_with("{\"material\":\"zqsn5-2\",\"points\":[{\"cycle\":1,\"wear_mm\":"),
        "{out}"
    );
    for key in ["life_cycles", "erases_per_sector_max", "remaining_cycles"] {
        field(&out, key);
    }
    // The cycle-50 point against Eq. 17's reduced-order form (the odometer's model).
    let p50 = &out[out.find("{\"cycle\":50,").unwrap()..];
    let wear = field(p50, "wear_mm");
    let eq = 0.01372 * (50.0f64 + 1.961_921_5).powf(0.3813) - 0.01774;
    assert!((wear - eq).abs() / eq < 0.01, "{wear} vs {eq}");
    let life = field(&out, "life_cycles");
    assert!((life - 45_270.0).abs() / 45_270.0 < 0.005, "{life}");
}

#[test]
fn life_materials_have_their_own_lives() {
    let life = |m: &str| {
        let (code, out, _) = run(&["life", "--cycles", "5", "--material", m, "--json"]);
        assert_eq!(code, 0, "{m}");
        field(&out, "life_cycles")
    };
    let (z, q, p) = (life("zqsn5-2"), life("QSn6-6-3"), life("cf-peek"));
    assert!(((q / z) - 1.0 / 0.5701).abs() < 0.01, "{q} / {z}");
    assert!((p - 90_540.0).abs() / 90_540.0 < 0.005, "{p}");
}

#[test]
fn life_text_is_a_table() {
    let (code, out, _) = run(&["life", "--cycles", "3"]);
    assert_eq!(code, 0);
    let mut lines = out.lines();
    assert_eq!(lines.next(), Some("cycle,wear_mm,remaining_cycles"));
    assert!(lines.next().unwrap().starts_with("1,0.00"));
    assert!(out
        .lines()
        .last()
        .unwrap()
        .starts_with("# zqsn5-2: the model's life "));
}

/// `life` names each life it reports: the model's and, with readings, the estimate's.
#[test]
fn life_names_the_model_and_the_estimate() {
    let readings = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/readings-1.3x.csv");
    let (code, out, err) = run(&["life", "--cycles", "2000", "--readings", readings]);
    assert_eq!(code, 0, "{err}");
    let last = out.lines().last().unwrap();
    assert!(
        last.starts_with("# zqsn5-2: the model's life ")
            && last.contains(" cycles (extrapolated); the estimate's life ")
            && last.contains(" cycles (from the readings, at cycle 2000)"),
        "{last}"
    );
}

#[test]
fn bad_life_arguments_exit_2_with_one_line() {
    for args in [
        &["life"][..],
        &["life", "--cycles", "0"],
        &["life", "--cycles", "-5"],
        &["life", "--cycles", "10", "--material", "unobtainium"],
        &["life", "--cycles", "10", "--at", "1,,3"],
        &["life", "--cycles", "10", "--at", "11"],
        &["life", "--cycles", "10", "--at", "0"],
        &["life", "--cycles", "10", "--at", "a"],
        &["life", "--cycles", "10", "--rate", "81"],
        &["endurance", "--cycles", "0"],
        &["accuracy", "--extra"],
    ] {
        usage_error(args);
    }
}

/// Write `text` to a fresh file under the target directory; its path.
fn readings_file(name: &str, text: &str) -> String {
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR"));
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p.to_string_lossy().into_owned()
}

#[test]
fn life_replays_a_technicians_readings() {
    // A cone that wears 1.3× the model, read every 100 cycles, baseline 25.991 mm.
    let model = |m: f64| 0.01372 * (m + 1.961_921_5).powf(0.3813) - 0.01774;
    let mut csv = String::from("cycle,bore_mm\n0,25.991\n");
    for m in (100..=400).step_by(100) {
        csv += &format!("{m},{:.3}\n", 25.991 + 1.3 * model(m as f64));
    }
    let path = readings_file("readings-ok.csv", &csv);
    let (code, out, err) = run(&[
        "life",
        "--cycles",
        "400",
        "--at",
        "100,400",
        "--readings",
        &path,
        "--json",
    ]);
    assert_eq!(code, 0, "{err}");
    let p400 = &out[out.find("{\"cycle\":400,").unwrap()..];
    let est = field(p400, "wear_estimate_mm");
    let (lo, hi) = (
        field(p400, "estimate_low_mm"),
        field(p400, "estimate_high_mm"),
    );
    let truth = 1.3 * model(400.0);
    assert!((est - truth).abs() < 0.003, "{est} vs {truth}");
    assert!(lo <= truth && truth <= hi, "{lo}..{hi} vs {truth}");
    assert!(
        field(p400, "wear_mm") < est,
        "the model alone is below the cone"
    );
    let (left_lo, left, left_hi) = (
        field(p400, "remaining_estimate_low_cycles"),
        field(p400, "remaining_estimate_cycles"),
        field(p400, "remaining_estimate_high_cycles"),
    );
    assert!(
        left_lo <= left && left <= left_hi,
        "{left_lo} {left} {left_hi}"
    );
    // The text table carries the same columns.
    let (code, out, _) = run(&[
        "life",
        "--cycles",
        "100",
        "--at",
        "100",
        "--readings",
        &path,
    ]);
    assert_eq!(code, 0);
    assert!(out.starts_with(
        "cycle,wear_mm,remaining_cycles,wear_estimate_mm,estimate_low_mm,estimate_high_mm,remaining_estimate_cycles,remaining_estimate_low_cycles,remaining_estimate_high_cycles\n100,"
    ));
}

#[test]
fn bad_readings_files_exit_2_with_one_line() {
    for (name, text) in [
        ("empty.csv", ""),
        ("no-baseline.csv", "100,26.010\n"),
        ("order.csv", "0,26.000\n200,26.050\n100,26.040\n"),
        ("same.csv", "0,26.000\n100,26.050\n100,26.051\n"),
        ("range.csv", "0,26.000\n100,41.000\n"),
        ("decimals.csv", "0,26.0001\n"),
        ("garbage.csv", "0,26.000\nhello\n"),
        ("sign.csv", "0,-26.000\n"),
    ] {
        let path = readings_file(name, text);
        let (code, out, err) = run(&["life", "--cycles", "10", "--readings", &path]);
        assert_eq!(code, 2, "{name}");
        assert!(out.is_empty(), "{name}");
        assert_eq!(err.lines().count(), 1, "{name}: {err}");
    }
    let (code, _, err) = run(&["life", "--cycles", "10", "--readings", "/nonexistent/r.csv"]);
    assert_eq!(code, 2);
    assert_eq!(err.lines().count(), 1, "{err}");
}

/// A long run shows progress on a terminal; on a pipe (a script, CI) stderr stays
/// empty.
#[test]
fn endurance_shows_progress_on_a_terminal_only() {
    let bar = hil_sim::cli::Progress::new("endurance", true);
    let line = bar.line(5_000_000, 10_000_000, 120.0);
    assert!(
        line.starts_with("endurance  [###############...............]   50 %  5000000 / 10000000 cycles, 2 min left"),
        "{line}"
    );
    assert!(bar.line(0, 10, 0.0).contains("  0 %  0 / 10 cycles"));
    let (code, out, err) = run(&["endurance", "--cycles", "3"]);
    assert_eq!(code, 0);
    assert!(out.starts_with("endurance: 3 cycles"), "{out}");
    assert!(err.is_empty(), "stderr is a pipe here: {err:?}");
}

/// What a life run computes does not change when it is made faster (issue 20): its
/// JSON, `wall_time_s` aside, as b859484 printed it, with and without readings — and as
/// issue 34 changed it: the signature store's writes after each docking take flash time
/// at rest (a part of a record a turn), which moves every later sample (by cycle 100 4
/// nm more wear, by cycle 250 1, by cycle 500 none; 1.6 s more simulated time).
/// `tools/life-ratio.sh` checks the full `life --cycles 45270` against
/// `tools/life-45270.json` the same way.
#[test]
fn life_computes_what_it_computed_before_the_speed_up() {
    let readings = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/readings-1.3x.csv");
    for (args, want) in [
        (
            &[
                "life",
                "--cycles",
                "500",
                "--at",
                "1,10,100,250,500",
                "--json",
            ][..],
            r#"{"material":"zqsn5-2","points":[{"cycle":1,"wear_mm":0.003018,"remaining_cycles":45267},{"cycle":10,"wear_mm":0.017609,"remaining_cycles":45258},{"cycle":100,"wear_mm":0.062279,"remaining_cycles":45168},{"cycle":250,"wear_mm":0.095237,"remaining_cycles":45018},{"cycle":500,"wear_mm":0.129194,"remaining_cycles":44768}],"not_reached":[],"life_cycles":45268,"limit_reached":false,"cycles_run":500,"erases_per_sector_max":0,"faults":0,"sim_time_s":29120.4}"#,
        ),
        (
            &[
                "life",
                "--cycles",
                "1000",
                "--at",
                "1,1000",
                "--readings",
                readings,
                "--json",
            ][..],
            r#"{"material":"zqsn5-2","points":[{"cycle":1,"wear_mm":0.003018,"remaining_cycles":45267,"wear_estimate_mm":0.003018,"estimate_low_mm":0.000000,"estimate_high_mm":0.048755,"remaining_estimate_cycles":45267,"remaining_estimate_low_cycles":6299,"remaining_estimate_high_cycles":1642125},{"cycle":1000,"wear_mm":0.173505,"remaining_cycles":44268,"wear_estimate_mm":0.225902,"estimate_low_mm":0.218359,"estimate_high_mm":0.233686,"remaining_estimate_cycles":23043,"remaining_estimate_low_cycles":6687,"remaining_estimate_high_cycles":4294967295}],"not_reached":[],"life_cycles":45268,"limit_reached":false,"cycles_run":1000,"erases_per_sector_max":0,"faults":0,"sim_time_s":58240.3}"#,
        ),
    ] {
        let (code, out, err) = run(args);
        assert_eq!(code, 0, "{args:?}: {err}");
        let wall = out.find(",\"wall_time_s\":").expect("wall_time_s");
        let got = format!("{}}}", &out[..wall]);
        assert_eq!(got, want, "{args:?}");
    }
}
