//! A complete simulated docking machine: the devices of this crate wired to the real
//! `docking_logic::Controller`, in virtual time.

use std::cell::{Cell, RefCell};
use std::rc::Rc;

use docking_logic::config::MachineConfig;
use docking_logic::controller::{Bsp, Controller, ControllerConfig, Parts};
use docking_logic::hal::{LoadCellAdc, StepPulses, StopLatch, Watchdog};
use docking_logic::hx711::{Calibration, Gain, Hx711};
use docking_logic::profile::STROKE_UM;
use docking_logic::safety::{GatedEn, GatedHigh, GatedPulses, SafetyKernel};

use crate::axis::{AxisPin, AxisPulses, EndSwitch, HomeSwitch, SimAxis};
use crate::clock::SimClock;
use crate::console::SimConsole;
use crate::flash::{SharedFlash, SimFlash};
use crate::hx711::{ForceSource, Hx711Config, Hx711Dout, Hx711Sck, SimHx711};
use crate::line::SimLine;
use crate::lock::{LockPin, LockedSwitch, ReleasedSwitch, SimLock};
use docking_logic::console::service::{Console, ConsolePoll};

/// The shortest time the board's watchdog may bite after a feed, ns: the firmware sets a
/// nominal 500 ms at the LSI's typical 32 kHz, and the LSI may run at up to 47 kHz
/// (DS8626), so 500 × 32/47 = 340 ms.
pub const WATCHDOG_WORST_NS: u64 = 500_000_000 * 32_000 / 47_000;

/// The simulated watchdog: records feeds; "bites" if not fed within its shortest real
/// timeout ([`WATCHDOG_WORST_NS`]).
#[derive(Clone, Debug)]
pub struct SimWatchdog {
    clock: SimClock,
    timeout_ns: u64,
    /// Shared between clones (one watchdog).
    state: Rc<WatchdogState>,
}

/// What a [`SimWatchdog`]'s clones share.
#[derive(Debug, Default)]
struct WatchdogState {
    last_feed_ns: Cell<u64>,
    feeds: Cell<u64>,
    bitten: Cell<bool>,
}

impl SimWatchdog {
    /// A watchdog with the board's period, on the fastest LSI.
    pub fn new(clock: SimClock) -> Self {
        let now = clock.now_ns();
        Self {
            clock,
            timeout_ns: WATCHDOG_WORST_NS,
            state: Rc::new(WatchdogState {
                last_feed_ns: Cell::new(now),
                ..WatchdogState::default()
            }),
        }
    }

    /// Whether it would have reset the MCU by now (not fed within the timeout).
    pub fn check(&self) -> bool {
        let s = &self.state;
        if self.clock.now_ns().saturating_sub(s.last_feed_ns.get()) > self.timeout_ns {
            s.bitten.set(true);
        }
        s.bitten.get()
    }

    /// Feeds so far.
    pub fn feeds(&self) -> u64 {
        self.state.feeds.get()
    }
}

impl Watchdog for SimWatchdog {
    fn feed(&mut self) {
        // `check` at the feed's instant, then the feed.
        let now = self.clock.now_ns();
        let s = &self.state;
        if now.saturating_sub(s.last_feed_ns.get()) > self.timeout_ns {
            s.bitten.set(true);
        }
        s.last_feed_ns.set(now);
        s.feeds.set(s.feeds.get() + 1);
    }
}

/// The real HX711 driver on the simulated part's pins.
pub type PinDriver = Hx711<Hx711Dout<ProfileForce>, Hx711Sck<ProfileForce>, SimClock>;

/// How the controller reads the simulated HX711.
pub enum SimAdc {
    /// The firmware's HX711 driver bit-banging the simulated pins (scenes, tests).
    Pins(PinDriver),
    /// Word-level: the whole readout in one call, same data-ready semantics and virtual
    /// readout time, ~20x cheaper (long runs: `bench`, `life`; the bit protocol is proven
    /// by the driver tests and by every scene).
    Word(SimHx711<ProfileForce>),
}

/// Which [`SimAdc`] a rig uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum AdcMode {
    /// The firmware's driver at pin level.
    Pins,
    /// Word-level reads.
    Word,
}

impl LoadCellAdc for SimAdc {
    fn read_code(&mut self) -> nb::Result<i32, ()> {
        match self {
            SimAdc::Pins(d) => d.read_code(),
            SimAdc::Word(hx) => hx.read_word().ok_or(nb::Error::WouldBlock),
        }
    }
}

/// The simulated board.
pub struct SimBsp;

/// The rig's stop latch: EN high and the pulse rate to zero on the simulated axis, the
/// latch shared by the kernel's handle, the controller's and the EN gate's.
#[derive(Clone)]
pub struct SimStop {
    en_n: Rc<RefCell<AxisPin>>,
    pulses: Rc<RefCell<AxisPulses>>,
    /// (stops so far, latched)
    state: Rc<Cell<(u32, bool)>>,
    /// Something to do at a look at the latch (see [`LatchHook`]).
    hook: LatchHook,
}

/// An action run **inside** a control step: at the `n`-th look at the stop latch from
/// now (the step's gate check, each gated pin's checks before and after its write, the
/// step rate's) or write of a motor pin (EN, DIR, the lock's bridge: [`Watched`]), the
/// instants where a stop from an interrupt would land between a check and a write on
/// the board. The rig has no interrupts; this is how a host test puts an
/// event there (`host-tests/tests/interleavings.rs`: an E-STOP pulse inside a step).
#[derive(Clone, Default)]
pub struct LatchHook(Rc<LatchHookState>);

/// Type of a [`LatchHook`]'s action.
type LatchAction = Box<dyn FnMut()>;

#[derive(Default)]
struct LatchHookState {
    /// Looks at the latch still to come before the action (0: none armed).
    countdown: Cell<u32>,
    action: RefCell<Option<LatchAction>>,
}

impl LatchHook {
    /// Run `action` at the `n`-th look at the latch from now (`n` ≥ 1).
    pub fn arm(&self, n: u32, action: impl FnMut() + 'static) {
        self.0.countdown.set(n.max(1));
        *self.0.action.borrow_mut() = Some(Box::new(action));
    }

    /// Forget an action not run yet; whether one was armed.
    pub fn disarm(&self) -> bool {
        self.0.countdown.set(0);
        self.0.action.borrow_mut().take().is_some()
    }

    /// A look at the latch.
    fn look(&self) {
        let n = self.0.countdown.get();
        if n == 0 {
            return;
        }
        self.0.countdown.set(n - 1);
        if n == 1 {
            let action = self.0.action.borrow_mut().take();
            if let Some(mut f) = action {
                f();
            }
        }
    }
}

/// A motor output whose every write is first a look for the stop latch's [`LatchHook`]:
/// an interrupt just before the write.
pub struct Watched<P>(P, LatchHook);

impl<P> Watched<P> {
    /// `pin`, watched by `stop`'s hook.
    pub fn new(pin: P, stop: &SimStop) -> Self {
        Self(pin, stop.hook.clone())
    }
}

impl<P: embedded_hal::digital::ErrorType> embedded_hal::digital::ErrorType for Watched<P> {
    type Error = P::Error;
}

impl<P: embedded_hal::digital::OutputPin> embedded_hal::digital::OutputPin for Watched<P> {
    fn set_low(&mut self) -> Result<(), Self::Error> {
        self.1.look();
        self.0.set_low()
    }
    fn set_high(&mut self) -> Result<(), Self::Error> {
        self.1.look();
        self.0.set_high()
    }
}

impl SimStop {
    /// A latch on `axis`'s EN line and pulse generator.
    pub fn new(axis: &SimAxis) -> Self {
        Self {
            en_n: Rc::new(RefCell::new(axis.enable_n())),
            pulses: Rc::new(RefCell::new(axis.pulses())),
            state: Rc::new(Cell::new((0, false))),
            hook: LatchHook::default(),
        }
    }

    /// The hook run at a look at the latch.
    pub fn hook(&self) -> &LatchHook {
        &self.hook
    }
}

impl StopLatch for SimStop {
    fn stop_now(&mut self) -> u32 {
        let _ = embedded_hal::digital::OutputPin::set_high(&mut *self.en_n.borrow_mut());
        StepPulses::set_rate_hz(&mut *self.pulses.borrow_mut(), 0);
        let n = self.state.get().0 + 1;
        self.state.set((n, true));
        n
    }
    fn stops(&self) -> u32 {
        self.state.get().0
    }
    fn latched(&self) -> bool {
        self.hook.look();
        self.state.get().1
    }
    fn rearm(&mut self, seen: u32) -> bool {
        let (n, latched) = self.state.get();
        if latched && seen >= n {
            self.state.set((n, false));
        }
        !self.state.get().1
    }
}

impl Bsp for SimBsp {
    type EnN = GatedEn<Watched<AxisPin>, SimStop>;
    type Dir = Watched<AxisPin>;
    type Pulses = GatedPulses<AxisPulses, SimStop>;
    type LockIn1 = GatedHigh<Watched<LockPin>, SimStop>;
    type LockIn2 = GatedHigh<Watched<LockPin>, SimStop>;
    type Home = HomeSwitch;
    type End = EndSwitch;
    type Locked = LockedSwitch;
    type Released = ReleasedSwitch;
    type Stop = SimStop;
    type Wdg = SimWatchdog;
    type Flash = BoardFlash;
    type Options = SimOptions;
    type SigFlash = SigBoardFlash;
    type SigMem = Box<docking_logic::signature::monitor::SignatureMem>;
    type Sig = Box<docking_logic::signature::Signature<SigBoardFlash, Self::SigMem>>;
}

/// The signature store's sectors (2–4) as the board's driver drives them: 16, 16 and
/// 64 KiB, every operation charged its datasheet time in virtual time (×32: a word
/// 100 µs, a 16 KiB sector 500 ms, the 64 KiB sector 1.1 s, at most), the watchdog
/// fed through an erase as the board's wait from SRAM feeds it. The array is a
/// [`SimFlash`] of six 16 KiB sectors (the 64 KiB sector is its last four, erased
/// together).
#[derive(Clone, Debug)]
pub struct SigBoardFlash {
    /// The flash array.
    pub flash: SharedFlash,
    clock: SimClock,
    wdg: SimWatchdog,
    /// Operations take their time ([`RigOptions::timed_signature_flash`]).
    timed: bool,
}

/// The signature store's region: sectors 2–4, as six 16 KiB simulated sectors.
pub fn sig_flash_array() -> SimFlash {
    SimFlash::new(6, 16 * 1024)
}

impl embedded_storage::nor_flash::ErrorType for SigBoardFlash {
    type Error = crate::flash::SimFlashError;
}

impl embedded_storage::nor_flash::ReadNorFlash for SigBoardFlash {
    const READ_SIZE: usize = 1;
    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.flash.read(offset, bytes)
    }
    fn capacity(&self) -> usize {
        self.flash.capacity()
    }
}

impl embedded_storage::nor_flash::NorFlash for SigBoardFlash {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = 16 * 1024;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        // Sector 4 (64 KiB, from 32 KiB on): 1.1 s; sectors 2 and 3: 0.5 s each.
        let ns: u64 = if !self.timed {
            0
        } else if from >= 32 * 1024 {
            1_100_000_000
        } else {
            500_000_000 * u64::from(to.saturating_sub(from)).div_ceil(16 * 1024)
        };
        let mut waited = 0;
        while waited < ns {
            let d = (ns - waited).min(50_000_000);
            self.clock.advance_ns(d);
            waited += d;
            self.wdg.feed();
        }
        self.flash.erase(from, to)
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        if self.timed {
            self.clock
                .advance_ns(bytes.len().div_ceil(4) as u64 * FlashTimes::MAX.word_ns);
        }
        self.flash.write(offset, bytes)
    }
}

/// The simulated option bytes: the BOR level (factory default off), programmed only
/// when asked.
#[derive(Clone, Debug, Default)]
pub struct SimOptions {
    /// The brown-out reset level (shared between clones).
    pub bor: Rc<Cell<u8>>,
    /// The programming fails (option bytes write-protected): FLASH_SR's WRPERR.
    pub locked: Rc<Cell<bool>>,
}

impl docking_logic::hal::OptionBytes for SimOptions {
    fn bor_level(&self) -> u8 {
        self.bor.get()
    }
    fn program_bor_level_3(&mut self) -> Result<(), u32> {
        if self.locked.get() {
            return Err(0x10); // WRPERR
        }
        self.bor.set(3);
        Ok(())
    }
}

/// Flash operation times (DS8626 Table 41, PSIZE ×32 as the board's driver uses).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct FlashTimes {
    /// Word program, ns.
    pub word_ns: u64,
    /// 128 KiB sector erase, ns.
    pub erase_ns: u64,
}

impl FlashTimes {
    /// The datasheet's maximum: 100 µs per word, 2 s per sector.
    pub const MAX: Self = Self {
        word_ns: 100_000,
        erase_ns: 2_000_000_000,
    };
}

/// How long the board's erase wait feeds the watchdog at most, ns (`board/flash.rs`:
/// `ERASE_TIMEOUT_CYCLES`, 3 s).
pub const ERASE_FEED_LIMIT_NS: u64 = 3_000_000_000;

/// The odometer flash as the board's driver (`src/board/flash.rs`) drives it: every
/// operation costs its datasheet time in virtual time, during which the controller does
/// nothing else (the CPU stalls on flash fetches); an erase waits from SRAM feeding the
/// watchdog for at most [`ERASE_FEED_LIMIT_NS`]. So the rig sees what the board sees: a
/// long erase delays the next control step, and one that outlasts the feeding is a
/// watchdog reset.
#[derive(Clone, Debug)]
pub struct BoardFlash {
    /// The flash array.
    pub flash: SharedFlash,
    clock: SimClock,
    wdg: SimWatchdog,
    /// Operation times.
    pub times: FlashTimes,
}

impl embedded_storage::nor_flash::ErrorType for BoardFlash {
    type Error = crate::flash::SimFlashError;
}

impl embedded_storage::nor_flash::ReadNorFlash for BoardFlash {
    const READ_SIZE: usize = 1;
    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.flash.read(offset, bytes)
    }
    fn capacity(&self) -> usize {
        self.flash.capacity()
    }
}

impl embedded_storage::nor_flash::NorFlash for BoardFlash {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = crate::flash::SECTOR_SIZE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        let sectors = (to.saturating_sub(from) as u64).div_ceil(Self::ERASE_SIZE as u64);
        for _ in 0..sectors {
            let mut waited = 0;
            while waited < self.times.erase_ns {
                let d = (self.times.erase_ns - waited).min(50_000_000);
                self.clock.advance_ns(d);
                waited += d;
                if waited <= ERASE_FEED_LIMIT_NS {
                    self.wdg.feed();
                }
            }
        }
        self.flash.erase(from, to)
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.clock
            .advance_ns(bytes.len().div_ceil(4) as u64 * self.times.word_ns);
        self.flash.write(offset, bytes)
    }
}

/// Extra force a scene puts on the load cell (jam, spikes), N.
#[derive(Clone, Debug, Default)]
pub struct ForceScript {
    /// A jam: from this insertion depth on, the force grows by `jam_n_per_mm` per mm.
    pub jam_from_um: Option<f64>,
    /// Jam stiffness, N/mm.
    pub jam_n_per_mm: f64,
    /// Add `spike_n` to these conversion numbers.
    pub spikes_at: Vec<u64>,
    /// Spike height, N.
    pub spike_n: f64,
    /// Offset added to every conversion (a shifted bridge: implausible tare), N.
    pub offset_n: f64,
    /// The bridge wired in reverse (its signal leads swapped): compression reads as
    /// tension.
    pub reversed: bool,
    /// The vehicle pulls (or drifts) while mated: the force grows by this much per
    /// second from the first conversion after it is set, N/s.
    pub pull_n_per_s: f64,
    /// When the pull began (set by the force source), ns.
    pub pull_from_ns: Option<u64>,
    /// The rod meets the cone this much later than the engagement point (a lateral
    /// misalignment): the profile is shifted deeper, and before it the load is 0, µm.
    pub entry_delay_um: f64,
    /// A local bump of force (debris in the bore, a catch), on one stroke.
    pub bump: Option<Bump>,
    /// Another machine's contact force replaces the profile, N per step of insertion
    /// depth (a dry guide: the plant with another µ2).
    pub profile_n: Option<Rc<Vec<f64>>>,
}

/// A force bump between two depths, on the insertion (`forward`) or the extraction.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Bump {
    /// From this insertion depth, µm.
    pub from_um: f64,
    /// To this insertion depth, µm.
    pub to_um: f64,
    /// Added force, N.
    pub add_n: f64,
    /// On the insertion (the axis going forward); else on the extraction.
    pub forward: bool,
}

impl ForceScript {
    /// Whether it adds nothing: no jam, spike, offset, pull or reversal.
    fn adds_nothing(&self) -> bool {
        self.jam_from_um.is_none()
            && self.spikes_at.is_empty()
            && self.offset_n == 0.0
            && !self.reversed
            && self.pull_n_per_s == 0.0
            && self.entry_delay_um == 0.0
            && self.bump.is_none()
            && self.profile_n.is_none()
    }
}

/// The scene's [`ForceScript`], shared by the scene and the force source, with a flag
/// set whenever it is changed: whether it adds nothing. The force source reads the
/// flag at every conversion (a long run's scripts are empty) instead of the script.
///
/// Used like a `RefCell`: `script.borrow_mut().offset_n = 50.0`.
#[derive(Debug, Default)]
pub struct SharedScript {
    script: RefCell<ForceScript>,
    /// `script.adds_nothing()`, as of the last change.
    adds_nothing: Cell<bool>,
}

impl SharedScript {
    /// An empty script.
    pub fn new() -> Self {
        Self {
            script: RefCell::default(),
            adds_nothing: Cell::new(true),
        }
    }

    /// The script, to read.
    pub fn borrow(&self) -> std::cell::Ref<'_, ForceScript> {
        self.script.borrow()
    }

    /// The script, to change (the flag follows when the borrow ends).
    pub fn borrow_mut(&self) -> ScriptMut<'_> {
        ScriptMut {
            script: self.script.borrow_mut(),
            adds_nothing: &self.adds_nothing,
        }
    }

    /// Whether the script adds nothing to the force.
    fn adds_nothing(&self) -> bool {
        self.adds_nothing.get()
    }
}

/// A change to a [`SharedScript`] under way.
pub struct ScriptMut<'a> {
    script: std::cell::RefMut<'a, ForceScript>,
    adds_nothing: &'a Cell<bool>,
}

impl std::ops::Deref for ScriptMut<'_> {
    type Target = ForceScript;
    fn deref(&self) -> &ForceScript {
        &self.script
    }
}

impl std::ops::DerefMut for ScriptMut<'_> {
    fn deref_mut(&mut self) -> &mut ForceScript {
        &mut self.script
    }
}

impl Drop for ScriptMut<'_> {
    fn drop(&mut self) {
        self.adds_nothing.set(self.script.adds_nothing());
    }
}

/// What the rig's load cell measures: N3 of Eq. 7 at the carriage's position (the
/// carriage moves in whole steps, so it is tabulated once per step position over the
/// stroke: the same values without per-sample divisions), plus the scene's additions.
///
/// With nothing added, the bridge's output in counts (`offset + counts/N · F`, see
/// [`ForceSource::counts`]) is tabulated too, for the front end the machine was built
/// with: the same arithmetic on the same values, done once per step position instead
/// of at every conversion.
pub struct ProfileForce {
    axis: SimAxis,
    script: Rc<SharedScript>,
    conversions: Rc<Cell<u64>>,
    /// N3 at each step of insertion depth, N.
    table: Vec<f64>,
    /// N3 past the end of the stroke, N.
    n3_end: f64,
    engage_steps: i64,
    um_per_step: f64,
    /// The bridge's output, counts, at each step of insertion depth (`table`'s), through
    /// the part's front end (empty until [`ForceSource::front_end`]).
    counts: Vec<f64>,
    /// The same before contact and past the end of the stroke.
    counts_before: f64,
    counts_end: f64,
}

impl ProfileForce {
    fn new(
        machine: MachineConfig,
        model: &crate::machine::ForceModel,
        axis: SimAxis,
        script: Rc<SharedScript>,
        conversions: Rc<Cell<u64>>,
    ) -> Self {
        let um_per_step = 1000.0 / machine.steps_per_mm as f64;
        let table: Vec<f64> = (0..=machine.um_to_steps(STROKE_UM))
            .map(|k| model.n3_at_depth_um(k as f64 * um_per_step))
            .collect();
        Self {
            axis,
            script,
            conversions,
            n3_end: table.last().copied().unwrap_or(0.0),
            table,
            engage_steps: machine.um_to_steps(machine.engage_um) as i64,
            um_per_step,
            counts: Vec::new(),
            counts_before: 0.0,
            counts_end: 0.0,
        }
    }

    /// [`ForceSource::counts`] with the script adding something (or untabulated).
    #[inline(never)]
    fn counts_scripted(&mut self, t_ns: u64, front: &Hx711Config) -> f64 {
        front.offset_counts + front.counts_per_n * self.force_n(t_ns)
    }
}

impl ForceSource for ProfileForce {
    fn force_n(&mut self, t_ns: u64) -> f64 {
        let n = self.conversions.get();
        self.conversions.set(n + 1);
        let depth_steps = self.axis.pos_steps() - self.engage_steps;
        let mut s = self.script.borrow_mut();
        let pull = if s.pull_n_per_s != 0.0 {
            let t0 = *s.pull_from_ns.get_or_insert(t_ns);
            t_ns.saturating_sub(t0) as f64 * 1e-9 * s.pull_n_per_s
        } else {
            0.0
        };
        let table = s.profile_n.as_deref().unwrap_or(&self.table);
        let delay_steps = (s.entry_delay_um / self.um_per_step).round() as i64;
        let mut f = match usize::try_from(depth_steps - delay_steps) {
            Err(_) => 0.0, // before contact
            Ok(k) => table
                .get(k)
                .copied()
                .unwrap_or_else(|| table.last().copied().unwrap_or(self.n3_end)),
        } + s.offset_n
            + pull;
        if let Some(b) = s.bump {
            let depth = depth_steps as f64 * self.um_per_step;
            if (b.from_um..b.to_um).contains(&depth) && self.axis.forward() == b.forward {
                f += b.add_n;
            }
        }
        if let Some(j) = s.jam_from_um {
            let depth = depth_steps as f64 * self.um_per_step;
            if depth > j {
                f += (depth - j) / 1000.0 * s.jam_n_per_mm;
            }
        }
        if !s.spikes_at.is_empty() && s.spikes_at.binary_search(&n).is_ok() {
            f += s.spike_n;
        }
        if s.reversed {
            -f
        } else {
            f
        }
    }

    fn front_end(&mut self, front: &Hx711Config) {
        // As `force_n` sums them with nothing added (`+ 0.0 + 0.0`: the offset and the
        // pull), then as `counts` scales them.
        let counts_of = |n3: f64| front.offset_counts + front.counts_per_n * (n3 + 0.0 + 0.0);
        self.counts = self.table.iter().map(|&n3| counts_of(n3)).collect();
        self.counts_before = counts_of(0.0);
        self.counts_end = counts_of(self.n3_end);
    }

    /// Tabulated while the script adds nothing (`front` is the one `front_end` was
    /// told: the part's, which never changes).
    #[inline]
    fn counts(&mut self, t_ns: u64, front: &Hx711Config) -> f64 {
        if !self.script.adds_nothing() || self.counts.is_empty() {
            return self.counts_scripted(t_ns, front);
        }
        let n = self.conversions.get();
        self.conversions.set(n + 1);
        let depth_steps = self.axis.pos_steps() - self.engage_steps;
        match usize::try_from(depth_steps) {
            Err(_) => self.counts_before,
            Ok(k) => self.counts.get(k).copied().unwrap_or(self.counts_end),
        }
    }
}

/// The simulated machine: every device on one virtual clock, without a controller.
/// The host rig ([`Rig`]) wires it to the library's controller; the virtual board wires
/// it to the pins of the emulated MCU.
pub struct Machine {
    /// Virtual time shared by every device.
    pub clock: SimClock,
    /// Propulsion axis (parked at home, driver off).
    pub axis: SimAxis,
    /// Lock actuator (parked locked).
    pub lock: SimLock,
    /// Load cell, powered up at t = 0.
    pub hx: SimHx711<ProfileForce>,
    /// Scene force additions.
    pub script: Rc<SharedScript>,
    /// Conversions so far (the force source's call count).
    pub conversions: Rc<Cell<u64>>,
    /// The PLC's DOCK line (active low: asserted = low = "be docked"; released = high).
    pub dock_request: SimLine,
    /// The E-STOP line (normally closed to ground: low = closed; high = open, a stop).
    pub estop: SimLine,
    /// The load cell's front end.
    pub hx_config: Hx711Config,
}

impl Machine {
    /// The devices a scene disturbs.
    pub fn devices(&self) -> crate::scene::Devices<'_> {
        crate::scene::Devices {
            script: &self.script,
            hx: &self.hx,
            axis: &self.axis,
            lock: &self.lock,
            estop: &self.estop,
        }
    }

    /// A machine at t = 0, parked at home and locked, with the load cell of `opts`.
    pub fn new(opts: &RigOptions) -> Self {
        let machine = MachineConfig::DEFAULT;
        let clock = SimClock::new();
        let axis = SimAxis::new(machine, clock.clone(), 0);
        let lock = SimLock::new_locked(clock.clone());
        let script = Rc::new(SharedScript::new());
        let conversions = Rc::new(Cell::new(0u64));
        let mut hx_config = Hx711Config::default_for_rate(opts.rate_sps);
        if let Some(n) = opts.noise_counts {
            hx_config.noise_counts = n;
        }
        let source = ProfileForce::new(
            machine,
            &opts.force_model,
            axis.clone(),
            script.clone(),
            conversions.clone(),
        );
        let hx = SimHx711::with_source(hx_config, clock.clone(), source, opts.seed);
        Self {
            clock,
            axis,
            lock,
            hx,
            script,
            conversions,
            dock_request: SimLine::new(true),
            estop: SimLine::new(false),
            hx_config,
        }
    }
}

/// Rig options.
#[derive(Clone, Copy, Debug)]
pub struct RigOptions {
    /// Load-cell rate, SPS.
    pub rate_sps: u32,
    /// Noise seed.
    pub seed: u64,
    /// How the load cell is read.
    pub adc: AdcMode,
    /// Cone material of a new machine (no cone record in flash).
    pub material: docking_logic::material::Material,
    /// Load-cell RMS noise in counts (`None` = the part's default, ≈ 0.3 N).
    pub noise_counts: Option<f64>,
    /// A technician has calibrated the load cell: a new machine's flash gets the
    /// calibration record (without one the controller refuses to dock).
    pub commissioned: bool,
    /// The machine's contact forces: Eq. 7 (the paper's machine) or the plant of another.
    pub force_model: crate::machine::ForceModel,
    /// The controller configured for another machine (commissioning); `None`: the
    /// build's defaults (the paper's machine).
    pub tuning: Option<crate::machine::Tuning>,
    /// Device identification's names (a commissioning file's `cfg.identity`).
    pub identity: docking_logic::controller::Identity,
    /// The signature store's flash takes its datasheet times (the board's). `false`
    /// only for the tests that replay a recording made before the store existed: its
    /// writes at rest take flash time, which moves every later sample of a run.
    pub timed_signature_flash: bool,
}

impl RigOptions {
    /// 80 SPS, seed 1, word-level reads, ZQSn5-2.
    pub fn new(rate_sps: u32) -> Self {
        Self {
            rate_sps,
            seed: 1,
            adc: AdcMode::Word,
            material: docking_logic::material::Material::ZQSn5_2,
            noise_counts: None,
            commissioned: true,
            force_model: crate::machine::ForceModel::Eq7,
            tuning: None,
            identity: docking_logic::controller::Identity::DEFAULT,
            timed_signature_flash: true,
        }
    }
}

/// Commission `flash` as a technician does at installation: store the calibration of the
/// simulated cell's front end `hx` and its rate, unless they are stored already.
pub fn commission(flash: &SharedFlash, hx: &Hx711Config) {
    use docking_logic::controller::{calibration_to_bytes, Settings};
    use docking_logic::odometer::kind;
    if let Ok((mut log, _)) = docking_logic::odometer::open_log(flash.clone()) {
        if log.latest(kind::CALIBRATION).ok().flatten().is_none() {
            let _ = log.append(
                kind::CALIBRATION,
                &calibration_to_bytes(&sim_calibration(hx)),
            );
        }
        if log.latest(kind::SETTINGS).ok().flatten().is_none() {
            let st = Settings {
                rate_sps: hx.rate_sps,
            };
            if Settings::from_bytes(&st.to_bytes()).is_some() {
                let _ = log.append(kind::SETTINGS, &st.to_bytes());
            }
        }
    }
}

/// The whole machine.
pub struct Rig {
    /// Virtual time.
    pub clock: SimClock,
    /// Propulsion axis.
    pub axis: SimAxis,
    /// Lock actuator.
    pub lock: SimLock,
    /// Load cell.
    pub hx: SimHx711<ProfileForce>,
    /// Watchdog.
    pub wdg: SimWatchdog,
    /// Scene force additions.
    pub script: Rc<SharedScript>,
    /// The controller under test.
    pub ctrl: Controller<SimBsp>,
    /// The safety path (the board runs it in the HX711's data-ready interrupt).
    pub kernel: SafetyKernel<SimAdc>,
    /// The kernel's stop latch.
    pub stop: SimStop,
    /// Conversions so far (the force source's call count).
    pub conversions: Rc<Cell<u64>>,
    /// The odometer flash (shared: cut power on it, reboot on it).
    pub flash: SharedFlash,
    /// The signature store's flash (sectors 2–4; shared likewise).
    pub sig_flash: SharedFlash,
    /// Sample period, ns.
    period_ns: u64,
    /// The technician console and its serial link (polled after the controller when
    /// `console_enabled`).
    pub console: Console,
    /// The terminal end of the serial link.
    pub term: SimConsole,
    /// Poll the console in [`Rig::tick`].
    pub console_enabled: bool,
    /// The PLC's DOCK line (low = asserted).
    pub dock_line: SimLine,
    /// The E-STOP line (high = open: a stop).
    pub estop_line: SimLine,
    estop_was_open: bool,
    /// The board's E-STOP interrupt's record of edges (the firmware's own type).
    pub estop_edges: Rc<docking_logic::safety::EstopEdges>,
    /// What the rig was built with (a reset builds the controller again from it).
    opts: RigOptions,
    /// The MCU's option bytes (the BOR level).
    pub options: SimOptions,
    /// What the last console poll did.
    pub last_console: ConsolePoll,
}

/// Virtual CPU time charged for console work (pessimistic Cortex-M4 figures): per byte
/// read, per command run, per PIN hash (257 SHA-256 compressions).
pub const CONSOLE_NS_PER_BYTE: u64 = 2_000;
/// See [`CONSOLE_NS_PER_BYTE`].
pub const CONSOLE_NS_PER_COMMAND: u64 = 50_000;
/// See [`CONSOLE_NS_PER_BYTE`].
pub const CONSOLE_NS_PER_PIN_HASH: u64 = 3_000_000;

/// What the board's E-STOP interrupt does to the lock besides the stop: both bridge
/// inputs low, now (`estop_lock_and_mated_off` in `src/board.rs`).
fn estop_lock_off(lock: &SimLock) {
    use embedded_hal::digital::OutputPin;
    let _ = lock.in1().set_low();
    let _ = lock.in2().set_low();
}

/// The calibration of the simulated cell's default front end (offset 31 000 counts,
/// 8 590 counts/N): mN per count in Q32.32.
pub fn sim_calibration(hx: &Hx711Config) -> Calibration {
    let q32 = (1000.0 / hx.counts_per_n * 4_294_967_296.0).round() as i64;
    Calibration {
        offset_counts: hx.offset_counts.round() as i32,
        mn_per_count_q32: q32,
    }
}

/// Control steps [`Rig::booted`] runs: enough to come up, home and lock at 80 SPS.
pub const BOOT_TICKS: usize = 100;

impl Rig {
    /// A new machine (erased odometer flash, STM32F407 geometry) parked at home,
    /// locked, powered up at t = 0.
    pub fn new(opts: RigOptions) -> Self {
        Self::with_flash(opts, SharedFlash::new(SimFlash::stm32f407_odometer()))
    }

    /// A new machine ([`Self::new`]) run through its boot: 100 control steps, at rest
    /// in `idle` (what most tests start from).
    pub fn booted(opts: RigOptions) -> Self {
        let mut r = Self::new(opts);
        for _ in 0..BOOT_TICKS {
            r.tick();
        }
        r
    }

    /// The machine booting on an existing odometer flash (a reboot: parked at home),
    /// with an erased signature store.
    pub fn with_flash(opts: RigOptions, flash: SharedFlash) -> Self {
        Self::with_flashes(opts, flash, SharedFlash::new(sig_flash_array()))
    }

    /// The machine booting on existing odometer and signature flashes.
    pub fn with_flashes(opts: RigOptions, flash: SharedFlash, sig_flash: SharedFlash) -> Self {
        let Machine {
            clock,
            axis,
            lock,
            hx,
            script,
            conversions,
            hx_config: hx_cfg,
            dock_request,
            estop,
        } = Machine::new(&opts);
        if opts.commissioned {
            commission(&flash, &hx_cfg);
        }
        let mcu = Mcu::on(
            &opts,
            &clock,
            &axis,
            &lock,
            &hx,
            &hx_cfg,
            (&flash, &sig_flash),
        );
        Self {
            clock,
            axis,
            lock,
            hx,
            wdg: mcu.wdg,
            script,
            ctrl: mcu.ctrl,
            kernel: mcu.kernel,
            stop: mcu.stop,
            conversions,
            flash,
            sig_flash,
            period_ns: 1_000_000_000 / opts.rate_sps.max(1) as u64,
            console: mcu.console,
            term: SimConsole::new(),
            console_enabled: false,
            dock_line: dock_request,
            estop_line: estop,
            estop_was_open: false,
            estop_edges: Rc::new(docking_logic::safety::EstopEdges::new()),
            opts,
            options: mcu.options,
            last_console: ConsolePoll::default(),
        }
    }

    /// A reset of the MCU (`cause`: a pin reset, the watchdog…) with the machine where
    /// it is: the axis, the lock, the load cell, the lines and the flashes stay;
    /// the controller, its kernel and the console start again, and take back from the RAM
    /// journal the counters the flash does not hold yet (as the board's journal, which
    /// a reset does not clear: `src/board/crash.rs`). The E-STOP interrupt's record
    /// starts again from zero (the board's is in RAM the reset initialises). The option
    /// bytes (BOR) stay.
    pub fn reset(&mut self, cause: docking_logic::diag::ResetCause) {
        let journal = self.ctrl.journal();
        let hx_cfg = self.hx.config();
        let mut mcu = Mcu::on(
            &self.opts,
            &self.clock,
            &self.axis,
            &self.lock,
            &self.hx,
            &hx_cfg,
            (&self.flash, &self.sig_flash),
        );
        mcu.ctrl.boot(cause, None, &[journal]);
        mcu.options = self.options.clone();
        self.wdg = mcu.wdg;
        self.ctrl = mcu.ctrl;
        self.kernel = mcu.kernel;
        self.stop = mcu.stop;
        self.console = mcu.console;
        self.estop_edges = Rc::new(docking_logic::safety::EstopEdges::new());
        // The interrupt sees the input as it is from now on (no edge for its level).
        self.estop_was_open = self.estop_line.is_high();
    }
}

/// The MCU's side of a rig: the controller on the machine's devices, its safety kernel,
/// the console, and what they are built with.
struct Mcu {
    ctrl: Controller<SimBsp>,
    kernel: SafetyKernel<SimAdc>,
    stop: SimStop,
    wdg: SimWatchdog,
    console: Console,
    options: SimOptions,
}

impl Mcu {
    /// Built at the clock's now, on the devices of a machine and its odometer and
    /// signature flashes.
    fn on(
        opts: &RigOptions,
        clock: &SimClock,
        axis: &SimAxis,
        lock: &SimLock,
        hx: &SimHx711<ProfileForce>,
        hx_cfg: &Hx711Config,
        (flash, sig_flash): (&SharedFlash, &SharedFlash),
    ) -> Self {
        let (clock, axis, lock, hx, hx_cfg, flash) = (clock, axis, lock, hx, *hx_cfg, flash);
        let now_us = clock.now_ns() / 1_000;
        let wdg = SimWatchdog::new(clock.clone());
        let stop = SimStop::new(axis);
        let adc = match opts.adc {
            AdcMode::Word => SimAdc::Word(hx.clone()),
            AdcMode::Pins => match Hx711::new(hx.dout(), hx.pd_sck(), clock.clone(), Gain::A128) {
                Ok(d) => SimAdc::Pins(d),
                Err(e) => unreachable!("simulated pins are infallible: {e:?}"),
            },
        };
        let options = SimOptions::default();
        let parts = Parts::<SimBsp> {
            en_n: GatedEn::new(Watched::new(axis.enable_n(), &stop), stop.clone()),
            dir: Watched::new(axis.dir(), &stop),
            pulses: GatedPulses::new(axis.pulses(), stop.clone()),
            lock_in1: GatedHigh::new(Watched::new(lock.in1(), &stop), stop.clone()),
            lock_in2: GatedHigh::new(Watched::new(lock.in2(), &stop), stop.clone()),
            home: axis.home_switch_line(),
            end: axis.end_switch_line(),
            locked: lock.locked_switch_line(),
            released: lock.released_switch_line(),
            stop: stop.clone(),
            wdg: wdg.clone(),
            flash: BoardFlash {
                flash: flash.clone(),
                clock: clock.clone(),
                wdg: wdg.clone(),
                times: FlashTimes::MAX,
            },
            options: options.clone(),
            sig: Box::new(docking_logic::signature::Signature::new(
                SigBoardFlash {
                    flash: sig_flash.clone(),
                    clock: clock.clone(),
                    wdg: wdg.clone(),
                    timed: opts.timed_signature_flash,
                },
                Box::new(docking_logic::signature::monitor::SignatureMem::zeroed()),
            )),
        };
        let mut cfg = ControllerConfig::new(opts.rate_sps, sim_calibration(&hx_cfg));
        cfg.default_material = opts.material;
        if let Some(t) = &opts.tuning {
            t.apply(&mut cfg);
        }
        cfg.identity = opts.identity;
        let ctrl = match Controller::new(parts, cfg) {
            Ok(c) => c,
            Err(e) => unreachable!("simulated pins are infallible: {e:?}"),
        };
        let mut kernel =
            SafetyKernel::new(adc, cfg.guard, opts.rate_sps, ctrl.calibration(), now_us);
        kernel.configure(ctrl.kernel_config(), now_us);
        // The board's greeting at boot (a terminal on `hil-sim serve` sees it first).
        let mut console = Console::new([0x5A; 32]);
        console.observe(ctrl.state().name(), now_us / 1_000);
        console.banner("power_on");
        Self {
            ctrl,
            kernel,
            stop,
            wdg,
            console,
            options,
        }
    }
}

impl Rig {
    /// Advance virtual time to the next event (a conversion, or a sample period) and run
    /// what the board runs there: the safety kernel on the sample (it stops the
    /// propulsion itself if it must), then the control step, then the kernel's new
    /// configuration.
    pub fn tick(&mut self) -> docking_logic::controller::PollResult {
        let next = self
            .hx
            .next_conversion_ns()
            .min(self.clock.now_ns() + self.period_ns);
        self.clock.advance_to_ns(next);
        let now_us = self.clock.now_ns() / 1_000;
        // The board's E-STOP interrupt, at its edge (here at the tick: the rig is not
        // interrupt-accurate; the virtual board measures the real latency).
        let estop_open = self.estop_line.is_high();
        if estop_open != self.estop_was_open {
            self.estop_edge(estop_open, now_us);
        }
        self.estop_was_open = estop_open;
        self.ctrl.set_plc(
            !self.dock_line.is_high(),
            estop_open,
            self.estop_edges.snapshot(),
        );
        let ev = self
            .kernel
            .on_ready(now_us, &mut self.stop)
            .or_else(|| self.kernel.check(now_us, &mut self.stop));
        let r = if ev.is_some() || self.ctrl.step_due(now_us) {
            self.ctrl.step(now_us, ev)
        } else {
            docking_logic::controller::PollResult::default()
        };
        self.kernel.configure(self.ctrl.kernel_config(), now_us);
        // The board's service, after the step: the signature's capture, then the flash.
        self.ctrl.capture(self.kernel.last_sample_us());
        self.ctrl.background();
        if self.console_enabled {
            self.poll_console();
        }
        r
    }

    /// The main loop polls the console after the controller, and its work takes CPU
    /// time: charge it to virtual time. (Out of the tick's line: the console's code and
    /// its buffers are large, and most ticks of a long run have no console.)
    #[inline(never)]
    fn poll_console(&mut self) {
        let c = self.console.poll(
            &mut self.ctrl,
            &mut self.term,
            self.clock.now_ns() / 1_000_000,
        );
        self.clock.advance_ns(
            c.bytes_in as u64 * CONSOLE_NS_PER_BYTE
                + c.commands as u64 * CONSOLE_NS_PER_COMMAND
                + c.pin_hashes as u64 * CONSOLE_NS_PER_PIN_HASH,
        );
        self.last_console = c;
    }

    /// What the board's E-STOP interrupt does at an edge of the input (`open`: it
    /// opened) at `at_us`: stop (EN high, pulses halted, latched; the lock's bridge held
    /// low by the latch) and count the edge, stamped as the board stamps it (TIM5's
    /// 32-bit µs count).
    fn estop_edge(&mut self, open: bool, at_us: u64) {
        let n = self.stop.stop_now();
        estop_lock_off(&self.lock);
        self.estop_edges.on_edge(n, open, at_us as u32);
    }

    /// An E-STOP pulse **inside** the next control step, at its `n`-th look at the stop
    /// latch (see [`LatchHook`]): both edges there, each stopping as the board's
    /// interrupt does. The rig has no interrupts; on the board this is a pulse landing
    /// between the step's check of the latch and a write it guards. `false` from
    /// [`Self::disarm_inside_step`] afterwards: it ran.
    pub fn estop_pulse_inside_next_step(&mut self, n: u32) {
        let mut stop = self.stop.clone();
        let edges = self.estop_edges.clone();
        let lock = self.lock.clone();
        let clock = self.clock.clone();
        self.stop.hook().arm(n, move || {
            let t = (clock.now_ns() / 1_000) as u32;
            for open in [true, false] {
                let k = stop.stop_now();
                estop_lock_off(&lock);
                edges.on_edge(k, open, t);
            }
        });
    }

    /// Forget an action [`Self::estop_pulse_inside_next_step`] armed that has not run;
    /// whether one was still armed.
    pub fn disarm_inside_step(&mut self) -> bool {
        self.stop.hook().disarm()
    }

    /// The E-STOP input opens (`true`) or closes, now: the board's interrupt at its edge
    /// (stop, lock off, the edge counted), not at the next tick as [`Self::tick`] sees
    /// a change of [`Self::estop_line`].
    pub fn estop_input(&mut self, open: bool) {
        self.estop_line.set(open);
        if open != self.estop_was_open {
            let now_us = self.clock.now_ns() / 1_000;
            self.estop_edge(open, now_us);
            self.estop_was_open = open;
        }
    }

    /// An open pulse of `open_us` on a closed E-STOP input, shorter than a tick: the
    /// board's interrupt sees both its edges; the control step never samples it open.
    pub fn estop_pulse(&mut self, open_us: u64) {
        let now_us = self.clock.now_ns() / 1_000;
        self.estop_edge(true, now_us);
        self.estop_edge(false, now_us + open_us);
    }

    /// The devices a scene disturbs.
    pub fn devices(&self) -> crate::scene::Devices<'_> {
        crate::scene::Devices {
            script: &self.script,
            hx: &self.hx,
            axis: &self.axis,
            lock: &self.lock,
            estop: &self.estop_line,
        }
    }

    /// Type `line` on the terminal, run the machine until the reply is complete (or
    /// `max_ticks` pass), and return the reply text.
    ///
    /// A script's view: echo and prompt off (what `echo off` does), and whatever the
    /// console printed before (the banner) left out of the reply.
    pub fn command(&mut self, line: &str, max_ticks: usize) -> String {
        self.console_enabled = true;
        self.console.set_interactive(false);
        self.console.flush_output(&mut self.term);
        let _ = self.term.take_output();
        self.term.send(line.as_bytes());
        self.term.send(b"\r\n");
        let mut out = Vec::new();
        for _ in 0..max_ticks {
            self.tick();
            out.extend(self.term.take_output());
            if self.term.rx_pending() == 0
                && out.ends_with(b"\r\n")
                && self.last_console.commands == 0
            {
                break;
            }
        }
        String::from_utf8_lossy(&out).into_owned()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The table of counts the HX711 reads while the script adds nothing is the
    /// formula it stands for (`offset + counts/N · force_n`), bit for bit, at every step
    /// position (before contact and past the stroke too); once the script adds
    /// something, the formula itself.
    #[test]
    fn tabulated_counts_are_the_formula_bit_for_bit() {
        let clock = SimClock::new();
        let machine = MachineConfig::DEFAULT;
        let front = Hx711Config::default_for_rate(80);
        let axis = SimAxis::new(machine, clock.clone(), 0);
        let script = Rc::new(SharedScript::new());
        let conversions = Rc::new(Cell::new(0));
        let mut tabulated = ProfileForce::new(
            machine,
            &crate::machine::ForceModel::Eq7,
            axis.clone(),
            script.clone(),
            conversions.clone(),
        );
        tabulated.front_end(&front);
        let mut formula = ProfileForce::new(
            machine,
            &crate::machine::ForceModel::Eq7,
            axis.clone(),
            script.clone(),
            Rc::new(Cell::new(0)),
        );
        let mut pulses = axis.pulses();
        let (mut en, mut dir) = (axis.enable_n(), axis.dir());
        embedded_hal::digital::OutputPin::set_high(&mut dir).unwrap();
        embedded_hal::digital::OutputPin::set_low(&mut en).unwrap();
        // One step per microsecond, from home to 4 mm past the stroke's end.
        pulses.set_rate_hz(1_000_000);
        let last = machine.um_to_steps(machine.engage_um + STROKE_UM + 4_000) as u64;
        for k in 0..=last {
            clock.advance_to_ns(k * 1_000);
            let t = clock.now_ns();
            let want = front.offset_counts + front.counts_per_n * formula.force_n(t);
            let got = tabulated.counts(t, &front);
            assert_eq!(got.to_bits(), want.to_bits(), "step {k}: {got} != {want}");
        }
        assert_eq!(
            conversions.get(),
            last + 1,
            "each one counts as a conversion"
        );
        script.borrow_mut().offset_n = 1.5;
        let t = clock.now_ns();
        let want = front.offset_counts + front.counts_per_n * formula.force_n(t);
        assert_eq!(tabulated.counts(t, &front).to_bits(), want.to_bits());
    }
}
