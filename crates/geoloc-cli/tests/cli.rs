//! The binary as a user runs it.

use std::process::Command;

fn geoloc_rs(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_geoloc-rs")).args(args).output().expect("binary runs")
}

#[test]
fn version_and_help() {
    let out = geoloc_rs(&["--version"]);
    assert!(out.status.success());
    assert_eq!(String::from_utf8_lossy(&out.stdout).trim(), format!("geoloc-rs {}", env!("CARGO_PKG_VERSION")));
    let help = geoloc_rs(&["--help"]);
    assert!(help.status.success());
    assert!(String::from_utf8_lossy(&help.stdout).contains("selfcheck"));
}

#[test]
fn selfcheck_passes() {
    let out = geoloc_rs(&["selfcheck", "--samples", "50"]);
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{stdout}");
    assert!(stdout.contains("all checks passed"));
}

/// A thread count that is not one ran on every core without a word: a robot capping its CPU
/// use with a typo is now told (the run goes on with the default).
#[test]
fn a_wrong_thread_count_in_the_environment_is_named() {
    let run = |value: &str| {
        Command::new(env!("CARGO_BIN_EXE_geoloc-rs"))
            .args(["selfcheck", "--samples", "20"])
            .env("GEOLOC_NUM_THREADS", value)
            .output()
            .expect("binary runs")
    };
    let out = run("two");
    assert!(out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.starts_with("geoloc-rs: warning: GEOLOC_NUM_THREADS=\"two\" is not a thread count"), "{err}");
    let out = run("2");
    assert!(out.status.success() && out.stderr.is_empty(), "{}", String::from_utf8_lossy(&out.stderr));
}

#[test]
fn bad_arguments_fail_with_usage() {
    let out = geoloc_rs(&["selfcheck", "--samples", "0"]);
    assert!(!out.status.success());
    assert!(String::from_utf8_lossy(&out.stderr).contains("--samples"));
    assert!(!geoloc_rs(&[]).status.success());
}
