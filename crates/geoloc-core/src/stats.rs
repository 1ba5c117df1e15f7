//! Small statistics shared by the estimators, the tests and the tools: the median (the one
//! robust location/scale summary the crate uses) and the χ² distribution ([`chi2`]: every
//! χ² quantile the crate tests against, its CDF and quantile function).

pub mod chi2;

/// Which middle element the median of an even number of values is.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum EvenMedian {
    /// The upper of the two middle values, `sorted[n / 2]`: always one of the data (the
    /// robust scale estimates and the test summaries use it).
    Upper,
    /// The mean of the two middle values, ½(`sorted[n/2 − 1]` + `sorted[n/2]`): the textbook
    /// median (the motion model's process-noise estimate and the robot binary's timings).
    Mean,
}

/// The median of `values`, sorting them in place by [`f64::total_cmp`]; None when empty.
///
/// Odd n: the middle value. Even n: per `even` ([`EvenMedian`]). NaN values are not skipped:
/// `total_cmp` orders a positive NaN above +∞ and a negative NaN below −∞, so a few NaNs
/// shift the median by as many places and it is NaN only when the middle lands on one.
///
/// ```
/// use geoloc_core::stats::{EvenMedian, median};
/// assert_eq!(median(&mut [3.0, 1.0, 2.0], EvenMedian::Upper), Some(2.0));
/// assert_eq!(median(&mut [4.0, 1.0, 2.0, 3.0], EvenMedian::Upper), Some(3.0));
/// assert_eq!(median(&mut [4.0, 1.0, 2.0, 3.0], EvenMedian::Mean), Some(2.5));
/// assert_eq!(median(&mut [], EvenMedian::Mean), None);
/// ```
pub fn median(values: &mut [f64], even: EvenMedian) -> Option<f64> {
    if values.is_empty() {
        return None;
    }
    values.sort_by(f64::total_cmp);
    let n = values.len();
    Some(match even {
        EvenMedian::Mean if n.is_multiple_of(2) => 0.5 * (values[n / 2 - 1] + values[n / 2]),
        _ => values[n / 2],
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_even_empty_and_nan() {
        for even in [EvenMedian::Upper, EvenMedian::Mean] {
            assert_eq!(median(&mut [5.0], even), Some(5.0));
            assert_eq!(median(&mut [3.0, -1.0, 2.0], even), Some(2.0));
            assert_eq!(median(&mut [], even), None);
        }
        assert_eq!(median(&mut [1.0, 4.0, 2.0, 3.0], EvenMedian::Upper), Some(3.0));
        assert_eq!(median(&mut [1.0, 4.0, 2.0, 3.0], EvenMedian::Mean).map(f64::to_bits), Some(2.5f64.to_bits()));
        // NaN sorts last (positive) and moves the middle by one place
        assert_eq!(median(&mut [f64::NAN, 1.0, 2.0], EvenMedian::Upper), Some(2.0));
        assert!(median(&mut [f64::NAN, f64::NAN, 1.0], EvenMedian::Upper).is_some_and(f64::is_nan));
    }
}
