"""What ``ampc`` prints: help texts, XLA's log lines kept off the terminal, the
tuning summaries against the command's own defaults (in-process main, no
closed loop compiled)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import ampc_jax.cli as cli
from ampc_jax.cli import main
from ampc_jax.sweep.families import FAMILIES
from ampc_jax.tuning import weights as weights_mod
from ampc_jax.tuning.solver import DEFAULTS_ROW, evaluation_verdicts

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[2]


def _help(capsys, *argv):
    with pytest.raises(SystemExit) as exc:
        main([*argv, "-h"])
    assert exc.value.code == 0
    return " ".join(capsys.readouterr().out.split())  # argparse wraps lines


def test_sweep_help_lists_every_family(capsys):
    text = _help(capsys, "sweep")
    missing = [name for name in FAMILIES if name not in text]
    assert not missing, missing
    loops = [name for name, fam in FAMILIES.items() if fam.kind == "loop"]
    assert "stability_manoeuvres" in loops
    tune = _help(capsys, "tune")
    assert not [name for name in loops if name not in tune]
    assert "weights with the defaults takes about 15 min" in tune


def test_demo_help_states_the_timing_flag(capsys):
    text = _help(capsys, "demo")
    assert "--no-timing skip the r_time replay" in text and "load-sensitive" in text
    assert "--repeats REPEATS" in text


# ------------------------------------------------------------------ XLA's log lines
def test_main_raises_absl_log_level_to_fatal(monkeypatch, tmp_path, capsys):
    from jaxlib import utils

    seen = []
    monkeypatch.setattr(utils, "absl_set_min_log_level", seen.append)
    monkeypatch.delenv("TF_CPP_MIN_LOG_LEVEL", raising=False)
    # a command refused after parsing: quieting comes first
    assert main(["tune", "--family", "nope", "--out", str(tmp_path / "t"), "--quiet"]) == 2
    assert seen == [3]
    capsys.readouterr()
    monkeypatch.setenv("TF_CPP_MIN_LOG_LEVEL", "0")  # asking for XLA's lines keeps them
    assert cli.quiet_xla_logs() is False and seen == [3]


_FOLD = """
import sys
import numpy as np
import jax
import jax.numpy as jnp

c = np.random.default_rng(0).random((3000, 3000), dtype=np.float32)

def fold(k):  # a constant product XLA folds while compiling: more than 1 s
    jax.jit(lambda: (jnp.asarray(c) * k) @ jnp.asarray(c)).lower().compile()

fold(1.0)
sys.stderr.write("QUIETED\\n")
sys.stderr.flush()
from ampc_jax.cli import quiet_xla_logs
assert quiet_xla_logs()
fold(2.0)
"""


@pytest.mark.slow  # two slow constant folds: about 15 s on a 2-core machine
@pytest.mark.timeout(300)
def test_xla_slow_operation_alarm_is_kept_off_stderr():
    """XLA's slow-operation alarm (the logger of "Very slow compile? If you want
    to file a bug", here its constant-folding alarm) reaches stderr before
    :func:`quiet_xla_logs` and not after it."""
    env = {k: v for k, v in os.environ.items() if k != "TF_CPP_MIN_LOG_LEVEL"}
    env["PYTHONPATH"] = str(ROOT)
    proc = subprocess.run(
        [sys.executable, "-c", _FOLD], env=env, capture_output=True, text=True, timeout=280
    )
    assert proc.returncode == 0, proc.stderr
    before, after = proc.stderr.split("QUIETED\n")
    if "slow_operation_alarm" not in before:
        pytest.skip("the fold took under XLA's 1 s alarm here: nothing to keep off")
    assert "slow_operation_alarm" not in after and "file a bug" not in after, after


# ------------------------------------------------------------------ tuning summaries
def _row(name, median, p95, converged=1.0):
    return {"name": name, "median": median, "p95": p95, "converged": converged}


def test_solver_verdict_compares_with_the_example_defaults():
    ev = {
        "seed 1, N_p 2": {
            "rows": [_row("eq.opt_ro", 30, 40), _row(DEFAULTS_ROW, 12, 20), _row("tuned", 15, 18)]
        },
        "seed 1, N_p 5": {
            "rows": [_row("eq.opt_ro", 30, 40), _row(DEFAULTS_ROW, 12, 20), _row("tuned", 9, 30)]
        },
        "no example": {"rows": [_row("eq.opt_ro", 30, 40), _row("tuned", 30, 40)]},
        "fewer converged": {
            "rows": [_row(DEFAULTS_ROW, 12, 20, 1.0), _row("tuned", 5, 6, 0.9)],
        },
    }
    worse, better, same, fewer = evaluation_verdicts(ev)
    assert "tuned is worse than the example defaults (median 15.0 vs 12.0" in worse
    assert worse.endswith("keep the defaults (run without this params.json)")
    assert "tuned is better than the example defaults" in better and "keep" not in better
    assert "tuned is as good as the eq.opt_ro" in same
    assert "worse than" in fewer and "converged 0.90 vs 1.00" in fewer


def _weights_eval(default_yaw, tuned_yaw, default_over=0, tuned_over=0):
    def one(yaw, over):
        return {
            "n_cases": 4,
            "yaw_rms_focus": yaw,
            "yaw_ratio": 2.0,
            "rear_slip_max": 0.12,
            "cases_over_slip_limit": over,
            "torque_max": 900.0,
            "iterations_p95": 12.0,
            "fallbacks": 0,
        }

    return {"default": one(default_yaw, default_over), "tuned": one(tuned_yaw, tuned_over)}


def test_weights_summary_is_a_table_with_verdicts():
    ev = {
        "run": {"tune_seconds": 12.0},
        "train": _weights_eval(0.02, 0.01),
        "heldout": _weights_eval(0.02, 0.01, default_over=0, tuned_over=1),
    }
    table = weights_mod.weights_table(ev).splitlines()
    assert len(table) == 5 and "yaw RMS rad/s" in table[0] and "rear slip max" in table[0]
    assert table[1].split()[:3] == ["train", "(4)", "default"] and table[2].split()[0] == "tuned"
    train, held = weights_mod.weights_verdicts(ev)
    assert train.startswith("train: tuned weights are better than the example's defaults")
    assert held.startswith("heldout: tuned weights are worse than the example's defaults")
    assert held.endswith("keep the defaults (run without this params.json)")


def test_tune_weights_prints_a_table_not_json(monkeypatch, tmp_path, capsys):
    """The CLI's weights path (the tuner replaced by a stand-in result: the
    closed-loop tuner is tests/tuning/test_weights_tuning.py's)."""
    seen = {}

    def fake(config, cases, **kw):
        seen.update(kw, config=config)
        tuned = {f: 2.0 for f in weights_mod.weight_fields(config.settings)}
        ev = {"run": {"tune_seconds": 3.0}, "heldout": _weights_eval(0.02, 0.03)}
        return weights_mod.WeightsResult(tuned, [{"loss": 2.0}, {"loss": 1.0}], ev)

    monkeypatch.setattr(weights_mod, "tune_weights", fake)
    out = tmp_path / "w"
    code = main(
        ["tune", "--objective", "weights", "--cases", "1", "--steps", "1", "--quiet",
         "--out", str(out)]
    )  # fmt: skip
    text = capsys.readouterr().out
    assert code == 0, text
    lines = text.splitlines()
    assert lines[0].startswith("ampc tune: weights on cruise_lane_change") and "minutes" in lines[0]
    assert lines[1].startswith("tuned weights in 3 s: ")
    assert "yaw RMS rad/s" in lines[2] and not any(x.lstrip().startswith("{") for x in lines)
    assert "heldout: tuned weights are worse than the example's defaults" in text
    assert "keep the defaults" in text and len(lines) < 20
    doc = json.loads((out / "tune.json").read_text())  # the per-case numbers stay in the file
    assert doc["evaluation"]["heldout"]["tuned"]["yaw_rms_focus"] == 0.03
    assert seen["steps"] == 1 and np.isfinite(doc["history"][-1]["loss"])
