//! candump `-L` style log lines with python-can's direction suffix:
//! `(SEC.USEC) CHANNEL ID#DATA R|T`, written by a background thread so the
//! tick thread never touches the file.

use crate::error::{Error, Result};
use crate::frame::CanFrame;
use std::fmt::Write as _;
use std::io::Write as _;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::mpsc::{sync_channel, Receiver, RecvTimeoutError, SyncSender, TrySendError};
use std::sync::Arc;
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

/// Sending side, cloned into the tick and receive threads.
#[derive(Clone)]
pub struct LogSender {
    tx: SyncSender<Entry>,
    dropped: Arc<AtomicU64>,
}

impl LogSender {
    /// Queue a frame without blocking; counts a drop when the queue is full.
    pub fn log(&self, wall_ns: u64, frame: &CanFrame, dir: Dir) {
        match self.tx.try_send(Entry {
            wall_ns,
            frame: *frame,
            dir,
        }) {
            Ok(()) => {}
            Err(TrySendError::Full(_)) | Err(TrySendError::Disconnected(_)) => {
                self.dropped.fetch_add(1, Ordering::Relaxed);
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

/// Open `path` (truncating) and start the writer thread. Lines lost to
/// write errors (a full disk, `/dev/full`, a FIFO whose reader stalls) are
/// counted in `errors`.
///
/// The file is opened with `O_NONBLOCK`: a FIFO without a reader is refused
/// at once (instead of blocking `start` forever), and a FIFO whose reader
/// stops reading costs lost (counted) lines, never a blocked `stop`.
pub fn start(
    path: &std::path::Path,
    channel: String,
    dropped: Arc<AtomicU64>,
    errors: Arc<AtomicU64>,
) -> Result<(LogSender, LogWriter)> {
    use std::os::unix::fs::OpenOptionsExt;
    let file = std::fs::OpenOptions::new()
        .write(true)
        .create(true)
        .truncate(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_CLOEXEC)
        .open(path)
        .map_err(|e| {
            if e.raw_os_error() == Some(libc::ENXIO) {
                Error::Config(format!(
                    "log_path {} is a FIFO with no reader; open it for reading first or use a regular file",
                    path.display()
                ))
            } else {
                Error::io(&format!("cannot create log file {}", path.display()), &e)
            }
        })?;
    let (tx, rx) = sync_channel::<Entry>(8192);
    let out = Out {
        file,
        buf: Vec::with_capacity(FLUSH_AT + 128),
        lines: 0,
        errors,
    };
    let handle = std::thread::Builder::new()
        .name("can_bridge-log".into())
        .spawn(move || writer_loop(rx, out, &channel))
        .map_err(|e| Error::io("cannot start log thread", &e))?;
    Ok((LogSender { tx, dropped }, LogWriter { handle }))
}

/// Buffered lines are written once this many bytes are pending.
const FLUSH_AT: usize = 8192;

/// The writer's own buffer, so lines lost to a failed write can be counted.
struct Out {
    file: std::fs::File,
    buf: Vec<u8>,
    lines: u64,
    errors: Arc<AtomicU64>,
}

impl Out {
    fn flush(&mut self) {
        if self.buf.is_empty() {
            return;
        }
        if self.file.write_all(&self.buf).is_err() {
            self.errors.fetch_add(self.lines, Ordering::Relaxed);
        }
        self.buf.clear();
        self.lines = 0;
    }
}

fn writer_loop(rx: Receiver<Entry>, mut out: Out, channel: &str) {
    let mut line = String::with_capacity(64);
    loop {
        match rx.recv_timeout(Duration::from_millis(200)) {
            Ok(e) => {
                line.clear();
                format_line(&mut line, e.wall_ns, channel, &e.frame, e.dir);
                out.buf.extend_from_slice(line.as_bytes());
                out.lines += 1;
                if out.buf.len() >= FLUSH_AT {
                    out.flush();
                }
            }
            Err(RecvTimeoutError::Timeout) => out.flush(),
            Err(RecvTimeoutError::Disconnected) => break,
        }
    }
    out.flush();
}

#[cfg(test)]
mod tests {
    use super::*;

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
        let dropped = Arc::new(AtomicU64::new(0));
        let errors = Arc::new(AtomicU64::new(0));
        let (tx, w) = start(&dir, "can0".into(), dropped.clone(), errors.clone()).unwrap();
        let f = CanFrame::new(0x101, false, &[1]).unwrap();
        for _ in 0..3 {
            tx.log(1_000_000_000, &f, Dir::Tx);
        }
        drop(tx);
        w.join();
        let text = std::fs::read_to_string(&dir).unwrap();
        let _ = std::fs::remove_file(&dir);
        assert_eq!(text.lines().count(), 3);
        assert_eq!(dropped.load(Ordering::Relaxed), 0);
        assert_eq!(errors.load(Ordering::Relaxed), 0);
    }

    #[test]
    fn write_errors_are_counted() {
        let errors = Arc::new(AtomicU64::new(0));
        let (tx, w) = start(
            std::path::Path::new("/dev/full"),
            "can0".into(),
            Arc::new(AtomicU64::new(0)),
            errors.clone(),
        )
        .unwrap();
        let f = CanFrame::new(0x101, false, &[1]).unwrap();
        for _ in 0..1000 {
            tx.log(1_000_000_000, &f, Dir::Tx);
        }
        drop(tx);
        w.join();
        assert_eq!(errors.load(Ordering::Relaxed), 1000);
    }

    #[test]
    fn fifo_without_reader_is_refused_not_a_hang() {
        let dir = std::env::temp_dir().join(format!("can_bridge_fifo_{}", std::process::id()));
        let c = std::ffi::CString::new(dir.to_str().unwrap()).unwrap();
        let _ = std::fs::remove_file(&dir);
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        let p = dir.clone();
        std::thread::spawn(move || {
            let r = start(
                &p,
                "can0".into(),
                Arc::new(AtomicU64::new(0)),
                Arc::new(AtomicU64::new(0)),
            );
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
}
