//! USART (RM0090 §30), asynchronous mode: a **one-byte receive data register** and a
//! transmit data register in front of a shift register, at the baud rate `BRR` gives
//! from the bus clock, as the part has.
//!
//! * Receive: the far end's bytes arrive at its line rate (one frame each). A byte that
//!   arrives while `RXNE` is still set is lost and sets `ORE` (the old byte stays). A far
//!   end whose baud rate differs from ours by more than 3 %, or whose frame has another
//!   length (8N1 against 8E1), produces framing errors.
//!   `RXNE` clears on a `DR` read; `ORE`/`FE`/`NF`/`PE` clear by an `SR` read that saw
//!   them followed by a `DR` read (a flag that rose after the `SR` read stays).
//! * Receive by DMA (`CR3.DMAR`, on a USART whose RX request is wired to a stream: USART2
//!   only, [`Usart::dma_rx_wired`]): each byte that sets `RXNE` is read from `DR` by the
//!   DMA at once (the stream's [`super::dma`] takes it), so nothing overruns while the
//!   stream runs, however late the CPU is. The error flags stay for the CPU (with
//!   `CR3.EIE` they interrupt). The `RXNE` of a byte the DMA took lasted an instant: with
//!   `RXNEIE` the NVIC latched it ([`Usart::take_irq_pulse`]).
//! * Transmit: a `DR` write moves to the shift register at once if it is idle (`TXE`
//!   stays set), else waits in `DR` (`TXE` clear); a frame takes 10 (8N1) or 11 (9-bit
//!   word: 8 data + parity) bit times; `TC` sets when the shift register empties with
//!   nothing waiting. Sent bytes go to the far end with their time.
//! * Interrupt line: `RXNEIE·(RXNE|ORE) | TXEIE·TXE | TCIE·TC | PEIE·PE |
//!   EIE·DMAR·(FE|NF|ORE)`. Transmission by DMA (`CR3.DMAT`) is not modelled.
//!
//! | off | name | reset |
//! |---|---|---|
//! | 0x00 | SR | 0x0000_00C0 (TXE, TC) |
//! | 0x04 | DR | 0 |
//! | 0x08 | BRR | 0 |
//! | 0x0C | CR1 | 0 (RE 2, TE 3, RXNEIE 5, TCIE 6, TXEIE 7, PCE 10, M 12, UE 13, OVER8 15) |
//! | 0x10 | CR2 | 0 |
//! | 0x14 | CR3 | 0 (EIE 0, DMAR 6, DMAT 7) |
//! | 0x18 | GTPR | 0 |

use std::collections::VecDeque;

use super::{lane, merge, no_read, no_write, Access};
use crate::time::PS_PER_S;

mod bit {
    pub const PE: u32 = 1 << 0;
    pub const FE: u32 = 1 << 1;
    pub const NF: u32 = 1 << 2;
    pub const ORE: u32 = 1 << 3;
    pub const RXNE: u32 = 1 << 5;
    pub const TC: u32 = 1 << 6;
    pub const TXE: u32 = 1 << 7;
}

/// A USART and its far end.
#[derive(Clone, Debug)]
pub struct Usart {
    /// Name (reports).
    pub name: &'static str,
    sr: u32,
    dr_rx: u8,
    brr: u32,
    cr1: u32,
    cr2: u32,
    cr3: u32,
    gtpr: u32,
    /// SR was read since the last DR read (for clearing TC).
    sr_read: bool,
    /// The error flags that SR read saw (a DR read clears them).
    sr_seen: u32,
    /// RXNE rose and the DMA read DR at once, with RXNEIE set: the NVIC latched it.
    irq_pulse: bool,
    /// Its RX request is wired to a DMA stream (CR3.DMAR may be set).
    pub dma_rx_wired: bool,
    /// Byte in the transmit data register, waiting for the shift register.
    tx_dr: Option<u8>,
    /// The shift register: byte and the time its stop bit ends.
    tx_shift: Option<(u8, u64)>,
    /// The far end's bytes, with the time each frame ends.
    rx_line: VecDeque<(u64, u8)>,
    /// When the far end's last queued frame ends.
    rx_line_end: u64,
    /// Far end's baud rate.
    pub far_baud: u32,
    /// Far end's frame, bits (10: 8N1; 11: 8E1 or 8N2). A receiver set to another
    /// frame length sees framing errors.
    pub far_bits: u64,
    /// Bytes sent to the far end, with the time each frame ended.
    pub sent: Vec<(u64, u8)>,
    /// Bytes lost to overrun.
    pub overruns: u64,
    /// Bytes received with a framing error (baud mismatch).
    pub framing_errors: u64,
}

impl Usart {
    /// A USART at reset whose far end talks at `far_baud`.
    pub fn new(name: &'static str, far_baud: u32) -> Self {
        let mut u = Self {
            name,
            sr: 0,
            dr_rx: 0,
            brr: 0,
            cr1: 0,
            cr2: 0,
            cr3: 0,
            gtpr: 0,
            sr_read: false,
            sr_seen: 0,
            irq_pulse: false,
            dma_rx_wired: false,
            tx_dr: None,
            tx_shift: None,
            rx_line: VecDeque::new(),
            rx_line_end: 0,
            far_baud,
            far_bits: 10,
            sent: Vec::new(),
            overruns: 0,
            framing_errors: 0,
        };
        u.reset();
        u
    }

    /// The far end's frame length, bits (10: 8N1, 11: 8E1).
    pub fn with_far_bits(mut self, bits: u64) -> Self {
        self.far_bits = bits;
        self
    }

    /// Registers to reset values (a frame on the line is lost; the far end keeps its
    /// queue).
    pub fn reset(&mut self) {
        self.sr = bit::TXE | bit::TC;
        self.dr_rx = 0;
        self.brr = 0;
        self.cr1 = 0;
        self.cr2 = 0;
        self.cr3 = 0;
        self.gtpr = 0;
        self.sr_read = false;
        self.sr_seen = 0;
        self.irq_pulse = false;
        self.tx_dr = None;
        self.tx_shift = None;
    }

    fn enabled(&self) -> bool {
        self.cr1 & (1 << 13) != 0
    }

    /// Our baud rate at bus clock `pclk`, from BRR (0 when unset).
    pub fn baud(&self, pclk: u64) -> u64 {
        let over8 = self.cr1 & (1 << 15) != 0;
        let mant = (self.brr >> 4) as u64;
        let frac = (self.brr & 0xF) as u64;
        // USARTDIV = mant + frac/16 (OVER8 = 0) or mant + frac/8 (OVER8 = 1).
        let div16 = if over8 {
            mant * 16 + (frac & 7) * 2
        } else {
            mant * 16 + frac
        };
        if div16 == 0 {
            return 0;
        }
        let per = if over8 { 8 } else { 16 };
        pclk * 16 / (div16 * per)
    }

    fn bits_per_frame(&self) -> u64 {
        // Start + 8 or 9 data (M) + stop (CR2.STOP: 1 assumed; 2 adds one).
        let stop = if (self.cr2 >> 12) & 3 == 2 { 2 } else { 1 };
        1 + if self.cr1 & (1 << 12) != 0 { 9 } else { 8 } + stop
    }

    /// Duration of one frame at our baud rate, ps.
    fn frame_ps(&self, pclk: u64) -> u64 {
        let b = self.baud(pclk).max(1);
        self.bits_per_frame() * PS_PER_S / b
    }

    /// The far end sends `bytes` at its line rate, starting no earlier than `now`.
    pub fn far_send(&mut self, bytes: &[u8], now: u64) {
        let frame = self.far_bits * PS_PER_S / self.far_baud.max(1) as u64;
        let mut t = self.rx_line_end.max(now);
        for &b in bytes {
            t += frame;
            self.rx_line.push_back((t, b));
        }
        self.rx_line_end = t;
    }

    /// Bytes the far end has queued that have not arrived yet.
    pub fn far_pending(&self) -> usize {
        self.rx_line.len()
    }

    /// The far end goes away: the bytes it queued that have not arrived (the one on the
    /// wire included) never do. Returns how many were dropped.
    pub fn far_cancel(&mut self, now: u64) -> usize {
        let n = self.rx_line.len();
        self.rx_line.clear();
        self.rx_line_end = self.rx_line_end.min(now);
        n
    }

    /// Everything sent so far (drained).
    pub fn take_sent(&mut self) -> Vec<(u64, u8)> {
        std::mem::take(&mut self.sent)
    }

    /// Its RX request is wired to a DMA stream.
    pub fn with_dma_rx(mut self) -> Self {
        self.dma_rx_wired = true;
        self
    }

    /// Bring the line up to `now` at bus clock `pclk` (no DMA stream: with `CR3.DMAR`
    /// set, no request is served).
    pub fn sync(&mut self, now: u64, pclk: u64) {
        self.sync_dma(now, pclk, &mut |_, _| false);
    }

    /// Whether `CR3.DMAR` is set.
    fn dmar(&self) -> bool {
        self.cr3 & (1 << 6) != 0
    }

    /// The byte waiting in `DR` for a DMA request (`RXNE` with `CR3.DMAR`).
    pub fn dma_request(&self) -> Option<u8> {
        (self.dmar() && self.sr & bit::RXNE != 0).then_some(self.dr_rx)
    }

    /// The DMA read `DR` (it took the byte [`Usart::dma_request`] offered).
    pub fn dma_read(&mut self) {
        self.read_dr();
        if self.cr1 & (1 << 5) != 0 {
            self.irq_pulse = true;
        }
    }

    /// Whether an RXNE the DMA cleared at once pended the interrupt since the last call.
    pub fn take_irq_pulse(&mut self) -> bool {
        std::mem::take(&mut self.irq_pulse)
    }

    /// A read of `DR` (by the CPU or the DMA): `RXNE` clears, and the error flags the
    /// last `SR` read saw.
    fn read_dr(&mut self) -> u32 {
        let v = self.dr_rx as u32;
        self.sr &= !bit::RXNE;
        if self.sr_read {
            self.sr &= !self.sr_seen;
        }
        self.sr_read = false;
        self.sr_seen = 0;
        v
    }

    /// Bring the line up to `now` at bus clock `pclk`; each byte that arrives with
    /// `CR3.DMAR` set is offered to `dma` (its time, the byte), which says whether a
    /// stream took it.
    pub fn sync_dma(&mut self, now: u64, pclk: u64, dma: &mut dyn FnMut(u64, u8) -> bool) {
        // Receive.
        while let Some(&(t, b)) = self.rx_line.front() {
            if t > now {
                break;
            }
            self.rx_line.pop_front();
            if !self.enabled() || self.cr1 & (1 << 2) == 0 {
                continue; // receiver off: the byte is not seen
            }
            let ours = self.baud(pclk) as i64;
            let far = self.far_baud as i64;
            let mismatch =
                (ours - far).abs() * 100 > far * 3 || self.bits_per_frame() != self.far_bits;
            if self.sr & bit::RXNE != 0 {
                self.sr |= bit::ORE;
                self.overruns += 1;
                continue;
            }
            self.dr_rx = if mismatch { b ^ 0x5A } else { b };
            if mismatch {
                self.sr |= bit::FE;
                self.framing_errors += 1;
            }
            self.sr |= bit::RXNE;
            if self.dmar() && dma(t, self.dr_rx) {
                self.dma_read();
            }
        }
        // Transmit.
        while let Some((b, end)) = self.tx_shift {
            if end > now {
                break;
            }
            self.sent.push((end, b));
            self.tx_shift = self.tx_dr.take().map(|n| (n, end + self.frame_ps(pclk)));
            if self.tx_shift.is_some() {
                self.sr |= bit::TXE;
            } else {
                self.sr |= bit::TC;
            }
        }
    }

    /// The next time the line changes something software can see, ps.
    pub fn next_event(&self) -> Option<u64> {
        let rx = if self.enabled() && self.cr1 & (1 << 2) != 0 {
            self.rx_line.front().map(|&(t, _)| t)
        } else {
            None
        };
        let tx = self.tx_shift.map(|(_, t)| t);
        match (rx, tx) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        }
    }

    /// The interrupt line.
    pub fn irq(&self) -> bool {
        let cr1 = self.cr1;
        (cr1 & (1 << 5) != 0 && self.sr & (bit::RXNE | bit::ORE) != 0)
            || (cr1 & (1 << 7) != 0 && self.sr & bit::TXE != 0)
            || (cr1 & (1 << 6) != 0 && self.sr & bit::TC != 0)
            || (cr1 & (1 << 8) != 0 && self.sr & bit::PE != 0)
            || (self.cr3 & 1 != 0 && self.dmar() && self.sr & (bit::FE | bit::NF | bit::ORE) != 0)
    }

    /// What a read at `off` returns until the line's next event, read again and again
    /// after a first read (`SR`: its error flags are then already noted as seen; the
    /// control registers). `None`: `DR` (a read takes the byte) and the rest.
    pub fn peek(&self, off: u32, size: usize) -> Option<u32> {
        let v = match off & !3 {
            0x00 if self.sr_read
                && self.sr_seen == self.sr & (bit::ORE | bit::FE | bit::NF | bit::PE) =>
            {
                self.sr
            }
            0x08 => self.brr,
            0x0C => self.cr1,
            0x10 => self.cr2,
            0x14 => self.cr3,
            0x18 => self.gtpr,
            _ => return None,
        };
        Some(lane(v, off, size))
    }

    /// Read at `off`.
    pub fn read(&mut self, off: u32, size: usize, now: u64, pclk: u64) -> Access<u32> {
        self.sync(now, pclk);
        let v = match off & !3 {
            0x00 => {
                self.sr_read = true;
                self.sr_seen = self.sr & (bit::ORE | bit::FE | bit::NF | bit::PE);
                self.sr
            }
            0x04 => self.read_dr(),
            0x08 => self.brr,
            0x0C => self.cr1,
            0x10 => self.cr2,
            0x14 => self.cr3,
            0x18 => self.gtpr,
            _ => return no_read(off),
        };
        Ok(lane(v, off, size))
    }

    /// Write at `off`.
    pub fn write(&mut self, off: u32, size: usize, value: u32, now: u64, pclk: u64) -> Access<()> {
        self.sync(now, pclk);
        match off & !3 {
            0x00 => {
                // rc_w0 for RXNE, TC, LBD, CTS; the rest read-only.
                let v = merge(0xFFFF_FFFF, off, size, value);
                self.sr &= v | !(bit::RXNE | bit::TC | (1 << 8) | (1 << 9));
            }
            0x04 => {
                let b = value as u8;
                if self.enabled() && self.cr1 & (1 << 3) != 0 {
                    if self.tx_shift.is_none() {
                        self.tx_shift = Some((b, now + self.frame_ps(pclk)));
                        self.sr &= !bit::TC;
                    } else if self.tx_dr.is_none() {
                        self.tx_dr = Some(b);
                        self.sr &= !(bit::TXE | bit::TC);
                    }
                    // A write while TXE is clear overwrites nothing useful: the byte is lost,
                    // as on the part.
                }
                if self.sr_read {
                    self.sr &= !bit::TC;
                }
            }
            0x08 => self.brr = merge(self.brr, off, size, value) & 0xFFFF,
            0x0C => self.cr1 = merge(self.cr1, off, size, value) & 0xBFFF,
            0x10 => self.cr2 = merge(self.cr2, off, size, value) & 0x7F7F,
            0x14 => {
                let v = merge(self.cr3, off, size, value) & 0x0FFF;
                // DMA transmission, or reception with no stream wired: not modelled.
                if v & (1 << 7) != 0 || (v & (1 << 6) != 0 && !self.dma_rx_wired) {
                    return no_write(off);
                }
                self.cr3 = v;
            }
            0x18 => self.gtpr = merge(self.gtpr, off, size, value) & 0xFFFF,
            _ => return no_write(off),
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const PCLK: u64 = 42_000_000;

    fn at_115200() -> Usart {
        let mut u = Usart::new("USART2", 115_200);
        // 42 MHz / 115200 / 16 = 22.786 → mantissa 22, fraction 13.
        u.write(0x08, 4, (22 << 4) | 13, 0, PCLK).unwrap();
        u.write(0x0C, 4, (1 << 13) | (1 << 3) | (1 << 2), 0, PCLK)
            .unwrap();
        u
    }

    #[test]
    fn one_byte_receive_register_overruns() {
        let mut u = at_115200();
        assert_eq!(u.baud(PCLK), 115_068, "22 + 13/16: −0.11 %");
        u.far_send(b"ab", 0);
        let frame = 10 * PS_PER_S / 115_200;
        assert_eq!(u.read(0x00, 4, frame - 1, PCLK).unwrap() & bit::RXNE, 0);
        assert_ne!(
            u.read(0x00, 4, 2 * frame, PCLK).unwrap() & bit::ORE,
            0,
            "b lost"
        );
        assert_eq!(u.read(0x04, 4, 2 * frame, PCLK).unwrap(), b'a' as u32);
        assert_eq!(
            u.read(0x00, 4, 2 * frame, PCLK).unwrap() & (bit::ORE | bit::RXNE),
            0
        );
        assert_eq!(u.overruns, 1);
    }

    #[test]
    fn transmit_takes_a_frame_per_byte() {
        let mut u = at_115200();
        u.write(0x04, 4, b'x' as u32, 0, PCLK).unwrap();
        u.write(0x04, 4, b'y' as u32, 0, PCLK).unwrap();
        assert_eq!(u.read(0x00, 4, 0, PCLK).unwrap() & (bit::TXE | bit::TC), 0);
        let frame = 10 * PS_PER_S / 115_068 + 1;
        u.sync(2 * frame + 10, PCLK);
        assert_eq!(
            u.take_sent().iter().map(|&(_, b)| b).collect::<Vec<_>>(),
            b"xy"
        );
        assert_ne!(u.read(0x00, 4, 2 * frame + 10, PCLK).unwrap() & bit::TC, 0);
    }

    #[test]
    fn a_wrong_baud_rate_gives_framing_errors() {
        let mut u = at_115200();
        u.far_baud = 9_600;
        u.far_send(b"z", 0);
        u.sync(PS_PER_S, PCLK);
        assert_ne!(u.read(0x00, 4, PS_PER_S, PCLK).unwrap() & bit::FE, 0);
    }

    #[test]
    fn with_dmar_the_dma_takes_every_byte_and_the_error_flags_stay_for_the_cpu() {
        let mut u = at_115200().with_dma_rx();
        u.write(0x0C, 4, (1 << 13) | (1 << 5) | (1 << 3) | (1 << 2), 0, PCLK)
            .unwrap(); // RXNEIE
        u.write(0x14, 4, (1 << 6) | 1, 0, PCLK).unwrap(); // DMAR, EIE
        let frame = 10 * PS_PER_S / 115_200;
        u.far_send(b"abc", 0);
        let mut took = Vec::new();
        // The CPU looks only after all three arrived (it was stalled): nothing overran.
        u.sync_dma(10 * frame, PCLK, &mut |_, b| {
            took.push(b);
            true
        });
        assert_eq!(took, b"abc");
        assert_eq!(u.overruns, 0);
        assert!(u.take_irq_pulse(), "RXNE pended the interrupt");
        assert!(!u.irq(), "RXNE already cleared by the DMA");
        // A framing error: the byte goes to the DMA, FE stays and interrupts (EIE).
        u.far_baud = 9_600;
        u.far_send(b"z", 10 * frame);
        u.sync_dma(PS_PER_S, PCLK, &mut |_, _| true);
        assert!(u.irq());
        let sr = u.read(0x00, 4, PS_PER_S, PCLK).unwrap();
        assert_eq!(sr & (bit::FE | bit::RXNE), bit::FE);
        u.read(0x04, 4, PS_PER_S, PCLK).unwrap();
        assert!(!u.irq(), "SR then DR cleared it");
        // USART3 has no stream: DMAR there is not modelled.
        let mut u3 = at_115200();
        assert!(u3.write(0x14, 4, 1 << 6, 0, PCLK).is_err());
    }

    #[test]
    fn an_error_flag_that_rose_after_the_sr_read_survives_the_dr_read() {
        let mut u = at_115200();
        u.far_baud = 9_600;
        u.read(0x00, 4, 0, PCLK).unwrap();
        u.far_send(b"z", 0);
        u.sync(PS_PER_S, PCLK);
        u.read(0x04, 4, PS_PER_S, PCLK).unwrap();
        assert_ne!(u.read(0x00, 4, PS_PER_S, PCLK).unwrap() & bit::FE, 0);
    }

    #[test]
    fn a_far_end_that_leaves_takes_its_queued_bytes_with_it() {
        let mut u = at_115200();
        let frame = 10 * PS_PER_S / 115_200;
        u.far_send(b"abc", 0);
        // 'a' has arrived; 'b' is on the wire, 'c' queued.
        u.sync(frame + frame / 2, PCLK);
        assert_eq!(u.far_cancel(frame + frame / 2), 2);
        assert_eq!(u.read(0x04, 4, 10 * frame, PCLK).unwrap(), b'a' as u32);
        assert_eq!(u.read(0x00, 4, 10 * frame, PCLK).unwrap() & bit::RXNE, 0);
        // The next far end's bytes start from now, not after the dropped ones.
        u.far_send(b"d", 10 * frame);
        u.sync(11 * frame, PCLK);
        assert_eq!(u.read(0x04, 4, 11 * frame, PCLK).unwrap(), b'd' as u32);
    }
}
