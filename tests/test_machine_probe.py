"""benchmarks/machine.py, the GEMM probe a speed figure is quoted with: its flop count, on a clock
that makes every product take exactly one second (so the rate is the count, on any machine)."""

from __future__ import annotations

import importlib.util
import itertools
from pathlib import Path

import pytest

PROBE = Path(__file__).resolve().parents[1] / "benchmarks/machine.py"


@pytest.fixture
def machine(monkeypatch):
    spec = importlib.util.spec_from_file_location("machine_probe", PROBE)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    ticks = itertools.count()
    monkeypatch.setattr(module.time, "perf_counter", lambda: float(next(ticks)))  # +1 s per reading
    return module


@pytest.mark.parametrize("shape", [(64, 64), (3, 32, 32)], ids=["N", "BxN"])
def test_a_product_is_counted_as_2_b_n_cubed_flops(machine, shape):
    n, batch = shape[-1], (shape[0] if len(shape) == 3 else 1)
    rate, seconds = machine.gemm_rate(shape, reps=3)  # median of timed products: one tick each
    assert seconds == 1.0 and rate == pytest.approx(2 * batch * n**3 / 1e9, rel=1e-12)
    assert machine.gemm_gflops(n=n, reps=3) == pytest.approx(2 * n**3 / 1e9, rel=1e-12)
    rate, seconds = machine.gemm_rate(shape, reps=4, median=False)  # one stream of 4: one tick in all
    assert seconds == 0.25 and rate == pytest.approx(4 * 2 * batch * n**3 / 1e9, rel=1e-12)
