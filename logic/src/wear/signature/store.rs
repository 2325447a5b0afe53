//! The signature's flash store: [`crate::framelog::FrameLog`] over sectors 2–4 with the
//! frames of [`super::records`], and what the signature reads back from it.
//!
//! Writes happen at rest only (the controller's one rule for the flash,
//! `Controller::at_rest`), after the odometer's own, one frame at a time and each in
//! parts of a budget of bytes a turn (`write_*`'s `budget`: a word program stalls the
//! CPU, and a whole curve programmed at once held the control step for 25–35 ms on the
//! virtual board); reads are
//! bounded: the newest frame of a kind, or `history`'s walk back through the summaries
//! (one frame a step, by each summary's `prev` link).

use embedded_storage::nor_flash::NorFlash;

use super::capture::Capture;
use super::records::{
    self, curve_byte, kind, RefHeader, Reference, StoredCurve, Summary, CURVE_LEN, KEEP, MAX_LEN,
    NOK_LEN, REFERENCE_LEN, SECTORS, SUMMARY_LEN,
};
use super::Stroke;
use crate::framelog::{Frame, FrameError, FrameLog, OpenReport};
use zerocopy::FromBytes;

/// Bytes of a record a turn at rest writes ([`super::monitor::Monitor::persist`]'s
/// budget): 128 B, 32 words — at most 3.2 ms of word programming at the datasheet's
/// maximum (100 µs a word; 0.5 ms typical), so a turn that begins after a control step
/// ends well before the next is due, even at 80 SPS (12.5 ms). A NOK docking's curves
/// (1.4 KiB) take 11 turns, a reference 9, a summary 1.
pub const WRITE_BUDGET: usize = 128;

/// The store.
#[derive(Debug)]
pub struct SigStore<F: NorFlash> {
    log: FrameLog<F>,
}

/// A store error: the log's.
pub type StoreError<E> = FrameError<E>;

impl<F: NorFlash> SigStore<F> {
    /// Open over `flash`: sectors of [`SECTORS`] from its start (2–4 on the board).
    pub fn open(flash: F) -> Result<(Self, OpenReport), StoreError<F::Error>> {
        Self::open_with(flash, &SECTORS)
    }

    /// Open over sectors of `sizes` bytes (tests use smaller ones).
    pub fn open_with(flash: F, sizes: &[u32]) -> Result<(Self, OpenReport), StoreError<F::Error>> {
        let (log, report) = FrameLog::open(flash, sizes, KEEP, MAX_LEN)?;
        Ok((Self { log }, report))
    }

    /// The newest summary and where it is.
    pub fn newest_summary(&mut self) -> Result<Option<(Summary, u32)>, StoreError<F::Error>> {
        let Some(f) = self.log.newest(kind::SUMMARY, 0)? else {
            return Ok(None);
        };
        Ok(self.summary_of(&f)?.map(|s| (s, f.offset)))
    }

    fn summary_of(&mut self, f: &Frame) -> Result<Option<Summary>, StoreError<F::Error>> {
        let mut b = [0u8; SUMMARY_LEN];
        self.log.read(f, 0, &mut b)?;
        Ok(Summary::from_bytes(&b))
    }

    /// Write a frame of `kind` in parts: begin it unless one of that kind is being
    /// written, then write up to `budget` bytes of it. Whether it is whole.
    fn write(
        &mut self,
        kind: u8,
        len: usize,
        budget: usize,
        fill: &mut dyn FnMut(usize, &mut [u8]),
    ) -> Result<bool, StoreError<F::Error>> {
        if self.log.writing() != Some(kind) {
            self.log.begin(kind, len)?;
        }
        Ok(self.log.resume(budget, fill)?.is_some())
    }

    /// The kind of the frame being written in parts, if one is.
    pub fn writing(&self) -> Option<u8> {
        self.log.writing()
    }

    /// Give up the frame being written in parts (its data changed): a torn frame.
    pub fn abandon(&mut self) {
        self.log.abandon();
    }

    /// Append a summary (its `prev` set to the newest summary's offset), up to
    /// `budget` bytes of it this call. Whether it is whole.
    pub fn write_summary(
        &mut self,
        s: &Summary,
        budget: usize,
    ) -> Result<bool, StoreError<F::Error>> {
        let prev = self.log.newest(kind::SUMMARY, 0)?.map(|f| f.offset);
        let b = Summary { prev, ..*s }.to_bytes();
        self.write(kind::SUMMARY, SUMMARY_LEN, budget, &mut |at, dst| {
            for (i, d) in dst.iter_mut().enumerate() {
                *d = b.get(at + i).copied().unwrap_or(0xFF);
            }
        })
    }

    /// Append a NOK docking: its summary and both curves of `cap`, up to `budget` bytes
    /// this call. Whether it is whole.
    pub fn write_nok(
        &mut self,
        s: &Summary,
        cap: &Capture,
        budget: usize,
    ) -> Result<bool, StoreError<F::Error>> {
        let b = Summary { prev: None, ..*s }.to_bytes();
        let (ins, ext) = (
            cap.stroke(Stroke::Insertion),
            cap.stroke(Stroke::Extraction),
        );
        self.write(kind::NOK, NOK_LEN, budget, &mut |at, dst| {
            for (i, d) in dst.iter_mut().enumerate() {
                let a = at + i;
                *d = if a < SUMMARY_LEN {
                    b.get(a).copied().unwrap_or(0xFF)
                } else if a < SUMMARY_LEN + CURVE_LEN {
                    curve_byte(ins, a - SUMMARY_LEN)
                } else {
                    curve_byte(ext, a - SUMMARY_LEN - CURVE_LEN)
                };
            }
        })
    }

    /// Append a cone's reference, up to `budget` bytes this call. Whether it is whole.
    pub fn write_reference(
        &mut self,
        r: &Reference,
        budget: usize,
    ) -> Result<bool, StoreError<F::Error>> {
        self.write(kind::REFERENCE, REFERENCE_LEN, budget, &mut |at, dst| {
            for (i, d) in dst.iter_mut().enumerate() {
                *d = r.byte(at + i);
            }
        })
    }

    /// Read the newest reference into `r` (left as it is if there is none, or if it is
    /// another cone's). Whether it was read.
    pub fn read_reference(
        &mut self,
        cone_id: u16,
        r: &mut Reference,
    ) -> Result<bool, StoreError<F::Error>> {
        let Some(f) = self.log.newest(kind::REFERENCE, 0)? else {
            return Ok(false);
        };
        let mut h = [0u8; 32];
        self.log.read(&f, 0, &mut h)?;
        let Ok(h) = RefHeader::read_from_bytes(&h) else {
            return Ok(false);
        };
        if h.cone_id.get() != cone_id {
            return Ok(false);
        }
        *r = Reference::from_header(&h);
        let mut buf = [0u8; 64];
        let mut at = 0;
        while at < REFERENCE_LEN - 32 {
            self.log.read(&f, 32 + at, &mut buf)?;
            let n = buf.len().min(REFERENCE_LEN - 32 - at);
            r.set_sum_bytes(at, buf.get(..n).unwrap_or(&[]));
            at += n;
        }
        Ok(true)
    }

    /// The `n`-th newest NOK docking (0: the newest): its summary and curves.
    pub fn read_nok(
        &mut self,
        n: usize,
        curves: &mut [StoredCurve; 2],
    ) -> Result<Option<Summary>, StoreError<F::Error>> {
        if n >= records::NOK_KEPT {
            return Ok(None);
        }
        let Some(f) = self.log.newest(kind::NOK, n)? else {
            return Ok(None);
        };
        let Some(s) = self.summary_of(&f)? else {
            return Ok(None);
        };
        let mut buf = [0u8; 64];
        let mut at = 0;
        while at < 2 * CURVE_LEN {
            self.log.read(&f, SUMMARY_LEN + at, &mut buf)?;
            let n = buf.len().min(2 * CURVE_LEN - at);
            for (k, &b) in buf.iter().take(n).enumerate() {
                let a = at + k;
                let (c, off) = if a < CURVE_LEN {
                    (0, a)
                } else {
                    (1, a - CURVE_LEN)
                };
                if let Some(curve) = curves.get_mut(c) {
                    curve.set_bytes(off, &[b]);
                }
            }
            at += n;
        }
        Ok(Some(s))
    }

    /// Walk back from the newest summary through `prev` links, calling `f` for each
    /// (newest first) while it returns `true`, at most `max`; a link that no longer
    /// leads to an older summary (its sector erased since) ends the walk.
    pub fn walk_summaries(
        &mut self,
        max: usize,
        f: &mut dyn FnMut(&Summary) -> bool,
    ) -> Result<usize, StoreError<F::Error>> {
        let mut frame = self.log.newest(kind::SUMMARY, 0)?;
        let mut count = 0;
        while let Some(fr) = frame {
            if count >= max || fr.kind != kind::SUMMARY {
                break;
            }
            let Some(s) = self.summary_of(&fr)? else {
                break;
            };
            count += 1;
            if !f(&s) {
                break;
            }
            frame = match s.prev {
                Some(p) => self.log.frame_at(p)?.filter(|p| p.seq < fr.seq),
                None => None,
            };
        }
        Ok(count)
    }

    /// Whether a pre-erase is due ([`FrameLog::needs_maintenance`]).
    pub fn needs_maintenance(&self) -> bool {
        self.log.needs_maintenance()
    }

    /// Pre-erase the next sector if due (at rest only).
    pub fn maintain(&mut self) -> Result<(), StoreError<F::Error>> {
        self.log.maintain()
    }

    /// The log.
    pub fn log(&self) -> &FrameLog<F> {
        &self.log
    }

    /// The log, mutably.
    pub fn log_mut(&mut self) -> &mut FrameLog<F> {
        &mut self.log
    }
}
