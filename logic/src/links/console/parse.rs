//! Console command parser.
//!
//! [`parse`] turns one line (from [`super::line::LineReader`]) into a [`Command`].
//! Tokens are separated by any amount of spaces and tabs; command words are lowercase
//! and case-sensitive (material names are matched case-insensitively). Grammar:
//!
//! ```text
//! help [<command>] [--json]             all commands, or one (e.g. `help cone`)
//! echo [on|off]                         the terminal's echo and prompt (on at reset)
//! version [--json]
//! status [--json]
//! wear [--json]
//! history [N] [--json]                  N = 1..=100, default 10
//! curve [last|ref|nok N] [--json|--csv] the newest docking's force–position curve, the
//!                                       cone's reference, or the Nth newest NOK curve
//!                                       (N = 1..=4); default last
//! faults [--json]
//! measurements [--json]                 the current cone's readings
//! clear-fault
//! home                                  power-up homing (out of the cone) and lock
//! dock                                  dock and stay mated until undock
//! undock                                undock (or abort a docking under way)
//! stop                                  stop all motion now (latched `stopped` fault)
//! rate <10|80>                          the HX711's RATE pin setting, from the next boot
//! modbus [<unit> <baud>]                the Modbus line: show, or store (unit 1..=247;
//!                                       baud 9600|19200|38400|57600|115200; 8E1), from
//!                                       the next boot
//! update                                receive a signed image by YMODEM-1K, verify
//!                                       it, restart into it (docs/update.md)
//! cone replace <material> <serial> [--bore <d0_mm>]
//!                                       material: zqsn5-2 | qsn6-6-3 | cf-peek
//!                                       serial: 1..=20 chars of [A-Za-z0-9_-]
//!                                       d0_mm: the new cone's bore, as below
//! measure [--baseline] <bore_diameter_mm>
//!                                       20.000..=40.000, up to 3 decimals → bore_um
//! calibrate tare
//! calibrate span <force_n>              known load, 1.000..=900.000, up to 3 decimals
//!                                       → force_mn
//! maint <pin>                           enter maintenance mode (pin: 4..=12 digits)
//! maint exit                            leave maintenance mode
//! pin set <new_pin>                     new_pin: 4..=12 ASCII digits
//! ```
//!
//! * `--json` may appear anywhere after the command words, at most once, and only on
//!   the read commands (help, version, status, wear, history, faults, curve; `curve`
//!   also takes `--csv`, not with `--json`); elsewhere it is
//!   [`ParseError::JsonNotSupported`]. The token `--json` is always this option, never
//!   a value. On read commands any other token starting with `--` is
//!   [`ParseError::UnknownOption`].
//! * Decimals are plain: digits, optionally `.` and 1..=3 digits (`26`, `26.05`,
//!   `026.050`). Signs, exponents, a bare or trailing `.`, more than 3 decimals,
//!   `nan`, `inf` are rejected; values are converted exactly to integer milli-units
//!   (`26.05` mm → 26050 µm).
//! * `N` is 1..=3 ASCII digits.
//!
//! Guarantees: O(line length) work, no allocation, no panic on any input; the
//! [`ParseError`] `Display` is one line of printable ASCII (an unknown command word is
//! echoed truncated, with anything but printable ASCII replaced by `?`). A `Command`'s
//! `Debug` output never shows a PIN.

use core::fmt;

use crate::material::Material;

/// Default `history` length.
pub const HISTORY_DEFAULT: u16 = 10;
/// Largest `history` length.
pub const HISTORY_MAX: u16 = 100;
/// Smallest accepted bore diameter, µm.
pub const BORE_MIN_UM: u32 = 20_000;
/// Largest accepted bore diameter, µm.
pub const BORE_MAX_UM: u32 = 40_000;
/// Smallest accepted span-calibration load, mN.
pub const SPAN_MIN_MN: u32 = 1_000;
/// Largest accepted span-calibration load, mN.
pub const SPAN_MAX_MN: u32 = 900_000;
/// Longest cone serial number, characters.
pub const SERIAL_MAX_LEN: usize = 20;
/// Shortest maintenance PIN, digits.
pub const PIN_MIN_LEN: usize = 4;
/// Longest maintenance PIN, digits.
pub const PIN_MAX_LEN: usize = 12;

/// How a command's arguments become a [`Command`].
type Parser = for<'a> fn(&Args<'a>) -> Result<Command<'a>, ParseError>;

/// One command: its word, its syntax and what it does as `help` shows them, and its
/// parser. This table is the console's one list of commands: [`parse`] finds a line's
/// first word here and runs that entry's parser, and `help` prints it.
#[derive(Clone, Copy)]
pub struct CommandHelp {
    /// The syntax (its first word is the command's, [`Self::word`]).
    pub usage: &'static str,
    /// What it does, one line.
    pub what: &'static str,
    parse: Parser,
}

impl CommandHelp {
    /// The first word (what `help <command>` takes): the usage's, up to its first space
    /// (not stored apart: issue 20).
    pub fn word(&self) -> &'static str {
        let n = self.usage.bytes().position(|b| b == b' ');
        self.usage
            .get(..n.unwrap_or(self.usage.len()))
            .unwrap_or(self.usage)
    }
}

impl core::fmt::Debug for CommandHelp {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.debug_struct("CommandHelp")
            .field("word", &self.word())
            .field("usage", &self.usage)
            .finish()
    }
}

/// One entry: `word` must be the first word of `usage` (checked when the table is
/// built, at compile time).
// Evaluated only to build the constant table: an index out of bounds here (there is
// none: `i < w.len() <= u.len()`) would fail the build, not the firmware; `get` is not
// available in a const fn.
#[allow(clippy::indexing_slicing)]
const fn c(
    word: &'static str,
    usage: &'static str,
    what: &'static str,
    parse: Parser,
) -> CommandHelp {
    let (w, u) = (word.as_bytes(), usage.as_bytes());
    assert!(w.len() <= u.len() && (u.len() == w.len() || u[w.len()] == b' '));
    let mut i = 0;
    while i < w.len() {
        assert!(w[i] == u[i], "a command's word starts its usage");
        i += 1;
    }
    CommandHelp { usage, what, parse }
}

/// Every console command, in `help`'s order.
pub const COMMANDS: [CommandHelp; 26] = [
    c(
        "help",
        "help [<command>] [--json]",
        "this list, or one command's",
        help_args,
    ),
    c(
        "echo",
        "echo [on|off]",
        "terminal echo and prompt (off: the bare line protocol for scripts, until reset)",
        echo_args,
    ),
    c(
        "version",
        "version [--json]",
        "firmware name and version",
        version_args,
    ),
    c(
        "status",
        "status [--json]",
        "state, phase, force, position, fault, PLC lines",
        status_args,
    ),
    c(
        "wear",
        "wear [--json]",
        "the cone's wear odometer and the lifetime counters",
        wear_args,
    ),
    c(
        "history",
        "history [N] [--json]",
        "the newest N completed cycles (1..100, default 10)",
        history_args,
    ),
    c(
        "curve",
        "curve [last|ref|nok N] [--json|--csv]",
        "the newest docking's force-position curve and its verdict, the cone's reference, or the Nth newest NOK curve (1..4)",
        curve_args,
    ),
    c(
        "faults",
        "faults [--json]",
        "active fault, recent faults, resets, last crash",
        faults_args,
    ),
    c(
        "measurements",
        "measurements [--json]",
        "the current cone's bore readings",
        measurements_args,
    ),
    c(
        "clear-fault",
        "clear-fault",
        "clear a latched fault and recover to home (maint)",
        clear_fault_args,
    ),
    c(
        "home",
        "home",
        "home the axis and lock the panel (maint)",
        home_args,
    ),
    c(
        "dock",
        "dock",
        "dock and stay mated until undock (maint)",
        dock_args,
    ),
    c(
        "undock",
        "undock",
        "undock, or abort a docking under way (maint)",
        undock_args,
    ),
    c(
        "stop",
        "stop",
        "stop all motion now, latched; never refused",
        stop_args,
    ),
    c(
        "rate",
        "rate <10|80>",
        "the HX711's rate, from the next boot (maint)",
        rate_args,
    ),
    c(
        "modbus",
        "modbus [<unit> <baud>]",
        "show or store the Modbus line's settings (maint to store)",
        modbus_args,
    ),
    c(
        "bor",
        "bor [set]",
        "show, or program at rest, the brown-out reset level (maint to set)",
        bor_args,
    ),
    c(
        "update",
        "update",
        "receive a signed firmware image by YMODEM-1K, verify it, restart into it (maint)",
        update_args,
    ),
    c(
        "cone",
        "cone replace <material> <serial> [--bore <d0_mm>]",
        "a new cone: its counters start at zero (maint)",
        cone_args,
    ),
    c(
        "measure",
        "measure <bore_diameter_mm>",
        "record a micrometer bore reading (maint)",
        measure_args,
    ),
    c(
        "measure",
        "measure --baseline <d0_mm>",
        "the new cone's bore, before its first docking (maint)",
        measure_args,
    ),
    c(
        "calibrate",
        "calibrate tare",
        "zero the load cell with nothing on it (maint)",
        calibrate_args,
    ),
    c(
        "calibrate",
        "calibrate span <force_n>",
        "set the span with a known load on the cell (maint)",
        calibrate_args,
    ),
    c(
        "maint",
        "maint <pin>",
        "enter maintenance mode (ends after 10 min idle)",
        maint_args,
    ),
    c("maint", "maint exit", "leave maintenance mode", maint_args),
    c(
        "pin",
        "pin set <new_pin>",
        "set the maintenance PIN (4-12 digits; maint once one exists)",
        pin_args,
    ),
];

/// A parsed console command; string fields borrow the line.
#[derive(Clone, Copy, PartialEq, Eq)]
pub enum Command<'a> {
    /// `help [<command>] [--json]`.
    Help {
        /// One command's word (`help dock`), else all of them.
        topic: Option<&'a str>,
        /// Reply in JSON.
        json: bool,
    },
    /// `echo [on|off]`: show, or set, the terminal's echo and prompt.
    Echo {
        /// `on`/`off`; `None` shows the setting.
        on: Option<bool>,
    },
    /// `version [--json]`.
    Version {
        /// Reply in JSON.
        json: bool,
    },
    /// `status [--json]`.
    Status {
        /// Reply in JSON.
        json: bool,
    },
    /// `wear [--json]`.
    Wear {
        /// Reply in JSON.
        json: bool,
    },
    /// `history [N] [--json]`.
    History {
        /// Number of entries, 1..=100.
        n: u16,
        /// Reply in JSON.
        json: bool,
    },
    /// `curve [last|ref|nok N] [--json|--csv]`.
    Curve {
        /// Which curve.
        which: crate::signature::view::Which,
        /// How it is written.
        format: CurveFormat,
    },
    /// `measurements [--json]`.
    Measurements {
        /// Reply in JSON.
        json: bool,
    },
    /// `faults [--json]`.
    Faults {
        /// Reply in JSON.
        json: bool,
    },
    /// `clear-fault`.
    ClearFault,
    /// `home`: find home and lock after a reset.
    Home,
    /// `dock`: dock and stay mated until `undock`.
    Dock,
    /// `undock`: extraction, re-lock, home (or abort a docking under way).
    Undock,
    /// `stop`: stop all motion now, latched.
    Stop,
    /// `rate <10|80>`: the HX711's output rate (its RATE pin), from the next boot.
    Rate {
        /// Samples per second.
        sps: u32,
    },
    /// `modbus`: show the Modbus line's settings.
    ModbusShow,
    /// `bor`: show the brown-out reset level in the option bytes.
    BorShow,
    /// `bor set`: program brown-out reset level 3 (2.70 V), at rest.
    BorSet,
    /// `update`: receive a signed image by YMODEM-1K into DFU page 0, verify it, mark
    /// it for the bootloader's swap and restart (issue 21; `console/update.rs`).
    Update,
    /// `modbus <unit> <baud>`: store them (from the next boot).
    ModbusSet {
        /// Unit address, 1..=247.
        unit: u8,
        /// Baud rate.
        baud: u32,
    },
    /// `cone replace <material> <serial>`.
    ConeReplace {
        /// The new cone's material.
        material: Material,
        /// The new cone's serial number (1..=20 chars of `[A-Za-z0-9_-]`).
        serial: &'a str,
        /// `--bore <d0_mm>`: the new cone's bore before its first docking, µm.
        bore_um: Option<u32>,
    },
    /// `measure [--baseline] <bore_diameter_mm>`.
    Measure {
        /// Measured bore diameter, µm (20_000..=40_000).
        bore_um: u32,
        /// `--baseline`: the cone's bore when new, not a wear reading.
        baseline: bool,
    },
    /// `calibrate tare`.
    CalibrateTare,
    /// `calibrate span <force_n>`.
    CalibrateSpan {
        /// The known load, mN (1_000..=900_000).
        force_mn: u32,
    },
    /// `maint <pin>`.
    Maint {
        /// The PIN typed (4..=12 ASCII digits; not yet checked against the record).
        pin: &'a str,
    },
    /// `maint exit`.
    MaintExit,
    /// `pin set <new_pin>`.
    PinSet {
        /// The new PIN (4..=12 ASCII digits).
        pin: &'a str,
    },
}

impl Command<'_> {
    /// The command words, e.g. `"cone replace"`.
    pub const fn name(&self) -> &'static str {
        match self {
            Self::Help { .. } => "help",
            Self::Echo { .. } => "echo",
            Self::Version { .. } => "version",
            Self::Status { .. } => "status",
            Self::Wear { .. } => "wear",
            Self::History { .. } => "history",
            Self::Curve { .. } => "curve",
            Self::Faults { .. } => "faults",
            Self::Measurements { .. } => "measurements",
            Self::ClearFault => "clear-fault",
            Self::Home => "home",
            Self::Dock => "dock",
            Self::Undock => "undock",
            Self::Stop => "stop",
            Self::Rate { .. } => "rate",
            Self::ModbusShow | Self::ModbusSet { .. } => "modbus",
            Self::BorShow => "bor",
            Self::BorSet => "bor set",
            Self::Update => "update",
            Self::ConeReplace { .. } => "cone replace",
            Self::Measure { .. } => "measure",
            Self::CalibrateTare => "calibrate tare",
            Self::CalibrateSpan { .. } => "calibrate span",
            Self::Maint { .. } => "maint",
            Self::MaintExit => "maint exit",
            Self::PinSet { .. } => "pin set",
        }
    }

    /// True for commands that change persistent machine state or move the machine (need
    /// maintenance mode). `stop` is not one: a stop is never refused.
    pub const fn is_state_changing(&self) -> bool {
        matches!(
            self,
            Self::ClearFault
                | Self::Home
                | Self::Dock
                | Self::Undock
                | Self::Rate { .. }
                | Self::ModbusSet { .. }
                | Self::BorSet
                | Self::Update
                | Self::ConeReplace { .. }
                | Self::CalibrateTare
                | Self::CalibrateSpan { .. }
                | Self::PinSet { .. }
        )
    }

    /// True for the state-changing commands that need a machine at rest (all but
    /// `undock`, which applies to a docking under way).
    pub const fn needs_rest(&self) -> bool {
        self.is_state_changing() && !matches!(self, Self::Undock)
    }

    /// True when the reply was asked for in JSON (`--json`).
    pub const fn json(&self) -> bool {
        match self {
            Self::Help { json, .. }
            | Self::Version { json }
            | Self::Status { json }
            | Self::Wear { json }
            | Self::History { json, .. }
            | Self::Measurements { json }
            | Self::Faults { json } => *json,
            Self::Curve { format, .. } => matches!(format, CurveFormat::Json),
            _ => false,
        }
    }
}

/// `Debug` that never shows a PIN.
impl fmt::Debug for Command<'_> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Help { topic, json } => f
                .debug_struct("Help")
                .field("topic", topic)
                .field("json", json)
                .finish(),
            Self::Echo { on } => f.debug_struct("Echo").field("on", on).finish(),
            Self::Version { json } => f.debug_struct("Version").field("json", json).finish(),
            Self::Status { json } => f.debug_struct("Status").field("json", json).finish(),
            Self::Wear { json } => f.debug_struct("Wear").field("json", json).finish(),
            Self::History { n, json } => f
                .debug_struct("History")
                .field("n", n)
                .field("json", json)
                .finish(),
            Self::Faults { json } => f.debug_struct("Faults").field("json", json).finish(),
            Self::Curve { which, format } => f
                .debug_struct("Curve")
                .field("which", which)
                .field("format", format)
                .finish(),
            Self::Measurements { json } => {
                f.debug_struct("Measurements").field("json", json).finish()
            }
            Self::ClearFault => f.write_str("ClearFault"),
            Self::Home => f.write_str("Home"),
            Self::Dock => f.write_str("Dock"),
            Self::Undock => f.write_str("Undock"),
            Self::Stop => f.write_str("Stop"),
            Self::Rate { sps } => f.debug_struct("Rate").field("sps", sps).finish(),
            Self::ModbusShow => f.write_str("ModbusShow"),
            Self::BorShow => f.write_str("BorShow"),
            Self::BorSet => f.write_str("BorSet"),
            Self::Update => f.write_str("Update"),
            Self::ModbusSet { unit, baud } => f
                .debug_struct("ModbusSet")
                .field("unit", unit)
                .field("baud", baud)
                .finish(),
            Self::ConeReplace {
                material,
                serial,
                bore_um,
            } => f
                .debug_struct("ConeReplace")
                .field("material", material)
                .field("serial", serial)
                .field("bore_um", bore_um)
                .finish(),
            Self::Measure { bore_um, baseline } => f
                .debug_struct("Measure")
                .field("bore_um", bore_um)
                .field("baseline", baseline)
                .finish(),
            Self::CalibrateTare => f.write_str("CalibrateTare"),
            Self::CalibrateSpan { force_mn } => f
                .debug_struct("CalibrateSpan")
                .field("force_mn", force_mn)
                .finish(),
            Self::Maint { .. } => f.write_str("Maint { pin: <redacted> }"),
            Self::MaintExit => f.write_str("MaintExit"),
            Self::PinSet { .. } => f.write_str("PinSet { pin: <redacted> }"),
        }
    }
}

/// How `curve` writes a curve.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CurveFormat {
    /// A compact table for a terminal.
    Text,
    /// One JSON line (what `hil-sim plot-curve` reads).
    Json,
    /// CSV that a spreadsheet opens: a header, then one row per bin.
    Csv,
}

/// A short, sanitised copy of an unknown command word (printable ASCII, <= 15 chars).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Snippet(heapless::String<16>);

impl Snippet {
    /// Characters kept before truncating with `...`.
    const KEEP: usize = 12;

    /// Copy `word`: at most 12 characters, anything but printable ASCII as `?`,
    /// `...` appended when truncated.
    pub fn new(word: &str) -> Self {
        let mut s = heapless::String::new();
        // Character by character, counted at the first byte of each (UTF-8 continuation
        // bytes, `10xxxxxx`, are no character of their own): no decoding (issue 20).
        let starts = word.bytes().filter(|&b| b & 0xC0 != 0x80);
        for (i, b) in starts.enumerate() {
            if i >= Self::KEEP {
                let _ = s.push_str("...");
                break;
            }
            let _ = s.push(if b.is_ascii_graphic() {
                char::from(b)
            } else {
                '?'
            });
        }
        Self(s)
    }

    /// The sanitised text.
    pub fn as_str(&self) -> &str {
        self.0.as_str()
    }
}

/// Why a line is not a valid command.
#[non_exhaustive]
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ParseError {
    /// The line holds no tokens.
    Empty,
    /// The first word is not a command (a sanitised copy of it).
    UnknownCommand(Snippet),
    /// A `--option` other than `--json` on a read command.
    UnknownOption,
    /// A required argument is missing (its name).
    MissingArgument(&'static str),
    /// An argument is malformed or out of range (its name).
    BadArgument(&'static str),
    /// More arguments than the command takes (or `--json` twice).
    ExtraArgument,
    /// `--json` on a command that does not print a report.
    JsonNotSupported,
}

/// What each argument must look like, for error messages: a table searched in order
/// (a `match` on strings compiled to a comparison chain three times its size).
const HINTS: [(&str, &str); 18] = [
    ("N", "1..100"),
    ("curve", "last | ref | nok N (N = 1..4)"),
    ("material", "zqsn5-2 | qsn6-6-3 | cf-peek"),
    ("serial", "1-20 chars of A-Z a-z 0-9 _ -"),
    ("bore_diameter_mm", "20.000..40.000, up to 3 decimals"),
    ("d0_mm", "20.000..40.000, up to 3 decimals"),
    ("force_n", "1.000..900.000, up to 3 decimals"),
    ("pin", "4-12 digits"),
    ("new_pin", "4-12 digits"),
    ("cone subcommand", "replace"),
    ("calibrate subcommand", "tare | span"),
    ("pin subcommand", "set"),
    ("bor subcommand", "set"),
    ("rate_sps", "10 | 80"),
    ("unit", "1..247"),
    ("baud", "9600 | 19200 | 38400 | 57600 | 115200"),
    ("echo setting", "on | off"),
    ("command", "a command word, e.g. 'help dock'"),
];

/// What an argument must look like, for error messages (`see 'help'` for any other).
fn hint(arg: &str) -> &'static str {
    HINTS
        .iter()
        .find(|(a, _)| *a == arg)
        .map_or("see 'help'", |&(_, h)| h)
}

impl ParseError {
    /// Write the message (one line; `Display` writes the same). Pieces, not `write!`:
    /// the console writes no number or text through core::fmt (issue 20).
    pub fn write_message(&self, f: &mut dyn super::json::Sink) -> fmt::Result {
        // A fixed text, or a head, an argument, a middle and the argument's hint.
        let (head, arg, mid, tail) = match self {
            Self::Empty => ("empty line; type 'help'", "", "", ""),
            Self::UnknownCommand(w) => ("unknown command '", w.as_str(), "'; type 'help'", ""),
            Self::UnknownOption => ("unknown option; only --json is accepted", "", "", ""),
            Self::MissingArgument(a) => ("missing <", *a, "> (", ")"),
            Self::BadArgument(a) => ("bad <", *a, ">; expected ", ""),
            Self::ExtraArgument => ("too many arguments; type 'help'", "", "", ""),
            Self::JsonNotSupported => (
                "--json only applies to help, version, status, wear, history, curve, measurements, faults",
                "",
                "",
                "",
            ),
        };
        f.put(head)?;
        f.put(arg)?;
        f.put(mid)?;
        if let Self::MissingArgument(a) | Self::BadArgument(a) = self {
            f.put(hint(a))?;
        }
        f.put(tail)
    }
}

impl fmt::Display for ParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.write_message(f)
    }
}

/// Tokens after the command word: positional arguments and the `--json` flag.
struct Args<'a> {
    pos: heapless::Vec<&'a str, 5>,
    json: bool,
    unknown_option: bool,
}

impl<'a> Args<'a> {
    fn collect(tokens: impl Iterator<Item = &'a str>) -> Result<Self, ParseError> {
        let mut a = Args {
            pos: heapless::Vec::new(),
            json: false,
            unknown_option: false,
        };
        for t in tokens {
            if t == "--json" {
                if a.json {
                    return Err(ParseError::ExtraArgument);
                }
                a.json = true;
            } else {
                if t.starts_with("--") {
                    a.unknown_option = true;
                }
                a.pos.push(t).map_err(|_| ParseError::ExtraArgument)?;
            }
        }
        Ok(a)
    }

    /// Read command: `--json` allowed, no positional arguments.
    fn report(&self) -> Result<bool, ParseError> {
        if self.unknown_option {
            return Err(ParseError::UnknownOption);
        }
        if !self.pos.is_empty() {
            return Err(ParseError::ExtraArgument);
        }
        Ok(self.json)
    }

    /// Non-read command: no `--json`, at most `max` positional arguments.
    fn action(&self, max: usize) -> Result<(), ParseError> {
        if self.json {
            return Err(ParseError::JsonNotSupported);
        }
        if self.pos.len() > max {
            return Err(ParseError::ExtraArgument);
        }
        Ok(())
    }

    /// Positional argument `i`, or `MissingArgument(name)`.
    fn get(&self, i: usize, name: &'static str) -> Result<&'a str, ParseError> {
        self.pos
            .get(i)
            .copied()
            .ok_or(ParseError::MissingArgument(name))
    }
}

/// Parse one console line (see the module doc for the grammar): its first word names
/// the [`COMMANDS`] entry whose parser reads the rest.
#[inline(never)]
pub fn parse(line: &str) -> Result<Command<'_>, ParseError> {
    let mut tokens = line.split([' ', '\t']).filter(|t| !t.is_empty());
    let word = tokens.next().ok_or(ParseError::Empty)?;
    let entry = COMMANDS
        .iter()
        .find(|c| c.word() == word)
        .ok_or(ParseError::UnknownCommand(Snippet::new(word)))?;
    let a = Args::collect(tokens)?;
    (entry.parse)(&a)
}

fn help_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    if a.unknown_option {
        return Err(ParseError::UnknownOption);
    }
    let topic = match a.pos.as_slice() {
        [] => None,
        [t] if COMMANDS.iter().any(|c| c.word() == *t) => Some(*t),
        [_] => return Err(ParseError::BadArgument("command")),
        _ => return Err(ParseError::ExtraArgument),
    };
    Ok(Command::Help {
        topic,
        json: a.json,
    })
}

fn echo_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(1)?;
    match a.pos.first().copied() {
        None => Ok(Command::Echo { on: None }),
        Some("on") => Ok(Command::Echo { on: Some(true) }),
        Some("off") => Ok(Command::Echo { on: Some(false) }),
        Some(_) => Err(ParseError::BadArgument("echo setting")),
    }
}

fn version_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    Ok(Command::Version { json: a.report()? })
}

fn status_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    Ok(Command::Status { json: a.report()? })
}

fn wear_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    Ok(Command::Wear { json: a.report()? })
}

fn faults_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    Ok(Command::Faults { json: a.report()? })
}

fn measurements_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    Ok(Command::Measurements { json: a.report()? })
}

fn history_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    if a.unknown_option {
        return Err(ParseError::UnknownOption);
    }
    let n = match a.pos.as_slice() {
        [] => HISTORY_DEFAULT,
        [n] => parse_count(n).ok_or(ParseError::BadArgument("N"))?,
        _ => return Err(ParseError::ExtraArgument),
    };
    Ok(Command::History { n, json: a.json })
}

fn curve_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    use crate::signature::view::Which;
    // `--csv` is this command's own option (the others take `--json` only).
    let csv = a.pos.iter().filter(|t| **t == "--csv").count();
    if csv > 1 || (csv == 1 && a.json) {
        return Err(ParseError::ExtraArgument);
    }
    let mut rest = a.pos.iter().copied().filter(|t| *t != "--csv");
    if rest.clone().any(|t| t.starts_with("--")) {
        return Err(ParseError::UnknownOption);
    }
    let which = match (rest.next(), rest.next(), rest.next()) {
        (None | Some("last"), None, None) => Which::Last,
        (Some("ref"), None, None) => Which::Reference,
        (Some("nok"), Some(n), None) => match parse_count(n) {
            Some(n @ 1..=4) => Which::Nok(n as u8),
            _ => return Err(ParseError::BadArgument("curve")),
        },
        (Some("nok"), None, None) => return Err(ParseError::MissingArgument("curve")),
        (Some(_), None, None) | (Some("last" | "ref"), Some(_), _) => {
            return Err(ParseError::BadArgument("curve"))
        }
        _ => return Err(ParseError::ExtraArgument),
    };
    let format = if a.json {
        CurveFormat::Json
    } else if csv == 1 {
        CurveFormat::Csv
    } else {
        CurveFormat::Text
    };
    Ok(Command::Curve { which, format })
}

// The actions without arguments.
fn clear_fault_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(0).map(|()| Command::ClearFault)
}

fn home_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(0).map(|()| Command::Home)
}

fn dock_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(0).map(|()| Command::Dock)
}

fn undock_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(0).map(|()| Command::Undock)
}

fn stop_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(0).map(|()| Command::Stop)
}

fn rate_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(1)?;
    match a.get(0, "rate_sps")? {
        "10" => Ok(Command::Rate { sps: 10 }),
        "80" => Ok(Command::Rate { sps: 80 }),
        _ => Err(ParseError::BadArgument("rate_sps")),
    }
}

fn modbus_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(2)?;
    match a.pos.as_slice() {
        [] => Ok(Command::ModbusShow),
        [unit, baud] => {
            let unit = (unit.len() <= 3 && unit.bytes().all(|b| b.is_ascii_digit()))
                .then(|| parse_u32(unit))
                .flatten()
                .and_then(|u| u8::try_from(u).ok())
                .filter(|u| (1..=247).contains(u))
                .ok_or(ParseError::BadArgument("unit"))?;
            let baud = crate::modbus::BAUD_RATES
                .into_iter()
                .find(|b| parse_u32(baud) == Some(*b) && baud.len() <= 6)
                .ok_or(ParseError::BadArgument("baud"))?;
            Ok(Command::ModbusSet { unit, baud })
        }
        _ => Err(ParseError::MissingArgument("baud")),
    }
}

fn cone_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(5)?;
    if a.get(0, "cone subcommand")? != "replace" {
        return Err(ParseError::BadArgument("cone subcommand"));
    }
    let material =
        Material::from_name(a.get(1, "material")?).ok_or(ParseError::BadArgument("material"))?;
    let serial = a.get(2, "serial")?;
    if !is_serial(serial) {
        return Err(ParseError::BadArgument("serial"));
    }
    let bore_um = match a.pos.get(3).copied() {
        None => None,
        Some("--bore") => Some(bore(a.get(4, "d0_mm")?, "d0_mm")?),
        Some(t) if t.starts_with("--") => return Err(ParseError::UnknownOption),
        Some(_) => return Err(ParseError::ExtraArgument),
    };
    Ok(Command::ConeReplace {
        material,
        serial,
        bore_um,
    })
}

fn measure_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(2)?;
    match a.pos.as_slice() {
        ["--baseline", d] => Ok(Command::Measure {
            bore_um: bore(d, "d0_mm")?,
            baseline: true,
        }),
        ["--baseline"] => Err(ParseError::MissingArgument("d0_mm")),
        [t, ..] if t.starts_with("--") => Err(ParseError::UnknownOption),
        [d] => Ok(Command::Measure {
            bore_um: bore(d, "bore_diameter_mm")?,
            baseline: false,
        }),
        [] => Err(ParseError::MissingArgument("bore_diameter_mm")),
        _ => Err(ParseError::ExtraArgument),
    }
}

fn calibrate_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(2)?;
    match a.get(0, "calibrate subcommand")? {
        "tare" if a.pos.len() > 1 => Err(ParseError::ExtraArgument),
        "tare" => Ok(Command::CalibrateTare),
        "span" => {
            let force_mn = parse_milli(a.get(1, "force_n")?)
                .filter(|v| (SPAN_MIN_MN..=SPAN_MAX_MN).contains(v))
                .ok_or(ParseError::BadArgument("force_n"))?;
            Ok(Command::CalibrateSpan { force_mn })
        }
        _ => Err(ParseError::BadArgument("calibrate subcommand")),
    }
}

fn maint_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(1)?;
    match a.get(0, "pin")? {
        "exit" => Ok(Command::MaintExit),
        pin if is_pin(pin) => Ok(Command::Maint { pin }),
        _ => Err(ParseError::BadArgument("pin")),
    }
}

fn bor_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(1)?;
    match a.pos.as_slice() {
        [] => Ok(Command::BorShow),
        ["set"] => Ok(Command::BorSet),
        _ => Err(ParseError::BadArgument("bor subcommand")),
    }
}

fn update_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(0).map(|()| Command::Update)
}

fn pin_args<'a>(a: &Args<'a>) -> Result<Command<'a>, ParseError> {
    a.action(2)?;
    if a.get(0, "pin subcommand")? != "set" {
        return Err(ParseError::BadArgument("pin subcommand"));
    }
    let pin = a.get(1, "new_pin")?;
    if !is_pin(pin) {
        return Err(ParseError::BadArgument("new_pin"));
    }
    Ok(Command::PinSet { pin })
}

/// A PIN as accepted on the console: 4..=12 ASCII digits.
pub fn is_pin(s: &str) -> bool {
    (PIN_MIN_LEN..=PIN_MAX_LEN).contains(&s.len()) && s.bytes().all(|b| b.is_ascii_digit())
}

/// A cone serial number: 1..=20 chars of `[A-Za-z0-9_-]`.
pub fn is_serial(s: &str) -> bool {
    (1..=SERIAL_MAX_LEN).contains(&s.len())
        && s.bytes()
            .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-')
}

/// A bore diameter in mm (20.000..=40.000, up to 3 decimals), as µm.
fn bore(t: &str, name: &'static str) -> Result<u32, ParseError> {
    parse_milli(t)
        .filter(|v| (BORE_MIN_UM..=BORE_MAX_UM).contains(v))
        .ok_or(ParseError::BadArgument(name))
}

/// `s` as `u32::from_str` reads it: an optional `+`, then decimal digits; `None` on
/// anything else or on overflow. By hand: core's generic integer parser, instantiated
/// for `u8` and `u32`, cost more flash than `modbus`'s two arguments are worth (issue
/// 20).
fn parse_u32(s: &str) -> Option<u32> {
    let d = s.strip_prefix('+').unwrap_or(s);
    if d.is_empty() || !d.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    d.bytes().try_fold(0u32, |v, b| {
        v.checked_mul(10)?.checked_add(u32::from(b - b'0'))
    })
}

/// `history` count: 1..=3 ASCII digits, value 1..=100.
fn parse_count(s: &str) -> Option<u16> {
    if !(1..=3).contains(&s.len()) || !s.bytes().all(|b| b.is_ascii_digit()) {
        return None;
    }
    let n = s.bytes().fold(0u16, |n, b| n * 10 + u16::from(b - b'0'));
    (1..=HISTORY_MAX).contains(&n).then_some(n)
}

/// A plain decimal with up to 3 decimals, in thousandths (`"26.05"` → 26050).
///
/// Grammar: `digit+ ('.' digit{1,3})?`; `None` on anything else or on overflow.
pub fn parse_milli(s: &str) -> Option<u32> {
    let (int, frac) = match s.split_once('.') {
        Some((i, f)) => (i, f),
        None => (s, "000"),
    };
    if int.is_empty()
        || !(1..=3).contains(&frac.len())
        || !int.bytes().all(|b| b.is_ascii_digit())
        || !frac.bytes().all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let mut v: u32 = 0;
    for b in int.bytes() {
        v = v.checked_mul(10)?.checked_add(u32::from(b - b'0'))?;
    }
    let mut f: u32 = 0;
    for b in frac.bytes() {
        f = f * 10 + u32::from(b - b'0');
    }
    for _ in frac.len()..3 {
        f *= 10;
    }
    v.checked_mul(1000)?.checked_add(f)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// docs/console.md lists every command of the table (its syntax starting a line of
    /// the command block): a command added to COMMANDS and not to the page fails here.
    #[test]
    fn the_console_page_lists_every_command_of_the_table() {
        let page = include_str!("../../../../docs/console.md");
        for c in COMMANDS.iter() {
            assert!(
                page.lines().any(|l| l.starts_with(c.usage)),
                "docs/console.md does not list `{}`",
                c.usage
            );
        }
    }

    /// `parse_u32` reads what `u32::from_str` reads, and refuses what it refuses.
    #[test]
    fn u32_as_from_str_reads_it() {
        for t in [
            "0",
            "7",
            "+7",
            "09600",
            "+19200",
            "4294967295",
            "4294967296",
            "",
            "+",
            "-1",
            "+-1",
            "1.0",
            " 1",
            "1 ",
            "12a",
            "99999999999",
        ] {
            assert_eq!(parse_u32(t), t.parse::<u32>().ok(), "{t:?}");
        }
    }

    #[test]
    fn milli() {
        assert_eq!(parse_milli("26.05"), Some(26_050));
        assert_eq!(parse_milli("26"), Some(26_000));
        assert_eq!(parse_milli("0.001"), Some(1));
        assert_eq!(parse_milli("4294967.295"), Some(u32::MAX));
        assert_eq!(parse_milli("4294967.296"), None);
        assert_eq!(parse_milli("99999999999999"), None);
        for bad in [
            "", ".", "1.", ".5", "1.0000", "+1", "-1", "1e3", "nan", "inf", "1.2.3",
        ] {
            assert_eq!(parse_milli(bad), None, "{bad}");
        }
    }

    #[test]
    fn snippet_is_sanitised() {
        assert_eq!(Snippet::new("ab\u{1b}cdé").as_str(), "ab?cd?");
        assert_eq!(Snippet::new("abcdefghijklmnop").as_str(), "abcdefghijkl...");
    }
}
