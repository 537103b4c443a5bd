"""The EKF's C kernel against its Python reference: the same bits, function by function and over whole runs.

rover_bridge/estimate/_ekf_kernel.c is built at install where a C compiler is found (pyproject.toml). Without
it the filter runs PythonKernel, the same numbers; this file then fails in its first test, saying how to build
it, unless ROVER_BRIDGE_PURE_PYTHON=1 says that the pure-Python kernel is meant (the comparisons then skip:
there is nothing to compare).
"""

from __future__ import annotations

import copy
import json
import math
import os
import struct
from collections.abc import Callable
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from rover_bridge.estimate import ekf
from rover_bridge.estimate.ekf import (
    IB,
    IV,
    IW,
    N_CAL,
    NATIVE_KERNEL,
    PYTHON_KERNEL,
    EkfKernel,
    NoiseModel,
    WheelGyroEKF,
)
from rover_bridge.odometry import Pose2D

PURE_MEANT = os.environ.get("ROVER_BRIDGE_PURE_PYTHON") == "1"
needs_native = pytest.mark.skipif(NATIVE_KERNEL is None and PURE_MEANT,
                                  reason="ROVER_BRIDGE_PURE_PYTHON=1: no C kernel to compare")


NOT_BUILT = ("rover_bridge.estimate._ekf_kernel is not built: the EKF runs its Python kernel (the same numbers, about "
             "0.1x the router more CPU). Install a C compiler and the Python headers (Debian: build-essential "
             "python3-dev) and reinstall, or set ROVER_BRIDGE_PURE_PYTHON=1 to accept it.")


def native() -> EkfKernel:
    if NATIVE_KERNEL is None:
        pytest.fail(NOT_BUILT)
    return NATIVE_KERNEL


def bits(values: list[float]) -> list[bytes | str]:
    """Each float's exact bits (-0.0 is not 0.0); every NaN alike (C may pick either operand's payload)."""
    return ["nan" if math.isnan(v) else struct.pack("<d", v) for v in values]


def outcome(fn: Callable[[], tuple[list[float], ...] | list[float]]) -> object:
    """What a kernel call gave: the bits of each list it returned, or the type of what it raised."""
    try:
        got = fn()
    except ArithmeticError as exc:
        return type(exc)
    return [bits(v) for v in got] if isinstance(got, tuple) else bits(got)


# Any double at all, including signed zeros, subnormals, infinities and NaN: both kernels must round alike.
anything = st.floats(allow_nan=True, allow_infinity=True, width=64)
# What a covariance holds in practice: finite, of every magnitude and sign.
finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False, width=64)
nonzero = finite.filter(lambda v: abs(v) > 1e-300)


def test_the_c_kernel_is_built() -> None:
    if NATIVE_KERNEL is None and not PURE_MEANT:
        pytest.fail(NOT_BUILT)
    assert ekf.kernel_name(ekf.DEFAULT_KERNEL) == ("python" if NATIVE_KERNEL is None else "native")
    assert ekf.kernel_name(PYTHON_KERNEL) == "python"


@needs_native
@settings(max_examples=300, deadline=None)
@given(n=st.integers(5, N_CAL), data=st.data(), element=st.sampled_from([anything, finite]))
def test_propagate_cov_is_the_reference_bit_for_bit(n: int, data: st.DataObject, element: st.SearchStrategy[float]
                                                    ) -> None:
    p = data.draw(st.lists(element, min_size=n * n, max_size=n * n))
    f = data.draw(st.lists(element, min_size=7, max_size=7))
    q = data.draw(st.lists(element, min_size=n, max_size=N_CAL))  # extrapolate passes all 8 for a 5-block
    p_c, p_py = list(p), list(p)
    assert native().propagate_cov(p_c, n, *f[:6], f[6], q) is None
    PYTHON_KERNEL.propagate_cov(p_py, n, *f[:6], f[6], q)
    assert bits(p_c) == bits(p_py)


@needs_native
@settings(max_examples=200, deadline=None)
@given(p=st.lists(anything, min_size=64, max_size=64), i=st.integers(0, 7), j=st.integers(0, 7), c=anything)
def test_column_sum_is_the_reference(p: list[float], i: int, j: int, c: float) -> None:
    got = outcome(lambda: native().column_sum(list(p), N_CAL, i, j, c))
    assert got == outcome(lambda: PYTHON_KERNEL.column_sum(p, N_CAL, i, j, c))


@needs_native
@settings(max_examples=200, deadline=None)
@given(p=st.lists(anything, min_size=64, max_size=64), h=st.lists(anything, min_size=8, max_size=8))
def test_wheel_columns_are_the_reference(p: list[float], h: list[float]) -> None:
    u_c, w_c = native().wheel_columns(list(p), *h)
    u_py, w_py = PYTHON_KERNEL.wheel_columns(p, *h)
    assert (bits(u_c), bits(w_c)) == (bits(u_py), bits(w_py))


@needs_native
@settings(max_examples=200, deadline=None)
@given(data=st.data(), n=st.integers(1, N_CAL), c=st.lists(anything, min_size=3, max_size=3))
def test_whiten_is_the_reference(data: st.DataObject, n: int, c: list[float]) -> None:
    u = data.draw(st.lists(anything, min_size=n, max_size=n))
    w = data.draw(st.lists(anything, min_size=n, max_size=n))
    got = outcome(lambda: native().whiten(list(u), list(w), *c))
    assert got == outcome(lambda: PYTHON_KERNEL.whiten(u, w, *c))  # a zero divisor: ZeroDivisionError from both


@needs_native
@settings(max_examples=300, deadline=None)
@given(data=st.data(), two=st.booleans(), element=st.sampled_from([anything, finite]))
def test_fuse_is_the_reference(data: st.DataObject, two: bool, element: st.SearchStrategy[float]) -> None:
    n = N_CAL
    x = data.draw(st.lists(element, min_size=n, max_size=n))
    p = data.draw(st.lists(element, min_size=n * n, max_size=n * n))
    mask = data.draw(st.lists(st.sampled_from([0.0, 1.0]), min_size=n, max_size=n))
    fixed = data.draw(st.lists(st.integers(0, n * n - 1), max_size=6))
    a = data.draw(st.lists(element, min_size=n, max_size=n))
    b = data.draw(st.lists(element, min_size=n, max_size=n)) if two else None
    e0, e1 = data.draw(element), data.draw(element)
    x_c, p_c = native().fuse(list(x), list(p), mask, fixed, a, e0, b, e1)
    x_py, p_py = PYTHON_KERNEL.fuse(x, p, mask, fixed, a, e0, b, e1)
    assert (bits(x_c), bits(p_c)) == (bits(x_py), bits(p_py))


def _drive(kernel: EkfKernel, calibrate: bool, steps: list[tuple[str, float, float, float]]
           ) -> list[list[bytes | str]]:
    """A filter through a sequence of gyro samples, wheel readings and publications; its x and P after each."""
    f = WheelGyroEKF(0.3, NoiseModel(), calibrate=calibrate, pose=Pose2D(1.0, -2.0, 0.5), kernel=kernel)
    t = 10.0
    seen = []
    for kind, dt, a, b in steps:
        t += dt
        if kind == "gyro":
            f.update_gyro(t, a)
        elif kind == "wheels":
            f.update_wheels(t, a, b, max(dt, 1e-3), gyro_omega_rad_s=a - b, gyro_spread_rad_s=abs(b) * 0.1)
        else:
            x, rows = f.extrapolate(t + abs(a) * 0.1, ekf.PUBLISHED)
            seen.append(bits(x + [v for row in rows for v in row]))
        seen.append(bits([float(v) for v in f.x] + [float(v) for v in f.P.ravel()]))
    return seen


step = st.tuples(st.sampled_from(["gyro", "wheels", "publish"]),
                 st.sampled_from([0.0, 0.0005, 0.02, 0.05, 0.3, 2.0]),  # same instant, usual, sub-steps, a gap
                 st.floats(-0.5, 0.5), st.floats(-0.5, 0.5))


@needs_native
@settings(max_examples=60, deadline=None)
@given(calibrate=st.booleans(), steps=st.lists(step, min_size=1, max_size=60))
def test_the_filter_runs_the_same_on_either_kernel(calibrate: bool, steps: list[tuple[str, float, float, float]]
                                                   ) -> None:
    assert _drive(native(), calibrate, steps) == _drive(PYTHON_KERNEL, calibrate, steps)


@needs_native
def test_a_long_drive_with_slip_and_standstill_is_the_same_on_either_kernel() -> None:
    # 40 s at 50 Hz: arcs, a spin, standstill, wheels slipping against the gyro; every x and P bit equal.
    steps: list[tuple[str, float, float, float]] = []
    for k in range(2000):
        phase = (k // 250) % 4
        omega = (0.0, 0.4, 2.0, 0.0)[phase]
        d = (0.01, 0.008, 0.0, 0.0)[phase] if k % 400 < 380 else 0.03  # the last 20 readings of 400 slip
        steps.append(("gyro", 0.02, omega, 0.0))
        steps.append(("wheels", 0.0, d - 0.003 * omega, d + 0.003 * omega))
        if k % 3 == 0:
            steps.append(("publish", 0.0, 0.2, 0.0))
    for calibrate in (False, True):
        assert _drive(native(), calibrate, steps) == _drive(PYTHON_KERNEL, calibrate, steps)


@needs_native
def test_the_filter_chooses_the_c_kernel_by_default_and_state_stays_in_filterpy_arrays() -> None:
    f = WheelGyroEKF(0.3)
    assert f.kernel is ekf.DEFAULT_KERNEL is NATIVE_KERNEL
    assert isinstance(NATIVE_KERNEL, ekf.NativeKernel)
    assert copy.deepcopy(f).kernel is NATIVE_KERNEL  # a copied filter (tests copy whole cores) shares it
    x_array, p_array = f.x, f.P
    f.update_gyro(1.0, 0.1)
    f.update_gyro(1.02, 0.2)
    assert f.x is x_array and f.P is p_array  # the arrays stay filterpy's, updated in place
    assert float(f.x[IW]) + float(f.x[IB]) == pytest.approx(0.2, abs=0.05)
    assert float(f.P[IV, IV]) > 0.0


@needs_native
def test_the_c_kernel_refuses_what_it_cannot_read_without_crashing() -> None:
    k = native()
    p = [0.0] * 64
    with pytest.raises(TypeError, match="p: expected a list of 64 floats"):
        k.propagate_cov(p[:63], 8, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01, [0.0] * 8)
    with pytest.raises(TypeError, match="q: expected a list of at least 8 floats"):
        k.propagate_cov(p, 8, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01, [0.0] * 7)
    with pytest.raises(ValueError, match="n must be 5 to 8"):
        k.propagate_cov(p, 9, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01, [0.0] * 9)
    with pytest.raises(TypeError):
        k.propagate_cov(p, 8, "x", 0.0, 0.0, 0.0, 0.0, 0.0, 0.01, [0.0] * 8)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="takes 10 arguments"):
        k.propagate_cov(p, 8)  # type: ignore[call-arg]
    with pytest.raises(TypeError, match="p: expected a list"):
        k.wheel_columns(tuple(p), 1, 1, 1, 1, 1, 1, 1, 1)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="w: expected a list of 8 floats"):
        k.whiten([1.0] * 8, [1.0] * 7, 1.0, 0.0, 1.0)
    with pytest.raises(IndexError, match="out of range"):
        k.fuse([0.0] * 8, list(p), [1.0] * 8, [64], [0.0] * 8, 0.0, None, 0.0)
    with pytest.raises(TypeError, match="b: expected a list of 8 floats"):
        k.fuse([0.0] * 8, list(p), [1.0] * 8, [], [0.0] * 8, 0.0, [0.0] * 3, 0.0)
    with pytest.raises(ValueError, match="i must be 0 to 7"):
        k.column_sum(p, 8, 8, 0, 1.0)
    # A list whose items are not numbers: an error, and the list is left as it was.
    bad = [0.0] * 63 + ["x"]
    with pytest.raises(TypeError):
        k.propagate_cov(bad, 8, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.01, [0.0] * 8)  # type: ignore[arg-type]
    assert bad[-1] == "x" and bad[:63] == [0.0] * 63


def test_the_stats_say_which_kernel_the_bridge_runs(tmp_path: Path) -> None:
    from rover_bridge.app.commands.run import write_stats
    from rover_bridge.app.composition import BridgeCore
    from rover_bridge.app.demo import free_udp_port
    from rover_bridge.app.loop import Runner
    from rover_bridge.mavlink.links import Endpoint
    from rover_bridge.mavlink.wire import Link
    from rover_bridge.params import Profile

    ap = Endpoint(f"udpin:127.0.0.1:{free_udp_port()}", Link.AUTOPILOT)
    gcs = Endpoint(f"udpin:127.0.0.1:{free_udp_port()}", Link.GCS)
    runner = Runner(BridgeCore(Profile()), ap, [gcs])
    try:
        write_stats(str(tmp_path / "stats.json"), runner)
    finally:
        runner.close()
    said = json.loads((tmp_path / "stats.json").read_text())["ekf_kernel"]
    assert said == ("python" if NATIVE_KERNEL is None and PURE_MEANT else "native")
