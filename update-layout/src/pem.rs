//! The DER inside a PEM file (the body between the `-----` lines, standard base64), by
//! hand and without allocation: the application's build script (the public key it builds
//! in, `build.rs`, which includes this file by path) and the simulators' signer (the test
//! key's seed, `hil-sim/src/update.rs`) read the project's ed25519 keys with it. A
//! build script and a test signer need no crate for 60 bytes.

/// The DER bytes of `pem` into `out`, and how many; `None` for a character outside
/// base64 or a body longer than `out`.
pub fn der(pem: &str, out: &mut [u8]) -> Option<usize> {
    let mut n = 0;
    let (mut acc, mut bits) = (0u32, 0);
    for line in pem.lines().filter(|l| !l.starts_with("-----")) {
        for c in line.bytes().filter(|c| !c.is_ascii_whitespace()) {
            let v = match c {
                b'A'..=b'Z' => c - b'A',
                b'a'..=b'z' => c - b'a' + 26,
                b'0'..=b'9' => c - b'0' + 52,
                b'+' => 62,
                b'/' => 63,
                b'=' => return Some(n),
                _ => return None,
            };
            acc = (acc << 6) | u32::from(v);
            bits += 6;
            if bits >= 8 {
                bits -= 8;
                *out.get_mut(n)? = (acc >> bits) as u8;
                n += 1;
            }
        }
    }
    Some(n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_test_keys_pem_is_its_pkcs8_der() {
        let pem = include_str!("../../boot/keys/test-signing-key.pem");
        let mut out = [0u8; 64];
        let n = der(pem, &mut out).unwrap();
        // PKCS#8 for ed25519: 48 bytes, the seed's OCTET STRING last.
        assert_eq!(n, 48);
        assert_eq!(
            out[..16],
            [
                0x30, 0x2e, 0x02, 0x01, 0x00, 0x30, 0x05, 0x06, 0x03, 0x2b, 0x65, 0x70, 0x04, 0x22,
                0x04, 0x20
            ]
        );
    }

    #[test]
    fn base64_by_the_rfc_4648_vectors_and_bad_input() {
        let mut out = [0u8; 8];
        for (text, want) in [
            ("Zg==", &b"f"[..]),
            ("Zm8=", b"fo"),
            ("Zm9v", b"foo"),
            ("Zm9vYmFy", b"foobar"),
        ] {
            let n = der(text, &mut out).unwrap();
            assert_eq!(&out[..n], want, "{text}");
        }
        assert_eq!(der("Zm9v*", &mut out), None);
        assert_eq!(der("Zm9vYmFyZm9vYmFy", &mut out), None, "longer than out");
    }
}
