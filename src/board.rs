//! Board layer for the STM32F407VGTx (thin: pins, clocks, peripherals, fault handlers).
//!
//! Pin map (documented in the README):
//!
//! | signal | pin | safe (disabled) level |
//! |---|---|---|
//! | propulsion STEP | PE9 | low |
//! | propulsion DIR | PE10 | — |
//! | propulsion EN (active low) | PE11 | **high** (driver off) |
//! | lock motor IN1 (toward locked) | PD12 | **low** |
//! | lock motor IN2 (toward released) | PD13 | **low** |
//! | home / end switch (active low) | PC0 / PC1 | input, pull-up |
//! | lock locked / released switch (active low) | PC2 / PC3 | input, pull-up |
//! | HX711 DOUT / PD_SCK | PB0 / PB1 | input pull-up / low |
//! | console USART2 TX / RX | PA2 / PA3 | 115200 8N1 |
//! | dock request from the vehicle/PLC (active low) | PC4 | input, pull-up |
//!
//! Step pulses come from a SysTick interrupt at 20 kHz (a phase accumulator, i.e. DDS):
//! the step rates this machine needs are ≤ 4 kHz, SysTick needs no PAC-specific timer
//! code, and the panic/fault path can stop it with one register write.

mod delay;
mod flash;

use flash::OdometerFlash;

use core::cell::RefCell;
use core::sync::atomic::{AtomicU32, Ordering};

use cortex_m::interrupt::Mutex;
use cortex_m::peripheral::syst::SystClkSource;
use cortex_m_rt::{entry, exception, ExceptionFrame};
use defmt_rtt as _;
use docking_controller::console::service::Console;
use docking_controller::controller::{Bsp, Controller, ControllerConfig, Parts};
use docking_controller::hal::{ConsoleIo, Monotonic, StepPulses, Watchdog};
use docking_controller::hx711::{Calibration, Gain, Hx711};
use embedded_hal_nb::serial::{Read as _, Write as _};
use heapless::Deque;
use stm32f4xx_hal::interrupt;
use stm32f4xx_hal::serial::{config::Config as SerialConfig, Rx, RxListen, Tx};
use stm32f4xx_hal::{
    gpio::{Input, Output, PinState, PB0, PB1, PC0, PC1, PC2, PC3, PD12, PD13, PE10, PE11, PE9},
    pac,
    prelude::*,
    rcc::Config,
    watchdog::IndependentWatchdog,
};

/// Core clock, Hz (HSE 8 MHz → PLL → 168 MHz).
const SYSCLK_HZ: u32 = 168_000_000;
/// Step-pulse interrupt rate, Hz.
const STEP_TICK_HZ: u32 = 20_000;
/// Independent watchdog period, ms (the control loop runs at ≥ 10 Hz).
const WATCHDOG_MS: u32 = 500;
/// A dock request must stay asserted this long to count, µs.
const DOCK_REQUEST_DEBOUNCE_US: u64 = 20_000;
/// HX711 output data rate (its RATE pin is tied high on this board: 80 SPS).
const SAMPLE_RATE_SPS: u32 = 80;
/// Load-cell calibration until a technician calibrates the machine (500 N, 2 mV/V
/// cell on channel A/128 at 5 V excitation: ≈ 8 590 counts/N).
const DEFAULT_CALIBRATION: Calibration = Calibration::SIM_DEFAULT;

// --- Safe state, by raw register writes (RM0090 §7.4, §8.4) ------------------------
// Used first thing at boot and from the panic and HardFault handlers, where the HAL's
// pin objects are out of reach or the HAL's state cannot be trusted.
const RCC_AHB1ENR: *mut u32 = 0x4002_3830 as *mut u32;
const GPIOD_BASE: usize = 0x4002_0C00;
const GPIOE_BASE: usize = 0x4002_1000;
const MODER: usize = 0x00;
const BSRR: usize = 0x18;
const SYST_CSR: *mut u32 = 0xE000_E010 as *mut u32;

/// Drive every motor output to its safe (disabled) state: stop step pulses, propulsion
/// EN (PE11) high, STEP (PE9) low, lock IN1/IN2 (PD12/PD13) low. Idempotent, needs no
/// HAL object, safe to call from any context.
pub fn force_safe_outputs() {
    // SAFETY: fixed, documented MMIO addresses of this chip; the writes only set the
    // motor pins' output level and mode and stop SysTick, which is what every caller
    // wants, whatever the HAL believes about them.
    unsafe {
        core::ptr::write_volatile(SYST_CSR, 0); // stop the step-pulse tick
        let en = core::ptr::read_volatile(RCC_AHB1ENR);
        core::ptr::write_volatile(RCC_AHB1ENR, en | (1 << 3) | (1 << 4)); // GPIOD, GPIOE clocks
                                                                          // Levels first (BSRR), then mode, so the pin never drives the wrong level.
        core::ptr::write_volatile((GPIOE_BASE + BSRR) as *mut u32, (1 << 11) | (1 << (9 + 16)));
        core::ptr::write_volatile(
            (GPIOD_BASE + BSRR) as *mut u32,
            (1 << (12 + 16)) | (1 << (13 + 16)),
        );
        let moder_e = (GPIOE_BASE + MODER) as *mut u32;
        let m = core::ptr::read_volatile(moder_e) & !((0b11 << 18) | (0b11 << 22));
        core::ptr::write_volatile(moder_e, m | (0b01 << 18) | (0b01 << 22));
        let moder_d = (GPIOD_BASE + MODER) as *mut u32;
        let m = core::ptr::read_volatile(moder_d) & !((0b11 << 24) | (0b11 << 26));
        core::ptr::write_volatile(moder_d, m | (0b01 << 24) | (0b01 << 26));
    }
}

#[panic_handler]
fn panic(info: &core::panic::PanicInfo) -> ! {
    // panic-probe would report first and has no hook to run before it; motors must be
    // safe before anything that can itself fail, so this handler is ours.
    force_safe_outputs();
    defmt::error!("panic: {}", defmt::Display2Format(info));
    // Hand over to the debugger / HardFault like panic-probe does.
    cortex_m::asm::udf()
}

#[exception]
unsafe fn HardFault(frame: &ExceptionFrame) -> ! {
    force_safe_outputs();
    defmt::error!("HardFault at pc={=u32:#x}", frame.pc());
    loop {
        // With a probe attached this stops the session; without one, the IWDG resets.
        cortex_m::asm::bkpt();
    }
}

defmt::timestamp!("{=u64:us}", {
    // Timestamp from the DWT cycle counter (wraps every 25 s; good enough for logs).
    (cortex_m::peripheral::DWT::cycle_count() / (SYSCLK_HZ / 1_000_000)) as u64
});

// --- Step pulses: SysTick DDS ----------------------------------------------------------

struct StepGen {
    pin: PE9<Output>,
    phase: u32,
    increment: u32,
    pin_high: bool,
}

static STEP_GEN: Mutex<RefCell<Option<StepGen>>> = Mutex::new(RefCell::new(None));
static STEP_COUNT: AtomicU32 = AtomicU32::new(0);

#[exception]
fn SysTick() {
    cortex_m::interrupt::free(|cs| {
        if let Some(g) = STEP_GEN.borrow(cs).borrow_mut().as_mut() {
            if g.pin_high {
                g.pin.set_low();
                g.pin_high = false;
            }
            let (next, overflow) = g.phase.overflowing_add(g.increment);
            g.phase = next;
            if overflow {
                g.pin.set_high();
                g.pin_high = true;
                STEP_COUNT.fetch_add(1, Ordering::Relaxed);
            }
        }
    });
}

/// Handle to the SysTick step generator.
pub struct BoardStepPulses;

impl StepPulses for BoardStepPulses {
    fn set_rate_hz(&mut self, rate_hz: u32) {
        // increment = rate / tick · 2^32; rates are capped below the tick rate / 2.
        let rate = rate_hz.min(STEP_TICK_HZ / 2) as u64;
        let inc = ((rate << 32) / STEP_TICK_HZ as u64) as u32;
        cortex_m::interrupt::free(|cs| {
            if let Some(g) = STEP_GEN.borrow(cs).borrow_mut().as_mut() {
                g.increment = inc;
            }
        });
    }

    fn take_pulses(&mut self) -> u32 {
        STEP_COUNT.swap(0, Ordering::Relaxed)
    }
}

/// Monotonic µs clock from the DWT cycle counter, extended to 64 bits (must be read at
/// least every 25 s; the control loop reads it every iteration).
pub struct BoardClock {
    last: u32,
    high: u64,
}

impl Monotonic for BoardClock {
    fn now_us(&mut self) -> u64 {
        let now = cortex_m::peripheral::DWT::cycle_count();
        if now < self.last {
            self.high += 1 << 32;
        }
        self.last = now;
        (self.high | now as u64) / (SYSCLK_HZ / 1_000_000) as u64
    }
}

/// The independent watchdog, fed only by a healthy control loop.
pub struct BoardWatchdog(IndependentWatchdog);

impl Watchdog for BoardWatchdog {
    fn feed(&mut self) {
        self.0.feed();
    }
}

// --- Console: USART2, 115200 8N1, PA2 (TX) / PA3 (RX) ------------------------------

/// Receive ring filled by the USART2 interrupt (bytes beyond it are lost: an overrun).
static RX_RING: Mutex<RefCell<Deque<u8, 256>>> = Mutex::new(RefCell::new(Deque::new()));
/// The receiver, owned by the interrupt.
static CONSOLE_RX: Mutex<RefCell<Option<Rx<pac::USART2>>>> = Mutex::new(RefCell::new(None));
/// Receive errors (framing, noise, overrun) and ring overruns.
static RX_ERRORS: AtomicU32 = AtomicU32::new(0);

#[interrupt]
fn USART2() {
    cortex_m::interrupt::free(|cs| {
        let mut rx = CONSOLE_RX.borrow(cs).borrow_mut();
        let Some(rx) = rx.as_mut() else { return };
        let mut ring = RX_RING.borrow(cs).borrow_mut();
        match rx.read() {
            Ok(b) => {
                if ring.push_back(b).is_err() {
                    RX_ERRORS.fetch_add(1, Ordering::Relaxed);
                }
            }
            Err(nb::Error::WouldBlock) => {}
            Err(nb::Error::Other(_)) => {
                RX_ERRORS.fetch_add(1, Ordering::Relaxed);
            }
        }
    });
}

/// The console's byte stream: RX from the interrupt's ring, TX through a ring pumped
/// from the main loop (never blocks the control loop).
pub struct BoardConsole {
    tx: Tx<pac::USART2>,
    out: Deque<u8, 1024>,
}

impl BoardConsole {
    /// Move queued bytes into the transmitter while it has room.
    pub fn pump(&mut self) {
        while let Some(&b) = self.out.front() {
            if self.tx.write(b).is_err() {
                break;
            }
            self.out.pop_front();
        }
    }
}

impl ConsoleIo for BoardConsole {
    fn read_byte(&mut self) -> nb::Result<u8, ()> {
        cortex_m::interrupt::free(|cs| RX_RING.borrow(cs).borrow_mut().pop_front())
            .ok_or(nb::Error::WouldBlock)
    }

    fn write(&mut self, bytes: &[u8]) -> usize {
        let mut n = 0;
        for &b in bytes {
            if self.out.push_back(b).is_err() {
                break;
            }
            n += 1;
        }
        self.pump();
        n
    }
}

/// Seed for PIN salts: the chip's 96-bit unique ID and the cycle counter at boot.
fn entropy() -> [u8; 32] {
    let uid = stm32f4xx_hal::signature::Uid::get();
    let mut e = [0u8; 32];
    let parts: [&[u8]; 4] = [
        &uid.x().to_le_bytes(),
        &uid.y().to_le_bytes(),
        uid.lot_num().as_bytes(),
        &cortex_m::peripheral::DWT::cycle_count().to_le_bytes(),
    ];
    let mut at = 0;
    for p in parts {
        for &b in p {
            if let Some(slot) = e.get_mut(at) {
                *slot = b;
            }
            at += 1;
        }
    }
    e
}

/// The board's parts for the controller.
pub struct Board;

impl Bsp for Board {
    type EnN = PE11<Output>;
    type Dir = PE10<Output>;
    type Pulses = BoardStepPulses;
    type LockIn1 = PD12<Output>;
    type LockIn2 = PD13<Output>;
    type Home = PC0<Input>;
    type End = PC1<Input>;
    type Locked = PC2<Input>;
    type Released = PC3<Input>;
    /// The HX711 on PB0/PB1, timed by the core's cycle counter (a busy-wait delay: the
    /// driver runs each clock-high phase inside a critical section, so the delay must
    /// not need interrupts; see [`delay::CycleDelay`] for why not the HAL's).
    type Adc = Hx711<PB0<Input>, PB1<Output>, delay::CycleDelay>;
    type Wdg = BoardWatchdog;
    type Flash = OdometerFlash;
}

#[entry]
fn main() -> ! {
    // 1. Motors safe before anything else, before clocks.
    force_safe_outputs();

    let (Some(dp), Some(mut cp)) = (pac::Peripherals::take(), cortex_m::Peripherals::take()) else {
        // Unreachable at reset; stay safe and let the watchdog (if any) reset us.
        loop {
            cortex_m::asm::wfi();
        }
    };

    // 2. Clocks.
    let mut rcc = dp.RCC.freeze(Config::hse(8.MHz()).sysclk(SYSCLK_HZ.Hz()));
    cp.DCB.enable_trace();
    cp.DWT.enable_cycle_counter();

    // 3. Pins, motor outputs created in their safe level (no glitch).
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
    // Dock request from the vehicle/PLC: a debounced press starts one cycle (the
    // controller refuses it unless idle, homed, locked, tared and the cone not worn out).
    let dock_request = gpioc.pc4.into_pull_up_input();
    let hx_dout = gpiob.pb0.into_pull_up_input();
    let hx_sck = gpiob.pb1.into_push_pull_output_in_state(PinState::Low);
    let gpioa = dp.GPIOA.split(&mut rcc);

    cortex_m::interrupt::free(|cs| {
        STEP_GEN.borrow(cs).replace(Some(StepGen {
            pin: step,
            phase: 0,
            increment: 0,
            pin_high: false,
        }));
    });
    cp.SYST.set_clock_source(SystClkSource::Core);
    cp.SYST.set_reload(SYSCLK_HZ / STEP_TICK_HZ - 1);
    cp.SYST.clear_current();
    cp.SYST.enable_interrupt();
    cp.SYST.enable_counter();
    let mut pulses = BoardStepPulses;
    pulses.set_rate_hz(0);

    // The HX711 may have been mid-readout when the MCU reset: power-cycle it (settles in
    // 4 conversions, which the controller's disconnect timeout allows for).
    let Ok(mut adc) = Hx711::new(hx_dout, hx_sck, delay::CycleDelay, Gain::A128) else {
        halt_safe()
    };
    if adc.power_down().and_then(|_| adc.power_up()).is_err() {
        halt_safe();
    }

    let mut clock = BoardClock { last: 0, high: 0 };
    let mut iwdg = IndependentWatchdog::new(dp.IWDG);
    iwdg.start(WATCHDOG_MS.millis());
    let wdg = BoardWatchdog(iwdg);

    let flash = OdometerFlash::new(dp.FLASH);
    let parts = Parts::<Board> {
        flash,
        en_n,
        dir,
        pulses,
        lock_in1,
        lock_in2,
        home,
        end,
        locked,
        released,
        adc,
        wdg,
    };
    let cfg = ControllerConfig::new(SAMPLE_RATE_SPS, DEFAULT_CALIBRATION);
    // Console on USART2; a console that cannot start leaves the controller running.
    let mut term = match dp.USART2.serial(
        (gpioa.pa2, gpioa.pa3),
        SerialConfig::default().baudrate(115_200.bps()),
        &mut rcc,
    ) {
        Ok(serial) => {
            let (tx, mut rx) = serial.split();
            rx.listen();
            cortex_m::interrupt::free(|cs| CONSOLE_RX.borrow(cs).replace(Some(rx)));
            // SAFETY: the handler only touches statics behind critical sections.
            unsafe { cortex_m::peripheral::NVIC::unmask(pac::Interrupt::USART2) };
            Some(BoardConsole {
                tx,
                out: Deque::new(),
            })
        }
        Err(_) => None,
    };
    let mut console = Console::new(entropy());
    let Ok(mut ctrl) = Controller::new(parts, cfg, clock.now_us()) else {
        halt_safe()
    };
    defmt::info!(
        "docking-controller {} booted; motors safe",
        env!("CARGO_PKG_VERSION")
    );

    // 4. The control loop: poll as fast as possible; a step runs per load-cell sample.
    let mut request_low_since: Option<u64> = None;
    let mut request_latched = false;
    loop {
        let now_us = clock.now_us();
        // Dock request: low for 20 ms (debounce) starts one cycle; release re-arms.
        if dock_request.is_low() {
            let since = *request_low_since.get_or_insert(now_us);
            if !request_latched && now_us.saturating_sub(since) >= DOCK_REQUEST_DEBOUNCE_US {
                request_latched = true;
                ctrl.request(docking_controller::sequencer::Request::StartCycle);
            }
        } else {
            request_low_since = None;
            request_latched = false;
        }
        let _ = ctrl.poll(now_us);
        if let Some(t) = term.as_mut() {
            // After the control step: bounded work, see console::service.
            let _ = console.poll(&mut ctrl, t, now_us / 1_000);
            t.pump();
        }
        while let Some(ev) = ctrl.next_event() {
            defmt::info!("t={=u64} ms {}", ev.t_ms, ev.event);
        }
    }
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
