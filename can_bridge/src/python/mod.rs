//! The pyo3 layer: the `Bridge` class and the module's functions. Arguments
//! and results go through one conversion layer ([`convert`]); every Rust
//! [`Error`] becomes a Python exception through one `From<Error> for PyErr`
//! (each kind to one class declared in `can_bridge/_errors.py`); the GIL is
//! released around everything that blocks.

mod convert;

use crate::bridge::Bridge;
use crate::codec::ALL_MESSAGES;
use crate::error::Error;
use convert::short_repr;
use pyo3::exceptions::{PyRuntimeError, PyTypeError};
use pyo3::prelude::*;
use pyo3::types::{PyBytes, PyDict, PyTuple};

/// The one mapping from error kinds to Python exception classes.
impl From<Error> for PyErr {
    fn from(e: Error) -> PyErr {
        let class = match e {
            Error::Config(_) => "ConfigError",
            Error::Command(_) => "CommandError",
            Error::Transport(_) => "TransportError",
            Error::State(_) => "StateError",
        };
        let msg = e.message().to_string();
        Python::attach(|py| {
            let made = py
                .import("can_bridge._errors")
                .and_then(|m| m.getattr(class))
                .and_then(|cls| cls.call1((msg.clone(),)));
            match made {
                Ok(inst) => PyErr::from_value(inst),
                Err(_) => PyRuntimeError::new_err(msg),
            }
        })
    }
}

/// A CAN bridge: frames the latest wheel-torque command every tick.
#[pyclass(name = "Bridge", module = "can_bridge", frozen)]
struct PyBridge {
    inner: Bridge,
}

#[pymethods]
impl PyBridge {
    /// `Bridge(channel, period_ms=None, *, config=None, **settings)`: the
    /// defaults, then the file, then each keyword setting (`None` keeps the
    /// value before it); see the stubs for every setting.
    #[new]
    #[pyo3(signature = (channel, period_ms = None, *, config = None, **settings))]
    fn new(
        channel: &Bound<'_, PyAny>,
        period_ms: Option<&Bound<'_, PyAny>>,
        config: Option<&Bound<'_, PyAny>>,
        settings: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        if let Some(kw) = settings {
            for k in kw.keys() {
                let name: String = k.extract().unwrap_or_default();
                if !convert::SETTINGS.iter().any(|(n, _)| *n == name) {
                    return Err(PyTypeError::new_err(format!(
                        "Bridge() got an unexpected keyword argument {}",
                        short_repr(&k)
                    )));
                }
            }
        }
        let cfg = convert::bridge_config(channel, period_ms, config, settings)?;
        Ok(PyBridge {
            inner: Bridge::new(cfg)?,
        })
    }

    /// Open the transport and start the transmit and receive threads.
    fn start(&self, py: Python<'_>) -> PyResult<()> {
        Ok(py.detach(|| self.inner.start())?)
    }

    /// Send the safe frames, stop the threads and close the transport.
    fn stop(&self, py: Python<'_>) -> PyResult<()> {
        Ok(py.detach(|| self.inner.stop())?)
    }

    fn __enter__(slf: Bound<'_, Self>) -> PyResult<Bound<'_, Self>> {
        let py = slf.py();
        {
            let me = slf.get();
            py.detach(|| me.inner.start())?;
        }
        Ok(slf)
    }

    #[pyo3(signature = (*_args))]
    fn __exit__(&self, py: Python<'_>, _args: &Bound<'_, PyTuple>) -> PyResult<bool> {
        py.detach(|| self.inner.stop())?;
        Ok(false)
    }

    /// Hand over the latest command: torques (FL, FR, RL, RR) in Nm and a
    /// strictly increasing sequence number.
    fn set_command(&self, torques: &Bound<'_, PyAny>, seq: &Bound<'_, PyAny>) -> PyResult<()> {
        let t = convert::four_reals(torques, "torques", Error::Command)?;
        let seq = convert::seq(seq)?;
        Ok(self.inner.set_command(t, seq)?)
    }

    /// Clear a latched fault (effective on the next tick).
    fn reset_fault(&self) {
        self.inner.reset_fault();
    }

    /// The received vehicle state as a dict.
    fn latest_state<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        convert::state_dict(py, &self.inner.latest_state())
    }

    /// Counters and timing as a dict.
    fn stats<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        let s = py.detach(|| self.inner.stats());
        convert::stats_dict(py, &s)
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
        .ok_or_else(|| Error::Config(format!("unknown message {name:?}")))?;
    let counter =
        convert::small_uint(counter, u16::from(crate::e2e::MAX_COUNTER)).ok_or_else(|| {
            Error::Command(format!(
                "counter = {} is not an E2E Profile 1 alive counter (an integer in 0..={})",
                short_repr(counter),
                crate::e2e::MAX_COUNTER
            ))
        })?;
    let v = convert::message_values(m, values)?;
    let f = m.encode_checked(&v, counter as u8)?;
    Ok(PyBytes::new(py, f.data()))
}

/// The AUTOSAR E2E Profile 1 CRC of `data` (byte 0 ignored) for `data_id`
/// (an integer in 0..=65535, else `ConfigError`).
#[pyfunction]
fn e2e_p01_crc(data_id: &Bound<'_, PyAny>, data: &[u8]) -> PyResult<u8> {
    let id = convert::small_uint(data_id, u16::MAX).ok_or_else(|| {
        Error::Config(format!(
            "data_id = {} must be an integer in 0..=65535",
            short_repr(data_id)
        ))
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
