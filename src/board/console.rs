//! The technician console on USART2 (PA2 TX, PA3 RX, 115200 8N1): received by DMA into
//! a ring, sent from a ring by the USART2 interrupt, so that the idle loop never waits on
//! the line and the core can sleep.
//!
//! # Receive: DMA1 stream 5 into a 512-byte ring
//!
//! USART2_RX is DMA1 stream 5, channel 4 (RM0090 table 42). The stream runs in circular
//! mode from USART2's DR into [`RX_RING`] bytes of SRAM (`.bss`), one byte per RXNE, and
//! needs no CPU: a flash record write stalls every fetch from flash for up to 100 µs per
//! word (the datasheet's maximum), and a byte takes 87 µs at 115200 Bd, so the
//! one-byte data register overran while the receive interrupt waited on the flash
//! (`console_overruns` 2–3 in `vboard scene nominal --flood --cpi 3`); the DMA's
//! access to SRAM goes on meanwhile.
//!
//! The console service (idle) reads the ring through [`BoardConsole`]: the DMA's write
//! position is `RX_RING − NDTR`, and a 32-bit count of the bytes written so far is that
//! position plus the half-rings the stream has completed ([`HALVES`], counted by its
//! half-transfer and transfer-complete interrupts). The reader keeps its own count;
//! the difference is what waits.
//!
//! # Loss is reported, never silent
//!
//! The line a loss spoils is discarded by the console (`error: input lost …`), never
//! run with a byte missing. A loss is noted ([`LOSS`], with the count it happened at)
//! when:
//! * the USART reports a framing, noise or overrun error (its EIE interrupt, enabled
//!   with DMAR);
//! * the reader fell a whole ring behind (idle busy for more than 44 ms of input at
//!   line rate): the DMA wrote over bytes not yet read (found from the counts, and
//!   checked again after each byte is read);
//! * the half-transfer and transfer-complete flags are both set when the stream's
//!   interrupt runs: it came half a ring late (only while an erase masks every
//!   interrupt), so the ring may have been lapped;
//! * the stream stopped (a transfer or direct-mode error): it is restarted.
//!
//! The reader then skips to that count and returns one error, which spoils the line
//! being assembled: it is discarded at its terminator with `error: input lost`. After a
//! lapped ring the count is the newest half ring's start: those 256 bytes were written
//! last and are intact, so the lines complete in them still run.
//!
//! # Waking the idle loop
//!
//! RXNEIE stays on: each byte pends the USART2 interrupt for the instant before the DMA
//! reads DR (the NVIC latches it), which wakes the idle loop from `wfi` as before. The
//! handler reads nothing for a byte: it only clears and reports error flags, and feeds
//! the transmitter. (The IDLE-line interrupt would wake less often, but clearing it
//! takes a CPU read of DR, which could take a byte that lands at that instant from
//! under the DMA, unseen.)
//!
//! # Why raw registers, not stm32f4xx-hal's DMA
//!
//! stm32f4xx-hal 0.23's `dma::Transfer` has no plain circular mode: it offers one
//! transfer, or double buffering where the CPU must hand over the next buffer in time
//! (`next_transfer`, which panics on an overrun in the `_with` form), and it owns the
//! stream, so idle (which reads NDTR) and the interrupt (which clears flags) would have
//! to share it under a lock. A ring read by NDTR needs neither: the stream is set up once
//! in [`start_rx`] and then only read, and its flags only cleared by its own interrupt.

use core::cell::UnsafeCell;
use core::sync::atomic::{AtomicBool, AtomicU32, Ordering};

use docking_logic::hal::ConsoleIo;
use embedded_hal_nb::serial::Write as _;
use heapless::spsc::{Consumer, Producer};
use stm32f4xx_hal::pac;
use stm32f4xx_hal::serial::Tx;

/// Losses noted so far (receive errors, a lapped ring, a stream restarted).
pub static RX_ERRORS: AtomicU32 = AtomicU32::new(0);

/// The receive ring, bytes: 44 ms of input at line rate.
pub const RX_RING: usize = 512;
const RING: u32 = RX_RING as u32;
const HALF: u32 = RING / 2;

/// The DMA's ring, in `.bss`.
#[repr(C, align(4))]
struct DmaRing(UnsafeCell<[u8; RX_RING]>);

// SAFETY: only the DMA writes the ring; the console's reader reads it with volatile byte
// reads through a raw pointer, after NDTR said the byte is there (no reference to the
// array is ever made).
unsafe impl Sync for DmaRing {}

static RX_DMA: DmaRing = DmaRing(UnsafeCell::new([0; RX_RING]));

/// Half-rings the stream has completed (HT and TC events), as its interrupt counted
/// them: with the position, the count of bytes written.
static HALVES: AtomicU32 = AtomicU32::new(0);
/// A loss was noted since the reader last looked.
static LOSS: AtomicBool = AtomicBool::new(false);
/// The count of bytes written when it was noted: the reader skips to it.
static LOSS_AT: AtomicU32 = AtomicU32::new(0);

// RM0090 §30.6 (USART), §10.5 (DMA). DMA1 stream 5's flags are bits 6–11 of HISR/HIFCR.
const USART2_BASE: u32 = 0x4000_4400;
const USART2_SR: *const u32 = USART2_BASE as *const u32;
const USART2_DR: *const u32 = (USART2_BASE + 0x04) as *const u32;
const USART2_CR3: *mut u32 = (USART2_BASE + 0x14) as *mut u32;
const SR_FE_NF_ORE: u32 = 0b1110;
const SR_RXNE: u32 = 1 << 5;
const CR3_EIE: u32 = 1 << 0;
const CR3_DMAR: u32 = 1 << 6;
const DMA1_BASE: u32 = 0x4002_6000;
const DMA1_HISR: *const u32 = (DMA1_BASE + 0x04) as *const u32;
const DMA1_HIFCR: *mut u32 = (DMA1_BASE + 0x0C) as *mut u32;
const S5: u32 = DMA1_BASE + 0x10 + 0x18 * 5;
const S5CR: *mut u32 = S5 as *mut u32;
const S5NDTR: *mut u32 = (S5 + 0x04) as *mut u32;
const S5PAR: *mut u32 = (S5 + 0x08) as *mut u32;
const S5M0AR: *mut u32 = (S5 + 0x0C) as *mut u32;
const FLAGS_SHIFT: u32 = 6;
const F_FE: u32 = 1 << 0;
const F_DME: u32 = 1 << 2;
const F_TE: u32 = 1 << 3;
const F_HT: u32 = 1 << 4;
const F_TC: u32 = 1 << 5;
const F_ALL: u32 = F_FE | F_DME | F_TE | F_HT | F_TC;
const CR_EN: u32 = 1 << 0;
/// Channel 4, high priority, memory increment, circular, peripheral to memory, bytes;
/// interrupts on half transfer, transfer complete, transfer error and direct-mode error.
/// Direct mode (FCR at its reset value).
const CR_RX: u32 = (4 << 25) | (2 << 16) | (1 << 10) | (1 << 8) | (0b1111 << 1);

/// USART2 CR1.TXEIE through the peripheral bit-band alias: one store, no
/// read-modify-write, so the idle loop can set it while the interrupt clears it.
const USART2_CR1_TXEIE_BB: *mut u32 = (0x4200_0000 + 0x440C * 32 + 7 * 4) as *mut u32;

/// One character on the console's line at 115 200 Bd 8N1 (10 bits: 86.8 µs), rounded
/// up, µs: how long before it lands a byte may have begun.
pub const CHAR_US: u32 = 87;

/// When the console's receive was set up in init (`mark_rx_start`), µs (low word of
/// the clock).
static RX_STARTED_US: core::sync::atomic::AtomicU32 = core::sync::atomic::AtomicU32::new(0);

/// Init, before USART2 is set up: no byte of the console came before `now_us`.
pub fn mark_rx_start(now_us: u32) {
    RX_STARTED_US.store(now_us, core::sync::atomic::Ordering::Relaxed);
}

/// The instant [`mark_rx_start`] recorded: the idle loop's first bound for a line's
/// issue time.
pub fn rx_started_us() -> u32 {
    RX_STARTED_US.load(core::sync::atomic::Ordering::Relaxed)
}

/// Set up DMA1 stream 5 (its clock enabled) to receive USART2 into the ring, and let
/// USART2 request it. Taking DMA1 claims it: nothing else uses it.
pub fn start_rx(_dma1: pac::DMA1) {
    stream_start();
    // SAFETY: USART2 CR3 (init only, nothing else writes it): DMA requests for
    // reception, and error interrupts (FE, NF, ORE) while they are on.
    unsafe {
        let cr3 = core::ptr::read_volatile(USART2_CR3);
        core::ptr::write_volatile(USART2_CR3, cr3 | CR3_DMAR | CR3_EIE);
    }
}

/// (Re)start stream 5 at the ring's first byte. Out of line (issue 20): two copies
/// (-28 B).
#[inline(never)]
fn stream_start() {
    // SAFETY: DMA1 stream 5's registers and flags (fixed addresses), owned by the
    // console since `start_rx`; the stream is off before it is set up (RM0090 §10.3.18).
    unsafe {
        core::ptr::write_volatile(S5CR, 0);
        for _ in 0..64 {
            if core::ptr::read_volatile(S5CR) & CR_EN == 0 {
                break;
            }
        }
        core::ptr::write_volatile(DMA1_HIFCR, F_ALL << FLAGS_SHIFT);
        core::ptr::write_volatile(S5PAR, USART2_DR as u32);
        core::ptr::write_volatile(S5M0AR, RX_DMA.0.get() as u32);
        core::ptr::write_volatile(S5NDTR, RING);
        core::ptr::write_volatile(S5CR, CR_RX);
        core::ptr::write_volatile(S5CR, CR_RX | CR_EN);
    }
}

/// The DMA's write position in the ring, 0..RX_RING.
fn position() -> u32 {
    // SAFETY: a read of stream 5's NDTR (no side effect).
    let n = unsafe { core::ptr::read_volatile(S5NDTR) } & 0xFFFF;
    RING.wrapping_sub(n) % RING
}

/// Bytes the DMA has written since start (wrapping): the half-rings counted, and the
/// position. A half-ring the stream finished but its interrupt has not counted yet (it
/// is pending, or the reader reads between its two loads) shows as a position in the
/// other half than the count's parity says, and is added here.
// Out of line (issue 20): the reader and the DMA interrupt ask; inlined it was nine
// copies (-244 B).
#[inline(never)]
fn written() -> u32 {
    let h = HALVES.load(Ordering::Acquire);
    let p = position();
    let h = if h & 1 != p / HALF {
        h.wrapping_add(1)
    } else {
        h
    };
    h.wrapping_mul(HALF).wrapping_add(p % HALF)
}

/// Note a loss at byte count `at`: the reader skips to it and reports it.
fn note_loss(at: u32) {
    RX_ERRORS.fetch_add(1, Ordering::Relaxed);
    LOSS_AT.store(at, Ordering::Relaxed);
    LOSS.store(true, Ordering::Release);
}

/// The byte at count `i`, from the ring.
fn ring_byte(i: u32) -> u8 {
    let slot = (i % RING) as usize;
    // SAFETY: `slot` < RX_RING, inside the ring; a volatile read of one byte the DMA may
    // be writing (a torn byte cannot happen; a byte overwritten meanwhile is detected
    // by the caller from the count).
    unsafe { core::ptr::read_volatile(RX_DMA.0.get().cast::<u8>().add(slot)) }
}

/// DMA1 stream 5's interrupt (same priority as USART2's: neither preempts the other):
/// count the half-rings, note a ring the stream may have lapped, restart a stream that
/// stopped.
pub fn on_dma_interrupt() {
    // A consistent snapshot: the flags, the position, the flags again unchanged (a
    // half-ring completed between them is counted on the next pass).
    let (mut f, mut p) = (0, 0);
    for _ in 0..4 {
        // SAFETY: reads of DMA1 HISR and stream 5's NDTR (no side effects).
        f = (unsafe { core::ptr::read_volatile(DMA1_HISR) } >> FLAGS_SHIFT) & F_ALL;
        p = position();
        // SAFETY: as above.
        let again = (unsafe { core::ptr::read_volatile(DMA1_HISR) } >> FLAGS_SHIFT) & F_ALL;
        if again == f {
            break;
        }
    }
    // SAFETY: HIFCR is write-1-to-clear; only stream 5's flags read above.
    unsafe { core::ptr::write_volatile(DMA1_HIFCR, f << FLAGS_SHIFT) };
    // SAFETY: a read of stream 5's CR.
    if unsafe { core::ptr::read_volatile(S5CR) } & CR_EN == 0 {
        // Stopped by a transfer error: start again at the ring's first byte, counting on
        // from the next whole ring; whatever was unread is suspect.
        let base = (written() / RING).wrapping_add(1).wrapping_mul(RING);
        stream_start();
        HALVES.store(base / HALF, Ordering::Release);
        note_loss(base);
        return;
    }
    let mut h = HALVES.load(Ordering::Relaxed);
    let both = f & (F_HT | F_TC) == F_HT | F_TC;
    if both {
        h = h.wrapping_add(2);
    } else if f & (F_HT | F_TC) != 0 {
        h = h.wrapping_add(1);
    }
    // Two half-rings (or more) since the last pass: the count is set by the position's
    // half, and the ring may have been lapped meanwhile.
    let odd = h & 1 != p / HALF;
    if odd {
        h = h.wrapping_add(1);
    }
    HALVES.store(h, Ordering::Release);
    if both || odd {
        // The newest half ring is intact (written last): read on from its start.
        note_loss(written().wrapping_sub(HALF));
    } else if f & F_DME != 0 {
        note_loss(written());
    }
}

/// The USART2 interrupt's side: the transmitter and its ring's far end.
pub struct ConsoleIsr {
    /// Transmitter.
    pub tx: Tx<pac::USART2>,
    /// Bytes to send come from here.
    pub tx_out: Consumer<'static, u8>,
}

impl ConsoleIsr {
    /// The USART2 interrupt: report receive errors, send what is queued. (Received bytes
    /// are the DMA's; their RXNE only woke the core.)
    pub fn on_interrupt(&mut self) {
        // SAFETY: a read of USART2 SR.
        let sr = unsafe { core::ptr::read_volatile(USART2_SR) };
        if sr & SR_FE_NF_ORE != 0 {
            // Cleared by SR then DR read; DR only once the DMA has taken the byte (RXNE
            // clear), so the read takes none from it. The loss is noted after the DR
            // read: a byte that landed between the two would be the next one counted,
            // in the line the loss spoils.
            if sr & SR_RXNE == 0 {
                // SAFETY: a read of USART2 DR (clears the error flags).
                let _ = unsafe { core::ptr::read_volatile(USART2_DR) };
            }
            note_loss(written());
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

/// The console service's side: the ring's reader and the bytes to send.
pub struct BoardConsole {
    /// Bytes read from the ring so far (wrapping, as [`written`]).
    read: u32,
    /// Bytes to send.
    tx_in: Producer<'static, u8>,
}

impl BoardConsole {
    /// The reader at the ring's start (before [`start_rx`]).
    pub fn new(tx_in: Producer<'static, u8>) -> Self {
        Self { read: 0, tx_in }
    }

    #[cfg(feature = "updater")]
    /// Whether everything queued has left the line (the ring empty, USART2's TC set).
    pub fn tx_idle(&self) -> bool {
        // SAFETY: a read of USART2 SR (no side effect on TC).
        let tc = unsafe { core::ptr::read_volatile(USART2_SR) } & (1 << 6) != 0;
        self.tx_in.is_empty() && tc
    }

    /// Whether received bytes (or a loss) wait for the console service.
    pub fn rx_pending(&self) -> bool {
        LOSS.load(Ordering::Acquire) || written() != self.read
    }
}

impl ConsoleIo for BoardConsole {
    fn read_byte(&mut self) -> nb::Result<u8, ()> {
        if LOSS.swap(false, Ordering::Acquire) {
            // Skip to the loss, if it lies ahead in what is unread (else read on: the
            // normal path below catches a ring that was lapped meanwhile).
            let at = LOSS_AT.load(Ordering::Relaxed);
            if at.wrapping_sub(self.read) <= written().wrapping_sub(self.read) {
                self.read = at;
            }
            return Err(nb::Error::Other(()));
        }
        let w = written();
        let unread = w.wrapping_sub(self.read);
        if unread == 0 {
            return Err(nb::Error::WouldBlock);
        }
        if unread <= RING {
            let b = ring_byte(self.read);
            // The DMA writes byte `read + RING` over it: still there after the read?
            if written().wrapping_sub(self.read) <= RING {
                self.read = self.read.wrapping_add(1);
                return Ok(b);
            }
        }
        // A whole ring behind: the DMA wrote over bytes not yet read. Read on from the
        // newest half ring (written last, intact).
        RX_ERRORS.fetch_add(1, Ordering::Relaxed);
        self.read = written().wrapping_sub(HALF);
        Err(nb::Error::Other(()))
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
