//! The `vboard` command line. Output on stdout; bad arguments: one line on stderr, exit
//! code 2; a board that cannot go on (an unmodelled access): one line on stderr, exit 1.

use std::io::Write;

use hil_sim::cli::{Opts, UsageError};

use crate::cpu::{BoardConfig, Timing};
use crate::periph::flash::FlashTiming;
use crate::scene::{Options, SceneOptions, SCENES};

/// One-line usage summary.
pub const USAGE: &str = "usage: vboard scene NAME [--firmware ELF] [--cycles N] [--rate 10|80] [--cpi X] [--timing cpi|art] [--lsi-hz HZ] [--flash-timing max|typical] [--seed S] [--cut transfer|swap|boot] [--curve FILE.json] [--flood] [--log] [--json] [--no-skip] | serve [--pty | --tcp 127.0.0.1:PORT] [--modbus-pty | --modbus-tcp 127.0.0.1:PORT] [--plc] [--firmware ELF] [--rate 10|80] [--cpi X] [--timing cpi|art] [--speed X] [--for SECONDS] [--no-skip] | estimate-cost [--readings N] [--firmware ELF] | signature-cost [--rate 10|80] [--cpi X] [--firmware ELF] [--json] [--no-skip] | swap-time [--firmware ELF] [--json]";

/// The sweep's usage (`vboard sweep`).
pub const SWEEP_USAGE: &str = "       vboard sweep [--scene NAME[,NAME...]] [--seeds 1..10|1,2,3] [--cpi X[,X...]] [--timing cpi|art[,...]] [--flood] [--cycles N] [--rate 10|80] [--lsi-hz HZ] [--flash-timing max|typical] [--firmware ELF] [--jobs N] [--json] [--no-skip]";

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

/// `--firmware FILE`, if given: a file that is not there is a usage error (exit 2),
/// like every other bad argument.
fn firmware(o: &Opts) -> Result<Option<String>, Failure> {
    match o.get("firmware") {
        None => Ok(None),
        Some(f) if std::path::Path::new(f).is_file() => Ok(Some(f.to_string())),
        Some(f) => usage(format!("--firmware {f}: no such file")),
    }
}

/// `vboard COMMAND --help`: that command's synopsis.
fn command_help(cmd: &str) -> Option<String> {
    if cmd == "sweep" {
        return Some(one_option_a_line(SWEEP_USAGE.trim_start()));
    }
    // USAGE's synopses, split at " | " before a command word (options have "|" too).
    let mut parts: Vec<String> = Vec::new();
    for piece in USAGE.trim_start_matches("usage: vboard ").split(" | ") {
        let word = piece.split_whitespace().next().unwrap_or("");
        match parts.last_mut() {
            Some(last)
                if ![
                    "scene",
                    "serve",
                    "estimate-cost",
                    "signature-cost",
                    "swap-time",
                ]
                .contains(&word) =>
            {
                last.push_str(" | ");
                last.push_str(piece);
            }
            _ => parts.push(piece.to_string()),
        }
    }
    parts
        .into_iter()
        .find(|p| p.split_whitespace().next() == Some(cmd))
        .map(|p| one_option_a_line(&format!("vboard {p}")))
}

/// What each option does, by its flag (shared by the commands that take it).
const OPTION_HELP: [(&str, &str); 25] = [
    ("--no-skip", "emulate every iteration of the polling loops (the same results, slower: the proof that skipping changes nothing)"),
    ("--firmware", "the image to run (default: the release build at the root; refused if older than its sources)"),
    ("--cycles", "docking cycles to run"),
    ("--rate", "the HX711's output rate, samples a second (its RATE pin)"),
    ("--cpi", "cycles per instruction of the emulated core (1-3; real silicon runs branchy code at 1.5-3)"),
    ("--timing", "cpi: a fixed CPI; art: the flash accelerator's cache model"),
    ("--lsi-hz", "the watchdog's LSI clock (17 000-47 000 Hz, the datasheet's spread)"),
    ("--flash-timing", "flash program/erase times: the datasheet's maximum or typical"),
    ("--seed", "the simulated devices' random seed"),
    ("--seeds", "seeds to sweep over (a range or a list)"),
    ("--flood", "a console and Modbus flood throughout"),
    ("--log", "print the image's defmt log"),
    ("--json", "one JSON object instead of text"),
    ("--pty", "the console on a pty or on TCP (first stdout line: its path or address)"),
    ("--modbus-pty", "USART3's Modbus RTU on a pty or TCP (stdout line: modbus ADDRESS); no demo cycles"),
    ("--plc", "the PLC drives (stdin: dock on|off, estop open|close, plc); no demo cycles"),
    ("--speed", "machine time per wall time"),
    ("--for", "stop after this long"),
    ("--readings", "micrometer readings the estimate is fitted to"),
    ("--scene", "scenes to sweep (default overload,estop)"),
    ("--jobs", "runs at once (default: the cores)"),
    ("NAME", "the scene"),
    ("--tcp", "the console on TCP (first stdout line: its address)"),
    ("--cut", "update-cut: the power cut during the transfer, the swap or the first boot"),
    ("--curve", "late-entry, dry-guide, debris, catch: write the board's `curve last --json` reply there (for `hil-sim plot-curve`)"),
];

/// A synopsis as the command's line, then its options one a line with what each does.
fn one_option_a_line(synopsis: &str) -> String {
    // Split at top-level `[...]` groups.
    let (mut head, mut groups) = (String::new(), Vec::<String>::new());
    let mut depth = 0u32;
    for ch in synopsis.chars() {
        let outer = depth == 0;
        match ch {
            '[' => depth += 1,
            ']' => depth = depth.saturating_sub(1),
            _ => {}
        }
        match (outer, depth) {
            // A group opens.
            (true, 1) => groups.push(String::new()),
            // Before the first group: the command's words.
            (true, 0) if groups.is_empty() => head.push(ch),
            (true, 0) => {}
            // Inside a group, its own outer brackets left out.
            (false, 0) => {}
            (false, _) => {
                if let Some(g) = groups.last_mut() {
                    g.push(ch);
                }
            }
            (true, _) => {}
        }
    }
    let mut out = format!("{} [OPTIONS]", head.trim_end());
    for g in groups {
        let flag = g.split_whitespace().next().unwrap_or("");
        let what = OPTION_HELP
            .iter()
            .find(|(f, _)| *f == flag)
            .map(|(_, w)| *w)
            .unwrap_or("");
        out += &format!("\n  {g:<44} {what}");
    }
    out
}

/// The commands, one a line (`vboard --help`, and after a usage error).
fn overview() -> String {
    let mut s = String::from(
        "usage: vboard COMMAND [OPTIONS]   (vboard COMMAND --help: its options, one a line)",
    );
    for (cmd, what) in [
        ("scene", "a scene on the virtual board"),
        (
            "serve",
            "the image in real time, its console (and Modbus) on a pty or TCP",
        ),
        ("estimate-cost", "the wear estimate's cost on the M4"),
        (
            "sweep",
            "scenes over seeds and timing models, the worst figures",
        ),
        ("swap-time", "the bootloader's swap and revert, timed"),
    ] {
        let first = command_help(cmd).unwrap_or_default();
        let first = first.lines().next().unwrap_or(cmd);
        s += &format!("\n  {:<40} {what}", first.trim_start_matches("vboard "));
    }
    s
}

/// Session options from the common flags.
fn session(o: &Opts) -> Result<Options, Failure> {
    let mut s = Options::new();
    if let Some(f) = firmware(o)? {
        s.firmware = f;
    }
    s.rate_sps = o.num("rate", 80u32, 1, u32::MAX)?;
    if !matches!(s.rate_sps, 10 | 80) {
        return usage(format!(
            "--rate must be 10 or 80 (the HX711's RATE pin), got '{}'",
            s.rate_sps
        ));
    }
    s.seed = o.num("seed", 1u64, 0, u64::MAX)?;
    let cpi = o.num("cpi", 1.0f64, 1.0, 3.0)?;
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
        skip: !o.flag("no-skip"),
        ..BoardConfig::default()
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
            "cut",
            "curve",
        ],
        &["json", "flood", "log", "no-skip"],
    )?;
    if o.get("curve").is_some() && !hil_sim::sigscene::SCENES.contains(&name.as_str()) {
        return usage(format!(
            "--curve is the signature scenes' ({})",
            hil_sim::sigscene::SCENES.join(", ")
        ));
    }
    let cut = match o.get("cut") {
        None => None,
        Some(c) => match crate::update::Cut::parse(c) {
            Some(c) if name == "update-cut" => Some(c),
            Some(_) => return usage("--cut is update-cut's".to_string()),
            None => return usage(format!("--cut must be transfer, swap or boot, got '{c}'")),
        },
    };
    let opts = SceneOptions {
        session: session(&o)?,
        cycles: o.num("cycles", 1u32, 1, 1_000)?,
        flood: o.flag("flood"),
        cut,
    };
    let r = crate::scene::run(name, &opts).map_err(Failure::Run)?;
    if let (Some(path), Some(curve)) = (o.get("curve"), r.curve_json.as_ref()) {
        std::fs::write(path, curve).map_err(|e| Failure::Run(format!("--curve {path}: {e}")))?;
    }
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
            "modbus-tcp",
        ],
        &["pty", "modbus-pty", "plc", "no-skip"],
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
    let modbus = match (o.flag("modbus-pty"), o.get("modbus-tcp")) {
        (true, Some(_)) => return usage("give --modbus-pty or --modbus-tcp, not both"),
        (_, Some(a)) => match a.parse::<std::net::SocketAddr>() {
            Ok(addr) if addr.ip().is_loopback() => Some(hil_sim::serve::Link::Tcp(addr)),
            _ => {
                return usage(format!(
                    "--modbus-tcp must be a loopback address like 127.0.0.1:5020, got '{a}'"
                ))
            }
        },
        (true, None) => Some(hil_sim::serve::Link::Pty),
        (false, None) => None,
    };
    let opts = crate::serve::ServeOptions {
        link,
        modbus,
        plc: o.flag("plc"),
        session: session(&o)?,
        speed: o.num("speed", 1.0f64, 1e-3, 1e3)?,
        duration_s: match o.get("for") {
            None => None,
            Some(_) => Some(o.num("for", 0.0f64, 0.0, 1e7)?),
        },
    };
    crate::serve::run(&opts, out).map_err(Failure::Run)
}

/// `vboard sweep`: `--scene` (default `overload,estop`) over `--seeds` (default 1..10)
/// and every timing model (each of the `--timing` list, default `cpi`, at each of the
/// `--cpi` list, default 1; with neither: CPI 1, 2, 3 and `art` at CPI 1); one row a run
/// as it completes on stderr, the table (or `--json`) on stdout. Exit 1 when a run
/// misses a target (the reasons on stderr).
fn sweep_cmd(args: &[String], out: &mut dyn Write) -> Result<(), Failure> {
    let own = ["scene", "seeds", "cpi", "timing", "jobs"];
    let common = ["firmware", "cycles", "rate", "lsi-hz", "flash-timing"];
    let valued: Vec<&str> = own.iter().chain(&common).copied().collect();
    let o = Opts::parse(args, &valued, &["json", "flood", "no-skip"])?;
    let scenes: Vec<String> = o
        .get("scene")
        .unwrap_or("overload,estop")
        .split(',')
        .map(|x| x.trim().to_string())
        .collect();
    if let Some(bad) = scenes.iter().find(|n| !SCENES.contains(&n.as_str())) {
        return usage(format!(
            "unknown scene '{bad}' (scenes: {})",
            SCENES.join(", ")
        ));
    }
    let seeds =
        crate::sweep::parse_seeds(o.get("seeds").unwrap_or("1..10")).map_err(Failure::Usage)?;
    // The models: each `--timing` with each `--cpi`; by default the set, CPI 1,
    // 2 and 3 and the ART cache model at CPI 1.
    let plan: Vec<(Option<&str>, &str)> = match (o.get("timing"), o.get("cpi")) {
        (None, None) => vec![(None, "1"), (None, "2"), (None, "3"), (Some("art"), "1")],
        (t, c) => {
            let cpis: Vec<&str> = c.unwrap_or("1").split(',').map(str::trim).collect();
            let timings: Vec<Option<&str>> = match t {
                None => vec![None],
                Some(t) => t.split(',').map(|x| Some(x.trim())).collect(),
            };
            timings
                .iter()
                .flat_map(|&t| cpis.iter().map(move |&c| (t, c)))
                .collect()
        }
    };
    // Each model's board from the scene's own options: `--cpi X [--timing T]` and the
    // common flags, as `vboard scene` would take them.
    let mut base_args: Vec<String> = Vec::new();
    for k in common {
        if let Some(v) = o.get(k) {
            base_args.extend([format!("--{k}"), v.to_string()]);
        }
    }
    let mut models = Vec::new();
    let mut base = None;
    for (t, c) in plan {
        let mut a = base_args.clone();
        if o.flag("no-skip") {
            a.push("--no-skip".to_string());
        }
        a.extend(["--cpi".to_string(), c.to_string()]);
        if let Some(t) = t {
            a.extend(["--timing".to_string(), t.to_string()]);
        }
        let mut keys = vec!["cpi", "timing"];
        keys.extend(common);
        let s = session(&Opts::parse(&a, &keys, &["no-skip"])?)?;
        models.push(crate::sweep::Model {
            label: format!("{} {c}", t.unwrap_or("cpi")),
            board: s.board,
        });
        base.get_or_insert(s);
    }
    let Some(session) = base else {
        return usage("--cpi needs at least one value");
    };
    let jobs_default = std::thread::available_parallelism().map_or(1, |n| n.get());
    let opts = crate::sweep::SweepOptions {
        scenes,
        seeds,
        models,
        base: SceneOptions {
            session,
            cycles: o.num("cycles", 1u32, 1, 1_000)?,
            flood: o.flag("flood"),
            cut: None,
        },
        jobs: o.num("jobs", jobs_default, 1, 64)?,
    };
    let total = opts.scenes.len() * opts.seeds.len() * opts.models.len();
    let count = std::sync::atomic::AtomicUsize::new(0);
    let r = crate::sweep::sweep(&opts, &|row| {
        let n = count.fetch_add(1, std::sync::atomic::Ordering::Relaxed) + 1;
        eprintln!("[{n}/{total}] {}", row.to_text());
    });
    let text = if o.flag("json") {
        r.to_json()
    } else {
        r.to_text()
    };
    let _ = writeln!(out, "{text}");
    let misses = r.misses();
    if misses.is_empty() {
        Ok(())
    } else {
        for m in &misses {
            eprintln!("missed: {m}");
        }
        Err(Failure::Run(format!(
            "{} of {total} run(s) miss a target",
            r.worst(None).missing
        )))
    }
}

fn estimate_cost(args: &[String], out: &mut dyn Write) -> Result<(), Failure> {
    let o = Opts::parse(args, &["firmware", "readings"], &[])?;
    let mut opts = Options::new();
    if let Some(f) = firmware(&o)? {
        opts.firmware = f;
    }
    let n = o.num("readings", 30usize, 1, 40)?;
    let r = crate::scene::estimate_cost(&opts, n).map_err(Failure::Run)?;
    let _ = writeln!(out, "{}", r.to_text());
    Ok(())
}

/// `signature-cost [--rate 10|80] [--cpi X] [--firmware ELF] [--json]`: what the docking
/// signature costs the image (crate::scene::signature_cost).
fn signature_cost(args: &[String], out: &mut dyn Write) -> Result<(), Failure> {
    let o = Opts::parse(args, &["firmware", "rate", "cpi"], &["json", "no-skip"])?;
    let opts = session(&o)?;
    let r = crate::scene::signature_cost(&opts).map_err(Failure::Run)?;
    let text = if o.flag("json") {
        r.to_json()
    } else {
        r.to_text()
    };
    let _ = writeln!(out, "{text}");
    Ok(())
}

/// `swap-time [--firmware ELF] [--json]`: the bootloader's swap and revert, timed
/// (crate::swap).
fn swap_time(args: &[String], out: &mut dyn Write) -> Result<(), Failure> {
    let o = Opts::parse(args, &["firmware"], &["json"])?;
    let path = match firmware(&o)? {
        Some(f) => f,
        None => crate::image::default_path(),
    };
    let img = crate::image::Image::load(&path).map_err(Failure::Run)?;
    let app = crate::update::app_bytes(&img);
    let rows = crate::swap::table(&crate::image::bootloader_path(), &app).map_err(Failure::Run)?;
    if o.flag("json") {
        for r in &rows {
            let _ = writeln!(out, "{}", r.to_json());
        }
    } else {
        let _ = writeln!(out, "{}", crate::swap::HEADER);
        for r in &rows {
            let _ = writeln!(out, "{}", r.to_text());
        }
    }
    Ok(())
}

/// Run the command line `args` (without the program name).
pub fn run(args: &[String], out: &mut dyn Write) -> Result<(), Failure> {
    let Some((cmd, rest)) = args.split_first() else {
        return usage(overview());
    };
    if rest.iter().any(|a| a == "--help" || a == "-h") {
        if let Some(h) = command_help(cmd) {
            let _ = writeln!(out, "{h}");
            return Ok(());
        }
    }
    match cmd.as_str() {
        "scene" => scene(rest, out),
        "serve" => serve(rest, out),
        "estimate-cost" => estimate_cost(rest, out),
        "signature-cost" => signature_cost(rest, out),
        "sweep" => sweep_cmd(rest, out),
        "swap-time" => swap_time(rest, out),
        "help" | "--help" | "-h" => {
            let _ = writeln!(out, "{}", overview());
            Ok(())
        }
        other => usage(format!("unknown command '{other}'\n{}", overview())),
    }
}

#[cfg(test)]
mod help_tests {
    use super::{run, Failure};

    fn run_args(args: &[&str]) -> (Result<(), Failure>, String) {
        let args: Vec<String> = args.iter().map(|a| a.to_string()).collect();
        let mut out = Vec::new();
        let r = run(&args, &mut out);
        (r, String::from_utf8(out).unwrap())
    }

    #[test]
    fn every_command_answers_help_with_one_option_a_line() {
        for cmd in [
            "scene",
            "serve",
            "estimate-cost",
            "signature-cost",
            "sweep",
            "swap-time",
        ] {
            let (r, out) = run_args(&[cmd, "--help"]);
            assert!(r.is_ok(), "{cmd}");
            assert!(out.starts_with(&format!("vboard {cmd} ")), "{cmd}: {out}");
            let firmware = out
                .lines()
                .find(|l| l.trim_start().starts_with("--firmware ELF"))
                .unwrap_or_else(|| panic!("{cmd}: no --firmware line: {out}"));
            assert!(firmware.contains("the image to run"), "{firmware}");
            // Every option line says what it does.
            for l in out.lines().skip(1) {
                let words: Vec<&str> = l.split("  ").filter(|w| !w.is_empty()).collect();
                assert!(
                    words.len() >= 2,
                    "{cmd}: an option without its meaning: {l:?}"
                );
            }
        }
        let (_, out) = run_args(&["serve", "--help"]);
        assert!(out.contains("\n  --pty | --tcp 127.0.0.1:PORT "), "{out}");
        assert!(
            out.contains("\n  --modbus-pty | --modbus-tcp 127.0.0.1:PORT "),
            "{out}"
        );
    }

    /// `vboard --help` printed one line of 1,200 characters; `--cpi 9` was run.
    #[test]
    fn help_is_a_command_a_line_and_cpi_is_one_to_three() {
        let (r, out) = run_args(&["--help"]);
        assert!(r.is_ok());
        let lines: Vec<&str> = out.lines().collect();
        assert_eq!(lines.len(), 6, "{out}");
        assert!(lines.iter().all(|l| l.len() < 120), "{out}");
        for cmd in ["scene", "serve", "estimate-cost", "sweep", "swap-time"] {
            assert!(
                lines.iter().any(|l| l.trim_start().starts_with(cmd)),
                "{cmd}: {out}"
            );
        }
        match run_args(&[]).0 {
            Err(Failure::Usage(e)) => assert_eq!(e.lines().count(), 6, "{e}"),
            _ => panic!("no command is a usage error"),
        }
        for cpi in ["9", "0.5", "3.5"] {
            match run_args(&["scene", "boot", "--cpi", cpi]).0 {
                Err(Failure::Usage(e)) => assert!(e.contains("cpi"), "{e}"),
                _ => panic!("--cpi {cpi} accepted"),
            }
        }
    }

    #[test]
    fn modbus_links_are_one_and_on_loopback() {
        for args in [
            &["serve", "--modbus-pty", "--modbus-tcp", "127.0.0.1:0"][..],
            &["serve", "--modbus-tcp", "10.0.0.1:502"],
            &["serve", "--modbus-tcp", "localhost"],
        ] {
            match run_args(args).0 {
                Err(Failure::Usage(e)) => assert!(e.contains("--modbus"), "{e}"),
                other => panic!("{args:?}: {:?}", other.err().map(|_| "not a usage error")),
            }
        }
    }

    #[test]
    fn a_missing_firmware_file_is_a_usage_error() {
        for cmd in [
            "scene nominal",
            "estimate-cost",
            "signature-cost",
            "sweep",
            "swap-time",
        ] {
            let mut args: Vec<&str> = cmd.split(' ').collect();
            args.extend(["--firmware", "/no/such/image.elf"]);
            match run_args(&args).0 {
                Err(Failure::Usage(e)) => assert!(e.contains("/no/such/image.elf"), "{e}"),
                other => panic!("{cmd}: {:?}", other.err().map(|_| "not a usage error")),
            }
        }
    }
}
