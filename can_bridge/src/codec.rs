//! The messages of the shipped DBC (`python/can_bridge/can_bridge.dbc`) as
//! static tables, with little-endian (Intel) signal packing that agrees with
//! cantools: raw = round_half_even((value - offset) / factor).

use crate::e2e;
use crate::error::{Error, Result};
use crate::frame::CanFrame;

/// One signal: little-endian, `len` bits from bit `start` (DBC numbering).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Signal {
    /// Name as in the DBC.
    pub name: &'static str,
    /// Start bit (least significant bit, DBC little-endian numbering).
    pub start: u32,
    /// Length in bits (1..=32).
    pub len: u32,
    /// Two's complement when true.
    pub signed: bool,
    /// Physical = raw * factor + offset.
    pub factor: f64,
    /// Physical offset.
    pub offset: f64,
    /// Physical minimum from the DBC.
    pub min: f64,
    /// Physical maximum from the DBC.
    pub max: f64,
}

const fn sig(
    name: &'static str,
    start: u32,
    len: u32,
    signed: bool,
    factor: f64,
    min: f64,
    max: f64,
) -> Signal {
    Signal {
        name,
        start,
        len,
        signed,
        factor,
        offset: 0.0,
        min,
        max,
    }
}

impl Signal {
    /// Smallest raw value the bit field holds.
    pub fn raw_min(&self) -> i64 {
        if self.signed {
            -(1i64 << (self.len - 1))
        } else {
            0
        }
    }

    /// Largest raw value the bit field holds.
    pub fn raw_max(&self) -> i64 {
        if self.signed {
            (1i64 << (self.len - 1)) - 1
        } else {
            (1i64 << self.len) - 1
        }
    }

    /// Physical to raw, as cantools does; fails on non-finite values and on
    /// values outside the field.
    pub fn to_raw(&self, value: f64) -> Result<i64> {
        if !value.is_finite() {
            return Err(Error::Command(format!(
                "{} = {value} is not a finite number",
                self.name
            )));
        }
        let raw = ((value - self.offset) / self.factor).round_ties_even();
        if raw < self.raw_min() as f64 || raw > self.raw_max() as f64 {
            return Err(Error::Command(format!(
                "{} = {value} does not fit the {}-bit field",
                self.name, self.len
            )));
        }
        Ok(raw as i64)
    }

    /// Raw to physical.
    pub fn to_phys(&self, raw: i64) -> f64 {
        raw as f64 * self.factor + self.offset
    }

    /// Write `raw` (truncated to the field width) into `data`.
    pub fn put_raw(&self, data: &mut [u8; 8], raw: i64) {
        let mask: u64 = (1u64 << self.len) - 1;
        let mut word = u64::from_le_bytes(*data);
        word &= !(mask << self.start);
        word |= ((raw as u64) & mask) << self.start;
        *data = word.to_le_bytes();
    }

    /// Read the raw value (sign-extended) from `data` (missing bytes read as 0).
    pub fn get_raw(&self, data: &[u8]) -> i64 {
        let mut buf = [0u8; 8];
        let n = data.len().min(8);
        buf[..n].copy_from_slice(&data[..n]);
        let word = u64::from_le_bytes(buf);
        let mask: u64 = (1u64 << self.len) - 1;
        let v = (word >> self.start) & mask;
        if self.signed && (v >> (self.len - 1)) & 1 == 1 {
            (v | !mask) as i64
        } else {
            v as i64
        }
    }

    /// Physical value read from `data`.
    pub fn get(&self, data: &[u8]) -> f64 {
        self.to_phys(self.get_raw(data))
    }

    /// Whether the signal counts in ones (factor 1, integer offset): an
    /// enum-like signal such as `Mode`, where rounding 2.6 would change its
    /// meaning. (The torques' factor 2 is a resolution: they are rounded.)
    pub fn is_integer_valued(&self) -> bool {
        self.factor == 1.0 && self.offset.fract() == 0.0
    }

    /// Refuse what the DBC does not allow for this signal: a non-finite
    /// value, a value outside `min..=max`, or a non-integral value for an
    /// integer-valued signal (which would otherwise be rounded).
    pub fn check(&self, value: f64) -> Result<()> {
        if !value.is_finite() {
            return Err(Error::Command(format!(
                "{} = {value} is not a finite number",
                self.name
            )));
        }
        if value < self.min || value > self.max {
            return Err(Error::Command(format!(
                "{} = {value} is outside the signal's range {}..={}",
                self.name, self.min, self.max
            )));
        }
        if self.is_integer_valued() && value.fract() != 0.0 {
            return Err(Error::Command(format!(
                "{} = {value} is not an integer (the signal takes integer values {}..={})",
                self.name, self.min, self.max
            )));
        }
        Ok(())
    }
}

/// One message of the DBC.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Message {
    /// Name as in the DBC.
    pub name: &'static str,
    /// 11-bit CAN identifier.
    pub id: u32,
    /// Payload length in bytes.
    pub len: usize,
    /// E2E Data ID (DBC attribute `E2EDataID`).
    pub data_id: u16,
    /// Send period, ms (DBC attribute `GenMsgCycleTime`).
    pub cycle_ms: u32,
    /// Signals in DBC order.
    pub signals: &'static [Signal],
}

const CRC: Signal = sig("CRC", 0, 8, false, 1.0, 0.0, 255.0);
const COUNTER: Signal = sig("Counter", 8, 4, false, 1.0, 0.0, 14.0);

/// `WheelTorqueCmd`, sent by the bridge every tick.
pub const WHEEL_TORQUE_CMD: Message = Message {
    name: "WheelTorqueCmd",
    id: 0x101,
    len: 8,
    data_id: 3073,
    cycle_ms: 50,
    signals: &[
        CRC,
        COUNTER,
        sig("Mode", 12, 2, false, 1.0, 0.0, 3.0),
        sig("TorqueFL", 16, 12, true, 2.0, -4096.0, 4094.0),
        sig("TorqueFR", 28, 12, true, 2.0, -4096.0, 4094.0),
        sig("TorqueRL", 40, 12, true, 2.0, -4096.0, 4094.0),
        sig("TorqueRR", 52, 12, true, 2.0, -4096.0, 4094.0),
    ],
};

/// `VehicleMotion`: longitudinal and lateral speed (m/s), yaw rate (rad/s).
pub const VEHICLE_MOTION: Message = Message {
    name: "VehicleMotion",
    id: 0x201,
    len: 8,
    data_id: 3089,
    cycle_ms: 20,
    signals: &[
        CRC,
        COUNTER,
        sig("LongSpeed", 16, 16, true, 0.01, -20.0, 90.0),
        sig("LatSpeed", 32, 16, true, 0.01, -20.0, 20.0),
        sig("YawRate", 48, 16, true, 0.001, -3.0, 3.0),
    ],
};

/// `WheelSpeeds`: the four wheel angular speeds (rad/s).
pub const WHEEL_SPEEDS: Message = Message {
    name: "WheelSpeeds",
    id: 0x202,
    len: 8,
    data_id: 3090,
    cycle_ms: 20,
    signals: &[
        CRC,
        COUNTER,
        sig("WheelSpeedFL", 16, 12, true, 0.1, -60.0, 204.7),
        sig("WheelSpeedFR", 28, 12, true, 0.1, -60.0, 204.7),
        sig("WheelSpeedRL", 40, 12, true, 0.1, -60.0, 204.7),
        sig("WheelSpeedRR", 52, 12, true, 0.1, -60.0, 204.7),
    ],
};

/// `SteeringState`: front road-wheel steering angle (rad).
pub const STEERING_STATE: Message = Message {
    name: "SteeringState",
    id: 0x203,
    len: 4,
    data_id: 3091,
    cycle_ms: 20,
    signals: &[
        CRC,
        COUNTER,
        sig("SteeringAngle", 16, 16, true, 0.0001, -1.0, 1.0),
    ],
};

/// `VehicleAccel`: body-frame longitudinal and lateral acceleration at the
/// centre of gravity (m/s^2, IMU).
pub const VEHICLE_ACCEL: Message = Message {
    name: "VehicleAccel",
    id: 0x204,
    len: 6,
    data_id: 3092,
    cycle_ms: 20,
    signals: &[
        CRC,
        COUNTER,
        sig("LongAccel", 16, 16, true, 0.001, -20.0, 20.0),
        sig("LatAccel", 32, 16, true, 0.001, -20.0, 20.0),
    ],
};

/// `DriverDemand`: the driver's rear-axle torque request (Nm), the cruise
/// set speed (m/s) and the road-friction estimate the vehicle publishes.
pub const DRIVER_DEMAND: Message = Message {
    name: "DriverDemand",
    id: 0x205,
    len: 8,
    data_id: 3093,
    cycle_ms: 20,
    signals: &[
        CRC,
        COUNTER,
        sig("DriverTorque", 16, 16, true, 0.5, -8000.0, 8000.0),
        sig("SetSpeed", 32, 16, true, 0.01, 0.0, 90.0),
        sig("RoadFriction", 48, 8, false, 0.01, 0.05, 2.0),
    ],
};

/// Every message of the DBC.
pub const ALL_MESSAGES: [&Message; 6] = [
    &WHEEL_TORQUE_CMD,
    &VEHICLE_MOTION,
    &WHEEL_SPEEDS,
    &STEERING_STATE,
    &VEHICLE_ACCEL,
    &DRIVER_DEMAND,
];

/// Number of received messages.
pub const N_RX: usize = 5;

/// The received messages, in the order of [`crate::bridge::RX_NAMES`] and
/// of `VehicleState::status`.
pub const RX_MESSAGES: [&Message; N_RX] = [
    &VEHICLE_MOTION,
    &WHEEL_SPEEDS,
    &STEERING_STATE,
    &VEHICLE_ACCEL,
    &DRIVER_DEMAND,
];

/// Safety state carried in `WheelTorqueCmd.Mode`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
#[repr(u8)]
pub enum Mode {
    /// Following fresh commands.
    Active = 0,
    /// Command late: last output held.
    Hold = 1,
    /// Command missing: zero torque.
    Safe = 2,
    /// Latched after a long silence: zero torque until `reset_fault`.
    Fault = 3,
}

impl Mode {
    /// The DBC value name.
    pub fn name(self) -> &'static str {
        match self {
            Mode::Active => "active",
            Mode::Hold => "hold",
            Mode::Safe => "safe",
            Mode::Fault => "fault",
        }
    }
}

impl Message {
    /// The signal called `name`.
    pub fn signal(&self, name: &str) -> Option<&Signal> {
        self.signals.iter().find(|s| s.name == name)
    }

    /// Pack physical values (one per non-E2E signal, in DBC order after CRC and
    /// Counter) and protect with `counter`.
    pub fn encode(&self, values: &[f64], counter: u8) -> Result<CanFrame> {
        let payload_signals = self.signals.get(2..).unwrap_or(&[]);
        if values.len() != payload_signals.len() {
            return Err(Error::Command(format!(
                "{} takes {} values, got {}",
                self.name,
                payload_signals.len(),
                values.len()
            )));
        }
        let mut data = [0u8; 8];
        for (s, &v) in payload_signals.iter().zip(values) {
            s.put_raw(&mut data, s.to_raw(v)?);
        }
        e2e::protect(&mut data[..self.len], self.data_id, counter);
        CanFrame::new(self.id, false, &data[..self.len])
    }

    /// Like [`Message::encode`], but strict about its input: the counter
    /// must be an E2E Profile 1 alive counter (0..=14, never reduced) and
    /// every value must pass [`Signal::check`] (DBC range, integer-valued
    /// signals given integers).
    pub fn encode_checked(&self, values: &[f64], counter: u8) -> Result<CanFrame> {
        if counter > e2e::MAX_COUNTER {
            return Err(Error::Command(format!(
                "counter = {counter} is not an E2E Profile 1 alive counter (0..={})",
                e2e::MAX_COUNTER
            )));
        }
        let payload_signals = self.signals.get(2..).unwrap_or(&[]);
        for (s, &v) in payload_signals.iter().zip(values) {
            s.check(v)?;
        }
        self.encode(values, counter)
    }

    /// Physical values of the non-E2E signals (no E2E check here).
    pub fn decode_values(&self, data: &[u8], out: &mut [f64]) {
        let payload_signals = self.signals.get(2..).unwrap_or(&[]);
        for (s, o) in payload_signals.iter().zip(out.iter_mut()) {
            *o = s.get(data);
        }
    }

    /// The first decoded value outside its signal's DBC `[min|max]` (the
    /// plausibility bounds of a received message), as (signal, value).
    pub fn implausible(&self, values: &[f64]) -> Option<(&'static str, f64)> {
        let payload_signals = self.signals.get(2..).unwrap_or(&[]);
        payload_signals
            .iter()
            .zip(values)
            .find(|(s, &v)| !(s.min..=s.max).contains(&v))
            .map(|(s, &v)| (s.name, v))
    }
}

/// Frame `WheelTorqueCmd`. `torques_nm` must already be limited to the
/// actuators (the limiter works on the signals' 2 Nm grid, so nothing is rounded here).
pub fn encode_torque_cmd(torques_nm: &[f64; 4], mode: Mode, counter: u8) -> Result<CanFrame> {
    let v = [
        f64::from(mode as u8),
        torques_nm[0],
        torques_nm[1],
        torques_nm[2],
        torques_nm[3],
    ];
    WHEEL_TORQUE_CMD.encode(&v, counter)
}

#[cfg(test)]
mod tests {
    use super::*;

    const DBC: &str = include_str!("../python/can_bridge/can_bridge.dbc");

    /// Parse `BO_`, `SG_` and `BA_ "E2EDataID"` lines of the shipped DBC and
    /// check the static tables against them, so the two cannot drift apart.
    #[test]
    fn tables_match_shipped_dbc() {
        let mut current: Option<&Message> = None;
        let mut seen_signals = 0;
        let mut seen_ids = 0;
        let mut seen_cycles = 0;
        for line in DBC.lines() {
            let t = line.trim();
            if let Some(rest) = t.strip_prefix("BO_ ") {
                let mut it = rest.split_whitespace();
                let id: u32 = it.next().unwrap().parse().unwrap();
                let name = it.next().unwrap().trim_end_matches(':');
                let len: usize = it.next().unwrap().parse().unwrap();
                let m = ALL_MESSAGES.iter().find(|m| m.id == id).unwrap();
                assert_eq!(m.name, name);
                assert_eq!(m.len, len);
                current = Some(m);
            } else if let Some(rest) = t.strip_prefix("SG_ ") {
                let m = current.unwrap();
                let (name, rest) = rest.split_once(" : ").unwrap();
                let s = m.signal(name.trim()).unwrap();
                let (layout, rest) = rest.split_once(' ').unwrap();
                let (start, rest2) = layout.split_once('|').unwrap();
                let (len, fmt) = rest2.split_once('@').unwrap();
                assert_eq!(s.start, start.parse::<u32>().unwrap(), "{name}");
                assert_eq!(s.len, len.parse::<u32>().unwrap(), "{name}");
                assert_eq!(&fmt[..1], "1", "{name} must be little-endian");
                assert_eq!(s.signed, &fmt[1..] == "-", "{name}");
                let fo = rest.trim().strip_prefix('(').unwrap();
                let (fo, rest) = fo.split_once(')').unwrap();
                let (f, o) = fo.split_once(',').unwrap();
                assert_eq!(s.factor, f.parse::<f64>().unwrap(), "{name}");
                assert_eq!(s.offset, o.parse::<f64>().unwrap(), "{name}");
                let mm = rest.trim().strip_prefix('[').unwrap();
                let (mm, _) = mm.split_once(']').unwrap();
                let (lo, hi) = mm.split_once('|').unwrap();
                assert_eq!(s.min, lo.parse::<f64>().unwrap(), "{name}");
                assert_eq!(s.max, hi.parse::<f64>().unwrap(), "{name}");
                seen_signals += 1;
            } else if let Some(rest) = t.strip_prefix("BA_ \"GenMsgCycleTime\" BO_ ") {
                let mut it = rest.trim_end_matches(';').split_whitespace();
                let id: u32 = it.next().unwrap().parse().unwrap();
                let ms: u32 = it.next().unwrap().parse().unwrap();
                let m = ALL_MESSAGES.iter().find(|m| m.id == id).unwrap();
                assert_eq!(m.cycle_ms, ms, "{}", m.name);
                seen_cycles += 1;
            } else if let Some(rest) = t.strip_prefix("BA_ \"E2EDataID\" BO_ ") {
                let mut it = rest.trim_end_matches(';').split_whitespace();
                let id: u32 = it.next().unwrap().parse().unwrap();
                let did: u16 = it.next().unwrap().parse().unwrap();
                let m = ALL_MESSAGES.iter().find(|m| m.id == id).unwrap();
                assert_eq!(m.data_id, did, "{}", m.name);
                seen_ids += 1;
            }
        }
        let total: usize = ALL_MESSAGES.iter().map(|m| m.signals.len()).sum();
        assert_eq!(seen_signals, total);
        assert_eq!(seen_ids, ALL_MESSAGES.len());
        assert_eq!(seen_cycles, ALL_MESSAGES.len());
    }

    /// Bytes produced by cantools 45.1 (`db.encode_message`) for the same
    /// values, with CRC/Counter then filled in by `autosar-e2e`.
    #[test]
    fn packing_matches_cantools_example() {
        // cantools 45.1: WheelTorqueCmd {CRC:0, Counter:3, Mode:hold, FL:-12,
        // FR:100, RL:0, RR:4000} -> 00 13 fa 2f 03 00 00 7d (CRC not yet set).
        let mut data = [0u8; 8];
        let m = &WHEEL_TORQUE_CMD;
        for (name, v) in [
            ("Counter", 3.0),
            ("Mode", 1.0),
            ("TorqueFL", -12.0),
            ("TorqueFR", 100.0),
            ("TorqueRL", 0.0),
            ("TorqueRR", 4000.0),
        ] {
            let s = m.signal(name).unwrap();
            s.put_raw(&mut data, s.to_raw(v).unwrap());
        }
        assert_eq!(data, [0x00, 0x13, 0xfa, 0x2f, 0x03, 0x00, 0x00, 0x7d]);
        let f = encode_torque_cmd(&[-12.0, 100.0, 0.0, 4000.0], Mode::Hold, 3).unwrap();
        assert_eq!(&f.data()[1..], &data[1..]);
        assert!(e2e::crc_ok(f.data(), m.data_id));
    }

    /// Bytes produced by cantools 45.1 + `autosar-e2e` (counter 7) for the
    /// two sensor messages added last; the Rust tables must agree.
    #[test]
    fn accel_and_driver_demand_match_cantools_example() {
        let f = DRIVER_DEMAND.encode(&[-1234.5, 17.25, 0.35], 7).unwrap();
        assert_eq!(f.data(), [0x18, 0x07, 0x5b, 0xf6, 0xbd, 0x06, 0x23, 0x00]);
        let f = VEHICLE_ACCEL.encode(&[-3.21, 7.5], 7).unwrap();
        assert_eq!(f.data(), [0x93, 0x07, 0x76, 0xf3, 0x4c, 0x1d]);
        let mut out = [0.0; 2];
        VEHICLE_ACCEL.decode_values(f.data(), &mut out);
        assert!((out[0] + 3.21).abs() < 1e-12 && (out[1] - 7.5).abs() < 1e-12);
        assert_eq!(VEHICLE_ACCEL.implausible(&out), None);
        assert_eq!(
            DRIVER_DEMAND.implausible(&[0.0, 10.0, 0.04]),
            Some(("RoadFriction", 0.04))
        );
        assert_eq!(
            DRIVER_DEMAND.implausible(&[0.0, -0.01, 1.0]),
            Some(("SetSpeed", -0.01))
        );
    }

    /// The receiver keeps at most four values per message.
    #[test]
    fn received_messages_fit_the_receive_slots() {
        for m in RX_MESSAGES {
            assert!(m.signals.len() - 2 <= 4, "{}", m.name);
            assert!(m.len <= 8, "{}", m.name);
        }
        let mut ids: Vec<u32> = ALL_MESSAGES.iter().map(|m| m.id).collect();
        ids.sort_unstable();
        ids.dedup();
        assert_eq!(ids.len(), ALL_MESSAGES.len());
    }

    #[test]
    fn round_half_even_like_python() {
        let s = WHEEL_TORQUE_CMD.signal("TorqueFL").unwrap();
        // 1 / 2 = 0.5 -> 0 ; 3 / 2 = 1.5 -> 2 ; -1 -> -0.5 -> 0
        assert_eq!(s.to_raw(1.0).unwrap(), 0);
        assert_eq!(s.to_raw(3.0).unwrap(), 2);
        assert_eq!(s.to_raw(-1.0).unwrap(), 0);
        assert_eq!(s.to_raw(-3.0).unwrap(), -2);
        assert!(s.to_raw(f64::NAN).is_err());
        assert!(s.to_raw(f64::INFINITY).is_err());
        assert!(s.to_raw(4095.0).is_err());
        assert_eq!(s.to_raw(4094.0).unwrap(), 2047);
        assert_eq!(s.to_raw(-4096.0).unwrap(), -2048);
    }

    #[test]
    fn signed_roundtrip_all_raw_values() {
        for m in ALL_MESSAGES {
            for s in m.signals {
                for raw in [s.raw_min(), -1, 0, 1, s.raw_max()] {
                    if raw < s.raw_min() {
                        continue;
                    }
                    let mut d = [0xA5u8; 8];
                    s.put_raw(&mut d, raw);
                    assert_eq!(s.get_raw(&d), raw, "{}", s.name);
                }
            }
        }
    }

    #[test]
    fn encode_checked_refuses_counter_range_and_fractional_integers() {
        let ok = [1.0, 1.0, 1.0, 1.0, 1.0];
        let f = WHEEL_TORQUE_CMD.encode_checked(&ok, 14).unwrap();
        assert_eq!(e2e::counter_of(f.data()), Some(14));
        for counter in [15u8, 200] {
            let e = WHEEL_TORQUE_CMD.encode_checked(&ok, counter).unwrap_err();
            assert!(e.message().contains(&format!("counter = {counter}")), "{e}");
        }
        let e = WHEEL_TORQUE_CMD
            .encode_checked(&[0.0, 4095.0, 1.0, 1.0, 1.0], 0)
            .unwrap_err();
        assert!(e.message().contains("TorqueFL = 4095"), "{e}");
        assert!(e.message().contains("-4096..=4094"), "{e}");
        let e = WHEEL_TORQUE_CMD
            .encode_checked(&[2.6, 1.0, 1.0, 1.0, 1.0], 0)
            .unwrap_err();
        assert!(e.message().contains("Mode = 2.6 is not an integer"), "{e}");
        // Limits themselves and off-grid torques (rounded) are fine.
        WHEEL_TORQUE_CMD
            .encode_checked(&[3.0, -4096.0, 4094.0, 0.3, 0.25], 0)
            .unwrap();
        let e = STEERING_STATE.encode_checked(&[f64::NAN], 0).unwrap_err();
        assert!(e.message().contains("not a finite number"), "{e}");
    }

    #[test]
    fn wrong_value_count_is_an_error() {
        assert!(VEHICLE_MOTION.encode(&[1.0], 0).is_err());
        let f = STEERING_STATE.encode(&[0.5], 4).unwrap();
        assert_eq!(f.len(), 4);
        let mut out = [0.0];
        STEERING_STATE.decode_values(f.data(), &mut out);
        assert!((out[0] - 0.5).abs() < 1e-12);
    }
}
