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
        if let Some(l) = got.lines().find(|l| l.starts_with(want)) {
            return l.to_string();
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
    assert_eq!(reply.trim(), format!("docking-controller {}", "0.1.0"));
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
