//! `hil-sim serve`: the simulated controller in (scaled) real time, its technician
//! console bridged to a pseudo-terminal or a loopback TCP port, so a technician can
//! connect with `picocom`/`screen` (or `nc`) and practise; optionally its Modbus RTU
//! port on a second link, and the PLC's hard-wired inputs on stdin.
//!
//! ## stdout
//!
//! The first line is the console's pty path or bound address. With a Modbus link
//! (`--modbus-pty` / `--modbus-tcp`), the second line is `modbus <pty path or bound
//! address>`. Then only the replies to `plc` (below).
//!
//! ## Console
//!
//! The bridge applies back-pressure: bytes are taken from the link only as fast as the
//! board's 256-byte receive ring drains, so a paste is not lost to an overrun (a real
//! UART without flow control would lose it).
//!
//! ## Modbus RTU
//!
//! The second link carries raw Modbus **RTU** frames (address, PDU, CRC; no MBAP
//! header), as a transparent serial-to-Ethernet gateway would: the bytes go onto a
//! simulated RS-485 line at 19 200 baud 8E1 into the controller's server, unit 1, in
//! virtual time ([`crate::rtu_line`]: timing, one request at a time, back-pressure). A
//! reply comes within a tick (≤ 12.5 ms at 80 SPS, 100 ms at 10 SPS, virtual time) of
//! the request's t3.5 silence. Device identification object 0x80 (the unit's serial
//! number) is [`UNIT_SERIAL`], `HILSIM-0001`. A TCP address must be on loopback; one
//! client at a time.
//!
//! ## PLC inputs on stdin
//!
//! One command a line (surrounding blanks ignored, blank lines ignored):
//!
//! | line | effect |
//! |---|---|
//! | `dock on` / `dock off` | the DOCK line asserted (low) / released (high) |
//! | `estop open` / `estop close` | the E-STOP loop open (a stop) / closed |
//! | `plc` | one line on stdout: `plc dock=on\|off estop=open\|closed ready=0\|1 mated=0\|1 fault=0\|1 maintenance=0\|1` |
//!
//! `plc` prints the controller's handshake ([`Controller::handshake`]: DOCK as
//! filtered, E-STOP as read, and the outputs). A line takes effect at the next tick, and
//! the controller reads DOCK over two control steps (its debounce): a `plc` after a
//! `dock`/`estop` command is answered once two control steps have run since, so
//! `estop open` then `plc` reports the open E-STOP and the fault it latched. Any other
//! line: one line on stderr, and it is ignored. stdin is read by a thread, so the
//! simulation never waits for it; its end (EOF) changes nothing.
//!
//! ## Who starts cycles
//!
//! Without a Modbus link and without `--plc`, the machine docks continuously (a test
//! cycle whenever it is idle), with the scene's disturbance injected in its first
//! cycle. With a Modbus link or `--plc`, the PLC is in charge: **no automatic cycles**;
//! the machine docks when the PLC commands it (Modbus, or DOCK on stdin), and the
//! scene's disturbance comes in the first docking.
//!
//! [`Controller::handshake`]: docking_logic::controller::Controller::handshake

use std::collections::VecDeque;
use std::io::{BufRead, Write};
use std::net::SocketAddr;
use std::sync::mpsc;
use std::time::{Duration, Instant};

use docking_logic::controller::Handshake;
use docking_logic::modbus::ModbusSettings;
use docking_logic::sequencer::{Request, State};

use crate::console::RX_RING;
use crate::link::{Bridge, Pty};
use crate::rig::{AdcMode, Rig, RigOptions};
use crate::rtu_line::RtuLine;
pub use crate::rtu_line::UNIT_SERIAL;
use crate::scene::SceneDriver;

/// Where the console goes.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Link {
    /// A new pseudo-terminal (its path is printed).
    Pty,
    /// A TCP listener on a loopback address (the bound address is printed).
    Tcp(SocketAddr),
}

/// Options.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    /// Link.
    pub link: Link,
    /// The Modbus RTU link (`None`: no Modbus).
    pub modbus: Option<Link>,
    /// The PLC is in charge (no automatic cycles) even without a Modbus link.
    pub plc: bool,
    /// Scene whose disturbance to inject.
    pub scene: String,
    /// Virtual seconds per wall second.
    pub speed: f64,
    /// Load-cell rate, SPS.
    pub rate_sps: u32,
    /// Stop after this many wall seconds (`None`: run until killed).
    pub duration_s: Option<f64>,
}

/// A PLC input command from stdin.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum PlcCommand {
    /// DOCK asserted (`true`) or released.
    Dock(bool),
    /// E-STOP open (`true`) or closed.
    Estop(bool),
    /// Print the handshake.
    Report,
}

impl PlcCommand {
    /// Parse one stdin line: `Ok(None)` for a blank line, `Err` (the message for stderr)
    /// for anything unknown.
    pub fn parse(line: &str) -> Result<Option<Self>, String> {
        let words: Vec<&str> = line.split_whitespace().collect();
        Ok(Some(match words.as_slice() {
            [] => return Ok(None),
            ["dock", "on"] => Self::Dock(true),
            ["dock", "off"] => Self::Dock(false),
            ["estop", "open"] => Self::Estop(true),
            ["estop", "close"] => Self::Estop(false),
            ["plc"] => Self::Report,
            _ => {
                return Err(format!(
                    "unknown command '{}' (dock on|off, estop open|close, plc)",
                    line.trim()
                ))
            }
        }))
    }
}

/// The `plc` line for handshake `h`.
pub fn plc_line(h: &Handshake) -> String {
    let b = |x: bool| u8::from(x);
    format!(
        "plc dock={} estop={} ready={} mated={} fault={} maintenance={}",
        if h.dock { "on" } else { "off" },
        if h.estop { "open" } else { "closed" },
        b(h.ready),
        b(h.mated),
        b(h.fault),
        b(h.maintenance)
    )
}

/// Control steps after a PLC input change before `plc` answers (DOCK's debounce).
const SETTLE_STEPS: u64 = 2;

/// Machine time the demo cycling waits after anything typed on the console, ns: a
/// technician commissioning the machine (`pin set` is refused while a docking moves)
/// finds it at rest once the cycle in progress ends.
const DEMO_PAUSE_NS: u64 = 60_000_000_000;

/// The demo's rest between two cycles, machine time, ns: a person may act then.
const DEMO_REST_NS: u64 = 10_000_000_000;

/// Open the Modbus link (a TCP client that comes while another is connected is closed
/// with no text: on a bus it would be noise); its address is printed as
/// `modbus ADDRESS`. Shared with `vboard serve`.
pub fn open_modbus(link: &Link, out: &mut dyn Write) -> Result<Bridge, String> {
    let bridge = match link {
        Link::Pty => Bridge::Pty(Pty::open()?),
        Link::Tcp(addr) => {
            let (listener, _) = crate::link::listen(*addr)?;
            Bridge::Tcp {
                listener,
                client: None,
                closing: None,
                busy: b"",
                departed: false,
                screen: None,
            }
        }
    };
    let _ = writeln!(out, "modbus {}", bridge.address());
    Ok(bridge)
}

/// Lines of stdin, read by a thread (the loop never waits for them). Shared with
/// `vboard serve`.
pub fn stdin_lines() -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in std::io::stdin().lock().lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

/// Run the live simulator; prints the links' addresses first, then runs until killed
/// (or `duration_s`).
pub fn run(opts: &ServeOptions, out: &mut dyn Write) -> Result<(), String> {
    let mut driver = SceneDriver::new(&opts.scene, 1)?;
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
        Some(link) => Some((
            open_modbus(link, out)?,
            RtuLine::new(ModbusSettings::DEFAULT),
        )),
    };
    let _ = out.flush();
    let auto_cycles = modbus.is_none() && !opts.plc;
    let stdin = stdin_lines();
    let mut commands: VecDeque<PlcCommand> = VecDeque::new();
    let mut rig = Rig::new(RigOptions {
        adc: AdcMode::Pins,
        ..RigOptions::new(opts.rate_sps)
    });
    // A board's boot: the reset cause counted and shown (`status`, `faults`).
    rig.ctrl
        .boot(docking_logic::diag::ResetCause::PowerOn, None, &[]);
    rig.console_enabled = true;
    // The unit's serial, as `version` and device identification name it.
    rig.console.set_unit(UNIT_SERIAL);
    driver.setup(rig.devices(), 1, opts.rate_sps, 1_000);
    // Control steps run, and the count at the last PLC input change.
    let mut steps: u64 = 0;
    let mut changed_at: Option<u64> = None;
    let start = Instant::now();
    let mut last_command_ns: Option<u64> = None;
    // When the machine came to rest (the demo rests there), and when a byte was typed.
    let mut idle_since_ns: Option<u64> = None;
    let mut typed = false;
    loop {
        let wall = start.elapsed().as_secs_f64();
        if opts.duration_s.is_some_and(|d| wall >= d) {
            return Ok(());
        }
        // PLC inputs: they take effect at the next tick.
        while let Ok(line) = stdin.try_recv() {
            match PlcCommand::parse(&line) {
                Ok(Some(c)) => commands.push_back(c),
                Ok(None) => {}
                Err(e) => eprintln!("hil-sim serve: {e}"),
            }
        }
        while let Some(&c) = commands.front() {
            match c {
                PlcCommand::Report => {
                    if changed_at.is_some_and(|at| steps < at + SETTLE_STEPS) {
                        break; // the controller has not read the change yet
                    }
                    let _ = writeln!(out, "{}", plc_line(&rig.ctrl.handshake()));
                    let _ = out.flush();
                }
                PlcCommand::Dock(on) => {
                    rig.dock_line.set(!on); // active low
                    changed_at = Some(steps);
                }
                PlcCommand::Estop(open) => {
                    rig.estop_line.set(open);
                    changed_at = Some(steps);
                }
            }
            commands.pop_front();
        }
        let target_ns = (wall * opts.speed * 1e9) as u64;
        while rig.clock.now_ns() < target_ns {
            if rig.tick().stepped {
                steps += 1;
            }
            let st = rig.ctrl.status();
            driver.on_tick(&mut rig, &st);
            // The demo cycling waits while a technician is at the console: in
            // maintenance mode (a console `dock` stays docked until `undock`), and for
            // a while after any command (a `pin set` finds the machine at rest).
            let now_ns = rig.clock.now_ns();
            if rig.last_console.commands > 0 || std::mem::take(&mut typed) {
                last_command_ns = Some(now_ns);
            }
            let technician = rig.console.maintenance_active(now_ns / 1_000_000)
                || last_command_ns.is_some_and(|t| now_ns < t + DEMO_PAUSE_NS);
            if st.state == State::Idle {
                idle_since_ns.get_or_insert(now_ns);
            } else {
                idle_since_ns = None;
            }
            let rested = idle_since_ns.is_some_and(|t| now_ns >= t + DEMO_REST_NS);
            if auto_cycles
                && !technician
                && rested
                && st.state == State::Idle
                && !rig.ctrl.persist_pending()
            {
                rig.ctrl.request(Request::StartCycle);
            }
            if let Some((link, line)) = modbus.as_mut() {
                // The reply goes onto the wire character by character (DE high while
                // it is sent: no flash erase meanwhile, as on the board).
                let now_us = rig.clock.now_ns() / 1_000;
                let reply = line.service(now_us, &mut rig.ctrl, UNIT_SERIAL);
                line.send(&reply, now_us);
                link.write(&line.transmit(now_us));
                rig.ctrl.set_bus_busy(line.sending() > 0);
            }
        }
        let room = RX_RING.saturating_sub(rig.term.rx_pending());
        if room > 0 {
            let bytes = bridge.read(room);
            typed |= !bytes.is_empty();
            rig.term.send(&bytes);
        }
        let output = rig.term.take_output();
        bridge.write(&output);
        bridge.reap(output.is_empty() && rig.term.rx_pending() == 0);
        if let Some((link, line)) = modbus.as_mut() {
            let room = line.room();
            if room > 0 {
                let bytes = link.read(room);
                // Stamped at the machine time of the wall clock now, not of the last
                // tick: a pause between two pieces of a request is seen as it was.
                let wall_us = (start.elapsed().as_secs_f64() * opts.speed * 1e6) as u64;
                line.receive(&bytes, wall_us);
            }
            link.reap(line.sending() == 0 && line.waiting() == 0);
            if link.departed() {
                line.drop_client();
            }
        }
        // The links are read every millisecond (wall) with a Modbus line (its t1.5 is
        // 0.86 ms at 19 200 baud), every 2 ms otherwise.
        let nap_ms = if modbus.is_some() { 1 } else { 2 };
        std::thread::sleep(Duration::from_millis(nap_ms));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plc_commands_parse() {
        assert_eq!(
            PlcCommand::parse("dock on"),
            Ok(Some(PlcCommand::Dock(true)))
        );
        assert_eq!(
            PlcCommand::parse("  dock   off \r"),
            Ok(Some(PlcCommand::Dock(false)))
        );
        assert_eq!(
            PlcCommand::parse("estop open"),
            Ok(Some(PlcCommand::Estop(true)))
        );
        assert_eq!(
            PlcCommand::parse("estop close"),
            Ok(Some(PlcCommand::Estop(false)))
        );
        assert_eq!(PlcCommand::parse("plc"), Ok(Some(PlcCommand::Report)));
        assert_eq!(PlcCommand::parse("   "), Ok(None));
        for bad in [
            "dock",
            "dock maybe",
            "estop closed",
            "plc now",
            "DOCK ON",
            "x",
        ] {
            assert!(PlcCommand::parse(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn plc_line_formats_the_handshake() {
        let h = Handshake {
            dock: true,
            estop: false,
            ready: false,
            mated: true,
            fault: false,
            maintenance: true,
        };
        assert_eq!(
            plc_line(&h),
            "plc dock=on estop=closed ready=0 mated=1 fault=0 maintenance=1"
        );
        assert_eq!(
            plc_line(&Handshake {
                estop: true,
                fault: true,
                ..Handshake::default()
            }),
            "plc dock=off estop=open ready=0 mated=0 fault=1 maintenance=0"
        );
    }
}
