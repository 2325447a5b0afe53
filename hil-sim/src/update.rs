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

pub use docking_logic::ymodem::SendState;
use docking_logic::ymodem::{Sender, PACKET_MAX};

/// A YMODEM-1K sender of one file (lrzsz's `sb -k`), owning its file: the project's
/// sender ([`docking_logic::ymodem::Sender`], beside the receiver and sharing its
/// constants; `dockctl update` sends with it too) with the packets it builds returned
/// as vectors.
pub struct YmodemSender {
    inner: Sender,
    data: Vec<u8>,
    /// Where it stands (as [`Sender::state`] after the last call).
    pub state: SendState,
    /// Packets sent again (on a NAK, a repeated 'C' or a time-out).
    pub retries: u32,
}

impl YmodemSender {
    /// A sender of `data` as file `name`.
    pub fn new(name: &str, data: Vec<u8>) -> Self {
        let inner = Sender::new(name, data.len() as u32);
        Self {
            state: inner.state(),
            retries: 0,
            inner,
            data,
        }
    }

    /// What a call built, and the state after it.
    fn sent(&mut self, out: &[u8; PACKET_MAX], n: usize) -> Vec<u8> {
        self.state = self.inner.state();
        self.retries = self.inner.retries();
        out[..n].to_vec()
    }

    /// Whether the transfer is over (done or cancelled).
    pub fn finished(&self) -> bool {
        self.inner.finished()
    }

    /// Bytes of the file acknowledged so far.
    pub fn acknowledged(&self) -> usize {
        self.inner.acknowledged() as usize
    }

    /// The sender's own timeout ran out (lrzsz's `sb`: 10 s without an answer): the
    /// packet it waits on, again; nothing while it waits for the receiver's 'C'.
    pub fn on_timeout(&mut self) -> Vec<u8> {
        let mut out = [0u8; PACKET_MAX];
        let n = self.inner.on_timeout(&self.data, &mut out);
        self.sent(&out, n)
    }

    /// One byte from the receiver; what to send back.
    pub fn on_byte(&mut self, b: u8) -> Vec<u8> {
        let mut out = [0u8; PACKET_MAX];
        let n = self.inner.on_byte(b, &self.data, &mut out);
        self.sent(&out, n)
    }
}

/// CRC-16/XMODEM (poly 0x1021, init 0), bit by bit: not the logic crate's table, so
/// the tests check the shared sender's packets against a CRC of their own.
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

    /// The shared sender's blocks carry the file and a CRC that this bit-by-bit one
    /// agrees with (the sender's is the receiver's table: a mistake there would pass a
    /// sender-to-receiver test).
    #[test]
    fn the_shared_senders_blocks_carry_this_crc() {
        use docking_logic::ymodem::{ACK, C, STX};
        let file: Vec<u8> = (0..2500u32).map(|i| (i * 7 + i / 3) as u8).collect();
        let mut s = YmodemSender::new("f", file.clone());
        let b0 = s.on_byte(C);
        assert_eq!(b0.len(), 133);
        assert_eq!(crc16_xmodem(&b0[3..131]).to_be_bytes(), [b0[131], b0[132]]);
        assert!(s.on_byte(ACK).is_empty());
        let mut got = Vec::new();
        let mut p = s.on_byte(C);
        while p.first() == Some(&STX) {
            assert_eq!(p.len(), 1029);
            assert_eq!(crc16_xmodem(&p[3..1027]).to_be_bytes(), [p[1027], p[1028]]);
            got.extend_from_slice(&p[3..1027]);
            p = s.on_byte(ACK);
        }
        assert_eq!(&got[..file.len()], &file[..]);
        assert_eq!(s.acknowledged(), file.len());
    }
}
