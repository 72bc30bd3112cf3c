//! `can_bridge`: frames a controller's wheel-torque commands on CAN at a
//! deterministic rate (20 Hz by default), with AUTOSAR E2E Profile 1
//! protection, actuator limits and a command watchdog, over SocketCAN, SLCAN
//! (serial or pseudo-terminal) or socketcand.
//!
//! The core is plain Rust (`cargo test` needs no Python); the `python`
//! feature adds the pyo3 module `can_bridge._can_bridge`.

#![deny(missing_docs)]
// Tests may unwrap: a failed unwrap there is a failed test (`Cargo.toml`'s lints).
#![cfg_attr(
    test,
    allow(
        clippy::unwrap_used,
        clippy::expect_used,
        clippy::panic,
        clippy::disallowed_methods
    )
)]

pub mod bridge;
pub mod candump;
pub mod channel;
pub mod codec;
pub mod config;
pub mod e2e;
pub mod error;
pub mod frame;
pub mod plausibility;
pub mod safety;
pub mod scheduler;
pub mod slcan;
pub mod socketcand;
mod sync;
#[cfg(test)]
mod test_support;
pub mod transport;

#[cfg(feature = "python")]
mod python;

pub use bridge::{Bridge, BridgeConfig, OnTransportLoss, Stats, VehicleState};
pub use error::{Error, Result};
pub use frame::CanFrame;
