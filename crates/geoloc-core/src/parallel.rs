//! The one place that decides whether, and on which threads, geoloc-core runs in parallel.
//!
//! Every parallel loop of the crate goes through the helpers below ([`map_indices`],
//! [`map_slice`], [`try_fill_items`]); nothing else calls rayon. Each helper returns its
//! results in input order and never reduces across items in a schedule-dependent order, so
//! results are **bit-identical whatever the thread count**, and with parallelism off.
//!
//! # Environment switch (read once, at the first parallel call of the process)
//! * `GEOLOC_PARALLELISM=false` (or `0`, `off`, `no`): run everything on the calling thread.
//! * `GEOLOC_NUM_THREADS=N` (N ≥ 1): run on a dedicated pool of N threads, built once
//!   (`N = 1` is the calling thread plus nothing: it runs sequentially).
//! * Neither: rayon's global pool (which itself honours `RAYON_NUM_THREADS`).
//!
//! Values that do not parse are ignored (the default applies); counts above [`MAX_THREADS`]
//! run on [`MAX_THREADS`] (results are the same with any count; a pool of 100 000 threads
//! took longer to start than the run). A call made from inside a
//! rayon worker (a caller's own pool, or a nested geoloc loop) runs on that pool. A process
//! forked after the setting was resolved runs its loops on the calling thread: the pool's
//! threads are not copied by a fork.
//! [`with_parallelism`] overrides the setting for one closure on the calling thread (tests
//! and benchmarks use it to compare thread counts within one process).

use std::cell::RefCell;
use std::num::NonZero;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::{Arc, OnceLock};

use rayon::prelude::*;

use crate::error::{GeolocError, Result};

/// Batches with at least this many items are split across rayon's thread pool; smaller ones
/// run on the calling thread, where the pool's start-up and stealing would cost more than
/// the work (an SE(3) exp is ~30 ns).
pub const PARALLEL_MIN_ITEMS: usize = 2048;

/// The most threads a pool gets: more than any machine geoloc runs on has cores to give a
/// loop, few enough that starting the pool costs milliseconds.
pub const MAX_THREADS: usize = 256;

/// How parallel loops run.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum Parallelism {
    /// On the calling thread.
    Off,
    /// On rayon's global pool.
    Global,
    /// On a pool of this many threads (at most [`MAX_THREADS`]: a larger count gets that).
    Threads(NonZero<usize>),
}

impl Parallelism {
    /// The setting of the environment (see the module doc).
    fn from_env() -> Self {
        let off = std::env::var("GEOLOC_PARALLELISM")
            .is_ok_and(|v| matches!(v.trim().to_ascii_lowercase().as_str(), "false" | "0" | "off" | "no"));
        if off {
            return Self::Off;
        }
        match std::env::var("GEOLOC_NUM_THREADS").ok().and_then(|v| v.trim().parse::<usize>().ok()) {
            Some(1) => Self::Off,
            Some(n) => NonZero::new(n).map_or(Self::Global, Self::Threads),
            None => Self::Global,
        }
    }
}

/// What is wrong with a `GEOLOC_NUM_THREADS` value, if anything: not a whole number ≥ 1
/// (ignored: the default applies, every core) or above [`MAX_THREADS`] (capped). Unset or
/// empty is no setting, not a wrong one. A front end prints it, so that a robot capping its
/// CPU use with a typo learns that it did not.
pub fn num_threads_warning(value: Option<&str>) -> Option<String> {
    let v = value.map(str::trim).filter(|v| !v.is_empty())?;
    match v.parse::<usize>() {
        Ok(n) if n > MAX_THREADS => {
            Some(format!("GEOLOC_NUM_THREADS={n} is above {MAX_THREADS}: {MAX_THREADS} threads run"))
        }
        Ok(n) if n >= 1 => None,
        _ => Some(format!(
            "GEOLOC_NUM_THREADS={v:?} is not a thread count (a whole number ≥ 1): ignored, the default applies"
        )),
    }
}

/// [`num_threads_warning`] of this process's environment.
pub fn environment_warning() -> Option<String> {
    num_threads_warning(std::env::var("GEOLOC_NUM_THREADS").ok().as_deref())
}

/// A resolved setting: sequential, or a pool (None: rayon's global one).
#[derive(Clone)]
enum Runner {
    Sequential,
    Pool(Option<Arc<rayon::ThreadPool>>),
}

fn runner_for(p: &Parallelism) -> Runner {
    match p {
        Parallelism::Off => Runner::Sequential,
        Parallelism::Global => Runner::Pool(None),
        Parallelism::Threads(n) => rayon::ThreadPoolBuilder::new()
            .num_threads(n.get().min(MAX_THREADS))
            .thread_name(|i| format!("geoloc-{i}"))
            .build()
            .map_or(Runner::Sequential, |pool| Runner::Pool(Some(Arc::new(pool)))),
    }
}

/// The process-wide setting, from the environment, resolved once, with the id of the process
/// that resolved it.
fn process_runner() -> &'static (u32, Runner) {
    static RUNNER: OnceLock<(u32, Runner)> = OnceLock::new();
    RUNNER.get_or_init(|| (std::process::id(), runner_for(&Parallelism::from_env())))
}

/// The process-wide runner for this process: the resolved one, or sequential in a child
/// forked after it was resolved (Python's multiprocessing `fork`, a robot's supervisor). A
/// fork copies the pool but not its threads, and a loop handed to it would wait forever; on
/// the calling thread it gives the same results (see the module doc).
fn runner_here() -> Runner {
    let (pid, runner) = process_runner();
    if *pid == std::process::id() { runner.clone() } else { Runner::Sequential }
}

thread_local! {
    static OVERRIDE: RefCell<Option<Runner>> = const { RefCell::new(None) };
}

/// The process-wide setting as read from the environment.
pub fn configured() -> Parallelism {
    Parallelism::from_env()
}

/// Runs `f` with parallel loops started on this thread run as `parallelism` says (the
/// environment's setting is restored afterwards, also if `f` panics).
pub fn with_parallelism<R>(parallelism: &Parallelism, f: impl FnOnce() -> R) -> R {
    struct Restore(Option<Runner>);
    impl Drop for Restore {
        fn drop(&mut self) {
            let previous = self.0.take();
            OVERRIDE.with(|o| *o.borrow_mut() = previous);
        }
    }
    let previous = OVERRIDE.with(|o| o.borrow_mut().replace(runner_for(parallelism)));
    let _restore = Restore(previous);
    f()
}

/// Where a loop of `n_items` runs: None on the calling thread, else on the given pool
/// (`Some(None)`: the current one — rayon's global pool, or the worker's pool we are on).
fn pool_for(n_items: usize, min_items: usize) -> Option<Option<Arc<rayon::ThreadPool>>> {
    if n_items < min_items.max(2) {
        return None;
    }
    if rayon::current_thread_index().is_some() {
        return Some(None); // already on a pool's worker: stay there
    }
    match OVERRIDE.with(|o| o.borrow().clone()).unwrap_or_else(runner_here) {
        Runner::Sequential => None,
        Runner::Pool(pool) => Some(pool),
    }
}

/// Runs `f` on `pool` (None: the current pool).
fn install<R: Send>(pool: Option<Arc<rayon::ThreadPool>>, f: impl FnOnce() -> R + Send) -> R {
    match pool {
        Some(pool) => pool.install(f),
        None => f(),
    }
}

/// `[f(0), f(1), …, f(n − 1)]`, in parallel when `n ≥ min_items` (results in index order, so
/// identical whatever the schedule).
pub fn map_indices<T, F>(n: usize, min_items: usize, f: F) -> Vec<T>
where
    T: Send,
    F: Fn(usize) -> T + Sync + Send,
{
    match pool_for(n, min_items) {
        None => (0..n).map(f).collect(),
        Some(pool) => install(pool, || (0..n).into_par_iter().map(f).collect()),
    }
}

/// `items.iter().map(f)`, in parallel when there are at least `min_items` (results in order).
pub fn map_slice<T, U, F>(items: &[T], min_items: usize, f: F) -> Vec<U>
where
    T: Sync,
    U: Send,
    F: Fn(&T) -> U + Sync + Send,
{
    match pool_for(items.len(), min_items) {
        None => items.iter().map(f).collect(),
        Some(pool) => install(pool, || items.par_iter().map(f).collect()),
    }
}

/// Fills `output`, viewed as consecutive items of `item_len` values, with `fill(i, item)`.
///
/// Runs in parallel above [`PARALLEL_MIN_ITEMS`]. If some items fail, the error of the
/// lowest index is returned (deterministic whatever the scheduling) and the contents of
/// `output` are unspecified.
///
/// # Errors
/// The first (lowest-index) error returned by `fill`.
pub fn try_fill_items<F>(output: &mut [f64], item_len: usize, fill: F) -> Result<()>
where
    F: Fn(usize, &mut [f64]) -> Result<()> + Sync,
{
    if item_len == 0 {
        return Err(GeolocError::invalid("item_len", "must be positive"));
    }
    let n_items = output.len() / item_len;
    match pool_for(n_items, PARALLEL_MIN_ITEMS) {
        None => output.chunks_mut(item_len).enumerate().try_for_each(|(i, item)| fill(i, item)),
        Some(pool) => {
            // the failing items are only marked here (an error is a large value: carrying one
            // per item through a reduction cost more than the work of an SE(3) exp); the first
            // of them is filled again for its error, so the error is the same on any schedule
            let first_failed = AtomicUsize::new(usize::MAX);
            install(pool, || {
                output.par_chunks_mut(item_len).enumerate().for_each(|(i, item)| {
                    if fill(i, item).is_err() {
                        first_failed.fetch_min(i, Ordering::Relaxed);
                    }
                });
            });
            match first_failed.into_inner() {
                usize::MAX => Ok(()),
                i => fill(i, &mut output[i * item_len..(i + 1) * item_len]),
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::float_cmp)] // integers stored in f64 compare exactly
mod tests {
    use super::*;

    #[test]
    fn sequential_and_parallel_fill_every_item() {
        for n in [0, 1, 7, PARALLEL_MIN_ITEMS + 5] {
            let mut out = vec![0.0; 2 * n];
            try_fill_items(&mut out, 2, |i, item| {
                item[0] = i as f64;
                item[1] = 2.0 * i as f64;
                Ok(())
            })
            .expect("invariant: fill never fails here");
            for i in 0..n {
                assert_eq!(out[2 * i], i as f64);
                assert_eq!(out[2 * i + 1], 2.0 * i as f64);
            }
        }
    }

    /// The same loop with parallelism off, and on 1, 2 and 4 threads: identical results.
    #[test]
    fn every_setting_gives_the_same_results() {
        let work = || map_indices(10_000, 1, |i| ((i as f64).sqrt() * 1.5).sin().to_bits());
        let reference = with_parallelism(&Parallelism::Off, work);
        for n in [1, 2, 4] {
            let p = Parallelism::Threads(NonZero::new(n).expect("n > 0"));
            assert_eq!(with_parallelism(&p, work), reference, "{n} threads");
        }
        assert_eq!(with_parallelism(&Parallelism::Global, work), reference);
    }

    /// With 2 threads the work really runs on the dedicated pool's workers.
    #[test]
    fn threads_setting_uses_its_pool() {
        let p = Parallelism::Threads(NonZero::new(2).expect("2 > 0"));
        let names =
            with_parallelism(&p, || map_indices(64, 1, |_| std::thread::current().name().unwrap_or("").to_owned()));
        assert!(names.iter().all(|n| n.starts_with("geoloc-")), "{names:?}");
        let names = with_parallelism(&Parallelism::Off, || {
            map_indices(64, 1, |_| std::thread::current().name().unwrap_or("").to_owned())
        });
        let here = std::thread::current().name().unwrap_or("").to_owned();
        assert!(names.iter().all(|n| *n == here));
    }

    /// Unparsable, zero and negative counts are ignored and said so; too many are capped and
    /// said so; a count in range, unset or empty says nothing.
    #[test]
    fn a_wrong_thread_count_is_named() {
        for bad in ["abc", "0", "-1", "1.5", "two"] {
            let w = num_threads_warning(Some(bad)).expect("a warning");
            assert!(w.contains(&format!("{bad:?}")) && w.contains("ignored"), "{w}");
        }
        assert!(num_threads_warning(Some("100000")).expect("a warning").contains("256 threads run"));
        for fine in [None, Some(""), Some("  "), Some("1"), Some(" 8 "), Some("256")] {
            assert_eq!(num_threads_warning(fine), None, "{fine:?}");
        }
    }

    /// A thread count far beyond any machine's runs on a pool of [`MAX_THREADS`] (a pool of
    /// 100 000 threads never finished starting within a minute): the items still run, on at
    /// most that many distinct threads, with the same results.
    #[test]
    fn a_huge_thread_count_gets_a_pool_of_max_threads() {
        let p = Parallelism::Threads(NonZero::new(100_000).expect("positive"));
        let names: Vec<String> = with_parallelism(&p, || {
            map_indices(4 * MAX_THREADS, 1, |_| std::thread::current().name().unwrap_or("").to_owned())
        });
        let distinct: std::collections::BTreeSet<&String> = names.iter().collect();
        assert!(names.iter().all(|n| n.starts_with("geoloc-")) && distinct.len() <= MAX_THREADS, "{}", distinct.len());
        let squares = |_: &()| map_indices(1000, 1, |i| (i * i) as u64);
        assert_eq!(with_parallelism(&p, || squares(&())), with_parallelism(&Parallelism::Off, || squares(&())));
    }

    /// Several items fail: the error is the lowest failing item's, sequentially and on 1–4
    /// threads alike.
    #[test]
    fn the_first_failing_item_gives_the_error_on_any_schedule() {
        let n = 4 * PARALLEL_MIN_ITEMS;
        let failing = [3 * PARALLEL_MIN_ITEMS + 1, PARALLEL_MIN_ITEMS + 7, 2 * PARALLEL_MIN_ITEMS];
        let settings = [Parallelism::Off, Parallelism::Global]
            .into_iter()
            .chain((1..=4).map(|t| Parallelism::Threads(NonZero::new(t).expect("positive"))));
        for parallelism in settings {
            let mut out = vec![0.0; 3 * n];
            let err = with_parallelism(&parallelism, || {
                try_fill_items(&mut out, 3, |i, item| {
                    item[0] = i as f64;
                    if failing.contains(&i) { Err(GeolocError::invalid("item", format!("{i}"))) } else { Ok(()) }
                })
            })
            .expect_err("three items fail");
            assert_eq!(err.to_string(), format!("item: {}", PARALLEL_MIN_ITEMS + 7), "{parallelism:?}");
        }
    }

    #[test]
    fn zero_item_len_is_an_error() {
        assert!(try_fill_items(&mut [], 0, |_, _| Ok(())).is_err());
    }
}
