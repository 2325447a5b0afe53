//! The field update on the board (issue 21): the release image receives a signed image
//! over its console by YMODEM-1K (the in-process sender, [`hil_sim::update::YmodemSender`],
//! answer by answer as lrzsz's `sb -k`), verifies it and restarts; the bootloader swaps
//! it in; the new image confirms itself. The bootloader and the application are the
//! unmodified release builds.
//!
//! The new image is the release image with another version stamped into its header and
//! signed (as `tools/sign-image.sh --version` does, [`hil_sim::update::signed_file`]):
//! one build gives the old and the new version.
//!
//! | scene | what is checked |
//! |---|---|
//! | `update` | old → new over the console: the new version runs, every odometer counter and reading as before, READY low and a DOCK edge refused during the update, the odometer's sectors never erased |
//! | `update-bad` | a corrupted (a flipped byte), a truncated, an unsigned and a wrongly signed file: each refused in one line, STATE and ACTIVE unchanged, the old version still runs |
//! | `update-rollback` | an image that never confirms (and never feeds the watchdog) is swapped in, reset by the watchdog and rolled back; the old image reports the rollback and its counters |
//! | `update-cut --cut transfer\|swap\|boot` | the power cut at a seeded instant of the transfer, of the bootloader's swap, or of the new image's first boot: a whole image (old or new, as the instant allows) boots, no counter lost, nothing moves |

use hil_sim::flash::SharedFlash;
use hil_sim::update::{other_key_seed, signed_file, stamp, test_key_seed, YmodemSender};
use update_layout::header::Version;
use update_layout::layout::{ACTIVE_BASE, ACTIVE_LEN, FLASH_BASE, ODOMETER_BASE, STATE_BASE};

use crate::cpu::Halt;
use crate::image::Image;
use crate::scene::{json_field, Options, Session, PS_PER_MS};
use crate::time::PS_PER_S;

/// The version the new image is stamped with.
pub const NEW_VERSION: Version = Version {
    major: 0,
    minor: 1,
    patch: 1,
    build: 0,
};

/// Checks of a scene: (name, passed, detail).
pub type Checks = Vec<(String, bool, String)>;

/// The release image's application bytes as `llvm-objcopy -O binary` writes them (the
/// signing tool's input): from ACTIVE's first byte to the last loaded one, a gap
/// between two segments (alignment) zero (a probe leaves it erased, 0xFF).
pub fn app_bytes(img: &Image) -> Vec<u8> {
    use object::read::elf::{FileHeader, ProgramHeader};
    let start = (ACTIVE_BASE - FLASH_BASE) as usize;
    let mut v = img.flash[start..img.flash_used as usize].to_vec();
    let mut loaded = vec![false; v.len()];
    if let Ok(f) = object::read::elf::ElfFile32::<object::Endianness>::parse(&*img.elf) {
        let e = f.endian();
        for ph in f.elf_header().program_headers(e, &*img.elf).unwrap_or(&[]) {
            let (pa, n) = (ph.p_paddr(e) as usize, ph.p_filesz(e) as usize);
            let Some(off) = pa.checked_sub(ACTIVE_BASE as usize) else {
                continue;
            };
            for l in loaded.iter_mut().skip(off).take(n) {
                *l = true;
            }
        }
    }
    for (b, l) in v.iter_mut().zip(&loaded) {
        if !l {
            *b = 0;
        }
    }
    v
}

/// The update file of `app` stamped `v`, signed with the test key.
pub fn update_file(app: &[u8], v: Version) -> Vec<u8> {
    let mut a = app.to_vec();
    stamp(&mut a, v);
    signed_file(&a, &test_key_seed())
}

/// How a transfer ended.
#[derive(Clone, Debug, Default)]
pub struct Transfer {
    /// The console's reply after the transfer (`ok: update verified …` or `error: update
    /// refused: …`), or empty (cut, or none in time).
    pub reply: String,
    /// Virtual time from `update` to the reply, s.
    pub seconds: f64,
    /// READY was high at some instant between `update` and the reply.
    pub ready_seen: bool,
    /// The motors were driven at some instant of it.
    pub moved: bool,
    /// The sender was cut off (power cut) after this many acknowledged bytes.
    pub cut_at: Option<usize>,
    /// The longest pause between two bytes on the line from `update` to the receiver's
    /// first 'C' (the command's echo and its reply), ms: a reply cut in two by a DFU
    /// erase (the CPU and the transmit interrupt stalled) pauses for seconds.
    pub reply_gap_ms: f64,
    /// Virtual time from `update` typed to the receiver's first 'C', ms (issue 31: the
    /// transfer starts within a second; DFU is erased page by page as blocks arrive).
    pub first_c_ms: f64,
    /// Code-flash sectors erased from `update` to the reply (the DFU pages; none for a
    /// file refused by its first block).
    pub erases: u64,
    /// The pace (issue 35): the first data block sent → the last block's ACK, ps.
    pub blocks_ps: u64,
    /// Bytes of the data blocks the sender put on the line (1029 B each, repeats too).
    pub wire_bytes: u64,
    /// Each data block's wait: its last byte at the board → its ACK leaving it, ps.
    pub ack_waits_ps: Vec<u64>,
    /// Packets the sender sent again.
    pub retries: u32,
}

/// Picoseconds of one 8N1 character at 115 200 Bd (the console's line).
pub const CHAR_PS: u64 = 10 * crate::time::PS_PER_S / 115_200;

impl Transfer {
    /// The transfer's pace against the line's limit, one line (issue 35;
    /// tools/figures.sh puts it in docs/measurements.md).
    pub fn pace(&self, file_len: usize) -> String {
        let s = |ps: u64| ps as f64 / PS_PER_S as f64;
        let total = s(self.blocks_ps);
        let wire = s(self.wire_bytes * CHAR_PS);
        let waits: u64 = self.ack_waits_ps.iter().sum();
        let mut sorted = self.ack_waits_ps.clone();
        sorted.sort_unstable();
        let median = sorted.get(sorted.len() / 2).copied().unwrap_or(0);
        let longest = sorted.last().copied().unwrap_or(0);
        let blocks = self.wire_bytes / 1029;
        format!(
            "{file_len} B in {total:.2} s from the first block to the last ACK: {:.0} B/s, {:.1} % of the line's 11 520 B/s; on the wire {wire:.2} s ({} B: {blocks} blocks, 5 B of framing each, 0.49 %, and {} B of the last one's padding), the board's ACK waits {:.2} s ({} blocks: median {:.1} ms, the longest {:.3} s), the rest {:.2} s (the sender's replies, within 1 ms each here)",
            file_len as f64 / total.max(1e-9),
            100.0 * file_len as f64 / total.max(1e-9) / 11_520.0,
            self.wire_bytes,
            (blocks * 1024).saturating_sub(file_len as u64),
            s(waits),
            self.ack_waits_ps.len(),
            median as f64 / PS_PER_MS as f64,
            s(longest),
            (total - wire - s(waits)).max(0.0),
        )
    }
}

/// Type `update` and send `file` by YMODEM-1K; `cut_at_bytes`: pull the power once the
/// board has acknowledged that many bytes of the file. `dock_at_bytes`: the PLC asserts
/// DOCK once that many are acknowledged (and releases it 300 ms later).
pub fn transfer(
    s: &mut Session,
    file: &[u8],
    cut_at_bytes: Option<usize>,
    dock_at_bytes: Option<usize>,
) -> Result<Transfer, Halt> {
    let t0 = s.now();
    let wall0 = std::time::Instant::now();
    let mut out = Transfer::default();
    let erases0 = s.board.soc().code_erases;
    let start = s.board.soc().console_out.len();
    let _ = s.board.soc_mut().console_send(b"update\r\n");
    let mut sender = YmodemSender::new("docking-controller.dcs", file.to_vec());
    let mut seen = start;
    let mut docked_at: Option<u64> = None;
    let deadline = s.now() + 300 * PS_PER_S;
    let mut text_from: Option<usize> = None;
    let mut gap_done = false;
    // The pace: when the last packet's last byte reaches the board, the first data
    // block, the last block's ACK.
    let mut arrived = 0u64;
    let mut first_block: Option<u64> = None;
    let mut last_ack = 0u64;
    while s.now() < deadline {
        s.run_for(PS_PER_MS)?;
        let m = s.machine();
        out.moved |= m.axis.enabled() || m.lock.driven();
        out.ready_seen |= s.plc_out().ready;
        let bytes: Vec<u8> = s.board.soc().console_out[seen..]
            .iter()
            .map(|&(_, b)| b)
            .collect();
        if !gap_done {
            // The bytes up to the first 'C' (the reply has no 'C' after "ok: ": its text
            // is lowercase but for "YMODEM-1K"; the echo's "update" none).
            let out_bytes = &s.board.soc().console_out[start..];
            if let Some(c) = out_bytes.iter().position(|&(_, b)| b == b'C').filter(|&c| {
                out_bytes[..c]
                    .windows(2)
                    .any(|w| w[0].1 == b'\r' && w[1].1 == b'\n')
            }) {
                gap_done = true;
                out.first_c_ms = (out_bytes[c].0 - t0) as f64 / PS_PER_MS as f64;
                out.reply_gap_ms = out_bytes[..c]
                    .windows(2)
                    .map(|w| (w[1].0 - w[0].0) as f64 / PS_PER_MS as f64)
                    .fold(0.0, f64::max);
            }
        }
        seen += bytes.len();
        if sender.state == hil_sim::update::SendState::Start {
            // `update` refused at once (no 'C' will come): its one line is the reply.
            let text: Vec<u8> = s.board.soc().console_out[start..]
                .iter()
                .map(|&(_, b)| b)
                .collect();
            let text = String::from_utf8_lossy(&text).into_owned();
            if let Some(line) = text.split("\r\n").find(|l| l.starts_with("error:")) {
                if text.contains(&format!("{line}\r\n")) {
                    out.reply = line.to_string();
                    break;
                }
            }
        }
        if !sender.finished() {
            let stamped: Vec<(u64, u8)> =
                s.board.soc().console_out[seen - bytes.len()..seen].to_vec();
            for (at, b) in stamped {
                if std::env::var_os("VBOARD_TRACE_UPDATE").is_some()
                    && !matches!(sender.state, hil_sim::update::SendState::Block(_))
                {
                    eprintln!("  board → {b:#04x} in {:?}", sender.state);
                }
                let was = sender.state;
                let reply = sender.on_byte(b);
                if let (hil_sim::update::SendState::Block(_), docking_logic::ymodem::ACK) = (was, b)
                {
                    out.ack_waits_ps.push(at.saturating_sub(arrived));
                    last_ack = at;
                }
                if !reply.is_empty() {
                    let now = s.now();
                    if matches!(sender.state, hil_sim::update::SendState::Block(_)) {
                        first_block.get_or_insert(now);
                        out.wire_bytes += reply.len() as u64;
                    }
                    // At line rate after whatever is still on its way (as the UART model
                    // queues it).
                    arrived = arrived.max(now) + reply.len() as u64 * CHAR_PS;
                    let _ = s.board.soc_mut().console_send(&reply);
                }
            }
            if sender.finished() {
                text_from = Some(seen);
            }
        }
        let acked = sender.acknowledged();
        if std::env::var_os("VBOARD_TRACE_UPDATE").is_some() && (s.now() / PS_PER_MS) % 500 == 0 {
            eprintln!(
                "[{:.3} s] sender {:?} acked {acked} retries {}",
                s.now() as f64 / PS_PER_S as f64,
                sender.state,
                sender.retries
            );
        }
        if let (Some(at), None) = (dock_at_bytes, docked_at) {
            if acked >= at {
                s.set_dock(true);
                docked_at = Some(s.now());
            }
        }
        if docked_at.is_some_and(|t| s.now() > t + 300 * PS_PER_MS) {
            s.set_dock(false);
        }
        if let Some(at) = cut_at_bytes {
            if acked >= at && !sender.finished() {
                out.cut_at = Some(acked);
                s.board.power_on();
                return Ok(out);
            }
        }
        if let Some(from) = text_from {
            let text: Vec<u8> = s.board.soc().console_out[from..]
                .iter()
                .map(|&(_, b)| b)
                .collect();
            let text = String::from_utf8_lossy(&text).into_owned();
            if let Some(line) = text
                .split("\r\n")
                .find(|l| l.starts_with("ok: update") || l.starts_with("error: update"))
            {
                if text.contains(&format!("{line}\r\n")) {
                    out.reply = line.to_string();
                    break;
                }
            }
        }
    }
    s.set_dock(false);
    out.blocks_ps = first_block.map_or(0, |f| last_ack.saturating_sub(f));
    out.retries = sender.retries;
    out.seconds = (s.now() - t0) as f64 / PS_PER_S as f64;
    out.erases = s.board.soc().code_erases - erases0;
    if std::env::var_os("VBOARD_TRACE_UPDATE").is_some() {
        eprintln!(
            "transfer: {:.1} s virtual, {:.1} s wall",
            out.seconds,
            wall0.elapsed().as_secs_f64()
        );
    }
    Ok(out)
}

/// Bytes of flash at `[addr, addr + len)` as the core reads them.
pub fn read_flash(s: &Session, addr: u32, len: u32) -> Vec<u8> {
    (0..len / 4)
        .flat_map(|i| s.board.peek(addr + 4 * i).unwrap_or(0).to_le_bytes())
        .collect()
}

/// The state record's magic.
fn state_word(s: &Session) -> u32 {
    s.board.peek(STATE_BASE).unwrap_or(0)
}

/// The odometer's counters and readings as the console reports them (`wear --json`
/// without the fields of the moment, `measurements --json`).
fn counters(s: &mut Session) -> Result<String, Halt> {
    let w = s.console_json("wear --json")?;
    let m = s.console_json("measurements --json")?;
    Ok(format!("{}|{}", w.trim(), m.trim()))
}

/// Whether the firmware has logged a line containing `text` (defmt, over RTT).
fn logged(s: &Session, text: &str) -> bool {
    s.board.log.iter().any(|l| l.msg.contains(text))
}

fn version(s: &mut Session) -> Result<String, Halt> {
    s.console_json("version --json")
}

/// Run until the image has logged `boots` boots and then `extra_ps` more.
fn run_to_boot(s: &mut Session, boots: u32, limit_ps: u64) -> Result<bool, Halt> {
    let deadline = s.now() + limit_ps;
    let ok = s.run_until(deadline, |x| x.seen.boots >= boots)?;
    // Init, the confirmation, the console's banner.
    s.run_for(2 * PS_PER_S)?;
    Ok(ok)
}

/// The machine docked once (so the counters are not zero), a micrometer reading taken,
/// maintenance mode entered: the board as a technician finds it before an update.
fn prepare(s: &mut Session, checks: &mut Checks) -> Result<(), Halt> {
    let deadline = s.now() + 150 * PS_PER_S;
    s.run_until(deadline, |x| {
        x.seen.boots >= 1 && x.at_rest() && x.plc_out().ready
    })?;
    s.press_dock();
    let deadline = s.now() + 150 * PS_PER_S;
    let cycled = s.run_until(deadline, |x| x.seen.cycles_completed >= 1 && x.at_rest())?;
    s.run_for(PS_PER_S)?;
    checks.push((
        "a docking cycle before the update".into(),
        cycled,
        String::new(),
    ));
    let m = s.maint_enter()?;
    let r = s.console("measure 26.004", 5 * PS_PER_S)?;
    checks.push((
        "maintenance mode and a reading".into(),
        m && r.starts_with("ok"),
        r.trim().into(),
    ));
    Ok(())
}

/// Scene `update`.
pub fn update(s: &mut Session, checks: &mut Checks) -> Result<(), Halt> {
    prepare(s, checks)?;
    let before = counters(s)?;
    let v_before = version(s)?;
    let erases_before = s
        .board
        .soc()
        .world
        .flash
        .with(|f| f.erase_counts().to_vec());
    let app = app_bytes(&s.board.image);
    let file = update_file(&app, NEW_VERSION);
    let boots = s.seen.boots;
    let t0 = s.now();
    let t = transfer(s, &file, None, Some(file.len() / 2))?;
    checks.push((
        "the update verified".into(),
        t.reply.starts_with("ok: update verified: version 0.1.1"),
        format!("{} ({:.1} s)", t.reply, t.seconds),
    ));
    // Issue 32's review: the update's end wrote its image record (MARKED) and its audit
    // record before the reply, at rest with the line free (`update::at_rest` in
    // src/board/update.rs), not queued in RAM for a rest the restart never gives it.
    let (image, audit) = (image_event(s), newest_audit_action(s));
    checks.push((
        "the update's image record (MARKED) and audit record in flash before the restart".into(),
        image == Some(docking_logic::update::event::MARKED)
            && audit == Some(docking_logic::console::service::action::UPDATE),
        format!("newest image record's event {image:?}, newest audit record's action {audit:?}"),
    ));
    // Issue 35: the pace against the line's limit; no block sent twice and every ACK
    // within a sender's 10 s (lrzsz's sb) even while a DFU page erases.
    let longest = t.ack_waits_ps.iter().copied().max().unwrap_or(u64::MAX);
    checks.push((
        "the transfer's pace: no block sent twice, every ACK within sb's 10 s".into(),
        t.retries == 0 && longest < 10 * PS_PER_S && !t.ack_waits_ps.is_empty(),
        t.pace(file.len()),
    ));
    checks.push((
        "update's reply whole on the line before the first 'C' (no pause over 20 ms in it)".into(),
        t.reply_gap_ms < 20.0,
        format!("longest pause {:.3} ms", t.reply_gap_ms),
    ));
    checks.push((
        "the first 'C' within 1 s of `update` (nothing erased before the first block)".into(),
        t.first_c_ms <= 1_000.0,
        format!("{:.1} ms", t.first_c_ms),
    ));
    checks.push((
        "READY low and nothing moving for the whole update, the DOCK edge refused".into(),
        !t.ready_seen
            && !t.moved
            && s.board
                .log
                .iter()
                .any(|l| l.msg.contains("DOCK") && l.msg.contains("refused")),
        format!("ready seen {}, moved {}", t.ready_seen, t.moved),
    ));
    // The restart, the bootloader's swap, the new image's trial boot.
    let booted = run_to_boot(s, boots + 1, 90 * PS_PER_S)?;
    let confirmed = logged(s, "trial boot confirmed");
    checks.push((
        "the new image booted and confirmed itself".into(),
        booted && confirmed && state_word(s) == update_layout::state::BOOT,
        format!("STATE {:#010x}", state_word(s)),
    ));
    let v = version(s)?;
    let mut want = app.clone();
    stamp(&mut want, NEW_VERSION);
    let active = read_flash(s, ACTIVE_BASE, want.len() as u32 / 4 * 4);
    checks.push((
        "the new version runs (ACTIVE is the new image; version says so, the previous too)".into(),
        json_field(&v, "version").as_deref() == Some("0.1.1")
            && json_field(&v, "previous").as_deref() == Some("0.1.0")
            && json_field(&v, "test_key").as_deref() == Some("true")
            && active[..] == want[..active.len()],
        format!("before: {} after: {}", v_before.trim(), v.trim()),
    ));
    let after = counters(s)?;
    checks.push((
        "every odometer counter and reading intact".into(),
        after == before,
        if after == before {
            String::new()
        } else {
            format!("before {before} after {after}")
        },
    ));
    let erases_after = s
        .board
        .soc()
        .world
        .flash
        .with(|f| f.erase_counts().to_vec());
    checks.push((
        "the odometer's sectors never erased by the update".into(),
        erases_after == erases_before,
        format!("{erases_before:?} → {erases_after:?}"),
    ));
    let (ok, detail) = one_erase_a_window(s, t0);
    checks.push((
        "one flash erase a service window, the trial's confirmation included (a control step between any two)".into(),
        ok,
        detail,
    ));
    Ok(())
}

/// Whether every two sector erases the application started after `after_ps` have a
/// control step (TIM2's entry) between them: one erase a service window (issue 31, fix
/// 2: the control step's deadline and the watchdog keep their margins). The bootloader's
/// swap, which has no control step, is left out: its erases are between the update's
/// reset and the new image's first instruction in ACTIVE.
pub fn one_erase_a_window(s: &Session, after_ps: u64) -> (bool, String) {
    let steps = s
        .board
        .soc()
        .entry_log
        .times(crate::scene::CONTROL_EXCEPTION);
    let erases: Vec<(u64, u64, u32)> = s
        .board
        .soc()
        .flash
        .erase_log()
        .iter()
        .copied()
        .filter(|&(start, _, _)| start >= after_ps)
        .collect();
    let resets: Vec<u64> = s.board.resets.iter().map(|&(t, _)| t).collect();
    let mut worst = String::new();
    let mut ok = true;
    for w in erases.windows(2) {
        let ((_, end, a), (start, _, b)) = (w[0], w[1]);
        // In the bootloader (a reset since the last control step before the erase):
        // the swap has no control step at all; left out.
        let last_step = steps.iter().copied().filter(|&t| t < start).max();
        let last_reset = resets.iter().copied().filter(|&t| t < start).max();
        let in_boot = match (last_step, last_reset) {
            (_, None) => false,
            (None, Some(_)) => true,
            (Some(st), Some(r)) => r > st,
        };
        let between = steps.iter().any(|&t| t >= end && t <= start);
        if !in_boot && !between {
            ok = false;
            worst = format!("sector {a} then sector {b} with no control step between");
        }
    }
    (
        ok,
        format!(
            "{} erases after the transfer began{}",
            erases.len(),
            if worst.is_empty() {
                String::new()
            } else {
                format!(": {worst}")
            }
        ),
    )
}

/// A bad file of `update-bad`.
pub struct BadFile {
    /// What is wrong with it.
    pub what: &'static str,
    /// The file.
    pub file: Vec<u8>,
    /// Words of the refusal.
    pub words: &'static str,
    /// Refused by its first block: nothing may be erased.
    pub before_erase: bool,
}

/// The bad files of `update-bad`.
pub fn bad_files(app: &[u8]) -> Vec<BadFile> {
    let good = update_file(app, NEW_VERSION);
    let mut flipped = good.clone();
    flipped[good.len() / 3] ^= 0x01;
    // A small image of its own for the rest (a vector table into ACTIVE, no more): the
    // same refusals at a sixth of the transfer time.
    let mut small = app[..16 * 1024].to_vec();
    stamp(&mut small, NEW_VERSION);
    // The image built for layout B: its header names B (a file of an earlier build is
    // also linked at B's ACTIVE; either is refused by its first block).
    let mut layout_b = app.to_vec();
    let at = update_layout::header::HEADER_OFFSET as usize + 13;
    layout_b[at] = update_layout::layout::Layout::B.id();
    let bad = |what, file, words, before_erase| BadFile {
        what,
        file,
        words,
        before_erase,
    };
    vec![
        bad(
            "corrupted (one bit flipped)",
            flipped,
            "signature does not verify",
            false,
        ),
        bad(
            "truncated (the file cut at 16 KiB)",
            good[..16 * 1024].to_vec(),
            "no update trailer",
            false,
        ),
        bad(
            "unsigned (no trailer)",
            small.clone(),
            "no update trailer",
            false,
        ),
        bad(
            "signed with another key",
            signed_file(&small, &other_key_seed()),
            "signature does not verify",
            false,
        ),
        bad(
            "built for layout B",
            update_file(&layout_b, NEW_VERSION),
            "built for layout B; this board has layout C",
            true,
        ),
    ]
}

/// Scene `update-bad`.
pub fn update_bad(s: &mut Session, checks: &mut Checks) -> Result<(), Halt> {
    prepare(s, checks)?;
    let before = counters(s)?;
    let v_before = version(s)?;
    let state_before = state_word(s);
    let active_before = read_flash(s, ACTIVE_BASE, ACTIVE_LEN);
    let app = app_bytes(&s.board.image);
    for BadFile {
        what,
        file,
        words,
        before_erase,
    } in bad_files(&app)
    {
        let t = transfer(s, &file, None, None)?;
        checks.push((
            format!("{what}: refused in one line"),
            t.reply.starts_with("error: update refused:") && t.reply.contains(words),
            t.reply.clone(),
        ));
        if before_erase {
            checks.push((
                format!("{what}: refused before anything was erased"),
                t.erases == 0,
                format!("{} sectors erased", t.erases),
            ));
        }
        checks.push((
            format!("{what}: STATE untouched, READY low and nothing moving meanwhile"),
            state_word(s) == state_before && !t.ready_seen && !t.moved,
            format!("STATE {:#010x}", state_word(s)),
        ));
    }
    let active_after = read_flash(s, ACTIVE_BASE, ACTIVE_LEN);
    let v = version(s)?;
    checks.push((
        "nothing changed: ACTIVE, the version, the counters".into(),
        active_after == active_before && v == v_before && counters(s)? == before,
        v.trim().into(),
    ));
    // The machine is the PLC's again once the technician leaves.
    s.maint_exit()?;
    let deadline = s.now() + 5 * PS_PER_S;
    let ready = s.run_until(deadline, |x| x.plc_out().ready)?;
    checks.push(("READY back after maint exit".into(), ready, String::new()));
    Ok(())
}

/// The tiny image that never confirms (vboard/tests/boot.rs's application): a vector
/// table into ACTIVE, code that writes a tag to SRAM and spins without feeding the
/// watchdog; a header stamped 9.9.9.
pub fn never_confirming_image() -> Vec<u8> {
    const MARK: u32 = 0x2001_F000;
    let mut v = Vec::new();
    v.extend(0x2002_0000u32.to_le_bytes());
    v.extend((ACTIVE_BASE + 0x40 + 1).to_le_bytes());
    v.resize(0x40, 0xFF);
    // ldr r0,=MARK; ldr r1,=tag; str r1,[r0]; mov r2,sp; str r2,[r0,#4];
    // ldr r3,=VTOR; ldr r3,[r3]; str r3,[r0,#8]; then `wfi; b .-2`: it sleeps (no
    // interrupt is enabled) until the bootloader's watchdog resets it.
    for hw in [
        0x4804u16, 0x4905, 0x6001, 0x466A, 0x6042, 0x4B04, 0x681B, 0x6083, 0xBF30, 0xE7FD,
    ] {
        v.extend(hw.to_le_bytes());
    }
    for w in [MARK, 0xB0B0_0002, 0xE000_ED08] {
        v.extend(w.to_le_bytes());
    }
    v.resize(0x200, 0xFF);
    v.extend(
        update_layout::header::Header {
            version: Version {
                major: 9,
                minor: 9,
                patch: 9,
                build: 0,
            },
            flags: update_layout::header::FLAG_STAMPED
                | update_layout::header::Header::flags_for(update_layout::layout::LAYOUT),
            key_id: [0; 16],
        }
        .to_bytes(),
    );
    while v.len() < 4096 {
        v.push(v.len() as u8);
    }
    v
}

/// Scene `update-rollback`.
pub fn update_rollback(s: &mut Session, checks: &mut Checks) -> Result<(), Halt> {
    prepare(s, checks)?;
    let before = counters(s)?;
    let file = signed_file(&never_confirming_image(), &test_key_seed());
    let boots = s.seen.boots;
    let t = transfer(s, &file, None, None)?;
    checks.push((
        "the never-confirming image verified (it is signed)".into(),
        t.reply.starts_with("ok: update verified: version 9.9.9"),
        t.reply.clone(),
    ));
    // Reset, swap, the image spins until the bootloader's watchdog resets it, revert.
    let booted = run_to_boot(s, boots + 1, 120 * PS_PER_S)?;
    let watchdog = s.reset_causes().contains(&"watchdog");
    checks.push((
        "reset by the watchdog and rolled back".into(),
        booted && watchdog && state_word(s) == update_layout::state::REVERT,
        format!("resets {:?}", s.reset_causes()),
    ));
    let v = version(s)?;
    checks.push((
        "the old image reports the rollback".into(),
        json_field(&v, "version").as_deref() == Some("0.1.0")
            && json_field(&v, "rolled_back").as_deref() == Some("true")
            && json_field(&v, "rolled_back_version").as_deref() == Some("9.9.9")
            && logged(s, "rolled back"),
        v.trim().into(),
    ));
    checks.push((
        "every odometer counter and reading intact".into(),
        counters(s)? == before,
        String::new(),
    ));
    Ok(())
}

/// A cut scene's kind.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Cut {
    /// During the YMODEM transfer.
    Transfer,
    /// During the bootloader's swap.
    Swap,
    /// During the new image's first boot (before, during or after its confirmation).
    Boot,
}

impl Cut {
    /// From `--cut`.
    pub fn parse(s: &str) -> Option<Self> {
        match s {
            "transfer" => Some(Self::Transfer),
            "swap" => Some(Self::Swap),
            "boot" => Some(Self::Boot),
            _ => None,
        }
    }
}

/// xorshift64: the cut's instant from the seed.
pub fn fraction(seed: u64) -> f64 {
    let mut x = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
    for _ in 0..4 {
        x ^= x << 13;
        x ^= x >> 7;
        x ^= x << 17;
    }
    (x % 1_000_000) as f64 / 1_000_000.0
}

/// The board after a verified update, at the instant of its reply (STATE says SWAP):
/// the flash (code and odometer) to power a board on from, the counters, the images.
pub struct Marked {
    /// Code flash, sectors 0-9.
    pub code: Vec<u8>,
    /// The odometer's flash.
    pub odometer: hil_sim::flash::SimFlash,
    /// The counters before.
    pub counters: String,
    /// ACTIVE's image before and after.
    pub old: Vec<u8>,
    /// The new image.
    pub new: Vec<u8>,
    /// The transfer's virtual length, s.
    pub transfer_s: f64,
    /// The bootloader's swap: power-on to the new image's first log line, ps (measured
    /// on a board powered on from this flash).
    pub swap_ps: u64,
}

/// Run the update to the instant it is marked (once per process for the cut scenes'
/// seeds); `measure_swap`: then power a board on from it to time the swap
/// ([`Marked::swap_ps`]; else 0, see [`update_from_marked`]).
pub fn marked(opts: &Options, measure_swap: bool) -> Result<Marked, String> {
    let mut s = Session::new(opts.clone())?;
    let mut checks = Checks::new();
    prepare(&mut s, &mut checks).map_err(|e| e.to_string())?;
    let counters = counters(&mut s).map_err(|e| e.to_string())?;
    let app = app_bytes(&s.board.image);
    let old = read_flash(&s, ACTIVE_BASE, app.len() as u32 / 4 * 4);
    let file = update_file(&app, NEW_VERSION);
    // Stop at the reply: the board's restart is the next instant.
    let t = transfer(&mut s, &file, None, None).map_err(|e| e.to_string())?;
    if !t.reply.starts_with("ok: update verified") {
        return Err(format!("the update was not verified: {}", t.reply));
    }
    let mut new = app.clone();
    stamp(&mut new, NEW_VERSION);
    let mut m = Marked {
        code: read_flash(&s, FLASH_BASE, ODOMETER_BASE - FLASH_BASE),
        odometer: s.board.soc().world.flash.with(|f| f.clone()),
        counters,
        old,
        new,
        transfer_s: t.seconds,
        swap_ps: 0,
    };
    if measure_swap {
        let mut b = from_marked(opts, &m)?;
        let deadline = b.now() + 120 * PS_PER_S;
        b.run_until(deadline, |x| !x.board.log.is_empty())
            .map_err(|e| e.to_string())?;
        m.swap_ps = b.now();
    }
    Ok(m)
}

/// A board powered on from `m`'s flash: the update as it restarts (its SRAM lost: the
/// counters are in flash by then, written at rest).
pub fn from_marked(opts: &Options, m: &Marked) -> Result<Session, String> {
    let mut img = Image::load(&opts.firmware)?;
    img.flash = m.code.clone();
    let mut o = opts.clone();
    o.commissioned = false;
    Session::with_image(o, img, SharedFlash::new(m.odometer.clone()))
}

/// Which image ACTIVE holds: "old", "new" or "neither".
fn which(s: &Session, old: &[u8], new: &[u8]) -> &'static str {
    let n = old.len().max(new.len()) as u32 / 4 * 4;
    let active = read_flash(s, ACTIVE_BASE, n);
    let is = |img: &[u8]| {
        let mut padded = img.to_vec();
        padded.resize(n as usize, 0xFF);
        active == padded
    };
    if is(new) {
        "new"
    } else if is(old) {
        "old"
    } else {
        "neither"
    }
}

/// After a cut: a whole image boots, its counters are the ones before, nothing moves
/// (no request comes); `want`: the images the instant allows.
#[allow(clippy::too_many_arguments)]
fn after_cut(
    s: &mut Session,
    old: &[u8],
    new: &[u8],
    counters_before: &str,
    want: &[&str],
    checks: &mut Checks,
    what: &str,
    cut_ps: u64,
) -> Result<(), Halt> {
    let booted = run_to_boot(s, 1, 120 * PS_PER_S)?;
    let moved = s
        .board
        .soc()
        .edges
        .iter()
        .any(|e| e.t_ps >= cut_ps && e.signal == crate::world::Signal::EnN && !e.high);
    let img = which(s, old, new);
    let v = version(s)?;
    let v_ok = match img {
        "new" => json_field(&v, "version").as_deref() == Some("0.1.1"),
        "old" => json_field(&v, "version").as_deref() == Some("0.1.0"),
        _ => false,
    };
    checks.push((
        format!(
            "{what}: a whole, validly signed image boots ({})",
            want.join(" or ")
        ),
        booted && want.contains(&img) && v_ok,
        format!("ACTIVE {img}, {}", v.trim()),
    ));
    if img == "new" {
        // On trial, from DFU page 1; confirmed, from its CONFIRMED record.
        checks.push((
            format!("{what}: the new image names the one it replaced (0.1.0)"),
            json_field(&v, "previous").as_deref() == Some("0.1.0"),
            v.trim().to_string(),
        ));
    }
    let c = counters(s)?;
    checks.push((
        format!("{what}: every counter and reading intact"),
        c == counters_before,
        if c == counters_before {
            String::new()
        } else {
            format!("before {counters_before} after {c}")
        },
    ));
    checks.push((
        format!("{what}: nothing moved without a request"),
        !moved && !s.machine().axis.enabled() && !s.machine().lock.driven(),
        String::new(),
    ));
    Ok(())
}

/// From the marked flash `m`, the new image's trial boot with its load cell dead from
/// power-on: silent (`Hx711Fault::Disconnected`: no sample ever) or stuck
/// (`Hx711Fault::Stuck`: every conversion the first one's code). Its self-test never
/// sees two live samples of different codes, so it never confirms (STATE stays SWAP
/// however long it runs) and a technician's update meanwhile is refused (nothing is
/// marked over a trial; tried with the silent load cell); the next reset (a pin reset here, the load cell working again)
/// rolls it back to the old image, which reports the rollback; the trial's sensor fault
/// is on record, every other counter and reading intact.
pub fn update_dead_sensor(
    opts: &Options,
    m: &Marked,
    fault: hil_sim::hx711::Hx711Fault,
    checks: &mut Checks,
) -> Result<Session, String> {
    let what = match fault {
        hil_sim::hx711::Hx711Fault::Stuck => "stuck load cell",
        _ => "silent load cell",
    };
    let mut s = from_marked(opts, m)?;
    s.machine().hx.set_fault(fault);
    let deadline = s.now() + 120 * PS_PER_S;
    s.run_until(deadline, |x| {
        logged(x, "trial boot, confirmed once the load cell answers")
    })
    .map_err(|e| e.to_string())?;
    let on_trial = which(&s, &m.old, &m.new) == "new";
    s.run_for(5 * PS_PER_S).map_err(|e| e.to_string())?;
    let confirmed = logged(&s, "trial boot confirmed");
    checks.push((
        format!("{what}: the new image on trial, not confirmed after 5 s (STATE says SWAP)"),
        on_trial && !confirmed && state_word(&s) == update_layout::state::SWAP,
        format!(
            "ACTIVE new {on_trial}, confirmed {confirmed}, STATE {:#010x}",
            state_word(&s)
        ),
    ));
    // A technician's update meanwhile: refused at `update`, before anything is erased
    // (DFU holds the image the rollback needs: issue 31), STATE untouched. (With the
    // silent load cell only: the refusal does not depend on why the trial waits.)
    if fault == hil_sim::hx711::Hx711Fault::Disconnected {
        let entered = s.maint_enter().map_err(|e| e.to_string())?;
        let file = signed_file(&never_confirming_image(), &test_key_seed());
        let t = transfer(&mut s, &file, None, None).map_err(|e| e.to_string())?;
        checks.push((
            format!("{what}: an update meanwhile refused (on trial) before anything was erased, STATE still SWAP"),
            entered
                && t.reply.contains("this image is on trial, not confirmed")
                && t.erases == 0
                && state_word(&s) == update_layout::state::SWAP,
            format!("{} ({} sectors erased)", t.reply.trim(), t.erases),
        ));
        let v = version(&mut s).map_err(|e| e.to_string())?;
        checks.push((
            format!("{what}: version says the image is on trial, and what to do"),
            json_field(&v, "trial").as_deref() == Some("yes")
                && json_field(&v, "trial_advice").is_some_and(|a| a.contains("rolls it back")),
            v.trim().to_string(),
        ));
    }
    s.machine().hx.set_fault(hil_sim::hx711::Hx711Fault::None);
    s.seen.boots = 0;
    s.board.reset_pin();
    let booted = run_to_boot(&mut s, 1, 120 * PS_PER_S).map_err(|e| e.to_string())?;
    let img = which(&s, &m.old, &m.new);
    checks.push((
        format!("{what}, then a reset: the old image boots"),
        booted && img == "old",
        format!("ACTIVE {img}"),
    ));
    // The trial latched its sensor fault (`sensor_disconnected` or `sensor_stuck`): one
    // fault more on record, every other counter and reading as before.
    let c = counters(&mut s).map_err(|e| e.to_string())?;
    let faults = |x: &str| json_field(x, "faults").and_then(|f| f.parse::<u64>().ok());
    let others = |x: &str| x.replacen(&format!("\"faults\":{}", faults(x).unwrap_or(0)), "", 1);
    checks.push((
        format!("{what}, then a reset: the trial's one fault on record, every other counter and reading intact"),
        faults(&c) == faults(&m.counters).map(|f| f + 1) && others(&c) == others(&m.counters),
        format!("before {} after {c}", m.counters),
    ));
    let v = version(&mut s).map_err(|e| e.to_string())?;
    checks.push((
        format!("{what}: the old image reports the rollback of 0.1.1"),
        json_field(&v, "rolled_back").as_deref() == Some("true")
            && json_field(&v, "rolled_back_version").as_deref() == Some("0.1.1"),
        v.trim().to_string(),
    ));
    Ok(s)
}

/// One `update-cut` run of the transfer kind: the power cut once the board has
/// acknowledged a seeded share of the file.
pub fn update_cut_transfer(
    seed: u64,
    opts: &Options,
    checks: &mut Checks,
) -> Result<Session, String> {
    let f = fraction(seed);
    let mut s = Session::new(opts.clone())?;
    prepare(&mut s, checks).map_err(|e| e.to_string())?;
    let before = counters(&mut s).map_err(|e| e.to_string())?;
    let state = state_word(&s);
    let app = app_bytes(&s.board.image);
    // What ACTIVE holds now (as the probe flashed it) and what the update would put there.
    let old = read_flash(&s, ACTIVE_BASE, app.len() as u32 / 4 * 4);
    let mut new = app.clone();
    stamp(&mut new, NEW_VERSION);
    let file = update_file(&app, NEW_VERSION);
    let at = ((file.len() as f64 * f) as usize).max(1);
    let t = transfer(&mut s, &file, Some(at), None).map_err(|e| e.to_string())?;
    checks.push((
        format!("power cut at byte {at} of {} of the transfer", file.len()),
        t.cut_at.is_some(),
        String::new(),
    ));
    let cut_ps = s.now();
    s.seen.boots = 0;
    after_cut(
        &mut s,
        &old,
        &new,
        &before,
        &["old"],
        checks,
        "transfer",
        cut_ps,
    )
    .map_err(|e| e.to_string())?;
    checks.push((
        "transfer: STATE untouched".into(),
        state_word(&s) == state,
        format!("{state:#x} → {:#x}", state_word(&s)),
    ));
    Ok(s)
}

/// One `update-cut` run of the swap or boot kind, from the marked flash `m`: the power
/// cut at a seeded instant of the bootloader's swap, or of the new image's first 1.5 s
/// (its confirmation inside).
pub fn update_cut_marked(
    cut: Cut,
    seed: u64,
    opts: &Options,
    m: &Marked,
    checks: &mut Checks,
) -> Result<Session, String> {
    let f = fraction(seed);
    let mut s = from_marked(opts, m)?;
    let t0 = s.now();
    if cut == Cut::Boot {
        // The new image's first log line: the swap is over, its init runs.
        let deadline = s.now() + 120 * PS_PER_S;
        s.run_until(deadline, |x| !x.board.log.is_empty())
            .map_err(|e| e.to_string())?;
        let end = s.now() + (1_500.0 * f) as u64 * PS_PER_MS;
        s.run_until(end, |_| false).map_err(|e| e.to_string())?;
    } else {
        let end = t0 + (m.swap_ps.max(PS_PER_S) as f64 * f) as u64;
        s.run_until(end, |_| false).map_err(|e| e.to_string())?;
    }
    let what = if cut == Cut::Swap {
        "swap"
    } else {
        "first boot"
    };
    checks.push((
        format!(
            "power cut {:.3} s after the restart (the swap takes {:.3} s)",
            (s.now() - t0) as f64 / PS_PER_S as f64,
            m.swap_ps as f64 / PS_PER_S as f64
        ),
        true,
        String::new(),
    ));
    // The swap resumes from its progress words and the new image runs; a cut in its
    // first instants, before it confirmed itself, rolls it back: either is whole.
    cut_marked_board(&mut s, m, &["new", "old"], checks, what)?;
    Ok(s)
}

/// Cut the power of a board started from the marked flash `m` now, power it on again
/// and check what boots ([`after_cut`]: one of `want`, whole, with `m`'s counters).
fn cut_marked_board(
    s: &mut Session,
    m: &Marked,
    want: &[&str],
    checks: &mut Checks,
    what: &str,
) -> Result<(), String> {
    let cut_ps = s.now();
    s.board.power_on();
    s.seen.boots = 0;
    after_cut(s, &m.old, &m.new, &m.counters, want, checks, what, cut_ps).map_err(|e| e.to_string())
}

/// The first byte of the newest record of `kind` in the odometer's flash (a copy of it
/// is opened: nothing is written), `None` without one.
fn newest_first_byte(s: &Session, kind: u8) -> Option<u8> {
    let copy = SharedFlash::new(s.board.soc().world.flash.with(|f| f.clone()));
    let newest = crate::scene::read_newest(&copy).ok()?;
    let (_, data) = newest.get(usize::from(kind))?.as_ref()?;
    data.first().copied()
}

/// The event of the newest image record (its first byte: logic/src/links/update.rs,
/// `ImageRecord`).
fn image_event(s: &Session) -> Option<u8> {
    newest_first_byte(s, docking_logic::odometer::kind::IMAGE)
}

/// The action of the newest audit record (its first byte: logic/src/links/console/service.rs,
/// `AuditLayout`).
fn newest_audit_action(s: &Session) -> Option<u8> {
    newest_first_byte(s, docking_logic::odometer::kind::AUDIT)
}

/// From the marked flash `m`, the power cut at the worst instant of the new image's
/// first boot: the trial has confirmed itself (STATE says BOOT), its CONFIRMED record is
/// not written yet. The instant is found on one run (to the millisecond), then a second
/// run from the same flash (the board is deterministic) goes to it in 2 µs steps. The
/// next boot is a confirmed one; it writes the record the cut lost, so `version` names
/// the image this one replaced. (Before `at_boot` wrote it, the record was lost and
/// `previous` stayed unknown for good.)
pub fn update_cut_at_confirmation(
    opts: &Options,
    m: &Marked,
    checks: &mut Checks,
) -> Result<Session, String> {
    const BOOT: u32 = update_layout::state::BOOT;
    let mut s = from_marked(opts, m)?;
    let deadline = s.now() + 120 * PS_PER_S;
    if !s
        .run_until(deadline, |x| state_word(x) == BOOT)
        .map_err(|e| e.to_string())?
    {
        return Err("the new image never confirmed itself".into());
    }
    let confirmed_ps = s.now();
    let mut s = from_marked(opts, m)?;
    s.run_until(confirmed_ps.saturating_sub(3 * PS_PER_MS), |_| false)
        .map_err(|e| e.to_string())?;
    while state_word(&s) != BOOT && s.now() < confirmed_ps + PS_PER_MS {
        let next = s.now() + 2 * PS_PER_MS / 1_000;
        s.board.run_until(next).map_err(|e| e.to_string())?;
    }
    let event = image_event(&s);
    checks.push((
        format!(
            "power cut {:.6} s after the restart: STATE says BOOT, the newest image record \
             is still MARKED",
            s.now() as f64 / PS_PER_S as f64
        ),
        state_word(&s) == BOOT && event == Some(docking_logic::update::event::MARKED),
        format!(
            "STATE {:#010x}, newest image record's event {event:?}",
            state_word(&s)
        ),
    ));
    cut_marked_board(
        &mut s,
        m,
        &["new"],
        checks,
        "cut before the CONFIRMED record",
    )?;
    let event = image_event(&s);
    checks.push((
        "the next boot wrote the CONFIRMED record the cut lost".into(),
        event == Some(docking_logic::update::event::CONFIRMED),
        format!("newest image record's event {event:?}"),
    ));
    Ok(s)
}

/// From the marked flash, no cut: the swap runs to its end, the new image confirms
/// itself and runs with every counter (what the `update` scene checks after its
/// restart); `m.swap_ps` measured on the way.
pub fn update_from_marked(
    opts: &Options,
    m: &mut Marked,
    checks: &mut Checks,
) -> Result<Session, String> {
    let mut s = from_marked(opts, m)?;
    let deadline = s.now() + 120 * PS_PER_S;
    s.run_until(deadline, |x| !x.board.log.is_empty())
        .map_err(|e| e.to_string())?;
    m.swap_ps = s.now();
    after_cut(
        &mut s,
        &m.old,
        &m.new,
        &m.counters,
        &["new"],
        checks,
        "no cut",
        0,
    )
    .map_err(|e| e.to_string())?;
    checks.push((
        "no cut: confirmed (STATE says BOOT)".into(),
        state_word(&s) == update_layout::state::BOOT,
        format!("{:#010x}", state_word(&s)),
    ));
    Ok(s)
}

/// Issue 31, fix 1: from the marked flash `m`, the new image's trial whose confirmation
/// cannot be written (STATE, sector 1, write-protected once the bootloader has swapped:
/// the first word program fails with WRPERR). It is tried again at later rests, three
/// attempts in all, each logged; after the last, `version --json` and Modbus device
/// identification (object 0x84) say `failed`, STATE still says SWAP, and the next reset,
/// the protection gone, rolls the image back.
pub fn update_confirm_fails(
    opts: &Options,
    m: &Marked,
    checks: &mut Checks,
) -> Result<Session, String> {
    let mut s = from_marked(opts, m)?;
    // The swap first (it writes STATE's progress words), then the protection.
    let deadline = s.now() + 120 * PS_PER_S;
    s.run_until(deadline, |x| {
        logged(x, "trial boot, confirmed once the load cell answers")
    })
    .map_err(|e| e.to_string())?;
    s.board.soc_mut().flash.write_protect(1, true);
    let deadline = s.now() + 10 * PS_PER_S;
    s.run_until(deadline, |x| logged(x, "attempt 3 of 3"))
        .map_err(|e| e.to_string())?;
    s.run_for(PS_PER_S).map_err(|e| e.to_string())?;
    let attempts: Vec<String> = s
        .board
        .log
        .iter()
        .filter(|l| l.msg.contains("trial boot not confirmed"))
        .map(|l| l.msg.clone())
        .collect();
    checks.push((
        "a failed confirmation: three attempts, each logged".into(),
        attempts.len() == 3
            && (1..=3).all(|n| {
                attempts
                    .iter()
                    .any(|a| a.contains(&format!("attempt {n} of 3")))
            }),
        attempts.join(" | "),
    ));
    let v = version(&mut s).map_err(|e| e.to_string())?;
    let ident = s
        .modbus(&crate::scene::rtu(1, &[0x2B, 0x0E, 0x04, 0x84]), PS_PER_S)
        .map_err(|e| e.to_string())?;
    // The one object's value: unit, 2B, 0E, 04, conformity, more, next, count, id, len.
    let value = ident.get(10..ident.len().saturating_sub(2)).unwrap_or(&[]);
    checks.push((
        "then version and Modbus identification say trial failed, STATE still SWAP".into(),
        json_field(&v, "trial").as_deref() == Some("failed")
            && value == b"failed"
            && state_word(&s) == update_layout::state::SWAP,
        format!(
            "{} | object 0x84 {:?} | STATE {:#010x}",
            v.trim(),
            String::from_utf8_lossy(value),
            state_word(&s)
        ),
    ));
    s.board.soc_mut().flash.write_protect(1, false);
    s.seen.boots = 0;
    s.board.reset_pin();
    let booted = run_to_boot(&mut s, 1, 120 * PS_PER_S).map_err(|e| e.to_string())?;
    let img = which(&s, &m.old, &m.new);
    checks.push((
        "the next reset rolls it back".into(),
        booted && img == "old",
        format!("ACTIVE {img}"),
    ));
    Ok(s)
}
