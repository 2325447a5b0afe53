//! The RTT up-channel, read as a probe reads it, and the defmt frames in it decoded with
//! the image's own table (`defmt-decoder`).
//!
//! The control block `_SEGGER_RTT` (defmt-rtt) is: 16-byte id, `max_up`, `max_down`,
//! then up-channel 0 `{name, buffer, size, write, read, flags}` (u32 each). The board
//! reads the bytes between `read` and `write` and advances `read`, every
//! [`POLL_PS`] of virtual time and at the end of a run, like a probe polling its target.

use defmt_decoder::{DecodeError, StreamDecoder, Table};

/// How often the board drains the RTT buffer, ps of virtual time (1 ms).
pub const POLL_PS: u64 = 1_000_000_000;

/// One decoded log line.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LogLine {
    /// Virtual time the board read it, ps.
    pub t_ps: u64,
    /// Level (`info`, `warn`, …), empty when the frame has none.
    pub level: String,
    /// The firmware's own timestamp, as formatted by the image.
    pub timestamp: String,
    /// The message.
    pub msg: String,
}

/// The decoder of one image's RTT stream.
pub struct Rtt {
    /// Address of the control block.
    pub cb: u32,
    decoder: Box<dyn StreamDecoder + Send + Sync>,
    table: &'static Table,
    /// Frames that did not decode.
    pub malformed: u64,
    /// Bytes read so far.
    pub bytes: u64,
}

impl Rtt {
    /// A reader for the image `elf` whose control block is at `cb`; `None` if the image
    /// has no defmt table.
    pub fn new(elf: &[u8], cb: u32) -> Result<Option<Self>, String> {
        let Some(table) = Table::parse(elf).map_err(|e| format!("defmt table: {e}"))? else {
            return Ok(None);
        };
        // The stream decoder borrows the table for its whole life; a board lives as long
        // as its process needs it, so the table is given a static home.
        let table: &'static Table = Box::leak(Box::new(table));
        Ok(Some(Self {
            cb,
            decoder: table.new_stream_decoder(),
            table,
            malformed: 0,
            bytes: 0,
        }))
    }

    /// Where the up-channel's fields live: (buffer ptr, size, write, read) addresses.
    pub fn fields(&self) -> [u32; 4] {
        let up = self.cb + 24;
        [up + 4, up + 8, up + 12, up + 16]
    }

    /// Feed bytes read from the buffer; decoded lines go to `out`.
    pub fn feed(&mut self, bytes: &[u8], t_ps: u64, out: &mut Vec<LogLine>) {
        self.bytes += bytes.len() as u64;
        self.decoder.received(bytes);
        loop {
            match self.decoder.decode() {
                Ok(frame) => out.push(LogLine {
                    t_ps,
                    level: frame
                        .level()
                        .map(|l| l.as_str().to_string())
                        .unwrap_or_default(),
                    timestamp: frame
                        .display_timestamp()
                        .map(|t| t.to_string())
                        .unwrap_or_default(),
                    msg: frame.display_message().to_string(),
                }),
                Err(DecodeError::UnexpectedEof) => break,
                Err(DecodeError::Malformed) => {
                    self.malformed += 1;
                    if self.table.encoding().can_recover() {
                        continue;
                    }
                    break;
                }
            }
        }
    }
}
