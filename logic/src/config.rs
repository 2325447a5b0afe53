//! Machine configuration: geometry, speeds, deadlines. Integer units only.
//!
//! Axis coordinates are µm from the home switch, positive toward the male panel:
//!
//! ```text
//!  home 0 ──pre-alignment (locked, fast)──▶ engage_um ──compliant (released, ≤ v0)──▶ mated_um ─▶ end switch
//!           ◀────────── return (locked, fast) ───────────  ◀──────── extraction (released, ≤ v0) ──
//! ```
//!
//! `engage_um` is where the guide rod sits on the cone's conical surface: compliant
//! contact (depth 0 of the force profile) starts there and the mated position is
//! `engage_um + STROKE_UM`.

use crate::profile::{STROKE_UM, V0_UM_PER_S};

/// Why a configuration is refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[non_exhaustive]
pub enum ConfigError {
    /// Docking speed zero or above v0 = 1.2 mm/s (the force model holds only to v0).
    DockSpeedOutOfRange,
    /// Fast (non-contact) speed zero or above the axis limit.
    FastSpeedOutOfRange,
    /// Acceleration zero or above the axis limit.
    AccelOutOfRange,
    /// Steps per mm zero or above 10 000.
    StepsPerMmOutOfRange,
    /// Engagement point not inside the travel, or mated position past the end switch.
    GeometryInvalid,
    /// A deadline or hold time of zero.
    TimeInvalid,
}

impl core::fmt::Display for ConfigError {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(match self {
            Self::DockSpeedOutOfRange => "docking speed must be 1..=1200 um/s",
            Self::FastSpeedOutOfRange => "fast speed must be 1..=20000 um/s",
            Self::AccelOutOfRange => "acceleration must be 1..=200000 um/s^2",
            Self::StepsPerMmOutOfRange => "steps per mm must be 1..=10000",
            Self::GeometryInvalid => "engage/mated positions must lie inside the travel",
            Self::TimeInvalid => "deadlines and hold time must be non-zero",
        })
    }
}

/// Highest fast-travel speed the axis accepts, µm/s.
pub const FAST_SPEED_MAX_UM_PER_S: u32 = 20_000;
/// Highest acceleration the axis accepts, µm/s².
pub const ACCEL_MAX_UM_PER_S2: u32 = 200_000;

/// Geometry, speeds and timings of the docking machine.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MachineConfig {
    /// Propulsion steps per millimetre of panel travel (lead screw × microstepping).
    pub steps_per_mm: u32,
    /// Speed in compliant contact (insertion and extraction), µm/s; ≤ v0.
    pub dock_speed_um_per_s: u32,
    /// Speed outside contact (pre-alignment, return, homing), µm/s.
    pub fast_speed_um_per_s: u32,
    /// Acceleration ramp of the propulsion, µm/s².
    pub accel_um_per_s2: u32,
    /// Engagement point (start of compliant contact), µm from home.
    pub engage_um: i32,
    /// Overtravel (end) switch position, µm from home; must lie beyond mated.
    pub end_switch_um: i32,
    /// Hold time at the mated position, ms.
    pub hold_ms: u32,
    /// Deadline for the lock actuator to reach either switch, ms.
    pub lock_deadline_ms: u32,
    /// Deadline for the homing search (axis to the home switch), ms.
    pub homing_deadline_ms: u32,
    /// Slack added to every computed move deadline, ms.
    pub move_slack_ms: u32,
}

impl MachineConfig {
    /// The defaults used on the board and in the simulator.
    pub const DEFAULT: Self = match Self::new(Self {
        steps_per_mm: 200,
        dock_speed_um_per_s: V0_UM_PER_S,
        fast_speed_um_per_s: 10_000,
        accel_um_per_s2: 20_000,
        engage_um: 20_000,
        end_switch_um: 52_000,
        hold_ms: 1_000,
        lock_deadline_ms: 2_000,
        homing_deadline_ms: 15_000,
        move_slack_ms: 1_500,
    }) {
        Ok(c) => c,
        Err(_) => panic!("default machine configuration is invalid"),
    };

    /// Validate a configuration (a `const fn`, so a bad constant fails the build).
    pub const fn new(c: Self) -> Result<Self, ConfigError> {
        if c.dock_speed_um_per_s == 0 || c.dock_speed_um_per_s > V0_UM_PER_S {
            return Err(ConfigError::DockSpeedOutOfRange);
        }
        if c.fast_speed_um_per_s == 0 || c.fast_speed_um_per_s > FAST_SPEED_MAX_UM_PER_S {
            return Err(ConfigError::FastSpeedOutOfRange);
        }
        if c.accel_um_per_s2 == 0 || c.accel_um_per_s2 > ACCEL_MAX_UM_PER_S2 {
            return Err(ConfigError::AccelOutOfRange);
        }
        if c.steps_per_mm == 0 || c.steps_per_mm > 10_000 {
            return Err(ConfigError::StepsPerMmOutOfRange);
        }
        if c.engage_um < 1_000
            || c.engage_um > 500_000
            || c.end_switch_um <= c.engage_um + STROKE_UM
        {
            return Err(ConfigError::GeometryInvalid);
        }
        if c.hold_ms == 0 || c.lock_deadline_ms == 0 || c.homing_deadline_ms == 0 {
            return Err(ConfigError::TimeInvalid);
        }
        Ok(c)
    }

    /// Mated position, µm from home.
    pub const fn mated_um(&self) -> i32 {
        self.engage_um + STROKE_UM
    }

    /// Axis position in µm for a step count (truncating toward zero).
    pub const fn steps_to_um(&self, steps: i32) -> i32 {
        ((steps as i64 * 1000) / self.steps_per_mm as i64) as i32
    }

    /// Step count for a position in µm (rounded to nearest).
    pub const fn um_to_steps(&self, um: i32) -> i32 {
        let num = um as i64 * self.steps_per_mm as i64;
        let q = if num >= 0 {
            (num + 500) / 1000
        } else {
            (num - 500) / 1000
        };
        q as i32
    }

    /// Step rate for a speed in µm/s (at least 1 step/s for a non-zero speed).
    pub const fn speed_to_step_hz(&self, um_per_s: u32) -> u32 {
        let hz = (um_per_s as u64 * self.steps_per_mm as u64) / 1000;
        if hz == 0 && um_per_s > 0 {
            1
        } else {
            hz as u32
        }
    }
}

impl Default for MachineConfig {
    fn default() -> Self {
        Self::DEFAULT
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_are_valid_and_consistent() {
        let c = MachineConfig::DEFAULT;
        assert_eq!(c.mated_um(), 50_000);
        assert_eq!(c.um_to_steps(1_200), 240);
        assert_eq!(c.steps_to_um(240), 1_200);
        assert_eq!(c.speed_to_step_hz(1_200), 240);
    }

    #[test]
    fn dock_speed_above_v0_is_refused() {
        let c = MachineConfig {
            dock_speed_um_per_s: 1_201,
            ..MachineConfig::DEFAULT
        };
        assert_eq!(MachineConfig::new(c), Err(ConfigError::DockSpeedOutOfRange));
        let c = MachineConfig {
            dock_speed_um_per_s: 0,
            ..MachineConfig::DEFAULT
        };
        assert_eq!(MachineConfig::new(c), Err(ConfigError::DockSpeedOutOfRange));
    }

    #[test]
    fn geometry_must_fit() {
        let c = MachineConfig {
            end_switch_um: 50_000,
            ..MachineConfig::DEFAULT
        };
        assert_eq!(MachineConfig::new(c), Err(ConfigError::GeometryInvalid));
    }
}
