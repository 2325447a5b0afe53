//! The simulated serial link: a [`ConsoleIo`] byte stream like the board's USART2 with
//! its interrupt-fed receive ring (256 entries: bytes beyond it are lost, an overrun,
//! and the loss is reported in their place as the board's ring does) and a transmit
//! ring drained by the terminal.

use std::collections::VecDeque;

use docking_logic::hal::ConsoleIo;

/// Receive ring of the board's console UART, bytes.
pub const RX_RING: usize = 256;
/// Transmit ring of the board's console UART, bytes.
pub const TX_RING: usize = 8192;

/// The link, seen from both ends.
#[derive(Debug, Default)]
pub struct SimConsole {
    /// Received bytes; `None` stands for lost input.
    rx: VecDeque<Option<u8>>,
    /// Input was lost and its entry is not queued yet.
    loss_pending: bool,
    tx: VecDeque<u8>,
    /// Bytes lost to a full receive ring.
    pub rx_overruns: u64,
}

impl SimConsole {
    /// An idle link.
    pub fn new() -> Self {
        Self::default()
    }

    /// The terminal sends `bytes` (what does not fit in the ring is lost, counted).
    pub fn send(&mut self, bytes: &[u8]) {
        for &b in bytes {
            if self.loss_pending && self.rx.len() < RX_RING {
                self.rx.push_back(None);
                self.loss_pending = false;
            }
            if !self.loss_pending && self.rx.len() < RX_RING {
                self.rx.push_back(Some(b));
            } else {
                self.rx_overruns += 1;
                self.loss_pending = true;
            }
        }
    }

    /// Bytes waiting in the receive ring.
    pub fn rx_pending(&self) -> usize {
        self.rx.len()
    }

    /// Everything the controller has sent so far (drains the transmit ring).
    pub fn take_output(&mut self) -> Vec<u8> {
        self.tx.drain(..).collect()
    }
}

impl ConsoleIo for SimConsole {
    fn read_byte(&mut self) -> nb::Result<u8, ()> {
        match self.rx.pop_front() {
            None => {
                // The ring drained: a loss still pending takes its place now.
                if std::mem::take(&mut self.loss_pending) {
                    return Err(nb::Error::Other(()));
                }
                Err(nb::Error::WouldBlock)
            }
            Some(Some(b)) => Ok(b),
            Some(None) => Err(nb::Error::Other(())),
        }
    }

    fn write(&mut self, bytes: &[u8]) -> usize {
        let n = bytes.len().min(TX_RING - self.tx.len());
        self.tx.extend(bytes.iter().take(n));
        n
    }
}
