//! `vboard serve`: a technician's terminal talks to the image's USART2 over a loopback
//! TCP port and over a pseudo-terminal, as with `hil-sim serve`.

use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn start(args: &[&str]) -> (Child, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_vboard"))
        .args(["serve", "--for", "60"])
        .args(args)
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("vboard runs");
    let mut line = String::new();
    BufReader::new(child.stdout.as_mut().unwrap())
        .read_line(&mut line)
        .expect("first line: the address");
    (child, line.trim().to_string())
}

/// Send `cmd` and read until a line starting with `want` arrives (the board boots at a
/// third of real time; the first command may meet it still booting).
fn ask(io: &mut (impl Read + Write), cmd: &str, want: &str) -> String {
    let deadline = Instant::now() + Duration::from_secs(40);
    let mut got = String::new();
    let mut last_send = Instant::now() - Duration::from_secs(10);
    while Instant::now() < deadline {
        if last_send.elapsed() > Duration::from_secs(5) {
            io.write_all(format!("{cmd}\r\n").as_bytes()).unwrap();
            last_send = Instant::now();
        }
        let mut buf = [0u8; 512];
        match io.read(&mut buf) {
            Ok(n) if n > 0 => got.push_str(&String::from_utf8_lossy(&buf[..n])),
            _ => std::thread::sleep(Duration::from_millis(20)),
        }
        // Whole lines only: a read can end in the middle of the reply's line (seen on a
        // loaded machine: "docking-controller 0.1." compared as the version).
        if let Some(l) = got
            .split_inclusive('\n')
            .filter(|l| l.ends_with('\n'))
            .find(|l| l.starts_with(want))
        {
            return l.trim_end().to_string();
        }
    }
    panic!("no reply starting {want:?} to {cmd:?}; got {got:?}");
}

#[test]
fn a_terminal_reads_the_version_over_tcp() {
    let (mut child, addr) = start(&["--tcp", "127.0.0.1:0"]);
    let mut s = std::net::TcpStream::connect(&addr).expect("connect");
    s.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let reply = ask(&mut s, "version", "docking-controller ");
    // Then the unit: the chip's 96-bit unique ID (issue 35), in hex.
    let (head, unit) = reply
        .trim()
        .rsplit_once(" unit=")
        .expect("the unit at the end");
    assert_eq!(
        head,
        "docking-controller 0.1.0 (test key) previous=none rolled_back=no trial=no"
    );
    assert!(
        unit.len() == 24 && unit.bytes().all(|c| c.is_ascii_hexdigit()),
        "{reply}"
    );
    let _ = child.kill();
    let _ = child.wait();
}

#[test]
fn a_terminal_reads_wear_as_json_over_a_pty() {
    let (mut child, path) = start(&["--pty"]);
    assert!(path.starts_with("/dev/pts/"), "{path}");
    let mut pty = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&path)
        .expect("open the pty");
    // A non-blocking read would need libc; the board writes often enough (the reply)
    // that a blocking read in a helper thread is simpler.
    let (tx, rx) = std::sync::mpsc::channel::<Vec<u8>>();
    let mut reader = pty.try_clone().unwrap();
    std::thread::spawn(move || {
        let mut buf = [0u8; 512];
        while let Ok(n) = reader.read(&mut buf) {
            if n == 0 || tx.send(buf[..n].to_vec()).is_err() {
                break;
            }
        }
    });
    let deadline = Instant::now() + Duration::from_secs(40);
    let mut got = String::new();
    let mut sent_at = Instant::now() - Duration::from_secs(10);
    let complete = |g: &str| {
        g.split("\r\n")
            .any(|l| l.starts_with("{\"cone\"") && l.ends_with('}'))
    };
    while Instant::now() < deadline && !complete(&got) {
        if sent_at.elapsed() > Duration::from_secs(5) {
            pty.write_all(b"wear --json\r\n").unwrap();
            sent_at = Instant::now();
        }
        if let Ok(b) = rx.recv_timeout(Duration::from_millis(200)) {
            got.push_str(&String::from_utf8_lossy(&b));
        }
    }
    let line = got
        .split("\r\n")
        .find(|l| l.starts_with("{\"cone\"") && l.ends_with('}'))
        .unwrap_or_else(|| panic!("no wear reply; got {got:?}"));
    let v: serde_json::Value = serde_json::from_str(line).expect("JSON");
    assert_eq!(v["material"], "zqsn5-2");
    let _ = child.kill();
    let _ = child.wait();
}

/// A console client that closed its connection cleanly was never let go: its socket
/// stayed in CLOSE-WAIT and every later client was told `busy: another terminal is
/// connected` for the rest of the run.
#[test]
fn a_terminal_that_closed_cleanly_left_the_console_busy_for_the_rest_of_the_run() {
    let (mut child, addr) = start(&["--tcp", "127.0.0.1:0"]);
    let greeting = |s: &mut std::net::TcpStream| {
        s.set_read_timeout(Some(Duration::from_millis(200)))
            .unwrap();
        let deadline = Instant::now() + Duration::from_secs(30);
        let mut got = Vec::new();
        while !got.ends_with(b"> ") && !got.ends_with(b"\n") && Instant::now() < deadline {
            let mut buf = [0u8; 256];
            match s.read(&mut buf) {
                Ok(0) => break,
                Ok(n) => got.extend_from_slice(&buf[..n]),
                Err(_) => {}
            }
        }
        String::from_utf8_lossy(&got).into_owned()
    };
    let mut first = std::net::TcpStream::connect(&addr).expect("connect");
    first
        .set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let reply = ask(&mut first, "version", "docking-controller ");
    assert!(reply.starts_with("docking-controller 0.1.0"), "{reply}");
    drop(first);
    // The next terminal gets the console (once the first is let go: 0.5 s of quiet).
    let deadline = Instant::now() + Duration::from_secs(30);
    loop {
        std::thread::sleep(Duration::from_millis(700));
        let mut next = std::net::TcpStream::connect(&addr).expect("connect");
        let g = greeting(&mut next);
        if g.starts_with("# docking-controller ") {
            break;
        }
        assert!(g.starts_with("busy"), "{g:?}");
        assert!(Instant::now() < deadline, "still busy: {g:?}");
    }
    let _ = child.kill();
    let _ = child.wait();
}

/// Commissioning on the live board was a race lost every time: `pin set` is refused
/// while a docking moves, and the demo docked again as soon as the machine was home
/// (none of 120 tries over two minutes found a rest). The demo rests between cycles and
/// pauses while a terminal types: a technician's `pin set` goes through once the cycle
/// in progress has ended.
#[test]
fn a_technician_could_not_commission_the_live_board_between_demo_cycles() {
    let mut child = Command::new(env!("CARGO_BIN_EXE_vboard"))
        .args([
            "serve",
            "--for",
            "300",
            "--tcp",
            "127.0.0.1:0",
            "--speed",
            "10",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .expect("vboard runs");
    let mut line = String::new();
    BufReader::new(child.stdout.as_mut().unwrap())
        .read_line(&mut line)
        .expect("first line: the address");
    let mut s = std::net::TcpStream::connect(line.trim()).expect("connect");
    s.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    // Let the demo start a cycle (10 s of rest after the boot, then it docks: 3 s of
    // wall time at speed 10 is 30 s of machine time where the machine keeps up), then
    // commission: refused while it moves, through once the cycle has ended.
    std::thread::sleep(Duration::from_secs(3));
    let deadline = Instant::now() + Duration::from_secs(120);
    let mut got = String::new();
    let mut tries = 0;
    let mut sent = Instant::now() - Duration::from_secs(10);
    let done = loop {
        assert!(
            Instant::now() < deadline,
            "no PIN set after {tries} tries; got {got:?}"
        );
        if sent.elapsed() > Duration::from_secs(2) {
            s.write_all(b"pin set 2468\r\n").unwrap();
            sent = Instant::now();
            tries += 1;
        }
        let mut buf = [0u8; 512];
        if let Ok(n) = s.read(&mut buf) {
            got.push_str(&String::from_utf8_lossy(&buf[..n]));
        }
        if let Some(l) = got.split("\r\n").find(|l| l.starts_with("ok: PIN set")) {
            break l.to_string();
        }
    };
    assert!(done.starts_with("ok: PIN set"), "{done}");
    let _ = child.kill();
    let _ = child.wait();
}

/// `vboard serve` with a Modbus link and the PLC's inputs on stdin; killed when dropped.
struct Plc {
    child: Child,
    stdin: std::process::ChildStdin,
    lines: std::sync::mpsc::Receiver<String>,
}

impl Drop for Plc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Plc {
    /// Start it with `args`; returns it, the console's address and the Modbus link's.
    fn start(args: &[&str]) -> (Self, String, String) {
        let mut child = Command::new(env!("CARGO_BIN_EXE_vboard"))
            .args(["serve", "--for", "120"])
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("vboard runs");
        let stdin = child.stdin.take().unwrap();
        let out = child.stdout.take().unwrap();
        let (tx, lines) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for l in BufReader::new(out).lines() {
                let Ok(l) = l else { break };
                if tx.send(l).is_err() {
                    break;
                }
            }
        });
        let mut p = Self {
            child,
            stdin,
            lines,
        };
        let console = p.line();
        let modbus = p.line();
        let modbus = modbus
            .strip_prefix("modbus ")
            .unwrap_or_else(|| panic!("second line: {modbus:?}"))
            .to_string();
        (p, console, modbus)
    }

    fn line(&mut self) -> String {
        self.lines
            .recv_timeout(Duration::from_secs(20))
            .expect("a line on stdout")
    }

    /// `plc` on stdin until its line satisfies `want`.
    fn plc_until(&mut self, want: &str) -> String {
        let deadline = Instant::now() + Duration::from_secs(60);
        while Instant::now() < deadline {
            writeln!(self.stdin, "plc").unwrap();
            let l = self.line();
            assert!(l.starts_with("plc dock="), "{l}");
            if l.split_whitespace().any(|w| w == want) {
                return l;
            }
            std::thread::sleep(Duration::from_millis(200));
        }
        panic!("never {want}");
    }
}

/// A Modbus RTU request: `pdu` for unit 1 and its CRC.
fn rtu(pdu: &[u8]) -> Vec<u8> {
    vboard::scene::rtu(1, pdu)
}

/// Whether `r` is a well-formed RTU frame from unit 1 (its CRC right).
fn well_formed(r: &[u8]) -> bool {
    r.len() >= 4 && r[0] == 1 && rtu(&r[1..r.len() - 2]) == r
}

/// Read `n` bytes (fewer: what came before `timeout`).
fn read_n(s: &mut std::net::TcpStream, n: usize, timeout: Duration) -> Vec<u8> {
    let deadline = Instant::now() + timeout;
    let mut got = Vec::new();
    s.set_read_timeout(Some(Duration::from_millis(50))).unwrap();
    while got.len() < n && Instant::now() < deadline {
        let mut buf = [0u8; 512];
        match s.read(&mut buf) {
            Ok(0) => break,
            Ok(k) => got.extend_from_slice(&buf[..k]),
            Err(_) => {}
        }
    }
    got
}

/// Send `req` until a reply of `len` bytes comes (a request the booting board missed
/// gets none).
fn ask_modbus(s: &mut std::net::TcpStream, req: &[u8], len: usize) -> Vec<u8> {
    let deadline = Instant::now() + Duration::from_secs(40);
    while Instant::now() < deadline {
        s.write_all(req).unwrap();
        let r = read_n(s, len, Duration::from_secs(2));
        if !r.is_empty() {
            return r;
        }
    }
    panic!("no reply to {req:02x?}");
}

#[test]
fn a_plc_reads_input_registers_over_modbus_tcp() {
    use docking_logic::modbus::{ir, MAP_VERSION};
    let (_board, console, modbus) =
        Plc::start(&["--tcp", "127.0.0.1:0", "--modbus-tcp", "127.0.0.1:0"]);
    assert!(console.starts_with("127.0.0.1:"), "{console}");
    let mut s = std::net::TcpStream::connect(&modbus).expect("connect");
    // Read input registers (04): the firmware version and the map's.
    let req = rtu(&[0x04, 0, ir::FW_MAJOR as u8, 0, 4]);
    let r = ask_modbus(&mut s, &req, 13);
    assert!(well_formed(&r), "{r:02x?}");
    assert_eq!(r[..3], [1, 0x04, 8], "{r:02x?}");
    let regs: Vec<u16> = r[3..11]
        .chunks(2)
        .map(|c| u16::from_be_bytes([c[0], c[1]]))
        .collect();
    let version: Vec<u16> = docking_logic::modbus::REVISION
        .split('.')
        .map(|x| x.parse().unwrap())
        .collect();
    assert_eq!(regs[..3], version[..], "{regs:?}");
    assert_eq!(regs[3], MAP_VERSION);

    // A second client is closed at once, with nothing said (on a bus it would be noise).
    let mut second = std::net::TcpStream::connect(&modbus).expect("connect");
    assert_eq!(read_n(&mut second, 1, Duration::from_secs(5)), b"");

    // The request in two pieces 200 ms apart (wall; ≥ 60 ms of machine time even while
    // the board boots): a silence over t1.5 inside it, so the firmware drops it.
    s.write_all(&req[..3]).unwrap();
    std::thread::sleep(Duration::from_millis(200));
    s.write_all(&req[3..]).unwrap();
    assert_eq!(read_n(&mut s, 13, Duration::from_secs(1)), b"");
    assert_eq!(ask_modbus(&mut s, &req, 13), r);

    // A client that leaves while its reply (141 bytes, 81 ms at 19 200 baud) is on the
    // wire: closed with reply bytes unread (one read), its socket resets. The next
    // client, there 10 ms later with its request, gets its own reply and nothing of
    // the other's.
    let all = rtu(&[0x04, 0, 0, 0, ir::COUNT as u8]);
    s.write_all(&all).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
    let mut first = [0u8; 1];
    s.read_exact(&mut first).expect("the reply starts");
    assert_eq!(first, [1]);
    std::thread::sleep(Duration::from_millis(5));
    drop(s);
    let deadline = Instant::now() + Duration::from_secs(10);
    let r2 = loop {
        std::thread::sleep(Duration::from_millis(10));
        let mut next = std::net::TcpStream::connect(&modbus).expect("connect");
        next.write_all(&req).unwrap();
        let got = read_n(&mut next, 13, Duration::from_secs(2));
        // Closed at once: the first was still being let go.
        if !got.is_empty() || Instant::now() > deadline {
            // Anything after its reply would be someone else's.
            let more = read_n(&mut next, 1, Duration::from_millis(300));
            assert_eq!(more, b"", "after {got:02x?}");
            break got;
        }
    };
    assert_eq!(r2, r);
}

#[test]
fn a_plc_docks_the_firmware_over_modbus_and_over_the_dock_line() {
    use docking_logic::modbus::{ir, status};
    let (mut board, _console, modbus) = Plc::start(&[
        "--tcp",
        "127.0.0.1:0",
        "--modbus-tcp",
        "127.0.0.1:0",
        "--speed",
        "10",
    ]);
    let mut s = std::net::TcpStream::connect(&modbus).expect("connect");
    // No automatic cycles: ready, at rest.
    let at_rest = board.plc_until("ready=1");
    assert!(at_rest.contains("mated=0"), "{at_rest}");
    // Dock: coil 0 on (echoed when accepted).
    let dock = rtu(&[0x05, 0, 0, 0xFF, 0]);
    assert_eq!(ask_modbus(&mut s, &dock, dock.len()), dock);
    let mated = board.plc_until("mated=1");
    assert!(mated.starts_with("plc dock=off estop=closed"), "{mated}");
    let st = rtu(&[0x04, 0, ir::STATUS as u8, 0, 1]);
    let r = ask_modbus(&mut s, &st, 7);
    assert!(well_formed(&r), "{r:02x?}");
    assert_ne!(u16::from_be_bytes([r[3], r[4]]) & status::MATED, 0);
    // Undock: coil 1.
    let undock = rtu(&[0x05, 0, 1, 0xFF, 0]);
    assert_eq!(ask_modbus(&mut s, &undock, undock.len()), undock);
    board.plc_until("ready=1");
    // The hard-wired DOCK line.
    writeln!(board.stdin, "dock on").unwrap();
    let mated = board.plc_until("mated=1");
    assert!(mated.starts_with("plc dock=on estop=closed"), "{mated}");
    writeln!(board.stdin, "dock off").unwrap();
    board.plc_until("ready=1");
}

/// CRC-16/MODBUS (polynomial 0xA001 reflected, from 0xFFFF), written here from the
/// serial line specification rather than taken from the firmware's library, so that
/// the pty test below is a client of its own.
fn crc16(bytes: &[u8]) -> u16 {
    let mut crc = 0xFFFFu16;
    for &b in bytes {
        crc ^= u16::from(b);
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
        }
    }
    crc
}

/// A serial Modbus RTU master on a pty: whole frames out, replies read back by a
/// thread until the line has been quiet.
struct PtyMaster {
    port: std::fs::File,
    rx: std::sync::mpsc::Receiver<Vec<u8>>,
}

impl PtyMaster {
    /// Open `path` as a client opens a serial port: 19 200 baud, raw, 8 data bits, no
    /// parity (a pty carries bytes: this kernel refuses PARENB on one, and the 8E1
    /// framing is the board's own, emulated on USART3).
    fn open(path: &str) -> Self {
        let stty = Command::new("stty")
            .args([
                "-F", path, "19200", "raw", "-echo", "cs8", "-parenb", "-cstopb",
            ])
            .status()
            .expect("stty runs");
        assert!(stty.success(), "stty on {path}");
        let port = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(path)
            .expect("open the pty");
        let mut reader = port.try_clone().unwrap();
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let mut buf = [0u8; 512];
            while let Ok(n) = reader.read(&mut buf) {
                if n == 0 || tx.send(buf[..n].to_vec()).is_err() {
                    break;
                }
            }
        });
        Self { port, rx }
    }

    /// Send `pdu` to unit 1 until a reply comes (a request the booting board missed
    /// gets none); returns the reply's PDU after checking its unit and CRC.
    fn ask(&mut self, pdu: &[u8]) -> Vec<u8> {
        let mut req = vec![1u8];
        req.extend_from_slice(pdu);
        req.extend_from_slice(&crc16(&req).to_le_bytes());
        let deadline = Instant::now() + Duration::from_secs(40);
        while Instant::now() < deadline {
            self.port.write_all(&req).unwrap();
            let mut r = Vec::new();
            let mut wait = Duration::from_secs(2);
            // A reply ends with a silence (at a third of real time a 141-byte one
            // takes 0.25 s; its bytes come as each one's stop bit ends).
            while let Ok(b) = self.rx.recv_timeout(wait) {
                r.extend_from_slice(&b);
                wait = Duration::from_millis(500);
            }
            if r.is_empty() {
                continue;
            }
            let n = r.len();
            assert!(n >= 4 && r[0] == 1, "{r:02x?}");
            assert_eq!(
                crc16(&r[..n - 2]).to_le_bytes(),
                [r[n - 2], r[n - 1]],
                "CRC of {r:02x?}"
            );
            return r[1..n - 2].to_vec();
        }
        panic!("no reply to {req:02x?}");
    }
}

/// Registers from a read reply's PDU (function, byte count, values).
fn registers(pdu: &[u8]) -> Vec<u16> {
    assert_eq!(usize::from(pdu[1]), pdu.len() - 2, "{pdu:02x?}");
    pdu[2..]
        .chunks(2)
        .map(|c| u16::from_be_bytes([c[0], c[1]]))
        .collect()
}

#[test]
fn a_plc_reads_the_firmware_over_modbus_rtu_on_a_pty() {
    use docking_logic::modbus::{ir, status, REVISION};
    let (mut board, _console, modbus) = Plc::start(&["--tcp", "127.0.0.1:0", "--modbus-pty"]);
    assert!(modbus.starts_with("/dev/pts/"), "{modbus}");
    let mut plc = PtyMaster::open(&modbus);
    board.plc_until("ready=1");
    // Input registers 0-1: the status word and the sequencer's state, at rest.
    let r = plc.ask(&[0x04, 0, ir::STATUS as u8, 0, 2]);
    assert_eq!(r[0], 0x04, "{r:02x?}");
    let regs = registers(&r);
    assert_ne!(regs[0] & status::READY, 0, "{regs:?}");
    assert_eq!(regs[1], 3, "idle: {regs:?}");
    // Holding register 0, the command register: reads 0.
    assert_eq!(plc.ask(&[0x03, 0, 0, 0, 1]), [0x03, 2, 0, 0]);
    // The firmware version, in input registers 64-66 and in device identification.
    let version: Vec<u16> = REVISION.split('.').map(|x| x.parse().unwrap()).collect();
    let r = plc.ask(&[0x04, 0, ir::FW_MAJOR as u8, 0, 3]);
    assert_eq!(registers(&r), version);
    // Read device identification (0x2B / MEI 0x0E), basic objects from 0: VendorName,
    // ProductCode, MajorMinorRevision.
    let r = plc.ask(&[0x2B, 0x0E, 1, 0]);
    assert_eq!(r[..3], [0x2B, 0x0E, 1], "{r:02x?}");
    let mut objects = Vec::new();
    let mut at = 7; // function, MEI, code, conformity, more follows, next id, count
    for _ in 0..r[6] {
        let (id, len) = (r[at], usize::from(r[at + 1]));
        objects.push((
            id,
            String::from_utf8(r[at + 2..at + 2 + len].to_vec()).unwrap(),
        ));
        at += 2 + len;
    }
    assert_eq!(at, r.len(), "{r:02x?}");
    assert_eq!(
        objects[1],
        (1, "docking-controller".to_string()),
        "{objects:?}"
    );
    assert_eq!(objects[2], (2, REVISION.to_string()), "{objects:?}");
}

/// The console printed its banner and prompt at boot, to nobody: a technician who
/// connected to `vboard serve --tcp` afterwards saw nothing until pressing Enter. Each
/// client is now sent the image's boot banner and the line its console stands at.
#[test]
fn a_terminal_that_connects_after_the_boot_sees_the_banner_and_the_prompt() {
    let (mut board, console, _modbus) =
        Plc::start(&["--tcp", "127.0.0.1:0", "--modbus-tcp", "127.0.0.1:0"]);
    // Booted and at rest (READY) before anyone connects.
    board.plc_until("ready=1");
    let mut s = std::net::TcpStream::connect(&console).expect("connect");
    s.set_read_timeout(Some(Duration::from_millis(200)))
        .unwrap();
    let deadline = Instant::now() + Duration::from_secs(10);
    let mut got = Vec::new();
    while !got.ends_with(b"> ") && Instant::now() < deadline {
        let mut buf = [0u8; 256];
        if let Ok(n) = s.read(&mut buf) {
            got.extend_from_slice(&buf[..n]);
        }
    }
    let got = String::from_utf8_lossy(&got);
    assert!(
        got.starts_with("# docking-controller ")
            && got.contains(" reset=power_on; type 'help'\r\n")
            && got.ends_with("> "),
        "nothing typed, got {got:?}"
    );
}

/// Read the pty in a thread until `stop` appears in what it read (then it lets go of
/// the pty, so that another program can read it).
fn pty_reader(pty: &std::fs::File, stop: &'static str) -> std::sync::mpsc::Receiver<Vec<u8>> {
    let (tx, rx) = std::sync::mpsc::channel::<Vec<u8>>();
    let mut reader = pty.try_clone().unwrap();
    std::thread::spawn(move || {
        let mut buf = [0u8; 512];
        let mut seen = String::new();
        while let Ok(n) = reader.read(&mut buf) {
            if n == 0 || tx.send(buf[..n].to_vec()).is_err() {
                break;
            }
            seen.push_str(&String::from_utf8_lossy(&buf[..n]));
            if seen.contains(stop) {
                break;
            }
        }
    });
    rx
}

/// Collect from `rx` until a line starting with `want` is complete.
fn until_line(rx: &std::sync::mpsc::Receiver<Vec<u8>>, want: &str, secs: u64) -> String {
    let deadline = Instant::now() + Duration::from_secs(secs);
    let mut got = String::new();
    while Instant::now() < deadline {
        if let Ok(b) = rx.recv_timeout(Duration::from_millis(200)) {
            got.push_str(&String::from_utf8_lossy(&b));
        }
        // Whole lines only (the last piece has no CR LF yet).
        let lines: Vec<&str> = got.split("\r\n").collect();
        let whole = &lines[..lines.len() - 1];
        if let Some(l) = whole.iter().find(|l| l.starts_with(want)) {
            return l.to_string();
        }
    }
    panic!("no line starting {want:?}; got {got:?}");
}

/// Issue 21: Debian's lrzsz (`sb -k`, YMODEM-1K) sends a signed image into the board
/// over `vboard serve --pty`, as a technician would from a laptop: the board verifies it
/// and restarts into it. Needs `sb` (`apt-get install lrzsz`; .ci/run installs it).
#[test]
fn lrzsz_sb_sends_a_signed_image_into_the_board_over_a_pty() {
    let img = vboard::image::Image::load(&vboard::image::default_path()).unwrap();
    let file = vboard::update::update_file(
        &vboard::update::app_bytes(&img),
        vboard::update::NEW_VERSION,
    );
    let path = std::env::temp_dir().join(format!("vboard-sb-{}.dcs", std::process::id()));
    std::fs::write(&path, &file).unwrap();
    // No demo cycles (--plc): the machine rests, the PLC never asks.
    struct Kill(Child);
    impl Drop for Kill {
        fn drop(&mut self) {
            let _ = self.0.kill();
            let _ = self.0.wait();
        }
    }
    let mut child = Kill(
        Command::new(env!("CARGO_BIN_EXE_vboard"))
            .args(["serve", "--for", "300", "--pty", "--plc"])
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("vboard runs"),
    );
    let mut line = String::new();
    BufReader::new(child.0.stdout.as_mut().unwrap())
        .read_line(&mut line)
        .expect("first line: the pty");
    let pty_path = line.trim().to_string();
    let mut pty = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&pty_path)
        .expect("open the pty");
    // The reader lets go of the pty at the end of `update`'s reply: sb reads from there.
    let rx = pty_reader(&pty, "of silence cancels\r\n");
    // Commissioning: a PIN, maintenance mode, then `update`.
    for (cmd, want) in [
        ("pin set 2468", "ok: PIN set"),
        ("maint 2468", "ok: maintenance mode"),
    ] {
        let deadline = Instant::now() + Duration::from_secs(60);
        loop {
            pty.write_all(format!("{cmd}\r\n").as_bytes()).unwrap();
            match std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                until_line(&rx, want, 5)
            })) {
                Ok(_) => break,
                Err(_) if Instant::now() < deadline => continue,
                Err(e) => std::panic::resume_unwind(e),
            }
        }
    }
    pty.write_all(b"update\r\n").unwrap();
    until_line(&rx, "ok: update: send", 30);
    let st = Command::new("sb")
        .arg("-k")
        .arg(&path)
        .stdin(std::fs::File::open(&pty_path).unwrap())
        .stdout(
            std::fs::OpenOptions::new()
                .write(true)
                .open(&pty_path)
                .unwrap(),
        )
        .stderr(Stdio::null())
        .status()
        .expect("sb runs (apt-get install lrzsz)");
    let _ = std::fs::remove_file(&path);
    let rx = pty_reader(&pty, "does not confirm)\r\n");
    let reply = until_line(&rx, "ok: update verified", 120);
    assert!(st.success(), "sb failed: {st}");
    assert!(
        reply.starts_with("ok: update verified: version 0.1.1"),
        "{reply}"
    );
}
