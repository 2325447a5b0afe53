//! The PLC's Modbus RTU line on USART3 (PB10 TX, PB11 RX, alternate function 7) through
//! an RS-485 transceiver whose driver PB14 enables (DE, high = we drive the bus; the
//! board's pull-down keeps it off through a reset). 19200 8E1 unless a technician stored
//! other settings (console `modbus`).
//!
//! The USART3 interrupt stamps each received character with the microsecond clock and
//! queues it (a character with a parity, framing, noise or overrun error as
//! [`LINE_ERROR`]): the RTU framer measures its t1.5 / t3.5 silences from those stamps,
//! not from when the idle loop gets round to them. The idle loop feeds the server and
//! stays awake while a request is being received (at most t3.5 after its last
//! character: 2 ms at 19200 Bd), so a reply is not held back to the next control step.
//!
//! Sending: the idle loop raises DE, queues the reply and enables TXE interrupts; the
//! interrupt feeds the data register, then waits for TC (the last stop bit out) and
//! drops DE — never earlier (the last character would be cut), never much later (the
//! master's next request would collide with our driver).

use core::sync::atomic::{AtomicU32, Ordering};

use embedded_hal_nb::serial::{Read as _, Write as _};
use heapless::spsc::{Consumer, Producer};
use stm32f4xx_hal::pac;
use stm32f4xx_hal::serial::{Rx, Tx};

/// A receive-queue entry's character that stands for a character received with an
/// error.
pub const LINE_ERROR: u16 = 0x100;

/// Characters lost because the receive queue was full.
pub static RX_DROPPED: AtomicU32 = AtomicU32::new(0);

const USART3_BASE: usize = 0x4000_4800;
const SR: *const u32 = USART3_BASE as *const u32;
const CR1: *const u32 = (USART3_BASE + 0x0C) as *const u32;
const SR_TC: u32 = 1 << 6;
const CR1_TCIE: u32 = 1 << 6;
/// USART3 CR1 bits through the peripheral bit-band alias (one store each, no
/// read-modify-write between the idle loop and the interrupt).
const fn cr1_bb(bit: usize) -> *mut u32 {
    (0x4200_0000 + (USART3_BASE - 0x4000_0000 + 0x0C) * 32 + bit * 4) as *mut u32
}
const TXEIE_BB: *mut u32 = cr1_bb(7);
const TCIE_BB: *mut u32 = cr1_bb(6);
/// GPIOB BSRR: PB14 (DE) set / reset.
const GPIOB_BSRR: *mut u32 = 0x4002_0418 as *mut u32;
const DE_HIGH: u32 = 1 << 14;
/// GPIOB ODR (PB14 = DE).
const GPIOB_ODR: *const u32 = 0x4002_0414 as *const u32;
const DE_LOW: u32 = 1 << (14 + 16);

/// The interrupt's side.
pub struct ModbusIsr {
    /// Receiver.
    pub rx: Rx<pac::USART3>,
    /// Transmitter.
    pub tx: Tx<pac::USART3>,
    /// Received characters with their time (µs).
    pub rx_in: Producer<'static, (u16, u64)>,
    /// The reply being sent.
    pub tx_out: Consumer<'static, u8>,
}

impl ModbusIsr {
    /// The USART3 interrupt.
    pub fn on_interrupt(&mut self) {
        let got = match self.rx.read() {
            Ok(b) => Some(u16::from(b)),
            Err(nb::Error::WouldBlock) => None,
            Err(nb::Error::Other(_)) => Some(LINE_ERROR),
        };
        if let Some(c) = got {
            if self.rx_in.enqueue((c, super::clock::now_us())).is_err() {
                RX_DROPPED.fetch_add(1, Ordering::Relaxed);
            }
        }
        let mut wrote = false;
        while let Some(&b) = self.tx_out.peek() {
            if self.tx.write(b).is_err() {
                return; // the data register is full: TXE interrupts again
            }
            let _ = self.tx_out.dequeue();
            wrote = true;
        }
        // SAFETY: reads of USART3 SR / CR1 and bit-band stores to CR1's TXEIE / TCIE and
        // GPIOB's BSRR (fixed addresses of this chip; PB14 is ours).
        unsafe {
            // All queued: no more TXE interrupts; wait for the last stop bit (TC).
            core::ptr::write_volatile(TXEIE_BB, 0);
            if wrote {
                core::ptr::write_volatile(TCIE_BB, 1);
            } else if core::ptr::read_volatile(CR1) & CR1_TCIE != 0
                && core::ptr::read_volatile(SR) & SR_TC != 0
            {
                // The last character is out: release the bus.
                core::ptr::write_volatile(GPIOB_BSRR, DE_LOW);
                core::ptr::write_volatile(TCIE_BB, 0);
            }
        }
    }
}

/// [`ModbusLine::sending`], from anywhere (the pin is the truth: the update's flash
/// jobs read it at each try, `update.rs`).
pub fn line_driven() -> bool {
    // SAFETY: read of GPIOB's ODR, a fixed MMIO address.
    unsafe { core::ptr::read_volatile(GPIOB_ODR) & DE_HIGH != 0 }
}

/// The idle loop's side.
pub struct ModbusLine {
    /// Received characters.
    pub rx_out: Consumer<'static, (u16, u64)>,
    /// Reply bytes to send.
    pub tx_in: Producer<'static, u8>,
}

impl ModbusLine {
    /// Whether received characters wait.
    pub fn rx_pending(&self) -> bool {
        !self.rx_out.is_empty()
    }

    /// The next received character and its time: `Ok(byte)` or `Err(())` for a line
    /// error.
    pub fn next(&mut self) -> Option<(Result<u8, ()>, u64)> {
        self.rx_out
            .dequeue()
            .map(|(c, t)| (u8::try_from(c).map_err(|_| ()), t))
    }

    /// Whether a reply is on the line: the RS-485 driver is enabled (DE high from
    /// [`Self::send`] until the last stop bit is out). The flash waits meanwhile.
    pub fn sending(&self) -> bool {
        line_driven()
    }

    /// Send `reply`: DE high, the bytes queued, TXE interrupts on. A reply that does not
    /// fit the queue is not sent at all (a cut frame would only fail its CRC).
    pub fn send(&mut self, reply: &[u8]) {
        if self.tx_in.capacity() - self.tx_in.len() < reply.len() {
            return;
        }
        // SAFETY: GPIOB BSRR (PB14 is ours) and a bit-band store to USART3 CR1.TXEIE.
        unsafe { core::ptr::write_volatile(GPIOB_BSRR, DE_HIGH) };
        for &b in reply {
            let _ = self.tx_in.enqueue(b);
        }
        // SAFETY: as above.
        unsafe { core::ptr::write_volatile(TXEIE_BB, 1) };
    }
}
