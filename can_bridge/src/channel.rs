//! The channel string that selects a transport.

use crate::error::{clip, Error, Result};

/// Default serial speed for `slcan:PATH` without `@BAUD`.
pub const DEFAULT_BAUD: u32 = 115_200;

/// A parsed channel string.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum ChannelSpec {
    /// `socketcan:IFACE`: Linux SocketCAN raw socket.
    SocketCan {
        /// Interface name, e.g. `can0`.
        iface: String,
    },
    /// `slcan:PATH[@BAUD]`: an SLCAN serial adapter.
    Slcan {
        /// Device path.
        path: String,
        /// Serial speed.
        baud: u32,
    },
    /// `slcan-pty:`: the bridge plays the SLCAN adapter on a new pseudo-terminal.
    SlcanPty,
    /// `socketcand:HOST:PORT/BUS`: a socketcand gateway over TCP.
    Socketcand {
        /// Host name or address (IPv6 without brackets).
        host: String,
        /// TCP port.
        port: u16,
        /// Bus name on the gateway, e.g. `can0`.
        bus: String,
    },
}

const HELP: &str =
    "expected socketcan:IFACE, slcan:PATH[@BAUD], slcan-pty: or socketcand:HOST:PORT/BUS";

impl ChannelSpec {
    /// Parse a channel string.
    pub fn parse(s: &str) -> Result<Self> {
        let bad = |why: &str| Error::Config(format!("channel {}: {why} ({HELP})", clip(s)));
        let (kind, rest) = s.split_once(':').unwrap_or((s, ""));
        match kind {
            "socketcan" => {
                if rest.is_empty() || rest.len() > 15 || rest.contains(['/', ' ', '\0']) {
                    return Err(bad(
                        "interface name must have 1 to 15 characters, no '/' or space",
                    ));
                }
                Ok(ChannelSpec::SocketCan {
                    iface: rest.to_string(),
                })
            }
            "slcan" => {
                let (path, baud) = match rest.rsplit_once('@') {
                    Some((p, b)) if !b.is_empty() && b.bytes().all(|c| c.is_ascii_digit()) => {
                        let baud: u32 = b.parse().map_err(|_| bad("baud rate out of range"))?;
                        (p, baud)
                    }
                    _ => (rest, DEFAULT_BAUD),
                };
                if path.is_empty() || path.contains('\0') {
                    return Err(bad("missing device path"));
                }
                if baud_constant(baud).is_none() {
                    return Err(bad(&format!("unsupported serial speed {baud}")));
                }
                Ok(ChannelSpec::Slcan {
                    path: path.to_string(),
                    baud,
                })
            }
            "slcan-pty" => {
                if !rest.is_empty() {
                    return Err(bad("slcan-pty takes nothing after the colon"));
                }
                Ok(ChannelSpec::SlcanPty)
            }
            "socketcand" => {
                let (hostport, bus) = rest.rsplit_once('/').ok_or_else(|| bad("missing /BUS"))?;
                let (host, port) = hostport
                    .rsplit_once(':')
                    .ok_or_else(|| bad("missing :PORT"))?;
                let host = host.trim_start_matches('[').trim_end_matches(']');
                let port: u16 = port.parse().map_err(|_| bad("port must be 1..65535"))?;
                if host.is_empty() || port == 0 {
                    return Err(bad("host and a non-zero port are required"));
                }
                if bus.is_empty()
                    || !bus
                        .bytes()
                        .all(|c| c.is_ascii_graphic() && c != b'<' && c != b'>')
                {
                    return Err(bad(
                        "bus name must be non-empty printable ASCII without < >",
                    ));
                }
                Ok(ChannelSpec::Socketcand {
                    host: host.to_string(),
                    port,
                    bus: bus.to_string(),
                })
            }
            _ => Err(bad("unknown transport")),
        }
    }

    /// Channel name written to the candump log.
    pub fn log_name(&self) -> String {
        match self {
            ChannelSpec::SocketCan { iface } => iface.clone(),
            ChannelSpec::Socketcand { bus, .. } => bus.clone(),
            ChannelSpec::Slcan { .. } | ChannelSpec::SlcanPty => "slcan0".to_string(),
        }
    }
}

/// termios speed constant for a baud rate.
pub fn baud_constant(baud: u32) -> Option<libc::speed_t> {
    Some(match baud {
        9600 => libc::B9600,
        19200 => libc::B19200,
        38400 => libc::B38400,
        57600 => libc::B57600,
        115_200 => libc::B115200,
        230_400 => libc::B230400,
        460_800 => libc::B460800,
        500_000 => libc::B500000,
        921_600 => libc::B921600,
        1_000_000 => libc::B1000000,
        2_000_000 => libc::B2000000,
        3_000_000 => libc::B3000000,
        _ => return None,
    })
}

/// SLCAN `S<n>` code for a CAN bit rate.
pub fn slcan_bitrate_code(bitrate: u32) -> Option<u8> {
    Some(match bitrate {
        10_000 => 0,
        20_000 => 1,
        50_000 => 2,
        100_000 => 3,
        125_000 => 4,
        250_000 => 5,
        500_000 => 6,
        800_000 => 7,
        1_000_000 => 8,
        _ => return None,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_all_forms() {
        assert_eq!(
            ChannelSpec::parse("socketcan:can0").unwrap(),
            ChannelSpec::SocketCan {
                iface: "can0".into()
            }
        );
        assert_eq!(
            ChannelSpec::parse("slcan:/dev/ttyACM0@921600").unwrap(),
            ChannelSpec::Slcan {
                path: "/dev/ttyACM0".into(),
                baud: 921_600
            }
        );
        assert_eq!(
            ChannelSpec::parse("slcan:/dev/ttyACM0").unwrap(),
            ChannelSpec::Slcan {
                path: "/dev/ttyACM0".into(),
                baud: DEFAULT_BAUD
            }
        );
        assert_eq!(
            ChannelSpec::parse("slcan-pty:").unwrap(),
            ChannelSpec::SlcanPty
        );
        assert_eq!(
            ChannelSpec::parse("slcan-pty").unwrap(),
            ChannelSpec::SlcanPty
        );
        assert_eq!(
            ChannelSpec::parse("socketcand:127.0.0.1:29536/can0").unwrap(),
            ChannelSpec::Socketcand {
                host: "127.0.0.1".into(),
                port: 29536,
                bus: "can0".into()
            }
        );
        assert_eq!(
            ChannelSpec::parse("socketcand:[::1]:29536/vcan1").unwrap(),
            ChannelSpec::Socketcand {
                host: "::1".into(),
                port: 29536,
                bus: "vcan1".into()
            }
        );
    }

    #[test]
    fn rejects_bad_strings() {
        for s in [
            "",
            "can0",
            "socketcan:",
            "socketcan:averyveryverylongname",
            "slcan:",
            "slcan:/dev/x@123",
            "slcan-pty:/dev/x",
            "socketcand:host:1",
            "socketcand:host/can0",
            "socketcand:host:0/can0",
            "socketcand:host:99999/can0",
            "socketcand::29536/can0",
            "socketcand:h:1/",
            "udp_multicast:x",
        ] {
            let e = ChannelSpec::parse(s).unwrap_err();
            assert!(matches!(e, Error::Config(_)), "{s}");
            assert!(e.to_string().contains("expected"), "{s}: {e}");
        }
    }
}
