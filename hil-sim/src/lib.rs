//! # hil-sim — the simulated HAL of the docking controller
//!
//! Host-side devices that behave like their datasheets, faults included, in virtual
//! time, so that `cargo test` exercises the real control code of `docking-logic`:
//!
//! * [`hx711`]: the HX711 24-bit load-cell ADC at pin level, whose force is the Eq. 7
//!   contact profile at the simulated axis position;
//! * [`axis`]: the step/dir propulsion axis with home and end switches;
//! * [`lock`]: the adaptive-lock actuator with locked/released switches;
//! * [`flash`]: NOR flash with STM32F4 semantics and power-cut injection;
//! * [`line`]: a digital line driven from outside (dock request, PLC signals);
//! * [`clock`]: virtual time (nothing sleeps).
//!
//! [`rig::Machine`] is all of them on one clock, without a controller: the host rig
//! wires it to the library's controller, the virtual board (`vboard/`) to the pins of
//! the emulated STM32F407 running the firmware image. One model of each device.
//!
//! [`cli`] is the `hil-sim` command line.

/// An input line of a simulated device as its own type (a role fixed by the type, so
/// the controller's read compiles to the check itself): `input_line!(Type, |dev| high)`
/// implements embedded-hal's `InputPin` for `Type(Dev)` with `is_high` = `high`.
macro_rules! input_line {
    ($t:ty, |$d:ident| $high:expr) => {
        impl embedded_hal::digital::ErrorType for $t {
            type Error = core::convert::Infallible;
        }

        impl embedded_hal::digital::InputPin for $t {
            #[inline]
            fn is_high(&mut self) -> Result<bool, Self::Error> {
                let $d = &self.0;
                Ok($high)
            }
            #[inline]
            fn is_low(&mut self) -> Result<bool, Self::Error> {
                self.is_high().map(|h| !h)
            }
        }
    };
}

pub mod accuracy;
pub mod axis;
pub mod cli;
pub mod clock;
pub mod console;
pub mod curvedump;
pub mod early_life;
pub mod flash;
pub mod hx711;
pub mod life;
pub mod line;
pub mod link;
pub mod lock;
pub mod machine;
pub mod plant;
pub mod plot;
pub mod previous_estimate;
pub mod profile_cmd;
pub mod rig;
pub mod rng;
pub mod rtu_line;
pub mod scene;
pub mod serve;
pub mod sigscene;
pub mod sigstudy;
pub mod update;
