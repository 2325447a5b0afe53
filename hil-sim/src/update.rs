//! The far side of a field update (issue 21), for the host tests and the virtual board:
//! the update file as `tools/sign-image.sh` writes it ([`signed_file`], the version
//! stamped into the image header first, [`stamp`]), and a YMODEM-1K sender
//! ([`YmodemSender`]: what lrzsz's `sb -k` sends, answer by answer).
//!
//! The signer is salty's ed25519 (the same crate the firmware verifies with, built for
//! the host): ed25519 is deterministic, so a file signed here is byte for byte the
//! script's (vboard's `update` tests compare them).

use update_layout::header::{Version, FLAG_STAMPED, HEADER_OFFSET};

/// The test key's seed (boot/keys/test-signing-key.pem: PKCS#8, the seed its last 32
/// bytes).
pub fn test_key_seed() -> [u8; 32] {
    pem_seed(include_str!("../../boot/keys/test-signing-key.pem"))
        .unwrap_or_else(|| panic!("boot/keys/test-signing-key.pem is not an ed25519 key"))
}

/// Another key (a seed of its own): what an image signed by someone else carries.
pub fn other_key_seed() -> [u8; 32] {
    let mut s = [0u8; 32];
    for (i, b) in s.iter_mut().enumerate() {
        *b = (i as u8).wrapping_mul(37).wrapping_add(11);
    }
    s
}

/// The public key of `seed`.
pub fn public_key(seed: &[u8; 32]) -> [u8; 32] {
    salty::Keypair::from(seed).public.to_bytes()
}

fn pem_seed(pem: &str) -> Option<[u8; 32]> {
    let mut buf = [0u8; 64];
    let n = update_layout::pem::der(pem, &mut buf)?;
    let der = buf.get(..n)?;
    der.get(der.len().checked_sub(32)?..)?.try_into().ok()
}

/// Stamp `v` into `image`'s header (its version, the flag "stamped"), as
/// `sign-image.sh --version` does. `false`: the image has no header.
pub fn stamp(image: &mut [u8], v: Version) -> bool {
    let at = HEADER_OFFSET as usize;
    if image.get(at..at + 4) != Some(update_layout::header::MAGIC.as_slice()) {
        return false;
    }
    image[at + 4..at + 12].copy_from_slice(&v.to_bytes());
    let mut f = [0u8; 4];
    f.copy_from_slice(&image[at + 12..at + 16]);
    let flags = u32::from_le_bytes(f) | FLAG_STAMPED;
    image[at + 12..at + 16].copy_from_slice(&flags.to_le_bytes());
    true
}

/// The version in `image`'s header.
pub fn version_of(image: &[u8]) -> Option<Version> {
    let at = HEADER_OFFSET as usize;
    let h: [u8; 32] = image.get(at..at + 32)?.try_into().ok()?;
    update_layout::header::Header::parse(&h).map(|h| h.version)
}

/// The update file of `image` (padded with 0xFF to whole words), signed with `seed`:
/// image | ed25519(SHA-512(image)) | len u32 LE | "DCS1".
pub fn signed_file(image: &[u8], seed: &[u8; 32]) -> Vec<u8> {
    let mut f = image.to_vec();
    while f.len() % 4 != 0 {
        f.push(0xFF);
    }
    let len = f.len() as u32;
    let digest = salty::Sha512::new().updated(&f).finalize();
    let sig = salty::Keypair::from(seed).sign(&digest).to_bytes();
    f.extend_from_slice(&sig);
    f.extend_from_slice(&len.to_le_bytes());
    f.extend_from_slice(b"DCS1");
    f
}

// The protocol's bytes are the receiver's (one definition); the CRC below is the
// sender's own, so that a mistake in the receiver's table is not also the sender's.
use docking_logic::ymodem::{ACK, C, CAN, EOT, NAK, SOH, STX};

/// Where the sender stands.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SendState {
    /// Waiting for the receiver's first 'C'.
    Start,
    /// Block 0 sent: waiting for ACK (then 'C').
    Header,
    /// Waiting for the 'C' after block 0's ACK.
    HeaderC,
    /// Block `n` sent.
    Block(usize),
    /// EOT sent (first or second).
    Eot(u8),
    /// The closing empty block 0 sent.
    Close,
    /// Finished (the receiver acknowledged the end).
    Done,
    /// The receiver cancelled.
    Cancelled,
}

/// A YMODEM-1K sender of one file (lrzsz's `sb -k`): 1024-byte blocks (STX), CRC-16,
/// the file's name and size in block 0, EOT twice, an empty block 0 to end the batch.
pub struct YmodemSender {
    name: String,
    data: Vec<u8>,
    /// Where it stands.
    pub state: SendState,
    /// Blocks (re)sent on a NAK.
    pub retries: u32,
    can: bool,
}

impl YmodemSender {
    /// A sender of `data` as file `name`.
    pub fn new(name: &str, data: Vec<u8>) -> Self {
        Self {
            name: name.to_string(),
            data,
            state: SendState::Start,
            retries: 0,
            can: false,
        }
    }

    fn blocks(&self) -> usize {
        self.data.len().div_ceil(1024)
    }

    fn packet(blk: u8, data: &[u8], len: usize, pad: u8) -> Vec<u8> {
        let mut d = data.to_vec();
        d.resize(len, pad);
        let mut p = vec![if len == 128 { SOH } else { STX }, blk, !blk];
        p.extend_from_slice(&d);
        p.extend_from_slice(&crc16_xmodem(&d).to_be_bytes());
        p
    }

    fn header(&self) -> Vec<u8> {
        let mut h = self.name.as_bytes().to_vec();
        h.push(0);
        h.extend_from_slice(format!("{} 0 100644", self.data.len()).as_bytes());
        Self::packet(0, &h, 128, 0)
    }

    fn block(&self, n: usize) -> Vec<u8> {
        let from = (n - 1) * 1024;
        let to = (from + 1024).min(self.data.len());
        Self::packet(n as u8, &self.data[from..to], 1024, 0x1A)
    }

    /// Whether the transfer is over (done or cancelled).
    pub fn finished(&self) -> bool {
        matches!(self.state, SendState::Done | SendState::Cancelled)
    }

    /// Bytes of the file acknowledged so far.
    pub fn acknowledged(&self) -> usize {
        match self.state {
            SendState::Block(n) => ((n - 1) * 1024).min(self.data.len()),
            SendState::Eot(_) | SendState::Close | SendState::Done => self.data.len(),
            _ => 0,
        }
    }

    /// The sender's own timeout ran out (lrzsz's `sb`: 10 s without an answer): the
    /// packet it waits on, again; nothing while it waits for the receiver's 'C'.
    pub fn on_timeout(&mut self) -> Vec<u8> {
        match self.state {
            SendState::Header => {
                self.retries += 1;
                self.header()
            }
            SendState::Block(n) => {
                self.retries += 1;
                self.block(n)
            }
            SendState::Eot(_) => vec![EOT],
            _ => Vec::new(),
        }
    }

    /// One byte from the receiver; what to send back.
    pub fn on_byte(&mut self, b: u8) -> Vec<u8> {
        if b == CAN {
            if self.can {
                self.state = SendState::Cancelled;
            }
            self.can = true;
            return Vec::new();
        }
        self.can = false;
        match (self.state, b) {
            (SendState::Start, C) => {
                self.state = SendState::Header;
                self.header()
            }
            (SendState::Header, ACK) => {
                self.state = SendState::HeaderC;
                Vec::new()
            }
            (SendState::Header, NAK | C) => {
                self.retries += 1;
                self.header()
            }
            (SendState::HeaderC, C) => {
                if self.blocks() == 0 {
                    self.state = SendState::Eot(1);
                    return vec![EOT];
                }
                self.state = SendState::Block(1);
                self.block(1)
            }
            (SendState::Block(n), ACK) => {
                if n >= self.blocks() {
                    self.state = SendState::Eot(1);
                    vec![EOT]
                } else {
                    self.state = SendState::Block(n + 1);
                    self.block(n + 1)
                }
            }
            (SendState::Block(n), NAK) => {
                self.retries += 1;
                self.block(n)
            }
            (SendState::Eot(1), NAK) => {
                self.state = SendState::Eot(2);
                vec![EOT]
            }
            (SendState::Eot(_), ACK) => {
                self.state = SendState::Close;
                Vec::new()
            }
            (SendState::Close, C) => Self::packet(0, &[], 128, 0),
            (SendState::Close, ACK) => {
                self.state = SendState::Done;
                Vec::new()
            }
            _ => Vec::new(),
        }
    }
}

/// CRC-16/XMODEM (poly 0x1021, init 0), bit by bit: the sender's own, not the
/// receiver's table.
pub fn crc16_xmodem(data: &[u8]) -> u16 {
    let mut crc: u16 = 0;
    for &b in data {
        crc ^= u16::from(b) << 8;
        for _ in 0..8 {
            crc = if crc & 0x8000 != 0 {
                (crc << 1) ^ 0x1021
            } else {
                crc << 1
            };
        }
    }
    crc
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_test_key_is_the_one_in_boot_keys() {
        let public = std::fs::read(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../boot/keys/test-public-key.bin"
        ))
        .unwrap();
        assert_eq!(public_key(&test_key_seed()).as_slice(), public.as_slice());
        assert_ne!(public_key(&other_key_seed()), public_key(&test_key_seed()));
    }

    #[test]
    fn crc_matches_the_xmodem_check_value() {
        assert_eq!(crc16_xmodem(b"123456789"), 0x31C3);
    }
}
