//! The `hil-sim` command line. Output on stdout; errors are one line on stderr with
//! exit code 2.

use std::io::Write;

use crate::profile_cmd::{self, Stroke};

/// A command-line error: printed as one line, exit code 2.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UsageError(pub String);

impl std::fmt::Display for UsageError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

/// One-line usage summary.
pub const USAGE: &str = "usage: hil-sim profile [--rate HZ] [--stroke insert|extract]";

fn err<T>(msg: impl Into<String>) -> Result<T, UsageError> {
    Err(UsageError(msg.into()))
}

/// Options as `--name value` pairs, refusing unknown names, repeats and missing values.
pub struct Opts {
    pairs: Vec<(String, String)>,
}

impl Opts {
    /// Parse `args` as `--name value` pairs; `flags` are names that take no value.
    pub fn parse(args: &[String], valued: &[&str], flags: &[&str]) -> Result<Self, UsageError> {
        let mut pairs: Vec<(String, String)> = Vec::new();
        let mut it = args.iter();
        while let Some(a) = it.next() {
            let Some(name) = a.strip_prefix("--") else {
                return err(format!("unexpected argument '{a}'"));
            };
            if pairs.iter().any(|(n, _)| n == name) {
                return err(format!("--{name} given twice"));
            }
            if flags.contains(&name) {
                pairs.push((name.to_string(), String::new()));
            } else if valued.contains(&name) {
                let Some(v) = it.next() else {
                    return err(format!("--{name} needs a value"));
                };
                pairs.push((name.to_string(), v.clone()));
            } else {
                return err(format!("unknown option '--{name}'"));
            }
        }
        Ok(Self { pairs })
    }

    /// The value of `--name`, if given.
    pub fn get(&self, name: &str) -> Option<&str> {
        self.pairs
            .iter()
            .find(|(n, _)| n == name)
            .map(|(_, v)| v.as_str())
    }

    /// Whether flag `--name` was given.
    pub fn flag(&self, name: &str) -> bool {
        self.get(name).is_some()
    }

    /// `--name` as a number in `[min, max]`, or `default`.
    pub fn num<T>(&self, name: &str, default: T, min: T, max: T) -> Result<T, UsageError>
    where
        T: std::str::FromStr + PartialOrd + std::fmt::Display + Copy,
    {
        let Some(v) = self.get(name) else {
            return Ok(default);
        };
        match v.trim().parse::<T>() {
            Ok(x) if x >= min && x <= max => Ok(x),
            _ => err(format!(
                "--{name} must be a number from {min} to {max}, got '{v}'"
            )),
        }
    }
}

/// Largest profile rate, Hz (25 s × 100 kHz = 2.5 M rows).
pub const PROFILE_RATE_MAX_HZ: f64 = 100_000.0;

fn profile(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let o = Opts::parse(args, &["rate", "stroke"], &[])?;
    let rate = match o.get("rate") {
        None => 80.0,
        Some(v) => match v.trim().parse::<f64>() {
            Ok(r) if r.is_finite() && r > 0.0 && r <= PROFILE_RATE_MAX_HZ => r,
            _ => {
                return err(format!(
                "--rate must be a sample rate in Hz, > 0 and <= {PROFILE_RATE_MAX_HZ}, got '{v}'"
            ))
            }
        },
    };
    let stroke = match o.get("stroke") {
        None | Some("insert") => Stroke::Insert,
        Some("extract") => Stroke::Extract,
        Some(s) => return err(format!("--stroke must be 'insert' or 'extract', got '{s}'")),
    };
    let mut buf = std::io::BufWriter::new(out);
    // A closed pipe (`| head`) is not an error of ours.
    let _ = profile_cmd::write_csv(&mut buf, rate, stroke).and_then(|_| buf.flush());
    Ok(())
}

/// Run the command line `args` (without the program name), writing to `out`.
pub fn run(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let Some((cmd, rest)) = args.split_first() else {
        return err(USAGE);
    };
    match cmd.as_str() {
        "profile" => profile(rest, out),
        "help" | "--help" | "-h" => {
            let _ = writeln!(out, "{USAGE}");
            Ok(())
        }
        other => err(format!("unknown command '{other}'; {USAGE}")),
    }
}
