//! Issue 21 on the virtual board: the release image updated over its own console
//! (YMODEM-1K, the in-process sender), the bootloader's swap, the trial boot, the
//! refusals, the rollback and power cuts — the bootloader and the application are the
//! unmodified release builds (docs/update.md, docs/vboard.md).
//!
//! CI runs each scene once at the datasheet's *typical* flash times (an erase polled
//! from SRAM is executed instruction by instruction: at the maximum times the four DFU
//! erases of `update-bad` alone are 2.7 G instructions) and two seeds of each power cut;
//! the 200 seeds of each cut at the maximum flash times are the ignored tests:
//! `cd vboard && cargo test --release --test update -- --ignored` (75 min on two cores, 97900f2).

use hil_sim::hx711::Hx711Fault;
use vboard::periph::flash::FlashTiming;
use vboard::scene::{run, Options, SceneOptions};
use vboard::update::{
    bad_files, marked, transfer, update_confirm_fails, update_cut_at_confirmation,
    update_cut_marked, update_cut_transfer, update_dead_sensor, update_from_marked, Checks, Cut,
};

fn typical() -> Options {
    let mut o = Options::new();
    o.board.flash_timing = FlashTiming::Typical;
    o
}

fn scene(name: &str) {
    let r = run(
        name,
        &SceneOptions {
            session: typical(),
            ..SceneOptions::default()
        },
    )
    .unwrap_or_else(|e| panic!("{name}: {e}"));
    assert!(r.passed(), "{}", r.to_text());
    assert!(r.core_faults.is_empty(), "{:?}", r.core_faults);
}

/// The scene `update`, in full (the transfer with a DOCK edge during it, the restart,
/// the swap, the trial boot, the new version, the counters).
#[test]
fn the_release_image_updates_itself_over_the_console_with_every_counter_intact() {
    scene("update");
}

/// Three of `update-bad`'s files in CI (the scene has all five; the corrupted full-size
/// image is also the host's `update_session` test): a truncated file, an image signed
/// with another key and an image built for layout B, each refused in one line, STATE
/// untouched, the last before anything is erased.
#[test]
fn a_truncated_a_wrongly_signed_and_another_layouts_image_are_refused_with_state_untouched() {
    let mut s = vboard::scene::Session::new(typical()).unwrap();
    let deadline = s.now() + 60 * vboard::time::PS_PER_S;
    s.run_until(deadline, |x| x.seen.boots >= 1 && x.at_rest())
        .unwrap();
    assert!(s.maint_enter().unwrap());
    let state = s.board.peek(update_layout::layout::STATE_BASE);
    let app = vboard::update::app_bytes(&s.board.image);
    let picked = bad_files(&app)
        .into_iter()
        .enumerate()
        .filter(|(i, f)| i % 2 == 1 || f.before_erase);
    for (_, f) in picked {
        let what = f.what;
        let t = transfer(&mut s, &f.file, None, None).unwrap();
        assert!(
            t.reply.starts_with("error: update refused:") && t.reply.contains(f.words),
            "{what}: {}",
            t.reply
        );
        assert!(
            !f.before_erase || t.erases == 0,
            "{what}: {} erased",
            t.erases
        );
        assert!(!t.ready_seen && !t.moved, "{what}");
        assert_eq!(
            s.board.peek(update_layout::layout::STATE_BASE),
            state,
            "{what}: STATE"
        );
    }
}

#[test]
fn an_image_that_never_confirms_is_rolled_back_after_the_watchdog_reset() {
    scene("update-rollback");
}

fn passed(checks: &Checks) -> bool {
    checks.iter().all(|(_, ok, _)| *ok)
}

fn show(checks: &Checks) -> String {
    checks
        .iter()
        .map(|(n, ok, d)| format!("{} {n}: {d}", if *ok { "ok" } else { "FAILED" }))
        .collect::<Vec<_>>()
        .join("\n")
}

/// The seeds of each cut CI runs (issue 21: two or three in CI, 200 in the ignored tests
/// below).
const CI_SEEDS: [u64; 2] = [7, 11];

/// Two seeds of the transfer's cut.
#[test]
fn a_power_cut_in_the_transfer_boots_the_old_image_with_state_untouched() {
    for seed in CI_SEEDS {
        let mut checks = Checks::new();
        update_cut_transfer(seed, &typical(), &mut checks).unwrap();
        assert!(passed(&checks), "transfer seed {seed}: {}", show(&checks));
    }
}

/// Two seeds of the swap's and of the first boot's cut, from one marked flash (which
/// also runs once without a cut, timing the swap); then the first boot's worst instant:
/// the trial confirmed itself (STATE says BOOT) and the power goes before its CONFIRMED
/// record is written. The next boot writes the record, and `version` names the image
/// the new one replaced (before `at_boot` wrote it, the record was lost for good:
/// `previous` null). All on one marked flash: building it takes about 15 s.
#[test]
fn a_power_cut_in_the_swap_or_the_first_boot_boots_a_whole_image_and_loses_no_record() {
    let o = typical();
    let mut m = marked(&o, false).unwrap();
    let mut checks = Checks::new();
    update_from_marked(&o, &mut m, &mut checks).unwrap();
    assert!(passed(&checks), "no cut: {}", show(&checks));
    for cut in [Cut::Swap, Cut::Boot] {
        for seed in CI_SEEDS {
            let mut checks = Checks::new();
            update_cut_marked(cut, seed, &o, &m, &mut checks).unwrap();
            assert!(passed(&checks), "{cut:?} seed {seed}: {}", show(&checks));
        }
    }
    let mut checks = Checks::new();
    update_cut_at_confirmation(&o, &m, &mut checks).unwrap();
    assert!(
        passed(&checks),
        "cut at the confirmation: {}",
        show(&checks)
    );
}

/// The trial boot's self-test includes the load cell: a new image whose HX711 never
/// answers, or answers with one code only (stuck), is not confirmed and the next reset
/// rolls it back. (Until issue 21's last step it confirmed at init, before any sample;
/// then at the first live sample, which a stuck converter gives too.)
///
/// From the same marked flash (one transfer for both, CI's time): a trial whose
/// confirmation cannot be written (STATE write-protected) is tried again, three attempts
/// each logged, then reported `trial=failed` by `version` and Modbus identification, and
/// rolled back at the next reset (issue 31, fix 1: a failed confirmation was tried once
/// and only the defmt log said so).
#[test]
fn a_trial_image_whose_load_cell_is_silent_or_stuck_or_whose_confirmation_fails_is_rolled_back() {
    let o = typical();
    let m = marked(&o, false).unwrap();
    for fault in [Hx711Fault::Disconnected, Hx711Fault::Stuck] {
        let mut checks = Checks::new();
        update_dead_sensor(&o, &m, fault, &mut checks).unwrap();
        assert!(passed(&checks), "{fault:?}: {}", show(&checks));
    }
    let mut checks = Checks::new();
    update_confirm_fails(&o, &m, &mut checks).unwrap();
    assert!(passed(&checks), "confirmation fails: {}", show(&checks));
}

/// Seeds 1 to 200 of `cut`, on as many boards at a time as the machine has cores (each
/// seed is a board of its own from the same flash: the order does not matter); every
/// seed that failed, in the message.
fn many(cut: Cut) {
    let o = Options::new();
    let m = (cut != Cut::Transfer).then(|| marked(&o, true).unwrap());
    let next = std::sync::atomic::AtomicU64::new(1);
    let failed = std::sync::Mutex::new(Vec::new());
    let workers = std::thread::available_parallelism().map_or(1, |n| n.get());
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| loop {
                let seed = next.fetch_add(1, std::sync::atomic::Ordering::Relaxed);
                if seed > 200 {
                    break;
                }
                let mut checks = Checks::new();
                let r = match &m {
                    None => update_cut_transfer(seed, &o, &mut checks).map(|_| ()),
                    Some(m) => update_cut_marked(cut, seed, &o, m, &mut checks).map(|_| ()),
                };
                let why = match r {
                    Err(e) => Some(e.to_string()),
                    Ok(()) if !passed(&checks) => Some(show(&checks)),
                    Ok(()) => None,
                };
                if let Some(why) = why {
                    failed.lock().unwrap().push((seed, why));
                }
            });
        }
    });
    let mut failed = failed.into_inner().unwrap();
    failed.sort();
    assert!(failed.is_empty(), "{cut:?}: {failed:#?}");
}

/// 200 seeds (`cargo test --release --test update -- --ignored`).
#[test]
#[ignore]
fn a_power_cut_at_200_instants_of_the_transfer_boots_the_old_image_whole() {
    many(Cut::Transfer);
}

/// 200 seeds.
#[test]
#[ignore]
fn a_power_cut_at_200_instants_of_the_swap_boots_a_whole_image() {
    many(Cut::Swap);
}

/// 200 seeds.
#[test]
#[ignore]
fn a_power_cut_at_200_instants_of_the_first_boot_boots_a_whole_image() {
    many(Cut::Boot);
}

/// `tools/sign-image.sh --version` and the scenes' signer write the same file, byte
/// for byte (ed25519 is deterministic): what the scenes prove holds for the script.
#[test]
fn sign_image_sh_and_the_scenes_signer_agree() {
    let elf = vboard::image::default_path();
    let out = std::env::temp_dir().join(format!("vboard-sign-{}.dcs", std::process::id()));
    let root = concat!(env!("CARGO_MANIFEST_DIR"), "/..");
    let st = std::process::Command::new("bash")
        .args([
            "tools/sign-image.sh",
            "--version",
            "0.1.1",
            &elf,
            "boot/keys/test-signing-key.pem",
        ])
        .arg(&out)
        .current_dir(root)
        .status()
        .expect("bash");
    assert!(st.success(), "sign-image.sh failed");
    let script = std::fs::read(&out).unwrap();
    let _ = std::fs::remove_file(&out);
    let img = vboard::image::Image::load(&elf).unwrap();
    let ours = vboard::update::update_file(
        &vboard::update::app_bytes(&img),
        vboard::update::NEW_VERSION,
    );
    assert_eq!(script.len(), ours.len());
    let first = script.iter().zip(&ours).position(|(a, b)| a != b);
    assert!(first.is_none(), "the files differ first at byte {first:?}");
}
