//! # RTU framing
//!
//! A frame is the bytes between two silences of at least **t3.5** (3.5 character
//! times); a silence of more than **t1.5** inside a frame makes it bad, and a bad frame is
//! discarded whole. Above 19 200 baud the spec fixes t3.5 = 1750 µs and t1.5 = 750 µs.
//!
//! ```text
//!  baud      char (11 bit)   t1.5      t3.5
//!  9600      1146 µs         1719 µs   4011 µs
//!  19200      573 µs          860 µs   2006 µs
//!  38400      287 µs          750 µs   1750 µs
//!  57600      191 µs          750 µs   1750 µs
//!  115200      96 µs          750 µs   1750 µs
//! ```
//!
//! The silence before a byte stamped `t` is `t − one character time − the previous
//! byte's stamp` (stamps are taken at the end of each character); at [`RtuFramer::poll`]
//! it is `now − the last byte's stamp`. The framer also discards frames of more than
//! 256 bytes (and ignores bytes up to the next t3.5 silence), frames of fewer than 4
//! bytes, and frames holding a character received with a line error. See
//! [`RtuFramer`].

use super::{ModbusSettings, MAX_FRAME, MIN_FRAME};

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Rx {
    /// Between frames: nothing received since the last frame ended (it was delivered,
    /// discarded, or there was none).
    Idle,
    /// Receiving a frame (`len` bytes so far).
    Receiving,
    /// The frame went bad (a t1.5 gap, over 256 bytes, a line error): bytes are ignored
    /// until a t3.5 silence.
    Discarding,
}

/// Byte-at-a-time RTU frame receiver.
///
/// [`RtuFramer::push`] takes each byte with its time stamp (µs, at the end of the
/// character); [`RtuFramer::poll`] returns the frame once the line has been silent for
/// t3.5 after it, once. Both are O(1) (no copying: the bytes go straight into a fixed
/// 256-byte buffer), and neither panics on any input, time stamps going backwards
/// included (they count as no silence).
///
/// ```text
///  bytes   ▌▌▌▌▌▌▌▌   ≥ t3.5   ▌▌▌▌ >t1.5 ▌▌▌   ≥ t3.5   ▌▌▌ … (257th byte) …   ≥ t3.5
///          └ frame ┘ delivered  └─ bad: discarded ─┘      └── over 256: discarded ──┘
/// ```
///
/// * a silence ≥ t3.5 before a byte (or, at `poll`, since the last byte) ends the frame;
/// * a silence > t1.5 (and < t3.5) inside a frame makes it bad: it is discarded whole
///   at the next t3.5 silence, its later bytes ignored (counted in
///   [`RtuFramer::framing_errors`]);
/// * a 257th byte makes the frame bad, likewise; so do fewer than 4 bytes, and a
///   character reported with a line error ([`RtuFramer::line_error`]);
/// * a frame that was complete but not polled when the next one began is dropped
///   (counted in [`RtuFramer::overruns`]): a reply to it would now collide with the
///   traffic on the bus. Poll at least once per t3.5 after a request to answer them
///   all.
///
/// Until the first byte there is no previous character, so the first byte starts a
/// frame (the CRC catches one begun mid-frame).
#[derive(Clone, Debug)]
pub struct RtuFramer {
    buf: [u8; MAX_FRAME],
    len: usize,
    rx: Rx,
    last_us: Option<u64>,
    /// When the frame in progress (or the last) began: its first character's start.
    start_us: u64,
    char_us: u64,
    t1_5_us: u64,
    t3_5_us: u64,
    framing_errors: u32,
    overruns: u32,
}

impl RtuFramer {
    /// A framer for the timing of `settings`' baud rate.
    /// A framer with no timing yet, every byte zero (for [`Server::unconfigured`]).
    pub(super) const fn unconfigured() -> Self {
        Self {
            buf: [0; MAX_FRAME],
            len: 0,
            rx: Rx::Idle,
            last_us: None,
            start_us: 0,
            char_us: 0,
            t1_5_us: 0,
            t3_5_us: 0,
            framing_errors: 0,
            overruns: 0,
        }
    }

    pub const fn new(settings: &ModbusSettings) -> Self {
        Self {
            buf: [0; MAX_FRAME],
            len: 0,
            rx: Rx::Idle,
            last_us: None,
            start_us: 0,
            char_us: settings.char_us() as u64,
            t1_5_us: settings.t1_5_us() as u64,
            t3_5_us: settings.t3_5_us() as u64,
            framing_errors: 0,
            overruns: 0,
        }
    }

    /// The silence before a character stamped `t_us` (`None`: none received yet).
    fn silence_before(&self, t_us: u64) -> Option<u64> {
        self.last_us
            .map(|l| t_us.saturating_sub(l).saturating_sub(self.char_us))
    }

    /// The frame in progress ends (a t3.5 silence was seen at a new character).
    fn close(&mut self) {
        match self.rx {
            Rx::Idle => {}
            Rx::Receiving if self.len >= MIN_FRAME => {
                self.overruns = self.overruns.saturating_add(1);
            }
            Rx::Receiving | Rx::Discarding => {
                self.framing_errors = self.framing_errors.saturating_add(1);
            }
        }
        self.rx = Rx::Idle;
        self.len = 0;
    }

    /// A byte received, stamped `t_us` (µs, at the end of its stop bit).
    pub fn push(&mut self, byte: u8, t_us: u64) {
        let silence = self.silence_before(t_us);
        self.last_us = Some(t_us);
        if silence.is_none_or(|s| s >= self.t3_5_us) {
            self.close();
            self.rx = Rx::Receiving;
            self.start_us = t_us.saturating_sub(self.char_us);
        } else if silence.is_some_and(|s| s > self.t1_5_us) || self.rx == Rx::Idle {
            // A gap inside the frame, or a byte too soon after a frame already ended.
            self.rx = Rx::Discarding;
        }
        if self.rx != Rx::Receiving {
            return;
        }
        match self.buf.get_mut(self.len) {
            Some(slot) => {
                *slot = byte;
                self.len += 1;
            }
            None => self.rx = Rx::Discarding,
        }
    }

    /// A character received with a parity, framing, noise or overrun error, at `t_us`:
    /// the frame it belongs to is bad.
    pub fn line_error(&mut self, t_us: u64) {
        let silence = self.silence_before(t_us);
        self.last_us = Some(t_us);
        if silence.is_none_or(|s| s >= self.t3_5_us) {
            self.close();
        }
        self.rx = Rx::Discarding;
    }

    /// A frame is being received (or has ended and waits for [`RtuFramer::poll`]):
    /// poll again within t3.5.
    pub fn receiving(&self) -> bool {
        self.rx != Rx::Idle
    }

    /// Whether [`Self::poll`] has something to end at `now_us` (a frame, or a fragment
    /// to count as a framing error): the line has been silent for t3.5 after it.
    pub fn due(&self, now_us: u64) -> bool {
        self.rx != Rx::Idle
            && self
                .last_us
                .is_some_and(|last| now_us.saturating_sub(last) >= self.t3_5_us)
    }

    /// The frame, once the line has been silent for t3.5 after it (returned once).
    pub fn poll(&mut self, now_us: u64) -> Option<&[u8]> {
        let last = self.last_us?;
        if now_us.saturating_sub(last) < self.t3_5_us {
            return None;
        }
        let rx = core::mem::replace(&mut self.rx, Rx::Idle);
        match rx {
            Rx::Receiving if self.len >= MIN_FRAME => self.buf.get(..self.len),
            Rx::Receiving | Rx::Discarding => {
                self.framing_errors = self.framing_errors.saturating_add(1);
                None
            }
            Rx::Idle => None,
        }
    }

    /// When the frame [`Self::poll`] returned last (or the one in progress) began: its
    /// first character's start, µs (a request is issued then: issue 32).
    pub fn frame_start_us(&self) -> u64 {
        self.start_us
    }

    /// Frames discarded: a silence over t1.5 inside, over 256 bytes, under 4 bytes, a
    /// line error.
    pub fn framing_errors(&self) -> u32 {
        self.framing_errors
    }

    /// Complete frames dropped because the next began before they were polled.
    pub fn overruns(&self) -> u32 {
        self.overruns
    }
}
