//! The pyo3 layer: argument conversion, the GIL released around everything
//! that blocks, and one mapping from [`Error`] kinds to the exception classes
//! declared in `can_bridge/_errors.py`.

use crate::bridge::{Bridge, BridgeConfig, OnTransportLoss, RX_NAMES};
use crate::codec::{Mode, ALL_MESSAGES};
use crate::error::Error;
use crate::safety::LimitRule;
use pyo3::exceptions::{PyOverflowError, PyRuntimeError};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyBool, PyBytes, PyDict, PyString, PyType};
use std::path::PathBuf;

/// The one mapping from error kinds to Python exception classes.
fn err(py: Python<'_>, e: Error) -> PyErr {
    let class = match e {
        Error::Config(_) => "ConfigError",
        Error::Command(_) => "CommandError",
        Error::Transport(_) => "TransportError",
        Error::State(_) => "StateError",
    };
    let msg = e.message().to_string();
    let made = py
        .import("can_bridge._errors")
        .and_then(|m| m.getattr(class))
        .and_then(|cls| cls.call1((msg.clone(),)));
    match made {
        Ok(inst) => PyErr::from_value(inst),
        Err(_) => PyRuntimeError::new_err(msg),
    }
}

fn ms_to_ns(name: &str, ms: f64) -> Result<u64, Error> {
    if !(ms.is_finite() && ms > 0.0 && ms <= 1e7) {
        return Err(Error::Config(format!(
            "{name} = {ms} must be a positive number of milliseconds"
        )));
    }
    Ok((ms * 1e6).round() as u64)
}

/// `repr(obj)` for error messages.
fn repr(obj: &Bound<'_, PyAny>) -> String {
    obj.repr()
        .map_or_else(|_| "?".to_string(), |r| r.to_string())
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
fn real(item: &Bound<'_, PyAny>) -> Result<f64, NotReal> {
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

/// `repr(obj)` cut to a readable length (a huge integer has hundreds of digits).
fn short_repr(obj: &Bound<'_, PyAny>) -> String {
    let r = repr(obj);
    if r.chars().count() <= 40 {
        r
    } else {
        let head: String = r.chars().take(20).collect();
        format!("{head}... ({} characters)", r.chars().count())
    }
}

fn four_floats(
    obj: &Bound<'_, PyAny>,
    what: &str,
    kind: fn(String) -> Error,
) -> Result<[f64; 4], Error> {
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
        let v = real(&item).map_err(|why| match why {
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

/// A numeric constructor argument (`None`: not given).
fn opt_f64(name: &str, obj: Option<&Bound<'_, PyAny>>) -> Result<Option<f64>, Error> {
    match obj {
        None => Ok(None),
        Some(o) if o.is_none() => Ok(None),
        Some(o) => real(o).map(Some).map_err(|why| match why {
            NotReal::Type => Error::Config(format!(
                "{name} must be a real number, got {}",
                short_repr(o)
            )),
            NotReal::OutOfRange => Error::Config(format!(
                "{name} = {} is out of range (too large for a float)",
                short_repr(o)
            )),
        }),
    }
}

/// A per-wheel argument: one number for all four wheels, or four (FL, FR, RL, RR).
fn per_wheel(name: &str, obj: Option<&Bound<'_, PyAny>>) -> Result<Option<[f64; 4]>, Error> {
    let Some(o) = obj.filter(|o| !o.is_none()) else {
        return Ok(None);
    };
    match real(o) {
        Ok(v) => Ok(Some([v; 4])),
        Err(NotReal::OutOfRange) => Err(Error::Config(format!(
            "{name} = {} is out of range (too large for a float)",
            short_repr(o)
        ))),
        Err(NotReal::Type) if is_bool(o) => Err(Error::Config(format!(
            "{name} must be a real number or 4 of them, got {}",
            short_repr(o)
        ))),
        Err(NotReal::Type) => four_floats(o, name, Error::Config).map(Some),
    }
}

/// An integer constructor argument in `lo..=hi` (`None`: the default).
fn arg_int(
    name: &str,
    obj: Option<&Bound<'_, PyAny>>,
    default: i64,
    lo: i64,
    hi: i64,
) -> Result<i64, Error> {
    let o = match obj {
        Some(o) if !o.is_none() => o,
        _ => return Ok(default),
    };
    let v = if is_bool(o) {
        None
    } else {
        o.extract::<i64>().ok()
    };
    match v {
        Some(v) if (lo..=hi).contains(&v) => Ok(v),
        _ => Err(Error::Config(format!(
            "{name} must be an integer in {lo}..={hi}, got {}",
            short_repr(o)
        ))),
    }
}

/// A CAN bridge: frames the latest wheel-torque command every tick.
#[pyclass(name = "Bridge", module = "can_bridge", frozen)]
struct PyBridge {
    inner: Bridge,
}

#[pymethods]
impl PyBridge {
    #[new]
    #[pyo3(signature = (
        channel,
        period_ms = None,
        *,
        config = None,
        torque_min_nm = None,
        torque_max_nm = None,
        rise_nm_per_s = None,
        release_nm_per_s = None,
        safe_release_nm_per_s = None,
        limit_rule = None,
        hold_after_ms = None,
        safe_after_ms = None,
        fault_after_ms = None,
        state_timeout_ms = None,
        transport_timeout_ms = None,
        on_transport_loss = None,
        log_path = None,
        log_overwrite = None,
        bitrate = None,
        stop_safe_frames = None,
        rx_max_counter_delta = None,
        rx_sync_frames = None,
        rx_max_strikes = None,
        trace_capacity = None,
        rt_priority = None,
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        channel: &Bound<'_, PyAny>,
        period_ms: Option<&Bound<'_, PyAny>>,
        config: Option<&Bound<'_, PyAny>>,
        torque_min_nm: Option<&Bound<'_, PyAny>>,
        torque_max_nm: Option<&Bound<'_, PyAny>>,
        rise_nm_per_s: Option<&Bound<'_, PyAny>>,
        release_nm_per_s: Option<&Bound<'_, PyAny>>,
        safe_release_nm_per_s: Option<&Bound<'_, PyAny>>,
        limit_rule: Option<&Bound<'_, PyAny>>,
        hold_after_ms: Option<&Bound<'_, PyAny>>,
        safe_after_ms: Option<&Bound<'_, PyAny>>,
        fault_after_ms: Option<&Bound<'_, PyAny>>,
        state_timeout_ms: Option<&Bound<'_, PyAny>>,
        transport_timeout_ms: Option<&Bound<'_, PyAny>>,
        on_transport_loss: Option<&Bound<'_, PyAny>>,
        log_path: Option<&Bound<'_, PyAny>>,
        log_overwrite: Option<&Bound<'_, PyAny>>,
        bitrate: Option<&Bound<'_, PyAny>>,
        stop_safe_frames: Option<&Bound<'_, PyAny>>,
        rx_max_counter_delta: Option<&Bound<'_, PyAny>>,
        rx_sync_frames: Option<&Bound<'_, PyAny>>,
        rx_max_strikes: Option<&Bound<'_, PyAny>>,
        trace_capacity: Option<&Bound<'_, PyAny>>,
        rt_priority: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<Self> {
        let build = || -> Result<Bridge, Error> {
            let channel: String = channel.extract().map_err(|_| {
                Error::Config(format!(
                    "channel must be a str, got {}",
                    short_repr(channel)
                ))
            })?;
            let mut cfg = BridgeConfig::new(&channel);
            if let Some(path) = config.filter(|o| !o.is_none()) {
                let p: PathBuf = path.extract().map_err(|_| {
                    Error::Config(format!(
                        "config must be a str or os.PathLike, got {}",
                        short_repr(path)
                    ))
                })?;
                crate::config::apply_file(&mut cfg, &p)?;
            }
            let ms = |name: &str, obj: Option<&Bound<'_, PyAny>>, slot: &mut u64| {
                if let Some(v) = opt_f64(name, obj)? {
                    *slot = ms_to_ns(name, v)?;
                }
                Ok::<(), Error>(())
            };
            ms("period_ms", period_ms, &mut cfg.period_ns)?;
            ms(
                "hold_after_ms",
                hold_after_ms,
                &mut cfg.safety.hold_after_ns,
            )?;
            ms(
                "safe_after_ms",
                safe_after_ms,
                &mut cfg.safety.safe_after_ns,
            )?;
            ms(
                "fault_after_ms",
                fault_after_ms,
                &mut cfg.safety.fault_after_ns,
            )?;
            ms(
                "state_timeout_ms",
                state_timeout_ms,
                &mut cfg.state_timeout_ns,
            )?;
            ms(
                "transport_timeout_ms",
                transport_timeout_ms,
                &mut cfg.transport_timeout_ns,
            )?;
            let wheels = &mut cfg.safety.wheels;
            if let Some(v) = per_wheel("torque_min_nm", torque_min_nm)? {
                wheels.iter_mut().zip(v).for_each(|(w, x)| w.min_nm = x);
            }
            if let Some(v) = per_wheel("torque_max_nm", torque_max_nm)? {
                wheels.iter_mut().zip(v).for_each(|(w, x)| w.max_nm = x);
            }
            if let Some(v) = per_wheel("rise_nm_per_s", rise_nm_per_s)? {
                wheels
                    .iter_mut()
                    .zip(v)
                    .for_each(|(w, x)| w.rise_nm_per_s = x);
            }
            if let Some(v) = per_wheel("release_nm_per_s", release_nm_per_s)? {
                wheels
                    .iter_mut()
                    .zip(v)
                    .for_each(|(w, x)| w.release_nm_per_s = x);
            }
            if let Some(v) = opt_f64("safe_release_nm_per_s", safe_release_nm_per_s)? {
                cfg.safety.safe_release_nm_per_s = v;
            }
            if let Some(o) = limit_rule.filter(|o| !o.is_none()) {
                let s: String = o.extract().map_err(|_| {
                    Error::Config(format!(
                        "limit_rule must be \"clamp\" or \"refuse\", got {}",
                        short_repr(o)
                    ))
                })?;
                cfg.safety.limit_rule = LimitRule::parse(&s)?;
            }
            if let Some(o) = on_transport_loss.filter(|o| !o.is_none()) {
                let s: Option<String> = o.extract().ok();
                cfg.on_transport_loss = match s.as_deref() {
                    Some("report") => OnTransportLoss::Report,
                    Some("raise") => OnTransportLoss::Raise,
                    _ => {
                        return Err(Error::Config(format!(
                            "on_transport_loss must be \"report\" or \"raise\", got {}",
                            short_repr(o)
                        )))
                    }
                };
            }
            cfg.log_path = match log_path {
                Some(o) if !o.is_none() => Some(o.extract::<PathBuf>().map_err(|_| {
                    Error::Config(format!(
                        "log_path must be a str or os.PathLike, got {}",
                        short_repr(o)
                    ))
                })?),
                _ => None,
            };
            if let Some(o) = log_overwrite.filter(|o| !o.is_none()) {
                if !o.is_instance_of::<PyBool>() {
                    return Err(Error::Config(format!(
                        "log_overwrite must be a bool, got {}",
                        short_repr(o)
                    )));
                }
                cfg.log_overwrite = o.is_truthy().unwrap_or(false);
            }
            let int = |name: &str, obj, default: i64, lo: i64, hi: i64| {
                arg_int(name, obj, default, lo, hi)
            };
            cfg.bitrate = int("bitrate", bitrate, cfg.bitrate.into(), 1, u32::MAX.into())? as u32;
            cfg.stop_safe_frames = int(
                "stop_safe_frames",
                stop_safe_frames,
                cfg.stop_safe_frames.into(),
                1,
                100,
            )? as u32;
            cfg.rx_max_counter_delta = int(
                "rx_max_counter_delta",
                rx_max_counter_delta,
                cfg.rx_max_counter_delta.into(),
                1,
                14,
            )? as u8;
            cfg.rx_sync_frames = int(
                "rx_sync_frames",
                rx_sync_frames,
                cfg.rx_sync_frames.into(),
                1,
                14,
            )? as u8;
            cfg.rx_max_strikes = int(
                "rx_max_strikes",
                rx_max_strikes,
                cfg.rx_max_strikes.into(),
                0,
                16,
            )? as u32;
            cfg.trace_capacity = int("trace_capacity", trace_capacity, 0, 0, 10_000_000)? as usize;
            cfg.rt_priority = match rt_priority {
                Some(o) if !o.is_none() => Some(int("rt_priority", Some(o), 0, 1, 99)? as i32),
                _ => None,
            };
            Bridge::new(cfg)
        };
        build()
            .map(|inner| PyBridge { inner })
            .map_err(|e| err(py, e))
    }

    /// Open the transport and start the transmit and receive threads.
    fn start(&self, py: Python<'_>) -> PyResult<()> {
        py.detach(|| self.inner.start()).map_err(|e| err(py, e))
    }

    /// Send the safe frames, stop the threads and close the transport.
    fn stop(&self, py: Python<'_>) -> PyResult<()> {
        py.detach(|| self.inner.stop()).map_err(|e| err(py, e))
    }

    fn __enter__(slf: Bound<'_, Self>) -> PyResult<Bound<'_, Self>> {
        let py = slf.py();
        {
            let me = slf.get();
            py.detach(|| me.inner.start()).map_err(|e| err(py, e))?;
        }
        Ok(slf)
    }

    #[pyo3(signature = (*_args))]
    fn __exit__(&self, py: Python<'_>, _args: &Bound<'_, pyo3::types::PyTuple>) -> PyResult<bool> {
        py.detach(|| self.inner.stop()).map_err(|e| err(py, e))?;
        Ok(false)
    }

    /// Hand over the latest command: torques (FL, FR, RL, RR) in Nm and a
    /// strictly increasing sequence number.
    fn set_command(
        &self,
        py: Python<'_>,
        torques: &Bound<'_, PyAny>,
        seq: &Bound<'_, PyAny>,
    ) -> PyResult<()> {
        let t = four_floats(torques, "torques", Error::Command).map_err(|e| err(py, e))?;
        let value = if is_bool(seq) {
            None
        } else {
            seq.extract::<u64>().ok()
        };
        let seq = value.ok_or_else(|| {
            err(
                py,
                Error::Command(format!(
                    "seq must be an integer in 0..2**63, got {}",
                    short_repr(seq)
                )),
            )
        })?;
        self.inner.set_command(t, seq).map_err(|e| err(py, e))
    }

    /// Clear a latched fault (effective on the next tick).
    fn reset_fault(&self) {
        self.inner.reset_fault();
    }

    /// The received vehicle state as a dict.
    fn latest_state<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let s = self.inner.latest_state();
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
        d.set_item("reason", s.reason)?;
        Ok(d)
    }

    /// Counters and timing as a dict.
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let s = py.detach(|| self.inner.stats());
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
        d.set_item("last_limit_event", s.last_limit_event)?;
        d.set_item("rate_limited_ticks", s.rate_limited_ticks)?;
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
        d.set_item("rx_length_errors", s.rx_length_errors)?;
        d.set_item("rx_malformed", s.rx_malformed)?;
        d.set_item("rx_unknown_id", s.rx_unknown_id)?;
        d.set_item("rx_transport_errors", s.rx_transport_errors)?;
        d.set_item("bus_errors", s.bus_errors)?;
        d.set_item("log_dropped", s.log_dropped)?;
        d.set_item("log_errors", s.log_errors)?;
        let lost = s.transport_state == crate::bridge::TransportState::Lost;
        d.set_item(
            "safety_state",
            if lost && s.running {
                "lost"
            } else {
                s.safety_state.name()
            },
        )?;
        d.set_item("tx_mode", s.safety_state.name())?;
        d.set_item("state_valid", s.state_valid)?;
        d.set_item("state_reason", s.state_reason)?;
        d.set_item("last_tx_error", s.last_tx_error)?;
        d.set_item("last_rx_error", s.last_rx_error)?;
        Ok(d)
    }

    /// Recorded ticks as (index, deadline_ns, wake_ns), up to `trace_capacity`.
    fn tick_trace(&self, py: Python<'_>) -> Vec<(u64, u64, u64)> {
        py.detach(|| {
            self.inner
                .tick_trace()
                .iter()
                .map(|r| (r.index, r.deadline_ns, r.wake_ns))
                .collect()
        })
    }

    /// Pseudo-terminal slave path for `slcan-pty:` while running (`None`
    /// before `start` and once `stop` has begun: the path may be reused).
    #[getter]
    fn pty_path(&self) -> Option<String> {
        self.inner.pty_path()
    }

    /// Whether the threads are running.
    #[getter]
    fn running(&self) -> bool {
        self.inner.is_running()
    }

    /// The channel string.
    #[getter]
    fn channel(&self) -> String {
        self.inner.config().channel.clone()
    }

    /// Tick period in ms.
    #[getter]
    fn period_ms(&self) -> f64 {
        self.inner.config().period_ns as f64 / 1e6
    }

    fn __repr__(&self) -> String {
        format!(
            "Bridge({:?}, period_ms={}, running={})",
            self.inner.config().channel,
            self.inner.config().period_ns as f64 / 1e6,
            self.inner.is_running()
        )
    }
}

/// Pack a DBC message with the Rust codec: `values` maps each payload signal
/// name to its physical value (`Mode` also takes its value name); CRC and the
/// alive counter (0..=14) are filled in (E2E Profile 1). Refused with
/// `CommandError`: a counter outside 0..=14, a missing or unknown key, a value
/// that is not a real number, outside the DBC's range, or not integral for an
/// integer-valued signal such as `Mode`.
#[pyfunction]
fn encode_message<'py>(
    py: Python<'py>,
    name: &str,
    values: &Bound<'py, PyDict>,
    counter: &Bound<'py, PyAny>,
) -> PyResult<Bound<'py, PyBytes>> {
    let m = ALL_MESSAGES
        .iter()
        .find(|m| m.name == name)
        .ok_or_else(|| err(py, Error::Config(format!("unknown message {name:?}"))))?;
    let payload = m.signals.get(2..).unwrap_or(&[]);
    let refuse = |msg: String| err(py, Error::Command(msg));
    let counter_value = if is_bool(counter) {
        None
    } else {
        counter.extract::<i64>().ok()
    };
    let counter = counter_value
        .and_then(|c| u8::try_from(c).ok())
        .filter(|c| *c <= crate::e2e::MAX_COUNTER)
        .ok_or_else(|| {
            refuse(format!(
                "counter = {} is not an E2E Profile 1 alive counter (an integer in 0..={})",
                short_repr(counter),
                crate::e2e::MAX_COUNTER
            ))
        })?;
    for key in values.keys().iter() {
        let known = key
            .extract::<String>()
            .is_ok_and(|k| payload.iter().any(|s| s.name == k));
        if !known {
            let names: Vec<&str> = payload.iter().map(|s| s.name).collect();
            return Err(refuse(format!(
                "{name} has no signal {} to set (its signals: {}; CRC and Counter are filled in)",
                short_repr(&key),
                names.join(", ")
            )));
        }
    }
    let mut v = Vec::new();
    for s in payload {
        let item = values
            .get_item(s.name)?
            .ok_or_else(|| refuse(format!("{name}: missing signal {}", s.name)))?;
        let x: f64 = if s.name == "Mode" && item.is_instance_of::<PyString>() {
            let label: String = item.extract()?;
            let modes = [Mode::Active, Mode::Hold, Mode::Safe, Mode::Fault];
            let mode = modes
                .into_iter()
                .find(|m| m.name() == label)
                .ok_or_else(|| {
                    let names: Vec<&str> = modes.iter().map(|m| m.name()).collect();
                    refuse(format!(
                        "unknown Mode {} (one of {}, or 0..=3)",
                        short_repr(&item),
                        names.join(", ")
                    ))
                })?;
            f64::from(mode as u8)
        } else {
            real(&item).map_err(|why| match why {
                NotReal::Type => refuse(format!(
                    "{name}: {} = {} is not a real number",
                    s.name,
                    short_repr(&item)
                )),
                NotReal::OutOfRange => refuse(format!(
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
    let f = m.encode_checked(&v, counter).map_err(|e| err(py, e))?;
    Ok(PyBytes::new(py, f.data()))
}

/// The AUTOSAR E2E Profile 1 CRC of `data` (byte 0 ignored) for `data_id`
/// (an integer in 0..=65535, else `ConfigError`).
#[pyfunction]
fn e2e_p01_crc(py: Python<'_>, data_id: &Bound<'_, PyAny>, data: &[u8]) -> PyResult<u8> {
    let id = if is_bool(data_id) {
        None
    } else {
        data_id.extract::<i64>().ok()
    }
    .and_then(|v| u16::try_from(v).ok())
    .ok_or_else(|| {
        err(
            py,
            Error::Config(format!(
                "data_id = {} must be an integer in 0..=65535",
                short_repr(data_id)
            )),
        )
    })?;
    Ok(crate::e2e::p01_crc(id, data))
}

#[pymodule]
#[pyo3(name = "_can_bridge")]
fn native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyBridge>()?;
    m.add_function(wrap_pyfunction!(encode_message, m)?)?;
    m.add_function(wrap_pyfunction!(e2e_p01_crc, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("DEFAULT_CONFIG_TOML", crate::config::DEFAULT_TOML)?;
    Ok(())
}
