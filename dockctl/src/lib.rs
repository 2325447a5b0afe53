//! `dockctl`: the technician's tool for the docking controller, on a laptop (issue 35).
//!
//! It talks to the board's console exactly as a person does (docs/console.md: the line
//! protocol with `echo off`, and `--json` replies), over a serial port (`--port
//! /dev/ttyUSB0`, also the simulators' ptys) or TCP (`--tcp 127.0.0.1:PORT`: `hil-sim
//! serve` and `vboard serve`). It reads the reports as tables with units (`--json`,
//! `--csv` for scripts), exports one machine's maintenance record, watches the machine
//! live, and updates the firmware: the file checked first, maintenance mode, `update`,
//! YMODEM-1K with a progress bar (the project's own sender, `docking_logic::ymodem`),
//! the restart, and what happened, said plainly.
//!
//! Every failure a technician can cause is one line on stderr and a non-zero exit, and
//! leaves the board as it was: what the tool changed on the console (maintenance mode
//! it entered, echo it turned off) is put back on every path, Ctrl-C included
//! ([`console::Session::close`]).
//!
//! Exit status: 0 done; 1 failed or refused (nothing changed on the board); 2 a wrong
//! command line; 3 an update that did not take (rolled back, or not confirmed); 130
//! interrupted by Ctrl-C.

pub mod cli;
pub mod console;
pub mod image;
pub mod json;
pub mod link;
pub mod pin;
pub mod reports;
pub mod table;
pub mod update;

use std::io::Write;

pub use console::Cancel;

/// What went wrong, for one line on stderr.
#[derive(Debug)]
pub enum Error {
    /// A wrong command line.
    Usage(String),
    /// The line: it did not open, or went away.
    Link(link::LinkError),
    /// Nothing (or nothing sensible) answered.
    NoAnswer(String),
    /// The board answered something the tool did not expect.
    Protocol(String),
    /// The board's `error: ` line.
    Board(String),
    /// The board refused the PIN.
    Pin(String),
    /// A file could not be read or is not what it must be.
    File(String),
    /// The update was refused (by the board, or before anything was sent); nothing
    /// changed.
    Refused(String),
    /// The line was cut during a transfer.
    Cut(String),
    /// The board restarted (its banner: the line).
    Restarted(String),
    /// Ctrl-C (what was put back is said on stderr before).
    Interrupted,
    /// An update that did not take: rolled back, or not confirmed.
    NotTaken(String),
    /// What this version of the tool cannot do yet.
    NotYet(String),
}

impl std::fmt::Display for Error {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Error::Usage(s)
            | Error::NoAnswer(s)
            | Error::File(s)
            | Error::NotTaken(s)
            | Error::NotYet(s) => f.write_str(s),
            Error::Link(link::LinkError::Cut(s)) => write!(f, "the line was cut: {s}"),
            Error::Link(e) => write!(f, "{e}"),
            Error::Protocol(s) => write!(f, "unexpected reply: {s}"),
            Error::Board(s) => write!(f, "the board says: {s}"),
            Error::Pin(s) => write!(f, "the board refused the PIN: {s}; nothing was changed"),
            Error::Refused(s) => write!(f, "update refused: {s}"),
            Error::Cut(s) => f.write_str(s),
            Error::Restarted(s) => write!(f, "the board restarted: {s}"),
            Error::Interrupted => f.write_str("interrupted (Ctrl-C)"),
        }
    }
}

impl Error {
    /// The exit status.
    pub fn code(&self) -> i32 {
        match self {
            Error::Usage(_) => 2,
            Error::Interrupted => 130,
            Error::NotTaken(_) => 3,
            _ => 1,
        }
    }
}

/// Where the tool writes, and what it knows of its terminal.
pub struct Ctx<'a> {
    /// Results (tables, JSON, CSV).
    pub out: &'a mut dyn Write,
    /// Messages, progress, errors.
    pub err: &'a mut dyn Write,
    /// Ctrl-C.
    pub cancel: Cancel,
    /// stdout is a terminal (`watch` rewrites one line).
    pub out_tty: bool,
    /// stderr is a terminal (the progress bar).
    pub err_tty: bool,
    /// stdin is a terminal (the PIN may be asked).
    pub in_tty: bool,
}

/// Run `dockctl` with `args` (the program's name first); the exit status.
pub fn run<I, T>(args: I, ctx: &mut Ctx) -> i32
where
    I: IntoIterator<Item = T>,
    T: Into<std::ffi::OsString> + Clone,
{
    use clap::Parser;
    let cli = match cli::Cli::try_parse_from(args) {
        Ok(c) => c,
        Err(e) => {
            let code = if e.use_stderr() { 2 } else { 0 };
            let text = e.render().to_string();
            if code == 0 {
                let _ = write!(ctx.out, "{text}");
            } else {
                let _ = write!(ctx.err, "{text}");
            }
            return code;
        }
    };
    match cli::dispatch(&cli, ctx) {
        Ok(code) => code,
        Err(e) => {
            let _ = writeln!(ctx.err, "error: {e}");
            let _ = ctx.err.flush();
            e.code()
        }
    }
}
