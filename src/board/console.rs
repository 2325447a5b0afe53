//! The technician console on USART2 (PA2 TX, PA3 RX, 115200 8N1), interrupt-driven both
//! ways so that the idle loop never waits on the line and the core can sleep.
//!
//! The USART2 interrupt moves each received byte into a 256-entry ring and feeds the
//! transmitter from a 1024-byte ring; the console service takes bytes from one and puts
//! replies into the other ([`ConsoleIo`]).
//!
//! A byte can be lost on the way in: the UART's one-byte data register overruns when
//! the interrupt comes late (it waits on the flash while a record is programmed, up to
//! 100 µs per word; a byte takes 87 µs at 115200 Bd), the line is noisy, or the ring is
//! full. The loss is not silent: a [`LOST`] entry takes the lost bytes' place in the
//! ring, and the console discards the line it spoils (never runs it with a byte
//! missing). Ring entries are `u16`: a byte, or [`LOST`].

use core::sync::atomic::{AtomicU32, Ordering};

use docking_controller::hal::ConsoleIo;
use embedded_hal_nb::serial::{Read as _, Write as _};
use heapless::spsc::{Consumer, Producer};
use stm32f4xx_hal::pac;
use stm32f4xx_hal::serial::{Rx, Tx};

/// Receive errors (framing, noise, overrun) and ring overruns.
pub static RX_ERRORS: AtomicU32 = AtomicU32::new(0);

/// A receive-ring entry that stands for lost input.
pub const LOST: u16 = 0x100;

/// USART2 CR1.TXEIE through the peripheral bit-band alias: one store, no
/// read-modify-write, so the idle loop can set it while the interrupt clears it.
const USART2_CR1_TXEIE_BB: *mut u32 = (0x4200_0000 + 0x440C * 32 + 7 * 4) as *mut u32;

/// The interrupt's side: the UART and the rings' far ends.
pub struct ConsoleIsr {
    /// Receiver.
    pub rx: Rx<pac::USART2>,
    /// Transmitter.
    pub tx: Tx<pac::USART2>,
    /// Received bytes go here.
    pub rx_in: Producer<'static, u16>,
    /// Bytes to send come from here.
    pub tx_out: Consumer<'static, u8>,
    /// Input was lost and its [`LOST`] entry could not be queued yet (the ring was
    /// full).
    pub loss_pending: bool,
}

impl ConsoleIsr {
    /// The USART2 interrupt: receive what arrived, send what is queued.
    pub fn on_interrupt(&mut self) {
        let got = match self.rx.read() {
            Ok(b) => Some(u16::from(b)),
            Err(nb::Error::WouldBlock) => None,
            Err(nb::Error::Other(_)) => {
                RX_ERRORS.fetch_add(1, Ordering::Relaxed);
                self.loss_pending = true;
                None
            }
        };
        if self.loss_pending && self.rx_in.enqueue(LOST).is_ok() {
            self.loss_pending = false;
        }
        if let Some(b) = got {
            // Behind a loss not yet queued, a byte would hide it: it goes too.
            if self.loss_pending || self.rx_in.enqueue(b).is_err() {
                RX_ERRORS.fetch_add(1, Ordering::Relaxed);
                self.loss_pending = true;
            }
        }
        while let Some(&b) = self.tx_out.peek() {
            if self.tx.write(b).is_err() {
                return; // the data register is full: TXE interrupts again
            }
            let _ = self.tx_out.dequeue();
        }
        // Nothing left to send: no more TXE interrupts until the idle loop queues some.
        // SAFETY: a bit-band alias store to USART2 CR1.TXEIE (fixed address).
        unsafe { core::ptr::write_volatile(USART2_CR1_TXEIE_BB, 0) };
    }
}

/// The console service's side.
pub struct BoardConsole {
    /// Received bytes (and [`LOST`] entries).
    pub rx_out: Consumer<'static, u16>,
    /// Bytes to send.
    pub tx_in: Producer<'static, u8>,
}

impl BoardConsole {
    /// Whether received bytes wait for the console service.
    pub fn rx_pending(&self) -> bool {
        !self.rx_out.is_empty()
    }
}

impl ConsoleIo for BoardConsole {
    fn read_byte(&mut self) -> nb::Result<u8, ()> {
        match self.rx_out.dequeue() {
            None => Err(nb::Error::WouldBlock),
            Some(e) => u8::try_from(e).map_err(|_| nb::Error::Other(())),
        }
    }

    fn write(&mut self, bytes: &[u8]) -> usize {
        let mut n = 0;
        for &b in bytes {
            if self.tx_in.enqueue(b).is_err() {
                break;
            }
            n += 1;
        }
        if n > 0 {
            // SAFETY: a bit-band alias store to USART2 CR1.TXEIE (fixed address).
            unsafe { core::ptr::write_volatile(USART2_CR1_TXEIE_BB, 1) };
        }
        n
    }
}
