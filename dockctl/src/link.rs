//! The line to the board: a serial port (`--port /dev/ttyUSB0 --baud 115200`, 8N1, no
//! flow control, as the console's USART2 is set up; the simulators' ptys too) or a TCP
//! connection (`--tcp 127.0.0.1:PORT`: `hil-sim serve` and `vboard serve`). Every way
//! opening it can fail is told in one line a technician can act on.

use std::io::{self, Read, Write};
use std::net::TcpStream;
use std::time::Duration;

/// Where the board is.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Target {
    /// A serial port and its baud rate.
    Serial {
        /// The device, e.g. `/dev/ttyUSB0`.
        path: String,
        /// Bits per second (the console: 115 200).
        baud: u32,
    },
    /// A TCP address (the simulators' `serve --tcp`).
    Tcp(String),
}

impl Target {
    /// What was tried, for a message: `/dev/ttyUSB0 at 115200 Bd 8N1` or `tcp 127.0.0.1:5000`.
    pub fn describe(&self) -> String {
        match self {
            Target::Serial { path, baud } => format!("{path} at {baud} Bd 8N1"),
            Target::Tcp(a) => format!("tcp {a}"),
        }
    }
}

/// Why the line failed.
#[derive(Debug)]
pub enum LinkError {
    /// Opening it failed: one line saying why and what to do.
    Open(String),
    /// The line went away while in use (an adapter unplugged, the far end closed).
    Cut(String),
    /// Any other error while in use.
    Io(String),
}

impl std::fmt::Display for LinkError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            LinkError::Open(s) | LinkError::Cut(s) | LinkError::Io(s) => f.write_str(s),
        }
    }
}

enum Inner {
    Serial(Box<dyn serialport::SerialPort>),
    Tcp(TcpStream),
}

/// An open line.
pub struct Link {
    inner: Inner,
    target: Target,
    /// `DOCKCTL_TRACE=FILE`: every byte in and out, with the time, appended to FILE (to
    /// see what went over the line when something went wrong).
    trace: Option<(std::fs::File, std::time::Instant)>,
}

/// The environment variable naming the trace file.
pub const TRACE_ENV: &str = "DOCKCTL_TRACE";

/// How long one read waits at most (the caller's loops check Ctrl-C between reads).
pub const READ_SLICE: Duration = Duration::from_millis(50);

impl Link {
    /// Open `target`.
    pub fn open(target: &Target) -> Result<Link, LinkError> {
        let inner = match target {
            Target::Serial { path, baud } => Inner::Serial(open_serial(path, *baud)?),
            Target::Tcp(addr) => Inner::Tcp(open_tcp(addr)?),
        };
        let trace = std::env::var_os(TRACE_ENV).and_then(|p| {
            std::fs::OpenOptions::new()
                .create(true)
                .append(true)
                .open(p)
                .ok()
                .map(|f| (f, std::time::Instant::now()))
        });
        let mut l = Link {
            inner,
            target: target.clone(),
            trace,
        };
        l.log("open", target.describe().as_bytes());
        Ok(l)
    }

    /// A trace line: the time, the direction, the bytes in hex (and as text).
    fn log(&mut self, dir: &str, bytes: &[u8]) {
        if let Some((f, t0)) = &mut self.trace {
            let hex: Vec<String> = bytes.iter().map(|b| format!("{b:02x}")).collect();
            let text: String = bytes
                .iter()
                .map(|&b| {
                    if (0x20..0x7f).contains(&b) {
                        b as char
                    } else {
                        '.'
                    }
                })
                .collect();
            let _ = writeln!(
                f,
                "{:10.6} {dir} {} [{}] {text}",
                t0.elapsed().as_secs_f64(),
                bytes.len(),
                hex.join(" ")
            );
        }
    }

    /// What the line is.
    pub fn target(&self) -> &Target {
        &self.target
    }

    /// Throw away what the board sent before now (a serial port's input buffer).
    pub fn discard_input(&mut self) {
        if let Inner::Serial(p) = &mut self.inner {
            let _ = p.clear(serialport::ClearBuffer::Input);
        }
    }

    /// Read what has come, waiting at most [`READ_SLICE`]: `Ok(0)` when nothing came.
    pub fn read(&mut self, buf: &mut [u8]) -> Result<usize, LinkError> {
        let r = match &mut self.inner {
            Inner::Serial(p) => p.read(buf),
            Inner::Tcp(s) => match s.read(buf) {
                Ok(0) => {
                    return Err(LinkError::Cut(format!(
                        "{} closed the connection",
                        self.target.describe()
                    )))
                }
                r => r,
            },
        };
        match r {
            Ok(n) => {
                if n > 0 && self.trace.is_some() {
                    let b = buf[..n].to_vec();
                    self.log("<", &b);
                }
                Ok(n)
            }
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::TimedOut
                        | io::ErrorKind::WouldBlock
                        | io::ErrorKind::Interrupted
                ) =>
            {
                Ok(0)
            }
            Err(e) => Err(self.in_use(e)),
        }
    }

    /// Write all of `bytes`.
    pub fn write_all(&mut self, bytes: &[u8]) -> Result<(), LinkError> {
        self.log(">", bytes);
        let r = match &mut self.inner {
            Inner::Serial(p) => write_retrying(p.as_mut(), bytes),
            Inner::Tcp(s) => write_retrying(s, bytes),
        };
        r.map_err(|e| self.in_use(e))
    }

    /// Wait until what was written has left (a serial port's output buffer drained).
    pub fn drain(&mut self) {
        if let Inner::Serial(p) = &mut self.inner {
            let _ = p.flush();
        }
    }

    fn in_use(&self, e: io::Error) -> LinkError {
        let what = self.target.describe();
        match e.kind() {
            io::ErrorKind::BrokenPipe
            | io::ErrorKind::ConnectionReset
            | io::ErrorKind::ConnectionAborted
            | io::ErrorKind::NotConnected
            | io::ErrorKind::UnexpectedEof => LinkError::Cut(format!("{what} went away ({e})")),
            // A USB adapter pulled out: its reads and writes fail with EIO (Other).
            _ if e.raw_os_error() == Some(libc::EIO)
                || e.raw_os_error() == Some(libc::ENXIO)
                || e.raw_os_error() == Some(libc::ENODEV)
                || e.to_string().contains("I/O error")
                || e.to_string().contains("Input/output error") =>
            {
                LinkError::Cut(format!("{what} went away ({e})"))
            }
            _ => LinkError::Io(format!("{what}: {e}")),
        }
    }
}

/// Write all of `bytes`, going on after an interrupted or timed-out write.
fn write_retrying(w: &mut dyn Write, mut bytes: &[u8]) -> io::Result<()> {
    let mut stalls = 0;
    while !bytes.is_empty() {
        match w.write(bytes) {
            Ok(0) => return Err(io::ErrorKind::WriteZero.into()),
            Ok(n) => {
                bytes = &bytes[n..];
                stalls = 0;
            }
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::Interrupted
                        | io::ErrorKind::TimedOut
                        | io::ErrorKind::WouldBlock
                ) =>
            {
                stalls += 1;
                if stalls > 100 {
                    return Err(io::Error::new(
                        io::ErrorKind::TimedOut,
                        "the line takes no more bytes (5 s)",
                    ));
                }
            }
            Err(e) => return Err(e),
        }
    }
    w.flush()
}

fn open_serial(path: &str, baud: u32) -> Result<Box<dyn serialport::SerialPort>, LinkError> {
    let port = serialport::new(path, baud)
        .data_bits(serialport::DataBits::Eight)
        .parity(serialport::Parity::None)
        .stop_bits(serialport::StopBits::One)
        .flow_control(serialport::FlowControl::None)
        .timeout(READ_SLICE)
        .open();
    match port {
        Ok(p) => Ok(p),
        Err(e) => Err(LinkError::Open(serial_open_error(path, baud, &e))),
    }
}

/// One line for a serial port that did not open.
fn serial_open_error(path: &str, baud: u32, e: &serialport::Error) -> String {
    use serialport::ErrorKind as K;
    match e.kind() {
        K::Io(io::ErrorKind::NotFound) => {
            let others = serial_ports();
            if others.is_empty() {
                format!("no such port: {path} (no serial port is plugged in here: is the USB adapter connected?)")
            } else {
                format!("no such port: {path} (serial ports here: {})", others.join(", "))
            }
        }
        K::Io(io::ErrorKind::PermissionDenied) => permission_denied(path),
        K::NoDevice => format!(
            "port busy: {path} is open in another program (picocom, screen, another dockctl?): close it first"
        ),
        K::InvalidInput => format!("{path} at {baud} Bd: {}", e.description),
        _ if e.description.contains("Not a typewriter")
            || e.description.contains("Inappropriate ioctl") =>
        {
            format!("not a serial port: {path}")
        }
        _ => format!("{path}: {}", e.description),
    }
}

/// Permission denied on `path`: which group may open it, and how to join it.
fn permission_denied(path: &str) -> String {
    use std::os::unix::fs::MetadataExt;
    let group = std::fs::metadata(path).ok().map(|m| (m.gid(), m.mode()));
    match group {
        Some((gid, mode)) if mode & 0o060 == 0o060 => {
            let name = group_name(gid).unwrap_or_else(|| gid.to_string());
            format!(
                "permission denied: {path} belongs to group {name}; join it (sudo usermod -aG {name} $USER), then log in again"
            )
        }
        _ => format!(
            "permission denied: {path} (its owner and mode allow no one but root to open it)"
        ),
    }
}

/// The name of group `gid`.
fn group_name(gid: u32) -> Option<String> {
    let text = std::fs::read_to_string("/etc/group").ok()?;
    text.lines().find_map(|l| {
        let mut f = l.split(':');
        let name = f.next()?;
        let _ = f.next();
        (f.next()?.parse::<u32>().ok()? == gid).then(|| name.to_string())
    })
}

/// The serial ports of this machine that are likely a board's (USB adapters and built-in
/// UARTs that have a device behind them), from sysfs.
pub fn serial_ports() -> Vec<String> {
    let Ok(ports) = serialport::available_ports() else {
        return Vec::new();
    };
    let mut v: Vec<String> = ports
        .into_iter()
        .filter(|p| {
            !matches!(p.port_type, serialport::SerialPortType::Unknown)
                || p.port_name.contains("USB")
                || p.port_name.contains("ACM")
        })
        .map(|p| match p.port_type {
            serialport::SerialPortType::UsbPort(u) => match u.product {
                Some(prod) => format!("{} ({prod})", p.port_name),
                None => p.port_name,
            },
            _ => p.port_name,
        })
        .collect();
    v.sort();
    v
}

fn open_tcp(addr: &str) -> Result<TcpStream, LinkError> {
    use std::net::ToSocketAddrs;
    let addrs: Vec<_> = addr
        .to_socket_addrs()
        .map_err(|e| LinkError::Open(format!("bad address {addr}: {e} (expected HOST:PORT)")))?
        .collect();
    let Some(a) = addrs.first() else {
        return Err(LinkError::Open(format!("bad address {addr}")));
    };
    let s = TcpStream::connect_timeout(a, Duration::from_secs(3)).map_err(|e| {
        LinkError::Open(match e.kind() {
            io::ErrorKind::ConnectionRefused => format!(
                "nothing listens on {addr} (start `hil-sim serve --tcp {addr}` or `vboard serve --tcp {addr}`, or give the port it printed)"
            ),
            io::ErrorKind::TimedOut => format!("{addr} does not answer (3 s)"),
            _ => format!("{addr}: {e}"),
        })
    })?;
    let _ = s.set_nodelay(true);
    s.set_read_timeout(Some(READ_SLICE))
        .map_err(|e| LinkError::Open(format!("{addr}: {e}")))?;
    s.set_write_timeout(Some(Duration::from_millis(50)))
        .map_err(|e| LinkError::Open(format!("{addr}: {e}")))?;
    Ok(s)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Tests run as root here, who opens any port: the message is checked on a file
    /// with a serial port's mode (crw-rw---- root:dialout on a Debian machine).
    #[test]
    fn permission_denied_names_the_group_that_may_open_the_port() {
        use std::os::unix::fs::PermissionsExt;
        let p = std::env::temp_dir().join(format!("dockctl-perm-{}", std::process::id()));
        std::fs::write(&p, b"").unwrap();
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o660)).unwrap();
        let path = p.to_str().unwrap();
        let gid = {
            use std::os::unix::fs::MetadataExt;
            std::fs::metadata(&p).unwrap().gid()
        };
        let group = group_name(gid).unwrap_or_else(|| gid.to_string());
        assert_eq!(
            permission_denied(path),
            format!("permission denied: {path} belongs to group {group}; join it (sudo usermod -aG {group} $USER), then log in again")
        );
        std::fs::set_permissions(&p, std::fs::Permissions::from_mode(0o600)).unwrap();
        assert!(permission_denied(path).contains("allow no one but root"));
        let _ = std::fs::remove_file(&p);
    }
}
