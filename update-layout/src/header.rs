//! The image header: 32 bytes at a fixed offset of every application image, right
//! after its vector table, with the image's version and the key it trusts.
//!
//! ```text
//!  ACTIVE + 0x200 (HEADER_OFFSET), 32 bytes, little-endian:
//!  0       4       5       6        8        12       16                 32
//!  +-------+-------+-------+--------+--------+--------+------------------+
//!  | magic | major | minor | patch  | build  | flags  | key id           |
//!  | DCIH  | u8    | u8    | u16    | u32    | u32    | 16 B             |
//!  +-------+-------+-------+--------+--------+--------+------------------+
//!  version: major.minor.patch+build, as MCUboot's `imgtool sign --version` stamps it
//!  flags:   bit 0: stamped by the signing tool (else the build's own, from Cargo.toml,
//!           build 0); bits 8-15: the partition map the image is linked for
//!           (`layout::Layout`'s number; 0 in images built before layout C, whose
//!           headers named none); the other bits 0
//!  key id:  the first 16 bytes of the ed25519 public key the image verifies updates with
//! ```
//!
//! The signing tool (`tools/sign-image.sh --version X.Y.Z[+B]`) writes the version and
//! sets bit 0 **before** it signs, so the version is covered by the signature: one build
//! gives an old and a new image that differ only in their header. The application reads
//! its own header from ACTIVE (and a previous image's from DFU page 1). Format version 1
//! is the magic `DCIH`; another format takes another magic.

/// Offset of the header in the image (after the 98-entry vector table, 0x188 bytes).
pub const HEADER_OFFSET: u32 = 0x200;
/// The header's length.
pub const HEADER_LEN: usize = 32;
/// Format version 1.
pub const MAGIC: [u8; 4] = *b"DCIH";
/// Flag: the version was stamped by the signing tool.
pub const FLAG_STAMPED: u32 = 1;
/// The flags' bits that hold the image's layout (`layout::Layout::id`).
pub const LAYOUT_SHIFT: u32 = 8;
/// Bytes of the public key kept as its id.
pub const KEY_ID_LEN: usize = 16;

/// An image's version: major.minor.patch+build.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, PartialOrd, Ord)]
pub struct Version {
    /// Major.
    pub major: u8,
    /// Minor.
    pub minor: u8,
    /// Patch.
    pub patch: u16,
    /// Build number (0: none shown).
    pub build: u32,
}

/// Longest text of a version (`255.255.65535+4294967295`).
pub const VERSION_TEXT_MAX: usize = 24;

impl Version {
    /// Its 8 bytes in the header (and in the application's records).
    pub const fn to_bytes(self) -> [u8; 8] {
        let p = self.patch.to_le_bytes();
        let b = self.build.to_le_bytes();
        [self.major, self.minor, p[0], p[1], b[0], b[1], b[2], b[3]]
    }

    /// From its 8 bytes.
    pub const fn from_bytes(b: [u8; 8]) -> Self {
        Self {
            major: b[0],
            minor: b[1],
            patch: u16::from_le_bytes([b[2], b[3]]),
            build: u32::from_le_bytes([b[4], b[5], b[6], b[7]]),
        }
    }

    /// `major.minor.patch`, and `+build` when the build is not 0, into `out`; the length
    /// written. By hand, not `core::fmt`: the image reports it in three places and
    /// pulls in no formatting machinery for it.
    pub fn write_text(self, out: &mut [u8; VERSION_TEXT_MAX]) -> usize {
        let mut n = 0;
        let parts: [(u32, u8); 4] = [
            (self.major as u32, b'.'),
            (self.minor as u32, b'.'),
            (self.patch as u32, b'+'),
            (self.build, 0),
        ];
        for (i, (v, sep)) in parts.into_iter().enumerate() {
            if i == 3 && v == 0 {
                break;
            }
            if i == 3 {
                if let Some(s) = out.get_mut(n) {
                    *s = b'+';
                }
                n += 1;
            }
            let mut digits = [0u8; 10];
            let mut k = 0;
            let mut x = v;
            loop {
                if let Some(d) = digits.get_mut(k) {
                    *d = b'0' + (x % 10) as u8;
                }
                k += 1;
                x /= 10;
                if x == 0 {
                    break;
                }
            }
            while k > 0 {
                k -= 1;
                if let (Some(s), Some(&d)) = (out.get_mut(n), digits.get(k)) {
                    *s = d;
                }
                n += 1;
            }
            if i < 2 {
                if let Some(s) = out.get_mut(n) {
                    *s = sep;
                }
                n += 1;
            }
        }
        n.min(VERSION_TEXT_MAX)
    }
}

/// A parsed header.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Header {
    /// The image's version.
    pub version: Version,
    /// Flags ([`FLAG_STAMPED`]).
    pub flags: u32,
    /// The first bytes of the public key the image trusts.
    pub key_id: [u8; KEY_ID_LEN],
}

impl Header {
    /// The flags of an image built for `layout`, not stamped.
    pub const fn flags_for(layout: crate::layout::Layout) -> u32 {
        (layout.id() as u32) << LAYOUT_SHIFT
    }

    /// The number of the layout the image names (0: none, an image from before layout C).
    pub const fn layout_id(&self) -> u8 {
        (self.flags >> LAYOUT_SHIFT) as u8
    }

    /// The header's bytes.
    pub const fn to_bytes(self) -> [u8; HEADER_LEN] {
        let [m0, m1, m2, m3] = MAGIC;
        let [v0, v1, v2, v3, v4, v5, v6, v7] = self.version.to_bytes();
        let [f0, f1, f2, f3] = self.flags.to_le_bytes();
        let [k0, k1, k2, k3, k4, k5, k6, k7, k8, k9, k10, k11, k12, k13, k14, k15] = self.key_id;
        [
            m0, m1, m2, m3, v0, v1, v2, v3, v4, v5, v6, v7, f0, f1, f2, f3, k0, k1, k2, k3, k4, k5,
            k6, k7, k8, k9, k10, k11, k12, k13, k14, k15,
        ]
    }

    /// From the bytes at [`HEADER_OFFSET`]; `None` without the magic (erased flash, an
    /// image from before the header, a partial update).
    pub fn parse(b: &[u8; HEADER_LEN]) -> Option<Self> {
        let (magic, rest) = b.split_first_chunk::<4>()?;
        if *magic != MAGIC {
            return None;
        }
        let (v, rest) = rest.split_first_chunk::<8>()?;
        let (f, rest) = rest.split_first_chunk::<4>()?;
        let (k, _) = rest.split_first_chunk::<KEY_ID_LEN>()?;
        Some(Self {
            version: Version::from_bytes(*v),
            flags: u32::from_le_bytes(*f),
            key_id: *k,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn text(v: Version) -> std::string::String {
        let mut b = [0u8; VERSION_TEXT_MAX];
        let n = v.write_text(&mut b);
        std::string::String::from_utf8(b[..n].to_vec()).unwrap()
    }

    #[test]
    fn versions_read_as_imgtool_writes_them() {
        let v = |major, minor, patch, build| Version {
            major,
            minor,
            patch,
            build,
        };
        assert_eq!(text(v(0, 1, 0, 0)), "0.1.0");
        assert_eq!(text(v(0, 1, 1, 0)), "0.1.1");
        assert_eq!(text(v(12, 0, 305, 7)), "12.0.305+7");
        assert_eq!(
            text(v(255, 255, 65535, u32::MAX)),
            "255.255.65535+4294967295"
        );
        assert!(v(0, 1, 1, 0) > v(0, 1, 0, 9));
    }

    #[test]
    fn a_header_round_trips_and_erased_flash_is_none() {
        let h = Header {
            version: Version {
                major: 1,
                minor: 2,
                patch: 3,
                build: 4,
            },
            flags: FLAG_STAMPED,
            key_id: [7; KEY_ID_LEN],
        };
        let b = h.to_bytes();
        assert_eq!(
            h.layout_id(),
            0,
            "no layout named: an image from before layout C"
        );
        assert_eq!(&b[..4], b"DCIH");
        assert_eq!(&b[4..12], &[1, 2, 3, 0, 4, 0, 0, 0]);
        assert_eq!(Header::parse(&b), Some(h));
        assert_eq!(Header::parse(&[0xFF; HEADER_LEN]), None);
    }

    #[test]
    fn a_header_names_its_layout_in_flags_bits_8_to_15() {
        use crate::layout::Layout;
        let flags = Header::flags_for(Layout::C) | FLAG_STAMPED;
        assert_eq!(flags, 0x0301);
        let h = Header {
            version: Version::default(),
            flags,
            key_id: [0; KEY_ID_LEN],
        };
        let b = h.to_bytes();
        // The byte at header offset 13 (image offset 0x20D) is the layout's number.
        assert_eq!(b[13], 3);
        assert_eq!(Header::parse(&b).map(|h| h.layout_id()), Some(3));
    }
}
