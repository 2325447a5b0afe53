// The register map's table, once: docs/modbus-map.md is this module's doc.
#![doc = include_str!("../../../../docs/modbus-map.md")]

use crate::machine::Machine;
use crate::odometer::WearLevel;
use crate::sequencer::{Request, State};

/// The register map's version: bumped when registers are added (never moved or
/// reused).
pub const MAP_VERSION: u16 = 4;

/// Input register addresses (function 0x04); see the module doc for units.
pub mod ir {
    /// Status word ([`super::status`] bits).
    pub const STATUS: u16 = 0;
    /// Sequencer state code ([`super::state_code`]).
    pub const STATE: u16 = 1;
    /// Contact phase, 0 none, 1–4.
    pub const PHASE: u16 = 2;
    /// Force, 0.1 N, i16.
    pub const FORCE: u16 = 3;
    /// Force limit at the present depth, 0.1 N, i16.
    pub const FORCE_LIMIT: u16 = 4;
    /// Axis position from home, 0.01 mm, i16.
    pub const POSITION: u16 = 5;
    /// Active fault code, 0xFFFF none.
    pub const ACTIVE_FAULT: u16 = 6;
    /// Peak force since boot, 0.1 N, i16.
    pub const PEAK_FORCE: u16 = 7;
    /// The last command written to this server (its code, [`super::Command::code`]),
    /// 0 none since boot.
    pub const LAST_COMMAND: u16 = 8;
    /// Its result: 0 accepted, else why it was refused
    /// ([`crate::controller::Refusal::code`]).
    pub const LAST_COMMAND_RESULT: u16 = 9;
    /// Maintenance mode at the console: 1 on (PLC motion refused), 0 off.
    pub const MAINTENANCE_MODE: u16 = 10;
    /// Lifetime cycles, u32 (high word first).
    pub const LIFETIME_CYCLES: u16 = 16;
    /// Cone cycles, u32.
    pub const CONE_CYCLES: u16 = 18;
    /// Cone wear (the odometer's model), nm, u32.
    pub const WEAR_NM: u16 = 20;
    /// Cone wear (the odometer's model), µm (rounded down), u16.
    pub const WEAR_UM: u16 = 22;
    /// Wear level acted on: 0 ok, 1 warning, 2 limit.
    pub const WEAR_LEVEL: u16 = 23;
    /// Remaining cone life, nominal cycles, u32.
    pub const REMAINING_CYCLES: u16 = 24;
    /// Wear as a share of the limit, 0.1 %.
    pub const WEAR_PERMILLE: u16 = 26;
    /// Wear limit, µm.
    pub const WEAR_LIMIT_UM: u16 = 27;
    /// Overload events over the machine's life, u32.
    pub const OVERLOAD_EVENTS: u16 = 28;
    /// Faults over the machine's life, u32.
    pub const FAULTS_LIFETIME: u16 = 30;
    /// Faults latched since boot, u32.
    pub const FAULTS_SINCE_BOOT: u16 = 32;
    /// Overload trips since boot, u32.
    pub const OVERLOAD_TRIPS_SINCE_BOOT: u16 = 34;
    /// Last fault's code, 0xFFFF none.
    pub const LAST_FAULT_CODE: u16 = 40;
    /// Last fault's cycle number, u32.
    pub const LAST_FAULT_CYCLE: u16 = 41;
    /// Last fault's peak force, 0.1 N, i16.
    pub const LAST_FAULT_PEAK_FORCE: u16 = 43;
    /// Last fault's contact phase, 0 none, 1–4.
    pub const LAST_FAULT_PHASE: u16 = 44;
    /// Cone id (installation number).
    pub const CONE_ID: u16 = 48;
    /// Cone material code.
    pub const CONE_MATERIAL: u16 = 49;
    /// Cone serial, [`CONE_SERIAL_REGS`] registers of ASCII.
    pub const CONE_SERIAL: u16 = 50;
    /// Registers of the cone serial (2 characters each).
    pub const CONE_SERIAL_REGS: u16 = 10;
    /// Firmware version: major.
    pub const FW_MAJOR: u16 = 64;
    /// Firmware version: minor.
    pub const FW_MINOR: u16 = 65;
    /// Firmware version: patch.
    pub const FW_PATCH: u16 = 66;
    /// [`super::MAP_VERSION`].
    pub const MAP_VERSION: u16 = 67;
    /// The newest judged docking's verdict (the docking signature, map version 3): 0
    /// none yet, 1 OK, 2 NOK.
    pub const SIG_VERDICT: u16 = 68;
    /// Its first failed object's code (0 none).
    pub const SIG_FAILED: u16 = 69;
    /// The figure that failed it, i32 (high word first), in [`SIG_UNIT`].
    pub const SIG_FIGURE: u16 = 70;
    /// The limit it broke, i32.
    pub const SIG_LIMIT: u16 = 72;
    /// Their unit: 0 mN, 1 µm.
    pub const SIG_UNIT: u16 = 74;
    /// That docking's lifetime cycle, u32.
    pub const SIG_CYCLE: u16 = 75;
    /// Its insertion work ∫F·dx, N·mm.
    pub const SIG_WORK: u16 = 77;
    /// Its phase-4 plateau, 0.1 N, i16.
    pub const SIG_PLATEAU: u16 = 78;
    /// Where its force stepped from single- to two-point contact, µm (0xFFFF none).
    pub const SIG_STEP: u16 = 79;
    /// Its work's drift from the cone's reference, 0.1 %, i16 (0x8000: no reference
    /// yet).
    pub const SIG_DRIFT_WORK: u16 = 80;
    /// Its plateau's drift from the reference, 0.1 %, i16.
    pub const SIG_DRIFT_PLATEAU: u16 = 81;
    /// The cone's trend of the work's drift (moving average, α = 1/16), 0.1 %, i16.
    pub const SIG_TREND_WORK: u16 = 82;
    /// The cone's trend of the plateau's drift, 0.1 %, i16.
    pub const SIG_TREND_PLATEAU: u16 = 83;
    /// NOK dockings of the current cone, u32.
    pub const SIG_CONE_NOK: u16 = 84;
    /// Judged dockings of the current cone, u32.
    pub const SIG_CONE_JUDGED: u16 = 86;
    /// Dockings in the cone's reference so far.
    pub const SIG_REFERENCE_N: u16 = 88;
    /// Dockings its reference takes (20 by default).
    pub const SIG_REFERENCE_TARGET: u16 = 89;
    /// The newest stroke's verdict (at MATED for an insertion, home for an
    /// extraction): 0 none, 1 insertion OK, 2 insertion NOK, 3 extraction OK, 4
    /// extraction NOK.
    pub const SIG_STROKE: u16 = 90;
    /// Its first failed object's code (0 none).
    pub const SIG_STROKE_FAILED: u16 = 91;
    /// Stroke verdicts since boot (wraps): a change is a new verdict.
    pub const SIG_STROKE_COUNT: u16 = 92;
    /// The cone's wear estimated from its docking signature's 3→4 step (map version 4;
    /// [`crate::signature::stepwear`]), µm, i16 (0x8000: no estimate yet).
    pub const SIG_WEAR_UM: u16 = 93;
    /// Its 95 % band, ± µm (rounded up; 0xFFFF: no estimate).
    pub const SIG_WEAR_BAND_UM: u16 = 94;
    /// Dockings the estimate rests on (its window; 0: no estimate).
    pub const SIG_WEAR_DOCKINGS: u16 = 95;
    /// Input registers in the map (addresses 0..COUNT).
    pub const COUNT: u16 = 96;
}

/// Status word bits (input register 0), and the discrete inputs (bit n = input n).
pub mod status {
    /// READY: idle, homed, locked, calibrated, cone not worn out, E-STOP closed.
    pub const READY: u16 = 1 << 0;
    /// MATED: connectors engaged, force in the hold envelope.
    pub const MATED: u16 = 1 << 1;
    /// The propulsion may be moving.
    pub const MOVING: u16 = 1 << 2;
    /// FAULT: a latched fault or the overload back-off.
    pub const FAULT: u16 = 1 << 3;
    /// Force above the warning level.
    pub const WARNING: u16 = 1 << 4;
    /// MAINTENANCE: the cone past its warning level.
    pub const MAINTENANCE: u16 = 1 << 5;
    /// A technician's load-cell calibration is stored.
    pub const CALIBRATED: u16 = 1 << 6;
    /// The E-STOP input is open.
    pub const ESTOP_OPEN: u16 = 1 << 7;
    /// The DOCK input is asserted (as filtered).
    pub const DOCK_INPUT: u16 = 1 << 8;
    /// The cone is worn out (docking refused until it is replaced).
    pub const WORN_OUT: u16 = 1 << 9;
    /// A docking is under way or mated.
    pub const DOCKING: u16 = 1 << 10;
    /// A technician has the machine in maintenance mode at the console: motion
    /// commands from the PLC are refused (refusal 9) and READY is low.
    pub const MAINTENANCE_MODE: u16 = 1 << 11;
    /// The newest judged docking was NOK by its signature (map version 3): for the
    /// people who maintain the machine, nothing stopped.
    pub const SIGNATURE_NOK: u16 = 1 << 12;
    /// Discrete inputs in the map (the bits above).
    pub const COUNT: u16 = 13;
}

/// Commands (coil address = code − 1; holding register 0 value = code).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Command {
    /// Dock and hold until undock (accepted when READY).
    Dock,
    /// Undock (accepted while docking or mated).
    Undock,
    /// Clear the latched fault and recover to home (accepted when faulted, E-STOP
    /// closed).
    ClearFault,
    /// Stop all motion, latching the `stopped` fault (always accepted; also broadcast).
    Stop,
    /// Find home and lock after a reset (accepted at power-up).
    Home,
}

impl Command {
    /// Every command, in coil order.
    pub const ALL: [Self; 5] = [
        Self::Dock,
        Self::Undock,
        Self::ClearFault,
        Self::Stop,
        Self::Home,
    ];

    /// The command register's value (1–5).
    pub const fn code(self) -> u16 {
        match self {
            Self::Dock => 1,
            Self::Undock => 2,
            Self::ClearFault => 3,
            Self::Stop => 4,
            Self::Home => 5,
        }
    }

    /// From the command register's value.
    pub const fn from_code(code: u16) -> Option<Self> {
        match code {
            1 => Some(Self::Dock),
            2 => Some(Self::Undock),
            3 => Some(Self::ClearFault),
            4 => Some(Self::Stop),
            5 => Some(Self::Home),
            _ => None,
        }
    }

    /// The command's coil.
    pub const fn coil(self) -> u16 {
        self.code() - 1
    }

    /// What is asked of the controller.
    pub const fn request(self) -> Request {
        match self {
            Self::Dock => Request::Dock,
            Self::Undock => Request::Undock,
            Self::ClearFault => Request::ClearFault,
            Self::Stop => Request::Stop,
            Self::Home => Request::Home,
        }
    }

    /// Whether it moves the machine (unicast only).
    pub const fn moves(self) -> bool {
        !matches!(self, Self::Stop)
    }
}

/// Command coils in the map (addresses 0..COIL_COUNT).
pub const COIL_COUNT: u16 = 5;
/// Holding registers in the map: 0, the command register.
pub const HOLDING_COUNT: u16 = 1;

/// The sequencer state's code (input register 1).
pub const fn state_code(s: &State) -> u16 {
    match s {
        State::PowerUp => 0,
        State::Homing { .. } => 1,
        State::Locking { .. } => 2,
        State::Idle => 3,
        State::PreAlign { .. } => 4,
        State::Releasing { .. } => 5,
        State::Inserting { .. } => 6,
        State::Holding { .. } => 7,
        State::Extracting { .. } => 8,
        State::Returning { .. } => 9,
        State::BackingOff { .. } => 10,
        State::Faulted { .. } => 11,
        State::Recovering { .. } => 12,
    }
}

/// Decimal digits at the start of `s`, saturating.
pub(super) const fn parse_u16(s: &str) -> u16 {
    let mut b = s.as_bytes();
    let mut v: u16 = 0;
    while let [d, rest @ ..] = b {
        if !d.is_ascii_digit() {
            break;
        }
        v = v.saturating_mul(10).saturating_add((*d - b'0') as u16);
        b = rest;
    }
    v
}

/// The firmware version (major, minor, patch), from `Cargo.toml` at build time.
pub const FIRMWARE_VERSION: [u16; 3] = [
    parse_u16(env!("CARGO_PKG_VERSION_MAJOR")),
    parse_u16(env!("CARGO_PKG_VERSION_MINOR")),
    parse_u16(env!("CARGO_PKG_VERSION_PATCH")),
];

/// mN → 0.1 N, rounded to the nearest, saturating to `i16`, as a register.
pub(super) fn decinewtons(mn: i32) -> u16 {
    in_units(mn, 100)
}

/// µm → 0.01 mm, rounded to the nearest, saturating to `i16`, as a register.
pub(super) fn centimillimetres(um: i32) -> u16 {
    in_units(um, 10)
}

/// `v / unit` rounded to the nearest (halves away from zero), saturating to `i16`, as
/// a register (`unit` even). Out of line: four registers take it (issue 20).
#[inline(never)]
fn in_units(v: i32, unit: i32) -> u16 {
    let (v, unit) = (i64::from(v), i64::from(unit));
    let q = (v + if v >= 0 { unit / 2 } else { -unit / 2 }) / unit;
    q.clamp(i64::from(i16::MIN), i64::from(i16::MAX)) as i16 as u16
}

fn sat_u16(v: u64) -> u16 {
    u16::try_from(v).unwrap_or(u16::MAX)
}

/// The status word (input register 0; discrete inputs 0–12).
pub fn status_word(ctrl: &dyn Machine) -> u16 {
    let s = ctrl.status();
    let h = s.handshake;
    let bit = |on: bool, b: u16| if on { b } else { 0 };
    bit(h.ready, status::READY)
        | bit(h.mated, status::MATED)
        | bit(s.state.is_moving(), status::MOVING)
        | bit(h.fault, status::FAULT)
        | bit(s.warning, status::WARNING)
        | bit(h.maintenance, status::MAINTENANCE)
        | bit(ctrl.calibrated(), status::CALIBRATED)
        | bit(h.estop, status::ESTOP_OPEN)
        | bit(h.dock, status::DOCK_INPUT)
        | bit(s.wear_level == WearLevel::Limit, status::WORN_OUT)
        | bit(s.state.is_docking(), status::DOCKING)
        | bit(ctrl.maintenance_mode(), status::MAINTENANCE_MODE)
        | bit(
            ctrl.signature_status().last.is_some_and(|l| l.nok()),
            status::SIGNATURE_NOK,
        )
}

/// The input registers now, 0..[`ir::COUNT`] (reserved addresses 0; the last command
/// and its result, 8–9, are the [`Server`](super::Server)'s and read 0 here).
pub fn input_registers(ctrl: &dyn Machine) -> [u16; ir::COUNT as usize] {
    let mut r = [0u16; ir::COUNT as usize];
    let mut set = |addr: u16, v: u16| {
        if let Some(x) = r.get_mut(usize::from(addr)) {
            *x = v;
        }
    };
    let s = ctrl.status();
    let odo = ctrl.odometer();
    let life = odo.lifetime();
    let cone = odo.cone();
    let limit_nm = odo.config().limit_nm;
    let phase = |p: Option<crate::profile::ContactPhase>| p.map_or(0, |p| u16::from(p.number()));

    set(ir::STATUS, status_word(ctrl));
    set(ir::STATE, state_code(&s.state));
    set(ir::PHASE, phase(s.phase));
    set(ir::FORCE, decinewtons(s.force_mn));
    set(ir::FORCE_LIMIT, decinewtons(s.limit_mn));
    set(ir::POSITION, centimillimetres(s.pos_um));
    set(
        ir::ACTIVE_FAULT,
        s.fault.map_or(0xFFFF, |f| u16::from(f.code())),
    );
    set(ir::PEAK_FORCE, decinewtons(s.peak_force_mn));

    let mut set32 = |addr: u16, v: u32| {
        set(addr, (v >> 16) as u16);
        set(addr.saturating_add(1), v as u16);
    };
    set32(ir::LIFETIME_CYCLES, life.cycles);
    set32(ir::CONE_CYCLES, cone.cycles);
    set32(ir::WEAR_NM, odo.wear_nm());
    set32(ir::REMAINING_CYCLES, odo.remaining_cycles());
    set32(ir::OVERLOAD_EVENTS, life.overload_events);
    set32(ir::FAULTS_LIFETIME, life.faults);
    set32(ir::FAULTS_SINCE_BOOT, ctrl.fault_count());
    set32(ir::OVERLOAD_TRIPS_SINCE_BOOT, ctrl.overload_trips());
    let mut last = None;
    ctrl.each_fault(&mut |f| last = Some(*f));
    set32(ir::LAST_FAULT_CYCLE, last.map_or(0, |f| f.cycle));

    set(ir::WEAR_UM, sat_u16(u64::from(odo.wear_nm() / 1_000)));
    set(
        ir::WEAR_LEVEL,
        match s.wear_level {
            WearLevel::Ok => 0,
            WearLevel::Warning => 1,
            WearLevel::Limit => 2,
        },
    );
    set(
        ir::WEAR_PERMILLE,
        sat_u16(u64::from(odo.wear_nm()) * 1_000 / u64::from(limit_nm.max(1))),
    );
    set(ir::WEAR_LIMIT_UM, sat_u16(u64::from(limit_nm / 1_000)));
    set(
        ir::LAST_FAULT_CODE,
        last.map_or(0xFFFF, |f| u16::from(f.kind.code())),
    );
    set(
        ir::LAST_FAULT_PEAK_FORCE,
        last.map_or(0, |f| decinewtons(f.peak_force_mn)),
    );
    set(ir::LAST_FAULT_PHASE, last.map_or(0, |f| phase(f.phase)));
    set(ir::CONE_ID, cone.id);
    set(ir::CONE_MATERIAL, u16::from(cone.material.code()));
    let serial = cone
        .serial
        .get(..usize::from(cone.serial_len))
        .unwrap_or(&[]);
    let serial_regs = ir::CONE_SERIAL..ir::CONE_SERIAL + ir::CONE_SERIAL_REGS;
    for (addr, pair) in serial_regs.zip(serial.chunks(2)) {
        let hi = pair.first().copied().unwrap_or(0);
        let lo = pair.get(1).copied().unwrap_or(0);
        set(addr, u16::from_be_bytes([hi, lo]));
    }
    // The running image's version (its header), else the build's.
    let [major, minor, patch] = ctrl.images().running.map_or(FIRMWARE_VERSION, |v| {
        [u16::from(v.major), u16::from(v.minor), v.patch]
    });
    set(ir::FW_MAJOR, major);
    set(ir::FW_MINOR, minor);
    set(ir::FW_PATCH, patch);
    set(ir::MAP_VERSION, MAP_VERSION);
    set(ir::MAINTENANCE_MODE, u16::from(ctrl.maintenance_mode()));
    signature_registers(ctrl, &mut set);
    r
}

/// The docking signature's registers (68–95).
fn signature_registers(ctrl: &dyn Machine, set: &mut dyn FnMut(u16, u16)) {
    let sig = ctrl.signature_status();
    let mut set32 = |addr: u16, v: u32| {
        set(addr, (v >> 16) as u16);
        set(addr.saturating_add(1), v as u16);
    };
    let pm = |v: Option<i16>| v.map_or(0x8000, |x| x as u16);
    let trend = |v: Option<i32>| pm(v.map(|t| (t / 16).clamp(-32_767, 32_767) as i16));
    set32(ir::SIG_CONE_NOK, sig.cone.nok);
    set32(ir::SIG_CONE_JUDGED, sig.cone.judged);
    if let Some(l) = sig.last {
        let f = l.failure;
        set32(ir::SIG_FIGURE, f.map_or(0, |f| f.figure as u32));
        set32(ir::SIG_LIMIT, f.map_or(0, |f| f.limit as u32));
        set32(ir::SIG_CYCLE, l.lifetime_cycle);
        set(ir::SIG_VERDICT, if l.nok() { 2 } else { 1 });
        set(ir::SIG_FAILED, f.map_or(0, |f| u16::from(f.object.code())));
        set(ir::SIG_UNIT, f.map_or(0, |f| f.unit as u16));
        set(ir::SIG_WORK, sat_u16(u64::from(l.work_mnmm / 1_000)));
        set(ir::SIG_PLATEAU, decinewtons(l.plateau_mn));
        set(
            ir::SIG_STEP,
            l.step_um.map_or(0xFFFF, |s| sat_u16(s.max(0) as u64)),
        );
        set(ir::SIG_DRIFT_WORK, pm(l.drift_work_pm));
        set(ir::SIG_DRIFT_PLATEAU, pm(l.drift_plateau_pm));
    }
    set(ir::SIG_TREND_WORK, trend(sig.cone.trend_work_x16));
    set(ir::SIG_TREND_PLATEAU, trend(sig.cone.trend_plateau_x16));
    set(ir::SIG_REFERENCE_N, u16::from(sig.reference_n));
    set(ir::SIG_REFERENCE_TARGET, u16::from(sig.reference_target));
    if let Some(v) = sig.newest {
        let ext = v.stroke == crate::signature::Stroke::Extraction;
        set(
            ir::SIG_STROKE,
            1 + u16::from(v.failure.is_some()) + 2 * u16::from(ext),
        );
        set(
            ir::SIG_STROKE_FAILED,
            v.failure.map_or(0, |f| u16::from(f.object.code())),
        );
    }
    set(ir::SIG_STROKE_COUNT, sig.verdicts as u16);
    match sig.step_wear {
        Some(w) => {
            // nm → µm, rounded half away from zero; the band rounded up.
            let um = (i64::from(w.wear_nm) + if w.wear_nm >= 0 { 500 } else { -500 }) / 1_000;
            set(
                ir::SIG_WEAR_UM,
                um.clamp(-i64::from(i16::MAX), i64::from(i16::MAX)) as i16 as u16,
            );
            set(
                ir::SIG_WEAR_BAND_UM,
                u16::try_from(w.band_nm.div_ceil(1_000))
                    .unwrap_or(0xFFFE)
                    .min(0xFFFE),
            );
            set(ir::SIG_WEAR_DOCKINGS, u16::from(w.dockings));
        }
        None => {
            set(ir::SIG_WEAR_UM, 0x8000);
            set(ir::SIG_WEAR_BAND_UM, 0xFFFF);
        }
    }
}
