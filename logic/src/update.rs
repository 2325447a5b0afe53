//! The update file's format (issue 21, docs/update.md), checked before anything is
//! marked for the swap: the application's bytes, then a 72-byte trailer.
//!
//! ```text
//!  0                      len          len+64        len+68   len+72
//!  +----------------------+-------------+-------------+--------+
//!  | image (len B, words) | signature   | len, u32 LE | "DCS1" |
//!  +----------------------+-------------+-------------+--------+
//!  signature: ed25519(key, SHA-512(image)) — what embassy-boot's
//!  verify_and_mark_updated(public key, signature, len) checks against DFU page 0
//! ```
//!
//! `tools/sign-image.sh` writes it. Format version 1 is the magic `DCS1`; another
//! format takes another magic. The image must be an application linked behind the
//! bootloader ([`vector_table_ok`], the bootloader's own rule): a file built for
//! 0x0800_0000, or not an image at all, is refused here, before its signature is even
//! looked at. Nothing here panics on any input.

/// Length of the trailer.
pub const TRAILER_LEN: usize = 72;
/// Format version 1.
pub const MAGIC: [u8; 4] = *b"DCS1";

/// The trailer of a well-formed file.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Trailer {
    /// The image's length, bytes (the file less the trailer).
    pub len: u32,
    /// The ed25519 signature of the image's SHA-512.
    pub signature: [u8; 64],
}

/// Why a file is refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Refusal {
    /// Shorter than a vector table and a trailer.
    TooShort,
    /// No `DCS1` at the end: not an update file, or truncated.
    NoMagic,
    /// The trailer's length is not the file's less the trailer (truncated or padded).
    Length,
    /// The image is not whole words.
    NotWords,
    /// The image does not fit the application's partition.
    TooLarge,
    /// The image's vector table does not point into the application's partition.
    NotBootable,
}

impl Refusal {
    /// For the technician: one line.
    pub fn text(self) -> &'static str {
        match self {
            Self::TooShort => "too short to be an image",
            Self::NoMagic => "no update trailer (not a signed image, or truncated)",
            Self::Length => "truncated or padded: the trailer's length is not the file's",
            Self::NotWords => "the image is not whole words",
            Self::TooLarge => "the image does not fit the application's partition",
            Self::NotBootable => "not an application linked behind the bootloader",
        }
    }
}

/// Check a received file of `file_len` bytes by its last [`TRAILER_LEN`] bytes `tail`
/// and its first 8 (`head`: the vector table's SP and reset vector), for a partition of
/// `partition_len` bytes at `partition_base` (the trailer must fit in it too).
pub fn check(
    file_len: u32,
    head: &[u8; 8],
    tail: &[u8; TRAILER_LEN],
    partition_base: u32,
    partition_len: u32,
) -> Result<Trailer, Refusal> {
    if (file_len as usize) < TRAILER_LEN + 8 {
        return Err(Refusal::TooShort);
    }
    let [s @ .., m0, m1, m2, m3] = *tail;
    if [m0, m1, m2, m3] != MAGIC {
        return Err(Refusal::NoMagic);
    }
    let [sig @ .., l0, l1, l2, l3] = s;
    let len = u32::from_le_bytes([l0, l1, l2, l3]);
    if len as u64 + TRAILER_LEN as u64 != file_len as u64 {
        return Err(Refusal::Length);
    }
    if len % 4 != 0 {
        return Err(Refusal::NotWords);
    }
    if file_len > partition_len {
        return Err(Refusal::TooLarge);
    }
    if !vector_table_ok(head, partition_base, partition_len) {
        return Err(Refusal::NotBootable);
    }
    Ok(Trailer {
        len,
        signature: sig,
    })
}

/// The bootloader's rule for a vector table it jumps to: the initial SP in SRAM
/// (word-aligned, the top included), the reset vector inside the partition with the
/// Thumb bit.
pub fn vector_table_ok(head: &[u8; 8], base: u32, len: u32) -> bool {
    let [a, b, c, d, e, f, g, h] = *head;
    let sp = u32::from_le_bytes([a, b, c, d]);
    let pc = u32::from_le_bytes([e, f, g, h]);
    let sp_ok = sp > 0x2000_0000 && sp <= 0x2002_0000 && sp % 4 == 0;
    let pc_ok = pc & 1 == 1 && pc > base && pc < base.saturating_add(len);
    sp_ok && pc_ok
}

#[cfg(test)]
#[allow(clippy::unwrap_used, clippy::indexing_slicing)]
mod tests {
    extern crate std;
    use super::*;
    use std::vec::Vec;

    const BASE: u32 = 0x0800_8000;
    const LEN: u32 = 224 * 1024;

    fn file(image_len: usize) -> Vec<u8> {
        let mut f: Vec<u8> = (0..image_len).map(|i| i as u8).collect();
        f[..4].copy_from_slice(&0x2000_6000u32.to_le_bytes());
        f[4..8].copy_from_slice(&0x0800_8189u32.to_le_bytes());
        f.extend([0x5A; 64]);
        f.extend((image_len as u32).to_le_bytes());
        f.extend(MAGIC);
        f
    }

    fn run(f: &[u8]) -> Result<Trailer, Refusal> {
        let head: [u8; 8] = f[..8].try_into().unwrap();
        let tail: [u8; TRAILER_LEN] = f[f.len() - TRAILER_LEN..].try_into().unwrap();
        check(f.len() as u32, &head, &tail, BASE, LEN)
    }

    #[test]
    fn a_signed_image_is_taken_with_its_length_and_signature() {
        let t = run(&file(104_912)).unwrap();
        assert_eq!(t.len, 104_912);
        assert_eq!(t.signature, [0x5A; 64]);
    }

    #[test]
    fn truncated_padded_foreign_and_oversized_files_are_refused() {
        let f = file(4096);
        // Truncated: the magic is gone.
        assert_eq!(run(&f[..f.len() - 100]), Err(Refusal::NoMagic));
        // Cut inside the image but the trailer kept (a bad concatenation).
        let mut cut = f[..1000].to_vec();
        cut.extend(&f[f.len() - TRAILER_LEN..]);
        assert_eq!(run(&cut), Err(Refusal::Length));
        // Not whole words.
        let g = file(4098);
        assert_eq!(run(&g), Err(Refusal::NotWords));
        // Linked at 0x08000000 (no bootloader).
        let mut h = file(4096);
        h[4..8].copy_from_slice(&0x0800_0189u32.to_le_bytes());
        assert_eq!(run(&h), Err(Refusal::NotBootable));
        // Larger than the partition.
        assert_eq!(run(&file(LEN as usize)), Err(Refusal::TooLarge));
        assert_eq!(run(&[0u8; 79]), Err(Refusal::TooShort));
        for r in [Refusal::TooShort, Refusal::NoMagic, Refusal::NotBootable] {
            assert!(!r.text().is_empty());
        }
    }
}
