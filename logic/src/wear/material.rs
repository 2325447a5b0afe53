//! Guide-cone materials (`docs/physics.md` §5). Each has its own calibrated wear coefficient,
//! expressed relative to the ZQSn5-2 baseline whose Km = 3.3e-5 the paper measured;
//! hardness alone under-predicts the difference (HV 213.77 vs 242.8 gives 0.88, the
//! measured wear ratio of QSn6-6-3 is 0.5701).

/// Cone material.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum Material {
    /// ZQSn5-2 tin bronze, the baseline (Km = 3.3e-5, HV 213.77).
    ZQSn5_2 = 0,
    /// QSn6-6-3 tin bronze: 0.5701× the baseline's wear (measured, prototype test).
    QSn6_6_3 = 1,
    /// Carbon-fibre PEEK composite: ≈ 0.5× (the paper's projection: 90,540 cycles).
    CfPeek = 2,
}

impl Material {
    /// Every material, in code order.
    pub const ALL: [Self; 3] = [Self::ZQSn5_2, Self::QSn6_6_3, Self::CfPeek];

    /// The name used on the console and in JSON (`zqsn5-2`, `qsn6-6-3`, `cf-peek`).
    pub const fn name(self) -> &'static str {
        match self {
            Self::ZQSn5_2 => "zqsn5-2",
            Self::QSn6_6_3 => "qsn6-6-3",
            Self::CfPeek => "cf-peek",
        }
    }

    /// Parse a console/CLI name, case-insensitively.
    pub fn from_name(s: &str) -> Option<Self> {
        Self::ALL
            .into_iter()
            .find(|m| m.name().eq_ignore_ascii_case(s))
    }

    /// The persisted code.
    pub const fn code(self) -> u8 {
        self as u8
    }

    /// From a persisted code.
    pub const fn from_code(c: u8) -> Option<Self> {
        match c {
            0 => Some(Self::ZQSn5_2),
            1 => Some(Self::QSn6_6_3),
            2 => Some(Self::CfPeek),
            _ => None,
        }
    }
}
