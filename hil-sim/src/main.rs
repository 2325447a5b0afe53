//! `hil-sim`: the docking controller's simulator on the command line (see `cli`).
//!
//! A host program; on bare metal it compiles to an empty image so that a workspace-wide
//! thumb build works.
#![cfg_attr(target_os = "none", no_std, no_main)]

#[cfg(not(target_os = "none"))]
fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    if let Err(e) = hil_sim::cli::run(&args, &mut out) {
        eprintln!("hil-sim: {e}");
        std::process::exit(2);
    }
}

#[cfg(target_os = "none")]
#[panic_handler]
fn panic(_: &core::panic::PanicInfo) -> ! {
    loop {}
}
