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
//!
//! [`Sender`] is the other side (issue 35: `dockctl update`, the simulators' tests and
//! the virtual board's scenes send with it): lrzsz's `sb -k`, answer by answer, each
//! packet built into the caller's buffer (no allocation). It takes the protocol's bytes
//! from this module, one definition for both ends; its tests check its packets against
//! the `crc` crate's CRC, not this crate's, so a mistake in the table is not in both.

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

/// Copy `bytes` into `out` at `at` (as many as fit); how many.
fn put(out: &mut [u8], at: usize, bytes: &[u8]) -> usize {
    let n = bytes.len().min(out.len().saturating_sub(at));
    if let (Some(dst), Some(src)) = (out.get_mut(at..at + n), bytes.get(..n)) {
        dst.copy_from_slice(src);
    }
    n
}

/// Data bytes of a YMODEM-1K block (STX).
pub const BLOCK_LEN: usize = 1024;
/// Data bytes of a short block (SOH: block 0).
pub const SHORT_LEN: usize = 128;
/// The longest packet: STX, the block number and its complement, 1024 bytes, the CRC.
pub const PACKET_MAX: usize = BLOCK_LEN + 5;
/// The longest file name block 0 carries (a longer one is cut).
pub const NAME_MAX: usize = 64;
/// The padding of the last block (SUB, as lrzsz pads).
pub const PAD: u8 = 0x1A;

/// Where a [`Sender`] stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SendState {
    /// Waiting for the receiver's first 'C'.
    Start,
    /// Block 0 sent: waiting for its ACK (then 'C').
    Header,
    /// Waiting for the 'C' after block 0's ACK.
    HeaderC,
    /// Block `n` (1-based) sent: waiting for its ACK.
    Block(u32),
    /// EOT sent (the first, or the second after the receiver's NAK).
    Eot(u8),
    /// The closing empty block 0 sent, or about to be.
    Close,
    /// Finished: the receiver acknowledged the end of the batch.
    Done,
    /// The receiver cancelled (CAN CAN), or the sender did ([`Sender::cancel`]).
    Cancelled,
}

/// A YMODEM-1K sender of one file, as lrzsz's `sb -k` sends it: the file's name and
/// size in block 0 (SOH, 128 bytes), the data in 1024-byte blocks (STX, the last padded
/// with [`PAD`]), CRC-16, EOT answered by NAK then sent again, an empty block 0 to end
/// the batch. Each call answers one byte from the receiver (or the sender's own
/// time-out) with the bytes to send, built into the caller's `out`; the file is the
/// caller's, passed whole to each call (its length is the size given to [`Sender::new`]).
#[derive(Clone, Debug)]
pub struct Sender {
    name: [u8; NAME_MAX],
    name_len: usize,
    size: u32,
    state: SendState,
    retries: u32,
    can: bool,
}

impl Sender {
    /// A sender of a file of `size` bytes named `name` (cut to [`NAME_MAX`] bytes).
    pub fn new(name: &str, size: u32) -> Self {
        let mut n = [0u8; NAME_MAX];
        let len = name.len().min(NAME_MAX);
        if let (Some(dst), Some(src)) = (n.get_mut(..len), name.as_bytes().get(..len)) {
            dst.copy_from_slice(src);
        }
        Self {
            name: n,
            name_len: len,
            size,
            state: SendState::Start,
            retries: 0,
            can: false,
        }
    }

    /// Where it stands.
    pub fn state(&self) -> SendState {
        self.state
    }

    /// Packets sent again (on a NAK, a repeated 'C' or a time-out).
    pub fn retries(&self) -> u32 {
        self.retries
    }

    /// The file's blocks.
    pub fn blocks(&self) -> u32 {
        self.size.div_ceil(BLOCK_LEN as u32)
    }

    /// Whether the transfer is over (done or cancelled).
    pub fn finished(&self) -> bool {
        matches!(self.state, SendState::Done | SendState::Cancelled)
    }

    /// Bytes of the file the receiver has acknowledged.
    pub fn acknowledged(&self) -> u32 {
        match self.state {
            SendState::Block(n) => (n.saturating_sub(1) * BLOCK_LEN as u32).min(self.size),
            SendState::Eot(_) | SendState::Close | SendState::Done => self.size,
            _ => 0,
        }
    }

    /// Give up: the bytes that cancel the transfer (CAN CAN) into `out`.
    pub fn cancel(&mut self, out: &mut [u8; PACKET_MAX]) -> usize {
        self.state = SendState::Cancelled;
        put(out, 0, &[CAN, CAN])
    }

    /// A packet into `out`: block `blk`, `data` padded with `pad` to 128 bytes
    /// (`short`, SOH) or 1024 (STX), its CRC; its length.
    fn packet(out: &mut [u8; PACKET_MAX], blk: u8, data: &[u8], short: bool, pad: u8) -> usize {
        let (head, len) = if short {
            (SOH, SHORT_LEN)
        } else {
            (STX, BLOCK_LEN)
        };
        put(out, 0, &[head, blk, !blk]);
        let n = put(out, 3, data.get(..data.len().min(len)).unwrap_or(&[]));
        if let Some(rest) = out.get_mut(3 + n..3 + len) {
            rest.fill(pad);
        }
        let crc = crate::crc::crc16_xmodem(out.get(3..3 + len).unwrap_or(&[]));
        put(out, 3 + len, &crc.to_be_bytes());
        len + 5
    }

    /// Block 0: the name, NUL, the size in decimal, a modification time of 0 and the
    /// mode, as `sb` writes them; zero-padded.
    fn header(&self, out: &mut [u8; PACKET_MAX]) -> usize {
        let mut d = [0u8; SHORT_LEN];
        let mut at = put(&mut d, 0, self.name.get(..self.name_len).unwrap_or(&[])) + 1;
        let mut digits = [0u8; 10];
        let mut k = digits.len();
        let mut x = self.size;
        loop {
            k -= 1;
            if let Some(c) = digits.get_mut(k) {
                *c = b'0' + (x % 10) as u8;
            }
            x /= 10;
            if x == 0 || k == 0 {
                break;
            }
        }
        at += put(&mut d, at, digits.get(k..).unwrap_or(&[]));
        put(&mut d, at, b" 0 100644");
        Self::packet(out, 0, &d, true, 0)
    }

    /// Block `n` (1-based) of `file`.
    fn block(&self, n: u32, file: &[u8], out: &mut [u8; PACKET_MAX]) -> usize {
        let from = (n.saturating_sub(1) as usize).saturating_mul(BLOCK_LEN);
        let to = from.saturating_add(BLOCK_LEN).min(file.len());
        let data = file.get(from..to).unwrap_or(&[]);
        Self::packet(out, n as u8, data, false, PAD)
    }

    /// The sender's own time-out ran out (`sb` waits 10 s for an answer): the packet it
    /// waits on, again; nothing while it waits for the receiver's 'C'.
    pub fn on_timeout(&mut self, file: &[u8], out: &mut [u8; PACKET_MAX]) -> usize {
        match self.state {
            SendState::Header => {
                self.retries += 1;
                self.header(out)
            }
            SendState::Block(n) => {
                self.retries += 1;
                self.block(n, file, out)
            }
            SendState::Eot(_) => put(out, 0, &[EOT]),
            _ => 0,
        }
    }

    /// One byte from the receiver; the bytes to send back, in `out` (their count).
    pub fn on_byte(&mut self, b: u8, file: &[u8], out: &mut [u8; PACKET_MAX]) -> usize {
        if self.finished() {
            return 0;
        }
        if b == CAN {
            if self.can {
                self.state = SendState::Cancelled;
            }
            self.can = true;
            return 0;
        }
        self.can = false;
        match (self.state, b) {
            (SendState::Start, C) => {
                self.state = SendState::Header;
                self.header(out)
            }
            (SendState::Header, ACK) => {
                self.state = SendState::HeaderC;
                0
            }
            (SendState::Header, NAK | C) => {
                self.retries += 1;
                self.header(out)
            }
            (SendState::HeaderC, C) => {
                if self.blocks() == 0 {
                    self.state = SendState::Eot(1);
                    return put(out, 0, &[EOT]);
                }
                self.state = SendState::Block(1);
                self.block(1, file, out)
            }
            (SendState::Block(n), ACK) => {
                if n >= self.blocks() {
                    self.state = SendState::Eot(1);
                    put(out, 0, &[EOT])
                } else {
                    self.state = SendState::Block(n + 1);
                    self.block(n + 1, file, out)
                }
            }
            (SendState::Block(n), NAK) => {
                self.retries += 1;
                self.block(n, file, out)
            }
            (SendState::Eot(1), NAK) => {
                self.state = SendState::Eot(2);
                put(out, 0, &[EOT])
            }
            (SendState::Eot(_), ACK) => {
                self.state = SendState::Close;
                0
            }
            (SendState::Close, C) => Self::packet(out, 0, &[], true, 0),
            (SendState::Close, ACK) => {
                self.state = SendState::Done;
                0
            }
            _ => 0,
        }
    }
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::indexing_slicing, clippy::panic)]
mod tests {
    extern crate std;
    use super::*;
    use std::format;
    use std::string::String;
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

    /// The sender's packet is well framed, its CRC the `crc` crate's (not this
    /// crate's table), its data `want` padded with `pad`.
    fn assert_packet(p: &[u8], blk: u8, want: &[u8], pad: u8) {
        let n = if p[0] == SOH { 128 } else { 1024 };
        assert_eq!(p.len(), n + 5);
        assert_eq!(p[0], if n == 128 { SOH } else { STX });
        assert_eq!((p[1], p[2]), (blk, !blk));
        let data = &p[3..3 + n];
        assert_eq!(&data[..want.len()], want);
        assert!(data[want.len()..].iter().all(|&b| b == pad));
        let crc = crc::Crc::<u16>::new(&crc::CRC_16_XMODEM).checksum(data);
        assert_eq!(&p[3 + n..], &crc.to_be_bytes());
    }

    /// Send `file` through a sender into a receiver, byte by byte both ways; the file
    /// received, and the sender.
    fn loopback(file: &[u8]) -> (Vec<u8>, Sender) {
        let mut tx = Sender::new("docking-controller.dcs", file.len() as u32);
        let mut rx = Receiver::new(1 << 20);
        let mut got = Vec::new();
        let mut out = [0u8; PACKET_MAX];
        let mut to_rx: Vec<u8> = Vec::new();
        let mut to_tx: Vec<u8> = rx.idle().to_vec();
        for _ in 0..10_000 {
            for b in core::mem::take(&mut to_tx) {
                let n = tx.on_byte(b, file, &mut out);
                to_rx.extend_from_slice(&out[..n]);
            }
            for b in core::mem::take(&mut to_rx) {
                match rx.feed(b) {
                    Action::Send(x) => to_tx.extend_from_slice(x),
                    Action::Start { .. } => to_tx.extend_from_slice(rx.ack()),
                    Action::Data { offset, len } => {
                        assert_eq!(offset as usize, got.len());
                        assert_eq!(rx.data().len(), len);
                        got.extend_from_slice(rx.data());
                        to_tx.extend_from_slice(rx.ack());
                    }
                    Action::Done(x) | Action::Aborted(_, x) => to_tx.extend_from_slice(x),
                    Action::None => {}
                }
            }
            if to_tx.is_empty() && to_rx.is_empty() {
                break;
            }
        }
        (got, tx)
    }

    #[test]
    fn the_sender_and_the_receiver_carry_a_file_whole() {
        for len in [1, 1023, 1024, 1025, 3000, 256 * 1024 + 7] {
            let img = image(len);
            let (got, tx) = loopback(&img);
            assert!(got == img, "{len} bytes");
            assert_eq!(tx.state(), SendState::Done);
            assert_eq!(tx.acknowledged(), len as u32);
            assert_eq!(tx.retries(), 0);
        }
    }

    #[test]
    fn the_senders_packets_are_sbs() {
        let img = image(1500);
        let mut tx = Sender::new("app.dcs", 1500);
        let mut out = [0u8; PACKET_MAX];
        // Nothing before the receiver's 'C'.
        assert_eq!(tx.on_byte(ACK, &img, &mut out), 0);
        let n = tx.on_byte(C, &img, &mut out);
        assert_packet(&out[..n], 0, b"app.dcs\x001500 0 100644", 0);
        assert_eq!(tx.on_byte(ACK, &img, &mut out), 0);
        let n = tx.on_byte(C, &img, &mut out);
        assert_packet(&out[..n], 1, &img[..1024], PAD);
        assert_eq!(tx.acknowledged(), 0);
        // A NAK: the same block again.
        let n = tx.on_byte(NAK, &img, &mut out);
        assert_packet(&out[..n], 1, &img[..1024], PAD);
        assert_eq!(tx.retries(), 1);
        let n = tx.on_byte(ACK, &img, &mut out);
        assert_packet(&out[..n], 2, &img[1024..], PAD);
        assert_eq!(tx.acknowledged(), 1024);
        // The time-out: the same block again.
        let n = tx.on_timeout(&img, &mut out);
        assert_packet(&out[..n], 2, &img[1024..], PAD);
        assert_eq!(tx.on_byte(ACK, &img, &mut out), 1);
        assert_eq!(out[0], EOT);
        assert_eq!(tx.acknowledged(), 1500);
        assert_eq!(tx.on_byte(NAK, &img, &mut out), 1);
        assert_eq!(out[0], EOT);
        assert_eq!(tx.on_byte(ACK, &img, &mut out), 0);
        let n = tx.on_byte(C, &img, &mut out);
        assert_packet(&out[..n], 0, &[], 0);
        assert_eq!(tx.on_byte(ACK, &img, &mut out), 0);
        assert!(tx.finished());
        assert_eq!(tx.state(), SendState::Done);
    }

    #[test]
    fn the_sender_stops_on_the_receivers_cancel_and_cancels_itself() {
        let img = image(5000);
        let mut out = [0u8; PACKET_MAX];
        let mut tx = Sender::new("a", 5000);
        tx.on_byte(C, &img, &mut out);
        tx.on_byte(ACK, &img, &mut out);
        tx.on_byte(C, &img, &mut out);
        // One CAN is noise; two cancel.
        assert_eq!(tx.on_byte(CAN, &img, &mut out), 0);
        assert!(!tx.finished());
        assert_eq!(tx.on_byte(CAN, &img, &mut out), 0);
        assert_eq!(tx.state(), SendState::Cancelled);
        assert_eq!(tx.on_byte(ACK, &img, &mut out), 0);
        let mut tx = Sender::new("a", 5000);
        assert_eq!(tx.cancel(&mut out), 2);
        assert_eq!(&out[..2], &[CAN, CAN]);
        assert!(tx.finished());
        // A receiver cancelled by the sender's CAN CAN ends without the file.
        let mut rx = Receiver::new(1 << 20);
        let mut f = Vec::new();
        run(&mut rx, &header("a", 5000), &mut f);
        assert_eq!(
            run(&mut rx, &out[..2], &mut f),
            [Action::Aborted(Abort::Cancelled, &[])]
        );
    }

    #[test]
    fn a_long_name_is_cut_and_block_numbers_wrap() {
        let name: String = core::iter::repeat_n('n', 100).collect();
        let img = image(300 * 1024);
        let mut tx = Sender::new(&name, img.len() as u32);
        let mut out = [0u8; PACKET_MAX];
        let n = tx.on_byte(C, &img, &mut out);
        let mut want = std::vec![b'n'; NAME_MAX];
        want.push(0);
        want.extend_from_slice(b"307200 0 100644");
        assert_packet(&out[..n], 0, &want, 0);
        tx.on_byte(ACK, &img, &mut out);
        tx.on_byte(C, &img, &mut out);
        for blk in 2..=257u32 {
            let n = tx.on_byte(ACK, &img, &mut out);
            let from = (blk as usize - 1) * 1024;
            assert_packet(&out[..n], blk as u8, &img[from..from + 1024], PAD);
        }
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
