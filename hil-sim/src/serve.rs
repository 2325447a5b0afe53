//! `hil-sim serve`: the simulated controller in (scaled) real time, its technician
//! console bridged to a pseudo-terminal or a loopback TCP port, so a technician can
//! connect with `picocom`/`screen` (or `nc`) and practise.
//!
//! The first line on stdout is the pty's path or the bound address; the machine then
//! docks continuously (a new cycle whenever it is idle), with the scene's disturbance
//! injected in its first cycle. The bridge applies back-pressure: bytes are taken from
//! the link only as fast as the board's 256-byte receive ring drains, so a paste is not
//! lost to an overrun (a real UART without flow control would lose it).

use std::io::{self, Read, Write};
use std::net::{SocketAddr, TcpListener, TcpStream};
use std::os::fd::{FromRawFd, OwnedFd};
use std::time::{Duration, Instant};

use docking_controller::sequencer::{Request, State};

use crate::console::RX_RING;
use crate::rig::{AdcMode, Rig, RigOptions};
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
    /// Scene whose disturbance to inject.
    pub scene: String,
    /// Virtual seconds per wall second.
    pub speed: f64,
    /// Load-cell rate, SPS.
    pub rate_sps: u32,
    /// Stop after this many wall seconds (`None`: run until killed).
    pub duration_s: Option<f64>,
}

/// A pty master opened non-blocking, with its slave configured raw (no echo, no line
/// editing: the console does its own) and kept open so the master never sees a hangup.
struct Pty {
    master: std::fs::File,
    _slave: OwnedFd,
    path: String,
}

fn os_err(what: &str) -> String {
    format!("{what}: {}", io::Error::last_os_error())
}

impl Pty {
    fn open() -> Result<Self, String> {
        // SAFETY: plain libc calls on fds we own; every return value is checked, and
        // ptsname_r writes into a buffer whose length we pass.
        unsafe {
            let m = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY);
            if m < 0 {
                return Err(os_err("posix_openpt"));
            }
            let master = std::fs::File::from_raw_fd(m);
            if libc::grantpt(m) != 0 || libc::unlockpt(m) != 0 {
                return Err(os_err("grantpt/unlockpt"));
            }
            let mut buf = [0 as libc::c_char; 128];
            if libc::ptsname_r(m, buf.as_mut_ptr(), buf.len()) != 0 {
                return Err(os_err("ptsname_r"));
            }
            let path = std::ffi::CStr::from_ptr(buf.as_ptr())
                .to_string_lossy()
                .into_owned();
            let s = libc::open(buf.as_ptr(), libc::O_RDWR | libc::O_NOCTTY);
            if s < 0 {
                return Err(os_err("open slave"));
            }
            let slave = OwnedFd::from_raw_fd(s);
            let mut t: libc::termios = std::mem::zeroed();
            if libc::tcgetattr(s, &mut t) != 0 {
                return Err(os_err("tcgetattr"));
            }
            libc::cfmakeraw(&mut t);
            libc::cfsetspeed(&mut t, libc::B115200);
            if libc::tcsetattr(s, libc::TCSANOW, &t) != 0 {
                return Err(os_err("tcsetattr"));
            }
            let flags = libc::fcntl(m, libc::F_GETFL);
            if flags < 0 || libc::fcntl(m, libc::F_SETFL, flags | libc::O_NONBLOCK) != 0 {
                return Err(os_err("fcntl"));
            }
            Ok(Self {
                master,
                _slave: slave,
                path,
            })
        }
    }
}

enum Bridge {
    Pty(Pty),
    Tcp {
        listener: TcpListener,
        client: Option<TcpStream>,
    },
}

impl Bridge {
    /// Read up to `max` bytes from the link (empty: nothing waiting).
    fn read(&mut self, max: usize) -> Vec<u8> {
        let mut buf = vec![0u8; max];
        let n = match self {
            Bridge::Pty(p) => p.master.read(&mut buf).unwrap_or(0),
            Bridge::Tcp { listener, client } => {
                if client.is_none() {
                    if let Ok((s, _)) = listener.accept() {
                        let _ = s.set_nonblocking(true);
                        let _ = s.set_nodelay(true);
                        *client = Some(s);
                    }
                }
                match client.as_mut().map(|c| c.read(&mut buf)) {
                    Some(Ok(0)) => {
                        *client = None; // the client left; wait for the next one
                        0
                    }
                    Some(Ok(n)) => n,
                    _ => 0,
                }
            }
        };
        buf.truncate(n);
        buf
    }

    fn write(&mut self, bytes: &[u8]) {
        if bytes.is_empty() {
            return;
        }
        let _ = match self {
            Bridge::Pty(p) => p.master.write_all(bytes),
            Bridge::Tcp {
                client: Some(c), ..
            } => c.write_all(bytes),
            Bridge::Tcp { client: None, .. } => Ok(()),
        };
    }
}

/// Run the live simulator; prints the link's address first, then runs until killed (or
/// `duration_s`).
pub fn run(opts: &ServeOptions, out: &mut dyn Write) -> Result<(), String> {
    let mut driver = SceneDriver::new(&opts.scene, 1)?;
    if !(opts.speed.is_finite() && opts.speed > 0.0) {
        return Err(format!(
            "--speed must be a positive number, got {}",
            opts.speed
        ));
    }
    let mut bridge = match &opts.link {
        Link::Pty => {
            let p = Pty::open()?;
            let _ = writeln!(out, "{}", p.path);
            Bridge::Pty(p)
        }
        Link::Tcp(addr) => {
            if !addr.ip().is_loopback() {
                return Err(format!(
                    "--tcp must be a loopback address (127.0.0.1:PORT), got {addr}"
                ));
            }
            let l = TcpListener::bind(addr).map_err(|e| format!("bind {addr}: {e}"))?;
            l.set_nonblocking(true).map_err(|e| e.to_string())?;
            let bound = l.local_addr().map_err(|e| e.to_string())?;
            let _ = writeln!(out, "{bound}");
            Bridge::Tcp {
                listener: l,
                client: None,
            }
        }
    };
    let _ = out.flush();
    let mut rig = Rig::new(RigOptions {
        adc: AdcMode::Pins,
        ..RigOptions::new(opts.rate_sps)
    });
    rig.console_enabled = true;
    driver.setup(&mut rig, 1, opts.rate_sps, 1_000);
    let start = Instant::now();
    loop {
        let wall = start.elapsed().as_secs_f64();
        if opts.duration_s.is_some_and(|d| wall >= d) {
            return Ok(());
        }
        let target_ns = (wall * opts.speed * 1e9) as u64;
        while rig.clock.now_ns() < target_ns {
            rig.tick();
            let st = rig.ctrl.status();
            driver.on_tick(&mut rig, &st);
            if st.state == State::Idle && !rig.ctrl.persist_pending() {
                rig.ctrl.request(Request::StartCycle);
            }
        }
        let room = RX_RING.saturating_sub(rig.term.rx_pending());
        if room > 0 {
            let bytes = bridge.read(room);
            rig.term.send(&bytes);
        }
        bridge.write(&rig.term.take_output());
        std::thread::sleep(Duration::from_millis(2));
    }
}
