//! An update file checked before anything is sent: the board's own checks
//! (`docking_logic::update::check` for the trailer, `check_head` for the vector table
//! and the image header's layout: the same code, so the tool refuses what the board would,
//! in the board's words), the size against `update_layout::layout::UPDATE_IMAGE_MAX`,
//! and what a technician wants to know first: its version, its layout, and whether it
//! is signed with the test key (its signature then checked against it here).

use docking_logic::update::{check, check_head, Refusal, TRAILER_LEN};
use update_layout::header::{Header, Version, FLAG_STAMPED, HEADER_LEN, HEADER_OFFSET, KEY_ID_LEN};
use update_layout::layout::{Layout, ACTIVE_BASE, ACTIVE_LEN, LAYOUT, UPDATE_IMAGE_MAX};

/// The test key (boot/keys/test-public-key.bin): an image that trusts it says so, and
/// a file signed with it is checked against it before it is sent.
pub const TEST_PUBLIC_KEY: &[u8; 32] = include_bytes!("../../boot/keys/test-public-key.bin");

/// What the tool found in an update file.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct FileInfo {
    /// The file's bytes (image and trailer).
    pub file_len: usize,
    /// The image's bytes (the file less the trailer).
    pub image_len: u32,
    /// The version in its header.
    pub version: Version,
    /// The version was stamped by the signing tool (else the build's own).
    pub stamped: bool,
    /// The layout its header names.
    pub layout: Layout,
    /// The first bytes of the key the image trusts for its own updates.
    pub key_id: [u8; KEY_ID_LEN],
    /// The image trusts the test key (its header's key id): once it runs, the board
    /// takes any update signed with the test key, whose private half is public.
    pub test_key: bool,
    /// The file is signed with the test key (its signature verifies with it).
    pub signed_with_test_key: bool,
}

impl FileInfo {
    /// The image's share of what an update can carry in this layout, %.
    pub fn share_pct(&self) -> f64 {
        100.0 * f64::from(self.image_len) / f64::from(UPDATE_IMAGE_MAX)
    }
}

/// A version as text (`0.1.1`, `1.2.3+4`).
pub fn version_text(v: Version) -> String {
    let mut b = [0u8; update_layout::header::VERSION_TEXT_MAX];
    let n = v.write_text(&mut b);
    String::from_utf8_lossy(&b[..n]).into_owned()
}

/// Parse `major.minor.patch[+build]`.
pub fn parse_version(s: &str) -> Option<Version> {
    let (main, build) = match s.split_once('+') {
        Some((m, b)) => (m, b.parse().ok()?),
        None => (s, 0),
    };
    let mut p = main.split('.');
    let v = Version {
        major: p.next()?.parse().ok()?,
        minor: p.next()?.parse().ok()?,
        patch: p.next()?.parse().ok()?,
        build,
    };
    p.next().is_none().then_some(v)
}

/// Check an update file. `Err`: one line saying why it cannot be sent.
pub fn check_file(f: &[u8]) -> Result<FileInfo, String> {
    if f.starts_with(b"\x7fELF") {
        return Err(
            "an ELF, not an update file: sign it first (bash tools/sign-image.sh --version X.Y.Z ELF)"
                .into(),
        );
    }
    let Ok(file_len) = u32::try_from(f.len()) else {
        return Err(format!("not an update file: {} bytes", f.len()));
    };
    let (Some(head), Some(tail)) = (
        f.first_chunk::<8>(),
        f.len()
            .checked_sub(TRAILER_LEN)
            .and_then(|at| f.get(at..))
            .and_then(|t| <&[u8; TRAILER_LEN]>::try_from(t).ok()),
    ) else {
        return Err(format!("not an update file: {} bytes, too short", f.len()));
    };
    let refused = |r: Refusal| -> String {
        match r {
            Refusal::NoMagic => "not an update file: no update trailer (DCS1) at its end (unsigned, truncated, or another file: sign the ELF with bash tools/sign-image.sh)".into(),
            Refusal::Length => "not a whole update file: its trailer's length is not the file's (truncated, or something appended)".into(),
            Refusal::OtherLayout(_) => format!("an image for another layout: {}", r.text()),
            r => format!("not an update file for this board: {}", r.text()),
        }
    };
    // The trailer (magic, length, words), then the head as the board checks its first
    // block: a file for another layout is named as such rather than "not bootable".
    if let Err(r) = check(file_len, head, tail, ACTIVE_BASE, ACTIVE_LEN) {
        if r == Refusal::NotBootable || r == Refusal::TooLarge {
            check_head(f.get(..1024).unwrap_or(f)).map_err(refused)?;
        }
        return Err(refused(r));
    }
    check_head(f.get(..1024).unwrap_or(f)).map_err(refused)?;
    let image_len = file_len - TRAILER_LEN as u32;
    if image_len > UPDATE_IMAGE_MAX {
        return Err(format!(
            "image too large for layout {}: {image_len} B, at most {UPDATE_IMAGE_MAX} B",
            LAYOUT.name()
        ));
    }
    let at = HEADER_OFFSET as usize;
    let header = f
        .get(at..at + HEADER_LEN)
        .and_then(|h| <[u8; HEADER_LEN]>::try_from(h).ok())
        .and_then(|h| Header::parse(&h))
        .ok_or_else(|| refused(Refusal::NoHeader))?;
    let layout =
        Layout::from_id(header.layout_id()).ok_or_else(|| refused(Refusal::OtherLayout(None)))?;
    let test_key = header.key_id[..] == TEST_PUBLIC_KEY[..KEY_ID_LEN];
    let signed_with_test_key = verifies(&f[..image_len as usize], &tail[..64], TEST_PUBLIC_KEY);
    Ok(FileInfo {
        file_len: f.len(),
        image_len,
        version: header.version,
        stamped: header.flags & FLAG_STAMPED != 0,
        layout,
        key_id: header.key_id,
        test_key,
        signed_with_test_key,
    })
}

/// Whether `sig` is the ed25519 signature of `image`'s SHA-512 by `key` (what the
/// board's updater checks with its built-in key).
pub fn verifies(image: &[u8], sig: &[u8], key: &[u8; 32]) -> bool {
    let (Ok(public), Ok(sig)) = (salty::PublicKey::try_from(key), <[u8; 64]>::try_from(sig)) else {
        return false;
    };
    let digest = salty::Sha512::new().updated(image).finalize();
    public
        .verify(&digest, &salty::Signature::from(&sig))
        .is_ok()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn versions_parse_as_the_board_writes_them() {
        for t in ["0.1.0", "0.1.1", "12.0.305+7"] {
            assert_eq!(version_text(parse_version(t).unwrap()), t);
        }
        for t in ["0.1", "1.2.3.4", "a.b.c", "1.2.3+", "256.0.0"] {
            assert!(parse_version(t).is_none(), "{t}");
        }
    }

    #[test]
    fn what_is_not_an_update_file_is_named() {
        assert!(check_file(b"\x7fELF\x01\x01")
            .unwrap_err()
            .contains("an ELF"));
        assert!(check_file(b"short").unwrap_err().contains("too short"));
        let junk = vec![0x5Au8; 4096];
        assert!(check_file(&junk).unwrap_err().contains("no update trailer"));
    }
}
