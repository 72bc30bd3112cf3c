//! `start` and `stop` racing from several threads on one bridge: every call
//! must return, and no transmit/receive thread may outlive the last `stop`.
//! (Own test binary, so the thread count of the process is ours alone.)

// A test may unwrap: a failed unwrap is a failed test (`Cargo.toml`'s lints).
#![allow(
    clippy::unwrap_used,
    clippy::expect_used,
    clippy::panic,
    clippy::disallowed_methods
)]

use can_bridge::{Bridge, BridgeConfig};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Threads of this process whose name starts with `can_bridge`.
fn bridge_threads() -> usize {
    let Ok(dir) = std::fs::read_dir("/proc/self/task") else {
        return 0;
    };
    dir.flatten()
        .filter(|t| {
            std::fs::read_to_string(t.path().join("comm"))
                .is_ok_and(|c| c.trim().starts_with("can_bridge"))
        })
        .count()
}

#[test]
fn racing_start_and_stop_never_hangs_or_leaks_threads() {
    let mut cfg = BridgeConfig::new("slcan-pty:");
    cfg.period_ns = 2_000_000;
    cfg.stop_safe_frames = 1;
    let bridge = Arc::new(Bridge::new(cfg).unwrap());
    let end = Instant::now() + Duration::from_millis(2500);
    let ops = Arc::new(AtomicU64::new(0));
    let finished = Arc::new(AtomicU64::new(0));
    let workers = 6;
    let stop_all = Arc::new(AtomicBool::new(false));
    for k in 0..workers {
        let (b, ops, finished, stop_all) = (
            bridge.clone(),
            ops.clone(),
            finished.clone(),
            stop_all.clone(),
        );
        std::thread::spawn(move || {
            let mut x: u64 = 0x9E37_79B9_7F4A_7C15 ^ k;
            let mut seq = k * 1_000_000_000;
            while Instant::now() < end && !stop_all.load(Ordering::Relaxed) {
                x ^= x << 13;
                x ^= x >> 7;
                x ^= x << 17;
                match x % 5 {
                    0 | 1 => {
                        let _ = b.start();
                    }
                    2 | 3 => {
                        let _ = b.stop();
                    }
                    _ => {
                        seq += 1;
                        let _ = b.set_command([1.0; 4], seq);
                        let _ = b.stats();
                    }
                }
                ops.fetch_add(1, Ordering::Relaxed);
            }
            finished.fetch_add(1, Ordering::SeqCst);
        });
    }
    // Every worker must come back soon after the deadline; a stop() that
    // signalled the wrong run would block in join() forever.
    let give_up = end + Duration::from_secs(5);
    while finished.load(Ordering::SeqCst) < workers && Instant::now() < give_up {
        std::thread::sleep(Duration::from_millis(20));
    }
    stop_all.store(true, Ordering::Relaxed);
    assert_eq!(
        finished.load(Ordering::SeqCst),
        workers,
        "a start()/stop() call hung ({} operations done)",
        ops.load(Ordering::Relaxed)
    );
    assert!(ops.load(Ordering::Relaxed) > 50);
    bridge.stop().unwrap();
    assert!(!bridge.is_running());
    // Threads that were joined are gone at once; allow the kernel a moment.
    let deadline = Instant::now() + Duration::from_secs(2);
    while bridge_threads() > 0 && Instant::now() < deadline {
        std::thread::sleep(Duration::from_millis(20));
    }
    assert_eq!(bridge_threads(), 0, "bridge threads outlived stop()");
}
