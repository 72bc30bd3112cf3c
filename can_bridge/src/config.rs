//! The configuration file: TOML, one table of settings plus `[wheels.FL]`
//! .. `[wheels.RR]` with each wheel's limits (the shipped
//! `python/can_bridge/vehicle.toml` documents every key and is the default).
//! Every key is optional; an unknown key, a wrong type or a value out of its
//! range is refused with an error naming the key (the ranges are checked by
//! [`BridgeConfig::validate`], after the file is applied).

use crate::bridge::BridgeConfig;
use crate::error::{clip, Error, Result};
use crate::safety::{LimitRule, WHEELS};
use std::path::Path;
use toml::{Table, Value};

const TOP: [&str; 27] = [
    "period_ms",
    "limit_rule",
    "safe_release_nm_per_s",
    "hold_after_ms",
    "safe_after_ms",
    "fault_after_ms",
    "state_timeout_ms",
    "transport_timeout_ms",
    "actuator_timeout_ms",
    "socketcand_active",
    "log_rx_per_s",
    "log_max_bytes",
    "stop_safe_frames",
    "rx_max_counter_delta",
    "rx_sync_frames",
    "rx_max_strikes",
    "rx_window",
    "rx_min_ok_init",
    "rx_max_error_init",
    "rx_min_ok_valid",
    "rx_max_error_valid",
    "rx_min_ok_invalid",
    "rx_max_error_invalid",
    "rx_confirm_ms",
    "wheels",
    "rx_max_rate",
    "rx_wheels",
];
const RX_WHEEL_KEYS: [&str; 5] = [
    "radius_m",
    "track_m",
    "cg_to_front_m",
    "tolerance_mps",
    "tolerance_rel",
];
const WHEEL_KEYS: [&str; 4] = ["min_nm", "max_nm", "rise_nm_per_s", "release_nm_per_s"];

/// The shipped default configuration (also `can_bridge.default_config_path()`).
pub const DEFAULT_TOML: &str = include_str!("../python/can_bridge/vehicle.toml");

fn number(v: &Value, key: &str) -> Result<f64> {
    match v {
        Value::Float(x) => Ok(*x),
        Value::Integer(i) => Ok(*i as f64),
        _ => Err(Error::Config(format!(
            "{key} must be a number, got {}",
            clip(&format!("{v:?}"))
        ))),
    }
}

fn integer(v: &Value, key: &str, lo: i64, hi: i64) -> Result<i64> {
    match v {
        Value::Integer(i) if (lo..=hi).contains(i) => Ok(*i),
        _ => Err(Error::Config(format!(
            "{key} must be an integer in {lo}..={hi}, got {}",
            clip(&format!("{v:?}"))
        ))),
    }
}

fn ms_to_ns(key: &str, ms: f64) -> Result<u64> {
    if !(ms.is_finite() && ms > 0.0 && ms <= 1e7) {
        return Err(Error::Config(format!(
            "{key} = {ms} must be a positive number of milliseconds"
        )));
    }
    Ok((ms * 1e6).round() as u64)
}

/// Apply the settings of a TOML text to `cfg` (`origin` names it in errors).
pub fn apply_str(cfg: &mut BridgeConfig, text: &str, origin: &str) -> Result<()> {
    let table: Table = toml::from_str(text).map_err(|e| {
        let msg = e.to_string();
        Error::Config(format!(
            "config {origin}: not valid TOML: {}",
            msg.lines().next().unwrap_or("")
        ))
    })?;
    let key_err = |k: &str, allowed: &[&str]| {
        Error::Config(format!(
            "config {origin}: unknown key {} (known: {})",
            clip(k),
            allowed.join(", ")
        ))
    };
    for (k, v) in &table {
        let name = k.as_str();
        match name {
            "period_ms" => cfg.period_ns = ms_to_ns(name, number(v, name)?)?,
            "hold_after_ms" => cfg.safety.hold_after_ns = ms_to_ns(name, number(v, name)?)?,
            "safe_after_ms" => cfg.safety.safe_after_ns = ms_to_ns(name, number(v, name)?)?,
            "fault_after_ms" => cfg.safety.fault_after_ns = ms_to_ns(name, number(v, name)?)?,
            "state_timeout_ms" => cfg.state_timeout_ns = ms_to_ns(name, number(v, name)?)?,
            "transport_timeout_ms" => cfg.transport_timeout_ns = ms_to_ns(name, number(v, name)?)?,
            "actuator_timeout_ms" => cfg.actuator_timeout_ns = ms_to_ns(name, number(v, name)?)?,
            "socketcand_active" => match v {
                Value::Boolean(b) => cfg.socketcand_active = *b,
                _ => {
                    return Err(Error::Config(
                        "socketcand_active must be true or false".into(),
                    ))
                }
            },
            "log_rx_per_s" => cfg.log_rx_per_s = integer(v, name, 1, 1_000_000)? as u32,
            "log_max_bytes" => cfg.log_max_bytes = integer(v, name, 4096, 1 << 50)? as u64,
            "safe_release_nm_per_s" => cfg.safety.safe_release_nm_per_s = number(v, name)?,
            "limit_rule" => match v {
                Value::String(s) => cfg.safety.limit_rule = LimitRule::parse(s)?,
                _ => return Err(Error::Config("limit_rule must be a string".into())),
            },
            "stop_safe_frames" => cfg.stop_safe_frames = integer(v, name, 1, 100)? as u32,
            "rx_max_counter_delta" => cfg.rx_max_counter_delta = integer(v, name, 1, 14)? as u8,
            "rx_sync_frames" => cfg.rx_sync_frames = integer(v, name, 1, 14)? as u8,
            // the former name of rx_max_error_valid, kept for older files
            "rx_max_strikes" | "rx_max_error_valid" => {
                cfg.rx_sm.max_error_valid = integer(v, name, 0, 16)? as u8
            }
            "rx_window" => cfg.rx_sm.window = integer(v, name, 1, 16)? as u8,
            "rx_min_ok_init" => cfg.rx_sm.min_ok_init = integer(v, name, 1, 16)? as u8,
            "rx_max_error_init" => cfg.rx_sm.max_error_init = integer(v, name, 0, 16)? as u8,
            "rx_min_ok_valid" => cfg.rx_sm.min_ok_valid = integer(v, name, 1, 16)? as u8,
            "rx_min_ok_invalid" => cfg.rx_sm.min_ok_invalid = integer(v, name, 1, 16)? as u8,
            "rx_max_error_invalid" => cfg.rx_sm.max_error_invalid = integer(v, name, 0, 16)? as u8,
            "rx_confirm_ms" => cfg.rx_confirm_ns = ms_to_ns(name, number(v, name)?)?,
            "rx_max_rate" => {
                let Value::Table(rates) = v else {
                    return Err(Error::Config(
                        "rx_max_rate must be a table of signal = rate".into(),
                    ));
                };
                for (sig, rv) in rates {
                    let key = format!("rx_max_rate.{sig}");
                    let x = number(rv, &key)?;
                    let slot = cfg.plausibility.rate_mut(sig).ok_or_else(|| {
                        let names: Vec<&str> = (0..crate::codec::N_RX)
                            .flat_map(crate::plausibility::signal_names)
                            .collect();
                        key_err(&key, &names)
                    })?;
                    *slot = x;
                }
            }
            "rx_wheels" => {
                let Value::Table(geo) = v else {
                    return Err(Error::Config("rx_wheels must be a table".into()));
                };
                for (gk, gv) in geo {
                    let key = format!("rx_wheels.{gk}");
                    let x = number(gv, &key)?;
                    let slot = cfg
                        .plausibility
                        .geometry_mut(gk)
                        .ok_or_else(|| key_err(&key, &RX_WHEEL_KEYS))?;
                    *slot = x;
                }
            }
            "wheels" => {
                let Value::Table(wheels) = v else {
                    return Err(Error::Config("wheels must be a table".into()));
                };
                for (w, limits) in wheels {
                    let i = WHEELS
                        .iter()
                        .position(|x| x == w)
                        .ok_or_else(|| key_err(&format!("wheels.{w}"), &WHEELS))?;
                    let Value::Table(limits) = limits else {
                        return Err(Error::Config(format!("wheels.{w} must be a table")));
                    };
                    let l = &mut cfg.safety.wheels[i];
                    for (lk, lv) in limits {
                        let key = format!("wheels.{w}.{lk}");
                        let x = number(lv, &key)?;
                        match lk.as_str() {
                            "min_nm" => l.min_nm = x,
                            "max_nm" => l.max_nm = x,
                            "rise_nm_per_s" => l.rise_nm_per_s = x,
                            "release_nm_per_s" => l.release_nm_per_s = x,
                            _ => return Err(key_err(&key, &WHEEL_KEYS)),
                        }
                    }
                }
            }
            _ => return Err(key_err(name, &TOP)),
        }
    }
    Ok(())
}

/// Apply the settings of a TOML file to `cfg`.
pub fn apply_file(cfg: &mut BridgeConfig, path: &Path) -> Result<()> {
    let text = std::fs::read_to_string(path).map_err(|e| {
        Error::Config(format!(
            "config {}: cannot read: {e}",
            clip(&path.display().to_string())
        ))
    })?;
    apply_str(cfg, &text, &clip(&path.display().to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shipped_file_is_the_default() {
        let mut c = BridgeConfig::new("slcan-pty:");
        let before = c.clone();
        apply_str(&mut c, DEFAULT_TOML, "vehicle.toml").unwrap();
        assert_eq!(c, before);
        c.validate().unwrap();
    }

    #[test]
    fn applies_and_refuses_by_key() {
        let mut c = BridgeConfig::new("slcan-pty:");
        apply_str(
            &mut c,
            "period_ms = 20\nlimit_rule = \"refuse\"\n[wheels.RL]\nmax_nm = 1500\n",
            "t",
        )
        .unwrap();
        assert_eq!(c.period_ns, 20_000_000);
        assert_eq!(c.safety.limit_rule, LimitRule::Refuse);
        assert_eq!(c.safety.wheels[2].max_nm, 1500.0);
        for (text, want) in [
            ("perod_ms = 20", "unknown key \"perod_ms\""),
            ("[wheels.XX]\nmin_nm = 1", "unknown key \"wheels.XX\""),
            ("[wheels.FL]\nmax = 1", "unknown key \"wheels.FL.max\""),
            (
                "[wheels.FL]\nmax_nm = \"a\"",
                "wheels.FL.max_nm must be a number",
            ),
            (
                "stop_safe_frames = 0",
                "stop_safe_frames must be an integer in 1..=100",
            ),
            ("limit_rule = \"maybe\"", "limit_rule = \"maybe\""),
            ("period_ms = ", "not valid TOML"),
        ] {
            let e = apply_str(&mut BridgeConfig::new("slcan-pty:"), text, "t")
                .unwrap_err()
                .to_string();
            assert!(e.contains(want), "{text}: {e}");
        }
        let mut c = BridgeConfig::new("slcan-pty:");
        apply_str(&mut c, "[wheels.FL]\nmax_nm = 5000", "t").unwrap();
        let e = c.validate().unwrap_err().to_string();
        assert!(e.contains("torque_max_nm[FL] = 5000"), "{e}");
    }
}
