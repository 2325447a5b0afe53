//! YMODEM-1K receiver (issue 21: the update's delivery over the console), as lrzsz's `sb`
//! and terminal programs send it. Hardware-free: bytes in, actions out; the caller owns
//! the link, the clock and the flash.
//!
//! ```text
//!  receiver               sender
//!  'C' (every 3 s) ─────▶
//!                  ◀───── SOH 00 FF "name\0size ..." CRC      block 0: the file's size
//!  ACK, 'C'        ─────▶
//!                  ◀───── STX 01 FE [1024 B] CRC              data: STX 1024 B / SOH 128 B
//!  ACK             ─────▶  (after the caller has stored the bytes)
//!       ...
//!                  ◀───── EOT
//!  NAK             ─────▶
//!                  ◀───── EOT
//!  ACK, 'C'        ─────▶
//!                  ◀───── SOH 00 FF [0 ...] CRC               empty block 0: end of batch
//!  ACK             ─────▶  Done
//! ```
//!
//! CRC-16/XMODEM over the data, big-endian. A bad CRC or a torn packet is answered NAK
//! (the sender repeats it); the previous block again is acknowledged and not delivered
//! twice; any other block number, a file without a size, or one over the caller's
//! maximum cancels the transfer (CAN CAN). CAN CAN from the sender aborts. The last
//! block's padding (0x1A) is cut at the size block 0 gave: [`Action::Data`] carries
//! exactly the file's bytes. Nothing here panics on any input.

/// Start of a 128-byte block.
pub const SOH: u8 = 0x01;
/// Start of a 1024-byte block.
pub const STX: u8 = 0x02;
/// End of file.
pub const EOT: u8 = 0x04;
/// Acknowledge.
pub const ACK: u8 = 0x06;
/// Negative acknowledge.
pub const NAK: u8 = 0x15;
/// Cancel (twice).
pub const CAN: u8 = 0x18;
/// The receiver asks for CRC mode.
pub const C: u8 = b'C';

/// Why a transfer ended without the file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Abort {
    /// The sender cancelled (CAN CAN).
    Cancelled,
    /// Block 0 gave no size.
    NoSize,
    /// The file is larger than the receiver takes.
    TooLarge,
    /// A block out of sequence.
    Sequence,
    /// The sender ended the file before its size.
    Short,
    /// The caller gave up (time-out, a flash error).
    Local,
}

/// What the caller does after a byte.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Action {
    /// Nothing yet.
    None,
    /// Send these bytes to the sender.
    Send(&'static [u8]),
    /// The file: `size` bytes. The caller prepares (erases) and answers [`Receiver::ack`].
    Start {
        /// Bytes.
        size: u32,
    },
    /// `len` bytes of the file at `offset` are in [`Receiver::data`]: store them, then
    /// send what [`Receiver::ack`] returns.
    Data {
        /// Offset in the file.
        offset: u32,
        /// Bytes.
        len: usize,
    },
    /// The whole file was received; send these bytes.
    Done(&'static [u8]),
    /// The transfer ended without the file; send these bytes (CAN CAN, or nothing).
    Aborted(Abort, &'static [u8]),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Phase {
    /// Waiting for block 0 (the file's header).
    Header,
    /// Receiving the file.
    File,
    /// The first EOT came; waiting for the second.
    Eot,
    /// Waiting for the closing empty block 0.
    Close,
    /// Over.
    Over,
}

const CAN2: &[u8] = &[CAN, CAN];
const ACK_C: &[u8] = &[ACK, C];

/// The receiver.
pub struct Receiver {
    phase: Phase,
    max: u32,
    size: u32,
    offset: u32,
    /// The block number expected next.
    block: u8,
    buf: [u8; 1024 + 5],
    len: usize,
    need: usize,
    /// A CAN just came.
    can: bool,
    /// Bytes delivered by the last [`Action::Data`].
    data: (usize, usize),
}

impl Receiver {
    /// A receiver for one file of at most `max` bytes (`const`: the board keeps its
    /// session in a static).
    pub const fn new(max: u32) -> Self {
        Self {
            phase: Phase::Header,
            max,
            size: 0,
            offset: 0,
            block: 0,
            buf: [0; 1024 + 5],
            len: 0,
            need: 0,
            can: false,
            data: (0, 0),
        }
    }

    /// What to send while nothing arrives (every 3 s or so): 'C' before the file and
    /// before the closing block, NAK inside the file; nothing when over.
    pub fn idle(&mut self) -> &'static [u8] {
        self.len = 0;
        match self.phase {
            Phase::Header | Phase::Close => &[C],
            Phase::File | Phase::Eot => &[NAK],
            Phase::Over => &[],
        }
    }

    /// Give up (the caller's time-out or a flash error): CAN CAN to send.
    pub fn cancel(&mut self) -> Action {
        self.phase = Phase::Over;
        Action::Aborted(Abort::Local, CAN2)
    }

    /// The file's size (after [`Action::Start`]).
    pub fn size(&self) -> u32 {
        self.size
    }

    /// The bytes of the last [`Action::Data`].
    pub fn data(&self) -> &[u8] {
        self.buf.get(self.data.0..self.data.1).unwrap_or(&[])
    }

    /// The answer once the caller has handled [`Action::Start`] or [`Action::Data`].
    pub fn ack(&self) -> &'static [u8] {
        match self.phase {
            Phase::File if self.offset == 0 && self.block == 1 => ACK_C,
            _ => &[ACK],
        }
    }

    /// One byte from the sender.
    pub fn feed(&mut self, b: u8) -> Action {
        if self.phase == Phase::Over {
            return Action::None;
        }
        if self.len == 0 {
            // Between packets.
            if b == CAN {
                if self.can {
                    self.phase = Phase::Over;
                    return Action::Aborted(Abort::Cancelled, &[]);
                }
                self.can = true;
                return Action::None;
            }
            self.can = false;
            match b {
                SOH | STX => {
                    self.need = if b == SOH { 128 + 5 } else { 1024 + 5 };
                    if let Some(x) = self.buf.get_mut(0) {
                        *x = b;
                    }
                    self.len = 1;
                    Action::None
                }
                EOT => self.eot(),
                // Line noise between packets.
                _ => Action::None,
            }
        } else {
            if let Some(x) = self.buf.get_mut(self.len) {
                *x = b;
            }
            self.len += 1;
            if self.len < self.need {
                return Action::None;
            }
            self.len = 0;
            self.packet()
        }
    }

    fn eot(&mut self) -> Action {
        match self.phase {
            Phase::File if self.offset >= self.size => {
                self.phase = Phase::Eot;
                Action::Send(&[NAK])
            }
            Phase::File => {
                self.phase = Phase::Over;
                Action::Aborted(Abort::Short, CAN2)
            }
            Phase::Eot => {
                self.phase = Phase::Close;
                Action::Send(ACK_C)
            }
            _ => Action::None,
        }
    }

    fn packet(&mut self) -> Action {
        let n = self.need - 5;
        let (Some(&blk), Some(&inv), Some(data), Some(&hi), Some(&lo)) = (
            self.buf.get(1),
            self.buf.get(2),
            self.buf.get(3..3 + n),
            self.buf.get(3 + n),
            self.buf.get(4 + n),
        ) else {
            return Action::Send(&[NAK]);
        };
        if blk != !inv || crate::crc::crc16_xmodem(data) != u16::from_be_bytes([hi, lo]) {
            return Action::Send(&[NAK]);
        }
        match self.phase {
            Phase::Header if blk == 0 => self.header(n),
            Phase::Close if blk == 0 => {
                self.phase = Phase::Over;
                Action::Done(&[ACK])
            }
            // Block 0 again (our ACK was lost): acknowledge it again.
            Phase::File if blk == 0 && self.offset == 0 => Action::Send(ACK_C),
            Phase::File if blk == self.block => {
                let len = (n as u32).min(self.size.saturating_sub(self.offset)) as usize;
                let offset = self.offset;
                self.data = (3, 3 + len);
                self.offset = self.offset.saturating_add(len as u32);
                self.block = self.block.wrapping_add(1);
                Action::Data { offset, len }
            }
            // The previous block again (our ACK was lost).
            Phase::File if blk == self.block.wrapping_sub(1) => Action::Send(&[ACK]),
            _ => {
                self.phase = Phase::Over;
                Action::Aborted(Abort::Sequence, CAN2)
            }
        }
    }

    /// Block 0: "name\0size[ more]\0...".
    fn header(&mut self, n: usize) -> Action {
        let data = self.buf.get(3..3 + n).unwrap_or(&[]);
        if data.first() == Some(&0) {
            // An empty batch: nothing sent.
            self.phase = Phase::Over;
            return Action::Aborted(Abort::NoSize, &[ACK]);
        }
        let after_name = data.iter().position(|&c| c == 0).map(|i| i + 1);
        let mut size: u32 = 0;
        let mut digits = 0;
        for &c in data.get(after_name.unwrap_or(n)..).unwrap_or(&[]) {
            if !c.is_ascii_digit() {
                break;
            }
            size = match size
                .checked_mul(10)
                .and_then(|s| s.checked_add((c - b'0') as u32))
            {
                Some(s) => s,
                None => {
                    self.phase = Phase::Over;
                    return Action::Aborted(Abort::TooLarge, CAN2);
                }
            };
            digits += 1;
        }
        if digits == 0 || size == 0 {
            self.phase = Phase::Over;
            return Action::Aborted(Abort::NoSize, CAN2);
        }
        if size > self.max {
            self.phase = Phase::Over;
            return Action::Aborted(Abort::TooLarge, CAN2);
        }
        self.size = size;
        self.offset = 0;
        self.block = 1;
        self.phase = Phase::File;
        Action::Start { size }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::indexing_slicing, clippy::panic)]
mod tests {
    extern crate std;
    use super::*;
    use std::format;
    use std::vec;
    use std::vec::Vec;

    /// A packet as a sender frames it.
    fn packet(blk: u8, data: &[u8]) -> Vec<u8> {
        let n = if data.len() <= 128 { 128 } else { 1024 };
        let mut d = data.to_vec();
        d.resize(n, if blk == 0 { 0 } else { 0x1A });
        let mut p = vec![if n == 128 { SOH } else { STX }, blk, !blk];
        p.extend(&d);
        // The sender's CRC from the crc crate, not the receiver's own.
        p.extend(
            crc::Crc::<u16>::new(&crc::CRC_16_XMODEM)
                .checksum(&d)
                .to_be_bytes(),
        );
        p
    }

    fn header(name: &str, size: usize) -> Vec<u8> {
        let mut h = name.as_bytes().to_vec();
        h.push(0);
        h.extend(format!("{size} 14712345670 100644").as_bytes());
        packet(0, &h)
    }

    /// Feed `bytes`; the actions other than None, data collected into `file`.
    fn run(r: &mut Receiver, bytes: &[u8], file: &mut Vec<u8>) -> Vec<Action> {
        let mut out = Vec::new();
        for &b in bytes {
            let a = r.feed(b);
            if let Action::Data { offset, len } = a {
                assert_eq!(offset as usize, file.len());
                assert_eq!(r.data().len(), len);
                file.extend(r.data());
            }
            if a != Action::None {
                out.push(a);
            }
        }
        out
    }

    fn image(n: usize) -> Vec<u8> {
        (0..n).map(|i| (i * 31 + i / 7) as u8).collect()
    }

    #[test]
    fn a_file_arrives_whole_and_cut_at_its_size() {
        let img = image(3000);
        let mut r = Receiver::new(1 << 20);
        assert_eq!(r.idle(), &[C]);
        let mut file = Vec::new();
        let a = run(&mut r, &header("app.dcs", img.len()), &mut file);
        assert_eq!(a, [Action::Start { size: 3000 }]);
        assert_eq!(r.ack(), ACK_C);
        for (i, chunk) in img.chunks(1024).enumerate() {
            let a = run(&mut r, &packet(i as u8 + 1, chunk), &mut file);
            assert!(matches!(a[..], [Action::Data { .. }]), "{a:?}");
            assert_eq!(r.ack(), &[ACK]);
        }
        assert_eq!(run(&mut r, &[EOT], &mut file), [Action::Send(&[NAK])]);
        assert_eq!(run(&mut r, &[EOT], &mut file), [Action::Send(ACK_C)]);
        assert_eq!(
            run(&mut r, &packet(0, &[]), &mut file),
            [Action::Done(&[ACK])]
        );
        assert!(file == img);
    }

    #[test]
    fn a_damaged_packet_is_refused_and_the_repeat_taken_once() {
        let img = image(2048);
        let mut r = Receiver::new(1 << 20);
        let mut file = Vec::new();
        run(&mut r, &header("a", img.len()), &mut file);
        let mut bad = packet(1, &img[..1024]);
        bad[100] ^= 0x40;
        assert_eq!(run(&mut r, &bad, &mut file), [Action::Send(&[NAK])]);
        run(&mut r, &packet(1, &img[..1024]), &mut file);
        // Our ACK lost: the same block again is acknowledged, not stored twice.
        assert_eq!(
            run(&mut r, &packet(1, &img[..1024]), &mut file),
            [Action::Send(&[ACK])]
        );
        run(&mut r, &packet(2, &img[1024..]), &mut file);
        assert!(file == img);
        // A block from elsewhere cancels.
        let a = run(&mut r, &packet(7, &img[..1024]), &mut file);
        assert_eq!(a, [Action::Aborted(Abort::Sequence, CAN2)]);
    }

    #[test]
    fn too_large_sizeless_short_and_cancelled_transfers_end_without_a_file() {
        let mut f = Vec::new();
        let mut r = Receiver::new(1000);
        let a = run(&mut r, &header("big", 1001), &mut f);
        assert_eq!(a, [Action::Aborted(Abort::TooLarge, CAN2)]);
        let mut r = Receiver::new(1000);
        let a = run(&mut r, &packet(0, b"name\0"), &mut f);
        assert_eq!(a, [Action::Aborted(Abort::NoSize, CAN2)]);
        let mut r = Receiver::new(1 << 20);
        run(&mut r, &header("a", 2000), &mut f);
        run(&mut r, &packet(1, &image(1024)), &mut f);
        assert_eq!(
            run(&mut r, &[EOT], &mut f),
            [Action::Aborted(Abort::Short, CAN2)]
        );
        let mut r = Receiver::new(1 << 20);
        run(&mut r, &header("a", 2000), &mut f);
        assert_eq!(
            run(&mut r, &[CAN, CAN], &mut f),
            [Action::Aborted(Abort::Cancelled, &[])]
        );
        let mut r = Receiver::new(1 << 20);
        assert_eq!(r.cancel(), Action::Aborted(Abort::Local, CAN2));
        assert_eq!(run(&mut r, &header("a", 10), &mut f), []);
    }

    #[test]
    fn noise_never_panics() {
        let mut x = 0x1234_5678_9ABC_DEF0u64;
        for _ in 0..200 {
            let mut r = Receiver::new(1 << 18);
            for _ in 0..5000 {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                let b = match x % 8 {
                    0 => SOH,
                    1 => STX,
                    2 => EOT,
                    _ => (x >> 8) as u8,
                };
                let _ = r.feed(b);
                let _ = r.data();
            }
        }
    }
}
