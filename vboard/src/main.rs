//! `vboard`: the docking controller's firmware image on a virtual STM32F407 board.

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let stdout = std::io::stdout();
    let mut out = stdout.lock();
    match vboard::cli::run(&args, &mut out) {
        Ok(()) => {}
        Err(vboard::cli::Failure::Usage(e)) => {
            eprintln!("vboard: {e}");
            std::process::exit(2);
        }
        Err(vboard::cli::Failure::Run(e)) => {
            eprintln!("vboard: {e}");
            std::process::exit(1);
        }
    }
}
