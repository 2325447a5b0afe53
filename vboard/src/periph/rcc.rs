//! RCC: reset and clock control (RM0090 §7).
//!
//! Oscillator and PLL ready bits follow their enables after the datasheet's start-up
//! times (HSI 2 µs, HSE 2 ms for the board's 8 MHz crystal, PLL lock 100 µs, LSI 40 µs);
//! the system clock switches only to a ready source, and SWS follows SW. The clock tree
//! (SYSCLK, HCLK, PCLK1/2, timer clocks) is derived from the registers and drives the
//! board's time. `CSR` keeps the reset-cause flags across resets until `RMVF`.
//!
//! | off | name | reset |
//! |---|---|---|
//! | 0x00 | CR | 0x0000_0083 (HSION, HSIRDY, HSITRIM 16) |
//! | 0x04 | PLLCFGR | 0x2400_3010 |
//! | 0x08 | CFGR | 0 |
//! | 0x0C | CIR | 0 |
//! | 0x10–0x24 | AHB1/2/3RSTR, APB1/2RSTR | 0 |
//! | 0x30–0x44 | AHB1ENR (0x0010_0000), AHB2/3ENR, APB1/2ENR | |
//! | 0x50–0x64 | …LPENR | 0x7E67_91FF, 0xF1, 1, 0x36FE_C9FF, 0x0007_5F33 |
//! | 0x70 | BDCR | 0 (backup domain: survives resets) |
//! | 0x74 | CSR | reset flags; LSION/LSIRDY |
//! | 0x80 | SSCGR | 0 |
//! | 0x84 | PLLI2SCFGR | 0x2000_3000 |

use super::{lane, merge, no_read, no_write, Access};

/// HSI frequency, Hz.
pub const HSI_HZ: u64 = 16_000_000;
/// The board's crystal, Hz.
pub const HSE_HZ: u64 = 8_000_000;

const HSI_STARTUP_PS: u64 = 2_000_000;
const HSE_STARTUP_PS: u64 = 2_000_000_000;
const PLL_LOCK_PS: u64 = 100_000_000;
const LSI_STARTUP_PS: u64 = 40_000_000;

/// Reset-cause flags of RCC_CSR.
pub mod csr {
    /// Brown-out reset.
    pub const BORRSTF: u32 = 1 << 25;
    /// NRST pin reset (set by every reset: the internal sources pull NRST low).
    pub const PINRSTF: u32 = 1 << 26;
    /// Power-on / power-down reset.
    pub const PORRSTF: u32 = 1 << 27;
    /// Software reset (AIRCR.SYSRESETREQ).
    pub const SFTRSTF: u32 = 1 << 28;
    /// Independent watchdog reset.
    pub const IWDGRSTF: u32 = 1 << 29;
    /// Window watchdog reset.
    pub const WWDGRSTF: u32 = 1 << 30;
    /// Low-power reset.
    pub const LPWRRSTF: u32 = 1 << 31;
    /// All reset flags.
    pub const ALL: u32 = 0xFE00_0000;
}

/// Why the MCU reset.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum ResetCause {
    /// Power applied.
    PowerOn,
    /// The NRST pin pulled low (a button, a debugger).
    Pin,
    /// The independent watchdog expired.
    Watchdog,
    /// Software (SCB AIRCR.SYSRESETREQ).
    Software,
    /// The supply fell below the brown-out level.
    BrownOut,
    /// A low-power-mode entry with its reset option set.
    LowPower,
}

impl ResetCause {
    /// The CSR flags the reset leaves set.
    pub fn flags(self) -> u32 {
        csr::PINRSTF
            | match self {
                Self::PowerOn => csr::PORRSTF | csr::BORRSTF,
                Self::Pin => 0,
                Self::Watchdog => csr::IWDGRSTF,
                Self::Software => csr::SFTRSTF,
                Self::BrownOut => csr::BORRSTF,
                Self::LowPower => csr::LPWRRSTF,
            }
    }

    /// Stable name (reports).
    pub fn name(self) -> &'static str {
        match self {
            Self::PowerOn => "power_on",
            Self::Pin => "pin",
            Self::Watchdog => "watchdog",
            Self::Software => "software",
            Self::BrownOut => "brown_out",
            Self::LowPower => "low_power",
        }
    }
}

/// The clock tree.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Clocks {
    /// System clock, Hz.
    pub sysclk: u64,
    /// AHB (core) clock, Hz.
    pub hclk: u64,
    /// APB1 clock, Hz.
    pub pclk1: u64,
    /// APB2 clock, Hz.
    pub pclk2: u64,
    /// APB1 timer clock, Hz.
    pub tim1clk: u64,
    /// APB2 timer clock, Hz.
    pub tim2clk: u64,
}

/// The RCC.
#[derive(Clone, Debug)]
pub struct Rcc {
    cr: u32,
    pllcfgr: u32,
    cfgr: u32,
    cir: u32,
    rstr: [u32; 5],
    enr: [u32; 5],
    lpenr: [u32; 5],
    bdcr: u32,
    csr: u32,
    sscgr: u32,
    plli2scfgr: u32,
    /// When each oscillator was switched on (None: off): HSI, HSE, PLL, LSI.
    on_since: [Option<u64>; 4],
    /// The clock tree (derived from CFGR/PLLCFGR; cached: every access asks for it).
    tree: Clocks,
}

const RSTR_OFF: [u32; 5] = [0x10, 0x14, 0x18, 0x20, 0x24];
const ENR_OFF: [u32; 5] = [0x30, 0x34, 0x38, 0x40, 0x44];
const LPENR_OFF: [u32; 5] = [0x50, 0x54, 0x58, 0x60, 0x64];
const LPENR_RESET: [u32; 5] = [0x7E67_91FF, 0xF1, 1, 0x36FE_C9FF, 0x0007_5F33];

/// Bus index of an enable register.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Bus {
    /// AHB1.
    Ahb1 = 0,
    /// AHB2.
    Ahb2 = 1,
    /// AHB3.
    Ahb3 = 2,
    /// APB1.
    Apb1 = 3,
    /// APB2.
    Apb2 = 4,
}

impl Rcc {
    /// At power-on (reset cause flags: power-on).
    pub fn new() -> Self {
        let mut r = Self {
            cr: 0,
            pllcfgr: 0,
            cfgr: 0,
            cir: 0,
            rstr: [0; 5],
            enr: [0; 5],
            lpenr: LPENR_RESET,
            bdcr: 0,
            csr: 0,
            sscgr: 0,
            plli2scfgr: 0,
            on_since: [None; 4],
            tree: Clocks {
                sysclk: HSI_HZ,
                hclk: HSI_HZ,
                pclk1: HSI_HZ,
                pclk2: HSI_HZ,
                tim1clk: HSI_HZ,
                tim2clk: HSI_HZ,
            },
        };
        r.reset(ResetCause::PowerOn, 0);
        r
    }

    /// A system reset at `now` for `cause`: registers to reset values, except the
    /// backup domain and the reset flags, which accumulate.
    pub fn reset(&mut self, cause: ResetCause, now: u64) {
        self.cr = 0x0000_0083;
        self.pllcfgr = 0x2400_3010;
        self.cfgr = 0;
        self.cir = 0;
        self.rstr = [0; 5];
        self.enr = [0x0010_0000, 0, 0, 0, 0];
        self.lpenr = LPENR_RESET;
        self.sscgr = 0;
        self.plli2scfgr = 0x2000_3000;
        // LSI is off after a system reset (the IWDG turns it on again when started).
        self.csr = (self.csr & csr::ALL) | cause.flags();
        if cause == ResetCause::PowerOn {
            self.csr = cause.flags();
            self.bdcr = 0;
        }
        // HSI runs (and is ready) out of reset.
        self.on_since = [Some(now.saturating_sub(HSI_STARTUP_PS)), None, None, None];
        self.tree = self.derive();
    }

    fn ready(&self, i: usize, now: u64) -> bool {
        let startup = [HSI_STARTUP_PS, HSE_STARTUP_PS, PLL_LOCK_PS, LSI_STARTUP_PS][i];
        self.on_since[i].is_some_and(|t| now >= t + startup)
    }

    fn cr_value(&self, now: u64) -> u32 {
        let mut v = self.cr & !((1 << 1) | (1 << 17) | (1 << 25) | (1 << 27));
        if self.ready(0, now) {
            v |= 1 << 1;
        }
        if self.ready(1, now) {
            v |= 1 << 17;
        }
        if self.ready(2, now) {
            v |= 1 << 25;
        }
        if self.cr & (1 << 26) != 0 {
            v |= 1 << 27; // PLLI2S: not used by the image; ready at once
        }
        v
    }

    /// The LSI is on (started by software, or forced on by a running IWDG).
    pub fn force_lsi(&mut self, now: u64) {
        if self.on_since[3].is_none() {
            self.on_since[3] = Some(now);
        }
    }

    fn source_ready(&self, sw: u32, now: u64) -> bool {
        match sw {
            0 => self.ready(0, now),
            1 => self.ready(1, now),
            2 => self.ready(2, now),
            _ => false,
        }
    }

    /// The clock tree now.
    pub fn clocks(&self) -> Clocks {
        self.tree
    }

    fn derive(&self) -> Clocks {
        let sws = (self.cfgr >> 2) & 3;
        let pll_in = if self.pllcfgr & (1 << 22) != 0 {
            HSE_HZ
        } else {
            HSI_HZ
        };
        let m = (self.pllcfgr & 0x3F).max(2) as u64;
        let n = ((self.pllcfgr >> 6) & 0x1FF).max(2) as u64;
        let p = 2 * (((self.pllcfgr >> 16) & 3) as u64 + 1);
        let sysclk = match sws {
            1 => HSE_HZ,
            2 => pll_in / m * n / p,
            _ => HSI_HZ,
        };
        let hpre = (self.cfgr >> 4) & 0xF;
        let ahb_div = if hpre & 8 == 0 {
            1
        } else {
            [2, 4, 8, 16, 64, 128, 256, 512][(hpre & 7) as usize]
        };
        let hclk = sysclk / ahb_div;
        let apb = |ppre: u32| if ppre & 4 == 0 { 1 } else { 2 << (ppre & 3) };
        let d1 = apb((self.cfgr >> 10) & 7);
        let d2 = apb((self.cfgr >> 13) & 7);
        Clocks {
            sysclk,
            hclk,
            pclk1: hclk / d1,
            pclk2: hclk / d2,
            tim1clk: if d1 == 1 { hclk } else { 2 * hclk / d1 },
            tim2clk: if d2 == 1 { hclk } else { 2 * hclk / d2 },
        }
    }

    /// Whether a peripheral's clock is enabled.
    pub fn enabled(&self, bus: Bus, bit: u32) -> bool {
        self.enr[bus as usize] & (1 << bit) != 0
    }

    /// The reset-cause flags now.
    pub fn reset_flags(&self) -> u32 {
        self.csr & csr::ALL
    }

    /// The next instant after `now` at which a ready bit changes (an oscillator or the
    /// PLL becomes ready), ps (`u64::MAX`: none).
    pub fn next_ready_after(&self, now: u64) -> u64 {
        let startup = [HSI_STARTUP_PS, HSE_STARTUP_PS, PLL_LOCK_PS, LSI_STARTUP_PS];
        self.on_since
            .iter()
            .zip(startup)
            .filter_map(|(on, s)| on.map(|t| t + s))
            .filter(|&t| t > now)
            .min()
            .unwrap_or(u64::MAX)
    }

    /// Read at `off` (reads change nothing: the ready bits follow time).
    pub fn read(&mut self, off: u32, size: usize, now: u64) -> Access<u32> {
        self.peek(off, size, now)
    }

    /// Read at `off` at `now`, changing nothing.
    pub fn peek(&self, off: u32, size: usize, now: u64) -> Access<u32> {
        let v = match off & !3 {
            0x00 => self.cr_value(now),
            0x04 => self.pllcfgr,
            0x08 => self.cfgr,
            0x0C => self.cir,
            0x70 => self.bdcr,
            0x74 => {
                let mut v = self.csr & !2;
                if self.ready(3, now) {
                    v |= 2;
                }
                v
            }
            0x80 => self.sscgr,
            0x84 => self.plli2scfgr,
            o => {
                if let Some(i) = RSTR_OFF.iter().position(|&x| x == o) {
                    self.rstr[i]
                } else if let Some(i) = ENR_OFF.iter().position(|&x| x == o) {
                    self.enr[i]
                } else if let Some(i) = LPENR_OFF.iter().position(|&x| x == o) {
                    self.lpenr[i]
                } else {
                    return no_read(off);
                }
            }
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off`. Returns whether the clock tree may have changed.
    pub fn write(&mut self, off: u32, size: usize, value: u32, now: u64) -> Access<bool> {
        let o = off & !3;
        let old = self.read(o, 4, now)?;
        let v = merge(old, off, size, value);
        match o {
            0x00 => {
                // Writable: HSION(0) HSITRIM(7:3) HSEON(16) HSEBYP(18) CSSON(19) PLLON(24)
                // PLLI2SON(26). HSI cannot be stopped while it is the system clock.
                let keep_hsi = (self.cfgr >> 2) & 3 == 0;
                let v = v & 0x050D_00F9 | if keep_hsi { 1 } else { 0 };
                for (i, bit) in [(0usize, 0u32), (1, 16), (2, 24)] {
                    let on = v & (1 << bit) != 0;
                    match (on, self.on_since[i]) {
                        (true, None) => self.on_since[i] = Some(now),
                        (false, Some(_)) => self.on_since[i] = None,
                        _ => {}
                    }
                }
                self.cr = v;
            }
            0x04 => {
                self.pllcfgr = v & 0x0F43_7FFF;
                self.tree = self.derive();
            }
            0x08 => {
                let sw = v & 3;
                // SWS follows SW if the source is ready; otherwise the switch waits.
                let sws = if self.source_ready(sw, now) {
                    sw
                } else {
                    (self.cfgr >> 2) & 3
                };
                self.cfgr = (v & !0xC) | (sws << 2);
                self.tree = self.derive();
                return Ok(true);
            }
            0x0C => self.cir = v & 0x00BF_3F00 & !0x00FF_0000,
            0x70 => self.bdcr = v,
            0x74 => {
                if v & (1 << 24) != 0 {
                    self.csr &= !csr::ALL; // RMVF
                }
                let lsion = v & 1 != 0;
                self.csr = (self.csr & !1) | u32::from(lsion);
                if lsion {
                    self.force_lsi(now);
                }
            }
            0x80 => self.sscgr = v,
            0x84 => self.plli2scfgr = v,
            _ => {
                if let Some(i) = RSTR_OFF.iter().position(|&x| x == o) {
                    self.rstr[i] = v;
                } else if let Some(i) = ENR_OFF.iter().position(|&x| x == o) {
                    self.enr[i] = v;
                } else if let Some(i) = LPENR_OFF.iter().position(|&x| x == o) {
                    self.lpenr[i] = v;
                } else {
                    return no_write(off);
                }
            }
        }
        Ok(false)
    }
}

impl Default for Rcc {
    fn default() -> Self {
        Self::new()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pll_to_168_mhz_and_ready_bits_follow_enables() {
        let mut r = Rcc::new();
        assert_eq!(r.clocks().hclk, HSI_HZ);
        r.write(0x00, 4, 0x0001_0081, 0).unwrap(); // HSEON
        assert_eq!(
            r.read(0x00, 4, 1_000_000).unwrap() & (1 << 17),
            0,
            "HSE not yet up"
        );
        assert_ne!(r.read(0x00, 4, HSE_STARTUP_PS).unwrap() & (1 << 17), 0);
        // HSE / 8 * 336 / 2 = 168 MHz.
        r.write(
            0x04,
            4,
            (1 << 22) | (336 << 6) | 8 | (7 << 24),
            HSE_STARTUP_PS,
        )
        .unwrap();
        r.write(0x00, 4, 0x0101_0081, HSE_STARTUP_PS).unwrap();
        r.write(0x08, 4, 2 | (5 << 10) | (4 << 13), HSE_STARTUP_PS)
            .unwrap();
        assert_eq!(r.clocks().hclk, HSI_HZ, "PLL not locked: no switch");
        let t = HSE_STARTUP_PS + PLL_LOCK_PS;
        r.write(0x08, 4, 2 | (5 << 10) | (4 << 13), t).unwrap();
        let c = r.clocks();
        assert_eq!(
            (c.sysclk, c.hclk, c.pclk1, c.pclk2),
            (168_000_000, 168_000_000, 42_000_000, 84_000_000)
        );
        assert_eq!((c.tim1clk, c.tim2clk), (84_000_000, 168_000_000));
    }

    #[test]
    fn reset_flags_accumulate_until_rmvf() {
        let mut r = Rcc::new();
        assert_eq!(r.reset_flags(), csr::PORRSTF | csr::PINRSTF | csr::BORRSTF);
        r.write(0x74, 4, 1 << 24, 0).unwrap();
        assert_eq!(r.reset_flags(), 0);
        r.reset(ResetCause::Watchdog, 0);
        r.reset(ResetCause::Software, 0);
        assert_eq!(r.reset_flags(), csr::IWDGRSTF | csr::SFTRSTF | csr::PINRSTF);
        assert!(
            r.read(0x1000, 4, 0).is_err(),
            "unmodelled offsets are reported"
        );
    }
}
