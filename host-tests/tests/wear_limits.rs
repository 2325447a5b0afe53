//! The odometer's limits acting on the machine: a worn-out cone is refused, a cone past
//! the warning level warns on every cycle; and the watchdog is not fed by a late step.

use docking_logic::controller::Event;
use docking_logic::material::Material;
use docking_logic::odometer::{self, Cone, Lifetime, StateRecord, WearLevel, W_NOM_Q1};
use docking_logic::sequencer::{Request, State};
use hil_sim::flash::{SharedFlash, SimFlash};
use hil_sim::rig::{Rig, RigOptions};

/// A flash holding one cone with `nominal_cycles` of nominal wear.
fn flash_with_wear(nominal_cycles: u64) -> SharedFlash {
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    let (mut log, _) = docking_logic::odometer::open_log(flash.clone()).unwrap();
    let cone = Cone::new(1, Material::ZQSn5_2, "OLD-1", 0);
    log.append(odometer::kind::CONE, &odometer::cone_to_bytes(&cone))
        .unwrap();
    let rec = StateRecord {
        life: Lifetime {
            cycles: nominal_cycles as u32,
            w_q1: W_NOM_Q1 * nominal_cycles,
            ..Lifetime::default()
        },
        cone_id: 1,
        material: Material::ZQSn5_2,
        cone_cycles: nominal_cycles as u32,
        cone_w_q1: W_NOM_Q1 * nominal_cycles,
        last_cycle_q1: W_NOM_Q1,
        cycle_end: true,
    };
    log.append(odometer::kind::STATE, &rec.to_bytes()).unwrap();
    flash
}

fn boot(flash: &SharedFlash) -> Rig {
    let mut r = Rig::with_flash(RigOptions::new(80), flash.clone());
    for _ in 0..50 {
        r.tick();
    }
    assert_eq!(r.ctrl.state(), State::Idle);
    r
}

#[test]
fn a_worn_out_cone_is_refused_until_replaced() {
    let flash = flash_with_wear(45_300);
    let mut r = boot(&flash);
    assert_eq!(r.ctrl.odometer().level(), WearLevel::Limit);
    let mut refused = 0;
    for _ in 0..400 {
        if r.ctrl.state() == State::Idle {
            r.ctrl.request(Request::StartCycle);
        }
        r.tick();
        while let Some(e) = r.ctrl.next_event() {
            if e.event == Event::WearLimitRefusal {
                refused += 1;
            }
        }
        assert_eq!(
            r.ctrl.state(),
            State::Idle,
            "nothing moves with a worn-out cone"
        );
    }
    assert!(refused > 10, "{refused}");
    assert!(!r.axis.enabled());
    // The technician replaces the cone: docking resumes; lifetime totals stay.
    r.ctrl.replace_cone(Material::QSn6_6_3, "NEW-2").unwrap();
    r.ctrl.request(Request::StartCycle);
    for _ in 0..100 {
        r.tick();
    }
    assert!(
        matches!(
            r.ctrl.state(),
            State::PreAlign { .. } | State::Releasing { .. } | State::Inserting { .. }
        ),
        "{:?}",
        r.ctrl.state()
    );
    assert_eq!(r.ctrl.odometer().lifetime().cycles, 45_300);
    assert_eq!(r.ctrl.odometer().cone().cycles, 0);
}

#[test]
fn past_the_warning_level_every_cycle_warns() {
    // 80 % of 0.8 mm is reached at about 29 560 nominal cycles.
    let flash = flash_with_wear(29_700);
    let mut r = boot(&flash);
    assert_eq!(r.ctrl.odometer().level(), WearLevel::Warning);
    let mut warned = 0;
    let mut done = 0;
    for _ in 0..20_000 {
        if r.ctrl.state() == State::Idle && !r.ctrl.persist_pending() {
            if done == 2 {
                break;
            }
            r.ctrl.request(Request::StartCycle);
        }
        r.tick();
        while let Some(e) = r.ctrl.next_event() {
            if let Event::CycleCounted(c) = e.event {
                done += 1;
                if c.level == WearLevel::Warning {
                    warned += 1;
                }
            }
        }
    }
    assert_eq!((done, warned), (2, 2));
}

#[test]
fn a_stalled_loop_does_not_feed_the_watchdog() {
    let mut r = Rig::new(RigOptions::new(80));
    for _ in 0..200 {
        r.tick();
    }
    assert!(!r.wdg.check(), "a healthy loop keeps it fed");
    let feeds = r.wdg.feeds();
    // The loop hangs for 600 ms (longer than the 500 ms watchdog), then steps again.
    r.clock.advance_ns(600_000_000);
    r.tick();
    assert_eq!(r.wdg.feeds(), feeds, "a step after a stall must not feed");
    assert!(r.wdg.check(), "the watchdog bites");
}
