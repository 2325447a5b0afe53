//! HX711 24-bit load-cell ADC driver (embedded-hal 1.0 digital pins) and the
//! calibration of its codes to force in millinewtons.
//!
//! # What it guarantees
//!
//! * [`Hx711::read`] never blocks: while DOUT is high (no conversion ready, or the part
//!   powered down or disconnected: DOUT floats high on its pull-up) it returns
//!   `nb::Error::WouldBlock` **without touching PD_SCK**. When a conversion is ready it
//!   clocks out the 24 data bits MSB first plus 1–3 gain pulses and returns the
//!   sign-extended two's-complement code in [`CODE_MIN`]`..=`[`CODE_MAX`].
//! * During a readout PD_SCK is never high longer than [`SCK_HIGH_NS`] plus one pin
//!   write and one pin read, whatever interrupts do (see "Power-down hazard" below; this
//!   assumes the `DelayNs` does not overshoot by tens of µs), so a readout cannot power
//!   the part down and return garbage.
//! * PD_SCK is driven low again after every clock pulse, even when a pin operation
//!   fails.
//! * [`Calibration`] arithmetic is integer only, cannot overflow or panic for any
//!   input, and saturates into `i32` millinewtons.
//! * No floating point, no `unsafe`, no panics, no indexing.
//!
//! # Timing (Avia HX711 datasheet, "PD_SCK and DOUT timing")
//!
//! | symbol | meaning | datasheet | used here |
//! |---|---|---|---|
//! | T1 | DOUT falling edge → first PD_SCK rising edge | ≥ 0.1 µs | [`T1_WAIT_NS`] = 0.5 µs |
//! | T2 | PD_SCK rising edge → DOUT valid | ≤ 0.1 µs | DOUT sampled after T3 |
//! | T3 | PD_SCK high time | 0.2–50 µs | [`SCK_HIGH_NS`] = 0.5 µs |
//! | T4 | PD_SCK low time | ≥ 0.2 µs | [`SCK_LOW_NS`] = 0.5 µs |
//! | — | PD_SCK high → power-down | > 60 µs | [`POWER_DOWN_WAIT_US`] = 80 µs |
//! | — | settling after reset/power-up | 4 conversions (50 ms at 80 SPS, 400 ms at 10 SPS) | [`settling_time_us`] |
//!
//! A readout is T1 + (25…27) × (T3 + T4) = 25.5–27.5 µs ([`readout_ns`]): 2.5× the
//! datasheet minimum on every phase, and short, because the board reads the HX711 in
//! its stop path (the overload stop counts from DOUT falling).
//!
//! # Power-down hazard
//!
//! If PD_SCK stays high for more than 60 µs the HX711 powers down; when PD_SCK falls
//! again it resets, the word being shifted out is corrupted, and the next sample
//! arrives only after the settling time. On the board the step-pulse SysTick interrupt
//! fires every 50 µs (20 kHz), so an unprotected readout would routinely be interrupted
//! mid-pulse. Each clock-high phase (set PD_SCK high, wait T3,
//! sample DOUT, set PD_SCK low) therefore runs inside `critical_section::with`: no
//! interrupt can stretch it. The low phases run with interrupts enabled (T4 has no
//! maximum), so interrupts are delayed by at most one high phase (≈ 1 µs).
//! Consequence for the `DelayNs` given to [`Hx711::new`]: it must be a busy-wait delay
//! (cycle counter or polled timer) that works with interrupts masked — not one that
//! sleeps until an interrupt, and not SysTick if SysTick is the step generator.
//!
//! # Why not the `hx711` crate
//!
//! `hx711` 0.7.0 (crates.io, checked from its published source) is on embedded-hal
//! 1.0, but it is not correct for this controller:
//! * its `MIN_VALUE` is `1 << 23` = **+**8 388 608 (larger than its `MAX_VALUE`); the
//!   smallest code is −8 388 608;
//! * nothing protects the clock-high phase from interrupts, so an interrupt between
//!   `set_high` and `set_low` longer than 60 µs powers the part down and the corrupted
//!   word is returned as a valid sample;
//! * `Hx711::new` resets the part and then `nb::block!`s on a read, so with a
//!   disconnected sensor (DOUT held high by its pull-up) construction never returns —
//!   the controller could not report the fault;
//! * it has no calibration to physical units.
//!
//! # Pin errors
//!
//! Both pins must have the same error type `E` (on the STM32F4 HAL and in the
//! simulator both are `Infallible`); [`Hx711Error::Pin`] keeps that error unchanged and
//! stays `defmt::Format` on the board. Mapping both into `embedded_hal::digital::ErrorKind`
//! would accept mixed error types but lose the original error, and `ErrorKind` is
//! `defmt::Format` only with embedded-hal's `defmt-03` feature, which is not enabled. After a pin error mid-readout the part's bit counter
//! is unknown: reset it with [`Hx711::power_down`] + [`Hx711::power_up`].

use embedded_hal::delay::DelayNs;
use embedded_hal::digital::{InputPin, OutputPin};

/// Data bits per conversion.
pub const DATA_BITS: u8 = 24;
/// Largest code: 0x7FFFFF, the positive rail (input ≥ +0.5·AVDD/gain).
pub const CODE_MAX: i32 = 0x7F_FFFF;
/// Smallest code: 0x800000 sign-extended, the negative rail.
pub const CODE_MIN: i32 = -0x80_0000;

/// Datasheet T1 minimum: DOUT falling edge to the first PD_SCK rising edge, ns.
pub const T1_DOUT_TO_SCK_MIN_NS: u32 = 100;
/// Datasheet T2 maximum: PD_SCK rising edge to DOUT valid, ns.
pub const T2_SCK_TO_DOUT_MAX_NS: u32 = 100;
/// Datasheet T3 minimum: PD_SCK high time, ns.
pub const T3_SCK_HIGH_MIN_NS: u32 = 200;
/// Datasheet T3 maximum: PD_SCK high time, ns.
pub const T3_SCK_HIGH_MAX_NS: u32 = 50_000;
/// Datasheet T4 minimum: PD_SCK low time, ns (no maximum).
pub const T4_SCK_LOW_MIN_NS: u32 = 200;
/// PD_SCK high for longer than this powers the part down, ns (datasheet: 60 µs).
pub const POWER_DOWN_NS: u32 = 60_000;
/// Conversions the output needs to settle after reset or power-up (datasheet).
pub const SETTLING_CONVERSIONS: u32 = 4;

/// Wait between DOUT seen low and the first rising edge, ns (≥ T1).
pub const T1_WAIT_NS: u32 = 500;
/// PD_SCK high time this driver uses, ns (T3 within 0.2–50 µs).
pub const SCK_HIGH_NS: u32 = 500;
/// PD_SCK low time this driver uses, ns (T4 ≥ 0.2 µs).
pub const SCK_LOW_NS: u32 = 500;

/// The delays of one readout of `pulses` clock pulses (25–27), ns (the pin operations
/// come on top).
pub const fn readout_ns(pulses: u8) -> u32 {
    T1_WAIT_NS + pulses as u32 * (SCK_HIGH_NS + SCK_LOW_NS)
}
/// How long [`Hx711::power_down`] holds PD_SCK high, µs (> 60 µs, with margin).
pub const POWER_DOWN_WAIT_US: u32 = 80;

// The chosen timing must sit inside the datasheet limits.
const _: () = {
    assert!(T1_WAIT_NS >= T1_DOUT_TO_SCK_MIN_NS);
    assert!(SCK_HIGH_NS >= T3_SCK_HIGH_MIN_NS && SCK_HIGH_NS >= T2_SCK_TO_DOUT_MAX_NS);
    assert!(SCK_HIGH_NS <= T3_SCK_HIGH_MAX_NS);
    assert!(SCK_LOW_NS >= T4_SCK_LOW_MIN_NS);
    assert!(POWER_DOWN_WAIT_US * 1_000 > POWER_DOWN_NS);
};

/// Settling time after reset/power-up at `rate_sps` samples/s, µs (4 conversion
/// periods: 400 000 at 10 SPS, 50 000 at 80 SPS; a rate of 0 is treated as 1).
pub const fn settling_time_us(rate_sps: u32) -> u32 {
    let rate = if rate_sps == 0 { 1 } else { rate_sps };
    SETTLING_CONVERSIONS * (1_000_000 / rate)
}

/// Sign-extend a 24-bit two's-complement word (bits above 23 are ignored).
pub const fn sign_extend_24(raw: u32) -> i32 {
    // Move bit 23 to bit 31, reinterpret, arithmetic shift back.
    ((raw << 8) as i32) >> 8
}

/// Channel and gain of the **next** conversion, selected by the number of PD_SCK
/// pulses that end a readout (datasheet Table 3). The part starts on A/128 after reset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum Gain {
    /// Channel A, gain 128 (±20 mV input at 5 V AVDD): 25 pulses.
    A128 = 25,
    /// Channel B, gain 32: 26 pulses.
    B32 = 26,
    /// Channel A, gain 64: 27 pulses.
    A64 = 27,
}

impl Gain {
    /// PD_SCK pulses of a readout that selects this gain (24 data + 1–3).
    pub const fn pulses(self) -> u8 {
        self as u8
    }
}

/// Driver error.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum Hx711Error<E> {
    /// A DOUT or PD_SCK pin operation failed (the HAL's error, unchanged).
    Pin(E),
}

impl<E: core::fmt::Debug> core::fmt::Display for Hx711Error<E> {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        match self {
            Self::Pin(e) => write!(f, "HX711 pin error: {e:?}"),
        }
    }
}

impl<E: core::fmt::Debug> core::error::Error for Hx711Error<E> {}

/// HX711 driver on a DOUT input pin, a PD_SCK output pin and a busy-wait delay.
pub struct Hx711<DOUT: InputPin, SCK: OutputPin, D: DelayNs> {
    dout: DOUT,
    sck: SCK,
    delay: D,
    gain: Gain,
    powered_down: bool,
}

impl<DOUT, SCK, D, E> Hx711<DOUT, SCK, D>
where
    DOUT: InputPin<Error = E>,
    SCK: OutputPin<Error = E>,
    D: DelayNs,
{
    /// Take the pins and delay, drive PD_SCK low (part running); `gain` is selected by
    /// every readout, so it applies from the conversion after the first read.
    ///
    /// Does not wait for anything. After an MCU reset the part may be mid-readout or
    /// powered down; call [`Self::power_down`] + [`Self::power_up`] to start clean.
    pub fn new(dout: DOUT, mut sck: SCK, delay: D, gain: Gain) -> Result<Self, Hx711Error<E>> {
        sck.set_low().map_err(Hx711Error::Pin)?;
        Ok(Self {
            dout,
            sck,
            delay,
            gain,
            powered_down: false,
        })
    }

    /// The gain each readout selects for the following conversion.
    pub fn gain(&self) -> Gain {
        self.gain
    }

    /// Change the gain: the next [`Self::read`] still returns a conversion at the old
    /// gain (it was selected by the previous readout); the one after uses `gain`.
    pub fn set_gain(&mut self, gain: Gain) {
        self.gain = gain;
    }

    /// Whether [`Self::power_down`] was called without [`Self::power_up`] since.
    pub fn is_powered_down(&self) -> bool {
        self.powered_down
    }

    /// Read the latest conversion: `WouldBlock` while DOUT is high (nothing ready) or the
    /// part is powered down, without touching PD_SCK; otherwise the signed code.
    ///
    /// A disconnected part (DOUT held high by the pull-up) is `WouldBlock` for ever: the
    /// caller detects it by timing out (a sample is due every conversion period).
    pub fn read(&mut self) -> nb::Result<i32, Hx711Error<E>> {
        if self.powered_down || self.dout.is_high().map_err(Hx711Error::Pin)? {
            return Err(nb::Error::WouldBlock);
        }
        self.delay.delay_ns(T1_WAIT_NS);
        let mut raw: u32 = 0;
        for _ in 0..DATA_BITS {
            let bit = self.pulse()?;
            raw = (raw << 1) | u32::from(bit);
        }
        for _ in DATA_BITS..self.gain.pulses() {
            self.pulse()?;
        }
        Ok(sign_extend_24(raw))
    }

    /// One PD_SCK pulse; returns DOUT as sampled at the end of the high phase.
    ///
    /// The high phase runs with interrupts masked so that it cannot exceed
    /// T3 max / the 60 µs power-down threshold; PD_SCK is set low even on error.
    fn pulse(&mut self) -> Result<bool, Hx711Error<E>> {
        let (sck, dout, delay) = (&mut self.sck, &mut self.dout, &mut self.delay);
        let bit = critical_section::with(|_| {
            let bit = sck.set_high().and_then(|()| {
                delay.delay_ns(SCK_HIGH_NS);
                dout.is_high()
            });
            let low = sck.set_low();
            bit.and_then(|b| low.map(|()| b))
        })
        .map_err(Hx711Error::Pin)?;
        self.delay.delay_ns(SCK_LOW_NS);
        Ok(bit)
    }

    /// Power the part down: PD_SCK high, then wait [`POWER_DOWN_WAIT_US`] (> 60 µs).
    /// [`Self::read`] returns `WouldBlock` until [`Self::power_up`].
    pub fn power_down(&mut self) -> Result<(), Hx711Error<E>> {
        self.sck.set_high().map_err(Hx711Error::Pin)?;
        self.powered_down = true;
        self.delay.delay_us(POWER_DOWN_WAIT_US);
        Ok(())
    }

    /// Power up: PD_SCK low resets the part to A/128; the first sample is ready only
    /// after the settling time ([`settling_time_us`]). The next readout selects
    /// [`Self::gain`] again.
    pub fn power_up(&mut self) -> Result<(), Hx711Error<E>> {
        self.sck.set_low().map_err(Hx711Error::Pin)?;
        self.powered_down = false;
        Ok(())
    }

    /// Give back the pins and the delay.
    pub fn release(self) -> (DOUT, SCK, D) {
        (self.dout, self.sck, self.delay)
    }
}

/// Why a calibration could not be made.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum CalError {
    /// Tare of zero samples.
    NoSamples,
    /// Tare of more than [`Calibration::TARE_MAX_SAMPLES`] samples.
    TooManySamples,
    /// The two calibration points have the same code.
    EqualCodes,
    /// The two calibration points have the same force.
    EqualForces,
    /// The two codes are less than [`Calibration::MIN_SPAN_COUNTS`] apart.
    SpanTooSmall,
    /// More force gave fewer counts (or the sensitivity rounds to zero).
    NonPositiveSensitivity,
    /// The code at zero force, extrapolated from the two points, is not an `i32`.
    OffsetOutOfRange,
}

impl core::fmt::Display for CalError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::NoSamples => "tare needs at least one sample",
            Self::TooManySamples => "too many tare samples",
            Self::EqualCodes => "calibration points have equal codes",
            Self::EqualForces => "calibration points have equal forces",
            Self::SpanTooSmall => "calibration span below the minimum number of counts",
            Self::NonPositiveSensitivity => "calibration gives zero or negative sensitivity",
            Self::OffsetOutOfRange => "calibration offset out of range",
        })
    }
}

impl core::error::Error for CalError {}

/// Linear calibration of HX711 codes to force.
///
/// Format: force in mN = `((code − offset_counts) as i64 · mn_per_count_q32) >> 32`,
/// i.e. `mn_per_count_q32` is the sensitivity in mN per count in Q32.32 fixed point
/// (arithmetic shift, so the result is rounded toward −∞ and reads up to 1 mN low:
/// exactly −100 N on [`Calibration::SIM_DEFAULT`] gives −100 001 mN), saturated into
/// `i32`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Calibration {
    /// Code at zero force (the tare), counts.
    pub offset_counts: i32,
    /// Sensitivity, mN per count, Q32.32.
    pub mn_per_count_q32: i64,
}

impl Calibration {
    /// The simulator's cell (`hil_sim` default): offset 31 000 counts, 8 590 counts/N,
    /// so `mn_per_count_q32` = round(1000 / 8590 · 2³²) = 499 996 193.
    pub const SIM_DEFAULT: Self = Self {
        offset_counts: 31_000,
        mn_per_count_q32: 499_996_193,
    };

    /// Smallest code span between the two points of [`Self::from_two_points`], counts
    /// (below it one count of quantisation is > 0.1 % of the sensitivity).
    pub const MIN_SPAN_COUNTS: u32 = 1_000;

    /// Largest plausible tare magnitude, counts: 2²¹, a quarter of full scale (2²³).
    pub const TARE_LIMIT_COUNTS: i32 = 1 << 21;

    /// Most samples [`Self::tare`] averages (keeps the sum far inside `i64`).
    pub const TARE_MAX_SAMPLES: usize = 65_536;

    /// Force at `code`, mN (see the type's format); saturates, never overflows.
    pub fn to_force_mn(&self, code: i32) -> i32 {
        // |diff| < 2^32: cannot overflow.
        let diff = i64::from(code) - i64::from(self.offset_counts);
        match diff.checked_mul(self.mn_per_count_q32) {
            Some(p) => saturate_i32(p >> 32),
            // The exact product is beyond ±2^63, so its force is far beyond ±2^31 mN.
            None if (diff < 0) != (self.mn_per_count_q32 < 0) => i32::MIN,
            None => i32::MAX,
        }
    }

    /// Tare: the mean of `samples_counts` (codes at zero force), rounded to the nearest
    /// count (halves up). Check the result with [`Self::tare_plausible`].
    pub fn tare(samples_counts: &[i32]) -> Result<i32, CalError> {
        let n = samples_counts.len();
        if n == 0 {
            return Err(CalError::NoSamples);
        }
        if n > Self::TARE_MAX_SAMPLES {
            return Err(CalError::TooManySamples);
        }
        // ≤ 2^16 samples of magnitude ≤ 2^31: |sum| ≤ 2^47.
        let sum: i64 = samples_counts.iter().map(|&s| i64::from(s)).sum();
        let n = i64::try_from(n).map_err(|_| CalError::TooManySamples)?;
        // floor(sum/n + 1/2); lies between the smallest and largest sample.
        Ok(saturate_i32((2 * sum + n).div_euclid(2 * n)))
    }

    /// Whether a tare `offset_counts` is plausible: |offset| ≤ [`Self::TARE_LIMIT_COUNTS`].
    ///
    /// The tare is taken with the connector unloaded, so it is the bridge's zero
    /// balance only. Full scale is ±2²³ counts (±20 mV at gain 128 and 5 V); a
    /// 2 mV/V cell gives 10 mV, about half of full scale, at rated load, and a healthy
    /// cell's zero balance is a few % of its rated output. A quarter of full scale
    /// (2²¹ counts, ≈ 244 N on the simulator's cell) is therefore far outside it: it
    /// means a damaged or overloaded bridge, a broken bridge wire pulling the input
    /// toward a rail, or a load on the cell while taring — and it would also cost a
    /// quarter of the measuring range on one side. The controller reports it as a
    /// sensor fault instead of using it.
    pub const fn tare_plausible(offset_counts: i32) -> bool {
        offset_counts.unsigned_abs() <= Self::TARE_LIMIT_COUNTS.unsigned_abs()
    }

    /// Calibration through two points (code, force): sensitivity and zero offset, both
    /// rounded to nearest. Refuses equal codes or forces, a span under
    /// [`Self::MIN_SPAN_COUNTS`], and zero or negative sensitivity.
    pub fn from_two_points(
        code0_counts: i32,
        force0_mn: i32,
        code1_counts: i32,
        force1_mn: i32,
    ) -> Result<Self, CalError> {
        if code0_counts == code1_counts {
            return Err(CalError::EqualCodes);
        }
        if force0_mn == force1_mn {
            return Err(CalError::EqualForces);
        }
        // Differences of two i32 fit in i64 (|d| < 2^32).
        let dc = i64::from(code1_counts) - i64::from(code0_counts);
        let df = i64::from(force1_mn) - i64::from(force0_mn);
        if dc.unsigned_abs() < u64::from(Self::MIN_SPAN_COUNTS) {
            return Err(CalError::SpanTooSmall);
        }
        if (dc > 0) != (df > 0) {
            return Err(CalError::NonPositiveSensitivity);
        }
        // Same sign: work with magnitudes. i128 holds df·2^32 (< 2^64) exactly.
        let dc = i128::from(dc.unsigned_abs());
        let df = i128::from(df.unsigned_abs());
        let q = div_round(df << 32, dc);
        // q ≤ 2^64 / 1000 < 2^54: always an i64.
        let q = i64::try_from(q).unwrap_or(i64::MAX);
        if q <= 0 {
            return Err(CalError::NonPositiveSensitivity);
        }
        // Code at zero force: code0 − force0 / sensitivity = code0 − force0·dc/df.
        let offset = i128::from(code0_counts) - div_round(i128::from(force0_mn) * dc, df);
        let offset = i32::try_from(offset).map_err(|_| CalError::OffsetOutOfRange)?;
        Ok(Self {
            offset_counts: offset,
            mn_per_count_q32: q,
        })
    }

    /// The same sensitivity with a new zero offset (a fresh tare).
    pub const fn with_tare(self, offset_counts: i32) -> Self {
        Self {
            offset_counts,
            ..self
        }
    }
}

/// `num / den` rounded to nearest (halves up); `den` > 0, magnitudes < 2^96.
/// (`(2·num + den).div_euclid(2·den)`, through the one out-of-line 128-bit division.)
fn div_round(num: i128, den: i128) -> i128 {
    let (n, d) = (2 * num + den, 2 * den);
    let q = crate::fixed::div_u128(n.unsigned_abs(), d.unsigned_abs()) as i128;
    if n >= 0 {
        q
    } else if q * d == -n {
        -q
    } else {
        -q - 1 // floor
    }
}

fn saturate_i32(v: i64) -> i32 {
    i32::try_from(v).unwrap_or(if v < 0 { i32::MIN } else { i32::MAX })
}

/// The controller reads the load cell through [`LoadCellAdc`](crate::hal::LoadCellAdc);
/// a pin error is reported as `Other(())` (the controller latches an I/O fault).
impl<DOUT, SCK, D, E> crate::hal::LoadCellAdc for Hx711<DOUT, SCK, D>
where
    DOUT: InputPin<Error = E>,
    SCK: OutputPin<Error = E>,
    D: DelayNs,
{
    fn read_code(&mut self) -> nb::Result<i32, ()> {
        self.read().map_err(|e| e.map(|_| ()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn div_round_is_the_euclidean_rounding() {
        for num in [
            0i128,
            1,
            -1,
            2,
            -2,
            3,
            -3,
            5,
            -5,
            999,
            -1_000,
            1 << 63,
            -(1 << 90) + 17,
            (1 << 95) - 1,
        ] {
            for den in [1i128, 2, 3, 4, 7, 1_000, (1 << 40) + 9, 1 << 94] {
                assert_eq!(
                    div_round(num, den),
                    (2 * num + den).div_euclid(2 * den),
                    "{num} / {den}"
                );
            }
        }
    }

    #[test]
    fn sign_extension_at_both_ends_and_around_zero() {
        assert_eq!(sign_extend_24(0x7F_FFFF), 8_388_607);
        assert_eq!(sign_extend_24(0x7F_FFFF), CODE_MAX);
        assert_eq!(sign_extend_24(0x80_0000), -8_388_608);
        assert_eq!(sign_extend_24(0x80_0000), CODE_MIN);
        assert_eq!(sign_extend_24(0x7F_FFFE), CODE_MAX - 1);
        assert_eq!(sign_extend_24(0x80_0001), CODE_MIN + 1);
        assert_eq!(sign_extend_24(0), 0);
        assert_eq!(sign_extend_24(1), 1);
        assert_eq!(sign_extend_24(0xFF_FFFF), -1);
        assert_eq!(sign_extend_24(0xFF_FFFE), -2);
        // Bits above 23 are ignored.
        assert_eq!(sign_extend_24(0xFF00_0001), 1);
        assert_eq!(sign_extend_24(0x01FF_FFFF), -1);
        assert_eq!(CODE_MAX, (1 << 23) - 1);
        assert_eq!(CODE_MIN, -(1 << 23));
    }

    #[test]
    fn gain_pulses_and_settling() {
        assert_eq!(Gain::A128.pulses(), 25);
        assert_eq!(Gain::B32.pulses(), 26);
        assert_eq!(Gain::A64.pulses(), 27);
        assert_eq!(settling_time_us(10), 400_000);
        assert_eq!(settling_time_us(80), 50_000);
        assert_eq!(settling_time_us(0), 4_000_000);
        // The longest readout stays far from the 60 µs power-down.
        let longest_ns = T1_WAIT_NS + u32::from(Gain::A64.pulses()) * (SCK_HIGH_NS + SCK_LOW_NS);
        assert!(longest_ns < POWER_DOWN_NS);
    }

    #[test]
    fn sim_default_is_1000_over_8590_in_q32() {
        let q = ((1_000i64 << 32) + 8_590 / 2) / 8_590;
        assert_eq!(Calibration::SIM_DEFAULT.mn_per_count_q32, q);
        let c = Calibration::SIM_DEFAULT;
        assert_eq!(c.to_force_mn(31_000), 0);
        assert_eq!(c.to_force_mn(31_000 + 8_590), 1_000);
        assert_eq!(c.to_force_mn(31_000 + 859_000), 100_000);
        // Floor (>> 32) of a product 0.22 LSB above the exact value: −100 N reads 1 mN low.
        assert_eq!(c.to_force_mn(31_000 - 859_000), -100_001);
    }

    #[test]
    fn to_force_never_overflows() {
        let cals = [
            Calibration::SIM_DEFAULT,
            Calibration {
                offset_counts: i32::MIN,
                mn_per_count_q32: i64::MAX,
            },
            Calibration {
                offset_counts: i32::MAX,
                mn_per_count_q32: i64::MIN,
            },
            Calibration {
                offset_counts: 0,
                mn_per_count_q32: -1,
            },
        ];
        for c in cals {
            for code in [i32::MIN, -1, 0, 1, i32::MAX, CODE_MIN, CODE_MAX] {
                let _ = c.to_force_mn(code);
            }
        }
        let big = Calibration {
            offset_counts: 0,
            mn_per_count_q32: i64::MAX,
        };
        assert_eq!(big.to_force_mn(i32::MAX), i32::MAX);
        assert_eq!(big.to_force_mn(i32::MIN), i32::MIN);
        assert_eq!(big.to_force_mn(0), 0);
        let neg = Calibration {
            offset_counts: 0,
            mn_per_count_q32: i64::MIN,
        };
        assert_eq!(neg.to_force_mn(i32::MAX), i32::MIN);
        assert_eq!(neg.to_force_mn(i32::MIN), i32::MAX);
        // Saturation after the shift, without i64 overflow.
        let one = Calibration {
            offset_counts: i32::MIN,
            mn_per_count_q32: 1 << 32,
        };
        assert_eq!(one.to_force_mn(i32::MAX), i32::MAX);
        assert_eq!(one.to_force_mn(i32::MIN), 0);
        // Floor semantics of the stated format.
        let half = Calibration {
            offset_counts: 0,
            mn_per_count_q32: 1 << 31,
        };
        assert_eq!(half.to_force_mn(1), 0);
        assert_eq!(half.to_force_mn(-1), -1);
    }

    #[test]
    fn tare_is_the_rounded_mean() {
        assert_eq!(Calibration::tare(&[]), Err(CalError::NoSamples));
        assert_eq!(Calibration::tare(&[7]), Ok(7));
        assert_eq!(Calibration::tare(&[1, 2]), Ok(2));
        assert_eq!(Calibration::tare(&[-1, -2]), Ok(-1));
        assert_eq!(Calibration::tare(&[1, 2, 2]), Ok(2));
        assert_eq!(Calibration::tare(&[i32::MAX; 16]), Ok(i32::MAX));
        assert_eq!(Calibration::tare(&[i32::MIN; 16]), Ok(i32::MIN));
        assert_eq!(Calibration::tare(&[i32::MIN, i32::MAX]), Ok(0));
        let many = [0i32; Calibration::TARE_MAX_SAMPLES + 1];
        assert_eq!(Calibration::tare(&many), Err(CalError::TooManySamples));
        assert_eq!(
            Calibration::tare(&many[..Calibration::TARE_MAX_SAMPLES]),
            Ok(0)
        );
    }

    #[test]
    fn tare_plausibility_limit() {
        assert!(Calibration::tare_plausible(0));
        assert!(Calibration::tare_plausible(31_000));
        assert!(Calibration::tare_plausible(1 << 21));
        assert!(Calibration::tare_plausible(-(1 << 21)));
        assert!(!Calibration::tare_plausible((1 << 21) + 1));
        assert!(!Calibration::tare_plausible(-(1 << 21) - 1));
        assert!(!Calibration::tare_plausible(CODE_MAX));
        assert!(!Calibration::tare_plausible(CODE_MIN));
        assert!(!Calibration::tare_plausible(i32::MIN));
    }

    #[test]
    fn two_points_reproduce_the_sim_cell() {
        let c = Calibration::from_two_points(31_000, 0, 31_000 + 1_718_000, 200_000).unwrap();
        assert_eq!(c, Calibration::SIM_DEFAULT);
        // Order of the points does not matter; a point away from zero gives the offset.
        let c2 =
            Calibration::from_two_points(31_000 + 1_718_000, 200_000, 31_000 - 859_000, -100_000)
                .unwrap();
        assert_eq!(c2, Calibration::SIM_DEFAULT);
        assert_eq!(c.with_tare(-5).offset_counts, -5);
        assert_eq!(c.with_tare(-5).mn_per_count_q32, c.mn_per_count_q32);
    }

    #[test]
    fn two_points_refusals() {
        use CalError::*;
        let f = Calibration::from_two_points;
        assert_eq!(f(100, 0, 100, 5), Err(EqualCodes));
        assert_eq!(f(0, 5, 10_000, 5), Err(EqualForces));
        assert_eq!(f(0, 0, 999, 1_000), Err(SpanTooSmall));
        assert_eq!(f(0, 0, -999, 1_000), Err(SpanTooSmall));
        assert!(f(0, 0, 1_000, 1_000).is_ok());
        assert_eq!(f(0, 0, 10_000, -1_000), Err(NonPositiveSensitivity));
        assert_eq!(f(10_000, 0, 0, 1_000), Err(NonPositiveSensitivity));
        // Extremes: no overflow, offset extrapolated beyond i32 is refused.
        assert!(f(i32::MIN, i32::MIN, i32::MAX, i32::MAX).is_ok());
        assert_eq!(
            f(0, i32::MAX, 1_000, i32::MAX - 1),
            Err(NonPositiveSensitivity)
        );
        assert_eq!(f(0, i32::MIN, 1_000, i32::MIN + 1), Err(OffsetOutOfRange));
        let c = f(i32::MIN, i32::MIN, i32::MAX, i32::MAX).unwrap();
        assert_eq!(c.mn_per_count_q32, 1 << 32);
        assert_eq!(c.offset_counts, 0);
    }

    #[derive(Debug)]
    struct MockErr;

    #[test]
    fn errors_display() {
        extern crate std;
        use std::string::ToString;
        assert_eq!(
            Hx711Error::Pin(MockErr).to_string(),
            "HX711 pin error: MockErr"
        );
        assert_eq!(
            CalError::SpanTooSmall.to_string(),
            "calibration span below the minimum number of counts"
        );
    }
}
