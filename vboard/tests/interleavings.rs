//! The random-interleaving campaign on the virtual board (issue 32): the release image,
//! a fresh board per run, a script of random events — E-STOP pulses and presses, DOCK,
//! the PLC's Modbus commands and polls, console lines (a login, clears, stops, dockings)
//! — each at a random microsecond, or at the instant the image reaches a chosen
//! instruction inside its control step or its service (the step's entry, its gate
//! between the driver's enable and its step rate, a request's acceptance, a login's
//! grant, the queued records' write), where priorities and the owner's window decide
//! what happens. After each run the invariants of docs/board.md ("What holds between
//! the steps") are judged on the pins, the console, the Modbus line and the flash:
//!
//! 1. no motor driven after an E-STOP edge (20 µs for the interrupt to act) until a
//!    clear issued after that edge;
//! 2. no motion started while the console had been granted maintenance, but by the
//!    console's own request;
//! 3. every audit record the console accepted is written, queued or counted as dropped;
//! 4. a completed cycle only for a cycle that reached the cone (its contact phase 1),
//!    counted in order;
//! 5. READY low while the console has maintenance, and never with FAULT;
//! 6. no STEP pulse with the driver off.
//!
//! A failing run is shrunk (events left out one by one while it still fails) and printed
//! with its seed and script. CI runs a sample (`a_sample_of_random_interleavings_keeps_the_invariants`,
//! 12 runs); the campaign is ignored: `cd vboard && cargo test --release --test
//! interleavings -- --ignored` (1 000 runs; `VBOARD_CAMPAIGN_RUNS` sets another count,
//! `VBOARD_CAMPAIGN_FIRST` the first seed; `VBOARD_CAMPAIGN_SURVEY` runs them all and
//! lists what each broke, unshrunk). `VBOARD_FIRMWARE=ELF` runs another image.

use std::cell::RefCell;
use std::rc::Rc;

use hil_sim::rng::Rng;
use vboard::scene::{rtu, Options, Session, PS_PER_MS};
use vboard::time::PS_PER_S;
use vboard::world::Signal;

const PS_PER_US: u64 = 1_000_000;

/// Instructions of the image an event can be placed at (a mangled name's part), each
/// inside the control step or the service.
const PLACES: [(&str, &str); 6] = [
    (
        "TIM2",
        "the control task's entry (before it reads the PLC's pins)",
    ),
    (
        "10controller19Controller$LT$B$GT$4step",
        "the control step's entry (after the pins are read)",
    ),
    (
        "4lock29LockActuator$LT$IN1$C$IN2$GT$5apply",
        "the step's lock outputs (after its gate, before its step rate)",
    ),
    (
        "12command_from",
        "a request's acceptance (a job: console or Modbus)",
    ),
    (
        "7Console5store",
        "the console's fourth phase (a login's grant)",
    ),
    (
        "20write_queued_records",
        "the queued records' write (the flash's turn)",
    ),
];

/// What an event does.
#[derive(Clone, Copy, Debug, PartialEq)]
enum What {
    /// The E-STOP input opens for this long, then closes.
    EstopPulse { open_us: u64 },
    /// The PLC asserts or releases DOCK.
    Dock(bool),
    /// A coil written on the Modbus line (0 dock, 1 undock, 2 clear, 3 stop).
    Coil(u8),
    /// Ten input registers read (a polling PLC).
    Poll,
    /// A console line.
    Line(&'static str),
}

/// When it happens.
#[derive(Clone, Copy, Debug, PartialEq)]
enum When {
    /// At this time after the script's start, µs.
    At(u64),
    /// The first time the image reaches `PLACES[i]` after this time, µs.
    AtPlace(usize, u64),
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Event {
    when: When,
    what: What,
}

impl Event {
    fn t_us(&self) -> u64 {
        match self.when {
            When::At(t) | When::AtPlace(_, t) => t,
        }
    }
}

/// A run's script: the rate, how the PLC answers, and the events in time order.
#[derive(Clone, Debug)]
struct Script {
    seed: u64,
    rate_sps: u32,
    /// The PLC docks when READY rises, undocks once mated this long, and clears a fault
    /// (coil 2) this long after FAULT rose with the E-STOP closed, ms (`None`: it does
    /// nothing by itself, only the events).
    plc_ms: Option<u64>,
    events: Vec<Event>,
}

/// How long a script runs, µs.
const SCRIPT_US: u64 = 5_000_000;

/// The script of seed `seed`: 6 to 20 events over 5 s; half the runs begin with the PLC
/// asserting DOCK (a docking under way when the rest comes).
fn script(seed: u64) -> Script {
    let mut rng = Rng::new(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0x32);
    let mut pick = |n: u64| rng.next_u64() % n;
    let rate_sps = if pick(5) == 0 { 10 } else { 80 };
    let plc_ms = (pick(4) != 0).then(|| 20 + pick(400));
    let n = 6 + pick(15) as usize;
    let mut events = Vec::with_capacity(n + 1);
    if pick(2) == 0 {
        events.push(Event {
            when: When::At(0),
            what: What::Dock(true),
        });
    }
    for _ in 0..n {
        let t = pick(SCRIPT_US);
        let what = match pick(20) {
            0..=2 => What::EstopPulse {
                open_us: match pick(3) {
                    0 => 20 + pick(200),
                    1 => 1_000 + pick(10_000),
                    _ => 20_000 + pick(200_000),
                },
            },
            3..=6 => What::Dock(pick(2) == 0),
            7..=11 => What::Coil(match pick(6) {
                0 | 1 => 0,
                2 => 1,
                3 | 4 => 2,
                _ => 3,
            }),
            12 => What::Poll,
            _ => What::Line(match pick(9) {
                0..=2 => "maint 2468",
                3 | 4 => "clear-fault",
                5 => "maint exit",
                6 => "stop",
                7 => "dock",
                _ => "status",
            }),
        };
        // E-STOP pulses half the time, coils a quarter, at a place inside a task.
        let when = match what {
            What::EstopPulse { .. } if pick(2) == 0 => {
                When::AtPlace(pick(PLACES.len() as u64) as usize, t)
            }
            What::Coil(_) if pick(4) == 0 => When::AtPlace(pick(PLACES.len() as u64) as usize, t),
            _ => When::At(t),
        };
        events.push(Event { when, what });
    }
    events.sort_by_key(Event::t_us);
    Script {
        seed,
        rate_sps,
        plc_ms,
        events,
    }
}

/// The PLC answering the handshake (`Script::plc_ms`).
#[derive(Debug, Default)]
struct Plc {
    /// When FAULT was first seen high with the E-STOP closed, ps.
    fault_since: Option<u64>,
    /// When MATED was first seen high, ps.
    mated_since: Option<u64>,
    /// When DOCK last changed, ps.
    dock_changed: u64,
}

impl Plc {
    fn tick(&mut self, s: &mut Session, ms: u64, run: &mut Run) {
        let now = s.now();
        let out = s.plc_out();
        let dock = !s.machine().dock_request.is_high();
        let delay = ms * PS_PER_MS;
        if out.fault && !s.machine().estop.is_high() {
            let t = *self.fault_since.get_or_insert(now);
            if now >= t + delay {
                send_coil(s, 2, run);
                self.fault_since = None;
            }
        } else {
            self.fault_since = None;
        }
        if out.mated {
            let t = *self.mated_since.get_or_insert(now);
            if dock && now >= t + delay {
                s.set_dock(false);
                self.dock_changed = now;
            }
        } else {
            self.mated_since = None;
        }
        if out.ready && !dock && now >= self.dock_changed + 200 * PS_PER_MS {
            s.set_dock(true);
            self.dock_changed = now;
        }
    }
}

/// An E-STOP edge placed at an instruction: armed by the script, made by the hook.
#[derive(Default)]
struct Armed {
    /// The place and the earliest time (ps).
    at: Option<(usize, u64)>,
    /// When the hook made the opening edge (ps).
    fired: Option<u64>,
}

/// What a run saw, for the invariants.
#[derive(Debug, Default)]
struct Run {
    /// Every E-STOP edge made, ps.
    estop_edges: Vec<u64>,
    /// When a clear was issued (a coil 2 or a `clear-fault` line sent), ps.
    clears: Vec<u64>,
    /// When a console line that may start a motion was sent (`clear-fault`, `dock`), ps.
    console_motion: Vec<u64>,
    /// When `maint exit` was sent, ps.
    logouts: Vec<u64>,
    /// The console's output from this byte on is the script's.
    console_from: usize,
    /// Audit records in flash before the script.
    audits_before: u64,
}

fn options(rate_sps: u32) -> Options {
    let mut o = Options::new();
    o.rate_sps = rate_sps;
    if let Ok(p) = std::env::var("VBOARD_FIRMWARE") {
        o.firmware = p;
    }
    o
}

fn audits_in_flash(s: &Session) -> u64 {
    let flash = s.board.soc().world.flash.clone();
    let Ok((mut log, _)) = docking_logic::odometer::open_log(flash) else {
        return 0;
    };
    log.for_each_newest_first(docking_logic::odometer::kind::AUDIT, usize::MAX, |_| {})
        .unwrap_or(0) as u64
}

/// Run `sc` on a fresh board; the invariants broken (empty: none).
fn run(sc: &Script) -> Result<Vec<String>, String> {
    let mut s = Session::new(options(sc.rate_sps))?;
    // The hooks before the image runs (a block translated earlier would not call them).
    let armed = Rc::new(RefCell::new(Armed::default()));
    for (i, (name, _)) in PLACES.iter().enumerate() {
        let addr = if *name == "TIM2" {
            s.board.image.symbol("TIM2")
        } else {
            s.board.image.symbol_containing(name)
        };
        let Some((addr, _)) = addr else {
            return Err(format!("no symbol {name} in the image"));
        };
        let a = armed.clone();
        s.board.at_pc(addr & !1, move |soc| {
            let mut a = a.borrow_mut();
            match a.at {
                Some((p, t)) if p == i && soc.now() >= t => {
                    a.at = None;
                    a.fired = Some(soc.now());
                    soc.world.machine.estop.set(true);
                    soc.sample_exti();
                    soc.update_lines();
                    true
                }
                _ => false,
            }
        });
    }
    let deadline = s.now() + 30 * PS_PER_S;
    let up = s
        .run_until(deadline, |x| {
            let out = &x.board.soc().console_out;
            // Up, at rest, READY, and the console's greeting out (its prompt last).
            x.seen.boots >= 1
                && x.at_rest()
                && x.plc_out().ready
                && out.len() >= 2
                && out[out.len() - 2..].iter().map(|&(_, b)| b).eq(*b"> ")
        })
        .map_err(|e| e.to_string())?;
    if !up {
        return Err("the board did not come up".into());
    }
    let r = s
        .console("pin set 2468", 5 * PS_PER_S)
        .map_err(|e| e.to_string())?;
    if !r.starts_with("ok") {
        return Err(format!("pin set: {r}"));
    }
    s.run_for(100 * PS_PER_MS).map_err(|e| e.to_string())?;
    let mut run = Run {
        console_from: s.board.soc().console_out.len(),
        audits_before: audits_in_flash(&s),
        ..Run::default()
    };
    let t0 = s.now();
    let mut plc = Plc {
        dock_changed: t0,
        ..Plc::default()
    };
    let mut plc_at = t0;
    // Pulses under way: when each closes, ps.
    let mut closing: Vec<u64> = Vec::new();
    // Placed pulses armed and not fired yet: (open for, µs).
    let mut placed: Vec<u64> = Vec::new();
    let mut events = sc.events.clone();
    events.reverse();
    let end = t0 + SCRIPT_US * PS_PER_US + 300 * PS_PER_MS;
    let halt = |e: vboard::cpu::Halt| e.to_string();
    while s.now() < end {
        // A placed pulse fired: its closing edge.
        if let Some(f) = armed.borrow_mut().fired.take() {
            run.estop_edges.push(f);
            if let Some(open_us) = placed.pop() {
                closing.push(f + open_us * PS_PER_US);
            }
        }
        let now = s.now();
        if let Some(ms) = sc.plc_ms {
            if now >= plc_at {
                plc.tick(&mut s, ms, &mut run);
                plc_at = now + PS_PER_MS;
            }
        }
        // Closing edges due.
        if let Some(i) = closing.iter().position(|&c| c <= now) {
            closing.remove(i);
            if closing.is_empty() && placed.is_empty() {
                s.set_estop(false);
                run.estop_edges.push(s.now());
            }
            continue;
        }
        if let Some(&e) = events.last() {
            if t0 + e.t_us() * PS_PER_US <= now {
                events.pop();
                apply(&mut s, &e, &armed, &mut run, &mut closing, &mut placed);
                continue;
            }
        }
        // To the next thing due, in steps of at most 1 ms (a placed event: 20 µs).
        let next_event = events
            .last()
            .map_or(end, |e| t0 + e.t_us() * PS_PER_US)
            .min(closing.iter().copied().min().unwrap_or(end))
            .min(end);
        let step = if placed.is_empty() {
            PS_PER_MS
        } else {
            20 * PS_PER_US
        };
        let to = next_event.min(now + step).max(now + PS_PER_US);
        s.run_exact(to - now).map_err(halt)?;
    }
    s.set_estop(false);
    s.run_for(300 * PS_PER_MS).map_err(halt)?;
    let broken = judge(&mut s, &run);
    if !broken.is_empty() && std::env::var_os("VBOARD_CAMPAIGN_TRACE").is_some() {
        for l in &s.board.log {
            eprintln!("  log {:.6} {}", l.t_ps as f64 * 1e-12, l.msg);
        }
        for e in &s.board.soc().edges {
            if matches!(
                e.signal,
                Signal::EnN | Signal::LockIn1 | Signal::LockIn2 | Signal::Estop | Signal::Dock
            ) {
                eprintln!(
                    "  pin {:.6} {:?} {}",
                    e.t_ps as f64 * 1e-12,
                    e.signal,
                    e.high
                );
            }
        }
        eprintln!("  clears {:?}", run.clears);
    }
    if std::env::var_os("VBOARD_CAMPAIGN_VERBOSE").is_some() {
        let starts = motor_timeline(&s).iter().filter(|&&(_, on)| on).count();
        let faults: Vec<&str> = s.seen.faults.iter().map(|f| f.kind).collect();
        eprintln!(
            "seed {} ({} SPS): {} events, {} E-STOP edges, {} clears, {} motion starts,              faults {faults:?}, {} cycles; {} broken",
            sc.seed,
            sc.rate_sps,
            sc.events.len(),
            run.estop_edges.len(),
            run.clears.len(),
            starts,
            s.seen.cycles_completed,
            broken.len()
        );
    }
    Ok(broken)
}

fn apply(
    s: &mut Session,
    e: &Event,
    armed: &Rc<RefCell<Armed>>,
    run: &mut Run,
    closing: &mut Vec<u64>,
    placed: &mut Vec<u64>,
) {
    let now = s.now();
    match (e.what, e.when) {
        (What::EstopPulse { open_us }, When::AtPlace(p, _)) => {
            if armed.borrow().at.is_none() && placed.is_empty() {
                armed.borrow_mut().at = Some((p, now));
                placed.push(open_us);
            }
        }
        (What::EstopPulse { open_us }, When::At(_)) => {
            if !s.machine().estop.is_high() {
                s.set_estop(true);
                run.estop_edges.push(s.now());
            }
            closing.push(now + open_us * PS_PER_US);
        }
        (What::Dock(on), _) => s.set_dock(on),
        (What::Coil(c), When::AtPlace(p, _)) => {
            // The coil's frame now; an E-STOP pulse of 50 µs at the place from now on
            // (the acceptance, a step…): between the request and its step.
            send_coil(s, c, run);
            if armed.borrow().at.is_none() && placed.is_empty() {
                armed.borrow_mut().at = Some((p, now));
                placed.push(50);
            }
        }
        (What::Coil(c), When::At(_)) => send_coil(s, c, run),
        (What::Poll, _) => {
            let _ = s.board.soc_mut().modbus_send(&rtu(1, &[0x04, 0, 0, 0, 10]));
        }
        (What::Line(l), _) => {
            let mut b = l.as_bytes().to_vec();
            b.extend_from_slice(b"\r\n");
            let _ = s.board.soc_mut().console_send(&b);
            match l {
                "clear-fault" => {
                    run.clears.push(now);
                    run.console_motion.push(now);
                }
                "dock" => run.console_motion.push(now),
                "maint exit" => run.logouts.push(now),
                _ => {}
            }
        }
    }
}

fn send_coil(s: &mut Session, c: u8, run: &mut Run) {
    if s.board.soc().usart3.far_pending() > 0 {
        return; // the master waits for the line
    }
    let now = s.now();
    let _ = s
        .board
        .soc_mut()
        .modbus_send(&rtu(1, &[0x05, 0, c, 0xFF, 0]));
    if c == 2 {
        run.clears.push(now);
    }
}

/// The motors' state from the pins' edges: (time ps, driven after it), in order.
fn motor_timeline(s: &Session) -> Vec<(u64, bool)> {
    let (mut en, mut in1, mut in2) = (false, false, false);
    let mut out = Vec::new();
    let mut was = false;
    for e in &s.board.soc().edges {
        match e.signal {
            Signal::EnN => en = !e.high,
            Signal::LockIn1 => in1 = e.high,
            Signal::LockIn2 => in2 = e.high,
            _ => continue,
        }
        let on = en || in1 || in2;
        if on != was {
            out.push((e.t_ps, on));
            was = on;
        }
    }
    out
}

/// A level's timeline from the pins' edges.
fn level_timeline(s: &Session, sig: Signal) -> Vec<(u64, bool)> {
    s.board
        .soc()
        .edges
        .iter()
        .filter(|e| e.signal == sig)
        .map(|e| (e.t_ps, e.high))
        .collect()
}

fn level_at(tl: &[(u64, bool)], t: u64) -> bool {
    tl.iter()
        .take_while(|&&(te, _)| te <= t)
        .last()
        .is_some_and(|&(_, h)| h)
}

/// The invariants over a finished run.
fn judge(s: &mut Session, run: &Run) -> Vec<String> {
    let mut broken = Vec::new();
    let motors = motor_timeline(s);
    let reaction = 20 * PS_PER_US;
    // 1. E-STOP.
    for &e in &run.estop_edges {
        let clear = run.clears.iter().copied().filter(|&c| c > e).min();
        let until = clear.unwrap_or(u64::MAX);
        if level_at(&motors, e + reaction) {
            broken.push(format!(
                "a motor still driven 20 µs after the E-STOP edge at {:.6} s",
                e as f64 * 1e-12
            ));
        }
        if let Some(&(t, _)) = motors
            .iter()
            .find(|&&(t, on)| on && t > e + reaction && t < until)
        {
            broken.push(format!(
                "a motor driven at {:.6} s after the E-STOP edge at {:.6} s, no clear issued since",
                t as f64 * 1e-12,
                e as f64 * 1e-12
            ));
        }
    }
    // 2. and 5. Maintenance.
    let out: Vec<(u64, u8)> = s.board.soc().console_out[run.console_from..].to_vec();
    let text: Vec<u8> = out.iter().map(|&(_, b)| b).collect();
    let text = String::from_utf8_lossy(&text).into_owned();
    let mut grants = Vec::new();
    let needle = b"ok: maintenance mode (";
    let bytes: Vec<u8> = out.iter().map(|&(_, b)| b).collect();
    for i in 0..bytes.len().saturating_sub(needle.len()) {
        if &bytes[i..i + needle.len()] == needle {
            // The reply said so once its line was out.
            if let Some(j) = bytes[i..].iter().position(|&b| b == b'\n') {
                grants.push(out[i + j].0);
            }
        }
    }
    let ready = level_timeline(s, Signal::Ready);
    let fault = level_timeline(s, Signal::Fault);
    for &g in &grants {
        let end = run
            .logouts
            .iter()
            .copied()
            .filter(|&x| x > g)
            .min()
            .unwrap_or(u64::MAX);
        // A console line that moves (clear-fault, dock) runs only in maintenance: one
        // sent before a start and after the start before it (typed ahead of the login's
        // reply, say) is the console's own request.
        let starts: Vec<u64> = motors
            .iter()
            .filter(|&&(_, on)| on)
            .map(|&(t, _)| t)
            .collect();
        if let Some(&t) = starts.iter().enumerate().find_map(|(i, t)| {
            let before = if i == 0 { 0 } else { starts[i - 1] };
            (*t > g && *t < end && !run.console_motion.iter().any(|&c| c > before && c < *t))
                .then_some(t)
        }) {
            broken.push(format!(
                "a motion started at {:.6} s while the console had been granted maintenance \
                 at {:.6} s, not by the console",
                t as f64 * 1e-12,
                g as f64 * 1e-12
            ));
        }
        if level_at(&ready, g) || ready.iter().any(|&(t, h)| h && t > g && t < end) {
            broken.push(format!(
                "READY high after the console said maintenance at {:.6} s",
                g as f64 * 1e-12
            ));
        }
    }
    for &(t, h) in ready.iter().chain(fault.iter()) {
        if h && level_at(&ready, t) && level_at(&fault, t) {
            broken.push(format!(
                "READY and FAULT both high at {:.6} s",
                t as f64 * 1e-12
            ));
            break;
        }
    }
    // 6. No STEP pulse with the driver off.
    let st = s.machine().axis.step_timing();
    if st.pulses_disabled > 0 {
        broken.push(format!(
            "{} STEP pulses with the driver off",
            st.pulses_disabled
        ));
    }
    // 4. Cycles: each completed one reached the cone, in order.
    let mut started: Option<u32> = None;
    let mut in_cone = false;
    let mut last_completed = 0u32;
    for l in &s.board.log {
        let w: Vec<&str> = l.msg.split_whitespace().collect();
        match w.as_slice() {
            ["cycle", n, "started"] => {
                started = n.parse().ok();
                in_cone = false;
            }
            ["contact", "phase", _] => in_cone = true,
            ["cycle", n, "completed:", ..] => {
                let n: u32 = n.parse().unwrap_or(0);
                if !in_cone {
                    broken.push(format!("cycle {n} counted, its rod never in the cone"));
                }
                if n != last_completed + 1 && last_completed != 0 {
                    broken.push(format!("cycle {n} counted after {last_completed}"));
                }
                if started != Some(n) {
                    broken.push(format!("cycle {n} counted, {started:?} started"));
                }
                last_completed = n;
                in_cone = false;
            }
            _ => {}
        }
    }
    // 3. Records: the console's `ok` to an audited command (clear-fault, dock) is a
    // record written, queued or counted as dropped.
    let accepted = text.matches("ok: fault cleared").count() + text.matches("ok: docking").count();
    let f = s.console_json("faults --json").unwrap_or_default();
    let queued: u64 = vboard::scene::json_field(&f, "records_queued")
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    let dropped: u64 = vboard::scene::json_field(&f, "records_dropped")
        .and_then(|v| v.parse().ok())
        .unwrap_or(0);
    let written = audits_in_flash(s) - run.audits_before;
    if written + queued + dropped != accepted as u64 {
        broken.push(format!(
            "audit records: {accepted} accepted, {written} written, {queued} queued, {dropped} dropped"
        ));
    }
    broken
}

/// Run `sc`; if it breaks an invariant, shrink it (events left out one at a time while
/// it still breaks one) and panic with the smallest script.
fn check(sc: &Script) {
    let broken = match run(sc) {
        Ok(b) => b,
        Err(e) => panic!("seed {}: the board could not run: {e}", sc.seed),
    };
    if broken.is_empty() {
        return;
    }
    let mut small = sc.clone();
    let mut why = broken;
    loop {
        let mut shrunk = false;
        for i in 0..small.events.len() {
            let mut t = small.clone();
            t.events.remove(i);
            if let Ok(b) = run(&t) {
                if !b.is_empty() {
                    small = t;
                    why = b;
                    shrunk = true;
                    break;
                }
            }
        }
        if !shrunk {
            break;
        }
    }
    let places: Vec<String> = PLACES
        .iter()
        .enumerate()
        .map(|(i, (_, what))| format!("  place {i}: {what}"))
        .collect();
    panic!(
        "seed {} ({} SPS) breaks: {why:#?}\nsmallest script ({} of {} events): {:#?}\n{}",
        sc.seed,
        sc.rate_sps,
        small.events.len(),
        sc.events.len(),
        small.events,
        places.join("\n")
    );
}

fn campaign(first: u64, runs: u64) {
    let first = std::env::var("VBOARD_CAMPAIGN_FIRST")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(first);
    let runs = std::env::var("VBOARD_CAMPAIGN_RUNS")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(runs);
    let t = std::time::Instant::now();
    // `VBOARD_CAMPAIGN_SURVEY`: every run, each broken invariant listed, no shrinking
    // (how the campaign was run on 7c11783's image).
    let survey = std::env::var_os("VBOARD_CAMPAIGN_SURVEY").is_some();
    let mut failed = 0;
    for seed in first..first + runs {
        let sc = script(seed);
        if survey {
            match run(&sc) {
                Ok(b) if b.is_empty() => {}
                Ok(b) => {
                    failed += 1;
                    eprintln!("SURVEY seed {seed} ({} SPS): {b:?}", sc.rate_sps);
                }
                Err(e) => eprintln!("SURVEY seed {seed}: could not run: {e}"),
            }
        } else {
            check(&sc);
        }
    }
    assert_eq!(failed, 0, "{failed} of {runs} runs broke an invariant");
    eprintln!(
        "{runs} runs from seed {first}: every invariant held ({:.0} s)",
        t.elapsed().as_secs_f64()
    );
}

/// CI's sample: 12 runs (seeds 1–12).
#[test]
fn a_sample_of_random_interleavings_keeps_the_invariants() {
    campaign(1, 12);
}

/// The campaign: 1 000 runs (seeds 1 000 on).
#[test]
#[ignore]
fn a_thousand_random_interleavings_keep_the_invariants() {
    campaign(1_000, 1_000);
}
