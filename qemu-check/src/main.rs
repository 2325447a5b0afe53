//! Runs `docking_logic::odometer::reference_run` on a Cortex-M4 and prints its
//! result through semihosting; `.ci/run` compares it with the host's.
#![no_std]
#![no_main]

use cortex_m_rt::entry;
use cortex_m_semihosting::{debug, hprintln};

#[entry]
fn main() -> ! {
    let r = docking_logic::odometer::reference_run(300);
    hprintln!("{}", r);
    debug::exit(debug::EXIT_SUCCESS);
    loop {
        cortex_m::asm::wfi();
    }
}

#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    debug::exit(debug::EXIT_FAILURE);
    loop {
        cortex_m::asm::wfi();
    }
}
