//! # Request handling
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

use super::exception::{ILLEGAL_DATA_ADDRESS, ILLEGAL_DATA_VALUE, ILLEGAL_FUNCTION};
use super::ident::device_identification;
use super::map::{input_registers, ir, status, status_word, Command, COIL_COUNT, HOLDING_COUNT};
use super::{crc16, exception, BROADCAST, MAX_FRAME, MIN_FRAME};
use crate::controller::Source;
use crate::machine::Machine;

/// What to send (`out[0]` holds the unit address).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Reply {
    /// Nothing (broadcast, or nothing to say).
    None,
    /// `out[..len]`, the CRC still to add.
    Normal(usize),
    /// An exception with this code, to build.
    Exception(u8),
}

/// What handling one frame did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum Outcome {
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
pub(super) struct Session {
    /// The last command written (its code, [`Command::code`]); 0 none since boot.
    pub(super) last_command: u16,
    /// Its result: 0 accepted, else the refusal's code
    /// ([`crate::controller::Refusal::code`]).
    pub(super) last_result: u16,
    /// Commands accepted.
    pub(super) accepted: u32,
}

impl Session {
    /// Nothing since boot.
    pub(super) const NEW: Self = Self {
        last_command: 0,
        last_result: 0,
        accepted: 0,
    };
}

/// Check the frame length and the quantity limits of functions 0x01–0x06, 0x0F, 0x10
/// (`pdu` from the function code on, CRC excluded).
pub(super) fn validate(function: u8, pdu: &[u8]) -> Result<(), u8> {
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

/// Run the commands of `mask` (bit n = coil n). See the module doc for the rules. `Err`:
/// the exception code.
fn run_commands(
    mask: u8,
    broadcast: bool,
    ctrl: &mut dyn Machine,
    session: &mut Session,
) -> Result<(), u8> {
    let stop_bit = 1u8 << Command::Stop.coil();
    let single = if mask & stop_bit != 0 {
        Some(Command::Stop) // run whatever else is written with it
    } else if mask.count_ones() > 1 {
        return Err(ILLEGAL_DATA_VALUE);
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
            info!("modbus: {}", cmd);
            session.accepted = session.accepted.saturating_add(1);
            0
        }
        Err(r) => {
            warn!("modbus: {} {}", cmd, r);
            u16::from(r.code())
        }
    };
    if result.is_err() {
        Err(ILLEGAL_FUNCTION)
    } else if mask != 1u8 << cmd.coil() {
        Err(ILLEGAL_DATA_VALUE) // a stop with other commands: only the stop ran
    } else {
        Ok(())
    }
}

fn bit(data: &[u8], i: usize) -> bool {
    data.get(i / 8).is_some_and(|b| b >> (i % 8) & 1 != 0)
}

fn write_coils(
    address: u16,
    count: u16,
    data: &[u8],
    broadcast: bool,
    ctrl: &mut dyn Machine,
    session: &mut Session,
) -> Result<(), u8> {
    if !in_map(address, count, COIL_COUNT) {
        return Err(ILLEGAL_DATA_ADDRESS);
    }
    let mask = (0..usize::from(count))
        .filter(|&i| bit(data, i))
        .fold(0u8, |m, i| m | 1 << (usize::from(address) + i));
    run_commands(mask, broadcast, ctrl, session)
}

fn write_registers(
    address: u16,
    count: u16,
    data: &[u8],
    broadcast: bool,
    ctrl: &mut dyn Machine,
    session: &mut Session,
) -> Result<(), u8> {
    if !in_map(address, count, HOLDING_COUNT) {
        return Err(ILLEGAL_DATA_ADDRESS);
    }
    let Some(&[hi, lo]) = data.first_chunk::<2>() else {
        return Err(ILLEGAL_DATA_VALUE);
    };
    let mask = match u16::from_be_bytes([hi, lo]) {
        0 => 0,
        v => match Command::from_code(v) {
            Some(c) => 1u8 << c.coil(),
            None => return Err(ILLEGAL_DATA_VALUE),
        },
    };
    run_commands(mask, broadcast, ctrl, session)
}

fn read_words(
    function: u8,
    address: u16,
    count: u16,
    buf: &mut [u8],
    ctrl: &dyn Machine,
    session: &Session,
) -> Result<(), u8> {
    let len = if function == 0x04 {
        ir::COUNT
    } else {
        HOLDING_COUNT
    };
    if !in_map(address, count, len) {
        return Err(ILLEGAL_DATA_ADDRESS);
    }
    // The command register (function 0x03) reads 0.
    let mut regs = [0u16; ir::COUNT as usize];
    if function == 0x04 {
        regs = input_registers(ctrl);
        for (addr, v) in [
            (ir::LAST_COMMAND, session.last_command),
            (ir::LAST_COMMAND_RESULT, session.last_result),
        ] {
            if let Some(r) = regs.get_mut(usize::from(addr)) {
                *r = v;
            }
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

fn read_bits(
    function: u8,
    address: u16,
    count: u16,
    buf: &mut [u8],
    ctrl: &dyn Machine,
) -> Result<(), u8> {
    let len = if function == 0x02 {
        status::COUNT
    } else {
        COIL_COUNT
    };
    if !in_map(address, count, len) {
        return Err(ILLEGAL_DATA_ADDRESS);
    }
    // Momentary command coils (function 0x01) read 0.
    let word = if function == 0x02 {
        u32::from(status_word(ctrl))
    } else {
        0
    };
    // Each byte whole (nothing zeroes the buffer first): bit k of byte j is input
    // `address + 8j + k`, for the `count` inputs asked for.
    for (j, b) in buf.iter_mut().enumerate() {
        let mut v = 0u8;
        for k in 0..8 {
            let i = 8 * j + k;
            if i < usize::from(count) && word >> (usize::from(address) + i) & 1 != 0 {
                v |= 1 << k;
            }
        }
        *b = v;
    }
    Ok(())
}

/// Functions 0x01–0x06, 0x0F, 0x10 (`pdu` from the function code on, checked by
/// [`validate`] already): the reply in `out` (`out[0]`, the unit, set by the caller).
///
/// By hand, not through rmodbus (used up to issue 20): once the frame is checked here,
/// what it did for these functions was the reply's header (a read's function and byte
/// count, a write's echo of its first five PDU bytes) and the exception for an error,
/// after parsing the frame and checking its CRC a second time with its own CRC-16 —
/// 1 960 B of flash for a dozen lines. The replies are the same bytes
/// (host-tests/tests/modbus_transcript.rs, recorded with rmodbus).
fn standard(
    pdu: &[u8],
    function: u8,
    broadcast: bool,
    ctrl: &mut dyn Machine,
    out: &mut [u8; MAX_FRAME],
    session: &mut Session,
) -> Reply {
    let word = |i: usize| match (pdu.get(i), pdu.get(i + 1)) {
        (Some(&h), Some(&l)) => u16::from_be_bytes([h, l]),
        _ => 0,
    };
    let (address, count) = (word(1), word(3));
    let data = pdu.get(6..).unwrap_or(&[]);
    let result = match function {
        0x01..=0x04 => {
            // function, byte count, then the data (zeroed, filled by the read).
            let n = if function <= 0x02 {
                count.div_ceil(8)
            } else {
                count.saturating_mul(2)
            };
            let n = usize::from(n);
            // Every byte is written by the read (no `fill`: the only zeroing of an
            // unaligned buffer in the image, which linked compiler_builtins' memclr).
            let Some(buf) = out.get_mut(3..3 + n) else {
                return Reply::None;
            };
            let read = if function <= 0x02 {
                read_bits(function, address, count, buf, ctrl)
            } else {
                read_words(function, address, count, buf, ctrl, session)
            };
            read.map(|()| {
                if let Some(h) = out.get_mut(1..3) {
                    h.copy_from_slice(&[function, n as u8]);
                }
                3 + n
            })
        }
        _ => {
            let written = match function {
                0x05 => {
                    let on = [u8::from(count == 0xFF00)];
                    write_coils(address, 1, &on, broadcast, ctrl, session)
                }
                0x06 => {
                    let value = pdu.get(3..5).unwrap_or(&[]);
                    write_registers(address, 1, value, broadcast, ctrl, session)
                }
                0x0F => write_coils(address, count, data, broadcast, ctrl, session),
                0x10 => write_registers(address, count, data, broadcast, ctrl, session),
                _ => Err(ILLEGAL_FUNCTION),
            };
            // A write's reply echoes its function, address and value or quantity.
            written.map(|()| {
                if let (Some(dst), Some(src)) = (out.get_mut(1..6), pdu.get(..5)) {
                    dst.copy_from_slice(src);
                }
                6
            })
        }
    };
    match result {
        Ok(n) => Reply::Normal(n),
        Err(code) => Reply::Exception(code),
    }
}

/// Append the CRC to `out[..len]`; the frame's length.
fn seal(out: &mut [u8; MAX_FRAME], len: usize) -> Option<usize> {
    let crc = crc16(out.get(..len)?);
    out.get_mut(len..len + 2)?
        .copy_from_slice(&crc.to_le_bytes());
    Some(len + 2)
}

pub(super) fn process(
    frame: &[u8],
    unit: u8,
    ctrl: &mut dyn Machine,
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
        0x2B => device_identification(
            pdu,
            unit_serial,
            ctrl.config().identity,
            &ctrl.images(),
            out,
        ),
        _ => match validate(function, pdu) {
            Err(code) => Reply::Exception(code),
            Ok(()) => standard(pdu, function, broadcast, ctrl, out, session),
        },
    };
    Outcome::Handled(match reply {
        _ if broadcast => None,
        Reply::None => None,
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
/// command goes through [`Machine::command_from`]. `unit_serial` is the unit's serial
/// number (device identification object 0x80).
///
/// Stateless: the last command and its result (input registers 8–9) are kept by a
/// [`Server`](super::Server); here they read 0.
pub fn handle_frame(
    frame: &[u8],
    unit: u8,
    ctrl: &mut dyn Machine,
    unit_serial: &str,
    out: &mut [u8; MAX_FRAME],
) -> Option<usize> {
    let mut session = Session::default();
    match process(frame, unit, ctrl, unit_serial, out, &mut session) {
        Outcome::Handled(reply) => reply.map(|(n, _)| n),
        _ => None,
    }
}
