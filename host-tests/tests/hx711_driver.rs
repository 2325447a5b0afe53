//! The HX711 driver (`docking_logic::hx711`) against the simulated part
//! (`hil_sim::hx711`) at pin level in virtual time, plus a tiny mock part for the
//! exact pulse counts and the pin-error path.

use std::cell::{Cell, RefCell};
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use docking_logic::hx711::{
    settling_time_us, sign_extend_24, Calibration, Gain, Hx711, Hx711Error, CODE_MAX, CODE_MIN,
    POWER_DOWN_NS, T3_SCK_HIGH_MAX_NS,
};
use embedded_hal::delay::DelayNs;
use embedded_hal::digital::{ErrorType, InputPin, OutputPin};
use hil_sim::clock::SimClock;
use hil_sim::hx711::{Hx711Config, Hx711Dout, Hx711Fault, Hx711Sck, SimHx711};

/// Settling time after power-up at 80 SPS, ns (4 periods of 12.5 ms).
const SETTLE_80_NS: u64 = 50_000_000;
/// Conversion period at 80 SPS, ns.
const PERIOD_80_NS: u64 = 12_500_000;

/// What the PD_SCK line did, as seen in virtual time.
#[derive(Default)]
struct SckLog {
    rises: Cell<u64>,
    high_since_ns: Cell<Option<u64>>,
    max_high_ns: Cell<u64>,
}

/// The sim's PD_SCK pin, recording rising edges and the longest high phase.
struct TimedSck {
    inner: Hx711Sck,
    clock: SimClock,
    log: Rc<SckLog>,
}

impl ErrorType for TimedSck {
    type Error = core::convert::Infallible;
}

impl OutputPin for TimedSck {
    fn set_high(&mut self) -> Result<(), Self::Error> {
        if self.log.high_since_ns.get().is_none() {
            self.log.rises.set(self.log.rises.get() + 1);
            self.log.high_since_ns.set(Some(self.clock.now_ns()));
        }
        self.inner.set_high()
    }

    fn set_low(&mut self) -> Result<(), Self::Error> {
        if let Some(t) = self.log.high_since_ns.take() {
            let high = self.clock.now_ns() - t;
            self.log
                .max_high_ns
                .set(self.log.max_high_ns.get().max(high));
        }
        self.inner.set_low()
    }
}

type Driver = Hx711<Hx711Dout, TimedSck, SimClock>;

struct Rig {
    hx: SimHx711,
    clock: SimClock,
    force_n: Rc<Cell<f64>>,
    log: Rc<SckLog>,
    drv: Driver,
}

/// A zero-noise 80 SPS part (offset 31 000 counts, 8 590 counts/N) at t = 0 whose force
/// is `force_n`, and the driver on its pins.
fn rig(force_n: f64, gain: Gain) -> Rig {
    rig_with(
        Hx711Config {
            noise_counts: 0.0,
            ..Hx711Config::default_for_rate(80)
        },
        force_n,
        gain,
    )
}

fn rig_with(cfg: Hx711Config, force_n: f64, gain: Gain) -> Rig {
    let clock = SimClock::new();
    let force = Rc::new(Cell::new(force_n));
    let f = force.clone();
    let hx = SimHx711::new(cfg, clock.clone(), move |_t_ns| f.get(), 7);
    let log = Rc::new(SckLog::default());
    let sck = TimedSck {
        inner: hx.pd_sck(),
        clock: clock.clone(),
        log: log.clone(),
    };
    let drv = Hx711::new(hx.dout(), sck, clock.clone(), gain).unwrap();
    Rig {
        hx,
        clock,
        force_n: force,
        log,
        drv,
    }
}

impl Rig {
    /// Wait for the next conversion and read it.
    fn next_sample(&mut self) -> i32 {
        self.clock.advance_to_ns(self.hx.next_conversion_ns());
        self.drv.read().unwrap()
    }

    /// Set the force, then read the next conversion (which sees that force).
    fn sample_at(&mut self, force_n: f64) -> i32 {
        self.force_n.set(force_n);
        self.next_sample()
    }
}

/// The sim's code for `force_n` at gain 128 with zero noise.
fn expected_code(force_n: f64) -> i32 {
    (31_000.0 + 8_590.0 * force_n)
        .round()
        .clamp(CODE_MIN as f64, CODE_MAX as f64) as i32
}

#[test]
fn would_block_before_first_conversion_and_between_conversions() {
    let mut r = rig(10.0, Gain::A128);
    // Settling: nothing for the first 50 ms at 80 SPS.
    for t in [0, 1_000_000, 25_000_000, SETTLE_80_NS - 1] {
        r.clock.advance_to_ns(t);
        assert_eq!(r.drv.read(), Err(nb::Error::WouldBlock), "t = {t} ns");
    }
    assert_eq!(r.log.rises.get(), 0, "WouldBlock never touches PD_SCK");
    r.clock.advance_to_ns(SETTLE_80_NS);
    assert_eq!(r.drv.read(), Ok(expected_code(10.0)));
    // Read once: WouldBlock until the next conversion, one period later.
    let rises = r.log.rises.get();
    for t in [SETTLE_80_NS + 100_000, SETTLE_80_NS + PERIOD_80_NS - 1] {
        r.clock.advance_to_ns(t);
        assert_eq!(r.drv.read(), Err(nb::Error::WouldBlock), "t = {t} ns");
    }
    assert_eq!(r.log.rises.get(), rises);
    r.clock.advance_to_ns(SETTLE_80_NS + PERIOD_80_NS);
    assert_eq!(r.drv.read(), Ok(expected_code(10.0)));
    assert_eq!(settling_time_us(80) as u64 * 1_000, SETTLE_80_NS);
}

#[test]
fn read_returns_offset_plus_gain_times_force_exactly() {
    let mut r = rig(0.0, Gain::A128);
    for f in [
        0.0, 10.0, -10.0, 0.5, -37.25, 123.456, 500.0, -500.0, 976.0, -979.0,
    ] {
        let code = r.sample_at(f);
        assert_eq!(code, expected_code(f), "force {f} N");
        assert_eq!(r.hx.last_read().map(|(c, _)| c), Some(code));
    }
    assert_eq!(r.sample_at(0.0), 31_000);
    assert_eq!(r.sample_at(10.0), 116_900);
    assert_eq!(r.sample_at(-10.0), 31_000 - 85_900);
}

#[test]
fn both_adc_rails_read_as_code_max_and_code_min() {
    let mut r = rig(2_000.0, Gain::A128);
    assert_eq!(r.next_sample(), CODE_MAX);
    assert_eq!(r.sample_at(-2_000.0), CODE_MIN);
    assert_eq!(r.sample_at(2_000.0), CODE_MAX);
    assert_eq!(CODE_MAX, hil_sim::hx711::CODE_MAX);
    assert_eq!(CODE_MIN, hil_sim::hx711::CODE_MIN);
    // Saturated-bridge fault: the positive rail every time.
    r.hx.set_fault(Hx711Fault::Saturated);
    assert_eq!(r.sample_at(0.0), CODE_MAX);
    assert_eq!(r.sample_at(-100.0), CODE_MAX);
}

#[test]
fn readout_is_short_clock_never_high_long_and_no_power_downs_in_1000_reads() {
    let mut r = rig(0.0, Gain::A128);
    let mut longest_ns = 0;
    for i in 0..1_000u32 {
        let f = f64::from(i % 200) * 4.0 - 400.0;
        r.force_n.set(f);
        r.clock.advance_to_ns(r.hx.next_conversion_ns());
        let t0 = r.clock.now_ns();
        let code = r.drv.read().unwrap();
        let dt = r.clock.now_ns() - t0;
        longest_ns = longest_ns.max(dt);
        assert_eq!(code, expected_code(f), "read {i}");
    }
    assert!(longest_ns < 60_000, "readout {longest_ns} ns");
    assert!(r.log.max_high_ns.get() <= u64::from(T3_SCK_HIGH_MAX_NS));
    assert!(r.log.max_high_ns.get() < u64::from(POWER_DOWN_NS));
    let s = r.hx.stats();
    assert_eq!(s.power_downs, 0);
    assert_eq!(s.samples_read, 1_000);
    assert_eq!(s.samples_missed, 0);
    assert_eq!(r.log.rises.get(), 25_000, "25 pulses per A/128 readout");

    // The longest readout (27 pulses, A/64) is still well under 60 µs.
    for gain in [Gain::B32, Gain::A64] {
        r.drv.set_gain(gain);
        for _ in 0..3 {
            r.clock.advance_to_ns(r.hx.next_conversion_ns());
            let t0 = r.clock.now_ns();
            r.drv.read().unwrap();
            assert!(r.clock.now_ns() - t0 < 60_000);
        }
    }
    assert!(r.log.max_high_ns.get() <= u64::from(T3_SCK_HIGH_MAX_NS));
    assert_eq!(r.hx.stats().power_downs, 0);
}

#[test]
fn power_down_then_power_up_would_block_for_the_settling_time() {
    let mut r = rig(20.0, Gain::A128);
    assert_eq!(r.next_sample(), expected_code(20.0));
    r.drv.power_down().unwrap();
    assert!(r.drv.is_powered_down());
    // Powered down: nothing, however long we wait.
    for _ in 0..10 {
        r.clock.advance_ns(PERIOD_80_NS);
        assert_eq!(r.drv.read(), Err(nb::Error::WouldBlock));
    }
    r.drv.power_up().unwrap();
    assert_eq!(r.hx.stats().power_downs, 1);
    let t_up = r.clock.now_ns();
    let settle_ns = u64::from(settling_time_us(80)) * 1_000;
    for dt in [0, 1_000_000, PERIOD_80_NS, settle_ns - 1] {
        r.clock.advance_to_ns(t_up + dt);
        assert_eq!(
            r.drv.read(),
            Err(nb::Error::WouldBlock),
            "{dt} ns after power-up"
        );
    }
    r.clock.advance_to_ns(t_up + settle_ns);
    assert_eq!(r.drv.read(), Ok(expected_code(20.0)));
    assert_eq!(r.hx.stats().power_downs, 1, "only the deliberate one");
}

#[test]
fn power_up_resets_to_a128() {
    let mut r = rig(10.0, Gain::A64);
    assert_eq!(r.next_sample(), 116_900);
    assert_eq!(r.next_sample(), 116_900 / 2);
    r.drv.power_down().unwrap();
    r.drv.power_up().unwrap();
    assert_eq!(r.next_sample(), 116_900, "reset selects A/128");
    assert_eq!(r.next_sample(), 116_900 / 2);
}

#[test]
fn gain_pulses_select_the_next_reading() {
    // Constructed with A/64: the first conversion is A/128 (reset default), the next halved.
    let mut r = rig(10.0, Gain::A64);
    assert_eq!(r.next_sample(), 116_900);
    assert_eq!(r.next_sample(), 58_450);
    assert_eq!(r.next_sample(), 58_450);

    // Changing the gain takes effect one reading later.
    let mut r = rig(10.0, Gain::A128);
    let a128 = r.next_sample();
    assert_eq!(a128, 116_900);
    r.drv.set_gain(Gain::A64);
    assert_eq!(r.drv.gain(), Gain::A64);
    assert_eq!(
        r.next_sample(),
        a128,
        "still selected by the previous readout"
    );
    assert_eq!(r.next_sample(), a128 / 2);
    r.drv.set_gain(Gain::B32);
    assert_eq!(r.next_sample(), a128 / 2);
    assert_eq!(r.next_sample(), a128 / 4);
    r.drv.set_gain(Gain::A128);
    assert_eq!(r.next_sample(), a128 / 4);
    assert_eq!(r.next_sample(), a128);
}

#[test]
fn disconnected_part_always_would_block() {
    let mut r = rig(10.0, Gain::A128);
    r.hx.set_fault(Hx711Fault::Disconnected);
    for _ in 0..400 {
        r.clock.advance_ns(PERIOD_80_NS / 5);
        assert_eq!(r.drv.read(), Err(nb::Error::WouldBlock));
    }
    assert_eq!(
        r.log.rises.get(),
        0,
        "never clocks a part that is not there"
    );
    // Reconnected: samples again.
    r.hx.set_fault(Hx711Fault::None);
    assert_eq!(r.next_sample(), expected_code(10.0));
}

#[test]
fn two_point_calibration_from_sim_codes_reproduces_forces() {
    let mut r = rig(0.0, Gain::A128);
    let c0 = r.sample_at(0.0);
    let c200 = r.sample_at(200.0);
    let cal = Calibration::from_two_points(c0, 0, c200, 200_000).unwrap();
    assert_eq!(cal, Calibration::SIM_DEFAULT);
    // Error sources: the sim's rounding to a whole count (±0.5 count ≈ ±0.058 mN) and
    // the floor of the Q32.32 product (0 to −1 mN).
    let half_count_mn = 0.5 * 1_000.0 / 8_590.0;
    let mut f = -500.0;
    while f <= 900.0 {
        let code = r.sample_at(f);
        let err_mn = f64::from(cal.to_force_mn(code)) - f * 1_000.0;
        assert!(
            err_mn >= -1.0 - half_count_mn - 1e-6 && err_mn <= half_count_mn + 1e-6,
            "{f} N: {} mN (error {err_mn} mN)",
            cal.to_force_mn(code)
        );
        f += 3.217;
    }
    // Both rails map to forces beyond the cell's range, not to garbage.
    assert!(cal.to_force_mn(CODE_MAX) > 970_000);
    assert!(cal.to_force_mn(CODE_MIN) < -970_000);
}

#[test]
fn tare_from_16_samples() {
    // Zero noise: the tare is the sim's offset exactly.
    let mut r = rig(0.0, Gain::A128);
    let samples: Vec<i32> = (0..16).map(|_| r.next_sample()).collect();
    let offset = Calibration::tare(&samples).unwrap();
    assert_eq!(offset, 31_000);
    assert!(Calibration::tare_plausible(offset));

    // Default noise (2 600 counts RMS): the mean of 16 is within 4σ/√16 = 2 600 counts.
    let mut r = rig_with(Hx711Config::default_for_rate(80), 0.0, Gain::A128);
    let samples: Vec<i32> = (0..16).map(|_| r.next_sample()).collect();
    assert!(samples.iter().any(|&s| s != samples[0]), "noise present");
    let offset = Calibration::tare(&samples).unwrap();
    assert!((offset - 31_000).abs() <= 2_600, "offset {offset}");
    assert!(Calibration::tare_plausible(offset));
    let cal = Calibration::SIM_DEFAULT.with_tare(offset);
    let at_zero_mn: Vec<i32> = samples.iter().map(|&c| cal.to_force_mn(c)).collect();
    let mean_mn = at_zero_mn.iter().map(|&m| i64::from(m)).sum::<i64>() / 16;
    assert!(mean_mn.abs() <= 1, "mean force after tare {mean_mn} mN");

    // Taring with 300 N on the cell (≈ 2.6 M counts > 2^21) is implausible.
    let mut r = rig(300.0, Gain::A128);
    let samples: Vec<i32> = (0..16).map(|_| r.next_sample()).collect();
    let offset = Calibration::tare(&samples).unwrap();
    assert!(!Calibration::tare_plausible(offset), "offset {offset}");
}

#[test]
fn sim_default_calibration_matches_the_sim_cell() {
    let mut r = rig(0.0, Gain::A128);
    let cal = Calibration::SIM_DEFAULT;
    for f_n in [-300, -1, 0, 1, 100, 250, 500] {
        let mn = cal.to_force_mn(r.sample_at(f64::from(f_n)));
        assert!((mn - f_n * 1_000).abs() <= 1, "{f_n} N -> {mn} mN");
    }
}

/// Set while the probe's PD_SCK is high (only the critical-section test uses it).
static PROBE_SCK_HIGH: AtomicBool = AtomicBool::new(false);

/// The sim's PD_SCK pin that stays high for 50 µs of *wall* time (virtual time is
/// untouched), so that a thread entering a critical section would see it high if the
/// driver's high phase were not itself a critical section.
struct ProbeSck(Hx711Sck);

impl ErrorType for ProbeSck {
    type Error = core::convert::Infallible;
}

impl OutputPin for ProbeSck {
    fn set_high(&mut self) -> Result<(), Self::Error> {
        self.0.set_high()?;
        PROBE_SCK_HIGH.store(true, Ordering::SeqCst);
        std::thread::sleep(Duration::from_micros(50));
        Ok(())
    }

    fn set_low(&mut self) -> Result<(), Self::Error> {
        PROBE_SCK_HIGH.store(false, Ordering::SeqCst);
        self.0.set_low()
    }
}

#[test]
fn clock_high_phase_runs_inside_a_critical_section() {
    // On the board an interrupt is code that runs only outside critical sections; here a
    // second thread plays it (critical-section's `std` impl is a global lock), checking
    // PD_SCK every time it gets in. It must never find it high.
    let clock = SimClock::new();
    let cfg = Hx711Config {
        noise_counts: 0.0,
        ..Hx711Config::default_for_rate(80)
    };
    let hx = SimHx711::new(cfg, clock.clone(), |_t_ns| 10.0, 1);
    let mut drv = Hx711::new(hx.dout(), ProbeSck(hx.pd_sck()), clock.clone(), Gain::A128).unwrap();

    let stop = Arc::new(AtomicBool::new(false));
    let isr = {
        let stop = stop.clone();
        std::thread::spawn(move || {
            let (mut runs, mut saw_high) = (0u64, 0u64);
            while !stop.load(Ordering::SeqCst) {
                critical_section::with(|_| {
                    runs += 1;
                    if PROBE_SCK_HIGH.load(Ordering::SeqCst) {
                        saw_high += 1;
                    }
                });
                std::thread::yield_now();
            }
            (runs, saw_high)
        })
    };
    for _ in 0..20 {
        clock.advance_to_ns(hx.next_conversion_ns());
        assert_eq!(drv.read(), Ok(expected_code(10.0)));
    }
    stop.store(true, Ordering::SeqCst);
    let (runs, saw_high) = isr.join().unwrap();
    assert!(runs > 0, "the interrupt thread ran");
    assert_eq!(
        saw_high, 0,
        "an interrupt found PD_SCK high {saw_high} times"
    );
    assert_eq!(hx.stats().power_downs, 0);
}

// --- A tiny mock part: exact pulse counts, pin errors -----------------------------------

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct MockErr;

impl embedded_hal::digital::Error for MockErr {
    fn kind(&self) -> embedded_hal::digital::ErrorKind {
        embedded_hal::digital::ErrorKind::Other
    }
}

#[derive(Default)]
struct Part {
    code: u32,
    ready: bool,
    pulses: u8,
    sck_high: bool,
    rises: u32,
    /// Fail the DOUT read made while this pulse is high.
    fail_read_at_pulse: Option<u8>,
}

struct MockDout(Rc<RefCell<Part>>);
struct MockSck(Rc<RefCell<Part>>);
struct NoDelay;

impl ErrorType for MockDout {
    type Error = MockErr;
}

impl InputPin for MockDout {
    fn is_high(&mut self) -> Result<bool, MockErr> {
        let p = self.0.borrow();
        if p.pulses > 0 && p.fail_read_at_pulse == Some(p.pulses) {
            return Err(MockErr);
        }
        Ok(match p.pulses {
            0 => !p.ready,
            n @ 1..=24 => (p.code >> (24 - n)) & 1 == 1,
            _ => true,
        })
    }

    fn is_low(&mut self) -> Result<bool, MockErr> {
        self.is_high().map(|h| !h)
    }
}

impl ErrorType for MockSck {
    type Error = MockErr;
}

impl OutputPin for MockSck {
    fn set_high(&mut self) -> Result<(), MockErr> {
        let mut p = self.0.borrow_mut();
        if !p.sck_high {
            p.pulses += 1;
            p.rises += 1;
        }
        p.sck_high = true;
        Ok(())
    }

    fn set_low(&mut self) -> Result<(), MockErr> {
        self.0.borrow_mut().sck_high = false;
        Ok(())
    }
}

impl DelayNs for NoDelay {
    fn delay_ns(&mut self, _ns: u32) {}
}

fn mock(gain: Gain) -> (Rc<RefCell<Part>>, Hx711<MockDout, MockSck, NoDelay>) {
    let part = Rc::new(RefCell::new(Part {
        sck_high: true,
        ..Part::default()
    }));
    let hx = Hx711::new(MockDout(part.clone()), MockSck(part.clone()), NoDelay, gain).unwrap();
    assert!(!part.borrow().sck_high, "new() leaves PD_SCK low");
    (part, hx)
}

fn serve(part: &Rc<RefCell<Part>>, code: u32) {
    let mut p = part.borrow_mut();
    p.code = code;
    p.ready = true;
    p.pulses = 0;
}

#[test]
fn mock_readout_codes_and_pulse_counts() {
    for (gain, pulses) in [(Gain::A128, 25), (Gain::B32, 26), (Gain::A64, 27)] {
        let (part, mut hx) = mock(gain);
        assert_eq!(hx.read(), Err(nb::Error::WouldBlock));
        assert_eq!(part.borrow().rises, 0, "WouldBlock does not clock");
        for (raw, code) in [
            (0x7F_FFFFu32, CODE_MAX),
            (0x80_0000, CODE_MIN),
            (0x00_0000, 0),
            (0xFF_FFFF, -1),
            (0x00_0001, 1),
            (0x12_3456, 0x12_3456),
            (0xA5_5A5A, sign_extend_24(0xA5_5A5A)),
        ] {
            serve(&part, raw);
            let before = part.borrow().rises;
            assert_eq!(hx.read(), Ok(code), "{raw:#08x}");
            let p = part.borrow();
            assert_eq!(p.rises - before, pulses);
            assert!(!p.sck_high);
        }
    }
}

#[test]
fn mock_pin_error_still_drops_the_clock() {
    let (part, mut hx) = mock(Gain::A128);
    serve(&part, 0x12_3456);
    part.borrow_mut().fail_read_at_pulse = Some(5);
    assert_eq!(hx.read(), Err(nb::Error::Other(Hx711Error::Pin(MockErr))));
    let p = part.borrow();
    assert!(!p.sck_high, "PD_SCK low after the error");
    assert_eq!(p.rises, 5, "no clocking after the error");
}

#[test]
fn mock_power_down_blocks_reads_until_power_up() {
    let (part, mut hx) = mock(Gain::A128);
    hx.power_down().unwrap();
    assert!(hx.is_powered_down());
    assert!(part.borrow().sck_high);
    serve(&part, 5);
    assert_eq!(hx.read(), Err(nb::Error::WouldBlock));
    assert_eq!(part.borrow().rises, 1, "only power_down's own rising edge");
    hx.power_up().unwrap();
    assert!(!hx.is_powered_down());
    assert!(!part.borrow().sck_high);
    serve(&part, 5);
    assert_eq!(hx.read(), Ok(5));
    let (_dout, _sck, _delay) = hx.release();
}

#[test]
fn error_display() {
    assert_eq!(
        Hx711Error::Pin(MockErr).to_string(),
        "HX711 pin error: MockErr"
    );
}
