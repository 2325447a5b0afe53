//! `dockctl` (the binary, as a technician runs it) against the live simulator,
//! `hil-sim serve`, in this process: over TCP and over a pty. Every reading command in
//! its three forms, `export`, `watch` and Ctrl-C, and the failures a technician can
//! cause that the simulator can stage: a wrong PIN, files that are not update files or
//! are another layout's, the board's own refusal (`update` on a simulator), a port that
//! does not exist, is busy or is not a serial port, nothing answering, a wrong baud
//! rate. Each failure: one line on stderr, a non-zero exit, the board as it was (not in
//! maintenance mode, echo on). The update itself runs on the virtual board, whose image
//! has the updater (vboard/tests/dockctl.rs).

use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::process::{Command, Output, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use hil_sim::serve::{Link, ServeOptions};

/// `hil-sim serve` in a thread; its address (a TCP address or a pty's path).
fn serve(link: Link) -> String {
    serve_at(link, 1.0)
}

/// The same at `speed` × real time.
fn serve_at(link: Link, speed: f64) -> String {
    struct Lines(mpsc::Sender<String>, Vec<u8>);
    impl Write for Lines {
        fn write(&mut self, b: &[u8]) -> std::io::Result<usize> {
            self.1.extend_from_slice(b);
            while let Some(at) = self.1.iter().position(|&c| c == b'\n') {
                let line: Vec<u8> = self.1.drain(..=at).collect();
                let _ = self
                    .0
                    .send(String::from_utf8_lossy(&line).trim().to_string());
            }
            Ok(b.len())
        }
        fn flush(&mut self) -> std::io::Result<()> {
            Ok(())
        }
    }
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let opts = ServeOptions {
            link,
            modbus: None,
            plc: false,
            scene: "nominal".into(),
            speed,
            rate_sps: 80,
            duration_s: Some(300.0),
        };
        let mut out = Lines(tx, Vec::new());
        if let Err(e) = hil_sim::serve::run(&opts, &mut out) {
            panic!("hil-sim serve: {e}");
        }
    });
    rx.recv_timeout(Duration::from_secs(10))
        .expect("the server's address")
}

fn tcp_server() -> String {
    serve(Link::Tcp("127.0.0.1:0".parse().unwrap()))
}

/// Run dockctl with `args`; stdin from `stdin`.
fn dockctl_in(args: &[&str], stdin: Stdio) -> Output {
    Command::new(env!("CARGO_BIN_EXE_dockctl"))
        .args(args)
        .env_remove("DOCKCTL_PIN")
        .env_remove("DOCKCTL_PORT")
        .stdin(stdin)
        .output()
        .expect("dockctl runs")
}

fn dockctl(args: &[&str]) -> Output {
    dockctl_in(args, Stdio::null())
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

/// Run over TCP `addr`; stdout, after checking it exited 0 with nothing on stderr.
fn ok(addr: &str, args: &[&str]) -> String {
    let mut a = vec!["--tcp", addr];
    a.extend_from_slice(args);
    let o = dockctl(&a);
    assert!(
        o.status.success() && o.stderr.is_empty(),
        "dockctl {args:?}: {:?}\nstdout: {}\nstderr: {}",
        o.status,
        text(&o.stdout),
        text(&o.stderr)
    );
    text(&o.stdout)
}

/// Run, expecting a failure: (exit code, its one stderr line).
fn fails(args: &[&str]) -> (i32, String) {
    let o = dockctl(args);
    let err = text(&o.stderr);
    let lines: Vec<&str> = err.lines().filter(|l| l.starts_with("error: ")).collect();
    assert_eq!(lines.len(), 1, "one error line for {args:?}; stderr: {err}");
    (o.status.code().unwrap_or(-1), lines[0].to_string())
}

/// The console as a script sees it: (maintenance mode, echo) after dockctl left.
fn board_state(addr: &str) -> (bool, bool) {
    // `echo` first (before dockctl's own `echo off`, which it puts back): what the next
    // technician finds.
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let mut s = TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_millis(200)))
            .unwrap();
        s.write_all(b"\x03\r\necho\r\n").unwrap();
        let mut got = Vec::new();
        let t = Instant::now() + Duration::from_secs(3);
        let mut buf = [0u8; 1024];
        while Instant::now() < t && !text(&got).contains("echo=") {
            if let Ok(n) = s.read(&mut buf) {
                got.extend_from_slice(&buf[..n]);
            }
        }
        let g = text(&got);
        if g.contains("busy:") || !g.contains("echo=") {
            assert!(Instant::now() < deadline, "the console: {g:?}");
            std::thread::sleep(Duration::from_millis(300));
            continue;
        }
        let echo = g.contains("echo=on");
        drop(s);
        let st = ok(addr, &["status", "--json"]);
        return (st.contains("\"maintenance\":true"), echo);
    }
}

/// Type `line` on the console as a person would (over TCP), return what came back.
fn type_line(addr: &str, line: &str, want: &str) -> String {
    let deadline = Instant::now() + Duration::from_secs(10);
    loop {
        let mut s = TcpStream::connect(addr).unwrap();
        s.set_read_timeout(Some(Duration::from_millis(200)))
            .unwrap();
        s.write_all(format!("{line}\r\n").as_bytes()).unwrap();
        let mut got = Vec::new();
        let t = Instant::now() + Duration::from_secs(3);
        let mut buf = [0u8; 1024];
        while Instant::now() < t && !text(&got).contains(want) {
            if let Ok(n) = s.read(&mut buf) {
                got.extend_from_slice(&buf[..n]);
            }
        }
        if text(&got).contains(want) {
            return text(&got);
        }
        assert!(Instant::now() < deadline, "{line}: {:?}", text(&got));
        std::thread::sleep(Duration::from_millis(300));
    }
}

#[test]
fn every_reading_command_as_a_table_as_json_and_as_csv() {
    // At 20 × real time: the demo docks only after 60 s of machine time without a
    // keystroke (3 s of wall here), and every dockctl run types.
    let a = serve_at(Link::Tcp("127.0.0.1:0".parse().unwrap()), 20.0);
    // Tables with units.
    let st = ok(&a, &["status"]);
    for want in [
        "state ",
        "force ",
        " N\n",
        "position ",
        " mm\n",
        "cycles completed ",
        "out ready ",
    ] {
        assert!(st.contains(want), "status lacks {want:?}:\n{st}");
    }
    let w = ok(&a, &["wear"]);
    for want in [
        "material ",
        "zqsn5-2",
        "wear ",
        " mm\n",
        "remaining ",
        " cycles\n",
        "estimate low ",
        "estimate high ",
    ] {
        assert!(w.contains(want), "wear lacks {want:?}:\n{w}");
    }
    let f = ok(&a, &["faults"]);
    assert!(
        f.contains("resets\n") && f.contains("  power on ") && f.contains("faults (0)"),
        "{f}"
    );
    let m = ok(&a, &["measurements"]);
    assert!(
        m.contains("baseline bore ") && m.contains("readings (0)"),
        "{m}"
    );
    let v = ok(&a, &["version"]);
    assert!(
        v.contains("name ") && v.contains("docking-controller") && v.contains("trial "),
        "{v}"
    );
    // The board's JSON, one line, as it wrote it.
    for cmd in ["status", "wear", "faults", "measurements", "version"] {
        let j = ok(&a, &[cmd, "--json"]);
        assert_eq!(j.lines().count(), 1, "{cmd}: {j}");
        let v: serde_json::Value = serde_json::from_str(&j).unwrap();
        assert!(v.is_object(), "{cmd}: {j}");
    }
    // The history fills as the demo docks: wait for a cycle without typing (8 s of
    // wall, 160 s of machine time: the 60 s the demo waits after a keystroke and a
    // cycle), then read.
    let deadline = Instant::now() + Duration::from_secs(90);
    let h = loop {
        std::thread::sleep(Duration::from_secs(8));
        let h = ok(&a, &["history", "3"]);
        if !h.starts_with("no completed cycles") {
            break h;
        }
        assert!(Instant::now() < deadline, "no cycle in 90 s");
    };
    let head = h.lines().next().unwrap();
    assert!(
        head.starts_with("cycle  cone  cone cycle  load distance (N·mm)  wear (mm)"),
        "{h}"
    );
    let csv = ok(&a, &["history", "3", "--csv"]);
    let mut lines = csv.lines();
    // The board's columns, the docking signature's (issue 34) after the odometer's.
    assert_eq!(
        lines.next(),
        Some("cycle,cone,cone_cycle,load_distance_nmm,wear_mm,signature,failed,work_nmm,plateau_n,drift_work_pct,drift_plateau_pct")
    );
    let row: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(row.len(), 11, "{csv}");
    // The board's digits, not a float's: six decimals of mm.
    assert_eq!(row[4].split('.').nth(1).map(str::len), Some(6), "{csv}");
    // A docking done: `export` carries its curve and the cone's reference as the board
    // wrote them (issue 34).
    let path = std::env::temp_dir().join(format!("dockctl-sigs-{}.json", std::process::id()));
    let o = dockctl(&["--tcp", &a, "export", path.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let _ = std::fs::remove_file(&path);
    let sig = &doc["signatures"];
    assert_eq!(sig["last"]["curve"], "last", "{sig}");
    assert_eq!(sig["last"]["bins"], 128, "{sig}");
    assert_eq!(sig["reference"]["curve"], "ref", "{sig}");
    let csv = ok(&a, &["wear", "--csv", "--no-header"]);
    assert_eq!(csv.lines().count(), 1, "{csv}");
    assert!(csv.starts_with("1,zqsn5-2,"), "{csv}");
    assert_eq!(ok(&a, &["faults", "--csv"]).lines().next(), Some(""));
    // Nothing left behind: echo on, no maintenance mode.
    assert_eq!(board_state(&a), (false, true));
}

#[test]
fn export_writes_one_machines_record_and_watch_stops_on_ctrl_c() {
    let a = tcp_server();
    let path = std::env::temp_dir().join(format!("dockctl-export-{}.json", std::process::id()));
    let o = dockctl(&["--tcp", &a, "export", path.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    let doc: serde_json::Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    let _ = std::fs::remove_file(&path);
    assert_eq!(doc["format"], "dockctl-export-1");
    assert_eq!(doc["tool"]["name"], "dockctl");
    assert!(doc["time"].as_str().unwrap().ends_with('Z'));
    assert_eq!(doc["identity"]["product"], "docking-controller");
    assert_eq!(doc["identity"]["unit"], "HILSIM-0001");
    for k in ["version", "status", "wear", "faults", "measurements"] {
        assert!(doc[k].is_object(), "{k}: {doc}");
    }
    assert!(doc["history"].is_array());
    assert!(doc["wear"]["estimate_high_mm"].is_number());
    // The docking signatures (issue 34): nothing docked yet on this fresh simulator.
    assert!(
        doc["signatures"]["last"].is_null()
            && doc["signatures"]["reference"].is_null()
            && doc["signatures"]["nok"].as_array().unwrap().is_empty(),
        "{}",
        doc["signatures"]
    );
    // `watch` piped: a JSON line per reading, until Ctrl-C (SIGINT), then exit 0.
    let mut child = Command::new(env!("CARGO_BIN_EXE_dockctl"))
        .args(["--tcp", &a, "watch", "--interval-ms", "200"])
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut out = BufReader::new(child.stdout.take().unwrap());
    let mut lines = Vec::new();
    for _ in 0..4 {
        let mut l = String::new();
        out.read_line(&mut l).unwrap();
        lines.push(l);
    }
    // SAFETY: a signal to our own child.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let st = child.wait().unwrap();
    assert_eq!(st.code(), Some(0), "watch after Ctrl-C");
    for l in &lines {
        let v: serde_json::Value = serde_json::from_str(l).unwrap();
        assert!(
            v["time"].is_string() && v["state"].is_string() && v["force_n"].is_number(),
            "{l}"
        );
    }
    assert_eq!(board_state(&a), (false, true));
}

/// A tiny image for layout C (vector table, header), made into an update file signed
/// with the test key; `layout` is the id its header names, `vt_base` where its reset
/// vector points.
fn image_file(layout: u8, vt_base: u32, version: (u8, u8, u16)) -> Vec<u8> {
    use update_layout_hdr::*;
    let mut img = vec![0xFFu8; 4096];
    img[0..4].copy_from_slice(&0x2002_0000u32.to_le_bytes());
    img[4..8].copy_from_slice(&(vt_base + 0x401).to_le_bytes());
    let at = HEADER_OFFSET;
    img[at..at + 4].copy_from_slice(b"DCIH");
    img[at + 4] = version.0;
    img[at + 5] = version.1;
    img[at + 6..at + 8].copy_from_slice(&version.2.to_le_bytes());
    img[at + 8..at + 12].copy_from_slice(&0u32.to_le_bytes());
    img[at + 12..at + 16].copy_from_slice(&(1u32 | (u32::from(layout) << 8)).to_le_bytes());
    let key = hil_sim::update::public_key(&hil_sim::update::test_key_seed());
    img[at + 16..at + 32].copy_from_slice(&key[..16]);
    hil_sim::update::signed_file(&img, &hil_sim::update::test_key_seed())
}

mod update_layout_hdr {
    pub const HEADER_OFFSET: usize = 0x200;
}

fn write_tmp(name: &str, bytes: &[u8]) -> String {
    let p = std::env::temp_dir().join(format!("dockctl-{}-{name}", std::process::id()));
    std::fs::write(&p, bytes).unwrap();
    p.to_str().unwrap().to_string()
}

#[test]
fn a_wrong_pin_bad_files_and_the_boards_refusal_each_fail_in_one_line_and_change_nothing() {
    let a = tcp_server();
    type_line(&a, "pin set 2468", "ok: PIN set");
    let good_pin = write_tmp("pin-good", b"2468\n");
    let bad_pin = write_tmp("pin-bad", b"1357\n");
    let c = 0x0802_0000;
    let newer = write_tmp("newer.dcs", &image_file(3, c, (0, 2, 0)));
    // Files refused before anything is sent (not even a connection: no such server).
    let mut elf = b"\x7fELF\x01\x01\x01".to_vec();
    elf.resize(4096, 0);
    let mut truncated = image_file(3, c, (0, 2, 0));
    truncated.truncate(3000);
    let files = [
        ("elf", elf, "an ELF, not an update file"),
        (
            "junk",
            vec![0x42u8; 5000],
            "not an update file: no update trailer",
        ),
        ("truncated", truncated, "no update trailer"),
        (
            "layout-b",
            image_file(2, c, (0, 2, 0)),
            "an image for another layout: built for layout B; this board has layout C",
        ),
        (
            "layout-a-or-b",
            image_file(0, 0x0800_8000, (0, 2, 0)),
            "an image for another layout: built for an earlier layout (A or B)",
        ),
    ];
    for (name, bytes, want) in files {
        let p = write_tmp(name, &bytes);
        let (code, line) = fails(&[
            "--tcp",
            "127.0.0.1:1",
            "update",
            &p,
            "--pin-file",
            &good_pin,
        ]);
        assert_eq!(code, 1, "{name}");
        assert!(line.contains(want), "{name}: {line}");
        let _ = std::fs::remove_file(p);
    }
    // The simulator's `version` names no test key: a file signed with the test key
    // would be refused by such a board, and is refused here (--force sends it anyway).
    let (code, line) = fails(&["--tcp", &a, "update", &newer, "--pin-file", &good_pin]);
    assert_eq!(code, 1);
    assert!(
        line.contains("signed with the test key: it would refuse it; nothing was sent"),
        "{line}"
    );
    // A wrong PIN: the board's words, nothing changed.
    let (code, line) = fails(&[
        "--tcp",
        &a,
        "update",
        &newer,
        "--force",
        "--pin-file",
        &bad_pin,
    ]);
    assert_eq!(code, 1);
    assert!(
        line.contains(
            "the board refused the PIN: wrong PIN; 4 attempt(s) left; nothing was changed"
        ),
        "{line}"
    );
    assert_eq!(board_state(&a), (false, true));
    // No PIN and no terminal to ask on.
    let (code, line) = fails(&["--tcp", &a, "update", &newer, "--force"]);
    assert_eq!(code, 2);
    assert!(
        line.contains("give --pin-file FILE or DOCKCTL_PIN"),
        "{line}"
    );
    // The right PIN: the simulator itself refuses `update` (it has no update
    // partition); maintenance mode, which the tool entered, is left again.
    let (code, line) = fails(&[
        "--tcp",
        &a,
        "update",
        &newer,
        "--force",
        "--pin-file",
        &good_pin,
    ]);
    assert_eq!(code, 1);
    assert!(
        line.contains("update refused: the board says: no field update here (a simulator has no update partition)"),
        "{line}"
    );
    assert_eq!(board_state(&a), (false, true));
    for p in [good_pin, bad_pin, newer] {
        let _ = std::fs::remove_file(p);
    }
}

#[test]
fn ports_that_do_not_exist_are_busy_or_are_not_serial_and_lines_that_do_not_answer() {
    let (code, line) = fails(&["--port", "/dev/ttyDOCKCTL9", "status"]);
    assert_eq!(code, 1);
    assert!(
        line.starts_with("error: no such port: /dev/ttyDOCKCTL9 ("),
        "{line}"
    );
    let (code, line) = fails(&["--port", "/dev/null", "status"]);
    assert_eq!(code, 1);
    assert!(line.contains("not a serial port: /dev/null"), "{line}");
    let (code, line) = fails(&["status"]);
    assert_eq!(code, 2);
    assert!(line.contains("where is the board? give --port"), "{line}");
    // A pty the simulator serves, held open by another program: busy.
    let pty = serve(Link::Pty);
    let held = serialport::new(&pty, 115_200)
        .open()
        .expect("the pty opens");
    let (code, line) = fails(&["--port", &pty, "status"]);
    assert_eq!(code, 1);
    assert!(
        line.contains(&format!("port busy: {pty} is open in another program")),
        "{line}"
    );
    drop(held);
    // Let go, the same pty works.
    let o = dockctl(&["--port", &pty, "status", "--json"]);
    assert!(o.status.success(), "{}", text(&o.stderr));
    // Something that listens and says nothing (a wrong port), then something that
    // answers garbage (a wrong baud rate).
    for (garbage, want) in [
        (false, "nothing answers on tcp "),
        (true, "bytes came back on tcp "),
    ] {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap().to_string();
        std::thread::spawn(move || {
            let (mut s, _) = l.accept().unwrap();
            let mut buf = [0u8; 256];
            s.set_read_timeout(Some(Duration::from_millis(100)))
                .unwrap();
            let t = Instant::now();
            while t.elapsed() < Duration::from_secs(10) {
                if let Ok(n) = s.read(&mut buf) {
                    if n > 0 && garbage {
                        let _ = s.write_all(&[0xF0, 0x0F, 0xE6, 0x86, 0x98]);
                    }
                }
            }
        });
        let (code, line) = fails(&["--tcp", &addr, "--timeout", "1", "status"]);
        assert_eq!(code, 1);
        assert!(
            line.contains(want) && line.contains("sent Ctrl-C, Enter and `echo` "),
            "{line}"
        );
        if garbage {
            assert!(
                line.contains("a wrong baud rate? the console runs at 115200 8N1"),
                "{line}"
            );
        }
    }
}

/// Ctrl-C while the PIN is asked (on a terminal): the terminal's echo back, the board as
/// it was, exit 130.
#[test]
fn ctrl_c_at_the_pin_prompt_leaves_the_terminal_and_the_board_as_they_were() {
    let a = tcp_server();
    type_line(&a, "pin set 2468", "ok: PIN set");
    let newer = write_tmp("ctrlc.dcs", &image_file(3, 0x0802_0000, (0, 2, 0)));
    // A terminal for dockctl: a pty pair, the child's stdin on its slave.
    let (mut master, slave) = openpty();
    let slave_in = slave.try_clone().unwrap();
    let slave_err = slave.try_clone().unwrap();
    use std::os::unix::process::CommandExt;
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_dockctl"));
    // SAFETY: setsid and TIOCSCTTY between fork and exec, on the child's own stdin:
    // the pty becomes its controlling terminal (/dev/tty, where the PIN is asked).
    unsafe {
        cmd.pre_exec(|| {
            libc::setsid();
            libc::ioctl(0, libc::TIOCSCTTY, 0);
            Ok(())
        });
    }
    let mut child = cmd
        .args(["--tcp", &a, "update", &newer, "--force"])
        .env_remove("DOCKCTL_PIN")
        .stdin(Stdio::from(slave_in))
        .stdout(Stdio::from(slave))
        .stderr(Stdio::from(slave_err))
        .spawn()
        .unwrap();
    // The question on the terminal.
    let deadline = Instant::now() + Duration::from_secs(20);
    let mut got = Vec::new();
    let mut buf = [0u8; 512];
    while !text(&got).contains("maintenance PIN: ") {
        assert!(Instant::now() < deadline, "no PIN prompt: {}", text(&got));
        if let Ok(n) = master.read(&mut buf) {
            got.extend_from_slice(&buf[..n]);
        }
    }
    // SAFETY: a signal to our own child.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    let st = child.wait().unwrap();
    assert_eq!(st.code(), Some(130), "{}", text(&got));
    assert_eq!(board_state(&a), (false, true));
    let _ = std::fs::remove_file(newer);
}

/// A pty pair (master non-blocking).
fn openpty() -> (std::fs::File, std::fs::File) {
    use std::os::fd::FromRawFd;
    let (mut m, mut s) = (0, 0);
    // SAFETY: openpty writes two fds we then own.
    unsafe {
        assert_eq!(
            libc::openpty(
                &mut m,
                &mut s,
                std::ptr::null_mut(),
                std::ptr::null(),
                std::ptr::null()
            ),
            0
        );
        let flags = libc::fcntl(m, libc::F_GETFL);
        libc::fcntl(m, libc::F_SETFL, flags | libc::O_NONBLOCK);
        (std::fs::File::from_raw_fd(m), std::fs::File::from_raw_fd(s))
    }
}
