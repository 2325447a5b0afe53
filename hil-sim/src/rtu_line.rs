//! A simulated RS-485 line into the controller's Modbus RTU server
//! ([`docking_logic::modbus::Server`]), as `hil-sim serve --modbus-pty|--modbus-tcp`
//! drives it.
//!
//! The outside (a pty, or a loopback TCP port acting as a transparent serial-to-Ethernet
//! gateway) carries raw RTU frames: address, PDU, CRC, no MBAP header. The board's UART
//! stamps every character at the end of its stop bit; here the bytes read from the link
//! get those stamps in **virtual** time at the line rate (8E1, 11 bits a character:
//! [`ModbusSettings::char_us`], 573 µs at the default 19 200 baud):
//!
//! * a byte's stamp is one character time after the previous byte's stamp, or after the
//!   virtual time at which it was read from the link (the wall clock's machine time,
//!   read every millisecond: not the last tick's), whichever is later: bytes read
//!   together go back to back, as a gateway sends a packet, and a request read after a
//!   pause starts after a silence;
//! * [`RtuLine::service`], called after every rig tick, hands the server the bytes
//!   whose stamps have passed (with those stamps), then polls it at the tick's time; a
//!   reply (CRC included) is returned, to be written to the link as it is.
//!
//! The rig ticks at its sample events: every conversion of the load cell and at least
//! once a sample period (12.5 ms at 80 SPS, 100 ms at 10 SPS), and a tick may run longer
//! (a flash erase stalls the board). So a request is answered at the first tick at or
//! after its t3.5 silence (2006 µs at 19 200 baud) in virtual time: within a tick of it.
//! At `--speed 20` a tick of 12.5 ms is 0.6 ms of wall time, and the serve loop reads
//! the link every 2 ms of wall time.
//!
//! One request at a time, as on a serial line: a master waits for the reply (or its
//! timeout) before the next request. Requests written back to back in one go reach the
//! line back to back, with no t3.5 between them: the server sees one bad frame and
//! answers nothing (as a real bus would). A request whose bytes reach the link in
//! pieces far apart in time gets a silence over t1.5 inside and is discarded, as on a
//! real line.
//!
//! **Replies take the wire's time**: [`RtuLine::send`] queues a reply's characters one
//! character time apart from when it was made (after any still on the wire), and
//! [`RtuLine::transmit`] hands out those whose end has passed: a 141-byte reply takes
//! 81 ms at 19 200 baud, not a tick. **A client that leaves** takes its line with it:
//! [`RtuLine::drop_client`] discards what it left waiting and any reply still on the
//! wire, so the next client never gets them.
//!
//! Back-pressure: at most [`RX_WINDOW`] bytes wait for their stamps; the link is read
//! only for the room left ([`RtuLine::room`]), so a flood drains at the line rate
//! (in virtual time) and is never queued without bound.

use std::collections::VecDeque;

use docking_logic::controller::{Bsp, Controller};
use docking_logic::modbus::{ModbusSettings, ModbusStats, Server};

/// The simulated unit's serial number: device identification object 0x80 (the board
/// passes its own, from the MCU's unique id).
pub const UNIT_SERIAL: &str = "HILSIM-0001";

/// Most bytes waiting on the line (read from the link, their stamp not yet reached).
pub const RX_WINDOW: usize = 256;

/// The line and the server at its end.
#[derive(Clone, Debug)]
pub struct RtuLine {
    server: Server,
    char_us: u64,
    /// Bytes read from the link with their stamps (µs, virtual), not yet delivered.
    waiting: VecDeque<(u8, u64)>,
    /// The last byte's stamp (waiting or delivered).
    last_stamp_us: Option<u64>,
    /// Reply characters on the wire with the time each one's stop bit ends (µs).
    tx: VecDeque<(u8, u64)>,
}

impl RtuLine {
    /// A line at `settings`' baud rate into a server with `settings`.
    pub fn new(settings: ModbusSettings) -> Self {
        let server = Server::new(settings);
        Self {
            char_us: u64::from(server.settings().char_us()),
            server,
            waiting: VecDeque::new(),
            last_stamp_us: None,
            tx: VecDeque::new(),
        }
    }

    /// Put `reply` on the wire at `now_us`: its characters one character time apart,
    /// after any still being sent.
    pub fn send(&mut self, reply: &[u8], now_us: u64) {
        let mut t = self.tx.back().map_or(now_us, |&(_, t)| t.max(now_us));
        for &b in reply {
            t += self.char_us;
            self.tx.push_back((b, t));
        }
    }

    /// The reply characters whose stop bit has ended by `now_us` (to write to the link).
    pub fn transmit(&mut self, now_us: u64) -> Vec<u8> {
        let mut out = Vec::new();
        while let Some(&(b, t)) = self.tx.front() {
            if t > now_us {
                break;
            }
            out.push(b);
            self.tx.pop_front();
        }
        out
    }

    /// Reply characters still on the wire.
    pub fn sending(&self) -> usize {
        self.tx.len()
    }

    /// The client left: what it sent that the server has not taken, and the reply still
    /// on the wire, are gone with it.
    pub fn drop_client(&mut self) {
        self.waiting.clear();
        self.tx.clear();
    }

    /// How many more bytes may be read from the link now (0: leave them there).
    pub fn room(&self) -> usize {
        RX_WINDOW.saturating_sub(self.waiting.len())
    }

    /// Bytes waiting for their stamps.
    pub fn waiting(&self) -> usize {
        self.waiting.len()
    }

    /// `bytes` read from the link at virtual time `now_us`: stamped back to back, the
    /// first one character after the previous byte or after `now_us`, whichever is
    /// later. Bytes beyond [`RtuLine::room`] are queued all the same (the caller reads
    /// no more than the room).
    pub fn receive(&mut self, bytes: &[u8], now_us: u64) {
        for &b in bytes {
            let start = self.last_stamp_us.map_or(now_us, |l| l.max(now_us));
            let t = start + self.char_us;
            self.waiting.push_back((b, t));
            self.last_stamp_us = Some(t);
        }
    }

    /// After a tick at `now_us`: deliver the bytes whose stamps have passed, then poll
    /// the server; the replies to send (usually one frame or nothing). A frame that
    /// ended before the next byte began is polled at that byte's start, so a second
    /// request delivered in the same tick does not overrun the first.
    pub fn service<B: Bsp>(
        &mut self,
        now_us: u64,
        ctrl: &mut Controller<B>,
        unit_serial: &str,
    ) -> Vec<u8> {
        let mut out = Vec::new();
        while let Some(&(b, t)) = self.waiting.front() {
            if t > now_us {
                break;
            }
            if let Some(r) = self
                .server
                .poll(t.saturating_sub(self.char_us), ctrl, unit_serial)
            {
                out.extend_from_slice(r);
            }
            self.server.on_byte(b, t);
            self.waiting.pop_front();
        }
        if let Some(r) = self.server.poll(now_us, ctrl, unit_serial) {
            out.extend_from_slice(r);
        }
        out
    }

    /// The server's counters.
    pub fn stats(&self) -> ModbusStats {
        self.server.stats()
    }

    /// The server.
    pub fn server(&self) -> &Server {
        &self.server
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rig::{Rig, RigOptions};
    use docking_logic::modbus::crc16;

    fn frame(body: &[u8]) -> Vec<u8> {
        let mut f = body.to_vec();
        f.extend_from_slice(&crc16(body).to_le_bytes());
        f
    }

    /// Tick until a reply (or `max_ticks`); the reply and the virtual time it came, µs.
    fn run(rig: &mut Rig, line: &mut RtuLine, max_ticks: usize) -> (Vec<u8>, u64) {
        for _ in 0..max_ticks {
            rig.tick();
            let now = rig.clock.now_ns() / 1_000;
            let r = line.service(now, &mut rig.ctrl, UNIT_SERIAL);
            if !r.is_empty() {
                return (r, now);
            }
        }
        (Vec::new(), rig.clock.now_ns() / 1_000)
    }

    #[test]
    fn a_request_is_answered_within_a_tick_of_its_t3_5_silence() {
        let mut rig = Rig::new(RigOptions::new(80));
        let mut line = RtuLine::new(ModbusSettings::DEFAULT);
        for _ in 0..10 {
            rig.tick();
        }
        let t0 = rig.clock.now_ns() / 1_000;
        let req = frame(&[1, 0x04, 0, 67, 0, 1]);
        line.receive(&req, t0);
        assert_eq!(line.waiting(), req.len());
        assert_eq!(line.room(), RX_WINDOW - req.len());
        let (reply, at) = run(&mut rig, &mut line, 100);
        assert_eq!(
            reply,
            frame(&[1, 0x04, 2, 0, docking_logic::modbus::MAP_VERSION as u8]),
            "the map version"
        );
        let silent_from = t0 + req.len() as u64 * 573;
        assert!(at >= silent_from + 2_006, "{at} {silent_from}");
        assert!(at <= silent_from + 2_006 + 12_500, "{at} {silent_from}");
        assert_eq!(line.waiting(), 0);
        assert_eq!(line.stats().replies, 1);
    }

    #[test]
    fn a_request_in_pieces_far_apart_is_discarded_and_the_next_answered() {
        let mut rig = Rig::new(RigOptions::new(80));
        let mut line = RtuLine::new(ModbusSettings::DEFAULT);
        let req = frame(&[1, 0x04, 0, 67, 0, 1]);
        line.receive(&req[..3], 0);
        line.receive(&req[3..], 5_000);
        let (reply, _) = run(&mut rig, &mut line, 20);
        assert!(reply.is_empty());
        assert_eq!(line.stats().framing_errors, 1);
        let now = rig.clock.now_ns() / 1_000;
        line.receive(&req, now);
        let (reply, _) = run(&mut rig, &mut line, 20);
        assert_eq!(
            reply,
            frame(&[1, 0x04, 2, 0, docking_logic::modbus::MAP_VERSION as u8])
        );
    }

    #[test]
    fn a_reply_takes_the_wire_time_of_its_length() {
        let mut line = RtuLine::new(ModbusSettings::DEFAULT);
        let reply = vec![0x55u8; 141];
        line.send(&reply, 1_000);
        // 141 characters of 573 µs: 80.8 ms on a 19 200-baud line.
        assert!(line.transmit(1_000 + 573 - 1).is_empty());
        assert_eq!(line.transmit(1_000 + 573), [0x55]);
        assert_eq!(line.transmit(1_000 + 40_000).len(), 68);
        assert_eq!(line.sending(), 141 - 69);
        assert_eq!(line.transmit(1_000 + 141 * 573).len(), 141 - 69);
        // A second reply queued while the first is on the wire follows it.
        line.send(&[1, 2], 0);
        line.send(&[3], 0);
        assert_eq!(line.transmit(3 * 573), [1, 2, 3]);
    }

    #[test]
    fn what_a_departed_client_left_does_not_reach_the_next_one() {
        let mut rig = Rig::new(RigOptions::new(80));
        let mut line = RtuLine::new(ModbusSettings::DEFAULT);
        let req = frame(&[1, 0x04, 0, 67, 0, 1]);
        line.receive(&req, 0);
        line.send(&[9; 20], 0);
        line.drop_client();
        assert_eq!(line.waiting(), 0);
        assert_eq!(line.sending(), 0);
        assert!(line.service(50_000, &mut rig.ctrl, UNIT_SERIAL).is_empty());
        assert!(line.transmit(1_000_000).is_empty());
    }

    #[test]
    fn two_requests_delivered_in_one_tick_are_both_answered() {
        let mut rig = Rig::new(RigOptions::new(80));
        let mut line = RtuLine::new(ModbusSettings::DEFAULT);
        let req = frame(&[1, 0x04, 0, 67, 0, 1]);
        line.receive(&req, 0);
        // The second read 10 ms later: after a silence.
        line.receive(&req, 10_000);
        let mut replies = Vec::new();
        // One long tick covering both.
        let r = line.service(50_000, &mut rig.ctrl, UNIT_SERIAL);
        replies.extend(r);
        let one = frame(&[1, 0x04, 2, 0, docking_logic::modbus::MAP_VERSION as u8]);
        assert_eq!(replies, [one.clone(), one].concat());
        assert_eq!(line.stats().overruns, 0);
    }
}
