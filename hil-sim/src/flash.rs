//! Simulated NOR flash with STM32F4 semantics, for the odometer's sectors.
//!
//! * Erased bytes read `0xFF`; programming can only clear bits (the stored value is
//!   `old & new`); programming a byte twice with different bits is allowed (the F4
//!   permits it, the result is the AND), like `MultiwriteNorFlash`.
//! * Writes are `WRITE_SIZE` = 4 bytes, aligned (the F4 at 2.7–3.6 V programs 32-bit
//!   words); reads are byte-granular. Erase is per sector (`ERASE_SIZE`).
//! * Every sector counts its erases (endurance: 10 000 on the F4).
//! * **Power-cut injection**: [`SimFlash::cut_after_bytes`] lets the next N programmed
//!   bytes through, then "cuts the power": the byte in flight is left half-programmed
//!   (some of its bits cleared), nothing after it is written, and every later operation
//!   fails with [`SimFlashError::PowerLost`] until [`SimFlash::power_on`]. An erase that
//!   is cut leaves its sector partly erased: the first half reads 0xFF, the rest keeps
//!   old data. An erase costs one unit of the budget.
//! * **Marginal erase**: an erase stopped before its end ([`SimFlash::abort_erase`], a
//!   cut) leaves the sector *marginal* until a complete erase: its cells may read 0xFF
//!   without the margin the erase verifies (from 80 % of the erase time on, the whole
//!   sector reads erased). Data programmed there is not retained: at the next power-on
//!   every byte programmed into a marginal sector loses bit 0 (its CRC fails), and
//!   [`SimFlash::marginal_programs`] counts the programs that went there.
//! * **Write protection** ([`SimFlash::write_protect`], the option bytes' nWRP): every
//!   program and erase fails with [`SimFlashError::Protected`], as on the part.

use embedded_storage::nor_flash::{
    ErrorType, MultiwriteNorFlash, NorFlash, NorFlashError, NorFlashErrorKind, ReadNorFlash,
};

/// Sector size of the STM32F407's sectors 5–11, bytes.
pub const SECTOR_SIZE: usize = 128 * 1024;

/// Errors of the simulated flash.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum SimFlashError {
    /// Offset or length not aligned to `WRITE_SIZE` / `ERASE_SIZE`.
    NotAligned,
    /// Range outside the flash.
    OutOfBounds,
    /// Power was cut; nothing works until `power_on`.
    PowerLost,
    /// The sector is write-protected (the controller's WRPERR).
    Protected,
}

impl NorFlashError for SimFlashError {
    fn kind(&self) -> NorFlashErrorKind {
        match self {
            Self::NotAligned => NorFlashErrorKind::NotAligned,
            Self::OutOfBounds => NorFlashErrorKind::OutOfBounds,
            Self::PowerLost | Self::Protected => NorFlashErrorKind::Other,
        }
    }
}

/// The simulated flash region.
#[derive(Clone, Debug)]
pub struct SimFlash {
    mem: Vec<u8>,
    sector_size: usize,
    erase_counts: Vec<u32>,
    /// Bytes (and erases) still allowed before the cut; `None` = no cut armed.
    budget: Option<u64>,
    powered: bool,
    bytes_written: u64,
    /// Sectors whose last erase did not complete.
    marginal: Vec<bool>,
    /// Byte ranges programmed into a marginal sector (not retained over a power cycle).
    weak: Vec<core::ops::Range<usize>>,
    marginal_programs: u64,
    protected: bool,
    program_calls: u64,
    read_calls: u64,
}

impl SimFlash {
    /// `sectors` erased sectors of `sector_size` bytes.
    pub fn new(sectors: usize, sector_size: usize) -> Self {
        Self {
            mem: vec![0xFF; sectors * sector_size],
            sector_size,
            erase_counts: vec![0; sectors],
            budget: None,
            powered: true,
            bytes_written: 0,
            marginal: vec![false; sectors],
            weak: Vec::new(),
            marginal_programs: 0,
            protected: false,
            program_calls: 0,
            read_calls: 0,
        }
    }

    /// The odometer's region on the STM32F407: sectors 10 and 11, 2 × 128 KiB.
    pub fn stm32f407_odometer() -> Self {
        Self::new(2, SECTOR_SIZE)
    }

    /// Erases of each sector so far.
    pub fn erase_counts(&self) -> &[u32] {
        &self.erase_counts
    }

    /// Bytes programmed so far.
    pub fn bytes_written(&self) -> u64 {
        self.bytes_written
    }

    /// Arm a power cut after `n` more programmed bytes (an erase counts as one).
    pub fn cut_after_bytes(&mut self, n: u64) {
        self.budget = Some(n);
    }

    /// Whether the power has been cut.
    pub fn power_lost(&self) -> bool {
        !self.powered
    }

    /// Restore power (a reboot); disarms any pending cut. What was programmed into a
    /// marginal sector is not retained (bit 0 of every byte programmed there reads 0).
    pub fn power_on(&mut self) {
        self.powered = true;
        self.budget = None;
        for r in std::mem::take(&mut self.weak) {
            for b in &mut self.mem[r] {
                *b &= 0xFE;
            }
        }
    }

    /// Programs into a marginally erased sector so far.
    pub fn marginal_programs(&self) -> u64 {
        self.marginal_programs
    }

    /// Whether sector `index`'s last erase did not complete.
    pub fn is_marginal(&self, index: usize) -> bool {
        self.marginal.get(index).copied().unwrap_or(false)
    }

    /// Write-protect the whole region (or lift it).
    pub fn write_protect(&mut self, on: bool) {
        self.protected = on;
    }

    /// Program calls so far, refused ones included.
    pub fn program_calls(&self) -> u64 {
        self.program_calls
    }

    /// `read` calls so far (each costs real flash reads on the board: a log walk is
    /// thousands of them).
    pub fn read_calls(&self) -> u64 {
        self.read_calls
    }

    /// Flip bits of stored bytes (radiation, retention loss): `mem[off] ^= mask`.
    pub fn corrupt(&mut self, offset: usize, mask: u8) {
        if let Some(b) = self.mem.get_mut(offset) {
            *b ^= mask;
        }
    }

    /// Raw contents (for tests).
    pub fn contents(&self) -> &[u8] {
        &self.mem
    }

    /// Program `bytes` at `offset` as the flash controller does, with no alignment rule of
    /// its own (the controller enforces its PSIZE): every bit can only be cleared, each
    /// byte spends one unit of an armed power-cut budget.
    pub fn program(&mut self, offset: u32, bytes: &[u8]) -> Result<(), SimFlashError> {
        self.program_calls += 1;
        self.check(offset, bytes.len(), 1)?;
        if self.protected {
            return Err(SimFlashError::Protected);
        }
        if self.is_marginal(offset as usize / self.sector_size) {
            self.marginal_programs += 1;
            let o = offset as usize;
            self.weak.push(o..o + bytes.len());
        }
        for (i, b) in bytes.iter().enumerate() {
            let o = offset as usize + i;
            if !self.spend() {
                // The byte in flight is half-programmed: only its low nibble's zeros land.
                self.mem[o] &= b | 0xF0;
                return Err(SimFlashError::PowerLost);
            }
            self.mem[o] &= b;
            self.bytes_written += 1;
        }
        Ok(())
    }

    /// Erase sector `index` (counts one unit of an armed power-cut budget; a cut leaves
    /// the first half erased and the rest as it was).
    pub fn erase_sector(&mut self, index: usize) -> Result<(), SimFlashError> {
        let from = index * self.sector_size;
        self.check(from as u32, self.sector_size, self.sector_size)?;
        if self.protected {
            return Err(SimFlashError::Protected);
        }
        let range = from..from + self.sector_size;
        if !self.spend() {
            let half = range.start + self.sector_size / 2;
            self.mem[range.start..half].fill(0xFF);
            self.marginal[index] = true;
            return Err(SimFlashError::PowerLost);
        }
        self.weak
            .retain(|r| r.end <= range.start || r.start >= range.end);
        self.mem[range].fill(0xFF);
        self.erase_counts[index] += 1;
        self.marginal[index] = false;
        Ok(())
    }

    /// An erase of sector `index` stopped by a reset when `done_permille` of its time had
    /// passed: that fraction of the sector (from its start) reads erased, the rest keeps
    /// its old data — from 800 ‰ on, all of it reads erased; either way the sector is
    /// marginal until a complete erase. Not counted as an erase.
    pub fn abort_erase(&mut self, index: usize, done_permille: u32) {
        let from = index * self.sector_size;
        if let Some(m) = self.marginal.get_mut(index) {
            *m = true;
        }
        let permille = if done_permille >= 800 {
            1000
        } else {
            done_permille
        };
        let n = self.sector_size * permille as usize / 1000;
        if let Some(part) = self.mem.get_mut(from..from + n) {
            part.fill(0xFF);
        }
    }

    /// Sector size, bytes.
    pub fn sector_size(&self) -> usize {
        self.sector_size
    }

    fn check(&self, offset: u32, len: usize, align: usize) -> Result<(), SimFlashError> {
        if !self.powered {
            return Err(SimFlashError::PowerLost);
        }
        if offset as usize % align != 0 || len % align != 0 {
            return Err(SimFlashError::NotAligned);
        }
        if offset as usize + len > self.mem.len() {
            return Err(SimFlashError::OutOfBounds);
        }
        Ok(())
    }

    /// Take one unit of the power budget; `false` = the power goes now.
    fn spend(&mut self) -> bool {
        match &mut self.budget {
            None => true,
            Some(0) => {
                self.powered = false;
                false
            }
            Some(n) => {
                *n -= 1;
                true
            }
        }
    }
}

impl ErrorType for SimFlash {
    type Error = SimFlashError;
}

impl ReadNorFlash for SimFlash {
    const READ_SIZE: usize = 1;

    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.read_calls += 1;
        self.check(offset, bytes.len(), 1)?;
        let o = offset as usize;
        bytes.copy_from_slice(&self.mem[o..o + bytes.len()]);
        Ok(())
    }

    fn capacity(&self) -> usize {
        self.mem.len()
    }
}

impl NorFlash for SimFlash {
    const WRITE_SIZE: usize = 4;
    const ERASE_SIZE: usize = SECTOR_SIZE;

    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        if to < from {
            return Err(SimFlashError::OutOfBounds);
        }
        self.check(from, (to - from) as usize, self.sector_size)?;
        for s in (from as usize / self.sector_size)..(to as usize / self.sector_size) {
            self.erase_sector(s)?;
        }
        Ok(())
    }

    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.check(offset, bytes.len(), Self::WRITE_SIZE)?;
        self.program(offset, bytes)
    }
}

impl MultiwriteNorFlash for SimFlash {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nor_semantics() {
        let mut f = SimFlash::new(2, 1024);
        let mut b = [0u8; 4];
        f.read(0, &mut b).unwrap();
        assert_eq!(b, [0xFF; 4]);
        f.write(0, &[0xF0, 0x0F, 0xAA, 0x55]).unwrap();
        f.write(0, &[0x3C, 0xFF, 0xFF, 0x00]).unwrap();
        f.read(0, &mut b).unwrap();
        assert_eq!(b, [0x30, 0x0F, 0xAA, 0x00], "programming only clears bits");
        assert_eq!(f.write(2, &[0; 4]), Err(SimFlashError::NotAligned));
        assert_eq!(f.write(2048, &[0; 4]), Err(SimFlashError::OutOfBounds));
        f.erase(0, 1024).unwrap();
        f.read(0, &mut b).unwrap();
        assert_eq!(b, [0xFF; 4]);
        assert_eq!(f.erase_counts(), &[1, 0]);
    }

    #[test]
    fn power_cut_mid_write_and_mid_erase() {
        let mut f = SimFlash::new(2, 1024);
        f.cut_after_bytes(5);
        assert_eq!(f.write(0, &[0; 8]), Err(SimFlashError::PowerLost));
        let mut b = [0u8; 8];
        assert_eq!(f.read(0, &mut b), Err(SimFlashError::PowerLost));
        f.power_on();
        f.read(0, &mut b).unwrap();
        assert_eq!(b, [0, 0, 0, 0, 0, 0xF0, 0xFF, 0xFF]);
        f.write(1020, &[0x11; 4]).unwrap();
        f.cut_after_bytes(0);
        assert_eq!(f.erase(0, 1024), Err(SimFlashError::PowerLost));
        f.power_on();
        f.read(0, &mut b).unwrap();
        assert_eq!(b, [0xFF; 8], "first half erased");
        let mut tail = [0u8; 4];
        f.read(1020, &mut tail).unwrap();
        assert_eq!(tail, [0x11; 4], "second half keeps old data");
        assert!(f.is_marginal(0));
        assert_eq!(
            f.erase_counts(),
            &[0, 0],
            "a cut erase is not counted as done"
        );
        f.erase(0, 1024).unwrap();
        assert!(!f.is_marginal(0), "a complete erase restores the margin");
    }

    #[test]
    fn a_late_aborted_erase_reads_blank_but_does_not_retain() {
        let mut f = SimFlash::new(2, 1024);
        f.write(1020, &[0x11; 4]).unwrap();
        f.abort_erase(0, 900);
        let mut all = [0u8; 1024];
        f.read(0, &mut all).unwrap();
        assert!(all.iter().all(|&b| b == 0xFF), "reads blank");
        f.write(0, &[0x55; 4]).unwrap();
        assert_eq!(f.marginal_programs(), 1);
        f.power_on();
        let mut b = [0u8; 4];
        f.read(0, &mut b).unwrap();
        assert_eq!(b, [0x54; 4], "not retained");
    }

    #[test]
    fn write_protection_refuses_programs_and_erases() {
        let mut f = SimFlash::new(2, 1024);
        f.write_protect(true);
        assert_eq!(f.write(0, &[0; 4]), Err(SimFlashError::Protected));
        assert_eq!(f.erase(0, 1024), Err(SimFlashError::Protected));
        assert_eq!(f.program_calls(), 1);
        f.write_protect(false);
        f.write(0, &[0; 4]).unwrap();
    }
}

/// A [`SimFlash`] shared between the controller and the test or scene that injects
/// power cuts and "reboots" the controller on the same flash.
#[derive(Clone, Debug)]
pub struct SharedFlash(std::rc::Rc<std::cell::RefCell<SimFlash>>);

impl SharedFlash {
    /// Share `flash`.
    pub fn new(flash: SimFlash) -> Self {
        Self(std::rc::Rc::new(std::cell::RefCell::new(flash)))
    }

    /// Work on the flash (arm a cut, restore power, read counters).
    pub fn with<R>(&self, f: impl FnOnce(&mut SimFlash) -> R) -> R {
        f(&mut self.0.borrow_mut())
    }
}

impl ErrorType for SharedFlash {
    type Error = SimFlashError;
}

impl ReadNorFlash for SharedFlash {
    const READ_SIZE: usize = SimFlash::READ_SIZE;
    fn read(&mut self, offset: u32, bytes: &mut [u8]) -> Result<(), Self::Error> {
        self.0.borrow_mut().read(offset, bytes)
    }
    fn capacity(&self) -> usize {
        self.0.borrow().capacity()
    }
}

impl NorFlash for SharedFlash {
    const WRITE_SIZE: usize = SimFlash::WRITE_SIZE;
    const ERASE_SIZE: usize = SimFlash::ERASE_SIZE;
    fn erase(&mut self, from: u32, to: u32) -> Result<(), Self::Error> {
        self.0.borrow_mut().erase(from, to)
    }
    fn write(&mut self, offset: u32, bytes: &[u8]) -> Result<(), Self::Error> {
        self.0.borrow_mut().write(offset, bytes)
    }
}

impl MultiwriteNorFlash for SharedFlash {}

/// Fill the odometer log in `flash` — with the firmware's own record format (the
/// library's `RecordLog`) — with a cone record and cycle snapshots, until its current
/// sector is past the maintenance mark and the next sector still holds older records:
/// the controller's next idle moment erases that sector. For tests and scenes of the
/// sector erase.
pub fn fill_log_to_maintenance(flash: &SharedFlash) -> Result<(), String> {
    use docking_logic::material::Material;
    use docking_logic::odometer::{self, kind, StateRecord, WearConfig};
    let (mut log, _) =
        docking_logic::odometer::open_log(flash.clone()).map_err(|e| format!("open: {e}"))?;
    let cone = odometer::Cone::new(1, Material::ZQSn5_2, "SN-1", 0);
    log.append(kind::CONE, &odometer::cone_to_bytes(&cone))
        .map_err(|e| format!("append: {e}"))?;
    let mut odo = odometer::restore(WearConfig::DEFAULT, Some(cone), None, cone.material);
    // One full sector, then 95 % of the next: the sector after that (the first) is not
    // blank.
    let per_sector = log.slots_per_sector();
    for _ in 0..per_sector + per_sector * 95 / 100 {
        odo.on_contact_sample(0, 100_000);
        odo.on_contact_sample(30_000, 100_000);
        odo.end_contact();
        let _ = odo.complete_cycle();
        log.append(kind::STATE, &StateRecord::of(&odo, true).to_bytes())
            .map_err(|e| format!("append: {e}"))?;
    }
    if log.needs_maintenance() {
        Ok(())
    } else {
        Err("the log did not reach its maintenance mark".into())
    }
}
