//! NVIC and SCB (ARMv7-M ARM B1.5, B3.2, B3.4): which exception is pending, active and
//! enabled, their priorities, and the core's system control registers.
//!
//! The unicorn engine has none of this; the board (`cpu.rs`) asks this model which
//! exception to take and when, and does the stacking itself.
//!
//! * 16 system exceptions + 82 interrupts (STM32F407). 4 priority bits (7:4) are
//!   implemented; `AIRCR.PRIGROUP` splits them into group priority and subpriority.
//! * Execution priority: the highest (lowest value) group priority of the active
//!   exceptions, raised by `BASEPRI` (if non-zero), `PRIMASK` (0) and `FAULTMASK` (−1).
//! * A pending enabled exception preempts when its group priority is higher than the
//!   execution priority; among several, the lowest priority value wins, then the lowest
//!   exception number.
//! * Interrupt lines are level-sensitive: an asserted line of an exception that is not
//!   active makes it pending; one still asserted when its handler returns pends it
//!   again.
//!
//! | addr | name |
//! |---|---|
//! | 0xE000_E004 | ICTR (reads 2: up to 96 interrupts) |
//! | 0xE000_E008 | ACTLR |
//! | 0xE000_E100–11C / 180 / 200 / 280 / 300 | ISER / ICER / ISPR / ICPR / IABR |
//! | 0xE000_E400–451 | IPR (byte-accessible) |
//! | 0xE000_ED00 | CPUID 0x410F_C241 |
//! | 0xE000_ED04 | ICSR |
//! | 0xE000_ED08 | VTOR |
//! | 0xE000_ED0C | AIRCR (key 0x05FA; SYSRESETREQ) |
//! | 0xE000_ED10 | SCR |
//! | 0xE000_ED14 | CCR (reset 0x200: STKALIGN) |
//! | 0xE000_ED18–20 | SHPR1–3 |
//! | 0xE000_ED24 | SHCSR |
//! | 0xE000_ED28–3C | CFSR, HFSR, DFSR, MMFAR, BFAR, AFSR |
//! | 0xE000_ED88 | CPACR |
//! | 0xE000_ED90 | MPU_TYPE (8 regions); MPU_CTRL and region registers |
//! | 0xE000_EF00 | STIR |
//! | 0xE000_EF34–3C | FPCCR (reset 0xC000_0000), FPCAR, FPDSCR |

use super::{lane, merge, no_read, no_write, Access};

/// Exception numbers.
pub mod exc {
    /// Reset.
    pub const RESET: u32 = 1;
    /// Non-maskable interrupt.
    pub const NMI: u32 = 2;
    /// HardFault.
    pub const HARD_FAULT: u32 = 3;
    /// MemManage fault.
    pub const MEM_MANAGE: u32 = 4;
    /// BusFault.
    pub const BUS_FAULT: u32 = 5;
    /// UsageFault.
    pub const USAGE_FAULT: u32 = 6;
    /// Supervisor call.
    pub const SVCALL: u32 = 11;
    /// PendSV.
    pub const PENDSV: u32 = 14;
    /// SysTick.
    pub const SYSTICK: u32 = 15;
    /// First external interrupt.
    pub const IRQ0: u32 = 16;
}

/// Interrupts of the STM32F407.
pub const IRQS: u32 = 82;
/// Exception slots (system + interrupts).
pub const SLOTS: u32 = exc::IRQ0 + IRQS;

/// Thread mode's execution priority (lower than any exception).
pub const THREAD_PRIORITY: i16 = 256;

/// The core's interrupt masks, as read from the CPU.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Masks {
    /// PRIMASK bit.
    pub primask: bool,
    /// FAULTMASK bit.
    pub faultmask: bool,
    /// BASEPRI (0 = off).
    pub basepri: u8,
}

/// When chosen exceptions were entered (taken, or tail-chained into), ps: what a logic
/// analyser would show of a GPIO toggled at each handler's first instruction, without
/// the GPIO. The board notes every entry ([`EntryLog::note`]); only the watched ones are
/// kept. It lives in the SoC, not in [`Nvic`], so a reset does not clear it.
///
/// It also keeps when they became pending (not pending → pending, by any path: an
/// interrupt line rising, a line still asserted at exception return, ISPR, STIR, ICSR):
/// [`Nvic`] collects the exceptions that became pending ([`Nvic::take_rises`]), the board
/// hands them over with the time ([`EntryLog::note_pends`]) before it takes any of them.
#[derive(Clone, Debug, Default)]
pub struct EntryLog {
    watched: u128,
    /// (exception number, entry time ps), in time order.
    pub entries: Vec<(u32, u64)>,
    /// (exception number, time it became pending ps), in time order.
    pub pends: Vec<(u32, u64)>,
}

impl EntryLog {
    /// Keep the entries of exception `e` from now on.
    pub fn watch(&mut self, e: u32) {
        if e < SLOTS {
            self.watched |= bit(e);
        }
    }

    /// Exception `e` was entered at `t_ps`.
    #[inline]
    pub fn note(&mut self, e: u32, t_ps: u64) {
        if e < SLOTS && self.watched & bit(e) != 0 {
            self.entries.push((e, t_ps));
        }
    }

    /// The exceptions of the set `rose` (bit `e` = exception `e`) became pending at
    /// `t_ps`; the watched ones are kept.
    #[inline]
    pub fn note_pends(&mut self, rose: u128, t_ps: u64) {
        let mut w = rose & self.watched;
        while w != 0 {
            let e = w.trailing_zeros();
            w &= w - 1;
            self.pends.push((e, t_ps));
        }
    }

    /// The entry times of exception `e`, ps.
    pub fn times(&self, e: u32) -> Vec<u64> {
        self.entries
            .iter()
            .filter(|&&(x, _)| x == e)
            .map(|&(_, t)| t)
            .collect()
    }

    /// The times exception `e` became pending, ps.
    pub fn pend_times(&self, e: u32) -> Vec<u64> {
        self.pends
            .iter()
            .filter(|&&(x, _)| x == e)
            .map(|&(_, t)| t)
            .collect()
    }
}

/// NVIC + SCB.
#[derive(Clone, Debug)]
pub struct Nvic {
    pending: u128,
    /// Exceptions that became pending (from not pending) since the board last took the
    /// set ([`Nvic::take_rises`]).
    rose: u128,
    active: u128,
    enabled: u128,
    /// Programmable priorities (byte per exception; system ones from SHPR).
    prio: [u8; SLOTS as usize],
    /// Order of activation (the active stack), innermost last.
    stack: Vec<u32>,
    /// Level of each interrupt line (sampled by the board).
    lines: u128,
    vtor: u32,
    prigroup: u32,
    scr: u32,
    ccr: u32,
    shcsr: u32,
    cfsr: u32,
    hfsr: u32,
    mmfar: u32,
    bfar: u32,
    actlr: u32,
    cpacr: u32,
    fpccr: u32,
    fpcar: u32,
    fpdscr: u32,
    mpu_ctrl: u32,
    mpu_rnr: u32,
    mpu_rbar: [u32; 8],
    mpu_rasr: [u32; 8],
    /// A system reset was requested (AIRCR.SYSRESETREQ).
    pub reset_requested: bool,
}

impl Default for Nvic {
    fn default() -> Self {
        Self {
            pending: 0,
            rose: 0,
            active: 0,
            enabled: 0,
            prio: [0; SLOTS as usize],
            stack: Vec::new(),
            lines: 0,
            vtor: 0,
            prigroup: 0,
            scr: 0,
            ccr: 0x200,
            shcsr: 0,
            cfsr: 0,
            hfsr: 0,
            mmfar: 0,
            bfar: 0,
            actlr: 0,
            cpacr: 0,
            fpccr: 0xC000_0000,
            fpcar: 0,
            fpdscr: 0,
            mpu_ctrl: 0,
            mpu_rnr: 0,
            mpu_rbar: [0; 8],
            mpu_rasr: [0; 8],
            reset_requested: false,
        }
    }
}

fn bit(e: u32) -> u128 {
    1u128 << e
}

impl Nvic {
    /// At reset.
    pub fn reset(&mut self) {
        *self = Self::default();
    }

    /// The vector table's address.
    pub fn vtor(&self) -> u32 {
        self.vtor
    }

    /// Priority of exception `e` (fixed ones negative).
    pub fn priority(&self, e: u32) -> i16 {
        match e {
            exc::RESET => -3,
            exc::NMI => -2,
            exc::HARD_FAULT => -1,
            _ => self.prio.get(e as usize).copied().unwrap_or(0) as i16,
        }
    }

    /// Group priority of a priority value under the current PRIGROUP.
    fn group(&self, p: i16) -> i16 {
        if p < 0 {
            return p;
        }
        let sub_bits = self.prigroup + 1;
        (p as u16 & (0xFF << sub_bits) & 0xFF) as i16
    }

    fn enabled_exc(&self, e: u32) -> bool {
        match e {
            exc::MEM_MANAGE => self.shcsr & (1 << 16) != 0,
            exc::BUS_FAULT => self.shcsr & (1 << 17) != 0,
            exc::USAGE_FAULT => self.shcsr & (1 << 18) != 0,
            e if e >= exc::IRQ0 => self.enabled & bit(e) != 0,
            _ => true,
        }
    }

    /// The execution priority with `masks` (ignoring PRIMASK when `wake` — WFI wakes on
    /// an interrupt PRIMASK holds off).
    pub fn execution_priority(&self, m: Masks, wake: bool) -> i16 {
        let mut p = THREAD_PRIORITY;
        for &e in &self.stack {
            p = p.min(self.group(self.priority(e)));
        }
        if m.basepri != 0 {
            p = p.min(self.group(m.basepri as i16));
        }
        if m.primask && !wake {
            p = p.min(0);
        }
        if m.faultmask {
            p = p.min(-1);
        }
        p
    }

    /// The pending, enabled exception that would be taken over priority `exec`.
    pub fn preempting(&self, exec: i16) -> Option<u32> {
        let mut best: Option<(i16, i16, u32)> = None;
        let mut p = self.pending;
        while p != 0 {
            let e = p.trailing_zeros();
            p &= p - 1;
            if !self.enabled_exc(e) {
                continue;
            }
            let pr = self.priority(e);
            let key = (self.group(pr), pr, e);
            if key.0 < exec && best.is_none_or(|b| key < b) {
                best = Some(key);
            }
        }
        best.map(|(_, _, e)| e)
    }

    /// The exception to take now, if any.
    pub fn to_take(&self, m: Masks) -> Option<u32> {
        self.preempting(self.execution_priority(m, false))
    }

    /// Whether a sleeping core wakes (an exception would preempt with PRIMASK clear).
    pub fn wakes(&self, m: Masks) -> bool {
        self.preempting(self.execution_priority(m, true)).is_some()
    }

    /// Pending and enabled exceptions, as a bit set (to notice new arrivals).
    pub fn pending_enabled(&self) -> u128 {
        let sys = bit(exc::NMI)
            | bit(exc::HARD_FAULT)
            | bit(exc::SVCALL)
            | bit(exc::PENDSV)
            | bit(exc::SYSTICK)
            | bit(12);
        let faults = (bit(exc::MEM_MANAGE) | bit(exc::BUS_FAULT) | bit(exc::USAGE_FAULT))
            & ((self.shcsr as u128 >> 16) << exc::MEM_MANAGE);
        self.pending & (self.enabled | sys | faults)
    }

    /// Whether anything is pending and enabled (masked or not).
    pub fn anything_pending(&self) -> bool {
        self.preempting(i16::MAX).is_some()
    }

    /// Mark the set `m` pending, noting which were not pending before. Every path that
    /// sets a pending bit goes through here.
    #[inline]
    fn set_pending(&mut self, m: u128) {
        self.rose |= m & !self.pending;
        self.pending |= m;
    }

    /// The exceptions that became pending since the last call (bit `e` = exception
    /// `e`); the set is emptied.
    #[inline]
    pub fn take_rises(&mut self) -> u128 {
        std::mem::take(&mut self.rose)
    }

    /// Mark `e` pending.
    pub fn pend(&mut self, e: u32) {
        if e < SLOTS {
            self.set_pending(bit(e));
        }
    }

    /// Whether `e` is pending.
    pub fn is_pending(&self, e: u32) -> bool {
        self.pending & bit(e) != 0
    }

    /// Whether `e` is active.
    pub fn is_active(&self, e: u32) -> bool {
        self.active & bit(e) != 0
    }

    /// Exception entry: `e` becomes active, no longer pending.
    pub fn activate(&mut self, e: u32) {
        self.pending &= !bit(e);
        self.active |= bit(e);
        self.stack.push(e);
    }

    /// Exception return from `e`: no longer active; a line still asserted pends it again.
    pub fn deactivate(&mut self, e: u32) {
        self.active &= !bit(e);
        if let Some(i) = self.stack.iter().rposition(|&x| x == e) {
            self.stack.remove(i);
        }
        if self.lines & bit(e) != 0 {
            self.set_pending(bit(e));
        }
    }

    /// Active exceptions, outermost first.
    pub fn active_stack(&self) -> &[u32] {
        &self.stack
    }

    /// Set the level of interrupt line `irq` (0-based); asserted lines of inactive
    /// exceptions become pending.
    pub fn set_line(&mut self, irq: u32, high: bool) {
        let e = exc::IRQ0 + irq;
        if e < SLOTS {
            self.set_lines(bit(e), if high { bit(e) } else { 0 });
        }
    }

    /// Every line of `mask` at once: those of `high` high (each pending again unless
    /// active: a level), the rest low.
    pub fn set_lines(&mut self, mask: u128, high: u128) {
        let valid = if SLOTS >= 128 {
            u128::MAX
        } else {
            (1u128 << SLOTS) - 1
        };
        let (mask, high) = (mask & valid, high & mask & valid);
        self.lines = (self.lines & !mask) | high;
        self.set_pending(high & !self.active);
    }

    /// Record a fault's status bits (CFSR) and, for an escalation, HFSR.FORCED.
    pub fn fault_status(&mut self, cfsr: u32, forced: bool, bfar: Option<u32>) {
        self.cfsr |= cfsr;
        if forced {
            self.hfsr |= 1 << 30;
        }
        if let Some(a) = bfar {
            self.bfar = a;
            self.cfsr |= 1 << 15; // BFARVALID
        }
    }

    /// A vector table read error on an exception entry: HFSR.VECTTBL.
    pub fn vector_table_error(&mut self) {
        self.hfsr |= 1 << 1;
    }

    /// The exception a fault of kind `e` (MemManage, BusFault, UsageFault) is taken as:
    /// itself if enabled and of higher priority than `exec`, else HardFault.
    pub fn fault_target(&self, e: u32, exec: i16) -> u32 {
        if self.enabled_exc(e) && self.group(self.priority(e)) < exec {
            e
        } else {
            exc::HARD_FAULT
        }
    }

    /// Whether the MPU is enabled (not modelled: the board refuses to run then).
    pub fn mpu_enabled(&self) -> bool {
        self.mpu_ctrl & 1 != 0
    }

    /// SCR.SLEEPONEXIT.
    pub fn sleep_on_exit(&self) -> bool {
        self.scr & 2 != 0
    }

    fn icsr(&self) -> u32 {
        let vectactive = self.stack.last().copied().unwrap_or(0);
        let vectpending = self.preempting(i16::MAX).unwrap_or(0);
        let mut v = vectactive | (vectpending << 12);
        if self.pending >> exc::IRQ0 != 0 {
            v |= 1 << 22;
        }
        if self.stack.len() <= 1 {
            v |= 1 << 11; // RETTOBASE
        }
        if self.is_pending(exc::SYSTICK) {
            v |= 1 << 26;
        }
        if self.is_pending(exc::PENDSV) {
            v |= 1 << 28;
        }
        if self.is_pending(exc::NMI) {
            v |= 1 << 31;
        }
        v
    }

    fn word_bits(set: u128, word: u32) -> u32 {
        (set >> (exc::IRQ0 + 32 * word)) as u32
    }

    fn irq_mask(word: u32, v: u32) -> u128 {
        let mut m = (v as u128) << (exc::IRQ0 + 32 * word);
        m &= (1u128 << SLOTS) - 1;
        m
    }

    /// Read at `off` from 0xE000_E000 (SysTick and the debug registers excluded).
    pub fn read(&self, off: u32, size: usize) -> Access<u32> {
        let o = off & !3;
        let v = match o {
            0x004 => 2,
            0x008 => self.actlr,
            0x100..=0x11C => Self::word_bits(self.enabled, (o - 0x100) / 4),
            0x180..=0x19C => Self::word_bits(self.enabled, (o - 0x180) / 4),
            0x200..=0x21C => Self::word_bits(self.pending, (o - 0x200) / 4),
            0x280..=0x29C => Self::word_bits(self.pending, (o - 0x280) / 4),
            0x300..=0x31C => Self::word_bits(self.active, (o - 0x300) / 4),
            0x400..=0x450 => {
                let base = exc::IRQ0 + (o - 0x400);
                (0..4).fold(0u32, |acc, i| {
                    acc | (self.prio.get((base + i) as usize).copied().unwrap_or(0) as u32)
                        << (8 * i)
                })
            }
            0xD00 => 0x410F_C241,
            0xD04 => self.icsr(),
            0xD08 => self.vtor,
            0xD0C => 0xFA05_0000 | (self.prigroup << 8),
            0xD10 => self.scr,
            0xD14 => self.ccr,
            0xD18..=0xD20 => {
                let base = 4 + (o - 0xD18);
                (0..4).fold(0u32, |acc, i| {
                    acc | (self.prio[(base + i) as usize] as u32) << (8 * i)
                })
            }
            0xD24 => {
                let mut v = self.shcsr & 0x0007_0000;
                for (e, b) in [(4u32, 0u32), (5, 1), (6, 3), (11, 7), (14, 10), (15, 11)] {
                    if self.is_active(e) {
                        v |= 1 << b;
                    }
                }
                v
            }
            0xD28 => self.cfsr,
            0xD2C => self.hfsr,
            0xD30 => 0,
            0xD34 => self.mmfar,
            0xD38 => self.bfar,
            0xD3C => 0,
            0xD88 => self.cpacr,
            0xD90 => 0x0000_0800,
            0xD94 => self.mpu_ctrl,
            0xD98 => self.mpu_rnr,
            0xD9C => self.mpu_rbar[(self.mpu_rnr & 7) as usize],
            0xDA0 => self.mpu_rasr[(self.mpu_rnr & 7) as usize],
            0xF34 => self.fpccr,
            0xF38 => self.fpcar,
            0xF3C => self.fpdscr,
            0xFD0..=0xFFC => {
                // Peripheral and component IDs of the SCS.
                const ID: [u32; 12] = [4, 0, 0, 0, 0x00, 0xB0, 0x0B, 0x00, 0x0D, 0xE0, 0x05, 0xB1];
                ID[((o - 0xFD0) / 4) as usize]
            }
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off` from 0xE000_E000.
    pub fn write(&mut self, off: u32, size: usize, value: u32) -> Access<()> {
        let o = off & !3;
        match o {
            0x008 => self.actlr = merge(self.actlr, off, size, value) & 0x307,
            0x100..=0x11C => self.enabled |= Self::irq_mask((o - 0x100) / 4, value),
            0x180..=0x19C => self.enabled &= !Self::irq_mask((o - 0x180) / 4, value),
            0x200..=0x21C => self.set_pending(Self::irq_mask((o - 0x200) / 4, value)),
            0x280..=0x29C => {
                self.pending &= !Self::irq_mask((o - 0x280) / 4, value);
                // A still-asserted line pends again at once.
                self.set_pending(self.lines & !self.active);
            }
            0x300..=0x31C => {}
            0x400..=0x450 => {
                let base = exc::IRQ0 + (o - 0x400);
                let old = self.read(o, 4)?;
                let v = merge(old, off, size, value);
                for i in 0..4 {
                    if let Some(p) = self.prio.get_mut((base + i) as usize) {
                        *p = ((v >> (8 * i)) & 0xF0) as u8;
                    }
                }
            }
            0xD04 => {
                let v = merge(0, off, size, value);
                if v & (1 << 31) != 0 {
                    self.pend(exc::NMI);
                }
                if v & (1 << 28) != 0 {
                    self.pend(exc::PENDSV);
                }
                if v & (1 << 27) != 0 {
                    self.pending &= !bit(exc::PENDSV);
                }
                if v & (1 << 26) != 0 {
                    self.pend(exc::SYSTICK);
                }
                if v & (1 << 25) != 0 {
                    self.pending &= !bit(exc::SYSTICK);
                }
            }
            0xD08 => self.vtor = merge(self.vtor, off, size, value) & 0xFFFF_FF80,
            0xD0C => {
                if size == 4 && value >> 16 == 0x05FA {
                    self.prigroup = (value >> 8) & 7;
                    if value & 4 != 0 {
                        self.reset_requested = true;
                    }
                }
            }
            0xD10 => self.scr = merge(self.scr, off, size, value) & 0x16,
            0xD14 => self.ccr = merge(self.ccr, off, size, value) & 0x31B,
            0xD18..=0xD20 => {
                let base = 4 + (o - 0xD18);
                let old = self.read(o, 4)?;
                let v = merge(old, off, size, value);
                for i in 0..4 {
                    let e = (base + i) as usize;
                    if e >= 4 {
                        self.prio[e] = ((v >> (8 * i)) & 0xF0) as u8;
                    }
                }
            }
            0xD24 => self.shcsr = merge(self.shcsr, off, size, value) & 0x0007_0000,
            0xD28 => self.cfsr &= !merge(0, off, size, value),
            0xD2C => self.hfsr &= !merge(0, off, size, value),
            0xD30 | 0xD3C => {}
            0xD34 => self.mmfar = value,
            0xD38 => self.bfar = value,
            0xD88 => self.cpacr = merge(self.cpacr, off, size, value),
            0xD94 => {
                let v = merge(self.mpu_ctrl, off, size, value) & 7;
                if v & 1 != 0 {
                    // Enforcing an MPU is not modelled: refuse rather than pretend.
                    return no_write(off);
                }
                self.mpu_ctrl = v;
            }
            0xD98 => self.mpu_rnr = value & 7,
            0xD9C => {
                if value & 0x10 != 0 {
                    self.mpu_rnr = value & 7;
                }
                self.mpu_rbar[(self.mpu_rnr & 7) as usize] = value & !0x1F;
            }
            0xDA0 => self.mpu_rasr[(self.mpu_rnr & 7) as usize] = value,
            0xF00 => self.pend(exc::IRQ0 + (value & 0x1FF)),
            0xF34 => self.fpccr = merge(self.fpccr, off, size, value),
            0xF38 => self.fpcar = value & !7,
            0xF3C => self.fpdscr = value & 0x07C0_0000,
            _ => return no_write(off),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn priorities_masks_and_preemption() {
        let mut n = Nvic::default();
        // IRQ6 (EXTI0) at priority 0x10, SysTick at 0xF0, USART2 (38) at 0x80.
        n.write(0x100, 4, 1 << 6).unwrap();
        n.write(0x104, 4, 1 << (38 - 32)).unwrap();
        n.write(0x404, 4, 0x10 << 16).unwrap(); // IPR1: IRQ6 in byte 2
        n.write(0x424, 4, 0x80 << 16).unwrap(); // IPR9: IRQ38 in byte 2
        n.write(0xD20, 4, 0xF0 << 24).unwrap(); // SHPR3: SysTick
        n.pend(exc::SYSTICK);
        n.set_line(38, true);
        let m = Masks::default();
        assert_eq!(n.to_take(m), Some(exc::IRQ0 + 38), "USART2 before SysTick");
        n.activate(exc::IRQ0 + 38);
        assert_eq!(n.to_take(m), None, "SysTick cannot preempt USART2");
        n.set_line(6, true);
        assert_eq!(n.to_take(m), Some(exc::IRQ0 + 6), "EXTI0 preempts");
        assert_eq!(
            n.to_take(Masks { basepri: 0x10, ..m }),
            None,
            "BASEPRI holds it"
        );
        assert_eq!(n.to_take(Masks { primask: true, ..m }), None);
        assert!(n.wakes(Masks { primask: true, ..m }), "WFI still wakes");
        n.deactivate(exc::IRQ0 + 38);
        assert!(
            n.is_pending(exc::IRQ0 + 38),
            "line still asserted: pending again"
        );
    }

    #[test]
    fn every_path_that_sets_a_pending_bit_notes_the_rise_once() {
        let tim2 = exc::IRQ0 + 28;
        let mut n = Nvic::default();
        assert_eq!(n.take_rises(), 0);
        // The timer's line: a rise, then nothing while it stays pending.
        n.set_line(28, true);
        assert_eq!(n.take_rises(), bit(tim2));
        n.set_line(28, true);
        n.pend(tim2);
        assert_eq!(n.take_rises(), 0, "already pending");
        // Entered: no longer pending; the line stays asserted, but an active exception
        // is not pended by it — until it returns.
        n.activate(tim2);
        n.set_line(28, true);
        assert_eq!(n.take_rises(), 0);
        n.deactivate(tim2);
        assert_eq!(n.take_rises(), bit(tim2), "still asserted at return");
        // ICPR with the line asserted: cleared and pended again at once (a new pend).
        n.write(0x280, 4, 1 << 28).unwrap();
        assert_eq!(n.take_rises(), bit(tim2));
        n.set_line(28, false);
        n.write(0x280, 4, 1 << 28).unwrap();
        assert_eq!(n.take_rises(), 0);
        assert!(!n.is_pending(tim2));
        // Software: ISPR, STIR, ICSR.PENDSVSET.
        n.write(0x200, 4, 1 << 28).unwrap();
        assert_eq!(n.take_rises(), bit(tim2), "ISPR");
        n.write(0x280, 4, 1 << 28).unwrap();
        n.write(0xF00, 4, 28).unwrap();
        assert_eq!(n.take_rises(), bit(tim2), "STIR");
        n.write(0xD04, 4, 1 << 28).unwrap();
        assert_eq!(n.take_rises(), bit(exc::PENDSV), "ICSR");
        // The log keeps only the watched ones.
        let mut log = EntryLog::default();
        log.watch(tim2);
        log.note_pends(bit(tim2) | bit(exc::PENDSV), 7);
        log.note(exc::PENDSV, 8);
        log.note(tim2, 9);
        assert_eq!(log.pend_times(tim2), vec![7]);
        assert_eq!(log.pends.len(), 1);
        assert_eq!(log.times(tim2), vec![9]);
    }

    #[test]
    fn sysresetreq_needs_the_key() {
        let mut n = Nvic::default();
        n.write(0xD0C, 4, 4).unwrap();
        assert!(!n.reset_requested);
        n.write(0xD0C, 4, 0x05FA_0004).unwrap();
        assert!(n.reset_requested);
    }
}
