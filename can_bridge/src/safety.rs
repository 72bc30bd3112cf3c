//! Actuator limits and the command watchdog.
//!
//! Per tick: the target torque is clamped to `±max_torque_nm` and the output
//! moves towards it by at most `max_delta_nm_per_tick` per wheel. Both limits
//! are enforced on the value that goes on the wire: the output lives on the
//! torque signals' grid (0.5 Nm), each limit is rounded toward zero onto that
//! grid (300.3 Nm acts as 300.0, a rate of 1.3 Nm as 1.0 Nm), and a limit
//! below one grid step is refused by [`SafetyConfig::validate`]. So
//! `|torque on the wire| <= max_torque_nm` and `|step on the wire| <=
//! max_delta_nm_per_tick` hold exactly, not merely up to rounding. The age of
//! the latest command (or, without one, the time since start or reset) selects
//! the mode: `Active` up to `hold_after`, `Hold` (output frozen) up to
//! `safe_after`, `Safe` (zero torque) up to `fault_after`, then a latched
//! `Fault` (zero torque) that only [`Safety::reset`] clears.

use crate::codec::{Mode, WHEEL_TORQUE_CMD};
use crate::error::{Error, Result};

/// Limits and watchdog timeouts.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SafetyConfig {
    /// Largest torque magnitude per wheel (FL, FR, RL, RR), Nm.
    pub max_torque_nm: [f64; 4],
    /// Largest change of the output per wheel and tick, Nm.
    pub max_delta_nm_per_tick: f64,
    /// Command age after which the output is held, ns.
    pub hold_after_ns: u64,
    /// Command age after which the output is zero, ns.
    pub safe_after_ns: u64,
    /// Silence after which a fault latches, ns.
    pub fault_after_ns: u64,
}

impl Default for SafetyConfig {
    fn default() -> Self {
        SafetyConfig {
            max_torque_nm: [300.0; 4],
            max_delta_nm_per_tick: 25.0,
            hold_after_ns: 150_000_000,
            safe_after_ns: 500_000_000,
            fault_after_ns: 2_000_000_000,
        }
    }
}

/// Resolution of the torque signals on the wire, Nm (the DBC factor of
/// `TorqueFL`..`TorqueRR`, 0.5 Nm).
pub fn torque_quantum_nm() -> f64 {
    WHEEL_TORQUE_CMD
        .signal("TorqueFL")
        .map(|s| s.factor)
        .unwrap_or(0.5)
}

/// A limit in whole grid steps, rounded toward zero (never above the limit).
fn steps_within(limit: f64, quantum: f64) -> i64 {
    (limit / quantum).floor() as i64
}

impl SafetyConfig {
    /// Check the settings against each other and against the DBC's range and
    /// resolution.
    pub fn validate(&self) -> Result<()> {
        let dbc_max = WHEEL_TORQUE_CMD
            .signal("TorqueFL")
            .map(|s| s.max)
            .unwrap_or(0.0);
        let q = torque_quantum_nm();
        for (i, &t) in self.max_torque_nm.iter().enumerate() {
            if !(t.is_finite() && t > 0.0 && t <= dbc_max) {
                return Err(Error::Config(format!(
                    "max_torque_nm[{i}] = {t} must be in (0, {dbc_max}] (the DBC's range)"
                )));
            }
            if t < q {
                return Err(Error::Config(format!(
                    "max_torque_nm[{i}] = {t} is below the torque signal's resolution of {q} Nm; \
                     the wire could only carry 0 Nm"
                )));
            }
        }
        let d = self.max_delta_nm_per_tick;
        if !(d.is_finite() && d > 0.0) {
            return Err(Error::Config(format!(
                "max_rate_nm_per_tick = {d} must be a positive finite number"
            )));
        }
        if d < q {
            return Err(Error::Config(format!(
                "max_rate_nm_per_tick = {d} is below the torque signal's resolution of {q} Nm; \
                 the torque on the wire moves in steps of {q} Nm"
            )));
        }
        if !(self.hold_after_ns > 0
            && self.hold_after_ns < self.safe_after_ns
            && self.safe_after_ns < self.fault_after_ns)
        {
            return Err(Error::Config(format!(
                "watchdog timeouts must satisfy 0 < hold_after ({} ms) < safe_after ({} ms) < fault_after ({} ms)",
                self.hold_after_ns as f64 / 1e6,
                self.safe_after_ns as f64 / 1e6,
                self.fault_after_ns as f64 / 1e6
            )));
        }
        Ok(())
    }
}

/// A validated command as handed over by `set_command`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Command {
    /// Requested torques FL, FR, RL, RR in Nm (finite).
    pub torques_nm: [f64; 4],
    /// Caller's sequence number (strictly increasing).
    pub seq: u64,
    /// Monotonic time of arrival, ns.
    pub received_ns: u64,
}

impl Command {
    /// Refuse NaN and infinities before anything is stored.
    pub fn new(torques_nm: [f64; 4], seq: u64, received_ns: u64) -> Result<Self> {
        for (name, t) in ["FL", "FR", "RL", "RR"].iter().zip(torques_nm) {
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

/// The watchdog and limiter state.
#[derive(Clone, Debug)]
pub struct Safety {
    cfg: SafetyConfig,
    /// Grid step of the output, Nm.
    quantum: f64,
    /// Torque limits in grid steps, rounded toward zero.
    limit_steps: [i64; 4],
    /// Rate limit in grid steps per tick, rounded toward zero (at least 1
    /// for a validated configuration).
    rate_steps: i64,
    /// Output in grid steps: exactly what goes on the wire.
    output_steps: [i64; 4],
    output: [f64; 4],
    mode: Mode,
    latched: bool,
    /// Commands received before this time are ignored (start or last reset).
    epoch_ns: u64,
}

impl Safety {
    /// Start at `now_ns` in `Safe` with zero output.
    pub fn new(cfg: SafetyConfig, now_ns: u64) -> Self {
        let quantum = torque_quantum_nm();
        Safety {
            cfg,
            quantum,
            limit_steps: cfg.max_torque_nm.map(|l| steps_within(l, quantum).max(0)),
            rate_steps: steps_within(cfg.max_delta_nm_per_tick, quantum).max(0),
            output_steps: [0; 4],
            output: [0.0; 4],
            mode: Mode::Safe,
            latched: false,
            epoch_ns: now_ns,
        }
    }

    /// Current mode.
    pub fn mode(&self) -> Mode {
        self.mode
    }

    /// Current output torques.
    pub fn output(&self) -> [f64; 4] {
        self.output
    }

    /// Whether a fault is latched.
    pub fn is_latched(&self) -> bool {
        self.latched
    }

    /// Clear a latched fault. Commands older than `now_ns` stay ignored, so the
    /// bridge stays in `Safe` until a new command arrives. Returns whether a
    /// fault was cleared. Without a latched fault this does nothing at all (the
    /// output keeps following the command under the rate limit).
    pub fn reset(&mut self, now_ns: u64) -> bool {
        if !self.latched {
            return false;
        }
        self.latched = false;
        self.epoch_ns = now_ns;
        self.output_steps = [0; 4];
        self.output = [0.0; 4];
        if self.mode == Mode::Fault {
            self.mode = Mode::Safe;
        }
        true
    }

    /// Force zero output in `Safe` mode (used for the frames sent on stop);
    /// a latched fault stays `Fault`.
    pub fn force_safe(&mut self) -> (Mode, [f64; 4]) {
        self.output_steps = [0; 4];
        self.output = [0.0; 4];
        self.mode = if self.latched {
            Mode::Fault
        } else {
            Mode::Safe
        };
        (self.mode, self.output)
    }

    /// One tick at `now_ns` with the latest command, if any.
    pub fn step(&mut self, now_ns: u64, cmd: Option<&Command>) -> (Mode, [f64; 4]) {
        let fresh = cmd.filter(|c| c.received_ns >= self.epoch_ns);
        let since = fresh.map_or(self.epoch_ns, |c| c.received_ns);
        let age = now_ns.saturating_sub(since);
        if !self.latched && age > self.cfg.fault_after_ns {
            self.latched = true;
        }
        self.mode = if self.latched {
            Mode::Fault
        } else if fresh.is_none() || age > self.cfg.safe_after_ns {
            Mode::Safe
        } else if age > self.cfg.hold_after_ns {
            Mode::Hold
        } else {
            Mode::Active
        };
        match (self.mode, fresh) {
            (Mode::Active, Some(c)) => {
                let d = self.rate_steps;
                for i in 0..4 {
                    let lim = self.limit_steps[i];
                    let lim_nm = lim as f64 * self.quantum;
                    // Clamp to the (on-grid) limit first, then round to the
                    // grid as cantools would: the result stays within the limit.
                    let target = (c.torques_nm[i].clamp(-lim_nm, lim_nm) / self.quantum)
                        .round_ties_even() as i64;
                    let target = target.clamp(-lim, lim);
                    let step = (target - self.output_steps[i]).clamp(-d, d);
                    self.output_steps[i] = (self.output_steps[i] + step).clamp(-lim, lim);
                }
            }
            (Mode::Hold, _) => {}
            _ => self.output_steps = [0; 4],
        }
        self.output = self.output_steps.map(|s| s as f64 * self.quantum);
        (self.mode, self.output)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MS: u64 = 1_000_000;

    fn cfg() -> SafetyConfig {
        SafetyConfig {
            max_torque_nm: [100.0, 100.0, 50.0, 50.0],
            max_delta_nm_per_tick: 10.0,
            hold_after_ns: 100 * MS,
            safe_after_ns: 300 * MS,
            fault_after_ns: 1000 * MS,
        }
    }

    #[test]
    fn refuses_non_finite() {
        assert!(Command::new([f64::NAN, 0.0, 0.0, 0.0], 1, 0).is_err());
        assert!(Command::new([0.0, f64::INFINITY, 0.0, 0.0], 1, 0).is_err());
        assert!(Command::new([0.0, 0.0, 0.0, f64::NEG_INFINITY], 1, 0).is_err());
        assert!(Command::new([1.0; 4], 1, 0).is_ok());
    }

    #[test]
    fn validates_config() {
        assert!(cfg().validate().is_ok());
        let mut c = cfg();
        c.max_torque_nm[2] = f64::NAN;
        assert!(c.validate().is_err());
        let mut c = cfg();
        c.max_torque_nm[0] = 5000.0;
        assert!(c.validate().is_err());
        let mut c = cfg();
        c.safe_after_ns = c.hold_after_ns;
        assert!(c.validate().is_err());
        let mut c = cfg();
        c.max_delta_nm_per_tick = 0.0;
        assert!(c.validate().is_err());
    }

    #[test]
    fn clamps_and_rate_limits() {
        let mut s = Safety::new(cfg(), 0);
        let c = Command::new([500.0, -500.0, 30.0, -1000.0], 1, 0).unwrap();
        let mut outs = vec![];
        for k in 0..20u64 {
            let (m, o) = s.step(k * MS, Some(&c));
            assert_eq!(m, Mode::Active);
            outs.push(o);
        }
        assert_eq!(outs[0], [10.0, -10.0, 10.0, -10.0]);
        assert_eq!(outs[1], [20.0, -20.0, 20.0, -20.0]);
        assert_eq!(outs[2], [30.0, -30.0, 30.0, -30.0]);
        assert_eq!(outs[19], [100.0, -100.0, 30.0, -50.0]);
        for w in outs.windows(2) {
            for (a, b) in w[0].iter().zip(w[1].iter()) {
                assert!((b - a).abs() <= 10.0 + 1e-12);
            }
        }
    }

    #[test]
    fn watchdog_hold_safe_fault_and_reset() {
        let mut s = Safety::new(cfg(), 0);
        // No command at all: Safe, then Fault after fault_after.
        assert_eq!(s.step(10 * MS, None).0, Mode::Safe);
        let c = Command::new([20.0; 4], 1, 50 * MS).unwrap();
        assert_eq!(s.step(50 * MS, Some(&c)), (Mode::Active, [10.0; 4]));
        assert_eq!(s.step(100 * MS, Some(&c)), (Mode::Active, [20.0; 4]));
        assert_eq!(s.step(150 * MS, Some(&c)).0, Mode::Active); // age 100 ms: not yet late
        assert_eq!(s.step(151 * MS, Some(&c)), (Mode::Hold, [20.0; 4]));
        assert_eq!(s.step(350 * MS, Some(&c)), (Mode::Hold, [20.0; 4]));
        assert_eq!(s.step(351 * MS, Some(&c)), (Mode::Safe, [0.0; 4]));
        assert_eq!(s.step(1050 * MS, Some(&c)), (Mode::Safe, [0.0; 4]));
        assert_eq!(s.step(1051 * MS, Some(&c)), (Mode::Fault, [0.0; 4]));
        // A fresh command does not clear a latched fault.
        let c2 = Command::new([20.0; 4], 2, 1100 * MS).unwrap();
        assert_eq!(s.step(1100 * MS, Some(&c2)), (Mode::Fault, [0.0; 4]));
        // Reset: old command ignored, Safe until a newer one arrives.
        assert!(s.reset(1200 * MS));
        assert_eq!(s.step(1210 * MS, Some(&c2)), (Mode::Safe, [0.0; 4]));
        let c3 = Command::new([20.0; 4], 3, 1220 * MS).unwrap();
        assert_eq!(s.step(1250 * MS, Some(&c3)), (Mode::Active, [10.0; 4]));
        // Silence after a reset latches again.
        assert_eq!(s.step(2300 * MS, Some(&c3)).0, Mode::Fault);
        assert!(!Safety::new(cfg(), 0).reset(5));
    }

    /// A command far beyond every limit, then a reversal; checks every output.
    fn drive(c: SafetyConfig, ticks: u64) -> Vec<[f64; 4]> {
        let mut s = Safety::new(c, 0);
        let mut outs = vec![[0.0; 4]];
        for k in 0..ticks {
            let sign = if k < ticks / 2 { 1.0 } else { -1.0 };
            let cmd = Command::new(
                [sign * 1000.0, -sign * 1000.0, sign * 7.3, 5.25],
                k + 1,
                k * MS,
            )
            .unwrap();
            let (m, o) = s.step(k * MS, Some(&cmd));
            assert_eq!(m, Mode::Active);
            outs.push(o);
        }
        outs
    }

    fn assert_within_limits(c: &SafetyConfig, outs: &[[f64; 4]]) {
        for o in outs {
            for (i, x) in o.iter().enumerate() {
                assert!(
                    x.abs() <= c.max_torque_nm[i],
                    "{x} over {:?}",
                    c.max_torque_nm
                );
                assert_eq!((x / 0.5).fract(), 0.0, "{x} is not on the 0.5 Nm grid");
            }
        }
        for w in outs.windows(2) {
            for (a, b) in w[0].iter().zip(w[1].iter()) {
                assert!((b - a).abs() <= c.max_delta_nm_per_tick, "step {a} -> {b}");
            }
        }
    }

    #[test]
    fn limits_hold_on_the_wire_grid() {
        // Limits that are not multiples of the 0.5 Nm resolution act rounded
        // toward zero: 300.3 -> 300.0, 100.8 -> 100.5, a rate of 1.3 -> 1.0.
        for (lim, rate) in [
            ([300.3, 100.8, 0.5, 999.9], 1000.0),
            ([300.3, 0.76, 50.0, 1000.0], 1.3),
            ([10.0, 10.0, 10.0, 10.0], 0.5),
            ([2.9, 3.1, 1.2, 0.99], 0.7),
        ] {
            let mut c = cfg();
            c.max_torque_nm = lim;
            c.max_delta_nm_per_tick = rate;
            c.validate().unwrap();
            let outs = drive(c, 4000);
            assert_within_limits(&c, &outs);
            // The output still reaches the (rounded) limits: no deadlock.
            let mid = outs[2000];
            let floor = |x: f64| (x / 0.5).floor() * 0.5;
            assert_eq!(mid[0], floor(lim[0]));
            assert_eq!(mid[1], -floor(lim[1]));
        }
        let mut c = cfg();
        c.max_torque_nm = [300.3; 4];
        c.max_delta_nm_per_tick = 1000.0;
        let mut s = Safety::new(c, 0);
        let cmd = Command::new([1000.0, -1000.0, 300.2, 5.25], 1, 0).unwrap();
        assert_eq!(s.step(0, Some(&cmd)).1, [300.0, -300.0, 300.0, 5.0]);
        // Rate 1.3: steps of 1.0 on the wire.
        let mut c = cfg();
        c.max_delta_nm_per_tick = 1.3;
        let mut s = Safety::new(c, 0);
        let cmd = Command::new([100.0; 4], 1, 0).unwrap();
        assert_eq!(s.step(0, Some(&cmd)).1, [1.0; 4]);
        assert_eq!(s.step(MS, Some(&cmd)).1, [2.0; 4]);
    }

    #[test]
    fn limits_below_one_grid_step_are_refused() {
        let mut c = cfg();
        c.max_torque_nm[1] = 0.3;
        let e = c.validate().unwrap_err().to_string();
        assert!(
            e.contains("max_torque_nm[1] = 0.3") && e.contains("resolution"),
            "{e}"
        );
        for r in [0.2, 0.3, 0.49] {
            let mut c = cfg();
            c.max_delta_nm_per_tick = r;
            let e = c.validate().unwrap_err().to_string();
            assert!(
                e.contains("max_rate_nm_per_tick") && e.contains("resolution"),
                "{e}"
            );
        }
        let mut c = cfg();
        c.max_delta_nm_per_tick = 0.5;
        c.max_torque_nm = [0.5; 4];
        assert!(c.validate().is_ok());
    }

    #[test]
    fn reset_without_a_latched_fault_changes_nothing() {
        let mut s = Safety::new(cfg(), 0);
        let c = Command::new([100.0; 4], 1, 0).unwrap();
        for k in 0..5 {
            s.step(k * MS, Some(&c));
        }
        assert_eq!(s.output(), [50.0, 50.0, 50.0, 50.0]);
        assert!(!s.reset(5 * MS));
        // Still active, still ramping from 50 under the rate limit.
        assert_eq!(
            s.step(6 * MS, Some(&c)),
            (Mode::Active, [60.0, 60.0, 50.0, 50.0])
        );
    }

    #[test]
    fn force_safe_keeps_fault() {
        let mut s = Safety::new(cfg(), 0);
        let c = Command::new([20.0; 4], 1, 0).unwrap();
        s.step(0, Some(&c));
        assert_eq!(s.force_safe(), (Mode::Safe, [0.0; 4]));
        s.step(2000 * MS, Some(&c));
        assert_eq!(s.force_safe().0, Mode::Fault);
    }
}
