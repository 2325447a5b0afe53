//! Who may touch the controller, and when: the control step owns it; everyone else asks.
//!
//! The controller is shared by two tasks **at the same priority** (1): `control` (TIM2,
//! the control step) and `service` (SPI1, a software-pended vector the board does not
//! otherwise use). Tasks at one priority never preempt each other, so neither ever
//! waits on a lock held by the other in the middle of its work: RTIC's lock between them
//! costs nothing. (The service also reads the safety kernel's last code, under the
//! kernel's lock, only at rest while a trial boot waits for its load cell: board.rs.)
//! The idle task (console, Modbus, the log) has **no access** to the
//! controller at all — RTIC checks that at compile time.
//!
//! Idle reaches the machine through [`Mailbox`], a one-slot request queue: it lends the
//! service a job (a closure over the controller: run one console command's gather, one
//! Modbus PDU, store one record), pends the service and sleeps until the job is done.
//! Reading input, line editing, a PIN's hash, formatting a report and sending happen in
//! idle, before and after the job, with the controller free.
//!
//! # The window: client work never delays a step
//!
//! The service runs a job, and the flash's turn (`Controller::background`: record
//! writes and erases, at rest only), only **inside the window after a step**:
//!
//! * the control step began less than `period − RESERVE_US` ago ([`step_began`]), and
//! * TIM2 (the control tick's timeout) is more than `RESERVE_US` from its update.
//!
//! Outside it, the service returns at once and the control task pends it again after
//! its next step, so a job waits at most one sample period (12.5 ms at 80 SPS). Before
//! the first step the window is open while TIM2's update is more than `RESERVE_US`
//! away. A client whose job found the machine not ready for it (the update's flash
//! work while a Modbus reply is on the line) waits for the next window
//! ([`sleep_until_step_after`]) rather than posting the job again in the same one. A job
//! that fits in the reserve therefore ends before the next step is due: what a
//! technician or the PLC does cannot delay the control step. Every job that runs while
//! anything moves is short (a console command's gather, one Modbus PDU: tens of µs);
//! the long ones (`measure`'s fit, a record write at the datasheet's maximum program
//! time, a sector erase) run at rest only, where the virtual board does not judge the
//! period and the watchdog (500 ms) still has its margin. `vboard sweep --flood`
//! measures the result as `control_entry_latency_max_us` (docs/board.md).
//!
//! # What the service publishes
//!
//! After each run the service publishes, with single-word atomics (no critical
//! section: nothing may mask the E-STOP), what idle reads between jobs: the state's name
//! (the console prompt). Idle publishes back the end of the maintenance mode (its idle
//! timeout: a grant is a job, in force before the console says so) and the stack's
//! high-water mark; whether the Modbus line holds the flash back is read fresh at every
//! run (`modbus::busy`). (The log's events are not handed over: the control step logs each one where it
//! happens; idle logged them a second time up to issue 20.)

use core::cell::UnsafeCell;
use core::sync::atomic::{AtomicBool, AtomicU32, AtomicU8, Ordering};

use docking_logic::controller::Controller;
use docking_logic::sequencer::State;

use super::Board;

/// The controller as the board builds it.
pub type Ctrl = Controller<Board>;

/// A job lent by idle: run once, in the service, with the controller.
type Job<'a> = dyn FnMut(&mut Ctrl) + 'a;

/// Time kept free before the next step for the step itself, µs: a job starts only if at
/// least this much remains until the next sample's step and TIM2's update.
pub const RESERVE_US: u32 = 2_000;

/// When the last control step began (TIM5's low word, µs).
static STEP_BEGAN_US: AtomicU32 = AtomicU32::new(0);
/// Whether any step has run yet.
static STEPPED: AtomicBool = AtomicBool::new(false);
/// Control runs that stepped so far (wraps): a new window opened when it changed.
static STEPS: AtomicU32 = AtomicU32::new(0);

/// The control task, as a step begins: the window opens.
pub fn step_began(now_us_low: u32) {
    STEP_BEGAN_US.store(now_us_low, Ordering::Relaxed);
    STEPPED.store(true, Ordering::Release);
    STEPS.fetch_add(1, Ordering::Release);
}

/// Whether a job may start now: inside the window after the step that began last, with
/// `RESERVE_US` left before the next one and before TIM2's update (`tim2_left_us`: how
/// long until it; TIM2 counts µs). Before the first step (boot: nothing moves, and at
/// 10 SPS the first step is 100 ms away), whenever TIM2's update is more than
/// `RESERVE_US` away: idle's first request (the greeting) used to wait for that step,
/// reading no console byte meanwhile, and a flooded console lapped its 44 ms ring
/// (issue 32, item 7).
pub fn in_window(now_us_low: u32, period_us: u32, tim2_left_us: u32) -> bool {
    if !STEPPED.load(Ordering::Acquire) {
        return tim2_left_us > RESERVE_US;
    }
    let since = now_us_low.wrapping_sub(STEP_BEGAN_US.load(Ordering::Relaxed));
    since < period_us.saturating_sub(RESERVE_US) && tim2_left_us > RESERVE_US
}

/// Idle: sleep until a control step has begun after `steps` ([`steps`]): the next
/// service window, with the inputs the step read (a retry that must wait for the world
/// to change waits here, not in a loop of jobs within one window: `update.rs`).
#[cfg(feature = "updater")]
pub fn sleep_until_step_after(steps: u32) {
    loop {
        // As `Mailbox::call`: checked with interrupts masked, so a step that begins
        // between the check and `wfi` leaves TIM2 pending and `wfi` returns at once.
        let stepped = cortex_m::interrupt::free(|_| {
            let s = STEPS.load(Ordering::Acquire) != steps;
            if !s {
                cortex_m::asm::wfi();
            }
            s
        });
        if stepped {
            return;
        }
    }
}

/// Control runs that stepped so far (see [`sleep_until_step_after`]).
#[cfg(feature = "updater")]
pub fn steps() -> u32 {
    STEPS.load(Ordering::Acquire)
}

const EMPTY: u8 = 0;
const POSTED: u8 = 1;
const DONE: u8 = 2;

/// The one-slot request queue from idle to the service (see the module doc).
pub struct Mailbox {
    state: AtomicU8,
    job: UnsafeCell<Option<*mut Job<'static>>>,
}

// SAFETY: `job` is written only by idle while `state` is EMPTY or DONE (the service
// does not read it then), and read only by the service while `state` is POSTED (idle
// does not touch it then); the Release/Acquire pairs on `state` order the accesses.
unsafe impl Sync for Mailbox {}

impl Mailbox {
    /// Empty.
    pub const fn new() -> Self {
        Self {
            state: AtomicU8::new(EMPTY),
            job: UnsafeCell::new(None),
        }
    }

    /// Idle: run `f` with the controller, in the service's window, and return when it
    /// has run. Sleeps meanwhile (interrupts still run). Call from idle only.
    pub fn call(&self, f: &mut Job<'_>) {
        let p: *mut Job<'_> = f;
        // SAFETY: only the lifetime is erased. `call` does not return before the service
        // has run the job and set DONE, so the closure (and everything it borrows from
        // idle's frame) outlives every use of the pointer; idle, the only caller, is
        // never preempted by itself.
        let p: *mut Job<'static> = unsafe { core::mem::transmute(p) };
        // SAFETY: state is EMPTY: the service does not read `job` (see `Sync`).
        unsafe { *self.job.get() = Some(p) };
        self.state.store(POSTED, Ordering::Release);
        rtic::pend(stm32f4xx_hal::pac::Interrupt::SPI1);
        loop {
            // The check with interrupts masked: the service's completion meanwhile
            // leaves nothing pending, but then `state` already reads DONE; anything
            // pending makes `wfi` return at once.
            let done = cortex_m::interrupt::free(|_| {
                let d = self.state.load(Ordering::Acquire) == DONE;
                if !d {
                    cortex_m::asm::wfi();
                }
                d
            });
            if done {
                break;
            }
        }
        // SAFETY: state is DONE: the service no longer reads `job`.
        unsafe { *self.job.get() = None };
        self.state.store(EMPTY, Ordering::Release);
    }

    /// The service: run the posted job, if any. Returns whether one ran.
    pub fn serve(&self, ctrl: &mut Ctrl) -> bool {
        if self.state.load(Ordering::Acquire) != POSTED {
            return false;
        }
        // SAFETY: state is POSTED: idle does not touch `job`, and the pointee lives until
        // idle sees DONE (see `call`).
        if let Some(p) = unsafe { *self.job.get() } {
            // SAFETY: as above; the closure is not aliased (idle sleeps in `call`).
            unsafe { (*p)(ctrl) };
        }
        self.state.store(DONE, Ordering::Release);
        true
    }
}

/// Idle's requests.
pub static MAILBOX: Mailbox = Mailbox::new();

// --- Published by the service, read by idle -----------------------------------------

/// The state's index in [`State::NAMES`] (the console's prompt).
static STATE_IX: AtomicU8 = AtomicU8::new(0);

/// The service: publish the controller's state.
pub fn publish_state(state: State) {
    STATE_IX.store(state.ordinal(), Ordering::Relaxed);
}

/// Idle: the state's name, as last published.
pub fn state_name() -> &'static str {
    State::NAMES
        .get(usize::from(STATE_IX.load(Ordering::Relaxed)))
        .copied()
        .unwrap_or("unknown")
}

// --- Published by idle, applied by the service -----------------------------------------

/// The console's maintenance mode (a technician logged in) as idle last saw it. Only
/// its **end** goes this way (the session's idle timeout): a grant is a job of its own
/// (the console's `store`, which replies only once the controller has it), and `maint
/// exit` ends it in its own job; idle publishes `true` before the grant's job, so that a
/// window between the job and the next publish never reads an older `false`
/// (docs/board.md, "What holds between the steps", rule 2).
pub static MAINTENANCE: AtomicBool = AtomicBool::new(false);
/// The stack's high-water mark, bytes (0: not measured yet), and its size.
pub static STACK_USED: AtomicU32 = AtomicU32::new(0);
/// The stack's size, bytes.
pub static STACK_SIZE: AtomicU32 = AtomicU32::new(0);

/// The service: apply what idle published.
pub fn apply_published(ctrl: &mut Ctrl) {
    if !MAINTENANCE.load(Ordering::Relaxed) {
        ctrl.set_maintenance_mode(false);
    }
    // The line as it is now (a request idle took and has not answered, a reply on the
    // wire): read at every run, never a flag published earlier (`modbus::busy`).
    ctrl.set_bus_busy(super::modbus::busy());
    let used = STACK_USED.load(Ordering::Relaxed);
    if used != 0 {
        ctrl.set_stack_usage(used, STACK_SIZE.load(Ordering::Relaxed));
    }
}
