//! The CRCs the controller computes, by nibble: CRC-32/ISO-HDLC (the odometer's
//! records, the crash record), CRC-16/MODBUS (the PLC link) and CRC-16/XMODEM (the
//! YMODEM update transfer). Each takes a 16-entry table (64 or 32 bytes) instead of the
//! `crc` crate's 256 entries (1 024 or 512 bytes of flash; issue 20), at two lookups a byte; the values are the same (tested
//! against the `crc` crate), so the persisted records and the frames on the line are
//! unchanged.

/// CRC-32/ISO-HDLC (reflected polynomial 0xEDB8_8320, initial and final XOR all ones).
const CRC32_NIBBLES: [u32; 16] = nibbles32(0xEDB8_8320);
/// CRC-16/MODBUS (reflected polynomial 0xA001, initial 0xFFFF, no final XOR).
const CRC16_NIBBLES: [u16; 16] = nibbles16(0xA001);
/// CRC-16/XMODEM (polynomial 0x1021, most significant bit first, initial 0, no final
/// XOR).
const XMODEM_NIBBLES: [u16; 16] = nibbles16_msb(0x1021);

// Evaluated at compile time only (the tables are consts): an index out of range
// would fail the build, never panic on the board.
#[allow(clippy::indexing_slicing)]
const fn nibbles32(poly: u32) -> [u32; 16] {
    let mut t = [0u32; 16];
    let mut i = 0;
    while i < 16 {
        let mut c = i as u32;
        let mut k = 0;
        while k < 4 {
            c = if c & 1 != 0 { (c >> 1) ^ poly } else { c >> 1 };
            k += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
}

// Evaluated at compile time only (the tables are consts): an index out of range
// would fail the build, never panic on the board.
#[allow(clippy::indexing_slicing)]
const fn nibbles16(poly: u16) -> [u16; 16] {
    let mut t = [0u16; 16];
    let mut i = 0;
    while i < 16 {
        let mut c = i as u16;
        let mut k = 0;
        while k < 4 {
            c = if c & 1 != 0 { (c >> 1) ^ poly } else { c >> 1 };
            k += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
}

// Evaluated at compile time only, as above.
#[allow(clippy::indexing_slicing)]
const fn nibbles16_msb(poly: u16) -> [u16; 16] {
    let mut t = [0u16; 16];
    let mut i = 0;
    while i < 16 {
        let mut c = (i as u16) << 12;
        let mut k = 0;
        while k < 4 {
            c = if c & 0x8000 != 0 {
                (c << 1) ^ poly
            } else {
                c << 1
            };
            k += 1;
        }
        t[i] = c;
        i += 1;
    }
    t
}

/// A CRC-32/ISO-HDLC over bytes given in pieces.
#[derive(Clone, Copy, Debug)]
pub struct Crc32(u32);

impl Default for Crc32 {
    fn default() -> Self {
        Self::new()
    }
}

impl Crc32 {
    pub const fn new() -> Self {
        Self(!0)
    }

    pub fn update(&mut self, bytes: &[u8]) {
        let mut c = self.0;
        for &b in bytes {
            c ^= u32::from(b);
            c = (c >> 4) ^ CRC32_NIBBLES.get(c as usize & 15).copied().unwrap_or(0);
            c = (c >> 4) ^ CRC32_NIBBLES.get(c as usize & 15).copied().unwrap_or(0);
        }
        self.0 = c;
    }

    pub const fn finalize(self) -> u32 {
        !self.0
    }
}

/// CRC-32/ISO-HDLC of `bytes`.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut d = Crc32::new();
    d.update(bytes);
    d.finalize()
}

/// CRC-16/MODBUS of `bytes` (sent on the line low byte first).
pub fn crc16_modbus(bytes: &[u8]) -> u16 {
    let mut c: u16 = 0xFFFF;
    for &b in bytes {
        c ^= u16::from(b);
        c = (c >> 4) ^ CRC16_NIBBLES.get(usize::from(c) & 15).copied().unwrap_or(0);
        c = (c >> 4) ^ CRC16_NIBBLES.get(usize::from(c) & 15).copied().unwrap_or(0);
    }
    c
}

/// CRC-16/XMODEM of `bytes` (sent big-endian after a YMODEM packet's data).
pub fn crc16_xmodem(bytes: &[u8]) -> u16 {
    let mut c: u16 = 0;
    for &b in bytes {
        c ^= u16::from(b) << 8;
        c = (c << 4)
            ^ XMODEM_NIBBLES
                .get(usize::from(c >> 12))
                .copied()
                .unwrap_or(0);
        c = (c << 4)
            ^ XMODEM_NIBBLES
                .get(usize::from(c >> 12))
                .copied()
                .unwrap_or(0);
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;

    const REF32: crc::Crc<u32> = crc::Crc::<u32>::new(&crc::CRC_32_ISO_HDLC);
    const REF16: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_MODBUS);
    const XMODEM: crc::Crc<u16> = crc::Crc::<u16>::new(&crc::CRC_16_XMODEM);

    fn data(n: usize, seed: u32) -> [u8; 300] {
        let mut out = [0u8; 300];
        let mut x = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
        for b in out.iter_mut().take(n) {
            x ^= x << 13;
            x ^= x >> 17;
            x ^= x << 5;
            *b = x as u8;
        }
        out
    }

    #[test]
    fn the_nibble_crcs_are_the_crc_crates() {
        assert_eq!(crc32(b"123456789"), 0xCBF4_3926);
        assert_eq!(crc16_modbus(b"123456789"), 0x4B37);
        assert_eq!(crc16_xmodem(b"123456789"), 0x31C3);
        for n in 0..300 {
            for seed in 0..4 {
                let d = data(n, seed);
                let s = &d[..n];
                assert_eq!(crc32(s), REF32.checksum(s), "crc32, {n} bytes");
                assert_eq!(crc16_modbus(s), REF16.checksum(s), "crc16, {n} bytes");
                assert_eq!(crc16_xmodem(s), XMODEM.checksum(s), "xmodem, {n} bytes");
                // In pieces, as the record log feeds it.
                let mut p = Crc32::new();
                let (a, b) = s.split_at(n / 3);
                p.update(a);
                p.update(b);
                assert_eq!(p.finalize(), REF32.checksum(s));
            }
        }
    }
}
