//! The console as a script talks to it (docs/console.md): `echo off` (no echo, no
//! prompt: the bare line protocol), then one command a line and its reply, `--json` for
//! the reports (one JSON object on one line). What the tool changed on the console it
//! puts back when it leaves, on every path (Ctrl-C included): maintenance mode it
//! entered is left, and echo it turned off is turned on again.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::json::{short, J};
use crate::link::{Link, LinkError};
use crate::Error;

/// Ctrl-C: set by the signal handler (or a test), checked between reads.
pub type Cancel = Arc<AtomicBool>;

/// Whether Ctrl-C was pressed.
pub fn cancelled(c: &Cancel) -> bool {
    c.load(Ordering::SeqCst)
}

/// YMODEM's cancel, as the board's receiver takes it between packets.
const CAN: u8 = docking_logic::ymodem::CAN;

/// A session with the board's console.
pub struct Session {
    link: Link,
    /// Bytes received and not yet taken.
    buf: Vec<u8>,
    /// Ctrl-C.
    pub cancel: Cancel,
    /// How long a reply may take.
    pub timeout: Duration,
    /// Echo was on when the tool came (it is turned on again when it leaves).
    echo_was_on: bool,
    /// The tool entered maintenance mode (it leaves it when it goes).
    maint_ours: bool,
    /// Put back already.
    closed: bool,
    /// The board's update receiver holds the line (after `update` was accepted, until
    /// the transfer ended): leaving cancels it first.
    pub transfer_open: bool,
    /// What the board said about itself when the session began (`version --json`).
    pub version: J,
    /// Things worth telling the technician that happened on the way.
    pub notes: Vec<String>,
}

/// What the board's refusal of an update says, if `line` holds one (after whatever
/// the receiver sent before it on the same line).
pub fn refusal(line: &str) -> Option<&str> {
    const AT: &str = "error: update refused: ";
    line.find(AT).map(|i| line[i + AT.len()..].trim_end())
}

/// Bytes of a reply line that say the board restarted (its boot banner).
pub const BANNER: &str = "# docking-controller ";

impl Session {
    /// Open the console over `link`: find it (a board waiting for an update file is
    /// given CAN CAN first), note whether echo is on, turn it off, read `version`.
    pub fn connect(link: Link, cancel: Cancel, timeout: Duration) -> Result<Session, Error> {
        let mut s = Session {
            link,
            buf: Vec::new(),
            cancel,
            timeout,
            echo_was_on: false,
            maint_ours: false,
            closed: false,
            transfer_open: false,
            version: J::Null,
            notes: Vec::new(),
        };
        s.link.discard_input();
        s.sync()?;
        Ok(s)
    }

    /// What the line is.
    pub fn link_name(&self) -> String {
        self.link.target().describe()
    }

    fn sync(&mut self) -> Result<(), Error> {
        const ATTEMPTS: usize = 3;
        let mut heard = 0usize;
        let mut sample: Vec<u8> = Vec::new();
        let mut ymodem_cancelled = false;
        let started = Instant::now();
        for attempt in 0..ATTEMPTS {
            // Ctrl-C abandons a half-typed line (echo on) or spoils it (echo off: its
            // Enter then gets an error, never a command run); `echo` says which. The
            // second attempt after silence only listens: an update receiver cut off in
            // the middle of a block takes what comes as the block's bytes, and says
            // something ('C' or NAK) only after 3 s of quiet.
            let listen = attempt == 1 && heard == 0;
            if !listen {
                self.send_raw(b"\x03\r\necho\r\n")?;
            }
            let wait = if listen {
                Duration::from_millis(3_500)
            } else {
                self.timeout.min(Duration::from_secs(3))
            };
            let deadline = Instant::now() + wait;
            let mut echo = None;
            let mut got: Vec<u8> = Vec::new();
            while echo.is_none() {
                let Some(line) = self.line_until(deadline, &mut got)? else {
                    break;
                };
                match line.trim() {
                    "echo=on" => echo = Some(true),
                    "echo=off" => echo = Some(false),
                    l if l.starts_with("busy: ") => {
                        return Err(Error::Link(LinkError::Open(format!(
                            "port busy: {} says {:?}",
                            self.link_name(),
                            l
                        ))))
                    }
                    _ => {}
                }
            }
            heard += got.len();
            if sample.len() < 16 {
                sample.extend(got.iter().take(16 - sample.len()));
            }
            let Some(on) = echo else {
                // The board's update receiver holds the line ('C' before a file, NAK
                // inside one: a transfer left unfinished): cancel it, then try again.
                // ('C' before a file, NAK inside one, ACK for a block that was on its way
                // when the line went, CAN: the receiver's bytes, never a console line.)
                use docking_logic::ymodem::{ACK, NAK};
                let ymodem = !got.is_empty()
                    && got
                        .iter()
                        .all(|&b| matches!(b, b'C' | ACK | NAK | CAN | b'\r' | b'\n'));
                if ymodem && !ymodem_cancelled {
                    self.cancel_transfer()?;
                    ymodem_cancelled = true;
                    self.notes.push(
                        "the board was waiting for an update file (a transfer left unfinished): cancelled it; nothing was changed".into(),
                    );
                }
                continue;
            };
            self.echo_was_on = on;
            if on {
                // Echo is on until this line's reply: the line comes back first, after
                // the prompt.
                self.send_raw(b"echo off\r\n")?;
                let deadline = Instant::now() + self.timeout;
                loop {
                    match self.reply_until(deadline)? {
                        Some(r) if r.starts_with("ok: echo") => break,
                        Some(r) if r.starts_with("error: ") => {
                            return Err(Error::Protocol(format!(
                                "`echo off` answered {:?}",
                                short(&r)
                            )))
                        }
                        Some(_) => {}
                        None => {
                            return Err(Error::NoAnswer(format!(
                                "no reply to `echo off` within {} s",
                                self.timeout.as_secs_f64()
                            )))
                        }
                    }
                }
            }
            self.version = self.json("version")?;
            if self.version.text("name") != "docking-controller" {
                return Err(Error::Protocol(format!(
                    "not a docking controller: `version --json` answered {}",
                    short(&self.version.to_json())
                )));
            }
            return Ok(());
        }
        let tried = format!(
            "sent Ctrl-C, Enter and `echo` {} times over {:.0} s",
            if heard == 0 { ATTEMPTS - 1 } else { ATTEMPTS },
            started.elapsed().as_secs_f64()
        );
        let what = self.link_name();
        Err(Error::NoAnswer(if heard == 0 {
            format!(
                "nothing answers on {what}: {tried} and no byte came back; check the cable and the port, and that the board is powered"
            )
        } else {
            format!(
                "{heard} bytes came back on {what} but not the console's replies (first: {}): a wrong baud rate? the console runs at 115200 8N1; {tried}",
                hex(&sample)
            )
        }))
    }

    /// Cancel a YMODEM transfer the board waits in: CAN CAN (more than once: a CAN
    /// inside a packet the receiver is still collecting is taken as data), then its
    /// refusal line, which comes once the line has been quiet for a second.
    pub fn cancel_transfer(&mut self) -> Result<Option<String>, Error> {
        for _ in 0..3 {
            self.send_raw(&[CAN; 8])?;
            let deadline = Instant::now() + Duration::from_secs(4);
            let mut got = Vec::new();
            while let Some(line) = self.line_until(deadline, &mut got)? {
                // The receiver's last ACK or NAK may come first, on the same line.
                if let Some(why) = refusal(&line) {
                    return Ok(Some(why.to_string()));
                }
            }
        }
        // Not seen: if the receiver had ended after all, the CANs are control
        // characters in a line of the console's; Enter ends it (an error line).
        self.send_raw(b"\r\n")?;
        let mut got = Vec::new();
        while self
            .line_until(Instant::now() + Duration::from_millis(500), &mut got)?
            .is_some()
        {}
        Ok(None)
    }

    /// Send bytes as they are.
    pub fn send_raw(&mut self, bytes: &[u8]) -> Result<(), Error> {
        self.link.write_all(bytes).map_err(Error::Link)
    }

    /// The next byte from the board, waiting until `deadline` (`None`: none came).
    /// Ctrl-C is an error here.
    pub fn byte_until(&mut self, deadline: Instant) -> Result<Option<u8>, Error> {
        loop {
            if !self.buf.is_empty() {
                return Ok(Some(self.buf.remove(0)));
            }
            if cancelled(&self.cancel) {
                return Err(Error::Interrupted);
            }
            if Instant::now() >= deadline {
                return Ok(None);
            }
            self.fill()?;
        }
    }

    /// Read what the line has (one slice of [`crate::link::READ_SLICE`]).
    fn fill(&mut self) -> Result<usize, Error> {
        let mut b = [0u8; 4096];
        let n = self.link.read(&mut b).map_err(Error::Link)?;
        self.buf.extend_from_slice(&b[..n]);
        Ok(n)
    }

    /// The next whole line (without its CR LF), waiting until `deadline`; every byte
    /// taken is also appended to `seen`. Ctrl-C is an error here.
    fn line_until(
        &mut self,
        deadline: Instant,
        seen: &mut Vec<u8>,
    ) -> Result<Option<String>, Error> {
        loop {
            if let Some(at) = self.buf.iter().position(|&b| b == b'\n') {
                let raw: Vec<u8> = self.buf.drain(..=at).collect();
                seen.extend_from_slice(&raw);
                let text = String::from_utf8_lossy(&raw);
                return Ok(Some(text.trim_end_matches(['\r', '\n']).to_string()));
            }
            if cancelled(&self.cancel) {
                return Err(Error::Interrupted);
            }
            if Instant::now() >= deadline {
                seen.extend_from_slice(&self.buf);
                return Ok(None);
            }
            self.fill()?;
        }
    }

    /// The next line that is a reply (not blank, not a boot banner), by `deadline`.
    pub fn reply_until(&mut self, deadline: Instant) -> Result<Option<String>, Error> {
        let mut seen = Vec::new();
        while let Some(line) = self.line_until(deadline, &mut seen)? {
            // A console line never starts with a control character: one there is the
            // update receiver's (its last ACK, a NAK) or the line's noise.
            let l = line.trim_start_matches(|c: char| c.is_ascii_control());
            if l.trim().is_empty() {
                continue;
            }
            if l.starts_with(BANNER) {
                return Err(Error::Restarted(l.to_string()));
            }
            return Ok(Some(l.to_string()));
        }
        Ok(None)
    }

    /// Send `cmd` and return its one-line reply.
    pub fn request(&mut self, cmd: &str) -> Result<String, Error> {
        self.send_raw(format!("{cmd}\r\n").as_bytes())?;
        let shown = if cmd.starts_with("maint ") && cmd != "maint exit" {
            "maint ****".to_string()
        } else {
            format!("`{cmd}`")
        };
        match self.reply_until(Instant::now() + self.timeout)? {
            Some(l) => Ok(l),
            None => Err(Error::NoAnswer(format!(
                "no reply to {shown} within {} s on {}",
                self.timeout.as_secs_f64(),
                self.link_name()
            ))),
        }
    }

    /// `cmd --json`: the board's object, or its `error: ` as [`Error::Board`].
    pub fn json(&mut self, cmd: &str) -> Result<J, Error> {
        let line = self.request(&format!("{cmd} --json"))?;
        if let Some(e) = line.strip_prefix("error: ") {
            return Err(Error::Board(e.to_string()));
        }
        J::parse(&line).map_err(|e| Error::Protocol(format!("`{cmd} --json`: {e}")))
    }

    /// `cmd --json`'s reply line as the board sent it (checked to be JSON).
    pub fn json_line(&mut self, cmd: &str) -> Result<(String, J), Error> {
        let line = self.request(&format!("{cmd} --json"))?;
        if let Some(e) = line.strip_prefix("error: ") {
            return Err(Error::Board(e.to_string()));
        }
        let j = J::parse(&line).map_err(|e| Error::Protocol(format!("`{cmd} --json`: {e}")))?;
        Ok((line, j))
    }

    /// Enter maintenance mode with `pin` (left again when the session ends).
    pub fn enter_maintenance(&mut self, pin: &str) -> Result<(), Error> {
        let r = self.request(&format!("maint {pin}"))?;
        if r.starts_with("ok: maintenance mode") {
            self.maint_ours = true;
            return Ok(());
        }
        match r.strip_prefix("error: ") {
            Some(e) => Err(Error::Pin(e.to_string())),
            None => Err(Error::Protocol(format!("`maint` answered {:?}", short(&r)))),
        }
    }

    /// Whether the tool holds maintenance mode (it entered it).
    pub fn maintenance_is_ours(&self) -> bool {
        self.maint_ours
    }

    /// The board said it restarts (an update verified): its restart ends maintenance
    /// mode and turns echo on, so leaving puts nothing back until the console is found
    /// again ([`Session::after_restart`]).
    pub fn board_restarts(&mut self) {
        self.maint_ours = false;
        self.echo_was_on = false;
    }

    /// The board restarted (an update): echo is on again and maintenance mode is over.
    /// Find the console again as at the start; echo is turned on again at the end, as
    /// the restart left it.
    pub fn after_restart(&mut self) -> Result<(), Error> {
        self.maint_ours = false;
        self.sync()?;
        self.echo_was_on = true;
        Ok(())
    }

    /// Put the console back as the tool found it: maintenance mode left (if the tool
    /// entered it), echo on (if it was). Ctrl-C no longer interrupts this. What could
    /// not be put back is returned, for the technician.
    pub fn close(&mut self) -> Vec<String> {
        if self.closed {
            return Vec::new();
        }
        self.closed = true;
        let mut left = Vec::new();
        let saved = std::mem::replace(&mut self.cancel, Arc::new(AtomicBool::new(false)));
        let timeout = self.timeout;
        self.timeout = timeout.min(Duration::from_secs(3));
        if self.transfer_open {
            let _ = self.cancel_transfer();
            self.transfer_open = false;
        }
        if self.maint_ours {
            match self.request("maint exit") {
                Ok(r) if r.starts_with("ok:") => self.maint_ours = false,
                Ok(r) => left.push(format!(
                    "could not leave maintenance mode (the board said {:?}): it ends by itself after 10 min idle, or type `maint exit`",
                    short(&r)
                )),
                Err(e) => left.push(format!(
                    "could not leave maintenance mode ({e}): it ends by itself after 10 min idle, or type `maint exit`"
                )),
            }
        }
        if self.echo_was_on {
            let _ = self.request("echo on");
        }
        self.link.drain();
        self.cancel = saved;
        self.timeout = timeout;
        left
    }
}

impl Drop for Session {
    fn drop(&mut self) {
        for l in self.close() {
            eprintln!("dockctl: {l}");
        }
    }
}

/// Up to 16 bytes in hex.
fn hex(b: &[u8]) -> String {
    b.iter()
        .take(16)
        .map(|x| format!("{x:02x}"))
        .collect::<Vec<_>>()
        .join(" ")
}

impl From<LinkError> for Error {
    fn from(e: LinkError) -> Self {
        Error::Link(e)
    }
}
