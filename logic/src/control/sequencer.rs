//! The docking sequencer: a pure step function.
//!
//! # Theory of operation
//!
//! [`Sequencer::step`] takes the time and everything the controller measured in this
//! control step ([`Inputs`]) and returns what the motors must do ([`Outputs`]). It reads
//! no clock and touches no I/O, so it is tested by feeding it timelines. Every state that
//! moves something carries its own deadline; a motion that misses it, or a switch that
//! disagrees with the motion, is a named [`FaultKind`]. Faults **latch**: the only ways
//! out are the automatic, controlled back-off after an overload and an explicit
//! [`Request::ClearFault`], which starts a recovery to home.
//!
//! **Nothing moves after a reset until someone asks.** At power-up (any reset: the
//! panel may be inside the cone) the sequencer waits in `PowerUp`. Only when the home
//! and locked switches are both closed does it zero there and go idle, moving nothing.
//! Otherwise a [`Request::Home`] or a [`Request::StartCycle`] (console, dock-request
//! input) starts the homing; the cycle itself then needs a request of its own.
//!
//! **In service** a [`Request::Dock`] docks and holds — minutes or hours — until a
//! [`Request::Undock`]; a **test cycle** ([`Request::StartCycle`], for life and endurance
//! runs) holds `hold_ms` and undocks by itself. An undock before the rod reaches the
//! cone returns without counting a cycle; during the insertion it turns into a
//! controlled extraction from where the rod is (counted: an insertion and an
//! extraction). From the hold, MATED is dropped first and the extraction starts
//! [`UNMATE_MS`] later. A [`Request::Stop`] latches [`FaultKind::Stopped`] from any
//! state.
//!
//! **Pulled while mated** ([`FaultKind::HoldForce`], detected by the controller against
//! the hold envelope): the connectors may be energised and the vehicle moving. The
//! reaction is to drop MATED (the PLC de-energises on it), latch the fault and **hold the
//! axis where it is, driven**: extracting on its own would pull live connectors apart
//! under load, and a free-wheeling axis would let the vehicle drag the panel. The force
//! limits keep running (an overload still disables the propulsion at the sample); the
//! way out is a person's clear, which extracts under control.
//!
//! One docking cycle is one insertion and one extraction:
//!
//! ```text
//!  PowerUp ─(home and locked sw: zero, no motion)───────────────────▶ Idle
//!  PowerUp ─(Home / StartCycle request)─▶ Homing ─(home sw)─▶ Locking ─(locked sw)─▶ Idle ◀┐
//!                                                        │ StartCycle (home, locked)     │
//!                                                        ▼                               │
//!   PreAlign (locked, fast, to engage) ─▶ Releasing (lock → released sw)                 │
//!        ─▶ Inserting (compliant, ≤ v0, phases 1→2→3→4, to mated) ─▶ Holding (hold_ms │
//!                                                      or, docked, until Undock)        │
//!        ─▶ Extracting (≤ v0, to engage) ─▶ Locking (→ locked sw) ─▶ Returning (fast to ─┘
//!                                               0.5 mm, then creeping onto the home sw)
//!
//!  any state ──fault──▶ Faulted (motors off, latched)
//!  moving, overload ──▶ BackingOff (retreat `back_off_um` at ≤ v0; cut only by a load rising past the trip's) ─▶ Faulted
//!  Faulted ──ClearFault──▶ Recovering (to engage at ≤ v0) ─▶ Locking ─▶ Returning ─▶ Idle
//! ```
//!
//! The sequencer is told about overloads and sensor faults (detected by the guard in the
//! same control step, which has already switched the propulsion off); it detects motion
//! faults itself: deadlines, a home switch that does not close where the counted position
//! says home is, the end (overtravel) switch, contradictory switches.

use crate::config::MachineConfig;
use crate::lock::LockCmd;

/// A latched fault.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum FaultKind {
    /// Contact force over the hard limit or the phase envelope.
    Overload,
    /// No load-cell sample for 3 sample periods.
    SensorDisconnected,
    /// Load-cell samples at an ADC rail.
    SensorSaturated,
    /// Load-cell converter stuck on one code.
    SensorStuck,
    /// Zero-load reading far from the calibration (or beyond a quarter of full scale).
    ImplausibleTare,
    /// The axis did not reach its position or switch by its deadline (stall, jam, or a
    /// dead home switch).
    AxisStall,
    /// The overtravel (end) switch closed.
    Overtravel,
    /// The lock did not reach its released switch by the deadline.
    LockNotReleased,
    /// The lock did not reach its locked switch by the deadline.
    LockNotLocked,
    /// Two switches that exclude each other are both closed.
    SwitchConflict,
    /// A pin or driver could not be read or driven.
    Io,
    /// A pulling force beyond the tension limit, or a load cell bridge wired in reverse
    /// (compression reading negative).
    Tension,
    /// The odometer's flash refused a record [`crate::controller::STORAGE_ATTEMPTS`]
    /// times in a row: wear would go unrecorded, so no new cycle starts (the counters
    /// are kept in RAM; clearing the fault tries again).
    Storage,
    /// The E-STOP input opened (pressed, or its wire broken): propulsion and lock off at
    /// once. Clearing needs the input closed again.
    EmergencyStop,
    /// A `stop` request (console, PLC): all motion stopped, latched.
    Stopped,
    /// While mated, the contact force left the hold envelope (the vehicle pulling or
    /// drifting): MATED drops, the axis holds where it is (see the theory of operation).
    HoldForce,
    /// The propulsion's stop latch held the driver off for a stop the controller could
    /// not account for (a safety event it never received): latched as a fault rather
    /// than a silent stall.
    UnseenStop,
}

impl FaultKind {
    /// Stable snake-case name (logs, JSON, console).
    pub const fn name(self) -> &'static str {
        match self {
            Self::Overload => "overload",
            Self::SensorDisconnected => "sensor_disconnected",
            Self::SensorSaturated => "sensor_saturated",
            Self::SensorStuck => "sensor_stuck",
            Self::ImplausibleTare => "implausible_tare",
            Self::AxisStall => "axis_stall",
            Self::Overtravel => "overtravel",
            Self::LockNotReleased => "lock_not_released",
            Self::LockNotLocked => "lock_not_locked",
            Self::SwitchConflict => "switch_conflict",
            Self::Io => "io",
            Self::Tension => "tension",
            Self::Storage => "storage",
            Self::EmergencyStop => "emergency_stop",
            Self::Stopped => "stopped",
            Self::HoldForce => "hold_force",
            Self::UnseenStop => "unseen_stop",
        }
    }

    /// Persisted code.
    pub const fn code(self) -> u8 {
        self as u8
    }

    /// From a persisted code.
    pub const fn from_code(c: u8) -> Option<Self> {
        Some(match c {
            0 => Self::Overload,
            1 => Self::SensorDisconnected,
            2 => Self::SensorSaturated,
            3 => Self::SensorStuck,
            4 => Self::ImplausibleTare,
            5 => Self::AxisStall,
            6 => Self::Overtravel,
            7 => Self::LockNotReleased,
            8 => Self::LockNotLocked,
            9 => Self::SwitchConflict,
            10 => Self::Io,
            11 => Self::Tension,
            12 => Self::Storage,
            13 => Self::EmergencyStop,
            14 => Self::Stopped,
            15 => Self::HoldForce,
            16 => Self::UnseenStop,
            _ => return None,
        })
    }
}

/// The switches, `true` = closed.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Switches {
    /// Axis at home.
    pub home: bool,
    /// Axis at the overtravel limit.
    pub end: bool,
    /// Lock fully locked.
    pub locked: bool,
    /// Lock fully released.
    pub released: bool,
}

impl Switches {
    /// One bit per switch (home, end, locked, released from bit 0 up), `1` = closed.
    pub const fn bits(self) -> u8 {
        self.home as u8
            | (self.end as u8) << 1
            | (self.locked as u8) << 2
            | (self.released as u8) << 3
    }

    /// The switches of [`Self::bits`].
    pub const fn from_bits(bits: u8) -> Self {
        Self {
            home: bits & 1 != 0,
            end: bits & 2 != 0,
            locked: bits & 4 != 0,
            released: bits & 8 != 0,
        }
    }
}

/// Requests from outside the control loop (console, scene, start button).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Request {
    /// Run one test cycle: dock, hold `hold_ms`, undock (accepted in `Idle` only; life
    /// and endurance runs).
    StartCycle,
    /// Dock and stay mated until [`Request::Undock`] (accepted in `Idle`).
    Dock,
    /// Undock: from the hold, or abort a docking under way and return (accepted while
    /// docking or mated).
    Undock,
    /// Stop all motion now; latches [`FaultKind::Stopped`] (accepted in any state but a
    /// latched fault).
    Stop,
    /// Clear a latched fault and recover to home (accepted in `Faulted` only).
    ClearFault,
    /// Find home and lock (accepted in `PowerUp` only: after a reset nothing moves
    /// without a request).
    Home,
}

/// What the controller measured in this control step.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Inputs {
    /// Time, ms since boot.
    pub now_ms: u64,
    /// Counted axis position, µm from home.
    pub pos_um: i32,
    /// The propulsion has reached its target and stands still.
    pub axis_idle: bool,
    /// Switch states.
    pub switches: Switches,
    /// A fault the guard or the drivers detected in this step.
    pub fault: Option<FaultKind>,
    /// A request to act on.
    pub request: Option<Request>,
}

/// What the propulsion must do.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum AxisCmd {
    /// Power stage off.
    Disabled,
    /// Enabled, standing still (stop at once if moving).
    Hold,
    /// Enabled, move to `target_um` at no more than `speed_um_per_s`.
    Move {
        /// Target, µm from home.
        target_um: i32,
        /// Speed limit, µm/s.
        speed_um_per_s: u32,
    },
}

/// Something worth logging and counting.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum SeqEvent {
    /// The home switch closed: the counted position is now 0.
    Homed,
    /// A docking cycle started (its 1-based number).
    CycleStarted(u32),
    /// A docking cycle completed (its 1-based number).
    CycleCompleted(u32),
    /// A fault latched.
    Fault(FaultKind),
    /// The fault was cleared by request; recovery begins.
    FaultCleared,
    /// A request that the current state does not accept.
    RequestRefused(Request),
}

/// Outputs of one step.
#[must_use]
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Outputs {
    /// Propulsion command.
    pub axis: AxisCmd,
    /// Lock command.
    pub lock: LockCmd,
    /// The counted position must be set to 0 (home switch just closed).
    pub zero_position: bool,
    /// Event of this step.
    pub event: Option<SeqEvent>,
}

/// Where a lock motion leads.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum AfterLock {
    /// Power-up: then idle.
    Idle,
    /// End of a cycle or a recovery: then return home.
    Return,
}

/// Sequencer state. Every moving state carries its deadline (ms since boot).
///
/// `repr(u8)`: a tag byte of its own, so the step's many matches on the state read it
/// directly (without it the tag shares a word with `Holding`'s `Option` and every match
/// first decodes it).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum State {
    /// Just booted: position unknown; nothing moves until a home or dock request.
    PowerUp,
    /// Searching the home switch (toward −, at ≤ v0: the panel may be in the cone).
    Homing {
        /// Deadline, ms.
        deadline_ms: u64,
    },
    /// Driving the lock to its locked switch.
    Locking {
        /// Deadline, ms.
        deadline_ms: u64,
        /// What follows.
        then: AfterLock,
    },
    /// Homed and locked, motors off, waiting for a start.
    Idle,
    /// Locked panel advancing fast to the engagement point.
    PreAlign {
        /// Deadline, ms.
        deadline_ms: u64,
    },
    /// Releasing the lock for the compliant phase.
    Releasing {
        /// Deadline, ms.
        deadline_ms: u64,
    },
    /// Compliant insertion through the four contact phases.
    Inserting {
        /// Deadline, ms.
        deadline_ms: u64,
    },
    /// Mated; holding until `until_ms` (a test cycle), or until undock is requested
    /// (`None`: in service).
    Holding {
        /// End of the hold, ms.
        until_ms: Option<u64>,
        /// Undock requested: the connectors are no longer reported mated; extraction
        /// starts at `until_ms`.
        unmating: bool,
    },
    /// Compliant extraction back to the engagement point.
    Extracting {
        /// Deadline, ms.
        deadline_ms: u64,
    },
    /// Locked panel returning to the home switch: fast to `HOME_APPROACH_UM`, then
    /// creeping onto the switch (so the switch is met at creep speed: the position error
    /// of zeroing is at most one control period of creep travel).
    Returning {
        /// Deadline, ms.
        deadline_ms: u64,
        /// Whether this return ends a docking cycle (else a recovery).
        ends_cycle: bool,
        /// In the creep phase.
        creeping: bool,
    },
    /// Controlled retreat after an overload.
    BackingOff {
        /// Deadline, ms.
        deadline_ms: u64,
        /// Retreat target, µm.
        target_um: i32,
    },
    /// Latched fault: motors off.
    Faulted {
        /// The fault.
        fault: FaultKind,
    },
    /// After a clear: compliant retreat to the engagement point.
    Recovering {
        /// Deadline, ms.
        deadline_ms: u64,
    },
}

impl State {
    /// Every state's stable snake-case name, in [`Self::ordinal`] order.
    pub const NAMES: [&'static str; 13] = [
        "power_up",
        "homing",
        "locking",
        "idle",
        "pre_align",
        "releasing",
        "inserting",
        "holding",
        "extracting",
        "returning",
        "backing_off",
        "faulted",
        "recovering",
    ];

    /// The state's index in [`Self::NAMES`] (one byte: the board publishes it to the
    /// console with a single atomic store).
    pub const fn ordinal(&self) -> u8 {
        match self {
            Self::PowerUp => 0,
            Self::Homing { .. } => 1,
            Self::Locking { .. } => 2,
            Self::Idle => 3,
            Self::PreAlign { .. } => 4,
            Self::Releasing { .. } => 5,
            Self::Inserting { .. } => 6,
            Self::Holding { .. } => 7,
            Self::Extracting { .. } => 8,
            Self::Returning { .. } => 9,
            Self::BackingOff { .. } => 10,
            Self::Faulted { .. } => 11,
            Self::Recovering { .. } => 12,
        }
    }

    /// Stable snake-case name.
    pub const fn name(&self) -> &'static str {
        // In range: `ordinal` is at most 12, and `NAMES` has 13 entries.
        #[allow(clippy::indexing_slicing)]
        Self::NAMES[self.ordinal() as usize]
    }

    /// Whether the propulsion may be moving in this state.
    pub const fn is_moving(&self) -> bool {
        matches!(
            self,
            Self::Homing { .. }
                | Self::PreAlign { .. }
                | Self::Inserting { .. }
                | Self::Extracting { .. }
                | Self::Returning { .. }
                | Self::BackingOff { .. }
                | Self::Recovering { .. }
        )
    }

    /// Whether a docking is under way or held (an undock request applies).
    pub const fn is_docking(&self) -> bool {
        matches!(
            self,
            Self::PreAlign { .. }
                | Self::Releasing { .. }
                | Self::Inserting { .. }
                | Self::Holding { .. }
        )
    }

    /// Whether the rod may be in the cone (compliant states).
    pub const fn in_compliant_motion(&self) -> bool {
        matches!(
            self,
            Self::Inserting { .. }
                | Self::Holding { .. }
                | Self::Extracting { .. }
                | Self::BackingOff { .. }
                | Self::Recovering { .. }
        )
    }
}

/// Retreat after an overload, µm.
pub const BACK_OFF_UM: i32 = 2_000;
/// How far past the counted home the search goes before it gives up, µm.
pub const HOME_OVERSHOOT_UM: i32 = 3_000;
/// Where the fast return hands over to the creep onto the home switch, µm.
pub const HOME_APPROACH_UM: i32 = 500;
/// Creep speed onto the home switch, µm/s (5 µm per control period at 80 SPS).
pub const HOME_CREEP_UM_PER_S: u32 = 400;
/// Between an undock request and the start of the extraction: MATED is already low
/// (the PLC de-energises the connectors on it), ms.
pub const UNMATE_MS: u64 = 200;

/// The sequencer.
#[derive(Clone, Debug)]
pub struct Sequencer {
    cfg: MachineConfig,
    state: State,
    cycles_completed: u32,
    cycle_in_progress: u32,
    /// The cycle under way is a service docking (hold until undock), not a test cycle.
    service: bool,
    /// The cycle under way reached the cone (its compliant insertion began): only such a
    /// cycle counts as one when its return ends ([`State::Returning`]'s `ends_cycle`).
    /// A docking stopped before the cone (an undock, a fault and its clear in the
    /// pre-alignment or the release) counts nothing (issue 32; docs/board.md, "What
    /// holds between the steps").
    reached_cone: bool,
}

impl Sequencer {
    /// A sequencer at power-up.
    pub const fn new(cfg: MachineConfig) -> Self {
        Self {
            cfg,
            state: State::PowerUp,
            cycles_completed: 0,
            cycle_in_progress: 0,
            service: false,
            reached_cone: false,
        }
    }

    /// Current state.
    pub const fn state(&self) -> State {
        self.state
    }

    /// Cycles completed since boot.
    pub const fn cycles_completed(&self) -> u32 {
        self.cycles_completed
    }

    /// The cycle in progress or last started (1-based; 0 = none yet).
    pub const fn cycle_number(&self) -> u32 {
        self.cycle_in_progress
    }

    /// Deadline for a move of `dist_um` at `speed`: travel time ×1.5 + ramps + slack.
    // Out of line: nine transitions start a move, once each; inlined at each (a copy
    // with its two 64-bit divisions), the image is 592 B larger (issue 31's
    // measurement, which kept this hint and dropped the ones under 256 B).
    #[inline(never)]
    fn move_deadline(&self, now_ms: u64, dist_um: i32, speed_um_per_s: u32) -> u64 {
        let speed = speed_um_per_s.max(1) as u64;
        let travel_ms = dist_um.unsigned_abs() as u64 * 1000 / speed;
        let ramp_ms = speed * 1000 / self.cfg.accel_um_per_s2.max(1) as u64;
        now_ms + travel_ms * 3 / 2 + 2 * ramp_ms + self.cfg.move_slack_ms as u64
    }

    fn lock_deadline(&self, now_ms: u64) -> u64 {
        now_ms + self.cfg.lock_deadline_ms as u64
    }

    fn fault(&mut self, fault: FaultKind, inp: &Inputs) -> (State, Option<SeqEvent>) {
        // An overload while the axis may be moving is answered with a controlled retreat.
        if fault == FaultKind::Overload
            && self.state.is_moving()
            && !matches!(self.state, State::BackingOff { .. })
        {
            let target_um = inp.pos_um - BACK_OFF_UM;
            let deadline_ms =
                self.move_deadline(inp.now_ms, BACK_OFF_UM, self.cfg.dock_speed_um_per_s);
            return (
                State::BackingOff {
                    deadline_ms,
                    target_um,
                },
                Some(SeqEvent::Fault(fault)),
            );
        }
        (State::Faulted { fault }, Some(SeqEvent::Fault(fault)))
    }

    fn start_return(&self, now_ms: u64, pos_um: i32, ends_cycle: bool) -> State {
        if pos_um <= HOME_APPROACH_UM {
            return self.start_creep(now_ms, ends_cycle);
        }
        let deadline_ms = self.move_deadline(
            now_ms,
            pos_um - HOME_APPROACH_UM,
            self.cfg.fast_speed_um_per_s,
        );
        State::Returning {
            deadline_ms,
            ends_cycle,
            creeping: false,
        }
    }

    fn start_creep(&self, now_ms: u64, ends_cycle: bool) -> State {
        let deadline_ms = self.move_deadline(
            now_ms,
            HOME_APPROACH_UM + HOME_OVERSHOOT_UM,
            HOME_CREEP_UM_PER_S,
        );
        State::Returning {
            deadline_ms,
            ends_cycle,
            creeping: true,
        }
    }

    /// One control step.
    pub fn step(&mut self, inp: &Inputs) -> Outputs {
        let sw = inp.switches;

        // Faults first: reported ones, then the switch checks that hold in every state.
        let switch_fault = if (sw.home && sw.end) || (sw.locked && sw.released) {
            Some(FaultKind::SwitchConflict)
        } else if sw.end {
            Some(FaultKind::Overtravel)
        } else {
            None
        };
        let stop = (inp.request == Some(Request::Stop)).then_some(FaultKind::Stopped);
        let detected = inp.fault.or(switch_fault).or(stop);
        // (Without one, the usual step, the state's own transition below.)
        let next = match detected {
            None => None,
            Some(f) => match self.state {
                // Pulled while mated holds the axis driven: any further fault (an
                // E-STOP, an overload, a stop) takes its place and turns the axis off.
                State::Faulted {
                    fault: FaultKind::HoldForce,
                } if f != FaultKind::HoldForce => {
                    Some((State::Faulted { fault: f }, Some(SeqEvent::Fault(f))))
                }
                // An E-STOP replaces any other latched fault (it is the one a clear
                // must wait for: the input closed again).
                State::Faulted { fault } if f == FaultKind::EmergencyStop && fault != f => {
                    Some((State::Faulted { fault: f }, Some(SeqEvent::Fault(f))))
                }
                // Latched: only a clear gets out, and **not in a step that detects a
                // fault**. A clear accepted before an E-STOP edge (or any other fault)
                // that reaches the step with it is refused here, never run past the
                // fault it has not seen (issue 32: the pulse's edges were consumed by
                // the step that ran the clear, and the machine moved; docs/board.md,
                // "What holds between the steps", rule 1). The state is written back
                // unchanged so that `transition` does not run.
                State::Faulted { .. } => Some((self.state, None)),
                // Any fault (a stop included) ends the controlled retreat of an overload.
                State::BackingOff { .. } => {
                    Some((State::Faulted { fault: f }, Some(SeqEvent::Fault(f))))
                }
                _ => Some(self.fault(f, inp)),
            },
        };
        // The state is written only when it changes (most steps it stays).
        let (mut event, zero_position) = match next {
            Some((s, e)) => {
                self.state = s;
                (e, false)
            }
            None => match self.transition(inp) {
                Some((s, e, zero)) => {
                    self.state = s;
                    (e, zero)
                }
                None => (None, false),
            },
        };

        if let (Some(r), None) = (inp.request, event) {
            let accepted = matches!(
                (r, self.state),
                (Request::StartCycle | Request::Dock, State::PreAlign { .. })
                    | (Request::Stop, State::Faulted { .. })
                    | (
                        Request::Undock,
                        State::Holding { unmating: true, .. }
                            | State::Extracting { .. }
                            | State::Locking { .. }
                            | State::Returning { .. }
                    )
                    | (
                        Request::Home | Request::StartCycle | Request::Dock,
                        State::Homing { .. } | State::Locking { .. }
                    )
                    | (
                        Request::ClearFault,
                        State::Recovering { .. } | State::Locking { .. } | State::Returning { .. }
                    )
            );
            if !accepted {
                event = Some(SeqEvent::RequestRefused(r));
            }
        }

        let (axis, lock) = self.commands(inp.pos_um);
        Outputs {
            axis,
            lock,
            zero_position,
            event,
        }
    }

    /// What the propulsion and the lock do in the current state (at `pos_um`).
    fn commands(&self, pos_um: i32) -> (AxisCmd, LockCmd) {
        let cfg = &self.cfg;
        match self.state {
            // Pulled while mated: stay put, driven (no free-wheeling with the connectors
            // under load), until a person decides (clear: a controlled extraction).
            State::Faulted {
                fault: FaultKind::HoldForce,
            } => (AxisCmd::Hold, LockCmd::Off),
            State::PowerUp | State::Idle | State::Faulted { .. } => {
                (AxisCmd::Disabled, LockCmd::Off)
            }
            State::Homing { .. } => (
                AxisCmd::Move {
                    target_um: pos_um.saturating_sub(cfg.end_switch_um + HOME_OVERSHOOT_UM),
                    speed_um_per_s: cfg.dock_speed_um_per_s,
                },
                LockCmd::Off,
            ),
            State::Locking { .. } => (AxisCmd::Hold, LockCmd::ToLocked),
            State::PreAlign { .. } => (
                AxisCmd::Move {
                    target_um: cfg.engage_um,
                    speed_um_per_s: cfg.fast_speed_um_per_s,
                },
                LockCmd::Off,
            ),
            State::Releasing { .. } => (AxisCmd::Hold, LockCmd::ToReleased),
            State::Inserting { .. } => (
                AxisCmd::Move {
                    target_um: cfg.mated_um(),
                    speed_um_per_s: cfg.dock_speed_um_per_s,
                },
                LockCmd::Off,
            ),
            State::Holding { .. } => (AxisCmd::Hold, LockCmd::Off),
            State::Extracting { .. } | State::Recovering { .. } => (
                AxisCmd::Move {
                    target_um: cfg.engage_um,
                    speed_um_per_s: cfg.dock_speed_um_per_s,
                },
                LockCmd::Off,
            ),
            State::Returning {
                creeping: false, ..
            } => (
                AxisCmd::Move {
                    target_um: HOME_APPROACH_UM,
                    speed_um_per_s: cfg.fast_speed_um_per_s,
                },
                LockCmd::Off,
            ),
            State::Returning { creeping: true, .. } => (
                AxisCmd::Move {
                    target_um: -HOME_OVERSHOOT_UM,
                    speed_um_per_s: HOME_CREEP_UM_PER_S,
                },
                LockCmd::Off,
            ),
            State::BackingOff { target_um, .. } => (
                AxisCmd::Move {
                    target_um,
                    speed_um_per_s: cfg.dock_speed_um_per_s,
                },
                LockCmd::Off,
            ),
        }
    }

    /// The fault-free transition of the current state: `None` when it stays as it is
    /// (the usual step), without a copy of it.
    fn transition(&mut self, inp: &Inputs) -> Option<(State, Option<SeqEvent>, bool)> {
        let now = inp.now_ms;
        let sw = inp.switches;
        let cfg = self.cfg;
        let past = |deadline_ms: u64| now > deadline_ms;
        let to = |s: State| Some((s, None, false));
        let fault =
            |f: FaultKind| Some((State::Faulted { fault: f }, Some(SeqEvent::Fault(f)), false));
        match self.state {
            // Home and locked already: zero here and idle, moving nothing at all.
            State::PowerUp if sw.home && sw.locked => {
                Some((State::Idle, Some(SeqEvent::Homed), true))
            }
            // Anything else needs a request: the panel may be inside the cone.
            State::PowerUp => match inp.request {
                Some(Request::Home | Request::StartCycle | Request::Dock) if sw.home => Some((
                    State::Locking {
                        deadline_ms: self.lock_deadline(now),
                        then: AfterLock::Idle,
                    },
                    Some(SeqEvent::Homed),
                    true,
                )),
                Some(Request::Home | Request::StartCycle | Request::Dock) => {
                    let deadline_ms = self.move_deadline(
                        now,
                        cfg.end_switch_um + HOME_OVERSHOOT_UM,
                        cfg.dock_speed_um_per_s,
                    );
                    Some((State::Homing { deadline_ms }, None, false))
                }
                _ => None,
            },
            State::Homing { deadline_ms } => {
                if sw.home {
                    Some((
                        State::Locking {
                            deadline_ms: self.lock_deadline(now),
                            then: AfterLock::Idle,
                        },
                        Some(SeqEvent::Homed),
                        true,
                    ))
                } else if past(deadline_ms) || inp.axis_idle {
                    fault(FaultKind::AxisStall)
                } else {
                    None
                }
            }
            State::Locking { deadline_ms, then } => {
                if sw.locked {
                    match then {
                        AfterLock::Idle => to(State::Idle),
                        AfterLock::Return => Some((
                            self.start_return(
                                now,
                                inp.pos_um,
                                self.reached_cone && self.cycle_in_progress > self.cycles_completed,
                            ),
                            None,
                            false,
                        )),
                    }
                } else if past(deadline_ms) {
                    fault(FaultKind::LockNotLocked)
                } else {
                    None
                }
            }
            State::Idle => match inp.request {
                Some(r @ (Request::StartCycle | Request::Dock)) if sw.home && sw.locked => {
                    self.service = r == Request::Dock;
                    self.reached_cone = false;
                    self.cycle_in_progress = self.cycles_completed.saturating_add(1);
                    let deadline_ms = self.move_deadline(
                        now,
                        cfg.engage_um - inp.pos_um,
                        cfg.fast_speed_um_per_s,
                    );
                    Some((
                        State::PreAlign { deadline_ms },
                        Some(SeqEvent::CycleStarted(self.cycle_in_progress)),
                        false,
                    ))
                }
                Some(Request::StartCycle | Request::Dock) if !sw.home => {
                    fault(FaultKind::AxisStall)
                }
                Some(Request::StartCycle | Request::Dock) => fault(FaultKind::LockNotLocked),
                _ => None,
            },
            // Undock before the rod is in the cone: no insertion, no cycle. Locked (or
            // locking again), the panel returns home.
            State::PreAlign { .. } if inp.request == Some(Request::Undock) => {
                self.cycle_in_progress = self.cycles_completed;
                Some((self.start_return(now, inp.pos_um, false), None, false))
            }
            State::Releasing { .. } if inp.request == Some(Request::Undock) => {
                self.cycle_in_progress = self.cycles_completed;
                Some((
                    State::Locking {
                        deadline_ms: self.lock_deadline(now),
                        then: AfterLock::Return,
                    },
                    None,
                    false,
                ))
            }
            // Undock during the insertion: a controlled extraction from where it is
            // (an insertion and an extraction: it counts as a cycle).
            State::Inserting { .. } if inp.request == Some(Request::Undock) => {
                let deadline_ms =
                    self.move_deadline(now, inp.pos_um - cfg.engage_um, cfg.dock_speed_um_per_s);
                Some((State::Extracting { deadline_ms }, None, false))
            }
            State::PreAlign { deadline_ms } => {
                if inp.axis_idle && (inp.pos_um - cfg.engage_um).abs() <= 10 {
                    Some((
                        State::Releasing {
                            deadline_ms: self.lock_deadline(now),
                        },
                        None,
                        false,
                    ))
                } else if past(deadline_ms) {
                    fault(FaultKind::AxisStall)
                } else {
                    None
                }
            }
            State::Releasing { deadline_ms } => {
                if sw.released {
                    let deadline_ms = self.move_deadline(
                        now,
                        cfg.mated_um() - inp.pos_um,
                        cfg.dock_speed_um_per_s,
                    );
                    // From here the rod goes into the cone: the cycle counts.
                    self.reached_cone = true;
                    Some((State::Inserting { deadline_ms }, None, false))
                } else if past(deadline_ms) {
                    fault(FaultKind::LockNotReleased)
                } else {
                    None
                }
            }
            State::Inserting { deadline_ms } => {
                if inp.axis_idle && (inp.pos_um - cfg.mated_um()).abs() <= 10 {
                    Some((
                        State::Holding {
                            until_ms: (!self.service).then_some(now + cfg.hold_ms as u64),
                            unmating: false,
                        },
                        None,
                        false,
                    ))
                } else if past(deadline_ms) {
                    fault(FaultKind::AxisStall)
                } else {
                    None
                }
            }
            State::Holding {
                unmating: false, ..
            } if inp.request == Some(Request::Undock) => Some((
                State::Holding {
                    until_ms: Some(now + UNMATE_MS),
                    unmating: true,
                },
                None,
                false,
            )),
            State::Holding { until_ms, .. } => {
                if until_ms.is_some_and(|t| now >= t) {
                    let deadline_ms = self.move_deadline(
                        now,
                        inp.pos_um - cfg.engage_um,
                        cfg.dock_speed_um_per_s,
                    );
                    Some((State::Extracting { deadline_ms }, None, false))
                } else {
                    None
                }
            }
            State::Extracting { deadline_ms } | State::Recovering { deadline_ms } => {
                if inp.axis_idle && (inp.pos_um - cfg.engage_um).abs() <= 10 {
                    Some((
                        State::Locking {
                            deadline_ms: self.lock_deadline(now),
                            then: AfterLock::Return,
                        },
                        None,
                        false,
                    ))
                } else if past(deadline_ms) {
                    fault(FaultKind::AxisStall)
                } else {
                    None
                }
            }
            State::Returning {
                deadline_ms,
                ends_cycle,
                creeping,
            } => {
                if sw.home {
                    let ev = if ends_cycle {
                        self.cycles_completed = self.cycle_in_progress;
                        Some(SeqEvent::CycleCompleted(self.cycles_completed))
                    } else {
                        Some(SeqEvent::Homed)
                    };
                    Some((State::Idle, ev, true))
                } else if !creeping && inp.axis_idle && (inp.pos_um - HOME_APPROACH_UM).abs() <= 10
                {
                    Some((self.start_creep(now, ends_cycle), None, false))
                } else if past(deadline_ms) || (creeping && inp.axis_idle) {
                    // Counted position says home (or time is up) but the switch is open.
                    fault(FaultKind::AxisStall)
                } else {
                    None
                }
            }
            State::BackingOff { deadline_ms, .. } => {
                if inp.axis_idle || past(deadline_ms) {
                    to(State::Faulted {
                        fault: FaultKind::Overload,
                    })
                } else {
                    None
                }
            }
            State::Faulted { .. } => match inp.request {
                Some(Request::ClearFault) => {
                    if inp.pos_um > cfg.engage_um {
                        let deadline_ms = self.move_deadline(
                            now,
                            inp.pos_um - cfg.engage_um,
                            cfg.dock_speed_um_per_s,
                        );
                        Some((
                            State::Recovering { deadline_ms },
                            Some(SeqEvent::FaultCleared),
                            false,
                        ))
                    } else {
                        Some((
                            State::Locking {
                                deadline_ms: self.lock_deadline(now),
                                then: AfterLock::Return,
                            },
                            Some(SeqEvent::FaultCleared),
                            false,
                        ))
                    }
                }
                _ => None,
            },
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The board publishes a state as its ordinal (one atomic byte) and the console
    /// names it from `NAMES`: every state round-trips to its own, distinct name.
    #[test]
    fn every_state_is_named_by_its_ordinal() {
        let states = [
            State::PowerUp,
            State::Homing { deadline_ms: 0 },
            State::Idle,
            State::Holding {
                until_ms: None,
                unmating: false,
            },
            State::Faulted {
                fault: FaultKind::Overload,
            },
            State::Recovering { deadline_ms: 0 },
        ];
        for st in states {
            assert_eq!(State::NAMES.get(st.ordinal() as usize), Some(&st.name()));
        }
        let mut names = State::NAMES.to_vec();
        names.sort_unstable();
        names.dedup();
        assert_eq!(names.len(), State::NAMES.len());
        assert_eq!(State::Recovering { deadline_ms: 0 }.name(), "recovering");
        assert_eq!(State::PowerUp.name(), "power_up");
    }

    struct Rig {
        seq: Sequencer,
        inp: Inputs,
    }

    impl Rig {
        fn new() -> Self {
            let sw = Switches {
                home: true,
                locked: true,
                ..Switches::default()
            };
            Self {
                seq: Sequencer::new(MachineConfig::DEFAULT),
                inp: Inputs {
                    switches: sw,
                    axis_idle: true,
                    ..Inputs::default()
                },
            }
        }
        fn tick(&mut self, dt_ms: u64) {
            let _ = self.step(dt_ms);
        }
        /// Boot to idle (at home, locked), then request a cycle: the start step's outputs.
        fn started(&mut self) -> Outputs {
            for _ in 0..3 {
                self.tick(10);
            }
            assert_eq!(self.seq.state(), State::Idle);
            self.inp.request = Some(Request::StartCycle);
            self.step(10)
        }
        fn step(&mut self, dt_ms: u64) -> Outputs {
            self.inp.now_ms += dt_ms;
            let o = self.seq.step(&self.inp);
            self.inp.request = None;
            self.inp.fault = None;
            o
        }
    }

    #[test]
    fn boots_home_and_locked_to_idle_moving_nothing() {
        // On the home switch and locked at power-up: zero at once, no motion at all.
        let mut r = Rig::new();
        let o = r.step(10);
        assert!(o.zero_position);
        assert_eq!(o.event, Some(SeqEvent::Homed));
        assert_eq!((o.axis, o.lock), (AxisCmd::Disabled, LockCmd::Off));
        assert_eq!(r.seq.state(), State::Idle);
    }

    #[test]
    fn after_a_reset_nothing_moves_until_a_request() {
        // At home but unlocked, or away from home (perhaps in the cone): wait.
        for (home, locked) in [(true, false), (false, true), (false, false)] {
            let mut r = Rig::new();
            r.inp.switches = Switches {
                home,
                locked,
                ..Switches::default()
            };
            for _ in 0..1_000 {
                let o = r.step(10);
                assert_eq!((o.axis, o.lock), (AxisCmd::Disabled, LockCmd::Off));
            }
            assert_eq!(r.seq.state(), State::PowerUp);
            r.inp.request = Some(Request::Home);
            let o = r.step(10);
            assert_ne!(
                (o.axis, o.lock),
                (AxisCmd::Disabled, LockCmd::Off),
                "moves on request"
            );
        }
    }

    #[test]
    fn boots_away_from_home_and_searches_at_no_more_than_v0() {
        let mut r = Rig::new();
        r.inp.switches.home = false;
        r.inp.axis_idle = false;
        r.inp.pos_um = 0; // unknown: counted from zero at boot
        assert_eq!(r.step(10).axis, AxisCmd::Disabled, "waits for a request");
        r.inp.request = Some(Request::Home);
        let o = r.step(10);
        assert!(matches!(r.seq.state(), State::Homing { .. }));
        assert!(
            matches!(o.axis, AxisCmd::Move { target_um, speed_um_per_s: 1_200 } if target_um < -50_000)
        );
        r.inp.switches.home = true;
        let o = r.step(10);
        assert_eq!(o.event, Some(SeqEvent::Homed));
        assert!(o.zero_position);
    }

    #[test]
    fn a_whole_cycle_as_a_timeline() {
        let cfg = MachineConfig::DEFAULT;
        let mut r = Rig::new();
        let o = r.started();
        assert_eq!(o.event, Some(SeqEvent::CycleStarted(1)));
        assert_eq!(
            o.axis,
            AxisCmd::Move {
                target_um: cfg.engage_um,
                speed_um_per_s: cfg.fast_speed_um_per_s
            }
        );
        r.inp.switches.home = false;
        r.inp.pos_um = cfg.engage_um;
        let o = r.step(2_000);
        assert_eq!(o.lock, LockCmd::ToReleased);
        r.inp.switches = Switches {
            released: true,
            ..Switches::default()
        };
        let o = r.step(400);
        assert_eq!(
            o.axis,
            AxisCmd::Move {
                target_um: cfg.mated_um(),
                speed_um_per_s: 1_200
            }
        );
        r.inp.pos_um = cfg.mated_um();
        r.tick(25_000);
        assert!(matches!(r.seq.state(), State::Holding { .. }));
        let o = r.step(1_000);
        assert!(matches!(r.seq.state(), State::Extracting { .. }));
        assert_eq!(
            o.axis,
            AxisCmd::Move {
                target_um: cfg.engage_um,
                speed_um_per_s: 1_200
            }
        );
        r.inp.pos_um = cfg.engage_um;
        let o = r.step(25_000);
        assert_eq!(o.lock, LockCmd::ToLocked);
        r.inp.switches = Switches {
            locked: true,
            ..Switches::default()
        };
        // Fast to the approach point, then creeping onto the switch.
        let o = r.step(400);
        assert_eq!(
            o.axis,
            AxisCmd::Move {
                target_um: HOME_APPROACH_UM,
                speed_um_per_s: cfg.fast_speed_um_per_s
            }
        );
        r.inp.pos_um = HOME_APPROACH_UM;
        let o = r.step(2_000);
        assert_eq!(
            o.axis,
            AxisCmd::Move {
                target_um: -HOME_OVERSHOOT_UM,
                speed_um_per_s: HOME_CREEP_UM_PER_S
            }
        );
        r.inp.switches.home = true;
        r.inp.pos_um = 0;
        let o = r.step(2_000);
        assert_eq!(o.event, Some(SeqEvent::CycleCompleted(1)));
        assert!(o.zero_position);
        assert_eq!(r.seq.cycles_completed(), 1);
    }

    /// Boot to idle, request `req` (Dock or StartCycle) and drive the rig through the
    /// pre-alignment and the release into the compliant insertion.
    fn inserting_by(r: &mut Rig, req: Request) {
        for _ in 0..3 {
            r.tick(10);
        }
        r.inp.request = Some(req);
        r.tick(10);
        r.inp.switches.home = false;
        r.inp.pos_um = MachineConfig::DEFAULT.engage_um;
        r.tick(2_000);
        r.inp.switches = Switches {
            released: true,
            ..Switches::default()
        };
        r.tick(400);
        assert!(matches!(r.seq.state(), State::Inserting { .. }));
    }

    /// Boot to idle, request `r` (Dock or StartCycle) and drive the rig to the mated
    /// position: the state once there.
    fn mated_by(r: &mut Rig, req: Request) -> State {
        inserting_by(r, req);
        r.inp.pos_um = MachineConfig::DEFAULT.mated_um();
        r.tick(25_000);
        r.seq.state()
    }

    /// Drive an extraction under way back to idle: the events seen.
    fn finish_return(r: &mut Rig) -> heapless::Vec<SeqEvent, 8> {
        let cfg = MachineConfig::DEFAULT;
        let mut ev = heapless::Vec::new();
        let push = |o: Outputs, ev: &mut heapless::Vec<SeqEvent, 8>| {
            if let Some(e) = o.event {
                let _ = ev.push(e);
            }
        };
        r.inp.pos_um = cfg.engage_um;
        push(r.step(25_000), &mut ev);
        r.inp.switches = Switches {
            locked: true,
            ..Switches::default()
        };
        push(r.step(400), &mut ev);
        r.inp.pos_um = HOME_APPROACH_UM;
        push(r.step(2_000), &mut ev);
        r.inp.switches.home = true;
        r.inp.pos_um = 0;
        push(r.step(2_000), &mut ev);
        ev
    }

    #[test]
    fn dock_holds_an_hour_until_undock_then_counts_one_cycle() {
        let mut r = Rig::new();
        let held = mated_by(&mut r, Request::Dock);
        assert_eq!(
            held,
            State::Holding {
                until_ms: None,
                unmating: false
            }
        );
        // An hour mated: still holding, the axis driven where it is.
        for _ in 0..360 {
            let o = r.step(10_000);
            assert_eq!(o.axis, AxisCmd::Hold);
            assert_eq!(o.event, None);
        }
        assert_eq!(r.seq.state(), held);
        // Undock: MATED drops first (unmating), the extraction starts UNMATE_MS later.
        r.inp.request = Some(Request::Undock);
        r.tick(10);
        assert!(matches!(
            r.seq.state(),
            State::Holding { unmating: true, .. }
        ));
        r.tick(UNMATE_MS - 20);
        assert!(matches!(r.seq.state(), State::Holding { .. }));
        r.tick(20);
        assert!(matches!(r.seq.state(), State::Extracting { .. }));
        let ev = finish_return(&mut r);
        assert_eq!(ev.last(), Some(&SeqEvent::CycleCompleted(1)));
        assert_eq!(r.seq.cycles_completed(), 1);
        assert_eq!(r.seq.state(), State::Idle);
    }

    #[test]
    fn a_test_cycle_still_undocks_by_itself() {
        let mut r = Rig::new();
        let held = mated_by(&mut r, Request::StartCycle);
        assert!(matches!(
            held,
            State::Holding {
                until_ms: Some(_),
                unmating: false
            }
        ));
        r.tick(MachineConfig::DEFAULT.hold_ms as u64);
        assert!(matches!(r.seq.state(), State::Extracting { .. }));
    }

    #[test]
    fn undock_during_insertion_extracts_from_where_it_is_and_counts() {
        let cfg = MachineConfig::DEFAULT;
        let mut r = Rig::new();
        inserting_by(&mut r, Request::StartCycle);
        r.inp.axis_idle = false;
        r.inp.pos_um = cfg.engage_um + 9_000; // mid-insertion
        r.tick(10);
        r.inp.request = Some(Request::Undock);
        let o = r.step(10);
        assert!(matches!(r.seq.state(), State::Extracting { .. }));
        assert_eq!(
            o.axis,
            AxisCmd::Move {
                target_um: cfg.engage_um,
                speed_um_per_s: cfg.dock_speed_um_per_s
            },
            "back out at no more than v0"
        );
        r.inp.axis_idle = true;
        let ev = finish_return(&mut r);
        assert_eq!(ev.last(), Some(&SeqEvent::CycleCompleted(1)));
    }

    #[test]
    fn undock_before_the_cone_returns_without_counting() {
        let cfg = MachineConfig::DEFAULT;
        // During the pre-alignment (locked): straight back.
        let mut r = Rig::new();
        let _ = r.started();
        r.inp.switches.home = false;
        r.inp.axis_idle = false;
        r.inp.pos_um = cfg.engage_um / 2;
        r.inp.request = Some(Request::Undock);
        r.tick(10);
        assert!(matches!(r.seq.state(), State::Returning { .. }));
        r.inp.axis_idle = true;
        r.inp.pos_um = HOME_APPROACH_UM;
        r.tick(2_000);
        r.inp.switches.home = true;
        r.inp.pos_um = 0;
        let mut last = None;
        for _ in 0..3 {
            last = r.step(100).event.or(last);
        }
        assert_eq!(r.seq.state(), State::Idle);
        assert_ne!(last, Some(SeqEvent::CycleCompleted(1)));
        assert_eq!(r.seq.cycles_completed(), 0);
        // During the release: lock again first.
        let mut r = Rig::new();
        let _ = r.started();
        r.inp.switches.home = false;
        r.inp.pos_um = cfg.engage_um;
        r.tick(2_000);
        assert!(matches!(r.seq.state(), State::Releasing { .. }));
        r.inp.request = Some(Request::Undock);
        let o = r.step(10);
        assert_eq!(o.lock, LockCmd::ToLocked);
        assert_eq!(r.seq.cycles_completed(), 0);
    }

    #[test]
    fn stop_latches_stopped_from_any_moving_state() {
        let mut r = Rig::new();
        let _ = r.started();
        r.inp.switches.home = false;
        r.inp.request = Some(Request::Stop);
        let o = r.step(10);
        assert_eq!(o.event, Some(SeqEvent::Fault(FaultKind::Stopped)));
        assert_eq!((o.axis, o.lock), (AxisCmd::Disabled, LockCmd::Off));
        // Latched: time and a new start do not move it.
        r.inp.request = Some(Request::Dock);
        let o = r.step(60_000);
        assert_eq!((o.axis, o.lock), (AxisCmd::Disabled, LockCmd::Off));
        assert_eq!(
            r.seq.state(),
            State::Faulted {
                fault: FaultKind::Stopped
            }
        );
    }

    #[test]
    fn pulled_while_mated_holds_the_axis_until_a_clear_extracts() {
        let mut r = Rig::new();
        let _ = mated_by(&mut r, Request::Dock);
        r.inp.fault = Some(FaultKind::HoldForce);
        let o = r.step(10);
        assert_eq!(o.event, Some(SeqEvent::Fault(FaultKind::HoldForce)));
        assert_eq!(o.axis, AxisCmd::Hold, "driven where it is, not free");
        assert_eq!(r.step(10_000).axis, AxisCmd::Hold);
        r.inp.request = Some(Request::ClearFault);
        let _ = r.step(10);
        assert!(matches!(r.seq.state(), State::Recovering { .. }));
    }

    #[test]
    fn lock_that_never_releases_is_a_named_latched_fault() {
        let mut r = Rig::new();
        let _ = r.started();
        r.inp.switches.home = false;
        r.inp.pos_um = 20_000;
        r.tick(2_000);
        assert!(matches!(r.seq.state(), State::Releasing { .. }));
        // The lock stays locked: at the deadline, a named fault.
        r.tick(1_999);
        assert!(matches!(r.seq.state(), State::Releasing { .. }));
        let o = r.step(2);
        assert_eq!(o.event, Some(SeqEvent::Fault(FaultKind::LockNotReleased)));
        assert_eq!((o.axis, o.lock), (AxisCmd::Disabled, LockCmd::Off));
        // Latched: a start is refused, time does not clear it.
        r.inp.request = Some(Request::StartCycle);
        let o = r.step(60_000);
        assert_eq!(o.event, Some(SeqEvent::RequestRefused(Request::StartCycle)));
        assert_eq!(
            r.seq.state(),
            State::Faulted {
                fault: FaultKind::LockNotReleased
            }
        );
        // Clear: recovery re-locks and returns home.
        r.inp.request = Some(Request::ClearFault);
        let o = r.step(10);
        assert_eq!(o.event, Some(SeqEvent::FaultCleared));
        assert_eq!(o.lock, LockCmd::ToLocked);
    }

    #[test]
    fn overload_while_inserting_backs_off_then_latches() {
        let cfg = MachineConfig::DEFAULT;
        let mut r = Rig::new();
        let _ = r.started();
        r.inp.switches = Switches {
            released: true,
            ..Switches::default()
        };
        r.inp.pos_um = cfg.engage_um;
        r.tick(2_000);
        r.tick(10);
        assert!(matches!(r.seq.state(), State::Inserting { .. }));
        r.inp.axis_idle = false;
        r.inp.pos_um = cfg.engage_um + 10_000;
        r.inp.fault = Some(FaultKind::Overload);
        let o = r.step(10);
        assert_eq!(o.event, Some(SeqEvent::Fault(FaultKind::Overload)));
        assert_eq!(
            o.axis,
            AxisCmd::Move {
                target_um: cfg.engage_um + 8_000,
                speed_um_per_s: 1_200
            }
        );
        r.inp.pos_um = cfg.engage_um + 8_000;
        r.inp.axis_idle = true;
        let o = r.step(2_000);
        assert_eq!(o.axis, AxisCmd::Disabled);
        assert_eq!(
            r.seq.state(),
            State::Faulted {
                fault: FaultKind::Overload
            }
        );
    }

    #[test]
    fn return_without_home_switch_is_a_stall() {
        let mut r = Rig::new();
        r.inp.switches.home = false;
        r.inp.axis_idle = false;
        r.inp.request = Some(Request::Home);
        let o = r.step(10);
        assert!(matches!(o.axis, AxisCmd::Move { .. }));
        r.inp.axis_idle = true; // reached the search limit, switch still open
        let o = r.step(10);
        assert_eq!(o.event, Some(SeqEvent::Fault(FaultKind::AxisStall)));
    }

    #[test]
    fn overtravel_and_switch_conflicts() {
        let mut r = Rig::new();
        r.inp.switches.end = true;
        let o = r.step(10);
        assert_eq!(o.event, Some(SeqEvent::Fault(FaultKind::SwitchConflict)));
        let mut r = Rig::new();
        r.inp.switches = Switches {
            end: true,
            locked: true,
            ..Switches::default()
        };
        let o = r.step(10);
        assert_eq!(o.event, Some(SeqEvent::Fault(FaultKind::Overtravel)));
    }

    #[test]
    fn fault_codes_round_trip() {
        for c in 0..=20u8 {
            if let Some(f) = FaultKind::from_code(c) {
                assert_eq!(f.code(), c);
            }
        }
        assert_eq!(FaultKind::from_code(0), Some(FaultKind::Overload));
        assert_eq!(FaultKind::from_code(10), Some(FaultKind::Io));
        assert_eq!(FaultKind::from_code(11), Some(FaultKind::Tension));
        assert_eq!(FaultKind::from_code(12), Some(FaultKind::Storage));
        assert_eq!(FaultKind::from_code(15), Some(FaultKind::HoldForce));
        assert_eq!(FaultKind::from_code(16), Some(FaultKind::UnseenStop));
        assert_eq!(FaultKind::from_code(17), None);
    }
}
