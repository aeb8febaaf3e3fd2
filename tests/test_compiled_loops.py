"""The compiled loops: the small linear algebra they do by hand (numba's np.linalg bindings and array expressions
cost seconds of a cold cache's first start), each against numpy or scipy, with the normals of neighbourhoods that
have no single least axis; the order a server's workers compile them in; and that `site compose` leaves them
compiled for the server's first start."""

import json
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cadreg.config import LocalizeConfig
from cadreg.localize import localizer
from cadreg.localize.field_kernels import _rotation, _solve_positive_definite, _turn_in_place
from cadreg.localize.grid_gicp import _least_axis
from service import worker
from tracking_rooms import write_layout


@pytest.mark.parametrize("n", [4, 6])
def test_a_positive_definite_system_is_solved_as_numpy_solves_it(n) -> None:
    rng = np.random.default_rng(n)
    for _ in range(20):
        J = rng.normal(size=(50, n)) * rng.uniform(0.01, 10.0, n)  # columns of very different scales, as x, y, yaw
        H, b, x = J.T @ J + 1e-6 * np.eye(n), rng.normal(size=n), np.empty(n)
        assert _solve_positive_definite(H, b, x)
        np.testing.assert_allclose(x, np.linalg.solve(H, b), rtol=1e-9, atol=1e-12)
    # not positive definite (indefinite, or a NaN in it): said so, where numpy would solve or spread the NaN
    for H in (np.array([[1.0, 2.0], [2.0, 1.0]]), np.array([[1.0, 0.0], [0.0, np.nan]])):
        assert not _solve_positive_definite(H, np.ones(2), np.empty(2))


def test_a_rotation_vector_turns_as_scipys_and_products_are_numpys() -> None:
    rng = np.random.default_rng(3)
    for w in [*rng.normal(size=(20, 3)), np.array([0.0, 0.0, np.pi - 1e-9]), np.array([2e-13, 0.0, 0.0])]:
        R = _rotation(*w)
        np.testing.assert_allclose(R, Rotation.from_rotvec(w).as_matrix(), atol=1e-12)
    A, B = rng.normal(size=(3, 3)), rng.normal(size=(3, 5))
    AB = A @ B
    _turn_in_place(A, B)
    np.testing.assert_allclose(B, AB, atol=1e-14)


@pytest.mark.parametrize("name, C", [
    ("alike", np.zeros((3, 3))),                                  # a neighbourhood of one point, repeated
    ("round", 2.0 * np.eye(3)),
    ("line along x", np.diag([3.0, 0.0, 0.0])),
    ("line", 5.0 * np.outer([1.0, 2.0, 3.0], [1.0, 2.0, 3.0]) / 14.0),
    ("line, two least alike", np.diag([3.0, 1.0, 1.0])),
    ("plane", np.diag([3.0, 2.0, 0.0])),
    ("scatter", (lambda X: X.T @ X)(np.random.default_rng(0).normal(size=(10, 3)))),
])
def test_the_least_axis_is_a_unit_eigenvector_of_the_least_eigenvalue(name, C) -> None:
    out = np.full(3, np.nan)
    _least_axis(C, out)
    least = np.linalg.eigvalsh(C)[0]
    assert np.isclose(np.linalg.norm(out), 1.0), name
    np.testing.assert_allclose(C @ out, least * out, atol=1e-7 * max(1.0, np.abs(C).max()), err_msg=name)


def test_workers_of_odd_slots_compile_from_the_other_end(monkeypatch) -> None:
    calls = []
    monkeypatch.setattr(localizer.field_kernels, "warm", lambda dtypes: calls.append(("field_kernels", dtypes)))
    modules = (localizer.cluster, localizer.frame_points, localizer.gravity, localizer.grid_gicp, localizer.match,
               localizer.point_tree, localizer.room_twins, localizer.view_kernels)
    for module in modules:
        monkeypatch.setattr(module, "warm", lambda name=module.__name__: calls.append((name, None)))
    localizer.compile_loops((np.uint8,))
    forward, calls[:] = list(calls), []
    localizer.compile_loops((np.uint8,), last_first=True)
    assert forward == [("field_kernels", (np.uint8,))] + [(m.__name__, None) for m in modules]
    assert calls == forward[::-1]
    config = LocalizeConfig()
    assert [worker._Sites(config, slot).compile_last_first for slot in range(4)] == [False, True, False, True]


# Run in a fresh process on an empty numba cache: counts what `Localizer.warm` (a server worker's start) compiles.
_COMPILED_AT_WARM = """
import json, sys
from numba.core import event
from cadreg.localize.localizer import Localizer
from cadreg.site.bundle import Site

compiled = []

class Compiles(event.Listener):
    def on_start(self, ev):
        compiled.append(ev.data["dispatcher"].py_func.__qualname__)

    def on_end(self, ev):
        pass

event.register("numba:compile", Compiles())
Localizer.from_site(Site.load(sys.argv[1])).warm()
print(json.dumps(compiled))
"""


@pytest.mark.realdata
def test_site_compose_leaves_the_loops_a_server_compiles_in_numbas_cache(scene0470_site_dir, tmp_path) -> None:
    layout = write_layout(scene0470_site_dir, tmp_path)
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba")}
    site = tmp_path / "site"

    def compiled_at_warm() -> list[str]:
        run = subprocess.run([sys.executable, "-c", _COMPILED_AT_WARM, str(site)], env=env, capture_output=True,
                             text=True, timeout=300, check=True)
        return json.loads(run.stdout.strip().splitlines()[-1])

    composed = subprocess.run([sys.executable, "-m", "cadreg.cli.main", "site", "compose", str(layout), "--out",
                               str(site)], env=env, capture_output=True, text=True, timeout=300, check=True)
    assert "compiled loops for this site are in numba's cache" in composed.stderr
    assert json.loads(composed.stdout)["rooms"] == 2  # stdout stays the summary
    assert compiled_at_warm() == []  # a worker's start reads every loop from the cache
    shutil.rmtree(tmp_path / "numba")
    assert len(compiled_at_warm()) > 20  # and without what compose left there, compiles them
