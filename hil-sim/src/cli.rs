//! The `hil-sim` command line. Output on stdout; errors are one line on stderr with
//! exit code 2.

use std::io::{IsTerminal, Write};

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
pub const USAGE: &str = "usage: hil-sim profile [--rate HZ] [--stroke insert|extract] [--plot FILE.svg] [--model eq7|plant] [--mass-kg M] [--mu1 X] [--mu2 X] [--gamma-deg G] [--theta0-deg T] [--v-model MM_PER_S] [--t3-s S] | scene NAME [--cycles N] [--rate 10|80] [--seed S] [--json] [--plot FILE.svg] [--model eq7|plant (plant options as for profile)] [--config default|matching] | bench [--cycles N] [--rate SPS] | life --cycles N [--material NAME] [--at m1,m2,...] [--rate SPS] [--readings FILE.csv] [--json] [--plot FILE.svg] | endurance --cycles N [--material NAME] [--rate SPS] | accuracy [--json] [--plot FILE.svg] | plot-curve DUMP.json [--ref REF.json] --plot FILE.svg | signature-study [--dockings N] [--rate 10|80] [--seed S] [--json] | commission --model plant [plant options] [--vendor NAME] [--product NAME] (Rust source for DOCKING_TUNING) | serve [--pty | --tcp 127.0.0.1:PORT] [--modbus-pty | --modbus-tcp 127.0.0.1:PORT] [--plc] [--scene NAME] [--speed X] [--rate SPS] [--for SECONDS] (stdin: dock on|off, estop open|close, plc)";

/// Parse `--rate` as one of the HX711 rates.
fn hx_rate(o: &Opts) -> Result<u32, UsageError> {
    let r = o.num("rate", 80u32, 1, u32::MAX)?;
    if !crate::hx711::Hx711Config::RATES_SPS.contains(&r) {
        return err(format!(
            "--rate must be 10 or 80 samples/s (the HX711's RATE pin), got '{r}'"
        ));
    }
    Ok(r)
}

fn scene(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let Some((name, rest)) = args.split_first() else {
        return err(format!(
            "scene needs a name ({})",
            crate::scene::SCENES.join(", ")
        ));
    };
    let valued: Vec<&str> = ["cycles", "rate", "seed", "plot", "config"]
        .into_iter()
        .chain(profile_cmd::MODEL_OPTIONS)
        .collect();
    let o = Opts::parse(rest, &valued, &["json"])?;
    // The machine (`--model plant …`: another machine's forces) and the controller's
    // configuration: the build's (`default`) or commissioned for that machine
    // (`matching`).
    let force_model = match profile_cmd::model(&o)? {
        profile_cmd::Model::Eq7 => crate::machine::ForceModel::Eq7,
        profile_cmd::Model::Plant(p) => crate::machine::ForceModel::Plant(p),
    };
    let tuning = match (o.get("config"), &force_model) {
        (None | Some("default"), _) => None,
        (Some("matching"), crate::machine::ForceModel::Eq7) => None,
        (Some("matching"), crate::machine::ForceModel::Plant(p)) => Some(
            crate::machine::Tuning::for_plant(*p.params())
                .map_err(|e| UsageError(format!("--config matching: {e}")))?,
        ),
        (Some(c), _) => {
            return err(format!(
                "--config must be 'default' or 'matching', got '{c}'"
            ))
        }
    };
    let opts = crate::scene::SceneOptions {
        cycles: o.num("cycles", 1u32, 1, 100_000)?,
        seed: o.num("seed", 1u64, 0, u64::MAX)?,
        force_model,
        tuning,
        ..crate::scene::SceneOptions::new(hx_rate(&o)?)
    };
    let report = match o.get("plot") {
        None => crate::scene::run(name, opts).map_err(UsageError)?,
        Some(path) => {
            // The title tells runs apart: the machine and the configuration too.
            let machine = match &force_model {
                crate::machine::ForceModel::Eq7 => "Eq. 7".to_string(),
                crate::machine::ForceModel::Plant(p) => {
                    let p = p.params();
                    format!("plant m {} kg, µ1 {}, µ2 {}", p.mass_kg, p.mu1, p.mu2)
                }
            };
            let config = if tuning.is_some() {
                "configuration matching it"
            } else {
                "the build's configuration"
            };
            let variant = format!("{machine}, {config}");
            let (report, trace) = crate::scene::run_traced(name, opts).map_err(UsageError)?;
            let guard = tuning.map_or(docking_logic::guard::GuardConfig::DEFAULT, |t| t.guard);
            crate::plot::scene(path.as_ref(), &report, &trace, &guard, &variant)?;
            report
        }
    };
    let verdict = report.verdict(opts.cycles);
    print(
        out,
        &o,
        || report.to_json(),
        || format!("{}\n{}", report.to_text(), verdict.to_text()),
    );
    Ok(())
}

fn life(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let o = Opts::parse(
        args,
        &["cycles", "material", "at", "rate", "readings", "plot"],
        &["json"],
    )?;
    if o.get("cycles").is_none() {
        return err("life needs --cycles N (N >= 1)");
    }
    let cycles = o.num("cycles", 1u32, 1, 10_000_000)?;
    let material = material(&o)?;
    let at = match o.get("at") {
        None => crate::life::default_checkpoints(cycles),
        Some(list) => {
            let mut v = Vec::new();
            for part in list.split(',') {
                match part.trim().parse::<u32>() {
                    Ok(c) if (1..=cycles).contains(&c) => v.push(c),
                    _ => return err(format!("--at must be a comma-separated list of cycle numbers from 1 to {cycles}, got '{list}'")),
                }
            }
            v.sort_unstable();
            v.dedup();
            v
        }
    };
    let readings = match o.get("readings") {
        None => Vec::new(),
        Some(path) => {
            let text = std::fs::read_to_string(path)
                .map_err(|e| UsageError(format!("--readings {path}: {e}")))?;
            parse_readings(&text).map_err(|e| UsageError(format!("--readings {path}: {e}")))?
        }
    };
    let opts = crate::life::LifeOptions {
        cycles,
        material,
        at,
        rate_sps: hx_rate(&o)?,
        readings,
    };
    let report = match o.get("plot") {
        None => crate::life::run(&opts),
        Some(path) => {
            let curve_at = crate::life::curve_checkpoints(cycles);
            let (report, curve) = crate::life::run_with_curve(&opts, &curve_at);
            crate::plot::life(path.as_ref(), &opts, &report, &curve)?;
            report
        }
    };
    print(out, &o, || report.to_json(), || report.to_text());
    Ok(())
}

/// A technician's readings: `cycle,bore_mm` lines (a `cycle,bore_mm` header, blank lines
/// and `#` comments allowed), cycles strictly increasing from 0 (the baseline), bores
/// 20.000–40.000 mm with at most 3 decimals.
pub fn parse_readings(text: &str) -> Result<Vec<(u32, u32)>, String> {
    let mut v: Vec<(u32, u32)> = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let n = i + 1;
        let line = raw.trim();
        if line.is_empty() || line.starts_with('#') || (v.is_empty() && line == "cycle,bore_mm") {
            continue;
        }
        let Some((c, d)) = line.split_once(',') else {
            return Err(format!("line {n}: expected 'cycle,bore_mm', got '{line}'"));
        };
        let cycle: u32 = c
            .trim()
            .parse()
            .map_err(|_| format!("line {n}: bad cycle '{}'", c.trim()))?;
        let bore_um = parse_mm(d.trim())
            .filter(|b| (20_000..=40_000).contains(b))
            .ok_or_else(|| {
                format!(
                    "line {n}: bore '{}' is not 20.000–40.000 mm with at most 3 decimals",
                    d.trim()
                )
            })?;
        match v.last() {
            None if cycle != 0 => {
                return Err(format!(
                    "line {n}: the first reading is the baseline, at cycle 0 (got {cycle})"
                ))
            }
            Some(&(last, _)) if cycle <= last => {
                return Err(format!(
                    "line {n}: cycles out of order ({cycle} after {last})"
                ))
            }
            _ => {}
        }
        v.push((cycle, bore_um));
    }
    if v.is_empty() {
        return Err("no readings".into());
    }
    Ok(v)
}

/// `26.012` → 26 012 µm (up to 3 decimals, no sign, no exponent).
fn parse_mm(t: &str) -> Option<u32> {
    let (i, f) = t.split_once('.').unwrap_or((t, ""));
    if i.is_empty()
        || i.len() > 3
        || f.len() > 3
        || !i.bytes().all(|b| b.is_ascii_digit())
        || !f.bytes().all(|b| b.is_ascii_digit())
    {
        return None;
    }
    let whole: u32 = i.parse().ok()?;
    let frac: u32 = format!("{f:0<3}").parse().ok()?;
    Some(whole * 1000 + frac)
}

fn endurance(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let o = Opts::parse(args, &["cycles", "material", "rate"], &[])?;
    let cycles = o.num("cycles", 100_000u32, 1, 10_000_000)?;
    let material = material(&o)?;
    // A progress bar on stderr when a person watches it (a terminal); nothing when
    // stderr goes to a file or a pipe.
    let mut bar = Progress::new("endurance", std::io::stderr().is_terminal());
    let r = crate::life::endurance_with_progress(cycles, hx_rate(&o)?, material, &mut |d, t| {
        bar.show(d, t)
    })
    .map_err(UsageError)?;
    bar.finish();
    let _ = writeln!(
        out,
        "endurance: {} cycles, {} cone(s), erases per sector {:?} (max {}; STM32F4 endurance 10000), {:.1} s",
        r.cycles_run,
        r.cones_used,
        r.erase_counts,
        r.erase_counts.iter().max().copied().unwrap_or(0),
        r.wall_time_s
    );
    Ok(())
}

fn accuracy(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let o = Opts::parse(args, &["plot"], &["json"])?;
    let r = crate::accuracy::run();
    if let Some(path) = o.get("plot") {
        crate::plot::accuracy(path.as_ref(), &r)?;
    }
    let plant = crate::accuracy::plant_study();
    print(
        out,
        &o,
        || crate::accuracy::json_with_plant(&r, &plant),
        || r.to_text() + &plant.to_text(),
    );
    Ok(())
}

fn serve(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let o = Opts::parse(
        args,
        &["tcp", "modbus-tcp", "scene", "speed", "rate", "for"],
        &["pty", "modbus-pty", "plc"],
    )?;
    let link = match (o.flag("pty"), o.get("tcp")) {
        (true, Some(_)) => return err("give --pty or --tcp, not both"),
        (_, Some(a)) => crate::serve::Link::Tcp(a.parse().map_err(|_| {
            UsageError(format!(
                "--tcp must be an address like 127.0.0.1:7000, got '{a}'"
            ))
        })?),
        _ => crate::serve::Link::Pty,
    };
    let modbus = match (o.flag("modbus-pty"), o.get("modbus-tcp")) {
        (true, Some(_)) => return err("give --modbus-pty or --modbus-tcp, not both"),
        (_, Some(a)) => Some(crate::serve::Link::Tcp(a.parse().map_err(|_| {
            UsageError(format!(
                "--modbus-tcp must be an address like 127.0.0.1:7001, got '{a}'"
            ))
        })?)),
        (true, None) => Some(crate::serve::Link::Pty),
        (false, None) => None,
    };
    let opts = crate::serve::ServeOptions {
        link,
        modbus,
        plc: o.flag("plc"),
        scene: o.get("scene").unwrap_or("nominal").to_string(),
        speed: o.num("speed", 1.0f64, 1e-3, 1e4)?,
        rate_sps: hx_rate(&o)?,
        duration_s: match o.get("for") {
            None => None,
            Some(_) => Some(o.num("for", 0.0f64, 0.0, 1e7)?),
        },
    };
    crate::serve::run(&opts, out).map_err(UsageError)
}

fn bench(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let o = Opts::parse(args, &["cycles", "rate"], &[])?;
    let cycles = o.num("cycles", 1_000u32, 1, 1_000_000)?;
    let rate_sps = hx_rate(&o)?;
    let r = crate::scene::run(
        "nominal",
        crate::scene::SceneOptions {
            cycles,
            seed: 1,
            adc: crate::rig::AdcMode::Word,
            ..crate::scene::SceneOptions::new(rate_sps)
        },
    )
    .map_err(UsageError)?;
    let ns_per_step = r.wall_time_s * 1e9 / r.control_steps.max(1) as f64;
    let _ = writeln!(
        out,
        "bench: {} nominal cycles at {} SPS: {} control steps, {:.1} s simulated in {:.3} s wall; {:.0} ns per control step (controller + simulated HAL); simulated/wall time ratio {:.0}x; faults {}",
        r.cycles_completed,
        rate_sps,
        r.control_steps,
        r.sim_time_s,
        r.wall_time_s,
        ns_per_step,
        r.sim_time_s / r.wall_time_s.max(1e-9),
        r.faults.len()
    );
    Ok(())
}

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

/// `--material NAME` (default ZQSn5-2), case-insensitive.
fn material(o: &Opts) -> Result<docking_logic::material::Material, UsageError> {
    use docking_logic::material::Material;
    match o.get("material") {
        None => Ok(Material::ZQSn5_2),
        Some(m) => Material::from_name(m).ok_or_else(|| {
            let names: Vec<_> = Material::ALL.iter().map(|m| m.name()).collect();
            UsageError(format!(
                "unknown material '{m}' (materials: {})",
                names.join(", ")
            ))
        }),
    }
}

/// Print a report as one JSON line with `--json`, else as text.
fn print(
    out: &mut dyn Write,
    o: &Opts,
    json: impl FnOnce() -> String,
    text: impl FnOnce() -> String,
) {
    let s = if o.flag("json") { json() } else { text() };
    let _ = writeln!(out, "{s}");
}

/// Largest profile rate, Hz (25 s × 100 kHz = 2.5 M rows).
pub const PROFILE_RATE_MAX_HZ: f64 = 100_000.0;

fn profile(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let valued: Vec<&str> = ["rate", "stroke", "plot"]
        .into_iter()
        .chain(profile_cmd::MODEL_OPTIONS)
        .collect();
    let o = Opts::parse(args, &valued, &[])?;
    let model = profile_cmd::model(&o)?;
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
    match (o.get("plot"), &model) {
        (Some(path), profile_cmd::Model::Plant(plant)) => {
            crate::plot::plant_profile(path.as_ref(), plant, rate, stroke)?
        }
        (Some(path), profile_cmd::Model::Eq7) => {
            crate::plot::eq7_profile(path.as_ref(), rate, stroke)?
        }
        (None, _) => {}
    }
    let mut buf = std::io::BufWriter::new(out);
    if let profile_cmd::Model::Plant(plant) = model {
        // A closed pipe (`| head`) is not an error of ours; lift-offs are noted on stderr.
        if let Ok(sum) = profile_cmd::write_plant_csv(&mut buf, &plant, rate, stroke) {
            let _ = buf.flush();
            if let Some(note) = sum.note() {
                eprintln!("hil-sim: {note}");
            }
        }
        return Ok(());
    }
    // A closed pipe (`| head`) is not an error of ours.
    let _ = profile_cmd::write_csv(&mut buf, rate, stroke).and_then(|_| buf.flush());
    Ok(())
}

/// `commission --model plant [plant options]`: the controller's tuning for that machine
/// as Rust source for the firmware's build (`DOCKING_TUNING=FILE`).
fn commission(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let valued: Vec<&str> = profile_cmd::MODEL_OPTIONS
        .into_iter()
        .chain(["vendor", "product"])
        .collect();
    let o = Opts::parse(args, &valued, &[])?;
    // Device identification's names (Modbus objects 0 and 4): the machine builder's.
    let name = |key: &str| -> Result<Option<&str>, UsageError> {
        match o.get(key) {
            Some(v)
                if v.is_empty()
                    || v.len() > 64
                    || !v.bytes().all(|b| (0x20..0x7F).contains(&b)) =>
            {
                err(format!(
                    "--{key} must be 1 to 64 printable ASCII characters, got '{v}'"
                ))
            }
            v => Ok(v),
        }
    };
    let (vendor, product) = (name("vendor")?, name("product")?);
    let profile_cmd::Model::Plant(plant) = profile_cmd::model(&o)? else {
        return err("commission needs --model plant (the paper's machine is the build's default)");
    };
    let p = *plant.params();
    let tuning = crate::machine::Tuning::for_plant(p).map_err(|e| UsageError(e.to_string()))?;
    let origin = format!(
        "m {} kg, µ1 {}, µ2 {}, γ {}°, θ0 {}°, v_model {} mm/s, µ spread ±{}",
        p.mass_kg,
        p.mu1,
        p.mu2,
        p.gamma_deg,
        p.theta0_deg,
        p.v_model_mm_s,
        crate::machine::MU_SPREAD
    );
    let mut source = tuning.to_rust(&origin);
    // The names, as lines of `apply` (a string literal in Rust's own escaping).
    let mut names = String::new();
    if let Some(v) = vendor {
        names += &format!("    cfg.identity.vendor = {v:?};\n");
    }
    if let Some(p) = product {
        names += &format!("    cfg.identity.product = {p:?};\n");
    }
    if let Some(end) = source.rfind("}\n") {
        source.insert_str(end, &names);
    }
    let _ = write!(out, "{source}");
    Ok(())
}

/// Each command's help (`hil-sim COMMAND --help`): what it does, then one option a line.
pub const COMMAND_HELP: [(&str, &str); 11] = [
    ("profile", "hil-sim profile [OPTIONS]: the nominal force against insertion depth (Eq. 7, or the plant model)
  --rate HZ                 sample rate of the printed profile
  --stroke insert|extract   which stroke (default insert)
  --plot FILE.svg           also draw it
  --model eq7|plant         the force model (default eq7)
  --mass-kg M --mu1 X --mu2 X --gamma-deg G --theta0-deg T --v-model MM_PER_S --t3-s S
                            the plant model's parameters (--model plant)"),
    ("scene", "hil-sim scene NAME [OPTIONS]: one scenario against the real controller; ends with a verdict
  NAME                      nominal overload spike disconnect saturation stuck bad-tare stall lock-stuck
                            dock-hold vehicle-pull estop estop-bounce heavy-default maintenance-lockout
  --cycles N                dockings to run (default 1)
  --rate 10|80              the HX711's rate, SPS (default 80)
  --seed S                  the noise seed (default 1)
  --json                    one JSON object instead of text
  --plot FILE.svg           force against depth, with the guard's envelope
  --model eq7|plant         the force model (plant options as for profile)
  --config default|matching the guard tuned by default or for the plant machine"),
    ("bench", "hil-sim bench [OPTIONS]: control-step speed on this host
  --cycles N                dockings to time
  --rate SPS                sample rate"),
    ("life", "hil-sim life --cycles N [OPTIONS]: a cone's life: the model's wear and the estimate from readings
  --cycles N                cycles to run (required)
  --material NAME           zqsn5-2 | qsn6-6-3 | cf-peek
  --at m1,m2,...            checkpoints to report (cycle numbers)
  --rate SPS                sample rate
  --readings FILE.csv       a technician's bore readings (cycle,bore_mm lines)
  --json                    one JSON object instead of text
  --plot FILE.svg           wear against cycles"),
    ("endurance", "hil-sim endurance --cycles N [OPTIONS]: flash erases over a long life
  --cycles N                cycles to run
  --material NAME           zqsn5-2 | qsn6-6-3 | cf-peek
  --rate SPS                sample rate"),
    ("accuracy", "hil-sim accuracy [OPTIONS]: the odometer's error against the exact integral
  --json                    one JSON object instead of text
  --plot FILE.svg           the error per phase"),
    ("commission", "hil-sim commission --model plant [OPTIONS]: Rust source of a machine's tuning (for DOCKING_TUNING)
  --model plant             required
  --vendor NAME             Modbus device identification's VendorName (1-64 printable ASCII)
  --product NAME            its ProductName
  (plant options as for profile)"),
    ("serve", "hil-sim serve [OPTIONS]: the simulator live, its console on a pty or TCP
  --pty | --tcp 127.0.0.1:PORT         the console's link (first stdout line: its address)
  --modbus-pty | --modbus-tcp 127.0.0.1:PORT
                            the Modbus RTU line (stdout line: modbus ADDRESS); no demo cycles
  --plc                     the PLC drives (stdin: dock on|off, estop open|close, plc); no demo cycles
  --scene NAME              disturbances of a scene
  --speed X                 machine time per wall time (default 1)
  --rate SPS                sample rate
  --for SECONDS             stop after this long"),
    ("plot-curve", "hil-sim plot-curve DUMP.json [OPTIONS]: a `curve --json` dump against its objects (SVG)
  --plot FILE.svg           the chart (required)
  --ref REF.json            the cone's reference (a `curve ref --json` dump), drawn beside it"),
    ("signature-study", "hil-sim signature-study [OPTIONS]: can the docking signature see wear? (the plant's worn bore, the firmware's figures)
  --dockings N              dockings a point (default 40)
  --rate 10|80              one sample rate (default both)
  --seed S                  the noise's and the frictions' seed (default 1)
  --json                    one JSON object"),
    ("odometer-reference", "hil-sim odometer-reference [--cycles N]: the odometer's integer workload (compared with QEMU in CI)
  --cycles N                cycles (default 300)"),
];

/// `hil-sim --help`: the commands, one a line.
fn overview() -> String {
    let mut s =
        String::from("usage: hil-sim COMMAND [OPTIONS]   (hil-sim COMMAND --help: its options)\n");
    for (_, h) in COMMAND_HELP {
        let first = h.lines().next().unwrap_or("");
        s += "  ";
        s += first.strip_prefix("hil-sim ").unwrap_or(first);
        s += "\n";
    }
    s
}

/// `hil-sim signature-study [--dockings N] [--rate 10|80] [--seed S] [--json]`.
fn signature_study(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let o = Opts::parse(args, &["dockings", "rate", "seed"], &["json"])?;
    let dockings = o.num("dockings", 40u32, 2, 10_000)?;
    let rates: Vec<u32> = match o.get("rate") {
        None => vec![10, 80],
        Some(_) => vec![hx_rate(&o)?],
    };
    let seed = o.num("seed", 1u64, 0, u64::MAX)?;
    let r = crate::sigstudy::run(dockings, &rates, seed);
    let text = if o.flag("json") {
        crate::sigstudy::to_json(&r, dockings)
    } else {
        crate::sigstudy::to_text(&r, dockings)
    };
    let _ = writeln!(out, "{text}");
    Ok(())
}

/// `hil-sim plot-curve DUMP.json [--ref REF.json] --plot FILE.svg`.
fn plot_curve(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let (file, rest) = match args.split_first() {
        Some((f, rest)) if !f.starts_with("--") => (f, rest),
        _ => return err("plot-curve needs a dump: hil-sim plot-curve DUMP.json --plot FILE.svg"),
    };
    let o = Opts::parse(rest, &["plot", "ref"], &[])?;
    let read = |p: &str| -> Result<crate::curvedump::CurveDump, UsageError> {
        let text = std::fs::read_to_string(p).map_err(|e| UsageError(format!("{p}: {e}")))?;
        crate::curvedump::CurveDump::parse(&text).map_err(|e| UsageError(format!("{p}: {e}")))
    };
    let dump = read(file)?;
    let reference = o.get("ref").map(read).transpose()?;
    let Some(path) = o.get("plot") else {
        return err("plot-curve needs --plot FILE.svg");
    };
    crate::plot::curve(path.as_ref(), &dump, reference.as_ref())?;
    let _ = writeln!(out, "wrote {path}");
    Ok(())
}

/// A one-line progress bar on stderr (`endurance  [#####.....]  52 %  5 200 000 / 10 000 000
/// cycles, 3 min left`), redrawn at most every 200 ms; nothing when `on` is false.
pub struct Progress {
    what: &'static str,
    on: bool,
    started: std::time::Instant,
    drawn: Option<std::time::Instant>,
}

impl Progress {
    /// A bar for `what`, drawn when `on`.
    pub fn new(what: &'static str, on: bool) -> Self {
        Self {
            what,
            on,
            started: std::time::Instant::now(),
            drawn: None,
        }
    }

    /// The line for `done` of `total`, `elapsed_s` in.
    pub fn line(&self, done: u32, total: u32, elapsed_s: f64) -> String {
        let frac = if total == 0 {
            1.0
        } else {
            f64::from(done.min(total)) / f64::from(total)
        };
        let filled = (frac * 30.0).round() as usize;
        let left = if done > 0 && frac < 1.0 {
            let s = elapsed_s * (1.0 - frac) / frac;
            if s >= 90.0 {
                format!(", {:.0} min left", s / 60.0)
            } else {
                format!(", {s:.0} s left")
            }
        } else {
            String::new()
        };
        format!(
            "{}  [{}{}]  {:3.0} %  {done} / {total} cycles{left}",
            self.what,
            "#".repeat(filled),
            ".".repeat(30 - filled.min(30)),
            frac * 100.0
        )
    }

    /// Redraw for `done` of `total` (throttled).
    pub fn show(&mut self, done: u32, total: u32) {
        if !self.on || self.drawn.is_some_and(|t| t.elapsed().as_millis() < 200) {
            return;
        }
        self.drawn = Some(std::time::Instant::now());
        let line = self.line(done, total, self.started.elapsed().as_secs_f64());
        eprint!("\r{line}\x1b[K");
    }

    /// Clear the bar.
    pub fn finish(&mut self) {
        if self.on && self.drawn.is_some() {
            eprint!("\r\x1b[K");
        }
    }
}

/// Run the command line `args` (without the program name), writing to `out`.
pub fn run(args: &[String], out: &mut dyn Write) -> Result<(), UsageError> {
    let Some((cmd, rest)) = args.split_first() else {
        return err(overview().trim_end());
    };
    if rest.iter().any(|a| a == "--help" || a == "-h") {
        if let Some((_, h)) = COMMAND_HELP.iter().find(|(c, _)| c == cmd) {
            let _ = writeln!(out, "{h}");
            return Ok(());
        }
    }
    match cmd.as_str() {
        "profile" => profile(rest, out),
        "scene" => scene(rest, out),
        "bench" => bench(rest, out),
        "life" => life(rest, out),
        "endurance" => endurance(rest, out),
        "accuracy" => accuracy(rest, out),
        "serve" => serve(rest, out),
        "commission" => commission(rest, out),
        "plot-curve" => plot_curve(rest, out),
        "signature-study" => signature_study(rest, out),
        // The odometer's integer workload, for comparison with the same code on a
        // Cortex-M4 under QEMU (.ci/run, qemu-check/).
        "odometer-reference" => {
            let o = Opts::parse(rest, &["cycles"], &[])?;
            let cycles = o.num("cycles", 300u32, 1, 1_000_000)?;
            let _ = writeln!(out, "{}", docking_logic::odometer::reference_run(cycles));
            Ok(())
        }
        "help" | "--help" | "-h" => {
            let _ = write!(out, "{}", overview());
            Ok(())
        }
        other => err(format!(
            "unknown command '{other}'\n{}",
            overview().trim_end()
        )),
    }
}
