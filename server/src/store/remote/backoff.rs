//! Waits with jitter for the loops this crate runs against the object store: following the
//! head, and a writer that lost the head race trying again.
//!
//! Without jitter, replicas started together poll the head in lockstep, and replicas that all
//! saw the store fail (or all lost one race) come back at the same instant, so the store sees
//! bursts instead of a steady rate. The requests themselves are retried by object_store (see
//! `docs/scaling.md`); these are the waits between whole operations.

use rand::{Rng, RngExt};
use std::time::Duration;

/// Exponential backoff with "equal jitter": the `n`-th wait (from 1) is drawn uniformly from
/// `[c / 2, c]` with `c = min(max, first * 2^(n - 1))`. Half of each wait is a floor, so a
/// failing peer is not hammered; the other half spreads the waiters apart.
#[derive(Debug, Clone)]
pub struct Backoff {
    first: Duration,
    max: Duration,
    waits: u32,
}

impl Backoff {
    /// A backoff whose first ceiling is `first`, doubling up to `max` (at least `first`).
    pub fn new(first: Duration, max: Duration) -> Backoff {
        Backoff {
            first,
            max: max.max(first),
            waits: 0,
        }
    }

    /// How many waits were taken since the start or the last [`Backoff::reset`].
    pub fn waits(&self) -> u32 {
        self.waits
    }

    /// The range the next wait is drawn from.
    pub fn bounds(&self) -> (Duration, Duration) {
        let doublings = self.waits.min(31);
        let ceiling = self.first.saturating_mul(1 << doublings).min(self.max);
        (ceiling / 2, ceiling)
    }

    /// The next wait, drawn from [`Backoff::bounds`] with the thread's random generator.
    pub fn next_wait(&mut self) -> Duration {
        self.next_wait_with(&mut rand::rng())
    }

    /// The next wait, drawn from [`Backoff::bounds`] with `rng`.
    pub fn next_wait_with(&mut self, rng: &mut impl Rng) -> Duration {
        let (low, high) = self.bounds();
        self.waits = self.waits.saturating_add(1);
        uniform(rng, low, high)
    }

    /// Starts over from the first ceiling (after a success).
    pub fn reset(&mut self) {
        self.waits = 0;
    }
}

/// `every` moved by up to a quarter of itself either way, uniformly: the mean interval stays
/// `every`, and processes that started together drift apart within a few intervals.
pub fn jittered(every: Duration) -> Duration {
    jittered_with(every, &mut rand::rng())
}

/// [`jittered`] with `rng`.
pub fn jittered_with(every: Duration, rng: &mut impl Rng) -> Duration {
    uniform(rng, every - every / 4, every + every / 4)
}

/// Uniform in `[low, high]`, to the nanosecond.
fn uniform(rng: &mut impl Rng, low: Duration, high: Duration) -> Duration {
    let low_ns = u64::try_from(low.as_nanos()).unwrap_or(u64::MAX);
    let high_ns = u64::try_from(high.as_nanos())
        .unwrap_or(u64::MAX)
        .max(low_ns);
    Duration::from_nanos(rng.random_range(low_ns..=high_ns))
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::StdRng;
    use rand::SeedableRng;

    const MS: Duration = Duration::from_millis(1);

    #[test]
    fn each_wait_lies_within_half_to_all_of_a_doubling_capped_ceiling() {
        let mut rng = StdRng::seed_from_u64(7);
        let mut backoff = Backoff::new(10 * MS, 500 * MS);
        // Ceilings by hand: 10, 20, 40, 80, 160, 320, then the cap 500 from then on.
        let ceilings = [10, 20, 40, 80, 160, 320, 500, 500, 500, 500];
        for (n, ceiling) in ceilings.into_iter().enumerate() {
            assert_eq!(backoff.waits(), n as u32);
            assert_eq!(
                backoff.bounds(),
                (ceiling * MS / 2, ceiling * MS),
                "wait {n}"
            );
            let wait = backoff.next_wait_with(&mut rng);
            assert!(
                wait >= ceiling * MS / 2 && wait <= ceiling * MS,
                "wait {n}: {wait:?} outside [{}, {ceiling}] ms",
                ceiling / 2
            );
        }
        backoff.reset();
        assert_eq!(backoff.bounds(), (5 * MS, 10 * MS));
    }

    #[test]
    fn the_ceiling_never_overflows_and_a_cap_below_the_first_wait_is_raised_to_it() {
        let mut backoff = Backoff::new(Duration::from_secs(1), Duration::from_secs(30));
        for _ in 0..200 {
            backoff.next_wait();
        }
        assert_eq!(
            backoff.bounds(),
            (Duration::from_secs(15), Duration::from_secs(30))
        );
        let backoff = Backoff::new(Duration::from_secs(2), Duration::from_secs(1));
        assert_eq!(
            backoff.bounds(),
            (Duration::from_secs(1), Duration::from_secs(2))
        );
    }

    #[test]
    fn waits_at_one_step_are_spread_over_their_range_not_equal() {
        // 1,000 replicas that all failed once: their second waits cover [10, 20] ms, so they do
        // not come back together. Fifths of the range each get a share near 1/5 (200 +- 60 is
        // more than 4 standard deviations of a binomial(1000, 0.2)).
        let mut rng = StdRng::seed_from_u64(11);
        let mut fifths = [0u32; 5];
        for _ in 0..1000 {
            let mut backoff = Backoff::new(10 * MS, Duration::from_secs(1));
            backoff.next_wait_with(&mut rng);
            let wait = backoff.next_wait_with(&mut rng);
            assert!((10 * MS..=20 * MS).contains(&wait), "{wait:?}");
            let fifth = ((wait - 10 * MS).as_nanos() * 5 / (10 * MS).as_nanos()).min(4);
            fifths[fifth as usize] += 1;
        }
        for count in fifths {
            assert!((140..=260).contains(&count), "{fifths:?}");
        }
    }

    #[test]
    fn a_jittered_interval_stays_within_a_quarter_and_keeps_its_mean() {
        let mut rng = StdRng::seed_from_u64(3);
        let every = 100 * MS;
        let mut total = Duration::ZERO;
        let (mut lowest, mut highest) = (Duration::MAX, Duration::ZERO);
        for _ in 0..10_000 {
            let wait = jittered_with(every, &mut rng);
            assert!((75 * MS..=125 * MS).contains(&wait), "{wait:?}");
            total += wait;
            lowest = lowest.min(wait);
            highest = highest.max(wait);
        }
        // The mean of 10,000 uniform draws on [75, 125] ms: 100 ms, standard error 0.14 ms.
        let mean = total / 10_000;
        assert!((99 * MS..=101 * MS).contains(&mean), "{mean:?}");
        assert!(
            lowest < 76 * MS && highest > 124 * MS,
            "{lowest:?} {highest:?}"
        );
    }
}
