//! Console input side: line assembly, command parsing, maintenance PIN, JSON writer.
//!
//! Besides example tests, property tests push arbitrary byte streams through
//! `LineReader<128>` + `parse` and check that nothing panics, every line is at most
//! 128 bytes, events only happen at terminators, and every error displays as one line
//! of printable ASCII. `fuzz_console_million` runs the same property for 1,000,000
//! cases; it is ignored by default, run it by hand:
//!
//! ```text
//! cargo test --release -p host-tests --test console_input -- --ignored
//! ```
//!
//! `corpus_inputs_keep_invariants` checks the same invariants on every file in
//! `fuzz-corpus/console/` (one raw input per file).

use std::fmt;

use docking_logic::console::auth::{
    make_pin_record, AuthError, MaintenanceAuth, PinRecord, LOCKOUT_MS, MAX_FAILURES,
    PIN_HASH_ROUNDS, SESSION_IDLE_MS,
};
use docking_logic::console::json::{write_fixed, write_str_escaped, JsonObject};
use docking_logic::console::line::{LineError, LineEvent, LineReader, MAX_BYTES_PER_POLL};
use docking_logic::console::parse::{parse, Command, ParseError};
use docking_logic::material::Material;
use proptest::prelude::*;
use proptest::test_runner::TestCaseError;

// ---------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------

/// An owned [`LineEvent`].
#[derive(Debug, PartialEq, Eq)]
enum Ev {
    Line(String),
    Err(LineError),
}

fn line(s: &str) -> Ev {
    Ev::Line(s.to_owned())
}

fn feed<const N: usize>(r: &mut LineReader<N>, bytes: &[u8]) -> Vec<Ev> {
    let mut out = Vec::new();
    for &b in bytes {
        match r.push(b) {
            Some(LineEvent::Line(s)) => out.push(Ev::Line(s.to_owned())),
            Some(LineEvent::Error(e)) => out.push(Ev::Err(e)),
            None => {}
        }
    }
    out
}

fn lines(bytes: &[u8]) -> Vec<Ev> {
    feed(&mut LineReader::<128>::new(), bytes)
}

/// Parse error's message, checked to be one line of printable ASCII.
fn msg(e: &impl fmt::Display) -> String {
    let s = e.to_string();
    assert!(is_printable_line(&s), "{s:?}");
    s
}

fn is_printable_line(s: &str) -> bool {
    !s.is_empty() && s.len() <= 100 && s.bytes().all(|b| (0x20..=0x7E).contains(&b))
}

fn ok(line: &str) -> Command<'_> {
    match parse(line) {
        Ok(c) => c,
        Err(e) => panic!("{line:?}: {e}"),
    }
}

fn err(line: &str) -> ParseError {
    match parse(line) {
        Ok(c) => panic!("{line:?} parsed as {c:?}"),
        Err(e) => {
            msg(&e);
            e
        }
    }
}

// ---------------------------------------------------------------------------------
// LineReader
// ---------------------------------------------------------------------------------

#[test]
fn line_cr_lf_and_crlf_each_end_one_line() {
    assert_eq!(lines(b"status\r"), [line("status")]);
    assert_eq!(lines(b"status\n"), [line("status")]);
    assert_eq!(lines(b"status\r\n"), [line("status")]);
    // CRLF never yields a second (empty or repeated) line; mixed terminators work.
    assert_eq!(
        lines(b"a\r\nb\nc\rd\r\n\r\ne\n\n"),
        [line("a"), line("b"), line("c"), line("d"), line("e")]
    );
    // LF CR is two terminators; the second ends an empty line (ignored).
    assert_eq!(lines(b"a\n\rb\r"), [line("a"), line("b")]);
    // A NUL between CR and LF (telnet CR NUL) does not split the pair.
    assert_eq!(lines(b"a\r\0\nb\r"), [line("a"), line("b")]);
    // Nothing without a terminator.
    assert_eq!(lines(b"status"), []);
}

#[test]
fn line_split_across_pushes_keeps_state() {
    let mut r = LineReader::<128>::new();
    assert_eq!(feed(&mut r, b"sta"), []);
    assert_eq!(feed(&mut r, b"tus\r"), [line("status")]);
    assert_eq!(feed(&mut r, b"\n"), []);
    assert_eq!(feed(&mut r, b"wear\n"), [line("wear")]);
}

#[test]
fn line_blank_lines_and_nul_are_ignored() {
    assert_eq!(lines(b"\r\n\n\r \t \r\0\0\n"), []);
    assert_eq!(lines(b"st\0atus\n"), [line("status")]);
    // Leading/trailing blanks are kept in the line (the parser skips them).
    assert_eq!(lines(b"  wear\t\n"), [line("  wear\t")]);
}

#[test]
fn line_backspace_and_del_erase_last_char() {
    assert_eq!(lines(b"statux\x08s\n"), [line("status")]);
    assert_eq!(lines(b"statux\x7fs\n"), [line("status")]);
    assert_eq!(lines(b"wearxyz\x7f\x7f\x7f\n"), [line("wear")]);
    // On an empty line it does nothing (and the line stays empty).
    assert_eq!(lines(b"\x7f\x08\x7fwear\n"), [line("wear")]);
    assert_eq!(lines(b"ab\x7f\x7f\x7f\n"), []);
    // A multi-byte UTF-8 character is erased whole.
    assert_eq!(lines("x€\x7fy\n".as_bytes()), [line("xy")]);
    assert_eq!(lines("x😀\x08y\n".as_bytes()), [line("xy")]);
}

#[test]
fn line_too_long_reported_once_then_next_line_works() {
    let mut r = LineReader::<128>::new();
    let mut input = vec![b'a'; 1000];
    input.extend_from_slice(b"\r\nstatus\r\n");
    assert_eq!(
        feed(&mut r, &input),
        [Ev::Err(LineError::TooLong), line("status")]
    );
    // Exactly N bytes is fine, N + 1 is not.
    let exact = "b".repeat(128);
    assert_eq!(
        feed(&mut r, format!("{exact}\n").as_bytes()),
        [Ev::Line(exact.clone())]
    );
    assert_eq!(
        feed(&mut r, format!("{exact}c\n").as_bytes()),
        [Ev::Err(LineError::TooLong)]
    );
    // Backspace does not rescue an overflowed line.
    assert_eq!(
        feed(&mut r, format!("{exact}cc\x7f\x7f\x7f\nwear\n").as_bytes()),
        [Ev::Err(LineError::TooLong), line("wear")]
    );
}

#[test]
fn line_not_utf8_rejected_valid_multibyte_kept() {
    assert_eq!(lines(b"cone \xff\xfe\n"), [Ev::Err(LineError::NotUtf8)]);
    assert_eq!(lines(b"a\xc3\n"), [Ev::Err(LineError::NotUtf8)]); // truncated sequence
    assert_eq!(lines(b"\xed\xa0\x80\n"), [Ev::Err(LineError::NotUtf8)]); // surrogate
    assert_eq!(
        lines("serial é€😀\nwear\n".as_bytes()),
        [line("serial é€😀"), line("wear")]
    );
}

#[test]
fn line_escape_sequences_swallowed_and_line_rejected() {
    // Arrow keys (CSI and SS3 forms), a CSI with parameters, a lone ESC.
    for seq in [
        &b"\x1b[A"[..],
        b"\x1bOB",
        b"\x1b[1;5C",
        b"\x1b[200~",
        b"\x1b",
    ] {
        let mut input = b"stat".to_vec();
        input.extend_from_slice(seq);
        input.extend_from_slice(b"us\r\nwear\r\n");
        assert_eq!(
            lines(&input),
            [Ev::Err(LineError::ControlChar), line("wear")],
            "{seq:?}"
        );
    }
    // The swallowed tail never becomes text of the next line.
    assert_eq!(
        lines(b"\x1b[A\r\nhelp\n"),
        [Ev::Err(LineError::ControlChar), line("help")]
    );
    // A terminator inside an unfinished sequence still ends the line.
    assert_eq!(
        lines(b"x\x1b[12\nhelp\n"),
        [Ev::Err(LineError::ControlChar), line("help")]
    );
}

#[test]
fn line_other_control_chars_rejected_tab_kept() {
    for c in [0x01u8, 0x03, 0x07, 0x0c, 0x1f] {
        assert_eq!(
            lines(&[b's', c, b't', b'\n']),
            [Ev::Err(LineError::ControlChar)],
            "{c:#x}"
        );
    }
    // C1 control (U+009B, a one-character CSI on some terminals).
    assert_eq!(
        lines("a\u{9b}A\n".as_bytes()),
        [Ev::Err(LineError::ControlChar)]
    );
    assert_eq!(lines(b"history\t5\n"), [line("history\t5")]);
}

#[test]
fn line_error_precedence_too_long_then_control_then_utf8() {
    let mut long = vec![b'a'; 200];
    long.extend_from_slice(b"\x01\xff\n");
    assert_eq!(lines(&long), [Ev::Err(LineError::TooLong)]);
    assert_eq!(lines(b"\x01\xff\n"), [Ev::Err(LineError::ControlChar)]);
}

#[test]
fn line_reset_discards_partial_line() {
    let mut r = LineReader::<128>::new();
    assert_eq!(feed(&mut r, b"garbage\x1b["), []);
    r.reset();
    assert_eq!(feed(&mut r, b"wear\n"), [line("wear")]);
    assert_eq!(r.capacity(), 128);
}

#[test]
fn line_debug_hides_typed_text() {
    let mut r = LineReader::<128>::new();
    assert_eq!(feed(&mut r, b"maint 97531"), []);
    let d = format!("{r:?}");
    assert!(!d.contains("97531") && d.contains("len: 11"), "{d}");
}

#[test]
fn line_errors_display_short_printable_ascii() {
    for e in [
        LineError::TooLong,
        LineError::NotUtf8,
        LineError::ControlChar,
    ] {
        msg(&e);
    }
    assert_eq!(MAX_BYTES_PER_POLL, 64);
}

// ---------------------------------------------------------------------------------
// parse: happy paths
// ---------------------------------------------------------------------------------

#[test]
fn parse_read_commands_with_and_without_json() {
    assert_eq!(
        ok("help"),
        Command::Help {
            topic: None,
            json: false
        }
    );
    assert_eq!(
        ok("help --json"),
        Command::Help {
            topic: None,
            json: true
        }
    );
    assert_eq!(ok("version"), Command::Version { json: false });
    assert_eq!(ok("version --json"), Command::Version { json: true });
    assert_eq!(ok("status"), Command::Status { json: false });
    assert_eq!(ok("  status \t --json  "), Command::Status { json: true });
    assert_eq!(ok("wear"), Command::Wear { json: false });
    assert_eq!(ok("wear\t--json"), Command::Wear { json: true });
    assert_eq!(ok("faults"), Command::Faults { json: false });
    assert_eq!(ok("faults --json"), Command::Faults { json: true });
    assert!(ok("faults --json").json());
    assert!(!ok("clear-fault").json());
}

#[test]
fn parse_history_count_and_json_anywhere() {
    assert_eq!(ok("history"), Command::History { n: 10, json: false });
    assert_eq!(ok("history 1"), Command::History { n: 1, json: false });
    assert_eq!(
        ok("history 100"),
        Command::History {
            n: 100,
            json: false
        }
    );
    assert_eq!(
        ok("history 25 --json"),
        Command::History { n: 25, json: true }
    );
    assert_eq!(
        ok("history --json 25"),
        Command::History { n: 25, json: true }
    );
    assert_eq!(ok("history --json"), Command::History { n: 10, json: true });
    assert_eq!(ok("history 007"), Command::History { n: 7, json: false });
    for bad in ["0", "101", "1000", "-5", "+5", "5.0", "abc", "0x10", "٣"] {
        assert_eq!(
            err(&format!("history {bad}")),
            ParseError::BadArgument("N"),
            "{bad}"
        );
    }
    assert_eq!(err("history 5 6"), ParseError::ExtraArgument);
}

#[test]
fn parse_clear_fault() {
    assert_eq!(ok("clear-fault"), Command::ClearFault);
    assert_eq!(err("clear-fault now"), ParseError::ExtraArgument);
}

#[test]
fn parse_cone_replace() {
    assert_eq!(
        ok("cone replace zqsn5-2 SN-0001"),
        Command::ConeReplace {
            material: Material::ZQSn5_2,
            serial: "SN-0001",
            bore_um: None
        }
    );
    assert_eq!(
        ok("cone replace qsn6-6-3 a_b-C9"),
        Command::ConeReplace {
            material: Material::QSn6_6_3,
            serial: "a_b-C9",
            bore_um: None
        }
    );
    assert_eq!(
        ok("cone\treplace  CF-PEEK   x"),
        Command::ConeReplace {
            material: Material::CfPeek,
            serial: "x",
            bore_um: None
        }
    );
    let serial20 = "A".repeat(20);
    assert_eq!(
        ok(&format!("cone replace cf-peek {serial20}")),
        Command::ConeReplace {
            material: Material::CfPeek,
            serial: &serial20,
            bore_um: None
        }
    );
    assert_eq!(
        err(&format!("cone replace cf-peek {serial20}B")),
        ParseError::BadArgument("serial")
    );
    for bad in ["SN/1", "SN.1", "sé", "a'b", "SN:1"] {
        assert_eq!(
            err(&format!("cone replace cf-peek {bad}")),
            ParseError::BadArgument("serial"),
            "{bad}"
        );
    }
    assert_eq!(
        err("cone replace brass SN1"),
        ParseError::BadArgument("material")
    );
    assert_eq!(
        err("cone replace cf-peek"),
        ParseError::MissingArgument("serial")
    );
    assert_eq!(err("cone replace"), ParseError::MissingArgument("material"));
    assert_eq!(err("cone"), ParseError::MissingArgument("cone subcommand"));
    assert_eq!(
        err("cone swap cf-peek SN1"),
        ParseError::BadArgument("cone subcommand")
    );
    assert_eq!(
        err("cone replace cf-peek SN1 extra"),
        ParseError::ExtraArgument
    );
    assert_eq!(
        ok("cone replace qsn6-6-3 SN-2 --bore 26.012"),
        Command::ConeReplace {
            material: Material::QSn6_6_3,
            serial: "SN-2",
            bore_um: Some(26_012)
        }
    );
    assert_eq!(
        err("cone replace qsn6-6-3 SN-2 --bore"),
        ParseError::MissingArgument("d0_mm")
    );
    assert_eq!(
        err("cone replace qsn6-6-3 SN-2 --bore 41"),
        ParseError::BadArgument("d0_mm")
    );
    assert_eq!(
        err("cone replace qsn6-6-3 SN-2 --diameter 26"),
        ParseError::UnknownOption
    );
}

#[test]
fn parse_measure_baseline() {
    assert_eq!(
        ok("measure --baseline 25.991"),
        Command::Measure {
            bore_um: 25_991,
            baseline: true
        }
    );
    assert_eq!(
        err("measure --baseline"),
        ParseError::MissingArgument("d0_mm")
    );
    assert_eq!(err("measure --bore 26"), ParseError::UnknownOption);
    assert_eq!(err("measure 26 27"), ParseError::ExtraArgument);
    assert_eq!(
        err("measure"),
        ParseError::MissingArgument("bore_diameter_mm")
    );
    assert_eq!(
        ok("measurements --json"),
        Command::Measurements { json: true }
    );
}

#[test]
fn parse_measure_fixed_point() {
    assert_eq!(
        ok("measure 26.050"),
        Command::Measure {
            bore_um: 26_050,
            baseline: false
        }
    );
    assert_eq!(
        ok("measure 26.05"),
        Command::Measure {
            bore_um: 26_050,
            baseline: false
        }
    );
    assert_eq!(
        ok("measure 26.5"),
        Command::Measure {
            bore_um: 26_500,
            baseline: false
        }
    );
    assert_eq!(
        ok("measure 26"),
        Command::Measure {
            bore_um: 26_000,
            baseline: false
        }
    );
    assert_eq!(
        ok("measure 20.000"),
        Command::Measure {
            bore_um: 20_000,
            baseline: false
        }
    );
    assert_eq!(
        ok("measure 40"),
        Command::Measure {
            bore_um: 40_000,
            baseline: false
        }
    );
    assert_eq!(
        ok("measure 040.000"),
        Command::Measure {
            bore_um: 40_000,
            baseline: false
        }
    );
    for bad in [
        "26.0501",
        "-26",
        "+26",
        "2.6e1",
        "26e0",
        "nan",
        "NaN",
        "inf",
        "40.001",
        "19.999",
        "26.",
        ".5",
        "26,05",
        "26.0.5",
        "0x1A",
        "",
        "99999999999999999999",
    ] {
        let line = format!("measure {bad}");
        let expect = if bad.is_empty() {
            ParseError::MissingArgument("bore_diameter_mm")
        } else {
            ParseError::BadArgument("bore_diameter_mm")
        };
        assert_eq!(err(&line), expect, "{line}");
    }
    assert_eq!(err("measure 26 27"), ParseError::ExtraArgument);
}

#[test]
fn parse_calibrate() {
    assert_eq!(ok("calibrate tare"), Command::CalibrateTare);
    assert_eq!(
        ok("calibrate span 500"),
        Command::CalibrateSpan { force_mn: 500_000 }
    );
    assert_eq!(
        ok("calibrate span 1.000"),
        Command::CalibrateSpan { force_mn: 1_000 }
    );
    assert_eq!(
        ok("calibrate span 900.000"),
        Command::CalibrateSpan { force_mn: 900_000 }
    );
    assert_eq!(
        ok("calibrate span 12.345"),
        Command::CalibrateSpan { force_mn: 12_345 }
    );
    for bad in ["0.999", "900.001", "-1", "1e2", "12.3456", "inf"] {
        assert_eq!(
            err(&format!("calibrate span {bad}")),
            ParseError::BadArgument("force_n"),
            "{bad}"
        );
    }
    assert_eq!(
        err("calibrate span"),
        ParseError::MissingArgument("force_n")
    );
    assert_eq!(
        err("calibrate"),
        ParseError::MissingArgument("calibrate subcommand")
    );
    assert_eq!(
        err("calibrate zero"),
        ParseError::BadArgument("calibrate subcommand")
    );
    assert_eq!(err("calibrate tare 5"), ParseError::ExtraArgument);
    assert_eq!(err("calibrate span 5 6"), ParseError::ExtraArgument);
}

#[test]
fn parse_maint_and_pin_set() {
    assert_eq!(ok("maint 1234"), Command::Maint { pin: "1234" });
    assert_eq!(
        ok("maint 123456789012"),
        Command::Maint {
            pin: "123456789012"
        }
    );
    assert_eq!(ok("maint exit"), Command::MaintExit);
    assert_eq!(ok("pin set 000000"), Command::PinSet { pin: "000000" });
    for bad in ["123", "1234567890123", "12a4", "exit2", "-1234", "１２３４"] {
        assert_eq!(
            err(&format!("maint {bad}")),
            ParseError::BadArgument("pin"),
            "{bad}"
        );
        assert_eq!(
            err(&format!("pin set {bad}")),
            ParseError::BadArgument("new_pin"),
            "{bad}"
        );
    }
    assert_eq!(err("maint"), ParseError::MissingArgument("pin"));
    assert_eq!(err("maint 1234 5678"), ParseError::ExtraArgument);
    assert_eq!(err("maint exit now"), ParseError::ExtraArgument);
    assert_eq!(err("pin set"), ParseError::MissingArgument("new_pin"));
    assert_eq!(err("pin"), ParseError::MissingArgument("pin subcommand"));
    assert_eq!(
        err("pin reset 1234"),
        ParseError::BadArgument("pin subcommand")
    );
    assert_eq!(err("pin set 1234 5678"), ParseError::ExtraArgument);
}

// ---------------------------------------------------------------------------------
// parse: errors
// ---------------------------------------------------------------------------------

#[test]
fn parse_empty_and_unknown_command() {
    assert_eq!(err(""), ParseError::Empty);
    assert_eq!(err(" \t "), ParseError::Empty);
    let e = err("foo");
    assert!(matches!(&e, ParseError::UnknownCommand(w) if w.as_str() == "foo"));
    assert_eq!(e.to_string(), "unknown command 'foo'; type 'help'");
    // Command words are case-sensitive.
    assert!(matches!(err("STATUS"), ParseError::UnknownCommand(_)));
    assert!(matches!(err("Help"), ParseError::UnknownCommand(_)));
    assert!(matches!(err("--json"), ParseError::UnknownCommand(_)));
}

#[test]
fn parse_unknown_command_echo_is_sanitised_and_truncated() {
    let e = err("averyveryverylongcommandword");
    assert_eq!(
        e.to_string(),
        "unknown command 'averyveryver...'; type 'help'"
    );
    // Non-ASCII (here a C1 control, which the reader would already reject) → '?'.
    let e = err("st\u{9b}2Jé");
    assert_eq!(e.to_string(), "unknown command 'st?2J?'; type 'help'");
}

#[test]
fn parse_json_flag_rules() {
    for line in [
        "clear-fault --json",
        "cone replace cf-peek SN1 --json",
        "cone --json replace cf-peek SN1",
        "measure 26 --json",
        "calibrate tare --json",
        "calibrate span 10 --json",
        "maint 1234 --json",
        "maint exit --json",
        "pin set 1234 --json",
    ] {
        assert_eq!(err(line), ParseError::JsonNotSupported, "{line}");
    }
    assert_eq!(err("status --json --json"), ParseError::ExtraArgument);
    assert_eq!(err("status --jsno"), ParseError::UnknownOption);
    assert_eq!(err("history 5 --verbose"), ParseError::UnknownOption);
    assert_eq!(err("status now"), ParseError::ExtraArgument);
    // `help <command>` takes one command word.
    assert_eq!(err("help me"), ParseError::BadArgument("command"));
    assert_eq!(err("help status wear"), ParseError::ExtraArgument);
}

#[test]
fn parse_error_messages_are_one_printable_line() {
    let expected = [
        (
            "cone replace",
            "missing <material> (zqsn5-2 | qsn6-6-3 | cf-peek)",
        ),
        (
            "measure 41",
            "bad <bore_diameter_mm>; expected 20.000..40.000, up to 3 decimals",
        ),
        ("status x", "too many arguments; type 'help'"),
        ("status --x", "unknown option; only --json is accepted"),
        (
            "clear-fault --json",
            "--json only applies to help, version, status, wear, history, curve, measurements, faults",
        ),
    ];
    for (line, text) in expected {
        assert_eq!(msg(&err(line)), text, "{line}");
    }
}

#[test]
fn command_state_changing_and_names() {
    let table: [(&str, &str, bool); 14] = [
        ("help", "help", false),
        ("version", "version", false),
        ("status", "status", false),
        ("wear", "wear", false),
        ("history", "history", false),
        ("faults", "faults", false),
        ("clear-fault", "clear-fault", true),
        ("cone replace cf-peek S1", "cone replace", true),
        ("measure 26", "measure", false),
        ("calibrate tare", "calibrate tare", true),
        ("calibrate span 10", "calibrate span", true),
        ("maint 1234", "maint", false),
        ("maint exit", "maint exit", false),
        ("pin set 1234", "pin set", true),
    ];
    for (line, name, changing) in table {
        let c = ok(line);
        assert_eq!(c.name(), name, "{line}");
        assert_eq!(c.is_state_changing(), changing, "{line}");
    }
}

#[test]
fn command_debug_never_shows_pin() {
    let d = format!("{:?}", ok("maint 73915"));
    assert!(!d.contains("73915"), "{d}");
    let d = format!("{:?}", ok("pin set 842617"));
    assert!(!d.contains("842617"), "{d}");
    assert_eq!(
        format!("{:?}", ok("history 5")),
        "History { n: 5, json: false }"
    );
}

// ---------------------------------------------------------------------------------
// auth
// ---------------------------------------------------------------------------------

const SALT_A: [u8; 16] = [0x11; 16];
const SALT_B: [u8; 16] = [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15];

#[test]
fn auth_pin_record_validates_pin_format() {
    for good in ["1234", "000000", "123456789012"] {
        assert!(make_pin_record(good, SALT_A).is_ok(), "{good}");
    }
    for bad in [
        "",
        "123",
        "1234567890123",
        "12a4",
        " 1234",
        "1234 ",
        "１２３４",
    ] {
        assert_eq!(
            make_pin_record(bad, SALT_A).map(|_| ()),
            Err(AuthError::InvalidPin),
            "{bad}"
        );
    }
}

#[test]
fn auth_hash_differs_with_salt_and_pin_and_verifies() {
    let a = make_pin_record("1234", SALT_A).unwrap();
    let b = make_pin_record("1234", SALT_B).unwrap();
    let c = make_pin_record("1235", SALT_A).unwrap();
    let a2 = make_pin_record("1234", SALT_A).unwrap();
    assert_ne!(a.hash, b.hash);
    assert_ne!(a.hash, c.hash);
    assert_eq!(a.hash, a2.hash);
    assert_eq!(a.salt, SALT_A);
    assert!(a.verify("1234") && b.verify("1234"));
    assert!(!a.verify("1235") && !a.verify("12345") && !a.verify("abcd"));
    assert_eq!(PIN_HASH_ROUNDS, 256);
}

#[test]
fn auth_pin_record_bytes_roundtrip() {
    let a = make_pin_record("55555", SALT_B).unwrap();
    let bytes = a.to_bytes();
    assert_eq!(bytes.len(), 48);
    assert_eq!(&bytes[..16], &SALT_B);
    assert_eq!(&bytes[16..], &a.hash);
    let back = PinRecord::from_bytes(&bytes).unwrap();
    assert!(back.verify("55555"));
    assert!(PinRecord::from_bytes(&bytes[..47]).is_none());
    assert!(PinRecord::from_bytes(&[bytes.as_slice(), &[0]].concat()).is_none());
    assert!(PinRecord::from_bytes(&[0xFF; 48]).is_none());
}

#[test]
fn auth_no_pin_set() {
    let mut auth = MaintenanceAuth::new();
    assert_eq!(auth.try_enter(0, "1234", None), Err(AuthError::NoPinSet));
    assert!(!auth.is_active(0));
    assert_eq!(auth.failures(), 0);
}

#[test]
fn auth_five_wrong_pins_lock_out_even_the_right_pin() {
    let rec = make_pin_record("2468", SALT_A).unwrap();
    let mut auth = MaintenanceAuth::new();
    let t0 = 1_000_000;
    for i in 0..4u8 {
        assert_eq!(
            auth.try_enter(t0 + u64::from(i), "1111", Some(&rec)),
            Err(AuthError::WrongPin {
                attempts_left: MAX_FAILURES - 1 - i
            })
        );
    }
    let t5 = t0 + 10_000;
    assert_eq!(
        auth.try_enter(t5, "1111", Some(&rec)),
        Err(AuthError::LockedOut { remaining_s: 300 })
    );
    // The right PIN is refused while locked, up to the last millisecond.
    assert_eq!(
        auth.try_enter(t5 + 1, "2468", Some(&rec)),
        Err(AuthError::LockedOut { remaining_s: 300 })
    );
    assert_eq!(
        auth.try_enter(t5 + LOCKOUT_MS - 1, "2468", Some(&rec)),
        Err(AuthError::LockedOut { remaining_s: 1 })
    );
    assert!(!auth.is_active(t5 + LOCKOUT_MS - 1));
    assert_eq!(auth.lockout_remaining_s(t5 + 150_000), Some(150));
    // Accepted once LOCKOUT_MS has passed since the 5th failure.
    assert_eq!(auth.lockout_remaining_s(t5 + LOCKOUT_MS), None);
    assert_eq!(auth.try_enter(t5 + LOCKOUT_MS, "2468", Some(&rec)), Ok(()));
    assert!(auth.is_active(t5 + LOCKOUT_MS));
    assert_eq!(auth.failures(), 0);
    let msg_text = msg(&AuthError::LockedOut { remaining_s: 300 });
    assert_eq!(msg_text, "too many wrong PINs; locked for 300 s");
}

#[test]
fn auth_after_lockout_expires_a_wrong_pin_starts_a_fresh_count() {
    let rec = make_pin_record("2468", SALT_A).unwrap();
    let mut auth = MaintenanceAuth::new();
    for _ in 0..MAX_FAILURES {
        let _ = auth.try_enter(0, "0000", Some(&rec));
    }
    assert_eq!(
        auth.try_enter(LOCKOUT_MS, "0000", Some(&rec)),
        Err(AuthError::WrongPin { attempts_left: 4 })
    );
}

#[test]
fn auth_success_resets_failure_count() {
    let rec = make_pin_record("2468", SALT_B).unwrap();
    let mut auth = MaintenanceAuth::new();
    for round in 0..3u64 {
        for _ in 0..MAX_FAILURES - 1 {
            assert!(matches!(
                auth.try_enter(round, "9999", Some(&rec)),
                Err(AuthError::WrongPin { .. })
            ));
        }
        assert_eq!(auth.try_enter(round, "2468", Some(&rec)), Ok(()));
        assert_eq!(auth.failures(), 0);
    }
}

#[test]
fn auth_session_idle_timeout_touch_and_exit() {
    let rec = make_pin_record("2468", SALT_A).unwrap();
    let mut auth = MaintenanceAuth::new();
    assert!(!auth.is_active(0));
    auth.try_enter(5_000, "2468", Some(&rec)).unwrap();
    assert!(auth.is_active(5_000));
    assert!(auth.is_active(5_000 + SESSION_IDLE_MS - 1));
    assert!(!auth.is_active(5_000 + SESSION_IDLE_MS));
    // touch() restarts the idle timer.
    auth.touch(400_000);
    assert!(auth.is_active(400_000 + SESSION_IDLE_MS - 1));
    assert!(!auth.is_active(400_000 + SESSION_IDLE_MS));
    // touch() after expiry does not revive the session.
    auth.touch(400_000 + SESSION_IDLE_MS);
    assert!(!auth.is_active(400_000 + SESSION_IDLE_MS));
    auth.touch(400_000 + SESSION_IDLE_MS + 1);
    assert!(!auth.is_active(400_000 + SESSION_IDLE_MS + 1));
    // exit() ends it at once.
    auth.try_enter(2_000_000, "2468", Some(&rec)).unwrap();
    assert!(auth.is_active(2_000_001));
    auth.exit();
    assert!(!auth.is_active(2_000_001));
}

#[test]
fn auth_errors_display_printable() {
    for e in [
        AuthError::NoPinSet,
        AuthError::WrongPin { attempts_left: 3 },
        AuthError::LockedOut { remaining_s: 17 },
        AuthError::InvalidPin,
    ] {
        msg(&e);
    }
}

// ---------------------------------------------------------------------------------
// json
// ---------------------------------------------------------------------------------

fn fixed(v: i64, d: u8) -> String {
    let mut s = String::new();
    write_fixed(&mut s, v, d).unwrap();
    s
}

#[test]
fn json_string_escaping() {
    let mut s = String::new();
    write_str_escaped(&mut s, "\"\\\n\u{1}").unwrap();
    assert_eq!(s, r#""\"\\\u000a\u0001""#);
    let mut s = String::new();
    write_str_escaped(&mut s, "a\tb\rc\u{7f}\u{9b}\u{2028}é€😀").unwrap();
    assert_eq!(s, r#""a\u0009b\u000dc\u007f\u009b\u2028é€😀""#);
    // Keys are escaped too.
    let mut s = String::new();
    let mut o = JsonObject::new(&mut s);
    o.str("k\"\n", "v").unwrap();
    o.finish().unwrap();
    assert_eq!(s, r#"{"k\"\u000a":"v"}"#);
}

#[test]
fn json_fixed_point_printing() {
    assert_eq!(fixed(12_345, 3), "12.345");
    assert_eq!(fixed(-5, 3), "-0.005");
    assert_eq!(fixed(0, 3), "0.000");
    assert_eq!(fixed(1_000, 3), "1.000");
    assert_eq!(fixed(26_050, 3), "26.050");
    assert_eq!(fixed(-12_345, 2), "-123.45");
    assert_eq!(fixed(7, 0), "7");
    assert_eq!(fixed(-7, 0), "-7");
    assert_eq!(fixed(5, 1), "0.5");
    assert_eq!(fixed(i64::MIN, 3), "-9223372036854775.808");
    assert_eq!(fixed(i64::MAX, 0), "9223372036854775807");
}

#[test]
fn json_object_all_value_kinds_nested() {
    let mut s = String::new();
    let mut o = JsonObject::new(&mut s);
    o.str("cone", "cf-peek")
        .unwrap()
        .u64("cycles", 90_540)
        .unwrap()
        .i64("offset", -3)
        .unwrap()
        .bool("ok", true)
        .unwrap()
        .null("fault")
        .unwrap()
        .fixed("bore_mm", 26_050, 3)
        .unwrap()
        .raw("extra", "{\"a\":[1,2]}")
        .unwrap();
    o.array("faults", |a| {
        a.object(|f| {
            f.u64("code", 3)?.str("msg", "over\"load")?;
            Ok(())
        })?
        .object(|_| Ok(()))?
        .u64(1)?
        .i64(-1)?
        .str("x")?
        .bool(false)?
        .null()?
        .fixed(-5, 3)?
        .raw("[]")?
        .array(|_| Ok(()))?;
        Ok(())
    })
    .unwrap();
    o.object("limits", |l| {
        l.fixed("max_n", 900_000, 3)?;
        Ok(())
    })
    .unwrap();
    o.array("empty", |_| Ok(())).unwrap();
    o.finish().unwrap();
    assert_eq!(
        s,
        concat!(
            r#"{"cone":"cf-peek","cycles":90540,"offset":-3,"ok":true,"fault":null,"#,
            r#""bore_mm":26.050,"extra":{"a":[1,2]},"#,
            r#""faults":[{"code":3,"msg":"over\"load"},{},1,-1,"x",false,null,-0.005,[],[]],"#,
            r#""limits":{"max_n":900.000},"empty":[]}"#
        )
    );
    let mut s = String::new();
    JsonObject::new(&mut s).finish().unwrap();
    assert_eq!(s, "{}");
}

#[test]
fn json_raw_newlines_become_spaces() {
    let mut s = String::new();
    let mut o = JsonObject::new(&mut s);
    o.raw("r", "{\r\n\"a\":\n1}").unwrap();
    o.finish().unwrap();
    assert_eq!(s, "{\"r\":{  \"a\": 1}}");
    assert!(!s.contains(['\r', '\n']));
}

/// A writer that fails once `cap` bytes have been written.
struct Limited {
    out: String,
    cap: usize,
}

impl fmt::Write for Limited {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        if self.out.len() + s.len() > self.cap {
            return Err(fmt::Error);
        }
        self.out.push_str(s);
        Ok(())
    }
}

fn write_sample(w: &mut Limited) -> fmt::Result {
    let mut o = JsonObject::new(w);
    o.str("s", "a\"b\u{1}")?
        .fixed("f", -12_345, 3)?
        .u64("n", 42)?;
    o.array("a", |a| {
        a.object(|x| {
            x.bool("b", true)?;
            Ok(())
        })?
        .u64(7)?;
        Ok(())
    })?;
    o.finish()
}

#[test]
fn json_write_errors_propagate_at_every_cut() {
    let full = {
        let mut w = Limited {
            out: String::new(),
            cap: usize::MAX,
        };
        write_sample(&mut w).unwrap();
        w.out
    };
    assert_eq!(
        full,
        r#"{"s":"a\"b\u0001","f":-12.345,"n":42,"a":[{"b":true},7]}"#
    );
    for cap in 0..full.len() {
        let mut w = Limited {
            out: String::new(),
            cap,
        };
        assert_eq!(write_sample(&mut w), Err(fmt::Error), "cap {cap}");
        assert!(full.starts_with(&w.out));
    }
}

// ---------------------------------------------------------------------------------
// Properties
// ---------------------------------------------------------------------------------

const CAP: usize = 128;

/// What a run over one input saw (the corpus test checks the corpus covers both).
#[derive(Default, Debug)]
struct Seen {
    commands: usize,
    errors: usize,
}

/// Push `bytes` through `LineReader<128>` + `parse` and check the invariants.
fn check_stream(bytes: &[u8]) -> Result<Seen, TestCaseError> {
    let mut r = LineReader::<CAP>::new();
    let mut seen = Seen::default();
    for &b in bytes {
        let Some(ev) = r.push(b) else { continue };
        prop_assert!(b == b'\r' || b == b'\n', "event on byte {:#x}", b);
        match ev {
            LineEvent::Error(e) => {
                seen.errors += 1;
                let m = e.to_string();
                prop_assert!(is_printable_line(&m), "{:?}", m);
            }
            LineEvent::Line(l) => {
                prop_assert!(l.len() <= CAP, "line of {} bytes", l.len());
                prop_assert!(
                    !l.chars().any(|c| c != '\t' && c.is_control()),
                    "control char in {:?}",
                    l
                );
                prop_assert!(!l.trim_matches([' ', '\t']).is_empty());
                match parse(l) {
                    Ok(cmd) => {
                        seen.commands += 1;
                        check_command(&cmd)?;
                    }
                    Err(e) => {
                        seen.errors += 1;
                        let m = e.to_string();
                        prop_assert!(is_printable_line(&m), "{:?}", m);
                    }
                }
            }
        }
    }
    Ok(seen)
}

/// Values carried by a parsed command are within the grammar's limits.
fn check_command(cmd: &Command<'_>) -> Result<(), TestCaseError> {
    let is_pin = |p: &str| (4..=12).contains(&p.len()) && p.bytes().all(|b| b.is_ascii_digit());
    match *cmd {
        Command::History { n, .. } => prop_assert!((1..=100).contains(&n)),
        Command::Measure { bore_um, .. } => prop_assert!((20_000..=40_000).contains(&bore_um)),
        Command::CalibrateSpan { force_mn } => {
            prop_assert!((1_000..=900_000).contains(&force_mn))
        }
        Command::ConeReplace {
            serial, bore_um, ..
        } => prop_assert!(
            (1..=20).contains(&serial.len())
                && serial
                    .bytes()
                    .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
                && bore_um.is_none_or(|b| (20_000..=40_000).contains(&b))
        ),
        Command::Maint { pin } | Command::PinSet { pin } => {
            prop_assert!(is_pin(pin));
            let debug = format!("{cmd:?}");
            prop_assert!(!debug.contains(pin), "{}", debug);
        }
        _ => {}
    }
    prop_assert!(!cmd.name().is_empty());
    Ok(())
}

/// Tokens that make the generated lines reach every parser branch.
const TOKENS: &[&str] = &[
    "help",
    "version",
    "status",
    "wear",
    "history",
    "faults",
    "clear-fault",
    "cone",
    "replace",
    "measure",
    "calibrate",
    "tare",
    "span",
    "maint",
    "exit",
    "pin",
    "set",
    "--json",
    "--json",
    "--jsno",
    "zqsn5-2",
    "qsn6-6-3",
    "cf-peek",
    "CF-PEEK",
    "brass",
    "SN-0001",
    "a_b",
    "26.050",
    "26.0501",
    "20",
    "40.000",
    "40.001",
    "-26",
    "2.6e1",
    "nan",
    "inf",
    "1",
    "10",
    "100",
    "101",
    "0",
    "1.000",
    "900.000",
    "0.999",
    "1234",
    "123456789012",
    "1234567890123",
    "12a4",
    "é",
    "€😀",
    "STATUS",
    "",
];

fn byte() -> impl Strategy<Value = u8> {
    prop_oneof![
        8 => 0x20u8..0x7F,
        2 => Just(b'\n'),
        2 => Just(b'\r'),
        1 => prop::sample::select(vec![
            0x00u8, 0x08, 0x09, 0x1B, b'[', b'O', 0x7F, 0x03, 0xC3, 0xA9, 0xE2, 0x82, 0xAC,
            0xF0, 0x9F, 0xFF, 0xC2, 0x9B, 0xED, 0xA0,
        ]),
        1 => any::<u8>(),
    ]
}

fn command_line() -> impl Strategy<Value = Vec<u8>> {
    (
        prop::collection::vec(
            (
                prop::sample::select(TOKENS),
                prop::sample::select(&[" ", "  ", "\t", " \t "][..]),
            ),
            1..6,
        ),
        prop::sample::select(&["\n", "\r", "\r\n", "\n\r", "\x1b[A\r", ""][..]),
    )
        .prop_map(|(toks, end)| {
            let mut s = String::new();
            for (t, sep) in toks {
                s.push_str(t);
                s.push_str(sep);
            }
            s.push_str(end);
            s.into_bytes()
        })
}

/// Byte streams of up to 4 KiB, biased to newlines, printable ASCII and commands.
fn stream() -> impl Strategy<Value = Vec<u8>> {
    let chunk = prop_oneof![
        3 => prop::collection::vec(byte(), 0..200),
        4 => command_line(),
        1 => (120usize..300, prop::sample::select(&[b'\n', b'\r'][..]))
            .prop_map(|(n, end)| {
                let mut v = vec![b'x'; n];
                v.push(end);
                v
            }),
    ];
    prop::collection::vec(chunk, 0..48).prop_map(|chunks| {
        let mut v = chunks.concat();
        v.truncate(4096);
        v
    })
}

proptest! {
    #[test]
    fn prop_stream_never_panics_and_keeps_invariants(bytes in stream()) {
        check_stream(&bytes)?;
    }

    #[test]
    fn prop_uniform_bytes_keep_invariants(
        bytes in prop::collection::vec(any::<u8>(), 0..4096)
    ) {
        check_stream(&bytes)?;
    }

    /// Printable-ASCII lines with any terminators come out exactly as a model says.
    #[test]
    fn prop_lines_match_model(
        input in prop::collection::vec(
            (
                prop::collection::vec(0x20u8..0x7F, 0..200),
                prop::sample::select(&["\n", "\r", "\r\n"][..]),
            ),
            0..20,
        )
    ) {
        let mut bytes = Vec::new();
        let mut expect = Vec::new();
        for (text, end) in &input {
            bytes.extend_from_slice(text);
            bytes.extend_from_slice(end.as_bytes());
            let s = String::from_utf8(text.clone()).unwrap();
            if s.len() > CAP {
                expect.push(Ev::Err(LineError::TooLong));
            } else if !s.trim_matches(' ').is_empty() {
                expect.push(Ev::Line(s));
            }
        }
        prop_assert_eq!(lines(&bytes), expect);
    }

    /// Every value in range written with 0..=3 decimals parses to the same µm/mN.
    #[test]
    fn prop_decimal_arguments_roundtrip(v in 20_000u32..=40_000, span in 1_000u32..=900_000) {
        let bore = format!("measure {}.{:03}", v / 1000, v % 1000);
        prop_assert_eq!(ok(&bore), Command::Measure { bore_um: v, baseline: false });
        let f = format!("calibrate span {}.{:03}", span / 1000, span % 1000);
        prop_assert_eq!(ok(&f), Command::CalibrateSpan { force_mn: span });
        if v % 10 == 0 {
            let two = format!("measure {}.{:02}", v / 1000, (v % 1000) / 10);
            prop_assert_eq!(ok(&two), Command::Measure { bore_um: v, baseline: false });
        }
    }

    /// `fixed` prints an exact decimal: digits back to the same integer.
    #[test]
    fn prop_fixed_roundtrip(v in any::<i64>(), d in 0u8..=18) {
        let s = fixed(v, d);
        let neg = s.starts_with('-');
        let body = s.trim_start_matches('-');
        let (int, frac) = body.split_once('.').unwrap_or((body, ""));
        prop_assert_eq!(frac.len(), usize::from(d));
        prop_assert!(!int.is_empty() && (int == "0" || !int.starts_with('0')));
        let digits: i128 = format!("{int}{frac}").parse().unwrap();
        prop_assert_eq!(if neg { -digits } else { digits }, i128::from(v));
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(1_000_000))]

    /// 1,000,000 cases of the stream property; run by hand (see the module doc).
    #[test]
    #[ignore = "long-running fuzz; run with --release -- --ignored"]
    fn fuzz_console_million(bytes in stream()) {
        check_stream(&bytes)?;
    }
}

#[test]
fn corpus_inputs_keep_invariants() {
    let files = host_tests::corpus_files("console");
    let mut total = Seen::default();
    for path in &files {
        let bytes = std::fs::read(path).unwrap();
        let seen = check_stream(&bytes).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        total.commands += seen.commands;
        total.errors += seen.errors;
    }
    assert!(total.commands >= 14 && total.errors >= 10, "{total:?}");
}
