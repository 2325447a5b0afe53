//! `hil-sim signature-study`: can the docking signature see wear? (issue 34)
//!
//! The plant (Eqs. 3–6, [`crate::plant`]) with the bore worn by `w` (D2 = 26 mm + w)
//! drives the rig's load cell; the firmware's own capture, figures and objects judge
//! every docking (the controller on the simulated HAL, as every scene). For each sample
//! rate and wear, `dockings` dockings with the load cell's noise and spikes at the
//! paper's frictions, and as many with µ1 and µ2 drawn per docking within ± 20 %; and at
//! no wear, all dockings with both frictions 20 % up, then 20 % down (a guide that dries
//! or is greased as a whole: a drift, not a spread). Per figure of the insertion (the
//! 3→4 step's depth, the phase-4 plateau, the work ∫F·dx, the end force at MATED) and
//! the extraction's peak:
//!
//! * `slope`: how it moves with wear, per µm (the fit of its means at the paper's
//!   frictions over the wear levels up to [`FIT_MAX_UM`]);
//! * `sd`: its spread from one docking to the next (noise, spikes, the grid, the
//!   frictions' spread), at no wear;
//! * `drift`: the largest shift of its mean under the frictions' ± 20 % drift;
//! * `min_wear_um[N]`: the smallest wear its mean over `N` dockings tells from the
//!   reference's (the mean of as many) at 95 % (two-sided): `1.96 · sd · √(2/N) /
//!   |slope|`; and `floor_um`: the wear a friction drift alone mimics, `drift / |slope|`
//!   (averaging does not remove it).
//!
//! And the firmware's own wear estimate from the step
//! ([`docking_logic::signature::stepwear`]) after each level's dockings at the paper's
//! frictions, against the study's first dockings at no wear as the cone's reference.
//!
//! The step's depth is also compared with the plant's own 3→4 boundary (the geometry:
//! `L* = (D2 − D1·cos θ0)/sin θ0`, mapped to the firmware's depth as §8.3 of
//! docs/physics.md says): its error (bias and spread) is the grid's and the sample
//! rate's. And the verdicts: the share of dockings NOK at each wear, and the first object
//! failed (the objects sit on the design's curve: a worn cone's step leaves them).

use std::rc::Rc;

use docking_logic::config::MachineConfig;
use docking_logic::profile::{STROKE_UM, V0_UM_PER_S};
use docking_logic::sequencer::{Request, State};
use docking_logic::signature::records::Summary;

use crate::machine::ForceModel;
use crate::plant::{Plant, PlantParams};
use crate::rig::{Rig, RigOptions};
use crate::rng::Rng;

/// Wear levels of the study, µm.
pub const WEAR_UM: [f64; 7] = [0.0, 10.0, 25.0, 50.0, 100.0, 200.0, 400.0];
/// The slopes are fitted over wear up to this, µm.
pub const FIT_MAX_UM: f64 = 100.0;
/// The frictions' spread and drift, ± this fraction.
pub const MU_SPREAD: f64 = 0.2;
/// Dockings averaged, for `min_wear_um`.
pub const AVERAGED: [u32; 3] = [1, 20, 100];

/// The figures of the study, in order.
pub const FIGURES: [&str; 5] = [
    "step_um",
    "plateau_mn",
    "work_mnmm",
    "end_mn",
    "ext_peak_mn",
];

fn figures_of(s: &Summary) -> [Option<f64>; 5] {
    [
        s.step_um.map(f64::from),
        Some(f64::from(s.plateau_mn)),
        Some(f64::from(s.work_mnmm)),
        Some(f64::from(s.end_mn)),
        Some(f64::from(s.ext_peak_mn)),
    ]
}

/// The plant's N3 per step of insertion depth (the rig's profile's form: the rig's
/// `script.profile_n`), with the bore worn by `wear_um` and the frictions scaled by
/// `mu1`, `mu2`.
pub fn table(machine: &MachineConfig, wear_um: f64, mu1: f64, mu2: f64) -> Rc<Vec<f64>> {
    let mut p = PlantParams::PAPER;
    p.geometry.d2_mm += wear_um / 1000.0;
    p.mu1 *= mu1;
    p.mu2 *= mu2;
    let um_per_step = 1000.0 / f64::from(machine.steps_per_mm);
    let Ok(m) = ForceModel::plant(p) else {
        return Rc::new(Vec::new());
    };
    Rc::new(
        (0..=machine.um_to_steps(STROKE_UM))
            .map(|k| m.n3_at_depth_um(f64::from(k) * um_per_step))
            .collect(),
    )
}

/// The plant's 3→4 boundary as the firmware's depth, µm, at `wear_um`.
pub fn true_step_um(wear_um: f64) -> f64 {
    let mut p = PlantParams::PAPER;
    p.geometry.d2_mm += wear_um / 1000.0;
    Plant::new(p).map_or(f64::NAN, |pl| pl.boundaries_s()[2] * f64::from(V0_UM_PER_S))
}

/// One docking's outcome.
#[derive(Clone, Debug)]
pub struct Docked {
    /// The figures ([`FIGURES`]).
    pub figures: [Option<f64>; 5],
    /// The first object failed (`None`: OK).
    pub failed: Option<&'static str>,
}

/// Run `n` dockings on `rig`, each with the N3 table `profile(k)`.
fn dock(rig: &mut Rig, n: u32, profile: &mut dyn FnMut(u32) -> Rc<Vec<f64>>) -> Vec<Docked> {
    let mut out = Vec::new();
    for k in 0..n {
        rig.devices().script.borrow_mut().profile_n = Some(profile(k));
        let done = rig.ctrl.status().cycles_completed;
        rig.ctrl.request(Request::StartCycle);
        for _ in 0..200_000 {
            rig.tick();
            while rig.ctrl.next_event().is_some() {}
            let st = rig.ctrl.status();
            if st.state == State::Idle && st.cycles_completed > done {
                break;
            }
            if matches!(st.state, State::Faulted { .. }) {
                break;
            }
        }
        // The rest: the monitor judges the extraction in the service's window.
        for _ in 0..5 {
            rig.tick();
        }
        if let Some(s) = rig.ctrl.signature().last() {
            out.push(Docked {
                figures: figures_of(s),
                failed: s.failure.map(|f| f.object.name()),
            });
        }
    }
    out
}

fn mean_sd(v: &[f64]) -> (f64, f64) {
    let n = v.len().max(1) as f64;
    let m = v.iter().sum::<f64>() / n;
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1.0).max(1.0);
    (m, var.sqrt())
}

fn column(d: &[Docked], f: usize) -> Vec<f64> {
    d.iter().filter_map(|x| x.figures[f]).collect()
}

/// One wear level at one rate.
#[derive(Clone, Debug)]
pub struct Level {
    /// Wear, µm.
    pub wear_um: f64,
    /// The plant's step (the truth), µm of depth.
    pub true_step_um: f64,
    /// Per figure: mean and sd at the paper's frictions.
    pub nominal: Vec<(f64, f64)>,
    /// Per figure: mean and sd with the frictions' spread.
    pub spread: Vec<(f64, f64)>,
    /// NOK dockings (both runs) and of how many.
    pub nok: (usize, usize),
    /// The first objects failed, most frequent first.
    pub failed: Vec<(&'static str, usize)>,
    /// The firmware's wear estimate from the step after this level's dockings at the
    /// paper's frictions (the reference: the first dockings of the study, at no wear):
    /// µm, its band ± µm, the dockings it rests on; `None` with fewer dockings a level
    /// than its window (the window would mix levels).
    pub estimate: Option<(f64, f64, u8)>,
}

/// A figure's sensitivity at one rate.
#[derive(Clone, Debug)]
pub struct Sensitivity {
    /// [`FIGURES`]'s name.
    pub figure: &'static str,
    /// Change per µm of wear.
    pub slope: f64,
    /// Spread per docking (noise, the grid, the frictions' spread), at no wear.
    pub sd: f64,
    /// Largest shift under the frictions' ± 20 % drift.
    pub drift: f64,
    /// The smallest wear told at 95 % after [`AVERAGED`] dockings, µm.
    pub min_wear_um: Vec<f64>,
    /// The wear a friction drift mimics, µm.
    pub floor_um: f64,
}

/// The study at one rate.
#[derive(Clone, Debug)]
pub struct RateStudy {
    /// Samples a second.
    pub rate_sps: u32,
    /// Per wear level.
    pub levels: Vec<Level>,
    /// Per figure.
    pub sensitivity: Vec<Sensitivity>,
    /// The step's error against the plant's boundary at the paper's frictions, over
    /// the wear levels: the largest |mean − truth| and the largest sd, µm.
    pub step_error_um: (f64, f64),
}

/// Run the study: `dockings` a point, at each of `rates`.
pub fn run(dockings: u32, rates: &[u32], seed: u64) -> Vec<RateStudy> {
    let machine = MachineConfig::DEFAULT;
    let mut out = Vec::new();
    for &rate in rates {
        let mut rng = Rng::new(seed ^ u64::from(rate));
        let mut rig = Rig::booted(RigOptions {
            seed: seed.wrapping_add(u64::from(rate)),
            ..RigOptions::new(rate)
        });
        let mut levels = Vec::new();
        for &w in &WEAR_UM {
            let fixed = table(&machine, w, 1.0, 1.0);
            let nominal = dock(&mut rig, dockings, &mut |_| fixed.clone());
            let window = u32::from(machine_window());
            let estimate = rig
                .ctrl
                .signature_status()
                .step_wear
                .filter(|e| {
                    u32::from(e.dockings) <= dockings.saturating_sub(window * u32::from(w == 0.0))
                })
                .map(|e| {
                    (
                        f64::from(e.wear_nm) / 1e3,
                        f64::from(e.band_nm) / 1e3,
                        e.dockings,
                    )
                });
            let spread = dock(&mut rig, dockings, &mut |_| {
                let a = 1.0 + MU_SPREAD * (2.0 * rng.uniform() - 1.0);
                let b = 1.0 + MU_SPREAD * (2.0 * rng.uniform() - 1.0);
                table(&machine, w, a, b)
            });
            let all: Vec<&Docked> = nominal.iter().chain(&spread).collect();
            let mut failed: Vec<(&'static str, usize)> = Vec::new();
            for d in &all {
                if let Some(o) = d.failed {
                    match failed.iter_mut().find(|(n, _)| *n == o) {
                        Some(e) => e.1 += 1,
                        None => failed.push((o, 1)),
                    }
                }
            }
            failed.sort_by_key(|e| std::cmp::Reverse(e.1));
            levels.push(Level {
                wear_um: w,
                true_step_um: true_step_um(w),
                nominal: (0..FIGURES.len())
                    .map(|f| mean_sd(&column(&nominal, f)))
                    .collect(),
                spread: (0..FIGURES.len())
                    .map(|f| mean_sd(&column(&spread, f)))
                    .collect(),
                nok: (all.iter().filter(|d| d.failed.is_some()).count(), all.len()),
                failed,
                estimate,
            });
        }
        // The frictions' drift at no wear: both up, both down.
        let drifted: Vec<Vec<(f64, f64)>> = [1.0 + MU_SPREAD, 1.0 - MU_SPREAD]
            .iter()
            .map(|&k| {
                let t = table(&machine, 0.0, k, k);
                let d = dock(&mut rig, dockings, &mut |_| t.clone());
                (0..FIGURES.len())
                    .map(|f| mean_sd(&column(&d, f)))
                    .collect()
            })
            .collect();
        let sensitivity = FIGURES
            .iter()
            .enumerate()
            .map(|(f, &name)| {
                let pts: Vec<(f64, f64)> = levels
                    .iter()
                    .filter(|l| l.wear_um <= FIT_MAX_UM && l.nominal[f].0.is_finite())
                    .map(|l| (l.wear_um, l.nominal[f].0))
                    .collect();
                let slope = fit_slope(&pts);
                let base = levels[0].nominal[f].0;
                let sd = levels[0].spread[f].1;
                let drift = drifted
                    .iter()
                    .map(|d| (d[f].0 - base).abs())
                    .fold(0.0, f64::max);
                let per = |x: f64| {
                    if slope.abs() > 1e-12 {
                        x / slope.abs()
                    } else {
                        f64::INFINITY
                    }
                };
                Sensitivity {
                    figure: name,
                    slope,
                    sd,
                    drift,
                    min_wear_um: AVERAGED
                        .iter()
                        .map(|&n| per(1.96 * sd * (2.0 / f64::from(n)).sqrt()))
                        .collect(),
                    floor_um: per(drift),
                }
            })
            .collect();
        let step_error_um = levels.iter().filter(|l| l.nominal[0].0.is_finite()).fold(
            (0.0f64, 0.0f64),
            |(b, s), l| {
                (
                    b.max((l.nominal[0].0 - l.true_step_um).abs()),
                    s.max(l.nominal[0].1),
                )
            },
        );
        out.push(RateStudy {
            rate_sps: rate,
            levels,
            sensitivity,
            step_error_um,
        });
    }
    out
}

/// The wear estimate's window (M dockings) and the reference's size, as the firmware
/// is configured.
fn machine_window() -> u8 {
    docking_logic::signature::objects::SignatureConfig::DEFAULT.wear_window
}

/// The least-squares slope of `pts`.
fn fit_slope(pts: &[(f64, f64)]) -> f64 {
    let n = pts.len() as f64;
    if n < 2.0 {
        return f64::NAN;
    }
    let (mx, my) = (
        pts.iter().map(|p| p.0).sum::<f64>() / n,
        pts.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    sxy / sxx
}

/// A figure in its natural unit: µm as mm, mN as N, mN·mm as N·mm.
fn unit(figure: &str) -> (&'static str, f64) {
    match figure {
        "step_um" => ("mm", 1e-3),
        "work_mnmm" => ("N·mm", 1e-3),
        _ => ("N", 1e-3),
    }
}

/// A table for a terminal.
pub fn to_text(studies: &[RateStudy], dockings: u32) -> String {
    let mut s = format!(
        "# can the signature see wear? the plant with D2 = 26 mm + wear; {dockings} dockings a point at the paper's frictions and {dockings} with µ1, µ2 each within ±{:.0} %; the load cell's noise and spikes\n",
        MU_SPREAD * 100.0
    );
    for r in studies {
        s += &format!("\n## {} SPS\n", r.rate_sps);
        s += "wear_um | true step mm | step mm (sd) | plateau N | work N·mm | end N | ext. peak N | NOK | first object failed\n";
        for l in &r.levels {
            let f = |k: usize| {
                let (u, k2) = unit(FIGURES[k]);
                let _ = u;
                l.nominal[k].0 * k2
            };
            s += &format!(
                "{:>7.0} | {:>11.3} | {:>7.3} ({:.3}) | {:>9.1} | {:>9.0} | {:>5.1} | {:>11.1} | {:>3}/{} | {}\n",
                l.wear_um,
                l.true_step_um * 1e-3,
                f(0),
                l.nominal[0].1 * 1e-3,
                f(1),
                f(2),
                f(3),
                f(4),
                l.nok.0,
                l.nok.1,
                l.failed
                    .iter()
                    .map(|(o, n)| format!("{o} ×{n}"))
                    .collect::<Vec<_>>()
                    .join(", ")
            );
        }
        s += "the firmware's wear estimate from the step (the reference: the first dockings at no wear), after each level's dockings at the paper's frictions:\n";
        for l in &r.levels {
            match l.estimate {
                Some((e, b, n)) => {
                    s += &format!(
                        "{:>7.0} µm of wear: estimate {e:.1} ± {b:.1} µm ({n} dockings){}\n",
                        l.wear_um,
                        if (e - l.wear_um).abs() <= b {
                            ""
                        } else {
                            "  OUTSIDE its band"
                        }
                    )
                }
                None => s += &format!("{:>7.0} µm of wear: no estimate\n", l.wear_um),
            }
        }
        s += &format!(
            "the step against the plant's boundary: bias up to {:.0} µm, sd up to {:.0} µm (the grid: 234 µm bins; the sample rate)\n",
            r.step_error_um.0, r.step_error_um.1
        );
        s += "figure | per µm of wear | sd a docking | friction drift ±20 % | smallest wear told at 95 % after 1 / 20 / 100 dockings | a friction drift mimics\n";
        for x in &r.sensitivity {
            let (u, k) = unit(x.figure);
            let w: Vec<String> = x.min_wear_um.iter().map(|w| format!("{w:.1}")).collect();
            s += &format!(
                "{} | {:+.4} {u} | {:.3} {u} | {:.3} {u} | {} µm | {:.1} µm\n",
                x.figure,
                x.slope * k,
                x.sd * k,
                x.drift * k,
                w.join(" / "),
                x.floor_um
            );
        }
    }
    s
}

/// One JSON object.
pub fn to_json(studies: &[RateStudy], dockings: u32) -> String {
    let num = |x: f64| {
        if x.is_finite() {
            format!("{x:.4}")
        } else {
            "null".into()
        }
    };
    let rates: Vec<String> = studies
        .iter()
        .map(|r| {
            let levels: Vec<String> = r
                .levels
                .iter()
                .map(|l| {
                    let figs: Vec<String> = FIGURES
                        .iter()
                        .enumerate()
                        .map(|(k, n)| {
                            format!(
                                "\"{n}\":{{\"mean\":{},\"sd\":{},\"spread_mean\":{},\"spread_sd\":{}}}",
                                num(l.nominal[k].0),
                                num(l.nominal[k].1),
                                num(l.spread[k].0),
                                num(l.spread[k].1)
                            )
                        })
                        .collect();
                    let failed: Vec<String> = l
                        .failed
                        .iter()
                        .map(|(o, n)| format!("{{\"object\":\"{o}\",\"dockings\":{n}}}"))
                        .collect();
                    let estimate = l.estimate.map_or("null".to_string(), |(e, b, n)| {
                        format!("{{\"wear_um\":{},\"band_um\":{},\"dockings\":{n}}}", num(e), num(b))
                    });
                    format!(
                        "{{\"wear_um\":{},\"true_step_um\":{},{},\"nok\":{},\"dockings\":{},\"failed\":[{}],\"estimate\":{}}}",
                        num(l.wear_um),
                        num(l.true_step_um),
                        figs.join(","),
                        l.nok.0,
                        l.nok.1,
                        failed.join(","),
                        estimate
                    )
                })
                .collect();
            let sens: Vec<String> = r
                .sensitivity
                .iter()
                .map(|x| {
                    format!(
                        "{{\"figure\":\"{}\",\"slope_per_um\":{},\"sd\":{},\"drift\":{},\"min_wear_um\":[{}],\"floor_um\":{}}}",
                        x.figure,
                        num(x.slope),
                        num(x.sd),
                        num(x.drift),
                        x.min_wear_um.iter().map(|w| num(*w)).collect::<Vec<_>>().join(","),
                        num(x.floor_um)
                    )
                })
                .collect();
            format!(
                "{{\"rate_sps\":{},\"levels\":[{}],\"sensitivity\":[{}],\"step_bias_um\":{},\"step_sd_um\":{}}}",
                r.rate_sps,
                levels.join(","),
                sens.join(","),
                num(r.step_error_um.0),
                num(r.step_error_um.1)
            )
        })
        .collect();
    format!(
        "{{\"dockings\":{dockings},\"mu_spread\":{MU_SPREAD},\"averaged\":{:?},\"rates\":[{}]}}",
        AVERAGED,
        rates.join(",")
    )
}
