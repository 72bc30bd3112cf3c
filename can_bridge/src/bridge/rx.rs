//! The receive loop and the received vehicle state. Each frame of a
//! received message goes through, in order: its length and E2E Profile 1
//! CRC and counter (`e2e::Receiver`); its pace (the time its counter steps
//! claim against the time that actually passed, [`RxSlotState::keeps_pace`]);
//! its values' DBC range, rate of change and, for the speeds,
//! wheel-against-vehicle consistency (`plausibility`); then the message's
//! AUTOSAR E2E state machine (`e2e::StateMachine`). A usable frame's values are believed only once
//! they have stood for `confirm_ns` with no sign of a second sender on the
//! identifier (a repeated counter with other data, a counter jump, a
//! restart): a frame an intruder slips in ahead of the real sender is
//! contradicted by the real sender's next frame, one cycle later at most,
//! and is thrown away unbelieved (`docs/bus-safety.md`).

use super::{lock, Shared};
use crate::candump::{Dir, LogSender};
use crate::codec::{N_RX, RX_MESSAGES};
use crate::e2e::{Check, Receiver, SmConfig, StateMachine};
use crate::frame::CanFrame;
use crate::plausibility::Plausibility;
use crate::scheduler::{monotonic_ns, realtime_ns};
use crate::transport::{RxItem, Source};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};

/// Receive thread poll timeout, ms (bounds stop latency).
const RX_POLL_MS: i32 = 20;

/// Usable frames kept per message while they wait to be believed.
const PENDING: usize = 16;

/// A sender's clock may run this fraction fast (1/50: 2 %) before its frames
/// come faster than their cycle; crystal and resonator clocks are within
/// 0.5 %.
const PACE_TOLERANCE_DIV: u64 = 50;

/// Indices into [`RX_MESSAGES`].
const MOTION: usize = 0;
const WHEELS: usize = 1;
const STEERING: usize = 2;

/// Everything the receive side is configured with.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RxConfig {
    /// Largest counter step still in sequence (AUTOSAR MaxDeltaCounter).
    pub max_delta: u8,
    /// In-sequence frames confirming a (re)anchored counter (SyncCounter).
    pub sync_frames: u8,
    /// The E2E state machine's window and thresholds.
    pub sm: SmConfig,
    /// A usable frame is believed once it has stood this long with no sign
    /// of a second sender, ns.
    pub confirm_ns: u64,
    /// A message without a believed frame this long is invalid, ns; a
    /// message silent this long restarts its counter and state machine.
    pub state_timeout_ns: u64,
    /// Rates of change and the wheel/vehicle speed check.
    pub plausibility: Plausibility,
    /// Wheels that brake only (their actuator's `max_nm` is 0), FL, FR, RL, RR.
    pub undriven: [bool; 4],
}

impl Default for RxConfig {
    /// The shipped `vehicle.toml`.
    fn default() -> Self {
        RxConfig {
            max_delta: 2,
            sync_frames: 2,
            sm: SmConfig::default(),
            confirm_ns: 25_000_000,
            state_timeout_ns: 250_000_000,
            plausibility: Plausibility::default(),
            undriven: [true, true, false, false],
        }
    }
}

/// The pace rule's state: the time the sender's counters claim.
#[derive(Debug, Clone, Copy)]
struct Pace {
    /// When the last frame in sequence was sent, by its counters: the
    /// claimed time of the one before plus its counter steps times the
    /// message's cycle, on the receiver's clock, ns (its arrival if it came
    /// faster than its cycle, or anchored the counter).
    claimed_ns: u64,
    /// That frame's arrival, ns.
    at_ns: u64,
    /// That frame's alive counter.
    counter: u8,
}

#[derive(Debug, Clone)]
struct RxSlotState {
    receiver: Receiver,
    sm: StateMachine,
    /// Last frame that passed length and CRC (for the restart after a gap).
    last_seen_ns: Option<u64>,
    /// Usable frames waiting to be believed: (arrival, values), oldest first.
    pending: VecDeque<(u64, [f64; 4])>,
    /// The last believed frame: (arrival, values).
    believed: Option<(u64, [f64; 4])>,
    /// The rate check's reference: the last usable, plausible frame
    /// (arrival, counter if known, values).
    reference: Option<(u64, Option<u8>, [f64; 4])>,
    /// The time the counters claim (`None` until a counter is anchored).
    pace: Option<Pace>,
}

impl RxSlotState {
    /// Believe the pending frames that have stood for `confirm`.
    fn promote(&mut self, now: u64, confirm: u64) {
        while let Some(&(t, v)) = self.pending.front() {
            if t.saturating_add(confirm) > now {
                break;
            }
            self.believed = Some((t, v));
            self.pending.pop_front();
        }
    }

    /// What is believed at `now` (without changing anything).
    fn believed_at(&self, now: u64, confirm: u64) -> Option<(u64, [f64; 4])> {
        self.pending
            .iter()
            .rev()
            .find(|(t, _)| t.saturating_add(confirm) <= now)
            .copied()
            .or(self.believed)
    }

    /// A sign of a second sender or a restart: nothing waiting is believed,
    /// and the rate check falls back to the last believed frame.
    fn discard_pending(&mut self) {
        self.pending.clear();
        self.reference = self.believed.map(|(t, v)| (t, None, v));
    }

    /// The pace rule: the time a frame's counter claims is bounded by the
    /// time that actually passed. Each frame in sequence (OK, OKSOMELOST,
    /// SYNC) claims its counter steps (modulo 15, at least one) times the
    /// message's `cycle` after the frame before; the claims add up on a
    /// clock that starts a cycle before the anchoring frame's arrival (it
    /// may have come late), never lags the
    /// last believed frame's arrival (a silence or a late frame widens
    /// nothing beyond the time that passed since), and gives back a lead
    /// over the arrival times at 2 % of the time that passes (a sender's
    /// clock may run that much fast). A frame whose claim lands more than
    /// one cycle after its own arrival came faster than its cycle: it is a
    /// fault, and the clock restarts at its arrival. So a frame's claim
    /// since the last believed frame is at most the time that passed since
    /// plus one cycle, however the counters step and however fast the
    /// frames come (a burst alternates faults and frames that claim from
    /// the last fault's arrival, whose rate check falls back to the last
    /// believed frame), and the rate check (the longer of the arrival gap
    /// and the counter steps times the cycle) allows no more change than
    /// that time does. Returns whether the frame kept pace, or else the
    /// counter steps it claimed and the time since the frame before, ns.
    fn keeps_pace(
        &mut self,
        check: Check,
        counter: u8,
        now: u64,
        cycle: u64,
    ) -> Result<(), (u64, u64)> {
        let fresh = Pace {
            claimed_ns: now,
            at_ns: now,
            counter,
        };
        match check {
            // The anchor itself may have come up to a cycle late (a receiver
            // busy when a stream starts): it claims to have been sent a cycle
            // before its arrival. No value is believed yet to bound by it.
            Check::Initial => {
                self.pace = Some(Pace {
                    claimed_ns: now.saturating_sub(cycle),
                    ..fresh
                });
                return Ok(());
            }
            Check::Ok | Check::OkSomeLost | Check::Sync | Check::WrongSequence => {}
            _ => return Ok(()),
        }
        let p = *self.pace.get_or_insert(fresh);
        let elapsed = now.saturating_sub(p.at_ns);
        // A jump re-anchors the counter: its steps tell nothing of the time,
        // so it claims none (and keeps any lead).
        let steps = if check == Check::WrongSequence {
            0
        } else {
            u64::from((counter + 15 - p.counter) % 15).max(1)
        };
        let believed = self.believed.map_or(0, |(t, _)| t);
        let claimed = p.claimed_ns.max(believed).saturating_add(steps * cycle);
        // a lead over the arrival (claimed - now, if any) gives back 2 % of
        // the time since the frame before
        let claimed = claimed
            .min(now)
            .max(claimed.saturating_sub(elapsed / PACE_TOLERANCE_DIV));
        if claimed > now.saturating_add(cycle) {
            // The clock restarts at this frame: it claims nothing, and
            // neither does an anchor that came late (a sender catching up,
            // a receiver that stalled on a stream's first frame) keep every
            // later frame of a sound sender early.
            self.pace = Some(fresh);
            return Err((steps, elapsed));
        }
        self.pace = Some(Pace {
            claimed_ns: claimed,
            at_ns: now,
            counter,
        });
        Ok(())
    }
}

/// Receive-side state and counters.
#[derive(Debug, Clone)]
pub struct RxStore {
    cfg: RxConfig,
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
    pub(super) rx_implausible_rate: u64,
    pub(super) rx_inconsistent: u64,
    pub(super) rx_faster_than_cycle: u64,
    pub(super) rx_discarded: u64,
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
    /// Empty state.
    pub fn new(cfg: RxConfig) -> Self {
        RxStore {
            cfg,
            slots: RX_MESSAGES
                .iter()
                .map(|m| RxSlotState {
                    receiver: Receiver::new(m.data_id, m.len, cfg.max_delta, cfg.sync_frames),
                    sm: StateMachine::new(cfg.sm),
                    last_seen_ns: None,
                    pending: VecDeque::with_capacity(PENDING),
                    believed: None,
                    reference: None,
                    pace: None,
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
            rx_implausible_rate: 0,
            rx_inconsistent: 0,
            rx_faster_than_cycle: 0,
            rx_discarded: 0,
            rx_length_errors: 0,
            rx_malformed: 0,
            rx_unknown_id: 0,
            rx_transport_errors: 0,
            bus_errors: 0,
            last_error: None,
        }
    }

    /// The latest usable values of message `m` no older than the state
    /// timeout (the other side of the wheel/vehicle speed check).
    fn fresh_reference(&self, m: usize, now: u64) -> Option<[f64; 4]> {
        let (t, _, v) = self.slots.get(m)?.reference?;
        (now.saturating_sub(t) <= self.cfg.state_timeout_ns).then_some(v)
    }

    /// Why `values` of message `m` are not physical, if they are not: the
    /// rate of change from the last accepted frame, or the wheel speeds
    /// against the vehicle speed. Returns (counter to bump, message).
    fn physical(
        &self,
        m: usize,
        values: &[f64; 4],
        counter: Option<u8>,
        now: u64,
    ) -> Option<(bool, String)> {
        let msg = RX_MESSAGES.get(m)?;
        let p = &self.cfg.plausibility;
        let slot = self.slots.get(m)?;
        // The bound holds however old the reference is: a gap (the sender, the
        // transport or this thread stalled past the state timeout) widens the
        // allowance by rate x gap, never lifts it; reason: a loaded receiver
        // once took a 12 -> 85 m/s jump after a 250 ms stall
        // (test_i4_a_speed_jumping_12_85_every_frame_is_never_believed).
        if let Some((t, c0, prev)) = slot.reference {
            let elapsed = now.saturating_sub(t);
            let steps = match (c0, counter) {
                (Some(a), Some(b)) => u64::from((b + 15 - a) % 15).max(1),
                _ => 1,
            };
            let dt = elapsed.max(steps * u64::from(msg.cycle_ms) * 1_000_000);
            if let Some((name, a, b)) = p.rate_violation(m, msg, &prev, values, dt as f64 / 1e9) {
                return Some((
                    true,
                    format!(
                        "{}: {name} {a} -> {b} in {} ms is faster than its rate limit",
                        msg.name,
                        dt / 1_000_000
                    ),
                ));
            }
        }
        let steer = self.fresh_reference(STEERING, now).map(|v| v[0]);
        let pair = match m {
            MOTION => self
                .fresh_reference(WHEELS, now)
                .map(|w| ([values[0], values[1], values[2]], w)),
            WHEELS => self
                .fresh_reference(MOTION, now)
                .map(|v| ([v[0], v[1], v[2]], *values)),
            _ => None,
        };
        let (motion, wheels) = pair?;
        let (i, v, bound) = p.wheel_violation(motion, &wheels, steer, self.cfg.undriven)?;
        Some((
            false,
            format!(
                "{}: wheel {} turns at {v:.2} m/s, faster than a brake-only wheel can at {:.2} m/s vehicle speed (bound {bound:.2})",
                msg.name,
                crate::safety::WHEELS.get(i).copied().unwrap_or("?"),
                motion[0]
            ),
        ))
    }

    /// Check, judge and (if usable and plausible) hold one received frame
    /// until it is believed.
    pub fn on_frame(&mut self, f: &CanFrame, now_ns: u64) -> Check {
        self.rx_frames += 1;
        let idx = RX_MESSAGES
            .iter()
            .position(|m| m.id == f.id() && !f.is_extended() && !f.is_remote());
        let Some((i, m)) = idx.and_then(|i| Some((i, RX_MESSAGES.get(i)?))) else {
            self.rx_unknown_id += 1;
            return Check::BadLength;
        };
        let (confirm, timeout) = (self.cfg.confirm_ns, self.cfg.state_timeout_ns);
        let mut verdict = {
            let Some(slot) = self.slots.get_mut(i) else {
                return Check::BadLength;
            };
            slot.promote(now_ns, confirm);
            // After a gap the counter is anchored afresh (INITIAL, then SYNC)
            // and the state machine starts from NODATA.
            if slot
                .last_seen_ns
                .is_none_or(|t| now_ns.saturating_sub(t) > timeout)
            {
                slot.receiver.resync();
                slot.sm.reset();
            }
            let v = slot.receiver.check(f.data());
            if !matches!(v, Check::BadLength | Check::BadCrc) {
                slot.last_seen_ns = Some(now_ns);
            }
            v
        };
        // The pace rule, on every frame whose counter the receiver took.
        let counter = crate::e2e::counter_of(f.data()).unwrap_or(0);
        let cycle = u64::from(m.cycle_ms) * 1_000_000;
        if let Some(slot) = self.slots.get_mut(i) {
            if let Err((steps, elapsed)) = slot.keeps_pace(verdict, counter, now_ns, cycle) {
                verdict = Check::FasterThanCycle;
                self.last_error = Some(format!(
                    "{}: counter step {steps} ({} ms) {:.1} ms after the frame before comes faster than its {} ms cycle",
                    m.name,
                    steps * u64::from(m.cycle_ms),
                    elapsed as f64 / 1e6,
                    m.cycle_ms
                ));
            }
        }
        let mut values = [0.0; 4];
        if verdict.usable() {
            m.decode_values(f.data(), &mut values);
            if let Some((name, v)) = m.implausible(&values[..m.signals.len() - 2]) {
                verdict = Check::Implausible;
                self.last_error = Some(format!("{}: {name} = {v} is implausible", m.name));
            } else if let Some((rate, why)) =
                self.physical(i, &values, crate::e2e::counter_of(f.data()), now_ns)
            {
                verdict = Check::Implausible;
                if rate {
                    self.rx_implausible_rate += 1;
                } else {
                    self.rx_inconsistent += 1;
                }
                self.last_error = Some(why);
            }
        }
        let Some(slot) = self.slots.get_mut(i) else {
            return verdict;
        };
        if matches!(
            verdict,
            Check::TwoSources | Check::WrongSequence | Check::Initial | Check::FasterThanCycle
        ) {
            self.rx_discarded += slot.pending.len() as u64;
            slot.discard_pending();
        }
        slot.sm.check(verdict);
        match verdict {
            Check::Ok | Check::OkSomeLost => {
                if slot.pending.len() >= PENDING {
                    slot.pending.pop_front();
                }
                slot.pending.push_back((now_ns, values));
                slot.reference = Some((now_ns, crate::e2e::counter_of(f.data()), values));
                if verdict == Check::OkSomeLost {
                    self.rx_lost_frames += 1;
                }
            }
            Check::Initial | Check::Sync => self.rx_sync += 1,
            Check::BadCrc => self.rx_crc_errors += 1,
            Check::BadLength => self.rx_length_errors += 1,
            Check::Implausible => self.rx_implausible += 1,
            Check::FasterThanCycle => self.rx_faster_than_cycle += 1,
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
    pub fn state(&self, now_ns: u64) -> VehicleState {
        let (confirm, timeout) = (self.cfg.confirm_ns, self.cfg.state_timeout_ns);
        let believed: Vec<Option<(u64, [f64; 4])>> = self
            .slots
            .iter()
            .map(|s| s.believed_at(now_ns, confirm))
            .collect();
        let mut status = ["no data"; N_RX];
        for ((st, slot), b) in status.iter_mut().zip(&self.slots).zip(&believed) {
            // A sender that keeps sending bad frames is reported by what is
            // wrong with them ("repeated", ...), not merely as a timeout.
            let fresh = slot
                .last_seen_ns
                .is_some_and(|t| now_ns.saturating_sub(t) <= timeout);
            *st = match (b, slot.sm.verdict()) {
                (_, Err(why)) if fresh || b.is_none() => why,
                // sound (the state machine says VALID), the first usable
                // frame still being confirmed
                (None, _) => "confirming",
                (Some((t, _)), _) if now_ns.saturating_sub(*t) > timeout => "timeout",
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
        let get = |i: usize| believed.get(i).copied().flatten();
        let (motion, wheels, steer, accel, driver) = (get(0), get(1), get(2), get(3), get(4));
        // The state is as old as its oldest message, and has no age until
        // every message has been believed once.
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
/// ([`RX_NAMES`]). Values are those of each message's last believed frame
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
                lock(&shared.rx).on_frame(&f, monotonic_ns());
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
mod pace_tests;

#[cfg(test)]
mod store_tests;

#[cfg(test)]
mod tests {
    use super::super::testutil::MS;
    use super::*;
    use crate::codec::{
        DRIVER_DEMAND, STEERING_STATE, VEHICLE_ACCEL, VEHICLE_MOTION, WHEEL_SPEEDS,
    };

    pub(super) const CYCLE: u64 = 20 * MS;
    pub(super) const T0: u64 = 10_000 * MS;

    /// Healthy values, physically consistent: 12.34 m/s, front wheels
    /// rolling at that speed (35.2 rad/s at R = 0.351 m), rear ones driving.
    pub(super) fn healthy(m: usize) -> Vec<f64> {
        match m {
            0 => vec![12.34, -0.5, 0.25],
            1 => vec![35.1, 35.2, 40.3, 40.4],
            2 => vec![0.1234],
            3 => vec![-3.21, 7.5],
            _ => vec![-1234.5, 17.25, 0.35],
        }
    }

    pub(super) fn frame_of(m: usize, values: &[f64], c: u8) -> CanFrame {
        let msg = [
            &VEHICLE_MOTION,
            &WHEEL_SPEEDS,
            &STEERING_STATE,
            &VEHICLE_ACCEL,
            &DRIVER_DEMAND,
        ][m];
        msg.encode(values, c).unwrap()
    }

    /// Feed one healthy frame of each received message but `skip`, counter `c`.
    fn all_but(rx: &mut RxStore, skip: Option<usize>, c: u8, t: u64) {
        for m in 0..N_RX {
            if Some(m) != skip {
                rx.on_frame(&frame_of(m, &healthy(m), c % 15), t);
            }
        }
    }

    /// Cycles `from..to` of healthy frames of every message, 20 ms apart.
    fn cycles(rx: &mut RxStore, from: u64, to: u64) {
        for k in from..to {
            all_but(rx, None, (k % 15) as u8, T0 + k * CYCLE);
        }
    }

    fn store() -> RxStore {
        RxStore::new(RxConfig::default())
    }

    #[test]
    fn a_sound_frame_is_believed_once_it_has_stood_for_the_confirmation_time() {
        let mut rx = store();
        let s = rx.state(T0);
        assert!(!s.valid && s.reason.unwrap().contains("VehicleMotion: no data"));
        cycles(&mut rx, 0, 2);
        assert_eq!(rx.state(T0 + CYCLE).status, ["sync"; N_RX]);
        cycles(&mut rx, 2, 3);
        // valid stream, nothing believed yet: the first usable frame is 25 ms away
        let t2 = T0 + 2 * CYCLE;
        assert_eq!(rx.state(t2 + MS).status, ["confirming"; N_RX]);
        assert!(!rx.state(t2 + 24 * MS).valid);
        let s = rx.state(t2 + 25 * MS);
        assert!(s.valid, "{s:?}");
        assert!((s.long_speed_mps.unwrap() - 12.34).abs() < 1e-9);
        assert!((s.wheel_speeds_radps.unwrap()[3] - 40.4).abs() < 1e-9);
        assert!((s.lat_accel_mps2.unwrap() - 7.5).abs() < 1e-9);
        assert!((s.road_friction.unwrap() - 0.35).abs() < 1e-9);
        assert_eq!(s.age_ms, Some(25.0));
    }

    #[test]
    fn what_is_wrong_is_reported_and_counted() {
        let mut rx = store();
        cycles(&mut rx, 0, 10);
        let t = T0 + 10 * CYCLE;
        assert!(rx.state(t).valid);
        // bad CRC: refused and counted, one error is tolerated
        let mut bad = frame_of(0, &[19.0, 0.0, 0.0], 10).data().to_vec();
        bad[0] ^= 1;
        rx.on_frame(&CanFrame::new(0x201, false, &bad).unwrap(), t);
        all_but(&mut rx, Some(0), 10, t);
        assert_eq!(rx.rx_crc_errors, 1);
        cycles(&mut rx, 11, 13);
        assert!(rx.state(T0 + 13 * CYCLE).valid);
        // a value outside the DBC's range: not used, counted
        rx.on_frame(&frame_of(0, &[150.0, 0.0, 0.0], 13), T0 + 13 * CYCLE);
        assert_eq!(rx.rx_implausible, 1);
        assert!((rx.state(T0 + 14 * CYCLE).long_speed_mps.unwrap() - 12.34).abs() < 1e-9);
        // wrong length, unknown identifier
        rx.on_frame(&CanFrame::new(0x203, false, &[0; 8]).unwrap(), t);
        rx.on_frame(&CanFrame::new(0x555, false, &[0; 8]).unwrap(), t);
        assert_eq!((rx.rx_length_errors, rx.rx_unknown_id), (1, 1));
        // silence: timeout; after the gap the stream restarts (INITIAL, SYNC)
        let late = T0 + 13 * CYCLE + 300 * MS;
        assert_eq!(rx.state(late).status[1], "timeout");
        let sync = rx.rx_sync;
        cycles(&mut rx, 40, 42);
        assert_eq!(rx.rx_sync, sync + 2 * N_RX as u64);
        assert!(!rx.state(T0 + 41 * CYCLE).valid);
        cycles(&mut rx, 42, 43);
        assert!(rx.state(T0 + 42 * CYCLE + 25 * MS).valid);
    }

    #[test]
    fn a_jump_after_a_stall_past_the_state_timeout_is_still_implausible() {
        // 300 ms of silence (past the 250 ms state timeout: the counter is anchored
        // afresh), then a stream at `speed`, every other message healthy
        let after_stall = |speed: f64| {
            let mut rx = store();
            cycles(&mut rx, 0, 10);
            assert!(rx.state(T0 + 10 * CYCLE).valid);
            let t1 = T0 + 9 * CYCLE + 300 * MS;
            for k in 0..6u64 {
                let (c, t) = (((10 + k) % 15) as u8, t1 + k * CYCLE);
                rx.on_frame(&frame_of(0, &[speed, -0.5, 0.25], c), t);
                all_but(&mut rx, Some(0), c, t);
            }
            let s = rx.state(t1 + 5 * CYCLE + 25 * MS);
            (rx.rx_implausible, s.valid, s.long_speed_mps)
        };
        // 12.34 -> 85 m/s within 0.4 s is faster than 20 m/s^2 whatever the gap
        // did to the counter's state: never believed
        let (implausible, _, v) = after_stall(85.0);
        assert!(implausible >= 1, "{implausible}");
        assert!(v.is_none_or(|v| v < 50.0), "{v:?}");
        // a change within rate x gap is physical after the same stall: believed
        let (implausible, valid, v) = after_stall(16.0);
        assert_eq!(implausible, 0);
        assert!(valid && (v.unwrap() - 16.0).abs() < 1e-9, "{valid} {v:?}");
    }

    #[test]
    fn a_missing_accel_or_driver_demand_makes_the_state_invalid() {
        for (skip, name) in [(3, "VehicleAccel"), (4, "DriverDemand")] {
            let mut rx = store();
            for k in 0..6u64 {
                all_but(&mut rx, Some(skip), k as u8, T0 + k * CYCLE);
            }
            let s = rx.state(T0 + 6 * CYCLE);
            assert_eq!(s.reason.as_deref(), Some(&*format!("{name}: no data")));
            assert_eq!(s.age_ms, None);
            let mut rx = store();
            cycles(&mut rx, 0, 6);
            assert!(rx.state(T0 + 6 * CYCLE).valid);
            for k in 6..25u64 {
                all_but(&mut rx, Some(skip), (k % 15) as u8, T0 + k * CYCLE);
            }
            let s = rx.state(T0 + 25 * CYCLE);
            assert_eq!(s.reason.as_deref(), Some(&*format!("{name}: timeout")));
            assert!(s.age_ms.unwrap() > 250.0, "{s:?}");
        }
    }

    #[test]
    fn a_corrupt_or_implausible_accel_or_driver_demand_is_not_used() {
        for skip in [3usize, 4] {
            let mut rx = store();
            cycles(&mut rx, 0, 6);
            let before = rx.state(T0 + 6 * CYCLE);
            assert!(before.valid);
            let other: Vec<f64> = healthy(skip).iter().map(|x| x + 1.0).collect();
            for k in 6..10u64 {
                let t = T0 + k * CYCLE;
                all_but(&mut rx, Some(skip), k as u8, t);
                let mut d = frame_of(skip, &other, k as u8).data().to_vec();
                d[0] ^= 0x01;
                rx.on_frame(&CanFrame::new(0x201 + skip as u32, false, &d).unwrap(), t);
            }
            let s = rx.state(T0 + 10 * CYCLE);
            assert!(!s.valid);
            assert!(s.reason.unwrap().contains("wrong crc"));
            assert_eq!(rx.rx_crc_errors, 4);
            assert_eq!(
                (s.long_accel_mps2, s.driver_torque_nm, s.road_friction),
                (
                    before.long_accel_mps2,
                    before.driver_torque_nm,
                    before.road_friction
                )
            );
            // beyond the DBC's [min|max]
            let mut rx = store();
            cycles(&mut rx, 0, 6);
            let bad: &[f64] = if skip == 3 {
                &[25.0, 0.0]
            } else {
                &[0.0, 10.0, 0.02]
            };
            rx.on_frame(&frame_of(skip, bad, 6), T0 + 6 * CYCLE);
            assert_eq!(rx.rx_implausible, 1);
            assert!(rx
                .last_error
                .as_deref()
                .unwrap()
                .starts_with(RX_NAMES[skip]));
            let s = rx.state(T0 + 6 * CYCLE + MS);
            assert!((s.long_accel_mps2.unwrap() + 3.21).abs() < 1e-9);
        }
    }

    /// A real sender at 12.34 m/s every 20 ms and an intruder on the same
    /// identifier with valid CRCs at 20 m/s: `intruder` lists (time after the
    /// real frame of cycle `k0`, counter) of its VehicleMotion frames. Returns
    /// the samples (every ms) that were valid at the intruder's speed, and
    /// whether the state is valid at the real speed at the end.
    fn intrude(intruder: &[(u64, u64)]) -> (usize, bool, RxStore) {
        let mut rx = store();
        let k0 = 20u64;
        let mut events: Vec<(u64, bool, u64)> =
            (0..k0 + 60).map(|k| (T0 + k * CYCLE, true, k)).collect();
        events.extend(
            intruder
                .iter()
                .map(|&(dt, c)| (T0 + k0 * CYCLE + dt, false, c)),
        );
        events.sort();
        let fake = [20.0, -0.5, 0.25];
        let mut believed = 0;
        let mut next = 0;
        let end = T0 + (k0 + 60) * CYCLE;
        for now in (T0..end).step_by(MS as usize) {
            while next < events.len() && events[next].0 <= now {
                let (t, real, c) = events[next];
                if real {
                    all_but(&mut rx, None, (c % 15) as u8, t);
                } else {
                    rx.on_frame(&frame_of(0, &fake, (c % 15) as u8), t);
                }
                next += 1;
            }
            let s = rx.state(now);
            if s.valid && s.long_speed_mps.is_some_and(|v| (v - 20.0).abs() < 0.5) {
                believed += 1;
            }
        }
        let s = rx.state(end);
        let recovered = s.valid && (s.long_speed_mps.unwrap() - 12.34).abs() < 1e-9;
        (believed, recovered, rx)
    }

    #[test]
    fn no_intruder_sample_is_ever_believed() {
        let k = 20u64;
        let patterns: Vec<(&str, Vec<(u64, u64)>)> = vec![
            // one frame a counter or two ahead of the real sender, 5 ms
            // before the real sender's next frame
            ("+1", vec![(15 * MS, k + 1)]),
            ("+2", vec![(15 * MS, k + 2)]),
            // three in sequence after a jump
            (
                "three after a jump",
                (0..3).map(|j| (12 * MS + j * MS, k + 7 + j)).collect(),
            ),
            // an interleaved second stream, its own counter two ahead
            (
                "interleaved",
                (0..30).map(|j| (j * CYCLE + 10 * MS, k + j + 2)).collect(),
            ),
            // a replayed stream with a constant counter offset
            (
                "replayed +1",
                (0..30).map(|j| (j * CYCLE + 10 * MS, k + j + 1)).collect(),
            ),
            // an intruder phase-locked just before the real sender, its
            // counter one ahead each time
            (
                "leading",
                (0..30).map(|j| (j * CYCLE + 19 * MS, k + j + 1)).collect(),
            ),
        ];
        for (name, p) in patterns {
            let (believed, recovered, rx) = intrude(&p);
            assert_eq!(believed, 0, "{name}: intruder samples believed");
            assert!(recovered, "{name}: the real sender is not valid again");
            assert!(
                rx.rx_discarded + rx.rx_wrong_sequence + rx.rx_two_sources > 0,
                "{name}"
            );
        }
    }

    #[test]
    fn two_sources_make_the_message_invalid_until_a_window_has_passed() {
        let mut rx = store();
        cycles(&mut rx, 0, 10);
        let t = T0 + 10 * CYCLE;
        // the same counter as the last frame, other data
        rx.on_frame(&frame_of(0, &[12.5, -0.5, 0.25], 9), t - 10 * MS);
        assert_eq!(rx.state(t - 9 * MS).status[0], "two sources");
        for k in 10..17 {
            cycles(&mut rx, k, k + 1);
            assert!(!rx.state(T0 + k * CYCLE + 25 * MS).valid, "cycle {k}");
        }
        cycles(&mut rx, 17, 18);
        assert!(rx.state(T0 + 17 * CYCLE + 25 * MS).valid);
    }

    #[test]
    fn one_bad_crc_in_eight_frames_keeps_the_state_valid() {
        // Issue 29 item 13.
        let mut rx = store();
        let mut valid = 0;
        for k in 0..200u64 {
            let t = T0 + k * CYCLE;
            if k % 8 == 7 {
                let mut d = frame_of(0, &healthy(0), (k % 15) as u8).data().to_vec();
                d[3] ^= 0x10;
                rx.on_frame(&CanFrame::new(0x201, false, &d).unwrap(), t);
                all_but(&mut rx, Some(0), (k % 15) as u8, t);
            } else {
                all_but(&mut rx, None, (k % 15) as u8, t);
            }
            if k >= 4 {
                valid += u32::from(rx.state(t + 10 * MS).valid);
            }
        }
        assert_eq!(valid, 196);
        assert_eq!(rx.rx_crc_errors, 25);
    }

    #[test]
    fn a_speed_jumping_faster_than_a_vehicle_can_is_implausible() {
        // Issue 29 item 4: 12 <-> 85 m/s every 20 ms, sound E2E.
        let mut rx = store();
        cycles(&mut rx, 0, 10);
        let mut believed_fast = 0;
        let mut valid_late = 0;
        for k in 10..60u64 {
            let t = T0 + k * CYCLE;
            let v = if k % 2 == 0 { 12.34 } else { 85.0 };
            rx.on_frame(&frame_of(0, &[v, -0.5, 0.25], (k % 15) as u8), t);
            all_but(&mut rx, Some(0), (k % 15) as u8, t);
            for dt in [MS, 10 * MS, 19 * MS] {
                let s = rx.state(t + dt);
                believed_fast += usize::from(s.valid && s.long_speed_mps.unwrap() > 50.0);
                valid_late += usize::from(k >= 13 && s.valid);
            }
        }
        assert_eq!((believed_fast, valid_late), (0, 0));
        assert_eq!(rx.rx_implausible_rate, 25);
        assert!(rx.last_error.unwrap().contains("LongSpeed 12.34 -> 85"));
        // a real acceleration at 8 m/s^2 is plausible
        let mut rx = store();
        for k in 0..50u64 {
            let t = T0 + k * CYCLE;
            let v = 10.0 + 0.16 * k as f64;
            rx.on_frame(&frame_of(0, &[v, -0.5, 0.25], (k % 15) as u8), t);
            let w = v / 0.351;
            rx.on_frame(&frame_of(1, &[w, w, w, w], (k % 15) as u8), t);
            for m in 2..N_RX {
                rx.on_frame(&frame_of(m, &healthy(m), (k % 15) as u8), t);
            }
        }
        assert_eq!(rx.rx_implausible, 0, "{:?}", rx.last_error);
        assert!(rx.state(T0 + 50 * CYCLE).valid);
    }

    #[test]
    fn front_wheels_faster_than_the_vehicle_are_inconsistent() {
        let mut rx = store();
        cycles(&mut rx, 0, 10);
        for k in 10..30u64 {
            let t = T0 + k * CYCLE;
            let c = (k % 15) as u8;
            rx.on_frame(&frame_of(0, &healthy(0), c), t);
            // 40 m/s on every wheel while the vehicle makes 12.34
            rx.on_frame(&frame_of(1, &[114.0; 4], c), t);
            for m in 2..N_RX {
                rx.on_frame(&frame_of(m, &healthy(m), c), t);
            }
        }
        let s = rx.state(T0 + 30 * CYCLE);
        assert!(!s.valid);
        assert_eq!(s.status[1], "implausible");
        assert_eq!(rx.rx_inconsistent, 20);
        assert!(rx.last_error.unwrap().contains("brake-only"));
        assert!((s.wheel_speeds_radps.unwrap()[0] - 35.1).abs() < 1e-9);
    }
}
