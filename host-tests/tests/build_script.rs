//! The firmware's build script (`build.rs`) as a user meets it: `DOCKING_TUNING=FILE`
//! naming a file that is not there stops the build with one line naming FILE, not a
//! panic's backtrace. The script is compiled on its own and run as cargo runs it.

use std::path::PathBuf;
use std::process::Command;

#[test]
fn a_missing_docking_tuning_file_is_one_error_line_naming_it() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("..");
    let dir = std::env::temp_dir().join(format!("build-script-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let exe = dir.join("build-script");
    let rustc = std::env::var("RUSTC").unwrap_or_else(|_| "rustc".into());
    let built = Command::new(rustc)
        .current_dir(&root)
        .args(["--edition", "2021", "-O", "build.rs", "-o"])
        .arg(&exe)
        .output()
        .unwrap();
    assert!(
        built.status.success(),
        "{}",
        String::from_utf8_lossy(&built.stderr)
    );
    let run = |tuning: Option<&str>| {
        let mut c = Command::new(&exe);
        c.current_dir(&root).env("OUT_DIR", &dir);
        c.env_remove("DOCKING_TUNING")
            .env_remove("CARGO_CFG_TARGET_OS");
        if let Some(t) = tuning {
            c.env("DOCKING_TUNING", t);
        }
        let o = c.output().unwrap();
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
        String::from_utf8(o.stdout).unwrap()
    };
    let out = run(Some("/no/such/tuning.rs"));
    let errors: Vec<&str> = out
        .lines()
        .filter(|l| l.starts_with("cargo::error="))
        .collect();
    assert_eq!(errors.len(), 1, "{out}");
    assert!(
        errors[0].starts_with("cargo::error=DOCKING_TUNING=/no/such/tuning.rs: "),
        "{out}"
    );
    // The shipped example is taken as it is.
    let example = root.join("docs/tuning-example-18kg.rs");
    let out = run(Some(example.to_str().unwrap()));
    assert!(!out.contains("cargo::error"), "{out}");
    let copied = std::fs::read_to_string(dir.join("tuning.rs")).unwrap();
    assert_eq!(copied, std::fs::read_to_string(&example).unwrap());
    // Without it: the library's defaults.
    let out = run(None);
    assert!(!out.contains("cargo::error"), "{out}");
    let default = std::fs::read_to_string(dir.join("tuning.rs")).unwrap();
    assert!(default.contains("pub fn apply(_cfg"), "{default}");
    let _ = std::fs::remove_dir_all(&dir);
}
