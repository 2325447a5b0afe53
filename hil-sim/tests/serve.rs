//! `hil-sim serve`: a technician's terminal on the live simulator, through a real
//! pseudo-terminal (as picocom would open it) and through loopback TCP.

use std::io::{BufRead, BufReader, Read, Write};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

struct Server(Child);

impl Drop for Server {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Start the server; return it and its first stdout line.
fn serve(args: &[&str]) -> (Server, String) {
    let mut child = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
        .arg("serve")
        .args(args)
        .args(["--for", "60"])
        .stdout(Stdio::piped())
        .spawn()
        .unwrap();
    let mut first = String::new();
    BufReader::new(child.stdout.take().unwrap())
        .read_line(&mut first)
        .unwrap();
    (Server(child), first.trim().to_string())
}

/// A terminal: a reader thread feeding a channel, so reads can time out.
struct Terminal<W: Write> {
    tx: W,
    rx: mpsc::Receiver<u8>,
}

impl<W: Write> Terminal<W> {
    fn new<R: Read + Send + 'static>(reader: R, writer: W) -> Self {
        let (send, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for b in BufReader::new(reader).bytes() {
                match b {
                    Ok(b) => {
                        if send.send(b).is_err() {
                            break;
                        }
                    }
                    Err(_) => break,
                }
            }
        });
        Self { tx: writer, rx }
    }

    /// Everything the console sends until `want` appears in it (10 s at most).
    fn read_until(&mut self, want: &str) -> String {
        let deadline = Instant::now() + Duration::from_secs(10);
        let mut got = Vec::new();
        while !String::from_utf8_lossy(&got).contains(want) {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(left) {
                Ok(b) => got.push(b),
                Err(_) => panic!("no {want:?}; got {:?}", String::from_utf8_lossy(&got)),
            }
        }
        String::from_utf8_lossy(&got).into_owned()
    }

    /// What a script does first: `echo off` (no echo, no prompt: one reply per line).
    fn script_mode(&mut self) {
        self.tx.write_all(b"echo off\r\n").unwrap();
        self.tx.flush().unwrap();
        self.read_until("ok: echo and prompt off");
        self.read_until("\r\n");
    }

    /// Type a command, return the reply's first line (without CR LF).
    fn ask(&mut self, cmd: &str) -> String {
        self.tx.write_all(cmd.as_bytes()).unwrap();
        self.tx.write_all(b"\r\n").unwrap();
        self.tx.flush().unwrap();
        let deadline = Instant::now() + Duration::from_secs(10);
        let mut line = Vec::new();
        while !line.ends_with(b"\r\n") {
            let left = deadline.saturating_duration_since(Instant::now());
            match self.rx.recv_timeout(left) {
                Ok(b) => line.push(b),
                Err(_) => panic!(
                    "no reply to {cmd:?}; got {:?}",
                    String::from_utf8_lossy(&line)
                ),
            }
        }
        line.truncate(line.len() - 2);
        String::from_utf8(line).unwrap()
    }
}

fn check_wear(term: &mut Terminal<impl Write>) {
    let text = term.ask("wear");
    assert!(
        text.starts_with("cone=1 material=zqsn5-2 serial=none cycles="),
        "{text}"
    );
    assert!(
        text.contains(" remaining_cycles=") && text.contains(" level=ok "),
        "{text}"
    );
    let json = term.ask("wear --json");
    assert!(
        json.starts_with("{\"cone\":1,\"material\":\"zqsn5-2\""),
        "{json}"
    );
    assert!(
        json.ends_with('}')
            && json.contains("\"remaining_cycles\":")
            && json.contains("\"wear_mm\":"),
        "{json}"
    );
    let err = term.ask("wear --xml");
    assert!(err.starts_with("error: "), "{err}");
}

#[test]
fn a_serial_client_reads_wear_through_a_real_pty() {
    let (_server, path) = serve(&["--pty", "--speed", "20"]);
    assert!(
        path.starts_with("/dev/pts/"),
        "first line is the pty path: {path:?}"
    );
    let port = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&path)
        .unwrap();
    let reader = port.try_clone().unwrap();
    let mut term = Terminal::new(reader, port);
    // A person at the terminal: the banner, then the prompt; what is typed is echoed
    // (backspace rubs out), the reply follows, then the prompt again.
    let banner = term.read_until("> ");
    assert!(banner.starts_with("# docking-controller "), "{banner:?}");
    term.tx.write_all(b"versiom\x7fn\r").unwrap();
    term.tx.flush().unwrap();
    let shown = term.read_until("> ");
    assert!(
        shown.starts_with("versiom\x08 \x08n\r\ndocking-controller "),
        "{shown:?}"
    );
    assert!(shown.ends_with("> "), "{shown:?}");
    term.script_mode();
    check_wear(&mut term);
    let status = term.ask("status");
    assert!(status.starts_with("state="), "{status}");
}

#[test]
fn a_script_reads_wear_over_loopback_tcp() {
    let (_server, addr) = serve(&["--tcp", "127.0.0.1:0", "--speed", "20"]);
    assert!(
        addr.starts_with("127.0.0.1:"),
        "first line is the bound address: {addr:?}"
    );
    let stream = std::net::TcpStream::connect(&addr).unwrap();
    let reader = stream.try_clone().unwrap();
    let mut term = Terminal::new(reader, stream);
    term.script_mode();
    check_wear(&mut term);
}

#[test]
fn serve_refuses_bad_arguments() {
    for args in [
        &["serve", "--tcp", "10.0.0.1:7000"][..],
        &["serve", "--tcp", "nonsense"],
        &["serve", "--pty", "--tcp", "127.0.0.1:0"],
        &["serve", "--scene", "meltdown"],
        &["serve", "--speed", "0"],
    ] {
        let out = Command::new(env!("CARGO_BIN_EXE_hil-sim"))
            .args(args)
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        assert_eq!(
            String::from_utf8_lossy(&out.stderr).lines().count(),
            1,
            "{args:?}"
        );
    }
}

/// `printf 'status\r\n' | nc -N 127.0.0.1 PORT`: the client half-closes after its line;
/// the reply was dropped with it.
#[test]
fn a_client_that_half_closes_still_gets_its_reply() {
    let (_server, addr) = serve(&["--tcp", "127.0.0.1:0", "--speed", "20"]);
    let mut s = std::net::TcpStream::connect(&addr).unwrap();
    s.write_all(b"echo off\r\nversion\r\n").unwrap();
    s.shutdown(std::net::Shutdown::Write).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(10))).unwrap();
    let mut got = String::new();
    s.read_to_string(&mut got).unwrap();
    assert!(got.contains("\r\ndocking-controller "), "{got:?}");
    // Served to the end, then let go: the connection closed (read_to_string returned).
}

#[test]
fn a_second_client_is_told_the_console_is_busy() {
    let (_server, addr) = serve(&["--tcp", "127.0.0.1:0", "--speed", "20"]);
    let first = std::net::TcpStream::connect(&addr).unwrap();
    let reader = first.try_clone().unwrap();
    let mut term = Terminal::new(reader, first);
    term.script_mode();
    let mut second = std::net::TcpStream::connect(&addr).unwrap();
    second
        .set_read_timeout(Some(Duration::from_secs(10)))
        .unwrap();
    let mut got = String::new();
    second.read_to_string(&mut got).unwrap();
    assert!(
        got.starts_with("busy: another terminal is connected"),
        "{got:?}"
    );
    // The first one is still served.
    assert!(term.ask("version").starts_with("docking-controller "));
}

/// A console `dock` answered "mated until undock", then the demo cycling undocked it.
#[test]
fn a_console_dock_is_not_undone_by_the_demo_cycling() {
    let (_server, addr) = serve(&["--tcp", "127.0.0.1:0", "--speed", "20"]);
    let stream = std::net::TcpStream::connect(&addr).unwrap();
    let reader = stream.try_clone().unwrap();
    let mut term = Terminal::new(reader, stream);
    term.script_mode();
    // Stored at rest: between two demo cycles.
    let deadline = Instant::now() + Duration::from_secs(20);
    while !term.ask("pin set 2468").starts_with("ok") {
        assert!(Instant::now() < deadline, "PIN never stored");
        std::thread::sleep(Duration::from_millis(20));
    }
    assert!(term.ask("maint 2468").starts_with("ok"));
    // The demo's cycle under way finishes; no new one starts.
    let deadline = Instant::now() + Duration::from_secs(20);
    while !term.ask("status").starts_with("state=idle") {
        assert!(Instant::now() < deadline, "never idle");
        std::thread::sleep(Duration::from_millis(100));
    }
    assert!(term.ask("dock").starts_with("ok: docking"));
    let deadline = Instant::now() + Duration::from_secs(20);
    while !term.ask("status").starts_with("state=holding") {
        assert!(Instant::now() < deadline, "never mated");
        std::thread::sleep(Duration::from_millis(50));
    }
    // 30 s of machine time later (speed 20): still mated.
    std::thread::sleep(Duration::from_millis(1500));
    let st = term.ask("status");
    assert!(st.starts_with("state=holding"), "{st}");
    assert!(term.ask("undock").starts_with("ok: undocking"));
}

/// The console printed its banner and prompt at boot, to nobody: a technician who
/// connected over TCP afterwards saw nothing until pressing Enter. Each client is now
/// sent the boot banner and the line the console stands at, as it connects.
#[test]
fn a_terminal_that_connects_after_the_boot_sees_the_banner_and_the_prompt() {
    let (_server, addr) = serve(&["--tcp", "127.0.0.1:0", "--speed", "20"]);
    // Booted (20 s of machine time) before anyone connects.
    std::thread::sleep(Duration::from_secs(1));
    let stream = std::net::TcpStream::connect(&addr).unwrap();
    let reader = stream.try_clone().unwrap();
    let first = stream.try_clone().unwrap();
    let mut term = Terminal::new(reader, stream);
    let shown = term.read_until("> ");
    assert!(
        shown.starts_with("# docking-controller ")
            && shown.contains(" reset=power_on; type 'help'\r\n"),
        "{shown:?}"
    );
    // Then the console as usual: what is typed is echoed, the reply, a prompt.
    term.tx.write_all(b"version\r").unwrap();
    let reply = term.read_until("> ");
    assert!(
        reply.starts_with("version\r\ndocking-controller "),
        "{reply:?}"
    );
    first.shutdown(std::net::Shutdown::Both).unwrap();
    // The next technician, once the first has been let go, is greeted the same way.
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let mut s = std::net::TcpStream::connect(&addr).unwrap();
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut got = Vec::new();
        let mut buf = [0u8; 256];
        while !(got.ends_with(b"> ") || got.starts_with(b"busy") && got.ends_with(b"\n")) {
            match s.read(&mut buf) {
                Ok(n) if n > 0 => got.extend_from_slice(&buf[..n]),
                _ => break,
            }
        }
        let got = String::from_utf8_lossy(&got).into_owned();
        if got.starts_with("busy: ") {
            assert!(
                Instant::now() < deadline,
                "the first client was never let go"
            );
            std::thread::sleep(Duration::from_millis(200));
            continue;
        }
        assert!(got.starts_with("# docking-controller "), "{got:?}");
        assert!(got.ends_with("> "), "{got:?}");
        break;
    }
}

/// picocom sets the port up with TCSAFLUSH (and pyserial flushes as it opens): the
/// banner and prompt the kernel kept on the pty for the first reader were thrown away,
/// and the technician saw nothing until pressing Enter. The flush is now answered with
/// the banner and the line the console stands at.
#[test]
fn a_terminal_that_flushes_the_pty_as_it_opens_it_sees_the_banner_and_the_prompt() {
    use std::os::fd::AsRawFd;
    let (_server, path) = serve(&["--pty", "--speed", "20"]);
    // Booted before anyone opens the port.
    std::thread::sleep(Duration::from_secs(1));
    let port = std::fs::OpenOptions::new()
        .read(true)
        .write(true)
        .open(&path)
        .unwrap();
    // As picocom opens it: raw, 115 200 baud, applied with TCSAFLUSH.
    // SAFETY: termios calls on an fd this test owns, into a struct it owns.
    unsafe {
        let fd = port.as_raw_fd();
        let mut t: libc::termios = std::mem::zeroed();
        assert_eq!(libc::tcgetattr(fd, &mut t), 0);
        libc::cfmakeraw(&mut t);
        libc::cfsetspeed(&mut t, libc::B115200);
        assert_eq!(libc::tcsetattr(fd, libc::TCSAFLUSH, &t), 0);
    }
    let reader = port.try_clone().unwrap();
    let mut term = Terminal::new(reader, port);
    let shown = term.read_until("> ");
    assert!(
        shown.starts_with("# docking-controller ")
            && shown.contains(" reset=power_on; type 'help'\r\n"),
        "{shown:?}"
    );
    term.tx.write_all(b"version\r").unwrap();
    let reply = term.read_until("> ");
    assert!(
        reply.starts_with("version\r\ndocking-controller "),
        "{reply:?}"
    );
}
