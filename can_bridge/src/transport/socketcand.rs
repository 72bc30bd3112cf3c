//! socketcand client over TCP (raw mode).
//!
//! **Age rule.** TCP cannot take back what the server's kernel has taken (on
//! Linux a reader gets queued bytes even after the connection is reset, and
//! socketcand's `state_raw.c` relays whatever it reads), so nothing is handed
//! to a server that may not be reading: each frame goes out with a
//! `< echo >` (socketcand answers it in raw mode), and once the server is
//! known to answer echoes, a probe `< echo >` goes out ahead of each
//! deadline ([`Sink::probe_lead_ns`]: three measured round trips plus 1 ms,
//! within 2 ms..half a period); the frame is written only if every echo is
//! answered by the deadline, and never while more than [`MAX_UNACKED`]
//! bytes sit unacknowledged in the socket (`SIOCOUTQ`). A server that stops
//! reading between two ticks gets no frame to hold
//! (`test_i2_a_stalled_socketcand_server_never_puts_a_stale_frame_on_the_bus`);
//! one that stops within the probe's lead before a deadline can still find
//! that one frame when it resumes.
//!
//! **Active frames.** Because of that residual, and because TCP cannot take
//! a frame back once the server's kernel holds it (an abortive close does
//! not help: Linux hands queued bytes to the reader before the reset), the
//! sink allows active frames only when the bridge was told to accept the
//! residual (`socketcand_active`, [`Assurance::Refused`] otherwise) and only
//! while the server answers echoes (a server that never has is
//! [`Assurance::Unverified`]); otherwise every frame is a safe one
//! (`test_tx_socketcand_*` in `tests/can_bridge`).
//!
//! **Reconnect.** A closed or broken connection marks the link down at once
//! (the bridge reports the transport lost on its next tick); the receive
//! thread reconnects with a backoff of 100 ms doubling to [`MAX_BACKOFF`]
//! (`test_f4_a_restarted_socketcand_server_is_reconnected`).

use super::{out_queue, Assurance, Gate, Health, Opened, Ready, RxItem, Sink, Source, Written};
use crate::error::{clip, Error, Result};
use crate::frame::CanFrame;
use crate::scheduler::monotonic_ns;
use crate::socketcand::{encode_send, Decoder, Event};
use crate::sync;
use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::sync::atomic::{AtomicBool, AtomicU32, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(3);

/// Bytes the socket may hold unacknowledged before a new frame is withheld
/// (a few messages: on a healthy link the queue is empty a period later).
pub const MAX_UNACKED: usize = 256;

/// Longest pause between two reconnection attempts.
pub const MAX_BACKOFF: Duration = Duration::from_secs(2);

/// Connect and handshake budget of a reconnection attempt (run by the
/// receive thread, so it bounds `stop()` latency while reconnecting).
const RECONNECT_BUDGET: Duration = Duration::from_millis(500);

/// Longest wait at close to finish a message cut by a full send buffer, ms.
const CLOSE_BUDGET_MS: i32 = 100;

/// A byte sink that never blocks: `write_nb` writes what fits now (or fails
/// with `WouldBlock`), `wait_writable` waits up to `ms` for room.
pub trait NbWrite {
    /// Write what fits without blocking.
    fn write_nb(&mut self, buf: &[u8]) -> io::Result<usize>;
    /// Wait up to `ms` for room.
    fn wait_writable(&mut self, ms: i32) -> io::Result<()>;
}

impl NbWrite for TcpStream {
    fn write_nb(&mut self, buf: &[u8]) -> io::Result<usize> {
        use std::os::fd::AsRawFd;
        loop {
            // SAFETY: buf is valid for buf.len() bytes; MSG_DONTWAIT makes this
            // one call non-blocking without touching the descriptor's flags
            // (shared with the receive half).
            let rc = unsafe {
                libc::send(
                    self.as_raw_fd(),
                    buf.as_ptr().cast(),
                    buf.len(),
                    libc::MSG_DONTWAIT | libc::MSG_NOSIGNAL,
                )
            };
            if rc >= 0 {
                return Ok(rc as usize);
            }
            let e = io::Error::last_os_error();
            if e.kind() != io::ErrorKind::Interrupted {
                return Err(e);
            }
        }
    }

    fn wait_writable(&mut self, ms: i32) -> io::Result<()> {
        use std::os::fd::AsRawFd;
        let mut p = libc::pollfd {
            fd: self.as_raw_fd(),
            events: libc::POLLOUT,
            revents: 0,
        };
        // SAFETY: one valid pollfd.
        let rc = unsafe { libc::poll(&mut p, 1, ms) };
        if rc < 0 {
            let e = io::Error::last_os_error();
            if e.kind() != io::ErrorKind::Interrupted {
                return Err(e);
            }
        }
        Ok(())
    }
}

/// Sends whole messages or nothing: a message the socket took only in part
/// keeps its unsent tail here, and the tail goes out before anything else. A
/// frame that cannot start (buffer full, or an earlier tail still pending)
/// is dropped whole and reported as an error, never half-written.
#[derive(Debug, Default)]
pub struct MessageWriter {
    tail: Vec<u8>,
}

fn would_block(msg: &str) -> io::Error {
    io::Error::new(io::ErrorKind::WouldBlock, msg.to_string())
}

impl MessageWriter {
    /// Bytes of a started message still to be written.
    pub fn pending(&self) -> usize {
        self.tail.len()
    }

    /// Write as much of the pending tail as fits; `Ok(true)` once it is empty.
    fn push_tail(&mut self, w: &mut dyn NbWrite) -> io::Result<bool> {
        while !self.tail.is_empty() {
            match w.write_nb(&self.tail) {
                Ok(0) => return Err(io::Error::new(io::ErrorKind::WriteZero, "send returned 0")),
                Ok(n) => {
                    self.tail.drain(..n.min(self.tail.len()));
                }
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => return Ok(false),
                Err(e) => return Err(e),
            }
        }
        Ok(true)
    }

    /// Finish the pending tail, waiting at most `budget_ms` in total.
    pub fn flush(&mut self, w: &mut dyn NbWrite, budget_ms: i32) -> io::Result<bool> {
        let end = std::time::Instant::now() + Duration::from_millis(budget_ms.max(0) as u64);
        loop {
            if self.push_tail(w)? {
                return Ok(true);
            }
            let left = end.saturating_duration_since(std::time::Instant::now());
            if left.is_zero() {
                return Ok(false);
            }
            w.wait_writable(left.as_millis().clamp(1, i32::MAX as u128) as i32)?;
        }
    }

    /// Send one whole message, waiting at most about `budget_ms` for room.
    /// `Err(WouldBlock)`: the message was dropped, nothing of it was written.
    pub fn send(&mut self, w: &mut dyn NbWrite, msg: &[u8], budget_ms: i32) -> io::Result<()> {
        let mut waited = false;
        while !self.push_tail(w)? {
            if waited {
                return Err(would_block(
                    "send buffer full (server not reading), previous message unfinished; frame dropped",
                ));
            }
            w.wait_writable(budget_ms)?;
            waited = true;
        }
        let mut off = 0usize;
        while off < msg.len() {
            match w.write_nb(msg.get(off..).unwrap_or(&[])) {
                Ok(0) => return Err(io::Error::new(io::ErrorKind::WriteZero, "send returned 0")),
                Ok(n) => off += n,
                Err(e) if e.kind() == io::ErrorKind::WouldBlock => {
                    if off == 0 && !waited {
                        w.wait_writable(budget_ms)?;
                        waited = true;
                    } else if off == 0 {
                        return Err(would_block(
                            "send buffer full (server not reading); frame dropped",
                        ));
                    } else {
                        // Started: the message is committed; its tail goes
                        // out before the next one.
                        self.tail.extend_from_slice(msg.get(off..).unwrap_or(&[]));
                        return Ok(());
                    }
                }
                Err(e) => return Err(e),
            }
        }
        Ok(())
    }
}

/// The connection both halves share; `tx` is swapped on reconnect.
struct Link {
    tx: Mutex<Option<TcpStream>>,
    /// The server has answered an echo: its answers can be waited for.
    echo_known: AtomicBool,
    /// Echoes written and not yet answered.
    echoes_out: AtomicU32,
    /// When the last echo was written (monotonic ns).
    echo_sent_ns: AtomicU64,
    /// Round trip of an echo, a decaying maximum (ns; `u64::MAX`: none yet).
    rtt_ns: AtomicU64,
    /// Connections made so far (a new one discards a message left half
    /// sent on the old one).
    generation: AtomicU64,
    health: Arc<Health>,
    what: String,
}

impl Link {
    /// Write `msg` (which ends with an echo) as one message, counting the
    /// echo out before the write: its answer can be read by the receive
    /// thread before this thread runs again, and must find it counted.
    fn send_with_echo(
        &self,
        writer: &mut MessageWriter,
        stream: &mut TcpStream,
        msg: &[u8],
    ) -> io::Result<()> {
        self.echo_sent_ns.store(monotonic_ns(), Ordering::Release);
        self.echoes_out.fetch_add(1, Ordering::AcqRel);
        let r = writer.send(stream, msg, 0);
        if r.is_err() {
            let _ = self
                .echoes_out
                .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                    Some(n.saturating_sub(1))
                });
        }
        r
    }

    /// Note an echo's answer: one fewer out, and the round trip of the last
    /// one written if it was the only one out.
    fn echo_answered(&self) {
        self.echo_known.store(true, Ordering::Release);
        let was = self
            .echoes_out
            .fetch_update(Ordering::AcqRel, Ordering::Acquire, |n| {
                Some(n.saturating_sub(1))
            })
            .unwrap_or(0);
        if was == 1 {
            let rtt = monotonic_ns().saturating_sub(self.echo_sent_ns.load(Ordering::Acquire));
            let old = self.rtt_ns.load(Ordering::Acquire);
            let decayed = if old == u64::MAX { 0 } else { old - old / 8 };
            self.rtt_ns.store(rtt.max(decayed), Ordering::Release);
        }
    }

    /// A fresh connection: nothing out, nothing known about its echoes.
    fn reset_echoes(&self) {
        self.echo_known.store(false, Ordering::Release);
        self.echoes_out.store(0, Ordering::Release);
        self.rtt_ns.store(u64::MAX, Ordering::Release);
    }

    fn down(&self) {
        self.health.link_up.store(false, Ordering::Release);
        if let Some(s) = sync::lock(&self.tx).take() {
            let _ = s.shutdown(std::net::Shutdown::Both);
        }
    }
}

/// Ticks a frame may be withheld for a missing echo before a bare
/// `< echo >` is sent again (a lost answer must not hold frames forever).
const REPROBE_TICKS: u32 = 5;

struct TcpSink {
    link: Arc<Link>,
    writer: MessageWriter,
    generation: u64,
    held: u32,
    /// Active frames allowed (`socketcand_active`).
    active: bool,
}

impl TcpSink {
    /// The connection to write on, with a message cut by a full buffer on
    /// it finished first; `Ok(None)` if it cannot be written now.
    fn stream<'a>(
        &mut self,
        guard: &'a mut std::sync::MutexGuard<'_, Option<TcpStream>>,
    ) -> Result<Option<&'a mut TcpStream>> {
        let Some(stream) = guard.as_mut() else {
            return Ok(None);
        };
        let generation = self.link.generation.load(Ordering::Acquire);
        if generation != self.generation {
            self.generation = generation;
            self.writer = MessageWriter::default();
            self.held = 0;
        }
        if self.writer.pending() > 0 {
            match self.writer.flush(stream, 0) {
                Ok(true) => {}
                Ok(false) => return Ok(None),
                Err(e) => return Err(Error::io(&format!("{} send", self.link.what), &e)),
            }
        }
        Ok(Some(stream))
    }

    fn lost(&self) -> Error {
        Error::Transport(format!("{}: connection lost; reconnecting", self.link.what))
    }
}

impl Sink for TcpSink {
    fn prepare(&mut self) -> Result<Ready> {
        let link = self.link.clone();
        if !link.health.link_up.load(Ordering::Acquire) {
            return Err(self.lost());
        }
        let busy = Ready {
            gate: Gate::Busy,
            flushed: 0,
        };
        // The receive thread holds this only to swap in a new connection.
        let Some(mut guard) = sync::try_lock(&link.tx) else {
            return Ok(busy);
        };
        let stream = match self.stream(&mut guard) {
            Ok(Some(s)) => s,
            Ok(None) => return Ok(busy),
            Err(e) => {
                drop(guard);
                link.down();
                return Err(e);
            }
        };
        use std::os::fd::AsRawFd;
        let waiting_echo =
            link.echo_known.load(Ordering::Acquire) && link.echoes_out.load(Ordering::Acquire) > 0;
        if waiting_echo || out_queue(stream.as_raw_fd()).is_some_and(|n| n > MAX_UNACKED) {
            self.held += 1;
            if waiting_echo && self.held % REPROBE_TICKS == 0 {
                let _ = link.send_with_echo(&mut self.writer, stream, b"< echo >");
            }
            return Ok(busy);
        }
        self.held = 0;
        Ok(Ready::OPEN)
    }

    fn write(&mut self, frame: &CanFrame) -> Result<Written> {
        let link = self.link.clone();
        let Some(mut guard) = sync::try_lock(&link.tx) else {
            return Ok(Written::Dropped);
        };
        let stream = match self.stream(&mut guard) {
            Ok(Some(s)) => s,
            Ok(None) => return Ok(Written::Dropped),
            Err(e) => {
                drop(guard);
                link.down();
                return Err(e);
            }
        };
        let mut msg = encode_send(frame);
        msg.push_str("< echo >");
        match link.send_with_echo(&mut self.writer, stream, msg.as_bytes()) {
            Ok(()) => Ok(Written::Yes),
            Err(e) if e.kind() == io::ErrorKind::WouldBlock => Ok(Written::Dropped),
            Err(e) => {
                drop(guard);
                link.down();
                Err(Error::io(&format!("{} send", link.what), &e))
            }
        }
    }

    /// Once the server is known to answer echoes: a probe ahead of each deadline, never less than three round trips (measured,
    /// a decaying maximum) plus 1 ms, at most half a period.
    fn probe_lead_ns(&self, period_ns: u64) -> Option<u64> {
        if !self.link.echo_known.load(Ordering::Acquire) {
            return None;
        }
        Some(super::probe_lead(
            self.link.rtt_ns.load(Ordering::Acquire),
            period_ns,
        ))
    }

    /// Ask the server for an echo ahead of the deadline, unless one is out
    /// already: the frame goes out only once it is answered, so a server
    /// that stopped reading since the last tick gets no frame to hold.
    fn probe(&mut self) {
        let link = self.link.clone();
        if !link.health.link_up.load(Ordering::Acquire)
            || link.echoes_out.load(Ordering::Acquire) > 0
        {
            return;
        }
        let Some(mut guard) = sync::try_lock(&link.tx) else {
            return;
        };
        if let Ok(Some(stream)) = self.stream(&mut guard) {
            let _ = link.send_with_echo(&mut self.writer, stream, b"< echo >");
        }
    }

    fn assurance(&self) -> Assurance {
        if !self.link.echo_known.load(Ordering::Acquire) {
            Assurance::Unverified
        } else if !self.active {
            Assurance::Refused
        } else {
            Assurance::Holds
        }
    }

    fn close(&mut self) {
        let mut guard = sync::lock(&self.link.tx);
        if let Some(stream) = guard.as_mut() {
            let _ = self.writer.flush(stream, CLOSE_BUDGET_MS);
            let _ = stream.shutdown(std::net::Shutdown::Write);
        }
    }
}

struct TcpSource {
    link: Arc<Link>,
    stream: Option<TcpStream>,
    dec: Decoder,
    pending: VecDeque<RxItem>,
    host: String,
    port: u16,
    bus: String,
    backoff: Duration,
    next_attempt: Instant,
}

fn push_event(pending: &mut VecDeque<RxItem>, link: &Link, ev: Event) {
    match ev {
        Event::Frame(f) => pending.push_back(RxItem::Frame(f)),
        Event::Malformed => pending.push_back(RxItem::Malformed),
        Event::Error(_) => pending.push_back(RxItem::BusError),
        Event::Other(w) if w == "echo" => link.echo_answered(),
        Event::Hi | Event::Ok | Event::Other(_) => {}
    }
}

impl TcpSource {
    fn lost(&mut self, why: String) -> Error {
        self.link.down();
        self.stream = None;
        self.backoff = Duration::from_millis(100);
        self.next_attempt = Instant::now() + self.backoff;
        Error::Transport(format!("{}: {why}; reconnecting", self.link.what))
    }

    fn reconnect(&mut self, timeout_ms: i32) -> Result<Option<RxItem>> {
        let now = Instant::now();
        if now < self.next_attempt {
            let wait =
                (self.next_attempt - now).min(Duration::from_millis(timeout_ms.max(1) as u64));
            std::thread::sleep(wait);
            return Ok(None);
        }
        match connect(&self.host, self.port, &self.bus, RECONNECT_BUDGET) {
            Ok((stream, dec, backlog)) => {
                let rx = stream
                    .try_clone()
                    .map_err(|e| Error::io(&format!("{}: clone socket", self.link.what), &e))?;
                self.link.reset_echoes();
                *sync::lock(&self.link.tx) = Some(stream);
                self.link.generation.fetch_add(1, Ordering::AcqRel);
                self.stream = Some(rx);
                self.dec = dec;
                for ev in backlog {
                    push_event(&mut self.pending, &self.link, ev);
                }
                self.link.health.reconnects.fetch_add(1, Ordering::Relaxed);
                self.link.health.link_up.store(true, Ordering::Release);
                Ok(None)
            }
            Err(e) => {
                self.backoff = (self.backoff * 2).min(MAX_BACKOFF);
                self.next_attempt = Instant::now() + self.backoff;
                Err(e)
            }
        }
    }
}

impl Source for TcpSource {
    fn recv(&mut self, timeout_ms: i32) -> Result<Option<RxItem>> {
        if let Some(x) = self.pending.pop_front() {
            return Ok(Some(x));
        }
        let Some(stream) = self.stream.as_mut() else {
            return self.reconnect(timeout_ms);
        };
        let t = Duration::from_millis(timeout_ms.max(1) as u64);
        if let Err(e) = stream.set_read_timeout(Some(t)) {
            return Err(self.lost(format!("{e}")));
        }
        let mut buf = [0u8; 1024];
        match stream.read(&mut buf) {
            Ok(0) => Err(self.lost("connection closed by the server".into())),
            Ok(n) => {
                let (pending, link) = (&mut self.pending, &self.link);
                self.dec.feed(buf.get(..n).unwrap_or(&[]), |e| {
                    push_event(pending, link, e)
                });
                Ok(self.pending.pop_front())
            }
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock
                        | io::ErrorKind::TimedOut
                        | io::ErrorKind::Interrupted
                ) =>
            {
                Ok(None)
            }
            Err(e) => Err(self.lost(format!("read: {e}"))),
        }
    }
}

/// Read until one handshake event arrives (by `deadline`).
fn expect(
    stream: &mut TcpStream,
    dec: &mut Decoder,
    backlog: &mut VecDeque<Event>,
    what: &str,
    step: &str,
    deadline: Instant,
) -> Result<Event> {
    loop {
        if let Some(ev) = backlog.pop_front() {
            return Ok(ev);
        }
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(Error::Transport(format!(
                "{what}: no reply to {step} in time"
            )));
        }
        stream
            .set_read_timeout(Some(left))
            .map_err(|e| Error::io(what, &e))?;
        let mut buf = [0u8; 256];
        let n = match stream.read(&mut buf) {
            Ok(0) => {
                return Err(Error::Transport(format!(
                    "{what}: server closed the connection during {step}"
                )))
            }
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    io::ErrorKind::WouldBlock
                        | io::ErrorKind::TimedOut
                        | io::ErrorKind::Interrupted
                ) =>
            {
                continue
            }
            Err(e) => return Err(Error::io(&format!("{what}: {step}"), &e)),
        };
        dec.feed(buf.get(..n).unwrap_or(&[]), |e| backlog.push_back(e));
    }
}

type Connected = (TcpStream, Decoder, VecDeque<Event>);

/// Connect to `host:port` and open `bus` in raw mode, all within `budget`.
fn connect(host: &str, port: u16, bus: &str, budget: Duration) -> Result<Connected> {
    let what = format!("socketcand {}:{port}/{}", clip(host), clip(bus));
    let deadline = Instant::now() + budget;
    let addrs: Vec<_> = (host, port)
        .to_socket_addrs()
        .map_err(|e| Error::io(&format!("{what}: cannot resolve host"), &e))?
        .collect();
    let mut last_err = None;
    let mut stream = None;
    for a in &addrs {
        let left = deadline
            .saturating_duration_since(Instant::now())
            .max(Duration::from_millis(1));
        match TcpStream::connect_timeout(a, left) {
            Ok(s) => {
                stream = Some(s);
                break;
            }
            Err(e) => last_err = Some(e),
        }
    }
    let mut stream = match (stream, last_err) {
        (Some(s), _) => s,
        (None, Some(e)) => return Err(Error::io(&format!("{what}: connect"), &e)),
        (None, None) => {
            return Err(Error::Transport(format!(
                "{what}: host resolves to no address"
            )))
        }
    };
    stream.set_nodelay(true).map_err(|e| Error::io(&what, &e))?;
    let mut dec = Decoder::default();
    let mut backlog = VecDeque::new();
    match expect(
        &mut stream,
        &mut dec,
        &mut backlog,
        &what,
        "connect (< hi >)",
        deadline,
    )? {
        Event::Hi => {}
        other => {
            return Err(Error::Transport(format!(
                "{what}: expected < hi >, got {}",
                clip(&format!("{other:?}"))
            )))
        }
    }
    for (msg, step) in [
        (format!("< open {bus} >"), "< open >"),
        ("< rawmode >".to_string(), "< rawmode >"),
    ] {
        stream
            .write_all(msg.as_bytes())
            .map_err(|e| Error::io(&format!("{what}: {step}"), &e))?;
        match expect(&mut stream, &mut dec, &mut backlog, &what, step, deadline)? {
            Event::Ok => {}
            Event::Error(text) => {
                return Err(Error::Transport(format!(
                    "{what}: server refused {step}: {}",
                    clip(&text)
                )))
            }
            other => {
                return Err(Error::Transport(format!(
                    "{what}: expected < ok > after {step}, got {}",
                    clip(&format!("{other:?}"))
                )))
            }
        }
    }
    Ok((stream, dec, backlog))
}

/// Connect to `host:port`, open `bus` in raw mode (refused at start if that
/// fails within the handshake timeout). `active`: allow active frames (see
/// the module's documentation).
pub fn open(host: &str, port: u16, bus: &str, active: bool) -> Result<Opened> {
    let (stream, dec, backlog) = connect(host, port, bus, HANDSHAKE_TIMEOUT)?;
    let what = format!("socketcand {}:{port}/{}", clip(host), clip(bus));
    let rx = stream
        .try_clone()
        .map_err(|e| Error::io(&format!("{what}: clone socket"), &e))?;
    let health = Arc::new(Health::default());
    let link = Arc::new(Link {
        tx: Mutex::new(Some(stream)),
        echo_known: AtomicBool::new(false),
        echoes_out: AtomicU32::new(0),
        echo_sent_ns: AtomicU64::new(0),
        rtt_ns: AtomicU64::new(u64::MAX),
        generation: AtomicU64::new(0),
        health: health.clone(),
        what,
    });
    let mut pending = VecDeque::new();
    for ev in backlog {
        push_event(&mut pending, &link, ev);
    }
    Ok(Opened {
        sink: Box::new(TcpSink {
            link: link.clone(),
            writer: MessageWriter::default(),
            generation: 0,
            held: 0,
            active,
        }),
        source: Box::new(TcpSource {
            link,
            stream: Some(rx),
            dec,
            pending,
            host: host.to_string(),
            port,
            bus: bus.to_string(),
            backoff: Duration::from_millis(100),
            next_attempt: Instant::now(),
        }),
        pty_path: None,
        health,
    })
}

#[cfg(test)]
mod tests {
    use super::super::Outcome;
    use super::*;
    use std::net::TcpListener;

    #[test]
    fn handshake_send_and_receive() {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = l.local_addr().unwrap().port();
        let server = std::thread::spawn(move || {
            let (mut s, _) = l.accept().unwrap();
            s.set_nodelay(true).unwrap();
            let mut got = Vec::new();
            let read_msg = |s: &mut TcpStream, got: &mut Vec<u8>| {
                let mut b = [0u8; 256];
                let n = s.read(&mut b).unwrap();
                got.extend_from_slice(&b[..n]);
            };
            s.write_all(b"< hi >").unwrap();
            read_msg(&mut s, &mut got);
            s.write_all(b"< ok >").unwrap();
            read_msg(&mut s, &mut got);
            s.write_all(b"< ok >").unwrap();
            s.write_all(b"< frame 201 1.000001 0A0B >< frame 1FFFFFFF 2.5  >")
                .unwrap();
            while !got.ends_with(b"< echo >") {
                read_msg(&mut s, &mut got);
            }
            String::from_utf8(got).unwrap()
        });
        let Opened {
            mut sink,
            mut source,
            ..
        } = open("127.0.0.1", port, "can0", true).unwrap();
        let mut frames = vec![];
        for _ in 0..100 {
            if let Some(RxItem::Frame(f)) = source.recv(20).unwrap() {
                frames.push(f);
            }
            if frames.len() == 2 {
                break;
            }
        }
        assert_eq!(
            frames[0],
            CanFrame::new(0x201, false, &[0x0A, 0x0B]).unwrap()
        );
        assert_eq!(frames[1], CanFrame::new(0x1FFFFFFF, true, &[]).unwrap());
        sink.send(&CanFrame::new(0x101, false, &[0xFF]).unwrap())
            .unwrap();
        let transcript = server.join().unwrap();
        assert_eq!(
            transcript,
            "< open can0 >< rawmode >< send 101 1 FF >< echo >"
        );
    }

    /// Takes at most `room` bytes; `wait_writable` frees a scripted amount.
    struct Trickle {
        out: Vec<u8>,
        room: usize,
        refills: Vec<usize>,
        k: usize,
    }

    impl NbWrite for Trickle {
        fn write_nb(&mut self, buf: &[u8]) -> io::Result<usize> {
            if self.room == 0 {
                return Err(io::ErrorKind::WouldBlock.into());
            }
            let n = buf.len().min(self.room);
            self.out.extend_from_slice(&buf[..n]);
            self.room -= n;
            Ok(n)
        }
        fn wait_writable(&mut self, _ms: i32) -> io::Result<()> {
            self.room += self.refills[self.k % self.refills.len()];
            self.k += 1;
            Ok(())
        }
    }

    fn msg(i: usize) -> Vec<u8> {
        let data: Vec<u8> = (0..(i % 9) as u8).collect();
        encode_send(&CanFrame::new(0x101 + (i as u32 % 3), false, &data).unwrap()).into_bytes()
    }

    #[test]
    fn message_writer_never_cuts_a_message() {
        for refills in [
            vec![0, 7, 0, 0, 13],
            vec![5],
            vec![40, 0],
            vec![0, 0, 0, 100, 3],
        ] {
            let mut w = Trickle {
                out: vec![],
                room: 10,
                refills,
                k: 0,
            };
            let mut mw = MessageWriter::default();
            let mut sent = vec![];
            let mut dropped = 0;
            for i in 0..500 {
                let m = msg(i);
                match mw.send(&mut w, &m, 5) {
                    Ok(()) => sent.extend_from_slice(&m),
                    Err(e) => {
                        assert_eq!(e.kind(), io::ErrorKind::WouldBlock);
                        dropped += 1;
                    }
                }
                // Whatever is on the wire is a prefix of the accepted messages.
                assert!(sent.starts_with(&w.out));
            }
            w.room = usize::MAX;
            assert!(mw.flush(&mut w, 5).unwrap());
            assert_eq!(w.out, sent);
            assert!(dropped > 0);
        }
    }

    #[test]
    fn full_send_buffer_drops_whole_frames_never_cuts_one() {
        use std::os::fd::AsRawFd;
        fn set_buf(fd: i32, opt: i32, n: i32) {
            // SAFETY: fd is an open socket; the option value is one valid i32.
            let rc = unsafe {
                libc::setsockopt(
                    fd,
                    libc::SOL_SOCKET,
                    opt,
                    (&n as *const i32).cast(),
                    std::mem::size_of::<i32>() as libc::socklen_t,
                )
            };
            assert_eq!(rc, 0);
        }
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        set_buf(l.as_raw_fd(), libc::SO_RCVBUF, 2048);
        let client = TcpStream::connect(l.local_addr().unwrap()).unwrap();
        set_buf(client.as_raw_fd(), libc::SO_SNDBUF, 4096);
        client.set_nodelay(true).unwrap();
        let (mut server, _) = l.accept().unwrap();
        let link = Arc::new(Link {
            tx: Mutex::new(Some(client)),
            echo_known: AtomicBool::new(false),
            echoes_out: AtomicU32::new(0),
            echo_sent_ns: AtomicU64::new(0),
            rtt_ns: AtomicU64::new(u64::MAX),
            generation: AtomicU64::new(0),
            health: Arc::new(Health::default()),
            what: "test".into(),
        });
        let mut sink = TcpSink {
            link,
            writer: MessageWriter::default(),
            generation: 0,
            held: 0,
            active: true,
        };
        // The server does not read: the buffers fill, sends start failing.
        let (mut ok, mut failed) = (0usize, 0usize);
        let mut i = 0usize;
        while failed < 40 && i < 20_000 {
            let data: Vec<u8> = (0..(i % 9) as u8).collect();
            match sink.send(&CanFrame::new(0x101, false, &data).unwrap()) {
                Ok(o) if o == Outcome::YES => ok += 1,
                Ok(o) => {
                    assert_eq!(o, Outcome::DROPPED);
                    failed += 1;
                }
                Err(e) => panic!("{e}"),
            }
            i += 1;
        }
        assert!(failed > 0, "the send buffer never filled");
        let reader = std::thread::spawn(move || {
            let mut got = vec![];
            server.read_to_end(&mut got).unwrap();
            got
        });
        sink.close();
        drop(sink);
        let got = String::from_utf8(reader.join().unwrap()).unwrap();
        // Every message is whole, and every accepted frame arrived.
        let mut n = 0;
        for part in got.split_inclusive('>') {
            if part == "< echo >" {
                continue;
            }
            let body = part
                .strip_prefix("< send 101 ")
                .and_then(|p| p.strip_suffix(" >"))
                .unwrap_or_else(|| panic!("cut or glued message {part:?}"));
            let mut it = body.split(' ');
            let len: usize = it.next().unwrap().parse().unwrap();
            assert_eq!(it.count(), len, "{part:?}");
            n += 1;
        }
        assert_eq!(n, ok);
    }

    #[test]
    fn refused_open_is_a_clear_error() {
        let l = TcpListener::bind("127.0.0.1:0").unwrap();
        let port = l.local_addr().unwrap().port();
        let server = std::thread::spawn(move || {
            let (mut s, _) = l.accept().unwrap();
            s.write_all(b"< hi >").unwrap();
            let mut b = [0u8; 64];
            let _ = s.read(&mut b).unwrap();
            s.write_all(b"< error could not open bus >").unwrap();
        });
        let e = open("127.0.0.1", port, "nope", false).err().unwrap();
        assert!(e.to_string().contains("could not open bus"), "{e}");
        server.join().unwrap();
    }
}
