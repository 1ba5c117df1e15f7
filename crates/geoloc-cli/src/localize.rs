//! `geoloc-rs localize`: frame records in, one pose line per frame out, flushed as it goes.
//!
//! The localizer is built exactly as `geoloc.Localizer` builds it through the bindings
//! (same options, same defaults), so the same map and the same features give the same bits.
//! Records are read one at a time (a stdin stream works: each line is written as soon as
//! its frame arrives). A frame the localizer cannot place is a `lost` line; a frame that is
//! *invalid* — truncated or corrupt record, non-finite values, descriptors of another kind
//! or width than the map's, a missing global descriptor, a timestamp not after the previous
//! frame's — stops the run with an error naming the frame index; what was written before
//! stays in the output, flushed.
//!
//! Files: `--output FILE` is written atomically ([`geoloc_core::files::AtomicFile`]: a temp
//! file of its own beside FILE, renamed onto it when the run ends, also when it ends with a
//! bad frame, so FILE is always a complete previous or new output); follow the poses live on
//! stdout (`--output -`). A character device (`/dev/null`) is written as it is; a FIFO is
//! refused (pipe stdout instead). An output that is one of the inputs (`--map`, `--input`, or stdin
//! redirected from it; the same path, another spelling, a symlink or a hard link) is refused
//! before anything is read or written. Inputs must be regular files (a FIFO would block the
//! run: pipe into stdin with `--input -` instead); a record length beyond the input file's
//! size is refused before anything is allocated.
//!
//! Signals: SIGINT (Ctrl-C), SIGTERM and SIGHUP end the run as the end of the stream does —
//! the lines written so far stay, an `--output` file is renamed onto its path complete — and
//! the exit status is 128 + the signal's number (130 for Ctrl-C), as a shell reports a
//! process a signal stopped ([`end_on_signal`]). On a live stream a signal is how a run ends.

use std::io::{BufRead, BufReader, Write};
use std::num::NonZero;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};

use geoloc_core::GeolocError;
use geoloc_core::files::{self, AtomicFile};
use geoloc_core::frames::{FrameReader, FrameRecord, read_json_records};
use geoloc_core::localizer::{Frame, Localizer, LocalizerOptions, Locator};
use geoloc_core::map::{Map, MapHeader, RetrievalHeader};
use geoloc_core::matching::DescriptorSet;
use geoloc_core::parallel::{Parallelism, with_parallelism};

use crate::InputFormat;
use crate::output;
use crate::stats::Stats;

/// Options of `geoloc-rs localize`; every localizer default is the core's
/// (`LocalizerOptions::default()`), the same as `geoloc.Localizer`'s.
#[derive(clap::Args, Debug)]
pub struct Args {
    /// The `.geoloc` map (written by `geoloc.Map.save` / `geoloc build-map`).
    #[arg(long)]
    map: PathBuf,
    /// The frame stream (from `geoloc.export_frames`), or `-` for stdin.
    #[arg(long)]
    input: PathBuf,
    /// Encoding of the frame stream.
    #[arg(long, value_enum, default_value_t = InputFormat::Auto)]
    format: InputFormat,
    /// Where the pose lines go (`-`: stdout); an existing file is replaced atomically when the
    /// run ends. Must not be one of the inputs.
    #[arg(long, default_value = "-")]
    output: PathBuf,
    /// Threads of the core's parallel loops (1: sequential). Default: the environment's
    /// GEOLOC_NUM_THREADS / GEOLOC_PARALLELISM, else all cores. Results are identical either way.
    /// At most 256.
    #[arg(long, value_parser = clap::value_parser!(u32).range(1..=geoloc_core::parallel::MAX_THREADS as i64))]
    threads: Option<u32>,
    /// Print a summary on stderr at the end: frames, frames/s, sources, median ms per stage, peak RSS.
    #[arg(long)]
    stats: bool,
    /// Positional σ of a keypoint (px), for PnP and triangulation.
    #[arg(long, default_value_t = LocalizerOptions::default().pixel_sigma())]
    pixel_sigma: f64,
    /// Largest reprojection residual kept (px).
    #[arg(long, default_value_t = LocalizerOptions::default().max_residual_px())]
    max_residual: f64,
    /// Gate of the geometric pose against the motion prediction (σ).
    #[arg(long, default_value_t = LocalizerOptions::default().gate_sigma)]
    gate_sigma: f64,
    /// Fused poses the constant-velocity model is fitted to.
    #[arg(long, default_value_t = LocalizerOptions::default().history)]
    history: usize,
    /// Geometric locator: "paper" (one retrieved keyframe and its group) or "model" (top-k
    /// retrieval against the map's 3D model; built at start when the map has none).
    #[arg(long, default_value_t = LocalizerOptions::default().locator, value_parser = parse_locator)]
    locator: Locator,
    /// Model locator: keyframes retrieved.
    #[arg(long, default_value_t = LocalizerOptions::default().top_k)]
    top_k: usize,
    /// Write the camera's own pose and its covariance (which adds the label-to-camera offset's
    /// uncertainty); by default both are in the convention of the map's pose labels, as
    /// geoloc.Localizer returns them (they differ by the offset the map estimated; `geoloc-rs
    /// info` shows it).
    #[arg(long)]
    camera_pose: bool,
}

fn parse_locator(s: &str) -> Result<Locator, String> {
    s.parse().map_err(|e: GeolocError| e.to_string())
}

type Records = Box<dyn Iterator<Item = geoloc_core::Result<FrameRecord>>>;

/// Runs the command; the error is the one line to print.
pub fn run(args: &Args) -> Result<(), String> {
    let parallelism = match args.threads {
        None => geoloc_core::parallel::configured(),
        Some(1) => Parallelism::Off,
        Some(n) => Parallelism::Threads(NonZero::new(n as usize).ok_or("--threads: must be ≥ 1")?),
    };
    with_parallelism(&parallelism, || localize(args))
}

fn localize(args: &Args) -> Result<(), String> {
    let start = Instant::now();
    refuse_aliased_output(args)?;
    let (map, header) = Map::load(&args.map).map_err(|e| format!("--map: {e}"))?;
    let map = Arc::new(map);
    let mut localizer = Localizer::new(Arc::clone(&map), options(args)).map_err(|e| e.to_string())?;
    let records = open_input(&args.input, args.format)?;
    // watched before the temp file exists: no signal can leave it behind
    let out: SharedOutput = Arc::new(Mutex::new(None));
    let stopping =
        end_on_signal(Arc::clone(&out), if is_dash(&args.output) { "stdout".into() } else { shown(&args.output) })?;
    *locked(&out) = Some(Output::open(&args.output)?);
    // what was written stays, also when a frame stops the run
    let result = localize_frames(args, &map, &header, &mut localizer, records, &out, start);
    // a Ctrl-C on `camera | geoloc-rs` also ends the stream (the camera dies with it): a run
    // that ended with a signal on its way is the signal's to end (exit 128 + it, the output
    // named), not an input error's
    if result.is_err() {
        let since = Instant::now();
        while !stopping.load(Ordering::SeqCst) && since.elapsed() < SIGNAL_GRACE {
            std::thread::sleep(Duration::from_millis(5));
        }
    }
    if stopping.load(Ordering::SeqCst) {
        loop {
            std::thread::park(); // the signal's thread finishes the output and exits
        }
    }
    let finished = finish(&out).map_err(|e| format!("--output {e}"));
    result.and(finished)
}

/// How long a run that ended with an input error waits for a signal that may have ended the
/// stream too before it reports the error.
const SIGNAL_GRACE: Duration = Duration::from_millis(200);

/// The output, shared with the thread that ends the run on a signal; None once finished.
type SharedOutput = Arc<Mutex<Option<Output>>>;

fn locked(out: &Mutex<Option<Output>>) -> MutexGuard<'_, Option<Output>> {
    out.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Writes `line` and flushes it, under the lock: a signal ends the run between lines.
fn write_line(out: &Mutex<Option<Output>>, line: &str) -> std::io::Result<()> {
    let mut guard = locked(out);
    let out = guard.as_mut().ok_or_else(|| std::io::Error::other("the output is finished"))?;
    writeln!(out, "{line}")?;
    out.flush()
}

/// [`Output::finish`], unless finished already.
fn finish(out: &Mutex<Option<Output>>) -> geoloc_core::Result<()> {
    locked(out).take().map_or(Ok(()), Output::finish)
}

/// Watches for SIGINT, SIGTERM and SIGHUP on a thread of its own; the first one finishes
/// `out` (the line being written completes first) and exits with 128 + its number. The lock
/// is held until the exit, so the run writes nothing after the output is finished. (Before,
/// the signal killed the process and left the poses in a temp file beside `--output`.)
///
/// Returns a flag the signal handler itself sets, at delivery, before the thread wakes: the run
/// reads it to leave the ending to that thread.
fn end_on_signal(out: SharedOutput, shown: String) -> Result<Arc<AtomicBool>, String> {
    use signal_hook::consts::{SIGHUP, SIGINT, SIGTERM};
    let watch_error = |e: std::io::Error| format!("cannot watch for signals: {e}");
    let stopping = Arc::new(AtomicBool::new(false));
    for signal in [SIGINT, SIGTERM, SIGHUP] {
        signal_hook::flag::register(signal, Arc::clone(&stopping)).map_err(watch_error)?;
    }
    let mut signals = signal_hook::iterator::Signals::new([SIGINT, SIGTERM, SIGHUP]).map_err(watch_error)?;
    std::thread::spawn(move || {
        if let Some(signal) = signals.forever().next() {
            let mut guard = locked(&out);
            match guard.take().map(Output::finish) {
                Some(Ok(())) => {
                    eprintln!("geoloc-rs: stopped by signal {signal}; the lines written so far are in {shown}")
                }
                Some(Err(e)) => eprintln!("geoloc-rs: stopped by signal {signal}; error: --output {e}"),
                None => eprintln!("geoloc-rs: stopped by signal {signal}"),
            }
            std::process::exit(128 + signal);
        }
    });
    Ok(stopping)
}

fn localize_frames(
    args: &Args,
    map: &Map,
    header: &MapHeader,
    localizer: &mut Localizer,
    records: Records,
    out: &Mutex<Option<Output>>,
    start: Instant,
) -> Result<(), String> {
    let write_err = |e: std::io::Error| format!("--output {}: {e}", shown(&args.output));
    write_line(out, &output::header(args.camera_pose)).map_err(write_err)?;
    let loaded = start.elapsed();
    let loop_start = Instant::now();
    let mut stats = Stats::default();
    let mut previous: Option<f64> = None;
    for (index, record) in records.enumerate() {
        let record = record.map_err(|e| input_error(&args.input, e))?;
        check_record(&record, header, previous, index).map_err(|e| format!("{}: {e}", shown(&args.input)))?;
        previous = Some(record.timestamp);
        let frame = Frame {
            timestamp: record.timestamp,
            keypoints: &record.keypoints,
            descriptors: record.descriptors.view(),
            global: record.global.as_deref(),
            pixel_sigmas: Some(&record.pixel_sigmas),
        };
        let result = localizer.localize(&frame).map_err(|e| format!("{}: frame {index}: {e}", shown(&args.input)))?;
        // in the labels' convention, as the Python Localizer returns it, unless the camera's
        // own pose is asked for
        let result = if args.camera_pose { map.to_camera_convention(result) } else { map.to_label_convention(result) };
        write_line(out, &output::line(record.timestamp, &result)).map_err(write_err)?;
        stats.push(result.timings, result.source);
    }
    if args.stats {
        eprintln!("{}", stats.report(loaded, loop_start.elapsed()));
    }
    Ok(())
}

/// Refuses an `--output` that is one of the inputs (see the module doc); stdin counts as the
/// file it is redirected from, where the system names it (`/dev/stdin`).
fn refuse_aliased_output(args: &Args) -> Result<(), String> {
    let out = args.output.as_path();
    if is_dash(out) || !out.is_file() {
        return Ok(()); // stdout, a device or a new file cannot destroy an input
    }
    let stdin = Path::new("/dev/stdin");
    let inputs: [(&str, &Path); 2] =
        [("--map", args.map.as_path()), ("--input", if is_dash(&args.input) { stdin } else { args.input.as_path() })];
    for (flag, input) in inputs {
        if files::same_file(out, input) {
            let which = if is_dash(&args.input) && flag == "--input" { "- (stdin)".into() } else { shown(input) };
            return Err(format!(
                "--output {}: is the same file as {flag} {which}; refusing to overwrite an input",
                shown(&args.output)
            ));
        }
    }
    Ok(())
}

/// The option values the core refuses ([`LocalizerOptions::check`]), as a usage error naming
/// the flag (`invalid value for '--top-k': must be ≥ 1`): checked before anything is read, so that a bad value
/// exits with the usage status like any other bad option, not with an input error's.
pub fn usage_error(args: &Args) -> Option<String> {
    let Err(GeolocError::InvalidInput { name, reason }) = options(args).check() else { return None };
    let flag = match name.as_str() {
        "top_k" => "--top-k",
        "history" => "--history",
        "pixel_sigma" => "--pixel-sigma",
        "max_residual" => "--max-residual",
        "gate_sigma" => "--gate-sigma",
        other => other,
    };
    Some(format!("invalid value for '{flag}': {reason}"))
}

/// The core's localizer options with the ones `geoloc.Localizer` also exposes set from `args`.
fn options(args: &Args) -> LocalizerOptions {
    LocalizerOptions {
        gate_sigma: args.gate_sigma,
        history: args.history,
        locator: args.locator,
        top_k: args.top_k,
        ..LocalizerOptions::default()
    }
    .with_pixel_noise(args.pixel_sigma, args.max_residual)
}

/// A reader error, prefixed with the input (the reader names the frame: `frame N: …`, or the
/// stream header).
fn input_error(input: &Path, e: GeolocError) -> String {
    format!("{}: {e}", shown(input))
}

/// Whether a path argument is `-` (stdin or stdout).
fn is_dash(path: &Path) -> bool {
    path.as_os_str() == "-"
}

/// A path for messages (bytes that are not UTF-8 shown as U+FFFD): paths are taken as the
/// system gives them, whatever their bytes.
fn shown(path: &Path) -> String {
    path.display().to_string()
}

/// What the map needs of a frame that the reader cannot know: the descriptor kind and width,
/// the global descriptor's length, and a timestamp after the previous frame's.
fn check_record(record: &FrameRecord, header: &MapHeader, previous: Option<f64>, index: usize) -> Result<(), String> {
    let (kind, width) = match &record.descriptors {
        DescriptorSet::Binary { width, .. } => ("binary", *width),
        DescriptorSet::Float { width, .. } => ("float", *width),
    };
    if kind != header.descriptor_kind || width != header.descriptor_width {
        return Err(format!(
            "frame {index}: {kind} descriptors of width {width}, but the map holds {} descriptors of width {}",
            header.descriptor_kind, header.descriptor_width
        ));
    }
    if let RetrievalHeader::Global { dim } | RetrievalHeader::Fused { dim, .. } = header.retrieval {
        match &record.global {
            None => {
                return Err(format!(
                    "frame {index}: the map retrieves by a {dim}-value global descriptor; the frame has none"
                ));
            }
            Some(g) if g.len() != dim => {
                return Err(format!("frame {index}: global descriptor of {} values, the map's have {dim}", g.len()));
            }
            Some(_) => {}
        }
    }
    if let Some(t0) = previous
        && record.timestamp <= t0
    {
        return Err(format!("frame {index}: timestamp {} is not after the previous frame's ({t0})", record.timestamp));
    }
    Ok(())
}

fn open_input(input: &Path, format: InputFormat) -> Result<Records, String> {
    let (mut reader, size): (Box<dyn BufRead>, Option<u64>) = if is_dash(input) {
        (Box::new(BufReader::new(std::io::stdin())), None)
    } else {
        let (file, len) = files::open_regular(input, "the frame stream").map_err(|e| format!("--input {e}"))?;
        (Box::new(BufReader::new(file)), Some(len))
    };
    let format = match format {
        InputFormat::Auto => {
            let first = reader.fill_buf().map_err(|e| format!("--input {}: {e}", shown(input)))?;
            if first.first() == Some(&b'{') { InputFormat::Jsonl } else { InputFormat::Binary }
        }
        other => other,
    };
    Ok(match (format, size) {
        (InputFormat::Jsonl, _) => Box::new(read_json_records(reader)),
        (_, Some(len)) => Box::new(FrameReader::with_size(reader, len).map_err(|e| input_error(input, e))?),
        (_, None) => Box::new(FrameReader::new(reader).map_err(|e| input_error(input, e))?),
    })
}

/// Where the pose lines go: stdout, a character device written as it is (`/dev/null`, a
/// terminal), or a file replaced atomically by [`Output::finish`] (anything else that is not
/// a regular file, such as a FIFO, is refused by [`AtomicFile::create`]).
enum Output {
    Stdout(std::io::Stdout),
    Device(std::fs::File),
    File(AtomicFile),
}

/// Whether `path` is a character device (`/dev/null`, a terminal).
fn is_char_device(path: &Path) -> bool {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        std::fs::metadata(path).is_ok_and(|m| m.file_type().is_char_device())
    }
    #[cfg(not(unix))]
    {
        let _ = path;
        false
    }
}

impl Output {
    fn open(path: &Path) -> Result<Self, String> {
        if is_dash(path) {
            Ok(Self::Stdout(std::io::stdout()))
        } else if is_char_device(path) {
            let device = std::fs::OpenOptions::new().write(true).open(path);
            device.map(Self::Device).map_err(|e| format!("--output {}: {e}", shown(path)))
        } else {
            AtomicFile::create(path).map(Self::File).map_err(|e| format!("--output {e}"))
        }
    }

    /// Renames the file onto its path (nothing to do for stdout or a device).
    fn finish(self) -> geoloc_core::Result<()> {
        match self {
            Self::Stdout(_) | Self::Device(_) => Ok(()),
            Self::File(f) => f.commit(),
        }
    }
}

impl Write for Output {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        match self {
            Self::Stdout(s) => s.write(buf),
            Self::Device(d) => d.write(buf),
            Self::File(f) => f.write(buf),
        }
    }

    fn flush(&mut self) -> std::io::Result<()> {
        match self {
            Self::Stdout(s) => s.flush(),
            Self::Device(d) => d.flush(),
            Self::File(f) => f.flush(),
        }
    }
}
