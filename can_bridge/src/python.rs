//! The pyo3 layer: argument conversion, the GIL released around everything
//! that blocks, and one mapping from [`Error`] kinds to the exception classes
//! declared in `can_bridge/_errors.py`.

use crate::bridge::{Bridge, BridgeConfig};
use crate::codec::{Mode, ALL_MESSAGES};
use crate::error::Error;
use crate::safety::SafetyConfig;
use pyo3::exceptions::PyRuntimeError;
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict, PyString};
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
    let iter = obj.try_iter().map_err(|_| {
        kind(format!(
            "{what} must be a sequence of 4 numbers (FL, FR, RL, RR)"
        ))
    })?;
    let mut out = [0.0; 4];
    let mut n = 0usize;
    for item in iter {
        let item = item.map_err(|e| kind(format!("{what}: {e}")))?;
        let v: f64 = item
            .extract()
            .map_err(|_| kind(format!("{what}[{n}] is not a number")))?;
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
        period_ms = 50.0,
        *,
        max_torque_nm = None,
        max_rate_nm_per_tick = 25.0,
        hold_after_ms = 150.0,
        safe_after_ms = 500.0,
        fault_after_ms = 2000.0,
        state_timeout_ms = 250.0,
        log_path = None,
        bitrate = 500_000,
        stop_safe_frames = 3,
        rx_max_counter_delta = 2,
        trace_capacity = 0,
        rt_priority = None,
    ))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        channel: &str,
        period_ms: f64,
        max_torque_nm: Option<&Bound<'_, PyAny>>,
        max_rate_nm_per_tick: f64,
        hold_after_ms: f64,
        safe_after_ms: f64,
        fault_after_ms: f64,
        state_timeout_ms: f64,
        log_path: Option<PathBuf>,
        bitrate: u32,
        stop_safe_frames: u32,
        rx_max_counter_delta: u8,
        trace_capacity: usize,
        rt_priority: Option<i32>,
    ) -> PyResult<Self> {
        let build = || -> Result<Bridge, Error> {
            let max_torque = match max_torque_nm {
                None => SafetyConfig::default().max_torque_nm,
                Some(obj) => match obj.extract::<f64>() {
                    Ok(v) => [v; 4],
                    Err(_) => four_floats(obj, "max_torque_nm", Error::Config)?,
                },
            };
            let mut cfg = BridgeConfig::new(channel);
            cfg.period_ns = ms_to_ns("period_ms", period_ms)?;
            cfg.safety = SafetyConfig {
                max_torque_nm: max_torque,
                max_delta_nm_per_tick: max_rate_nm_per_tick,
                hold_after_ns: ms_to_ns("hold_after_ms", hold_after_ms)?,
                safe_after_ns: ms_to_ns("safe_after_ms", safe_after_ms)?,
                fault_after_ns: ms_to_ns("fault_after_ms", fault_after_ms)?,
            };
            cfg.state_timeout_ns = ms_to_ns("state_timeout_ms", state_timeout_ms)?;
            cfg.log_path = log_path;
            cfg.bitrate = bitrate;
            cfg.stop_safe_frames = stop_safe_frames;
            cfg.rx_max_counter_delta = rx_max_counter_delta;
            cfg.trace_capacity = trace_capacity;
            cfg.rt_priority = rt_priority;
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
        let seq: u64 = seq.extract().map_err(|_| {
            err(
                py,
                Error::Command(format!(
                    "seq must be an integer in 0..2**64, got {}",
                    seq.repr()
                        .map_or_else(|_| "?".to_string(), |r| r.to_string())
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
        d.set_item("age_ms", s.age_ms)?;
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
        d.set_item("rx_frames", s.rx_frames)?;
        d.set_item("rx_crc_errors", s.rx_crc_errors)?;
        d.set_item("rx_counter_errors", s.rx_counter_errors)?;
        d.set_item("rx_length_errors", s.rx_length_errors)?;
        d.set_item("rx_malformed", s.rx_malformed)?;
        d.set_item("rx_unknown_id", s.rx_unknown_id)?;
        d.set_item("rx_transport_errors", s.rx_transport_errors)?;
        d.set_item("bus_errors", s.bus_errors)?;
        d.set_item("log_dropped", s.log_dropped)?;
        d.set_item("safety_state", s.safety_state.name())?;
        d.set_item("state_valid", s.state_valid)?;
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

    /// Pseudo-terminal slave path for `slcan-pty:` (set by `start`).
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
/// name to its physical value; CRC and counter are filled in (E2E Profile 1).
#[pyfunction]
fn encode_message<'py>(
    py: Python<'py>,
    name: &str,
    values: &Bound<'py, PyDict>,
    counter: u8,
) -> PyResult<Bound<'py, PyBytes>> {
    let m = ALL_MESSAGES
        .iter()
        .find(|m| m.name == name)
        .ok_or_else(|| err(py, Error::Config(format!("unknown message {name:?}"))))?;
    let mut v = Vec::new();
    for s in m.signals.iter().skip(2) {
        let item = values.get_item(s.name)?.ok_or_else(|| {
            err(
                py,
                Error::Command(format!("{name}: missing signal {}", s.name)),
            )
        })?;
        let x: f64 = if s.name == "Mode" {
            match item.extract::<String>() {
                Ok(label) => {
                    let mode = [Mode::Active, Mode::Hold, Mode::Safe, Mode::Fault]
                        .into_iter()
                        .find(|m| m.name() == label)
                        .ok_or_else(|| {
                            err(py, Error::Command(format!("unknown Mode {label:?}")))
                        })?;
                    f64::from(mode as u8)
                }
                Err(_) => item.extract()?,
            }
        } else {
            item.extract()?
        };
        v.push(x);
    }
    let f = m.encode(&v, counter).map_err(|e| err(py, e))?;
    Ok(PyBytes::new(py, f.data()))
}

/// The AUTOSAR E2E Profile 1 CRC of `data` (byte 0 ignored) for `data_id`.
#[pyfunction]
fn e2e_p01_crc(data_id: u16, data: &[u8]) -> u8 {
    crate::e2e::p01_crc(data_id, data)
}

#[pymodule]
#[pyo3(name = "_can_bridge")]
fn native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add_class::<PyBridge>()?;
    m.add_function(wrap_pyfunction!(encode_message, m)?)?;
    m.add_function(wrap_pyfunction!(e2e_p01_crc, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
