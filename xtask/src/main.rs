//! `cargo xtask`: the project's tasks in one place (the cargo-xtask convention: a plain
//! Rust program in the workspace, run through the alias in `.cargo/config.toml`).
//!
//! ```text
//! cargo xtask ci           what CI runs after .ci/run has installed the system packages:
//!                          fmt, clippy (host, thumb, QEMU image, vboard), rustdoc, the
//!                          README's test command, the firmware build and its size budget,
//!                          the odometer on QEMU against the host, the virtual board
//! cargo xtask size         build the image; the size policy (docs/board.md, "Flash and
//!                          size"): the update file within ACTIVE, the reserve, the
//!                          growth against tools/size-baseline.txt, static RAM; the
//!                          updater's cost; the biggest functions (tools/size-report.py)
//! cargo xtask size --record   the same, then record the image as the new baseline
//! cargo xtask boot         the bootloader (boot/): clippy, host tests, build, size
//! cargo xtask qemu         the odometer on a Cortex-M4 (QEMU) compared bit for bit
//! cargo xtask vboard       the virtual board's clippy, tests and boot scene
//! cargo xtask docs         every command the docs show, smoke-run with short arguments
//! cargo xtask measure      docs/measurements.md (tools/figures.sh; --sweep for the sweep)
//! cargo xtask opt-levels   the opt-level measurement (tools/opt-levels.sh)
//! ```
//!
//! Every task exits non-zero when it fails; `ci` runs every step, then fails if any did,
//! and ends with `N passed, N failed (Ts)` counted from the test binaries' summaries.

mod docs;

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Command, ExitCode, Stdio};
use std::time::Instant;

/// The firmware's target.
const TARGET: &str = "thumbv7em-none-eabihf";
/// Static RAM budget (SRAM above the 24 KiB stack: 32 KiB for .data, .bss, .uninit).
const RAM_BUDGET: u64 = 32 * 1024;
/// The bootloader's flash: sector 0 (update-layout's `BOOT_LEN`; sector 1 is its state).
const BOOT_BUDGET: u64 = update_layout::layout::BOOT_LEN as u64;
/// The reserve (issue 31): the image may take at most this share of what an update can
/// carry (`UPDATE_IMAGE_MAX`), per cent; the rest (about 64 KiB in layout C) is kept for
/// the fixes of boards whose layout can never change.
const RESERVE_PCT: u64 = 75;
/// The regression check (issue 31): growth over the recorded baseline that needs a
/// commit saying why (a `Size-growth:` trailer), bytes.
const GROWTH_LIMIT: u64 = 2 * 1024;
/// The size baseline: the image's per-symbol sizes at a commit (tools/size-report.py
/// --record; `cargo xtask size --record` writes it).
const BASELINE: &str = "tools/size-baseline.txt";
/// The trailer a commit gives its reason for growth in.
const GROWTH_TRAILER: &str = "Size-growth:";

const USAGE: &str =
    "usage: cargo xtask <ci | size [--record] | boot | qemu | vboard | docs | measure [--sweep] | opt-levels [LEVELS...]>";

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let root = root();
    let mut x = Xtask {
        root,
        t0: Instant::now(),
        cpu0: busy_cpu_s(),
        passed: 0,
        failed: 0,
    };
    let ok = match args.first().map(String::as_str) {
        Some("ci") if args.len() == 1 => x.ci(),
        Some("size") if args.len() == 1 => x.size(),
        Some("size") if args.len() == 2 && args[1] == "--record" => x.size() && x.record_size(),
        Some("qemu") if args.len() == 1 => x.qemu(),
        Some("boot") if args.len() == 1 => x.boot(),
        Some("vboard") if args.len() == 1 => x.vboard(),
        Some("docs") if args.len() == 1 => x.docs(),
        Some("measure") => x.script("tools/figures.sh", &args[1..]),
        Some("opt-levels") => x.script("tools/opt-levels.sh", &args[1..]),
        Some("-h" | "--help" | "help") => {
            println!("{USAGE}");
            return ExitCode::SUCCESS;
        }
        _ => {
            eprintln!("xtask: {USAGE}");
            return ExitCode::from(2);
        }
    };
    if ok {
        ExitCode::SUCCESS
    } else {
        ExitCode::FAILURE
    }
}

/// The repository's root (xtask's manifest is one level below it).
fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."))
}

/// The machine's busy CPU time so far, in seconds (`/proc/stat`'s first line: user,
/// nice, system, irq, softirq and steal ticks at 100 a second); `None` where there is
/// no such file.
fn busy_cpu_s() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/stat").ok()?;
    let ticks: Vec<u64> = stat
        .lines()
        .next()?
        .split_whitespace()
        .skip(1)
        .filter_map(|f| f.parse().ok())
        .collect();
    let busy: u64 = [0, 1, 2, 5, 6, 7]
        .iter()
        .filter_map(|&i| ticks.get(i))
        .sum();
    Some(busy as f64 / 100.0)
}

struct Xtask {
    root: PathBuf,
    t0: Instant,
    /// [`busy_cpu_s`] at the start.
    cpu0: Option<f64>,
    /// Tests passed and failed, summed over every `test result:` line seen.
    passed: u64,
    failed: u64,
}

impl Xtask {
    /// A step's header: the time since the start, and the machine's CPU time since the
    /// start (every process's, from `/proc/stat`: on a machine running nothing else,
    /// CI's own; the difference between two headers is what a step cost the cores).
    fn step(&self, what: &str) {
        let cpu = self
            .cpu_since_start()
            .map_or(String::new(), |c| format!(", {c:.0} s of CPU"));
        println!("\n=== {what} ({}s{cpu})", self.t0.elapsed().as_secs());
    }

    /// The machine's busy CPU time since the start, s ([`busy_cpu_s`]).
    fn cpu_since_start(&self) -> Option<f64> {
        Some(busy_cpu_s()? - self.cpu0?)
    }

    /// A command in `dir` (relative to the root), its output shown as it comes.
    fn run(&self, dir: &str, program: &str, args: &[&str], env: &[(&str, &str)]) -> bool {
        let mut c = Command::new(program);
        c.args(args).current_dir(self.root.join(dir));
        for (k, v) in env {
            c.env(k, v);
        }
        match c.status() {
            Ok(s) => s.success(),
            Err(e) => {
                eprintln!("xtask: {program}: {e}");
                false
            }
        }
    }

    /// A command's standard output (standard error shown), or `None` when it failed.
    fn output(&self, dir: &str, program: &str, args: &[&str]) -> Option<String> {
        let o = Command::new(program)
            .args(args)
            .current_dir(self.root.join(dir))
            .stderr(Stdio::inherit())
            .output()
            .ok()?;
        o.status
            .success()
            .then(|| String::from_utf8_lossy(&o.stdout).into_owned())
    }

    /// A test command: its output shown line by line and its summaries counted.
    fn tests(&mut self, dir: &str, args: &[&str]) -> bool {
        let child = Command::new("cargo")
            .args(args)
            .current_dir(self.root.join(dir))
            .stdout(Stdio::piped())
            .spawn();
        let mut child = match child {
            Ok(c) => c,
            Err(e) => {
                eprintln!("xtask: cargo: {e}");
                return false;
            }
        };
        if let Some(out) = child.stdout.take() {
            for line in BufReader::new(out).lines().map_while(Result::ok) {
                println!("{line}");
                if let Some((p, f)) = test_summary(&line) {
                    self.passed += p;
                    self.failed += f;
                }
            }
        }
        child.wait().is_ok_and(|s| s.success())
    }

    fn ci(&mut self) -> bool {
        let mut ok = true;
        // The virtual board's clippy and test build, and the bootloader's release build,
        // start first, in the background at a lower priority: they have target
        // directories of their own (no lock shared), and the steps before the firmware
        // leave cores idle (the host tests run one binary after another, some of them
        // paced to the wall clock: dockctl against the live simulators). Measured on a
        // fresh clone of 5d84fcd with nothing else running: 1 379 s of CPU in 758 s on 2
        // cores, 137 s of it idle; the test step alone left a core idle for 100 s.
        let vboard_build = self.vboard_build_start();
        self.step("format");
        ok &= self.run(".", "cargo", &["fmt", "--all", "--check"], &[]);
        for dir in ["qemu-check", "vboard", "boot"] {
            ok &= self.run(dir, "cargo", &["fmt", "--check"], &[]);
        }

        self.step("clippy (host, all targets)");
        ok &= self.run(
            ".",
            "cargo",
            &[
                "clippy",
                "--workspace",
                "--all-targets",
                "--",
                "-D",
                "warnings",
            ],
            &[],
        );
        self.step(&format!(
            "clippy ({TARGET}, firmware and the QEMU check image)"
        ));
        ok &= self.run(
            ".",
            "cargo",
            &[
                "clippy",
                "-p",
                "docking-controller",
                "-p",
                "docking-logic",
                "--target",
                TARGET,
                "--",
                "-D",
                "warnings",
            ],
            &[],
        );
        ok &= self.run(
            "qemu-check",
            "cargo",
            &["clippy", "--release", "--", "-D", "warnings"],
            &[],
        );

        self.step("rustdoc of the logic (-D warnings: a broken intra-doc link fails)");
        ok &= self.run(
            ".",
            "cargo",
            &["doc", "--no-deps", "-p", "docking-logic"],
            &[("RUSTDOCFLAGS", "-D warnings")],
        );

        self.step("tests: cargo test --workspace (the README's test command)");
        ok &= self.tests(".", &["test", "--workspace"]);

        ok &= self.size();
        // The virtual board's lanes start as soon as the image, the bootloader and
        // vboard's tests are built, and run beside the steps after them: those are
        // mostly single-threaded (fat-LTO links, QEMU, the docs' commands one at a time),
        // which left a core idle while the lanes waited (issue 33: CI in 10 minutes).
        let lanes = self.vboard_lanes_start(vboard_build);
        ok &= lanes.is_some();
        ok &= self.boot();
        ok &= self.qemu();
        ok &= self.docs();
        ok &= self.vboard_lanes_join(lanes);

        let cpu = self.cpu_since_start().map_or(String::new(), |c| {
            format!(", {c:.0} s of the machine's CPU")
        });
        println!(
            "\n{} passed, {} failed ({}s{cpu})",
            self.passed,
            self.failed,
            self.t0.elapsed().as_secs()
        );
        ok
    }

    /// The README's firmware build, then the size policy (issue 31, docs/board.md "Flash
    /// and size"): hard gates only at real limits, taken from update-layout (the link
    /// within ACTIVE fails the build itself; the update file within
    /// `UPDATE_IMAGE_MAX`), the reserve ([`RESERVE_PCT`]), the growth against the
    /// baseline ([`GROWTH_LIMIT`]) and the static RAM; the updater's cost printed.
    fn size(&mut self) -> bool {
        self.step("firmware release build (the README's command)");
        if !self.run(
            ".",
            "cargo",
            &["build", "--release", "--target", TARGET],
            &[],
        ) {
            return false;
        }
        let elf = format!("target/{TARGET}/release/docking-controller");
        self.step(&format!("size report ({elf})"));
        let Some(report) = self.output(".", "size", &["-A", &elf]) else {
            return false;
        };
        let s = Sections::of(&report);
        println!(
            "text {}  data {}  bss {}  =>  flash {} B, static RAM {} / {} bytes",
            s.text,
            s.data,
            s.bss,
            s.flash(),
            s.ram(),
            RAM_BUDGET
        );
        // Where it goes (issue 20): the 20 biggest symbols.
        self.run(
            ".",
            "python3",
            &["tools/size-report.py", "-n", "20", "--no-groups", &elf],
            &[],
        );
        let mut ok = self.update_file_fits(&elf);
        ok &= self.growth(&elf, s.flash());
        ok &= self.updater_cost(s.flash());
        if s.ram() > RAM_BUDGET {
            println!("FAIL: static RAM use over budget");
            ok = false;
        }
        ok
    }

    /// Whether the image can be delivered by a field update, and keeps the reserve: its
    /// update file (what `tools/sign-image.sh` writes and `update` receives into DFU) is
    /// the image's bytes as `llvm-objcopy -O binary` gives them (from ACTIVE's first
    /// address to the end of `.data`'s load image, alignment gaps included), padded to
    /// whole words, then the trailer. The flash figure counts the sections, not their
    /// span, and not the trailer: an image under the limit by that figure could link and
    /// still be refused by `update` ("file larger than ACTIVE").
    fn update_file_fits(&mut self, elf: &str) -> bool {
        use update_layout::layout::{LAYOUT, TRAILER_LEN, UPDATE_IMAGE_MAX};
        let bin = format!("{elf}.bin");
        let objcopy = ["llvm-objcopy", "llvm-objcopy-14"]
            .into_iter()
            .find(|c| Command::new(c).arg("--version").output().is_ok());
        let Some(objcopy) = objcopy else {
            println!("FAIL: llvm-objcopy not found (apt-get install llvm): the update file's size is not known");
            return false;
        };
        if !self.run(".", objcopy, &["-O", "binary", elf, &bin], &[]) {
            return false;
        }
        let Ok(len) = std::fs::metadata(&bin).map(|m| m.len()) else {
            println!("FAIL: no {bin}");
            return false;
        };
        let image = len.div_ceil(4) * 4;
        let max = u64::from(UPDATE_IMAGE_MAX);
        let reserve_at = max * RESERVE_PCT / 100;
        println!(
            "update file: {image} B image + {TRAILER_LEN} B trailer (layout {}: the image at most {max} B, {}.{} % of it used; the reserve starts at {RESERVE_PCT} %, {reserve_at} B)",
            LAYOUT.name(),
            image * 100 / max,
            image * 1000 / max % 10,
        );
        if image > max {
            println!("FAIL: the image ({image} B) is larger than an update can carry ({max} B): `update` would refuse it");
            return false;
        }
        if image > reserve_at {
            println!("FAIL: the image ({image} B) is in the reserve (over {RESERVE_PCT} % of {max} B): the reserve is kept for the fixes of boards in the field; the layout is reconsidered, not the reserve (docs/board.md, \"Flash and size\")");
            return false;
        }
        true
    }

    /// The regression check: the image against the recorded baseline ([`BASELINE`]),
    /// function by function; growth over [`GROWTH_LIMIT`] fails unless a commit since
    /// the baseline's says why in a [`GROWTH_TRAILER`] trailer.
    fn growth(&mut self, elf: &str, flash: u64) -> bool {
        let Ok(text) = std::fs::read_to_string(self.root.join(BASELINE)) else {
            println!("FAIL: no {BASELINE} (record one: cargo xtask size --record)");
            return false;
        };
        let header = text.lines().next().unwrap_or("");
        let word_after = |key: &str| {
            let mut w = header.split_whitespace();
            w.find(|x| *x == key).and(w.next()).map(str::to_string)
        };
        let (Some(commit), Some(base)) = (
            word_after("commit"),
            word_after("flash").and_then(|f| f.parse::<u64>().ok()),
        ) else {
            println!("FAIL: {BASELINE} has no '# ... commit C flash N' line");
            return false;
        };
        println!("growth against the baseline ({BASELINE}, commit {commit}):");
        self.run(
            ".",
            "python3",
            &[
                "tools/size-report.py",
                "-n",
                "12",
                "--baseline",
                BASELINE,
                elf,
            ],
            &[],
        );
        let grown = flash.saturating_sub(base);
        if grown <= GROWTH_LIMIT {
            println!("growth {grown} B: within {GROWTH_LIMIT} B");
            return true;
        }
        // The commits since the baseline's (all of them, when it is not an ancestor).
        let range = format!("{commit}..HEAD");
        let log = self
            .output(".", "git", &["log", "--format=%B", &range])
            .or_else(|| self.output(".", "git", &["log", "--format=%B", "-n", "200"]))
            .unwrap_or_default();
        let why = growth_reasons(&log);
        if why.is_empty() {
            println!("FAIL: the image grew {grown} B over the baseline (over {GROWTH_LIMIT} B) and no commit since {commit} says why: add a '{GROWTH_TRAILER} <why>' trailer to the commit that grows it, or record a new baseline where the growth was agreed (cargo xtask size --record)");
            return false;
        }
        println!("growth {grown} B over {GROWTH_LIMIT} B, said why:");
        for w in why {
            println!("  {}", w.trim());
        }
        true
    }

    /// Record the image just built as the size baseline.
    fn record_size(&mut self) -> bool {
        let elf = format!("target/{TARGET}/release/docking-controller");
        self.run(
            ".",
            "python3",
            &["tools/size-report.py", "--record", BASELINE, &elf],
            &[],
        )
    }

    /// The updater's cost (a figure, no gate since issue 31): the image without it
    /// (`--no-default-features`, copied to `target/lean`; the image every other step
    /// runs stays the README's) against the image.
    fn updater_cost(&mut self, flash: u64) -> bool {
        self.step("firmware without the updater (--no-default-features, copied to target/lean): the updater's cost");
        // In the same target directory: cargo keeps each feature set's artifacts apart
        // (the features are in their hashes), so only the two crates the feature changes
        // are built, not every dependency again (138 s of a fresh clone's CI in a
        // directory of its own); the README's image is put back by the same build after.
        let build = |x: &mut Self, extra: &[&str]| {
            let mut args = vec!["build", "--release", "--target", TARGET];
            args.extend_from_slice(extra);
            x.run(".", "cargo", &args, &[])
        };
        let built = format!("target/{TARGET}/release/docking-controller");
        let elf = format!("target/lean/{TARGET}/release/docking-controller");
        let copied = build(self, &["--no-default-features"])
            && std::fs::create_dir_all(format!("target/lean/{TARGET}/release")).is_ok()
            && std::fs::copy(&built, &elf).is_ok();
        // The README's image back in place for every later step (cargo's cache: no
        // compiling), whether or not the lean build worked.
        if !build(self, &[]) || !copied {
            return false;
        }
        let Some(report) = self.output(".", "size", &["-A", &elf]) else {
            return false;
        };
        let lean = Sections::of(&report).flash();
        println!(
            "the updater costs {} B of flash (the image {flash} B, without the updater {lean} B: {elf})",
            flash.saturating_sub(lean)
        );
        true
    }

    /// The bootloader (boot/, issue 21): clippy, its host tests (the swap and the revert
    /// under power cuts at every flash operation), its release build and its size
    /// against sector 0.
    fn boot(&mut self) -> bool {
        self.step("bootloader (boot/): clippy, host tests, release build, size against sector 0");
        let mut ok = self.run(
            "boot",
            "cargo",
            &["clippy", "--release", "--", "-D", "warnings"],
            &[],
        );
        let host = self
            .output(".", "rustc", &["-vV"])
            .and_then(|v| {
                v.lines()
                    .find_map(|l| l.strip_prefix("host: ").map(str::to_string))
            })
            .unwrap_or_default();
        ok &= self.tests("boot", &["test", "--lib", "--target", &host]);
        if !self.run("boot", "cargo", &["build", "--release"], &[]) {
            return false;
        }
        let elf = format!("boot/target/{TARGET}/release/docking-boot");
        let Some(report) = self.output(".", "size", &["-A", &elf]) else {
            return false;
        };
        let s = Sections::of(&report);
        println!(
            "bootloader: flash {} / {} bytes (sector 0, update-layout's BOOT_LEN), RAM {} bytes (CCM)",
            s.flash(),
            BOOT_BUDGET,
            s.ram()
        );
        if s.flash() > BOOT_BUDGET {
            println!("FAIL: the bootloader is over sector 0");
            ok = false;
        }
        ok
    }

    fn qemu(&mut self) -> bool {
        self.step("odometer bit for bit: host vs Cortex-M4 (QEMU mps2-an386)");
        let host = self.output(
            ".",
            "cargo",
            &[
                "run",
                "-q",
                "--release",
                "-p",
                "hil-sim",
                "--",
                "odometer-reference",
                "--cycles",
                "300",
            ],
        );
        let m4 = self.output(
            "qemu-check",
            "timeout",
            &["300", "cargo", "run", "-q", "--release"],
        );
        let host = host.unwrap_or_default();
        let m4 = m4.unwrap_or_default();
        // The image's own run-time functions, checked first on the M4, each in one line
        // qemu-check prints: memcpy and memclr (src/board/mem.rs), then the 64-bit
        // division (src/board/div.rs).
        for (report, what) in [
            ("memcpy and memclr", "memcpy or memclr"),
            ("64-bit division", "64-bit division"),
        ] {
            let line = m4.lines().find(|l| l.starts_with(report)).map_or_else(
                || format!("{report}: no report (hung or failed to build)"),
                |l| l.trim().to_string(),
            );
            println!("m4:   {line}");
            if !line.ends_with("cases ok") {
                println!("FAIL: the image's {what} on the Cortex-M4");
                return false;
            }
        }
        let host = host.lines().next().unwrap_or("").trim();
        let m4 = m4
            .lines()
            .find(|l| l.starts_with("odometer reference:"))
            .unwrap_or("")
            .trim();
        println!("host: {host}");
        println!("m4:   {m4}");
        if m4.is_empty() || host != m4 {
            println!("FAIL: the odometer differs between host and Cortex-M4");
            return false;
        }
        true
    }

    /// vboard's clippy, then its release test build, then the bootloader's release
    /// build (the board loads it), started in the background at a lower priority (`nice`:
    /// the steps in the foreground first, idle cores to these); their output goes to a
    /// log that [`Self::vboard_lanes_start`] prints.
    fn vboard_build_start(&self) -> Option<(std::process::Child, PathBuf)> {
        let log = self.root.join("vboard/target/xtask-build.log");
        let _ = std::fs::create_dir_all(self.root.join("vboard/target"));
        let file = std::fs::File::create(&log).ok()?;
        let err = file.try_clone().ok()?;
        Command::new("nice")
            .args([
                "-n",
                "10",
                "bash",
                "-c",
                "cargo clippy --release --all-targets -- -D warnings && cargo test --release --no-run && cd ../boot && cargo build --release",
            ])
            .current_dir(self.root.join("vboard"))
            .stdout(file)
            .stderr(err)
            .spawn()
            .ok()
            .map(|c| (c, log))
    }

    /// The virtual board's step in CI, its build already under way: the build waited
    /// for, the bootloader the image is linked behind built (the board loads both), and
    /// vboard's tests started in their lanes on a thread of their own.
    fn vboard_lanes_start(
        &mut self,
        build: Option<(std::process::Child, PathBuf)>,
    ) -> Option<std::thread::JoinHandle<(u64, u64)>> {
        self.step("virtual board: clippy and the test build (started in the background), then the release image against the simulated machine in lanes, beside the steps that follow");
        let built = match build {
            Some((mut child, log)) => {
                let status = child.wait();
                if let Ok(text) = std::fs::read_to_string(&log) {
                    print!("{text}");
                }
                status.is_ok_and(|s| s.success())
            }
            None => false,
        };
        if !built {
            println!("FAIL: vboard's clippy or test build");
            return None;
        }
        self.vboard_lanes_go()
    }

    /// The bootloader the image is linked behind built (the board loads both), then
    /// vboard's tests started in their lanes on a thread of their own.
    fn vboard_lanes_go(&mut self) -> Option<std::thread::JoinHandle<(u64, u64)>> {
        if !self.run("boot", "cargo", &["build", "--release"], &[]) {
            return None;
        }
        let plan = self.lanes_plan("vboard", &["--release"])?;
        Some(std::thread::spawn(move || plan.run()))
    }

    /// The lanes' end, and the boot scene on the release image.
    fn vboard_lanes_join(&mut self, lanes: Option<std::thread::JoinHandle<(u64, u64)>>) -> bool {
        self.step("virtual board: the lanes' end");
        let Some(Ok((passed, failed))) = lanes.map(std::thread::JoinHandle::join) else {
            println!("FAIL: the virtual board's lanes did not run");
            return false;
        };
        self.passed += passed;
        self.failed += failed;
        let scene = self.run(
            "vboard",
            "cargo",
            &["run", "-q", "--release", "--", "scene", "boot"],
            &[],
        );
        failed == 0 && scene
    }

    /// The bootloader the image is linked behind (the board loads both), then vboard's
    /// tests in lanes and its boot scene on the release image.
    fn vboard_tests(&mut self) -> bool {
        let lanes = self.vboard_lanes_go();
        self.vboard_lanes_join(lanes)
    }

    /// The tests of `cargo test ARGS` in `dir`, built and listed, in the lanes' order,
    /// to run each test in a process of its own, as many at a time as the machine has
    /// cores (longest first, [`LONG_FIRST`]): the virtual board's binaries are mostly one
    /// long emulation each, which cargo would run one binary after another with a core
    /// idle. Each test's result and time are printed; its output only when it fails.
    fn lanes_plan(&self, dir: &str, args: &[&str]) -> Option<Lanes> {
        let mut build = vec!["test", "--no-run", "--message-format=json"];
        build.extend_from_slice(args);
        let Some(json) = self.output(dir, "cargo", &build) else {
            println!("FAIL: cargo test --no-run in {dir}");
            return None;
        };
        let mut jobs = Vec::new();
        for exe in executables(&json) {
            let list = |extra: &[&str]| {
                let mut a = vec!["--list", "--format", "terse"];
                a.extend_from_slice(extra);
                self.output(dir, &exe, &a).map(|o| test_names(&o))
            };
            let (Some(all), Some(ignored)) = (list(&[]), list(&["--ignored"])) else {
                println!("FAIL: {exe} --list");
                return None;
            };
            jobs.extend(
                all.into_iter()
                    .filter(|t| !ignored.contains(t))
                    .map(|t| (exe.clone(), t)),
            );
        }
        // Longest first (stable: the rest keep cargo's order).
        jobs.sort_by_key(|(_, t)| {
            LONG_FIRST
                .iter()
                .position(|l| l == t)
                .unwrap_or(LONG_FIRST.len())
        });
        // The tests that talk to a program in wall time, after the lanes, one at a time.
        let (alone, jobs): (Vec<_>, Vec<_>) = jobs
            .into_iter()
            .partition(|(_, t)| ALONE.contains(&t.as_str()));
        let (paced, jobs): (Vec<_>, Vec<_>) = jobs
            .into_iter()
            .partition(|(_, t)| PACED.contains(&t.as_str()));
        Some(Lanes {
            jobs,
            paced,
            alone,
            cwd: self.root.join(dir),
        })
    }

    fn vboard(&mut self) -> bool {
        self.step("virtual board: clippy, then the release image against the simulated machine");
        let clean = self.run(
            "vboard",
            "cargo",
            &[
                "clippy",
                "--release",
                "--all-targets",
                "--",
                "-D",
                "warnings",
            ],
            &[],
        );
        self.vboard_tests() && clean
    }

    /// Every command the docs show, run in its short form (see `docs.rs`).
    fn docs(&mut self) -> bool {
        self.step("the docs' commands, smoke-run with short arguments");
        let mut failed = Vec::new();
        let (mut ran, mut skipped) = (0, 0);
        for (c, run) in docs::plan(&self.root) {
            match run {
                Err(why) => {
                    skipped += 1;
                    println!("skip {}: {} ({why})", c.at, c.shown);
                }
                Ok(cmd) => {
                    ran += 1;
                    let t = Instant::now();
                    let status = Command::new("timeout")
                        .args(["300", "bash", "-c", &cmd])
                        .current_dir(self.root.join(&c.dir))
                        .stdin(Stdio::null())
                        .stdout(Stdio::null())
                        .stderr(Stdio::piped())
                        .output();
                    println!(
                        "run  {} [{}]: {cmd} ({:.1} s)",
                        c.at,
                        c.dir,
                        t.elapsed().as_secs_f64()
                    );
                    match status {
                        Ok(o) if o.status.success() => {}
                        Ok(o) => {
                            let err = String::from_utf8_lossy(&o.stderr);
                            let last = err.lines().last().unwrap_or("").to_string();
                            println!("FAIL {}: {cmd}: {last}", c.at);
                            failed.push(c.at);
                        }
                        Err(e) => {
                            println!("FAIL {}: {cmd}: {e}", c.at);
                            failed.push(c.at);
                        }
                    }
                }
            }
        }
        println!(
            "docs' commands: {ran} run, {} failed, {skipped} not run (reasons above)",
            failed.len()
        );
        failed.is_empty()
    }

    fn script(&self, path: &str, args: &[String]) -> bool {
        let mut all = vec![path];
        all.extend(args.iter().map(String::as_str));
        self.run(".", "bash", &all, &[])
    }
}

/// Virtual-board tests that run after the lanes, alone on the machine (none now). lrzsz's
/// `sb` over `serve --pty` was one: the board ran in emulated time, slower than real
/// time where `sb` waits (the DFU erase polled at 0.05x), and beside another lane's
/// emulation `sb` timed out. With the polling loops skipped and `serve` paced to the wall
/// clock, it passes beside a lane and beside another build (issue 33).
const ALONE: &[&str] = &[];

/// Virtual-board tests paced to the wall clock (`serve` with a client: a terminal, a
/// Modbus master, lrzsz's `sb`) that leave a core mostly idle while they wait: measured
/// on a quiet machine, a fifth of a core or less (`lrzsz_sb…`: 5.9 s of CPU in 30.5 s;
/// the terminal and Modbus ones 0.3 s in 2-6 s). They run one after another on a lane of
/// their own beside the CPU lanes, instead of holding one of them idle for about 50 s.
/// The serve tests that keep a core busy (the PLC docking, the commissioning demo) stay
/// in the CPU lanes.
const PACED: &[&str] = &[
    "lrzsz_sb_sends_a_signed_image_into_the_board_over_a_pty",
    "a_terminal_that_closed_cleanly_left_the_console_busy_for_the_rest_of_the_run",
    "a_terminal_reads_wear_as_json_over_a_pty",
    "a_terminal_reads_the_version_over_tcp",
    "a_plc_reads_input_registers_over_modbus_tcp",
    "a_plc_reads_the_firmware_over_modbus_rtu_on_a_pty",
];

/// The virtual board's longest tests, longest first (started first so that the lanes
/// end together): every test of 3 s or more, by its time in a fresh clone's `.ci/run`
/// on 55ac642 (the 2-core machine, nothing else running; the in-run interrupts of that
/// round had moved the order), then the rest of the earlier list. Only a schedule: a
/// name that no longer exists is skipped, a new long test costs only the balance.
const LONG_FIRST: &[&str] = &[
    "one_seed_at_cpi_1_and_3_and_the_cache_model_under_flood_meets_the_targets",
    "dock_hold_an_hour_on_the_board_counts_one_cycle_without_wear_while_mated",
    "dockctl_reads_and_updates_the_real_image_over_a_pty",
    "a_console_byte_was_lost_while_a_record_was_written",
    "interrupts_and_sleep_inside_the_run_change_nothing_in_a_sample_of_the_suite",
    "skipping_the_polling_loops_changes_nothing_in_a_sample_of_the_suite",
    "estop_bounce_on_the_board_latches_every_edge_and_recovers",
    "a_plc_docks_the_firmware_over_modbus_and_over_the_dock_line",
    "the_release_image_updates_itself_over_the_console_with_every_counter_intact",
    "a_power_cut_in_the_swap_or_the_first_boot_boots_a_whole_image_and_loses_no_record",
    "overload_stop_waited_for_the_main_loop_at_80_sps_during_a_console_flood",
    "overload_stop_waited_for_the_main_loop_at_10_sps_during_a_console_flood",
    "a_trial_image_whose_load_cell_is_silent_or_stuck_or_whose_confirmation_fails_is_rolled_back",
    "a_technician_could_not_commission_the_live_board_between_demo_cycles",
    "a_power_cut_in_the_transfer_boots_the_old_image_with_state_untouched",
    "the_caches_were_not_reset_after_an_odometer_sector_erase",
    "a_sample_of_random_interleavings_keeps_the_invariants",
    "an_image_that_never_confirms_is_rolled_back_after_the_watchdog_reset",
    "maintenance_lockout_on_the_board_refuses_remote_motion_until_maint_exit",
    "debris_is_caught_by_band3_and_shown_on_the_console_modbus_and_the_plot",
    "the_plc_docks_and_undocks_through_the_map_and_the_reply_waits_t3_5",
    "a_write_protected_odometer_was_retried_at_every_step",
    "step_edges_came_too_close_to_dir_and_en_for_an_opto_isolated_driver",
    "a_detached_probe_blocked_the_control_loop",
    "one_nominal_cycle_through_the_four_contact_phases",
];

/// The test executables in `cargo test --no-run --message-format=json`'s output (the
/// artifacts built with the test profile: not the package's own binaries, which are
/// built too when a test runs them).
/// Test processes to run in lanes ([`Ci::lanes_plan`]): (executable, test name).
struct Lanes {
    jobs: Vec<(String, String)>,
    /// [`PACED`]: one after another beside the lanes.
    paced: Vec<(String, String)>,
    alone: Vec<(String, String)>,
    cwd: PathBuf,
}

impl Lanes {
    /// Run every job, as many at a time as the machine has cores, then the ones that
    /// run alone; each test's line printed as it ends. (passed, failed).
    fn run(self) -> (u64, u64) {
        let lanes = std::thread::available_parallelism().map_or(1, |n| n.get());
        println!(
            "{} tests in {lanes} lanes, {} paced to the wall clock beside them, then {} alone",
            self.jobs.len(),
            self.paced.len(),
            self.alone.len()
        );
        let queue = std::sync::Mutex::new(self.jobs.into_iter());
        let results = std::sync::Mutex::new((0u64, 0u64));
        let cwd = &self.cwd;
        let run_one = |exe: &str, test: &str| {
            let t = Instant::now();
            let out = Command::new(exe)
                .args(["--exact", test, "--test-threads", "1"])
                .current_dir(cwd)
                .stdin(Stdio::null())
                .output();
            let secs = t.elapsed().as_secs_f64();
            let name = Path::new(exe)
                .file_name()
                .map_or(String::new(), |n| n.to_string_lossy().into_owned());
            let bin = name.rsplit_once('-').map_or(name.as_str(), |(b, _)| b);
            let ok = out.as_ref().is_ok_and(|o| o.status.success());
            // One print a test (its output with it when it failed), so that lines of
            // steps running beside the lanes do not cut into it.
            let mut text = format!(
                "test {bin}::{test} ... {} ({secs:.1} s)\n",
                if ok { "ok" } else { "FAILED" }
            );
            if !ok {
                match &out {
                    Ok(o) => {
                        text.push_str(&String::from_utf8_lossy(&o.stdout));
                        text.push_str(&String::from_utf8_lossy(&o.stderr));
                    }
                    Err(e) => text.push_str(&format!("xtask: {exe}: {e}\n")),
                }
            }
            print!("{text}");
            if let Ok(mut r) = results.lock() {
                if ok {
                    r.0 += 1;
                } else {
                    r.1 += 1;
                }
            }
        };
        let paced = &self.paced;
        std::thread::scope(|s| {
            s.spawn(|| {
                for (exe, test) in paced {
                    run_one(exe, test);
                }
            });
            for _ in 0..lanes {
                s.spawn(|| loop {
                    let next = queue.lock().map(|mut q| q.next()).ok().flatten();
                    let Some((exe, test)) = next else { break };
                    run_one(&exe, &test);
                });
            }
        });
        for (exe, test) in &self.alone {
            run_one(exe, test);
        }
        let (passed, failed) = results.into_inner().unwrap_or_default();
        println!("test result (lanes): {passed} passed; {failed} failed");
        (passed, failed)
    }
}

fn executables(json: &str) -> Vec<String> {
    json.lines()
        .filter(|l| l.contains("\"reason\":\"compiler-artifact\""))
        .filter(|l| {
            // The profile's own `test` (the target object has a `test` key too).
            l.find("\"profile\":{").is_some_and(|at| {
                let profile = &l[at..];
                profile[..profile.find('}').unwrap_or(0)].contains("\"test\":true")
            })
        })
        .filter_map(|l| {
            let rest = &l[l.find("\"executable\":\"")? + 14..];
            Some(rest[..rest.find('"')?].to_string())
        })
        .collect()
}

/// The names in a libtest `--list --format terse` output (`name: test`).
fn test_names(list: &str) -> Vec<String> {
    list.lines()
        .filter_map(|l| l.strip_suffix(": test"))
        .map(str::to_string)
        .collect()
}

/// `(passed, failed)` of a libtest summary line
/// (`test result: ok. 12 passed; 0 failed; 1 ignored; …`).
fn test_summary(line: &str) -> Option<(u64, u64)> {
    let rest = line.trim().strip_prefix("test result: ")?;
    let count = |word: &str| -> Option<u64> {
        let end = rest.find(&format!(" {word}"))?;
        rest[..end].rsplit([' ', '.']).next()?.parse().ok()
    };
    Some((count("passed")?, count("failed")?))
}

/// The reasons commits give for the image's growth: their `Size-growth:` trailers
/// (`log`: their messages, `git log --format=%B`).
fn growth_reasons(log: &str) -> Vec<&str> {
    log.lines()
        .filter(|l| l.trim_start().starts_with(GROWTH_TRAILER))
        .collect()
}

/// The image's sections as `size -A` reports them, bytes.
#[derive(Debug, Default, PartialEq)]
struct Sections {
    /// .vector_table, .image_header (issue 21), .text.hot (the safety path's handlers,
    /// hot.x), .text, .rodata: in flash.
    text: u64,
    /// .data: in flash (its load image) and in RAM.
    data: u64,
    /// .bss, .uninit, .persist: in RAM.
    bss: u64,
}

impl Sections {
    fn of(report: &str) -> Self {
        let mut s = Self::default();
        for line in report.lines() {
            let mut w = line.split_whitespace();
            let (Some(name), Some(bytes)) = (w.next(), w.next()) else {
                continue;
            };
            let Ok(n) = bytes.parse::<u64>() else {
                continue;
            };
            match name {
                ".vector_table" | ".image_header" | ".text.hot" | ".text" | ".rodata" => {
                    s.text += n
                }
                ".data" => s.data += n,
                ".bss" | ".uninit" | ".persist" => s.bss += n,
                _ => {}
            }
        }
        s
    }

    fn flash(&self) -> u64 {
        self.text + self.data
    }

    fn ram(&self) -> u64 {
        self.data + self.bss
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn growth_is_excused_only_by_a_size_growth_trailer() {
        let log = "Layout C\n\nThe map is sized for the product.\n\nSize-growth: +2.8 KB for the layout check\n\nOther commit\n";
        assert_eq!(
            growth_reasons(log),
            ["Size-growth: +2.8 KB for the layout check"]
        );
        // Mentioned in the text, not a trailer at the start of a line: no reason.
        assert!(growth_reasons("this grows the size-growth of the image\nsize: 3 KB\n").is_empty());
        assert!(growth_reasons("").is_empty());
    }

    #[test]
    fn a_test_summary_is_counted_and_other_lines_are_not() {
        assert_eq!(
            test_summary("test result: ok. 12 passed; 0 failed; 1 ignored; 0 measured"),
            Some((12, 0))
        );
        assert_eq!(
            test_summary("test result: FAILED. 23 passed; 1 failed; 1 ignored;"),
            Some((23, 1))
        );
        assert_eq!(test_summary("running 12 tests"), None);
        assert_eq!(test_summary("test a ... ok"), None);
    }

    #[test]
    fn the_test_executables_and_names_are_read_from_cargo_and_libtest() {
        let json = concat!(
            r#"{"reason":"compiler-artifact","target":{"name":"vboard","test":true},"profile":{"opt_level":"3","test":false},"executable":"/t/release/vboard","fresh":true}"#,
            "\n",
            r#"{"reason":"compiler-artifact","target":{"name":"sweep"},"profile":{"test":true},"executable":"/t/release/deps/sweep-0123","fresh":true}"#,
            "\n",
            r#"{"reason":"build-finished","success":true}"#,
            "\n"
        );
        assert_eq!(executables(json), vec!["/t/release/deps/sweep-0123"]);
        assert_eq!(
            test_names("a_b: test\nc: test\nsome_bench: bench\n\n2 tests, 0 benchmarks\n"),
            vec!["a_b", "c"]
        );
    }

    #[test]
    fn the_sections_of_a_size_report_add_up_as_the_budget_counts_them() {
        let report = "docking-controller  :\nsection   size   addr\n.vector_table   392   134217728\n.text.hot   162   134218128\n.text   90000   134218296\n.rodata   14000   0\n.data   476   536895488\n.bss   24000   0\n.uninit   604   0\n.debug_info 99999 0\nTotal 1\n";
        let s = Sections::of(report);
        assert_eq!(
            s,
            Sections {
                text: 104_554,
                data: 476,
                bss: 24_604
            }
        );
        assert_eq!(s.flash(), 105_030);
        assert_eq!(s.ram(), 25_080);
    }
}
