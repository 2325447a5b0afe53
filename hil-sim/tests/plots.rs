//! `--plot FILE.svg` on `scene`, `profile`, `life` and `accuracy`: a well-formed SVG
//! with the expected content, the same bytes for the same command, stdout unchanged,
//! and a path that cannot be written refused with one line on stderr, exit 2.

mod common;

use std::path::PathBuf;

use common::{run, usage_error};

/// A fresh directory for one test's files.
fn dir(test: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("hil-sim-plots-{}-{test}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Run `args` with `--plot <dir>/<name>` appended; (stdout, the SVG).
fn plot(d: &std::path::Path, name: &str, args: &[&str]) -> (String, String) {
    let path = d.join(name);
    let p = path.to_str().unwrap();
    let mut a = args.to_vec();
    a.extend(["--plot", p]);
    let (code, out, err) = run(&a);
    assert_eq!(code, 0, "{args:?}: {err}");
    assert!(err.is_empty(), "{args:?}: {err}");
    (out, std::fs::read_to_string(&path).unwrap())
}

/// Well-formed: one `<svg>` root, every tag closed in order, text escaped.
fn assert_svg(svg: &str) {
    let s = svg.trim();
    assert!(
        s.starts_with("<svg") || s.starts_with("<?xml"),
        "{}",
        &s[..80]
    );
    assert!(s.ends_with("</svg>"), "{}", &s[s.len() - 80..]);
    let mut stack: Vec<&str> = Vec::new();
    let mut rest = s;
    while let Some(i) = rest.find('<') {
        let end = rest[i..].find('>').expect("unclosed tag") + i;
        let tag = &rest[i + 1..end];
        assert!(!tag.contains('<'), "'<' inside a tag: {tag}");
        if let Some(name) = tag.strip_prefix('/') {
            assert_eq!(stack.pop(), Some(name.trim()), "mismatched </{name}>");
        } else if !tag.ends_with('/') && !tag.starts_with('?') {
            stack.push(tag.split_whitespace().next().unwrap());
        }
        rest = &rest[end + 1..];
    }
    assert!(stack.is_empty(), "unclosed: {stack:?}");
    assert_eq!(s.matches("<svg").count(), 1);
}

fn assert_has(svg: &str, what: &[&str]) {
    for w in what {
        assert!(svg.contains(w), "'{w}' missing from the plot");
    }
}

/// Lines of a report that do not carry wall time.
fn without_wall_time(out: &str) -> Vec<&str> {
    out.lines()
        .filter(|l| !l.contains(" s wall") && !l.contains("simulated in"))
        .collect()
}

#[test]
fn scene_overload_plot_shows_phases_envelope_and_the_trip() {
    let d = dir("overload");
    let (out, svg) = plot(&d, "o.svg", &["scene", "overload"]);
    assert_svg(&svg);
    assert_has(
        &svg,
        &[
            "scene overload: force against insertion depth",
            "insertion depth (mm)",
            "force (N)",
            "phase 1",
            "phase 2",
            "phase 3",
            "phase 4",
            "guard envelope (limit in force)",
            "hard limit 300 N",
            "insertion (measured)",
            "trip (first over-limit sample)",
            "trip: ",
            "fault: overload",
        ],
    );
    // stdout is what it is without --plot.
    let (code, plain, _) = run(&["scene", "overload"]);
    assert_eq!(code, 0);
    assert_eq!(without_wall_time(&out), without_wall_time(&plain));
    // The same command, the same bytes.
    let (_, again) = plot(&d, "o2.svg", &["scene", "overload"]);
    assert!(again == svg, "two runs of the same scene plot differ");
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn scene_plots_mark_rejected_spikes_and_sensor_faults() {
    let d = dir("spike");
    let (_, svg) = plot(&d, "s.svg", &["scene", "spike"]);
    assert_svg(&svg);
    assert_has(&svg, &["rejected spike (", "extraction (measured)"]);
    assert!(!svg.contains("trip (first over-limit sample)"));
    let (_, svg) = plot(&d, "n.svg", &["scene", "nominal", "--json"]);
    assert_svg(&svg);
    assert!(!svg.contains("rejected spike") && !svg.contains("fault"));
    let (_, svg) = plot(&d, "d.svg", &["scene", "disconnect"]);
    assert_has(&svg, &["fault: sensor_disconnected", "fault latched"]);
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn profile_plot_has_the_four_forces_and_phases() {
    let d = dir("profile");
    let (out, svg) = plot(&d, "p.svg", &["profile", "--rate", "200"]);
    assert_svg(&svg);
    assert_has(
        &svg,
        &[
            "Eq. 7 contact forces, insertion stroke",
            "force (N)",
            "(s)",
            "N1 (support)",
            "N2 (support)",
            "N3 (rod–cone)",
            "N4 (second contact)",
            "phase 1",
            "phase 4",
        ],
    );
    let (_, plain, _) = run(&["profile", "--rate", "200"]);
    assert_eq!(out, plain);
    let (_, svg) = plot(&d, "x.svg", &["profile", "--stroke", "extract"]);
    assert_has(&svg, &["extraction stroke", "phase 4", "phase 1"]);
    let (_, again) = plot(&d, "x2.svg", &["profile", "--stroke", "extract"]);
    assert!(again == svg);
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn life_plot_has_eq17_and_with_readings_the_band() {
    let d = dir("life");
    let (out, svg) = plot(&d, "l.svg", &["life", "--cycles", "40", "--at", "1,20,40"]);
    assert_svg(&svg);
    assert_has(
        &svg,
        &[
            "wear against cycles",
            "cone cycles",
            "wear depth (mm)",
            "Eq. 17",
            "odometer (zqsn5-2)",
        ],
    );
    assert!(!svg.contains("estimate band") && !svg.contains("readings"));
    let (_, plain, _) = run(&["life", "--cycles", "40", "--at", "1,20,40"]);
    assert_eq!(without_wall_time(&out), without_wall_time(&plain));

    let csv = d.join("readings.csv");
    std::fs::write(&csv, "cycle,bore_mm\n0,26.000\n15,26.040\n30,26.055\n").unwrap();
    let csv = csv.to_str().unwrap();
    let args = ["life", "--cycles", "40", "--readings", csv, "--json"];
    let (out, svg) = plot(&d, "r.svg", &args);
    assert_svg(&svg);
    assert_has(
        &svg,
        &[
            "estimate band (≈ 95 %)",
            "estimate (model taught by the readings)",
            "micrometer readings (3)",
            "Eq. 17",
        ],
    );
    let (_, plain, _) = run(&args);
    let strip = |s: &str| s[..s.find("\"wall_time_s\"").unwrap()].to_string();
    assert_eq!(strip(&out), strip(&plain));
    let (_, again) = plot(&d, "r2.svg", &args);
    assert!(again == svg);
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn accuracy_plot_is_error_against_rate() {
    let d = dir("accuracy");
    let (_, svg) = plot(&d, "a.svg", &["accuracy", "--json"]);
    assert_svg(&svg);
    assert_has(
        &svg,
        &[
            "sample rate (samples/s)",
            "error",
            "(%)",
            "insertion stroke",
            "extraction stroke",
            "10 SPS: ",
            "1280 SPS: ",
        ],
    );
    let (_, again) = plot(&d, "a2.svg", &["accuracy", "--json"]);
    assert!(again == svg, "two accuracy plots differ");
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn an_unwritable_plot_path_is_one_line_and_exit_2() {
    let d = dir("unwritable");
    let missing = d.join("no-such-dir").join("x.svg");
    let missing = missing.to_str().unwrap();
    let a_dir = d.to_str().unwrap();
    for args in [
        vec!["scene", "overload", "--plot", missing],
        vec!["profile", "--plot", missing],
        vec!["life", "--cycles", "2", "--plot", missing],
        vec!["accuracy", "--plot", a_dir],
    ] {
        let err = usage_error(&args);
        assert!(err.starts_with("hil-sim: --plot "), "{args:?}: {err}");
    }
    let (code, _, err) = run(&["scene", "nominal", "--plot"]);
    assert_eq!(code, 2);
    assert_eq!(err.trim(), "hil-sim: --plot needs a value");
    let _ = std::fs::remove_dir_all(&d);
}

#[test]
fn the_drawn_envelope_is_the_guards_limit_at_every_depth() {
    use docking_logic::guard::{GuardConfig, OverloadGuard};
    let g = OverloadGuard::new(GuardConfig::DEFAULT);
    let env = hil_sim::plot::guard_envelope();
    assert_eq!(env.first().map(|p| p.0), Some(0.0));
    assert_eq!(env.last().map(|p| p.0), Some(30.0));
    // The horizontal step that covers depth x, mm.
    let level_at = |x: f64| {
        env.windows(2)
            .find(|w| w[0].1 == w[1].1 && w[0].0 <= x && x < w[1].0)
            .map(|w| w[0].1)
    };
    for d in (0..30_000).step_by(50) {
        let x = d as f64 / 1000.0;
        let limit = g.limit_mn(Some(d)) as f64 / 1000.0;
        assert_eq!(level_at(x), Some(limit), "at {x} mm");
    }
}

/// Defect (issue 17, item 4): `spikes_injected` counted every scheduled spike (155),
/// `spikes_rejected` the kernel's count (115), and the plot's legend the markers of the
/// traced cycle (104): three numbers for one thing. Now the JSON, the text and the
/// legend give the kernel's count, the legend the traced cycle's too, and a spike is
/// counted as injected only once the controller read the conversion it was in.
#[test]
fn spike_counts_agree_in_json_text_and_plot() {
    let d = dir("spike-counts");
    let args = ["scene", "spike", "--cycles", "3", "--seed", "2"];
    let (code, json, _) = run(&[&args[..], &["--json"]].concat());
    assert_eq!(code, 0);
    let field = |k: &str| -> u64 {
        let at = json.find(&format!("\"{k}\":")).expect(k) + k.len() + 3;
        let end = json[at..].find([',', '}']).unwrap() + at;
        json[at..end].parse().unwrap()
    };
    let (injected, rejected) = (field("spikes_injected"), field("spikes_rejected"));
    assert!(rejected > 50, "{json}");
    assert!(
        rejected <= injected,
        "a rejected spike was delivered: {json}"
    );
    // Scheduled over the horizon (3 × 75 s at 80 SPS, one about every 41 samples:
    // ≈ 440), far more than the run's conversions could carry.
    assert!(injected < 400, "only spikes in conversions read: {json}");
    let (text, svg) = plot(&d, "s.svg", &args);
    assert!(
        text.contains(&format!(
            "spikes: {injected} delivered in samples the controller read, {rejected} rejected"
        )),
        "{text}"
    );
    let label = svg
        .split("rejected spike (")
        .nth(1)
        .and_then(|r| r.split(')').next())
        .expect("the legend's spike entry");
    assert!(
        label.ends_with(&format!("; {rejected} in the run")),
        "legend '{label}' vs JSON {rejected}"
    );
    let in_cycle: u64 = label
        .split(" in cycle 3")
        .next()
        .and_then(|p| p.rsplit(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("the traced cycle's count in '{label}'"));
    assert!(in_cycle > 0 && in_cycle <= rejected, "{label}");
    let _ = std::fs::remove_dir_all(&d);
}

/// Plots of different runs carry different titles: the same scene on another machine
/// or configuration, and a life with readings, say so in the title.
#[test]
fn plots_of_different_runs_have_different_titles() {
    let d = dir("titles");
    let title = |svg: &str| {
        let i = svg.find("scene nominal:").expect("a scene title");
        svg[i..].split('<').next().unwrap().to_string()
    };
    let (_, a) = plot(&d, "a.svg", &["scene", "nominal"]);
    let (_, b) = plot(
        &d,
        "b.svg",
        &["scene", "nominal", "--model", "plant", "--mass-kg", "18"],
    );
    let (_, c) = plot(
        &d,
        "c.svg",
        &[
            "scene",
            "nominal",
            "--model",
            "plant",
            "--mass-kg",
            "18",
            "--config",
            "matching",
        ],
    );
    let (ta, tb, tc) = (title(&a), title(&b), title(&c));
    assert!(
        ta.contains("Eq. 7, the build&apos;s configuration")
            || ta.contains("Eq. 7, the build's configuration"),
        "{ta}"
    );
    assert!(
        tb.contains("plant m 18 kg") && tb.contains("s configuration"),
        "{tb}"
    );
    assert!(tc.contains("configuration matching it"), "{tc}");
    let readings = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/readings-1.3x.csv");
    let (_, l) = plot(
        &d,
        "l.svg",
        &["life", "--cycles", "2000", "--readings", readings],
    );
    assert!(
        l.contains("SPS, 21 readings)"),
        "the life title names its readings"
    );
}

/// `plot-curve` (issue 34): a `curve --json` dump of a NOK docking drawn against its
/// objects (boxes) and its cone's reference, the phases shaded, the axes labelled, the
/// failed object marked; the same dump, the same bytes.
#[test]
fn a_curve_dump_is_drawn_against_its_objects_and_the_reference() {
    use docking_logic::sequencer::{Request, State};
    use hil_sim::rig::{Rig, RigOptions};
    let d = dir("curve");
    let mut rig = Rig::booted(RigOptions::new(80));
    for k in 0..2 {
        if k == 1 {
            rig.devices().script.borrow_mut().bump = Some(hil_sim::sigscene::DEBRIS);
        }
        let done = rig.ctrl.status().cycles_completed;
        rig.ctrl.request(Request::StartCycle);
        while !(rig.ctrl.state() == State::Idle && rig.ctrl.status().cycles_completed > done) {
            rig.tick();
            while rig.ctrl.next_event().is_some() {}
        }
    }
    for _ in 0..50 {
        rig.tick();
    }
    let last = d.join("last.json");
    let reference = d.join("ref.json");
    std::fs::write(&last, rig.command("curve last --json", 400)).unwrap();
    std::fs::write(&reference, rig.command("curve ref --json", 400)).unwrap();
    let args = [
        "plot-curve",
        last.to_str().unwrap(),
        "--ref",
        reference.to_str().unwrap(),
    ];
    let (out, svg) = plot(&d, "curve.svg", &args);
    assert!(out.starts_with("wrote "), "{out}");
    assert_svg(&svg);
    assert_has(
        &svg,
        &[
            "insertion depth (mm)",
            "force (N)",
            "phase 1",
            "phase 4",
            "\nentry\n</text>",
            "\nplateau\n</text>",
            "\nend\n</text>",
            "\next. peak\n</text>",
            "reference (insertion, mean)",
            "insertion NOK: band3",
            "insertion nok (band3), extraction ok",
        ],
    );
    assert_eq!(plot(&d, "again.svg", &args).1, svg, "the same bytes");
    // A file that is no dump: one line, exit 2.
    let (code, _, err) = run(&[
        "plot-curve",
        reference.to_str().unwrap().replace("ref", "nope").as_str(),
        "--plot",
        "/tmp/x.svg",
    ]);
    assert_eq!(code, 2);
    assert_eq!(err.trim().lines().count(), 1, "{err}");
}
