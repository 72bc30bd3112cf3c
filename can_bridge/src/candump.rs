//! candump `-L` style log lines with python-can's direction suffix:
//! `(SEC.USEC) CHANNEL ID#DATA R|T`, written by a background thread so the
//! tick thread never touches the file.

use crate::error::{Error, Result};
use crate::frame::CanFrame;
use crate::scheduler::monotonic_ns;
use crate::sync::lock;
use std::fmt::Write as _;
use std::io::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;
use std::time::Duration;

/// Direction of a logged frame.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Dir {
    /// Received.
    Rx,
    /// Transmitted.
    Tx,
}

/// Format one log line (with trailing newline).
pub fn format_line(out: &mut String, wall_ns: u64, channel: &str, frame: &CanFrame, dir: Dir) {
    let sec = wall_ns / 1_000_000_000;
    let usec = (wall_ns % 1_000_000_000) / 1_000;
    let _ = write!(out, "({sec}.{usec:06}) {channel} ");
    let _ = if frame.is_extended() {
        write!(out, "{:08X}#", frame.id())
    } else {
        write!(out, "{:03X}#", frame.id())
    };
    if frame.is_remote() {
        let _ = write!(out, "R{}", frame.len());
    } else {
        for b in frame.data() {
            let _ = write!(out, "{b:02X}");
        }
    }
    out.push_str(match dir {
        Dir::Rx => " R\n",
        Dir::Tx => " T\n",
    });
}

struct Entry {
    wall_ns: u64,
    frame: CanFrame,
    dir: Dir,
}

/// What the log reports to `stats()`.
#[derive(Debug, Default)]
pub struct LogCounters {
    /// Lines dropped because the writer fell behind (`log_dropped`).
    pub dropped: AtomicU64,
    /// Lines lost to write errors (`log_errors`).
    pub errors: AtomicU64,
    /// Lines not written by the log's bounds (`log_suppressed`).
    pub suppressed: AtomicU64,
    /// The last write error or bound reached, naming the file.
    pub last_error: Mutex<Option<String>>,
}

impl LogCounters {
    fn note(&self, msg: String) {
        *lock(&self.last_error) = Some(msg);
    }
}

/// How a log is opened and bounded.
#[derive(Clone, Debug)]
pub struct LogSetup {
    /// The file.
    pub path: std::path::PathBuf,
    /// Replace an existing file (never through a symbolic link).
    pub overwrite: bool,
    /// The channel name written on each line.
    pub channel: String,
    /// Most received frames logged per second, per class (the identifiers
    /// the bridge receives, and all others), with a second's burst.
    pub rx_per_s: u32,
    /// Largest file, bytes.
    pub max_bytes: u64,
    /// Identifiers of the bridge's own received messages.
    pub known_ids: Vec<u32>,
}

/// A token bucket: `rate` tokens a second, at most `rate` held.
#[derive(Debug)]
struct Bucket {
    tokens: f64,
    last_ns: u64,
}

/// The receive side's rate limit: one bucket for the bridge's own
/// messages, one for every other identifier, so a flood of unknown frames
/// never hides the vehicle's.
#[derive(Debug)]
struct RxLimit {
    rate: f64,
    known: Vec<u32>,
    buckets: [Bucket; 2],
}

impl RxLimit {
    fn allow(&mut self, id: u32, now_ns: u64) -> bool {
        let b = &mut self.buckets[usize::from(!self.known.contains(&id))];
        let dt = now_ns.saturating_sub(b.last_ns) as f64 / 1e9;
        b.last_ns = now_ns;
        b.tokens = (b.tokens + dt * self.rate).min(self.rate);
        if b.tokens >= 1.0 {
            b.tokens -= 1.0;
            true
        } else {
            false
        }
    }
}

/// Sending side, cloned into the tick and receive threads.
#[derive(Clone)]
pub struct LogSender {
    tx: SyncSender<Entry>,
    counters: Arc<LogCounters>,
    rx_limit: Arc<Mutex<RxLimit>>,
}

impl LogSender {
    /// Queue a frame without blocking; counts a drop when the queue is full.
    /// A received frame over its class's rate is counted in `suppressed`
    /// instead (transmitted frames are bounded by the tick rate).
    pub fn log(&self, wall_ns: u64, frame: &CanFrame, dir: Dir) {
        if dir == Dir::Rx {
            let ok = lock(&self.rx_limit).allow(frame.id(), monotonic_ns());
            if !ok {
                self.counters.suppressed.fetch_add(1, Ordering::Relaxed);
                return;
            }
        }
        match self.tx.try_send(Entry {
            wall_ns,
            frame: *frame,
            dir,
        }) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                self.counters.dropped.fetch_add(1, Ordering::Relaxed);
            }
        }
    }
}

/// The writer thread; joined when all senders are gone.
pub struct LogWriter {
    handle: JoinHandle<()>,
}

impl LogWriter {
    /// Wait for the writer to flush and finish (all senders must be dropped).
    pub fn join(self) {
        let _ = self.handle.join();
    }
}

/// Open the log and start the writer thread. Lines lost to write errors (a
/// full disk, `/dev/full`, a file over the process's size limit, a FIFO
/// whose reader stalls) are counted in `errors`, and the error, naming the
/// file, is kept in `last_error`.
///
/// An existing file is refused unless `overwrite` (then truncated), and a
/// symbolic link is always refused (`O_NOFOLLOW`), so a log never clobbers
/// a file by accident or through a link
/// (`test_f8_log_path_is_not_overwritten_nor_followed_through_a_symlink`).
/// The file is opened with `O_NONBLOCK`: a FIFO without a reader is refused
/// at once (instead of blocking `start` forever), and a FIFO whose reader
/// stops reading costs lost (counted) lines, never a blocked `stop`.
///
/// **Bounds.** Received frames are logged at most `rx_per_s` a second per
/// class, and nothing once the file holds `max_bytes`; what is left out is
/// counted in `suppressed` (`test_tx_log_*` in `tests/can_bridge`: a flood of
/// 300,000 frames a second on the pty wrote 33 MB in 2 s before).
pub fn start(setup: &LogSetup, counters: Arc<LogCounters>) -> Result<(LogSender, LogWriter)> {
    use std::os::unix::fs::{FileTypeExt, OpenOptionsExt};
    let path = setup.path.as_path();
    let shown = show_path(path);
    let meta = std::fs::symlink_metadata(path).ok();
    if meta.as_ref().is_some_and(|m| m.file_type().is_symlink()) {
        return Err(Error::Config(format!(
            "log_path {shown} is a symbolic link; give the real path"
        )));
    }
    if meta.is_some() && !setup.overwrite {
        return Err(Error::Config(format!(
            "log_path {shown} exists; pass log_overwrite=True to replace it"
        )));
    }
    let mut opts = std::fs::OpenOptions::new();
    opts.write(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_CLOEXEC | libc::O_NOFOLLOW);
    if meta.is_some() {
        opts.truncate(true);
    } else {
        opts.create_new(true);
    }
    let file = opts.open(path).map_err(|e| {
        let fifo = std::fs::metadata(path).is_ok_and(|m| m.file_type().is_fifo());
        if fifo && e.raw_os_error() == Some(libc::ENXIO) {
            Error::Config(format!(
                "log_path {shown} is a FIFO with no reader; open it for reading first or use a regular file"
            ))
        } else if e.raw_os_error() == Some(libc::ELOOP) {
            Error::Config(format!(
                "log_path {shown} is a symbolic link; give the real path"
            ))
        } else {
            Error::io(&format!("cannot create log file {shown}"), &e)
        }
    })?;
    let (tx, rx) = sync_channel::<Entry>(8192);
    let out = Out {
        file,
        buf: Vec::with_capacity(FLUSH_AT + 128),
        counters: counters.clone(),
        shown: shown.clone(),
        room: setup.max_bytes,
        capped: false,
    };
    let channel = setup.channel.clone();
    let handle = std::thread::Builder::new()
        .name("can_bridge-log".into())
        .spawn(move || writer_loop(rx, out, &channel))
        .map_err(|e| {
            Error::io(
                &format!("log_path {shown}: cannot start the log thread"),
                &e,
            )
        })?;
    let rate = f64::from(setup.rx_per_s.max(1));
    let now = monotonic_ns();
    let full = || Bucket {
        tokens: rate,
        last_ns: now,
    };
    let rx_limit = RxLimit {
        rate,
        known: setup.known_ids.clone(),
        buckets: [full(), full()],
    };
    Ok((
        LogSender {
            tx,
            counters,
            rx_limit: Arc::new(Mutex::new(rx_limit)),
        },
        LogWriter { handle },
    ))
}

/// A path as every message about the log shows it: whole (a path is at most
/// `PATH_MAX`, 4096 bytes), quoted; anything longer is cut like other input.
fn show_path(path: &std::path::Path) -> String {
    let text = path.display().to_string();
    if text.len() <= 4096 {
        format!("{text:?}")
    } else {
        crate::error::clip(&text)
    }
}

/// Pending lines are written at the latest this long after the last write.
const FLUSH_EVERY: Duration = Duration::from_millis(200);

/// Buffered lines are written once this many bytes are pending.
const FLUSH_AT: usize = 8192;

/// Most bytes kept waiting for a slow reader (a FIFO); a line that would
/// exceed it is dropped whole and counted, so the buffer stays bounded.
const MAX_PENDING: usize = 64 * 1024;

/// The writer's own buffer, so lines lost to a failed write can be counted.
///
/// `buf` holds what is not yet written, possibly starting in the middle of a
/// line that a partial write began: it is always finished before anything
/// else, so the file only ever holds whole lines (a non-blocking write to a
/// pipe can take part of a buffer).
struct Out {
    file: std::fs::File,
    buf: Vec<u8>,
    counters: Arc<LogCounters>,
    /// The file's name as errors show it.
    shown: String,
    /// Bytes the file may still take (`max_bytes` less what was queued).
    room: u64,
    /// The cap was reached (reported once).
    capped: bool,
}

impl Out {
    /// Queue one whole line, or count it lost when a stalled reader has left
    /// `MAX_PENDING` bytes waiting, or suppressed once the file is full.
    fn push(&mut self, line: &[u8]) {
        let n = line.len() as u64;
        if n > self.room {
            self.counters.suppressed.fetch_add(1, Ordering::Relaxed);
            if !self.capped {
                self.capped = true;
                self.counters.note(format!(
                    "log_path {}: reached log_max_bytes; later lines are counted in log_suppressed, not written",
                    self.shown
                ));
            }
        } else if self.buf.len() + line.len() > MAX_PENDING {
            self.counters.errors.fetch_add(1, Ordering::Relaxed);
        } else {
            self.room -= n;
            self.buf.extend_from_slice(line);
        }
    }

    /// Write what the file takes now. `WouldBlock` keeps the rest for later;
    /// any other error loses (and counts) every line still pending.
    /// Returns whether bytes are still pending.
    fn flush(&mut self) -> bool {
        while !self.buf.is_empty() {
            match self.file.write(&self.buf) {
                Ok(0) => {
                    let e = std::io::Error::new(std::io::ErrorKind::WriteZero, "wrote nothing");
                    return self.lose_pending(Some(&e));
                }
                Ok(n) => {
                    self.buf.drain(..n);
                }
                Err(e) if e.kind() == std::io::ErrorKind::Interrupted => {}
                Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => return true,
                Err(e) => return self.lose_pending(Some(&e)),
            }
        }
        false
    }

    /// Count every line still pending as lost; `why`, naming the file, is
    /// kept for `stats()["last_log_error"]`.
    fn lose_pending(&mut self, why: Option<&std::io::Error>) -> bool {
        // a line already begun counts as lost too
        let lines = self.buf.iter().filter(|&&b| b == b'\n').count() as u64;
        self.counters.errors.fetch_add(lines, Ordering::Relaxed);
        self.buf.clear();
        if let Some(e) = why {
            self.counters.note(format!(
                "log_path {}: write failed: {e}; {lines} lines lost (counted in log_errors)",
                self.shown
            ));
        } else if lines > 0 {
            self.counters.note(format!(
                "log_path {}: the reader did not take {lines} lines within 100 ms of stop",
                self.shown
            ));
        }
        false
    }
}

fn writer_loop(rx: Receiver<Entry>, mut out: Out, channel: &str) {
    let mut line = String::with_capacity(64);
    let mut flushed = std::time::Instant::now();
    loop {
        match rx.recv_timeout(FLUSH_EVERY) {
            Ok(e) => {
                line.clear();
                format_line(&mut line, e.wall_ns, channel, &e.frame, e.dir);
                out.push(line.as_bytes());
                // a slow, steady trickle is written too, not held for 8 KB
                if out.buf.len() >= FLUSH_AT || flushed.elapsed() >= FLUSH_EVERY {
                    out.flush();
                    flushed = std::time::Instant::now();
                }
            }
            Err(RecvTimeoutError::Timeout) => {
                out.flush();
                flushed = std::time::Instant::now();
            }
            Err(RecvTimeoutError::Disconnected) => break,
        }
    }
    // On stop: give a slow reader up to about 100 ms, then count the rest lost.
    for _ in 0..50 {
        if !out.flush() {
            return;
        }
        std::thread::sleep(Duration::from_millis(2));
    }
    out.lose_pending(None);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn setup(path: &std::path::Path, overwrite: bool) -> LogSetup {
        LogSetup {
            path: path.to_path_buf(),
            overwrite,
            channel: "can0".into(),
            rx_per_s: 1000,
            max_bytes: 1 << 30,
            known_ids: vec![0x201],
        }
    }

    #[test]
    fn formats_lines() {
        let mut s = String::new();
        let f = CanFrame::new(0x101, false, &[0xDE, 0xAD]).unwrap();
        format_line(&mut s, 1_700_000_000_123_456_789, "can0", &f, Dir::Tx);
        assert_eq!(s, "(1700000000.123456) can0 101#DEAD T\n");
        s.clear();
        let f = CanFrame::new(0x1ABCDEF, true, &[]).unwrap();
        format_line(&mut s, 5_000_001_000, "slcan0", &f, Dir::Rx);
        assert_eq!(s, "(5.000001) slcan0 01ABCDEF# R\n");
        s.clear();
        let f = CanFrame::remote(0x7, false, 3).unwrap();
        format_line(&mut s, 0, "c", &f, Dir::Rx);
        assert_eq!(s, "(0.000000) c 007#R3 R\n");
    }

    #[test]
    fn writes_a_file() {
        let dir = std::env::temp_dir().join(format!("can_bridge_log_{}", std::process::id()));
        let c = Arc::new(LogCounters::default());
        let _ = std::fs::remove_file(&dir);
        let (tx, w) = start(&setup(&dir, false), c.clone()).unwrap();
        let f = CanFrame::new(0x101, false, &[1]).unwrap();
        for _ in 0..3 {
            tx.log(1_000_000_000, &f, Dir::Tx);
        }
        drop(tx);
        w.join();
        let text = std::fs::read_to_string(&dir).unwrap();
        let _ = std::fs::remove_file(&dir);
        assert_eq!(text.lines().count(), 3);
        assert_eq!(c.dropped.load(Ordering::Relaxed), 0);
        assert_eq!(c.errors.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn write_errors_are_counted() {
        let c = Arc::new(LogCounters::default());
        let (tx, w) = start(&setup(std::path::Path::new("/dev/full"), true), c.clone()).unwrap();
        let f = CanFrame::new(0x101, false, &[1]).unwrap();
        for _ in 0..1000 {
            tx.log(1_000_000_000, &f, Dir::Tx);
        }
        drop(tx);
        w.join();
        assert_eq!(c.errors.load(Ordering::Relaxed), 1000);
        // the error names the file
        let e = c.last_error.lock().unwrap().clone().unwrap();
        assert!(
            e.starts_with("log_path \"/dev/full\": write failed: "),
            "{e}"
        );
    }

    #[test]
    fn received_frames_are_rate_limited_per_class_and_the_file_is_capped() {
        let dir = std::env::temp_dir().join(format!("can_bridge_cap_{}", std::process::id()));
        let _ = std::fs::remove_file(&dir);
        let c = Arc::new(LogCounters::default());
        let mut su = setup(&dir, false);
        su.rx_per_s = 100;
        su.max_bytes = 20_000;
        let (tx, w) = start(&su, c.clone()).unwrap();
        let unknown = CanFrame::new(0x7FF, false, &[1]).unwrap();
        let known = CanFrame::new(0x201, false, &[2]).unwrap();
        // a flood far faster than the rate: about a second's burst of each
        // class gets through, well within the test's time
        for _ in 0..5_000 {
            tx.log(1, &unknown, Dir::Rx);
        }
        for _ in 0..150 {
            tx.log(1, &known, Dir::Rx);
        }
        drop(tx);
        w.join();
        let text = std::fs::read_to_string(&dir).unwrap();
        let _ = std::fs::remove_file(&dir);
        let n_unknown = text.lines().filter(|l| l.contains(" 7FF#")).count();
        let n_known = text.lines().filter(|l| l.contains(" 201#")).count();
        assert!((100..=110).contains(&n_unknown), "{n_unknown}");
        assert!((100..=110).contains(&n_known), "{n_known}");
        let suppressed = c.suppressed.load(Ordering::Relaxed) as usize;
        assert_eq!(n_unknown + n_known + suppressed, 5_150);
        // the cap: a tiny file holds what fits, counts the rest
        let c = Arc::new(LogCounters::default());
        su.rx_per_s = 1_000_000;
        su.max_bytes = 4096;
        let (tx, w) = start(&su, c.clone()).unwrap();
        for _ in 0..1_000 {
            tx.log(1, &known, Dir::Tx);
        }
        drop(tx);
        w.join();
        let len = std::fs::metadata(&dir).unwrap().len();
        let text = std::fs::read_to_string(&dir).unwrap();
        let _ = std::fs::remove_file(&dir);
        assert!(len <= 4096 && len > 4000, "{len}");
        let lines = text.lines().count() as u64;
        assert_eq!(lines + c.suppressed.load(Ordering::Relaxed), 1_000);
        let e = c.last_error.lock().unwrap().clone().unwrap();
        assert!(
            e.contains(&dir.display().to_string()) && e.contains("log_max_bytes"),
            "{e}"
        );
    }

    #[test]
    fn fifo_without_reader_is_refused_not_a_hang() {
        let dir = std::env::temp_dir().join(format!("can_bridge_fifo_{}", std::process::id()));
        let c = std::ffi::CString::new(dir.to_str().unwrap()).unwrap();
        let _ = std::fs::remove_file(&dir);
        // SAFETY: c is a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        let p = dir.clone();
        std::thread::spawn(move || {
            let r = start(&setup(&p, true), Arc::new(LogCounters::default()));
            let _ = done_tx.send(r.map(|_| ()));
        });
        let r = done_rx.recv_timeout(Duration::from_secs(3));
        // Unblock a hanging open (if any) before asserting, then clean up.
        if r.is_err() {
            let _ = std::fs::File::open(&dir);
        }
        let _ = std::fs::remove_file(&dir);
        let e = r
            .expect("start() blocked on a FIFO without a reader")
            .unwrap_err();
        assert!(matches!(e, Error::Config(_)), "{e}");
        assert!(
            e.to_string().contains("log_path") && e.to_string().contains("FIFO"),
            "{e}"
        );
    }

    #[test]
    fn a_slow_pipe_reader_gets_whole_lines_only() {
        // A pipe with a small buffer, written non-blocking, read slowly: every
        // line that arrives is whole, and arrived + counted lost = sent.
        let mut fds = [0i32; 2];
        // SAFETY: fds is a valid array of two ints for pipe2 to fill.
        assert_eq!(
            unsafe { libc::pipe2(fds.as_mut_ptr(), libc::O_NONBLOCK | libc::O_CLOEXEC) },
            0
        );
        // SAFETY: fds[1] is an open pipe descriptor owned by this test.
        unsafe { libc::fcntl(fds[1], libc::F_SETPIPE_SZ, 4096) };
        use std::os::fd::FromRawFd;
        // SAFETY: each descriptor is owned by exactly one File from here on.
        let (r, w) = unsafe {
            (
                std::fs::File::from_raw_fd(fds[0]),
                std::fs::File::from_raw_fd(fds[1]),
            )
        };
        let counters = Arc::new(LogCounters::default());
        let mut out = Out {
            file: w,
            buf: Vec::new(),
            counters: counters.clone(),
            shown: "pipe".into(),
            room: u64::MAX,
            capped: false,
        };
        let f = CanFrame::new(0x101, false, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap();
        let mut line = String::new();
        let mut got = Vec::new();
        let mut r = r;
        let sent = 20_000u64;
        for k in 0..sent {
            line.clear();
            format_line(&mut line, 1_000_000_000 + k, "can0", &f, Dir::Tx);
            out.push(line.as_bytes());
            if out.buf.len() >= 1000 {
                out.flush();
            }
            if k % 50 == 0 {
                let mut chunk = [0u8; 700];
                if let Ok(n) = std::io::Read::read(&mut r, &mut chunk) {
                    got.extend_from_slice(&chunk[..n]);
                }
            }
        }
        while out.flush() {
            let mut chunk = [0u8; 4096];
            if let Ok(n) = std::io::Read::read(&mut r, &mut chunk) {
                got.extend_from_slice(&chunk[..n]);
            }
        }
        drop(out);
        let _ = std::io::Read::read_to_end(&mut r, &mut got);
        let text = String::from_utf8(got).unwrap();
        assert!(text.ends_with('\n'));
        let mut arrived = 0u64;
        for l in text.lines() {
            assert!(
                l.starts_with('(') && l.ends_with(" T") && l.contains("101#0102030405060708"),
                "{l:?}"
            );
            arrived += 1;
        }
        let lost = counters.errors.load(Ordering::Relaxed);
        assert!(lost > 0, "the slow reader should have cost lines");
        assert_eq!(arrived + lost, sent);
    }
}
