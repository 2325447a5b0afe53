//! Host tests live in `tests/`; this crate holds only what several of them share.

mod shared {
    use docking_logic::sequencer::{Request, State};
    use hil_sim::rig::Rig;
    use std::path::PathBuf;

    /// Run `n` more test cycles on `r` (each started when idle and persisted); panics if
    /// they do not complete.
    pub fn run_cycles(r: &mut Rig, n: u32) {
        let target = r.ctrl.odometer().lifetime().cycles + n;
        for _ in 0..(n as usize * 6_000) {
            r.tick();
            if r.ctrl.state() == State::Idle && !r.ctrl.persist_pending() {
                if r.ctrl.odometer().lifetime().cycles >= target {
                    return;
                }
                r.ctrl.request(Request::StartCycle);
            }
        }
        panic!("cycles did not complete");
    }

    /// Tick `r` until `f` holds (`true`) or `max_ticks` pass (`false`).
    pub fn run_until(r: &mut Rig, max_ticks: usize, mut f: impl FnMut(&Rig) -> bool) -> bool {
        for _ in 0..max_ticks {
            r.tick();
            if f(r) {
                return true;
            }
        }
        false
    }

    /// Tick `r` until `done` holds, checking before each tick (so nothing ticks if it
    /// holds already); panics, naming the state, after `max_ticks`.
    pub fn reach(r: &mut Rig, max_ticks: usize, mut done: impl FnMut(&Rig) -> bool) {
        for _ in 0..max_ticks {
            if done(r) {
                return;
            }
            r.tick();
        }
        panic!(
            "not reached in {max_ticks} ticks: state {:?}",
            r.ctrl.state()
        );
    }

    /// Tick `r` `ticks` times; panics (saying `why`) if the propulsion or the lock is
    /// driven at any of them.
    pub fn run_without_motion(r: &mut Rig, ticks: usize, why: &str) {
        for _ in 0..ticks {
            r.tick();
            assert!(!r.axis.enabled() && !r.lock.driven(), "{why}");
        }
    }

    /// The files of the kept fuzz corpus `fuzz-corpus/NAME/`, sorted; panics with fewer
    /// than 20.
    pub fn corpus_files(name: &str) -> Vec<PathBuf> {
        let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("fuzz-corpus")
            .join(name);
        let mut files: Vec<_> = std::fs::read_dir(&dir)
            .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
            .map(|e| e.unwrap().path())
            .filter(|p| p.is_file())
            .collect();
        files.sort();
        assert!(files.len() >= 20, "only {} corpus files", files.len());
        files
    }
}

pub use shared::{corpus_files, reach, run_cycles, run_until, run_without_motion};
