//! A tiny JSON object writer over [`core::fmt::Write`] for `--json` replies.
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

/// Write `s` as a quoted, escaped JSON string.
pub fn write_str_escaped<W: Write + ?Sized>(w: &mut W, s: &str) -> fmt::Result {
    w.write_char('"')?;
    let mut start = 0;
    for (i, c) in s.char_indices() {
        let esc = match c {
            '"' => Some("\\\""),
            '\\' => Some("\\\\"),
            _ => None,
        };
        let needs_u = c.is_control() || c == '\u{2028}' || c == '\u{2029}';
        if esc.is_none() && !needs_u {
            continue;
        }
        w.write_str(s.get(start..i).unwrap_or(""))?;
        match esc {
            Some(e) => w.write_str(e)?,
            None => write!(w, "\\u{:04x}", u32::from(c))?,
        }
        start = i + c.len_utf8();
    }
    w.write_str(s.get(start..).unwrap_or(""))?;
    w.write_char('"')
}

/// Write the fixed-point number `value_scaled / 10^decimals` as a JSON number
/// (`12345, 3` → `12.345`; `-5, 3` → `-0.005`; `7, 0` → `7`).
pub fn write_fixed<W: Write + ?Sized>(w: &mut W, value_scaled: i64, decimals: u8) -> fmt::Result {
    let mut digits = [0u8; 20];
    let mut len = 0;
    let mut m = value_scaled.unsigned_abs();
    for d in digits.iter_mut().rev() {
        // u64 has at most 20 decimal digits, so this loop always ends with m == 0.
        *d = b'0' + (m % 10) as u8;
        m /= 10;
        len += 1;
        if m == 0 {
            break;
        }
    }
    let digits = digits.get(20 - len..).unwrap_or(&[]);
    let digits = core::str::from_utf8(digits).map_err(|_| fmt::Error)?;
    if value_scaled < 0 {
        w.write_char('-')?;
    }
    let dec = usize::from(decimals);
    if dec == 0 {
        return w.write_str(digits);
    }
    if digits.len() <= dec {
        w.write_str("0.")?;
        for _ in digits.len()..dec {
            w.write_char('0')?;
        }
        w.write_str(digits)
    } else {
        // `get` rather than `split_at`: digits are ASCII, and no panic path (with its
        // Unicode-aware message formatting) ends up in the firmware.
        let k = digits.len() - dec;
        let (int, frac) = (digits.get(..k).unwrap_or(""), digits.get(k..).unwrap_or(""));
        w.write_str(int)?;
        w.write_char('.')?;
        w.write_str(frac)
    }
}

/// Write `json` verbatim except CR and LF, which become spaces (one-line output).
fn write_raw<W: Write + ?Sized>(w: &mut W, json: &str) -> fmt::Result {
    for (i, part) in json.split(['\r', '\n']).enumerate() {
        if i > 0 {
            w.write_char(' ')?;
        }
        w.write_str(part)?;
    }
    Ok(())
}

/// A JSON object being written; `{` is written with the first member (or by
/// [`finish`](Self::finish) for an empty object).
pub struct JsonObject<'w, W: Write + ?Sized> {
    w: &'w mut W,
    opened: bool,
}

impl<'w, W: Write + ?Sized> JsonObject<'w, W> {
    /// Start an object on `w` (nothing is written yet).
    pub fn new(w: &'w mut W) -> Self {
        Self { w, opened: false }
    }

    /// Write `{` or `,`, then `"key":`.
    fn key(&mut self, key: &str) -> fmt::Result {
        self.w.write_char(if self.opened { ',' } else { '{' })?;
        self.opened = true;
        write_str_escaped(self.w, key)?;
        self.w.write_char(':')
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
        write!(self.w, "{v}")?;
        Ok(self)
    }

    /// `"key":v` for a signed integer.
    #[inline(never)]
    pub fn i64(&mut self, key: &str, v: i64) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        write!(self.w, "{v}")?;
        Ok(self)
    }

    /// `"key":true` / `"key":false`.
    #[inline(never)]
    pub fn bool(&mut self, key: &str, b: bool) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        self.w.write_str(if b { "true" } else { "false" })?;
        Ok(self)
    }

    /// `"key":null`.
    #[inline(never)]
    pub fn null(&mut self, key: &str) -> Result<&mut Self, fmt::Error> {
        self.key(key)?;
        self.w.write_str("null")?;
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
        F: FnOnce(&mut JsonArray<'_, W>) -> fmt::Result,
    {
        self.key(key)?;
        write_array(self.w, f)?;
        Ok(self)
    }

    /// `"key":{…}`, the members written by `f`.
    pub fn object<F>(&mut self, key: &str, f: F) -> Result<&mut Self, fmt::Error>
    where
        F: FnOnce(&mut JsonObject<'_, W>) -> fmt::Result,
    {
        self.key(key)?;
        write_object(self.w, f)?;
        Ok(self)
    }

    /// Close the object (`}`; `{}` when it has no members).
    pub fn finish(self) -> fmt::Result {
        if !self.opened {
            self.w.write_char('{')?;
        }
        self.w.write_char('}')
    }
}

/// Write a whole object whose members `f` writes.
fn write_object<W, F>(w: &mut W, f: F) -> fmt::Result
where
    W: Write + ?Sized,
    F: FnOnce(&mut JsonObject<'_, W>) -> fmt::Result,
{
    let mut o = JsonObject::new(w);
    f(&mut o)?;
    o.finish()
}

/// Write a whole array whose elements `f` writes.
fn write_array<W, F>(w: &mut W, f: F) -> fmt::Result
where
    W: Write + ?Sized,
    F: FnOnce(&mut JsonArray<'_, W>) -> fmt::Result,
{
    w.write_char('[')?;
    let mut a = JsonArray { w, first: true };
    f(&mut a)?;
    a.w.write_char(']')
}

/// A JSON array being written (inside [`JsonObject::array`] or [`JsonArray::array`]).
pub struct JsonArray<'w, W: Write + ?Sized> {
    w: &'w mut W,
    first: bool,
}

impl<W: Write + ?Sized> JsonArray<'_, W> {
    /// Write the `,` before every element but the first.
    fn sep(&mut self) -> fmt::Result {
        if !core::mem::replace(&mut self.first, false) {
            self.w.write_char(',')?;
        }
        Ok(())
    }

    /// An object element, its members written by `f`.
    pub fn object<F>(&mut self, f: F) -> Result<&mut Self, fmt::Error>
    where
        F: FnOnce(&mut JsonObject<'_, W>) -> fmt::Result,
    {
        self.sep()?;
        write_object(self.w, f)?;
        Ok(self)
    }

    /// A nested array element, its elements written by `f`.
    pub fn array<F>(&mut self, f: F) -> Result<&mut Self, fmt::Error>
    where
        F: FnOnce(&mut JsonArray<'_, W>) -> fmt::Result,
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
        write!(self.w, "{v}")?;
        Ok(self)
    }

    /// A signed integer element.
    #[inline(never)]
    pub fn i64(&mut self, v: i64) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        write!(self.w, "{v}")?;
        Ok(self)
    }

    /// A boolean element.
    #[inline(never)]
    pub fn bool(&mut self, b: bool) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        self.w.write_str(if b { "true" } else { "false" })?;
        Ok(self)
    }

    /// A `null` element.
    #[inline(never)]
    pub fn null(&mut self) -> Result<&mut Self, fmt::Error> {
        self.sep()?;
        self.w.write_str("null")?;
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

    #[test]
    fn write_error_propagates() {
        let mut s = heapless::String::<4>::new();
        let mut o = JsonObject::new(&mut s);
        assert!(o.str("key", "value").is_err());
    }
}
