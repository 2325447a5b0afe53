//! The simulated devices working together: the load cell sees the force of the axis
//! **position**, not of wall time.

use docking_logic::config::MachineConfig;
use docking_logic::hal::StepPulses;
use docking_logic::profile::forces_at_depth_um;
use embedded_hal::digital::OutputPin;
use hil_sim::axis::SimAxis;
use hil_sim::clock::SimClock;
use hil_sim::hx711::{Hx711Config, SimHx711};

#[test]
fn load_cell_force_follows_the_axis_position() {
    let cfg = MachineConfig::DEFAULT;
    let clk = SimClock::new();
    let axis = SimAxis::new(cfg, clk.clone(), cfg.engage_um);
    let a2 = axis.clone();
    let engage = cfg.engage_um as f64;
    let hx_cfg = Hx711Config {
        noise_counts: 0.0,
        ..Hx711Config::default_for_rate(80)
    };
    let hx = SimHx711::new(
        hx_cfg,
        clk.clone(),
        move |_t| forces_at_depth_um(a2.pos_um() - engage).n3_n,
        3,
    );
    let (mut p, mut en, mut dir) = (axis.pulses(), axis.enable_n(), axis.dir());
    dir.set_high().unwrap();
    en.set_low().unwrap();

    // Half speed: after 25 s the panel is only at depth 15 mm (phase 4 just begun), so the
    // force must be the force of depth 15 mm, not of t = 25 s.
    p.set_rate_hz(cfg.speed_to_step_hz(600));
    clk.advance_ns(25_000_000_000);
    p.set_rate_hz(0);
    let depth = axis.pos_um() - engage;
    assert_eq!(depth, 15_000.0);
    clk.advance_to_ns(hx.next_conversion_ns());
    let code = hx.read_word().unwrap();
    let f = (code as f64 - hx_cfg.offset_counts) / hx_cfg.counts_per_n;
    let expect = forces_at_depth_um(depth).n3_n;
    assert!((f - expect).abs() < 0.01, "{f} vs {expect}");
    assert!((f - forces_at_depth_um(30_000.0).n3_n).abs() > 50.0);
}
