//! Scenes: the real control code against the simulated machine, with a fault or
//! disturbance injected, in virtual time.
//!
//! | scene | what happens | expected |
//! |---|---|---|
//! | `nominal` | N full cycles | all complete, no fault, phases 1→2→3→4 on every insertion |
//! | `overload` | a jam in the last cycle's insertion: from 10 mm depth the force grows 60 N/mm | trip within one sample, back-off, `overload` latched |
//! | `spike` | N cycles with isolated single-sample +350 N spikes | no trip |
//! | `disconnect` | the HX711 goes silent at 5 mm depth | `sensor_disconnected` |
//! | `saturation` | the bridge saturates at 5 mm depth | `sensor_saturated` |
//! | `stuck` | the converter freezes at 5 mm depth | `sensor_stuck` |
//! | `bad-tare` | the zero-load reading is 50 N off before the first cycle | `implausible_tare` |
//! | `stall` | the carriage stalls when the first return starts | `axis_stall` |
//! | `lock-stuck` | the lock seizes before the first release | `lock_not_released` |
//! | `dock-hold` | in service, by the PLC's DOCK line: dock, hold a simulated hour, undock | no fault, one cycle counted, wear unchanged during the hold, MATED low before the extraction |
//! | `vehicle-pull` | docked by DOCK; while mated the vehicle pulls: the force grows 20 N/s | `hold_force`: MATED drops, the axis holds where it is (driven) |
//! | `estop` | docked by DOCK; E-STOP opens at 10 mm insertion depth | `emergency_stop`, motors and lock off; a clear is refused while E-STOP is open, accepted once closed (recovery home) |
//! | `estop-bounce` | E-STOP open pulses of 50 µs to 5 ms and releases with contact bounce ([`ESTOP_BOUNCE`]), at idle, in pre-alignment, in the insertion and mated | every episode latches `emergency_stop` with every edge accounted for, motors and lock off; the clear (the PLC's, over Modbus) is refused while the input is open and accepted once it is closed; after the last one the next dock completes |
//! | `heavy-default` | the 18 kg machine (µ2 0.1) on the default configuration, one test cycle | one `overload`, the back-off done (2 mm), and out of the cone (home) after a clear-fault |
//! | `maintenance-lockout` | a technician enters maintenance mode at the console (`pin set`, `maint <pin>`); the PLC asks to dock over Modbus (coil 0) and with the DOCK pin; then `maint exit` | READY low, status bit 11 and input register 10 show the mode, the Modbus dock is exception 01 (the wrong state), the pin is ignored and nothing moves; after `maint exit` the PLC docks |
//!
//! | `late-entry`, `dry-guide`, `debris`, `catch` | the docking signature's: a misalignment, a dry guide, debris, a catch ([`crate::sigscene`]) | the disturbed dockings NOK with the right object, the others OK; no fault |
//!
//! Every scene's report lists each stroke's signature verdict (`signatures`).
//!
//! `dock-hold`, `vehicle-pull`, `estop`, `estop-bounce` and `maintenance-lockout` are
//! driven by the PLC's lines (DOCK asserted when READY, released to undock) and its
//! Modbus commands; the others by test-cycle requests.

use std::time::Instant;

use docking_logic::controller::{Event, Refusal, Status};
use docking_logic::profile::ContactPhase;
use docking_logic::sequencer::{Request, SeqEvent, State, BACK_OFF_UM};

use crate::axis::{AxisFault, SimAxis};
use crate::hx711::{Hx711Fault, SimHx711};
use crate::line::SimLine;
use crate::lock::{LockFault, SimLock};
use crate::rig::{AdcMode, ProfileForce, Rig, RigOptions, SharedScript};
use crate::rng::Rng;

/// Scene names.
pub const SCENES: [&str; 19] = [
    "nominal",
    "overload",
    "spike",
    "disconnect",
    "saturation",
    "stuck",
    "bad-tare",
    "stall",
    "lock-stuck",
    "dock-hold",
    "vehicle-pull",
    "estop",
    "estop-bounce",
    "heavy-default",
    "maintenance-lockout",
    // The docking signature's (issue 34): `crate::sigscene`.
    "late-entry",
    "dry-guide",
    "debris",
    "catch",
];

/// The in-service scenes: the PLC docks with the DOCK line and undocks by releasing it.
pub const PLC_SCENES: [&str; 3] = ["dock-hold", "vehicle-pull", "estop"];

/// How long `dock-hold` stays mated, s (one simulated hour).
pub const DOCK_HOLD_S: u64 = 3_600;

/// The vehicle's pull in `vehicle-pull`, N/s.
pub const PULL_N_PER_S: f64 = 20.0;

/// Insertion depth at which `estop` opens the E-STOP line, µm.
pub const ESTOP_DEPTH_UM: i32 = 10_000;

/// What `estop-bounce` does to the E-STOP input.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EstopDisturbance {
    /// Open for this long (µs), then closed: two edges.
    Pulse(u32),
    /// Open for [`BOUNCE_OPEN_MS`], then a release that bounces: closed, then
    /// [`BOUNCE_RELEASE_US`] open pulses (µs) with [`BOUNCE_GAP_US`] closed between
    /// them: two edges and two a bounce.
    BouncingRelease,
}

impl EstopDisturbance {
    /// Edges of the input it makes.
    pub const fn edges(self) -> u32 {
        match self {
            Self::Pulse(_) => 2,
            Self::BouncingRelease => 2 + 2 * BOUNCE_RELEASE_US.len() as u32,
        }
    }
}

/// How long the input stays open before a bouncing release, ms.
pub const BOUNCE_OPEN_MS: u64 = 300;
/// The open pulses of a bouncing release, µs.
pub const BOUNCE_RELEASE_US: [u32; 3] = [100, 50, 20];
/// Closed between them, µs.
pub const BOUNCE_GAP_US: u32 = 200;

/// Where `estop-bounce` disturbs the E-STOP input, and how: every stage of a docking
/// that moves something, and idle.
pub const ESTOP_BOUNCE: [(Stage, EstopDisturbance); 8] = [
    (Stage::Idle, EstopDisturbance::Pulse(50)),
    (Stage::Idle, EstopDisturbance::Pulse(5_000)),
    (Stage::Idle, EstopDisturbance::BouncingRelease),
    (Stage::PreAlign, EstopDisturbance::Pulse(300)),
    (Stage::Inserting, EstopDisturbance::Pulse(500)),
    (Stage::Inserting, EstopDisturbance::BouncingRelease),
    (Stage::Mated, EstopDisturbance::Pulse(2_000)),
    (Stage::Mated, EstopDisturbance::BouncingRelease),
];

/// Insertion depth from which `estop-bounce` disturbs an insertion, µm.
pub const ESTOP_BOUNCE_DEPTH_UM: i32 = 5_000;

/// The machine of `heavy-default`: 18 kg, µ2 0.1 (its phase-4 peak is ≈ 352 N, over the
/// default guard's 300 N hard limit).
pub fn heavy_machine() -> crate::plant::PlantParams {
    crate::plant::PlantParams {
        mass_kg: 18.0,
        mu2: 0.1,
        ..crate::plant::PlantParams::PAPER
    }
}

/// The PIN the scenes' technician sets and enters.
pub const SCENE_PIN: &str = "2468";

/// Scene options.
#[derive(Clone, Copy, Debug)]
pub struct SceneOptions {
    /// Cycles to run (the disturbance comes in the last one where it applies).
    pub cycles: u32,
    /// Load-cell rate, SPS.
    pub rate_sps: u32,
    /// Seed for noise and spike placement.
    pub seed: u64,
    /// How the controller reads the load cell.
    pub adc: AdcMode,
    /// The machine's contact forces (Eq. 7, or the plant of another machine).
    pub force_model: crate::machine::ForceModel,
    /// The controller commissioned for another machine; `None`: the build's defaults.
    pub tuning: Option<crate::machine::Tuning>,
}

impl SceneOptions {
    /// One cycle at `rate_sps`, seed 1, the firmware's HX711 driver on the pins, the
    /// paper's machine with the default configuration.
    pub fn new(rate_sps: u32) -> Self {
        Self {
            cycles: 1,
            rate_sps,
            seed: 1,
            adc: AdcMode::Pins,
            force_model: crate::machine::ForceModel::Eq7,
            tuning: None,
        }
    }
}

/// A fault as the scene saw it.
#[derive(Clone, Debug, PartialEq)]
pub struct FaultSeen {
    /// Fault name.
    pub kind: &'static str,
    /// Cycle (1-based).
    pub cycle: u32,
    /// Contact phase number, if in the cone.
    pub phase: Option<u8>,
    /// Virtual time, s.
    pub t_s: f64,
    /// Peak force recorded with it, N.
    pub peak_force_n: f64,
}

/// What a scene run produced.
#[derive(Clone, Debug)]
pub struct SceneReport {
    /// Scene name.
    pub scene: String,
    /// Options.
    pub rate_sps: u32,
    /// Seed.
    pub seed: u64,
    /// Cycles completed.
    pub cycles_completed: u32,
    /// Faults latched.
    pub faults: Vec<FaultSeen>,
    /// Highest measured force, N.
    pub peak_force_n: f64,
    /// First over-limit sample (its conversion time) to propulsion disabled, s.
    pub stop_latency_s: Option<f64>,
    /// Final sequencer state.
    pub final_state: &'static str,
    /// Contact phases entered on each insertion, in order.
    pub insertion_phases: Vec<Vec<u8>>,
    /// Every motor output off at the end.
    pub motors_disabled: bool,
    /// Carriage travel toward the male panel after the trip, µm.
    pub forward_after_trip_um: Option<f64>,
    /// Retreat after the trip, µm.
    pub backed_off_um: Option<f64>,
    /// Spikes the guard rejected (the safety kernel's own count).
    pub spikes_rejected: u32,
    /// Spikes delivered: scheduled spikes that went into a conversion the controller
    /// read out ([`SpikeTally`]); a spike scheduled past the run's end, or in a
    /// conversion nobody read, is not one.
    pub spikes_injected: u32,
    /// Control steps run.
    pub control_steps: u64,
    /// Virtual time simulated, s.
    pub sim_time_s: f64,
    /// Wall time, s.
    pub wall_time_s: f64,
    /// The watchdog would have reset the MCU.
    pub watchdog_bit: bool,
    /// In-service scenes: what the PLC saw.
    pub plc: Option<PlcReport>,
    /// `heavy-default`: after a clear-fault the machine went home, out of the cone (idle,
    /// locked, driver off).
    pub recovered_after_clear: Option<bool>,
    /// Every stroke's signature verdict, in order.
    pub signatures: Vec<crate::sigscene::SignatureSeen>,
}

/// A scene's verdict: what it was expected to show, and what it did not.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Verdict {
    /// Each expectation, in words.
    pub expected: Vec<String>,
    /// Those this run did not meet.
    pub failed: Vec<String>,
}

impl Verdict {
    /// Every expectation met.
    pub fn passed(&self) -> bool {
        self.failed.is_empty()
    }

    /// `verdict: PASS (expected: …)` or `verdict: FAIL: … (expected: …)`.
    pub fn to_text(&self) -> String {
        if self.passed() {
            format!("verdict: PASS (expected: {})", self.expected.join("; "))
        } else {
            format!(
                "verdict: FAIL: not {} (expected: {})",
                self.failed.join("; not "),
                self.expected.join("; ")
            )
        }
    }
}

/// What an in-service scene ([`PLC_SCENES`]) saw on the handshake.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct PlcReport {
    /// Time the MATED output was high, s.
    pub mated_s: f64,
    /// The cone's load–distance added while MATED was high, Q63.1 mN·µm (wear is
    /// proportional to it: zero = no wear during the hold).
    pub hold_load_distance_q1: Option<u64>,
    /// MATED was low before the extraction started.
    pub mated_low_before_extraction: Option<bool>,
    /// E-STOP opening to the propulsion driver disabled, s (the host rig acts at its next
    /// tick; the virtual board measures the interrupt).
    pub estop_latency_s: Option<f64>,
    /// The lock was not driven after the E-STOP opened.
    pub lock_off_after_estop: Option<bool>,
    /// A clear while E-STOP was open was refused.
    pub clear_refused_while_open: Option<bool>,
    /// A clear once E-STOP closed was accepted.
    pub clear_accepted_when_closed: Option<bool>,
    /// After a `hold_force` fault the axis stayed driven (enabled) and where it was.
    pub axis_held: Option<bool>,
    /// `estop-bounce`: disturbances of the E-STOP input.
    pub estop_episodes: Option<u32>,
    /// `estop-bounce`: edges of the input the scene made.
    pub estop_edges_injected: Option<u32>,
    /// `estop-bounce`: edges the controller reported having latched (its
    /// `EstopEdges` events on the host rig, its log on the board).
    pub estop_edges_latched: Option<u32>,
    /// `estop-bounce`: episodes that ended with `emergency_stop` latched, FAULT high,
    /// READY low and every motor off.
    pub estop_faults_latched: Option<u32>,
    /// `estop-bounce`: the PLC's clears accepted once the input was closed (one an
    /// episode), and refused while it was open (one a bouncing release).
    pub clears_accepted: Option<u32>,
    /// See [`PlcReport::clears_accepted`].
    pub clears_refused_while_open: Option<u32>,
    /// `estop-bounce`: a dock after the last episode completed (mated, undocked, home).
    pub docked_after_estops: Option<bool>,
    /// `maintenance-lockout`: READY low throughout maintenance mode.
    pub ready_low_in_maintenance: Option<bool>,
    /// `maintenance-lockout`: status bit 11 and input register 10 showed the mode.
    pub maintenance_shown: Option<bool>,
    /// `maintenance-lockout`: the Modbus dock (coil 0) was refused with exception 01 (the wrong state).
    pub modbus_dock_refused: Option<bool>,
    /// `maintenance-lockout`: the DOCK pin was ignored (nothing moved).
    pub dock_pin_ignored: Option<bool>,
    /// `maintenance-lockout`: after `maint exit` the PLC docked (mated, undocked, home).
    pub docked_after_maintenance: Option<bool>,
}

impl PlcReport {
    /// The yes/no checks a scene filled in (`None`: not this scene's), each true when
    /// the machine did what it should.
    pub fn flags(&self) -> [(&'static str, Option<bool>); 11] {
        [
            (
                "mated_low_before_extraction",
                self.mated_low_before_extraction,
            ),
            ("lock_off_after_estop", self.lock_off_after_estop),
            ("clear_refused_while_open", self.clear_refused_while_open),
            (
                "clear_accepted_when_closed",
                self.clear_accepted_when_closed,
            ),
            ("axis_held", self.axis_held),
            ("docked_after_estops", self.docked_after_estops),
            ("ready_low_in_maintenance", self.ready_low_in_maintenance),
            ("maintenance_shown", self.maintenance_shown),
            ("modbus_dock_refused", self.modbus_dock_refused),
            ("dock_pin_ignored", self.dock_pin_ignored),
            ("docked_after_maintenance", self.docked_after_maintenance),
        ]
    }

    /// `key=value` pairs (what the JSON holds, without the ones that do not apply).
    pub fn to_text(&self) -> String {
        let json = self.to_json();
        let inner = json.trim_start_matches('{').trim_end_matches('}');
        inner
            .split(',')
            .filter_map(|kv| {
                let (k, v) = kv.split_once(':')?;
                (v != "null").then(|| format!("{}={}", k.trim_matches('"'), v))
            })
            .collect::<Vec<_>>()
            .join(" ")
    }

    fn to_json(&self) -> String {
        let ob = |x: Option<bool>| x.map_or("null".to_string(), |b| b.to_string());
        let on = |x: Option<u32>| x.map_or("null".to_string(), |n| n.to_string());
        format!(
            "{{\"mated_s\":{},\"hold_load_distance_q1\":{},\"mated_low_before_extraction\":{},\"estop_latency_s\":{},\"lock_off_after_estop\":{},\"clear_refused_while_open\":{},\"clear_accepted_when_closed\":{},\"axis_held\":{},\"estop_episodes\":{},\"estop_edges_injected\":{},\"estop_edges_latched\":{},\"estop_faults_latched\":{},\"clears_accepted\":{},\"clears_refused_while_open\":{},\"docked_after_estops\":{},\"ready_low_in_maintenance\":{},\"maintenance_shown\":{},\"modbus_dock_refused\":{},\"dock_pin_ignored\":{},\"docked_after_maintenance\":{}}}",
            num(self.mated_s),
            self.hold_load_distance_q1.map_or("null".to_string(), |x| x.to_string()),
            ob(self.mated_low_before_extraction),
            self.estop_latency_s.map_or("null".to_string(), num),
            ob(self.lock_off_after_estop),
            ob(self.clear_refused_while_open),
            ob(self.clear_accepted_when_closed),
            ob(self.axis_held),
            on(self.estop_episodes),
            on(self.estop_edges_injected),
            on(self.estop_edges_latched),
            on(self.estop_faults_latched),
            on(self.clears_accepted),
            on(self.clears_refused_while_open),
            ob(self.docked_after_estops),
            ob(self.ready_low_in_maintenance),
            ob(self.maintenance_shown),
            ob(self.modbus_dock_refused),
            ob(self.dock_pin_ignored),
            ob(self.docked_after_maintenance),
        )
    }
}

/// The PLC of an in-service scene: docks by DOCK when READY, undocks by releasing it,
/// and watches the handshake.
#[derive(Debug, Default)]
struct Plc {
    rep: PlcReport,
    docked: bool,
    released: bool,
    mated_since_ns: Option<u64>,
    w_at_mated: u64,
    mated_fell_ns: Option<u64>,
    estop_open_ns: Option<u64>,
    fault_ns: Option<u64>,
    pos_at_fault_um: f64,
    clear_step: u8,
    done: bool,
}

impl Plc {
    /// One tick of the PLC (after the rig's tick and the scene's disturbance).
    fn tick(&mut self, name: &str, rig: &mut Rig, st: &Status, now: u64) {
        let h = st.handshake;
        if !self.docked && h.ready {
            rig.dock_line.set(false); // assert DOCK
            self.docked = true;
        }
        let w = rig.ctrl.journal().cone_w_q1;
        match (h.mated, self.mated_since_ns) {
            (true, None) => {
                self.mated_since_ns = Some(now);
                self.w_at_mated = w;
            }
            (false, Some(t0)) => {
                self.rep.mated_s += now.saturating_sub(t0) as f64 * 1e-9;
                self.rep.hold_load_distance_q1 = Some(w.saturating_sub(self.w_at_mated));
                self.mated_fell_ns = Some(now);
                self.mated_since_ns = None;
            }
            _ => {}
        }
        if name == "dock-hold"
            && !self.released
            && self
                .mated_since_ns
                .is_some_and(|t0| now.saturating_sub(t0) >= DOCK_HOLD_S * 1_000_000_000)
        {
            rig.dock_line.set(true); // release DOCK: undock
            self.released = true;
        }
        if matches!(st.state, State::Extracting { .. })
            && self.rep.mated_low_before_extraction.is_none()
        {
            self.rep.mated_low_before_extraction =
                Some(!h.mated && self.mated_fell_ns.is_some_and(|t| t < now));
        }
        if rig.estop_line.is_high() && self.estop_open_ns.is_none() {
            self.estop_open_ns = Some(now);
        }
        if let Some(t0) = self.estop_open_ns {
            if self.rep.estop_latency_s.is_none() {
                if let Some(e) = rig
                    .axis
                    .enable_edges()
                    .iter()
                    .find(|e| !e.enabled && e.t_ns >= t0)
                {
                    self.rep.estop_latency_s = Some(e.t_ns.saturating_sub(t0) as f64 * 1e-9);
                }
            }
            if rig.estop_line.is_high() && now > t0 {
                let off = !rig.lock.driven();
                self.rep.lock_off_after_estop =
                    Some(self.rep.lock_off_after_estop.unwrap_or(true) && off);
            }
        }
        if matches!(st.state, State::Faulted { .. }) && self.fault_ns.is_none() {
            self.fault_ns = Some(now);
            self.pos_at_fault_um = rig.axis.pos_um();
            if name == "vehicle-pull" {
                // MATED dropped: the vehicle stops pulling.
                rig.devices().script.borrow_mut().pull_n_per_s = 0.0;
            }
        }
        let since_fault = self.fault_ns.map(|t| now.saturating_sub(t));
        match (name, since_fault) {
            ("vehicle-pull", Some(dt)) if dt >= 2_000_000_000 => {
                let still = (rig.axis.pos_um() - self.pos_at_fault_um).abs() < 1.0;
                self.rep.axis_held = Some(rig.axis.enabled() && still);
                self.done = true;
            }
            ("estop", Some(dt)) => {
                if self.clear_step == 0 && dt >= 1_000_000_000 {
                    rig.dock_line.set(true); // the PLC releases DOCK on the stop
                    self.rep.clear_refused_while_open =
                        Some(rig.ctrl.command(Request::ClearFault) == Err(Refusal::EstopOpen));
                    rig.estop_line.set(false); // E-STOP restored
                    self.clear_step = 1;
                } else if self.clear_step == 1 && dt >= 1_500_000_000 {
                    self.rep.clear_accepted_when_closed =
                        Some(rig.ctrl.command(Request::ClearFault).is_ok());
                    self.clear_step = 2;
                } else if self.clear_step == 2 && st.state == State::Idle {
                    self.done = true;
                }
            }
            ("dock-hold", _) if self.released && st.state == State::Idle => self.done = true,
            _ => {}
        }
    }
}

/// Sets up a scene's disturbance and injects it when its moment comes (shared by the
/// batch runner and `hil-sim serve`).
#[derive(Clone, Debug)]
pub struct SceneDriver {
    name: &'static str,
    /// The disturbance comes in this cycle (1-based).
    in_cycle: u32,
    injected: bool,
}

impl SceneDriver {
    /// A driver for scene `name` whose disturbance comes in cycle `in_cycle`.
    pub fn new(name: &str, in_cycle: u32) -> Result<Self, String> {
        let Some(&name) = SCENES.iter().find(|&&s| s == name) else {
            return Err(format!(
                "unknown scene '{name}' (scenes: {})",
                SCENES.join(", ")
            ));
        };
        Ok(Self {
            name,
            in_cycle: in_cycle.max(1),
            injected: false,
        })
    }

    /// Prepare the machine before the first tick (spike schedule, shifted bridge);
    /// returns the spikes scheduled. `horizon_cycles` bounds the spike schedule.
    pub fn setup(&self, dev: Devices<'_>, seed: u64, rate_sps: u32, horizon_cycles: u32) -> u32 {
        match self.name {
            "spike" => {
                // Isolated spikes: about every 40 samples, never two within 3 samples.
                let mut rng = Rng::new(seed ^ 0x5eed);
                let total = (horizon_cycles as f64 * 75.0 * rate_sps as f64) as u64;
                let mut at = Vec::new();
                let mut n = 20u64;
                while n < total {
                    n += 4 + (rng.uniform() * 70.0) as u64;
                    at.push(n);
                }
                let count = at.len() as u32;
                let mut s = dev.script.borrow_mut();
                s.spikes_at = at;
                s.spike_n = 350.0;
                count
            }
            "bad-tare" => {
                dev.script.borrow_mut().offset_n = 50.0;
                0
            }
            _ => 0,
        }
    }

    /// Inject the disturbance on the host rig if this is its moment.
    pub fn on_tick(&mut self, rig: &mut Rig, st: &Status) {
        let p = Progress::of_status(st, rig.ctrl.config().machine.engage_um);
        self.on_progress(rig.devices(), &p);
    }

    /// Inject the disturbance if this is its moment, whoever observed the progress (the
    /// host rig from the controller's status, the virtual board from the pins and log).
    pub fn on_progress(&mut self, dev: Devices<'_>, p: &Progress) {
        if self.injected {
            return;
        }
        let in_cycle = p.cycles_completed + 1 >= self.in_cycle;
        let inserting = p.stage == Stage::Inserting;
        self.injected = match self.name {
            "overload" if in_cycle && inserting => {
                let mut s = dev.script.borrow_mut();
                s.jam_from_um = Some(10_000.0);
                s.jam_n_per_mm = 60.0;
                true
            }
            "disconnect" | "saturation" | "stuck"
                if in_cycle && inserting && p.depth_um >= 5_000 =>
            {
                dev.hx.set_fault(match self.name {
                    "disconnect" => Hx711Fault::Disconnected,
                    "saturation" => Hx711Fault::Saturated,
                    _ => Hx711Fault::Stuck,
                });
                true
            }
            "stall" if in_cycle && p.stage == Stage::Returning => {
                dev.axis.set_fault(AxisFault::Stalled);
                true
            }
            "lock-stuck" if in_cycle && p.stage == Stage::PreAlign => {
                dev.lock.set_fault(LockFault::Stuck);
                true
            }
            "vehicle-pull" if in_cycle && p.stage == Stage::Mated => {
                dev.script.borrow_mut().pull_n_per_s = PULL_N_PER_S;
                true
            }
            "estop" if in_cycle && inserting && p.depth_um >= ESTOP_DEPTH_UM => {
                dev.estop.set(true);
                true
            }
            n if crate::sigscene::SCENES.contains(&n)
                && p.stage == Stage::PreAlign
                && crate::sigscene::disturbed(n, self.in_cycle)
                    .contains(&(p.cycles_completed + 1)) =>
            {
                crate::sigscene::disturb(n, &mut dev.script.borrow_mut());
                true
            }
            _ => false,
        };
    }

    /// Whether the disturbance has been injected.
    pub fn injected(&self) -> bool {
        self.injected
    }
}

/// Where the machine is in its docking cycle, as far as a disturbance cares.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stage {
    /// At rest (idle, faulted, powering up).
    Idle,
    /// Locked, moving fast to the engagement point.
    PreAlign,
    /// Compliant insertion.
    Inserting,
    /// Back from the engagement point to home.
    Returning,
    /// Mated, holding (no undock under way).
    Mated,
    /// Anything else (release, hold, extraction, locking, recovery).
    Other,
}

/// A scene's view of the machine's progress.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Progress {
    /// Docking cycles completed.
    pub cycles_completed: u32,
    /// Stage of the current cycle.
    pub stage: Stage,
    /// Insertion depth (position − engagement point), µm.
    pub depth_um: i32,
}

impl Progress {
    /// From the controller's status (host rig).
    pub fn of_status(st: &Status, engage_um: i32) -> Self {
        Self {
            cycles_completed: st.cycles_completed,
            stage: match st.state {
                State::PreAlign { .. } => Stage::PreAlign,
                State::Inserting { .. } => Stage::Inserting,
                State::Returning { .. } => Stage::Returning,
                State::Holding {
                    unmating: false, ..
                } => Stage::Mated,
                State::Idle | State::Faulted { .. } | State::PowerUp => Stage::Idle,
                _ => Stage::Other,
            },
            depth_um: st.pos_um - engage_um,
        }
    }
}

/// The devices a scene disturbs.
#[derive(Clone, Copy)]
pub struct Devices<'a> {
    /// Force additions.
    pub script: &'a SharedScript,
    /// Load cell.
    pub hx: &'a SimHx711<ProfileForce>,
    /// Axis.
    pub axis: &'a SimAxis,
    /// Lock.
    pub lock: &'a SimLock,
    /// The E-STOP line (normally closed: high = open = stop).
    pub estop: &'a SimLine,
}

/// What a flooding terminal sends (picked at random): commands with long replies, a full
/// `history`, garbage with control bytes and escape sequences, an overlong line.
pub const FLOOD_PIECES: [&[u8]; 6] = [
    b"status --json\r\n",
    b"history 100 --json\r\n",
    b"\xff\xfe\x00\x1b[A garbage \x07\r\n",
    b"cone replace zqsn5-2 X\r\n",
    b"wear\rfaults --json\n",
    b"AAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAAA",
];

/// A scene run while the console is flooded.
#[derive(Clone, Debug)]
pub struct FloodReport {
    /// The scene's report.
    pub report: SceneReport,
    /// Bytes sent to the console during the run.
    pub console_bytes: u64,
    /// Bytes lost to the UART's full receive ring.
    pub rx_overruns: u64,
}

/// Run scene `name` while a terminal floods the console at the line rate (115 200 baud:
/// 11.52 bytes/ms) with garbage, overlong lines, control characters and valid commands
/// that produce long replies (`history 100 --json`).
pub fn run_with_console_flood(name: &str, opts: SceneOptions) -> Result<FloodReport, String> {
    let mut sent = 0u64;
    let mut overruns = 0u64;
    let report = run_inner(name, opts, &mut |rig: &mut Rig, rng: &mut Rng| {
        rig.console_enabled = true;
        let due = (rig.clock.now_ns() as f64 * 11.52e-6) as u64;
        while sent < due {
            let piece = FLOOD_PIECES[(rng.next_u64() % FLOOD_PIECES.len() as u64) as usize];
            rig.term.send(piece);
            sent += piece.len() as u64;
        }
        let _ = rig.term.take_output();
        overruns = rig.term.rx_overruns;
    })?;
    Ok(FloodReport {
        report,
        console_bytes: sent,
        rx_overruns: overruns,
    })
}

/// Run scene `name`. `Err` for an unknown name.
pub fn run(name: &str, opts: SceneOptions) -> Result<SceneReport, String> {
    run_inner(name, opts, &mut |_, _| {})
}

/// Which way the carriage was going when a [`TraceSample`] was taken.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TraceStroke {
    /// Compliant insertion (`Inserting`).
    Insertion,
    /// Extraction (`Extracting`).
    Extraction,
    /// Any other state in the cone: holding, backing off after a trip, faulted.
    Other,
}

/// One load-cell sample of a [`SceneTrace`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TraceSample {
    /// Insertion depth (counted position − engagement point), mm.
    pub depth_mm: f64,
    /// The controller's measured (tared) force, N.
    pub force_n: f64,
    /// The guard's limit in force for this sample, N.
    pub limit_n: f64,
    /// Stroke.
    pub stroke: TraceStroke,
    /// Virtual time, s.
    pub t_s: f64,
}

/// What happened at a marked point of a [`SceneTrace`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TraceEventKind {
    /// The first over-limit sample of the episode that latched an overload (or
    /// tension) fault.
    Trip,
    /// A single-sample spike the guard rejected (the spike's own sample).
    SpikeRejected,
    /// A fault latched (its name).
    Fault(&'static str),
}

/// A marked point of a [`SceneTrace`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TraceEvent {
    /// What.
    pub kind: TraceEventKind,
    /// Where, mm of insertion depth.
    pub depth_mm: f64,
    /// The force measured there, N.
    pub force_n: f64,
    /// When, s.
    pub t_s: f64,
}

/// Counts the scheduled spikes ([`ForceScript::spikes_at`]: conversion numbers) that
/// went into a conversion the controller read: each completed conversion is one call of
/// the force source, in order, so the `k` conversions that completed since the last look
/// are the newest `k` of [`SimHx711::recent_conversions`]; a spike's conversion counts
/// once it is marked read, and is dropped if a newer one completed before it was.
///
/// [`ForceScript::spikes_at`]: crate::rig::ForceScript::spikes_at
#[derive(Clone, Debug, Default)]
pub struct SpikeTally {
    at: Vec<u64>,
    conversions_seen: u64,
    /// Completion times of spiked conversions not read yet, ns.
    pending: Vec<u64>,
    /// Spikes delivered in a conversion that was read.
    pub delivered: u32,
}

impl SpikeTally {
    /// For the spikes scheduled in `dev`'s script; conversions before now are not looked
    /// at.
    pub fn new(dev: Devices<'_>, conversions: u64) -> Self {
        Self {
            at: dev.script.borrow().spikes_at.clone(),
            conversions_seen: conversions,
            ..Self::default()
        }
    }

    /// Whether [`SpikeTally::observe`] has anything to do with `conversions` completed.
    pub fn due(&self, conversions: u64) -> bool {
        !self.at.is_empty() && (conversions > self.conversions_seen || !self.pending.is_empty())
    }

    /// Look after the devices ran: the HX711's `recent` conversions (time ns, code,
    /// read), oldest first, and `conversions` completed so far (the force source's count,
    /// read after `recent`: asking for the recent conversions completes those due).
    pub fn observe(&mut self, conversions: u64, recent: &[(u64, i32, bool)]) {
        let new = conversions.saturating_sub(self.conversions_seen);
        if new > 0 {
            let k = (new as usize).min(recent.len());
            let first = conversions - k as u64;
            for (i, c) in recent[recent.len() - k..].iter().enumerate() {
                if self.at.binary_search(&(first + i as u64)).is_ok() {
                    self.pending.push(c.0);
                }
            }
            self.conversions_seen = conversions;
        }
        let newest = recent.last().map(|c| c.0);
        let mut delivered = 0;
        self.pending
            .retain(|&t| match recent.iter().find(|c| c.0 == t) {
                Some(c) if c.2 => {
                    delivered += 1;
                    false
                }
                // Unread, and a newer conversion replaced it (or it left the window).
                Some(_) => Some(t) == newest,
                None => false,
            });
        self.delivered += delivered;
    }
}

/// A scene's force trace (for `--plot`): the samples taken within 2 mm of the cone or
/// deeper in the scene's last cycle (the one with the disturbance), and the events.
/// Samples are kept when the stroke changes, the carriage has moved or the force has
/// changed by 2 N (a long hold adds a handful, not one per sample); faults are kept
/// whatever the cycle.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct SceneTrace {
    /// The cycle traced (1-based).
    pub cycle: u32,
    /// Samples in time order.
    pub samples: Vec<TraceSample>,
    /// Events in time order.
    pub events: Vec<TraceEvent>,
    /// Spikes the safety kernel rejected during the traced cycle (its own count, as
    /// the report's `spikes_rejected`; the markers are those in the traced depths).
    pub spikes_rejected_in_cycle: u32,
    /// Spikes the kernel rejected in the whole run (the report's `spikes_rejected`).
    pub spikes_rejected_total: u32,
}

/// Depth from which samples are traced, µm (a little before the cone).
const TRACE_FROM_UM: i32 = -2_000;

/// Builds a [`SceneTrace`] from the rig between ticks.
struct TraceRecorder {
    trace: SceneTrace,
    last_conv_ns: Option<u64>,
    /// The previous sample (kept or not).
    prev: Option<TraceSample>,
    /// The first over-limit sample of the current episode.
    over_since: Option<TraceSample>,
    spikes_seen: u32,
    fault_seen: bool,
}

impl TraceRecorder {
    fn new(cycle: u32) -> Self {
        Self {
            trace: SceneTrace {
                cycle,
                ..SceneTrace::default()
            },
            last_conv_ns: None,
            prev: None,
            over_since: None,
            spikes_seen: 0,
            fault_seen: false,
        }
    }

    fn event(&mut self, kind: TraceEventKind, s: &TraceSample) {
        self.trace.events.push(TraceEvent {
            kind,
            depth_mm: s.depth_mm,
            force_n: s.force_n,
            t_s: s.t_s,
        });
    }

    /// Look at the rig after a tick.
    fn observe(&mut self, rig: &Rig) {
        let st = rig.ctrl.status();
        let conv = rig.hx.last_read().map(|(_, t)| t);
        let new_sample = conv.is_some() && conv != self.last_conv_ns;
        self.last_conv_ns = conv;
        let depth_um = st.pos_um - rig.ctrl.config().machine.engage_um;
        let s = TraceSample {
            depth_mm: depth_um as f64 / 1000.0,
            force_n: st.force_mn as f64 / 1000.0,
            limit_n: st.limit_mn as f64 / 1000.0,
            stroke: match st.state {
                State::Inserting { .. } => TraceStroke::Insertion,
                State::Extracting { .. } => TraceStroke::Extraction,
                _ => TraceStroke::Other,
            },
            t_s: rig.clock.now_s(),
        };
        let in_cycle = st.cycles_completed + 1 >= self.trace.cycle;
        if new_sample {
            if st.force_mn > st.limit_mn {
                self.over_since.get_or_insert(s);
            } else if st.fault.is_none() {
                self.over_since = None;
            }
            let spikes = rig.kernel.spikes_rejected();
            if in_cycle {
                self.trace.spikes_rejected_in_cycle += spikes.saturating_sub(self.spikes_seen);
            }
            self.trace.spikes_rejected_total = spikes;
            if spikes > self.spikes_seen && in_cycle {
                if let Some(p) = self
                    .prev
                    .filter(|p| p.depth_mm * 1000.0 >= TRACE_FROM_UM as f64)
                {
                    self.event(TraceEventKind::SpikeRejected, &p);
                }
            }
            self.spikes_seen = spikes;
            let keep = in_cycle
                && depth_um >= TRACE_FROM_UM
                && self.trace.samples.last().is_none_or(|l| {
                    l.stroke != s.stroke
                        || l.depth_mm != s.depth_mm
                        || (l.force_n - s.force_n).abs() >= 2.0
                });
            // (A spike's own sample is kept: it is 2 N off its neighbours.)
            if keep {
                self.trace.samples.push(s);
            }
            self.prev = Some(s);
        }
        match st.fault {
            Some(f) if !self.fault_seen => {
                self.fault_seen = true;
                let name = f.name();
                if matches!(name, "overload" | "tension") {
                    if let Some(o) = self.over_since {
                        self.event(TraceEventKind::Trip, &o);
                    }
                }
                self.event(TraceEventKind::Fault(name), &s);
            }
            None => self.fault_seen = false,
            _ => {}
        }
    }
}

/// [`run`], tracing the force against depth in the last cycle (for `--plot`).
pub fn run_traced(name: &str, opts: SceneOptions) -> Result<(SceneReport, SceneTrace), String> {
    let mut rec = TraceRecorder::new(opts.cycles.max(1));
    let report = run_inner(name, opts, &mut |rig: &mut Rig, _: &mut Rng| {
        rec.observe(rig)
    })?;
    Ok((report, rec.trace))
}

fn run_inner(
    name: &str,
    opts: SceneOptions,
    each_tick: &mut dyn FnMut(&mut Rig, &mut Rng),
) -> Result<SceneReport, String> {
    let mut driver = SceneDriver::new(name, opts.cycles.max(1))?;
    let started = Instant::now();
    match name {
        "estop-bounce" => return estop_bounce(opts, each_tick),
        "maintenance-lockout" => return maintenance_lockout(opts, each_tick),
        _ => {}
    }
    let opts = if name == "heavy-default" {
        SceneOptions {
            force_model: crate::machine::ForceModel::plant(heavy_machine())
                .map_err(|e| format!("heavy-default: {e:?}"))?,
            tuning: None,
            ..opts
        }
    } else {
        opts
    };
    let mut rig = Rig::new(RigOptions {
        seed: opts.seed,
        adc: opts.adc,
        force_model: opts.force_model,
        tuning: opts.tuning,
        ..RigOptions::new(opts.rate_sps)
    });
    let cycles = opts.cycles.max(1);
    driver.setup(rig.devices(), opts.seed, opts.rate_sps, cycles);
    let mut spikes = SpikeTally::new(rig.devices(), rig.conversions.get());

    let mut insertion_phases: Vec<Vec<u8>> = Vec::new();
    let mut signatures = Vec::new();
    let mut faults = Vec::new();
    let mut episode_start_ns: Option<u64> = None;
    let mut stop_latency_s = None;
    let mut trip_pos_um: Option<f64> = None;
    let (mut max_after, mut min_after) = (f64::MIN, f64::MAX);
    let mut steps = 0u64;
    let mut settle_until_ns: Option<u64> = None;
    let plc_scene = PLC_SCENES.contains(&name);
    let mut plc = plc_scene.then(Plc::default);
    let hold_s = if name == "dock-hold" { DOCK_HOLD_S } else { 0 };
    let max_ns = (cycles as u64 * 150 + 60 + hold_s) * 1_000_000_000;

    let mut tick_rng = Rng::new(opts.seed ^ 0xf100d);
    loop {
        each_tick(&mut rig, &mut tick_rng);
        let r = rig.tick();
        if r.stepped {
            steps += 1;
        }
        let now = rig.clock.now_ns();
        let st = rig.ctrl.status();
        if spikes.due(rig.conversions.get()) {
            // The recent conversions first: reading them completes any that are due.
            let recent = rig.hx.recent_conversions();
            spikes.observe(rig.conversions.get(), &recent);
        }

        // First over-limit sample of an episode, by the controller's own limit.
        if r.sampled {
            if let Some((code, t_conv)) = rig.hx.last_read() {
                let f = rig.ctrl.calibration().to_force_mn(code);
                if f > st.limit_mn {
                    episode_start_ns.get_or_insert(t_conv);
                } else if !r.tripped {
                    episode_start_ns = None;
                }
            }
        }
        if r.tripped && stop_latency_s.is_none() {
            if let (Some(t0), Some(edge)) = (
                episode_start_ns,
                rig.axis.enable_edges().iter().rev().find(|e| !e.enabled),
            ) {
                stop_latency_s = Some((edge.t_ns.saturating_sub(t0)) as f64 * 1e-9);
                trip_pos_um = Some(edge.pos_um);
            }
        }
        if let Some(p0) = trip_pos_um {
            let p = rig.axis.pos_um();
            max_after = max_after.max(p - p0);
            min_after = min_after.min(p - p0);
        }

        while let Some(ev) = rig.ctrl.next_event() {
            signatures.extend(crate::sigscene::SignatureSeen::of_event(&ev.event));
            match ev.event {
                Event::Seq(SeqEvent::CycleStarted(_)) => insertion_phases.push(Vec::new()),
                Event::Phase(p) if matches!(st.state, State::Inserting { .. }) => {
                    if let Some(v) = insertion_phases.last_mut() {
                        v.push(p.number());
                    }
                }
                _ => {}
            }
        }

        // Disturbances.
        driver.on_tick(&mut rig, &st);

        if let Some(p) = plc.as_mut() {
            // In service: the PLC drives DOCK and E-STOP.
            p.tick(name, &mut rig, &st, now);
            if p.done || now > max_ns {
                break;
            }
            continue;
        }
        // Drive the machine: start cycles while there are cycles to run.
        if st.state == State::Idle && st.cycles_completed < cycles {
            rig.ctrl.request(Request::StartCycle);
        }
        let done_nominal = st.state == State::Idle && st.cycles_completed >= cycles;
        if matches!(st.state, State::Faulted { .. }) {
            settle_until_ns.get_or_insert(now + 2_000_000_000);
        }
        if done_nominal || settle_until_ns.is_some_and(|t| now >= t) || now > max_ns {
            break;
        }
    }

    // `heavy-default`: a clear-fault must take the machine out of the cone, home.
    let recovered_after_clear = (name == "heavy-default").then(|| {
        let engage = rig.ctrl.config().machine.engage_um as f64;
        let cleared = rig.ctrl.command(Request::ClearFault).is_ok();
        let deadline = rig.clock.now_ns() + 60_000_000_000;
        while rig.ctrl.state() != State::Idle && rig.clock.now_ns() < deadline {
            each_tick(&mut rig, &mut tick_rng);
            rig.tick();
            while rig.ctrl.next_event().is_some() {}
        }
        cleared
            && rig.ctrl.state() == State::Idle
            && rig.axis.pos_um() < engage
            && rig.lock.fraction_locked() >= 1.0
            && !rig.axis.enabled()
    });
    for f in rig.ctrl.faults() {
        faults.push(FaultSeen {
            kind: f.kind.name(),
            cycle: f.cycle,
            phase: f.phase.map(ContactPhase::number),
            t_s: f.t_ms as f64 / 1000.0,
            peak_force_n: f.peak_force_mn as f64 / 1000.0,
        });
    }
    let st = rig.ctrl.status();
    let tripped = trip_pos_um.is_some();
    Ok(SceneReport {
        scene: name.to_string(),
        rate_sps: opts.rate_sps,
        seed: opts.seed,
        cycles_completed: st.cycles_completed,
        faults,
        peak_force_n: st.peak_force_mn as f64 / 1000.0,
        stop_latency_s,
        final_state: st.state.name(),
        insertion_phases,
        motors_disabled: !rig.axis.enabled() && !rig.lock.driven(),
        forward_after_trip_um: tripped.then_some(max_after.max(0.0)),
        backed_off_um: tripped.then_some((-min_after).max(0.0).min(BACK_OFF_UM as f64 + 100.0)),
        spikes_rejected: rig.kernel.spikes_rejected(),
        spikes_injected: spikes.delivered,
        control_steps: steps,
        sim_time_s: rig.clock.now_s(),
        wall_time_s: started.elapsed().as_secs_f64(),
        watchdog_bit: rig.wdg.check(),
        plc: plc.map(|p| p.rep),
        recovered_after_clear,
        signatures,
    })
}

/// A host rig a scripted scene runs step by step: each tick runs the scene's hook (a
/// flood, a trace) first and drains the controller's events into what the report needs.
struct Stepper<'a> {
    rig: Rig,
    each_tick: &'a mut dyn FnMut(&mut Rig, &mut Rng),
    rng: Rng,
    started: Instant,
    steps: u64,
    insertion_phases: Vec<Vec<u8>>,
    /// E-STOP edges the controller reported ([`Event::EstopEdges`]).
    estop_edges_latched: u32,
    signatures: Vec<crate::sigscene::SignatureSeen>,
}

impl<'a> Stepper<'a> {
    fn new(opts: SceneOptions, each_tick: &'a mut dyn FnMut(&mut Rig, &mut Rng)) -> Self {
        Self {
            rig: Rig::new(RigOptions {
                seed: opts.seed,
                adc: opts.adc,
                force_model: opts.force_model,
                tuning: opts.tuning,
                ..RigOptions::new(opts.rate_sps)
            }),
            each_tick,
            rng: Rng::new(opts.seed ^ 0xf100d),
            started: Instant::now(),
            steps: 0,
            insertion_phases: Vec::new(),
            estop_edges_latched: 0,
            signatures: Vec::new(),
        }
    }

    fn tick(&mut self) {
        (self.each_tick)(&mut self.rig, &mut self.rng);
        if self.rig.tick().stepped {
            self.steps += 1;
        }
        let inserting = matches!(self.rig.ctrl.state(), State::Inserting { .. });
        while let Some(ev) = self.rig.ctrl.next_event() {
            self.signatures
                .extend(crate::sigscene::SignatureSeen::of_event(&ev.event));
            match ev.event {
                Event::Seq(SeqEvent::CycleStarted(_)) => self.insertion_phases.push(Vec::new()),
                Event::Phase(p) if inserting => {
                    if let Some(v) = self.insertion_phases.last_mut() {
                        v.push(p.number());
                    }
                }
                Event::EstopEdges { edges, .. } => self.estop_edges_latched += edges,
                _ => {}
            }
        }
    }

    /// Tick for `ms` of virtual time.
    fn run_ms(&mut self, ms: u64) {
        let end = self.rig.clock.now_ns() + ms * 1_000_000;
        while self.rig.clock.now_ns() < end {
            self.tick();
        }
    }

    /// Tick until `pred` holds (checked after every tick) or `s` seconds have passed;
    /// whether it held.
    fn run_until(&mut self, s: u64, pred: impl Fn(&Rig) -> bool) -> bool {
        let end = self.rig.clock.now_ns() + s * 1_000_000_000;
        while !pred(&self.rig) {
            if self.rig.clock.now_ns() >= end {
                return false;
            }
            self.tick();
        }
        true
    }

    /// The machine's progress by the controller's status.
    fn progress(rig: &Rig) -> Progress {
        Progress::of_status(&rig.ctrl.status(), rig.ctrl.config().machine.engage_um)
    }

    /// Idle, homed, READY.
    fn ready(rig: &Rig) -> bool {
        rig.ctrl.state() == State::Idle && rig.ctrl.handshake().ready
    }

    /// The PLC sends `pdu` to unit 1 over Modbus (the server's own frame handling);
    /// the reply's PDU (empty: none). A command is acted on in the next control step.
    fn modbus(&mut self, pdu: &[u8]) -> Vec<u8> {
        use docking_logic::modbus::{crc16, handle_frame, MAX_FRAME};
        let mut f = vec![1u8];
        f.extend_from_slice(pdu);
        let crc = crc16(&f);
        f.extend_from_slice(&crc.to_le_bytes());
        let mut out = [0u8; MAX_FRAME];
        match handle_frame(&f, 1, &mut self.rig.ctrl, "scene", &mut out) {
            Some(n) if n >= 4 => out[1..n - 2].to_vec(),
            _ => Vec::new(),
        }
    }

    /// Write coil `coil` on: `Ok` (echoed) or the exception code.
    fn coil(&mut self, coil: u8) -> Result<(), u8> {
        let pdu = [0x05, 0, coil, 0xFF, 0x00];
        let r = self.modbus(&pdu);
        match r.as_slice() {
            r if r == pdu => Ok(()),
            [0x85, code] => Err(*code),
            _ => Err(0),
        }
    }

    /// The technician types `line` on the console; the reply.
    fn console(&mut self, line: &str) -> String {
        self.rig.command(line, 200)
    }

    fn report(self, name: &str, opts: SceneOptions, plc: PlcReport) -> SceneReport {
        let rig = &self.rig;
        let st = rig.ctrl.status();
        SceneReport {
            scene: name.to_string(),
            rate_sps: opts.rate_sps,
            seed: opts.seed,
            cycles_completed: st.cycles_completed,
            faults: rig
                .ctrl
                .faults()
                .map(|f| FaultSeen {
                    kind: f.kind.name(),
                    cycle: f.cycle,
                    phase: f.phase.map(ContactPhase::number),
                    t_s: f.t_ms as f64 / 1000.0,
                    peak_force_n: f.peak_force_mn as f64 / 1000.0,
                })
                .collect(),
            peak_force_n: st.peak_force_mn as f64 / 1000.0,
            stop_latency_s: None,
            final_state: st.state.name(),
            insertion_phases: self.insertion_phases,
            motors_disabled: !rig.axis.enabled() && !rig.lock.driven(),
            forward_after_trip_um: None,
            backed_off_um: None,
            spikes_rejected: rig.kernel.spikes_rejected(),
            spikes_injected: 0,
            control_steps: self.steps,
            sim_time_s: rig.clock.now_s(),
            wall_time_s: self.started.elapsed().as_secs_f64(),
            watchdog_bit: rig.wdg.check(),
            plc: Some(plc),
            recovered_after_clear: None,
            signatures: self.signatures,
        }
    }
}

/// `estop-bounce` on the host rig: the disturbances of [`ESTOP_BOUNCE`], each at its
/// stage of a docking the PLC asks for with DOCK; after each the PLC releases DOCK and
/// clears over Modbus (coil 2) once the input is closed; then one more dock.
fn estop_bounce(
    opts: SceneOptions,
    each_tick: &mut dyn FnMut(&mut Rig, &mut Rng),
) -> Result<SceneReport, String> {
    let mut x = Stepper::new(opts, each_tick);
    let mut rep = PlcReport {
        estop_episodes: Some(0),
        estop_edges_injected: Some(0),
        estop_faults_latched: Some(0),
        clears_accepted: Some(0),
        clears_refused_while_open: Some(0),
        ..PlcReport::default()
    };
    let inc = |c: &mut Option<u32>, n: u32| *c = Some(c.unwrap_or(0) + n);
    x.run_until(10, Stepper::ready);
    for (stage, d) in ESTOP_BOUNCE {
        if stage != Stage::Idle {
            x.rig.dock_line.set(false); // the PLC asserts DOCK
            let there = x.run_until(60, |r| {
                let p = Stepper::progress(r);
                p.stage == stage
                    && (stage != Stage::Inserting || p.depth_um >= ESTOP_BOUNCE_DEPTH_UM)
            });
            if !there {
                break; // the counts show the episodes that did not happen
            }
        }
        inc(&mut rep.estop_episodes, 1);
        match d {
            EstopDisturbance::Pulse(us) => x.rig.estop_pulse(u64::from(us)),
            EstopDisturbance::BouncingRelease => {
                x.rig.estop_line.set(true);
                x.run_ms(BOUNCE_OPEN_MS);
                if x.coil(2) == Err(0x01) {
                    inc(&mut rep.clears_refused_while_open, 1);
                }
                x.rig.estop_line.set(false);
                // (The rig is not interrupt-accurate: the closing edge is seen at the
                // next tick, the bounce's pulses now.)
                for us in BOUNCE_RELEASE_US {
                    x.rig.estop_pulse(u64::from(us));
                }
            }
        }
        inc(&mut rep.estop_edges_injected, d.edges());
        x.run_ms(100);
        let r = &x.rig;
        let h = r.ctrl.handshake();
        if r.ctrl.state()
            == (State::Faulted {
                fault: docking_logic::sequencer::FaultKind::EmergencyStop,
            })
            && h.fault
            && !h.ready
            && !r.axis.enabled()
            && !r.lock.driven()
        {
            inc(&mut rep.estop_faults_latched, 1);
        }
        x.rig.dock_line.set(true); // the PLC releases DOCK on the fault
        x.run_ms(100);
        if x.coil(2).is_ok() {
            inc(&mut rep.clears_accepted, 1);
        }
        x.run_until(60, Stepper::ready);
        x.run_ms(300);
    }
    rep.estop_edges_latched = Some(x.estop_edges_latched);
    // The next dock completes: mated, undocked, home.
    let before = x.rig.ctrl.status().cycles_completed;
    x.rig.dock_line.set(false);
    let mated = x.run_until(60, |r| r.ctrl.handshake().mated);
    x.rig.dock_line.set(true);
    let home = x.run_until(60, Stepper::ready);
    rep.docked_after_estops =
        Some(mated && home && x.rig.ctrl.status().cycles_completed == before + 1);
    Ok(x.report("estop-bounce", opts, rep))
}

/// `maintenance-lockout` on the host rig: a technician in maintenance mode at the
/// console; the PLC's Modbus dock and DOCK pin are refused and ignored, READY low; after
/// `maint exit` the PLC docks over Modbus and undocks.
fn maintenance_lockout(
    opts: SceneOptions,
    each_tick: &mut dyn FnMut(&mut Rig, &mut Rng),
) -> Result<SceneReport, String> {
    use docking_logic::modbus::{ir, status};
    let mut x = Stepper::new(opts, each_tick);
    let mut rep = PlcReport::default();
    x.run_until(10, Stepper::ready);
    let pin = x.console(&format!("pin set {SCENE_PIN}"));
    let maint = x.console(&format!("maint {SCENE_PIN}"));
    if !(pin.starts_with("ok") && maint.starts_with("ok")) {
        return Err(format!(
            "maintenance mode not entered: '{}' / '{}'",
            pin.trim(),
            maint.trim()
        ));
    }
    x.run_ms(50);
    let mut ready_low = !x.rig.ctrl.handshake().ready;
    let regs = x.modbus(&[0x04, 0, 0, 0, ir::MAINTENANCE_MODE as u8 + 1]);
    let word = |i: usize| {
        regs.get(2 + 2 * i..4 + 2 * i)
            .map(|b| u16::from_be_bytes([b[0], b[1]]))
    };
    rep.maintenance_shown = Some(
        word(0).is_some_and(|w| w & status::MAINTENANCE_MODE != 0)
            && word(usize::from(ir::MAINTENANCE_MODE)) == Some(1),
    );
    rep.modbus_dock_refused = Some(x.coil(0) == Err(0x01));
    // The DOCK pin, asserted for 2 s.
    x.rig.dock_line.set(false);
    let end = x.rig.clock.now_ns() + 2_000_000_000;
    let mut moved = false;
    while x.rig.clock.now_ns() < end {
        x.tick();
        moved |= x.rig.axis.enabled() || x.rig.lock.driven();
        ready_low &= !x.rig.ctrl.handshake().ready;
    }
    rep.dock_pin_ignored = Some(!moved && x.rig.ctrl.state() == State::Idle);
    rep.ready_low_in_maintenance = Some(ready_low);
    x.rig.dock_line.set(true);
    x.run_ms(200);
    let exit = x.console("maint exit").starts_with("ok");
    x.run_ms(100);
    let ready = Stepper::ready(&x.rig) && !x.rig.ctrl.maintenance_mode();
    let accepted = x.coil(0).is_ok();
    let mated = x.run_until(60, |r| r.ctrl.handshake().mated);
    let undock = x.coil(1).is_ok();
    let home = x.run_until(60, Stepper::ready);
    rep.docked_after_maintenance = Some(
        exit && ready
            && accepted
            && mated
            && undock
            && home
            && x.rig.ctrl.status().cycles_completed == 1,
    );
    Ok(x.report("maintenance-lockout", opts, rep))
}

/// A number for JSON: up to 6 decimals, trailing zeros trimmed; `null` if not finite.
pub fn num(x: f64) -> String {
    if x.is_finite() {
        let s = format!("{x:.6}");
        let s = s.trim_end_matches('0').trim_end_matches('.');
        if s.is_empty() || s == "-" {
            "0".into()
        } else {
            s.to_string()
        }
    } else {
        "null".into()
    }
}

impl SceneReport {
    /// One JSON object on one line.
    pub fn to_json(&self) -> String {
        let faults: Vec<String> = self
            .faults
            .iter()
            .map(|f| {
                format!(
                    "{{\"kind\":\"{}\",\"cycle\":{},\"phase\":{},\"t_s\":{},\"peak_force_n\":{}}}",
                    f.kind,
                    f.cycle,
                    f.phase.map_or("null".into(), |p| p.to_string()),
                    num(f.t_s),
                    num(f.peak_force_n)
                )
            })
            .collect();
        let phases: Vec<String> = self
            .insertion_phases
            .iter()
            .map(|v| format!("{v:?}").replace(' ', ""))
            .collect();
        let opt = |x: Option<f64>| x.map_or("null".to_string(), num);
        format!(
            "{{\"scene\":\"{}\",\"plc\":{},\"rate_sps\":{},\"seed\":{},\"cycles_completed\":{},\"faults\":[{}],\"peak_force_n\":{},\"stop_latency_s\":{},\"final_state\":\"{}\",\"motors_disabled\":{},\"insertion_phases\":[{}],\"forward_after_trip_um\":{},\"backed_off_um\":{},\"spikes_injected\":{},\"spikes_rejected\":{},\"control_steps\":{},\"sim_time_s\":{},\"wall_time_s\":{},\"watchdog_bit\":{},\"recovered_after_clear\":{},\"signatures\":[{}]}}",
            self.scene,
            self.plc
                .as_ref()
                .map_or("null".to_string(), PlcReport::to_json),
            self.rate_sps,
            self.seed,
            self.cycles_completed,
            faults.join(","),
            num(self.peak_force_n),
            opt(self.stop_latency_s),
            self.final_state,
            self.motors_disabled,
            phases.join(","),
            opt(self.forward_after_trip_um),
            opt(self.backed_off_um),
            self.spikes_injected,
            self.spikes_rejected,
            self.control_steps,
            num(self.sim_time_s),
            num(self.wall_time_s),
            self.watchdog_bit,
            self.recovered_after_clear
                .map_or("null".to_string(), |b| b.to_string()),
            self.signatures
                .iter()
                .map(crate::sigscene::SignatureSeen::to_json)
                .collect::<Vec<_>>()
                .join(",")
        )
    }

    /// What the scene is meant to show, and whether this run showed it.
    /// `cycles_requested`: the run's `--cycles`.
    pub fn verdict(&self, cycles_requested: u32) -> Verdict {
        // The fault each fault scene exists to provoke (none: a clean run).
        let fault = match self.scene.as_str() {
            "overload" | "heavy-default" => Some("overload"),
            "disconnect" => Some("sensor_disconnected"),
            "saturation" => Some("sensor_saturated"),
            "stuck" => Some("sensor_stuck"),
            "bad-tare" => Some("implausible_tare"),
            "stall" => Some("axis_stall"),
            "lock-stuck" => Some("lock_not_released"),
            "vehicle-pull" => Some("hold_force"),
            "estop" | "estop-bounce" => Some("emergency_stop"),
            _ => None,
        };
        // Scenes that clear the fault and dock again.
        let recovers = matches!(
            self.scene.as_str(),
            "estop" | "estop-bounce" | "heavy-default"
        );
        let mut v = Verdict::default();
        let mut check = |ok: bool, what: String| {
            v.expected.push(what.clone());
            if !ok {
                v.failed.push(what);
            }
        };
        check(!self.watchdog_bit, "the watchdog never fires".into());
        match fault {
            None => {
                check(self.faults.is_empty(), "no fault".into());
                check(
                    self.cycles_completed == cycles_requested,
                    format!("{cycles_requested} cycle(s) completed"),
                );
            }
            Some(f) => {
                let kinds_ok = !self.faults.is_empty() && self.faults.iter().all(|x| x.kind == f);
                check(kinds_ok, format!("{f} latched (and no other fault)"));
                if recovers {
                    check(
                        self.cycles_completed >= 1,
                        "a docking completes after the clear".into(),
                    );
                }
            }
        }
        let final_state = if fault.is_some() && !recovers {
            "faulted"
        } else {
            "idle"
        };
        check(
            self.final_state == final_state,
            format!("ends {final_state}"),
        );
        if self.scene == "vehicle-pull" {
            check(
                self.plc.as_ref().and_then(|p| p.axis_held) == Some(true),
                "the axis holds the vehicle".into(),
            );
        } else {
            check(self.motors_disabled, "every motor off at the end".into());
        }
        if fault == Some("overload") {
            check(
                self.backed_off_um.is_some_and(|b| b >= 1_900.0),
                "the back-off (2 mm) done".into(),
            );
        }
        if self.scene == "overload" {
            let period_s = 1.0 / self.rate_sps.max(1) as f64;
            check(
                self.stop_latency_s.is_some_and(|l| l <= period_s),
                "stopped within one sample".into(),
            );
        }
        crate::sigscene::check(
            &self.scene,
            &self.signatures,
            cycles_requested,
            1,
            &mut check,
        );
        if let Some(p) = &self.plc {
            let failed: Vec<&str> = p
                .flags()
                .into_iter()
                .filter(|&(_, b)| b == Some(false))
                .map(|(k, _)| k)
                .collect();
            check(
                failed.is_empty(),
                if failed.is_empty() {
                    "every PLC check holds".into()
                } else {
                    format!("every PLC check holds (failed: {})", failed.join(", "))
                },
            );
        }
        v
    }

    /// A short human summary.
    pub fn to_text(&self) -> String {
        let mut s = format!(
            "scene {}: {} cycle(s) completed at {} SPS, final state {}, peak force {:.2} N\n",
            self.scene, self.cycles_completed, self.rate_sps, self.final_state, self.peak_force_n
        );
        for f in &self.faults {
            s += &format!(
                "  fault {} in cycle {} phase {} at t = {:.3} s (peak {:.2} N)\n",
                f.kind,
                f.cycle,
                f.phase.map_or("-".into(), |p| p.to_string()),
                f.t_s,
                f.peak_force_n
            );
        }
        if let Some(l) = self.stop_latency_s {
            s += &format!(
                "  stop latency {:.6} s (sample period {:.6} s)\n",
                l,
                1.0 / self.rate_sps as f64
            );
        }
        if self.spikes_injected > 0 || self.spikes_rejected > 0 {
            s += &format!(
                "  spikes: {} delivered in samples the controller read, {} rejected by the guard\n",
                self.spikes_injected, self.spikes_rejected
            );
        }
        if let Some(p) = &self.plc {
            s += &format!("  plc: {}\n", p.to_text());
        }
        if !self.signatures.is_empty() {
            let nok: Vec<String> = self
                .signatures
                .iter()
                .filter(|x| !x.ok)
                .map(|x| format!("{} {} {}", x.cycle, x.stroke, x.failed.unwrap_or("?")))
                .collect();
            s += &format!(
                "  signatures: {} strokes judged, {} NOK{}\n",
                self.signatures.len(),
                nok.len(),
                if nok.is_empty() {
                    String::new()
                } else {
                    format!(" ({})", nok.join("; "))
                }
            );
        }
        s += &format!(
            "  motors disabled: {}; {} control steps, {:.1} s simulated in {:.3} s",
            self.motors_disabled, self.control_steps, self.sim_time_s, self.wall_time_s
        );
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A tally over spikes at conversions 2 and 5, fed conversions as an HX711 would
    /// report them (time ns = 10 × number).
    #[test]
    fn only_spikes_in_conversions_read_are_delivered() {
        let mut t = SpikeTally {
            at: vec![2, 5, 9],
            ..SpikeTally::default()
        };
        let conv = |n: u64, read: bool| (10 * n, 0, read);
        // Conversions 0–2 complete; 2 (a spike) is not read yet.
        t.observe(3, &[conv(0, true), conv(1, true), conv(2, false)]);
        assert_eq!(t.delivered, 0);
        // Now it is read.
        t.observe(3, &[conv(0, true), conv(1, true), conv(2, true)]);
        assert_eq!(t.delivered, 1);
        // 3–6 complete together; 5 (a spike) was never read, 6 replaced it.
        let recent: Vec<_> = (0..7).map(|n| conv(n, n != 5)).collect();
        t.observe(7, &recent);
        assert_eq!(t.delivered, 1, "a spike in a conversion nobody read");
        // 9 is scheduled past the end of the run: never delivered.
        assert!(!t.due(7));
    }
}
