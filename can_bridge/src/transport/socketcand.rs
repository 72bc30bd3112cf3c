//! socketcand client over TCP (raw mode).

use super::{Opened, RxItem, Sent, Sink, Source};
use crate::error::{Error, Result};
use crate::frame::CanFrame;
use crate::socketcand::{encode_send, Decoder, Event};
use std::collections::VecDeque;
use std::io::{self, Read, Write};
use std::net::{TcpStream, ToSocketAddrs};
use std::time::{Duration, Instant};

const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(3);

struct TcpSink {
    stream: TcpStream,
    what: String,
}

impl Sink for TcpSink {
    fn send(&mut self, frame: &CanFrame) -> Result<Sent> {
        let msg = encode_send(frame);
        self.stream
            .write_all(msg.as_bytes())
            .map_err(|e| Error::io(&format!("{} send", self.what), &e))?;
        Ok(Sent::Yes)
    }

    fn close(&mut self) {
        let _ = self.stream.shutdown(std::net::Shutdown::Write);
    }
}

struct TcpSource {
    stream: TcpStream,
    dec: Decoder,
    pending: VecDeque<RxItem>,
    what: String,
    closed: bool,
}

fn push_event(pending: &mut VecDeque<RxItem>, ev: Event) {
    match ev {
        Event::Frame(f) => pending.push_back(RxItem::Frame(f)),
        Event::Malformed => pending.push_back(RxItem::Malformed),
        Event::Error(_) => pending.push_back(RxItem::BusError),
        Event::Hi | Event::Ok | Event::Other(_) => {}
    }
}

impl Source for TcpSource {
    fn recv(&mut self, timeout_ms: i32) -> Result<Option<RxItem>> {
        if let Some(x) = self.pending.pop_front() {
            return Ok(Some(x));
        }
        if self.closed {
            std::thread::sleep(Duration::from_millis(timeout_ms.clamp(1, 100) as u64));
            return Err(Error::Transport(format!(
                "{}: connection closed by the server",
                self.what
            )));
        }
        let t = Duration::from_millis(timeout_ms.max(1) as u64);
        self.stream
            .set_read_timeout(Some(t))
            .map_err(|e| Error::io(&self.what, &e))?;
        let mut buf = [0u8; 1024];
        match self.stream.read(&mut buf) {
            Ok(0) => {
                self.closed = true;
                Err(Error::Transport(format!(
                    "{}: connection closed by the server",
                    self.what
                )))
            }
            Ok(n) => {
                let pending = &mut self.pending;
                self.dec
                    .feed(buf.get(..n).unwrap_or(&[]), |e| push_event(pending, e));
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
            Err(e) => Err(Error::io(&format!("{} read", self.what), &e)),
        }
    }
}

/// Read until one handshake event arrives.
fn expect(
    stream: &mut TcpStream,
    dec: &mut Decoder,
    backlog: &mut VecDeque<Event>,
    what: &str,
    step: &str,
) -> Result<Event> {
    let deadline = Instant::now() + HANDSHAKE_TIMEOUT;
    loop {
        if let Some(ev) = backlog.pop_front() {
            return Ok(ev);
        }
        let left = deadline.saturating_duration_since(Instant::now());
        if left.is_zero() {
            return Err(Error::Transport(format!(
                "{what}: no reply to {step} within {HANDSHAKE_TIMEOUT:?}"
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

/// Connect to `host:port`, open `bus` in raw mode.
pub fn open(host: &str, port: u16, bus: &str) -> Result<Opened> {
    let what = format!("socketcand {host}:{port}/{bus}");
    let addrs: Vec<_> = (host, port)
        .to_socket_addrs()
        .map_err(|e| Error::io(&format!("{what}: cannot resolve host"), &e))?
        .collect();
    let mut last_err = None;
    let mut stream = None;
    for a in &addrs {
        match TcpStream::connect_timeout(a, HANDSHAKE_TIMEOUT) {
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
    )? {
        Event::Hi => {}
        other => {
            return Err(Error::Transport(format!(
                "{what}: expected < hi >, got {other:?}"
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
        match expect(&mut stream, &mut dec, &mut backlog, &what, step)? {
            Event::Ok => {}
            Event::Error(text) => {
                return Err(Error::Transport(format!(
                    "{what}: server refused {step}: {text}"
                )))
            }
            other => {
                return Err(Error::Transport(format!(
                    "{what}: expected < ok > after {step}, got {other:?}"
                )))
            }
        }
    }
    stream
        .set_write_timeout(Some(Duration::from_millis(20)))
        .map_err(|e| Error::io(&what, &e))?;
    let rx = stream
        .try_clone()
        .map_err(|e| Error::io(&format!("{what}: clone socket"), &e))?;
    let mut pending = VecDeque::new();
    for ev in backlog {
        push_event(&mut pending, ev);
    }
    Ok(Opened {
        sink: Box::new(TcpSink {
            stream,
            what: what.clone(),
        }),
        source: Box::new(TcpSource {
            stream: rx,
            dec,
            pending,
            what,
            closed: false,
        }),
        pty_path: None,
    })
}

#[cfg(test)]
mod tests {
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
            while !got.ends_with(b"< send 101 1 FF >") {
                read_msg(&mut s, &mut got);
            }
            String::from_utf8(got).unwrap()
        });
        let Opened {
            mut sink,
            mut source,
            ..
        } = open("127.0.0.1", port, "can0").unwrap();
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
        assert_eq!(transcript, "< open can0 >< rawmode >< send 101 1 FF >");
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
        let e = open("127.0.0.1", port, "nope").err().unwrap();
        assert!(e.to_string().contains("could not open bus"), "{e}");
        server.join().unwrap();
    }
}
