//! The technician console on USART2 (PA2 TX, PA3 RX, 115200 8N1), interrupt-driven both
//! ways so that the idle loop never waits on the line and the core can sleep.
//!
//! The USART2 interrupt moves each received byte into a 256-byte ring (a byte that
//! arrives while the ring is full is counted and lost, as on any UART without flow
//! control) and feeds the transmitter from a 1024-byte ring; the console service takes
//! bytes from one and puts replies into the other ([`ConsoleIo`]).

use core::sync::atomic::{AtomicU32, Ordering};

use docking_controller::hal::ConsoleIo;
use embedded_hal_nb::serial::{Read as _, Write as _};
use heapless::spsc::{Consumer, Producer};
use stm32f4xx_hal::pac;
use stm32f4xx_hal::serial::{Rx, Tx};

/// Receive errors (framing, noise, overrun) and ring overruns.
pub static RX_ERRORS: AtomicU32 = AtomicU32::new(0);

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
    pub rx_in: Producer<'static, u8>,
    /// Bytes to send come from here.
    pub tx_out: Consumer<'static, u8>,
}

impl ConsoleIsr {
    /// The USART2 interrupt: receive what arrived, send what is queued.
    pub fn on_interrupt(&mut self) {
        match self.rx.read() {
            Ok(b) => {
                if self.rx_in.enqueue(b).is_err() {
                    RX_ERRORS.fetch_add(1, Ordering::Relaxed);
                }
            }
            Err(nb::Error::WouldBlock) => {}
            Err(nb::Error::Other(_)) => {
                RX_ERRORS.fetch_add(1, Ordering::Relaxed);
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
    /// Received bytes.
    pub rx_out: Consumer<'static, u8>,
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
        self.rx_out.dequeue().ok_or(nb::Error::WouldBlock)
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
