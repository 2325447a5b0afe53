//! The ART accelerator in front of the flash (RM0090 §3.5): wait states, the
//! instruction and data caches, the prefetch buffer — the timing model
//! [`crate::cpu::Timing::Art`] runs the core through.
//!
//! * **Wait states.** A read of a 128-bit flash line that neither cache nor buffer holds
//!   costs `FLASH_ACR.LATENCY` extra core cycles (5 at 168 MHz and 3.3 V).
//! * **Instruction side** (I-Code): the line being executed is held (a fetch inside it
//!   costs nothing); with `ICEN` set, **64 lines** of 128 bits are kept; "each time a miss
//!   occurs (requested data not present in the currently used instruction line, in the
//!   prefetched instruction line or in the instruction cache memory), the line read is
//!   copied into the instruction cache", replaced least recently used first (RM0090
//!   §3.5.2). The organisation is not stated beyond LRU: modelled fully associative.
//! * **Prefetch** (`PRFTEN`), modelled simply: once the core starts on line *L*, the
//!   flash reads *L + 1* in the background, ready `LATENCY + 1` cycles later; a request
//!   for *L + 1* before then waits the difference (straight code of 32-bit instructions
//!   outruns it by two cycles a line; 16-bit code does not). A branch anywhere else is a
//!   miss unless the cache holds the line. The buffer is one line, refilled at every
//!   new line; prefetched lines are not copied into the cache (only misses are).
//! * **Data side** (D-Code: literal pools, constants, the odometer's records): with
//!   `DCEN` set, **8 lines** of 128 bits, LRU; every read of a line the cache does not hold
//!   costs the wait states (no line buffer is assumed on this side).
//! * **Coherency**: none for an erase. A line cached before its sector is erased keeps
//!   the pre-erase bytes: a read that hits it returns them — until the cache is reset.
//!   `ICRST`/`DCRST` reset a cache **only while it is disabled** (`ICEN`/`DCEN` clear
//!   before and by the write); written while enabled, the bit is ignored and counted
//!   ([`ArtStats::resets_refused`]). A word program is taken as written through to a
//!   line that holds its address (ST's own driver flushes after erases only).
//! * A system reset empties both caches and the buffers (`FLASH_ACR` resets to 0).
//!
//! Served stale: the data cache's lines of the odometer sectors (the model keeps their
//! bytes; those sectors are the only ones the firmware erases). A stale line of a code
//! sector (erased only by a probe's mass erase, which destroys the image anyway) is
//! counted ([`ArtStats::stale_hits`]) but the core executes what the array holds.
//!
//! Reads that bypass the ART (a probe, the board's own instruction decode) neither
//! cost time nor change the caches.

/// Bytes per flash line (128 bits).
pub const LINE_BYTES: u32 = 16;
/// Instruction cache lines.
pub const ICACHE_LINES: usize = 64;
/// Data cache lines.
pub const DCACHE_LINES: usize = 8;
/// Lines of the 1 MiB flash.
const FLASH_LINES: usize = (crate::periph::flash::FLASH_SIZE / LINE_BYTES) as usize;
const NONE: u32 = u32::MAX;
const NO_SLOT: u8 = u8::MAX;

/// FLASH_ACR bits.
pub mod acr {
    /// Wait states.
    pub const LATENCY: u32 = 7;
    /// Prefetch enable.
    pub const PRFTEN: u32 = 1 << 8;
    /// Instruction cache enable.
    pub const ICEN: u32 = 1 << 9;
    /// Data cache enable.
    pub const DCEN: u32 = 1 << 10;
    /// Instruction cache reset.
    pub const ICRST: u32 = 1 << 11;
    /// Data cache reset.
    pub const DCRST: u32 = 1 << 12;
}

/// A fully associative line cache with LRU replacement, indexed by flash line number
/// (offset from the flash base / 16).
#[derive(Clone, Debug)]
pub struct LineCache {
    tags: Vec<u32>,
    stamps: Vec<u64>,
    /// The line's bytes as they were read from the array, for lines whose bytes the model
    /// serves (`None`: the array is read instead).
    data: Vec<Option<[u8; 16]>>,
    /// Filled before an erase of its address, not reset since.
    stale: Vec<bool>,
    /// Slot of each flash line (`NO_SLOT`: not cached).
    slot_of: Vec<u8>,
    now: u64,
    /// The slots in the order of their stamps, oldest first (ties: the lower slot, as
    /// the stamps of the never filled are all 0): a list through `older`/`newer`, so that
    /// the victim of a fill is found without a pass over the stamps (that pass was a
    /// third of a run under the cache model). Empty slots are always the oldest: they
    /// are emptied only all at once (`reset`), and every fill since stamped newer.
    older: Vec<u8>,
    newer: Vec<u8>,
    oldest: u8,
    newest: u8,
}

impl LineCache {
    /// An empty cache of `lines` lines.
    pub fn new(lines: usize) -> Self {
        assert!(lines < NO_SLOT as usize);
        Self {
            tags: vec![NONE; lines],
            stamps: vec![0; lines],
            data: vec![None; lines],
            stale: vec![false; lines],
            slot_of: vec![NO_SLOT; FLASH_LINES],
            now: 0,
            older: (0..lines)
                .map(|i| if i == 0 { NO_SLOT } else { i as u8 - 1 })
                .collect(),
            newer: (0..lines)
                .map(|i| if i + 1 == lines { NO_SLOT } else { i as u8 + 1 })
                .collect(),
            oldest: 0,
            newest: lines.saturating_sub(1) as u8,
        }
    }

    /// `slot` becomes the newest in the list (its stamp was just set to `now`).
    #[inline]
    fn touch(&mut self, slot: usize) {
        let s = slot as u8;
        if self.newest == s {
            return;
        }
        let (o, n) = (self.older[slot], self.newer[slot]);
        if o == NO_SLOT {
            self.oldest = n;
        } else {
            self.newer[o as usize] = n;
        }
        // `s` is not the newest, so it has a newer neighbour.
        self.older[n as usize] = o;
        self.older[slot] = self.newest;
        self.newer[slot] = NO_SLOT;
        self.newer[self.newest as usize] = s;
        self.newest = s;
    }

    /// The slot holding `line`, marked most recently used.
    #[inline]
    pub fn hit(&mut self, line: u32) -> Option<usize> {
        let s = *self.slot_of.get(line as usize)?;
        if s == NO_SLOT {
            return None;
        }
        self.now += 1;
        self.stamps[s as usize] = self.now;
        self.touch(s as usize);
        Some(s as usize)
    }

    /// Whether `line` is cached (no LRU update).
    pub fn holds(&self, line: u32) -> bool {
        self.slot_of
            .get(line as usize)
            .is_some_and(|&s| s != NO_SLOT)
    }

    /// Put `line` in the least recently used slot (an empty one first); returns it.
    pub fn fill(&mut self, line: u32, data: Option<[u8; 16]>) -> usize {
        let Some(&s) = self.slot_of.get(line as usize) else {
            return 0;
        };
        let slot = if s != NO_SLOT {
            s as usize
        } else {
            // The least recently used, an empty slot first (`older`/`newer`).
            let slot = self.oldest as usize;
            if let Some(old) = self
                .tags
                .get(slot)
                .and_then(|&t| self.slot_of.get_mut(t as usize))
            {
                *old = NO_SLOT;
            }
            self.slot_of[line as usize] = slot as u8;
            slot
        };
        self.now += 1;
        self.tags[slot] = line;
        self.stamps[slot] = self.now;
        self.data[slot] = data;
        self.stale[slot] = false;
        self.touch(slot);
        slot
    }

    /// Empty the cache.
    pub fn reset(&mut self) {
        for t in &mut self.tags {
            if let Some(s) = self.slot_of.get_mut(*t as usize) {
                *s = NO_SLOT;
            }
            *t = NONE;
        }
        self.data.iter_mut().for_each(|d| *d = None);
        self.stale.iter_mut().for_each(|s| *s = false);
    }

    /// Mark the cached lines in `first..=last` stale (their sector was erased); returns
    /// how many.
    pub fn erased(&mut self, first: u32, last: u32) -> u64 {
        let mut n = 0;
        for (i, &t) in self.tags.iter().enumerate() {
            if t != NONE && (first..=last).contains(&t) {
                self.stale[i] = true;
                n += 1;
            }
        }
        n
    }

    /// Lines cached.
    pub fn len(&self) -> usize {
        self.tags.iter().filter(|&&t| t != NONE).count()
    }

    /// Whether nothing is cached.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Lines cached that are stale.
    pub fn stale_lines(&self) -> usize {
        self.stale.iter().filter(|&&s| s).count()
    }
}

/// What the ART did, for reports and tests.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ArtStats {
    /// Instruction-line requests (a fetch outside the line being executed).
    pub i_lines: u64,
    /// Of those, served by the instruction cache.
    pub i_hits: u64,
    /// Served by the prefetch buffer.
    pub i_prefetched: u64,
    /// Read from the array (paying the wait states).
    pub i_misses: u64,
    /// Data-line reads.
    pub d_lines: u64,
    /// Of those, served by the data cache.
    pub d_hits: u64,
    /// Core cycles lost to wait states (instruction and data), thousandths.
    pub stall_mc: u64,
    /// Cache hits on a line that is stale (filled before its sector's erase).
    pub stale_hits: u64,
    /// Instruction and data cache resets done.
    pub i_resets: u64,
    /// See [`ArtStats::i_resets`].
    pub d_resets: u64,
    /// `ICRST`/`DCRST` written while the cache was enabled (ignored, as on the part).
    pub resets_refused: u64,
    /// Sector (or mass) erases completed.
    pub erases: u64,
    /// Cached lines an erase left stale (held when their sector was erased).
    pub lines_made_stale: u64,
    /// Of the erases, those after which the core ran on to the next erase or to a system
    /// reset without resetting both caches (see [`Art::erases_unflushed`]).
    pub erases_unflushed: u64,
}

/// The accelerator's state at the start of a loop iteration, as far as an iteration
/// changes it: to tell that iterations repeat, and to advance it over the skipped ones
/// ([`Art::advance_loop`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct LoopMark {
    stats: ArtStats,
    i_now: u64,
    d_now: u64,
    cur_line: u32,
    prefetch: (u32, u64),
}

impl ArtStats {
    fn sub(&self, o: &Self) -> Self {
        Self {
            i_lines: self.i_lines - o.i_lines,
            i_hits: self.i_hits - o.i_hits,
            i_prefetched: self.i_prefetched - o.i_prefetched,
            i_misses: self.i_misses - o.i_misses,
            d_lines: self.d_lines - o.d_lines,
            d_hits: self.d_hits - o.d_hits,
            stall_mc: self.stall_mc - o.stall_mc,
            stale_hits: self.stale_hits - o.stale_hits,
            i_resets: self.i_resets - o.i_resets,
            d_resets: self.d_resets - o.d_resets,
            resets_refused: self.resets_refused - o.resets_refused,
            erases: self.erases - o.erases,
            lines_made_stale: self.lines_made_stale - o.lines_made_stale,
            erases_unflushed: self.erases_unflushed - o.erases_unflushed,
        }
    }

    fn add_times(&mut self, d: &Self, k: u64) {
        self.i_lines += k * d.i_lines;
        self.i_hits += k * d.i_hits;
        self.i_prefetched += k * d.i_prefetched;
        self.i_misses += k * d.i_misses;
        self.d_lines += k * d.d_lines;
        self.d_hits += k * d.d_hits;
        self.stall_mc += k * d.stall_mc;
        self.stale_hits += k * d.stale_hits;
    }
}

impl LineCache {
    /// The lines touched since the counter stood at `since` move on by `k` touches of
    /// `per` each (a loop's iterations touch the same lines in the same order).
    fn advance(&mut self, since: u64, per: u64, k: u64) {
        for st in self.stamps.iter_mut() {
            if *st > since {
                *st += k * per;
            }
        }
        self.now += k * per;
    }
}

/// The accelerator.
#[derive(Clone, Debug)]
pub struct Art {
    /// Instruction cache.
    pub icache: LineCache,
    /// Data cache.
    pub dcache: LineCache,
    /// The instruction line being executed (`NONE`: none).
    cur_line: u32,
    /// The prefetch buffer's line, and the milli-cycle count at which it is ready.
    prefetch: (u32, u64),
    /// Counters.
    pub stats: ArtStats,
    /// An erase has completed and the instruction / data cache has not been reset since.
    unflushed: (bool, bool),
    /// Fault injection: `ICRST`/`DCRST` writes have no effect (a chip whose caches
    /// cannot be reset), to prove that a test sees the firmware's flush.
    pub ignore_cache_resets: bool,
}

impl Default for Art {
    fn default() -> Self {
        Self::new()
    }
}

/// The flash line number of `addr` (its code alias at 0 or 0x0800_0000), if in flash.
#[inline]
pub fn line_of(addr: u32) -> Option<u32> {
    use crate::periph::flash::{FLASH_BASE, FLASH_SIZE};
    let off = if addr < FLASH_SIZE {
        addr
    } else {
        addr.wrapping_sub(FLASH_BASE)
    };
    (off < FLASH_SIZE).then_some(off / LINE_BYTES)
}

impl Art {
    /// Empty caches and buffers.
    pub fn new() -> Self {
        Self {
            icache: LineCache::new(ICACHE_LINES),
            dcache: LineCache::new(DCACHE_LINES),
            cur_line: NONE,
            prefetch: (NONE, 0),
            stats: ArtStats::default(),
            unflushed: (false, false),
            ignore_cache_resets: false,
        }
    }

    /// The state a loop iteration starts from, at milli-cycle `mc`.
    pub fn loop_mark(&self) -> LoopMark {
        LoopMark {
            stats: self.stats,
            i_now: self.icache.now,
            d_now: self.dcache.now,
            cur_line: self.cur_line,
            prefetch: self.prefetch,
        }
    }

    /// Whether an iteration from `a` to `b` (`d_mc` milli-cycles apart) can be repeated
    /// from `b` and give the same: no line read from the array (a miss fills or
    /// evicts), no cache reset or erase, the same line executing and the prefetch buffer
    /// as far ahead in time.
    pub fn loop_repeats(a: &LoopMark, b: &LoopMark, d_mc: u64) -> bool {
        let d = b.stats.sub(&a.stats);
        // The buffer moves on with the fetches of a loop in flash, and stands still for
        // one in SRAM.
        let prefetch_same = a.prefetch.0 == b.prefetch.0
            && (a.prefetch.0 == NONE
                || b.prefetch.1 == a.prefetch.1 + d_mc
                || b.prefetch.1 == a.prefetch.1);
        d.i_misses == 0
            && d.d_lines == d.d_hits
            && d.i_resets == 0
            && d.d_resets == 0
            && d.resets_refused == 0
            && d.erases == 0
            && d.lines_made_stale == 0
            && d.erases_unflushed == 0
            && a.cur_line == b.cur_line
            && prefetch_same
    }

    /// `k` more iterations like the one from `a` to `b`, as they would have left the
    /// caches, the buffer and the counters.
    pub fn advance_loop(&mut self, a: &LoopMark, b: &LoopMark, k: u64) {
        let d = b.stats.sub(&a.stats);
        self.stats.add_times(&d, k);
        self.icache.advance(a.i_now, b.i_now - a.i_now, k);
        self.dcache.advance(a.d_now, b.d_now - a.d_now, k);
        if self.prefetch.0 != NONE {
            self.prefetch.1 += k * (b.prefetch.1 - a.prefetch.1);
        }
    }

    /// Erases whose caches software did not reset (`ICRST` and `DCRST`, while disabled)
    /// before the next erase or system reset, counting one that completed and has not
    /// been followed by both resets yet. ST's driver resets both after every erase;
    /// RM0090 §3.5.2 warns that lines may be stale otherwise. (A system reset empties
    /// the caches as well, but the firmware ran on stale lines until then.)
    pub fn erases_unflushed(&self) -> u64 {
        self.stats.erases_unflushed + u64::from(self.unflushed.0 || self.unflushed.1)
    }

    /// A system reset: both caches and the buffers emptied.
    pub fn reset(&mut self) {
        if self.unflushed.0 || self.unflushed.1 {
            self.stats.erases_unflushed += 1;
            self.unflushed = (false, false);
        }
        self.icache.reset();
        self.dcache.reset();
        self.cur_line = NONE;
        self.prefetch = (NONE, 0);
    }

    /// A write of `new` to FLASH_ACR over `old`; returns the value the register takes
    /// (a reset bit written while its cache is enabled is not taken).
    pub fn write_acr(&mut self, old: u32, new: u32) -> u32 {
        let mut v = new;
        for (rst, en) in [(acr::ICRST, acr::ICEN), (acr::DCRST, acr::DCEN)] {
            if new & rst == 0 {
                continue;
            }
            if (old | new) & en != 0 {
                v &= !rst;
                self.stats.resets_refused += 1;
                continue;
            }
            if self.ignore_cache_resets {
                continue;
            }
            if rst == acr::ICRST {
                self.icache.reset();
                self.stats.i_resets += 1;
                self.unflushed.0 = false;
            } else {
                self.dcache.reset();
                self.stats.d_resets += 1;
                self.unflushed.1 = false;
            }
        }
        v
    }

    /// An erase of flash offsets `from..to` completed: cached copies of those lines go
    /// stale, and both caches want a reset.
    pub fn erased(&mut self, from: u32, to: u32) {
        if to <= from {
            return;
        }
        self.stats.erases += 1;
        if self.unflushed.0 || self.unflushed.1 {
            self.stats.erases_unflushed += 1;
        }
        self.unflushed = (true, true);
        let (a, b) = (from / LINE_BYTES, (to - 1) / LINE_BYTES);
        self.stats.lines_made_stale += self.icache.erased(a, b) + self.dcache.erased(a, b);
        if (a..=b).contains(&self.cur_line) {
            self.cur_line = NONE;
        }
        if (a..=b).contains(&self.prefetch.0) {
            self.prefetch = (NONE, 0);
        }
    }

    /// A program at flash offset `off` left the array holding `bytes` there: written
    /// through to a cached line (which takes the array's bytes at those addresses).
    pub fn programmed(&mut self, off: u32, bytes: &[u8]) {
        for (i, &b) in bytes.iter().enumerate() {
            let a = off + i as u32;
            if let Some(&s) = self.dcache.slot_of.get((a / LINE_BYTES) as usize) {
                if s != NO_SLOT {
                    if let Some(d) = self.dcache.data[s as usize].as_mut() {
                        d[(a % LINE_BYTES) as usize] = b;
                    }
                }
            }
        }
    }

    /// The core executes a block of `insns` instructions, `size` bytes at flash address
    /// `addr`, starting at milli-cycle `mc0` at `cpi_milli`: the wait states it pays
    /// fetching its lines, milli-cycles.
    #[inline]
    pub fn fetch_block(
        &mut self,
        acr_v: u32,
        addr: u32,
        size: u32,
        insns: u64,
        mc0: u64,
        cpi_milli: u64,
    ) -> u64 {
        let Some(first) = line_of(addr) else {
            return 0;
        };
        let last = first + (addr % LINE_BYTES + size.max(1) - 1) / LINE_BYTES;
        if first == last && first == self.cur_line {
            return 0;
        }
        let wait_mc = u64::from(acr_v & acr::LATENCY) * 1_000;
        // The block's start as a flash offset.
        let start = first * LINE_BYTES + addr % LINE_BYTES;
        let mut stall = 0u64;
        for line in first..=last {
            if line == self.cur_line {
                continue;
            }
            // When the core needs this line: the block's start plus its share of the
            // block's instructions before it.
            let before = u64::from((line * LINE_BYTES).saturating_sub(start));
            let need = mc0 + stall + before * insns / u64::from(size.max(1)) * cpi_milli;
            self.stats.i_lines += 1;
            let cached = if acr_v & acr::ICEN != 0 {
                self.icache.hit(line)
            } else {
                None
            };
            let wait = if let Some(slot) = cached {
                self.stats.i_hits += 1;
                if self.icache.stale[slot] {
                    self.stats.stale_hits += 1;
                }
                0
            } else if acr_v & acr::PRFTEN != 0 && self.prefetch.0 == line {
                self.stats.i_prefetched += 1;
                self.prefetch.1.saturating_sub(need)
            } else {
                self.stats.i_misses += 1;
                if acr_v & acr::ICEN != 0 {
                    self.icache.fill(line, None);
                }
                wait_mc
            };
            stall += wait;
            self.cur_line = line;
            if acr_v & acr::PRFTEN != 0 {
                // The next line is read as soon as this one is in: LATENCY + 1 cycles.
                self.prefetch = (line + 1, need + wait + wait_mc + 1_000);
            }
        }
        self.stats.stall_mc += stall;
        stall
    }

    /// A data read of flash line `line` (D-Code): the line's bytes when the model serves
    /// them (`array` reads them from the array on a miss; `None` for lines the emulator
    /// serves), and the wait states paid, milli-cycles. A hit on a stale line returns its
    /// pre-erase bytes.
    pub fn read_line(
        &mut self,
        acr_v: u32,
        line: u32,
        array: impl FnOnce() -> Option<[u8; 16]>,
    ) -> (Option<[u8; 16]>, u64) {
        self.stats.d_lines += 1;
        if acr_v & acr::DCEN != 0 {
            if let Some(s) = self.dcache.hit(line) {
                if self.dcache.stale[s] {
                    self.stats.stale_hits += 1;
                }
                if let Some(d) = self.dcache.data[s] {
                    self.stats.d_hits += 1;
                    return (Some(d), 0);
                }
                // Cached by tag only, but its bytes are wanted now: read them (no
                // stall: it is a hit).
                let d = array();
                self.dcache.data[s] = d;
                self.stats.d_hits += 1;
                return (d, 0);
            }
        }
        let wait_mc = u64::from(acr_v & acr::LATENCY) * 1_000;
        self.stats.stall_mc += wait_mc;
        let d = array();
        if acr_v & acr::DCEN != 0 {
            self.dcache.fill(line, d);
        }
        (d, wait_mc)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The victim a fill took before the list: the empty slot with the oldest stamp,
    /// else the oldest (the first of equals).
    fn victim_by_scan(c: &LineCache) -> usize {
        c.stamps
            .iter()
            .enumerate()
            .min_by_key(|&(i, &st)| (c.tags[i] != NONE, st))
            .map_or(0, |(i, _)| i)
    }

    #[test]
    fn the_lru_list_picks_the_victim_the_scan_of_the_stamps_picked() {
        // Fills, hits, resets and a skipped loop's `advance`, in a pseudo-random mix
        // over few lines (so that hits and evictions both happen).
        let mut c = LineCache::new(8);
        let mut x: u64 = 0x9E37_79B9_7F4A_7C15;
        for step in 0..200_000 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let line = (x % 24) as u32;
            match x >> 60 {
                0 if step % 1000 == 0 => c.reset(),
                1 => {
                    let since = c.now.saturating_sub(x % 5);
                    c.advance(since, 3, 2);
                }
                2..=7 => {
                    c.hit(line);
                }
                _ => {
                    if !c.holds(line) {
                        let want = victim_by_scan(&c);
                        assert_eq!(c.fill(line, None), want, "step {step}");
                    }
                }
            }
        }
    }

    const ON: u32 = 5 | acr::PRFTEN | acr::ICEN | acr::DCEN;
    const ODO: u32 = 0xC_0000 / LINE_BYTES;

    fn line(b: u8) -> Option<[u8; 16]> {
        Some([b; 16])
    }

    #[test]
    fn a_miss_pays_the_wait_states_and_a_cached_line_does_not() {
        let mut a = Art::new();
        let no_prefetch = ON & !acr::PRFTEN;
        // Two lines, 8 instructions, CPI 1: both lines miss.
        assert_eq!(
            a.fetch_block(no_prefetch, 0x0800_0100, 32, 8, 0, 1_000),
            10_000
        );
        // The same code again from elsewhere: both lines are cached now.
        a.fetch_block(no_prefetch, 0x0800_4000, 2, 1, 0, 1_000);
        assert_eq!(a.fetch_block(no_prefetch, 0x0800_0100, 32, 8, 0, 1_000), 0);
        // The alias at 0 is the same flash.
        a.fetch_block(no_prefetch, 0x0800_4000, 2, 1, 0, 1_000);
        assert_eq!(a.fetch_block(no_prefetch, 0x100, 32, 8, 0, 1_000), 0);
        // Without the cache every new line pays; the line being executed does not.
        let mut a = Art::new();
        let bare = 5;
        assert_eq!(a.fetch_block(bare, 0x0800_0100, 16, 4, 0, 1_000), 5_000);
        assert_eq!(a.fetch_block(bare, 0x0800_0108, 8, 2, 0, 1_000), 0);
        a.fetch_block(bare, 0x0800_4000, 2, 1, 0, 1_000);
        assert_eq!(a.fetch_block(bare, 0x0800_0100, 16, 4, 0, 1_000), 5_000);
        // No wait states (16 MHz): nothing to pay.
        assert_eq!(a.fetch_block(0, 0x0800_2000, 64, 16, 0, 1_000), 0);
    }

    #[test]
    fn the_instruction_cache_keeps_64_lines_least_recently_used_out() {
        let mut a = Art::new();
        let cfg = 5 | acr::ICEN;
        for l in 0..65u32 {
            a.fetch_block(cfg, 0x0800_0000 + l * 16, 2, 1, 0, 1_000);
        }
        assert_eq!(a.icache.len(), ICACHE_LINES);
        assert!(!a.icache.holds(0), "line 0 was the least recently used");
        assert!(a.icache.holds(1) && a.icache.holds(64));
        assert_eq!(a.stats.i_misses, 65);
    }

    #[test]
    fn sequential_code_finds_the_next_line_prefetched() {
        let mut a = Art::new();
        let cfg = 5 | acr::PRFTEN;
        // 16-bit code: 8 instructions a line at CPI 1, slower than the flash (6 cycles
        // a line): after the first miss nothing waits.
        assert_eq!(a.fetch_block(cfg, 0x0800_0000, 64, 32, 0, 1_000), 5_000);
        assert_eq!(a.stats.i_prefetched, 3);
        // 32-bit code: 4 instructions a line, the prefetch is 2 cycles late each line.
        let mut a = Art::new();
        assert_eq!(
            a.fetch_block(cfg, 0x0800_0000, 64, 16, 0, 1_000),
            5_000 + 3 * 2_000
        );
        // A branch elsewhere misses.
        assert_eq!(a.fetch_block(cfg, 0x0800_1000, 4, 2, 0, 1_000), 5_000);
    }

    #[test]
    fn a_data_line_read_before_an_erase_stays_stale_until_dcrst() {
        let mut a = Art::new();
        // Read a record's line: cached.
        let (d, w) = a.read_line(ON, ODO, || line(0x42));
        assert_eq!((d, w), (line(0x42), 5_000));
        assert_eq!(a.read_line(ON, ODO, || line(0x42)), (line(0x42), 0));
        // The sector is erased: the array reads 0xFF, the cache still the record.
        a.erased(0xC_0000, 0xE_0000);
        assert_eq!(a.dcache.stale_lines(), 1);
        assert_eq!(a.stats.lines_made_stale, 1);
        assert_eq!(a.read_line(ON, ODO, || line(0xFF)).0, line(0x42), "stale");
        assert_eq!(a.stats.stale_hits, 1);
        // DCRST while the cache is enabled: ignored, as on the part.
        assert_eq!(a.write_acr(ON, ON | acr::DCRST), ON);
        assert_eq!(a.stats.resets_refused, 1);
        assert_eq!(a.read_line(ON, ODO, || line(0xFF)).0, line(0x42));
        // Disabled: reads bypass it (the array), but the line is kept.
        let off = ON & !acr::DCEN;
        assert_eq!(a.read_line(off, ODO, || line(0xFF)).0, line(0xFF));
        assert_eq!(a.read_line(ON, ODO, || line(0xFF)).0, line(0x42));
        // Disabled and reset (what the firmware's flush does): gone.
        assert_eq!(a.write_acr(off, off | acr::DCRST), off | acr::DCRST);
        assert_eq!(a.stats.d_resets, 1);
        assert!(a.dcache.is_empty());
        let (d, w) = a.read_line(ON, ODO, || line(0xFF));
        assert_eq!((d, w), (line(0xFF), 5_000), "read from the array again");
    }

    #[test]
    fn an_instruction_line_cached_before_an_erase_stays_stale_until_icrst() {
        let mut a = Art::new();
        let cfg = ON & !acr::PRFTEN;
        a.fetch_block(cfg, 0x0800_8000, 16, 4, 0, 1_000);
        a.fetch_block(cfg, 0x0800_0000, 2, 1, 0, 1_000);
        a.erased(0x8000, 0xC000);
        assert_eq!(a.icache.stale_lines(), 1);
        assert_eq!(a.fetch_block(cfg, 0x0800_8000, 16, 4, 0, 1_000), 0, "a hit");
        assert_eq!(a.stats.stale_hits, 1);
        // ICRST with the cache on is refused; the D-cache's reset leaves it alone.
        a.write_acr(cfg, cfg | acr::ICRST);
        assert_eq!(a.stats.resets_refused, 1);
        let off = cfg & !(acr::ICEN | acr::DCEN);
        a.write_acr(off, off | acr::DCRST);
        assert_eq!(a.icache.stale_lines(), 1);
        a.write_acr(off, off | acr::ICRST);
        assert_eq!(a.stats.i_resets, 1);
        assert_eq!(a.icache.stale_lines(), 0);
        a.fetch_block(cfg, 0x0800_0000, 2, 1, 0, 1_000);
        assert_eq!(a.fetch_block(cfg, 0x0800_8000, 16, 4, 0, 1_000), 5_000);
        assert_eq!(a.stats.stale_hits, 1);
    }

    #[test]
    fn an_erase_counts_as_flushed_once_both_caches_were_reset() {
        let off = ON & !(acr::ICEN | acr::DCEN);
        let mut a = Art::new();
        a.erased(0xC_0000, 0xE_0000);
        assert_eq!(a.erases_unflushed(), 1, "not flushed yet");
        a.write_acr(off, off | acr::DCRST);
        assert_eq!(
            a.erases_unflushed(),
            1,
            "the instruction cache still wants it"
        );
        a.write_acr(off, off | acr::ICRST);
        assert_eq!(a.erases_unflushed(), 0);
        // The next erase without a flush, then a reset (it empties the caches, but the
        // core ran on them meanwhile): counted once.
        a.erased(0xE_0000, 0x10_0000);
        a.reset();
        assert_eq!(a.erases_unflushed(), 1);
        assert_eq!(a.stats.erases, 2);
        // A reset refused (caches enabled) does not count as a flush.
        a.erased(0xC_0000, 0xE_0000);
        a.write_acr(ON, ON | acr::ICRST | acr::DCRST);
        assert_eq!(a.erases_unflushed(), 2);
    }

    #[test]
    fn a_chip_that_ignores_the_resets_keeps_the_stale_line() {
        let mut a = Art::new();
        a.ignore_cache_resets = true;
        a.read_line(ON, ODO, || line(0x42));
        a.erased(0xC_0000, 0xE_0000);
        let off = ON & !(acr::DCEN | acr::ICEN);
        a.write_acr(off, off | acr::DCRST | acr::ICRST);
        assert_eq!(a.read_line(ON, ODO, || line(0xFF)).0, line(0x42));
        assert_eq!(a.erases_unflushed(), 1);
    }

    #[test]
    fn a_program_writes_through_to_a_cached_line() {
        let mut a = Art::new();
        a.read_line(ON, ODO, || line(0xFF));
        // The array holds 0x12 0x34 there now.
        a.programmed(0xC_0004, &[0x12, 0x34]);
        let d = a.read_line(ON, ODO, || None).0.unwrap();
        assert_eq!(&d[3..7], &[0xFF, 0x12, 0x34, 0xFF]);
    }
}
