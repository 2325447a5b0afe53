//! Issue 21: the console's `update` session on the host, through the real pieces — the
//! YMODEM-1K receiver, the trailer check, embassy-boot's `verify_and_mark_updated` with
//! salty — over a simulated flash laid out as the board's (DFU pages, STATE): a signed
//! image is marked for the swap; a corrupted, truncated, unsigned or wrongly signed one
//! is refused and STATE is not touched; one for another layout is refused before
//! anything is erased; DFU is erased page by page as the file reaches it. (On the image
//! itself: vboard's `update` scenes.)

use std::cell::RefCell;
use std::collections::VecDeque;

use docking_logic::console::update::{why, Outcome, UpdateSession};
use docking_logic::hal::ConsoleIo;
use hil_sim::update::{other_key_seed, public_key, signed_file, test_key_seed, YmodemSender};
use update_layout::header::{Header, Version, HEADER_OFFSET};
use update_layout::layout::{
    Layout, ACTIVE_BASE, ACTIVE_LEN, DFU_BASE, DFU_PAGES, FLASH_BASE, LAYOUT, PAGE_LEN, STATE_BASE,
    STATE_LEN,
};
use update_layout::part::{FlashError, Sectors};

/// The 1 MiB of flash, erased; counts what is written where.
struct Flash {
    mem: Vec<u8>,
    state_writes: u32,
    dfu_erases: u32,
    /// The session's poll count at each DFU erase.
    erase_polls: Vec<u32>,
    polls: u32,
    /// Bytes read in each poll, by poll (index: the poll count).
    read_by_poll: Vec<u64>,
}

impl Flash {
    fn new() -> Self {
        Self {
            mem: vec![0xFF; 0x10_0000],
            state_writes: 0,
            dfu_erases: 0,
            erase_polls: Vec::new(),
            polls: 0,
            read_by_poll: Vec::new(),
        }
    }
}

/// Where the updater may write: the DFU pages an update file fills, and STATE.
fn updater_may_write(addr: u32, len: u32) -> bool {
    (addr >= DFU_BASE && addr + len <= DFU_BASE + ACTIVE_LEN)
        || (addr >= STATE_BASE && addr + len <= STATE_BASE + STATE_LEN)
}

impl Sectors for Flash {
    fn read(&mut self, addr: u32, buf: &mut [u8]) -> Result<(), FlashError> {
        let i = (addr - FLASH_BASE) as usize;
        buf.copy_from_slice(&self.mem[i..i + buf.len()]);
        let p = self.polls as usize;
        if self.read_by_poll.len() <= p {
            self.read_by_poll.resize(p + 1, 0);
        }
        self.read_by_poll[p] += buf.len() as u64;
        Ok(())
    }
    fn erase_sector(&mut self, base: u32) -> Result<(), FlashError> {
        let (_, start, len) = update_layout::layout::sector_of(base).unwrap();
        assert!(
            start == base && updater_may_write(base, len),
            "the updater erased sector {base:#x}"
        );
        if base == STATE_BASE {
            self.state_writes += 1;
        } else {
            self.dfu_erases += 1;
            self.erase_polls.push(self.polls);
        }
        let i = (start - FLASH_BASE) as usize;
        self.mem[i..i + len as usize].fill(0xFF);
        Ok(())
    }
    fn program(&mut self, addr: u32, data: &[u8]) -> Result<(), FlashError> {
        assert!(
            updater_may_write(addr, data.len() as u32),
            "the updater programmed {addr:#x}"
        );
        if addr < STATE_BASE + STATE_LEN {
            self.state_writes += 1;
        }
        let i = (addr - FLASH_BASE) as usize;
        for (m, d) in self.mem[i..i + data.len()].iter_mut().zip(data) {
            *m &= d;
        }
        Ok(())
    }
}

/// The link: what the sender sent, what the receiver answered.
#[derive(Default)]
struct Link {
    to_board: VecDeque<u8>,
    from_board: Vec<u8>,
}

impl ConsoleIo for Link {
    fn read_byte(&mut self) -> nb::Result<u8, ()> {
        self.to_board.pop_front().ok_or(nb::Error::WouldBlock)
    }
    fn write(&mut self, bytes: &[u8]) -> usize {
        self.from_board.extend_from_slice(bytes);
        bytes.len()
    }
}

/// A board's ACTIVE image: a vector table into ACTIVE, the image header naming this
/// layout, then a pattern.
fn image(len: usize) -> Vec<u8> {
    image_for(len, ACTIVE_BASE, Some(LAYOUT.id()))
}

/// An image linked at `base` whose header names layout `id` (`None`: no header).
fn image_for(len: usize, base: u32, id: Option<u8>) -> Vec<u8> {
    let mut v: Vec<u8> = (0..len).map(|i| (i * 7 + i / 251) as u8).collect();
    v[..4].copy_from_slice(&0x2002_0000u32.to_le_bytes());
    v[4..8].copy_from_slice(&(base + 0x1001).to_le_bytes());
    if let Some(id) = id {
        let h = Header {
            version: Version {
                major: 0,
                minor: 1,
                patch: 1,
                build: 0,
            },
            flags: u32::from(id) << update_layout::header::LAYOUT_SHIFT,
            key_id: [0; 16],
        };
        v[HEADER_OFFSET as usize..][..32].copy_from_slice(&h.to_bytes());
    }
    v
}

/// Send `file` by YMODEM into a session; the outcome and the flash after it.
fn deliver(file: Vec<u8>) -> (Outcome, Flash, Vec<u8>) {
    deliver_with(file, 0, None)
}

/// As [`deliver_with`], onto a flash prepared by `prepare`.
fn deliver_onto(
    file: Vec<u8>,
    erase_ms: u64,
    sender_timeout_ms: Option<u64>,
    prepare: impl FnOnce(&mut Flash),
) -> (Outcome, Flash, Vec<u8>) {
    let mut f = Flash::new();
    prepare(&mut f);
    run_session(f, file, erase_ms, sender_timeout_ms)
}

/// As [`deliver`], a DFU erase taking `erase_ms` (the poll that erases returns that
/// much later, as on the board, where a 128 KiB sector takes up to 2 s), and a sender
/// that sends its packet again after `sender_timeout_ms` without an answer (lrzsz's
/// `sb`: 10 s), as a real one does.
fn deliver_with(
    file: Vec<u8>,
    erase_ms: u64,
    sender_timeout_ms: Option<u64>,
) -> (Outcome, Flash, Vec<u8>) {
    run_session(Flash::new(), file, erase_ms, sender_timeout_ms)
}

fn run_session(
    flash: Flash,
    file: Vec<u8>,
    erase_ms: u64,
    sender_timeout_ms: Option<u64>,
) -> (Outcome, Flash, Vec<u8>) {
    let flash = RefCell::new(flash);
    // A confirmed board: STATE says BOOT.
    flash.borrow_mut().mem[(STATE_BASE - FLASH_BASE) as usize..][..4].fill(0xD0);
    let state_before = flash.borrow().mem[(STATE_BASE - FLASH_BASE) as usize..][..64].to_vec();
    let key = public_key(&test_key_seed());
    let mut s = UpdateSession::new();
    let mut link = Link::default();
    let mut sender = YmodemSender::new("app.dcs", file);
    s.start(0);
    let mut seen = 0;
    let mut out = None;
    // The line: 115200 Bd, 115 bytes in 10 ms.
    let mut wire: VecDeque<u8> = VecDeque::new();
    // 10 ms a poll, as the board's idle loop at least runs.
    let mut t = 0u64;
    // When the sender last heard the receiver.
    let mut heard = 0u64;
    while t < 600_000 {
        let erases = flash.borrow().dfu_erases;
        flash.borrow_mut().polls += 1;
        if let Some(o) = s.poll(&mut link, &flash, &key, t) {
            out = Some(o);
            break;
        }
        t += 10;
        if flash.borrow().dfu_erases != erases {
            t += erase_ms;
        }
        // The sender's timeout runs out before the answers of a poll that came back
        // late (they left the board at its end).
        if let Some(timeout) = sender_timeout_ms {
            if t.saturating_sub(heard) >= timeout && !sender.finished() {
                wire.extend(sender.on_timeout());
                heard = t;
            }
        }
        for _ in 0..115 {
            match wire.pop_front() {
                Some(b) => link.to_board.push_back(b),
                None => break,
            }
        }
        let answers: Vec<u8> = link.from_board[seen..].to_vec();
        seen = link.from_board.len();
        if !answers.is_empty() {
            heard = t;
        }
        for b in answers {
            let reply = sender.on_byte(b);
            wire.extend(reply);
        }
    }
    assert!(!s.active(), "the session ended");
    let flash = flash.into_inner();
    let _ = state_before;
    (out.expect("an outcome"), flash, link.from_board)
}

fn state_word(f: &Flash) -> [u8; 4] {
    f.mem[(STATE_BASE - FLASH_BASE) as usize..][..4]
        .try_into()
        .unwrap()
}

#[test]
fn a_signed_image_is_received_verified_and_marked_for_the_swap() {
    // An image near ACTIVE's size (two DFU pages in layout C), 4 KiB short of it.
    let len = ACTIVE_LEN as usize - 4096;
    let img = image(len);
    let (out, flash, _) = deliver(signed_file(&img, &test_key_seed()));
    assert!(
        matches!(out, Outcome::Verified { len: l, .. } if l as usize == len),
        "{out:?}"
    );
    assert_eq!(state_word(&flash), [0xF0; 4], "SWAP marked");
    let at = (DFU_PAGES[0] - FLASH_BASE) as usize;
    assert!(
        flash.mem[at..at + img.len()] == img[..],
        "DFU holds the image"
    );
}

/// The poll that erased a DFU page (seconds on the board) came back with its old time;
/// the next took the erase for the sender's silence and sent a NAK, the sender sent
/// block 1 again, and its extra ACK put sender and receiver one block apart: the
/// transfer hung at the end (found on the virtual board, `vboard scene update`).
#[test]
fn a_long_erase_was_taken_for_silence_and_a_block_went_twice() {
    let img = image(20_000);
    let (out, flash, _) = deliver_onto(signed_file(&img, &test_key_seed()), 4_000, None, |f| {
        // An earlier image in DFU page 0: it is erased (a blank one would not be).
        f.mem[(DFU_PAGES[0] - FLASH_BASE) as usize] = 0
    });
    assert!(matches!(out, Outcome::Verified { .. }), "{out:?}");
    assert_eq!(flash.dfu_erases, 1);
}

/// Each DFU page is erased just before the first block that lands in it, while the
/// sender waits for that block's ACK: at the datasheet's maximum for a 128 KiB sector at
/// ×32 (2 s) the ACK comes well inside the sender's 10 s (lrzsz's `sb`), and it sends
/// nothing twice.
#[test]
fn a_dfu_erase_at_the_datasheets_maximum_holds_an_ack_within_the_senders_timeout() {
    let img = image(ACTIVE_LEN as usize - 4096);
    let file = signed_file(&img, &test_key_seed());
    let (out, flash, _) = deliver_onto(file, 2_000, Some(10_000), |f| {
        // Both pages hold an earlier image: each is erased.
        for p in &DFU_PAGES[..2] {
            f.mem[(p - FLASH_BASE) as usize] = 0;
        }
    });
    assert!(matches!(out, Outcome::Verified { .. }), "{out:?}");
    assert_eq!(
        flash.dfu_erases, 2,
        "both DFU pages the file reaches, once each"
    );
}

/// The first 'C' goes out at the session's first poll, before anything is erased (the
/// whole DFU used to be erased first: seconds with nothing on the technician's screen);
/// DFU page 0 is erased only when block 1 has shown an image for this layout.
#[test]
fn the_first_c_goes_out_at_once_and_dfu_is_erased_by_the_first_block() {
    let flash = RefCell::new(Flash::new());
    flash.borrow_mut().mem[(DFU_PAGES[0] - FLASH_BASE) as usize] = 0;
    let mut s = UpdateSession::new();
    let mut link = Link::default();
    let key = public_key(&test_key_seed());
    s.start(0);
    assert_eq!(s.poll(&mut link, &flash, &key, 0), None);
    assert_eq!(link.from_board, b"C", "the first 'C' at the first poll");
    assert_eq!(
        flash.borrow().dfu_erases,
        0,
        "nothing erased before block 1"
    );
    // The whole transfer: the first erase came with block 1.
    let (out, flash, _) = deliver_onto(
        signed_file(&image(30_000), &test_key_seed()),
        1_000,
        Some(10_000),
        |f| f.mem[(DFU_PAGES[0] - FLASH_BASE) as usize] = 0,
    );
    assert!(matches!(out, Outcome::Verified { .. }), "{out:?}");
    assert_eq!(flash.dfu_erases, 1);
    assert!(
        flash.erase_polls[0] > 2,
        "DFU erased at poll {:?}",
        flash.erase_polls
    );
}

/// The swap copies all of ACTIVE's DFU pages to ACTIVE: a DFU page the file does not
/// reach is erased after the transfer when it holds an earlier image's bytes (as DFU
/// page 1 does after every swap), and left alone when it reads blank; a page the file
/// is programmed into is erased whatever it reads.
#[test]
fn dfu_pages_the_file_does_not_reach_are_left_erased_for_the_swap() {
    let file = signed_file(&image(40_000), &test_key_seed());
    let page1 = (DFU_PAGES[1] - FLASH_BASE) as usize;
    let (out, flash, _) = deliver_onto(file.clone(), 0, None, |f| {
        f.mem[page1..page1 + 1000].fill(0x42);
    });
    assert!(matches!(out, Outcome::Verified { .. }), "{out:?}");
    assert!(flash.mem[page1..page1 + PAGE_LEN as usize]
        .iter()
        .all(|&b| b == 0xFF));
    assert_eq!(
        flash.dfu_erases, 2,
        "page 0 (the file's) and page 1 (not blank)"
    );
    let (out, flash, _) = deliver(file);
    assert!(matches!(out, Outcome::Verified { .. }), "{out:?}");
    // Page 0 is erased although it reads blank (an erase cut short reads blank too:
    // nothing is programmed into a page not erased in this session); page 1, which
    // nothing is programmed into, is left as it reads.
    assert_eq!(flash.dfu_erases, 1, "page 0 only");
    // The swap's spare page is never the updater's (the flash model asserts it).
}

/// A file built for another partition map is refused by its first block, before
/// anything is erased or marked: linked for layout B (its header names none), linked for
/// this layout but naming another, or without a header.
#[test]
fn a_file_for_another_layout_is_refused_before_anything_is_erased() {
    use docking_logic::update::Refusal;
    for (name, img, expect) in [
        (
            "linked for layout B",
            image_for(60_000, Layout::B.active_base(), Some(0)),
            Refusal::OtherLayout(None),
        ),
        (
            "naming layout B",
            image_for(60_000, ACTIVE_BASE, Some(Layout::B.id())),
            Refusal::OtherLayout(Some(Layout::B)),
        ),
        (
            "no header",
            image_for(60_000, ACTIVE_BASE, None),
            Refusal::NoHeader,
        ),
    ] {
        let (out, flash, answers) =
            deliver_onto(signed_file(&img, &test_key_seed()), 0, None, |f| {
                f.mem[(DFU_PAGES[0] - FLASH_BASE) as usize] = 0
            });
        assert_eq!(out, Outcome::Refused(expect.text()), "{name}");
        assert!(
            answers.windows(2).any(|w| w == [0x18, 0x18]),
            "{name}: CAN CAN sent"
        );
        assert_eq!(flash.dfu_erases, 0, "{name}: DFU erased");
        assert_eq!(flash.state_writes, 0, "{name}: STATE written");
        assert_eq!(flash.mem[(DFU_PAGES[0] - FLASH_BASE) as usize], 0);
    }
}

/// Every bad file ends in a refusal and leaves STATE as it was (not one write to it).
#[test]
fn corrupted_truncated_unsigned_and_wrongly_signed_images_are_refused_with_state_untouched() {
    let img = image(60_000);
    let good = signed_file(&img, &test_key_seed());
    let mut flipped = good.clone();
    flipped[30_000] ^= 0x10;
    let truncated = good[..good.len() - 1000].to_vec();
    let unsigned = img.clone();
    let other = signed_file(&img, &other_key_seed());
    let foreign = image_for(60_000, 0x0800_0000, Some(LAYOUT.id()));
    let foreign = signed_file(&foreign, &test_key_seed());
    for (name, file, expect) in [
        ("a flipped bit", flipped, why::SIGNATURE),
        (
            "truncated",
            truncated,
            docking_logic::update::Refusal::NoMagic.text(),
        ),
        (
            "unsigned",
            unsigned,
            docking_logic::update::Refusal::NoMagic.text(),
        ),
        ("another key's", other, why::SIGNATURE),
        (
            "linked without the bootloader",
            foreign,
            docking_logic::update::Refusal::NotBootable.text(),
        ),
    ] {
        let (out, flash, _) = deliver(file);
        assert_eq!(out, Outcome::Refused(expect), "{name}");
        assert_eq!(flash.state_writes, 0, "{name}: STATE written");
        assert_eq!(state_word(&flash), [0xD0; 4], "{name}: STATE changed");
    }
}

#[test]
fn a_file_larger_than_active_is_cancelled_before_anything_is_written() {
    let img = image(ACTIVE_LEN as usize);
    let (out, flash, answers) = deliver(signed_file(&img, &test_key_seed()));
    assert_eq!(out, Outcome::Refused(why::TOO_LARGE));
    assert!(
        answers.windows(2).any(|w| w == [0x18, 0x18]),
        "CAN CAN sent"
    );
    let at = (DFU_PAGES[0] - FLASH_BASE) as usize;
    assert!(flash.mem[at..at + 4096].iter().all(|&b| b == 0xFF));
    assert_eq!(flash.state_writes, 0);
}

#[test]
fn silence_cancels_the_transfer_after_a_minute_with_c_every_three_seconds() {
    let flash = RefCell::new(Flash::new());
    let mut s = UpdateSession::new();
    let mut link = Link::default();
    s.start(0);
    let key = public_key(&test_key_seed());
    let mut out = None;
    for t in (0..80_000u64).step_by(10) {
        if let Some(o) = s.poll(&mut link, &flash, &key, t) {
            out = Some((o, t));
            break;
        }
    }
    let (o, t) = out.unwrap();
    assert_eq!(o, Outcome::Refused(why::SILENCE));
    assert!((60_000..62_000).contains(&t), "refused at {t} ms");
    let cs = link.from_board.iter().filter(|&&b| b == b'C').count();
    assert!((20..=21).contains(&cs), "{cs} 'C' sent");
}

/// The simulator has no update partition: `update` is refused in one line and the
/// machine is not left locked (a console that accepted it would hold READY low and
/// refuse every request, waiting for a session nobody runs).
#[test]
fn the_simulator_refuses_update_and_takes_requests_after_it() {
    let mut r = hil_sim::rig::Rig::new(hil_sim::rig::RigOptions::new(80));
    r.console_enabled = true;
    for _ in 0..hil_sim::rig::BOOT_TICKS {
        r.tick();
    }
    assert!(r.command("pin set 2468", 10).starts_with("ok"));
    assert!(r.command("maint 2468", 10).starts_with("ok"));
    let reply = r.command("update", 10);
    assert!(reply.starts_with("error: no field update here"), "{reply}");
    assert!(!r.ctrl.updating());
    assert!(r.command("maint exit", 10).starts_with("ok"));
    for _ in 0..10 {
        r.tick();
    }
    assert!(r.ctrl.handshake().ready, "READY back");
}

/// The image was hashed in one call (embassy-boot's `verify_and_mark_updated`, two bytes
/// a read): the board's idle loop, which runs the session, was held 0.41 s at CPI 1 for a
/// 113 KB image and the Modbus line went unanswered (the virtual board's `update` scene
/// with a polling PLC: 171 ms). Now no poll reads more than a chunk and a little of the
/// trailer and header, so idle answers the line between them.
#[test]
fn the_image_was_verified_in_one_poll_that_held_the_idle_loop() {
    // `docking_logic::console::update::VERIFY_CHUNK`.
    const VERIFY_CHUNK: u32 = 4096;
    let len = 100_000;
    let (out, flash, _) = deliver(signed_file(&image(len), &test_key_seed()));
    assert!(matches!(out, Outcome::Verified { .. }), "{out:?}");
    // One poll reads a whole DFU page beyond the file (is it blank? a read of the memory
    // map, about a millisecond on the board): the others a chunk at most.
    let mut reads: Vec<u64> = flash
        .read_by_poll
        .iter()
        .copied()
        .filter(|&b| b > 0)
        .collect();
    reads.sort_unstable();
    let second = reads.iter().rev().nth(1).copied().unwrap_or(0);
    assert!(
        second <= u64::from(VERIFY_CHUNK) + 1024,
        "a poll read {second} B of DFU (the chunk is {VERIFY_CHUNK} B)"
    );
    let hashing_polls = reads.len();
    assert!(
        hashing_polls as u64 >= len as u64 / u64::from(VERIFY_CHUNK),
        "{hashing_polls} polls read DFU"
    );
}
