//! Shared by the command-line tests: run `hil-sim` as a user runs it.

use std::process::Command;

/// Run `hil-sim args`: (exit code, stdout, stderr).
pub fn run(args: &[&str]) -> (i32, String, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .args(args)
        .output()
        .unwrap();
    (
        out.status.code().unwrap_or(-1),
        String::from_utf8(out.stdout).unwrap(),
        String::from_utf8(out.stderr).unwrap(),
    )
}

/// Run `hil-sim args` as a usage error: exit code 2, nothing on stdout, one line on
/// stderr (returned).
#[allow(dead_code)] // not every test file refuses arguments
pub fn usage_error(args: &[&str]) -> String {
    let (code, out, err) = run(args);
    assert_eq!(code, 2, "{args:?}");
    assert!(out.is_empty(), "{args:?}: {out}");
    assert_eq!(err.lines().count(), 1, "{args:?}: {err}");
    err
}
