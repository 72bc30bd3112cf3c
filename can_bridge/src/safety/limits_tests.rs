//! The limits' and the watchdog's edges: each bound of the configuration
//! inclusive where the documentation says so, a command exactly at a limit
//! not an event, the rate limiter's count, and a reset's effect.

use super::*;

const MS: u64 = 1_000_000;
const PERIOD: u64 = 50 * MS;

fn ok(c: &SafetyConfig) -> bool {
    c.validate(PERIOD).is_ok()
}

#[test]
fn the_limit_rules_are_named_as_configured() {
    for r in [LimitRule::Clamp, LimitRule::Refuse] {
        assert_eq!(LimitRule::parse(r.name()).unwrap(), r);
    }
    assert_eq!(LimitRule::Clamp.name(), "clamp");
    assert_eq!(LimitRule::Refuse.name(), "refuse");
    assert!(LimitRule::parse("Clamp").is_err());
}

#[test]
fn every_bound_of_the_limits_is_where_the_documentation_puts_it() {
    let d = SafetyConfig::default();
    let (lo, hi) = torque_range_nm();
    let with = |f: &dyn Fn(&mut SafetyConfig)| {
        let mut c = d;
        f(&mut c);
        c
    };
    // ranges: [DBC min, 0] and [0, DBC max], both ends included
    assert!(ok(&with(&|c| c.wheels[0].min_nm = 0.0)));
    assert!(ok(&with(&|c| c.wheels[0].min_nm = lo)));
    assert!(!ok(&with(&|c| c.wheels[0].min_nm = lo - 0.001)));
    assert!(!ok(&with(&|c| c.wheels[0].min_nm = 0.001)));
    assert!(ok(&with(&|c| c.wheels[2].max_nm = 0.0)));
    assert!(ok(&with(&|c| c.wheels[2].max_nm = hi)));
    assert!(!ok(&with(&|c| c.wheels[2].max_nm = hi + 0.001)));
    assert!(!ok(&with(&|c| c.wheels[2].max_nm = -0.001)));
    // rates: (0, MAX_RATE_NM_PER_S], at least one 2 Nm step a tick
    let step = torque_quantum_nm() / (PERIOD as f64 / 1e9);
    assert!(ok(&with(&|c| c.wheels[1].rise_nm_per_s = step)));
    assert!(!ok(&with(&|c| c.wheels[1].rise_nm_per_s = step * 0.999)));
    assert!(ok(&with(
        &|c| c.wheels[1].release_nm_per_s = MAX_RATE_NM_PER_S
    )));
    assert!(!ok(&with(
        &|c| c.wheels[1].release_nm_per_s = MAX_RATE_NM_PER_S * 1.001
    )));
    // a zero rate is out of the range, said so (not merely a short step)
    let e = with(&|c| c.safe_release_nm_per_s = 0.0)
        .validate(PERIOD)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("safe_release_nm_per_s = 0 must be in (0, 2000000] Nm/s"),
        "{e}"
    );
    assert!(!ok(&with(&|c| c.safe_release_nm_per_s = f64::INFINITY)));
    // watchdog: period <= hold <= 1 s < safe <= 5 s < fault <= 60 s
    let wd = |h: u64, sa: u64, f: u64| {
        ok(&with(&|c| {
            c.hold_after_ns = h;
            c.safe_after_ns = sa;
            c.fault_after_ns = f;
        }))
    };
    let (h, sa, f) = (150 * MS, 500 * MS, 2_000 * MS);
    assert!(wd(PERIOD, sa, f) && !wd(PERIOD - 1, sa, f));
    assert!(wd(1_000 * MS, 1_500 * MS, f) && !wd(1_000 * MS + 1, 1_500 * MS, f));
    assert!(wd(h, h + 1, f) && !wd(h, h, f));
    assert!(wd(h, 5_000 * MS, 6_000 * MS) && !wd(h, 5_000 * MS + 1, 6_000 * MS));
    assert!(wd(h, sa, sa + 1) && !wd(h, sa, sa));
    assert!(wd(h, sa, 60_000 * MS) && !wd(h, sa, 60_000 * MS + 1));
    // the errors give the times in ms
    let e = with(&|c| c.safe_after_ns = 6_000 * MS)
        .validate(PERIOD)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("safe_after_ms = 6000 must be above hold_after_ms (150)"),
        "{e}"
    );
}

#[test]
fn a_command_exactly_at_a_limit_is_no_limit_event() {
    let c = SafetyConfig::default();
    let (t, ev) = Safety::limit(&c, [-2000.0, 0.0, 2000.0, -2000.0]);
    assert_eq!((t, ev.len()), ([-2000.0, 0.0, 2000.0, -2000.0], 0));
    let (t, ev) = Safety::limit(&c, [-2000.5, 0.5, 2000.5, 0.0]);
    assert_eq!(t, [-2000.0, 0.0, 2000.0, 0.0]);
    let wheels: Vec<usize> = ev.iter().map(|e| e.wheel).collect();
    assert_eq!(wheels, [0, 1, 2]);
}

#[test]
fn the_ticks_a_rate_shaped_are_counted() {
    // 10,000 Nm/s = 500 Nm a 50 ms tick: 1200 Nm takes three ticks, two of
    // them shaped by the rate
    let mut s = Safety::new(SafetyConfig::default(), PERIOD, 0);
    let c = Command::new([0.0, 0.0, 1200.0, 0.0], 1, 0).unwrap();
    let out: Vec<f64> = (0..4).map(|k| s.step(k * MS, Some(&c)).1[2]).collect();
    assert_eq!(out, [500.0, 1000.0, 1200.0, 1200.0]);
    assert_eq!(s.rate_limited_ticks(), 2);
    assert_eq!(s.output_steps(), [0, 0, 600, 0]);
}

#[test]
fn a_reset_clears_a_latched_fault_at_once_and_nothing_else() {
    let mut s = Safety::new(SafetyConfig::default(), PERIOD, 0);
    assert!(!s.is_latched());
    let c = Command::new([0.0, 0.0, 100.0, 0.0], 1, 0).unwrap();
    s.step(0, Some(&c));
    assert_eq!(s.step(2_000 * MS, Some(&c)).0, Mode::Fault);
    assert!(s.is_latched());
    assert!(s.reset(2_100 * MS));
    assert!(!s.is_latched());
    assert_eq!(s.mode(), Mode::Safe);
    // without a latched fault a reset changes nothing
    let mut s = Safety::new(SafetyConfig::default(), PERIOD, 0);
    s.step(0, Some(&c));
    assert_eq!(s.mode(), Mode::Active);
    assert!(!s.reset(10 * MS));
    assert_eq!(s.step(20 * MS, Some(&c)).0, Mode::Active);
}
