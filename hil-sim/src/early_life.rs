//! The wear band early in a cone's life (issue 36): part of `hil-sim accuracy`.
//!
//! A new cone is measured every 100 cycles from 100 to 500 ([`READINGS_AT`], the paper's
//! protocol) while it runs in; the planner then wants the wear at 600–10 000 cycles
//! ([`HORIZONS`]) and the remaining life. The cones follow laws the model does not
//! ([`LAWS`]): pure power laws with exponents 0.25–0.6, two-regime running-in
//! (near-linear for a few hundred cycles, then a power law with a lower exponent), the
//! model itself and the late study's running-in bump; each cone is one of its law
//! scaled by a factor drawn uniformly from 1 ± [`SCALE_SPREAD`] (cone to cone), read
//! with the micrometer's 3 µm noise and rounded to its 1 µm resolution, [`SEEDS`] cones
//! per law. Per law and horizon the study reports the estimate's error, the model's, the
//! band's width, the share of cones whose truth is inside the band, and the band's
//! interval score (Gneiting & Raftery 2007, α = 0.05: the width plus 2/α times how far
//! the truth falls outside, so a band that is merely wide does not win).
//!
//! Then the remaining life ([`LifeRow`]): where each rule — the band's upper edge (what
//! the controller acts on), the point estimate, the model — would lock the cone out,
//! against where the truth reaches the limit: the cycles it refuses before the truth
//! reaches the limit (life lost), and the cones and cycles it lets the truth run past
//! the limit undetected (the risk). Once with the readings 100–500 alone (the
//! lock-out is then a prediction from the running-in), once with a reading every
//! [`LIFE_READING_EVERY`] cycles after them (the controller refits at each, and locks
//! out at the first cycle whose band reaches the limit).
//!
//! The truth of every law, unscaled, is the model's wear at 1 000 cycles there
//! ([`ANCHOR_CYCLES`]): the laws differ in shape, the scale spread does the rest.

use docking_logic::estimate::{Fit, Reading};
use docking_logic::material::Material;
use docking_logic::odometer::READINGS_KEPT;

use crate::accuracy::{depth_f64_nm, WearLaw};
use crate::rng::Rng;

/// Readings of the early-life protocol, cycles (nominal load: E = cycles).
pub const READINGS_AT: [u32; 5] = [100, 200, 300, 400, 500];
/// Where the estimate and its band are judged, cycles.
pub const HORIZONS: [u32; 6] = [600, 800, 1_000, 1_500, 5_000, 10_000];
/// Cones per law.
pub const SEEDS: u64 = 100;
/// Cone-to-cone scale: uniform on 1 ± this.
pub const SCALE_SPREAD: f64 = 0.3;
/// The micrometer's noise, µm (σ), before rounding to its 1 µm resolution.
pub const NOISE_UM: f64 = 3.0;
/// Where every law, unscaled, meets the model, cycles.
pub const ANCHOR_CYCLES: f64 = 1_000.0;
/// The wear limit of the life rows, nm (the default configuration's 0.8 mm).
pub const LIMIT_NM: u32 = 800_000;
/// After the early readings, one reading every this many cycles (the life rows'
/// second protocol).
pub const LIFE_READING_EVERY: u32 = 1_000;
/// The life rows look this far, cycles: a cone whose truth and lock-out both lie
/// beyond is counted as such, not simulated further.
pub const LIFE_HORIZON: u32 = 200_000;
/// The interval score's α (a ≈ 95 % band).
pub const ALPHA: f64 = 0.05;
/// Sharpness of the two-regime laws' knee: `g(x) = x / (1 + x^P)^((1 − b)/P)`.
const KNEE_P: f64 = 2.0;

/// The shape of a law.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Shape {
    /// Eq. 17 itself.
    Model,
    /// `K·m^b`.
    Power(f64),
    /// Near-linear to `end` cycles, then `m^settled`: `K·g(m/end)` with
    /// `g(x) = x / (1 + x²)^((1 − settled)/2)`.
    RunIn {
        /// Cycles where the running-in ends (the knee).
        end: f64,
        /// The settled exponent.
        settled: f64,
    },
    /// The late study's running-in ([`WearLaw::RunningIn`]): 0.9 × the model plus a
    /// 25 µm bump over the first few hundred cycles (not re-anchored).
    Bump,
}

/// One law of the study.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Law {
    /// Name for reports.
    pub name: &'static str,
    /// Its shape.
    pub shape: Shape,
}

/// The laws of the study.
pub const LAWS: [Law; 11] = [
    Law {
        name: "model",
        shape: Shape::Model,
    },
    Law {
        name: "power-0.25",
        shape: Shape::Power(0.25),
    },
    Law {
        name: "power-0.33",
        shape: Shape::Power(0.33),
    },
    Law {
        name: "power-0.43",
        shape: Shape::Power(0.43),
    },
    Law {
        name: "power-0.50",
        shape: Shape::Power(0.5),
    },
    Law {
        name: "power-0.60",
        shape: Shape::Power(0.6),
    },
    Law {
        name: "run-in-200/0.25",
        shape: Shape::RunIn {
            end: 200.0,
            settled: 0.25,
        },
    },
    Law {
        name: "run-in-300/0.30",
        shape: Shape::RunIn {
            end: 300.0,
            settled: 0.3,
        },
    },
    Law {
        name: "run-in-400/0.38",
        shape: Shape::RunIn {
            end: 400.0,
            settled: 0.38,
        },
    },
    Law {
        name: "run-in-500/0.30",
        shape: Shape::RunIn {
            end: 500.0,
            settled: 0.3,
        },
    },
    Law {
        name: "bump-25",
        shape: Shape::Bump,
    },
];

/// The model's wear after `m` nominal cycles, µm (`f64`).
pub fn model_um(m: f64) -> f64 {
    depth_f64_nm(m) / 1000.0
}

fn knee(x: f64, settled: f64) -> f64 {
    x / (1.0 + x.powf(KNEE_P)).powf((1.0 - settled) / KNEE_P)
}

impl Law {
    /// The law's wear after `m` nominal cycles, unscaled, µm.
    pub fn um(&self, m: f64) -> f64 {
        let anchor = model_um(ANCHOR_CYCLES);
        match self.shape {
            Shape::Model => model_um(m),
            Shape::Power(b) => anchor * (m / ANCHOR_CYCLES).powf(b),
            Shape::RunIn { end, settled } => {
                anchor * knee(m / end, settled) / knee(ANCHOR_CYCLES / end, settled)
            }
            Shape::Bump => WearLaw::RunningIn.um(m),
        }
    }

    /// Whether the law is the model's own shape (the model's error is the scale's only).
    pub fn is_model(&self) -> bool {
        self.shape == Shape::Model
    }
}

/// One cone of a law: its scale and its readings.
#[derive(Clone, Debug)]
pub struct Cone {
    /// The law.
    pub law: Law,
    /// Its scale (1 ± [`SCALE_SPREAD`]).
    pub scale: f64,
    rng: Rng,
}

impl Cone {
    /// Cone `seed` of `law`.
    pub fn new(law: Law, seed: u64) -> Self {
        let mut rng = Rng::new(0x3600_0000 + seed);
        let scale = 1.0 + SCALE_SPREAD * (2.0 * rng.uniform() - 1.0);
        Self { law, scale, rng }
    }

    /// Its true wear after `m` cycles, µm.
    pub fn um(&self, m: f64) -> f64 {
        self.scale * self.law.um(m)
    }

    /// A reading at `m` cycles: the truth, σ = [`NOISE_UM`], rounded to 1 µm.
    pub fn read(&mut self, m: u32) -> Reading {
        let y_um = (self.um(m as f64) + NOISE_UM * self.rng.normal()).round();
        Reading {
            e_q32: u64::from(m) << 32,
            wear_nm: (y_um * 1000.0) as i32,
        }
    }

    /// Cycles at which the truth reaches `limit_nm` (bisection; the laws are
    /// monotone), or `None` beyond `max`.
    pub fn life(&self, limit_nm: u32, max: f64) -> Option<f64> {
        let lim = limit_nm as f64 / 1000.0;
        first_at_or_above(|m| self.um(m), lim, 0.0, max)
    }
}

/// The smallest `m` in `[lo, hi]` with `f(m) ≥ level`, to 0.5 cycle, assuming `f`
/// increases; `None` if `f(hi)` is below.
fn first_at_or_above(f: impl Fn(f64) -> f64, level: f64, lo: f64, hi: f64) -> Option<f64> {
    if f(hi) < level {
        return None;
    }
    if f(lo) >= level {
        return Some(lo);
    }
    let (mut a, mut b) = (lo, hi);
    while b - a > 0.5 {
        let c = 0.5 * (a + b);
        if f(c) >= level {
            b = c;
        } else {
            a = c;
        }
    }
    Some(b)
}

/// An estimate and its band at one horizon, µm.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Band {
    /// The point estimate.
    pub wear_um: f64,
    /// The band's lower edge.
    pub low_um: f64,
    /// Its upper edge.
    pub high_um: f64,
}

/// What the study judges: readings in, a band at any cycle count out. The firmware's
/// ([`firmware`]) in the report; another (an `f64` candidate, the previous release's)
/// for comparison.
pub trait Estimator {
    /// Fit to `readings` (oldest first) and return the band at each of `at` (cycles).
    fn band(&self, readings: &[Reading], at: &[u32]) -> Vec<Band>;
    /// Fitted to `readings`, the first cycle count in `[from, to]` at which the band's
    /// upper edge, and the one at which the point estimate, reach `limit_nm` (`None`:
    /// not within).
    fn lockouts(&self, readings: &[Reading], from: u32, to: u32, limit_nm: u32)
        -> [Option<u32>; 2];
}

/// The firmware's estimator (`docking_logic::estimate`).
pub struct Firmware;

/// The firmware's estimator.
pub fn firmware() -> Firmware {
    Firmware
}

fn at_fit(f: &Fit, m: f64) -> docking_logic::estimate::Estimate {
    f.at((m * 4_294_967_296.0) as u64, LIMIT_NM, Material::ZQSn5_2)
}

/// The first cycle count in `[from, to]` at which `edge` (nm) reaches `limit_nm`.
pub fn edge_lockout(edge: impl Fn(f64) -> f64, from: u32, to: u32, limit_nm: u32) -> Option<u32> {
    first_at_or_above(edge, limit_nm as f64, from as f64, to as f64).map(|m| m.ceil() as u32)
}

impl Estimator for Firmware {
    fn band(&self, readings: &[Reading], at: &[u32]) -> Vec<Band> {
        let f = Fit::new(readings);
        at.iter()
            .map(|&m| {
                let e = at_fit(&f, m as f64);
                Band {
                    wear_um: e.wear_nm as f64 / 1000.0,
                    low_um: e.low_nm as f64 / 1000.0,
                    high_um: e.high_nm as f64 / 1000.0,
                }
            })
            .collect()
    }

    fn lockouts(
        &self,
        readings: &[Reading],
        from: u32,
        to: u32,
        limit_nm: u32,
    ) -> [Option<u32>; 2] {
        let f = Fit::new(readings);
        [
            edge_lockout(|m| at_fit(&f, m).high_nm as f64, from, to, limit_nm),
            edge_lockout(|m| at_fit(&f, m).wear_nm as f64, from, to, limit_nm),
        ]
    }
}

/// The previous release's estimator ([`crate::previous_estimate`], 7c11783).
pub struct Previous;

impl Estimator for Previous {
    fn band(&self, readings: &[Reading], at: &[u32]) -> Vec<Band> {
        let f = crate::previous_estimate::Fit::new(readings);
        at.iter()
            .map(|&m| {
                let e = f.at(u64::from(m) << 32, LIMIT_NM, Material::ZQSn5_2);
                Band {
                    wear_um: e.wear_nm as f64 / 1000.0,
                    low_um: e.low_nm as f64 / 1000.0,
                    high_um: e.high_nm as f64 / 1000.0,
                }
            })
            .collect()
    }

    fn lockouts(
        &self,
        readings: &[Reading],
        from: u32,
        to: u32,
        limit_nm: u32,
    ) -> [Option<u32>; 2] {
        let f = crate::previous_estimate::Fit::new(readings);
        let at = |m: f64| f.at((m * 4_294_967_296.0) as u64, LIMIT_NM, Material::ZQSn5_2);
        [
            edge_lockout(|m| at(m).high_nm as f64, from, to, limit_nm),
            edge_lockout(|m| at(m).wear_nm as f64, from, to, limit_nm),
        ]
    }
}

/// One law at one horizon, over [`SEEDS`] cones.
#[derive(Clone, Debug, PartialEq)]
pub struct HorizonRow {
    /// The law.
    pub law: &'static str,
    /// The law is the model's own shape.
    pub model_law: bool,
    /// Cycles.
    pub at: u32,
    /// Mean |estimate − truth|, µm.
    pub estimate_err_um: f64,
    /// Mean |model − truth|, µm.
    pub model_err_um: f64,
    /// Mean band width, µm.
    pub band_um: f64,
    /// Share of cones whose truth is inside the band, %.
    pub inside_pct: f64,
    /// Mean interval score (α = [`ALPHA`]), µm.
    pub score_um: f64,
}

/// A lock-out rule of the life rows.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Rule {
    /// The band's upper edge reaches the limit (what the controller acts on).
    Upper,
    /// The point estimate reaches it.
    Point,
    /// The model reaches it (no readings).
    Model,
    /// The controller's rule: the first of the model, the upper edge and a reading at
    /// or past the limit (`Controller::wear_level`).
    Controller,
}

impl Rule {
    /// Every rule, in the life rows' order.
    pub const ALL: [Self; 4] = [Self::Upper, Self::Point, Self::Model, Self::Controller];

    /// Name for reports.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Upper => "upper edge",
            Self::Point => "estimate",
            Self::Model => "model",
            Self::Controller => "controller",
        }
    }
}

/// One law, one protocol, one rule: where it locks the cone out against the truth.
#[derive(Clone, Debug, PartialEq)]
pub struct LifeRow {
    /// The law.
    pub law: &'static str,
    /// Readings after the early ones (every [`LIFE_READING_EVERY`] cycles) or not.
    pub continued: bool,
    /// The rule.
    pub rule: Rule,
    /// Cones whose truth reaches the limit within [`LIFE_HORIZON`].
    pub cones: u32,
    /// Their median true life, cycles.
    pub life_median: f64,
    /// Mean cycles refused before the truth reached the limit (life lost), over them.
    pub refused_mean: f64,
    /// The same as a share of each cone's true life, mean, %.
    pub refused_pct: f64,
    /// Share of them whose truth ran past the limit before the rule locked them out, %.
    pub past_pct: f64,
    /// Mean cycles the truth ran past the limit undetected, over all of them.
    pub past_mean: f64,
}

/// The study's figures.
#[derive(Clone, Debug, PartialEq)]
pub struct EarlyStudy {
    /// By law, then horizon.
    pub rows: Vec<HorizonRow>,
    /// By law, then protocol, then rule.
    pub life: Vec<LifeRow>,
}

/// The interval score of `[lo, hi]` for the truth `x` at level `1 − ALPHA`.
pub fn interval_score(lo: f64, hi: f64, x: f64) -> f64 {
    (hi - lo) + 2.0 / ALPHA * ((lo - x).max(0.0) + (x - hi).max(0.0))
}

/// The early readings of cone `seed` of `law`, and the cone.
pub fn early_readings(law: Law, seed: u64) -> (Cone, Vec<Reading>) {
    let mut cone = Cone::new(law, seed);
    let r = READINGS_AT.iter().map(|&m| cone.read(m)).collect();
    (cone, r)
}

/// The horizon rows of one law at `horizons` (cycles; [`HORIZONS`] in the report).
pub fn horizon_rows(
    est: &dyn Estimator,
    law: Law,
    seeds: u64,
    horizons: &[u32],
) -> Vec<HorizonRow> {
    let n = horizons.len();
    let mut acc = vec![[0.0f64; 5]; n];
    for seed in 0..seeds {
        let (cone, r) = early_readings(law, seed);
        let bands = est.band(&r, horizons);
        for ((a, &m), b) in acc.iter_mut().zip(horizons).zip(&bands) {
            let t = cone.um(m as f64);
            a[0] += (b.wear_um - t).abs();
            a[1] += (model_um(m as f64) - t).abs();
            a[2] += b.high_um - b.low_um;
            a[3] += f64::from(u8::from(b.low_um <= t && t <= b.high_um));
            a[4] += interval_score(b.low_um, b.high_um, t);
        }
    }
    let s = seeds.max(1) as f64;
    horizons
        .iter()
        .zip(acc)
        .map(|(&at, a)| HorizonRow {
            law: law.name,
            model_law: law.is_model(),
            at,
            estimate_err_um: a[0] / s,
            model_err_um: a[1] / s,
            band_um: a[2] / s,
            inside_pct: 100.0 * a[3] / s,
            score_um: a[4] / s,
        })
        .collect()
}

/// Where each rule ([`Rule::ALL`]'s order) locks cone `seed` of `law` out, with the
/// early readings alone or continued, within [`LIFE_HORIZON`]; `None` beyond.
fn lockouts(est: &dyn Estimator, law: Law, seed: u64, continued: bool) -> [Option<u32>; 4] {
    let model = first_at_or_above(model_um, LIMIT_NM as f64 / 1000.0, 0.0, LIFE_HORIZON as f64)
        .map(|m| m.ceil() as u32);
    let (mut cone, mut r) = early_readings(law, seed);
    let last = READINGS_AT.last().copied().unwrap_or(0);
    // (upper edge, estimate, a reading at or past the limit)
    let (mut upper, mut point, mut reading) = (None, None, None);
    if !continued {
        [upper, point] = est.lockouts(&r, last, LIFE_HORIZON, LIMIT_NM);
    } else {
        let mut from = last;
        while from < LIFE_HORIZON && (upper.is_none() || point.is_none()) {
            let next = (from / LIFE_READING_EVERY + 1) * LIFE_READING_EVERY;
            let to = next.min(LIFE_HORIZON);
            let kept = r.len().saturating_sub(READINGS_KEPT);
            let [u, p] = est.lockouts(r.get(kept..).unwrap_or(&[]), from, to, LIMIT_NM);
            upper = upper.or(u);
            point = point.or(p);
            let y = cone.read(next);
            if reading.is_none() && y.wear_nm >= LIMIT_NM as i32 && next <= LIFE_HORIZON {
                reading = Some(next);
            }
            r.push(y);
            from = next;
        }
    }
    let first = |v: [Option<u32>; 3]| v.into_iter().flatten().min();
    [upper, point, model, first([upper, reading, model])]
}

/// The life rows of one law.
pub fn life_rows(est: &dyn Estimator, law: Law, seeds: u64) -> Vec<LifeRow> {
    let mut rows = Vec::new();
    for continued in [false, true] {
        // Per rule: cones, refused, refused %, past, past cycles; lives.
        let mut acc = [(0u32, 0.0f64, 0.0f64, 0u32, 0.0f64); 4];
        let mut lives = Vec::new();
        for seed in 0..seeds {
            let cone = Cone::new(law, seed);
            let Some(life) = cone.life(LIMIT_NM, LIFE_HORIZON as f64) else {
                continue;
            };
            lives.push(life);
            let outs = lockouts(est, law, seed, continued);
            for (a, out) in acc.iter_mut().zip(outs) {
                let out = out.map_or(LIFE_HORIZON as f64, f64::from);
                a.0 += 1;
                if out < life {
                    a.1 += life - out;
                    a.2 += 100.0 * (life - out) / life;
                } else if out > life {
                    a.3 += 1;
                    a.4 += out - life;
                }
            }
        }
        lives.sort_by(f64::total_cmp);
        for (rule, a) in Rule::ALL.into_iter().zip(acc) {
            let k = f64::from(a.0.max(1));
            rows.push(LifeRow {
                law: law.name,
                continued,
                rule,
                cones: a.0,
                life_median: lives.get(lives.len() / 2).copied().unwrap_or(f64::NAN),
                refused_mean: a.1 / k,
                refused_pct: a.2 / k,
                past_pct: 100.0 * f64::from(a.3) / k,
                past_mean: a.4 / k,
            });
        }
    }
    rows
}

/// Run the study with `est` over `seeds` cones per law; `life`: with the life rows
/// (the slow part: a fit per reading over each cone's life).
pub fn study_with(est: &dyn Estimator, seeds: u64, life: bool) -> EarlyStudy {
    let mut s = EarlyStudy {
        rows: Vec::new(),
        life: Vec::new(),
    };
    for law in LAWS {
        s.rows.extend(horizon_rows(est, law, seeds, &HORIZONS));
        if life {
            s.life.extend(life_rows(est, law, seeds));
        }
    }
    s
}

/// The firmware's estimator and the previous release's on the same cones.
#[derive(Clone, Debug, PartialEq)]
pub struct EarlyComparison {
    /// The firmware's (`docking_logic::estimate`).
    pub now: EarlyStudy,
    /// The previous release's (7c11783, [`crate::previous_estimate`]).
    pub previous: EarlyStudy,
    /// Cones per law.
    pub seeds: u64,
}

/// The study of the firmware's estimator and the previous release's, `seeds` cones per
/// law ([`SEEDS`] in the report); `life`: with the life rows.
pub fn early_life_study(seeds: u64, life: bool) -> EarlyComparison {
    EarlyComparison {
        now: study_with(&firmware(), seeds, life),
        previous: study_with(&Previous, seeds, life),
        seeds,
    }
}

/// The point-estimate horizons of the target (600–1 500 cycles).
pub const NEAR: [u32; 4] = [600, 800, 1_000, 1_500];

/// The targets, as the study measures them.
#[derive(Clone, Debug, PartialEq)]
pub struct Targets {
    /// The lowest share of cones whose truth is in the band, any law, any horizon, %
    /// (target ≥ 90).
    pub worst_inside_pct: f64,
    /// Per near horizon, the mean over laws of the estimate's error against the previous
    /// release's (target ≤ 1).
    pub err_vs_previous: Vec<(u32, f64)>,
    /// The largest ratio of the estimate's error to the previous release's for one law
    /// at one near horizon (reported; the target is the mean's).
    pub worst_law_err_vs_previous: (f64, &'static str, u32),
    /// The largest ratio of the estimate's error to the model's, every law but the
    /// model's own at the near horizons (target < 1).
    pub worst_err_vs_model: (f64, &'static str, u32),
}

impl Targets {
    /// Every target met.
    pub fn met(&self) -> bool {
        self.worst_inside_pct >= 90.0
            && self.err_vs_previous.iter().all(|&(_, r)| r <= 1.0)
            && self.worst_err_vs_model.0 < 1.0
    }
}

impl EarlyComparison {
    /// The targets' figures.
    pub fn targets(&self) -> Targets {
        let near = |r: &&HorizonRow| NEAR.contains(&r.at);
        let err_vs_previous = NEAR
            .iter()
            .map(|&h| {
                let sum = |s: &EarlyStudy| {
                    s.rows
                        .iter()
                        .filter(|r| r.at == h)
                        .map(|r| r.estimate_err_um)
                        .sum::<f64>()
                };
                (h, sum(&self.now) / sum(&self.previous))
            })
            .collect();
        let mut worst_prev = (0.0, "", 0);
        for (a, b) in self
            .now
            .rows
            .iter()
            .zip(&self.previous.rows)
            .filter(|(a, _)| near(a))
        {
            let r = a.estimate_err_um / b.estimate_err_um;
            if r > worst_prev.0 {
                worst_prev = (r, a.law, a.at);
            }
        }
        let mut worst_model = (0.0, "", 0);
        for r in self.now.rows.iter().filter(near).filter(|r| !r.model_law) {
            let q = r.estimate_err_um / r.model_err_um;
            if q > worst_model.0 {
                worst_model = (q, r.law, r.at);
            }
        }
        Targets {
            worst_inside_pct: self.now.worst_inside_pct(),
            err_vs_previous,
            worst_law_err_vs_previous: worst_prev,
            worst_err_vs_model: worst_model,
        }
    }

    /// Tables for a terminal: each figure with the previous release's in parentheses.
    pub fn to_text(&self) -> String {
        let mut s = format!(
            "# early life (issue 36): readings at {READINGS_AT:?} cycles (σ {NOISE_UM} µm, 1 µm resolution), the estimate and its ≈95 % band at {HORIZONS:?}; {} cones per law, scale 1 ± {SCALE_SPREAD}; every law meets the model at {ANCHOR_CYCLES} cycles before scaling; interval score α = {ALPHA}; (in parentheses: the previous release, 7c11783)\n",
            self.seeds
        );
        s += "law             |  cycles | estimate err µm | model err µm |         band µm | truth in band % | interval score µm\n";
        for (r, p) in self.now.rows.iter().zip(&self.previous.rows) {
            s += &format!(
                "{:<15} | {:>7} | {:>5.1} ({:>6.1}) | {:>12.1} | {:>5.0} ({:>6.0}) | {:>5.1} ({:>6.1}) | {:>6.0} ({:>7.0})\n",
                r.law,
                r.at,
                r.estimate_err_um,
                p.estimate_err_um,
                r.model_err_um,
                r.band_um,
                p.band_um,
                r.inside_pct,
                p.inside_pct,
                r.score_um,
                p.score_um
            );
        }
        let per = |st: &EarlyStudy| {
            HORIZONS
                .iter()
                .map(|&m| format!("{m}: {:.1}", st.inside_pct_at(m)))
                .collect::<Vec<_>>()
                .join(", ")
        };
        s += &format!(
            "# truth in band over every law, %: {}; lowest of any law and horizon {:.1} (7c11783: {}; lowest {:.1})\n",
            per(&self.now),
            self.now.worst_inside_pct(),
            per(&self.previous),
            self.previous.worst_inside_pct()
        );
        let t = self.targets();
        let ratios: Vec<String> = t
            .err_vs_previous
            .iter()
            .map(|(h, r)| format!("{h}: {r:.2}"))
            .collect();
        s += &format!(
            "# targets: truth in band ≥ 90 % everywhere: lowest {:.1} %; estimate error at 600-1500 over the laws / 7c11783's: {} (one law at worst: {:.2}, {} at {}); estimate error / model's, every law but the model's at 600-1500: at most {:.2} ({} at {}) — {}\n",
            t.worst_inside_pct,
            ratios.join(", "),
            t.worst_law_err_vs_previous.0,
            t.worst_law_err_vs_previous.1,
            t.worst_law_err_vs_previous.2,
            t.worst_err_vs_model.0,
            t.worst_err_vs_model.1,
            t.worst_err_vs_model.2,
            if t.met() { "met" } else { "NOT MET" }
        );
        s += &format!(
            "# remaining life to {} mm: where each rule locks the cone out against where the truth reaches the limit (cones whose truth does within {LIFE_HORIZON} cycles); readings 100-500 alone, or continued every {LIFE_READING_EVERY} cycles; the controller locks out at the first of the upper edge, a reading past the limit and the model\n",
            LIMIT_NM as f64 / 1e6
        );
        s += "law             | readings  | rule       | cones | true life | refused (mean)   | refused % of life | truth past limit % | cycles past (mean)\n";
        for (r, p) in self.now.life.iter().zip(&self.previous.life) {
            s += &format!(
                "{:<15} | {:<9} | {:<10} | {:>5} | {:>9.0} | {:>6.0} ({:>7.0}) | {:>5.1} ({:>9.1}) | {:>5.1} ({:>10.1}) | {:>6.0} ({:>9.0})\n",
                r.law,
                if r.continued { "continued" } else { "100-500" },
                r.rule.name(),
                r.cones,
                r.life_median,
                r.refused_mean,
                p.refused_mean,
                r.refused_pct,
                p.refused_pct,
                r.past_pct,
                p.past_pct,
                r.past_mean,
                p.past_mean
            );
        }
        s
    }

    /// As JSON (an object): `now` and `previous`, each the study's rows.
    pub fn to_json(&self) -> String {
        let t = self.targets();
        format!(
            "{{\"readings_at\":{READINGS_AT:?},\"horizons\":{HORIZONS:?},\"seeds\":{},\"scale_spread\":{SCALE_SPREAD},\"noise_um\":{NOISE_UM},\"alpha\":{ALPHA},\"limit_nm\":{LIMIT_NM},\"life_reading_every\":{LIFE_READING_EVERY},\"life_horizon\":{LIFE_HORIZON},\"targets\":{{\"worst_inside_pct\":{:.1},\"err_vs_previous\":[{}],\"worst_err_vs_model\":{:.3},\"met\":{}}},\"now\":{},\"previous\":{}}}",
            self.seeds,
            t.worst_inside_pct,
            t.err_vs_previous
                .iter()
                .map(|(h, r)| format!("{{\"at_cycles\":{h},\"ratio\":{r:.3}}}"))
                .collect::<Vec<_>>()
                .join(","),
            t.worst_err_vs_model.0,
            t.met(),
            self.now.to_json(),
            self.previous.to_json()
        )
    }
}

impl EarlyStudy {
    /// The lowest coverage at any horizon of any law, %.
    pub fn worst_inside_pct(&self) -> f64 {
        self.rows
            .iter()
            .map(|r| r.inside_pct)
            .fold(f64::INFINITY, f64::min)
    }

    /// Coverage over every law at `at` cycles, %.
    pub fn inside_pct_at(&self, at: u32) -> f64 {
        let v: Vec<f64> = self
            .rows
            .iter()
            .filter(|r| r.at == at)
            .map(|r| r.inside_pct)
            .collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    }

    /// As JSON (an object).
    pub fn to_json(&self) -> String {
        let rows: Vec<String> = self
            .rows
            .iter()
            .map(|r| {
                format!(
                    "{{\"law\":\"{}\",\"at_cycles\":{},\"estimate_err_um\":{:.3},\"model_err_um\":{:.3},\"band_um\":{:.3},\"inside_pct\":{:.1},\"interval_score_um\":{:.3}}}",
                    r.law, r.at, r.estimate_err_um, r.model_err_um, r.band_um, r.inside_pct, r.score_um
                )
            })
            .collect();
        let life: Vec<String> = self
            .life
            .iter()
            .map(|r| {
                format!(
                    "{{\"law\":\"{}\",\"readings\":\"{}\",\"rule\":\"{}\",\"cones\":{},\"life_median_cycles\":{:.0},\"refused_mean_cycles\":{:.1},\"refused_pct_of_life\":{:.2},\"past_limit_pct\":{:.1},\"past_mean_cycles\":{:.1}}}",
                    r.law,
                    if r.continued { "continued" } else { "early" },
                    r.rule.name(),
                    r.cones,
                    r.life_median,
                    r.refused_mean,
                    r.refused_pct,
                    r.past_pct,
                    r.past_mean
                )
            })
            .collect();
        format!(
            "{{\"rows\":[{}],\"life\":[{}]}}",
            rows.join(","),
            life.join(",")
        )
    }
}
