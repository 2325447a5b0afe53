//! How long the bootloader's swap and revert take (issue 31: "the swap costs what the
//! image is, not what the partition is"), measured on the virtual board with the
//! unmodified bootloader, at the datasheet's typical and maximum flash times:
//! `vboard swap-time` (docs/update.md, "Swap time"; tools/figures.sh puts the table in
//! docs/measurements.md).
//!
//! Two pairs of images: the release image updated to itself (its size: what a swap
//! costs today), and two images that fill ACTIVE (layout C's 256 KiB: the worst case,
//! every word of both pages programmed). The swap is timed from power-on with STATE
//! saying SWAP to the new image's first instruction; the revert from the reset that
//! finds it unconfirmed to the old image's first instruction. The erases and the
//! programmed words are counted from the flash model.

use hil_sim::flash::{SharedFlash, SimFlash};
use hil_sim::rig::{Machine, RigOptions};
use update_layout::layout::{ACTIVE_BASE, ACTIVE_LEN, DFU_BASE, STATE_BASE};

use crate::cpu::{Board, BoardConfig};
use crate::image::Image;
use crate::periph::flash::FlashTiming;
use crate::scene::PS_PER_MS;

/// One swap and its revert.
#[derive(Clone, Debug)]
pub struct SwapTime {
    /// Which images.
    pub images: &'static str,
    /// Their lengths, bytes (old, new).
    pub lens: (usize, usize),
    /// Flash timing.
    pub timing: FlashTiming,
    /// Power-on → the new image's first instruction, ms.
    pub swap_ms: f64,
    /// Sectors erased and words programmed by the swap.
    pub swap_ops: (u64, u64),
    /// The reset → the old image's first instruction, ms.
    pub revert_ms: f64,
    /// Sectors erased and words programmed by the revert.
    pub revert_ops: (u64, u64),
}

/// An application that fills `len` bytes: a vector table (SP, the reset vector to a
/// `b .` at 0x40), then a pattern with no run of erased words (every word programmed).
pub fn filler_app(len: usize, tag: u8) -> Vec<u8> {
    let mut v = Vec::with_capacity(len);
    v.extend(0x2002_0000u32.to_le_bytes());
    v.extend((ACTIVE_BASE + 0x40 + 1).to_le_bytes());
    v.resize(0x40, 0xFF);
    v.extend(0xE7FEu16.to_le_bytes()); // b .
    while v.len() < len {
        v.push((v.len() as u8 ^ tag) | 1);
    }
    v
}

/// Run until the core executes in ACTIVE (the application's first instructions), at most
/// `limit_ms`; the virtual time it took, ms.
fn until_in_active(b: &mut Board, limit_ms: u64) -> Result<f64, String> {
    let t0 = b.now();
    let end = t0 + limit_ms * PS_PER_MS;
    while b.now() < end {
        let t = b.now() + PS_PER_MS / 10;
        b.run_until(t).map_err(|e| format!("{e:?}"))?;
        let pc = b.pc();
        if (ACTIVE_BASE..ACTIVE_BASE + ACTIVE_LEN).contains(&pc) {
            return Ok((b.now() - t0) as f64 / PS_PER_MS as f64);
        }
    }
    Err(format!("no application ran within {limit_ms} ms"))
}

/// The swap of `new` over `old` (each an application's bytes from ACTIVE's first
/// address), then its revert, with the bootloader `boot`.
pub fn measure(
    boot: &str,
    images: &'static str,
    old: &[u8],
    new: &[u8],
    timing: FlashTiming,
) -> Result<SwapTime, String> {
    let mut img = Image::load_bootloader(boot)?;
    img.put(ACTIVE_BASE, old)?;
    img.put(DFU_BASE, new)?;
    img.put(STATE_BASE, &update_layout::state::SWAP.to_le_bytes())?;
    let world = crate::world::World::new(
        Machine::new(&RigOptions::new(80)),
        SharedFlash::new(SimFlash::stm32f407_odometer()),
    );
    let cfg = BoardConfig {
        flash_timing: timing,
        ..BoardConfig::default()
    };
    let mut b = Board::new(img, world, cfg)?;
    let ops = |b: &Board| (b.soc().code_erases, b.soc().code_programs);
    b.power_on();
    let swap_ms = until_in_active(&mut b, 120_000)?;
    let swap_ops = ops(&b);
    // The new image never got to confirm itself: the next reset reverts.
    b.reset_pin();
    let revert_ms = until_in_active(&mut b, 120_000)?;
    let after = ops(&b);
    let head = |x: &[u8]| x.get(..64).map(<[u8]>::to_vec);
    let active: Vec<u8> = (0..16)
        .flat_map(|i| b.peek(ACTIVE_BASE + 4 * i).unwrap_or(0).to_le_bytes())
        .collect();
    if head(old) != Some(active) {
        return Err(format!(
            "{images}: the revert did not bring the old image back"
        ));
    }
    Ok(SwapTime {
        images,
        lens: (old.len(), new.len()),
        timing,
        swap_ms,
        swap_ops,
        revert_ms,
        revert_ops: (after.0 - swap_ops.0, after.1 - swap_ops.1),
    })
}

/// Every row: the release image `app` (its bytes from ACTIVE's first address) updated to
/// itself stamped, and two images filling ACTIVE; typical and maximum flash times.
pub fn table(boot: &str, app: &[u8]) -> Result<Vec<SwapTime>, String> {
    let stamped = crate::update::update_file(app, crate::update::NEW_VERSION);
    let new = stamped
        .get(..stamped.len() - update_layout::layout::TRAILER_LEN as usize)
        .unwrap_or(&stamped)
        .to_vec();
    let full = ACTIVE_LEN as usize;
    let (fa, fb) = (filler_app(full, 0x11), filler_app(full, 0x22));
    let mut rows = Vec::new();
    for timing in [FlashTiming::Typical, FlashTiming::Max] {
        rows.push(measure(
            boot,
            "the release image, updated to itself",
            app,
            &new,
            timing,
        )?);
        rows.push(measure(
            boot,
            "two images filling ACTIVE",
            &fa,
            &fb,
            timing,
        )?);
    }
    Ok(rows)
}

impl SwapTime {
    /// One JSON line.
    pub fn to_json(&self) -> String {
        format!(
            "{{\"images\":\"{}\",\"old_bytes\":{},\"new_bytes\":{},\"flash_timing\":\"{}\",\"swap_ms\":{:.1},\"swap_erases\":{},\"swap_words\":{},\"revert_ms\":{:.1},\"revert_erases\":{},\"revert_words\":{}}}",
            self.images,
            self.lens.0,
            self.lens.1,
            match self.timing {
                FlashTiming::Typical => "typical",
                FlashTiming::Max => "max",
            },
            self.swap_ms,
            self.swap_ops.0,
            self.swap_ops.1,
            self.revert_ms,
            self.revert_ops.0,
            self.revert_ops.1,
        )
    }

    /// One row of the text table.
    pub fn to_text(&self) -> String {
        format!(
            "{:<40} {:>7} {:>7} {:>8}  {:>9.0} ms ({} erases, {} words)  {:>9.0} ms ({} erases, {} words)",
            self.images,
            self.lens.0,
            self.lens.1,
            match self.timing {
                FlashTiming::Typical => "typical",
                FlashTiming::Max => "max",
            },
            self.swap_ms,
            self.swap_ops.0,
            self.swap_ops.1,
            self.revert_ms,
            self.revert_ops.0,
            self.revert_ops.1,
        )
    }
}

/// The header of the text table.
pub const HEADER: &str =
    "images                                      old B   new B   timing       swap                              revert";
