//! # The server: framer, request handling and statistics in one

use super::framer::RtuFramer;
use super::pdu::{process, Outcome, Session};
use super::settings::ModbusSettings;
use super::MAX_FRAME;
use crate::machine::Machine;

/// The server's counters since boot (saturating).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ModbusStats {
    /// Frames with a good CRC for this unit or broadcast.
    pub frames_ok: u32,
    /// Frames of 4 bytes or more with a wrong CRC (no reply).
    pub crc_errors: u32,
    /// Frames the framer discarded: a silence over t1.5 inside, over 256 bytes, under 4
    /// bytes, a line error.
    pub framing_errors: u32,
    /// Complete frames dropped because the next began before they were polled.
    pub overruns: u32,
    /// Good frames for other units (ignored).
    pub other_unit: u32,
    /// Replies sent, exceptions included.
    pub replies: u32,
    /// Exception replies sent.
    pub exceptions: u32,
    /// Commands passed to the controller.
    pub commands: u32,
}

impl ModbusStats {
    /// Every counter at zero (a `const`, for the servers built in statics).
    pub const ZERO: Self = Self {
        frames_ok: 0,
        crc_errors: 0,
        framing_errors: 0,
        overruns: 0,
        other_unit: 0,
        replies: 0,
        exceptions: 0,
        commands: 0,
    };
}

/// The Modbus RTU server: settings, framer, reply buffer, counters, the last command
/// (616 bytes on the board).
///
/// Held in a `static` built by the `const` [`Server::new`], its initial image lands in
/// `.data` (616 bytes of flash copied to RAM at reset); built at run time in `init`, it
/// would be `.bss`.
#[derive(Clone, Debug)]
pub struct Server {
    settings: ModbusSettings,
    framer: RtuFramer,
    reply: [u8; MAX_FRAME],
    stats: ModbusStats,
    session: Session,
}

impl Server {
    /// A server with `settings` (invalid ones: [`ModbusSettings::DEFAULT`]).
    pub const fn new(settings: ModbusSettings) -> Self {
        let settings = if settings.is_valid() {
            settings
        } else {
            ModbusSettings::DEFAULT
        };
        Self {
            settings,
            framer: RtuFramer::new(&settings),
            reply: [0; MAX_FRAME],
            stats: ModbusStats::ZERO,
            session: Session::NEW,
        }
    }

    /// A server with no settings yet, every byte zero: a static holding it is in
    /// `.bss`, not 616 bytes of `.data` copied from flash (issue 20). It answers nothing
    /// sensible until [`Self::set_settings`] gives it valid settings; the board does at
    /// the start of its idle loop.
    pub const fn unconfigured() -> Self {
        let none = ModbusSettings { unit: 0, baud: 0 };
        Self {
            settings: none,
            framer: RtuFramer::unconfigured(),
            reply: [0; MAX_FRAME],
            stats: ModbusStats::ZERO,
            session: Session::NEW,
        }
    }

    /// The settings in use.
    pub fn settings(&self) -> ModbusSettings {
        self.settings
    }

    /// Use `settings` from now on (a frame being received is dropped; the counters
    /// stay). `false`, and nothing changes, if they are not valid.
    pub fn set_settings(&mut self, settings: ModbusSettings) -> bool {
        if !settings.is_valid() {
            return false;
        }
        // The framer's counters move into the server's before it is replaced.
        self.stats = self.stats();
        self.settings = settings;
        self.framer = RtuFramer::new(&settings);
        true
    }

    /// A request is being received: [`Server::poll`] is due within t3.5 (a board
    /// that sleeps between control steps stays awake meanwhile).
    pub fn receiving(&self) -> bool {
        self.framer.receiving()
    }

    /// A byte received, stamped at the end of its stop bit (µs).
    #[inline(never)]
    pub fn on_byte(&mut self, byte: u8, t_us: u64) {
        self.framer.push(byte, t_us);
    }

    /// A character received with a line error (parity, framing, noise, overrun), µs.
    #[inline(never)]
    pub fn on_line_error(&mut self, t_us: u64) {
        self.framer.line_error(t_us);
    }

    /// Whether a request has ended at `now_us` (t3.5 of silence after it): the board
    /// takes the controller for [`Self::poll`] only then, one request at a time.
    pub fn request_due(&self, now_us: u64) -> bool {
        self.framer.due(now_us)
    }

    /// At `now_us`: if a request has ended (t3.5 of silence), handle it and return the
    /// reply to send (CRC included), if any. `unit_serial` is the unit's serial number
    /// (device identification object 0x80).
    #[inline(never)]
    pub fn poll(
        &mut self,
        now_us: u64,
        ctrl: &mut dyn Machine,
        unit_serial: &str,
    ) -> Option<&[u8]> {
        let frame = self.framer.poll(now_us)?;
        let outcome = process(
            frame,
            self.settings.unit,
            ctrl,
            unit_serial,
            &mut self.reply,
            &mut self.session,
        );
        let s = &mut self.stats;
        let inc = |c: &mut u32| *c = c.saturating_add(1);
        s.commands = self.session.accepted;
        let (n, exception) = match outcome {
            Outcome::Short => {
                inc(&mut s.framing_errors);
                return None;
            }
            Outcome::BadCrc => {
                inc(&mut s.crc_errors);
                return None;
            }
            Outcome::OtherUnit => {
                inc(&mut s.other_unit);
                return None;
            }
            Outcome::Handled(reply) => {
                inc(&mut s.frames_ok);
                reply?
            }
        };
        inc(&mut s.replies);
        if exception {
            inc(&mut s.exceptions);
        }
        self.reply.get(..n)
    }

    /// When the request [`Self::poll`] handles (or handled last) began on the line: its
    /// first character's start, µs — when the PLC issued it
    /// ([`crate::controller::Controller::issued_at`]).
    pub fn request_start_us(&self) -> u64 {
        self.framer.frame_start_us()
    }

    /// The last command written (its code, [`Command::code`](super::Command::code); 0 none since boot) and
    /// its result (0 accepted, else [`crate::controller::Refusal::code`]): input
    /// registers 8 and 9.
    pub fn last_command(&self) -> (u16, u16) {
        (self.session.last_command, self.session.last_result)
    }

    /// The counters since boot.
    pub fn stats(&self) -> ModbusStats {
        ModbusStats {
            framing_errors: self
                .stats
                .framing_errors
                .saturating_add(self.framer.framing_errors()),
            overruns: self.stats.overruns.saturating_add(self.framer.overruns()),
            ..self.stats
        }
    }
}
