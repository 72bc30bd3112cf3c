//! A long randomised run of the receive side (`RxStore`): five healthy
//! sensors at 20 ms, with faults injected at random rates in random
//! segments: frames lost, repeated (frozen), bad CRC, wrong length, counter
//! 15, an intruder's out-of-sequence pair, a second source repeating the last
//! counter with other data, implausible values, gaps longer than the state
//! timeout. Checked on every input:
//!
//! * nothing panics;
//! * a reported value is always one a healthy sensor sent (healthy values
//!   walk within [0, 40) at physical rates; every faulty frame carries a
//!   value in [60, 89]);
//! * the state is never valid while a message's last second source (the same
//!   counter with other data) is less than a window of frames ago, unless
//!   the message went silent and restarted since;
//! * the healthy stretches are valid.
//!
//! `cargo test` runs 30,000 inputs; the long run (10^6 by default, or
//! `CAN_BRIDGE_RX_INPUTS`) is `cargo test --release -- --ignored long_randomised`.

use can_bridge::bridge::{RxConfig, RxStore};
use can_bridge::codec::{
    DRIVER_DEMAND, N_RX, RX_MESSAGES, STEERING_STATE, VEHICLE_ACCEL, VEHICLE_MOTION, WHEEL_SPEEDS,
};
use can_bridge::e2e::Check;
use can_bridge::CanFrame;

const MS: u64 = 1_000_000;

struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
    fn unit(&mut self) -> f64 {
        (self.next() >> 11) as f64 / (1u64 << 53) as f64
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
}

/// Each message carries `value` in one signal, scaled so that healthy and
/// faulty values both lie within the signal's plausibility bounds (only the
/// implausible fault leaves them); [`reported`] undoes the scaling.
fn frame(msg: usize, value: f64, counter: u8) -> CanFrame {
    match msg {
        0 => VEHICLE_MOTION.encode(&[value, 0.5, 0.1], counter),
        1 => WHEEL_SPEEDS.encode(&[value; 4], counter),
        2 => STEERING_STATE.encode(&[value / 100.0], counter),
        3 => VEHICLE_ACCEL.encode(&[value / 5.0, -1.0], counter),
        _ => DRIVER_DEMAND.encode(&[value * 50.0, 20.0, 0.8], counter),
    }
    .unwrap()
}

fn reported(st: &can_bridge::VehicleState) -> [Option<f64>; N_RX] {
    [
        st.long_speed_mps,
        st.wheel_speeds_radps.map(|w| w[0]),
        st.steering_angle_rad.map(|s| s * 100.0),
        st.long_accel_mps2.map(|a| a * 5.0),
        st.driver_torque_nm.map(|t| t / 50.0),
    ]
}

/// Returns (inputs, valid samples) for a reproducible seed.
fn run(inputs: u64, seed: u64) -> (u64, u64) {
    let timeout = 250 * MS;
    // The wheel/vehicle speed check is off here (the messages carry
    // independent values); rates and everything else are the defaults.
    let mut cfg = RxConfig::default();
    cfg.plausibility.tolerance_mps = 20.0;
    cfg.plausibility.tolerance_rel = 1.0;
    let window = u64::from(cfg.sm.min_ok_invalid);
    let mut rx = RxStore::new(cfg);
    // Per message: frames fed since its last second source, and when a frame
    // with a sound CRC last arrived (a longer silence restarts it).
    let mut since_two = [u64::MAX; N_RX];
    let mut seen_at = [0u64; N_RX];
    let mut walk = [20.0f64; N_RX];
    let mut rng = Rng(seed | 1);
    let mut now = 1_000 * MS;
    let mut counter = [0u8; N_RX];
    // The counter the receiver last anchored or accepted (what a fault must
    // be out of sequence with, or equal to, to be a fault at all).
    let mut sent = [0u8; N_RX];
    let mut last_good = [f64::NAN; N_RX];
    let mut fault_rate = 0.0;
    let mut n = 0u64;
    let mut valid = 0u64;
    while n < inputs {
        if rng.below(500) == 0 {
            fault_rate = [0.0, 0.02, 0.1, 0.5, 0.9][rng.below(5) as usize];
        }
        if rng.below(3000) == 0 {
            now += 300 * MS; // a gap longer than the state timeout
        }
        now += 20 * MS / N_RX as u64;
        let m = rng.below(N_RX as u64) as usize;
        // a random walk of 0.1 a frame: within every signal's rate
        walk[m] = (walk[m] + [-0.1, 0.0, 0.1][rng.below(3) as usize]).clamp(0.0, 39.9);
        let good_value = (walk[m] * 10.0).round() / 10.0;
        if now.saturating_sub(seen_at[m]) > timeout {
            since_two[m] = u64::MAX;
        }
        let bad_value = 60.0 + (rng.unit() * 29.0).round();
        let mut feed = |rx: &mut RxStore, f: &CanFrame| {
            let c = rx.on_frame(f, now);
            if !matches!(c, Check::BadCrc | Check::BadLength) {
                seen_at[m] = now;
            }
            since_two[m] = if c == Check::TwoSources {
                0
            } else {
                since_two[m].saturating_add(1)
            };
            n += 1;
        };
        if rng.unit() >= fault_rate {
            counter[m] = (counter[m] + 1) % 15;
            feed(&mut rx, &frame(m, good_value, counter[m]));
            sent[m] = counter[m];
            last_good[m] = good_value;
        } else {
            let kind = rng.below(8);
            match kind {
                0 => counter[m] = (counter[m] + 1) % 15, // lost: nothing arrives
                1 => feed(&mut rx, &frame(m, last_good[m].max(0.0), sent[m])), // repeat
                2 => {
                    let mut d = frame(m, bad_value, (counter[m] + 1) % 15).data().to_vec();
                    d[2] ^= 0x5A;
                    feed(
                        &mut rx,
                        &CanFrame::new(0x201 + m as u32, false, &d).unwrap(),
                    );
                }
                3 => feed(
                    &mut rx,
                    &CanFrame::new(0x201 + m as u32, false, &[0; 3]).unwrap(),
                ),
                4 => {
                    let mut d = frame(m, bad_value, 0).data().to_vec();
                    d[1] |= 0x0F;
                    d[0] = can_bridge::e2e::p01_crc(RX_MESSAGES[m].data_id, &d);
                    feed(
                        &mut rx,
                        &CanFrame::new(0x201 + m as u32, false, &d).unwrap(),
                    );
                }
                5 => {
                    // an intruder's pair, out of sequence (jump of 3..=12)
                    let c = (sent[m] + 3 + rng.below(10) as u8) % 15;
                    feed(&mut rx, &frame(m, bad_value, c));
                    feed(&mut rx, &frame(m, bad_value, (c + 1) % 15));
                    sent[m] = (c + 1) % 15;
                }
                6 => feed(&mut rx, &frame(m, bad_value, sent[m])), // second source
                _ => {
                    // implausible: beyond the DBC's bounds (wheel speed < -60 etc.)
                    counter[m] = (counter[m] + 1) % 15;
                    let v = [120.0, -100.0, -150.0, 120.0, -200.0][m];
                    feed(&mut rx, &frame(m, v, counter[m]));
                    sent[m] = counter[m];
                }
            }
        }
        let st = rx.state(now);
        for (i, v) in reported(&st).iter().enumerate() {
            if let Some(v) = v {
                assert!(
                    (0.0..40.0 + 1e-6).contains(v),
                    "input {n}: message {i} reports {v}, a value only faulty frames carry"
                );
            }
        }
        if st.valid {
            valid += 1;
            assert!(
                since_two.iter().all(|k| *k >= window),
                "input {n}: valid within a window of a second source: {since_two:?} {st:?}"
            );
        }
    }
    (n, valid)
}

#[test]
fn randomised_receive_run() {
    let (n, valid) = run(30_000, 0x5EED);
    assert!(n >= 30_000);
    assert!(
        valid > 1_000,
        "the healthy stretches must be valid ({valid})"
    );
}

#[test]
#[ignore = "long run: cargo test --release -- --ignored long_randomised"]
fn long_randomised_receive_run() {
    let inputs = std::env::var("CAN_BRIDGE_RX_INPUTS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(1_000_000);
    let t0 = std::time::Instant::now();
    let mut total = 0;
    let mut valid = 0;
    for seed in 1..=4u64 {
        let (n, v) = run(inputs / 4, seed * 0x9E37_79B9);
        total += n;
        valid += v;
    }
    println!(
        "{total} receive inputs, {valid} valid samples, {:.1} s",
        t0.elapsed().as_secs_f64()
    );
    assert!(total >= inputs);
}
