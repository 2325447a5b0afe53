//! A simulated HX711 24-bit load-cell ADC, at pin level, in virtual time.
//!
//! Behaviour follows the Avia HX711 datasheet:
//! * conversions run continuously at the selected rate: 10 or 80 SPS (the RATE pin; a
//!   model at other rates is not an HX711 — the HX717 has 320 SPS — and only the
//!   accuracy study uses one); DOUT goes **low** when a conversion is ready;
//! * each PD_SCK rising edge shifts out one bit, MSB first, 24 bits in two's complement;
//!   after the 24th bit, 1–3 more pulses select the next conversion's channel/gain
//!   (25: A/128, 26: B/32, 27: A/64) and DOUT returns high;
//! * PD_SCK held high for more than 60 µs powers the chip down; returning it low resets
//!   it, and the first conversion after reset is ready only after the settling time
//!   (4 conversion periods: 400 ms at 10 SPS, 50 ms at 80 SPS); a readout that selects
//!   another gain or channel restarts the settling the same way;
//! * outputs saturate at 0x7FFFFF / 0x800000.
//!
//! The analogue side is `code = offset + gain · F + noise` with F from a
//! [`ForceSource`] (the docking profile at the simulated axis position, plus whatever a
//! scene adds). Faults: a disconnected part (DOUT floats high on its pull-up: never
//! ready), a saturated bridge (rail code), a stuck converter (the same code forever).

use std::cell::RefCell;
use std::rc::Rc;

use crate::clock::SimClock;
use crate::rng::Rng;

/// Largest 24-bit two's-complement code.
pub const CODE_MAX: i32 = 0x7F_FFFF;
/// Smallest 24-bit two's-complement code.
pub const CODE_MIN: i32 = -0x80_0000;
/// PD_SCK high longer than this powers the part down, ns (datasheet: 60 µs).
pub const POWER_DOWN_NS: u64 = 60_000;

/// What the load cell measures, N, as a function of virtual time.
pub trait ForceSource {
    /// Force on the load cell at `t_ns`, newtons.
    fn force_n(&mut self, t_ns: u64) -> f64;

    /// Told once, when the part is built, the front end the part reads this source
    /// through (a source may tabulate [`ForceSource::counts`] for it).
    fn front_end(&mut self, _front: &Hx711Config) {}

    /// The bridge's output at `t_ns` through `front` (the one [`ForceSource::front_end`]
    /// was told), counts at gain 128 before noise: `offset_counts + counts_per_n · F`.
    /// A source may tabulate it: it must give the same value, bit for bit, and count as
    /// one [`ForceSource::force_n`] call.
    #[inline]
    fn counts(&mut self, t_ns: u64, front: &Hx711Config) -> f64 {
        front.offset_counts + front.counts_per_n * self.force_n(t_ns)
    }
}

impl<F: FnMut(u64) -> f64> ForceSource for F {
    fn force_n(&mut self, t_ns: u64) -> f64 {
        self(t_ns)
    }
}

/// Any source, boxed (the default: scenes and tests pass closures).
pub type BoxedSource = Box<dyn ForceSource>;

impl ForceSource for BoxedSource {
    fn force_n(&mut self, t_ns: u64) -> f64 {
        (**self).force_n(t_ns)
    }
}

/// Injected device faults.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Hx711Fault {
    /// Working normally.
    None,
    /// Wire off: DOUT reads high (pull-up) for ever, so no sample is ever ready.
    Disconnected,
    /// Bridge fault: every conversion reads the positive rail.
    Saturated,
    /// Converter stuck: every conversion repeats the last code.
    Stuck,
}

/// Analogue front end and rate.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hx711Config {
    /// Output data rate, samples/s (10 or 80 on an HX711).
    pub rate_sps: u32,
    /// Code at zero force (bridge offset), counts.
    pub offset_counts: f64,
    /// Sensitivity, counts per newton (gain 128).
    pub counts_per_n: f64,
    /// RMS noise, counts.
    pub noise_counts: f64,
}

impl Hx711Config {
    /// A 500 N, 2 mV/V cell at 5 V excitation on channel A/128: ≈ 8 590 counts/N,
    /// rails at ±976 N; offset 31 000 counts (≈ 3.6 N); noise ≈ 0.3 N RMS.
    pub fn default_for_rate(rate_sps: u32) -> Self {
        Self {
            rate_sps,
            offset_counts: 31_000.0,
            counts_per_n: 8_590.0,
            noise_counts: 2_600.0,
        }
    }

    /// Rates this part offers (its RATE pin low or high).
    pub const RATES_SPS: [u32; 2] = [10, 80];

    fn period_ns(&self) -> u64 {
        1_000_000_000 / self.rate_sps.max(1) as u64
    }
}

/// Counters a test or scene can read.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Hx711Stats {
    /// Conversions completed.
    pub conversions: u64,
    /// Samples read out completely (24 bits).
    pub samples_read: u64,
    /// Conversions overwritten before they were read, once reading had begun (the
    /// conversions of a part nobody reads yet are not misses).
    pub samples_missed: u64,
    /// Times the part powered down (PD_SCK high > 60 µs).
    pub power_downs: u64,
}

/// The device model; shared by its two pins. Generic over its force source so that a
/// long run's source is called directly (inlined), not through a vtable.
pub struct Hx711Model<S = BoxedSource> {
    cfg: Hx711Config,
    /// Conversion period, ns (cached: the model is consulted several times a sample).
    period_ns: u64,
    source: S,
    rng: Rng,
    /// The noise of the next conversion that has any, counts (`noise_counts` times the
    /// generator's next normal): drawn one conversion ahead, so that drawing it is not on
    /// the way from the force to the code. Every noisy conversion takes the next one, in
    /// order: the same noise as drawing it at the conversion.
    next_noise: f64,
    fault: Hx711Fault,
    /// Time of the next conversion completion, ns.
    next_conv_ns: u64,
    /// Latest completed conversion (code, completion time), not yet read.
    ready: Option<(i32, u64)>,
    /// Code being shifted out.
    shift: i32,
    /// PD_SCK pulses since the readout began (0 = idle).
    pulses: u8,
    /// Gain pulses of the last complete readout (25, 26 or 27).
    gain_pulses: u8,
    sck_high_since: Option<u64>,
    last_code: i32,
    stats: Hx711Stats,
    /// Ready time of the conversion now being read (for latency measurements).
    reading_ready_ns: u64,
    last_read: Option<(i32, u64)>,
    /// The last [`RECENT`] conversions: (completion time ns, code, read out), a ring
    /// (a fixed array: this runs at every conversion of a 45 000-cycle life run).
    recent: [(u64, i32, bool); RECENT],
    /// Conversions written to `recent` so far (the next goes to this count modulo
    /// [`RECENT`]; the last `min(count, RECENT)` are kept).
    recent_count: u64,
}

/// Conversions kept in [`SimHx711::recent_conversions`].
pub const RECENT: usize = 64;

impl<S: ForceSource> Hx711Model<S> {
    fn settle_ns(&self) -> u64 {
        4 * self.period_ns
    }

    /// Complete the conversions due by `now`. Nothing is due in the common case (the
    /// model is consulted several times per conversion): that is decided inline.
    #[inline(always)]
    fn catch_up(&mut self, now: u64) {
        if now >= self.next_conv_ns {
            self.convert_due(now);
        }
    }

    fn convert_due(&mut self, now: u64) {
        if self
            .sck_high_since
            .is_some_and(|t| now.saturating_sub(t) > POWER_DOWN_NS)
        {
            return; // powered down: no conversions
        }
        while self.next_conv_ns <= now {
            self.complete_next();
        }
    }

    /// Complete the conversion due at `next_conv_ns`. Kept out of line: inlined into the
    /// loop above, every field it reads would be loaded before the loop (which runs once
    /// in the usual case) and spilled.
    #[inline(never)]
    fn complete_next(&mut self) {
        let t = self.next_conv_ns;
        self.next_conv_ns += self.period_ns;
        if self.pulses != 0 && self.pulses < 25 {
            return; // readout in progress: the part holds its output register
        }
        let code = self.convert(t);
        if self.ready.is_some() && self.stats.samples_read > 0 {
            self.stats.samples_missed += 1;
        }
        self.stats.conversions += 1;
        self.ready = Some((code, t));
        if let Some(slot) = self.recent.get_mut(self.recent_count as usize % RECENT) {
            *slot = (t, code, false);
        }
        self.recent_count += 1;
        self.pulses = 0;
    }

    /// The code of the conversion completing at `t_ns`: the analogue side at the gain
    /// of the last readout, noise, rounding, the rails; or what a fault makes of it.
    #[inline]
    fn convert(&mut self, t_ns: u64) -> i32 {
        if self.fault != Hx711Fault::None || self.gain_pulses != 25 {
            return self.convert_other(t_ns);
        }
        // Channel A/128 scales by 1.0: left out (`x * 1.0` is `x`).
        let counts = self.source.counts(t_ns, &self.cfg);
        let code = self.noisy_code(counts);
        self.last_code = code;
        code
    }

    /// [`Self::convert`] with a fault, or at another gain than A/128.
    #[inline(never)]
    fn convert_other(&mut self, t_ns: u64) -> i32 {
        let code = match self.fault {
            Hx711Fault::Saturated => CODE_MAX,
            Hx711Fault::Stuck if self.stats.conversions > 0 => self.last_code,
            _ => {
                let counts = self.source.counts(t_ns, &self.cfg);
                let at_gain = match self.gain_pulses {
                    26 => counts * (32.0 / 128.0),
                    27 => counts * (64.0 / 128.0),
                    _ => counts,
                };
                self.noisy_code(at_gain)
            }
        };
        self.last_code = code;
        code
    }

    /// `counts` plus the part's noise, rounded half away from zero with a cast (no libm
    /// call), saturated at the rails like the part.
    #[inline]
    fn noisy_code(&mut self, counts: f64) -> i32 {
        let v = counts + self.next_noise;
        self.next_noise = self.cfg.noise_counts * self.rng.normal();
        let r = (v + 0.5f64.copysign(v)) as i64;
        r.clamp(CODE_MIN as i64, CODE_MAX as i64) as i32
    }

    /// [`SimHx711::read_word`] at `now`, but for the readout's time.
    #[inline]
    fn read_word_at(&mut self, now: u64) -> Option<i32> {
        let t = self.next_conv_ns;
        let due_one = now >= t && now - t < self.period_ns;
        let between_readouts = self.pulses == 0 || self.pulses >= 25;
        if !(due_one
            && between_readouts
            && self.fault != Hx711Fault::Disconnected
            && self.sck_high_since.is_none())
        {
            return self.read_word_other(now);
        }
        // The usual read: one conversion is due and nothing holds it (the part is
        // connected, powered, not being read out): it completes and is read at once —
        // what `catch_up`, `complete_next` and the read in `read_word_other` do, in one
        // pass (it is the newest conversion, so it is marked read as it is recorded).
        self.next_conv_ns = t + self.period_ns;
        let code = self.convert(t);
        if self.ready.is_some() && self.stats.samples_read > 0 {
            self.stats.samples_missed += 1;
        }
        self.ready = None;
        self.stats.conversions += 1;
        if let Some(slot) = self.recent.get_mut(self.recent_count as usize % RECENT) {
            *slot = (t, code, true);
        }
        self.recent_count += 1;
        self.stats.samples_read += 1;
        self.gain_pulses = 25;
        self.pulses = 25;
        self.last_read = Some((code, t));
        Some(code)
    }

    /// [`Self::read_word_at`] in general: a disconnected part, one powered down or
    /// being read out, none or several conversions due.
    #[inline(never)]
    fn read_word_other(&mut self, now: u64) -> Option<i32> {
        if self.fault == Hx711Fault::Disconnected {
            return None;
        }
        self.catch_up(now);
        if self.pulses != 0 {
            return None;
        }
        let (code, t) = self.ready.take()?;
        self.stats.samples_read += 1;
        self.gain_pulses = 25;
        self.pulses = 25;
        self.last_read = Some((code, t));
        self.mark_read(t);
        Some(code)
    }

    #[inline]
    fn mark_read(&mut self, t: u64) {
        // The one read is the newest conversion (the part converts nothing while it is
        // read out, and a newer conversion replaces the one not yet read): checked
        // first, without the walk.
        if self.recent_count > 0 {
            let newest = (self.recent_count - 1) as usize % RECENT;
            if let Some(c) = self.recent.get_mut(newest).filter(|c| c.0 == t) {
                c.2 = true;
                return;
            }
        }
        self.mark_read_older(t);
    }

    /// [`Self::mark_read`] of a conversion older than the newest, newest first.
    #[cold]
    #[inline(never)]
    fn mark_read_older(&mut self, t: u64) {
        for back in 1..=self.recent_len() as u64 {
            let i = (self.recent_count - back) as usize % RECENT;
            if let Some(c) = self.recent.get_mut(i) {
                if c.0 == t {
                    c.2 = true;
                    return;
                }
            }
        }
    }

    /// Conversions kept in `recent`.
    fn recent_len(&self) -> usize {
        self.recent_count.min(RECENT as u64) as usize
    }

    fn dout_high(&mut self, now: u64) -> bool {
        if self.fault == Hx711Fault::Disconnected {
            return true;
        }
        self.catch_up(now);
        if self
            .sck_high_since
            .is_some_and(|t| now.saturating_sub(t) > POWER_DOWN_NS)
        {
            return true;
        }
        match self.pulses {
            0 => self.ready.is_none(),
            1..=24 => (self.shift >> (24 - self.pulses)) & 1 == 1,
            _ => true,
        }
    }

    fn sck_rise(&mut self, now: u64) {
        self.catch_up(now);
        self.sck_high_since = Some(now);
        if self.fault == Hx711Fault::Disconnected {
            return;
        }
        if self.pulses == 0 {
            if let Some((code, t)) = self.ready.take() {
                self.shift = code & 0xFF_FFFF;
                self.reading_ready_ns = t;
                self.pulses = 1;
            }
        } else if self.pulses < 27 {
            self.pulses += 1;
            if self.pulses == 24 {
                self.stats.samples_read += 1;
                let code = (self.shift << 8) >> 8;
                self.last_read = Some((code, self.reading_ready_ns));
                self.mark_read(self.reading_ready_ns);
            }
        }
    }

    fn sck_fall(&mut self, now: u64) {
        let high_since = self.sck_high_since.take();
        if high_since.is_some_and(|t| now.saturating_sub(t) > POWER_DOWN_NS) {
            // Power-down, then reset on the falling edge: settle before the next sample.
            self.stats.power_downs += 1;
            self.ready = None;
            self.pulses = 0;
            self.gain_pulses = 25;
            self.next_conv_ns = now + self.settle_ns();
            return;
        }
        if self.pulses >= 25 {
            if self.pulses != self.gain_pulses {
                // Another gain or channel: the output settles over 4 conversions again.
                self.ready = None;
                self.next_conv_ns = now + self.settle_ns();
            }
            self.gain_pulses = self.pulses;
        }
    }
}

/// Handle to a simulated HX711 for the scene (configuration, faults, statistics).
pub struct SimHx711<S = BoxedSource> {
    model: Rc<RefCell<Hx711Model<S>>>,
    clock: SimClock,
}

// Not derived: a derive would ask for `S: Clone`, and the handle only clones the `Rc`.
impl<S> Clone for SimHx711<S> {
    fn clone(&self) -> Self {
        Self {
            model: self.model.clone(),
            clock: self.clock.clone(),
        }
    }
}

impl SimHx711 {
    /// A part powered up at the clock's current time (first sample after settling).
    pub fn new(
        cfg: Hx711Config,
        clock: SimClock,
        source: impl ForceSource + 'static,
        seed: u64,
    ) -> Self {
        Self::with_source(cfg, clock, Box::new(source), seed)
    }
}

impl<S: ForceSource> SimHx711<S> {
    /// [`SimHx711::new`] with a source of a named type (called without a vtable).
    pub fn with_source(cfg: Hx711Config, clock: SimClock, source: S, seed: u64) -> Self {
        let now = clock.now_ns();
        let mut m = Hx711Model {
            period_ns: cfg.period_ns(),
            cfg,
            source,
            rng: Rng::new(seed),
            next_noise: 0.0,
            fault: Hx711Fault::None,
            next_conv_ns: 0,
            ready: None,
            shift: 0,
            pulses: 0,
            gain_pulses: 25,
            sck_high_since: None,
            last_code: 0,
            stats: Hx711Stats::default(),
            reading_ready_ns: 0,
            last_read: None,
            recent: [(0, 0, false); RECENT],
            recent_count: 0,
        };
        m.next_conv_ns = now + m.settle_ns();
        m.next_noise = cfg.noise_counts * m.rng.normal();
        m.source.front_end(&cfg);
        Self {
            model: Rc::new(RefCell::new(m)),
            clock,
        }
    }

    /// The data-output pin (an `InputPin` for the driver).
    pub fn dout(&self) -> Hx711Dout<S> {
        Hx711Dout {
            model: self.model.clone(),
            clock: self.clock.clone(),
        }
    }

    /// The clock/power-down pin (an `OutputPin` for the driver).
    pub fn pd_sck(&self) -> Hx711Sck<S> {
        Hx711Sck {
            model: self.model.clone(),
            clock: self.clock.clone(),
        }
    }

    /// Inject or clear a fault.
    pub fn set_fault(&self, fault: Hx711Fault) {
        self.model.borrow_mut().fault = fault;
    }

    /// The injected fault.
    pub fn fault(&self) -> Hx711Fault {
        self.model.borrow().fault
    }

    /// The last conversions, oldest first: (completion time ns, code, read out).
    pub fn recent_conversions(&self) -> Vec<(u64, i32, bool)> {
        let now = self.clock.now_ns();
        let mut m = self.model.borrow_mut();
        m.catch_up(now);
        (0..m.recent_len() as u64)
            .rev()
            .filter_map(|back| m.recent.get((m.recent_count - 1 - back) as usize % RECENT))
            .copied()
            .collect()
    }

    /// Counters so far.
    pub fn stats(&self) -> Hx711Stats {
        self.model.borrow().stats
    }

    /// Configuration.
    pub fn config(&self) -> Hx711Config {
        self.model.borrow().cfg
    }

    /// Time of the next conversion completion, ns (for an event-driven scene loop);
    /// `u64::MAX` while powered down (SCK high > 60 µs): none is due until SCK falls.
    pub fn next_conversion_ns(&self) -> u64 {
        let now = self.clock.now_ns();
        let mut m = self.model.borrow_mut();
        m.catch_up(now);
        if m.sck_high_since
            .is_some_and(|t| now.saturating_sub(t) > POWER_DOWN_NS)
        {
            // Powered down: nothing converts until SCK goes low again.
            return u64::MAX;
        }
        m.next_conv_ns
    }

    /// The last sample read out completely: (code, time its conversion completed, ns).
    pub fn last_read(&self) -> Option<(i32, u64)> {
        self.model.borrow().last_read
    }

    /// Word-level read: the whole 24-bit readout (with 25 gain pulses) in one call,
    /// taking the same virtual time as the firmware's driver's delays
    /// (`docking_logic::hx711::readout_ns`). Same
    /// data-ready and power-down semantics as the pins; for long runs where the
    /// bit-level protocol has been proven by the driver tests.
    pub fn read_word(&self) -> Option<i32> {
        let mut m = self.model.borrow_mut();
        let now = self.clock.now_ns();
        let code = m.read_word_at(now)?;
        drop(m);
        self.clock
            .advance_ns(docking_logic::hx711::readout_ns(25) as u64);
        Some(code)
    }
}

/// HX711 DOUT as an embedded-hal `InputPin`.
pub struct Hx711Dout<S = BoxedSource> {
    model: Rc<RefCell<Hx711Model<S>>>,
    clock: SimClock,
}

/// HX711 PD_SCK as an embedded-hal `OutputPin`.
pub struct Hx711Sck<S = BoxedSource> {
    model: Rc<RefCell<Hx711Model<S>>>,
    clock: SimClock,
}

impl<S> embedded_hal::digital::ErrorType for Hx711Dout<S> {
    type Error = core::convert::Infallible;
}

impl<S: ForceSource> embedded_hal::digital::InputPin for Hx711Dout<S> {
    fn is_high(&mut self) -> Result<bool, Self::Error> {
        Ok(self.model.borrow_mut().dout_high(self.clock.now_ns()))
    }

    fn is_low(&mut self) -> Result<bool, Self::Error> {
        self.is_high().map(|h| !h)
    }
}

impl<S> embedded_hal::digital::ErrorType for Hx711Sck<S> {
    type Error = core::convert::Infallible;
}

impl<S: ForceSource> embedded_hal::digital::OutputPin for Hx711Sck<S> {
    fn set_high(&mut self) -> Result<(), Self::Error> {
        let mut m = self.model.borrow_mut();
        if m.sck_high_since.is_none() {
            m.sck_rise(self.clock.now_ns());
        }
        Ok(())
    }

    fn set_low(&mut self) -> Result<(), Self::Error> {
        let mut m = self.model.borrow_mut();
        if m.sck_high_since.is_some() {
            m.sck_fall(self.clock.now_ns());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_hal::delay::DelayNs;
    use embedded_hal::digital::{InputPin, OutputPin};

    /// Bit-bang one readout exactly as the datasheet describes; `None` if not ready.
    fn bitbang(
        dout: &mut Hx711Dout,
        sck: &mut Hx711Sck,
        clk: &mut SimClock,
        pulses: u8,
    ) -> Option<i32> {
        if dout.is_high().unwrap() {
            return None;
        }
        let mut v: u32 = 0;
        for i in 0..pulses {
            sck.set_high().unwrap();
            clk.delay_us(1);
            if i < 24 {
                v = (v << 1) | dout.is_high().unwrap() as u32;
            }
            sck.set_low().unwrap();
            clk.delay_us(1);
        }
        Some(((v << 8) as i32) >> 8)
    }

    fn part(force: f64, rate: u32) -> (SimHx711, SimClock) {
        let clk = SimClock::new();
        let cfg = Hx711Config {
            noise_counts: 0.0,
            ..Hx711Config::default_for_rate(rate)
        };
        (SimHx711::new(cfg, clk.clone(), move |_| force, 1), clk)
    }

    #[test]
    fn first_sample_after_settling_then_at_the_rate() {
        let (hx, mut clk) = part(10.0, 80);
        let (mut d, mut s) = (hx.dout(), hx.pd_sck());
        clk.advance_to_ns(49_999_999);
        assert_eq!(bitbang(&mut d, &mut s, &mut clk, 25), None);
        clk.advance_to_ns(50_000_000);
        let code = bitbang(&mut d, &mut s, &mut clk, 25).unwrap();
        assert_eq!(code, (31_000.0f64 + 85_900.0) as i32);
        assert!(d.is_high().unwrap(), "DOUT returns high after the readout");
        clk.advance_to_ns(62_499_999);
        assert!(d.is_high().unwrap());
        clk.advance_to_ns(62_500_000);
        assert!(d.is_low().unwrap());
    }

    #[test]
    fn negative_codes_and_rails() {
        let (hx, mut clk) = part(-2_000.0, 10);
        clk.advance_to_ns(400_000_000);
        let (mut d, mut s) = (hx.dout(), hx.pd_sck());
        assert_eq!(bitbang(&mut d, &mut s, &mut clk, 25), Some(CODE_MIN));
        let (hx, mut clk) = part(2_000.0, 10);
        clk.advance_to_ns(400_000_000);
        let (mut d, mut s) = (hx.dout(), hx.pd_sck());
        assert_eq!(bitbang(&mut d, &mut s, &mut clk, 25), Some(CODE_MAX));
    }

    #[test]
    fn clock_high_over_60us_powers_down_and_resets() {
        let (hx, mut clk) = part(0.0, 80);
        let (mut d, mut s) = (hx.dout(), hx.pd_sck());
        clk.advance_to_ns(50_000_000);
        s.set_high().unwrap();
        clk.delay_us(61);
        assert!(d.is_high().unwrap(), "powered down");
        s.set_low().unwrap();
        assert_eq!(hx.stats().power_downs, 1);
        let t_reset = clk.now_ns();
        clk.advance_to_ns(t_reset + 49_000_000);
        assert!(d.is_high().unwrap(), "still settling");
        clk.advance_to_ns(t_reset + 50_000_000);
        assert!(d.is_low().unwrap());
    }

    #[test]
    fn a_powered_down_part_announced_a_conversion_in_the_past() {
        // An event loop waits for the next conversion: while the part is powered down
        // (SCK held high), a time in the past would make it spin without time passing.
        let (hx, clk) = part(0.0, 80);
        let mut s = hx.pd_sck();
        clk.advance_to_ns(45_000_000);
        s.set_high().unwrap();
        clk.advance_to_ns(70_000_000);
        assert_eq!(hx.next_conversion_ns(), u64::MAX, "powered down");
        s.set_low().unwrap();
        let next = hx.next_conversion_ns();
        assert!(
            next > clk.now_ns(),
            "{next} after power-up at {}",
            clk.now_ns()
        );
    }

    #[test]
    fn gain_pulses_select_the_next_gain_after_settling() {
        let (hx, mut clk) = part(10.0, 80);
        let (mut d, mut s) = (hx.dout(), hx.pd_sck());
        clk.advance_to_ns(50_000_000);
        let a128 = bitbang(&mut d, &mut s, &mut clk, 27).unwrap();
        let t = clk.now_ns();
        clk.advance_to_ns(t + 49_000_000);
        assert!(
            d.is_high().unwrap(),
            "settling over 4 conversions after a gain change"
        );
        clk.advance_to_ns(t + 50_000_000);
        let a64 = bitbang(&mut d, &mut s, &mut clk, 25).unwrap();
        assert_eq!(a64, a128 / 2);
    }

    #[test]
    fn faults_behave_like_the_hardware() {
        let (hx, mut clk) = part(10.0, 80);
        let (mut d, mut s) = (hx.dout(), hx.pd_sck());
        hx.set_fault(Hx711Fault::Disconnected);
        clk.advance_to_ns(1_000_000_000);
        assert_eq!(bitbang(&mut d, &mut s, &mut clk, 25), None);
        hx.set_fault(Hx711Fault::Saturated);
        clk.advance_ns(12_500_000);
        assert_eq!(bitbang(&mut d, &mut s, &mut clk, 25), Some(CODE_MAX));
        hx.set_fault(Hx711Fault::Stuck);
        clk.advance_ns(12_500_000);
        assert_eq!(bitbang(&mut d, &mut s, &mut clk, 25), Some(CODE_MAX));
    }

    /// A word read at the instant a conversion completes takes the one-pass path; the
    /// same read after something else completed the conversion takes the general one:
    /// the same codes, statistics and conversion record either way (missed samples
    /// included).
    #[test]
    fn a_word_read_at_the_conversion_is_the_general_read() {
        let parts = || {
            let clk = SimClock::new();
            let cfg = Hx711Config::default_for_rate(80);
            let hx = SimHx711::new(cfg, clk.clone(), |t: u64| (t % 7_000) as f64 * 0.01, 9);
            (hx, clk)
        };
        let (one_pass, c1) = parts();
        let (general, c2) = parts();
        for i in 0..300u64 {
            for (hx, clk, catch_up_first) in [(&one_pass, &c1, false), (&general, &c2, true)] {
                let next = hx.next_conversion_ns();
                clk.advance_to_ns(next + (i % 2) * 1_000);
                if catch_up_first {
                    let _ = hx.next_conversion_ns(); // completes the conversion
                }
            }
            if i % 5 != 3 {
                // (Every fifth sample is left unread: the next read counts it missed.)
                assert_eq!(one_pass.read_word(), general.read_word(), "read {i}");
            }
        }
        assert!(one_pass.stats().samples_missed > 0);
        assert_eq!(one_pass.stats(), general.stats());
        assert_eq!(one_pass.last_read(), general.last_read());
        assert_eq!(one_pass.recent_conversions(), general.recent_conversions());
    }

    #[test]
    fn word_read_matches_pin_read() {
        let (hx, clk) = part(42.0, 80);
        clk.advance_to_ns(50_000_000); // after the 4-conversion settling
        let w = hx.read_word().unwrap();
        assert_eq!(w, (31_000.0f64 + 42.0 * 8_590.0).round() as i32);
        assert_eq!(hx.read_word(), None);
    }
}
