//! The uncertainty models issue 36 compared, on the early-life study (`hil-sim
//! accuracy`'s, `hil_sim::early_life`): the design record behind the choice stated in
//! `logic/src/wear/estimate.rs`'s module doc.
//!
//! `cargo run --release -p hil-sim --example band_candidates [SEEDS]`
//!
//! Each candidate is an `f64` model of an estimator (the fixed-point firmware's agrees
//! with its candidate, "mixture 1:2", to 0.1 µm on every figure of the study); the
//! previous release (7c11783) is its own fixed-point code. For each: the lowest share
//! of cones whose truth is in the band (any law, any horizon 600–10 000), the
//! estimate's error at 600–1 500 cycles over the laws against the previous release's,
//! the worst one law's, the worst against the model's (every law but the model's), the
//! summed interval score, and the band at 30 000 cycles with a reading every 1 000 to
//! 30 000 (the late regime) against the previous release's.

use docking_logic::estimate::Reading;
use hil_sim::accuracy::WearLaw;
use hil_sim::early_life::{
    edge_lockout, firmware, study_with, Band, EarlyComparison, Estimator, Previous, LAWS, SEEDS,
};

const A: f64 = 13.72;
const B: f64 = 0.3813;
const C: f64 = 17.74;
const LOG2E: f64 = std::f64::consts::LOG2_E;

fn m0() -> f64 {
    (C / A).powf(1.0 / B)
}

fn u_of(m: f64) -> f64 {
    (m + m0()).log2() - 10.0
}

/// One candidate model.
#[derive(Clone, Copy, Debug)]
struct Cand {
    /// Prior σ of β.
    sb: f64,
    /// Bend: prior σ of γ (0: the line alone), its prior mean.
    sg: f64,
    mug: f64,
    /// The bend's basis centred at the newest reading (else at the readings' weighted
    /// mean u), the tangent there beyond.
    at_last: bool,
    /// Weigh the line and the bending law by their evidence, prior odds `odds`.
    mixture: bool,
    odds: f64,
    /// Symmetric discrepancy κ·(u − u_last) beyond the readings.
    kappa: f64,
    /// One-sided discrepancies while the newest reading is in the running-in.
    kup: f64,
    kdn: f64,
}

const LINE: Cand = Cand {
    sb: 0.08,
    sg: 0.0,
    mug: 0.0,
    at_last: false,
    mixture: false,
    odds: 1.0,
    kappa: 0.0,
    kup: 0.0,
    kdn: 0.0,
};

const fn mixture(odds: f64, kup: f64, kdn: f64) -> Cand {
    Cand {
        sb: 0.08,
        sg: 0.05,
        mug: -0.05,
        at_last: true,
        mixture: true,
        odds,
        kappa: 0.0,
        kup,
        kdn,
    }
}

const CANDIDATES: [(&str, Cand); 9] = [
    ("line (7c11783, f64)", LINE),
    ("line + discrepancy 0.1", Cand { kappa: 0.1, ..LINE }),
    ("line + discrepancy 0.2", Cand { kappa: 0.2, ..LINE }),
    ("exponent prior 0.04", Cand { sb: 0.04, ..LINE }),
    ("bending law alone", Cand { sg: 0.1, ..LINE }),
    ("mixture 1:2, no discrepancy", mixture(0.5, 0.0, 0.0)),
    ("mixture 1:1", mixture(1.0, 0.07, 0.15)),
    ("mixture 1:2 (the firmware's)", mixture(0.5, 0.07, 0.15)),
    ("mixture 1:3", mixture(1.0 / 3.0, 0.07, 0.15)),
];

/// One fitted law: parameters of `z = α + β·u + γ·g(u)`, covariance, log evidence.
struct Fitted {
    p: [f64; 3],
    cov: [[f64; 3]; 3],
    logev: f64,
    centre: f64,
    uf: f64,
    ul: f64,
    n: usize,
}

fn det3(a: &[[f64; 3]; 3]) -> f64 {
    a[0][0] * (a[1][1] * a[2][2] - a[1][2] * a[2][1])
        - a[0][1] * (a[1][0] * a[2][2] - a[1][2] * a[2][0])
        + a[0][2] * (a[1][0] * a[2][1] - a[1][1] * a[2][0])
}

fn inv3(a: &[[f64; 3]; 3]) -> [[f64; 3]; 3] {
    let d = det3(a);
    let mut inv = [[0.0; 3]; 3];
    for (i, row) in inv.iter_mut().enumerate() {
        for (j, v) in row.iter_mut().enumerate() {
            let r: Vec<usize> = (0..3).filter(|&k| k != j).collect();
            let c: Vec<usize> = (0..3).filter(|&k| k != i).collect();
            let m = a[r[0]][c[0]] * a[r[1]][c[1]] - a[r[0]][c[1]] * a[r[1]][c[0]];
            *v = if (i + j) % 2 == 0 { m / d } else { -m / d };
        }
    }
    inv
}

fn fit(c: Cand, bend: bool, rs: &[Reading]) -> Fitted {
    let a0 = A.log2() + B * 10.0;
    let pts: Vec<(f64, f64, f64, f64)> = rs
        .iter()
        .map(|r| {
            let u = u_of(r.e_q32 as f64 / 4_294_967_296.0);
            let v = (r.wear_nm as f64 / 1000.0 + C).max(C / 4.0);
            let sz = 3.0 / v * LOG2E;
            let var = sz * sz + 1e-4;
            (u, v.log2(), 1.0 / var, 2.5 * var.sqrt())
        })
        .collect();
    let n = pts.len();
    let uf = pts.iter().map(|p| p.0).fold(f64::INFINITY, f64::min);
    let ul = pts.iter().map(|p| p.0).fold(f64::NEG_INFINITY, f64::max);
    let wsum: f64 = pts.iter().map(|p| p.2).sum();
    let centre = if c.at_last {
        ul
    } else if n > 0 {
        pts.iter().map(|p| p.2 * p.0).sum::<f64>() / wsum
    } else {
        0.0
    };
    let pg = if bend { 1.0 / (c.sg * c.sg) } else { 1.0 };
    let g2 = |u: f64| if bend { (u - centre).powi(2) } else { 0.0 };
    let mut p = [a0, B, 0.0];
    let mut a = [[0.0; 3]; 3];
    let huber = |e: f64, w0: f64, ksd: f64| {
        if e.abs() > ksd {
            w0 * ksd / e.abs()
        } else {
            w0
        }
    };
    for pass in 0..3 {
        a = [[0.0; 3]; 3];
        let mut b = [
            4.0 * a0,
            B / (c.sb * c.sb),
            if bend { c.mug * pg } else { 0.0 },
        ];
        a[0][0] = 4.0;
        a[1][1] = 1.0 / (c.sb * c.sb);
        a[2][2] = pg;
        for &(u, z, w0, ksd) in &pts {
            let g = [1.0, u, g2(u)];
            let e = z - (p[0] + p[1] * u + p[2] * g[2]);
            let w = if pass > 0 { huber(e, w0, ksd) } else { w0 };
            for i in 0..3 {
                for j in 0..3 {
                    a[i][j] += w * g[i] * g[j];
                }
                b[i] += w * g[i] * z;
            }
        }
        let inv = inv3(&a);
        p = [0, 1, 2].map(|i| (0..3).map(|j| inv[i][j] * b[j]).sum());
        if !bend && !(0.05..=1.0).contains(&p[1]) {
            p[1] = p[1].clamp(0.05, 1.0);
            p[0] = (b[0] - a[0][1] * p[1]) / a[0][0];
        }
    }
    let mut q = 4.0 * (p[0] - a0).powi(2)
        + (p[1] - B).powi(2) / (c.sb * c.sb)
        + pg * (p[2] - if bend { c.mug } else { 0.0 }).powi(2);
    for &(u, z, w0, ksd) in &pts {
        let e = z - (p[0] + p[1] * u + p[2] * g2(u));
        q += huber(e, w0, ksd) * e * e;
    }
    let logev = -0.5 * q - 0.5 * det3(&a).ln() + 0.5 * pg.ln();
    Fitted {
        p,
        cov: inv3(&a),
        logev,
        centre,
        uf,
        ul,
        n,
    }
}

impl Fitted {
    /// Mean and variance of z at u (a bending law continues as its tangent outside the
    /// readings).
    fn mv(&self, u: f64, bend: bool) -> (f64, f64) {
        let g2 = if !bend || self.n == 0 {
            0.0
        } else if u > self.ul {
            let k = self.ul - self.centre;
            k * k + 2.0 * k * (u - self.ul)
        } else if u < self.uf {
            let k = self.uf - self.centre;
            k * k + 2.0 * k * (u - self.uf)
        } else {
            (u - self.centre).powi(2)
        };
        let g = [1.0, u, g2];
        let mean = (0..3).map(|i| g[i] * self.p[i]).sum();
        let mut var = 1e-4;
        for i in 0..3 {
            for j in 0..3 {
                var += g[i] * self.cov[i][j] * g[j];
            }
        }
        (mean, var)
    }
}

struct Model {
    c: Cand,
    line: Fitted,
    bent: Option<Fitted>,
    w: f64,
}

impl Model {
    fn new(c: Cand, rs: &[Reading]) -> Self {
        let line = fit(c, false, rs);
        if c.sg == 0.0 {
            return Self {
                c,
                line,
                bent: None,
                w: 0.0,
            };
        }
        let bent = fit(c, true, rs);
        let w = if !c.mixture {
            1.0
        } else if rs.is_empty() || !(0.05..=1.0).contains(&bent.p[1]) {
            0.0
        } else {
            1.0 / (1.0 + (-(bent.logev - line.logev + c.odds.ln())).exp())
        };
        Self {
            c,
            line,
            bent: Some(bent),
            w,
        }
    }

    fn band(&self, m: f64) -> Band {
        let u = u_of(m);
        let (m1, v1) = self.line.mv(u, false);
        let (m2, v2) = self.bent.as_ref().map_or((m1, v1), |b| b.mv(u, true));
        let w = self.w;
        let mean = (1.0 - w) * m1 + w * m2;
        let var = (1.0 - w) * v1 + w * v2 + w * (1.0 - w) * (m1 - m2).powi(2);
        let (d, r) = if self.line.n == 0 {
            (0.0, 0.0)
        } else {
            (
                (u - self.line.ul).max(0.0),
                (1.0 - self.line.ul).clamp(0.0, 1.0),
            )
        };
        let c = self.c;
        let up = (var + (c.kappa * d).powi(2) + (c.kup * r * d).powi(2)).sqrt();
        let dn = (var + (c.kappa * d).powi(2) + (c.kdn * r * d).powi(2)).sqrt();
        let wear = (mean.exp2() - C).max(0.0);
        Band {
            wear_um: wear,
            low_um: ((mean - 2.0 * dn).exp2() - C).max(0.0).min(wear),
            high_um: ((mean + 2.0 * up).exp2() - C).max(wear),
        }
    }
}

struct Candidate(Cand);

impl Estimator for Candidate {
    fn band(&self, readings: &[Reading], at: &[u32]) -> Vec<Band> {
        let m = Model::new(self.0, readings);
        at.iter().map(|&x| m.band(x as f64)).collect()
    }

    fn lockouts(
        &self,
        readings: &[Reading],
        from: u32,
        to: u32,
        limit_nm: u32,
    ) -> [Option<u32>; 2] {
        let m = Model::new(self.0, readings);
        [
            edge_lockout(|x| m.band(x).high_um * 1000.0, from, to, limit_nm),
            edge_lockout(|x| m.band(x).wear_um * 1000.0, from, to, limit_nm),
        ]
    }
}

/// The late regime: the band at 30 000 cycles from readings every 1 000 to 30 000,
/// over the late study's laws and 20 seeds, against the previous release's (the
/// largest ratio of one law's mean width).
fn late_band_ratio(est: &dyn Estimator) -> f64 {
    WearLaw::ALL
        .iter()
        .map(|law| {
            let (mut a, mut b) = (0.0, 0.0);
            for seed in 0..20 {
                let r = law.readings(30_000, seed);
                let x = est.band(&r, &[30_000])[0];
                let y = Previous.band(&r, &[30_000])[0];
                a += x.high_um - x.low_um;
                b += y.high_um - y.low_um;
            }
            a / b
        })
        .fold(0.0, f64::max)
}

fn main() {
    let seeds = std::env::args()
        .nth(1)
        .and_then(|s| s.parse().ok())
        .unwrap_or(SEEDS);
    let previous = study_with(&Previous, seeds, false);
    let score =
        |s: &hil_sim::early_life::EarlyStudy| s.rows.iter().map(|r| r.score_um).sum::<f64>();
    println!(
        "# the early-life study ({} laws, {seeds} cones each, readings 100-500, checkpoints 600-10 000): candidate models of the band",
        LAWS.len()
    );
    println!("candidate                    | lowest in band % | err / 7c11783's at 600, 800, 1000, 1500 | worst law / 7c11783 | worst / model | interval score µm | late band / 7c11783");
    let mut rows: Vec<(&str, &dyn Estimator)> = Vec::new();
    let cands: Vec<Candidate> = CANDIDATES.iter().map(|&(_, c)| Candidate(c)).collect();
    for ((name, _), c) in CANDIDATES.iter().zip(&cands) {
        rows.push((name, c));
    }
    let fw = firmware();
    rows.push(("the firmware (fixed point)", &fw));
    for (name, est) in rows {
        let cmp = EarlyComparison {
            now: study_with(est, seeds, false),
            previous: previous.clone(),
            seeds,
        };
        let t = cmp.targets();
        let ratios: Vec<String> = t
            .err_vs_previous
            .iter()
            .map(|(_, r)| format!("{r:.2}"))
            .collect();
        println!(
            "{:<28} | {:>16.1} | {:<38} | {:>19.2} | {:>13.2} | {:>17.0} | {:>19.2}",
            name,
            t.worst_inside_pct,
            ratios.join(", "),
            t.worst_law_err_vs_previous.0,
            t.worst_err_vs_model.0,
            score(&cmp.now),
            late_band_ratio(est)
        );
    }
}
