//! The board's side of the field update (issue 21, docs/update.md): the image header,
//! the public key updates are verified with, and the flash of DFU and STATE
//! behind the controller's owner.
//!
//! # The image header
//!
//! [`IMAGE_HEADER`] sits at ACTIVE + 0x200, right after the vector table
//! (`image-header.x`, written by build.rs): the version from Cargo.toml (build 0, not
//! stamped), the layout it is linked for (`update_layout::layout::LAYOUT`; an updater of
//! another layout refuses it) and the first bytes of [`PUBLIC_KEY`]. The signing tool stamps another
//! version into it before it signs. The running image reads its version from flash
//! ([`running_header`]), never from the constant: what runs is what was stamped.

use update_layout::header::{Header, Version, HEADER_LEN, HEADER_OFFSET, KEY_ID_LEN};
use update_layout::layout::{ACTIVE_BASE, DFU_PAGES};

include!(concat!(env!("OUT_DIR"), "/update_key.rs"));

/// A decimal of Cargo's version parts, at compile time (only in [`IMAGE_HEADER`]'s
/// initializer: an index out of bounds there fails the build, it cannot panic at run
/// time).
#[allow(clippy::indexing_slicing)]
const fn parse(s: &str) -> u32 {
    let b = s.as_bytes();
    let mut v: u32 = 0;
    let mut i = 0;
    while i < b.len() {
        v = v * 10 + (b[i] - b'0') as u32;
        i += 1;
    }
    v
}

/// The first bytes of the key, the header's key id (at compile time, as [`parse`]).
#[allow(clippy::indexing_slicing)]
const fn key_id() -> [u8; KEY_ID_LEN] {
    let mut id = [0u8; KEY_ID_LEN];
    let mut i = 0;
    while i < KEY_ID_LEN {
        id[i] = PUBLIC_KEY[i];
        i += 1;
    }
    id
}

/// The header as built (the signing tool may stamp another version over it).
#[used]
#[link_section = ".image_header"]
static IMAGE_HEADER: [u8; HEADER_LEN] = Header {
    version: Version {
        major: parse(env!("CARGO_PKG_VERSION_MAJOR")) as u8,
        minor: parse(env!("CARGO_PKG_VERSION_MINOR")) as u8,
        patch: parse(env!("CARGO_PKG_VERSION_PATCH")) as u16,
        build: 0,
    },
    flags: Header::flags_for(update_layout::layout::LAYOUT),
    key_id: key_id(),
}
.to_bytes();

/// The header at `base + HEADER_OFFSET` (an image's first address), read from flash.
/// Out of line (issue 20): two copies (-20 B).
#[inline(never)]
fn header_at(base: u32) -> Option<Header> {
    let mut b = [0u8; HEADER_LEN];
    for (i, x) in (base + HEADER_OFFSET..).zip(b.iter_mut()) {
        // SAFETY: inside ACTIVE or a DFU page, mapped readable flash (fixed addresses of
        // the partition map).
        *x = unsafe { core::ptr::read_volatile(i as *const u8) };
    }
    Header::parse(&b)
}

/// The running image's header (ACTIVE's).
pub fn running_header() -> Option<Header> {
    header_at(ACTIVE_BASE)
}

/// The header of the image in DFU page `page` (1: the one the last swap replaced; its
/// first page is there, embassy-boot's swap copies ACTIVE page 0 to DFU page 1).
pub fn dfu_header(page: usize) -> Option<Header> {
    header_at(*DFU_PAGES.get(page)?)
}

// --- DFU and STATE, behind the controller's owner ------------------------------------

use docking_logic::update::{BootFacts, ImageReport};
#[cfg(feature = "updater")]
use update_layout::part::{FlashError, Sectors};

#[cfg(feature = "updater")]
use super::flash::{OdoFlashError, OdometerFlash};
use super::owner::Ctrl;
#[cfg(feature = "updater")]
use super::owner::MAILBOX;

/// The `update` command's session (feature `updater`).
#[cfg(feature = "updater")]
pub type Session = docking_logic::console::update::UpdateSession;

/// Without the feature `updater` (issue 20's lean image, measured by `cargo xtask
/// size`): no session; the console refuses `update` (it was never enabled).
#[cfg(not(feature = "updater"))]
pub struct Session;

#[cfg(not(feature = "updater"))]
impl Session {
    /// Nothing.
    pub const fn new() -> Self {
        Self
    }
}

#[cfg(feature = "updater")]
/// The flash as the updater's partitions see it (`update_layout::part::Paged::dfu`,
/// `State`): reads straight from the memory map (idle, no owner needed: nothing else
/// writes these sectors), erases and programs through the controller's owner — a job
/// in the service's window, run only while an update is under way and the machine is
/// at rest (`Controller::at_rest`) — by [`OdometerFlash::erase_update_sector`] and
/// [`OdometerFlash::program_update`], which refuse anything but the DFU pages an update
/// file fills (ACTIVE's length of DFU) and STATE.
/// Call from idle only (the mailbox's rule).
pub struct UpdateFlash;

#[cfg(feature = "updater")]
/// Tries a flash job gets when the machine is not at rest just then (a Modbus reply on
/// the line): one per service window, 5 s at 80 SPS (50 s at 10 SPS).
const OWNER_TRIES: u32 = 400;

#[cfg(feature = "updater")]
/// Run `op` in the owner's window at rest; retried while a Modbus reply holds the flash.
///
/// Each try sees the line as it is at that try (`modbus::busy`: a request taken and not
/// answered, or the RS-485 driver's pin), and a try that finds the machine not at rest waits for
/// the next service window before the next: the 400 tries used to run back to back
/// in one window re-applying a bus-busy flag idle could not refresh, so a PLC polling
/// once a second failed the update (issue 32, item 3; docs/board.md, "What holds
/// between the steps", rule 8).
fn with_owner(op: &mut dyn FnMut() -> Result<(), OdoFlashError>) -> Result<(), FlashError> {
    let mut r = None;
    once_a_window(&mut |ctrl, _last| {
        if ctrl.updating() && ctrl.at_rest() {
            r = Some(op());
        }
        r.is_some()
    });
    match r {
        Some(Ok(())) => Ok(()),
        Some(Err(OdoFlashError::Status(sr))) => Err(FlashError::Status(sr)),
        Some(Err(OdoFlashError::OutOfBounds)) => Err(FlashError::OutOfBounds),
        Some(Err(OdoFlashError::NotAligned)) => Err(FlashError::NotAligned),
        Some(Err(OdoFlashError::Locked)) => Err(FlashError::Locked),
        Some(Err(OdoFlashError::Timeout)) | None => Err(FlashError::Timeout),
    }
}

#[cfg(feature = "updater")]
/// Run `op` with the controller in the owner's window once the machine is at rest with
/// the Modbus line free (tried once a window, [`OWNER_TRIES`] windows at most; then
/// run anyway, its records queued). The update's end writes its records at once and
/// then restarts: with a reply on the line its image record was refused and its audit
/// record queued in RAM, lost at the restart (issue 32's review).
pub fn at_rest(op: &mut dyn FnMut(&mut Ctrl)) {
    once_a_window(&mut |ctrl, last| {
        let run = ctrl.at_rest() || last;
        if run {
            op(ctrl);
        }
        run
    });
}

#[cfg(feature = "updater")]
/// Offer `job` the controller in the owner's window, once a window, [`OWNER_TRIES`]
/// windows at most: each try sees the Modbus line as it is then (`modbus::busy`), and
/// a try `job` declines (returns false) waits for the next window. `job`'s second
/// argument says the try is the last. True once `job` has run.
fn once_a_window(job: &mut dyn FnMut(&mut Ctrl, bool) -> bool) -> bool {
    for i in 0..OWNER_TRIES {
        let mut done = false;
        // The window the try ran in (read in it: the job may wait for the next).
        let mut steps = 0;
        MAILBOX.call(&mut |ctrl: &mut Ctrl| {
            steps = super::owner::steps();
            ctrl.set_bus_busy(super::modbus::busy());
            done = job(ctrl, i + 1 == OWNER_TRIES);
        });
        if done {
            return true;
        }
        super::owner::sleep_until_step_after(steps);
    }
    false
}

#[cfg(feature = "updater")]
impl Sectors for UpdateFlash {
    fn read(&mut self, addr: u32, buf: &mut [u8]) -> Result<(), FlashError> {
        let end = u64::from(addr) + buf.len() as u64;
        if addr < update_layout::layout::FLASH_BASE
            || end > u64::from(update_layout::layout::ODOMETER_BASE)
        {
            return Err(FlashError::OutOfBounds);
        }
        for (a, b) in (addr..).zip(buf.iter_mut()) {
            // SAFETY: inside the flash below the odometer (checked above), mapped
            // readable memory.
            *b = unsafe { core::ptr::read_volatile(a as *const u8) };
        }
        Ok(())
    }

    fn erase_sector(&mut self, base: u32) -> Result<(), FlashError> {
        with_owner(&mut || OdometerFlash::erase_update_sector(base))
    }

    fn program(&mut self, addr: u32, data: &[u8]) -> Result<(), FlashError> {
        with_owner(&mut || OdometerFlash::program_update(addr, data))
    }
}

/// At init: what `version` and Modbus identification report, and the image record a
/// rollback owes (a trial's confirmation records itself: [`confirm_trial`];
/// docs/update.md, "Versions").
pub fn boot_report(ctrl: &mut Ctrl, boot: update_layout::state::Boot) -> ImageReport {
    let facts = BootFacts {
        boot,
        running: running_header().map(|h| h.version),
        page1: dfu_header(1).map(|h| h.version),
        test_key: TEST_KEY,
    };
    docking_logic::update::at_boot(ctrl, facts)
}

/// Attempts at a trial's confirmation, each in a rest window of its own (issue 31).
pub const CONFIRM_ATTEMPTS: u8 = 3;

/// A trial boot's self-test passed (init, then the load cell's live samples, at rest):
/// confirm it (STATE says BOOT) and record it; `attempt` (1 to [`CONFIRM_ATTEMPTS`])
/// is logged. Whether the trial is over: confirmed, or its last attempt failed, which
/// `version` and Modbus identification then report (`trial=failed`: the next reset
/// rolls the image back). From the service only (the flash's owner).
#[inline(never)]
pub fn confirm_trial(ctrl: &mut Ctrl, attempt: u8) -> bool {
    match super::flash::OdometerFlash::confirm_boot() {
        Ok(()) => {
            defmt::info!("update: trial boot confirmed, this image is kept");
            let report = ctrl.images();
            docking_logic::update::confirmed(ctrl, &report);
            true
        }
        Err(e) if attempt < CONFIRM_ATTEMPTS => {
            defmt::warn!(
                "update: trial boot not confirmed (flash error {}), attempt {=u8} of {=u8}: tried again at the next rest",
                e,
                attempt,
                CONFIRM_ATTEMPTS
            );
            false
        }
        Err(e) => {
            defmt::error!(
                "update: trial boot not confirmed (flash error {}), attempt {=u8} of {=u8}: the next reset rolls this image back",
                e,
                attempt,
                CONFIRM_ATTEMPTS
            );
            let report = ctrl.images();
            ctrl.set_images(docking_logic::update::ImageReport {
                trial: docking_logic::update::Trial::Failed,
                ..report
            });
            true
        }
    }
}

#[cfg(feature = "updater")]
/// A verified update: the reply out (at most 200 ms), the motors safe, then the reset
/// into the bootloader's swap.
pub fn restart(term: &super::console::BoardConsole) -> ! {
    let start = super::clock::now_us();
    while !term.tx_idle() && super::clock::now_us().saturating_sub(start) < 200_000 {}
    super::force_safe_outputs();
    cortex_m::peripheral::SCB::sys_reset()
}
