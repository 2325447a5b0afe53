//! # Modbus RTU server for the vehicle's PLC
//!
//! The PLC reads the controller's status, counters and cone record, and commands dock,
//! undock, clear fault, stop and home, over RS-485 in Modbus RTU. This module is the
//! server side: a byte-at-a-time frame receiver ([`RtuFramer`]), the register map, and a
//! [`Server`] that turns a request frame into a reply frame. It is `no_std`, allocates
//! nothing, and never panics on input (every frame, any bytes, gets a reply or nothing).
//!
//! ## Serial line
//!
//! 8 data bits, even parity, 1 stop bit (**8E1**, fixed: 11 bits a character), at one of
//! 9600, 19 200 (default), 38 400, 57 600 or 115 200 baud; unit address 1–247 (default
//! 1). The board layer owns the UART; it timestamps every received byte (µs, at the end
//! of its stop bit — the receive interrupt) and hands it to [`Server::on_byte`], reports
//! a character with a parity, framing or overrun error to [`Server::on_line_error`], and
//! calls [`Server::poll`] often (every pass of its loop): a reply, if any, is returned
//! once the request has ended and is to be sent as it is (CRC included), with the
//! transceiver's driver enabled for exactly its bytes.
//!
//! ## Settings in flash
//!
//! [`ModbusSettings::to_bytes`] / [`ModbusSettings::from_bytes`], 6 bytes:
//!
//! ```text
//!  0        1          2                        6
//!  +--------+----------+------------------------+
//!  | unit u8| format u8| baud u32 (little-end.) |
//!  +--------+----------+------------------------+
//!  unit   1..=247
//!  format 0 = 8E1 (the only one defined; anything else is refused)
//!  baud   9600 | 19200 | 38400 | 57600 | 115200
//! ```
//!
//! A record that does not decode (wrong length, a value out of range) is refused whole:
//! the caller falls back to [`ModbusSettings::DEFAULT`].
//!
//! ## Framing (Modbus over serial line, §2.5.1.1)
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
//!
//! ## Requests
//!
//! A frame of 4 bytes or more is checked here first: its CRC over the **whole** frame
//! (a wrong CRC: no reply, counted), then the unit address (another unit: ignored; 0 is
//! broadcast: never a reply). Functions:
//!
//! | code | function | here |
//! |---|---|---|
//! | 0x01 | read coils | command coils, read 0 |
//! | 0x02 | read discrete inputs | the status bits |
//! | 0x03 | read holding registers | the command register, reads 0 |
//! | 0x04 | read input registers | the map below |
//! | 0x05 | write single coil | a command |
//! | 0x06 | write single register | a command |
//! | 0x0F | write multiple coils | a command |
//! | 0x10 | write multiple registers | a command |
//! | 0x2B / 0x0E | read device identification | below |
//!
//! Exceptions: **01** unknown function (or MEI type other than 0x0E); **02** an address
//! (range) outside the map, a write to a read-only address, an unknown device
//! identification object (individual access); **03** a quantity out of the spec's range
//! (1–2000 bits, 1–125 registers read; 1–1968 coils, 1–123 registers written), a byte
//! count that does not match, a frame of the wrong length for its function, a coil value
//! other than 0x0000/0xFF00, an unknown command code, more than one command at once, an
//! unknown read device id code; **01** (ILLEGAL FUNCTION) also for a command the
//! controller does not accept in its present state — the Modbus Application Protocol's
//! definition of 01 includes a server "in the wrong state to process a request of this
//! type" — with the reason in input register 9. The checks run in the spec's order:
//! function, quantity, address, value, then the action.
//!
//! Not 04 (SERVER DEVICE FAILURE): a dock refused because the machine is not READY is
//! not a failed device, and masters report 04 as one (a PLC may mark the node dead). Not
//! 06 (SERVER DEVICE BUSY): some masters retry BUSY by themselves, and a dock retried
//! until the machine is READY again would start a motion nobody asked for at that
//! moment. The PLC reads input register 9 (or the status word) to learn why.
//!
//! ## Register map
//!
//! Addresses are the PDU's (0-based; a PLC's "30001"/"40001"/"00001" numbering is the
//! address + 1 in its table). The map is stable: registers may be added, in reserved
//! addresses or at the end, never moved, rescaled or reused ([`MAP_VERSION`] counts
//! additions). Reserved addresses inside a block read 0, so a PLC can read a block in
//! one request; addresses past the end of a block are exception 02. 32-bit values are
//! two registers, **high word first** (at the lower address). Signed values are two's
//! complement `i16`, saturating at ±32 767 (±3276.7 N). Forces are rounded to the
//! nearest 0.1 N.
//!
//! **Input registers** (0x04), read-only, a consistent snapshot per request:
//!
//! | addr | name | unit, scaling | type |
//! |---|---|---|---|
//! | 0 | status word | bits below | u16 |
//! | 1 | sequencer state | code below | u16 |
//! | 2 | contact phase | 0 none, 1–4 | u16 |
//! | 3 | force | 0.1 N | i16 |
//! | 4 | force limit at the present depth | 0.1 N | i16 |
//! | 5 | axis position from home | 0.01 mm | i16 |
//! | 6 | active fault | fault code, 0xFFFF none | u16 |
//! | 7 | peak force since boot | 0.1 N | i16 |
//! | 8 | last command written here | command code (below), 0 none | u16 |
//! | 9 | its result | 0 accepted, else the refusal code (below) | u16 |
//! | 10 | maintenance mode at the console (map version 2) | 1 on: PLC motion refused, READY low; 0 off | u16 |
//! | 11–15 | reserved | | |
//! | 16–17 | lifetime cycles | cycles | u32 |
//! | 18–19 | cone cycles | cycles | u32 |
//! | 20–21 | cone wear (odometer model) | nm | u32 |
//! | 22 | cone wear (odometer model) | µm, rounded down | u16 |
//! | 23 | wear level (the one acted on) | 0 ok, 1 warning, 2 limit | u16 |
//! | 24–25 | remaining cone life | nominal cycles | u32 |
//! | 26 | wear of the limit | 0.1 % | u16 |
//! | 27 | wear limit | µm | u16 |
//! | 28–29 | overload events, lifetime | events | u32 |
//! | 30–31 | faults, lifetime | faults | u32 |
//! | 32–33 | faults since boot | faults | u32 |
//! | 34–35 | overload trips since boot | trips | u32 |
//! | 36–39 | reserved | | |
//! | 40 | last fault | fault code, 0xFFFF none | u16 |
//! | 41–42 | last fault's cycle | cycle number (0: before the first) | u32 |
//! | 43 | last fault's peak force | 0.1 N | i16 |
//! | 44 | last fault's contact phase | 0 none, 1–4 | u16 |
//! | 45–47 | reserved | | |
//! | 48 | cone id | installation number (1 = first) | u16 |
//! | 49 | cone material | 0 ZQSn5-2, 1 QSn6-6-3, 2 CF-PEEK | u16 |
//! | 50–59 | cone serial | ASCII, 2 chars a register (first in the high byte), NUL padded, 20 chars | 10 × u16 |
//! | 60–63 | reserved | | |
//! | 64 | firmware major | | u16 |
//! | 65 | firmware minor | | u16 |
//! | 66 | firmware patch | | u16 |
//! | 67 | register map version | [`MAP_VERSION`] | u16 |
//!
//! Status word (and **discrete inputs** 0–11, 0x02, the same bits): 0 READY, 1 MATED,
//! 2 moving, 3 FAULT, 4 force warning, 5 MAINTENANCE (cone past its warning level),
//! 6 load cell calibrated, 7 E-STOP open, 8 DOCK input asserted (as filtered), 9 cone
//! worn out (wear level limit: docking refused), 10 docking (under way or mated),
//! 11 maintenance mode at the console (map version 2).
//!
//! Sequencer state codes: 0 power-up, 1 homing, 2 locking, 3 idle, 4 pre-align,
//! 5 releasing, 6 inserting, 7 holding, 8 extracting, 9 returning, 10 backing off,
//! 11 faulted, 12 recovering.
//!
//! Fault codes ([`crate::sequencer::FaultKind::code`]): 0 overload, 1 sensor
//! disconnected, 2 sensor saturated, 3 sensor stuck, 4 implausible tare, 5 axis stall,
//! 6 overtravel, 7 lock not released, 8 lock not locked, 9 switch conflict, 10 I/O,
//! 11 tension, 12 storage, 13 emergency stop, 14 stopped, 15 hold force, 16 unseen stop
//! (the stop latch held the driver off for a stop never reported).
//!
//! **Coils** (0x01 / 0x05 / 0x0F), momentary commands, read back 0:
//!
//! | addr | command | accepted when (else exception 01, the reason in input register 9) |
//! |---|---|---|
//! | 0 | dock (and hold until undock) | READY: idle, homed and locked, calibrated, cone not worn out, E-STOP closed |
//! | 1 | undock | a docking under way or mated |
//! | 2 | clear fault (starts the recovery to home) | a latched fault, E-STOP closed |
//! | 3 | stop (latches the `stopped` fault) | always |
//! | 4 | home (after a reset) | power-up, E-STOP closed |
//!
//! **Holding register** (0x03 / 0x06 / 0x10) 0: command register, write 1 dock, 2 undock,
//! 3 clear fault, 4 stop, 5 home (the coil's address + 1); reads 0.
//!
//! The rules are the controller's own, the same for every source
//! ([`Controller::command`]); an accepted command is acted on in the next control step.
//! Input registers 8–9 hold the last command written to this server and its result: 0
//! accepted, or the refusal's code ([`crate::controller::Refusal::code`]: 1 E-STOP open,
//! 2 not idle, 3 not calibrated, 4 cone worn out, 5 not homed and locked, 6 nothing to
//! undock, 7 no fault to clear, 8 already homed, 9 maintenance mode: a technician is at
//! the console, and every command but stop is refused to the PLC).
//!
//! Writing 0 (a coil off, register value 0) is a no-op answered normally. One command a
//! request: a multiple write with more than one command is exception 03 and runs none
//! of them — except stop, which runs whenever it is written (a stop is never refused;
//! the exception still tells the PLC the rest did not run). **Broadcast** (unit 0): stop
//! runs on every unit; dock, undock, clear fault and home move the machine and are
//! **unicast only** (a broadcast one is ignored). Reads are never broadcast.
//!
//! ## Device identification (0x2B / MEI 0x0E)
//!
//! Conformity level 0x83 (basic, regular and extended objects; stream and individual
//! access). Read device id codes 1 (basic stream: objects 0–2), 2 (regular stream:
//! 0–0x7F), 3 (extended stream: all), 4 (one object). Objects: 0 VendorName
//! [`VENDOR_NAME`], 1 ProductCode [`PRODUCT_CODE`], 2 MajorMinorRevision (the firmware
//! version), 4 ProductName [`PRODUCT_NAME`], 5 ModelName [`MODEL_NAME`], 0x80 the unit's
//! serial number (as passed to [`Server::poll`], at most [`SERIAL_OBJECT_MAX`] bytes). A
//! stream that does not fit one reply sets "more follows" and the next object id; a
//! stream request for an object id that does not exist restarts at object 0 (the spec's
//! rule); an individual request for one is exception 02; any other read device id code
//! is exception 03.
//!
//! ## rmodbus, and what is done by hand
//!
//! The PDU parsing and the replies of functions 0x01–0x06, 0x0F and 0x10 go through the
//! `rmodbus` crate (0.13, `no_std`, `heapless` vectors; its "external" read/write API,
//! so no register image is kept). By hand, before a frame reaches it: the CRC over the
//! whole frame (rmodbus answers an unknown function before checking the CRC, and checks
//! the CRC only over the length it expects), the frame length of each function and the
//! quantity and byte-count limits (rmodbus accepts a quantity of 0, does not match the
//! byte count of 0x0F/0x10 to the quantity, computes `7 + byte count` in a `u8` and
//! indexes the frame by the byte count), unknown and ≥ 0x80 function codes (rmodbus
//! computes `function + 0x80` in a `u8`), and function 0x2B, which rmodbus does not
//! implement.

use heapless::Vec;
use rmodbus::server::{ModbusFrame, Read, Write};
use rmodbus::{ErrorKind, ModbusProto};

use crate::controller::{Bsp, Controller, Source};
use crate::odometer::WearLevel;
use crate::sequencer::{Request, State};

/// Largest RTU frame (address, PDU, CRC), bytes.
pub const MAX_FRAME: usize = 256;
/// Shortest frame that can be a request (address, function, CRC), bytes.
pub const MIN_FRAME: usize = 4;
/// The broadcast address.
pub const BROADCAST: u8 = 0;
/// Bits a character on the line: start, 8 data, parity, stop (8E1).
pub const BITS_PER_CHAR: u32 = 11;
/// The baud rates a unit may be set to.
pub const BAUD_RATES: [u32; 5] = [9_600, 19_200, 38_400, 57_600, 115_200];

/// The Modbus CRC-16 (polynomial 0xA001 reflected, initial 0xFFFF), sent low byte
/// first.
const CRC16: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_MODBUS);

/// CRC-16/MODBUS of `bytes` (sent on the line low byte first).
pub fn crc16(bytes: &[u8]) -> u16 {
    CRC16.checksum(bytes)
}

/// Exception codes.
pub mod exception {
    /// The function (or MEI type) is not supported, **or** the command is one the
    /// controller does not accept in its present state (the specification's "server in
    /// the wrong state"; the reason is in input register 9).
    pub const ILLEGAL_FUNCTION: u8 = 0x01;
    /// An address (range) outside the map, or not writable.
    pub const ILLEGAL_DATA_ADDRESS: u8 = 0x02;
    /// A quantity, byte count, length or value that is not allowed.
    pub const ILLEGAL_DATA_VALUE: u8 = 0x03;
}

// ---------------------------------------------------------------------------------
// Settings
// ---------------------------------------------------------------------------------

/// The unit's serial-line settings (stored by a technician; see the module doc for the
/// record). The character format is fixed at 8E1.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct ModbusSettings {
    /// Unit (server) address, 1–247.
    pub unit: u8,
    /// Baud rate, one of [`BAUD_RATES`].
    pub baud: u32,
}

impl Default for ModbusSettings {
    fn default() -> Self {
        Self::DEFAULT
    }
}

impl ModbusSettings {
    /// Unit 1 at 19 200 baud, 8E1 (the Modbus serial line default).
    pub const DEFAULT: Self = Self {
        unit: 1,
        baud: 19_200,
    };
    /// Bytes in the record.
    pub const LEN: usize = 6;
    /// The record's format byte for 8E1 (the only one defined).
    pub const FORMAT_8E1: u8 = 0;

    /// Validated settings.
    pub const fn new(unit: u8, baud: u32) -> Option<Self> {
        let s = Self { unit, baud };
        if s.is_valid() {
            Some(s)
        } else {
            None
        }
    }

    /// Unit 1–247 and a baud rate of [`BAUD_RATES`].
    pub const fn is_valid(&self) -> bool {
        matches!(self.unit, 1..=247)
            && matches!(self.baud, 9_600 | 19_200 | 38_400 | 57_600 | 115_200)
    }

    /// The record (see the module doc).
    pub fn to_bytes(&self) -> [u8; Self::LEN] {
        let [b0, b1, b2, b3] = self.baud.to_le_bytes();
        [self.unit, Self::FORMAT_8E1, b0, b1, b2, b3]
    }

    /// From a record; `None` unless it is exactly a valid one.
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let [unit, format, b0, b1, b2, b3]: [u8; Self::LEN] = b.try_into().ok()?;
        if format != Self::FORMAT_8E1 {
            return None;
        }
        Self::new(unit, u32::from_le_bytes([b0, b1, b2, b3]))
    }

    /// The settings `ctrl`'s odometer log holds (record kind
    /// [`crate::odometer::kind::MODBUS`]), else [`Self::DEFAULT`]: what the board opens
    /// the line with at boot, and what the console's `modbus` shows.
    pub fn stored<B: Bsp>(ctrl: &mut Controller<B>) -> Self {
        let mut buf = [0u8; Self::LEN];
        ctrl.load_record(crate::odometer::kind::MODBUS, &mut buf)
            .and_then(|n| buf.get(..n))
            .and_then(Self::from_bytes)
            .unwrap_or(Self::DEFAULT)
    }

    /// One character (11 bits) on the line, µs, rounded up.
    pub const fn char_us(&self) -> u32 {
        (BITS_PER_CHAR * 1_000_000).div_ceil(nonzero(self.baud))
    }

    /// The longest silence allowed inside a frame (1.5 characters; 750 µs above
    /// 19 200 baud), µs, rounded up.
    pub const fn t1_5_us(&self) -> u32 {
        if self.baud > 19_200 {
            750
        } else {
            (BITS_PER_CHAR * 1_500_000).div_ceil(nonzero(self.baud))
        }
    }

    /// The silence that ends a frame (3.5 characters; 1750 µs above 19 200 baud), µs,
    /// rounded up.
    pub const fn t3_5_us(&self) -> u32 {
        if self.baud > 19_200 {
            1_750
        } else {
            (BITS_PER_CHAR * 3_500_000).div_ceil(nonzero(self.baud))
        }
    }
}

const fn nonzero(x: u32) -> u32 {
    if x == 0 {
        1
    } else {
        x
    }
}

// ---------------------------------------------------------------------------------
// Framer
// ---------------------------------------------------------------------------------

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Rx {
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
    char_us: u64,
    t1_5_us: u64,
    t3_5_us: u64,
    framing_errors: u32,
    overruns: u32,
}

impl RtuFramer {
    /// A framer for the timing of `settings`' baud rate.
    pub const fn new(settings: &ModbusSettings) -> Self {
        Self {
            buf: [0; MAX_FRAME],
            len: 0,
            rx: Rx::Idle,
            last_us: None,
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

// ---------------------------------------------------------------------------------
// Register map
// ---------------------------------------------------------------------------------

/// The register map's version: bumped when registers are added (never moved or
/// reused).
pub const MAP_VERSION: u16 = 2;

/// Input register addresses (function 0x04); see the module doc for units.
pub mod ir {
    /// Status word ([`super::status`] bits).
    pub const STATUS: u16 = 0;
    /// Sequencer state code ([`super::state_code`]).
    pub const STATE: u16 = 1;
    /// Contact phase, 0 none, 1–4.
    pub const PHASE: u16 = 2;
    /// Force, 0.1 N, i16.
    pub const FORCE: u16 = 3;
    /// Force limit at the present depth, 0.1 N, i16.
    pub const FORCE_LIMIT: u16 = 4;
    /// Axis position from home, 0.01 mm, i16.
    pub const POSITION: u16 = 5;
    /// Active fault code, 0xFFFF none.
    pub const ACTIVE_FAULT: u16 = 6;
    /// Peak force since boot, 0.1 N, i16.
    pub const PEAK_FORCE: u16 = 7;
    /// The last command written to this server (its code, [`super::Command::code`]),
    /// 0 none since boot.
    pub const LAST_COMMAND: u16 = 8;
    /// Its result: 0 accepted, else why it was refused
    /// ([`crate::controller::Refusal::code`]).
    pub const LAST_COMMAND_RESULT: u16 = 9;
    /// Maintenance mode at the console: 1 on (PLC motion refused), 0 off.
    pub const MAINTENANCE_MODE: u16 = 10;
    /// Lifetime cycles, u32 (high word first).
    pub const LIFETIME_CYCLES: u16 = 16;
    /// Cone cycles, u32.
    pub const CONE_CYCLES: u16 = 18;
    /// Cone wear (the odometer's model), nm, u32.
    pub const WEAR_NM: u16 = 20;
    /// Cone wear (the odometer's model), µm (rounded down), u16.
    pub const WEAR_UM: u16 = 22;
    /// Wear level acted on: 0 ok, 1 warning, 2 limit.
    pub const WEAR_LEVEL: u16 = 23;
    /// Remaining cone life, nominal cycles, u32.
    pub const REMAINING_CYCLES: u16 = 24;
    /// Wear as a share of the limit, 0.1 %.
    pub const WEAR_PERMILLE: u16 = 26;
    /// Wear limit, µm.
    pub const WEAR_LIMIT_UM: u16 = 27;
    /// Overload events over the machine's life, u32.
    pub const OVERLOAD_EVENTS: u16 = 28;
    /// Faults over the machine's life, u32.
    pub const FAULTS_LIFETIME: u16 = 30;
    /// Faults latched since boot, u32.
    pub const FAULTS_SINCE_BOOT: u16 = 32;
    /// Overload trips since boot, u32.
    pub const OVERLOAD_TRIPS_SINCE_BOOT: u16 = 34;
    /// Last fault's code, 0xFFFF none.
    pub const LAST_FAULT_CODE: u16 = 40;
    /// Last fault's cycle number, u32.
    pub const LAST_FAULT_CYCLE: u16 = 41;
    /// Last fault's peak force, 0.1 N, i16.
    pub const LAST_FAULT_PEAK_FORCE: u16 = 43;
    /// Last fault's contact phase, 0 none, 1–4.
    pub const LAST_FAULT_PHASE: u16 = 44;
    /// Cone id (installation number).
    pub const CONE_ID: u16 = 48;
    /// Cone material code.
    pub const CONE_MATERIAL: u16 = 49;
    /// Cone serial, [`CONE_SERIAL_REGS`] registers of ASCII.
    pub const CONE_SERIAL: u16 = 50;
    /// Registers of the cone serial (2 characters each).
    pub const CONE_SERIAL_REGS: u16 = 10;
    /// Firmware version: major.
    pub const FW_MAJOR: u16 = 64;
    /// Firmware version: minor.
    pub const FW_MINOR: u16 = 65;
    /// Firmware version: patch.
    pub const FW_PATCH: u16 = 66;
    /// [`super::MAP_VERSION`].
    pub const MAP_VERSION: u16 = 67;
    /// Input registers in the map (addresses 0..COUNT).
    pub const COUNT: u16 = 68;
}

/// Status word bits (input register 0), and the discrete inputs (bit n = input n).
pub mod status {
    /// READY: idle, homed, locked, calibrated, cone not worn out, E-STOP closed.
    pub const READY: u16 = 1 << 0;
    /// MATED: connectors engaged, force in the hold envelope.
    pub const MATED: u16 = 1 << 1;
    /// The propulsion may be moving.
    pub const MOVING: u16 = 1 << 2;
    /// FAULT: a latched fault or the overload back-off.
    pub const FAULT: u16 = 1 << 3;
    /// Force above the warning level.
    pub const WARNING: u16 = 1 << 4;
    /// MAINTENANCE: the cone past its warning level.
    pub const MAINTENANCE: u16 = 1 << 5;
    /// A technician's load-cell calibration is stored.
    pub const CALIBRATED: u16 = 1 << 6;
    /// The E-STOP input is open.
    pub const ESTOP_OPEN: u16 = 1 << 7;
    /// The DOCK input is asserted (as filtered).
    pub const DOCK_INPUT: u16 = 1 << 8;
    /// The cone is worn out (docking refused until it is replaced).
    pub const WORN_OUT: u16 = 1 << 9;
    /// A docking is under way or mated.
    pub const DOCKING: u16 = 1 << 10;
    /// A technician has the machine in maintenance mode at the console: motion
    /// commands from the PLC are refused (refusal 9) and READY is low.
    pub const MAINTENANCE_MODE: u16 = 1 << 11;
    /// Discrete inputs in the map (the bits above).
    pub const COUNT: u16 = 12;
}

/// Commands (coil address = code − 1; holding register 0 value = code).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Command {
    /// Dock and hold until undock (accepted when READY).
    Dock,
    /// Undock (accepted while docking or mated).
    Undock,
    /// Clear the latched fault and recover to home (accepted when faulted, E-STOP
    /// closed).
    ClearFault,
    /// Stop all motion, latching the `stopped` fault (always accepted; also broadcast).
    Stop,
    /// Find home and lock after a reset (accepted at power-up).
    Home,
}

impl Command {
    /// Every command, in coil order.
    pub const ALL: [Self; 5] = [
        Self::Dock,
        Self::Undock,
        Self::ClearFault,
        Self::Stop,
        Self::Home,
    ];

    /// The command register's value (1–5).
    pub const fn code(self) -> u16 {
        match self {
            Self::Dock => 1,
            Self::Undock => 2,
            Self::ClearFault => 3,
            Self::Stop => 4,
            Self::Home => 5,
        }
    }

    /// From the command register's value.
    pub const fn from_code(code: u16) -> Option<Self> {
        match code {
            1 => Some(Self::Dock),
            2 => Some(Self::Undock),
            3 => Some(Self::ClearFault),
            4 => Some(Self::Stop),
            5 => Some(Self::Home),
            _ => None,
        }
    }

    /// The command's coil.
    pub const fn coil(self) -> u16 {
        self.code() - 1
    }

    /// What is asked of the controller.
    pub const fn request(self) -> Request {
        match self {
            Self::Dock => Request::Dock,
            Self::Undock => Request::Undock,
            Self::ClearFault => Request::ClearFault,
            Self::Stop => Request::Stop,
            Self::Home => Request::Home,
        }
    }

    /// Whether it moves the machine (unicast only).
    pub const fn moves(self) -> bool {
        !matches!(self, Self::Stop)
    }
}

/// Command coils in the map (addresses 0..COIL_COUNT).
pub const COIL_COUNT: u16 = 5;
/// Holding registers in the map: 0, the command register.
pub const HOLDING_COUNT: u16 = 1;

/// The sequencer state's code (input register 1).
pub const fn state_code(s: &State) -> u16 {
    match s {
        State::PowerUp => 0,
        State::Homing { .. } => 1,
        State::Locking { .. } => 2,
        State::Idle => 3,
        State::PreAlign { .. } => 4,
        State::Releasing { .. } => 5,
        State::Inserting { .. } => 6,
        State::Holding { .. } => 7,
        State::Extracting { .. } => 8,
        State::Returning { .. } => 9,
        State::BackingOff { .. } => 10,
        State::Faulted { .. } => 11,
        State::Recovering { .. } => 12,
    }
}

/// Decimal digits at the start of `s`, saturating.
const fn parse_u16(s: &str) -> u16 {
    let mut b = s.as_bytes();
    let mut v: u16 = 0;
    while let [d, rest @ ..] = b {
        if !d.is_ascii_digit() {
            break;
        }
        v = v.saturating_mul(10).saturating_add((*d - b'0') as u16);
        b = rest;
    }
    v
}

/// The firmware version (major, minor, patch), from `Cargo.toml` at build time.
pub const FIRMWARE_VERSION: [u16; 3] = [
    parse_u16(env!("CARGO_PKG_VERSION_MAJOR")),
    parse_u16(env!("CARGO_PKG_VERSION_MINOR")),
    parse_u16(env!("CARGO_PKG_VERSION_PATCH")),
];

/// mN → 0.1 N, rounded to the nearest, saturating to `i16`, as a register.
fn decinewtons(mn: i32) -> u16 {
    let mn = i64::from(mn);
    let dn = (mn + if mn >= 0 { 50 } else { -50 }) / 100;
    dn.clamp(i64::from(i16::MIN), i64::from(i16::MAX)) as i16 as u16
}

/// µm → 0.01 mm, rounded to the nearest, saturating to `i16`, as a register.
fn centimillimetres(um: i32) -> u16 {
    let um = i64::from(um);
    let v = (um + if um >= 0 { 5 } else { -5 }) / 10;
    v.clamp(i64::from(i16::MIN), i64::from(i16::MAX)) as i16 as u16
}

fn sat_u16(v: u64) -> u16 {
    u16::try_from(v).unwrap_or(u16::MAX)
}

/// The status word (input register 0; discrete inputs 0–11).
pub fn status_word<B: Bsp>(ctrl: &Controller<B>) -> u16 {
    let s = ctrl.status();
    let h = s.handshake;
    let bits = [
        (h.ready, status::READY),
        (h.mated, status::MATED),
        (s.state.is_moving(), status::MOVING),
        (h.fault, status::FAULT),
        (s.warning, status::WARNING),
        (h.maintenance, status::MAINTENANCE),
        (ctrl.calibrated(), status::CALIBRATED),
        (h.estop, status::ESTOP_OPEN),
        (h.dock, status::DOCK_INPUT),
        (s.wear_level == WearLevel::Limit, status::WORN_OUT),
        (s.state.is_docking(), status::DOCKING),
        (ctrl.maintenance_mode(), status::MAINTENANCE_MODE),
    ];
    bits.iter()
        .filter(|(on, _)| *on)
        .fold(0, |w, (_, bit)| w | bit)
}

/// The input registers now, 0..[`ir::COUNT`] (reserved addresses 0; the last command
/// and its result, 8–9, are the [`Server`]'s and read 0 here).
pub fn input_registers<B: Bsp>(ctrl: &Controller<B>) -> [u16; ir::COUNT as usize] {
    let mut r = [0u16; ir::COUNT as usize];
    let mut set = |addr: u16, v: u16| {
        if let Some(x) = r.get_mut(usize::from(addr)) {
            *x = v;
        }
    };
    let s = ctrl.status();
    let odo = ctrl.odometer();
    let life = odo.lifetime();
    let cone = odo.cone();
    let limit_nm = odo.config().limit_nm;
    let phase = |p: Option<crate::profile::ContactPhase>| p.map_or(0, |p| u16::from(p.number()));

    set(ir::STATUS, status_word(ctrl));
    set(ir::STATE, state_code(&s.state));
    set(ir::PHASE, phase(s.phase));
    set(ir::FORCE, decinewtons(s.force_mn));
    set(ir::FORCE_LIMIT, decinewtons(s.limit_mn));
    set(ir::POSITION, centimillimetres(s.pos_um));
    set(
        ir::ACTIVE_FAULT,
        s.fault.map_or(0xFFFF, |f| u16::from(f.code())),
    );
    set(ir::PEAK_FORCE, decinewtons(s.peak_force_mn));

    let mut set32 = |addr: u16, v: u32| {
        set(addr, (v >> 16) as u16);
        set(addr.saturating_add(1), v as u16);
    };
    set32(ir::LIFETIME_CYCLES, life.cycles);
    set32(ir::CONE_CYCLES, cone.cycles);
    set32(ir::WEAR_NM, odo.wear_nm());
    set32(ir::REMAINING_CYCLES, odo.remaining_cycles());
    set32(ir::OVERLOAD_EVENTS, life.overload_events);
    set32(ir::FAULTS_LIFETIME, life.faults);
    set32(ir::FAULTS_SINCE_BOOT, ctrl.fault_count());
    set32(ir::OVERLOAD_TRIPS_SINCE_BOOT, ctrl.overload_trips());
    let last = ctrl.faults().last().copied();
    set32(ir::LAST_FAULT_CYCLE, last.map_or(0, |f| f.cycle));

    set(ir::WEAR_UM, sat_u16(u64::from(odo.wear_nm() / 1_000)));
    set(
        ir::WEAR_LEVEL,
        match s.wear_level {
            WearLevel::Ok => 0,
            WearLevel::Warning => 1,
            WearLevel::Limit => 2,
        },
    );
    set(
        ir::WEAR_PERMILLE,
        sat_u16(u64::from(odo.wear_nm()) * 1_000 / u64::from(limit_nm.max(1))),
    );
    set(ir::WEAR_LIMIT_UM, sat_u16(u64::from(limit_nm / 1_000)));
    set(
        ir::LAST_FAULT_CODE,
        last.map_or(0xFFFF, |f| u16::from(f.kind.code())),
    );
    set(
        ir::LAST_FAULT_PEAK_FORCE,
        last.map_or(0, |f| decinewtons(f.peak_force_mn)),
    );
    set(ir::LAST_FAULT_PHASE, last.map_or(0, |f| phase(f.phase)));
    set(ir::CONE_ID, cone.id);
    set(ir::CONE_MATERIAL, u16::from(cone.material.code()));
    let serial = cone
        .serial
        .get(..usize::from(cone.serial_len))
        .unwrap_or(&[]);
    let serial_regs = ir::CONE_SERIAL..ir::CONE_SERIAL + ir::CONE_SERIAL_REGS;
    for (addr, pair) in serial_regs.zip(serial.chunks(2)) {
        let hi = pair.first().copied().unwrap_or(0);
        let lo = pair.get(1).copied().unwrap_or(0);
        set(addr, u16::from_be_bytes([hi, lo]));
    }
    let [major, minor, patch] = FIRMWARE_VERSION;
    set(ir::FW_MAJOR, major);
    set(ir::FW_MINOR, minor);
    set(ir::FW_PATCH, patch);
    set(ir::MAP_VERSION, MAP_VERSION);
    set(ir::MAINTENANCE_MODE, u16::from(ctrl.maintenance_mode()));
    r
}

// ---------------------------------------------------------------------------------
// Device identification
// ---------------------------------------------------------------------------------

/// Object 0, VendorName, unless the commissioning file names the machine's builder
/// ([`crate::controller::Identity`]).
pub const VENDOR_NAME: &str = "docking-controller project";
/// Object 1, ProductCode (the firmware package).
pub const PRODUCT_CODE: &str = env!("CARGO_PKG_NAME");
/// Object 2, MajorMinorRevision (the firmware version).
pub const REVISION: &str = env!("CARGO_PKG_VERSION");
/// Object 4, ProductName, unless the commissioning file names the product.
pub const PRODUCT_NAME: &str = "Automatic connector docking controller";
/// Object 5, ModelName.
pub const MODEL_NAME: &str = "STM32F407";
/// Object 0x80 (private): the unit's serial number.
pub const OBJECT_SERIAL: u8 = 0x80;
/// The unit serial's longest length in object 0x80, bytes (longer is cut).
pub const SERIAL_OBJECT_MAX: usize = 32;
/// The conformity level: basic, regular and extended, stream and individual access.
pub const CONFORMITY: u8 = 0x83;
/// The objects, in stream order.
const OBJECTS: [u8; 6] = [0, 1, 2, 4, 5, OBJECT_SERIAL];

fn device_object(id: u8, serial: &str, names: crate::controller::Identity) -> Option<&[u8]> {
    Some(match id {
        0 => names.vendor.as_bytes(),
        1 => PRODUCT_CODE.as_bytes(),
        2 => REVISION.as_bytes(),
        4 => names.product.as_bytes(),
        5 => MODEL_NAME.as_bytes(),
        OBJECT_SERIAL => {
            let b = serial.as_bytes();
            b.get(..SERIAL_OBJECT_MAX).unwrap_or(b)
        }
        _ => return None,
    })
}

/// Function 0x2B: `pdu` is the request's (function included); the reply goes to
/// `out` (the unit address is there already); returns its length without the CRC.
fn device_identification(
    pdu: &[u8],
    serial: &str,
    names: crate::controller::Identity,
    out: &mut [u8; MAX_FRAME],
) -> Reply {
    const HEAD: usize = 8; // unit, 0x2B, 0x0E, code, conformity, more, next, count
    let &[_, mei, code, object] = pdu else {
        return match pdu.get(1) {
            Some(&0x0E) | None => Reply::Exception(exception::ILLEGAL_DATA_VALUE),
            Some(_) => Reply::Exception(exception::ILLEGAL_FUNCTION),
        };
    };
    if mei != 0x0E {
        return Reply::Exception(exception::ILLEGAL_FUNCTION);
    }
    let last_id = match code {
        1 => 0x02,
        2 => 0x7F,
        3 | 4 => 0xFF,
        _ => return Reply::Exception(exception::ILLEGAL_DATA_VALUE),
    };
    let known = device_object(object, serial, names).is_some();
    if code == 4 && !known {
        return Reply::Exception(exception::ILLEGAL_DATA_ADDRESS);
    }
    let first = if known && object <= last_id {
        object
    } else {
        0
    };
    let mut pos = HEAD;
    let mut count: u8 = 0;
    let (mut more, mut next) = (0x00, 0x00);
    for &id in OBJECTS.iter().filter(|&&id| id >= first && id <= last_id) {
        if code == 4 && id != object {
            continue;
        }
        let value = device_object(id, serial, names).unwrap_or(&[]);
        let end = pos + 2 + value.len();
        // Room for the CRC after it.
        match out.get_mut(pos..end).filter(|_| end + 2 <= MAX_FRAME) {
            Some(dst) => {
                if let Some((hdr, body)) = dst.split_first_chunk_mut::<2>() {
                    *hdr = [id, value.len() as u8];
                    body.copy_from_slice(value);
                }
            }
            None => {
                more = 0xFF;
                next = id;
                break;
            }
        }
        pos = end;
        count += 1;
    }
    if let Some(h) = out.get_mut(1..HEAD) {
        h.copy_from_slice(&[0x2B, 0x0E, code, CONFORMITY, more, next, count]);
    }
    Reply::Normal(pos)
}

// ---------------------------------------------------------------------------------
// Request handling
// ---------------------------------------------------------------------------------

/// What to send (`out[0]` holds the unit address).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Reply {
    /// Nothing (broadcast, or nothing to say).
    None,
    /// `out[..len]`, the CRC still to add.
    Normal(usize),
    /// An exception with this code, to build.
    Exception(u8),
    /// `out[..len]`, complete (CRC included).
    Sealed(usize),
    /// `out[..len]`, a complete exception reply.
    SealedException(usize),
}

/// What handling one frame did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Outcome {
    /// Under 4 bytes (or over 256).
    Short,
    /// The CRC did not match.
    BadCrc,
    /// Addressed to another unit.
    OtherUnit,
    /// Handled: the reply's length with its CRC and whether it is an exception (`None`:
    /// no reply).
    Handled(Option<(usize, bool)>),
}

/// What the server remembers between requests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Session {
    /// The last command written (its code, [`Command::code`]); 0 none since boot.
    last_command: u16,
    /// Its result: 0 accepted, else the refusal's code
    /// ([`crate::controller::Refusal::code`]).
    last_result: u16,
    /// Commands accepted.
    accepted: u32,
}

impl Session {
    /// Nothing since boot.
    const NEW: Self = Self {
        last_command: 0,
        last_result: 0,
        accepted: 0,
    };
}

/// Check the frame length and the quantity limits of functions 0x01–0x06, 0x0F, 0x10
/// (`pdu` from the function code on, CRC excluded).
fn validate(function: u8, pdu: &[u8]) -> Result<(), u8> {
    let bad = Err(exception::ILLEGAL_DATA_VALUE);
    let word = |i: usize| match (pdu.get(i), pdu.get(i + 1)) {
        (Some(&h), Some(&l)) => Some(u16::from_be_bytes([h, l])),
        _ => None,
    };
    match function {
        0x01..=0x06 => {
            let Some(v) = word(3).filter(|_| pdu.len() == 5) else {
                return bad;
            };
            let ok = match function {
                0x01 | 0x02 => (1..=2_000).contains(&v),
                0x03 | 0x04 => (1..=125).contains(&v),
                0x05 => v == 0x0000 || v == 0xFF00,
                _ => true,
            };
            if ok {
                Ok(())
            } else {
                bad
            }
        }
        0x0F | 0x10 => {
            let (Some(qty), Some(&bytes)) = (word(3), pdu.get(5)) else {
                return bad;
            };
            let (max, need) = if function == 0x0F {
                (1_968, qty.div_ceil(8))
            } else {
                (123, qty.saturating_mul(2))
            };
            if (1..=max).contains(&qty)
                && u16::from(bytes) == need
                && pdu.len() == 6 + usize::from(bytes)
            {
                Ok(())
            } else {
                bad
            }
        }
        _ => Err(exception::ILLEGAL_FUNCTION),
    }
}

/// `address..address + count` inside a block of `len`.
fn in_map(address: u16, count: u16, len: u16) -> bool {
    u32::from(address) + u32::from(count) <= u32::from(len)
}

/// Run the commands of `mask` (bit n = coil n). See the module doc for the rules.
fn run_commands<B: Bsp>(
    mask: u8,
    broadcast: bool,
    ctrl: &mut Controller<B>,
    session: &mut Session,
) -> Result<(), ErrorKind> {
    let stop_bit = 1u8 << Command::Stop.coil();
    let single = if mask & stop_bit != 0 {
        Some(Command::Stop) // run whatever else is written with it
    } else if mask.count_ones() > 1 {
        return Err(ErrorKind::IllegalDataValue);
    } else {
        Command::ALL.into_iter().find(|c| mask == 1u8 << c.coil())
    };
    let Some(cmd) = single else {
        return Ok(()); // 0: a no-op
    };
    if broadcast && cmd.moves() {
        return Ok(()); // motion is unicast only (and a broadcast gets no reply)
    }
    let result = ctrl.command_from(Source::Plc, cmd.request());
    session.last_command = cmd.code();
    session.last_result = match result {
        Ok(()) => {
            info!("modbus: {:?}", cmd);
            session.accepted = session.accepted.saturating_add(1);
            0
        }
        Err(r) => {
            warn!("modbus: {:?} {}", cmd, r);
            u16::from(r.code())
        }
    };
    if result.is_err() {
        Err(ErrorKind::IllegalFunction)
    } else if mask != 1u8 << cmd.coil() {
        Err(ErrorKind::IllegalDataValue) // a stop with other commands: only the stop ran
    } else {
        Ok(())
    }
}

fn bit(data: &[u8], i: usize) -> bool {
    data.get(i / 8).is_some_and(|b| b >> (i % 8) & 1 != 0)
}

fn write_coils<B: Bsp>(
    address: u16,
    count: u16,
    data: &[u8],
    broadcast: bool,
    ctrl: &mut Controller<B>,
    session: &mut Session,
) -> Result<(), ErrorKind> {
    if !in_map(address, count, COIL_COUNT) {
        return Err(ErrorKind::IllegalDataAddress);
    }
    let mask = (0..usize::from(count))
        .filter(|&i| bit(data, i))
        .fold(0u8, |m, i| m | 1 << (usize::from(address) + i));
    run_commands(mask, broadcast, ctrl, session)
}

fn write_registers<B: Bsp>(
    address: u16,
    count: u16,
    data: &[u8],
    broadcast: bool,
    ctrl: &mut Controller<B>,
    session: &mut Session,
) -> Result<(), ErrorKind> {
    if !in_map(address, count, HOLDING_COUNT) {
        return Err(ErrorKind::IllegalDataAddress);
    }
    let Some(&[hi, lo]) = data.first_chunk::<2>() else {
        return Err(ErrorKind::IllegalDataValue);
    };
    let mask = match u16::from_be_bytes([hi, lo]) {
        0 => 0,
        v => match Command::from_code(v) {
            Some(c) => 1u8 << c.coil(),
            None => return Err(ErrorKind::IllegalDataValue),
        },
    };
    run_commands(mask, broadcast, ctrl, session)
}

fn read_words<B: Bsp>(
    function: u8,
    address: u16,
    count: u16,
    buf: &mut [u8],
    ctrl: &Controller<B>,
    session: &Session,
) -> Result<(), ErrorKind> {
    let len = if function == 0x04 {
        ir::COUNT
    } else {
        HOLDING_COUNT
    };
    if !in_map(address, count, len) {
        return Err(ErrorKind::IllegalDataAddress);
    }
    if function != 0x04 {
        return Ok(()); // the command register reads 0 (the buffer is zeroed)
    }
    let mut regs = input_registers(ctrl);
    for (addr, v) in [
        (ir::LAST_COMMAND, session.last_command),
        (ir::LAST_COMMAND_RESULT, session.last_result),
    ] {
        if let Some(r) = regs.get_mut(usize::from(addr)) {
            *r = v;
        }
    }
    let src = regs
        .get(usize::from(address)..)
        .unwrap_or(&[])
        .iter()
        .take(usize::from(count));
    for (dst, v) in buf.chunks_exact_mut(2).zip(src) {
        dst.copy_from_slice(&v.to_be_bytes());
    }
    Ok(())
}

fn read_bits<B: Bsp>(
    function: u8,
    address: u16,
    count: u16,
    buf: &mut [u8],
    ctrl: &Controller<B>,
) -> Result<(), ErrorKind> {
    let len = if function == 0x02 {
        status::COUNT
    } else {
        COIL_COUNT
    };
    if !in_map(address, count, len) {
        return Err(ErrorKind::IllegalDataAddress);
    }
    if function != 0x02 {
        return Ok(()); // momentary command coils read 0
    }
    let word = status_word(ctrl);
    for i in 0..usize::from(count) {
        if word >> (usize::from(address) + i) & 1 != 0 {
            if let Some(b) = buf.get_mut(i / 8) {
                *b |= 1 << (i % 8);
            }
        }
    }
    Ok(())
}

/// Functions 0x01–0x06, 0x0F, 0x10 through rmodbus (the frame checked already).
fn standard<B: Bsp>(
    frame: &[u8],
    unit: u8,
    function: u8,
    broadcast: bool,
    ctrl: &mut Controller<B>,
    out: &mut [u8; MAX_FRAME],
    session: &mut Session,
) -> Reply {
    let mut resp: Vec<u8, MAX_FRAME> = Vec::new();
    let mut f = ModbusFrame::new(unit, frame, ModbusProto::Rtu, &mut resp);
    if f.parse().is_err() {
        return Reply::None;
    }
    if f.processing_required {
        let done = if f.readonly {
            let result = match f.get_external_read() {
                Ok(Read::Words(w)) => {
                    read_words(function, w.address, w.count, w.buf, ctrl, session)
                }
                Ok(Read::Bits(b)) => read_bits(function, b.address, b.count, b.buf, ctrl),
                Err(e) => Err(e),
            };
            f.process_external_read(result)
        } else {
            let result = match f.get_external_write() {
                Ok(Write::Bits(b)) => {
                    write_coils(b.address, b.count, b.data, broadcast, ctrl, session)
                }
                Ok(Write::Words(w)) => {
                    write_registers(w.address, w.count, w.data, broadcast, ctrl, session)
                }
                Err(e) => Err(e),
            };
            f.process_external_write(result)
        };
        if done.is_err() {
            return Reply::None;
        }
    }
    if !f.response_required || broadcast || f.finalize_response().is_err() {
        return Reply::None;
    }
    let exception = f.error.is_some();
    let n = resp.len();
    match out.get_mut(..n) {
        Some(dst) => dst.copy_from_slice(&resp),
        None => return Reply::None,
    }
    if exception {
        Reply::SealedException(n)
    } else {
        Reply::Sealed(n)
    }
}

/// Append the CRC to `out[..len]`; the frame's length.
fn seal(out: &mut [u8; MAX_FRAME], len: usize) -> Option<usize> {
    let crc = crc16(out.get(..len)?);
    out.get_mut(len..len + 2)?
        .copy_from_slice(&crc.to_le_bytes());
    Some(len + 2)
}

fn process<B: Bsp>(
    frame: &[u8],
    unit: u8,
    ctrl: &mut Controller<B>,
    unit_serial: &str,
    out: &mut [u8; MAX_FRAME],
    session: &mut Session,
) -> Outcome {
    if frame.len() < MIN_FRAME || frame.len() > MAX_FRAME {
        return Outcome::Short;
    }
    let Some((body, crc)) = frame.split_last_chunk::<2>() else {
        return Outcome::Short;
    };
    if crc16(body) != u16::from_le_bytes(*crc) {
        return Outcome::BadCrc;
    }
    let Some((&address, pdu)) = body.split_first() else {
        return Outcome::Short;
    };
    let broadcast = address == BROADCAST;
    if !broadcast && address != unit {
        return Outcome::OtherUnit;
    }
    let Some(&function) = pdu.first() else {
        return Outcome::Short;
    };
    if broadcast && matches!(function, 0x01..=0x04 | 0x2B) {
        return Outcome::Handled(None); // reads are never broadcast
    }
    if let Some(o) = out.first_mut() {
        *o = unit;
    }
    let reply = match function {
        0x2B => device_identification(pdu, unit_serial, ctrl.config().identity, out),
        _ => match validate(function, pdu) {
            Err(code) => Reply::Exception(code),
            Ok(()) => standard(frame, unit, function, broadcast, ctrl, out, session),
        },
    };
    Outcome::Handled(match reply {
        _ if broadcast => None,
        Reply::None => None,
        Reply::Sealed(n) => Some((n, false)),
        Reply::SealedException(n) => Some((n, true)),
        Reply::Normal(n) => seal(out, n).map(|n| (n, false)),
        Reply::Exception(code) => {
            if let Some(h) = out.get_mut(1..3) {
                h.copy_from_slice(&[function | 0x80, code]);
            }
            seal(out, 3).map(|n| (n, true))
        }
    })
}

/// Handle one request frame (address, PDU, CRC) as unit `unit`: the reply (CRC
/// included) in `out[..n]`, `Some(n)`, or `None` when nothing is to be sent (under 4
/// bytes, a bad CRC, another unit, a broadcast). Reads do not change the controller; a
/// command goes through [`Controller::command`]. `unit_serial` is the unit's serial
/// number (device identification object 0x80).
///
/// Stateless: the last command and its result (input registers 8–9) are kept by a
/// [`Server`]; here they read 0.
pub fn handle_frame<B: Bsp>(
    frame: &[u8],
    unit: u8,
    ctrl: &mut Controller<B>,
    unit_serial: &str,
    out: &mut [u8; MAX_FRAME],
) -> Option<usize> {
    let mut session = Session::default();
    match process(frame, unit, ctrl, unit_serial, out, &mut session) {
        Outcome::Handled(reply) => reply.map(|(n, _)| n),
        _ => None,
    }
}

// ---------------------------------------------------------------------------------
// Server
// ---------------------------------------------------------------------------------

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
            framer: RtuFramer {
                buf: [0; MAX_FRAME],
                len: 0,
                rx: Rx::Idle,
                last_us: None,
                char_us: 0,
                t1_5_us: 0,
                t3_5_us: 0,
                framing_errors: 0,
                overruns: 0,
            },
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
    pub fn on_byte(&mut self, byte: u8, t_us: u64) {
        self.framer.push(byte, t_us);
    }

    /// A character received with a line error (parity, framing, noise, overrun), µs.
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
    pub fn poll<B: Bsp>(
        &mut self,
        now_us: u64,
        ctrl: &mut Controller<B>,
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

    /// The last command written (its code, [`Command::code`]; 0 none since boot) and
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_validate_and_round_trip() {
        assert_eq!(ModbusSettings::default(), ModbusSettings::DEFAULT);
        assert!(ModbusSettings::DEFAULT.is_valid());
        for baud in BAUD_RATES {
            for unit in [1, 2, 100, 247] {
                let s = ModbusSettings::new(unit, baud).unwrap();
                assert_eq!(ModbusSettings::from_bytes(&s.to_bytes()), Some(s));
            }
        }
        assert_eq!(ModbusSettings::new(0, 19_200), None);
        assert_eq!(ModbusSettings::new(248, 19_200), None);
        assert_eq!(ModbusSettings::new(255, 19_200), None);
        for baud in [0, 1_200, 4_800, 14_400, 19_201, 230_400, u32::MAX] {
            assert_eq!(ModbusSettings::new(1, baud), None, "{baud}");
        }
        let b = ModbusSettings::DEFAULT.to_bytes();
        assert_eq!(b, [1, 0, 0x00, 0x4B, 0x00, 0x00]);
        // Wrong length, format, or a value out of range: refused.
        assert_eq!(ModbusSettings::from_bytes(&b[..5]), None);
        assert_eq!(ModbusSettings::from_bytes(&[1, 0, 0, 0x4B, 0, 0, 0]), None);
        assert_eq!(ModbusSettings::from_bytes(&[1, 1, 0, 0x4B, 0, 0]), None);
        assert_eq!(ModbusSettings::from_bytes(&[0, 0, 0, 0x4B, 0, 0]), None);
        assert_eq!(ModbusSettings::from_bytes(&[1, 0, 0, 0x4C, 0, 0]), None);
        assert_eq!(ModbusSettings::from_bytes(&[0xFF; 6]), None);
    }

    #[test]
    fn character_times_follow_the_serial_line_spec() {
        let t = |baud| {
            let s = ModbusSettings { unit: 1, baud };
            (s.char_us(), s.t1_5_us(), s.t3_5_us())
        };
        assert_eq!(t(9_600), (1_146, 1_719, 4_011));
        assert_eq!(t(19_200), (573, 860, 2_006));
        assert_eq!(t(38_400), (287, 750, 1_750));
        assert_eq!(t(57_600), (191, 750, 1_750));
        assert_eq!(t(115_200), (96, 750, 1_750));
        // No division by zero on nonsense.
        let _ = t(0);
    }

    #[test]
    fn crc_matches_the_spec_example() {
        // Modbus over serial line, §6.2.2 style example: 01 03 00 00 00 0A → C5 CD.
        assert_eq!(
            crc16(&[0x01, 0x03, 0x00, 0x00, 0x00, 0x0A]).to_le_bytes(),
            [0xC5, 0xCD]
        );
    }

    #[test]
    fn firmware_version_is_the_package_version() {
        let v = env!("CARGO_PKG_VERSION");
        let mut parts = v.split(['.', '-', '+']).map(|p| p.parse::<u16>().unwrap());
        assert_eq!(
            FIRMWARE_VERSION,
            [
                parts.next().unwrap(),
                parts.next().unwrap(),
                parts.next().unwrap()
            ]
        );
        assert_eq!(parse_u16("12rc"), 12);
        assert_eq!(parse_u16(""), 0);
        assert_eq!(parse_u16("99999999"), u16::MAX);
    }

    #[test]
    fn scaling_rounds_and_saturates() {
        assert_eq!(decinewtons(0), 0);
        assert_eq!(decinewtons(125_098), 1_251);
        assert_eq!(decinewtons(49), 0);
        assert_eq!(decinewtons(50), 1);
        assert_eq!(decinewtons(-50) as i16, -1);
        assert_eq!(decinewtons(-149) as i16, -1);
        assert_eq!(decinewtons(i32::MAX) as i16, i16::MAX);
        assert_eq!(decinewtons(i32::MIN) as i16, i16::MIN);
        assert_eq!(centimillimetres(50_004), 5_000);
        assert_eq!(centimillimetres(-3_000) as i16, -300);
        assert_eq!(centimillimetres(i32::MAX) as i16, i16::MAX);
    }

    #[test]
    fn commands_codes_and_coils_agree() {
        for (i, c) in Command::ALL.into_iter().enumerate() {
            assert_eq!(c.coil() as usize, i);
            assert_eq!(Command::from_code(c.code()), Some(c));
        }
        assert_eq!(Command::from_code(0), None);
        assert_eq!(Command::from_code(6), None);
        assert_eq!(COIL_COUNT as usize, Command::ALL.len());
        assert!(!Command::Stop.moves() && Command::Dock.moves());
    }

    #[test]
    fn validation_checks_length_quantity_and_byte_count() {
        let v = |pdu: &[u8]| validate(pdu[0], pdu);
        assert_eq!(v(&[0x04, 0, 0, 0, 1]), Ok(()));
        assert_eq!(v(&[0x04, 0, 0, 0, 125]), Ok(()));
        assert_eq!(v(&[0x04, 0, 0, 0, 126]), Err(3));
        assert_eq!(v(&[0x04, 0, 0, 0, 0]), Err(3));
        assert_eq!(v(&[0x04, 0, 0, 0]), Err(3));
        assert_eq!(v(&[0x04, 0, 0, 0, 1, 0]), Err(3));
        assert_eq!(v(&[0x01, 0, 0, 0x07, 0xD0]), Ok(()));
        assert_eq!(v(&[0x01, 0, 0, 0x07, 0xD1]), Err(3));
        assert_eq!(v(&[0x05, 0, 0, 0xFF, 0x00]), Ok(()));
        assert_eq!(v(&[0x05, 0, 0, 0x00, 0x00]), Ok(()));
        assert_eq!(v(&[0x05, 0, 0, 0x00, 0x01]), Err(3));
        assert_eq!(v(&[0x06, 0, 0, 0xAB, 0xCD]), Ok(()));
        assert_eq!(v(&[0x0F, 0, 0, 0, 9, 2, 0xFF, 0x01]), Ok(()));
        assert_eq!(v(&[0x0F, 0, 0, 0, 9, 1, 0xFF]), Err(3));
        assert_eq!(v(&[0x0F, 0, 0, 0, 9, 2, 0xFF]), Err(3));
        assert_eq!(v(&[0x0F, 0, 0, 0, 0, 0]), Err(3));
        assert_eq!(v(&[0x10, 0, 0, 0, 1, 2, 0, 1]), Ok(()));
        assert_eq!(v(&[0x10, 0, 0, 0, 1, 3, 0, 1, 0]), Err(3));
        assert_eq!(v(&[0x10, 0, 0, 0, 124, 248]), Err(3));
        assert_eq!(v(&[0x10, 0, 0, 0, 1, 255]), Err(3));
        assert_eq!(v(&[0x10, 0, 0]), Err(3));
        assert_eq!(v(&[0x07]), Err(1));
    }

    #[test]
    fn state_codes_are_distinct() {
        use crate::sequencer::{AfterLock, FaultKind};
        let states = [
            State::PowerUp,
            State::Homing { deadline_ms: 0 },
            State::Locking {
                deadline_ms: 0,
                then: AfterLock::Idle,
            },
            State::Idle,
            State::PreAlign { deadline_ms: 0 },
            State::Releasing { deadline_ms: 0 },
            State::Inserting { deadline_ms: 0 },
            State::Holding {
                until_ms: None,
                unmating: false,
            },
            State::Extracting { deadline_ms: 0 },
            State::Returning {
                deadline_ms: 0,
                ends_cycle: true,
                creeping: false,
            },
            State::BackingOff {
                deadline_ms: 0,
                target_um: 0,
            },
            State::Faulted {
                fault: FaultKind::Stopped,
            },
            State::Recovering { deadline_ms: 0 },
        ];
        for (i, s) in states.iter().enumerate() {
            assert_eq!(state_code(s) as usize, i, "{}", s.name());
        }
    }

    // -- framer --

    const S: ModbusSettings = ModbusSettings::DEFAULT; // 19 200: char 573, t1.5 860, t3.5 2006

    /// Push `bytes` back to back from `t0` (one character time apart); the last stamp.
    fn burst(f: &mut RtuFramer, bytes: &[u8], t0: u64) -> u64 {
        let c = u64::from(S.char_us());
        let mut t = t0;
        for (i, &b) in bytes.iter().enumerate() {
            t = t0 + i as u64 * c;
            f.push(b, t);
        }
        t
    }

    #[test]
    fn framer_delivers_a_frame_after_t3_5_once() {
        let mut f = RtuFramer::new(&S);
        assert_eq!(f.poll(0), None);
        let end = burst(&mut f, &[1, 2, 3, 4, 5], 10_000);
        assert_eq!(f.poll(end + 2_005), None, "not yet silent for t3.5");
        assert_eq!(f.poll(end + 2_006), Some(&[1u8, 2, 3, 4, 5][..]));
        assert_eq!(f.poll(end + 9_000), None, "once");
        assert_eq!((f.framing_errors(), f.overruns()), (0, 0));
    }

    #[test]
    fn framer_splits_frames_at_t3_5_and_counts_unpolled_ones() {
        let mut f = RtuFramer::new(&S);
        let c = u64::from(S.char_us());
        let end = burst(&mut f, &[1, 2, 3, 4], 0);
        // The next frame starts exactly t3.5 of silence later: two frames, and the
        // first was never polled.
        let end2 = burst(&mut f, &[5, 6, 7, 8], end + c + 2_006);
        assert_eq!(f.poll(end2 + 2_006), Some(&[5u8, 6, 7, 8][..]));
        assert_eq!(f.overruns(), 1);
        // A silence just under t3.5 (and over t1.5): one bad frame.
        let end3 = burst(&mut f, &[1, 2, 3, 4], end2 + 10_000);
        let end4 = burst(&mut f, &[5, 6, 7, 8], end3 + c + 2_005);
        assert_eq!(f.poll(end4 + 2_006), None);
        assert_eq!(f.framing_errors(), 1);
    }

    #[test]
    fn framer_discards_a_frame_with_a_gap_over_t1_5() {
        let mut f = RtuFramer::new(&S);
        let c = u64::from(S.char_us());
        // Silence of exactly t1.5 is allowed.
        let end = burst(&mut f, &[1, 2, 3], 0);
        let end = burst(&mut f, &[4, 5], end + c + 860);
        assert_eq!(f.poll(end + 2_006), Some(&[1u8, 2, 3, 4, 5][..]));
        // One µs more is not: the whole frame goes, and the next one is fine.
        let end = burst(&mut f, &[1, 2, 3], end + 5_000);
        let end = burst(&mut f, &[4, 5], end + c + 861);
        assert_eq!(f.poll(end + 2_006), None);
        assert_eq!(f.framing_errors(), 1);
        let end = burst(&mut f, &[9, 9, 9, 9], end + 5_000);
        assert_eq!(f.poll(end + 2_006), Some(&[9u8, 9, 9, 9][..]));
    }

    #[test]
    fn framer_discards_overlong_frames_whole_and_short_ones() {
        let mut f = RtuFramer::new(&S);
        let max = [0xA5u8; MAX_FRAME];
        let end = burst(&mut f, &max, 0);
        assert_eq!(f.poll(end + 2_006).map(<[u8]>::len), Some(MAX_FRAME));
        let mut over = [0x5Au8; MAX_FRAME + 40];
        over[0] = 1;
        let end = burst(&mut f, &over, end + 5_000);
        assert_eq!(f.poll(end + 2_006), None);
        assert_eq!(f.framing_errors(), 1);
        let end = burst(&mut f, &[1, 2, 3], end + 5_000);
        assert_eq!(f.poll(end + 2_006), None, "under 4 bytes");
        assert_eq!(f.framing_errors(), 2);
        let end = burst(&mut f, &[1, 2, 3, 4], end + 5_000);
        assert_eq!(f.poll(end + 2_006), Some(&[1u8, 2, 3, 4][..]));
    }

    #[test]
    fn framer_line_error_spoils_its_frame_only() {
        let mut f = RtuFramer::new(&S);
        let c = u64::from(S.char_us());
        let end = burst(&mut f, &[1, 2, 3], 0);
        f.line_error(end + c);
        let end = burst(&mut f, &[4, 5], end + 2 * c);
        assert_eq!(f.poll(end + 2_006), None);
        assert_eq!(f.framing_errors(), 1);
        let end = burst(&mut f, &[1, 2, 3, 4], end + 5_000);
        assert_eq!(f.poll(end + 2_006), Some(&[1u8, 2, 3, 4][..]));
    }

    #[test]
    fn framer_survives_time_going_backwards_and_huge_stamps() {
        let mut f = RtuFramer::new(&S);
        f.push(1, u64::MAX);
        f.push(2, 0);
        f.push(3, 5);
        f.push(4, u64::MAX - 1);
        assert_eq!(f.poll(u64::MAX), None, "not silent");
        assert_eq!(f.poll(0), None);
    }
}
