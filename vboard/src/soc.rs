//! The STM32F407 around the core: the bus map (which model answers which address), the
//! clock, the interrupt lines, the events that happen on their own in time, the pins.
//!
//! Everything here is plain Rust with no emulator in it; `cpu.rs` runs the core and
//! calls in here for every peripheral access and at every event.

use crate::periph::art::LINE_BYTES;
use crate::periph::dma::Dma;
use crate::periph::dwt::Dwt;
use crate::periph::exti::Exti;
use crate::periph::flash::{self, Done, FlashCtl, FlashTiming, Op, ODOMETER_BASE};
use crate::periph::gpio::{Gpio, Mode, Pull};
use crate::periph::iwdg::Iwdg;
use crate::periph::nvic::{exc, Nvic};
use crate::periph::pwr::Pwr;
use crate::periph::rcc::{Bus, Rcc, ResetCause};
use crate::periph::systick::SysTick;
use crate::periph::tim::Tim;
use crate::periph::usart::Usart;
use crate::periph::Unmodelled;
use crate::time::Clock;
use crate::world::{wire_at, wire_of, Ext, Signal, World, WIRING};

/// Console baud rate of the far end (the technician's terminal).
pub const CONSOLE_BAUD: u32 = 115_200;
/// The PLC's Modbus RTU line (USART3, 8E1), baud.
pub const MODBUS_BAUD: u32 = 19_200;

/// A peripheral of the bus map.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Periph {
    /// A general-purpose timer (index into `Soc::tims`).
    Tim(usize),
    /// Independent watchdog.
    Iwdg,
    /// USART2.
    Usart2,
    /// USART3.
    Usart3,
    /// Power controller.
    Pwr,
    /// SYSCFG.
    Syscfg,
    /// EXTI.
    Exti,
    /// GPIO port (0 = A).
    Gpio(u8),
    /// Reset and clock control.
    Rcc,
    /// Flash interface.
    Flash,
    /// DMA1.
    Dma1,
}

/// A peripheral's clock enable: bus and bit of its RCC enable register.
pub type ClockEnable = Option<(Bus, u32)>;

/// The bus map: base, size, peripheral, and its clock enable.
pub const BUS_MAP: &[(u32, u32, Periph, ClockEnable)] = &[
    (0x4000_0000, 0x400, Periph::Tim(0), Some((Bus::Apb1, 0))),
    (0x4000_0400, 0x400, Periph::Tim(1), Some((Bus::Apb1, 1))),
    (0x4000_0800, 0x400, Periph::Tim(2), Some((Bus::Apb1, 2))),
    (0x4000_0C00, 0x400, Periph::Tim(3), Some((Bus::Apb1, 3))),
    (0x4000_3000, 0x400, Periph::Iwdg, None),
    (0x4000_4400, 0x400, Periph::Usart2, Some((Bus::Apb1, 17))),
    (0x4000_4800, 0x400, Periph::Usart3, Some((Bus::Apb1, 18))),
    (0x4000_7000, 0x400, Periph::Pwr, Some((Bus::Apb1, 28))),
    (0x4001_3800, 0x400, Periph::Syscfg, Some((Bus::Apb2, 14))),
    (0x4001_3C00, 0x400, Periph::Exti, None),
    (0x4002_0000, 0x400, Periph::Gpio(0), Some((Bus::Ahb1, 0))),
    (0x4002_0400, 0x400, Periph::Gpio(1), Some((Bus::Ahb1, 1))),
    (0x4002_0800, 0x400, Periph::Gpio(2), Some((Bus::Ahb1, 2))),
    (0x4002_0C00, 0x400, Periph::Gpio(3), Some((Bus::Ahb1, 3))),
    (0x4002_1000, 0x400, Periph::Gpio(4), Some((Bus::Ahb1, 4))),
    (0x4002_3800, 0x400, Periph::Rcc, None),
    (0x4002_3C00, 0x400, Periph::Flash, None),
    (0x4002_6000, 0x400, Periph::Dma1, Some((Bus::Ahb1, 21))),
];

/// Interrupt numbers wired to the models.
pub mod irq {
    /// Flash interface.
    pub const FLASH: u32 = 4;
    /// TIM2–TIM5.
    pub const TIM: [u32; 4] = [28, 29, 30, 50];
    /// USART2.
    pub const USART2: u32 = 38;
    /// USART3.
    pub const USART3: u32 = 39;
    /// DMA1 streams 0–7.
    pub const DMA1: [u32; 8] = [11, 12, 13, 14, 15, 16, 17, 47];
}

/// The interrupt lines [`Soc::update_lines`] drives, as exception bits: USART2, USART3,
/// the flash, DMA1's streams, the timers and EXTI's (lines 0-4, 9_5, 15_10).
const LINES: u128 = {
    let fixed = [irq::USART2, irq::USART3, irq::FLASH, 6, 7, 8, 9, 10, 23, 40];
    let mut m = 0u128;
    let mut i = 0;
    while i < fixed.len() {
        m |= 1 << (exc::IRQ0 + fixed[i]);
        i += 1;
    }
    i = 0;
    while i < irq::DMA1.len() {
        m |= 1 << (exc::IRQ0 + irq::DMA1[i]);
        i += 1;
    }
    i = 0;
    while i < irq::TIM.len() {
        m |= 1 << (exc::IRQ0 + irq::TIM[i]);
        i += 1;
    }
    m
};

/// Something the board noticed that software should not have done, but that the
/// hardware would have let pass (reported, the run continues).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Diagnostic {
    /// Virtual time, ps.
    pub t_ps: u64,
    /// What.
    pub what: String,
}

/// Count, mean and maximum of a latency, ps.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LatencyStats {
    /// Samples.
    pub count: u64,
    /// Sum, ps.
    pub sum_ps: u64,
    /// Maximum, ps.
    pub max_ps: u64,
}

impl LatencyStats {
    /// Add one.
    pub fn add(&mut self, ps: u64) {
        self.count += 1;
        self.sum_ps += ps;
        self.max_ps = self.max_ps.max(ps);
    }

    /// Mean, µs.
    pub fn mean_us(&self) -> f64 {
        self.sum_ps as f64 / self.count.max(1) as f64 * 1e-6
    }

    /// Maximum, µs.
    pub fn max_us(&self) -> f64 {
        self.max_ps as f64 * 1e-6
    }
}

/// A pin edge, as seen on the board.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Edge {
    /// Virtual time, ps.
    pub t_ps: u64,
    /// Signal.
    pub signal: Signal,
    /// Level after the edge.
    pub high: bool,
}

/// Instructions executed inside one function, per call, in the exception context it
/// was called from (instructions of interrupts taken meanwhile are not its own).
#[derive(Clone, Debug, Default)]
pub struct FnMeter {
    /// Entry address (Thumb bit clear).
    pub entry: u32,
    /// Calls completed.
    pub calls: u64,
    /// Instructions of the completed calls.
    pub insns: u64,
    /// The last call's instructions.
    pub last: u64,
    /// The most instructions of one call.
    pub max: u64,
    /// A call in progress: (its exception context, that context's instruction count at
    /// entry, return address, stack pointer at entry).
    pub active: Option<(usize, u64, u32, u32)>,
}

/// What a flash operation did to the code sectors, for the board to apply to the
/// emulator's memory.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CodeEffect {
    /// `len` bytes from `addr` erased (0xFF).
    Erased {
        /// First address.
        addr: u32,
        /// Bytes.
        len: u32,
    },
    /// The first `n` bytes of `value` (little-endian) programmed at `addr`: bits cleared.
    Programmed {
        /// Address.
        addr: u32,
        /// Bytes programmed (fewer than the store's when a reset cut it).
        n: usize,
        /// The stored value.
        value: u64,
    },
}

/// The SoC.
pub struct Soc {
    /// Virtual time.
    pub clock: Clock,
    /// RCC.
    pub rcc: Rcc,
    /// Flash interface.
    pub flash: FlashCtl,
    /// GPIO A–E.
    pub gpio: [Gpio; 5],
    /// TIM2, TIM3, TIM4, TIM5.
    pub tims: [Tim; 4],
    /// SysTick.
    pub systick: SysTick,
    /// NVIC and SCB.
    pub nvic: Nvic,
    /// DWT and DCB.
    pub dwt: Dwt,
    /// USART2 (console).
    pub usart2: Usart,
    /// USART3 (Modbus RTU to the PLC, through an RS-485 transceiver whose driver PB14
    /// enables).
    pub usart3: Usart,
    /// Modbus bytes that reached the bus (the transceiver's driver enabled), with their
    /// time.
    pub modbus_out: Vec<(u64, u8)>,
    /// Modbus bytes the MCU sent with the transceiver's driver off (DE low): they never
    /// reach the bus.
    pub modbus_de_losses: u64,
    /// Bytes the far end sent while our driver was on (DE high): they collide on the bus
    /// and are lost.
    pub modbus_collisions: u64,
    /// DMA1 (USART2_RX on stream 5).
    pub dma1: Dma,
    /// IWDG.
    pub iwdg: Iwdg,
    /// EXTI and SYSCFG.
    pub exti: Exti,
    /// PWR.
    pub pwr: Pwr,
    /// The machine outside.
    pub world: World,
    /// Level last delivered to each MCU→device line.
    out_levels: Vec<(Signal, Option<bool>)>,
    /// Edges of the motor and sensor lines (STEP excluded: counted by the axis).
    pub edges: Vec<Edge>,
    /// What the board noticed.
    pub diagnostics: Vec<Diagnostic>,
    /// An unmodelled access (fatal): address, write, pc.
    pub unmodelled: Option<(u32, bool)>,
    /// A reset is due (cause).
    pub reset_due: Option<ResetCause>,
    /// Code-sector bytes the engine stored raw (a flash program through the CPU), to be
    /// put back before anything reads them: the array changes when the program ends.
    pub code_restore: Vec<(u32, Vec<u8>)>,
    /// The code sectors' bytes, which the engine maps at 0 and at the flash's base
    /// (`hostmem.rs`); `None` before the board maps them.
    pub code_mem: Option<crate::hostmem::HostMem>,
    /// SRAM's bytes, which the engine maps at 0x2000_0000 (`hostmem.rs`); `None` before
    /// the board maps them.
    pub sram_mem: Option<crate::hostmem::HostMem>,
    /// Programs and sector erases of the code sectors (0-9) completed or cut.
    pub code_programs: u64,
    /// See `code_programs`.
    pub code_erases: u64,
    /// The emulation must stop after the current block.
    pub stop: bool,
    /// Milli-cycle count at which the next event is due (the block hook's compare).
    pub next_event_mc: u64,
    /// The same, ps.
    pub next_event_ps: u64,
    /// The end of the current run, ps: the caller's `until` or the next RTT poll,
    /// whichever is first (`next_event_ps` never passes it).
    pub run_limit_ps: u64,
    /// Interrupts are taken, and the core sleeps, inside the engine's run
    /// (`BoardConfig::in_run`).
    pub in_run: bool,
    /// The `wfi`s with an `in_run` hook (`hook_wfi_sites`), in the order hooked: the
    /// address, and the `wfi`'s length while the hook may sleep there (`None`: the code
    /// there has changed since, or a debugging hook watches it: `on_wfi` does nothing).
    pub wfi_hooked: Vec<(u32, Option<u32>)>,
    /// Code-sector bytes programmed or erased since the run loop last looked for new
    /// `wfi`s there: offsets `from..to`.
    pub wfi_unscanned: Option<(u32, u32)>,
    /// A hooked `wfi` was let run (`on_wfi`): its address. The engine that ends its run
    /// by itself right after it stopped at that `wfi`, whatever its bytes are now.
    pub wfi_ran_at: Option<u32>,
    /// An interrupt is pending but masked: re-check at every block.
    pub irq_waiting: bool,
    /// The block hook found the pending interrupt still not to be taken, at this
    /// `io_seq`, and no exception, flash operation's end or mask-register instruction
    /// came since (`None`: look again).
    pub masks_settled: Option<u64>,
    /// Instruction counts of translated blocks, by address (code flash and SRAM).
    pub icache: Vec<u32>,
    /// Flash stalls so far, ps.
    pub stall_ps: u64,
    /// Console bytes the far end received, with their time.
    pub console_out: Vec<(u64, u8)>,
    /// Console bytes lost because PA2/PA3 were not in their alternate function.
    pub console_pin_losses: u64,
    /// The core locked up (a fault it could not take).
    pub locked_up: bool,
    /// Faults the core took.
    pub core_faults: Vec<crate::cpu::CoreFault>,
    /// Exceptions taken.
    pub exceptions: u64,
    /// A memory access the engine refused (address, kind), for a bus fault.
    pub mem_fault: Option<(u32, unicorn_engine::MemType)>,
    /// The engine failed.
    pub engine_error: Option<String>,
    /// Engine runs (between two stops), for the figures.
    pub runs: u64,
    /// Engine starts (`emu_start`; `runs` counts the runs `in_run` continues too).
    pub engine_starts: u64,
    /// Instructions executed in each exception (0: thread mode), and its entries: the
    /// per-task cost of the firmware.
    pub exc_insns: Vec<u64>,
    /// A function whose executions are metered ([`crate::cpu::Board::meter`]).
    pub meter: Option<FnMeter>,
    /// Entries of each exception.
    pub exc_entries: Vec<u64>,
    /// Entry times of the watched exceptions and when they became pending (the control
    /// task's, for its period and its entry latency).
    pub entry_log: crate::periph::nvic::EntryLog,
    /// The exception running now (0: thread mode).
    pub current_exc: usize,
    /// When EXTI line 0's pending edge (the HX711's DOUT falling) was latched, while its
    /// handler was not running.
    pub exti0_edge_ps: Option<u64>,
    /// From each DOUT falling edge while the propulsion driver is on to the end of the
    /// handler that served it: what a stop decided in that handler takes at most, for
    /// every sample, not only the one that trips.
    pub sample_latency: LatencyStats,
    /// The same edges to the *entry* of their handler: what the sampler waited for
    /// (a higher or equal priority running, BASEPRI at its ceiling, a masked window, the
    /// exception entry), apart from what it ran.
    pub sample_entry_latency: LatencyStats,
    /// Where the longest of those waits ended: the exception running then (0: thread
    /// mode) and, when the sampler preempted it, the address it preempted (`None`: it
    /// was tail-chained after that exception).
    pub sample_entry_max_from: (usize, Option<u32>),
    /// An all-interrupts-masked window in progress (start, the `cpsid` site, the time
    /// asleep so far then).
    pub mask_start: Option<(u64, u32, u64)>,
    /// The longest such window while the propulsion was on, ps, and its `cpsid` site.
    pub mask_max: (u64, u32),
    /// The block running: its address and the milli-cycle count at its start (to time an
    /// instruction inside it).
    pub block_at: (u32, u64),
    /// The image's masking sites, by address (`Board::watch_masking`; empty: not watched).
    pub mask_sites: Vec<(u32, MaskSite)>,
    /// A site's block charged, its effect due once the block has run to its end (the
    /// site is its last instruction): at the next block, or between two runs; dropped
    /// if the block stopped short (a fault, a stop at a code hook).
    pub mask_pending: Option<MaskPending>,
    /// Peripheral accesses (reads, writes), for the figures.
    pub accesses: (u64, u64),
    /// Flash reads pay the ART's wait states ([`crate::cpu::Timing::Art`]).
    pub art_timing: bool,
    /// Core cycles (thousandths) spent in each exception (0: thread mode): execution
    /// and wait states, not sleep or flash-operation stalls.
    pub exc_mc: Vec<u64>,
    /// The watchdog's reloads, with their time (kept across resets: the gaps between
    /// them are the firmware's feeding, measured where the counter sees it).
    pub feeds: crate::realtime::Feeds,
    /// The last peripheral and core-peripheral accesses, in order (a ring of
    /// [`IO_LOG`]; `io_seq` counts them all): what a polling loop's iteration read and
    /// wrote, to check the prediction of it ([`crate::loops`]).
    pub io_log: [IoRec; IO_LOG],
    /// Accesses so far (the next one goes to `io_log[io_seq % IO_LOG]`).
    pub io_seq: u64,
    /// Polling loops found and skipped ([`crate::loops`]).
    pub loops: crate::loops::Loops,
}

/// Accesses the ring [`Soc::io_log`] keeps.
pub const IO_LOG: usize = 32;

/// A peripheral access, as [`Soc::io_log`] keeps it.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct IoRec {
    /// Address.
    pub addr: u32,
    /// Bytes.
    pub size: u8,
    /// Value read or written.
    pub value: u32,
    /// A write.
    pub write: bool,
}

/// Size of the instruction-count cache's code-flash part (sectors 0–9), halfwords.
pub const ICACHE_FLASH: usize = ((ODOMETER_BASE - flash::FLASH_BASE) / 2) as usize;
/// Size of its SRAM part, halfwords.
pub const ICACHE_SRAM: usize = (128 * 1024 / 2) as usize;

/// What an instruction that writes PRIMASK does to an all-interrupts-masked window
/// (`Board::watch_masking`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MaskSite {
    /// `cpsid i`: opens a window if interrupts were not masked.
    Disable,
    /// `cpsie i`: closes it.
    Enable,
    /// `msr primask, rN`: closes it if it leaves PRIMASK clear.
    Restore,
}

/// A masking site whose block was charged (see [`Soc::mask_pending`]).
#[derive(Clone, Copy, Debug)]
pub struct MaskPending {
    /// The kind.
    pub site: MaskSite,
    /// Its address.
    pub pc: u32,
    /// Its block's first address.
    pub block: u32,
    /// The milli-cycle count when it ran (its block's start plus the instructions
    /// before it).
    pub mc: u64,
    /// PRIMASK was set before it.
    pub masked: bool,
}

impl Soc {
    /// A powered-off board with `world` outside, the core at `cpi_milli`, the IWDG's LSI
    /// at `lsi_hz`, flash timing `timing`.
    pub fn new(world: World, cpi_milli: u64, lsi_hz: u64, timing: FlashTiming) -> Self {
        Self {
            clock: Clock::new(crate::periph::rcc::HSI_HZ, cpi_milli),
            rcc: Rcc::new(),
            flash: FlashCtl::new(timing),
            gpio: [0, 1, 2, 3, 4].map(Gpio::new),
            tims: [
                Tim::new("TIM2", true),
                Tim::new("TIM3", false),
                Tim::new("TIM4", false),
                Tim::new("TIM5", true),
            ],
            systick: SysTick::default(),
            nvic: Nvic::default(),
            dwt: {
                let mut d = Dwt::default();
                d.reset();
                d
            },
            usart2: Usart::new("USART2", CONSOLE_BAUD).with_dma_rx(),
            usart3: Usart::new("USART3", MODBUS_BAUD).with_far_bits(11), // 8E1
            modbus_out: Vec::new(),
            modbus_de_losses: 0,
            modbus_collisions: 0,
            dma1: Dma::new("DMA1"),
            iwdg: Iwdg::new(lsi_hz),
            exti: Exti::default(),
            pwr: Pwr::default(),
            world,
            out_levels: WIRING
                .iter()
                .filter(|w| w.signal.is_output())
                .map(|w| (w.signal, None))
                .collect(),
            edges: Vec::new(),
            diagnostics: Vec::new(),
            unmodelled: None,
            reset_due: None,
            code_restore: Vec::new(),
            code_mem: None,
            wfi_hooked: Vec::new(),
            wfi_unscanned: None,
            wfi_ran_at: None,
            sram_mem: None,
            code_programs: 0,
            code_erases: 0,
            stop: false,
            next_event_mc: 0,
            next_event_ps: 0,
            run_limit_ps: 0,
            in_run: true,
            irq_waiting: false,
            masks_settled: None,
            icache: vec![0; ICACHE_FLASH + ICACHE_SRAM],
            stall_ps: 0,
            console_out: Vec::new(),
            console_pin_losses: 0,
            locked_up: false,
            core_faults: Vec::new(),
            exceptions: 0,
            mem_fault: None,
            engine_error: None,
            runs: 0,
            engine_starts: 0,
            accesses: (0, 0),
            exc_insns: vec![0; crate::periph::nvic::SLOTS as usize],
            meter: None,
            exc_entries: vec![0; crate::periph::nvic::SLOTS as usize],
            entry_log: Default::default(),
            current_exc: 0,
            exti0_edge_ps: None,
            sample_latency: LatencyStats::default(),
            sample_entry_latency: LatencyStats::default(),
            sample_entry_max_from: (0, None),
            mask_start: None,
            mask_max: (0, 0),
            block_at: (0, 0),
            mask_sites: Vec::new(),
            mask_pending: None,
            art_timing: false,
            exc_mc: vec![0; crate::periph::nvic::SLOTS as usize],
            feeds: Default::default(),
            io_log: [IoRec::default(); IO_LOG],
            io_seq: 0,
            loops: Default::default(),
        }
    }

    #[inline]
    fn log_io(&mut self, addr: u32, size: usize, value: u32, write: bool) {
        self.io_log[(self.io_seq % IO_LOG as u64) as usize] = IoRec {
            addr,
            size: size as u8,
            value,
            write,
        };
        self.io_seq += 1;
    }

    /// Core cycles per instruction in exception `exc` so far (execution and flash wait
    /// states): the CPI a timing model gave that task.
    pub fn cycles_per_insn(&self, exc: usize) -> Option<f64> {
        let n = *self.exc_insns.get(exc)?;
        (n > 0).then(|| self.exc_mc[exc] as f64 / 1000.0 / n as f64)
    }

    /// The core waits `mc` milli-cycles for the flash (wait states; clock running).
    #[inline]
    pub fn wait_states(&mut self, mc: u64) {
        if mc > 0 {
            self.clock.add_mc(mc);
            if let Some(c) = self.exc_mc.get_mut(self.current_exc) {
                *c += mc;
            }
        }
    }

    /// A data read (D-Code) of `size` bytes at code-flash address `addr`, under the ART
    /// model: the wait states of the lines the cache does not hold.
    pub fn art_code_read(&mut self, addr: u32, size: usize) {
        let acr = self.flash.acr();
        let Some(first) = crate::periph::art::line_of(addr) else {
            return;
        };
        let last = crate::periph::art::line_of(addr + size.max(1) as u32 - 1).unwrap_or(first);
        let mut mc = 0;
        for line in first..=last {
            mc += self.flash.art.read_line(acr, line, || None).1;
        }
        self.wait_states(mc);
    }

    /// Now, ps.
    #[inline]
    pub fn now(&self) -> u64 {
        self.clock.now_ps()
    }

    fn diag(&mut self, what: String) {
        if self.diagnostics.len() < 1_000 && !self.diagnostics.iter().any(|d| d.what == what) {
            let t_ps = self.now();
            self.diagnostics.push(Diagnostic { t_ps, what });
        }
    }

    /// Reset every peripheral (a system reset for `cause`); returns a flash operation
    /// the reset cut short, for the board to apply.
    pub fn reset_peripherals(&mut self, cause: ResetCause) -> Option<Done> {
        let now = self.now();
        let cut = self.flash.reset(now);
        self.rcc.reset(cause, now);
        for g in &mut self.gpio {
            g.reset();
        }
        for t in &mut self.tims {
            t.reset();
        }
        self.systick.reset();
        self.nvic.reset();
        self.dwt.reset();
        self.sync_usart2(now);
        self.usart2.reset();
        self.dma1.reset();
        self.usart3.sync(now, self.rcc.clocks().pclk1);
        self.usart3.reset();
        self.iwdg.reset();
        self.feeds.close();
        self.exti.reset();
        self.pwr.reset();
        self.apply_clocks();
        self.update_outputs();
        cut
    }

    /// The clock tree changed: the core clock follows HCLK.
    pub fn apply_clocks(&mut self) {
        let hclk = self.rcc.clocks().hclk;
        let old = self.clock.hclk_hz();
        if hclk != old {
            let now = self.now();
            self.systick.clock_change(now, old);
            self.clock.set_hclk(hclk);
            // 3.3 V: one wait state per 30 MHz (RM0090 Table 10).
            let need = ((hclk.saturating_sub(1)) / 30_000_000) as u32;
            if self.flash.latency() < need {
                self.diag(format!(
                    "HCLK {hclk} Hz with {} flash wait states (needs {need}): a real part reads garbage",
                    self.flash.latency()
                ));
                self.unmodelled = Some((0x4002_3C00, false));
                self.stop = true;
            }
        }
    }

    /// Timer clock of timer `i` (TIM2–5 on APB1).
    fn tim_clk(&self, _i: usize) -> u64 {
        self.rcc.clocks().tim1clk
    }

    // --- pins ---------------------------------------------------------------------

    /// The level of pin `pin` of port `port` as IDR reads it.
    fn pin_level(&mut self, port: u8, pin: u8) -> bool {
        let g = &self.gpio[port as usize];
        let mode = g.mode(pin);
        if mode == Mode::Analog {
            return false;
        }
        if let Some(d) = g.driven(pin) {
            return d;
        }
        let pull = g.pull(pin);
        let wire = wire_at(port, pin);
        let now_ns = self.now() / 1_000;
        let device = match wire {
            Some(w) if !w.signal.is_output() => self.world.sense(w.signal, now_ns),
            _ => None,
        };
        if let Some(l) = device {
            return l;
        }
        match (wire.map(|w| w.ext), pull) {
            (Some(Ext::Up), _) | (_, Pull::Up) => true,
            (Some(Ext::Down), _) | (_, Pull::Down) => false,
            _ => {
                if mode == Mode::Input && wire.is_some() {
                    self.diag(format!(
                        "P{}{pin} read while floating (no pull-up, nothing driving it): reads 0 here, anything on a board",
                        (b'A' + port) as char
                    ));
                }
                false
            }
        }
    }

    fn port_levels(&mut self, port: u8) -> u16 {
        (0..16u8).fold(0u16, |acc, p| {
            acc | (u16::from(self.pin_level(port, p)) << p)
        })
    }

    /// Deliver the MCU's output levels to the devices (after a GPIO write or a reset).
    pub fn update_outputs(&mut self) {
        self.update_port_outputs(None);
    }

    /// Deliver the output levels of port `port` (all ports: `None`).
    fn update_port_outputs(&mut self, port: Option<u8>) {
        let now = self.now();
        for i in 0..self.out_levels.len() {
            let (signal, last) = self.out_levels[i];
            let Some(w) = wire_of(signal) else { continue };
            if port.is_some_and(|p| p != w.port) {
                continue;
            }
            let g = &self.gpio[w.port as usize];
            let level = g.driven(w.pin).unwrap_or(matches!(
                (w.ext, g.pull(w.pin)),
                (Ext::Up, _) | (_, Pull::Up)
            ));
            if last != Some(level) {
                self.out_levels[i].1 = Some(level);
                self.world.drive(signal, level, now / 1_000);
                if signal != Signal::Step {
                    self.edges.push(Edge {
                        t_ps: now,
                        signal,
                        high: level,
                    });
                }
            }
        }
        if port.is_none() {
            self.sample_exti();
        }
    }

    /// Sample the EXTI lines that watch an edge.
    pub fn sample_exti(&mut self) {
        let armed = self.exti.armed();
        if armed == 0 {
            return;
        }
        for line in 0..16u8 {
            if armed & (1 << line) != 0 {
                let port = self.exti.port_of(line);
                if (port as usize) < self.gpio.len() {
                    let l = self.pin_level(port, line);
                    let was = self.exti.pending(line);
                    self.exti.sample(line, l);
                    // Only while the propulsion driver is on (EN low): that is when the
                    // stop latency matters (and flash writes never happen then).
                    if line == 0
                        && !was
                        && self.exti.pending(0)
                        && !self.nvic.is_active(exc::IRQ0 + 6)
                        && self.exti0_edge_ps.is_none()
                        && self.world.machine.axis.enabled()
                    {
                        self.exti0_edge_ps = Some(self.now());
                    }
                }
            }
        }
    }

    // --- events -------------------------------------------------------------------

    /// The next time something happens on its own, ps (`u64::MAX`: nothing).
    pub fn next_event(&self) -> u64 {
        let c = self.rcc.clocks();
        let mut t = u64::MAX;
        let mut at = |x: Option<u64>| {
            if let Some(x) = x {
                t = t.min(x);
            }
        };
        at(self.systick.next_event(c.hclk));
        for (i, tim) in self.tims.iter().enumerate() {
            at(tim.next_event(self.tim_clk(i)));
        }
        at(self.usart2.next_event());
        at(self.usart3.next_event());
        at(self.iwdg.next_event());
        at(self.flash.busy_until());
        if self.exti.armed() != 0 {
            at(Some(self.world.next_change_ns().saturating_mul(1_000)));
        }
        t
    }

    /// Bring every model up to now: pend what is due, apply what ended, set the
    /// interrupt lines. A flash operation that ended is returned for the board to apply
    /// to the array.
    pub fn process(&mut self) -> Option<Done> {
        let now = self.now();
        let c = self.rcc.clocks();
        if self.systick.sync(now, c.hclk) > 0 && self.systick.tickint() {
            self.nvic.pend(exc::SYSTICK);
        }
        for i in 0..self.tims.len() {
            let clk = self.tim_clk(i);
            self.tims[i].sync(now, clk);
        }
        self.sync_usart2(now);
        self.collect_console();
        self.usart3.sync(now, c.pclk1);
        self.collect_modbus();
        if self.iwdg.running() {
            self.rcc.force_lsi(now);
        }
        if self.iwdg.sync(now) && self.reset_due.is_none() {
            self.reset_due = Some(ResetCause::Watchdog);
        }
        let done = self.flash.complete(now).or_else(|| self.flash.take_done());
        self.sample_exti();
        self.update_lines();
        done
    }

    /// Bring USART2 up to `now`, its received bytes through DMA1 stream 5 when it
    /// requests them (`CR3.DMAR`): the DMA moves each at its own time, whatever the core
    /// is doing (stalled on the flash included).
    fn sync_usart2(&mut self, now: u64) {
        let pclk = self.rcc.clocks().pclk1;
        let dma = &mut self.dma1;
        self.usart2
            .sync_dma(now, pclk, &mut |t, b| dma.usart2_rx(t, b));
    }

    /// A byte already waiting in USART2's DR when its DMA request or stream comes on is
    /// taken then (the request is a level).
    fn serve_usart2_dma(&mut self) {
        if let Some(b) = self.usart2.dma_request() {
            let now = self.now();
            if self.dma1.usart2_rx(now, b) {
                self.usart2.dma_read();
            }
        }
        for n in std::mem::take(&mut self.dma1.notes) {
            self.diag(n);
        }
    }

    /// The SRAM bytes the DMA wrote since the last call, for the board to store.
    pub fn take_dma_writes(&mut self) -> Vec<(u32, u8)> {
        self.dma1.take_writes()
    }

    /// Move the bytes USART2 sent to the far end (if PA2 is its alternate function).
    fn collect_console(&mut self) {
        let sent = self.usart2.take_sent();
        if sent.is_empty() {
            return;
        }
        if self.af_ok(Signal::ConsoleTx, 7) {
            self.console_out.extend(sent);
        } else {
            self.console_pin_losses += sent.len() as u64;
            self.diag("USART2 sent bytes but PA2 is not in alternate function 7".into());
        }
    }

    /// Move the bytes USART3 sent to the bus: only with PB10 in alternate function 7 and
    /// the transceiver's driver enabled (DE, PB14, high) at the byte's time.
    fn collect_modbus(&mut self) {
        let sent = self.usart3.take_sent();
        if sent.is_empty() {
            return;
        }
        let af = self.af_ok(Signal::ModbusTx, 7);
        // The character time at the rate USART3 is set to (the stored setting).
        let baud = self.usart3.baud(self.rcc.clocks().pclk1).max(1);
        for (t, b) in sent {
            // DE's level when the byte's stop bit ended (a byte starts 11 bit times
            // earlier; DE must have been high all along: checked at both ends).
            let start = t.saturating_sub(11 * crate::time::PS_PER_S / baud);
            if af && self.de_high_at(start) && self.de_high_at(t) {
                self.modbus_out.push((t, b));
            } else {
                self.modbus_de_losses += 1;
            }
        }
    }

    /// The DE line's level at `t_ps`, from its edges.
    fn de_high_at(&self, t_ps: u64) -> bool {
        self.edges
            .iter()
            .rev()
            .find(|e| e.signal == Signal::ModbusDe && e.t_ps <= t_ps)
            .is_some_and(|e| e.high)
    }

    /// The PLC sends `bytes` on the Modbus line (they arrive at its rate). Lost at once
    /// when PB11 is not USART3's RX, or when our transceiver's driver is on (DE high: a
    /// collision on the bus).
    pub fn modbus_send(&mut self, bytes: &[u8]) -> bool {
        let now = self.now();
        self.modbus_send_at(bytes, now)
    }

    /// [`Self::modbus_send`] with the first byte's start at `at_ps` (at most a step
    /// before now: a master on a fixed time grid, whatever instruction the board
    /// stopped at).
    pub fn modbus_send_at(&mut self, bytes: &[u8], at_ps: u64) -> bool {
        let now = at_ps;
        if !self.af_ok(Signal::ModbusRx, 7) {
            return false;
        }
        if self.de_high_at(now) {
            self.modbus_collisions += bytes.len() as u64;
            return false;
        }
        self.usart3.far_send(bytes, now);
        true
    }

    fn af_ok(&self, signal: Signal, af: u32) -> bool {
        let Some(w) = wire_of(signal) else {
            return false;
        };
        let g = &self.gpio[w.port as usize];
        let afr = g
            .read(if w.pin < 8 { 0x20 } else { 0x24 }, 4, 0)
            .unwrap_or(0);
        g.mode(w.pin) == Mode::Alternate && (afr >> (4 * (w.pin % 8))) & 0xF == af
    }

    /// The far end of the console sends `bytes` (they arrive at the line rate). Returns
    /// `false` when they are lost at once: PA3 is not (yet) USART2's RX.
    pub fn console_send(&mut self, bytes: &[u8]) -> bool {
        let now = self.now();
        self.console_send_at(bytes, now)
    }

    /// [`Self::console_send`] with the first byte's start at `at_ps` (at most a step
    /// before now: a sender on a fixed time grid, whatever instruction the board
    /// stopped at).
    pub fn console_send_at(&mut self, bytes: &[u8], at_ps: u64) -> bool {
        let now = at_ps;
        if !self.af_ok(Signal::ConsoleRx, 7) {
            self.console_pin_losses += bytes.len() as u64;
            return false;
        }
        self.usart2.far_send(bytes, now);
        true
    }

    /// Set the NVIC's interrupt lines from the models.
    pub fn update_lines(&mut self) {
        if self.usart2.take_irq_pulse() {
            self.nvic.pend(exc::IRQ0 + irq::USART2);
        }
        // Every modelled line at once, as one mask (the levels of `LINES`' bits): this
        // runs after every register access and exception return.
        let mut high = 0u128;
        let mut line = |irq: u32, on: bool| high |= u128::from(on) << (exc::IRQ0 + irq);
        line(irq::USART2, self.usart2.irq());
        for (s, &l) in irq::DMA1.iter().enumerate() {
            line(l, self.dma1.irq(s));
        }
        line(irq::USART3, self.usart3.irq());
        line(irq::FLASH, self.flash.irq());
        for (i, t) in self.tims.iter().enumerate() {
            if let Some(&l) = irq::TIM.get(i) {
                line(l, t.irq());
            }
        }
        for l in self.exti.irqs() {
            line(l, true);
        }
        self.nvic.set_lines(LINES, high);
        self.note_pends();
    }

    /// Hand the exceptions that became pending since the last call to the entry log,
    /// with the time now. Every path that sets a pending bit (a model's event, a register
    /// write, an exception return) ends in [`Soc::update_lines`], which calls this at the
    /// same instant; exception entry calls it too, so a pend is never noted after its
    /// entry.
    #[inline]
    pub fn note_pends(&mut self) {
        let rose = self.nvic.take_rises();
        if rose != 0 {
            let now = self.now();
            self.entry_log.note_pends(rose, now);
        }
    }

    // --- the bus ------------------------------------------------------------------

    fn lookup(addr: u32) -> Option<(u32, Periph, ClockEnable)> {
        BUS_MAP
            .iter()
            .find(|(b, s, _, _)| addr >= *b && addr < b + s)
            .map(|&(b, _, p, en)| (b, p, en))
    }

    fn clock_on(&mut self, name: Periph, en: ClockEnable) -> bool {
        match en {
            Some((bus, bit)) if !self.rcc.enabled(bus, bit) => {
                self.diag(format!(
                    "{name:?} accessed with its clock disabled: reads 0, writes are lost"
                ));
                false
            }
            _ => true,
        }
    }

    fn unmodelled_at(&mut self, addr: u32, write: bool) {
        if self.unmodelled.is_none() {
            self.unmodelled = Some((addr, write));
        }
        self.stop = true;
    }

    /// What a read of the peripheral register at `addr` would return if read again at
    /// any instant from now until the board's next event, and the instant (ps, at or
    /// before which it stops being so: `u64::MAX` when only an event can change it).
    /// Such a read changes nothing a second read would not (the flash's `SR` while it is
    /// busy, the RCC's registers, a USART's `SR` once read and its control registers,
    /// the IWDG's `SR`/`PR`/`RLR`, `PWR`; `DWT_CTRL`). `None`: any other register, for
    /// which a polling loop is not skipped.
    pub fn peek(&self, addr: u32, size: usize) -> Option<(u32, u64)> {
        if addr == 0xE000_1000 {
            let cycles = self.clock.cycles();
            return self.dwt.read(0, size, cycles).ok().map(|v| (v, u64::MAX));
        }
        let (base, p, en) = Self::lookup(addr)?;
        if let Some((bus, bit)) = en {
            if !self.rcc.enabled(bus, bit) {
                return None;
            }
        }
        let off = addr - base;
        let now = self.now();
        match p {
            Periph::Flash => self.flash.peek(off, size).map(|v| (v, u64::MAX)),
            Periph::Rcc => self
                .rcc
                .peek(off, size, now)
                .ok()
                .map(|v| (v, self.rcc.next_ready_after(now))),
            Periph::Usart2 => self.usart2.peek(off, size).map(|v| (v, u64::MAX)),
            Periph::Usart3 => self.usart3.peek(off, size).map(|v| (v, u64::MAX)),
            Periph::Iwdg => self.iwdg.peek(off, size).map(|v| (v, u64::MAX)),
            Periph::Pwr => self.pwr.read(off, size).ok().map(|v| (v, u64::MAX)),
            _ => None,
        }
    }

    /// Whether the cycle counter counts (its reads follow the core's cycles).
    pub fn cyccnt_counting(&self) -> bool {
        self.dwt.counting()
    }

    /// `DWT_CYCCNT` at core cycle `cycles`.
    pub fn cyccnt_at(&self, cycles: u64) -> u32 {
        self.dwt.cyccnt(cycles)
    }

    /// A peripheral read (0x4000_0000–0x5FFF_FFFF).
    pub fn bus_read(&mut self, addr: u32, size: usize) -> u32 {
        self.accesses.0 += 1;
        let Some((base, p, en)) = Self::lookup(addr) else {
            self.unmodelled_at(addr, false);
            return 0;
        };
        if !self.clock_on(p, en) {
            return 0;
        }
        let off = addr - base;
        let now = self.now();
        let c = self.rcc.clocks();
        let r = match p {
            Periph::Tim(i) => {
                let clk = self.tim_clk(i);
                self.tims[i].read(off, size, now, clk)
            }
            Periph::Iwdg => self.iwdg.read(off, size, now),
            Periph::Usart2 => {
                self.sync_usart2(now);
                let r = self.usart2.read(off, size, now, c.pclk1);
                self.collect_console();
                r
            }
            Periph::Usart3 => {
                let r = self.usart3.read(off, size, now, c.pclk1);
                self.collect_modbus();
                r
            }
            Periph::Pwr => self.pwr.read(off, size),
            Periph::Syscfg => self.exti.read_syscfg(off, size),
            Periph::Exti => self.exti.read(off, size),
            Periph::Gpio(n) => {
                let levels = if off & !3 == 0x10 {
                    self.port_levels(n)
                } else {
                    0
                };
                self.gpio[n as usize].read(off, size, levels)
            }
            Periph::Rcc => self.rcc.read(off, size, now),
            Periph::Flash => self.flash.read(off, size, now),
            Periph::Dma1 => {
                // NDTR counts what arrived up to now.
                self.sync_usart2(now);
                self.dma1.read(off, size)
            }
        };
        // A read can only clear flags (lower lines) or notice what time already brought:
        // no new event to schedule, no new interrupt to take. A read of a port, the RCC,
        // the PWR, SYSCFG or EXTI changes nothing a line comes from, and every change of
        // one has already ended in `update_lines`: nothing to update (the step
        // generator's ODR read at each SysTick, the HX711's IDR reads).
        if !matches!(
            p,
            Periph::Gpio(_) | Periph::Rcc | Periph::Pwr | Periph::Syscfg | Periph::Exti
        ) {
            self.update_lines();
        }
        let v = r.unwrap_or_else(|Unmodelled { .. }| {
            self.unmodelled_at(addr, false);
            0
        });
        self.log_io(addr, size, v, false);
        v
    }

    /// A peripheral write.
    pub fn bus_write(&mut self, addr: u32, size: usize, value: u32) {
        self.accesses.1 += 1;
        self.log_io(addr, size, value, true);
        let pending_before = self.nvic.pending_enabled();
        let Some((base, p, en)) = Self::lookup(addr) else {
            self.unmodelled_at(addr, true);
            return;
        };
        if !self.clock_on(p, en) {
            return;
        }
        let off = addr - base;
        let now = self.now();
        let c = self.rcc.clocks();
        let r = match p {
            Periph::Tim(i) => {
                let clk = self.tim_clk(i);
                self.tims[i].write(off, size, value, now, clk)
            }
            Periph::Iwdg => {
                let reloads = self.iwdg.reloads;
                let r = self.iwdg.write(off, value, now).map(|started| {
                    if started {
                        self.rcc.force_lsi(now);
                    }
                });
                if self.iwdg.reloads != reloads {
                    self.feeds.add(now);
                }
                r
            }
            Periph::Usart2 => {
                self.sync_usart2(now);
                let r = self.usart2.write(off, size, value, now, c.pclk1);
                self.serve_usart2_dma();
                r
            }
            Periph::Usart3 => self.usart3.write(off, size, value, now, c.pclk1),
            Periph::Pwr => self.pwr.write(off, size, value),
            Periph::Syscfg => self.exti.write_syscfg(off, size, value),
            Periph::Exti => self.exti.write(off, size, value),
            Periph::Gpio(n) => {
                let r = self.gpio[n as usize].write(off, size, value);
                self.update_port_outputs(Some(n));
                self.sample_exti();
                r
            }
            Periph::Rcc => self.rcc.write(off, size, value, now).map(|changed| {
                if changed {
                    self.apply_clocks();
                }
            }),
            Periph::Flash => self.flash.write(off, size, value, now),
            Periph::Dma1 => {
                self.sync_usart2(now);
                let r = self.dma1.write(off, size, value);
                self.serve_usart2_dma();
                r
            }
        };
        if let Err(Unmodelled { .. }) = r {
            self.unmodelled_at(addr, true);
        }
        self.after_access(pending_before);
    }

    /// After a register write: new lines, maybe an interrupt, new event times. The engine
    /// stops only for something new (an exception that became pending, a reset); one
    /// already pending but masked is watched by the block hook (`irq_waiting`).
    fn after_access(&mut self, pending_before: u128) {
        self.update_lines();
        let pending = self.nvic.pending_enabled();
        if pending & !pending_before != 0 || self.nvic.reset_requested {
            self.stop = true;
        }
        self.irq_waiting |= pending != 0;
        let t = self.next_event().min(self.next_event_ps);
        self.next_event_mc = self.clock.mc_at(t);
        self.next_event_ps = t;
    }

    /// A read of the private peripheral bus (0xE000_0000–0xE00F_FFFF).
    pub fn ppb_read(&mut self, addr: u32, size: usize) -> u32 {
        let now = self.now();
        let hclk = self.clock.hclk_hz();
        let cycles = self.clock.cycles();
        let r = match addr {
            0xE000_1000..=0xE000_1FFF => self.dwt.read(addr - 0xE000_1000, size, cycles),
            0xE000_E010..=0xE000_E01F => self.systick.read(addr - 0xE000_E010, size, now, hclk),
            0xE000_EDF0..=0xE000_EDFF => self.dwt.read_dcb(addr - 0xE000_EDF0, size),
            0xE000_E000..=0xE000_EFFF => self.nvic.read(addr - 0xE000_E000, size),
            _ => Err(Unmodelled {
                offset: addr,
                write: false,
            }),
        };
        let v = r.unwrap_or_else(|_| {
            self.unmodelled_at(addr, false);
            0
        });
        self.log_io(addr, size, v, false);
        v
    }

    /// A write of the private peripheral bus.
    pub fn ppb_write(&mut self, addr: u32, size: usize, value: u32) {
        self.log_io(addr, size, value, true);
        // Any write to the NVIC/SCB may change what can be taken (enables, priorities).
        let pending_before = if (0xE000_E100..0xE000_EF00).contains(&addr) {
            0
        } else {
            self.nvic.pending_enabled()
        };
        let now = self.now();
        let hclk = self.clock.hclk_hz();
        let cycles = self.clock.cycles();
        let r = match addr {
            0xE000_1000..=0xE000_1FFF => self.dwt.write(addr - 0xE000_1000, size, value, cycles),
            0xE000_E010..=0xE000_E01F => {
                self.systick
                    .write(addr - 0xE000_E010, size, value, now, hclk)
            }
            0xE000_EDF0..=0xE000_EDFF => {
                self.dwt.write_dcb(addr - 0xE000_EDF0, size, value, cycles)
            }
            0xE000_E000..=0xE000_EFFF => self.nvic.write(addr - 0xE000_E000, size, value),
            _ => Err(Unmodelled {
                offset: addr,
                write: true,
            }),
        };
        if r.is_err() {
            self.unmodelled_at(addr, true);
        }
        self.after_access(pending_before);
    }

    // --- flash array --------------------------------------------------------------

    /// The core waits (stalled) until `t`.
    pub fn stall_to(&mut self, t: u64) {
        let now = self.now();
        if t > now {
            self.stall_ps += t - now;
            self.clock.stall_until(t);
        }
    }

    /// The core waits for a flash operation in progress (a fetch or read from flash).
    /// Returns the operation that ended, for the board to apply.
    pub fn stall_for_flash(&mut self) -> Option<Done> {
        let end = self.flash.busy_until()?;
        self.stall_to(end);
        let d = self.flash.complete(self.now());
        let t = self.next_event().min(self.next_event_ps);
        self.next_event_mc = self.clock.mc_at(t);
        self.next_event_ps = t;
        d
    }

    /// Apply a finished (or cut) operation to the odometer sectors; code-sector effects
    /// are returned for the board to apply to emulator memory.
    pub fn apply_flash(&mut self, d: Done) -> Option<CodeEffect> {
        // Lines the ART cached from an erased sector keep their pre-erase bytes until the
        // caches are reset.
        // (An erase cut short by a reset: the reset emptied the caches.)
        match d.op {
            Op::Erase { sector } if d.permille >= 1000 => {
                let from = flash::sector_base(sector) - flash::FLASH_BASE;
                let len = flash::sector_kib(sector) * 1024;
                self.flash.art.erased(from, from + len);
            }
            Op::MassErase if d.permille >= 1000 => self.flash.art.erased(0, flash::FLASH_SIZE),
            _ => {}
        }
        match d.op {
            Op::Program { addr, size, value } => {
                if addr >= ODOMETER_BASE {
                    let bytes = value.to_le_bytes();
                    let n = if d.permille >= 1000 {
                        size
                    } else {
                        size * d.permille as usize / 1000
                    };
                    if let Some(b) = bytes.get(..n) {
                        let off = addr - ODOMETER_BASE;
                        let _ = self.world.flash.with(|f| f.program(off, b));
                        // Written through to a cached line: it takes what the array holds.
                        let mut now = vec![0xFFu8; b.len()];
                        let _ = self.world.flash.with(|f| {
                            embedded_storage::nor_flash::ReadNorFlash::read(f, off, &mut now)
                        });
                        self.flash.art.programmed(addr - flash::FLASH_BASE, &now);
                    }
                    None
                } else {
                    // A bootloader's swap programs the code sectors (sectors 1-9);
                    // nothing may program sector 0, the bootloader's own.
                    if addr < flash::sector_base(1) {
                        self.diag(format!("program of sector 0 at {addr:#x}"));
                    }
                    let n = if d.permille >= 1000 {
                        size
                    } else {
                        size * d.permille as usize / 1000
                    };
                    self.code_programs += 1;
                    Some(CodeEffect::Programmed { addr, n, value })
                }
            }
            Op::Erase { sector } => {
                if sector >= 10 {
                    let i = (sector - 10) as usize;
                    self.world.flash.with(|f| {
                        if d.permille >= 1000 {
                            let _ = f.erase_sector(i);
                        } else {
                            f.abort_erase(i, d.permille);
                        }
                    });
                    None
                } else {
                    let len = flash::sector_kib(sector) * 1024;
                    self.code_erases += 1;
                    Some(CodeEffect::Erased {
                        addr: flash::sector_base(sector),
                        len: len * d.permille.min(1000) / 1000,
                    })
                }
            }
            Op::MassErase => {
                self.world.flash.with(|f| {
                    let _ = f.erase_sector(0);
                    let _ = f.erase_sector(1);
                });
                Some(CodeEffect::Erased {
                    addr: flash::FLASH_BASE,
                    len: ODOMETER_BASE - flash::FLASH_BASE,
                })
            }
            Op::Options { .. } => None,
        }
    }

    /// A CPU read from the odometer sectors.
    pub fn odometer_read(&mut self, off: u32, size: usize) -> (u32, Option<Done>) {
        let done = if self.flash.busy_until().is_some() {
            self.stall_for_flash()
        } else {
            None
        };
        let mut b = [0u8; 4];
        let n = size.min(4);
        if self.art_timing {
            // Through the data cache: a hit returns the line as it was cached (stale if
            // its sector was erased since), a miss reads the array's line.
            let acr = self.flash.acr();
            let base = ODOMETER_BASE - flash::FLASH_BASE;
            let mut mc = 0;
            let mut i = 0;
            while i < n {
                let at = off + i as u32;
                let line_off = at & !(LINE_BYTES - 1);
                let world = &self.world;
                let (d, w) = self
                    .flash
                    .art
                    .read_line(acr, (base + line_off) / LINE_BYTES, || {
                        let mut l = [0xFFu8; 16];
                        world
                            .flash
                            .with(|f| {
                                embedded_storage::nor_flash::ReadNorFlash::read(f, line_off, &mut l)
                            })
                            .ok()
                            .map(|_| l)
                    });
                mc += w;
                let Some(d) = d else {
                    self.diag(format!("odometer flash read at {off:#x} failed"));
                    break;
                };
                while i < n && (off + i as u32) & !(LINE_BYTES - 1) == line_off {
                    b[i] = d[((off + i as u32) % LINE_BYTES) as usize];
                    i += 1;
                }
            }
            self.wait_states(mc);
            return (u32::from_le_bytes(b), done);
        }
        let ok = self
            .world
            .flash
            .with(|f| embedded_storage::nor_flash::ReadNorFlash::read(f, off, &mut b[..n]));
        if ok.is_err() {
            self.diag(format!("odometer flash read at {off:#x} failed"));
        }
        (u32::from_le_bytes(b), done)
    }

    /// A CPU store to the code sectors (0-9; a bootloader's program, if the interface
    /// allows it). The engine's own store into its memory is undone by the board
    /// (`cpu.rs`, `code_restore`): the array changes only when the program ends.
    pub fn code_write(&mut self, addr: u32, size: usize, value: u32) -> Option<Done> {
        let done = if self.flash.busy_until().is_some() {
            self.stall_for_flash()
        } else {
            None
        };
        let now = self.now();
        let pending_before = self.nvic.pending_enabled();
        self.flash.store(addr, size, value as u64, now);
        self.after_access(pending_before);
        done
    }

    /// A CPU store to the odometer sectors (a program, if the interface allows it).
    pub fn odometer_write(&mut self, off: u32, size: usize, value: u32) -> Option<Done> {
        let done = if self.flash.busy_until().is_some() {
            self.stall_for_flash()
        } else {
            None
        };
        let now = self.now();
        let pending_before = self.nvic.pending_enabled();
        self.flash
            .store(ODOMETER_BASE + off, size, value as u64, now);
        self.after_access(pending_before);
        done
    }
}

#[cfg(test)]
mod art_tests {
    use super::*;
    use crate::periph::art::acr;
    use hil_sim::flash::{SharedFlash, SimFlash};
    use hil_sim::rig::{Machine, RigOptions};

    const ACR: u32 = 0x4002_3C00;
    const ON: u32 = 5 | acr::PRFTEN | acr::ICEN | acr::DCEN;

    fn soc_with_record() -> Soc {
        let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
        flash.with(|f| f.program(0, &[0x42; 16])).unwrap();
        let world = World::new(Machine::new(&RigOptions::new(80)), flash);
        let mut soc = Soc::new(world, 1_000, 32_000, FlashTiming::Typical);
        soc.art_timing = true;
        soc.bus_write(ACR, 4, ON);
        soc
    }

    /// The board's wiring of the model: FLASH_ACR writes, the erase, odometer reads.
    #[test]
    fn an_odometer_line_read_before_its_erase_reads_stale_until_the_firmware_flushes() {
        let mut soc = soc_with_record();
        let c0 = soc.clock.cycles();
        assert_eq!(soc.odometer_read(0, 4).0, 0x4242_4242);
        assert_eq!(soc.clock.cycles() - c0, 5, "a miss: 5 wait states");
        assert_eq!(soc.odometer_read(4, 4).0, 0x4242_4242);
        assert_eq!(soc.clock.cycles() - c0, 5, "the same line: a hit");
        soc.apply_flash(Done {
            op: Op::Erase { sector: 10 },
            permille: 1000,
        });
        let mut array = [0u8; 4];
        soc.world
            .flash
            .with(|f| embedded_storage::nor_flash::ReadNorFlash::read(f, 0, &mut array))
            .unwrap();
        assert_eq!(array, [0xFF; 4], "the array is erased");
        assert_eq!(soc.odometer_read(0, 4).0, 0x4242_4242, "the cache is not");
        // A reset written with the caches on is ignored (RM0090: only while disabled).
        soc.bus_write(ACR, 4, ON | acr::ICRST | acr::DCRST);
        assert_eq!(soc.odometer_read(0, 4).0, 0x4242_4242);
        assert_eq!(soc.flash.art.erases_unflushed(), 1);
        // The firmware's flush: disable, reset, release, enable again.
        let off = ON & !(acr::ICEN | acr::DCEN);
        for v in [off, off | acr::ICRST | acr::DCRST, off, ON] {
            soc.bus_write(ACR, 4, v);
        }
        assert_eq!(soc.odometer_read(0, 4).0, 0xFFFF_FFFF);
        assert_eq!(soc.flash.art.erases_unflushed(), 0);
        assert_eq!(soc.flash.art.stats.stale_hits, 2);
    }

    #[test]
    fn under_fixed_cpi_timing_the_odometer_reads_the_array() {
        let mut soc = soc_with_record();
        soc.art_timing = false;
        let c0 = soc.clock.cycles();
        assert_eq!(soc.odometer_read(0, 4).0, 0x4242_4242);
        soc.apply_flash(Done {
            op: Op::Erase { sector: 10 },
            permille: 1000,
        });
        assert_eq!(soc.odometer_read(0, 4).0, 0xFFFF_FFFF);
        assert_eq!(soc.clock.cycles(), c0, "no wait states");
    }
}
