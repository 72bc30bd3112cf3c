//! Physical plausibility of the received signals, beyond each signal's DBC
//! range (`codec::Message::implausible`):
//!
//! * **Rate of change.** A value may move from the last one accepted for
//!   its message by at most its signal's `max_rate` times the time between
//!   the two (the longer of the arrival times' difference and the counter
//!   steps times the message's cycle, so a late or bunched arrival never
//!   makes a sound frame implausible), plus two steps of its resolution. A
//!   speed alternating 12 <-> 85 m/s every 20 ms (3,650 m/s^2) is refused
//!   (`test_i4_a_speed_jumping_12_85_every_frame_is_never_believed`).
//! * **Wheel speeds against the vehicle speed.** A wheel that brakes only
//!   (its actuator's `max_nm` is 0) cannot turn faster than the road under
//!   it: its circumferential speed `|omega| R` may exceed the vehicle's
//!   speed at that wheel, `|v_x| + |r| T/2 + (|v_y| + |r| a) |delta|`, by at
//!   most `tolerance_mps + tolerance_rel |v_x|`. A driven wheel can spin and
//!   any wheel can lock, so no other bound holds; a vehicle speed reported
//!   too high is caught by its rate of change only (`docs/bus-safety.md`).
//!
//! The defaults are the vehicle's: rates from its limits (`vehicle.toml`,
//! `[rx_max_rate]`), geometry from `ampc_jax.vehicle.params.VehicleParams`
//! (`[rx_wheels]`); both are configurable and validated by name.

use crate::codec::{Message, N_RX, RX_MESSAGES};

/// Names of the rate-checked signals, per received message, in payload order.
pub fn signal_names(m: usize) -> Vec<&'static str> {
    RX_MESSAGES
        .get(m)
        .map(|msg| msg.signals.iter().skip(2).map(|s| s.name).collect())
        .unwrap_or_default()
}

/// The plausibility settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plausibility {
    /// Largest rate of change per received signal, per second (`RX_MESSAGES`
    /// order, payload signals in DBC order; unused slots 0).
    pub max_rate: [[f64; 4]; N_RX],
    /// Effective wheel radius, m.
    pub wheel_radius_m: f64,
    /// Track width, m.
    pub track_m: f64,
    /// Centre of gravity to front axle, m.
    pub cg_to_front_m: f64,
    /// Absolute allowance of a brake-only wheel over the vehicle's speed, m/s.
    pub tolerance_mps: f64,
    /// Allowance relative to the vehicle's speed (tyre radius, slip).
    pub tolerance_rel: f64,
}

/// Largest rates of change, per signal: `(name, unit/s, reason)`. The
/// reasons are the vehicle's limits (`docs/bus-safety.md` lists them).
pub const DEFAULT_RATES: [(&str, f64); 13] = [
    // speed: no acceleration beyond the IMU's 20 m/s^2 range
    ("LongSpeed", 20.0),
    // dv_y/dt = a_y - r v_x: 20 m/s^2 plus 1 rad/s at 30 m/s
    ("LatSpeed", 50.0),
    // yaw acceleration: all four tyres' lateral force at mu = 2 on the
    // axles' lever arms over I_z, with margin
    ("YawRate", 20.0),
    // a wheel: (2000 Nm + mu F_z R) / I_w with mu = 2 and half the
    // vehicle's weight on it (6,100 rad/s^2), with margin
    ("WheelSpeedFL", 8000.0),
    ("WheelSpeedFR", 8000.0),
    ("WheelSpeedRL", 8000.0),
    ("WheelSpeedRR", 8000.0),
    // a driver's fastest road-wheel steering, with margin
    ("SteeringAngle", 3.0),
    // jerk: the full IMU range in 40 ms
    ("LongAccel", 1000.0),
    ("LatAccel", 1000.0),
    // the pedal map's full range in 0.3 s
    ("DriverTorque", 50000.0),
    // set speed and friction estimate: at most a step a frame that a
    // human or an estimator makes (resume to 90 m/s takes 2 s)
    ("SetSpeed", 50.0),
    ("RoadFriction", 25.0),
];

impl Default for Plausibility {
    /// The shipped `vehicle.toml` (a Rust test keeps the two equal).
    fn default() -> Self {
        let mut max_rate = [[0.0; 4]; N_RX];
        for (m, rates) in max_rate.iter_mut().enumerate() {
            for (slot, name) in rates.iter_mut().zip(signal_names(m)) {
                *slot = DEFAULT_RATES
                    .iter()
                    .find(|(n, _)| *n == name)
                    .map_or(0.0, |(_, r)| *r);
            }
        }
        Plausibility {
            max_rate,
            wheel_radius_m: 0.351,
            track_m: 1.66,
            cg_to_front_m: 1.42,
            tolerance_mps: 0.5,
            tolerance_rel: 0.05,
        }
    }
}

/// Bounds of each setting: `(name, lo, hi)`.
const GEOMETRY: [(&str, f64, f64); 5] = [
    ("rx_wheels.radius_m", 0.1, 2.0),
    ("rx_wheels.track_m", 0.3, 5.0),
    ("rx_wheels.cg_to_front_m", 0.0, 10.0),
    ("rx_wheels.tolerance_mps", 0.0, 20.0),
    ("rx_wheels.tolerance_rel", 0.0, 1.0),
];

/// Largest rate accepted for any signal, per second.
pub const MAX_RATE: f64 = 1e7;

impl Plausibility {
    /// The rate slot of signal `name`, if it is a received payload signal.
    pub fn rate_mut(&mut self, name: &str) -> Option<&mut f64> {
        let (m, i) =
            (0..N_RX).find_map(|m| Some((m, signal_names(m).iter().position(|n| *n == name)?)))?;
        self.max_rate.get_mut(m)?.get_mut(i)
    }

    /// The geometry slot of `rx_wheels.KEY`.
    pub fn geometry_mut(&mut self, key: &str) -> Option<&mut f64> {
        match key {
            "radius_m" => Some(&mut self.wheel_radius_m),
            "track_m" => Some(&mut self.track_m),
            "cg_to_front_m" => Some(&mut self.cg_to_front_m),
            "tolerance_mps" => Some(&mut self.tolerance_mps),
            "tolerance_rel" => Some(&mut self.tolerance_rel),
            _ => None,
        }
    }

    /// Check every setting; the error names it.
    pub fn validate(&self) -> std::result::Result<(), String> {
        for (m, rates) in self.max_rate.iter().enumerate() {
            for (name, r) in signal_names(m).iter().zip(rates) {
                if !(r.is_finite() && *r > 0.0 && *r <= MAX_RATE) {
                    return Err(format!(
                        "rx_max_rate.{name} = {r} must be in (0, {MAX_RATE}] per second"
                    ));
                }
            }
        }
        let vals = [
            self.wheel_radius_m,
            self.track_m,
            self.cg_to_front_m,
            self.tolerance_mps,
            self.tolerance_rel,
        ];
        for ((name, lo, hi), v) in GEOMETRY.iter().zip(vals) {
            if !(v.is_finite() && v >= *lo && v <= *hi) {
                return Err(format!("{name} = {v} must be in [{lo}, {hi}]"));
            }
        }
        Ok(())
    }

    /// The first signal of message `m` whose change from `prev` over `dt_s`
    /// is faster than its rate (plus two steps of its resolution).
    pub fn rate_violation(
        &self,
        m: usize,
        msg: &Message,
        prev: &[f64; 4],
        new: &[f64; 4],
        dt_s: f64,
    ) -> Option<(&'static str, f64, f64)> {
        let rates = self.max_rate.get(m)?;
        msg.signals
            .iter()
            .skip(2)
            .zip(rates)
            .zip(prev.iter().zip(new))
            .find_map(|((sig, rate), (a, b))| {
                let allowed = rate * dt_s + 2.0 * sig.factor;
                ((b - a).abs() > allowed).then_some((sig.name, *a, *b))
            })
    }

    /// The first brake-only wheel (`undriven`) that turns faster than the
    /// vehicle's speed at it allows: `(wheel index, its speed, the bound)`,
    /// both in m/s. `motion` is (v_x, v_y, yaw rate), `steer` the road-wheel
    /// angle (1 rad, the DBC's bound, when unknown).
    pub fn wheel_violation(
        &self,
        motion: [f64; 3],
        wheels: &[f64; 4],
        steer: Option<f64>,
        undriven: [bool; 4],
    ) -> Option<(usize, f64, f64)> {
        let [vx, vy, r] = motion;
        let delta = steer.map_or(1.0, f64::abs).min(1.0);
        let bound = vx.abs()
            + r.abs() * self.track_m / 2.0
            + (vy.abs() + r.abs() * self.cg_to_front_m) * delta
            + self.tolerance_mps
            + self.tolerance_rel * vx.abs();
        wheels
            .iter()
            .zip(undriven)
            .enumerate()
            .find_map(|(i, (w, free))| {
                let v = w.abs() * self.wheel_radius_m;
                (free && v > bound).then_some((i, v, bound))
            })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codec::{VEHICLE_MOTION, WHEEL_SPEEDS};

    #[test]
    fn every_received_signal_has_a_default_rate() {
        let p = Plausibility::default();
        p.validate().unwrap();
        assert_eq!(p.max_rate[0], [20.0, 50.0, 20.0, 0.0]);
        assert_eq!(p.max_rate[1], [8000.0; 4]);
    }

    #[test]
    fn rate_of_change_over_the_time_between_frames() {
        let p = Plausibility::default();
        let a = [12.0, 0.0, 0.0, 0.0];
        // 73 m/s in 20 ms: no
        let v = p.rate_violation(0, &VEHICLE_MOTION, &a, &[85.0, 0.0, 0.0, 0.0], 0.02);
        assert_eq!(v.map(|x| x.0), Some("LongSpeed"));
        // 0.4 m/s in 20 ms (20 m/s^2) plus two resolution steps: yes
        assert!(p
            .rate_violation(0, &VEHICLE_MOTION, &a, &[12.42, 0.0, 0.0, 0.0], 0.02)
            .is_none());
        // the same jump after 4 s: yes
        assert!(p
            .rate_violation(0, &VEHICLE_MOTION, &a, &[85.0, 0.0, 0.0, 0.0], 4.0)
            .is_none());
        assert!(p
            .rate_violation(1, &WHEEL_SPEEDS, &[0.0; 4], &[100.0; 4], 0.02)
            .is_none());
    }

    #[test]
    fn a_brake_only_wheel_faster_than_the_vehicle_is_inconsistent() {
        let p = Plausibility::default();
        let free = [true, true, false, false];
        let at = |v: f64| v / 0.351;
        // straight at 12 m/s: the front wheels at 12 m/s, the rear spinning at 40
        let w = [at(12.0), at(12.0), at(40.0), at(40.0)];
        assert!(p
            .wheel_violation([12.0, 0.0, 0.0], &w, Some(0.0), free)
            .is_none());
        // a front wheel at 40 m/s while the vehicle makes 12
        let w = [at(40.0), at(12.0), at(12.0), at(12.0)];
        let v = p
            .wheel_violation([12.0, 0.0, 0.0], &w, Some(0.0), free)
            .unwrap();
        assert_eq!(v.0, 0);
        // locked wheels are physical
        assert!(p
            .wheel_violation([30.0, 0.0, 0.0], &[0.0; 4], Some(0.0), free)
            .is_none());
        // the outer front wheel in a turn: v + r T/2
        let w = [at(20.0 + 0.8), at(20.0), at(20.0), at(20.0)];
        assert!(p
            .wheel_violation([20.0, 0.5, 1.0], &w, Some(0.1), free)
            .is_none());
        // reversing
        let w = [at(-5.0), at(-5.0), at(-5.0), at(-5.0)];
        assert!(p
            .wheel_violation([-5.0, 0.0, 0.0], &w, None, free)
            .is_none());
    }

    #[test]
    fn the_rate_bound_is_the_rate_times_the_time_plus_two_resolution_steps() {
        // LongSpeed: 20 m/s^2 and 0.01 m/s steps; LatSpeed 50 m/s^2
        let p = Plausibility::default();
        let check = |prev: [f64; 4], new: [f64; 4], dt: f64| {
            p.rate_violation(0, &VEHICLE_MOTION, &prev, &new, dt)
        };
        let allowed = 20.0 * 0.02 + 2.0 * 0.01;
        // exactly the allowance, either way: physical; beyond it: not
        assert_eq!(check([0.0; 4], [allowed, 0.0, 0.0, 0.0], 0.02), None);
        assert_eq!(check([allowed, 0.0, 0.0, 0.0], [0.0; 4], 0.02), None);
        let v = check([0.0; 4], [allowed + 1e-9, 0.0, 0.0, 0.0], 0.02);
        assert_eq!(v, Some(("LongSpeed", 0.0, allowed + 1e-9)));
        // a change across zero counts its whole size
        assert!(check([0.3, 0.0, 0.0, 0.0], [-0.3, 0.0, 0.0, 0.0], 0.02).is_some());
        // a small change far from zero is physical
        assert_eq!(
            check([10.0, 0.0, 0.0, 0.0], [10.1, 0.0, 0.0, 0.0], 0.02),
            None
        );
        // the allowance grows with the time: 0.42 m/s in 20 ms, 0.82 in 40
        assert_eq!(check([0.0; 4], [0.8, 0.0, 0.0, 0.0], 0.04), None);
        assert!(check([0.0; 4], [0.83, 0.0, 0.0, 0.0], 0.04).is_some());
        // each signal by its own rate and resolution: LatSpeed (50 m/s^2,
        // 0.01 m/s) may move 1.02 m/s in 20 ms; the first offender is named
        assert_eq!(check([0.0; 4], [0.0, 1.0, 0.0, 0.0], 0.02), None);
        let v = check([0.0; 4], [0.0, 1.1, 0.0, 0.0], 0.02);
        assert_eq!(v.map(|x| x.0), Some("LatSpeed"));
        // no such message: nothing to say
        assert_eq!(
            p.rate_violation(N_RX, &VEHICLE_MOTION, &[0.0; 4], &[50.0; 4], 0.02),
            None
        );
    }

    #[test]
    fn the_wheel_bound_is_the_road_speed_at_the_wheel_plus_the_tolerances() {
        // |v_x| + |r| T/2 + (|v_y| + |r| a) |delta| + tol + rel |v_x|, each
        // term with its own number so that each one counts
        let p = Plausibility {
            wheel_radius_m: 0.3,
            track_m: 1.6,
            cg_to_front_m: 1.2,
            tolerance_mps: 0.5,
            tolerance_rel: 0.05,
            ..Plausibility::default()
        };
        let (vx, vy, r, delta) = (-20.0, 1.5, -0.8, 0.3);
        let bound = 20.0 + 0.8 * 0.8 + (1.5 + 0.8 * 1.2) * 0.3 + 0.5 + 0.05 * 20.0;
        let at = |v: f64| v / 0.3;
        let free = [true, true, false, false];
        let judge =
            |w: [f64; 4], steer: Option<f64>| p.wheel_violation([vx, vy, r], &w, steer, free);
        // just inside: physical, whatever the sign of the wheel speed
        let inside = at(bound - 1e-6);
        assert_eq!(judge([inside, -inside, 0.0, 0.0], Some(delta)), None);
        // just outside on the second front wheel: that one, its speed and
        // the bound
        let (i, v, b) = judge([inside, at(bound + 1e-6), 0.0, 0.0], Some(-delta)).unwrap();
        assert_eq!(i, 1);
        assert!((v - (bound + 1e-6)).abs() < 1e-9, "{v}");
        assert!((b - bound).abs() < 1e-9, "{b} {bound}");
        // a driven wheel may spin
        assert_eq!(judge([0.0, 0.0, at(90.0), at(90.0)], Some(delta)), None);
        // exactly at the bound is physical (numbers exact in binary:
        // 10 + 0.5 + 0.05 x 10 = 11 m/s, 22 rad/s at 0.5 m)
        let p = Plausibility {
            wheel_radius_m: 0.5,
            ..p
        };
        assert_eq!(
            p.wheel_violation([10.0, 0.0, 0.0], &[22.0; 4], Some(0.0), free),
            None
        );
        assert!(p
            .wheel_violation([10.0, 0.0, 0.0], &[22.001; 4], Some(0.0), free)
            .is_some());
        // no steering angle, or one beyond 1 rad: 1 rad
        let wide = bound + (1.5 + 0.8 * 1.2) * 0.7;
        for steer in [None, Some(-3.0)] {
            let (_, _, b) = judge([at(wide + 1.0), 0.0, 0.0, 0.0], steer).unwrap();
            assert!((b - wide).abs() < 1e-9, "{steer:?}: {b} {wide}");
        }
    }

    #[test]
    fn the_limits_of_every_setting_are_inclusive_and_named() {
        // every rate: (0, MAX_RATE]
        for m in 0..N_RX {
            for name in signal_names(m) {
                for (r, ok) in [
                    (MAX_RATE, true),
                    (1e-9, true),
                    (MAX_RATE * 1.000_001, false),
                    (0.0, false),
                    (-1.0, false),
                    (f64::NAN, false),
                ] {
                    let mut p = Plausibility::default();
                    *p.rate_mut(name).unwrap() = r;
                    match p.validate() {
                        Ok(()) => assert!(ok, "{name} = {r} accepted"),
                        Err(e) => {
                            assert!(!ok, "{name} = {r} refused: {e}");
                            assert!(e.contains(&format!("rx_max_rate.{name} = ")), "{e}");
                        }
                    }
                }
            }
        }
        // every geometry setting: [lo, hi]
        for (key, lo, hi) in GEOMETRY {
            let short = key.trim_start_matches("rx_wheels.");
            for (v, ok) in [
                (lo, true),
                (hi, true),
                (lo - 1e-9, false),
                (hi + 1e-9, false),
                (f64::NAN, false),
            ] {
                let mut p = Plausibility::default();
                *p.geometry_mut(short).unwrap() = v;
                match p.validate() {
                    Ok(()) => assert!(ok, "{key} = {v} accepted"),
                    Err(e) => {
                        assert!(!ok, "{key} = {v} refused: {e}");
                        assert!(e.starts_with(&format!("{key} = ")), "{e}");
                    }
                }
            }
        }
    }

    #[test]
    fn each_setting_is_reached_by_its_own_name() {
        for m in 0..N_RX {
            for (i, name) in signal_names(m).into_iter().enumerate() {
                let mut p = Plausibility::default();
                *p.rate_mut(name).unwrap() = 123.0;
                let mut want = Plausibility::default().max_rate;
                want[m][i] = 123.0;
                assert_eq!(p.max_rate, want, "{name}");
            }
        }
        let fields = |p: &Plausibility| {
            [
                p.wheel_radius_m,
                p.track_m,
                p.cg_to_front_m,
                p.tolerance_mps,
                p.tolerance_rel,
            ]
        };
        for (j, key) in [
            "radius_m",
            "track_m",
            "cg_to_front_m",
            "tolerance_mps",
            "tolerance_rel",
        ]
        .into_iter()
        .enumerate()
        {
            let mut p = Plausibility::default();
            *p.geometry_mut(key).unwrap() = 0.123;
            let mut want = fields(&Plausibility::default());
            want[j] = 0.123;
            assert_eq!(fields(&p), want, "{key}");
        }
        assert!(Plausibility::default().geometry_mut("spokes").is_none());
        assert_eq!(signal_names(N_RX), Vec::<&str>::new());
        assert_eq!(signal_names(2), ["SteeringAngle"]);
    }

    #[test]
    fn settings_are_validated_by_name() {
        let mut p = Plausibility::default();
        *p.rate_mut("YawRate").unwrap() = -1.0;
        assert!(p.validate().unwrap_err().contains("rx_max_rate.YawRate"));
        let mut p = Plausibility::default();
        *p.geometry_mut("radius_m").unwrap() = 5.0;
        assert!(p.validate().unwrap_err().contains("rx_wheels.radius_m"));
        assert!(Plausibility::default().rate_mut("Nope").is_none());
    }
}
