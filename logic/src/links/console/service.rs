//! Console service: runs technician commands against the controller.
//!
//! [`Console::poll`] is called from the main loop after the controller's poll. Per call it
//! reads at most [`super::line::MAX_BYTES_PER_POLL`] bytes and runs
//! at most one command, so a flood of input costs the control loop a bounded slice of
//! time per iteration and is otherwise absorbed by the UART's receive buffer. Replies go
//! to an output ring that is drained into the [`ConsoleIo`] as fast as it takes them; a
//! reply that does not fit is dropped whole and replaced by a one-line notice.
//!
//! Text replies are `key=value` lines (easy to read, easy to `grep`); `CMD --json`
//! replies are one JSON object on one line. Errors are one line starting `error: `.
//! Every line ends with CR LF (terminals). The formats are documented in docs/console.md and
//! are stable: fields may be added, never renamed or removed.
//!
//! State-changing commands (`clear-fault`, `home`, `dock`, `undock`, `rate`,
//! `cone replace`, `measure`, `calibrate`, `pin set` once a PIN exists) need maintenance
//! mode (`maint <pin>`): they move the machine or change what it stores, and in service
//! the PLC owns the motion — a person at the console takes over knowingly. All but
//! `undock` (which applies to a docking under way) also need a machine at rest (idle or
//! faulted); each at rest writes an audit record with the cycle count. `stop` needs
//! nothing: a stop is never refused. Nothing on the console can reset the lifetime
//! totals.
//!
//! # Audit records
//!
//! Record kind [`kind::AUDIT`], 19 to 48 bytes (little-endian), declared once as the
//! `zerocopy` layout `AuditLayout` and written up to the end of its detail:
//!
//! ```text
//!  0        1                 5         7            11          19                48
//!  +--------+-----------------+---------+------------+-----------+------------------+
//!  | action | lifetime cycle  | cone id | cone cycle | t_ms      | detail (≤ 29 B)  |
//!  | u8     | u32             | u16     | u32        | u64       |                  |
//!  +--------+-----------------+---------+------------+-----------+------------------+
//!  action: a code of `action`; t_ms: milliseconds since boot
//!  detail: cone replace: material code u8 | serial (20 B, 0-pad)
//!          measure: bore_um u32 | baseline u8;  rate: sps u32;  modbus: its record;
//!          calibrate tare: offset_counts i32;  calibrate span: force_mn u32;
//!          bor: the level it was at u8;
//!          update: result u8 (0 verified, 1 refused) | new version (8 B) |
//!                  running version (8 B) | image length u32;  the others: none
//! ```

use core::fmt::{self, Write};
use core::mem::size_of;

use heapless::{Deque, String};
use zerocopy::byteorder::little_endian::{U16, U32, U64};
use zerocopy::{FromBytes, Immutable, IntoBytes, KnownLayout, Unaligned};

use super::auth::{make_pin_record, MaintenanceAuth, PinRecord};
use super::fields::{Fields, JsonFields, TextFields};
use super::json::{write_i64, write_u64, Sink};
use super::line::{LineEvent, LineReader, BS, CR, DEL, ESC, LF, MAX_BYTES_PER_POLL, TAB};
use super::parse::{parse, Command, COMMANDS};
use super::reports::{
    faults_fields, faults_view, history_fields, history_sig, measurements_fields,
    measurements_view, status_fields, status_view, wear_fields, wear_view, FaultsView,
    HistoryEntries, HistorySig, MeasurementsView, StatusView, WearView,
};
use crate::hal::ConsoleIo;
use crate::machine::Machine;
use crate::odometer::{kind, SERIAL_MAX};
use crate::sequencer::Request;
use crate::storage::PAYLOAD_MAX;
use crate::update::VERSION_TEXT_MAX;

const _: () = assert!(size_of::<AuditLayout>() == PAYLOAD_MAX);

/// Longest input line, bytes.
pub const LINE_MAX: usize = 128;
/// Output ring, bytes (holds `history 100 --json`).
pub const OUT_CAP: usize = 8192;

/// An audit record, as long as its longest detail (see the module doc).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct AuditLayout {
    action: u8,
    lifetime_cycle: U32,
    cone_id: U16,
    cone_cycle: U32,
    t_ms: U64,
    detail: [u8; AUDIT_DETAIL_MAX],
}

/// Longest detail of an audit record, bytes (the record fills a log payload).
const AUDIT_DETAIL_MAX: usize = 29;
/// Bytes of an audit record before its detail.
const AUDIT_HEAD_LEN: usize = size_of::<AuditLayout>() - AUDIT_DETAIL_MAX;

/// The detail of a `cone replace` audit record.
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct ConeReplaceDetail {
    material: u8,
    serial: [u8; SERIAL_MAX],
}

/// The detail of a `measure` audit record.
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct MeasureDetail {
    bore_um: U32,
    baseline: u8,
}

/// Audited maintenance actions (the `action` byte of an audit record).
pub mod action {
    /// A latched fault was cleared.
    pub const CLEAR_FAULT: u8 = 1;
    /// A cone was replaced.
    pub const CONE_REPLACE: u8 = 2;
    /// A bore measurement was recorded.
    pub const MEASURE: u8 = 3;
    /// The load cell was tared.
    pub const CALIBRATE_TARE: u8 = 4;
    /// The load cell's span was set.
    pub const CALIBRATE_SPAN: u8 = 5;
    /// The maintenance PIN was set.
    pub const PIN_SET: u8 = 6;
    /// Homing was asked for after a reset.
    pub const HOME: u8 = 7;
    /// The HX711's rate was set.
    pub const RATE: u8 = 8;
    /// A docking was started from the console. (`undock` is not audited here: it runs
    /// while the machine moves, when no flash is written; the cycle's history entry
    /// records it.)
    pub const DOCK: u8 = 9;
    /// The Modbus line's settings were stored.
    pub const MODBUS: u8 = 10;
    /// The brown-out reset level was programmed (detail: the level found, u8).
    pub const BOR: u8 = 11;
    /// A firmware update was received (issue 21; detail: result u8 — 0 verified and
    /// marked for the swap, 1 refused — the new image's version, the running image's
    /// (8 B each, `update_layout::header::Version`, FF.. unknown), its length u32).
    pub const UPDATE: u8 = 12;
}

/// What one poll did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ConsolePoll {
    /// Bytes read.
    pub bytes_in: usize,
    /// Commands run (0 or 1).
    pub commands: u32,
    /// PIN hashes computed (each ~257 SHA-256 compressions).
    pub pin_hashes: u32,
}

struct Out {
    buf: Deque<u8, OUT_CAP>,
}

impl Out {
    /// Bytes queued (out of line: the ring's length is a dozen instructions, and every
    /// reply takes it).
    #[inline(never)]
    fn len(&self) -> usize {
        self.buf.len()
    }

    /// Queue `bytes`, as many as fit; an error when one did not. Out of line: every
    /// reply, echo and formatted value goes through it (inlined, each copy cost flash).
    #[inline(never)]
    fn push(&mut self, bytes: &[u8]) -> fmt::Result {
        for &b in bytes {
            self.buf.push_back(b).map_err(|_| fmt::Error)?;
        }
        Ok(())
    }
}

impl Write for Out {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        self.push(s.as_bytes())
    }
}

/// Write ` key=` and a fixed-point value (`value_scaled` with `decimals` decimals).
fn kv_fixed(o: &mut Out, key: &str, value_scaled: i64, decimals: u8) -> fmt::Result {
    kv(o, key)?;
    super::json::write_fixed(o, value_scaled, decimals)
}

/// Write ` key=` (its value follows).
fn kv(o: &mut Out, key: &str) -> fmt::Result {
    o.write_str(" ")?;
    o.write_str(key)?;
    o.write_str("=")
}

/// Write each of `parts` in turn (a reply's literal text and the values between).
fn write_all(o: &mut Out, parts: &[&str]) -> fmt::Result {
    parts.iter().try_for_each(|p| o.write_str(p))
}

/// The running image's version (its header's), or the build's where no header is known
/// (the simulators).
fn running_text<'a>(
    images: &crate::update::ImageReport,
    buf: &'a mut [u8; VERSION_TEXT_MAX],
) -> &'a str {
    match images.running {
        Some(_) => super::update::version_text(images.running, buf),
        None => env!("CARGO_PKG_VERSION"),
    }
}

/// A reply's message: written piece by piece, never through core::fmt's `write!`
/// (issue 20: the console's replies are literal text, decimal numbers and fixed-point
/// values; core::fmt's machinery and an `Arguments` at every reply cost the image
/// more than the text itself).
trait Message {
    fn write_to(&self, w: &mut dyn Sink) -> fmt::Result;
}

impl Message for &str {
    fn write_to(&self, w: &mut dyn Sink) -> fmt::Result {
        w.put(self)
    }
}

impl Message for crate::controller::Refusal {
    fn write_to(&self, w: &mut dyn Sink) -> fmt::Result {
        w.put(self.message())
    }
}

impl Message for crate::controller::MaintError {
    fn write_to(&self, w: &mut dyn Sink) -> fmt::Result {
        w.put(self.message())
    }
}

impl Message for crate::controller::CalibrateError {
    fn write_to(&self, w: &mut dyn Sink) -> fmt::Result {
        w.put(self.message())
    }
}

impl Message for super::parse::ParseError {
    fn write_to(&self, w: &mut dyn Sink) -> fmt::Result {
        self.write_message(w)
    }
}

impl Message for super::auth::AuthError {
    fn write_to(&self, w: &mut dyn Sink) -> fmt::Result {
        self.write_message(w)
    }
}

/// The console.
pub struct Console {
    reader: LineReader<LINE_MAX>,
    auth: MaintenanceAuth,
    out: Out,
    entropy: [u8; 32],
    salts_made: u32,
    dropped_replies: u32,
    rx_errors: u32,
    /// Work left for [`Console::finish`]: all-zero when empty, so the console (8 KiB of
    /// output ring) stays in `.bss` rather than being copied from flash as `.data`.
    deferred: Deferred,
    /// The terminal (all fields zero at reset, for `.bss` too).
    term: TermState,
}

/// What an interactive terminal sees: echo, line editing, the prompt (see
/// [`Console::read_line`]).
struct TermState {
    /// `echo off`: no echo, no prompt, no editing keys (the bare line protocol).
    quiet: bool,
    /// Escape sequence: 0 none, 1 after ESC, 2 in a CSI (`ESC [`), 3 after `ESC O`.
    esc: u8,
    /// The previous byte was CR (the LF of a CR LF echoes nothing).
    after_cr: bool,
    /// The last lines run, oldest first (Up recalls them, Down comes back); never one
    /// holding a PIN.
    recall: Deque<String<LINE_MAX>, RECALL_LINES>,
    /// How far back Up went: 0 the line being typed, n the n-th newest of `recall`.
    recall_at: u8,
    /// The machine's state for the prompt, as last seen (`None`: not yet).
    state: Option<&'static str>,
    /// Maintenance mode, as last seen (the prompt ends `#` instead of `>`).
    maint: bool,
    /// The host runs `update`'s session ([`Console::enable_updater`]: the board); the
    /// simulators have no DFU partition and refuse `update`.
    updater: bool,
    /// The unit's serial number (the chip's unique ID in hex, as Modbus device
    /// identification's object 0x80), `unit_len` bytes of it ([`Console::set_unit`]).
    unit: [u8; UNIT_MAX],
    unit_len: u8,
}

/// The longest unit serial `version` reports (the chip's 96-bit ID in hex: 24).
pub const UNIT_MAX: usize = 24;

/// Ctrl-C: abandon the line.
const CTRL_C: u8 = 0x03;
/// Ctrl-U: erase the line.
const CTRL_U: u8 = 0x15;
/// What erases one character on a terminal.
const RUB_OUT: &[u8] = b"\x08 \x08";

/// Lines Up recalls (issue 35: it recalled one).
const RECALL_LINES: usize = 4;

/// A line whose rest is a PIN: echoed as `*`, never recalled. `maint exit`, and what is
/// typed on the way to it, is not one (issue 35: it was echoed `maint ****`).
fn is_secret(line: &[u8]) -> bool {
    match line.strip_prefix(b"maint ") {
        Some(rest) => !(b"exit".starts_with(rest) || rest.starts_with(b"exit")),
        None => line
            .strip_prefix(b"pin set ")
            .is_some_and(|rest| !rest.is_empty()),
    }
}

/// What a command leaves for after the controller is released.
struct Deferred {
    /// A maintenance login waits for its PIN check.
    login: bool,
    login_pin: String<LINE_MAX>,
    login_rec: [u8; PinRecord::LEN],
    login_has_rec: bool,
    /// A `pin set` waits for its hash (`login_pin` holds the new PIN), then for the
    /// controller again to store the record ([`Console::store`]).
    pin_set: bool,
    pin_rec: [u8; PinRecord::LEN],
    pin_rec_ready: bool,
    /// A login's PIN checked out: maintenance mode waits to be granted to the controller
    /// ([`Console::store`]) before the reply says so.
    grant: bool,
    /// A report waits to be written (`report_json`: as JSON).
    report: Report,
    report_json: bool,
    /// `update` was accepted: the board starts the session ([`Console::take_update`]).
    update: bool,
}

/// A report's data, copied from the controller while the console holds it
/// ([`Console::run_line`]) and written out after it is released ([`Console::finish`]):
/// the control step never waits for formatting.
// It lives in the console's static; `finish` moves it out once (as `history` did
// before it).
#[allow(clippy::large_enum_variant)]
enum Report {
    /// Nothing waits (all-zero: the console stays in `.bss`).
    None,
    Status(StatusView),
    Wear(WearView),
    Faults(FaultsView),
    Measurements(MeasurementsView),
    History(HistoryEntries, HistorySig),
    /// `curve`: the curve and how to write it.
    Curve(crate::signature::view::CurveView, super::parse::CurveFormat),
}

impl Console {
    /// A console; `entropy` seeds the PIN salts (device ID, boot time… anything unique).
    /// `const`: the board places it in a static, not on the init stack (it holds the
    /// 8 KiB output ring).
    pub const fn new(entropy: [u8; 32]) -> Self {
        Self {
            reader: LineReader::new(),
            auth: MaintenanceAuth::new(),
            out: Out { buf: Deque::new() },
            entropy,
            salts_made: 0,
            dropped_replies: 0,
            rx_errors: 0,
            deferred: Deferred {
                login: false,
                login_pin: String::new(),
                login_rec: [0; PinRecord::LEN],
                login_has_rec: false,
                pin_set: false,
                pin_rec: [0; PinRecord::LEN],
                pin_rec_ready: false,
                grant: false,
                report: Report::None,
                report_json: false,
                update: false,
            },
            term: TermState {
                quiet: false,
                esc: 0,
                after_cr: false,
                recall: Deque::new(),
                recall_at: 0,
                state: None,
                maint: false,
                updater: false,
                unit: [0; UNIT_MAX],
                unit_len: 0,
            },
        }
    }

    /// The boot banner: one line with a fixed prefix (`# `, so a script can skip it)
    /// naming the firmware and why it reset, then the prompt.
    #[inline(never)]
    pub fn banner(&mut self, reset: &str) {
        self.banner_of(&crate::update::ImageReport::UNKNOWN, reset);
    }

    /// [`Self::banner`] naming the running image's version (its header's; issue 21).
    #[inline(never)]
    pub fn banner_of(&mut self, images: &crate::update::ImageReport, reset: &str) {
        let mut t = [0u8; VERSION_TEXT_MAX];
        let v = running_text(images, &mut t);
        self.reply(|o| {
            write_all(
                o,
                &[
                    "# docking-controller ",
                    v,
                    " reset=",
                    reset,
                    "; type 'help'\r\n",
                ],
            )
        });
        self.prompt();
    }

    /// What the prompt shows: the machine's state, and maintenance mode at `now_ms`
    /// (the board tells the console each turn; a command's run tells it too).
    #[inline(never)]
    pub fn observe(&mut self, state: &'static str, now_ms: u64) {
        self.term.state = Some(state);
        self.term.maint = self.auth.is_active(now_ms);
    }

    /// Whether echo, prompt and line editing are on (`echo off` turns them off).
    pub fn interactive(&self) -> bool {
        !self.term.quiet
    }

    /// Turn echo, prompt and line editing on or off (a script's `echo off`).
    pub fn set_interactive(&mut self, on: bool) {
        self.term.quiet = !on;
    }

    /// Bytes shown as typed (best effort: a full output ring drops them).
    fn echo(&mut self, bytes: &[u8]) {
        let _ = self.out.push(bytes);
    }

    /// `idle> `, or `idle# ` in maintenance mode (interactive only).
    fn prompt(&mut self) {
        if self.term.quiet {
            return;
        }
        let st = self.term.state.unwrap_or("ready");
        let sign = if self.term.maint { "# " } else { "> " };
        let _ = write_all(&mut self.out, &[st, sign]);
    }

    /// Erase the characters of the line being typed from the screen.
    fn erase_shown(&mut self) {
        for _ in 0..self.reader.pending_chars() {
            self.echo(RUB_OUT);
        }
    }

    /// An interactive terminal's keys, before the line reader sees a byte: arrows
    /// (Up recalls the previous line, Down clears, the rest do nothing), Ctrl-C, Ctrl-U,
    /// backspace's rub-out. Returns the byte for the reader, `None` when taken here.
    #[inline(never)]
    fn edit_key(&mut self, byte: u8) -> Option<u8> {
        match self.term.esc {
            1 => {
                self.term.esc = match byte {
                    b'[' => 2,
                    b'O' => 3,
                    _ => 0,
                };
                return None;
            }
            2 if (0x20..=0x3F).contains(&byte) => return None,
            2 | 3 => {
                self.term.esc = 0;
                let n = self.term.recall.len();
                let at = match byte {
                    b'A' if usize::from(self.term.recall_at) < n => self.term.recall_at + 1,
                    b'B' => self.term.recall_at.saturating_sub(1),
                    _ => return None,
                };
                self.term.recall_at = at;
                self.erase_shown();
                // Newest last: the n-th newest at len - n (none at 0: a clear line).
                let line = match usize::from(at) {
                    0 => String::new(),
                    k => self
                        .term
                        .recall
                        .iter()
                        .nth(n.saturating_sub(k))
                        .cloned()
                        .unwrap_or_default(),
                };
                self.reader.replace_pending(line.as_bytes());
                self.echo(line.as_bytes());
                return None;
            }
            _ => {}
        }
        match byte {
            ESC => {
                self.term.esc = 1;
                None
            }
            CTRL_C => {
                self.echo(b"^C\r\n");
                self.reader.reset();
                self.term.recall_at = 0;
                self.prompt();
                None
            }
            CTRL_U => {
                self.erase_shown();
                self.reader.reset();
                None
            }
            BS | DEL => {
                if self.reader.pending_chars() > 0 {
                    self.echo(RUB_OUT);
                }
                Some(byte)
            }
            CR | LF | TAB => Some(byte),
            // Other control keys do nothing on a terminal.
            0x01..=0x1F => None,
            _ => Some(byte),
        }
    }

    /// Echo what `byte` did to the line (interactive): the character (`*` in a PIN),
    /// a bell when the line is full; the end of a line echoes CR LF once.
    fn echo_typed(&mut self, byte: u8, shown_before: usize, secret: bool) {
        match byte {
            BS | DEL => {}
            CR | LF => {}
            _ if self.reader.pending().len() > shown_before => {
                self.echo(&[if secret { b'*' } else { byte }]);
            }
            _ => self.echo(b"\x07"),
        }
    }

    /// Seed the PIN salts with `entropy` (for a console built in a static before the
    /// board could gather any).
    pub fn seed(&mut self, entropy: &[u8; 32]) {
        self.entropy.copy_from_slice(entropy);
    }

    /// Replies dropped because the output ring was full.
    pub fn dropped_replies(&self) -> u32 {
        self.dropped_replies
    }

    /// Whether maintenance mode is active at `now_ms`.
    pub fn maintenance_active(&self, now_ms: u64) -> bool {
        self.auth.is_active(now_ms)
    }

    fn flush(&mut self, io: &mut dyn ConsoleIo) {
        while !self.out.buf.is_empty() {
            let (a, b) = self.out.buf.as_slices();
            let chunk = if a.is_empty() { b } else { a };
            let n = io.write(chunk);
            if n == 0 {
                break;
            }
            for _ in 0..n.min(chunk.len()) {
                self.out.buf.pop_front();
            }
        }
    }

    /// Read and act on console input; bounded work (see the module doc). The three
    /// phases in one call: [`Self::read_line`], [`Self::run_line`] (the only one that
    /// needs the controller), [`Self::finish`]; the board calls them apart so that it
    /// holds the controller for the run only.
    pub fn poll(
        &mut self,
        ctrl: &mut dyn Machine,
        io: &mut dyn ConsoleIo,
        now_ms: u64,
    ) -> ConsolePoll {
        self.observe(ctrl.state().name(), now_ms);
        let (line, mut st) = self.read_line(io);
        if let Some(line) = line {
            st.pin_hashes = self.run_line(ctrl, &line, now_ms) + self.finish(now_ms);
            if self.store_due() {
                self.store(ctrl, now_ms);
            }
        }
        ctrl.set_maintenance_mode(self.auth.is_active(now_ms));
        self.flush(io);
        st
    }

    /// Whether a line is under way: bytes of it read (or a line recalled), an escape
    /// sequence begun, or a line being discarded (overlong, a byte lost). The board's
    /// idle loop takes the console for quiet (a later line was typed after that
    /// instant: its issue time, docs/board.md rule 1) only when its receive ring is
    /// empty **and** no line is under way here; the ring alone empties as this reads a
    /// line's first bytes.
    pub fn line_started(&self) -> bool {
        self.reader.under_way() || self.term.esc != 0
    }

    /// Phase 1, without the controller: take input bytes (at most
    /// `MAX_BYTES_PER_POLL`) until a whole line is in; bad input is answered here.
    #[inline(never)]
    pub fn read_line(&mut self, io: &mut dyn ConsoleIo) -> (Option<String<LINE_MAX>>, ConsolePoll) {
        self.flush(io);
        let mut st = ConsolePoll::default();
        while st.bytes_in < MAX_BYTES_PER_POLL {
            let byte = match io.read_byte() {
                Ok(b) => b,
                Err(nb::Error::WouldBlock) => break,
                Err(nb::Error::Other(())) => {
                    // Framing/overrun/noise/full ring: a byte is gone. The line it was
                    // part of is discarded, never run with a byte missing.
                    self.rx_errors = self.rx_errors.saturating_add(1);
                    self.reader.lost();
                    st.bytes_in += 1;
                    continue;
                }
            };
            st.bytes_in += 1;
            let interactive = !self.term.quiet;
            let byte = match interactive {
                true => match self.edit_key(byte) {
                    Some(b) => b,
                    None => continue,
                },
                false => byte,
            };
            let shown = self.reader.pending().len();
            // The end of a line: CR, LF, or the first of CR LF.
            let ends = (byte == CR || byte == LF) && !(byte == LF && self.term.after_cr);
            self.term.after_cr = byte == CR;
            if interactive && ends {
                self.echo(b"\r\n");
            }
            match self.reader.push(byte) {
                None => {
                    if interactive {
                        if ends {
                            self.prompt(); // a blank line
                        } else {
                            // Masked by what the line is with this byte in it.
                            let secret = is_secret(self.reader.pending());
                            self.echo_typed(byte, shown, secret);
                        }
                    }
                }
                Some(LineEvent::Error(e)) => {
                    self.reply(|o| write_all(o, &["error: ", e.message(), "\r\n"]));
                    self.prompt();
                }
                Some(LineEvent::Line(l)) => {
                    let mut line: String<LINE_MAX> = String::new();
                    let _ = line.push_str(l);
                    self.term.recall_at = 0;
                    let newest = self.term.recall.back().map(|l| l.as_str());
                    if !is_secret(line.as_bytes()) && newest != Some(line.as_str()) {
                        if self.term.recall.is_full() {
                            self.term.recall.pop_front();
                        }
                        let _ = self.term.recall.push_back(line.clone());
                    }
                    st.commands = 1;
                    return (Some(line), st);
                }
            }
        }
        (None, st)
    }

    /// Phase 3, without the controller: the work a command left for after the
    /// controller is released (a maintenance login's PIN check). Returns the PIN hashes
    /// computed. A login that checks out is granted to the controller by
    /// [`Self::store`] (phase 4, [`Self::store_due`]), which replies; the session's end
    /// by its idle timeout reaches it through [`Self::maintenance_active`] (the board
    /// and [`Self::poll`] tell it).
    #[inline(never)]
    pub fn finish(&mut self, now_ms: u64) -> u32 {
        let json = self.deferred.report_json;
        let report = core::mem::replace(&mut self.deferred.report, Report::None);
        match &report {
            Report::None => {}
            Report::Status(v) => self.render_status(v, json),
            Report::Wear(v) => self.render_wear(v, json),
            Report::Faults(v) => self.render_faults(v, json),
            Report::Measurements(v) => self.render_measurements(v, json),
            Report::History(entries, sig) => self.render_history(entries, sig, json),
            Report::Curve(v, format) => {
                self.reply(|o| super::curve::render(o, v, *format));
            }
        }
        let hashed = self.finish_login(now_ms) + self.finish_pin_set(now_ms);
        self.term.maint = self.auth.is_active(now_ms);
        // No prompt before an update's YMODEM session (its reply comes after it).
        if !self.store_due() && !self.deferred.update {
            self.prompt();
        }
        hashed
    }

    /// A `pin set`'s new record: salted and hashed here, without the controller.
    fn finish_pin_set(&mut self, now_ms: u64) -> u32 {
        if !core::mem::take(&mut self.deferred.pin_set) {
            return 0;
        }
        let pin = core::mem::take(&mut self.deferred.login_pin);
        let salt = self.new_salt(now_ms);
        match make_pin_record(&pin, salt) {
            Ok(rec) => {
                self.deferred.pin_rec = rec.to_bytes();
                self.deferred.pin_rec_ready = true;
            }
            Err(e) => self.err(&e),
        }
        1
    }

    /// Whether a command's record, or a login's grant, waits for [`Self::store`] (with
    /// the controller).
    pub fn store_due(&self) -> bool {
        self.deferred.pin_rec_ready || self.deferred.grant
    }

    /// Phase 4, with the controller again: what [`Self::finish`] prepared — a login's
    /// grant of maintenance mode (in force in the controller before the reply says so:
    /// a DOCK edge or a Modbus command from then on is refused, and the prompt shows
    /// the state the grant found: docs/board.md, "What holds between the steps", rule
    /// 2), a new PIN record (written at rest only, else refused) — then the prompt.
    #[inline(never)]
    pub fn store(&mut self, ctrl: &mut dyn Machine, now_ms: u64) {
        if core::mem::take(&mut self.deferred.grant) {
            ctrl.set_maintenance_mode(self.auth.is_active(now_ms));
            self.ok(&"maintenance mode (ends after 10 min idle or `maint exit`)");
        }
        if core::mem::take(&mut self.deferred.pin_rec_ready) {
            let rec = self.deferred.pin_rec;
            match ctrl.store_record(kind::PIN, &rec) {
                Ok(()) => {
                    self.audit(ctrl, action::PIN_SET, now_ms, &[]);
                    self.ok(&"PIN set");
                }
                Err(e) => self.err(&e),
            }
        }
        self.term.state = Some(ctrl.state().name());
        self.prompt();
    }

    /// A maintenance login's PIN check, if one waits; the PIN hashes computed.
    fn finish_login(&mut self, now_ms: u64) -> u32 {
        if !core::mem::take(&mut self.deferred.login) {
            return 0;
        }
        let pin = core::mem::take(&mut self.deferred.login_pin);
        let rec = core::mem::take(&mut self.deferred.login_has_rec)
            .then(|| PinRecord::from_bytes(&self.deferred.login_rec))
            .flatten();
        let hashed = rec.is_some() && self.auth.lockout_remaining_s(now_ms).is_none();
        match self.auth.try_enter(now_ms, &pin, rec.as_ref()) {
            Ok(()) => {
                info!("maintenance mode entered");
                // Granted to the controller, and only then said, by `store`.
                self.deferred.grant = true;
            }
            Err(e) => {
                warn!("maintenance login refused");
                self.err(&e);
            }
        }
        hashed as u32
    }

    /// Send what is in the output ring (as much as the link takes).
    #[inline(never)]
    pub fn flush_output(&mut self, io: &mut dyn ConsoleIo) {
        self.flush(io);
    }

    /// Write one whole reply or none (replaced by a short notice when it does not fit).
    fn reply(&mut self, f: impl FnOnce(&mut Out) -> fmt::Result) {
        let mark = self.out.len();
        let r = f(&mut self.out);
        self.reply_end(mark, r);
    }

    /// A reply written from `mark` on: kept whole, or (`r` an error: it did not fit)
    /// taken back and replaced by the notice. Not generic and out of line: one copy
    /// for every reply.
    #[inline(never)]
    fn reply_end(&mut self, mark: usize, r: fmt::Result) {
        if r.is_err() {
            self.out.buf.truncate(mark);
            self.dropped_replies = self.dropped_replies.saturating_add(1);
            let _ = self
                .out
                .write_str("error: reply dropped, output buffer full\r\n");
        }
    }

    fn err(&mut self, msg: &dyn Message) {
        self.said("error: ", msg);
    }

    fn ok(&mut self, msg: &dyn Message) {
        self.said("ok: ", msg);
    }

    /// `head`, the message, CR LF: one reply (out of line: every `ok` and `error`).
    #[inline(never)]
    fn said(&mut self, head: &str, msg: &dyn Message) {
        self.reply(|o| {
            o.write_str(head)?;
            msg.write_to(o)?;
            o.write_str("\r\n")
        });
    }

    /// One reply of these parts, whole or not at all (no formatting).
    pub(super) fn reply_parts(&mut self, parts: &[&[u8]]) {
        self.reply(|o| parts.iter().try_for_each(|p| o.push(p)));
    }

    /// `error: ` and a refusal's message (the update's, from its own module).
    pub(super) fn err_maint(&mut self, e: crate::controller::MaintError) {
        self.err(&e);
    }

    /// `update` was accepted: the board starts its session after this reply.
    pub(super) fn request_update(&mut self) {
        self.deferred.update = true;
    }

    /// The host runs `update`'s session when [`Self::take_update`] says so (the board).
    pub fn enable_updater(&mut self) {
        self.term.updater = true;
    }

    /// Whether `update` is taken here.
    pub(super) fn has_updater(&self) -> bool {
        self.term.updater
    }

    /// The unit's serial number `version` reports (issue 35: `dockctl export` names the
    /// machine by it): printable ASCII, at most [`UNIT_MAX`] bytes (more are cut).
    pub fn set_unit(&mut self, serial: &str) {
        let b = serial.as_bytes();
        let n = b
            .iter()
            .take(UNIT_MAX)
            .take_while(|c| c.is_ascii_graphic())
            .count();
        if let (Some(dst), Some(src)) = (self.term.unit.get_mut(..n), b.get(..n)) {
            dst.copy_from_slice(src);
        }
        self.term.unit_len = n as u8;
    }

    /// Whether an `update` waits for its session (asked once: it is cleared).
    pub fn take_update(&mut self) -> bool {
        core::mem::take(&mut self.deferred.update)
    }

    /// The prompt after an update's refusal.
    pub(super) fn prompt_after_update(&mut self) {
        self.prompt();
    }

    /// An audit record of `act` (the update's, from its own module).
    pub(super) fn audit_action(
        &mut self,
        ctrl: &mut dyn Machine,
        act: u8,
        now_ms: u64,
        detail: &[u8],
    ) {
        self.audit(ctrl, act, now_ms, detail);
    }

    fn pin_record(ctrl: &mut dyn Machine) -> Option<PinRecord> {
        let mut buf = [0u8; 48];
        let n = ctrl.load_record(kind::PIN, &mut buf)?;
        PinRecord::from_bytes(buf.get(..n)?)
    }

    fn new_salt(&mut self, now_ms: u64) -> [u8; 16] {
        self.salts_made = self.salts_made.wrapping_add(1);
        let d = super::auth::sha256_short(&[
            &self.entropy,
            &self.salts_made.to_le_bytes(),
            &now_ms.to_le_bytes(),
        ]);
        let mut salt = [0u8; 16];
        if let Some(src) = d.get(..16) {
            salt.copy_from_slice(src);
        }
        salt
    }

    /// A command to the controller ([`Controller::command`]): on acceptance the audit
    /// record `act` (if any) and `ok_msg`, else the refusal.
    fn request(
        &mut self,
        ctrl: &mut dyn Machine,
        r: Request,
        act: Option<u8>,
        now_ms: u64,
        ok_msg: &str,
    ) {
        match ctrl.command(r) {
            Ok(()) => {
                if let Some(act) = act {
                    self.audit(ctrl, act, now_ms, &[]);
                }
                self.ok(&ok_msg);
            }
            Err(e) => self.err(&e),
        }
    }

    fn audit(&mut self, ctrl: &mut dyn Machine, act: u8, now_ms: u64, detail: &[u8]) {
        let odo = ctrl.odometer();
        let rec = AuditLayout {
            action: act,
            lifetime_cycle: odo.lifetime().cycles.into(),
            cone_id: odo.cone().id.into(),
            cone_cycle: odo.cone().cycles.into(),
            t_ms: now_ms.into(),
            // Byte by byte, not zero-filled then copied: a zero fill of these unaligned
            // bytes was one of the three calls that linked compiler_builtins' memclr.
            detail: core::array::from_fn(|i| detail.get(i).copied().unwrap_or(0)),
        };
        let at = AUDIT_HEAD_LEN + detail.len().min(AUDIT_DETAIL_MAX);
        info!(
            "maintenance: action {=u8} at lifetime cycle {=u32}",
            act,
            odo.lifetime().cycles
        );
        // Written now at rest, else queued for the next rest (a clear-fault while the
        // axis is held, a reply on the Modbus line): never an erase out of turn.
        let rec = rec.as_bytes();
        let rec = rec.get(..at).unwrap_or(rec);
        let written = ctrl.write_or_queue_record(kind::AUDIT, rec);
        if !written {
            error!("maintenance: audit record not written");
        }
    }

    /// Phase 2, with the controller: run one line. A report's data is copied here and
    /// written out by [`Self::finish`]; a maintenance login only fetches the stored PIN
    /// record here and a `pin set` only takes the PIN: their hash (257 SHA-256
    /// compressions, milliseconds) waits for [`Self::finish`], without the controller,
    /// and a new PIN record is stored by [`Self::store`]. Returns the PIN hashes
    /// computed here (none).
    #[inline(never)]
    pub fn run_line(&mut self, ctrl: &mut dyn Machine, line: &str, now_ms: u64) -> u32 {
        let hashes = self.run_command(ctrl, line, now_ms);
        self.term.state = Some(ctrl.state().name());
        hashes
    }

    fn run_command(&mut self, ctrl: &mut dyn Machine, line: &str, now_ms: u64) -> u32 {
        let cmd = match parse(line) {
            Ok(c) => c,
            Err(e) => {
                self.err(&e);
                return 0;
            }
        };
        let maint = self.auth.is_active(now_ms);
        if maint {
            self.auth.touch(now_ms);
        }
        let pin_exists = Self::pin_record(ctrl).is_some();
        let gated = match cmd {
            Command::PinSet { .. } => pin_exists,
            Command::Measure { .. } => true,
            c => c.is_state_changing(),
        };
        if gated && !maint {
            self.err(&"maintenance mode required (maint <pin>)");
            return 0;
        }
        let rest = cmd.needs_rest() || matches!(cmd, Command::Measure { .. });
        if gated && rest && !ctrl.is_quiet() {
            // Say what it is (issue 35: a machine holding mated was "moving").
            self.err(&match ctrl.state() {
                crate::sequencer::State::Holding { .. } => {
                    "refused while mated: at rest only (undock first)"
                }
                _ => "refused while a docking is moving",
            });
            return 0;
        }
        match cmd {
            Command::Help { topic, json } => self.help(topic, json),
            Command::Echo { on: None } => {
                let on = if self.term.quiet { "off" } else { "on" };
                self.reply(|o| write_all(o, &["echo=", on, "\r\n"]));
            }
            Command::Echo { on: Some(on) } => {
                self.term.quiet = !on;
                if on {
                    self.ok(&"echo, prompt and line editing on");
                } else {
                    self.ok(&"echo and prompt off until reset (`echo on` turns them back on)");
                }
            }
            Command::Version { json } => self.version(&ctrl.images(), json),
            Command::Update => super::update::begin(self, ctrl),
            Command::Status { json } => self.defer(Report::Status(status_view(ctrl, maint)), json),
            Command::Wear { json } => self.defer(Report::Wear(wear_view(ctrl)), json),
            Command::History { n, json } => {
                let mut entries = HistoryEntries::new();
                ctrl.history(n as usize, &mut |e| {
                    let _ = entries.push(e);
                });
                let sig = history_sig(ctrl, &entries);
                self.defer(Report::History(entries, sig), json)
            }
            Command::Curve { which, format } => {
                let mut v = crate::signature::view::CurveView::empty(ctrl.config().signature);
                if ctrl.curve(which, &mut v) {
                    self.defer(Report::Curve(v, format), false);
                } else {
                    self.err(&match which {
                        crate::signature::view::Which::Last => "no docking captured since boot",
                        crate::signature::view::Which::Reference => {
                            "no reference yet: it is the mean of the cone's first OK dockings"
                        }
                        crate::signature::view::Which::Nok(_) => "no such NOK curve kept",
                    });
                }
            }
            Command::Faults { json } => self.defer(Report::Faults(faults_view(ctrl)), json),
            Command::ClearFault => self.request(
                ctrl,
                Request::ClearFault,
                Some(action::CLEAR_FAULT),
                now_ms,
                "fault cleared; recovering to home",
            ),
            Command::Home => self.request(
                ctrl,
                Request::Home,
                Some(action::HOME),
                now_ms,
                "homing: the axis moves at no more than v0, then the lock",
            ),
            Command::Dock => self.request(
                ctrl,
                Request::Dock,
                Some(action::DOCK),
                now_ms,
                "docking: mated until undock",
            ),
            // Runs while the machine moves, when no flash is written: not audited (the
            // cycle's history entry records it).
            Command::Undock => self.request(
                ctrl,
                Request::Undock,
                None,
                now_ms,
                "undocking: extraction, re-lock, home",
            ),
            // Never refused.
            Command::Stop => self.request(
                ctrl,
                Request::Stop,
                None,
                now_ms,
                "stopped: all motion off, latched (clear-fault to recover)",
            ),
            Command::Rate { sps } => match ctrl.store_rate(sps) {
                Ok(()) => {
                    self.audit(ctrl, action::RATE, now_ms, &sps.to_le_bytes());
                    self.ok(&"HX711 rate stored; it takes effect at the next boot");
                }
                Err(e) => self.err(&e),
            },
            Command::BorShow => {
                let l = ctrl.bor_level();
                self.reply(|o| {
                    o.write_str("bor level=")?;
                    write_u64(o, u64::from(l))?;
                    write_all(o, &[" (", bor_text(l), ")\r\n"])
                });
            }
            Command::BorSet => match ctrl.program_bor() {
                Ok(3) => self.ok(&"BOR level 3 (2.70 V) was set already"),
                Ok(from) => {
                    self.audit(ctrl, action::BOR, now_ms, &[from]);
                    self.ok(
                        &"BOR level 3 (2.70 V) programmed: a sagging supply now resets cleanly",
                    );
                }
                Err(e) => self.err(&e),
            },
            Command::ModbusShow => {
                let st = crate::modbus::ModbusSettings::stored(ctrl);
                self.reply(|o| {
                    o.write_str("modbus unit=")?;
                    write_u64(o, u64::from(st.unit))?;
                    o.write_str(" baud=")?;
                    write_u64(o, u64::from(st.baud))?;
                    o.write_str(" format=8E1 (stored; the line uses them from the boot after they were stored)\r\n")
                });
            }
            Command::ModbusSet { unit, baud } => {
                match crate::modbus::ModbusSettings::new(unit, baud) {
                    Some(st) => match ctrl.store_record(kind::MODBUS, &st.to_bytes()) {
                        Ok(()) => {
                            self.audit(ctrl, action::MODBUS, now_ms, &st.to_bytes());
                            self.ok(&"Modbus settings stored; they take effect at the next boot");
                        }
                        Err(e) => self.err(&e),
                    },
                    None => self.err(&"unit 1..=247, baud 9600|19200|38400|57600|115200"),
                }
            }
            Command::ConeReplace {
                material,
                serial,
                bore_um,
            } => match ctrl.replace_cone_measured(material, serial, bore_um) {
                Ok(()) => {
                    // Built byte by byte (no zero fill first: see `audit`).
                    let detail = ConeReplaceDetail {
                        material: material.code(),
                        serial: core::array::from_fn(|i| {
                            serial.as_bytes().get(i).copied().unwrap_or(0)
                        }),
                    };
                    self.audit(ctrl, action::CONE_REPLACE, now_ms, detail.as_bytes());
                    let id = ctrl.odometer().cone().id;
                    self.reply(|o| {
                            o.write_str("ok: cone ")?;
                            write_u64(o, u64::from(id))?;
                            write_all(o, &[" installed (", material.name(), ", serial ", serial, "); cone counters start at zero;"])?;
                            match bore_um {
                                Some(b) => kv_fixed(o, "baseline_bore_mm", b as i64, 3),
                                None => o.write_str(" no baseline: the nominal 26.000 mm is assumed until `measure --baseline`"),
                            }?;
                            o.write_str("\r\n")
                        });
                }
                Err(e) => self.err(&e),
            },
            Command::Measure { bore_um, baseline } => self.measure(ctrl, bore_um, baseline, now_ms),
            Command::Measurements { json } => {
                self.defer(Report::Measurements(measurements_view(ctrl)), json)
            }
            Command::CalibrateTare => match ctrl.calibrate_tare() {
                Ok(c) => {
                    self.audit(
                        ctrl,
                        action::CALIBRATE_TARE,
                        now_ms,
                        &c.offset_counts.to_le_bytes(),
                    );
                    self.reply(|o| {
                        o.write_str("ok: tare offset_counts=")?;
                        write_i64(o, i64::from(c.offset_counts))?;
                        o.write_str("\r\n")
                    });
                }
                Err(e) => self.err(&e),
            },
            Command::CalibrateSpan { force_mn } => {
                match ctrl.calibrate_span(force_mn.min(i32::MAX as u32) as i32) {
                    Ok(c) => {
                        self.audit(
                            ctrl,
                            action::CALIBRATE_SPAN,
                            now_ms,
                            &force_mn.to_le_bytes(),
                        );
                        self.reply(|o| {
                            o.write_str("ok: span set, mn_per_count_q32=")?;
                            write_i64(o, c.mn_per_count_q32)?;
                            o.write_str("\r\n")
                        });
                    }
                    Err(e) => self.err(&e),
                }
            }
            Command::Maint { pin } => {
                // The record now; the hash in `finish`, without the controller.
                let d = &mut self.deferred;
                d.login = true;
                d.login_pin.clear();
                let _ = d.login_pin.push_str(pin);
                let rec = Self::pin_record(ctrl);
                d.login_has_rec = rec.is_some();
                if let Some(r) = rec {
                    d.login_rec = r.to_bytes();
                }
                return 0;
            }
            Command::MaintExit => {
                self.auth.exit();
                ctrl.set_maintenance_mode(false);
                self.ok(&"maintenance mode ended");
            }
            Command::PinSet { pin } => {
                // The hash (milliseconds of SHA-256) in `finish`, the record's store in
                // `store`: the controller is not held across the hash.
                let d = &mut self.deferred;
                d.pin_set = true;
                d.login_pin.clear();
                let _ = d.login_pin.push_str(pin);
            }
        }
        0
    }

    /// `help`: every command (aligned: usage, then what it does), or those of one
    /// word (`help calibrate`: both of its forms).
    fn help(&mut self, topic: Option<&str>, json: bool) {
        let shown = |c: &&super::parse::CommandHelp| topic.is_none_or(|t| c.word() == t);
        if json {
            // Through the reports' JSON writer (`JsonFields`), as `version --json`.
            let n = COMMANDS.iter().filter(shown).count();
            self.reply(|o| {
                let mut j = JsonFields::new(o)?;
                j.strings(
                    "commands",
                    &mut COMMANDS.iter().filter(shown).map(|c| c.usage),
                )?;
                j.records("help", n, &mut |i, x| {
                    let Some(c) = COMMANDS.iter().filter(shown).nth(i) else {
                        return Ok(());
                    };
                    x.str("command", c.word())?;
                    x.str("usage", c.usage)?;
                    x.str("what", c.what)
                })?;
                j.finish()?;
                o.write_str("\r\n")
            });
        } else {
            let width = COMMANDS
                .iter()
                .filter(shown)
                .map(|c| c.usage.len())
                .max()
                .unwrap_or(0);
            self.reply(|o| {
                for c in COMMANDS.iter().filter(shown) {
                    o.write_str(c.usage)?;
                    for _ in c.usage.len()..width {
                        o.write_str(" ")?;
                    }
                    write_all(o, &["  ", c.what, "\r\n"])?;
                }
                o.write_str(
                    "(maint: needs `maint <pin>`, and all but undock a machine at rest)\r\n",
                )
            });
        }
    }

    /// `version`: the running image (its header's version; the build's without one),
    /// `(test key)` when the built-in key is the test key, the image it replaced, a
    /// rollback (issue 21), and whether it runs on trial (issue 31: `trial=yes|failed`,
    /// then what to do, on a line of its own), and the unit's serial (issue 35: `unit=`,
    /// `none` when the host gave none). Fields added to 927460b's reply, none renamed:
    /// the text's first two words and the JSON's `name` and `version` are as they were.
    #[inline(never)]
    fn version(&mut self, r: &crate::update::ImageReport, json: bool) {
        use super::update::version_text;
        let (mut a, mut b, mut c) = (
            [0u8; VERSION_TEXT_MAX],
            [0u8; VERSION_TEXT_MAX],
            [0u8; VERSION_TEXT_MAX],
        );
        let v = running_text(r, &mut a);
        let previous = version_text(r.previous, &mut b);
        let n = usize::from(self.term.unit_len).min(UNIT_MAX);
        let unit_bytes = self.term.unit;
        let unit = core::str::from_utf8(unit_bytes.get(..n).unwrap_or(&[])).unwrap_or("");
        let rolled = match (r.rolled_back, r.rolled_back_version) {
            (false, _) => "no",
            (true, None) => "yes",
            (true, Some(x)) => version_text(Some(x), &mut c),
        };
        if json {
            self.report(true, &mut |f| {
                f.str("name", "docking-controller")?;
                f.str("version", v)?;
                f.bool("test_key", r.test_key)?;
                match r.previous {
                    Some(_) => f.str("previous", previous)?,
                    None => f.none("previous")?,
                };
                f.bool("rolled_back", r.rolled_back)?;
                match (r.rolled_back, r.rolled_back_version) {
                    (true, Some(_)) => f.str("rolled_back_version", rolled)?,
                    _ => f.none("rolled_back_version")?,
                };
                f.str("trial", r.trial.word())?;
                match r.trial.advice() {
                    Some(a) => f.str("trial_advice", a)?,
                    None => f.none("trial_advice")?,
                };
                match unit {
                    "" => f.none("unit"),
                    u => f.str("unit", u),
                }
            });
        } else {
            let key = if r.test_key { " (test key)" } else { "" };
            self.reply(|o| {
                write_all(
                    o,
                    &[
                        "docking-controller ",
                        v,
                        key,
                        " previous=",
                        previous,
                        " rolled_back=",
                        rolled,
                        " trial=",
                        r.trial.word(),
                        " unit=",
                        if unit.is_empty() { "none" } else { unit },
                        "\r\n",
                    ],
                )?;
                match r.trial.advice() {
                    Some(a) => write_all(o, &["  ", a, "\r\n"]),
                    None => Ok(()),
                }
            });
        }
    }

    /// Leave `report` for [`Self::finish`] (out of line: one copy of the move).
    #[inline(never)]
    fn defer(&mut self, report: Report, json: bool) {
        self.deferred.report = report;
        self.deferred.report_json = json;
    }

    /// A report: `fields` written once, rendered as text or as one JSON line.
    fn report(&mut self, json: bool, fields: &mut dyn FnMut(&mut dyn Fields) -> fmt::Result) {
        self.report_as(json, false, fields);
    }

    /// [`Self::report`]; `grouped`: its text in topics, for a person (echo on).
    fn report_as(
        &mut self,
        json: bool,
        grouped: bool,
        fields: &mut dyn FnMut(&mut dyn Fields) -> fmt::Result,
    ) {
        self.reply(|o| {
            if json {
                let mut j = JsonFields::new(o)?;
                fields(&mut j)?;
                j.finish()?;
                o.write_str("\r\n")
            } else {
                let mut t = if grouped {
                    TextFields::grouped(o)
                } else {
                    TextFields::new(o)
                };
                fields(&mut t)?;
                t.finish()
            }
        });
    }

    /// `status` and `wear` as a person reads them with echo on: a topic a line (issue
    /// 35); a script's (`echo off`) the `key=value` line of docs/console.md.
    fn render_status(&mut self, v: &StatusView, json: bool) {
        self.report_as(json, !self.term.quiet, &mut |f| status_fields(f, v));
    }

    fn render_wear(&mut self, v: &WearView, json: bool) {
        self.report_as(json, !self.term.quiet, &mut |f| wear_fields(f, v));
    }

    fn render_history(&mut self, entries: &HistoryEntries, sig: &HistorySig, json: bool) {
        if !json && entries.is_empty() {
            self.reply(|o| o.write_str("no completed cycles recorded\r\n"));
            return;
        }
        self.report(json, &mut |f| history_fields(f, entries, sig));
    }

    fn render_faults(&mut self, v: &FaultsView, json: bool) {
        self.report(json, &mut |f| faults_fields(f, v));
    }

    fn measure(&mut self, ctrl: &mut dyn Machine, bore_um: u32, baseline: bool, now_ms: u64) {
        let m = match ctrl.add_measurement(bore_um, baseline) {
            Ok(m) => m,
            Err(e) => {
                self.err(&e);
                return;
            }
        };
        let detail = MeasureDetail {
            bore_um: bore_um.into(),
            baseline: u8::from(baseline),
        };
        self.audit(ctrl, action::MEASURE, now_ms, detail.as_bytes());
        if baseline {
            self.reply(|o| {
                o.write_str("ok: baseline")?;
                kv_fixed(o, "bore_mm", bore_um as i64, 3)?;
                kv(o, "cone")?;
                write_u64(o, u64::from(m.cone_id))?;
                o.write_str(" (its wear is measured from it)\r\n")
            });
            return;
        }
        let base = ctrl.baseline_or_nominal();
        let assumed = ctrl.odometer().cone().baseline().is_none();
        let est = ctrl.wear_estimate();
        let below = m.wear_nm(base) < 0;
        self.reply(|o| {
            o.write_str("ok:")?;
            kv_fixed(o, "bore_mm", bore_um as i64, 3)?;
            kv(o, "cone_cycle")?;
            write_u64(o, u64::from(m.cone_cycle))?;
            kv_fixed(o, "measured_wear_mm", m.wear_nm(base) as i64, 6)?;
            kv_fixed(o, "model_wear_mm", m.model_nm as i64, 6)?;
            kv_fixed(o, "wear_estimate_mm", est.wear_nm as i64, 6)?;
            kv_fixed(o, "estimate_low_mm", est.low_nm as i64, 6)?;
            kv_fixed(o, "estimate_high_mm", est.high_nm as i64, 6)?;
            kv(o, "remaining_estimate_cycles")?;
            write_u64(o, u64::from(est.remaining_cycles))?;
            kv(o, "remaining_estimate_low_cycles")?;
            write_u64(o, u64::from(est.remaining_low_cycles))?;
            kv(o, "remaining_estimate_high_cycles")?;
            write_u64(o, u64::from(est.remaining_high_cycles))?;
            kv_fixed(o, "baseline_bore_mm", base as i64, 3)?;
            if assumed {
                o.write_str(
                    " baseline_assumed=yes (nominal 26.000 mm: measure --baseline on a new cone)",
                )?;
            }
            if below {
                // A worn bore only grows: a smaller one is a misread or a wrong baseline.
                o.write_str(
                    " below_baseline=yes (the bore reads smaller than the cone's baseline: measure again, or check the baseline)",
                )?;
            }
            o.write_str("\r\n")
        });
    }

    fn render_measurements(&mut self, v: &MeasurementsView, json: bool) {
        self.report(json, &mut |f| measurements_fields(f, v));
    }
}

/// What a brown-out reset level means.
fn bor_text(level: u8) -> &'static str {
    match level {
        3 => "2.70 V",
        2 => "2.40 V",
        1 => "2.10 V",
        _ => "off: program it at rest with `bor set` (maintenance)",
    }
}
