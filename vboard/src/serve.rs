//! `vboard serve`: the image in (scaled) real time, its USART2 on a pseudo-terminal or a
//! loopback TCP port, so a technician talks to the real firmware with picocom, like
//! `hil-sim serve` talks to the library. The machine docks whenever it is at rest.
//!
//! The far end sends at the line rate (115 200 baud) with no flow control, as a
//! terminal does: a paste longer than the firmware's receive ring can absorb is partly
//! lost, as on the board.
//!
//! ## The PLC's side
//!
//! With `--modbus-pty` / `--modbus-tcp`, USART3 (the firmware's Modbus RTU server,
//! 19 200 8E1, unit 1 on a fresh board) goes on a second link carrying raw RTU frames
//! (no MBAP header), as a transparent serial-to-Ethernet gateway would; the second line
//! on stdout is `modbus ADDRESS`.
//!
//! * The client's bytes go onto the line at its character time (11 bits at 19 200
//!   baud, in virtual time, from the moment they are read): a frame read in one piece
//!   arrives back to back, never faster than the wire; pieces read far apart arrive
//!   with the silence between them (the firmware discards a request split by more than
//!   t1.5). At most [`RX_WINDOW`] bytes wait for the wire; the rest stay in the link.
//!   Bytes sent while the firmware's transceiver drives the bus (DE high: a collision)
//!   or before the firmware has set up USART3's RX pin (booting) are lost, as on the
//!   bus; each loss is one line on stderr.
//! * What reaches the client is what reached the bus: the bytes USART3 sent while DE
//!   (PB14) was high, as each one's stop bit ends. A byte sent with DE low never
//!   reaches the bus, so never the client; each such loss is one line on stderr (a
//!   firmware defect).
//! * One client at a time (a second TCP client is closed at once, with no text: on a
//!   bus it would be noise). A client that closes its side is served until the line
//!   has been quiet for 0.5 s (wall; its reply may still be coming, as with `nc -N`),
//!   then let go. One whose connection fails (a reset: it closed with a reply unread)
//!   is let go at once and takes its line with it: its bytes not yet on the wire are
//!   dropped, and so is the rest of a reply to it. Either way the next client's bytes
//!   are not read until the line has been quiet for [`HANDOVER_PS`] (virtual), and it
//!   gets only the replies that come after its first bytes reached the line.
//!
//! With a Modbus link or `--plc`, the PLC is in charge, as in `hil-sim serve`: no
//! automatic cycles, and the PLC's hard-wired inputs are lines on stdin (`dock on|off`,
//! `estop open|close`, `plc`: [`hil_sim::serve::PlcCommand`]); `plc` prints
//! [`hil_sim::serve::plc_line`] of the pins (DOCK and E-STOP as the PLC drives them,
//! READY, MATED, FAULT, MAINTENANCE as the firmware drives them) once the control task
//! has run twice since the last input change (DOCK's debounce).

use std::collections::VecDeque;
use std::io::Write;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use docking_logic::controller::Handshake;
use hil_sim::link::Bridge;
use hil_sim::serve::{Link, PlcCommand};

use crate::scene::{Options, Session, CONTROL_EXCEPTION, PS_PER_MS};
use crate::time::PS_PER_S;

/// Most client bytes waiting for the wire (read from the link, not yet arrived).
pub const RX_WINDOW: usize = 256;

/// After a client leaves: how long the line must be quiet (nothing arriving, nothing
/// sent, virtual time) before the next client's bytes are read, ps. The firmware starts
/// a reply about 2 ms after a request's last byte; ten times that covers one to a
/// request the leaving client completed just before it went.
pub const HANDOVER_PS: u64 = 20 * PS_PER_MS;

/// Control task entries after a PLC input change before `plc` answers.
const SETTLE_STEPS: usize = 2;

/// Options.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    /// Link.
    pub link: Link,
    /// The Modbus RTU link (`None`: none).
    pub modbus: Option<Link>,
    /// The PLC is in charge (no automatic cycles; its inputs on stdin) even without a
    /// Modbus link.
    pub plc: bool,
    /// Session.
    pub session: Options,
    /// Virtual seconds per wall second (the emulation may be slower: then it runs as
    /// fast as it can).
    pub speed: f64,
    /// Stop after this many wall seconds.
    pub duration_s: Option<f64>,
}

/// The Modbus link and the state of its handover between clients.
struct ModbusLink {
    bridge: Bridge,
    /// The present client's bytes have reached the line: replies are its.
    owned: bool,
    /// A client left: the next one's bytes wait for a quiet line.
    handover: bool,
    /// The last time the line carried anything (either way) or a client left, ps.
    busy_at_ps: u64,
    /// Losses already reported on stderr.
    de_losses: u64,
    collisions: u64,
}

impl ModbusLink {
    /// One round: the bus's new bytes to the client, the client's bytes to the line.
    fn service(&mut self, s: &mut Session) {
        let now = s.now();
        let soc = s.board.soc_mut();
        // What reached the bus since the last round (drained: `serve` never asks
        // `Session::modbus`, which indexes it).
        let out: Vec<u8> = std::mem::take(&mut soc.modbus_out)
            .into_iter()
            .map(|(_, b)| b)
            .collect();
        if !out.is_empty() {
            self.busy_at_ps = now;
        }
        if soc.modbus_de_losses > self.de_losses {
            eprintln!(
                "vboard serve: {} Modbus byte(s) sent by the firmware with DE (PB14) low never reached the bus",
                soc.modbus_de_losses - self.de_losses
            );
            self.de_losses = soc.modbus_de_losses;
        }
        let pending = soc.usart3.far_pending();
        if pending > 0 {
            self.busy_at_ps = now;
        }
        if self.handover && now >= self.busy_at_ps + HANDOVER_PS {
            self.handover = false;
        }
        // The bytes drained above reached the bus before anything read now.
        let theirs = self.owned;
        if !self.handover {
            let bytes = self.bridge.read(RX_WINDOW.saturating_sub(pending));
            if !bytes.is_empty() {
                if soc.modbus_send(&bytes) {
                    self.owned = true;
                } else if soc.modbus_collisions > self.collisions {
                    eprintln!(
                        "vboard serve: {} Modbus byte(s) from the client lost: the firmware was driving the bus (DE high)",
                        bytes.len()
                    );
                } else {
                    eprintln!(
                        "vboard serve: {} Modbus byte(s) from the client lost: USART3's RX pin is not set up yet (booting)",
                        bytes.len()
                    );
                }
                self.collisions = soc.modbus_collisions;
            }
        }
        self.bridge.reap(pending == 0 && out.is_empty());
        if self.bridge.departed() {
            soc.usart3.far_cancel(now);
            self.owned = false;
            self.handover = true;
            self.busy_at_ps = now;
        }
        // Written after the link was read: a client that reset is seen gone by the
        // read (a write first would take the reset's error, and the read would see a
        // plain end: the linger), so the rest of its reply goes nowhere.
        if theirs && self.owned && !out.is_empty() {
            self.bridge.write(&out);
        }
    }
}

/// The PLC's hard-wired inputs from stdin.
struct Plc {
    lines: mpsc::Receiver<String>,
    commands: VecDeque<PlcCommand>,
    /// DOCK as the PLC drives it.
    dock: bool,
    /// When the PLC's inputs last changed, ps (the control task's entries after it
    /// tell that the firmware has read them).
    changed_at: Option<u64>,
}

impl Plc {
    /// Apply the commands that came; print `plc` lines once the firmware has seen the
    /// inputs.
    fn service(&mut self, s: &mut Session, out: &mut dyn Write) {
        while let Ok(line) = self.lines.try_recv() {
            match PlcCommand::parse(&line) {
                Ok(Some(c)) => self.commands.push_back(c),
                Ok(None) => {}
                Err(e) => eprintln!("vboard serve: {e}"),
            }
        }
        while let Some(&c) = self.commands.front() {
            let entries = &s.board.soc().entry_log.entries;
            match c {
                PlcCommand::Report => {
                    let settled = self.changed_at.is_none_or(|at| {
                        entries
                            .iter()
                            .filter(|&&(e, t)| e == CONTROL_EXCEPTION && t > at)
                            .count()
                            >= SETTLE_STEPS
                    });
                    if !settled {
                        break; // the firmware has not read the change yet
                    }
                    let pins = s.plc_out();
                    let h = Handshake {
                        dock: self.dock,
                        estop: s.machine().estop.is_high(),
                        ready: pins.ready,
                        mated: pins.mated,
                        fault: pins.fault,
                        maintenance: pins.maintenance,
                    };
                    let _ = writeln!(out, "{}", hil_sim::serve::plc_line(&h));
                    let _ = out.flush();
                }
                PlcCommand::Dock(on) => {
                    self.changed_at = Some(s.now());
                    self.dock = on;
                    s.set_dock(on);
                }
                PlcCommand::Estop(open) => {
                    self.changed_at = Some(s.now());
                    s.set_estop(open);
                }
            }
            self.commands.pop_front();
        }
    }
}

/// How far behind the wall clock the board may fall before `serve` says so, wall.
pub const LAG_WARN: Duration = Duration::from_millis(100);

/// The demo's rest between two cycles, machine time: a person may type then.
pub const DEMO_REST_PS: u64 = 10 * PS_PER_S;

/// No demo cycle starts within this much machine time of a byte typed on the console
/// (or while the firmware is in maintenance mode): a technician commissioning the
/// machine finds it at rest once the cycle in progress has ended.
pub const DEMO_PAUSE_PS: u64 = 60 * PS_PER_S;

/// How much history `serve` keeps for what reads it back (pin edges, the control
/// task's entries, the log), machine time: older is forgotten every so often
/// ([`Session::forget_before`]), so memory stays bounded however long it runs.
pub const KEEP_PS: u64 = 10 * PS_PER_S;

/// The pacing: never ahead of the wall clock (× speed); how far behind, since when.
#[derive(Debug, Default)]
struct Pace {
    /// Behind by more than [`LAG_WARN`] since (wall s into the run), and the most.
    behind: Option<(f64, f64)>,
    /// When the last "behind" line was written (wall s).
    said_at: f64,
    /// The worst lag so far (wall s) and when (wall s).
    worst: (f64, f64),
}

impl Pace {
    /// The board stands `lag_s` of wall time behind the clock at `wall_s`: what to say
    /// on stderr, if anything.
    fn observe(&mut self, wall_s: f64, lag_s: f64) -> Option<String> {
        if lag_s > self.worst.0 {
            self.worst = (lag_s, wall_s);
        }
        let warn = LAG_WARN.as_secs_f64();
        match self.behind.as_mut() {
            None if lag_s > warn => {
                self.behind = Some((wall_s, lag_s));
                self.said_at = wall_s;
                Some(format!(
                    "vboard serve: behind real time by {lag_s:.2} s at {wall_s:.1} s (the emulation is slower than the board here)"
                ))
            }
            Some((since, most)) => {
                *most = most.max(lag_s);
                let (since, most) = (*since, *most);
                if lag_s < warn / 2.0 {
                    self.behind = None;
                    Some(format!(
                        "vboard serve: caught up with real time at {wall_s:.1} s (behind since {since:.1} s, by {most:.2} s at most)"
                    ))
                } else if wall_s - self.said_at >= 1.0 {
                    self.said_at = wall_s;
                    Some(format!(
                        "vboard serve: behind real time by {lag_s:.2} s since {since:.1} s"
                    ))
                } else {
                    None
                }
            }
            None => None,
        }
    }
}

/// Run until killed (or `duration_s`); the first line on stdout is the console link's
/// address, the second (with a Modbus link) `modbus ADDRESS`. The board runs in real
/// time (× `speed`), never ahead of the wall clock; when the emulation cannot keep up
/// it says so on stderr (by how much, since when, and when it caught up), and at the
/// end the worst lag.
pub fn run(opts: &ServeOptions, out: &mut dyn Write) -> Result<(), String> {
    if !(opts.speed.is_finite() && opts.speed > 0.0) {
        return Err(format!(
            "--speed must be a positive number, got {}",
            opts.speed
        ));
    }
    if let Some(Link::Tcp(addr)) = &opts.modbus {
        if !addr.ip().is_loopback() {
            return Err(format!(
                "--modbus-tcp must be a loopback address (127.0.0.1:PORT), got {addr}"
            ));
        }
    }
    let mut bridge = Bridge::open(&opts.link, out)?;
    let mut modbus = match &opts.modbus {
        None => None,
        Some(link) => Some(ModbusLink {
            bridge: hil_sim::serve::open_modbus(link, out)?,
            owned: false,
            handover: false,
            busy_at_ps: 0,
            de_losses: 0,
            collisions: 0,
        }),
    };
    let _ = out.flush();
    let mut plc = (modbus.is_some() || opts.plc).then(|| Plc {
        lines: hil_sim::serve::stdin_lines(),
        commands: VecDeque::new(),
        dock: false,
        changed_at: None,
    });
    let mut s = Session::new(opts.session.clone())?;
    let start = Instant::now();
    let mut pace = Pace::default();
    // The demo: when the machine came to rest, and when a byte was last typed.
    let mut rest_since: Option<u64> = None;
    let mut typed_at: Option<u64> = None;
    let mut forgot_at = 0u64;
    loop {
        let wall = start.elapsed().as_secs_f64();
        if opts.duration_s.is_some_and(|d| wall >= d) {
            let soc = s.board.soc();
            eprintln!(
                "vboard serve: {:.1} s of machine time in {wall:.1} s at speed {}; worst lag {:.2} s (at {:.1} s); {} instructions, {} of them in polling loops skipped",
                s.now() as f64 / PS_PER_S as f64,
                opts.speed,
                pace.worst.0,
                pace.worst.1,
                soc.clock.insns(),
                soc.loops.stats.insns,
            );
            return Ok(());
        }
        if let Some(p) = plc.as_mut() {
            p.service(&mut s, out);
        }
        let target = (wall * opts.speed * PS_PER_S as f64) as u64;
        let slice_end = Instant::now() + Duration::from_millis(20);
        while s.now() < target && Instant::now() < slice_end {
            let step = (target - s.now()).min(PS_PER_MS);
            s.run_for(step).map_err(|e| e.to_string())?;
            if plc.is_none() {
                let now = s.now();
                if s.at_rest() {
                    rest_since.get_or_insert(now);
                } else {
                    rest_since = None;
                }
                let rested = rest_since.is_some_and(|t| now >= t + DEMO_REST_PS);
                let quiet = typed_at.is_none_or(|t| now >= t + DEMO_PAUSE_PS);
                if rested && quiet && !s.plc_out().maintenance {
                    s.auto_dock(u32::MAX);
                }
            }
        }
        let lag_s = target.saturating_sub(s.now()) as f64 / PS_PER_S as f64 / opts.speed;
        if let Some(m) = pace.observe(start.elapsed().as_secs_f64(), lag_s) {
            eprintln!("{m}");
        }
        let bytes = bridge.read(256);
        if !bytes.is_empty() {
            typed_at = Some(s.now());
            let _ = s.board.soc_mut().console_send(&bytes);
        }
        let outb: Vec<u8> = std::mem::take(&mut s.board.soc_mut().console_out)
            .into_iter()
            .map(|(_, b)| b)
            .collect();
        bridge.write(&outb);
        // A client that closed its side is let go once the console is quiet: the next
        // one gets the console (it was told `busy` for the rest of the run).
        bridge.reap(bytes.is_empty() && outb.is_empty() && s.board.soc().usart2.far_pending() == 0);
        let _ = bridge.departed();
        if let Some(m) = modbus.as_mut() {
            m.service(&mut s);
        }
        if s.now() >= forgot_at + KEEP_PS {
            forgot_at = s.now();
            s.forget_before(forgot_at.saturating_sub(KEEP_PS));
        }
        if s.now() >= target {
            // The Modbus link is read every millisecond: t1.5 at 19 200 baud is 0.86 ms.
            let nap_ms = if modbus.is_some() { 1 } else { 2 };
            std::thread::sleep(Duration::from_millis(nap_ms));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Pace;

    #[test]
    fn falling_behind_is_said_once_a_second_with_since_when_and_the_worst_is_kept() {
        let mut p = Pace::default();
        assert_eq!(p.observe(1.0, 0.05), None, "within 100 ms: nothing");
        let m = p.observe(2.0, 0.3).unwrap();
        assert!(m.contains("behind real time by 0.30 s at 2.0 s"), "{m}");
        assert_eq!(p.observe(2.5, 0.8), None, "not again within a second");
        let m = p.observe(3.1, 1.2).unwrap();
        assert!(m.contains("by 1.20 s since 2.0 s"), "{m}");
        let m = p.observe(4.0, 0.01).unwrap();
        assert!(
            m.contains("caught up") && m.contains("by 1.20 s at most"),
            "{m}"
        );
        assert_eq!(p.worst, (1.2, 3.1));
    }
}
