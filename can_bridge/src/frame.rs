//! Classic CAN frames (up to 8 data bytes), independent of any transport.

use crate::error::{Error, Result};

/// Largest 11-bit identifier.
pub const MAX_STD_ID: u32 = 0x7FF;
/// Largest 29-bit identifier.
pub const MAX_EXT_ID: u32 = 0x1FFF_FFFF;

/// A classic CAN frame. Invariants (checked by the constructors): the ID fits
/// its format and `len <= 8`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct CanFrame {
    id: u32,
    extended: bool,
    rtr: bool,
    len: u8,
    data: [u8; 8],
}

fn check_id(id: u32, extended: bool) -> Result<()> {
    let max = if extended { MAX_EXT_ID } else { MAX_STD_ID };
    if id > max {
        return Err(Error::Config(format!(
            "CAN id {id:#x} does not fit a {} identifier",
            if extended { "29-bit" } else { "11-bit" }
        )));
    }
    Ok(())
}

impl CanFrame {
    /// A data frame. Fails if the ID does not fit or `data` is longer than 8 bytes.
    pub fn new(id: u32, extended: bool, data: &[u8]) -> Result<Self> {
        check_id(id, extended)?;
        if data.len() > 8 {
            return Err(Error::Config(format!(
                "CAN payload of {} bytes exceeds 8",
                data.len()
            )));
        }
        let mut buf = [0u8; 8];
        buf[..data.len()].copy_from_slice(data);
        Ok(CanFrame {
            id,
            extended,
            rtr: false,
            len: data.len() as u8,
            data: buf,
        })
    }

    /// A remote (RTR) frame with the given DLC.
    pub fn remote(id: u32, extended: bool, len: u8) -> Result<Self> {
        check_id(id, extended)?;
        if len > 8 {
            return Err(Error::Config(format!("CAN DLC {len} exceeds 8")));
        }
        Ok(CanFrame {
            id,
            extended,
            rtr: true,
            len,
            data: [0; 8],
        })
    }

    /// Identifier (without format flags).
    pub fn id(&self) -> u32 {
        self.id
    }
    /// True for a 29-bit identifier.
    pub fn is_extended(&self) -> bool {
        self.extended
    }
    /// True for a remote frame.
    pub fn is_remote(&self) -> bool {
        self.rtr
    }
    /// Data length code (0..=8).
    pub fn len(&self) -> usize {
        self.len as usize
    }
    /// True when the frame carries no data bytes.
    pub fn is_empty(&self) -> bool {
        self.len == 0
    }
    /// The payload (empty for remote frames).
    pub fn data(&self) -> &[u8] {
        if self.rtr {
            &[]
        } else {
            &self.data[..self.len as usize]
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rejects_bad_ids_and_lengths() {
        assert!(CanFrame::new(0x800, false, &[]).is_err());
        assert!(CanFrame::new(0x800, true, &[]).is_ok());
        assert!(CanFrame::new(0x2000_0000, true, &[]).is_err());
        assert!(CanFrame::new(1, false, &[0; 9]).is_err());
        assert!(CanFrame::remote(1, false, 9).is_err());
        let f = CanFrame::new(0x123, false, &[1, 2, 3]).unwrap();
        assert_eq!(f.data(), &[1, 2, 3]);
        assert_eq!(f.len(), 3);
        let r = CanFrame::remote(0x123, false, 4).unwrap();
        assert!(r.data().is_empty());
        assert_eq!(r.len(), 4);
    }
}
