//! SLCAN over a byte stream: a serial adapter (host role) or a
//! pseudo-terminal on which the bridge plays the adapter (device role).

use super::fd::{make_raw, Fd};
use super::{Opened, RxItem, Sent, Sink, Source};
use crate::channel::{baud_constant, slcan_bitrate_code};
use crate::error::{Error, Result};
use crate::frame::CanFrame;
use crate::slcan::{self, Event};
use std::collections::VecDeque;
use std::ffi::CString;
use std::io;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Longest wait for room in the output buffer per frame, ms.
const WRITE_BUDGET_MS: i32 = 5;

/// Longest wait at close for the pty peer to read what was written (the
/// safe frames of `stop`): closing the master discards unread output.
const DRAIN_BUDGET: Duration = Duration::from_millis(200);

struct Port {
    fd: Fd,
    /// Serialises writes of the two threads so lines never interleave.
    write_lock: Mutex<()>,
    /// For a pty: our own handle on the slave, so the master never sees a
    /// hang-up while no peer is connected; also how we see unread output.
    slave_keeper: Option<Fd>,
    what: String,
}

impl Port {
    fn write_line(&self, bytes: &[u8], budget_ms: i32) -> io::Result<()> {
        let _g = self.write_lock.lock().unwrap_or_else(|e| e.into_inner());
        self.fd.write_all_within(bytes, budget_ms)
    }

    /// Bytes written to a pty master that the peer has not read yet (the
    /// slave's input queue, `FIONREAD` on our slave handle). `TIOCOUTQ` on
    /// the master does not work for this: Linux reports 0 there.
    fn unread_by_peer(&self) -> Option<usize> {
        let keeper = self.slave_keeper.as_ref()?;
        let mut n: libc::c_int = 0;
        // SAFETY: FIONREAD writes one c_int to a valid pointer.
        let rc = unsafe { libc::ioctl(keeper.raw(), libc::FIONREAD, &mut n) };
        (rc == 0).then_some(n.max(0) as usize)
    }

    /// Wait (at most `budget`) until the peer has read everything written to
    /// the pty. Requires two empty readings 2 ms apart, so bytes still on
    /// their way from the master to the slave's queue are not missed.
    fn drain(&self, budget: Duration) {
        let end = std::time::Instant::now() + budget;
        let mut empty = 0;
        while std::time::Instant::now() < end {
            match self.unread_by_peer() {
                None => return,
                Some(0) => {
                    empty += 1;
                    if empty >= 2 {
                        return;
                    }
                }
                Some(_) => empty = 0,
            }
            std::thread::sleep(Duration::from_millis(2));
        }
    }
}

#[derive(Clone)]
enum Role {
    /// We are the adapter: frames go out only while the peer has the channel open.
    Device { open: Arc<AtomicBool> },
    /// We drive an adapter.
    Host,
}

struct SlcanSink {
    port: Arc<Port>,
    role: Role,
}

impl Sink for SlcanSink {
    fn send(&mut self, frame: &CanFrame) -> Result<Sent> {
        if let Role::Device { open } = &self.role {
            if !open.load(Ordering::Acquire) {
                return Ok(Sent::NotOpen);
            }
        }
        let line = slcan::encode(frame);
        self.port
            .write_line(line.as_bytes(), WRITE_BUDGET_MS)
            .map_err(|e| Error::io(&format!("{} write", self.port.what), &e))?;
        Ok(Sent::Yes)
    }

    fn close(&mut self) {
        match &self.role {
            Role::Host => {
                let _ = self.port.write_line(b"C\r", 20);
            }
            // Closing the master discards what the peer has not read yet:
            // give a slow reader a bounded time to take the last (safe) frames.
            // A peer that closed the channel (`C`) reads nothing more.
            Role::Device { open } => {
                if open.load(Ordering::Acquire) {
                    self.port.drain(DRAIN_BUDGET);
                }
            }
        }
    }
}

struct SlcanSource {
    port: Arc<Port>,
    role: Role,
    dec: slcan::Decoder,
    pending: VecDeque<RxItem>,
}

impl SlcanSource {
    fn handle(&mut self, ev: Event) {
        match (ev, &self.role) {
            (Event::Frame(f), _) => self.pending.push_back(RxItem::Frame(f)),
            (Event::Malformed, _) => self.pending.push_back(RxItem::Malformed),
            (Event::Bell, Role::Host) => self.pending.push_back(RxItem::BusError),
            (Event::Command(c), Role::Device { open }) => {
                let reply: &[u8] = match c {
                    b'O' | b'L' => {
                        open.store(true, Ordering::Release);
                        b"\r"
                    }
                    b'C' => {
                        open.store(false, Ordering::Release);
                        b"\r"
                    }
                    b'V' => b"V1013\r",
                    b'N' => b"NCB01\r",
                    b'F' => b"F00\r",
                    _ => b"\r",
                };
                let _ = self.port.write_line(reply, WRITE_BUDGET_MS);
            }
            _ => {}
        }
    }

    fn idle(timeout_ms: i32) {
        std::thread::sleep(Duration::from_millis(timeout_ms.clamp(1, 100) as u64));
    }
}

impl Source for SlcanSource {
    fn recv(&mut self, timeout_ms: i32) -> Result<Option<RxItem>> {
        if let Some(x) = self.pending.pop_front() {
            return Ok(Some(x));
        }
        let is_pty = matches!(self.role, Role::Device { .. });
        let rev = self
            .port
            .fd
            .poll(libc::POLLIN, timeout_ms)
            .map_err(|e| Error::io(&format!("{} poll", self.port.what), &e))?;
        if rev == 0 {
            return Ok(None);
        }
        if rev & libc::POLLIN == 0 {
            // Hang-up or error without data.
            if is_pty {
                Self::idle(timeout_ms);
                return Ok(None);
            }
            return Err(Error::Transport(format!("{} hung up", self.port.what)));
        }
        let mut buf = [0u8; 512];
        match self.port.fd.read(&mut buf) {
            Ok(0) => {
                Self::idle(timeout_ms);
                Ok(None)
            }
            Ok(n) => {
                let mut events: Vec<Event> = Vec::new();
                self.dec
                    .feed(buf.get(..n).unwrap_or(&[]), |e| events.push(e));
                for e in events {
                    self.handle(e);
                }
                Ok(self.pending.pop_front())
            }
            Err(e)
                if e.kind() == io::ErrorKind::WouldBlock
                    || e.kind() == io::ErrorKind::Interrupted =>
            {
                Ok(None)
            }
            Err(e) if is_pty && e.raw_os_error() == Some(libc::EIO) => {
                Self::idle(timeout_ms);
                Ok(None)
            }
            Err(e) => Err(Error::io(&format!("{} read", self.port.what), &e)),
        }
    }
}

fn cstring(path: &str) -> Result<CString> {
    CString::new(path).map_err(|_| Error::Config(format!("path {path:?} contains a NUL byte")))
}

/// Create a pseudo-terminal; the bridge plays an SLCAN adapter on its master.
pub fn open_pty() -> Result<Opened> {
    // SAFETY: plain libc call.
    let m = Fd::new(unsafe { libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY | libc::O_CLOEXEC) })
        .map_err(|e| Error::io("posix_openpt", &e))?;
    // SAFETY: m is a pty master.
    if unsafe { libc::grantpt(m.raw()) } < 0 || unsafe { libc::unlockpt(m.raw()) } < 0 {
        return Err(Error::last_os("grantpt/unlockpt"));
    }
    let mut name = [0 as libc::c_char; 128];
    // SAFETY: name is writable for its length.
    let rc = unsafe { libc::ptsname_r(m.raw(), name.as_mut_ptr(), name.len()) };
    if rc != 0 {
        return Err(Error::io("ptsname_r", &io::Error::from_raw_os_error(rc)));
    }
    // SAFETY: ptsname_r wrote a NUL-terminated string into name.
    let path = unsafe { std::ffi::CStr::from_ptr(name.as_ptr()) }
        .to_string_lossy()
        .into_owned();
    m.set_nonblocking()
        .map_err(|e| Error::io("pty O_NONBLOCK", &e))?;
    let cpath = cstring(&path)?;
    // SAFETY: cpath is NUL-terminated.
    let keeper = Fd::new(unsafe {
        libc::open(
            cpath.as_ptr(),
            libc::O_RDWR | libc::O_NOCTTY | libc::O_NONBLOCK | libc::O_CLOEXEC,
        )
    })
    .map_err(|e| Error::io(&format!("open pty slave {path}"), &e))?;
    make_raw(&keeper, None).map_err(|e| Error::io("pty raw mode", &e))?;
    let port = Arc::new(Port {
        fd: m,
        write_lock: Mutex::new(()),
        slave_keeper: Some(keeper),
        what: format!("slcan-pty {path}"),
    });
    let role = Role::Device {
        open: Arc::new(AtomicBool::new(false)),
    };
    Ok(Opened {
        sink: Box::new(SlcanSink {
            port: port.clone(),
            role: role.clone(),
        }),
        source: Box::new(SlcanSource {
            port,
            role,
            dec: slcan::Decoder::default(),
            pending: VecDeque::new(),
        }),
        pty_path: Some(path),
    })
}

/// Open an SLCAN serial adapter at `baud`, set the CAN bit rate and open the channel.
pub fn open_serial(path: &str, baud: u32, bitrate: u32) -> Result<Opened> {
    let speed = baud_constant(baud)
        .ok_or_else(|| Error::Config(format!("unsupported serial speed {baud}")))?;
    let code = slcan_bitrate_code(bitrate).ok_or_else(|| {
        Error::Config(format!(
            "SLCAN supports bit rates 10k, 20k, 50k, 100k, 125k, 250k, 500k, 800k, 1M; got {bitrate}"
        ))
    })?;
    let cpath = cstring(path)?;
    // SAFETY: cpath is NUL-terminated.
    let fd = Fd::new(unsafe {
        libc::open(
            cpath.as_ptr(),
            libc::O_RDWR | libc::O_NOCTTY | libc::O_NONBLOCK | libc::O_CLOEXEC,
        )
    })
    .map_err(|e| Error::io(&format!("cannot open SLCAN device {path}"), &e))?;
    make_raw(&fd, Some(speed))
        .map_err(|e| Error::io(&format!("{path} is not a usable tty"), &e))?;
    // SAFETY: fd is a tty.
    unsafe {
        libc::tcflush(fd.raw(), libc::TCIOFLUSH);
    }
    let port = Arc::new(Port {
        fd,
        write_lock: Mutex::new(()),
        slave_keeper: None,
        what: format!("slcan {path}"),
    });
    let init = format!("C\rS{code}\rO\r");
    port.write_line(init.as_bytes(), 200)
        .map_err(|e| Error::io(&format!("{path}: sending C/S{code}/O"), &e))?;
    Ok(Opened {
        sink: Box::new(SlcanSink {
            port: port.clone(),
            role: Role::Host,
        }),
        source: Box::new(SlcanSource {
            port,
            role: Role::Host,
            dec: slcan::Decoder::default(),
            pending: VecDeque::new(),
        }),
        pty_path: None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn open_slave(path: &str) -> Fd {
        let c = CString::new(path).unwrap();
        let fd = Fd::new(unsafe {
            libc::open(c.as_ptr(), libc::O_RDWR | libc::O_NOCTTY | libc::O_NONBLOCK)
        })
        .unwrap();
        make_raw(&fd, None).unwrap();
        fd
    }

    /// A pty with a peer that has sent `O` (open) and the source has seen it.
    fn opened_by_a_peer() -> (Box<dyn Sink>, Box<dyn Source>, Fd) {
        let Opened {
            sink,
            mut source,
            pty_path,
        } = open_pty().unwrap();
        let peer = open_slave(&pty_path.unwrap());
        peer.write(b"O\r").unwrap();
        for _ in 0..5 {
            let _ = source.recv(10).unwrap();
        }
        (sink, source, peer)
    }

    fn read_until(fd: &Fd, want: usize) -> Vec<u8> {
        let mut out = vec![];
        for _ in 0..100 {
            if out.len() >= want {
                break;
            }
            if fd.poll(libc::POLLIN, 20).unwrap() & libc::POLLIN != 0 {
                let mut b = [0u8; 256];
                if let Ok(n) = fd.read(&mut b) {
                    out.extend_from_slice(&b[..n]);
                }
            }
        }
        out
    }

    #[test]
    fn pty_device_role_gates_on_open_and_parses() {
        let Opened {
            mut sink,
            mut source,
            pty_path,
        } = open_pty().unwrap();
        let peer = open_slave(&pty_path.unwrap());
        let f = CanFrame::new(0x101, false, &[1, 2, 3]).unwrap();
        assert_eq!(sink.send(&f).unwrap(), Sent::NotOpen);
        peer.write(b"C\rS6\rO\rt2011AA\r").unwrap();
        let mut got = None;
        for _ in 0..50 {
            if let Some(x) = source.recv(20).unwrap() {
                got = Some(x);
                break;
            }
        }
        assert_eq!(
            got,
            Some(RxItem::Frame(CanFrame::new(0x201, false, &[0xAA]).unwrap()))
        );
        // Three CR replies for C, S6, O.
        assert_eq!(read_until(&peer, 3), b"\r\r\r");
        assert_eq!(sink.send(&f).unwrap(), Sent::Yes);
        assert_eq!(read_until(&peer, 12), b"t1013010203\r");
        peer.write(b"C\r").unwrap();
        for _ in 0..5 {
            let _ = source.recv(10).unwrap();
        }
        assert_eq!(sink.send(&f).unwrap(), Sent::NotOpen);
    }

    #[test]
    fn pty_close_waits_for_a_slow_peer_to_read_the_last_frames() {
        let (mut sink, source, peer) = opened_by_a_peer();
        assert_eq!(read_until(&peer, 1), b"\r");
        let f = CanFrame::new(0x101, false, &[0; 8]).unwrap();
        for _ in 0..3 {
            assert_eq!(sink.send(&f).unwrap(), Sent::Yes);
        }
        // The peer reads only every 120 ms: its next read is after close().
        let reader = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(120));
            let mut out = vec![];
            let mut b = [0u8; 256];
            while let Ok(n) = peer.read(&mut b) {
                if n == 0 {
                    break;
                }
                out.extend_from_slice(&b[..n]);
            }
            out
        });
        let t0 = std::time::Instant::now();
        sink.close();
        drop(sink);
        drop(source); // the master closes here
        let waited = t0.elapsed();
        let got = reader.join().unwrap();
        assert_eq!(
            got,
            b"t1018"
                .iter()
                .chain(&[b'0'; 16])
                .chain(b"\r")
                .copied()
                .collect::<Vec<u8>>()
                .repeat(3),
            "waited {waited:?}"
        );
        assert!(waited < Duration::from_millis(400), "waited {waited:?}");
    }

    #[test]
    fn pty_close_wait_is_bounded_without_a_reader() {
        let (mut sink, _source, peer) = opened_by_a_peer(); // the master stays open
        let f = CanFrame::new(0x101, false, &[0; 8]).unwrap();
        assert_eq!(sink.send(&f).unwrap(), Sent::Yes);
        // Nobody reads: close gives up after the bounded wait.
        let t0 = std::time::Instant::now();
        sink.close();
        let waited = t0.elapsed();
        assert!(
            waited >= Duration::from_millis(150) && waited < Duration::from_millis(400),
            "waited {waited:?}"
        );
        drop(peer);
    }

    #[test]
    fn serial_host_role_sends_init() {
        // A pty stands in for the adapter: the bridge opens the slave as its serial port.
        let m = Fd::new(unsafe { libc::posix_openpt(libc::O_RDWR | libc::O_NOCTTY) }).unwrap();
        unsafe {
            libc::grantpt(m.raw());
            libc::unlockpt(m.raw());
        }
        let mut name = [0 as libc::c_char; 128];
        unsafe { libc::ptsname_r(m.raw(), name.as_mut_ptr(), name.len()) };
        let slave = unsafe { std::ffi::CStr::from_ptr(name.as_ptr()) }
            .to_string_lossy()
            .into_owned();
        m.set_nonblocking().unwrap();
        let Opened { mut sink, .. } = open_serial(&slave, 115_200, 500_000).unwrap();
        assert_eq!(read_until(&m, 9), b"C\rS6\rO\r");
        let f = CanFrame::new(0x7FF, false, &[]).unwrap();
        assert_eq!(sink.send(&f).unwrap(), Sent::Yes);
        assert_eq!(read_until(&m, 6), b"t7FF0\r");
        sink.close();
        assert_eq!(read_until(&m, 2), b"C\r");
        assert!(open_serial(&slave, 115_200, 33_000).is_err());
        assert!(open_serial("/nonexistent/tty", 115_200, 500_000).is_err());
    }
}
