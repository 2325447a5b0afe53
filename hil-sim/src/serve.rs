//! `hil-sim serve`: the simulated controller in (scaled) real time, its technician
//! console bridged to a pseudo-terminal or a loopback TCP port, so a technician can
//! connect with `picocom`/`screen` (or `nc`) and practise.
//!
//! The first line on stdout is the pty's path or the bound address; the machine then
//! docks continuously (a new cycle whenever it is idle), with the scene's disturbance
//! injected in its first cycle. The bridge applies back-pressure: bytes are taken from
//! the link only as fast as the board's 256-byte receive ring drains, so a paste is not
//! lost to an overrun (a real UART without flow control would lose it).

use std::io::Write;
use std::net::SocketAddr;
use std::time::{Duration, Instant};

use docking_controller::sequencer::{Request, State};

use crate::console::RX_RING;
use crate::link::Bridge;
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
    let mut bridge = Bridge::open(&opts.link, out)?;
    let _ = out.flush();
    let mut rig = Rig::new(RigOptions {
        adc: AdcMode::Pins,
        ..RigOptions::new(opts.rate_sps)
    });
    // A board's boot: the reset cause counted and shown (`status`, `faults`).
    rig.ctrl
        .boot(docking_controller::diag::ResetCause::PowerOn, None, &[]);
    rig.console_enabled = true;
    driver.setup(rig.devices(), 1, opts.rate_sps, 1_000);
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
