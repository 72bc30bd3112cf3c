//! Actuator limits and the command watchdog.
//!
//! **Limits.** Each wheel has its own range `[min_nm, max_nm]` (asymmetric:
//! `max_nm = 0` is a brake-only wheel) and two rates: `rise_nm_per_s` for a
//! torque moving away from zero, `release_nm_per_s` for one moving toward
//! zero. A command outside a wheel's range is clamped to it or refused at
//! `set_command`, by the configured [`LimitRule`]; every such event is
//! counted. The output then moves toward the (in-range) target by at most
//! the rate's step per tick, and a sign reversal passes through 0 Nm (no
//! tick crosses zero, so the rise rate also holds on the far side).
//!
//! **The wire grid.** Everything is done in whole steps of the torque
//! signals' resolution (2 Nm): each limit is rounded toward zero onto it
//! (`max_nm = 2001` acts as 2000) and each rate step per tick is rounded
//! down (at least one step, else refused), so `min <= torque on the wire <=
//! max` and every change between two frames is within its rate exactly.
//!
//! **Watchdog.** The age of the latest command, `deadline - arrival` on the
//! monotonic clock, selects the mode at each tick: `Active` while age <
//! `hold_after`, `Hold` (output frozen) while < `safe_after`, `Safe` while <
//! `fault_after`, then a latched `Fault`. Each starts at the first tick whose
//! deadline is at or past the configured age: never early, at most one period
//! late (test `watchdog_edges_within_one_tick`, and on the wire
//! `test_f7_hold_safe_fault_within_one_tick_of_the_configured_times`). In
//! `Safe` and `Fault` the output is released toward zero at
//! `safe_release_nm_per_s` (brakes are not dropped in one step).

use crate::codec::{Mode, WHEEL_TORQUE_CMD};
use crate::error::{Error, Result};

/// Wheel names in frame order.
pub const WHEELS: [&str; 4] = ["FL", "FR", "RL", "RR"];

/// What happens to a command outside a wheel's range.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum LimitRule {
    /// Clamped to the range (counted, reported in `stats()`).
    Clamp,
    /// Refused at `set_command` with `CommandError` (counted).
    Refuse,
}

impl LimitRule {
    /// Parse `"clamp"` / `"refuse"`.
    pub fn parse(s: &str) -> Result<Self> {
        match s {
            "clamp" => Ok(LimitRule::Clamp),
            "refuse" => Ok(LimitRule::Refuse),
            _ => Err(Error::Config(format!(
                "limit_rule = {} must be \"clamp\" or \"refuse\"",
                crate::error::clip(s)
            ))),
        }
    }

    /// The name used in the configuration.
    pub fn name(self) -> &'static str {
        match self {
            LimitRule::Clamp => "clamp",
            LimitRule::Refuse => "refuse",
        }
    }
}

/// One wheel's actuator limits.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct WheelLimits {
    /// Most negative torque (braking), Nm; at most 0.
    pub min_nm: f64,
    /// Most positive torque (driving), Nm; at least 0 (0: brake only).
    pub max_nm: f64,
    /// Largest rate of a torque moving away from zero, Nm/s.
    pub rise_nm_per_s: f64,
    /// Largest rate of a torque moving toward zero, Nm/s.
    pub release_nm_per_s: f64,
}

/// Largest rate accepted for any limit, Nm/s (a step of 2,000 Nm per ms).
pub const MAX_RATE_NM_PER_S: f64 = 2.0e6;

/// Limits and watchdog timeouts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SafetyConfig {
    /// Per wheel, FL, FR, RL, RR.
    pub wheels: [WheelLimits; 4],
    /// Rate at which `Safe`, `Fault` and stop release the output toward 0, Nm/s.
    pub safe_release_nm_per_s: f64,
    /// Clamp or refuse a command outside a wheel's range.
    pub limit_rule: LimitRule,
    /// Command age at which the output is held, ns.
    pub hold_after_ns: u64,
    /// Command age at which the output is released to zero, ns.
    pub safe_after_ns: u64,
    /// Silence at which a fault latches, ns.
    pub fault_after_ns: u64,
}

/// The front wheels of the vehicle examples brake only (FDB in [-2000, 0] Nm
/// per wheel); the rear wheels drive and brake to +-2000 Nm (|DTR/2| + |RTV|).
const FRONT: WheelLimits = WheelLimits {
    min_nm: -2000.0,
    max_nm: 0.0,
    rise_nm_per_s: 10_000.0,
    release_nm_per_s: 20_000.0,
};
const REAR: WheelLimits = WheelLimits {
    min_nm: -2000.0,
    max_nm: 2000.0,
    rise_nm_per_s: 10_000.0,
    release_nm_per_s: 20_000.0,
};

impl Default for SafetyConfig {
    /// The shipped `vehicle.toml` (a Rust test keeps the two equal).
    fn default() -> Self {
        SafetyConfig {
            wheels: [FRONT, FRONT, REAR, REAR],
            safe_release_nm_per_s: 8_000.0,
            limit_rule: LimitRule::Clamp,
            hold_after_ns: 150_000_000,
            safe_after_ns: 500_000_000,
            fault_after_ns: 2_000_000_000,
        }
    }
}

/// Resolution of the torque signals on the wire, Nm (their DBC factor).
pub fn torque_quantum_nm() -> f64 {
    WHEEL_TORQUE_CMD
        .signal("TorqueFL")
        .map(|s| s.factor)
        .unwrap_or(2.0)
}

/// The torque signals' DBC range, Nm.
pub fn torque_range_nm() -> (f64, f64) {
    WHEEL_TORQUE_CMD
        .signal("TorqueFL")
        .map(|s| (s.min, s.max))
        .unwrap_or((0.0, 0.0))
}

/// Upper bounds of the watchdog times, ms (a longer hold than a second is
/// not a watchdog any more).
pub const MAX_HOLD_MS: f64 = 1_000.0;
/// See [`MAX_HOLD_MS`].
pub const MAX_SAFE_MS: f64 = 5_000.0;
/// See [`MAX_HOLD_MS`].
pub const MAX_FAULT_MS: f64 = 60_000.0;

fn ms(ns: u64) -> f64 {
    ns as f64 / 1e6
}

impl SafetyConfig {
    /// Check every limit against the DBC's range and resolution and the
    /// period (a rate must move at least one 2 Nm step per tick), and the
    /// watchdog times against each other, the period and their bounds.
    pub fn validate(&self, period_ns: u64) -> Result<()> {
        let (lo, hi) = torque_range_nm();
        let q = torque_quantum_nm();
        let dt = period_ns as f64 / 1e9;
        for (w, l) in WHEELS.iter().zip(&self.wheels) {
            if !(l.min_nm.is_finite() && l.min_nm <= 0.0 && l.min_nm >= lo) {
                return Err(Error::Config(format!(
                    "torque_min_nm[{w}] = {} must be in [{lo}, 0] (the DBC's range)",
                    l.min_nm
                )));
            }
            if !(l.max_nm.is_finite() && l.max_nm >= 0.0 && l.max_nm <= hi) {
                return Err(Error::Config(format!(
                    "torque_max_nm[{w}] = {} must be in [0, {hi}] (the DBC's range)",
                    l.max_nm
                )));
            }
            for (name, r) in [
                ("rise_nm_per_s", l.rise_nm_per_s),
                ("release_nm_per_s", l.release_nm_per_s),
            ] {
                check_rate(&format!("{name}[{w}]"), r, dt, q)?;
            }
        }
        check_rate("safe_release_nm_per_s", self.safe_release_nm_per_s, dt, q)?;
        let (h, s, f) = (self.hold_after_ns, self.safe_after_ns, self.fault_after_ns);
        if !(h >= period_ns && ms(h) <= MAX_HOLD_MS) {
            return Err(Error::Config(format!(
                "hold_after_ms = {} must be between period_ms ({}) and {MAX_HOLD_MS}",
                ms(h),
                ms(period_ns)
            )));
        }
        if !(s > h && ms(s) <= MAX_SAFE_MS) {
            return Err(Error::Config(format!(
                "safe_after_ms = {} must be above hold_after_ms ({}) and at most {MAX_SAFE_MS}",
                ms(s),
                ms(h)
            )));
        }
        if !(f > s && ms(f) <= MAX_FAULT_MS) {
            return Err(Error::Config(format!(
                "fault_after_ms = {} must be above safe_after_ms ({}) and at most {MAX_FAULT_MS}",
                ms(f),
                ms(s)
            )));
        }
        Ok(())
    }
}

fn check_rate(name: &str, r: f64, dt: f64, q: f64) -> Result<()> {
    if !(r.is_finite() && r > 0.0 && r <= MAX_RATE_NM_PER_S) {
        return Err(Error::Config(format!(
            "{name} = {r} must be in (0, {MAX_RATE_NM_PER_S}] Nm/s"
        )));
    }
    if r * dt < q {
        return Err(Error::Config(format!(
            "{name} = {r} Nm/s moves less than one {q} Nm step per {} ms tick; the torque on the wire moves in steps of {q} Nm",
            dt * 1e3
        )));
    }
    Ok(())
}

/// A validated command as handed over by `set_command`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Command {
    /// Target torques FL, FR, RL, RR in Nm (finite, within each wheel's range).
    pub torques_nm: [f64; 4],
    /// Caller's sequence number (strictly increasing within a run).
    pub seq: u64,
    /// Monotonic time of arrival, ns.
    pub received_ns: u64,
}

impl Command {
    /// Refuse NaN and infinities before anything is stored.
    pub fn new(torques_nm: [f64; 4], seq: u64, received_ns: u64) -> Result<Self> {
        for (name, t) in WHEELS.iter().zip(torques_nm) {
            if !t.is_finite() {
                return Err(Error::Command(format!(
                    "torque {name} = {t} is not finite; command refused"
                )));
            }
        }
        Ok(Command {
            torques_nm,
            seq,
            received_ns,
        })
    }
}

/// One wheel's limits on the grid, in steps.
#[derive(Clone, Copy, Debug)]
struct Grid {
    min: i64,
    max: i64,
    rise: i64,
    release: i64,
}

/// What `limit` did to a command.
#[derive(Clone, Debug, PartialEq)]
pub struct LimitEvent {
    /// Wheel index.
    pub wheel: usize,
    /// Commanded torque, Nm.
    pub commanded_nm: f64,
    /// Target after clamping, Nm.
    pub target_nm: f64,
}

/// The watchdog and limiter state.
#[derive(Clone, Debug)]
pub struct Safety {
    cfg: SafetyConfig,
    quantum: f64,
    grid: [Grid; 4],
    safe_release: i64,
    /// Output in grid steps: exactly what goes on the wire.
    output_steps: [i64; 4],
    mode: Mode,
    latched: bool,
    /// Start or last reset: the watchdog's origin while there is no command.
    epoch_ns: u64,
    /// Commands received before this are ignored (the last reset; 0 at start,
    /// as each run starts with no command at all).
    ignore_before_ns: u64,
    rate_limited: u64,
}

/// Round a limit toward zero onto the grid.
fn toward_zero(x: f64, q: f64) -> i64 {
    (x / q).trunc() as i64
}

impl Safety {
    /// Start at `now_ns` in `Safe` with zero output, ticking every `period_ns`.
    pub fn new(cfg: SafetyConfig, period_ns: u64, now_ns: u64) -> Self {
        let q = torque_quantum_nm();
        let dt = period_ns as f64 / 1e9;
        let per_tick = |r: f64| ((r * dt / q).floor() as i64).max(1);
        Safety {
            cfg,
            quantum: q,
            grid: cfg.wheels.map(|w| Grid {
                min: toward_zero(w.min_nm, q).min(0),
                max: toward_zero(w.max_nm, q).max(0),
                rise: per_tick(w.rise_nm_per_s),
                release: per_tick(w.release_nm_per_s),
            }),
            safe_release: per_tick(cfg.safe_release_nm_per_s),
            output_steps: [0; 4],
            mode: Mode::Safe,
            latched: false,
            epoch_ns: now_ns,
            ignore_before_ns: 0,
            rate_limited: 0,
        }
    }

    /// Clamp a command to the wheels' ranges (on the grid, rounded toward
    /// zero), listing each wheel it changed.
    pub fn limit(cfg: &SafetyConfig, torques_nm: [f64; 4]) -> ([f64; 4], Vec<LimitEvent>) {
        let q = torque_quantum_nm();
        let mut out = torques_nm;
        let mut events = Vec::new();
        for (i, (t, w)) in torques_nm.iter().zip(&cfg.wheels).enumerate() {
            let lo = toward_zero(w.min_nm, q) as f64 * q;
            let hi = toward_zero(w.max_nm, q) as f64 * q;
            if *t < lo || *t > hi {
                out[i] = t.clamp(lo, hi);
                events.push(LimitEvent {
                    wheel: i,
                    commanded_nm: *t,
                    target_nm: out[i],
                });
            }
        }
        (out, events)
    }

    /// Current mode.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// Current output torques, Nm.
    pub fn output(&self) -> [f64; 4] {
        self.output_steps.map(|s| s as f64 * self.quantum)
    }

    /// Whether a fault is latched.
    pub fn is_latched(&self) -> bool {
        self.latched
    }

    /// Ticks on which a rate limit shaped the output.
    pub fn rate_limited_ticks(&self) -> u64 {
        self.rate_limited
    }

    /// Clear a latched fault. Commands older than `now_ns` stay ignored, so the
    /// bridge stays in `Safe` until a new command arrives. Returns whether a
    /// fault was cleared; without one this does nothing at all.
    pub fn reset(&mut self, now_ns: u64) -> bool {
        if !self.latched {
            return false;
        }
        self.latched = false;
        self.epoch_ns = now_ns;
        self.ignore_before_ns = now_ns;
        if self.mode == Mode::Fault {
            self.mode = Mode::Safe;
        }
        true
    }

    /// Restart the output from 0 Nm (after a gap in transmission the
    /// actuator may have timed out or been re-initialised: it ramps up again
    /// at the rise rate).
    pub fn restart_output(&mut self) {
        self.output_steps = [0; 4];
    }

    /// The output on the wire's grid, in steps.
    pub fn output_steps(&self) -> [i64; 4] {
        self.output_steps
    }

    /// Put the output back to `steps`: the limiter advances only on frames
    /// that reach the wire, so a tick whose frame was not written (or was
    /// flushed unread) leaves it where the wire last saw it.
    pub fn set_output_steps(&mut self, steps: [i64; 4]) {
        self.output_steps = steps;
    }

    /// A frame of the stop sequence: `Safe` (or `Fault` if latched),
    /// released toward zero at the safe rate.
    pub fn stopping(&mut self) -> (Mode, [f64; 4]) {
        self.release_to_zero();
        self.mode = if self.latched {
            Mode::Fault
        } else {
            Mode::Safe
        };
        (self.mode, self.output())
    }

    /// One tick on a transport where the age rule cannot hold for an
    /// active frame: the watchdog runs as in [`Safety::step`] (a silent
    /// controller still latches a fault), but the output is released toward
    /// zero at the safe rate and the frame is `Safe` (`Fault` if latched).
    /// Also returns the mode [`Safety::step`] would have sent.
    pub fn step_safe_only(&mut self, now_ns: u64, cmd: Option<&Command>) -> (Mode, [f64; 4], Mode) {
        let (before, limited) = (self.output_steps, self.rate_limited);
        let (would, _) = self.step(now_ns, cmd);
        (self.output_steps, self.rate_limited) = (before, limited);
        let (mode, torques) = self.stopping();
        (mode, torques, would)
    }

    fn release_to_zero(&mut self) {
        let d = self.safe_release;
        for s in &mut self.output_steps {
            *s -= (*s).clamp(-d, d);
        }
    }

    /// One tick at deadline `now_ns` with the latest command, if any.
    pub fn step(&mut self, now_ns: u64, cmd: Option<&Command>) -> (Mode, [f64; 4]) {
        let fresh = cmd.filter(|c| c.received_ns >= self.ignore_before_ns);
        let since = fresh.map_or(self.epoch_ns, |c| c.received_ns);
        let age = now_ns.saturating_sub(since);
        if !self.latched && age >= self.cfg.fault_after_ns {
            self.latched = true;
        }
        self.mode = if self.latched {
            Mode::Fault
        } else if fresh.is_none() || age >= self.cfg.safe_after_ns {
            Mode::Safe
        } else if age >= self.cfg.hold_after_ns {
            Mode::Hold
        } else {
            Mode::Active
        };
        match (self.mode, fresh) {
            (Mode::Active, Some(c)) => self.follow(&c.torques_nm),
            (Mode::Hold, _) => {}
            _ => self.release_to_zero(),
        }
        (self.mode, self.output())
    }

    /// Move toward `target` within the range and the rates.
    fn follow(&mut self, target: &[f64; 4]) {
        let mut limited = false;
        for ((y, g), t) in self.output_steps.iter_mut().zip(&self.grid).zip(target) {
            let want = ((t / self.quantum).round_ties_even() as i64).clamp(g.min, g.max);
            let (up, down) = match (*y).signum() {
                1 => (g.rise, g.release),
                -1 => (g.release, g.rise),
                _ => (g.rise, g.rise),
            };
            let mut next = *y + (want - *y).clamp(-down, up);
            if (*y > 0 && next < 0) || (*y < 0 && next > 0) {
                next = 0;
            }
            limited |= next != want;
            *y = next.clamp(g.min, g.max);
        }
        if limited {
            self.rate_limited += 1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const MS: u64 = 1_000_000;
    const PERIOD: u64 = 50 * MS;

    fn wheel(min: f64, max: f64, rise: f64, release: f64) -> WheelLimits {
        WheelLimits {
            min_nm: min,
            max_nm: max,
            rise_nm_per_s: rise,
            release_nm_per_s: release,
        }
    }

    fn cfg() -> SafetyConfig {
        SafetyConfig {
            wheels: [
                wheel(-100.0, 0.0, 200.0, 400.0),
                wheel(-100.0, 100.0, 200.0, 400.0),
                wheel(-50.0, 50.0, 200.0, 200.0),
                wheel(-50.0, 50.0, 200.0, 200.0),
            ],
            safe_release_nm_per_s: 200.0,
            limit_rule: LimitRule::Clamp,
            hold_after_ns: 100 * MS,
            safe_after_ns: 300 * MS,
            fault_after_ns: 1000 * MS,
        }
    }

    #[test]
    fn refuses_non_finite() {
        assert!(Command::new([f64::NAN, 0.0, 0.0, 0.0], 1, 0).is_err());
        assert!(Command::new([0.0, f64::INFINITY, 0.0, 0.0], 1, 0).is_err());
        assert!(Command::new([1.0; 4], 1, 0).is_ok());
    }

    #[test]
    fn validates_config_and_names_the_setting() {
        assert!(cfg().validate(PERIOD).is_ok());
        assert!(SafetyConfig::default().validate(PERIOD).is_ok());
        let check = |c: SafetyConfig, want: &str| {
            let e = c.validate(PERIOD).unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
        };
        let mut c = cfg();
        c.wheels[2].max_nm = f64::NAN;
        check(c, "torque_max_nm[RL]");
        let mut c = cfg();
        c.wheels[0].min_nm = -5000.0;
        check(c, "torque_min_nm[FL] = -5000");
        let mut c = cfg();
        c.wheels[1].min_nm = 10.0;
        check(c, "torque_min_nm[FR]");
        let mut c = cfg();
        c.wheels[3].rise_nm_per_s = 30.0; // 1.5 Nm per 50 ms tick
        check(
            c,
            "rise_nm_per_s[RR] = 30 Nm/s moves less than one 2 Nm step",
        );
        let mut c = cfg();
        c.safe_release_nm_per_s = 1e9;
        check(c, "safe_release_nm_per_s");
        let mut c = cfg();
        c.safe_after_ns = c.hold_after_ns;
        check(c, "safe_after_ms");
        let mut c = cfg();
        c.hold_after_ns = 9_360_000 * MS;
        check(c, "hold_after_ms");
        let mut c = cfg();
        c.hold_after_ns = 20 * MS;
        check(c, "hold_after_ms = 20 must be between period_ms (50)");
        let mut c = cfg();
        c.fault_after_ns = 3_600_000 * MS;
        check(c, "fault_after_ms");
    }

    #[test]
    fn asymmetric_ranges_and_separate_rise_and_release() {
        let mut s = Safety::new(cfg(), PERIOD, 0);
        // 200 Nm/s rise = 10 Nm per 50 ms tick; release 400 Nm/s = 20 Nm per tick.
        let (target, ev) = Safety::limit(&cfg(), [500.0, -500.0, 30.0, -1000.0]);
        assert_eq!(target, [0.0, -100.0, 30.0, -50.0]);
        assert_eq!(ev.len(), 3);
        let c = Command::new(target, 1, 0).unwrap();
        let outs: Vec<[f64; 4]> = (0..12).map(|k| s.step(k * MS, Some(&c)).1).collect();
        assert_eq!(outs[0], [0.0, -10.0, 10.0, -10.0]);
        assert_eq!(outs[9], [0.0, -100.0, 30.0, -50.0]);
        // Release toward zero at 20 Nm per tick on FR, then a reversal via 0.
        let c = Command::new([0.0, 60.0, 0.0, 0.0], 2, 12 * MS).unwrap();
        let fr: Vec<f64> = (12..22).map(|k| s.step(k * MS, Some(&c)).1[1]).collect();
        assert_eq!(
            fr,
            [-80.0, -60.0, -40.0, -20.0, 0.0, 10.0, 20.0, 30.0, 40.0, 50.0]
        );
    }

    #[test]
    fn watchdog_edges_within_one_tick() {
        // The command arrives 1 ms after a deadline (the worst phase): each
        // mode starts at the first deadline whose age reaches its time.
        let mut s = Safety::new(cfg(), PERIOD, 0);
        let c = Command::new([-20.0; 4], 1, 51 * MS).unwrap();
        let modes: Vec<(u64, Mode)> = (1..30)
            .map(|k| (k * PERIOD, s.step(k * PERIOD, Some(&c)).0))
            .collect();
        let first = |m: Mode| modes.iter().find(|x| x.1 == m).unwrap().0 - 51 * MS;
        for (m, after) in [
            (Mode::Hold, 100 * MS),
            (Mode::Safe, 300 * MS),
            (Mode::Fault, 1000 * MS),
        ] {
            let t = first(m);
            assert!(t >= after && t < after + PERIOD, "{m:?} after {t}");
        }
        // Exactly on the edge: the mode changes at that tick.
        let mut s = Safety::new(cfg(), PERIOD, 0);
        let c = Command::new([-20.0; 4], 1, 0).unwrap();
        assert_eq!(s.step(50 * MS, Some(&c)).0, Mode::Active);
        assert_eq!(s.step(100 * MS, Some(&c)).0, Mode::Hold);
    }

    #[test]
    fn safe_releases_at_the_safe_rate_and_fault_latches() {
        let mut s = Safety::new(cfg(), PERIOD, 0);
        let c = Command::new([-100.0, -100.0, 50.0, -50.0], 1, 0).unwrap();
        for k in 0..10 {
            s.step(k * MS, Some(&c));
        }
        assert_eq!(s.output(), [-100.0, -100.0, 50.0, -50.0]);
        // Safe: released 10 Nm per tick (200 Nm/s at 50 ms).
        let (m, o) = s.step(300 * MS, Some(&c));
        assert_eq!((m, o), (Mode::Safe, [-90.0, -90.0, 40.0, -40.0]));
        let mut last = o;
        for k in 1..20 {
            let (_, o) = s.step(300 * MS + k * PERIOD, Some(&c));
            for (a, b) in last.iter().zip(&o) {
                assert!(b.abs() <= a.abs() && (a - b).abs() <= 10.0);
            }
            last = o;
        }
        assert_eq!(last, [0.0; 4]);
        assert_eq!(s.step(1000 * MS, Some(&c)).0, Mode::Fault);
        let c2 = Command::new([20.0; 4], 2, 1100 * MS).unwrap();
        assert_eq!(s.step(1100 * MS, Some(&c2)).0, Mode::Fault);
        assert!(s.reset(1200 * MS));
        assert_eq!(s.step(1210 * MS, Some(&c2)).0, Mode::Safe);
        let c3 = Command::new([-20.0; 4], 3, 1220 * MS).unwrap();
        assert_eq!(s.step(1250 * MS, Some(&c3)).0, Mode::Active);
        assert!(!Safety::new(cfg(), PERIOD, 0).reset(5));
    }

    #[test]
    fn stopping_ramps_to_zero_and_keeps_a_fault_visible() {
        let mut s = Safety::new(cfg(), PERIOD, 0);
        let c = Command::new([-30.0, 0.0, 0.0, 0.0], 1, 0).unwrap();
        for k in 0..5 {
            s.step(k * MS, Some(&c));
        }
        assert_eq!(s.stopping(), (Mode::Safe, [-20.0, 0.0, 0.0, 0.0]));
        assert_eq!(s.stopping().1, [-10.0, 0.0, 0.0, 0.0]);
        assert_eq!(s.stopping().1, [0.0; 4]);
        s.step(2000 * MS, Some(&c));
        assert_eq!(s.stopping().0, Mode::Fault);
    }

    #[test]
    fn safe_only_releases_and_still_latches_a_fault() {
        let mut s = Safety::new(cfg(), PERIOD, 0);
        let c = |k: u64| Command::new([100.0; 4], k, k * PERIOD).unwrap();
        for k in 1..=10 {
            s.step(k * PERIOD, Some(&c(k)));
        }
        let up = s.output();
        assert!(up[2] > 0.0);
        let (m, t, would) = s.step_safe_only(11 * PERIOD, Some(&c(11)));
        assert_eq!((m, would), (Mode::Safe, Mode::Active));
        assert!(t[2] < up[2] && t[2] >= 0.0, "{t:?} from {up:?}");
        // a silent controller still ends in a latched fault
        let mut k = 12;
        while s.step_safe_only(k * PERIOD, None).0 != Mode::Fault {
            k += 1;
            assert!(k < 1_000);
        }
        assert_eq!(s.output(), [0.0; 4]);
    }

    #[test]
    fn limits_round_toward_zero_onto_the_2_nm_grid() {
        let mut c = cfg();
        c.wheels[1] = wheel(-2001.0, 2001.0, 1e6, 1e6);
        let (t, _) = Safety::limit(&c, [0.0, 5000.0, 0.0, 0.0]);
        assert_eq!(t[1], 2000.0);
        let mut s = Safety::new(c, PERIOD, 0);
        let cmd = Command::new([0.0, -5000.0, 3.0, 5.0], 1, 0).unwrap();
        let o = s.step(0, Some(&cmd)).1;
        assert_eq!(o[1], -2000.0);
        assert_eq!(o[2], 4.0); // 3 Nm is a tie between 2 and 4: to even (4 = 2 x 2)
        assert_eq!(o[3], 4.0);
    }

    fn arb_wheel() -> impl Strategy<Value = WheelLimits> {
        (0u32..2000, 0u32..2000, 40.0f64..1e5, 40.0f64..1e5)
            .prop_map(|(lo, hi, r, l)| wheel(-(lo as f64) * 1.01, hi as f64 * 0.99, r, l))
    }

    fn cases() -> u32 {
        std::env::var("CAN_BRIDGE_PROPTEST_CASES")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(500)
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(cases()))]

        /// Any limits, any commands, any arrival times: every output is on
        /// the 2 Nm grid and within its wheel's range; every change between
        /// ticks is within the rise rate (away from zero) or the release
        /// rate (toward zero); no tick crosses zero; Hold keeps the output;
        /// Safe and Fault only move toward zero, at most the safe step.
        #[test]
        fn limiter_never_leaves_its_envelope(
            wheels in proptest::array::uniform4(arb_wheel()),
            safe in 40.0f64..1e5,
            cmds in proptest::collection::vec((proptest::array::uniform4(-5000.0f64..5000.0), 0u64..400), 1..120),
        ) {
            let c = SafetyConfig { wheels, safe_release_nm_per_s: safe, ..cfg() };
            prop_assume!(c.validate(PERIOD).is_ok());
            let q = torque_quantum_nm();
            let dt = PERIOD as f64 / 1e9;
            let mut s = Safety::new(c, PERIOD, 0);
            let mut prev = [0.0f64; 4];
            let mut now = 0u64;
            for (k, (t, gap_ms)) in cmds.iter().enumerate() {
                let (target, _) = Safety::limit(&c, *t);
                let cmd = Command::new(target, k as u64, now).unwrap();
                now += gap_ms * MS;
                let (mode, out) = s.step(now, Some(&cmd));
                for i in 0..4 {
                    let w = &c.wheels[i];
                    let (a, b) = (prev[i], out[i]);
                    prop_assert_eq!((b / q).fract(), 0.0);
                    prop_assert!(b >= w.min_nm && b <= w.max_nm, "{b} outside {w:?}");
                    prop_assert!(a * b >= 0.0, "{a} -> {b} crosses zero");
                    let away = b.abs() > a.abs();
                    let rate = if away { w.rise_nm_per_s } else { w.release_nm_per_s };
                    match mode {
                        Mode::Active => prop_assert!((b - a).abs() <= rate * dt + 1e-9),
                        Mode::Hold => prop_assert_eq!(a, b),
                        _ => {
                            prop_assert!(!away);
                            prop_assert!((b - a).abs() <= safe * dt + 1e-9);
                        }
                    }
                }
                prev = out;
            }
        }
    }
}

#[cfg(test)]
mod limits_tests;
