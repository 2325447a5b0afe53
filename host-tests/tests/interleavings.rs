//! The interleaving checker (issue 32): random sequences of everything that reaches the
//! machine — console lines and their phases, Modbus commands, the DOCK pin, E-STOP
//! pulses and presses (between steps, and **inside** a step: at a look of the step at
//! the stop latch), lock and load-cell faults, a failing flash, long jobs that queue
//! samples behind them, resets — at the instants the board has them, with the
//! invariants of docs/board.md ("What holds between the steps") checked after every tick
//! and every event. A failing sequence shrinks to a minimal one (proptest's state
//! machine testing, `proptest-state-machine`).
//!
//! The model of the board here is the board's structure, not a simulation of its code:
//! a control run (the PLC's pins read once, one step per queued sample, the outputs
//! written), then the service's window (what idle published applied, the jobs, the
//! flash's turn); console lines run as the board runs them (the line's job, idle's
//! third phase without the controller, the fourth phase's job), and so on. What it runs
//! is the logic crate's code: the controller, the safety kernel, the console. The
//! release image's own interleavings at µs resolution are the virtual board's campaign
//! (`vboard/tests/interleavings.rs`).
//!
//! CI runs 2 000 sequences from a fixed seed (`every_interleaving_keeps_the_invariants`;
//! `INTERLEAVINGS_SEED=N` draws others); the ignored
//! test runs 10⁶: `cargo test --release -p host-tests --test interleavings -- --ignored`
//! (`INTERLEAVINGS_CASES` sets another count). How the checker was shown to find the
//! defects of 7c11783: docs/board.md.

use docking_logic::controller::Source;
use docking_logic::diag::ResetCause;
use docking_logic::odometer::kind::AUDIT;
use docking_logic::safety::KernelEvent;
use docking_logic::sequencer::{Request, State};
use hil_sim::hx711::Hx711Fault;
use hil_sim::lock::LockFault;
use hil_sim::rig::{Rig, RigOptions};
use proptest::prelude::*;
use proptest::test_runner::Config;
use proptest_state_machine::{prop_state_machine, ReferenceStateMachine, StateMachineTest};

/// The maintenance PIN every machine here has.
const PIN: &str = "2468";

/// A console line.
#[derive(Clone, Copy, Debug)]
enum Line {
    ClearFault,
    Stop,
    Dock,
    Undock,
    Home,
    Login,
    Logout,
    Status,
}

impl Line {
    fn text(self) -> String {
        match self {
            Line::ClearFault => "clear-fault".into(),
            Line::Stop => "stop".into(),
            Line::Dock => "dock".into(),
            Line::Undock => "undock".into(),
            Line::Home => "home".into(),
            Line::Login => format!("maint {PIN}"),
            Line::Logout => "maint exit".into(),
            Line::Status => "status".into(),
        }
    }
}

/// A PLC command over Modbus (a coil written).
#[derive(Clone, Copy, Debug)]
enum Coil {
    Dock,
    Undock,
    Clear,
    Stop,
    Home,
}

impl Coil {
    fn request(self) -> Request {
        match self {
            Coil::Dock => Request::Dock,
            Coil::Undock => Request::Undock,
            Coil::Clear => Request::ClearFault,
            Coil::Stop => Request::Stop,
            Coil::Home => Request::Home,
        }
    }
}

/// Something the load cell does.
#[derive(Clone, Copy, Debug)]
enum Load {
    Disconnect,
    Reconnect,
    Spike,
    Pull(bool),
}

/// One event of a sequence, at the instant the sequence has reached.
#[derive(Clone, Debug)]
enum Op {
    /// The next sample: a control run, then the service's window.
    Tick,
    /// That, `n` times.
    Wait(u16),
    /// The service holds the controller for `n` sample periods (a long job at rest):
    /// the samples queue, then one control run steps them all with one reading of the
    /// PLC's pins.
    LongJob(u8),
    /// An E-STOP pulse inside the next control step, at its `n`-th look at the stop
    /// latch; then that step.
    InsideStep(u8),
    /// The PLC asserts or releases DOCK.
    Dock(bool),
    /// An E-STOP pulse shorter than anything else: both edges now.
    EstopPulse,
    /// The E-STOP input opens (pressed) or closes.
    Estop(bool),
    /// A console line: its job with the controller (the command accepted or refused).
    Console(Line),
    /// Idle's third phase of the last line (without the controller: a login's PIN
    /// check, a report's formatting), then the fourth phase's job if one is due (a
    /// login's grant).
    ConsoleFinish,
    /// A PLC command over Modbus: one PDU's job, its reply on the line for 5 ms.
    Modbus(Coil),
    /// The load cell.
    Sensor(Load),
    /// The lock's screw sticks (or works again).
    LockStuck(bool),
    /// The odometer flash refuses every write (or takes them again).
    FlashFail(bool),
    /// A pin reset of the MCU, the machine where it is.
    Reset,
}

/// The reference model: only the sample rate (the checker checks the real thing).
struct Events;

impl ReferenceStateMachine for Events {
    type State = u32;
    type Transition = Op;

    fn init_state() -> BoxedStrategy<u32> {
        prop_oneof![4 => Just(80u32), 1 => Just(10u32)].boxed()
    }

    fn transitions(_: &u32) -> BoxedStrategy<Op> {
        let line = prop_oneof![
            3 => Just(Line::ClearFault),
            1 => Just(Line::Stop),
            2 => Just(Line::Dock),
            1 => Just(Line::Undock),
            1 => Just(Line::Home),
            3 => Just(Line::Login),
            2 => Just(Line::Logout),
            1 => Just(Line::Status),
        ];
        let coil = prop_oneof![
            3 => Just(Coil::Dock),
            2 => Just(Coil::Undock),
            3 => Just(Coil::Clear),
            1 => Just(Coil::Stop),
            1 => Just(Coil::Home),
        ];
        let cell = prop_oneof![
            Just(Load::Disconnect),
            Just(Load::Reconnect),
            Just(Load::Spike),
            any::<bool>().prop_map(Load::Pull),
        ];
        prop_oneof![
            10 => Just(Op::Tick),
            10 => (1u16..400).prop_map(Op::Wait),
            2 => (2u8..8).prop_map(Op::LongJob),
            4 => (1u8..10).prop_map(Op::InsideStep),
            6 => any::<bool>().prop_map(Op::Dock),
            4 => Just(Op::EstopPulse),
            2 => any::<bool>().prop_map(Op::Estop),
            8 => line.prop_map(Op::Console),
            5 => Just(Op::ConsoleFinish),
            6 => coil.prop_map(Op::Modbus),
            1 => cell.prop_map(Op::Sensor),
            1 => any::<bool>().prop_map(Op::LockStuck),
            2 => any::<bool>().prop_map(Op::FlashFail),
            1 => Just(Op::Reset),
        ]
        .boxed()
    }

    fn apply(state: u32, _: &Op) -> u32 {
        state
    }
}

/// What the invariants remember between checks.
#[derive(Debug, Default)]
struct Seen {
    /// An E-STOP edge came, and no clear was issued after it (nor a reset).
    estop_unanswered: bool,
    /// The carriage's travel and the lock's position at that edge's control run.
    travel_at_edge_um: f64,
    lock_at_edge: f64,
    /// The console said `ok: maintenance mode` (and not yet that it ended).
    maintenance: bool,
    /// A console request that moves (dock, undock, home, clear-fault) was accepted and
    /// has not started its motion yet: control runs left for it to start.
    console_motion: u32,
    /// A Modbus dock was accepted and has not started yet (control runs left).
    remote_dock: u32,
    /// Something was driven at the last check.
    moving: bool,
    /// The state at the last check.
    state: Option<State>,
    /// Lifetime and cone cycles at the last check.
    cycles: (u32, u32),
    /// The cycle under way reached the cone.
    reached_cone: bool,
    /// Audit records the console had written or queued (its `ok` to an audited
    /// command), and those in flash when the count started.
    audits_expected: u64,
    /// DOCK through the two-reading filter as docs/board.md states it (a change counts
    /// once two readings at steps at least 3/4 of a period apart agree), kept here from
    /// each control run's reading: the reading last taken (time ns), the one before's
    /// level, the level that counts; `None` after a reset (the first reading sets it,
    /// without an edge).
    dock_filter: Option<(u64, bool, bool)>,
}

/// The board, as the checker drives it.
struct Board {
    r: Rig,
    /// Samples read and not stepped yet.
    queued: Vec<KernelEvent>,
    /// The last console line's third phase is due.
    finish_due: bool,
    /// READY as the pins show it (written by a control run, and by a job that granted
    /// a mode).
    ready_pin: bool,
    /// The Modbus reply is on the line until then, ns.
    line_busy_until_ns: u64,
    /// What idle published of the maintenance mode (the flag the service applies).
    maintenance_published: bool,
    /// The console's output so far.
    out: String,
    seen: Seen,
    /// Events so far (for messages).
    n: usize,
    /// Every audit record the log has shown (its payload), see `audits_in_flash`.
    audit_payloads: std::collections::HashMap<Vec<u8>, u64>,
    /// Sample period, ns.
    period_ns: u64,
}

/// An invariant left out (`INTERLEAVINGS_SKIP=ready,…`: to show what the checker finds
/// behind a first finding, in the demonstrations of docs/board.md).
fn skip(name: &str) -> bool {
    std::env::var("INTERLEAVINGS_SKIP").is_ok_and(|v| v.split(',').any(|x| x == name))
}

/// 7c11783's board: the login reached the controller through the published flag at the
/// next window, both ways, and a job that granted a mode left READY to the next step
/// (`INTERLEAVINGS_BOARD=7c11783`; with the console's half of issue 32 reverted, how the
/// checker finds that defect).
fn old_board() -> bool {
    std::env::var("INTERLEAVINGS_BOARD").is_ok_and(|v| v == "7c11783")
}

impl Board {
    fn new(rate_sps: u32) -> Self {
        let mut r = Rig::booted(RigOptions::new(rate_sps));
        r.console.set_interactive(false);
        let reply = r.command(&format!("pin set {PIN}"), 50);
        assert!(reply.starts_with("ok"), "{reply}");
        let now_ns = r.clock.now_ns();
        let mut b = Self {
            period_ns: 1_000_000_000 / u64::from(rate_sps),
            r,
            queued: Vec::new(),
            finish_due: false,
            ready_pin: false,
            line_busy_until_ns: 0,
            maintenance_published: false,
            out: String::new(),
            seen: Seen::default(),
            n: 0,
            audit_payloads: std::collections::HashMap::new(),
        };
        b.ready_pin = b.r.ctrl.handshake().ready;
        // Booted with DOCK released (the rig's line), read so since.
        b.seen.dock_filter = Some((now_ns, false, false));
        b.seen.cycles = b.cycles();
        b.seen.state = Some(b.r.ctrl.state());
        b
    }

    fn now_ms(&self) -> u64 {
        self.r.clock.now_ns() / 1_000_000
    }

    fn cycles(&self) -> (u32, u32) {
        let o = self.r.ctrl.odometer();
        (o.lifetime().cycles, o.cone().cycles)
    }

    /// Audit records written so far: every one the log has shown, told apart by their
    /// payload (a sector move carries only the newest of a kind and gives it a new
    /// `seq`: counting the records present undercounted after a move, the ignored
    /// batch's finding after 363 656 sequences, a bug of the checker's).
    ///
    /// Two records may have the same payload (two clears in the same millisecond): each
    /// payload counts as often as the log has ever shown it at once (a move carries one
    /// copy, never more).
    fn audits_in_flash(&mut self) -> u64 {
        let mut now: std::collections::HashMap<Vec<u8>, u64> = std::collections::HashMap::new();
        self.r.ctrl.records(AUDIT, usize::MAX, |rec| {
            *now.entry(rec.data().to_vec()).or_default() += 1;
        });
        for (payload, n) in now {
            let most = self.audit_payloads.entry(payload).or_default();
            *most = (*most).max(n);
        }
        self.audit_payloads.values().sum()
    }

    /// The board's control task: the pins read once, a step per sample (or one if a
    /// period passed without), the kernel told, the outputs written; then the service's
    /// window after it.
    fn control_run(&mut self, samples: Vec<KernelEvent>) {
        let r = &mut self.r;
        let now_ns = r.clock.now_ns();
        let now_us = now_ns / 1_000;
        let dock = !r.dock_line.is_high();
        r.ctrl
            .set_plc(dock, r.estop_line.is_high(), r.estop_edges.snapshot());
        let mut stepped = false;
        for ev in samples {
            let _ = r.ctrl.step(now_us, Some(ev));
            stepped = true;
        }
        if !stepped && r.ctrl.step_due(now_us) {
            let silent = r.kernel.check(now_us, &mut r.stop);
            let _ = r.ctrl.step(now_us, silent);
            stepped = true;
        }
        if stepped {
            let gap = self.period_ns * 3 / 4;
            self.seen.dock_filter = match self.seen.dock_filter {
                None => Some((now_ns, dock, dock)),
                Some((t, _, _)) if now_ns - t < gap => self.seen.dock_filter,
                Some((_, seen, level)) => {
                    Some((now_ns, dock, if seen == dock { dock } else { level }))
                }
            };
        }
        r.kernel.configure(r.ctrl.kernel_config(), now_us);
        self.ready_pin = r.ctrl.handshake().ready;
        self.service();
    }

    /// The service's window: what idle published applied, the flash's turn.
    fn service(&mut self) {
        let r = &mut self.r;
        if old_board() {
            r.ctrl.set_maintenance_mode(self.maintenance_published);
        } else if !self.maintenance_published {
            r.ctrl.set_maintenance_mode(false);
        }
        r.ctrl
            .set_bus_busy(r.clock.now_ns() < self.line_busy_until_ns);
        r.ctrl.background();
    }

    /// A job in the service's window (`f` with the controller); the outputs written
    /// again if it changed a mode (the board pends its control task then).
    fn job(&mut self, f: impl FnOnce(&mut Rig)) {
        let modes = (self.r.ctrl.maintenance_mode(), self.r.ctrl.updating());
        f(&mut self.r);
        if !old_board() && modes != (self.r.ctrl.maintenance_mode(), self.r.ctrl.updating()) {
            self.ready_pin = self.r.ctrl.handshake().ready;
        }
    }

    /// The next sample.
    fn tick(&mut self) {
        let r = &mut self.r;
        let next =
            r.hx.next_conversion_ns()
                .min(r.clock.now_ns() + self.period_ns);
        r.clock.advance_to_ns(next);
        let now_us = r.clock.now_ns() / 1_000;
        let mut samples = std::mem::take(&mut self.queued);
        samples.extend(r.kernel.on_ready(now_us, &mut r.stop));
        self.control_run(samples);
        self.check("tick");
    }

    /// The console's new output.
    fn read_console(&mut self) -> String {
        self.r.console.flush_output(&mut self.r.term);
        let t = String::from_utf8_lossy(&self.r.term.take_output()).into_owned();
        self.out.push_str(&t);
        t
    }

    /// What a console reply says happened.
    fn console_said(&mut self, reply: &str) {
        for l in reply.lines() {
            if l.starts_with("ok: maintenance mode (") {
                self.seen.maintenance = true;
            } else if l.starts_with("ok: maintenance mode ended") {
                self.seen.maintenance = false;
            }
            let audited = l.starts_with("ok: fault cleared")
                || l.starts_with("ok: homing")
                || l.starts_with("ok: docking");
            if audited {
                self.seen.audits_expected += 1;
            }
            if audited || l.starts_with("ok: undocking") {
                self.seen.console_motion = 40;
            }
            if l.starts_with("ok: fault cleared") {
                self.seen.estop_unanswered = false;
            }
        }
    }

    fn console_finish(&mut self) {
        if !std::mem::take(&mut self.finish_due) {
            return;
        }
        let now_ms = self.now_ms();
        self.r.console.finish(now_ms);
        if !old_board() {
            self.maintenance_published = self.r.console.maintenance_active(now_ms);
        }
        if self.r.console.store_due() {
            self.job(|r| r.console.store(&mut r.ctrl, now_ms));
        }
        if old_board() {
            self.maintenance_published = self.r.console.maintenance_active(now_ms);
        }
        let said = self.read_console();
        self.console_said(&said);
    }

    fn apply(&mut self, op: &Op) {
        self.n += 1;
        match *op {
            Op::Tick => self.tick(),
            Op::Wait(n) => {
                for _ in 0..n {
                    self.tick();
                }
            }
            Op::LongJob(n) => {
                // At most 250 ms (the watchdog's 340 ms on the fastest LSI).
                let n = u64::from(n).min(250_000_000 / self.period_ns).max(1);
                for _ in 0..n {
                    let t = self.r.hx.next_conversion_ns();
                    if t == u64::MAX {
                        break; // a silent load cell: nothing to queue
                    }
                    self.r.clock.advance_to_ns(t);
                    let now_us = t / 1_000;
                    let ev = self.r.kernel.on_ready(now_us, &mut self.r.stop);
                    self.queued.extend(ev);
                }
                let samples = std::mem::take(&mut self.queued);
                self.control_run(samples);
                self.check("long job");
            }
            Op::InsideStep(k) => {
                self.r.estop_pulse_inside_next_step(u32::from(k));
                self.tick_with_edge_inside();
            }
            Op::Dock(on) => self.r.dock_line.set(!on),
            Op::EstopPulse => {
                self.r.estop_pulse(50);
                self.estop_edge();
            }
            Op::Estop(open) => {
                if self.r.estop_line.is_high() != open {
                    self.r.estop_input(open);
                    self.estop_edge();
                }
            }
            Op::Console(line) => {
                self.console_finish();
                let now_ms = self.now_ms();
                let text = line.text();
                if matches!(line, Line::ClearFault) {
                    self.seen.estop_unanswered = false; // a clear issued after the edge
                }
                self.job(|r| {
                    r.console.run_line(&mut r.ctrl, &text, now_ms);
                });
                self.finish_due = true;
                let said = self.read_console();
                self.console_said(&said);
            }
            Op::ConsoleFinish => self.console_finish(),
            Op::Modbus(coil) => {
                let req = coil.request();
                if req == Request::ClearFault {
                    self.seen.estop_unanswered = false;
                }
                let until = self.r.clock.now_ns() + 5_000_000;
                let mut accepted = false;
                self.job(|r| {
                    accepted = r.ctrl.command_from(Source::Plc, req).is_ok();
                    r.ctrl.set_bus_busy(true);
                });
                self.line_busy_until_ns = until;
                if accepted && req == Request::Dock {
                    self.seen.remote_dock = 40;
                }
            }
            Op::Sensor(c) => match c {
                Load::Disconnect => self.r.hx.set_fault(Hx711Fault::Disconnected),
                Load::Reconnect => self.r.hx.set_fault(Hx711Fault::None),
                Load::Spike => {
                    let mut s = self.r.script.borrow_mut();
                    s.spikes_at = vec![self.r.conversions.get() + 1];
                    s.spike_n = 400.0;
                }
                Load::Pull(on) => {
                    self.r.script.borrow_mut().pull_n_per_s = if on { 200.0 } else { 0.0 };
                }
            },
            Op::LockStuck(on) => self.r.lock.set_fault(if on {
                LockFault::Stuck
            } else {
                LockFault::None
            }),
            Op::FlashFail(on) => self.r.flash.with(|f| f.write_protect(on)),
            Op::Reset => {
                // What waits in RAM is lost: the records queued, the count of those
                // dropped (reported until now), the login.
                let lost =
                    self.r.ctrl.records_queued() as u64 + u64::from(self.r.ctrl.records_dropped());
                self.seen.audits_expected = self.seen.audits_expected.saturating_sub(lost);
                self.r.reset(ResetCause::Pin);
                self.r.console.set_interactive(false);
                let _ = self.read_console();
                self.queued.clear();
                self.finish_due = false;
                self.maintenance_published = false;
                self.seen.maintenance = false;
                self.seen.console_motion = 0;
                self.seen.remote_dock = 0;
                // After a reset nothing moves until a request: the edge's latch is
                // gone with the RAM, and a move needs a request (home, dock).
                self.seen.estop_unanswered = false;
                self.seen.dock_filter = None;
                // The outputs are low through the reset.
                self.ready_pin = false;
            }
        }
        self.check(&format!("{op:?}"));
    }

    /// An E-STOP edge now (between steps).
    fn estop_edge(&mut self) {
        self.seen.estop_unanswered = true;
        self.seen.travel_at_edge_um = self.r.axis.travel_um();
        self.seen.lock_at_edge = self.r.lock.fraction_locked();
    }

    /// A tick whose control step has an E-STOP pulse inside it (if the step looked at
    /// the latch often enough).
    fn tick_with_edge_inside(&mut self) {
        let r = &mut self.r;
        let next =
            r.hx.next_conversion_ns()
                .min(r.clock.now_ns() + self.period_ns);
        r.clock.advance_to_ns(next);
        let now_us = r.clock.now_ns() / 1_000;
        let mut samples = std::mem::take(&mut self.queued);
        samples.extend(r.kernel.on_ready(now_us, &mut r.stop));
        // The positions at the step's instant (nothing moves during it).
        let travel = r.axis.travel_um();
        let lock = r.lock.fraction_locked();
        self.control_run(samples);
        if !self.r.disarm_inside_step() {
            // It ran, inside the step.
            self.seen.estop_unanswered = true;
            self.seen.travel_at_edge_um = travel;
            self.seen.lock_at_edge = lock;
        }
        self.check("step with an E-STOP pulse inside");
    }

    /// The invariants (docs/board.md, "What holds between the steps"), now.
    fn check(&mut self, at: &str) {
        let state = self.r.ctrl.state();
        let axis_on = self.r.axis.enabled();
        let lock_on = self.r.lock.driven();
        let moving = axis_on || lock_on;
        let started = moving && !self.seen.moving;
        let ctx = || format!("after event {} ({at}): state {state:?}", self.n);

        // 1. No motion from an E-STOP edge until a clear issued after that edge.
        if self.seen.estop_unanswered {
            assert!(
                !moving,
                "{}: driven after an E-STOP edge with no clear issued since",
                ctx()
            );
            let travel = self.r.axis.travel_um() - self.seen.travel_at_edge_um;
            let lock = (self.r.lock.fraction_locked() - self.seen.lock_at_edge).abs();
            assert!(
                travel == 0.0 && lock == 0.0,
                "{}: moved after an E-STOP edge ({travel} µm, lock {lock})",
                ctx()
            );
        }

        // 2. No motion started from a remote source while maintenance is granted.
        if started && self.seen.maintenance {
            assert!(
                self.seen.console_motion > 0,
                "{}: a motion started while the console had been granted maintenance, \
                 and the console asked for none",
                ctx()
            );
        }

        // 4. Counters never backwards, and only for a cycle that reached the cone.
        let engage = self.r.ctrl.config().machine.engage_um as f64;
        if matches!(
            state,
            State::Inserting { .. } | State::Holding { .. } | State::Extracting { .. }
        ) || self.r.axis.pos_um() > engage + 20.0
        {
            self.seen.reached_cone = true;
        }
        let cycles = self.cycles();
        assert!(
            cycles.0 >= self.seen.cycles.0 && cycles.1 >= self.seen.cycles.1,
            "{}: counters went backwards {:?} -> {cycles:?}",
            ctx(),
            self.seen.cycles
        );
        if cycles.0 > self.seen.cycles.0 {
            assert!(
                self.seen.reached_cone && cycles.0 == self.seen.cycles.0 + 1,
                "{}: a cycle counted ({:?} -> {cycles:?}) that never reached the cone",
                ctx(),
                self.seen.cycles
            );
            self.seen.reached_cone = false;
        }
        self.seen.cycles = cycles;

        // 5. READY only when a dock would be accepted.
        if self.ready_pin && !skip("ready") {
            let r = self.r.ctrl.check_command(Source::Plc, Request::Dock);
            assert!(
                r.is_ok(),
                "{}: READY high, and a dock refused: {r:?}",
                ctx()
            );
        }

        // A docking the DOCK pin started starts while DOCK, through the two-reading
        // filter, says "be docked" (not on one reading of a glitch, not after a release).
        let was_idle = self.seen.state == Some(State::Idle);
        if was_idle
            && matches!(state, State::PreAlign { .. })
            && self.seen.console_motion == 0
            && self.seen.remote_dock == 0
        {
            assert!(
                self.seen.dock_filter.is_some_and(|(_, _, level)| level),
                "{}: a docking from the DOCK pin while its filtered level is released ({:?})",
                ctx(),
                self.seen.dock_filter
            );
        }

        // No step pulse reaches the driver while it is off (a stop's zero rate kept).
        assert_eq!(
            self.r.axis.pulses_while_off(),
            0,
            "{}: step pulses while the driver was off",
            ctx()
        );

        if started {
            self.seen.console_motion = 0;
            self.seen.remote_dock = 0;
        } else if at == "tick" || at == "long job" || at.starts_with("step") {
            self.seen.console_motion = self.seen.console_motion.saturating_sub(1);
            self.seen.remote_dock = self.seen.remote_dock.saturating_sub(1);
        }
        self.seen.moving = moving;
        self.seen.state = Some(state);
    }

    /// Invariant 3: every record accepted is written or counted as dropped (or still
    /// waits), at the end of a sequence.
    fn check_records(&mut self, base: u64) {
        let written = self.audits_in_flash() - base;
        let queued = self.r.ctrl.records_queued() as u64;
        let dropped = u64::from(self.r.ctrl.records_dropped());
        assert_eq!(
            written + queued + dropped,
            self.seen.audits_expected,
            "audit records: {written} written, {queued} queued, {dropped} dropped, \
             {} accepted",
            self.seen.audits_expected
        );
    }
}

/// The board under test and the audit records in flash before the sequence.
struct Sut {
    board: Board,
    audits_base: u64,
}

struct Checker;

impl StateMachineTest for Checker {
    type SystemUnderTest = Sut;
    type Reference = Events;

    fn init_test(rate: &u32) -> Sut {
        let mut board = Board::new(*rate);
        let audits_base = board.audits_in_flash();
        Sut { board, audits_base }
    }

    fn apply(mut sut: Sut, _: &u32, op: Op) -> Sut {
        sut.board.apply(&op);
        // The audit records the log shows now (a move may carry away all but the
        // newest later): once an event, not at every tick (a walk of the log).
        sut.board.audits_in_flash();
        sut
    }

    fn teardown(mut sut: Sut, _: u32) {
        let base = sut.audits_base;
        sut.board.check_records(base);
    }
}

/// `cases` sequences; from a fixed seed when `seed` is given (CI's batch: the same
/// sequences on every run, so that a red run is the change's, not the draw's; another
/// draw with `INTERLEAVINGS_SEED=N`), else a random one (the large batch).
fn config(cases: u32, seed: Option<u64>) -> Config {
    let cases = std::env::var("INTERLEAVINGS_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(cases);
    let seed = std::env::var("INTERLEAVINGS_SEED")
        .ok()
        .and_then(|v| v.parse().ok())
        .or(seed);
    Config {
        cases,
        failure_persistence: None,
        max_shrink_iters: 100_000,
        rng_seed: seed.map_or(
            proptest::test_runner::RngSeed::Random,
            proptest::test_runner::RngSeed::Fixed,
        ),
        ..Config::default()
    }
}

prop_state_machine! {
    #![proptest_config(config(2_000, Some(32)))]
    /// CI's batch: 2 000 sequences of up to 40 events.
    #[test]
    fn every_interleaving_keeps_the_invariants(sequential 1..40 => Checker);
}

prop_state_machine! {
    #![proptest_config(config(1_000_000, None))]
    /// The large batch: 10⁶ sequences of up to 60 events (ignored: about an hour).
    #[test]
    #[ignore]
    fn a_million_interleavings_keep_the_invariants(sequential 1..60 => Checker);
}

/// Run `ops` from a fresh board at `rate` SPS and check the invariants at the end: a
/// sequence a batch found, kept as a regression.
fn replay(rate: u32, ops: impl IntoIterator<Item = Op>) {
    let mut sut = Checker::init_test(&rate);
    for op in ops {
        sut = Checker::apply(sut, &rate, op);
    }
    Checker::teardown(sut, rate);
}

/// The ignored batch's first finding (after 433 353 sequences), a bug of the checker's
/// own: a reset loses the count of dropped records with the RAM, and the checker
/// forgot only the queued ones. Kept as a regression of the checker.
#[test]
fn records_dropped_before_a_reset_are_accounted_for() {
    replay(
        80,
        [
            Op::FlashFail(true),
            Op::EstopPulse,
            Op::Tick,
            Op::Console(Line::Login),
            Op::Console(Line::ClearFault),
            Op::Console(Line::ClearFault),
            Op::Console(Line::ClearFault),
            Op::Console(Line::ClearFault),
            Op::Console(Line::ClearFault),
            Op::Reset,
        ],
    );
}

/// The ignored batch's finding on 3492742 (after 363 656 sequences), a bug of the
/// checker's: a pull at rest faults again and again, the log moves to its other sector
/// and carries only the newest audit record, and the checker counted the records
/// present, not those written. Kept as a regression of the checker.
#[test]
fn a_clear_after_a_pull_at_rest_keeps_its_audit_record() {
    let ops = [
        Op::Sensor(Load::Pull(true)),
        Op::Wait(104),
        Op::Console(Line::Login),
        Op::Wait(238),
        Op::Console(Line::ClearFault),
    ];
    let waits = [
        350, 104, 353, 216, 377, 334, 179, 324, 316, 285, 163, 371, 285,
    ];
    replay(80, ops.into_iter().chain(waits.map(Op::Wait)));
}

/// CI's batch on 829567a: two clears typed back to back after an E-STOP pulse, a
/// Modbus dock between; both audit records written, with the same payload (the same
/// millisecond): the checker's own count, kept as its regression.
#[test]
fn two_clears_back_to_back_each_keep_their_audit_record() {
    replay(
        80,
        [
            Op::EstopPulse,
            Op::Tick,
            Op::Console(Line::Login),
            Op::Modbus(Coil::Dock),
            Op::Console(Line::ClearFault),
            Op::Console(Line::ClearFault),
            Op::Wait(3),
        ],
    );
}
