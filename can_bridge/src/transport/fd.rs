//! A small owned file descriptor with poll-based, non-blocking I/O.

use std::io;
use std::os::fd::RawFd;

/// An owned file descriptor, closed on drop.
#[derive(Debug)]
pub struct Fd(RawFd);

fn cvt(rc: isize) -> io::Result<usize> {
    if rc < 0 {
        Err(io::Error::last_os_error())
    } else {
        Ok(rc as usize)
    }
}

impl Fd {
    /// Take ownership of `fd` (must be open; -1 is an error).
    pub fn new(fd: RawFd) -> io::Result<Self> {
        if fd < 0 {
            Err(io::Error::last_os_error())
        } else {
            Ok(Fd(fd))
        }
    }

    /// The raw descriptor.
    pub fn raw(&self) -> RawFd {
        self.0
    }

    /// Set `O_NONBLOCK`.
    pub fn set_nonblocking(&self) -> io::Result<()> {
        // SAFETY: fcntl on an fd we own.
        let flags = unsafe { libc::fcntl(self.0, libc::F_GETFL) };
        if flags < 0 {
            return Err(io::Error::last_os_error());
        }
        // SAFETY: as above.
        if unsafe { libc::fcntl(self.0, libc::F_SETFL, flags | libc::O_NONBLOCK) } < 0 {
            return Err(io::Error::last_os_error());
        }
        Ok(())
    }

    /// Wait up to `timeout_ms` for `events`; returns the revents (0 on timeout).
    pub fn poll(&self, events: libc::c_short, timeout_ms: i32) -> io::Result<libc::c_short> {
        let mut p = libc::pollfd {
            fd: self.0,
            events,
            revents: 0,
        };
        // SAFETY: one valid pollfd.
        let rc = unsafe { libc::poll(&mut p, 1, timeout_ms) };
        if rc < 0 {
            let e = io::Error::last_os_error();
            if e.kind() == io::ErrorKind::Interrupted {
                return Ok(0);
            }
            return Err(e);
        }
        Ok(if rc == 0 { 0 } else { p.revents })
    }

    /// One `read`.
    pub fn read(&self, buf: &mut [u8]) -> io::Result<usize> {
        // SAFETY: buf is valid for buf.len() bytes.
        cvt(unsafe { libc::read(self.0, buf.as_mut_ptr().cast(), buf.len()) })
    }

    /// One `write`.
    pub fn write(&self, buf: &[u8]) -> io::Result<usize> {
        // SAFETY: buf is valid for buf.len() bytes.
        cvt(unsafe { libc::write(self.0, buf.as_ptr().cast(), buf.len()) })
    }

    /// Write all of `buf` on a non-blocking fd, waiting at most `budget_ms`
    /// in total for room. Fails with `WouldBlock` if nothing could be written
    /// at all, or `TimedOut` if a line was cut.
    pub fn write_all_within(&self, mut buf: &[u8], budget_ms: i32) -> io::Result<()> {
        let mut waited = false;
        let total = buf.len();
        while !buf.is_empty() {
            match self.write(buf) {
                Ok(0) => return Err(io::Error::new(io::ErrorKind::WriteZero, "write returned 0")),
                Ok(n) => buf = buf.get(n..).unwrap_or(&[]),
                Err(e) if e.kind() == io::ErrorKind::Interrupted => {}
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    if waited {
                        return Err(if buf.len() == total {
                            io::Error::new(
                                io::ErrorKind::WouldBlock,
                                "output buffer full (peer not reading)",
                            )
                        } else {
                            io::Error::new(io::ErrorKind::TimedOut, "output buffer full, line cut")
                        });
                    }
                    self.poll(libc::POLLOUT, budget_ms)?;
                    waited = true;
                }
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}

impl Drop for Fd {
    fn drop(&mut self) {
        // SAFETY: we own the fd and close it once.
        unsafe {
            libc::close(self.0);
        }
    }
}

/// Put a terminal in raw mode (no echo, no line editing, no CR/NL mapping),
/// 8N1, receiver on, modem lines ignored, optionally at `speed`.
pub fn make_raw(fd: &Fd, speed: Option<libc::speed_t>) -> io::Result<()> {
    // SAFETY: zeroed termios is a valid out-parameter for tcgetattr.
    let mut t: libc::termios = unsafe { std::mem::zeroed() };
    // SAFETY: fd is a valid descriptor; t is writable.
    if unsafe { libc::tcgetattr(fd.raw(), &mut t) } < 0 {
        return Err(io::Error::last_os_error());
    }
    // SAFETY: t was filled by tcgetattr.
    unsafe { libc::cfmakeraw(&mut t) };
    t.c_cflag |= libc::CLOCAL | libc::CREAD;
    t.c_cc[libc::VMIN] = 0;
    t.c_cc[libc::VTIME] = 0;
    if let Some(s) = speed {
        // SAFETY: t is a valid termios.
        unsafe {
            libc::cfsetispeed(&mut t, s);
            libc::cfsetospeed(&mut t, s);
        }
    }
    // SAFETY: fd valid, t valid.
    if unsafe { libc::tcsetattr(fd.raw(), libc::TCSANOW, &t) } < 0 {
        return Err(io::Error::last_os_error());
    }
    Ok(())
}
