//! The one way this crate takes a mutex: [`lock`] and [`try_lock`], which
//! recover a poisoned lock instead of panicking (`clippy.toml` disallows
//! `Mutex::lock` and `Mutex::try_lock` elsewhere, so no call site can
//! forget the rule).

use std::sync::{Mutex, MutexGuard, PoisonError, TryLockError};

/// Lock `m`, recovering its data if a thread panicked while holding it.
///
/// Why recover rather than fail: no code outside tests may panic (the
/// crate's lints deny `unwrap`, `expect` and `panic!`), so a poisoned lock
/// can only follow a bug; failing every later call on it would also fail
/// `stop()`, the call that releases the output and sends the safe frames,
/// and `unwrap` would carry the panic into Python.
///
/// Why that is sound: no guarded value can turn a half-finished update into
/// an unsafe output.
/// * The command slot holds commands already checked (finite, in range, in
///   sequence); the transmit thread still limits, rate-limits and ages each
///   one at every tick.
/// * The transmit counters and the log's error text and rate limiter only
///   count, copy or bound diagnostics.
/// * The SLCAN transport's ledger of the lines written to a pty is rebuilt
///   from empty at every flush: an update cut short can only affect the one
///   flush after it.
/// * The received state is judged again on every read against the clock:
///   a message is valid only while its last believed frame is younger than
///   `state_timeout_ms`, so the store of a receive thread that panicked
///   (and so feeds it no more) is invalid within that time.
/// * The unit locks (`Mutex<()>`) and the socket slot guard no invariant
///   beyond exclusive use, which the guard still gives.
///
/// A thread that panicked has ended: `Bridge::stop` reports that as an
/// error ("a bridge thread ended abnormally").
#[allow(clippy::disallowed_methods)] // the one permitted `Mutex::lock`
pub(crate) fn lock<T: ?Sized>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(PoisonError::into_inner)
}

/// [`lock`] without waiting: `None` only while another thread holds `m`
/// (a poisoned lock is recovered as in [`lock`], not taken for busy, so a
/// transport whose lock was poisoned keeps sending rather than going quiet).
#[allow(clippy::disallowed_methods)] // the one permitted `Mutex::try_lock`
pub(crate) fn try_lock<T: ?Sized>(m: &Mutex<T>) -> Option<MutexGuard<'_, T>> {
    match m.try_lock() {
        Ok(g) => Some(g),
        Err(TryLockError::Poisoned(e)) => Some(e.into_inner()),
        Err(TryLockError::WouldBlock) => None,
    }
}

#[cfg(test)]
mod tests {
    use super::{lock, try_lock};
    use std::sync::{Arc, Mutex};

    #[test]
    fn a_poisoned_lock_is_recovered_with_its_data() {
        let m = Arc::new(Mutex::new(7_u32));
        let m2 = m.clone();
        let r = std::thread::spawn(move || {
            let mut g = m2.lock().unwrap();
            *g = 8;
            panic!("poison the lock while holding it");
        })
        .join();
        assert!(r.is_err());
        assert!(m.is_poisoned());
        assert_eq!(*lock(&m), 8);
        *lock(&m) = 9;
        assert_eq!(*lock(&m), 9);
        assert_eq!(try_lock(&m).map(|g| *g), Some(9));
    }

    #[test]
    fn try_lock_is_none_only_while_held() {
        let m = Mutex::new(1_u8);
        let g = lock(&m);
        assert!(try_lock(&m).is_none());
        drop(g);
        assert_eq!(try_lock(&m).map(|g| *g), Some(1));
    }
}
