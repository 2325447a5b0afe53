//! The docking signature's scenes (issue 34): what each does to the machine, which
//! verdicts it must produce, and the `signatures` list of a scene's report.
//!
//! | scene | what happens | expected |
//! |---|---|---|
//! | `late-entry` | a lateral misalignment in the last cycle: the rod meets the cone [`LATE_ENTRY_UM`] after the engagement point (the whole profile that much deeper) | that docking NOK, its first object `entry` |
//! | `dry-guide` | the rod–cone pair runs dry (µ2 0.25, the plant) for the last [`DRY_GUIDE_CYCLES`] cycles | each of them NOK, first object `plateau` |
//! | `debris` | a force bump in phase 3 of the last insertion: +30 N over 10.5–11.5 mm | that insertion NOK, `band3`; its extraction OK |
//! | `catch` | a catch on the last extraction: +40 N over 21.5–22.5 mm | that extraction NOK, `ext_band4`; its insertion OK |
//!
//! In every scene the dockings not disturbed are OK, and no NOK stops the machine (no
//! fault; every cycle completes). `nominal` and `spike` (the load cell's noise, and
//! +350 N single-sample spikes) must judge every stroke OK.

use std::rc::Rc;

use docking_logic::config::MachineConfig;
use docking_logic::controller::Event;
use docking_logic::profile::STROKE_UM;

use crate::machine::ForceModel;
use crate::plant::PlantParams;
use crate::rig::{Bump, ForceScript};

/// The signature's scenes.
pub const SCENES: [&str; 4] = ["late-entry", "dry-guide", "debris", "catch"];

/// How much later the rod meets the cone in `late-entry`, µm.
pub const LATE_ENTRY_UM: f64 = 2_000.0;
/// µ2 of the dry guide.
pub const DRY_MU2: f64 = 0.25;
/// Cycles the guide runs dry, at the end of the scene.
pub const DRY_GUIDE_CYCLES: u32 = 3;
/// `debris`: the bump on the insertion.
pub const DEBRIS: Bump = Bump {
    from_um: 10_500.0,
    to_um: 11_500.0,
    add_n: 30.0,
    forward: true,
};
/// `catch`: the bump on the extraction.
pub const CATCH: Bump = Bump {
    from_um: 21_500.0,
    to_um: 22_500.0,
    add_n: 40.0,
    forward: false,
};

/// One stroke's verdict as a scene saw it.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct SignatureSeen {
    /// Lifetime cycle of the docking.
    pub cycle: u32,
    /// `insertion` or `extraction`.
    pub stroke: &'static str,
    /// OK.
    pub ok: bool,
    /// The first object failed.
    pub failed: Option<&'static str>,
}

impl SignatureSeen {
    /// From the controller's event.
    pub fn of_event(ev: &Event) -> Option<Self> {
        match ev {
            Event::Signature(v) => Some(Self {
                cycle: v.cycle,
                stroke: v.stroke.name(),
                ok: v.failure.is_none(),
                failed: v.failure.map(|f| f.object.name()),
            }),
            _ => None,
        }
    }

    /// `{"cycle":…,"stroke":…,"verdict":"ok"|"nok","failed":…}`.
    pub fn to_json(&self) -> String {
        format!(
            "{{\"cycle\":{},\"stroke\":\"{}\",\"verdict\":\"{}\",\"failed\":{}}}",
            self.cycle,
            self.stroke,
            if self.ok { "ok" } else { "nok" },
            self.failed
                .map_or("null".to_string(), |f| format!("\"{f}\""))
        )
    }
}

/// The N3 table of the dry guide, per step of insertion depth of `machine` (the
/// rig's profile's form).
pub fn dry_profile(machine: &MachineConfig) -> Rc<Vec<f64>> {
    let model = ForceModel::plant(PlantParams {
        mu2: DRY_MU2,
        ..PlantParams::PAPER
    });
    let um_per_step = 1000.0 / f64::from(machine.steps_per_mm);
    let table = match model {
        Ok(m) => (0..=machine.um_to_steps(STROKE_UM))
            .map(|k| m.n3_at_depth_um(f64::from(k) * um_per_step))
            .collect(),
        Err(_) => Vec::new(),
    };
    Rc::new(table)
}

/// Set scene `name`'s disturbance in `s` (before the cycle it disturbs starts).
pub fn disturb(name: &str, s: &mut ForceScript) {
    match name {
        "late-entry" => s.entry_delay_um = LATE_ENTRY_UM,
        "dry-guide" => s.profile_n = Some(dry_profile(&MachineConfig::DEFAULT)),
        "debris" => s.bump = Some(DEBRIS),
        "catch" => s.bump = Some(CATCH),
        _ => {}
    }
}

/// The cycles of a run of `cycles` the scene disturbs (1-based, inclusive).
pub fn disturbed(name: &str, cycles: u32) -> std::ops::RangeInclusive<u32> {
    let last = cycles.max(1);
    match name {
        "dry-guide" => last.saturating_sub(DRY_GUIDE_CYCLES - 1).max(1)..=last,
        _ => last..=last,
    }
}

/// What scene `name` must judge in cycle `k` (of `cycles`): per stroke, `None` OK or
/// the first object that fails; for the docking, the object its first NOK stroke
/// fails.
pub fn expected(name: &str, k: u32, cycles: u32) -> (Option<&'static str>, Option<&'static str>) {
    if !disturbed(name, cycles).contains(&k) {
        return (None, None);
    }
    match name {
        "late-entry" => (Some("entry"), None),
        "dry-guide" => (Some("plateau"), None),
        "debris" => (Some("band3"), None),
        "catch" => (None, Some("ext_band4")),
        _ => (None, None),
    }
}

/// The checks on a run's `signatures` (`first_cycle`: the lifetime cycle of the run's
/// first docking): every docking judged on both strokes; the insertion's verdict as
/// expected; the extraction's as expected where the scene disturbs it on purpose (a
/// misalignment or a dry guide also moves the extraction's curve: its verdict there is
/// not the scene's point), OK elsewhere.
pub fn check(
    name: &str,
    sigs: &[SignatureSeen],
    cycles: u32,
    first_cycle: u32,
    check: &mut dyn FnMut(bool, String),
) {
    let judged = ["nominal", "spike"].contains(&name) || SCENES.contains(&name);
    if !judged {
        return;
    }
    let mut missing = Vec::new();
    let mut wrong = Vec::new();
    for k in 1..=cycles {
        let cycle = first_cycle + k - 1;
        let (ins, ext) = expected(name, k, cycles);
        let disturbed = disturbed(name, cycles).contains(&k) && SCENES.contains(&name);
        for (stroke, want) in [("insertion", ins), ("extraction", ext)] {
            let Some(seen) = sigs.iter().find(|s| s.cycle == cycle && s.stroke == stroke) else {
                missing.push(format!("{cycle} {stroke}"));
                continue;
            };
            let free = stroke == "extraction" && disturbed && ext.is_none() && ins.is_some();
            if !free && seen.failed != want {
                wrong.push(format!(
                    "{cycle} {stroke}: {} (expected {})",
                    seen.failed.unwrap_or("ok"),
                    want.unwrap_or("ok")
                ));
            }
        }
    }
    check(
        missing.is_empty(),
        if missing.is_empty() {
            "every stroke judged".into()
        } else {
            format!("every stroke judged (missing: {})", missing.join(", "))
        },
    );
    let what = match name {
        "nominal" | "spike" => "every stroke OK".to_string(),
        _ => format!(
            "cycles {:?} NOK with the right object, the others OK",
            disturbed(name, cycles)
        ),
    };
    check(
        wrong.is_empty(),
        if wrong.is_empty() {
            what
        } else {
            format!("{what} (got {})", wrong.join("; "))
        },
    );
}
