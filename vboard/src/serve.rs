//! `vboard serve`: the image in (scaled) real time, its USART2 on a pseudo-terminal or a
//! loopback TCP port, so a technician talks to the real firmware with picocom, like
//! `hil-sim serve` talks to the library. The machine docks whenever it is at rest.
//!
//! The far end sends at the line rate (115 200 baud) with no flow control, as a
//! terminal does: a paste longer than the firmware's receive ring can absorb is partly
//! lost, as on the board.

use std::io::Write;
use std::time::{Duration, Instant};

use hil_sim::link::Bridge;
use hil_sim::serve::Link;

use crate::scene::{Options, Session, PS_PER_MS};
use crate::time::PS_PER_S;

/// Options.
#[derive(Clone, Debug)]
pub struct ServeOptions {
    /// Link.
    pub link: Link,
    /// Session.
    pub session: Options,
    /// Virtual seconds per wall second (the emulation may be slower: then it runs as
    /// fast as it can).
    pub speed: f64,
    /// Stop after this many wall seconds.
    pub duration_s: Option<f64>,
}

/// Run until killed (or `duration_s`); the first line on stdout is the link's address.
pub fn run(opts: &ServeOptions, out: &mut dyn Write) -> Result<(), String> {
    if !(opts.speed.is_finite() && opts.speed > 0.0) {
        return Err(format!(
            "--speed must be a positive number, got {}",
            opts.speed
        ));
    }
    let mut bridge = Bridge::open(&opts.link, out)?;
    let _ = out.flush();
    let mut s = Session::new(opts.session.clone())?;
    let start = Instant::now();
    let mut sent = 0usize;
    loop {
        let wall = start.elapsed().as_secs_f64();
        if opts.duration_s.is_some_and(|d| wall >= d) {
            return Ok(());
        }
        let target = (wall * opts.speed * PS_PER_S as f64) as u64;
        let slice_end = Instant::now() + Duration::from_millis(20);
        while s.now() < target && Instant::now() < slice_end {
            s.run_for(PS_PER_MS).map_err(|e| e.to_string())?;
            s.auto_dock(u32::MAX);
        }
        let bytes = bridge.read(256);
        if !bytes.is_empty() {
            let _ = s.board.soc_mut().console_send(&bytes);
        }
        let outb: Vec<u8> = s.board.soc().console_out[sent..]
            .iter()
            .map(|&(_, b)| b)
            .collect();
        sent = s.board.soc().console_out.len();
        bridge.write(&outb);
        if s.now() >= target {
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}
