//! The control loop: one sample flows from the load cell through the sensor monitor, the
//! overload guard, the phase tracker and the sequencer to the motors in one step.
//!
//! [`Controller::poll`] is called from the main loop as often as it likes. It runs a
//! control step when the load cell has a new sample, or when a sample period has passed
//! without one (so that deadlines and the disconnect timeout still run). In a step:
//!
//! 1. the propulsion's emitted pulses are counted (position), the switches read;
//! 2. the sample is converted to force (calibration, tare) and judged: sensor health,
//!    then the overload guard at the current depth. **On a trip the propulsion is
//!    disabled right there**, before anything else runs;
//! 3. the contact phase is derived from the depth and cross-checked with the force;
//! 4. the pure sequencer decides; its commands are applied to the drivers;
//! 5. the watchdog is fed if the loop is keeping its period.
//!
//! The board and the simulator provide the hardware through [`Bsp`].

use embedded_hal::digital::{InputPin, OutputPin};
use heapless::Deque;

use crate::config::MachineConfig;
use crate::guard::{GuardConfig, OverloadGuard, SensorFault, SensorMonitor, Verdict};
use crate::hal::{LoadCellAdc, StepPulses, Watchdog};
use crate::hx711::{Calibration, CODE_MAX, CODE_MIN};
use crate::lock::{LockActuator, LockCmd};
use crate::profile::{ContactPhase, BOUNDARY_UM};
use crate::propulsion::Propulsion;
use crate::sequencer::{AxisCmd, FaultKind, Inputs, Request, SeqEvent, Sequencer, State, Switches};

/// The hardware a controller runs on (board support package).
pub trait Bsp {
    /// Propulsion EN, active low.
    type EnN: OutputPin;
    /// Propulsion DIR, high = toward the male panel.
    type Dir: OutputPin;
    /// Step-pulse generator.
    type Pulses: StepPulses;
    /// Lock H-bridge input toward locked.
    type LockIn1: OutputPin;
    /// Lock H-bridge input toward released.
    type LockIn2: OutputPin;
    /// Home switch, active low.
    type Home: InputPin;
    /// End (overtravel) switch, active low.
    type End: InputPin;
    /// Lock-locked switch, active low.
    type Locked: InputPin;
    /// Lock-released switch, active low.
    type Released: InputPin;
    /// Load-cell ADC.
    type Adc: LoadCellAdc;
    /// Independent watchdog.
    type Wdg: Watchdog;
}

/// The hardware parts, handed over at start.
pub struct Parts<B: Bsp> {
    /// Propulsion EN (active low).
    pub en_n: B::EnN,
    /// Propulsion DIR.
    pub dir: B::Dir,
    /// Step pulses.
    pub pulses: B::Pulses,
    /// Lock IN1.
    pub lock_in1: B::LockIn1,
    /// Lock IN2.
    pub lock_in2: B::LockIn2,
    /// Home switch.
    pub home: B::Home,
    /// End switch.
    pub end: B::End,
    /// Lock-locked switch.
    pub locked: B::Locked,
    /// Lock-released switch.
    pub released: B::Released,
    /// Load cell.
    pub adc: B::Adc,
    /// Watchdog.
    pub wdg: B::Wdg,
}

/// Controller configuration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ControllerConfig {
    /// Machine geometry and speeds.
    pub machine: MachineConfig,
    /// Overload limits.
    pub guard: GuardConfig,
    /// Load-cell sample rate, samples/s.
    pub sample_rate_sps: u32,
    /// Load-cell calibration (the offset is re-tared before every cycle).
    pub calibration: Calibration,
    /// Largest tare change from the calibrated offset that is plausible, mN equivalent.
    pub tare_tolerance_mn: i32,
}

impl ControllerConfig {
    /// Defaults at `sample_rate_sps` with the given calibration.
    pub const fn new(sample_rate_sps: u32, calibration: Calibration) -> Self {
        Self {
            machine: MachineConfig::DEFAULT,
            guard: GuardConfig::DEFAULT,
            sample_rate_sps,
            calibration,
            tare_tolerance_mn: 20_000,
        }
    }
}

/// A latched fault as recorded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub struct FaultRecord {
    /// What.
    pub kind: FaultKind,
    /// The docking cycle it happened in (1-based; 0 = before the first).
    pub cycle: u32,
    /// Contact phase at the time, if in the cone.
    pub phase: Option<ContactPhase>,
    /// Time, ms since boot.
    pub t_ms: u64,
    /// Highest force from the fault to its clear, mN.
    pub peak_force_mn: i32,
}

/// Something that happened, for logs and the console.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum Event {
    /// Sequencer event.
    Seq(SeqEvent),
    /// The rod entered a contact phase.
    Phase(ContactPhase),
    /// Force above the warning level (raised once, cleared with hysteresis).
    ForceWarning(i32),
    /// The force contradicts the phase the position says (3→4 cross-check).
    PhaseMismatch(ContactPhase),
}

/// An event with its time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub struct Timed {
    /// ms since boot.
    pub t_ms: u64,
    /// The event.
    pub event: Event,
}

/// What one `poll` did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct PollResult {
    /// A control step ran.
    pub stepped: bool,
    /// A sample was processed.
    pub sampled: bool,
    /// The overload guard tripped in this step.
    pub tripped: bool,
}

/// A snapshot for the console and logs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Status {
    /// Sequencer state.
    pub state: State,
    /// Contact phase, if in the cone.
    pub phase: Option<ContactPhase>,
    /// Last measured force, mN.
    pub force_mn: i32,
    /// Limit in force at the current depth, mN.
    pub limit_mn: i32,
    /// Counted axis position, µm.
    pub pos_um: i32,
    /// Cycles completed since boot.
    pub cycles_completed: u32,
    /// Latched fault, if any.
    pub fault: Option<FaultKind>,
    /// Force warning active.
    pub warning: bool,
    /// Highest force since boot, mN.
    pub peak_force_mn: i32,
}

/// Zero-load samples averaged for the tare.
const TARE_SAMPLES: usize = 16;
/// Fewest tare samples before a cycle may start.
const TARE_MIN_SAMPLES: usize = 8;
/// Force halfway across the 3→4 jump (107.09 N → 206.34 N), mN.
const JUMP_MID_MN: i32 = 156_700;
/// Events kept for readers.
const EVENT_QUEUE: usize = 32;
/// Fault records kept.
const FAULTS_KEPT: usize = 16;

/// The docking controller.
pub struct Controller<B: Bsp> {
    cfg: ControllerConfig,
    prop: Propulsion<B::EnN, B::Dir, B::Pulses>,
    lock: LockActuator<B::LockIn1, B::LockIn2>,
    home: B::Home,
    end: B::End,
    locked: B::Locked,
    released: B::Released,
    adc: B::Adc,
    wdg: B::Wdg,
    seq: Sequencer,
    guard: OverloadGuard,
    sensor: SensorMonitor,
    cal: Calibration,
    tare: Deque<i32, TARE_SAMPLES>,
    phase: Option<ContactPhase>,
    mismatch_reported: bool,
    mismatch_run: u8,
    force_mn: i32,
    limit_mn: i32,
    warning: bool,
    peak_force_mn: i32,
    last_step_us: Option<u64>,
    pending: Option<Request>,
    faults: Deque<FaultRecord, FAULTS_KEPT>,
    fault_count: u32,
    overload_trips: u32,
    events: Deque<Timed, EVENT_QUEUE>,
    events_dropped: u32,
    disabled_at_us: Option<u64>,
}

/// Errors that stop the controller from starting.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(target_os = "none", derive(defmt::Format))]
pub enum StartError {
    /// A motor output could not be put into its safe state.
    Pin,
}

fn closed<P: InputPin>(p: &mut P) -> Result<bool, ()> {
    p.is_low().map_err(|_| ())
}

impl<B: Bsp> Controller<B> {
    /// Take the parts, put every motor output in its safe state, start at `now_us`.
    pub fn new(parts: Parts<B>, cfg: ControllerConfig, now_us: u64) -> Result<Self, StartError> {
        let prop = Propulsion::new(parts.en_n, parts.dir, parts.pulses, cfg.machine)
            .map_err(|_| StartError::Pin)?;
        let lock =
            LockActuator::new(parts.lock_in1, parts.lock_in2).map_err(|_| StartError::Pin)?;
        Ok(Self {
            cfg,
            prop,
            lock,
            home: parts.home,
            end: parts.end,
            locked: parts.locked,
            released: parts.released,
            adc: parts.adc,
            wdg: parts.wdg,
            seq: Sequencer::new(cfg.machine),
            guard: OverloadGuard::new(cfg.guard),
            sensor: SensorMonitor::new(cfg.sample_rate_sps, now_us),
            cal: cfg.calibration,
            tare: Deque::new(),
            phase: None,
            mismatch_reported: false,
            mismatch_run: 0,
            force_mn: 0,
            limit_mn: cfg.guard.hard_limit_mn,
            warning: false,
            peak_force_mn: 0,
            last_step_us: None,
            pending: None,
            faults: Deque::new(),
            fault_count: 0,
            overload_trips: 0,
            events: Deque::new(),
            events_dropped: 0,
            disabled_at_us: None,
        })
    }

    /// Ask for something; acted on in the next control step.
    pub fn request(&mut self, r: Request) {
        self.pending = Some(r);
    }

    /// Poll from the main loop at `now_us`.
    pub fn poll(&mut self, now_us: u64) -> PollResult {
        let (sample, io_fault) = match self.adc.read_code() {
            Ok(c) => (Some(c), false),
            Err(nb::Error::WouldBlock) => (None, false),
            Err(nb::Error::Other(())) => (None, true),
        };
        let period = self.sensor.period_us();
        let due = sample.is_some()
            || io_fault
            || self
                .last_step_us
                .is_none_or(|t| now_us.saturating_sub(t) >= period);
        if !due {
            return PollResult::default();
        }
        self.step(now_us, sample, io_fault)
    }

    fn step(&mut self, now_us: u64, sample: Option<i32>, io_fault: bool) -> PollResult {
        let period = self.sensor.period_us();
        let dt_us = self
            .last_step_us
            .map_or(period, |t| now_us.saturating_sub(t));
        self.last_step_us = Some(now_us);
        let now_ms = now_us / 1000;
        let mut result = PollResult {
            stepped: true,
            sampled: sample.is_some(),
            tripped: false,
        };

        // 1. Position and switches.
        self.prop.sync();
        let pos_um = self.prop.position_um();
        let mut fault = io_fault.then_some(FaultKind::Io);
        let switches = match (
            closed(&mut self.home),
            closed(&mut self.end),
            closed(&mut self.locked),
            closed(&mut self.released),
        ) {
            (Ok(home), Ok(end), Ok(locked), Ok(released)) => Switches {
                home,
                end,
                locked,
                released,
            },
            _ => {
                fault = Some(FaultKind::Io);
                Switches::default()
            }
        };
        let state = self.seq.state();
        let depth_um = state
            .in_compliant_motion()
            .then(|| pos_um - self.cfg.machine.engage_um);
        // While retreating from an overload the load is expected to be high and falling:
        // only the hard limit applies then (a hard-limit trip ends the retreat).
        let guard_depth_um = if matches!(state, State::BackingOff { .. }) {
            None
        } else {
            depth_um
        };

        // 2. Sample: sensor health, then overload.
        if let Some(code) = sample {
            self.force_mn = self.cal.to_force_mn(code);
            self.peak_force_mn = self.peak_force_mn.max(self.force_mn);
            if let Some(f) = self.faults.back_mut() {
                if matches!(state, State::Faulted { .. } | State::BackingOff { .. }) {
                    f.peak_force_mn = f.peak_force_mn.max(self.force_mn);
                }
            }
            if let Some(sf) = self.sensor.on_sample(code, now_us, CODE_MIN, CODE_MAX) {
                fault = fault.or(Some(sensor_fault(sf)));
            }
            self.limit_mn = self.guard.limit_mn(guard_depth_um);
            match self.guard.check(self.force_mn, guard_depth_um) {
                Verdict::Trip { .. } => {
                    // Stop now, in this step; the sequencer then backs off under control.
                    let _ = self.prop.disable();
                    self.disabled_at_us = Some(now_us);
                    result.tripped = true;
                    self.overload_trips = self.overload_trips.saturating_add(1);
                    fault = fault.or(Some(FaultKind::Overload));
                }
                Verdict::Warn => {
                    if !self.warning {
                        warn!(
                            "force {} mN above the warning level (limit {} mN)",
                            self.force_mn, self.limit_mn
                        );
                        self.push_event(now_ms, Event::ForceWarning(self.force_mn));
                    }
                    self.warning = true;
                }
                Verdict::Ok | Verdict::Suspect => self.warning = false,
            }
            if state == State::Idle && switches.home {
                if self.tare.is_full() {
                    self.tare.pop_front();
                }
                let _ = self.tare.push_back(code);
            }
        } else if let Some(sf) = self.sensor.check_timeout(now_us) {
            fault = fault.or(Some(sensor_fault(sf)));
        }
        if fault.is_some_and(|f| f != FaultKind::Overload) && self.prop.is_enabled() {
            let _ = self.prop.disable();
            self.disabled_at_us = Some(now_us);
        }

        // 3. Contact phase from the depth, cross-checked with the force near 3→4.
        self.track_phase(now_ms, depth_um, sample.is_some());

        // 4. Sequencer.
        let mut request = self.pending.take();
        if request == Some(Request::StartCycle) && state == State::Idle {
            match self.take_tare() {
                TareResult::Ready => {}
                TareResult::NotYet => {
                    self.pending = request.take(); // wait for more zero-load samples
                }
                TareResult::Implausible => fault = fault.or(Some(FaultKind::ImplausibleTare)),
            }
        }
        if request == Some(Request::ClearFault) && matches!(state, State::Faulted { .. }) {
            self.guard.reset();
            self.sensor.reset(now_us);
        }
        let inputs = Inputs {
            now_ms,
            pos_um,
            axis_idle: self.prop.is_idle(),
            switches,
            fault,
            request,
        };
        let out = self.seq.step(&inputs);
        if let Some(ev) = out.event {
            self.on_seq_event(now_ms, ev);
        }

        // 5. Apply.
        if out.zero_position {
            self.prop.set_position_um(0);
        }
        let pin_ok = match out.axis {
            AxisCmd::Disabled => {
                if self.prop.is_enabled() {
                    self.disabled_at_us = Some(now_us);
                }
                self.prop.disable().is_ok()
            }
            AxisCmd::Hold => {
                self.prop.halt();
                self.prop.enable().is_ok()
            }
            AxisCmd::Move {
                target_um,
                speed_um_per_s,
            } => {
                if !self.prop.is_enabled() {
                    self.prop.halt();
                }
                self.prop.move_to(target_um, speed_um_per_s);
                self.prop.enable().is_ok()
            }
        };
        let lock_ok = self.lock.apply(out.lock).is_ok();
        let plan_ok = self.prop.plan(period.min(u32::MAX as u64) as u32).is_ok();
        if !(pin_ok && lock_ok && plan_ok) {
            // Could not drive an output: everything off; the next step latches `Io`.
            let _ = self.prop.disable();
            let _ = self.lock.apply(LockCmd::Off);
            self.pending = None;
        }

        // 6. A loop that keeps its period feeds the watchdog; a stalled one does not.
        if dt_us <= 3 * period {
            self.wdg.feed();
        }
        result
    }

    fn take_tare(&mut self) -> TareResult {
        if self.tare.len() < TARE_MIN_SAMPLES {
            return TareResult::NotYet;
        }
        let n = self.tare.len() as i64;
        let mean = (self.tare.iter().map(|&c| c as i64).sum::<i64>() / n) as i32;
        let drift_mn = Calibration {
            offset_counts: self.cfg.calibration.offset_counts,
            ..self.cal
        }
        .to_force_mn(mean);
        if !Calibration::tare_plausible(mean)
            || drift_mn.unsigned_abs() > self.cfg.tare_tolerance_mn.unsigned_abs()
        {
            error!(
                "implausible tare: {} counts ({} mN from calibration)",
                mean, drift_mn
            );
            return TareResult::Implausible;
        }
        self.cal = self.cal.with_tare(mean);
        self.tare.clear();
        TareResult::Ready
    }

    fn track_phase(&mut self, now_ms: u64, depth_um: Option<i32>, sampled: bool) {
        let phase = depth_um.and_then(ContactPhase::at_depth_um);
        if phase != self.phase {
            self.phase = phase;
            if let Some(p) = phase {
                info!("contact phase {}", p.number());
                self.push_event(now_ms, Event::Phase(p));
            }
        }
        if depth_um.is_none() {
            self.mismatch_reported = false;
            self.mismatch_run = 0;
            return;
        }
        // The 3→4 jump: within 1–3 mm before the boundary N3 < 156.7 N, within 1–4 mm
        // after it N3 > 156.7 N. Three contradicting samples in a row are reported once
        // per stroke (logged and counted, not a fault: the guard handles the forces).
        let (Some(d), Some(p), true) = (depth_um, phase, sampled) else {
            return;
        };
        let b = BOUNDARY_UM[2];
        let expect_high = if (b - 3_000..=b - 1_000).contains(&d) {
            Some(false)
        } else if (b + 1_000..=b + 4_000).contains(&d) {
            Some(true)
        } else {
            None
        };
        match expect_high {
            Some(high) if (self.force_mn > JUMP_MID_MN) != high => {
                self.mismatch_run = self.mismatch_run.saturating_add(1);
                if self.mismatch_run >= 3 && !self.mismatch_reported {
                    self.mismatch_reported = true;
                    warn!(
                        "phase {} by position, but {} mN contradicts it",
                        p.number(),
                        self.force_mn
                    );
                    self.push_event(now_ms, Event::PhaseMismatch(p));
                }
            }
            _ => self.mismatch_run = 0,
        }
    }

    fn on_seq_event(&mut self, now_ms: u64, ev: SeqEvent) {
        match ev {
            SeqEvent::Fault(kind) => {
                error!(
                    "fault {} in cycle {} at {} ms, force {} mN",
                    kind.name(),
                    self.seq.cycle_number(),
                    now_ms,
                    self.force_mn
                );
                if self.faults.is_full() {
                    self.faults.pop_front();
                }
                let rec = FaultRecord {
                    kind,
                    cycle: self.seq.cycle_number(),
                    phase: self.phase,
                    t_ms: now_ms,
                    peak_force_mn: self.force_mn,
                };
                let _ = self.faults.push_back(rec);
                self.fault_count = self.fault_count.saturating_add(1);
            }
            SeqEvent::CycleCompleted(n) => info!("cycle {} completed", n),
            SeqEvent::CycleStarted(n) => info!("cycle {} started", n),
            SeqEvent::FaultCleared => info!("fault cleared; recovering"),
            SeqEvent::Homed => info!("homed"),
            SeqEvent::RequestRefused(r) => warn!(
                "request {:?} refused in state {}",
                r,
                self.seq.state().name()
            ),
        }
        self.push_event(now_ms, Event::Seq(ev));
    }

    fn push_event(&mut self, t_ms: u64, event: Event) {
        if self.events.is_full() {
            self.events.pop_front();
            self.events_dropped = self.events_dropped.saturating_add(1);
        }
        let _ = self.events.push_back(Timed { t_ms, event });
    }

    /// The oldest unread event.
    pub fn next_event(&mut self) -> Option<Timed> {
        self.events.pop_front()
    }

    /// A status snapshot.
    pub fn status(&self) -> Status {
        let state = self.seq.state();
        Status {
            state,
            phase: self.phase,
            force_mn: self.force_mn,
            limit_mn: self.limit_mn,
            pos_um: self.prop.position_um(),
            cycles_completed: self.seq.cycles_completed(),
            fault: match state {
                State::Faulted { fault } => Some(fault),
                State::BackingOff { .. } => Some(FaultKind::Overload),
                _ => None,
            },
            warning: self.warning,
            peak_force_mn: self.peak_force_mn,
        }
    }

    /// Fault records, oldest first (the last 16).
    pub fn faults(&self) -> impl Iterator<Item = &FaultRecord> {
        self.faults.iter()
    }

    /// Faults latched since boot.
    pub fn fault_count(&self) -> u32 {
        self.fault_count
    }

    /// Overload trips since boot.
    pub fn overload_trips(&self) -> u32 {
        self.overload_trips
    }

    /// Single-sample spikes the guard rejected.
    pub fn spikes_rejected(&self) -> u32 {
        self.guard.spikes_rejected()
    }

    /// When the propulsion was last switched off by the controller, µs.
    pub fn disabled_at_us(&self) -> Option<u64> {
        self.disabled_at_us
    }

    /// Calibration in force (offset re-tared before each cycle).
    pub fn calibration(&self) -> Calibration {
        self.cal
    }

    /// Configuration.
    pub fn config(&self) -> &ControllerConfig {
        &self.cfg
    }
}

enum TareResult {
    Ready,
    NotYet,
    Implausible,
}

fn sensor_fault(f: SensorFault) -> FaultKind {
    match f {
        SensorFault::Disconnected => FaultKind::SensorDisconnected,
        SensorFault::Saturated => FaultKind::SensorSaturated,
        SensorFault::Stuck => FaultKind::SensorStuck,
    }
}
