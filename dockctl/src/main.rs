//! `dockctl`: see the library's documentation (`dockctl --help`).

use std::io::IsTerminal;
use std::sync::atomic::{AtomicU32, Ordering};
use std::sync::Arc;

fn main() {
    let cancel: dockctl::Cancel = Arc::new(Default::default());
    // Ctrl-C: the first asks the tool to stop and put the board back as it found it
    // (a transfer cancelled, maintenance mode left, echo on); a second one leaves at
    // once, saying what may be left behind.
    let presses = Arc::new(AtomicU32::new(0));
    let terminal = dockctl::pin::Termios::save();
    {
        let cancel = cancel.clone();
        let presses = presses.clone();
        let r = ctrlc::set_handler(move || {
            if presses.fetch_add(1, Ordering::SeqCst) == 0 {
                cancel.store(true, Ordering::SeqCst);
            } else {
                if let Some(t) = &terminal {
                    t.restore();
                }
                eprintln!(
                    "\ndockctl: interrupted again: left at once; the board may still be in maintenance mode (it ends after 10 min idle, or type `maint exit`)"
                );
                std::process::exit(130);
            }
        });
        if let Err(e) = r {
            eprintln!("dockctl: cannot catch Ctrl-C: {e}");
        }
    }
    let mut out = std::io::stdout();
    let mut err = std::io::stderr();
    let mut ctx = dockctl::Ctx {
        out_tty: out.is_terminal(),
        err_tty: err.is_terminal(),
        in_tty: std::io::stdin().is_terminal(),
        out: &mut out,
        err: &mut err,
        cancel,
    };
    let code = dockctl::run(std::env::args_os(), &mut ctx);
    std::process::exit(code);
}
