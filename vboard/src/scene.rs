//! Scenes on the virtual board: the image docks against the simulated machine, with the
//! disturbances of `hil-sim scene` (one definition: [`hil_sim::scene::SceneDriver`]).
//!
//! The board sees the firmware only from outside, as a test bench would: the pins (the
//! axis and lock models record what they were driven to do), the defmt log over RTT, and
//! the console on USART2. The vehicle's PLC docks as it would in service: it asserts
//! DOCK (PC4, a level) when READY is high and releases it to undock — for a test cycle
//! once MATED has been high for the hold time (1 s; an hour in `dock-hold`).
//!
//! | scene | what happens |
//! |---|---|
//! | `boot` | power-on → home → idle, no request |
//! | the scenes of `hil-sim scene` | the same disturbance at the same moment |
//! | `sector-move` | the odometer log is filled (through the firmware's own record format) until the next record write makes the firmware erase a sector, with the watchdog running |
//! | `power-cut-write` | a pin reset at a random instant inside a record write, then a reboot on the same flash |
//! | `power-cycle` | a pin reset in the middle of an insertion: after the reboot nothing may move until a request (DOCK released and asserted again), then the machine homes out of the cone |
//!
//! | `estop-bounce` | the host rig's disturbances ([`ESTOP_BOUNCE`]) at the board's own timing: a 50 µs pulse is 50 µs on the EXTI line, a bouncing release closes, opens for 100, 50 and 20 µs with 200 µs closed between; the edges the firmware logs as latched must be the edges made, the PLC's clears go over Modbus |
//! | `heavy-default` | the 18 kg machine (µ2 0.1) on the default configuration, one test cycle: one overload, the back-off done, and a console `clear-fault` takes it home out of the cone |
//! | `maintenance-lockout` | the technician's `pin set` / `maint <pin>` on USART2, the PLC's reads and coil writes on USART3 and its DOCK pin; READY (PD0) judged on its recorded edges |
//!
//! `dock-hold`, `vehicle-pull`, `estop` and `estop-bounce` are the host rig's in-service
//! scenes; here the E-STOP's edge to EN high and the lock bridge low is measured on the
//! pins.
//!
//! Every scene also reports, **over the time anything moves** (EN low or a lock bridge
//! input high, on the pins; see [`crate::realtime`]), the longest interval between
//! entries of the control task's interrupt (TIM2) on the NVIC model
//! (`control_period_max_ms`), how many exceeded the sample period + 1 ms
//! (`control_late`), the longest wait of that interrupt from pending to entered
//! (`control_entry_latency_max_us`; over the whole run, rest and boot included:
//! `control_entry_latency_max_us_all`), and the gaps between watchdog reloads (`KR` = 0xAAAA) on the IWDG
//! model longer than 3 sample periods (`watchdog_feeds_missed`); and for every E-STOP
//! edge while something moved, the edge to EN high and the lock off
//! (`estop_off_max_us`).

use std::time::Instant;

use hil_sim::flash::{SharedFlash, SimFlash};
use hil_sim::rig::{Machine, RigOptions};
use hil_sim::scene::{
    num, EstopDisturbance, FaultSeen, PlcReport, Progress, SceneDriver, SceneReport, SpikeTally,
    Stage, BOUNCE_GAP_US, BOUNCE_OPEN_MS, BOUNCE_RELEASE_US, DOCK_HOLD_S, ESTOP_BOUNCE,
    ESTOP_BOUNCE_DEPTH_UM, FLOOD_PIECES, PLC_SCENES,
};

use crate::cpu::{Board, BoardConfig, Halt};
use crate::image::Image;
use crate::periph::flash::FlashTiming;
use crate::periph::rcc::ResetCause;
use crate::realtime::{estop_reactions, moving_windows, ControlTiming};
use crate::rtt::LogLine;
use crate::time::PS_PER_S;
use crate::world::World;

/// The reply to `line` in what the console sent after it: the echo of the line
/// (echo is on at every reset), a banner (`# …`, after a reset) and the prompt left
/// out, so the scenes read the same text as over `echo off`.
fn script_reply(raw: &str, line: &str) -> String {
    let secret = |l: &str| l.starts_with("maint ") || l.starts_with("pin set ");
    let mut out = String::new();
    let mut first = true;
    for seg in raw.split_inclusive("\r\n") {
        let text = seg.trim_end_matches("\r\n");
        let is_echo = first && (text == line || (secret(line) && secret(text)));
        first = false;
        let is_prompt = !seg.ends_with("\r\n") && (text.ends_with("> ") || text.ends_with("# "));
        if is_echo || is_prompt || text.starts_with("# docking-controller ") {
            continue;
        }
        out.push_str(seg);
    }
    out
}

/// Picoseconds per millisecond.
pub const PS_PER_MS: u64 = 1_000_000_000;

/// Options of a session.
#[derive(Clone, Debug)]
pub struct Options {
    /// Firmware image (ELF).
    pub firmware: String,
    /// HX711 rate, SPS (the board's RATE pin: 10 or 80; 320 is not an HX711 rate).
    pub rate_sps: u32,
    /// Noise seed.
    pub seed: u64,
    /// Board configuration (CPI, LSI, flash timing).
    pub board: BoardConfig,
    /// A technician has calibrated the load cell: a new board's odometer flash holds the
    /// calibration (without one the firmware refuses to dock).
    pub commissioned: bool,
    /// The machine's contact forces (Eq. 7, or another machine's plant).
    pub force_model: hil_sim::machine::ForceModel,
}

impl Options {
    /// The release image at 80 SPS, seed 1, CPI 1, LSI 32 kHz, maximum flash times.
    pub fn new() -> Self {
        Self {
            firmware: crate::image::default_path(),
            rate_sps: 80,
            seed: 1,
            board: BoardConfig::default(),
            commissioned: true,
            force_model: hil_sim::machine::ForceModel::Eq7,
        }
    }
}

impl Default for Options {
    fn default() -> Self {
        Self::new()
    }
}

/// What the log says so far.
#[derive(Clone, Debug, Default)]
pub struct Observed {
    /// Cycles the firmware logged as completed.
    pub cycles_completed: u32,
    /// Cycles it logged as started.
    pub cycles_started: u32,
    /// Faults it logged.
    pub faults: Vec<FaultSeen>,
    /// Contact phases entered on each insertion.
    pub insertion_phases: Vec<Vec<u8>>,
    /// The firmware logged that it booted, this many times.
    pub boots: u32,
    /// E-STOP edges the firmware logged having latched (`E-STOP: N edge(s), …`).
    pub estop_edges_logged: u32,
    /// Each stroke's signature verdict the firmware logged (`signature: cycle N
    /// insertion ok`, `… nok band3 figure …`).
    pub signatures: Vec<hil_sim::sigscene::SignatureSeen>,
    /// Lines read so far.
    cursor: usize,
    /// The current insertion is over (a phase went down: extraction).
    extracting: bool,
}

/// A board with the image running, and the machine around it.
pub struct Session {
    /// The board.
    pub board: Board,
    /// Options.
    pub opts: Options,
    /// The log, interpreted.
    pub seen: Observed,
    /// Where the rod meets the cone (insertion depth 0), µm.
    pub engage_um: i32,
    /// DOCK is asserted (by [`Session::set_dock`]).
    dock: bool,
    /// When DOCK last changed, ps.
    dock_changed_ps: Option<u64>,
    /// MATED high since, ps.
    mated_since_ps: Option<u64>,
    /// How long a test cycle holds mated before the PLC releases DOCK, ps.
    pub hold_ps: u64,
    /// A test cycle is under way: release DOCK after the hold (or on a fault).
    test_cycle: bool,
    /// The E-STOP input's level as the board last saw it (`true`: open).
    estop_open: bool,
    /// Every edge of the E-STOP input: (time ps, opened).
    pub estop_edges: Vec<(u64, bool)>,
    /// A PLC's master polling the Modbus line (`crate::poller`; every 100 ms in the
    /// scenes that time the line's replies, issue 31), checking each reply.
    pub poller: Option<crate::poller::Poller>,
}

/// The control task's exception: TIM2 (IRQ 28).
pub const CONTROL_EXCEPTION: u32 = crate::periph::nvic::exc::IRQ0 + 28;

/// Load `path` (once per process: the table of a loaded image is kept).
fn image(path: &str) -> Result<Image, String> {
    Image::load(path)
}

impl Session {
    /// Power on a board with a fresh odometer flash.
    pub fn new(opts: Options) -> Result<Self, String> {
        Self::with_flash(opts, SharedFlash::new(SimFlash::stm32f407_odometer()))
    }

    /// Power on a board whose odometer sectors hold `flash`.
    pub fn with_flash(opts: Options, flash: SharedFlash) -> Result<Self, String> {
        let img = image(&opts.firmware)?;
        Self::with_image(opts, img, flash)
    }

    /// Power on a board with `img` in its code flash (a snapshot of another board's,
    /// say) and `flash` in the odometer's sectors.
    pub fn with_image(opts: Options, img: Image, flash: SharedFlash) -> Result<Self, String> {
        let machine = Machine::new(&RigOptions {
            seed: opts.seed,
            force_model: opts.force_model,
            ..RigOptions::new(opts.rate_sps)
        });
        if opts.commissioned {
            hil_sim::rig::commission(&flash, &machine.hx_config);
        }
        let world = World::new(machine, flash);
        let mut board = Board::new(img, world, opts.board)?;
        board.watch_masking();
        board.soc_mut().entry_log.watch(CONTROL_EXCEPTION);
        board.power_on();
        Ok(Self {
            board,
            engage_um: docking_logic::config::MachineConfig::DEFAULT.engage_um,
            opts,
            seen: Observed::default(),
            dock: false,
            dock_changed_ps: None,
            mated_since_ps: None,
            hold_ps: u64::from(docking_logic::config::MachineConfig::DEFAULT.hold_ms) * PS_PER_MS,
            test_cycle: false,
            estop_open: false,
            estop_edges: Vec::new(),
            poller: None,
        })
    }

    /// Now, ps.
    pub fn now(&self) -> u64 {
        self.board.now()
    }

    /// The simulated machine.
    pub fn machine(&self) -> &Machine {
        &self.board.soc().world.machine
    }

    /// Run `dt_ps` more, in 1 ms steps, reading the log as it comes.
    pub fn run_for(&mut self, dt_ps: u64) -> Result<(), Halt> {
        let mut end = self.now() + dt_ps;
        // Whole milliseconds end on the millisecond grid (see `run_until`).
        if dt_ps % PS_PER_MS == 0 {
            end -= end % PS_PER_MS;
        }
        self.run_until(end, |_| false).map(|_| ())
    }

    /// Run until `pred` holds (checked every millisecond) or until `deadline_ps`;
    /// returns whether `pred` held.
    pub fn run_until(
        &mut self,
        deadline_ps: u64,
        mut pred: impl FnMut(&Session) -> bool,
    ) -> Result<bool, Halt> {
        loop {
            if pred(self) {
                return Ok(true);
            }
            let now = self.now();
            if now >= deadline_ps {
                return Ok(false);
            }
            // On the millisecond grid, not a millisecond after wherever the board stopped
            // (it stops at the first instruction past the step's end): the scene's
            // stimuli (the masters on the lines, the PLC) then come at the same instants
            // whether or not the emulator jumped over a polling loop (`--no-skip`).
            let step_end = ((now / PS_PER_MS + 1) * PS_PER_MS).min(deadline_ps);
            self.board.run_until(step_end)?;
            self.tick();
        }
    }

    /// Housekeeping every millisecond: read the log, watch MATED, poll the Modbus line
    /// (when a master polls: `poller`).
    fn tick(&mut self) {
        self.board.poll_rtt();
        self.observe();
        if let Some(mut p) = self.poller.take() {
            p.tick(self);
            self.poller = Some(p);
        }
        let out = self.plc_out();
        match (out.mated, self.mated_since_ps) {
            (true, None) => self.mated_since_ps = Some(self.now()),
            (false, Some(_)) => self.mated_since_ps = None,
            _ => {}
        }
        if self.test_cycle && (out.fault || self.mated_for_ps() >= self.hold_ps) {
            self.test_cycle = false;
            self.set_dock(false);
        }
    }

    /// The PLC asks for one test cycle: DOCK asserted now, released once MATED has been
    /// high for [`Session::hold_ps`] (or on FAULT).
    pub fn press_dock(&mut self) {
        self.set_dock(true);
        self.test_cycle = true;
    }

    /// The PLC asserts (`true`) or releases DOCK.
    pub fn set_dock(&mut self, asserted: bool) {
        if self.dock != asserted {
            self.dock = asserted;
            self.dock_changed_ps = Some(self.now());
            self.machine().dock_request.set(!asserted);
        }
    }

    /// The PLC opens (`true`) or closes the E-STOP contact. The EXTI sees the edge at
    /// once (it is asynchronous on the part).
    pub fn set_estop(&mut self, open: bool) {
        self.machine().estop.set(open);
        self.inputs_changed();
    }

    /// The E-STOP input opens for `open_ps`, then closes (in the board's own time: the
    /// EXTI sees both edges where they are).
    pub fn estop_pulse(&mut self, open_ps: u64) -> Result<(), Halt> {
        self.set_estop(true);
        let t = self.now() + open_ps;
        self.board.run_until(t)?;
        self.set_estop(false);
        Ok(())
    }

    /// Run `dt_ps` without the millisecond housekeeping (a sub-millisecond wait).
    pub fn run_exact(&mut self, dt_ps: u64) -> Result<(), Halt> {
        let t = self.now() + dt_ps;
        self.board.run_until(t)
    }

    /// At rest by the pins alone: home, locked, driver off, READY high.
    pub fn home_and_ready(&self) -> bool {
        let m = self.machine();
        m.axis.pos_um() <= 0.0
            && m.lock.fraction_locked() >= 1.0
            && !m.axis.enabled()
            && !m.lock.driven()
            && self.plc_out().ready
    }

    /// A scene changed an input line: let the EXTI see it now.
    pub fn inputs_changed(&mut self) {
        let open = self.machine().estop.is_high();
        if open != self.estop_open {
            self.estop_open = open;
            self.estop_edges.push((self.now(), open));
        }
        let soc = self.board.soc_mut();
        soc.sample_exti();
        soc.update_lines();
    }

    /// The handshake outputs on the pins.
    pub fn plc_out(&self) -> crate::world::PlcOutputs {
        self.board.soc().world.plc_out
    }

    /// How long MATED has been high, ps (0: low).
    pub fn mated_for_ps(&self) -> u64 {
        self.mated_since_ps
            .map_or(0, |t| self.now().saturating_sub(t))
    }

    /// Whether the machine is at rest: idle by the log, home, locked, driver off.
    pub fn at_rest(&self) -> bool {
        let m = self.machine();
        self.progress().stage == Stage::Idle
            && m.axis.pos_um() <= 0.0
            && m.lock.fraction_locked() >= 1.0
            && !m.axis.enabled()
    }

    /// The PLC's test cycles: a [`Session::press_dock`] when READY (at rest, no fault,
    /// fewer than `cycles` done, DOCK released for 200 ms at least).
    pub fn auto_dock(&mut self, cycles: u32) {
        let now = self.now();
        let settled = self
            .dock_changed_ps
            .is_none_or(|t| now > t + 200 * PS_PER_MS);
        if !self.dock
            && self.at_rest()
            && self.plc_out().ready
            && self.seen.faults.is_empty()
            && self.seen.cycles_completed < cycles
            && self.seen.cycles_started == self.seen.cycles_completed
            && settled
        {
            self.press_dock();
        }
    }

    /// Forget what happened before `t_ps` that only reports read back (pin edges but
    /// the last of each signal before it, the control task's entries and pends, the
    /// watchdog's reloads, the console's output, log lines already read): a `serve`
    /// that runs for days keeps its memory bounded. Reports over a run that forgot are
    /// reports of what it kept.
    pub fn forget_before(&mut self, t_ps: u64) {
        self.observe();
        let log = std::mem::take(&mut self.board.log);
        self.board.log = log.into_iter().skip(self.seen.cursor).collect();
        self.seen.cursor = 0;
        let soc = self.board.soc_mut();
        let mut last: Vec<(crate::world::Signal, usize)> = Vec::new();
        for (i, e) in soc
            .edges
            .iter()
            .enumerate()
            .take_while(|(_, e)| e.t_ps < t_ps)
        {
            match last.iter_mut().find(|(s, _)| *s == e.signal) {
                Some(l) => l.1 = i,
                None => last.push((e.signal, i)),
            }
        }
        let mut i = 0;
        soc.edges.retain(|e| {
            let keep = e.t_ps >= t_ps || last.iter().any(|&(_, j)| j == i);
            i += 1;
            keep
        });
        soc.entry_log.entries.retain(|&(_, t)| t >= t_ps);
        soc.entry_log.pends.retain(|&(_, t)| t >= t_ps);
        soc.feeds.forget_before(t_ps);
        soc.console_out.retain(|&(t, _)| t >= t_ps);
    }

    /// Interpret new log lines.
    fn observe(&mut self) {
        let lines: Vec<LogLine> = self.board.log[self.seen.cursor..].to_vec();
        self.seen.cursor = self.board.log.len();
        for l in lines {
            let m = l.msg.as_str();
            let words: Vec<&str> = m.split_whitespace().collect();
            match words.as_slice() {
                ["cycle", n, "started"] => {
                    self.seen.cycles_started = n.parse().unwrap_or(self.seen.cycles_started);
                    self.seen.insertion_phases.push(Vec::new());
                    self.seen.extracting = false;
                }
                ["cycle", n, "completed:", ..] => {
                    self.seen.cycles_completed = n.parse().unwrap_or(self.seen.cycles_completed);
                }
                ["contact", "phase", p] => {
                    if let (Ok(p), Some(v)) =
                        (p.parse::<u8>(), self.seen.insertion_phases.last_mut())
                    {
                        if v.last().is_some_and(|&l| p < l) {
                            self.seen.extracting = true;
                        }
                        if !self.seen.extracting {
                            v.push(p);
                        }
                    }
                }
                ["fault", kind, "in", "cycle", c, "at", t, "ms,", "force", f, "mN"] => {
                    let kind: &'static str = docking_controller_fault_name(kind);
                    self.seen.faults.push(FaultSeen {
                        kind,
                        cycle: c.parse().unwrap_or(0),
                        phase: None,
                        t_s: t.parse::<f64>().unwrap_or(0.0) / 1000.0,
                        peak_force_n: f.parse::<f64>().unwrap_or(0.0) / 1000.0,
                    });
                }
                ["docking-controller", _, "booted;", ..] => self.seen.boots += 1,
                ["E-STOP:", n, "edge(s),", ..] => {
                    self.seen.estop_edges_logged += n.parse::<u32>().unwrap_or(0);
                }
                ["signature:", "cycle", n, stroke @ ("insertion" | "extraction"), verdict, rest @ ..] =>
                {
                    let name = |w: &str| {
                        docking_logic::signature::objects::Object::ALL
                            .into_iter()
                            .map(docking_logic::signature::objects::Object::name)
                            .find(|o| *o == w)
                    };
                    self.seen.signatures.push(hil_sim::sigscene::SignatureSeen {
                        cycle: n.parse().unwrap_or(0),
                        stroke: if *stroke == "insertion" {
                            "insertion"
                        } else {
                            "extraction"
                        },
                        ok: *verdict == "ok",
                        failed: rest.first().and_then(|w| name(w)),
                    });
                }
                _ => {}
            }
        }
    }

    /// The machine's progress as the pins and the log show it.
    pub fn progress(&self) -> Progress {
        let m = self.machine();
        let pos_um = m.axis.pos_um();
        let depth_um = pos_um as i32 - self.engage_um;
        let in_cycle =
            self.seen.cycles_started > self.seen.cycles_completed && self.seen.faults.is_empty();
        let moving = m.axis.enabled();
        let locked = m.lock.fraction_locked() >= 1.0;
        let released = m.lock.fraction_locked() <= 0.0;
        let stage = if !in_cycle {
            Stage::Idle
        } else if self.plc_out().mated {
            Stage::Mated
        } else if moving && locked && m.axis.forward() && depth_um < 0 {
            Stage::PreAlign
        } else if moving && released && m.axis.forward() && !self.seen.extracting {
            Stage::Inserting
        } else if moving && locked && !m.axis.forward() && self.seen.extracting {
            Stage::Returning
        } else {
            Stage::Other
        };
        Progress {
            cycles_completed: self.seen.cycles_completed,
            stage,
            depth_um,
        }
    }

    /// Type `line` on the console and wait for the reply (ends with CR LF and nothing
    /// more for 20 ms), at most `timeout_ps`.
    pub fn console(&mut self, line: &str, timeout_ps: u64) -> Result<String, Halt> {
        let start = self.board.soc().console_out.len();
        let mut bytes = line.as_bytes().to_vec();
        bytes.extend_from_slice(b"\r\n");
        let _ = self.board.soc_mut().console_send(&bytes);
        let deadline = self.now() + timeout_ps;
        let mut quiet_since: Option<(usize, u64)> = None;
        self.run_until(deadline, |s| {
            let out = &s.board.soc().console_out;
            let n = out.len();
            // A reply ends with CR LF, followed (echo on) by the prompt `STATE> `.
            let tail: Vec<u8> = out[start.min(n)..]
                .iter()
                .rev()
                .take(2)
                .map(|&(_, b)| b)
                .collect();
            let done = n > start
                && (tail.first() == Some(&b'\n')
                    || (tail == [b' ', b'>'] || tail == [b' ', b'#'])
                        && out[start..].iter().any(|&(_, b)| b == b'\n'));
            if !done || s.board.soc().usart2.far_pending() > 0 {
                return false;
            }
            match quiet_since {
                Some((m, t)) if m == n => s.now() >= t + 20 * PS_PER_MS,
                _ => {
                    quiet_since = Some((n, s.now()));
                    false
                }
            }
        })?;
        let out: Vec<u8> = self.board.soc().console_out[start..]
            .iter()
            .map(|&(_, b)| b)
            .collect();
        let raw = String::from_utf8_lossy(&out).into_owned();
        let reply = script_reply(&raw, line);
        if std::env::var_os("VBOARD_TRACE_CONSOLE").is_some() {
            eprintln!("[{:.6} s] > {line}\n{reply}", self.now() as f64 * 1e-12);
        }
        Ok(reply)
    }

    /// The technician enters maintenance mode with PIN 2468 (setting it first on a board
    /// that has none); whether the console said ok. A reply a lost byte spoiled is
    /// typed again (three times at most).
    pub fn maint_enter(&mut self) -> Result<bool, Halt> {
        for _ in 0..3 {
            let r = self.console("maint 2468", 5 * PS_PER_S)?;
            if r.starts_with("ok") {
                return Ok(true);
            }
            if r.contains("no maintenance PIN") {
                self.console("pin set 2468", 5 * PS_PER_S)?;
            }
        }
        Ok(false)
    }

    /// The technician leaves maintenance mode; whether the console said ok.
    pub fn maint_exit(&mut self) -> Result<bool, Halt> {
        for _ in 0..3 {
            if self.console("maint exit", 2 * PS_PER_S)?.starts_with("ok") {
                return Ok(true);
            }
        }
        Ok(false)
    }

    /// Ask `cmd` (a `--json` command) until a JSON reply comes (a byte the one-byte
    /// receive register lost makes an error reply; a technician types it again), at most
    /// three times.
    pub fn console_json(&mut self, cmd: &str) -> Result<String, Halt> {
        let mut last = String::new();
        for _ in 0..3 {
            last = self.console(cmd, 2 * PS_PER_S)?;
            if last.trim_start().starts_with('{') {
                break;
            }
        }
        Ok(last)
    }

    /// The reset causes so far (the power-on included), by name.
    pub fn reset_causes(&self) -> Vec<&'static str> {
        self.board.resets.iter().map(|(_, c)| c.name()).collect()
    }

    /// The sample period, ps.
    pub fn period_ps(&self) -> u64 {
        PS_PER_S / u64::from(self.opts.rate_sps.max(1))
    }

    /// The control step's period (the control task's entries on the NVIC model), its
    /// entry latency (pend → entry on the NVIC model) and the watchdog's feeding
    /// (reloads on the IWDG model) so far, over the time anything moved
    /// ([`crate::realtime`]).
    pub fn control_timing(&self) -> ControlTiming {
        let soc = self.board.soc();
        let end = self.now();
        let resets: Vec<u64> = self.board.resets.iter().map(|&(t, _)| t).collect();
        ControlTiming::measure(
            &soc.entry_log.times(CONTROL_EXCEPTION),
            &soc.entry_log.pend_times(CONTROL_EXCEPTION),
            &soc.feeds.bursts,
            &resets,
            end,
            &moving_windows(&soc.edges, end),
            self.period_ps(),
        )
    }

    /// For every E-STOP edge so far at which anything moved: edge → EN high and the lock
    /// bridge off, on the pins, µs (`None`: they never went off).
    pub fn estop_reactions_us(&self) -> Vec<Option<f64>> {
        estop_reactions(&self.estop_edges, &self.board.soc().edges)
    }

    /// Watchdog resets so far.
    pub fn watchdog_resets(&self) -> usize {
        self.board
            .resets
            .iter()
            .filter(|(_, c)| *c == ResetCause::Watchdog)
            .count()
    }
}

/// A Modbus RTU frame for `unit`: `pdu` and its CRC.
pub fn rtu(unit: u8, pdu: &[u8]) -> Vec<u8> {
    let mut f = vec![unit];
    f.extend_from_slice(pdu);
    let crc = docking_logic::modbus::crc16(&f);
    f.extend_from_slice(&crc.to_le_bytes());
    f
}

/// A Modbus master that floods the line (`--flood`): reads of every table for this
/// unit, for another unit, device identification, a wrong CRC, garbage, a frame over
/// 256 bytes — never a write (a flood must change nothing). A frame goes out once the
/// line has been quiet 3 ms (> t3.5), so most are frames the server must answer.
#[derive(Debug, Default)]
struct ModbusFlood {
    bytes: u64,
    quiet_since_ps: Option<u64>,
}

impl ModbusFlood {
    fn pieces() -> Vec<Vec<u8>> {
        let mut bad_crc = rtu(1, &[0x04, 0, 0, 0, 10]);
        if let Some(b) = bad_crc.last_mut() {
            *b ^= 0x55;
        }
        vec![
            rtu(1, &[0x04, 0, 0, 0, 68]),
            rtu(1, &[0x03, 0, 0, 0, 1]),
            rtu(1, &[0x01, 0, 0, 0, 5]),
            rtu(1, &[0x02, 0, 0, 0, 11]),
            rtu(1, &[0x2B, 0x0E, 0x01, 0x00]),
            rtu(1, &[0x04, 0x7F, 0xFF, 0, 2]),
            rtu(1, &[0x63]),
            rtu(9, &[0x04, 0, 0, 0, 10]),
            bad_crc,
            b"\xff\x00garbage\x01\x04".to_vec(),
            vec![0x01; 300],
        ]
    }

    fn tick(&mut self, s: &mut Session, rng: &mut hil_sim::rng::Rng) {
        // On the millisecond grid, as the polling master (`crate::poller`).
        let now = s.now() / PS_PER_MS * PS_PER_MS;
        if s.board.soc().usart3.far_pending() > 0 {
            self.quiet_since_ps = None;
            return;
        }
        let t0 = *self.quiet_since_ps.get_or_insert(now);
        if now < t0 + 3 * PS_PER_MS {
            return;
        }
        let pieces = Self::pieces();
        let i = (rng.next_u64() % pieces.len() as u64) as usize;
        if let Some(p) = pieces.get(i) {
            if s.board.soc_mut().modbus_send_at(p, now) {
                self.bytes += p.len() as u64;
            }
        }
        self.quiet_since_ps = None;
    }
}

impl Session {
    /// The PLC writes coil `coil` on (unit 1): `Ok` (echoed) or the exception code (0:
    /// no reply, or one that is neither).
    pub fn coil(&mut self, coil: u8) -> Result<Result<(), u8>, Halt> {
        let frame = rtu(1, &[0x05, 0, coil, 0xFF, 0x00]);
        let r = self.modbus(&frame, PS_PER_S)?;
        Ok(match r.as_slice() {
            r if r == frame => Ok(()),
            [1, 0x85, code, ..] if r == rtu(1, &[0x85, *code]) => Err(*code),
            _ => Err(0),
        })
    }

    /// The PLC reads `n` input registers from `addr` (unit 1); `None`: no valid reply.
    pub fn read_inputs(&mut self, addr: u16, n: u16) -> Result<Option<Vec<u16>>, Halt> {
        let [ah, al] = addr.to_be_bytes();
        let [nh, nl] = n.to_be_bytes();
        let r = self.modbus(&rtu(1, &[0x04, ah, al, nh, nl]), PS_PER_S)?;
        let ok = r.len() == 5 + 2 * n as usize
            && r[..3] == [1, 0x04, 2 * n as u8]
            && rtu(1, &r[1..r.len() - 2]) == r;
        Ok(ok.then(|| {
            r[3..r.len() - 2]
                .chunks_exact(2)
                .map(|c| u16::from_be_bytes([c[0], c[1]]))
                .collect()
        }))
    }

    /// The PLC sends `frame` on the Modbus line; the reply bytes that reached the bus
    /// (empty: none within `timeout_ps`; a reply ends after 5 ms of silence).
    pub fn modbus(&mut self, frame: &[u8], timeout_ps: u64) -> Result<Vec<u8>, Halt> {
        let start = self.board.soc().modbus_out.len();
        let _ = self.board.soc_mut().modbus_send(frame);
        let deadline = self.now() + timeout_ps;
        let mut quiet: Option<(usize, u64)> = None;
        self.run_until(deadline, |x| {
            let n = x.board.soc().modbus_out.len();
            if n == start {
                return false;
            }
            match quiet {
                Some((m, t)) if m == n => x.now() >= t + 5 * PS_PER_MS,
                _ => {
                    quiet = Some((n, x.now()));
                    false
                }
            }
        })?;
        Ok(self.board.soc().modbus_out[start..]
            .iter()
            .map(|&(_, b)| b)
            .collect())
    }
}

/// The firmware's fault names, as `'static` strings.
fn docking_controller_fault_name(s: &str) -> &'static str {
    use docking_logic::sequencer::FaultKind;
    (0..=255u8)
        .filter_map(FaultKind::from_code)
        .map(FaultKind::name)
        .find(|n| *n == s)
        .unwrap_or("unknown")
}

/// The scenes of `vboard scene`.
pub const SCENES: [&str; 27] = [
    "boot",
    "nominal",
    "overload",
    "spike",
    "disconnect",
    "saturation",
    "stuck",
    "bad-tare",
    "stall",
    "lock-stuck",
    "sector-move",
    "power-cut-write",
    "power-cycle",
    "dock-hold",
    "vehicle-pull",
    "estop",
    "estop-bounce",
    "heavy-default",
    "maintenance-lockout",
    "update",
    "update-bad",
    "update-cut",
    "update-rollback",
    // The docking signature's (issue 34): hil-sim's `sigscene`.
    "late-entry",
    "dry-guide",
    "debris",
    "catch",
];

/// What the PLC of an in-service scene saw on the pins.
#[derive(Debug, Default)]
struct VbPlc {
    rep: PlcReport,
    mated_rise_ps: Option<u64>,
    pos_at_mated_um: f64,
    w_after_mated: Option<f64>,
    w_before_undock: Option<f64>,
    estop_ps: Option<u64>,
    fault_pos_um: Option<f64>,
}

/// The cycle in progress's load–distance by the console (`wear --json`), N·mm.
fn in_cycle_load_distance(s: &mut Session) -> Result<Option<f64>, Halt> {
    let w = s.console_json("wear --json")?;
    Ok(json_field(&w, "load_distance_in_cycle_nmm").and_then(|v| v.parse().ok()))
}

impl VbPlc {
    /// Each millisecond of the scene.
    fn tick(&mut self, name: &str, s: &mut Session) -> Result<(), Halt> {
        let now = s.now();
        let mated = s.plc_out().mated;
        let pos = s.machine().axis.pos_um();
        match (mated, self.mated_rise_ps) {
            (true, None) => {
                self.mated_rise_ps = Some(now);
                self.pos_at_mated_um = pos;
            }
            (false, Some(t0)) => {
                self.rep.mated_s += now.saturating_sub(t0) as f64 / PS_PER_S as f64;
                self.mated_rise_ps = None;
                self.rep
                    .mated_low_before_extraction
                    .get_or_insert(pos >= self.pos_at_mated_um - 1.0);
            }
            _ => {}
        }
        if name == "dock-hold" && mated {
            let for_ps = s.mated_for_ps();
            if self.w_after_mated.is_none() && for_ps >= PS_PER_S {
                self.w_after_mated = in_cycle_load_distance(s)?;
            }
            if self.w_before_undock.is_none() && for_ps + PS_PER_S >= s.hold_ps {
                self.w_before_undock = in_cycle_load_distance(s)?;
                if let (Some(a), Some(b)) = (self.w_after_mated, self.w_before_undock) {
                    // N·mm (3 decimals) → Q63.1 mN·µm.
                    self.rep.hold_load_distance_q1 =
                        Some(((b - a) * 2_000.0).round().max(0.0) as u64);
                }
            }
        }
        if self.estop_ps.is_none() && s.machine().estop.is_high() {
            self.estop_ps = Some(now);
        }
        if self.fault_pos_um.is_none() && !s.seen.faults.is_empty() {
            self.fault_pos_um = Some(pos);
            if name == "vehicle-pull" {
                // MATED dropped: the vehicle stops pulling.
                s.machine().devices().script.borrow_mut().pull_n_per_s = 0.0;
            }
        }
        Ok(())
    }

    /// After the scene's loop: the E-STOP's latency on the pins and its clear; the axis
    /// after a pull.
    fn finish(
        &mut self,
        name: &str,
        s: &mut Session,
        checks: &mut Vec<(String, bool, String)>,
    ) -> Result<(), Halt> {
        use crate::world::Signal;
        if name == "vehicle-pull" {
            let m = s.machine();
            let held = m.axis.enabled()
                && self
                    .fault_pos_um
                    .is_some_and(|p| (m.axis.pos_um() - p).abs() < 1.0);
            self.rep.axis_held = Some(held);
            checks.push((
                "pulled while mated: MATED low, the axis held where it was, driven".into(),
                held && !s.plc_out().mated,
                format!(
                    "EN on {}, at {:.3} mm",
                    m.axis.enabled(),
                    m.axis.pos_um() / 1000.0
                ),
            ));
        }
        if let (Some(t0), "estop") = (self.estop_ps, name) {
            let edges = &s.board.soc().edges;
            let en = edges
                .iter()
                .find(|e| e.signal == Signal::EnN && e.high && e.t_ps >= t0)
                .map(|e| e.t_ps - t0);
            let lock_high_after = edges.iter().any(|e| {
                matches!(e.signal, Signal::LockIn1 | Signal::LockIn2) && e.high && e.t_ps > t0
            });
            let lock_off = !lock_high_after && !s.machine().lock.driven();
            self.rep.estop_latency_s = en.map(|ps| ps as f64 / PS_PER_S as f64);
            self.rep.lock_off_after_estop = Some(lock_off);
            checks.push((
                "E-STOP edge to EN high on the pins".into(),
                en.is_some_and(|ps| ps <= 100 * 1_000_000),
                format!("{:?} µs (≤ 100 µs)", en.map(|ps| ps as f64 * 1e-6)),
            ));
            checks.push((
                "lock bridge off after the E-STOP".into(),
                lock_off,
                String::new(),
            ));
            s.maint_enter()?;
            let r = s.console("clear-fault", 2 * PS_PER_S)?;
            let refused = r.contains("E-STOP");
            self.rep.clear_refused_while_open = Some(refused);
            checks.push((
                "clear refused while E-STOP is open".into(),
                refused,
                r.trim().into(),
            ));
            s.set_estop(false);
            s.run_for(100 * PS_PER_MS)?;
            let r = s.console("clear-fault", 2 * PS_PER_S)?;
            let ok = r.starts_with("ok");
            self.rep.clear_accepted_when_closed = Some(ok);
            checks.push((
                "clear accepted once E-STOP is closed".into(),
                ok,
                r.trim().into(),
            ));
            // The technician leaves maintenance mode: READY may come back.
            s.maint_exit()?;
            let deadline = s.now() + 60 * PS_PER_S;
            let home = s.run_until(deadline, |x| x.at_rest() && x.plc_out().ready)?;
            checks.push(("recovered home, READY".into(), home, String::new()));
        }
        if name == "dock-hold" {
            checks.push((
                "no wear while mated".into(),
                self.rep.hold_load_distance_q1 == Some(0),
                format!("{:?} / {:?} N·mm", self.w_after_mated, self.w_before_undock),
            ));
            checks.push((
                "MATED high for the hold, low before the extraction".into(),
                self.rep.mated_s >= s.hold_ps as f64 / PS_PER_S as f64
                    && self.rep.mated_low_before_extraction == Some(true),
                format!("{:.3} s", self.rep.mated_s),
            ));
        }
        Ok(())
    }
}

/// Options of a scene run.
#[derive(Clone, Debug)]
pub struct SceneOptions {
    /// Session options.
    pub session: Options,
    /// Docking cycles (the disturbance comes in the last).
    pub cycles: u32,
    /// Flood the console at the line rate during the scene (`hil-sim`'s flood: long
    /// replies, a full `history`, garbage, overlong lines).
    pub flood: bool,
    /// `update-cut`: where the power is cut (`--cut transfer|swap|boot`; default swap).
    pub cut: Option<crate::update::Cut>,
}

impl Default for SceneOptions {
    /// One cycle on a default session ([`Options::new`]), no flood.
    fn default() -> Self {
        Self {
            session: Options::new(),
            cycles: 1,
            flood: false,
            cut: None,
        }
    }
}

/// What a scene produced: the fields of `hil-sim scene --json`, and what only a board
/// shows.
#[derive(Clone, Debug)]
pub struct Report {
    /// The host rig's fields.
    pub scene: SceneReport,
    /// Resets, the power-on included.
    pub reset_count: usize,
    /// Their causes.
    pub reset_causes: Vec<&'static str>,
    /// All instructions executed / control steps (a busy-polling core counts its
    /// polling: that is what the step costs it).
    pub instructions_per_control_step: f64,
    /// Share of time the core was awake, %.
    pub cpu_load_pct: f64,
    /// From DOUT falling for the first over-limit sample to EN high, on the pins, µs.
    pub stop_latency_pins_us: Option<f64>,
    /// Samples read out of the HX711.
    pub samples_read: u64,
    /// For every sample: DOUT falling → end of the handler that read it (what a stop
    /// decided there takes at most), mean and maximum, µs.
    pub sample_latency_mean_us: f64,
    /// See [`Report::sample_latency_mean_us`].
    pub sample_latency_max_us: f64,
    /// For every sample: DOUT falling → its handler entered (what it waited for, apart
    /// from what it ran), mean and maximum, µs.
    pub sample_entry_latency_mean_us: f64,
    /// See [`Report::sample_entry_latency_mean_us`].
    pub sample_entry_latency_max_us: f64,
    /// Where the longest of those waits ended: the function the sampler preempted (with
    /// the exception it ran in), or the exception it was tail-chained after.
    pub sample_entry_max_at: String,
    /// The longest all-interrupts-masked window while the propulsion was on, µs, and the
    /// function it began in.
    pub masked_max_us: f64,
    /// See [`Report::masked_max_us`].
    pub masked_max_at: String,
    /// Conversions the firmware did not read before the next one.
    pub samples_missed: u64,
    /// HX711 power-downs (PD_SCK high > 60 µs), the firmware's boot power-cycle included.
    pub hx711_power_downs: u64,
    /// Console bytes lost to USART2 overruns (the one-byte data register was full).
    pub console_overruns: u64,
    /// Lines the firmware discarded because input was lost on the way in (its `input
    /// lost` errors): a USART overrun or receive error, or its receive ring lapped.
    pub console_input_lost: u64,
    /// Bytes the flooding terminal sent (`--flood`).
    pub console_flood_bytes: u64,
    /// Bytes the flooding Modbus master sent (`--flood`), and the reply bytes that
    /// reached the bus.
    pub modbus_flood_bytes: u64,
    /// See [`Report::modbus_flood_bytes`].
    pub modbus_reply_bytes: u64,
    /// Reply bytes sent with the RS-485 driver off (lost): must be 0.
    pub modbus_de_losses: u64,
    /// Modbus characters lost to USART3 overruns (its data register still full when
    /// the next stop bit ended: the receive interrupt ran too late, e.g. stalled on a
    /// flash program). A lost character fails its request's CRC or framing; the master
    /// retries.
    pub modbus_overruns: u64,
    /// Cycles per instruction used.
    pub cpi: f64,
    /// LSI frequency used, Hz.
    pub lsi_hz: u64,
    /// Flash timing column.
    pub flash_timing: &'static str,
    /// Instructions executed.
    pub instructions: u64,
    /// Emulation speed, million instructions per wall second.
    pub mips: f64,
    /// Virtual seconds per wall second, over the whole run.
    pub realtime_factor: f64,
    /// The same over the slowest window of at least 100 ms of wall time (the mean when
    /// the run was shorter): where a client in real time would have waited.
    pub realtime_factor_min: f64,
    /// Instructions charged without being emulated: the polling loops skipped
    /// ([`crate::loops`]; 0 with `--no-skip`).
    pub skipped_instructions: u64,
    /// [`crate::cpu::Board::trace_digest`] at the end: equal digests, equal runs.
    pub trace_digest: u64,
    /// Flash erases per odometer sector.
    pub erase_counts: Vec<u32>,
    /// Faults the core took (HardFault, lockup).
    pub core_faults: Vec<String>,
    /// What the board noticed.
    pub diagnostics: Vec<String>,
    /// Scene-specific checks (name, passed, detail).
    pub checks: Vec<(String, bool, String)>,
    /// What a polling PLC master saw (the scenes that poll: `sector-move`, `update`).
    pub modbus_poll: Option<crate::poller::PollStats>,
    /// `power-cycle`: whether anything moved after the reset before a request.
    pub motion_before_request: Option<bool>,
    /// The STEP/DIR/EN pins as a DM542-class driver sees them.
    pub step: hil_sim::axis::StepTiming,
    /// The firmware's defmt log, decoded.
    pub log: Vec<LogLine>,
    /// Per exception (task): name, entries, instructions executed in it (thread mode —
    /// RTIC's idle — as `thread`).
    pub tasks: Vec<(String, u64, u64)>,
    /// Over the time anything moved ([`crate::realtime`]): the control step's period
    /// (entries of TIM2 on the NVIC model) and the watchdog's feeding (reloads on the
    /// IWDG model).
    pub timing: ControlTiming,
    /// For every E-STOP edge while anything moved: edge → EN high and the lock bridge
    /// off, on the pins, µs (`None`: they never went off).
    pub estop_reactions_us: Vec<Option<f64>>,
    /// The docking signature's scenes: the board's `curve last --json` reply after the
    /// last docking (what `vboard scene NAME --curve FILE.json` writes for `hil-sim
    /// plot-curve`).
    pub curve_json: Option<String>,
}

/// A name for exception `e` (STM32F407 interrupt names for those the board models).
pub fn exception_name(e: usize) -> String {
    match e {
        0 => "thread".into(),
        2 => "NMI".into(),
        3 => "HardFault".into(),
        11 => "SVCall".into(),
        14 => "PendSV".into(),
        15 => "SysTick".into(),
        e if e >= 16 => match e - 16 {
            4 => "FLASH".into(),
            6 => "EXTI0".into(),
            23 => "EXTI9_5".into(),
            28 => "TIM2".into(),
            29 => "TIM3".into(),
            30 => "TIM4".into(),
            35 => "SPI1".into(),
            38 => "USART2".into(),
            39 => "USART3".into(),
            40 => "EXTI15_10".into(),
            50 => "TIM5".into(),
            n => format!("IRQ{n}"),
        },
        e => format!("exception{e}"),
    }
}

impl Report {
    /// One JSON object on one line.
    pub fn to_json(&self) -> String {
        let base = self.scene.to_json();
        let base = base.strip_suffix('}').unwrap_or(&base);
        let strs = |v: &[String]| {
            v.iter()
                .map(|s| format!("\"{}\"", json_escape(s)))
                .collect::<Vec<_>>()
                .join(",")
        };
        let causes: Vec<String> = self.reset_causes.iter().map(|s| s.to_string()).collect();
        let checks: Vec<String> = self
            .checks
            .iter()
            .map(|(n, ok, d)| {
                format!(
                    "{{\"name\":\"{}\",\"passed\":{ok},\"detail\":\"{}\"}}",
                    json_escape(n),
                    json_escape(d)
                )
            })
            .collect();
        let json = format!(
            "{base},\"reset_count\":{},\"reset_causes\":[{}],\"instructions_per_control_step\":{},\"cpu_load_pct\":{},\"stop_latency_pins_us\":{},\"samples_read\":{},\"sample_latency_mean_us\":{},\"sample_latency_max_us\":{},\"sample_entry_latency_mean_us\":{},\"sample_entry_latency_max_us\":{},\"sample_entry_max_at\":\"{}\",\"masked_max_us\":{},\"masked_max_at\":\"{}\",\"samples_missed\":{},\"hx711_power_downs\":{},\"console_overruns\":{},\"console_input_lost\":{},\"console_flood_bytes\":{},\"modbus_flood_bytes\":{},\"modbus_reply_bytes\":{},\"modbus_de_losses\":{},\"modbus_overruns\":{},\"cpi\":{},\"lsi_hz\":{},\"flash_timing\":\"{}\",\"tasks\":[{}],\"instructions\":{},\"mips\":{},\"realtime_factor\":{},\"realtime_factor_min\":{},\"skipped_instructions\":{},\"trace_digest\":\"{:016x}\",\"erase_counts\":{:?},\"core_faults\":[{}],\"diagnostics\":[{}],\"checks\":[{}],\"motion_before_request\":{},\"step_pulses_pos\":{},\"step_pulses_neg\":{},\"step_pulses_driver_off\":{},\"step_setup_violations\":{},\"step_width_violations\":{},\"step_min_setup_us\":{},\"step_min_high_us\":{},\"moving_s\":{},\"control_period_max_ms\":{},\"control_entry_latency_max_us\":{},\"control_entry_latency_max_us_all\":{},\"control_late\":{},\"watchdog_feed_gap_max_ms\":{},\"watchdog_feeds_missed\":{},\"estop_edges_moving\":{},\"estop_off_max_us\":{},\"estop_edges_not_stopped\":{}}}",
            self.reset_count,
            strs(&causes),
            num(self.instructions_per_control_step),
            num(self.cpu_load_pct),
            self.stop_latency_pins_us.map_or("null".into(), num),
            self.samples_read,
            num(self.sample_latency_mean_us),
            num(self.sample_latency_max_us),
            num(self.sample_entry_latency_mean_us),
            num(self.sample_entry_latency_max_us),
            json_escape(&self.sample_entry_max_at),
            num(self.masked_max_us),
            json_escape(&self.masked_max_at),
            self.samples_missed,
            self.hx711_power_downs,
            self.console_overruns,
            self.console_input_lost,
            self.console_flood_bytes,
            self.modbus_flood_bytes,
            self.modbus_reply_bytes,
            self.modbus_de_losses,
            self.modbus_overruns,
            num(self.cpi),
            self.lsi_hz,
            self.flash_timing,
            self.tasks
                .iter()
                .map(|(n, e, i)| format!(
                    "{{\"name\":\"{n}\",\"entries\":{e},\"instructions\":{i}}}"
                ))
                .collect::<Vec<_>>()
                .join(","),
            self.instructions,
            num(self.mips),
            num(self.realtime_factor),
            num(self.realtime_factor_min),
            self.skipped_instructions,
            self.trace_digest,
            self.erase_counts,
            strs(&self.core_faults),
            strs(&self.diagnostics),
            checks.join(","),
            self.motion_before_request
                .map_or("null".to_string(), |m| m.to_string()),
            self.step.pulses_pos,
            self.step.pulses_neg,
            self.step.pulses_disabled,
            self.step.setup_violations,
            self.step.width_violations,
            us_or_null(self.step.min_setup_ns),
            us_or_null(self.step.min_high_ns),
            num(self.timing.moving_s),
            self.timing.period_max_ms.map_or("null".into(), num),
            self.timing.entry_latency_max_us.map_or("null".into(), num),
            self.timing.entry_latency_max_us_all.map_or("null".into(), num),
            self.timing.late,
            self.timing.feed_gap_max_ms.map_or("null".into(), num),
            self.timing.feeds_missed,
            self.estop_reactions_us.len(),
            self.estop_reactions_us
                .iter()
                .flatten()
                .copied()
                .reduce(f64::max)
                .map_or("null".into(), num),
            self.estop_reactions_us.iter().filter(|r| r.is_none()).count(),
        );
        // The polling master's figures, in the scenes that poll (crate::poller).
        match self.modbus_poll {
            Some(p) => format!(
                "{},{}}}",
                json.strip_suffix('}').unwrap_or(&json),
                p.to_json_fields()
            ),
            None => json,
        }
    }

    /// A short human summary.
    pub fn to_text(&self) -> String {
        let mut s = self.scene.to_text();
        s += &format!(
            "\n  board: {} reset(s) [{}], {} samples read ({} missed, {} HX711 power-downs), CPU load {:.1} %, {:.0} instructions per control step",
            self.reset_count,
            self.reset_causes.join(", "),
            self.samples_read,
            self.samples_missed,
            self.hx711_power_downs,
            self.cpu_load_pct,
            self.instructions_per_control_step
        );
        if let Some(l) = self.stop_latency_pins_us {
            s += &format!("\n  stop latency at the pins (DOUT falling → EN high): {l:.1} µs");
        }
        if self.sample_latency_max_us > 0.0 {
            s += &format!(
                "\n  every sample while moving, DOUT falling → its handler done: mean {:.1} µs, max {:.1} µs (→ its handler entered: mean {:.2} µs, max {:.2} µs); longest all-masked window {:.1} µs ({})",
                self.sample_latency_mean_us,
                self.sample_latency_max_us,
                self.sample_entry_latency_mean_us,
                self.sample_entry_latency_max_us,
                self.masked_max_us,
                self.masked_max_at
            );
        }
        let t = &self.timing;
        let us = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.2} µs"));
        if t.moving_s > 0.0 {
            let ms = |x: Option<f64>| x.map_or("-".to_string(), |v| format!("{v:.2} ms"));
            s += &format!(
                "\n  over the {:.1} s anything moved: longest control period {} ({} late, > {:.1} ms); longest control entry latency (TIM2 pending → entered) {}; longest watchdog feed gap {} ({} missed, > {:.1} ms)",
                t.moving_s,
                ms(t.period_max_ms),
                t.late,
                self.period_ms() + 1.0,
                us(t.entry_latency_max_us),
                ms(t.feed_gap_max_ms),
                t.feeds_missed,
                3.0 * self.period_ms()
            );
        }
        if t.entry_latency_max_us_all.is_some() {
            s += &format!(
                "\n  longest control entry latency over the whole run (rest and boot included): {}",
                us(t.entry_latency_max_us_all)
            );
        }
        if !self.estop_reactions_us.is_empty() {
            s += &format!(
                "\n  E-STOP: {} edge(s) while moving, edge → EN high and lock off: longest {}",
                self.estop_reactions_us.len(),
                self.estop_off_max_us()
                    .filter(|v| v.is_finite())
                    .map_or("never (pins left on)".to_string(), |v| format!("{v:.2} µs"))
            );
        }
        if self.console_flood_bytes > 0 || self.console_overruns > 0 {
            s += &format!(
                "\n  console: {} bytes of flood sent, {} lost to overruns, {} line(s) discarded for lost input",
                self.console_flood_bytes, self.console_overruns, self.console_input_lost
            );
        }
        if self.modbus_flood_bytes > 0 {
            s += &format!(
                "\n  modbus: {} bytes of flood sent, {} reply bytes on the bus, {} sent with DE low, {} lost to overruns",
                self.modbus_flood_bytes, self.modbus_reply_bytes, self.modbus_de_losses, self.modbus_overruns
            );
        }
        s += &format!(
            "\n  emulation: {} instructions at CPI {}, {:.1} MIPS, {:.3}× real time ({:.3}× in the slowest 100 ms; {} instructions in polling loops skipped) (LSI {} Hz, flash timing {})",
            self.instructions, self.cpi, self.mips, self.realtime_factor, self.realtime_factor_min, self.skipped_instructions, self.lsi_hz, self.flash_timing
        );
        let st = &self.step;
        if st.pulses_pos + st.pulses_neg + st.pulses_disabled > 0 {
            s += &format!(
                "\n  step pins: {} pulses +, {} −, {} with the driver off; {} setup and {} width violations; shortest DIR/EN setup {} µs, STEP high {} µs",
                st.pulses_pos,
                st.pulses_neg,
                st.pulses_disabled,
                st.setup_violations,
                st.width_violations,
                us_or_null(st.min_setup_ns),
                us_or_null(st.min_high_ns)
            );
        }
        s += "\n  tasks:";
        for (n, e, i) in &self.tasks {
            s += &format!(" {n} {e}× {:.0}", *i as f64 / (*e).max(1) as f64);
        }
        for f in &self.core_faults {
            s += &format!("\n  core fault: {f}");
        }
        for d in &self.diagnostics {
            s += &format!("\n  noticed: {d}");
        }
        for (n, ok, d) in &self.checks {
            s += &format!("\n  check {n}: {} ({d})", if *ok { "ok" } else { "FAILED" });
        }
        s
    }

    /// The longest E-STOP edge → EN high (and lock off) while anything moved, µs
    /// (`None`: no such edge; infinite if the pins never went off).
    pub fn estop_off_max_us(&self) -> Option<f64> {
        self.estop_reactions_us
            .iter()
            .map(|r| r.unwrap_or(f64::INFINITY))
            .reduce(f64::max)
    }

    /// The sample period, ms.
    pub fn period_ms(&self) -> f64 {
        1_000.0 / f64::from(self.scene.rate_sps.max(1))
    }

    /// Whether every scene-specific check passed.
    pub fn passed(&self) -> bool {
        self.checks.iter().all(|(_, ok, _)| *ok)
    }
}

fn us_or_null(ns: u64) -> String {
    if ns == u64::MAX {
        "null".into()
    } else {
        num(ns as f64 / 1000.0)
    }
}

fn json_escape(s: &str) -> String {
    s.chars()
        .flat_map(|c| match c {
            '"' => vec!['\\', '"'],
            '\\' => vec!['\\', '\\'],
            c if (c as u32) < 0x20 => format!("\\u{:04x}", c as u32).chars().collect(),
            c => vec![c],
        })
        .collect()
}

/// Stop latency on the pins: from the ready time (DOUT falling) of the sample that made
/// the firmware disable the propulsion — counted from the first conversion after the
/// last one it had read before, if it missed any — to the EN rising edge at `edge_ns`.
fn latency_us(conv: &[(u64, i32, bool)], edge_ns: u64) -> Option<f64> {
    let before: Vec<&(u64, i32, bool)> = conv.iter().filter(|c| c.0 <= edge_ns).collect();
    let k = before.iter().rposition(|c| c.2)?;
    let mut first = k;
    while first > 0 && !before[first - 1].2 {
        first -= 1;
    }
    Some((edge_ns - before[first].0) as f64 / 1e3)
}

/// The check of a scene whose PLC polled the Modbus line: every request answered
/// (the registers, or exception 06 while the flash erases) within 100 ms.
fn poll_check(s: &Session, checks: &mut Vec<(String, bool, String)>, during: &str) {
    let Some(p) = s.poller.as_ref() else {
        return;
    };
    let st = p.stats;
    checks.push((
        format!("every Modbus request answered within 100 ms through {during}"),
        st.all_answered_within(100.0),
        format!(
            "{} requests: {} data, {} busy (06), {} bad, {} unanswered; longest wait {:.1} ms at {:.1} s",
            st.polls, st.data, st.busy, st.bad, st.timeouts, st.reply_max_ms, st.reply_max_at_s
        ),
    ));
}

/// Run scene `name`. `Err`: unknown scene, unloadable image, or a board that could not
/// go on (an unmodelled access, an engine failure).
pub fn run(name: &str, opts: &SceneOptions) -> Result<Report, String> {
    if !SCENES.contains(&name) {
        return Err(format!(
            "unknown scene '{name}' (scenes: {})",
            SCENES.join(", ")
        ));
    }
    let started = Instant::now();
    let cycles = opts.cycles.max(1);
    let mut checks = Vec::new();
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    let mut prefill = None;
    if name == "sector-move" {
        prefill = Some(prefill_log(&flash)?);
    }
    let mut session = opts.session.clone();
    if name == "heavy-default" {
        session.force_model = hil_sim::machine::ForceModel::plant(hil_sim::scene::heavy_machine())
            .map_err(|e| format!("heavy-default: {e:?}"))?;
    }
    let mut s = Session::with_flash(session, flash.clone()).map_err(|e| e.to_string())?;
    let host_scene = !matches!(
        name,
        "boot"
            | "sector-move"
            | "power-cut-write"
            | "power-cycle"
            | "estop-bounce"
            | "maintenance-lockout"
            | "update"
            | "update-bad"
            | "update-cut"
            | "update-rollback"
    );
    let mut scripted_plc: Option<PlcReport> = None;
    let mut motion_before_request = None;
    let mut driver = if host_scene {
        Some(SceneDriver::new(name, cycles)?)
    } else {
        None
    };
    if let Some(d) = driver.as_ref() {
        d.setup(
            s.machine().devices(),
            opts.session.seed,
            opts.session.rate_sps,
            cycles,
        );
    }
    // Spikes count as injected once the firmware read the conversion they were in.
    let mut spikes = SpikeTally::new(s.machine().devices(), s.machine().conversions.get());
    let mut trip: Option<(u64, f64)> = None;
    let mut stop_latency_pins_us = None;
    let (mut max_after, mut min_after) = (f64::MIN, f64::MAX);
    let mut plc = PLC_SCENES.contains(&name).then(VbPlc::default);
    match name {
        "dock-hold" => s.hold_ps = DOCK_HOLD_S * PS_PER_S,
        // In service: DOCK stays asserted (until the fault).
        "vehicle-pull" | "estop" => s.hold_ps = 3_600 * PS_PER_S,
        _ => {}
    }
    let max_ps = (cycles as u64 * 150 + 60) * PS_PER_S + s.hold_ps;
    let mut settle_until: Option<u64> = None;
    let mut flood_rng = hil_sim::rng::Rng::new(opts.session.seed ^ 0xf100d);
    let mut flood_bytes = 0u64;
    let mut mb_flood = ModbusFlood::default();
    let mut pos_checked = false;

    match name {
        "boot" => {
            s.run_for(2 * PS_PER_S).map_err(|e| e.to_string())?;
        }
        "sector-move" => {
            // Boot: the log is past its maintenance mark, so the firmware erases the next
            // sector as soon as it is idle with every motor off. A PLC polls the Modbus
            // line all along (issue 31: a reply within 100 ms, the erase included).
            s.poller = Some(crate::poller::Poller::new(0));
            let before = prefill.unwrap_or_default();
            let deadline = s.now() + 8 * PS_PER_S;
            let erased = |x: &Session| {
                x.board
                    .soc()
                    .world
                    .flash
                    .with(|f| f.erase_counts().iter().sum::<u32>())
                    > before.erases
            };
            // A technician types a line while the sector erases (the master's first
            // "busy" reply says the erase is on): the console is received by DMA
            // meanwhile and the line answered after it (issue 31).
            s.run_until(deadline, |x| {
                erased(x) || x.poller.as_ref().is_some_and(|p| p.stats.busy > 0)
            })
            .map_err(|e| e.to_string())?;
            let typed_in_erase = !erased(&s);
            let console_from = s.board.soc().console_out.len();
            if typed_in_erase {
                // On the millisecond grid (see `Session::run_until`).
                let at = s.now() / PS_PER_MS * PS_PER_MS;
                let _ = s.board.soc_mut().console_send_at(b"echo\r\n", at);
            }
            s.run_until(deadline, erased).map_err(|e| e.to_string())?;
            s.run_for(PS_PER_S).map_err(|e| e.to_string())?;
            let answer: Vec<u8> = s.board.soc().console_out[console_from..]
                .iter()
                .map(|&(_, b)| b)
                .collect();
            let answer = String::from_utf8_lossy(&answer).into_owned();
            checks.push((
                "a console line typed during the erase answered after it".into(),
                typed_in_erase && answer.contains("echo=on"),
                format!(
                    "typed during the erase {typed_in_erase}; answer {:?}",
                    answer.trim()
                ),
            ));
            let erases: u32 = flash.with(|f| f.erase_counts().iter().sum());
            checks.push((
                "sector erased".into(),
                erases > before.erases,
                format!("{} erase(s) before, {erases} after", before.erases),
            ));
            // Reboot on the same flash and compare every kind's newest record.
            let after = read_newest(&flash)?;
            // Lost: a kind whose newest record is gone, or older than before (a carried
            // copy has the same payload under a higher sequence number).
            let lost_records = before
                .newest
                .iter()
                .zip(&after)
                .filter(|(b, a)| match (b, a) {
                    (Some((bs, _)), Some((as_, _))) => as_ < bs,
                    (Some(_), None) => true,
                    (None, _) => false,
                })
                .count();
            checks.push((
                "no record lost".into(),
                lost_records == 0,
                format!("{lost_records} kind(s) lost their newest record"),
            ));
            poll_check(&s, &mut checks, "the boot and the sector's erase");
        }
        "power-cycle" => {
            motion_before_request =
                Some(power_cycle(&mut s, &mut checks).map_err(|e| e.to_string())?);
        }
        "power-cut-write" => {
            power_cut_write(&mut s, &mut checks, opts).map_err(|e| e.to_string())?;
        }
        "estop-bounce" => {
            scripted_plc = Some(estop_bounce(&mut s, &mut checks).map_err(|e| e.to_string())?);
        }
        "maintenance-lockout" => {
            scripted_plc =
                Some(maintenance_lockout(&mut s, &mut checks).map_err(|e| e.to_string())?);
        }
        "update" => {
            // A PLC polls the Modbus line through the whole update (issue 31: a reply
            // within 100 ms, the DFU's erases included; issue 32: the update does not
            // fail because the PLC polls).
            s.poller = Some(crate::poller::Poller::new(s.now() + 50 * PS_PER_MS));
            crate::update::update(&mut s, &mut checks).map_err(|e| e.to_string())?;
            poll_check(&s, &mut checks, "the update, its erases included");
        }
        "update-bad" => {
            crate::update::update_bad(&mut s, &mut checks).map_err(|e| e.to_string())?
        }
        "update-rollback" => {
            crate::update::update_rollback(&mut s, &mut checks).map_err(|e| e.to_string())?
        }
        "update-cut" => {
            use crate::update::Cut;
            let seed = opts.session.seed;
            s = match opts.cut.unwrap_or(Cut::Swap) {
                Cut::Transfer => {
                    crate::update::update_cut_transfer(seed, &opts.session, &mut checks)?
                }
                cut => {
                    let m = crate::update::marked(&opts.session, cut == Cut::Swap)?;
                    crate::update::update_cut_marked(cut, seed, &opts.session, &m, &mut checks)?
                }
            };
        }
        _ => loop {
            if opts.flood {
                // Keep the line busy: the next piece queued before the last one is sent.
                while s.board.soc().usart2.far_pending() < 32 {
                    let i = (flood_rng.next_u64() % FLOOD_PIECES.len() as u64) as usize;
                    if !s.board.soc_mut().console_send(FLOOD_PIECES[i]) {
                        break; // the console is not up yet
                    }
                    flood_bytes += FLOOD_PIECES[i].len() as u64;
                }
            }
            if opts.flood {
                mb_flood.tick(&mut s, &mut flood_rng);
            }
            s.run_for(PS_PER_MS).map_err(|e| e.to_string())?;
            if spikes.due(s.machine().conversions.get()) {
                // The recent conversions first: reading them completes any that are due.
                let recent = s.machine().hx.recent_conversions();
                spikes.observe(s.machine().conversions.get(), &recent);
            }
            let p = s.progress();
            if let Some(d) = driver.as_mut() {
                d.on_progress(s.machine().devices(), &p);
                s.inputs_changed();
            }
            let now = s.now();
            // Trip: the first EN rising edge after an overload fault was logged.
            if trip.is_none() && s.seen.faults.iter().any(|f| f.kind == "overload") {
                let edges = s.machine().axis.enable_edges();
                if let Some(e) = edges.iter().rev().find(|e| !e.enabled) {
                    trip = Some((e.t_ns, e.pos_um));
                    // Now, while the HX711 still remembers the conversions before it.
                    stop_latency_pins_us = latency_us(&s.machine().hx.recent_conversions(), e.t_ns);
                }
            }
            if let Some((_, p0)) = trip {
                let pos = s.machine().axis.pos_um();
                max_after = max_after.max(pos - p0);
                min_after = min_after.min(pos - p0);
            }
            // After the extraction (a reversal), while the lock re-locks at the engagement
            // point: the firmware's counted position must be the carriage's.
            if !pos_checked
                && s.seen.extracting
                && s.machine().lock.driven()
                && s.machine().lock.fraction_locked() < 1.0
            {
                pos_checked = true;
                if opts.flood {
                    // The flood's queued pieces first, and their replies out: asked
                    // behind them, `status` would be answered seconds later, and a
                    // flood piece's own `status --json` taken for its reply.
                    let t = s.now() + 3 * PS_PER_S;
                    s.run_until(t, |x| x.board.soc().usart2.far_pending() == 0)
                        .map_err(|e| e.to_string())?;
                    s.run_for(PS_PER_S / 2).map_err(|e| e.to_string())?;
                }
                // The count is taken at some instant while the command runs: the
                // carriage before the command and after its reply bracket it (the
                // same position when it stands still, as without a flood it does).
                let before_um = s.machine().axis.pos_um();
                let st = s.console_json("status --json").map_err(|e| e.to_string())?;
                let after_um = s.machine().axis.pos_um();
                let counted_um = json_field(&st, "pos_mm")
                    .and_then(|v| v.parse::<f64>().ok())
                    .map(|mm| mm * 1000.0);
                let (lo, hi) = (before_um.min(after_um), before_um.max(after_um));
                let ok = counted_um.is_some_and(|c| c >= lo - 5.0 && c <= hi + 5.0);
                checks.push((
                    "pulses counted in the direction they were emitted".into(),
                    ok,
                    format!(
                        "after the extraction: counted {counted_um:?} µm, carriage {before_um:.1} µm before the command, {after_um:.1} µm after its reply"
                    ),
                ));
            }
            if let Some(p) = plc.as_mut() {
                p.tick(name, &mut s).map_err(|e| e.to_string())?;
            }
            let at_rest = s.at_rest();
            let faulted = !s.seen.faults.is_empty();
            s.auto_dock(cycles);
            if faulted {
                settle_until.get_or_insert(now + 2 * PS_PER_S);
            }
            let done = at_rest && s.seen.cycles_completed >= cycles;
            if done || settle_until.is_some_and(|t| now >= t) || now > max_ps {
                break;
            }
        },
    }

    if opts.flood {
        // Let the line drain before asking (the flood's own replies would be taken for
        // the answers).
        let t = s.now() + 3 * PS_PER_S;
        s.run_until(t, |x| x.board.soc().usart2.far_pending() == 0)
            .map_err(|e| e.to_string())?;
        s.run_for(PS_PER_S).map_err(|e| e.to_string())?;
    }
    if let Some(p) = plc.as_mut() {
        p.finish(name, &mut s, &mut checks)
            .map_err(|e| e.to_string())?;
    }
    let recovered_after_clear = if name == "heavy-default" {
        Some(clear_out_of_the_cone(&mut s, &mut checks).map_err(|e| e.to_string())?)
    } else {
        None
    };
    // The end state, as the console reports it.
    let status = s.console_json("status --json").map_err(|e| e.to_string())?;
    let final_state = json_field(&status, "state").unwrap_or_else(|| "unknown".into());
    let wear = s.console_json("wear --json").map_err(|e| e.to_string())?;
    let peak_force_n = json_field(&wear, "peak_force_n")
        .and_then(|v| v.parse().ok())
        .unwrap_or(0.0);
    // The fault records as the firmware keeps them (phase, peak force to the clear).
    let faults_json = s.console_json("faults --json").map_err(|e| e.to_string())?;
    let faults = parse_faults(&faults_json).unwrap_or_else(|| s.seen.faults.clone());
    // The signature as the people and the PLC are shown it: the console's curve, the
    // registers.
    let curve_json = if hil_sim::sigscene::SCENES.contains(&name) {
        Some(signature_shown(&mut s, name, cycles, &mut checks).map_err(|e| e.to_string())?)
    } else {
        None
    };
    s.board.poll_rtt();

    let m = s.machine();
    let hx = m.hx.stats();
    let wall = started.elapsed().as_secs_f64();
    let soc = s.board.soc();
    let sim_s = s.now() as f64 / PS_PER_S as f64;
    let insns = soc.clock.insns();
    let awake = 1.0 - soc.clock.sleep_ps() as f64 / s.now().max(1) as f64;
    // The signature's verdicts, as the firmware logged them (hil-sim's expectations).
    if host_scene {
        hil_sim::sigscene::check(name, &s.seen.signatures, cycles, 1, &mut |ok, what| {
            checks.push((what, ok, String::new()))
        });
    }
    let scene = SceneReport {
        scene: name.to_string(),
        rate_sps: opts.session.rate_sps,
        seed: opts.session.seed,
        cycles_completed: s.seen.cycles_completed,
        faults,
        peak_force_n,
        stop_latency_s: stop_latency_pins_us.map(|u| u * 1e-6),
        final_state: leak(final_state),
        insertion_phases: s.seen.insertion_phases.clone(),
        motors_disabled: !m.axis.enabled() && !m.lock.driven(),
        forward_after_trip_um: trip.map(|_| max_after.max(0.0)),
        backed_off_um: trip.map(|_| (-min_after).max(0.0)),
        spikes_rejected: 0,
        spikes_injected: spikes.delivered,
        control_steps: hx.samples_read,
        sim_time_s: sim_s,
        wall_time_s: wall,
        watchdog_bit: s.watchdog_resets() > 0,
        plc: plc.map(|p| p.rep).or(scripted_plc),
        recovered_after_clear,
        signatures: s.seen.signatures.clone(),
    };
    Ok(Report {
        scene,
        reset_count: s.board.resets.len(),
        reset_causes: s.reset_causes(),
        // The control step is the TIM2 task on the interrupt-driven firmware; a polling
        // firmware has no such task, and then every instruction counts.
        instructions_per_control_step: match soc.exc_entries.get(16 + 28) {
            Some(&n) if n > 0 => soc.exc_insns[16 + 28] as f64 / n as f64,
            _ => insns as f64 / hx.samples_read.max(1) as f64,
        },
        cpu_load_pct: 100.0 * awake,
        stop_latency_pins_us,
        samples_read: hx.samples_read,
        sample_latency_mean_us: soc.sample_latency.mean_us(),
        sample_latency_max_us: soc.sample_latency.max_us(),
        sample_entry_latency_mean_us: soc.sample_entry_latency.mean_us(),
        sample_entry_latency_max_us: soc.sample_entry_latency.max_us(),
        sample_entry_max_at: match soc.sample_entry_max_from {
            (_, _) if soc.sample_entry_latency.count == 0 => "-".to_string(),
            (exc, Some(pc)) => format!(
                "{} (exception {exc})",
                s.board.image.function_at(pc).unwrap_or("-")
            ),
            (exc, None) => format!("tail-chained after exception {exc}"),
        },
        masked_max_us: soc.mask_max.0 as f64 * 1e-6,
        masked_max_at: s
            .board
            .image
            .function_at(soc.mask_max.1)
            .unwrap_or("-")
            .to_string(),
        samples_missed: hx.samples_missed,
        hx711_power_downs: hx.power_downs,
        console_overruns: soc.usart2.overruns,
        console_input_lost: {
            let out: Vec<u8> = soc.console_out.iter().map(|&(_, b)| b).collect();
            out.windows(10).filter(|w| w == b"input lost").count() as u64
        },
        cpi: soc.clock.cpi_milli() as f64 / 1000.0,
        lsi_hz: soc.iwdg.lsi_hz,
        flash_timing: match soc.flash.timing {
            FlashTiming::Max => "max",
            FlashTiming::Typical => "typical",
        },
        instructions: insns,
        mips: insns as f64 / wall.max(1e-9) / 1e6,
        realtime_factor: sim_s / wall.max(1e-9),
        realtime_factor_min: s.board.speed.min_factor.unwrap_or(sim_s / wall.max(1e-9)),
        skipped_instructions: soc.loops.stats.insns,
        trace_digest: s.board.trace_digest(),
        erase_counts: soc.world.flash.with(|f| f.erase_counts().to_vec()),
        core_faults: s
            .board
            .faults()
            .iter()
            .map(|f| {
                format!(
                    "{} at {:#010x} ({})",
                    f.what,
                    f.pc,
                    f.function.as_deref().unwrap_or("?")
                )
            })
            .collect(),
        diagnostics: soc.diagnostics.iter().map(|d| d.what.clone()).collect(),
        console_flood_bytes: flood_bytes,
        modbus_flood_bytes: mb_flood.bytes,
        modbus_reply_bytes: soc.modbus_out.len() as u64,
        modbus_de_losses: soc.modbus_de_losses,
        modbus_overruns: soc.usart3.overruns,
        checks,
        modbus_poll: s.poller.as_ref().map(|p| p.stats),
        motion_before_request,
        step: m.axis.step_timing(),
        log: s.board.log.clone(),
        tasks: (0..soc.exc_insns.len())
            .filter(|&e| e == 0 || soc.exc_entries[e] > 0)
            .map(|e| (exception_name(e), soc.exc_entries[e], soc.exc_insns[e]))
            .collect(),
        timing: s.control_timing(),
        estop_reactions_us: s.estop_reactions_us(),
        curve_json,
    })
}

/// After a signature scene (issue 34): the last docking as the console's `curve last
/// --json` shows it (its cycle, each stroke's verdict and first failed object) and as
/// the PLC reads it (status bit 12; input registers 68 on: the verdict, the failed
/// object's code, the cone's NOK and judged dockings, the newest stroke's verdict), each
/// against what the scene must produce ([`hil_sim::sigscene::expected`]). The curve's
/// line is returned.
fn signature_shown(
    s: &mut Session,
    name: &str,
    cycles: u32,
    checks: &mut Vec<(String, bool, String)>,
) -> Result<String, Halt> {
    use docking_logic::modbus::{ir, status};
    use docking_logic::signature::objects::Object;
    let (ins, ext) = hil_sim::sigscene::expected(name, cycles, cycles);
    let code = |o: Option<&str>| {
        o.and_then(|n| Object::ALL.into_iter().find(|x| x.name() == n))
            .map_or(0, |x| u16::from(x.code()))
    };
    let line = s.console_json("curve last --json")?;
    let v: serde_json::Value = serde_json::from_str(line.trim()).unwrap_or_default();
    let stroke = |k: &str| {
        (
            v[k]["verdict"].as_str().map(str::to_string),
            v[k]["failed"].as_str().map(str::to_string),
        )
    };
    let (si, se) = (stroke("insertion"), stroke("extraction"));
    let verdict = |want: Option<&str>| {
        (
            Some(if want.is_some() { "nok" } else { "ok" }.to_string()),
            want.map(str::to_string),
        )
    };
    // The extraction after a disturbed insertion is not the scene's point (sigscene).
    let ext_free = ins.is_some() && ext.is_none();
    let ok = v["cycle"].as_u64() == Some(u64::from(cycles))
        && si == verdict(ins)
        && (ext_free || se == verdict(ext));
    checks.push((
        format!(
            "the console's `curve last` shows cycle {cycles}: insertion {}, extraction {}",
            ins.unwrap_or("ok"),
            if ext_free { "any" } else { ext.unwrap_or("ok") }
        ),
        ok,
        format!(
            "cycle {:?}, insertion {si:?}, extraction {se:?}",
            v["cycle"].as_u64()
        ),
    ));
    let word = s.read_inputs(0, 1)?.and_then(|w| w.first().copied());
    let regs = s.read_inputs(ir::SIG_VERDICT, ir::COUNT - ir::SIG_VERDICT)?;
    let at = |r: &Option<Vec<u16>>, a: u16| {
        r.as_ref()
            .and_then(|r| r.get(usize::from(a - ir::SIG_VERDICT)).copied())
    };
    let u32_at =
        |r: &Option<Vec<u16>>, a: u16| Some(u32::from(at(r, a)?) << 16 | u32::from(at(r, a + 1)?));
    let nok_dockings = hil_sim::sigscene::disturbed(name, cycles).count() as u32;
    let failed = code(ins.or(ext));
    let ok = word.is_some_and(|w| w & status::SIGNATURE_NOK != 0)
        && at(&regs, ir::SIG_VERDICT) == Some(2)
        && at(&regs, ir::SIG_FAILED) == Some(failed)
        && u32_at(&regs, ir::SIG_CYCLE) == Some(cycles)
        && u32_at(&regs, ir::SIG_CONE_NOK) == Some(nok_dockings)
        && u32_at(&regs, ir::SIG_CONE_JUDGED) == Some(cycles)
        && at(&regs, ir::SIG_STROKE).is_some_and(|v| (1..=4).contains(&v));
    checks.push((
        format!(
            "Modbus: status bit 12, verdict 2 (NOK), failed object {failed}, cycle {cycles}, {nok_dockings} NOK of {cycles} judged"
        ),
        ok,
        format!(
            "status word {word:?}, registers {}-{} {regs:?}",
            ir::SIG_VERDICT,
            ir::COUNT - 1
        ),
    ));
    Ok(line)
}

/// The `faults` of a `faults --json` reply.
fn parse_faults(json: &str) -> Option<Vec<FaultSeen>> {
    let v: serde_json::Value = serde_json::from_str(json.trim()).ok()?;
    v["faults"]
        .as_array()?
        .iter()
        .map(|f| {
            Some(FaultSeen {
                kind: docking_controller_fault_name(f["kind"].as_str()?),
                cycle: f["cycle"].as_u64()? as u32,
                phase: f["phase"].as_u64().map(|p| p as u8),
                t_s: f["t_s"].as_f64()?,
                peak_force_n: f["peak_force_n"].as_f64()?,
            })
        })
        .collect()
}

fn leak(s: String) -> &'static str {
    Box::leak(s.into_boxed_str())
}

/// The value of `"key":` in a one-line JSON object (a string's contents, or the raw
/// number / literal).
pub fn json_field(json: &str, key: &str) -> Option<String> {
    let pat = format!("\"{key}\":");
    let at = json.find(&pat)? + pat.len();
    let rest = &json[at..];
    if let Some(r) = rest.strip_prefix('"') {
        Some(r[..r.find('"')?].to_string())
    } else {
        let end = rest.find([',', '}']).unwrap_or(rest.len());
        Some(rest[..end].trim().to_string())
    }
}

/// What the log held before the board ran.
#[derive(Clone, Debug, Default)]
pub struct Prefill {
    /// Erases done so far.
    pub erases: u32,
    /// The newest record of every kind.
    pub newest: Newest,
}

/// The newest record of every kind: (seq, payload).
pub type Newest = Vec<Option<(u32, Vec<u8>)>>;

pub(crate) fn read_newest(flash: &SharedFlash) -> Result<Newest, String> {
    let (mut log, _) =
        docking_logic::odometer::open_log(flash.clone()).map_err(|e| format!("open: {e}"))?;
    Ok((0..docking_logic::storage::MAX_KINDS)
        .map(|k| {
            log.latest(k)
                .ok()
                .flatten()
                .map(|r| (r.seq, r.data().to_vec()))
        })
        .collect())
}

fn prefill_log(flash: &SharedFlash) -> Result<Prefill, String> {
    hil_sim::flash::fill_log_to_maintenance(flash)?;
    Ok(Prefill {
        erases: flash.with(|f| f.erase_counts().iter().sum()),
        newest: read_newest(flash)?,
    })
}

/// Dock; in the middle of the insertion (10 mm deep, the rod in the cone, the lock
/// released) pull NRST; then watch the pins for 5 s: no STEP pulse, no EN low, no lock
/// drive may come before a request. Then ask (the dock-request input): the machine must
/// home out of the cone and lock, with no fault. Returns whether anything moved before
/// the request.
fn power_cycle(s: &mut Session, checks: &mut Vec<(String, bool, String)>) -> Result<bool, Halt> {
    let engage = s.engage_um;
    let deadline = s.now() + 60 * PS_PER_S;
    let mut inserting = false;
    while s.now() < deadline {
        s.auto_dock(1);
        s.run_for(PS_PER_MS)?;
        if s.machine().axis.pos_um() >= (engage + 10_000) as f64 {
            inserting = true;
            break;
        }
    }
    let t_reset = s.now();
    s.board.reset_pin();
    let steps = |x: &Session| {
        let t = x.machine().axis.step_timing();
        t.pulses_pos + t.pulses_neg + t.pulses_disabled
    };
    let pulses0 = steps(s);
    let pos0 = s.machine().axis.pos_um();
    s.run_for(5 * PS_PER_S)?;
    let edges = &s.board.soc().edges;
    let moved_pins = edges.iter().any(|e| {
        e.t_ps > t_reset
            && match e.signal {
                crate::world::Signal::EnN => !e.high,
                crate::world::Signal::LockIn1 | crate::world::Signal::LockIn2 => e.high,
                _ => false,
            }
    });
    let moved = moved_pins || steps(s) != pulses0 || s.machine().axis.pos_um() != pos0;
    checks.push((
        "in the cone at the reset".into(),
        inserting,
        format!(
            "carriage at {:.3} mm (engagement at {:.3} mm)",
            pos0 / 1000.0,
            engage as f64 / 1000.0
        ),
    ));
    checks.push((
        "no motion after the reset without a request".into(),
        !moved,
        format!(
            "{} step pulses, EN/lock edges after the reset: {}",
            steps(s) - pulses0,
            moved_pins
        ),
    ));
    // The request: the PLC releases DOCK (it was asserted through the reset) and asserts
    // it again.
    s.set_dock(false);
    s.run_for(100 * PS_PER_MS)?;
    s.set_dock(true);
    let deadline = s.now() + 60 * PS_PER_S;
    let homed = s.run_until(deadline, |x| {
        x.machine().axis.pos_um() <= 0.0
            && x.machine().lock.fraction_locked() >= 1.0
            && !x.machine().axis.enabled()
    })?;
    checks.push((
        "homes out of the cone on request".into(),
        homed,
        format!("carriage at {:.3} mm", s.machine().axis.pos_um() / 1000.0),
    ));
    Ok(moved)
}

/// Whether the pins show the machine at `stage` (`estop-bounce`'s moments; the log's
/// cycle bookkeeping is not used: an aborted cycle never completes).
fn at_stage(s: &Session, stage: Stage) -> bool {
    let m = s.machine();
    let depth = m.axis.pos_um() as i32 - s.engage_um;
    let moving_in = m.axis.enabled() && m.axis.forward();
    match stage {
        Stage::Idle => s.home_and_ready(),
        Stage::PreAlign => moving_in && m.lock.fraction_locked() >= 1.0 && depth < 0,
        Stage::Inserting => {
            moving_in && m.lock.fraction_locked() <= 0.0 && depth >= ESTOP_BOUNCE_DEPTH_UM
        }
        Stage::Mated => s.plc_out().mated,
        Stage::Returning | Stage::Other => false,
    }
}

/// `estop-bounce`: the disturbances of [`ESTOP_BOUNCE`], each at its stage of a docking
/// the PLC asks for with DOCK, at the board's own timing (a 50 µs pulse is 50 µs on the
/// EXTI line). After each: the fault latched with FAULT high, READY low and every motor
/// off; the PLC releases DOCK and clears over Modbus (coil 2), refused while a bouncing
/// release holds the input open, accepted once it is closed; home. Then one more dock.
fn estop_bounce(
    s: &mut Session,
    checks: &mut Vec<(String, bool, String)>,
) -> Result<PlcReport, Halt> {
    let mut rep = PlcReport::default();
    let (mut episodes, mut injected, mut latched, mut accepted, mut refused) = (0u32, 0, 0, 0, 0);
    let mut notes = Vec::new();
    let deadline = s.now() + 10 * PS_PER_S;
    s.run_until(deadline, Session::home_and_ready)?;
    for (stage, d) in ESTOP_BOUNCE {
        if stage != Stage::Idle {
            s.set_dock(true);
            let deadline = s.now() + 60 * PS_PER_S;
            if !s.run_until(deadline, |x| at_stage(x, stage))? {
                notes.push(format!("{stage:?} never reached"));
                break;
            }
        }
        episodes += 1;
        match d {
            EstopDisturbance::Pulse(us) => s.estop_pulse(u64::from(us) * 1_000_000)?,
            EstopDisturbance::BouncingRelease => {
                s.set_estop(true);
                s.run_for(BOUNCE_OPEN_MS * PS_PER_MS)?;
                if s.coil(2)? == Err(0x01) {
                    refused += 1;
                }
                s.set_estop(false);
                for us in BOUNCE_RELEASE_US {
                    s.run_exact(u64::from(BOUNCE_GAP_US) * 1_000_000)?;
                    s.estop_pulse(u64::from(us) * 1_000_000)?;
                }
            }
        }
        injected += d.edges();
        s.run_for(100 * PS_PER_MS)?;
        let st = s.console_json("status --json")?;
        let out = s.plc_out();
        let m = s.machine();
        let off = !m.axis.enabled() && !m.lock.driven();
        if json_field(&st, "fault").as_deref() == Some("emergency_stop")
            && out.fault
            && !out.ready
            && off
        {
            latched += 1;
        } else {
            notes.push(format!(
                "{stage:?} {d:?}: not latched ({out:?}, motors off {off}): {st}"
            ));
        }
        s.set_dock(false);
        s.run_for(100 * PS_PER_MS)?;
        match s.coil(2)? {
            Ok(()) => accepted += 1,
            Err(code) => notes.push(format!("{stage:?} {d:?}: clear refused ({code})")),
        }
        let deadline = s.now() + 60 * PS_PER_S;
        s.run_until(deadline, Session::home_and_ready)?;
        s.run_for(300 * PS_PER_MS)?;
    }
    s.board.poll_rtt();
    s.observe();
    let logged = s.seen.estop_edges_logged;
    // The next dock completes: mated, undocked, home.
    let before = s.seen.cycles_completed;
    s.set_dock(true);
    let deadline = s.now() + 60 * PS_PER_S;
    let mated = s.run_until(deadline, |x| x.plc_out().mated)?;
    s.set_dock(false);
    let deadline = s.now() + 60 * PS_PER_S;
    let home = s.run_until(deadline, Session::home_and_ready)?;
    let docked = mated && home && s.seen.cycles_completed == before + 1;
    let n = ESTOP_BOUNCE.len() as u32;
    checks.push((
        "every episode latched emergency_stop, FAULT high, READY low, every motor off".into(),
        episodes == n && latched == n,
        format!(
            "{latched} of {episodes} episodes ({n} planned); {}",
            notes.join("; ")
        ),
    ));
    checks.push((
        "every edge accounted for by the firmware".into(),
        logged == injected,
        format!("{injected} edges made, {logged} logged as latched"),
    ));
    checks.push((
        "the PLC's clear refused while open, accepted once closed".into(),
        refused == 3 && accepted == n,
        format!("{refused} refused while open (3 expected), {accepted} accepted of {n}"),
    ));
    checks.push((
        "the next dock completes".into(),
        docked,
        format!("mated {mated}, home {home}"),
    ));
    rep.estop_episodes = Some(episodes);
    rep.estop_edges_injected = Some(injected);
    rep.estop_edges_latched = Some(logged);
    rep.estop_faults_latched = Some(latched);
    rep.clears_accepted = Some(accepted);
    rep.clears_refused_while_open = Some(refused);
    rep.docked_after_estops = Some(docked);
    Ok(rep)
}

/// `maintenance-lockout`: the technician enters maintenance mode at the console; the
/// PLC reads the mode (status bit 11, input register 10), asks to dock over Modbus
/// (coil 0: exception 01, the wrong state) and with the DOCK pin for 2 s (nothing
/// moves; READY, PD0, stays low throughout, on the pin's recorded edges); `maint
/// exit`; the PLC docks over Modbus, undocks, home.
fn maintenance_lockout(
    s: &mut Session,
    checks: &mut Vec<(String, bool, String)>,
) -> Result<PlcReport, Halt> {
    use crate::world::Signal;
    use docking_logic::modbus::{ir, status};
    let mut rep = PlcReport::default();
    let deadline = s.now() + 10 * PS_PER_S;
    let ready_at_boot = s.run_until(deadline, Session::home_and_ready)?;
    let entered = s.maint_enter()?;
    s.run_for(50 * PS_PER_MS)?;
    let t_in = s.now();
    let ready_after_entry = s.plc_out().ready;
    let regs = s.read_inputs(0, ir::MAINTENANCE_MODE + 1)?;
    let shown = regs.as_ref().is_some_and(|r| {
        r[0] & status::MAINTENANCE_MODE != 0 && r[usize::from(ir::MAINTENANCE_MODE)] == 1
    });
    let dock_reply = s.coil(0)?;
    let refused = dock_reply == Err(0x01);
    // The DOCK pin, asserted for 2 s.
    let pulses = |x: &Session| {
        let t = x.machine().axis.step_timing();
        t.pulses_pos + t.pulses_neg + t.pulses_disabled
    };
    let p0 = pulses(s);
    s.set_dock(true);
    s.run_for(2 * PS_PER_S)?;
    s.set_dock(false);
    s.run_for(200 * PS_PER_MS)?;
    let t_out = s.now();
    let pulses_meanwhile = pulses(s) - p0;
    let edges = &s.board.soc().edges;
    let in_window = |e: &&crate::soc::Edge| e.t_ps >= t_in && e.t_ps <= t_out;
    let moved = pulses_meanwhile != 0
        || edges.iter().filter(in_window).any(|e| match e.signal {
            Signal::EnN => !e.high,
            Signal::LockIn1 | Signal::LockIn2 => e.high,
            _ => false,
        });
    let ready_rose = edges
        .iter()
        .filter(in_window)
        .any(|e| e.signal == Signal::Ready && e.high);
    let ready_low = ready_at_boot && !ready_after_entry && !ready_rose && !s.plc_out().ready;
    let exited = s.maint_exit()?;
    s.run_for(100 * PS_PER_MS)?;
    let ready_back = s.plc_out().ready;
    let regs_after = s.read_inputs(ir::MAINTENANCE_MODE, 1)?;
    let accepted = s.coil(0)? == Ok(());
    let deadline = s.now() + 60 * PS_PER_S;
    let mated = s.run_until(deadline, |x| x.plc_out().mated)?;
    let undock = s.coil(1)? == Ok(());
    let deadline = s.now() + 60 * PS_PER_S;
    let home = s.run_until(deadline, Session::home_and_ready)?;
    let docked =
        exited && ready_back && accepted && mated && undock && home && s.seen.cycles_completed == 1;
    checks.push((
        "maintenance mode entered at the console".into(),
        entered,
        String::new(),
    ));
    checks.push((
        "READY (PD0) low throughout maintenance mode".into(),
        ready_low,
        format!("READY at boot {ready_at_boot}, after entry {ready_after_entry}, rose meanwhile {ready_rose}"),
    ));
    checks.push((
        "status bit 11 and input register 10 show the mode".into(),
        shown,
        format!("{regs:?}"),
    ));
    checks.push((
        "the Modbus dock (coil 0) refused with exception 01 (the wrong state)".into(),
        refused,
        format!("{dock_reply:?}"),
    ));
    checks.push((
        "the DOCK pin ignored: nothing moved".into(),
        !moved,
        format!("{pulses_meanwhile} step pulses"),
    ));
    checks.push((
        "after maint exit the PLC docks over Modbus".into(),
        docked,
        format!("exit {exited}, READY {ready_back}, register 10 {regs_after:?}, dock accepted {accepted}, mated {mated}, undock {undock}, home {home}, cycles {}", s.seen.cycles_completed),
    ));
    rep.ready_low_in_maintenance = Some(ready_low);
    rep.maintenance_shown = Some(shown);
    rep.modbus_dock_refused = Some(refused);
    rep.dock_pin_ignored = Some(!moved);
    rep.docked_after_maintenance = Some(docked);
    Ok(rep)
}

/// `heavy-default` after its trip: the technician clears the fault at the console
/// (maintenance mode, `clear-fault`, `maint exit`); the machine must go home, out of the
/// cone, locked, driver off, within 60 s.
fn clear_out_of_the_cone(
    s: &mut Session,
    checks: &mut Vec<(String, bool, String)>,
) -> Result<bool, Halt> {
    let entered = s.maint_enter()?;
    let r = s.console("clear-fault", 2 * PS_PER_S)?;
    let cleared = r.starts_with("ok");
    let exited = s.maint_exit()?;
    let deadline = s.now() + 60 * PS_PER_S;
    let home = s.run_until(deadline, Session::home_and_ready)?;
    let pos = s.machine().axis.pos_um();
    let out = entered && cleared && exited && home && pos < s.engage_um as f64;
    checks.push((
        "out of the cone after a clear-fault".into(),
        out,
        format!(
            "'{}'; carriage at {:.3} mm, home and READY {home}",
            r.trim(),
            pos / 1000.0
        ),
    ));
    Ok(out)
}

/// Boot, make the firmware write a record (a latched fault writes a counter snapshot),
/// pull NRST at a random instruction inside that write, reboot on the same flash, and
/// check that the counters came back, old or new, never older.
fn power_cut_write(
    s: &mut Session,
    checks: &mut Vec<(String, bool, String)>,
    opts: &SceneOptions,
) -> Result<(), Halt> {
    s.run_for(PS_PER_S)?;
    let before = s.console_json("wear --json")?;
    let faults_before: u64 = json_field(&before, "faults")
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    // A disconnected load cell latches a fault within 3 sample periods; the fault
    // writes a counter snapshot.
    s.machine()
        .hx
        .set_fault(hil_sim::hx711::Hx711Fault::Disconnected);
    let ops0 = s.board.soc().flash.ops_started;
    let deadline = s.now() + 2 * PS_PER_S;
    // In 1 µs steps, so the write's first word program is seen when it starts.
    while s.board.soc().flash.ops_started == ops0 && s.now() < deadline {
        let t = s.now() + 1_000_000;
        s.board.run_until(t)?;
    }
    let started = s.board.soc().flash.ops_started > ops0;
    // A record is one 64-byte slot: 16 word programs (DS8626: up to 100 µs each) and the
    // CPU between them. Pull NRST at a random instant (1 µs resolution) inside it.
    let mut rng =
        hil_sim::rng::Rng::new(opts.session.seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xC07);
    let t0 = s.now();
    let cut_at = t0 + (rng.uniform() * 16.0 * 110.0) as u64 * 1_000_000;
    while s.now() < cut_at {
        let t = s.now() + 1_000_000;
        s.board.run_until(t)?;
    }
    let inside =
        s.board.soc().flash.busy_until().is_some() || s.board.soc().flash.ops_started - ops0 < 16;
    let writes = s.board.soc().flash.ops_started - ops0;
    s.board.reset_pin();
    s.machine().hx.set_fault(hil_sim::hx711::Hx711Fault::None);
    s.run_for(2 * PS_PER_S)?;
    let after = s.console_json("wear --json")?;
    let faults_after: u64 = json_field(&after, "faults")
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    let lifetime = |j: &str| json_field(j, "lifetime_cycles").and_then(|v| v.parse::<u64>().ok());
    checks.push((
        "record write cut".into(),
        started && writes > 0 && inside,
        format!(
            "NRST pulled {:.1} µs into the write, after {writes} of its 16 word programs",
            (cut_at - t0) as f64 * 1e-6
        ),
    ));
    checks.push((
        "counters intact".into(),
        faults_after >= faults_before
            && faults_after <= faults_before + 1
            && lifetime(&after) == lifetime(&before)
            && lifetime(&after).is_some(),
        format!("faults {faults_before} before, {faults_after} after; {before} / {after}"),
    ));
    Ok(())
}

/// What the wear estimate costs the Cortex-M4, measured on the image.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct EstimateCost {
    /// (readings, instructions) of one fit (`Fit::new`), after each reading entered.
    pub fit: Vec<(usize, u64)>,
    /// Instructions of one estimate at the current wear (`Fit::at`, a `wear` query).
    pub at: u64,
}

impl EstimateCost {
    /// A table for a terminal.
    pub fn to_text(&self) -> String {
        let mut s = String::from(
            "# the wear estimate on the Cortex-M4 (release image, instructions in thread mode; 168 MHz at CPI 1)\nreadings | fit instructions | µs\n",
        );
        for (k, n) in &self.fit {
            s += &format!("{k:>8} | {n:>16} | {:>5.0}\n", *n as f64 / 168.0);
        }
        s += &format!(
            "# one estimate at the current wear (wear query): {} instructions, {:.1} µs",
            self.at,
            self.at as f64 / 168.0
        );
        s
    }
}

/// Enter `n` micrometer readings on the console of a board running `opts`'s image and
/// meter the fit each one triggers, then one `wear` query.
pub fn estimate_cost(opts: &Options, n: usize) -> Result<EstimateCost, String> {
    let mut s = Session::new(opts.clone())?;
    let halt = |e: Halt| e.to_string();
    s.run_for(PS_PER_S).map_err(halt)?;
    for cmd in ["pin set 2468", "maint 2468", "measure --baseline 26.000"] {
        let r = s.console(cmd, 5 * PS_PER_S).map_err(halt)?;
        if !r.starts_with("ok") {
            return Err(format!("'{cmd}': {}", r.trim()));
        }
    }
    let entry = |part: &str| {
        s.board
            .image
            .symbol_containing(part)
            .map(|(a, _)| a)
            .ok_or_else(|| format!("no symbol {part} in the image"))
    };
    let (fit_at, at_at) = (entry("8estimate3Fit3new")?, entry("8estimate3Fit2at")?);
    let mut fit = Vec::new();
    s.board.meter(fit_at);
    for k in 1..=n {
        let bore = 26_000 + 10 * k as u32;
        let r = s
            .console(
                &format!("measure {}.{:03}", bore / 1000, bore % 1000),
                5 * PS_PER_S,
            )
            .map_err(halt)?;
        if !r.starts_with("ok") {
            return Err(format!("measure: {}", r.trim()));
        }
        let m = s.board.soc().meter.clone().unwrap_or_default();
        if m.calls as usize != k {
            return Err(format!("{} fits metered after {k} readings", m.calls));
        }
        fit.push((k, m.last));
    }
    // The estimate is evaluated when what it depends on changes (a reading, a cycle)
    // and kept: `wear` reads it for nothing. One more reading evaluates it.
    s.board.meter(at_at);
    let bore = 26_000 + 10 * (n as u32 + 1);
    let _ = s
        .console(
            &format!("measure {}.{:03}", bore / 1000, bore % 1000),
            5 * PS_PER_S,
        )
        .map_err(halt)?;
    let at = s.board.soc().meter.as_ref().map_or(0, |m| m.last);
    Ok(EstimateCost { fit, at })
}

#[cfg(test)]
mod script_reply_tests {
    use super::script_reply;

    #[test]
    fn the_echo_the_banner_and_the_prompt_are_left_out() {
        let raw = "status\r\nstate=idle phase=none\r\nidle> ";
        assert_eq!(script_reply(raw, "status"), "state=idle phase=none\r\n");
        // Echo off: the reply as it came.
        assert_eq!(script_reply("ok: x\r\n", "dock"), "ok: x\r\n");
        // A PIN is echoed as stars.
        assert_eq!(
            script_reply("maint ****\r\nok: maintenance mode\r\nidle# ", "maint 2468"),
            "ok: maintenance mode\r\n"
        );
        // After a reset: the banner and the boot prompt.
        let raw = "# docking-controller 0.1.0 reset=watchdog; type 'help'\r\npower_up> ";
        assert_eq!(script_reply(raw, "status"), "");
    }
}

/// One metered function: calls, instructions in all, the most of one call.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Metered {
    /// Calls completed.
    pub calls: u64,
    /// Their instructions.
    pub insns: u64,
    /// The most instructions of one call.
    pub max: u64,
}

impl Metered {
    fn of(m: Option<crate::soc::FnMeter>) -> Self {
        let m = m.unwrap_or_default();
        Self {
            calls: m.calls,
            insns: m.insns,
            max: m.max,
        }
    }

    /// Mean instructions a call.
    pub fn mean(&self) -> f64 {
        self.insns as f64 / self.calls.max(1) as f64
    }

    fn json(&self) -> String {
        format!(
            "{{\"calls\":{},\"instructions\":{},\"mean\":{:.1},\"max\":{}}}",
            self.calls,
            self.insns,
            self.mean(),
            self.max
        )
    }
}

/// What the docking signature costs the image (issue 34), measured on the board:
/// [`signature_cost`].
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SignatureCost {
    /// The HX711's rate and the emulated core's CPI.
    pub rate_sps: u32,
    /// See [`Self::rate_sps`].
    pub cpi: f64,
    /// `Controller::capture` over one docking: one call a service turn (after each
    /// control step), each taking the newest sample into its bin.
    pub capture: Metered,
    /// Samples the image read over that docking.
    pub samples: u64,
    /// `Monitor::judge`: one call a stroke (the objects, the figures, the summary).
    pub judge: Metered,
    /// `Controller::persist_signature`: a turn at rest (a part of a record, at most
    /// `WRITE_BUDGET` bytes) after the next docking, until nothing waits.
    pub persist: Metered,
    /// The signature's RAM: its buffers (`SIGNATURE_MEM`) and its monitor and store
    /// (`SIGNATURE`), both in the CCM RAM, bytes.
    pub ccm_bytes: (u32, u32),
    /// Flash a record takes in sectors 2–4: a NOK docking's curves, a reference, a
    /// summary, bytes (frame headers included); and the sectors' bytes.
    pub frame_bytes: (usize, usize, usize),
    /// See [`Self::frame_bytes`].
    pub store_bytes: u32,
}

impl SignatureCost {
    /// µs of `insns` instructions at 168 MHz and this CPI.
    fn us(&self, insns: f64) -> f64 {
        insns * self.cpi / 168.0
    }

    /// A table for a terminal.
    pub fn to_text(&self) -> String {
        let row = |what: &str, m: &Metered| {
            format!(
                "{what:<44} | {:>5} | {:>8.1} | {:>6} | {:>7.1}\n",
                m.calls,
                m.mean(),
                m.max,
                self.us(m.max as f64)
            )
        };
        let mut s = format!(
            "# the docking signature on the Cortex-M4 (release image, {} SPS, CPI {}, 168 MHz)\nwhat                                         | calls |     mean |    max | max µs\n",
            self.rate_sps, self.cpi
        );
        s += &row("capture, a service turn after each step", &self.capture);
        s += &row("judge, a stroke", &self.judge);
        s += &row("persist, a turn at rest (128 B a turn)", &self.persist);
        let (nok, reference, summary) = self.frame_bytes;
        s += &format!(
            "# capture: {:.1} instructions a sample ({} samples in the docking)\n# RAM (CCM): {} B of buffers (SIGNATURE_MEM), {} B of monitor and store (SIGNATURE)\n# flash: a NOK docking's curves {nok} B, a reference {reference} B, a summary {summary} B; sectors 2-4 {} B (about {} dockings of summaries a 16 KiB sector)",
            self.capture.insns as f64 / self.samples.max(1) as f64,
            self.samples,
            self.ccm_bytes.0,
            self.ccm_bytes.1,
            self.store_bytes,
            16 * 1024 / summary.max(1)
        );
        s
    }

    /// One JSON object.
    pub fn to_json(&self) -> String {
        let (nok, reference, summary) = self.frame_bytes;
        format!(
            "{{\"rate_sps\":{},\"cpi\":{},\"capture\":{},\"samples\":{},\"capture_instructions_per_sample\":{:.1},\"judge\":{},\"persist\":{},\"ccm_buffers_bytes\":{},\"ccm_monitor_store_bytes\":{},\"nok_frame_bytes\":{nok},\"reference_frame_bytes\":{reference},\"summary_frame_bytes\":{summary},\"store_bytes\":{}}}",
            self.rate_sps,
            self.cpi,
            self.capture.json(),
            self.samples,
            self.capture.insns as f64 / self.samples.max(1) as f64,
            self.judge.json(),
            self.persist.json(),
            self.ccm_bytes.0,
            self.ccm_bytes.1,
            self.store_bytes
        )
    }
}

/// Meter the docking signature on a board running `opts`'s image: the capture over one
/// docking (every service turn, every sample), then the next docking's two judgements
/// and the turns at rest that write its records.
pub fn signature_cost(opts: &Options) -> Result<SignatureCost, String> {
    use docking_logic::framelog::frame_size;
    use docking_logic::signature::records::{NOK_LEN, REFERENCE_LEN, SECTORS, SUMMARY_LEN};
    let mut s = Session::new(opts.clone())?;
    let halt = |e: Halt| e.to_string();
    s.run_for(PS_PER_S).map_err(halt)?;
    let entry = |s: &Session, part: &str| {
        s.board
            .image
            .symbol_containing(part)
            .map(|(a, _)| a)
            .ok_or_else(|| format!("no symbol {part} in the image"))
    };
    let capture_at = entry(&s, "10controller19Controller$LT$B$GT$7capture17h")?;
    let judge_at = entry(&s, "7monitor16Monitor$LT$M$GT$5judge17h")?;
    let persist_at = entry(
        &s,
        "10controller19Controller$LT$B$GT$17persist_signature17h",
    )?;
    let size = |s: &Session, part: &str| s.board.image.symbol_containing(part).map_or(0, |x| x.1);
    let ccm_bytes = (size(&s, "SIGNATURE_MEM"), size(&s, "9SIGNATURE17h"));
    // Run until `done` (at most 300 s of machine time), the PLC docking when ready.
    let run = |s: &mut Session, cycles: u32, done: &dyn Fn(&Session) -> bool| {
        let deadline = s.now() + 300 * PS_PER_S;
        while !done(s) {
            if s.now() > deadline {
                return Err("the docking did not end".to_string());
            }
            s.auto_dock(cycles);
            s.run_for(5 * PS_PER_MS).map_err(halt)?;
        }
        Ok(())
    };
    s.board.meter(capture_at);
    let samples0 = s.machine().hx.stats().samples_read;
    run(&mut s, 1, &|s| s.seen.cycles_completed >= 1 && s.at_rest())?;
    let capture = Metered::of(s.board.soc().meter.clone());
    let samples = s.machine().hx.stats().samples_read - samples0;
    s.board.meter(judge_at);
    run(&mut s, 2, &|s| {
        s.board.soc().meter.as_ref().is_some_and(|m| m.calls >= 2)
    })?;
    let judge = Metered::of(s.board.soc().meter.clone());
    s.board.meter(persist_at);
    run(&mut s, 2, &|s| s.seen.cycles_completed >= 2 && s.at_rest())?;
    // The rest: 3 s, every record written (a NOK-free docking: summary and reference).
    s.run_for(3 * PS_PER_S).map_err(halt)?;
    let persist = Metered::of(s.board.soc().meter.clone());
    Ok(SignatureCost {
        rate_sps: opts.rate_sps,
        cpi: opts.board.cpi_milli as f64 / 1000.0,
        capture,
        samples,
        judge,
        persist,
        ccm_bytes,
        frame_bytes: (
            frame_size(NOK_LEN),
            frame_size(REFERENCE_LEN),
            frame_size(SUMMARY_LEN),
        ),
        store_bytes: SECTORS.iter().sum(),
    })
}
