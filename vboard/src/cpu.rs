//! The Cortex-M4 core on the unicorn engine, and what unicorn does not do for a
//! Cortex-M: time, exception entry and return, sleep, lockup, reset.
//!
//! * The engine is opened `THUMB` with the CPU model set to Cortex-M4 (opening it
//!   `THUMB | MCLASS` makes a Cortex-M33 whatever the model says).
//! * **Time**: a block hook counts each translated block's instructions (decoded once,
//!   cached) into the clock and stops the engine when the next event is due, when an
//!   interrupt that was masked may now be taken, or when a fetch from flash must wait
//!   for a flash operation. Interrupts are therefore taken at block boundaries.
//!   Peripheral callbacks never stop the engine themselves (a stop inside an access
//!   makes unicorn execute the instruction again on restart); they raise a flag that
//!   the next block hook acts on.
//! * **Exception entry** (`enter`): the 8-word frame (26 words with the FP context when
//!   `CONTROL.FPCA` is set) is stacked on the current stack with the 8-byte alignment
//!   bit, `LR` = EXC_RETURN, `IPSR` and `PC` = the vector from `VTOR`; the engine's
//!   cached mode flags are rebuilt afterwards (a write to a coprocessor register does
//!   that in unicorn 2.1).
//! * **Exception return**: the engine reports a branch to EXC_RETURN in handler mode as
//!   interrupt 8; the hook tail-chains to a pending exception that may preempt the
//!   context being returned to, or unstacks.
//! * **Faults**: an undefined instruction, a `bkpt` without a debugger, an access to
//!   unmapped (reserved) memory are faults, escalated to HardFault (the image enables
//!   no configurable fault); a fault in HardFault is a **lockup**: the core stops, and
//!   only a reset (the watchdog's, for instance) restarts it.
//! * **Sleep**: `wfi` ends the engine's run; the board jumps time to the next event that
//!   wakes the core.
//! * **Reset**: peripherals to reset values (RCC keeps the reset flags), SRAM kept,
//!   `SP` and `PC` from the vector table.

use unicorn_engine::{
    Arch, ArmCpuModel, HookType, MemType, Mode, Prot, RegisterARM, TlbType, Unicorn,
};

use crate::hostmem::HostMem;
use crate::image::Image;
use crate::periph::flash::{FlashTiming, FLASH_BASE, ODOMETER_BASE};
use crate::periph::nvic::{exc, Masks};
use crate::periph::rcc::ResetCause;
use crate::rtt::{LogLine, Rtt, POLL_PS};
use crate::soc::{CodeEffect, MaskPending, MaskSite, Soc, ICACHE_FLASH};
use crate::world::World;

/// How executing costs time.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum Timing {
    /// Every instruction costs `cpi_milli`, wherever it runs from.
    #[default]
    Cpi,
    /// Every instruction costs `cpi_milli`, plus the flash wait states (`FLASH_ACR`
    /// `LATENCY`) of each instruction fetch and data read of flash that the ART
    /// accelerator's caches and prefetch buffer do not serve ([`crate::periph::art`]);
    /// a cache line left stale by an erase returns its old bytes until the caches are
    /// reset.
    Art,
}

impl Timing {
    /// The name the command line uses.
    pub fn name(self) -> &'static str {
        match self {
            Self::Cpi => "cpi",
            Self::Art => "art",
        }
    }
}

/// Board configuration.
#[derive(Clone, Copy, Debug)]
pub struct BoardConfig {
    /// Core cycles per instruction, thousandths (1000 = 1.0); under [`Timing::Art`] the
    /// cost of an instruction before flash wait states.
    pub cpi_milli: u64,
    /// Timing model.
    pub timing: Timing,
    /// LSI frequency (clocks the IWDG), Hz: 17 000–47 000 on real parts.
    pub lsi_hz: u64,
    /// Flash program/erase timing.
    pub flash_timing: FlashTiming,
    /// Skip polling loops ([`crate::loops`]; `--no-skip`: every iteration runs).
    pub skip: bool,
    /// Take interrupts and sleep inside the engine's run (`in_run`), not by stopping it
    /// for the run loop: the same results, faster (`vboard/tests/skip.rs` compares).
    pub in_run: bool,
}

impl Default for BoardConfig {
    fn default() -> Self {
        Self {
            cpi_milli: 1_000,
            timing: Timing::Cpi,
            lsi_hz: 32_000,
            flash_timing: FlashTiming::Max,
            skip: true,
            in_run: true,
        }
    }
}

pub(crate) const SRAM: u32 = 0x2000_0000;
pub(crate) const SRAM_SIZE: u32 = 128 * 1024;
/// The engine's page (ARM: 1 KiB), the unit SRAM is made executable in.
const SRAM_PAGE: u32 = crate::tlb::PAGE;
/// R0–R12.
const GP_REGS: [RegisterARM; 13] = [
    RegisterARM::R0,
    RegisterARM::R1,
    RegisterARM::R2,
    RegisterARM::R3,
    RegisterARM::R4,
    RegisterARM::R5,
    RegisterARM::R6,
    RegisterARM::R7,
    RegisterARM::R8,
    RegisterARM::R9,
    RegisterARM::R10,
    RegisterARM::R11,
    RegisterARM::R12,
];
const CODE_LEN: u32 = ODOMETER_BASE - FLASH_BASE;
const WFI: u16 = 0xBF30;

/// FNV-1a, 64 bits.
struct Fnv(u64);

impl Default for Fnv {
    fn default() -> Self {
        Self(0xCBF2_9CE4_8422_2325)
    }
}

impl Fnv {
    fn bytes(&mut self, b: &[u8]) {
        for &x in b {
            self.0 = (self.0 ^ u64::from(x)).wrapping_mul(0x0100_0000_01B3);
        }
    }

    fn u64(&mut self, x: u64) {
        self.bytes(&x.to_le_bytes());
    }
}

/// Why a run stopped before its end time.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Halt {
    /// An access to a peripheral register the board does not model.
    Unmodelled {
        /// Address.
        addr: u32,
        /// Write or read.
        write: bool,
        /// Program counter.
        pc: u32,
    },
    /// The emulator failed in a way that is not a fault of the image.
    Engine(String),
}

impl std::fmt::Display for Halt {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Unmodelled { addr, write, pc } => write!(
                f,
                "unmodelled peripheral {} at {addr:#010x} (pc {pc:#010x})",
                if *write { "write" } else { "read" }
            ),
            Self::Engine(e) => write!(f, "emulator: {e}"),
        }
    }
}

/// A fault the core took, for reports.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CoreFault {
    /// Virtual time, ps.
    pub t_ps: u64,
    /// What.
    pub what: String,
    /// Where (pc).
    pub pc: u32,
    /// The function there, if the image's symbols tell.
    pub function: Option<String>,
}

/// The board: core, SoC, image.
pub struct Board {
    uc: Unicorn<'static, Soc>,
    /// The image running.
    pub image: Image,
    rtt: Option<Rtt>,
    /// A probe reads the RTT buffer (a detached probe reads nothing: the buffer fills).
    probe_attached: bool,
    /// The defmt log, decoded.
    pub log: Vec<LogLine>,
    next_rtt_ps: u64,
    /// SRAM's 1 KiB pages granted EXEC so far, bit n for page n (`grant_sram_exec`).
    sram_exec: u128,
    sleeping: bool,
    /// Resets so far, with their time, ps (the power-on included).
    pub resets: Vec<(u64, ResetCause)>,
    /// The emulation's speed against the wall clock, window by window.
    pub speed: crate::time::SpeedMeter,
}

fn reg(uc: &Unicorn<'_, Soc>, r: RegisterARM) -> u32 {
    uc.reg_read(r).unwrap_or(0) as u32
}

fn set(uc: &mut Unicorn<'_, Soc>, r: RegisterARM, v: u32) {
    let _ = uc.reg_write(r, v as u64);
}

/// Rebuild the engine's cached mode flags after a change of IPSR/CONTROL from outside.
/// A write of the flags does that in unicorn 2.1 (`APSR_NZCV`: `arm_rebuild_hflags`);
/// the flags are written back as they are. (A failing coprocessor-register write did it
/// too, but each failure costs the engine a `getenv` for its warning: 1 % of a run.)
fn rebuild_hflags(uc: &mut Unicorn<'_, Soc>) {
    let nzcv = uc.reg_read(RegisterARM::APSR_NZCV).unwrap_or(0);
    let _ = uc.reg_write(RegisterARM::APSR_NZCV, nzcv);
}

fn masks(uc: &Unicorn<'_, Soc>) -> Masks {
    let [primask, faultmask, basepri] = crate::regs::read(
        uc,
        [
            RegisterARM::PRIMASK,
            RegisterARM::FAULTMASK,
            RegisterARM::BASEPRI,
        ],
    );
    Masks {
        primask: primask & 1 != 0,
        faultmask: faultmask & 1 != 0,
        basepri: basepri as u8,
    }
}

fn read_u32(uc: &Unicorn<'_, Soc>, addr: u32) -> Option<u32> {
    let mut b = [0u8; 4];
    uc.mem_read(addr as u64, &mut b).ok()?;
    Some(u32::from_le_bytes(b))
}

/// A vector (`addr` in the table VTOR points to): from the code sectors' array itself
/// where the table is in flash (at every exception entry: without a walk of the
/// engine's memory map), else as any read.
fn read_vector(uc: &Unicorn<'_, Soc>, addr: u32) -> Option<u32> {
    let off = if addr < CODE_LEN {
        Some(addr)
    } else {
        addr.checked_sub(FLASH_BASE).filter(|&o| o < CODE_LEN)
    };
    if let (Some(off), Some(c)) = (off, uc.get_data().code_mem.as_ref()) {
        let mut b = [0u8; 4];
        if c.read(off as usize, &mut b) {
            return Some(u32::from_le_bytes(b));
        }
    }
    read_u32(uc, addr)
}

/// An exception frame's bytes at `addr` (`buf.len()` of them): from SRAM's array where
/// they are all in it, else through the engine. False if the engine refuses.
fn frame_read(uc: &Unicorn<'_, Soc>, addr: u32, buf: &mut [u8]) -> bool {
    if let (Some(off), Some(m)) = (addr.checked_sub(SRAM), uc.get_data().sram_mem.as_ref()) {
        if m.read(off as usize, buf) {
            return true;
        }
    }
    uc.mem_read(u64::from(addr), buf).is_ok()
}

/// Stack `bytes` at `addr`: into SRAM's array where they all fit in it and no page of
/// them holds code (a store there must go through the engine, which drops the
/// translations it overwrites), else through the engine. False if the engine refuses.
fn frame_write(uc: &mut Unicorn<'_, Soc>, addr: u32, bytes: &[u8]) -> bool {
    let end = addr.wrapping_add(bytes.len().max(1) as u32 - 1);
    let inside = addr >= SRAM && end >= addr && end < SRAM + SRAM_SIZE;
    if inside && !crate::tlb::executable(addr) && !crate::tlb::executable(end) {
        if let Some(m) = uc.get_data_mut().sram_mem.as_mut() {
            m.write((addr - SRAM) as usize, bytes);
            return true;
        }
    }
    uc.mem_write(u64::from(addr), bytes).is_ok()
}

/// The Thumb instructions in `bytes`: each one's offset and first halfword (a 32-bit
/// instruction starts with 0b11101, 0b11110 or 0b11111).
fn thumb_insns(bytes: &[u8]) -> impl Iterator<Item = (usize, u16)> + '_ {
    let mut i = 0;
    std::iter::from_fn(move || {
        let hw = u16::from_le_bytes([*bytes.get(i)?, *bytes.get(i + 1)?]);
        let at = i;
        i += if wide(hw) { 4 } else { 2 };
        Some((at, hw))
    })
}

/// Whether `hw` starts a 32-bit Thumb instruction.
fn wide(hw: u16) -> bool {
    hw >> 11 >= 0b11101
}

/// The instructions in `bytes` of Thumb code, and whether one of them may write
/// PRIMASK, FAULTMASK or BASEPRI: a CPS (`1011 0110 011x 0xxx`) or an MSR
/// (`1111 0011 1000 nnnn`, any special register: a superset, never a miss).
fn scan_insns(bytes: &[u8]) -> (u32, bool) {
    thumb_insns(bytes).fold((0, false), |(n, masks), (_, hw)| {
        let writes = if wide(hw) {
            hw & 0xFFF0 == 0xF380
        } else {
            hw & 0xFFE8 == 0xB660
        };
        (n + 1, masks || writes)
    })
}

/// An icache entry: bits 0–11 the block's instructions, 12–24 its size in bytes (a
/// block is at most 512 instructions), 25–26 its masking site, and flags. The flag of a
/// block that may write a mask register ([`scan_insns`]):
const ICACHE_MASKS: u32 = 1 << 31;
/// The block's masking site was looked up (`note_mask_site`); bits 25–26 then say what
/// it ends with: 0 no site, 1 `cpsid i`, 2 `cpsie i`, 3 `msr primask`.
const ICACHE_SITE_CHECKED: u32 = 1 << 30;
/// The size's bits.
const ICACHE_SIZE: u32 = ((1 << 13) - 1) << 12;
/// The site's bits.
const ICACHE_SITE_SHIFT: u32 = 25;

fn icache_index(addr: u64) -> Option<usize> {
    let a = addr as u32;
    if (FLASH_BASE..FLASH_BASE + CODE_LEN).contains(&a) {
        Some(((a - FLASH_BASE) / 2) as usize)
    } else if (SRAM..SRAM + SRAM_SIZE).contains(&a) {
        Some(ICACHE_FLASH + ((a - SRAM) / 2) as usize)
    } else {
        None
    }
}

/// The instructions of the block at `addr` (`size` bytes), and whether it may write a
/// mask register (the block hook's pending-interrupt check is then due at the next block).
#[inline]
fn block_insns(uc: &mut Unicorn<'_, Soc>, addr: u64, size: u32) -> (u64, bool) {
    let idx = icache_index(addr);
    if let Some(i) = idx {
        let c = uc.get_data().icache[i];
        if c != 0 && (c & ICACHE_SIZE) >> 12 == size {
            return ((c & 0xFFF) as u64, c & ICACHE_MASKS != 0);
        }
    }
    let mut buf = vec![0u8; size as usize];
    let (n, masks) = if uc.mem_read(addr, &mut buf).is_ok() {
        scan_insns(&buf)
    } else {
        (size / 2, true)
    };
    if let Some(i) = idx {
        if size < (1 << 13) && n < 0x1000 {
            uc.get_data_mut().icache[i] = (size << 12) | n | if masks { ICACHE_MASKS } else { 0 };
        }
    }
    (n as u64, masks)
}

impl Board {
    /// A board with `image` loaded into flash and `world` outside it, powered off.
    pub fn new(image: Image, world: World, cfg: BoardConfig) -> Result<Self, String> {
        // The hflags rebuild (below) goes through a coprocessor-register write that an M
        // profile does not have; unicorn 2.1 warns about it on stderr unless told not to.
        static QUIET: std::sync::Once = std::sync::Once::new();
        QUIET.call_once(|| {
            if std::env::var_os("UC_IGNORE_REG_BREAK").is_none() {
                std::env::set_var("UC_IGNORE_REG_BREAK", "1");
            }
        });
        let mut soc = Soc::new(world, cfg.cpi_milli, cfg.lsi_hz, cfg.flash_timing);
        let art = cfg.timing == Timing::Art;
        soc.art_timing = art;
        soc.loops.enabled = cfg.skip;
        soc.in_run = cfg.in_run;
        let e = |w: &str, err: unicorn_engine::uc_error| format!("unicorn {w}: {err:?}");
        let mut uc =
            Unicorn::new_with_data(Arch::ARM, Mode::THUMB, soc).map_err(|x| e("open", x))?;
        uc.ctl_set_cpu_model(ArmCpuModel::CORTEX_M4 as i32)
            .map_err(|x| e("cpu model", x))?;
        // The engine's TLB filled by the board (src/tlb.rs: data pages without execute,
        // but those code runs from, so that stores to SRAM stay on the fast path).
        if uc.ctl_get_page_size().map_err(|x| e("page size", x))? != crate::tlb::PAGE {
            return Err("unicorn: the engine's page is not 1 KiB (src/tlb.rs)".into());
        }
        uc.ctl_set_tlb_type(TlbType::VIRTUAL)
            .map_err(|x| e("tlb type", x))?;
        // Flash: the boot alias at 0 and the code sectors, read/execute only, both over
        // the one array of bytes the board owns (`HostMem`).
        let mut code = HostMem::new(CODE_LEN as usize, 0xFF);
        code.write(0, &image.flash);
        for base in [0u64, FLASH_BASE as u64] {
            code.map(&mut uc, base, Prot::READ | Prot::EXEC)
                .map_err(|x| e("map flash", x))?;
        }
        uc.get_data_mut().code_mem = Some(code);
        // The odometer sectors go through the flash interface model.
        uc.mmio_map(
            ODOMETER_BASE as u64,
            (flash_len() - CODE_LEN) as u64,
            Some(|uc: &mut Unicorn<'_, Soc>, off: u64, size: usize| -> u64 {
                let (v, done) = uc.get_data_mut().odometer_read(off as u32, size);
                if let Some(d) = done {
                    apply_done(uc, d);
                }
                v as u64
            }),
            Some(|uc: &mut Unicorn<'_, Soc>, off: u64, size: usize, v: u64| {
                if let Some(d) = uc.get_data_mut().odometer_write(off as u32, size, v as u32) {
                    apply_done(uc, d);
                }
            }),
        )
        .map_err(|x| e("map odometer", x))?;
        // CCM RAM (data only), system memory with the unique ID and flash size, option
        // bytes, SRAM.
        uc.mem_map(0x1000_0000, 0x1_0000, Prot::READ | Prot::WRITE)
            .map_err(|x| e("map ccm", x))?;
        uc.mem_map(0x1FFF_0000, 0x8000, Prot::READ)
            .map_err(|x| e("map system memory", x))?;
        let uid: [u8; 12] = [
            0x33, 0x00, 0x2F, 0x00, 0x0A, 0x51, 0x35, 0x31, 0x38, 0x33, 0x36, 0x37,
        ];
        uc.mem_write(0x1FFF_7A10, &uid).map_err(|x| e("uid", x))?;
        uc.mem_write(0x1FFF_7A22, &1024u16.to_le_bytes())
            .map_err(|x| e("flash size", x))?;
        uc.mem_map(0x1FFF_C000, 0x1000, Prot::READ)
            .map_err(|x| e("map option bytes", x))?;
        // SRAM: read/write; a page becomes executable at its first instruction fetch
        // (`run`: the engine stops with FETCH_PROT there, the page is granted EXEC and the
        // run goes on, nothing executed twice). The silicon executes from any SRAM byte;
        // the engine, though, sends every store to an executable page through its slow
        // path (unicorn 2.1.5, cputlb.c `notdirty_write`: a TLB entry with a code address
        // is never marked dirty), so mapping all of SRAM executable cost about a third of
        // the engine's time in stack and `.bss` stores. Only the pages the RAM functions
        // occupy (flash.rs, options.rs, modbus.rs) pay it now.
        // Over the board's own array: exception frames go there directly (`hostmem.rs`).
        let mut sram = HostMem::new(SRAM_SIZE as usize, 0);
        sram.map(&mut uc, SRAM as u64, Prot::READ | Prot::WRITE)
            .map_err(|x| e("map sram", x))?;
        uc.get_data_mut().sram_mem = Some(sram);
        // SRAM bit-band alias (0x2200_0000: 32 bytes per SRAM byte).
        uc.mmio_map(
            0x2200_0000,
            (SRAM_SIZE * 32) as u64,
            Some(|uc: &mut Unicorn<'_, Soc>, off: u64, _size: usize| -> u64 {
                let (addr, bit) = bitband(SRAM, off as u32);
                let mut b = [0u8; 4];
                let _ = uc.mem_read(addr as u64, &mut b);
                ((u32::from_le_bytes(b) >> bit) & 1) as u64
            }),
            Some(
                |uc: &mut Unicorn<'_, Soc>, off: u64, _size: usize, v: u64| {
                    let (addr, bit) = bitband(SRAM, off as u32);
                    let mut b = [0u8; 4];
                    let _ = uc.mem_read(addr as u64, &mut b);
                    let w = u32::from_le_bytes(b) & !(1 << bit) | (((v & 1) as u32) << bit);
                    let _ = uc.mem_write(addr as u64, &w.to_le_bytes());
                },
            ),
        )
        .map_err(|x| e("map sram bit-band", x))?;
        // Peripherals: APB1, APB2, AHB1; their bit-band alias; AHB2 (nothing modelled).
        for (base, size) in [(0x4000_0000u64, 0x8_0000u64), (0x5000_0000, 0x6_1000)] {
            uc.mmio_map(
                base,
                size,
                Some(
                    move |uc: &mut Unicorn<'_, Soc>, off: u64, size: usize| -> u64 {
                        let s = uc.get_data_mut();
                        let v = s.bus_read((base + off) as u32, size);
                        if let Some(d) = s.flash.take_done() {
                            apply_done(uc, d);
                        }
                        store_dma(uc);
                        v as u64
                    },
                ),
                Some(
                    move |uc: &mut Unicorn<'_, Soc>, off: u64, size: usize, v: u64| {
                        let s = uc.get_data_mut();
                        s.bus_write((base + off) as u32, size, v as u32);
                        store_dma(uc);
                    },
                ),
            )
            .map_err(|x| e("map peripherals", x))?;
        }
        uc.mmio_map(
            0x4200_0000,
            0x8_0000 * 32,
            Some(|uc: &mut Unicorn<'_, Soc>, off: u64, _size: usize| -> u64 {
                let (addr, bit) = bitband(0x4000_0000, off as u32);
                let s = uc.get_data_mut();
                let v = (s.bus_read(addr, 4) >> bit) & 1;
                store_dma(uc);
                v as u64
            }),
            Some(
                |uc: &mut Unicorn<'_, Soc>, off: u64, _size: usize, v: u64| {
                    let (addr, bit) = bitband(0x4000_0000, off as u32);
                    let s = uc.get_data_mut();
                    let w = s.bus_read(addr, 4) & !(1 << bit) | (((v & 1) as u32) << bit);
                    s.bus_write(addr, 4, w);
                    store_dma(uc);
                },
            ),
        )
        .map_err(|x| e("map peripheral bit-band", x))?;
        uc.mmio_map(
            0xE000_0000,
            0x10_0000,
            Some(|uc: &mut Unicorn<'_, Soc>, off: u64, size: usize| -> u64 {
                let s = uc.get_data_mut();
                let v = s.ppb_read(0xE000_0000 + off as u32, size);
                v as u64
            }),
            Some(|uc: &mut Unicorn<'_, Soc>, off: u64, size: usize, v: u64| {
                let s = uc.get_data_mut();
                s.ppb_write(0xE000_0000 + off as u32, size, v as u32);
            }),
        )
        .map_err(|x| e("map private peripheral bus", x))?;

        // Time, stalls, events: at every block. A block whose hook stops the engine is
        // not executed (unicorn stops before it and runs it again on restart), so it is
        // counted only when it runs: the stop decision comes first.
        uc.add_block_hook(1, 0, |uc: &mut Unicorn<'_, Soc>, addr: u64, size: u32| {
            restore_code(uc);
            // The block before ran to its end: a masking site it ended with takes effect.
            finish_mask_site(uc);
            let s = uc.get_data();
            let mut stop = s.stop || s.clock.mc() >= s.next_event_mc;
            // An interrupt pending but masked: is it taken now? The answer changes only
            // with the NVIC (a register access, which counts in `io_seq`; an event, which
            // ends the run; an exception entry or return) or with a mask register (an
            // instruction of the block before: `block_insns`' flag); until then the last
            // answer stands, without its register reads (8 % of a run at rest).
            if !stop && s.irq_waiting && s.masks_settled != Some(s.io_seq) {
                // With PRIMASK set nothing but an NMI (none wired) can be taken: one
                // register read instead of three while code runs with interrupts masked.
                let mut take = None;
                if reg(uc, RegisterARM::PRIMASK) & 1 == 0 {
                    let m = masks(uc);
                    take = uc.get_data().nvic.to_take(m).map(|_| m);
                }
                if let Some(m) = take {
                    if uc.get_data().in_run && in_run(uc, addr as u32, false, m) == InRun::Goes {
                        // Entered: the block did not run; the engine goes on at the vector.
                        return;
                    }
                    stop = true;
                } else {
                    let s = uc.get_data_mut();
                    s.masks_settled = Some(s.io_seq);
                }
            }
            if stop {
                uc.get_data_mut().stop = true;
                let _ = uc.emu_stop();
                return;
            }
            let a = addr as u32;
            let in_flash = a.wrapping_sub(FLASH_BASE) < CODE_LEN || a < CODE_LEN;
            if in_flash && uc.get_data().flash.busy_until().is_some() {
                // The fetch waits for the flash operation, or for the next event if that
                // comes first (a watchdog reset cuts the operation short).
                let s = uc.get_data_mut();
                let end = s.flash.busy_until().unwrap_or(0);
                if s.next_event_ps < end {
                    let t = s.next_event_ps;
                    s.stall_to(t);
                    s.stop = true;
                    let _ = uc.emu_stop();
                    return;
                }
                if let Some(d) = s.stall_for_flash() {
                    apply_done(uc, d);
                    uc.get_data_mut().masks_settled = None;
                }
            }
            let (n, writes_masks) = block_insns(uc, addr, size);
            if writes_masks {
                uc.get_data_mut().masks_settled = None;
            }
            if uc.get_data().loops.enabled && crate::loops::on_block(uc, a, size, n) {
                return;
            }
            if uc.get_data().meter.is_some() {
                meter_block(uc, addr as u32);
            }
            let s = uc.get_data_mut();
            if in_flash && s.art_timing {
                let (acr, mc, cpi) = (s.flash.acr(), s.clock.mc(), s.clock.cpi_milli());
                let w = s.flash.art.fetch_block(acr, a, size, n, mc, cpi);
                s.wait_states(w);
            }
            s.block_at = (addr as u32, s.clock.mc());
            s.clock.execute(n);
            if let Some(c) = s.exc_insns.get_mut(s.current_exc) {
                *c += n;
            }
            if let Some(c) = s.exc_mc.get_mut(s.current_exc) {
                *c += n * s.clock.cpi_milli();
            }
            if writes_masks && !s.mask_sites.is_empty() {
                note_mask_site(uc, a, size, n);
            }
        })
        .map_err(|x| e("block hook", x))?;
        // `wfi`: the core sleeps, and wakes, inside the run (`in_run`), where the engine
        // would stop for the run loop to do the same: at 20 kHz while the axis moves.
        if cfg.in_run {
            let used = (image.flash_used as usize).min(image.flash.len());
            hook_wfi_sites(&mut uc, 0, used).map_err(|x| e("wfi hook", x))?;
        }
        uc.add_intr_hook(|uc: &mut Unicorn<'_, Soc>, intno: u32| {
            on_interrupt(uc, intno);
        })
        .map_err(|x| e("intr hook", x))?;
        uc.add_insn_invalid_hook(|uc: &mut Unicorn<'_, Soc>| {
            // Undefined instruction (`udf`, a panic's end): UsageFault → HardFault.
            let pc = reg(uc, RegisterARM::PC);
            fault(uc, exc::USAGE_FAULT, 1 << 16, pc, "undefined instruction");
            true
        })
        .map_err(|x| e("invalid-insn hook", x))?;
        // Every address but SRAM's and the code sectors': any memory hook over an
        // address keeps the engine's stores to it on the slow path (cputlb.c
        // `uc_mem_hook_installed`), and SRAM is mapped whole, so nothing there is invalid
        // but a fetch (`run` grants it). A store to the code sectors is the flash
        // interface's (the hook below): this hook ran first and left a fault behind for
        // the next engine error to report (a bus fault at a flash program's address
        // when the first fetch from an SRAM page stopped the run after a frame-log write).
        let code = |base: u32| (base as u64, (base + CODE_LEN) as u64);
        let (alias, flash) = (code(0), code(FLASH_BASE));
        for (lo, hi) in [
            (alias.1, FLASH_BASE as u64 - 1),
            (flash.1, SRAM as u64 - 1),
            ((SRAM + SRAM_SIZE) as u64, u32::MAX as u64),
        ] {
            uc.add_mem_hook(
                HookType::MEM_INVALID,
                lo,
                hi,
                |uc: &mut Unicorn<'_, Soc>, t: MemType, addr: u64, _size: usize, _v: i64| {
                    uc.get_data_mut().mem_fault = Some((addr as u32, t));
                    false
                },
            )
            .map_err(|x| e("memory hook", x))?;
        }
        // A store to the code sectors (a bootloader's flash program): the region is
        // read-only to the engine, so the store comes here first; it goes to the flash
        // interface, and the engine's raw store that follows is undone before anything
        // runs on (the array changes only when the program ends, `apply_done`).
        for base in [0u64, FLASH_BASE as u64] {
            uc.add_mem_hook(
                HookType::MEM_WRITE_PROT,
                base,
                base + CODE_LEN as u64 - 1,
                |uc: &mut Unicorn<'_, Soc>, _t: MemType, addr: u64, size: usize, v: i64| {
                    let a = if addr < CODE_LEN as u64 {
                        addr as u32 + FLASH_BASE
                    } else {
                        addr as u32
                    };
                    let mut old = vec![0u8; size];
                    let _ = uc.mem_read(addr, &mut old);
                    uc.get_data_mut().masks_settled = None;
                    if let Some(d) = uc.get_data_mut().code_write(a, size, v as u32) {
                        apply_done(uc, d);
                        let _ = uc.mem_read(addr, &mut old);
                    }
                    uc.get_data_mut().code_restore.push((addr as u32, old));
                    true
                },
            )
            .map_err(|x| e("flash store hook", x))?;
        }

        if art {
            // Data reads of the code sectors (literal pools, constants, `.data`'s load
            // image) through the data cache. (Any memory hook sends every load and store
            // of the engine through its slow path: installed only for this model.)
            for base in [0u64, FLASH_BASE as u64] {
                uc.add_mem_hook(
                    HookType::MEM_READ,
                    base,
                    base + CODE_LEN as u64 - 1,
                    |uc: &mut Unicorn<'_, Soc>, _t: MemType, addr: u64, size: usize, _v: i64| {
                        uc.get_data_mut().art_code_read(addr as u32, size);
                        true
                    },
                )
                .map_err(|x| e("flash read hook", x))?;
            }
        }

        let rtt = match image.rtt {
            Some(cb) => Rtt::new(&image.elf, cb)?,
            None => None,
        };
        Ok(Self {
            uc,
            image,
            rtt,
            probe_attached: true,
            log: Vec::new(),
            next_rtt_ps: 0,
            sram_exec: 0,
            sleeping: false,
            resets: Vec::new(),
            speed: Default::default(),
        })
    }
}

fn flash_len() -> u32 {
    crate::periph::flash::FLASH_SIZE
}

/// The word address and bit of a bit-band alias offset over `region`.
fn bitband(region: u32, off: u32) -> (u32, u32) {
    let byte = off / 32;
    let bit = (off % 32) / 4;
    let addr = region + (byte & !3);
    (addr, (byte & 3) * 8 + bit)
}

/// Store in SRAM the bytes the DMA moved (the models run without the engine's memory),
/// before the core reads anything that says they are there (NDTR, a flag).
fn store_dma(uc: &mut Unicorn<'_, Soc>) {
    if !uc.get_data().dma1.has_writes() {
        return;
    }
    let writes = uc.get_data_mut().take_dma_writes();
    let mut i = 0;
    while i < writes.len() {
        // Runs of consecutive addresses in one write.
        let (start, _) = writes[i];
        let mut run = vec![writes[i].1];
        while let Some(&(a, b)) = writes.get(i + run.len()) {
            if a != start + run.len() as u32 {
                break;
            }
            run.push(b);
        }
        i += run.len();
        let _ = uc.mem_write(start as u64, &run);
    }
}

/// Apply a finished flash operation; erased code sectors are erased in emulator memory
/// too (the image would be destroyed, as on the part).
fn apply_done(uc: &mut Unicorn<'_, Soc>, d: crate::periph::flash::Done) {
    restore_code(uc);
    match uc.get_data_mut().apply_flash(d) {
        Some(CodeEffect::Erased { addr, len }) => {
            let ff = vec![0xFFu8; len as usize];
            code_changed(uc, addr, &ff);
        }
        Some(CodeEffect::Programmed { addr, n, value }) => {
            let mut now = vec![0u8; n];
            if uc.mem_read(addr as u64, &mut now).is_ok() {
                for (b, v) in now.iter_mut().zip(value.to_le_bytes()) {
                    *b &= v;
                }
                code_changed(uc, addr, &now);
            }
        }
        None => {}
    }
}

/// Store `bytes` at `addr` in the code sectors (either mapping: both are the one array),
/// as the board, not as the core; `false` when `addr` is not in them.
fn write_code(uc: &mut Unicorn<'_, Soc>, addr: u32, bytes: &[u8]) -> bool {
    let off = if addr < CODE_LEN {
        addr
    } else if addr.wrapping_sub(FLASH_BASE) < CODE_LEN {
        addr - FLASH_BASE
    } else {
        return false;
    };
    match uc.get_data_mut().code_mem.as_mut() {
        Some(c) => {
            c.write(off as usize, bytes);
            true
        }
        None => false,
    }
}

/// New contents of the code sectors at `addr` (both the flash and its alias at 0): the
/// engine's translated blocks and the instruction counts there are dropped.
fn code_changed(uc: &mut Unicorn<'_, Soc>, addr: u32, bytes: &[u8]) {
    let len = bytes.len() as u32;
    {
        let s = uc.get_data_mut();
        if s.in_run {
            let off = addr - FLASH_BASE;
            let (lo, hi) = s.wfi_unscanned.unwrap_or((off, off + len));
            s.wfi_unscanned = Some((lo.min(off), hi.max(off + len)));
            // A hooked `wfi` whose bytes, or those of an IT before it, change sleeps no
            // more until the run loop has looked at the new code (`hook_wfi_sites`).
            let to = addr + len;
            for (site, live) in &mut s.wfi_hooked {
                if addr < *site + 4 && to + 2 * IT_REACH as u32 > *site {
                    *live = None;
                }
            }
        }
    }
    if !write_code(uc, addr, bytes) {
        let _ = uc.mem_write(addr as u64, bytes);
    }
    let _ = uc.ctl_remove_cache(addr as u64, (addr + len) as u64);
    let _ = uc.ctl_remove_cache((addr - FLASH_BASE) as u64, (addr - FLASH_BASE + len) as u64);
    if let (Some(from), Some(to)) = (
        icache_index(addr as u64),
        icache_index((addr + len.max(1) - 1) as u64),
    ) {
        let icache = &mut uc.get_data_mut().icache;
        let from = from.saturating_sub(2048);
        for c in icache.iter_mut().take(to + 1).skip(from) {
            *c = 0;
        }
    }
}

/// Put back the code-sector bytes the engine stored raw (see `Soc::code_restore`).
#[inline]
fn restore_code(uc: &mut Unicorn<'_, Soc>) {
    // At every block: the test inlined, the work (after a store to the code sectors:
    // rare) out of line.
    if !uc.get_data().code_restore.is_empty() {
        restore_code_now(uc);
    }
}

#[inline(never)]
fn restore_code_now(uc: &mut Unicorn<'_, Soc>) {
    for (addr, old) in std::mem::take(&mut uc.get_data_mut().code_restore) {
        if !write_code(uc, addr, &old) {
            let _ = uc.mem_write(addr as u64, &old);
        }
    }
}

/// The FPU's part of an extended frame, in frame order: S0–S15, FPSCR.
const FP_REGS: [RegisterARM; 17] = [
    RegisterARM::S0,
    RegisterARM::S1,
    RegisterARM::S2,
    RegisterARM::S3,
    RegisterARM::S4,
    RegisterARM::S5,
    RegisterARM::S6,
    RegisterARM::S7,
    RegisterARM::S8,
    RegisterARM::S9,
    RegisterARM::S10,
    RegisterARM::S11,
    RegisterARM::S12,
    RegisterARM::S13,
    RegisterARM::S14,
    RegisterARM::S15,
    RegisterARM::FPSCR,
];

/// Exception entry: stack the frame on the current stack and continue at the vector of
/// `e` in handler mode; `ret` is the return address. `Err` when the frame cannot be
/// stacked (the stack points outside RAM): nothing has changed. A vector that cannot
/// be read is a HardFault on the frame stacked, or a lockup ([`vector_of`]).
fn enter(uc: &mut Unicorn<'_, Soc>, e: u32, ret: u32) -> Result<(), ()> {
    uc.get_data_mut().masks_settled = None;
    use RegisterARM as R;
    // SP is the stack the frame goes on: the process stack in thread mode with
    // CONTROL.SPSEL set (`use_psp`), else the main stack.
    let [xpsr, control, sp, r0, r1, r2, r3, r12, lr] = crate::regs::read(
        uc,
        [
            R::XPSR,
            R::CONTROL,
            R::SP,
            R::R0,
            R::R1,
            R::R2,
            R::R3,
            R::R12,
            R::LR,
        ],
    );
    let from_exc = (xpsr & 0x1FF) as usize;
    let handler = from_exc != 0;
    let use_psp = !handler && control & 2 != 0;
    let fpca = control & 4 != 0;
    let size = if fpca { 0x68 } else { 0x20 };
    let unaligned = sp.wrapping_sub(size);
    let frame = unaligned & !7;
    let realign = frame != unaligned;
    // The frame: R0-R3, R12, LR, the return address, xPSR; then S0-S15, FPSCR and a
    // reserved word if the thread used the FPU.
    let mut words = [0u32; 26];
    words[..8].copy_from_slice(&[
        r0,
        r1,
        r2,
        r3,
        r12,
        lr,
        ret & !1,
        (xpsr & !(1 << 9)) | (u32::from(realign) << 9),
    ]);
    if fpca {
        let fp = crate::regs::read(uc, FP_REGS);
        words[8..25].copy_from_slice(&fp);
    }
    let n = (size / 4) as usize;
    let mut bytes = [0u8; 4 * 26];
    for (b, w) in bytes.chunks_exact_mut(4).zip(&words[..n]) {
        b.copy_from_slice(&w.to_le_bytes());
    }
    if !frame_write(uc, frame, &bytes[..4 * n]) {
        return Err(());
    }
    let exc_return = 0xFFFF_FFE1
        | if fpca { 0 } else { 0x10 }
        | if handler {
            0
        } else if use_psp {
            0xC
        } else {
            0x8
        };
    if use_psp {
        crate::regs::write(
            uc,
            [
                (R::PSP, frame),
                (R::CONTROL, control & !(2 | 4)),
                (R::LR, exc_return),
            ],
        );
    } else if fpca {
        crate::regs::write(
            uc,
            [
                (R::MSP, frame),
                (R::CONTROL, control & !4),
                (R::LR, exc_return),
            ],
        );
    } else {
        crate::regs::write(uc, [(R::MSP, frame), (R::LR, exc_return)]);
    }
    // The vector, after the stacking (the core fetches it while it stacks).
    let Some((e, vector)) = vector_of(uc, e, ret) else {
        lock_up(uc);
        return Ok(());
    };
    let new_xpsr = (xpsr & 0xF800_0000) | (1 << 24) | e;
    write_xpsr(uc, new_xpsr);
    taken(uc, e, vector, from_exc, Some(ret));
    Ok(())
}

/// Exception `e` taken at `vector` (xPSR and LR written), from exception `from_exc` at
/// `from_pc` (`None`: tail-chained): the PC, the NVIC's active state and the counts.
#[inline]
fn taken(uc: &mut Unicorn<'_, Soc>, e: u32, vector: u32, from_exc: usize, from_pc: Option<u32>) {
    set(uc, RegisterARM::PC, vector | 1);
    let s = uc.get_data_mut();
    s.note_pends();
    s.nvic.activate(e);
    s.exceptions += 1;
    s.current_exc = e as usize;
    if let Some(c) = s.exc_entries.get_mut(e as usize) {
        *c += 1;
    }
    note_entry(s, e, from_exc, from_pc);
}

/// The vector of exception `e`, entered at `pc` (for the fault's record), and the
/// exception taken: `e`, or HardFault when `e`'s vector cannot be read (a vector table
/// read error: HFSR.VECTTBL, taken on the frame already stacked, as the ARMv7-M
/// exception entry does). `None`: HardFault's vector cannot be read either, or the
/// error happened where HardFault cannot preempt (entering HardFault, or from it): the
/// core locks up.
fn vector_of(uc: &mut Unicorn<'_, Soc>, e: u32, pc: u32) -> Option<(u32, u32)> {
    let vtor = uc.get_data().nvic.vtor();
    if let Some(v) = read_vector(uc, vtor + 4 * e) {
        return Some((e, v));
    }
    let m = masks(uc);
    let t_ps = uc.get_data().now();
    let s = uc.get_data_mut();
    let exec = s.nvic.execution_priority(m, false);
    s.core_faults.push(CoreFault {
        t_ps,
        what: format!(
            "vector table read error (HFSR.VECTTBL): exception {e}'s vector at {:#010x}",
            vtor.wrapping_add(4 * e)
        ),
        pc,
        function: None,
    });
    s.nvic.vector_table_error();
    if e == exc::HARD_FAULT || e == exc::NMI || exec <= -1 {
        return None;
    }
    read_vector(uc, vtor + 4 * exc::HARD_FAULT).map(|v| (exc::HARD_FAULT, v))
}

/// The core locks up (a fault it cannot take): it runs nothing until a reset.
fn lock_up(uc: &mut Unicorn<'_, Soc>) {
    let s = uc.get_data_mut();
    s.locked_up = true;
    s.stop = true;
    let _ = uc.emu_stop();
}

/// Write xPSR (exception number and mode with it) and rebuild the engine's cached mode
/// flags, as [`rebuild_hflags`] does, in one call: its write of the flags writes back
/// the NZCV the xPSR write has just set.
fn write_xpsr(uc: &mut Unicorn<'_, Soc>, xpsr: u32) {
    crate::regs::write(
        uc,
        [
            (RegisterARM::XPSR, xpsr),
            (RegisterARM::APSR_NZCV, xpsr & 0xF000_0000),
        ],
    );
}

/// How [`in_run`] left the core.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
enum InRun {
    /// The run goes on at the PC written (a vector, or after the `wfi`).
    Goes,
    /// The run loop must decide (a reset or a halt due, the run's limit reached, a frame
    /// that cannot be stacked, nothing to take after all); `entered`: an exception was
    /// entered first (the PC is its vector).
    Stop { entered: bool },
}

/// The run loop's work between two runs (`run_until_inner`: the models brought up to
/// now, the DMA's bytes stored, a sleeping core woken at the next event, an exception
/// entered, again while another is to be taken, then the next event's time), done
/// inside a run, at an instruction that has not run: an interrupt made takeable by the
/// block before (the block hook at `resume`), or a `wfi` (a code hook; `resume` is the
/// instruction after it, `asleep`). Writing the PC makes unicorn leave the block there
/// and go on at the new PC in the same run (`quit_request`), at a fraction of a stop
/// and a restart: a moving axis takes an interrupt at every SysTick, and its idle loop
/// masks around its `wfi`, so each tick was two stops. Where the loop must decide, the
/// run stops and the loop finds everything as it would have (a second `process` at the
/// same instant changes nothing). `m`: the mask registers now.
fn in_run(uc: &mut Unicorn<'_, Soc>, resume: u32, asleep: bool, m: Masks) -> InRun {
    let loop_must_decide = |s: &Soc| {
        s.stop
            || s.nvic.reset_requested
            || s.reset_due.is_some()
            || s.locked_up
            || s.unmodelled.is_some()
            || s.engine_error.is_some()
            || s.now() >= s.run_limit_ps
    };
    if loop_must_decide(uc.get_data()) {
        return InRun::Stop { entered: false };
    }
    let mut asleep = asleep;
    let mut entered = false;
    // An entry takes no time, and the models' state at one instant is theirs after one
    // `process` as after two: only a new instant needs one.
    let mut new_instant = true;
    loop {
        if new_instant {
            if let Some(d) = uc.get_data_mut().process() {
                apply_done(uc, d);
            }
            store_dma(uc);
            if loop_must_decide(uc.get_data()) {
                return InRun::Stop { entered };
            }
        }
        // `m`, the mask registers, stay as they are: asleep nothing runs, and an entry
        // does not change them.
        if asleep && !uc.get_data().nvic.wakes(m) {
            let s = uc.get_data_mut();
            let now = s.now();
            let t = s.next_event().min(s.run_limit_ps);
            s.clock.sleep_until(t.max(now + 1));
            new_instant = true;
            continue;
        }
        asleep = false;
        let Some(e) = uc.get_data().nvic.to_take(m) else {
            break;
        };
        let ret = if entered {
            reg(uc, RegisterARM::PC)
        } else {
            resume
        };
        if enter(uc, e, ret).is_err() {
            return InRun::Stop { entered };
        }
        if uc.get_data().locked_up && !entered {
            // A lockup at the entry (`vector_of`) leaves the PC where the run loop's
            // entry would: after the `wfi`, not at it.
            set(uc, RegisterARM::PC, resume | 1);
        }
        entered = true;
        new_instant = false;
        if loop_must_decide(uc.get_data()) {
            return InRun::Stop { entered };
        }
    }
    if !entered {
        if resume == reg(uc, RegisterARM::PC) {
            // Nothing to take after all, and nothing slept: the loop restarts the block.
            return InRun::Stop { entered };
        }
        // Woken with the interrupt masked: on after the `wfi`.
        set(uc, RegisterARM::PC, resume | 1);
    }
    let s = uc.get_data_mut();
    let t = s.next_event().min(s.run_limit_ps);
    s.next_event_mc = s.clock.mc_at(t);
    s.next_event_ps = t;
    s.irq_waiting = s.nvic.anything_pending();
    s.masks_settled = None;
    s.runs += 1;
    s.loops.restart();
    InRun::Goes
}

/// Halfwords looked at before a `wfi` for an IT it may be in: the last instruction of a
/// block of four 32-bit ones starts seven halfwords after its IT (the eighth is a
/// margin; [`wfi_at`] checks each IT's own reach).
const IT_REACH: usize = 8;

/// The length of a `wfi` (`wfi`, 2; `wfi.w`, 4) that starts at halfword `i` of the code
/// (`hw`: halfword `n`, if any), by its bytes: a match that is data or the second
/// halfword of a 32-bit instruction never starts an instruction, and its hook never
/// fires. `None` also where the `wfi` may be inside an IT block (an IT instruction
/// before it whose block reaches it: four instructions of up to two halfwords each):
/// unicorn treats an IT block as one instruction and would run the `wfi` after the hook
/// whatever the hook wrote; such a `wfi` stops the engine as before.
fn wfi_at(hw: impl Fn(usize) -> Option<u16>, i: usize) -> Option<u32> {
    let len = match (hw(i)?, hw(i + 1)) {
        (WFI, _) => 2,
        (0xF3AF, Some(0x8003)) => 4,
        _ => return None,
    };
    // IT: 0xBFxy with a mask `y` other than 0; its block holds 4 - (trailing zeros of
    // `y`) instructions, so the last one starts at most 2 × that - 1 halfwords after it.
    let in_it = (1..=IT_REACH).any(|k| {
        i.checked_sub(k).and_then(&hw).is_some_and(|h| {
            let mask = h & 0xF;
            h & 0xFF00 == 0xBF00 && mask != 0 && k < 2 * (4 - mask.trailing_zeros() as usize)
        })
    });
    (!in_it).then_some(len)
}

/// A `wfi` about to run (its block has been charged, the instruction with it): sleep,
/// wake and take what wakes the core here ([`in_run`]). If the run loop must decide, the
/// `wfi` runs and the engine stops after it, as it did, unless an exception was entered
/// first (the engine then stops at its vector). `site`: its index in
/// `Soc::wfi_hooked`; nothing where that says the hook may not sleep (code programmed
/// there since it was placed, by an update or the bootloader, or a debugging hook that
/// watches it: `Board::at_pc`'s instant is before the instruction, not after a sleep).
fn on_wfi(uc: &mut Unicorn<'_, Soc>, site: usize, pc: u32) {
    let (at, len) = uc
        .get_data()
        .wfi_hooked
        .get(site)
        .copied()
        .unwrap_or((0, None));
    let Some(len) = len.filter(|_| at == pc) else {
        // The instruction there runs; a `wfi` that ends the run is known as one without
        // its bytes (which may have changed since the block was translated).
        uc.get_data_mut().wfi_ran_at = Some(pc);
        return;
    };
    let m = masks(uc);
    match in_run(uc, pc + len, true, m) {
        InRun::Goes => {}
        InRun::Stop { entered: true } => {
            uc.get_data_mut().stop = true;
            let _ = uc.emu_stop();
        }
        InRun::Stop { entered: false } => uc.get_data_mut().wfi_ran_at = Some(pc),
    }
}

/// A hook (`on_wfi`) at each `wfi` the code sectors' bytes `from..to` (offsets) hold now
/// ([`wfi_at`]) that has none yet, and the hooks of the `wfi`s that bytes there may
/// have made or unmade set again: the image's at power-on; after new code is programmed
/// (an update), those of the new code (`Soc::wfi_unscanned`, from the run loop).
fn hook_wfi_sites(
    uc: &mut Unicorn<'_, Soc>,
    from: usize,
    to: usize,
) -> Result<(), unicorn_engine::uc_error> {
    // From the halfword before `from` (a `wfi.w` whose second halfword is new) to the
    // last a new IT reaches; with the halfwords before, for the IT they may be in.
    let first = (from & !1).saturating_sub(2);
    let end = (to + 2 * IT_REACH).min(CODE_LEN as usize);
    let start = first.saturating_sub(2 * IT_REACH);
    let mut code = vec![0u8; end.saturating_sub(start) + 2];
    let n = code.len().min(CODE_LEN as usize - start);
    let read = match uc.get_data().code_mem.as_ref() {
        Some(c) => c.read(start, &mut code[..n]),
        None => false,
    };
    if !read {
        return Ok(());
    }
    code.truncate(n);
    let hw = |i: usize| {
        code.get(2 * i..2 * i + 2)
            .map(|b| u16::from_le_bytes([b[0], b[1]]))
    };
    for i in (first - start) / 2..(end - start).div_ceil(2) {
        let addr = FLASH_BASE + (start + 2 * i) as u32;
        let watched = uc.get_data().loops.watched_pcs.contains(&addr);
        let len = wfi_at(hw, i).filter(|_| !watched);
        let s = uc.get_data_mut();
        if let Some(site) = s.wfi_hooked.iter_mut().find(|(a, _)| *a == addr) {
            site.1 = len;
            continue;
        }
        if len.is_none() {
            continue;
        }
        let site = s.wfi_hooked.len();
        s.wfi_hooked.push((addr, len));
        uc.add_code_hook(
            u64::from(addr),
            u64::from(addr),
            move |uc: &mut Unicorn<'_, Soc>, _: u64, _: u32| {
                on_wfi(uc, site, addr);
            },
        )?;
        // A block translated before the hook would not call it.
        uc.ctl_remove_cache(u64::from(addr), u64::from(addr) + 4)?;
    }
    Ok(())
}

/// Exception `e` entered now, from exception `from_exc` (0: thread mode) at `from_pc`
/// (stacked) or tail-chained after it (`None`): its entry time, and for the sampler's
/// (EXTI0) the wait since its DOUT edge, with where the longest ended.
fn note_entry(s: &mut Soc, e: u32, from_exc: usize, from_pc: Option<u32>) {
    let now = s.now();
    s.entry_log.note(e, now);
    if e == exc::IRQ0 + 6 {
        if let Some(t) = s.exti0_edge_ps {
            let wait = now.saturating_sub(t);
            if wait > s.sample_entry_latency.max_ps {
                s.sample_entry_max_from = (from_exc, from_pc);
            }
            s.sample_entry_latency.add(wait);
        }
    }
}

/// Exception return through EXC_RETURN (the engine's interrupt 8): tail-chain or
/// unstack.
fn exception_return(uc: &mut Unicorn<'_, Soc>) {
    uc.get_data_mut().masks_settled = None;
    use RegisterARM as R;
    // In handler mode SP is the main stack.
    let [pc, xpsr, msp] = crate::regs::read(uc, [R::PC, R::XPSR, R::SP]);
    let exc_return = pc | 1;
    let ipsr = xpsr & 0x1FF;
    {
        let s = uc.get_data_mut();
        if ipsr == exc::IRQ0 + 6 {
            if let Some(t) = s.exti0_edge_ps.take() {
                let now = s.now();
                s.sample_latency.add(now.saturating_sub(t));
            }
        }
    }
    uc.get_data_mut().nvic.deactivate(ipsr);
    uc.get_data_mut().update_lines();
    // The mask registers only if something could be taken.
    let tail = if uc.get_data().nvic.anything_pending() {
        let m = masks(uc);
        uc.get_data().nvic.to_take(m)
    } else {
        None
    };
    if let Some(n) = tail {
        // Tail-chain: the frame stays; the next handler returns through it.
        let Some((n, vector)) = vector_of(uc, n, exc_return) else {
            lock_up(uc);
            return;
        };
        let new_xpsr = (xpsr & 0xF800_0000) | (1 << 24) | n;
        crate::regs::write(
            uc,
            [
                (R::XPSR, new_xpsr),
                (R::LR, exc_return),
                (R::APSR_NZCV, new_xpsr & 0xF000_0000),
            ],
        );
        taken(uc, n, vector, ipsr as usize, None);
        return;
    }
    let to_thread = exc_return & 8 != 0;
    let use_psp = to_thread && exc_return & 4 != 0;
    let std_frame = exc_return & 0x10 != 0;
    let sp = if use_psp {
        reg(uc, RegisterARM::PSP)
    } else {
        msp
    };
    let n = if std_frame { 8 } else { 26 };
    let mut buf = [0u8; 4 * 26];
    if !frame_read(uc, sp, &mut buf[..4 * n]) {
        fault(
            uc,
            exc::HARD_FAULT,
            0,
            exc_return,
            "exception return: stack unreadable",
        );
        return;
    }
    let mut w = [0u32; 26];
    for (v, c) in w.iter_mut().zip(buf.chunks_exact(4)) {
        *v = u32::from_le_bytes([c[0], c[1], c[2], c[3]]);
    }
    let ret = w[6];
    let frame_xpsr = w[7];
    let regs = [
        (R::R0, w[0]),
        (R::R1, w[1]),
        (R::R2, w[2]),
        (R::R3, w[3]),
        (R::R12, w[4]),
        (R::LR, w[5]),
    ];
    let new_sp = sp + 4 * n as u32 + if frame_xpsr & (1 << 9) != 0 { 4 } else { 0 };
    let new_xpsr =
        (frame_xpsr & !(1 << 9) & !0x1FF) | if to_thread { 0 } else { frame_xpsr & 0x1FF };
    if std_frame && !use_psp {
        // The common return, in one call: the frame's registers, xPSR, the main stack,
        // and the engine's mode flags rebuilt (as `rebuild_hflags`: NZCV as just set).
        let [r0, r1, r2, r3, r12, lr] = regs;
        crate::regs::write(
            uc,
            [
                r0,
                r1,
                r2,
                r3,
                r12,
                lr,
                (R::XPSR, new_xpsr),
                (R::MSP, new_sp),
                (R::APSR_NZCV, new_xpsr & 0xF000_0000),
            ],
        );
    } else {
        crate::regs::write(uc, regs);
        if !std_frame {
            let mut fp = [(R::S0, 0u32); 17];
            for ((slot, &r), &v) in fp.iter_mut().zip(FP_REGS.iter()).zip(&w[8..25]) {
                *slot = (r, v);
            }
            crate::regs::write(uc, fp);
        }
        if use_psp {
            // Thread mode again: selecting the process stack swaps it in.
            let control = reg(uc, RegisterARM::CONTROL);
            crate::regs::write(
                uc,
                [
                    (R::XPSR, new_xpsr),
                    (R::CONTROL, control | 2),
                    (R::PSP, new_sp),
                ],
            );
        } else {
            crate::regs::write(uc, [(R::XPSR, new_xpsr), (R::MSP, new_sp)]);
        }
        if !std_frame {
            let c = reg(uc, RegisterARM::CONTROL);
            set(uc, RegisterARM::CONTROL, c | 4);
        }
        rebuild_hflags(uc);
    }
    set(uc, RegisterARM::PC, ret | 1);
    let s = uc.get_data_mut();
    s.current_exc = s.nvic.active_stack().last().copied().unwrap_or(0) as usize;
}

/// The function meter at a block boundary (before the block's own instructions are
/// counted): a call starts at the entry block and ends at the block its return address
/// starts, with the stack back where it was.
fn meter_block(uc: &mut Unicorn<'_, Soc>, addr: u32) {
    let (lr, sp) = (reg(uc, RegisterARM::LR), reg(uc, RegisterARM::SP));
    let s = uc.get_data_mut();
    let exc = s.current_exc;
    let count = s.exc_insns.get(exc).copied().unwrap_or(0);
    let Some(m) = s.meter.as_mut() else { return };
    match m.active {
        None if addr & !1 == m.entry => m.active = Some((exc, count, lr & !1, sp)),
        Some((e, start, ret, sp0)) if e == exc && addr & !1 == ret && sp >= sp0 => {
            m.last = count - start;
            m.max = m.max.max(m.last);
            m.insns += m.last;
            m.calls += 1;
            m.active = None;
        }
        _ => {}
    }
}

/// A block with a mask write was charged: if it ends with a masking site
/// (`Board::watch_masking`), the site is noted, with its time (the block's start plus the
/// instructions before it: the site is the block's last) and PRIMASK before it (nothing
/// before it in the block writes PRIMASK). It counts once the block has run to its end.
#[inline(never)]
fn note_mask_site(uc: &mut Unicorn<'_, Soc>, addr: u32, size: u32, n: u64) {
    let end = addr.wrapping_add(size);
    let s = uc.get_data();
    // What the block ends with is looked up once and kept in its icache entry, which
    // `block_insns` has just filled for this size (and which a code change clears with
    // the count).
    let entry = icache_index(u64::from(addr)).filter(|&i| {
        s.icache
            .get(i)
            .is_some_and(|c| (c & ICACHE_SIZE) >> 12 == size)
    });
    let cached = entry
        .and_then(|i| s.icache.get(i))
        .filter(|&&c| c & ICACHE_SITE_CHECKED != 0)
        .map(|&c| match (c >> ICACHE_SITE_SHIFT) & 3 {
            1 => Some(MaskSite::Disable),
            2 => Some(MaskSite::Enable),
            3 => Some(MaskSite::Restore),
            _ => None,
        });
    let site = match cached {
        Some(site) => site,
        None => {
            let site = block_mask_site(uc, addr, size);
            let bits = match site {
                None => 0,
                Some(MaskSite::Disable) => 1,
                Some(MaskSite::Enable) => 2,
                Some(MaskSite::Restore) => 3,
            };
            if let Some(c) = entry.and_then(|i| uc.get_data_mut().icache.get_mut(i)) {
                *c |= ICACHE_SITE_CHECKED | bits << ICACHE_SITE_SHIFT;
            }
            site
        }
    };
    let Some(site) = site else {
        return;
    };
    // `msr primask` is the 32-bit one.
    let pc = end.wrapping_sub(if site == MaskSite::Restore { 4 } else { 2 });
    // Only a `cpsid i` asks whether interrupts were masked before it.
    let masked = site == MaskSite::Disable && reg(uc, RegisterARM::PRIMASK) & 1 != 0;
    let s = uc.get_data_mut();
    let mc = s.block_at.1 + n.saturating_sub(1) * s.clock.cpi_milli();
    s.mask_pending = Some(MaskPending {
        site,
        pc,
        block: addr,
        mc,
        masked,
    });
}

/// The masking site the block at `addr` (`size` bytes) ends with, if any: a site of
/// `Board::watch_masking`'s list that starts the block's last instruction, not the
/// second halfword of a 32-bit one (the sites are found by their bytes).
fn block_mask_site(uc: &Unicorn<'_, Soc>, addr: u32, size: u32) -> Option<MaskSite> {
    let end = addr.wrapping_add(size);
    let s = uc.get_data();
    let (pc, site) = [(2, false), (4, true)]
        .into_iter()
        .find_map(|(len, wide)| {
            let pc = end.wrapping_sub(len);
            let i = s.mask_sites.binary_search_by_key(&pc, |&(a, _)| a).ok()?;
            let site = s.mask_sites.get(i)?.1;
            ((site == MaskSite::Restore) == wide).then_some((pc, site))
        })?;
    let mut bytes = vec![0u8; size as usize];
    let starts_last = uc.mem_read(u64::from(addr), &mut bytes).is_ok()
        && thumb_insns(&bytes).last().map(|(at, _)| at as u32) == Some(pc - addr);
    starts_last.then_some(site)
}

/// The noted masking site has run (its block reached its end): the window it opens or
/// closes. Called at the next block and between runs; what a site changes (PRIMASK) is
/// read now, and nothing else has run since.
#[inline]
fn finish_mask_site(uc: &mut Unicorn<'_, Soc>) {
    if uc.get_data().mask_pending.is_some() {
        finish_mask_site_now(uc);
    }
}

/// Between two runs: a masking site noted in the last run's last block counts if the
/// block ran to its end, and not if the run stopped inside it, before the site (a stop
/// at a code hook: the PC is then between the block's start and the site; a fault has
/// already dropped it).
fn settle_mask_site(uc: &mut Unicorn<'_, Soc>) {
    if let Some(p) = uc.get_data().mask_pending {
        if (p.block..=p.pc).contains(&reg(uc, RegisterARM::PC)) {
            uc.get_data_mut().mask_pending = None;
        } else {
            finish_mask_site_now(uc);
        }
    }
}

#[inline(never)]
fn finish_mask_site_now(uc: &mut Unicorn<'_, Soc>) {
    let Some(p) = uc.get_data_mut().mask_pending.take() else {
        return;
    };
    let unmasks = match p.site {
        MaskSite::Disable => false,
        MaskSite::Enable => true,
        MaskSite::Restore => reg(uc, RegisterARM::PRIMASK) & 1 == 0,
    };
    let s = uc.get_data_mut();
    let now = s.clock.time_at_mc(p.mc);
    // Time asleep inside a window does not delay anything: a pending interrupt wakes the
    // core, which leaves the window at once.
    let slept = s.clock.sleep_ps();
    if p.site == MaskSite::Disable {
        if !p.masked && s.world.machine.axis.enabled() {
            s.mask_start = Some((now, p.pc, slept));
        }
    } else if unmasks {
        if let Some((t, at, slept0)) = s.mask_start.take() {
            let w = now.saturating_sub(t).saturating_sub(slept - slept0);
            if w > s.mask_max.0 {
                s.mask_max = (w, at);
            }
        }
    }
}

/// A synchronous fault of kind `kind` (MemManage, BusFault, UsageFault or HardFault)
/// at `pc`: taken as itself if enabled and allowed, else escalated to HardFault; a
/// fault that HardFault cannot take is a lockup.
fn fault(uc: &mut Unicorn<'_, Soc>, kind: u32, cfsr: u32, pc: u32, what: &str) {
    // The block stopped at the faulting instruction: a masking site at its end never ran.
    uc.get_data_mut().mask_pending = None;
    uc.get_data_mut().masks_settled = None;
    let m = masks(uc);
    let (target, exec) = {
        let n = &uc.get_data().nvic;
        let exec = n.execution_priority(m, false);
        (n.fault_target(kind, exec), exec)
    };
    let t_ps = uc.get_data().now();
    let s = uc.get_data_mut();
    s.core_faults.push(CoreFault {
        t_ps,
        what: what.to_string(),
        pc,
        function: None,
    });
    s.nvic.fault_status(
        cfsr,
        target == exc::HARD_FAULT && kind != exc::HARD_FAULT,
        None,
    );
    if (target == exc::HARD_FAULT && exec <= -1) || enter(uc, target, pc).is_err() {
        lock_up(uc);
    }
}

fn on_interrupt(uc: &mut Unicorn<'_, Soc>, intno: u32) {
    let pc = reg(uc, RegisterARM::PC);
    if intno != 8 {
        // An exception raised inside the block (svc, bkpt, a usage fault): the rest of
        // the block, a masking site at its end included, did not run. (An exception
        // return ends its block: a site of the block before has already been counted.)
        uc.get_data_mut().mask_pending = None;
    }
    match intno {
        8 => exception_return(uc),
        2 => {
            if enter(uc, exc::SVCALL, pc).is_err() {
                fault(uc, exc::HARD_FAULT, 0, pc, "svc: stacking failed");
            }
        }
        // No debugger attached: a breakpoint is a HardFault (HFSR.DEBUGEVT).
        7 => fault(uc, exc::HARD_FAULT, 0, pc, "bkpt without a debugger"),
        17 => fault(
            uc,
            exc::USAGE_FAULT,
            1 << 19,
            pc,
            "coprocessor access (NOCP)",
        ),
        18 => fault(
            uc,
            exc::USAGE_FAULT,
            1 << 17,
            pc,
            "invalid state (INVSTATE)",
        ),
        22 => fault(uc, exc::USAGE_FAULT, 1 << 24, pc, "unaligned access"),
        other => {
            let s = uc.get_data_mut();
            s.engine_error = Some(format!("unexpected exception {other} at pc {pc:#x}"));
            s.stop = true;
            let _ = uc.emu_stop();
        }
    }
}

/// What a run can report.
impl Board {
    /// The SoC.
    pub fn soc(&self) -> &Soc {
        self.uc.get_data()
    }

    /// The SoC, mutably (scenes drive the world through it).
    pub fn soc_mut(&mut self) -> &mut Soc {
        self.uc.get_data_mut()
    }

    /// Now, ps.
    pub fn now(&self) -> u64 {
        self.soc().now()
    }

    /// Apply power (a power-on reset). SRAM and CCM RAM come up holding noise, not what
    /// the last run left (a pin, watchdog or software reset keeps them).
    pub fn power_on(&mut self) {
        let mut x = 0x9E37_79B9_7F4A_7C15u64 ^ self.now();
        for (base, len) in [(SRAM, SRAM_SIZE), (0x1000_0000, 0x1_0000)] {
            let noise: Vec<u8> = (0..len)
                .map(|_| {
                    // xorshift64
                    x ^= x << 13;
                    x ^= x >> 7;
                    x ^= x << 17;
                    x as u8
                })
                .collect();
            let _ = self.uc.mem_write(base as u64, &noise);
        }
        self.reset(ResetCause::PowerOn);
    }

    /// Pull NRST low (a pin reset, at the next instant the board runs).
    pub fn reset_pin(&mut self) {
        self.soc_mut().reset_due = Some(ResetCause::Pin);
    }

    /// Whether the core sleeps (`wfi`).
    pub fn sleeping(&self) -> bool {
        self.sleeping
    }

    fn reset(&mut self, cause: ResetCause) {
        let cut = self.uc.get_data_mut().reset_peripherals(cause);
        if let Some(d) = cut {
            apply_done(&mut self.uc, d);
        }
        // A masking site that ran before the reset counts, then the window ends.
        settle_mask_site(&mut self.uc);
        let uc = &mut self.uc;
        let sp = read_u32(uc, 0).unwrap_or(0);
        let pc = read_u32(uc, 4).unwrap_or(0);
        for r in GP_REGS {
            set(uc, r, 0);
        }
        set(uc, RegisterARM::XPSR, 1 << 24);
        set(uc, RegisterARM::PRIMASK, 0);
        set(uc, RegisterARM::BASEPRI, 0);
        set(uc, RegisterARM::FAULTMASK, 0);
        set(uc, RegisterARM::CONTROL, 0);
        rebuild_hflags(uc);
        set(uc, RegisterARM::MSP, sp & !3);
        set(uc, RegisterARM::PSP, 0);
        set(uc, RegisterARM::LR, 0xFFFF_FFFF);
        for &r in &FP_REGS[..16] {
            set(uc, r, 0);
        }
        set(uc, RegisterARM::FPSCR, 0);
        set(uc, RegisterARM::PC, pc | 1);
        let s = uc.get_data_mut();
        s.locked_up = false;
        s.current_exc = 0;
        // A reset ends any masked window and any sample in flight.
        s.mask_start = None;
        s.exti0_edge_ps = None;
        s.reset_due = None;
        s.nvic.reset_requested = false;
        let now = s.now();
        self.sleeping = false;
        self.resets.push((now, cause));
    }

    /// Drain the RTT buffer into the log.
    pub fn poll_rtt(&mut self) {
        if !self.probe_attached {
            return;
        }
        let Some(rtt) = self.rtt.as_mut() else {
            return;
        };
        let [buf_a, size_a, write_a, read_a] = rtt.fields();
        let uc = &mut self.uc;
        let (Some(buf), Some(size), Some(write), Some(read)) = (
            read_u32(uc, buf_a),
            read_u32(uc, size_a),
            read_u32(uc, write_a),
            read_u32(uc, read_a),
        ) else {
            return;
        };
        if size == 0 || write >= size || read >= size || write == read {
            return;
        }
        let mut bytes = Vec::new();
        let mut r = read;
        while r != write {
            let end = if write > r { write } else { size };
            let mut chunk = vec![0u8; (end - r) as usize];
            if uc.mem_read((buf + r) as u64, &mut chunk).is_err() {
                return;
            }
            bytes.extend(chunk);
            r = if end == size { 0 } else { end };
        }
        let _ = uc.mem_write(read_a as u64, &write.to_le_bytes());
        let t = uc.get_data().now();
        rtt.feed(&bytes, t, &mut self.log);
    }

    /// Run until virtual time `until_ps`. `Err` when the board cannot go on (an
    /// unmodelled peripheral access, an engine failure); faults of the image are not
    /// errors: they are taken as the core would.
    pub fn run_until(&mut self, until_ps: u64) -> Result<(), Halt> {
        let r = self.run_until_inner(until_ps);
        self.speed.tick(self.now());
        r
    }

    fn run_until_inner(&mut self, until_ps: u64) -> Result<(), Halt> {
        loop {
            settle_mask_site(&mut self.uc);
            if let Some((from, to)) = self.uc.get_data_mut().wfi_unscanned.take() {
                // The code array as programmed, not a store the engine left in it raw.
                restore_code(&mut self.uc);
                hook_wfi_sites(&mut self.uc, from as usize, to as usize)
                    .map_err(|x| Halt::Engine(format!("unicorn wfi hook: {x:?}")))?;
            }
            let done = self.uc.get_data_mut().process();
            if let Some(d) = done {
                apply_done(&mut self.uc, d);
            }
            store_dma(&mut self.uc);
            let reset = {
                let s = self.uc.get_data_mut();
                if s.nvic.reset_requested {
                    Some(ResetCause::Software)
                } else {
                    s.reset_due
                }
            };
            if let Some(c) = reset {
                self.reset(c);
                continue;
            }
            let now = self.now();
            if now >= self.next_rtt_ps {
                self.poll_rtt();
                self.next_rtt_ps = now + POLL_PS;
            }
            self.check_halt()?;
            let m = masks(&self.uc);
            let (locked, wakes) = {
                let s = self.uc.get_data();
                (s.locked_up, s.nvic.wakes(m))
            };
            if locked || (self.sleeping && !wakes) {
                let t = self
                    .uc
                    .get_data()
                    .next_event()
                    .min(self.next_rtt_ps)
                    .min(until_ps);
                if now >= until_ps {
                    return Ok(());
                }
                self.uc.get_data_mut().clock.sleep_until(t.max(now + 1));
                continue;
            }
            self.sleeping = false;
            if let Some(e) = self.uc.get_data().nvic.to_take(m) {
                let pc = reg(&self.uc, RegisterARM::PC);
                if enter(&mut self.uc, e, pc).is_err() {
                    fault(
                        &mut self.uc,
                        exc::HARD_FAULT,
                        0,
                        pc,
                        "exception entry: stack outside RAM",
                    );
                }
                continue;
            }
            if now >= until_ps {
                return Ok(());
            }
            {
                let t = self
                    .uc
                    .get_data()
                    .next_event()
                    .min(self.next_rtt_ps)
                    .min(until_ps);
                let s = self.uc.get_data_mut();
                s.run_limit_ps = self.next_rtt_ps.min(until_ps);
                s.next_event_mc = s.clock.mc_at(t);
                s.next_event_ps = t;
                s.irq_waiting = s.nvic.anything_pending();
                s.masks_settled = None;
                s.stop = false;
            }
            let pc = reg(&self.uc, RegisterARM::PC);
            let s = self.uc.get_data_mut();
            s.runs += 1;
            s.engine_starts += 1;
            s.wfi_ran_at = None;
            s.loops.restart();
            let r = self.uc.emu_start((pc | 1) as u64, 0, 0, 0);
            // A run translates at least its first block (a fetch, a fill): none counted,
            // and the linker took unicorn's fill instead of the board's (src/tlb.rs).
            if crate::tlb::fills() == 0 {
                return Err(Halt::Engine(
                    "the engine's TLB fill is unicorn's, not the board's (src/tlb.rs)".into(),
                ));
            }
            let stopped = self.uc.get_data().stop;
            match r {
                Err(unicorn_engine::uc_error::FETCH_PROT)
                    if self.uc.get_data().mem_fault.is_none()
                        && self.grant_sram_exec(reg(&self.uc, RegisterARM::PC)) => {}
                Err(err) => {
                    let pc = reg(&self.uc, RegisterARM::PC);
                    match self.uc.get_data_mut().mem_fault.take() {
                        Some((addr, t)) => {
                            let what = format!("bus fault: {t:?} at {addr:#010x}");
                            self.uc
                                .get_data_mut()
                                .nvic
                                .fault_status(1 << 9, false, Some(addr));
                            fault(&mut self.uc, exc::BUS_FAULT, 1 << 9, pc, &what);
                        }
                        None => {
                            self.check_halt()?;
                            return Err(Halt::Engine(format!("{err:?} at pc {pc:#010x}")));
                        }
                    }
                }
                Ok(()) if stopped => {}
                Ok(()) => {
                    // The engine ends a run by itself only at `wfi`.
                    let pc = reg(&self.uc, RegisterARM::PC);
                    let mut hw = [0u8; 2];
                    let ran_at = self.uc.get_data().wfi_ran_at;
                    let hooked =
                        ran_at == Some(pc.wrapping_sub(2)) || ran_at == Some(pc.wrapping_sub(4));
                    let is_wfi = hooked
                        || self
                            .uc
                            .mem_read(u64::from(pc.wrapping_sub(2)), &mut hw)
                            .is_ok()
                            && u16::from_le_bytes(hw) == WFI;
                    let is_wfi_w = read_u32(&self.uc, pc.wrapping_sub(4)) == Some(0x8003_F3AF);
                    if is_wfi || is_wfi_w {
                        self.sleeping = true;
                    } else {
                        return Err(Halt::Engine(format!(
                            "the core stopped at pc {pc:#010x} for no reason"
                        )));
                    }
                }
            }
        }
    }

    /// The first instruction fetch from an SRAM page (see the SRAM map in `new`): the
    /// page becomes executable, and the run goes on from `pc`, where the fetch stopped it
    /// before anything of that instruction ran. False if `pc` is not in SRAM or its page
    /// is executable already (a fault of another kind).
    fn grant_sram_exec(&mut self, pc: u32) -> bool {
        // A 32-bit instruction may straddle two pages: its second halfword's too.
        let mut granted = false;
        for a in [pc, pc.wrapping_add(2)] {
            let Some(page) = a.checked_sub(SRAM).map(|o| o / SRAM_PAGE) else {
                continue;
            };
            if page >= SRAM_SIZE / SRAM_PAGE || self.sram_exec & (1 << page) != 0 {
                continue;
            }
            let base = SRAM + page * SRAM_PAGE;
            crate::tlb::mark_executable(base);
            if self
                .uc
                .mem_protect(base as u64, SRAM_PAGE as u64, Prot::ALL)
                .is_ok()
            {
                self.sram_exec |= 1 << page;
                granted = true;
            }
        }
        granted
    }

    fn check_halt(&mut self) -> Result<(), Halt> {
        let pc = reg(&self.uc, RegisterARM::PC);
        let s = self.uc.get_data_mut();
        if let Some((addr, write)) = s.unmodelled {
            return Err(Halt::Unmodelled { addr, write, pc });
        }
        if let Some(e) = s.engine_error.take() {
            return Err(Halt::Engine(e));
        }
        Ok(())
    }

    /// Measure how long the firmware masks every interrupt (`cpsid i` … `cpsie i`) while
    /// the propulsion driver is on: each window delays the safety path by as much. Code
    /// hooks on every `cpsid i` / `cpsie i` of the image's code (a halfword that is data
    /// and never executes costs nothing).
    pub fn watch_masking(&mut self) {
        // Sites: `cpsid i` (masks), `cpsie i` (unmasks), `msr primask, rN` (restores what
        // an earlier `mrs` read: unmasks if rN's bit 0 is clear, that is if it leaves
        // PRIMASK clear). Each ends its translated block (translate.c: CPS and MSR end
        // with `gen_lookup_tb`), so the block hook finds it at its block's end and counts
        // it once the block has run (`note_mask_site`, `finish_mask_site`). They were
        // code hooks: unicorn walks every code hook at each hooked instruction, and the
        // walk, the hook and the exit check after it were a tenth of a flooded run.
        let code =
            &self.image.flash[..(self.image.flash_used as usize).min(self.image.flash.len())];
        let hw = |i: usize| {
            code.get(2 * i..2 * i + 2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]))
        };
        let mut sites = Vec::new();
        for i in 0..code.len() / 2 {
            let addr = FLASH_BASE + 2 * i as u32;
            match (hw(i), hw(i + 1)) {
                (Some(0xB672), _) => sites.push((addr, MaskSite::Disable)),
                (Some(0xB662), _) => sites.push((addr, MaskSite::Enable)),
                // From any of r0–r12 and lr (the compiler keeps PRIMASK in lr too:
                // `mrs lr, primask` … `msr primask, lr`; a missed restore would make a
                // window look as long as the time to the next unmask elsewhere).
                (Some(h1), Some(0x8810))
                    if h1 & 0xFFF0 == 0xF380 && !matches!(h1 & 0xF, 13 | 15) =>
                {
                    sites.push((addr, MaskSite::Restore));
                }
                _ => {}
            }
        }
        sites.sort_by_key(|&(addr, _)| addr);
        let s = self.uc.get_data_mut();
        s.mask_sites = sites;
        // What blocks end with is looked up again, against these sites.
        for c in &mut s.icache {
            *c &= !(ICACHE_SITE_CHECKED | 3 << ICACHE_SITE_SHIFT);
        }
    }

    /// A debugging hook goes on the instruction at `addr` (`watch_pc`, `at_pc`): a
    /// polling loop that holds it is never skipped, a `wfi` there is not slept through
    /// inside the run (`on_wfi`), and the blocks translated without a call to the hook
    /// are dropped (unicorn places a code hook's calls when it translates), so that it
    /// sees every execution from now on, whenever it is placed.
    /// The instruction's address (`addr` without the Thumb bit: a hook at an odd
    /// address never fires) is returned.
    fn watch_addr(&mut self, addr: u32) -> u32 {
        let a = addr & !1;
        let s = self.soc_mut();
        s.loops.watched_pcs.push(a);
        for (site, live) in &mut s.wfi_hooked {
            if *site == a {
                *live = None;
            }
        }
        let _ = self.uc.ctl_remove_cache(u64::from(a), u64::from(a) + 2);
        a
    }

    /// Count the executions of the instruction at `addr` (a debugging aid: a code hook on
    /// that one instruction; [`Board::watch_addr`]).
    pub fn watch_pc(&mut self, addr: u32) -> std::rc::Rc<std::cell::Cell<u64>> {
        let hits = std::rc::Rc::new(std::cell::Cell::new(0u64));
        let h = hits.clone();
        let a = u64::from(self.watch_addr(addr));
        let _ = self.uc.add_code_hook(a, a, move |_, _, _| {
            h.set(h.get() + 1);
        });
        hits
    }

    /// Run `f` with the board's peripherals and world each time the core is about to
    /// execute the instruction at `addr`; when it returns `true`, the engine stops there,
    /// so an interrupt `f` made pending (a line it changed, [`Soc::sample_exti`]) is
    /// taken before the next instruction runs, as on the part at that instant. For
    /// placing an event at a sub-step instant (`tests/between_steps.rs`: an E-STOP edge
    /// between the control step's gate check and its step rate).
    /// [`Board::watch_addr`]: a `wfi` there runs as the instruction it is, after `f`.
    pub fn at_pc(&mut self, addr: u32, mut f: impl FnMut(&mut Soc) -> bool + 'static) {
        let a = u64::from(self.watch_addr(addr));
        let _ = self.uc.add_code_hook(a, a, move |uc, _, _| {
            let s = uc.get_data_mut();
            if f(s) {
                // The engine stops before this instruction (a masking site after it
                // in the block does not run: `settle_mask_site`), or, inside an IT
                // block, where unicorn defers a hook's stop, at the next block.
                s.stop = true;
                s.irq_waiting = true;
                let _ = uc.emu_stop();
            }
        });
    }

    /// An imprecise bus error now (a write buffered to a peripheral that errs, a glitch
    /// on the bus): asynchronous, so it is taken at the current instruction as the core
    /// would, escalated to HardFault (no configurable fault is enabled). Wakes a
    /// sleeping core. For proving the HardFault path; a locked-up core ignores it.
    pub fn inject_bus_fault(&mut self) {
        if self.uc.get_data().locked_up {
            return;
        }
        let pc = reg(&self.uc, RegisterARM::PC);
        self.sleeping = false;
        fault(
            &mut self.uc,
            exc::BUS_FAULT,
            1 << 10,
            pc,
            "imprecise bus error (injected)",
        );
    }

    /// Meter the function at `entry` (instructions per call, see [`crate::soc::FnMeter`]);
    /// replaces any meter before.
    pub fn meter(&mut self, entry: u32) {
        self.soc_mut().meter = Some(crate::soc::FnMeter {
            entry: entry & !1,
            ..Default::default()
        });
    }

    /// Detach the probe: nothing reads the RTT buffer any more, and the log stops.
    pub fn detach_probe(&mut self) {
        self.probe_attached = false;
    }

    /// Write the main stack pointer, as a debugger would (for proving what a stack
    /// overflow does: the next exception stacks from there).
    pub fn set_msp(&mut self, sp: u32) {
        set(&mut self.uc, RegisterARM::MSP, sp);
        if reg(&self.uc, RegisterARM::CONTROL) & 2 == 0 {
            set(&mut self.uc, RegisterARM::SP, sp);
        }
    }

    /// Read a word of memory (RAM, flash) as a probe would.
    pub fn peek(&self, addr: u32) -> Option<u32> {
        read_u32(&self.uc, addr)
    }

    /// The core's program counter.
    pub fn pc(&self) -> u32 {
        reg(&self.uc, RegisterARM::PC)
    }

    /// A digest of everything a run leaves that could tell two runs apart: every pin
    /// edge and console and Modbus byte with its time, the defmt log, the resets, the
    /// clock (time, instructions, cycles, sleep), the instructions, cycles and entries
    /// of every exception, the control task's entries and pends, the watchdog's
    /// reloads, the accesses counted, the accelerator's counters, the core's registers,
    /// SRAM and CCM RAM. Not what only tells how the emulation got there (engine runs,
    /// the loops skipped). FNV-1a, 64 bits.
    pub fn trace_digest(&self) -> u64 {
        let mut h = Fnv::default();
        let s = self.soc();
        for e in &s.edges {
            h.u64(e.t_ps);
            h.bytes(format!("{:?}", e.signal).as_bytes());
            h.u64(u64::from(e.high));
        }
        for &(t, b) in s.console_out.iter().chain(&s.modbus_out) {
            h.u64(t);
            h.u64(u64::from(b));
        }
        for l in &self.log {
            h.u64(l.t_ps);
            for x in [&l.level, &l.timestamp, &l.msg] {
                h.bytes(x.as_bytes());
            }
        }
        for &(t, c) in &self.resets {
            h.u64(t);
            h.bytes(format!("{c:?}").as_bytes());
        }
        let c = &s.clock;
        for x in [c.now_ps(), c.insns(), c.mc(), c.sleep_ps(), s.stall_ps] {
            h.u64(x);
        }
        for v in [&s.exc_insns, &s.exc_entries, &s.exc_mc] {
            v.iter().for_each(|&x| h.u64(x));
        }
        for &(e, t) in s.entry_log.entries.iter().chain(&s.entry_log.pends) {
            h.u64(u64::from(e));
            h.u64(t);
        }
        for b in &s.feeds.bursts {
            for x in [b.first, b.last, b.count, b.max_gap] {
                h.u64(x);
            }
        }
        h.u64(s.accesses.0);
        h.u64(s.accesses.1);
        h.bytes(format!("{:?}", s.flash.art.stats).as_bytes());
        for r in GP_REGS.iter().chain(&[
            RegisterARM::SP,
            RegisterARM::LR,
            RegisterARM::PC,
            RegisterARM::XPSR,
            RegisterARM::PRIMASK,
            RegisterARM::BASEPRI,
        ]) {
            h.u64(u64::from(reg(&self.uc, *r)));
        }
        for (base, len) in [(SRAM, SRAM_SIZE), (0x1000_0000, 0x1_0000)] {
            let mut b = vec![0u8; len as usize];
            if self.uc.mem_read(u64::from(base), &mut b).is_ok() {
                h.bytes(&b);
            }
        }
        h.0
    }

    /// Name a fault's location from the image's symbols.
    pub fn faults(&self) -> Vec<CoreFault> {
        self.soc()
            .core_faults
            .iter()
            .map(|f| CoreFault {
                function: self.image.function_at(f.pc).map(str::to_string),
                ..f.clone()
            })
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn thumb(hws: &[u16]) -> Vec<u8> {
        hws.iter().flat_map(|h| h.to_le_bytes()).collect()
    }

    #[test]
    fn a_block_is_flagged_when_it_may_write_a_mask_register_and_only_then() {
        // movs r0, #1; adds r0, r0, #1; bx lr: three instructions, no mask.
        assert_eq!(scan_insns(&thumb(&[0x2001, 0x1c40, 0x4770])), (3, false));
        // cpsie i; cpsid i; cpsie f
        for cps in [0xb662, 0xb672, 0xb661] {
            assert_eq!(scan_insns(&thumb(&[0x2001, cps])), (2, true), "{cps:#06x}");
        }
        // msr basepri, r0 (f380 8811); msr primask, r3 (f383 8810)
        assert_eq!(scan_insns(&thumb(&[0xf380, 0x8811, 0x4770])), (2, true));
        assert_eq!(scan_insns(&thumb(&[0xf383, 0x8810])), (1, true));
        // mrs r0, basepri (f3ef 8011) reads, bl (f000 f800) branches: neither writes.
        assert_eq!(
            scan_insns(&thumb(&[0xf3ef, 0x8011, 0xf000, 0xf800])),
            (2, false)
        );
        // The halfword of a 32-bit instruction that looks like a CPS is not one.
        assert_eq!(scan_insns(&thumb(&[0xf000, 0xb662])), (1, false));
    }

    /// The `wfi` instructions of the code sectors' image (`code`, from `FLASH_BASE`): each
    /// one's address and length ([`wfi_at`]).
    fn wfi_sites(code: &[u8]) -> Vec<(u32, u32)> {
        let hw = |i: usize| {
            code.get(2 * i..2 * i + 2)
                .map(|b| u16::from_le_bytes([b[0], b[1]]))
        };
        (0..code.len() / 2)
            .filter_map(|i| wfi_at(hw, i).map(|len| (FLASH_BASE + 2 * i as u32, len)))
            .collect()
    }

    #[test]
    fn wfi_sites_are_found_by_their_bytes_and_not_after_an_it() {
        // nop; wfi; nop; wfi.w; it eq; wfi (conditional: unicorn runs an IT block whole);
        // then four other halfwords and a wfi again.
        let code = thumb(&[
            0xbf00, 0xbf30, 0xbf00, 0xf3af, 0x8003, 0xbf08, 0xbf30, 0x4600, 0x4600, 0x4600, 0x4600,
            0xbf30,
        ]);
        assert_eq!(
            wfi_sites(&code),
            vec![
                (FLASH_BASE + 2, 2),
                (FLASH_BASE + 6, 4),
                (FLASH_BASE + 22, 2)
            ]
        );
    }

    #[test]
    fn a_wfi_seven_halfwords_into_an_it_block_of_four_is_not_a_site() {
        // itttt eq; ldr.w r1, [r0] three times; wfi: the block's fourth instruction,
        // seven halfwords after the IT.
        let in_block = thumb(&[
            0xbf01, 0xf8d0, 0x1000, 0xf8d0, 0x1000, 0xf8d0, 0x1000, 0xbf30,
        ]);
        assert_eq!(wfi_sites(&in_block), vec![]);
        // it eq; nop; wfi: the block holds the nop only, and the wfi is a site.
        let after_block = thumb(&[0xbf08, 0xbf00, 0xbf30]);
        assert_eq!(wfi_sites(&after_block), vec![(FLASH_BASE + 4, 2)]);
    }
}
