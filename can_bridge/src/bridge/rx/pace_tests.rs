//! The pace rule (`RxSlotState::keeps_pace`) on the injected clock: a burst
//! claims no more time than has passed since the last believed frame plus
//! one cycle, frames faster than their cycle are counted faults, and no
//! sound stream (on time, jittered, late, bunched by a stalled receiver, a
//! sender's clock a little fast) trips it.

use super::tests::{frame_of, healthy, CYCLE, T0};
use super::*;
use crate::bridge::testutil::MS;

const US: u64 = 1_000;

/// One frame to feed: (arrival, message, values, counter).
type Ev = (u64, usize, Vec<f64>, u64);

/// Every message but those in `skip`, healthy, each cycle `from..to`, counter `k`.
fn rest(from: u64, to: u64, skip: &[usize]) -> Vec<Ev> {
    (from..to)
        .flat_map(|k| {
            (0..N_RX)
                .filter(|m| !skip.contains(m))
                .map(move |m| (T0 + k * CYCLE, m, healthy(m), k))
        })
        .collect()
}

/// Feed `events` in time order and sample the state every half millisecond
/// from the first event to `end`: (time, state).
fn play(rx: &mut RxStore, mut events: Vec<Ev>, end: u64) -> Vec<(u64, VehicleState)> {
    events.sort_by_key(|e| e.0);
    let mut out = Vec::new();
    let mut next = 0;
    let mut now = events.first().map_or(end, |e| e.0);
    while now < end {
        while let Some((t, m, v, c)) = events.get(next) {
            if *t > now {
                break;
            }
            rx.on_frame(&frame_of(*m, v, (*c % 15) as u8), *t);
            next += 1;
        }
        out.push((now, rx.state(now)));
        now += 500 * US;
    }
    out
}

/// The speed of the healthy sender.
fn v0() -> f64 {
    healthy(0)[0]
}

/// The sender's VehicleMotion at `speed`.
fn motion(speed: f64) -> Vec<f64> {
    vec![speed, -0.5, 0.25]
}

/// Healthy VehicleMotion on cycles `from..to`, counter k (no speed change).
fn motion_cycles(from: u64, to: u64) -> Vec<Ev> {
    (from..to)
        .map(|k| (T0 + k * CYCLE, MOTION, motion(v0()), k))
        .collect()
}

/// The largest amount by which a believed speed moved from the healthy one
/// faster than 20 m/s^2 over the time since `t_ref` (the arrival of the last
/// frame believed before the disturbance), over every sample (valid or
/// not); 0 if never.
fn excess_over_rate(samples: &[(u64, VehicleState)], t_ref: u64) -> f64 {
    samples
        .iter()
        .filter_map(|(t, s)| {
            let v = s.long_speed_mps?;
            let allowed = 20.0 * t.saturating_sub(t_ref) as f64 / 1e9 + 0.05;
            Some((v - v0()).abs() - allowed)
        })
        .fold(0.0, f64::max)
}

#[test]
fn a_burst_of_90_frames_in_11_ms_from_12_to_85_is_never_believed() {
    // The reported case: ten healthy cycles, then one sender emits 90
    // VehicleMotion frames 0.122 ms apart, each counter +2 and speed +0.8 m/s
    // (12.34 -> 84.34 m/s), and goes on at 84.34 m/s every 20 ms. Before the
    // pace rule each frame claimed 40 ms and was within 20 m/s^2 of the last:
    // valid at > 80 m/s within 36 ms, rx_implausible_rate 0.
    let mut rx = RxStore::new(RxConfig::default());
    let t_burst = T0 + 9 * CYCLE + MS;
    let mut ev = rest(0, 70, &[MOTION]);
    ev.extend(motion_cycles(0, 10));
    let mut c = 9;
    let mut v = v0();
    for j in 0..90 {
        c += 2;
        v += 0.8;
        ev.push((t_burst + j * 122 * US, MOTION, motion(v), c));
    }
    for k in 10..70 {
        c += 1;
        ev.push((T0 + k * CYCLE + MS, MOTION, motion(v), c));
    }
    let s = play(&mut rx, ev, T0 + 70 * CYCLE);
    assert!(s.iter().any(|(t, st)| *t < t_burst && st.valid));
    let fast = s
        .iter()
        .filter(|(_, st)| st.long_speed_mps.is_some_and(|x| x > v0() + 0.5))
        .count();
    assert_eq!(fast, 0, "samples believing the burst's speed");
    let valid_after = s
        .iter()
        .filter(|(t, st)| *t > t_burst + 5 * MS && st.valid)
        .count();
    assert_eq!(valid_after, 0, "a bursting sender stays invalid");
    assert!(rx.rx_faster_than_cycle >= 85, "{}", rx.rx_faster_than_cycle);
    assert!(rx.rx_implausible_rate >= 50, "{}", rx.rx_implausible_rate);
    assert!(rx.last_error.as_deref().unwrap().contains("LongSpeed"));
    assert_eq!(s.last().unwrap().1.status[0], "implausible");
}

/// A burst of VehicleMotion frames: `n` frames `spacing` apart from
/// `t_start`, counter steps `step`, speed steps `dv`; before it healthy
/// cycles `0..last` (the last at T0 + (last - 1) cycles), after it the
/// sender goes on every 20 ms at the burst's last speed, in sequence.
fn burst_case(last: u64, t_start: u64, n: u64, spacing: u64, step: u64, dv: f64) -> RxStore {
    let mut rx = RxStore::new(RxConfig::default());
    let mut ev = rest(0, 60, &[MOTION]);
    ev.extend(motion_cycles(0, last));
    let mut c = last - 1;
    let mut v = v0();
    for j in 0..n {
        c += step;
        v += dv;
        ev.push((t_start + j * spacing, MOTION, motion(v), c));
    }
    let t_end = t_start + n * spacing;
    let mut k = 0;
    while t_end + k * CYCLE < T0 + 60 * CYCLE {
        k += 1;
        c += 1;
        ev.push((t_end + k * CYCLE, MOTION, motion(v), c));
    }
    // the last frame believed when the burst starts (the two after it are
    // still being confirmed)
    let t_ref = T0 + (last - 3) * CYCLE;
    let s = play(&mut rx, ev, T0 + 60 * CYCLE);
    let excess = excess_over_rate(&s, t_ref);
    assert!(
        excess <= 0.0,
        "a believed speed {excess:.2} m/s beyond 20 m/s^2 of real time"
    );
    rx
}

#[test]
fn no_burst_moves_a_believed_value_faster_than_real_time_allows() {
    // Variants the report did not name; each frame of each burst is within
    // the rate bound of the one before for the time its counter step claims.
    let t = T0 + 9 * CYCLE + MS;
    for (name, n, spacing, step, dv) in [
        ("counter +1, +0.35 m/s", 90, 122 * US, 1, 0.35),
        ("counter +2, +0.75 m/s", 90, 122 * US, 2, 0.75),
        ("counter +1, +0.1 m/s", 200, 50 * US, 1, 0.1),
        ("counter +2, 2 ms apart", 40, 2 * MS, 2, 0.7),
        ("counter +1, 10 ms apart", 60, 10 * MS, 1, 0.35),
        ("three frames", 3, 100 * US, 1, 0.35),
    ] {
        let rx = burst_case(10, t, n, spacing, step, dv);
        assert!(rx.rx_faster_than_cycle >= 1, "{name}: not counted");
    }
}

#[test]
fn a_burst_after_a_gap_claims_the_gap_and_no_more() {
    // VehicleMotion silent for 200 ms (below the 250 ms state timeout) after
    // its last believed frame, then frames 0.1 ms apart, counter +1, +0.35
    // m/s each: eleven claim 220 ms, the time that passed plus one cycle, and
    // keep pace; a twelfth does not. No believed speed ever moves faster than
    // 20 m/s^2 of real time.
    let t = T0 + 9 * CYCLE + 200 * MS;
    assert_eq!(
        burst_case(10, t, 11, 100 * US, 1, 0.35).rx_faster_than_cycle,
        0
    );
    assert!(burst_case(10, t, 12, 100 * US, 1, 0.35).rx_faster_than_cycle >= 1);
    // beyond it every other frame is a fault
    assert!(burst_case(10, t, 20, 100 * US, 1, 0.35).rx_faster_than_cycle >= 4);
}

#[test]
fn a_burst_on_the_wheel_speeds_is_never_believed() {
    // The rear wheels (driven: no bound from the vehicle speed) +150 rad/s a
    // frame, within 8000 rad/s^2 for a 20 ms counter step, 60 frames in 6 ms.
    let mut rx = RxStore::new(RxConfig::default());
    let mut ev = rest(0, 60, &[WHEELS]);
    let w0 = healthy(WHEELS);
    ev.extend((0..10).map(|k| (T0 + k * CYCLE, WHEELS, w0.clone(), k)));
    let mut c = 9;
    let mut w = w0.clone();
    let t_burst = T0 + 9 * CYCLE + MS;
    for j in 0..60 {
        c += 1;
        w[2] = (w[2] + 2.5).min(200.0);
        w[3] = (w[3] + 2.5).min(200.0);
        ev.push((t_burst + j * 100 * US, WHEELS, w.clone(), c));
    }
    // then back to the healthy speeds, in sequence
    for k in 10..60 {
        c += 1;
        ev.push((T0 + k * CYCLE + MS, WHEELS, w0.clone(), c));
    }
    let s = play(&mut rx, ev, T0 + 60 * CYCLE);
    let fastest = s
        .iter()
        .filter_map(|(_, st)| st.wheel_speeds_radps.map(|w| w[2]))
        .fold(0.0, f64::max);
    // no frame of the burst is believed, and the bursting message is
    // invalid until a window of sound frames has passed
    assert!(fastest <= w0[2] + 1e-9, "{fastest}");
    assert!(rx.rx_faster_than_cycle >= 29, "{}", rx.rx_faster_than_cycle);
    let invalid = |from: u64, to: u64| {
        s.iter()
            .filter(|(t, _)| (from..to).contains(t))
            .all(|(_, st)| !st.valid && st.status[1] != "ok")
    };
    assert!(invalid(t_burst + 200 * US, t_burst + 8 * CYCLE));
    assert!(s.last().unwrap().1.valid);
}

#[test]
fn a_burst_at_the_start_of_a_stream_is_invalid_until_a_window_of_sound_frames() {
    // Nothing believed yet, so no value to bound the burst's by: 60 frames
    // 0.1 ms apart, counter +1, then the sender goes on every 20 ms. Every
    // other frame of the burst is a fault: the message is invalid, and
    // valid again only once a window of 8 frames in pace has passed (the
    // burst's last one among them).
    let mut rx = RxStore::new(RxConfig::default());
    let mut ev = rest(0, 40, &[MOTION]);
    let v = |j: u64| v0() + 0.3 * j as f64;
    ev.extend((0..60).map(|j| (T0 + j * 100 * US, MOTION, motion(v(j)), j)));
    let t_end = T0 + 6 * MS;
    ev.extend((1..30).map(|k| (t_end + k * CYCLE, MOTION, motion(v(59)), 59 + k)));
    let s = play(&mut rx, ev, T0 + 40 * CYCLE);
    assert!(rx.rx_faster_than_cycle >= 29, "{}", rx.rx_faster_than_cycle);
    assert!(s
        .iter()
        .filter(|(t, _)| *t < t_end + 6 * CYCLE)
        .all(|(_, st)| !st.valid));
    assert!(s.last().unwrap().1.valid);
}

#[test]
fn a_claim_of_exactly_one_cycle_beyond_the_arrival_keeps_pace() {
    // A sound stream on time claims each frame's arrival; a frame two
    // counter steps on arriving with the last claims one cycle beyond its
    // arrival: still in pace. One more step at that instant is not.
    let mut rx = RxStore::new(RxConfig::default());
    for k in 0..6u64 {
        rx.on_frame(&frame_of(MOTION, &motion(v0()), k as u8), T0 + k * CYCLE);
    }
    let t = T0 + 5 * CYCLE;
    assert_eq!(
        rx.on_frame(&frame_of(MOTION, &motion(v0()), 7), t),
        Check::OkSomeLost
    );
    assert_eq!(
        rx.on_frame(&frame_of(MOTION, &motion(v0()), 8), t),
        Check::FasterThanCycle
    );
}

/// VehicleMotion every `period`, counter +1, `n` frames, healthy speed, the
/// other messages healthy at 20 ms: the faults counted.
fn paced(period: u64, n: u64) -> (u64, RxStore) {
    let mut rx = RxStore::new(RxConfig::default());
    let end = T0 + n * period;
    let cycles = (n * period).div_ceil(CYCLE) + 1;
    let mut ev = rest(0, cycles, &[MOTION]);
    ev.extend((0..n).map(|k| (T0 + k * period, MOTION, motion(v0()), k)));
    play(&mut rx, ev, end);
    (rx.rx_faster_than_cycle, rx)
}

#[test]
fn frames_at_their_cycle_keep_pace_and_faster_ones_are_counted_faults() {
    // exactly at the cycle, and a sender's clock 1.5 % fast: no fault
    assert_eq!(paced(CYCLE, 300).0, 0);
    assert_eq!(paced(19_700 * US, 300).0, 0);
    // slower than the cycle: no fault
    assert_eq!(paced(25 * MS, 200).0, 0);
    // 5 % fast: the lead grows by 0.6 ms a frame beyond what 2 % gives
    // back, a fault each time it passes a cycle (and the clock restarts)
    let (faults, rx) = paced(19 * MS, 300);
    assert!((6..=12).contains(&faults), "{faults}");
    assert!(rx
        .last_error
        .unwrap()
        .contains("faster than its 20 ms cycle"));
    // twice the rate: every third frame is a fault, and the message invalid
    let (faults, rx) = paced(10 * MS, 200);
    assert!(faults >= 60, "{faults}");
    assert!(!rx.state(T0 + 2000 * MS).valid);
}

#[test]
fn sound_streams_never_trip_the_pace_rule() {
    let check = |name: &str, times: Vec<u64>| {
        let mut rx = RxStore::new(RxConfig::default());
        let end = *times.last().unwrap() + 100 * MS;
        let cycles = (end - T0) / CYCLE + 1;
        let mut ev = rest(0, cycles, &[MOTION]);
        ev.extend(
            times
                .iter()
                .enumerate()
                .map(|(k, t)| (*t, MOTION, motion(v0()), k as u64)),
        );
        let s = play(&mut rx, ev, end);
        assert_eq!(rx.rx_faster_than_cycle, 0, "{name}: {:?}", rx.last_error);
        assert!(s.last().unwrap().1.valid, "{name}");
    };
    let on_time: Vec<u64> = (0..100).map(|k| T0 + k * CYCLE).collect();
    // each frame up to 9 ms late, by a fixed pseudo-random pattern
    let jittered = on_time
        .iter()
        .enumerate()
        .map(|(k, t)| t + (k as u64 * 7919 % 10) * MS)
        .collect();
    check("jittered", jittered);
    // the receiver stalls 120 ms: six frames arrive together, then on time
    let stalled = on_time
        .iter()
        .map(|&t| {
            let (a, b) = (T0 + 30 * CYCLE, T0 + 30 * CYCLE + 120 * MS);
            if t > a && t <= b {
                b + (t - a) / CYCLE * 20 * US
            } else {
                t
            }
        })
        .collect();
    check("a stalled receiver", stalled);
    // the sender is 35 ms late once and catches up
    let late = on_time
        .iter()
        .enumerate()
        .map(|(k, &t)| if k == 40 { t + 35 * MS } else { t })
        .collect::<Vec<_>>();
    let late = late
        .iter()
        .enumerate()
        .map(|(k, &t)| if k == 41 { late[40] + 100 * US } else { t })
        .collect();
    check("late and catching up", late);
    // the stream's first frames handled late, together (a sender catching
    // up, or a receiver busy when the stream starts): up to two cycles late
    // the anchor costs nothing; later, the first frame on time is early
    // against it, one fault, and the clock restarts there
    let late_start = |late: u64| {
        let mut rx = RxStore::new(RxConfig::default());
        let mut ev = rest(0, 30, &[MOTION]);
        ev.extend((0..30u64).map(|k| {
            let t = (T0 + k * CYCLE).max(T0 + late + k * 100 * US);
            (t, MOTION, motion(v0()), k)
        }));
        let s = play(&mut rx, ev, T0 + 30 * CYCLE);
        assert!(s.last().unwrap().1.valid, "{late}");
        rx.rx_faster_than_cycle
    };
    assert_eq!(late_start(30 * MS), 0);
    assert_eq!(late_start(39 * MS), 0);
    assert_eq!(late_start(70 * MS), 1);
    // one frame lost (a counter step of 2 after 40 ms), the next 15 ms late
    let mut rx = RxStore::new(RxConfig::default());
    let mut ev = rest(0, 110, &[MOTION]);
    ev.extend((0..100u64).filter(|k| *k != 50).map(|k| {
        let late = if k == 51 { 15 * MS } else { 0 };
        (T0 + k * CYCLE + late, MOTION, motion(v0()), k)
    }));
    let s = play(&mut rx, ev, T0 + 105 * CYCLE);
    assert_eq!(rx.rx_faster_than_cycle, 0, "{:?}", rx.last_error);
    assert!(s.last().unwrap().1.valid);
}
