//! The PLC's Modbus RTU line on USART3 (PB10 TX, PB11 RX, alternate function 7) through
//! an RS-485 transceiver whose driver PB14 enables (DE, high = we drive the bus; the
//! board's pull-down keeps it off through a reset). 19200 8E1 unless a technician stored
//! other settings (console `modbus`).
//!
//! The USART3 interrupt stamps each received character with the microsecond clock and
//! puts it in [`RING`] (a character with a parity, framing, noise or overrun error as
//! [`LINE_ERROR`]): the RTU framer measures its t1.5 / t3.5 silences from those stamps,
//! not from when the idle loop gets round to them. The idle loop takes **whole frames**
//! from the ring (a frame is whole once a t3.5 silence follows it:
//! [`RxRing::first_frame_end`])
//! into the server, and stays awake while one is being received (at most t3.5 after its
//! last character: 2 ms at 19200 Bd), so a reply is not held back to the next control
//! step.
//!
//! # While the flash erases (issue 31)
//!
//! A sector erase stalls every fetch from flash for up to 2 s, so it runs from SRAM with
//! every interrupt masked (`flash.rs`), and neither this interrupt nor idle runs. The
//! erase's loop in SRAM then stands in for both ([`busy_responder`], in SRAM too,
//! called from it): it reads USART3's data register into the same ring, and answers every whole frame
//! addressed to this unit with **exception 06, server device busy** (the Modbus
//! specification's answer for a request the server cannot take now; a broadcast, another
//! unit's request or a bad CRC get no reply, as always), within t3.5 of the request's
//! end. The ring is the one place a frame lives until one of them answers it: idle never
//! holds part of a frame (it takes whole ones), so a frame the erase interrupts is taken
//! whole by the responder, and one in progress when the erase ends is left, whole, to
//! idle. The service starts flash work only when no request is open ([`busy`]: a
//! character not yet framed by idle, a request framed and not yet answered, a reply on
//! the line), so a request idle had already taken is answered with its data first.
//! (Every character reaches the responder or idle whole: idle takes a frame only once it
//! is whole, and the responder only whole frames too, leaving a frame still being
//! received at the erase's end to idle.)
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

/// The most a character's stamp can be late, µs: the interrupt's stamp is taken when
/// USART3's handler (priority 2) runs, which the HX711's readout and guard (EXTI0,
/// priority 4: 32 µs at CPI 1, under 100 µs at CPI 3), the step generator (SysTick), the
/// E-STOP's handler, the console's handlers at its own level and the masked windows can
/// hold back by well under a millisecond together. A request's issue time (its first
/// character's start, `Controller::issued_at`) is taken this much earlier, so that it is
/// never later than the PLC sent it: an E-STOP edge in the first microseconds of a
/// clear's frame seemed to come before the clear, which then recovered the machine
/// (issue 32's review; `an_estop_pulse_in_the_first_microseconds_of_a_clears_frame_was_swallowed`
/// on the virtual board). The cost: a clear whose frame began within a millisecond after
/// an E-STOP edge is refused at its step (no PLC answers an edge that fast; it sends the
/// clear again).
pub const STAMP_LATE_MAX_US: u32 = 1_000;

/// Characters lost because the receive ring was full.
pub static RX_DROPPED: AtomicU32 = AtomicU32::new(0);

/// Requests answered with exception 06 (server device busy) while the flash erased.
pub static BUSY_REPLIES: AtomicU32 = AtomicU32::new(0);

/// Ring entries (a power of two): two of the longest frames.
const RING_LEN: u32 = 512;

/// The received characters with their stamps (TIM5's low word, µs): single producer
/// (the USART3 interrupt, or the erase's responder while interrupts are masked), single
/// consumer (idle, or the responder). Every access is a volatile read or write and a
/// compiler fence (one core: no barrier instruction is needed between the interrupt and
/// thread mode), so that the responder's copy of this code, in SRAM, calls nothing.
pub struct RxRing {
    chars: core::cell::UnsafeCell<[u16; RING_LEN as usize]>,
    stamps: core::cell::UnsafeCell<[u32; RING_LEN as usize]>,
    /// Entries written (wraps).
    head: core::cell::UnsafeCell<u32>,
    /// Entries taken (wraps).
    tail: core::cell::UnsafeCell<u32>,
}

// SAFETY: one producer and one consumer at a time (the interrupt and idle; the responder
// is both, with every interrupt masked and idle preempted), each index written by one
// side only.
unsafe impl Sync for RxRing {}

/// The Modbus line's receive ring.
pub static RING: RxRing = RxRing {
    chars: core::cell::UnsafeCell::new([0; RING_LEN as usize]),
    stamps: core::cell::UnsafeCell::new([0; RING_LEN as usize]),
    head: core::cell::UnsafeCell::new(0),
    tail: core::cell::UnsafeCell::new(0),
};

impl RxRing {
    #[inline(always)]
    fn head(&self) -> u32 {
        // SAFETY: a word of this static, read whole.
        unsafe { core::ptr::read_volatile(self.head.get()) }
    }

    #[inline(always)]
    fn tail(&self) -> u32 {
        // SAFETY: as above.
        unsafe { core::ptr::read_volatile(self.tail.get()) }
    }

    /// Entry `i` (any count: taken modulo the ring's length).
    #[inline(always)]
    fn at(&self, i: u32) -> (u16, u32) {
        let k = (i % RING_LEN) as usize;
        // SAFETY: `k` < RING_LEN, inside both arrays; the producer wrote the entry before
        // it moved `head` past it (fence), and does not touch it until `tail` passes.
        unsafe {
            (
                core::ptr::read_volatile((self.chars.get() as *const u16).add(k)),
                core::ptr::read_volatile((self.stamps.get() as *const u32).add(k)),
            )
        }
    }

    /// The producer: a character and its stamp (counted in [`RX_DROPPED`] when full).
    #[inline(always)]
    pub fn push(&self, c: u16, stamp_us: u32) {
        let (head, tail) = (self.head(), self.tail());
        if head.wrapping_sub(tail) >= RING_LEN {
            bump(&RX_DROPPED);
            return;
        }
        let k = (head % RING_LEN) as usize;
        // SAFETY: `k` < RING_LEN; the consumer reads this entry only once `head` has
        // moved past it, which the fence orders after these stores.
        unsafe {
            core::ptr::write_volatile((self.chars.get() as *mut u16).add(k), c);
            core::ptr::write_volatile((self.stamps.get() as *mut u32).add(k), stamp_us);
            core::sync::atomic::compiler_fence(Ordering::Release);
            core::ptr::write_volatile(self.head.get(), head.wrapping_add(1));
        }
    }

    /// Whether characters wait.
    #[inline(always)]
    pub fn pending(&self) -> bool {
        self.head() != self.tail()
    }

    /// The entry count one past the ring's first **whole** frame, if there is one: a
    /// frame is whole when a silence of at least `t3_5_us` follows its last character,
    /// before the next one (a silence as the framer counts it: the next stamp less one
    /// character time less this stamp) or before `now_us`.
    #[inline(always)]
    pub fn first_frame_end(&self, now_us: u32, char_us: u32, t3_5_us: u32) -> Option<u32> {
        core::sync::atomic::compiler_fence(Ordering::Acquire);
        let (head, mut i) = (self.head(), self.tail());
        while i != head {
            let (_, t) = self.at(i);
            let next = i.wrapping_add(1);
            let silence = if next == head {
                now_us.wrapping_sub(t)
            } else {
                self.at(next).1.wrapping_sub(t).wrapping_sub(char_us)
            };
            // A stamp a little after `now` (a character stamped after `now` was read)
            // wraps to a huge silence: counted as none.
            if silence >= t3_5_us && silence < 0x8000_0000 {
                return Some(next);
            }
            i = next;
        }
        None
    }

    /// The consumer: the oldest entry, if any, and the ring moved past it.
    #[inline(always)]
    pub fn pop(&self) -> Option<(u16, u32)> {
        core::sync::atomic::compiler_fence(Ordering::Acquire);
        let tail = self.tail();
        if tail == self.head() {
            return None;
        }
        let e = self.at(tail);
        core::sync::atomic::compiler_fence(Ordering::Release);
        // SAFETY: a word of this static, written by the consumer only.
        unsafe { core::ptr::write_volatile(self.tail.get(), tail.wrapping_add(1)) };
        Some(e)
    }
}

/// What the erase's responder needs of the line's settings (idle sets them once it has
/// them): the unit's address (0: not configured, no reply), one character and t3.5, µs.
static RESPONDER_UNIT: AtomicU32 = AtomicU32::new(0);
static RESPONDER_CHAR_US: AtomicU32 = AtomicU32::new(573);
static RESPONDER_T35_US: AtomicU32 = AtomicU32::new(2_006);

/// Idle: the line's settings, for [`busy_responder`] and idle's own framing.
pub fn configure(settings: &docking_logic::modbus::ModbusSettings) {
    RESPONDER_CHAR_US.store(settings.char_us(), Ordering::Relaxed);
    RESPONDER_T35_US.store(settings.t3_5_us(), Ordering::Relaxed);
    RESPONDER_UNIT.store(u32::from(settings.unit), Ordering::Relaxed);
}

/// One character, µs, and t3.5, µs, of the configured line.
pub fn timing_us() -> (u32, u32) {
    (
        RESPONDER_CHAR_US.load(Ordering::Relaxed),
        RESPONDER_T35_US.load(Ordering::Relaxed),
    )
}

/// Idle's Modbus work is open: it has taken characters into the server that make no
/// answered request yet, or a request waits for its reply (set before idle takes
/// characters out of the ring, cleared when it has answered all it took).
static IDLE_OPEN: core::sync::atomic::AtomicBool = core::sync::atomic::AtomicBool::new(false);

/// Idle: it is about to take characters from the ring (`true`), or everything it took is
/// answered or discarded (`false`).
pub fn set_idle_open(open: bool) {
    IDLE_OPEN.store(open, Ordering::Release);
}

/// Whether the flash must wait for the line: a request idle has taken from the ring and
/// not answered yet, or a reply on the wire (DE high). The service starts no flash work
/// then (`Controller::set_bus_busy`, from `owner::apply_published`). Characters still in
/// the ring do not hold it back: they are the erase's responder's, if idle has not
/// taken them by then.
pub fn busy() -> bool {
    IDLE_OPEN.load(Ordering::Acquire) || line_driven()
}

/// Whether our transceiver drives the bus (DE high).
pub fn line_driven() -> bool {
    // SAFETY: read of GPIOB's ODR, a fixed MMIO address.
    unsafe { core::ptr::read_volatile(GPIOB_ODR) & DE_HIGH != 0 }
}

/// USART3 SR's RXNE and its error flags (ORE, NE, FE, PE).
const SR_RXNE: u32 = 1 << 5;
const SR_RX_ERRORS: u32 = 0x0F;
const SR_TXE: u32 = 1 << 7;
/// USART3 DR.
const DR: *mut u32 = (USART3_BASE + 0x04) as *mut u32;

/// The responder's frame buffer (in `.bss`: a buffer on the stack would be zeroed by a
/// call into flash). Used only with every interrupt masked, by the SRAM wait of a flash
/// operation (`flash.rs`'s `wait_idle_feeding!`).
pub static mut RESPONDER: Responder = Responder::new();

/// The responder's state between its steps: the frame being answered.
pub struct Responder {
    frame: [u8; 256],
    len: usize,
    bad: bool,
}

impl Responder {
    /// Nothing taken yet.
    #[inline(always)]
    pub const fn new() -> Self {
        Self {
            frame: [0; 256],
            len: 0,
            bad: false,
        }
    }
}

/// CRC-16/MODBUS, bit by bit (no table: the responder runs from SRAM and reads no
/// flash).
#[inline(always)]
fn crc16(bytes: &[u8], n: usize) -> u16 {
    let mut crc: u16 = 0xFFFF;
    let mut i = 0;
    while i < n && i < bytes.len() {
        // SAFETY: `i` < bytes.len().
        crc ^= u16::from(unsafe { *bytes.as_ptr().add(i) });
        let mut b = 0;
        while b < 8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xA001
            } else {
                crc >> 1
            };
            b += 1;
        }
        i += 1;
    }
    crc
}

/// Spin until `flag` is set in USART3's SR, at most `max` reads.
#[inline(always)]
fn wait_sr(flag: u32, max: u32) {
    let mut n = 0;
    // SAFETY: reads of USART3 SR, a fixed MMIO address.
    while unsafe { core::ptr::read_volatile(SR) } & flag == 0 && n < max {
        n += 1;
    }
}

/// Whether a character waits in USART3's data register (inlined into `flash.rs`'s SRAM
/// loop, with every interrupt masked: it calls nothing and reads no flash). One status
/// register: the loop that polls it reads nothing but status registers while the line is
/// quiet (the virtual board jumps over such a wait, as over any polling loop).
#[inline(always)]
pub fn char_waiting() -> bool {
    // SAFETY: a read of USART3's SR (fixed MMIO): no side effect.
    unsafe { core::ptr::read_volatile(SR) & (SR_RXNE | SR_RX_ERRORS) != 0 }
}

/// The erase's responder, once a character came (or the ring held some when the erase
/// began): each character into the ring, each whole frame answered — exception 06 to a
/// valid request for this unit — until the ring is empty; a frame still arriving when
/// the flash is done (`FLASH_SR.BSY` clear) or `cycles_left` have passed is left in the
/// ring, whole, to idle. Feeds the watchdog meanwhile. In SRAM (`.data`), called from
/// the flash's wait only, every interrupt masked.
#[inline(never)]
#[link_section = ".data.modbus_busy_responder"]
pub fn busy_responder(r: &mut Responder, start_cycles: u32, max_cycles: u32) {
    use super::flash::{DWT_CYCCNT, FLASH_SR, IWDG_KR, SR_BSY};
    loop {
        // SAFETY: USART3's SR and DR, TIM5's counter, FLASH_SR, the cycle counter and
        // the watchdog's key register (fixed MMIO); reading SR then DR clears RXNE and
        // the error flags, as the interrupt would have.
        unsafe {
            let sr = core::ptr::read_volatile(SR);
            if sr & (SR_RXNE | SR_RX_ERRORS) != 0 {
                let dr = core::ptr::read_volatile(DR) as u16 & 0xFF;
                let c = if sr & SR_RX_ERRORS != 0 {
                    LINE_ERROR
                } else {
                    dr
                };
                RING.push(c, core::ptr::read_volatile(super::clock::TIM5_CNT));
            }
            answer_whole_frames(r);
            if !RING.pending()
                || core::ptr::read_volatile(FLASH_SR) & SR_BSY == 0
                || core::ptr::read_volatile(DWT_CYCCNT).wrapping_sub(start_cycles) > max_cycles
            {
                return;
            }
            core::ptr::write_volatile(IWDG_KR, 0xAAAA);
        }
    }
}

/// Each whole frame in the ring answered.
#[inline(always)]
fn answer_whole_frames(r: &mut Responder) {
    // SAFETY: TIM5's counter, a fixed MMIO address.
    let now_us = unsafe { core::ptr::read_volatile(super::clock::TIM5_CNT) };
    let char_us = setting(&RESPONDER_CHAR_US);
    let t35 = setting(&RESPONDER_T35_US);
    while let Some(end) = RING.first_frame_end(now_us, char_us, t35) {
        r.len = 0;
        r.bad = false;
        while RING.tail() != end {
            let Some((c, _)) = RING.pop() else {
                break;
            };
            if c & LINE_ERROR != 0 || r.len >= r.frame.len() {
                r.bad = true;
            } else {
                // SAFETY: `r.len` < the frame's length (checked above).
                unsafe { *r.frame.as_mut_ptr().add(r.len) = c as u8 };
                r.len += 1;
            }
        }
        answer_busy(r);
    }
}

/// Answer the frame in `r`, if it is a valid request for this unit (not a broadcast):
/// `unit, function | 0x80, 06, CRC` (exception 06, server device busy), DE high for it.
#[inline(always)]
fn answer_busy(r: &Responder) {
    let unit = setting(&RESPONDER_UNIT);
    if r.bad || r.len < 4 || unit == 0 {
        return;
    }
    // SAFETY: r.len >= 4, inside the frame.
    let (addr, func) = unsafe { (*r.frame.as_ptr(), *r.frame.as_ptr().add(1)) };
    let (lo, hi) = unsafe {
        (
            *r.frame.as_ptr().add(r.len - 2),
            *r.frame.as_ptr().add(r.len - 1),
        )
    };
    if u32::from(addr) != unit || crc16(&r.frame, r.len - 2) != u16::from_le_bytes([lo, hi]) {
        return;
    }
    let mut reply = [addr, func | 0x80, 0x06, 0, 0];
    let [c0, c1] = crc16(&reply, 3).to_le_bytes();
    // SAFETY: indices 3 and 4 of a 5-byte array.
    unsafe {
        *reply.as_mut_ptr().add(3) = c0;
        *reply.as_mut_ptr().add(4) = c1;
    }
    // SAFETY: GPIOB's BSRR (PB14, DE, is ours) and USART3's SR and DR (fixed MMIO).
    unsafe {
        core::ptr::write_volatile(GPIOB_BSRR, DE_HIGH);
        let mut i = 0;
        while i < reply.len() {
            wait_sr(SR_TXE, 2_000_000);
            core::ptr::write_volatile(DR, u32::from(*reply.as_ptr().add(i)));
            i += 1;
        }
        wait_sr(SR_TC, 2_000_000);
        core::ptr::write_volatile(GPIOB_BSRR, DE_LOW);
    }
    bump(&BUSY_REPLIES);
}

/// One more in `counter` (a volatile increment: its one writer is the interrupt, or the
/// responder with the interrupt masked; and the responder's code calls nothing).
#[inline(always)]
fn bump(counter: &AtomicU32) {
    let p = counter.as_ptr();
    // SAFETY: a word of a static atomic, read and written whole by its one writer.
    unsafe { core::ptr::write_volatile(p, core::ptr::read_volatile(p).wrapping_add(1)) };
}

/// A responder setting, read with a volatile load (see [`bump`]).
#[inline(always)]
fn setting(s: &AtomicU32) -> u32 {
    // SAFETY: a word of a static atomic.
    unsafe { core::ptr::read_volatile(s.as_ptr()) }
}

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
            RING.push(c, super::clock::now_us_low());
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

/// The idle loop's side.
pub struct ModbusLine {
    /// Reply bytes to send.
    pub tx_in: Producer<'static, u8>,
}

impl ModbusLine {
    /// Whether received characters wait (a frame being received, or one whole).
    pub fn rx_pending(&self) -> bool {
        RING.pending()
    }

    /// The characters of the ring's first whole frame, each with its time on
    /// `now_us`'s clock (µs since boot), to `f`: `Ok(byte)` or `Err(())` for a line
    /// error; whether there was one. A frame still being received stays in the ring (the
    /// erase's responder may answer it). Marks idle's Modbus work open
    /// ([`set_idle_open`]) before it takes any. One frame a call: the framer drops a
    /// frame that was not polled before the next began.
    pub fn take_whole_frame(
        &mut self,
        now_us: u64,
        mut f: impl FnMut(Result<u8, ()>, u64),
    ) -> bool {
        let (char_us, t35) = timing_us();
        let now_low = now_us as u32;
        let Some(end) = RING.first_frame_end(now_low, char_us, t35) else {
            return false;
        };
        set_idle_open(true);
        while RING.tail() != end {
            let Some((c, stamp)) = RING.pop() else {
                break;
            };
            // The stamp on the 64-bit clock: `now` less how long ago it was.
            let t = now_us.saturating_sub(u64::from(now_low.wrapping_sub(stamp)));
            f(u8::try_from(c).map_err(|_| ()), t);
        }
        true
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
