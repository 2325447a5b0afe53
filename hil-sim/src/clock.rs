//! Virtual time. Nothing in the simulator sleeps: time advances only when the scene
//! runner (or a `DelayNs` call from the code under test) advances it.

use std::cell::Cell;
use std::rc::Rc;

use docking_logic::hal::Monotonic;

/// A shared virtual clock, nanoseconds since simulated power-on.
#[derive(Clone, Debug, Default)]
pub struct SimClock {
    now_ns: Rc<Cell<u64>>,
}

impl SimClock {
    /// A clock at t = 0.
    pub fn new() -> Self {
        Self::default()
    }

    /// Current virtual time, ns.
    pub fn now_ns(&self) -> u64 {
        self.now_ns.get()
    }

    /// Current virtual time, s.
    pub fn now_s(&self) -> f64 {
        self.now_ns.get() as f64 * 1e-9
    }

    /// Advance by `dt_ns`.
    pub fn advance_ns(&self, dt_ns: u64) {
        self.now_ns.set(self.now_ns.get().saturating_add(dt_ns));
    }

    /// Advance to `t_ns` (no-op if that is in the past: time never goes backwards).
    pub fn advance_to_ns(&self, t_ns: u64) {
        if t_ns > self.now_ns.get() {
            self.now_ns.set(t_ns);
        }
    }
}

impl Monotonic for SimClock {
    fn now_us(&mut self) -> u64 {
        self.now_ns.get() / 1_000
    }
}

/// `DelayNs` that advances virtual time by exactly the requested amount.
impl embedded_hal::delay::DelayNs for SimClock {
    fn delay_ns(&mut self, ns: u32) {
        self.advance_ns(ns as u64);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use embedded_hal::delay::DelayNs;

    #[test]
    fn delay_advances_and_clones_share_time() {
        let mut a = SimClock::new();
        let mut b = a.clone();
        a.delay_us(5);
        assert_eq!(b.now_us(), 5);
        b.advance_to_ns(1_000);
        assert_eq!(a.now_ns(), 5_000);
    }
}
