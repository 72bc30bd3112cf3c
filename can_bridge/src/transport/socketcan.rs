//! Linux SocketCAN raw sockets. Writes are non-blocking (a full transmit
//! queue, ENOBUFS, is an error for that tick, never a stall); reads use `poll`
//! with a timeout because `close` does not wake a blocked read.

use super::fd::Fd;
use super::{out_queue, Gate, Health, Opened, Ready, RxItem, Sink, Source, Written};
use crate::error::{Error, Result};
use crate::frame::CanFrame;
use std::ffi::CString;
use std::io;
use std::sync::Arc;

/// `AF_CAN` / `PF_CAN`.
pub const AF_CAN: libc::c_int = 29;
/// `CAN_RAW` protocol.
pub const CAN_RAW: libc::c_int = 1;
/// `SOL_CAN_RAW` = SOL_CAN_BASE + CAN_RAW.
pub const SOL_CAN_RAW: libc::c_int = 101;
/// `CAN_RAW_ERR_FILTER` option.
pub const CAN_RAW_ERR_FILTER: libc::c_int = 2;
/// Extended-frame flag in `can_id`.
pub const CAN_EFF_FLAG: u32 = 0x8000_0000;
/// Remote-frame flag in `can_id`.
pub const CAN_RTR_FLAG: u32 = 0x4000_0000;
/// Error-frame flag in `can_id`.
pub const CAN_ERR_FLAG: u32 = 0x2000_0000;
/// Error classes reported: controller problems, bus-off, restarted.
pub const ERR_MASK: u32 = 0x0000_0004 | 0x0000_0040 | 0x0000_0100;

/// `struct can_frame` (16 bytes, data 8-byte aligned).
#[repr(C, align(8))]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RawCanFrame {
    /// ID with EFF/RTR/ERR flags.
    pub can_id: u32,
    /// Payload length 0..=8.
    pub len: u8,
    /// Padding.
    pub pad: u8,
    /// Reserved.
    pub res0: u8,
    /// DLC 9..15 for lengths of 8 (unused here).
    pub len8_dlc: u8,
    /// Payload.
    pub data: [u8; 8],
}

/// `struct sockaddr_can` (24 bytes).
#[repr(C)]
struct SockaddrCan {
    can_family: libc::sa_family_t,
    can_ifindex: libc::c_int,
    addr: [u64; 2],
}

/// Our frame to the kernel's layout.
pub fn to_raw(f: &CanFrame) -> RawCanFrame {
    let mut id = f.id();
    if f.is_extended() {
        id |= CAN_EFF_FLAG;
    }
    if f.is_remote() {
        id |= CAN_RTR_FLAG;
    }
    let mut data = [0u8; 8];
    data[..f.data().len()].copy_from_slice(f.data());
    RawCanFrame {
        can_id: id,
        len: f.len() as u8,
        data,
        ..RawCanFrame::default()
    }
}

/// The kernel's layout to a receive item (error frames become `BusError`).
pub fn from_raw(r: &RawCanFrame) -> RxItem {
    if r.can_id & CAN_ERR_FLAG != 0 {
        return RxItem::BusError;
    }
    let extended = r.can_id & CAN_EFF_FLAG != 0;
    let id = if extended {
        r.can_id & 0x1FFF_FFFF
    } else {
        r.can_id & 0x7FF
    };
    let len = r.len.min(8);
    let f = if r.can_id & CAN_RTR_FLAG != 0 {
        CanFrame::remote(id, extended, len)
    } else {
        CanFrame::new(id, extended, &r.data[..len as usize])
    };
    f.map_or(RxItem::Malformed, RxItem::Frame)
}

struct CanSink {
    fd: Arc<Fd>,
    what: String,
}

impl Sink for CanSink {
    fn prepare(&mut self) -> Result<Ready> {
        // A frame still in the socket's queue a period after it was written
        // (bus-off, lost arbitration, a stuck controller) is not joined by a
        // newer one that would go out stale behind it.
        let busy = out_queue(self.fd.raw()).is_some_and(|n| n > 0);
        Ok(Ready {
            gate: if busy { Gate::Busy } else { Gate::Open },
            flushed: 0,
        })
    }

    fn write(&mut self, frame: &CanFrame) -> Result<Written> {
        let raw = to_raw(frame);
        let size = std::mem::size_of::<RawCanFrame>();
        // SAFETY: raw is a valid can_frame of `size` bytes.
        let rc = unsafe {
            libc::send(
                self.fd.raw(),
                (&raw as *const RawCanFrame).cast(),
                size,
                libc::MSG_DONTWAIT,
            )
        };
        if rc < 0 {
            let e = io::Error::last_os_error();
            let why = match e.raw_os_error() {
                Some(libc::ENOBUFS) | Some(libc::EAGAIN) => "transmit queue full (frame dropped)",
                Some(libc::ENETDOWN) => "interface is down",
                _ => "send failed",
            };
            return Err(Error::io(&format!("{}: {why}", self.what), &e));
        }
        Ok(Written::Yes)
    }
}

struct CanSource {
    fd: Arc<Fd>,
    what: String,
}

impl Source for CanSource {
    fn recv(&mut self, timeout_ms: i32) -> Result<Option<RxItem>> {
        let rev = self
            .fd
            .poll(libc::POLLIN, timeout_ms)
            .map_err(|e| Error::io(&self.what, &e))?;
        if rev & libc::POLLIN == 0 {
            return Ok(None);
        }
        let mut raw = RawCanFrame::default();
        let size = std::mem::size_of::<RawCanFrame>();
        // SAFETY: raw is writable for `size` bytes.
        let rc = unsafe {
            libc::recv(
                self.fd.raw(),
                (&mut raw as *mut RawCanFrame).cast(),
                size,
                libc::MSG_DONTWAIT,
            )
        };
        if rc < 0 {
            let e = io::Error::last_os_error();
            if matches!(
                e.kind(),
                io::ErrorKind::WouldBlock | io::ErrorKind::Interrupted
            ) {
                return Ok(None);
            }
            return Err(Error::io(&format!("{} read", self.what), &e));
        }
        if rc as usize != size {
            return Ok(Some(RxItem::Malformed));
        }
        Ok(Some(from_raw(&raw)))
    }
}

/// Open a raw CAN socket bound to `iface`.
pub fn open(iface: &str) -> Result<Opened> {
    let what = format!("socketcan {iface}");
    // SAFETY: plain libc call.
    let fd = Fd::new(unsafe { libc::socket(AF_CAN, libc::SOCK_RAW | libc::SOCK_CLOEXEC, CAN_RAW) })
        .map_err(|e| {
            if e.raw_os_error() == Some(libc::EAFNOSUPPORT) {
                Error::Transport(format!(
                    "{what}: socket(AF_CAN) failed: {e}; this kernel has no SocketCAN support (use slcan: or socketcand: instead)"
                ))
            } else {
                Error::io(&format!("{what}: socket(AF_CAN)"), &e)
            }
        })?;
    let name = CString::new(iface)
        .map_err(|_| Error::Config(format!("interface name {iface:?} contains NUL")))?;
    // SAFETY: name is NUL-terminated.
    let index = unsafe { libc::if_nametoindex(name.as_ptr()) };
    if index == 0 {
        return Err(Error::Transport(format!(
            "{what}: no such network interface"
        )));
    }
    let addr = SockaddrCan {
        can_family: AF_CAN as libc::sa_family_t,
        can_ifindex: index as libc::c_int,
        addr: [0; 2],
    };
    // SAFETY: addr is a valid sockaddr_can of the given size.
    let rc = unsafe {
        libc::bind(
            fd.raw(),
            (&addr as *const SockaddrCan).cast(),
            std::mem::size_of::<SockaddrCan>() as libc::socklen_t,
        )
    };
    if rc < 0 {
        return Err(Error::last_os(&format!("{what}: bind")));
    }
    let mask: u32 = ERR_MASK;
    // SAFETY: mask is a valid u32 option value.
    unsafe {
        libc::setsockopt(
            fd.raw(),
            SOL_CAN_RAW,
            CAN_RAW_ERR_FILTER,
            (&mask as *const u32).cast(),
            std::mem::size_of::<u32>() as libc::socklen_t,
        );
    }
    let fd = Arc::new(fd);
    Ok(Opened {
        sink: Box::new(CanSink {
            fd: fd.clone(),
            what: what.clone(),
        }),
        source: Box::new(CanSource { fd, what }),
        pty_path: None,
        health: Arc::new(Health::default()),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn layout_matches_the_kernel() {
        assert_eq!(std::mem::size_of::<RawCanFrame>(), 16);
        assert_eq!(std::mem::offset_of!(RawCanFrame, data), 8);
        assert_eq!(std::mem::size_of::<SockaddrCan>(), 24);
        assert_eq!(std::mem::offset_of!(SockaddrCan, can_ifindex), 4);
    }

    #[test]
    fn frame_conversion_roundtrip() {
        let cases = [
            CanFrame::new(0x101, false, &[1, 2, 3, 4, 5, 6, 7, 8]).unwrap(),
            CanFrame::new(0x1ABC_DEF0, true, &[0xFF]).unwrap(),
            CanFrame::new(0, false, &[]).unwrap(),
            CanFrame::remote(0x7FF, false, 8).unwrap(),
            CanFrame::remote(0x1FFF_FFFF, true, 0).unwrap(),
        ];
        for f in cases {
            let r = to_raw(&f);
            assert_eq!(from_raw(&r), RxItem::Frame(f));
        }
        let r = to_raw(&cases[1]);
        assert_eq!(r.can_id, 0x1ABC_DEF0 | CAN_EFF_FLAG);
        assert_eq!(r.len, 1);
        let r = to_raw(&cases[3]);
        assert_eq!(r.can_id, 0x7FF | CAN_RTR_FLAG);
        let err = RawCanFrame {
            can_id: CAN_ERR_FLAG | 0x40,
            len: 8,
            ..Default::default()
        };
        assert_eq!(from_raw(&err), RxItem::BusError);
        // A corrupt length from the kernel is clamped, never a panic.
        let odd = RawCanFrame {
            can_id: 0x10,
            len: 200,
            ..Default::default()
        };
        assert!(matches!(from_raw(&odd), RxItem::Frame(f) if f.len() == 8));
    }

    #[test]
    fn open_reports_a_clear_error_without_can_support() {
        match open("vcan0") {
            Ok(_) => {} // a kernel with vcan0: nothing to check here
            Err(e) => {
                let s = e.to_string();
                assert!(s.contains("socketcan vcan0"), "{s}");
            }
        }
    }
}
