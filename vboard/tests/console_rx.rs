//! The console's receive path on the release image: USART2 received by DMA1 stream 5
//! into a ring (`src/board/console.rs`). What arrives is kept, or its loss is reported
//! and the line it spoils discarded; a line never runs with a byte missing or garbled.
//! Build the image first: `cargo build --release --target thumbv7em-none-eabihf`.

use hil_sim::flash::{SharedFlash, SimFlash};
use vboard::scene::{Options, Session, PS_PER_MS};
use vboard::time::PS_PER_S;

fn out_since(s: &Session, start: usize) -> String {
    let out: Vec<u8> = s.board.soc().console_out[start..]
        .iter()
        .map(|&(_, b)| b)
        .collect();
    String::from_utf8_lossy(&out).into_owned()
}

fn send(s: &mut Session, bytes: &[u8]) {
    assert!(s.board.soc_mut().console_send(bytes), "PA3 is USART2's RX");
}

/// A terminal at the wrong baud rate garbles a line (framing errors on every byte): the
/// line is discarded with `input lost`, and the next one runs.
#[test]
fn a_console_line_garbled_on_the_wire_is_discarded_and_the_next_one_runs() {
    let mut s = Session::new(Options::new()).expect("board");
    s.run_for(2 * PS_PER_S).unwrap();
    let start = s.board.soc().console_out.len();
    s.board.soc_mut().usart2.far_baud = 9_600;
    send(&mut s, b"status --json");
    s.run_for(50 * PS_PER_MS).unwrap();
    s.board.soc_mut().usart2.far_baud = 115_200;
    send(&mut s, b"\r\n");
    s.run_for(200 * PS_PER_MS).unwrap();
    let out = out_since(&s, start);
    assert!(
        s.board.soc().usart2.framing_errors >= 13,
        "the line was garbled"
    );
    assert!(out.contains("error: input lost"), "{out:?}");
    assert!(!out.contains("\"state\""), "the garbled line ran: {out:?}");
    let reply = s.console("status --json", 2 * PS_PER_S).unwrap();
    assert!(reply.trim_start().starts_with('{'), "{reply:?}");
}

/// Boot on an odometer log past its maintenance mark: the firmware erases the next
/// sector at its first idle moment, every interrupt masked for up to 2 s (the
/// datasheet's maximum). Returns the session once the erase has begun.
fn at_a_sector_erase() -> Session {
    let flash = SharedFlash::new(SimFlash::stm32f407_odometer());
    hil_sim::flash::fill_log_to_maintenance(&flash).expect("prefill");
    let mut s = Session::with_flash(Options::new(), flash).expect("board");
    let t = s.now() + 8 * PS_PER_S;
    let erasing = s
        .run_until(t, |x| {
            x.board
                .soc()
                .flash
                .busy_until()
                .is_some_and(|end| end > x.now() + 100 * PS_PER_MS)
        })
        .unwrap();
    assert!(erasing, "no sector erase began");
    s
}

fn erased(s: &mut Session) {
    let t = s.now() + 5 * PS_PER_S;
    let done = s
        .run_until(t, |x| x.board.soc().flash.busy_until().is_none())
        .unwrap();
    assert!(done, "the erase did not end");
    s.run_for(PS_PER_S).unwrap();
}

/// Lines typed while a sector erase masks every interrupt: the DMA moves them into the
/// ring meanwhile, and they run once it is over (the one-byte receive register kept the
/// first byte and overran on the second).
#[test]
fn console_lines_typed_during_a_sector_erase_were_lost() {
    let mut s = at_a_sector_erase();
    let start = s.board.soc().console_out.len();
    send(&mut s, &b"status --json\r\n".repeat(4));
    erased(&mut s);
    let out = out_since(&s, start);
    assert_eq!(s.board.soc().usart2.overruns, 0);
    assert!(!out.contains("input lost"), "{out:?}");
    assert_eq!(out.matches("\"state\"").count(), 4, "{out:?}");
}

/// More than a ring of input while the erase masks every interrupt: the ring is lapped
/// (the stream's interrupt finds both half-ring flags set). The loss is reported once,
/// the line it spoils is discarded, the lines complete in the newest half ring run,
/// none is run from the mixed ring, and the console answers afterwards.
#[test]
fn a_lapped_console_ring_is_reported_never_run_mixed() {
    let mut s = at_a_sector_erase();
    let start = s.board.soc().console_out.len();
    // 1 200 bytes: 104 ms at line rate, well inside the erase.
    let lines = b"status --json\r\nfaults --json\r\n".repeat(40);
    send(&mut s, &lines);
    erased(&mut s);
    let out = out_since(&s, start);
    assert_eq!(out.matches("input lost").count(), 1, "{out:?}");
    for l in out.split("\r\n").filter(|l| l.contains("error")) {
        assert!(l.contains("input lost"), "only the loss is an error: {l:?}");
    }
    // The newest half ring (256 bytes, 17 lines of 15) holds 16 whole lines after the
    // one the loss spoils: they run.
    let replies = out.split("\r\n").filter(|l| l.starts_with('{')).count();
    assert!(replies >= 16, "{replies} replies: {out:?}");
    let reply = s.console("status --json", 2 * PS_PER_S).unwrap();
    assert!(reply.trim_start().starts_with('{'), "{reply:?}");
}
