//! The `--stats` summary: frames, throughput, per-stage median time, peak memory.

use std::time::Duration;

use geoloc_core::localizer::Timings;
use geoloc_core::stats::EvenMedian;

/// Per-frame stage times, collected for the summary.
#[derive(Default)]
pub struct Stats {
    timings: Vec<Timings>,
    sources: [usize; 4],
}

/// Median of `values` (mean of the middle two for an even count); NaN when empty.
fn median(mut values: Vec<f64>) -> f64 {
    geoloc_core::stats::median(&mut values, EvenMedian::Mean).unwrap_or(f64::NAN)
}

/// Peak resident set size in kB (`VmHWM` of /proc/self/status), where Linux provides it.
pub fn peak_rss_kb() -> Option<u64> {
    let status = std::fs::read_to_string("/proc/self/status").ok()?;
    let line = status.lines().find(|l| l.starts_with("VmHWM:"))?;
    line.split_whitespace().nth(1)?.parse().ok()
}

impl Stats {
    /// Records one localized frame.
    pub fn push(&mut self, timings: Timings, source: geoloc_core::localizer::Source) {
        self.timings.push(timings);
        let i = geoloc_core::localizer::Source::ALL.iter().position(|s| *s == source).unwrap_or(3);
        self.sources[i] += 1;
    }

    /// The summary lines (map loading and the frame loop timed separately).
    pub fn report(&self, load: Duration, frames: Duration) -> String {
        let n = self.timings.len();
        let secs = frames.as_secs_f64();
        let rate = if secs > 0.0 { n as f64 / secs } else { f64::NAN };
        let mut out = format!(
            "geoloc-rs stats: {n} frames in {secs:.3} s ({rate:.1} frames/s); map loaded in {:.3} s\n",
            load.as_secs_f64()
        );
        let sources: Vec<String> =
            geoloc_core::localizer::Source::ALL.iter().zip(self.sources).map(|(s, c)| format!("{s} {c}")).collect();
        out += &format!("  sources: {}\n", sources.join(", "));
        let medians: Vec<String> = Timings::STAGES
            .iter()
            .enumerate()
            .map(|(i, name)| format!("{name} {:.3}", median(self.timings.iter().map(|t| t.stages()[i].1).collect())))
            .collect();
        out += &format!("  median ms per stage: {}\n", medians.join(", "));
        out += &match peak_rss_kb() {
            Some(kb) => format!("  peak RSS: {:.1} MiB ({kb} kB, VmHWM)", kb as f64 / 1024.0),
            None => "  peak RSS: unavailable (no /proc/self/status on this system)".to_string(),
        };
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_odd_even_and_empty() {
        assert_eq!(median(vec![3.0, 1.0, 2.0]).to_bits(), 2.0f64.to_bits());
        assert_eq!(median(vec![4.0, 1.0, 2.0, 3.0]).to_bits(), 2.5f64.to_bits());
        assert!(median(vec![]).is_nan());
    }
}
