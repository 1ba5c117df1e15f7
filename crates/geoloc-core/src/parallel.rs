//! The one place that decides whether a batch runs on rayon.

use rayon::prelude::*;

use crate::error::{GeolocError, Result};

/// Batches with at least this many items are split across rayon's thread pool; smaller ones
/// run on the calling thread, where the pool's start-up and stealing would cost more than
/// the work (an SE(3) exp is ~30 ns).
pub const PARALLEL_MIN_ITEMS: usize = 2048;

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
    if n_items >= PARALLEL_MIN_ITEMS {
        let first_error = output
            .par_chunks_mut(item_len)
            .enumerate()
            .filter_map(|(i, item)| fill(i, item).err().map(|e| (i, e)))
            .min_by_key(|(i, _)| *i);
        first_error.map_or(Ok(()), |(_, e)| Err(e))
    } else {
        output.chunks_mut(item_len).enumerate().try_for_each(|(i, item)| fill(i, item))
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

    #[test]
    fn reports_lowest_failing_index() {
        let n = PARALLEL_MIN_ITEMS * 4;
        let mut out = vec![0.0; n];
        let err = try_fill_items(&mut out, 1, |i, _| {
            if i % 1000 == 999 { Err(GeolocError::invalid(format!("x{i}"), "bad")) } else { Ok(()) }
        })
        .expect_err("items fail");
        assert_eq!(err, GeolocError::invalid("x999", "bad"));
    }

    #[test]
    fn zero_item_len_is_an_error() {
        assert!(try_fill_items(&mut [], 0, |_, _| Ok(())).is_err());
    }
}
