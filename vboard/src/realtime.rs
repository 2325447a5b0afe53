//! The control step's timing, the watchdog's feeding and the E-STOP's reaction,
//! measured in the emulator rather than reported by the firmware.
//!
//! * **Control period**: the NVIC model notes every entry of the control task's
//!   interrupt (TIM2, IRQ 28: [`crate::periph::nvic::EntryLog`]); the intervals between
//!   consecutive entries are the periods the control step actually got.
//! * **Control entry latency**: the NVIC model also notes when that interrupt became
//!   pending (not pending → pending: TIM2's update raising its line, a line still
//!   asserted at exception return, a software pend through ISPR or STIR); from each pend
//!   to the entry that serves it is how long the control step waited — for lower-priority
//!   work holding its resource (an RTIC lock raises BASEPRI), for higher-priority tasks,
//!   for interrupts masked. The pend is the NVIC's: up to one translated block after the
//!   timer's update while the core runs (interrupts are taken at block boundaries).
//! * **Watchdog feeds**: the board notes every reload of the IWDG model (`KR` = 0xAAAA,
//!   [`Feeds`]); a gap longer than three sample periods is a missed feed. Reloads less
//!   than [`BURST_PS`] apart are kept as one burst (first, last, count, largest gap):
//!   the flash erase's wait reloads every few cycles, tens of millions of times a
//!   sector; within a burst its largest gap stands for every gap it holds.
//! * Both are judged **over the time anything moves**: an interval counts when it
//!   overlaps a window in which the propulsion driver is enabled (EN low) or a lock
//!   bridge input is high, as the pins show it. Boot, the BOR programming of a first
//!   boot, a sector erase at rest and the idle machine are not judged: nothing can hurt
//!   anyone then, and the firmware is allowed to be slow.
//! * A reset ends a segment: the interval from the last event before it to the reset
//!   counts (a watchdog reset after a starved step is a missed feed), the one from the
//!   reset to the first event after it does not (that is the boot). The scene's end
//!   closes the last segment the same way. A pend before a reset is never paired with an
//!   entry after it (the reset cleared it); a pend still waiting at the scene's end is
//!   not counted (the control period's tail shows a step that stopped).
//! * **E-STOP**: for every edge of the E-STOP input while anything moved, the time from
//!   the edge to EN high (if the driver was on) and to both lock bridge inputs low (if
//!   the lock was driven), on the pins; the longer of the two.

use crate::soc::Edge;
use crate::world::Signal;

/// Picoseconds per millisecond.
const PS_PER_MS: u64 = 1_000_000_000;

/// When something moved: `[start, end)` windows in ps, in time order, from the recorded
/// pin edges (EN low, or a lock bridge input high); a window still open at `end_ps`
/// ends there.
pub fn moving_windows(edges: &[Edge], end_ps: u64) -> Vec<(u64, u64)> {
    let mut en_on = false;
    let (mut in1, mut in2) = (false, false);
    let mut since: Option<u64> = None;
    let mut out = Vec::new();
    for e in edges {
        match e.signal {
            Signal::EnN => en_on = !e.high,
            Signal::LockIn1 => in1 = e.high,
            Signal::LockIn2 => in2 = e.high,
            _ => continue,
        }
        let moving = en_on || in1 || in2;
        match (moving, since) {
            (true, None) => since = Some(e.t_ps),
            (false, Some(t0)) => {
                if e.t_ps > t0 {
                    out.push((t0, e.t_ps));
                }
                since = None;
            }
            _ => {}
        }
    }
    if let Some(t0) = since {
        if end_ps > t0 {
            out.push((t0, end_ps));
        }
    }
    out
}

/// Whether `[a, b]` overlaps any of `windows`.
fn overlaps(windows: &[(u64, u64)], a: u64, b: u64) -> bool {
    windows.iter().any(|&(s, e)| a < e && b > s)
}

/// The intervals between consecutive `events` (ps, in time order) that overlap
/// `windows`, segment by segment: `boundaries` (resets, in time order) end a segment
/// — the interval from its last event to the boundary counts, the one from the boundary
/// to the next event does not — and `end_ps` ends the last one.
pub fn judged_intervals(
    events: &[u64],
    boundaries: &[u64],
    end_ps: u64,
    windows: &[(u64, u64)],
) -> Vec<u64> {
    let mut out = Vec::new();
    let mut seg_ends: Vec<u64> = boundaries.to_vec();
    seg_ends.push(end_ps);
    let mut i = 0;
    let mut seg_start = 0u64;
    for &seg_end in &seg_ends {
        let mut last: Option<u64> = None;
        while i < events.len() && events[i] <= seg_end {
            let t = events[i];
            if t >= seg_start {
                if let Some(p) = last {
                    if overlaps(windows, p, t) {
                        out.push(t - p);
                    }
                }
                last = Some(t);
            }
            i += 1;
        }
        if let Some(p) = last {
            if seg_end > p && overlaps(windows, p, seg_end) {
                out.push(seg_end - p);
            }
        }
        seg_start = seg_end;
    }
    out
}

/// Each entry of an interrupt paired with the pend it served: `(pend, entry)` ps, for
/// `pends` and `entries` in time order. An entry serves the latest pend before it (at
/// equal times the pend comes first; a pend the software cleared is superseded by the
/// next); `boundaries` (resets, in time order) end a segment, and a pend is never paired
/// across one (events at a boundary's time belong to the segment it ends). An entry with
/// no pend in its segment is left out.
pub fn pend_entry_pairs(pends: &[u64], entries: &[u64], boundaries: &[u64]) -> Vec<(u64, u64)> {
    let mut out = Vec::new();
    let (mut i, mut j) = (0, 0);
    for seg_end in boundaries.iter().copied().chain(std::iter::once(u64::MAX)) {
        let mut pend: Option<u64> = None;
        loop {
            let p = pends.get(i).copied().filter(|&t| t <= seg_end);
            let e = entries.get(j).copied().filter(|&t| t <= seg_end);
            match (p, e) {
                (Some(tp), Some(te)) if tp <= te => {
                    pend = Some(tp);
                    i += 1;
                }
                (Some(tp), None) => {
                    pend = Some(tp);
                    i += 1;
                }
                (_, Some(te)) => {
                    if let Some(tp) = pend.take() {
                        out.push((tp, te));
                    }
                    j += 1;
                }
                (None, None) => break,
            }
        }
    }
    out
}

/// Reloads closer than this to the previous one join its burst, ps (1 ms: far below
/// any feed gap that counts, far above the erase's wait loop's reloads).
pub const BURST_PS: u64 = PS_PER_MS;

/// Reloads less than [`BURST_PS`] apart: the first, the last, how many and the largest
/// gap between two of them, ps.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Burst {
    /// First reload.
    pub first: u64,
    /// Last reload.
    pub last: u64,
    /// Reloads.
    pub count: u64,
    /// Largest gap between consecutive reloads in it (0: one reload).
    pub max_gap: u64,
}

/// The watchdog's reloads as bursts, in time order; a reset ends a burst.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct Feeds {
    /// The bursts.
    pub bursts: Vec<Burst>,
    closed: bool,
}

impl Feeds {
    /// A reload at `t_ps`.
    pub fn add(&mut self, t_ps: u64) {
        self.add_run(t_ps, t_ps, 1, 0);
    }

    /// `count` reloads from `first` to `last` whose consecutive gaps are at most
    /// `max_gap` (< [`BURST_PS`]): as `count` calls of [`Feeds::add`] would leave it.
    pub fn add_run(&mut self, first: u64, last: u64, count: u64, max_gap: u64) {
        if count == 0 {
            return;
        }
        match self.bursts.last_mut() {
            Some(b) if !self.closed && first.saturating_sub(b.last) < BURST_PS => {
                b.max_gap = b.max_gap.max(first - b.last).max(max_gap);
                b.last = last;
                b.count += count;
            }
            _ => self.bursts.push(Burst {
                first,
                last,
                count,
                max_gap,
            }),
        }
        self.closed = false;
    }

    /// A reset: the next reload starts a burst of its own.
    pub fn close(&mut self) {
        self.closed = true;
    }

    /// Forget the bursts that ended before `t_ps` (a long `serve` keeps memory bounded);
    /// the last one is kept.
    pub fn forget_before(&mut self, t_ps: u64) {
        let keep_from = self
            .bursts
            .iter()
            .position(|b| b.last >= t_ps)
            .unwrap_or(self.bursts.len())
            .min(self.bursts.len().saturating_sub(1));
        self.bursts.drain(..keep_from);
    }
}

/// The gaps between the watchdog's reloads judged as [`judged_intervals`] judges
/// events, bursts of reloads standing for their reloads: a burst that overlaps
/// `windows` adds its largest internal gap.
pub fn judged_feed_gaps(
    bursts: &[Burst],
    boundaries: &[u64],
    end_ps: u64,
    windows: &[(u64, u64)],
) -> Vec<u64> {
    let mut out = Vec::new();
    let mut seg_ends: Vec<u64> = boundaries.to_vec();
    seg_ends.push(end_ps);
    let mut i = 0;
    let mut seg_start = 0u64;
    for &seg_end in &seg_ends {
        let mut last: Option<u64> = None;
        while i < bursts.len() && bursts[i].first <= seg_end {
            let b = bursts[i];
            if b.first >= seg_start {
                if let Some(p) = last {
                    if overlaps(windows, p, b.first) {
                        out.push(b.first - p);
                    }
                }
                if b.count > 1 && overlaps(windows, b.first, b.last) {
                    out.push(b.max_gap);
                }
                last = Some(b.last);
            }
            i += 1;
        }
        if let Some(p) = last {
            if seg_end > p && overlaps(windows, p, seg_end) {
                out.push(seg_end - p);
            }
        }
        seg_start = seg_end;
    }
    out
}

/// The control step's timing and the watchdog's feeding over the time anything moved.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ControlTiming {
    /// Time anything moved, s (what the figures below are judged over).
    pub moving_s: f64,
    /// Longest interval between entries of the control task's interrupt, ms (`None`:
    /// nothing moved, or no entry).
    pub period_max_ms: Option<f64>,
    /// Intervals longer than the sample period + 1 ms.
    pub late: u64,
    /// Longest time from the control task's interrupt becoming pending to its entry,
    /// among those whose `[pend, entry]` overlaps the time anything moved, µs (`None`:
    /// no such pair).
    pub entry_latency_max_us: Option<f64>,
    /// The same over the whole run (boot, rest, flash erases at rest included), µs.
    pub entry_latency_max_us_all: Option<f64>,
    /// Longest gap between watchdog reloads, ms.
    pub feed_gap_max_ms: Option<f64>,
    /// Gaps between watchdog reloads longer than three sample periods.
    pub feeds_missed: u64,
}

impl ControlTiming {
    /// Judge the control task's `entries`, its `pends` (when its interrupt became
    /// pending) and the watchdog's `reloads` over `windows`, with resets at
    /// `resets` and the scene ending at `end_ps`, for a sample period of `period_ps`.
    pub fn measure(
        entries: &[u64],
        pends: &[u64],
        reloads: &[Burst],
        resets: &[u64],
        end_ps: u64,
        windows: &[(u64, u64)],
        period_ps: u64,
    ) -> Self {
        let steps = judged_intervals(entries, resets, end_ps, windows);
        let feeds = judged_feed_gaps(reloads, resets, end_ps, windows);
        let ms = |ps: u64| ps as f64 / PS_PER_MS as f64;
        let us = |ps: u64| ps as f64 * 1e-6;
        let pairs = pend_entry_pairs(pends, entries, resets);
        let latency = |moving: bool| {
            pairs
                .iter()
                .filter(|&&(p, e)| !moving || overlaps(windows, p, e))
                .map(|&(p, e)| e - p)
                .max()
                .map(us)
        };
        Self {
            moving_s: windows.iter().map(|(a, b)| b - a).sum::<u64>() as f64 * 1e-12,
            period_max_ms: steps.iter().max().map(|&p| ms(p)),
            late: steps.iter().filter(|&&p| p > period_ps + PS_PER_MS).count() as u64,
            entry_latency_max_us: latency(true),
            entry_latency_max_us_all: latency(false),
            feed_gap_max_ms: feeds.iter().max().map(|&p| ms(p)),
            feeds_missed: feeds.iter().filter(|&&g| g > 3 * period_ps).count() as u64,
        }
    }
}

/// For every E-STOP input edge `(time ps, opened)` at which anything moved: the time to
/// EN high (if the driver was on) and to both lock bridge inputs low (if the lock was
/// driven), the longer of the two, µs (`None`: the pins never went off).
pub fn estop_reactions(estop: &[(u64, bool)], edges: &[Edge]) -> Vec<Option<f64>> {
    let mut out = Vec::new();
    for &(t0, _) in estop {
        // The pins' levels just before the edge.
        let (mut en_on, mut in1, mut in2) = (false, false, false);
        for e in edges.iter().take_while(|e| e.t_ps < t0) {
            match e.signal {
                Signal::EnN => en_on = !e.high,
                Signal::LockIn1 => in1 = e.high,
                Signal::LockIn2 => in2 = e.high,
                _ => {}
            }
        }
        if !(en_on || in1 || in2) {
            continue;
        }
        let mut off_at: Option<u64> = None;
        let mut en_off = !en_on;
        let (mut l1, mut l2) = (in1, in2);
        for e in edges.iter().skip_while(|e| e.t_ps < t0) {
            match e.signal {
                Signal::EnN => en_off = e.high,
                Signal::LockIn1 => l1 = e.high,
                Signal::LockIn2 => l2 = e.high,
                _ => continue,
            }
            if en_off && !l1 && !l2 {
                off_at = Some(e.t_ps);
                break;
            }
        }
        out.push(off_at.map(|t| (t - t0) as f64 * 1e-6));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = PS_PER_MS;

    fn edge(t_ms: u64, signal: Signal, high: bool) -> Edge {
        Edge {
            t_ps: t_ms * MS,
            signal,
            high,
        }
    }

    #[test]
    fn windows_follow_en_and_the_lock_bridge() {
        let edges = [
            edge(1, Signal::EnN, true), // reset level: off
            edge(10, Signal::LockIn2, true),
            edge(20, Signal::EnN, false),
            edge(25, Signal::LockIn2, false),
            edge(40, Signal::EnN, true),
            edge(50, Signal::EnN, false),
        ];
        assert_eq!(
            moving_windows(&edges, 60 * MS),
            vec![(10 * MS, 40 * MS), (50 * MS, 60 * MS)]
        );
    }

    #[test]
    fn a_late_step_and_a_missed_feed_are_counted_only_while_moving() {
        let period = 12_500_000_000; // 12.5 ms
                                     // Steps every 12.5 ms, one 30 ms gap at rest and one 15 ms gap while moving.
        let mut entries: Vec<u64> = (0..10).map(|k| k * period).collect();
        let t = entries[9] + 30 * MS; // at rest
        entries.push(t);
        entries.push(t + period);
        entries.push(t + period + 15 * MS); // moving from t + period on
        let windows = [(t + period, t + period + 100 * MS)];
        let end = t + period + 100 * MS;
        // Feeds with the steps, but one of 40 ms while moving.
        let mut feeds = Feeds::default();
        for r in [t + period, t + period + 40 * MS, t + period + 50 * MS] {
            feeds.add(r);
        }
        let m = ControlTiming::measure(&entries, &[], &feeds.bursts, &[], end, &windows, period);
        // The 30 ms gap was at rest; the tail (85 ms to the end) counts: the step stopped.
        assert_eq!(m.period_max_ms, Some(85.0));
        assert_eq!(m.late, 2, "15 ms and the 85 ms tail: {m:?}");
        assert_eq!(m.feeds_missed, 2, "40 ms and the 50 ms tail: {m:?}");
        assert_eq!(m.feed_gap_max_ms, Some(50.0));
        assert!((m.moving_s - 0.1).abs() < 1e-9);
    }

    #[test]
    fn sparse_feeds_are_judged_as_events_and_a_burst_by_its_largest_gap() {
        let windows = [(0, 1_000 * MS)];
        let times: Vec<u64> = (1..=20).map(|k| k * 12 * MS + k * 7).collect();
        let mut feeds = Feeds::default();
        times.iter().for_each(|&t| feeds.add(t));
        assert_eq!(feeds.bursts.len(), 20);
        for resets in [&[][..], &[100 * MS]] {
            assert_eq!(
                judged_feed_gaps(&feeds.bursts, resets, 1_000 * MS, &windows),
                judged_intervals(&times, resets, 1_000 * MS, &windows)
            );
        }
        // A burst of reloads 48 ns apart between two feeds 12 ms apart.
        let mut f = Feeds::default();
        f.add(0);
        for k in 0..1_000u64 {
            f.add(12 * MS + k * 48_000 + k % 3);
        }
        f.add(30 * MS);
        assert_eq!(f.bursts.len(), 3);
        assert_eq!(f.bursts[1].count, 1_000);
        assert_eq!(f.bursts[1].max_gap, 48_001);
        let gaps = judged_feed_gaps(&f.bursts, &[], 40 * MS, &windows);
        assert_eq!(gaps[0], 12 * MS);
        assert_eq!(gaps[1], 48_001);
        assert_eq!(*gaps.iter().max().unwrap(), 30 * MS - f.bursts[1].last);
        // A run added at once is the same as its reloads one by one; a reset closes.
        let mut g = Feeds::default();
        g.add(0);
        g.add_run(12 * MS, 12 * MS + 999 * 48_000, 1_000, 48_001);
        g.add(30 * MS);
        assert_eq!(g, f);
        g.close();
        g.add(30 * MS + 10);
        assert_eq!(g.bursts.len(), 4);
    }

    #[test]
    fn a_reset_ends_a_segment_and_the_boot_after_it_is_not_judged() {
        let windows = [(0, 1_000 * MS)];
        // Entries every 10 ms until 100 ms, a reset at 105 ms, the boot until 600 ms.
        let mut entries: Vec<u64> = (0..=10).map(|k| k * 10 * MS).collect();
        entries.extend((60..=70).map(|k| k * 10 * MS));
        let got = judged_intervals(&entries, &[105 * MS], 700 * MS, &windows);
        assert!(got.iter().all(|&g| g <= 10 * MS), "{got:?}");
        assert!(got.contains(&(5 * MS)), "to the reset: {got:?}");
    }

    const US: u64 = 1_000_000;

    #[test]
    fn an_entry_serves_the_latest_pend_before_it_and_never_one_across_a_reset() {
        // p 10 → e 12; p 20, p 21 (the first cleared) → e 25; p 30 → reset 31 → e 40
        // (the boot's: no pend since the reset); p 50 = e 50 (pend first at equal times);
        // p 60 at the reset 60 belongs before it, e 61 has no pend after the reset.
        let pends = [10, 20, 21, 30, 50, 60].map(|t| t * US);
        let entries = [12, 25, 40, 50, 61].map(|t| t * US);
        let pairs = pend_entry_pairs(&pends, &entries, &[31 * US, 60 * US]);
        assert_eq!(
            pairs,
            vec![(10 * US, 12 * US), (21 * US, 25 * US), (50 * US, 50 * US)]
        );
        // No reset: the pend at 30 is served at 40, the one at 60 at 61.
        let pairs = pend_entry_pairs(&pends, &entries, &[]);
        assert!(pairs.contains(&(30 * US, 40 * US)), "{pairs:?}");
        assert!(pairs.contains(&(60 * US, 61 * US)), "{pairs:?}");
        // A pend with no entry after it is not a pair.
        assert_eq!(pend_entry_pairs(&[5 * US], &[US], &[]), vec![]);
    }

    #[test]
    fn entry_latency_is_judged_while_moving_and_over_the_whole_run() {
        let period = 12_500_000_000;
        // A 300 µs wait at rest (an idle lock), then a moving window from 100 ms: waits of
        // 20 µs, 80 µs (pend 10 µs before the window opens: overlaps, counts), 50 µs.
        let pends = [0, 50 * MS, 100 * MS - 10 * US, 120 * MS, 200 * MS];
        let entries = [
            20 * US,
            50 * MS + 300 * US,
            100 * MS + 70 * US,
            120 * MS + 50 * US,
            // A reset at 150 ms: the pend at 200 ms is the boot's next, entered 1 ms later
            // but outside the window (ends at 150 ms).
            201 * MS,
        ];
        let windows = [(100 * MS, 150 * MS)];
        let m = ControlTiming::measure(
            &entries,
            &pends,
            &[],
            &[150 * MS],
            250 * MS,
            &windows,
            period,
        );
        assert_eq!(m.entry_latency_max_us, Some(80.0), "{m:?}");
        assert_eq!(m.entry_latency_max_us_all, Some(1_000.0), "{m:?}");
        // Nothing moved: no figure while moving, the whole run's still.
        let m = ControlTiming::measure(&entries, &pends, &[], &[], 250 * MS, &[], period);
        assert_eq!(m.entry_latency_max_us, None);
        assert_eq!(m.entry_latency_max_us_all, Some(1_000.0));
        // A pend before the reset entered after it is not a latency (the reset cleared
        // it; the entry after the reset is the boot's).
        let m = ControlTiming::measure(
            &[160 * MS],
            &[140 * MS],
            &[],
            &[150 * MS],
            250 * MS,
            &[(0, 250 * MS)],
            period,
        );
        assert_eq!(
            (m.entry_latency_max_us, m.entry_latency_max_us_all),
            (None, None)
        );
    }

    #[test]
    fn estop_reaction_is_measured_only_when_something_moved() {
        let edges = [
            edge(0, Signal::EnN, true),
            edge(10, Signal::EnN, false), // driver on
            edge(10, Signal::LockIn1, true),
            Edge {
                t_ps: 20 * MS + 3_000_000, // 3 µs after the edge
                signal: Signal::EnN,
                high: true,
            },
            Edge {
                t_ps: 20 * MS + 5_000_000, // 5 µs
                signal: Signal::LockIn1,
                high: false,
            },
        ];
        let r = estop_reactions(&[(20 * MS, true), (30 * MS, false)], &edges);
        assert_eq!(r.len(), 1, "the closing edge at rest is not judged");
        assert!((r[0].unwrap() - 5.0).abs() < 1e-9, "{r:?}");
    }
}
