//! # The docking signature
//!
//! Every docking's force against position, judged by contact phase, kept, and shown
//! (issue 34). A press-fit monitor's method on this machine's richer curve:
//!
//! 1. **Capture** ([`capture`]): each sample of the insertion and the extraction into
//!    its bin of a fixed position grid ([`grid`]: 128 bins over the 30 mm stroke): the
//!    bin's peak and mean force and its sample count, in fixed point, after a median
//!    filter that takes out single-sample spikes. Off the control step: the board's
//!    service task feeds it after each step.
//! 2. **Figures** ([`figures`]): the entry depth, the insertion work ∫F·dx, the phase-4
//!    plateau, the 3→4 step's position, the end force; the extraction's peak.
//! 3. **Evaluation objects** ([`objects`]): an entry window, a band per contact phase,
//!    the plateau, the end force at MATED, the extraction's bands and peak, placed on
//!    the design's force profile (Eq. 7, or another machine's plant). A stroke is OK,
//!    or NOK with the first object it failed and the figure that failed it.
//!
//! 4. **Monitor** ([`monitor`]): each cone's reference (the mean of its first OK
//!    dockings) and every later docking's drift from it; the summary, the NOK curves
//!    and the reference kept in flash ([`store`], [`records`]: sectors 2–4 through the
//!    power-cut-safe [`crate::framelog`]).
//!
//! 5. **Wear from the step** ([`stepwear`]): the 3→4 step's depth against the
//!    reference's, over the bore's geometry, as a wear estimate with its 95 % band,
//!    shown beside the micrometer's reading and the odometer's model (never in their
//!    place).
//!
//! A NOK stops nothing (only the overload guard does): the verdict is for the people
//! who maintain the machine and for the PLC.

pub mod capture;
pub mod figures;
pub mod grid;
pub mod monitor;
pub mod objects;
pub mod records;
pub mod stepwear;
pub mod store;
pub mod view;

/// The signature as the controller holds it (through one handle the board places: on
/// the STM32F407 in the CCM RAM, so that the controller's own layout, and with it the
/// control step's code, does not change): the monitor, and its store in flash.
pub struct Signature<F: embedded_storage::nor_flash::NorFlash, M> {
    /// Verdicts, counts, reference, the newest capture.
    pub monitor: monitor::Monitor<M>,
    /// The store (`None`: its flash could not be read; nothing is kept).
    pub store: Option<store::SigStore<F>>,
}

impl<F, M> Signature<F, M>
where
    F: embedded_storage::nor_flash::NorFlash,
    M: core::ops::DerefMut<Target = monitor::SignatureMem>,
{
    /// Open the store over `flash` (reads only) and take the buffers `mem`.
    pub fn new(flash: F, mem: M) -> Self {
        let store = match store::SigStore::open(flash) {
            Ok((st, _)) => Some(st),
            Err(_) => {
                error!("signature flash unreadable: curves are not kept");
                None
            }
        };
        Self {
            monitor: monitor::Monitor::new(mem),
            store,
        }
    }
}

/// Which stroke of a docking.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum Stroke {
    /// The compliant insertion, engagement point to mated.
    Insertion = 0,
    /// The extraction, mated to the engagement point.
    Extraction = 1,
}

impl Stroke {
    /// Its name, as the console, the log and the scenes say it.
    pub const fn name(self) -> &'static str {
        match self {
            Self::Insertion => "insertion",
            Self::Extraction => "extraction",
        }
    }
}
