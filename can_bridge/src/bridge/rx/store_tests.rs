//! The received state's bookkeeping, on the injected clock: every kind of
//! frame counted once in its own stat, the state timeout and the
//! confirmation time at their exact edges, what a frame that is not the
//! message's (extended, remote, broken) may not do, the wheel check in both
//! directions, and the receive loop over a scripted transport.

use super::tests::{frame_of, healthy, CYCLE, T0};
use super::*;
use crate::bridge::testutil::MS;
use crate::error::Error;
use std::sync::Arc;

/// Feeds frames and counts them.
struct Feed {
    rx: RxStore,
    n: u64,
}

impl Feed {
    fn new() -> Self {
        Feed {
            rx: RxStore::new(RxConfig::default()),
            n: 0,
        }
    }

    fn raw(&mut self, f: &CanFrame, t: u64) -> Check {
        self.n += 1;
        self.rx.on_frame(f, t)
    }

    /// Message `m` with `values`, counter `c`, at cycle `k` plus `dt`.
    fn at(&mut self, m: usize, values: &[f64], c: u8, k: u64, dt: u64) -> Check {
        self.raw(&frame_of(m, values, c), T0 + k * CYCLE + dt)
    }

    fn motion(&mut self, speed: f64, c: u8, k: u64, dt: u64) -> Check {
        self.at(MOTION, &[speed, -0.5, 0.25], c, k, dt)
    }
}

#[test]
fn every_kind_of_frame_is_counted_once_in_its_own_stat() {
    let v = healthy(0)[0];
    let mut f = Feed::new();
    assert_eq!(f.motion(v, 0, 0, 0), Check::Initial);
    assert_eq!(f.motion(v, 1, 1, 0), Check::Sync);
    assert_eq!(f.motion(v, 2, 2, 0), Check::Ok);
    // one lost (counter 3), the next two steps on
    assert_eq!(f.motion(v, 4, 4, 0), Check::OkSomeLost);
    // a frozen frame, then one lost again
    assert_eq!(f.motion(v, 4, 5, 0), Check::Repeated);
    assert_eq!(f.motion(v, 6, 6, 0), Check::OkSomeLost);
    // the same counter with other data, 5 ms later: the frame of cycle 6,
    // still being confirmed, is thrown away unbelieved
    assert_eq!(f.motion(v + 0.01, 6, 6, 5 * MS), Check::TwoSources);
    assert_eq!(f.rx.rx_discarded, 1);
    assert_eq!(f.motion(v, 7, 7, 0), Check::Ok);
    // a jump: cycle 7's frame, still being confirmed, goes too
    assert_eq!(f.motion(v, 12, 8, 0), Check::WrongSequence);
    assert_eq!(f.rx.rx_discarded, 2);
    assert_eq!(f.motion(v, 13, 9, 0), Check::Sync);
    assert_eq!(f.motion(v, 14, 10, 0), Check::Ok);
    // broken frames: CRC, length, counter 15
    let mut bad = frame_of(0, &healthy(0), 0).data().to_vec();
    bad[4] ^= 0x20;
    let crc = CanFrame::new(0x201, false, &bad).unwrap();
    assert_eq!(f.raw(&crc, T0 + 11 * CYCLE), Check::BadCrc);
    let short = CanFrame::new(0x201, false, &bad[..7]).unwrap();
    assert_eq!(f.raw(&short, T0 + 11 * CYCLE + MS), Check::BadLength);
    let mut c15 = frame_of(0, &healthy(0), 0).data().to_vec();
    c15[1] |= 0x0F;
    c15[0] = crate::e2e::p01_crc(RX_MESSAGES[0].data_id, &c15);
    let c15 = CanFrame::new(0x201, false, &c15).unwrap();
    assert_eq!(f.raw(&c15, T0 + 11 * CYCLE + 2 * MS), Check::InvalidCounter);
    // beyond the DBC's range, then faster than the rate limit
    assert_eq!(f.motion(150.0, 0, 11, 3 * MS), Check::Implausible);
    assert_eq!(f.motion(20.0, 1, 12, 0), Check::Implausible);
    // the front wheels at 40 m/s against 12.34 m/s
    assert_eq!(f.at(WHEELS, &[114.0; 4], 0, 12, 0), Check::Initial);
    assert_eq!(f.at(WHEELS, &[114.0; 4], 1, 13, 0), Check::Sync);
    assert_eq!(f.at(WHEELS, &[114.0; 4], 2, 14, 0), Check::Implausible);
    // not the message: another identifier, an extended or a remote frame
    // with its identifier
    let other = CanFrame::new(0x555, false, &[0; 8]).unwrap();
    let extended = CanFrame::new(0x201, true, frame_of(0, &healthy(0), 2).data()).unwrap();
    let remote = CanFrame::remote(0x201, false, 8).unwrap();
    for frame in [&other, &extended, &remote] {
        f.raw(frame, T0 + 14 * CYCLE + MS);
    }
    let rx = &f.rx;
    assert_eq!(rx.rx_frames, f.n);
    assert_eq!(rx.rx_sync, 5);
    assert_eq!(rx.rx_lost_frames, 2);
    assert_eq!(rx.rx_repeated, 1);
    assert_eq!(rx.rx_two_sources, 1);
    assert_eq!(rx.rx_wrong_sequence, 1);
    assert_eq!(rx.rx_counter_errors, 4);
    assert_eq!(rx.rx_crc_errors, 1);
    assert_eq!(rx.rx_length_errors, 1);
    assert_eq!(rx.rx_implausible, 3);
    assert_eq!(rx.rx_implausible_rate, 1);
    assert_eq!(rx.rx_inconsistent, 1);
    assert_eq!(rx.rx_unknown_id, 3);
    assert_eq!(rx.rx_faster_than_cycle, 0);
    // and frames faster than their cycle: a millisecond apart
    let fast = (2..6u8)
        .filter(|&c| f.motion(v, c, 12, u64::from(c) * MS) == Check::FasterThanCycle)
        .count() as u64;
    assert!(fast >= 1);
    assert_eq!(f.rx.rx_faster_than_cycle, fast);
    assert_eq!(f.rx.rx_frames, f.n);
}

#[test]
fn every_payload_signal_is_held_to_its_dbc_range_the_last_one_too() {
    // one signal at a time beyond its range, the others sound
    for (m, i, bad) in [
        (MOTION, 0, 95.0),
        (MOTION, 2, 3.5),
        (WHEELS, 0, -70.0),
        (WHEELS, 3, -70.0),
        (STEERING, 0, 1.2),
        (3, 1, 25.0),
        (4, 2, 2.3),
    ] {
        let mut f = Feed::new();
        for k in 0..3u64 {
            f.at(m, &healthy(m), k as u8, k, 0);
        }
        let mut v = healthy(m);
        v[i] = bad;
        assert_eq!(f.at(m, &v, 3, 3, 0), Check::Implausible, "{m} {i}");
        let e = f.rx.last_error.clone().unwrap();
        assert!(e.ends_with("is implausible"), "{e}");
    }
}

#[test]
fn the_errors_name_what_was_wrong_and_by_how_much() {
    let mut f = Feed::new();
    for k in 0..3 {
        f.motion(12.34, k as u8, k, 0);
    }
    f.motion(20.0, 3, 3, 0);
    let e = f.rx.last_error.clone().unwrap();
    assert!(
        e.contains("VehicleMotion: LongSpeed 12.34 -> 20 in 20 ms"),
        "{e}"
    );
    // against the last plausible frame, two counter steps and cycles back
    f.motion(13.5, 4, 4, 0);
    let e = f.rx.last_error.clone().unwrap();
    assert!(e.contains("12.34 -> 13.5 in 40 ms"), "{e}");
    // frames a millisecond apart: the first that claims too much says so
    let c = (5..10u8)
        .find(|&c| f.motion(12.34, c, 4, u64::from(c - 4) * MS) == Check::FasterThanCycle)
        .unwrap();
    let e = f.rx.last_error.clone().unwrap();
    assert!(
        e.contains("VehicleMotion: counter step 1 (20 ms) 1.0 ms after the frame before comes faster than its 20 ms cycle"),
        "{c}: {e}"
    );
}

#[test]
fn the_rate_allows_the_time_the_counter_steps_claim() {
    // A frame two counter steps on (one lost), arriving a cycle after the
    // last: it may change by two cycles' worth (0.8 m/s at 20 m/s^2), not
    // more; a frame one step on a cycle later by one cycle's worth.
    let step = |c_next: u8, dv: f64| {
        let mut f = Feed::new();
        for k in 0..4 {
            f.motion(12.34, k as u8, k, 0);
        }
        f.motion(12.34 + dv, c_next, 4, 0)
    };
    assert_eq!(step(5, 0.75), Check::OkSomeLost);
    assert_eq!(step(5, 0.85), Check::Implausible);
    assert_eq!(step(4, 0.38), Check::Ok);
    assert_eq!(step(4, 0.45), Check::Implausible);
}

/// Healthy cycles `0..n` of every message; the last at T0 + (n - 1) cycles.
fn healthy_cycles(f: &mut Feed, n: u64) {
    for k in 0..n {
        for m in 0..N_RX {
            f.at(m, &healthy(m), (k % 15) as u8, k, 0);
        }
    }
}

#[test]
fn the_state_timeout_holds_to_the_nanosecond() {
    let timeout = RxConfig::default().state_timeout_ns;
    // a silence of exactly the state timeout keeps the stream; a
    // nanosecond more restarts it (the frame anchors the counter afresh)
    let after = |silence: u64| {
        let mut f = Feed::new();
        healthy_cycles(&mut f, 5);
        let t = T0 + 4 * CYCLE + silence;
        f.raw(&frame_of(0, &healthy(0), 5), t)
    };
    assert_eq!(after(timeout), Check::Ok);
    assert_eq!(after(timeout + 1), Check::Initial);
    // a believed frame exactly the state timeout old is valid, a
    // nanosecond older times out
    let mut f = Feed::new();
    healthy_cycles(&mut f, 5);
    let last = T0 + 4 * CYCLE;
    assert!(f.rx.state(last + timeout).valid);
    let s = f.rx.state(last + timeout + 1);
    assert!(!s.valid);
    assert_eq!(s.status, ["timeout"; N_RX]);
}

#[test]
fn frames_with_a_broken_crc_do_not_keep_a_silent_stream_alive() {
    // Only broken frames for longer than the state timeout: the next sound
    // frame restarts the stream, and the state says what was wrong.
    let mut f = Feed::new();
    healthy_cycles(&mut f, 5);
    let mut bad = frame_of(0, &healthy(0), 5).data().to_vec();
    bad[3] ^= 0x01;
    let bad = CanFrame::new(0x201, false, &bad).unwrap();
    for k in 5..20 {
        f.raw(&bad, T0 + k * CYCLE);
        for m in 1..N_RX {
            f.at(m, &healthy(m), (k % 15) as u8, k, 0);
        }
    }
    let s = f.rx.state(T0 + 19 * CYCLE);
    assert_eq!(s.status[0], "timeout");
    assert_eq!(f.motion(12.34, 5, 20, 0), Check::Initial);
}

#[test]
fn a_frame_that_has_stood_the_confirmation_time_survives_a_discard_at_that_instant() {
    // Believed once it has stood exactly rx_confirm_ms: a second source
    // arriving at that very instant discards only what came after it.
    let confirm = RxConfig::default().confirm_ns;
    let mut f = Feed::new();
    healthy_cycles(&mut f, 5);
    f.motion(12.5, 5, 5, 0);
    let t = T0 + 5 * CYCLE + confirm;
    f.raw(&frame_of(0, &[12.6, -0.5, 0.25], 5), t);
    assert_eq!(f.rx.rx_two_sources, 1);
    assert_eq!(f.rx.rx_discarded, 0);
    assert_eq!(f.rx.state(t).long_speed_mps, Some(12.5));
}

#[test]
fn a_vehicle_speed_below_what_the_front_wheels_show_is_inconsistent() {
    // The check runs on a VehicleMotion frame against fresh wheel speeds
    // too, not only the other way round; wheel speeds a state timeout old
    // still count, a nanosecond older not.
    let timeout = RxConfig::default().state_timeout_ns;
    let check_at = |age: u64| {
        let mut f = Feed::new();
        let w = healthy(WHEELS);
        for k in 0..3u64 {
            f.at(WHEELS, &w, k as u8, k, 0);
        }
        // the vehicle speed's stream, its usable frame `age` after the
        // last wheel speeds: 5 m/s against front wheels at 12.34 m/s
        let t = T0 + 2 * CYCLE + age;
        for (j, c) in [(2u64, 0u8), (1, 1), (0, 2)] {
            f.raw(&frame_of(0, &[5.0, 0.0, 0.0], c), t - j * CYCLE);
        }
        (f.rx.rx_inconsistent, f.rx.last_error)
    };
    let (n, e) = check_at(timeout);
    assert_eq!(n, 1);
    assert!(e.unwrap().starts_with("VehicleMotion: wheel FL"));
    assert_eq!(check_at(timeout + 1).0, 0);
}

/// A transport that hands over `items` one per call, then asks the loop
/// to stop.
struct Script {
    items: Vec<crate::error::Result<Option<RxItem>>>,
    stop: Arc<AtomicBool>,
}

impl Source for Script {
    fn recv(&mut self, _timeout_ms: i32) -> crate::error::Result<Option<RxItem>> {
        if self.items.is_empty() {
            self.stop.store(true, Ordering::Release);
            return Ok(None);
        }
        self.items.remove(0)
    }
}

#[test]
fn the_receive_loop_counts_what_the_transport_hands_over_and_stops() {
    let shared = Shared::new(&crate::bridge::BridgeConfig::new("slcan-pty:"));
    let stop = Arc::new(AtomicBool::new(false));
    let mut src = Script {
        items: vec![
            Ok(Some(RxItem::Frame(frame_of(2, &healthy(2), 0)))),
            Ok(None),
            Ok(Some(RxItem::Malformed)),
            Ok(Some(RxItem::Malformed)),
            Ok(Some(RxItem::BusError)),
            Err(Error::Transport("the adapter went away".into())),
            Ok(Some(RxItem::Frame(frame_of(2, &healthy(2), 1)))),
        ],
        stop: stop.clone(),
    };
    run_rx(&shared, &mut src, &stop, None);
    let rx = lock(&shared.rx);
    assert_eq!(rx.rx_frames, 2);
    assert_eq!(rx.rx_sync, 2);
    assert_eq!(rx.rx_malformed, 2);
    assert_eq!(rx.bus_errors, 1);
    assert_eq!(rx.rx_transport_errors, 1);
    assert_eq!(
        rx.last_error.as_deref(),
        Some("transport error: the adapter went away")
    );
    // nothing is read once asked to stop
    drop(rx);
    let mut src = Script {
        items: vec![Ok(Some(RxItem::Malformed))],
        stop: stop.clone(),
    };
    run_rx(&shared, &mut src, &stop, None);
    assert_eq!(lock(&shared.rx).rx_malformed, 2);
}
