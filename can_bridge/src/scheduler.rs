//! Absolute-deadline tick scheduling and lateness statistics.
//!
//! Deadline k is `origin + k * period`: wake-ups never accumulate drift. When
//! a tick's work ends at or after the next deadline (an overrun), the missed
//! deadlines are skipped, never run back to back.

/// A monotonic clock that can sleep to an absolute time; injected in tests.
pub trait Clock: Send {
    /// Monotonic time, ns.
    fn now_ns(&self) -> u64;
    /// Sleep until the monotonic time `deadline_ns` (returns at once if past).
    fn sleep_until_ns(&self, deadline_ns: u64);
}

/// `CLOCK_MONOTONIC` with `clock_nanosleep(TIMER_ABSTIME)`.
#[derive(Clone, Copy, Debug, Default)]
pub struct MonotonicClock;

/// `CLOCK_MONOTONIC` now, ns.
pub fn monotonic_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec.
    unsafe {
        libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts);
    }
    (ts.tv_sec as u64).saturating_mul(1_000_000_000) + ts.tv_nsec as u64
}

/// `CLOCK_REALTIME` now, ns since the Unix epoch (for log time stamps).
pub fn realtime_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `ts` is a valid, writable timespec.
    unsafe {
        libc::clock_gettime(libc::CLOCK_REALTIME, &mut ts);
    }
    (ts.tv_sec as u64).saturating_mul(1_000_000_000) + ts.tv_nsec as u64
}

impl Clock for MonotonicClock {
    fn now_ns(&self) -> u64 {
        monotonic_ns()
    }

    fn sleep_until_ns(&self, deadline_ns: u64) {
        let ts = libc::timespec {
            tv_sec: (deadline_ns / 1_000_000_000) as libc::time_t,
            tv_nsec: (deadline_ns % 1_000_000_000) as libc::c_long,
        };
        loop {
            // SAFETY: `ts` is a valid timespec; the remaining-time pointer may be
            // null with TIMER_ABSTIME.
            let rc = unsafe {
                libc::clock_nanosleep(
                    libc::CLOCK_MONOTONIC,
                    libc::TIMER_ABSTIME,
                    &ts,
                    std::ptr::null_mut(),
                )
            };
            if rc != libc::EINTR {
                break;
            }
        }
    }
}

/// The deadline sequence.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Schedule {
    origin_ns: u64,
    period_ns: u64,
    index: u64,
}

impl Schedule {
    /// Deadlines `origin + k * period`, starting at k = 0. `period_ns` >= 1.
    pub fn new(origin_ns: u64, period_ns: u64) -> Self {
        Schedule {
            origin_ns,
            period_ns: period_ns.max(1),
            index: 0,
        }
    }

    /// Index of the current deadline.
    pub fn index(&self) -> u64 {
        self.index
    }

    /// Current deadline, ns.
    pub fn deadline(&self) -> u64 {
        self.origin_ns + self.index * self.period_ns
    }

    /// Move on after a tick whose work ended at `now_ns`: to the next deadline,
    /// or, if that is already due, to the first one still in the future.
    /// Returns how many deadlines were skipped (0 unless overrun).
    pub fn advance(&mut self, now_ns: u64) -> u64 {
        let next = self.index + 1;
        let next_deadline = self.origin_ns + next * self.period_ns;
        if now_ns < next_deadline {
            self.index = next;
            return 0;
        }
        let first_future = (now_ns - self.origin_ns) / self.period_ns + 1;
        self.index = first_future;
        first_future - next
    }
}

/// Histogram bin width for lateness, ns.
pub const BIN_NS: u64 = 10_000;
/// Number of bins (the last one collects everything beyond 100 ms).
pub const BINS: usize = 10_000;

/// One tick as recorded in the optional trace.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TickRecord {
    /// Deadline index k.
    pub index: u64,
    /// Deadline, ns (monotonic).
    pub deadline_ns: u64,
    /// Actual wake-up, ns (monotonic).
    pub wake_ns: u64,
}

/// Tick counters and the lateness distribution; no allocation per tick.
#[derive(Clone, Debug)]
pub struct TickStats {
    period_ns: u64,
    ticks: u64,
    overruns: u64,
    skipped: u64,
    hist: Vec<u32>,
    sum_ns: u128,
    max_ns: u64,
    first: Option<TickRecord>,
    last: Option<TickRecord>,
    trace: Vec<TickRecord>,
    trace_cap: usize,
}

/// Summary of [`TickStats`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TickSummary {
    /// Ticks run.
    pub ticks: u64,
    /// Ticks whose work ended after the next deadline.
    pub overruns: u64,
    /// Deadlines skipped because of overruns.
    pub skipped_ticks: u64,
    /// Mean wake-up lateness, µs.
    pub lateness_mean_us: f64,
    /// Median lateness, µs (10 µs bins, upper edge).
    pub lateness_p50_us: f64,
    /// 99th percentile lateness, µs (10 µs bins, upper edge).
    pub lateness_p99_us: f64,
    /// Largest lateness, µs.
    pub lateness_max_us: f64,
    /// Mean interval between actual wake-ups, µs (`None` before two ticks).
    pub mean_period_us: Option<f64>,
    /// (last wake - first wake) - (k_last - k_first) * period, µs.
    pub drift_us: Option<f64>,
}

impl TickStats {
    /// Empty statistics; `trace_cap` tick records are kept (allocated now).
    pub fn new(period_ns: u64, trace_cap: usize) -> Self {
        TickStats {
            period_ns,
            ticks: 0,
            overruns: 0,
            skipped: 0,
            hist: vec![0; BINS],
            sum_ns: 0,
            max_ns: 0,
            first: None,
            last: None,
            trace: Vec::with_capacity(trace_cap),
            trace_cap,
        }
    }

    /// Record one tick's wake-up. Lateness is measured from `due_ns`, the
    /// first deadline not yet served: after skipped deadlines it is the
    /// whole wait, not just the distance to the deadline the tick woke for
    /// (`test_f6_a_flooding_peer_cannot_starve_the_ticker`).
    pub fn record_wake(&mut self, rec: TickRecord, due_ns: u64) {
        let late = rec.wake_ns.saturating_sub(due_ns.min(rec.deadline_ns));
        self.ticks += 1;
        self.sum_ns += u128::from(late);
        self.max_ns = self.max_ns.max(late);
        let bin = ((late / BIN_NS) as usize).min(BINS - 1);
        if let Some(h) = self.hist.get_mut(bin) {
            *h = h.saturating_add(1);
        }
        if self.first.is_none() {
            self.first = Some(rec);
        }
        self.last = Some(rec);
        if self.trace.len() < self.trace_cap {
            self.trace.push(rec);
        }
    }

    /// Record the outcome of `Schedule::advance`.
    pub fn record_skip(&mut self, skipped: u64) {
        if skipped > 0 {
            self.overruns += 1;
            self.skipped += skipped;
        }
    }

    /// The recorded trace.
    pub fn trace(&self) -> &[TickRecord] {
        &self.trace
    }

    fn percentile_us(&self, q: f64) -> f64 {
        if self.ticks == 0 {
            return 0.0;
        }
        let rank = ((q * self.ticks as f64).ceil() as u64).max(1);
        let mut acc = 0u64;
        for (i, &c) in self.hist.iter().enumerate() {
            acc += u64::from(c);
            if acc >= rank {
                let edge = (i as u64 + 1) * BIN_NS;
                return edge.min(self.max_ns) as f64 / 1e3;
            }
        }
        self.max_ns as f64 / 1e3
    }

    /// Summarise.
    pub fn summary(&self) -> TickSummary {
        let (mean_period_us, drift_us) = match (self.first, self.last) {
            (Some(a), Some(b)) if b.index > a.index => {
                let span = b.wake_ns as f64 - a.wake_ns as f64;
                let n = (b.index - a.index) as f64;
                let ticks_between = (self.ticks - 1).max(1) as f64;
                (
                    Some(span / ticks_between / 1e3),
                    Some((span - n * self.period_ns as f64) / 1e3),
                )
            }
            _ => (None, None),
        };
        TickSummary {
            ticks: self.ticks,
            overruns: self.overruns,
            skipped_ticks: self.skipped,
            lateness_mean_us: if self.ticks == 0 {
                0.0
            } else {
                self.sum_ns as f64 / self.ticks as f64 / 1e3
            },
            lateness_p50_us: self.percentile_us(0.50),
            lateness_p99_us: self.percentile_us(0.99),
            lateness_max_us: self.max_ns as f64 / 1e3,
            mean_period_us,
            drift_us,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn deadlines_are_absolute() {
        let mut s = Schedule::new(1_000, 50);
        assert_eq!(s.deadline(), 1_000);
        // Work ends late but before the next deadline: no skip, no drift.
        assert_eq!(s.advance(1_049), 0);
        assert_eq!(s.deadline(), 1_050);
        assert_eq!(s.advance(1_051), 0);
        assert_eq!(s.deadline(), 1_100);
    }

    #[test]
    fn overrun_skips_instead_of_bursting() {
        let mut s = Schedule::new(0, 50);
        // Work of tick 0 ends at 170: deadlines 50, 100, 150 are gone; next is 200.
        assert_eq!(s.advance(170), 3);
        assert_eq!(s.deadline(), 200);
        assert_eq!(s.index(), 4);
        // Ending exactly on a deadline counts as missing it.
        assert_eq!(s.advance(250), 1);
        assert_eq!(s.deadline(), 300);
    }

    #[test]
    fn stats_percentiles_and_drift() {
        let mut st = TickStats::new(50_000_000, 3);
        for k in 0..100u64 {
            let d = k * 50_000_000;
            let late = if k == 99 { 5_000_000 } else { 20_000 };
            st.record_wake(
                TickRecord {
                    index: k,
                    deadline_ns: d,
                    wake_ns: d + late,
                },
                d,
            );
        }
        st.record_skip(0);
        st.record_skip(2);
        let s = st.summary();
        assert_eq!(s.ticks, 100);
        assert_eq!(s.overruns, 1);
        assert_eq!(s.skipped_ticks, 2);
        assert_eq!(s.lateness_max_us, 5_000.0);
        assert_eq!(s.lateness_p50_us, 30.0);
        assert_eq!(s.lateness_p99_us, 30.0);
        assert!((s.drift_us.unwrap() - (5_000.0 - 20.0)).abs() < 1e-6);
        assert_eq!(st.trace().len(), 3);
    }
}
