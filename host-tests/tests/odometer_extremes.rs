//! Extreme cases of the wear odometer (`docking_logic::odometer`): zero load,
//! full-scale load on every sample, 10^7 cycles and u64/u32 saturation, loads far below
//! one state LSB, a single 1000× nominal cycle, irregular sampling, materials, and the
//! persisted record's determinism.
//!
//! The load–distance `W` is exact integer arithmetic (Q63.1 mN·µm: the trapezoid
//! `(F_prev + F)·|Δx|`), `E = k·W / W_nom` is a floor in u128, so almost everything
//! here is asserted exactly against an independent integer computation in the test.
//!
//! `ten_million_cycles_loop` is `#[ignore]`d (10^7 real `complete_cycle()` calls): run
//! it with `cargo test --release -p host-tests --test odometer_extremes -- --ignored`.

use docking_logic::fixed::ONE_Q32;
use docking_logic::material::Material;
use docking_logic::odometer::{
    cone_from_bytes, cone_to_bytes, depth_nm, e_at_depth_q32, equivalent_cycles_q32, restore,
    wear_factor_q32, Cone, Lifetime, Odometer, StateRecord, StrokeIntegrator, WearConfig,
    WearLevel, STATE_LEN, W_NOM_MN_UM, W_NOM_Q1,
};
use hil_sim::rng::Rng;

// --- the measured cycle --------------------------------------------------------------

/// One stroke of the axis in the cone, µm.
const STROKE_UM: i32 = 30_000;
/// Sample spacing of the regular cycles, µm.
const STEP_UM: i32 = 15;
/// Sample intervals per stroke (2000).
const STEPS: i32 = STROKE_UM / STEP_UM;
/// Total travel of one two-stroke cycle, µm.
const CYCLE_TRAVEL_UM: u64 = 2 * STROKE_UM as u64;
/// A fully loaded HX711 (positive rail), mN.
const FULL_SCALE_MN: i32 = 976_000;
/// Default limit and warning depth, nm.
const LIMIT_NM: u32 = 800_000;
const WARN_NM: u32 = 640_000;
/// Nominal life of a fresh ZQSn5-2 cone, nominal cycles (E(0.8 mm) = 45 268.2).
const ZQSN_LIFE: u32 = 45_268;

/// A nominal cycle in two samples: (F0 + F1)·Δx = W_NOM_Q1 exactly
/// (W_NOM_Q1 = 2²·3·5²·53 903 063 = 53 903 063 · 300).
const NOM_DX_UM: i32 = 300;
const NOM_F0_MN: i32 = 26_951_531;
const NOM_F1_MN: i32 = 26_951_532;
const _: () = assert!((NOM_F0_MN as u64 + NOM_F1_MN as u64) * NOM_DX_UM as u64 == W_NOM_Q1);
const _: () = assert!(W_NOM_Q1 == 2 * W_NOM_MN_UM);

/// The sample positions of one regular two-stroke cycle: 0 → 30 mm every 15 µm, then
/// back to 0 (the turnaround is sampled once): 4001 samples, 4000 intervals of 15 µm.
fn cycle_positions() -> impl Iterator<Item = i32> {
    (0..=STEPS)
        .map(|i| i * STEP_UM)
        .chain((0..STEPS).rev().map(|i| i * STEP_UM))
}

/// Feed one regular cycle with `force(sample_index, pos_um)` (left pending).
fn feed_cycle(o: &mut Odometer, force: impl Fn(usize, i32) -> i32) {
    for (i, p) in cycle_positions().enumerate() {
        o.on_contact_sample(p, force(i, p));
    }
}

/// Feed a list of `(pos_um, force_mn)` samples.
fn feed(o: &mut Odometer, samples: &[(i32, i32)]) {
    for &(p, f) in samples {
        o.on_contact_sample(p, f);
    }
}

/// One nominal cycle's load–distance as pending (two samples).
fn feed_nominal(o: &mut Odometer) {
    o.on_contact_sample(0, NOM_F0_MN);
    o.on_contact_sample(NOM_DX_UM, NOM_F1_MN);
}

/// The trapezoid sum of a sample list, computed independently of the library
/// (negative forces count as zero).
fn trapezoid_q1(samples: &[(i32, i32)]) -> u64 {
    samples
        .windows(2)
        .map(|w| {
            let (p0, f0) = w[0];
            let (p1, f1) = w[1];
            let df = i128::from(f0.max(0)) + i128::from(f1.max(0));
            let dx = (i128::from(p1) - i128::from(p0)).abs();
            u64::try_from(df * dx).unwrap()
        })
        .sum()
}

fn fresh(m: Material) -> Odometer {
    Odometer::new(
        WearConfig::DEFAULT,
        Cone::new(1, m, "T1", 0),
        Lifetime::default(),
    )
}

/// An odometer whose cone already carries `w_q1` over `cycles` cycles.
fn worn(m: Material, w_q1: u64, cycles: u32) -> Odometer {
    Odometer::new(
        WearConfig::DEFAULT,
        Cone {
            w_q1,
            cycles,
            ..Cone::new(1, m, "T1", 0)
        },
        Lifetime::default(),
    )
}

/// `E = k·W / W_nom`, floor, in u128 (the model's definition, computed here).
fn e_of(w_q1: u64, m: Material) -> u64 {
    let e = u128::from(wear_factor_q32(m)) * u128::from(w_q1) / u128::from(W_NOM_Q1);
    u64::try_from(e).unwrap()
}

/// The reduced-order power law in f64: h(E) = a·(E + m0)^b − c, nm.
fn h_f64(e_cycles: f64) -> f64 {
    let (a, b, c): (f64, f64, f64) = (13_720.0, 0.3813, 17_740.0);
    let m0 = (c / a).powf(1.0 / b);
    a * (e_cycles + m0).powf(b) - c
}

/// Smallest number of cycles of load–distance `w_cycle` (each) after which the cone's
/// E reaches `e_target` on material `m`: floor(k·n·W/Wn) ≥ e ⟺ k·n·W ≥ e·Wn.
fn cycles_to_reach(e_target: u64, w_cycle: u64, m: Material) -> u64 {
    let num = u128::from(e_target) * u128::from(W_NOM_Q1);
    let den = u128::from(wear_factor_q32(m)) * u128::from(w_cycle);
    u64::try_from(num.div_ceil(den)).unwrap()
}

// --- 1. zero load --------------------------------------------------------------------

#[test]
fn zero_load_cycle_adds_nothing() {
    let mut o = fresh(Material::ZQSn5_2);
    assert_eq!(o.remaining_cycles(), ZQSN_LIFE);
    for n in 1..=3u32 {
        feed_cycle(&mut o, |_, _| 0);
        assert_eq!(o.pending_q1(), 0);
        let s = o.complete_cycle();
        assert_eq!(s.w_q1, 0);
        assert_eq!(s.wear_nm, 0);
        assert_eq!(s.remaining_cycles, ZQSN_LIFE);
        assert_eq!(s.level, WearLevel::Ok);
        assert_eq!((s.cone_cycle, s.lifetime_cycle), (n, n));
        assert_eq!(o.cone().w_q1, 0);
        assert_eq!(o.lifetime().w_q1, 0);
        assert_eq!(o.equivalent_cycles_q32(), 0);
        assert_eq!(o.wear_nm(), 0);
        assert_eq!(o.remaining_cycles(), ZQSN_LIFE);
        assert_eq!(o.level(), WearLevel::Ok);
        assert_eq!(o.last_cycle_q1(), 0);
    }

    // A zero-load cycle after a loaded one leaves every derived value exactly as it was.
    feed_nominal(&mut o);
    o.complete_cycle();
    let (e, wear, left) = (o.equivalent_cycles_q32(), o.wear_nm(), o.remaining_cycles());
    assert_eq!(e, ONE_Q32);
    assert_eq!(left, ZQSN_LIFE - 1);
    feed_cycle(&mut o, |_, _| 0);
    let s = o.complete_cycle();
    assert_eq!(s.w_q1, 0);
    assert_eq!(o.last_cycle_q1(), 0);
    assert_eq!(o.cone().w_q1, W_NOM_Q1);
    assert_eq!(
        (o.equivalent_cycles_q32(), o.wear_nm(), o.remaining_cycles()),
        (e, wear, left)
    );
}

#[test]
fn negative_forces_count_as_zero() {
    // Noise below zero on every sample (down to −5 N): no load–distance at all.
    let mut o = fresh(Material::ZQSn5_2);
    feed_cycle(&mut o, |i, _| -((i as i32 * 7919) % 5_000));
    assert_eq!(o.pending_q1(), 0);
    let s = o.complete_cycle();
    assert_eq!((s.w_q1, s.wear_nm, s.remaining_cycles), (0, 0, ZQSN_LIFE));
    assert_eq!(s.level, WearLevel::Ok);

    // Even i32::MIN counts as zero (no overflow, no backwards wear).
    feed(&mut o, &[(0, i32::MIN), (STROKE_UM, i32::MIN), (0, -1)]);
    assert_eq!(o.pending_q1(), 0);

    // A negative sample on either side of an interval counts as zero, the positive
    // one as itself: (0 + 1000)·15 + (1000 + 0)·15 + (0 + 0)·15 + (0 + 2)·15.
    let mut o = fresh(Material::ZQSn5_2);
    feed(
        &mut o,
        &[(0, -700), (15, 1000), (30, -3), (45, -1), (60, 2)],
    );
    assert_eq!(o.pending_q1(), 1000 * 15 + 1000 * 15 + 2 * 15);

    // Same through the bare integrator: increments, not only the sum.
    let mut g = StrokeIntegrator::default();
    assert_eq!(g.add(100, -50_000), 0);
    assert_eq!(g.add(90, 3), 30);
    assert_eq!(g.add(80, -9), 30);
    assert_eq!(g.add(70, -9), 0);
}

// --- 2. full-scale load on every sample ----------------------------------------------

/// W of one full-scale cycle: (976 000 + 976 000) mN · 60 000 µm in Q63.1.
const W_FULL_SCALE_Q1: u64 = 117_120_000_000;
const _: () = assert!(W_FULL_SCALE_Q1 == 2 * FULL_SCALE_MN as u64 * CYCLE_TRAVEL_UM);

#[test]
fn full_scale_on_every_sample_until_the_limit() {
    let m = Material::ZQSn5_2;
    let e_limit = e_at_depth_q32(LIMIT_NM);
    let e_warn = e_at_depth_q32(WARN_NM);
    let n_limit = cycles_to_reach(e_limit, W_FULL_SCALE_Q1, m);
    let n_warn = cycles_to_reach(e_warn, W_FULL_SCALE_Q1, m);
    // About 45 268.2 / 7.2426 nominal cycles per full-scale cycle.
    assert!((6_200..6_300).contains(&n_limit), "{n_limit}");
    assert!(n_warn < n_limit);

    let mut o = fresh(m);
    let (mut prev_wear, mut prev_left) = (0u32, ZQSN_LIFE);
    for n in 1..=n_limit + 2 {
        feed_cycle(&mut o, |_, _| FULL_SCALE_MN);
        assert_eq!(o.pending_q1(), W_FULL_SCALE_Q1, "cycle {n}");
        let s = o.complete_cycle();
        assert_eq!(s.w_q1, W_FULL_SCALE_Q1);
        let w = u64::from(s.cone_cycle) * W_FULL_SCALE_Q1;
        assert_eq!(o.cone().w_q1, w);
        assert_eq!(o.lifetime().w_q1, w);
        let e = e_of(w, m);
        assert_eq!(o.equivalent_cycles_q32(), e, "cycle {n}");
        assert_eq!(s.wear_nm, depth_nm(e));
        // Finite and strictly increasing (≈ 50 nm per full-scale cycle even at the limit).
        assert!(
            s.wear_nm > prev_wear,
            "cycle {n}: {} <= {prev_wear}",
            s.wear_nm
        );
        assert!(s.wear_nm < 1_000_000);
        assert!(s.remaining_cycles <= prev_left);
        let left = u32::try_from(e_limit.saturating_sub(e) / ONE_Q32).unwrap();
        assert_eq!(s.remaining_cycles, left);
        let want = if n >= n_limit {
            WearLevel::Limit
        } else if n >= n_warn {
            WearLevel::Warning
        } else {
            WearLevel::Ok
        };
        assert_eq!(s.level, want, "cycle {n}");
        if n == n_limit {
            assert!(s.wear_nm >= LIMIT_NM, "{}", s.wear_nm);
            assert_eq!(s.remaining_cycles, 0);
        }
        prev_wear = s.wear_nm;
        prev_left = s.remaining_cycles;
    }
    // f64 cross-check of the depth at the end (no overflow anywhere on the way).
    let e = o.equivalent_cycles_q32() as f64 / ONE_Q32 as f64;
    let rel = (f64::from(o.wear_nm()) - h_f64(e)).abs() / h_f64(e);
    assert!(rel < 1e-6, "{} vs {}", o.wear_nm(), h_f64(e));
}

#[test]
fn full_scale_cycle_is_exactly_k_w_over_w_nom() {
    let mut o = fresh(Material::ZQSn5_2);
    feed_cycle(&mut o, |_, _| FULL_SCALE_MN);
    o.complete_cycle();
    let want = (u128::from(ONE_Q32) * u128::from(W_FULL_SCALE_Q1)) / u128::from(W_NOM_Q1);
    assert_eq!(u128::from(o.equivalent_cycles_q32()), want);
    // 117.12 / 16.1709189 = 7.2426… nominal cycles.
    let e = o.equivalent_cycles_q32() as f64 / ONE_Q32 as f64;
    assert!(
        (e - 117_120_000_000.0 / 16_170_918_900.0).abs() < 1e-9,
        "{e}"
    );
}

// --- 3. 10^7 cycles --------------------------------------------------------------------

const TEN_MILLION: u32 = 10_000_000;

#[test]
fn ten_million_nominal_cycles_of_state() {
    let m = Material::ZQSn5_2;
    let mut prev: Option<Odometer> = None;
    for n in [TEN_MILLION - 1, TEN_MILLION, TEN_MILLION + 1] {
        let o = worn(m, u64::from(n) * W_NOM_Q1, n);
        assert_eq!(o.equivalent_cycles_q32(), u64::from(n) << 32);
        assert_eq!(o.level(), WearLevel::Limit);
        assert_eq!(o.remaining_cycles(), 0);
        assert!(o.wear_nm() > LIMIT_NM);
        let rel = (f64::from(o.wear_nm()) - h_f64(f64::from(n))).abs() / h_f64(f64::from(n));
        assert!(
            rel < 1e-6,
            "n = {n}: {} nm vs {}",
            o.wear_nm(),
            h_f64(f64::from(n))
        );
        if let Some(p) = &prev {
            // dh/dm ≈ 0.24 nm per cycle here: monotone, not necessarily strictly in nm.
            assert!(o.wear_nm() >= p.wear_nm());
            assert!(o.equivalent_cycles_q32() > p.equivalent_cycles_q32());
        }
        prev = Some(o);
    }
    // ≈ 6.39 mm at 10^7 cycles; 10 cycles later it is strictly deeper.
    let at = |n: u32| worn(m, u64::from(n) * W_NOM_Q1, n).wear_nm();
    assert!(
        (6_380_000..6_390_000).contains(&at(TEN_MILLION)),
        "{}",
        at(TEN_MILLION)
    );
    assert!(at(TEN_MILLION + 10) > at(TEN_MILLION - 10));

    // One more real cycle on top of 10^7: exactly one more nominal cycle of E.
    let mut o = worn(m, u64::from(TEN_MILLION) * W_NOM_Q1, TEN_MILLION);
    let before = o.wear_nm();
    feed_nominal(&mut o);
    let s = o.complete_cycle();
    assert_eq!(s.cone_cycle, TEN_MILLION + 1);
    assert_eq!(o.equivalent_cycles_q32(), u64::from(TEN_MILLION + 1) << 32);
    assert_eq!(s.wear_nm, at(TEN_MILLION + 1));
    assert!(s.wear_nm >= before);
    assert_eq!((s.level, s.remaining_cycles), (WearLevel::Limit, 0));
}

#[test]
fn depth_is_monotone_from_zero_to_saturation() {
    // Geometric sweep over the whole u64 range of E plus dense windows around 10^7.
    let mut prev = 0;
    let mut e = 0u64;
    loop {
        let d = depth_nm(e);
        assert!(d >= prev, "depth_nm({e}) = {d} < {prev}");
        prev = d;
        if e == u64::MAX {
            break;
        }
        e = e.saturating_add(e / 4_096 + 1);
    }
    assert!(depth_nm(u64::MAX) < u32::MAX);
    for centre in [u64::from(TEN_MILLION) << 32, e_at_depth_q32(LIMIT_NM)] {
        let mut prev = depth_nm(centre - (1 << 20));
        let mut e = centre - (1 << 20);
        while e < centre + (1 << 20) {
            let d = depth_nm(e);
            assert!(d >= prev, "depth_nm({e}) = {d} < {prev}");
            prev = d;
            e += 997;
        }
    }
}

#[test]
fn cone_load_distance_saturates_at_u64_max_and_stays_monotone() {
    let m = Material::ZQSn5_2;
    let mut o = worn(m, u64::MAX - W_NOM_Q1 / 2, u32::MAX - 1);
    let e0 = o.equivalent_cycles_q32();
    let w0 = o.wear_nm();
    assert_eq!(e0, e_of(u64::MAX - W_NOM_Q1 / 2, m));
    assert_eq!(o.level(), WearLevel::Limit);

    feed_nominal(&mut o);
    let s = o.complete_cycle();
    assert_eq!(s.w_q1, W_NOM_Q1, "the cycle's own W is not clipped");
    assert_eq!(o.last_cycle_q1(), W_NOM_Q1);
    assert_eq!(o.cone().w_q1, u64::MAX);
    assert_eq!(o.cone().cycles, u32::MAX);
    let e1 = o.equivalent_cycles_q32();
    assert_eq!(e1, e_of(u64::MAX, m));
    assert!(e1 > e0);
    assert!(s.wear_nm >= w0);
    assert_eq!(s.wear_nm, depth_nm(e1));
    assert_eq!((s.level, s.remaining_cycles), (WearLevel::Limit, 0));

    // Further cycles: saturated, nothing decreases or wraps.
    for _ in 0..3 {
        feed_nominal(&mut o);
        let s = o.complete_cycle();
        assert_eq!(o.cone().w_q1, u64::MAX);
        assert_eq!(s.cone_cycle, u32::MAX);
        assert_eq!(o.equivalent_cycles_q32(), e1);
        assert_eq!(s.wear_nm, depth_nm(e1));
        assert_eq!(s.level, WearLevel::Limit);
    }

    // Every material at W = u64::MAX: E fits, wear finite, at the limit.
    for m in Material::ALL {
        let o = worn(m, u64::MAX, u32::MAX);
        assert_eq!(o.equivalent_cycles_q32(), e_of(u64::MAX, m));
        assert!(o.equivalent_cycles_q32() < u64::MAX);
        assert_eq!(o.wear_nm(), depth_nm(e_of(u64::MAX, m)));
        assert!(o.wear_nm() > LIMIT_NM && o.wear_nm() < u32::MAX);
        assert_eq!((o.level(), o.remaining_cycles()), (WearLevel::Limit, 0));
    }
}

#[test]
fn pending_saturates_from_samples_and_complete_cycle_saturates_the_totals() {
    // The largest single increment: both forces i32::MAX over the whole i32 range,
    // (2·(2^31 − 1))·(2^32 − 1) — fits u64, must not panic with overflow checks on.
    let biggest = (2 * (u64::from(u32::MAX >> 1))) * u64::from(u32::MAX);
    let mut g = StrokeIntegrator::default();
    g.add(i32::MIN, i32::MAX);
    assert_eq!(g.add(i32::MAX, i32::MAX), biggest);

    let mut o = worn(Material::ZQSn5_2, 5 * W_NOM_Q1, 5);
    let wear0 = o.wear_nm();
    feed(&mut o, &[(i32::MIN, i32::MAX), (i32::MAX, i32::MAX)]);
    assert_eq!(o.pending_q1(), biggest);
    o.on_contact_sample(i32::MIN, i32::MAX);
    assert_eq!(o.pending_q1(), u64::MAX);
    o.on_contact_sample(i32::MAX, i32::MAX);
    assert_eq!(o.pending_q1(), u64::MAX);
    let s = o.complete_cycle();
    assert_eq!(s.w_q1, u64::MAX);
    assert_eq!(o.cone().w_q1, u64::MAX);
    assert_eq!(o.lifetime().w_q1, u64::MAX);
    assert_eq!(o.pending_q1(), 0);
    assert!(s.wear_nm > wear0);
    assert_eq!(s.wear_nm, depth_nm(e_of(u64::MAX, Material::ZQSn5_2)));
    assert_eq!((s.level, s.remaining_cycles), (WearLevel::Limit, 0));
}

#[test]
fn lifetime_cycle_counter_does_not_wrap() {
    let life = Lifetime {
        cycles: u32::MAX - 1,
        w_q1: u64::MAX - 3,
        ..Lifetime::default()
    };
    let mut o = Odometer::new(
        WearConfig::DEFAULT,
        Cone::new(1, Material::ZQSn5_2, "T1", u32::MAX - 1),
        life,
    );
    feed_nominal(&mut o);
    let s = o.complete_cycle();
    assert_eq!(s.lifetime_cycle, u32::MAX);
    assert_eq!(s.cone_cycle, 1);
    assert_eq!(o.lifetime().w_q1, u64::MAX);
    assert_eq!(o.cone().w_q1, W_NOM_Q1);
    for _ in 0..3 {
        feed_nominal(&mut o);
        let s = o.complete_cycle();
        assert_eq!(s.lifetime_cycle, u32::MAX);
        assert_eq!(o.lifetime().cycles, u32::MAX);
        assert_eq!(o.lifetime().w_q1, u64::MAX);
    }
    // The cone's own counters are unaffected by the saturated lifetime totals.
    assert_eq!(o.cone().cycles, 4);
    assert_eq!(o.cone().w_q1, 4 * W_NOM_Q1);
    assert_eq!(o.equivalent_cycles_q32(), 4 << 32);
}

#[test]
#[ignore = "10^7 real cycles: run in release with -- --ignored"]
fn ten_million_cycles_loop() {
    let start = std::time::Instant::now();
    let mut o = fresh(Material::ZQSn5_2);
    let mut prev_wear = 0u32;
    let mut prev_checkpoint = 0u32;
    for n in 1..=TEN_MILLION {
        feed_nominal(&mut o);
        let s = o.complete_cycle();
        assert_eq!(s.w_q1, W_NOM_Q1);
        assert!(
            s.wear_nm >= prev_wear,
            "cycle {n}: {} < {prev_wear}",
            s.wear_nm
        );
        prev_wear = s.wear_nm;
        if n % 100_000 == 0 {
            assert_eq!(s.cone_cycle, n);
            assert_eq!(s.lifetime_cycle, n);
            assert_eq!(o.cone().w_q1, u64::from(n) * W_NOM_Q1);
            assert_eq!(o.lifetime().w_q1, u64::from(n) * W_NOM_Q1);
            assert_eq!(o.equivalent_cycles_q32(), u64::from(n) << 32);
            assert_eq!(s.wear_nm, depth_nm(u64::from(n) << 32));
            // Strictly deeper than 10^5 cycles ago (≥ 0.24 nm per cycle up to 10^7).
            assert!(s.wear_nm > prev_checkpoint, "cycle {n}");
            prev_checkpoint = s.wear_nm;
            assert_eq!(s.level, WearLevel::Limit);
            assert_eq!(s.remaining_cycles, 0);
        }
        if n == ZQSN_LIFE {
            assert_eq!(s.level, WearLevel::Warning);
            assert_eq!(s.remaining_cycles, 0);
        }
        if n == ZQSN_LIFE + 1 {
            assert_eq!(s.level, WearLevel::Limit);
        }
    }
    let rel = (f64::from(o.wear_nm()) - h_f64(f64::from(TEN_MILLION))).abs()
        / h_f64(f64::from(TEN_MILLION));
    assert!(rel < 1e-6);
    eprintln!(
        "ten_million_cycles_loop: 10^7 cycles in {:.2?}, wear {} nm",
        start.elapsed(),
        o.wear_nm()
    );
}

// --- 4. loads far below one LSB per sample -----------------------------------------

/// A triangle wave over the stroke with 5 µm steps: every interval is exactly 5 µm.
fn zigzag_um(i: u32) -> i32 {
    let period = 2 * STROKE_UM as u32;
    let x = (i * 5) % period;
    (if x <= STROKE_UM as u32 { x } else { period - x }) as i32
}

#[test]
fn one_millinewton_loads_accumulate_without_loss() {
    const N: u32 = 1_000_000;
    // 1 mN on every sample: (1 + 1)·5 per interval.
    let mut o = fresh(Material::ZQSn5_2);
    for i in 0..N {
        o.on_contact_sample(zigzag_um(i), 1);
    }
    assert_eq!(o.pending_q1(), u64::from(N - 1) * 2 * 5);
    assert_eq!(o.pending_q1(), 9_999_990);

    // 0 / 1 mN alternating: (0 + 1)·5 per interval.
    let mut o = fresh(Material::ZQSn5_2);
    for i in 0..N {
        o.on_contact_sample(zigzag_um(i), (i % 2) as i32);
    }
    assert_eq!(o.pending_q1(), u64::from(N - 1) * 5);
    let s = o.complete_cycle();
    assert_eq!(s.w_q1, 4_999_995);
    assert_eq!(o.cone().w_q1, 4_999_995);
    // 5·10^6 Q1 is 3.1e-4 nominal cycles: well above one Q32.32 LSB (3.7e-6 Q1/LSB).
    assert_eq!(
        o.equivalent_cycles_q32(),
        e_of(4_999_995, Material::ZQSn5_2)
    );
    assert!(o.equivalent_cycles_q32() > 0);
}

#[test]
fn thousand_tiny_cycles_equal_their_summed_load_distance() {
    for m in Material::ALL {
        // 1000 cycles of 1000 samples at 1 mN, 5 µm apart: W = 999·10 each.
        let mut o = fresh(m);
        for _ in 0..1000 {
            for i in 0..1000 {
                o.on_contact_sample(zigzag_um(i), 1);
            }
            assert_eq!(o.complete_cycle().w_q1, 9_990);
        }
        let sum = 1000 * 9_990;
        assert_eq!(o.cone().w_q1, sum);
        assert_eq!(o.equivalent_cycles_q32(), equivalent_cycles_q32(sum, m));
        assert_eq!(o.equivalent_cycles_q32(), e_of(sum, m));
        // Rounding E per cycle would have lost up to 1 LSB each time.
        let per_cycle = 1000 * equivalent_cycles_q32(9_990, m);
        assert!(o.equivalent_cycles_q32() > per_cycle, "{m:?}");
        assert_eq!(o.wear_nm(), depth_nm(e_of(sum, m)));

        // 1000 cycles of W = 1 Q1 (0.5 mN·µm) each: 0 LSB of E per cycle on its own.
        let mut o = fresh(m);
        for _ in 0..1000 {
            feed(&mut o, &[(0, 0), (1, 1)]);
            assert_eq!(o.complete_cycle().w_q1, 1);
        }
        assert_eq!(equivalent_cycles_q32(1, m), 0);
        assert_eq!(o.cone().w_q1, 1000);
        assert_eq!(o.equivalent_cycles_q32(), equivalent_cycles_q32(1000, m));
        assert_eq!(o.equivalent_cycles_q32(), e_of(1000, m));
        assert!(o.equivalent_cycles_q32() > 100, "{m:?}");
    }
}

// --- 5. one cycle at 1000× nominal load ----------------------------------------------

/// One regular cycle (4000 intervals of 15 µm) with forces alternating between these:
/// (F_a + F_b)·60 000 µm = 1000·W_NOM_Q1 exactly.
const KILO_FA_MN: i32 = 134_757_657;
const KILO_FB_MN: i32 = 134_757_658;
const _: () = assert!((KILO_FA_MN as u64 + KILO_FB_MN as u64) * CYCLE_TRAVEL_UM == 1000 * W_NOM_Q1);

#[test]
fn one_cycle_at_a_thousand_times_nominal() {
    for m in Material::ALL {
        let k = wear_factor_q32(m);
        let mut o = fresh(m);
        feed_cycle(
            &mut o,
            |i, _| {
                if i % 2 == 0 {
                    KILO_FA_MN
                } else {
                    KILO_FB_MN
                }
            },
        );
        assert_eq!(o.pending_q1(), 1000 * W_NOM_Q1);
        let s = o.complete_cycle();
        assert_eq!(s.w_q1, 1000 * W_NOM_Q1);
        assert_eq!(s.cone_cycle, 1);
        // E = k·1000·Wn/Wn = 1000·k exactly (1000 << 32 for the baseline).
        assert_eq!(o.equivalent_cycles_q32(), 1000 * k, "{m:?}");
        assert_eq!(s.wear_nm, depth_nm(1000 * k));
        if m == Material::ZQSn5_2 {
            assert_eq!(o.equivalent_cycles_q32(), 1000 << 32);
            // Eq. 17 at 1000 cycles: ≈ 0.17 mm.
            assert!((170_000..176_000).contains(&s.wear_nm), "{}", s.wear_nm);
        }

        // The next nominal cycle adds exactly one nominal cycle of E.
        feed_nominal(&mut o);
        let s2 = o.complete_cycle();
        assert_eq!(s2.w_q1, W_NOM_Q1);
        assert_eq!(o.equivalent_cycles_q32(), 1001 * k);
        assert_eq!(s2.wear_nm, depth_nm(1001 * k));
        assert!(s2.wear_nm > s.wear_nm);

        // Archard: one 1000× cycle + 1 nominal ≡ 1001 nominal cycles, bit for bit.
        let mut r = fresh(m);
        for _ in 0..1001 {
            feed_nominal(&mut r);
            r.complete_cycle();
        }
        assert_eq!(r.cone().w_q1, o.cone().w_q1);
        assert_eq!(r.equivalent_cycles_q32(), o.equivalent_cycles_q32());
        assert_eq!(r.wear_nm(), o.wear_nm());
        assert_eq!(r.remaining_cycles(), o.remaining_cycles());
        assert_eq!(r.level(), o.level());
    }
}

// --- 6. irregular sample intervals ---------------------------------------------------

/// Ramp F(x) = F0 + s·x, mN (x in µm): 20 N at the entry, 200 N at 30 mm.
const RAMP_F0_MN: i64 = 20_000;
const RAMP_S_MN_PER_UM: i64 = 6;

fn ramp_mn(x: i32) -> i32 {
    i32::try_from(RAMP_F0_MN + RAMP_S_MN_PER_UM * i64::from(x)).unwrap()
}

/// ∫ over [0, L] of the trapezoid sum of a linear F: Σ (2F0 + s(x0 + x1))(x1 − x0)
/// telescopes to 2·F0·L + s·L², for any partition.
fn ramp_w_q1(len_um: i32) -> u64 {
    let l = i64::from(len_um);
    u64::try_from(2 * RAMP_F0_MN * l + RAMP_S_MN_PER_UM * l * l).unwrap()
}

/// Strictly increasing positions 0 → `len` with seeded random steps of 1..=200 µm.
fn irregular_positions(rng: &mut Rng, len: i32) -> Vec<i32> {
    let mut v = vec![0];
    let mut p = 0;
    while p < len {
        p = (p + 1 + (rng.next_u64() % 200) as i32).min(len);
        v.push(p);
    }
    v
}

fn w_of(samples: &[(i32, i32)]) -> u64 {
    let mut o = fresh(Material::ZQSn5_2);
    feed(&mut o, samples);
    o.pending_q1()
}

#[test]
fn irregular_intervals_give_the_exact_ramp_integral() {
    let want = ramp_w_q1(STROKE_UM);
    assert_eq!(want, 6_600_000_000);
    let even: Vec<(i32, i32)> = (0..=STEPS)
        .map(|i| (i * STEP_UM, ramp_mn(i * STEP_UM)))
        .collect();
    assert_eq!(w_of(&even), want);
    // Just the two end points.
    assert_eq!(
        w_of(&[(0, ramp_mn(0)), (STROKE_UM, ramp_mn(STROKE_UM))]),
        want
    );

    for seed in [1, 2, 3, 0xC0FFEE, 0xDEAD_BEEF] {
        let mut rng = Rng::new(seed);
        let pos = irregular_positions(&mut rng, STROKE_UM);
        assert!(pos.windows(2).all(|w| (1..=200).contains(&(w[1] - w[0]))));
        let s: Vec<(i32, i32)> = pos.iter().map(|&x| (x, ramp_mn(x))).collect();
        assert_eq!(w_of(&s), want, "seed {seed}");
        assert_eq!(trapezoid_q1(&s), want);

        // A full cycle: in on one irregular grid, out on another.
        let back = irregular_positions(&mut rng, STROKE_UM);
        let mut o = fresh(Material::ZQSn5_2);
        feed(&mut o, &s);
        for &x in back.iter().rev() {
            o.on_contact_sample(x, ramp_mn(x));
        }
        assert_eq!(o.complete_cycle().w_q1, 2 * want, "seed {seed}");
    }
}

#[test]
fn load_distance_is_position_based_not_time_based() {
    let mut rng = Rng::new(0x5EED);
    let pos = irregular_positions(&mut rng, STROKE_UM);
    let fwd: Vec<(i32, i32)> = pos.iter().map(|&x| (x, ramp_mn(x))).collect();
    let want = ramp_w_q1(STROKE_UM);
    assert_eq!(w_of(&fwd), want);

    // The same positions visited in the opposite time order (the extraction stroke).
    let rev: Vec<(i32, i32)> = fwd.iter().rev().copied().collect();
    assert_eq!(w_of(&rev), want);

    // The same positions on another time base: the axis dwells (random numbers of
    // extra samples at the same position and load) — time passes, nothing slides.
    let mut dwell = Vec::new();
    for &(x, f) in &fwd {
        for _ in 0..=rng.next_u64() % 5 {
            dwell.push((x, f));
        }
    }
    assert!(dwell.len() > fwd.len());
    assert_eq!(w_of(&dwell), want);

    // A non-linear profile (random loads) in reverse time order: also identical.
    let rnd: Vec<(i32, i32)> = pos
        .iter()
        .map(|&x| (x, (rng.next_u64() % (FULL_SCALE_MN as u64 + 1)) as i32))
        .collect();
    let rnd_rev: Vec<(i32, i32)> = rnd.iter().rev().copied().collect();
    assert_eq!(w_of(&rnd), trapezoid_q1(&rnd));
    assert_eq!(w_of(&rnd_rev), w_of(&rnd));
}

#[test]
fn archard_proportionality_in_load_and_travel() {
    let mut rng = Rng::new(42);
    let pos_in = irregular_positions(&mut rng, STROKE_UM);
    let pos_out = irregular_positions(&mut rng, STROKE_UM);
    // A random measured cycle (0 … full scale), in and out on different grids.
    let cycle: Vec<(i32, i32)> = pos_in
        .iter()
        .copied()
        .chain(pos_out.iter().rev().copied())
        .map(|x| (x, (rng.next_u64() % (FULL_SCALE_MN as u64 + 1)) as i32))
        .collect();
    let w1 = w_of(&cycle);
    assert_eq!(w1, trapezoid_q1(&cycle));
    assert!(w1 > 0);

    // Doubling every force doubles W exactly.
    let doubled: Vec<(i32, i32)> = cycle.iter().map(|&(x, f)| (x, 2 * f)).collect();
    assert_eq!(w_of(&doubled), 2 * w1);
    // And for the ramp.
    let ramp: Vec<(i32, i32)> = pos_in.iter().map(|&x| (x, ramp_mn(x))).collect();
    let ramp2: Vec<(i32, i32)> = ramp.iter().map(|&(x, f)| (x, 2 * f)).collect();
    assert_eq!(w_of(&ramp2), 2 * ramp_w_q1(STROKE_UM));

    // Doubling the travel (two passes in one cycle, the chain unbroken) doubles W.
    let mut o = fresh(Material::ZQSn5_2);
    feed(&mut o, &cycle);
    feed(&mut o, &cycle);
    assert_eq!(o.pending_q1(), 2 * w1);
    let s = o.complete_cycle();
    assert_eq!(s.w_q1, 2 * w1);

    // Two cycles of the same profile: the cone carries exactly twice one cycle.
    let mut a = fresh(Material::ZQSn5_2);
    feed(&mut a, &cycle);
    a.complete_cycle();
    feed(&mut a, &cycle);
    a.complete_cycle();
    assert_eq!(a.cone().w_q1, 2 * w1);
    assert_eq!(a.equivalent_cycles_q32(), o.equivalent_cycles_q32());
    assert_eq!(a.wear_nm(), o.wear_nm());

    // A broken chain (end_contact) between passes does not add the jump back to 0.
    let mut b = fresh(Material::ZQSn5_2);
    feed(&mut b, &ramp);
    b.end_contact();
    feed(&mut b, &ramp);
    assert_eq!(b.pending_q1(), 2 * ramp_w_q1(STROKE_UM));
}

// --- 7. materials ---------------------------------------------------------------------

#[test]
fn same_measured_cycle_on_each_material() {
    let kz = wear_factor_q32(Material::ZQSn5_2);
    let kq = wear_factor_q32(Material::QSn6_6_3);
    let kp = wear_factor_q32(Material::CfPeek);
    assert_eq!(kz, ONE_Q32);
    // 0.5701 in Q32.32 (2 448 560 855.4…), within one LSB.
    assert!(
        kq.abs_diff((0.5701 * ONE_Q32 as f64).round() as u64) <= 1,
        "{kq}"
    );

    let mut rng = Rng::new(7);
    let pos = irregular_positions(&mut rng, STROKE_UM);
    let cycle: Vec<(i32, i32)> = pos
        .iter()
        .copied()
        .chain(pos.iter().rev().copied())
        .map(|x| (x, (rng.next_u64() % (FULL_SCALE_MN as u64 + 1)) as i32))
        .collect();
    let mut odos: Vec<Odometer> = Material::ALL.into_iter().map(fresh).collect();
    for _ in 0..20 {
        for o in &mut odos {
            feed(o, &cycle);
            o.complete_cycle();
        }
    }
    let w = odos[0].cone().w_q1;
    assert!(odos.iter().all(|o| o.cone().w_q1 == w));
    assert_eq!(w, 20 * trapezoid_q1(&cycle));
    let e: Vec<u64> = odos.iter().map(|o| o.equivalent_cycles_q32()).collect();
    for (o, m) in odos.iter().zip(Material::ALL) {
        assert_eq!(o.equivalent_cycles_q32(), e_of(w, m));
    }
    let (ez, eq, ep) = (e[0], e[1], e[2]);
    assert!(ez > 10 << 32, "{ez}");
    // E scales by the factor: within one LSB of E_baseline · k.
    let scaled = |k: u64| u64::try_from((u128::from(ez) * u128::from(k)) >> 32).unwrap();
    assert!(eq.abs_diff(scaled(kq)) <= 1, "{eq} vs {}", scaled(kq));
    assert!(ep.abs_diff(scaled(kp)) <= 1, "{ep} vs {}", scaled(kp));
    let ratio = eq as f64 / ez as f64;
    assert!((ratio - 0.5701).abs() < 1e-6, "{ratio}");
    assert!(odos[1].wear_nm() < odos[0].wear_nm());
    assert!(odos[2].wear_nm() < odos[1].wear_nm());
}

#[test]
fn material_nominal_lives() {
    let e_limit = e_at_depth_q32(LIMIT_NM);
    let life = |m: Material| fresh(m).remaining_cycles();
    assert_eq!(life(Material::ZQSn5_2), ZQSN_LIFE);
    // QSn6-6-3: 45 268.2 / 0.5701 ≈ 79 404.
    let q = f64::from(life(Material::QSn6_6_3));
    assert!((q - 45_268.2 / 0.5701).abs() < 2.0, "{q}");
    // CF-PEEK: the paper's 90 540 cycles, ±0.5 %.
    let p = life(Material::CfPeek);
    assert!((f64::from(p) - 90_540.0).abs() / 90_540.0 < 0.005, "{p}");

    // And in nominal cycles actually run: the level reaches Limit at exactly the first
    // n with k·n ≥ E_limit, and the remaining count is consistent one cycle before.
    for m in Material::ALL {
        let n = u32::try_from(cycles_to_reach(e_limit, W_NOM_Q1, m)).unwrap();
        let before = worn(m, u64::from(n - 1) * W_NOM_Q1, n - 1);
        let at = worn(m, u64::from(n) * W_NOM_Q1, n);
        assert_ne!(before.level(), WearLevel::Limit, "{m:?} n = {n}");
        assert_eq!(at.level(), WearLevel::Limit, "{m:?} n = {n}");
        assert_eq!(at.remaining_cycles(), 0);
        assert!(before.remaining_cycles() <= 1);
        assert!(n.abs_diff(life(m)) <= 1, "{m:?}: {n} vs {}", life(m));
        if m == Material::CfPeek {
            assert!((f64::from(n) - 90_540.0).abs() / 90_540.0 < 0.005, "{n}");
        }
    }
}

#[test]
fn level_boundaries_are_exact_in_load_distance() {
    // For every material and configuration: the smallest W whose E reaches the
    // threshold switches the level; one Q1 unit (0.5 mN·µm) less does not.
    let cfgs = [
        WearConfig::DEFAULT,
        WearConfig::new(400_000, 50).unwrap(),
        WearConfig::new(5_000_000, 99).unwrap(),
        WearConfig::new(10_000, 1).unwrap(),
    ];
    for cfg in cfgs {
        let warn_nm =
            u32::try_from(u64::from(cfg.limit_nm) * u64::from(cfg.warn_pct) / 100).unwrap();
        for m in Material::ALL {
            let at = |w: u64| {
                Odometer::new(
                    cfg,
                    Cone {
                        w_q1: w,
                        ..Cone::new(1, m, "T1", 0)
                    },
                    Lifetime::default(),
                )
            };
            for (depth, below, level) in [
                (cfg.limit_nm, WearLevel::Warning, WearLevel::Limit),
                (warn_nm, WearLevel::Ok, WearLevel::Warning),
            ] {
                let e = e_at_depth_q32(depth);
                let w = cycles_to_reach(e, 1, m);
                assert!(e_of(w, m) >= e && e_of(w - 1, m) < e);
                assert_eq!(at(w).level(), level, "{cfg:?} {m:?} {depth}");
                assert_eq!(at(w - 1).level(), below, "{cfg:?} {m:?} {depth}");
                // The reported depth there is the threshold to within 1 nm (depth_nm
                // floors: at exactly E(0.8 mm) it reads 799 999 nm, level already Limit).
                assert!(depth.saturating_sub(at(w).wear_nm()) <= 1);
            }
            assert_eq!(
                at(cycles_to_reach(e_at_depth_q32(cfg.limit_nm), 1, m)).remaining_cycles(),
                0
            );
        }
    }
    // E at depth is monotone over the whole validated limit range.
    let mut prev = 0;
    for d in (10_000..=5_000_000).step_by(997) {
        let e = e_at_depth_q32(d);
        assert!(e > prev, "e_at_depth_q32({d})");
        assert!(depth_nm(e).abs_diff(d) <= 1, "{d}: {}", depth_nm(e));
        prev = e;
    }
}

// --- 8. persisted record ---------------------------------------------------------------

/// A seeded sequence of cycles with noise below zero, overloads and faults; returns
/// the odometer and the cone's load–distance computed independently.
fn scripted(m: Material, seed: u64, tweak: Option<usize>) -> (Odometer, u64) {
    let mut rng = Rng::new(seed);
    let mut o = fresh(m);
    let mut k = 0usize;
    let mut w = 0u64;
    for c in 0..25 {
        let pos = irregular_positions(&mut rng, STROKE_UM);
        let mut samples = Vec::new();
        for &x in pos.iter().chain(pos.iter().rev()) {
            let mut f = (rng.next_u64() % 300_000) as i32 - 5_000;
            if tweak == Some(k) {
                f += 1_000;
            }
            k += 1;
            samples.push((x, f));
            o.on_contact_sample(x, f);
            o.record_force(f);
        }
        w += trapezoid_q1(&samples);
        if c % 7 == 3 {
            o.record_overload(250_000);
        }
        if c % 11 == 5 {
            o.record_fault();
        }
        assert_eq!(o.complete_cycle().w_q1, trapezoid_q1(&samples));
    }
    (o, w)
}

#[test]
fn state_record_round_trips_and_is_bit_identical() {
    for m in Material::ALL {
        let (a, wa) = scripted(m, 99, None);
        let (b, _) = scripted(m, 99, None);
        assert_eq!(a.cone().w_q1, wa);
        let ra = StateRecord::of(&a, true).to_bytes();
        let rb = StateRecord::of(&b, true).to_bytes();
        assert_eq!(ra, rb, "{m:?}");
        assert_eq!(
            (a.equivalent_cycles_q32(), a.wear_nm(), a.remaining_cycles()),
            (b.equivalent_cycles_q32(), b.wear_nm(), b.remaining_cycles())
        );

        // One newton more on one sample: a different record, by exactly that much.
        let (c, wc) = scripted(m, 99, Some(12_345));
        assert_eq!(c.cone().w_q1, wc);
        assert!(wc > wa);
        assert_ne!(StateRecord::of(&c, true).to_bytes(), ra);

        // Round trip: bytes → record → bytes, and the decoded fields.
        let rec = StateRecord::of(&a, true);
        let back = StateRecord::from_bytes(&ra).unwrap();
        assert_eq!(back, rec, "{m:?}");
        assert_eq!(back.to_bytes(), ra);
        assert_eq!(ra.len(), STATE_LEN);

        // The layout, against the odometer's own counters.
        let life = a.lifetime();
        assert_eq!(ra[0..4], life.cycles.to_le_bytes());
        assert_eq!(ra[4..8], a.cone().cycles.to_le_bytes());
        assert_eq!(ra[8..16], a.cone().w_q1.to_le_bytes());
        assert_eq!(ra[16..24], life.w_q1.to_le_bytes());
        assert_eq!(ra[24..28], life.overload_events.to_le_bytes());
        assert_eq!(ra[28..32], life.peak_force_mn.to_le_bytes());
        assert_eq!(ra[32..36], life.faults.to_le_bytes());
        assert_eq!(ra[36..38], a.cone().id.to_le_bytes());
        assert_eq!(ra[38], m.code());
        assert_eq!(ra[39], 1);
        assert_eq!(ra[40..48], a.last_cycle_q1().to_le_bytes());
        assert_eq!((life.cycles, life.overload_events, life.faults), (25, 4, 2));
        assert_eq!(StateRecord::of(&a, false).to_bytes()[39], 0);

        // Restored from the records, the odometer derives bit-identical values.
        let cone = cone_from_bytes(&cone_to_bytes(a.cone())).unwrap();
        let r = restore(
            WearConfig::DEFAULT,
            Some(cone),
            Some(back),
            Material::ZQSn5_2,
        );
        assert_eq!(r.cone().w_q1, a.cone().w_q1);
        assert_eq!(r.equivalent_cycles_q32(), a.equivalent_cycles_q32());
        assert_eq!(r.wear_nm(), a.wear_nm());
        assert_eq!(r.remaining_cycles(), a.remaining_cycles());
        assert_eq!(r.level(), a.level());
        assert_eq!(StateRecord::of(&r, true).to_bytes(), ra);
    }

    // Extreme counters survive the round trip unchanged.
    let life = Lifetime {
        cycles: u32::MAX,
        w_q1: u64::MAX,
        overload_events: u32::MAX,
        faults: u32::MAX,
        peak_force_mn: i32::MIN,
        cones_installed: 0,
    };
    let o = Odometer::new(
        WearConfig::DEFAULT,
        Cone {
            w_q1: u64::MAX,
            cycles: u32::MAX,
            ..Cone::new(u16::MAX, Material::CfPeek, "X", u32::MAX)
        },
        life,
    );
    let rec = StateRecord::of(&o, false);
    let bytes = rec.to_bytes();
    assert_eq!(StateRecord::from_bytes(&bytes), Some(rec));
    assert_eq!(bytes[8..16], [0xFF; 8]);
}
