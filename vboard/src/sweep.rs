//! `vboard sweep`: scenes over seeds and timing models, one row a run, and the worst
//! figures against the targets of issue 17.
//!
//! Every run is a [`crate::scene::run`] of its own board; runs go in parallel
//! (`jobs` at a time), each on its own thread. The figures are the scene report's:
//!
//! | figure | from | target |
//! |---|---|---|
//! | `control_period_max_ms` | TIM2 entries on the NVIC model, while anything moves | ≤ sample period + 1 ms (13.5 ms at 80 SPS) |
//! | `control_late` | intervals over the period + 1 ms | 0 (the same target, counted) |
//! | `control_entry_latency_max_us` | TIM2 pending → entered on the NVIC model, while anything moves (`_all`: the whole run, reported only) | ≤ 100 µs ([`ENTRY_LATENCY_TARGET_US`]: nothing below the step holds it; only higher-priority tasks, the sample's readout the longest, delay it) |
//! | `watchdog_feeds_missed` | IWDG reload gaps > 3 periods, while anything moves | 0 |
//! | `backed_off_um` | the carriage's retreat after the first overload trip | 2 mm (1.9–2.1 mm) in every run that tripped |
//! | `stop_latency_pins_us` | DOUT falling → EN high, overload | ≤ 100 µs |
//! | `estop_off_max_us` | E-STOP edge → EN high and the lock off on the pins, while anything moves | ≤ 10 µs |
//!
//! A run whose own checks fail, that latched more than one overload, whose board took a
//! core fault or a watchdog reset, or that could not run at all, also misses its
//! targets.
//!
//! The sweep: `vboard sweep --flood` (`overload` and `estop`, seeds 1 to 10,
//! CPI 1, 2, 3 and the ART cache model at CPI 1).

use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;

use hil_sim::scene::num;

use crate::cpu::BoardConfig;
use crate::scene::{run, Report, SceneOptions};

/// The control step's entry latency while anything moves, at most, µs. Nothing at a
/// lower priority holds what the step needs (the firmware's `src/board/owner.rs`), so
/// only the tasks above it delay it: the longest is the sample's handler (its HX711
/// readout, 45 µs at CPI 3). The image before the one-owner design took 256 µs at CPI 3
/// (idle holding the controller for a console command).
pub const ENTRY_LATENCY_TARGET_US: f64 = 100.0;

/// One timing model of a sweep: a name for the rows and the board it configures.
#[derive(Clone, Debug)]
pub struct Model {
    /// How rows name it (`cpi 1`, `cpi 3`, …).
    pub label: String,
    /// The board.
    pub board: BoardConfig,
}

/// What a sweep runs.
#[derive(Clone, Debug)]
pub struct SweepOptions {
    /// Scenes, each over every seed and model.
    pub scenes: Vec<String>,
    /// Seeds.
    pub seeds: Vec<u64>,
    /// Timing models.
    pub models: Vec<Model>,
    /// Everything else (firmware, rate, cycles, flood); its seed and board are replaced
    /// per run.
    pub base: SceneOptions,
    /// Runs at a time.
    pub jobs: usize,
}

/// One run's figures.
#[derive(Clone, Debug)]
pub struct Row {
    /// Scene.
    pub scene: String,
    /// Seed.
    pub seed: u64,
    /// Model label.
    pub model: String,
    /// The run's report (`Err`: it could not run).
    pub report: Result<Box<Report>, String>,
}

impl Row {
    fn r(&self) -> Option<&Report> {
        self.report.as_deref().ok()
    }

    /// Longest control period while moving, ms.
    pub fn control_period_max_ms(&self) -> Option<f64> {
        self.r()?.timing.period_max_ms
    }

    /// Longest control entry latency (TIM2 pending → entered) while moving, µs.
    pub fn control_entry_latency_max_us(&self) -> Option<f64> {
        self.r()?.timing.entry_latency_max_us
    }

    /// Longest control entry latency over the whole run, µs.
    pub fn control_entry_latency_max_us_all(&self) -> Option<f64> {
        self.r()?.timing.entry_latency_max_us_all
    }

    /// E-STOP edge → EN high and lock off, the longest while moving, µs: the pins as the
    /// board measures them in every scene, and the `estop` scene's own check.
    pub fn estop_us(&self) -> Option<f64> {
        let r = self.r()?;
        let plc = r
            .scene
            .plc
            .as_ref()
            .and_then(|p| p.estop_latency_s)
            .map(|s| s * 1e6);
        match (r.estop_off_max_us(), plc) {
            (Some(a), Some(b)) => Some(a.max(b)),
            (a, b) => a.or(b),
        }
    }

    /// Why this run misses the targets (empty: it meets them).
    pub fn misses(&self) -> Vec<String> {
        let r = match &self.report {
            Ok(r) => r,
            Err(e) => return vec![format!("did not run: {e}")],
        };
        let mut m = Vec::new();
        let period = r.period_ms();
        if let Some(p) = r.timing.period_max_ms {
            if p > period + 1.0 {
                m.push(format!(
                    "control period {p:.2} ms > {:.1} ms ({} late)",
                    period + 1.0,
                    r.timing.late
                ));
            }
        }
        if let Some(l) = r.timing.entry_latency_max_us {
            if l > ENTRY_LATENCY_TARGET_US {
                m.push(format!(
                    "control entry latency {l:.1} µs > {ENTRY_LATENCY_TARGET_US:.0} µs"
                ));
            }
        }
        if r.timing.feeds_missed > 0 {
            m.push(format!(
                "{} watchdog feed(s) missed (longest gap {:.2} ms)",
                r.timing.feeds_missed,
                r.timing.feed_gap_max_ms.unwrap_or(0.0)
            ));
        }
        if let Some(b) = r.scene.backed_off_um {
            if !(1_900.0..=2_100.0).contains(&b) {
                m.push(format!("backed off {b:.0} µm, not 2 mm"));
            }
        }
        let overloads = r
            .scene
            .faults
            .iter()
            .filter(|f| f.kind == "overload")
            .count();
        if overloads > 1 {
            m.push(format!("{overloads} overload faults"));
        }
        if let Some(l) = r.stop_latency_pins_us {
            if l > 100.0 {
                m.push(format!("overload stop latency {l:.1} µs > 100 µs"));
            }
        }
        if let Some(e) = self.estop_us() {
            if e > 10.0 {
                m.push(format!("E-STOP edge → EN high {e:.2} µs > 10 µs"));
            }
        }
        if r.reset_causes.contains(&"watchdog") {
            m.push("watchdog reset".into());
        }
        if !r.core_faults.is_empty() {
            m.push(format!("core fault: {}", r.core_faults.join("; ")));
        }
        for (n, ok, d) in &r.checks {
            if !ok {
                m.push(format!("check '{n}' failed ({d})"));
            }
        }
        m
    }

    /// The row for a terminal.
    pub fn to_text(&self) -> String {
        let head = format!("{:<12} {:>4} {:<8}", self.scene, self.seed, self.model);
        let Some(r) = self.r() else {
            return format!(
                "{head} did not run: {}",
                self.report.as_ref().err().map_or("", |e| e)
            );
        };
        let f = |x: Option<f64>, d: usize| x.map_or("-".to_string(), |v| format!("{v:.d$}"));
        let misses = self.misses();
        format!(
            "{head} {:>9} {:>5} {:>8} {:>8} {:>7} {:>8} {:>9} {:>9}  {}",
            f(r.timing.period_max_ms, 2),
            r.timing.late,
            f(r.timing.entry_latency_max_us, 1),
            f(r.timing.entry_latency_max_us_all, 1),
            r.timing.feeds_missed,
            f(r.scene.backed_off_um, 0),
            f(r.stop_latency_pins_us, 1),
            f(self.estop_us(), 2),
            if misses.is_empty() {
                "ok".to_string()
            } else {
                misses.join("; ")
            }
        )
    }

    /// The row as one JSON object.
    pub fn to_json(&self) -> String {
        let o = |x: Option<f64>| x.map_or("null".to_string(), num);
        let misses: Vec<String> = self
            .misses()
            .iter()
            .map(|m| format!("\"{}\"", m.replace('\\', "\\\\").replace('"', "\\\"")))
            .collect();
        let r = self.r();
        format!(
            "{{\"scene\":\"{}\",\"seed\":{},\"model\":\"{}\",\"cpi\":{},\"control_period_max_ms\":{},\"control_entry_latency_max_us\":{},\"control_entry_latency_max_us_all\":{},\"control_late\":{},\"watchdog_feeds_missed\":{},\"backed_off_um\":{},\"stop_latency_pins_us\":{},\"estop_off_max_us\":{},\"faults\":[{}],\"misses\":[{}]}}",
            self.scene,
            self.seed,
            self.model,
            o(r.map(|r| r.cpi)),
            o(self.control_period_max_ms()),
            o(self.control_entry_latency_max_us()),
            o(self.control_entry_latency_max_us_all()),
            r.map_or("null".to_string(), |r| r.timing.late.to_string()),
            r.map_or("null".to_string(), |r| r.timing.feeds_missed.to_string()),
            o(r.and_then(|r| r.scene.backed_off_um)),
            o(r.and_then(|r| r.stop_latency_pins_us)),
            o(self.estop_us()),
            r.map_or(String::new(), |r| r
                .scene
                .faults
                .iter()
                .map(|f| format!("\"{}\"", f.kind))
                .collect::<Vec<_>>()
                .join(",")),
            misses.join(",")
        )
    }
}

/// The worst figures of some rows.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Worst {
    /// Runs.
    pub runs: usize,
    /// Runs that miss a target.
    pub missing: usize,
    /// Longest control period, ms.
    pub control_period_max_ms: Option<f64>,
    /// Most late control periods in a run.
    pub control_late: u64,
    /// Longest control entry latency (TIM2 pending → entered) while moving, µs.
    pub control_entry_latency_max_us: Option<f64>,
    /// Longest control entry latency over a whole run, µs.
    pub control_entry_latency_max_us_all: Option<f64>,
    /// Most missed watchdog feeds in a run.
    pub watchdog_feeds_missed: u64,
    /// Shortest and longest back-off of the runs that tripped, µm.
    pub backed_off_um: Option<(f64, f64)>,
    /// Longest overload stop latency at the pins, µs.
    pub stop_latency_pins_us: Option<f64>,
    /// Longest E-STOP edge → EN high while moving, µs.
    pub estop_us: Option<f64>,
}

fn max_opt(a: Option<f64>, b: Option<f64>) -> Option<f64> {
    match (a, b) {
        (Some(x), Some(y)) => Some(x.max(y)),
        (x, y) => x.or(y),
    }
}

impl Worst {
    /// Of `rows`.
    pub fn of<'a>(rows: impl IntoIterator<Item = &'a Row>) -> Self {
        let mut w = Self::default();
        for row in rows {
            w.runs += 1;
            if !row.misses().is_empty() {
                w.missing += 1;
            }
            let Some(r) = row.r() else { continue };
            w.control_period_max_ms = max_opt(w.control_period_max_ms, r.timing.period_max_ms);
            w.control_late = w.control_late.max(r.timing.late);
            w.control_entry_latency_max_us = max_opt(
                w.control_entry_latency_max_us,
                r.timing.entry_latency_max_us,
            );
            w.control_entry_latency_max_us_all = max_opt(
                w.control_entry_latency_max_us_all,
                r.timing.entry_latency_max_us_all,
            );
            w.watchdog_feeds_missed = w.watchdog_feeds_missed.max(r.timing.feeds_missed);
            if let Some(b) = r.scene.backed_off_um {
                w.backed_off_um = Some(
                    w.backed_off_um
                        .map_or((b, b), |(lo, hi)| (lo.min(b), hi.max(b))),
                );
            }
            w.stop_latency_pins_us = max_opt(w.stop_latency_pins_us, r.stop_latency_pins_us);
            w.estop_us = max_opt(w.estop_us, row.estop_us());
        }
        w
    }

    /// One line for a terminal, headed `what`.
    pub fn to_text(&self, what: &str) -> String {
        let f = |x: Option<f64>, d: usize| x.map_or("-".to_string(), |v| format!("{v:.d$}"));
        format!(
            "worst {what}: {} run(s), {} missing a target; control period {} ms ({} late), control entry latency {} µs ({} µs over the whole run), {} watchdog feed(s) missed, backed off {} µm, overload stop latency {} µs, E-STOP edge → EN high {} µs",
            self.runs,
            self.missing,
            f(self.control_period_max_ms, 2),
            self.control_late,
            f(self.control_entry_latency_max_us, 1),
            f(self.control_entry_latency_max_us_all, 1),
            self.watchdog_feeds_missed,
            self.backed_off_um
                .map_or("-".to_string(), |(lo, hi)| if lo == hi {
                    format!("{lo:.0}")
                } else {
                    format!("{lo:.0}–{hi:.0}")
                }),
            f(self.stop_latency_pins_us, 1),
            f(self.estop_us, 2),
        )
    }

    /// As one JSON object.
    pub fn to_json(&self) -> String {
        let o = |x: Option<f64>| x.map_or("null".to_string(), num);
        format!(
            "{{\"runs\":{},\"missing\":{},\"control_period_max_ms\":{},\"control_entry_latency_max_us\":{},\"control_entry_latency_max_us_all\":{},\"control_late\":{},\"watchdog_feeds_missed\":{},\"backed_off_um_min\":{},\"backed_off_um_max\":{},\"stop_latency_pins_us\":{},\"estop_off_max_us\":{}}}",
            self.runs,
            self.missing,
            o(self.control_period_max_ms),
            o(self.control_entry_latency_max_us),
            o(self.control_entry_latency_max_us_all),
            self.control_late,
            self.watchdog_feeds_missed,
            o(self.backed_off_um.map(|b| b.0)),
            o(self.backed_off_um.map(|b| b.1)),
            o(self.stop_latency_pins_us),
            o(self.estop_us),
        )
    }
}

/// A sweep's rows, in (scene, model, seed) order.
#[derive(Clone, Debug)]
pub struct Sweep {
    /// Every run.
    pub rows: Vec<Row>,
    /// The models, in order.
    pub models: Vec<String>,
}

impl Sweep {
    /// The worst figures of every run of `model` (all runs: `None`).
    pub fn worst(&self, model: Option<&str>) -> Worst {
        Worst::of(
            self.rows
                .iter()
                .filter(|r| model.is_none_or(|m| r.model == m)),
        )
    }

    /// Every run's misses, `scene seed model: why`.
    pub fn misses(&self) -> Vec<String> {
        self.rows
            .iter()
            .flat_map(|r| {
                r.misses()
                    .into_iter()
                    .map(move |m| format!("{} seed {} {}: {m}", r.scene, r.seed, r.model))
            })
            .collect()
    }

    /// A table for a terminal: one row a run, the worst figures per model and overall.
    pub fn to_text(&self) -> String {
        let mut s = format!(
            "{:<12} {:>4} {:<8} {:>9} {:>5} {:>8} {:>8} {:>7} {:>8} {:>9} {:>9}  {}\n",
            "scene",
            "seed",
            "model",
            "period ms",
            "late",
            "entry µs",
            "all µs",
            "missed",
            "back µm",
            "stop µs",
            "estop µs",
            "targets"
        );
        for r in &self.rows {
            s += &r.to_text();
            s.push('\n');
        }
        for m in &self.models {
            s += &self.worst(Some(m)).to_text(m);
            s.push('\n');
        }
        s += &self.worst(None).to_text("overall");
        s += "\ntargets: control period ≤ sample period + 1 ms (13.5 ms at 80 SPS), control entry latency ≤ 100 µs while anything moves, no watchdog feed missed, back-off 2 mm every trip, overload stop latency ≤ 100 µs, E-STOP edge → EN high ≤ 10 µs";
        s
    }

    /// One JSON object: the rows, the worst figures per model and overall.
    pub fn to_json(&self) -> String {
        let rows: Vec<String> = self.rows.iter().map(Row::to_json).collect();
        let per: Vec<String> = self
            .models
            .iter()
            .map(|m| format!("\"{m}\":{}", self.worst(Some(m)).to_json()))
            .collect();
        format!(
            "{{\"rows\":[{}],\"worst_by_model\":{{{}}},\"worst\":{}}}",
            rows.join(","),
            per.join(","),
            self.worst(None).to_json()
        )
    }
}

/// Run the sweep; `progress` sees each row as it completes (in completion order).
pub fn sweep(opts: &SweepOptions, progress: &(dyn Fn(&Row) + Sync)) -> Sweep {
    let mut plan = Vec::new();
    for scene in &opts.scenes {
        for model in &opts.models {
            for &seed in &opts.seeds {
                plan.push((scene.clone(), model.clone(), seed));
            }
        }
    }
    let next = AtomicUsize::new(0);
    let done: Mutex<Vec<Option<Row>>> = Mutex::new(vec![None; plan.len()]);
    std::thread::scope(|sc| {
        for _ in 0..opts.jobs.clamp(1, plan.len().max(1)) {
            sc.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::Relaxed);
                let Some((scene, model, seed)) = plan.get(i) else {
                    break;
                };
                let mut o = opts.base.clone();
                o.session.seed = *seed;
                o.session.board = model.board;
                let row = Row {
                    scene: scene.clone(),
                    seed: *seed,
                    model: model.label.clone(),
                    report: run(scene, &o).map(Box::new),
                };
                progress(&row);
                if let Ok(mut d) = done.lock() {
                    d[i] = Some(row);
                }
            });
        }
    });
    let rows = done
        .into_inner()
        .unwrap_or_default()
        .into_iter()
        .flatten()
        .collect();
    Sweep {
        rows,
        models: opts.models.iter().map(|m| m.label.clone()).collect(),
    }
}

/// Seeds from `1..10` (inclusive: seeds 1 to 10), `1..=10`, `3` or `1,4,7`.
pub fn parse_seeds(s: &str) -> Result<Vec<u64>, String> {
    let bad = || format!("--seeds must be like 1..10 or 1,2,3, got '{s}'");
    if let Some((a, b)) = s.split_once("..") {
        let b = b.strip_prefix('=').unwrap_or(b);
        let (a, b): (u64, u64) = (
            a.trim().parse().map_err(|_| bad())?,
            b.trim().parse().map_err(|_| bad())?,
        );
        if a > b || b - a >= 10_000 {
            return Err(bad());
        }
        return Ok((a..=b).collect());
    }
    s.split(',')
        .map(|x| x.trim().parse::<u64>().map_err(|_| bad()))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seeds_are_ranges_or_lists() {
        assert_eq!(parse_seeds("1..10").unwrap(), (1..=10).collect::<Vec<_>>());
        assert_eq!(parse_seeds("2..=3").unwrap(), vec![2, 3]);
        assert_eq!(parse_seeds("5,1").unwrap(), vec![5, 1]);
        assert!(parse_seeds("3..1").is_err());
        assert!(parse_seeds("x").is_err());
    }

    #[test]
    fn a_run_that_could_not_run_misses_its_targets() {
        let row = Row {
            scene: "overload".into(),
            seed: 1,
            model: "cpi 1".into(),
            report: Err("no image".into()),
        };
        assert_eq!(row.misses().len(), 1);
        let w = Worst::of([&row]);
        assert_eq!((w.runs, w.missing), (1, 1));
    }
}
