//! `hil-sim life`: N full closed-loop docking cycles — sequencer, simulated HAL, wear
//! odometer, simulated flash — with the cone's wear at checkpoints.

use std::time::Instant;

use docking_logic::material::Material;
use docking_logic::odometer::WearLevel;
use docking_logic::sequencer::{Request, State};

use crate::rig::{Rig, RigOptions};

/// Options.
#[derive(Clone, Debug)]
pub struct LifeOptions {
    /// Cycles to run.
    pub cycles: u32,
    /// Cone material.
    pub material: Material,
    /// Checkpoints (cycle numbers, ascending, ≤ cycles).
    pub at: Vec<u32>,
    /// Load-cell rate, SPS.
    pub rate_sps: u32,
    /// A technician's micrometer readings to replay, `(cone cycle, bore µm)`, cycles
    /// increasing, the first at cycle 0 (the cone's baseline). Entered on the console
    /// (`measure`) when the run reaches each cycle.
    pub readings: Vec<(u32, u32)>,
}

/// Default checkpoints: 1, 10, 100, … below N, and N.
pub fn default_checkpoints(n: u32) -> Vec<u32> {
    let mut v: Vec<u32> = std::iter::successors(Some(1u32), |x| x.checked_mul(10))
        .take_while(|&x| x < n)
        .collect();
    v.push(n);
    v
}

/// One checkpoint.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LifePoint {
    /// Cone cycle count.
    pub cycle: u32,
    /// Wear depth, nm.
    pub wear_nm: u32,
    /// Remaining life, nominal cycles.
    pub remaining_cycles: u32,
    /// The estimate taught by the readings so far (with `--readings`).
    pub estimate: Option<docking_logic::estimate::Estimate>,
}

/// The run's result.
#[derive(Clone, Debug)]
pub struct LifeReport {
    /// Material.
    pub material: Material,
    /// Checkpoints reached.
    pub points: Vec<LifePoint>,
    /// Checkpoints not reached: the cone hit its wear limit first and the controller
    /// refused to dock it again.
    pub not_reached: Vec<u32>,
    /// Cycle at which the wear limit was reached (extrapolated by the model if later).
    pub life_cycles: u32,
    /// Whether the limit was reached within the run (the controller then refused to go on).
    pub limit_reached: bool,
    /// Cycles completed.
    pub cycles_run: u32,
    /// Most erases of any odometer flash sector.
    pub erases_per_sector_max: u32,
    /// Faults latched (a nominal life run has none).
    pub faults: u32,
    /// Virtual time, s.
    pub sim_time_s: f64,
    /// Wall time, s.
    pub wall_time_s: f64,
}

/// The technician's PIN in a run with readings.
const PIN: &str = "2468";

/// Run it.
pub fn run(opts: &LifeOptions) -> LifeReport {
    let started = Instant::now();
    let mut rig = Rig::new(RigOptions {
        material: opts.material,
        ..RigOptions::new(opts.rate_sps)
    });
    let mut points = Vec::with_capacity(opts.at.len());
    let mut next_at = opts.at.iter().copied().peekable();
    let mut seen_cycles = 0u32;
    let mut limit_at: Option<u32> = None;
    let mut readings = opts.readings.iter().copied().peekable();
    let technician = !opts.readings.is_empty();
    if technician {
        // The technician's PIN (first use: allowed without maintenance mode).
        let _ = rig.command(&format!("pin set {PIN}"), 100);
    }
    let mut checkpoint_due = false;
    loop {
        rig.tick();
        let cycles = rig.ctrl.odometer().cone().cycles;
        if cycles != seen_cycles {
            seen_cycles = cycles;
            checkpoint_due = true;
        }
        // Moving (most ticks): nothing to do but go on, or stop at a fault.
        match rig.ctrl.state() {
            State::Idle => {}
            State::Faulted { .. } => break,
            _ => continue,
        }
        let at_rest = !rig.ctrl.persist_pending();
        if at_rest {
            // Readings due by now, through the console as a technician enters them.
            while let Some(&(c, bore_um)) = readings.peek().filter(|r| r.0 <= cycles) {
                readings.next();
                let _ = rig.command(&format!("maint {PIN}"), 100);
                let flag = if c == 0 { "--baseline " } else { "" };
                let _ = rig.command(
                    &format!("measure {flag}{}.{:03}", bore_um / 1000, bore_um % 1000),
                    100,
                );
                let _ = rig.command("maint exit", 100);
            }
        }
        if checkpoint_due && at_rest {
            checkpoint_due = false;
            if limit_at.is_none() && rig.ctrl.wear_level() == WearLevel::Limit {
                limit_at = Some(cycles);
            }
            let odo = rig.ctrl.odometer();
            while next_at.peek().is_some_and(|&c| c <= cycles) {
                next_at.next();
                points.push(LifePoint {
                    cycle: cycles,
                    wear_nm: odo.wear_nm(),
                    remaining_cycles: odo.remaining_cycles(),
                    estimate: technician.then(|| rig.ctrl.wear_estimate()),
                });
            }
        }
        match rig.ctrl.state() {
            State::Idle if !rig.ctrl.persist_pending() && !checkpoint_due => {
                if cycles >= opts.cycles || limit_at.is_some() {
                    break;
                }
                rig.ctrl.request(Request::StartCycle);
            }
            State::Faulted { .. } => break,
            _ => {}
        }
    }
    let odo = rig.ctrl.odometer();
    let life_cycles = limit_at.unwrap_or(odo.cone().cycles.saturating_add(odo.remaining_cycles()));
    LifeReport {
        material: opts.material,
        points,
        not_reached: next_at.collect(),
        life_cycles,
        limit_reached: limit_at.is_some(),
        cycles_run: odo.cone().cycles,
        erases_per_sector_max: rig
            .flash
            .with(|f| f.erase_counts().iter().copied().max().unwrap_or(0)),
        faults: rig.ctrl.fault_count(),
        sim_time_s: rig.clock.now_s(),
        wall_time_s: started.elapsed().as_secs_f64(),
    }
}

/// About this many points on a `--plot` curve (plus 1, 2, 5, 10, 20, 50, … early on,
/// where the wear rises fastest).
pub const CURVE_POINTS: u32 = 300;

/// Cycles at which a wear curve of an `n`-cycle run is sampled: [`CURVE_POINTS`] evenly
/// spaced, and 1, 2, 5, 10, 20, 50, … below `n`.
pub fn curve_checkpoints(n: u32) -> Vec<u32> {
    let mut v: Vec<u32> = (1..=CURVE_POINTS)
        .map(|i| (n as u64 * i as u64 / CURVE_POINTS as u64) as u32)
        .chain(
            std::iter::successors(Some(1u32), |x| x.checked_mul(10))
                .flat_map(|d| [d, 2 * d, 5 * d])
                .take_while(|&x| x < n),
        )
        .filter(|&c| (1..=n).contains(&c))
        .collect();
    v.sort_unstable();
    v.dedup();
    v
}

/// [`run`], with the wear also taken at the cycles of `curve` (for `--plot`): the report
/// is the one [`run`] gives for `opts` (the curve's checkpoints are not in it), and the
/// curve's points come apart, the report's checkpoints among them.
pub fn run_with_curve(opts: &LifeOptions, curve: &[u32]) -> (LifeReport, Vec<LifePoint>) {
    let mut all: Vec<u32> = opts.at.iter().chain(curve).copied().collect();
    all.sort_unstable();
    all.dedup();
    let mut report = run(&LifeOptions {
        at: all.clone(),
        ..opts.clone()
    });
    // `run` takes one point per checkpoint, in order, until the cone is worn out.
    let curve_points = std::mem::take(&mut report.points);
    report.points = all
        .iter()
        .zip(&curve_points)
        .filter(|(c, _)| opts.at.contains(c))
        .map(|(_, p)| *p)
        .collect();
    report.not_reached = all
        .iter()
        .skip(curve_points.len())
        .filter(|c| opts.at.contains(c))
        .copied()
        .collect();
    (report, curve_points)
}

fn mm(nm: u32) -> String {
    format!("{}.{:06}", nm / 1_000_000, nm % 1_000_000)
}

impl LifeReport {
    /// One JSON object on one line.
    pub fn to_json(&self) -> String {
        let pts: Vec<String> = self
            .points
            .iter()
            .map(|p| {
                let est = p.estimate.map_or(String::new(), |e| {
                    format!(
                        ",\"wear_estimate_mm\":{},\"estimate_low_mm\":{},\"estimate_high_mm\":{},\"remaining_estimate_cycles\":{},\"remaining_estimate_low_cycles\":{},\"remaining_estimate_high_cycles\":{}",
                        mm(e.wear_nm),
                        mm(e.low_nm),
                        mm(e.high_nm),
                        e.remaining_cycles,
                        e.remaining_low_cycles,
                        e.remaining_high_cycles
                    )
                });
                format!(
                    "{{\"cycle\":{},\"wear_mm\":{},\"remaining_cycles\":{}{est}}}",
                    p.cycle,
                    mm(p.wear_nm),
                    p.remaining_cycles
                )
            })
            .collect();
        format!(
            "{{\"material\":\"{}\",\"points\":[{}],\"not_reached\":{:?},\"life_cycles\":{},\"limit_reached\":{},\"cycles_run\":{},\"erases_per_sector_max\":{},\"faults\":{},\"sim_time_s\":{:.1},\"wall_time_s\":{:.3}}}",
            self.material.name(),
            pts.join(","),
            self.not_reached,
            self.life_cycles,
            self.limit_reached,
            self.cycles_run,
            self.erases_per_sector_max,
            self.faults,
            self.sim_time_s,
            self.wall_time_s
        )
    }

    /// A table and a summary line.
    pub fn to_text(&self) -> String {
        let estimates = self.points.iter().any(|p| p.estimate.is_some());
        let mut s = String::from(if estimates {
            "cycle,wear_mm,remaining_cycles,wear_estimate_mm,estimate_low_mm,estimate_high_mm,remaining_estimate_cycles,remaining_estimate_low_cycles,remaining_estimate_high_cycles\n"
        } else {
            "cycle,wear_mm,remaining_cycles\n"
        });
        for p in &self.points {
            s += &format!("{},{},{}", p.cycle, mm(p.wear_nm), p.remaining_cycles);
            if let Some(e) = p.estimate {
                s += &format!(
                    ",{},{},{},{},{},{}",
                    mm(e.wear_nm),
                    mm(e.low_nm),
                    mm(e.high_nm),
                    e.remaining_cycles,
                    e.remaining_low_cycles,
                    e.remaining_high_cycles
                );
            }
            s += "\n";
        }
        if !self.not_reached.is_empty() {
            s += &format!(
                "# not reached (the cone hit its wear limit at cycle {} and the controller refuses to dock it): {:?}\n",
                self.life_cycles, self.not_reached
            );
        }
        // Which life: the cycle the controller locked the cone out at, or the model's
        // extrapolation; and the estimate's, from the last reading, beside it by name.
        let life = if self.limit_reached {
            format!(
                "worn out at cycle {} (the controller locked the cone out)",
                self.life_cycles
            )
        } else {
            format!(
                "the model's life {} cycles (extrapolated)",
                self.life_cycles
            )
        };
        let estimate = self
            .points
            .iter()
            .rev()
            .find_map(|p| p.estimate.map(|e| (p.cycle, e.remaining_cycles)))
            .filter(|_| !self.limit_reached)
            .map_or(String::new(), |(c, r)| {
                format!(
                    "; the estimate's life {} cycles (from the readings, at cycle {c})",
                    u64::from(c) + u64::from(r)
                )
            });
        s += &format!(
            "# {}: {life}{estimate}; {} cycles run, {} fault(s), erases per sector max {}, {:.0} s simulated in {:.2} s",
            self.material.name(),
            self.cycles_run,
            self.faults,
            self.erases_per_sector_max,
            self.sim_time_s,
            self.wall_time_s
        );
        s
    }
}

/// What an endurance run found.
#[derive(Clone, Debug)]
pub struct EnduranceReport {
    /// Lifetime cycles run.
    pub cycles_run: u32,
    /// Cones used (each replaced when it reached its wear limit).
    pub cones_used: u16,
    /// Erases of each odometer flash sector.
    pub erase_counts: Vec<u32>,
    /// Wall time, s.
    pub wall_time_s: f64,
}

/// `cycles` closed-loop cycles on one machine; a technician replaces the cone (same
/// material) each time the controller refuses to dock because the cone is worn out.
pub fn endurance(
    cycles: u32,
    rate_sps: u32,
    material: Material,
) -> Result<EnduranceReport, String> {
    endurance_with_progress(cycles, rate_sps, material, &mut |_, _| {})
}

/// [`endurance`], telling `progress(done, total)` each completed cycle.
pub fn endurance_with_progress(
    cycles: u32,
    rate_sps: u32,
    material: Material,
    progress: &mut dyn FnMut(u32, u32),
) -> Result<EnduranceReport, String> {
    let started = Instant::now();
    let mut reported = u32::MAX;
    let mut rig = Rig::new(RigOptions {
        material,
        ..RigOptions::new(rate_sps)
    });
    loop {
        rig.tick();
        match rig.ctrl.state() {
            State::Idle if !rig.ctrl.persist_pending() => {
                let done = rig.ctrl.odometer().lifetime().cycles;
                if done != reported {
                    reported = done;
                    progress(done, cycles);
                }
                if done >= cycles {
                    break;
                }
                if rig.ctrl.odometer().level() == WearLevel::Limit {
                    let serial =
                        format!("E-{}", rig.ctrl.odometer().lifetime().cones_installed + 1);
                    rig.ctrl
                        .replace_cone(material, &serial)
                        .map_err(|e| e.to_string())?;
                }
                rig.ctrl.request(Request::StartCycle);
            }
            State::Faulted { fault } => return Err(format!("fault {}", fault.name())),
            _ => {}
        }
    }
    Ok(EnduranceReport {
        cycles_run: rig.ctrl.odometer().lifetime().cycles,
        cones_used: rig.ctrl.odometer().lifetime().cones_installed,
        erase_counts: rig.flash.with(|f| f.erase_counts().to_vec()),
        wall_time_s: started.elapsed().as_secs_f64(),
    })
}
