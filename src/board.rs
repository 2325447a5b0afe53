//! Board layer for the STM32F407VGTx: pins, clocks, interrupts and their priorities,
//! fault handlers. The control logic is `docking_logic`'s. What follows is
//! `docs/board.md`, included (the pin map, the priorities and the safety path are written
//! once, there).
//!
#![doc = include_str!("../docs/board.md")]

mod clock;
mod console;
mod crash;
mod delay;
mod div;
mod flash;
mod mem;
mod modbus;
mod options;
mod owner;
mod step;
mod update;

use core::mem::MaybeUninit;
use core::sync::atomic::{AtomicBool, AtomicI32, AtomicU8, Ordering};

use cortex_m_rt::{exception, ExceptionFrame};
use defmt_rtt as _;
use docking_logic::console::service::Console;
#[cfg(feature = "updater")]
use docking_logic::console::update::Outcome as UpdateOutcome;
use docking_logic::controller::Handshake;
use docking_logic::controller::{Bsp, Controller, ControllerConfig, Parts};
use docking_logic::diag::{file_tail, Crash, CrashKind, ResetCause};
use docking_logic::hal::StopLatch;
use docking_logic::hal::Watchdog;
use docking_logic::hx711::{Calibration, Gain, Hx711};
use docking_logic::safety::{
    EstopEdges, GatedEn, GatedHigh, GatedPulses, KernelEvent, SafetyKernel,
};
use docking_logic::signature::monitor::SignatureMem;
use docking_logic::signature::Signature;
use stm32f4xx_hal::gpio::{
    Input, Output, PinState, PB0, PB1, PC0, PC1, PC2, PC3, PC4, PC5, PD0, PD1, PD12, PD13, PD2,
    PD3, PE10, PE11,
};
use stm32f4xx_hal::pac;
use stm32f4xx_hal::watchdog::IndependentWatchdog;

use flash::OdometerFlash;
use step::{BoardStepPulses, BoardStop};

/// The machine's tuning, generated at build time (build.rs).
mod tuning {
    // Tuning files written before the logic had its own crate name it
    // `docking_controller`; they keep building.
    #[allow(unused_imports)]
    use docking_logic as docking_controller;
    include!(concat!(env!("OUT_DIR"), "/tuning.rs"));
}

/// Core clock, Hz (HSE 8 MHz → PLL → 168 MHz).
pub const SYSCLK_HZ: u32 = 168_000_000;
/// Independent watchdog period, ms (fed by a control step that keeps its period).
const WATCHDOG_MS: u32 = 500;
/// HX711 output data rate until a technician stores the module's (console `rate`):
/// 80 SPS with its RATE pin high; most modules tie it low, 10 SPS.
const DEFAULT_SAMPLE_RATE_SPS: u32 = 80;
/// Load-cell calibration until a technician calibrates the machine (a 500 N, 2 mV/V cell
/// on channel A/128 at 5 V: ≈ 8 590 counts/N). Without a stored calibration the
/// controller refuses to dock.
const DEFAULT_CALIBRATION: Calibration = Calibration::SIM_DEFAULT;

// --- Safe state, by raw register writes (RM0090 §7.4, §8.4) ------------------------
// Used first thing at boot and from the panic and HardFault handlers, where the HAL's
// pin objects are out of reach or the HAL's state cannot be trusted.
const SYST_CSR: *mut u32 = 0xE000_E010 as *mut u32;

/// Drive every motor output to its safe (disabled) state: stop step pulses, propulsion
/// EN (PE11) high, STEP (PE9) low, lock IN1/IN2 (PD12/PD13) low. Idempotent, needs no
/// HAL object, safe to call from any context.
pub fn force_safe_outputs() {
    use update_layout::safe::{
        BSRR, D_LEVELS, D_MODE_MASK, D_MODE_OUT, E_LEVELS, E_MODE_MASK, E_MODE_OUT, GPIOD,
        GPIOD_E_CLOCKS, GPIOE, MODER, RCC_AHB1ENR,
    };
    let reg = |a: u32| a as *mut u32;
    // SAFETY: fixed, documented MMIO addresses of this chip; the writes only set the
    // motor and PLC pins' output level and mode and stop SysTick, which is what every
    // caller wants, whatever the HAL believes about them.
    unsafe {
        core::ptr::write_volatile(SYST_CSR, 0); // stop the step-pulse tick
        let en = core::ptr::read_volatile(reg(RCC_AHB1ENR));
        core::ptr::write_volatile(reg(RCC_AHB1ENR), en | GPIOD_E_CLOCKS);
        // A write to a peripheral right after its clock enable can be lost (RM0090
        // §6.3.11, ES0182 errata 2.2.x): the bus must see the enable first.
        cortex_m::asm::dsb();
        // Levels first (BSRR), then mode, so the pin never drives the wrong level: EN
        // high, STEP low, the lock bridge and the PLC outputs low (a crashing controller
        // is not ready and reports nothing mated). update-layout's `safe`, as the
        // bootloader's and this image's `__pre_init` (crash.rs).
        for (port, levels, mask, out) in [
            (GPIOE, E_LEVELS, E_MODE_MASK, E_MODE_OUT),
            (GPIOD, D_LEVELS, D_MODE_MASK, D_MODE_OUT),
        ] {
            core::ptr::write_volatile(reg(port + BSRR), levels);
            let m = core::ptr::read_volatile(reg(port + MODER)) & !mask;
            core::ptr::write_volatile(reg(port + MODER), m | out);
        }
    }
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    // Motors safe before anything that can itself fail; then the crash record, which the
    // next boot reports (a log call here could find the logger taken by the code that
    // panicked); then a reset: after it nothing moves without a request.
    force_safe_outputs();
    let (file, line) = info.location().map_or(("?", 0), |l| (l.file(), l.line()));
    crash::record(&Crash {
        kind: CrashKind::Panic,
        pc: 0,
        lr: 0,
        cfsr: 0,
        hfsr: 0,
        line,
        file: file_tail(file),
    });
    cortex_m::peripheral::SCB::sys_reset()
}

#[exception]
unsafe fn HardFault(frame: &ExceptionFrame) -> ! {
    force_safe_outputs();
    // SAFETY: reads of SCB CFSR and HFSR (fixed addresses).
    let (cfsr, hfsr) = unsafe {
        (
            core::ptr::read_volatile(0xE000_ED28 as *const u32),
            core::ptr::read_volatile(0xE000_ED2C as *const u32),
        )
    };
    crash::record(&Crash {
        kind: CrashKind::HardFault,
        pc: frame.pc(),
        lr: frame.lr(),
        cfsr,
        hfsr,
        line: 0,
        file: [0; 20],
    });
    cortex_m::peripheral::SCB::sys_reset()
}

defmt::timestamp!("{=u64:us}", clock::now_us());

/// The independent watchdog, fed only by a control step that keeps its period.
pub struct BoardWatchdog(IndependentWatchdog);

impl Watchdog for BoardWatchdog {
    fn feed(&mut self) {
        self.0.feed();
    }
}

/// The chip's 96-bit unique ID as the serial and the salts use it: X and Y (little
/// endian) and the 7-byte lot number (the wafer number is not in it), then a zero byte.
fn uid_bytes() -> [u8; 12] {
    let uid = stm32f4xx_hal::signature::Uid::get();
    let (x, y) = (uid.x().to_le_bytes(), uid.y().to_le_bytes());
    let mut b = [0u8; 12];
    for (d, s) in b
        .iter_mut()
        .zip(x.iter().chain(&y).chain(uid.lot_num().as_bytes()))
    {
        *d = *s;
    }
    b
}

/// Seed for PIN salts: the chip's unique ID (its 11 bytes) and the microsecond clock at
/// boot.
fn entropy() -> [u8; 32] {
    let mut e = [0u8; 32];
    if let (Some(id), Some(t)) = (e.get_mut(..11), uid_bytes().get(..11)) {
        id.copy_from_slice(t);
    }
    if let Some(t) = e.get_mut(11..19) {
        t.copy_from_slice(&clock::now_us().to_le_bytes());
    }
    e
}

/// The chip's 96-bit unique ID in hex (24 characters): the unit's serial number.
fn unit_serial() -> [u8; 24] {
    const HEX: &[u8; 16] = b"0123456789ABCDEF";
    let mut out = [0u8; 24]; // every byte written below
    for (pair, b) in out.chunks_exact_mut(2).zip(uid_bytes()) {
        if let [hi, lo] = pair {
            *hi = HEX.get(usize::from(b >> 4)).copied().unwrap_or(b'0');
            *lo = HEX.get(usize::from(b & 0xF)).copied().unwrap_or(b'0');
        }
    }
    out
}

/// The HX711 on PB0/PB1, its clock phases timed by the core's cycle counter.
pub type BoardAdc = Hx711<PB0<Input>, PB1<Output>, delay::CycleDelay>;

/// The board's parts for the controller.
pub struct Board;

impl Bsp for Board {
    type EnN = GatedEn<PE11<Output>, BoardStop>;
    type Dir = PE10<Output>;
    type Pulses = GatedPulses<BoardStepPulses, BoardStop>;
    type LockIn1 = GatedHigh<PD12<Output>, BoardStop>;
    type LockIn2 = GatedHigh<PD13<Output>, BoardStop>;
    type Home = PC0<Input>;
    type End = PC1<Input>;
    type Locked = PC2<Input>;
    type Released = PC3<Input>;
    type Stop = BoardStop;
    type Wdg = BoardWatchdog;
    type Flash = OdometerFlash;
    type Options = options::BoardOptions;
    type SigFlash = flash::SigFlash;
    type SigMem = &'static mut SignatureMem;
    type Sig = &'static mut Signature<flash::SigFlash, &'static mut SignatureMem>;
}

/// The docking signature's buffers, in the CCM RAM (`ccm.x`): zeroed in place by init
/// (all-zero is an empty [`SignatureMem`], which its `FromZeros` derive proves), never
/// built on a stack.
#[link_section = ".ccmram.SIGNATURE_MEM"]
static mut SIGNATURE_MEM: MaybeUninit<SignatureMem> = MaybeUninit::uninit();

/// The docking signature (its monitor and store), in the CCM RAM as its buffers: the
/// controller holds only a reference, so its own layout (and the control step's code)
/// does not change with it.
#[link_section = ".ccmram.SIGNATURE"]
static mut SIGNATURE: MaybeUninit<Signature<flash::SigFlash, &'static mut SignatureMem>> =
    MaybeUninit::uninit();

/// The signature, its store opened over sectors 2-4: call once, from init.
fn signature() -> &'static mut Signature<flash::SigFlash, &'static mut SignatureMem> {
    let sig = Signature::new(flash::SigFlash, signature_mem());
    // SAFETY: called once, from init, before anything else can reach the static.
    unsafe { (*core::ptr::addr_of_mut!(SIGNATURE)).write(sig) }
}

/// The signature's buffers, zeroed: call once, from init.
fn signature_mem() -> &'static mut SignatureMem {
    // SAFETY: called once, from init, before anything else can reach the static; the
    // zeroed bytes are a valid `SignatureMem` (it derives `zerocopy::FromZeros`, which
    // the compiler checks field by field), so the reference made is to a valid value.
    unsafe {
        let p = (*core::ptr::addr_of_mut!(SIGNATURE_MEM)).as_mut_ptr();
        p.write_bytes(0, 1);
        &mut *p
    }
}

/// The PLC handshake's pins.
pub struct PlcPins {
    /// DOCK (active low).
    pub dock: PC4<Input>,
    /// E-STOP (normally closed to ground: high = open = stop).
    pub estop: PC5<Input>,
    /// READY out.
    pub ready: PD0<Output>,
    /// MATED out.
    pub mated: PD1<Output>,
    /// FAULT out.
    pub fault: PD2<Output>,
    /// MAINTENANCE out.
    pub maintenance: PD3<Output>,
}

impl PlcPins {
    /// Drive the outputs (after each control step).
    fn write(&mut self, h: Handshake) {
        self.ready.set_state(h.ready.into());
        self.mated.set_state(h.mated.into());
        self.fault.set_state(h.fault.into());
        self.maintenance.set_state(h.maintenance.into());
    }
}

/// The E-STOP's outputs besides the propulsion (whose EN the safety path's
/// [`BoardStop::stop_now`] sets): lock IN1/IN2 (PD12/PD13), MATED (PD1) and READY (PD0)
/// low — one set/reset store, no read-modify-write, from any context. (READY stayed
/// high until the next control run, up to a sample period, with an edge no step had
/// taken: a dock then was refused at its step, but the PLC saw READY: issue 32's
/// second review.)
fn estop_outputs_off() {
    // SAFETY: a fixed MMIO set/reset register of GPIOD (clocked since init).
    unsafe {
        core::ptr::write_volatile(
            (update_layout::safe::GPIOD + update_layout::safe::BSRR) as *mut u32,
            (1 << (12 + 16)) | (1 << (13 + 16)) | (1 << (1 + 16)) | (1 << 16),
        );
    }
}

/// GPIOC's input data register (the E-STOP on PC5).
const GPIOC_IDR: *const u32 = 0x4002_0810 as *const u32;

/// The E-STOP interrupt's edge record, read by the control step.
static ESTOP_EDGES: EstopEdges = EstopEdges::new();

/// Set by every interrupt that gives the idle loop work: the service after each run
/// (events, persistence, the mailbox), the console's and the Modbus line's receive
/// interrupts and the console's DMA. Idle's sleep check reads only this flag with
/// interrupts masked.
static IDLE_WORK: AtomicBool = AtomicBool::new(false);

/// This boot is a trial after a field update, not confirmed yet (set at init, cleared by
/// the service when it confirms: issue 21).
static TRIAL: AtomicBool = AtomicBool::new(false);

/// The load cell's code the service saw last while the trial waits ([`NO_CODE`]: none
/// yet); a different one confirms it.
static TRIAL_CODE: AtomicI32 = AtomicI32::new(NO_CODE);

/// Attempts at the trial's confirmation so far (`update::CONFIRM_ATTEMPTS` at most).
static TRIAL_ATTEMPTS: AtomicU8 = AtomicU8::new(0);

/// Not a code: the HX711's are 24-bit.
const NO_CODE: i32 = i32::MIN;

/// How long until TIM2's next update, µs (it counts µs up to ARR; the service keeps
/// its reserve before it).
fn tim2_left_us() -> u32 {
    const TIM2_CNT: *const u32 = 0x4000_0024 as *const u32;
    const TIM2_ARR: *const u32 = 0x4000_002C as *const u32;
    // SAFETY: reads of TIM2's CNT and ARR, fixed MMIO addresses of this chip.
    let (cnt, arr) = unsafe {
        (
            core::ptr::read_volatile(TIM2_CNT),
            core::ptr::read_volatile(TIM2_ARR),
        )
    };
    arr.saturating_sub(cnt)
}

/// Could not even build the controller: keep the motors safe and wait for the watchdog
/// (or a debugger).
fn halt_safe() -> ! {
    force_safe_outputs();
    defmt::error!("start-up failed; motors safe, halted");
    loop {
        cortex_m::asm::wfi();
    }
}

#[rtic::app(device = stm32f4xx_hal::pac, peripherals = true)]
mod app {
    use super::*;
    use heapless::spsc::{Consumer, Producer, Queue};
    use stm32f4xx_hal::gpio::{Edge, ExtiPin};
    use stm32f4xx_hal::prelude::*;
    use stm32f4xx_hal::rcc::{Config, Enable};
    use stm32f4xx_hal::serial::config::Config as SerialConfig;

    #[shared]
    struct Shared {
        // In statics of init's (below), shared by reference: returned by value they
        // would be moved through init's stack, KiBs each.
        ctrl: &'static mut Controller<Board>,
        kernel: &'static mut SafetyKernel<BoardAdc>,
    }

    #[local]
    struct Local {
        modbus_isr: modbus::ModbusIsr,
        modbus_line: modbus::ModbusLine,
        modbus_settings: docking_logic::modbus::ModbusSettings,
        stop: BoardStop,
        events_tx: Producer<'static, KernelEvent>,
        events_rx: Consumer<'static, KernelEvent>,
        step_gen: step::StepGen,
        console_isr: console::ConsoleIsr,
        term: console::BoardConsole,
        entropy: [u8; 32],
        plc: PlcPins,
        estop_stop: BoardStop,
        tim2: pac::TIM2,
    }

    #[init(local = [
        events: Queue<KernelEvent, 16> = Queue::new(),
        mb_tx: Queue<u8, 257> = Queue::new(),
        tx_ring: Queue<u8, 1025> = Queue::new(),
        ctrl_slot: MaybeUninit<Controller<Board>> = MaybeUninit::uninit(),
        kernel_slot: MaybeUninit<SafetyKernel<BoardAdc>> = MaybeUninit::uninit(),
    ])]
    fn init(cx: init::Context) -> (Shared, Local) {
        // 1. Motors safe before anything else, before clocks.
        force_safe_outputs();
        let dp: pac::Peripherals = cx.device;
        let mut cp = cx.core;

        // 2. Why we reset, and what the last run left behind; then clear the flags.
        let csr = dp.RCC.csr().read().bits();
        dp.RCC.csr().modify(|_, w| w.rmvf().set_bit());
        let cause = ResetCause::from_csr(csr);
        let crashed = crash::take();

        // 3. Clocks; the cycle counter (the HX711's delay); the microsecond clock.
        let mut rcc = dp.RCC.freeze(Config::hse(8.MHz()).sysclk(SYSCLK_HZ.Hz()));
        cp.DCB.enable_trace();
        cp.DWT.enable_cycle_counter();
        let tim_hz = rcc.clocks.timclk1().raw();
        clock::start(dp.TIM5, &mut rcc, tim_hz);

        // 4. The brown-out reset level, read and reported (programming it is a
        // maintenance step at rest, `bor set`: see options.rs).
        let bor = options::bor_level();

        // 5. Pins, motor outputs created at their safe level (no glitch).
        let gpioa = dp.GPIOA.split(&mut rcc);
        let gpiob = dp.GPIOB.split(&mut rcc);
        let gpioc = dp.GPIOC.split(&mut rcc);
        let gpiod = dp.GPIOD.split(&mut rcc);
        let gpioe = dp.GPIOE.split(&mut rcc);
        let step = gpioe.pe9.into_push_pull_output_in_state(PinState::Low);
        let dir = gpioe.pe10.into_push_pull_output_in_state(PinState::Low);
        let en_n = gpioe.pe11.into_push_pull_output_in_state(PinState::High);
        let lock_in1 = gpiod.pd12.into_push_pull_output_in_state(PinState::Low);
        let lock_in2 = gpiod.pd13.into_push_pull_output_in_state(PinState::Low);
        let home = gpioc.pc0.into_pull_up_input();
        let end = gpioc.pc1.into_pull_up_input();
        let locked = gpioc.pc2.into_pull_up_input();
        let released = gpioc.pc3.into_pull_up_input();
        let dock = gpioc.pc4.into_pull_up_input();
        let mut estop = gpioc.pc5.into_pull_up_input();
        let ready = gpiod.pd0.into_push_pull_output_in_state(PinState::Low);
        let mated = gpiod.pd1.into_push_pull_output_in_state(PinState::Low);
        let fault = gpiod.pd2.into_push_pull_output_in_state(PinState::Low);
        let maintenance = gpiod.pd3.into_push_pull_output_in_state(PinState::Low);
        let mut hx_dout = gpiob.pb0.into_pull_up_input();
        let hx_sck = gpiob.pb1.into_push_pull_output_in_state(PinState::Low);

        // 6. HX711 data ready: DOUT falling on EXTI0.
        let mut syscfg = dp.SYSCFG.constrain(&mut rcc);
        let mut exti = dp.EXTI;
        hx_dout.make_interrupt_source(&mut syscfg);
        hx_dout.trigger_on_edge(&mut exti, Edge::Falling);
        hx_dout.enable_interrupt(&mut exti);
        // E-STOP: every edge of the input on EXTI5 (opening and closing: a bouncing
        // release is edges too, each one counted; see `estop`).
        estop.make_interrupt_source(&mut syscfg);
        estop.trigger_on_edge(&mut exti, Edge::RisingFalling);
        estop.enable_interrupt(&mut exti);

        // 7. Step pulses: SysTick at 20 kHz, its interrupt on only while moving.
        cp.SYST
            .set_clock_source(cortex_m::peripheral::syst::SystClkSource::Core);
        cp.SYST.set_reload(SYSCLK_HZ / step::STEP_TICK_HZ - 1);
        cp.SYST.clear_current();
        cp.SYST.enable_counter();

        // 8. The HX711 may have been mid-readout when the MCU reset: power-cycle it (it
        // settles in 4 conversions, which the disconnect timeout allows for).
        let Ok(mut adc) = Hx711::new(hx_dout, hx_sck, delay::CycleDelay, Gain::A128) else {
            halt_safe()
        };
        if adc.power_down().and_then(|_| adc.power_up()).is_err() {
            halt_safe();
        }

        // 9. The watchdog.
        let mut iwdg = IndependentWatchdog::new(dp.IWDG);
        iwdg.start(WATCHDOG_MS.millis());

        // 10. The controller and its safety kernel.
        let parts = Parts::<Board> {
            flash: OdometerFlash::new(dp.FLASH),
            en_n: GatedEn::new(en_n, BoardStop),
            dir,
            pulses: GatedPulses::new(BoardStepPulses, BoardStop),
            lock_in1: GatedHigh::new(lock_in1, BoardStop),
            lock_in2: GatedHigh::new(lock_in2, BoardStop),
            home,
            end,
            locked,
            released,
            stop: BoardStop,
            wdg: BoardWatchdog(iwdg),
            options: options::BoardOptions,
            sig: signature(),
        };
        let mut cfg = ControllerConfig::new(DEFAULT_SAMPLE_RATE_SPS, DEFAULT_CALIBRATION);
        // Another machine's guard envelope, hold force and nominal load-distance, if the
        // image was built for one (`DOCKING_TUNING`, see build.rs and docs/simulator.md).
        tuning::apply(&mut cfg);
        let ctrl = match Controller::new_in(cx.local.ctrl_slot, parts, cfg) {
            Ok(c) => c,
            Err(_) => halt_safe(),
        };
        let rate_sps = ctrl.sample_rate_sps();
        let now = clock::now_us();
        let kernel = cx.local.kernel_slot.write(SafetyKernel::new(
            adc,
            cfg.guard,
            rate_sps,
            ctrl.calibration(),
            now,
        ));
        kernel.configure(ctrl.kernel_config(), now);
        defmt::info!(
            "docking-controller {=str} booted; motors safe; HX711 at {=u32} SPS; BOR level {=u8}",
            env!("CARGO_PKG_VERSION"),
            rate_sps,
            bor
        );
        if bor != 3 {
            defmt::warn!(
                "BOR level {=u8} (3 = 2.70 V wanted): program it at rest with `bor set`",
                bor
            );
        }
        let journals = crash::journal_take();
        let journals: heapless::Vec<_, 2> = journals.into_iter().flatten().collect();
        ctrl.boot(cause, crashed, &journals);
        // A trial boot after an update (issue 21, docs/update.md): its self-test is the
        // board come up, the flash answering and the odometer restored (here), then a
        // live sample from the load cell; the service confirms it at the first rest
        // after that (`update::confirm_trial`). A reset before (the watchdog's included)
        // rolls it back.
        let boot = flash::OdometerFlash::boot_trial();
        match boot {
            flash::BootTrial::Trial => {
                TRIAL.store(true, Ordering::Relaxed);
                defmt::info!("update: trial boot, confirmed once the load cell answers");
            }
            flash::BootTrial::RolledBack => {
                defmt::warn!("update: the last update never confirmed and was rolled back")
            }
            flash::BootTrial::Confirmed => {}
        }
        // What `version` and Modbus identification say about the images; the image
        // record a rollback owes (a trial's confirmation writes its own, later).
        let images = update::boot_report(ctrl, boot);
        ctrl.set_images(images);
        crash::journal_write(&ctrl.journal());
        let (used, size) = crash::stack_usage();
        ctrl.set_stack_usage(used, size);

        // 11. The console on USART2 (from here a byte may come in: a line typed while
        // booting was typed after this instant, its issue time's bound).
        console::mark_rx_start(clock::now_us_low());
        let serial = match dp.USART2.serial(
            (gpioa.pa2, gpioa.pa3),
            SerialConfig::default().baudrate(115_200.bps()),
            &mut rcc,
        ) {
            Ok(s) => s,
            Err(_) => halt_safe(),
        };
        let (tx, mut rx) = serial.split();
        // Received bytes go to a ring by DMA (console.rs); RXNE's interrupt only wakes
        // the core.
        rx.listen();
        pac::DMA1::enable(&mut rcc);
        console::start_rx(dp.DMA1);
        let (tx_in, tx_out) = cx.local.tx_ring.split();

        // 12. The Modbus line on USART3 (settings as stored, else 19200 8E1 unit 1).
        let modbus_settings = docking_logic::modbus::ModbusSettings::stored(ctrl);
        // The flash erase's responder answers the line from the first erase on (one may
        // come at the first rest, before idle has run: `modbus.rs`).
        modbus::configure(&modbus_settings);
        let _de = gpiob.pb14.into_push_pull_output_in_state(PinState::Low);
        let mb_serial = match dp.USART3.serial(
            (gpiob.pb10, gpiob.pb11),
            SerialConfig::default()
                .baudrate(modbus_settings.baud.bps())
                .wordlength_9()
                .parity_even(),
            &mut rcc,
        ) {
            Ok(s) => s,
            Err(_) => halt_safe(),
        };
        let (mb_tx, mut mb_rx) = mb_serial.split();
        mb_rx.listen();
        let (mb_tx_in, mb_tx_out) = cx.local.mb_tx.split();

        // 13. The control tick: TIM2 every sample period (and pended after every sample).
        pac::TIM2::enable(&mut rcc);
        let tim2 = dp.TIM2;
        let period_us = 1_000_000 / rate_sps;
        tim2.psc()
            .write(|w| w.psc().set((tim_hz / 1_000_000 - 1) as u16));
        tim2.arr().write(|w| w.arr().set(period_us - 1));
        tim2.egr().write(|w| w.ug().set_bit());
        tim2.sr().write(|w| w.uif().clear_bit());
        tim2.dier().write(|w| w.uie().set_bit());
        tim2.cr1().write(|w| w.cen().set_bit());

        let (events_tx, events_rx) = cx.local.events.split();
        (
            Shared { ctrl, kernel },
            Local {
                modbus_isr: modbus::ModbusIsr {
                    rx: mb_rx,
                    tx: mb_tx,
                    tx_out: mb_tx_out,
                },
                modbus_line: modbus::ModbusLine { tx_in: mb_tx_in },
                modbus_settings,
                stop: BoardStop,
                events_tx,
                events_rx,
                step_gen: step::StepGen::new(step),
                console_isr: console::ConsoleIsr { tx, tx_out },
                term: console::BoardConsole::new(tx_in),
                entropy: entropy(),
                plc: PlcPins {
                    dock,
                    estop,
                    ready,
                    mated,
                    fault,
                    maintenance,
                },
                estop_stop: BoardStop,
                tim2,
            },
        )
    }

    /// The HX711's DOUT fell: a sample is ready. Read it, judge it, stop if it must —
    /// here, before anything else runs — then hand it to the control task.
    #[task(binds = EXTI0, priority = 4, shared = [kernel], local = [stop, events_tx])]
    fn data_ready(mut cx: data_ready::Context) {
        let now = clock::now_us();
        let ev = cx.shared.kernel.lock(|k| k.on_ready(now, cx.local.stop));
        // DOUT toggles with the data bits during the readout: those edges are not
        // samples. Clear the pending edge only now.
        // SAFETY: EXTI PR is write-1-to-clear; line 0 is ours.
        unsafe {
            (*pac::EXTI::ptr())
                .pr()
                .write(|w| w.pr0().clear_bit_by_one())
        };
        if let Some(ev) = ev {
            let _ = cx.local.events_tx.enqueue(ev);
            rtic::pend(pac::Interrupt::TIM2);
        }
    }

    /// The E-STOP input opened (pressed, or its wire broken): propulsion and lock off
    /// now, latched; the control step latches the `emergency_stop` fault.
    #[task(binds = EXTI9_5, priority = 5, local = [estop_stop])]
    fn estop(cx: estop::Context) {
        // The propulsion first, by the same stop and latch as the overload's — on every
        // edge, the closing one too: nothing filters the stop.
        let n = cx.local.estop_stop.stop_now();
        estop_outputs_off();
        // SAFETY: EXTI PR is write-1-to-clear; line 5 is ours. Cleared before the level
        // is read: an edge after this read pends the interrupt again.
        unsafe {
            (*pac::EXTI::ptr())
                .pr()
                .write(|w| w.pr5().clear_bit_by_one())
        };
        // The edge, counted for the control step (atomics only: no critical section,
        // no log at this priority). The level says which edge it was.
        // SAFETY: read of GPIOC IDR, a fixed MMIO address.
        let open = unsafe { core::ptr::read_volatile(GPIOC_IDR) } & (1 << 5) != 0;
        ESTOP_EDGES.on_edge(n, open, clock::now_us_low());
    }

    /// Modbus characters in and out.
    #[task(binds = USART3, priority = 2, local = [modbus_isr])]
    fn usart3(cx: usart3::Context) {
        cx.local.modbus_isr.on_interrupt();
        // A character in (or a reply's end): idle's work (its sleep check reads the flag).
        IDLE_WORK.store(true, Ordering::Relaxed);
    }

    /// Step pulses (20 kHz while the axis moves).
    #[task(binds = SysTick, priority = 3, local = [step_gen])]
    fn step_tick(cx: step_tick::Context) {
        cx.local.step_gen.tick();
    }

    /// Console bytes out; receive errors (the bytes in are the DMA's).
    #[task(binds = USART2, priority = 2, local = [console_isr])]
    fn usart2(cx: usart2::Context) {
        cx.local.console_isr.on_interrupt();
        // A byte in (RXNE pends this before the DMA takes it): idle's work.
        IDLE_WORK.store(true, Ordering::Relaxed);
    }

    /// The console's receive ring: DMA1 stream 5's half and full ring (`console.rs`).
    #[task(binds = DMA1_STREAM5, priority = 2)]
    fn console_rx_dma(_: console_rx_dma::Context) {
        console::on_dma_interrupt();
        IDLE_WORK.store(true, Ordering::Relaxed);
    }

    /// The control step: once per sample (pended by `data_ready`) and once per sample
    /// period without one (TIM2), so that deadlines and the disconnect timeout run.
    /// Then the service's turn (`owner.rs`): it runs right after this task returns.
    #[task(binds = TIM2, priority = 1, shared = [ctrl, kernel], local = [events_rx, tim2, plc])]
    fn control(mut cx: control::Context) {
        cx.local.tim2.sr().write(|w| w.uif().clear_bit());
        let now = clock::now_us();
        let now_low = clock::now_us_low();
        let events_rx = cx.local.events_rx;
        let plc = cx.local.plc;
        cx.shared.ctrl.lock(|ctrl| {
            ctrl.set_plc(
                plc.dock.is_low(),
                plc.estop.is_high(),
                ESTOP_EDGES.snapshot(),
            );
            let mut stepped = false;
            while let Some(ev) = events_rx.dequeue() {
                if !stepped {
                    owner::step_began(now_low);
                }
                let _ = ctrl.step(now, Some(ev));
                stepped = true;
            }
            if !stepped && ctrl.step_due(now) {
                owner::step_began(now_low);
                let mut stop = BoardStop;
                let silent = cx.shared.kernel.lock(|k| k.check(now, &mut stop));
                let _ = ctrl.step(now, silent);
            }
            let cfg = ctrl.kernel_config();
            cx.shared.kernel.lock(|k| k.configure(cfg, now));
            // What a reset must not lose (the flash snapshot waits for a rest).
            crash::journal_write(&ctrl.journal());
            // The handshake with the E-STOP's edges as they are now: one no step has
            // taken keeps MATED and READY low (the interrupt drove them low; issue 32's
            // review). An edge between this snapshot and the write: its interrupt's
            // MATED- and READY-low may have come before the write, so it is done again
            // after.
            let edges = ESTOP_EDGES.snapshot();
            ctrl.set_plc(plc.dock.is_low(), plc.estop.is_high(), edges);
            plc.write(ctrl.handshake());
            if ESTOP_EDGES.snapshot().edges != edges.edges {
                estop_outputs_off();
            }
        });
        rtic::pend(pac::Interrupt::SPI1);
    }

    /// The service (`owner.rs`): idle's jobs and the flash's turn, with the controller,
    /// only in the window after a step; what idle reads published. Same priority as
    /// `control`: neither preempts the other.
    #[task(binds = SPI1, priority = 1, shared = [ctrl, kernel])]
    fn service(mut cx: service::Context) {
        let now_low = clock::now_us_low();
        let kernel = &mut cx.shared.kernel;
        // The docking signature's capture of the step's sample, first and outside the
        // window (it must see every sample; a few hundred instructions): the kernel's
        // newest sample time, read under its lock (the sampler's priority for a few
        // instructions, right after the step that took the sample).
        let sample_us = kernel.lock(|k| k.last_sample_us());
        cx.shared.ctrl.lock(|ctrl| {
            ctrl.capture(sample_us);
            let period_us = 1_000_000 / ctrl.sample_rate_sps().max(1);
            if !owner::in_window(now_low, period_us, tim2_left_us()) {
                return; // `control` pends us again after its next step
            }
            owner::apply_published(ctrl);
            let modes = (ctrl.maintenance_mode(), ctrl.updating());
            owner::MAILBOX.serve(ctrl);
            if modes != (ctrl.maintenance_mode(), ctrl.updating()) {
                // A mode granted by the job (a login, an update begun): the control task
                // writes the PLC outputs now, READY low before the console says so, not
                // at the next step (it steps only when one is due; docs/board.md, "What
                // holds between the steps", rule 3).
                rtic::pend(pac::Interrupt::TIM2);
            }
            // The flash's turn (at rest only: `Controller::at_rest`).
            let erases = OdometerFlash::erases();
            ctrl.background();
            // A trial boot's last check, the load cell answering: two live samples of
            // different codes (one code alone is what a stuck converter gives too). Its
            // confirmation erases STATE's sector: at rest, as the odometer's erases, and
            // not in a window that erased already (one erase a window: the control
            // step's deadline and the watchdog keep their margins; issue 31). A failed
            // attempt is tried again at a later rest, up to `update::CONFIRM_ATTEMPTS`.
            if TRIAL.load(Ordering::Relaxed)
                && ctrl.at_rest()
                && !ctrl.updating()
                && OdometerFlash::erases() == erases
            {
                if let Some(code) = kernel.lock(|k| k.answered_code()) {
                    let before = TRIAL_CODE.load(Ordering::Relaxed);
                    TRIAL_CODE.store(code, Ordering::Relaxed);
                    if before != NO_CODE && before != code {
                        let attempt = TRIAL_ATTEMPTS.load(Ordering::Relaxed).saturating_add(1);
                        TRIAL_ATTEMPTS.store(attempt, Ordering::Relaxed);
                        if update::confirm_trial(ctrl, attempt) {
                            TRIAL.store(false, Ordering::Relaxed);
                        }
                    }
                }
            }
            owner::publish_state(ctrl.state());
        });
        IDLE_WORK.store(true, Ordering::Relaxed);
    }

    /// Everything that may wait: console commands, Modbus requests, the log. Sleeps when
    /// there is nothing to do. Reaches the controller only through the service's
    /// mailbox (`owner.rs`): it has no access of its own.
    #[idle(local = [
        term,
        entropy,
        modbus_line,
        modbus_settings,
        // In a static (616 bytes), all-zero so that it is in `.bss` (not copied from
        // flash): its settings are set first thing in `idle`.
        server: docking_logic::modbus::Server =
            docking_logic::modbus::Server::unconfigured(),
        // In a static (it holds the 8 KiB output ring): returned from init it would be
        // moved through init's stack.
        console: Console = Console::new([0; 32]),
        // The `update` command's YMODEM session (in a static: its 1 KiB block buffer;
        // nothing without the feature `updater`).
        session: update::Session = update::Session::new(),
    ])]
    fn idle(cx: idle::Context) -> ! {
        let mailbox = &owner::MAILBOX;
        cx.local.console.seed(cx.local.entropy);
        // This image runs `update`'s YMODEM session (below).
        #[cfg(feature = "updater")]
        cx.local.console.enable_updater();
        // The greeting: firmware, why it reset, the prompt (a terminal's first line).
        let (mut reset, mut state) = (None, "unknown");
        let mut images = docking_logic::update::ImageReport::UNKNOWN;
        mailbox
            .call(&mut |c| (reset, state, images) = (c.last_reset(), c.state().name(), c.images()));
        cx.local.console.observe(state, clock::now_us() / 1_000);
        cx.local
            .console
            .banner_of(&images, reset.map_or("unknown", |r| r.name()));
        // As `Server::new` would: invalid settings (never, `ModbusSettings::stored`
        // checks them) give the default ones.
        if !cx.local.server.set_settings(*cx.local.modbus_settings) {
            let _ = cx
                .local
                .server
                .set_settings(docking_logic::modbus::ModbusSettings::DEFAULT);
        }
        // The settings in force (the default ones if the stored were refused) for the
        // flash erase's responder too (`modbus.rs`).
        modbus::configure(&cx.local.server.settings());
        // The unit's serial for Modbus device identification and `version`: the chip's
        // unique ID.
        let serial_hex = unit_serial();
        let serial = core::str::from_utf8(&serial_hex).unwrap_or("");
        cx.local.console.set_unit(serial);
        let mut stack_checked_us = 0u64;
        // Before the console's receive started in init (a line typed while booting
        // came after it).
        let mut console_quiet_us = console::rx_started_us();
        loop {
            // Sleep until there is work: every interrupt that gives idle work sets
            // IDLE_WORK (the service after each run, at least once a sample period; the
            // console's and the Modbus line's receive interrupts, and the console's
            // DMA). What idle left itself (bytes not yet read, a Modbus frame waiting
            // for its t3.5) is checked first, unmasked; under the mask only the flag
            // (issue 31: that check is the longest window with every interrupt masked
            // but the HX711's own pulse, and a DOUT edge at its start waits for all of
            // it). An interrupt after the unmasked check sets the flag; one during the
            // masked check stays pending and `wfi` returns at once.
            // The time before a look that found the console's ring empty: a line read
            // later was typed after it (its issue time, below).
            let looked_us = clock::now_us_low();
            let console_waiting = cx.local.term.rx_pending();
            // Quiet: nothing in the ring and no line under way in the reader (the ring
            // empties as the reader takes a line's first bytes: counting the ring alone
            // made a clear's issue time its last byte's, and a pulse in the middle of
            // the line came before it: issue 32's second review). Less one character's
            // time: a byte being shifted in at the look lands after it.
            if !console_waiting && !cx.local.console.line_started() {
                console_quiet_us = looked_us.wrapping_sub(console::CHAR_US);
            }
            let pending =
                console_waiting || cx.local.modbus_line.rx_pending() || cx.local.server.receiving();
            let work = pending
                || cortex_m::interrupt::free(|_| {
                    let w = IDLE_WORK.swap(false, Ordering::Relaxed);
                    if !w {
                        cortex_m::asm::wfi();
                    }
                    w
                });
            if !work {
                continue;
            }
            let now_us = clock::now_us();
            // The stack's high-water mark, once a second (a walk of the unused part).
            if now_us.saturating_sub(stack_checked_us) >= 1_000_000 {
                stack_checked_us = now_us;
                let (used, size) = crash::stack_usage();
                owner::STACK_SIZE.store(size, Ordering::Relaxed);
                owner::STACK_USED.store(used, Ordering::Relaxed);
            }
            // Each job below is one bounded piece of work the service runs in its window
            // after a step: a Modbus request, a console command's gather, a record.
            // Reading input, framing, a PIN's hash, formatting and sending happen here,
            // with the controller free.
            let (term, console) = (&mut *cx.local.term, &mut *cx.local.console);
            let (line, server) = (&mut *cx.local.modbus_line, &mut *cx.local.server);
            // Modbus: each whole frame into the framer (a frame still being received
            // stays in the ring: a flash erase's responder may take it, `modbus.rs`); a
            // request whose t3.5 has passed is answered by one job (one PDU).
            loop {
                let took = line.take_whole_frame(clock::now_us(), |c, t| match c {
                    Ok(b) => server.on_byte(b, t),
                    Err(()) => server.on_line_error(t),
                });
                let t = clock::now_us();
                if server.request_due(t) {
                    // Issued when its first character began (a clear refused if an E-STOP
                    // edge came after that: docs/board.md, "What holds between the steps"),
                    // less the most its interrupt's stamp can be late: never later than
                    // the PLC sent it.
                    let issued =
                        (server.request_start_us() as u32).wrapping_sub(modbus::STAMP_LATE_MAX_US);
                    mailbox.call(&mut |ctrl| {
                        ctrl.issued_at(Some(issued));
                        let reply = server.poll(t, ctrl, serial);
                        ctrl.issued_at(None);
                        if let Some(reply) = reply {
                            line.send(reply);
                            // No flash work from now until the reply is out.
                            ctrl.set_bus_busy(true);
                        }
                    });
                }
                // Everything taken is answered (or was no request of ours); a reply on
                // the wire holds the flash by itself (DE).
                modbus::set_idle_open(server.receiving() || server.request_due(clock::now_us()));
                if !took {
                    break;
                }
            }
            let now_ms = now_us / 1_000;
            // A firmware update (console `update`): YMODEM has the line until it ends;
            // the flash goes through the owner (update.rs).
            let session = &mut *cx.local.session;
            #[cfg(feature = "updater")]
            if session.active() {
                let flash = core::cell::RefCell::new(update::UpdateFlash);
                let key = &update::PUBLIC_KEY;
                if let Some(out) = session.poll(term, &flash, key, now_ms) {
                    // Its records are written at once, before the restart: at rest with
                    // the line free (`update::at_rest`).
                    update::at_rest(&mut |ctrl| {
                        docking_logic::console::update::finish(console, ctrl, out, now_ms)
                    });
                    console.flush_output(term);
                    if matches!(out, UpdateOutcome::Verified { .. }) {
                        update::restart(term);
                    }
                }
                continue;
            }
            // The console: a line in without the controller; the command's job; a
            // login's PIN hash and the reply's formatting and sending without it.
            let (cmd_line, _) = console.read_line(term);
            if let Some(cmd_line) = cmd_line {
                // Issued no later than the last look that found the console's ring empty
                // (its end, the CR, came after that look): never later than it was typed.
                // The read time less the line's time on the wire was later whenever idle
                // read late (a Modbus job's wait for its window, an erase), and a clear
                // typed before an E-STOP pulse ran after it (issue 32's review).
                let issued = console_quiet_us;
                mailbox.call(&mut |ctrl| {
                    ctrl.issued_at(Some(issued));
                    console.run_line(ctrl, &cmd_line, now_ms);
                    ctrl.issued_at(None);
                });
                console.finish(now_ms);
                // A login that checked out: published first (only the mode's end goes
                // through the flag, `owner.rs`), then granted by its own job before the
                // console says so.
                owner::MAINTENANCE.store(console.maintenance_active(now_ms), Ordering::Relaxed);
                if console.store_due() {
                    // A login's grant, a record the hash just made (`pin set`).
                    mailbox.call(&mut |ctrl| console.store(ctrl, now_ms));
                }
            }
            console.flush_output(term);
            #[cfg(feature = "updater")]
            if console.take_update() {
                session.start(now_ms);
            }
            #[cfg(not(feature = "updater"))]
            let _ = session;
            // What the service applies at its next run: the login's end, the line.
            owner::MAINTENANCE.store(console.maintenance_active(now_ms), Ordering::Relaxed);
            console.observe(owner::state_name(), now_ms);
        }
    }
}
