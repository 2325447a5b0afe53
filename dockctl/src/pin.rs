//! The maintenance PIN: from `--pin-file` (its first line), the environment
//! (`DOCKCTL_PIN`), or asked on the terminal without echo (rpassword). The question
//! waits in a thread of its own so that Ctrl-C is noticed while it is asked: the
//! terminal's settings are put back and the tool leaves the board as it found it.

use std::path::Path;
use std::sync::mpsc;
use std::time::Duration;

use crate::console::{cancelled, Cancel};
use crate::Error;

/// The environment variable a script may give the PIN in.
pub const ENV: &str = "DOCKCTL_PIN";

/// A PIN as the console takes it: 4-12 digits.
pub fn valid(pin: &str) -> bool {
    (4..=12).contains(&pin.len()) && pin.bytes().all(|b| b.is_ascii_digit())
}

/// The PIN from `file`, the environment, or the terminal (`tty`: stdin is one).
pub fn get(file: Option<&Path>, tty: bool, cancel: &Cancel) -> Result<String, Error> {
    let pin = if let Some(f) = file {
        let text = std::fs::read_to_string(f)
            .map_err(|e| Error::File(format!("cannot read the PIN file {}: {e}", f.display())))?;
        text.lines().next().unwrap_or("").trim().to_string()
    } else if let Ok(p) = std::env::var(ENV) {
        p.trim().to_string()
    } else if tty {
        ask(cancel)?
    } else {
        return Err(Error::Usage(format!(
            "the board needs its maintenance PIN: give --pin-file FILE or {ENV} (stdin is not a terminal to ask on)"
        )));
    };
    if !valid(&pin) {
        return Err(Error::Usage(
            "a maintenance PIN is 4-12 digits (nothing was sent)".into(),
        ));
    }
    Ok(pin)
}

/// Ask on the terminal, without echo.
fn ask(cancel: &Cancel) -> Result<String, Error> {
    let saved = Termios::save();
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(rpassword::prompt_password("maintenance PIN: "));
    });
    loop {
        match rx.recv_timeout(Duration::from_millis(50)) {
            Ok(Ok(p)) => return Ok(p),
            Ok(Err(e)) => return Err(Error::Usage(format!("cannot read the PIN: {e}"))),
            Err(mpsc::RecvTimeoutError::Timeout) if cancelled(cancel) => {
                // The question's thread stays blocked in its read; the terminal gets its
                // echo back here.
                if let Some(t) = saved {
                    t.restore();
                }
                eprintln!();
                return Err(Error::Interrupted);
            }
            Err(mpsc::RecvTimeoutError::Timeout) => {}
            Err(mpsc::RecvTimeoutError::Disconnected) => {
                return Err(Error::Usage("cannot read the PIN".into()))
            }
        }
    }
}

/// The controlling terminal's settings, to put back.
pub struct Termios(libc::termios);

impl Termios {
    /// The settings of /dev/tty now (`None`: no terminal).
    pub fn save() -> Option<Termios> {
        let f = std::fs::File::open("/dev/tty").ok()?;
        use std::os::fd::AsRawFd;
        // SAFETY: tcgetattr writes a termios into the zeroed struct we own; the fd is
        // open for the call.
        unsafe {
            let mut t: libc::termios = std::mem::zeroed();
            (libc::tcgetattr(f.as_raw_fd(), &mut t) == 0).then_some(Termios(t))
        }
    }

    /// Put them back.
    pub fn restore(&self) {
        use std::os::fd::AsRawFd;
        if let Ok(f) = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open("/dev/tty")
        {
            // SAFETY: the termios is one tcgetattr filled; the fd is open for the call.
            unsafe {
                libc::tcsetattr(f.as_raw_fd(), libc::TCSANOW, &self.0);
            }
        }
    }
}
