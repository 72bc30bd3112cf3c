//! The bridge's life cycle: validate at construction, open the transport
//! and start the threads at `start`, release, send the safe frames and join
//! them at `stop`; every run with fresh state.

use super::{lock, run_rx, run_tx, BridgeConfig, Shared, TxParams, VehicleState};
use crate::candump::{self, LogSetup, LogWriter};
use crate::channel::ChannelSpec;
use crate::codec::RX_MESSAGES;
use crate::error::{Error, Result};
use crate::scheduler::{monotonic_ns, MonotonicClock};
use crate::transport::{self, OpenOptions};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::thread::JoinHandle;

/// Put the calling thread under `SCHED_FIFO` at `priority`.
pub fn set_realtime(priority: i32) -> Result<()> {
    let param = libc::sched_param {
        sched_priority: priority,
    };
    // SAFETY: pthread_self is always valid; param is a valid sched_param.
    let rc = unsafe { libc::pthread_setschedparam(libc::pthread_self(), libc::SCHED_FIFO, &param) };
    if rc != 0 {
        return Err(Error::Config(format!(
            "rt_priority = {priority}: SCHED_FIFO refused: {} (needs root or CAP_SYS_NICE)",
            std::io::Error::from_raw_os_error(rc)
        )));
    }
    Ok(())
}

struct Running {
    /// The state this run's threads use: the stop request must go to this
    /// one, not to whatever `Bridge::shared` holds by the time `stop` runs.
    shared: Arc<Shared>,
    tx: JoinHandle<()>,
    rx: JoinHandle<()>,
    rx_stop: Arc<AtomicBool>,
    log: Option<LogWriter>,
}

/// The bridge.
pub struct Bridge {
    cfg: BridgeConfig,
    spec: ChannelSpec,
    shared: Mutex<Arc<Shared>>,
    run: Mutex<Option<Running>>,
    pty_path: Mutex<Option<String>>,
    /// Serialises `start` and `stop` as a whole (held across the joins), so a
    /// start never overlaps a stop that is still sending its safe frames.
    lifecycle: Mutex<()>,
}

impl Bridge {
    /// Validate the configuration; nothing is opened until [`Bridge::start`].
    pub fn new(cfg: BridgeConfig) -> Result<Self> {
        let spec = cfg.validate()?;
        let shared = Arc::new(Shared::new(&cfg));
        Ok(Bridge {
            cfg,
            spec,
            shared: Mutex::new(shared),
            run: Mutex::new(None),
            pty_path: Mutex::new(None),
            lifecycle: Mutex::new(()),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &BridgeConfig {
        &self.cfg
    }

    pub(super) fn shared(&self) -> Arc<Shared> {
        lock(&self.shared).clone()
    }

    /// Open the transport and start the threads. Each run starts with fresh
    /// counters, no command and a fresh `seq`.
    pub fn start(&self) -> Result<()> {
        let _life = lock(&self.lifecycle);
        let mut run = lock(&self.run);
        if run.is_some() {
            return Err(Error::State("bridge is already running".into()));
        }
        let shared = Arc::new(Shared::new(&self.cfg));
        *lock(&self.shared) = shared.clone();
        let (log_tx, log_writer) = match &self.cfg.log_path {
            Some(p) => {
                let setup = LogSetup {
                    path: p.clone(),
                    overwrite: self.cfg.log_overwrite,
                    channel: self.spec.log_name(),
                    rx_per_s: self.cfg.log_rx_per_s,
                    max_bytes: self.cfg.log_max_bytes,
                    known_ids: RX_MESSAGES.iter().map(|m| m.id).collect(),
                };
                let (s, w) = candump::start(&setup, shared.log.clone())?;
                (Some(s), Some(w))
            }
            None => (None, None),
        };
        let opened = transport::open(
            &self.spec,
            OpenOptions {
                bitrate: self.cfg.bitrate,
                socketcand_active: self.cfg.socketcand_active,
            },
        )?;
        // Published only once the run is up, so a failed start leaves no
        // path to a pty that is already closed again.
        let pty_path = opened.pty_path.clone();
        let health = opened.health.clone();
        *lock(&shared.health) = Some(health.clone());
        let params = TxParams {
            period_ns: self.cfg.period_ns,
            safety: self.cfg.safety,
            stop_safe_frames: self.cfg.stop_safe_frames,
            transport_timeout_ns: self.cfg.transport_timeout_ns,
            actuator_timeout_ns: self.cfg.actuator_timeout_ns,
        };
        let mut sink = opened.sink;
        let mut source = opened.source;
        let tx_shared = shared.clone();
        let tx_log = log_tx.clone();
        let rt = self.cfg.rt_priority;
        let (ready_tx, ready_rx) = std::sync::mpsc::sync_channel::<Result<()>>(1);
        let tx = std::thread::Builder::new()
            .name("can_bridge-tx".into())
            .spawn(move || {
                let ready = rt.map_or(Ok(()), set_realtime);
                let ok = ready.is_ok();
                let _ = ready_tx.send(ready);
                if !ok {
                    return;
                }
                run_tx(
                    &MonotonicClock,
                    params,
                    &tx_shared,
                    sink.as_mut(),
                    Some(&health),
                    tx_log.as_ref(),
                )
            })
            .map_err(|e| Error::io("cannot start transmit thread", &e))?;
        match ready_rx.recv() {
            Ok(Ok(())) => {}
            Ok(Err(e)) => {
                let _ = tx.join();
                return Err(e);
            }
            Err(_) => {
                let _ = tx.join();
                return Err(Error::State("transmit thread ended during start".into()));
            }
        }
        let rx_stop = Arc::new(AtomicBool::new(false));
        let rx_stop2 = rx_stop.clone();
        let rx_shared = shared.clone();
        let rx = match std::thread::Builder::new()
            .name("can_bridge-rx".into())
            .spawn(move || run_rx(&rx_shared, source.as_mut(), &rx_stop2, log_tx.as_ref()))
        {
            Ok(h) => h,
            Err(e) => {
                shared.request_stop();
                let _ = tx.join();
                return Err(Error::io("cannot start receive thread", &e));
            }
        };
        shared.open_for_commands();
        *run = Some(Running {
            shared,
            tx,
            rx,
            rx_stop,
            log: log_writer,
        });
        *lock(&self.pty_path) = pty_path;
        Ok(())
    }

    /// Release the output, send the zero frames, stop the threads, close the
    /// transport. Does nothing if not running.
    pub fn stop(&self) -> Result<()> {
        let _life = lock(&self.lifecycle);
        let Some(r) = lock(&self.run).take() else {
            return Ok(());
        };
        // The pty closes with this run; its /dev/pts/N may then be handed to
        // another process, so the old path is no longer reported.
        *lock(&self.pty_path) = None;
        r.shared.request_stop();
        let tx_ok = r.tx.join().is_ok();
        r.rx_stop.store(true, Ordering::Release);
        let rx_ok = r.rx.join().is_ok();
        if let Some(w) = r.log {
            w.join();
        }
        if !(tx_ok && rx_ok) {
            return Err(Error::State("a bridge thread ended abnormally".into()));
        }
        Ok(())
    }

    /// Whether the threads are running.
    pub fn is_running(&self) -> bool {
        lock(&self.run).is_some()
    }

    /// Hand over the latest command (FL, FR, RL, RR in Nm); see
    /// [`Shared::set_command`] for what is refused.
    pub fn set_command(&self, torques_nm: [f64; 4], seq: u64) -> Result<()> {
        self.shared().set_command(torques_nm, seq, monotonic_ns())
    }

    /// Clear a latched fault (takes effect on the next tick).
    pub fn reset_fault(&self) {
        self.shared().request_reset(monotonic_ns());
    }

    /// The received vehicle state now.
    pub fn latest_state(&self) -> VehicleState {
        let sh = self.shared();
        let rx = lock(&sh.rx);
        rx.state(monotonic_ns())
    }

    /// Pseudo-terminal slave path for `slcan-pty:` while running (`None`
    /// before `start` and once `stop` has begun).
    pub fn pty_path(&self) -> Option<String> {
        lock(&self.pty_path).clone()
    }
}

impl Drop for Bridge {
    fn drop(&mut self) {
        let _ = self.stop();
    }
}
