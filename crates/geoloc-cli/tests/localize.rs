//! `geoloc-rs info` and `geoloc-rs localize` as a robot runs them, on a simulated scene built
//! in Rust: the same poses and covariances as the core localizer in-process (bit for bit),
//! bad input refused with the frame named, and 200 mutated streams that never panic or hang.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::Arc;
use std::time::{Duration, Instant};

use geoloc_core::frames::{FrameRecord, write_json_header, write_json_record, write_record, write_stream_header};
use geoloc_core::lie::SE3;
use geoloc_core::localizer::{Frame, Localizer, LocalizerOptions, Locator};
use geoloc_core::map::{DescriptorSet, Keyframe, Map, RetrievalKind};
use geoloc_core::testing::{self, LandmarkScene, SplitMix64};

const WIDTH: usize = testing::LANDMARK_DESCRIPTOR_BYTES;
const LANDMARKS: usize = 1200;
/// Mutated streams run through the real binary.
const FUZZ_CASES: usize = 200;
/// A run longer than this is a hang.
const HANG: Duration = Duration::from_secs(30);
/// Exit status of a Rust panic.
const PANIC_STATUS: i32 = 101;

/// The camera path of these tests: [`testing::walk`] (the scene is [`LandmarkScene`]).
fn walk(t: f64, offset: f64) -> SE3 {
    testing::walk(t, offset, -1.0)
}

/// The map (saved to `dir/scene.geoloc`) and `frames` query records along a parallel path.
fn scene(dir: &Path, frames: usize) -> (PathBuf, Vec<FrameRecord>) {
    let mut rng = SplitMix64::new(7);
    let scene = LandmarkScene::new(&mut rng, LANDMARKS, 6.0);
    let keyframes = (0..30)
        .map(|i| {
            let pose = walk(i as f64 * 0.1, 0.0);
            let (keypoints, data) = scene.observe(&mut rng, &pose, 1);
            Keyframe {
                world_from_cam: pose,
                keypoints,
                descriptors: DescriptorSet::Binary { data, width: WIDTH },
                global: None,
            }
        })
        .collect();
    let map =
        Map::build(scene.camera, keyframes, None, RetrievalKind::Bow { branching: 8, depth: 3 }, 0).expect("valid");
    let path = dir.join("scene.geoloc");
    map.save(&path, r#"{"features":{"kind":"synthetic","n_features":0,"root_sift":false}}"#).expect("saves");
    let records = (0..frames)
        .map(|f| {
            let t = 0.3 + f as f64 / 30.0;
            let (keypoints, data) = scene.observe(&mut rng, &walk(t, 0.1), 1);
            let n = keypoints.len();
            FrameRecord {
                timestamp: t,
                keypoints,
                pixel_sigmas: (0..n).map(|i| 1.2f64.powi((i % 3) as i32)).collect(),
                descriptors: DescriptorSet::Binary { data, width: WIDTH },
                global: None,
            }
        })
        .collect();
    (path, records)
}

fn stream(records: &[FrameRecord]) -> Vec<u8> {
    let mut out = Vec::new();
    write_stream_header(&mut out).expect("in memory");
    for (i, r) in records.iter().enumerate() {
        write_record(&mut out, r, i).expect("valid");
    }
    out
}

fn dir(name: &str) -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("geoloc-rs-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

/// `geoloc-rs args…` started on one thread with stdin, stdout and stderr piped.
/// The names of the files in `dir` (lossy UTF-8).
fn file_names(dir: &Path) -> Vec<String> {
    std::fs::read_dir(dir)
        .expect("lists")
        .filter_map(Result::ok)
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect()
}

fn spawn(args: &[&str]) -> std::process::Child {
    Command::new(env!("CARGO_BIN_EXE_geoloc-rs"))
        .args(args)
        .env("GEOLOC_NUM_THREADS", "1")
        .stdin(Stdio::piped())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .expect("binary runs")
}

/// Runs `geoloc-rs args…` with `stdin` piped in, killed (and reported) after [`HANG`].
fn run(args: &[&str], stdin: &[u8]) -> (Output, bool) {
    let mut child = spawn(args);
    let mut pipe = child.stdin.take().expect("piped");
    let data = stdin.to_vec();
    let feeder = std::thread::spawn(move || {
        let _ = pipe.write_all(&data); // the binary may stop reading early (an error): fine
    });
    let start = Instant::now();
    let mut hung = false;
    while child.try_wait().expect("waits").is_none() {
        if start.elapsed() > HANG {
            let _ = child.kill();
            hung = true;
            break;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    let out = child.wait_with_output().expect("output");
    let _ = feeder.join();
    (out, hung)
}

fn lines(out: &Output) -> Vec<String> {
    String::from_utf8_lossy(&out.stdout).lines().map(str::to_owned).collect()
}

/// The core localizer in-process with the default options, formatted as the binary formats it.
fn expected(map_path: &Path, records: &[FrameRecord]) -> Vec<Vec<u64>> {
    expected_with(map_path, records, LocalizerOptions::default())
}

/// [`expected`] with `options`.
fn expected_with(map_path: &Path, records: &[FrameRecord], options: LocalizerOptions) -> Vec<Vec<u64>> {
    let (map, _) = Map::load(map_path).expect("loads");
    let mut loc = Localizer::new(Arc::new(map), options).expect("options");
    records
        .iter()
        .map(|r| {
            let frame = Frame {
                timestamp: r.timestamp,
                keypoints: &r.keypoints,
                descriptors: r.descriptors.view(),
                global: None,
                pixel_sigmas: Some(&r.pixel_sigmas),
            };
            let res = loc.localize(&frame).expect("valid frame");
            let e = res.estimate.expect("this scene localizes");
            let mut bits: Vec<u64> = e.world_from_cam.translation.iter().map(|v| v.to_bits()).collect();
            for i in 0..6 {
                for j in i..6 {
                    bits.push(e.covariance[(i, j)].to_bits());
                }
            }
            bits
        })
        .collect()
}

fn parsed_bits(line: &str) -> Vec<u64> {
    let cols: Vec<&str> = line.split(' ').collect();
    assert_eq!(cols.len(), 30, "{line}");
    cols[1..4].iter().chain(&cols[9..]).map(|c| c.parse::<f64>().expect("a number").to_bits()).collect()
}

#[test]
fn localize_matches_the_core_in_process_bit_for_bit_from_a_file_and_from_stdin() {
    let d = dir("e2e");
    let (map, records) = scene(&d, 12);
    let want = expected(&map, &records);
    let input = d.join("frames.bin");
    std::fs::write(&input, stream(&records)).expect("writes");
    let map_s = map.to_str().expect("utf-8");
    for (args, stdin) in [
        (vec!["localize", "--map", map_s, "--input", input.to_str().expect("utf-8"), "--threads", "2"], Vec::new()),
        (vec!["localize", "--map", map_s, "--input", "-", "--format", "binary"], stream(&records)),
    ] {
        let (out, hung) = run(&args, &stdin);
        assert!(!hung && out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let got = lines(&out);
        assert!(got[0].starts_with("# timestamp tx ty tz qx qy qz qw source cov_upper_21"));
        assert!(got[0].ends_with("; pose: world_from_cam in the convention of the map's pose labels"), "{}", got[0]);
        assert_eq!(got.len(), 1 + records.len());
        for (line, want) in got[1..].iter().zip(&want) {
            assert_eq!(&parsed_bits(line), want, "{line}");
        }
    }
    // JSON lines give the same output
    let mut json = Vec::new();
    write_json_header(&mut json).expect("in memory");
    for (i, r) in records.iter().enumerate() {
        write_json_record(&mut json, r, i).expect("valid");
    }
    let (out, _) = run(&["localize", "--map", map_s, "--input", "-", "--stats"], &json);
    assert!(out.status.success());
    let got = lines(&out);
    assert_eq!(got[1..].iter().map(|l| parsed_bits(l)).collect::<Vec<_>>(), want);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("12 frames") && stderr.contains("frames/s") && stderr.contains("peak RSS"), "{stderr}");
    assert!(stderr.contains("median ms per stage: retrieval"), "{stderr}");
}

/// The locator flag on a map saved without a 3D model: `--locator model` (the default) makes
/// the binary build the model as the core does and give the core's model-locator poses and
/// covariances bit for bit; `--locator paper` gives the paper locator's, which differ (so the
/// flag reaches the localizer).
#[test]
fn locator_flag_matches_the_core_in_process_bit_for_bit() {
    let d = dir("e2e-model");
    let (map, records) = scene(&d, 8);
    let map_s = map.to_str().expect("utf-8");
    let paper =
        expected_with(&map, &records, LocalizerOptions { locator: Locator::Paper, ..LocalizerOptions::default() });
    let model =
        expected_with(&map, &records, LocalizerOptions { locator: Locator::Model, ..LocalizerOptions::default() });
    assert_ne!(paper, model);
    for (flag, want) in [("model", &model), ("paper", &paper)] {
        let (out, hung) = run(&["localize", "--map", map_s, "--input", "-", "--locator", flag], &stream(&records));
        assert!(!hung && out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        let got = lines(&out);
        assert_eq!(&got[1..].iter().map(|l| parsed_bits(l)).collect::<Vec<_>>(), want, "--locator {flag}");
    }
    let (out, _) = run(&["localize", "--map", map_s, "--input", "-", "--locator", "nearest"], &stream(&records));
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("locator"));
}

#[test]
fn info_describes_the_map_and_refuses_a_corrupt_one() {
    let d = dir("info");
    let (map, _) = scene(&d, 0);
    let (out, _) = run(&["info", map.to_str().expect("utf-8")], b"");
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    for want in [
        "format            geoloc-map version 1",
        "keyframes         30",
        "binary (32 bytes, Hamming)",
        "bag of words",
        "pose covariances  no",
        "map noise         none: not estimated",
        "fx 525 fy 525 cx 320 cy 240",
        "camera estimate   none (the given intrinsics are used as they are)",
        "pose labels       as given (not adjusted)",
        "3D model          none stored (the model locator builds it when it starts)",
        "synthetic",
    ] {
        assert!(text.contains(want), "{want:?} not in\n{text}");
    }
    let mut bytes = std::fs::read(&map).expect("reads");
    let bad = d.join("bad.geoloc");
    let n = bytes.len();
    bytes[n - 100] ^= 0x10;
    std::fs::write(&bad, &bytes).expect("writes");
    let (out, _) = run(&["info", bad.to_str().expect("utf-8")], b"");
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.starts_with("geoloc-rs: error: ") && err.contains("checksum"), "{err}");
    std::fs::write(&bad, &bytes[..n / 2]).expect("writes");
    let (out, _) = run(&["localize", "--map", bad.to_str().expect("utf-8"), "--input", "-"], b"");
    assert_eq!(out.status.code(), Some(1));
    assert!(out.stdout.is_empty(), "nothing written for a refused map");
}

#[test]
fn bad_frames_stop_with_the_frame_named_and_earlier_lines_kept() {
    let d = dir("bad");
    let (map, records) = scene(&d, 4);
    let map_s = map.to_str().expect("utf-8");
    let full = stream(&records);
    let mut backwards = records.clone();
    backwards[2].timestamp = backwards[1].timestamp;
    let mut wide = records.clone();
    wide[3].descriptors = DescriptorSet::Binary { data: vec![0; 64 * wide[3].keypoints.len()], width: 64 };
    let cases: Vec<(Vec<u8>, usize, &str)> = vec![
        (full[..full.len() - 7].to_vec(), 3, "frame 3: truncated record"),
        (stream(&backwards), 2, "frame 2: timestamp"),
        (stream(&wide), 3, "frame 3: binary descriptors of width 64, but the map holds binary descriptors of width 32"),
    ];
    for (bytes, good, message) in cases {
        let out_path = d.join("poses.txt");
        let (out, hung) =
            run(&["localize", "--map", map_s, "--input", "-", "--output", out_path.to_str().expect("utf-8")], &bytes);
        assert!(!hung);
        assert_eq!(out.status.code(), Some(1));
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(message) && err.lines().count() == 1, "{err}");
        let written = std::fs::read_to_string(&out_path).expect("output kept");
        assert_eq!(written.lines().count(), 1 + good, "{written}");
    }
}

/// `geoloc-rs localize --input - --output out_path` on a live stream: `sent` written and
/// flushed, stdin left open (the child and its stdin).
#[cfg(unix)]
fn live_run(map: &str, out_path: &Path, sent: &[u8]) -> (std::process::Child, std::process::ChildStdin) {
    let mut child = spawn(&["localize", "--map", map, "--input", "-", "--output", out_path.to_str().expect("utf-8")]);
    let mut pipe = child.stdin.take().expect("piped");
    pipe.write_all(sent).expect("writes");
    pipe.flush().expect("flushes");
    (child, pipe)
}

/// On a live stream a signal is how a run ends: SIGINT, SIGTERM and SIGHUP end it as the end
/// of the stream does — the lines so far in `--output`, no temp file left — with the exit
/// status 128 + the signal (the signal used to kill it, leaving the poses in a temp file).
#[cfg(unix)]
#[test]
fn a_signal_ends_a_live_run_with_its_lines_written() {
    let d = dir("signal");
    let (map, records) = scene(&d, 3);
    let map_s = map.to_str().expect("utf-8");
    for (signal, status) in [("INT", 130), ("TERM", 143), ("HUP", 129)] {
        let out_path = d.join("poses.txt");
        std::fs::write(&out_path, "the previous run\n").expect("writes");
        // the camera keeps the stream open: every frame sent, no end of stream
        let (child, pipe) = live_run(map_s, &out_path, &stream(&records));
        // wait until the three lines are in the temp file (header + frames)
        let start = Instant::now();
        let written = || {
            file_names(&d)
                .iter()
                .filter(|n| n.starts_with(".poses.txt."))
                .any(|n| std::fs::read_to_string(d.join(n)).is_ok_and(|t| t.lines().count() == 1 + records.len()))
        };
        while !written() {
            assert!(start.elapsed() < HANG, "the frames were never written");
            std::thread::sleep(Duration::from_millis(5));
        }
        let sent =
            Command::new("kill").args([format!("-{signal}"), child.id().to_string()]).status().expect("kill runs");
        assert!(sent.success());
        let out = child.wait_with_output().expect("exits");
        drop(pipe);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(status), "SIG{signal}: {err}");
        assert!(err.contains("the lines written so far are in"), "{err}");
        let kept = std::fs::read_to_string(&out_path).expect("output");
        assert_eq!(kept.lines().count(), 1 + records.len(), "SIG{signal}: {kept}");
        let names = file_names(&d);
        assert!(!names.iter().any(|n| n.ends_with(".tmp")), "SIG{signal}: {names:?}");
    }
}

/// Ctrl-C on `camera | geoloc-rs …` ends the stream as it signals: a truncated last record
/// and the signal arrive together. The run is the signal's (exit 130, the output named), not
/// an input error's (exit 1, "truncated record") — it was the error's in 5 of 8 runs on a busy
/// CPU.
#[cfg(unix)]
#[test]
fn a_signal_with_the_end_of_the_stream_is_the_signals() {
    let d = dir("signal-eof");
    let (map, records) = scene(&d, 3);
    let map_s = map.to_str().expect("utf-8");
    let bytes = stream(&records);
    for round in 0..4 {
        let out_path = d.join("poses.txt");
        let (child, pipe) = live_run(map_s, &out_path, &bytes[..bytes.len() - 100]); // the last record cut short
        std::thread::sleep(Duration::from_millis(300)); // the whole records localized
        let kill = Command::new("kill").args(["-INT", &child.id().to_string()]).spawn().expect("kill runs");
        drop(pipe); // the end of the stream, with the signal
        let out = child.wait_with_output().expect("exits");
        let _ = kill.wait_with_output();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(130), "round {round}: {err}");
        assert!(err.contains("the lines written so far are in") && !err.contains("truncated"), "round {round}: {err}");
    }
}

/// File names are bytes on Linux: `--input` and `--output` of bytes that are not UTF-8 (a
/// folder a Python tool made) are taken as they are, like `--map` — they were refused as
/// "invalid UTF-8 was detected in one or more arguments".
#[cfg(unix)]
#[test]
fn paths_that_are_not_utf8_are_taken_as_they_are() {
    use std::os::unix::ffi::OsStrExt;
    let d = dir("bytes");
    let (map, records) = scene(&d, 2);
    let odd = |ext: &str| d.join(std::ffi::OsStr::from_bytes(&[b'x', 0xff, b'.', ext.as_bytes()[0]]));
    let (input, output) = (odd("b"), odd("t"));
    std::fs::write(&input, stream(&records)).expect("writes");
    let out = Command::new(env!("CARGO_BIN_EXE_geoloc-rs"))
        .arg("localize")
        .arg("--map")
        .arg(&map)
        .arg("--input")
        .arg(&input)
        .arg("--output")
        .arg(&output)
        .env("GEOLOC_NUM_THREADS", "1")
        .output()
        .expect("binary runs");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(std::fs::read_to_string(&output).expect("written").lines().count(), 1 + records.len());
}

#[test]
fn mutated_streams_never_panic_or_hang() {
    let d = dir("fuzz");
    let (map, records) = scene(&d, 3);
    let map_s = map.to_str().expect("utf-8");
    let bytes = stream(&records);
    let mut rng = SplitMix64::new(2024);
    let (mut ok, mut refused) = (0, 0);
    for case in 0..FUZZ_CASES {
        let mut bad = bytes.clone();
        for _ in 0..1 + rng.next_u64() % 3 {
            let i = (rng.next_u64() % bad.len() as u64) as usize;
            bad[i] ^= 1 << (rng.next_u64() % 8);
        }
        if case % 2 == 0 {
            bad.truncate((rng.next_u64() % bad.len() as u64) as usize);
        }
        let (out, hung) = run(&["localize", "--map", map_s, "--input", "-"], &bad);
        assert!(!hung, "case {case} hung");
        let code = out.status.code();
        assert!(
            code.is_some() && code != Some(PANIC_STATUS),
            "case {case}: {:?}\n{}",
            out.status,
            String::from_utf8_lossy(&out.stderr)
        );
        let written = lines(&out);
        assert!(written.iter().skip(1).all(|l| l.split(' ').count() == 30), "case {case}");
        if code == Some(0) {
            ok += 1;
        } else {
            refused += 1;
            assert!(String::from_utf8_lossy(&out.stderr).starts_with("geoloc-rs: error: "), "case {case}");
        }
    }
    eprintln!("{FUZZ_CASES} mutated streams: {ok} read to a clean end, {refused} refused; no panic, no hang");
}

/// Flips 1–3 bytes inside one record's payload and re-seals its checksum, so the mutation
/// gets past the checksum to the reader's structural checks and the localizer's.
fn resealed(bytes: &[u8], rng: &mut SplitMix64) -> Vec<u8> {
    let mut bad = bytes.to_vec();
    let mut starts = Vec::new();
    let mut at = 16;
    while at < bad.len() {
        starts.push(at);
        at += 4 + u32::from_le_bytes(bad[at..at + 4].try_into().expect("4 bytes")) as usize;
    }
    let start = starts[(rng.next_u64() % starts.len() as u64) as usize];
    let len = u32::from_le_bytes(bad[start..start + 4].try_into().expect("4 bytes")) as usize;
    let body = start + 4..start + 4 + len - 8;
    for _ in 0..1 + rng.next_u64() % 3 {
        let i = body.start + (rng.next_u64() % (len as u64 - 8)) as usize;
        bad[i] = (rng.next_u64() & 0xff) as u8;
    }
    let mut h = geoloc_core::checksum::Fnv1a::new();
    h.update(&bad[body.clone()]);
    bad[body.end..body.end + 8].copy_from_slice(&h.finish().to_le_bytes());
    bad
}

/// In-process cases of re-sealed mutations (the binary's read → check → localize loop).
const RESEALED_CASES: usize = 1000;
/// Of which every this-many-th also runs through the real binary.
const RESEALED_BINARY_EVERY: usize = 50;

#[test]
fn resealed_mutations_reach_the_localizer_and_never_panic_or_hang() {
    let d = dir("reseal");
    let (map_path, records) = scene(&d, 2);
    let map_s = map_path.to_str().expect("utf-8");
    let (map, _) = Map::load(&map_path).expect("loads");
    let map = Arc::new(map);
    let bytes = stream(&records);
    let mut rng = SplitMix64::new(77);
    let (mut read_ok, mut localized) = (0, 0);
    // one localizer, its history reset per case: the triangulated groups stay cached
    let mut loc = Localizer::new(Arc::clone(&map), LocalizerOptions::default()).expect("options");
    for case in 0..RESEALED_CASES {
        let bad = resealed(&bytes, &mut rng);
        loc.reset();
        let reader = geoloc_core::frames::FrameReader::new(bad.as_slice()).expect("header intact");
        for record in reader {
            let Ok(r) = record else { break };
            read_ok += 1;
            let frame = Frame {
                timestamp: r.timestamp,
                keypoints: &r.keypoints,
                descriptors: r.descriptors.view(),
                global: None,
                pixel_sigmas: Some(&r.pixel_sigmas),
            };
            if loc.localize(&frame).is_ok() {
                localized += 1;
            }
        }
        if case % RESEALED_BINARY_EVERY == 0 {
            let (out, hung) = run(&["localize", "--map", map_s, "--input", "-"], &bad);
            assert!(!hung, "case {case} hung");
            assert!(out.status.code().is_some_and(|c| c != PANIC_STATUS), "case {case}: {:?}", out.status);
        }
    }
    eprintln!("{RESEALED_CASES} re-sealed mutations: {read_ok} records read, {localized} localized; no panic, no hang");
}

// ------------------------------------------------------------------ files a robot meets

/// `--output` naming an input — the same path, a `./` spelling, a symlink, a hard link, the
/// map, or the file stdin is redirected from — is refused with `--output` and the input
/// named, exit 1, and every input byte-identical afterwards.
#[test]
fn an_output_that_is_an_input_is_refused_and_the_inputs_kept() {
    let d = dir("alias");
    let (map, records) = scene(&d, 3);
    let input = d.join("frames.bin");
    std::fs::write(&input, stream(&records)).expect("writes");
    let symlink = d.join("frames-link.bin");
    let hard = d.join("frames-hard.bin");
    let _ = std::fs::remove_file(&symlink);
    let _ = std::fs::remove_file(&hard);
    std::os::unix::fs::symlink(&input, &symlink).expect("symlink");
    std::fs::hard_link(&input, &hard).expect("hard link");
    let dotted = d.join(".").join("frames.bin");
    let (map_bytes, input_bytes) = (std::fs::read(&map).expect("reads"), std::fs::read(&input).expect("reads"));
    let s = |p: &Path| p.to_str().expect("utf-8").to_owned();
    for (output, aliased) in [
        (s(&input), "--input"),
        (s(&dotted), "--input"),
        (s(&symlink), "--input"),
        (s(&hard), "--input"),
        (s(&map), "--map"),
    ] {
        let (out, hung) = run(&["localize", "--map", &s(&map), "--input", &s(&input), "--output", &output], b"");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!hung && out.status.code() == Some(1), "{output}: {err}");
        assert!(err.contains(&format!("--output {output}: is the same file as {aliased}")), "{err}");
        assert_eq!(std::fs::read(&map).expect("reads"), map_bytes, "{output}: the map is untouched");
        assert_eq!(std::fs::read(&input).expect("reads"), input_bytes, "{output}: the input is untouched");
    }
    // stdin redirected from the output file
    let child = Command::new(env!("CARGO_BIN_EXE_geoloc-rs"))
        .args(["localize", "--map", &s(&map), "--input", "-", "--output", &s(&input)])
        .stdin(std::fs::File::open(&input).expect("opens"))
        .output()
        .expect("runs");
    let err = String::from_utf8_lossy(&child.stderr);
    assert_eq!(child.status.code(), Some(1), "{err}");
    assert!(err.contains("is the same file as --input - (stdin)"), "{err}");
    assert_eq!(std::fs::read(&input).expect("reads"), input_bytes);
    // a distinct output is written, atomically: no temp file is left beside it
    let poses = d.join("poses.txt");
    let (out, _) = run(&["localize", "--map", &s(&map), "--input", &s(&symlink), "--output", &s(&poses)], b"");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert_eq!(std::fs::read_to_string(&poses).expect("written").lines().count(), 1 + records.len());
    let temps: Vec<String> = file_names(&d).into_iter().filter(|n| n.ends_with(".tmp")).collect();
    assert!(temps.is_empty(), "{temps:?}");
    // a folder given as the output is named by the value given ("./": no file name at all;
    // "d/.": the folder it is)
    let out = Command::new(env!("CARGO_BIN_EXE_geoloc-rs"))
        .args(["localize", "--map", &s(&map), "--input", &s(&input), "--output", "./"])
        .current_dir(&d)
        .output()
        .expect("runs");
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("--output ./: expected a file path, not a folder"), "{err}");
    let folder = format!("{}/.", s(&d));
    let (out, _) = run(&["localize", "--map", &s(&map), "--input", &s(&input), "--output", &folder], b"");
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.code() == Some(1) && err.contains("not a regular file (a folder)"), "{err}");
    // a device is written as it is, never replaced
    let (out, _) = run(&["localize", "--map", &s(&map), "--input", &s(&input), "--output", "/dev/null"], b"");
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    assert!(std::fs::metadata("/dev/null").is_ok_and(|m| !m.is_file()), "/dev/null is still a device");
}

/// A FIFO in place of the map or the frame stream (or as the output) is refused at once,
/// named, instead of blocking forever on open.
#[test]
fn a_fifo_in_place_of_a_file_is_refused_without_hanging() {
    let d = dir("fifo");
    let (map, records) = scene(&d, 2);
    let input = d.join("frames.bin");
    std::fs::write(&input, stream(&records)).expect("writes");
    let fifo = d.join("pipe");
    let _ = std::fs::remove_file(&fifo);
    if !Command::new("mkfifo").arg(&fifo).status().is_ok_and(|s| s.success()) {
        return; // no mkfifo on this system
    }
    let (f, m, i) = (fifo.to_str().expect("utf-8"), map.to_str().expect("utf-8"), input.to_str().expect("utf-8"));
    for args in [
        vec!["info", f],
        vec!["localize", "--map", f, "--input", i],
        vec!["localize", "--map", m, "--input", f],
        vec!["localize", "--map", m, "--input", i, "--output", f],
    ] {
        let start = Instant::now();
        let (out, hung) = run(&args, b"");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(!hung && start.elapsed() < Duration::from_secs(5), "{args:?} blocked");
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        assert!(err.contains(&format!("{f}: not a regular file (a FIFO)")), "{args:?}: {err}");
    }
}

/// The adversarial probe's 44-byte stream: a record whose self-consistent sizes claim
/// ~4.12 GB. Under `ulimit -v 2000000` (2 GB of address space) it used to abort (SIGABRT,
/// allocation failure); now it is a clean error naming the record, from a file and from stdin.
#[test]
fn a_huge_record_claim_is_a_clean_error_under_a_memory_limit() {
    let d = dir("claim");
    let (map, _) = scene(&d, 0);
    let (bytes, len) = testing::huge_frame_record_claim();
    let input = d.join("claim.bin");
    std::fs::write(&input, &bytes).expect("writes");
    let bin = env!("CARGO_BIN_EXE_geoloc-rs");
    let (m, i) = (map.to_str().expect("utf-8"), input.to_str().expect("utf-8"));
    for (script, want) in [
        (
            format!("ulimit -v 2000000 && exec '{bin}' localize --map '{m}' --input '{i}'"),
            format!("frame 0: payload length field claims {len} bytes, but only 24 are left in the stream"),
        ),
        (
            format!("ulimit -v 2000000 && exec '{bin}' localize --map '{m}' --input - < '{i}'"),
            format!("frame 0: truncated record (24 of {len} payload bytes)"),
        ),
    ] {
        let out = Command::new("sh").args(["-c", &script]).env("GEOLOC_NUM_THREADS", "1").output().expect("runs");
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{script}: {err}");
        assert!(err.contains(&want), "{script}: {err}");
    }
}

/// A chain vocabulary of 200 000 levels with a valid checksum (written by the core's own map
/// writer): `geoloc-rs info` refuses it at once, naming the depth limit, instead of a load of
/// tens of seconds.
#[test]
fn a_crafted_chain_vocabulary_is_refused_at_once() {
    use geoloc_core::map::file::{self, Tensor, TensorData};
    use geoloc_core::map::{MapHeader, RetrievalHeader};
    const NODES: usize = 200_000;
    let d = dir("chain");
    let (map, _) = scene(&d, 0);
    let mut f = file::read(&map).expect("reads");
    let (offsets, children) = testing::chain_vocabulary(NODES);
    let rows = children.len();
    let tensors = [
        ("vocabulary.node_offsets", vec![offsets.len()], TensorData::I64(offsets)),
        ("vocabulary.children", vec![rows], TensorData::I64(children)),
        ("vocabulary.centres", vec![rows, WIDTH], TensorData::U8(vec![0; rows * WIDTH])),
    ];
    for (name, shape, data) in tensors {
        f.tensors.insert(name.to_owned(), Tensor::new(name, shape, data).expect("consistent"));
    }
    let mut header: MapHeader = serde_json::from_str(&f.header).expect("header");
    header.retrieval = RetrievalHeader::Bow { words: NODES + 1 };
    f.header = serde_json::to_string(&header).expect("header");
    let crafted = d.join("chain.geoloc");
    file::write(&crafted, &f).expect("writes with a valid checksum");
    let start = Instant::now();
    let (out, hung) = run(&["info", crafted.to_str().expect("utf-8")], b"");
    let took = start.elapsed();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!hung && out.status.code() == Some(1), "{err}");
    assert!(err.contains("deeper than the limit of 24 levels (MAX_DEPTH)"), "{err}");
    assert!(took < Duration::from_secs(2), "refused after {took:?}");
}

/// Every option value the core refuses is a usage error (exit 2, the flag named, nothing
/// read), like a bad `--threads` that clap refuses itself; they were input errors (exit 1,
/// the core's field name `top_k`).
#[test]
fn option_values_the_core_refuses_are_usage_errors_naming_the_flag() {
    let d = dir("usage");
    let (map, _) = scene(&d, 1);
    let map_s = map.to_str().expect("utf-8");
    for (flag, value) in [
        ("--top-k", "0"),
        ("--history", "1"),
        ("--pixel-sigma", "nan"),
        ("--gate-sigma", "0"),
        ("--max-residual", "0"),
        ("--threads", "0"),
    ] {
        let (out, hung) = run(&["localize", "--map", map_s, "--input", "-", flag, value], b"");
        assert!(!hung);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{flag} {value}: {err}");
        assert!(err.contains(&format!("'{flag}")), "{flag} {value}: {err}");
        // a usage line, if any, is the subcommand's (not the top level's list of commands)
        assert!(!err.contains("Usage: geoloc-rs <COMMAND>"), "{flag} {value}: {err}");
        assert!(out.stdout.is_empty(), "{flag} {value}: nothing written");
    }
}
