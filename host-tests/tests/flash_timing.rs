//! The rig is as honest as the board about the flash: an operation costs its datasheet
//! time in virtual time, and the watchdog sees it (the virtual board found the reset
//! loop a sector erase caused; the rig's flash used to erase in zero time).

use docking_logic::sequencer::State;
use hil_sim::flash::{fill_log_to_maintenance, SharedFlash, SimFlash};
use hil_sim::rig::{Rig, RigOptions, ERASE_FEED_LIMIT_NS};

fn erases(flash: &SharedFlash) -> u32 {
    flash.with(|f| f.erase_counts().iter().sum())
}

/// Boot on a log at its maintenance mark with sector erases of `erase_ns`; returns
/// (virtual time the erase step took, watchdog bitten).
fn boot_and_erase(erase_ns: u64) -> (u64, bool) {
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    fill_log_to_maintenance(&flash).unwrap();
    let mut r = Rig::with_flash(RigOptions::new(80), flash.clone());
    r.ctrl.log_mut().unwrap().flash_mut().times.erase_ns = erase_ns;
    let before = erases(&flash);
    for _ in 0..1_000 {
        let t0 = r.clock.now_ns();
        r.tick();
        if erases(&flash) > before {
            assert_eq!(r.ctrl.state(), State::Idle, "erased only at rest");
            return (r.clock.now_ns() - t0, r.wdg.check());
        }
    }
    panic!("no erase happened");
}

#[test]
fn a_sector_erase_takes_its_datasheet_time_and_the_watchdog_sees_it() {
    // The board's driver: 2 s at ×32 (maximum), the watchdog fed from SRAM meanwhile.
    let (took, bitten) = boot_and_erase(2_000_000_000);
    assert!(
        took >= 2_000_000_000,
        "the erase took {took} ns of virtual time"
    );
    assert!(!bitten, "fed through a 2 s erase");
    // An erase outlasting the board's feeding limit (the HAL's ×8: up to 4 s) resets.
    let (took, bitten) = boot_and_erase(4_000_000_000);
    assert!(took >= 4_000_000_000 && 4_000_000_000 > ERASE_FEED_LIMIT_NS);
    assert!(bitten, "a 4 s erase starves the watchdog");
}
