//! The console as a person at a terminal meets it (echo on, the default) and as a
//! script drives it (`echo off`): the banner, echo, line editing, the prompt, `help`.

use hil_sim::rig::{Rig, RigOptions};

/// A booted machine with a terminal attached (nothing read yet).
fn rig() -> Rig {
    let mut r = Rig::new(RigOptions::new(80));
    r.console_enabled = true;
    for _ in 0..hil_sim::rig::BOOT_TICKS {
        r.tick();
    }
    r
}

/// Type `bytes`, run the machine a while, return what the terminal shows.
fn typed(r: &mut Rig, bytes: &[u8]) -> String {
    r.term.send(bytes);
    let mut out = Vec::new();
    for _ in 0..40 {
        r.tick();
        out.extend(r.term.take_output());
    }
    String::from_utf8_lossy(&out).into_owned()
}

#[test]
fn a_terminal_gets_a_banner_echo_and_a_prompt() {
    let mut r = rig();
    let boot = String::from_utf8_lossy(&r.term.take_output()).into_owned();
    assert!(
        boot.starts_with("# docking-controller ") && boot.contains(" reset=power_on"),
        "{boot:?}"
    );
    // The prompt names the state at boot.
    assert!(boot.ends_with("\r\npower_up> "), "{boot:?}");
    let shown = typed(&mut r, b"version\r\n");
    assert!(
        shown.starts_with("version\r\ndocking-controller "),
        "echo, CR LF once, then the reply: {shown:?}"
    );
    assert!(shown.ends_with("\r\nidle> "), "{shown:?}");
    // A blank line: just a new prompt.
    assert_eq!(typed(&mut r, b"\r"), "\r\nidle> ");
}

#[test]
fn editing_keys_edit_the_line_instead_of_discarding_it() {
    let mut r = rig();
    r.term.take_output();
    // Backspace rubs out one character.
    let shown = typed(&mut r, b"versiox\x7fn\r");
    assert!(
        shown.starts_with("versiox\x08 \x08n\r\ndocking-controller "),
        "{shown:?}"
    );
    // Ctrl-U erases the line; what is typed after it runs.
    let shown = typed(&mut r, b"wear\x15version\r");
    assert!(
        shown.starts_with("wear\x08 \x08\x08 \x08\x08 \x08\x08 \x08version\r\ndocking-controller "),
        "{shown:?}"
    );
    // An arrow key (left) does nothing to the line: it still runs.
    let shown = typed(&mut r, b"version\x1b[D\r");
    assert!(shown.contains("\r\ndocking-controller "), "{shown:?}");
    assert!(!shown.contains("error"), "{shown:?}");
    // Up recalls the previous line.
    let shown = typed(&mut r, b"\x1b[A\r");
    assert!(
        shown.starts_with("version\r\ndocking-controller "),
        "{shown:?}"
    );
    // Ctrl-C abandons the line.
    let shown = typed(&mut r, b"dock\x03");
    assert_eq!(shown, "dock^C\r\nidle> ");
    assert_eq!(r.ctrl.state().name(), "idle");
}

#[test]
fn a_pin_is_echoed_as_stars_and_maintenance_shows_in_the_prompt() {
    let mut r = rig();
    r.term.take_output();
    let shown = typed(&mut r, b"pin set 2468\r");
    assert!(
        shown.starts_with("pin set ****\r\nok: PIN set"),
        "{shown:?}"
    );
    let shown = typed(&mut r, b"maint 2468\r");
    assert!(
        shown.starts_with("maint ****\r\nok: maintenance mode"),
        "{shown:?}"
    );
    assert!(shown.ends_with("idle# "), "{shown:?}");
    // Up does not recall a line holding a PIN.
    let shown = typed(&mut r, b"\x1b[A");
    assert!(
        !shown.contains("2468") && !shown.contains("maint"),
        "{shown:?}"
    );
    let shown = typed(&mut r, b"\x15maint exit\r");
    assert!(shown.ends_with("idle> "), "{shown:?}");
}

#[test]
fn echo_off_is_the_bare_line_protocol_until_echo_on() {
    let mut r = rig();
    r.term.take_output();
    let shown = typed(&mut r, b"echo off\r\n");
    assert!(
        shown.starts_with("echo off\r\nok: echo and prompt off"),
        "{shown:?}"
    );
    assert!(shown.ends_with("\r\n"), "no prompt after it: {shown:?}");
    // One reply line per command, no echo, no prompt; JSON on one line.
    let shown = typed(&mut r, b"status --json\r\n");
    assert_eq!(shown.matches("\r\n").count(), 1, "{shown:?}");
    assert!(shown.starts_with("{\"state\":\"idle\""), "{shown:?}");
    // Without line editing an escape sequence spoils the line, as before.
    let shown = typed(&mut r, b"version\x1b[D\r\n");
    assert!(shown.starts_with("error: control character"), "{shown:?}");
    assert_eq!(typed(&mut r, b"echo\r\n"), "echo=off\r\n");
    let shown = typed(&mut r, b"echo on\r\n");
    assert!(
        shown.starts_with("ok: echo, prompt and line editing on"),
        "{shown:?}"
    );
    assert!(shown.ends_with("idle> "), "{shown:?}");
}

#[test]
fn help_is_aligned_and_answers_for_one_command() {
    let mut r = rig();
    let all = r.command("help", 10);
    let lines: Vec<&str> = all.lines().collect();
    assert!(lines.len() > 20, "{all}");
    // Every description starts in the same column.
    let col = |l: &str| {
        l.find("  ")
            .map(|i| i + l[i..].len() - l[i..].trim_start().len())
    };
    let first = col(lines[0]).unwrap();
    for l in &lines[..lines.len() - 1] {
        assert_eq!(col(l), Some(first), "{l:?}");
    }
    let one = r.command("help calibrate", 10);
    assert_eq!(one.lines().count(), 3, "two forms and the note: {one}");
    assert!(one.starts_with("calibrate tare "), "{one}");
    let v: serde_json::Value =
        serde_json::from_str(r.command("help dock --json", 10).trim_end()).unwrap();
    assert_eq!(v["help"][0]["usage"], "dock");
    let e = r.command("help nonsense", 10);
    assert!(
        e.starts_with("error: bad <command>; expected a command word"),
        "{e}"
    );
}

#[test]
fn errors_say_what_was_expected() {
    let mut r = rig();
    for (line, want) in [
        ("rate 20", "error: bad <rate_sps>; expected 10 | 80"),
        ("modbus 300 19200", "error: bad <unit>; expected 1..247"),
        ("modbus 7 1234", "error: bad <baud>; expected 9600 | 19200"),
        ("echo loud", "error: bad <echo setting>; expected on | off"),
    ] {
        let e = r.command(line, 10);
        assert!(e.starts_with(want), "{line}: {e}");
    }
}
