//! The receive loop and the received vehicle state: each frame checked
//! (length, E2E Profile 1 CRC and counter, plausibility), judged over its
//! message's window, and stored only if usable.

use super::{lock, Shared};
use crate::candump::{Dir, LogSender};
use crate::codec::{N_RX, RX_MESSAGES};
use crate::e2e::{Check, Judge, Receiver};
use crate::frame::CanFrame;
use crate::scheduler::{monotonic_ns, realtime_ns};
use crate::transport::{RxItem, Source};
use std::sync::atomic::{AtomicBool, Ordering};

/// Receive thread poll timeout, ms (bounds stop latency).
const RX_POLL_MS: i32 = 20;

#[derive(Debug, Clone)]
struct RxSlotState {
    receiver: Receiver,
    judge: Judge,
    /// Last frame that passed length and CRC (for the resync after a gap).
    last_seen_ns: Option<u64>,
    /// Last usable frame.
    last_ok_ns: Option<u64>,
    values: [f64; 4],
}

/// Receive-side state and counters.
#[derive(Debug, Clone)]
pub struct RxStore {
    slots: Vec<RxSlotState>,
    pub(super) rx_frames: u64,
    pub(super) rx_crc_errors: u64,
    pub(super) rx_counter_errors: u64,
    pub(super) rx_repeated: u64,
    pub(super) rx_two_sources: u64,
    pub(super) rx_wrong_sequence: u64,
    pub(super) rx_lost_frames: u64,
    pub(super) rx_sync: u64,
    pub(super) rx_implausible: u64,
    pub(super) rx_length_errors: u64,
    pub(super) rx_malformed: u64,
    pub(super) rx_unknown_id: u64,
    pub(super) rx_transport_errors: u64,
    pub(super) bus_errors: u64,
    pub(super) last_error: Option<String>,
}

/// Names of the received messages, in [`RX_MESSAGES`] order.
pub const RX_NAMES: [&str; N_RX] = [
    "VehicleMotion",
    "WheelSpeeds",
    "SteeringState",
    "VehicleAccel",
    "DriverDemand",
];

impl RxStore {
    /// Empty state; see [`BridgeConfig`] for the receiver settings.
    pub fn new(max_delta: u8, sync_frames: u8, max_strikes: u32) -> Self {
        RxStore {
            slots: RX_MESSAGES
                .iter()
                .map(|m| RxSlotState {
                    receiver: Receiver::new(m.data_id, m.len, max_delta, sync_frames),
                    judge: Judge::new(max_strikes),
                    last_seen_ns: None,
                    last_ok_ns: None,
                    values: [0.0; 4],
                })
                .collect(),
            rx_frames: 0,
            rx_crc_errors: 0,
            rx_counter_errors: 0,
            rx_repeated: 0,
            rx_two_sources: 0,
            rx_wrong_sequence: 0,
            rx_lost_frames: 0,
            rx_sync: 0,
            rx_implausible: 0,
            rx_length_errors: 0,
            rx_malformed: 0,
            rx_unknown_id: 0,
            rx_transport_errors: 0,
            bus_errors: 0,
            last_error: None,
        }
    }

    /// Check, judge and (if usable and plausible) store one received frame.
    pub fn on_frame(&mut self, f: &CanFrame, now_ns: u64, state_timeout_ns: u64) -> Check {
        self.rx_frames += 1;
        let idx = RX_MESSAGES
            .iter()
            .position(|m| m.id == f.id() && !f.is_extended() && !f.is_remote());
        let Some((m, slot)) = idx.and_then(|i| Some((RX_MESSAGES.get(i)?, self.slots.get_mut(i)?)))
        else {
            self.rx_unknown_id += 1;
            return Check::BadLength;
        };
        // After a gap the counter is anchored afresh (INITIAL, then SYNC).
        if slot
            .last_seen_ns
            .is_none_or(|t| now_ns.saturating_sub(t) > state_timeout_ns)
        {
            slot.receiver.resync();
            slot.judge.reset();
        }
        let mut verdict = slot.receiver.check(f.data());
        if !matches!(verdict, Check::BadLength | Check::BadCrc) {
            slot.last_seen_ns = Some(now_ns);
        }
        let mut values = [0.0; 4];
        if verdict.usable() {
            m.decode_values(f.data(), &mut values);
            if let Some((name, v)) = m.implausible(&values[..m.signals.len() - 2]) {
                verdict = Check::Implausible;
                self.last_error = Some(format!("{}: {name} = {v} is implausible", m.name));
            }
        }
        slot.judge.record(verdict);
        match verdict {
            Check::Ok | Check::OkSomeLost => {
                slot.values = values;
                slot.last_ok_ns = Some(now_ns);
                if verdict == Check::OkSomeLost {
                    self.rx_lost_frames += 1;
                }
            }
            Check::Initial | Check::Sync => self.rx_sync += 1,
            Check::BadCrc => self.rx_crc_errors += 1,
            Check::BadLength => self.rx_length_errors += 1,
            Check::Implausible => self.rx_implausible += 1,
            Check::Repeated => {
                self.rx_repeated += 1;
                self.rx_counter_errors += 1;
            }
            Check::TwoSources => {
                self.rx_two_sources += 1;
                self.rx_counter_errors += 1;
            }
            Check::WrongSequence => {
                self.rx_wrong_sequence += 1;
                self.rx_counter_errors += 1;
            }
            Check::InvalidCounter => self.rx_counter_errors += 1,
        }
        verdict
    }

    /// The vehicle state as of `now_ns`.
    pub fn state(&self, now_ns: u64, state_timeout_ns: u64) -> VehicleState {
        let mut status = ["no data"; N_RX];
        for (st, slot) in status.iter_mut().zip(&self.slots) {
            // A sender that keeps sending bad frames is reported by what is
            // wrong with them ("repeated", ...), not merely as a timeout.
            let fresh = slot
                .last_seen_ns
                .is_some_and(|t| now_ns.saturating_sub(t) <= state_timeout_ns);
            *st = match (slot.last_ok_ns, slot.judge.verdict()) {
                (_, Err(why)) if fresh || slot.last_ok_ns.is_none() => why,
                (None, _) => "no data",
                (Some(t), _) if now_ns.saturating_sub(t) > state_timeout_ns => "timeout",
                (Some(_), Err(why)) => why,
                (Some(_), Ok(())) => "ok",
            };
        }
        let valid = status.iter().all(|s| *s == "ok");
        let reason = (!valid).then(|| {
            RX_NAMES
                .iter()
                .zip(status)
                .filter(|(_, s)| *s != "ok")
                .map(|(n, s)| format!("{n}: {s}"))
                .collect::<Vec<_>>()
                .join("; ")
        });
        let get = |i: usize| {
            self.slots
                .get(i)
                .and_then(|s| s.last_ok_ns.map(|t| (t, s.values)))
        };
        let (motion, wheels, steer, accel, driver) = (get(0), get(1), get(2), get(3), get(4));
        // The state is as old as its oldest message, and has no age until
        // every message has arrived once.
        let ages: [Option<u64>; N_RX] = [motion, wheels, steer, accel, driver]
            .map(|x| x.map(|(t, _)| now_ns.saturating_sub(t)));
        let age_ms = if ages.iter().all(Option::is_some) {
            ages.iter().flatten().max().map(|a| *a as f64 / 1e6)
        } else {
            None
        };
        VehicleState {
            valid,
            long_speed_mps: motion.map(|(_, v)| v[0]),
            lat_speed_mps: motion.map(|(_, v)| v[1]),
            yaw_rate_radps: motion.map(|(_, v)| v[2]),
            wheel_speeds_radps: wheels.map(|(_, v)| v),
            steering_angle_rad: steer.map(|(_, v)| v[0]),
            long_accel_mps2: accel.map(|(_, v)| v[0]),
            lat_accel_mps2: accel.map(|(_, v)| v[1]),
            driver_torque_nm: driver.map(|(_, v)| v[0]),
            set_speed_mps: driver.map(|(_, v)| v[1]),
            road_friction: driver.map(|(_, v)| v[2]),
            age_ms,
            status,
            reason,
        }
    }
}

/// The received vehicle state, from the five received messages
/// ([`RX_NAMES`]). Values are those of each message's last usable frame
/// (`None` until there is one); `valid` is true only while all five are
/// judged valid (`status`, `reason` say why not).
#[derive(Clone, Debug, PartialEq)]
pub struct VehicleState {
    /// All five messages fresh and judged valid over their windows.
    pub valid: bool,
    /// Longitudinal speed, m/s.
    pub long_speed_mps: Option<f64>,
    /// Lateral speed, m/s.
    pub lat_speed_mps: Option<f64>,
    /// Yaw rate, rad/s.
    pub yaw_rate_radps: Option<f64>,
    /// Wheel speeds FL, FR, RL, RR, rad/s.
    pub wheel_speeds_radps: Option<[f64; 4]>,
    /// Steering angle, rad.
    pub steering_angle_rad: Option<f64>,
    /// Longitudinal acceleration (body frame, centre of gravity), m/s^2.
    pub long_accel_mps2: Option<f64>,
    /// Lateral acceleration (body frame, centre of gravity), m/s^2.
    pub lat_accel_mps2: Option<f64>,
    /// The driver's rear-axle torque request, Nm.
    pub driver_torque_nm: Option<f64>,
    /// Cruise set speed, m/s.
    pub set_speed_mps: Option<f64>,
    /// Road-friction estimate published by the vehicle (dimensionless).
    pub road_friction: Option<f64>,
    /// Age of the oldest of the five messages, ms (`None` until all arrived).
    pub age_ms: Option<f64>,
    /// Per message (`RX_NAMES` order): "ok" or why it is not valid.
    pub status: [&'static str; N_RX],
    /// `None` when valid, else "Message: why; ...".
    pub reason: Option<String>,
}

/// The receive loop: runs until `stop` is set.
pub fn run_rx(
    shared: &Shared,
    source: &mut dyn Source,
    state_timeout_ns: u64,
    stop: &AtomicBool,
    log: Option<&LogSender>,
) {
    while !stop.load(Ordering::Acquire) {
        match source.recv(RX_POLL_MS) {
            Ok(None) => {}
            Ok(Some(RxItem::Frame(f))) => {
                if let Some(l) = log {
                    l.log(realtime_ns(), &f, Dir::Rx);
                }
                lock(&shared.rx).on_frame(&f, monotonic_ns(), state_timeout_ns);
            }
            Ok(Some(RxItem::Malformed)) => lock(&shared.rx).rx_malformed += 1,
            Ok(Some(RxItem::BusError)) => lock(&shared.rx).bus_errors += 1,
            Err(e) => {
                {
                    let mut rx = lock(&shared.rx);
                    rx.rx_transport_errors += 1;
                    rx.last_error = Some(e.to_string());
                }
                std::thread::sleep(std::time::Duration::from_millis(RX_POLL_MS as u64));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::testutil::MS;
    use super::*;

    /// index into `RX_MESSAGES`), all with counter `c`.
    fn all_but(rx: &mut RxStore, skip: Option<usize>, c: u8, t: u64, to: u64) {
        use crate::codec::{
            DRIVER_DEMAND, STEERING_STATE, VEHICLE_ACCEL, VEHICLE_MOTION, WHEEL_SPEEDS,
        };
        let frames = [
            VEHICLE_MOTION.encode(&[12.34, -0.5, 0.25], c),
            WHEEL_SPEEDS.encode(&[40.1, 40.2, 40.3, 40.4], c),
            STEERING_STATE.encode(&[0.1234], c),
            VEHICLE_ACCEL.encode(&[-3.21, 7.5], c),
            DRIVER_DEMAND.encode(&[-1234.5, 17.25, 0.35], c),
        ];
        for (i, f) in frames.into_iter().enumerate() {
            if Some(i) != skip {
                rx.on_frame(&f.unwrap(), t, to);
            }
        }
    }

    /// One healthy frame of every received message, counter `c`.
    fn all_five(rx: &mut RxStore, c: u8, t: u64, to: u64) {
        all_but(rx, None, c, t, to);
    }

    #[test]
    fn receive_checks_and_state_validity() {
        use crate::codec::VEHICLE_MOTION;
        let mut rx = RxStore::new(2, 2, 2);
        let to = 250 * MS;
        let t = 10_000 * MS;
        let s = rx.state(t, to);
        assert!(
            !s.valid
                && s.reason
                    .as_deref()
                    .unwrap()
                    .contains("VehicleMotion: no data")
        );
        all_five(&mut rx, 0, t, to);
        all_five(&mut rx, 1, t, to);
        assert_eq!(rx.state(t, to).status, ["sync"; N_RX]);
        all_five(&mut rx, 2, t + MS, to);
        let s = rx.state(t + 2 * MS, to);
        assert!(s.valid, "{s:?}");
        assert!((s.long_speed_mps.unwrap() - 12.34).abs() < 1e-9);
        assert!((s.wheel_speeds_radps.unwrap()[3] - 40.4).abs() < 1e-9);
        assert_eq!(s.age_ms, Some(1.0));
        assert_eq!(s.status, ["ok"; N_RX]);
        // Bad CRC: rejected, value unchanged; one strike keeps it valid.
        let mut bad = VEHICLE_MOTION
            .encode(&[19.0, 0.0, 0.0], 3)
            .unwrap()
            .data()
            .to_vec();
        bad[0] ^= 1;
        rx.on_frame(&CanFrame::new(0x201, false, &bad).unwrap(), t + 3 * MS, to);
        assert_eq!(rx.rx_crc_errors, 1);
        assert_eq!(rx.state(t + 3 * MS, to).status[0], "wrong crc");
        rx.on_frame(
            &VEHICLE_MOTION.encode(&[1.0, 0.0, 0.0], 3).unwrap(),
            t + 4 * MS,
            to,
        );
        assert!(rx.state(t + 4 * MS, to).valid);
        // A repeat: invalid at once, and counted.
        rx.on_frame(
            &VEHICLE_MOTION.encode(&[1.0, 0.0, 0.0], 3).unwrap(),
            t + 5 * MS,
            to,
        );
        assert_eq!(rx.rx_repeated, 1);
        assert_eq!(rx.state(t + 5 * MS, to).status[0], "repeated");
        // Implausible value: not used.
        rx.on_frame(
            &VEHICLE_MOTION.encode(&[150.0, 0.0, 0.0], 4).unwrap(),
            t + 6 * MS,
            to,
        );
        assert_eq!(rx.rx_implausible, 1);
        assert!((rx.state(t + 6 * MS, to).long_speed_mps.unwrap() - 1.0).abs() < 1e-9);
        // Wrong length, unknown id.
        rx.on_frame(&CanFrame::new(0x203, false, &[0; 8]).unwrap(), t, to);
        rx.on_frame(&CanFrame::new(0x555, false, &[0; 8]).unwrap(), t, to);
        assert_eq!(rx.rx_length_errors, 1);
        assert_eq!(rx.rx_unknown_id, 1);
        // Goes invalid when it stops arriving; after the gap it re-synchronises.
        assert_eq!(rx.state(t + 300 * MS, to).status[1], "timeout");
        let sync = rx.rx_sync;
        all_five(&mut rx, 9, t + 600 * MS, to);
        all_five(&mut rx, 10, t + 601 * MS, to);
        assert_eq!(rx.rx_sync, sync + 2 * N_RX as u64);
        assert!(!rx.state(t + 601 * MS, to).valid);
        all_five(&mut rx, 11, t + 602 * MS, to);
        assert!(rx.state(t + 602 * MS, to).valid);
    }

    #[test]
    fn accel_and_driver_demand_decode_into_the_state() {
        let mut rx = RxStore::new(2, 2, 2);
        let to = 250 * MS;
        let t = 10_000 * MS;
        let s = rx.state(t, to);
        assert_eq!(
            (s.long_accel_mps2, s.driver_torque_nm, s.road_friction),
            (None, None, None)
        );
        for c in 0..3 {
            all_five(&mut rx, c, t + u64::from(c) * 20 * MS, to);
        }
        let s = rx.state(t + 45 * MS, to);
        assert!(s.valid, "{s:?}");
        let near = |x: Option<f64>, want: f64| (x.unwrap() - want).abs() < 1e-9;
        assert!(near(s.long_accel_mps2, -3.21), "{s:?}");
        assert!(near(s.lat_accel_mps2, 7.5), "{s:?}");
        assert!(near(s.driver_torque_nm, -1234.5), "{s:?}");
        assert!(near(s.set_speed_mps, 17.25), "{s:?}");
        assert!(near(s.road_friction, 0.35), "{s:?}");
        // Oldest of the five: all fed at t + 40 ms.
        assert_eq!(s.age_ms, Some(5.0));
    }

    #[test]
    fn a_missing_accel_or_driver_demand_makes_the_state_invalid() {
        for (skip, name) in [(3, "VehicleAccel"), (4, "DriverDemand")] {
            let mut rx = RxStore::new(2, 2, 2);
            let to = 250 * MS;
            let t = 10_000 * MS;
            // Never received: no data, and no age for the whole state.
            for c in 0..4 {
                all_but(&mut rx, Some(skip), c, t + u64::from(c) * 20 * MS, to);
            }
            let s = rx.state(t + 70 * MS, to);
            assert!(!s.valid);
            assert_eq!(s.reason.as_deref(), Some(&*format!("{name}: no data")));
            assert_eq!(s.status[skip], "no data");
            assert_eq!(s.age_ms, None);
            // Received, then it stops while the others go on: timeout.
            let mut rx = RxStore::new(2, 2, 2);
            for c in 0..4 {
                all_five(&mut rx, c, t + u64::from(c) * 20 * MS, to);
            }
            assert!(rx.state(t + 70 * MS, to).valid);
            for c in 4..20u8 {
                all_but(&mut rx, Some(skip), c % 15, t + u64::from(c) * 20 * MS, to);
            }
            let s = rx.state(t + 390 * MS, to);
            assert!(!s.valid);
            assert_eq!(s.reason.as_deref(), Some(&*format!("{name}: timeout")));
            assert!(s.age_ms.unwrap() > 250.0, "{s:?}");
        }
    }

    #[test]
    fn a_corrupt_or_implausible_accel_or_driver_demand_is_not_used() {
        use crate::codec::{DRIVER_DEMAND, VEHICLE_ACCEL};
        let to = 250 * MS;
        let t = 10_000 * MS;
        for (skip, m) in [(3, &VEHICLE_ACCEL), (4, &DRIVER_DEMAND)] {
            let mut rx = RxStore::new(2, 2, 2);
            for c in 0..3 {
                all_five(&mut rx, c, t + u64::from(c) * 20 * MS, to);
            }
            assert!(rx.state(t + 40 * MS, to).valid);
            let before = rx.state(t + 40 * MS, to);
            // Bad CRC on every frame from now on: rejected, then invalid by
            // the strikes in its window; the last good values stay.
            let other: &[f64] = if skip == 3 {
                &[1.0, 1.0]
            } else {
                &[1.0, 1.0, 1.0]
            };
            for c in 3..7u8 {
                let ts = t + u64::from(c) * 20 * MS;
                all_but(&mut rx, Some(skip), c, ts, to);
                let mut d = m.encode(other, c).unwrap().data().to_vec();
                d[0] ^= 0x01;
                rx.on_frame(&CanFrame::new(m.id, false, &d).unwrap(), ts, to);
            }
            let s = rx.state(t + 121 * MS, to);
            assert!(!s.valid);
            assert_eq!(
                s.reason.as_deref(),
                Some(&*format!("{}: wrong crc", m.name))
            );
            assert_eq!(rx.rx_crc_errors, 4);
            assert_eq!(
                (s.long_accel_mps2, s.driver_torque_nm, s.road_friction),
                (
                    before.long_accel_mps2,
                    before.driver_torque_nm,
                    before.road_friction
                )
            );
            // Implausible values (outside the DBC's [min|max]) are not used.
            let mut rx = RxStore::new(2, 2, 2);
            for c in 0..3 {
                all_five(&mut rx, c, t + u64::from(c) * 20 * MS, to);
            }
            let bad: &[f64] = if skip == 3 {
                &[25.0, 0.0]
            } else {
                &[0.0, 10.0, 0.02]
            };
            rx.on_frame(&m.encode(bad, 3).unwrap(), t + 60 * MS, to);
            assert_eq!(rx.rx_implausible, 1);
            let s = rx.state(t + 61 * MS, to);
            assert_eq!(s.status[skip], "implausible");
            assert!(s
                .reason
                .unwrap()
                .starts_with(&format!("{}: implausible", m.name)));
            assert!(rx.last_error.as_deref().unwrap().starts_with(m.name));
            assert!((s.long_accel_mps2.unwrap() + 3.21).abs() < 1e-9);
            assert!((s.road_friction.unwrap() - 0.35).abs() < 1e-9);
        }
    }
}
