//! `dockctl update FILE`: the firmware update a technician runs (docs/update.md).
//!
//! ```text
//!  1. FILE checked (image::check_file: the board's own checks, the size, the key)
//!  2. the console found; `version`: refused here while the board's image is on trial,
//!     or for the same or an older version (--force), or a file the board's key would
//!     not take; `status`, `wear` (the counters, to compare after)
//!  3. the PIN (--pin-file, DOCKCTL_PIN, or asked without echo); `maint <pin>` unless
//!     maintenance mode is on already
//!  4. `update`; YMODEM-1K (docking_logic::ymodem::Sender) with a progress bar
//!  5. the board's verdict: `ok: update verified …` or `error: update refused: …`
//!  6. the restart: its banner, then `version` until the new image has confirmed itself
//!  7. what happened: updated to X (the counters as before), refused (the board's
//!     reason), rolled back, or not confirmed
//! ```
//!
//! Ctrl-C at any point: a transfer is cancelled (CAN CAN: the board refuses the
//! partial image and keeps its own), maintenance mode the tool entered is left, echo
//! put back. Once the last block is sent the board has the file and nothing stops it:
//! Ctrl-C then waits for the verdict (a refusal is said, maintenance mode left) and
//! stops only the waiting through the restart, which itself ends maintenance mode. A line cut during the transfer: the board keeps its image and refuses the
//! partial one after 60 s of silence; run the tool again (it cancels a transfer the
//! board still waits in).

use std::path::PathBuf;
use std::time::{Duration, Instant};

use clap::Args;
use docking_logic::ymodem::{SendState, Sender, PACKET_MAX};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};

use crate::cli::{session, LineArgs};
use crate::console::{cancelled, Session};
use crate::image::{check_file, parse_version, version_text, FileInfo};
use crate::json::{quote, J};
use crate::link::{LinkError, Target};
use crate::{Ctx, Error};

/// `update`'s arguments.
#[derive(Args, Debug, Clone)]
pub struct UpdateArgs {
    /// The update file (tools/sign-image.sh writes target/update.dcs)
    pub file: PathBuf,
    /// Read the maintenance PIN from this file's first line (else DOCKCTL_PIN, else it
    /// is asked)
    #[arg(long, value_name = "FILE")]
    pub pin_file: Option<PathBuf>,
    /// Send it even when it is the version the board runs, an older one, or signed with
    /// a key the board's version says it does not take (the board checks it again)
    #[arg(long)]
    pub force: bool,
    /// The result as one JSON object on stdout
    #[arg(long)]
    pub json: bool,
    /// Seconds to wait for the board after its restart (the bootloader's swap: 4-22 s)
    #[arg(long, default_value_t = 120.0, value_name = "SECONDS")]
    pub restart_timeout: f64,
}

/// What the sender waits for an answer before it sends a packet again. The board's
/// receiver asks again by itself (NAK) after 3 s of silence, so this only matters when
/// that NAK is lost; it is long so that no block goes twice while the board holds an
/// ACK for a DFU page's erase (2 s at most on the board; 26 s of wall time was seen on
/// the virtual board on a loaded machine, where `sb`'s 10 s had a block sent three
/// times, the copies overrunning the board's receive ring).
const PACKET_TIMEOUT: Duration = Duration::from_secs(30);
/// Packets sent again in a row (time-outs) before the transfer is given up.
const RETRIES_MAX: u32 = 3;
/// Packets sent again in all before the transfer is given up.
const RETRIES_TOTAL: u32 = 30;
/// The board's verdict after the last block: the pages the file did not reach erased
/// (one 128 KiB page: 2 s at most), the SHA-512 and the signature (about a second).
const VERDICT_TIMEOUT: Duration = Duration::from_secs(60);
/// A second NAK of a block is answered only after the sender has been this quiet (the
/// receiver's NAK after its 3 s of silence, when it has dropped a torn packet).
const RESYNC_QUIET: Duration = Duration::from_millis(2_500);
/// How long the new image may take to confirm itself once it answers (it confirms at
/// rest once the load cell has answered twice: about 0.6 s).
const CONFIRM_TIMEOUT: Duration = Duration::from_secs(30);

/// The transfer's figures.
#[derive(Clone, Copy, Debug, Default)]
pub struct Transfer {
    /// Bytes of the file.
    pub bytes: u64,
    /// From the first block sent to the last ACK, s.
    pub seconds: f64,
    /// Blocks sent again.
    pub retries: u32,
}

impl Transfer {
    /// File bytes per second.
    pub fn rate(&self) -> f64 {
        self.bytes as f64 / self.seconds.max(1e-9)
    }
}

/// What happened, for the last line and `--json`.
struct Report<'a> {
    args: &'a UpdateArgs,
    file: Option<FileInfo>,
    from: Option<String>,
    transfer: Option<Transfer>,
    restart_s: Option<f64>,
    line_bps: Option<f64>,
}

impl Report<'_> {
    fn json(&self, result: &str, detail: &str, to: Option<&str>) -> String {
        let opt = |v: Option<&str>| v.map_or("null".to_string(), quote);
        let num = |v: Option<f64>, d: usize| v.map_or("null".to_string(), |x| format!("{x:.d$}"));
        format!(
            "{{\"result\":{},\"detail\":{},\"file\":{},\"file_version\":{},\"from\":{},\"to\":{},\"bytes\":{},\"transfer_s\":{},\"bytes_per_s\":{},\"line_bytes_per_s\":{},\"retries\":{},\"restart_s\":{},\"tool\":{}}}",
            quote(result),
            quote(detail),
            quote(&self.args.file.display().to_string()),
            opt(self.file.as_ref().map(|f| version_text(f.version)).as_deref()),
            opt(self.from.as_deref()),
            opt(to),
            self.transfer.map_or("null".into(), |t| t.bytes.to_string()),
            num(self.transfer.map(|t| t.seconds), 2),
            num(self.transfer.map(|t| t.rate()), 0),
            num(self.line_bps, 0),
            self.transfer.map_or("null".into(), |t| t.retries.to_string()),
            num(self.restart_s, 1),
            quote(env!("CARGO_PKG_VERSION")),
        )
    }
}

/// `dockctl update`.
pub fn run(line: &LineArgs, ctx: &mut Ctx, args: &UpdateArgs) -> Result<i32, Error> {
    let mut rep = Report {
        args,
        file: None,
        from: None,
        transfer: None,
        restart_s: None,
        line_bps: None,
    };
    let r = update(line, ctx, args, &mut rep);
    if args.json {
        let (result, detail, to) = match &r {
            Ok(to) => ("updated", String::new(), Some(to.clone())),
            Err(Error::NotTaken(d)) => ("not_taken", d.clone(), None),
            Err(Error::Interrupted) => ("interrupted", String::new(), None),
            Err(Error::Refused(d)) | Err(Error::Pin(d)) | Err(Error::Board(d)) => {
                ("refused", d.clone(), None)
            }
            Err(e) => ("failed", e.to_string(), None),
        };
        let _ = writeln!(ctx.out, "{}", rep.json(result, &detail, to.as_deref()));
    }
    r.map(|_| 0)
}

/// One step said: `what` in a column of its own, then `text`; on a terminal wrapped at
/// [`WRAP`] columns under the text's start (a log or a pipe gets one line a step).
fn say(ctx: &mut Ctx, what: &str, text: &str) {
    let line = format!("{what:<9}{text}");
    let shown = if ctx.err_tty {
        wrap(&line, WRAP, 9)
    } else {
        line
    };
    let _ = writeln!(ctx.err, "{shown}");
    let _ = ctx.err.flush();
}

/// Where a terminal's lines are wrapped, columns.
const WRAP: usize = 96;

/// `line` wrapped at spaces within `width` columns, the next lines indented by `indent`.
fn wrap(line: &str, width: usize, indent: usize) -> String {
    let mut out = String::new();
    let mut col = 0;
    for (i, word) in line.split(' ').enumerate() {
        let w = word.chars().count();
        if i > 0 && col + 1 + w > width && col > indent {
            out.push('\n');
            out.push_str(&" ".repeat(indent));
            col = indent;
        } else if i > 0 {
            out.push(' ');
            col += 1;
        }
        out.push_str(word);
        col += w;
    }
    out
}

fn update(
    line: &LineArgs,
    ctx: &mut Ctx,
    args: &UpdateArgs,
    rep: &mut Report,
) -> Result<String, Error> {
    // 1. The file, before anything is sent.
    let bytes = std::fs::read(&args.file)
        .map_err(|e| Error::File(format!("cannot read {}: {e}", args.file.display())))?;
    let info =
        check_file(&bytes).map_err(|e| Error::File(format!("{}: {e}", args.file.display())))?;
    let file_version = version_text(info.version);
    rep.file = Some(info.clone());
    say(
        ctx,
        "file",
        &format!(
            "{}: version {file_version}{}, layout {}, {} B of image ({:.1} % of the {} B an update carries){}",
            args.file.display(),
            if info.stamped { "" } else { " (the build's, not stamped)" },
            info.layout.name(),
            info.image_len,
            info.share_pct(),
            update_layout::layout::UPDATE_IMAGE_MAX,
            match (info.signed_with_test_key, info.test_key) {
                (true, true) => "; signed with the TEST KEY, and trusts it for its own updates: for a test bench only",
                (true, false) => "; signed with the TEST KEY",
                (false, true) => "; its image trusts the TEST KEY for its own updates",
                (false, false) => "",
            }
        ),
    );
    // 2. The board.
    let mut s = session(line, ctx)?;
    for n in std::mem::take(&mut s.notes) {
        say(ctx, "note", &n);
    }
    rep.line_bps = match s_target(line) {
        Some(Target::Serial { baud, .. }) => Some(f64::from(baud) / 10.0),
        _ => None,
    };
    let v = s.version.clone();
    let running = v.text("version").to_string();
    rep.from = Some(running.clone());
    let board_test_key = v.get("test_key").and_then(J::as_bool);
    say(
        ctx,
        "board",
        &format!(
            "docking-controller {running}{} on {}",
            if board_test_key == Some(true) {
                " (test key)"
            } else {
                ""
            },
            s.link_name()
        ),
    );
    match v.text("trial") {
        "" | "no" => {}
        _ => {
            return Err(Error::Refused(format!(
                "the board's image runs on trial ({}); nothing was sent",
                v.text("trial_advice")
            )))
        }
    }
    if !args.force {
        if let Some(rv) = parse_version(&running) {
            if info.version == rv {
                return Err(Error::Refused(format!(
                    "the board runs {running} already (--force sends it anyway); nothing was sent"
                )));
            }
            if info.version < rv {
                return Err(Error::Refused(format!(
                    "{file_version} is older than the board's {running} (--force to go back); nothing was sent"
                )));
            }
        }
        match (board_test_key, info.signed_with_test_key) {
            (Some(true), false) => return Err(Error::Refused(
                "the board takes updates signed with the test key (its version says so) and this file is signed with another: it would refuse it; nothing was sent".into(),
            )),
            (Some(false), true) => return Err(Error::Refused(
                "the board takes updates signed with its integrator's key and this file is signed with the test key: it would refuse it; nothing was sent".into(),
            )),
            _ => {}
        }
    }
    let status = s.json("status")?;
    let before = s.json("wear")?;
    // 3. Maintenance mode.
    if status.get("maintenance").and_then(J::as_bool) == Some(true) {
        say(ctx, "maint", "maintenance mode is on already (left on)");
    } else {
        let pin = crate::pin::get(args.pin_file.as_deref(), ctx.in_tty, &ctx.cancel)?;
        s.enter_maintenance(&pin)?;
        say(
            ctx,
            "maint",
            "maintenance mode entered (left again at the end)",
        );
    }
    // 4. `update`, then the file.
    let r = s.request("update")?;
    if let Some(e) = r.strip_prefix("error: ") {
        return Err(Error::Refused(format!("the board says: {e}")));
    }
    if !r.starts_with("ok: update") {
        return Err(Error::Protocol(format!("`update` answered {r:?}")));
    }
    s.transfer_open = true;
    let name = args
        .file
        .file_name()
        .map_or("update.dcs".into(), |n| n.to_string_lossy().into_owned());
    let sent = send(&mut s, ctx, &bytes, &name, &args.file.display().to_string());
    // Over, whichever way (a cancel was answered, or the line is gone).
    s.transfer_open = matches!(sent, Err(Error::NoAnswer(_)));
    let t = sent?;
    rep.transfer = Some(t);
    let kib = |b: f64| b / 1024.0;
    say(
        ctx,
        "sent",
        &format!(
            "{} B in {:.1} s: {:.1} KiB/s{}{}",
            t.bytes,
            t.seconds,
            kib(t.rate()),
            match rep.line_bps {
                Some(l) => format!(
                    ", {:.0} % of what the line carries ({l:.0} B/s)",
                    100.0 * t.rate() / l
                ),
                None => String::new(),
            },
            if t.retries > 0 {
                format!(", {} blocks sent again", t.retries)
            } else {
                String::new()
            }
        ),
    );
    // 5. The board's verdict. The board has the whole file: Ctrl-C stops nothing on it
    // now, so the first one is held until the verdict (a second of the board's checks;
    // a second Ctrl-C leaves at once): a refusal is then said, and maintenance mode left.
    let pressed = std::mem::take(&mut s.cancel);
    let verdict = s.reply_until(Instant::now() + VERDICT_TIMEOUT);
    let held = cancelled(&s.cancel);
    s.cancel = pressed;
    if held {
        s.cancel.store(true, std::sync::atomic::Ordering::SeqCst);
    }
    let verdict = match verdict {
        Ok(Some(l)) => l,
        Ok(None) => {
            return Err(Error::NoAnswer(format!(
                "the board said nothing within {} s of the file's end",
                VERDICT_TIMEOUT.as_secs()
            )))
        }
        Err(e) => return Err(e),
    };
    if let Some(why) = crate::console::refusal(&verdict) {
        return Err(Error::Refused(format!(
            "the board says: {why}; it keeps running {running}"
        )));
    }
    if !verdict.starts_with("ok: update verified") {
        return Err(Error::Protocol(format!("after the file: {verdict:?}")));
    }
    say(
        ctx,
        "verified",
        verdict.trim_start_matches("ok: update verified: "),
    );
    // The restart ends maintenance mode and turns echo on: nothing to put back on a
    // board that is restarting (a `maint exit` now would go to the bootloader).
    s.board_restarts();
    // 6. The restart. Ctrl-C from here on stops the waiting, not the update: the
    // board has verified the image and restarts into it.
    let waited = |e: Error, ctx: &mut Ctx| {
        if matches!(e, Error::Interrupted) {
            say(
                ctx,
                "stopped",
                &format!("waiting only: the board verified {file_version} and restarts into it; `dockctl version` says how it stands"),
            );
        }
        e
    };
    if cancelled(&s.cancel) {
        return Err(waited(Error::Interrupted, ctx));
    }
    let t0 = Instant::now();
    let limit = Duration::from_secs_f64(args.restart_timeout.clamp(10.0, 600.0));
    say(
        ctx,
        "restart",
        "the board restarts; the bootloader swaps the new image in (4-22 s)",
    );
    let banner = wait_banner(&mut s, t0 + limit).map_err(|e| waited(e, ctx))?;
    let back_s = t0.elapsed().as_secs_f64();
    say(ctx, "back", &format!("after {back_s:.1} s: {banner}"));
    s.after_restart().map_err(|e| waited(e, ctx))?;
    let (now, confirmed) = confirmation(&mut s, ctx, Instant::now() + CONFIRM_TIMEOUT.min(limit))
        .map_err(|e| waited(e, ctx))?;
    rep.restart_s = Some(t0.elapsed().as_secs_f64());
    let now_running = now.text("version").to_string();
    // 7. What happened.
    if now.get("rolled_back").and_then(J::as_bool) == Some(true) && now_running == running {
        return Err(Error::NotTaken(format!(
            "rolled back: {file_version} did not confirm itself and the bootloader put {running} back; the board runs {running}"
        )));
    }
    if now_running != file_version {
        return Err(Error::NotTaken(format!(
            "the board runs {now_running} after the restart, not {file_version}"
        )));
    }
    if !confirmed {
        return Err(Error::NotTaken(format!(
            "{file_version} runs on trial and has not confirmed itself ({}): a reset rolls it back to {running}",
            now.text("trial_advice")
        )));
    }
    let after = s.json("wear")?;
    let changed = counters_changed(&before, &after);
    s.close();
    let counters = if changed.is_empty() {
        let f = |k: &str| format!("{k}={}", before.get(k).map_or("?".into(), J::plain));
        format!(
            "the counters as before ({} {} {} {} {})",
            f("lifetime_cycles"),
            f("cone"),
            f("cycles"),
            f("wear_mm"),
            f("readings"),
        )
    } else {
        format!("counters that changed meanwhile: {}", changed.join(", "))
    };
    let done = format!(
        "updated to {file_version} (from {running}, previous={}); {counters}",
        now.get("previous").map_or("?".into(), J::plain)
    );
    let _ = writeln!(
        ctx.err,
        "{}",
        if ctx.err_tty {
            wrap(&done, WRAP, 11)
        } else {
            done
        }
    );
    Ok(file_version)
}

fn s_target(line: &LineArgs) -> Option<Target> {
    crate::cli::target(line).ok()
}

/// The wear counters that differ between two `wear` reports.
fn counters_changed(before: &J, after: &J) -> Vec<String> {
    // The persisted ones (the lifetime peak force is left out: at rest it follows the
    // load cell's noise, kept in RAM until the next record).
    const KEPT: [&str; 10] = [
        "cone",
        "cycles",
        "load_distance_nmm",
        "wear_mm",
        "lifetime_cycles",
        "cones_installed",
        "overload_events",
        "faults",
        "readings",
        "wear_measured_mm",
    ];
    KEPT.iter()
        .filter(|k| before.get(k) != after.get(k))
        .map(|k| {
            format!(
                "{k} {} -> {}",
                before.get(k).map_or("?".into(), J::plain),
                after.get(k).map_or("?".into(), J::plain)
            )
        })
        .collect()
}

/// Wait for the board's boot banner.
fn wait_banner(s: &mut Session, deadline: Instant) -> Result<String, Error> {
    loop {
        match s.reply_until(deadline) {
            Err(Error::Restarted(b)) => return Ok(b),
            Ok(Some(_)) => continue,
            Ok(None) => {
                return Err(Error::NotTaken(
                    "the board did not come back after its restart (no boot banner): check it with `dockctl version`; if it never answers, it needs a probe"
                        .into(),
                ))
            }
            Err(e) => return Err(e),
        }
    }
}

/// `version` until the running image is confirmed (or rolled back); the last report
/// and whether it is confirmed.
fn confirmation(s: &mut Session, ctx: &mut Ctx, deadline: Instant) -> Result<(J, bool), Error> {
    let mut said = false;
    loop {
        let v = match s.json("version") {
            Ok(v) => v,
            Err(Error::Restarted(b)) => {
                say(ctx, "back", &format!("it restarted again: {b}"));
                s.after_restart()?;
                continue;
            }
            Err(e) => return Err(e),
        };
        match v.text("trial") {
            "" | "no" => return Ok((v, true)),
            "failed" => return Ok((v, false)),
            _ if Instant::now() >= deadline => return Ok((v, false)),
            _ => {
                if !said {
                    say(
                        ctx,
                        "trial",
                        &format!(
                            "{} runs on trial; waiting for it to confirm itself",
                            v.text("version")
                        ),
                    );
                    said = true;
                }
                std::thread::sleep(Duration::from_millis(300));
            }
        }
    }
}

/// How the progress is shown.
enum Progress {
    Bar(ProgressBar),
    /// Not a terminal: a line at every quarter.
    Lines {
        total: u64,
        next: u64,
    },
}

impl Progress {
    fn new(ctx: &Ctx, total: u64) -> Progress {
        if ctx.err_tty {
            let bar =
                ProgressBar::with_draw_target(Some(total), ProgressDrawTarget::stderr_with_hz(8));
            bar.set_style(
                ProgressStyle::with_template(
                    "sending  [{wide_bar}] {bytes:>9}/{total_bytes}  {binary_bytes_per_sec:>11}  {eta} left",
                )
                .unwrap_or_else(|_| ProgressStyle::default_bar())
                .progress_chars("=> "),
            );
            Progress::Bar(bar)
        } else {
            Progress::Lines {
                total,
                next: total / 4,
            }
        }
    }

    fn set(&mut self, ctx: &mut Ctx, done: u64) {
        match self {
            Progress::Bar(b) => b.set_position(done),
            Progress::Lines { total, next } => {
                if done >= *next && *next > 0 && done < *total {
                    let _ = writeln!(
                        ctx.err,
                        "sending  {:>3} % ({done} of {total} B)",
                        done * 100 / (*total).max(1)
                    );
                    *next = (done / (*total / 4).max(1) + 1) * (*total / 4).max(1);
                }
            }
        }
    }

    fn finish(&self) {
        if let Progress::Bar(b) = self {
            b.finish_and_clear();
        }
    }
}

/// Send `file` by YMODEM-1K to a board whose receiver waits; the figures.
pub fn send(
    s: &mut Session,
    ctx: &mut Ctx,
    file: &[u8],
    name: &str,
    path: &str,
) -> Result<Transfer, Error> {
    let mut tx = Sender::new(name, file.len() as u32);
    let mut out = [0u8; PACKET_MAX];
    let mut progress = Progress::new(ctx, file.len() as u64);
    let mut heard = Instant::now();
    let mut started: Option<Instant> = None;
    let mut in_a_row = 0u32;
    // NAKs of one block in a row: the second and later wait for the receiver to have
    // been quiet (its own NAK after 3 s of silence, when it has thrown away what it
    // held): a packet it took a byte too many or too few of would otherwise be misread
    // the same way at every repeat, its tail starting another packet.
    let mut naks = 0u32;
    let mut sent_at = Instant::now();
    let result = loop {
        if cancelled(&s.cancel) {
            break Err(cancel_sending(s, &mut tx, ctx, &mut progress));
        }
        let b = match s.byte_until(Instant::now() + Duration::from_millis(100)) {
            Ok(b) => b,
            Err(Error::Interrupted) => continue,
            Err(Error::Link(LinkError::Cut(why))) => {
                progress.finish();
                let done = tx.acknowledged();
                break Err(Error::Cut(format!(
                    "the line was cut during the transfer ({why}) at {} % ({done} of {} B): the board keeps its image and refuses the partial one after 60 s of silence; run `dockctl update {}` again",
                    u64::from(done) * 100 / (file.len() as u64).max(1),
                    file.len(),
                    path
                )));
            }
            Err(e) => break Err(e),
        };
        let n = match b {
            Some(docking_logic::ymodem::NAK)
                if naks >= 1
                    && matches!(tx.state(), SendState::Block(_))
                    && sent_at.elapsed() < RESYNC_QUIET =>
            {
                heard = Instant::now();
                naks += 1;
                0 // not answered: the receiver's own NAK after a quiet line is
            }
            Some(b) => {
                heard = Instant::now();
                in_a_row = 0;
                naks = if b == docking_logic::ymodem::NAK {
                    naks + 1
                } else {
                    0
                };
                tx.on_byte(b, file, &mut out)
            }
            None if heard.elapsed() >= PACKET_TIMEOUT && tx.state() != SendState::Start => {
                in_a_row += 1;
                heard = Instant::now();
                if in_a_row > RETRIES_MAX {
                    let _ = s.cancel_transfer();
                    progress.finish();
                    break Err(Error::NoAnswer(format!(
                        "the board stopped answering the transfer at {} of {} B ({} packets sent again, {} s apart): cancelled; run it again",
                        tx.acknowledged(),
                        file.len(),
                        RETRIES_MAX,
                        PACKET_TIMEOUT.as_secs()
                    )));
                }
                tx.on_timeout(file, &mut out)
            }
            None if heard.elapsed() >= 2 * PACKET_TIMEOUT => {
                progress.finish();
                break Err(Error::NoAnswer(format!(
                    "the board's receiver never asked for the file ({} s without its 'C')",
                    2 * PACKET_TIMEOUT.as_secs()
                )));
            }
            None => 0,
        };
        if tx.retries() > RETRIES_TOTAL {
            let _ = s.cancel_transfer();
            progress.finish();
            break Err(Error::NoAnswer(format!(
                "the board asked for blocks again {} times (CRC errors: a noisy line, or one that loses bytes): cancelled at {} of {} B; check the cable and run it again",
                tx.retries(),
                tx.acknowledged(),
                file.len()
            )));
        }
        if n > 0 {
            if started.is_none() && matches!(tx.state(), SendState::Block(_)) {
                started = Some(Instant::now());
            }
            s.send_raw(&out[..n])?;
            sent_at = Instant::now();
        }
        progress.set(ctx, u64::from(tx.acknowledged()));
        match tx.state() {
            SendState::Done => {
                progress.finish();
                break Ok(Transfer {
                    bytes: file.len() as u64,
                    seconds: started.map_or(0.0, |t| t.elapsed().as_secs_f64()),
                    retries: tx.retries(),
                });
            }
            SendState::Cancelled => {
                progress.finish();
                // The board cancelled: its reason follows once the line is quiet.
                let why = match s.reply_until(Instant::now() + Duration::from_secs(15)) {
                    Ok(Some(l)) => crate::console::refusal(&l).unwrap_or(&l).to_string(),
                    _ => "it cancelled the transfer".into(),
                };
                break Err(Error::Refused(format!(
                    "the board says: {why}; it keeps running its image"
                )));
            }
            _ => {}
        }
    };
    result
}

/// Ctrl-C during the transfer: CAN CAN, the board's refusal.
fn cancel_sending(
    s: &mut Session,
    tx: &mut Sender,
    ctx: &mut Ctx,
    progress: &mut Progress,
) -> Error {
    progress.finish();
    let mut out = [0u8; PACKET_MAX];
    let n = tx.cancel(&mut out);
    let _ = s.send_raw(&out[..n]);
    let saved = std::mem::replace(&mut s.cancel, std::sync::Arc::new(Default::default()));
    let why = s.cancel_transfer();
    s.cancel = saved;
    match why {
        Ok(Some(why)) => say(
            ctx,
            "stopped",
            &format!("the transfer was cancelled; the board refused the partial image ({why}) and keeps its own"),
        ),
        _ => say(
            ctx,
            "stopped",
            "the transfer was cancelled (the board's refusal was not seen: it gives up after 60 s of silence and keeps its image)",
        ),
    }
    Error::Interrupted
}

#[cfg(test)]
mod tests {
    use super::wrap;

    #[test]
    fn a_step_is_wrapped_under_its_text() {
        let w = wrap(
            "file     target/update.dcs: version 0.1.1, layout C, 104808 B of image",
            40,
            9,
        );
        assert_eq!(
            w,
            "file     target/update.dcs: version\n         0.1.1, layout C, 104808 B of\n         image"
        );
        assert!(w.lines().all(|l| l.chars().count() <= 40));
        assert_eq!(wrap("short", 40, 9), "short");
    }
}
