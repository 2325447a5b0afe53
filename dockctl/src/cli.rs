//! The command line.

use std::path::PathBuf;
use std::time::Duration;

use clap::{Args, Parser, Subcommand};

use crate::console::Session;
use crate::link::{Link, LinkError, Target};
use crate::{Ctx, Error};

/// The technician's tool for the docking controller: read, export and update a board
/// over its console.
#[derive(Parser, Debug)]
#[command(
    name = "dockctl",
    version,
    after_help = "The line: --port /dev/ttyUSB0 (a USB-serial adapter on the board's console, USART2; \
the simulators' ptys too) or --tcp 127.0.0.1:PORT (hil-sim serve, vboard serve).\n\
Exit status: 0 done; 1 failed or refused (nothing changed on the board); 2 a wrong command line; \
3 an update that did not take (rolled back, or not confirmed); 130 Ctrl-C."
)]
pub struct Cli {
    #[command(flatten)]
    pub line: LineArgs,
    #[command(subcommand)]
    pub command: Cmd,
}

/// Where the board is.
#[derive(Args, Debug, Clone)]
pub struct LineArgs {
    /// The serial port the board's console is on (e.g. /dev/ttyUSB0)
    #[arg(
        long,
        global = true,
        value_name = "PATH",
        conflicts_with = "tcp",
        env = "DOCKCTL_PORT"
    )]
    pub port: Option<String>,
    /// The port's baud rate (the console runs at 115200 8N1)
    #[arg(long, global = true, default_value_t = 115_200)]
    pub baud: u32,
    /// A TCP address instead (hil-sim serve --tcp, vboard serve --tcp)
    #[arg(long, global = true, value_name = "HOST:PORT")]
    pub tcp: Option<String>,
    /// Seconds a reply may take
    #[arg(long, global = true, default_value_t = 5.0, value_name = "SECONDS")]
    pub timeout: f64,
}

/// How a report is printed.
#[derive(Args, Debug, Clone, Copy)]
pub struct Format {
    /// The board's JSON, one line
    #[arg(long, conflicts_with = "csv")]
    pub json: bool,
    /// CSV (a header line, then the rows)
    #[arg(long)]
    pub csv: bool,
    /// CSV without its header line (to append to a file)
    #[arg(long, requires = "csv")]
    pub no_header: bool,
}

#[derive(Subcommand, Debug)]
pub enum Cmd {
    /// The machine now: state, phase, force, position, cycles, fault, the PLC's lines
    Status(Format),
    /// The cone's wear: the odometer, the estimate and its band, remaining life
    Wear(Format),
    /// The last N completed cycles (1-100, default 10)
    History {
        /// How many
        #[arg(default_value_t = 10, value_parser = clap::value_parser!(u32).range(1..=100))]
        n: u32,
        #[command(flatten)]
        format: Format,
    },
    /// Faults: the active one, counts, resets by cause, the last crash, the last 16
    Faults(Format),
    /// The current cone's micrometer readings
    Measurements(Format),
    /// The running firmware: its version, the key it trusts, the image it replaced,
    /// a rollback, the trial after an update
    Version {
        /// The board's JSON, one line
        #[arg(long)]
        json: bool,
    },
    /// Everything a maintenance record needs from one machine, in one JSON file
    /// (`-`: stdout), stamped with the time and the tool's version
    Export {
        /// Where to write it
        file: PathBuf,
    },
    /// A live status line until Ctrl-C (one JSON line per reading when piped)
    Watch {
        /// Milliseconds between readings
        #[arg(long, default_value_t = 250, value_parser = clap::value_parser!(u64).range(100..=60_000))]
        interval_ms: u64,
    },
    /// Update the firmware: check FILE, maintenance mode, send it by YMODEM-1K, wait
    /// through the restart, say what happened
    Update(crate::update::UpdateArgs),
    /// A stroke's force curve as SVG (not yet: `export` carries the board's curves, and
    /// `hil-sim plot-curve` draws one)
    Curve {
        /// Where the SVG would go
        file: Option<PathBuf>,
    },
    /// The serial ports of this machine (where to find the adapter)
    Ports,
}

/// Open the line the arguments name and find the console.
pub fn session(line: &LineArgs, ctx: &Ctx) -> Result<Session, Error> {
    let target = target(line)?;
    let timeout = timeout(line)?;
    // A simulator's TCP console serves one terminal at a time and lets a closed one
    // go half a second after its last byte: a command run right after another may find
    // it busy for that long.
    let mut tries = 0;
    loop {
        let link = Link::open(&target).map_err(Error::Link)?;
        match Session::connect(link, ctx.cancel.clone(), timeout) {
            Err(Error::Link(LinkError::Open(e)) | Error::Link(LinkError::Cut(e)))
                if matches!(target, Target::Tcp(_))
                    && tries < 10
                    && !crate::console::cancelled(&ctx.cancel) =>
            {
                tries += 1;
                std::thread::sleep(Duration::from_millis(300));
                if tries == 10 {
                    let link = Link::open(&target).map_err(Error::Link)?;
                    return Session::connect(link, ctx.cancel.clone(), timeout)
                        .map_err(|_| Error::Link(LinkError::Open(e)));
                }
            }
            r => return r,
        }
    }
}

/// The target the arguments name.
pub fn target(line: &LineArgs) -> Result<Target, Error> {
    match (&line.port, &line.tcp) {
        (Some(p), _) => Ok(Target::Serial {
            path: p.clone(),
            baud: line.baud,
        }),
        (None, Some(t)) => Ok(Target::Tcp(t.clone())),
        (None, None) => {
            let ports = crate::link::serial_ports();
            Err(Error::Usage(if ports.is_empty() {
                "where is the board? give --port /dev/ttyUSB0 (no serial port is plugged in here) or --tcp 127.0.0.1:PORT".into()
            } else {
                format!(
                    "where is the board? give --port PATH (serial ports here: {}) or --tcp 127.0.0.1:PORT",
                    ports.join(", ")
                )
            }))
        }
    }
}

fn timeout(line: &LineArgs) -> Result<Duration, Error> {
    if line.timeout.is_finite() && line.timeout > 0.0 && line.timeout <= 600.0 {
        Ok(Duration::from_secs_f64(line.timeout))
    } else {
        Err(Error::Usage(format!(
            "--timeout must be 0-600 seconds, got {}",
            line.timeout
        )))
    }
}

/// Run the command; its exit status.
pub fn dispatch(cli: &Cli, ctx: &mut Ctx) -> Result<i32, Error> {
    use crate::reports as r;
    match &cli.command {
        Cmd::Ports => {
            let ports = crate::link::serial_ports();
            if ports.is_empty() {
                let _ = writeln!(ctx.out, "no serial port here (is the USB adapter plugged in?)");
            }
            for p in ports {
                let _ = writeln!(ctx.out, "{p}");
            }
            Ok(0)
        }
        Cmd::Curve { .. } => Err(Error::NotYet(
            "curve: not yet in dockctl: `dockctl export` carries the board's docking signatures (`curve --json` on the console), and `hil-sim plot-curve` draws one".into(),
        )),
        Cmd::Status(f) => r::report(&cli.line, ctx, "status", *f),
        Cmd::Wear(f) => r::report(&cli.line, ctx, "wear", *f),
        Cmd::Faults(f) => r::report(&cli.line, ctx, "faults", *f),
        Cmd::Measurements(f) => r::report(&cli.line, ctx, "measurements", *f),
        Cmd::History { n, format } => r::report(&cli.line, ctx, &format!("history {n}"), *format),
        Cmd::Version { json } => r::version(&cli.line, ctx, *json),
        Cmd::Export { file } => r::export(&cli.line, ctx, file),
        Cmd::Watch { interval_ms } => r::watch(&cli.line, ctx, Duration::from_millis(*interval_ms)),
        Cmd::Update(args) => crate::update::run(&cli.line, ctx, args),
    }
}
