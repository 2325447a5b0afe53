//! `hil-sim serve --modbus-tcp`: a PLC talks Modbus RTU to the live simulator through a
//! loopback TCP port carrying raw RTU frames (a transparent serial-to-Ethernet
//! gateway), with a real Modbus client (`rmodbus`) building the requests and parsing
//! the replies; and the PLC's hard-wired inputs on stdin.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use docking_logic::modbus::{crc16, ir, status, PRODUCT_CODE, REVISION, VENDOR_NAME};
use rmodbus::client::ModbusRequest;
use rmodbus::{ErrorKind, ModbusProto};

/// How long a reply may take on a loaded machine (the simulator answers within a tick:
/// under a millisecond of wall time at `--speed 20`).
const REPLY_TIMEOUT: Duration = Duration::from_secs(10);
/// How long the machine may take to get somewhere (a docking is ~25 s of virtual time,
/// ~1.3 s of wall time at `--speed 20`).
const MOTION_TIMEOUT: Duration = Duration::from_secs(40);

/// The simulator; killed when dropped.
struct Server {
    child: Child,
    stdin: ChildStdin,
    lines: mpsc::Receiver<String>,
    errors: mpsc::Receiver<String>,
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Lines of `r`, read by a thread.
fn line_reader(r: impl Read + Send + 'static) -> mpsc::Receiver<String> {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(r).lines() {
            let Ok(line) = line else { break };
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    rx
}

impl Server {
    fn start(args: &[&str]) -> Self {
        Self::start_at(args, "20")
    }

    /// At `speed` × real time.
    fn start_at(args: &[&str], speed: &str) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
            .arg("serve")
            .args(args)
            .args(["--speed", speed, "--for", "120"])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        let stdin = child.stdin.take().unwrap();
        let lines = line_reader(child.stdout.take().unwrap());
        let errors = line_reader(child.stderr.take().unwrap());
        Self {
            child,
            stdin,
            lines,
            errors,
        }
    }

    fn line(&self) -> String {
        self.lines
            .recv_timeout(REPLY_TIMEOUT)
            .expect("a line on stdout")
    }

    /// Send a command on stdin.
    fn say(&mut self, cmd: &str) {
        writeln!(self.stdin, "{cmd}").unwrap();
        self.stdin.flush().unwrap();
    }

    /// `plc` until `pred` holds for its line; the line.
    fn plc_until(&mut self, pred: impl Fn(&str) -> bool) -> String {
        let deadline = Instant::now() + MOTION_TIMEOUT;
        loop {
            self.say("plc");
            let l = self.line();
            assert!(l.starts_with("plc dock="), "{l}");
            if pred(&l) {
                return l;
            }
            assert!(Instant::now() < deadline, "timed out; last {l}");
            std::thread::sleep(Duration::from_millis(50));
        }
    }
}

/// Start the simulator with a console and a Modbus link on loopback TCP; connect.
fn start_with_modbus() -> (Server, Plc) {
    start_with_modbus_at("20")
}

/// The same at `speed` × real time.
fn start_with_modbus_at(speed: &str) -> (Server, Plc) {
    let server = Server::start_at(
        &["--tcp", "127.0.0.1:0", "--modbus-tcp", "127.0.0.1:0"],
        speed,
    );
    let console = server.line();
    assert!(console.starts_with("127.0.0.1:"), "{console}");
    let second = server.line();
    let addr = second
        .strip_prefix("modbus ")
        .unwrap_or_else(|| panic!("second line is 'modbus ADDRESS': {second:?}"));
    assert!(addr.starts_with("127.0.0.1:"), "{addr}");
    assert_ne!(addr, console);
    let stream = TcpStream::connect(addr).unwrap();
    stream.set_nodelay(true).unwrap();
    (server, Plc { stream })
}

/// A Modbus RTU master on the gateway's TCP stream.
struct Plc {
    stream: TcpStream,
}

/// Unit address of the simulator's server.
const UNIT: u8 = 1;

impl Plc {
    /// Send `req` (one write, as one packet); the reply, read until `complete` says it
    /// is whole. Panics on a timeout.
    fn transact(&mut self, req: &[u8], complete: impl Fn(&[u8]) -> bool) -> Vec<u8> {
        self.stream.write_all(req).unwrap();
        self.read_reply(REPLY_TIMEOUT, complete)
            .unwrap_or_else(|got| panic!("no whole reply to {req:02X?}; got {got:02X?}"))
    }

    /// Read until `complete` (or an exception reply, 5 bytes) or `timeout`: `Err` with
    /// what came.
    fn read_reply(
        &mut self,
        timeout: Duration,
        complete: impl Fn(&[u8]) -> bool,
    ) -> Result<Vec<u8>, Vec<u8>> {
        let deadline = Instant::now() + timeout;
        let mut buf = Vec::new();
        loop {
            let is_exception = buf.len() >= 2 && buf[1] & 0x80 != 0;
            if (is_exception && buf.len() >= 5) || (!is_exception && complete(&buf)) {
                return Ok(buf);
            }
            let left = deadline.saturating_duration_since(Instant::now());
            if left.is_zero() {
                return Err(buf);
            }
            self.stream.set_read_timeout(Some(left)).unwrap();
            let mut chunk = [0u8; 256];
            match self.stream.read(&mut chunk) {
                Ok(0) => return Err(buf),
                Ok(n) => buf.extend_from_slice(&chunk[..n]),
                Err(e)
                    if matches!(
                        e.kind(),
                        std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                    ) =>
                {
                    return Err(buf)
                }
                Err(e) => panic!("{e}"),
            }
        }
    }

    /// Read `count` input registers from `reg` (rmodbus builds and parses).
    fn try_inputs(&mut self, reg: u16, count: u16) -> Result<Vec<u16>, ErrorKind> {
        let mut mreq = ModbusRequest::new(UNIT, ModbusProto::Rtu);
        let mut req = Vec::new();
        mreq.generate_get_inputs(reg, count, &mut req).unwrap();
        let len = 5 + 2 * usize::from(count);
        let reply = self.transact(&req, |b| b.len() >= len);
        let mut words = Vec::new();
        mreq.parse_u16(&reply, &mut words)?;
        assert_eq!(words.len(), usize::from(count));
        Ok(words)
    }

    fn inputs(&mut self, reg: u16, count: u16) -> Vec<u16> {
        self.try_inputs(reg, count).unwrap()
    }

    /// A u32 register pair (high word first), through rmodbus' 32-bit parser.
    fn input_u32(&mut self, reg: u16) -> u32 {
        let mut mreq = ModbusRequest::new(UNIT, ModbusProto::Rtu);
        let mut req = Vec::new();
        mreq.generate_get_inputs(reg, 2, &mut req).unwrap();
        let reply = self.transact(&req, |b| b.len() >= 9);
        let mut v: Vec<u32> = Vec::new();
        mreq.parse_u32_be(&reply, &mut v).unwrap();
        v[0]
    }

    fn status(&mut self) -> u16 {
        self.inputs(ir::STATUS, 1)[0]
    }

    /// Poll the status word until `bit` is set.
    fn wait_for(&mut self, bit: u16, what: &str) -> u16 {
        let deadline = Instant::now() + MOTION_TIMEOUT;
        loop {
            let s = self.status();
            if s & bit != 0 {
                return s;
            }
            assert!(
                Instant::now() < deadline,
                "timed out waiting for {what}; status {s:#06x}, state {}",
                self.inputs(ir::STATE, 1)[0]
            );
            std::thread::sleep(Duration::from_millis(50));
        }
    }

    fn set_coil(&mut self, coil: u16, on: bool) {
        let mut mreq = ModbusRequest::new(UNIT, ModbusProto::Rtu);
        let mut req = Vec::new();
        mreq.generate_set_coil(coil, on, &mut req).unwrap();
        let reply = self.transact(&req, |b| b.len() >= 8);
        mreq.parse_ok(&reply).unwrap();
        assert_eq!(reply, req, "a write single coil reply echoes the request");
    }

    fn set_holding(&mut self, reg: u16, value: u16) {
        let mut mreq = ModbusRequest::new(UNIT, ModbusProto::Rtu);
        let mut req = Vec::new();
        mreq.generate_set_holding(reg, value, &mut req).unwrap();
        let reply = self.transact(&req, |b| b.len() >= 8);
        mreq.parse_ok(&reply).unwrap();
        assert_eq!(reply, req);
    }
}

/// With the RTU CRC (low byte first).
fn with_crc(body: &[u8]) -> Vec<u8> {
    let mut f = body.to_vec();
    f.extend_from_slice(&crc16(body).to_le_bytes());
    f
}

/// A Read Device Identification reply (0x2B / 0x0E) is whole: its objects all there,
/// and the CRC after them.
fn device_id_complete(b: &[u8]) -> bool {
    if b.len() < 8 {
        return false;
    }
    let mut pos = 8;
    for _ in 0..b[7] {
        match b.get(pos + 1) {
            Some(&len) => pos += 2 + usize::from(len),
            None => return false,
        }
    }
    b.len() >= pos + 2
}

/// Parse a device identification reply by hand (rmodbus' client has no 0x2B): the
/// objects (id, value), checking the CRC and the header.
fn parse_device_id(reply: &[u8], code: u8) -> Vec<(u8, String)> {
    let (body, crc) = reply.split_at(reply.len() - 2);
    assert_eq!(crc16(body).to_le_bytes(), crc, "reply CRC: {reply:02X?}");
    assert_eq!(&body[..4], &[UNIT, 0x2B, 0x0E, code], "{reply:02X?}");
    assert_eq!(body[4], 0x83, "conformity level");
    assert_eq!((body[5], body[6]), (0x00, 0x00), "all in one reply");
    let mut objects = Vec::new();
    let mut pos = 8;
    for _ in 0..body[7] {
        let (id, len) = (body[pos], usize::from(body[pos + 1]));
        let value = &body[pos + 2..pos + 2 + len];
        objects.push((id, String::from_utf8(value.to_vec()).unwrap()));
        pos += 2 + len;
    }
    assert_eq!(pos, body.len(), "nothing after the objects");
    objects
}

#[test]
fn a_plc_identifies_the_unit_and_gets_its_errors_over_modbus_rtu() {
    let (_server, mut plc) = start_with_modbus();

    // (a) Read Device Identification, extended stream from object 0, built by hand.
    let req = with_crc(&[UNIT, 0x2B, 0x0E, 0x03, 0x00]);
    let reply = plc.transact(&req, device_id_complete);
    let objects = parse_device_id(&reply, 0x03);
    let get = |id: u8| {
        objects
            .iter()
            .find(|(i, _)| *i == id)
            .map(|(_, v)| v.as_str())
            .unwrap_or_else(|| panic!("object {id:#04x} missing: {objects:?}"))
    };
    assert_eq!(get(0x00), VENDOR_NAME);
    assert_eq!(get(0x01), PRODUCT_CODE);
    assert_eq!(get(0x02), REVISION);
    assert_eq!(get(0x80), "HILSIM-0001");
    // Individual access to the serial number.
    let reply = plc.transact(
        &with_crc(&[UNIT, 0x2B, 0x0E, 0x04, 0x80]),
        device_id_complete,
    );
    assert_eq!(
        parse_device_id(&reply, 0x04),
        vec![(0x80, "HILSIM-0001".to_string())]
    );

    // (b) The counters of a new machine: no cycles yet, a new cone, wear not at a level.
    let fw = plc.inputs(ir::FW_MAJOR, 4);
    assert_eq!(fw[3], docking_logic::modbus::MAP_VERSION);
    assert_eq!(plc.input_u32(ir::LIFETIME_CYCLES), 0);
    let wear = plc.inputs(
        ir::LIFETIME_CYCLES,
        ir::WEAR_LIMIT_UM - ir::LIFETIME_CYCLES + 1,
    );
    let at = |reg: u16| wear[usize::from(reg - ir::LIFETIME_CYCLES)];
    let pair = |reg: u16| u32::from(at(reg)) << 16 | u32::from(at(reg + 1));
    assert_eq!(pair(ir::CONE_CYCLES), 0);
    assert_eq!(pair(ir::WEAR_NM), 0);
    assert_eq!(at(ir::WEAR_LEVEL), 0);
    assert!(pair(ir::REMAINING_CYCLES) > 0, "{wear:?}");
    assert!(at(ir::WEAR_LIMIT_UM) > 0, "{wear:?}");
    assert_eq!(plc.inputs(ir::CONE_ID, 1), [1]);

    // (d) A wrong CRC: no reply (the PLC's timeout).
    let mut bad = with_crc(&[UNIT, 0x04, 0x00, 0x00, 0x00, 0x01]);
    bad[6] ^= 0xFF;
    plc.stream.write_all(&bad).unwrap();
    let got = plc.read_reply(Duration::from_millis(1_500), |b| !b.is_empty());
    assert_eq!(got, Err(vec![]), "no reply to a bad CRC");

    // An address outside the map: exception 02, as rmodbus' client reads it.
    assert_eq!(
        plc.try_inputs(ir::COUNT, 1),
        Err(ErrorKind::IllegalDataAddress)
    );
    assert_eq!(
        plc.try_inputs(ir::COUNT - 1, 2),
        Err(ErrorKind::IllegalDataAddress)
    );
    // And on the wire: 01 84 02 + CRC.
    let req = with_crc(&[UNIT, 0x04, 0x01, 0x00, 0x00, 0x01]);
    assert_eq!(plc.transact(&req, |_| false), with_crc(&[UNIT, 0x84, 0x02]));

    // The line still works after all that.
    assert_eq!(
        plc.inputs(ir::MAP_VERSION, 1),
        [docking_logic::modbus::MAP_VERSION]
    );
}

#[test]
fn a_plc_docks_and_undocks_over_modbus_rtu_and_the_cycle_counts() {
    let (_server, mut plc) = start_with_modbus();
    // Boot: homed, locked, READY (no automatic cycles with a Modbus link).
    let s = plc.wait_for(status::READY, "READY after boot");
    assert_eq!(
        s & (status::MATED | status::FAULT | status::DOCKING),
        0,
        "{s:#06x}"
    );
    assert_eq!(plc.input_u32(ir::LIFETIME_CYCLES), 0);
    // Nothing moves by itself.
    std::thread::sleep(Duration::from_millis(300));
    let s = plc.status();
    assert!(
        s & status::READY != 0 && s & status::DOCKING == 0,
        "{s:#06x}"
    );

    // Dock through the coil.
    plc.set_coil(0, true);
    assert_eq!(plc.inputs(ir::LAST_COMMAND, 2), [1, 0], "dock accepted");
    let s = plc.wait_for(status::MATED, "MATED");
    assert!(
        s & status::DOCKING != 0 && s & status::READY == 0,
        "{s:#06x}"
    );
    // A second dock is refused: exception 01 (the wrong state), "not idle" in input register 9.
    let mut mreq = ModbusRequest::new(UNIT, ModbusProto::Rtu);
    let mut req = Vec::new();
    mreq.generate_set_coil(0, true, &mut req).unwrap();
    let reply = plc.transact(&req, |b| b.len() >= 8);
    assert_eq!(
        mreq.parse_ok(&reply),
        Err(ErrorKind::IllegalFunction),
        "{reply:02X?}"
    );
    assert_eq!(plc.inputs(ir::LAST_COMMAND, 2), [1, 2]);

    // Undock through the command register.
    plc.set_holding(0, 2);
    assert_eq!(plc.inputs(ir::LAST_COMMAND, 2), [2, 0], "undock accepted");
    let s = plc.wait_for(status::READY, "READY after undocking");
    assert_eq!(
        s & (status::MATED | status::FAULT | status::DOCKING),
        0,
        "{s:#06x}"
    );
    assert_eq!(plc.input_u32(ir::LIFETIME_CYCLES), 1);
    assert_eq!(plc.input_u32(ir::CONE_CYCLES), 1);
    assert!(plc.input_u32(ir::WEAR_NM) > 0, "one cycle wears the cone");
}

#[test]
fn the_plc_inputs_on_stdin_reach_the_handshake() {
    let started = Instant::now();
    let mut server = Server::start(&["--tcp", "127.0.0.1:0", "--plc"]);
    assert!(server.line().starts_with("127.0.0.1:"));

    server.plc_until(|l| l == "plc dock=off estop=closed ready=1 mated=0 fault=0 maintenance=0");
    server.say("fly away");
    let err = server
        .errors
        .recv_timeout(REPLY_TIMEOUT)
        .expect("a line on stderr");
    assert!(err.contains("unknown command 'fly away'"), "{err}");

    // DOCK asserted: the machine docks; released: it undocks.
    server.say("dock on");
    server.say("plc");
    let l = server.line();
    assert!(l.starts_with("plc dock=on estop=closed ready=0 "), "{l}");
    server.plc_until(|l| l.contains(" mated=1 "));
    server.say("dock off");
    server.plc_until(|l| l == "plc dock=off estop=closed ready=1 mated=0 fault=0 maintenance=0");

    // E-STOP open: the next report has it, and the fault it latched.
    server.say("estop open");
    server.say("plc");
    let l = server.line();
    assert_eq!(
        l, "plc dock=off estop=open ready=0 mated=0 fault=1 maintenance=0",
        "{l}"
    );
    // Closing it does not clear the fault.
    server.say("estop close");
    server.say("plc");
    let l = server.line();
    assert_eq!(
        l, "plc dock=off estop=closed ready=0 mated=0 fault=1 maintenance=0",
        "{l}"
    );
    assert!(server.errors.try_recv().is_err(), "nothing else on stderr");
    assert!(started.elapsed() < Duration::from_secs(60));
}

#[test]
fn serve_refuses_bad_modbus_arguments() {
    for args in [
        &["serve", "--modbus-tcp", "10.0.0.1:502"][..],
        &["serve", "--modbus-tcp", "nonsense"],
        &["serve", "--modbus-pty", "--modbus-tcp", "127.0.0.1:0"],
        &["serve", "--modbus-tcp"],
        &["serve", "--plc", "yes"],
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
            .args(args)
            .stdin(Stdio::null())
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(err.lines().count(), 1, "{args:?}: {err}");
        assert!(out.stdout.is_empty(), "{args:?}: nothing opened");
    }
}

/// The line as the bus has it: a request whose halves arrive with a pause between them
/// (longer than t1.5, 0.86 ms at 19 200 baud) is discarded; the same request whole is
/// answered. Bytes were stamped at the last tick's time, so at real time a 5 ms pause
/// (shorter than the 12.5 ms tick) went unseen and the split request was answered.
#[test]
fn a_request_split_by_a_pause_is_discarded_as_on_the_wire() {
    let (_server, mut plc) = start_with_modbus_at("1");
    let req = with_crc(&[UNIT, 0x04, 0, ir::MAP_VERSION as u8, 0, 1]);
    let complete = |b: &[u8]| b.len() >= 7;
    // The server is up: a whole request is answered.
    plc.transact(&req, complete);
    plc.stream.write_all(&req[..4]).unwrap();
    std::thread::sleep(Duration::from_millis(5));
    plc.stream.write_all(&req[4..]).unwrap();
    let got = plc.read_reply(Duration::from_millis(800), complete);
    assert!(got.is_err(), "a split request was answered: {got:02X?}");
    assert_eq!(plc.transact(&req, complete).len(), 7);
}

/// A client that left: the request it sent and the reply to it are not handed to the
/// next client.
#[test]
fn what_a_departed_modbus_client_left_does_not_reach_the_next() {
    let (server, mut plc) = start_with_modbus();
    let req = with_crc(&[UNIT, 0x04, 0, ir::MAP_VERSION as u8, 0, 1]);
    let complete = |b: &[u8]| b.len() >= 7;
    plc.transact(&req, complete);
    let addr = plc.stream.peer_addr().unwrap();
    // Ask, and leave before the reply.
    plc.stream.write_all(&req).unwrap();
    drop(plc);
    std::thread::sleep(Duration::from_millis(1_000));
    let stream = TcpStream::connect(addr).unwrap();
    let mut next = Plc { stream };
    let stale = next.read_reply(Duration::from_millis(800), complete);
    assert_eq!(
        stale,
        Err(Vec::new()),
        "the next client got a reply it did not ask for"
    );
    assert_eq!(next.transact(&req, complete).len(), 7);
    drop(server);
}
