//! `cargo xtask docs`: every command the docs show, smoke-run with short arguments, so a
//! command that stops working (a renamed flag, a moved file) fails CI instead of a
//! reader.
//!
//! The commands are the lines of the ```` ```sh ```` blocks of `README.md` and
//! `docs/*.md` (a `\` continues a line; `$ ` marks a command in a transcript, whose other
//! lines are output; `cd DIR` sets the directory of the page's later lines). A
//! synopsis is run in its shortest form: optional `[…]` groups dropped, placeholders
//! filled ([`fill`]); long runs are shortened ([`shorten`]); servers get `--for 2`. What
//! is not run says why ([`skip_reason`]): the probe's command is only built, CI's own
//! steps (the tests, the firmware build) are not run twice, and measurements that take
//! minutes are left to `cargo xtask measure`.

use std::path::Path;

/// One command the docs show.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DocCommand {
    /// The page and line it is on.
    pub at: String,
    /// The directory it runs in, relative to the root.
    pub dir: String,
    /// The command as shown (continuations joined).
    pub shown: String,
}

/// The commands of one page's ```` ```sh ```` blocks.
pub fn commands(page: &str, text: &str) -> Vec<DocCommand> {
    // The blocks: (first line number, lines).
    let mut blocks: Vec<(usize, Vec<&str>)> = Vec::new();
    let mut current: Option<(usize, Vec<&str>)> = None;
    for (i, raw) in text.lines().enumerate() {
        let line = raw.trim();
        match current.as_mut() {
            None if line == "```sh" || line == "```bash" => current = Some((i + 2, Vec::new())),
            None => {}
            Some(_) if line.starts_with("```") => blocks.extend(current.take()),
            Some((_, lines)) => lines.push(line),
        }
    }
    let mut out = Vec::new();
    // A reader who typed `cd DIR` stays there for the rest of the page.
    let mut dir = String::from(".");
    for (first, lines) in blocks {
        // In a transcript only `$ ` lines are commands; the rest is output.
        let transcript = lines.iter().any(|l| l.starts_with("$ "));
        let mut pending: Option<(usize, String)> = None;
        for (k, line) in lines.iter().enumerate() {
            let (start, cmd) = match pending.take() {
                Some((start, so_far)) => (start, format!("{so_far} {line}")),
                None => {
                    let line = match (transcript, line.strip_prefix("$ ")) {
                        (true, Some(c)) => c,
                        (true, None) => continue,
                        (false, _) => line,
                    };
                    if line.is_empty() || line.starts_with('#') {
                        continue;
                    }
                    (first + k, line.to_string())
                }
            };
            if let Some(head) = cmd.strip_suffix('\\') {
                pending = Some((start, head.trim_end().to_string()));
                continue;
            }
            let cmd = strip_comment(&cmd);
            if let Some(d) = cmd.strip_prefix("cd ") {
                dir = change_dir(&dir, d.trim());
                continue;
            }
            out.push(DocCommand {
                at: format!("{page}:{start}"),
                dir: dir.clone(),
                shown: cmd,
            });
        }
    }
    out
}

/// `cd to` from `dir`, both relative to the root (`..` steps back; `.` is the root).
fn change_dir(dir: &str, to: &str) -> String {
    let mut parts: Vec<&str> = dir
        .split('/')
        .filter(|p| !p.is_empty() && *p != ".")
        .collect();
    for p in to.split('/') {
        match p {
            "" | "." => {}
            ".." => {
                parts.pop();
            }
            p => parts.push(p),
        }
    }
    if parts.is_empty() {
        ".".into()
    } else {
        parts.join("/")
    }
}

/// A command without its trailing `# comment`.
fn strip_comment(cmd: &str) -> String {
    match cmd.find(" #") {
        Some(at) => cmd[..at].trim_end().to_string(),
        None => cmd.trim_end().to_string(),
    }
}

/// Why a shown command is not run, or `None` when it is.
pub fn skip_reason(cmd: &str) -> Option<&'static str> {
    let c = cmd.trim();
    if c.starts_with("bash tools/flash-board.sh") {
        return Some("needs a probe; its images are built by CI's firmware and bootloader steps");
    }
    if c.starts_with("cargo board") {
        return Some("needs a probe; its image is built by `cargo build --release --target …`");
    }
    if c.starts_with("cargo test") {
        return Some("CI's own test step");
    }
    if c.starts_with("cargo build --release --target thumbv7em-none-eabihf") {
        return Some("CI's own firmware build step");
    }
    if c.starts_with("bash tools/life-ratio.sh") || c.starts_with("bash tools/figures.sh") {
        return Some("a measurement of minutes: `cargo xtask measure`");
    }
    if c.starts_with("picocom") || c.starts_with("nc ") {
        return Some("a terminal for a person");
    }
    if c.starts_with("cargo install --path dockctl") {
        return Some("installs into ~/.cargo/bin; dockctl is built and tested by CI's test step");
    }
    if c.starts_with("dockctl ") {
        return Some("needs a board on a serial port; dockctl/tests and vboard/tests/dockctl.rs run it against the simulators");
    }
    if c.starts_with("for n in") && c.contains("valgrind") {
        return Some("needs valgrind; a measurement");
    }
    if !(c.starts_with("cargo ") || c.starts_with("bash tools/")) {
        return Some("not this project's program");
    }
    None
}

/// The shortest form of a synopsis: optional groups dropped, placeholders filled.
pub fn fill(cmd: &str) -> String {
    // Drop `[…]` groups (nested too).
    let mut out = String::new();
    let mut depth = 0u32;
    for ch in cmd.chars() {
        match ch {
            '[' => depth += 1,
            ']' => depth = depth.saturating_sub(1),
            _ if depth == 0 => out.push(ch),
            _ => {}
        }
    }
    out.split_whitespace()
        .map(|w| match w {
            "NAME" => "nominal",
            "N" => "3",
            "SECONDS" => "2",
            "127.0.0.1:PORT" => "127.0.0.1:0",
            other => other,
        })
        .collect::<Vec<_>>()
        .join(" ")
}

/// Long runs shortened: cycles cut to a handful (a `--at` list scaled with them), a
/// sweep to one scene at one seed at CPI 1, a server stopped after 2 s.
pub fn shorten(cmd: &str) -> String {
    let words: Vec<&str> = cmd.split_whitespace().collect();
    let mut out: Vec<String> = Vec::new();
    let mut i = 0;
    let mut scale = 1u64;
    while i < words.len() {
        let w = words[i];
        if w == "--cycles" {
            if let Some(n) = words.get(i + 1).and_then(|v| v.parse::<u64>().ok()) {
                let short = n.min(20);
                scale = n.div_ceil(short.max(1));
                out.push(w.into());
                out.push(short.to_string());
                i += 2;
                continue;
            }
        }
        out.push(w.into());
        i += 1;
    }
    // A `--at` list of cycles follows the shortened count.
    if scale > 1 {
        if let Some(p) = out.iter().position(|w| w == "--at") {
            if let Some(list) = out.get(p + 1) {
                let scaled: Vec<String> = list
                    .split(',')
                    .filter_map(|v| v.parse::<u64>().ok())
                    .map(|v| (v / scale).max(1).to_string())
                    .collect();
                out[p + 1] = scaled.join(",");
            }
        }
    }
    let has = |out: &[String], word: &str| out.iter().any(|w| w == word);
    if has(&out, "sweep") && !has(&out, "--seeds") {
        out.extend(
            [
                "--scene", "estop", "--seeds", "1..1", "--cpi", "1", "--timing", "cpi",
            ]
            .map(String::from),
        );
    }
    if has(&out, "serve") && !has(&out, "--for") {
        out.extend(["--for", "2"].map(String::from));
    }
    out.join(" ")
}

/// Every command of the README and docs/, with what to run (or why not).
pub fn plan(root: &Path) -> Vec<(DocCommand, Result<String, &'static str>)> {
    let mut pages = vec![root.join("README.md")];
    if let Ok(entries) = std::fs::read_dir(root.join("docs")) {
        let mut md: Vec<_> = entries
            .flatten()
            .map(|e| e.path())
            .filter(|p| p.extension().is_some_and(|x| x == "md"))
            .collect();
        md.sort();
        pages.extend(md);
    }
    let mut out = Vec::new();
    for page in pages {
        let Ok(text) = std::fs::read_to_string(&page) else {
            continue;
        };
        let name = page
            .strip_prefix(root)
            .unwrap_or(&page)
            .display()
            .to_string();
        for c in commands(&name, &text) {
            let run = match skip_reason(&c.shown) {
                Some(why) => Err(why),
                None => Ok(shorten(&fill(&c.shown))),
            };
            out.push((c, run));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_synopsis_runs_in_its_shortest_form() {
        let shown = "cargo run --release -p hil-sim -- scene NAME [--cycles N] [--rate 10|80] [--model eq7|plant [--mass-kg M]] --json";
        assert_eq!(
            fill(shown),
            "cargo run --release -p hil-sim -- scene nominal --json"
        );
        assert_eq!(
            shorten(&fill(
                "cargo run --release -- serve [--pty | --tcp 127.0.0.1:PORT] --tcp 127.0.0.1:PORT"
            )),
            "cargo run --release -- serve --tcp 127.0.0.1:0 --for 2"
        );
    }

    #[test]
    fn cd_is_relative_to_where_the_reader_is() {
        assert_eq!(change_dir(".", "boot"), "boot");
        assert_eq!(change_dir("boot", "../vboard"), "vboard");
        assert_eq!(change_dir("vboard", ".."), ".");
    }

    #[test]
    fn long_runs_are_shortened_with_their_at_list() {
        assert_eq!(
            shorten(
                "hil-sim -- life --cycles 20000 --at 1000,5000,10000,15000,20000 --readings f.csv"
            ),
            "hil-sim -- life --cycles 20 --at 1,5,10,15,20 --readings f.csv"
        );
        assert_eq!(
            shorten("vboard -- sweep --flood"),
            "vboard -- sweep --flood --scene estop --seeds 1..1 --cpi 1 --timing cpi"
        );
    }

    #[test]
    fn blocks_transcripts_continuations_and_cd_are_read_as_a_reader_would() {
        let page = "text\n```sh\ncargo build --release --target thumbv7em-none-eabihf   # the image\ncd vboard\ncargo run --release -- scene NAME [--cycles N] \\\n    [--json]\n```\n```\nnot a command\n```\n```sh\n$ cargo run -- serve --pty\n/dev/pts/7\n$ picocom -b 115200 /dev/pts/7\n```\n";
        let c = commands("p.md", page);
        let shown: Vec<(&str, &str)> = c
            .iter()
            .map(|c| (c.dir.as_str(), c.shown.as_str()))
            .collect();
        assert_eq!(
            shown,
            [
                (".", "cargo build --release --target thumbv7em-none-eabihf"),
                (
                    "vboard",
                    "cargo run --release -- scene NAME [--cycles N] [--json]"
                ),
                ("vboard", "cargo run -- serve --pty"),
                ("vboard", "picocom -b 115200 /dev/pts/7"),
            ]
        );
        assert_eq!(c[1].at, "p.md:5");
        assert!(skip_reason(&c[0].shown).is_some());
        assert!(skip_reason(&c[1].shown).is_none());
        assert!(skip_reason(&c[3].shown).is_some());
    }
}
