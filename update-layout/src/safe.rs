//! The motor and PLC outputs' safe levels, as the registers take them: one copy for the
//! bootloader's `__pre_init`, the application's `__pre_init` and its panic and fault
//! handlers' `force_safe_outputs` (issue 31: they were three copies of the same
//! stores).
//!
//! ```text
//!  pin    what                     safe level   register writes (levels first, then modes)
//!  PE11   propulsion EN (active low)  high      GPIOE BSRR: set 11
//!  PE9    propulsion STEP             low       GPIOE BSRR: reset 9
//!  PD12   lock bridge IN1             low       GPIOD BSRR: reset 12
//!  PD13   lock bridge IN2             low       GPIOD BSRR: reset 13
//!  PD0-3  READY, MATED, FAULT, MAINT. low       GPIOD BSRR: reset 0-3
//!  all of them push-pull outputs (MODER 01), after the levels: a pin never drives the
//!  wrong level on its way to being an output
//! ```
//!
//! GPIOD's and GPIOE's clocks are turned on first (RCC AHB1ENR), and a `dsb` separates
//! that from the first store to them (RM0090 §6.3.11: a write right after the clock
//! enable can be lost).

/// RCC AHB1ENR.
pub const RCC_AHB1ENR: u32 = 0x4002_3830;
/// AHB1ENR's GPIODEN and GPIOEEN.
pub const GPIOD_E_CLOCKS: u32 = (1 << 3) | (1 << 4);
/// GPIOD's base address.
pub const GPIOD: u32 = 0x4002_0C00;
/// GPIOE's base address.
pub const GPIOE: u32 = 0x4002_1000;
/// MODER's offset.
pub const MODER: u32 = 0x00;
/// BSRR's offset.
pub const BSRR: u32 = 0x18;
/// GPIOE BSRR: EN (PE11) high, STEP (PE9) low.
pub const E_LEVELS: u32 = (1 << 11) | (1 << (9 + 16));
/// GPIOE MODER's bits for PE9 and PE11.
pub const E_MODE_MASK: u32 = (0b11 << 18) | (0b11 << 22);
/// ... as outputs.
pub const E_MODE_OUT: u32 = (0b01 << 18) | (0b01 << 22);
/// GPIOD BSRR: lock IN1/IN2 (PD12/13) and READY..MAINTENANCE (PD0-3) low.
pub const D_LEVELS: u32 = 0x300F << 16;
/// GPIOD MODER's bits for PD0-3, PD12 and PD13.
pub const D_MODE_MASK: u32 = (0b1111 << 24) | 0xFF;
/// ... as outputs.
pub const D_MODE_OUT: u32 = (0b0101 << 24) | 0x55;

/// `__pre_init` (cortex-m-rt's hook, run before RAM is initialised): the outputs safe as
/// its first instructions, then the caller's own assembly (`$tail`, ending in `bx lr`)
/// with its own operands. Assembly, because no Rust may run before RAM initialisation;
/// the values are this module's constants.
#[macro_export]
macro_rules! pre_init_safe_outputs {
    ($($tail:literal),* ; $($ops:tt)*) => {
        core::arch::global_asm!(
            ".section .text.__pre_init,\"ax\",%progbits",
            ".global __pre_init",
            ".type __pre_init,%function",
            ".thumb_func",
            "__pre_init:",
            // GPIOD/GPIOE clocks on; levels (BSRR) before modes.
            "    ldr r0, ={rcc_ahb1enr}",
            "    ldr r1, [r0]",
            "    orr r1, r1, #{clocks}",
            "    str r1, [r0]",
            "    dsb",
            "    ldr r0, ={gpioe}",
            "    ldr r1, ={e_levels}",
            "    str r1, [r0, #{bsrr}]",
            "    ldr r1, [r0, #{moder}]",
            "    ldr r2, ={e_mask}",
            "    bic r1, r1, r2",
            "    ldr r2, ={e_out}",
            "    orr r1, r1, r2",
            "    str r1, [r0, #{moder}]",
            "    ldr r0, ={gpiod}",
            "    ldr r1, ={d_levels}",
            "    str r1, [r0, #{bsrr}]",
            "    ldr r1, [r0, #{moder}]",
            "    ldr r2, ={d_mask}",
            "    bic r1, r1, r2",
            "    ldr r2, ={d_out}",
            "    orr r1, r1, r2",
            "    str r1, [r0, #{moder}]",
            $($tail,)*
            rcc_ahb1enr = const $crate::safe::RCC_AHB1ENR,
            clocks = const $crate::safe::GPIOD_E_CLOCKS,
            gpioe = const $crate::safe::GPIOE,
            gpiod = const $crate::safe::GPIOD,
            bsrr = const $crate::safe::BSRR,
            moder = const $crate::safe::MODER,
            e_levels = const $crate::safe::E_LEVELS,
            e_mask = const $crate::safe::E_MODE_MASK,
            e_out = const $crate::safe::E_MODE_OUT,
            d_levels = const $crate::safe::D_LEVELS,
            d_mask = const $crate::safe::D_MODE_MASK,
            d_out = const $crate::safe::D_MODE_OUT,
            $($ops)*
        );
    };
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_levels_and_modes_touch_only_the_motor_and_plc_pins() {
        // EN set, STEP reset; nothing else of GPIOE.
        assert_eq!(E_LEVELS, (1 << 11) | (1 << 25));
        // PD0-3, PD12, PD13 reset; nothing set.
        assert_eq!(D_LEVELS & 0xFFFF, 0);
        assert_eq!(D_LEVELS >> 16, 0b0011_0000_0000_1111);
        // Every mode bit written belongs to a pin whose level is set first, as output 01.
        for (mask, out, levels) in [
            (E_MODE_MASK, E_MODE_OUT, E_LEVELS),
            (D_MODE_MASK, D_MODE_OUT, D_LEVELS),
        ] {
            for pin in 0..16 {
                let m = (mask >> (2 * pin)) & 0b11;
                let o = (out >> (2 * pin)) & 0b11;
                let touched = levels & ((1 << pin) | (1 << (pin + 16))) != 0;
                assert_eq!(m != 0, touched, "pin {pin}");
                assert!(m == 0 || o == 0b01, "pin {pin}: an output");
            }
        }
    }
}
