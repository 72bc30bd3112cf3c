//! The whole bridge (real threads, real clock) over a pseudo-terminal, with
//! a raw-mode peer on the slave side: no Python involved.

// A test may unwrap: a failed unwrap is a failed test (`Cargo.toml`'s lints).
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::disallowed_methods
)]

use can_bridge::codec::{Mode, WHEEL_TORQUE_CMD};
use can_bridge::slcan::{Decoder, Event};
use can_bridge::{e2e, Bridge, BridgeConfig, CanFrame};
use std::ffi::CString;
use std::time::{Duration, Instant};

struct Peer(i32);

impl Peer {
    fn open(path: &str) -> Peer {
        let c = CString::new(path).unwrap();
        let fd =
            unsafe { libc::open(c.as_ptr(), libc::O_RDWR | libc::O_NOCTTY | libc::O_NONBLOCK) };
        assert!(fd >= 0);
        let mut t: libc::termios = unsafe { std::mem::zeroed() };
        unsafe {
            libc::tcgetattr(fd, &mut t);
            libc::cfmakeraw(&mut t);
            libc::tcsetattr(fd, libc::TCSANOW, &t);
        }
        Peer(fd)
    }
    fn write(&self, b: &[u8]) {
        let n = unsafe { libc::write(self.0, b.as_ptr().cast(), b.len()) };
        assert_eq!(n as usize, b.len());
    }
    fn read_frames(
        &self,
        dec: &mut Decoder,
        until: impl Fn(&[CanFrame]) -> bool,
        timeout: Duration,
    ) -> Vec<CanFrame> {
        let mut out = vec![];
        let end = Instant::now() + timeout;
        while Instant::now() < end && !until(&out) {
            let mut p = libc::pollfd {
                fd: self.0,
                events: libc::POLLIN,
                revents: 0,
            };
            unsafe { libc::poll(&mut p, 1, 20) };
            let mut buf = [0u8; 1024];
            let n = unsafe { libc::read(self.0, buf.as_mut_ptr().cast(), buf.len()) };
            if n > 0 {
                dec.feed(&buf[..n as usize], |e| {
                    if let Event::Frame(f) = e {
                        out.push(f)
                    }
                });
            } else if n == 0 {
                break;
            }
        }
        out
    }
}

impl Drop for Peer {
    fn drop(&mut self) {
        unsafe { libc::close(self.0) };
    }
}

fn mode_and_torques(f: &CanFrame) -> (u8, [f64; 4]) {
    let m = &WHEEL_TORQUE_CMD;
    assert!(e2e::crc_ok(f.data(), m.data_id));
    let g = |n: &str| m.signal(n).unwrap().get(f.data());
    (
        g("Mode") as u8,
        [g("TorqueFL"), g("TorqueFR"), g("TorqueRL"), g("TorqueRR")],
    )
}

#[test]
fn bridge_over_pty_end_to_end() {
    let mut cfg = BridgeConfig::new("slcan-pty:");
    cfg.period_ns = 10_000_000;
    for w in &mut cfg.safety.wheels {
        w.rise_nm_per_s = 1e5;
        w.release_nm_per_s = 1e5;
    }
    cfg.safety.hold_after_ns = 100_000_000;
    let bridge = Bridge::new(cfg).unwrap();
    bridge.start().unwrap();
    let peer = Peer::open(&bridge.pty_path().unwrap());
    peer.write(b"C\rS6\rO\r");
    let mut dec = Decoder::default();
    let mut seq = 0;
    let mut frames = vec![];
    for _ in 0..20 {
        seq += 1;
        bridge.set_command([-12.0, -12.0, 2.0, 300.0], seq).unwrap();
        frames.extend(peer.read_frames(&mut dec, |v| !v.is_empty(), Duration::from_millis(200)));
    }
    assert!(frames.len() >= 15);
    let last = mode_and_torques(frames.last().unwrap());
    assert_eq!(last, (Mode::Active as u8, [-12.0, -12.0, 2.0, 300.0]));
    for w in frames.windows(2) {
        assert_eq!(
            e2e::counter_of(w[1].data()),
            Some(e2e::next_counter(e2e::counter_of(w[0].data()).unwrap()))
        );
    }
    // NaN never reaches a frame.
    assert!(bridge
        .set_command([f64::NAN, 0.0, 0.0, 0.0], seq + 1)
        .is_err());
    // Stop in another thread while reading: the last three frames are safe.
    std::thread::scope(|s| {
        let h = s.spawn(|| bridge.stop().unwrap());
        let tail = peer.read_frames(&mut dec, |_| false, Duration::from_millis(400));
        h.join().unwrap();
        assert!(tail.len() >= 3);
        for f in &tail[tail.len() - 3..] {
            assert_eq!(mode_and_torques(f), (Mode::Safe as u8, [0.0; 4]));
        }
    });
    let s = bridge.stats();
    assert!(!s.running);
    assert_eq!(s.tx_errors, 0);
    assert!(s.tick.ticks >= 20);
    // The closed pty's path may be reused by another pty: no longer reported.
    assert_eq!(bridge.pty_path(), None);
}
