//! A PLC's Modbus master polling the board as in service (issue 31: "every Modbus
//! request gets a valid reply within 100 ms at all times"): a read of input registers
//! 0–9 of unit 1, the next one 100 ms after the last transaction ended, each timed from
//! the end of the request on the line to the first byte of the reply; no reply within
//! 1 s is a timeout (a master's usual time-out is 100–1000 ms). A reply is the data, or
//! exception 06 (server device busy: what the board answers while its flash erases,
//! `src/board/modbus.rs`), or anything else (counted as bad).

use crate::scene::{rtu, Session, PS_PER_MS};

/// The request: read input registers 0–9 of unit 1.
fn request() -> Vec<u8> {
    rtu(1, &[0x04, 0, 0, 0, 10])
}

/// One character on the line at the board's default 19 200 Bd 8E1 (11 bits), ps.
const CHAR_PS: u64 = 11 * 1_000_000_000_000 / 19_200;
/// A reply is over after this much silence.
const REPLY_END_PS: u64 = 5 * PS_PER_MS;
/// No reply within this long: a timeout.
const TIMEOUT_PS: u64 = 1_000 * PS_PER_MS;
/// Between the end of one transaction and the next request.
pub const POLL_PS: u64 = 100 * PS_PER_MS;

#[derive(Clone, Copy, Debug)]
enum State {
    /// The next request at this time.
    Idle { next_ps: u64 },
    /// A request sent; its last stop bit at `end_ps`; the reply's bytes from
    /// `modbus_out[from..]`.
    Waiting { end_ps: u64, from: usize },
}

/// What the master saw.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PollStats {
    /// Requests sent.
    pub polls: u64,
    /// Replies with the registers.
    pub data: u64,
    /// Exception 06 replies (server device busy).
    pub busy: u64,
    /// Replies that were neither.
    pub bad: u64,
    /// No reply within 1 s.
    pub timeouts: u64,
    /// The longest time from a request's end to its reply's first byte (a timeout counts
    /// its 1 s), ms.
    pub reply_max_ms: f64,
    /// When the longest wait began, s of the scene.
    pub reply_max_at_s: f64,
}

/// The polling master.
#[derive(Clone, Debug)]
pub struct Poller {
    state: State,
    /// From the end of one transaction to the next request.
    period_ps: u64,
    /// What it saw so far.
    pub stats: PollStats,
}

impl Poller {
    /// The first request at `start_ps`, the next [`POLL_PS`] after each transaction.
    pub fn new(start_ps: u64) -> Self {
        Self::every(start_ps, POLL_PS)
    }

    /// The first request at `start_ps`, the next `period_ps` after each transaction
    /// (a PLC polling once a second: `PS_PER_S`).
    pub fn every(start_ps: u64, period_ps: u64) -> Self {
        Self {
            state: State::Idle { next_ps: start_ps },
            period_ps,
            stats: PollStats::default(),
        }
    }

    /// Each millisecond of the scene. The first request once the firmware has booted
    /// (it opens the line in init; a master that asks earlier times out once, as it
    /// would on any board coming up).
    pub fn tick(&mut self, s: &mut Session) {
        // The scene's millisecond grid (the board stops a little past each step's end,
        // by as much as the instruction it was in: the master's instants are the
        // grid's, so that they do not move with it).
        let now = s.now() / PS_PER_MS * PS_PER_MS;
        if s.seen.boots == 0 {
            return;
        }
        match self.state {
            State::Idle { next_ps } if now >= next_ps => {
                // Not into a line another master (the flood) is using.
                if s.board.soc().usart3.far_pending() > 0 {
                    return;
                }
                let req = request();
                let from = s.board.soc().modbus_out.len();
                if s.board.soc_mut().modbus_send_at(&req, now) {
                    self.stats.polls += 1;
                    self.state = State::Waiting {
                        end_ps: now + req.len() as u64 * CHAR_PS,
                        from,
                    };
                } else {
                    self.state = State::Idle {
                        next_ps: now + self.period_ps,
                    };
                }
            }
            State::Idle { .. } => {}
            State::Waiting { end_ps, from } => {
                let out = &s.board.soc().modbus_out;
                let reply: Vec<(u64, u8)> = out.get(from..).unwrap_or(&[]).to_vec();
                let waited = match reply.first() {
                    Some(&(t, _)) => t.saturating_sub(end_ps),
                    None if now >= end_ps + TIMEOUT_PS => TIMEOUT_PS,
                    None => return,
                };
                // A reply is whole after 5 ms of silence.
                if let Some(&(last, _)) = reply.last() {
                    if now < last + REPLY_END_PS {
                        return;
                    }
                }
                let bytes: Vec<u8> = reply.iter().map(|&(_, b)| b).collect();
                let st = &mut self.stats;
                match bytes.as_slice() {
                    [] => st.timeouts += 1,
                    [1, 0x04, 20, ..] if bytes.len() == 25 && rtu(1, &bytes[1..23]) == bytes => {
                        st.data += 1
                    }
                    b if b == rtu(1, &[0x84, 0x06]) => st.busy += 1,
                    _ => st.bad += 1,
                }
                let ms = waited as f64 / PS_PER_MS as f64;
                if ms > st.reply_max_ms {
                    st.reply_max_ms = ms;
                    st.reply_max_at_s = end_ps as f64 / (1000 * PS_PER_MS) as f64;
                }
                self.state = State::Idle {
                    next_ps: now + self.period_ps,
                };
            }
        }
    }
}

impl PollStats {
    /// The JSON fields (each scene that polls adds them).
    pub fn to_json_fields(&self) -> String {
        format!(
            "\"modbus_polls\":{},\"modbus_poll_data\":{},\"modbus_poll_busy\":{},\"modbus_poll_bad\":{},\"modbus_poll_timeouts\":{},\"modbus_reply_max_ms\":{:.3},\"modbus_reply_max_at_s\":{:.3}",
            self.polls,
            self.data,
            self.busy,
            self.bad,
            self.timeouts,
            self.reply_max_ms,
            self.reply_max_at_s
        )
    }

    /// Every request answered (data or busy) within `limit_ms`.
    pub fn all_answered_within(&self, limit_ms: f64) -> bool {
        self.polls > 0 && self.timeouts == 0 && self.bad == 0 && self.reply_max_ms <= limit_ms
    }
}
