//! The `vboard` command line. Output on stdout; bad arguments: one line on stderr, exit
//! code 2; a board that cannot go on (an unmodelled access): one line on stderr, exit 1.

use std::io::Write;

use hil_sim::cli::{Opts, UsageError};

use crate::cpu::{BoardConfig, Timing};
use crate::periph::flash::FlashTiming;
use crate::scene::{Options, SceneOptions, SCENES};

/// One-line usage summary.
pub const USAGE: &str = "usage: vboard scene NAME [--firmware ELF] [--cycles N] [--rate 10|80] [--cpi X] [--timing cpi|art] [--lsi-hz HZ] [--flash-timing max|typical] [--seed S] [--flood] [--log] [--json] | serve [--pty | --tcp 127.0.0.1:PORT] [--firmware ELF] [--rate 10|80] [--cpi X] [--timing cpi|art] [--speed X] [--for SECONDS] | estimate-cost [--readings N] [--firmware ELF]";

/// How the command failed.
#[derive(Debug)]
pub enum Failure {
    /// Bad arguments (exit 2).
    Usage(String),
    /// The run could not complete (exit 1).
    Run(String),
}

fn usage<T>(msg: impl Into<String>) -> Result<T, Failure> {
    Err(Failure::Usage(msg.into()))
}

impl From<UsageError> for Failure {
    fn from(e: UsageError) -> Self {
        Failure::Usage(e.0)
    }
}

/// Session options from the common flags.
fn session(o: &Opts) -> Result<Options, Failure> {
    let mut s = Options::new();
    if let Some(f) = o.get("firmware") {
        s.firmware = f.to_string();
    }
    s.rate_sps = o.num("rate", 80u32, 1, u32::MAX)?;
    if !matches!(s.rate_sps, 10 | 80) {
        return usage(format!(
            "--rate must be 10 or 80 (the HX711's RATE pin), got '{}'",
            s.rate_sps
        ));
    }
    s.seed = o.num("seed", 1u64, 0, u64::MAX)?;
    let cpi = o.num("cpi", 1.0f64, 0.5, 10.0)?;
    let lsi = o.num("lsi-hz", 32_000u64, 17_000, 47_000)?;
    let timing = match o.get("flash-timing") {
        None | Some("max") => FlashTiming::Max,
        Some("typical") => FlashTiming::Typical,
        Some(x) => {
            return usage(format!(
                "--flash-timing must be 'max' or 'typical', got '{x}'"
            ))
        }
    };
    let timing_model = match o.get("timing") {
        None | Some("cpi") => Timing::Cpi,
        Some("art") => Timing::Art,
        Some(x) => return usage(format!("--timing must be 'cpi' or 'art', got '{x}'")),
    };
    s.board = BoardConfig {
        cpi_milli: (cpi * 1000.0).round() as u64,
        timing: timing_model,
        lsi_hz: lsi,
        flash_timing: timing,
    };
    Ok(s)
}

fn scene(args: &[String], out: &mut dyn Write) -> Result<(), Failure> {
    let Some((name, rest)) = args.split_first() else {
        return usage(format!("scene needs a name ({})", SCENES.join(", ")));
    };
    if !SCENES.contains(&name.as_str()) {
        return usage(format!(
            "unknown scene '{name}' (scenes: {})",
            SCENES.join(", ")
        ));
    }
    let o = Opts::parse(
        rest,
        &[
            "firmware",
            "cycles",
            "rate",
            "cpi",
            "timing",
            "lsi-hz",
            "flash-timing",
            "seed",
        ],
        &["json", "flood", "log"],
    )?;
    let opts = SceneOptions {
        session: session(&o)?,
        cycles: o.num("cycles", 1u32, 1, 1_000)?,
        flood: o.flag("flood"),
    };
    let r = crate::scene::run(name, &opts).map_err(Failure::Run)?;
    if o.flag("log") {
        for l in &r.log {
            eprintln!("{} {:<5} {}", l.timestamp, l.level, l.msg);
        }
    }
    let text = if o.flag("json") {
        r.to_json()
    } else {
        r.to_text()
    };
    let _ = writeln!(out, "{text}");
    Ok(())
}

fn serve(args: &[String], out: &mut dyn Write) -> Result<(), Failure> {
    let o = Opts::parse(
        args,
        &[
            "tcp",
            "firmware",
            "rate",
            "cpi",
            "timing",
            "speed",
            "for",
            "lsi-hz",
            "flash-timing",
            "seed",
        ],
        &["pty"],
    )?;
    let link = match (o.flag("pty"), o.get("tcp")) {
        (true, Some(_)) => return usage("give --pty or --tcp, not both"),
        (_, Some(a)) => hil_sim::serve::Link::Tcp(a.parse().map_err(|_| {
            Failure::Usage(format!(
                "--tcp must be an address like 127.0.0.1:7000, got '{a}'"
            ))
        })?),
        _ => hil_sim::serve::Link::Pty,
    };
    let opts = crate::serve::ServeOptions {
        link,
        session: session(&o)?,
        speed: o.num("speed", 1.0f64, 1e-3, 1e3)?,
        duration_s: match o.get("for") {
            None => None,
            Some(_) => Some(o.num("for", 0.0f64, 0.0, 1e7)?),
        },
    };
    crate::serve::run(&opts, out).map_err(Failure::Run)
}

fn estimate_cost(args: &[String], out: &mut dyn Write) -> Result<(), Failure> {
    let o = Opts::parse(args, &["firmware", "readings"], &[])?;
    let mut opts = Options::new();
    if let Some(f) = o.get("firmware") {
        opts.firmware = f.to_string();
    }
    let n = o.num("readings", 30usize, 1, 40)?;
    let r = crate::scene::estimate_cost(&opts, n).map_err(Failure::Run)?;
    let _ = writeln!(out, "{}", r.to_text());
    Ok(())
}

/// Run the command line `args` (without the program name).
pub fn run(args: &[String], out: &mut dyn Write) -> Result<(), Failure> {
    let Some((cmd, rest)) = args.split_first() else {
        return usage(USAGE);
    };
    match cmd.as_str() {
        "scene" => scene(rest, out),
        "serve" => serve(rest, out),
        "estimate-cost" => estimate_cost(rest, out),
        "help" | "--help" | "-h" => {
            let _ = writeln!(out, "{USAGE}");
            Ok(())
        }
        other => usage(format!("unknown command '{other}'; {USAGE}")),
    }
}
