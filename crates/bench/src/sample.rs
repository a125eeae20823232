//! Timing samples: the one helper every benchmark times with.

use std::time::Instant;

/// Observations (milliseconds, or any unit), sorted, with their median and percentiles.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Samples {
    sorted: Vec<f64>,
}

impl Samples {
    /// The samples of `values` (NaNs sort last).
    pub fn new(mut values: Vec<f64>) -> Samples {
        values.sort_by(f64::total_cmp);
        Samples { sorted: values }
    }

    /// How many there are.
    pub fn len(&self) -> usize {
        self.sorted.len()
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.sorted.is_empty()
    }

    /// The median (the upper one of an even count; 0 without samples).
    pub fn median(&self) -> f64 {
        self.sorted
            .get(self.sorted.len() / 2)
            .copied()
            .unwrap_or(0.0)
    }

    /// The `p`-th percentile (0 to 100, nearest rank; 0 without samples).
    pub fn percentile(&self, p: f64) -> f64 {
        if self.sorted.is_empty() {
            return 0.0;
        }
        let rank = (p.clamp(0.0, 100.0) / 100.0 * self.sorted.len() as f64).ceil() as usize;
        self.sorted[rank.clamp(1, self.sorted.len()) - 1]
    }

    /// The smallest (0 without samples).
    pub fn min(&self) -> f64 {
        self.sorted.first().copied().unwrap_or(0.0)
    }

    /// The largest (0 without samples).
    pub fn max(&self) -> f64 {
        self.sorted.last().copied().unwrap_or(0.0)
    }
}

/// Most runs [`sample`] makes, however short each is.
pub const MAX_RUNS: usize = 1000;

/// Wall times of `f` in milliseconds: two warm-up runs (page faults, caches, thread pools),
/// then at least `min_runs` runs and more until about `seconds` have passed (at most
/// [`MAX_RUNS`]).
pub fn sample(seconds: f64, min_runs: usize, mut f: impl FnMut()) -> Samples {
    let r: Result<Samples, std::convert::Infallible> = try_sample(seconds, min_runs, || {
        f();
        Ok(())
    });
    match r {
        Ok(s) => s,
        Err(never) => match never {},
    }
}

/// [`sample`] of a fallible `f`: the first error stops it.
pub fn try_sample<E>(
    seconds: f64,
    min_runs: usize,
    mut f: impl FnMut() -> Result<(), E>,
) -> Result<Samples, E> {
    f()?;
    f()?;
    let mut times = Vec::new();
    let start = Instant::now();
    while times.len() < min_runs.max(1)
        || (start.elapsed().as_secs_f64() < seconds && times.len() < MAX_RUNS)
    {
        let t = Instant::now();
        f()?;
        times.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok(Samples::new(times))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn medians_and_percentiles_are_ranks_of_the_sorted_values() {
        let s = Samples::new(vec![5.0, 1.0, 4.0, 2.0, 3.0]);
        assert_eq!((s.len(), s.median(), s.min(), s.max()), (5, 3.0, 1.0, 5.0));
        assert_eq!(s.percentile(50.0), 3.0);
        assert_eq!(s.percentile(99.0), 5.0);
        assert_eq!(s.percentile(0.0), 1.0);
        assert_eq!(Samples::new(vec![1.0, 2.0]).median(), 2.0);
        assert_eq!(Samples::default().median(), 0.0);
        let mut n = 0;
        let timed = sample(0.0, 3, || n += 1);
        assert_eq!((timed.len(), n), (3, 5), "two warm-ups, then the runs");
        let failed: Result<Samples, &str> = try_sample(1.0, 3, || Err("no"));
        assert_eq!(failed, Err("no"));
    }
}
