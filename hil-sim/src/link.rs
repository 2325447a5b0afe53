//! The bridge between a simulated serial port and the outside: a new pseudo-terminal
//! (for picocom or screen) or a loopback TCP port (for nc or a script), as a
//! serial-to-Ethernet gateway would carry it. Shared by `hil-sim serve` and the virtual
//! board's `vboard serve`.

use std::io::{self, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::os::fd::{AsRawFd, FromRawFd, OwnedFd};
use std::time::{Duration, Instant};

use crate::serve::Link;

/// A pty master opened non-blocking, with its slave configured raw (no echo, no line
/// editing: the console does its own) and kept open so the master never sees a hangup.
pub struct Pty {
    master: std::fs::File,
    _slave: OwnedFd,
    path: String,
    /// A console's screen, replayed when the terminal flushes what was waiting for it
    /// (packet mode; `None`: a plain byte pipe, as the Modbus link is).
    screen: Option<Screen>,
}

/// Packet mode's first byte of a read: data follows.
const TIOCPKT_DATA: u8 = 0;
/// Packet mode's status bit: the terminal side flushed its input (what the master wrote
/// and nobody had read).
const TIOCPKT_FLUSHREAD: u8 = 1;

fn os_err(what: &str) -> String {
    format!("{what}: {}", io::Error::last_os_error())
}

impl Pty {
    /// Open a new pty.
    pub fn open() -> Result<Self, String> {
        // SAFETY: plain libc calls on fds we own; every return value is checked, and
        // ptsname_r writes into a buffer whose length we pass.
        unsafe {
            let m = libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY);
            if m < 0 {
                return Err(os_err("posix_openpt"));
            }
            let master = std::fs::File::from_raw_fd(m);
            // Close-on-exec, as every fd std opens: a program this process starts must
            // not hold the pty open (the far end would never see it close).
            if libc::fcntl(m, libc::F_SETFD, libc::FD_CLOEXEC) != 0 {
                return Err(os_err("fcntl FD_CLOEXEC"));
            }
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
            let s = libc::open(
                buf.as_ptr(),
                libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC,
            );
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
                screen: None,
            })
        }
    }

    /// Follow the console's output and replay its [`Screen`] whenever the terminal
    /// side flushes its input. picocom sets the port up with `TCSAFLUSH` and pyserial
    /// flushes as it opens, so the banner and prompt the kernel kept for the first
    /// reader were thrown away unseen; in packet mode the flush is reported, and what
    /// it threw away is the screen sent again.
    pub fn replay_on_flush(&mut self) -> Result<(), String> {
        let on: libc::c_int = 1;
        // SAFETY: TIOCPKT takes a pointer to an int, which lives across the call; the
        // fd is the master we own.
        if unsafe { libc::ioctl(self.master.as_raw_fd(), libc::TIOCPKT, &on) } != 0 {
            return Err(os_err("ioctl TIOCPKT"));
        }
        self.screen = Some(Screen::default());
        Ok(())
    }

    /// Read up to `buf.len()` bytes the terminal sent (0: none waiting); a flush
    /// reported on the way replays the screen.
    fn read(&mut self, buf: &mut [u8]) -> usize {
        let Some(screen) = &self.screen else {
            return self.master.read(buf).unwrap_or(0);
        };
        let mut packet = vec![0u8; buf.len() + 1];
        // A status packet or two (a flush, a flow-control change) may come before data.
        for _ in 0..4 {
            let n = self.master.read(&mut packet).unwrap_or(0);
            match packet[..n] {
                [] => return 0,
                [TIOCPKT_DATA, ref data @ ..] => {
                    buf[..data.len()].copy_from_slice(data);
                    return data.len();
                }
                [status, ..] => {
                    if status & TIOCPKT_FLUSHREAD != 0 && screen.at_a_line() {
                        let _ = self.master.write_all(&screen.replay());
                    }
                }
            }
        }
        0
    }

    /// Write what the console printed.
    fn write(&mut self, bytes: &[u8]) -> io::Result<()> {
        if let Some(screen) = &mut self.screen {
            screen.observe(bytes);
        }
        self.master.write_all(bytes)
    }
}

/// An open link: a pty or a TCP listener with at most one client.
pub enum Bridge {
    /// A pseudo-terminal.
    Pty(Pty),
    /// A TCP listener.
    Tcp {
        /// The listener.
        listener: TcpListener,
        /// The connected client.
        client: Option<TcpStream>,
        /// The client closed its sending side (`nc -N` after its last line) at this
        /// instant: it is served until the console has been quiet for
        /// [`LINGER`], then let go.
        closing: Option<Instant>,
        /// What a second client is told before it is let go ([`BUSY`] on a console;
        /// nothing on a Modbus link, where text would be noise on the bus).
        busy: &'static [u8],
        /// A client was let go since [`Bridge::departed`] was last asked.
        departed: bool,
        /// A console's screen, replayed to each client as it connects (`None` on a
        /// Modbus link, where nothing may be said unasked).
        screen: Option<Screen>,
    },
}

/// The console's boot banner starts with this (the firmware's fixed prefix).
pub const BANNER_PREFIX: &[u8] = b"# docking-controller ";

/// Longest unfinished line kept for a replay; a longer one keeps its last bytes.
const SCREEN_LINE_MAX: usize = 1024;

/// What a terminal connected since the boot would show last: the boot banner
/// (`# docking-controller VERSION reset=CAUSE; type 'help'`, the last one printed: the
/// present boot's) and the line being written now (the prompt, and what was typed
/// after it). The firmware prints them once, at boot and after each reply, whether a
/// client is connected or not; a TCP client that connects later is sent this first,
/// and so is a pty's terminal when it flushes what was waiting for it (picocom does as
/// it opens the port), so it sees whom it talks to and where the console stands
/// without pressing Enter.
/// Nothing is made up and nothing is typed for it: with `echo off` (no prompt) the
/// line is empty, and a line a previous client left half typed is shown as it stands.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Screen {
    banner: Vec<u8>,
    line: Vec<u8>,
}

impl Screen {
    /// Follow the console's output.
    pub fn observe(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.line.push(b);
            if b == b'\n' {
                // A reset may cut a line short: the banner then follows on it.
                let line = core::mem::take(&mut self.line);
                if let Some(at) = line
                    .windows(BANNER_PREFIX.len())
                    .position(|w| w == BANNER_PREFIX)
                {
                    self.banner = line[at..].to_vec();
                }
            }
        }
        if self.line.len() > SCREEN_LINE_MAX {
            let cut = self.line.len() - SCREEN_LINE_MAX;
            self.line.drain(..cut);
        }
    }

    /// What a newly connected client is sent: the banner, then the unfinished line.
    pub fn replay(&self) -> Vec<u8> {
        [&self.banner[..], &self.line[..]].concat()
    }

    /// Whether the console stands at a line a terminal may be shown again: nothing, or
    /// printable text (a prompt and what was typed after it). Not while a file transfer
    /// holds the line (`update`'s YMODEM: 'C', ACK, NAK and no line end), where a
    /// sender's own flush (lrzsz's `sb` flushes its input before each EOT) must not put
    /// a banner in its way.
    pub fn at_a_line(&self) -> bool {
        let printable = self.line.iter().all(|&b| (0x20..0x7F).contains(&b));
        let ymodem_c = !self.line.is_empty() && self.line.iter().all(|&b| b == b'C');
        printable && !ymodem_c
    }
}

/// How long a client that half-closed is kept once the console is quiet: its last
/// command's reply is still coming.
pub const LINGER: Duration = Duration::from_millis(500);

/// What a second client is told before it is let go (one terminal at a time, like a
/// serial port).
pub const BUSY: &[u8] = b"busy: another terminal is connected; try again when it leaves\r\n";

impl Bridge {
    /// Read up to `max` bytes from the link (empty: nothing waiting).
    pub fn read(&mut self, max: usize) -> Vec<u8> {
        let mut buf = vec![0u8; max];
        let n = match self {
            Bridge::Pty(p) => p.read(&mut buf),
            Bridge::Tcp {
                listener,
                client,
                closing,
                busy,
                departed,
                screen,
            } => {
                if let Ok((mut s, _)) = listener.accept() {
                    if client.is_none() {
                        let _ = s.set_nonblocking(true);
                        let _ = s.set_nodelay(true);
                        if let Some(screen) = screen {
                            let _ = write_blocking(&mut s, &screen.replay());
                        }
                        *client = Some(s);
                        *closing = None;
                    } else {
                        let _ = s.write_all(busy);
                        let _ = s.shutdown(std::net::Shutdown::Both);
                    }
                }
                if closing.is_some() {
                    0 // it sends nothing more
                } else {
                    match client.as_mut().map(|c| c.read(&mut buf)) {
                        Some(Ok(0)) => {
                            // Half-closed (or gone): its reply may still be coming.
                            *closing = Some(Instant::now());
                            0
                        }
                        Some(Ok(n)) => n,
                        Some(Err(e)) if e.kind() != std::io::ErrorKind::WouldBlock => {
                            *client = None; // reset by the peer
                            *departed = true;
                            0
                        }
                        _ => 0,
                    }
                }
            }
        };
        buf.truncate(n);
        buf
    }

    /// Write to the link (dropped when no client is connected; a console's screen
    /// follows it either way).
    pub fn write(&mut self, bytes: &[u8]) {
        if bytes.is_empty() {
            return;
        }
        if let Bridge::Tcp {
            screen: Some(screen),
            ..
        } = self
        {
            screen.observe(bytes);
        }
        let _ = match self {
            Bridge::Pty(p) => p.write(bytes),
            Bridge::Tcp {
                client: Some(c),
                closing,
                ..
            } => {
                if let Some(t) = closing.as_mut() {
                    *t = Instant::now(); // still answering: the linger starts again
                }
                write_blocking(c, bytes)
            }
            Bridge::Tcp { client: None, .. } => Ok(()),
        };
    }

    /// Let a half-closed client go once the console has been quiet (`quiet`: no
    /// input waiting, nothing sent this round) for [`LINGER`]: the next client then
    /// gets the console.
    pub fn reap(&mut self, quiet: bool) {
        if let Bridge::Tcp {
            client,
            closing,
            departed,
            ..
        } = self
        {
            if let Some(t) = *closing {
                if !quiet {
                    *closing = Some(Instant::now());
                } else if t.elapsed() >= LINGER {
                    if let Some(c) = client.take() {
                        let _ = c.shutdown(std::net::Shutdown::Both);
                    }
                    *closing = None;
                    *departed = true;
                }
            }
        }
    }

    /// Whether a client left since the last call (a pty's reader never "leaves").
    pub fn departed(&mut self) -> bool {
        match self {
            Bridge::Tcp { departed, .. } => core::mem::take(departed),
            Bridge::Pty(_) => false,
        }
    }
}

impl Bridge {
    /// Open `link` and print its address (the pty's path or the bound TCP address) as
    /// one line on `out`. A TCP address must be on loopback.
    pub fn open(link: &Link, out: &mut dyn Write) -> Result<Self, String> {
        match link {
            Link::Pty => {
                let mut p = Pty::open()?;
                p.replay_on_flush()?;
                let _ = writeln!(out, "{}", p.path);
                Ok(Bridge::Pty(p))
            }
            Link::Tcp(addr) => {
                let (l, bound) = listen(*addr)?;
                let _ = writeln!(out, "{bound}");
                Ok(Bridge::Tcp {
                    listener: l,
                    client: None,
                    closing: None,
                    busy: BUSY,
                    departed: false,
                    screen: Some(Screen::default()),
                })
            }
        }
    }

    /// The pty's path or the bound address.
    pub fn address(&self) -> String {
        match self {
            Bridge::Pty(p) => p.path.clone(),
            Bridge::Tcp { listener, .. } => listener
                .local_addr()
                .map_or_else(|e| e.to_string(), |a| a.to_string()),
        }
    }
}

/// Write all of `bytes` to a non-blocking stream (a full socket buffer is waited
/// out, a second at most: a reply is never cut in the middle).
fn write_blocking(c: &mut TcpStream, mut bytes: &[u8]) -> std::io::Result<()> {
    let deadline = Instant::now() + Duration::from_secs(1);
    while !bytes.is_empty() {
        match c.write(bytes) {
            Ok(0) => return Err(std::io::ErrorKind::WriteZero.into()),
            Ok(n) => bytes = bytes.get(n..).unwrap_or(&[]),
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock && Instant::now() < deadline => {
                std::thread::sleep(Duration::from_millis(1));
            }
            Err(e) => return Err(e),
        }
    }
    Ok(())
}

/// Bind a non-blocking listener on a loopback address; returns it and its bound address.
pub fn listen(addr: std::net::SocketAddr) -> Result<(TcpListener, std::net::SocketAddr), String> {
    if !addr.ip().is_loopback() {
        return Err(format!(
            "--tcp must be a loopback address (127.0.0.1:PORT), got {addr}"
        ));
    }
    let l = TcpListener::bind(addr).map_err(|e| format!("bind {addr}: {e}"))?;
    l.set_nonblocking(true).map_err(|e| e.to_string())?;
    let bound = l.local_addr().map_err(|e| e.to_string())?;
    Ok((l, bound))
}

#[cfg(test)]
mod tests {
    use super::Screen;

    const BANNER: &[u8] = b"# docking-controller 0.1.0 reset=power_on; type 'help'\r\n";

    #[test]
    fn a_screen_is_not_replayed_while_a_file_transfer_holds_the_line() {
        let mut s = Screen::default();
        s.observe(b"# docking-controller 0.1.0 reset=power_on; type 'help'\r\nidle# ");
        assert!(s.at_a_line());
        s.observe(b"update\r\nok: update: send the signed image\r\n");
        assert!(s.at_a_line(), "an empty line");
        s.observe(b"C");
        assert!(!s.at_a_line(), "the receiver's 'C'");
        s.observe(b"\x06C\x06\x06");
        assert!(!s.at_a_line(), "ACKs");
        s.observe(b"\x06\x15\x06Cerror: update refused: x\r\nidle# ");
        assert!(s.at_a_line(), "the prompt again");
    }

    #[test]
    fn a_screen_replays_the_banner_and_the_unfinished_line() {
        let mut s = Screen::default();
        assert_eq!(s.replay(), b"");
        s.observe(BANNER);
        s.observe(b"idle> ");
        assert_eq!(s.replay(), [BANNER, b"idle> "].concat());
        // A command, its reply, a new prompt with something half typed.
        s.observe(b"status\r\nstate=idle phase=0\r\nid");
        s.observe(b"le> sta");
        assert_eq!(s.replay(), [BANNER, b"idle> sta"].concat());
        // `echo off`: no prompt, nothing unfinished.
        s.observe(b"\x08 \x08\x08 \x08\x08 \x08echo off\r\nok: echo and prompt off\r\n");
        assert_eq!(s.replay(), BANNER);
    }

    #[test]
    fn a_reset_in_the_middle_of_a_line_brings_the_new_banner() {
        let mut s = Screen::default();
        s.observe(BANNER);
        s.observe(b"idle> hist");
        s.observe(b"# docking-controller 0.1.0 reset=watchdog; type 'help'\r\nready> ");
        assert_eq!(
            s.replay(),
            b"# docking-controller 0.1.0 reset=watchdog; type 'help'\r\nready> "
        );
    }

    #[test]
    fn an_endless_line_keeps_its_last_bytes() {
        let mut s = Screen::default();
        s.observe(BANNER);
        s.observe(&[b'x'; 5000]);
        s.observe(b"idle> ");
        let r = s.replay();
        assert!(r.starts_with(BANNER) && r.ends_with(b"xidle> "));
        assert_eq!(r.len(), BANNER.len() + super::SCREEN_LINE_MAX);
    }
}
