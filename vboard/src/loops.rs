//! Polling loops of the running image, found and skipped on the engine (the analysis
//! itself, without the engine: [`crate::skip`]).
//!
//! The block hook (`cpu.rs`) hands every block the core is about to execute to
//! [`on_block`] before charging it:
//!
//! 1. **Found**: the last blocks repeat with a period of 1 to [`MAX_PERIOD`] blocks,
//!    twice in a row. The registers, the flags, the cycle count, the accelerator's
//!    state and the position in the board's access log are noted at the head (a
//!    *watch*).
//! 2. **Checked**: one iteration later, back at the head, the iteration just run is
//!    executed again by [`crate::skip::execute`] from the noted registers, with the
//!    peripheral values the log says it read: its registers and flags must be what the
//!    engine has now, its accesses those of the log, its cost (milli-cycles, every
//!    block's) the same as the iteration before, the accelerator's state repeated
//!    ([`crate::periph::art::Art::loop_repeats`]).
//! 3. **Predicted**: the next iteration from the registers now, with what the models
//!    say a read will return ([`crate::soc::Soc::peek`]) and until when, the cycle
//!    counter as a value of its own: it must leave every register and flag it reads as
//!    it found them ([`crate::skip::is_fixpoint`]).
//! 4. **Jumped**: over `K` iterations, `K` the largest for which every block of every
//!    skipped iteration starts before the board's next event (and before the event a
//!    write would bring forward), every read happens before the instant its register
//!    may change, and the cycle counter stays inside the interval on which the path is
//!    the same. Instructions, cycles, wait states, the per-exception counts, the
//!    accelerator's counters and caches, the reads and writes counted, the watchdog's
//!    reloads (each with its time) and the registers of the last skipped iteration are
//!    as the engine would have left them; the engine stops and starts again at the head,
//!    where the iteration that sees the change runs for real.
//!
//! `--no-skip` ([`Loops::enabled`] false) runs every iteration; `vboard/tests/skip.rs`
//! proves the two give the same bit for bit.

use std::collections::HashMap;

use unicorn_engine::{RegisterARM, Unicorn};

use crate::periph::art::{Art, LoopMark};
use crate::skip::{self, Abort, Block, Env, Loaded, Outcome};
use crate::soc::{IoRec, Soc, IO_LOG};

/// Blocks remembered.
const RING: usize = 16;
/// Longest loop, blocks.
pub const MAX_PERIOD: usize = 4;
/// Fewest instructions a jump must save (below, the check costs more than it saves).
const MIN_SAVED_INSNS: u64 = 400;

/// The watchdog's key register (a reload: `0xAAAA`).
const IWDG_KR: u32 = 0x4000_3000;
/// `DWT_CYCCNT`.
const CYCCNT: u32 = 0xE000_1004;

#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Seen {
    addr: u32,
    size: u32,
    mc: u64,
    insns: u64,
}

#[derive(Clone, Debug)]
struct Watch {
    head: u32,
    period: usize,
    regs: [u32; 15],
    nzcv: u32,
    mc: u64,
    io_seq: u64,
    art: LoopMark,
}

#[derive(Clone, Debug)]
struct Plan {
    blocks: Vec<(u32, u32)>,
    bytes: Vec<u8>,
    decoded: Option<Vec<Block>>,
}

/// Holds on loops recently looked at, by head (a small direct-mapped table).
const HOLDS: usize = 256;

/// A loop's head not looked at again before `until` (milli-cycles): after `rejects`
/// refusals in a row (not a polling loop: seldom), or `not_now` checks that found it
/// not the time (an event close, its cost settling: soon).
#[derive(Clone, Copy, Debug, Default)]
struct Hold {
    head: u32,
    until: u64,
    rejects: u32,
    not_now: u32,
}

/// What the skipping did, for reports.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct LoopStats {
    /// Jumps.
    pub skips: u64,
    /// Iterations skipped.
    pub iterations: u64,
    /// Instructions skipped.
    pub insns: u64,
    /// Checks whose prediction of an iteration the engine had just run disagreed with
    /// it (a fault of the analysis: the loop is not skipped).
    pub mismatches: u64,
}

/// The loop finder's state (in the SoC, where the block hook reaches it).
#[derive(Clone, Debug, Default)]
pub struct Loops {
    /// Skip polling loops (`--no-skip`: false).
    pub enabled: bool,
    ring: [Seen; RING],
    pos: usize,
    len: usize,
    watch: Option<Watch>,
    plans: HashMap<u32, Plan>,
    holds: Vec<Hold>,
    /// Addresses of instructions a debugging hook counts (`Board::watch_pc`): a loop
    /// that holds one is never skipped.
    pub watched_pcs: Vec<u32>,
    /// Counters.
    pub stats: LoopStats,
}

impl Loops {
    /// The engine starts a run: what was seen before is forgotten (the models may have
    /// moved on between two runs).
    pub fn restart(&mut self) {
        self.len = 0;
        self.watch = None;
    }

    fn hold(&mut self, head: u32) -> &mut Hold {
        if self.holds.is_empty() {
            self.holds = vec![Hold::default(); HOLDS];
        }
        let h = &mut self.holds[(head as usize >> 1) % HOLDS];
        if h.head != head {
            *h = Hold {
                head,
                ..Hold::default()
            };
        }
        h
    }

    fn push(&mut self, s: Seen) {
        self.ring[self.pos] = s;
        self.pos = (self.pos + 1) % RING;
        self.len = (self.len + 1).min(RING);
    }

    /// The block `back` places before the newest (0: the newest).
    fn at(&self, back: usize) -> Seen {
        self.ring[(self.pos + RING - 1 - back) % RING]
    }

    /// Whether the newest block's address is that of one of the `MAX_PERIOD` blocks
    /// before it, with two periods seen: [`Loops::period`]'s first test, for every period.
    #[inline]
    fn head_repeats(&self) -> bool {
        let cur = self.at(0).addr;
        (1..=MAX_PERIOD).any(|p| 2 * p < self.len && self.at(p).addr == cur)
    }

    /// The loop's period if the newest block closes two equal iterations.
    fn period(&self) -> Option<usize> {
        let cur = self.at(0);
        (1..=MAX_PERIOD).find(|&p| {
            2 * p < self.len
                && self.at(p).addr == cur.addr
                && (0..=p).all(|i| {
                    let (a, b) = (self.at(i), self.at(i + p));
                    a.addr == b.addr && a.size == b.size
                })
        })
    }
}

/// `VBOARD_LOOPS_DEBUG` set: why each loop found is not skipped, on stderr.
fn debug() -> bool {
    static ON: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    *ON.get_or_init(|| std::env::var_os("VBOARD_LOOPS_DEBUG").is_some())
}

fn reg(uc: &Unicorn<'_, Soc>, r: RegisterARM) -> u32 {
    uc.reg_read(r).unwrap_or(0) as u32
}

const REGS: [RegisterARM; 15] = [
    RegisterARM::R0,
    RegisterARM::R1,
    RegisterARM::R2,
    RegisterARM::R3,
    RegisterARM::R4,
    RegisterARM::R5,
    RegisterARM::R6,
    RegisterARM::R7,
    RegisterARM::R8,
    RegisterARM::R9,
    RegisterARM::R10,
    RegisterARM::R11,
    RegisterARM::R12,
    RegisterARM::SP,
    RegisterARM::LR,
];

fn regs(uc: &Unicorn<'_, Soc>) -> [u32; 15] {
    REGS.map(|r| reg(uc, r))
}

/// The flags (bits 31–28) and whether an IT block is in progress.
fn flags(uc: &Unicorn<'_, Soc>) -> (u32, bool) {
    let nzcv = reg(uc, RegisterARM::APSR_NZCV) & 0xF000_0000;
    let xpsr = reg(uc, RegisterARM::XPSR);
    (nzcv, xpsr & 0x0600_FC00 != 0)
}

fn readable(addr: u32, size: u8) -> bool {
    let end = addr.wrapping_add(u32::from(size));
    let within = |lo: u32, hi: u32| addr >= lo && end <= hi && end > addr;
    within(0x2000_0000, 0x2002_0000)
        || within(0x1000_0000, 0x1001_0000)
        || within(
            crate::periph::flash::FLASH_BASE,
            crate::periph::flash::ODOMETER_BASE,
        )
        || within(
            0,
            crate::periph::flash::ODOMETER_BASE - crate::periph::flash::FLASH_BASE,
        )
        || within(0x1FFF_0000, 0x1FFF_8000)
}

fn mem(uc: &Unicorn<'_, Soc>, addr: u32, size: u8) -> Result<u32, Abort> {
    if !readable(addr, size) {
        return Err(Abort("a load outside RAM and the code flash"));
    }
    let mut b = [0u8; 4];
    uc.mem_read(u64::from(addr), &mut b[..size as usize])
        .map_err(|_| Abort("memory unreadable"))?;
    Ok(u32::from_le_bytes(b))
}

fn peripheral(addr: u32) -> bool {
    (0x4000_0000..0x4008_0000).contains(&addr)
        || (0x5000_0000..0x5006_1000).contains(&addr)
        || (0xE000_0000..0xE010_0000).contains(&addr)
}

/// The iteration the engine just ran, replayed from the access log.
struct Replay<'a, 'u> {
    uc: &'a Unicorn<'u, Soc>,
    log: Vec<IoRec>,
    next: usize,
}

impl Env for Replay<'_, '_> {
    fn load(&mut self, addr: u32, size: u8, _blk: usize) -> Result<Loaded, Abort> {
        if !peripheral(addr) {
            return mem(self.uc, addr, size).map(Loaded::Val);
        }
        let r = self
            .log
            .get(self.next)
            .ok_or(Abort("a read the log lacks"))?;
        self.next += 1;
        if r.write || r.addr != addr || r.size != size {
            return Err(Abort("a read the log has otherwise"));
        }
        Ok(Loaded::Val(r.value))
    }

    fn store(&mut self, addr: u32, size: u8, value: u32, _blk: usize) -> Result<(), Abort> {
        if !peripheral(addr) {
            return Err(Abort("a store to memory"));
        }
        let r = self
            .log
            .get(self.next)
            .ok_or(Abort("a write the log lacks"))?;
        self.next += 1;
        if !r.write || r.addr != addr || r.size != size || r.value != value {
            return Err(Abort("a write the log has otherwise"));
        }
        Ok(())
    }
}

/// A read the prediction depends on: its block, and until when its value holds (ps).
#[derive(Clone, Copy, Debug)]
struct Held {
    blk: usize,
    until_ps: u64,
}

/// The next iteration as the models say it will go.
struct Predict<'a, 'u> {
    uc: &'a Unicorn<'u, Soc>,
    /// Milli-cycle count of each block's accesses (after the block's charge).
    access_mc: Vec<u64>,
    held: Vec<Held>,
    /// The block of each counter read.
    syms: Vec<usize>,
    bus_reads: u64,
    /// Watchdog reloads: the block and the store's size.
    reloads: Vec<(usize, u8)>,
}

impl Env for Predict<'_, '_> {
    fn load(&mut self, addr: u32, size: u8, blk: usize) -> Result<Loaded, Abort> {
        let soc = self.uc.get_data();
        if addr == CYCCNT {
            let at = *self.access_mc.get(blk).ok_or(Abort("no such block"))?;
            let c = soc.cyccnt_at(at / 1_000);
            if !soc.cyccnt_counting() {
                return Ok(Loaded::Val(c));
            }
            if size != 4 {
                return Err(Abort("a part of the cycle counter"));
            }
            self.syms.push(blk);
            return Ok(Loaded::Cycles(c));
        }
        if !peripheral(addr) {
            return mem(self.uc, addr, size).map(Loaded::Val);
        }
        let (v, until_ps) = soc
            .peek(addr, size as usize)
            .ok_or(Abort("a register that may change with any read"))?;
        if addr < 0xE000_0000 {
            self.bus_reads += 1;
        }
        self.held.push(Held { blk, until_ps });
        Ok(Loaded::Val(v))
    }

    fn store(&mut self, addr: u32, size: u8, value: u32, blk: usize) -> Result<(), Abort> {
        if addr == IWDG_KR && size >= 2 && value & 0xFFFF == 0xAAAA {
            self.reloads.push((blk, size));
            return Ok(());
        }
        Err(Abort("a store other than a watchdog reload"))
    }
}

/// The first `j` at which `start + j·step >= limit` (0 if already).
fn first_reaching(start: u64, step: u64, limit: u64) -> u64 {
    if limit <= start {
        0
    } else {
        (limit - start).div_ceil(step.max(1))
    }
}

/// How many whole iterations, the first from its head at `mc_b`, `d` milli-cycles each,
/// its last block starting `last_start` (in the first), end before `event_mc`: every
/// block starts before it **and every read is done before it** (a block's reads come
/// after its charge, up to the next iteration's head; counting block starts only, the
/// skip took one iteration too many whenever the event fell in the last block, and the
/// skipping run differed from `--no-skip` by one iteration: 11 instructions of the
/// sector erase's wait under the ART model).
fn whole_iterations_before(mc_b: u64, d: u64, last_start: u64, event_mc: u64) -> u64 {
    first_reaching(last_start.max(mc_b + d), d, event_mc)
}

/// The largest gap between consecutive times of `count` events `d_mc` milli-cycles
/// apart from `m0`, on a clock at `(base_ps, base_mc, hz)` (the times are
/// `base_ps + (mc - base_mc)·10^9 / hz`, rounded down, as [`crate::time::Clock`] has
/// them).
fn max_gap_ps(base: (u64, u64, u64), m0: u64, d_mc: u64, count: u64) -> u64 {
    if count < 2 {
        return 0;
    }
    let (_, base_mc, hz) = base;
    let hz = u128::from(hz.max(1));
    let step = u128::from(d_mc) * 1_000_000_000;
    let (q, s) = ((step / hz) as u64, step % hz);
    if s == 0 {
        return q;
    }
    // A gap is q + 1 when the remainder wraps; it wraps at least once in every
    // ceil(hz / s) steps.
    let mut r = (u128::from(m0.saturating_sub(base_mc)) * 1_000_000_000) % hz;
    let steps = (count - 1).min((hz / s) as u64 + 2);
    for _ in 0..steps {
        if r + s >= hz {
            return q + 1;
        }
        r = (r + s) % hz;
    }
    q
}

/// The block at `addr` (`size` bytes, `insns` instructions) is about to run: note it,
/// and skip the loop it closes if it is a polling loop. `true`: skipped (the engine is
/// stopped; the block is not to be charged).
#[inline]
pub fn on_block(uc: &mut Unicorn<'_, Soc>, addr: u32, size: u32, insns: u64) -> bool {
    let s = uc.get_data_mut();
    let mc = s.clock.mc();
    s.loops.push(Seen {
        addr,
        size,
        mc,
        insns,
    });
    if s.loops.len < 3 {
        return false;
    }
    // Most blocks close no loop: their address is not among the last MAX_PERIOD blocks'
    // (the first test of `period`). Decided here, inlined into the block hook; the rest
    // out of line (a sixth of a flooded run went to this function's entry and exit).
    if !s.loops.head_repeats() {
        s.loops.watch = None;
        return false;
    }
    on_repeat(uc, addr, mc)
}

/// [`on_block`] where the newest block's address repeats: a loop may close here.
#[inline(never)]
fn on_repeat(uc: &mut Unicorn<'_, Soc>, addr: u32, mc: u64) -> bool {
    let s = uc.get_data_mut();
    let Some(p) = s.loops.period() else {
        s.loops.watch = None;
        return false;
    };
    if let Some(h) = s.loops.holds.get((addr as usize >> 1) % HOLDS) {
        if h.head == addr && mc < h.until {
            return false;
        }
    }
    match &s.loops.watch {
        Some(w) if w.head == addr && w.period == p => match attempt(uc, p) {
            Ok(true) => {
                let h = uc.get_data_mut().loops.hold(addr);
                (h.rejects, h.not_now, h.until) = (0, 0, 0);
                return true;
            }
            Ok(false) => {
                if debug() {
                    eprintln!("loop at {addr:#010x} (period {p}): not now");
                }
                // Not yet (the cost settling, an event close): look again soon, later
                // each time in a row (up to about 0.4 ms of cycles).
                let s = uc.get_data_mut();
                let h = s.loops.hold(addr);
                h.not_now += 1;
                h.until = h.until.max(mc + (1_000u64 << h.not_now.min(16)));
                s.loops.watch = None;
                return false;
            }
            Err(why) => {
                if debug() {
                    eprintln!("loop at {addr:#010x} (period {p}): {}", why.0);
                }
                // Not a polling loop (or not one worth skipping): looked at again
                // after 1 µs of cycles, doubling to about a second.
                let s = uc.get_data_mut();
                let h = s.loops.hold(addr);
                h.rejects = (h.rejects + 1).min(20);
                h.until = mc + (168_000u64 << h.rejects);
                s.loops.watch = None;
                return false;
            }
        },
        // Inside the watched loop, between two passes of its head.
        Some(w) if w.period == p && (1..p).any(|i| s.loops.at(i).addr == w.head) => {
            return false;
        }
        _ => {}
    }
    // Watch this iteration.
    let r = regs(uc);
    let (nzcv, in_it) = flags(uc);
    let s = uc.get_data_mut();
    s.loops.watch = (!in_it).then(|| Watch {
        head: addr,
        period: p,
        regs: r,
        nzcv,
        mc,
        io_seq: s.io_seq,
        art: s.flash.art.loop_mark(),
    });
    false
}

/// Back at the head of a watched loop: check, predict, jump. `Ok(false)`: not now (an
/// event too close, the cost still settling); `Err`: not this loop (for a while).
fn attempt(uc: &mut Unicorn<'_, Soc>, p: usize) -> Result<bool, Abort> {
    let s = uc.get_data();
    let w = s.loops.watch.clone().ok_or(Abort("no watch"))?;
    // The iteration just run: blocks and their start, oldest first, then the head now.
    let iter: Vec<Seen> = (0..=p).rev().map(|i| s.loops.at(i)).collect();
    let mc_b = iter[p].mc;
    let d = mc_b - iter[0].mc;
    if iter[0].mc != w.mc || d == 0 {
        return Ok(false);
    }
    // The same cost as the iteration before it (the accelerator settled), block by block.
    if s.loops.len > 2 * p {
        let before: Vec<Seen> = (p..=2 * p).rev().map(|i| s.loops.at(i)).collect();
        for i in 0..=p {
            if iter[i].mc - iter[0].mc != before[i].mc - before[0].mc {
                return Ok(false);
            }
        }
    } else {
        return Ok(false);
    }
    let mark_b = s.flash.art.loop_mark();
    if s.art_timing && !Art::loop_repeats(&w.art, &mark_b, d) {
        return Ok(false);
    }
    let n_iter: u64 = iter[..p].iter().map(|b| b.insns).sum();
    let head = w.head;
    if s.meter.is_some() {
        return Err(Abort("a function is metered"));
    }
    // The loop's code, decoded once.
    let spans: Vec<(u32, u32)> = iter[..p].iter().map(|b| (b.addr, b.size)).collect();
    let mut bytes = Vec::new();
    for &(a, n) in &spans {
        let mut b = vec![0u8; n as usize];
        uc.mem_read(u64::from(a), &mut b)
            .map_err(|_| Abort("code unreadable"))?;
        bytes.extend(b);
    }
    if spans
        .iter()
        .any(|&(a, n)| s.loops.watched_pcs.iter().any(|&w| w >= a && w < a + n))
    {
        return Err(Abort("a watched instruction"));
    }
    let fresh = match s.loops.plans.get(&head) {
        Some(pl) => pl.blocks != spans || pl.bytes != bytes,
        None => true,
    };
    if fresh {
        let mut decoded = Some(Vec::new());
        let mut at = 0usize;
        for &(a, n) in &spans {
            let code = &bytes[at..at + n as usize];
            at += n as usize;
            match (skip::decode_block(code, a), decoded.as_mut()) {
                (Ok(insns), Some(v)) => v.push(Block { addr: a, insns }),
                _ => decoded = None,
            }
        }
        uc.get_data_mut().loops.plans.insert(
            head,
            Plan {
                blocks: spans,
                bytes,
                decoded,
            },
        );
    }
    let s = uc.get_data();
    let plan = s.loops.plans.get(&head).ok_or(Abort("no plan"))?;
    let blocks = plan.decoded.clone().ok_or(Abort("undecodable"))?;
    let regs_b = regs(uc);
    let (nzcv_b, in_it) = flags(uc);
    if in_it {
        return Err(Abort("an IT block at the head"));
    }
    // Check: the iteration just run, replayed from the log.
    let s = uc.get_data();
    let logged = s.io_seq - w.io_seq;
    if logged > IO_LOG as u64 {
        return Err(Abort("more accesses than the log keeps"));
    }
    let log: Vec<IoRec> = (w.io_seq..s.io_seq)
        .map(|q| s.io_log[(q % IO_LOG as u64) as usize])
        .collect();
    let n_log = log.len();
    let mut replay = Replay { uc, log, next: 0 };
    let seen = skip::execute(&blocks, w.regs, w.nzcv, &mut replay);
    let consumed = replay.next;
    let checked = match seen {
        Ok(o) => {
            consumed == n_log
                && o.insns == n_iter
                && o.concrete(&o.sym_vals) == Some((regs_b, nzcv_b))
        }
        Err(why) => return Err(why),
    };
    if !checked && debug() {
        let mut replay = Replay {
            uc,
            log: (w.io_seq..uc.get_data().io_seq)
                .map(|q| uc.get_data().io_log[(q % IO_LOG as u64) as usize])
                .collect(),
            next: 0,
        };
        let o = skip::execute(&blocks, w.regs, w.nzcv, &mut replay);
        eprintln!(
            "check at {head:#010x}: {o:?}\n  a {:x?} {:x}\n  b {regs_b:x?} {nzcv_b:x}\n  log {:x?}",
            w.regs, w.nzcv, replay.log
        );
    }
    if !checked {
        let s = uc.get_data_mut();
        s.loops.stats.mismatches += 1;
        return Err(Abort("the check disagrees with the engine"));
    }
    // Predict the next iteration.
    // The next iteration's accesses, block by block: after the block's charge.
    let access_mc: Vec<u64> = iter[1..]
        .iter()
        .map(|b| mc_b + (b.mc - iter[0].mc))
        .collect();
    let mut pred = Predict {
        uc,
        access_mc: access_mc.clone(),
        held: Vec::new(),
        syms: Vec::new(),
        bus_reads: 0,
        reloads: Vec::new(),
    };
    let o = skip::execute(&blocks, regs_b, nzcv_b, &mut pred)?;
    if !skip::is_fixpoint(&o, &regs_b, nzcv_b) {
        return Err(Abort("not a fixpoint"));
    }
    if o.regs[13] != skip::Val::C(regs_b[13]) {
        return Err(Abort("the stack pointer moves"));
    }
    let (held, syms, bus_reads, reloads) = (pred.held, pred.syms, pred.bus_reads, pred.reloads);
    if reloads.len() > 1 {
        return Err(Abort("two reloads an iteration"));
    }
    // How far: the blocks start before the next event, the reads before their change,
    // the counter inside the path's interval.
    let s = uc.get_data();
    let last_start = mc_b + (iter[p - 1].mc - iter[0].mc);
    let mut next_event_mc = s.next_event_mc;
    if let Some(&(blk, _)) = reloads.first() {
        // A reload moves the watchdog's expiry: the earliest is the first reload's.
        let mut w = s.iwdg.clone();
        let t = s.clock.time_at_mc(access_mc[blk]);
        let _ = w.write(0, 0xAAAA, t);
        if let Some(e) = w.next_event() {
            next_event_mc = next_event_mc.min(s.clock.mc_at(e));
        }
    }
    // The event bounds whole iterations, reads included: a block's reads come after its
    // charge, up to the next iteration's head (`mc_b + d` for the first), so an
    // iteration whose last block *starts* before the event may read after it (a device
    // that answers by the time of the read, the flash's BSY at the erase's end, has
    // changed then: the loop leaves one iteration earlier than the skip assumed).
    let by_event = whole_iterations_before(mc_b, d, last_start, next_event_mc);
    let mut k = by_event;
    for h in &held {
        if h.until_ps != u64::MAX {
            k = k.min(first_reaching(
                access_mc[h.blk],
                d,
                s.clock.mc_at(h.until_ps),
            ));
        }
    }
    for c in &o.constraints {
        let blk = syms[c.sym as usize];
        let m_r = access_mc[blk];
        let c0 = o.sym_vals[c.sym as usize];
        if let Some(dist) = c.holds.exit_distance(c0) {
            let limit = (m_r / 1_000 + dist).saturating_mul(1_000);
            k = k.min(first_reaching(m_r, d, limit));
        }
    }
    // Never past the point where the arithmetic below could overflow.
    k = k.min(1 << 40);
    if debug() {
        let ev = by_event;
        let hs: Vec<(usize, u64, u64, u64)> = held
            .iter()
            .filter(|h| h.until_ps != u64::MAX)
            .map(|h| {
                let kk = first_reaching(access_mc[h.blk], d, s.clock.mc_at(h.until_ps));
                let t_last = s
                    .clock
                    .time_at_mc(access_mc[h.blk] + kk.saturating_sub(1) * d);
                (h.blk, kk, t_last, h.until_ps)
            })
            .collect();
        eprintln!(
            "SKIPK head {head:#x} d {d} k {k} ev {ev} held {hs:?} ncons {}",
            o.constraints.len()
        );
    }
    if k.saturating_mul(n_iter) < MIN_SAVED_INSNS {
        // An event is close (try again after it), or the loop ends soon by itself.
        let bounded_by_loop = k < by_event;
        return if bounded_by_loop {
            Err(Abort("too short to be worth it"))
        } else {
            Ok(false)
        };
    }
    apply(
        uc, &o, &syms, &access_mc, &reloads, bus_reads, mc_b, d, n_iter, k, &w.art, &mark_b,
    )?;
    Ok(true)
}

/// Leave the board as `k` iterations from the head at `mc_b` would have.
#[allow(clippy::too_many_arguments)]
fn apply(
    uc: &mut Unicorn<'_, Soc>,
    o: &Outcome,
    syms: &[usize],
    access_mc: &[u64],
    reloads: &[(usize, u8)],
    bus_reads: u64,
    mc_b: u64,
    d: u64,
    n_iter: u64,
    k: u64,
    art_a: &LoopMark,
    art_b: &LoopMark,
) -> Result<(), Abort> {
    // The last skipped iteration's registers: the counter at its reads.
    let last = (k - 1) * d;
    let soc = uc.get_data();
    let c: Vec<u32> = syms
        .iter()
        .map(|&blk| soc.cyccnt_at((access_mc[blk] + last) / 1_000))
        .collect();
    let (r, nzcv) = o
        .concrete(&c)
        .ok_or(Abort("a register depends on an unknown read"))?;
    let s = uc.get_data_mut();
    if s.art_timing {
        s.flash.art.advance_loop(art_a, art_b, k);
    }
    s.accesses.0 += k * bus_reads;
    let cur = s.current_exc;
    if let Some(x) = s.exc_insns.get_mut(cur) {
        *x += k * n_iter;
    }
    if let Some(x) = s.exc_mc.get_mut(cur) {
        *x += k * d;
    }
    match reloads.first() {
        Some(&(blk, size)) => {
            let w0 = access_mc[blk];
            if k >= 2 {
                let first = s.clock.time_at_mc(w0);
                let last_t = s.clock.time_at_mc(w0 + (k - 2) * d);
                let gap = max_gap_ps(s.clock.base(), w0, d, k - 1);
                s.feeds.add_run(first, last_t, k - 1, gap);
                s.iwdg.reloads += k - 1;
                s.accesses.1 += k - 1;
            }
            // The last one for real, at its instant.
            let to_write = w0 + last - mc_b;
            s.clock.skip(0, to_write);
            s.bus_write(IWDG_KR, size as usize, 0xAAAA);
            s.clock.skip(k * n_iter, k * d - to_write);
        }
        None => s.clock.skip(k * n_iter, k * d),
    }
    s.loops.stats.skips += 1;
    s.loops.stats.iterations += k;
    s.loops.stats.insns += k * n_iter;
    s.loops.restart();
    s.stop = true;
    for (i, &rg) in REGS.iter().enumerate() {
        if i != 13 {
            let _ = uc.reg_write(rg, u64::from(r[i]));
        }
    }
    let _ = uc.reg_write(RegisterARM::APSR_NZCV, u64::from(nzcv));
    let _ = uc.emu_stop();
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_largest_gap_is_the_one_the_clock_rounds_up() {
        // 168 MHz, 8 cycles an iteration: 47.619… ns, so 47 619 or 47 620 ps.
        let base = (0, 0, 168_000_000);
        let times: Vec<u64> = (0..50u64)
            .map(|j| ((j * 8_000) as u128 * 1_000_000_000 / 168_000_000) as u64)
            .collect();
        let want = times.windows(2).map(|w| w[1] - w[0]).max().unwrap();
        assert_eq!(max_gap_ps(base, 0, 8_000, 50), want);
        assert_eq!(want, 47_620);
        // An exact period: one gap.
        assert_eq!(max_gap_ps((0, 0, 1_000_000), 0, 1_000, 10), 1_000_000);
        // Two events whose gap does not round up.
        assert_eq!(max_gap_ps(base, 0, 8_000, 2), times[1] - times[0]);
        assert_eq!(max_gap_ps(base, 0, 8_000, 1), 0);
    }

    #[test]
    fn an_iteration_whose_last_block_read_after_the_event_was_skipped() {
        // 11 cycles an iteration, its last block starting 8 cycles in: the second
        // iteration's last block starts at 19 000 mc, before an event at 21 000, but
        // its reads run to 22 000, after it. Only the first iteration is skipped.
        assert_eq!(whole_iterations_before(0, 11_000, 8_000, 21_000), 1);
        // The old count (block starts only) took both.
        assert_eq!(first_reaching(8_000, 11_000, 21_000), 2);
        // An event after both iterations' ends: both.
        assert_eq!(whole_iterations_before(0, 11_000, 8_000, 22_001), 2);
        assert_eq!(whole_iterations_before(0, 11_000, 8_000, 22_000), 1);
        // An event before the first iteration ends: none.
        assert_eq!(whole_iterations_before(0, 11_000, 8_000, 10_000), 0);
    }

    #[test]
    fn the_first_iteration_to_reach_a_limit() {
        assert_eq!(first_reaching(100, 10, 100), 0);
        assert_eq!(first_reaching(100, 10, 101), 1);
        assert_eq!(first_reaching(100, 10, 110), 1);
        assert_eq!(first_reaching(100, 10, 111), 2);
    }
}
