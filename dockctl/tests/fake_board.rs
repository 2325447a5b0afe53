//! `dockctl update`'s outcomes that the virtual board stages only with minutes of
//! emulation, against a scripted console on TCP whose update receiver is the
//! firmware's own (`docking_logic::ymodem::Receiver`, with its 'C' and its NAK after
//! 3 s of quiet): a byte lost on the line in the middle of a block (the transfer must
//! go on, not loop on NAKs), an image rolled back after its restart, one that never
//! confirms, and the board's refusal after the last block. The real image's update,
//! end to end, is vboard/tests/dockctl.rs.

use std::io::{Read, Write};
use std::net::{TcpListener, TcpStream};
use std::process::{Command, Output, Stdio};
use std::time::{Duration, Instant};

use docking_logic::ymodem::{Action, Receiver};

/// How the scripted board behaves after the file.
#[derive(Clone, Copy, PartialEq)]
enum After {
    /// Verified, restarts into 0.1.1, confirms after two `version`s on trial.
    Updated,
    /// Verified, restarts, and comes back as 0.1.0 reporting 0.1.1 rolled back.
    RolledBack,
    /// Verified, restarts into 0.1.1, stays on trial.
    NeverConfirms,
    /// Refuses the file after its last block.
    Refused,
}

struct Fake {
    after: After,
    /// Drop the byte at this offset of the YMODEM input (a byte lost on the line).
    drop_at: Option<usize>,
    /// A noise byte (STX) on the line just before this block.
    noise_before: Option<u32>,
    /// From the last block to the verdict, and from the verdict to the boot banner, ms
    /// (what the board receives meanwhile is lost, as in a reset).
    verdict_ms: u64,
    restart_ms: u64,
}

impl Fake {
    fn new(after: After) -> Fake {
        Fake {
            after,
            drop_at: None,
            noise_before: None,
            verdict_ms: 300,
            restart_ms: 1500,
        }
    }
}

struct State {
    version: &'static str,
    maint: bool,
    trial_polls: u32,
    rolled_back: bool,
    restarted: bool,
}

fn line(s: &mut TcpStream, text: &str) {
    let _ = s.write_all(format!("{text}\r\n").as_bytes());
}

impl Fake {
    /// Serve one client at a time, forever (a thread); the address.
    fn start(self) -> String {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let addr = l.local_addr().unwrap().to_string();
        std::thread::spawn(move || {
            let mut st = State {
                version: "0.1.0",
                maint: false,
                trial_polls: 0,
                rolled_back: false,
                restarted: false,
            };
            for c in l.incoming() {
                let Ok(mut c) = c else { continue };
                c.set_read_timeout(Some(Duration::from_millis(20))).unwrap();
                self.serve(&mut c, &mut st);
            }
        });
        addr
    }

    fn serve(&self, c: &mut TcpStream, st: &mut State) {
        let mut pending: Vec<u8> = Vec::new();
        let mut buf = [0u8; 2048];
        loop {
            match c.read(&mut buf) {
                Ok(0) => return,
                Ok(n) => pending.extend_from_slice(&buf[..n]),
                Err(e)
                    if e.kind() == std::io::ErrorKind::WouldBlock
                        || e.kind() == std::io::ErrorKind::TimedOut =>
                {
                    continue
                }
                Err(_) => return,
            }
            while let Some(at) = pending.iter().position(|&b| b == b'\r' || b == b'\n') {
                let raw: Vec<u8> = pending.drain(..=at).collect();
                let text = String::from_utf8_lossy(&raw[..raw.len() - 1]).to_string();
                if text.is_empty() {
                    continue;
                }
                if text.bytes().any(|b| b < 0x20) {
                    line(
                        c,
                        "error: control character or escape sequence in line; discarded",
                    );
                    continue;
                }
                self.command(c, st, &text);
            }
        }
    }

    fn command(&self, c: &mut TcpStream, st: &mut State, cmd: &str) {
        match cmd {
            "echo" => line(c, "echo=off"),
            "echo off" => line(c, "ok: echo and prompt off until reset (`echo on` turns them back on)"),
            "echo on" => line(c, "ok: echo, prompt and line editing on"),
            "version --json" => {
                let trial = match (st.restarted, self.after) {
                    (true, After::NeverConfirms) => "yes",
                    (true, After::Updated) if st.trial_polls < 2 => "yes",
                    _ => "no",
                };
                if trial == "yes" {
                    st.trial_polls += 1;
                }
                let advice = if trial == "yes" { "\"on trial: it confirms itself at rest once the load cell answers; a reset before that rolls it back; update is refused until then\"" } else { "null" };
                let previous = if st.restarted && st.version == "0.1.1" { "\"0.1.0\"" } else { "null" };
                let rolled = if st.rolled_back { "\"0.1.1\"" } else { "null" };
                line(c, &format!(
                    "{{\"name\":\"docking-controller\",\"version\":\"{}\",\"test_key\":true,\"previous\":{previous},\"rolled_back\":{},\"rolled_back_version\":{rolled},\"trial\":\"{trial}\",\"trial_advice\":{advice}}}",
                    st.version, st.rolled_back
                ));
            }
            "status --json" => line(c, &format!("{{\"state\":\"idle\",\"maintenance\":{}}}", st.maint)),
            "wear --json" => line(c, "{\"cone\":1,\"material\":\"zqsn5-2\",\"serial\":null,\"cycles\":3,\"load_distance_nmm\":24281.976,\"wear_mm\":0.007536,\"lifetime_cycles\":3,\"readings\":1}"),
            "maint exit" => {
                st.maint = false;
                line(c, "ok: maintenance mode ended");
            }
            "maint 2468" => {
                st.maint = true;
                line(c, "ok: maintenance mode (ends after 10 min idle or `maint exit`)");
            }
            m if m.starts_with("maint ") => line(c, "error: wrong PIN; 4 attempt(s) left"),
            "update" => {
                line(c, "ok: update: send the signed image by YMODEM-1K now (sb -k FILE, or the terminal's YMODEM upload); at most 262144 bytes; 60 s of silence cancels");
                self.receive(c, st);
            }
            _ => line(c, "error: unknown command; type 'help'"),
        }
    }

    /// The firmware's receiver, timed as the board's session times it.
    fn receive(&self, c: &mut TcpStream, st: &mut State) {
        let mut rx = Receiver::new(262_144);
        let _ = c.write_all(rx.idle());
        let mut quiet_since = Instant::now();
        let mut fed = 0usize;
        let mut size = 0u32;
        let mut buf = [0u8; 2048];
        let start = Instant::now();
        while start.elapsed() < Duration::from_secs(120) {
            let n = match c.read(&mut buf) {
                Ok(0) => return,
                Ok(n) => n,
                Err(_) => 0,
            };
            if n > 0 {
                quiet_since = Instant::now();
            } else if quiet_since.elapsed() >= Duration::from_secs(3) {
                let _ = c.write_all(rx.idle());
                quiet_since = Instant::now();
            }
            for &b in &buf[..n] {
                fed += 1;
                if self.drop_at == Some(fed) {
                    continue; // lost on the line
                }
                match rx.feed(b) {
                    Action::None => {}
                    Action::Send(x) => {
                        let _ = c.write_all(x);
                    }
                    Action::Start { size: s } => {
                        size = s;
                        let _ = c.write_all(rx.ack());
                    }
                    Action::Data { offset, len } => {
                        let _ = c.write_all(rx.ack());
                        let next = (offset as usize + len) / 1024 + 1;
                        if self.noise_before == Some(next as u32) {
                            let _ = rx.feed(docking_logic::ymodem::STX);
                        }
                    }
                    Action::Done(x) => {
                        let _ = c.write_all(x);
                        std::thread::sleep(Duration::from_millis(self.verdict_ms));
                        if self.after == After::Refused {
                            line(c, "error: update refused: signature does not verify (unsigned, another key's, or changed)");
                            return;
                        }
                        line(c, &format!("ok: update verified: version 0.1.1, {} bytes, signature good; restarting into it (the old image comes back if it does not confirm)", size - 72));
                        std::thread::sleep(Duration::from_millis(self.restart_ms));
                        // Whatever came during the reset is lost.
                        while matches!(c.read(&mut buf), Ok(n) if n > 0) {}
                        st.restarted = true;
                        st.maint = false;
                        if self.after == After::RolledBack {
                            st.rolled_back = true;
                        } else {
                            st.version = "0.1.1";
                        }
                        let _ = c.write_all(
                            format!(
                                "# docking-controller {} reset=software; type 'help'\r\nidle> ",
                                st.version
                            )
                            .as_bytes(),
                        );
                        return;
                    }
                    Action::Aborted(_, x) => {
                        let _ = c.write_all(x);
                        std::thread::sleep(Duration::from_millis(1000));
                        line(c, "error: update refused: cancelled by the sender");
                        return;
                    }
                }
            }
        }
    }
}

/// An update file of code-like bytes (SOH and STX among them, as in any image); with
/// `crc_low`, one whose some block (2 or later) ends in that byte: that block's number.
fn file_with(crc_low: Option<u8>) -> (String, Option<u32>) {
    for seed in 1u64.. {
        let mut x = 0x2545_F491_4F6C_DD1Du64 ^ seed;
        let mut img: Vec<u8> = (0..20_000)
            .map(|_| {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                (x >> 24) as u8
            })
            .collect();
        img[0..4].copy_from_slice(&0x2002_0000u32.to_le_bytes());
        img[4..8].copy_from_slice(&0x0802_0401u32.to_le_bytes());
        let at = 0x200;
        img[at..at + 4].copy_from_slice(b"DCIH");
        img[at + 4..at + 12].copy_from_slice(&[0, 1, 1, 0, 0, 0, 0, 0]);
        img[at + 12..at + 16].copy_from_slice(&(1u32 | 3 << 8).to_le_bytes());
        let key = hil_sim::update::public_key(&hil_sim::update::test_key_seed());
        img[at + 16..at + 32].copy_from_slice(&key[..16]);
        let f = hil_sim::update::signed_file(&img, &hil_sim::update::test_key_seed());
        let block = match crc_low {
            None => None,
            Some(low) => {
                let found = f.chunks(1024).enumerate().skip(1).find(|(_, c)| {
                    let mut d = c.to_vec();
                    d.resize(1024, 0x1A);
                    hil_sim::update::crc16_xmodem(&d) & 0xFF == u16::from(low)
                });
                match found {
                    Some((i, _)) => Some(i as u32 + 1),
                    None => continue,
                }
            }
        };
        let p = std::env::temp_dir().join(format!(
            "dockctl-fake-{}-{}.dcs",
            std::process::id(),
            rand()
        ));
        std::fs::write(&p, f).unwrap();
        return (p.to_str().unwrap().to_string(), block);
    }
    unreachable!()
}

fn file() -> String {
    file_with(None).0
}

fn rand() -> u128 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap()
        .as_nanos()
}

fn update(addr: &str, file: &str) -> Output {
    let pin = std::env::temp_dir().join(format!("dockctl-fake-pin-{}", rand()));
    std::fs::write(&pin, "2468\n").unwrap();
    let o = Command::new(env!("CARGO_BIN_EXE_dockctl"))
        .args([
            "--tcp",
            addr,
            "update",
            file,
            "--pin-file",
            pin.to_str().unwrap(),
            "--restart-timeout",
            "10",
        ])
        .stdin(Stdio::null())
        .output()
        .unwrap();
    let _ = std::fs::remove_file(pin);
    o
}

fn err(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// A byte lost in the middle of a block: the receiver reads a packet short (and the
/// start of the repeat as its last byte), NAKs, and the repeat's tail, read as the
/// start of another packet, would have the same block misread at every repeat. The
/// sender answers a second NAK only after the receiver's own NAK on a quiet line.
#[test]
fn a_byte_lost_in_a_block_costs_a_repeat_not_the_transfer() {
    let addr = Fake {
        drop_at: Some(133 + 1029 + 500),
        ..Fake::new(After::Updated)
    }
    .start();
    let o = update(&addr, &file());
    let e = err(&o);
    assert_eq!(o.status.code(), Some(0), "{e}");
    assert!(e.contains("updated to 0.1.1 (from 0.1.0"), "{e}");
    assert!(e.contains("blocks sent again"), "{e}");
}

/// A noise byte that looks like a block's start (STX) just before a block whose last
/// byte (its CRC's low byte) is an STX too: the receiver reads the noise and the block
/// but its last byte as a packet (NAK at once), and that last byte, left over, starts
/// another packet that the repeat completes, NAK at once, again and again: the same
/// block misread the same way at every repeat (seen once on the virtual board, where a
/// transfer looped on one block's NAK for minutes). The second NAK is answered only
/// after the receiver's own NAK on a quiet line, when it has dropped what it held.
#[test]
fn noise_before_a_block_does_not_loop_the_transfer_on_one_blocks_nak() {
    let (f, block) = file_with(Some(docking_logic::ymodem::STX));
    let addr = Fake {
        noise_before: block,
        ..Fake::new(After::Updated)
    }
    .start();
    let o = update(&addr, &f);
    let e = err(&o);
    assert_eq!(o.status.code(), Some(0), "block {block:?}: {e}");
    assert!(e.contains("updated to 0.1.1 (from 0.1.0"), "{e}");
}

#[test]
fn an_update_rolled_back_is_said_so_and_exits_3() {
    let addr = Fake::new(After::RolledBack).start();
    let o = update(&addr, &file());
    let e = err(&o);
    assert_eq!(o.status.code(), Some(3), "{e}");
    assert!(
        e.contains("error: rolled back: 0.1.1 did not confirm itself and the bootloader put 0.1.0 back; the board runs 0.1.0"),
        "{e}"
    );
}

#[test]
fn an_image_that_never_confirms_is_said_so_and_exits_3() {
    let addr = Fake::new(After::NeverConfirms).start();
    let o = update(&addr, &file());
    let e = err(&o);
    assert_eq!(o.status.code(), Some(3), "{e}");
    assert!(
        e.contains("error: 0.1.1 runs on trial and has not confirmed itself (on trial: it confirms itself at rest once the load cell answers"),
        "{e}"
    );
}

#[test]
fn the_boards_refusal_after_the_file_is_its_reason_and_maintenance_mode_is_left() {
    let addr = Fake::new(After::Refused).start();
    let o = update(&addr, &file());
    let e = err(&o);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert!(
        e.contains("error: update refused: the board says: signature does not verify (unsigned, another key's, or changed); it keeps running 0.1.0"),
        "{e}"
    );
    // The tool left maintenance mode: the scripted board says so on `status`.
    let mut s = TcpStream::connect(&addr).unwrap();
    s.write_all(b"status --json\r\n").unwrap();
    s.set_read_timeout(Some(Duration::from_secs(2))).unwrap();
    let mut b = [0u8; 256];
    let n = s.read(&mut b).unwrap();
    assert!(String::from_utf8_lossy(&b[..n]).contains("\"maintenance\":false"));
}

/// `dockctl update` run in the background, SIGINT once a stderr line starts with
/// `at`: (exit status, all of stderr).
fn update_interrupted_at(addr: &str, file: &str, at: &str) -> (Option<i32>, String) {
    use std::io::BufRead;
    let pin = std::env::temp_dir().join(format!("dockctl-fake-pin-{}", rand()));
    std::fs::write(&pin, "2468\n").unwrap();
    let mut child = Command::new(env!("CARGO_BIN_EXE_dockctl"))
        .args(["--tcp", addr, "update", file, "--pin-file"])
        .arg(&pin)
        .args(["--restart-timeout", "30"])
        .stdin(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    let mut lines = std::io::BufReader::new(child.stderr.take().unwrap());
    let mut err = String::new();
    loop {
        let mut l = String::new();
        assert!(
            lines.read_line(&mut l).unwrap() > 0,
            "dockctl ended before {at:?}: {err}"
        );
        err.push_str(&l);
        if l.starts_with(at) {
            break;
        }
    }
    // SAFETY: a signal to our own child.
    unsafe { libc::kill(child.id() as i32, libc::SIGINT) };
    lines.read_to_string(&mut err).unwrap();
    let st = child.wait().unwrap();
    let _ = std::fs::remove_file(pin);
    (st.code(), err)
}

/// Ctrl-C while the board restarts into the verified image: the waiting stops (exit
/// 130, said so), and nothing is sent to put the console back: the restart ended
/// maintenance mode (before, a `maint exit` went to the restarting board, unanswered,
/// and the tool said it could not leave maintenance mode).
#[test]
fn ctrl_c_during_the_restart_stops_the_waiting_and_sends_nothing_to_the_restarting_board() {
    let addr = Fake {
        restart_ms: 3000,
        ..Fake::new(After::Updated)
    }
    .start();
    let (code, e) = update_interrupted_at(&addr, &file(), "restart ");
    assert_eq!(code, Some(130), "{e}");
    assert!(
        e.contains("stopped  waiting only: the board verified 0.1.1 and restarts into it; `dockctl version` says how it stands"),
        "{e}"
    );
    assert!(e.contains("error: interrupted (Ctrl-C)"), "{e}");
    assert!(!e.contains("could not leave maintenance mode"), "{e}");
}

/// Ctrl-C after the last block, before the board's verdict: the board has the whole
/// file, so the tool waits for the verdict and then stops waiting, saying what the
/// board does (before, the wait was cut off and its `maint exit` was answered by the
/// verdict: "could not leave maintenance mode", and the board restarted anyway).
#[test]
fn ctrl_c_before_the_verdict_waits_for_it_and_says_what_the_board_does() {
    let addr = Fake {
        verdict_ms: 2000,
        ..Fake::new(After::Updated)
    }
    .start();
    let (code, e) = update_interrupted_at(&addr, &file(), "sent ");
    assert_eq!(code, Some(130), "{e}");
    assert!(e.contains("verified version 0.1.1"), "{e}");
    assert!(
        e.contains("stopped  waiting only: the board verified 0.1.1 and restarts into it"),
        "{e}"
    );
    assert!(!e.contains("could not leave maintenance mode"), "{e}");
}
