//! The `update` command (issue 21, docs/update.md): a signed image received by
//! YMODEM-1K into DFU, its trailer checked, its SHA-512 computed a few KiB a poll and its
//! ed25519 signature verified (salty, as embassy-boot's `verify_and_mark_updated` does
//! it), then marked for the bootloader's swap by embassy-boot (only when the signature
//! holds), then a restart into it.
//!
//! ```text
//!  technician        console (maintenance mode, at rest)            flash
//!  update  ───────▶  ok: update: send the signed image by YMODEM-1K …
//!                    (READY low, every request but stop refused: Controller::begin_update)
//!          ◀───────  'C' at once, then every 3 s
//!  block 0 ───────▶  size ≤ ACTIVE
//!          ◀───────  ACK 'C'
//!  block 1 ───────▶  vector table and header: this layout's       (nothing erased
//!                    (`update::check_head`; else refused here)     before this check)
//!                                                                   erase DFU page 0
//!          ◀───────  ACK                     (held while the page erases: 1-2 s;
//!  block n ───────▶                           senders wait 10 s)    program the block
//!          ◀───────  ACK                     (a block entering the next DFU page
//!                                             erases that page first)
//!  EOT, end ──────▶  DFU pages the file did not reach, up to ACTIVE's, erased where not
//!                    blank (the swap copies them to ACTIVE);
//!                    trailer: magic, length, words, vector table, header's layout
//!                    SHA-512 of the image, [`VERIFY_CHUNK`] bytes a poll (idle
//!                    answers the Modbus line and the console between them),
//!                    ed25519 with the built-in key
//!                    → STATE: SWAP (embassy-boot)                    STATE marked
//!          ◀───────  ok: update verified: version V …; restarting     audit, image record
//!                    reset → the bootloader swaps, the new image runs on trial
//! ```
//!
//! Every way it can fail ends in one line, `error: update refused: <why>`, with STATE
//! as it was (nothing is marked before the signature holds): the sender's cancel, 60 s
//! of silence, a file larger than ACTIVE, a file for another layout (before anything is
//! erased), a flash error, a bad trailer ([`crate::update::Refusal`]), a signature that
//! does not verify (unsigned, another key's, or a byte changed), or a trial image not
//! yet confirmed. After a refusal the line is let go quiet first (the sender's last
//! bytes are not taken for commands).
//!
//! Nothing is printed while the transfer runs: the link carries YMODEM then. The
//! session runs in the board's idle loop (`UpdateSession::poll`, feature `updater`),
//! without the controller; the flash it writes through is the board's (DFU and STATE
//! behind the controller's owner, at rest). No `core::fmt`: fixed texts and a
//! hand-written decimal.

#[cfg(feature = "updater")]
pub use session::UpdateSession;
use update_layout::header::{Version, VERSION_TEXT_MAX};
use update_layout::layout::ACTIVE_LEN;

use super::json::dec_text;
use super::service::{action, Console};
use crate::machine::Machine;
use crate::odometer::kind;
use crate::update::{marked_record, ImageReport};

/// What the receiver sends while nothing arrives ('C', or NAK inside the file), ms.
pub const IDLE_MS: u64 = 3_000;
/// Silence after which the transfer is cancelled, ms.
pub const SILENCE_MS: u64 = 60_000;
/// After a refusal: the line must be quiet this long before the reply, ms.
pub const QUIET_MS: u64 = 1_000;
/// ...but the reply comes at the latest this long after the refusal, ms.
pub const QUIET_MAX_MS: u64 = 10_000;

/// Bytes of the image hashed per poll while it is verified: about 1.5 ms of SHA-512 at
/// CPI 1, so that idle's loop answers the Modbus line between them (issue 31: a reply
/// within 100 ms at all times; the whole image hashed in one call held it 0.41 s).
pub const VERIFY_CHUNK: u32 = 4096;

/// How the session ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Outcome {
    /// Verified and marked for the swap: the records, the reply, then the restart.
    Verified {
        /// The image's length (without the trailer), bytes.
        len: u32,
        /// Its version (its header), if it has one.
        version: Option<Version>,
    },
    /// Refused, STATE as it was: why, for the technician.
    Refused(&'static str),
}

/// The refusal texts (one line each, after `error: update refused: `).
pub mod why {
    /// The sender cancelled.
    pub const CANCELLED: &str = "cancelled by the sender";
    /// 60 s without a byte.
    pub const SILENCE: &str = "60 s of silence";
    /// Block 0 without a size, or an empty batch.
    pub const NO_SIZE: &str = "no file size in YMODEM block 0";
    /// Larger than ACTIVE.
    pub const TOO_LARGE: &str = "file larger than ACTIVE";
    /// A block out of sequence.
    pub const SEQUENCE: &str = "block out of sequence";
    /// EOT before the size.
    pub const SHORT: &str = "truncated: EOT before the size";
    /// Flash.
    pub const FLASH: &str = "DFU flash error; nothing marked";
    /// The signature.
    pub const SIGNATURE: &str = "signature does not verify (unsigned, another key's, or changed)";
    /// A trial image (not confirmed) cannot mark another.
    pub const TRIAL: &str = "this image is on trial, not confirmed";
    /// The state sector could not be read or written.
    pub const STATE: &str = "STATE flash error";
}

/// The session (the board's, and the host tests'; feature `updater`).
#[cfg(feature = "updater")]
mod session {
    use core::cell::RefCell;

    use embassy_boot::{BlockingFirmwareState, FirmwareUpdaterError};
    use embedded_storage::nor_flash::{NorFlash, ReadNorFlash};
    use update_layout::header::{Header, HEADER_LEN, HEADER_OFFSET};
    use update_layout::layout::{ACTIVE_BASE, ACTIVE_LEN, ACTIVE_PAGES, PAGE_LEN};
    use update_layout::part::{FlashError, Paged, Sectors, State};

    use super::{why, Outcome, IDLE_MS, QUIET_MAX_MS, QUIET_MS, SILENCE_MS, VERIFY_CHUNK};
    use crate::hal::ConsoleIo;
    use crate::update::{check, check_head, TRAILER_LEN};
    use crate::ymodem::{Abort, Action, Receiver};

    /// DFU (its pages, as embassy-boot sees it) over the board's flash.
    type Dfu<'a> = Paged<'a, dyn Sectors + 'a>;
    /// STATE over the board's flash.
    type StateFlash<'a> = State<'a, dyn Sectors + 'a>;

    #[derive(Clone, Copy, Debug, PartialEq, Eq)]
    enum Phase {
        Off,
        Receiving,
        /// The file received and its trailer checked: its SHA-512, a chunk a poll
        /// (`UpdateSession::hashing`), then the signature and the mark.
        Verifying,
        /// Refused: waiting for the line to go quiet (`until`), at the latest `deadline`.
        Quiet {
            until: u64,
            deadline: u64,
        },
    }

    /// The session: the YMODEM receiver and its timers.
    pub struct UpdateSession {
        phase: Phase,
        rx: Receiver,
        last_rx_ms: u64,
        last_idle_ms: u64,
        /// Tenths of the file reported in the log so far.
        progress: u8,
        why: Option<&'static str>,
        /// A flash operation ran in the last poll (an erase takes seconds): the next poll
        /// counts the silence from its own time, not from before it.
        worked: bool,
        /// DFU pages erased (or found blank) in this session: each is erased before the
        /// first block that lands in it.
        erased_pages: u32,
        /// The verification under way (phase `Verifying`).
        hashing: Option<Hashing>,
    }

    /// An image being verified: what its trailer and header said, and its SHA-512 so far.
    struct Hashing {
        /// The image's length (without the trailer), bytes.
        len: u32,
        /// Bytes hashed so far.
        done: u32,
        signature: [u8; 64],
        /// The header's version, valid when `has_version` is 1. Plain integers, no
        /// `Option` or `bool` inside: `Option<Hashing>`'s `None` is then a tag of 0, all
        /// zero, and the board's session stays in `.bss` (with a niche to use, `None`
        /// was not zero and the session cost 1.4 KB of flash in `.data`).
        version: update_layout::header::Version,
        has_version: u8,
        sha: salty::Sha512,
    }

    impl Default for UpdateSession {
        fn default() -> Self {
            Self::new()
        }
    }

    impl UpdateSession {
        /// No session (`const` and all-zero: the board keeps it in a static in `.bss`, not
        /// copied from flash; [`Self::start`] sets the receiver's maximum).
        pub const fn new() -> Self {
            Self {
                phase: Phase::Off,
                rx: Receiver::new(0),
                last_rx_ms: 0,
                last_idle_ms: 0,
                progress: 0,
                why: None,
                worked: false,
                erased_pages: 0,
                hashing: None,
            }
        }

        /// Whether a session runs (the console's line editor rests meanwhile).
        pub fn active(&self) -> bool {
            self.phase != Phase::Off
        }

        /// Begin: the first 'C' goes out at the first poll; nothing is erased before the
        /// first block has shown the file to be an image for this board's layout.
        pub fn start(&mut self, now_ms: u64) {
            self.rx = Receiver::new(ACTIVE_LEN);
            self.phase = Phase::Receiving;
            self.last_rx_ms = now_ms;
            // Never: the first 'C' goes out at once.
            self.last_idle_ms = u64::MAX;
            self.progress = 0;
            self.erased_pages = 0;
        }

        fn refuse(&mut self, why: &'static str, now_ms: u64) {
            warn!("update refused: {}", why);
            self.why = Some(why);
            self.phase = Phase::Quiet {
                until: now_ms + QUIET_MS,
                deadline: now_ms + QUIET_MAX_MS,
            };
        }

        /// Run the session: bytes in, flash written through `flash` (the DFU partition:
        /// its pages, as embassy-boot sees it, and STATE; `update_layout::part`),
        /// YMODEM's answers out. `key`: the ed25519 public key built in. `Some` once it
        /// has ended.
        ///
        /// Not generic, and out of line: the session, embassy-boot's updater and the
        /// verification are compiled once, here at the logic crate's opt-level, not in
        /// the board's idle loop at the image's (issue 21: 96 KiB with the updater).
        #[inline(never)]
        pub fn poll<'f>(
            &mut self,
            io: &mut dyn ConsoleIo,
            flash: &'f RefCell<dyn Sectors + 'f>,
            key: &[u8; 32],
            now_ms: u64,
        ) -> Option<Outcome> {
            let mut dfu = Paged::dfu(flash);
            let mut state = State::new(flash);
            match self.phase {
                Phase::Off => None,
                Phase::Quiet { until, deadline } => {
                    // Whatever the sender still sends is dropped; the reply waits for a quiet
                    // line.
                    let mut until = until;
                    while !matches!(io.read_byte(), Err(nb::Error::WouldBlock)) {
                        until = now_ms + QUIET_MS;
                    }
                    if now_ms >= until || now_ms >= deadline {
                        self.phase = Phase::Off;
                        return Some(Outcome::Refused(self.why.unwrap_or(why::FLASH)));
                    }
                    self.phase = Phase::Quiet { until, deadline };
                    None
                }
                Phase::Receiving => self.receive(io, &mut dfu, now_ms),
                Phase::Verifying => {
                    // The sender has its last ACK: whatever still comes is dropped.
                    while !matches!(io.read_byte(), Err(nb::Error::WouldBlock)) {}
                    let out = self.hash_some(&mut dfu, &mut state, key)?;
                    self.hashing = None;
                    match out {
                        Outcome::Verified { .. } => {
                            self.phase = Phase::Off;
                            Some(out)
                        }
                        Outcome::Refused(w) => {
                            self.refuse(w, now_ms);
                            None
                        }
                    }
                }
            }
        }

        /// The next [`VERIFY_CHUNK`] bytes into the hash; at the end the signature and,
        /// if it holds, the mark (`Some`: the outcome).
        fn hash_some(
            &mut self,
            dfu: &mut Dfu<'_>,
            state: &mut StateFlash<'_>,
            key: &[u8; 32],
        ) -> Option<Outcome> {
            let Some(h) = self.hashing.as_mut() else {
                return Some(Outcome::Refused(why::FLASH));
            };
            let mut buf = [0u8; 256];
            let end = h.len.min(h.done.saturating_add(VERIFY_CHUNK));
            while h.done < end {
                let n = (end - h.done).min(buf.len() as u32) as usize;
                let Some(part) = buf.get_mut(..n) else {
                    return Some(Outcome::Refused(why::FLASH));
                };
                if dfu.read(h.done, part).is_err() {
                    return Some(Outcome::Refused(why::FLASH));
                }
                h.sha.update(part);
                h.done += n as u32;
            }
            if h.done < h.len {
                return None;
            }
            let sha = core::mem::replace(&mut h.sha, salty::Sha512::new());
            Some(verify_and_mark(
                state,
                key,
                &h.signature,
                &sha.finalize(),
                h.len,
                (h.has_version == 1).then_some(h.version),
            ))
        }

        fn receive(
            &mut self,
            io: &mut dyn ConsoleIo,
            dfu: &mut Dfu<'_>,
            now_ms: u64,
        ) -> Option<Outcome> {
            if core::mem::take(&mut self.worked) {
                // The poll before wrote the flash and returned after `now_ms` of its own:
                // that time was the receiver's, not the sender's silence (a NAK now would
                // have the sender send the block twice).
                self.last_rx_ms = now_ms;
            }
            loop {
                let b = match io.read_byte() {
                    Ok(b) => b,
                    Err(nb::Error::WouldBlock) => break,
                    // A byte lost on the way in: the packet's CRC fails, it is asked again.
                    Err(nb::Error::Other(())) => continue,
                };
                self.last_rx_ms = now_ms;
                match self.rx.feed(b) {
                    Action::None => {}
                    Action::Send(bytes) => send(io, bytes),
                    Action::Start { size } => {
                        info!("update: receiving {} bytes", size);
                        send(io, self.rx.ack());
                    }
                    Action::Data { offset, len } => {
                        if offset == 0 {
                            // Before anything is erased: an image for this layout.
                            if let Err(r) = check_head(self.rx.data()) {
                                return self.cancel(io, r.text(), now_ms);
                            }
                        }
                        self.worked = true;
                        let end = offset.saturating_add(self.rx.data().len() as u32);
                        if self.erase_pages_below(dfu, end).is_err()
                            || program(dfu, offset, self.rx.data()).is_err()
                        {
                            return self.cancel(io, why::FLASH, now_ms);
                        }
                        send(io, self.rx.ack());
                        self.report_progress(offset.saturating_add(len as u32));
                    }
                    Action::Done(bytes) => {
                        send(io, bytes);
                        let size = self.rx.size();
                        // The swap copies all of ACTIVE's pages of DFU: those the file
                        // did not reach must not hold an earlier image's bytes.
                        self.worked = true;
                        let checked = match self.clear_pages_after(dfu) {
                            Ok(()) => check_file(dfu, size),
                            Err(_) => Err(why::FLASH),
                        };
                        match checked {
                            Ok(h) => {
                                info!("update: {} bytes received; verifying the signature", h.len);
                                self.hashing = Some(h);
                                self.phase = Phase::Verifying;
                            }
                            Err(w) => self.refuse(w, now_ms),
                        }
                        return None;
                    }
                    Action::Aborted(why, bytes) => {
                        send(io, bytes);
                        self.refuse(abort_text(why), now_ms);
                        return None;
                    }
                }
            }
            if now_ms.saturating_sub(self.last_rx_ms) >= SILENCE_MS {
                return self.cancel(io, why::SILENCE, now_ms);
            }
            let quiet_since = match self.last_idle_ms {
                u64::MAX => None,
                idle => Some(self.last_rx_ms.max(idle)),
            };
            if quiet_since.is_none_or(|t| now_ms.saturating_sub(t) >= IDLE_MS) {
                self.last_idle_ms = now_ms;
                send(io, self.rx.idle());
            }
            None
        }

        fn cancel(
            &mut self,
            io: &mut dyn ConsoleIo,
            why: &'static str,
            now_ms: u64,
        ) -> Option<Outcome> {
            if let Action::Aborted(_, bytes) = self.rx.cancel() {
                send(io, bytes);
            }
            self.refuse(why, now_ms);
            None
        }

        /// Erase every DFU page below `end` not erased yet in this session, blank or not
        /// (data is programmed into it: `update_layout::part`'s module doc); never
        /// beyond ACTIVE's pages (the swap's spare page is the bootloader's).
        fn erase_pages_below(&mut self, dfu: &mut Dfu<'_>, end: u32) -> Result<(), FlashError> {
            let pages = end.min(ACTIVE_LEN).div_ceil(PAGE_LEN);
            while self.erased_pages < pages.min(ACTIVE_PAGES.len() as u32) {
                let p = self.erased_pages;
                info!("update: erasing DFU page {}", p);
                dfu.erase_page(p)?;
                self.erased_pages += 1;
            }
            Ok(())
        }

        /// The DFU pages of ACTIVE's the file did not reach, left reading blank (erased
        /// only where they do not: nothing is programmed into them).
        fn clear_pages_after(&mut self, dfu: &mut Dfu<'_>) -> Result<(), FlashError> {
            for p in self.erased_pages..ACTIVE_PAGES.len() as u32 {
                if dfu.clear_page(p)? {
                    info!("update: DFU page {} cleared for the swap", p);
                }
            }
            self.erased_pages = ACTIVE_PAGES.len() as u32;
            Ok(())
        }

        fn report_progress(&mut self, done: u32) {
            let size = self.rx.size().max(1);
            let tenths = (u64::from(done) * 10 / u64::from(size)).min(10) as u8;
            if tenths > self.progress {
                self.progress = tenths;
                info!(
                    "update: {} % received ({} of {} bytes)",
                    tenths * 10,
                    done,
                    size
                );
            }
        }
    }

    /// Everything of `bytes` into the link (the transmit ring takes a YMODEM answer whole).
    fn send(io: &mut dyn ConsoleIo, mut bytes: &[u8]) {
        for _ in 0..8 {
            if bytes.is_empty() {
                return;
            }
            let n = io.write(bytes);
            bytes = bytes.get(n..).unwrap_or(&[]);
        }
    }

    /// Program a block at `offset`: whole words; a last block that is not (a file that is
    /// not a signed image) is padded with erased bytes, and refused at the trailer check.
    fn program(dfu: &mut Dfu<'_>, offset: u32, data: &[u8]) -> Result<(), FlashError> {
        let whole = data.len() / 4 * 4;
        let (words, rest) = data.split_at(whole);
        if !words.is_empty() {
            dfu.write(offset, words)?;
        }
        if !rest.is_empty() {
            let mut last = [0xFF; 4];
            for (d, s) in last.iter_mut().zip(rest) {
                *d = *s;
            }
            dfu.write(offset + whole as u32, &last)?;
        }
        Ok(())
    }

    fn abort_text(a: Abort) -> &'static str {
        match a {
            Abort::Cancelled => why::CANCELLED,
            Abort::NoSize => why::NO_SIZE,
            Abort::TooLarge => why::TOO_LARGE,
            Abort::Sequence => why::SEQUENCE,
            Abort::Short => why::SHORT,
            Abort::Local => why::SILENCE,
        }
    }

    /// The file of `size` bytes in DFU: its trailer and its first bytes (vector table,
    /// header's layout) checked; the verification to run (its hash not begun).
    fn check_file(dfu: &mut Dfu<'_>, size: u32) -> Result<Hashing, &'static str> {
        let mut head = [0u8; 8];
        let mut tail = [0u8; TRAILER_LEN];
        let tail_at = size.saturating_sub(TRAILER_LEN as u32);
        if size < (TRAILER_LEN + 8) as u32 {
            return Err(crate::update::Refusal::TooShort.text());
        }
        if dfu.read(0, &mut head).is_err() || dfu.read(tail_at, &mut tail).is_err() {
            return Err(why::FLASH);
        }
        let trailer = check(size, &head, &tail, ACTIVE_BASE, ACTIVE_LEN).map_err(|r| r.text())?;
        // The first block was checked as it came; a sender's 128-byte blocks bring the
        // header later: all of it again, from the flash.
        let mut first = [0u8; HEADER_OFFSET as usize + HEADER_LEN];
        if trailer.len < first.len() as u32 {
            return Err(crate::update::Refusal::NoHeader.text());
        }
        if dfu.read(0, &mut first).is_err() {
            return Err(why::FLASH);
        }
        check_head(&first).map_err(|r| r.text())?;
        let version = first
            .last_chunk::<HEADER_LEN>()
            .and_then(Header::parse)
            .map(|h| h.version);
        Ok(Hashing {
            len: trailer.len,
            done: 0,
            signature: trailer.signature,
            version: version.unwrap_or(update_layout::header::Version {
                major: 0,
                minor: 0,
                patch: 0,
                build: 0,
            }),
            has_version: u8::from(version.is_some()),
            sha: salty::Sha512::new(),
        })
    }

    /// The image's SHA-512 `digest` against its `signature` with the built-in `key`, as
    /// embassy-boot's `verify_and_mark_updated` checks it (ed25519 over the 64-byte
    /// digest, salty), then marked for the swap by embassy-boot, which refuses while
    /// STATE is not at rest (a trial image: its own `verify_booted`'s rule).
    fn verify_and_mark(
        state: &mut StateFlash<'_>,
        key: &[u8; 32],
        signature: &[u8; 64],
        digest: &[u8; 64],
        len: u32,
        version: Option<update_layout::header::Version>,
    ) -> Outcome {
        let Ok(public) = salty::PublicKey::try_from(key) else {
            return Outcome::Refused(why::SIGNATURE);
        };
        if public
            .verify(digest, &salty::Signature::from(signature))
            .is_err()
        {
            return Outcome::Refused(why::SIGNATURE);
        }
        // embassy-boot's state buffer is one word of STATE (its own assertion).
        if <StateFlash<'_> as NorFlash>::WRITE_SIZE != 4 {
            return Outcome::Refused(why::STATE);
        }
        let mut aligned = [0u8; 4];
        let mut st = BlockingFirmwareState::new(&mut *state, &mut aligned);
        match st.get_state() {
            Ok(
                embassy_boot::State::Boot
                | embassy_boot::State::DfuDetach
                | embassy_boot::State::Revert,
            ) => {}
            Ok(_) => return Outcome::Refused(why::TRIAL),
            Err(_) => return Outcome::Refused(why::STATE),
        }
        match st.mark_updated() {
            Ok(()) => Outcome::Verified { len, version },
            Err(FirmwareUpdaterError::BadState) => Outcome::Refused(why::TRIAL),
            Err(_) => Outcome::Refused(why::STATE),
        }
    }
}

/// `v`'s text (`none` without one).
pub fn version_text(v: Option<Version>, buf: &mut [u8; VERSION_TEXT_MAX]) -> &str {
    crate::update::version_or(v, "none", buf)
}

/// `update` (run with the controller, maintenance mode and rest checked by the
/// console): at rest, READY low and requests refused for the whole update; the
/// session starts once the reply is out ([`Console::take_update`]).
pub(super) fn begin(console: &mut Console, ctrl: &mut dyn Machine) {
    if !console.has_updater() {
        console.reply_parts(&[
            b"error: no field update here (a simulator has no update partition): flash a board, or use the virtual board (vboard)\r\n",
        ]);
        return;
    }
    if let Err(e) = ctrl.begin_update() {
        console.err_maint(e);
        return;
    }
    let mut n = [0u8; 20];
    console.reply_parts(&[
        b"ok: update: send the signed image by YMODEM-1K now (sb -k FILE, or the terminal's YMODEM upload); at most ",
        dec_text(ACTIVE_LEN.into(), &mut n).as_bytes(),
        b" bytes; 60 s of silence cancels\r\n",
    ]);
    console.request_update();
}

/// The session ended (with the controller): the audit record, the image record of a
/// verified update, the reply. A refused update gives the machine back to its
/// requests; a verified one is followed by the restart (the board's).
pub fn finish(console: &mut Console, ctrl: &mut dyn Machine, out: Outcome, now_ms: u64) {
    let images: ImageReport = ctrl.images();
    let v = |x: Option<Version>| x.map_or([0xFF; 8], Version::to_bytes);
    let (result, len, version) = match out {
        Outcome::Verified { len, version } => (0u8, len, version),
        Outcome::Refused(_) => (1u8, 0, None),
    };
    // Audit detail: result u8 (0 verified and marked, 1 refused) | the new image's
    // version | the running image's | the image's length u32 (versions FF.. unknown).
    let mut detail = [0u8; 21];
    let parts: [&[u8]; 4] = [
        &[result],
        &v(version),
        &v(images.running),
        &len.to_le_bytes(),
    ];
    for (d, s) in detail.iter_mut().zip(parts.into_iter().flatten()) {
        *d = *s;
    }
    console.audit_action(ctrl, action::UPDATE, now_ms, &detail);
    match out {
        Outcome::Verified { len, version } => {
            let rec = marked_record(&images, version);
            // Written at once at rest (the board runs this job at rest with the line
            // free), else queued and counted like every record (rule 4).
            if !ctrl.write_or_queue_record(kind::IMAGE, rec.bytes()) {
                error!("update: the image record was not written");
            }
            info!("update verified and marked: restarting into it");
            let mut t = [0u8; VERSION_TEXT_MAX];
            let mut n = [0u8; 20];
            console.reply_parts(&[
                b"ok: update verified: version ",
                version_text(version, &mut t).as_bytes(),
                b", ",
                dec_text(len.into(), &mut n).as_bytes(),
                b" bytes, signature good; restarting into it (the old image comes back if it does not confirm)\r\n",
            ]);
        }
        Outcome::Refused(why) => {
            ctrl.end_update();
            console.reply_parts(&[b"error: update refused: ", why.as_bytes(), b"\r\n"]);
            console.prompt_after_update();
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn decimals_and_versions_are_written_without_core_fmt() {
        let mut b = [0u8; 20];
        assert_eq!(dec_text(0, &mut b), "0");
        assert_eq!(dec_text(229_376, &mut b), "229376");
        assert_eq!(dec_text(u32::MAX.into(), &mut b), "4294967295");
        let mut t = [0u8; VERSION_TEXT_MAX];
        assert_eq!(version_text(None, &mut t), "none");
        let v = Version {
            major: 0,
            minor: 2,
            patch: 0,
            build: 0,
        };
        assert_eq!(version_text(Some(v), &mut t), "0.2.0");
        let longest = Version {
            major: 255,
            minor: 255,
            patch: 65535,
            build: u32::MAX,
        };
        assert_eq!(
            version_text(Some(longest), &mut t),
            "255.255.65535+4294967295"
        );
        let built = Version { build: 7, ..v };
        assert_eq!(version_text(Some(built), &mut t), "0.2.0+7");
    }
}
