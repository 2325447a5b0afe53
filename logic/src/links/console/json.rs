//! A tiny JSON object writer over [`Sink`] (any [`core::fmt::Write`] is one) for `--json`
//! replies.
//!
//! Guarantees: no allocation, no float, no panic; every write error (`fmt::Error`,
//! e.g. a full buffer) is returned to the caller; the output is one line: strings
//! and keys are escaped (`"` → `\"`, `\` → `\\`, every control character — C0, DEL,
//! C1 — and U+2028/U+2029 as `\uXXXX`), and [`JsonObject::raw`] turns CR/LF into
//! spaces. Output is valid JSON as long as `raw` is given valid JSON and `finish` is
//! called. Keys are not checked for duplicates.
//!
//! ```
//! use docking_logic::console::json::JsonObject;
//! let mut s = heapless::String::<128>::new();
//! let mut o = JsonObject::new(&mut s);
//! o.str("cone", "cf-peek")?.fixed("bore_mm", 26050, 3)?;
//! o.array("faults", |a| {
//!     a.object(|f| {
//!         f.u64("code", 3)?;
//!         Ok(())
//!     })?;
//!     Ok(())
//! })?;
//! o.finish()?;
//! assert_eq!(s, r#"{"cone":"cf-peek","bore_mm":26.050,"faults":[{"code":3}]}"#);
//! # Ok::<(), core::fmt::Error>(())
//! ```

use core::fmt::{self, Write};

/// Where the console's text goes: one method, `put` (= `write_str`). Every
/// [`core::fmt::Write`] is a `Sink`. The console writes through `dyn Sink` rather than
/// `dyn core::fmt::Write`, whose vtable would bring `write_char` and `write_fmt` (and
/// with it core::fmt's machinery) into the image although nothing formats (issue 20).
pub trait Sink {
    /// Append `s`; an error when it does not fit.
    fn put(&mut self, s: &str) -> fmt::Result;
}

impl<W: Write + ?Sized> Sink for W {
    fn put(&mut self, s: &str) -> fmt::Result {
        self.write_str(s)
    }
}

/// Write `s` as a quoted, escaped JSON string.
///
/// Over the bytes, not the chars: every character escaped is recognised by its UTF-8
/// bytes (C0 and DEL: one byte; C1: `C2 80`–`C2 9F`; U+2028/U+2029: `E2 80 A8`/`A9`),
/// and what lies between is passed on whole (issue 20: no UTF-8 decoding linked for
/// it). The same output as escaping each `char` (`char::is_control`, U+2028, U+2029).
pub fn write_str_escaped(w: &mut dyn Sink, s: &str) -> fmt::Result {
    w.put("\"")?;
    let b = s.as_bytes();
    let (mut start, mut i) = (0, 0);
    while let Some(&x) = b.get(i) {
        // (the escape, the code point for a \uXXXX, the bytes it spans)
        let (esc, code, len) = match (x, b.get(i + 1).copied(), b.get(i + 2).copied()) {
            (b'"', _, _) => ("\\\"", 0, 1),
            (b'\\', _, _) => ("\\\\", 0, 1),
            (0..=0x1F | 0x7F, _, _) => ("", u32::from(x), 1),
            (0xC2, Some(c @ 0x80..=0x9F), _) => ("", u32::from(c), 2),
            (0xE2, Some(0x80), Some(c @ (0xA8 | 0xA9))) => ("", 0x2000 | u32::from(c & 0x3F), 3),
            _ => {
                i += 1;
                continue;
            }
        };
        w.put(s.get(start..i).unwrap_or(""))?;
        if esc.is_empty() {
            w.put("\\u")?;
            write_hex(w, code, 4)?;
        } else {
            w.put(esc)?;
        }
        i += len;
        start = i;
    }
    w.put(s.get(start..).unwrap_or(""))?;
    w.put("\"")
}

// Numbers are written by hand here, not by `write!`: core::fmt's integer formatting,
// its `Formatter` (padding, flags) and an `Arguments` built at every call site cost the
// image 4.7 KB (issue 20: 101 780 → 97 044 B, the console's messages written in pieces
// too), and every number the console prints is a plain decimal (or, for `\uXXXX` and a
// text report's `0x…` words, fixed-width hex): these few functions are all it needs
// (a formatting crate such as ufmt would bring a macro and a trait per type for them).

/// The decimal digits of `m` (no sign), at the end of `buf`.
fn dec_digits(mut m: u64, buf: &mut [u8; 20]) -> &str {
    let mut len = 0;
    for d in buf.iter_mut().rev() {
        // u64 has at most 20 decimal digits, so this loop always ends with m == 0.
        // Below 2^32 in 32-bit arithmetic: a 64-bit division is a library call.
        let (q, r) = match u32::try_from(m) {
            Ok(s) => (u64::from(s / 10), s % 10),
            Err(_) => (m / 10, (m % 10) as u32),
        };
        *d = b'0' + r as u8;
        m = q;
        len += 1;
        if m == 0 {
            break;
        }
    }
    let digits = buf.get(20 - len..).unwrap_or(&[]);
    core::str::from_utf8(digits).unwrap_or("")
}

/// `v` in decimal, in `buf` (the same digits as [`write_u64`], for a reply written as
/// byte parts).
pub fn dec_text(v: u64, buf: &mut [u8; 20]) -> &str {
    dec_digits(v, buf)
}

/// Write `v` in decimal (as `{v}` does).
pub fn write_u64(w: &mut dyn Sink, v: u64) -> fmt::Result {
    let mut buf = [0u8; 20];
    w.put(dec_digits(v, &mut buf))
}

/// Write `v` in decimal, `-` first when negative (as `{v}` does).
pub fn write_i64(w: &mut dyn Sink, v: i64) -> fmt::Result {
    write_fixed(w, v, 0)
}

/// Write the low `digits` hex digits of `v`, lowercase, zero-padded (as `{v:0N$x}`
/// does for a value that fits; at most 8).
pub fn write_hex(w: &mut dyn Sink, v: u32, digits: u8) -> fmt::Result {
    const HEX: &[u8; 16] = b"0123456789abcdef";
    let mut buf = [0u8; 8];
    let n = usize::from(digits.min(8));
    for (i, d) in buf.iter_mut().take(n).enumerate() {
        let shift = 4 * (n - 1 - i);
        *d = HEX
            .get(((v >> shift) & 0xF) as usize)
            .copied()
            .unwrap_or(b'0');
    }
    w.put(core::str::from_utf8(buf.get(..n).unwrap_or(&[])).unwrap_or(""))
}

/// Write the fixed-point number `value_scaled / 10^decimals` as a JSON number
/// (`12345, 3` → `12.345`; `-5, 3` → `-0.005`; `7, 0` → `7`).
pub fn write_fixed(w: &mut dyn Sink, value_scaled: i64, decimals: u8) -> fmt::Result {
    let mut buf = [0u8; 20];
    let digits = dec_digits(value_scaled.unsigned_abs(), &mut buf);
    if value_scaled < 0 {
        w.put("-")?;
    }
    let dec = usize::from(decimals);
    if dec == 0 {
        return w.put(digits);
    }
    if digits.len() <= dec {
        w.put("0.")?;
        for _ in digits.len()..dec {
            w.put("0")?;
        }
        w.put(digits)
    } else {
        // `get` rather than `split_at`: digits are ASCII, and no panic path (with its
        // Unicode-aware message formatting) ends up in the firmware.
        let k = digits.len() - dec;
        let (int, frac) = (digits.get(..k).unwrap_or(""), digits.get(k..).unwrap_or(""));
        w.put(int)?;
        w.put(".")?;
        w.put(frac)
    }
}

/// Write `json` verbatim except CR and LF, which become spaces (one-line output).
fn write_raw(w: &mut dyn Sink, json: &str) -> fmt::Result {
    for (i, part) in json.split(['\r', '\n']).enumerate() {
        if i > 0 {
            w.put(" ")?;
        }
        w.put(part)?;
    }
    Ok(())
}

/// A JSON object being written; `{` is written with the first member (or by
/// [`finish`](Self::finish) for an empty object).
pub struct JsonObject<'w> {
    w: &'w mut dyn Sink,
    opened: bool,
}

impl<'w> JsonObject<'w> {
    /// Start an object on `w` (nothing is written yet).
    pub fn new(w: &'w mut dyn Sink) -> Self {
        Self { w, opened: false }
    }

    /// Write `{` or `,`, then `"key":`.
    fn key(&mut self, key: &str) -> fmt::Result {
        self.w.put(if self.opened { "," } else { "{" })?;
        self.opened = true;
        write_str_escaped(self.w, key)?;
        self.w.put(":")
    }

    /// `"key":"value"` (escaped).
    #[inline(never)]
    pub fn str(&mut self, key: &str, value: &str) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        write_str_escaped(self.w, value)?;
        Ok(self)
    }

    /// `"key":v` for an unsigned integer.
    #[inline(never)]
    pub fn u64(&mut self, key: &str, v: u64) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        write_u64(self.w, v)?;
        Ok(self)
    }

    /// `"key":v` for a signed integer.
    #[inline(never)]
    pub fn i64(&mut self, key: &str, v: i64) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        write_i64(self.w, v)?;
        Ok(self)
    }

    /// `"key":true` / `"key":false`.
    #[inline(never)]
    pub fn bool(&mut self, key: &str, b: bool) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        self.w.put(if b { "true" } else { "false" })?;
        Ok(self)
    }

    /// `"key":null`.
    #[inline(never)]
    pub fn null(&mut self, key: &str) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        self.w.put("null")?;
        Ok(self)
    }

    /// `"key":` the fixed-point number `value_scaled / 10^decimals` (see [`write_fixed`]).
    #[inline(never)]
    pub fn fixed(
        &mut self,
        key: &str,
        value_scaled: i64,
        decimals: u8,
    ) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        write_fixed(self.w, value_scaled, decimals)?;
        Ok(self)
    }

    /// `"key":` followed by `json`, which must already be valid JSON (CR/LF → space).
    pub fn raw(&mut self, key: &str, json: &str) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        write_raw(self.w, json)?;
        Ok(self)
    }

    /// `"key":[…]`, the elements written by `f`.
    pub fn array<F>(&mut self, key: &str, f: F) -> Result<&mut Self, fmt::Error>
    where
        F: FnOnce(&mut JsonArray<'_>) -> fmt::Result,
    {
        self.key(key)?;
        write_array(self.w, f)?;
        Ok(self)
    }

    /// `"key":{…}`, the members written by `f`.
    pub fn object<F>(&mut self, key: &str, f: F) -> Result<&mut Self, fmt::Error>
    where
        F: FnOnce(&mut JsonObject<'_>) -> fmt::Result,
    {
        self.key(key)?;
        write_object(self.w, f)?;
        Ok(self)
    }

    /// Close the object (`}`; `{}` when it has no members).
    pub fn finish(self) -> fmt::Result {
        if !self.opened {
            self.w.put("{")?;
        }
        self.w.put("}")
    }
}

/// Write a whole object whose members `f` writes.
fn write_object<F>(w: &mut dyn Sink, f: F) -> fmt::Result
where
    F: FnOnce(&mut JsonObject<'_>) -> fmt::Result,
{
    let mut o = JsonObject::new(w);
    f(&mut o)?;
    o.finish()
}

/// Write a whole array whose elements `f` writes.
fn write_array<F>(w: &mut dyn Sink, f: F) -> fmt::Result
where
    F: FnOnce(&mut JsonArray<'_>) -> fmt::Result,
{
    w.put("[")?;
    let mut a = JsonArray { w, first: true };
    f(&mut a)?;
    a.w.put("]")
}

/// A JSON array being written (inside [`JsonObject::array`] or [`JsonArray::array`]).
pub struct JsonArray<'w> {
    w: &'w mut dyn Sink,
    first: bool,
}

impl JsonArray<'_> {
    /// Write the `,` before every element but the first.
    fn sep(&mut self) -> fmt::Result {
        if !core::mem::replace(&mut self.first, false) {
            self.w.put(",")?;
        }
        Ok(())
    }

    /// An object element, its members written by `f`.
    pub fn object<F>(&mut self, f: F) -> Result<&mut Self, fmt::Error>
    where
        F: FnOnce(&mut JsonObject<'_>) -> fmt::Result,
    {
        self.sep()?;
        write_object(self.w, f)?;
        Ok(self)
    }

    /// A nested array element, its elements written by `f`.
    pub fn array<F>(&mut self, f: F) -> Result<&mut Self, fmt::Error>
    where
        F: FnOnce(&mut JsonArray<'_>) -> fmt::Result,
    {
        self.sep()?;
        write_array(self.w, f)?;
        Ok(self)
    }

    /// A string element (escaped).
    #[inline(never)]
    pub fn str(&mut self, value: &str) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        write_str_escaped(self.w, value)?;
        Ok(self)
    }

    /// An unsigned integer element.
    #[inline(never)]
    pub fn u64(&mut self, v: u64) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        write_u64(self.w, v)?;
        Ok(self)
    }

    /// A signed integer element.
    #[inline(never)]
    pub fn i64(&mut self, v: i64) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        write_i64(self.w, v)?;
        Ok(self)
    }

    /// A boolean element.
    #[inline(never)]
    pub fn bool(&mut self, b: bool) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        self.w.put(if b { "true" } else { "false" })?;
        Ok(self)
    }

    /// A `null` element.
    #[inline(never)]
    pub fn null(&mut self) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        self.w.put("null")?;
        Ok(self)
    }

    /// A fixed-point number element (see [`write_fixed`]).
    #[inline(never)]
    pub fn fixed(&mut self, value_scaled: i64, decimals: u8) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        write_fixed(self.w, value_scaled, decimals)?;
        Ok(self)
    }

    /// An element that is already valid JSON (CR/LF → space).
    pub fn raw(&mut self, json: &str) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        write_raw(self.w, json)?;
        Ok(self)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn fixed_edges() {
        let mut s = heapless::String::<256>::new();
        for (v, d) in [
            (0, 0),
            (0, 2),
            (i64::MIN, 0),
            (i64::MIN, 3),
            (i64::MAX, 19),
            (-1, 20),
            (100, 2),
        ] {
            write_fixed(&mut s, v, d).unwrap();
            s.push(' ').unwrap();
        }
        assert_eq!(
            s,
            "0 0.00 -9223372036854775808 -9223372036854775.808 0.9223372036854775807 \
             -0.00000000000000000001 1.00 "
        );
    }

    /// The hand-written numbers (issue 20) write what core::fmt wrote before them.
    #[test]
    fn numbers_are_written_as_core_fmt_writes_them() {
        extern crate std;
        use std::format;
        use std::string::String;
        let u = [
            0,
            1,
            9,
            10,
            99,
            100,
            4_294_967_295,
            4_294_967_296,
            10_000_000_000,
            u64::MAX,
        ];
        for v in u {
            let mut s = String::new();
            write_u64(&mut s, v).unwrap();
            assert_eq!(s, format!("{v}"));
        }
        for v in [
            0,
            -1,
            1,
            -10,
            i64::from(i32::MIN),
            i64::MIN,
            i64::MAX,
            -4_294_967_296,
        ] {
            let mut s = String::new();
            write_i64(&mut s, v).unwrap();
            assert_eq!(s, format!("{v}"));
        }
        for v in [0, 0xa, 0x2028, 0xffff, 0x0800_abcd, u32::MAX] {
            let mut s = String::new();
            write_hex(&mut s, v, 8).unwrap();
            assert_eq!(s, format!("{v:08x}"));
            if v <= 0xffff {
                s.clear();
                write_hex(&mut s, v, 4).unwrap();
                assert_eq!(s, format!("{v:04x}"));
            }
        }
    }

    /// The byte-wise escaper writes what escaping each `char` wrote (the code before
    /// issue 20, kept here), for strings made of every kind of character it treats.
    #[test]
    fn escaping_by_bytes_is_escaping_by_chars() {
        extern crate std;
        use std::string::String;
        fn by_chars(s: &str) -> String {
            let mut o = String::from("\"");
            for c in s.chars() {
                match c {
                    '"' => o.push_str("\\\""),
                    '\\' => o.push_str("\\\\"),
                    c if c.is_control() || c == '\u{2028}' || c == '\u{2029}' => {
                        o.push_str(&std::format!("\\u{:04x}", u32::from(c)))
                    }
                    c => o.push(c),
                }
            }
            o.push('"');
            o
        }
        let pieces = [
            "a", "\"", "\\", "\n", "\u{0}", "\u{1f}", " ", "\u{7f}", "\u{80}", "\u{9f}", "\u{a0}",
            "é", "\u{2027}", "\u{2028}", "\u{2029}", "\u{202a}", "€", "😀", "\u{c2}", "\u{2000}",
        ];
        let mut x: u32 = 7;
        for _ in 0..2_000 {
            let mut s = String::new();
            for _ in 0..(x % 7) {
                x = x.wrapping_mul(1_103_515_245).wrapping_add(12_345);
                s.push_str(pieces[(x >> 16) as usize % pieces.len()]);
            }
            x = x.wrapping_mul(1_103_515_245).wrapping_add(12_345);
            let mut got = String::new();
            write_str_escaped(&mut got, &s).unwrap();
            assert_eq!(got, by_chars(&s), "{s:?}");
        }
    }

    #[test]
    fn write_error_propagates() {
        let mut s = heapless::String::<4>::new();
        let mut o = JsonObject::new(&mut s);
        assert!(o.str("key", "value").is_err());
    }
}
