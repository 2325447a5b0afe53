//! One field list per report, rendered as `key=value` text or as one JSON object.
//!
//! A report writes its fields once, through [`Fields`]; [`TextFields`] and
//! [`JsonFields`] render them, so the text and the JSON name every field the same way
//! (`cycles_completed=3` / `"cycles_completed":3`) and cannot drift apart. One copy of
//! each report's code is in the image (the sinks are `dyn`).
//!
//! | field | text | JSON |
//! |---|---|---|
//! | [`Fields::str`] | `key=value` | `"key":"value"` (escaped) |
//! | [`Fields::u64`] | `key=12` | `"key":12` |
//! | [`Fields::fixed`] (`12345`, 3 decimals) | `key=12.345` | `"key":12.345` |
//! | [`Fields::hex32`] | `key=0x0800abcd` | `"key":134261709` |
//! | [`Fields::bool`] | `key=yes` / `key=no` | `"key":true` / `false` |
//! | [`Fields::none`] | `key=none` | `"key":null` |
//! | [`Fields::object`] | a line of its own: `key a=1 b=2` | `"key":{"a":1,"b":2}` |
//! | [`Fields::records`] | a line per record: `a=1 b=2` | `"key":[{"a":1,"b":2},…]` |
//!
//! Text: the report's own fields on its first line, each object and record on a line of
//! its own after it (a field of the report's own written after one starts a new line);
//! lines end with CR LF. JSON: one line.
//!
//! ```
//! use docking_logic::console::fields::{Fields, JsonFields, TextFields};
//! fn report(f: &mut dyn Fields) -> core::fmt::Result {
//!     f.u64("cycles_completed", 3)?;
//!     f.bool("in_estop_open", false)?;
//!     f.records("faults", 1, &mut |_, r| r.str("kind", "overload"))
//! }
//! let mut t = String::new();
//! let mut w = TextFields::new(&mut t);
//! report(&mut w)?;
//! w.finish()?;
//! assert_eq!(t, "cycles_completed=3 in_estop_open=no\r\nkind=overload\r\n");
//! let mut j = String::new();
//! let mut w = JsonFields::new(&mut j)?;
//! report(&mut w)?;
//! w.finish()?;
//! assert_eq!(j, r#"{"cycles_completed":3,"in_estop_open":false,"faults":[{"kind":"overload"}]}"#);
//! # Ok::<(), core::fmt::Error>(())
//! ```

use core::fmt;

use super::json::{write_fixed, write_hex, write_str_escaped, write_u64, Sink};

/// A record's fields, written into a [`Fields`] sink.
pub type Record<'a> = dyn FnMut(usize, &mut dyn Fields) -> fmt::Result + 'a;

/// Where a report writes its fields (see the module doc for each one's rendering).
pub trait Fields {
    /// Write `key` and what separates it from its value (`key=`, `"key":`, after the
    /// previous field's separator); the value goes to the writer returned.
    fn value(&mut self, key: &str) -> Result<&mut dyn Sink, fmt::Error>;
    /// A string.
    fn str(&mut self, key: &str, v: &str) -> fmt::Result;
    /// An unsigned integer (the same digits in text and JSON).
    fn u64(&mut self, key: &str, v: u64) -> fmt::Result {
        write_u64(self.value(key)?, v)
    }
    /// A fixed-point number: `v / 10^decimals` (the same digits in text and JSON).
    fn fixed(&mut self, key: &str, v: i64, decimals: u8) -> fmt::Result {
        write_fixed(self.value(key)?, v, decimals)
    }
    /// A 32-bit word (an address, a register): hex in text, a number in JSON.
    fn hex32(&mut self, key: &str, v: u32) -> fmt::Result;
    /// A yes/no.
    fn bool(&mut self, key: &str, v: bool) -> fmt::Result;
    /// No value.
    fn none(&mut self, key: &str) -> fmt::Result;
    /// A nested object: `f` writes its fields.
    fn object(
        &mut self,
        key: &str,
        f: &mut dyn FnMut(&mut dyn Fields) -> fmt::Result,
    ) -> fmt::Result;
    /// `n` records: `item(i, sink)` writes record `i`'s fields.
    fn records(&mut self, key: &str, n: usize, item: &mut Record<'_>) -> fmt::Result;
    /// A topic of the report's own fields starts (`status`'s and `wear`'s): a person's
    /// terminal shows each topic on a line of its own, its name first
    /// ([`TextFields::grouped`]); a script's text and JSON are as without it.
    fn group(&mut self, _name: &str) -> fmt::Result {
        Ok(())
    }
}

/// Where a grouped line's fields start (after the topic's name), columns.
const GROUP_INDENT: usize = 10;
/// A grouped line wraps before a field that would end past this column (its value
/// guessed at [`VALUE_GUESS`] characters); the next line starts at [`GROUP_INDENT`].
const GROUP_WIDTH: usize = 78;
const VALUE_GUESS: usize = 8;

/// `key=value` text: the report's fields on the first line, each object and record on
/// a line of its own.
pub struct TextFields<'w> {
    w: &'w mut dyn Sink,
    /// Something is on the current line (the next field is preceded by a space).
    on_line: bool,
    /// Any line begun (the next object or record starts a new line).
    started: bool,
    /// The current line is an object's or a record's: a field of the report's own
    /// written after it starts a line of its own.
    nested: bool,
    /// Topics on lines of their own, wrapped at [`GROUP_WIDTH`] (a person's terminal).
    grouped: bool,
    /// The column the line stands at (grouped only).
    col: usize,
}

impl<'w> TextFields<'w> {
    /// Text into `w`: a script's `key=value` lines.
    pub fn new(w: &'w mut dyn Sink) -> Self {
        Self {
            w,
            on_line: false,
            started: false,
            nested: false,
            grouped: false,
            col: 0,
        }
    }

    /// Text for a person (issue 35: `status` and `wear` were single lines of 370
    /// characters): each topic ([`Fields::group`]) on a line of its own, its name
    /// first, its `key=value` fields after, wrapped at 78 columns under the first:
    ///
    /// ```text
    /// motion    force_n=0.003 limit_n=300.000 pos_mm=0.000 cycles_completed=3
    /// plc       in_dock=no in_estop_open=no out_ready=yes out_mated=no
    ///           out_fault=no out_maintenance=no
    /// ```
    pub fn grouped(w: &'w mut dyn Sink) -> Self {
        let mut t = Self::new(w);
        t.grouped = true;
        t
    }

    fn new_line(&mut self) -> fmt::Result {
        if self.started {
            self.w.put("\r\n")?;
        }
        self.on_line = false;
        self.started = true;
        self.nested = false;
        self.col = 0;
        Ok(())
    }

    /// `n` spaces.
    fn pad(&mut self, n: usize) -> fmt::Result {
        for _ in 0..n {
            fmt::Write::write_str(self, " ")?;
        }
        Ok(())
    }

    /// End the last line.
    pub fn finish(self) -> fmt::Result {
        if self.started {
            self.w.put("\r\n")?;
        }
        Ok(())
    }
}

/// What a grouped line writes goes through here: its column counted.
impl fmt::Write for TextFields<'_> {
    fn write_str(&mut self, s: &str) -> fmt::Result {
        self.col += s.len();
        self.w.put(s)
    }
}

impl Fields for TextFields<'_> {
    fn value(&mut self, key: &str) -> Result<&mut dyn Sink, fmt::Error> {
        if self.nested {
            self.new_line()?;
        }
        if self.grouped && self.on_line && self.col + 1 + key.len() + 1 + VALUE_GUESS > GROUP_WIDTH
        {
            self.new_line()?;
            self.pad(GROUP_INDENT)?;
        }
        if self.on_line {
            self.w.put(" ")?;
            self.col += 1;
        }
        self.on_line = true;
        self.started = true;
        self.col += key.len() + 1;
        self.w.put(key)?;
        self.w.put("=")?;
        Ok(self)
    }

    fn str(&mut self, key: &str, v: &str) -> fmt::Result {
        self.value(key)?.put(v)
    }

    fn hex32(&mut self, key: &str, v: u32) -> fmt::Result {
        let w = self.value(key)?;
        w.put("0x")?;
        write_hex(w, v, 8)
    }

    fn group(&mut self, name: &str) -> fmt::Result {
        if !self.grouped {
            return Ok(());
        }
        self.new_line()?;
        fmt::Write::write_str(self, name)?;
        self.pad(GROUP_INDENT.saturating_sub(name.len()))
    }

    fn bool(&mut self, key: &str, v: bool) -> fmt::Result {
        self.str(key, if v { "yes" } else { "no" })
    }

    fn none(&mut self, key: &str) -> fmt::Result {
        self.str(key, "none")
    }

    fn object(
        &mut self,
        key: &str,
        f: &mut dyn FnMut(&mut dyn Fields) -> fmt::Result,
    ) -> fmt::Result {
        self.new_line()?;
        self.w.put(key)?;
        self.on_line = true;
        f(self)?;
        self.nested = true;
        Ok(())
    }

    fn records(&mut self, _key: &str, n: usize, item: &mut Record<'_>) -> fmt::Result {
        for i in 0..n {
            self.new_line()?;
            item(i, self)?;
            self.nested = true;
        }
        Ok(())
    }
}

/// One JSON object on one line.
pub struct JsonFields<'w> {
    w: &'w mut dyn Sink,
    /// No field written yet in the innermost object.
    first: bool,
}

impl<'w> JsonFields<'w> {
    /// An object into `w` (its opening brace written now).
    pub fn new(w: &'w mut dyn Sink) -> Result<Self, fmt::Error> {
        w.put("{")?;
        Ok(Self { w, first: true })
    }

    /// Close the object.
    pub fn finish(self) -> fmt::Result {
        self.w.put("}")
    }

    /// An array of strings, `"key":["a","b"]` (JSON only: `help --json`'s list).
    pub fn strings(&mut self, key: &str, items: &mut dyn Iterator<Item = &str>) -> fmt::Result {
        self.value(key)?.put("[")?;
        for (i, s) in items.enumerate() {
            if i > 0 {
                self.w.put(",")?;
            }
            write_str_escaped(self.w, s)?;
        }
        self.w.put("]")
    }
}

impl Fields for JsonFields<'_> {
    fn value(&mut self, key: &str) -> Result<&mut dyn Sink, fmt::Error> {
        if !self.first {
            self.w.put(",")?;
        }
        self.first = false;
        write_str_escaped(self.w, key)?;
        self.w.put(":")?;
        Ok(&mut *self.w)
    }

    fn str(&mut self, key: &str, v: &str) -> fmt::Result {
        write_str_escaped(self.value(key)?, v)
    }

    fn hex32(&mut self, key: &str, v: u32) -> fmt::Result {
        self.u64(key, u64::from(v))
    }

    fn bool(&mut self, key: &str, v: bool) -> fmt::Result {
        self.value(key)?.put(if v { "true" } else { "false" })
    }

    fn none(&mut self, key: &str) -> fmt::Result {
        self.value(key)?.put("null")
    }

    fn object(
        &mut self,
        key: &str,
        f: &mut dyn FnMut(&mut dyn Fields) -> fmt::Result,
    ) -> fmt::Result {
        self.value(key)?.put("{")?;
        self.first = true;
        f(self)?;
        self.first = false;
        self.w.put("}")
    }

    fn records(&mut self, key: &str, n: usize, item: &mut Record<'_>) -> fmt::Result {
        self.value(key)?.put("[")?;
        for i in 0..n {
            if i > 0 {
                self.w.put(",")?;
            }
            self.w.put("{")?;
            self.first = true;
            item(i, self)?;
            self.w.put("}")?;
        }
        self.first = false;
        self.w.put("]")
    }
}

#[cfg(test)]
mod tests {
    extern crate std;
    use super::*;
    use std::string::String;

    fn both(f: &dyn Fn(&mut dyn Fields) -> fmt::Result) -> (String, String) {
        let (mut t, mut j) = (String::new(), String::new());
        let mut tw = TextFields::new(&mut t);
        f(&mut tw).unwrap();
        tw.finish().unwrap();
        let mut jw = JsonFields::new(&mut j).unwrap();
        f(&mut jw).unwrap();
        jw.finish().unwrap();
        (t, j)
    }

    #[test]
    fn every_kind_of_field_renders_as_text_and_json() {
        let (t, j) = both(&|f| {
            f.str("state", "idle")?;
            f.fixed("force_n", -5, 3)?;
            f.none("phase")?;
            f.hex32("pc", 0x0800_abcd)?;
            f.object("resets", &mut |r| {
                r.u64("power_on", 1)?;
                r.u64("watchdog", 0)
            })?;
            f.records("list", 2, &mut |i, r| {
                r.u64("i", i as u64)?;
                r.bool("odd", i % 2 == 1)
            })
        });
        assert_eq!(
            t,
            "state=idle force_n=-0.005 phase=none pc=0x0800abcd\r\n\
             resets power_on=1 watchdog=0\r\ni=0 odd=no\r\ni=1 odd=yes\r\n"
        );
        assert_eq!(
            j,
            r#"{"state":"idle","force_n":-0.005,"phase":null,"pc":134261709,"resets":{"power_on":1,"watchdog":0},"list":[{"i":0,"odd":false},{"i":1,"odd":true}]}"#
        );
    }

    /// `faults` put `last_crash=none` on its `resets …` line: a report's own field after
    /// an object or a record starts a line of its own.
    #[test]
    fn a_field_after_an_object_starts_its_own_line() {
        let (t, _) = both(&|f| {
            f.u64("count", 0)?;
            f.object("resets", &mut |r| r.u64("power_on", 1))?;
            f.none("last_crash")?;
            f.records("faults", 1, &mut |_, r| r.str("kind", "overload"))?;
            f.u64("after", 2)
        });
        assert_eq!(
            t,
            "count=0\r\nresets power_on=1\r\nlast_crash=none\r\nkind=overload\r\nafter=2\r\n"
        );
    }

    #[test]
    fn records_alone_start_on_the_first_line_and_an_empty_report_is_empty() {
        let (t, j) = both(&|f| f.records("history", 1, &mut |_, r| r.u64("cycle", 3)));
        assert_eq!(t, "cycle=3\r\n");
        assert_eq!(j, r#"{"history":[{"cycle":3}]}"#);
        let (t, j) = both(&|f| f.records("history", 0, &mut |_, _| Ok(())));
        assert_eq!(t, "");
        assert_eq!(j, r#"{"history":[]}"#);
    }

    /// Issue 35: a person's terminal shows each topic on a line of its own, wrapped
    /// under its first field; the script's text and the JSON are as without topics.
    #[test]
    fn topics_on_lines_of_their_own_for_a_person_and_nothing_else_changes() {
        let report = |f: &mut dyn Fields| -> fmt::Result {
            f.group("state")?;
            f.str("state", "idle")?;
            f.none("phase")?;
            f.group("plc")?;
            for k in [
                "in_dock",
                "in_estop_open",
                "out_ready",
                "out_mated",
                "out_fault",
                "out_maintenance",
            ] {
                f.bool(k, false)?;
            }
            Ok(())
        };
        let (t, j) = both(&report);
        assert_eq!(
            t,
            "state=idle phase=none in_dock=no in_estop_open=no out_ready=no out_mated=no out_fault=no out_maintenance=no\r\n"
        );
        assert!(j.starts_with(r#"{"state":"idle","phase":null,"in_dock":false"#));
        let mut g = String::new();
        let mut w = TextFields::grouped(&mut g);
        report(&mut w).unwrap();
        w.finish().unwrap();
        assert_eq!(
            g,
            "state     state=idle phase=none\r\n\
             plc       in_dock=no in_estop_open=no out_ready=no out_mated=no\r\n          \
             out_fault=no out_maintenance=no\r\n"
        );
        assert!(g.split("\r\n").all(|l| l.len() <= GROUP_WIDTH));
    }

    #[test]
    fn a_json_array_of_strings() {
        let mut j = String::new();
        let mut w = JsonFields::new(&mut j).unwrap();
        w.strings("a", &mut ["x", "y\""].into_iter()).unwrap();
        w.strings("b", &mut core::iter::empty()).unwrap();
        w.finish().unwrap();
        assert_eq!(j, r#"{"a":["x","y\""],"b":[]}"#);
    }

    #[test]
    fn strings_are_escaped_in_json() {
        let (_, j) = both(&|f| f.str("serial", "a\"b\n"));
        assert_eq!(j, r#"{"serial":"a\"b\u000a"}"#);
    }
}
