//! The reading commands: `status`, `wear`, `history`, `faults`, `measurements`,
//! `version` (a table, the board's JSON line, or CSV), `export` (one machine's record in
//! one JSON file) and `watch` (a live line).

use std::path::Path;
use std::time::{Duration, Instant, SystemTime};

use crate::cli::{session, Format, LineArgs};
use crate::json::{quote, J};
use crate::table;
use crate::{Ctx, Error};

/// The list of records a report's CSV is made of (`None`: the report is one row).
fn records_of(cmd: &str) -> Option<&'static str> {
    match cmd.split_whitespace().next() {
        Some("history") => Some("history"),
        Some("faults") => Some("faults"),
        Some("measurements") => Some("readings"),
        _ => None,
    }
}

/// One report: `cmd --json` from the board, printed as `f` asks.
pub fn report(line: &LineArgs, ctx: &mut Ctx, cmd: &str, f: Format) -> Result<i32, Error> {
    let mut s = session(line, ctx)?;
    let (raw, j) = s.json_line(cmd)?;
    s.close();
    let text = if f.json {
        format!("{raw}\n")
    } else if f.csv {
        match records_of(cmd) {
            Some(list) => match j.get(list) {
                Some(J::Arr(items)) => table::rows_csv(items, !f.no_header),
                _ => table::rows_csv(&[], !f.no_header),
            },
            None => table::flat_csv(&j, &[], !f.no_header),
        }
    } else {
        human(cmd, &j)
    };
    write_out(ctx, &text)?;
    Ok(0)
}

/// A report for a person.
fn human(cmd: &str, j: &J) -> String {
    match (records_of(cmd), j) {
        // `history` is its records only.
        (Some("history"), _) => match j.get("history") {
            Some(J::Arr(items)) if items.is_empty() => "no completed cycles recorded\n".into(),
            Some(J::Arr(items)) => table::rows_table(items),
            _ => table::key_values(j),
        },
        _ => table::key_values(j),
    }
}

fn write_out(ctx: &mut Ctx, text: &str) -> Result<(), Error> {
    ctx.out
        .write_all(text.as_bytes())
        .and_then(|_| ctx.out.flush())
        .map_err(|e| Error::File(format!("stdout: {e}")))
}

/// `version`: a sentence, or the board's JSON.
pub fn version(line: &LineArgs, ctx: &mut Ctx, json: bool) -> Result<i32, Error> {
    let mut s = session(line, ctx)?;
    let (raw, j) = s.json_line("version")?;
    s.close();
    let text = if json {
        format!("{raw}\n")
    } else {
        table::key_values(&j)
    };
    write_out(ctx, &text)?;
    Ok(0)
}

/// Now, as RFC 3339 (UTC, seconds).
pub fn now_text() -> String {
    humantime::format_rfc3339_seconds(SystemTime::now()).to_string()
}

/// `export FILE`: everything a maintenance record needs from one machine, one JSON
/// document: the tool and the time, the line, the firmware (`version`), the machine's
/// state (`status`), the cone's wear with the estimate and its band (`wear`), the last
/// 100 cycles (`history`), the faults, the micrometer readings; the docking signatures
/// (issue 34: `signatures`: the newest docking's curve since the board's boot, the
/// cone's reference, the NOK curves kept, newest first; `null` where the board has
/// none). Each report is the board's own JSON, its numbers as it wrote them.
pub fn export(line: &LineArgs, ctx: &mut Ctx, file: &Path) -> Result<i32, Error> {
    let mut s = session(line, ctx)?;
    let link = s.link_name();
    let mut doc: Vec<(String, J)> = vec![
        ("format".into(), J::Str("dockctl-export-1".into())),
        (
            "tool".into(),
            J::Obj(vec![
                ("name".into(), J::Str("dockctl".into())),
                ("version".into(), J::Str(env!("CARGO_PKG_VERSION").into())),
            ]),
        ),
        ("time".into(), J::Str(now_text())),
        ("line".into(), J::Str(link)),
    ];
    let version = s.json("version")?;
    let wear = s.json("wear")?;
    // The machine's identity: the product and its firmware, the unit's serial where the
    // firmware reports one, the cone installed.
    let field = |j: &J, k: &str| j.get(k).cloned().unwrap_or(J::Null);
    doc.push((
        "identity".into(),
        J::Obj(vec![
            ("product".into(), field(&version, "name")),
            ("unit".into(), field(&version, "unit")),
            ("firmware".into(), field(&version, "version")),
            ("cone".into(), field(&wear, "cone")),
            ("cone_material".into(), field(&wear, "material")),
            ("cone_serial".into(), field(&wear, "serial")),
        ]),
    ));
    doc.push(("version".into(), version));
    doc.push(("status".into(), s.json("status")?));
    doc.push(("wear".into(), wear));
    let history = s.json(&format!(
        "history {}",
        docking_logic::console::parse::HISTORY_MAX
    ))?;
    doc.push((
        "history".into(),
        history.get("history").cloned().unwrap_or(J::Arr(vec![])),
    ));
    doc.push(("faults".into(), s.json("faults")?));
    doc.push(("measurements".into(), s.json("measurements")?));
    // A curve the board does not have is its one-line error: null here.
    let mut curve = |which: &str| match s.json(&format!("curve {which}")) {
        Err(Error::Board(_)) => Ok(J::Null),
        r => r,
    };
    let last = curve("last")?;
    let reference = curve("ref")?;
    let mut nok = Vec::new();
    for n in 1..=4 {
        match curve(&format!("nok {n}"))? {
            J::Null => break,
            j => nok.push(j),
        }
    }
    doc.push((
        "signatures".into(),
        J::Obj(vec![
            ("last".into(), last),
            ("reference".into(), reference),
            ("nok".into(), J::Arr(nok)),
        ]),
    ));
    let left = s.close();
    let text = J::Obj(doc).to_pretty();
    if file.as_os_str() == "-" {
        write_out(ctx, &text)?;
    } else {
        std::fs::write(file, &text)
            .map_err(|e| Error::File(format!("cannot write {}: {e}", file.display())))?;
        let _ = writeln!(
            ctx.err,
            "exported to {} ({} bytes)",
            file.display(),
            text.len()
        );
    }
    for l in left {
        let _ = writeln!(ctx.err, "dockctl: {l}");
    }
    Ok(0)
}

/// The live line's fields: (key, label).
const WATCH: [(&str, &str); 7] = [
    ("state", ""),
    ("phase", "phase "),
    ("force_n", ""),
    ("pos_mm", ""),
    ("cycles_completed", "cycles "),
    ("fault", "fault "),
    ("maintenance", "maint "),
];

/// One status reading as a short line.
fn watch_line(j: &J) -> String {
    let mut parts = Vec::new();
    for (k, label) in WATCH {
        let Some(v) = j.get(k) else { continue };
        let (_, unit) = table::label_unit(k);
        let mut p = format!("{label}{}", v.plain());
        if !unit.is_empty() && !matches!(v, J::Null) {
            p.push(' ');
            p.push_str(unit);
        }
        parts.push(p);
    }
    parts.join("  ")
}

/// `watch`: `status` a few times a second until Ctrl-C; on a terminal one line
/// rewritten in place, else one JSON line per reading (the time first, then the
/// board's fields).
pub fn watch(line: &LineArgs, ctx: &mut Ctx, every: Duration) -> Result<i32, Error> {
    let mut s = session(line, ctx)?;
    let mut readings = 0u64;
    let result = loop {
        let t = Instant::now();
        let j = match s.json("status") {
            Ok(j) => j,
            Err(Error::Interrupted) => break Ok(()),
            Err(e) => break Err(e),
        };
        readings += 1;
        let text = if ctx.out_tty {
            format!("\r\x1b[K{}", watch_line(&j))
        } else {
            let J::Obj(mut f) = j else { continue };
            f.insert(0, ("time".into(), J::Str(now_millis())));
            format!("{}\n", J::Obj(f).to_json())
        };
        if ctx
            .out
            .write_all(text.as_bytes())
            .and_then(|_| ctx.out.flush())
            .is_err()
        {
            break Ok(()); // the reader went away (a closed pipe)
        }
        while t.elapsed() < every {
            if crate::console::cancelled(&ctx.cancel) {
                break;
            }
            std::thread::sleep(Duration::from_millis(20));
        }
        if crate::console::cancelled(&ctx.cancel) {
            break Ok(());
        }
    };
    let left = s.close();
    if ctx.out_tty {
        let _ = writeln!(ctx.out);
    }
    for l in left {
        let _ = writeln!(ctx.err, "dockctl: {l}");
    }
    result.map(|_| {
        let _ = readings;
        0
    })
}

fn now_millis() -> String {
    humantime::format_rfc3339_millis(SystemTime::now()).to_string()
}

/// A JSON string (for the update's result).
pub fn jstr(s: &str) -> String {
    quote(s)
}
