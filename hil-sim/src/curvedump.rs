//! A `curve … --json` dump read back (the firmware's one JSON line,
//! `logic/src/links/console/curve.rs`), for `hil-sim plot-curve`: a small JSON reader, enough
//! for that line (objects, arrays, numbers, strings, `null`, booleans).

use std::collections::BTreeMap;

/// A JSON value.
#[derive(Clone, Debug, PartialEq)]
pub enum Json {
    /// `null`.
    Null,
    /// `true` / `false`.
    Bool(bool),
    /// A number.
    Num(f64),
    /// A string (escapes taken as they come; the firmware's strings have none).
    Str(String),
    /// An array.
    Arr(Vec<Json>),
    /// An object.
    Obj(BTreeMap<String, Json>),
}

impl Json {
    /// Parse `s` (one value, surrounding white space allowed).
    pub fn parse(s: &str) -> Result<Self, String> {
        let b = s.as_bytes();
        let mut i = 0;
        let v = value(b, &mut i)?;
        skip_ws(b, &mut i);
        if i != b.len() {
            return Err(format!("trailing characters at byte {i}"));
        }
        Ok(v)
    }

    /// `self[key]` of an object.
    pub fn get(&self, key: &str) -> Option<&Json> {
        match self {
            Self::Obj(m) => m.get(key),
            _ => None,
        }
    }

    /// A number.
    pub fn num(&self) -> Option<f64> {
        match self {
            Self::Num(x) => Some(*x),
            _ => None,
        }
    }

    /// A string.
    pub fn str(&self) -> Option<&str> {
        match self {
            Self::Str(s) => Some(s),
            _ => None,
        }
    }

    /// An array of numbers (`null` as `None`).
    pub fn nums(&self) -> Option<Vec<Option<f64>>> {
        match self {
            Self::Arr(v) => Some(v.iter().map(Json::num).collect()),
            _ => None,
        }
    }
}

fn skip_ws(b: &[u8], i: &mut usize) {
    while b.get(*i).is_some_and(|c| c.is_ascii_whitespace()) {
        *i += 1;
    }
}

fn expect(b: &[u8], i: &mut usize, c: u8) -> Result<(), String> {
    skip_ws(b, i);
    if b.get(*i) == Some(&c) {
        *i += 1;
        Ok(())
    } else {
        Err(format!("expected '{}' at byte {i}", c as char))
    }
}

fn string(b: &[u8], i: &mut usize) -> Result<String, String> {
    expect(b, i, b'"')?;
    let start = *i;
    while let Some(&c) = b.get(*i) {
        if c == b'\\' {
            *i += 2;
            continue;
        }
        if c == b'"' {
            let s = String::from_utf8_lossy(&b[start..*i]).into_owned();
            *i += 1;
            return Ok(s);
        }
        *i += 1;
    }
    Err("unterminated string".into())
}

fn value(b: &[u8], i: &mut usize) -> Result<Json, String> {
    skip_ws(b, i);
    match b.get(*i) {
        Some(b'{') => {
            *i += 1;
            let mut m = BTreeMap::new();
            skip_ws(b, i);
            if b.get(*i) == Some(&b'}') {
                *i += 1;
                return Ok(Json::Obj(m));
            }
            loop {
                let k = string(b, i)?;
                expect(b, i, b':')?;
                m.insert(k, value(b, i)?);
                skip_ws(b, i);
                match b.get(*i) {
                    Some(b',') => *i += 1,
                    Some(b'}') => {
                        *i += 1;
                        return Ok(Json::Obj(m));
                    }
                    _ => return Err(format!("expected ',' or '}}' at byte {i}")),
                }
            }
        }
        Some(b'[') => {
            *i += 1;
            let mut v = Vec::new();
            skip_ws(b, i);
            if b.get(*i) == Some(&b']') {
                *i += 1;
                return Ok(Json::Arr(v));
            }
            loop {
                v.push(value(b, i)?);
                skip_ws(b, i);
                match b.get(*i) {
                    Some(b',') => *i += 1,
                    Some(b']') => {
                        *i += 1;
                        return Ok(Json::Arr(v));
                    }
                    _ => return Err(format!("expected ',' or ']' at byte {i}")),
                }
            }
        }
        Some(b'"') => Ok(Json::Str(string(b, i)?)),
        Some(b'n') if b[*i..].starts_with(b"null") => {
            *i += 4;
            Ok(Json::Null)
        }
        Some(b't') if b[*i..].starts_with(b"true") => {
            *i += 4;
            Ok(Json::Bool(true))
        }
        Some(b'f') if b[*i..].starts_with(b"false") => {
            *i += 5;
            Ok(Json::Bool(false))
        }
        Some(_) => {
            let start = *i;
            while b
                .get(*i)
                .is_some_and(|c| c.is_ascii_digit() || b"+-.eE".contains(c))
            {
                *i += 1;
            }
            std::str::from_utf8(&b[start..*i])
                .ok()
                .and_then(|s| s.parse().ok())
                .map(Json::Num)
                .ok_or_else(|| format!("bad value at byte {start}"))
        }
        None => Err("unexpected end".into()),
    }
}

/// One stroke of a dump.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct DumpStroke {
    /// `ok`, `nok`, or none (not judged).
    pub verdict: Option<String>,
    /// The first failed object, its figure and where.
    pub failed: Option<(String, f64, f64)>,
    /// Bin means and peaks, N (`None`: empty).
    pub mean_n: Vec<Option<f64>>,
    /// See [`Self::mean_n`].
    pub peak_n: Vec<Option<f64>>,
}

/// A box object: depths and forces.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Box4 {
    /// From, to depth, mm.
    pub from_mm: f64,
    /// See [`Self::from_mm`].
    pub to_mm: f64,
    /// Low, high force, N.
    pub low_n: f64,
    /// See [`Self::low_n`].
    pub high_n: f64,
}

/// A `curve --json` dump.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct CurveDump {
    /// `last`, `ref` or `nok`.
    pub which: String,
    /// Lifetime cycle (0: a reference).
    pub cycle: u32,
    /// The stroke's length, mm.
    pub stroke_mm: f64,
    /// Phase boundaries, mm.
    pub phases_mm: Vec<f64>,
    /// The insertion and the extraction.
    pub strokes: [DumpStroke; 2],
    /// Each bin's band, low and high, N.
    pub band_low_n: Vec<f64>,
    /// See [`Self::band_low_n`].
    pub band_high_n: Vec<f64>,
    /// The entry window: to this depth, at least this force.
    pub entry: (f64, f64),
    /// The plateau, end and extraction-peak boxes.
    pub plateau: Box4,
    /// See [`Self::plateau`].
    pub end: Box4,
    /// See [`Self::plateau`].
    pub ext_peak: Box4,
}

impl CurveDump {
    /// Read a dump (the first line of `text` that is a `curve` JSON object).
    pub fn parse(text: &str) -> Result<Self, String> {
        let line = text
            .lines()
            .find(|l| l.trim_start().starts_with("{\"curve\""))
            .ok_or("no `curve --json` line")?;
        let j = Json::parse(line.trim())?;
        let need = |v: Option<&Json>, what: &str| v.cloned().ok_or(format!("no {what}"));
        let nums = |v: Option<&Json>, what: &str| -> Result<Vec<f64>, String> {
            Ok(need(v, what)?
                .nums()
                .ok_or(format!("{what}: not numbers"))?
                .into_iter()
                .map(|x| x.unwrap_or(f64::NAN))
                .collect())
        };
        let stroke = |k: &str| -> Result<DumpStroke, String> {
            let s = need(j.get(k), k)?;
            let failed = s.get("failed").and_then(Json::str).map(|name| {
                (
                    name.to_string(),
                    s.get("figure").and_then(Json::num).unwrap_or(f64::NAN),
                    s.get("at_mm").and_then(Json::num).unwrap_or(f64::NAN),
                )
            });
            Ok(DumpStroke {
                verdict: s.get("verdict").and_then(Json::str).map(str::to_string),
                failed,
                mean_n: need(s.get("mean_n"), "mean_n")?.nums().ok_or("mean_n")?,
                peak_n: need(s.get("peak_n"), "peak_n")?.nums().ok_or("peak_n")?,
            })
        };
        let o = need(j.get("objects"), "objects")?;
        let box4 = |k: &str| -> Result<Box4, String> {
            let b = need(o.get(k), k)?;
            let n = |f: &str| b.get(f).and_then(Json::num).ok_or(format!("{k}.{f}"));
            Ok(Box4 {
                from_mm: n("from_mm")?,
                to_mm: n("to_mm")?,
                low_n: n("low_n")?,
                high_n: n("high_n")?,
            })
        };
        let entry = need(o.get("entry"), "entry")?;
        Ok(Self {
            which: j.get("curve").and_then(Json::str).unwrap_or("").to_string(),
            cycle: j.get("cycle").and_then(Json::num).unwrap_or(0.0) as u32,
            stroke_mm: j.get("stroke_mm").and_then(Json::num).unwrap_or(30.0),
            phases_mm: nums(j.get("phases_mm"), "phases_mm")?,
            strokes: [stroke("insertion")?, stroke("extraction")?],
            band_low_n: nums(o.get("band_low_n"), "band_low_n")?,
            band_high_n: nums(o.get("band_high_n"), "band_high_n")?,
            entry: (
                entry.get("to_mm").and_then(Json::num).unwrap_or(1.0),
                entry.get("force_n").and_then(Json::num).unwrap_or(0.0),
            ),
            plateau: box4("plateau")?,
            end: box4("end")?,
            ext_peak: box4("ext_peak")?,
        })
    }

    /// The bins' edges, mm.
    pub fn edge_mm(&self, i: usize) -> f64 {
        let n = self.band_low_n.len().max(1);
        ((i as f64 * self.stroke_mm * 1000.0 / n as f64).floor()) / 1000.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn json_values_parse() {
        let j = Json::parse(r#" {"a":[1,-2.5,null],"b":"x","c":{"d":true}} "#).unwrap();
        assert_eq!(
            j.get("a").and_then(Json::nums),
            Some(vec![Some(1.0), Some(-2.5), None])
        );
        assert_eq!(j.get("b").and_then(Json::str), Some("x"));
        assert_eq!(j.get("c").and_then(|c| c.get("d")), Some(&Json::Bool(true)));
        assert!(Json::parse("{\"a\":}").is_err());
        assert!(Json::parse("[1,2").is_err());
    }
}
