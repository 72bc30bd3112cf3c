//! The one conversion layer between Python objects and the Rust core.
//!
//! **In.** Every argument is read by one function per kind ([`real`],
//! [`four_reals`], [`int_in`], ...), which refuses what Python would
//! silently coerce (a `bool` for a number, a complex number, a mapping or a
//! set for an ordered sequence) with an [`Error`] naming the argument; the
//! constructor's keyword settings are one table ([`SETTINGS`]) from a name to
//! the kind it is read as and the field it sets. Quoted input is cut short,
//! so a huge argument never makes a huge message.
//!
//! **Out.** The received state and the counters become dicts here
//! ([`state_dict`], [`stats_dict`]), keyed as the shipped stubs declare
//! (`test_stats_keys_match_stub`).

use crate::bridge::{BridgeConfig, OnTransportLoss, Stats, TransportState, VehicleState, RX_NAMES};
use crate::codec::{Message, Mode};
use crate::error::Error;
use crate::safety::{LimitRule, WheelLimits};
use pyo3::exceptions::PyOverflowError;
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyBool, PyBytes, PyDict, PyString, PyType};
use std::path::PathBuf;

/// Which error kind a refused argument raises: a setting (`ConfigError`) or
/// a command (`CommandError`).
pub type Kind = fn(String) -> Error;

/// `repr(obj)` cut to a readable length (a huge integer has hundreds of digits).
pub fn short_repr(obj: &Bound<'_, PyAny>) -> String {
    let r = obj
        .repr()
        .map_or_else(|_| "?".to_string(), |r| r.to_string());
    if r.chars().count() <= 40 {
        r
    } else {
        let head: String = r.chars().take(20).collect();
        format!("{head}... ({} characters)", r.chars().count())
    }
}

/// Python's `bool` and NumPy's `bool_`: integers to Python, never a torque,
/// a sequence number or a setting.
fn is_bool(obj: &Bound<'_, PyAny>) -> bool {
    obj.is_instance_of::<PyBool>()
        || obj
            .get_type()
            .name()
            .is_ok_and(|n| n == "bool" || n == "bool_")
}

/// The abstract base classes the argument checks use.
#[derive(Clone, Copy)]
enum Abc {
    Complex,
    Real,
    Mapping,
    Set,
}

/// Whether `obj` is an instance of `abc` (false if the lookup fails). Each
/// ABC is imported once per interpreter and cached.
fn is_abc(obj: &Bound<'_, PyAny>, abc: Abc) -> bool {
    static COMPLEX: PyOnceLock<Py<PyType>> = PyOnceLock::new();
    static REAL: PyOnceLock<Py<PyType>> = PyOnceLock::new();
    static MAPPING: PyOnceLock<Py<PyType>> = PyOnceLock::new();
    static SET: PyOnceLock<Py<PyType>> = PyOnceLock::new();
    let (cell, module, name) = match abc {
        Abc::Complex => (&COMPLEX, "numbers", "Complex"),
        Abc::Real => (&REAL, "numbers", "Real"),
        Abc::Mapping => (&MAPPING, "collections.abc", "Mapping"),
        Abc::Set => (&SET, "collections.abc", "Set"),
    };
    cell.import(obj.py(), module, name)
        .and_then(|cls| obj.is_instance(cls.as_any()))
        .unwrap_or(false)
}

/// Why an object is not accepted as one real number.
enum NotReal {
    /// Not a real number at all (also a bool or a complex number).
    Type,
    /// A real number too large for a float (e.g. `10**400`).
    OutOfRange,
}

/// One real number: refuses bools and complex numbers (whose `float()`
/// would drop the imaginary part); tells an overflowing number apart.
fn real_or(item: &Bound<'_, PyAny>) -> Result<f64, NotReal> {
    if is_bool(item) {
        return Err(NotReal::Type);
    }
    if is_abc(item, Abc::Complex) && !is_abc(item, Abc::Real) {
        return Err(NotReal::Type);
    }
    item.extract().map_err(|e: PyErr| {
        if e.is_instance_of::<PyOverflowError>(item.py()) {
            NotReal::OutOfRange
        } else {
            NotReal::Type
        }
    })
}

/// One real number named `name`.
pub fn real(obj: &Bound<'_, PyAny>, name: &str, kind: Kind) -> Result<f64, Error> {
    real_or(obj).map_err(|why| match why {
        NotReal::Type => kind(format!(
            "{name} must be a real number, got {}",
            short_repr(obj)
        )),
        NotReal::OutOfRange => kind(format!(
            "{name} = {} is out of range (too large for a float)",
            short_repr(obj)
        )),
    })
}

/// Exactly four real numbers (FL, FR, RL, RR) from an ordered iterable.
pub fn four_reals(obj: &Bound<'_, PyAny>, what: &str, kind: Kind) -> Result<[f64; 4], Error> {
    if obj.is_instance_of::<PyString>() || obj.is_instance_of::<PyBytes>() {
        return Err(kind(format!(
            "{what} must be 4 numbers (FL, FR, RL, RR), not a string"
        )));
    }
    if is_abc(obj, Abc::Mapping) || is_abc(obj, Abc::Set) {
        return Err(kind(format!(
            "{what} must be an ordered sequence of 4 numbers (FL, FR, RL, RR), not a {}",
            obj.get_type()
                .name()
                .map_or_else(|_| "mapping or set".to_string(), |n| n.to_string())
        )));
    }
    let iter = obj.try_iter().map_err(|_| {
        kind(format!(
            "{what} must be a sequence of 4 numbers (FL, FR, RL, RR)"
        ))
    })?;
    let mut out = [0.0; 4];
    let mut n = 0usize;
    for item in iter {
        let item = item.map_err(|e| kind(format!("{what}: {e}")))?;
        let v = real_or(&item).map_err(|why| match why {
            NotReal::Type => kind(format!(
                "{what}[{n}] = {} is not a real number",
                short_repr(&item)
            )),
            NotReal::OutOfRange => kind(format!(
                "{what}[{n}] = {} is out of range (too large for a float)",
                short_repr(&item)
            )),
        })?;
        if let Some(slot) = out.get_mut(n) {
            *slot = v;
        }
        n += 1;
        if n > 4 {
            break;
        }
    }
    if n != 4 {
        return Err(kind(format!(
            "{what} must have exactly 4 values (FL, FR, RL, RR), got {}",
            if n > 4 {
                "more".to_string()
            } else {
                n.to_string()
            }
        )));
    }
    Ok(out)
}

/// A per-wheel setting: one number for all four wheels, or four.
pub fn per_wheel(obj: &Bound<'_, PyAny>, name: &str) -> Result<[f64; 4], Error> {
    match real_or(obj) {
        Ok(v) => Ok([v; 4]),
        Err(NotReal::OutOfRange) => Err(Error::Config(format!(
            "{name} = {} is out of range (too large for a float)",
            short_repr(obj)
        ))),
        Err(NotReal::Type) if is_bool(obj) => Err(Error::Config(format!(
            "{name} must be a real number or 4 of them, got {}",
            short_repr(obj)
        ))),
        Err(NotReal::Type) => four_reals(obj, name, Error::Config),
    }
}

/// An integer in `lo..=hi` (never a bool).
pub fn int_in(obj: &Bound<'_, PyAny>, name: &str, lo: i64, hi: i64) -> Result<i64, Error> {
    let v = if is_bool(obj) {
        None
    } else {
        obj.extract::<i64>().ok()
    };
    match v {
        Some(v) if (lo..=hi).contains(&v) => Ok(v),
        _ => Err(Error::Config(format!(
            "{name} must be an integer in {lo}..={hi}, got {}",
            short_repr(obj)
        ))),
    }
}

/// A command's sequence number: an integer in `0..2**64` (the bridge then
/// bounds it further), never a bool.
pub fn seq(obj: &Bound<'_, PyAny>) -> Result<u64, Error> {
    let v = if is_bool(obj) {
        None
    } else {
        obj.extract::<u64>().ok()
    };
    v.ok_or_else(|| {
        Error::Command(format!(
            "seq must be an integer in 0..2**63, got {}",
            short_repr(obj)
        ))
    })
}

/// A small non-negative integer such as a counter or a Data ID, in `0..=hi`
/// (never a bool); `None` if it is not one.
pub fn small_uint(obj: &Bound<'_, PyAny>, hi: u16) -> Option<u16> {
    if is_bool(obj) {
        return None;
    }
    obj.extract::<i64>()
        .ok()
        .and_then(|v| u16::try_from(v).ok())
        .filter(|v| *v <= hi)
}

/// A `str`.
pub fn string(obj: &Bound<'_, PyAny>, name: &str, want: &str) -> Result<String, Error> {
    obj.extract()
        .map_err(|_| Error::Config(format!("{name} must be {want}, got {}", short_repr(obj))))
}

/// A `str` or `os.PathLike`.
pub fn path(obj: &Bound<'_, PyAny>, name: &str) -> Result<PathBuf, Error> {
    obj.extract().map_err(|_| {
        Error::Config(format!(
            "{name} must be a str or os.PathLike, got {}",
            short_repr(obj)
        ))
    })
}

/// A real `bool` (not an integer).
pub fn flag(obj: &Bound<'_, PyAny>, name: &str) -> Result<bool, Error> {
    if !obj.is_instance_of::<PyBool>() {
        return Err(Error::Config(format!(
            "{name} must be a bool, got {}",
            short_repr(obj)
        )));
    }
    Ok(obj.is_truthy().unwrap_or(false))
}

/// A positive number of milliseconds, as ns.
fn ms_to_ns(name: &str, ms: f64) -> Result<u64, Error> {
    if !(ms.is_finite() && ms > 0.0 && ms <= 1e7) {
        return Err(Error::Config(format!(
            "{name} = {ms} must be a positive number of milliseconds"
        )));
    }
    Ok((ms * 1e6).round() as u64)
}

/// How one keyword setting is read and which field it sets. The ranges are
/// checked afterwards, by [`BridgeConfig::validate`], for the file and the
/// keywords alike.
pub enum Setting {
    /// Milliseconds, stored as ns.
    Ms(fn(&mut BridgeConfig) -> &mut u64),
    /// A real number.
    Real(fn(&mut BridgeConfig) -> &mut f64),
    /// One number or four, one per wheel.
    PerWheel(fn(&mut WheelLimits) -> &mut f64),
    /// An integer in `lo..=hi`.
    Int(i64, i64, fn(&mut BridgeConfig, i64)),
    /// A string, parsed by the setter.
    Text(
        &'static str,
        fn(&mut BridgeConfig, &str) -> Result<(), Error>,
    ),
    /// A `bool`.
    Flag(fn(&mut BridgeConfig) -> &mut bool),
    /// A path (`None` clears it).
    Path(fn(&mut BridgeConfig) -> &mut Option<PathBuf>),
    /// A mapping of names to real numbers, each set by the setter.
    Table(fn(&mut BridgeConfig, &str, f64) -> Result<(), Error>),
}

fn rx_max_rate(c: &mut BridgeConfig, name: &str, v: f64) -> Result<(), Error> {
    let slot = c.plausibility.rate_mut(name).ok_or_else(|| {
        let names: Vec<&str> = (0..crate::codec::N_RX)
            .flat_map(crate::plausibility::signal_names)
            .collect();
        Error::Config(format!(
            "rx_max_rate has no signal {} (received signals: {})",
            crate::error::clip(name),
            names.join(", ")
        ))
    })?;
    *slot = v;
    Ok(())
}

fn rx_wheels(c: &mut BridgeConfig, name: &str, v: f64) -> Result<(), Error> {
    let slot = c.plausibility.geometry_mut(name).ok_or_else(|| {
        Error::Config(format!(
            "rx_wheels has no key {} (radius_m, track_m, cg_to_front_m, tolerance_mps, tolerance_rel)",
            crate::error::clip(name)
        ))
    })?;
    *slot = v;
    Ok(())
}

fn limit_rule(c: &mut BridgeConfig, s: &str) -> Result<(), Error> {
    c.safety.limit_rule = LimitRule::parse(s)?;
    Ok(())
}

fn on_loss(c: &mut BridgeConfig, s: &str) -> Result<(), Error> {
    c.on_transport_loss = match s {
        "report" => OnTransportLoss::Report,
        "raise" => OnTransportLoss::Raise,
        _ => {
            return Err(Error::Config(format!(
                "on_transport_loss must be \"report\" or \"raise\", got {}",
                crate::error::clip(s)
            )))
        }
    };
    Ok(())
}

/// Every keyword setting of `Bridge(...)` (besides `channel`, `period_ms`
/// and `config`), by name.
pub const SETTINGS: &[(&str, Setting)] = &[
    ("torque_min_nm", Setting::PerWheel(|w| &mut w.min_nm)),
    ("torque_max_nm", Setting::PerWheel(|w| &mut w.max_nm)),
    ("rise_nm_per_s", Setting::PerWheel(|w| &mut w.rise_nm_per_s)),
    (
        "release_nm_per_s",
        Setting::PerWheel(|w| &mut w.release_nm_per_s),
    ),
    (
        "safe_release_nm_per_s",
        Setting::Real(|c| &mut c.safety.safe_release_nm_per_s),
    ),
    (
        "limit_rule",
        Setting::Text("\"clamp\" or \"refuse\"", limit_rule),
    ),
    (
        "hold_after_ms",
        Setting::Ms(|c| &mut c.safety.hold_after_ns),
    ),
    (
        "safe_after_ms",
        Setting::Ms(|c| &mut c.safety.safe_after_ns),
    ),
    (
        "fault_after_ms",
        Setting::Ms(|c| &mut c.safety.fault_after_ns),
    ),
    ("state_timeout_ms", Setting::Ms(|c| &mut c.state_timeout_ns)),
    (
        "transport_timeout_ms",
        Setting::Ms(|c| &mut c.transport_timeout_ns),
    ),
    (
        "on_transport_loss",
        Setting::Text("\"report\" or \"raise\"", on_loss),
    ),
    (
        "actuator_timeout_ms",
        Setting::Ms(|c| &mut c.actuator_timeout_ns),
    ),
    (
        "socketcand_active",
        Setting::Flag(|c| &mut c.socketcand_active),
    ),
    ("log_path", Setting::Path(|c| &mut c.log_path)),
    ("log_overwrite", Setting::Flag(|c| &mut c.log_overwrite)),
    (
        "log_rx_per_s",
        Setting::Int(1, 1_000_000, |c, v| c.log_rx_per_s = v as u32),
    ),
    (
        "log_max_bytes",
        Setting::Int(4096, 1 << 50, |c, v| c.log_max_bytes = v as u64),
    ),
    (
        "bitrate",
        Setting::Int(1, u32::MAX as i64, |c, v| c.bitrate = v as u32),
    ),
    (
        "stop_safe_frames",
        Setting::Int(1, 100, |c, v| c.stop_safe_frames = v as u32),
    ),
    (
        "rx_max_counter_delta",
        Setting::Int(1, 14, |c, v| c.rx_max_counter_delta = v as u8),
    ),
    (
        "rx_sync_frames",
        Setting::Int(1, 14, |c, v| c.rx_sync_frames = v as u8),
    ),
    // the former name of rx_max_error_valid
    (
        "rx_max_strikes",
        Setting::Int(0, 16, |c, v| c.rx_sm.max_error_valid = v as u8),
    ),
    (
        "rx_window",
        Setting::Int(1, 16, |c, v| c.rx_sm.window = v as u8),
    ),
    (
        "rx_min_ok_init",
        Setting::Int(1, 16, |c, v| c.rx_sm.min_ok_init = v as u8),
    ),
    (
        "rx_max_error_init",
        Setting::Int(0, 16, |c, v| c.rx_sm.max_error_init = v as u8),
    ),
    (
        "rx_min_ok_valid",
        Setting::Int(1, 16, |c, v| c.rx_sm.min_ok_valid = v as u8),
    ),
    (
        "rx_max_error_valid",
        Setting::Int(0, 16, |c, v| c.rx_sm.max_error_valid = v as u8),
    ),
    (
        "rx_min_ok_invalid",
        Setting::Int(1, 16, |c, v| c.rx_sm.min_ok_invalid = v as u8),
    ),
    (
        "rx_max_error_invalid",
        Setting::Int(0, 16, |c, v| c.rx_sm.max_error_invalid = v as u8),
    ),
    ("rx_confirm_ms", Setting::Ms(|c| &mut c.rx_confirm_ns)),
    ("rx_max_rate", Setting::Table(rx_max_rate)),
    ("rx_wheels", Setting::Table(rx_wheels)),
    (
        "trace_capacity",
        Setting::Int(0, 10_000_000, |c, v| c.trace_capacity = v as usize),
    ),
    (
        "rt_priority",
        Setting::Int(1, 99, |c, v| c.rt_priority = Some(v as i32)),
    ),
];

/// Apply one keyword setting (`None` keeps the file's value or the default).
pub fn apply(cfg: &mut BridgeConfig, name: &str, obj: &Bound<'_, PyAny>) -> Result<(), Error> {
    let Some((_, setting)) = SETTINGS.iter().find(|(n, _)| *n == name) else {
        return Err(Error::Config(format!(
            "unknown setting {}",
            crate::error::clip(name)
        )));
    };
    if obj.is_none() {
        return Ok(());
    }
    match setting {
        Setting::Ms(field) => *field(cfg) = ms_to_ns(name, real(obj, name, Error::Config)?)?,
        Setting::Real(field) => *field(cfg) = real(obj, name, Error::Config)?,
        Setting::PerWheel(field) => {
            let v = per_wheel(obj, name)?;
            for (w, x) in cfg.safety.wheels.iter_mut().zip(v) {
                *field(w) = x;
            }
        }
        Setting::Int(lo, hi, set) => set(cfg, int_in(obj, name, *lo, *hi)?),
        Setting::Text(want, set) => set(cfg, &string(obj, name, want)?)?,
        Setting::Flag(field) => *field(cfg) = flag(obj, name)?,
        Setting::Path(field) => *field(cfg) = Some(path(obj, name)?),
        Setting::Table(set) => {
            let d = obj.cast::<PyDict>().map_err(|_| {
                Error::Config(format!(
                    "{name} must be a dict of names to numbers, got {}",
                    short_repr(obj)
                ))
            })?;
            for (k, v) in d.iter() {
                let key: String = k.extract().map_err(|_| {
                    Error::Config(format!("{name}: key {} is not a str", short_repr(&k)))
                })?;
                set(
                    cfg,
                    &key,
                    real(&v, &format!("{name}[{key:?}]"), Error::Config)?,
                )?;
            }
        }
    }
    Ok(())
}

/// The configuration `Bridge(channel, period_ms, config=..., **settings)`
/// describes: the defaults, then the file, then each keyword.
pub fn bridge_config(
    channel: &Bound<'_, PyAny>,
    period_ms: Option<&Bound<'_, PyAny>>,
    config: Option<&Bound<'_, PyAny>>,
    settings: Option<&Bound<'_, PyDict>>,
) -> Result<BridgeConfig, Error> {
    let channel: String = channel.extract().map_err(|_| {
        Error::Config(format!(
            "channel must be a str, got {}",
            short_repr(channel)
        ))
    })?;
    let mut cfg = BridgeConfig::new(&channel);
    if let Some(p) = config.filter(|o| !o.is_none()) {
        crate::config::apply_file(&mut cfg, &path(p, "config")?)?;
    }
    if let Some(p) = period_ms.filter(|o| !o.is_none()) {
        cfg.period_ns = ms_to_ns("period_ms", real(p, "period_ms", Error::Config)?)?;
    }
    if let Some(kw) = settings {
        for (k, v) in kw.iter() {
            let name: String = k.extract().unwrap_or_default();
            apply(&mut cfg, &name, &v)?;
        }
    }
    Ok(cfg)
}

/// The payload values of message `m` from a dict of signal names (`Mode`
/// also by its value name): every payload signal, no other key, each a real
/// number (the DBC's range is checked by the encoder).
pub fn message_values(m: &Message, values: &Bound<'_, PyDict>) -> Result<Vec<f64>, Error> {
    let name = m.name;
    let payload = m.signals.get(2..).unwrap_or(&[]);
    for key in values.keys().iter() {
        let known = key
            .extract::<String>()
            .is_ok_and(|k| payload.iter().any(|s| s.name == k));
        if !known {
            let names: Vec<&str> = payload.iter().map(|s| s.name).collect();
            return Err(Error::Command(format!(
                "{name} has no signal {} to set (its signals: {}; CRC and Counter are filled in)",
                short_repr(&key),
                names.join(", ")
            )));
        }
    }
    let mut v = Vec::with_capacity(payload.len());
    for s in payload {
        let item = values
            .get_item(s.name)
            .ok()
            .flatten()
            .ok_or_else(|| Error::Command(format!("{name}: missing signal {}", s.name)))?;
        let x = if s.name == "Mode" && item.is_instance_of::<PyString>() {
            let label: String = item.extract().unwrap_or_default();
            let modes = [Mode::Active, Mode::Hold, Mode::Safe, Mode::Fault];
            let mode = modes
                .into_iter()
                .find(|m| m.name() == label)
                .ok_or_else(|| {
                    let names: Vec<&str> = modes.iter().map(|m| m.name()).collect();
                    Error::Command(format!(
                        "unknown Mode {} (one of {}, or 0..=3)",
                        short_repr(&item),
                        names.join(", ")
                    ))
                })?;
            f64::from(mode as u8)
        } else {
            real_or(&item).map_err(|why| match why {
                NotReal::Type => Error::Command(format!(
                    "{name}: {} = {} is not a real number",
                    s.name,
                    short_repr(&item)
                )),
                NotReal::OutOfRange => Error::Command(format!(
                    "{} = {} is outside the signal's range {}..={}",
                    s.name,
                    short_repr(&item),
                    s.min,
                    s.max
                )),
            })?
        };
        v.push(x);
    }
    Ok(v)
}

/// The received state as `latest_state()` returns it.
pub fn state_dict<'py>(py: Python<'py>, s: &VehicleState) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("valid", s.valid)?;
    d.set_item("long_speed_mps", s.long_speed_mps)?;
    d.set_item("lat_speed_mps", s.lat_speed_mps)?;
    d.set_item("yaw_rate_radps", s.yaw_rate_radps)?;
    d.set_item("steering_angle_rad", s.steering_angle_rad)?;
    d.set_item(
        "wheel_speeds_radps",
        s.wheel_speeds_radps.map(|w| (w[0], w[1], w[2], w[3])),
    )?;
    d.set_item("long_accel_mps2", s.long_accel_mps2)?;
    d.set_item("lat_accel_mps2", s.lat_accel_mps2)?;
    d.set_item("driver_torque_nm", s.driver_torque_nm)?;
    d.set_item("set_speed_mps", s.set_speed_mps)?;
    d.set_item("road_friction", s.road_friction)?;
    d.set_item("age_ms", s.age_ms)?;
    let status = PyDict::new(py);
    for (n, st) in RX_NAMES.iter().zip(s.status) {
        status.set_item(*n, st)?;
    }
    d.set_item("status", status)?;
    d.set_item("reason", s.reason.as_deref())?;
    Ok(d)
}

/// The counters as `stats()` returns them.
pub fn stats_dict<'py>(py: Python<'py>, s: &Stats) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("running", s.running)?;
    d.set_item("ticks", s.tick.ticks)?;
    d.set_item("overruns", s.tick.overruns)?;
    d.set_item("skipped_ticks", s.tick.skipped_ticks)?;
    d.set_item("lateness_mean_ms", s.tick.lateness_mean_us / 1e3)?;
    d.set_item("lateness_p50_ms", s.tick.lateness_p50_us / 1e3)?;
    d.set_item("lateness_p99_ms", s.tick.lateness_p99_us / 1e3)?;
    d.set_item("lateness_max_ms", s.tick.lateness_max_us / 1e3)?;
    d.set_item("mean_period_ms", s.tick.mean_period_us.map(|v| v / 1e3))?;
    d.set_item("drift_ms", s.tick.drift_us.map(|v| v / 1e3))?;
    d.set_item("tx_frames", s.tx_frames)?;
    d.set_item("tx_errors", s.tx_errors)?;
    d.set_item("tx_not_open", s.tx_not_open)?;
    d.set_item("tx_stale_dropped", s.tx_stale_dropped)?;
    d.set_item("send_max_ms", s.send_max_ns as f64 / 1e6)?;
    let a = s.applied_torques_nm;
    d.set_item("applied_torques_nm", (a[0], a[1], a[2], a[3]))?;
    d.set_item("limit_events", s.limit_events)?;
    d.set_item("last_limit_event", s.last_limit_event.as_deref())?;
    d.set_item("rate_limited_ticks", s.rate_limited_ticks)?;
    d.set_item("ramp_restarts", s.ramp_restarts)?;
    d.set_item("tx_safe_only", s.tx_safe_only)?;
    d.set_item("transport_state", s.transport_state.name())?;
    d.set_item("transport_losses", s.transport_losses)?;
    d.set_item("reconnects", s.reconnects)?;
    d.set_item("replies_dropped", s.replies_dropped)?;
    d.set_item("rx_frames", s.rx_frames)?;
    d.set_item("rx_crc_errors", s.rx_crc_errors)?;
    d.set_item("rx_counter_errors", s.rx_counter_errors)?;
    d.set_item("rx_repeated", s.rx_repeated)?;
    d.set_item("rx_two_sources", s.rx_two_sources)?;
    d.set_item("rx_wrong_sequence", s.rx_wrong_sequence)?;
    d.set_item("rx_lost_frames", s.rx_lost_frames)?;
    d.set_item("rx_sync", s.rx_sync)?;
    d.set_item("rx_implausible", s.rx_implausible)?;
    d.set_item("rx_implausible_rate", s.rx_implausible_rate)?;
    d.set_item("rx_inconsistent", s.rx_inconsistent)?;
    d.set_item("rx_faster_than_cycle", s.rx_faster_than_cycle)?;
    d.set_item("rx_discarded", s.rx_discarded)?;
    d.set_item("rx_length_errors", s.rx_length_errors)?;
    d.set_item("rx_malformed", s.rx_malformed)?;
    d.set_item("rx_unknown_id", s.rx_unknown_id)?;
    d.set_item("rx_transport_errors", s.rx_transport_errors)?;
    d.set_item("bus_errors", s.bus_errors)?;
    d.set_item("log_dropped", s.log_dropped)?;
    d.set_item("log_errors", s.log_errors)?;
    d.set_item("log_suppressed", s.log_suppressed)?;
    d.set_item("last_log_error", s.last_log_error.as_deref())?;
    // What the wire saw: nothing while the transport is lost or the channel
    // not open, else the mode of the last frame that reached it.
    d.set_item(
        "safety_state",
        match s.transport_state {
            TransportState::Lost if s.running => "lost",
            TransportState::NotOpen if s.running => "not_open",
            _ if s.running && s.safe_only => "safe_only",
            _ => s.safety_state.name(),
        },
    )?;
    d.set_item("tx_mode", s.safety_state.name())?;
    d.set_item("state_valid", s.state_valid)?;
    d.set_item("state_reason", s.state_reason.as_deref())?;
    d.set_item("last_tx_error", s.last_tx_error.as_deref())?;
    d.set_item("last_rx_error", s.last_rx_error.as_deref())?;
    Ok(d)
}
