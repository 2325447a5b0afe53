//! `hil-sim scene` and `hil-sim bench` on the command line.

mod common;

use common::{run, usage_error};

#[test]
fn json_has_the_documented_fields() {
    let (code, out, _) = run(&["scene", "overload", "--rate", "80", "--seed", "4", "--json"]);
    assert_eq!(code, 0);
    assert_eq!(out.lines().count(), 1);
    for key in [
        "\"scene\":\"overload\"",
        "\"cycles_completed\":0",
        "\"faults\":[{\"kind\":\"overload\",\"cycle\":1,\"phase\":3,",
        "\"peak_force_n\":",
        "\"stop_latency_s\":0.0000",
        "\"final_state\":\"faulted\"",
    ] {
        assert!(out.contains(key), "{key} missing in {out}");
    }
    let (_, out, _) = run(&["scene", "nominal", "--json"]);
    assert!(
        out.contains("\"stop_latency_s\":null") && out.contains("\"faults\":[]"),
        "{out}"
    );
}

#[test]
fn bad_scene_arguments_exit_2_with_one_line() {
    for args in [
        &["scene"][..],
        &["scene", "meltdown"],
        &["scene", "nominal", "--rate", "81"],
        &["scene", "nominal", "--cycles", "0"],
        &["scene", "nominal", "--cycles", "-1"],
        &["scene", "nominal", "--seed", "x"],
        &["scene", "nominal", "--json", "yes"],
        &["bench", "--rate", "0"],
    ] {
        usage_error(args);
    }
}

/// `hil-sim` with no command, or an unknown one, printed its usage as one line of
/// 1,200 characters: it is one command a line, as `--help` has it.
#[test]
fn no_command_or_an_unknown_one_prints_the_commands_one_a_line() {
    for args in [&[][..], &["fly"]] {
        let (code, out, err) = run(args);
        assert_eq!(code, 2, "{args:?}");
        assert!(out.is_empty(), "{out}");
        let lines: Vec<&str> = err.lines().collect();
        assert!(lines.len() >= 9, "{err}");
        assert!(lines.iter().all(|l| l.len() < 160), "{err}");
        assert!(
            lines.iter().any(|l| l.trim_start().starts_with("serve ")),
            "{err}"
        );
    }
}

#[test]
fn bench_reports_figures() {
    let (code, out, _) = run(&["bench", "--cycles", "5"]);
    assert_eq!(code, 0);
    assert!(
        out.contains("ns per control step") && out.contains("faults 0"),
        "{out}"
    );
}

#[test]
fn another_machine_runs_from_the_command_line_with_its_configuration() {
    let heavy = [
        "--model",
        "plant",
        "--mass-kg",
        "18",
        "--mu2",
        "0.1",
        "--json",
    ];
    let args = |cfg: &'static str| {
        let mut v = vec!["scene", "nominal"];
        v.extend(heavy);
        v.extend(["--config", cfg]);
        v
    };
    let (code, out, _) = run(&args("matching"));
    assert_eq!(code, 0);
    assert!(
        out.contains("\"faults\":[]") && out.contains("\"cycles_completed\":1"),
        "{out}"
    );
    let (code, out, _) = run(&args("default"));
    assert_eq!(code, 0);
    assert!(out.contains("\"kind\":\"overload\""), "{out}");
    // A machine this load cell cannot protect, an unknown configuration, plant options
    // without the plant: one line on stderr, exit 2.
    for bad in [
        &[
            "scene",
            "nominal",
            "--model",
            "plant",
            "--mass-kg",
            "40",
            "--mu2",
            "0.05",
            "--config",
            "matching",
        ][..],
        &["scene", "nominal", "--config", "bespoke"],
        &["scene", "nominal", "--mass-kg", "18"],
        &["scene", "nominal", "--model", "plant", "--mu2", "0.9"],
    ] {
        usage_error(bad);
    }
}

/// `hil-sim COMMAND --help` on every command: its synopsis and one option a line,
/// naming every option the command's synopsis in USAGE takes.
#[test]
fn every_command_has_help_naming_its_options() {
    use hil_sim::cli::{run, COMMAND_HELP, USAGE};
    // USAGE's synopses, split at " | " before a command word (options have "|" too).
    let mut parts: Vec<String> = Vec::new();
    for piece in USAGE.trim_start_matches("usage: hil-sim ").split(" | ") {
        let word = piece.split_whitespace().next().unwrap_or("");
        match parts.last_mut() {
            Some(last) if !COMMAND_HELP.iter().any(|(c, _)| *c == word) => {
                last.push_str(" | ");
                last.push_str(piece);
            }
            _ => parts.push(piece.to_string()),
        }
    }
    assert!(parts.len() >= 8, "{parts:?}");
    for part in &parts {
        let cmd = part.split_whitespace().next().unwrap();
        let mut out = Vec::new();
        run(&[cmd.to_string(), "--help".to_string()], &mut out).unwrap();
        let help = String::from_utf8(out).unwrap();
        assert!(
            help.starts_with(&format!("hil-sim {cmd} ")),
            "{cmd}: {help}"
        );
        for opt in part
            .split(['[', ']', ' ', '|', '('])
            .filter(|t| t.starts_with("--"))
        {
            assert!(
                help.contains(opt),
                "{cmd} --help does not name {opt}: {help}"
            );
        }
    }
    let mut out = Vec::new();
    run(&["--help".to_string()], &mut out).unwrap();
    let all = String::from_utf8(out).unwrap();
    for (cmd, _) in COMMAND_HELP {
        assert!(
            all.contains(&format!("\n  {cmd} ")),
            "{cmd} missing from --help"
        );
    }
}
