//! DMA controller (RM0090 §10): DMA1's register map, its eight streams, and the one
//! request the image uses: **USART2_RX on stream 5, channel 4** (RM0090 table 42),
//! peripheral to memory, bytes, in direct mode, normal or circular.
//!
//! * A stream is set up while disabled (`EN` = 0: `CR`'s other bits, `NDTR`, `PAR`,
//!   `M0AR`, `M1AR`, `FCR` are read-only while it runs; a write then is ignored, as on the
//!   part, and reported). Enabling it latches `NDTR` as the reload value.
//! * Each request moves one byte from the peripheral (USART2's `DR`, which clears RXNE)
//!   to `M0AR` + the bytes done (memory increment), at the byte's own time: the DMA
//!   needs no CPU, so it goes on while the core is stalled on a flash program or erase
//!   (RM0090 §3.5: the flash interface stalls the core's fetches, not the bus matrix;
//!   the DMA reaches SRAM meanwhile). The bytes are handed to the board as SRAM writes
//!   ([`Dma::take_writes`]).
//! * `NDTR` counts down; `HTIF` sets when half the items are done, `TCIF` when `NDTR`
//!   reaches 0: in circular mode `NDTR` reloads and the memory address starts again
//!   at `M0AR`; in normal mode the stream disables itself. Disabling an enabled stream
//!   by software sets `TCIF` too (RM0090 §10.3.17).
//! * A destination outside SRAM1/SRAM2 (the CCM RAM and the flash are not on the DMA's
//!   bus) is a transfer error: `TEIF`, and the stream disables itself.
//! * Interrupt line of a stream: `TCIE·TCIF | HTIE·HTIF | TEIE·TEIF | DMEIE·DMEIF |
//!   FCR.FEIE·FEIF`. Flags clear by writing 1 to `LIFCR`/`HIFCR`.
//!
//! Enabling any other stream, channel, direction, data size, double-buffer mode, FIFO
//! mode or peripheral address is not modelled: the access stops the run.
//!
//! | off | name | reset |
//! |---|---|---|
//! | 0x00 / 0x04 | LISR / HISR (streams 0–3 / 4–7: flags at bits 0, 6, 16, 22) | 0 |
//! | 0x08 / 0x0C | LIFCR / HIFCR (write 1 to clear) | — |
//! | 0x10 + 0x18·s | SxCR (EN 0, DMEIE 1, TEIE 2, HTIE 3, TCIE 4, PFCTRL 5, DIR 7:6, CIRC 8, PINC 9, MINC 10, PSIZE 12:11, MSIZE 14:13, PL 17:16, DBM 18, CHSEL 27:25) | 0 |
//! | 0x14 + 0x18·s | SxNDTR (16 bits) | 0 |
//! | 0x18 + 0x18·s | SxPAR | 0 |
//! | 0x1C + 0x18·s | SxM0AR | 0 |
//! | 0x20 + 0x18·s | SxM1AR | 0 |
//! | 0x24 + 0x18·s | SxFCR (FTH 1:0, DMDIS 2, FS 5:3, FEIE 7) | 0x21 |

use super::{lane, merge, no_read, no_write, Access};

/// The stream USART2_RX requests.
pub const USART2_RX_STREAM: usize = 5;
/// Its channel.
pub const USART2_RX_CHANNEL: u32 = 4;
/// USART2's data register, the stream's peripheral address.
pub const USART2_DR: u32 = 0x4000_4404;

/// SRAM1 and SRAM2 (the DMA's reach; not the CCM RAM).
const SRAM: std::ops::Range<u32> = 0x2000_0000..0x2002_0000;

/// Stream flag bits (within the stream's 6-bit group).
pub mod flag {
    /// FIFO error.
    pub const FE: u32 = 1 << 0;
    /// Direct-mode error.
    pub const DME: u32 = 1 << 2;
    /// Transfer error.
    pub const TE: u32 = 1 << 3;
    /// Half transfer.
    pub const HT: u32 = 1 << 4;
    /// Transfer complete.
    pub const TC: u32 = 1 << 5;
    /// All of them.
    pub const ALL: u32 = FE | DME | TE | HT | TC;
}

mod cr {
    pub const EN: u32 = 1 << 0;
    pub const DMEIE: u32 = 1 << 1;
    pub const TEIE: u32 = 1 << 2;
    pub const HTIE: u32 = 1 << 3;
    pub const TCIE: u32 = 1 << 4;
    pub const PFCTRL: u32 = 1 << 5;
    pub const DIR: u32 = 3 << 6;
    pub const CIRC: u32 = 1 << 8;
    pub const PINC: u32 = 1 << 9;
    pub const MINC: u32 = 1 << 10;
    pub const PSIZE: u32 = 3 << 11;
    pub const MSIZE: u32 = 3 << 13;
    pub const DBM: u32 = 1 << 18;
    pub const CHSEL_SHIFT: u32 = 25;
    /// Writable bits.
    pub const MASK: u32 = 0x0FEF_FFFF;
}

const FCR_RESET: u32 = 0x21;
const FCR_FEIE: u32 = 1 << 7;
const FCR_DMDIS: u32 = 1 << 2;

/// Bit offset of stream `s`'s flags within LISR/HISR.
fn flag_shift(s: usize) -> u32 {
    [0, 6, 16, 22][s % 4]
}

/// One stream's registers.
#[derive(Clone, Copy, Debug, Default)]
struct Stream {
    cr: u32,
    ndtr: u32,
    par: u32,
    m0ar: u32,
    m1ar: u32,
    fcr: u32,
    /// NDTR when the stream was enabled (circular mode reloads it).
    reload: u32,
    /// Flags (FE, DME, TE, HT, TC).
    flags: u32,
}

impl Stream {
    fn enabled(&self) -> bool {
        self.cr & cr::EN != 0
    }

    fn irq(&self) -> bool {
        let f = self.flags;
        (self.cr & cr::TCIE != 0 && f & flag::TC != 0)
            || (self.cr & cr::HTIE != 0 && f & flag::HT != 0)
            || (self.cr & cr::TEIE != 0 && f & flag::TE != 0)
            || (self.cr & cr::DMEIE != 0 && f & flag::DME != 0)
            || (self.fcr & FCR_FEIE != 0 && f & flag::FE != 0)
    }
}

/// A DMA controller.
#[derive(Clone, Debug)]
pub struct Dma {
    /// Name (reports).
    pub name: &'static str,
    streams: [Stream; 8],
    /// Bytes written to SRAM that the board has not applied yet: (address, byte).
    writes: Vec<(u32, u8)>,
    /// What software did that the part ignores (reported by the board).
    pub notes: Vec<String>,
    /// Items transferred so far (all streams).
    pub transfers: u64,
    /// Times a stream wrapped in circular mode.
    pub wraps: u64,
}

impl Dma {
    /// A DMA controller at reset.
    pub fn new(name: &'static str) -> Self {
        let mut d = Self {
            name,
            streams: [Stream::default(); 8],
            writes: Vec::new(),
            notes: Vec::new(),
            transfers: 0,
            wraps: 0,
        };
        d.reset();
        d
    }

    /// Registers to reset values (SRAM writes already made stay made).
    pub fn reset(&mut self) {
        for s in &mut self.streams {
            *s = Stream {
                fcr: FCR_RESET,
                ..Stream::default()
            };
        }
    }

    /// The SRAM bytes written since the last call, for the board to store.
    pub fn take_writes(&mut self) -> Vec<(u32, u8)> {
        std::mem::take(&mut self.writes)
    }

    /// Whether SRAM writes wait for the board.
    pub fn has_writes(&self) -> bool {
        !self.writes.is_empty()
    }

    /// The interrupt line of stream `s`.
    pub fn irq(&self, s: usize) -> bool {
        self.streams.get(s).is_some_and(Stream::irq)
    }

    /// Stream `s`'s NDTR now (tests, reports).
    pub fn ndtr(&self, s: usize) -> u32 {
        self.streams.get(s).map_or(0, |x| x.ndtr)
    }

    /// Whether stream 5 is enabled for USART2_RX.
    pub fn usart2_rx_ready(&self) -> bool {
        let s = &self.streams[USART2_RX_STREAM];
        s.enabled() && (s.cr >> cr::CHSEL_SHIFT) & 7 == USART2_RX_CHANNEL
    }

    /// USART2_RX requests a transfer of `byte` (its DR read) at `_t_ps`: whether the
    /// stream took it.
    pub fn usart2_rx(&mut self, _t_ps: u64, byte: u8) -> bool {
        if !self.usart2_rx_ready() {
            return false;
        }
        let s = &mut self.streams[USART2_RX_STREAM];
        let done = s.reload.saturating_sub(s.ndtr);
        let addr = s.m0ar.wrapping_add(done);
        if !SRAM.contains(&addr) {
            s.flags |= flag::TE;
            s.cr &= !cr::EN;
            return false;
        }
        self.writes.push((addr, byte));
        self.transfers += 1;
        s.ndtr -= 1;
        if s.reload >= 2 && s.reload - s.ndtr == s.reload / 2 {
            s.flags |= flag::HT;
        }
        if s.ndtr == 0 {
            s.flags |= flag::TC;
            if s.cr & cr::CIRC != 0 {
                s.ndtr = s.reload;
                self.wraps += 1;
            } else {
                s.cr &= !cr::EN;
            }
        }
        true
    }

    /// Whether enabling stream `s` with `crv` is a configuration the model has.
    fn modelled(&self, s: usize, crv: u32) -> bool {
        let st = &self.streams[s];
        s == USART2_RX_STREAM
            && (crv >> cr::CHSEL_SHIFT) & 7 == USART2_RX_CHANNEL
            && crv & (cr::DIR | cr::PFCTRL | cr::PINC | cr::PSIZE | cr::MSIZE | cr::DBM) == 0
            && crv & cr::MINC != 0
            && st.fcr & FCR_DMDIS == 0
            && st.par == USART2_DR
            && st.ndtr > 0
    }

    /// Read at `off`.
    pub fn read(&mut self, off: u32, size: usize) -> Access<u32> {
        let v = match off & !3 {
            0x00 | 0x04 => {
                let base = if off & !3 == 0 { 0 } else { 4 };
                (0..4).fold(0, |acc, i| {
                    acc | (self.streams[base + i].flags << flag_shift(base + i))
                })
            }
            0x10..=0xCF => {
                let s = ((off & !3) - 0x10) as usize / 0x18;
                let st = &self.streams[s];
                match ((off & !3) - 0x10) % 0x18 {
                    0x00 => st.cr,
                    0x04 => st.ndtr,
                    0x08 => st.par,
                    0x0C => st.m0ar,
                    0x10 => st.m1ar,
                    _ => st.fcr,
                }
            }
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off`.
    pub fn write(&mut self, off: u32, size: usize, value: u32) -> Access<()> {
        match off & !3 {
            0x08 | 0x0C => {
                let base = if off & !3 == 0x08 { 0 } else { 4 };
                let v = merge(0, off, size, value);
                for i in 0..4 {
                    self.streams[base + i].flags &= !((v >> flag_shift(base + i)) & flag::ALL);
                }
            }
            0x10..=0xCF => {
                let s = ((off & !3) - 0x10) as usize / 0x18;
                let reg = ((off & !3) - 0x10) % 0x18;
                let running = self.streams[s].enabled();
                if reg == 0 {
                    let v = merge(self.streams[s].cr, off, size, value) & cr::MASK;
                    if running {
                        if v & cr::EN == 0 {
                            // Disabled by software: the transfer stops, TCIF sets.
                            let st = &mut self.streams[s];
                            st.cr &= !cr::EN;
                            st.flags |= flag::TC;
                        }
                        if (v | cr::EN) != self.streams[s].cr | cr::EN {
                            self.notes.push(format!(
                                "{} stream {s}: CR written while enabled (only EN can change)",
                                self.name
                            ));
                        }
                    } else if v & cr::EN != 0 {
                        if !self.modelled(s, v) {
                            return no_write(off);
                        }
                        if self.streams[s].flags != 0 {
                            self.notes.push(format!(
                                "{} stream {s} enabled with its flags set (RM0090: clear them first)",
                                self.name
                            ));
                        }
                        let st = &mut self.streams[s];
                        st.cr = v;
                        st.reload = st.ndtr;
                    } else {
                        self.streams[s].cr = v;
                    }
                } else if running {
                    self.notes.push(format!(
                        "{} stream {s}: register {:#x} written while enabled (ignored)",
                        self.name,
                        0x10 + 0x18 * s as u32 + reg
                    ));
                } else {
                    let st = &mut self.streams[s];
                    match reg {
                        0x04 => st.ndtr = merge(st.ndtr, off, size, value) & 0xFFFF,
                        0x08 => st.par = merge(st.par, off, size, value),
                        0x0C => st.m0ar = merge(st.m0ar, off, size, value),
                        0x10 => st.m1ar = merge(st.m1ar, off, size, value),
                        _ => {
                            // FS (5:3) is read-only.
                            let v = merge(st.fcr, off, size, value);
                            st.fcr = (st.fcr & 0x38) | (v & 0x87);
                        }
                    }
                }
            }
            _ => return no_write(off),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const S5: u32 = 0x10 + 0x18 * 5;
    const CIRC_RX: u32 = (4 << 25) | (2 << 16) | cr::MINC | cr::CIRC | (0b1111 << 1);

    fn ring(len: u32) -> Dma {
        let mut d = Dma::new("DMA1");
        d.write(S5 + 0x08, 4, USART2_DR).unwrap();
        d.write(S5 + 0x0C, 4, 0x2000_1000).unwrap();
        d.write(S5 + 0x04, 4, len).unwrap();
        d.write(S5, 4, CIRC_RX | cr::EN).unwrap();
        d
    }

    fn hisr(d: &mut Dma) -> u32 {
        (d.read(0x04, 4).unwrap() >> 6) & flag::ALL
    }

    #[test]
    fn a_circular_stream_counts_down_flags_the_halves_and_wraps() {
        let mut d = ring(4);
        for (i, b) in b"abcdef".iter().enumerate() {
            assert!(d.usart2_rx(0, *b));
            let n = d.read(S5 + 0x04, 4).unwrap();
            assert_eq!(n, 4 - (i as u32 + 1) % 4, "NDTR after {} bytes", i + 1);
            if i == 1 {
                assert_eq!(hisr(&mut d), flag::HT);
                assert!(d.irq(5));
                d.write(0x0C, 4, flag::HT << 6).unwrap();
                assert!(!d.irq(5));
            }
            if i == 3 {
                assert_eq!(hisr(&mut d), flag::TC);
                d.write(0x0C, 4, flag::ALL << 6).unwrap();
            }
        }
        let w = d.take_writes();
        let addrs: Vec<u32> = w.iter().map(|&(a, _)| a - 0x2000_1000).collect();
        assert_eq!(addrs, [0, 1, 2, 3, 0, 1]);
        assert_eq!(w[4].1, b'e');
        assert_eq!(d.wraps, 1);
        assert!(d.usart2_rx_ready(), "circular: still running");
    }

    #[test]
    fn a_normal_stream_stops_at_the_end_and_refuses_more() {
        let mut d = ring(2);
        d.write(S5, 4, 0).unwrap(); // disable (TCIF set), then normal mode
        assert_eq!(hisr(&mut d), flag::TC);
        d.write(0x0C, 4, flag::ALL << 6).unwrap();
        d.write(S5 + 0x04, 4, 2).unwrap();
        d.write(S5, 4, (CIRC_RX & !cr::CIRC) | cr::EN).unwrap();
        assert!(d.usart2_rx(0, 1) && d.usart2_rx(0, 2));
        assert!(!d.usart2_rx(0, 3), "stopped after NDTR items");
        assert_eq!(d.read(S5, 4).unwrap() & cr::EN, 0);
    }

    #[test]
    fn a_destination_off_the_dma_bus_is_a_transfer_error() {
        let mut d = Dma::new("DMA1");
        d.write(S5 + 0x08, 4, USART2_DR).unwrap();
        d.write(S5 + 0x0C, 4, 0x1000_0000).unwrap(); // CCM RAM
        d.write(S5 + 0x04, 4, 8).unwrap();
        d.write(S5, 4, CIRC_RX | cr::EN).unwrap();
        assert!(!d.usart2_rx(0, 1));
        assert_eq!(hisr(&mut d), flag::TE);
        assert!(d.irq(5));
        assert!(!d.usart2_rx_ready());
    }

    #[test]
    fn registers_are_read_only_while_the_stream_runs_and_other_streams_are_not_modelled() {
        let mut d = ring(8);
        d.write(S5 + 0x04, 4, 100).unwrap();
        assert_eq!(d.read(S5 + 0x04, 4).unwrap(), 8);
        assert_eq!(d.notes.len(), 1);
        let s2 = 0x10 + 0x18 * 2;
        d.write(s2 + 0x08, 4, USART2_DR).unwrap();
        d.write(s2 + 0x04, 4, 8).unwrap();
        assert!(d.write(s2, 4, CIRC_RX | cr::EN).is_err());
    }
}
