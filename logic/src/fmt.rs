//! Crate-internal logging macros, after embassy-sync's `fmt.rs`.
//!
//! With the `defmt` feature (the board turns it on) they forward to `defmt` (RTT);
//! without it, to the `log` facade, so the library builds and tests on the host without
//! defmt's linker symbols (a `defmt::` call in host-linked code fails with undefined
//! `_defmt_*`).
//!
//! Format strings are defmt's, **typed** where the argument is a primitive or a string
//! (`{=u32}`, `{=i32}`, `{=u64}`, `{=str}`, `{=bool}`, `{=u32:#x}`) and `{}` / `{:?}`
//! (the argument's `defmt::Format`) otherwise: a typed argument is written as its
//! bytes, where `{}` first writes its type's format string at every call site (about
//! 12 bytes of flash an argument, issue 20). On the host every placeholder shows its
//! argument's `Debug` ([`Host`]); arguments must implement `defmt::Format` (board) and
//! `Debug` (host).
#![allow(unused_macros)]

macro_rules! log_with {
    ($defmt:ident, $log:ident, $fmt:literal $(, $arg:expr)* $(,)?) => {{
        #[cfg(feature = "defmt")]
        ::defmt::$defmt!($fmt $(, $arg)*);
        #[cfg(not(feature = "defmt"))]
        ::log::$log!(
            "{}",
            crate::fmt::Host($fmt, &[$(&$arg as &dyn ::core::fmt::Debug),*])
        );
    }};
}

macro_rules! info {
    ($($t:tt)*) => { log_with!(info, info, $($t)*) };
}

macro_rules! warn {
    ($($t:tt)*) => { log_with!(warn, warn, $($t)*) };
}

macro_rules! error {
    ($($t:tt)*) => { log_with!(error, error, $($t)*) };
}

macro_rules! debug {
    ($($t:tt)*) => { log_with!(debug, debug, $($t)*) };
}

/// A defmt format string and its arguments, shown on the host: each `{…}` placeholder
/// by its argument's `Debug`, in order (`{{` and `}}` are braces).
#[cfg(not(feature = "defmt"))]
pub(crate) struct Host<'a>(pub &'a str, pub &'a [&'a dyn core::fmt::Debug]);

#[cfg(not(feature = "defmt"))]
impl core::fmt::Display for Host<'_> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        let mut args = self.1.iter();
        let mut rest = self.0;
        while let Some(i) = rest.find(['{', '}']) {
            f.write_str(rest.get(..i).unwrap_or(""))?;
            let tail = rest.get(i..).unwrap_or("");
            if tail.starts_with("{{") || tail.starts_with("}}") {
                f.write_str(tail.get(..1).unwrap_or(""))?;
                rest = tail.get(2..).unwrap_or("");
            } else if tail.starts_with('{') {
                let end = tail.find('}').map_or(tail.len(), |e| e + 1);
                match args.next() {
                    Some(a) => write!(f, "{a:?}")?,
                    None => f.write_str(tail.get(..end).unwrap_or(""))?,
                }
                rest = tail.get(end..).unwrap_or("");
            } else {
                f.write_str("}")?;
                rest = tail.get(1..).unwrap_or("");
            }
        }
        f.write_str(rest)
    }
}

#[cfg(all(test, not(feature = "defmt")))]
mod tests {
    extern crate std;
    use super::Host;
    use std::string::ToString;

    #[test]
    fn host_shows_each_placeholder_by_its_argument() {
        let s = Host(
            "cone {=u16} ({=str}), {} us, pc {=u32:#x} {{x}}",
            &[&3u16, &"zqsn5-2", &Some(5u32), &255u32],
        )
        .to_string();
        assert_eq!(s, "cone 3 (\"zqsn5-2\"), Some(5) us, pc 255 {x}");
        assert_eq!(Host("left {} {}", &[&1]).to_string(), "left 1 {}");
    }
}
