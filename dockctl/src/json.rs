//! The board's JSON replies, kept as the board wrote them: the fields in its order and
//! each number as its digits (`0.003018`, `8087.360`: the console's fixed-point values,
//! never a float made from them), so a table shows what the board said and an export
//! carries it unchanged. Parsed with serde_json (its `RawValue` keeps a number's text).

use std::fmt::Write as _;

use serde::de::{Deserialize, Deserializer, MapAccess, Visitor};
use serde_json::value::RawValue;

/// A JSON value, its object fields in order and its numbers as text.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum J {
    /// `null`.
    Null,
    /// `true` / `false`.
    Bool(bool),
    /// A number, as written.
    Num(String),
    /// A string.
    Str(String),
    /// An array.
    Arr(Vec<J>),
    /// An object, in its order.
    Obj(Vec<(String, J)>),
}

/// An object's fields, in order, each value still raw.
struct Fields(Vec<(String, Box<RawValue>)>);

impl<'de> Deserialize<'de> for Fields {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V;
        impl<'de> Visitor<'de> for V {
            type Value = Fields;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str("a JSON object")
            }
            fn visit_map<A: MapAccess<'de>>(self, mut m: A) -> Result<Fields, A::Error> {
                let mut v = Vec::new();
                while let Some(k) = m.next_key::<String>()? {
                    v.push((k, m.next_value::<Box<RawValue>>()?));
                }
                Ok(Fields(v))
            }
        }
        d.deserialize_map(V)
    }
}

impl J {
    /// Parse one JSON text.
    pub fn parse(text: &str) -> Result<J, String> {
        let t = text.trim();
        let bad = |e: serde_json::Error| format!("not JSON ({e}): {}", short(t));
        Ok(match t.as_bytes().first() {
            Some(b'{') => {
                let Fields(f) = serde_json::from_str(t).map_err(bad)?;
                let mut out = Vec::with_capacity(f.len());
                for (k, v) in f {
                    out.push((k, J::parse(v.get())?));
                }
                J::Obj(out)
            }
            Some(b'[') => {
                let items: Vec<Box<RawValue>> = serde_json::from_str(t).map_err(bad)?;
                J::Arr(
                    items
                        .iter()
                        .map(|v| J::parse(v.get()))
                        .collect::<Result<_, _>>()?,
                )
            }
            Some(b'"') => J::Str(serde_json::from_str(t).map_err(bad)?),
            Some(b't' | b'f') => J::Bool(serde_json::from_str(t).map_err(bad)?),
            Some(b'n') => {
                let () = serde_json::from_str(t).map_err(bad)?;
                J::Null
            }
            _ => {
                let _: serde_json::Number = serde_json::from_str(t).map_err(bad)?;
                J::Num(t.to_string())
            }
        })
    }

    /// A field of an object.
    pub fn get(&self, key: &str) -> Option<&J> {
        match self {
            J::Obj(f) => f.iter().find(|(k, _)| k == key).map(|(_, v)| v),
            _ => None,
        }
    }

    /// A string's text.
    pub fn as_str(&self) -> Option<&str> {
        match self {
            J::Str(s) => Some(s),
            _ => None,
        }
    }

    /// A number's value.
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            J::Num(n) => n.parse().ok(),
            _ => None,
        }
    }

    /// A whole number's value.
    pub fn as_u64(&self) -> Option<u64> {
        match self {
            J::Num(n) => n.parse().ok(),
            _ => None,
        }
    }

    /// A yes/no.
    pub fn as_bool(&self) -> Option<bool> {
        match self {
            J::Bool(b) => Some(*b),
            _ => None,
        }
    }

    /// The string field `key` (empty when missing or not a string).
    pub fn text(&self, key: &str) -> &str {
        self.get(key).and_then(J::as_str).unwrap_or("")
    }

    /// A value for a person: a string's text, a number's digits, yes/no, `none`.
    pub fn plain(&self) -> String {
        match self {
            J::Null => "none".into(),
            J::Bool(true) => "yes".into(),
            J::Bool(false) => "no".into(),
            J::Num(n) => n.clone(),
            J::Str(s) => s.clone(),
            other => other.to_json(),
        }
    }

    /// The JSON text, on one line (numbers as they were read).
    pub fn to_json(&self) -> String {
        let mut s = String::new();
        self.write(&mut s);
        s
    }

    fn write(&self, s: &mut String) {
        match self {
            J::Null => s.push_str("null"),
            J::Bool(b) => s.push_str(if *b { "true" } else { "false" }),
            J::Num(n) => s.push_str(n),
            J::Str(t) => s.push_str(&quote(t)),
            J::Arr(items) => {
                s.push('[');
                for (i, v) in items.iter().enumerate() {
                    if i > 0 {
                        s.push(',');
                    }
                    v.write(s);
                }
                s.push(']');
            }
            J::Obj(f) => {
                s.push('{');
                for (i, (k, v)) in f.iter().enumerate() {
                    if i > 0 {
                        s.push(',');
                    }
                    s.push_str(&quote(k));
                    s.push(':');
                    v.write(s);
                }
                s.push('}');
            }
        }
    }

    /// The JSON text, indented by two spaces a level (an export file).
    pub fn to_pretty(&self) -> String {
        let mut s = String::new();
        self.pretty(&mut s, 0);
        s.push('\n');
        s
    }

    fn pretty(&self, s: &mut String, depth: usize) {
        let pad = |s: &mut String, d: usize| {
            s.push('\n');
            for _ in 0..d {
                s.push_str("  ");
            }
        };
        match self {
            J::Arr(items) if !items.is_empty() => {
                s.push('[');
                for (i, v) in items.iter().enumerate() {
                    if i > 0 {
                        s.push(',');
                    }
                    pad(s, depth + 1);
                    v.pretty(s, depth + 1);
                }
                pad(s, depth);
                s.push(']');
            }
            J::Obj(f) if !f.is_empty() => {
                s.push('{');
                for (i, (k, v)) in f.iter().enumerate() {
                    if i > 0 {
                        s.push(',');
                    }
                    pad(s, depth + 1);
                    s.push_str(&quote(k));
                    s.push_str(": ");
                    v.pretty(s, depth + 1);
                }
                pad(s, depth);
                s.push('}');
            }
            other => other.write(s),
        }
    }
}

/// A JSON string literal of `t`.
pub fn quote(t: &str) -> String {
    let mut s = String::with_capacity(t.len() + 2);
    s.push('"');
    for c in t.chars() {
        match c {
            '"' => s.push_str("\\\""),
            '\\' => s.push_str("\\\\"),
            '\n' => s.push_str("\\n"),
            '\r' => s.push_str("\\r"),
            '\t' => s.push_str("\\t"),
            c if (c as u32) < 0x20 => {
                let _ = write!(s, "\\u{:04x}", c as u32);
            }
            c => s.push(c),
        }
    }
    s.push('"');
    s
}

/// The first 80 characters of `t` (for an error message).
pub fn short(t: &str) -> String {
    let mut s: String = t.chars().take(80).collect();
    if t.chars().count() > 80 {
        s.push('…');
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_boards_numbers_and_order_are_kept() {
        let text = r#"{"state":"idle","force_n":0.003,"wear_mm":0.003018,"load_distance_nmm":8087.360,"phase":null,"ok":true,"resets":{"power_on":1},"faults":[{"kind":"overload","t_s":12.500}],"serial":"a\"b"}"#;
        let j = J::parse(text).unwrap();
        assert_eq!(j.to_json(), text);
        assert_eq!(j.get("load_distance_nmm").unwrap().plain(), "8087.360");
        assert_eq!(j.get("phase").unwrap().plain(), "none");
        assert_eq!(j.get("ok").unwrap().plain(), "yes");
        assert_eq!(j.text("serial"), "a\"b");
        assert_eq!(j.get("force_n").unwrap().as_f64(), Some(0.003));
        assert!(J::parse(&j.to_pretty()).unwrap() == j);
    }

    #[test]
    fn what_is_not_json_is_refused() {
        for t in ["", "{", "{\"a\":}", "nul", "1.2.3", "[1,]", "ok: fine"] {
            assert!(J::parse(t).is_err(), "{t:?}");
        }
    }
}
