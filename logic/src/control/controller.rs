//! The control loop: one sample flows from the load cell through the sensor monitor, the
//! overload guard, the phase tracker and the sequencer to the motors in one step.
//!
//! The sample is read and judged first by the **safety kernel** ([`crate::safety`]): it
//! stops the propulsion itself, in the same call, on an overload, a pull or a sensor
//! fault, and hands the judged sample on as a [`KernelEvent`]. [`Controller::step`]
//! then runs once per event, and once a sample period without one (so that deadlines
//! still run), as its stages, each a function named for it:
//!
//! 1. **sample** (`stage_sample`): the stops the event reports, the propulsion's emitted
//!    pulses counted (position), the switches read and filtered (a change counts when two
//!    steps agree), I/O faults;
//! 2. **guard** (`stage_guard`): the kernel's verdict acted on: a stop it made becomes a
//!    latched fault (an overload backs off under control), sensor faults too;
//! 3. **odometer** (`stage_odometer`): the force feeds the wear odometer and, at rest,
//!    the tare;
//! 4. **phase** (`stage_phase`): the contact phase from the depth, cross-checked with the
//!    force;
//! 5. **PLC inputs** (`stage_plc`): DOCK's edges, E-STOP's edges and level, the hold
//!    envelope;
//! 6. **sequencer** (`stage_sequencer`): the request's gates, then the pure sequencer
//!    decides;
//! 7. **outputs** (`stage_outputs`): its commands applied to the drivers (the driver is
//!    enabled again only once the controller has seen every stop the kernel made);
//! 8. **watchdog** (`stage_watchdog`): fed if the steps keep their period.
//!
//! After the step the kernel is told the limit for the next samples
//! ([`Controller::kernel_config`]) and the board writes the PLC outputs
//! ([`Controller::handshake`]).
//!
//! On the board the kernel runs in the HX711's data-ready interrupt and the step in a
//! lower-priority task (`src/board.rs`); on the host rig one after the other. The
//! board and the simulator provide the hardware through [`Bsp`].

use core::mem::size_of;

use embedded_hal::digital::{InputPin, OutputPin};
use embedded_storage::nor_flash::NorFlash;
use heapless::Deque;
use zerocopy::byteorder::little_endian::{I32, I64, U32};
use zerocopy::{FromBytes, Immutable, IntoBytes, KnownLayout, Unaligned};

use crate::config::MachineConfig;
use crate::diag::{Crash, ResetCause, ResetCounts};
use crate::estimate::{Estimate, Fit, Reading};
use crate::guard::{GuardConfig, SensorFault, Verdict};
use crate::hal::{OptionBytes, StepPulses, StopLatch, Watchdog};
use crate::hx711::Calibration;
use crate::lock::{LockActuator, LockCmd};
use crate::material::Material;
use crate::odometer::{
    self, restore, CycleSummary, Journal, Measurement, Odometer, RetiredCone, StateRecord,
    WearConfig, WearLevel,
};
use crate::profile::{ContactPhase, BOUNDARY_UM, STROKE_UM};
use crate::propulsion::Propulsion;
use crate::safety::{EstopEvents, GuardMode, KernelConfig, KernelEvent, BACKOFF_RISE_MN};
use crate::sequencer::{AxisCmd, FaultKind, Inputs, Request, SeqEvent, Sequencer, State, Switches};
use crate::signature::monitor::{Docking, HistoryCols, Monitor, SignatureMem, StrokeVerdict};
use crate::signature::objects::SignatureConfig;
use crate::signature::store::SigStore;
use crate::signature::view::{CurveView, SignatureStatus, Which};
use crate::signature::Signature;
use crate::signature::Stroke;
use crate::storage::{OpenReport, RecordLog, PAYLOAD_MAX};

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
    /// The safety path's stop latch (shared with the kernel).
    type Stop: StopLatch;
    /// Independent watchdog.
    type Wdg: Watchdog;
    /// The flash sectors reserved for the wear odometer.
    type Flash: NorFlash;
    /// The option bytes (brown-out reset level).
    type Options: OptionBytes;
    /// The flash sectors of the docking signature's store (2–4 on the board).
    type SigFlash: NorFlash;
    /// Where the signature's buffers live (the board's CCM RAM).
    type SigMem: core::ops::DerefMut<Target = SignatureMem>;
    /// The signature, monitor and store, where the board placed it (the CCM RAM).
    type Sig: core::ops::DerefMut<Target = Signature<Self::SigFlash, Self::SigMem>>;
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
    /// The stop latch.
    pub stop: B::Stop,
    /// Watchdog.
    pub wdg: B::Wdg,
    /// Odometer flash.
    pub flash: B::Flash,
    /// Option bytes.
    pub options: B::Options,
    /// The docking signature ([`Signature::new`]: its store opened, its buffers).
    pub sig: B::Sig,
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
    /// Wear limit and warning level.
    pub wear: WearConfig,
    /// Cone material assumed when the flash holds no cone record (a new machine).
    pub default_material: Material,
    /// The mated contact force, mN: the nominal N3 at the end of the stroke
    /// ([`HOLD_EXPECTED_MN`] for the paper's machine; another machine's from its force
    /// model). MATED and the hold envelope ([`HOLD_TOLERANCE_MN`]) are around it.
    pub hold_expected_mn: i32,
    /// Who made the machine and what it is called: Modbus device identification's
    /// VendorName and ProductName (a machine builder's, from its commissioning file).
    pub identity: Identity,
    /// The docking signature's evaluation objects (Eq. 7's by default; another
    /// machine's from its commissioning file).
    pub signature: SignatureConfig,
}

/// Device identification's names (Modbus objects 0 and 4).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Identity {
    /// VendorName.
    pub vendor: &'static str,
    /// ProductName.
    pub product: &'static str,
}

impl Identity {
    /// Until a commissioning file names them.
    pub const DEFAULT: Self = Self {
        vendor: crate::modbus::VENDOR_NAME,
        product: crate::modbus::PRODUCT_NAME,
    };
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
            wear: WearConfig::DEFAULT,
            default_material: Material::ZQSn5_2,
            hold_expected_mn: HOLD_EXPECTED_MN,
            identity: Identity::DEFAULT,
            signature: SignatureConfig::DEFAULT,
        }
    }
}

/// Settings a technician stores at commissioning, record kind
/// [`odometer::kind::SETTINGS`] (4 bytes, little-endian):
///
/// ```text
///  0             4
///  +-------------+
///  | rate_sps u32|   10 or 80: the HX711's RATE pin (most modules tie it low: 10)
///  +-------------+
/// ```
///
/// They take effect at the next boot (the sample period sets the safety kernel's
/// timeouts and the control tick).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Settings {
    /// HX711 output data rate, samples/s (10 or 80).
    pub rate_sps: u32,
}

/// A [`Settings`] record as laid out in flash (drawn above).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct SettingsLayout {
    rate_sps: U32,
}

impl Settings {
    /// Bytes of the record.
    pub const LEN: usize = size_of::<SettingsLayout>();

    /// The record.
    pub fn to_bytes(&self) -> [u8; Self::LEN] {
        let layout = SettingsLayout {
            rate_sps: self.rate_sps.into(),
        };
        zerocopy::transmute!(layout)
    }

    /// From a record; `None` if it is not a valid one.
    pub fn from_bytes(b: &[u8]) -> Option<Self> {
        let rate_sps = SettingsLayout::read_from_bytes(b).ok()?.rate_sps.get();
        matches!(rate_sps, 10 | 80).then_some(Self { rate_sps })
    }
}

/// A latched fault as recorded.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
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
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Event {
    /// Sequencer event.
    Seq(SeqEvent),
    /// The rod entered a contact phase.
    Phase(ContactPhase),
    /// Force above the warning level (raised once, cleared with hysteresis).
    ForceWarning(i32),
    /// The force contradicts the phase the position says (3→4 cross-check).
    PhaseMismatch(ContactPhase),
    /// A cycle completed and was counted by the wear odometer.
    CycleCounted(CycleSummary),
    /// A stroke of a docking was judged by its signature (OK, or NOK and why).
    Signature(StrokeVerdict),
    /// A start was refused: the cone has reached its wear limit.
    WearLimitRefusal,
    /// A start was refused: the load cell has no stored calibration.
    UncalibratedRefusal,
    /// A fault clear refused: the E-STOP input is open.
    EstopClearRefusal,
    /// A DOCK pin request refused (why: the same reasons as a command's), or a request
    /// accepted before a mode that refuses it was granted, refused at its step.
    RemoteRefused(Refusal),
    /// E-STOP edges the control step had not seen (each stopped the machine in its
    /// interrupt): how many, and how long the input was open if it has closed again
    /// (µs; `None` while it is still open).
    EstopEdges {
        /// New edges (opening and closing).
        edges: u32,
        /// The last opening's length, µs.
        open_us: Option<u32>,
    },
}

/// An event with its time.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
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
    /// The PLC handshake as it is now.
    pub handshake: Handshake,
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
    /// Cone wear depth, nm.
    pub wear_nm: u32,
    /// Remaining cone life, nominal cycles.
    pub remaining_cycles: u32,
    /// Wear level.
    pub wear_level: WearLevel,
}

/// Samples this close outside the cone (µm) still count for wear (the mouth).
const CONE_MARGIN_UM: i32 = 500;
/// Zero-load samples averaged for the tare.
const TARE_SAMPLES: usize = 16;
/// Fewest tare samples before a cycle may start.
const TARE_MIN_SAMPLES: usize = 8;
/// Force halfway across the 3→4 jump (107.09 N → 206.34 N), mN.
const JUMP_MID_MN: i32 = 156_700;
/// Records that can wait for a rest ([`Controller::queue_record`]).
const RECORD_QUEUE: usize = 4;
/// Largest queued record payload, bytes (an audit record is at most 48).
pub const QUEUED_RECORD_MAX: usize = 48;

/// A record waiting for the flash's turn.
#[derive(Clone, Debug)]
struct QueuedRecord {
    kind: u8,
    data: heapless::Vec<u8, QUEUED_RECORD_MAX>,
}

/// What the cached wear estimate was computed from: cone id, equivalent cycles (Q32),
/// readings, baseline bore (µm).
type WearKey = (u16, u64, usize, u32);

/// Events kept for readers.
const EVENT_QUEUE: usize = 32;
/// Fault records kept.
const FAULTS_KEPT: usize = 16;
/// The mated contact force: Eq. 7's N3 at the end of the stroke (30 mm deep), mN.
pub const HOLD_EXPECTED_MN: i32 = 125_098;
/// How far the contact force may stray from [`HOLD_EXPECTED_MN`] while mated, mN: more
/// (two samples in a row) is the vehicle pulling or drifting ([`FaultKind::HoldForce`]),
/// and MATED is reported only within it.
pub const HOLD_TOLERANCE_MN: i32 = 40_000;

/// The PLC handshake (board pins; Modbus status bits).
///
/// Inputs: **DOCK** (level: asserted = "be docked", released = "be undocked"; debounced
/// over two control steps; acted on at its edges — after a reset or a fault the PLC
/// releases and asserts it again), **E-STOP** (normally closed: open — pressed or a
/// broken wire — is a stop). Outputs, active high (a dead controller reads as not
/// ready, not mated):
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Handshake {
    /// DOCK input, as filtered.
    pub dock: bool,
    /// E-STOP input open (stopping).
    pub estop: bool,
    /// READY: idle, homed, locked, calibrated, cone not worn out, E-STOP closed, no
    /// technician in maintenance mode.
    pub ready: bool,
    /// MATED: connectors engaged — at the mated position, the force in the hold
    /// envelope, no undock under way; low before any extraction starts.
    pub mated: bool,
    /// FAULT: a latched fault (or the overload back-off).
    pub fault: bool,
    /// MAINTENANCE: the cone past its warning level (or worn out).
    pub maintenance: bool,
}

/// Tries a counter snapshot (or a sector pre-erase) gets, one per rest, before the
/// controller raises [`FaultKind::Storage`].
pub const STORAGE_ATTEMPTS: u8 = 3;

/// The docking controller.
pub struct Controller<B: Bsp> {
    cfg: ControllerConfig,
    prop: Propulsion<B::EnN, B::Dir, B::Pulses>,
    lock: LockActuator<B::LockIn1, B::LockIn2>,
    home: B::Home,
    end: B::End,
    locked: B::Locked,
    released: B::Released,
    stop: B::Stop,
    wdg: B::Wdg,
    options: B::Options,
    seq: Sequencer,
    /// Sample period, µs.
    period_us: u64,
    /// Bumped when a fault is cleared: the kernel forgets its history.
    clear_epoch: u32,
    /// Switch debouncing: the raw reading of the last step and the accepted state.
    /// ([`Switches::bits`]: the filter works on all four at once.)
    switch_raw: u8,
    switches: u8,
    /// When the input filters (the switches, DOCK) last took a reading ([`FILTER_GAP`]).
    filtered_at_us: Option<u64>,
    last_step_us: Option<u64>,
    pending: Option<Request>,
    /// Who asked for `pending`: its gate ([`Controller::gate`]) is checked again at the
    /// step that runs it.
    pending_source: Source,
    /// Who started the docking under way (or the last one): the PLC may withdraw its
    /// own docking while a technician holds maintenance mode ([`Self::gate`]).
    docking_source: Source,
    /// When `pending` was issued, if its client said ([`Controller::issued_at`]): the
    /// first character of a Modbus frame, a console line's (µs since boot, low 32 bits,
    /// the E-STOP interrupt's clock).
    pending_issued_us: Option<u32>,
    /// What the next request's client says of its issue ([`Controller::issued_at`]).
    issued_hint: Option<u32>,
    odo: Odometer,
    /// The current cone's micrometer readings (not its baseline), oldest first.
    readings: heapless::Vec<Measurement, { odometer::READINGS_KEPT }>,
    /// The wear estimate's fit to them.
    fit: Fit,
    /// [`Controller::wear_level`] and [`Controller::wear_estimate`] as of `level_key`
    /// ([`Controller::wear_key`]): the estimate costs ~53 k instructions on the M4
    /// (`vboard estimate-cost`, since issue 36), too much for every `status` or Modbus
    /// read while the console or the PLC holds the controller.
    level: WearLevel,
    estimate: Estimate,
    level_key: Option<WearKey>,
    /// Stage 2, guard: the force, the limit and what the kernel's verdicts left.
    guard: GuardState,
    /// The load cell's calibration and tare (stage 3 keeps its zero-load samples).
    cell: CellState,
    /// Stage 4, phase: the contact phase and its cross-check with the force.
    contact: ContactState,
    /// Stage 5, PLC inputs: DOCK's filter, E-STOP's edges and level, the hold envelope, maintenance mode.
    plc: PlcState,
    /// Stages 1 and 7: the stops seen and the stop latch's gate.
    gate: GateState,
    /// The odometer flash: the log, what waits for a rest, the storage faults (written by `background` only at rest).
    store: StoreState<B::Flash>,
    /// What the console and the log report: faults, events, resets, crashes, the stack.
    diag: DiagState,
    /// The docking signature: capture, verdicts, reference, counts, and its store.
    sig: B::Sig,
}

/// Stage 2, guard: the force, the limit and what the kernel's verdicts left.
struct GuardState {
    force_mn: i32,
    /// The force at the overload trip that started the back-off, mN.
    trip_force_mn: i32,
    limit_mn: i32,
    warning: bool,
    peak_force_mn: i32,
    overload_trips: u32,
    disabled_at_us: Option<u64>,
}

/// The load cell's calibration and tare (stage 3 keeps its zero-load samples).
struct CellState {
    /// A technician's calibration is in flash: without one the machine does not dock.
    calibrated: bool,
    cal: Calibration,
    /// The calibration as set by a technician (the tare moves `cal.offset` per cycle).
    base_cal: Calibration,
    /// Raw codes of the last samples taken at rest (Idle or Faulted): the per-cycle tare
    /// and the technician's calibration both average them.
    recent_raw: Deque<i32, TARE_SAMPLES>,
}

/// Stage 4, phase: the contact phase and its cross-check with the force.
struct ContactState {
    phase: Option<ContactPhase>,
    mismatch_reported: bool,
    mismatch_run: u8,
}

/// Stage 5, PLC inputs: DOCK's filter, E-STOP's edges and level, the hold envelope, maintenance mode.
struct PlcState {
    /// DOCK input: last raw reading, filtered level.
    dock_raw: bool,
    dock_seen: bool,
    dock: bool,
    /// E-STOP input open.
    estop_open: bool,
    /// A technician's maintenance mode at the console: remote motion locked out.
    maintenance_mode: bool,
    /// A firmware update is under way (console `update`): READY low, every request but
    /// a stop refused, from any source.
    updating: bool,
    /// The E-STOP interrupt's record as last read, and how many of its edges the
    /// control step has consumed.
    estop_events: EstopEvents,
    estop_edges_seen: u32,
    /// Consecutive samples outside the hold envelope while mated.
    hold_out: u8,
    /// The PLC inputs were read once since the reset.
    plc_read: bool,
}

/// Stages 1 and 7: the stops seen and the stop latch's gate.
struct GateState {
    /// The highest stop number the controller has seen (re-arm only up to it).
    seen_stop: u32,
    /// Consecutive steps the stop latch refused to re-arm with motion commanded.
    gate_refused: u8,
    /// An unaccounted stop waits for the sequencer (raised at the next step).
    unseen_stop_due: bool,
}

/// The odometer flash: the log, what waits for a rest, the storage faults (written by `background` only at rest).
struct StoreState<F: NorFlash> {
    log: Option<RecordLog<F>>,
    open_report: OpenReport,
    /// A counter snapshot waits for a moment with every motor off.
    persist_pending: bool,
    /// The pending snapshot ends a cycle (a history entry).
    persist_cycle_end: bool,
    storage_errors: u32,
    /// Records made when the flash may not be written (an audit record while the axis
    /// is held, or a Modbus reply is on the line), waiting for the next rest.
    record_queue: Deque<QueuedRecord, RECORD_QUEUE>,
    /// Records the full queue could not take.
    records_dropped: u32,
    /// A Modbus reply is on the line (the board's RS-485 driver is enabled): an erase
    /// now would stall the CPU with DE high and cut the reply.
    bus_busy: bool,
    /// Failed record writes (or erases) in a row, up to [`STORAGE_ATTEMPTS`].
    storage_failures: u8,
    /// The flash refused [`STORAGE_ATTEMPTS`] times: no more tries until a fault clear.
    storage_blocked: bool,
    /// A storage fault waits for the sequencer (raised at the next step it can latch).
    storage_fault_due: bool,
    /// The newest completed cycles as recorded in flash, oldest first.
    recent_cycles: Deque<HistoryEntry, HISTORY_KEPT>,
    /// The newest record of each kind a client reads on request ([`CACHED_KINDS`]:
    /// the PIN, the Modbus settings), loaded at boot and kept as they are written, so
    /// that a console command or a Modbus request never walks the log (milliseconds of
    /// flash reads) while it holds the controller.
    /// `None`: not known (read from the log); `Some(None)`: there is none.
    cached: [Option<Option<heapless::Vec<u8, CACHED_RECORD_MAX>>>; CACHED_KINDS.len()],
}

/// Record kinds kept in RAM ([`Controller::load_record`] answers them without a flash
/// read): those the console and Modbus read per request.
pub const CACHED_KINDS: [u8; 2] = [odometer::kind::PIN, odometer::kind::MODBUS];
/// Longest cached record payload, bytes (a PIN record is 48).
const CACHED_RECORD_MAX: usize = 48;

/// What the console and the log report: faults, events, resets, crashes, the stack.
struct DiagState {
    /// Resets by cause since commissioning (from flash).
    resets: ResetCounts,
    /// This boot's reset cause (`None` until the board reports it).
    last_reset: Option<ResetCause>,
    /// The crash stored last (this boot's, or an earlier one from flash).
    last_crash: Option<Crash>,
    /// Deepest stack use seen (bytes) and the stack's size, as the board measures it.
    stack: Option<(u32, u32)>,
    faults: Deque<FaultRecord, FAULTS_KEPT>,
    fault_count: u32,
    events: Deque<Timed, EVENT_QUEUE>,
    events_dropped: u32,
    /// The running image, the one before it, a rollback (issue 21).
    images: crate::update::ImageReport,
}

/// What one control step's stages hand on to the next ([`Controller::step`]).
struct Step {
    now_us: u64,
    now_ms: u64,
    /// The sequencer's state at the step's start.
    state: State,
    /// The kernel's judged sample, if this step has one.
    sample: Option<crate::safety::Sample>,
    /// Counted position, µm.
    pos_um: i32,
    /// The switches, debounced.
    switches: Switches,
    /// The fault this step detected (the first one wins).
    fault: Option<FaultKind>,
    /// The guard tripped (overload or tension) in this step.
    tripped: bool,
    /// This step's readings of the switches and of DOCK advance their two-reading
    /// filters ([`FILTER_GAP`]).
    filter: bool,
}

/// The two-reading input filters (the switches, DOCK: "a change counts once two control
/// steps read it alike") take a reading only at a step at least this fraction of the
/// sample period (numerator, denominator) after the one they last took: two steps run
/// back to back (the control task catching up on samples queued behind a long job at
/// rest, with the PLC's pins read once for all of them) are one reading, not two, so a
/// glitch shorter than a period is still filtered (issue 32; docs/board.md, "What holds
/// between the steps").
const FILTER_GAP: (u64, u64) = (3, 4);

/// Why a command ([`Controller::command`]) was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Refusal {
    /// The E-STOP input is open.
    EstopOpen,
    /// Not idle (docking, moving, faulted or not homed yet).
    NotIdle,
    /// The load cell has no stored calibration.
    Uncalibrated,
    /// The cone is worn out: replace it first.
    WornOut,
    /// Not on the home switch and locked.
    NotHomed,
    /// No docking under way or held.
    NotDocked,
    /// No latched fault.
    NoFault,
    /// Homing is for after a reset.
    AlreadyHomed,
    /// A technician has the machine in maintenance mode at the console: motion
    /// requested from the PLC (Modbus, the DOCK pin) is refused until it ends.
    MaintenanceMode,
    /// A firmware update is being received and verified (console `update`): nothing
    /// but a stop is accepted, from anyone, until it ends (issue 21).
    Updating,
}

/// Who asks for something ([`Controller::command_from`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum Source {
    /// The technician's console (beside the machine).
    Console,
    /// The vehicle's PLC: Modbus or the DOCK pin (remote: locked out in maintenance).
    Plc,
}

impl Refusal {
    /// Stable code (Modbus, logs): 1..=10.
    pub const fn code(self) -> u8 {
        self as u8 + 1
    }
}

impl Refusal {
    /// What the console says (one line; `Display` writes the same).
    pub const fn message(self) -> &'static str {
        match self {
            Self::EstopOpen => "refused: the E-STOP input is open",
            Self::NotIdle => "refused: not idle",
            Self::Uncalibrated => {
                "refused: the load cell is not calibrated (calibrate tare, calibrate span)"
            }
            Self::WornOut => "refused: the cone is worn out (cone replace)",
            Self::NotHomed => "refused: not homed and locked",
            Self::NotDocked => "refused: nothing to undock",
            Self::NoFault => "no fault to clear",
            Self::AlreadyHomed => "already homed (home is for after a reset)",
            Self::MaintenanceMode => {
                "refused: a technician has the machine in maintenance mode (console)"
            }
            Self::Updating => "refused: a firmware update is in progress (console)",
        }
    }
}

impl core::fmt::Display for Refusal {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.message())
    }
}

/// Why a maintenance action was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum MaintError {
    /// A docking is moving (only `idle` and `faulted` accept maintenance).
    Moving,
    /// A motor output is still on (the axis held after a pull while mated included),
    /// or a Modbus reply is on the line: the flash is not written until the machine is
    /// at rest.
    NotAtRest,
    /// The serial number is empty, too long, or not `[A-Za-z0-9_-]`.
    BadSerial,
    /// The record could not be written to flash (nothing was changed).
    Storage,
    /// Not an HX711 rate (10 or 80 samples/s).
    BadRate,
    /// The cone has a baseline already.
    BaselineExists,
    /// The cone has docked: its bore is no longer its bore when new.
    BaselineAfterUse,
    /// The option bytes could not be programmed (locked, write-protected, or the
    /// flash interface reported an error).
    OptionBytes,
    /// This image runs on trial after an update (not confirmed yet): DFU holds the image
    /// a rollback needs, so no update may write it (issue 31).
    OnTrial,
}

impl MaintError {
    /// What the console says (one line; `Display` writes the same).
    pub const fn message(self) -> &'static str {
        match self {
            Self::Moving => "refused while a docking is moving",
            Self::NotAtRest => {
                "the flash is written only at rest (a motor on, the axis held, or a Modbus \
                 reply on the line); try again at rest"
            }
            Self::BadSerial => "serial must be 1-20 characters of A-Z a-z 0-9 _ -",
            Self::Storage => "could not write to the odometer flash; nothing changed",
            Self::BadRate => "the HX711 samples at 10 or 80 per second (its RATE pin)",
            Self::BaselineExists => {
                "the cone has its baseline already (a new cone: cone replace ... --bore)"
            }
            Self::OptionBytes => {
                "the option bytes could not be programmed (flash interface error; see the log)"
            }
            Self::OnTrial => {
                "this image is on trial, not confirmed (DFU holds the image a rollback needs): it confirms itself at rest once the load cell answers, see `version`"
            }
            Self::BaselineAfterUse => {
                "the cone has docked since it was installed: its bore is no longer its new \
                 bore, so it cannot be the baseline (the nominal 26.000 mm stays assumed)"
            }
        }
    }
}

impl core::fmt::Display for MaintError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.message())
    }
}

/// Why a calibration was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum CalibrateError {
    /// A docking is moving.
    Moving,
    /// Fewer than 8 samples taken at rest yet.
    NotEnoughSamples,
    /// The reading is implausible (tare beyond a quarter of full scale, span too small
    /// or of the wrong sign).
    Implausible,
    /// The calibration could not be stored.
    Storage,
}

impl CalibrateError {
    /// What the console says (one line; `Display` writes the same).
    pub const fn message(self) -> &'static str {
        match self {
            Self::Moving => "refused while a docking is moving",
            Self::NotEnoughSamples => "not enough samples at rest yet; try again in a second",
            Self::Implausible => "implausible reading; check the load cell and the applied load",
            Self::Storage => "could not write to the odometer flash; nothing changed",
        }
    }
}

impl core::fmt::Display for CalibrateError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.message())
    }
}

/// A calibration record as laid out in flash (drawn at [`calibration_to_bytes`]).
#[derive(FromBytes, IntoBytes, Immutable, KnownLayout, Unaligned)]
#[repr(C)]
struct CalibrationLayout {
    offset_counts: I32,
    mn_per_count_q32: I64,
}

/// Bytes of a calibration record.
pub const CALIBRATION_LEN: usize = size_of::<CalibrationLayout>();

/// Encode a calibration record, kind [`odometer::kind::CALIBRATION`] (12 bytes, LE),
/// declared once as `CalibrationLayout`:
///
/// ```text
///  0                4                                12
///  +----------------+--------------------------------+
///  | offset_counts  | mn_per_count_q32               |
///  | i32            | i64 (Q32.32 mN per count)      |
///  +----------------+--------------------------------+
/// ```
pub fn calibration_to_bytes(c: &Calibration) -> [u8; CALIBRATION_LEN] {
    let layout = CalibrationLayout {
        offset_counts: c.offset_counts.into(),
        mn_per_count_q32: c.mn_per_count_q32.into(),
    };
    zerocopy::transmute!(layout)
}

/// Decode a calibration record; `None` if malformed or implausible.
pub fn calibration_from_bytes(b: &[u8]) -> Option<Calibration> {
    let l = CalibrationLayout::read_from_bytes(b).ok()?;
    let c = Calibration {
        offset_counts: l.offset_counts.get(),
        mn_per_count_q32: l.mn_per_count_q32.get(),
    };
    (c.mn_per_count_q32 > 0 && Calibration::tare_plausible(c.offset_counts)).then_some(c)
}

/// Completed cycles [`Controller::history`] keeps in RAM (the console's `history` asks
/// for at most this many).
pub const HISTORY_KEPT: usize = 100;

/// One completed cycle as recorded in flash (newest first from [`Controller::history`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct HistoryEntry {
    /// Lifetime cycle number.
    pub lifetime_cycle: u32,
    /// Cycle number on its cone.
    pub cone_cycle: u32,
    /// Cone id.
    pub cone_id: u16,
    /// This cycle's load–distance, Q63.1 mN·µm.
    pub w_q1: u64,
    /// Cone wear after it, nm.
    pub wear_nm: u32,
}

/// Errors that stop the controller from starting.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum StartError {
    /// A motor output could not be put into its safe state.
    Pin,
}

/// The payload of the newest record of `kind` in `log`, copied into `buf` (`None`: none,
/// or the log unreadable). One out-of-line read for the constructor's six: the
/// `Result<Option<Record>>` each returned by value and copied through `ok`, `flatten` and
/// `and_then` at every call cost 0.4 KB of flash (issue 20).
#[inline(never)]
fn newest<'b, F: NorFlash>(
    log: &mut Option<RecordLog<F>>,
    kind: u8,
    buf: &'b mut [u8; PAYLOAD_MAX],
) -> Option<&'b [u8]> {
    let r = log.as_mut()?.latest(kind).ok()??;
    let d = r.data();
    let dst = buf.get_mut(..d.len())?;
    dst.copy_from_slice(d);
    Some(dst)
}

fn closed<P: InputPin>(p: &mut P) -> Result<bool, ()> {
    p.is_low().map_err(|_| ())
}

/// Insertion sort, for the [`TARE_SAMPLES`] codes of a tare: the order `sort_unstable`
/// gives (integers: any correct sort gives the same slice), without the 3.3 KB of
/// its general-purpose quicksort and sorting networks in the image.
fn sort_small(v: &mut [i32]) {
    for i in 1..v.len() {
        let mut j = i;
        while j > 0 {
            match v.get_mut(j - 1..=j) {
                Some([a, b]) if *a > *b => core::mem::swap(a, b),
                _ => break,
            }
            j -= 1;
        }
    }
}

/// The interquartile mean of up to [`TARE_SAMPLES`] raw codes (`None` below
/// [`TARE_MIN_SAMPLES`]): sorted, `n / 4` dropped at each end, the rest averaged.
fn rest_zero_code(codes: impl Iterator<Item = i32>) -> Option<i32> {
    let mut v: heapless::Vec<i32, TARE_SAMPLES> = codes.take(TARE_SAMPLES).collect();
    if v.len() < TARE_MIN_SAMPLES {
        return None;
    }
    sort_small(&mut v);
    let cut = v.len() / 4;
    let mid = v.get(cut..v.len() - cut)?;
    let n = i64::try_from(mid.len()).ok()?.max(1);
    i32::try_from(mid.iter().map(|&c| i64::from(c)).sum::<i64>() / n).ok()
}

impl HistoryEntry {
    /// The history entry of a cycle-end counter snapshot.
    fn of(s: &StateRecord) -> Self {
        Self {
            lifetime_cycle: s.life.cycles,
            cone_cycle: s.cone_cycles,
            cone_id: s.cone_id,
            w_q1: s.last_cycle_q1,
            wear_nm: odometer::depth_nm(odometer::equivalent_cycles_q32(s.cone_w_q1, s.material)),
        }
    }
}

impl<B: Bsp> Controller<B> {
    /// Take the parts, put every motor output in its safe state, start at `now_us`.
    pub fn new(parts: Parts<B>, cfg: ControllerConfig) -> Result<Self, StartError> {
        let mut slot = None;
        Self::new_with(parts, cfg, |c| slot.insert(c))?;
        // `new_with` placed the controller when it returned `Ok`.
        slot.ok_or(StartError::Pin)
    }

    /// [`Controller::new`], built in `slot` (the board's static): the controller is
    /// never built on the stack and copied from there (it is KiBs: init's stack frame,
    /// and the code that built and then copied it, issue 20). Nothing is written to
    /// `slot` unless this returns `Ok`.
    pub fn new_in(
        slot: &mut core::mem::MaybeUninit<Self>,
        parts: Parts<B>,
        cfg: ControllerConfig,
    ) -> Result<&mut Self, StartError> {
        Self::new_with(parts, cfg, |c| slot.write(c))
    }

    /// The constructor: the controller is built by `place`, where it will live.
    #[inline(always)]
    fn new_with<'s>(
        parts: Parts<B>,
        cfg: ControllerConfig,
        place: impl FnOnce(Self) -> &'s mut Self,
    ) -> Result<&'s mut Self, StartError> {
        let prop = Propulsion::new(parts.en_n, parts.dir, parts.pulses, cfg.machine)
            .map_err(|_| StartError::Pin)?;
        let lock =
            LockActuator::new(parts.lock_in1, parts.lock_in2).map_err(|_| StartError::Pin)?;
        // The counters come back from flash; a log that cannot even be read leaves the
        // odometer in RAM (reported; nothing is written over what may still be there).
        let (mut log, open_report) = match odometer::open_log(parts.flash) {
            Ok((log, report)) => (Some(log), report),
            Err(_) => (None, OpenReport::default()),
        };
        let mut buf = [0u8; PAYLOAD_MAX];
        let cone =
            newest(&mut log, odometer::kind::CONE, &mut buf).and_then(odometer::cone_from_bytes);
        let state =
            newest(&mut log, odometer::kind::STATE, &mut buf).and_then(StateRecord::from_bytes);
        if log.is_none() {
            error!("odometer flash unreadable: wear is counted in RAM only");
        } else if open_report.corrupt > 0 {
            warn!(
                "odometer log: {=u32} corrupt or torn record(s) skipped",
                open_report.corrupt
            );
        }
        let fresh = cone.is_none();
        // A technician's calibration from flash overrides the built-in default; without
        // one the machine refuses to dock (the default is a datasheet guess).
        let stored_cal = newest(&mut log, odometer::kind::CALIBRATION, &mut buf)
            .and_then(calibration_from_bytes);
        let calibrated = stored_cal.is_some();
        if !calibrated {
            warn!("load cell not calibrated: docking refused until a technician calibrates it");
        }
        let cal0 = stored_cal.unwrap_or(cfg.calibration);
        // The HX711's rate as commissioned (else the build's default).
        let mut cfg = cfg;
        if let Some(st) =
            newest(&mut log, odometer::kind::SETTINGS, &mut buf).and_then(Settings::from_bytes)
        {
            cfg.sample_rate_sps = st.rate_sps;
        }
        let resets = newest(&mut log, odometer::kind::RESETS, &mut buf)
            .and_then(ResetCounts::from_bytes)
            .unwrap_or_default();
        let last_crash =
            newest(&mut log, odometer::kind::CRASH, &mut buf).and_then(Crash::from_bytes);
        let odo = restore(cfg.wear, cone, state, cfg.default_material);

        info!(
            "odometer: cone {=u16} ({=str}), {=u32} cycles, wear {=u32} nm; lifetime {=u32} cycles",
            odo.cone().id,
            odo.cone().material.name(),
            odo.cone().cycles,
            odo.wear_nm(),
            odo.lifetime().cycles
        );
        let me = place(Self {
            sig: parts.sig,
            cfg,
            prop,
            lock,
            home: parts.home,
            end: parts.end,
            locked: parts.locked,
            released: parts.released,
            stop: parts.stop,
            wdg: parts.wdg,
            options: parts.options,
            seq: Sequencer::new(cfg.machine),
            period_us: 1_000_000 / cfg.sample_rate_sps.max(1) as u64,
            clear_epoch: 0,
            switch_raw: 0,
            switches: 0,
            filtered_at_us: None,
            last_step_us: None,
            pending: None,
            pending_source: Source::Console,
            docking_source: Source::Console,
            pending_issued_us: None,
            issued_hint: None,
            odo,
            readings: heapless::Vec::new(),
            fit: Fit::prior(),
            level: WearLevel::Ok,
            estimate: Estimate::default(),
            level_key: None,
            guard: GuardState {
                force_mn: 0,
                trip_force_mn: 0,
                limit_mn: cfg.guard.hard_limit_mn,
                warning: false,
                peak_force_mn: 0,
                overload_trips: 0,
                disabled_at_us: None,
            },
            cell: CellState {
                calibrated,
                cal: cal0,
                base_cal: cal0,
                recent_raw: Deque::new(),
            },
            contact: ContactState {
                phase: None,
                mismatch_reported: false,
                mismatch_run: 0,
            },
            plc: PlcState {
                dock_raw: false,
                dock_seen: false,
                dock: false,
                estop_open: false,
                maintenance_mode: false,
                updating: false,
                estop_events: EstopEvents::default(),
                estop_edges_seen: 0,
                hold_out: 0,
                plc_read: false,
            },
            gate: GateState {
                seen_stop: 0,
                gate_refused: 0,
                unseen_stop_due: false,
            },
            store: StoreState {
                log,
                open_report,
                persist_pending: false,
                persist_cycle_end: false,
                storage_errors: 0,
                record_queue: Deque::new(),
                records_dropped: 0,
                bus_busy: false,
                storage_failures: 0,
                storage_blocked: false,
                storage_fault_due: false,
                recent_cycles: Deque::new(),
                cached: [None, None],
            },
            diag: DiagState {
                resets,
                last_reset: None,
                last_crash,
                stack: None,
                faults: Deque::new(),
                fault_count: 0,
                events: Deque::new(),
                events_dropped: 0,
                images: crate::update::ImageReport::UNKNOWN,
            },
        });
        me.load_readings();
        me.load_history();
        me.load_cached_records();
        let cone_id = me.odo.cone().id;
        let sig = &mut *me.sig;
        if let Some(st) = sig.store.as_mut() {
            sig.monitor.load(st, cone_id);
        }
        // The switches as they are now: the filter starts from them.
        if let (Ok(home), Ok(end), Ok(locked), Ok(released)) = (
            closed(&mut me.home),
            closed(&mut me.end),
            closed(&mut me.locked),
            closed(&mut me.released),
        ) {
            me.switch_raw = Switches {
                home,
                end,
                locked,
                released,
            }
            .bits();
            me.switches = me.switch_raw;
        }
        if fresh {
            // A new machine: record its first cone so its identity survives.
            me.write_cone_record();
        }
        Ok(me)
    }

    fn write_cone_record(&mut self) {
        let bytes = odometer::cone_to_bytes(self.odo.cone());
        if let Some(l) = self.store.log.as_mut() {
            if l.append(odometer::kind::CONE, &bytes).is_err() {
                self.store.storage_errors = self.store.storage_errors.saturating_add(1);
                error!("odometer: cone record not written");
            }
        }
    }

    /// Background work, off the control step: judge a stroke the signature's capture
    /// ended; count the load–distance of a cycle cut short, write the pending counter
    /// snapshot and the signature's records, pre-erase the next sector if due — the
    /// flash only at rest (power-up, idle, faulted) with every motor off: a flash
    /// erase stalls the CPU for up to 2 s. The board runs it at its lowest priority; the
    /// rig after each step.
    pub fn background(&mut self) {
        // The docking signature's judgement of a stroke that ended (the service's window:
        // thousands of instructions, which the capture of a sample does not carry).
        if let Some(v) = self.sig.monitor.judge_due(&self.cfg.signature) {
            let t_ms = self.last_step_us.unwrap_or(0) / 1000;
            self.push_event(t_ms, Event::Signature(v));
        }
        // The wear level the handshake reports, when what it depends on changed at rest
        // (a cycle's unfinished load-distance counted, a reading, a baseline): here,
        // not in the control step (the estimate's evaluation costs ~53 k instructions on
        // the M4, `vboard estimate-cost`). A cycle's end refreshes it in its step (the
        // cycle's record carries the level), and a start's gate refreshes it before it
        // decides, so no docking starts on a level older than its step.
        if self.at_rest() {
            self.refresh_level();
            // One failed write per rest at most: the snapshot waits while a queued
            // record ahead of it fails (both go to the same flash).
            let queue_written = self.write_queued_records();
            // A cycle that ended in a fault (or a recovery that touched the cone) left
            // load–distance no completed cycle will count: it is the cone's now.
            let w = self.odo.fold_pending();
            if w > 0 {
                info!(
                    "odometer: {=u64} mN·µm of an unfinished cycle counted",
                    w / 2
                );
                self.store.persist_pending = true;
            }
            // The odometer first; the signature's store only in a turn the odometer
            // left unused (one flash job, and at most one erase, a turn), and not
            // after a queued record failed (one failed write per rest).
            let odometer_busy = !queue_written
                || self.store.persist_pending
                || self
                    .store
                    .log
                    .as_ref()
                    .is_some_and(|l| l.needs_maintenance());
            if queue_written {
                self.persist();
            }
            if !odometer_busy && !self.plc.updating {
                self.persist_signature();
            }
        }
    }

    /// The signature's turn at the flash: a part of a record (the store's
    /// `WRITE_BUDGET`), or one pre-erase.
    // Out of line: `vboard signature-cost` meters it by its symbol.
    #[inline(never)]
    fn persist_signature(&mut self) {
        let sig = &mut *self.sig;
        let Some(st) = sig.store.as_mut() else {
            return;
        };
        if sig.monitor.persist_pending() {
            sig.monitor
                .persist(st, crate::signature::store::WRITE_BUDGET);
        } else if st.needs_maintenance() && st.maintain().is_err() {
            error!("signature: sector pre-erase failed");
        }
    }

    /// The docking signature's capture of the newest sample, off the control step: the
    /// board's service task calls it after each step, the rig after each tick.
    /// `sample_us` is when the safety kernel read its newest sample
    /// ([`crate::safety::SafetyKernel::last_sample_us`]); a sample no step has taken
    /// yet waits for the next call, one seen already is ignored. The force is the one
    /// the step judged, the depth the position it counted.
    // Out of line: `vboard signature-cost` meters it by its symbol (one call a service
    // turn; with this and `persist_signature` out of line the image is 232 B smaller).
    #[inline(never)]
    pub fn capture(&mut self, sample_us: Option<u64>) {
        let Some(t_us) = sample_us else {
            return;
        };
        if self.last_step_us.is_none_or(|s| t_us > s) {
            return;
        }
        let stroke = match self.seq.state() {
            State::Inserting { .. } => Some(Stroke::Insertion),
            State::Extracting { .. } => Some(Stroke::Extraction),
            _ => None,
        };
        let docking = Docking {
            lifetime_cycle: self.odo.lifetime().cycles.saturating_add(1),
            cone_cycle: self.odo.cone().cycles.saturating_add(1),
            cone_id: self.odo.cone().id,
        };
        let depth_um = self.prop.position_um() - self.cfg.machine.engage_um;
        let force_mn = self.guard.force_mn;
        if let Some(v) = self.sig.monitor.tap(
            &self.cfg.signature,
            t_us,
            depth_um,
            force_mn,
            stroke,
            docking,
        ) {
            self.push_event(t_us / 1000, Event::Signature(v));
        }
    }

    /// The docking signature's monitor (verdicts, counts, the newest capture).
    pub fn signature(&self) -> &Monitor<B::SigMem> {
        &self.sig.monitor
    }

    /// The signature's state for the PLC and `wear`.
    pub fn signature_status(&self) -> SignatureStatus {
        SignatureStatus::of(
            &self.sig.monitor,
            &self.cfg.signature,
            crate::profile::V0_UM_PER_S / self.cfg.sample_rate_sps.max(1),
        )
    }

    /// Copy curve `which` into `out` (`curve`); `false`: there is none.
    pub fn curve(&mut self, which: Which, out: &mut CurveView) -> bool {
        let sig = &mut *self.sig;
        out.fill(which, &sig.monitor, sig.store.as_mut(), &self.cfg.signature)
    }

    /// `history`'s signature columns of lifetime cycle `cycle`.
    pub fn signature_history(&self, cycle: u32) -> Option<HistoryCols> {
        self.sig.monitor.history_cols(cycle)
    }

    /// The signature's store, if its flash could be read.
    pub fn signature_store(&mut self) -> Option<&mut SigStore<B::SigFlash>> {
        self.sig.store.as_mut()
    }

    /// Write the pending counter snapshot, and pre-erase the next sector if due. A
    /// failure is retried at the next rest, [`STORAGE_ATTEMPTS`] times in all; then a
    /// storage fault is raised and nothing more is tried until it is cleared (a retry at
    /// every step would fill a sector with torn slots in seconds).
    fn persist(&mut self) {
        if self.store.storage_blocked {
            return;
        }
        let Some(l) = self.store.log.as_mut() else {
            return;
        };
        let mut failed = false;
        // Only a write that happened clears the failures in a row (a rest with nothing to
        // write must not forget a queued record's failed tries).
        let mut wrote = false;
        if self.store.persist_pending {
            let st = StateRecord::of(&self.odo, self.store.persist_cycle_end);
            let rec = st.to_bytes();
            match l.append(odometer::kind::STATE, &rec) {
                Ok(_) => {
                    if st.cycle_end {
                        if self.store.recent_cycles.is_full() {
                            self.store.recent_cycles.pop_front();
                        }
                        let _ = self.store.recent_cycles.push_back(HistoryEntry::of(&st));
                    }
                    self.store.persist_pending = false;
                    self.store.persist_cycle_end = false;
                    wrote = true;
                }
                Err(_) => {
                    // Kept pending (the counters stay in RAM and in the RAM journal).
                    failed = true;
                    error!("odometer: counter snapshot not written");
                }
            }
        }
        if !self.store.persist_pending && !failed && l.needs_maintenance() {
            if l.maintain().is_err() {
                failed = true;
                error!("odometer: sector pre-erase failed");
            } else {
                wrote = true;
            }
        }
        if !failed {
            if wrote {
                self.store.storage_failures = 0;
            }
            return;
        }
        self.store.storage_errors = self.store.storage_errors.saturating_add(1);
        self.store.storage_failures = self.store.storage_failures.saturating_add(1);
        if self.store.storage_failures >= STORAGE_ATTEMPTS {
            error!(
                "odometer: flash failed {=u8} times in a row; storage fault",
                self.store.storage_failures
            );
            self.store.storage_blocked = true;
            self.store.storage_fault_due = true;
        }
    }

    /// At boot, before the first step (every motor off): count the reset `cause` in
    /// flash, store and report `crash` if the last run ended in one, and take back from
    /// `journals` (the RAM journals the last run left that survived) what the flash
    /// snapshot does not hold yet.
    pub fn boot(&mut self, cause: ResetCause, crash: Option<Crash>, journals: &[Journal]) {
        self.diag.resets.count(cause);
        self.diag.last_reset = Some(cause);
        info!("reset cause: {=str}", cause.name());
        if let Some(c) = crash {
            error!(
                "the last run crashed: {=str} at pc {=u32:#x} (lr {=u32:#x}, cfsr {=u32:#x}, line {=u32})",
                c.kind.name(),
                c.pc,
                c.lr,
                c.cfsr,
                c.line
            );
            self.diag.last_crash = Some(c);
        }
        let before = self.odo.journal();
        let w: u64 = journals.iter().map(|j| self.odo.recover(j)).sum();
        {
            if self.odo.journal() != before {
                warn!(
                    "odometer: {=u64} mN·µm and {=u32} cycle(s) the reset cut off recovered from RAM",
                    w / 2,
                    self.odo.cone().cycles.saturating_sub(before.cone_cycles)
                );
                self.store.persist_pending = true;
            }
        }
        if let Some(l) = self.store.log.as_mut() {
            let mut ok = l
                .append(odometer::kind::RESETS, &self.diag.resets.to_bytes())
                .is_ok();
            if let Some(c) = crash {
                ok &= l.append(odometer::kind::CRASH, &c.to_bytes()).is_ok();
            }
            if !ok {
                self.store.storage_errors = self.store.storage_errors.saturating_add(1);
            }
        }
    }

    /// The counters a reset must not lose, for the board's RAM journal (after every
    /// step).
    pub fn journal(&self) -> Journal {
        self.odo.journal()
    }

    /// The board's measurement of the stack: deepest use and size, bytes.
    pub fn set_stack_usage(&mut self, used: u32, size: u32) {
        self.diag.stack = Some((used, size));
    }

    /// Resets by cause since commissioning.
    pub fn reset_counts(&self) -> ResetCounts {
        self.diag.resets
    }

    /// This boot's reset cause.
    pub fn last_reset(&self) -> Option<ResetCause> {
        self.diag.last_reset
    }

    /// The last crash on record.
    pub fn last_crash(&self) -> Option<Crash> {
        self.diag.last_crash
    }

    /// Deepest stack use and the stack's size, bytes (`None` off the board).
    pub fn stack_usage(&self) -> Option<(u32, u32)> {
        self.diag.stack
    }

    /// Ask for something; acted on in the next control step.
    ///
    /// A pending [`Request::Stop`] is never replaced by another request.
    pub fn request(&mut self, r: Request) {
        self.queue(Source::Console, r);
    }

    /// Queue `r` from `source` for the next step, unless a stop waits there: a stop
    /// always wins.
    fn queue(&mut self, source: Source, r: Request) {
        if self.pending != Some(Request::Stop) {
            self.pending = Some(r);
            self.pending_source = source;
            self.pending_issued_us = self.issued_hint;
        }
    }

    /// The HX711's output data rate in force, samples/s (commissioned, or the default).
    pub fn sample_rate_sps(&self) -> u32 {
        self.cfg.sample_rate_sps
    }

    /// Store the HX711's rate (technician action, at rest): it takes effect at the next
    /// boot.
    pub fn store_rate(&mut self, rate_sps: u32) -> Result<(), MaintError> {
        let st = Settings { rate_sps };
        if Settings::from_bytes(&st.to_bytes()).is_none() {
            return Err(MaintError::BadRate);
        }
        self.store_record(odometer::kind::SETTINGS, &st.to_bytes())
    }

    /// The sample period, µs: step at least this often.
    pub fn period_us(&self) -> u64 {
        self.period_us
    }

    /// Whether a step is due at `now_us` without a kernel event (a period has passed).
    pub fn step_due(&self, now_us: u64) -> bool {
        self.last_step_us
            .is_none_or(|t| now_us.saturating_sub(t) >= self.period_us)
    }

    /// One control step at `now_us` for the kernel's event `ev` (`None`: a period passed
    /// without one).
    pub fn step(&mut self, now_us: u64, ev: Option<KernelEvent>) -> PollResult {
        // The stages in order; each reads and writes its own part of the controller
        // and hands on what the next needs in `st`.
        let (mut st, dt_us) = self.stage_sample(now_us, ev);
        self.stage_guard(&mut st);
        self.stage_odometer(&st);
        self.stage_phase(&st);
        self.stage_plc(&mut st);
        let out = self.stage_sequencer(&mut st);
        self.stage_outputs(&st, &out);
        self.stage_watchdog(dt_us);
        PollResult {
            stepped: true,
            sampled: st.sample.is_some(),
            tripped: st.tripped,
        }
    }

    /// Stage 1, **sample**: the time, the stops the kernel's event reports, the counted
    /// position, the switches (debounced) and the I/O faults.
    fn stage_sample(&mut self, now_us: u64, ev: Option<KernelEvent>) -> (Step, u64) {
        let sample = match ev {
            Some(KernelEvent::Sample(s)) => Some(s),
            _ => None,
        };
        if let Some(n) = ev.and_then(|e| e.stop()) {
            self.gate.seen_stop = self.gate.seen_stop.max(n);
        }
        let dt_us = self
            .last_step_us
            .map_or(self.period_us, |t| now_us.saturating_sub(t));
        self.last_step_us = Some(now_us);
        let filter = self.filtered_at_us.is_none_or(|t| {
            now_us.saturating_sub(t) * FILTER_GAP.1 >= self.period_us * FILTER_GAP.0
        });
        if filter {
            self.filtered_at_us = Some(now_us);
        }
        self.prop.sync();
        let mut fault = match ev {
            Some(KernelEvent::Io { .. }) => Some(FaultKind::Io),
            Some(KernelEvent::Silent { .. }) => Some(FaultKind::SensorDisconnected),
            _ => None,
        };
        let switches = match (
            closed(&mut self.home),
            closed(&mut self.end),
            closed(&mut self.locked),
            closed(&mut self.released),
        ) {
            (Ok(home), Ok(end), Ok(locked), Ok(released)) if filter => {
                self.filter_switches(Switches {
                    home,
                    end,
                    locked,
                    released,
                })
            }
            (Ok(_), Ok(_), Ok(_), Ok(_)) => Switches::from_bits(self.switches),
            _ => {
                fault = Some(FaultKind::Io);
                Switches::default()
            }
        };
        let st = Step {
            now_us,
            now_ms: now_us / 1000,
            state: self.seq.state(),
            sample,
            pos_um: self.prop.position_um(),
            switches,
            fault,
            tripped: false,
            filter,
        };
        (st, dt_us)
    }

    /// Stage 2, **guard**: the kernel's verdict on the sample (it has stopped the
    /// propulsion already if it had to) becomes the force, the limit, a trip, a
    /// warning; any fault but an overload (which backs off under control) turns the
    /// propulsion off now.
    fn stage_guard(&mut self, st: &mut Step) {
        if let Some(smp) = st.sample {
            self.guard.force_mn = smp.force_mn;
            self.guard.peak_force_mn = self.guard.peak_force_mn.max(self.guard.force_mn);
            if matches!(st.state, State::Faulted { .. } | State::BackingOff { .. }) {
                if let Some(f) = self.diag.faults.back_mut() {
                    f.peak_force_mn = f.peak_force_mn.max(self.guard.force_mn);
                }
            }
            if let Some(sf) = smp.sensor {
                st.fault = st.fault.or(Some(sensor_fault(sf)));
            }
            self.guard.limit_mn = smp.limit_mn;
            match smp.verdict {
                Verdict::Trip { .. } => {
                    // The kernel stopped it at the sample; the propulsion driver learns it
                    // here, and the sequencer backs off under control.
                    let _ = self.prop.disable();
                    self.guard.disabled_at_us = Some(smp.t_us);
                    st.tripped = true;
                    self.guard.overload_trips = self.guard.overload_trips.saturating_add(1);
                    if !matches!(st.state, State::BackingOff { .. }) {
                        // The back-off's ceiling: the load may not rise past it.
                        self.guard.trip_force_mn = self.guard.force_mn;
                    }
                    self.odo.record_overload(self.guard.force_mn);
                    self.store.persist_pending = true;
                    st.fault = st.fault.or(Some(FaultKind::Overload));
                }
                Verdict::Tension { .. } => {
                    let _ = self.prop.disable();
                    self.guard.disabled_at_us = Some(smp.t_us);
                    st.tripped = true;
                    st.fault = st.fault.or(Some(FaultKind::Tension));
                }
                Verdict::Warn => {
                    if !self.guard.warning {
                        warn!(
                            "force {=i32} mN above the warning level (limit {=i32} mN)",
                            self.guard.force_mn, self.guard.limit_mn
                        );
                        self.push_event(st.now_ms, Event::ForceWarning(self.guard.force_mn));
                    }
                    self.guard.warning = true;
                }
                Verdict::Ok | Verdict::Suspect => self.guard.warning = false,
            }
        }
        if st.fault.is_some_and(|f| f != FaultKind::Overload) && self.prop.is_enabled() {
            let _ = self.prop.disable();
            self.guard.disabled_at_us = Some(st.now_us);
        }
    }

    /// Stage 3, **odometer**: the sample's load–distance where the rod can touch the
    /// cone, and the zero-load samples for the tare at rest.
    fn stage_odometer(&mut self, st: &Step) {
        let Some(smp) = st.sample else { return };
        // Wear: load × sliding distance wherever the rod can touch the cone (by
        // position, whatever the state: the sample at the cone mouth belongs to the
        // stroke); outside it the chain is broken so sensor noise adds nothing.
        self.odo.record_force(self.guard.force_mn);
        let cone_depth_um = st.pos_um - self.cfg.machine.engage_um;
        if (-CONE_MARGIN_UM..=STROKE_UM + CONE_MARGIN_UM).contains(&cone_depth_um) {
            self.odo.on_contact_sample(st.pos_um, self.guard.force_mn);
        } else {
            self.odo.end_contact();
        }
        if matches!(st.state, State::Idle | State::Faulted { .. }) {
            if self.cell.recent_raw.is_full() {
                self.cell.recent_raw.pop_front();
            }
            let _ = self.cell.recent_raw.push_back(smp.code);
        } else {
            self.cell.recent_raw.clear();
        }
    }

    /// Stage 4, **phase**: the contact phase from the depth, cross-checked with the
    /// force near the 3→4 jump.
    fn stage_phase(&mut self, st: &Step) {
        let depth_um = st
            .state
            .in_compliant_motion()
            .then(|| st.pos_um - self.cfg.machine.engage_um);
        self.track_phase(st.now_ms, depth_um, st.sample.is_some());
    }

    /// Stage 5, **PLC inputs**: DOCK's edges become requests (none in maintenance
    /// mode), E-STOP edges and level latch the fault, and a mated force outside the
    /// hold envelope latches `hold_force`.
    fn stage_plc(&mut self, st: &mut Step) {
        // The PLC: DOCK counts once two steps read it alike (steps a period apart:
        // `FILTER_GAP`), and acts at its edges.
        if st.filter
            && self.plc.dock_raw == self.plc.dock_seen
            && self.plc.dock_raw != self.plc.dock
        {
            self.plc.dock = self.plc.dock_raw;
            let r = match (self.plc.dock, st.state) {
                (true, State::PowerUp) => Some(Request::Home),
                (true, _) => Some(Request::Dock),
                (false, s) if s.is_docking() => Some(Request::Undock),
                (false, _) => {
                    // "Be undocked" withdraws a docking of the PLC's not started yet (it
                    // waits for the tare's zero-load samples): as it aborts one under
                    // way, the level is the request (issue 32, found by the checker;
                    // docs/board.md, "What holds between the steps", rule 6).
                    if self.pending == Some(Request::Dock) && self.pending_source == Source::Plc {
                        self.pending = None;
                        warn!("DOCK released: the docking not started yet is withdrawn");
                    }
                    None
                }
            };
            // Through the same gate as the console's and Modbus's commands. A refused
            // edge is consumed, not deferred: the PLC asks again (after maintenance,
            // once READY).
            if let Some(r) = r {
                if let Err(why) = self.command_from(Source::Plc, r) {
                    warn!("DOCK {} refused ({})", r, why);
                    self.push_event(st.now_ms, Event::RemoteRefused(why));
                }
            }
        }
        if st.filter {
            self.plc.dock_seen = self.plc.dock_raw;
        }
        // E-STOP: every edge its interrupt counted (each one stopped the machine
        // there) latches the fault, however short the pulse; so does the input open.
        let es = self.plc.estop_events;
        let new_edges = es.edges.wrapping_sub(self.plc.estop_edges_seen);
        if new_edges != 0 {
            self.plc.estop_edges_seen = es.edges;
            // Its stops are accounted for by the fault latched here.
            self.gate.seen_stop = self.gate.seen_stop.max(es.stop);
            let open_us = (!self.plc.estop_open).then(|| es.closed_us.wrapping_sub(es.opened_us));
            warn!("E-STOP: {=u32} edge(s), open {} us", new_edges, open_us);
            self.push_event(
                st.now_ms,
                Event::EstopEdges {
                    edges: new_edges,
                    open_us,
                },
            );
        }
        // Whatever the state, a latched E-STOP included: the sequencer keeps it latched
        // and refuses a clear in a step that detects a fault (a clear accepted before
        // these edges must not run past them: `Sequencer::step`). And whatever else
        // this step found: an overload found with it would be answered by the
        // controlled back-off, a motion (issue 32, found by the interleaving checker;
        // docs/board.md, "What holds between the steps", rule 1).
        if new_edges != 0 || self.plc.estop_open {
            st.fault = Some(FaultKind::EmergencyStop);
        }
        // Mated: the force must stay in the hold envelope.
        if let (
            Some(_),
            State::Holding {
                unmating: false, ..
            },
        ) = (st.sample, st.state)
        {
            if (self.guard.force_mn - self.cfg.hold_expected_mn).abs() > HOLD_TOLERANCE_MN {
                self.plc.hold_out = self.plc.hold_out.saturating_add(1);
            } else {
                self.plc.hold_out = 0;
            }
            if self.plc.hold_out >= 2 {
                warn!(
                    "mated force {=i32} mN outside {=i32}±{=i32} mN: the vehicle pulls or drifts",
                    self.guard.force_mn, self.cfg.hold_expected_mn, HOLD_TOLERANCE_MN
                );
                st.fault = st.fault.or(Some(FaultKind::HoldForce));
            }
        } else if !matches!(st.state, State::Holding { .. }) {
            self.plc.hold_out = 0;
        }
    }

    /// Stage 6, **sequencer**: the pending request through its gates (E-STOP, wear
    /// limit, calibration, tare), the faults of this step, the sequencer's decision.
    fn stage_sequencer(&mut self, st: &mut Step) -> crate::sequencer::Outputs {
        let mut request = self.pending.take();
        if let Some(r) = request {
            if let Err(why) = self.gate(self.pending_source, r) {
                // Accepted before a mode that now refuses it was granted.
                request = None;
                warn!("{} refused at its step ({})", r, why);
                self.push_event(st.now_ms, Event::RemoteRefused(why));
            }
        }
        let starting =
            matches!(request, Some(Request::StartCycle | Request::Dock)) && st.state == State::Idle;
        if request == Some(Request::ClearFault)
            && (self.plc.estop_open || self.estop_edge_since_issue(st.now_us))
        {
            request = None;
            error!(
                "clear refused: the E-STOP input is open, or changed since the clear was issued"
            );
            self.push_event(st.now_ms, Event::EstopClearRefusal);
        }
        if starting && self.plc.estop_open {
            request = None;
        }
        if starting && request.is_some() && self.refresh_level() == WearLevel::Limit {
            // Worn out: no new docking until the cone is replaced.
            request = None;
            error!(
                "start refused: cone worn to {=u32} nm (limit {=u32} nm); replace it",
                self.odo.wear_nm(),
                self.cfg.wear.limit_nm
            );
            self.push_event(st.now_ms, Event::WearLimitRefusal);
        }
        if starting && request.is_some() && !self.cell.calibrated {
            request = None;
            error!(
                "start refused: the load cell is not calibrated (calibrate tare, calibrate span)"
            );
            self.push_event(st.now_ms, Event::UncalibratedRefusal);
        }
        if starting && request.is_some() {
            match self.take_tare() {
                TareResult::Ready => self.docking_source = self.pending_source,
                TareResult::NotYet => {
                    // Wait for more zero-load samples (from the same source: its gate
                    // is checked again at the next step).
                    self.pending = request.take();
                }
                TareResult::Implausible => st.fault = st.fault.or(Some(FaultKind::ImplausibleTare)),
            }
        }
        if self.store.storage_fault_due && !matches!(st.state, State::Faulted { .. }) {
            self.store.storage_fault_due = false;
            st.fault = st.fault.or(Some(FaultKind::Storage));
        }
        if core::mem::take(&mut self.gate.unseen_stop_due) {
            st.fault = st.fault.or(Some(FaultKind::UnseenStop));
        }
        let inputs = Inputs {
            now_ms: st.now_ms,
            pos_um: st.pos_um,
            axis_idle: self.prop.is_idle(),
            switches: st.switches,
            fault: st.fault,
            request,
        };
        let out = self.seq.step(&inputs);
        if out.event == Some(SeqEvent::FaultCleared) {
            // The clear ran (not one the sequencer refused for a fault this step
            // detected): the kernel forgets its sample history and restarts its
            // timeout, and the flash gets another STORAGE_ATTEMPTS tries.
            self.clear_epoch = self.clear_epoch.wrapping_add(1);
            self.store.storage_blocked = false;
            self.store.storage_failures = 0;
            self.store.storage_fault_due = false;
        }
        if let Some(ev) = out.event {
            self.on_seq_event(st.now_ms, ev);
        }
        out
    }

    /// Stage 7, **outputs**: the sequencer's commands to the propulsion (through the
    /// stop latch's gate) and the lock.
    fn stage_outputs(&mut self, st: &Step, out: &crate::sequencer::Outputs) {
        if out.zero_position {
            self.prop.set_position_um(0);
        }
        // The driver may be enabled only once every stop the kernel made has been seen
        // here; a stop still in flight keeps it off for this step.
        let gate_open = !matches!(out.axis, AxisCmd::Disabled)
            && (!self.stop.latched() || self.stop.rearm(self.gate.seen_stop));
        // A refusal for one step is a stop whose event is still on its way (it faults
        // the next step); refused twice, the stop is one this controller never heard of
        // (an event lost): a fault, not a silent stall.
        if gate_open || matches!(out.axis, AxisCmd::Disabled) {
            self.gate.gate_refused = 0;
        } else {
            self.gate.gate_refused = self.gate.gate_refused.saturating_add(1);
            if self.gate.gate_refused >= 2 {
                self.gate.gate_refused = 0;
                error!("the stop latch holds the driver off for a stop never reported");
                self.gate.seen_stop = self.gate.seen_stop.max(self.stop.stops());
                self.gate.unseen_stop_due = true;
            }
        }
        let pin_ok = match out.axis {
            _ if !gate_open && !matches!(out.axis, AxisCmd::Disabled) => {
                let _ = self.prop.disable();
                true
            }
            AxisCmd::Disabled => {
                if self.prop.is_enabled() {
                    self.guard.disabled_at_us = Some(st.now_us);
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
        let plan_ok = self
            .prop
            .plan(self.period_us.min(u32::MAX as u64) as u32)
            .is_ok();
        if !(pin_ok && lock_ok && plan_ok) {
            // Could not drive an output: everything off; the next step latches `Io`.
            let _ = self.prop.disable();
            let _ = self.lock.apply(LockCmd::Off);
            self.pending = None;
        }
    }

    /// Stage 8, **watchdog** (fed by a loop that keeps its period). (The wear level the
    /// handshake reports is refreshed at the cycle's end and in the service's window at
    /// rest: [`Self::background`].)
    fn stage_watchdog(&mut self, dt_us: u64) {
        if dt_us <= 3 * self.period_us {
            self.wdg.feed();
        }
    }

    /// The wear level, the estimate computed again first when what it depends on
    /// changed, and both kept ([`Self::wear_key`]): the cycle's end and a start's gate in
    /// the step, the service's window at rest ([`Self::background`]); each evaluates the
    /// estimate only when the key moved.
    #[inline(always)]
    fn refresh_level(&mut self) -> WearLevel {
        let key = self.wear_key();
        if self.level_key != Some(key) {
            let est = self.compute_estimate();
            self.level = self.compute_level(&est);
            self.estimate = est;
            self.level_key = Some(key);
        }
        self.level
    }

    /// What the wear estimate and level depend on: the cone, its equivalent cycles,
    /// its readings, its baseline.
    fn wear_key(&self) -> WearKey {
        (
            self.odo.cone().id,
            self.odo.equivalent_cycles_q32(),
            self.readings.len(),
            self.baseline_or_nominal(),
        )
    }

    /// Switch debouncing: a switch's change counts once two consecutive steps read it,
    /// so one noisy reading never stops, zeroes or faults anything, and a real change
    /// (an overtravel) counts at most one step — one sample period — later.
    fn filter_switches(&mut self, raw: Switches) -> Switches {
        // Per switch (one bit each): the reading where it agrees with the last one, else
        // the accepted state.
        let raw = raw.bits();
        let alike = !(raw ^ self.switch_raw);
        self.switches = (raw & alike) | (self.switches & !alike);
        self.switch_raw = raw;
        Switches::from_bits(self.switches)
    }

    /// What the safety kernel must judge the next samples by: the calibration in force
    /// and the limit of the state and depth the machine is in now. (Inlined: the
    /// control task asks after every step; out of line it was 60 B less and 12
    /// instructions more a step, issue 20.)
    pub fn kernel_config(&self) -> KernelConfig {
        let state = self.seq.state();
        let mode = match state {
            State::BackingOff { .. } => GuardMode::BackOff {
                ceiling_mn: self.guard.trip_force_mn.saturating_add(BACKOFF_RISE_MN),
            },
            s if s.in_compliant_motion() => GuardMode::Cone {
                depth_um: self.prop.position_um() - self.cfg.machine.engage_um,
            },
            _ => GuardMode::Free,
        };
        KernelConfig {
            cal: self.cell.cal,
            mode,
            clear: self.clear_epoch,
        }
    }

    /// Whether a technician's calibration is stored (without one the machine does not
    /// dock).
    pub fn calibrated(&self) -> bool {
        self.cell.calibrated
    }

    /// The zero of the samples at rest, once there are enough of them: their
    /// **interquartile mean** (sorted, a quarter dropped at each end, the middle half
    /// averaged). A load spike — or up to a quarter of the window's samples spiking —
    /// moves it by nothing more than the noise, where a plain mean of 16 samples moves
    /// 22 N for one 350 N spike and fails the tare (`spike_during_tare_neither_faults_nor_moves_the_zero`).
    fn rest_mean_code(&self) -> Option<i32> {
        rest_zero_code(self.cell.recent_raw.iter().copied())
    }

    fn take_tare(&mut self) -> TareResult {
        let Some(mean) = self.rest_mean_code() else {
            return TareResult::NotYet;
        };
        let drift_mn = Calibration {
            offset_counts: self.cell.base_cal.offset_counts,
            ..self.cell.cal
        }
        .to_force_mn(mean);
        if !Calibration::tare_plausible(mean)
            || drift_mn.unsigned_abs() > self.cfg.tare_tolerance_mn.unsigned_abs()
        {
            error!(
                "implausible tare: {=i32} counts ({=i32} mN from calibration)",
                mean, drift_mn
            );
            return TareResult::Implausible;
        }
        self.cell.cal = self.cell.cal.with_tare(mean);
        self.cell.recent_raw.clear();
        TareResult::Ready
    }

    fn track_phase(&mut self, now_ms: u64, depth_um: Option<i32>, sampled: bool) {
        let phase = depth_um.and_then(ContactPhase::at_depth_um);
        if phase != self.contact.phase {
            self.contact.phase = phase;
            if let Some(p) = phase {
                info!("contact phase {=u8}", p.number());
                self.push_event(now_ms, Event::Phase(p));
            }
        }
        if depth_um.is_none() {
            self.contact.mismatch_reported = false;
            self.contact.mismatch_run = 0;
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
            Some(high) if (self.guard.force_mn > JUMP_MID_MN) != high => {
                self.contact.mismatch_run = self.contact.mismatch_run.saturating_add(1);
                if self.contact.mismatch_run >= 3 && !self.contact.mismatch_reported {
                    self.contact.mismatch_reported = true;
                    warn!(
                        "phase {=u8} by position, but {=i32} mN contradicts it",
                        p.number(),
                        self.guard.force_mn
                    );
                    self.push_event(now_ms, Event::PhaseMismatch(p));
                }
            }
            _ => self.contact.mismatch_run = 0,
        }
    }

    fn on_seq_event(&mut self, now_ms: u64, ev: SeqEvent) {
        match ev {
            SeqEvent::Fault(kind) => {
                error!(
                    "fault {=str} in cycle {=u32} at {=u64} ms, force {=i32} mN",
                    kind.name(),
                    self.seq.cycle_number(),
                    now_ms,
                    self.guard.force_mn
                );
                if self.diag.faults.is_full() {
                    self.diag.faults.pop_front();
                }
                let rec = FaultRecord {
                    kind,
                    cycle: self.seq.cycle_number(),
                    phase: self.contact.phase,
                    t_ms: now_ms,
                    peak_force_mn: self.guard.force_mn,
                };
                let _ = self.diag.faults.push_back(rec);
                self.diag.fault_count = self.diag.fault_count.saturating_add(1);
                self.odo.record_fault();
                self.store.persist_pending = true;
            }
            SeqEvent::CycleCompleted(n) => {
                let mut c = self.odo.complete_cycle();
                // The level the machine acts on (the estimate's band, once measured),
                // kept for the handshake (one evaluation of the estimate, at the cycle's
                // end).
                c.level = self.refresh_level();
                info!(
                    "cycle {=u32} completed: cone cycle {=u32}, wear {=u32} nm, remaining {=u32} cycles",
                    n, c.cone_cycle, c.wear_nm, c.remaining_cycles
                );
                match c.level {
                    WearLevel::Ok => {}
                    WearLevel::Warning => {
                        warn!("cone wear {=u32} nm is past the warning level", c.wear_nm)
                    }
                    WearLevel::Limit => error!(
                        "cone wear {=u32} nm reached the limit: replace the cone",
                        c.wear_nm
                    ),
                }
                self.push_event(now_ms, Event::CycleCounted(c));
                self.store.persist_pending = true;
                self.store.persist_cycle_end = true;
            }
            SeqEvent::CycleStarted(n) => {
                self.odo.start_cycle();
                info!("cycle {=u32} started", n)
            }
            SeqEvent::FaultCleared => info!("fault cleared; recovering"),
            SeqEvent::Homed => info!("homed"),
            SeqEvent::RequestRefused(r) => warn!(
                "request {} refused in state {=str}",
                r,
                self.seq.state().name()
            ),
        }
        self.push_event(now_ms, Event::Seq(ev));
    }

    fn push_event(&mut self, t_ms: u64, event: Event) {
        if self.diag.events.is_full() {
            self.diag.events.pop_front();
            self.diag.events_dropped = self.diag.events_dropped.saturating_add(1);
        }
        let _ = self.diag.events.push_back(Timed { t_ms, event });
    }

    /// The oldest unread event.
    pub fn next_event(&mut self) -> Option<Timed> {
        self.diag.events.pop_front()
    }

    /// The PLC's inputs as read now (the board reads its pins before each step): DOCK
    /// asserted, E-STOP open.
    ///
    /// The first reading after a reset sets the DOCK filter without an edge: a DOCK
    /// still asserted from before the reset is not a request (nothing moves after a reset
    /// until one) — the PLC releases and asserts it again.
    ///
    /// `estop` is the E-STOP interrupt's record ([`crate::safety::EstopEdges`]): its
    /// edges latch `emergency_stop` even when the level reads closed again.
    pub fn set_plc(&mut self, dock_asserted: bool, estop_open: bool, estop: EstopEvents) {
        if !self.plc.plc_read {
            self.plc.plc_read = true;
            self.plc.dock = dock_asserted;
            self.plc.dock_seen = dock_asserted;
        }
        self.plc.dock_raw = dock_asserted;
        self.plc.estop_open = estop_open;
        self.plc.estop_events = estop;
    }

    /// A command from a person or the PLC (console, Modbus), checked now: `Ok` when the
    /// request is queued for the next step, or why it cannot be carried out. The same
    /// rules for every source:
    ///
    /// * `Stop` is never refused.
    /// * `Dock` / `StartCycle`: idle, homed and locked, E-STOP closed, calibrated, cone
    ///   not worn out (the READY output).
    /// * `Undock`: a docking under way or held.
    /// * `ClearFault`: a latched fault, E-STOP closed.
    /// * `Home`: after a reset only (power-up), E-STOP closed.
    pub fn command(&mut self, r: Request) -> Result<(), Refusal> {
        self.command_from(Source::Console, r)
    }

    /// [`Self::command`] from `source`: while a technician has the machine in
    /// maintenance mode, everything but `Stop` from the PLC is refused
    /// ([`Refusal::MaintenanceMode`]).
    pub fn command_from(&mut self, source: Source, r: Request) -> Result<(), Refusal> {
        self.check_command(source, r)?;
        self.queue(source, r);
        Ok(())
    }

    /// Whether [`Self::command_from`] would accept `r` from `source` now, and why not:
    /// its rules, without queueing anything. READY is high only when this accepts a dock
    /// from the PLC (docs/board.md, "What holds between the steps").
    pub fn check_command(&self, source: Source, r: Request) -> Result<(), Refusal> {
        self.gate(source, r)?;
        let state = self.seq.state();
        let estop = |me: &Self| {
            if me.plc.estop_open {
                Err(Refusal::EstopOpen)
            } else {
                Ok(())
            }
        };
        match r {
            Request::Stop => {}
            Request::Dock | Request::StartCycle => {
                estop(self)?;
                if state != State::Idle {
                    return Err(Refusal::NotIdle);
                }
                if !self.cell.calibrated {
                    return Err(Refusal::Uncalibrated);
                }
                if self.wear_level() == WearLevel::Limit {
                    return Err(Refusal::WornOut);
                }
                let sw = Switches::from_bits(self.switches);
                if !(sw.home && sw.locked) {
                    return Err(Refusal::NotHomed);
                }
            }
            Request::Undock => {
                if !state.is_docking() {
                    return Err(Refusal::NotDocked);
                }
            }
            Request::ClearFault => {
                estop(self)?;
                if !matches!(state, State::Faulted { .. }) {
                    return Err(Refusal::NoFault);
                }
            }
            Request::Home => {
                estop(self)?;
                if state != State::PowerUp {
                    return Err(Refusal::AlreadyHomed);
                }
            }
        }
        Ok(())
    }

    /// The client of the next request says when it was issued: `issued_us` (µs since
    /// boot, low 32 bits: the E-STOP interrupt's clock), the first character of its
    /// Modbus frame or console line; `None` after the job (a request without it counts
    /// from its acceptance). A clear issued before an E-STOP edge is refused at its
    /// step even when a step before it, or before its acceptance, consumed that edge: the
    /// PLC that sent it, or the technician who typed it, had not seen that edge
    /// (docs/board.md, "What holds between the steps", rule 1; found by the virtual
    /// board's campaign: a clear in flight on the Modbus line as a 50 µs pulse came).
    pub fn issued_at(&mut self, issued_us: Option<u32>) {
        self.issued_hint = issued_us;
    }

    /// Whether an E-STOP edge came after the pending request was issued (and before
    /// `now_us`), by the interrupt's time stamps of the last opening and closing.
    fn estop_edge_since_issue(&self, now_us: u64) -> bool {
        let Some(t) = self.pending_issued_us else {
            return false;
        };
        let es = self.plc.estop_events;
        let window = (now_us as u32).wrapping_sub(t);
        es.edges != 0
            && [es.opened_us, es.closed_us]
                .iter()
                .any(|&e| e != t && e.wrapping_sub(t) <= window)
    }

    /// The modes' gate of [`Self::command_from`], checked when a request is accepted
    /// **and again at the step that runs it** ([`Self::stage_sequencer`]): a mode
    /// granted in between (maintenance mode to the console, an update begun) is in force
    /// from its grant, not from the next request (issue 32; docs/board.md, "What holds
    /// between the steps").
    fn gate(&self, source: Source, r: Request) -> Result<(), Refusal> {
        if self.plc.updating && r != Request::Stop {
            return Err(Refusal::Updating);
        }
        // The PLC's undock of a docking the PLC started stays its own: one started just
        // before a grant would otherwise mate and hold with no way back for the PLC
        // (issue 32's review; item 2's outcome). It starts nothing.
        let own_undock = r == Request::Undock
            && self.docking_source == Source::Plc
            && self.seq.state().is_docking();
        if source == Source::Plc && self.plc.maintenance_mode && r != Request::Stop && !own_undock {
            return Err(Refusal::MaintenanceMode);
        }
        Ok(())
    }

    /// The handshake outputs now.
    pub fn handshake(&self) -> Handshake {
        let state = self.seq.state();
        let sw = Switches::from_bits(self.switches);
        let in_envelope =
            (self.guard.force_mn - self.cfg.hold_expected_mn).abs() <= HOLD_TOLERANCE_MN;
        // As of the last step (cached: see step 7).
        let level = self.level;
        // An E-STOP edge no step has taken yet (the board's control run without a step,
        // between two sample steps, or pended by the service): the E-STOP interrupt
        // drove MATED and the lock low; nothing raises them again before the step that
        // latches the fault (issue 32's review: MATED went low, high, low).
        let unseen_edge = self.plc.estop_events.edges != self.plc.estop_edges_seen;
        let estop = self.plc.estop_open || unseen_edge;
        Handshake {
            dock: self.plc.dock,
            estop: self.plc.estop_open,
            ready: state == State::Idle
                && sw.home
                && sw.locked
                && self.cell.calibrated
                && level != WearLevel::Limit
                && !estop
                && !self.plc.maintenance_mode
                && !self.plc.updating,
            mated: matches!(
                state,
                State::Holding {
                    unmating: false,
                    ..
                }
            ) && in_envelope
                && !estop,
            fault: matches!(state, State::Faulted { .. } | State::BackingOff { .. }),
            maintenance: level >= WearLevel::Warning,
        }
    }

    /// A status snapshot.
    pub fn status(&self) -> Status {
        let state = self.seq.state();
        Status {
            handshake: self.handshake(),
            state,
            phase: self.contact.phase,
            force_mn: self.guard.force_mn,
            limit_mn: self.guard.limit_mn,
            pos_um: self.prop.position_um(),
            cycles_completed: self.seq.cycles_completed(),
            fault: match state {
                State::Faulted { fault } => Some(fault),
                State::BackingOff { .. } => Some(FaultKind::Overload),
                _ => None,
            },
            warning: self.guard.warning,
            peak_force_mn: self.guard.peak_force_mn,
            wear_nm: self.odo.wear_nm(),
            remaining_cycles: self.odo.remaining_cycles(),
            wear_level: self.wear_level(),
        }
    }

    /// Whether maintenance actions are allowed now (nothing moving).
    pub fn is_quiet(&self) -> bool {
        matches!(
            self.seq.state(),
            State::Idle | State::PowerUp | State::Faulted { .. }
        )
    }

    /// A latched state that keeps the axis driven (pulled while mated: the axis holds
    /// the vehicle).
    fn axis_held(&self) -> bool {
        self.seq.state()
            == (State::Faulted {
                fault: FaultKind::HoldForce,
            })
    }

    /// **The one rule for writing the flash** (a record programmed, a sector erased,
    /// by [`Self::background`], [`Self::store_record`] and every maintenance action):
    /// at rest — idle, powering up or faulted with nothing driven — the propulsion
    /// driver off, the lock bridge off, and no Modbus reply on the line. An erase stalls
    /// the CPU with every interrupt masked for up to 2 s: nothing may be moving, held
    /// or talking then.
    // Out of line: every flash writer and the service ask; inlined at each, the image
    // is 324 B larger (issue 31's measurement, which kept this hint and dropped the
    // ones under 256 B).
    #[inline(never)]
    pub fn at_rest(&self) -> bool {
        self.motionless() && !self.store.bus_busy
    }

    /// At rest but for the Modbus line: quiet, nothing held or driven.
    fn motionless(&self) -> bool {
        self.is_quiet()
            && !self.axis_held()
            && !self.prop.is_enabled()
            && self.lock.cmd() == LockCmd::Off
    }

    /// Whether a maintenance action may write the flash now ([`Self::at_rest`]), and
    /// why not.
    fn flash_turn(&self) -> Result<(), MaintError> {
        if !self.is_quiet() {
            Err(MaintError::Moving)
        } else if !self.at_rest() {
            Err(MaintError::NotAtRest)
        } else {
            Ok(())
        }
    }

    /// The brown-out reset level in the option bytes: 3 (2.70 V) .. 0 (off).
    pub fn bor_level(&self) -> u8 {
        self.options.bor_level()
    }

    /// Program brown-out reset level 3 (technician action, at rest: the flash interface
    /// is busy meanwhile). The level found is returned when it was 3 already.
    pub fn program_bor(&mut self) -> Result<u8, MaintError> {
        let from = self.options.bor_level();
        if from == 3 {
            return Ok(3);
        }
        self.flash_turn()?;
        match self.options.program_bor_level_3() {
            Ok(()) => {
                info!("BOR level 3 programmed (was {=u8})", from);
                Ok(from)
            }
            Err(sr) => {
                error!("BOR programming failed: FLASH_SR {=u32:#x}", sr);
                Err(MaintError::OptionBytes)
            }
        }
    }

    /// The console's maintenance mode (a technician logged in): READY drops and the
    /// PLC's motion requests (Modbus, the DOCK pin) are refused while it lasts.
    pub fn set_maintenance_mode(&mut self, on: bool) {
        if on != self.plc.maintenance_mode {
            info!(
                "maintenance mode {=str}",
                if on { "entered" } else { "ended" }
            );
        }
        self.plc.maintenance_mode = on;
    }

    /// Whether a technician has the machine in maintenance mode.
    pub fn maintenance_mode(&self) -> bool {
        self.plc.maintenance_mode
    }

    /// A firmware update begins (console `update`, issue 21): only with nothing moving,
    /// held or driven. A Modbus reply on the line does not refuse it: `begin_update`
    /// writes nothing, and each of the update's flash jobs waits for the line by itself
    /// (the board's `with_owner`), so a PLC that polls does not make `update` fail at
    /// random (refused when the command met one of its replies, up to 7c11783's
    /// successor of issue 32). From now until
    /// [`Self::end_update`] READY is low and every request but a stop is refused, from
    /// the console, Modbus and the DOCK pin alike (a DOCK edge is refused and logged).
    pub fn begin_update(&mut self) -> Result<(), MaintError> {
        if self.diag.images.trial != crate::update::Trial::No {
            return Err(MaintError::OnTrial);
        }
        if !self.is_quiet() {
            return Err(MaintError::Moving);
        }
        if !self.motionless() {
            return Err(MaintError::NotAtRest);
        }
        if !self.plc.updating {
            info!("firmware update: receiving; READY low, requests refused");
        }
        self.plc.updating = true;
        Ok(())
    }

    /// The update ended without a restart (refused, cancelled): requests are taken
    /// again.
    pub fn end_update(&mut self) {
        if self.plc.updating {
            info!("firmware update ended; requests taken again");
        }
        self.plc.updating = false;
    }

    /// Whether a firmware update is under way.
    pub fn updating(&self) -> bool {
        self.plc.updating
    }

    /// What this image and the previous ones are ([`crate::update::ImageReport`]),
    /// as the board found them at boot.
    pub fn images(&self) -> crate::update::ImageReport {
        self.diag.images
    }

    /// The board's word on the images (at boot: [`crate::update::at_boot`]).
    pub fn set_images(&mut self, images: crate::update::ImageReport) {
        self.diag.images = images;
    }

    /// The board's word that a Modbus reply is on the line (its RS-485 driver enabled).
    pub fn set_bus_busy(&mut self, busy: bool) {
        self.store.bus_busy = busy;
    }

    /// Write the records queued for a rest, oldest first (call only at rest); whether the
    /// queue is empty now.
    ///
    /// **A queued record leaves the queue only when it is written, or counted as
    /// dropped** ([`Self::records_dropped`], reported by `faults`; docs/board.md, "What
    /// holds between the steps"). A write that fails leaves it at the head of the queue,
    /// tried again at the next rest under the counter snapshot's rule: one failure more
    /// in a row, [`STORAGE_ATTEMPTS`] of them latch the `storage` fault and nothing is
    /// tried until a clear. Only a log that could not even be opened (no flash to write
    /// to) drops what waits, counted.
    fn write_queued_records(&mut self) -> bool {
        while let Some(r) = self.store.record_queue.front() {
            if self.store.storage_blocked {
                return false;
            }
            let Some(l) = self.store.log.as_mut() else {
                // Nowhere to write it, ever: dropped, and counted.
                let n = self.store.record_queue.len() as u32;
                self.store.record_queue.clear();
                self.store.records_dropped = self.store.records_dropped.saturating_add(n);
                error!("odometer: {=u32} queued record(s) dropped: no log", n);
                return true;
            };
            if l.append(r.kind, &r.data).is_err() {
                error!("odometer: a queued record was not written; kept for the next rest");
                self.store.storage_errors = self.store.storage_errors.saturating_add(1);
                self.store.storage_failures = self.store.storage_failures.saturating_add(1);
                if self.store.storage_failures >= STORAGE_ATTEMPTS {
                    error!(
                        "odometer: flash failed {=u8} times in a row; storage fault",
                        STORAGE_ATTEMPTS
                    );
                    self.store.storage_blocked = true;
                    self.store.storage_fault_due = true;
                }
                return false;
            }
            self.store.storage_failures = 0;
            if let Some(r) = self.store.record_queue.pop_front() {
                self.cache_record(r.kind, &r.data);
            }
        }
        true
    }

    /// A record that may wait (an audit record): written now if the machine is at rest
    /// and nothing waits before it (so the log keeps their order), else — or if the
    /// flash refuses it now — queued for the next rest ([`Self::at_rest`];
    /// [`Self::background`] writes it). `false`: not written and not queued (the queue
    /// was full, or the record too long: counted in [`Self::records_dropped`]).
    pub fn write_or_queue_record(&mut self, kind: u8, data: &[u8]) -> bool {
        if self.at_rest() && self.write_queued_records() {
            if self.store_record(kind, data).is_ok() {
                return true;
            }
            // The flash refused it: one failure more in a row, and the record waits
            // for the next rest like one made out of turn.
            self.store.storage_failures = self.store.storage_failures.saturating_add(1);
        }
        self.queue_record(kind, data)
    }

    /// Queue a record for the next rest. `false`: the queue was full or the record too
    /// long — dropped, and counted ([`Self::records_dropped`]).
    fn queue_record(&mut self, kind: u8, data: &[u8]) -> bool {
        let Ok(data) = heapless::Vec::from_slice(data) else {
            self.store.records_dropped = self.store.records_dropped.saturating_add(1);
            return false;
        };
        if self
            .store
            .record_queue
            .push_back(QueuedRecord { kind, data })
            .is_err()
        {
            self.store.records_dropped = self.store.records_dropped.saturating_add(1);
            error!("odometer: record queue full; a record was dropped");
            return false;
        }
        true
    }

    /// Records waiting for a rest.
    pub fn records_queued(&self) -> usize {
        self.store.record_queue.len()
    }

    /// Records dropped because the queue was full.
    pub fn records_dropped(&self) -> u32 {
        self.store.records_dropped
    }

    /// Install a new cone (technician action): new per-cone counters, lifetime totals and
    /// history untouched. Refused while anything moves. The cone record and a counter
    /// snapshot are written before it returns; if the cone record cannot be written,
    /// nothing changes.
    pub fn replace_cone(&mut self, material: Material, serial: &str) -> Result<(), MaintError> {
        self.replace_cone_measured(material, serial, None)
    }

    /// [`Self::replace_cone`] with the new cone's bore measured before its first
    /// docking (`baseline_um`, µm): its measured wear is the bore's growth from it. The
    /// old cone's summary is kept in flash ([`odometer::RetiredCone`]).
    pub fn replace_cone_measured(
        &mut self,
        material: Material,
        serial: &str,
        baseline_um: Option<u32>,
    ) -> Result<(), MaintError> {
        self.flash_turn()?;
        let ok = !serial.is_empty()
            && serial.len() <= odometer::SERIAL_MAX
            && serial
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'_' || b == b'-');
        if !ok {
            return Err(MaintError::BadSerial);
        }
        let mut next = self.odo.clone();
        next.replace_cone(material, serial);
        if let Some(b) = baseline_um {
            next.set_baseline(b);
        }
        let retired = RetiredCone {
            cone: *self.odo.cone(),
            model_nm: self.odo.wear_nm(),
            measured_nm: self
                .readings
                .last()
                .map(|m| m.wear_nm(self.baseline_or_nominal())),
            readings: self.readings.len() as u32,
        };
        if let Some(l) = self.store.log.as_mut() {
            // The summary first: a cut before the cone record leaves the old cone
            // installed, and its summary written again at the next replacement.
            if l.append(odometer::kind::RETIRED, &retired.to_bytes())
                .is_err()
            {
                self.store.storage_errors = self.store.storage_errors.saturating_add(1);
                return Err(MaintError::Storage);
            }
            let cone = odometer::cone_to_bytes(next.cone());
            let state = StateRecord::of(&next, false).to_bytes();
            if l.append(odometer::kind::CONE, &cone).is_err() {
                self.store.storage_errors = self.store.storage_errors.saturating_add(1);
                return Err(MaintError::Storage);
            }
            // The cone record is the commitment; a lost snapshot is rebuilt from it
            // (restore() starts a cone whose id has no snapshot at zero).
            if l.append(odometer::kind::STATE, &state).is_err() {
                self.store.storage_errors = self.store.storage_errors.saturating_add(1);
                self.store.persist_pending = true;
            }
        }
        self.odo = next;
        self.sig.monitor.on_cone(self.odo.cone().id);
        self.readings.clear();
        self.refit();
        info!(
            "cone {=u16} installed: {=str} serial {=str}",
            self.odo.cone().id,
            material.name(),
            serial
        );
        Ok(())
    }

    /// The cone's baseline bore, or the nominal 26.000 mm when none was measured, µm.
    pub fn baseline_or_nominal(&self) -> u32 {
        self.odo
            .cone()
            .baseline()
            .unwrap_or(odometer::NOMINAL_BORE_UM)
    }

    /// The current cone's readings from flash, oldest first (the log keeps the last 40
    /// of all cones through its sector moves); then the fit.
    fn load_readings(&mut self) {
        let id = self.odo.cone().id;
        let readings = &mut self.readings;
        readings.clear();
        if let Some(l) = self.store.log.as_mut() {
            let _ =
                l.for_each_newest_first(odometer::kind::MEASURE, odometer::READINGS_KEPT, |r| {
                    if let Some(m) = Measurement::from_bytes(r.data()) {
                        if m.cone_id == id && !m.baseline {
                            let _ = readings.push(m);
                        }
                    }
                });
        }
        readings.reverse();
        self.refit();
    }

    /// The newest completed cycles from flash (once, at start).
    fn load_history(&mut self) {
        let recent = &mut self.store.recent_cycles;
        recent.clear();
        if let Some(l) = self.store.log.as_mut() {
            let _ = l.for_each_newest_first_while(odometer::kind::STATE, |r| {
                if let Some(st) = StateRecord::from_bytes(r.data()).filter(|s| s.cycle_end) {
                    let _ = recent.push_front(HistoryEntry::of(&st));
                }
                !recent.is_full()
            });
        }
    }

    fn refit(&mut self) {
        let base = self.baseline_or_nominal();
        let rs: heapless::Vec<Reading, { odometer::READINGS_KEPT }> =
            self.readings.iter().map(|m| m.reading(base)).collect();
        self.fit = Fit::new(&rs);
    }

    /// The current cone's micrometer readings, oldest first (its baseline excluded).
    pub fn measurements(&self) -> &[Measurement] {
        &self.readings
    }

    /// The wear estimate now: the model, taught by the cone's readings.
    ///
    /// Kept from the last control step while nothing it depends on changed (a read
    /// costs nothing then); computed afresh otherwise.
    pub fn wear_estimate(&self) -> Estimate {
        if self.level_key == Some(self.wear_key()) {
            return self.estimate;
        }
        self.compute_estimate()
    }

    fn compute_estimate(&self) -> Estimate {
        let cone = self.odo.cone();
        self.fit.at(
            self.odo.equivalent_cycles_q32(),
            self.cfg.wear.limit_nm,
            cone.material,
        )
    }

    /// The wear level the machine acts on: the model's, or — once the cone has been
    /// measured — the most worn of the model, the estimate's upper band and the last
    /// reading itself, so that a cone the micrometer shows worn is not docked again on
    /// the model's word (nor on the estimate's, which weighs one reading against the
    /// rest: a reading past the limit stands until the cone is measured again).
    pub fn wear_level(&self) -> WearLevel {
        if self.level_key == Some(self.wear_key()) {
            return self.level;
        }
        self.compute_level(&self.compute_estimate())
    }

    fn compute_level(&self, est: &Estimate) -> WearLevel {
        let model = self.odo.level();
        let Some(last) = self.readings.last() else {
            return model;
        };
        let measured = u32::try_from(last.wear_nm(self.baseline_or_nominal())).unwrap_or(0);
        let high = est.high_nm.max(measured);
        let w = &self.cfg.wear;
        let warn_nm = (w.limit_nm as u64 * w.warn_pct as u64 / 100) as u32;
        let est = if high >= w.limit_nm {
            WearLevel::Limit
        } else if high >= warn_nm {
            WearLevel::Warning
        } else {
            WearLevel::Ok
        };
        model.max(est)
    }

    /// Record a micrometer reading of the cone's bore (`bore_um`), or its `baseline`
    /// (its bore when new: only before its first docking, and once). Refused while
    /// anything moves. Returns the stored measurement.
    pub fn add_measurement(
        &mut self,
        bore_um: u32,
        baseline: bool,
    ) -> Result<Measurement, MaintError> {
        self.flash_turn()?;
        let cone = *self.odo.cone();
        if baseline && cone.baseline().is_some() {
            return Err(MaintError::BaselineExists);
        }
        if baseline && cone.cycles > 0 {
            return Err(MaintError::BaselineAfterUse);
        }
        let m = Measurement {
            bore_um,
            lifetime_cycle: self.odo.lifetime().cycles,
            cone_id: cone.id,
            cone_cycle: cone.cycles,
            model_nm: self.odo.wear_nm(),
            baseline,
        };
        let Some(l) = self.store.log.as_mut() else {
            return Err(MaintError::Storage);
        };
        if baseline {
            let mut c = cone;
            c.baseline_um = bore_um;
            if l.append(odometer::kind::CONE, &odometer::cone_to_bytes(&c))
                .is_err()
            {
                self.store.storage_errors = self.store.storage_errors.saturating_add(1);
                return Err(MaintError::Storage);
            }
            self.odo.set_baseline(bore_um);
        }
        if l.append(odometer::kind::MEASURE, &m.to_bytes()).is_err() {
            self.store.storage_errors = self.store.storage_errors.saturating_add(1);
            if !baseline {
                return Err(MaintError::Storage);
            }
        }
        if !baseline {
            if self.readings.is_full() {
                // The oldest out: swapped to the end and dropped (`remove(0)`'s
                // overlapping copy would link the 1.5 KB memmove for this alone).
                for i in 1..self.readings.len() {
                    self.readings.swap(i - 1, i);
                }
                self.readings.pop();
            }
            let _ = self.readings.push(m);
        }
        self.refit();
        Ok(m)
    }

    /// Append a record of `kind` to the odometer log (maintenance records: PIN, audit,
    /// measurements). Refused while anything moves (an erase may stall the CPU).
    pub fn store_record(&mut self, kind: u8, data: &[u8]) -> Result<(), MaintError> {
        self.flash_turn()?;
        match self.store.log.as_mut().map(|l| l.append(kind, data)) {
            Some(Ok(_)) => {
                self.cache_record(kind, data);
                Ok(())
            }
            _ => {
                self.store.storage_errors = self.store.storage_errors.saturating_add(1);
                Err(MaintError::Storage)
            }
        }
    }

    /// The newest record of `kind`, if any (payload bytes copied into `buf`; returns
    /// the length).
    ///
    /// The kinds in [`CACHED_KINDS`] come from RAM (no flash read); the others walk the
    /// log (milliseconds: boot, or a machine at rest).
    pub fn load_record(&mut self, kind: u8, buf: &mut [u8]) -> Option<usize> {
        let cached = CACHED_KINDS
            .iter()
            .position(|&k| k == kind)
            .and_then(|i| self.store.cached.get(i))
            .and_then(Option::as_ref);
        if let Some(known) = cached {
            let d = known.as_ref()?;
            let dst = buf.get_mut(..d.len())?;
            dst.copy_from_slice(d);
            return Some(d.len());
        }
        let r = self.store.log.as_mut()?.latest(kind).ok().flatten()?;
        let d = r.data();
        let dst = buf.get_mut(..d.len())?;
        dst.copy_from_slice(d);
        Some(d.len())
    }

    /// Load the newest record of each of [`CACHED_KINDS`] (at boot).
    fn load_cached_records(&mut self) {
        for (kind, slot) in CACHED_KINDS.iter().zip(self.store.cached.iter_mut()) {
            // An unreadable log, or a record too long to keep: not known (`None`).
            *slot = match self.store.log.as_mut().map(|l| l.latest(*kind)) {
                Some(Ok(None)) => Some(None),
                Some(Ok(Some(r))) => heapless::Vec::from_slice(r.data()).ok().map(Some),
                _ => None,
            };
        }
    }

    /// Keep `data` as the newest record of `kind` if that kind is cached.
    fn cache_record(&mut self, kind: u8, data: &[u8]) {
        let Some(i) = CACHED_KINDS.iter().position(|&k| k == kind) else {
            return;
        };
        if let Some(slot) = self.store.cached.get_mut(i) {
            // Longer than any cached kind's record: not known (read from the log).
            *slot = heapless::Vec::from_slice(data).ok().map(Some);
        }
    }

    /// Up to `max` records of `kind`, newest first.
    pub fn records(
        &mut self,
        kind: u8,
        max: usize,
        out: impl FnMut(&crate::storage::Record),
    ) -> usize {
        match self.store.log.as_mut() {
            Some(l) => l.for_each_newest_first(kind, max, out).unwrap_or(0),
            None => 0,
        }
    }

    /// Mean of the raw codes of the last samples taken with nothing moving.
    fn quiet_mean_code(&self) -> Result<i32, CalibrateError> {
        if !self.is_quiet() {
            return Err(CalibrateError::Moving);
        }
        self.rest_mean_code()
            .ok_or(CalibrateError::NotEnoughSamples)
    }

    fn store_calibration(&mut self, cal: Calibration) -> Result<Calibration, CalibrateError> {
        self.store_record(odometer::kind::CALIBRATION, &calibration_to_bytes(&cal))
            .map_err(|e| match e {
                MaintError::Moving | MaintError::NotAtRest => CalibrateError::Moving,
                _ => CalibrateError::Storage,
            })?;
        self.cell.base_cal = cal;
        self.cell.cal = cal;
        self.cell.calibrated = true;
        info!(
            "load cell calibrated: offset {=i32} counts, {=i64} mN/count (Q32.32)",
            cal.offset_counts, cal.mn_per_count_q32
        );
        Ok(cal)
    }

    /// Technician tare: the load cell is unloaded; its mean reading becomes the zero.
    pub fn calibrate_tare(&mut self) -> Result<Calibration, CalibrateError> {
        let code = self.quiet_mean_code()?;
        if !Calibration::tare_plausible(code) {
            return Err(CalibrateError::Implausible);
        }
        self.store_calibration(self.cell.base_cal.with_tare(code))
    }

    /// Technician span: a known `force_mn` hangs on the (tared) load cell.
    pub fn calibrate_span(&mut self, force_mn: i32) -> Result<Calibration, CalibrateError> {
        let code = self.quiet_mean_code()?;
        let cal = Calibration::from_two_points(self.cell.base_cal.offset_counts, 0, code, force_mn)
            .map_err(|_| CalibrateError::Implausible)?;
        self.store_calibration(cal)
    }

    /// Up to `max` completed cycles from the flash log, newest first, into `out`.
    pub fn history(&mut self, max: usize, mut out: impl FnMut(HistoryEntry)) -> usize {
        // From RAM: the newest [`HISTORY_KEPT`] entries, loaded at boot and kept as
        // each cycle's record is written. A walk of the log here read every slot of
        // both sectors (milliseconds) with the controller held.
        let mut n = 0;
        for e in self.store.recent_cycles.iter().rev().take(max) {
            // Field by field: a whole-entry copy here is a `memmove` (see
            // `console::reports::fault_records`).
            out(HistoryEntry {
                lifetime_cycle: e.lifetime_cycle,
                cone_cycle: e.cone_cycle,
                cone_id: e.cone_id,
                w_q1: e.w_q1,
                wear_nm: e.wear_nm,
            });
            n += 1;
        }
        n
    }

    /// Sequencer state.
    pub fn state(&self) -> State {
        self.seq.state()
    }

    /// The wear odometer.
    pub fn odometer(&self) -> &Odometer {
        &self.odo
    }

    /// What the odometer log held at boot.
    pub fn open_report(&self) -> OpenReport {
        self.store.open_report
    }

    /// Odometer writes that failed since boot.
    pub fn storage_errors(&self) -> u32 {
        self.store.storage_errors
    }

    /// A counter snapshot is waiting to be written.
    pub fn persist_pending(&self) -> bool {
        self.store.persist_pending
    }

    /// The odometer log (history reads; `None` if the flash was unreadable at boot).
    pub fn log_mut(&mut self) -> Option<&mut RecordLog<B::Flash>> {
        self.store.log.as_mut()
    }

    /// The odometer flash (for tests and the simulator).
    pub fn flash(&self) -> Option<&B::Flash> {
        self.store.log.as_ref().map(|l| l.flash())
    }

    /// Fault records, oldest first (the last 16).
    pub fn faults(&self) -> impl Iterator<Item = &FaultRecord> {
        self.diag.faults.iter()
    }

    /// Faults latched since boot.
    pub fn fault_count(&self) -> u32 {
        self.diag.fault_count
    }

    /// Overload trips since boot.
    pub fn overload_trips(&self) -> u32 {
        self.guard.overload_trips
    }

    /// When the propulsion was last switched off by the controller, µs.
    pub fn disabled_at_us(&self) -> Option<u64> {
        self.guard.disabled_at_us
    }

    /// Calibration in force (offset re-tared before each cycle).
    pub fn calibration(&self) -> Calibration {
        self.cell.cal
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

#[cfg(test)]
mod tests {
    use super::{rest_zero_code, sort_small};

    #[test]
    fn sort_small_sorts_like_sort_unstable() {
        let mut x: u32 = 12_345;
        for len in 0..=16 {
            for _ in 0..50 {
                let mut v: heapless::Vec<i32, 16> = heapless::Vec::new();
                for _ in 0..len {
                    x = x.wrapping_mul(1_103_515_245).wrapping_add(12_345);
                    let _ = v.push((x >> 8) as i32 % 7 - 3 + (x as i32 >> 20));
                }
                let mut want = v.clone();
                want.sort_unstable();
                sort_small(&mut v);
                assert_eq!(v, want);
            }
        }
    }

    #[test]
    fn tare_zero_ignores_a_spike_and_needs_eight_samples() {
        // 16 samples of noise ±20 counts around 1000, one at +350 N (≈ 3 M counts).
        let mut codes: [i32; 16] = core::array::from_fn(|i| 1000 + (i as i32 % 5) * 10 - 20);
        let clean = rest_zero_code(codes.iter().copied()).unwrap();
        codes[7] = 3_000_000;
        let spiked = rest_zero_code(codes.iter().copied()).unwrap();
        assert!((spiked - clean).abs() <= 20, "{clean} -> {spiked}");
        assert!((clean - 1000).abs() <= 20);
        assert_eq!(rest_zero_code(codes.iter().copied().take(7)), None);
        assert!(rest_zero_code(codes.iter().copied().take(8)).is_some());
    }
}
