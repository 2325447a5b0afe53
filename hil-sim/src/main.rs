//! `hil-sim`: the docking controller's simulator on the command line (see `cli`).

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    if let Err(e) = hil_sim::cli::run(&args, &mut out) {
        eprintln!("hil-sim: {e}");
        std::process::exit(2);
    }
}
