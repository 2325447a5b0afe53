//! Line assembly from a raw serial byte stream.
//!
//! [`LineReader`] turns the bytes a terminal (picocom, screen) or a script sends into
//! whole lines, one byte per [`LineReader::push`] call. It guarantees:
//!
//! * **Terminators.** CR, LF and CRLF each end a line exactly once (the LF of a CRLF
//!   pair does not produce a second, empty line; a NUL between them is ignored).
//! * **Editing.** Backspace (0x08) and DEL (0x7F) erase the last character (a whole
//!   UTF-8 sequence, up to 4 bytes); on an empty line they do nothing. NUL is ignored.
//! * **Control characters.** Tab is kept (it separates tokens). Any other C0 control
//!   character, and any C1 control (U+0080..=U+009F) in the decoded line, makes the
//!   line invalid ([`LineError::ControlChar`]). An escape sequence (ESC `[` … final
//!   byte, ESC `O` x, or ESC x — what arrow and function keys send) is swallowed
//!   whole so that its tail is not taken as text; the line is still invalid.
//! * **UTF-8.** Bytes >= 0x80 are collected and the line is validated as UTF-8 at the
//!   terminator; invalid UTF-8 gives [`LineError::NotUtf8`].
//! * **Length.** A line longer than `N` bytes is discarded up to the next terminator
//!   and reported once, at that terminator, as [`LineError::TooLong`].
//!   A reported [`LineEvent::Line`] is never longer than `N` bytes and contains no CR,
//!   LF or control character other than tab.
//! * **Blank lines** (empty, or only spaces/tabs) produce no event.
//! * **Lost input.** [`LineReader::lost`] (the UART lost a byte: overrun, framing,
//!   noise, a full receive ring) spoils the line being assembled: it is discarded at
//!   its terminator as [`LineError::InputLost`], never executed with a byte missing
//!   (`history 100` must not run as `history 10`). A lost terminator merges two lines
//!   into one spoiled line.
//! * **Error precedence** for one line: `InputLost`, `TooLong`, then `ControlChar`, then
//!   `NotUtf8`.
//! * **Bounded work.** O(1) per byte, O(N) at a terminator; no allocation, no panic.

use core::fmt;

/// Bytes the controller reads from the console per control step; the rest of a flood
/// waits in the UART/ring buffer, so input never lengthens a control step.
///
/// 115200 8N1 delivers at most 11,520 bytes/s, so this budget keeps up with the line
/// at any control rate of 180 Hz or more.
pub const MAX_BYTES_PER_POLL: usize = 64;

/// Backspace.
pub(crate) const BS: u8 = 0x08;
pub(crate) const TAB: u8 = 0x09;
pub(crate) const LF: u8 = 0x0A;
pub(crate) const CR: u8 = 0x0D;
pub(crate) const ESC: u8 = 0x1B;
/// DEL: what most terminals send for the backspace key.
pub(crate) const DEL: u8 = 0x7F;

/// Why a line was rejected.
#[non_exhaustive]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum LineError {
    /// The line exceeded the reader's capacity and was discarded.
    TooLong,
    /// The line is not valid UTF-8.
    NotUtf8,
    /// The line contained a control character or an escape sequence.
    ControlChar,
    /// Bytes of the line were lost on the way in (receive error, full ring).
    InputLost,
}

impl LineError {
    /// Short one-line message (printable ASCII).
    pub const fn message(self) -> &'static str {
        match self {
            Self::TooLong => "line too long; discarded",
            Self::NotUtf8 => "line is not valid UTF-8; discarded",
            Self::ControlChar => "control character or escape sequence in line; discarded",
            Self::InputLost => "input lost (receive error or overrun); line discarded",
        }
    }
}

impl fmt::Display for LineError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.message())
    }
}

/// What a terminator produced.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LineEvent<'a> {
    /// A complete, valid, non-blank line (without its terminator).
    Line(&'a str),
    /// A rejected line.
    Error(LineError),
}

/// Escape-sequence state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Esc {
    /// Not in an escape sequence.
    None,
    /// After ESC.
    Start,
    /// After ESC `[`: parameter/intermediate bytes until a final byte 0x40..=0x7E.
    Csi,
    /// After ESC `O`: one more byte.
    Ss3,
}

/// Assembles lines of at most `N` bytes from a byte stream (see the module doc).
///
/// Its `Debug` output shows the state but not the text (which may hold a PIN).
#[derive(Clone)]
pub struct LineReader<const N: usize> {
    buf: heapless::Vec<u8, N>,
    /// The previous terminator was CR: swallow one LF.
    after_cr: bool,
    /// The current line overflowed; discard until the terminator.
    overflow: bool,
    /// The current line contained a control character.
    control: bool,
    /// Bytes of the current line were lost.
    lost: bool,
    esc: Esc,
    /// The buffer still holds the line returned by the previous call.
    returned: bool,
}

impl<const N: usize> fmt::Debug for LineReader<N> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("LineReader")
            .field("capacity", &N)
            .field("len", &self.buf.len())
            .field("overflow", &self.overflow)
            .field("control", &self.control)
            .finish_non_exhaustive()
    }
}

impl<const N: usize> Default for LineReader<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> LineReader<N> {
    /// An empty reader.
    pub const fn new() -> Self {
        Self {
            buf: heapless::Vec::new(),
            after_cr: false,
            overflow: false,
            control: false,
            lost: false,
            esc: Esc::None,
            returned: false,
        }
    }

    /// Maximum line length in bytes (`N`).
    pub const fn capacity(&self) -> usize {
        N
    }

    /// Discard any partial line and escape state.
    pub fn reset(&mut self) {
        self.buf.clear();
        self.after_cr = false;
        self.overflow = false;
        self.control = false;
        self.lost = false;
        self.esc = Esc::None;
        self.returned = false;
    }

    /// Whether a line is under way: a byte of it taken (kept, or a line being
    /// discarded: overlong, a byte lost) or an escape sequence begun, and not yet
    /// returned.
    pub fn under_way(&self) -> bool {
        !self.returned
            && (!self.buf.is_empty() || self.overflow || self.lost || self.esc != Esc::None)
    }

    /// The line typed so far (empty once a line was returned, or while an overlong
    /// one is being discarded): what an interactive terminal shows after its prompt.
    pub fn pending(&self) -> &[u8] {
        if self.returned || self.overflow {
            &[]
        } else {
            &self.buf
        }
    }

    /// Characters (not bytes: a UTF-8 sequence is one) in [`Self::pending`].
    pub fn pending_chars(&self) -> usize {
        self.pending().iter().filter(|&&b| b & 0xC0 != 0x80).count()
    }

    /// Start a new line holding `text` (a recalled line; cut to `N` bytes).
    pub fn replace_pending(&mut self, text: &[u8]) {
        self.reset();
        let n = text.len().min(N);
        let _ = self.buf.extend_from_slice(text.get(..n).unwrap_or(&[]));
    }

    /// A byte was lost here (the UART reported an error, or its ring was full): the
    /// line being assembled is spoiled.
    pub fn lost(&mut self) {
        if self.returned {
            self.buf.clear();
            self.returned = false;
        }
        self.lost = true;
        self.after_cr = false;
    }

    /// Feed one received byte; returns an event when it ends a line.
    pub fn push(&mut self, byte: u8) -> Option<LineEvent<'_>> {
        if self.returned {
            self.buf.clear();
            self.returned = false;
        }
        if byte == 0 {
            // NUL: ignored entirely (also between the CR and LF of a pair).
            return None;
        }
        let after_cr = core::mem::replace(&mut self.after_cr, false);
        if byte == LF && after_cr {
            return None;
        }
        if byte == CR || byte == LF {
            self.after_cr = byte == CR;
            return self.terminate();
        }
        if self.swallow_escape(byte) {
            return None;
        }
        match byte {
            BS | DEL => self.erase(),
            ESC => {
                self.control = true;
                self.esc = Esc::Start;
            }
            TAB => self.store(byte),
            0x01..=0x1F => self.control = true,
            _ => self.store(byte),
        }
        None
    }

    /// Escape-sequence handling; true when `byte` was consumed by a sequence.
    fn swallow_escape(&mut self, byte: u8) -> bool {
        match self.esc {
            Esc::None => false,
            Esc::Start => match byte {
                b'[' => {
                    self.esc = Esc::Csi;
                    true
                }
                b'O' => {
                    self.esc = Esc::Ss3;
                    true
                }
                0x20..=0x7E => {
                    self.esc = Esc::None;
                    true
                }
                _ => {
                    self.esc = Esc::None;
                    false
                }
            },
            Esc::Csi => match byte {
                0x20..=0x3F => true,
                0x40..=0x7E => {
                    self.esc = Esc::None;
                    true
                }
                _ => {
                    self.esc = Esc::None;
                    false
                }
            },
            Esc::Ss3 => {
                self.esc = Esc::None;
                (0x20..=0x7E).contains(&byte)
            }
        }
    }

    /// Append a text byte, or mark the line overflowed.
    fn store(&mut self, byte: u8) {
        if self.overflow {
            return;
        }
        if self.buf.push(byte).is_err() {
            self.overflow = true;
            self.buf.clear();
        }
    }

    /// Erase the last character (a whole UTF-8 sequence of up to 4 bytes).
    fn erase(&mut self) {
        if self.overflow {
            return;
        }
        for _ in 0..4 {
            match self.buf.pop() {
                Some(b) if b & 0xC0 == 0x80 => continue,
                _ => break,
            }
        }
    }

    /// End the current line and report it.
    fn terminate(&mut self) -> Option<LineEvent<'_>> {
        let overflow = core::mem::replace(&mut self.overflow, false);
        let control = core::mem::replace(&mut self.control, false);
        let lost = core::mem::replace(&mut self.lost, false);
        self.esc = Esc::None;
        // The buffer is cleared on the next push (the returned line borrows it).
        self.returned = true;
        if lost {
            return Some(LineEvent::Error(LineError::InputLost));
        }
        if overflow {
            return Some(LineEvent::Error(LineError::TooLong));
        }
        if control {
            return Some(LineEvent::Error(LineError::ControlChar));
        }
        match core::str::from_utf8(&self.buf) {
            Err(_) => Some(LineEvent::Error(LineError::NotUtf8)),
            // The C0 controls and DEL never reach the buffer (`push`): what is left to
            // find are the C1 controls, U+0080–U+009F, `C2 80`–`C2 9F` in UTF-8 (by
            // bytes, not chars: no decoding, issue 20).
            Ok(s)
                if s.as_bytes()
                    .windows(2)
                    .any(|w| matches!(w, [0xC2, 0x80..=0x9F])) =>
            {
                Some(LineEvent::Error(LineError::ControlChar))
            }
            Ok(s) if s.trim_matches([' ', '\t']).is_empty() => None,
            Ok(s) => Some(LineEvent::Line(s)),
        }
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::string::{String, ToString};
    use std::vec::Vec;

    #[derive(Debug, PartialEq)]
    enum Ev {
        L(String),
        E(LineError),
    }

    fn feed<const N: usize>(r: &mut LineReader<N>, bytes: &[u8]) -> Vec<Ev> {
        let mut out = Vec::new();
        for &b in bytes {
            match r.push(b) {
                Some(LineEvent::Line(s)) => out.push(Ev::L(s.to_string())),
                Some(LineEvent::Error(e)) => out.push(Ev::E(e)),
                None => {}
            }
        }
        out
    }

    #[test]
    fn a_line_that_lost_a_byte_was_executed() {
        let mut r = LineReader::<64>::new();
        assert_eq!(feed(&mut r, b"history 1"), []);
        r.lost(); // the UART dropped the "0"
        assert_eq!(
            feed(&mut r, b"0\r\nstatus\r\n"),
            [Ev::E(LineError::InputLost), Ev::L("status".to_string())]
        );
        // A lost terminator: the two lines it separated are one spoiled line.
        assert_eq!(feed(&mut r, b"wear"), []);
        r.lost();
        assert_eq!(feed(&mut r, b"faults\r\n"), [Ev::E(LineError::InputLost)]);
        // Lost between the CR and LF of a pair: the LF ends the (empty) spoiled line.
        assert_eq!(feed(&mut r, b"wear\r"), [Ev::L("wear".to_string())]);
        r.lost();
        assert_eq!(feed(&mut r, b"\n"), [Ev::E(LineError::InputLost)]);
    }

    /// Issue 32's second review: the board took the console for quiet whenever its
    /// receive ring was empty, which it is as soon as this reader has taken a line's
    /// first bytes; a clear's issue time then followed its last byte, not its first.
    /// The reader says a line is under way from its first byte to its end.
    #[test]
    fn a_line_under_way_from_its_first_byte_to_its_end() {
        let mut r = LineReader::<8>::new();
        assert!(!r.under_way());
        assert_eq!(feed(&mut r, b"cl"), []);
        assert!(r.under_way(), "bytes of a line taken");
        assert_eq!(feed(&mut r, b"ear\r"), [Ev::L("clear".into())]);
        assert!(!r.under_way(), "the line returned");
        // An overlong line being discarded, and a line that lost a byte: under way too.
        assert_eq!(feed(&mut r, b"123456789"), []);
        assert!(r.under_way());
        assert_eq!(feed(&mut r, b"\n"), [Ev::E(LineError::TooLong)]);
        assert!(!r.under_way());
        r.lost();
        assert!(r.under_way());
        // An escape sequence begun.
        let mut r = LineReader::<8>::new();
        assert_eq!(feed(&mut r, b"\x1b"), []);
        assert!(r.under_way());
    }

    #[test]
    fn crlf_is_one_terminator() {
        let mut r = LineReader::<16>::new();
        assert_eq!(
            feed(&mut r, b"a\r\nb\rc\n\r\n"),
            [Ev::L("a".into()), Ev::L("b".into()), Ev::L("c".into())]
        );
    }

    #[test]
    fn exactly_n_fits_n_plus_one_does_not() {
        let mut r = LineReader::<4>::new();
        assert_eq!(feed(&mut r, b"abcd\n"), [Ev::L("abcd".into())]);
        assert_eq!(feed(&mut r, b"abcde\n"), [Ev::E(LineError::TooLong)]);
    }

    #[test]
    fn backspace_erases_utf8_char() {
        let mut r = LineReader::<16>::new();
        assert_eq!(
            feed(&mut r, "aé\x7f\x08b\n".as_bytes()),
            [Ev::L("b".into())]
        );
    }

    #[test]
    fn c1_control_rejected() {
        let mut r = LineReader::<16>::new();
        assert_eq!(
            feed(&mut r, "a\u{9b}b\n".as_bytes()),
            [Ev::E(LineError::ControlChar)]
        );
    }
}
